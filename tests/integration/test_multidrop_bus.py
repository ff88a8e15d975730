"""The simulated multi-drop RS-485 bus: every node hears the others, paced, and overlaps collide.

The bus on real ptys (nodes opened by path, as a gateway opens an adapter), and its
clockless core, ``BusTimeline``, on literal times (one character = 1 s there).
Synchronisation is by bytes arriving and by the bus's own counters, never by sleeping.
"""

from __future__ import annotations

import errno
import fcntl
import os
import select
import struct
import termios
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.config import build_config
from gateway.core.rtu import RtuFrame, RtuResponseDecoder, encode_rtu
from gateway.io.links.serial_port import open_serial
from gateway.sim import BusStats, BusTimeline, MultidropBus, plc
from tests.helpers import DEADLINE_S, GatewayFactory

BAUD = 9600
READ_10 = bytes.fromhex("03 0000 000A")
PLC_FIRST_10 = bytes.fromhex("03 14 0000 0002 0004 0006 0008 000A 0000 0000 0000 0000")
MARKER = b"\x7e"
TIOCGEXCL = 0x80045440  # Linux: is the tty held exclusively (not in the termios module)

Opener = Callable[[str], int]


@pytest.fixture
def bus() -> Iterator[MultidropBus]:
    """A running bus at 9600 baud, closed at teardown."""
    with MultidropBus(BAUD) as running:
        yield running


@pytest.fixture
def open_port() -> Iterator[Opener]:
    """Opens a node's path like an adapter (raw, non-blocking); closes every port at teardown."""
    fds: list[int] = []

    def opener(path: str) -> int:
        fds.append(os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK))
        return fds[-1]

    yield opener
    for fd in fds:
        os.close(fd)


def read_exactly(fd: int, count: int, timeout: float = DEADLINE_S) -> bytes:
    """The next ``count`` bytes from ``fd``; fails naming what came after ``timeout``."""
    deadline = time.monotonic() + timeout
    got = bytearray()
    while len(got) < count:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"got {bytes(got).hex()} of {count} bytes"
        readable, _, _ = select.select([fd], [], [], remaining)
        if readable:
            got += os.read(fd, count - len(got))
    return bytes(got)


def settled(stats: BusStats) -> bool:
    """Every byte written has been delivered."""
    return stats.in_flight == 0


# ---------------------------------------------------------------------- on real ptys


def test_a_node_is_heard_by_every_other_node_paced(bus: MultidropBus, open_port: Opener) -> None:
    a, b, c = (open_port(bus.node(name).path) for name in "abc")
    payload = bytes(range(100))
    written_at = time.monotonic()
    os.write(a, payload)
    assert read_exactly(b, 100) == payload
    took = time.monotonic() - written_at
    assert read_exactly(c, 100) == payload
    assert took >= 100 * bus.character_time  # ~104 ms at 9600 8N1: the wire, not the pty
    # The writer does not hear itself: the next thing it reads is another node's marker.
    os.write(b, MARKER)
    assert read_exactly(a, 1) == MARKER
    stats = bus.wait_for(settled, DEADLINE_S)
    assert stats.frames_written == {"a": 1, "b": 1, "c": 0}
    assert stats.bytes_written == {"a": 100, "b": 1, "c": 0}
    (frame,) = stats.frames_of("a")
    assert frame.data == payload
    assert frame.end - frame.start == pytest.approx(100 * bus.character_time)
    assert stats.collisions == 0 and stats.two_writer_s == 0


def test_a_node_added_with_echo_hears_itself(bus: MultidropBus, open_port: Opener) -> None:
    """A two-wire adapter without echo suppression reads back what it sends."""
    talker = open_port(bus.node("talker", echo=True).path)
    other = open_port(bus.node("other").path)
    os.write(talker, b"hello")
    assert read_exactly(talker, 5) == b"hello"
    assert read_exactly(other, 5) == b"hello"


