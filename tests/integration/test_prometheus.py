"""The metrics as Prometheus itself sees them: promtool, a real server scraping, the dashboard.

A missing ``prometheus``/``promtool`` is a skip on a developer's machine and a
failure under CI (``CI`` set), so CI cannot go green by not checking. The
server is started on 127.0.0.1 with a 1 s scrape interval and a temporary
storage directory; the test polls its HTTP API with a deadline (targets are
loaded about every 5 s, so the first sample shows after 5-6 s).
"""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gateway.core import pdu as fc
from gateway.metrics import GatewayMetrics
from gateway.sim import plc
from tests.helpers import GatewayOnSim, RunningGateway, require_tool
from tests.integration.metrics_harness import exposition, metrics_address

REPO = Path(__file__).resolve().parents[2]
PROMETHEUS_CONFIG = REPO / "conf" / "prometheus.yml"
ALERT_RULES = REPO / "conf" / "rules" / "modbus-gateway.yml"
DASHBOARD = REPO / "conf" / "grafana" / "dashboards" / "modbus-gateway.json"
DOCS = REPO / "docs" / "metrics.md"
#: Generous: Prometheus loads its targets every ~5 s, and a busy machine slows it further.
QUERY_DEADLINE_S = 60.0
#: How long the load's masters may take (400 reads; seconds when the machine is idle).
LOAD_DEADLINE_S = 120.0
READ_10 = bytes.fromhex("03 0000 000A")


def _run(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, input=stdin, capture_output=True, text=True, timeout=30)


def _traffic_with_every_fault(gw: RunningGateway) -> None:
    """Requests that create a series in every labelled family (ok, 0x0B, 0x0A, reject)."""
    with gw.connect() as master:
        assert master.request(1, READ_10)[0] == 0x03
        assert master.request(2, READ_10) == bytes((0x83, 0x0B))
        assert master.request(99, READ_10) == bytes((0x83, 0x0A))
        assert master.request(1, bytes.fromhex("03 0000 00C8")) == bytes((0x83, 0x03))
        assert master.request(1, bytes.fromhex("06 0001 0007"))[0] == 0x06


def test_promtool_accepts_the_exposition(gateway_with: GatewayOnSim) -> None:
    promtool = require_tool("promtool")
    sim, gw = gateway_with({1: plc(1), 2: plc(2)}, line={"timeout": 0.05, "retries": 1})
    sim.faults(2).silent = True
    _traffic_with_every_fault(gw)
    text = exposition(gw)
    checked = _run(promtool, "check", "metrics", stdin=text)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert "modbus_gateway_timeouts_total" in text


def test_promtool_accepts_the_shipped_scrape_config_and_alert_rules() -> None:
    promtool = require_tool("promtool")
    checked = _run(promtool, "check", "config", str(PROMETHEUS_CONFIG))
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert "1 rule files found" in checked.stdout + checked.stderr  # the example alerts
    checked = _run(promtool, "check", "rules", str(ALERT_RULES))
    assert checked.returncode == 0, checked.stdout + checked.stderr


def test_the_timeout_alert_fires_on_a_silent_unit(tmp_path: Path) -> None:
    """``promtool test rules``: 0.2 timeouts/s for 15 min fire ModbusSlaveTimeouts after 5."""
    promtool = require_tool("promtool")
    test = {
        "rule_files": [str(ALERT_RULES)],
        "evaluation_interval": "1m",
        "tests": [
            {
                "interval": "1m",
                "input_series": [
                    {
                        "series": 'modbus_gateway_timeouts_total{line="a", unit="5"}',
                        "values": "0+12x15",
                    },
                    {
                        "series": 'modbus_gateway_timeouts_total{line="a", unit="6"}',
                        "values": "0x15",
                    },
                ],
                "alert_rule_test": [
                    {"eval_time": "3m", "alertname": "ModbusSlaveTimeouts", "exp_alerts": []},
                    {
                        "eval_time": "12m",
                        "alertname": "ModbusSlaveTimeouts",
                        "exp_alerts": [
                            {
                                "exp_labels": {"line": "a", "unit": "5", "severity": "warning"},
                                "exp_annotations": {
                                    "summary": "Unit 5 on line a times out (200m/s)"
                                },
                            }
                        ],
                    },
                ],
            }
        ],
    }
    path = tmp_path / "alerts_test.yml"
    path.write_text(json.dumps(test))  # JSON is YAML
    checked = _run(promtool, "test", "rules", str(path))
    assert checked.returncode == 0, checked.stdout + checked.stderr


