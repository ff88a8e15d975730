"""A standby's forwarding: its masters' requests go to the active gateway's Modbus TCP
listener, and the active's answers come back to exactly the requests they answer.

Theory of operation. The standby of a redundant pair never transmits on the bus, yet
its masters stay served: each request the master side would hand a line (the
``Bus.submit`` seam: a ``LineRequest`` and its line name) is sent to the peer under the
unit id the peer routes to that same line and slave (``units``: both gateways of a pair
run the same routes; the map is the routing table's own, ``RouteTable.units``, replaced
with the table at every reload). Each master's rules and its audit record are applied
here, where the master is connected, before the request reaches ``submit``: the
standby's record is the one that names the master, so a forwarded request is marked
``sent`` once its frame is handed to the link (a write answered 0x0B, or lost with the
link, is then ``unknown``, never missing).

Shares. One TCP connection (a *link*) to the peer per source address of the masters
(the address the standby's listener admitted them from; a master without one, such as
a serial master, has a link of its own), opened on first need without blocking the loop,
``TCP_NODELAY``. A link holds at most ``LINK_WINDOW`` requests outstanding, taken from
its masters' queues in turn (``core.forwarding.Rounds``: one request per master per
round, each master's order kept). So the active, which shares its lines and its
connection slots among connections, sees one connection per address behind the standby,
whatever the number of connections that address holds there: a host with many
connections takes one slot and one share at the active, as many as a host with one.

Exactness (an answer reaches only the request it answers): the core's in-flight tracking
(``core.forwarding.Flights``: transaction ids from ``TransactionIds``, deadlines, matching
by ``check_identity``, lost ids kept reserved). A frame that answers nothing outstanding
or reserved is counted as ``discarded`` and logged at a bounded rate; the link is closed,
since its stream can no longer be trusted, and its requests are answered 0x0B. A request
not answered within ``timeout`` of its submission is answered 0x0B (its id stays
reserved: its late answer is recognised and dropped, ``late``). A refused, timed out or
lost link answers what it holds 0x0A, and so is every request for ``backoff`` after a
connection attempt failed; the next request after that tries again. While
``peer_active`` is false every request is answered 0x0A at once, without any
connection: a standby never forwards to a peer that is itself standby.

A broadcast (slave 0) is forwarded once as unit 0, however many broadcast lines the
master side hands it to (it submits one request per line, sharing one reply callback:
those requests are answered together). It completes (``Outcome.BROADCAST``) once its
frame is handed to the link, as a line completes it once it is on the wire; the peer
answers it only with ``broadcast_reply`` set, and that answer is dropped.

Bounds: at most ``max_pending`` requests per master waiting or outstanding (0x06
beyond), ``LINK_WINDOW`` outstanding and ``LOST_TIDS`` reserved ids per link, and one
link per source address the listener admitted.
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
from ...core.errors import ExceptionCode, FramingError
from ...core.forwarding import INFINITY, Answered, Flights, Late, Match, Rounds
from ...core.line import LineRequest, no_reply
from ...core.mbap import MbapDecoder
from ...core.outcome import Outcome
from ...logs import RateLimitedLogger

log = logging.getLogger("gateway.peer_forward")

#: Requests of one master waiting or outstanding, as a line's ``max_queue_per_master``.
MAX_PENDING_PER_MASTER = 32
#: Requests outstanding on one link (the active's default ``max_pipeline``).
LINK_WINDOW = 16
#: Transaction ids of given-up requests kept reserved per link (oldest freed first).
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

    forwarded: int = 0  #: requests taken for the peer (a broadcast once)
    answered: int = 0  #: the peer's answers delivered to their requests
    unavailable: int = 0  #: answered 0x0A here: peer not active, unreachable, no route
    failed: int = 0  #: answered 0x0B here: no answer in time, or an untrustworthy stream
    busy: int = 0  #: answered 0x06 here: the master's pending bound reached
    discarded: int = 0  #: frames from the peer that answered nothing outstanding
    late: int = 0  #: answers to requests already answered 0x0B, dropped
    latency_sum: float = 0.0  #: seconds from submit to answer, summed over ``answered``
    recent: deque[float] = field(default_factory=lambda: deque(maxlen=RECENT_LATENCIES))

    def by_outcome(self) -> dict[str, int]:
        """The counts as ``modbus_gateway_redundancy_forwarded_total`` labels them."""
        return {
            "forwarded": self.forwarded,
            "answered": self.answered,
            "path_unavailable": self.unavailable,
            "target_failed": self.failed,
            "busy": self.busy,
            "discarded": self.discarded,
            "late": self.late,
        }

    def observe(self, latency: float) -> None:
        """One answer delivered after ``latency`` seconds."""
        self.answered += 1
        self.latency_sum += latency
        self.recent.append(latency)


@dataclass(slots=True, eq=False)
class _Forwarded:
    """One forwarded request (and, for a broadcast, the other lines' copies of it)."""

    request: LineRequest
    unit: int
    submitted: float
    key: Reply  #: the reply callback as submitted: a broadcast's copies share it
    followers: list[LineRequest] = field(default_factory=list)
    outcome: Outcome | None = None  #: a broadcast's, once completed


def link_key(master: Hashable) -> Hashable:
    """The link a master's requests take: its source address's, else its own."""
    source = getattr(master, "source", None)
    return ("source", source) if isinstance(source, str) and source else master


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


def _settle(record: _Forwarded, pdu: bytes, outcome: Outcome) -> None:
    """Answer a record's request, and a broadcast's copies with it."""
    record.outcome = outcome
    followers, record.followers = record.followers, []
    _answer(record.request, pdu, outcome)
    for follower in followers:
        _answer(follower, pdu, outcome)


def _settle_exception(record: _Forwarded, code: ExceptionCode, outcome: Outcome) -> None:
    _settle(record, fc.exception_pdu(record.request.pdu[0], code), outcome)


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
        window: int = LINK_WINDOW,
        local_host: str | None = None,
    ) -> None:
        self.host = host
        #: The source address of the links (this gateway's listener address when it is a
        #: specific one): the peer then knows them as this gateway's and, standing by
        #: itself, never forwards them back.
        self.local_addr = None if local_host is None else (local_host, 0)
        self.port = port
        #: (line, slave) -> the unit id sent for it: the routing table's (``reroute``).
        self.units: Mapping[tuple[str, int], int] = units
        self.timeout = timeout
        self.max_pending = max_pending
        self.window = window
        #: Set by the role logic: whether the peer answers as active. False: 0x0A at once.
        self.peer_active = False
        self.stats = ForwardStats()
        self._loop = loop
        self._links: dict[Hashable, _PeerLink] = {}  # by ``link_key``
        self._retry_at = 0.0  # loop time before which connecting is not tried again
        self._backoff = FIRST_BACKOFF_S
        self._faults = RateLimitedLogger(log, loop, window=LOG_WINDOW_S)

    @property
    def connections(self) -> int:
        """Links to the peer open or being opened (one per source address of the masters)."""
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
        key = link_key(request.master)
        link = self._links.get(key)
        if link is not None and request.broadcast and link.joins_broadcast(request):
            return True
        if link is None:
            if self._loop.time() < self._retry_at:
                return self._unavailable(request)
            link = self._links[key] = _PeerLink(self, key)
            link.connect()
        if not link.add(request, unit):
            self.stats.busy += 1
            _exception(request, ExceptionCode.SERVER_DEVICE_BUSY, Outcome.BUSY)
            return True
        self.stats.forwarded += 1
        return True

    def reroute(self, units: Mapping[tuple[str, int], int]) -> None:
        """The routing table changed (start, reload): send each request under its new unit."""
        self.units = units

    def cancel(self, master: Hashable) -> None:
        """``master`` left: its requests are dropped; its link closes once no master is on it."""
        link = self._links.get(link_key(master))
        if link is not None:
            link.leave(master)

    def close(self) -> None:
        """Close every link (a stop): what is pending is answered 0x0A."""
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
        self._faults.note(
            f"peer {self.host}:{self.port}",
            "unreachable",
            f"{error or type(error).__name__}; answering 0x0A",
        )
        self._forget(link)

    def _forget(self, link: _PeerLink) -> None:
        if self._links.get(link.key) is link:
            del self._links[link.key]

    def _discarded(self, link: _PeerLink, why: str) -> None:
        self.stats.discarded += 1
        self._faults.note(
            f"peer {self.host}:{self.port}",
            "answer to nothing pending",
            f"{why}; closing that connection",
            plural="answers to nothing pending",
        )
        self._forget(link)


