"""The line's one state machine: every transition of a request, every action emitted.

Theory of operation: see the package's docstring (``gateway.core.line``). The parts
(the fair queue, slave health and the lane, late-answer windows, read sharing, the
order rules) keep state and answer questions; the wire strategy (one attempt at a
time, or flights by transaction id) says which bytes answer which attempt. Every
change of what becomes of a request is made by ``LineCore``, and only it appends to
``transmits``, ``deliveries`` and ``notes`` (h11's "Rule 1"). Its class body is
written in four layers, each under 400 lines: this module (the masters' side, the
port, the reload, the timer), ``sending.py`` (which request goes next, sending it),
``listening.py`` (frames heard that no attempt took) and ``ends.py`` (what the end of
an attempt does; every delivery).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable

from .. import pdu as fc
from ..errors import ExceptionCode
from ..framing import RTU, Framing, LineKind
from ..outcome import LineEvent, Outcome, SlaveState
from ..timing import character_time
from .fair_queue import FairQueue, Master
from .foreign import ForeignMasters
from .health import ProbeLane, SlaveHealth, SlaveRecord
from .late import LateWindows
from .order import OrderRules
from .records import (
    INFINITY,
    Delivery,
    Handover,
    LinePolicy,
    LineRequest,
    LineStats,
    Note,
    Transmit,
)
from .response_timing import ResponseTiming
from .sending import Sending
from .sharing import ReadSharing
from .wire import SerialWire, Wire


class LineCore(Sending):
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
        self.wire.bind(self)

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
        # A foreign request awaits its answer as long as any of ours may wait for one.
        longest = max(policy.max_timeout, policy.timeout_for(0), *policy.slave_timeouts.values())
        self.foreign.configure(policy.silence, longest)
        self._max_wait = policy.max_queue_wait or INFINITY  # 0: no limit

    def reconfigure(self, policy: LinePolicy, now: float) -> None:
        """Take new timeouts, retries and limits (the port settings are unchanged)."""
        caching = bool(self.policy.cache)
        self._apply_policy(policy)
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
        if self._noisy:
            when = min(when, self.quiet_since + self._gap)
        if self.foreign.shared:
            when = min(when, self.foreign.shared_until)
        return None if when == INFINITY else when

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
            if record is not None and record.state is not SlaveState.UP:
                self._submit_isolated(request, record, now)
                return
            if record is None and self.health.absent and self._first_contact(request, now):
                self.service(now)  # a first contact among absent slaves: a probe
                return
            if not self._admit_read(request, now):
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
        return Handover(self.quiet_since, tuple(windows), self.foreign.handover())

    def take_over(self, handover: Handover, now: float) -> None:
        """Start where the line this one replaces left the wire: quiet no earlier than it
        was, its late-answer windows kept as if opened here."""
        self.quiet_since = max(self.quiet_since, handover.quiet_since)
        if handover.heard is not None:
            self.foreign.take_over(handover.heard, now)
        if self.framing.transaction_ids is None:  # else answers carry transaction ids
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
        self.wire.receive(data, now)

    def handle_timer(self, now: float) -> None:
        """Time passed: end attempts, expire windows and waits, send what may go."""
        lane = self.lane
        if lane.requests:
            lane.credit_now(now)  # so the share's next instant is never in the past
        self.wire.expire(now)
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
