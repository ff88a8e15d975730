"""A simulated multi-drop RS-485 bus: every node hears every byte the others put on the wire.

Several gateways (masters) and the simulator's slaves share one bus, as on a plant's
RS-485 pair. Each node is a pty pair: a gateway opens its slave path (``node.path``)
as it would a USB adapter; the bus holds the master fd. ``attach_slaves`` makes a
``SimulatedLine`` one more node (the line serves one pty pair's master, the bus
drives its other end). Used by the redundancy tests: two masters on one bus must
never transmit at once, and the bus, not the gateways, is the judge of that.

Theory of operation. One daemon thread reads every node's fd and delivers bytes;
``BusTimeline`` is its clockless core (literal times, tested without ptys).

- Clock and pacing: the bus keeps its own clock (``time.monotonic``). A byte a node
  writes occupies the wire for one character time, starting when the bus read it or
  when that node's previous byte ends, whichever is later. It is delivered to the other
  nodes (and to its writer when the node was added with ``echo=True``, as a two-wire
  adapter without echo suppression does) at the end of its character, never earlier: a
  heap holds the deliveries, and the thread sleeps in ``select`` until the next one is
  due (every byte due by then goes out in one write per receiver). Without this a
  gateway would see the line free before the wire really is.
- Frames: a node's run of bytes with no gap longer than 1.5 character times
  (``FRAME_GAP_CHARACTERS``). ``stats().frames`` lists them (node, start, end, bytes).
- Collisions: RS-485 has no arbitration. When a byte overlaps in time, on the bus's
  own timestamps, with a byte of another node, the pair of frames they belong to
  counts one collision (once per pair, whatever the number of bytes), the overlap's
  duration adds to ``two_writer_s``, and both bytes are delivered damaged: each as
  the OR of itself and every byte it overlapped (a driver pulling a bit to its
  dominant state wins). Receivers get both writers' characters, interleaved by time
  (more than the wire could carry then: only the damage is modelled), so neither frame
  arrives as it was sent and its CRC fails.
- The simulator's slaves: their ``SimulatedLine`` runs unpaced (the bus paces its
  bytes) and receives each run of bytes whole at the end of its last character, so
  its framing never depends on catching every inter-character gap on a loaded
  machine. A slave starts answering ``turnaround`` (default t3.5, the silence the
  specification asks before any frame) after the last byte it heard.
- A receiver whose pty cannot take more (nobody reading it) loses the bytes, as a
  UART overruns; ``stats().overruns`` counts them. ``replug(name)`` makes a node a
  fresh adapter again after its gateway was killed (exclusive open cleared, unread
  bytes dropped).
- Lateness: the thread sleeps in ``select`` with 1 ns timer slack. Measured here
  (2 cores shared with other work, 9600 baud, 4 nodes): deliveries p50 48 us and
  p99 157 us behind their time, worst ~4 ms; with ``realtime=True`` worst 0.4 ms.
  ``stats().max_lateness_s`` reports it; ``wait_for`` waits on the bus's counters.
  The bus thread cost ~5 % of a core at 9600 baud with the wire 90 % busy, ~28 % at
  115200 (where the process's other threads holding the GIL delay it by a few ms).

Limits: fds are watched with ``select`` (numbers below 1024). A node's serial
settings are not checked: a gateway set to another speed is still heard. Frame and
collision histories keep the last ``history`` entries; the counters never are.
"""

from __future__ import annotations

import errno
import fcntl
import heapq
import itertools
import os
import select
import termios
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from gateway.core.timing import character_time, t35

from .device import SimulatedDevice
from .line import SimulatedLine, _enter_realtime, _reduce_timer_slack
from .pty import PtyPair, open_pty_pair

FRAME_GAP_CHARACTERS = 1.5  #: a longer silence inside a node's bytes starts a new frame
DEFAULT_HISTORY = 10_000  #: frames and collisions kept for ``stats()``
_OPEN_COLLISIONS = 64  #: recent frame pairs whose collision may still grow
_READ_SIZE = 4096
_JOIN_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class BusNode:
    """A node on the bus: a gateway opens ``path`` as its serial device."""

    name: str
    path: str
    echo: bool


@dataclass(frozen=True)
class BusFrame:
    """One node's run of bytes on the wire, in the bus's clock (``time.monotonic``)."""

    node: str
    start: float
    end: float
    data: bytes


