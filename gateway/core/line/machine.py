"""The line's one state machine: every transition of a request, every action emitted.

Rule 1 (h11's): everything that changes what becomes of a request lives in this file,
in ``LineCore``. The parts (``fair_queue``, ``health``, ``late``, ``sharing``, ``order``,
``response_timing``, ``foreign``, ``polling``) keep state and answer questions; the wire
strategy (``wire.SerialWire``, one attempt at a time; ``flights.FlightWire``, attempts by
transaction id) decodes and returns what it found (``wire.Finding``): which bytes answer
which attempt. It never calls the machine; the machine applies each finding
(``_apply``). Only ``LineCore`` appends to ``transmits``, ``deliveries`` and ``notes``.
Theory of operation and invariants: the package's docstring (``gateway.core.line``).

The transitions, by entry point (``now`` in every one; ``get_timer`` says when to call
``handle_timer`` next):

==========================  ===========================================================
entry point                 what a request can become
==========================  ===========================================================
``submit``                  queued (fair order), joined to an identical read, answered
                            from the cache, put in the isolated slaves' lane (suspect,
                            down or a first contact beside absent slaves), or answered
                            at once: 0x0A (down, stopping, full), 0x06 (the master's
                            queue), 0x0B (noisy line, isolated slave); or sent at once
                            when the serial line is free, nothing waits and nothing
                            holds it (as ``service`` would send it, the fair accounts
                            kept as if it had queued: ``FairQueue.went_at_once``)
``service``                 sent (a retry, a proof read, the lane on its share, the
                            fairest master, the lane free), broadcast, or dropped
                            (nobody waits for it)
``receive`` (the wire's     answered (``complete``), garbled (``garbled`` then ``fail``),
findings, ``_apply``)       another master's frame heard (``hear``), a lost answer
                            recognised (``late_bytes``, ``late_frame``, by its id)
``handle_timer``            an attempt timed out (``fail``: window, isolation, retry or
                            0x0B, maybe a reconnect), a lane request or a queued one
                            overdue (0x0B), windows and foreign requests expired
``cancel``                  dropped: every master that waited for it left
``port_opened``/``lost``    the line taken up (after a reconnect too) or lost: 0x0A
``pause``/``resume``        nothing sent meanwhile (a reload, a standby)
``stop``/``abandon``        0x0A for what waits, then for what is on the wire
``take_queued``/``take_over``  handed to the line that replaces this one
``reconfigure``             new settings; isolation off returns the lane to the queue
==========================  ===========================================================
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable, Iterable
from typing import Final

from .. import pdu as fc
from ..errors import ExceptionCode, ResponseError
from ..framing import RTU, Framing, LineKind
from ..outcome import DiscardReason, LineEvent, Outcome, ReconnectReason, SlaveState
from ..rtu import RtuFrame
from ..timing import character_time
from .fair_queue import TYPICAL_WEIGHT, FairQueue, Master
from .foreign import ANSWERED_BY_ECHO, ForeignMasters, ForeignRequest, Heard, HeardKind, Own
from .health import FIRST_CONTACT_QUIET_S, ProbeLane, SlaveHealth, SlaveRecord
from .late import MAX_INCONCLUSIVE, PROOF_FUNCTIONS, LateWindows, proof_pdu
from .order import OrderRules
from .polling import POLLER, PollBlock, PollPlan
from .records import (
    BAD_CHECK,
    FRAME_CACHE_SIZE,
    INFINITY,
    SHARED_ANSWER,
    Attempt,
    Delivery,
    Handover,
    LinePolicy,
    LineRequest,
    LineStats,
    Note,
    Transmit,
    may_change,
    no_reply,
    tuple_new,
)
from .response_timing import DECAY_EVERY, EVIDENCE, ResponseTiming
from .sharing import ReadSharing
from .wire import COMPLETE, Finding, Found, SerialWire, Wire, WireParts

# Looked up once, not at each transaction (an enum member is a class attribute lookup).
UP: Final = SlaveState.UP
OK: Final = Outcome.OK

#: The master a proof read is charged to when the request that lost its answer is gone.
PROOF_MASTER: Final = "the line's proof reads"


class LineCore:
    """One line's decisions; see the package docstring."""

    def __init__(
        self,
        policy: LinePolicy,
        now: float,
        stats: LineStats | None = None,
        framing: Framing = RTU,
        wire: Wire | None = None,
    ) -> None:
        self.stats = stats if stats is not None else LineStats()
        self.framing = framing
        self.encode = framing.encode  # bound once: for RTU, encode_rtu itself
        self.new_decoder = framing.decoder  # for RTU, the RtuResponseDecoder class
        #: Request frames by (slave, PDU): masters poll the same requests over and over, and
        #: a frame is a pure function of them (not for MBAP: its frames carry a fresh id).
        self._frames: dict[tuple[int, bytes], bytes] | None = (
            {} if framing.transaction_ids is None else None
        )
        self.transmits: list[Transmit] = []
        self.deliveries: list[Delivery] = []
        self.notes: list[Note] = []
        self.queue = FairQueue(self.stats)
        self.health = SlaveHealth()
        self.lane = ProbeLane(now)
        self.late = LateWindows(self.new_decoder)
        self.sharing = ReadSharing()
        self.retries: deque[LineRequest] = deque()  # failed attempts due again, in order
        self.plan = PollPlan(policy.polls, now)  # agent mode's blocks (``polling``)
        self.polls: deque[LineRequest] = deque()  # the plan's polls that are due, in order
        #: The last transaction was a poll that went before masters' waiting requests: the
        #: next goes to a master (a plan that needs the whole line cannot take it).
        self._poll_went_first = False
        #: The last request picked came from the lane: a probe, which may have held the line
        #: for a timeout; the lane's share does not send another before a waiting master's.
        self._lane_went_last = False
        self.wire: Wire = wire if wire is not None else SerialWire()
        self.order = OrderRules(self.queue, self.lane, self.sharing, self.retries, self.wire)
        self.max_in_flight = self.wire.capacity
        self.timing = ResponseTiming(policy, framing, 0.0)
        self.foreign = ForeignMasters(ascii=framing.kind is LineKind.ASCII)
        self.foreign_pending = self.foreign.pending
        self.answered_at: float | None = None  # when the last answer to our attempts came
        self._send_at = INFINITY  # when the next frame may go (set by ``service``)
        self.quiet_since = now
        self._wanting_since: float | None = None
        self._noisy = False
        self._up = False
        self._stopping = False
        self._paused = False
        #: A network line's connection is being made again (``_reconnect``): nothing goes.
        self.reconnecting = False
        self._heard_on_connection = False  # something came in since it was (re)opened
        self._silent_misses = 0  # timeouts in a row with nothing heard on the connection
        #: Slaves that timed out during that silence: their state and misses before it.
        self._silent_streak: dict[int, tuple[SlaveState, int]] = {}
        self._submitted = 0  # requests submitted so far (``LineRequest.order``)
        self._apply_policy(policy)
        self.wire.attach(WireParts(self.late, self.foreign, self.order, self.sharing, self.lane))

    # -- configuration -------------------------------------------------------------------

    def _apply_policy(self, policy: LinePolicy) -> None:
        self.policy = policy
        # A Modbus TCP or TLS slave (MBAP framing) has no serial wire behind the socket: its
        # frames take no transmission time (9600 baud would hold each request ~12 ms).
        self.char_time = (
            0.0
            if self.framing.kind is LineKind.TCP
            else character_time(policy.baudrate, policy.data_bits, policy.parity, policy.stop_bits)
        )
        self._gap = policy.gap
        self.silence = policy.silence
        self.garbled_wait = max(2 * policy.silence, 0.003)
        # Only a shared medium can be noisy: a connection's frames need no gap to be read.
        self.timing.configure(policy, self.wire.quiet_line, self.char_time)
        self.lane.configure(policy.probe_share)
        self.echo = policy.echo
        wire = self.wire
        wire.char_time, wire.silence, wire.echo = self.char_time, self.silence, self.echo
        wire.garbled_wait = self.garbled_wait
        wire.listens = self.framing.transaction_ids is None
        # A foreign request awaits its answer as long as any of ours may wait for one.
        longest = max(policy.max_timeout, policy.timeout_for(0), *policy.slave_timeouts.values())
        self.foreign.configure(policy.silence, longest)
        self._max_wait = policy.max_queue_wait or INFINITY  # 0: no limit

    def reconfigure(self, policy: LinePolicy, now: float) -> None:
        """Take new timeouts, retries and limits (the port settings are unchanged)."""
        caching = bool(self.policy.cache)
        self._apply_policy(policy)
        self.plan.configure(policy.polls, now)
        polled = {id(block.poll) for block in self.plan.blocks}
        for poll in [poll for poll in self.polls if id(poll) not in polled]:
            self.polls.remove(poll)  # its block left the plan
        if policy.cache and not caching:
            self.wire.uncacheable()
        if policy.dead_after <= 0:  # isolation off: every slave is served again
            self.health.absent.clear()
            for slave, record in self.health.not_up():
                self._set_state(slave, record, SlaveState.UP)
            for request in list(self.lane.requests.values()):
                self._lane_remove(request)
                self._queue_at_front(request)
        if not policy.cache:
            self.sharing.cache.clear()
        self.service(now)

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
        return self.queue.queued

    @property
    def idle(self) -> bool:
        """True when nothing is on the wire or waiting."""
        return not self.wire.outstanding and self.queue.queued == 0

    @property
    def wire_busy(self) -> bool:
        """True while a transaction is on the wire."""
        return self.wire.outstanding > 0

    @property
    def in_flight(self) -> int:
        """Attempts on the wire."""
        return self.wire.outstanding

    def slave_state(self, slave: int) -> SlaveState:
        """The isolation state of ``slave``."""
        return self.health.state(slave)

    def slave_states(self) -> dict[int, SlaveState]:
        """Every slave the line has heard from or given up on, with its state."""
        return self.health.states()

    def queued_for(self, master: Hashable) -> int:
        """Requests ``master`` has waiting on this line."""
        record = self.queue.masters.get(master)
        return record.queued if record is not None else 0

    def get_timer(self) -> float | None:
        """The next time ``handle_timer`` must be called, ``None`` when nothing is due."""
        wire = self.wire
        when = wire.timer() if wire.outstanding else INFINITY
        queue = self.queue
        if queue.queued:
            arrivals = queue.arrivals  # the oldest queued request's patience (``max_queue_wait``)
            if arrivals and arrivals[0].enqueued_at + self._max_wait < when:
                when = arrivals[0].enqueued_at + self._max_wait
            if wire.concurrent or not wire.outstanding:
                lane = self.lane
                if wire.outstanding < wire.capacity:
                    when = min(when, self._send_at)
                    if self._wanting_since is not None:
                        when = min(when, self._wanting_since + self.timing.noisy_after)
                    if lane.requests and lane.credit < 0.0:
                        when = min(when, lane.credit_time())
                if lane.requests:
                    when = min(when, lane.earliest())
                if self.late.windows:
                    when = min(when, self.late.earliest())
                if self.foreign_pending:
                    when = min(when, self.foreign.earliest())
        if self.polls or self.plan.next_due < when:
            when = min(when, self._poll_time())
        if self._noisy:
            when = min(when, self.quiet_since + self._gap)
        if self.foreign.shared:
            when = min(when, self.foreign.shared_until)
        return None if when == INFINITY else when

    def _poll_time(self) -> float:
        """When the plan next needs ``service``: a due poll once the line may send (never
        while it cannot: the timer would spin), a held one when its hold may end."""
        wire = self.wire
        if not self._up or self._paused or self.reconnecting or self._stopping or self._noisy:
            return INFINITY
        if wire.outstanding >= wire.capacity or (wire.outstanding and not wire.concurrent):
            return INFINITY  # the attempt's end services the line
        when = self.plan.next_due
        if self.polls:
            when = min(when, self._send_at)
            if self.late.windows:
                when = min(when, self.late.earliest())
            if self.foreign_pending:
                when = min(when, self.foreign.earliest())
        return max(when, self.quiet_since + self._gap)

    # -- the masters' side ---------------------------------------------------------------

    def submit(self, request: LineRequest, now: float, *, handed_over: bool = False) -> None:
        """Queue ``request``, or answer it at once (line down, full, isolated, cached...).

        ``handed_over``: taken from the line this core replaces (``take_queued``); it keeps
        the time its master sent it, so its wait counts from then (``max_queue_wait``) and
        an answer read since then may still serve it, but none read before."""
        if not handed_over:
            request.enqueued_at = now
        self._submitted += 1
        request.order = self._submitted
        if self._stopping or not self._up:
            self._answer(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
            return
        plan = self.plan
        if request.pdu[0] in fc.READ_FUNCTIONS and not request.broadcast:
            if plan.blocks:
                answer = plan.serve(request.slave, request.pdu, now)
                if answer is not None:
                    self._deliver(request, answer, Outcome.MEMORY, -1.0)
                    return
        elif plan.change_submitted(request):  # also without blocks: a reload may add some
            request.counted_change = True  # until it ends (``_deliver``)
        if self._noisy:
            self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
            return
        queue = self.queue
        master = queue.masters.get(request.master)  # ``queue.master``, inline: once a request
        if master is None:
            master = queue.master(request.master)
        on_wire = self.wire.on_wire_for(request.master)
        if master.queued + on_wire >= self.policy.max_queue_per_master:  # the master's bound
            self._answer(request, ExceptionCode.SERVER_DEVICE_BUSY, Outcome.BUSY)
            return
        if queue.queued >= self.policy.max_queue and not self._push_out(master):
            self._answer(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
            return
        if request.broadcast:
            self.sharing.broadcast()
        else:
            record = self.health.slaves.get(request.slave)
            if record is not None and record.state is not UP:
                self._submit_isolated(request, record, now)
                return
            if record is None and self.health.absent and self._first_contact(request, now):
                self.service(now)  # a first contact among absent slaves: a probe
                return
            if not self._admit_read(request, now):
                return
        wire = self.wire
        if (
            not queue.queued
            and not wire.outstanding
            and not wire.concurrent
            and not wire.draining
            and not request.broadcast
            and not handed_over
            and master.heap_seq < 0
            and now >= self.quiet_since + self._gap
            and not (self._paused or self.reconnecting or self.polls or self.foreign_pending)
            and not (self.late.windows or self.sharing.joined)
            and self.plan.next_due > now
        ):
            # The line is free and nothing waits, nothing holds it back: it goes now, as
            # ``service`` would choose it, the accounts kept as if it had queued. The usual
            # case of a master polling a line alone: once per transaction.
            queue.went_at_once(master, now)
            self._send_at = INFINITY
            self._wanting_since = None
            self._poll_went_first = self._lane_went_last = False
            self._send(request, master, now, False)
            return
        queue.enqueue(master, request, master.queued == 0 and not on_wire, now)
        self.service(now)

    def _push_out(self, master: Master) -> bool:
        victim = self.queue.push_out(master)
        if victim is None:
            return False
        self._answer(victim, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
        return True

    def _submit_isolated(self, request: LineRequest, record: SlaveRecord, now: float) -> None:
        """A request for a suspect or down slave: the one lane place, or 0x0B at once."""
        slave = request.slave
        busy = slave in self.lane.requests or self.wire.on_wire_to(slave)
        if busy or self.health.refused_at_once(record, now):
            self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
            return
        if request.pdu[0] not in fc.READ_FUNCTIONS:
            self.sharing.change(slave)
        self._lane_put(request, now)
        self.service(now)

    def _admit_read(self, request: LineRequest, now: float) -> bool:
        """Cache and coalescing; ``False`` when the request was answered or joined another."""
        slave = request.slave
        sharing = self.sharing
        if request.pdu[0] not in fc.READ_FUNCTIONS:
            sharing.change(slave)  # later reads must not be served from before it
            request.epoch = sharing.epoch(slave)
            return True
        key = (slave, request.pdu)
        if sharing.cache:
            cached = sharing.cached(key, now)
            if cached is not None:
                self._deliver(request, cached, Outcome.CACHED, -1.0)
                return False
        if self.policy.coalesce:
            # ``sharing.epoch`` and ``sharing.leader``, inline: once per read
            epoch = sharing.write_epoch.get(slave, 0) + sharing.broadcast_epoch
            leader = sharing.open_reads.get(key)
            if (
                leader is not None
                and leader.epoch == epoch
                and not self.order.change_pending(request.master, slave)
            ):
                sharing.join(leader, request)
                self.wire.joined(request)
                self.notes.append(Note(LineEvent.COALESCED, slave))
                return False
            request.epoch = epoch
            sharing.open_reads[key] = request
        return True

    def cancel(self, master: Hashable, now: float) -> None:
        """``master`` left: drop what nobody still connected waits for. Its requests stay
        when a connected master joined them; a read it had joined goes when it was the
        last to wait for it (the read's own master left before)."""
        for leader in self.order.carriers():
            for follower in leader.followers:
                if follower.master == master:
                    follower.cancelled = True
        record = self.queue.masters.get(master)
        if record is not None:
            record.gone = True
            for request in record.queue:
                request.cancelled = True
        for request in [*self.lane.requests.values(), *self.retries]:
            if request.master == master:
                request.cancelled = True
        for request in self.order.leaders():  # reads that others joined, this master's or not
            if not request.wanted:
                self._drop(request)
        if record is not None:
            for request in [r for r in record.queue if not r.wanted]:
                self._drop(request)
            if not record.queue and record.queued == 0:
                self.queue.masters.pop(master, None)
        for request in [r for r in self.lane.requests.values() if not r.wanted]:
            self._drop(request)
        self.service(now)

    def _drop(self, request: LineRequest) -> None:
        """Take ``request`` from where it waits, answered ``DROPPED``: every master that
        waited for it has left."""
        if request.answered:
            return  # already dropped by another of ``cancel``'s sweeps
        if self.lane.holds(request):
            self._lane_remove(request)
        else:
            self.queue.remove(request)
        self.sharing.close(request)
        self._deliver(request, b"", Outcome.DROPPED, -1.0)

    # -- the line's side -----------------------------------------------------------------

    def port_opened(self, now: float) -> None:
        """The port is open: requests are taken from now on."""
        self.wire.opened()
        self._up = True
        self.reconnecting = False
        self._heard_on_connection = False
        self.quiet_since = max(self.quiet_since, now)
        self.service(now)

    def port_lost(self, now: float) -> None:
        """The port went away: the attempts and the queue are answered 0x0A."""
        self._up = False
        self._noisy = False
        self._wanting_since = None
        self.abandon(now)
        self._fail_all(ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
        self.wire.lost()

    def pause(self, now: float) -> None:
        """Send nothing more: the transaction on the wire finishes and requests keep queuing
        (a reload is about to reopen the line; ``take_queued`` hands them to the new one)."""
        self._paused = True
        self.service(now)

    def resume(self, now: float) -> None:
        """Send again after ``pause`` (a redundancy pair's standby became active)."""
        self._paused = False
        self.service(now)

    def stop(self, now: float) -> None:
        """Take no more requests; answer the queue 0x0A; the attempt on the wire finishes."""
        self._stopping = True
        self.plan.stop()  # the plan's own polls end with the line's
        self._fail_all(ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)

    def abandon(self, now: float) -> None:
        """Give up the attempts on the wire (a stop's grace is over): 0x0A for them. Their
        answers may still come once the port is back: look-alikes are held meanwhile."""
        for attempt in self.wire.take_all():
            request = attempt.request
            self._open_window(request.slave, self.health.record(request.slave), request, now)
            self._answer(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)

    def handover(self) -> Handover:
        """What the line that replaces this one must know of the wire (a reload that
        reopens the line, once the transaction on the wire has ended): a broadcast's
        turnaround still runs, and the slaves' lost answers may still come. An MBAP line
        hands on no late-answer windows: its lost answers went with the old connection."""
        windows = self.late.handover() if self.framing.transaction_ids is None else []
        kind = self.framing.kind
        return Handover(
            self.quiet_since, tuple(windows), self.foreign.handover(), kind, self.plan.handover()
        )

    def take_over(self, handover: Handover, now: float) -> None:
        """Start where the line this one replaces left the wire: quiet no earlier than it
        was, its late-answer windows kept as if opened here."""
        self.quiet_since = max(self.quiet_since, handover.quiet_since)
        if handover.blocks:
            self.plan.take_over(handover.blocks)
        if handover.heard is not None:
            self.foreign.take_over(handover.heard, now)
        # Answers carry transaction ids on MBAP lines; and a lost answer in another framing
        # (a reload that changed RTU to ASCII) cannot be taken for one in this line's.
        if self.framing.transaction_ids is None and handover.framing in ("", self.framing.kind):
            for window in handover.windows:
                if window.until > now:
                    self.health.record(window.slave)
                    self.late.keep(window)
        self.service(now)

    def receive(self, data: bytes, now: float) -> None:
        """Bytes read from the line at ``now``."""
        self.stats.bytes_read += len(data)
        self._heard_on_connection = True
        if self._silent_misses:
            self._silent_misses = 0
            self._silent_streak.clear()
        wire = self.wire
        if wire.quiet_line and now > self.quiet_since:
            self.quiet_since = now
        found = wire.receive(data, now)
        if found:  # else the answer is not complete yet: nothing changed for ``service``
            if len(found) == 1 and found[0][0] is COMPLETE:  # the usual: one answer
                self.complete(found[0][1], found[0][2], now)  # type: ignore[arg-type]
            else:
                self._apply(found, now)
            self.service(now)

    def _apply(self, found: list[Finding], now: float) -> None:
        """Apply what the wire found, in the order found (``wire.Found``)."""
        for finding in found:
            kind = finding.kind
            attempt = finding.attempt
            if kind is Found.COMPLETE:
                assert attempt is not None and finding.frame is not None
                self.complete(attempt, finding.frame, now)
            elif kind is Found.DISCARD:
                assert finding.reason is not None
                self.discard(finding.reason, finding.amount, finding.slave)
            elif kind is Found.FAILED:
                assert attempt is not None
                self.fail(attempt, finding.error, now)
            elif kind is Found.GARBLED:
                assert attempt is not None and finding.error is not None
                self.garbled(attempt, finding.error, finding.damaged, now)
            elif kind is Found.HEAR:
                self.hear(finding.data, now, asked=finding.slave)
            elif kind is Found.HEARD:
                self._heard(finding.heard)
            elif kind is Found.LATE_BYTES:
                self.late_bytes(finding.data, now)
            elif kind is Found.LATE_FRAME:
                self.late_frame(finding.data, now)
            else:  # a lost attempt's answer, by its transaction id
                self._late_answer(
                    finding.slave, {finding.slave: (finding.sent_at, finding.function)}, now
                )

    def handle_timer(self, now: float) -> None:
        """Time passed: end attempts, expire windows and waits, send what may go."""
        lane = self.lane
        if lane.requests:
            lane.credit_now(now)  # so the share's next instant is never in the past
        found = self.wire.expire(now)
        if found:
            self._apply(found, now)
        if lane.requests:
            for request in lane.expired(now):
                self._lane_remove(request)
                self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
        if self.late.windows:
            for slave in self.late.expired(now):
                self.late.close(slave)
        if self._noisy and now >= self.quiet_since + self._gap:
            self._noisy = False
            self.notes.append(Note(LineEvent.LINE_QUIET, 0))
        if self.foreign_pending:
            self.foreign.expire(now)
        if self.foreign.shared and self.foreign.decays(now):
            self.notes.append(Note(LineEvent.LINE_NOT_SHARED, 0))
        if self.queue.queued:
            arrivals = self.queue.arrivals
            if arrivals and arrivals[0].enqueued_at + self._max_wait <= now:
                self._expire_waits(now)
        self.service(now)

    def _expire_waits(self, now: float) -> None:
        """Requests unsent after ``max_queue_wait``: 0x0B without the wire (their masters
        have given up by now); the slave's health is not touched."""
        for request in self.queue.overdue(now - self._max_wait + 1e-9):
            self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)

    # -- choosing and sending: which request goes next, putting it on the wire ---------

    def service(self, now: float) -> None:
        """Put the next requests on the wire while they may go now."""
        self._send_at = INFINITY
        wire = self.wire
        if (
            wire.outstanding >= wire.capacity
            or not self._up
            or not (self.queue.queued or self.polls or self.plan.next_due <= now)
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
        plan = self.plan
        while (
            self.queue.queued or self.polls or plan.next_due <= now
        ) and wire.outstanding < wire.capacity:
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
        if (self.polls or self.plan.next_due <= now) and not (
            self._poll_went_first and self.queue.queued
        ):
            poll = self._due_poll(now)
            if poll is not None:
                self._poll_went_first = self.queue.queued > 0
                return poll, None, False
        lane = self.lane
        if lane.requests and lane.credit_now(now) >= 0.0:
            if self._lane_went_last and self.queue.queued > len(lane.requests):
                # A probe just held the line: a master's request that may go goes before
                # the next one, so that a poll meets one probe, not two in a row.
                picked = self.queue.pop(now, self.wire.first_eligible)
                if picked is not None:
                    self._poll_went_first = self._lane_went_last = False
                    return picked[0], picked[1], False
            request = self._lane_candidate(now)
            if request is not None:
                self._lane_went_last = True
                return request, None, True
        picked = self.queue.pop(now, self.wire.first_eligible)
        if picked is not None:
            self._poll_went_first = self._lane_went_last = False
            return picked[0], picked[1], False
        if self._poll_went_first and (self.polls or self.plan.next_due <= now):
            # The masters' turn, but none of theirs may go now (what waits is in the lane,
            # off its credit): the plan's due poll goes rather than the line idling.
            poll = self._due_poll(now)
            if poll is not None:
                return poll, None, False
        if self.late.wanted:  # the queue's requests were held: a proof lets them go
            waiting = self.queue.queued - len(self.lane.requests) - len(self.retries)
            proof = self._proof(now, free=waiting <= 0)
            if proof is not None:
                return proof
        if lane.requests:
            request = self._lane_candidate(now, free=True)
            if request is not None:
                self._lane_went_last = True
                return request, None, False
        return None

    def _due_poll(self, now: float) -> LineRequest | None:
        """The plan's next poll that may go now (``polling`` module doc): due polls go
        before the masters' requests; an isolated slave's wait in the lane, at its pace."""
        plan = self.plan
        for block in plan.due(now):
            self._make_poll(block, now)
        wire = self.wire
        order = self.order
        for poll in self.polls:
            if wire.may_go(poll, now) and not order.behind_broadcast(poll):
                self.polls.remove(poll)
                return poll
        return None

    def _make_poll(self, block: PollBlock, now: float) -> None:
        spec = block.spec
        slave = spec.slave
        pdu = fc.read_request(spec.function, spec.address, spec.count)
        poll = LineRequest(slave, pdu, POLLER, no_reply)
        poll.poll = True
        poll.enqueued_at = now
        self._submitted += 1
        poll.order = self._submitted
        record = self.health.slaves.get(slave)
        if record is None or record.state is SlaveState.UP:
            self.plan.poll_made(block, poll, now)
            self.polls.append(poll)
            return
        lane = self.lane
        if (
            slave in lane.requests
            or self.wire.on_wire_to(slave)
            or self.health.refused_at_once(record, now)
        ):
            # Its slave's one lane place is taken, or its next probe is not due (a dead
            # slave is probed at the back-off, its blocks too).
            self.plan.skipped(block, now)
            return
        self.plan.poll_made(block, poll, now)
        self._lane_put(poll, now)

    def _lighter_master_polls(self, probe: LineRequest, now: float, hold: float) -> bool:
        """True when another master that used the line less than ``probe``'s was answered
        within ``2 x hold``: it polls, and a free probe would hold its next poll up for
        ``hold`` (``health`` module doc: the absent addresses cost their own masters)."""
        masters = self.queue.masters
        own = masters.get(probe.master)
        account = own.vtime if own is not None else 0.0
        for master in masters.values():
            answered_at = master.answered_at
            if (
                master is not own
                and answered_at is not None
                and now - answered_at <= 2.0 * hold
                and master.vtime < account
            ):
                return True
        return False

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
            pdu = None
            if record.answered:  # a slave never heard from would time a proof read out too
                lost = owner.pdu if owner else None
                pdu = proof_pdu(window.signatures, record.known_read, lost)
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
            # Without the share's credit: not into the gap before a lighter master's poll.
            hold = self.timing.longest_attempt(best.slave, best.pdu[0])
            if not self._lighter_master_polls(best, now, hold):
                hold = 0.0  # nobody lighter comes back soon: only the short quiet
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
        if not retry:  # its first attempt on this line (a handed-over one's too): no more
            request.sent = True  # reads join it, whatever an earlier line did with it
            self.sharing.close(request)
        wire = self.wire
        slave = request.slave
        pdu = request.pdu
        frames = self._frames  # ``frame``, inline: once per transaction
        known = None if frames is None else frames.get((slave, pdu))
        if known is not None:
            frame = known
        elif frames is None:
            frame = self.encode(slave, pdu)
        else:
            frame = frames[slave, pdu] = self.encode(slave, pdu)
            if len(frames) > FRAME_CACHE_SIZE:
                frames.clear()  # a bound, not an LRU: polling refills it with what is used
        sent_by = now + len(frame) * self.char_time
        timing = self.timing
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
        attempt = Attempt(
            request, self.new_decoder(slave, pdu), now, deadline, credit, expected, above
        )
        if wire.concurrent:
            self._start_concurrent(attempt, master, credit)
        frame = wire.start(attempt, frame)
        if wire.quiet_line:
            self.quiet_since = sent_by
            if self.echo:
                wire.expect_echo(frame)
        if request.poll:
            block = self.plan.block_of(request)
            if block is not None:
                self.plan.sent(block, now)
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

    def _start_concurrent(self, attempt: Attempt, master: Master | None, credit: bool) -> None:
        """An attempt beside others: its master is charged the wire's estimate now (its
        answer's time is not known before the next is chosen), and a read sent while a
        change to its slave is outstanding is not cached (the device may run it first)."""
        slave = attempt.request.slave
        if master is not None and not credit:
            charged = attempt.charged = self.wire.estimate
            self.queue.charge_ahead(master, charged)
            if master.queue and master.heap_seq < 0:
                self.queue.push(master)
        attempt.epoch = self.sharing.epoch(slave)
        if self.policy.cache and any(may_change(r, slave) for r in self.wire.requests()):
            attempt.epoch = -1

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
        if self.echo:
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
        polls = list(self.polls)
        self.polls.clear()
        for request in self.take_queued():
            self._answer(request, code, outcome)
        for poll in polls:
            self._answer(poll, code, outcome)

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
            if request.poll:  # the plan polls again; the line taking over has its own
                self._deliver(request, b"", Outcome.DROPPED, -1.0)
                continue
            request.attempts = 0
            request.single = False
            request.lane_deadline = INFINITY
            kept.append(request)
        return kept

    # -- listening: frames heard that no attempt took (other masters; the pair reads the bus)

    def hear(self, data: bytes, now: float, stop: bool = False, asked: int = -1) -> bool:
        """Bytes heard at ``now`` that no attempt took: note foreign master frames, learn
        from their answers; ``True`` when a master frame was among them (with ``stop``,
        the bytes after it are left to ``foreign.take_unframed``)."""
        if self.framing.transaction_ids is not None:
            return False  # a tcp or tls line: its answers name their requests
        own: Own = [(request.slave, request.pdu) for request in self.wire.requests()]
        if self.late.windows:
            own.extend(self.late.owners())
        return self._heard(self.foreign.feed(data, now, self.char_time, own, stop, asked))

    def _heard(self, frames: Iterable[Heard]) -> bool:
        """Note other masters' frames among ``frames`` and learn from their answers;
        ``True`` when a request frame was among them."""
        foreign = self.foreign
        master = False
        for heard in frames:
            if heard.kind is HeardKind.MASTER:
                master = True
                if not foreign.listening:
                    self.notes.append(
                        Note(LineEvent.FOREIGN_MASTER, heard.slave, f"function {heard.pdu[0]}")
                    )
            elif heard.kind is HeardKind.ASKED:
                master = True  # awaited like a master's request, noted as none
            elif heard.kind is HeardKind.ANSWER and heard.request is not None:
                self._learn_from(heard.request, heard.at)
        return master

    def _learn_from(self, request: ForeignRequest, answered_at: float) -> None:
        """A foreign request's answer came: its slave's turnaround, measured as the line
        measures its own (the answer's end less its transmission time and the request's
        end), teaches the learned timing, so a standby starts with it."""
        timing = self.timing
        slave = request.slave
        if not timing.learn or slave in timing.fixed:
            return
        turnaround = answered_at - request.heard_at - timing.answer_time(request.pdu)
        timing.answered(slave, request.pdu[0], max(0.0, turnaround))

    # -- what a redundancy pair reads of the bus ---------------------------------------------

    @property
    def shared(self) -> bool:
        """True while a foreign master frame was heard within ``foreign.SHARED_FOR_S``."""
        return self.foreign.shared

    @property
    def last_master_frame_at(self) -> float | None:
        """The end of the last master frame heard that this gateway did not send."""
        return self.foreign.last_master_frame_at

    @property
    def last_frame_at(self) -> float | None:
        """The end of the last intact frame heard: an answer to our attempts or any other."""
        heard, answered = self.foreign.last_frame_at, self.answered_at
        if heard is None or answered is None:
            return answered if heard is None else heard
        return max(heard, answered)

    @property
    def heard_master_frames(self) -> int:
        """Master frames heard while listening (the active peer's)."""
        return self.foreign.heard_master_frames

    @property
    def foreign_frames(self) -> int:
        """Foreign master frames heard while not listening."""
        return self.foreign.foreign_frames

    @property
    def listening(self) -> bool:
        return self.foreign.listening

    def set_listening(self, listening: bool) -> None:
        """A standby listens: master frames heard are its peer's (timed, learned from,
        counted in ``heard_master_frames``), not a foreign master's."""
        self.foreign.listening = listening

    # -- the end of an attempt, and every delivery -----------------------------------------

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
        if record.state is UP:
            record.misses = 0  # ``alive``, for a slave that was up
            lane = self.lane
            if lane.first_contacts and slave in lane.first_contacts:
                # Heard now: another master's first contact with it, waiting in the lane,
                # goes back to the queue, before its master's later requests to it.
                waiting = lane.requests.get(slave)
                if waiting is not None:
                    self._lane_remove(waiting)
                    self._queue_at_front(waiting)
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
        self._charge(attempt, wire, now, answered=True)
        if response[0] & fc.EXCEPTION_FLAG:
            outcome = Outcome.SLAVE_EXCEPTION
        elif function in fc.READ_FUNCTIONS:
            if self.policy.cache:
                self._store_cache(attempt, response, now)
            outcome = OK
        else:
            outcome = OK
        if request.followers:  # answered now too: asking again at once, they are not rested
            self.queue.answered(request.followers, now)
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
        """A garbled frame (the wire decided, ``SerialWire._garbled``): noted; a damaged
        answer fails the attempt at once, anything else only after ``garbled_wait`` of
        quiet (a valid answer meanwhile is taken)."""
        slave = attempt.request.slave
        if error.kind == BAD_CHECK:
            self.notes.append(Note(LineEvent.CRC_ERROR, slave, error.reason))
        else:
            self.discard(DiscardReason(error.kind), 1, slave)
        if damaged:
            self.fail(attempt, error, now, damaged=True)

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
        self._charge(attempt, wire, now, answered=False)
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
            if self._paused:  # a reload takes what waits: what was on the wire ends here
                self._answer(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
            elif fc.is_safe_to_retry(request.pdu) and request.wanted and not request.proof:
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

    def _charge(self, attempt: Attempt, wire: float, now: float, answered: bool) -> None:
        """Account the line time to the master who used it (or to the isolated share): the
        attempt's time on the wire and the silence the line keeps after it. Without the
        silence an answer on a fast port would cost next to nothing, and a master that paid
        for one timeout would wait behind thousands of cheap transactions."""
        wire += self._gap
        queue = self.queue
        master = queue.masters.get(attempt.request.master)
        # The line's typical transaction (a moving mean) and when the master was served: the
        # fair queue's rest rule reads both (``FairQueue.enqueue``). An answered one also
        # teaches it the turn it charges in; a timeout does not (``FairQueue.learned``).
        queue.typical += (wire - queue.typical) * TYPICAL_WEIGHT
        if answered:
            queue.learned(wire)
        if master is not None:
            master.answered_at = now
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
        if not rules or not self.wire.may_cache(attempt, self.sharing.epoch(attempt.request.slave)):
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
        if request.counted_change:
            request.counted_change = False
            self.plan.change_ended(request)
        if request.poll:
            block = self.plan.block_of(request)
            if block is not None:
                self.plan.ended(block, pdu, outcome)
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
