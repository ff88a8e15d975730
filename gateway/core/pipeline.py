"""Several requests outstanding on one MBAP line (``max_in_flight`` > 1).

Theory of operation. On a line framed by MBAP (``kind = "tcp"``, and any kind whose
framing numbers its requests with ``TransactionIds``) every answer carries the
transaction id (TID) of its request, so answers need not come in order and need not
be told apart by their shape. ``PipelinedLineCore`` is ``LineCore`` with the attempt on
the wire replaced by up to ``max_in_flight`` attempts, each with its own TID and its own
deadline; an answer is matched by its TID, in any order. Everything else is the line
core's own: fair order over masters, per-master and line-wide bounds, isolation of
suspect and down slaves, coalescing, the cache, safe-only retries (a retry is sent
under a new TID), stop, abandon, cancel and port loss (every outstanding attempt
answered once, 0x0A as for the single attempt).

What changes with pipelining:

* **No late-answer windows.** An attempt that timed out keeps its TID reserved (no new
  request gets it); its answer, if it comes, is discarded as ``unexpected_tid`` and
  shows the slave alive. Nothing needs holding back to keep answers apart.
* **Ordering per master and unit.** A device may work on several requests at once, so
  one master's requests to one unit are kept in an order that cannot break
  read-after-write: a request with side effects (anything ``pdu.is_safe_to_retry``
  calls unsafe) is not sent while an earlier request of the same master to that unit is
  outstanding (sent and not yet finally answered, retries included), and nothing of
  that master to that unit is sent while such a write is outstanding. Reads pass reads.
  Once one of a master's requests to a unit is held, its later ones to that unit wait
  behind it; its requests to other units go on. A read that joined another master's
  identical read counts as outstanding too.
* **Broadcasts** go alone: the line stops sending while one waits until nothing is
  outstanding, then the broadcast and its turnaround, as on a serial line.
* **No quiet time.** A TCP connection is no shared medium: frames do not wait for the
  line's silence (``frame_gap``, when set, still follows a broadcast).
* **Fair share.** A master is charged an estimate of a transaction's time (the recent
  average) when its request is sent, so its next request competes at once, and the
  difference when the answer comes: one master's deep pipeline does not take every
  slot while others wait.
* **Cache.** A read's answer is cached only if no write to its slave was submitted
  after it was sent, nor was outstanding when it was sent (answers may overtake each
  other, and a device may run the write after the read).

The serial core is untouched: a line with ``max_in_flight = 1`` (the default) uses
``LineCore`` itself (``new_line_core``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Final

from . import pdu as fc
from .errors import ExceptionCode, FramingError, ResponseError
from .framing import RTU, Framing, ResponseDecoder
from .line import (
    INFINITY,
    LineCore,
    LinePolicy,
    LineRequest,
    LineStats,
    Note,
    Transmit,
    _Attempt,
    _Master,
    _Slave,
    may_change,
)
from .mbap import MbapDecoder, TransactionIds
from .outcome import LineEvent, Outcome
from .rtu import RtuFrame, check_identity

#: The most requests ``max_in_flight`` may allow on one connection.
MAX_IN_FLIGHT: Final = 64
#: TIDs of timed-out attempts kept reserved (their answers may still come).
_LOST_TIDS_KEPT: Final = 4096
#: Weight of the newest transaction in the estimate charged when a request is sent.
_ESTIMATE_WEIGHT: Final = 0.125


@dataclass(slots=True, eq=False, init=False)
class _Flight(_Attempt):
    """One outstanding attempt: its TID, the slave's write epoch when sent, its charge."""

    tid: int
    epoch: int
    charged: float

    def __init__(
        self,
        request: LineRequest,
        decoder: ResponseDecoder,
        sent_at: float,
        deadline: float,
        from_credit: bool,
        tid: int,
        epoch: int,
        charged: float,
    ) -> None:
        # Not super(): a slots dataclass is a new class, the one super() would not find.
        _Attempt.__init__(self, request, decoder, sent_at, deadline, from_credit)
        self.tid = tid
        self.epoch = epoch
        self.charged = charged


def new_line_core(
    policy: LinePolicy,
    now: float,
    stats: LineStats | None = None,
    framing: Framing = RTU,
    max_in_flight: int = 1,
) -> LineCore:
    """The line's core: pipelined for an MBAP framing with ``max_in_flight`` > 1."""
    if max_in_flight > 1:
        return PipelinedLineCore(policy, now, stats, framing, max_in_flight)
    return LineCore(policy, now, stats, framing)