@dataclass(frozen=True)
class BusCollision:
    """Two nodes' frames that overlapped: from the first overlapping instant to the last."""

    start: float
    end: float
    nodes: tuple[str, str]  #: the earlier frame's node first


@dataclass(frozen=True)
class BusStats:
    """A snapshot of what the bus carried."""

    collisions: int  #: pairs of frames from two nodes that overlapped in time
    two_writer_s: float  #: seconds with two writers: the sum of every overlap
    frames_written: Mapping[str, int]  #: frames by node
    bytes_written: Mapping[str, int]  #: bytes by node
    overruns: Mapping[str, int]  #: bytes a node's pty could not take, by receiving node
    in_flight: int  #: bytes on the wire not yet delivered
    max_lateness_s: float  #: worst delay of a delivery behind its character's end
    frames: tuple[BusFrame, ...]  #: the last ``history`` frames, oldest first
    collision_log: tuple[BusCollision, ...]  #: the last ``history`` collisions

    def frames_of(self, node: str) -> tuple[BusFrame, ...]:
        """The frames ``node`` wrote (among those kept)."""
        return tuple(frame for frame in self.frames if frame.node == node)


class _Frame:
    __slots__ = ("data", "end", "node", "serial", "snapshot", "start")

    def __init__(self, serial: int, node: str, start: float) -> None:
        self.serial = serial
        self.node = node
        self.start = start
        self.end = start
        self.data = bytearray()
        self.snapshot: BusFrame | None = None  # set once the node starts its next frame

    def frozen(self) -> BusFrame:
        if self.snapshot is not None:
            return self.snapshot
        return BusFrame(self.node, self.start, self.end, bytes(self.data))


class _Char:
    """One character on the wire; ``heard`` is what receivers get (damaged by overlaps)."""

    __slots__ = ("end", "frame", "heard", "start", "value", "writer")

    def __init__(self, start: float, end: float, writer: int, value: int, frame: _Frame) -> None:
        self.start = start
        self.end = end
        self.writer = writer
        self.value = value
        self.heard = value
        self.frame = frame


class _Collision:
    __slots__ = ("end", "nodes", "start")

    def __init__(self, start: float, end: float, nodes: tuple[str, str]) -> None:
        self.start = start
        self.end = end
        self.nodes = nodes


class _NodeState:
    __slots__ = (
        "busy_until",
        "bytes",
        "echo",
        "frame",
        "frames",
        "heard_until",
        "held",
        "name",
        "overruns",
        "pending",
        "turnaround",
        "whole_runs",
    )

    def __init__(self, name: str, echo: bool, turnaround: float, whole_runs: bool) -> None:
        self.name = name
        self.echo = echo
        self.turnaround = turnaround
        self.whole_runs = whole_runs
        self.busy_until = float("-inf")  # end of this node's last character on the wire
        self.heard_until = float("-inf")  # end of the last character it heard from others
        self.frame: _Frame | None = None
        self.pending: deque[_Char] = deque()  # its characters not yet delivered, in time order
        self.held = bytearray()  # for ``whole_runs``: characters kept until their run ends
        self.frames = 0
        self.bytes = 0
        self.overruns = 0


