"""Agent mode over real loopback and a paced pty: poll blocks answered from memory.

A gateway with ``[[poll]]`` blocks in front of a simulated slave at 19200 baud. The slave
logs every request it hears, so "no wire traffic" is counted where the wire ends, not
taken from the gateway's word. Masters are raw Modbus TCP sockets; every answer is held
byte for byte against the slave's own tables.
"""

from __future__ import annotations

import asyncio
import itertools
import random
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import pytest
from prometheus_client import CollectorRegistry

from gateway.config import MetricsConfig, build_config
from gateway.core.redundancy import Role
from gateway.io.http.endpoint import HttpEndpoint, respond, start_http
from gateway.io.http.guard import RouteAccess
from gateway.io.pair.channel import role_body
from gateway.sim import DataBank, SimulatedDevice
from gateway.sim.device import pack_bits, pack_registers
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    RunningGateway,
    SimBus,
    SimFactory,
    h,
    mbap,
    read,
    wait_until,
)

BAUDRATE = 19200
UNIT = 1
#: The holding-register block the tests read (its addresses 10..59) and the coil block.
REGISTERS = {"unit": UNIT, "function": 3, "address": 10, "count": 50}
COILS = {"unit": UNIT, "function": 1, "address": 5, "count": 37}
#: How long a flood runs at most, and what the other masters and the poller may wait meanwhile
#: (generous: the machine runs other work).
FLOOD_S = 2.0
HONEST_BOUND_S = 0.5
#: Long enough that no second poll comes during a test: every frame after the first polls
#: is a master's.
QUIET = {"every": 60.0, "max_age": 120.0}


