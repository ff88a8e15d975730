"""Hostile masters over loopback, each beside an honest master whose service must stay bounded.

Every attack is bounded in count and in time (``ATTACK_S`` at most), runs from
its own source address (127.0.0.2; the honest masters use 127.0.0.1 and
127.0.0.3), and is judged by what the honest master got: every poll answered
correctly within ``HONEST_BOUND_S``. That bound is generous on purpose (the
machine runs other work); the latency figures themselves are measured by
``python -m bench --scenario hostile``. Memory and descriptors of the gateway
process are checked in ``tests/e2e/test_hostile_process.py``.
"""

from __future__ import annotations

import asyncio
import logging
import re
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress

import pytest
from prometheus_client.parser import text_string_to_metric_families

from gateway.sim import plc
from tests.helpers import (
    DEADLINE_S,
    ConnectionClosedError,
    GatewayFactory,
    GatewayOnSim,
    LogCollector,
    RunningGateway,
    SimFactory,
    mbap,
    wait_until,
)
from tests.integration.metrics_harness import exposition, http_get, metrics_address, series, value

READ_1 = bytes.fromhex("03 0000 0001")
#: How long an attack runs at most.
ATTACK_S = 2.0
#: The honest master's bound: every poll answered within this, whatever the attacker does.
HONEST_BOUND_S = 0.5
#: The line under the honest master: the simulated slave is a thread of this process, which
#: a busy machine (and the attackers' own threads) can delay past the default timeout
#: (~0.12 s at the test line's rate); a 0x0B then says nothing about the gateway. What the
#: gateway owes the honest master is bounded by ``HONEST_BOUND_S`` instead.
HONEST_LINE = {"timeout": 2.0}
ATTACKER = "127.0.0.2"
OTHER_HONEST = "127.0.0.3"
MINIMUM_POLLS = 10


def connect_from(source: str, address: tuple[str, int]) -> socket.socket:
    """A TCP connection to ``address`` from the loopback address ``source``."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind((source, 0))
    sock.settimeout(DEADLINE_S)
    sock.connect(address)
    return sock


class HonestMaster:
    """Polls unit 1 in a thread, one request at a time, and records each round trip."""

    def __init__(self, gw: RunningGateway) -> None:
        self._gw = gw
        self.latencies: list[float] = []
        self.errors: list[BaseException] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        try:
            with self._gw.connect() as master:
                while not self._stop.is_set():
                    started = time.monotonic()
                    reply = master.request(1, READ_1)
                    self.latencies.append(time.monotonic() - started)
                    assert reply[0] == 0x03, reply
        except BaseException as error:  # reported by check()
            self.errors.append(error)

    def __enter__(self) -> HonestMaster:
        self._thread.start()
        wait_until(lambda: len(self.latencies) >= 3 or bool(self.errors), "honest polls")
        return self

    def __exit__(self, *_exc: object) -> None:
        try:  # a short attack still sees MINIMUM_POLLS polls, some after it
            wait_until(lambda: len(self.latencies) >= MINIMUM_POLLS or bool(self.errors), "polls")
        finally:
            self._stop.set()
            self._thread.join(DEADLINE_S)

    def check(self, minimum: int = MINIMUM_POLLS) -> None:
        """Every poll answered, correctly, within the bound."""
        assert not self.errors, self.errors
        assert len(self.latencies) >= minimum, f"only {len(self.latencies)} polls answered"
        worst = max(self.latencies)
        assert worst <= HONEST_BOUND_S, f"an honest poll took {worst:.3f} s"


def until(seconds: float) -> Iterator[None]:
    """Iterate until ``seconds`` have passed (bounds an attack loop)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        yield


def flood_payload(unit: int, count: int = 4096) -> bytes:
    """``count`` pipelined requests the gateway answers itself (``unit`` has no route)."""
    return b"".join(mbap(tid & 0xFFFF, unit, READ_1) for tid in range(count))


def closed_reason(gw: RunningGateway, reason: str) -> float:
    return value(gw, series("modbus_gateway_connections_closed_total", reason=reason))


# --------------------------------------------------------------------------- floods


