"""Choosing and sending: which request goes next, and putting it on the wire.

The middle layer of ``LineCore``'s class body (see ``ends.py`` for the layering).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

from ..errors import ExceptionCode
from ..outcome import LineEvent, Outcome, SlaveState
from .fair_queue import Master
from .foreign import ANSWERED_BY_ECHO
from .late import proof_pdu
from .listening import Listening
from .records import (
    FRAME_CACHE_SIZE,
    INFINITY,
    LineRequest,
    Note,
    Transmit,
    no_reply,
    tuple_new,
)

#: The master a proof read is charged to when the request that lost its answer is gone.
PROOF_MASTER: Final = "the line's proof reads"


class Sending(Listening):
    """Which request goes next, and sending it (see the module doc)."""

    transmits: list[Transmit]
    quiet_since: float
    echo: bool
    encode: Callable[[int, bytes], bytes]
    _frames: dict[tuple[int, bytes], bytes] | None
    _send_at: float
    _wanting_since: float | None
    _noisy: bool
    _up: bool
    _paused: bool
    reconnecting: bool
    _gap: float

    def service(self, now: float) -> None:
        """Put the next requests on the wire while they may go now."""
        self._send_at = INFINITY
        wire = self.wire
        if (
            wire.outstanding >= wire.capacity
            or not self._up
            or not self.queue.queued
            or self._paused
            or self.reconnecting
        ):
            self._wanting_since = None
            return
        if wire.draining:  # a broadcast waits for the attempts outstanding
            if wire.outstanding:
                return
            wire.draining = False
        ready_at = self.quiet_since + self._gap
        if now < ready_at:
            self._send_at = ready_at
            if self._wanting_since is None:
                self._wanting_since = now
            elif now >= self._wanting_since + self.timing.noisy_after:
                self._go_noisy()
            return
        self._wanting_since = None
        while self.queue.queued and wire.outstanding < wire.capacity:
            picked = self._pick(now)
            if picked is None:
                return
            request, master, from_credit = picked
            if request.broadcast:
                wire.draining = False
                self._send_broadcast(request, master, now)
                self._send_at = self.quiet_since + self._gap  # after the turnaround
                return
            if request.cancelled and not request.wanted:
                self.sharing.close(request)
                self._deliver(request, b"", Outcome.DROPPED, -1.0)
                if master is not None:
                    self.queue.reschedule(master)
                continue
            self._send(request, master, now, from_credit)
            if wire.draining:
                return

    def _pick(self, now: float) -> tuple[LineRequest, Master | None, bool] | None:
        """The next request: a retry, the lane on credit, the fairest master, the lane free."""
        retries = self.retries
        if retries and not (
            self.foreign_pending and self.foreign.holds(retries[0].slave, retries[0].pdu, now)
        ):
            retry = retries.popleft()
            self.queue.count_waiting(retry, -1)
            return retry, None, False
        if self.late.wanted:
            proof = self._proof(now)
            if proof is not None:
                return proof
        lane = self.lane
        if lane.requests and lane.credit_now(now) >= 0.0:
            request = self._lane_candidate(now)
            if request is not None:
                return request, None, True
        picked = self.queue.pop(now, self.wire.first_eligible)
        if picked is not None:
            return picked[0], picked[1], False
        if self.late.wanted:  # the queue's requests were held: a proof lets them go
            waiting = self.queue.queued - len(self.lane.requests) - len(self.retries)
            proof = self._proof(now, free=waiting <= 0)
            if proof is not None:
                return proof
        if lane.requests:
            request = self._lane_candidate(now, free=True)
            if request is not None:
                return request, None, False
        return None

    def _proof(
        self, now: float, free: bool = False
    ) -> tuple[LineRequest, Master | None, bool] | None:
        """A proof read for a slave whose late-answer window holds a request back (``late``
        module doc): charged to the master whose request lost its answer, or to the lane's
        share when the slave is suspect or down (then when the share allows, or ``free``:
        nothing else waits, as the lane's own requests go)."""
        late = self.late
        for slave in sorted(late.wanted):
            window = late.windows.get(slave)
            if window is None or window.proof is not None or window.until != INFINITY:
                late.wanted.discard(slave)
                continue
            if self.wire.on_wire_to(slave):
                continue
            record = self.health.record(slave)
            owner = window.owner
            pdu = proof_pdu(window.signatures, record.known_read, owner.pdu if owner else None)
            if pdu is None:  # nothing known to read: the window closes after a time
                window.until = now + 2.0 * self.policy.max_timeout
                late.wanted.discard(slave)
                continue
            if self.foreign_pending and self.foreign.holds(slave, pdu, now):
                continue
            credit = record.state is not SlaveState.UP
            if credit and self.lane.credit_now(now) < 0.0:
                if not free:
                    continue  # the isolated slaves' share is spent: later
                credit = False
            proof = LineRequest(slave, pdu, owner.master if owner else PROOF_MASTER, no_reply)
            proof.proof = proof.single = True
            proof.enqueued_at = now
            window.proof = proof
            late.wanted.discard(slave)
            self.notes.append(Note(LineEvent.PROOF_READ, slave, f"function {pdu[0]}"))
            return proof, None, credit
        return None

    def _lane_candidate(self, now: float, free: bool = False) -> LineRequest | None:
        """The lane's next request. A first contact goes ``free`` (without the lane's
        credit) once it and the line have been quiet a while (``health`` module doc); the
        fairest one is waited for, so the first to ask when the line is quiet is not
        always the one that goes."""
        wire = self.wire
        order = self.order
        lane = self.lane
        masters = self.queue.masters

        def account(request: LineRequest) -> float:
            master = masters.get(request.master)
            return 1.0 + master.vtime if master is not None else 1.0  # isolated ones: 0

        best = lane.candidate(
            lambda r: wire.may_go(r, now) and not order.behind_broadcast(r),
            account if lane.first_contacts else None,
        )
        if best is None:
            return None
        if free and best.slave in lane.first_contacts:
            hold = self.timing.longest_attempt(best.slave, best.pdu[0])
            free_at = lane.free_at(self.quiet_since, best, hold)
            if now < free_at:
                self._send_at = free_at  # ``service`` keeps it when nothing goes now
                return None
        lane.take(best)
        self.queue.dequeued(self.queue.masters.get(best.master), best)
        return best

    def _send(self, request: LineRequest, master: Master | None, now: float, credit: bool) -> None:
        retry = request.attempts > 0
        request.attempts += 1
        if not request.sent:
            request.sent = True
            self.sharing.close(request)
        frame = self.wire.start(request, master, now, credit)
        if request.pdu[0] in ANSWERED_BY_ECHO and self.framing.transaction_ids is None:
            self.foreign.sent_echoed(request.slave, request.pdu, now)
        stats = self.stats
        stats.frames_sent += 1
        stats.bytes_written += len(frame)
        if retry:
            self.notes.append(Note(LineEvent.RETRY, request.slave))
        self.transmits.append(  # a proof read has no queue wait to observe: as a retry
            tuple_new(Transmit, (frame, request, now - request.enqueued_at, retry or request.proof))
        )

    def frame(self, slave: int, pdu: bytes) -> bytes:
        """The request frame for ``pdu`` to ``slave``, encoded once per distinct request."""
        frames = self._frames
        if frames is None:
            return self.encode(slave, pdu)
        key = (slave, pdu)
        frame = frames.get(key)
        if frame is None:
            frame = self.encode(slave, pdu)
            if len(frames) >= FRAME_CACHE_SIZE:
                frames.clear()  # a bound, not an LRU: polling refills it with what is used
            frames[key] = frame
        return frame

    def _send_broadcast(self, request: LineRequest, master: Master | None, now: float) -> None:
        frame = self.frame(0, request.pdu)
        transmit_time = len(frame) * self.char_time
        self.quiet_since = now + transmit_time + self.policy.broadcast_turnaround
        self.stats.frames_sent += 1
        self.stats.bytes_written += len(frame)
        self.sharing.cache.clear()  # what was read while it waited in the queue is stale now
        self.wire.expect_echo(frame)
        self.transmits.append(Transmit(frame, request, now - request.enqueued_at, False))
        self._deliver(request, b"", Outcome.BROADCAST, -1.0)
        if master is not None:
            self.queue.charge_ahead(master, self.quiet_since - now)
            self.queue.reschedule(master)

    def _go_noisy(self) -> None:
        self._noisy = True
        self._wanting_since = None
        waited = self.timing.noisy_after
        self.notes.append(Note(LineEvent.LINE_NOISY, 0, f"no gap for {waited:g} s"))
        self._fail_all(ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)

    def _fail_all(self, code: ExceptionCode, outcome: Outcome) -> None:
        for request in self.take_queued():
            self._answer(request, code, outcome)

    def take_queued(self) -> list[LineRequest]:
        """Remove every waiting request unanswered (a reload moves them to a reopened line),
        in the order they were submitted, each read that joined one of them a request of
        its own again, with no attempts made. Requests whose master left are answered
        ``DROPPED`` here, as ``cancel`` would have: nobody waits for them."""
        taken = list(self.retries)
        for request in taken:
            self.wire.forget(request)
        self.retries.clear()
        taken.extend(self.queue.take_all())
        taken.extend(self.lane.requests.values())
        self.lane.requests.clear()
        self.sharing.forget_open()
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
