"""A standby's forwarding (``PeerForwarder``) over real loopback TCP.

The peer is a real gateway in front of a simulated line (on its own loop in a
background thread), or, for the hostile and slow cases, a small asyncio server that
answers what a test tells it to. The forwarder runs on the test's own event loop.
Synchronisation is by replies and by state the code reaches (polled with a deadline,
as ``tests.helpers.wait_until`` does), never by sleeping a guessed time.
"""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

import pytest

from gateway.core.line import LineRequest
from gateway.core.outcome import Outcome
from gateway.io.pair.forward import PeerForwarder
from gateway.sim import plc
from gateway.sim.device import pack_registers
from tests.helpers import DEADLINE_S, GatewayOnSim, RunningGateway, mbap

READ_6 = struct.pack(">BHH", 3, 0, 6)
READ_1 = struct.pack(">BHH", 3, 100, 1)
UNAVAILABLE = bytes((0x83, 0x0A))
FAILED = bytes((0x83, 0x0B))
Answer = tuple[bytes, Outcome]


def registers(values: list[int]) -> bytes:
    data = pack_registers(values)
    return bytes((3, len(data))) + data


class Master:
    """Stands for one master's connection on the standby (the forwarder's key)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return f"Master({self.name})"


class Asked:
    """One request handed to the forwarder, and every answer it got (exactly one, we check)."""

    def __init__(self, slave: int, pdu: bytes, master: Master, broadcast: bool = False) -> None:
        self.answers: list[Answer] = []
        self.done = asyncio.get_running_loop().create_future()
        self.request = LineRequest(slave, pdu, master, self._reply, broadcast=broadcast)

    def _reply(self, pdu: bytes, outcome: Outcome) -> None:
        self.answers.append((pdu, outcome))
        if not self.done.done():
            self.done.set_result((pdu, outcome))

    async def answer(self) -> Answer:
        """The one answer (fails after the deadline, or if a second came)."""
        answer: Answer = await asyncio.wait_for(asyncio.shield(self.done), DEADLINE_S)
        assert self.answers == [answer], self.answers
        return answer


def ask(forwarder: PeerForwarder, slave: int, pdu: bytes, master: Master, line: str = "a") -> Asked:
    asked = Asked(slave, pdu, master)
    assert forwarder.submit(line, asked.request)
    return asked


async def until(condition: Callable[[], bool], what: str) -> None:
    """Let the loop run until ``condition`` holds (a state the code reaches by itself)."""
    deadline = asyncio.get_running_loop().time() + DEADLINE_S
    while not condition():
        assert asyncio.get_running_loop().time() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.002)


def forwarder_to(address: tuple[str, int], timeout: float = 2.0, **options: Any) -> PeerForwarder:
    forwarder = PeerForwarder(
        address[0], address[1], {("a", 1): 1, ("a", 2): 2}, asyncio.get_running_loop(),
        timeout=timeout, **options,
    )  # fmt: skip
    forwarder.peer_active = True
    return forwarder


async def shut(forwarder: PeerForwarder) -> None:
    """Close every connection and let the loop release the sockets."""
    forwarder.close()
    await asyncio.sleep(0)
    await asyncio.sleep(0)


def run(scenario: Callable[[], Coroutine[Any, Any, None]]) -> None:
    asyncio.run(scenario())


def peer_connections(gw: RunningGateway) -> int:
    """Masters connected to the peer's listener, read on its loop."""
    return gw.call(lambda: sum(server.connections for server in gw.gateway.servers))


# --------------------------------------------------------------------------- a real peer


