"""A standby's forwarding: its masters' requests go to the active gateway's Modbus TCP
listener, and the active's answers come back to exactly the requests they answer.

Theory of operation. The standby of a redundant pair never transmits on the bus, yet
its masters stay served: each request the master side would hand a line (the
``Bus.submit`` seam: a ``LineRequest`` and its line name) is sent to the peer under the
unit id the peer routes to that same line and slave (``units``: both gateways of a pair
run the same routes; the map is the routing table's own, ``RouteTable.units``, replaced
with the table at every reload). Each master's rules and its audit record are applied
here, where the master is connected, before the request reaches ``submit``.

One TCP connection to the peer per master (keyed by ``request.master``, opened on first
need without blocking the loop, ``TCP_NODELAY``). The active's fair queue shares a line
among masters by connection, so each forwarded master gets its own share there: the
forwarding link's share is weighted by the number of masters it carries, and one busy
master behind the standby cannot starve the others, nor they it.

Exactness (an answer reaches only the request it answers). Every forwarded request has
its own MBAP transaction id on its connection. A frame from the peer is delivered only
when its transaction id is pending and it can answer that request (its unit, its
function or function | 0x80, and for a read its byte count or a write's echo:
``check_identity``). Anything else is counted as ``discarded`` and logged at a bounded
rate; the connection is closed, since its stream can no longer be trusted, and its
pending requests are answered 0x0B. A request not answered within ``timeout`` is
answered 0x0B and its transaction id stays reserved (``LOST_TIDS`` per connection, the
oldest freed first; ids are handed out in sequence, so a freed one returns only after
65,536 others): its late answer is recognised and dropped (``late``). A refused, timed
out or lost connection answers what is pending 0x0A, and so is every request for
``backoff`` after a connection attempt failed; the next request after that tries again.
While ``peer_active`` is false every request is answered 0x0A at once, without any
connection: a standby never forwards to a peer that is itself standby.

A broadcast (slave 0) is forwarded once as unit 0, however many broadcast lines the
master side hands it to (it submits one request per line, sharing one reply callback:
those requests are answered together). It completes (``Outcome.BROADCAST``) once its
frame is handed to the peer's connection, as a line completes it once it is on the
wire; the peer answers it only with ``broadcast_reply`` set, and that answer is dropped.

Bounds: at most ``max_pending`` requests per master (0x06 beyond), ``LOST_TIDS`` lost
transaction ids per connection, and one connection per master the listener admitted.
"""

from __future__ import annotations

import asyncio
import logging
import socket
from collections import deque
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from typing import cast

from ...core import pdu as fc
from ...core.errors import ExceptionCode, FramingError, ResponseError
from ...core.line import LineRequest, no_reply
from ...core.mbap import MbapDecoder, MbapFrame, encode_mbap
from ...core.outcome import Outcome
from ...core.rtu import check_identity
from ...logs import RateLimitedLogger

log = logging.getLogger("gateway.peer_forward")

#: Requests of one master waiting for the peer, as a line's ``max_queue_per_master``.
MAX_PENDING_PER_MASTER = 32
#: Transaction ids of timed-out requests kept reserved per connection (oldest freed first).
LOST_TIDS = 256
#: How long requests are answered 0x0A after a connection attempt to the peer failed.
FIRST_BACKOFF_S = 0.25
MAX_BACKOFF_S = 1.0
#: Latencies kept for percentiles (the most recent answers).
RECENT_LATENCIES = 4096
#: Window of the rate-limited log of frames that answered nothing.
LOG_WINDOW_S = 60.0

#: The peer's own gateway exceptions, counted as the path's outcomes rather than a slave's.
_GATEWAY_OUTCOMES: dict[int, Outcome] = {
    ExceptionCode.GATEWAY_PATH_UNAVAILABLE: Outcome.NO_ROUTE,
    ExceptionCode.GATEWAY_TARGET_FAILED: Outcome.TARGET_FAILED,
}

Reply = Callable[[bytes, Outcome], None]


@dataclass(slots=True)
class ForwardStats:
    """What forwarding did, counted: plain integers the hot path only adds to."""

    forwarded: int = 0  #: requests sent to the peer (a broadcast once)
    answered: int = 0  #: the peer's answers delivered to their requests
    unavailable: int = 0  #: answered 0x0A here: peer not active, unreachable, no route
    failed: int = 0  #: answered 0x0B here: no answer in time, or an untrustworthy stream
    busy: int = 0  #: answered 0x06 here: the master's pending bound reached
    discarded: int = 0  #: frames from the peer that answered nothing pending
    late: int = 0  #: answers to requests already answered 0x0B, dropped
    latency_sum: float = 0.0  #: seconds from submit to answer, summed over ``answered``
    recent: deque[float] = field(default_factory=lambda: deque(maxlen=RECENT_LATENCIES))

    def by_outcome(self) -> dict[str, int]:
        """The counts as ``modbus_gateway_redundancy_forwarded_total`` labels them."""
        return {
            "forwarded": self.forwarded, "answered": self.answered,
            "path_unavailable": self.unavailable, "target_failed": self.failed,
            "busy": self.busy, "discarded": self.discarded, "late": self.late,
        }  # fmt: skip

    def observe(self, latency: float) -> None:
        """One answer delivered after ``latency`` seconds."""
        self.answered += 1
        self.latency_sum += latency
        self.recent.append(latency)