def test_two_nodes_writing_at_once_collide(bus: MultidropBus, open_port: Opener) -> None:
    a, b, c = (open_port(bus.node(name).path) for name in "abc")
    os.write(a, b"\x55" * 100)  # each occupies the wire ~104 ms: the second write lands in it
    os.write(b, b"\xaa" * 100)
    heard = read_exactly(c, 200)
    stats = bus.wait_for(settled, DEADLINE_S)
    assert stats.collisions == 1
    (collision,) = stats.collision_log
    assert set(collision.nodes) == {"a", "b"}
    assert 0 < stats.two_writer_s <= 100 * bus.character_time
    assert collision.end - collision.start == pytest.approx(stats.two_writer_s, rel=0.02)
    # Receivers get the overlap damaged (0x55 | 0xAA), so neither frame arrives intact.
    assert heard.count(0xFF) >= 2
    assert b"\x55" * 100 not in heard and b"\xaa" * 100 not in heard
    assert 0xFF in read_exactly(a, 100)  # a writer hears the other's frame, damaged too


def test_writes_separated_by_a_gap_do_not_collide(bus: MultidropBus, open_port: Opener) -> None:
    a, b, c = (open_port(bus.node(name).path) for name in "abc")
    first, second = bytes(range(10)), bytes(range(10, 20))
    os.write(a, first)
    assert read_exactly(c, 10) == first  # delivered: a's last character has ended
    os.write(b, second)
    assert read_exactly(c, 10) == second
    stats = bus.wait_for(settled, DEADLINE_S)
    assert stats.collisions == 0 and stats.two_writer_s == 0
    (from_a,) = stats.frames_of("a")
    (from_b,) = stats.frames_of("b")
    assert from_b.start >= from_a.end


def test_a_gateway_reads_the_slaves_and_a_third_node_hears_both(
    bus: MultidropBus, open_port: Opener
) -> None:
    line = bus.attach_slaves({1: plc(1)})
    gateway_node = bus.node("gateway")
    ear = open_port(bus.node("ear").path)
    config = build_config({"lines": {"a": {"device": gateway_node.path, "baudrate": BAUD}}})
    port = open_serial(config.lines[0])
    try:
        request = encode_rtu(1, READ_10)
        sent_at = time.monotonic()
        port.write(request)
        answer = _read_answer(port.fileno(), port.read, RtuResponseDecoder(1, READ_10))
        took = time.monotonic() - sent_at
    finally:
        port.close()
    assert answer.pdu == PLC_FIRST_10
    assert read_exactly(ear, 8 + 25) == request + encode_rtu(1, PLC_FIRST_10)
    assert took >= (8 + 25) * bus.character_time + bus.t35
    stats = bus.wait_for(settled, DEADLINE_S)
    (asked,) = stats.frames_of("gateway")
    (answered,) = stats.frames_of("slaves")
    assert answered.start - asked.end >= bus.t35 - 1e-9  # the slave keeps t3.5 before answering
    assert stats.collisions == 0
    assert line.stats().requests == 1


def test_a_gateway_serves_a_master_through_the_bus(
    bus: MultidropBus, make_gateway: GatewayFactory, open_port: Opener
) -> None:
    """The gateway itself on a node (``bus`` is set up first, so it stops after the gateway)."""
    bus.attach_slaves({1: plc(1)})
    ear = open_port(bus.node("ear").path)
    node = bus.node("gateway")
    gw = make_gateway({"lines": {"a": {"device": node.path, "baudrate": BAUD, "units": [1]}}})
    with gw.connect() as master:
        assert master.request(1, READ_10) == PLC_FIRST_10
    assert read_exactly(ear, 8 + 25) == encode_rtu(1, READ_10) + encode_rtu(1, PLC_FIRST_10)
    stats = bus.wait_for(settled, DEADLINE_S)
    assert stats.frames_written["gateway"] == stats.frames_written["slaves"] == 1
    assert stats.collisions == 0