def test_reads_and_writes_reach_the_active_peer(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1), 2: plc(2)})
    sim.device(2).holding[100] = 0xBEEF

    async def scenario() -> None:
        forwarder = forwarder_to(gw.address)
        master = Master("m")
        try:
            expected = registers(list(sim.device(1).holding.read(0, 6)))
            assert await ask(forwarder, 1, READ_6, master).answer() == (expected, Outcome.OK)
            assert await ask(forwarder, 2, READ_1, master).answer() == (
                registers([0xBEEF]), Outcome.OK)  # fmt: skip
            write = struct.pack(">BHH", 6, 100, 0x1234)
            assert await ask(forwarder, 2, write, master).answer() == (write, Outcome.OK)
            assert sim.device(2).holding[100] == 0x1234
            # A slave the routes do not reach on this line: 0x0A, nothing sent.
            assert await ask(forwarder, 9, READ_1, master).answer() == (
                UNAVAILABLE, Outcome.NO_ROUTE)  # fmt: skip
            stats = forwarder.stats
            assert (stats.forwarded, stats.answered, stats.unavailable) == (3, 3, 1)
            assert stats.latency_sum > 0 and len(stats.recent) == 3
        finally:
            await shut(forwarder)

    run(scenario)


def test_each_master_has_its_own_connection_and_cancel_closes_only_its_own(
    gateway_with: GatewayOnSim,
) -> None:
    sim, gw = gateway_with({1: plc(1)})
    expected = registers(list(sim.device(1).holding.read(0, 6)))

    async def scenario() -> None:
        forwarder = forwarder_to(gw.address)
        one, two = Master("one"), Master("two")
        try:
            answers = await asyncio.gather(
                ask(forwarder, 1, READ_6, one).answer(), ask(forwarder, 1, READ_6, two).answer()
            )
            assert list(answers) == [(expected, Outcome.OK)] * 2
            assert forwarder.connections == 2
            assert peer_connections(gw) == 2  # the active's fair queue sees two masters
            forwarder.cancel(one)
            assert forwarder.connections == 1
            await until(lambda: peer_connections(gw) == 1, "the peer to see one connection")
            assert await ask(forwarder, 1, READ_6, two).answer() == (expected, Outcome.OK)
            assert peer_connections(gw) == 1  # the other master's connection was kept
        finally:
            await shut(forwarder)

    run(scenario)


def test_many_requests_in_flight_each_get_their_own_answer(gateway_with: GatewayOnSim) -> None:
    """Three masters, 20 reads each in flight at once, each of its own register: every
    answer is the value of the register its request asked for."""
    sim, gw = gateway_with({1: plc(1)})
    holding = sim.device(1).holding
    for address in range(60):
        holding[3000 + address] = 0x5000 + address

    async def scenario() -> None:
        forwarder = forwarder_to(gw.address)
        masters = [Master(f"m{n}") for n in range(3)]
        try:
            asked = {
                address: ask(forwarder, 1, struct.pack(">BHH", 3, 3000 + address, 1),
                             masters[address % 3])
                for address in range(60)
            }  # fmt: skip
            for address, request in asked.items():
                assert await request.answer() == (registers([0x5000 + address]), Outcome.OK)
            assert forwarder.connections == 3 and forwarder.stats.answered == 60
        finally:
            await shut(forwarder)

    run(scenario)


def test_a_peer_that_is_not_active_gets_nothing(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)})

    async def scenario() -> None:
        forwarder = forwarder_to(gw.address)
        forwarder.peer_active = False  # the peer is standby too: never forward to it
        try:
            assert await ask(forwarder, 1, READ_6, Master("m")).answer() == (
                UNAVAILABLE, Outcome.NO_ROUTE)  # fmt: skip
            assert forwarder.connections == 0 and forwarder.stats.forwarded == 0
            assert peer_connections(gw) == 0
        finally:
            await shut(forwarder)

    run(scenario)