class BusTimeline:
    """The bus's clockless core: schedules characters, finds collisions, says what is due.

    Every method takes the time from its caller, so it runs on literal times in tests;
    ``now`` must never go backwards between calls. Not thread safe: ``MultidropBus``
    calls it under its lock.
    """

    def __init__(self, char_time: float, *, history: int = DEFAULT_HISTORY) -> None:
        if char_time <= 0:
            raise ValueError(f"character time {char_time} is not positive")
        self.character_time = char_time
        self._frame_gap = FRAME_GAP_CHARACTERS * char_time
        self._nodes: list[_NodeState] = []
        self._heap: list[tuple[float, int, _Char]] = []
        self._order = itertools.count()
        self._serials = itertools.count()
        self._frames: deque[_Frame] = deque(maxlen=history)
        self._collisions = 0
        self._collision_log: deque[_Collision] = deque(maxlen=history)
        self._open: dict[tuple[int, int], _Collision] = {}
        self._two_writer_s = 0.0
        self._max_lateness_s = 0.0
        # Snapshots of the histories, rebuilt only after they change (``wait_for`` asks often).
        self._frames_view: tuple[BusFrame, ...] | None = None
        self._collisions_view: tuple[BusCollision, ...] | None = None

    def add_node(
        self, name: str, *, echo: bool = False, turnaround: float = 0.0, whole_runs: bool = False
    ) -> int:
        """Add a node; returns its index.

        ``turnaround``: a new frame of this node starts no sooner than this after the
        end of the last character it heard. ``whole_runs``: it receives each run of
        another node's characters in one piece, at the end of the run's last one.
        """
        if any(node.name == name for node in self._nodes):
            raise ValueError(f"the bus already has a node named {name!r}")
        self._nodes.append(_NodeState(name, echo, turnaround, whole_runs))
        return len(self._nodes) - 1

    def transmit(self, index: int, data: bytes, now: float) -> None:
        """Put ``data``, which node ``index`` wrote and the bus read at ``now``, on the wire."""
        if not data:
            return
        node = self._nodes[index]
        start = max(now, node.busy_until)
        frame = node.frame
        if frame is None or start - frame.end > self._frame_gap:
            start = max(start, node.heard_until + node.turnaround)
            frame = self._open_frame(node, start)
        char_time = self.character_time
        for value in data:
            end = start + char_time
            char = _Char(start, end, index, value, frame)
            self._collide(char)
            node.pending.append(char)
            heapq.heappush(self._heap, (end, next(self._order), char))
            start = end
        frame.data += data
        frame.end = start
        self._frames_view = None
        node.busy_until = start
        node.bytes += len(data)

    def next_due(self) -> float | None:
        """When the next character's transmission ends (``None``: the wire is idle)."""
        return self._heap[0][0] if self._heap else None

    def take_due(self, now: float) -> dict[int, bytes]:
        """The bytes each node receives now: every character that ended by ``now``."""
        out: dict[int, bytearray] = {}
        heap = self._heap
        while heap and heap[0][0] <= now:
            end, _, char = heapq.heappop(heap)
            writer = self._nodes[char.writer]
            writer.pending.popleft()
            run_ends = not writer.pending or writer.pending[0].start > end
            self._max_lateness_s = max(self._max_lateness_s, now - end)
            for index, node in enumerate(self._nodes):
                if index == char.writer:
                    if not node.echo:
                        continue
                else:
                    node.heard_until = end
                if not node.whole_runs:
                    out.setdefault(index, bytearray()).append(char.heard)
                    continue
                node.held.append(char.heard)
                if run_ends:
                    out.setdefault(index, bytearray()).extend(node.held)
                    node.held.clear()
        return {index: bytes(data) for index, data in out.items()}

    def note_overrun(self, index: int, lost: int) -> None:
        """Node ``index`` could not take ``lost`` bytes delivered to it."""
        self._nodes[index].overruns += lost

    def stats(self) -> BusStats:
        """A snapshot of the counters and histories."""
        nodes = self._nodes
        if self._frames_view is None:
            self._frames_view = tuple(frame.frozen() for frame in self._frames)
        if self._collisions_view is None:
            self._collisions_view = tuple(
                BusCollision(c.start, c.end, c.nodes) for c in self._collision_log
            )
        return BusStats(
            collisions=self._collisions,
            two_writer_s=self._two_writer_s,
            frames_written={node.name: node.frames for node in nodes},
            bytes_written={node.name: node.bytes for node in nodes},
            overruns={node.name: node.overruns for node in nodes},
            in_flight=len(self._heap),
            max_lateness_s=self._max_lateness_s,
            frames=self._frames_view,
            collision_log=self._collisions_view,
        )

    def _open_frame(self, node: _NodeState, start: float) -> _Frame:
        if node.frame is not None:
            node.frame.snapshot = node.frame.frozen()
        frame = _Frame(next(self._serials), node.name, start)
        node.frame = frame
        node.frames += 1
        self._frames.append(frame)
        return frame

    def _collide(self, char: _Char) -> None:
        """Damage and count every overlap of ``char`` with another node's pending characters."""
        for index, other in enumerate(self._nodes):
            pending = other.pending
            if index == char.writer or not pending:
                continue
            if pending[-1].end <= char.start or pending[0].start >= char.end:
                continue
            for held in pending:
                if held.end <= char.start:
                    continue
                if held.start >= char.end:
                    break
                self._overlap(char, held)

    def _overlap(self, new: _Char, old: _Char) -> None:
        start = max(new.start, old.start)
        end = min(new.end, old.end)
        self._two_writer_s += end - start
        self._collisions_view = None
        new.heard |= old.value
        old.heard |= new.value
        first, second = sorted((new.frame, old.frame), key=lambda frame: frame.serial)
        key = (first.serial, second.serial)
        record = self._open.get(key)
        if record is not None:
            record.start = min(record.start, start)
            record.end = max(record.end, end)
            return
        record = _Collision(start, end, (first.node, second.node))
        self._collisions += 1
        self._collision_log.append(record)
        self._open[key] = record
        if len(self._open) > _OPEN_COLLISIONS:
            del self._open[next(iter(self._open))]


