"""The wire as a strategy the machine holds: which bytes answer which attempt.

Theory of operation. ``Wire`` is what the machine asks about the attempts on the wire
and tells to start one. Given bytes or time, a wire decodes and *returns* what it found
(``Finding``: an answer, a garbled or failed attempt, bytes to discard or to hear as
another master's, a lost answer); the machine applies each in order. A wire never calls
the machine nor writes its state: it keeps its own (the attempts, the echo to strip) and
asks the parts it is given (``attach``) questions. ``SerialWire`` is a shared medium with
one attempt at a time: its answers are known by their shape (unit, function, length,
echo), the line must be quiet for the gap before each frame, an adapter may echo our own
frame, and a lost answer needs a late-answer window. ``flights.FlightWire`` keeps several
attempts outstanding on a connection whose answers carry their transaction ids.
"""

from __future__ import annotations

from collections.abc import Hashable
from enum import IntEnum
from typing import Final, NamedTuple

from .. import pdu as fc
from ..echo import strip_echo
from ..errors import ResponseError
from ..outcome import DiscardReason
from ..rtu import RtuFrame
from .fair_queue import Master
from .foreign import ForeignMasters, Heard, HeardKind
from .health import ProbeLane
from .late import LateWindows
from .order import OrderRules
from .records import DISCARD_KINDS, INFINITY, Attempt, LineRequest, tuple_new
from .sharing import ReadSharing


class Found(IntEnum):
    """What a wire found in bytes or time (``Finding.kind``)."""

    COMPLETE = 0  # ``attempt`` answered by ``frame`` (the wire has ended it)
    GARBLED = 1  # ``attempt`` got ``error``; ``damaged``: its own answer, damaged (ended)
    FAILED = 2  # ``attempt`` ended without an answer (``error``: the garble that ended it)
    DISCARD = 3  # ``amount`` frames or bytes thrown away for ``reason`` (``slave``'s)
    HEAR = 4  # ``data`` no attempt took: perhaps another master's (``slave``: the one asked)
    HEARD = 5  # frames the wire had classified already (``heard``), to note and learn from
    LATE_BYTES = 6  # ``data`` while nothing is on the wire: perhaps a lost answer
    LATE_FRAME = 7  # ``data``, an intact frame the attempt discarded: perhaps a lost answer
    LATE_ANSWER = 8  # a lost attempt's answer by its id: ``slave`` alive, ``at`` - ``sent_at``


class Finding(NamedTuple):
    """One thing a wire found; which fields mean something depends on ``kind``."""

    kind: Found
    attempt: Attempt | None = None
    frame: RtuFrame | None = None
    error: ResponseError | None = None
    damaged: bool = False
    reason: DiscardReason | None = None
    amount: int = 0
    slave: int = -1
    data: bytes = b""
    heard: tuple[Heard, ...] = ()
    sent_at: float = 0.0
    function: int = 0


#: The fields of a ``Finding`` after ``frame``, at their defaults.
_NO_DETAIL: Final = (None, False, None, 0, -1, b"", (), 0.0, 0)
#: The usual finding, looked up once (an enum member is a class attribute lookup).
COMPLETE: Final = Found.COMPLETE


def discarded(reason: DiscardReason, count: int, slave: int = 0) -> Finding:
    return Finding(Found.DISCARD, reason=reason, amount=count, slave=slave)


class WireParts(NamedTuple):
    """The machine's parts a wire asks questions of (``Wire.attach``)."""

    late: LateWindows
    foreign: ForeignMasters
    order: OrderRules
    sharing: ReadSharing
    lane: ProbeLane