def test_unread_flood_is_throttled_then_closed_and_the_honest_master_is_served(
    gateway_with: GatewayOnSim,
) -> None:
    _sim, gw = gateway_with({1: plc(1)}, line=HONEST_LINE, server={"send_timeout": 1.0})
    payload = flood_payload(99)
    attacker = connect_from(ATTACKER, gw.address)
    attacker.setblocking(False)
    sent = 0
    try:
        with HonestMaster(gw) as honest:
            for _ in until(ATTACK_S + 2.0):  # the gateway closes it after ~1 s of unread replies
                try:
                    sent += attacker.send(payload)
                except BlockingIOError:
                    select.select([], [attacker], [], 0.05)
                except (ConnectionResetError, BrokenPipeError):
                    break
            else:
                pytest.fail("the gateway kept a master that reads none of its replies")
        honest.check()
    finally:
        attacker.close()
    assert closed_reason(gw, "stalled") == 1
    # The gateway stopped reading: what it took is bounded by the socket buffers, not the
    # attacker's persistence (~4 million requests at the rate of an unthrottled loop).
    assert sent < 64 * 1024 * 1024


def test_flood_that_reads_its_replies_does_not_starve_the_honest_master(
    gateway_with: GatewayOnSim,
) -> None:
    _sim, gw = gateway_with({1: plc(1)}, line=HONEST_LINE)
    payload = flood_payload(99, 512) + mbap(1, 0, bytes((0x03, 0, 0, 0, 200)))  # + an invalid one
    attacker = connect_from(ATTACKER, gw.address)
    replies = 0
    stop = threading.Event()
    failures: list[OSError] = []

    def read_replies() -> None:
        nonlocal replies
        with attacker.makefile("rb") as stream:
            while not stop.is_set():
                try:
                    header = stream.read(7)
                    if len(header) < 7:
                        return
                    stream.read(struct.unpack(">H", header[4:6])[0] - 1)
                except OSError as error:
                    # The attacker's own teardown: its end shut with requests the gateway
                    # has not read, the gateway's close resets the connection.
                    if not stop.is_set():
                        failures.append(error)
                    return
                replies += 1

    reader = threading.Thread(target=read_replies, daemon=True)
    reader.start()
    try:
        with HonestMaster(gw) as honest:
            started = time.monotonic()
            for _ in until(DEADLINE_S):  # ATTACK_S, longer only if the machine is too busy
                attacker.sendall(payload)  # to serve the attacker its 1000 replies meanwhile
                if time.monotonic() - started >= ATTACK_S and replies > 1000:
                    break
        honest.check()
    finally:
        stop.set()
        attacker.shutdown(socket.SHUT_RDWR)
        attacker.close()
        reader.join(DEADLINE_S)
    assert failures == []  # the gateway never closed a master that reads its replies
    assert replies > 1000  # the attacker was served too, just not before everyone else


def test_connections_closed_for_bad_framing_release_their_unsent_replies(
    gateway_with: GatewayOnSim,
) -> None:
    _sim, gw = gateway_with({1: plc(1)}, line=HONEST_LINE)
    # Requests answered locally, unread replies, then a header no Modbus peer sends.
    payload = flood_payload(99, 2000) + mbap(1, 1, READ_1, protocol_id=7)
    attackers = [connect_from(ATTACKER, gw.address) for _ in range(3)]
    try:
        with HonestMaster(gw) as honest:
            for attacker in attackers:
                attacker.sendall(payload)
            wait_until(
                lambda: closed_reason(gw, "protocol_error") == 3, "3 connections closed for framing"
            )
            # Closed (aborted) while the attackers still hold their ends open and read nothing.
            assert gw.call(lambda: _open_connections(gw)) == 1
        honest.check()
    finally:
        for attacker in attackers:
            attacker.close()


# --------------------------------------------------------------------------- admission


