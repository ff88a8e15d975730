"""``[redundancy]``: the keys of an active/standby pair, their flags and their mistakes."""

from __future__ import annotations

from typing import Any

import pytest

from gateway.cli import apply_overrides, build_parser
from gateway.config import RedundancyConfig, build_config, config_warnings
from tests.helpers import problems

LINE = {"a": {"device": "/dev/ttyUSB0", "units": [1]}}


def test_without_a_peer_the_gateway_runs_alone() -> None:
    config = build_config({"lines": LINE})
    assert config.redundancy == RedundancyConfig()
    assert not config.redundancy.paired
    assert (config.redundancy.lease, config.redundancy.takeover_after) == (1.0, 1.5)


def test_a_pair_reads_every_key() -> None:
    raw = {
        "lines": LINE,
        "redundancy": {
            "peer": "192.0.2.12:9502", "peer_modbus": "192.0.2.12:502", "priority": 200,
            "lease": 2, "takeover_after": 3.0, "keepalive": "7:100",
        },
    }  # fmt: skip
    pair = build_config(raw).redundancy
    assert pair.paired
    assert (pair.peer, pair.peer_modbus) == (("192.0.2.12", 9502), ("192.0.2.12", 502))
    assert (pair.priority, pair.lease, pair.takeover_after) == (200, 2.0, 3.0)
    assert pair.keepalive == (7, 100)


@pytest.mark.parametrize(("value", "expected"), [("auto", (0, 0)), ("off", None), ("1:0", (1, 0))])
def test_keepalive_values(value: str, expected: tuple[int, int] | None) -> None:
    raw = {"lines": LINE, "redundancy": {"keepalive": value}}
    assert build_config(raw).redundancy.keepalive == expected


@pytest.mark.parametrize(
    ("table", "key", "words"),
    [
        ({"peer": "h:9502"}, "redundancy.peer_modbus", "Modbus TCP listener"),
        ({"peer_modbus": "h:502"}, "redundancy.peer", "a pair needs both"),
        ({"peer": "nowhere", "peer_modbus": "h:502"}, "redundancy.peer", "HOST:PORT"),
        ({"keepalive": "0:1"}, "redundancy.keepalive", "1..247"),
        ({"keepalive": "sometimes"}, "redundancy.keepalive", '"SLAVE:REGISTER"'),
        ({"lease": 2.0, "takeover_after": 2.2}, "redundancy.takeover_after", "lease plus"),
        ({"priority": 300}, "redundancy.priority", "255"),
        ({"peers": "h:1"}, "redundancy.peers", "did you mean 'peer'"),
    ],
)
def test_a_mistake_names_the_key_and_the_fix(table: dict[str, Any], key: str, words: str) -> None:
    found = problems({"lines": LINE, "redundancy": table})
    assert any(problem.startswith(key) and words in problem for problem in found), found


def test_the_flags_set_the_pair() -> None:
    args = build_parser().parse_args(
        ["--redundancy-peer", "10.0.0.2:9502", "--redundancy-peer-modbus", "10.0.0.2:502",
         "--redundancy-priority", "150"]
    )  # fmt: skip
    raw = apply_overrides({"lines": LINE}, args)
    pair = build_config(raw).redundancy
    assert (pair.peer, pair.peer_modbus, pair.priority) == (
        ("10.0.0.2", 9502), ("10.0.0.2", 502), 150,
    )  # fmt: skip


def test_a_pair_needs_the_http_endpoint() -> None:
    raw = {"lines": LINE, "metrics": {"listen": "off"},
           "redundancy": {"peer": "192.0.2.12:9502", "peer_modbus": "192.0.2.12:502"}}  # fmt: skip
    found = problems(raw)
    assert any(p.startswith("metrics.listen") and "GET /role" in p for p in found), found


def test_a_pair_that_cannot_reach_itself_is_warned_about() -> None:
    raw = {"lines": LINE, "redundancy": {"peer": "plc-gw-2:9502", "peer_modbus": "192.0.2.12:502"},
           "server": {"listen": "127.0.0.1:502"}}  # fmt: skip
    warnings = config_warnings(build_config(raw))
    # [metrics] listen defaults to 127.0.0.1:9502: the peer cannot poll it.
    assert any(w.startswith("metrics.listen: 127.0.0.1 is a loopback") for w in warnings)
    assert any(w.startswith("server.listen: 127.0.0.1 is a loopback") for w in warnings)
    assert any(w.startswith("redundancy.peer: plc-gw-2 is a name") for w in warnings)
    assert not any(w.startswith("redundancy.peer_modbus") for w in warnings)
    pair = {"peer": "192.0.2.12:9502", "peer_modbus": "192.0.2.12:502"}
    reachable = {"lines": LINE, "metrics": {"listen": "0.0.0.0:9502"}, "redundancy": pair}
    warned = config_warnings(build_config(reachable))
    assert not [w for w in warned if "redundancy" in w or "loopback" in w], warned