class Wire:
    """The strategy's questions and commands; the defaults suit a wire without them."""

    parts: WireParts

    def __init__(
        self,
        quiet_line: bool = True,
        concurrent: bool = False,
        capacity: int = 1,
        orders_outstanding: bool = False,
    ) -> None:
        # Instance attributes, not class ones: the machine reads them on every pass.
        #: A shared medium: quiet time before each frame, noise, echo, late-answer windows.
        self.quiet_line = quiet_line
        #: Several attempts may be outstanding (the queue is served while one is).
        self.concurrent = concurrent
        #: Attempts at most on the wire at once.
        self.capacity = capacity
        #: The wire keeps accounts of outstanding requests: tell it of every answer.
        self.orders_outstanding = orders_outstanding
        self.draining = False  # a broadcast waits for every attempt to end
        #: Attempts on the wire now: a plain attribute, read on every pass of the machine.
        self.outstanding = 0
        #: The wire time charged ahead to a master when its request is sent (``FlightWire``).
        self.estimate = 0.0
        # Settings the machine gives (``LineCore._apply_policy``).
        self.char_time = 0.0
        self.silence = 0.0  # the quiet that ends an RTU answer
        self.garbled_wait = 0.0  # the quiet after a garble before the attempt fails
        self.echo = False  # the adapter echoes our frames
        self.listens = True  # frames no attempt took may be other masters' (not MBAP)

    def attach(self, parts: WireParts) -> None:
        """The parts this wire asks questions of (it never calls the machine)."""
        self.parts = parts

    def timer(self) -> float:
        """The attempts' next deadline (``INFINITY``: none)."""
        raise NotImplementedError

    def on_wire_for(self, master: Hashable) -> int:
        raise NotImplementedError

    def on_wire_to(self, slave: int) -> bool:
        raise NotImplementedError

    def requests(self) -> list[LineRequest]:
        """The requests of the attempts on the wire."""
        raise NotImplementedError

    def overtakable(self) -> list[LineRequest]:
        """Requests on the wire that a request sent now could overtake."""
        return []

    def first_eligible(self, master: Master, now: float) -> LineRequest | None:
        """The oldest request of ``master`` that may go now."""
        raise NotImplementedError

    def may_go(self, request: LineRequest, now: float) -> bool:
        """True when the lane's ``request`` may go now."""
        raise NotImplementedError

    def start(self, attempt: Attempt, frame: bytes) -> bytes:
        """``attempt`` starts with ``frame``: the frame to transmit (the wire may give it
        another transaction id)."""
        raise NotImplementedError

    def end(self, attempt: Attempt) -> None:
        """``attempt`` is over (a no-op when it was ended already)."""
        raise NotImplementedError

    def take_all(self) -> list[Attempt]:
        """Give up every attempt on the wire."""
        raise NotImplementedError

    def receive(self, data: bytes, now: float) -> list[Finding]:
        raise NotImplementedError

    def expire(self, now: float) -> list[Finding]:
        """Time passed: end the attempts whose time is up."""
        raise NotImplementedError

    def opened(self) -> None:
        """A new port or connection."""

    def lost(self) -> None:
        """The port or connection went away (its attempts were answered)."""

    def expect_echo(self, frame: bytes) -> None:
        """``frame`` was sent: the adapter's echo of it is to be dropped (``echo``)."""

    def joined(self, request: LineRequest) -> None:
        """``request`` joined another master's read."""

    def released(self, request: LineRequest) -> None:
        """``request`` (and the reads that joined it) is about to be answered."""

    def forget(self, request: LineRequest) -> None:
        """``request`` leaves this line unanswered (a reload takes it)."""

    def may_cache(self, attempt: Attempt, epoch: int) -> bool:
        """True when the answer to ``attempt`` is no older than any change submitted
        (``epoch``: the slave's write epoch now)."""
        return True

    def uncacheable(self) -> None:
        """The cache was just turned on: the answers of the attempts outstanding, sent
        without the cache's checks, are not kept."""