@dataclass(slots=True)
class _Pending:
    """One forwarded request (and, for a broadcast, the other lines' copies of it)."""

    request: LineRequest
    unit: int
    tid: int
    submitted: float
    deadline: float
    key: Reply  #: the reply callback as submitted: a broadcast's copies share it
    followers: list[LineRequest] = field(default_factory=list)
    outcome: Outcome | None = None  #: a broadcast's, once completed


def _answer(request: LineRequest, pdu: bytes, outcome: Outcome) -> None:
    """Hand ``request`` its one answer (a second goes nowhere); a broken callback is logged."""
    request.answered = True
    reply, request.reply = request.reply, no_reply
    try:
        reply(pdu, outcome)
    except Exception:  # a boundary: one master's broken reply path must not cost the rest
        log.exception("forwarding: handing an answer back failed")


def _exception(request: LineRequest, code: ExceptionCode, outcome: Outcome) -> None:
    _answer(request, fc.exception_pdu(request.pdu[0], code), outcome)


class PeerForwarder:
    """Forwards masters' requests to the active peer's Modbus TCP listener."""

    def __init__(
        self,
        host: str,
        port: int,
        units: Mapping[tuple[str, int], int],
        loop: asyncio.AbstractEventLoop,
        *,
        timeout: float,
        max_pending: int = MAX_PENDING_PER_MASTER,
        local_host: str | None = None,
    ) -> None:
        self.host = host
        #: The source address of the connections (this gateway's listener address when it
        #: is a specific one): the peer then knows them as this gateway's and, standing by
        #: itself, never forwards them back.
        self.local_addr = None if local_host is None else (local_host, 0)
        self.port = port
        #: (line, slave) -> the unit id sent for it: the routing table's (``reroute``).
        self.units: Mapping[tuple[str, int], int] = units
        self.timeout = timeout
        self.max_pending = max_pending
        #: Set by the role logic: whether the peer answers as active. False: 0x0A at once.
        self.peer_active = False
        self.stats = ForwardStats()
        self._loop = loop
        self._links: dict[Hashable, _PeerLink] = {}
        self._retry_at = 0.0  # loop time before which connecting is not tried again
        self._backoff = FIRST_BACKOFF_S
        self._faults = RateLimitedLogger(log, loop, window=LOG_WINDOW_S)

    @property
    def connections(self) -> int:
        """Connections to the peer open or being opened (one per master)."""
        return len(self._links)

    def submit(self, line: str, request: LineRequest) -> bool:
        """Forward ``request`` (for ``line``); its answer comes through ``request.reply``.

        Always ``True``, as ``Bus.submit``: what cannot be forwarded is answered at once
        (0x0A peer not active, unreachable or no unit for the slave; 0x06 too many pending).
        """
        if not self.peer_active:
            return self._unavailable(request)
        unit = 0 if request.broadcast else self.units.get((line, request.slave))
        if unit is None:
            return self._unavailable(request)
        link = self._links.get(request.master)
        if link is not None and request.broadcast and link.joins_broadcast(request):
            return True
        if link is not None and len(link.pending) >= self.max_pending:
            self.stats.busy += 1
            _exception(request, ExceptionCode.SERVER_DEVICE_BUSY, Outcome.BUSY)
            return True
        if link is None:
            if self._loop.time() < self._retry_at:
                return self._unavailable(request)
            link = self._links[request.master] = _PeerLink(self, request.master)
            link.connect()
        self.stats.forwarded += 1
        link.send(request, unit)
        return True

    def reroute(self, units: Mapping[tuple[str, int], int]) -> None:
        """The routing table changed (start, reload): send each request under its new unit."""
        self.units = units

    def cancel(self, master: Hashable) -> None:
        """``master`` left: its pending requests are dropped and its connection closed."""
        link = self._links.pop(master, None)
        if link is not None:
            link.close(None)

    def close(self) -> None:
        """Close every connection (a stop): what is pending is answered 0x0A."""
        links, self._links = self._links, {}
        for link in links.values():
            link.close(Outcome.NO_ROUTE)

    def _unavailable(self, request: LineRequest) -> bool:
        self.stats.unavailable += 1
        _exception(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE)
        return True

    # -- the links' reports ----------------------------------------------------------------

    def _connected(self) -> None:
        self._backoff = FIRST_BACKOFF_S

    def _connect_failed(self, link: _PeerLink, error: BaseException) -> None:
        """The peer refused or did not answer: 0x0A for ``backoff``, then try again."""
        self._retry_at = self._loop.time() + self._backoff
        self._backoff = min(self._backoff * 2, MAX_BACKOFF_S)
        self._faults.note(f"peer {self.host}:{self.port}", "unreachable",
                          f"{error or type(error).__name__}; answering 0x0A")  # fmt: skip
        self._forget(link)

    def _forget(self, link: _PeerLink) -> None:
        if self._links.get(link.master) is link:
            del self._links[link.master]

    def _discarded(self, link: _PeerLink, why: str) -> None:
        self.stats.discarded += 1
        self._faults.note(f"peer {self.host}:{self.port}", "answer to nothing pending",
                          f"{why}; closing that connection",
                          plural="answers to nothing pending")  # fmt: skip
        self._forget(link)