def test_connection_bursts_do_not_cost_honest_masters_their_service(
    gateway_with: GatewayOnSim,
) -> None:
    limit = 20
    _sim, gw = gateway_with(
        {1: plc(1)},
        line=HONEST_LINE,
        server={"max_connections": limit, "max_connections_per_source": 10},
    )
    stop = threading.Event()
    per_poll_ok: list[bool] = []

    def per_poll_master() -> None:  # connects, polls once, disconnects, like some SCADA drivers
        while not stop.is_set():
            try:
                with connect_from(OTHER_HONEST, gw.address) as sock:
                    sock.sendall(mbap(7, 1, READ_1))
                    per_poll_ok.append(sock.recv(64)[7:8] == b"\x03")
            except OSError:
                per_poll_ok.append(False)

    other = threading.Thread(target=per_poll_master, daemon=True)
    try:
        with HonestMaster(gw) as honest:
            other.start()
            for _ in range(4):  # bursts of more than the whole limit, every 0.5 s
                burst = []
                for _ in range(limit + 10):
                    with suppress(OSError):
                        burst.append(connect_from(ATTACKER, gw.address))
                # Everything past its address's limit is refused; the rest is held 0.5 s.
                assert closed_within(burst, 20, 0.5) >= 20
                for sock in burst:
                    sock.close()
        honest.check()
    finally:
        stop.set()
        other.join(DEADLINE_S)
    assert per_poll_ok and sum(per_poll_ok) / len(per_poll_ok) >= 0.9, per_poll_ok.count(False)
    assert value(gw, series("modbus_gateway_connections_closed_total", reason="evicted")) == 0
    refused = series("modbus_gateway_connections_rejected_total", reason="max_per_source")
    assert value(gw, refused) >= 80


def closed_within(socks: list[socket.socket], expected: int, hold: float) -> int:
    """How many of ``socks`` the gateway closed, waiting (bounded) until ``expected`` are.

    The rest are held open until ``hold`` seconds have passed: the burst's pressure. The
    wait for the closes is not ``hold``: a busy machine may take longer to refuse them.
    """
    closed: set[socket.socket] = set()
    started = time.monotonic()
    deadline = started + DEADLINE_S
    while len(closed) < expected and (left := deadline - time.monotonic()) > 0:
        readable, _, _ = select.select([s for s in socks if s not in closed], [], [], left)
        closed.update(s for s in readable if _wait_closed(s, 0.0))
    select.select([], [], [], max(0.0, started + hold - time.monotonic()))  # the hold
    return len(closed)


def _wait_closed(sock: socket.socket, timeout: float) -> bool:
    """True when the gateway closes ``sock`` (EOF or reset) within ``timeout``; bounded wait."""
    sock.settimeout(timeout)
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def test_eviction_takes_only_masters_idle_long_enough_and_never_busy_ones(
    gateway_with: GatewayOnSim,
) -> None:
    sim, gw = gateway_with(
        {1: plc(1), 2: plc(2)},
        server={"max_connections": 2, "evict_min_idle": 0.3, "max_connections_per_source": 0},
        line={"timeout": 1.5, "retries": 0, "dead_after": 0},
    )
    sim.faults(2).silent = True
    with gw.connect() as busy, gw.connect() as idle:
        assert idle.request(1, READ_1)[0] == 0x03
        became_idle = time.monotonic()
        tid = busy.send(2, READ_1)  # in flight for 1.5 s: never evicted
        with gw.connect() as newcomer:  # idle has been idle < 0.3 s: refused, nobody evicted
            assert newcomer.is_closed_by_peer(DEADLINE_S)
        admitted_at = None
        for _ in until(DEADLINE_S):
            with gw.connect() as newcomer:
                # Admitted or refused is told by what comes back (a reply, or the close),
                # never by how soon: a busy machine may take long to refuse.
                try:
                    tid = newcomer.send(1, READ_1)
                    reply = newcomer.receive(timeout=DEADLINE_S)
                except (ConnectionClosedError, ConnectionError):
                    continue  # refused: idle has not been idle long enough yet
                admitted_at = time.monotonic()
                assert (reply.transaction_id, reply.pdu[0]) == (tid, 0x03)
                break
        assert admitted_at is not None and admitted_at - became_idle >= 0.3
        assert idle.is_closed_by_peer(DEADLINE_S)  # the idle one made room
        reply = busy.receive(timeout=DEADLINE_S)  # the busy one kept its connection
        assert (reply.transaction_id, reply.pdu) == (tid, bytes((0x83, 0x0B)))
    assert closed_reason(gw, "evicted") == 1