class MultidropBus:
    """A simulated RS-485 bus joining ptys: ``node()`` for gateways, ``attach_slaves()``.

    Use as a context manager (or ``start()``/``close()``); nodes may be added before or
    while it runs. Thread safe. ``realtime`` asks for SCHED_FIFO for the bus thread
    (``realtime_active`` says whether it was granted): on a loaded machine it keeps
    deliveries within a fraction of a character of their time.
    """

    def __init__(
        self,
        baudrate: int,
        *,
        data_bits: int = 8,
        parity: str = "N",
        stop_bits: float = 1,
        history: int = DEFAULT_HISTORY,
        realtime: bool = False,
    ) -> None:
        self.baudrate = baudrate
        self._realtime = realtime
        self.realtime_active = False  # set by the bus thread once it runs
        self.character_time = character_time(baudrate, data_bits, parity, stop_bits)
        self.t35 = t35(baudrate, data_bits, parity, stop_bits)
        self._timeline = BusTimeline(self.character_time, history=history)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._nodes: dict[str, BusNode] = {}
        self._fds: dict[int, int] = {}  # fd the bus reads and writes -> node index
        self._pairs: list[PtyPair] = []
        self._adapters: dict[str, PtyPair] = {}  # the nodes gateways open, by name
        self._lines: list[SimulatedLine] = []
        self._wake_r, self._wake_w = os.pipe()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: Exception | None = None
        self._closed = False

    # ------------------------------------------------------------------ public API

    @property
    def nodes(self) -> Mapping[str, BusNode]:
        """The nodes by name."""
        with self._lock:
            return dict(self._nodes)

    def node(self, name: str, echo: bool = False) -> BusNode:
        """Add a node a gateway opens by ``path``; ``echo``: it hears its own bytes too."""
        pair = open_pty_pair()
        try:
            node = self._join(name, pair, pair.sim_fd, echo=echo)
        except BaseException:
            pair.close()
            raise
        with self._lock:
            self._adapters[name] = pair
        return node

    def replug(self, name: str) -> None:
        """Make node ``name`` a freshly plugged adapter: not held exclusively, nothing unread.

        A gateway takes its port with TIOCEXCL, and on a pty the flag outlives the process
        (the bus keeps the tty open): a gateway killed by SIGKILL and started again would
        get EBUSY (unless root). Call this between the kill and the restart; it also drops
        the bytes the dead gateway never read.
        """
        with self._lock:
            pair = self._adapters.get(name)
        if pair is None:
            raise KeyError(f"no node {name!r} opened by a gateway on this bus")
        fcntl.ioctl(pair.hold_fd, termios.TIOCNXCL)
        termios.tcflush(pair.hold_fd, termios.TCIFLUSH)

    def attach_slaves(
        self,
        devices: Mapping[int, SimulatedDevice],
        *,
        name: str = "slaves",
        turnaround: float | None = None,
        **line_kwargs: Any,
    ) -> SimulatedLine:
        """Make ``devices`` one more node, served by a started ``SimulatedLine`` (returned).

        ``turnaround``: silence after a request before a slave's answer starts (default
        t3.5). ``line_kwargs`` go to ``SimulatedLine`` (seed, framing...); not the baud
        rate: the bus paces the slaves' bytes, so their line runs unpaced.
        """
        if "baudrate" in line_kwargs:
            raise ValueError("the bus paces the slaves' bytes: give the baud rate to the bus")
        pair = open_pty_pair()
        try:
            os.set_blocking(pair.hold_fd, False)
            line = SimulatedLine(pair.sim_fd, devices, **line_kwargs)
            gap = self.t35 if turnaround is None else turnaround
            self._join(name, pair, pair.hold_fd, turnaround=gap, whole_runs=True)
        except BaseException:
            pair.close()
            raise
        self._lines.append(line)
        line.start()
        return line

    def stats(self) -> BusStats:
        """A snapshot of what the bus carried."""
        with self._lock:
            return self._timeline.stats()

    def wait_for(self, condition: Callable[[BusStats], bool], timeout: float) -> BusStats:
        """Wait until ``condition(stats)`` holds; raise ``TimeoutError`` after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                stats = self._timeline.stats()
                if condition(stats):
                    return stats
                if self._error is not None:
                    raise RuntimeError("the bus thread failed") from self._error
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(
                        f"bus condition not met within {timeout} s: {_summary(stats)}"
                    )
                self._changed.wait(remaining)

    def start(self) -> None:
        """Start carrying bytes in a daemon thread."""
        if self._thread is not None or self._closed:
            raise RuntimeError("a bus is started once")
        self._thread = threading.Thread(target=self._run, name="multidrop-bus", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the thread and the slaves' lines, close every fd; re-raise a thread's error."""
        if self._closed:
            return
        self._closed = True
        self._stopping.set()
        os.write(self._wake_w, b"x")
        errors: list[BaseException] = []
        if self._thread is not None:
            self._thread.join(_JOIN_TIMEOUT_S)
            if self._thread.is_alive():
                errors.append(RuntimeError("the bus thread did not stop"))
        for line in self._lines:
            try:
                line.stop()
            except Exception as error:  # every fd is still closed below
                errors.append(error)
        for pair in self._pairs:
            pair.close()
        os.close(self._wake_r)
        os.close(self._wake_w)
        if self._error is not None:
            errors.insert(0, self._error)
        if errors:
            raise errors[0]

    def __enter__(self) -> MultidropBus:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ the bus thread

    def _join(
        self,
        name: str,
        pair: PtyPair,
        fd: int,
        *,
        echo: bool = False,
        turnaround: float = 0.0,
        whole_runs: bool = False,
    ) -> BusNode:
        """Register ``pair`` as node ``name``, the bus reading and writing ``fd``."""
        if self._closed:
            raise RuntimeError("the bus is closed")
        with self._lock:
            index = self._timeline.add_node(
                name, echo=echo, turnaround=turnaround, whole_runs=whole_runs
            )
            node = BusNode(name, pair.path, echo)
            self._nodes[name] = node
            self._pairs.append(pair)
            self._fds[fd] = index
        os.write(self._wake_w, b"n")  # the thread watches the new fd from its next turn
        return node

    def _run(self) -> None:
        _reduce_timer_slack()
        if self._realtime:
            self.realtime_active = _enter_realtime()
        try:
            while True:
                with self._lock:
                    due = self._timeline.next_due()
                    watched = [*self._fds, self._wake_r]
                timeout = None if due is None else max(0.0, due - time.monotonic())
                readable, _, _ = select.select(watched, [], [], timeout)
                if self._stopping.is_set():
                    return
                for fd in readable:
                    if fd == self._wake_r:
                        os.read(self._wake_r, _READ_SIZE)
                    else:
                        self._receive(fd)
                self._deliver()
        except Exception as error:  # kept for close() to re-raise in the caller's thread
            with self._changed:
                self._error = error
                self._changed.notify_all()

    def _receive(self, fd: int) -> None:
        """Take what a node wrote and put it on the wire, timed by the bus's clock."""
        try:
            data = os.read(fd, _READ_SIZE)
        except BlockingIOError:
            return
        except OSError as error:
            if error.errno != errno.EIO:
                raise
            return
        if data:
            with self._changed:
                self._timeline.transmit(self._fds[fd], data, time.monotonic())
                self._changed.notify_all()

    def _deliver(self) -> None:
        """Write every byte whose character has ended to the nodes that hear it."""
        with self._changed:
            due = self._timeline.take_due(time.monotonic())
            if not due:
                return
            self._changed.notify_all()
            fds = {index: fd for fd, index in self._fds.items()}
        for index, data in due.items():
            lost = len(data) - _write_some(fds[index], data)
            if lost:
                with self._lock:
                    self._timeline.note_overrun(index, lost)


def _summary(stats: BusStats) -> str:
    """The counters of ``stats``, without the histories (for an error message)."""
    return (
        f"collisions={stats.collisions} frames={dict(stats.frames_written)} "
        f"bytes={dict(stats.bytes_written)} in_flight={stats.in_flight}"
    )


def _write_some(fd: int, data: bytes) -> int:
    """Write what the pty takes without blocking; returns the bytes written."""
    view = memoryview(data)
    written = 0
    while written < len(data):
        try:
            count = os.write(fd, view[written:])
        except (BlockingIOError, InterruptedError):
            return written
        except OSError as error:
            if error.errno != errno.EIO:
                raise
            return written
        if count == 0:
            return written
        written += count
    return written