def test_a_stopped_peer_listener_answers_0x0a(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)})
    expected = registers(list(sim.device(1).holding.read(0, 6)))

    async def scenario() -> None:
        forwarder = forwarder_to(gw.address)
        master = Master("m")
        try:
            assert await ask(forwarder, 1, READ_6, master).answer() == (expected, Outcome.OK)
            await asyncio.get_running_loop().run_in_executor(None, gw.stop)
            # Lost connection or refused reconnection: 0x0A either way; then the back-off.
            for _ in range(3):
                assert await ask(forwarder, 1, READ_6, master).answer() == (
                    UNAVAILABLE, Outcome.NO_ROUTE)  # fmt: skip
            assert forwarder.connections == 0
            assert forwarder.stats.unavailable == 3 and forwarder.stats.answered == 1
        finally:
            await shut(forwarder)

    run(scenario)


def test_a_broadcast_is_forwarded_once_for_every_line_that_takes_it(
    gateway_with: GatewayOnSim,
) -> None:
    sim, gw = gateway_with({1: plc(1), 2: plc(2)})

    async def scenario() -> None:
        forwarder = forwarder_to(gw.address)
        master = Master("m")
        write = struct.pack(">BHH", 6, 100, 0x0042)
        try:
            first = Asked(0, write, master, broadcast=True)
            copy = LineRequest(0, write, master, first.request.reply, broadcast=True)
            assert forwarder.submit("a", first.request)  # one request per broadcast line,
            assert forwarder.submit("b", copy)  # sharing one reply: as the TCP side does
            await until(lambda: len(first.answers) == 2, "both copies' answers")
            assert first.answers == [(b"", Outcome.BROADCAST)] * 2
            assert forwarder.stats.forwarded == 1
            # Read after write, on the same connection: the peer keeps the master's order.
            assert await ask(forwarder, 1, READ_1, master).answer() == (
                registers([0x0042]), Outcome.OK)  # fmt: skip
            assert sim.device(2).holding[100] == 0x0042
        finally:
            await shut(forwarder)

    run(scenario)


# --------------------------------------------------------------------------- a fake peer