def test_stray_bytes_do_not_keep_a_slot_only_complete_requests_do(
    gateway_with: GatewayOnSim,
) -> None:
    _sim, gw = gateway_with({1: plc(1)}, server={"idle_timeout": 0.5})
    with gw.connect() as trickler, gw.connect() as poller:
        header = mbap(1, 1, READ_1)
        started = time.monotonic()
        for index in range(len(header) - 1):  # never a whole request
            trickler.send_raw(header[index : index + 1])
            assert poller.request(1, READ_1)[0] == 0x03  # complete requests: kept
            if trickler.is_closed_by_peer(0.1):
                break
        else:
            assert trickler.is_closed_by_peer(DEADLINE_S)
        assert time.monotonic() - started < 0.5 + 1.0  # the bytes did not extend its time
        assert poller.request(1, READ_1)[0] == 0x03
    assert closed_reason(gw, "idle") >= 1


# --------------------------------------------------------------------------- logs


@contextmanager
def collected_logs(level: int) -> Iterator[LogCollector]:
    collector = LogCollector()
    logger = logging.getLogger("gateway")
    previous = logger.level
    logger.setLevel(level)
    logger.addHandler(collector)
    try:
        yield collector
    finally:
        logger.removeHandler(collector)
        logger.setLevel(previous)


