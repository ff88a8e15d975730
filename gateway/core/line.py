"""The serial line as a pure state machine: every decision about the wire, no I/O.

Theory of operation. ``LineCore`` owns one serial line: which request goes next and
when, the attempt on the wire, retries, late answers, dead-slave isolation,
coalescing and the read cache. It never reads a clock or touches a port: every
entry point takes ``now`` (seconds on one monotonic clock), ``get_timer()`` says
when it next wants ``handle_timer``, and its decisions come out as actions the
driver executes in order: ``transmits`` (write this frame now), ``deliveries``
(this request's answer and outcome) and ``notes`` (events for metrics and logs).
How frames look on the wire is the line's ``Framing`` (``gateway.core.framing``:
RTU by default, ASCII); the decisions are the same for every framing.

Invariants, each checked by the stateful tests in ``tests/property``:

* **Exactly once.** Every submitted request gets exactly one ``Delivery``.
* **Only its own answer.** A frame is delivered to a request only when it can be
  the answer to the attempt on the wire (unit, function, length, echo: see the
  framing's response decoder, e.g. ``RtuResponseDecoder``). After an attempt fails
  without its answer (timeout, or garbage that was not the answer itself), the
  slave's answer may still come: for that slave's *late-answer window* no request
  that could be confused with the lost one (same slave and function, whose
  exception replies look alike) is sent;
  other slaves are served meanwhile. The window closes early once the slave
  answers a request sent after the loss that could not be confused with it: a
  slave answers one request at a time, so the lost answer will not follow. The
  retry of the lost request itself is exempt: any answer to it is its answer.
* **Quiet line.** Nothing is transmitted before ``gap`` seconds of silence after
  the last byte seen on the line or the end of the gateway's own transmission
  (plus the turnaround after a broadcast).
* **Safe retries.** Only requests without side effects (``pdu.is_safe_to_retry``)
  are sent again after a failed attempt, unless ``retry_unsafe`` says otherwise.
* **Order.** One master's requests to one slave keep read-after-write order: a
  request that may change the slave (a write, any code but a plain read; a broadcast
  changes every slave) passes none of its master's earlier requests to it, and nothing
  of that master passes it, also through the isolated slaves' lane. A read joins another
  master's identical queued read only when no change to that slave was submitted after
  that read and none of its own master's waits; the cache keeps no answer older than a
  change still to run.
* **Fair share.** Masters are served in start-time fair order, charged with the
  wire time their transactions actually took (timeouts included), so a master
  provoking timeouts spends its own share. Each master has its own queue bound
  (0x06 beyond it); the line-wide bound pushes out the longest queue's newest
  request before refusing a master with a shorter queue.
* **Isolation.** A timeout counts against a slave only for a function it has
  answered before (or when it never answered anything), so a master sending a
  code the slave ignores cannot isolate it. After a counted timeout the slave is
  *suspect*: at most one of its requests waits, behind the healthy slaves', and
  others are answered 0x0B at once. ``dead_after`` counted timeouts in a row mark
  it *down*: 0x0B at once, one probe per back-off interval. Suspect and down
  slaves share ``probe_share`` of the line's time; they also go whenever no
  healthy request is waiting.
* **Own echo.** With ``echo`` (a half-duplex adapter that hears itself), the bytes
  of the frame just sent are dropped when they come back, exactly those; bytes that
  are not the echo are the line's, and the echo is still expected after them (until
  the next frame is sent).
* **Bounded noise.** If no usable gap appears for ``noisy_after`` seconds while
  requests wait, they are answered 0x0B and the line is *noisy* (new requests are
  answered 0x0B at once) until a gap appears.
"""

from __future__ import annotations

import heapq
from collections import deque
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from typing import Final, NamedTuple, Protocol

from . import pdu as fc
from .errors import ExceptionCode, ResponseError
from .framing import RTU, Framing, LineKind, ResponseDecoder
from .outcome import LineEvent, Outcome, SlaveState
from .rtu import RtuFrame
from .timing import character_time

INFINITY: Final = float("inf")
#: Builds a NamedTuple from a tuple without its Python-level ``__new__``: the actions made
#: once per transaction use it (``Transmit(...)`` elsewhere means the same).
_tuple_new: Final = tuple.__new__
#: Distinct request frames kept encoded per line (about 70 kB at most).
FRAME_CACHE_SIZE: Final = 256

#: Frames that are not garbage, just not this answer: discard them and go on waiting.
DISCARD_KINDS: Final = frozenset(
    {"unexpected_unit", "unexpected_function", "mismatch", "unexpected_tid", "noise"}
)


