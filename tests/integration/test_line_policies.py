"""Dead-slave isolation, request coalescing, the read cache and per-slave timeouts, end to end.

Each test runs the real gateway against a simulated line on a pty and checks
what reached the wire through the simulator's own counters, so "served without
using the line" is observed, not assumed.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import time
from pathlib import Path

from gateway.config import build_config
from gateway.sim import plc
from tests.helpers import (
    DEADLINE_S,
    GatewayOnSim,
    LogCollector,
    RawClient,
    RunningGateway,
    wait_until,
)

READ_10 = bytes.fromhex("03 0000 000A")
SLOW_READ = bytes.fromhex("03 0100 007D")  # 125 registers: ~265 ms on the wire at 9600 baud


def sample(gw: RunningGateway, name: str, **labels: str) -> float:
    """A metric's current value (0 when the series does not exist yet)."""
    value = gw.gateway.metrics.registry.get_sample_value(name, labels)
    return 0.0 if value is None else value


def registers(pdu: bytes) -> list[int]:
    """Register values of an FC3 response PDU."""
    assert pdu[0] == 0x03, pdu.hex()
    return list(struct.unpack(f">{pdu[1] // 2}H", pdu[2:]))


def test_a_dead_slave_is_isolated_then_probed_back(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        # No late-answer window: a silent slave sends nothing late (the window's own tests
        # are in test_gateway and tests/unit/test_line_core).
        line={"timeout": 0.05, "retries": 0, "dead_after": 3, "probe_interval": 0.2,
              "probe_max_interval": 0.4, "late_answer_window": 0},
    )  # fmt: skip
    with gw.connect() as master:
        assert master.request(2, READ_10)[0] == 0x03  # heard from: it gets its own series
        sim.faults(2).silent = True
        assert master.request(2, READ_10) == bytes([0x83, 0x0B])
        assert sample(gw, "modbus_gateway_slave_suspect", line="a", unit="2") == 1
        assert sample(gw, "modbus_gateway_slaves_isolated", line="a", state="suspect") == 1
        assert sample(gw, "modbus_gateway_slave_up", line="a", unit="2") == 1
        for _ in range(2):
            assert master.request(2, READ_10) == bytes([0x83, 0x0B])
        assert sim.stats().silent_drops == 3
        assert sample(gw, "modbus_gateway_slave_up", line="a", unit="2") == 0
        assert sample(gw, "modbus_gateway_slaves_isolated", line="a", state="down") == 1
        # Isolated: answered 0x0B at once, nothing sent on the line.
        assert master.request(2, READ_10) == bytes([0x83, 0x0B])
        assert sim.stats().silent_drops == 3
        # The healthy slave is served as before.
        assert registers(master.request(1, READ_10))[:6] == [0, 2, 4, 6, 8, 10]

        def probed() -> bool:
            assert master.request(2, READ_10) == bytes([0x83, 0x0B])
            return sim.stats().silent_drops == 4

        wait_until(probed, "a probe of the dead slave")
        sim.faults(2).silent = False

        def answers() -> bool:
            return master.request(2, READ_10)[0] == 0x03

        wait_until(answers, "the slave to be marked up by a probe's answer")
        assert sample(gw, "modbus_gateway_slave_up", line="a", unit="2") == 1
        requests_before = sim.stats().requests
        assert registers(master.request(2, READ_10))[:3] == [0, 2, 4]
        assert sim.stats().requests == requests_before + 1


def _occupy_the_wire(master: RawClient) -> int:
    """Start a long read so that what follows has to queue behind it."""
    return master.send(1, SLOW_READ)


def test_identical_queued_reads_share_one_transaction(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, sim={"baudrate": 9600})
    masters = [gw.connect() for _ in range(4)]
    try:
        before = sim.stats().requests
        busy_tid = _occupy_the_wire(masters[0])
        tids = [master.send(1, READ_10) for master in masters[1:]]
        busy = masters[0].receive()
        assert busy.transaction_id == busy_tid and busy.pdu[1] == 250
        for master, tid in zip(masters[1:], tids, strict=True):
            reply = master.receive()
            assert reply.transaction_id == tid
            assert registers(reply.pdu)[:6] == [0, 2, 4, 6, 8, 10]
        assert sim.stats().requests == before + 2
        assert sample(gw, "modbus_gateway_coalesced_requests_total", line="a") == 2
    finally:
        for master in masters:
            master.close()


def test_coalescing_can_be_switched_off(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, sim={"baudrate": 9600}, line={"coalesce": False})
    masters = [gw.connect() for _ in range(4)]
    try:
        before = sim.stats().requests
        _occupy_the_wire(masters[0])
        for master in masters[1:]:
            master.send(1, READ_10)
        for master in masters:
            master.receive()
        assert sim.stats().requests == before + 4
    finally:
        for master in masters:
            master.close()


