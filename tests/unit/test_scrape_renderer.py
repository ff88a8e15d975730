"""The /metrics renderer: sliced over turns of the loop, yet byte for byte what the encoders give.

Runs on a real asyncio loop with a real registry; nothing is mocked.
"""

from __future__ import annotations

import asyncio

from prometheus_client import CollectorRegistry, Counter, Gauge
from prometheus_client.exposition import generate_latest
from prometheus_client.openmetrics.exposition import generate_latest as generate_openmetrics

from gateway.core.outcome import CloseReason, MasterFault, Outcome, RejectReason
from gateway.core.slave_side import FrameFault
from gateway.io.http.endpoint import SAMPLES_PER_TURN, ScrapeRenderer
from gateway.metrics import (
    BROADCAST_OUTCOMES,
    LINE_OUTCOMES,
    LOCAL_OUTCOMES,
    GatewayMetrics,
    WithoutCreated,
)

OPENMETRICS = "application/openmetrics-text;version=1.0.0"


def big_registry() -> CollectorRegistry:
    registry = CollectorRegistry()
    counter = Counter("many", "A family larger than one slice.", ["unit"], registry=registry)
    for unit in range(3 * SAMPLES_PER_TURN + 5):
        counter.labels(str(unit)).inc(unit)
    Gauge("small", "One sample.", registry=registry).set(3)
    return registry


def test_sliced_rendering_is_what_the_encoders_produce() -> None:
    # The gateway's exposition has no _created series (the text format would write them as
    # families of their own after each counter's samples, which slicing would interleave).
    registry = WithoutCreated(big_registry())

    async def render() -> tuple[bytes, bytes]:
        renderer = ScrapeRenderer(registry)
        text, _ = await renderer.render("")
        openmetrics, content_type = await renderer.render(OPENMETRICS)
        assert content_type.startswith("application/openmetrics-text")
        return text, openmetrics

    text, openmetrics = asyncio.run(render())
    assert text == generate_latest(registry)
    assert openmetrics == generate_openmetrics(registry)  # type: ignore[no-untyped-call]


def test_scrapes_waiting_together_share_one_rendering_and_renderings_are_spaced() -> None:
    registry = big_registry()

    async def scrape() -> None:
        loop = asyncio.get_running_loop()
        renderer = ScrapeRenderer(registry, share=0.1)
        started = loop.time()
        bodies = await asyncio.gather(*(renderer.render("") for _ in range(5)))
        assert len({body for body, _ in bodies}) == 1
        assert renderer.renderings == 1
        # The next rendering waits 9 x this one's cost: rendering takes a tenth of the loop.
        assert renderer.not_before >= started + 9 * renderer.last_cost
        spaced_until = renderer.not_before
        await renderer.render("")
        assert renderer.renderings == 2
        assert loop.time() >= spaced_until - 0.001  # the loop's clock is millisecond-grained

    asyncio.run(scrape())


def test_the_exposition_has_no_created_series() -> None:
    metrics = GatewayMetrics()
    metrics.count_request("a", "1", 3, Outcome.OK)
    body = generate_latest(metrics.exposition_registry()).decode()
    assert "modbus_gateway_requests_total" in body
    assert "_created" not in body
    assert "_created" in generate_latest(metrics.registry).decode()  # what it leaves out


def test_requests_name_a_unit_only_once_its_slave_has_answered() -> None:
    metrics = GatewayMetrics()
    for function in range(1, 60):
        metrics.count_request("a", "7", function, Outcome.TARGET_FAILED)  # never heard: "other"
    metrics.count_request("a", "5", 3, Outcome.OK)
    metrics.count_request("a", "5", 3, Outcome.TARGET_FAILED)
    metrics.count_request("broadcast", "0", 6, Outcome.BROADCAST)
    units = {
        sample.labels["unit"]
        for family in metrics.registry.collect()
        if family.name == "modbus_gateway_requests"
        for sample in family.samples
        if sample.name.endswith("_total")
    }
    functions = {
        sample.labels["function"]
        for family in metrics.registry.collect()
        if family.name == "modbus_gateway_requests"
        for sample in family.samples
    }
    assert units == {"other", "5", "0"}
    assert "other" in functions and len(functions) <= 20
    value = metrics.registry.get_sample_value
    assert (
        value(
            "modbus_gateway_requests_total",
            {
                "line": "a",
                "unit": "5",
                "function": "read_holding_registers",
                "outcome": "target_failed",
            },
        )
        == 1
    )