class PipelinedLineCore(LineCore):
    """An MBAP line with up to ``max_in_flight`` attempts outstanding; see the module docs."""

    def __init__(
        self,
        policy: LinePolicy,
        now: float,
        stats: LineStats | None = None,
        framing: Framing = RTU,
        max_in_flight: int = 2,
    ) -> None:
        ids = framing.transaction_ids
        if ids is None:
            raise ValueError(
                f"max_in_flight > 1 needs a framing with transaction ids, not {framing.kind}"
            )
        if not 1 <= max_in_flight <= MAX_IN_FLIGHT:
            raise ValueError(f"max_in_flight {max_in_flight} outside 1..{MAX_IN_FLIGHT}")
        super().__init__(policy, now, stats, framing)
        self.max_in_flight = max_in_flight
        self._ids: TransactionIds = ids
        self._in_flight: dict[int, _Flight] = {}  # TID -> attempt
        self._retries: deque[LineRequest] = deque()
        self._stream = MbapDecoder()
        self._out_of_step = False
        self._lost: dict[int, int] = {}  # TID of a timed-out attempt -> its slave
        # (master, slave) -> [requests outstanding, of which with side effects]
        self._open: dict[tuple[Hashable, int], list[int]] = {}
        self._opened: dict[LineRequest, tuple[tuple[Hashable, int], bool]] = {}  # by identity
        self._draining = False  # a broadcast waits for the outstanding attempts
        self._estimate = 0.0
        self._completing: _Flight | None = None

    # -- observation ---------------------------------------------------------------------

    @property
    def idle(self) -> bool:
        """True when nothing is outstanding or waiting."""
        return not self._in_flight and self._queued == 0

    @property
    def wire_busy(self) -> bool:
        """True while an attempt is outstanding on the connection."""
        return bool(self._in_flight)

    @property
    def in_flight(self) -> int:
        """Attempts outstanding on the connection."""
        return len(self._in_flight)

    def get_timer(self) -> float | None:
        """The next deadline: an attempt's, a lane request's, the share's, a turnaround's."""
        when = INFINITY
        for flight in self._in_flight.values():
            if flight.deadline < when:
                when = flight.deadline
        if self._queued:
            if len(self._in_flight) < self.max_in_flight:
                when = min(when, self._send_at)
                if self._lane and self._credit < 0.0:
                    when = min(when, self._credit_time())
            for request in self._lane.values():
                when = min(when, request.lane_deadline)
        return None if when == INFINITY else when

    # -- the masters' side ---------------------------------------------------------------

    def _on_wire_to(self, slave: int) -> bool:
        return any(flight.request.slave == slave for flight in self._in_flight.values())

    def _admit_read(self, request: LineRequest, now: float) -> bool:
        """As on the serial line; a read that joins another's counts as its master's
        outstanding request to that unit until it is answered (its write waits for it)."""
        if super()._admit_read(request, now):
            return True
        if not request.answered:  # joined a queued read, not answered from the cache
            self._mark_open(request)
        return False

    def cancel(self, master: Hashable, now: float) -> None:
        """``master`` left: its waiting retries are dropped when their turn comes (and
        those it alone still waited for, having joined them)."""
        for request in self._retries:
            if request.master == master:
                request.cancelled = True
        super().cancel(master, now)

    def _carriers(self) -> list[LineRequest]:
        """The serial core's, plus the retries waiting and the attempts outstanding."""
        carriers = super()._carriers()
        carriers.extend(self._retries)
        carriers.extend(flight.request for flight in self._in_flight.values())
        return carriers

    def take_queued(self) -> list[LineRequest]:
        """Remove every waiting request unanswered, retries included."""
        retries = list(self._retries)
        self._retries.clear()
        for request in retries:
            self._close_open(request)
        return self._hand_over(retries + super().take_queued())

    # -- the line's side -----------------------------------------------------------------

    def port_opened(self, now: float) -> None:
        """A new connection: a new byte stream, no answers owed on it."""
        self._stream = MbapDecoder()
        self._out_of_step = False
        self._lost.clear()
        super().port_opened(now)

    def port_lost(self, now: float) -> None:
        """The connection went away: every outstanding attempt and the queue get 0x0A."""
        super().port_lost(now)
        self._stream = MbapDecoder()
        self._lost.clear()

    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the connection: each complete frame goes to the attempt its TID names."""
        self.stats.bytes_read += len(data)
        if self._out_of_step:
            self._discard("late", len(data))
            return
        stream = self._stream
        try:
            stream.feed(data)
            while (frame := stream.next_frame()) is not None:
                self._take(frame.transaction_id, frame.unit_id, frame.pdu, now)
        except FramingError:
            # Out of step: every later byte is suspect. The driver reconnects on this note.
            self._out_of_step = True
            self._discard("bad_header", 1)
        self._service(now)

    def _take(self, tid: int, unit: int, pdu: bytes, now: float) -> None:
        flight = self._in_flight.get(tid)
        if flight is None:
            slave = self._lost.pop(tid, None)
            self._discard("unexpected_tid", 1, slave if slave is not None else 0)
            if slave is not None:  # a timed-out attempt's answer: the slave is alive, slow
                self._alive(slave, self._record(slave))
            return
        request = flight.request
        try:
            check_identity(unit, request.pdu[0], request.pdu, unit, pdu)
        except ResponseError as error:
            # Its TID but not its answer: discarded; the attempt waits on to its deadline.
            self._discard(error.kind, 1, request.slave)
            return
        del self._in_flight[tid]
        wire = now - flight.sent_at
        self._estimate += (wire - self._estimate) * _ESTIMATE_WEIGHT
        self._completing = flight
        try:
            self._complete(flight, RtuFrame(unit, pdu), now)
        finally:
            self._completing = None

    def handle_timer(self, now: float) -> None:
        """Time passed: attempts past their deadline fail; lane waits expire; send."""
        if self._lane:
            self._credit_now(now)
        expired = [flight for flight in self._in_flight.values() if now >= flight.deadline]
        for flight in expired:
            del self._in_flight[flight.tid]
            self._keep_lost(flight.tid, flight.request.slave)
            self._fail(flight, None, now)
        if self._lane:
            for request in [r for r in self._lane.values() if now >= r.lane_deadline]:
                self._lane_remove(request)
                self._answer(request, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
        self._service(now)

    def _keep_lost(self, tid: int, slave: int) -> None:
        lost = self._lost
        lost[tid] = slave
        if len(lost) > _LOST_TIDS_KEPT:
            del lost[next(iter(lost))]

    # -- choosing and sending ------------------------------------------------------------

    def _service(self, now: float) -> None:
        """Send while there is room on the connection and a request may go."""
        self._send_at = INFINITY
        self._wanting_since = None
        if not self._up or not self._queued or self._paused:
            return
        in_flight = self._in_flight
        if self._draining:
            if in_flight:
                return
            self._draining = False
        if now < self._quiet_since + self._gap:  # a broadcast's turnaround
            self._send_at = self._quiet_since + self._gap
            return
        while self._queued and len(in_flight) < self.max_in_flight:
            picked = self._pick(now)
            if picked is None:
                return
            request, master, from_credit = picked
            if request.broadcast:
                self._draining = False
                self._send_broadcast(request, master, now)
                self._send_at = self._quiet_since + self._gap
                return
            if not request.wanted:
                self._close_to_joiners(request)
                self._deliver(request, b"", Outcome.DROPPED, -1.0)
                if master is not None:
                    self._reschedule(master)
                continue
            self._send_flight(request, master, now, from_credit)
            if self._draining:
                return

    def _pick(self, now: float) -> tuple[LineRequest, _Master | None, bool] | None:
        """Retries first (in the order their attempts failed), then the line core's order."""
        retries = self._retries
        if retries:
            retry = retries.popleft()
            self._count_waiting(retry, -1)
            return retry, None, False
        return super()._pick(now)

    def _may_go(self, request: LineRequest) -> bool:
        """The ordering rule for one master's requests to one unit (see the module docs)."""
        counts = self._open.get((request.master, request.slave))
        if counts is None:
            return True
        outstanding, writes = counts
        own = self._opened.get(request)  # a lane retry counts itself: not an earlier one
        if own is not None:
            outstanding -= 1
            writes -= own[1]
        if writes:  # a write of this master to this unit is outstanding
            return False
        return outstanding == 0 or fc.is_safe_to_retry(request.pdu)

    def _first_eligible(self, master: _Master, now: float) -> LineRequest | None:
        """The oldest request of ``master`` that may go now under the ordering rule."""
        held: set[int] | None = None
        for request in master.queue:
            if request.broadcast:
                if held or self._broadcast_held(master.key, request):
                    return None  # its master's earlier requests go first
                if self._in_flight:
                    self._draining = True
                    return None
                return request
            slave = request.slave
            if held is not None and slave in held:
                continue
            if self._may_go(request):
                return request
            if held is None:
                held = set()
            held.add(slave)
        return None

    def _lane_candidate(self, now: float) -> LineRequest | None:
        """The oldest lane request that the ordering rule lets go, and that no broadcast
        of its master submitted before it still waits for."""
        best: LineRequest | None = None
        for request in self._lane.values():
            if not self._may_go(request) or self._behind_broadcast(request):
                continue
            if best is None or request.enqueued_at < best.enqueued_at:
                best = request
        if best is not None:
            self._lane_remove(best)
        return best

    def _send_flight(
        self, request: LineRequest, master: _Master | None, now: float, from_credit: bool
    ) -> None:
        retry = request.attempts > 0
        request.attempts += 1
        if not request.sent:
            request.sent = True
            self._close_to_joiners(request)
        if request not in self._opened:
            self._mark_open(request)
        slave = request.slave
        pdu = request.pdu
        frame = self._encode(slave, pdu)
        tid = self._ids.current
        while tid in self._in_flight or tid in self._lost:  # never two meanings for one TID
            frame = self._encode(slave, pdu)
            tid = self._ids.current
        charged = 0.0
        if master is not None and not from_credit:
            charged = self._estimate
            master.vtime = max(master.vtime, self._vclock) + charged
            if master.queue and master.heap_seq < 0:
                self._push_master(master)
        transmit_time = len(frame) * self._char_time
        epoch = self._write_epoch.get(slave, 0) + self._broadcast_epoch
        if self.policy.cache and any(
            may_change(f.request, slave) for f in self._in_flight.values()
        ):
            epoch = -1  # a change to it is outstanding: the device may run it after this read
        self._in_flight[tid] = _Flight(
            request,
            self._new_decoder(slave, pdu),
            now,
            now + transmit_time + self._timeout_for(slave),
            from_credit,
            tid=tid,
            epoch=epoch,
            charged=charged,
        )
        stats = self.stats
        stats.frames_sent += 1
        stats.bytes_written += len(frame)
        if retry:
            self.notes.append(Note(LineEvent.RETRY, slave))
        self.transmits.append(Transmit(frame, request, now - request.enqueued_at, retry))

    # -- ends of attempts ----------------------------------------------------------------

    def _open_guard(self, slave: int, record: _Slave, request: LineRequest, now: float) -> None:
        """No window: the lost attempt's TID stays reserved and names its answer."""

    def _fail(
        self, attempt: _Attempt, error: ResponseError | None, now: float, damaged: bool = False
    ) -> None:
        super()._fail(attempt, error, now, damaged)
        retry = self._retry
        if retry is not None:  # the line core's one retry slot: here, one per failed attempt
            self._retry = None
            self._retries.append(retry)

    def _abandon_attempt(self, now: float) -> None:
        flights = list(self._in_flight.values())
        self._in_flight.clear()
        for flight in flights:
            self._answer(flight.request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)

    def _charge(self, attempt: _Attempt, wire: float, now: float) -> None:
        """Charge the wire time, less the estimate charged when the request was sent."""
        charged = attempt.charged if isinstance(attempt, _Flight) else 0.0
        master = self._masters.get(attempt.request.master)
        if attempt.from_credit:
            self._credit_now(now)
            self._credit -= wire
        elif master is not None:
            if charged:
                master.vtime += wire - charged
            else:
                master.vtime = max(master.vtime, self._vclock) + wire
            if master.heap_seq >= 0:
                self._push_master(master)  # its old entry goes stale
        if master is not None:
            self._reschedule(master)

    def _on_wire_for(self, master: Hashable) -> int:
        return sum(1 for flight in self._in_flight.values() if flight.request.master == master)

    def _change_pending(self, master: Hashable, slave: int) -> bool:
        """Also a change of ``master`` outstanding or due for a retry: another master's
        read sent now could run before it."""
        if any(
            request.master == master and may_change(request, slave)
            for request in [flight.request for flight in self._in_flight.values()]
            + list(self._retries)
        ):
            return True
        return super()._change_pending(master, slave)

    def _change_waits_for(self, slave: int) -> bool:
        """Also a write outstanding or due for a retry: it may run after this read's answer."""
        outstanding = [flight.request for flight in self._in_flight.values()]
        if any(may_change(request, slave) for request in [*outstanding, *self._retries]):
            return True
        return super()._change_waits_for(slave)

    def _store_cache(self, request: LineRequest, response: bytes, now: float) -> None:
        flight = self._completing
        slave = request.slave
        if flight is not None and flight.epoch != (
            self._write_epoch.get(slave, 0) + self._broadcast_epoch
        ):
            return  # a write was submitted after this read went: its answer may be older
        super()._store_cache(request, response, now)

    def _deliver(self, request: LineRequest, pdu: bytes, outcome: Outcome, wire: float) -> None:
        if not request.answered:
            self._close_open(request)
        for follower in request.followers:
            if not follower.answered:
                self._close_open(follower)
        super()._deliver(request, pdu, outcome, wire)

    def _mark_open(self, request: LineRequest) -> None:
        """``request`` is now outstanding for the ordering rule, until finally answered."""
        key = (request.master, request.slave)
        write = not fc.is_safe_to_retry(request.pdu)
        counts = self._open.get(key)
        if counts is None:
            counts = self._open[key] = [0, 0]
        counts[0] += 1
        if write:
            counts[1] += 1
        self._opened[request] = (key, write)

    def _close_open(self, request: LineRequest) -> None:
        """``request`` is finally answered (or leaves the line): it holds nothing back now."""
        opened = self._opened.pop(request, None)
        if opened is None:
            return
        key, write = opened
        counts = self._open[key]
        counts[0] -= 1
        if write:
            counts[1] -= 1
        if counts[0] == 0:
            del self._open[key]