def test_a_read_never_jumps_over_a_write_queued_before_it(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)}, sim={"baudrate": 9600})
    busy, other, writer = gw.connect(), gw.connect(), gw.connect()
    try:
        _occupy_the_wire(busy)
        other_tid = other.send(1, READ_10)  # queued before the write, may see the old value
        write_tid = writer.send(1, bytes.fromhex("06 0000 04D2"))
        read_tid = writer.send(1, READ_10)  # pipelined behind its own write: must see it
        busy.receive()
        assert other.receive().transaction_id == other_tid
        write = writer.receive()
        assert write.transaction_id == write_tid and write.pdu == bytes.fromhex("06 0000 04D2")
        read = writer.receive()
        assert read.transaction_id == read_tid
        assert registers(read.pdu)[0] == 1234
        assert sim.device(1).holding[0] == 1234
    finally:
        for master in (busy, other, writer):
            master.close()


def test_the_read_cache_serves_within_max_age_and_forgets_on_write(
    gateway_with: GatewayOnSim,
) -> None:
    sim, gw = gateway_with(
        {1: plc(1)},
        line={"cache": [{"unit": 1, "function": 3, "start": 0, "count": 100, "max_age": 60.0}]},
    )
    with gw.connect() as master:
        before = sim.stats().requests
        assert registers(master.request(1, READ_10))[:3] == [0, 2, 4]
        assert sim.stats().requests == before + 1
        assert registers(master.request(1, READ_10))[:3] == [0, 2, 4]
        assert sim.stats().requests == before + 1  # from the cache
        outside = bytes.fromhex("03 0064 0001")  # address 100: outside the rule
        master.request(1, outside)
        master.request(1, outside)
        assert sim.stats().requests == before + 3
        master.request(1, bytes.fromhex("06 0001 0063"))
        assert registers(master.request(1, READ_10))[:3] == [0, 99, 4]
        assert sim.stats().requests == before + 5
        assert sample(gw, "modbus_gateway_requests_total", line="a", unit="1",
                      function="read_holding_registers", outcome="cached") == 1  # fmt: skip


def test_a_per_slave_timeout_overrides_the_lines(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        line={"timeout": 3.0, "retries": 0, "slave_timeouts": {"2": 0.05}},
    )
    sim.faults(2).silent = True
    with gw.connect() as master:
        started = time.monotonic()
        assert master.request(2, READ_10) == bytes([0x83, 0x0B])
        assert time.monotonic() - started < 1.5  # the line's 3 s would be twice this


def test_a_broadcast_write_empties_the_cache(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        line={"cache": [{"unit": 1, "function": 3, "start": 0, "count": 100, "max_age": 60.0}],
              "broadcast_turnaround": 0.01},
        server={"broadcast_reply": True},
    )  # fmt: skip
    with gw.connect() as master:
        assert registers(master.request(1, READ_10))[:3] == [0, 2, 4]
        assert registers(master.request(1, READ_10))[:3] == [0, 2, 4]  # cached
        before = sim.stats().requests
        assert master.request(0, bytes.fromhex("06 0002 0777")) == bytes.fromhex("06 0002 0777")
        assert registers(master.request(1, READ_10))[:3] == [0, 2, 0x0777]
        assert sim.stats().requests == before + 2  # the broadcast, then a real read
    assert sim.device(2).holding[2] == 0x0777


def test_switching_isolation_off_on_reload_serves_the_slave_again(
    gateway_with: GatewayOnSim,
) -> None:
    line = {"timeout": 0.05, "retries": 0, "dead_after": 1, "probe_interval": 60.0}
    sim, gw = gateway_with({1: plc(1), 2: plc(2)}, line=line)
    with gw.connect() as master:
        assert master.request(2, READ_10)[0] == 0x03  # heard from: it gets its own series
        sim.faults(2).silent = True
        assert master.request(2, READ_10) == bytes([0x83, 0x0B])
        assert master.request(2, READ_10) == bytes([0x83, 0x0B])  # isolated: not sent
        assert sim.stats().silent_drops == 1
        assert sample(gw, "modbus_gateway_slave_up", line="a", unit="2") == 0
        raw = {
            "server": {"listen": "127.0.0.1:0"},
            "metrics": {"listen": "127.0.0.1:0"},
            "lines": {"a": sim.line_table([1, 2], **{**line, "dead_after": 0})},
        }
        gw.run(gw.gateway.reload(build_config(raw, "<reload>")))
        sim.faults(2).silent = False
        assert registers(master.request(2, READ_10))[:3] == [0, 2, 4]
    assert sample(gw, "modbus_gateway_slave_up", line="a", unit="2") == 1