def _series(metrics: GatewayMetrics, family: str) -> set[tuple[str, ...]]:
    return {
        tuple(sample.labels.values())
        for metric in metrics.registry.collect()
        if metric.name == family
        for sample in metric.samples
        if sample.name.endswith("_total")
    }


def test_every_series_of_a_fixed_vocabulary_exists_at_zero_from_the_start() -> None:
    metrics = GatewayMetrics()
    p = "modbus_gateway_"
    assert _series(metrics, p + "connections_closed") == {(r.value,) for r in CloseReason}
    assert _series(metrics, p + "connections_rejected") == {(r.value,) for r in RejectReason}
    assert _series(metrics, p + "protocol_errors") == {(f.value,) for f in MasterFault}
    assert {f.value for f in FrameFault} <= {f.value for f in MasterFault}
    assert _series(metrics, p + "requests") == set()  # rows come with their first request


def test_a_request_row_gets_every_outcome_it_can_take_at_zero_once_in_use() -> None:
    metrics = GatewayMetrics()
    metrics.count_request("a", "5", 3, Outcome.OK)
    metrics.count_request("none", "other", 3, Outcome.NO_ROUTE)
    metrics.count_request("broadcast", "0", 6, Outcome.BROADCAST)
    rows = _series(metrics, "modbus_gateway_requests")
    read = "read_holding_registers"
    assert rows == (
        {("a", "5", read, outcome.value) for outcome in LINE_OUTCOMES}
        | {("none", "other", read, "no_route")}  # answered locally: only what happened
        | {("broadcast", "0", "write_single_register", o.value) for o in BROADCAST_OUTCOMES}
    )
    value = metrics.registry.get_sample_value
    labels = {"line": "a", "unit": "5", "function": read}
    assert value("modbus_gateway_requests_total", {**labels, "outcome": "ok"}) == 1
    assert value("modbus_gateway_requests_total", {**labels, "outcome": "target_failed"}) == 0
    assert set(LINE_OUTCOMES) | set(LOCAL_OUTCOMES) | set(BROADCAST_OUTCOMES) == set(Outcome)


def test_outcomes_a_master_causes_without_an_answer_add_one_series_each() -> None:
    # Every function to a slave that never answered it, and to no line at all: one series
    # per function and outcome met, not a row of seven.
    metrics = GatewayMetrics()
    for function in range(1, 25):
        metrics.count_request("a", "5", function, Outcome.BUSY)
        metrics.count_request("a", "5", function, Outcome.TARGET_FAILED)
        metrics.count_request("none", "other", function, Outcome.REJECTED)
    rows = _series(metrics, "modbus_gateway_requests")
    functions = {row[2] for row in rows}
    assert len(rows) == 3 * len(functions) and "other" in functions
    assert {row[1] for row in rows} == {"other"}  # slave 5 never answered: not its own label
    metrics.count_request("a", "5", 3, Outcome.OK)  # now it answers a read: its row, whole
    assert {row[3] for row in _series(metrics, "modbus_gateway_requests") if row[1] == "5"} == {
        outcome.value for outcome in LINE_OUTCOMES
    }


def test_status_reads_the_slave_counters_as_numbers() -> None:
    metrics = GatewayMetrics()
    metrics.prepare_units([("a", 1), ("a", 2), ("b", 1)])
    metrics.timeouts.labels("a", "1").inc()
    metrics.crc_errors.labels("a", "1").inc(2)
    metrics.crc_errors.labels("b", "1").inc()
    metrics.trace_dropped.inc(3)
    assert metrics.slave_errors("a") == {1: 3, 2: 0}
    assert (metrics.crc_errors_on("a"), metrics.crc_errors_on("b")) == (2, 1)
    assert metrics.trace_events_dropped() == 3
