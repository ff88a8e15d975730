"""Reading a running gateway's metrics for the observability tests: scrapes, series, diffs.

The gateway, the simulated line and the raw client come from ``tests/helpers.py``.
Reading through ``/metrics`` doubles as a synchronisation point: the HTTP
request is served on the gateway's loop after every callback that ran before
it, so a scrape taken after a reply was received sees that reply's counts.
Waits that have no such point poll with a deadline.
"""

from __future__ import annotations

import http.client
from collections.abc import Mapping

from prometheus_client.parser import text_string_to_metric_families

from tests.helpers import DEADLINE_S, RunningGateway

#: A series: sample name and its labels, sorted.
Series = tuple[str, tuple[tuple[str, str], ...]]


def series(name: str, **labels: str) -> Series:
    """The key of one sample, as ``samples`` returns them."""
    return name, tuple(sorted(labels.items()))


def metrics_address(gw: RunningGateway) -> tuple[str, int]:
    """The HTTP endpoint's address."""
    address = gw.gateway.metrics_address
    assert address is not None, "the gateway runs without its HTTP endpoint"
    return address


def http_get(
    gw: RunningGateway, path: str, accept: str | None = None
) -> tuple[int, dict[str, str], bytes]:
    """GET on the gateway's HTTP endpoint: status, headers (lower-case names), body."""
    host, port = metrics_address(gw)
    connection = http.client.HTTPConnection(host, port, timeout=DEADLINE_S)
    try:
        connection.request("GET", path, headers={"Accept": accept} if accept else {})
        response = connection.getresponse()
        headers = {name.lower(): value for name, value in response.getheaders()}
        return response.status, headers, response.read()
    finally:
        connection.close()


def exposition(gw: RunningGateway) -> str:
    """The /metrics text (Prometheus text format 0.0.4)."""
    status, _, body = http_get(gw, "/metrics")
    assert status == 200
    return body.decode()


def samples(gw: RunningGateway) -> dict[Series, float]:
    """Every sample of one scrape, by name and labels."""
    return {
        series(sample.name, **sample.labels): sample.value
        for family in text_string_to_metric_families(exposition(gw))
        for sample in family.samples
    }


def value(gw: RunningGateway, key: Series) -> float:
    """One sample read straight from the registry (0 when the series does not exist)."""
    found = gw.gateway.metrics.registry.get_sample_value(key[0], dict(key[1]))
    return 0.0 if found is None else found


def counter_changes(
    before: Mapping[Series, float], after: Mapping[Series, float], families: tuple[str, ...]
) -> dict[Series, float]:
    """The ``_total`` samples of ``families`` whose value changed, with the increase."""
    changes = {}
    for key, sample in after.items():
        name = key[0]
        if name.endswith("_total") and name.removesuffix("_total") in families:
            delta = sample - before.get(key, 0.0)
            if delta:
                changes[key] = delta
    return changes


def increase(before: Mapping[Series, float], after: Mapping[Series, float], key: Series) -> float:
    """How much one series grew between two scrapes."""
    return after.get(key, 0.0) - before.get(key, 0.0)