def answer_signature(request: bytes) -> bytes:
    """What a normal answer to ``request`` looks like without its data.

    Two requests with the same signature cannot be told apart by their answers
    (same function, same byte count, or the same echo); requests whose signatures
    differ can. Function codes whose answer length is unknown: the function alone.
    """
    function = request[0]
    if function in _BYTE_COUNT_BITS and len(request) >= 5:
        return bytes((function, ((((request[3] << 8) | request[4]) + 7) // 8) & 0xFF))
    if function in _BYTE_COUNT_REGISTERS and len(request) >= 5:
        return bytes((function, (2 * ((request[3] << 8) | request[4])) & 0xFF))
    if function in fc.ECHOED_WRITES:
        return fc.write_response(request)
    return bytes((function,))


_BYTE_COUNT_BITS: Final = frozenset({fc.READ_COILS, fc.READ_DISCRETE_INPUTS})
_BYTE_COUNT_REGISTERS: Final = frozenset(
    {fc.READ_HOLDING_REGISTERS, fc.READ_INPUT_REGISTERS, fc.READ_WRITE_MULTIPLE_REGISTERS}
)


class CacheRulePolicy(Protocol):
    """A read-cache rule, as the configuration gives it."""

    @property
    def max_age(self) -> float: ...

    def covers(self, unit: int, function: int, address: int, quantity: int) -> bool: ...


class LinePolicy(Protocol):
    """The settings the core needs from one line's configuration (``config.LineConfig``)."""

    @property
    def baudrate(self) -> int: ...
    @property
    def data_bits(self) -> int: ...
    @property
    def parity(self) -> str: ...
    @property
    def stop_bits(self) -> float: ...
    @property
    def retries(self) -> int: ...
    @property
    def retry_unsafe(self) -> bool: ...
    @property
    def broadcast_turnaround(self) -> float: ...
    @property
    def max_queue(self) -> int: ...
    @property
    def max_queue_per_master(self) -> int: ...
    @property
    def dead_after(self) -> int: ...
    @property
    def probe_interval(self) -> float: ...
    @property
    def probe_max_interval(self) -> float: ...
    @property
    def probe_share(self) -> float: ...
    @property
    def coalesce(self) -> bool: ...
    @property
    def cache(self) -> Sequence[CacheRulePolicy]: ...
    @property
    def gap(self) -> float: ...
    @property
    def silence(self) -> float: ...
    @property
    def noisy_deadline(self) -> float: ...
    @property
    def echo(self) -> bool: ...

    def timeout_for(self, slave: int) -> float: ...

    def late_window_for(self, slave: int) -> float: ...


def no_reply(_pdu: bytes, _outcome: Outcome) -> None:
    """A reply that goes nowhere: a broadcast's, or a request's once it has been answered."""


@dataclass(slots=True, eq=False, init=False)
class LineRequest:
    """One master's request for one slave; ``reply`` is for the driver, never called here."""

    slave: int
    pdu: bytes
    master: Hashable
    reply: Callable[[bytes, Outcome], None]
    broadcast: bool
    enqueued_at: float
    attempts: int  # attempts made so far
    cancelled: bool  # its master left
    answered: bool
    sent: bool  # its frame went on the wire at least once
    single: bool  # one attempt only (it went through the lane: a probe)
    lane_deadline: float
    epoch: int
    order: int  # its place among the line's submissions (set by ``submit``)
    followers: list[LineRequest]

    def __init__(
        self,
        slave: int,
        pdu: bytes,
        master: Hashable,
        reply: Callable[[bytes, Outcome], None],
        broadcast: bool = False,
    ) -> None:
        # Written out rather than generated by ``dataclass``: the compiled build runs this
        # one natively, where a generated one costs several times more per request.
        self.slave = slave
        self.pdu = pdu
        self.master = master
        self.reply = reply
        self.broadcast = broadcast
        self.enqueued_at = 0.0
        self.attempts = 0
        self.cancelled = False
        self.answered = False
        self.sent = False
        self.single = False
        self.lane_deadline = INFINITY
        self.epoch = 0
        self.order = 0
        self.followers = []

    @property
    def wanted(self) -> bool:
        """False when nobody waits for the answer any more."""
        return not self.cancelled or any(not f.cancelled for f in self.followers)


def may_change(request: LineRequest, slave: int) -> bool:
    """True when ``request`` may change what ``slave`` holds: anything but a plain read,
    sent to it or broadcast."""
    return (request.slave == slave or request.broadcast) and request.pdu[0] not in fc.READ_FUNCTIONS


@dataclass(slots=True)
class LineStats:
    """Traffic counts as plain integers (exported at scrape time; the hot path only adds)."""

    frames_sent: int = 0
    frames_received: int = 0
    bytes_written: int = 0
    bytes_read: int = 0
    queue_depth: int = 0


class Transmit(NamedTuple):
    """Write ``frame`` to the line now (the core has checked the quiet time)."""

    frame: bytes
    request: LineRequest
    queue_wait: float
    retry: bool


class Delivery(NamedTuple):
    """The answer for ``request``; ``wire_time`` is negative when no transaction produced it."""

    request: LineRequest
    pdu: bytes
    outcome: Outcome
    wire_time: float


class LateWindow(NamedTuple):
    """A slave's open late-answer window, handed on to the line that replaces this one."""

    slave: int
    until: float
    signatures: frozenset[bytes]  # answers that may still come
    owner: LineRequest | None  # the request whose attempts were lost
    pending: int  # its attempts whose answers may still come


class Handover(NamedTuple):
    """The wire as a line leaves it to the line that replaces it (``LineCore.handover``)."""

    quiet_since: float  # no frame before this plus the gap (a broadcast's turnaround)
    windows: tuple[LateWindow, ...]


class Note(NamedTuple):
    """An event for metrics and logs."""

    event: LineEvent
    slave: int
    detail: str = ""
    amount: int = 1
    state: SlaveState | None = None


@dataclass(slots=True, eq=False)
class _Master:
    """One master's queue and its account of wire time (start-time fair queuing)."""

    key: Hashable
    queue: deque[LineRequest] = field(default_factory=deque)
    vtime: float = 0.0
    heap_seq: int = -1  # the sequence number of its live heap entry, -1 when not in the heap
    queued: int = 0  # requests waiting (its queue, the lane, the retry slot)
    gone: bool = False


@dataclass(slots=True)
class _Slave:
    """What the line knows of one slave address."""

    state: SlaveState = SlaveState.UP
    misses: int = 0  # counted timeouts in a row
    answered: set[int] = field(default_factory=set)  # functions it has answered
    backoff: float = 0.0
    next_probe_at: float = 0.0
    guard_until: float = 0.0  # end of the late-answer window
    guard_signatures: set[bytes] = field(default_factory=set)  # answers that may still come
    guard_owner: LineRequest | None = None
    guard_decoder: ResponseDecoder | None = None  # recognises the lost answer itself
    guard_pending: int = 0  # the owner's attempts whose answers may still come


@dataclass(slots=True, eq=False, init=False)
class _Attempt:
    """The transaction on the wire."""

    request: LineRequest
    decoder: ResponseDecoder
    sent_at: float
    deadline: float
    from_credit: bool
    silence_at: float
    garbled_at: float
    garbled: ResponseError | None

    def __init__(
        self,
        request: LineRequest,
        decoder: ResponseDecoder,
        sent_at: float,
        deadline: float,
        from_credit: bool,
    ) -> None:
        # Written out, as ``LineRequest``'s: one per transaction.
        self.request = request
        self.decoder = decoder
        self.sent_at = sent_at
        self.deadline = deadline
        self.from_credit = from_credit
        self.silence_at = INFINITY
        self.garbled_at = INFINITY
        self.garbled = None


class LineCore:
    """One serial line's decisions; see the module docstring."""

    def __init__(
        self,
        policy: LinePolicy,
        now: float,
        stats: LineStats | None = None,
        framing: Framing = RTU,
    ) -> None:
        self.stats = stats if stats is not None else LineStats()
        self.framing = framing
        self._encode = framing.encode  # bound once: for RTU, encode_rtu itself
        self._new_decoder = framing.decoder  # for RTU, the RtuResponseDecoder class
        #: Request frames by (slave, PDU): masters poll the same requests over and over, and
        #: a frame is a pure function of them (not for MBAP: its frames carry a fresh id).
        self._frames: dict[tuple[int, bytes], bytes] | None = (
            {} if framing.transaction_ids is None else None
        )
        self.transmits: list[Transmit] = []
        self.deliveries: list[Delivery] = []
        self.notes: list[Note] = []
        self._masters: dict[Hashable, _Master] = {}
        self._heap: list[tuple[float, int, _Master]] = []
        self._seq = 0
        self._vclock = 0.0
        self._slaves: dict[int, _Slave] = {}
        self._lane: dict[int, LineRequest] = {}
        self._guards: dict[int, _Slave] = {}  # slaves in their late-answer window
        self._send_at = INFINITY  # when the next frame may go (set by ``_service``)
        self._retry: LineRequest | None = None
        self._attempt: _Attempt | None = None
        self._queued = 0
        self._quiet_since = now
        self._wanting_since: float | None = None
        self._noisy = False
        self._up = False
        self._stopping = False
        self._paused = False
        self._credit = 0.0
        self._credit_at = now
        self._open_reads: dict[tuple[int, bytes], LineRequest] = {}
        #: Queued reads that others joined, until sent or answered (``_held_by_joined``); a
        #: read back in the queue after a failed attempt (from the lane) is queued again.
        self._joined_leaders: dict[LineRequest, None] = {}
        self._write_epoch: dict[int, int] = {}
        self._broadcast_epoch = 0
        self._submitted = 0  # requests submitted so far (``LineRequest.order``)
        self._cache: dict[tuple[int, bytes], tuple[float, bytes]] = {}
        self._echo_left = b""  # the part of our own frame still to come back (``echo``)
        self._apply_policy(policy)

    # -- configuration -------------------------------------------------------------------

    def _apply_policy(self, policy: LinePolicy) -> None:
        self.policy = policy
        # A Modbus TCP or TLS slave (MBAP framing) has no serial wire behind the socket: its
        # frames take no transmission time (9600 baud would hold each request ~12 ms).
        self._char_time = (
            0.0
            if self.framing.kind is LineKind.TCP
            else character_time(policy.baudrate, policy.data_bits, policy.parity, policy.stop_bits)
        )
        self._gap = policy.gap
        self._silence = policy.silence
        self._garbled_wait = max(2 * policy.silence, 0.003)
        self._noisy_after = policy.noisy_deadline
        self._share = policy.probe_share
        self._credit_cap = self._share  # at most one second's share banked
        self._echo = policy.echo
        self._timeouts: dict[int, float] = {}  # ``policy.timeout_for``, asked once per slave

    def _timeout_for(self, slave: int) -> float:
        timeout = self._timeouts.get(slave)
        if timeout is None:
            timeout = self._timeouts[slave] = self.policy.timeout_for(slave)
        return timeout

    def reconfigure(self, policy: LinePolicy, now: float) -> None:
        """Take new timeouts, retries and limits (the port settings are unchanged)."""
        self._apply_policy(policy)
        if policy.dead_after <= 0:  # isolation off: every slave is served again
            for slave, record in self._slaves.items():
                if record.state is not SlaveState.UP:
                    self._set_state(slave, record, SlaveState.UP)
            for request in list(self._lane.values()):
                self._lane_remove(request)
                self._queue_at_front(request)
        if not policy.cache:
            self._cache.clear()
        self._service(now)

    # -- observation ---------------------------------------------------------------------

    @property
    def up(self) -> bool:
        """True while the port is open."""
        return self._up

    @property
    def noisy(self) -> bool:
        """True while the line has had no usable gap for too long."""
        return self._noisy

    @property
    def queued(self) -> int:
        """Requests waiting for the line."""
        return self._queued

    @property
    def idle(self) -> bool:
        """True when nothing is on the wire or waiting."""
        return self._attempt is None and self._queued == 0

    @property
    def wire_busy(self) -> bool:
        """True while a transaction is on the wire."""
        return self._attempt is not None

    def slave_state(self, slave: int) -> SlaveState:
        """The isolation state of ``slave``."""
        record = self._slaves.get(slave)
        return record.state if record is not None else SlaveState.UP

    def slave_states(self) -> dict[int, SlaveState]:
        """Every slave the line has heard from or given up on, with its state."""
        return {slave: record.state for slave, record in self._slaves.items()}

    def queued_for(self, master: Hashable) -> int:
        """Requests ``master`` has waiting on this line."""
        record = self._masters.get(master)
        return record.queued if record is not None else 0

    def get_timer(self) -> float | None:
        """The next time ``handle_timer`` must be called, ``None`` when nothing is due."""
        attempt = self._attempt
        when = INFINITY
        if attempt is not None:
            when = min(attempt.deadline, attempt.silence_at, attempt.garbled_at)
        elif self._queued:
            when = self._send_at
            if self._wanting_since is not None:
                when = min(when, self._wanting_since + self._noisy_after)
            if self._lane:
                if self._credit < 0.0:
                    when = min(when, self._credit_time())
                for request in self._lane.values():
                    when = min(when, request.lane_deadline)
            for record in self._guards.values():
                when = min(when, record.guard_until)
        if self._noisy:
            when = min(when, self._quiet_since + self._gap)
        return None if when == INFINITY else when

    # -- the masters' side ---------------------------------------------------------------

    def submit(self, request: LineRequest, now: float) -> None:
        """Queue ``request``, or answer it at once (line down, full, isolated, cached...)."""
        request.enqueued_at = now
        self._submitted += 1
        request.order = self._submitted
        if self._stopping or not self._up:
            self._answer(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
            return
        if self._noisy:
            self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
            return
        master = self._masters.get(request.master)
        if master is None:
            master = self._masters[request.master] = _Master(request.master)
        if master.queued + self._on_wire_for(request.master) >= self.policy.max_queue_per_master:
            self._answer(request, ExceptionCode.SERVER_DEVICE_BUSY, Outcome.BUSY)
            return
        if self._queued >= self.policy.max_queue and not self._push_out(master):
            self._answer(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
            return
        if request.broadcast:
            # A broadcast writes to every slave: no later read may share a transaction
            # queued before it, and nothing cached may survive it.
            self._broadcast_epoch += 1
            self._cache.clear()
        else:
            slave = request.slave
            record = self._slaves.get(slave)
            if record is not None and record.state is not SlaveState.UP:
                self._submit_isolated(request, record, now)
                return
            if not self._admit_read(request, now):
                return
        self._enqueue(master, request)
        self._service(now)

    def _on_wire_for(self, master: Hashable) -> int:
        """``master``'s requests on the wire: a failed one comes back to wait for its retry,
        so the per-master bound counts it (waiting plus on the wire never pass the bound)."""
        attempt = self._attempt
        return 1 if attempt is not None and attempt.request.master == master else 0

    def _on_wire_to(self, slave: int) -> bool:
        """True while a request to ``slave`` is on the wire."""
        attempt = self._attempt
        return attempt is not None and attempt.request.slave == slave

    def _submit_isolated(self, request: LineRequest, record: _Slave, now: float) -> None:
        """A request for a suspect or down slave: the one lane place, or 0x0B at once."""
        slave = request.slave
        busy = slave in self._lane or self._on_wire_to(slave)
        if busy or (record.state is SlaveState.DOWN and now < record.next_probe_at):
            self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
            return
        if request.pdu[0] not in fc.READ_FUNCTIONS:
            self._bump_write_epoch(slave)
        self._lane_put(request, now)
        self._service(now)

    def _admit_read(self, request: LineRequest, now: float) -> bool:
        """Cache and coalescing; ``False`` when the request was answered or joined another."""
        slave = request.slave
        if request.pdu[0] not in fc.READ_FUNCTIONS:
            # Anything but a plain read may change the slave: later reads must not be
            # served by a response from before it.
            self._bump_write_epoch(slave)
            request.epoch = self._write_epoch[slave] + self._broadcast_epoch
            return True
        key = (slave, request.pdu)
        if self._cache:
            cached = self._cache.get(key)
            if cached is not None and now <= cached[0]:
                self._deliver(request, cached[1], Outcome.CACHED, -1.0)
                return False
        if self.policy.coalesce:
            epoch = self._write_epoch.get(slave, 0) + self._broadcast_epoch
            leader = self._open_reads.get(key)
            if (
                leader is not None
                and leader.epoch == epoch
                and not self._change_pending(request.master, slave)
            ):
                leader.followers.append(request)
                self._joined_leaders[leader] = None
                self.notes.append(Note(LineEvent.COALESCED, slave))
                return False
            request.epoch = epoch
            self._open_reads[key] = request
        return True

    def _bump_write_epoch(self, slave: int) -> None:
        self._write_epoch[slave] = self._write_epoch.get(slave, 0) + 1
        if self._cache:
            for key in [key for key in self._cache if key[0] == slave]:
                del self._cache[key]

    def cancel(self, master: Hashable, now: float) -> None:
        """``master`` left: drop what nobody still connected waits for. Its requests stay
        when a connected master joined them; a read it had joined goes when it was the
        last to wait for it (the read's own master left before)."""
        for leader in self._carriers():
            for follower in leader.followers:
                if follower.master == master:
                    follower.cancelled = True
        record = self._masters.get(master)
        if record is not None:
            record.gone = True
            for request in record.queue:
                request.cancelled = True
        for request in self._lane.values():
            if request.master == master:
                request.cancelled = True
        if self._retry is not None and self._retry.master == master:
            self._retry.cancelled = True
        for request in self._leaders():  # reads that others joined, this master's or not
            if not request.wanted:
                self._drop(request)
        if record is not None:
            for request in [r for r in record.queue if not r.wanted]:
                self._drop(request)
            if not record.queue and record.queued == 0:
                self._masters.pop(master, None)
        for request in [r for r in self._lane.values() if not r.wanted]:
            self._drop(request)
        self._service(now)

    def _carriers(self) -> list[LineRequest]:
        """Every request whose answer others that joined it still wait for: the waiting
        leaders, the retry and the attempt on the wire (not retried once nobody waits)."""
        carriers = self._leaders()
        if self._retry is not None:
            carriers.append(self._retry)
        if self._attempt is not None:
            carriers.append(self._attempt.request)
        return carriers

    def _drop(self, request: LineRequest) -> None:
        """Take ``request`` from where it waits (its master's queue or the lane), answered
        ``DROPPED``: every master that waited for it has left."""
        if request.answered:
            return  # already dropped by another of ``cancel``'s sweeps
        if self._lane.get(request.slave) is request:
            self._lane_remove(request)
        else:
            owner = self._masters[request.master]
            owner.queue.remove(request)
            self._dequeued(owner, request)
            self._reschedule(owner)
        self._close_to_joiners(request)
        self._deliver(request, b"", Outcome.DROPPED, -1.0)

    # -- the line's side -----------------------------------------------------------------

    def port_opened(self, now: float) -> None:
        """The port is open: requests are taken from now on."""
        self._up = True
        self._quiet_since = max(self._quiet_since, now)
        self._service(now)

    def port_lost(self, now: float) -> None:
        """The port went away: the attempt and the queue are answered 0x0A."""
        self._up = False
        self._noisy = False
        self._echo_left = b""
        self._wanting_since = None
        self._abandon_attempt(now)
        self._fail_all(ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)

    def pause(self, now: float) -> None:
        """Send nothing more: the transaction on the wire finishes and requests keep queuing
        (a reload is about to reopen the line; ``take_queued`` hands them to the new one)."""
        self._paused = True
        self._service(now)

    def stop(self, now: float) -> None:
        """Take no more requests; answer the queue 0x0A; the attempt on the wire finishes."""
        self._stopping = True
        self._fail_all(ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)

    def abandon(self, now: float) -> None:
        """Give up the attempt on the wire (a stop's grace is over): 0x0A for it."""
        self._abandon_attempt(now)

    def handover(self) -> Handover:
        """What the line that replaces this one must know of the wire (a reload that
        reopens the line, once the transaction on the wire has ended). The port is new,
        the wire and the slaves are not: a broadcast's turnaround still runs, and the
        slaves' lost answers may still come (the device under another name, new RS485
        settings, a device server's new connection). An MBAP line hands on no late-answer
        windows: its lost answers went with the old connection."""
        windows: list[LateWindow] = []
        if self.framing.transaction_ids is None:
            windows = [
                LateWindow(
                    slave,
                    record.guard_until,
                    frozenset(record.guard_signatures),
                    record.guard_owner,
                    record.guard_pending,
                )
                for slave, record in self._guards.items()
            ]
        return Handover(self._quiet_since, tuple(windows))

    def take_over(self, handover: Handover, now: float) -> None:
        """Start where the line this one replaces left the wire: quiet no earlier than it
        was, its late-answer windows kept as if opened here."""
        self._quiet_since = max(self._quiet_since, handover.quiet_since)
        if self.framing.transaction_ids is None:  # else answers carry transaction ids
            for window in handover.windows:
                if window.until > now:
                    self._keep_window(window)
        self._service(now)

    def _keep_window(self, window: LateWindow) -> None:
        record = self._record(window.slave)
        record.guard_until = max(record.guard_until, window.until)
        record.guard_signatures |= window.signatures
        owner = window.owner
        record.guard_owner = owner
        record.guard_decoder = None if owner is None else self._new_decoder(window.slave, owner.pdu)
        record.guard_pending = window.pending
        self._guards[window.slave] = record

    def take_queued(self) -> list[LineRequest]:
        """Remove every waiting request unanswered (a reload moves them to a reopened line)."""
        taken: list[LineRequest] = []
        if self._retry is not None:
            taken.append(self._retry)
            self._retry = None
        for master in self._masters.values():
            taken.extend(master.queue)
            master.queue.clear()
            master.queued = 0
            master.heap_seq = -1
        taken.extend(self._lane.values())
        self._lane.clear()
        self._heap.clear()
        self._open_reads.clear()
        self._joined_leaders.clear()
        self._masters = {k: m for k, m in self._masters.items() if not m.gone}
        self._queued = 0
        self.stats.queue_depth = 0
        return self._hand_over(taken)

    def _hand_over(self, taken: list[LineRequest]) -> list[LineRequest]:
        """Requests taken from this line, ready for another: in the order they were
        submitted, each read that joined one of them a request of its own again (the new
        line joins them again where it may), with no attempts made.

        Nothing may stay hidden behind another request: the taker answers each request it
        got (0x0A when the reload stops) or submits it, and a read that joins one there
        must not carry followers of its own. Requests whose master left are answered
        ``DROPPED`` here, as ``cancel`` would have: nobody waits for them."""
        handed: list[LineRequest] = []
        for request in taken:
            handed.append(request)
            handed.extend(request.followers)
            request.followers.clear()
        handed.sort(key=lambda request: request.order)
        kept: list[LineRequest] = []
        for request in handed:
            if request.cancelled:
                self._deliver(request, b"", Outcome.DROPPED, -1.0)
                continue
            request.attempts = 0
            request.single = False
            request.lane_deadline = INFINITY
            kept.append(request)
        return kept

    def receive(self, data: bytes, now: float) -> None:
        """Bytes read from the line at ``now``."""
        self.stats.bytes_read += len(data)
        if now > self._quiet_since:
            self._quiet_since = now
        if self._echo_left:
            data = self._strip_echo(data)
            if not data:
                return
        attempt = self._attempt
        if attempt is None:
            self._discard("late", len(data))
            if self._guards:
                self._watch_late(data)
                self._service(now)
            return
        if attempt.garbled is not None:
            attempt.garbled_at = now + self._garbled_wait  # the line is not quiet yet
        self._decode(attempt, data, now)

    def _decode(self, attempt: _Attempt, data: bytes, now: float) -> None:
        """Feed ``data`` to the attempt's decoder: complete it, skip what is not its answer,
        or note that it was garbled."""
        decoder = attempt.decoder
        while True:
            try:
                frame = decoder.feed(data)
            except ResponseError as error:
                if error.kind in DISCARD_KINDS:
                    # Another unit's frame, a late answer to an earlier request, or noise
                    # in front of the answer: drop it and keep decoding what followed it.
                    self._discard(error.kind, 1, attempt.request.slave)
                    if self._guards and error.frame:
                        self._late_frame(error.frame)
                else:
                    self._garbled(attempt, error, decoder.looks_like_answer, now)
                    if self._attempt is not attempt:  # failed: the rest is late bytes
                        if decoder.leftover:
                            self._discard("late", len(decoder.leftover))
                        self._service(now)
                        return
                data = decoder.leftover
                decoder.reset()
                if data:
                    continue
                return
            break
        if frame is not None:
            if decoder.leftover:
                self._discard("trailing_bytes", len(decoder.leftover), attempt.request.slave)
            self._complete(attempt, frame, now)
            self._service(now)
        elif decoder.waits_for_silence:
            attempt.silence_at = now + self._silence

    def handle_timer(self, now: float) -> None:
        """Time passed: end attempts, expire windows and waits, send what may go."""
        if self._lane:
            self._credit_now(now)  # so the share's next instant is never in the past
        attempt = self._attempt
        if attempt is not None:
            if now >= attempt.silence_at:
                attempt.silence_at = INFINITY
                decoder = attempt.decoder
                try:
                    frame = decoder.end_of_frame()
                except ResponseError as error:
                    rest = decoder.leftover  # bytes behind noise: the answer may start there
                    if error.kind in DISCARD_KINDS:
                        self._discard(error.kind, 1, attempt.request.slave)
                    else:
                        self._garbled(attempt, error, decoder.looks_like_answer, now)
                    decoder.reset()
                    if rest and self._attempt is attempt:
                        self._decode(attempt, rest, now)
                else:
                    self._complete(attempt, frame, now)
            if self._attempt is attempt and now >= attempt.garbled_at:
                self._fail(attempt, attempt.garbled, now)
            if self._attempt is attempt and now >= attempt.deadline:
                if attempt.decoder.buffered:
                    self._discard("incomplete", attempt.decoder.buffered, attempt.request.slave)
                self._fail(attempt, attempt.garbled, now)
        if self._lane:
            for request in [r for r in self._lane.values() if now >= r.lane_deadline]:
                self._lane_remove(request)
                self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
        if self._guards:
            for slave in [s for s, r in self._guards.items() if now >= r.guard_until]:
                self._clear_guard(slave)
        if self._noisy and now >= self._quiet_since + self._gap:
            self._noisy = False
            self.notes.append(Note(LineEvent.LINE_QUIET, 0))
        self._service(now)

    # -- choosing and sending ------------------------------------------------------------

    def _service(self, now: float) -> None:
        """Put the next request on the wire if one may go now."""
        self._send_at = INFINITY
        if self._attempt is not None or not self._up or not self._queued or self._paused:
            self._wanting_since = None
            return
        ready_at = self._quiet_since + self._gap
        if now < ready_at:
            self._send_at = ready_at
            if self._wanting_since is None:
                self._wanting_since = now
            elif now >= self._wanting_since + self._noisy_after:
                self._go_noisy()
            return
        self._wanting_since = None
        while self._queued:
            picked = self._pick(now)
            if picked is None:
                return
            request, master, from_credit = picked
            if request.broadcast:
                self._send_broadcast(request, master, now)
                self._send_at = self._quiet_since + self._gap  # after the turnaround
                return
            if request.cancelled and not request.wanted:
                self._close_to_joiners(request)
                self._deliver(request, b"", Outcome.DROPPED, -1.0)
                if master is not None:
                    self._reschedule(master)
                continue
            self._send(request, now, from_credit)
            return

    def _pick(self, now: float) -> tuple[LineRequest, _Master | None, bool] | None:
        """The next request: a retry, the lane on credit, the fairest master, the lane free."""
        retry = self._retry
        if retry is not None:
            self._retry = None
            self._count_waiting(retry, -1)
            return retry, None, False
        lane = self._lane
        if lane and self._credit_now(now) >= 0.0:
            request = self._lane_candidate(now)
            if request is not None:
                return request, None, True
        heap = self._heap
        skipped: list[_Master] = []
        chosen: tuple[LineRequest, _Master | None, bool] | None = None
        while heap:
            vtime, seq, master = heapq.heappop(heap)
            if master.heap_seq != seq:
                continue  # stale entry
            master.heap_seq = -1
            request = self._first_eligible(master, now)
            if request is None:
                if master.queue:
                    skipped.append(master)
                continue
            master.queue.remove(request)
            master.queued -= 1  # ``_dequeued``
            self._queued -= 1
            self.stats.queue_depth = self._queued
            if vtime > self._vclock:
                self._vclock = vtime
            chosen = request, master, False
            break
        for master in skipped:
            self._push_master(master)
        if chosen is None and lane:
            request = self._lane_candidate(now)
            if request is not None:
                chosen = request, None, False
        return chosen

    def _first_eligible(self, master: _Master, now: float) -> LineRequest | None:
        """The oldest request of ``master`` that may go now.

        A request held by a late-answer window holds back the master's later requests
        to that slave, unless all of them are free of side effects (reads may pass reads;
        nothing passes a write, and a write passes nothing).
        """
        blocked: dict[int, bool] | None = None  # slave -> only safe requests held so far
        slaves = self._slaves
        for request in master.queue:
            if request.broadcast:
                return None if blocked or self._broadcast_held(master.key, request) else request
            slave = request.slave
            safe = fc.is_safe_to_retry(request.pdu) if blocked else True
            if blocked is not None and slave in blocked and not (blocked[slave] and safe):
                blocked[slave] = False
                continue
            record = slaves.get(slave)
            held = record is not None and self._guarded(record, request, now)
            if (
                not held
                and (self._joined_leaders or self._lane)
                and request.pdu[0] not in fc.READ_FUNCTIONS
            ):
                held = self._held_by_joined(master.key, request)
            if not held:
                return request
            if blocked is None:
                blocked = {}
                safe = fc.is_safe_to_retry(request.pdu)
            blocked[slave] = blocked.get(slave, True) and safe
        return None

    def _change_pending(self, master: Hashable, slave: int) -> bool:
        """True while a request of ``master`` that may change ``slave`` waits for the line.

        A read of that master must not join another master's queued read meanwhile: the
        other master's read may go first, and its answer would predate the change.
        """
        record = self._masters.get(master)
        if record is not None and any(may_change(r, slave) for r in record.queue):
            return True
        retry = self._retry
        if retry is not None and retry.master == master and may_change(retry, slave):
            return True
        return any(r.master == master and may_change(r, slave) for r in self._lane.values())

    def _broadcast_held(self, master: Hashable, broadcast: LineRequest) -> bool:
        """True while a read ``master`` submitted before ``broadcast`` has not gone: in the
        isolated slaves' lane, or joined to another master's read that still waits."""
        for request in self._lane.values():
            if request.master == master and request.order < broadcast.order:
                return True
        for leader in self._leaders():
            for follower in leader.followers:
                if (
                    follower.master == master
                    and follower.order < broadcast.order
                    and not follower.cancelled
                ):
                    return True
        return False

    def _leaders(self) -> list[LineRequest]:
        """Reads that others joined and that still wait: queued, or back in the isolated
        slaves' lane after a failed attempt (their followers still wait with them)."""
        leaders = list(self._joined_leaders)
        leaders.extend(r for r in self._lane.values() if r.followers)
        return leaders

    def _behind_broadcast(self, request: LineRequest) -> bool:
        """True while a broadcast its master submitted before ``request`` waits (a request
        from the lane must not pass it)."""
        master = self._masters.get(request.master)
        return master is not None and any(
            queued.broadcast and queued.order < request.order for queued in master.queue
        )

    def _held_by_joined(self, master: Hashable, write: LineRequest) -> bool:
        """True while a read ``master`` sent before ``write`` waits inside another master's
        read (it joined it; queued, or back in the lane): the write must not overtake it."""
        for leader in self._leaders():
            if leader.slave == write.slave and leader.epoch < write.epoch:
                for follower in leader.followers:
                    if follower.master == master and not follower.cancelled:
                        return True
        return False

    @staticmethod
    def _guarded(record: _Slave, request: LineRequest, now: float) -> bool:
        """True when ``request`` could be confused with a lost answer still on its way."""
        return (
            now < record.guard_until
            and answer_signature(request.pdu) in record.guard_signatures
            and request is not record.guard_owner
        )

    def _lane_candidate(self, now: float) -> LineRequest | None:
        best: LineRequest | None = None
        for request in self._lane.values():
            record = self._slaves[request.slave]
            if self._guarded(record, request, now) or self._behind_broadcast(request):
                continue
            if best is None or request.enqueued_at < best.enqueued_at:
                best = request
        if best is not None:
            self._lane_remove(best)
        return best

    def _send(self, request: LineRequest, now: float, from_credit: bool) -> None:
        retry = request.attempts > 0
        request.attempts += 1
        if not request.sent:
            request.sent = True
            self._close_to_joiners(request)
        slave = request.slave
        frame = self._frame(slave, request.pdu)
        transmit_time = len(frame) * self._char_time
        self._attempt = _Attempt(
            request,
            self._new_decoder(slave, request.pdu),
            now,
            now + transmit_time + self._timeout_for(slave),
            from_credit,
        )
        self._quiet_since = now + transmit_time
        stats = self.stats
        stats.frames_sent += 1
        stats.bytes_written += len(frame)
        if retry:
            self.notes.append(Note(LineEvent.RETRY, slave))
        if self._echo:
            self._echo_left = frame
        self.transmits.append(
            _tuple_new(Transmit, (frame, request, now - request.enqueued_at, retry))
        )

    def _frame(self, slave: int, pdu: bytes) -> bytes:
        """The request frame for ``pdu`` to ``slave``, encoded once per distinct request."""
        frames = self._frames
        if frames is None:
            return self._encode(slave, pdu)
        key = (slave, pdu)
        frame = frames.get(key)
        if frame is None:
            frame = self._encode(slave, pdu)
            if len(frames) >= FRAME_CACHE_SIZE:
                frames.clear()  # a bound, not an LRU: polling refills it with what is used
            frames[key] = frame
        return frame

    def _send_broadcast(self, request: LineRequest, master: _Master | None, now: float) -> None:
        frame = self._frame(0, request.pdu)
        transmit_time = len(frame) * self._char_time
        self._quiet_since = now + transmit_time + self.policy.broadcast_turnaround
        self.stats.frames_sent += 1
        self.stats.bytes_written += len(frame)
        self._cache.clear()  # what was read while it waited in the queue is stale now
        if self._echo:
            self._echo_left = frame
        self.transmits.append(Transmit(frame, request, now - request.enqueued_at, False))
        self._deliver(request, b"", Outcome.BROADCAST, -1.0)
        if master is not None:
            master.vtime = max(master.vtime, self._vclock) + (self._quiet_since - now)
            self._reschedule(master)

    # -- ends of attempts ----------------------------------------------------------------

    def _complete(self, attempt: _Attempt, frame: RtuFrame, now: float) -> None:
        """The slave answered the request on the wire."""
        self._attempt = None
        request = attempt.request
        wire = now - attempt.sent_at
        slave = request.slave
        function = request.pdu[0]
        self.stats.frames_received += 1
        record = self._slaves.get(slave)
        if record is None:
            record = self._record(slave)
        record.answered.add(function)
        if record.state is SlaveState.UP:
            record.misses = 0  # ``_alive``, for a slave that was up
        else:
            self._alive(slave, record)
        response = frame.pdu
        if record.guard_until and request is not record.guard_owner:
            if response[0] & fc.EXCEPTION_FLAG:
                if function in {signature[0] for signature in record.guard_signatures}:
                    # An exception cannot be told from the lost request's: this one's
                    # own answer may be the one still on its way now.
                    self._open_guard(slave, record, request, now)
            else:
                self._clear_guard(slave)  # it answered something after the loss: done
        self._charge(attempt, wire, now)
        if response[0] & fc.EXCEPTION_FLAG:
            outcome = Outcome.SLAVE_EXCEPTION
        elif function in fc.READ_FUNCTIONS:
            if self.policy.cache:
                self._store_cache(request, response, now)
            outcome = Outcome.OK
        else:
            outcome = Outcome.OK
        self._deliver(request, response, outcome, wire)

    def _garbled(
        self, attempt: _Attempt, error: ResponseError, damaged_answer: bool, now: float
    ) -> None:
        """A garbled frame: fail the attempt at once, or listen a little longer first.

        A frame with the awaited unit, function and length is the answer itself,
        damaged: no other answer is coming, the attempt fails at once. Anything else
        may be noise in front of the real answer: the attempt fails only after the
        line stayed quiet for ``_garbled_wait``, and a valid answer meanwhile is taken.
        """
        slave = attempt.request.slave
        if error.kind == "crc":
            self.notes.append(Note(LineEvent.CRC_ERROR, slave, error.reason))
        else:
            self._discard(error.kind, 1, slave)
        attempt.garbled = error
        if damaged_answer:
            self._fail(attempt, error, now, damaged=True)
        else:
            attempt.garbled_at = now + self._garbled_wait

    def _fail(
        self, attempt: _Attempt, error: ResponseError | None, now: float, damaged: bool = False
    ) -> None:
        """An attempt ended without an answer: window, isolation, then retry or 0x0B."""
        self._attempt = None
        request = attempt.request
        slave = request.slave
        function = request.pdu[0]
        wire = now - attempt.sent_at
        record = self._record(slave)
        if not damaged:
            self._open_guard(slave, record, request, now)
        before = record.state
        if error is None:
            timeout = self._timeout_for(slave)
            self.notes.append(Note(LineEvent.TIMEOUT, slave, f"no answer within {timeout:g} s"))
            self._count_timeout(slave, record, function, now)
        elif error.kind != "crc":  # a CRC error was noted when it arrived
            self.notes.append(Note(LineEvent.GARBLED, slave, error.reason))
        if before is SlaveState.UP and record.state is not SlaveState.UP:
            self._credit_now(now)
            self._credit -= wire  # the loss that made it suspect is paid from its share
        self._charge(attempt, wire, now)
        retryable = (
            not self._stopping
            and not request.single
            and request.attempts <= self.policy.retries
            and request.wanted
            and (self.policy.retry_unsafe or fc.is_safe_to_retry(request.pdu))
            and record.state is not SlaveState.DOWN
        )
        if retryable and record.state is SlaveState.UP:
            self._retry = request
            self._count_waiting(request, +1)
        elif retryable and slave not in self._lane:
            self._lane_put(request, now)
        else:
            self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
        if before is not record.state:
            keep = 1 if record.state is SlaveState.SUSPECT and slave not in self._lane else 0
            self._isolate(slave, keep)

    def _count_timeout(self, slave: int, record: _Slave, function: int, now: float) -> None:
        """Count a timeout against the slave's health, unless it may just ignore the code."""
        policy = self.policy
        if policy.dead_after <= 0:
            return
        if record.answered and function not in record.answered:
            return  # a code it never answered: it may ignore it, and that is no sign of death
        record.misses += 1
        if record.state is SlaveState.DOWN:
            record.backoff = min(record.backoff * 2, policy.probe_max_interval)
            record.next_probe_at = now + record.backoff
        elif record.misses >= policy.dead_after:
            record.backoff = policy.probe_interval
            record.next_probe_at = now + record.backoff
            self._set_state(slave, record, SlaveState.DOWN)
        elif record.state is SlaveState.UP:
            self._set_state(slave, record, SlaveState.SUSPECT)

    def _isolate(self, slave: int, keep: int) -> None:
        """Answer the slave's waiting requests 0x0B, keeping the oldest ``keep`` in the lane."""
        lane_request = self._lane.get(slave)
        if lane_request is not None and self._slaves[slave].state is SlaveState.DOWN:
            self._lane_remove(lane_request)
            self._answer(lane_request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
        doomed: list[tuple[_Master, LineRequest]] = []
        for master in self._masters.values():
            for request in master.queue:
                if request.slave == slave and not request.broadcast:
                    doomed.append((master, request))
        doomed.sort(key=lambda pair: pair[1].enqueued_at)
        for index, (master, request) in enumerate(doomed):
            master.queue.remove(request)
            self._dequeued(master, request)
            if index < keep:
                self._lane_put(request, request.enqueued_at)
            else:
                self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)

    def _abandon_attempt(self, now: float) -> None:
        attempt = self._attempt
        if attempt is not None:
            self._attempt = None
            # Its answer may still come once the port is back: hold look-alikes meanwhile.
            slave = attempt.request.slave
            record = self._record(slave)
            self._open_guard(slave, record, attempt.request, now)
            self._answer(attempt.request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)

    def _go_noisy(self) -> None:
        self._noisy = True
        self._wanting_since = None
        self.notes.append(Note(LineEvent.LINE_NOISY, 0, f"no gap for {self._noisy_after:g} s"))
        self._fail_all(ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)

    def _fail_all(self, code: ExceptionCode, outcome: Outcome) -> None:
        for request in self.take_queued():
            self._answer(request, code, outcome)

    # -- bookkeeping ---------------------------------------------------------------------

    def _enqueue(self, master: _Master, request: LineRequest) -> None:
        master.queue.append(request)
        master.queued += 1
        self._queued += 1
        self.stats.queue_depth = self._queued
        if master.heap_seq < 0:
            if master.vtime < self._vclock:
                master.vtime = self._vclock
            self._push_master(master)

    def _queue_at_front(self, request: LineRequest) -> None:
        master = self._masters.get(request.master)
        if master is None:
            master = self._masters[request.master] = _Master(request.master)
        if request.followers:  # still waited for by the reads that joined it
            self._joined_leaders[request] = None
        # Back from the lane: first, but behind its master's earlier broadcasts.
        place = 0
        for index, queued in enumerate(master.queue):
            if queued.broadcast and queued.order < request.order:
                place = index + 1
        master.queue.insert(place, request)
        master.queued += 1
        self._queued += 1
        self.stats.queue_depth = self._queued
        if master.heap_seq < 0:
            self._push_master(master)

    def _count_waiting(self, request: LineRequest, delta: int) -> None:
        """A request enters (+1) or leaves (-1) the waiting set outside its master's queue."""
        master = self._masters.get(request.master)
        if master is not None:
            master.queued += delta
        self._queued += delta
        self.stats.queue_depth = self._queued

    def _push_master(self, master: _Master) -> None:
        self._seq += 1
        master.heap_seq = self._seq
        heapq.heappush(self._heap, (master.vtime, self._seq, master))

    def _reschedule(self, master: _Master) -> None:
        """Put ``master`` back in the fair order after its transaction (or forget it)."""
        if master.queue:
            if master.heap_seq < 0:
                self._push_master(master)
        elif master.queued == 0 and master.gone:
            self._masters.pop(master.key, None)

    def _dequeued(self, master: _Master | None, request: LineRequest) -> None:
        if master is not None:
            master.queued -= 1
        self._queued -= 1
        self.stats.queue_depth = self._queued

    def _lane_put(self, request: LineRequest, now: float) -> None:
        """Wait in the isolated slaves' lane: one attempt, answered 0x0B if not sent in time."""
        request.single = True
        request.lane_deadline = now + self._timeout_for(request.slave)
        self._lane[request.slave] = request
        if request.master not in self._masters:
            self._masters[request.master] = _Master(request.master)
        self._count_waiting(request, +1)

    def _lane_remove(self, request: LineRequest) -> None:
        del self._lane[request.slave]
        request.lane_deadline = INFINITY
        self._dequeued(self._masters.get(request.master), request)

    def _push_out(self, master: _Master) -> bool:
        """The line is full: drop the newest request of the longest queue if that is not ours."""
        longest = max(self._masters.values(), key=lambda m: len(m.queue), default=None)
        if longest is None or longest is master or len(longest.queue) <= len(master.queue) + 1:
            return False
        victim = longest.queue.pop()
        self._dequeued(longest, victim)
        self._close_to_joiners(victim)
        self._answer(victim, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
        return True

    def _charge(self, attempt: _Attempt, wire: float, now: float) -> None:
        """Account the wire time to the master who used it (or to the isolated share)."""
        master = self._masters.get(attempt.request.master)
        if attempt.from_credit:
            self._credit_now(now)
            self._credit -= wire
        elif master is not None:
            master.vtime = max(master.vtime, self._vclock) + wire
            if master.heap_seq >= 0:
                self._push_master(master)  # its old entry goes stale
        if master is not None and (master.gone or (master.queue and master.heap_seq < 0)):
            self._reschedule(master)  # back in the fair order, or forgotten

    def _credit_now(self, now: float) -> float:
        """The isolated slaves' share of line time banked so far (negative: in debt)."""
        if now > self._credit_at:
            banked = self._credit + self._share * (now - self._credit_at)
            if banked > -1e-9:  # paid off: rounding must not leave a debt too small to wait for
                banked = max(banked, 0.0)
            self._credit = min(banked, self._credit_cap)
            self._credit_at = now
        return self._credit

    def _credit_time(self) -> float:
        """When the banked share reaches zero again."""
        if self._credit >= 0.0:
            return self._credit_at
        if self._share <= 0.0:
            return INFINITY
        return self._credit_at - self._credit / self._share

    def _set_state(self, slave: int, record: _Slave, state: SlaveState) -> None:
        record.state = state
        if state is SlaveState.UP:
            record.misses = 0
        self.notes.append(Note(LineEvent.SLAVE_STATE, slave, state=state, amount=record.misses))

    def _open_guard(self, slave: int, record: _Slave, request: LineRequest, now: float) -> None:
        """The slave's answer to ``request`` may still come: nothing that could be taken for
        it goes to this slave until the window ends or the slave shows it is done."""
        window = self.policy.late_window_for(slave)
        record.guard_until = max(record.guard_until, now + window)
        record.guard_signatures.add(answer_signature(request.pdu))
        if record.guard_owner is request:
            record.guard_pending += 1  # another attempt of it whose answer may still come
        else:
            # Answers come in order: the new owner's come after any earlier request's.
            record.guard_owner = request
            record.guard_decoder = self._new_decoder(slave, request.pdu)
            record.guard_pending = 1
        self._guards[slave] = record
        self.notes.append(Note(LineEvent.LATE_WINDOW, slave, f"{window:g} s"))

    def _clear_guard(self, slave: int) -> None:
        record = self._guards.pop(slave)
        record.guard_until = 0.0
        record.guard_signatures.clear()
        record.guard_owner = None
        record.guard_decoder = None
        record.guard_pending = 0

    def _watch_late(self, data: bytes) -> None:
        """Bytes while nothing is on the wire: lost answers arriving, thrown away.

        When the answers of all the owner's failed attempts have arrived, nothing more is
        coming for it and its window ends.
        """
        for slave, record in list(self._guards.items()):
            decoder = record.guard_decoder
            if decoder is None:
                continue
            chunk = data
            while True:
                try:
                    frame = decoder.feed(chunk)
                except ResponseError:
                    chunk = decoder.leftover  # what followed the bad frame may be the answer
                    decoder.reset()
                    if chunk:
                        continue
                    break
                if frame is None:
                    if decoder.waits_for_silence:
                        decoder.reset()  # noise with no length to wait for: start afresh
                    break
                chunk = decoder.leftover
                decoder.reset()
                if self._late_answer_arrived(slave, record) or not chunk:
                    break

    def _late_frame(self, frame: bytes) -> None:
        """An intact frame the attempt on the wire discarded: is it a lost answer?"""
        slave = frame[0]
        record = self._guards.get(slave)
        if record is None or record.guard_owner is None:
            return
        try:
            answer = self._new_decoder(slave, record.guard_owner.pdu).feed(frame)
        except ResponseError:
            return
        if answer is not None:
            self._late_answer_arrived(slave, record)

    def _record(self, slave: int) -> _Slave:
        """What the line knows of ``slave``, created on first need."""
        record = self._slaves.get(slave)
        if record is None:
            record = self._slaves[slave] = _Slave()
        return record

    def _alive(self, slave: int, record: _Slave) -> None:
        """The slave answered: no missed answers in a row, and back in the fair order."""
        record.misses = 0
        if record.state is not SlaveState.UP:
            self._set_state(slave, record, SlaveState.UP)
            waiting = self._lane.get(slave)
            if waiting is not None:
                self._lane_remove(waiting)
                self._queue_at_front(waiting)

    def _late_answer_arrived(self, slave: int, record: _Slave) -> bool:
        """A lost attempt's answer came (and was thrown away); ``True`` when the window ended.

        The slave is alive, only slow: it is no longer suspect or down.
        """
        record.guard_pending -= 1
        self._alive(slave, record)
        if record.guard_pending <= 0:  # every lost attempt's answer has come
            self._clear_guard(slave)
            return True
        return False

    def _strip_echo(self, data: bytes) -> bytes:
        """Drop the echo of our own frame from the front of ``data``; the rest is the line's."""
        echo = self._echo_left
        count = min(len(echo), len(data))
        if data[:count] == echo[:count]:
            self._echo_left = echo[count:]
            return data[count:]
        # Not our echo: a slave talking over our frame (its answer to an earlier request),
        # or noise. Those bytes are the line's; the echo may still follow them.
        return data

    def _close_to_joiners(self, request: LineRequest) -> None:
        """From now on (its frame goes on the wire) no other read may join ``request``."""
        key = (request.slave, request.pdu)
        if self._open_reads.get(key) is request:
            del self._open_reads[key]
        self._joined_leaders.pop(request, None)

    def _store_cache(self, request: LineRequest, response: bytes, now: float) -> None:
        rules = self.policy.cache
        if not rules:
            return
        if self._change_waits_for(request.slave):
            return  # the answer is older than a write still to run: kept, it would be stale
        pdu = request.pdu
        address = (pdu[1] << 8) | pdu[2]
        quantity = (pdu[3] << 8) | pdu[4]
        for rule in rules:
            if rule.covers(request.slave, pdu[0], address, quantity):
                self._cache[(request.slave, pdu)] = (now + rule.max_age, response)
                return

    def _change_waits_for(self, slave: int) -> bool:
        """True while a request that may change ``slave`` (a write, a broadcast, any code
        but a plain read) waits for the line: queued, in the lane, or due for a retry."""
        retry = self._retry
        waiting = [retry] if retry is not None else []
        waiting.extend(self._lane.values())
        for master in self._masters.values():
            waiting.extend(master.queue)
        return any(may_change(request, slave) for request in waiting)

    def _discard(self, reason: str, count: int, slave: int = 0) -> None:
        self.notes.append(Note(LineEvent.DISCARDED, slave, reason, count))

    def _answer(self, request: LineRequest, code: ExceptionCode, outcome: Outcome) -> None:
        self._close_to_joiners(request)
        self._deliver(request, fc.exception_pdu(request.pdu[0], code), outcome, -1.0)

    def _deliver(self, request: LineRequest, pdu: bytes, outcome: Outcome, wire: float) -> None:
        """Deliver exactly once, to ``request`` and every read that joined it."""
        deliveries = self.deliveries
        if request.followers:
            self._joined_leaders.pop(request, None)
        if not request.answered:
            request.answered = True
            deliveries.append(_tuple_new(Delivery, (request, pdu, outcome, wire)))
        for follower in request.followers:
            if not follower.answered:
                follower.answered = True
                deliveries.append(Delivery(follower, pdu, outcome, -1.0))
        request.followers.clear()