class _PeerLink(asyncio.Protocol):
    """One connection to the peer: its masters' turns (``Rounds``) and its requests in
    flight (``Flights``); this class only moves bytes and time."""

    def __init__(self, forwarder: PeerForwarder, key: Hashable) -> None:
        self.forwarder = forwarder
        self.key = key
        self.rounds: Rounds[_Forwarded] = Rounds(forwarder.max_pending)
        self.flights: Flights[_Forwarded] = Flights(LOST_TIDS)
        self.closed = False
        self._loop = forwarder._loop
        self._transport: asyncio.Transport | None = None
        self._connecting: asyncio.Task[None] | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = INFINITY
        self._decoder = MbapDecoder()
        self._last_broadcast: _Forwarded | None = None

    # -- connecting ------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the connection in the background; requests wait meanwhile."""
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
        self._pump()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed:
            self.forwarder._forget(self)
            self.close(Outcome.NO_ROUTE)

    # -- requests in ---------------------------------------------------------------------

    def add(self, request: LineRequest, unit: int) -> bool:
        """Queue ``request`` in its master's turn; False when the master's bound is reached."""
        now = self._loop.time()
        record = _Forwarded(request, unit, now, request.reply)
        if not self.rounds.add(request.master, record, now + self.forwarder.timeout):
            return False
        if request.broadcast:
            self._last_broadcast = record
        self._pump()
        return True

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

    def leave(self, master: Hashable) -> None:
        """``master`` left: what it has waiting is dropped, what it has outstanding too (the
        ids stay reserved: their answers are dropped); no master left, the link closes."""
        dropped = self.rounds.leave(master)
        for tid, flight in list(self.flights.outstanding.items()):
            if flight.item.request.master is master:
                self.flights.give_up(tid, expected=False)
                dropped.append(flight.item)
        for record in dropped:
            _settle(record, b"", Outcome.DROPPED)
        if not any(True for _ in self.rounds):
            self.forwarder._forget(self)
            self.close(None)
        else:
            self._pump()

    # -- sending ---------------------------------------------------------------------------

    def _pump(self) -> None:
        """Fill the window from the masters' turns, then arm the timer."""
        transport = self._transport
        if transport is not None and not self.closed:
            flights, rounds, window = self.flights, self.rounds, self.forwarder.window
            frames: list[bytes] = []
            handed: list[_Forwarded] = []
            while len(flights) < window and rounds:
                taken = rounds.next()
                assert taken is not None
                _master, record, deadline = taken
                request = record.request
                frames.append(flights.send(record, record.unit, request.pdu, deadline))
                request.sent = True  # the active may now execute it (the audit's ``unknown``)
                for follower in record.followers:
                    follower.sent = True
                if request.broadcast:  # complete once handed over; its id waits for nothing
                    flights.give_up(flights.ids.current, expected=False)
                    rounds.done(request.master)
                    handed.append(record)
            if frames:
                transport.write(b"".join(frames))
            for record in handed:
                _settle(record, b"", Outcome.BROADCAST)
        self._arm()

    def _arm(self) -> None:
        if self.closed:
            return
        when = min(self.flights.get_timer(), self.rounds.get_timer())
        if when == INFINITY:
            return
        if self._timer is None or when < self._timer_at:
            if self._timer is not None:
                self._timer.cancel()
            self._timer = self._loop.call_at(when, self._expire)
            self._timer_at = when

    # -- answers ---------------------------------------------------------------------------

    def data_received(self, data: bytes) -> None:
        try:
            self._decoder.feed(data)
            while not self.closed:
                frame = self._decoder.next_frame()
                if frame is None:
                    break
                self._take(self.flights.match(frame))
        except FramingError as error:
            self._distrust(f"a frame no Modbus TCP server sends ({error.reason})")
        self._pump()

    def _take(self, match: Match[_Forwarded]) -> None:
        stats = self.forwarder.stats
        if isinstance(match, Answered):
            record, pdu = match.item, match.pdu
            self.rounds.done(record.request.master)
            stats.observe(self._loop.time() - record.submitted)
            if pdu[0] & fc.EXCEPTION_FLAG and len(pdu) >= 2:
                outcome = _GATEWAY_OUTCOMES.get(pdu[1], Outcome.SLAVE_EXCEPTION)
            else:
                outcome = Outcome.OK
            _settle(record, pdu, outcome)
        elif isinstance(match, Late):
            stats.late += match.expected  # a broadcast's or a departed master's: no news
        else:
            self._distrust(match.why)

    def _distrust(self, why: str) -> None:
        """A frame that answers nothing outstanding: the stream cannot be trusted any more."""
        self.forwarder._discarded(self, why)
        self.close(Outcome.TARGET_FAILED)

    # -- time ------------------------------------------------------------------------------

    def _expire(self) -> None:
        """Answer 0x0B what is past its deadline, sent or still waiting its turn."""
        self._timer = None
        self._timer_at = INFINITY
        now = self._loop.time()
        expired = self.flights.expire(now)
        for record in expired:
            self.rounds.done(record.request.master)
        expired += self.rounds.expire(now)
        self.forwarder.stats.failed += len(expired)
        for record in expired:
            _settle_exception(record, ExceptionCode.GATEWAY_TARGET_FAILED, Outcome.TARGET_FAILED)
        self._pump()

    # -- ends ------------------------------------------------------------------------------

    def close(self, outcome: Outcome | None) -> None:
        """Close the link; its requests are answered with ``outcome``'s exception (0x0A,
        0x0B), or dropped (``None``: their masters left)."""
        if self.closed:
            return
        self.closed = True
        for handle in (self._timer, self._connecting):
            if handle is not None:
                handle.cancel()
        self._timer = self._connecting = None
        if self._transport is not None:
            self._transport.abort()
        records = self.flights.take_all() + self.rounds.take_all()
        stats = self.forwarder.stats
        for record in records:
            if outcome is None:
                _settle(record, b"", Outcome.DROPPED)
            elif outcome is Outcome.TARGET_FAILED:
                stats.failed += 1
                _settle_exception(record, ExceptionCode.GATEWAY_TARGET_FAILED, outcome)
            else:
                stats.unavailable += 1
                _settle_exception(record, ExceptionCode.GATEWAY_PATH_UNAVAILABLE, outcome)