def test_a_reload_that_reopens_the_line_keeps_its_queue(gateway_with: GatewayOnSim) -> None:
    """Requests queued on a line whose port settings change wait for the reopened line
    instead of being answered 0x0A."""
    sim, gw = gateway_with({1: plc(1)}, sim={"baudrate": 4800})
    with gw.connect() as master:
        tids = [master.send(1, bytes.fromhex(f"03 {1000 + 10 * i:04X} 0001")) for i in range(6)]
        first = master.receive()
        assert first.transaction_id == tids[0]
        raw = {
            "server": {"listen": "127.0.0.1:0"},
            "metrics": {"listen": "127.0.0.1:0"},
            "lines": {"a": sim.line_table([1], baudrate=9600)},  # a port setting: reopen
        }
        gw.run(gw.gateway.reload(build_config(raw, "<reload>")))
        assert gw.gateway.buses["a"].config.baudrate == 9600
        for index, tid in enumerate(tids[1:], start=1):
            reply = master.receive()
            assert reply.transaction_id == tid
            assert registers(reply.pdu) == [1000 + 10 * index]


def test_a_late_answer_through_a_reopened_port_reaches_no_request(
    gateway_with: GatewayOnSim, tmp_path: Path
) -> None:
    """A reload that reopens the line (here: the device under another name, the same wire)
    keeps the slave's late-answer window: the answer to the read that timed out before the
    reload arrives through the new port, and must not answer the same read sent after it,
    when the register holds another value."""
    sim, gw = gateway_with({1: plc(1)}, line={"timeout": 0.5, "retries": 0})
    alias = tmp_path / "ttyBUS"
    alias.symlink_to(sim.path)
    sim.device(1).holding[7] = 100
    sim.faults(1).reply_delay = 1.0  # answers 0.5 s after the gateway gave up
    with gw.connect() as master:
        lost = master.request(1, bytes.fromhex("03 0007 0001"))
        assert lost == bytes.fromhex("83 0B")
        raw = {
            "server": {"listen": "127.0.0.1:0"},
            "lines": {"a": sim.line_table([1], device=str(alias), timeout=0.5, retries=0)},
        }
        gw.run(gw.gateway.reload(build_config(raw, "<reload>")))
        assert gw.gateway.buses["a"].config.device == str(alias)
        sim.device(1).holding[7] = 200
        sim.faults(1).reply_delay = 0.0
        assert registers(master.request(1, bytes.fromhex("03 0007 0001"))) == [200]
    # The late answer did come, through the new port; the held read may have brought a
    # proof read of the gateway's own first (its answer goes to nobody).
    assert sim.stats().responses in (2, 3)


def test_requests_sent_while_a_reopening_line_finishes_its_transaction_wait_for_it(
    gateway_with: GatewayOnSim,
) -> None:
    """A reload that reopens the line lets the transaction on the wire finish first; what
    masters send meanwhile waits for the reopened line too, rather than being refused."""
    sim, gw = gateway_with({1: plc(1)}, sim={"baudrate": 4800})
    with gw.connect() as master:
        slow = master.send(1, SLOW_READ)  # ~0.6 s on the wire at 4800 baud
        wait_until(lambda: sim.stats().requests >= 1, "the slow read on the wire")
        raw = {
            "server": {"listen": "127.0.0.1:0"},
            "lines": {"a": sim.line_table([1], baudrate=9600)},  # a port setting: reopen
        }
        logs = LogCollector()
        logger = logging.getLogger("gateway")
        level = logger.level
        logger.setLevel(logging.INFO)
        logger.addHandler(logs)
        try:
            reload = asyncio.run_coroutine_threadsafe(
                gw.gateway.reload(build_config(raw, "<reload>")), gw.loop
            )
            # Logged as the line stops sending, in the same turn of the loop.
            wait_until(lambda: any("reopening" in m for m in logs.messages), "the hand-over")
            meanwhile = [master.send(1, bytes.fromhex(f"03 {2000 + i:04X} 0001")) for i in range(3)]
            reload.result(DEADLINE_S)
        finally:
            logger.removeHandler(logs)
            logger.setLevel(level)
        assert gw.gateway.buses["a"].config.baudrate == 9600
        first = master.receive()
        assert first.transaction_id == slow and first.pdu[0] == 0x03
        for index, tid in enumerate(meanwhile):
            reply = master.receive()
            assert reply.transaction_id == tid
            assert registers(reply.pdu) == [2000 + index]
