"""Agent mode seen by operators: each poll block in ``GET /status`` (and so the console)
and in the metrics, on a running gateway over real HTTP on loopback, with a simulated RTU
line on a pty."""

from __future__ import annotations

import json
import math
import subprocess
from typing import Any

import pytest

from gateway.config import build_config
from gateway.sim import plc
from tests.helpers import (
    GatewayFactory,
    RunningGateway,
    SimBus,
    SimFactory,
    require_tool,
    wait_until,
)
from tests.integration.metrics_harness import exposition, http_get, samples, series

READ_2 = bytes.fromhex("03 0002 0002")


def start(make_sim: SimFactory, make_gateway: GatewayFactory) -> tuple[SimBus, RunningGateway]:
    """Line ``a``: slave 1 answers, slave 2 is absent; a block on each (every 0.05 s)."""
    sim = make_sim({1: plc(1)})
    raw: dict[str, Any] = {
        "lines": {"a": sim.line_table([1, 2], timeout=0.1, retries=0)},
        "poll": [
            {"unit": 1, "function": 3, "address": 0, "count": 10, "every": 0.05, "max_age": 0.5},
            {"unit": 2, "function": 4, "address": 100, "count": 2, "every": 0.05},
        ],
    }
    return sim, make_gateway(raw)


def status(gateway: RunningGateway) -> dict[str, Any]:
    code, _headers, body = http_get(gateway, "/status")
    assert code == 200
    result: dict[str, Any] = json.loads(body)
    return result


def blocks(gateway: RunningGateway) -> list[dict[str, Any]]:
    (line,) = status(gateway)["lines"]
    found: list[dict[str, Any]] = line["blocks"]
    return found


def test_status_lists_each_block_with_its_range_pace_age_and_state(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim, gateway = start(make_sim, make_gateway)
    wait_until(
        lambda: (
            [b["state"] for b in blocks(gateway)] == ["fresh", "failing"]
            and blocks(gateway)[0]["period"] is not None
        ),
        "block 1:3 fresh with a measured period, block 2:4 failing",
    )
    with gateway.connect() as client:
        for _ in range(3):
            client.request(1, READ_2)  # inside the block: answered from memory
    fresh, failing = blocks(gateway)
    # The slave's own row counts masters' requests (answered from memory too), not polls;
    # a poll's answer says when it was last heard.
    (slave,) = [s for s in status(gateway)["lines"][0]["slaves"] if s["unit"] == 1]
    assert slave["requests"] == 3 and slave["last_seen"] is not None
    where = {k: fresh[k] for k in ("block", "line", "unit", "slave", "function")}
    assert where == {"block": "1:3:0-9", "line": "a", "unit": 1, "slave": 1, "function": 3}
    assert (fresh["first"], fresh["last"], fresh["every"], fresh["max_age"]) == (0, 9, 0.05, 0.5)
    assert 0.0 <= fresh["age"] <= 0.5
    assert 0.02 < fresh["period"] < 0.5  # achieved: about every, on a free line
    assert fresh["served"] == 3
    assert fresh["polls"]["ok"] >= 2 and set(fresh["polls"]) == {"ok"}
    assert (failing["block"], failing["first"], failing["last"]) == ("2:4:100-101", 100, 101)
    assert failing["age"] is None  # never polled
    assert failing["max_age"] == pytest.approx(0.15)  # 3 x every
    assert failing["polls"]["target_failed"] >= 1 and "ok" not in failing["polls"]
    assert failing["served"] == 0
    # The slave stops answering: its block turns failing, and its age keeps growing.
    sim.faults(1).silent = True
    wait_until(lambda: blocks(gateway)[0]["state"] == "failing", "block 1:3 failing")
    wait_until(lambda: blocks(gateway)[0]["age"] > 0.5, "block 1:3 older than max_age")


def test_metrics_give_each_blocks_age_state_period_polls_and_reads_served(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim, gateway = start(make_sim, make_gateway)
    fresh, failing = {"line": "a", "block": "1:3:0-9"}, {"line": "a", "block": "2:4:100-101"}

    def sample(name: str, labels: dict[str, str]) -> float:
        return samples(gateway).get(series(name, **labels), -1.0)

    age, state = "modbus_gateway_poll_block_age_seconds", "modbus_gateway_poll_block_state"
    period = "modbus_gateway_poll_block_period_seconds"

    def polled() -> bool:
        measured = not math.isnan(sample(period, fresh))
        return measured and (sample(state, fresh), sample(state, failing)) == (0, 2)

    wait_until(polled, "block 1:3 fresh with a measured period, block 2:4 failing")
    with gateway.connect() as client:
        for _ in range(3):
            client.request(1, READ_2)  # answered from memory
    scraped = samples(gateway)
    assert 0.0 <= scraped[series(age, **fresh)] <= 0.5
    assert scraped[series(age, **failing)] == math.inf  # never a good poll
    assert 0.02 < scraped[series(period, **fresh)] < 0.5
    assert scraped[series("modbus_gateway_poll_block_served_total", **fresh)] == 3
    assert scraped[series("modbus_gateway_poll_block_served_total", **failing)] == 0
    polls = "modbus_gateway_polls_total"
    assert scraped[series(polls, **fresh, outcome="ok")] >= 2
    assert scraped[series(polls, **fresh, outcome="target_failed")] == 0  # there at 0
    assert scraped[series(polls, **failing, outcome="target_failed")] >= 1
    assert scraped[series(polls, **failing, outcome="ok")] == 0
    row = {"line": "a", "unit": "1", "function": "read_holding_registers"}
    memory = series("modbus_gateway_requests_total", **row, outcome="memory")
    assert scraped[memory] == 3
    # The slave stops answering: failing, and older than max_age.
    sim.faults(1).silent = True
    wait_until(lambda: sample(state, fresh) == 2, "block 1:3 failing")
    wait_until(lambda: sample(age, fresh) > 0.5, "block 1:3 older than max_age")
    # A reload that removes a block takes its series away; the other's stay.
    raw: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0"},
        "lines": {"a": sim.line_table([1, 2], timeout=0.1, retries=0)},
        "poll": [{"unit": 1, "function": 3, "address": 0, "count": 10, "every": 0.05}],
    }
    gateway.run(gateway.gateway.reload(build_config(raw, "<test>")))
    scraped = samples(gateway)
    assert series(state, **fresh) in scraped and series(state, **failing) not in scraped
    assert series(polls, **failing, outcome="ok") not in scraped


def test_promtool_accepts_the_poll_block_series(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    promtool = require_tool("promtool")
    _sim, gateway = start(make_sim, make_gateway)
    wait_until(lambda: [b["state"] for b in blocks(gateway)] == ["fresh", "failing"], "both polled")
    text = exposition(gateway)
    assert "modbus_gateway_poll_block_age_seconds" in text
    checked = subprocess.run(
        [promtool, "check", "metrics"], input=text, capture_output=True, text=True, timeout=30
    )
    assert checked.returncode == 0, checked.stdout + checked.stderr
