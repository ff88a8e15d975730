"""The frame trace on a running gateway: what the masters sent and got, filtered, decoded."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from gateway.sim import plc
from gateway.trace import Tracer
from tests.helpers import GatewayOnSim, LogCollector, RunningGateway, wait_until
from tests.integration.metrics_harness import http_get

READ_10 = bytes.fromhex("03 0000 000A")


class Collect(LogCollector):
    def fields(self) -> list[tuple[str, int, int, str | None]]:
        return [
            (r.__dict__["direction"], r.__dict__["transaction_id"], r.__dict__["unit"],
             r.__dict__.get("outcome"))
            for r in self.records
        ]  # fmt: skip


@pytest.fixture
def trace_log() -> Iterator[Collect]:
    log = logging.getLogger("gateway.trace")
    handler = Collect()
    log.addHandler(handler)
    yield handler
    log.removeHandler(handler)


def _trace(gw: RunningGateway, tracer: Tracer | None) -> None:
    """Subscribe ``tracer`` to the gateway's frame trace (``None``: leave it unsubscribed)."""

    async def install() -> None:
        if tracer is not None:
            gw.gateway.trace.subscribe(tracer)

    gw.run(install())


def test_trace_shows_the_frames_that_pass_the_filters(
    gateway_with: GatewayOnSim, trace_log: Collect
) -> None:
    sim, gw = gateway_with({1: plc(1), 2: plc(2), 3: plc(3)}, line={"timeout": 0.1, "retries": 0})
    sim.faults(2).silent = True
    _trace(gw, Tracer(units=[1, 2], functions=[3]))
    with gw.connect() as master:
        assert master.request(1, READ_10, tid=101)[0] == 0x03
        assert master.request(1, bytes.fromhex("06 0001 0007"), tid=102)[0] == 0x06  # function
        assert master.request(2, READ_10, tid=103) == bytes((0x83, 0x0B))
        assert master.request(3, READ_10, tid=104)[0] == 0x03  # unit filtered out
        assert master.request(1, bytes.fromhex("03 0000 00C8"), tid=105) == bytes((0x83, 0x03))
        assert master.request(9, READ_10, tid=106) == bytes((0x83, 0x0A))  # unit filtered out
    http_get(gw, "/healthz")  # served after every reply's callback: the trace is complete
    assert trace_log.fields() == [
        ("request", 101, 1, None),
        ("reply", 101, 1, "ok"),
        ("request", 103, 2, None),
        ("reply", 103, 2, "target_failed"),
        ("request", 105, 1, None),
        ("reply", 105, 1, "rejected"),
    ]
    first_reply = trace_log.records[1]
    assert first_reply.__dict__["detail"] == "byte_count=20"
    assert first_reply.__dict__["latency_ms"] > 0
    assert first_reply.getMessage().startswith("<- 127.0.0.1:")
    assert (
        trace_log.records[0]
        .getMessage()
        .endswith("tid=101 unit=1 read_holding_registers(3) address=0 quantity=10 via tcp")
    )


def test_an_answer_for_a_master_gone_is_traced_as_dropped(
    gateway_with: GatewayOnSim, trace_log: Collect
) -> None:
    sim, gw = gateway_with({1: plc(1)}, line={"timeout": 1.0})
    sim.faults(1).reply_delay = 0.1
    _trace(gw, Tracer())
    master = gw.connect()
    master.send(1, READ_10, tid=7)
    wait_until(lambda: sim.stats().requests == 1, "the request on the wire")
    master.close()
    wait_until(lambda: len(trace_log.records) == 2, "the dropped answer in the trace")
    assert trace_log.fields() == [("request", 7, 1, None), ("none", 7, 1, "dropped")]


def test_nothing_is_traced_when_the_trace_is_off(
    gateway_with: GatewayOnSim, trace_log: Collect
) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    _trace(gw, None)
    with gw.connect() as master:
        master.request(1, READ_10)
    http_get(gw, "/healthz")
    assert trace_log.records == []
