"""The machine's transitions at the end of an attempt, and the answers it delivers.

``LineCore`` (``machine.py``) is one state machine whose class body is written in four
layers, each under 400 lines: this one (an attempt ends: the request, the slave's
health, the late-answer window, the accounts; every delivery), ``listening.py`` (frames
heard that no attempt took: other masters), ``sending.py`` (which request goes next,
sending it) and ``machine.py`` (the masters' side, the port, the reload). The layers
are not variants: nothing is overridden, and only the machine is ever built. The wire
strategy (``wire.py``, ``flights.py``) calls ``complete``, ``garbled``, ``fail``,
``discard``, ``alive``, ``late_bytes``, ``late_frame`` and ``hear``.
"""

from __future__ import annotations

from collections import deque

from .. import pdu as fc
from ..errors import ExceptionCode, ResponseError
from ..framing import Framing
from ..outcome import DiscardReason, LineEvent, Outcome, ReconnectReason, SlaveState
from ..rtu import RtuFrame
from .fair_queue import FairQueue
from .foreign import ForeignMasters, ForeignRequest
from .health import FIRST_CONTACT_QUIET_S, ProbeLane, SlaveHealth, SlaveRecord
from .late import MAX_INCONCLUSIVE, PROOF_FUNCTIONS, LateWindows
from .order import OrderRules
from .records import (
    BAD_CHECK,
    INFINITY,
    SHARED_ANSWER,
    Attempt,
    Delivery,
    LinePolicy,
    LineRequest,
    LineStats,
    Note,
    tuple_new,
)
from .response_timing import ResponseTiming
from .sharing import ReadSharing
from .wire import Wire