class LoggingSlave(SimulatedDevice):
    """A slave that keeps every request it handles (what reached it over the wire)."""

    def __init__(self) -> None:
        holding = {address: (address * 7919 + 13) & 0xFFFF for address in range(200)}
        coils = {address: (address * 5 // 3) & 1 for address in range(100)}
        inputs = {address: (address * 31 + 7) & 0xFFFF for address in range(200)}
        super().__init__(
            name="logging slave",
            holding=DataBank(200, holding),
            coils=DataBank(100, coils, bits=True),
            input_registers=DataBank(200, inputs),
        )
        self.heard: list[tuple[float, bytes]] = []  # (arrival, PDU)
        self.mute = False  # hears (and logs) every request, answers none: a dead device
        self._lock = threading.Lock()

    def handle(self, pdu: bytes, *, broadcast: bool = False) -> bytes | None:
        with self._lock:
            self.heard.append((time.monotonic(), bytes(pdu)))
        if self.mute:
            return None
        return super().handle(pdu, broadcast=broadcast)

    def requests(self) -> list[bytes]:
        with self._lock:
            return [pdu for _, pdu in self.heard]

    def heard_since(self, moment: float) -> list[tuple[float, bytes]]:
        """(arrival, PDU) of every request the slave executed after ``moment``."""
        with self._lock:
            return [(arrived, pdu) for arrived, pdu in self.heard if arrived > moment]

    def arrivals(self, pdu: bytes) -> list[float]:
        """When each ``pdu`` the slave executed arrived."""
        with self._lock:
            return [arrived for arrived, heard in self.heard if heard == pdu]


def block_pdu(block: Mapping[str, Any]) -> bytes:
    return read(block["address"], block["count"], block["function"])


def registers(slave: LoggingSlave, address: int, count: int) -> bytes:
    data = pack_registers(slave.holding.read(address, count))
    return bytes((3, len(data))) + data


def bits(slave: LoggingSlave, address: int, count: int) -> bytes:
    data = pack_bits(slave.coils.read(address, count))
    return bytes((1, len(data))) + data


Agent = tuple["LoggingSlave", SimBus, RunningGateway, dict[str, Any]]
AgentFactory = Callable[..., Agent]


def answered_polls(gw: RunningGateway) -> int:
    """How many of the line's blocks hold an answer (read on the gateway's loop)."""

    def count() -> int:
        plan = gw.gateway.buses["a"]._core.plan
        return sum(1 for block in plan.blocks if block.answer is not None)

    return gw.call(count)


def serving(gw: RunningGateway) -> int:
    """How many of the line's blocks may answer from memory now (their poll's answer has
    arrived, no change since): the slave logs a poll before its answer is on the wire."""

    def count() -> int:
        plan = gw.gateway.buses["a"]._core.plan
        now = time.monotonic()
        return sum(1 for block in plan.blocks if block.usable(now))

    return gw.call(count)


def failing(gw: RunningGateway) -> int:
    """How many of the line's blocks are failing (their last poll got no normal answer)."""

    def count() -> int:
        return sum(1 for block in gw.gateway.buses["a"]._core.plan.blocks if block.failing)

    return gw.call(count)


@pytest.fixture
def agent(make_sim: SimFactory, make_gateway: GatewayFactory) -> Iterator[AgentFactory]:
    """``agent(polls, line={...})`` → (slave, sim, gateway, raw tables), the slave paced at
    19200 baud on a pty, the gateway polling ``polls``; returns once every block is polled."""

    def start(
        polls: Sequence[Mapping[str, Any]],
        line: Mapping[str, Any] | None = None,
        **tables: Any,
    ) -> Agent:
        slave = LoggingSlave()
        sim = make_sim({UNIT: slave}, baudrate=BAUDRATE)
        raw: dict[str, Any] = {
            "lines": {"a": sim.line_table([UNIT], **(line or {}))},
            "poll": [dict(block) for block in polls],
            **tables,
        }
        gw = make_gateway(raw)
        wait_until(lambda: answered_polls(gw) == len(polls), "every block polled")
        return slave, sim, gw, raw

    yield start


def test_reads_inside_a_block_come_from_memory_byte_for_byte(agent: AgentFactory) -> None:
    """Hundreds of sub-ranges of both blocks, from three masters, pipelined under their own
    transaction ids: each answer is exactly the slave's, and none reaches the wire."""
    slave, sim, gw, _ = agent([{**REGISTERS, **QUIET}, {**COILS, **QUIET}])
    polls = slave.requests()
    assert sorted(polls) == sorted([block_pdu(REGISTERS), block_pdu(COILS)])
    rng = random.Random(31)
    cases: list[tuple[bytes, bytes]] = []
    for _ in range(300):
        first = rng.randrange(10, 60)
        count = rng.randint(1, 60 - first)
        cases.append((read(first, count), registers(slave, first, count)))
        first = rng.randrange(5, 42)
        count = rng.randint(1, 42 - first)
        cases.append((read(first, count, 1), bits(slave, first, count)))
    cases += [
        (read(10, 50), registers(slave, 10, 50)),
        (read(5, 37, 1), bits(slave, 5, 37)),
    ]
    masters = [gw.connect() for _ in range(3)]
    try:
        for start in range(0, len(cases), 6):
            batch = cases[start : start + 6]
            client = masters[start // 6 % 3]
            tids = [
                client.send(UNIT, pdu, tid=1000 + start + index)
                for index, (pdu, _) in enumerate(batch)
            ]
            replies = {reply.transaction_id: reply for reply in (client.receive() for _ in batch)}
            for tid, (pdu, expected) in zip(tids, batch, strict=True):
                assert replies[tid].unit == UNIT
                assert replies[tid].pdu == expected, pdu.hex()
        assert slave.requests() == polls  # not one frame more on the wire
        # A read across the block's edge, another function, a range outside: the wire.
        client = masters[0]
        assert client.request(UNIT, read(55, 10)) == registers(slave, 55, 10)
        assert client.request(UNIT, read(0, 10)) == registers(slave, 0, 10)
        assert client.request(UNIT, read(10, 5, 4))[:2] == b"\x04\x0a"
        assert slave.requests()[len(polls) :] == [
            read(55, 10),
            read(0, 10),
            read(10, 5, 4),
        ]
    finally:
        for client in masters:
            client.close()
    assert sim.stats().early_requests == 0


WRITES = [
    # (request, the register or coil it changes, the value it leaves there)
    (h("06 0014 BEEF"), 20, 0xBEEF),
    (h("10 0021 0002 04 1234 5678"), 34, 0x5678),
    (h("16 0014 00F0 0F00"), 20, (0xBEEF & 0x00F0) | (0x0F00 & ~0x00F0)),
    (h("17 0000 0001 003B 0001 02 CAFE"), 59, 0xCAFE),
]


def test_a_write_then_a_read_sees_the_new_value_at_once(agent: AgentFactory) -> None:
    """Every write function, answered then read back at once; and a write and a read sent
    together (the read submitted before the write's answer): never the old value. Once
    the block has been polled again, reads come from memory with the new value."""
    slave, _, gw, _ = agent([{**REGISTERS, **QUIET}, {**COILS, **QUIET}])
    with gw.connect() as client:
        for request, register, value in WRITES:
            assert client.request(UNIT, request)[0] == request[0]
            assert client.request(UNIT, read(register, 1)) == registers(slave, register, 1)
            assert slave.holding[register] == value
        # The write and the read back to back on one connection, the read not waiting.
        for value in (0x0101, 0x0202, 0x0303):
            client.send_raw(
                mbap(1, UNIT, struct.pack(">BHH", 6, 40, value)) + mbap(2, UNIT, read(38, 5))
            )
            replies = {
                reply.transaction_id: reply.pdu for reply in (client.receive(), client.receive())
            }
            assert replies[1] == struct.pack(">BHH", 6, 40, value)
            assert replies[2] == registers(slave, 38, 5)
            assert struct.unpack(">H", replies[2][6:8])[0] == value
        # Coils: FC 5 and FC 15.
        assert client.request(UNIT, h("05 0007 FF00")) == h("05 0007 FF00")
        assert client.request(UNIT, read(5, 8, 1)) == bits(slave, 5, 8)
        assert slave.coils[7] == 1
        assert client.request(UNIT, h("0F 0010 0003 01 05"))[0] == 0x0F
        assert client.request(UNIT, read(16, 3, 1)) == bits(slave, 16, 3) == b"\x01\x01\x05"

        # The plan polls both blocks again after the writes: then memory has the new values.
        def polled_after(block: Mapping[str, Any], write: bytes) -> bool:
            heard = slave.requests()
            last_write = len(heard) - 1 - heard[::-1].index(write)
            return block_pdu(block) in heard[last_write:]

        wait_until(
            lambda: (
                polled_after(REGISTERS, struct.pack(">BHH", 6, 40, 0x0303))
                and polled_after(COILS, h("0F 0010 0003 01 05"))
            ),
            "both blocks polled again after their last write",
        )
        wait_until(lambda: serving(gw) == 2, "the new answers kept")
        heard = len(slave.requests())
        assert client.request(UNIT, read(10, 50)) == registers(slave, 10, 50)
        assert client.request(UNIT, read(5, 37, 1)) == bits(slave, 5, 37)
        assert len(slave.requests()) == heard


def test_a_write_through_another_unit_id_of_the_same_slave_invalidates(agent: AgentFactory) -> None:
    """Blocks are kept by line and slave address: a write under unit 9, routed to the same
    slave, is seen by a read under unit 1."""
    _, _, gw, _ = agent([{**REGISTERS, **QUIET}], routes=[{"unit": 9, "line": "a", "slave": UNIT}])
    with gw.connect() as client:
        assert client.request(9, h("06 001E 4242")) == h("06 001E 4242")
        assert client.request(UNIT, read(30, 1)) == b"\x03\x02\x42\x42"


def test_a_broadcast_write_and_a_function_the_gateway_cannot_place_invalidate(
    agent: AgentFactory,
) -> None:
    """A broadcast write reaches the slave and the next read sees it; a vendor function
    may change anything, so the next read goes to the wire too. A write outside every block
    leaves memory serving."""
    slave, _, gw, _ = agent([{**REGISTERS, **QUIET}])
    with gw.connect() as client:
        # Each change sent with a read right behind it, the read submitted before the
        # change has ended: the read goes to the wire (the block may be polled again
        # before it: a due poll goes first).
        for change, answer in (
            (mbap(1, 0, h("06 0019 0B0B")), None),
            (mbap(1, UNIT, h("41 0001")), h("C1 01")),
        ):  # a vendor's own
            heard = len(slave.requests())
            client.send_raw(change + mbap(2, UNIT, read(25, 1)))
            replies = [client.receive() for _ in range(1 if answer is None else 2)]
            assert {reply.transaction_id: reply.pdu for reply in replies} == (
                {2: b"\x03\x02\x0b\x0b"} | ({} if answer is None else {1: answer})
            )
            wait_until(lambda: serving(gw) == 1, "the block polled again after the change")
            after = slave.requests()[heard:]
            assert after[0] == change[7:] and sorted(after[1:]) == [
                block_pdu(REGISTERS),
                read(25, 1),
            ]
        heard = len(slave.requests())
        assert client.request(UNIT, h("06 0096 0001")) == h("06 0096 0001")  # register 150
        assert client.request(UNIT, read(25, 1)) == b"\x03\x02\x0b\x0b"
        assert slave.requests()[heard:] == [h("06 0096 0001")]


def test_an_exception_is_never_kept(agent: AgentFactory) -> None:
    """A block the slave answers with an exception (its range runs past the slave's map)
    serves nothing: every read inside it goes to the wire, and gets what the slave says."""
    beyond = {"unit": UNIT, "function": 3, "address": 190, "count": 20, **QUIET}
    slave, _, gw, raw = agent([{**REGISTERS, **QUIET}])
    config = build_config({**raw, "poll": [{**REGISTERS, **QUIET}, beyond]}, "<reloaded>")
    gw.run(gw.gateway.reload(config))
    wait_until(lambda: block_pdu(beyond) in slave.requests(), "the block polled")
    wait_until(lambda: failing(gw) == 1, "the block failing")
    heard = len(slave.requests())
    with gw.connect() as client:
        for _ in range(2):
            assert client.request(UNIT, read(195, 2)) == registers(slave, 195, 2)
            assert client.request(UNIT, read(195, 10)) == h("83 02")
    assert slave.requests()[heard:] == [read(195, 2), read(195, 10)] * 2


def test_a_flood_of_reads_from_memory_starves_neither_masters_nor_the_poller(
    agent: AgentFactory,
) -> None:
    """One master pipelines reads from memory as fast as it can (reading its answers), for
    at most ``FLOOD_S``; another master's reads from memory stay within ``HONEST_BOUND_S``
    and the block is still polled at its period."""
    every = 0.2
    slave, _, gw, _ = agent([{**REGISTERS, "every": every, "max_age": 1.0}])
    flood = b"".join(mbap(tid, UNIT, read(10 + tid % 50, 1)) for tid in range(2048))
    attacker = socket.create_connection(gw.address, timeout=DEADLINE_S)
    answered = 0
    stop = threading.Event()

    def drain() -> None:
        nonlocal answered
        with attacker.makefile("rb") as stream:
            while not stop.is_set():
                try:
                    header = stream.read(7)
                    if len(header) < 7:
                        return
                    stream.read(struct.unpack(">H", header[4:6])[0] - 1)
                except OSError:
                    if stop.is_set():
                        return  # the test closed it (the gateway may reset it unread)
                    raise
                answered += 1

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    waits: list[float] = []
    expected = registers(slave, 30, 5)
    started = time.monotonic()
    try:
        with gw.connect() as honest:
            while time.monotonic() - started < FLOOD_S:
                attacker.sendall(flood)
                sent = time.monotonic()
                assert honest.request(UNIT, read(30, 5)) == expected
                waits.append(time.monotonic() - sent)
    finally:
        stop.set()
        attacker.shutdown(socket.SHUT_RDWR)
        attacker.close()
        reader.join(DEADLINE_S)
    assert answered > 2048  # the flood was served too
    assert max(waits) <= HONEST_BOUND_S, max(waits)
    polls = [t for t in slave.arrivals(block_pdu(REGISTERS)) if t >= started]
    gaps = [later - earlier for earlier, later in itertools.pairwise(polls)]
    assert len(polls) >= FLOOD_S / every / 2 and max(gaps) <= every + HONEST_BOUND_S, gaps


def test_a_silent_slave_ages_out_of_memory_then_gets_0x0b(agent: AgentFactory) -> None:
    """The slave stops answering: memory serves until max_age after the last good poll,
    never after; then reads go to the wire and get 0x0B. When it answers again, memory
    serves again."""
    every, max_age = 0.2, 1.0
    # A fixed timeout, generous on a busy machine: the slave's answers are not learned yet.
    slave, sim, gw, _ = agent(
        [{**REGISTERS, "every": every, "max_age": max_age}], line={"timeout": 0.5}
    )
    expected = registers(slave, 20, 10)
    answers: list[tuple[float, float, bytes]] = []  # sent, answered, PDU
    with gw.connect(timeout=5.0) as client:

        def ask() -> bytes:
            sent = time.monotonic()
            pdu: bytes = client.request(UNIT, read(20, 10))
            answers.append((sent, time.monotonic(), pdu))
            return pdu

        for _ in range(20):
            assert ask() == expected
        sim.faults(UNIT).silent = True
        silenced_at = time.monotonic()
        deadline = time.monotonic() + DEADLINE_S
        while sum(pdu == b"\x83\x0b" for _, _, pdu in answers) < 5:
            ask()
            assert time.monotonic() < deadline, answers[-5:]
        normal = [(sent, pdu) for sent, _, pdu in answers if pdu != b"\x83\x0b"]
        assert all(pdu == expected for _, pdu in normal)
        # The last good poll's frame left before it arrived, and before the silence: no
        # read sent later than max_age after that was answered.
        last_poll = max(t for t in slave.arrivals(block_pdu(REGISTERS)) if t < silenced_at)
        late = [sent - last_poll for sent, _ in normal if sent > last_poll + max_age]
        assert late == []
        # Memory served on while its data was young, and no read failed before the data was
        # old (give or take how late the slave took the poll's frame on a busy machine).
        slack = 0.3
        assert any(sent > last_poll + max_age - slack for sent, _ in normal)
        failed = [sent for sent, _, pdu in answers if pdu == b"\x83\x0b"]
        assert min(failed) > last_poll + max_age - slack
        sim.faults(UNIT).silent = False

        def from_memory() -> bool:
            on_the_wire = slave.requests().count(read(20, 10))
            return ask() == expected and slave.requests().count(read(20, 10)) == on_the_wire

        wait_until(
            from_memory,
            "memory serving again",
            timeout=DEADLINE_S,
        )


@pytest.mark.slow  # the back-off's doublings, 1.5 s, after the isolation
def test_a_dead_slaves_block_is_polled_at_the_probe_back_off(agent: AgentFactory) -> None:
    """Once its slave is isolated as dead, a block is polled (or its slave proved) at the
    probe back-off, ``probe_interval`` doubling, not every period: a dead slave's polls do
    not hold the line for a timeout every ``every``."""
    every, probe = 0.1, 0.1
    slave, _, gw, _ = agent(
        [{**REGISTERS, "every": every, "max_age": 0.3}],
        line={"timeout": 0.1, "probe_interval": probe, "probe_max_interval": 10.0},
    )

    def health() -> tuple[str, float]:
        record = gw.gateway.buses["a"]._core.health.slaves.get(UNIT)
        return ("", 0.0) if record is None else (record.state.value, record.backoff)

    slave.mute = True
    wait_until(lambda: gw.call(health)[0] == "down", "the slave isolated as dead")
    down_at = time.monotonic()
    # Each probe without an answer doubles the back-off: 0.1 + 0.2 + 0.4 + 0.8 s of probes
    # before it reaches 1.6 s (at the pace of every period, 4 x 0.2 s).
    wait_until(lambda: gw.call(health)[1] >= 16 * probe, "the back-off at 1.6 s")
    took = time.monotonic() - down_at
    heard = [round(t - down_at, 3) for t, _ in slave.heard_since(down_at)]
    assert took >= 0.9 * (1 + 2 + 4 + 8) * probe, (took, heard)


def test_a_reload_that_keeps_a_block_keeps_its_data(agent: AgentFactory) -> None:
    """A reload that retunes the line, changes a block's period and adds a block keeps the
    unchanged block's memory (no poll of it); so does one that reopens the port. A block
    whose range changed starts empty."""
    slave, sim, gw, raw = agent([{**REGISTERS, **QUIET}])
    polls = slave.requests()

    def reload(tables: dict[str, Any]) -> None:
        gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))

    added = {"unit": UNIT, "function": 3, "address": 100, "count": 10, **QUIET}
    retuned = {
        **raw,
        "lines": {"a": {**raw["lines"]["a"], "timeout": 0.3}},
        "poll": [{**REGISTERS, "every": 50.0, "max_age": 100.0}, added],
    }
    reload(retuned)
    wait_until(lambda: answered_polls(gw) == 2, "the added block polled")
    assert slave.requests() == [*polls, block_pdu(added)]
    with gw.connect() as client:
        assert client.request(UNIT, read(10, 50)) == registers(slave, 10, 50)
    assert slave.requests() == [*polls, block_pdu(added)]
    # A reopened port (another baud rate: the slave no longer understands the line) hands
    # the memory to the new line: still answered, from memory alone.
    reopened = {**retuned, "lines": {"a": {**retuned["lines"]["a"], "baudrate": 9600}}}
    reload(reopened)
    with gw.connect() as client:
        assert client.request(UNIT, read(12, 7)) == registers(slave, 12, 7)
        assert client.request(UNIT, read(100, 10)) == registers(slave, 100, 10)
    assert slave.requests() == [*polls, block_pdu(added)]
    # A changed range is another block: what memory had is not served for it.
    moved = {**reopened, "lines": retuned["lines"], "poll": [{**REGISTERS, "count": 40, **QUIET}]}
    reload(moved)
    wait_until(lambda: answered_polls(gw) == 1, "the changed block polled")
    assert slave.requests()[-1] == read(10, 40)
    assert sim.stats().early_requests == 0


class FakePeer:
    """The other gateway of a pair as far as ``/role`` goes, on a loop of its own: active
    (its lease renewed at every answer) until ``active`` is cleared."""

    def __init__(self) -> None:
        self.active = True
        self.asked = 0
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="fake-peer")
        self._thread.start()
        self.endpoint = asyncio.run_coroutine_threadsafe(self._start(), self.loop).result(
            DEADLINE_S
        )

    async def _route(
        self,
        method: str,
        _target: str,
        _headers: Mapping[str, str],
        _reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        self.asked += 1
        if self.active:
            await respond(
                writer, 200, "application/json", role_body(Role.ACTIVE, 5.0, 100, True), method
            )
        else:
            await respond(
                writer, 503, "application/json", role_body(Role.STANDBY, 0.0, 100, True), method
            )

    async def _start(self) -> HttpEndpoint:
        routes = {"/role": (self._route, RouteAccess.STATUS)}
        return await start_http(
            MetricsConfig(True, "127.0.0.1", 0), CollectorRegistry(), lambda: (True, "ok"), routes
        )

    @property
    def address(self) -> str:
        host, port = self.endpoint.address
        return f"{host}:{port}"

    def stop(self) -> None:
        asyncio.run_coroutine_threadsafe(self.endpoint.close(), self.loop).result(DEADLINE_S)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(DEADLINE_S)
        self.loop.close()


@pytest.fixture
def fake_peer() -> Iterator[FakePeer]:
    peer = FakePeer()
    try:
        yield peer
    finally:
        peer.stop()


@pytest.mark.slow
def test_the_standby_of_a_pair_does_not_poll_until_it_takes_over(
    make_sim: SimFactory, make_gateway: GatewayFactory, fake_peer: FakePeer
) -> None:
    """Beside an active peer the gateway stands by and its blocks are never polled; once the
    peer stops being active and the gateway takes over, it polls them."""
    slave = LoggingSlave()
    sim = make_sim({UNIT: slave}, baudrate=BAUDRATE)
    with socket.socket() as hole:  # the peer's Modbus listener: nobody (nothing forwarded)
        hole.bind(("127.0.0.1", 0))
        nobody = f"127.0.0.1:{hole.getsockname()[1]}"
    gw = make_gateway(
        {
            "lines": {"a": sim.line_table([UNIT])},
            "poll": [{**REGISTERS, "every": 0.1, "max_age": 0.3}],
            "redundancy": {
                "peer": fake_peer.address,
                "peer_modbus": nobody,
                "lease": 0.2,
                "takeover_after": 0.6,
                "keepalive": "off",
            },
        }
    )
    pair = gw.gateway.pair
    assert pair is not None
    assert gw.call(lambda: pair.standing_by)
    asked = fake_peer.asked
    # Three rounds of the pair's role poll: a dozen periods of the block.
    wait_until(lambda: fake_peer.asked >= asked + 3, "the pair asking its peer")
    assert gw.call(lambda: pair.standing_by)
    assert slave.requests() == []
    fake_peer.active = False
    wait_until(lambda: gw.call(lambda: not pair.standing_by), "the gateway taking over")
    wait_until(lambda: block_pdu(REGISTERS) in slave.requests(), "the block polled")
