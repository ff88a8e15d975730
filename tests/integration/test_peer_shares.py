"""Forwarding between two real gateways over loopback: each master's share and record.

A pair in one process: the *active* (127.0.0.2, priority 200) in front of a simulated
line, started first, takes over; the *standby* (127.0.0.3), with a line of its own that
it only listens to, finds it active and forwards. A short lease keeps the start quick.
Masters connect from their own loopback addresses (127.0.0.5 and up), since a gateway
answers 0x0A to anything from its peer's address while it stands by.
"""

from __future__ import annotations

import asyncio
import json
import socket
import struct
from pathlib import Path
from typing import Any

import pytest

from bench.hostile import read_exactly
from bench.pair_lab import free_ports
from gateway.sim import plc
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    RunningGateway,
    SimBus,
    SimFactory,
    mbap,
    wait_until,
)

READ_1 = struct.pack(">BHH", 3, 0, 1)
HOSTILE, HONEST, DIRECT = "127.0.0.5", "127.0.0.6", "127.0.0.7"
ACTIVE_HOST, STANDBY_HOST = "127.0.0.2", "127.0.0.3"
MANY_HOSTILE = [f"127.0.0.{n}" for n in range(10, 22)]  # twelve addresses


def pair_of(
    make_sim: SimFactory,
    make_gateway: GatewayFactory,
    server: dict[str, Any] | None = None,
    line: dict[str, Any] | None = None,
    audit: Path | None = None,
) -> tuple[SimBus, RunningGateway, RunningGateway]:
    """(the active's line, the active, the standby), the standby forwarding to the active."""
    sim = make_sim({1: plc(1), 2: plc(2)})
    quiet = make_sim({1: plc(1), 2: plc(2)})  # the standby's own line: it only listens
    ports = {host: free_ports(host, 2) for host in (ACTIVE_HOST, STANDBY_HOST)}

    def tables(host: str, peer: str, priority: int, bus: SimBus) -> dict[str, Any]:
        modbus, http = ports[host]
        peer_modbus, peer_http = ports[peer]
        raw: dict[str, Any] = {
            "server": {**(server or {}), "listen": f"{host}:{modbus}"},
            "metrics": {"listen": f"{host}:{http}"},
            "lines": {"a": bus.line_table([1, 2], **(line or {}))},
            "redundancy": {
                "peer": f"{peer}:{peer_http}",
                "peer_modbus": f"{peer}:{peer_modbus}",
                "priority": priority,
                "lease": 0.2,
                "takeover_after": 0.6,
            },
        }
        if audit is not None:
            raw["audit"] = {"path": str(audit / f"{host}.jsonl")}
        return raw

    active = make_gateway(tables(ACTIVE_HOST, STANDBY_HOST, 200, sim))
    active_pair = active.gateway.pair
    assert active_pair is not None
    wait_until(lambda: active.call(lambda: not active_pair.standing_by), "the first one active")
    standby = make_gateway(tables(STANDBY_HOST, ACTIVE_HOST, 100, quiet))
    pair = standby.gateway.pair
    assert pair is not None
    wait_until(lambda: standby.call(lambda: pair.forwarder.peer_active), "the peer seen active")
    assert standby.call(lambda: pair.standing_by)
    assert active.call(lambda: not active_pair.standing_by)
    return sim, active, standby


class Poller:
    """One master connection from ``source``: a request, its answer, again."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.tid = 0

    @classmethod
    async def open(cls, address: tuple[str, int], source: str) -> Poller:
        reader, writer = await asyncio.wait_for(
            asyncio.open_connection(*address, local_addr=(source, 0)), DEADLINE_S
        )
        return cls(reader, writer)

    async def ask(self, unit: int, pdu: bytes) -> bytes:
        """The answer's PDU; b"" when the connection closed."""
        self.tid = (self.tid + 1) & 0xFFFF
        self.writer.write(mbap(self.tid, unit, pdu))
        try:
            header = await asyncio.wait_for(self.reader.readexactly(7), DEADLINE_S)
            tid, _protocol, length, _unit = struct.unpack(">HHHB", header)
            answer = await asyncio.wait_for(self.reader.readexactly(length - 1), DEADLINE_S)
        except (asyncio.IncompleteReadError, ConnectionError):
            return b""
        assert tid == self.tid
        return answer

    def close(self) -> None:
        self.writer.transport.abort()


async def flat_out(poller: Poller, stop: asyncio.Event) -> None:
    """Poll as fast as answered until ``stop``; a closed connection ends it."""
    while not stop.is_set():
        if not await poller.ask(1, READ_1):
            return


