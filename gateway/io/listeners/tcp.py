"""The Modbus TCP server: many masters, several requests in flight on each.

Theory of operation: each connection owns an incremental ``MbapDecoder``. A
complete frame goes to the core's admission (``core.admission``: route,
authorize, the gateway's refusals, validate), which the connection only
executes: an answer given locally, a broadcast, or the request handed to its
line's ``Bus`` with a callback that writes the reply under the request's own
transaction id, in whatever order replies complete. A framing error closes that connection only.
When a master leaves, its queued requests are cancelled so nothing is sent on
its behalf.

Every connection's resources are bounded, whatever the master does:

- *Reading* stops (TCP back-pressure) for any of three reasons
  (``ReadPause``): ``max_pipeline`` requests are in flight; the replies not
  yet sent exceed ``max_pipeline`` full-size ADUs (``pause_writing``); or this
  turn of the loop's batch is used up. Bytes are read into a fixed 8 KiB
  buffer, so the decoder never holds more than one read.
- *Batches*: one turn of the event loop handles at most ``max_pipeline`` of a
  connection's requests, counting those answered locally (no route, invalid)
  until their replies are handed to the socket in one write; the rest wait for
  the next turn, after every other connection's. A flood of requests the
  gateway answers itself therefore costs other masters one batch per turn.
- *Unread replies*: a master whose send buffer stays full for
  ``send_timeout`` is closed. A connection the gateway closes is aborted:
  its buffers and descriptor are freed at once.

Admission happens at accept, with the peer's address from ``accept()``
itself, before a byte is read (so before a TLS handshake): the allow lists
(core's ``connection_admission.admit``; ``SourceScreen`` counts and logs), then
(``ModbusTcpServer._admit``) fair share, decided by core's
``connection_share``: while a slot is free every master is admitted (unless an
explicit ``max_connections_per_source`` cap, off by default, is reached); at
``max_connections``, under both ``when_full`` policies, a newcomer whose address
holds less than its fair share takes the place of the heaviest address's
longest-open connection that never sent a request. Otherwise, under
``close_oldest_idle`` only, the address holding the most connections yields its
longest-idle one with nothing in flight (a never-used one while any is open):
one idle for ``evict_min_idle`` to a newcomer of its own address or of one a
connection lighter, any to a newcomer whose address holds at least two fewer;
else the next heaviest address is tried, down to the newcomer's own; none:
refused. Only a complete request makes a master active (and used). The redundancy
peer's links (``pair_sources``) have a budget of their own, outside the others' count.
Connection events are logged at DEBUG and summarised at INFO once a minute;
faults a client can repeat at will are rate-limited per source and kind.

A reload judges every open connection again (``reevaluate``) with the same
decision as at accept (``core.connection_admission``), now with what the
handshake showed: one no longer admitted is closed as at a stop, alone (its
queued requests answered 0x0A, none sent), counted as ``no_longer_admitted``.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
import ssl
import time
from dataclasses import replace
from typing import TYPE_CHECKING, Final, Protocol, cast

from ...config import GatewayConfig, ListenerConfig, ServerConfig
from ...core import pdu as fc
from ...core.admission import AnswerLocally, Broadcast, Submit
from ...core.connection_admission import CertificateFacts, ConnectionFacts, NotAdmitted, admit
from ...core.connection_share import (
    Evict,
    OpenConnection,
    Refusal,
    Refuse,
    ShareLimits,
    admit_connection,
    has_free_slot,
)
from ...core.errors import ExceptionCode, FramingError
from ...core.line import LineRequest, no_reply
from ...core.mbap import MAX_ADU, MbapDecoder, MbapFrame, encode_mbap
from ...core.outcome import Outcome
from ...core.policy import IPAddress, Policy, Principal
from ...core.reasons import CloseReason, RejectReason
from ...logs import EventSummary, RateLimitedLogger
from ...metrics import GatewayMetrics
from ..audit import AuditLog, AuditTicket
from ..frame_trace import FrameTrace
from ..status import MasterStatus
from . import spine
from .access import SourceScreen, peer_address_of
from .spine import LineService, Router, listener_policy
from .tls import (
    HandshakeFailure,
    HandshakeNote,
    ServerTls,
    certificate_facts,
    handshake_failure_reason,
    observed,
    peer_chain,
    role_of,
)

if TYPE_CHECKING:  # only TLS listeners hold certificates
    from cryptography import x509

log = logging.getLogger("gateway.tcp")

#: Bytes read from a socket at a time: the decoder's buffer never holds more (plus a partial ADU).
READ_CHUNK = 8192
#: Kernel send buffer per master: replies are small, and a master that does not read them
#: fills this and then the gateway's own bounded buffer, which starts ``send_timeout``.
SEND_BUFFER = 65536
#: Connections accepted per readiness event of a listening socket, before other work runs.
ACCEPT_BATCH = 32
#: How long accepting pauses when the process is out of descriptors (EMFILE): the pending
#: connection stays in the kernel's queue, and the loop does not spin on it.
ACCEPT_RETRY_S = 0.1
#: Interval of the INFO summary of connection events, and of the rate-limited fault logs.
LOG_INTERVAL_S = 60.0
#: Verified client chains remembered per listener (by leaf), for resumed TLS sessions.
CHAIN_MEMORY = 1024
_ACCEPT_RESOURCE_ERRORS = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM})


class ReadPause:
    """Why a connection is not read from (bits); reading resumes when no reason is left.

    Plain integers, not an ``enum.Flag``: each Flag operation costs microseconds in
    Python, and these are tested and set several times per request.
    """

    NONE: Final = 0
    PIPELINE: Final = 1  #: ``max_pipeline`` requests in flight
    BACKLOG: Final = 2  #: too many replies not yet sent (the master does not read)
    BATCH: Final = 4  #: this turn's batch is used up; the rest waits for the next turn


def _peer_text(address: object) -> tuple[str, str]:
    """``(peer, source)`` from an ``accept()`` address: ``"10.0.0.7:50312"``, ``"10.0.0.7"``."""
    if isinstance(address, tuple) and len(address) >= 2:
        host = str(address[0])
        shown = f"[{host}]" if ":" in host else host
        return f"{shown}:{address[1]}", host
    return str(address), str(address)


def _eviction_why(verdict: Evict) -> str:
    """Why a connection was closed to make room, as the log says it."""
    if verdict.never_used:
        return "never sent a request, and its address holds the most"
    return "its address holds more than the newcomer's" if verdict.over_share else "idle longest"


def _refusal_why(config: ServerConfig, source: str) -> str:
    """Why a newcomer from ``source`` found no room, naming the settings."""
    if config.when_full != "close_oldest_idle":
        return (
            f'server.when_full = "refuse", and {source} holds its share or no heavier '
            "address holds a connection that never sent a request"
        )
    return (
        f"none that a master from {source} may displace is idle for "
        f"{config.evict_min_idle:g} s (server.evict_min_idle) or held by an address "
        "with two more connections than its own (while connections that never sent "
        "a request are open, only those may go)"
    )


class RequestSplitter(Protocol):
    """Splits a master's byte stream into requests: MBAP here, RTU frames for RTU over TCP."""

    @property
    def buffered(self) -> int: ...

    def feed(self, data: bytes | bytearray | memoryview) -> None: ...

    def next_frame(self) -> MbapFrame | None: ...