def _read_answer(fd: int, read: Callable[[int], bytes], decoder: RtuResponseDecoder) -> RtuFrame:
    deadline = time.monotonic() + DEADLINE_S
    while True:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"no answer, {decoder.buffered} bytes collected"
        readable, _, _ = select.select([fd], [], [], remaining)
        if readable:
            frame = decoder.feed(read(256))
            if frame is not None:
                return frame


def test_close_leaves_no_fd_open_and_no_thread_running() -> None:
    def open_fds() -> set[str]:
        return set(os.listdir("/proc/self/fd"))

    before = open_fds()
    bus = MultidropBus(BAUD)
    bus.start()
    nodes = [bus.node(name) for name in ("a", "b", "c")]
    bus.attach_slaves({1: plc(1)})
    fd = os.open(nodes[0].path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        os.write(fd, MARKER)
        bus.wait_for(lambda stats: stats.bytes_written["a"] == 1 and settled(stats), DEADLINE_S)
    finally:
        os.close(fd)
    bus.close()
    bus.close()  # twice is harmless
    assert open_fds() == before
    assert not [
        t for t in threading.enumerate() if t.name in ("multidrop-bus", "simulated-rtu-line")
    ]


def _held_exclusively(path: str) -> bool:
    """True when TIOCEXCL is set on the tty at ``path`` (an open as root bypasses it: ask)."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as error:
        if error.errno == errno.EBUSY:
            return True
        raise
    try:
        flag = fcntl.ioctl(fd, TIOCGEXCL, b"\0\0\0\0")
    finally:
        os.close(fd)
    return bool(struct.unpack("i", flag)[0])


def test_replug_undoes_what_a_killed_gateway_left_on_its_node(
    bus: MultidropBus, open_port: Opener
) -> None:
    """Exclusive open and unread bytes outlive a SIGKILLed gateway on a pty; replug clears both."""
    node = bus.node("gateway")
    other = open_port(bus.node("other").path)
    killed = os.open(node.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        fcntl.ioctl(killed, termios.TIOCEXCL)
        os.write(other, b"?")
        assert select.select([killed], [], [], DEADLINE_S)[0]  # queued, never read
    finally:
        os.close(killed)  # as the kernel does for a killed process: TIOCEXCL stays
    assert _held_exclusively(node.path)
    bus.replug("gateway")
    assert not _held_exclusively(node.path)
    restarted = open_port(node.path)
    os.write(other, MARKER)
    assert read_exactly(restarted, 1) == MARKER
    with pytest.raises(KeyError):
        bus.replug("nobody")


def test_the_slaves_line_is_paced_by_the_bus_not_by_itself() -> None:
    with MultidropBus(BAUD) as bus, pytest.raises(ValueError, match="baud rate"):
        bus.attach_slaves({1: plc(1)}, baudrate=BAUD)


# ---------------------------------------------------------------------- the core, literal times


def test_frames_are_runs_with_no_gap_over_one_and_a_half_characters() -> None:
    timeline = BusTimeline(1.0)
    a, b = timeline.add_node("a"), timeline.add_node("b")
    timeline.transmit(a, b"xy", now=0.0)
    assert timeline.next_due() == 1.0
    assert timeline.take_due(0.99) == {}
    assert timeline.take_due(1.0) == {b: b"x"}
    assert timeline.take_due(2.5) == {b: b"y"}
    timeline.transmit(a, b"z", now=3.5)  # 1.5 characters after "y" ended: the same frame
    timeline.transmit(a, b"w", now=6.1)  # 1.6 after "z": a new one
    assert timeline.take_due(10.0) == {b: b"zw"}
    stats = timeline.stats()
    assert [f.data for f in stats.frames] == [b"xyz", b"w"]
    assert [(f.start, f.end) for f in stats.frames] == [(0.0, 4.5), pytest.approx((6.1, 7.1))]
    assert stats.frames_written == {"a": 2, "b": 0} and stats.collisions == 0


def test_one_collision_per_overlapping_pair_of_frames() -> None:
    timeline = BusTimeline(1.0)
    a, b, c, ear = (timeline.add_node(name) for name in ("a", "b", "c", "ear"))
    timeline.transmit(a, b"\x01" * 4, now=0.0)  # [0, 4]
    timeline.transmit(b, b"\x02" * 4, now=1.5)  # [1.5, 5.5]
    timeline.transmit(c, b"\x04" * 2, now=2.25)  # [2.25, 4.25]
    stats = timeline.stats()
    assert stats.collisions == 3
    assert stats.two_writer_s == pytest.approx(2.5 + 1.75 + 2.0)
    spans = {c.nodes: (c.start, c.end) for c in stats.collision_log}
    assert spans == {("a", "b"): (1.5, 4.0), ("a", "c"): (2.25, 4.0), ("b", "c"): (2.25, 4.25)}
    heard = timeline.take_due(100.0)
    # By end time: a0 a1 b0 a2 c0 b1 a3 c1 b2 b3, each ORed with what it overlapped.
    assert heard[ear] == bytes.fromhex("01 03 07 07 07 07 07 07 07 02")
    assert len(heard[a]) == 6  # a hears b and c, never itself


def test_the_slaves_hear_whole_runs_and_answer_after_their_turnaround() -> None:
    timeline = BusTimeline(1.0)
    master = timeline.add_node("master")
    slaves = timeline.add_node("slaves", turnaround=3.5, whole_runs=True)
    timeline.transmit(master, b"abc", now=0.0)
    assert timeline.take_due(2.0) == {}  # held until the run's last character ends
    assert timeline.take_due(3.0) == {slaves: b"abc"}
    timeline.transmit(slaves, b"ok", now=3.01)
    assert timeline.next_due() == 3.0 + 3.5 + 1.0
    assert timeline.take_due(8.5) == {master: b"ok"}
    assert [f.start for f in timeline.stats().frames_of("slaves")] == [6.5]


WRITES = st.lists(
    st.tuples(st.integers(0, 2), st.binary(min_size=1, max_size=6), st.floats(0.0, 8.0)),
    max_size=12,
)


@settings(max_examples=300, deadline=None)
@given(WRITES)
def test_every_byte_reaches_every_other_node_once(writes: list[tuple[int, bytes, float]]) -> None:
    """Whatever the timing: a collision exactly when two nodes' characters overlap, no byte
    lost or duplicated, and every byte intact and in wire order when nothing collided."""
    timeline = BusTimeline(1.0)
    for name in ("a", "b", "c"):
        timeline.add_node(name)
    received: dict[int, bytearray] = {index: bytearray() for index in range(3)}
    chars: list[tuple[float, float, int, int]] = []  # the oracle: (start, end, writer, value)
    busy = [0.0, 0.0, 0.0]
    now = 0.0
    for writer, data, pause in writes:
        now += pause
        for index, got in timeline.take_due(now).items():
            received[index] += got
        timeline.transmit(writer, data, now)
        start = max(now, busy[writer])
        for value in data:
            end = start + 1.0
            chars.append((start, end, writer, value))
            start = end
        busy[writer] = start
    for index, got in timeline.take_due(float("inf")).items():
        received[index] += got
    stats = timeline.stats()
    overlapping = any(
        x[2] != y[2] and min(x[1], y[1]) > max(x[0], y[0]) for x in chars for y in chars
    )
    assert (stats.collisions > 0) == overlapping == (stats.two_writer_s > 0)
    for index in range(3):
        heard = [
            value for _, end, writer, value in sorted(chars, key=lambda c: c[1]) if writer != index
        ]
        assert len(received[index]) == len(heard)
        if not overlapping:
            assert received[index] == bytes(heard)
    assert stats.in_flight == 0
