"""Several requests outstanding on one MBAP line (``max_in_flight`` > 1): the flight wire.

Theory of operation. On a line framed by MBAP (``kind = "tcp"``, and any kind whose
framing numbers its requests with ``TransactionIds``) every answer carries the
transaction id (TID) of its request, so answers need not come in order and need not
be told apart by their shape. ``FlightWire`` is the wire strategy with up to
``max_in_flight`` attempts, each with its own TID and its own deadline; an answer is
matched by its TID, in any order. Everything else is the machine's own: fair order
over masters, per-master and line-wide bounds, isolation of suspect and down slaves,
coalescing, the cache, safe-only retries (a retry is sent under a new TID), stop,
abandon, cancel and port loss (every outstanding attempt answered once, 0x0A).

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
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Final

from .. import pdu as fc
from ..errors import FramingError, ResponseError
from ..mbap import MbapDecoder, TransactionIds
from ..outcome import DiscardReason
from ..rtu import RtuFrame, check_identity
from .fair_queue import Master
from .records import INFINITY, Attempt, LineRequest
from .wire import Finding, Found, Wire, discarded

#: The most requests ``max_in_flight`` may allow on one connection.
MAX_IN_FLIGHT: Final = 64
#: TIDs of timed-out attempts kept reserved (their answers may still come).
_LOST_TIDS_KEPT: Final = 4096
#: Weight of the newest transaction in the estimate charged when a request is sent.
_ESTIMATE_WEIGHT: Final = 0.125

OpenKey = tuple[Hashable, int]


class FlightWire(Wire):
    """Up to ``capacity`` attempts outstanding, matched by TID; see the module doc."""

    def __init__(
        self, ids: TransactionIds, max_in_flight: int, encode: Callable[[int, bytes], bytes]
    ) -> None:
        if not 1 <= max_in_flight <= MAX_IN_FLIGHT:
            raise ValueError(f"max_in_flight {max_in_flight} outside 1..{MAX_IN_FLIGHT}")
        super().__init__(
            quiet_line=False, concurrent=True, capacity=max_in_flight, orders_outstanding=True
        )
        self.ids = ids
        self.encode = encode  # the framing's: each call takes the next transaction id
        self.flights: dict[int, Attempt] = {}  # TID -> attempt
        self.stream = MbapDecoder()
        self.out_of_step = False
        #: TID of a timed-out attempt -> its slave, when it was sent, its function.
        self.lost_tids: dict[int, tuple[int, float, int]] = {}
        # (master, slave) -> [requests outstanding, of which with side effects]
        self.open: dict[OpenKey, list[int]] = {}
        self.opened_by: dict[LineRequest, tuple[OpenKey, bool]] = {}  # by identity

    def timer(self) -> float:
        when = INFINITY
        for flight in self.flights.values():
            if flight.deadline < when:
                when = flight.deadline
        return when

    def on_wire_for(self, master: Hashable) -> int:
        return sum(1 for flight in self.flights.values() if flight.request.master == master)

    def on_wire_to(self, slave: int) -> bool:
        return any(flight.request.slave == slave for flight in self.flights.values())

    def requests(self) -> list[LineRequest]:
        return [flight.request for flight in self.flights.values()]

    def overtakable(self) -> list[LineRequest]:
        """Every outstanding request: a device may run a later one first."""
        return self.requests()

    # -- the connection ------------------------------------------------------------------

    def opened(self) -> None:
        """A new connection: a new byte stream, no answers owed on it."""
        self.stream = MbapDecoder()
        self.out_of_step = False
        self.lost_tids.clear()

    def lost(self) -> None:
        self.stream = MbapDecoder()
        self.lost_tids.clear()

    def receive(self, data: bytes, now: float) -> list[Finding]:
        """Bytes from the connection: each complete frame goes to the attempt its TID names."""
        found: list[Finding] = []
        if self.out_of_step:
            found.append(discarded(DiscardReason.LATE, len(data)))
            return found
        stream = self.stream
        try:
            stream.feed(data)
            while (frame := stream.next_frame()) is not None:
                self._take(frame.transaction_id, frame.unit_id, frame.pdu, now, found)
        except FramingError:
            # Out of step: every later byte is suspect. The machine reconnects on this.
            self.out_of_step = True
            found.append(discarded(DiscardReason.BAD_HEADER, 1))
        return found

    def _take(self, tid: int, unit: int, pdu: bytes, now: float, found: list[Finding]) -> None:
        flight = self.flights.get(tid)
        if flight is None:
            lost = self.lost_tids.pop(tid, None)
            found.append(
                discarded(DiscardReason.UNEXPECTED_TID, 1, lost[0] if lost is not None else 0)
            )
            if lost is not None:  # a timed-out attempt's answer: the slave is alive, slow
                slave, sent_at, function = lost
                found.append(
                    Finding(Found.LATE_ANSWER, slave=slave, sent_at=sent_at, function=function)
                )
            return
        request = flight.request
        try:
            check_identity(unit, request.pdu[0], request.pdu, unit, pdu)
        except ResponseError as error:
            # Its TID but not its answer: discarded; the attempt waits on to its deadline.
            found.append(discarded(DiscardReason(error.kind), 1, request.slave))
            return
        self.estimate += (now - flight.sent_at - self.estimate) * _ESTIMATE_WEIGHT
        self.end(flight)
        found.append(Finding(Found.COMPLETE, flight, RtuFrame(unit, pdu)))

    def expire(self, now: float) -> list[Finding]:
        """Attempts past their deadline fail; their TIDs stay reserved."""
        found: list[Finding] = []
        expired = [flight for flight in self.flights.values() if now >= flight.deadline]
        for flight in expired:
            lost = self.lost_tids
            request = flight.request
            lost[flight.tid] = (request.slave, flight.sent_at, request.pdu[0])
            if len(lost) > _LOST_TIDS_KEPT:
                del lost[next(iter(lost))]
            self.end(flight)
            found.append(Finding(Found.FAILED, flight))
        return found

    # -- choosing and sending ------------------------------------------------------------

    def _may_go(self, request: LineRequest) -> bool:
        """The ordering rule for one master's requests to one unit (see the module docs)."""
        counts = self.open.get((request.master, request.slave))
        if counts is None:
            return True
        outstanding, writes = counts
        own = self.opened_by.get(request)  # a lane retry counts itself: not an earlier one
        if own is not None:
            outstanding -= 1
            writes -= own[1]
        if writes:  # a write of this master to this unit is outstanding
            return False
        return outstanding == 0 or fc.is_safe_to_retry(request.pdu)

    def first_eligible(self, master: Master, now: float) -> LineRequest | None:
        """The oldest request of ``master`` that may go now under the ordering rule."""
        held: set[int] | None = None
        for request in master.queue:
            if request.broadcast:
                if held or self.parts.order.broadcast_held(master.key, request):
                    return None  # its master's earlier requests go first
                if self.flights:
                    self.draining = True
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

    def may_go(self, request: LineRequest, now: float) -> bool:
        return self._may_go(request)

    def start(self, attempt: Attempt, frame: bytes) -> bytes:
        """``frame`` was encoded with the next transaction id: another one while that id
        still names an attempt or a lost one (never two meanings for one id)."""
        request = attempt.request
        if request not in self.opened_by:
            self._mark_open(request)
        tid = self.ids.current
        while tid in self.flights or tid in self.lost_tids:
            frame = self.encode(request.slave, request.pdu)
            tid = self.ids.current
        attempt.tid = tid
        self.flights[tid] = attempt
        self.outstanding = len(self.flights)
        return frame

    def end(self, attempt: Attempt) -> None:
        if self.flights.get(attempt.tid) is attempt:
            del self.flights[attempt.tid]
            self.outstanding = len(self.flights)

    def take_all(self) -> list[Attempt]:
        flights = list(self.flights.values())
        self.flights.clear()
        self.outstanding = 0
        return flights

    def may_cache(self, attempt: Attempt, epoch: int) -> bool:
        """Not when a write was submitted after this read went: its answer may be older."""
        return attempt.epoch == epoch

    def uncacheable(self) -> None:
        """Reads sent while the cache was off were not checked for a change outstanding
        beside them (``start``): their answers may predate it, so none is kept."""
        for attempt in self.flights.values():
            attempt.epoch = -1

    # -- the ordering rule's accounts ----------------------------------------------------

    def joined(self, request: LineRequest) -> None:
        """A read that joins another's counts as its master's outstanding request to that
        unit until it is answered (its write waits for it)."""
        self._mark_open(request)

    def released(self, request: LineRequest) -> None:
        if not request.answered:
            self.forget(request)
        for follower in request.followers:
            if not follower.answered:
                self.forget(follower)

    def _mark_open(self, request: LineRequest) -> None:
        """``request`` is now outstanding for the ordering rule, until finally answered."""
        key = (request.master, request.slave)
        write = not fc.is_safe_to_retry(request.pdu)
        counts = self.open.get(key)
        if counts is None:
            counts = self.open[key] = [0, 0]
        counts[0] += 1
        if write:
            counts[1] += 1
        self.opened_by[request] = (key, write)

    def forget(self, request: LineRequest) -> None:
        """``request`` is finally answered (or leaves the line): it holds nothing back now."""
        opened = self.opened_by.pop(request, None)
        if opened is None:
            return
        key, write = opened
        counts = self.open[key]
        counts[0] -= 1
        if write:
            counts[1] -= 1
        if counts[0] == 0:
            del self.open[key]