class AttemptEnds:
    """The line's state, and what the end of an attempt does to it (see the module doc)."""

    policy: LinePolicy
    framing: Framing
    stats: LineStats
    deliveries: list[Delivery]
    notes: list[Note]
    queue: FairQueue
    health: SlaveHealth
    lane: ProbeLane
    late: LateWindows
    sharing: ReadSharing
    order: OrderRules
    wire: Wire
    retries: deque[LineRequest]
    garbled_wait: float
    _gap: float
    timing: ResponseTiming
    foreign: ForeignMasters
    #: ``foreign.pending`` itself (the same dict), one attribute away on the answer's path.
    foreign_pending: dict[int, list[ForeignRequest]]
    answered_at: float | None
    _stopping: bool
    _up: bool
    reconnecting: bool
    _heard_on_connection: bool
    _silent_misses: int
    _silent_streak: dict[int, tuple[SlaveState, int]]

    def complete(self, attempt: Attempt, frame: RtuFrame, now: float) -> None:
        """The slave answered the request on the wire (the wire has ended ``attempt``)."""
        request = attempt.request
        if self.foreign_pending and self.foreign.claims(request.slave, request.pdu, frame.pdu, now):
            self._not_ours(attempt, now)
            return
        wire = now - attempt.sent_at
        slave = request.slave
        function = request.pdu[0]
        self.stats.frames_received += 1
        self.answered_at = now  # the last intact frame heard, with ``foreign``'s
        record = self.health.slaves.get(slave)  # ``health.record``, inline: once per answer
        if record is None:
            record = self.health.record(slave)
        record.answered.add(function)
        response = frame.pdu
        if function in PROOF_FUNCTIONS and not response[0] & fc.EXCEPTION_FLAG:
            record.known_read = request.pdu
        if record.state is SlaveState.UP:
            record.misses = 0  # ``alive``, for a slave that was up
        else:
            self.alive(slave)
        if now > attempt.learn_above:  # slower than its slave's peak so far, or a first
            self.timing.answered(slave, function, now - attempt.expected_at)
        if self.late.windows:
            window = self.late.windows.get(slave)
            if window is not None and window.owner is request and window.sent_at is not None:
                # Perhaps the lost attempt's answer: the slave may be that slow.
                self.timing.late(slave, function, now - window.sent_at)
            ends = self.late.ends_on(slave, request, response)
            if request.proof and ends is not True and slave in self.late.windows:
                ends = self._proof_ended(slave, response, now)
            if ends is True:
                self.late.close(slave)  # it answered something after the loss: done
            elif ends is False:
                # An exception cannot be told from the lost request's: this one's own
                # answer may be the one still on its way now.
                self._open_window(slave, record, request, now, attempt.sent_at)
        self._charge(attempt, wire, now)
        if response[0] & fc.EXCEPTION_FLAG:
            outcome = Outcome.SLAVE_EXCEPTION
        elif function in fc.READ_FUNCTIONS:
            if self.policy.cache:
                self._store_cache(attempt, response, now)
            outcome = Outcome.OK
        else:
            outcome = Outcome.OK
        self._deliver(request, response, outcome, wire)

    def _proof_ended(self, slave: int, response: bytes, now: float) -> bool | None:
        """A proof read was answered by an exception: proof when no awaited answer has its
        function (the lost answer would have come first), else nothing proved; after
        ``MAX_INCONCLUSIVE`` of those the window closes after a time instead."""
        window = self.late.windows[slave]
        window.proof = None
        if (response[0] & 0x7F) not in {signature[0] for signature in window.signatures}:
            return True
        window.inconclusive += 1
        if window.inconclusive >= MAX_INCONCLUSIVE:
            window.until = now + 2.0 * self.policy.max_timeout
        return None

    def _not_ours(self, attempt: Attempt, now: float) -> None:
        """An answer a foreign master's pending request may own (``foreign``): not delivered.
        The attempt failed, heard: retried when safe, else 0x0B; its own answer may still
        come (the late-answer window)."""
        slave = attempt.request.slave
        detail = "an answer another master's request may own"
        self.notes.append(Note(LineEvent.SHARED_ANSWER, slave, detail))
        self.fail(attempt, ResponseError(SHARED_ANSWER, detail), now)

    def garbled(self, attempt: Attempt, error: ResponseError, damaged: bool, now: float) -> None:
        """A garbled frame: fail the attempt at once, or listen a little longer first.

        A frame with the awaited unit, function and length is the answer itself,
        damaged: no other answer is coming, the attempt fails at once. Anything else
        may be noise in front of the real answer: the attempt fails only after the
        line stayed quiet for ``garbled_wait``, and a valid answer meanwhile is taken.
        """
        slave = attempt.request.slave
        if error.kind == BAD_CHECK:
            self.notes.append(Note(LineEvent.CRC_ERROR, slave, error.reason))
        else:
            self.discard(DiscardReason(error.kind), 1, slave)
        attempt.garbled = error
        if damaged:
            self.fail(attempt, error, now, damaged=True)
        else:
            attempt.garbled_at = now + self.garbled_wait

    def fail(
        self, attempt: Attempt, error: ResponseError | None, now: float, damaged: bool = False
    ) -> None:
        """An attempt ended without an answer: window, isolation, then retry or 0x0B."""
        self.wire.end(attempt)
        request = attempt.request
        slave = request.slave
        wire = now - attempt.sent_at
        record = self.health.record(slave)
        if not damaged:
            self._open_window(slave, record, request, now, attempt.sent_at)
        before = record.state
        silent = False
        if error is None:
            timeout = self.timing.wait(slave, request.pdu[0], request.attempts)
            self.notes.append(Note(LineEvent.TIMEOUT, slave, f"no answer within {timeout:g} s"))
            silent = self._heard_on_connection and self.policy.networked
            if silent and self.policy.reconnect_after:
                self._silent_misses += 1
                self._silent_streak.setdefault(slave, (record.state, record.misses))
            state = self.health.count_timeout(record, request.pdu[0], now, self.policy)
            if state is not None:
                self._set_state(slave, record, state)
        elif error.kind != BAD_CHECK and error.kind != SHARED_ANSWER:  # noted already
            self.notes.append(Note(LineEvent.GARBLED, slave, error.reason))
        # The loss that made it suspect is paid from the lane's share (by ``_charge`` when
        # it was sent on that share).
        if (
            before is SlaveState.UP
            and record.state is not SlaveState.UP
            and not attempt.from_credit
        ):
            self.lane.spend(wire + self._gap, now)
        self.lane.last_loss = now
        self._charge(attempt, wire, now)
        self._retry_or_answer(request, record, now, heard=error is not None)
        if before is not record.state:
            keep = (
                1 if record.state is SlaveState.SUSPECT and slave not in self.lane.requests else 0
            )
            self._isolate(slave, keep)
        if (
            not record.answered
            and record.state is not SlaveState.UP
            and self.timing.first_contact(slave)
        ):
            self._absent(slave, now)
        reconnect_after = self.policy.reconnect_after
        if silent and reconnect_after and self._silent_misses >= reconnect_after:
            self._reconnect(ReconnectReason.SILENT, self._silent_misses)

    def _reconnect(self, reason: ReconnectReason, missed: int = 0) -> None:
        """Close the connection and open it again (the driver does, on the note): reads on
        the wire go again on the new connection, other attempts are answered 0x0B, the queue
        waits. The timeouts of a silent connection do not count against its slaves."""
        if self.reconnecting or not self._up:
            return
        self.reconnecting = True
        self._heard_on_connection = False
        self._silent_misses = 0
        for slave, (state, misses) in self._silent_streak.items():
            record = self.health.record(slave)
            if state is SlaveState.UP and record.state is not SlaveState.UP:
                self.alive(slave)
            record.misses = misses
        self._silent_streak.clear()
        for attempt in reversed(self.wire.take_all()):
            request = attempt.request
            if fc.is_safe_to_retry(request.pdu) and request.wanted and not request.proof:
                request.single = False
                self.retries.appendleft(request)
                self.queue.count_waiting(request, +1)
            else:
                self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
        self.notes.append(Note(LineEvent.RECONNECT, 0, reason, missed))

    def _absent(self, slave: int, now: float) -> None:
        """``slave`` missed its first contact: the first contacts still queued for other
        slaves never heard from become probes (``health`` module doc)."""
        absent = self.health.absent
        if slave in absent:
            return
        absent.add(slave)
        lane = self.lane
        health = self.health
        wire = self.wire

        def unheard(other: int) -> bool:
            return (
                health.unheard(other)
                and self.timing.first_contact(other)
                and not wire.on_wire_to(other)
            )

        for request in self.queue.first_contacts(unheard, lane.requests):
            # waiting there as long as its first contact would have waited for its answer
            self._lane_put(request, request.enqueued_at, first_contact=True)

    def _first_contact(self, request: LineRequest, now: float) -> bool:
        """A request for a slave never heard from while others are absent: a probe in
        the lane, or 0x0B at once when the slave's first contact already waits there;
        ``False`` (queue it as usual) while its first contact is on the wire."""
        slave = request.slave
        if self.wire.on_wire_to(slave):
            return False
        master = self.queue.masters.get(request.master)
        if master is not None and any(other.slave == slave for other in master.queue):
            return False  # behind its master's earlier requests to that slave, in order
        if slave in self.lane.requests:  # even if its timing was learned meanwhile (heard
            # answering another master): queued, this request would pass the one waiting
            self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
            return True
        if not self.timing.first_contact(slave):
            return False
        if request.pdu[0] not in fc.READ_FUNCTIONS:
            self.sharing.change(slave)
        self._lane_put(request, now, first_contact=True)
        return True

    def _retry_or_answer(
        self, request: LineRequest, record: SlaveRecord, now: float, heard: bool
    ) -> None:
        """Only requests without side effects go again, and not to a down slave, nor to a
        slave never heard from that stayed silent (no answer seen: the retry's doubled wait
        buys nothing; a damaged answer (``heard``) shows the slave is there)."""
        policy = self.policy
        retryable = (
            not self._stopping
            and not request.single
            and (heard or bool(record.answered) or not self.timing.first_contact(request.slave))
            and request.attempts <= policy.retries
            and request.wanted
            and (policy.retry_unsafe or fc.is_safe_to_retry(request.pdu))
            and record.state is not SlaveState.DOWN
        )
        if retryable and record.state is SlaveState.UP:
            self.retries.append(request)
            self.queue.count_waiting(request, +1)
        elif retryable and request.slave not in self.lane.requests:
            self._lane_put(request, now)
        else:
            self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)

    def _isolate(self, slave: int, keep: int) -> None:
        """Answer the slave's waiting requests 0x0B, keeping the oldest ``keep`` in the lane."""
        lane_request = self.lane.requests.get(slave)
        if lane_request is not None and self.health.slaves[slave].state is SlaveState.DOWN:
            self._lane_remove(lane_request)
            self._answer(lane_request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
        for index, request in enumerate(self.queue.isolated(slave)):
            if index < keep:
                self._lane_put(request, request.enqueued_at)
            else:
                self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)

    def _charge(self, attempt: Attempt, wire: float, now: float) -> None:
        """Account the line time to the master who used it (or to the isolated share): the
        attempt's time on the wire and the silence the line keeps after it. Without the
        silence an answer on a fast port would cost next to nothing, and a master that paid
        for one timeout would wait behind thousands of cheap transactions."""
        wire += self._gap
        queue = self.queue
        master = queue.masters.get(attempt.request.master)
        queue.ended(master, wire, now)
        if attempt.from_credit:
            self.lane.spend(wire, now)
        elif master is not None:
            queue.charge(master, wire, attempt.charged)
        if master is not None and (master.gone or (master.queue and master.heap_seq < 0)):
            queue.reschedule(master)  # back in the fair order, or forgotten

    def alive(self, slave: int) -> None:
        """The slave answered: no missed answers in a row, and back in the fair order."""
        record = self.health.record(slave)
        record.misses = 0
        if record.state is not SlaveState.UP:
            absent = self.health.absent
            was_absent = slave in absent
            absent.discard(slave)
            self._set_state(slave, record, SlaveState.UP)
            waiting = self.lane.requests.get(slave)
            if waiting is not None:
                self._lane_remove(waiting)
                self._queue_at_front(waiting)
            if was_absent and not absent:
                self._release_first_contacts()

    def _release_first_contacts(self) -> None:
        """No slave is absent any more: the first contacts that waited in the lane because
        one was go back to the queue, so that their masters' later requests to those
        slaves, queued as usual from now on, go after them, not before."""
        lane = self.lane
        waiting = [lane.requests[slave] for slave in lane.first_contacts if slave in lane.requests]
        for request in sorted(waiting, key=lambda request: request.order, reverse=True):
            self._lane_remove(request)
            self._queue_at_front(request)

    def late_bytes(self, data: bytes, now: float) -> None:
        """Bytes while nothing is on the wire: a lost answer shows its slave alive, slow."""
        lost = self.late.lost_attempts()
        for slave in self.late.watch(data):
            self._late_answer(slave, lost, now)

    def late_frame(self, frame: bytes, now: float) -> None:
        """An intact frame the attempt on the wire discarded: is it a lost answer?"""
        lost = self.late.lost_attempts()
        slave = self.late.is_lost_answer(frame)
        if slave is not None:
            self._late_answer(slave, lost, now)

    def _late_answer(self, slave: int, lost: dict[int, tuple[float, int]], now: float) -> None:
        """A lost answer came: the slave is alive, and as slow as that (the bound widens)."""
        sent = lost.get(slave)
        if sent is not None and self.timing.learn:
            self.timing.late(slave, sent[1], now - sent[0])
        self.alive(slave)

    def _open_window(
        self,
        slave: int,
        record: SlaveRecord,
        request: LineRequest,
        now: float,
        sent_at: float | None = None,
    ) -> None:
        """The slave's answer to ``request`` may still come: nothing that could be taken for
        it goes to this slave until the window ends or the slave shows it is done. A line
        whose answers carry transaction ids needs no window (the id names the answer)."""
        if not self.wire.quiet_line or self.framing.transaction_ids is not None:
            return
        window = self.timing.late_window()
        self.late.open(slave, request, now + window, sent_at)
        detail = "until proof" if window == INFINITY else f"{window:g} s"
        self.notes.append(Note(LineEvent.LATE_WINDOW, slave, detail))

    def _set_state(self, slave: int, record: SlaveRecord, state: SlaveState) -> None:
        record.state = state
        if state is SlaveState.UP:
            record.misses = 0
        self.notes.append(Note(LineEvent.SLAVE_STATE, slave, state=state, amount=record.misses))

    def _store_cache(self, attempt: Attempt, response: bytes, now: float) -> None:
        request = attempt.request
        rules = self.policy.cache
        if not rules or not self.wire.may_cache(attempt):
            return  # a write was submitted after this read went: its answer may be older
        if self.order.change_waits_for(request.slave):
            return  # the answer is older than a write still to run: kept, it would be stale
        self.sharing.store(request, response, now, rules)

    def _lane_put(self, request: LineRequest, now: float, first_contact: bool = False) -> None:
        """Wait in the isolated slaves' lane: one attempt, answered 0x0B if not sent in time."""
        slave, function = request.slave, request.pdu[0]
        if first_contact:  # there at the next free slot: the quiet before it, then the probe
            hold = self.timing.longest_attempt(slave, function)
            deadline = now + hold + max(hold, FIRST_CONTACT_QUIET_S)
        else:
            deadline = now + self.timing.wait(slave, function, 1)
        self.lane.put(request, deadline, first_contact)
        self.queue.master(request.master)
        self.queue.count_waiting(request, +1)

    def _lane_remove(self, request: LineRequest) -> None:
        self.lane.remove(request)
        self.queue.dequeued(self.queue.masters.get(request.master), request)

    def _queue_at_front(self, request: LineRequest) -> None:
        if request.followers:  # still waited for by the reads that joined it
            self.sharing.joined[request] = None
        self.queue.queue_at_front(request)

    def discard(self, reason: DiscardReason, count: int, slave: int = 0) -> None:
        self.notes.append(Note(LineEvent.DISCARDED, slave, reason, count))
        if reason is DiscardReason.BAD_HEADER:  # a Modbus TCP stream out of step
            self._reconnect(ReconnectReason.OUT_OF_STEP)

    def _answer(self, request: LineRequest, code: ExceptionCode, outcome: Outcome) -> None:
        self.sharing.close(request)
        self._deliver(request, fc.exception_pdu(request.pdu[0], code), outcome, -1.0)

    def _deliver(self, request: LineRequest, pdu: bytes, outcome: Outcome, wire: float) -> None:
        """Deliver exactly once, to ``request`` and every read that joined it (a proof
        read's answer goes to nobody)."""
        if self.wire.orders_outstanding:
            self.wire.released(request)
        if request.proof:
            request.answered = True
            return
        deliveries = self.deliveries
        if request.followers:
            self.sharing.joined.pop(request, None)
        if not request.answered:
            request.answered = True
            deliveries.append(tuple_new(Delivery, (request, pdu, outcome, wire)))
        for follower in request.followers:
            if not follower.answered:
                follower.answered = True
                deliveries.append(Delivery(follower, pdu, outcome, -1.0))
        request.followers.clear()