class SerialWire(Wire):
    """One attempt at a time on a shared medium (see the module doc)."""

    def __init__(self) -> None:
        super().__init__()
        self.attempt: Attempt | None = None
        self.echo_left = b""  # the part of our own frame still to come back (``echo``)
        self.echo_frame = b""  # that frame, whole

    def timer(self) -> float:
        attempt = self.attempt
        if attempt is None:
            return INFINITY
        return min(attempt.deadline, attempt.silence_at, attempt.garbled_at)

    def on_wire_for(self, master: Hashable) -> int:
        """A failed request comes back to wait for its retry, so the per-master bound
        counts it (waiting plus on the wire never pass the bound)."""
        attempt = self.attempt
        return 1 if attempt is not None and attempt.request.master == master else 0

    def on_wire_to(self, slave: int) -> bool:
        attempt = self.attempt
        return attempt is not None and attempt.request.slave == slave

    def requests(self) -> list[LineRequest]:
        return [] if self.attempt is None else [self.attempt.request]

    def first_eligible(self, master: Master, now: float) -> LineRequest | None:
        """A request held by a late-answer window holds back the master's later requests
        to that slave, unless all of them are free of side effects (reads may pass reads;
        nothing passes a write, and a write passes nothing)."""
        parts = self.parts
        late, foreign, order = parts.late, parts.foreign, parts.order
        blocked: dict[int, bool] | None = None  # slave -> only safe requests held so far
        for request in master.queue:
            if request.broadcast:
                if blocked or order.broadcast_held(master.key, request):
                    return None
                return request
            slave = request.slave
            safe = fc.is_safe_to_retry(request.pdu) if blocked else True
            if blocked is not None and slave in blocked and not (blocked[slave] and safe):
                blocked[slave] = False
                continue
            held = bool(late.windows) and late.holds(request, now)
            if foreign.pending and not held:
                held = foreign.holds(slave, request.pdu, now)
            if (
                not held
                and (parts.sharing.joined or parts.lane.requests)
                and request.pdu[0] not in fc.READ_FUNCTIONS
            ):
                held = order.held_by_joined(master.key, request)
            if not held:
                return request
            if blocked is None:
                blocked = {}
                safe = fc.is_safe_to_retry(request.pdu)
            blocked[slave] = blocked.get(slave, True) and safe
        return None

    def may_go(self, request: LineRequest, now: float) -> bool:
        parts = self.parts
        foreign = parts.foreign
        if foreign.pending and foreign.holds(request.slave, request.pdu, now):
            return False
        return not parts.late.holds(request, now)

    def start(self, attempt: Attempt, frame: bytes) -> bytes:
        self.attempt = attempt
        self.outstanding = 1
        return frame

    def end(self, attempt: Attempt) -> None:
        if self.attempt is attempt:
            self.attempt = None
            self.outstanding = 0

    def take_all(self) -> list[Attempt]:
        attempt = self.attempt
        if attempt is None:
            return []
        self.end(attempt)
        return [attempt]

    def lost(self) -> None:
        self.echo_left = self.echo_frame = b""

    def expect_echo(self, frame: bytes) -> None:
        self.echo_left = self.echo_frame = frame

    def receive(self, data: bytes, now: float) -> list[Finding]:
        found: list[Finding] = []
        if self.echo_left:
            data = self._strip_echo(data)
            if not data:
                return found
        attempt = self.attempt
        if attempt is None:
            # Another master's frames, its slaves' answers, or a lost answer of ours.
            found.append(discarded(DiscardReason.LATE, len(data)))
            found.append(Finding(Found.HEAR, data=data))
            if self.parts.late.windows:
                found.append(Finding(Found.LATE_BYTES, data=data))
            return found
        if attempt.garbled is not None:
            attempt.garbled_at = now + self.garbled_wait  # the line is not quiet yet
        self._decode(attempt, data, now, found)
        return found

    def _garbled(
        self, attempt: Attempt, error: ResponseError, damaged: bool, now: float
    ) -> Finding:
        """The attempt got a garbled frame. A frame with the awaited unit, function and
        length is the answer itself, damaged: the attempt ends now. Anything else may be
        noise in front of the real answer: it ends only after ``garbled_wait`` of quiet,
        and a valid answer meanwhile is taken."""
        attempt.garbled = error
        if damaged:
            self.end(attempt)
        else:
            attempt.garbled_at = now + self.garbled_wait
        return Finding(Found.GARBLED, attempt, error=error, damaged=damaged)

    def _hear_now(self, data: bytes, now: float, asked: int, found: list[Finding]) -> bool:
        """Classify ``data`` as the machine's ``hear`` would, here, because the decoding
        goes on from the answer: ``True`` when another master's request was among them
        (the bytes after it are left in ``foreign.take_unframed``)."""
        if not self.listens:
            return False
        parts = self.parts
        own = [(request.slave, request.pdu) for request in self.requests()]
        own.extend(parts.late.owners())
        heard = parts.foreign.feed(data, now, self.char_time, own, True, asked)
        if not heard:
            return False
        found.append(Finding(Found.HEARD, heard=tuple(heard)))
        return any(h.kind is HeardKind.MASTER or h.kind is HeardKind.ASKED for h in heard)

    def _decode(self, attempt: Attempt, data: bytes, now: float, found: list[Finding]) -> None:
        """Feed ``data`` to the attempt's decoder: complete it, skip what is not its answer,
        or note that it was garbled."""
        decoder = attempt.decoder
        slave = attempt.request.slave
        unheard = data  # what the decoder has that ``hear`` has not (after ``heard``)
        while True:
            try:
                frame = decoder.feed(data)
            except ResponseError as error:
                if unheard:  # not the answer (or not only): perhaps another master's frames
                    master = self._hear_now(attempt.heard + unheard, now, slave, found)
                    attempt.heard = unheard = b""
                    if master:  # no damaged answer: the answer may follow it
                        decoder.reset()
                        data = unheard = self.parts.foreign.take_unframed()
                        if data:
                            continue
                        return
                if error.kind in DISCARD_KINDS:
                    # Another unit's frame, a late answer to an earlier request, or noise
                    # in front of the answer: drop it and keep decoding what followed it.
                    found.append(discarded(DiscardReason(error.kind), 1, slave))
                    if error.frame and self.parts.late.windows:
                        found.append(Finding(Found.LATE_FRAME, data=error.frame))
                else:
                    found.append(self._garbled(attempt, error, decoder.looks_like_answer, now))
                    if self.attempt is not attempt:  # ended: the rest is late bytes
                        if decoder.leftover:
                            found.append(discarded(DiscardReason.LATE, len(decoder.leftover)))
                        return
                data = decoder.leftover
                decoder.reset()
                if data:
                    continue
                return
            break
        if frame is not None:
            trailing = decoder.leftover
            if trailing:
                found.append(discarded(DiscardReason.TRAILING_BYTES, len(trailing), slave))
            self.attempt = None  # ``end``, inline: once per transaction
            self.outstanding = 0
            # ``Finding(Found.COMPLETE, attempt, frame)`` without its Python-level ``__new__``:
            # once per transaction.
            found.append(tuple_new(Finding, (COMPLETE, attempt, frame, *_NO_DETAIL)))
            if trailing and unheard:  # another master's frame right behind the answer?
                found.append(Finding(Found.HEAR, data=trailing))
            return
        if unheard:
            attempt.heard += unheard  # heard by ``hear`` if they turn out not to be the answer
        if decoder.waits_for_silence:
            attempt.silence_at = now + self.silence

    def expire(self, now: float) -> list[Finding]:
        found: list[Finding] = []
        attempt = self.attempt
        if attempt is None:
            return found
        slave = attempt.request.slave
        if now >= attempt.silence_at:
            attempt.silence_at = INFINITY
            decoder = attempt.decoder
            try:
                frame = decoder.end_of_frame()
            except ResponseError as error:
                rest = decoder.leftover  # bytes behind noise: the answer may start there
                if error.kind in DISCARD_KINDS:
                    found.append(discarded(DiscardReason(error.kind), 1, slave))
                else:
                    found.append(self._garbled(attempt, error, decoder.looks_like_answer, now))
                decoder.reset()
                if rest and self.attempt is attempt:
                    self._decode(attempt, rest, now, found)
            else:
                self.end(attempt)
                found.append(Finding(Found.COMPLETE, attempt, frame))
        if self.attempt is attempt and now >= attempt.garbled_at:
            self._fail(attempt, found, 0)
        if self.attempt is attempt and now >= attempt.deadline:
            self._fail(attempt, found, attempt.decoder.buffered)
        return found

    def _fail(self, attempt: Attempt, found: list[Finding], incomplete: int) -> None:
        """The attempt ends unanswered: the bytes its decoder kept without a verdict were
        no answer (heard first), and ``incomplete`` bytes of half an answer are dropped."""
        self.end(attempt)
        slave = attempt.request.slave
        if attempt.heard:
            found.append(Finding(Found.HEAR, data=attempt.heard, slave=slave))
            attempt.heard = b""
        if incomplete:
            found.append(discarded(DiscardReason.INCOMPLETE, incomplete, slave))
        found.append(Finding(Found.FAILED, attempt, error=attempt.garbled))

    def _strip_echo(self, data: bytes) -> bytes:
        """Drop the echo of our own frame from ``data``; the rest is the line's."""
        data, self.echo_left = strip_echo(data, self.echo_left, self.echo_frame)
        return data
