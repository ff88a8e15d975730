"""The wire as a strategy the machine holds: which bytes answer which attempt.

Theory of operation. ``Wire`` is what the machine asks about the attempts on the wire
and tells to start one; the wire decodes what comes back and calls the machine's
transitions (``complete``, ``garbled``, ``fail``, ``discard``...). ``SerialWire`` is a
shared medium with one attempt at a time: its answers are known by their shape
(unit, function, length, echo), the line must be quiet for the gap before each frame,
an adapter may echo our own frame, and a lost answer needs a late-answer window.
``flights.FlightWire`` keeps several attempts outstanding on a connection whose
answers carry their transaction ids.
"""

from __future__ import annotations

from collections.abc import Hashable
from typing import TYPE_CHECKING

from .. import pdu as fc
from ..echo import strip_echo
from ..errors import ResponseError
from ..outcome import DiscardReason
from .fair_queue import Master
from .records import DISCARD_KINDS, FRAME_CACHE_SIZE, INFINITY, Attempt, LineRequest
from .response_timing import DECAY_EVERY, EVIDENCE

if TYPE_CHECKING:
    from .machine import LineCore


class Wire:
    """The strategy's questions and commands; the defaults suit a wire without them."""

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

    def bind(self, line: LineCore) -> None:
        """The machine this wire serves (it calls its transitions)."""
        self.line = line

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

    def start(self, request: LineRequest, master: Master | None, now: float, credit: bool) -> bytes:
        """Start an attempt of ``request``: its frame, for the machine to transmit."""
        raise NotImplementedError

    def end(self, attempt: Attempt) -> None:
        """``attempt`` failed (an answered one the wire ends itself)."""
        raise NotImplementedError

    def take_all(self) -> list[Attempt]:
        """Give up every attempt on the wire."""
        raise NotImplementedError

    def receive(self, data: bytes, now: float) -> None:
        raise NotImplementedError

    def expire(self, now: float) -> None:
        """Time passed: end the attempts whose time is up."""
        raise NotImplementedError

    def opened(self) -> None:
        """A new port or connection."""

    def lost(self) -> None:
        """The port or connection went away (its attempts were answered)."""

    def expect_echo(self, frame: bytes) -> None:
        """``frame`` was sent outside an attempt (a broadcast)."""

    def joined(self, request: LineRequest) -> None:
        """``request`` joined another master's read."""

    def released(self, request: LineRequest) -> None:
        """``request`` (and the reads that joined it) is about to be answered."""

    def forget(self, request: LineRequest) -> None:
        """``request`` leaves this line unanswered (a reload takes it)."""

    def may_cache(self, attempt: Attempt) -> bool:
        """True when the answer to ``attempt`` is no older than any change submitted."""
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
        line = self.line
        late = line.late
        blocked: dict[int, bool] | None = None  # slave -> only safe requests held so far
        for request in master.queue:
            if request.broadcast:
                if blocked or line.order.broadcast_held(master.key, request):
                    return None
                return request
            slave = request.slave
            safe = fc.is_safe_to_retry(request.pdu) if blocked else True
            if blocked is not None and slave in blocked and not (blocked[slave] and safe):
                blocked[slave] = False
                continue
            held = bool(late.windows) and late.holds(request, now)
            if line.foreign_pending and not held:
                held = line.foreign.holds(slave, request.pdu, now)
            if (
                not held
                and (line.sharing.joined or line.lane.requests)
                and request.pdu[0] not in fc.READ_FUNCTIONS
            ):
                held = line.order.held_by_joined(master.key, request)
            if not held:
                return request
            if blocked is None:
                blocked = {}
                safe = fc.is_safe_to_retry(request.pdu)
            blocked[slave] = blocked.get(slave, True) and safe
        return None

    def may_go(self, request: LineRequest, now: float) -> bool:
        line = self.line
        if line.foreign_pending and line.foreign.holds(request.slave, request.pdu, now):
            return False
        return not line.late.holds(request, now)

    def start(self, request: LineRequest, master: Master | None, now: float, credit: bool) -> bytes:
        line = self.line
        slave = request.slave
        pdu = request.pdu
        # ``line.frame``, inline: once per transaction (a poll of many addresses misses).
        frames = line._frames
        if frames is None:
            frame = line.encode(slave, pdu)
        else:
            key = (slave, pdu)
            cached = frames.get(key)
            if cached is None:
                if len(frames) >= FRAME_CACHE_SIZE:
                    frames.clear()  # a bound, not an LRU: polling refills it with what is used
                cached = frames[key] = line.encode(slave, pdu)
            frame = cached
        sent_by = now + len(frame) * line.char_time
        timing = line.timing
        # ``timing.deadline``, inline for a request heard before: once per transaction.
        predicted = timing.predicted.get(pdu) if timing.plain else None
        state = None
        if predicted is not None and request.attempts == 1:
            state = timing.peaks.get(slave << 8 | pdu[0])  # [peak, attempts, bound]
        if predicted is None or state is None:
            deadline = timing.deadline(slave, pdu, request.attempts, sent_by)
            expected = timing.expected_at
            above = timing.learn_above
        else:
            expected = sent_by + predicted
            deadline = expected + state[2]
            above = expected + state[0] if state[3] >= EVIDENCE else -INFINITY
            state[1] += 1.0
            if state[1] >= DECAY_EVERY:
                timing.decay(slave << 8 | pdu[0], state)
        self.attempt = Attempt(
            request, line.new_decoder(slave, pdu), now, deadline, credit, expected, above
        )
        self.outstanding = 1
        line.quiet_since = sent_by
        if line.echo:
            self.echo_left = self.echo_frame = frame
        return frame

    def end(self, attempt: Attempt) -> None:
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
        if self.line.echo:
            self.echo_left = self.echo_frame = frame

    def receive(self, data: bytes, now: float) -> None:
        line = self.line
        if now > line.quiet_since:
            line.quiet_since = now
        if self.echo_left:
            data = self._strip_echo(data)
            if not data:
                return
        attempt = self.attempt
        if attempt is None:
            line.discard(DiscardReason.LATE, len(data))
            line.hear(data, now)  # another master's frames, or its slaves' answers
            if line.late.windows:
                line.late_bytes(data, now)
            line.service(now)  # a foreign request answered, or a window closed
            return
        if attempt.garbled is not None:
            attempt.garbled_at = now + line.garbled_wait  # the line is not quiet yet
        self._decode(attempt, data, now)

    def _decode(self, attempt: Attempt, data: bytes, now: float) -> None:
        """Feed ``data`` to the attempt's decoder: complete it, skip what is not its answer,
        or note that it was garbled."""
        line = self.line
        decoder = attempt.decoder
        unheard = data  # what the decoder has that ``line.hear`` has not (after ``heard``)
        while True:
            try:
                frame = decoder.feed(data)
            except ResponseError as error:
                if unheard:  # not the answer (or not only): perhaps another master's frames
                    master = line.hear(attempt.heard + unheard, now, True, attempt.request.slave)
                    attempt.heard = unheard = b""
                    if master:  # no damaged answer: the answer may follow it
                        decoder.reset()
                        data = unheard = line.foreign.take_unframed()
                        if data:
                            continue
                        return
                if error.kind in DISCARD_KINDS:
                    # Another unit's frame, a late answer to an earlier request, or noise
                    # in front of the answer: drop it and keep decoding what followed it.
                    line.discard(DiscardReason(error.kind), 1, attempt.request.slave)
                    if line.late.windows and error.frame:
                        line.late_frame(error.frame, now)
                else:
                    line.garbled(attempt, error, decoder.looks_like_answer, now)
                    if self.attempt is not attempt:  # failed: the rest is late bytes
                        if decoder.leftover:
                            line.discard(DiscardReason.LATE, len(decoder.leftover))
                        line.service(now)
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
                line.discard(DiscardReason.TRAILING_BYTES, len(trailing), attempt.request.slave)
            self.attempt = None  # ``end``, inline: once per transaction
            self.outstanding = 0
            line.complete(attempt, frame, now)
            if trailing and unheard:
                line.hear(trailing, now)  # another master's frame right behind the answer?
            line.service(now)
            return
        if unheard:
            attempt.heard += unheard  # heard by ``line.hear`` if they turn out not to be the answer
        if decoder.waits_for_silence:
            attempt.silence_at = now + line.silence

    def expire(self, now: float) -> None:
        attempt = self.attempt
        if attempt is None:
            return
        line = self.line
        if now >= attempt.silence_at:
            attempt.silence_at = INFINITY
            decoder = attempt.decoder
            try:
                frame = decoder.end_of_frame()
            except ResponseError as error:
                rest = decoder.leftover  # bytes behind noise: the answer may start there
                if error.kind in DISCARD_KINDS:
                    line.discard(DiscardReason(error.kind), 1, attempt.request.slave)
                else:
                    line.garbled(attempt, error, decoder.looks_like_answer, now)
                decoder.reset()
                if rest and self.attempt is attempt:
                    self._decode(attempt, rest, now)
            else:
                self.end(attempt)
                line.complete(attempt, frame, now)
        if self.attempt is attempt and now >= attempt.garbled_at:
            self._unheard(attempt, now)
            line.fail(attempt, attempt.garbled, now)
        if self.attempt is attempt and now >= attempt.deadline:
            self._unheard(attempt, now)
            if attempt.decoder.buffered:
                line.discard(
                    DiscardReason.INCOMPLETE, attempt.decoder.buffered, attempt.request.slave
                )
            line.fail(attempt, attempt.garbled, now)

    def _unheard(self, attempt: Attempt, now: float) -> None:
        """The attempt fails: the bytes its decoder kept without a verdict were no answer."""
        if attempt.heard:
            self.line.hear(attempt.heard, now, asked=attempt.request.slave)
            attempt.heard = b""

    def _strip_echo(self, data: bytes) -> bytes:
        """Drop the echo of our own frame from ``data``; the rest is the line's."""
        data, self.echo_left = strip_echo(data, self.echo_left, self.echo_frame)
        return data