class FakePeer:
    """A Modbus TCP server that answers as ``respond`` says: ``respond(tid, unit, pdu)``
    returns the frames to send (raw bytes), after awaiting whatever it likes."""

    def __init__(self, respond: Callable[[int, int, bytes], Awaitable[list[bytes]]]) -> None:
        self.respond = respond
        self.accepted = 0
        self.ended = 0  #: connections the forwarder closed (EOF or reset seen)
        self._server: asyncio.Server | None = None

    async def start(self) -> tuple[str, int]:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        host, port = self._server.sockets[0].getsockname()[:2]
        return host, port

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Read requests until the forwarder closes; answer each in its own task, so that
        a held answer does not stop the reading (and EOF is seen)."""
        self.accepted += 1
        answering: set[asyncio.Task[None]] = set()
        try:
            while True:
                header = await reader.readexactly(7)
                tid, _protocol, length, unit = struct.unpack(">HHHB", header)
                pdu = await reader.readexactly(length - 1)
                task = asyncio.ensure_future(self._answer(writer, tid, unit, pdu))
                answering.add(task)
                task.add_done_callback(answering.discard)
        except (asyncio.IncompleteReadError, ConnectionError):
            self.ended += 1
        finally:
            for task in list(answering):
                task.cancel()
            writer.close()

    async def _answer(self, writer: asyncio.StreamWriter, tid: int, unit: int, pdu: bytes) -> None:
        try:
            for frame in await self.respond(tid, unit, pdu):
                writer.write(frame)
        except ConnectionError:  # the peer goes away
            writer.transport.abort()


HOSTILE = {
    "another transaction id": lambda tid, unit: mbap(tid + 1, unit, registers([7])),
    "another unit": lambda tid, unit: mbap(tid, unit + 1, registers([7])),
    "another function": lambda tid, unit: mbap(tid, unit, bytes((4, 2, 0, 7))),
    "another byte count": lambda tid, unit: mbap(tid, unit, registers([7, 8])),
    "a protocol id not 0": lambda tid, unit: mbap(tid, unit, registers([7]), protocol_id=1),
}


@pytest.mark.parametrize("answer", list(HOSTILE), ids=list(HOSTILE))
def test_an_answer_that_answers_nothing_pending_never_reaches_a_master(answer: str) -> None:
    async def scenario() -> None:
        async def respond(tid: int, unit: int, _pdu: bytes) -> list[bytes]:
            return [HOSTILE[answer](tid, unit)]

        peer = FakePeer(respond)
        forwarder = forwarder_to(await peer.start())
        try:
            assert await ask(forwarder, 1, READ_1, Master("m")).answer() == (
                FAILED, Outcome.TARGET_FAILED)  # fmt: skip
            assert forwarder.stats.discarded == 1 and forwarder.stats.answered == 0
            await until(lambda: peer.ended == 1, "the untrusted connection to close")
            assert forwarder.connections == 0
        finally:
            await shut(forwarder)
            await peer.stop()

    run(scenario)


def test_a_timeout_answers_0x0b_and_the_late_answer_is_dropped() -> None:
    async def scenario() -> None:
        release = asyncio.Event()

        async def respond(tid: int, unit: int, pdu: bytes) -> list[bytes]:
            if pdu == READ_1:  # the slow one: answered only once released
                await release.wait()
                return [mbap(tid, unit, registers([0x1111]))]
            return [mbap(tid, unit, registers([0x2222]))]

        peer = FakePeer(respond)
        forwarder = forwarder_to(await peer.start(), timeout=0.2)
        master = Master("m")
        try:
            assert await ask(forwarder, 1, READ_1, master).answer() == (
                FAILED, Outcome.TARGET_FAILED)  # fmt: skip
            release.set()  # the late answer goes out before the next one
            other = struct.pack(">BHH", 3, 200, 1)  # same function and length
            assert await ask(forwarder, 1, other, master).answer() == (
                registers([0x2222]), Outcome.OK)  # fmt: skip
            stats = forwarder.stats
            assert (stats.failed, stats.late, stats.discarded, stats.answered) == (1, 1, 0, 1)
            assert peer.accepted == 1 and forwarder.connections == 1  # the stream stays
        finally:
            await shut(forwarder)
            await peer.stop()

    run(scenario)


def test_cancel_drops_only_its_masters_requests_and_bounds_hold() -> None:
    async def scenario() -> None:
        release = asyncio.Event()

        async def respond(tid: int, unit: int, _pdu: bytes) -> list[bytes]:
            await release.wait()
            return [mbap(tid, unit, registers([5]))]

        peer = FakePeer(respond)
        forwarder = forwarder_to(await peer.start(), max_pending=2)
        one, two = Master("one"), Master("two")
        try:
            gone = [ask(forwarder, 1, READ_1, one) for _ in range(2)]
            kept = [ask(forwarder, 1, READ_1, two) for _ in range(2)]
            assert await ask(forwarder, 1, READ_1, two).answer() == (
                bytes((0x83, 0x06)), Outcome.BUSY)  # fmt: skip
            await until(lambda: peer.accepted == 2, "both connections")
            forwarder.cancel(one)
            for asked in gone:
                assert await asked.answer() == (b"", Outcome.DROPPED)
            await until(lambda: peer.ended == 1, "the cancelled master's connection to close")
            release.set()
            for asked in kept:
                assert await asked.answer() == (registers([5]), Outcome.OK)
            assert forwarder.connections == 1
        finally:
            await shut(forwarder)
            await peer.stop()

    run(scenario)


def test_a_lost_connection_answers_what_is_pending_0x0a() -> None:
    async def scenario() -> None:
        async def respond(_tid: int, _unit: int, _pdu: bytes) -> list[bytes]:
            raise ConnectionResetError  # the peer goes away with the request unanswered

        peer = FakePeer(respond)
        forwarder = forwarder_to(await peer.start())
        try:
            assert await ask(forwarder, 1, READ_1, Master("m")).answer() == (
                UNAVAILABLE, Outcome.NO_ROUTE)  # fmt: skip
            assert forwarder.connections == 0
        finally:
            await shut(forwarder)
            await peer.stop()

    run(scenario)


def test_an_unreachable_peer_answers_0x0a_without_waiting() -> None:
    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        address = probe.getsockname()

    async def scenario() -> None:
        forwarder = forwarder_to(address)
        try:
            for _ in range(2):  # refused, then within the back-off
                assert await ask(forwarder, 1, READ_1, Master("m")).answer() == (
                    UNAVAILABLE, Outcome.NO_ROUTE)  # fmt: skip
            assert forwarder.connections == 0 and forwarder.stats.unavailable == 2
        finally:
            await shut(forwarder)

    run(scenario)


class Connection(Master):
    """A master connection as the listener gives it: with its source address."""

    def __init__(self, name: str, source: str) -> None:
        super().__init__(name)
        self.source = source


def test_the_masters_of_one_address_share_a_link_and_take_turns_on_it() -> None:
    """Two connections of one host take one link to the peer, one request each per round
    through its window; one that leaves has its requests dropped (an answer on its way is
    dropped, not delivered) and the other keeps the link."""

    async def scenario() -> None:
        release = asyncio.Event()
        order: list[int] = []

        async def respond(tid: int, unit: int, pdu: bytes) -> list[bytes]:
            order.append(struct.unpack(">H", pdu[1:3])[0])
            await release.wait()
            return [mbap(tid, unit, registers([5]))]

        peer = FakePeer(respond)
        forwarder = forwarder_to(await peer.start(), window=2)
        busy, quiet = Connection("busy", "127.0.0.5"), Connection("quiet", "127.0.0.5")
        try:
            gone = [ask(forwarder, 1, struct.pack(">BHH", 3, n, 1), busy) for n in range(4)]
            kept = ask(forwarder, 1, struct.pack(">BHH", 3, 9, 1), quiet)
            await until(lambda: len(order) == 2, "the window's two requests")
            assert forwarder.connections == 1 and peer.accepted == 1
            assert order == [0, 9]  # one of each master in the window, not the busy one's two
            forwarder.cancel(busy)
            for asked in gone:
                assert await asked.answer() == (b"", Outcome.DROPPED)
            release.set()
            assert await kept.answer() == (registers([5]), Outcome.OK)
            # The answer to the departed master's request came first (the peer answers in
            # order) and was dropped, neither counted late nor distrusted; its waiting
            # requests never went.
            assert order == [0, 9] and forwarder.connections == 1
            assert (forwarder.stats.late, forwarder.stats.discarded) == (0, 0)
            forwarder.cancel(quiet)  # the last master of the link: it closes
            await until(lambda: peer.ended == 1, "the link to close")
            assert forwarder.connections == 0
        finally:
            await shut(forwarder)
            await peer.stop()

    run(scenario)


def test_turns_on_a_shared_link_go_round_the_masters() -> None:
    async def scenario() -> None:
        order: list[str] = []

        async def respond(tid: int, unit: int, pdu: bytes) -> list[bytes]:
            order.append("ab"[struct.unpack(">H", pdu[1:3])[0] // 100])
            return [mbap(tid, unit, registers([5]))]

        peer = FakePeer(respond)
        forwarder = forwarder_to(await peer.start(), window=1)
        a, b = Connection("a", "127.0.0.5"), Connection("b", "127.0.0.5")
        try:
            asked = [ask(forwarder, 1, struct.pack(">BHH", 3, n, 1), a) for n in range(6)]
            asked += [ask(forwarder, 1, struct.pack(">BHH", 3, 100 + n, 1), b) for n in range(2)]
            for request in asked:
                assert (await request.answer())[1] is Outcome.OK
            assert "".join(order) == "ababaaaa"  # one each per round, while both wait
        finally:
            await shut(forwarder)
            await peer.stop()

    run(scenario)