def test_one_client_cannot_flood_the_log(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with(
        {1: plc(1)},
        line=HONEST_LINE,
        server={"max_connections": 10, "max_connections_per_source": 5},
    )
    attacks: list[Callable[[], None]] = []

    def bad_header() -> None:
        with connect_from(ATTACKER, gw.address) as sock:
            sock.sendall(mbap(1, 1, READ_1, protocol_id=3))
            _wait_closed(sock, DEADLINE_S)

    def reset_at_once() -> None:
        sock = connect_from(ATTACKER, gw.address)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()

    def bad_length() -> None:
        with connect_from(ATTACKER, gw.address) as sock:
            sock.sendall(b"\x00\x01\x00\x00\x04\x00\x01")
            _wait_closed(sock, DEADLINE_S)

    attacks = [bad_header, reset_at_once, bad_length]
    with collected_logs(logging.DEBUG) as logs, HonestMaster(gw) as honest:
        count = 0
        for _ in until(ATTACK_S):
            for attack in attacks:
                attack()
                count += 1
            held = [connect_from(ATTACKER, gw.address) for _ in range(8)]  # past both limits
            for sock in held:
                sock.close()
        # (An honest master that failed has left too: its error is what check() reports.)
        wait_until(lambda: gw.call(lambda: _open_connections(gw)) == 1 or bool(honest.errors),
                   "attackers gone")  # fmt: skip
    honest.check()
    assert count >= 30
    loud = [r for r in logs.records if r.levelno >= logging.INFO and r.name == "gateway.tcp"]
    assert len(loud) <= 6, [r.getMessage() for r in loud]  # one first line per kind of fault
    # Every line about a connection names its peer as accept() gave it, never "None".
    about = [r.getMessage() for r in logs.records if r.getMessage().startswith("master ")]
    assert about and all(m.startswith(("master 127.0.0.", "master [")) for m in about), about
    assert any("127.0.0.2" in r.getMessage() for r in loud)


def _open_connections(gw: RunningGateway) -> int:
    server = gw.gateway.server
    return server.connections if server is not None else -1


def test_connection_events_are_summarised_once_per_interval(gateway_with: GatewayOnSim) -> None:
    _sim, gw = gateway_with({1: plc(1)})
    server = gw.gateway.server
    assert server is not None
    interval = 0.3
    gw.call(lambda: setattr(server.events, "interval", interval))

    def summaries() -> list[str]:
        return [m for m in logs.messages if "connections in the last" in m]

    def opened() -> int:
        found = (re.search(r"(\d+) opened", summary) for summary in summaries())
        return sum(int(match[1]) for match in found if match)

    with collected_logs(logging.INFO) as logs:
        started = time.monotonic()
        for _ in range(20):
            with connect_from(ATTACKER, gw.address) as sock:
                sock.sendall(mbap(1, 1, READ_1))
                sock.recv(64)
        # One line per interval: the 20 connections take one interval on an idle machine,
        # more when it is busy; every one is counted either way.
        wait_until(lambda: opened() >= 20, "the summaries of 20 connections")
        intervals = (time.monotonic() - started) / interval
    assert opened() == 20, summaries()
    assert len(summaries()) <= intervals + 1, summaries()
    assert all("most from 127.0.0.2" in summary for summary in summaries()), summaries()


# --------------------------------------------------------------------------- metrics


def test_scanning_every_unit_and_function_keeps_the_exposition_bounded(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    table = sim.line_table(  # every address routed, as with --serial; only unit 1 exists
        ["1-247"], timeout=0.005, retries=0, dead_after=1, probe_interval=60.0,
        slave_timeouts={"1": 1.0},
    )  # fmt: skip
    gw = make_gateway({"lines": {"a": table}, "server": {"max_pipeline": 64}})
    functions = [*range(1, 25), 43, 65, 100, 127]
    with gw.connect() as master:
        assert master.request(1, READ_1)[0] == 0x03
        before = exposition(gw)
        for unit in range(1, 256):
            for function in functions:
                master.send(unit, bytes((function, 0, 0, 0, 1)))
            for _ in functions:
                master.receive(timeout=DEADLINE_S)
        after = exposition(gw)
    assert "_created" not in before + after
    assert len(after) <= 1.5 * len(before), (len(before), len(after))
    units = {
        sample.labels["unit"]
        for family in text_string_to_metric_families(after)
        if family.name == "modbus_gateway_requests"
        for sample in family.samples
    }
    assert units == {"1", "other"}  # the slave that answered, and everything else


# --------------------------------------------------------------------------- HTTP


def test_idle_http_connections_cannot_lock_out_scrapes_or_masters(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    gw = make_gateway(
        {
            "lines": {"a": sim.line_table([1])},
            "metrics": {"listen": "127.0.0.1:0", "max_connections": 8, "header_timeout": 0.5},
        }
    )
    idle = [connect_from(ATTACKER, metrics_address(gw)) for _ in range(40)]
    try:
        status, _, body = http_get(gw, "/metrics")  # makes room: the idle ones sent nothing
        assert status == 200 and b"modbus_gateway_requests_total" in body
        with gw.connect() as master:
            assert master.request(1, READ_1)[0] == 0x03
        endpoint = gw.gateway._http
        assert endpoint is not None
        assert gw.call(lambda: endpoint.connections) <= 8
        # The header timeout closes those that were let in and still say nothing.
        assert all(_wait_closed(sock, DEADLINE_S) for sock in idle)
    finally:
        for sock in idle:
            sock.close()


def test_a_noisy_line_is_live_and_ready(gateway_with: GatewayOnSim) -> None:
    # Every answer must come back (damaged) within the timeout, not after it: a timeout far
    # above what a busy machine delays the simulator by (a damaged answer fails at once).
    sim, gw = gateway_with({1: plc(1)}, line={"timeout": 1.0, "retries": 0})
    sim.faults(1).crc_error_rate = 1.0  # every answer garbled: the line is open, but noisy
    with gw.connect() as master:
        for _ in range(5):
            assert master.request(1, READ_1) == bytes((0x83, 0x0B))
    assert http_get(gw, "/healthz")[0] == 200
    assert http_get(gw, "/readyz")[0] == 200  # its faults are in the metrics, not here
    crc = series("modbus_gateway_crc_errors_total", line="a", unit="1")
    assert value(gw, crc) >= 5


def test_a_streaming_route_outlives_the_header_timeout(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    gw = make_gateway(
        {
            "lines": {"a": sim.line_table([1])},
            "metrics": {"listen": "127.0.0.1:0", "header_timeout": 0.2},
        }
    )
    endpoint = gw.gateway._http
    assert endpoint is not None
    ticks = 6

    async def stream(
        _method: str, _target: str, _headers: Mapping[str, str],
        _reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
    ) -> None:  # fmt: skip
        writer.write(b"HTTP/1.1 200 OK\r\nContent-Type: text/plain\r\n\r\n")
        for tick in range(ticks):
            writer.write(f"tick {tick}\n".encode())
            await writer.drain()
            await asyncio.sleep(0.1)  # a stream paced by its source, not a synchronisation
        writer.close()

    gw.call(lambda: endpoint.add_route("/stream", stream))
    with socket.create_connection(metrics_address(gw), timeout=DEADLINE_S) as sock:
        sock.sendall(b"GET /stream HTTP/1.1\r\n\r\n")
        received = b""
        while chunk := sock.recv(4096):
            received += chunk
    assert received.count(b"tick ") == ticks