@pytest.mark.parametrize(
    "hostile_sources", [[HOSTILE] * 12, MANY_HOSTILE], ids=["one address", "12 addresses"]
)
def test_a_host_holding_most_of_the_standbys_connections_leaves_the_others_their_share(
    make_sim: SimFactory, make_gateway: GatewayFactory, hostile_sources: list[str]
) -> None:
    """A host holds 12 of the standby's 16 connections, each polling flat out, while four
    masters of the active keep it busy (16 slots on each): an honest master of the
    standby still gets at least 90 % of 40 polls answered. From one address, the host's
    connections share one link (one slot and one share of the active's line); from
    twelve, they take twelve links, which the active admits within the peer's own budget
    of connections, beside the four of its masters, without refusing the honest one's."""
    _sim, active, standby = pair_of(make_sim, make_gateway, server={"max_connections": 16})
    pair = standby.gateway.pair
    assert pair is not None
    forwarder = pair.forwarder

    async def scenario() -> tuple[list[bytes], int]:
        stop = asyncio.Event()
        direct = [await Poller.open(active.address, DIRECT) for _ in range(4)]
        hostile = [await Poller.open(standby.address, source) for source in hostile_sources]
        load = [asyncio.ensure_future(flat_out(p, stop)) for p in direct + hostile]
        honest = await Poller.open(standby.address, HONEST)
        answers: list[bytes] = []
        try:
            for _ in range(40):
                answers.append(await honest.ask(1, READ_1))
                await asyncio.sleep(0.01)  # the honest master's poll period, not a sync
            links = standby.call(lambda: forwarder.connections)
        finally:
            stop.set()
            await asyncio.wait(load, timeout=DEADLINE_S)
            for poller in [*direct, *hostile, honest]:
                poller.close()
        return answers, links

    answers, links = asyncio.run(scenario())
    good = [answer for answer in answers if answer[:2] == bytes((3, 2))]  # one register
    assert len(good) >= 36, [answer.hex() for answer in answers if answer not in good][:5]
    assert links == len(set(hostile_sources)) + 1  # one per address; the honest has its own


def records(gateway: RunningGateway, path: Path) -> list[dict[str, Any]]:
    audit = gateway.gateway.audit
    assert audit is not None and audit.flush(DEADLINE_S)
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_a_forwarded_write_that_executed_but_got_0x0b_has_one_record_naming_its_master(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    """The slave stores the write, but every answer it sends is corrupted: the active
    answers 0x0B. The standby's audit record names the master with outcome ``unknown``;
    the active's names the standby only."""
    sim, active, standby = pair_of(
        make_sim, make_gateway, line={"timeout": 0.1, "retries": 0}, audit=tmp_path
    )
    sim.faults(2).crc_error_rate = 1.0
    write = struct.pack(">BHH", 6, 100, 0x4321)

    async def scenario() -> tuple[bytes, str]:
        master = await Poller.open(standby.address, HONEST)
        try:
            answer = await master.ask(2, write)
            host, port = master.writer.get_extra_info("sockname")[:2]
            return answer, f"{host}:{port}"
        finally:
            master.close()

    answer, peer = asyncio.run(scenario())
    assert answer == bytes((0x86, 0x0B))
    assert sim.device(2).holding[100] == 0x4321  # it executed

    def naming(gateway: RunningGateway, path: Path) -> list[dict[str, Any]]:
        """The request records that name the master anywhere (written before its answer)."""
        return [
            r for r in records(gateway, path) if r["event"] == "request" and peer in json.dumps(r)
        ]

    mine = naming(standby, tmp_path / f"{STANDBY_HOST}.jsonl")
    assert len(mine) == 1, mine
    assert mine[0]["peer"] == peer and mine[0]["outcome"] == "unknown"
    assert mine[0]["function"] == 6 and mine[0]["slave"] == 2
    # The active recorded the write under the standby's address, never the master's.
    theirs = [
        r for r in records(active, tmp_path / f"{ACTIVE_HOST}.jsonl") if r["event"] == "request"
    ]
    assert [r["outcome"] for r in theirs] == ["unknown"]
    assert theirs[0]["peer"].startswith(f"{STANDBY_HOST}:")
    assert naming(active, tmp_path / f"{ACTIVE_HOST}.jsonl") == []


def test_only_the_configured_peers_address_has_a_budget_and_it_is_bounded(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    """With max_connections = 2 held by masters at work (``when_full = "refuse"``), the
    peer's address still gets two connections in, and no third; any other address gets
    nothing more."""
    sim = make_sim({1: plc(1)})
    nobody = free_ports(STANDBY_HOST, 2)  # the peer's addresses, nothing listening there
    server_table = {"max_connections": 2, "when_full": "refuse", "listen": f"{ACTIVE_HOST}:0"}
    gateway = make_gateway(
        {
            "server": server_table,
            "lines": {"a": sim.line_table([1])},
            "redundancy": {
                "peer": f"{STANDBY_HOST}:{nobody[0]}",
                "peer_modbus": f"{STANDBY_HOST}:{nobody[1]}",
            },
        }
    )
    server = gateway.gateway.servers[0]
    held: list[socket.socket] = []

    def connect(source: str) -> socket.socket:
        sock = socket.create_connection(gateway.address, DEADLINE_S, (source, 0))
        sock.settimeout(DEADLINE_S)
        held.append(sock)
        return sock

    def admitted(count: int) -> None:
        wait_until(lambda: gateway.call(lambda: server.connections) == count, f"{count} open")

    try:
        for sock in (connect(DIRECT), connect(DIRECT)):  # masters at work: each has asked
            sock.sendall(struct.pack(">HHHB", 1, 0, len(READ_1) + 1, 1) + READ_1)
            assert read_exactly(sock, 7)[:2] == b"\x00\x01"
        admitted(2)
        connect(STANDBY_HOST)
        connect(STANDBY_HOST)
        admitted(4)
        for source in (DIRECT, HOSTILE, STANDBY_HOST):
            assert connect(source).recv(1) == b"", source  # closed at accept: an EOF
        assert gateway.call(lambda: server.connections) == 4
    finally:
        for sock in held:
            sock.close()