class _PeerLink(asyncio.Protocol):
    """One master's connection to the peer: its transaction ids, deadlines and answers."""

    def __init__(self, forwarder: PeerForwarder, master: Hashable) -> None:
        self.forwarder = forwarder
        self.master = master
        #: Requests sent or waiting for the connection, by transaction id, in deadline order.
        self.pending: dict[int, _Pending] = {}
        #: Transaction ids answered without their answer: (unit, request PDU, broadcast).
        self.lost: dict[int, tuple[int, bytes, bool]] = {}
        self.closed = False
        self._loop = forwarder._loop
        self._next_tid = 0
        self._unsent: list[bytes] = []  # frames waiting for the connection
        self._transport: asyncio.Transport | None = None
        self._connecting: asyncio.Task[None] | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._decoder = MbapDecoder()
        self._last_broadcast: _Pending | None = None

    # -- connecting ------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the connection in the background; requests queue meanwhile."""
        self._connecting = self._loop.create_task(self._connect())

    async def _connect(self) -> None:
        forwarder = self.forwarder
        try:
            await asyncio.wait_for(
                self._loop.create_connection(
                    lambda: self, forwarder.host, forwarder.port, local_addr=forwarder.local_addr
                ),
                forwarder.timeout,
            )
        except (OSError, TimeoutError) as error:
            self._connecting = None
            if not self.closed:
                forwarder._connect_failed(self, error)
                self.close(Outcome.NO_ROUTE)
            return
        self._connecting = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # uvloop's TCP transport is not an ``asyncio.Transport`` subclass: a cast, no check.
        transport = cast(asyncio.Transport, transport)
        if self.closed:  # cancelled while connecting
            transport.abort()
            return
        self._transport = transport
        sock = transport.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.forwarder._connected()
        unsent, self._unsent = self._unsent, []
        if unsent:
            transport.write(b"".join(unsent))
        self._complete_broadcasts()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed:
            self.forwarder._forget(self)
            self.close(Outcome.NO_ROUTE)

    # -- sending ---------------------------------------------------------------------------

    def _take_tid(self) -> int:
        tid = self._next_tid
        while tid in self.pending or tid in self.lost:
            tid = (tid + 1) & 0xFFFF
        self._next_tid = (tid + 1) & 0xFFFF
        return tid

    def send(self, request: LineRequest, unit: int) -> None:
        """Send ``request`` as ``unit`` under a fresh transaction id (or queue it)."""
        now = self._loop.time()
        tid = self._take_tid()
        record = _Pending(request, unit, tid, now, now + self.forwarder.timeout, request.reply)
        self.pending[tid] = record
        frame = encode_mbap(tid, unit, request.pdu)
        if request.broadcast:
            self._last_broadcast = record
        if self._transport is None:
            self._unsent.append(frame)
        else:
            self._transport.write(frame)
            if request.broadcast:
                self._complete_broadcasts()
                return
        if self._timer is None:
            self._timer = self._loop.call_at(record.deadline, self._expire)

    def joins_broadcast(self, request: LineRequest) -> bool:
        """A copy of the broadcast just forwarded (another line's): answered with it."""
        record = self._last_broadcast
        if record is None or record.key is not request.reply or record.request.pdu != request.pdu:
            return False
        if record.outcome is None:
            record.followers.append(request)
        else:
            _answer(request, b"", record.outcome)
        return True

    def _complete_broadcasts(self) -> None:
        """Broadcasts handed to the connection are complete: their tids wait for answers."""
        for record in [r for r in self.pending.values() if r.request.broadcast]:
            del self.pending[record.tid]
            self._lose(record, broadcast=True)
            self._settle(record, b"", Outcome.BROADCAST)

    # -- answers ---------------------------------------------------------------------------

    def data_received(self, data: bytes) -> None:
        try:
            self._decoder.feed(data)
            while not self.closed:
                frame = self._decoder.next_frame()
                if frame is None:
                    return
                self._take(frame)
        except FramingError as error:
            self._distrust(f"a frame no Modbus TCP server sends ({error.reason})")

    def _take(self, frame: MbapFrame) -> None:
        tid, unit, pdu = frame
        record = self.pending.get(tid)
        if record is None:
            lost = self.lost.pop(tid, None)
            why = "not pending" if lost is None else self._mismatch(lost[0], lost[1], unit, pdu)
            if why:
                self._distrust(f"transaction id {tid}: {why}")
            elif lost is not None and not lost[2]:
                self.forwarder.stats.late += 1  # a broadcast's answer is no news
            return
        why = self._mismatch(record.unit, record.request.pdu, unit, pdu)
        if why:
            self._distrust(f"transaction id {tid}: {why}")
            return
        del self.pending[tid]
        self.forwarder.stats.observe(self._loop.time() - record.submitted)
        if pdu[0] & fc.EXCEPTION_FLAG and len(pdu) >= 2:
            outcome = _GATEWAY_OUTCOMES.get(pdu[1], Outcome.SLAVE_EXCEPTION)
        else:
            outcome = Outcome.OK
        self._settle(record, pdu, outcome)

    @staticmethod
    def _mismatch(unit: int, request_pdu: bytes, got_unit: int, pdu: bytes) -> str:
        """Why ``pdu`` from ``got_unit`` cannot answer the request (empty when it can)."""
        if not pdu:
            return "an empty answer"
        try:
            check_identity(unit, request_pdu[0], request_pdu, got_unit, pdu)
        except ResponseError as error:
            return str(error)
        return ""

    def _distrust(self, why: str) -> None:
        """A frame that answers nothing pending: the stream cannot be trusted any more."""
        self.forwarder._discarded(self, why)
        self.close(Outcome.TARGET_FAILED)

    # -- time ------------------------------------------------------------------------------

    def _expire(self) -> None:
        """Answer 0x0B what is past its deadline; keep its transaction id reserved."""
        self._timer = None
        now = self._loop.time()
        expired: list[_Pending] = []
        for record in self.pending.values():  # in deadline order
            if record.deadline > now:
                self._timer = self._loop.call_at(record.deadline, self._expire)
                break
            expired.append(record)
        for record in expired:
            del self.pending[record.tid]
            self._lose(record, broadcast=False)
        self.forwarder.stats.failed += len(expired)
        for record in expired:
            code = ExceptionCode.GATEWAY_TARGET_FAILED
            self._settle(record, fc.exception_pdu(record.request.pdu[0], code),
                         Outcome.TARGET_FAILED)  # fmt: skip

    def _lose(self, record: _Pending, *, broadcast: bool) -> None:
        lost = self.lost
        lost[record.tid] = (record.unit, record.request.pdu, broadcast)
        if len(lost) > LOST_TIDS:
            del lost[next(iter(lost))]  # the oldest: its id returns last in the sequence

    # -- ends ------------------------------------------------------------------------------

    def _settle(self, record: _Pending, pdu: bytes, outcome: Outcome) -> None:
        """Answer a record's request, and a broadcast's copies with it."""
        record.outcome = outcome
        followers, record.followers = record.followers, []
        _answer(record.request, pdu, outcome)
        for follower in followers:
            _answer(follower, pdu, outcome)

    def close(self, outcome: Outcome | None) -> None:
        """Close the connection; pending requests are answered with ``outcome``'s exception
        (0x0A, 0x0B), or dropped (``None``: their master left)."""
        if self.closed:
            return
        self.closed = True
        for handle in (self._timer, self._connecting):
            if handle is not None:
                handle.cancel()
        self._timer = self._connecting = None
        if self._transport is not None:
            self._transport.abort()
        pending, self.pending = list(self.pending.values()), {}
        self.lost.clear()
        self._unsent.clear()
        stats = self.forwarder.stats
        for record in pending:
            if outcome is None:
                self._settle(record, b"", Outcome.DROPPED)
            elif outcome is Outcome.TARGET_FAILED:
                stats.failed += 1
                code = ExceptionCode.GATEWAY_TARGET_FAILED
                self._settle(record, fc.exception_pdu(record.request.pdu[0], code), outcome)
            else:
                stats.unavailable += 1
                code = ExceptionCode.GATEWAY_PATH_UNAVAILABLE
                self._settle(record, fc.exception_pdu(record.request.pdu[0], code), outcome)
