"""The Modbus TCP server: many masters, several requests in flight on each.

Theory of operation: each connection owns an incremental ``MbapDecoder``. A
complete frame is validated by the core (answered locally when no slave
could accept it), routed by unit id, and handed to its line's ``Bus`` with a
callback that writes the reply under the request's own transaction id, in
whatever order replies complete. A framing error closes that connection only.
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
(``SourceScreen``), then (``ModbusTcpServer._admit``) a per-source limit, then
the listener's cap,
which closes the master idle longest (at least ``evict_min_idle``, nothing in
flight) or refuses. Only a complete request makes a master active again.
Connection events are logged at DEBUG and summarised at INFO once a minute;
faults a client can repeat at will are rate-limited per source and kind.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
import ssl
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Final, Protocol, cast

from ..config import ListenerConfig, ServerConfig
from ..core import pdu as fc
from ..core.errors import ExceptionCode, FramingError, ModbusError
from ..core.mbap import MAX_ADU, MbapDecoder, MbapFrame, encode_mbap
from ..core.outcome import Outcome
from ..core.policy import Decision, IPAddress, Policy, Principal
from ..logs import EventSummary, RateLimitedLogger
from ..metrics import UNIT_LABELS, CloseReason, GatewayMetrics, RejectReason
from ..status import MasterStatus
from ..trace import FrameTrace
from .access import SourceScreen, peer_address_of
from .bus import Bus, Request
from .tls import HandshakeFailure, handshake_failure_reason, role_of

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


@dataclass(frozen=True, slots=True)
class Target:
    """Where a TCP unit id goes."""

    bus: Bus
    slave: int


class Router:
    """TCP unit id → (bus, slave); replaced as a whole on reload."""

    def __init__(self, routes: Mapping[int, Target], broadcast_buses: list[Bus]) -> None:
        self.routes = dict(routes)
        self.broadcast_buses = broadcast_buses
        self.buses = list({id(t.bus): t.bus for t in self.routes.values()}.values())
        for bus in broadcast_buses:
            if bus not in self.buses:
                self.buses.append(bus)

    def lookup(self, unit: int) -> Target | None:
        """The route for ``unit``, ``None`` when there is none."""
        return self.routes.get(unit)


def _peer_text(address: object) -> tuple[str, str]:
    """``(peer, source)`` from an ``accept()`` address: ``"10.0.0.7:50312"``, ``"10.0.0.7"``."""
    if isinstance(address, tuple) and len(address) >= 2:
        host = str(address[0])
        shown = f"[{host}]" if ":" in host else host
        return f"{shown}:{address[1]}", host
    return str(address), str(address)


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
        self._pending: set[Request] = set()
        self._in_flight = 0
        self._pauses: int = ReadPause.NONE
        self._batch: list[bytes] | None = None  # replies of the running batch, one write
        self._next_batch: asyncio.Handle | None = None
        self._closed = False
        self.requests = 0  #: frames received, for the status page
        #: When this master last became idle: accepted, sent a complete request, or had its
        #: last request answered. Stray bytes do not count.
        self.idle_since = accepted
        self._idle_timer: asyncio.TimerHandle | None = None
        self._stall_timer: asyncio.TimerHandle | None = None

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
        budget = self._server.config.max_pipeline - self._in_flight
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
        if self._in_flight >= self._server.config.max_pipeline:
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
        server = self._server
        arrived = time.monotonic()
        self.idle_since = arrived
        self.requests += 1
        transaction_id, unit, pdu = frame
        function = pdu[0] if pdu else 0
        tracer = server.tracer
        if tracer.active:
            tracer.request(self.peer, transaction_id, unit, pdu, server.name, self.role_text)
        # Authorization first: a master learns nothing about requests it may not send. An open
        # policy can only refuse Force Listen Only Mode (FC 8/4), so only FC 8 asks it.
        policy = server.policy
        if not policy.open or function == fc.DIAGNOSTICS:
            decision = policy.decide(self.principal, unit, pdu)
            if decision.denied is not None:
                self._deny(transaction_id, unit, function, decision)
                return
        try:
            if function in server.config.refuse_functions:
                raise ModbusError(
                    ExceptionCode.ILLEGAL_FUNCTION, "function refused by configuration"
                )
            fc.validate_request(pdu)
            if unit == 0 and function not in fc.BROADCAST_FUNCTIONS:
                raise ModbusError(ExceptionCode.ILLEGAL_FUNCTION, "only writes can be broadcast")
        except ModbusError as error:
            server.metrics.protocol_errors.labels("invalid_request").inc()
            rejection = fc.exception_pdu(function, error.code)
            self._send(transaction_id, unit, rejection, Outcome.REJECTED)
            server.metrics.count_request("none", "other", function, Outcome.REJECTED)
            return
        if unit == 0:
            self._broadcast(transaction_id, pdu, arrived)
            return
        target = server.router.lookup(unit)
        if target is None:
            self._send(
                transaction_id,
                unit,
                fc.exception_pdu(function, ExceptionCode.GATEWAY_PATH_UNAVAILABLE),
            )
            server.metrics.count_request("none", "other", function, Outcome.NO_ROUTE)
            return
        bus = target.bus
        line = bus.name
        unit_label = UNIT_LABELS[target.slave]  # the slave address, as in the line's metrics
        duration = bus.request_duration

        def reply(response: bytes, outcome: Outcome) -> None:
            self._pending.discard(request)
            if self._closed:
                outcome = Outcome.DROPPED
                if server.tracer.active:
                    server.tracer.dropped(self.peer, transaction_id, unit, function)
            else:
                self._send(transaction_id, unit, response, outcome)
                duration.observe(time.monotonic() - arrived)
            server.metrics.count_request(line, unit_label, function, outcome)
            self._request_done()

        request = Request(target.slave, pdu, self, reply)
        self._pending.add(request)
        self._in_flight += 1
        if not bus.submit(request):
            self._pending.discard(request)
            self._in_flight -= 1
            self._send(
                transaction_id,
                unit,
                fc.exception_pdu(function, ExceptionCode.GATEWAY_PATH_UNAVAILABLE),
            )
            server.metrics.count_request(line, unit_label, function, Outcome.NO_ROUTE)

    def _deny(self, transaction_id: int, unit: int, function: int, decision: Decision) -> None:
        """Answer 0x01 (Illegal Function) to a request the policy refuses; none reaches the line."""
        server = self._server
        self._send(
            transaction_id, unit, fc.exception_pdu(function, ExceptionCode.ILLEGAL_FUNCTION),
            Outcome.DENIED,
        )  # fmt: skip
        server.metrics.count_denial(
            server.name, server.policy.role_label(self.principal.role), function
        )
        server.metrics.count_request("none", "other", function, Outcome.DENIED)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("master %s on %s: %s denied (%s)", self.peer, server.name,
                      fc.function_name(function), decision.denied)  # fmt: skip

    def _broadcast(self, transaction_id: int, pdu: bytes, arrived: float) -> None:
        server = self._server
        buses = [bus for bus in server.router.broadcast_buses if bus.up]
        if not buses:
            self._send(
                transaction_id, 0, fc.exception_pdu(pdu[0], ExceptionCode.GATEWAY_PATH_UNAVAILABLE)
            )
            server.metrics.count_request("none", "other", pdu[0], Outcome.NO_ROUTE)
            return
        remaining = len(buses)

        def sent(_response: bytes, outcome: Outcome) -> None:
            nonlocal remaining
            remaining -= 1
            if remaining:
                return
            if server.config.broadcast_reply and not self._closed:
                # What a single slave would have answered to the write.
                self._send(transaction_id, 0, fc.write_response(pdu))
            server.metrics.count_request("broadcast", "0", pdu[0], outcome)
            self._request_done()

        self._in_flight += 1
        for bus in buses:
            request = Request(0, pdu, self, sent, broadcast=True)
            if bus.submit(request):
                self._pending.add(request)
            else:
                sent(b"", Outcome.NO_ROUTE)

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

    def close(self, reason: CloseReason) -> None:
        """Close this connection, recording why.

        A master the gateway turns away is aborted (its unsent replies dropped,
        its descriptor freed at once); at shutdown the replies already written
        (0x0A for what was queued) are flushed first.
        """
        if self._closed:
            return
        self._release()
        self._server.forget(self, reason)
        if self._transport is not None:
            if reason == CloseReason.SHUTDOWN:
                self._transport.close()
            else:
                self._transport.abort()

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
        self.tracer = FrameTrace()  #: the gateway's, given at construction; used while active
        self._connections: dict[MasterConnection, None] = {}
        self._per_source: dict[str, int] = {}
        self._listeners: list[socket.socket] = []
        self._addresses: list[tuple[str, int]] = []
        self._accepting = False
        self._starting: set[asyncio.Task[object]] = set()
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
                        error.errno, f"error while attempting to bind on address {address!r}: "
                        f"{(error.strerror or str(error)).lower()}",
                    ) from None  # fmt: skip
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
            "server", "accept failed", f"{error.strerror}; accepting again in {ACCEPT_RETRY_S} s "
            "(raise the open-file limit, or lower server.max_connections)",
        )  # fmt: skip
        self._loop.remove_reader(listener.fileno())

        def again() -> None:
            if self._accepting:
                self._loop.add_reader(listener.fileno(), self._accept_ready, listener)

        self._loop.call_later(ACCEPT_RETRY_S, again)

    def _accepted(self, sock: socket.socket, address: object) -> None:
        peer, source = _peer_text(address)
        ip = peer_address_of(address)
        if not self.screen.allows(ip):  # counted and logged (rate-limited) by the screen
            self.screen.refuse(ip)
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
        self.metrics.connections_open.set(len(self._connections))
        self.events.note("opened", source)
        log.debug("master %s connected", peer)
        if self.ssl_context is None:
            setup = self._loop.connect_accepted_socket(lambda: connection, sock)
        else:  # the handshake completes before the connection is made
            setup = self._loop.connect_accepted_socket(
                lambda: connection, sock, ssl=self.ssl_context,
                ssl_handshake_timeout=self.config.tls_handshake_timeout,
            )  # fmt: skip
        task = self._loop.create_task(setup)
        self._starting.add(task)
        task.add_done_callback(lambda done: self._started(done, connection, sock))

    def _started(
        self, task: asyncio.Task[object], connection: MasterConnection, sock: socket.socket
    ) -> None:
        self._starting.discard(task)
        error = None if task.cancelled() else task.exception()
        if task.cancelled() or error is not None:
            sock.close()
            connection.close(CloseReason.ERROR)
            if self.ssl_context is not None and error is not None:
                self.handshake_failed(handshake_failure_reason(error), error)

    def handshake_failed(self, reason: HandshakeFailure, error: BaseException) -> None:
        """Count and log (at a bounded rate) a failed TLS handshake."""
        self.screen.handshake_failed(reason, error)

    def masters(self) -> list[MasterStatus]:
        """A snapshot of the connected masters, for the status page."""
        host, port = self.sockets[0] if self.sockets else (self.listener.host, self.listener.port)
        listener = f"{self.name} {host}:{port}"
        return [
            MasterStatus(connection.peer, listener, connection.in_flight, connection.requests)
            for connection in self._connections
        ]

    # -- admission ---------------------------------------------------------------------

    def _admit(self, source: str, peer: str) -> RejectReason | None:
        """Make room for a master from ``source`` or say why not (see the module docstring)."""
        config = self.config
        per_source = config.max_connections_per_source
        if per_source and self._per_source.get(source, 0) >= per_source:
            self.faults.note(
                f"master {source}", "connection limit of its address",
                f"{per_source} connections open (server.max_connections_per_source); "
                "refusing more from it", plural="connections refused, limit of its address",
            )  # fmt: skip
            return RejectReason.MAX_PER_SOURCE
        if len(self._connections) < config.max_connections:
            return None
        victim = self._eviction_candidate() if config.when_full == "close_oldest_idle" else None
        if victim is None:
            self.faults.note(
                "server", "connection limit",
                f"{len(self._connections)} masters connected (server.max_connections), none idle "
                f"for {config.evict_min_idle:g} s (server.evict_min_idle); refusing new ones",
                plural="connections refused at the limit",
            )  # fmt: skip
            return RejectReason.MAX_CONNECTIONS
        log.debug("master %s: closed to make room for %s", victim.peer, peer)
        self.events.note("evicted", victim.source)
        victim.close(CloseReason.EVICTED)
        return None

    def _eviction_candidate(self) -> MasterConnection | None:
        """The master idle longest, if idle for ``evict_min_idle`` with nothing in flight."""
        now = time.monotonic()
        victim = max(self._connections, key=lambda c: c.idle_for(now), default=None)
        if victim is None or victim.busy or victim.idle_for(now) < self.config.evict_min_idle:
            return None
        return victim

    def forget(self, connection: MasterConnection, reason: CloseReason) -> None:
        """Drop a closed connection from the books (once)."""
        if self._connections.pop(connection, False) is None:
            source = connection.source
            remaining = self._per_source.get(source, 1) - 1
            if remaining > 0:
                self._per_source[source] = remaining
            else:
                self._per_source.pop(source, None)
            self.metrics.connections_closed.labels(reason).inc()
            self.metrics.connections_open.set(len(self._connections))
            self.events.note("closed", source)
            log.debug("master %s disconnected (%s)", connection.peer, reason)

    # -- stopping ----------------------------------------------------------------------

    def stop_accepting(self) -> None:
        """Close the listening sockets; connections stay, handshakes under way are abandoned."""
        self._accepting = False
        for sock in self._listeners:
            self._loop.remove_reader(sock.fileno())
            sock.close()
        if self.ssl_context is not None:
            for task in self._starting:
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
            await asyncio.wait(set(self._starting), timeout=1.0)