class MasterConnection(asyncio.BufferedProtocol):
    """One TCP master; ``peer`` and ``source`` come from ``accept()``, never from the socket."""

    def __init__(
        self,
        server: ModbusTcpServer,
        peer: str,
        source: str,
        accepted: float,
        address: IPAddress | None = None,
        splitter: RequestSplitter | None = None,
    ) -> None:
        self._server = server
        self.peer = peer
        self.source = source
        self.principal = Principal(address)  #: the source, and the TLS role once known
        self.role_text: str | None = None  #: the role as the trace shows it (TLS only)
        self._decoder: RequestSplitter = MbapDecoder() if splitter is None else splitter
        self._buffer = memoryview(bytearray(READ_CHUNK))
        self._transport: asyncio.Transport | None = None
        self._pending: set[LineRequest] = set()
        self._in_flight = 0
        self._pauses: int = ReadPause.NONE
        self._batch: list[bytes] | None = None  # replies of the running batch, one write
        self._next_batch: asyncio.Handle | None = None
        self._closed = False
        self.requests = 0  #: frames received, for the status page
        self.denied = 0  #: requests the listener's policy refused, for the status page
        self.unrouted = 0  #: requests to a unit with no route (0x0A), for the status page
        #: When this master last became idle: accepted, sent a complete request, or had its
        #: last request answered. Stray bytes do not count.
        self.idle_since = accepted
        self._idle_timer: asyncio.TimerHandle | None = None
        self._stall_timer: asyncio.TimerHandle | None = None
        self.chain: tuple[bytes, ...] = ()  #: the client's verified chain (DER), TLS only
        self.epoch = server.epoch  #: the server's reload count when it was accepted

    # -- asyncio.BufferedProtocol ------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # uvloop's transports implement asyncio.Transport without subclassing it.
        self._transport = cast(asyncio.Transport, transport)
        if self._closed:  # evicted or shut down between accept and now
            self._transport.abort()
            return
        tls, role = role_of(transport)  # read once from the client certificate
        if tls:
            self.principal = Principal(self.principal.source, role)
            self.role_text = "NULL" if role is None else role
            self.chain = peer_chain(transport)
        if self.epoch != self._server.epoch and self._server.refuses_late(self):
            return  # a reload came during its handshake, and its door is now shut to it
        sock = transport.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        high = self._server.config.max_pipeline * MAX_ADU
        self._transport.set_write_buffer_limits(high=high, low=high // 4)
        self._arm_idle_timer()

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._buffer

    def buffer_updated(self, nbytes: int) -> None:
        try:
            self._decoder.feed(self._buffer[:nbytes])
        except FramingError:
            return  # already reported when the decoder failed
        self._run_batch()

    def pause_writing(self) -> None:
        """The send buffer is full: stop reading, and give the master ``send_timeout``."""
        self._pause(ReadPause.BACKLOG)
        timeout = self._server.config.send_timeout
        if timeout > 0 and self._stall_timer is None and not self._closed:
            loop = asyncio.get_running_loop()
            self._stall_timer = loop.call_later(timeout, self._stalled)

    def resume_writing(self) -> None:
        """The master reads its replies again."""
        if self._stall_timer is not None:
            self._stall_timer.cancel()
            self._stall_timer = None
        self._resume(ReadPause.BACKLOG)
        self._schedule_batch()  # frames may wait in the decoder

    def connection_lost(self, exc: Exception | None) -> None:
        self._release()
        self._server.forget(self, CloseReason.PEER_CLOSED if exc is None else CloseReason.ERROR)

    # -- reading: pauses and batches ---------------------------------------------------

    def _pause(self, reason: int) -> None:
        was = self._pauses
        self._pauses = was | reason
        if not was and self._transport is not None and not self._closed:
            self._transport.pause_reading()

    def _resume(self, reason: int) -> None:
        was = self._pauses
        self._pauses = was & ~reason
        if was and not self._pauses and self._transport is not None and not self._closed:
            self._transport.resume_reading()

    def _schedule_batch(self) -> None:
        """Handle the decoder's remaining frames on the next turn of the loop."""
        if self._next_batch is None and not self._closed and self._decoder.buffered:
            self._pause(ReadPause.BATCH)
            self._next_batch = asyncio.get_running_loop().call_soon(self._next_turn)

    def _next_turn(self) -> None:
        self._next_batch = None
        self._run_batch()

    def _run_batch(self) -> None:
        """Handle at most ``max_pipeline`` requests, minus those in flight; write replies once."""
        max_pipeline = self._server.max_pipeline
        budget = max_pipeline - self._in_flight
        batch: list[bytes] = []
        self._batch = batch
        try:
            while budget > 0 and not self._closed and not self._pauses & ReadPause.BACKLOG:
                try:
                    frame = self._decoder.next_frame()
                except FramingError as error:
                    self._protocol_error(error)
                    return
                if frame is None:
                    break
                budget -= 1
                self._handle(frame)
        finally:
            self._batch = None
            if batch and not self._closed and self._transport is not None:
                self._transport.write(b"".join(batch))  # may call pause_writing at once
        if self._closed:
            return
        if self._in_flight >= max_pipeline:
            self._pause(ReadPause.PIPELINE)
        elif self._pauses:
            self._resume(ReadPause.PIPELINE)
        if budget <= 0 and self._decoder.buffered and not self._pauses & ReadPause.PIPELINE:
            self._schedule_batch()  # more frames may be complete: after the other masters
        elif self._pauses:
            self._resume(ReadPause.BATCH)

    def _protocol_error(self, error: FramingError) -> None:
        server = self._server
        server.metrics.protocol_errors.labels(error.kind).inc()
        server.faults.note(
            f"master {self.source}", error.kind, f"{error.reason}; closing {self.peer}"
        )
        self.close(CloseReason.PROTOCOL_ERROR)

    # -- requests ----------------------------------------------------------------------

    @property
    def in_flight(self) -> int:
        """Requests of this master queued or on the wire."""
        return self._in_flight

    @property
    def busy(self) -> bool:
        """True while requests of this master are queued or on the wire."""
        return self._in_flight > 0

    def _handle(self, frame: MbapFrame) -> None:
        """Admit one request (``core.admission``) and carry out the result (``spine``)."""
        server = self._server
        arrived = time.monotonic()
        self.idle_since = arrived
        self.requests += 1
        transaction_id, unit, pdu = frame
        tracer = server.tracer
        if tracer.active:
            tracer.request(self.peer, transaction_id, unit, pdu, server.name, self.role_text)
        result, ticket = spine.admit(server, self.principal, self.peer, self.role_text, unit, pdu)
        if isinstance(result, Submit):
            target = result.target
            bus = server.router.by_line[target.line]  # ``router.bus``, inline: once per request
            self._submit(transaction_id, unit, pdu, bus, target.slave, arrived, ticket)
        elif isinstance(result, Broadcast):
            buses = [server.router.bus(line) for line in result.lines]
            self._broadcast(transaction_id, pdu, buses, ticket)
        else:
            self._answer_locally(transaction_id, unit, pdu, result)

    def _submit(
        self,
        transaction_id: int,
        unit: int,
        pdu: bytes,
        bus: LineService,
        slave: int,
        arrived: float,
        ticket: AuditTicket | None = None,
    ) -> None:
        """Queue the request on ``bus``; the reply goes out under its own transaction id."""
        server = self._server
        duration = bus.request_duration

        def deliver(request: LineRequest, response: bytes, outcome: Outcome) -> Outcome:
            """Write the answer under its transaction id, unless the master left."""
            # Reads ``self._server`` and ``request.pdu`` rather than the enclosing names:
            # each name it captures costs a cell per request.
            self._pending.discard(request)
            if self._closed:
                outcome = Outcome.DROPPED
                tracer = self._server.tracer
                if tracer.active:
                    tracer.dropped(self.peer, transaction_id, unit, request.pdu[0])
            else:
                self._send(transaction_id, unit, response, outcome)
                duration.observe(time.monotonic() - arrived)
            self._request_done()
            return outcome

        request = spine.line_request(server, bus, slave, pdu, self, ticket, deliver)
        self._pending.add(request)
        self._in_flight += 1
        if not bus.submit(request):
            self._pending.discard(request)
            self._in_flight -= 1
            no_route = spine.unsubmitted(server, bus, slave, pdu[0])
            self._send(transaction_id, unit, no_route, Outcome.NO_ROUTE)

    def _answer_locally(
        self, transaction_id: int, unit: int, pdu: bytes, answer: AnswerLocally
    ) -> None:
        """Answer the exception admission chose; nothing reaches a line."""
        server = self._server
        refusal = spine.answer_locally(server, self.principal.role, pdu, answer)
        self._send(transaction_id, unit, refusal, answer.outcome)
        if answer.outcome is Outcome.DENIED:
            self.denied += 1
        elif answer.outcome is Outcome.NO_ROUTE:
            self.unrouted += 1
        if answer.denied is not None and log.isEnabledFor(logging.DEBUG):
            log.debug(
                "master %s on %s: %s denied (%s)",
                self.peer,
                server.name,
                fc.function_name(pdu[0] if pdu else 0),
                answer.denied,
            )

    def _broadcast(
        self, transaction_id: int, pdu: bytes, lines: list[LineService], ticket: AuditTicket | None
    ) -> None:
        """A write to every line that takes broadcasts and is up (``spine.broadcast``),
        answered as a single slave would when ``broadcast_reply`` says so; 0x0A when no
        line is up."""
        server = self._server

        def done(_outcome: Outcome) -> None:
            if server.config.broadcast_reply and not self._closed:
                # What a single slave would have answered to the write.
                self._send(transaction_id, 0, fc.write_response(pdu))
            self._request_done()

        self._in_flight += 1
        requests = spine.broadcast(server, lines, pdu, self, ticket, done)
        if requests is None:  # no line up
            self._in_flight -= 1
            refusal = fc.exception_pdu(pdu[0], ExceptionCode.GATEWAY_PATH_UNAVAILABLE)
            self._send(transaction_id, 0, refusal, Outcome.NO_ROUTE)
            return
        self._pending.update(requests)

    def _request_done(self) -> None:
        self._in_flight -= 1
        if not self._in_flight:
            self.idle_since = time.monotonic()
        if self._pauses & ReadPause.PIPELINE and not self._closed and self._batch is None:
            self._run_batch()

    def _send(
        self, transaction_id: int, unit: int, pdu: bytes, outcome: Outcome | None = None
    ) -> None:
        if self._transport is None or self._closed:
            return
        adu = encode_mbap(transaction_id, unit, pdu)
        if self._batch is not None:
            self._batch.append(adu)
        else:
            self._transport.write(adu)
        tracer = self._server.tracer
        if tracer.active:
            tracer.reply(self.peer, transaction_id, unit, pdu, outcome)

    # -- closing -----------------------------------------------------------------------

    @property
    def established(self) -> bool:
        """True once connected (after the TLS handshake on a tls listener), until closed."""
        return self._transport is not None and not self._closed

    def close(self, reason: CloseReason) -> None:
        """Close this connection, recording why.

        A master the gateway turns away is aborted (its unsent replies dropped, its
        descriptor freed at once); at shutdown, and for one a reload no longer admits,
        the replies already written (0x0A for what was queued) are flushed first.
        """
        if self._closed:
            return
        if reason == CloseReason.NO_LONGER_ADMITTED:
            self._answer_queued()
        self._release()
        self._server.forget(self, reason)
        if self._transport is not None:
            if reason in (CloseReason.SHUTDOWN, CloseReason.NO_LONGER_ADMITTED):
                self._transport.close()
            else:
                self._transport.abort()

    def _answer_queued(self) -> None:
        """Answer 0x0A, as a stop does, what this master has queued (no line sent it yet).

        Told the master left (``_release``), the lines then drop those requests and answer
        nothing more; one on a wire is not answered (its answer goes nowhere). The replies
        go out in one write; no further request is read meanwhile (a batch is open).
        """
        outer = self._batch
        batch = self._batch = [] if outer is None else outer
        try:
            for request in [r for r in self._pending if not r.sent and not r.broadcast]:
                reply, request.reply = request.reply, no_reply
                unavailable = fc.exception_pdu(
                    request.pdu[0], ExceptionCode.GATEWAY_PATH_UNAVAILABLE
                )
                reply(unavailable, Outcome.NO_ROUTE)
        finally:
            self._batch = outer
        if outer is None and batch and self._transport is not None:
            self._transport.write(b"".join(batch))

    def _release(self) -> None:
        self._closed = True
        for timer in (self._idle_timer, self._stall_timer, self._next_batch):
            if timer is not None:
                timer.cancel()
        self._idle_timer = self._stall_timer = self._next_batch = None
        for request in self._pending:
            request.cancelled = True
        self._pending.clear()
        for bus in self._server.router.buses:
            bus.cancel(self)  # its waiting requests leave the lines' queues now

    def _stalled(self) -> None:
        self._stall_timer = None
        if self._closed:
            return
        timeout = self._server.config.send_timeout
        self._server.faults.note(
            f"master {self.source}",
            "unread replies",
            f"{self.peer} read none of its replies for {timeout:g} s (server.send_timeout); "
            "closing",
            plural="connections closed with unread replies",
        )
        self.close(CloseReason.STALLED)

    def idle_for(self, now: float) -> float:
        """Seconds since this master was last active (0 while it has requests in flight)."""
        return 0.0 if self.busy else now - self.idle_since

    def _arm_idle_timer(self) -> None:
        timeout = self._server.config.idle_timeout
        if timeout <= 0 or self._closed:
            return
        delay = self.idle_since + timeout - time.monotonic()
        loop = asyncio.get_running_loop()
        self._idle_timer = loop.call_later(max(delay, 0.0), self._check_idle)

    def _check_idle(self) -> None:
        self._idle_timer = None
        timeout = self._server.config.idle_timeout
        if self._closed:
            return
        now = time.monotonic()
        if timeout > 0 and self.idle_for(now) >= timeout:
            log.debug("master %s: no request for %.0f s, closing", self.peer, timeout)
            self.close(CloseReason.IDLE)
            return
        if self.busy:
            self.idle_since = now  # checked again a whole timeout from now
        self._arm_idle_timer()


class ModbusTcpServer:
    """One listener: accepts masters (allow lists, admission, eviction) and keeps the books."""

    def __init__(
        self,
        config: ServerConfig,
        router: Router,
        metrics: GatewayMetrics,
        listener: ListenerConfig | None = None,
        policy: Policy | None = None,
        ssl_context: ssl.SSLContext | None = None,
        *,
        connection_class: type[MasterConnection] = MasterConnection,
        one_at_a_time: bool = False,
    ) -> None:
        #: What serves one accepted master (``rtu_listener`` gives RTU framing its own).
        self.connection_class = connection_class
        #: Masters whose frames carry no transaction id (RTU over TCP): one request in
        #: flight each, and a broadcast is never answered, whatever ``[server]`` says.
        self.one_at_a_time = one_at_a_time
        self.config = config  # through the setter: it shapes the settings
        self.router = router
        self.metrics = metrics
        self.listener = listener or ListenerConfig("tcp", host=config.host, port=config.port)
        self.name = self.listener.name
        self.policy = policy or Policy()  #: replaced as a whole on reload
        self.ssl_context = ssl_context  #: replaced on reload; new connections use the new one
        self.screen = SourceScreen(self.name, (config.allow, self.listener.allow), metrics)
        metrics.connections_open.labels(self.name).set(0)  # the series exists from the start
        self.epoch = 0  #: reloads seen: a connection accepted before one is judged again
        #: The CAs of a tls listener as of the last reload (``reevaluate``); ``None`` until
        #: then: the handshake's verdict on the chain stands.
        self._authorities: tuple[x509.Certificate, ...] | None = None
        self._revocations: tuple[x509.CertificateRevocationList, ...] = ()  #: the crl, likewise
        #: Chains full handshakes verified, by leaf: a resumed session shows only its leaf.
        self._chains: dict[bytes, tuple[bytes, ...]] = {}
        self.tracer = FrameTrace()  #: the gateway's, given at construction; used while active
        self.audit: AuditLog | None = None  #: the audit log, when configured (``Gateway``)
        #: The redundancy peer's addresses (``Gateway``): its links, which carry the masters
        #: it admitted, have a connection budget of their own (``core.connection_share``).
        self.pair_sources: frozenset[str] = frozenset()
        self._connections: dict[MasterConnection, None] = {}
        self._per_source: dict[str, int] = {}
        self._listeners: list[socket.socket] = []
        self._addresses: list[tuple[str, int]] = []
        self._accepting = False
        #: Connections being set up (a TLS handshake under way): closing one cancels its
        #: setup, which closes its socket at once instead of at the handshake timeout.
        self._starting: dict[MasterConnection, asyncio.Task[object]] = {}
        loop = asyncio.get_running_loop()
        self._loop = loop
        #: Faults a client can repeat at will, logged per (source, kind) at a bounded rate.
        self.faults = RateLimitedLogger(log, loop, window=LOG_INTERVAL_S)
        self.events = EventSummary(
            log, loop, "connections", LOG_INTERVAL_S, extra=lambda: f"{self.connections} open"
        )

    @property
    def config(self) -> ServerConfig:
        """The ``[server]`` settings as this listener applies them (see ``one_at_a_time``)."""
        return self._config

    @config.setter
    def config(self, value: ServerConfig) -> None:
        if self.one_at_a_time:
            value = replace(value, max_pipeline=1, broadcast_reply=False)
        self._config = value
        #: ``config.max_pipeline``, a plain attribute: every batch reads it.
        self.max_pipeline = value.max_pipeline

    @property
    def connections(self) -> int:
        """Masters connected now."""
        return len(self._connections)

    @property
    def sockets(self) -> list[tuple[str, int]]:
        """The addresses the server listens on."""
        return list(self._addresses)

    # -- listening ---------------------------------------------------------------------

    async def start(self) -> None:
        """Bind the listening sockets and start accepting."""
        self.screen.start(self._loop)
        self._listeners = await self._bind(self.listener.host, self.listener.port)
        self._addresses = [sock.getsockname()[:2] for sock in self._listeners]
        self._accepting = True
        for sock in self._listeners:
            self._loop.add_reader(sock.fileno(), self._accept_ready, sock)

    async def _bind(self, host: str, port: int) -> list[socket.socket]:
        """One listening socket per address ``host`` resolves to (as ``create_server`` does)."""
        infos = await self._loop.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
        sockets: list[socket.socket] = []
        seen: set[tuple[int, object]] = set()
        try:
            for family, kind, proto, _name, address in infos:
                if (family, address) in seen:
                    continue
                seen.add((family, address))
                sock = socket.socket(family, kind, proto)
                sockets.append(sock)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if family == socket.AF_INET6:
                    sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                try:
                    sock.bind(address)
                except OSError as error:
                    raise OSError(
                        error.errno,
                        f"error while attempting to bind on address {address!r}: "
                        f"{(error.strerror or str(error)).lower()}",
                    ) from None
                sock.listen(self.config.backlog)
                sock.setblocking(False)
        except BaseException:
            for sock in sockets:
                sock.close()
            raise
        return sockets

    def _accept_ready(self, listener: socket.socket) -> None:
        """Accept up to ``ACCEPT_BATCH`` pending connections, then let other work run."""
        for _ in range(ACCEPT_BATCH):
            try:
                sock, address = listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as error:
                if error.errno in _ACCEPT_RESOURCE_ERRORS:
                    self._pause_accepting(listener, error)
                    return
                continue  # ECONNABORTED and the like: that connection is gone already
            self._accepted(sock, address)

    def _pause_accepting(self, listener: socket.socket, error: OSError) -> None:
        self.faults.note(
            "server",
            "accept failed",
            f"{error.strerror}; accepting again in {ACCEPT_RETRY_S} s "
            "(raise the open-file limit, or lower server.max_connections)",
        )
        self._loop.remove_reader(listener.fileno())

        def again() -> None:
            if self._accepting:
                self._loop.add_reader(listener.fileno(), self._accept_ready, listener)

        self._loop.call_later(ACCEPT_RETRY_S, again)

    def _accepted(self, sock: socket.socket, address: object) -> None:
        peer, source = _peer_text(address)
        ip = peer_address_of(address)
        door = self.screen.door(self.listener.tls)  # the source only: no byte read yet
        if admit(door, ConnectionFacts(ip), time.time()) is not None:  # counted and logged
            self.screen.refuse(ip, self.audit)
            sock.close()
            return
        refusal = self._admit(source, peer)
        if refusal is not None:
            sock.close()  # a FIN, not a reset: the master's connect() always completes
            self.metrics.connections_rejected.labels(refusal).inc()
            self.events.note("refused", source)
            log.debug("master %s refused (%s)", peer, refusal)
            return
        sock.setblocking(False)
        connection = self.connection_class(self, peer, source, time.monotonic(), ip)
        self._connections[connection] = None
        self._per_source[source] = self._per_source.get(source, 0) + 1
        self.metrics.connections_accepted.inc()
        self.metrics.connections_open.labels(self.name).set(len(self._connections))
        self.events.note("opened", source)
        log.debug("master %s connected", peer)
        if self.ssl_context is None:
            setup = self._loop.connect_accepted_socket(lambda: connection, sock)
        else:  # the handshake completes before the connection is made
            setup = self._loop.connect_accepted_socket(
                lambda: connection,
                sock,
                ssl=self.ssl_context,
                ssl_handshake_timeout=self.config.tls_handshake_timeout,
            )
        note = HandshakeNote()  # what the handshake shows, for the log line of a failure
        task = self._loop.create_task(setup, context=observed(note))
        self._starting[connection] = task
        task.add_done_callback(lambda done: self._started(done, connection, sock, note))

    def _started(
        self,
        task: asyncio.Task[object],
        connection: MasterConnection,
        sock: socket.socket,
        note: HandshakeNote,
    ) -> None:
        if self._starting.get(connection) is task:
            del self._starting[connection]
        error = None if task.cancelled() else task.exception()
        if error is None and not task.cancelled() and connection.chain:
            self._complete_chain(connection)
        if task.cancelled() or error is not None:
            sock.close()
            connection.close(CloseReason.ERROR)
            if self.ssl_context is not None and error is not None:
                reason = handshake_failure_reason(error)
                self.handshake_failed(reason, error, connection, note.subject)

    def _complete_chain(self, connection: MasterConnection) -> None:
        """Remember a full handshake's chain; give a resumed session (its leaf alone) the
        chain its first handshake verified, so a reload judges it the same way."""
        chain = connection.chain
        if len(chain) > 1:
            self._chains.pop(chain[0], None)
            self._chains[chain[0]] = chain
            if len(self._chains) > CHAIN_MEMORY:
                del self._chains[next(iter(self._chains))]
        else:
            connection.chain = self._chains.get(chain[0], chain)

    def handshake_failed(
        self,
        reason: HandshakeFailure,
        error: BaseException,
        connection: MasterConnection,
        subject: str | None = None,
    ) -> None:
        """Count and log (at a bounded rate per source) a failed TLS handshake."""
        source = connection.principal.source
        self.screen.handshake_failed(reason, error, connection.peer, source, subject)

    def masters(self) -> list[MasterStatus]:
        """A snapshot of the connected masters, for the status page."""
        host, port = self.sockets[0] if self.sockets else (self.listener.host, self.listener.port)
        listener = f"{self.name} {host}:{port}"
        return [
            MasterStatus(
                connection.peer,
                listener,
                connection.in_flight,
                connection.requests,
                connection.role_text,
                connection.denied,
                connection.unrouted,
            )
            for connection in self._connections
        ]

    # -- admission ---------------------------------------------------------------------

    def _admit(self, source: str, peer: str) -> RejectReason | None:
        """Make room for a master from ``source`` or say why not (core's ``connection_share``).

        While a slot is free (the common case) the counts decide alone; only at a limit is
        a snapshot of every connection taken and handed to core.
        """
        config = self.config
        limits = ShareLimits(
            config.max_connections,
            config.max_connections_per_source,
            config.when_full == "close_oldest_idle",
            config.evict_min_idle,
        )
        pair = self.pair_sources
        total = len(self._connections)
        if pair:  # the redundancy peer's links have a budget of their own (core)
            total -= sum(self._per_source.get(host, 0) for host in pair)
        held = self._per_source.get(source, 0)
        if source not in pair and has_free_slot(limits, total, held):
            return None
        connections = list(self._connections)
        now = time.monotonic()
        snapshot = [
            OpenConnection(c.source, c.idle_for(now), c.in_flight, c.requests > 0)
            for c in connections
        ]
        verdict = admit_connection(source, limits, snapshot, pair)
        if isinstance(verdict, Evict):
            self._evict(connections[verdict.index], verdict, peer)
            return None
        if isinstance(verdict, Refuse):
            self._note_refusal(source, verdict.reason)
            return RejectReason(verdict.reason.value)
        return None

    def _evict(self, victim: MasterConnection, verdict: Evict, peer: str) -> None:
        """Close ``victim`` to make room for ``peer``."""
        why = _eviction_why(verdict)
        log.debug("master %s: closed to make room for %s (%s)", victim.peer, peer, why)
        self.events.note("evicted", victim.source)
        victim.close(CloseReason.EVICTED)

    def _note_refusal(self, source: str, reason: Refusal) -> None:
        """Log a refusal at a bounded rate, naming the setting that caused it."""
        config = self.config
        if reason == Refusal.MAX_PER_SOURCE:
            self.faults.note(
                f"master {source}",
                "connection limit of its address",
                f"{config.max_connections_per_source} connections open "
                "(server.max_connections_per_source); refusing more from it",
                plural="connections refused, limit of its address",
            )
            return
        why = _refusal_why(config, source)
        self.faults.note(
            "server",
            "connection limit",
            f"{len(self._connections)} masters connected (server.max_connections); {why}; "
            "refusing it",
            plural="connections refused at the limit",
        )

    def forget(self, connection: MasterConnection, reason: CloseReason) -> None:
        """Drop a closed connection from the books (once); abandon its setup if under way."""
        setup = self._starting.pop(connection, None)
        if setup is not None and not setup.done():
            setup.cancel()  # the transport is aborted and the descriptor freed now
        if self._connections.pop(connection, False) is None:
            source = connection.source
            remaining = self._per_source.get(source, 1) - 1
            if remaining > 0:
                self._per_source[source] = remaining
            else:
                self._per_source.pop(source, None)
            self.metrics.connections_closed.labels(reason).inc()
            self.metrics.connections_open.labels(self.name).set(len(self._connections))
            self.events.note("closed", source)
            log.debug("master %s disconnected (%s)", connection.peer, reason)

    # -- reload: new settings, and every open connection judged again ---------------------

    def reconfigure(
        self, config: GatewayConfig, router: Router, tls: ServerTls | None, now: float
    ) -> int:
        """Take a reload's settings: the ``[server]`` table and the routes always; this
        listener's own table (policy, allow lists, certificates) while it keeps its
        protocol (its address needs a restart); then judge every open connection again
        (``reevaluate``) and return how many were closed. ``tls`` is this listener's
        context and CAs read again, ``now`` the wall-clock time of the reload."""
        self.config = config.server
        self.router = router
        listener = next((lst for lst in config.listeners if lst.name == self.name), None)
        if listener is not None and listener.protocol == self.listener.protocol:
            self.listener = replace(listener, host=self.listener.host, port=self.listener.port)
            self.policy = listener_policy(config, self.listener)
            self.screen.allow_lists = tuple(
                tuple(nets) for nets in (config.server.allow, listener.allow) if nets
            )
            if tls is not None:
                self.ssl_context = tls.context
        return self.reevaluate(tls, now)

    def reevaluate(self, tls: ServerTls | None, now: float) -> int:
        """Close every connection this listener would no longer admit; return how many.

        Called at a reload once the listener's new settings (allow lists, listener)
        are in place; ``tls`` carries the CAs read again, ``now`` is the wall-clock
        time (seconds since the epoch). A connection still in its handshake is
        judged on its source now, and on its certificate once the handshake is done.
        """
        self.epoch += 1
        if tls is not None:
            self._authorities = tls.authorities
            self._revocations = tls.revocations
        seen: dict[tuple[bytes, ...], CertificateFacts | None] = {}
        closed = 0
        for connection in list(self._connections):
            reason = self._judge(connection, now, seen)
            if reason is not None:
                self._close_unadmitted(connection, reason)
                closed += 1
        return closed

    def refuses_late(self, connection: MasterConnection) -> bool:
        """Judge a connection set up across a reload; close it (``True``) if refused."""
        reason = self._judge(connection, time.time(), {})
        if reason is not None:
            self._close_unadmitted(connection, reason)
        return reason is not None

    def _judge(
        self,
        connection: MasterConnection,
        now: float,
        seen: dict[tuple[bytes, ...], CertificateFacts | None],
    ) -> NotAdmitted | None:
        """Core's decision for one connection, its chain's facts worked out once per chain."""
        established = connection.established
        certificate = None
        if established and self.listener.tls:
            chain = connection.chain
            if chain not in seen:
                seen[chain] = certificate_facts(chain, self._authorities, self._revocations)
            certificate = seen[chain]
        facts = ConnectionFacts(connection.principal.source, established, certificate)
        return admit(self.screen.door(self.listener.tls), facts, now)

    def _close_unadmitted(self, connection: MasterConnection, reason: NotAdmitted) -> None:
        self.screen.closed_at_reload(connection, reason, self.audit)
        self.events.note("closed at reload", connection.source)
        connection.close(CloseReason.NO_LONGER_ADMITTED)

    # -- stopping ----------------------------------------------------------------------

    def stop_accepting(self) -> None:
        """Close the listening sockets; connections stay, handshakes under way are abandoned."""
        self._accepting = False
        for sock in self._listeners:
            self._loop.remove_reader(sock.fileno())
            sock.close()
        if self.ssl_context is not None:
            for task in self._starting.values():
                task.cancel()

    def close_all(self, reason: CloseReason) -> None:
        """Close every connection."""
        for connection in list(self._connections):
            connection.close(reason)
        self.events.flush()
        self.faults.flush()

    async def wait_closed(self) -> None:
        """Wait for the connections still being set up to settle."""
        if self._starting:
            await asyncio.wait(set(self._starting.values()), timeout=1.0)