# --------------------------------------------------------------------------- a real Prometheus


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


class Prometheus:
    """A Prometheus server process and its query API."""

    def __init__(self, binary: str, target: tuple[str, int], directory: Path) -> None:
        self.port = _free_port()
        config = directory / "prometheus.yml"
        config.write_text(
            "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\n"
            "scrape_configs:\n  - job_name: modbus-gateway\n    static_configs:\n"
            f"      - targets: ['{target[0]}:{target[1]}']\n"
        )
        self.process = subprocess.Popen(
            [
                binary,
                f"--config.file={config}",
                f"--storage.tsdb.path={directory / 'data'}",
                f"--web.listen-address=127.0.0.1:{self.port}",
                "--log.level=warn",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )

    def api(self, path: str, **params: str) -> Any:
        """GET an API endpoint; the ``data`` of a successful answer."""
        url = f"http://127.0.0.1:{self.port}/api/v1/{path}?{urllib.parse.urlencode(params)}"
        with urllib.request.urlopen(url, timeout=5) as response:
            body = json.load(response)
        assert body["status"] == "success", body
        return body["data"]

    def query(self, expr: str) -> list[dict[str, Any]]:
        """An instant query's vector; empty while Prometheus is not up or has no sample."""
        try:
            data = self.api("query", query=expr)
        except (urllib.error.URLError, ConnectionError):
            if self.process.poll() is not None:
                raise AssertionError("prometheus exited") from None
            return []
        result: list[dict[str, Any]] = data["result"]
        return result

    def wait_for(self, expr: str, expected: float) -> list[dict[str, Any]]:
        """Poll ``expr`` until its single value equals ``expected``; fail at the deadline."""
        deadline = time.monotonic() + QUERY_DEADLINE_S
        last: list[dict[str, Any]] = []
        while time.monotonic() < deadline:
            last = self.query(expr)
            if len(last) == 1 and float(last[0]["value"][1]) == expected:
                return last
            time.sleep(0.2)
        targets = self.api("targets")["activeTargets"]
        raise AssertionError(f"{expr} = {last}, expected {expected}; targets: {targets}")

    def stop(self) -> str:
        """SIGTERM and wait; return what it logged."""
        self.process.send_signal(signal.SIGTERM)
        try:
            _, stderr = self.process.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            _, stderr = self.process.communicate()
        return stderr.decode(errors="replace")


@pytest.fixture
def prometheus_binary() -> str:
    return require_tool("prometheus")


@pytest.fixture
def make_prometheus(prometheus_binary: str, tmp_path: Path) -> Iterator[Any]:
    servers: list[Prometheus] = []

    def factory(target: tuple[str, int]) -> Prometheus:
        server = Prometheus(prometheus_binary, target, tmp_path)
        servers.append(server)
        return server

    yield factory
    for server in servers:
        server.stop()


@pytest.mark.slow  # Prometheus queries its first scrape after ~5 s
def test_prometheus_scrapes_the_gateway_under_load(
    gateway_with: GatewayOnSim, make_prometheus: Any
) -> None:
    # Every read of unit 1 must be answered and unit 2 must time out exactly twice: a
    # timeout far above what a busy machine delays the simulator by (only unit 2 waits it out).
    sim, gw = gateway_with({1: plc(1), 2: plc(2)}, line={"timeout": 1.0, "retries": 1})
    with gw.connect() as master:  # unit 2 answers once: requests_total names it from now on
        assert master.request(2, READ_10)[0] == 0x03
    sim.faults(2).silent = True
    prometheus: Prometheus = make_prometheus(metrics_address(gw))
    masters, per_master = 4, 100
    errors: list[BaseException] = []

    def load() -> None:
        try:
            with gw.connect() as master:
                for index in range(per_master):
                    address = 1000 + index
                    reply = master.request(1, bytes((0x03, address >> 8, address & 0xFF, 0, 2)))
                    assert reply == bytes((0x03, 4, address >> 8, address & 0xFF)) + bytes(
                        ((address + 1) >> 8, (address + 1) & 0xFF)
                    )
        except BaseException as error:  # reported by the main thread
            errors.append(error)

    # One request to the silent unit on the idle line: 2 timeouts, 1 retry. (Under load its
    # retry would wait behind the healthy slave's requests, a suspect slave's place.)
    with gw.connect() as master:
        assert master.request(2, READ_10) == bytes((0x83, 0x0B))
    threads = [threading.Thread(target=load) for _ in range(masters)]
    for thread in threads:
        thread.start()
    deadline = time.monotonic() + LOAD_DEADLINE_S
    for thread in threads:
        thread.join(max(0.0, deadline - time.monotonic()))
    assert not errors, errors
    assert not any(thread.is_alive() for thread in threads), "the load did not finish"
    total = masters * per_master

    ok = 'modbus_gateway_requests_total{line="a",unit="1",outcome="ok"}'
    [sample] = prometheus.wait_for(ok, total)
    assert sample["metric"]["function"] == fc.function_name(fc.READ_HOLDING_REGISTERS)
    prometheus.wait_for('modbus_gateway_request_duration_seconds_count{line="a"}', total + 2)
    prometheus.wait_for('modbus_gateway_request_duration_seconds_bucket{line="a",le="+Inf"}',
                        total + 2)  # fmt: skip
    prometheus.wait_for('modbus_gateway_timeouts_total{line="a",unit="2"}', 2)
    prometheus.wait_for('modbus_gateway_requests_total{unit="2",outcome="target_failed"}', 1)
    # The latency histogram answers quantile queries, within the bucket range.
    buckets = 'modbus_gateway_request_duration_seconds_bucket{line="a"}'
    [median] = prometheus.query(f"histogram_quantile(0.5, sum by (le) ({buckets}))")
    assert 0 < float(median["value"][1]) <= 5.0
    # Identical reads of the masters may share one transaction (coalescing): fewer waits.
    [queue] = prometheus.query('modbus_gateway_queue_wait_seconds_count{line="a"}')
    assert 0 < float(queue["value"][1]) <= total + 1
    # The latest scrape succeeded (one scrape may time out while the machine is busy).
    prometheus.wait_for('up{job="modbus-gateway"}', 1)


# --------------------------------------------------------------------------- dashboard and docs


def _families() -> dict[str, set[str]]:
    """Every metric the gateway can expose, by the name docs use, with its sample names."""
    families = {}
    for family in GatewayMetrics().registry.collect():
        base = family.name
        if family.type == "counter":
            families[base + "_total"] = {base + "_total", base + "_created"}
        elif family.type == "histogram":
            suffixes = ("_bucket", "_count", "_sum", "_created")
            families[base] = {base + suffix for suffix in suffixes}
        elif family.type == "info":
            families[base + "_info"] = {base + "_info"}
        else:
            families[base] = {base}
    return families


def _known_series_names() -> set[str]:
    """Every sample name the gateway can expose."""
    return set().union(*_families().values())


def _expressions(node: Any) -> Iterator[str]:
    if isinstance(node, dict):
        for key, value in node.items():
            if key in ("expr", "definition") and isinstance(value, str):
                yield value
            elif key == "query" and isinstance(value, dict) and "query" in value:
                yield value["query"]
            else:
                yield from _expressions(value)
    elif isinstance(node, list):
        for item in node:
            yield from _expressions(item)


def test_dashboard_references_only_metrics_that_exist() -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    expressions = list(_expressions(dashboard))
    assert len(expressions) >= 20
    used = {name for expr in expressions for name in re.findall(r"modbus_gateway_\w+", expr)}
    assert used - _known_series_names() == set()
    # What the deployment issue asks the dashboard to show.
    for wanted in (
        "modbus_gateway_requests_total",
        "modbus_gateway_request_duration_seconds_bucket",
        "modbus_gateway_crc_errors_total",
        "modbus_gateway_timeouts_total",
        "modbus_gateway_queue_depth",
        "modbus_gateway_connections_open",
    ):
        assert wanted in used, wanted
    ids = [panel["id"] for panel in dashboard["panels"]]
    assert len(ids) == len(set(ids))


def test_alert_rules_and_docs_name_only_metrics_that_exist() -> None:
    known = _known_series_names()
    rules = set(re.findall(r"modbus_gateway_\w+", ALERT_RULES.read_text()))
    assert rules and rules - known == set()
    documented = set(re.findall(r"modbus_gateway_\w+", DOCS.read_text()))
    families = set(_families())
    assert documented - known - families == set()
    assert families - documented == set(), "every metric has its line in docs/metrics.md"
