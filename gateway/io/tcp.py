"""The Modbus TCP server: many masters, several requests in flight on each.

Theory of operation: each connection owns an incremental ``MbapDecoder``. A
complete frame is validated by the core (answered locally when no slave
could accept it), routed by unit id, and handed to its line's ``Bus`` with a
callback that writes the reply under the request's own transaction id, in
whatever order replies complete. At ``max_pipeline`` requests in flight the
connection stops reading (TCP back-pressure) until a reply goes out. A framing
error closes that connection only. When a master leaves, its queued requests
are cancelled so nothing is sent on its behalf.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import ssl
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import cast

from ..config import ListenerConfig, ServerConfig
from ..core import pdu as fc
from ..core.errors import ExceptionCode, FramingError, ModbusError
from ..core.mbap import MbapDecoder, MbapFrame, encode_mbap
from ..core.policy import Decision, Policy, Principal
from ..metrics import UNIT_LABELS, GatewayMetrics
from ..status import MasterStatus
from ..trace import FrameTracer
from .access import SourceScreen, peer_address, peer_address_of
from .bus import Bus, Request
from .tls import HandshakeFailure, TlsServer, role_of

log = logging.getLogger("gateway.tcp")


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

    def lookup(self, unit: int) -> Target | None:
        """The route for ``unit``, ``None`` when there is none."""
        return self.routes.get(unit)


class MasterConnection(asyncio.Protocol):
    """One TCP master."""

    def __init__(self, server: ModbusTcpServer) -> None:
        self._server = server
        self._decoder = MbapDecoder()
        self._transport: asyncio.Transport | None = None
        self._pending: set[Request] = set()
        self._in_flight = 0
        self._paused = False
        self._closed = False
        self.peer = "?"
        self.requests = 0  # frames received, for the status page
        self.last_activity = time.monotonic()
        self._idle_timer: asyncio.TimerHandle | None = None
        self.principal = Principal(None)  #: set by the source screen (and the TLS role)
        self.role_text: str | None = None  #: the role as the trace shows it (TLS only)

    # -- asyncio.Protocol --------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # uvloop's transports implement asyncio.Transport without subclassing it.
        self._transport = cast(asyncio.Transport, transport)
        peer = transport.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        if not self._server.screen_source(self, self._transport):
            self._closed = True
            self._transport.abort()
            return
        sock = transport.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        if not self._server.admit(self):
            self._closed = True
            self._transport.abort()
            return
        self._arm_idle_timer()

    def data_received(self, data: bytes) -> None:
        self.last_activity = time.monotonic()
        try:
            self._decoder.feed(data)
        except FramingError:
            return  # already reported when the decoder failed
        self._process_frames()

    def connection_lost(self, exc: Exception | None) -> None:
        self._closed = True
        if self._idle_timer is not None:
            self._idle_timer.cancel()
        for request in self._pending:
            request.cancelled = True
        self._pending.clear()
        self._server.forget(self, "peer_closed" if exc is None else "error")

    # -- requests ----------------------------------------------------------------------

    @property
    def in_flight(self) -> int:
        """Requests of this master queued or on the wire."""
        return self._in_flight

    @property
    def busy(self) -> bool:
        """True while requests of this master are queued or on the wire."""
        return self._in_flight > 0

    def _process_frames(self) -> None:
        limit = self._server.config.max_pipeline
        while not self._closed and self._in_flight < limit:
            try:
                frame = self._decoder.next_frame()
            except FramingError as error:
                self._server.metrics.protocol_errors.labels(error.kind).inc()
                log.warning("master %s: %s; closing the connection", self.peer, error.reason)
                self.close("protocol_error")
                return
            if frame is None:
                break
            self._handle(frame)
        if self._closed or self._transport is None:
            return
        if self._in_flight >= limit and not self._paused:
            self._paused = True
            self._transport.pause_reading()
        elif self._in_flight < limit and self._paused:
            self._paused = False
            self._transport.resume_reading()

    def _handle(self, frame: MbapFrame) -> None:
        server = self._server
        arrived = time.monotonic()
        self.requests += 1
        transaction_id, unit, pdu = frame
        function = pdu[0] if pdu else 0
        tracer = server.tracer
        if tracer is not None:
            tracer.request(self.peer, transaction_id, unit, pdu, server.name, self.role_text)
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
            self._send(transaction_id, unit, fc.exception_pdu(function, error.code), "rejected")
            server.metrics.count_request("none", "other", function, "rejected")
            return
        if not server.policy.open:
            decision = server.policy.decide(self.principal, unit, pdu)
            if decision.denied is not None:
                self._deny(transaction_id, unit, function, decision)
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
            server.metrics.count_request("none", "other", function, "no_route")
            return
        bus = target.bus
        line = bus.name
        unit_label = UNIT_LABELS[target.slave]  # the slave address, as in the line's metrics
        duration = server.metrics.request_duration_for(line)

        def reply(response: bytes, outcome: str) -> None:
            self._pending.discard(request)
            if self._closed:
                outcome = "dropped"
                if server.tracer is not None:
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
            server.metrics.count_request(line, unit_label, function, "no_route")

    def _deny(self, transaction_id: int, unit: int, function: int, decision: Decision) -> None:
        """Answer 0x01 (Illegal Function) to a request the policy refuses; none reaches the line."""
        server = self._server
        self._send(
            transaction_id, unit, fc.exception_pdu(function, ExceptionCode.ILLEGAL_FUNCTION),
            "denied",
        )  # fmt: skip
        server.metrics.count_denial(
            server.name, server.policy.role_label(self.principal.role), function
        )
        server.metrics.count_request("none", "other", function, "denied")
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
            server.metrics.count_request("none", "other", pdu[0], "no_route")
            return
        remaining = len(buses)

        def sent(_response: bytes, outcome: str) -> None:
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
                sent(b"", "no_route")

    def _request_done(self) -> None:
        self._in_flight -= 1
        self.last_activity = time.monotonic()
        if self._paused and not self._closed:
            self._process_frames()

    def _send(self, transaction_id: int, unit: int, pdu: bytes, outcome: str | None = None) -> None:
        if self._transport is not None and not self._closed:
            self._transport.write(encode_mbap(transaction_id, unit, pdu))
            tracer = self._server.tracer
            if tracer is not None:
                tracer.reply(self.peer, transaction_id, unit, pdu, outcome)

    # -- closing -----------------------------------------------------------------------

    def close(self, reason: str) -> None:
        """Close this connection, recording why."""
        if self._closed:
            return
        self._closed = True
        for request in self._pending:
            request.cancelled = True
        self._server.forget(self, reason)
        if self._transport is not None:
            self._transport.close()

    def _arm_idle_timer(self) -> None:
        timeout = self._server.config.idle_timeout
        if timeout <= 0 or self._closed:
            return
        delay = self.last_activity + timeout - time.monotonic()
        loop = asyncio.get_running_loop()
        self._idle_timer = loop.call_later(max(delay, 0.0), self._check_idle)

    def _check_idle(self) -> None:
        timeout = self._server.config.idle_timeout
        if self._closed:
            return
        if timeout > 0 and not self.busy and time.monotonic() - self.last_activity >= timeout:
            log.info("master %s: idle for %.0f s, closing", self.peer, timeout)
            self.close("idle")
            return
        if self.busy:
            self.last_activity = time.monotonic()
        self._arm_idle_timer()


class ModbusTcpServer:
    """Accepts masters and enforces the connection limit."""

    def __init__(
        self,
        config: ServerConfig,
        router: Router,
        metrics: GatewayMetrics,
        listener: ListenerConfig | None = None,
        policy: Policy | None = None,
        ssl_context: ssl.SSLContext | None = None,
    ) -> None:
        self.config = config
        self.router = router
        self.metrics = metrics
        self.listener = listener or ListenerConfig("tcp", host=config.host, port=config.port)
        self.name = self.listener.name
        self.policy = policy or Policy()  #: replaced as a whole on reload
        self.ssl_context = ssl_context  #: replaced on reload; new connections use the new one
        self.screen = SourceScreen(self.name, (config.allow, self.listener.allow), metrics)
        self.tracer: FrameTracer | None = None  # only while tracing: the frame path tests for None
        self._connections: dict[MasterConnection, None] = {}
        self._server: asyncio.Server | TlsServer | None = None

    @property
    def connections(self) -> int:
        """Masters connected now."""
        return len(self._connections)

    @property
    def sockets(self) -> list[tuple[str, int]]:
        """The addresses the server listens on."""
        if self._server is None:
            return []
        return [sock.getsockname()[:2] for sock in self._server.sockets]

    async def start(self) -> None:
        """Bind and start accepting."""
        loop = asyncio.get_running_loop()
        self.screen.start(loop)
        host, port, backlog = self.listener.host, self.listener.port, self.config.backlog
        if self.ssl_context is not None:
            self._server = await TlsServer.start(
                self, lambda: MasterConnection(self), host, port, backlog
            )
            return
        self._server = await loop.create_server(
            lambda: MasterConnection(self), host, port, backlog=backlog, reuse_address=True
        )

    def admits(self, address: object) -> bool:
        """Allow-list check of a TLS listener at accept, before the handshake reads a byte."""
        source = peer_address_of(address)
        if self.screen.allows(source):
            return True
        self.screen.refuse(source)
        return False

    def screen_source(self, connection: MasterConnection, transport: asyncio.Transport) -> bool:
        """The allow lists at accept (before any byte is read); the source and TLS role."""
        source = peer_address(transport)
        if not self.screen.allows(source):
            self.screen.refuse(source)
            return False
        tls, role = role_of(transport)
        connection.principal = Principal(source, role)
        if tls:
            connection.role_text = "NULL" if role is None else role
        return True

    def handshake_failed(self, reason: HandshakeFailure, error: BaseException) -> None:
        """Count and log (at a bounded rate) a failed TLS handshake."""
        self.screen.handshake_failed(reason, error)

    def stop_accepting(self) -> None:
        """Close the listening sockets; connections stay."""
        if self._server is not None:
            self._server.close()

    def close_all(self, reason: str) -> None:
        """Close every connection."""
        for connection in list(self._connections):
            connection.close(reason)

    async def wait_closed(self) -> None:
        """Wait for the listening sockets to close."""
        if self._server is not None:
            await self._server.wait_closed()

    def masters(self) -> list[MasterStatus]:
        """A snapshot of the connected masters, for the status page."""
        host, port = self.sockets[0] if self.sockets else (self.listener.host, self.listener.port)
        listener = f"{self.name} {host}:{port}"
        return [
            MasterStatus(connection.peer, listener, connection.in_flight, connection.requests)
            for connection in self._connections
        ]

    def admit(self, connection: MasterConnection) -> bool:
        """Accept a new master, or make room (or refuse) at the limit."""
        if len(self._connections) >= self.config.max_connections:
            victim = None
            if self.config.when_full == "close_oldest_idle":
                idle = [c for c in self._connections if not c.busy]
                if idle:
                    victim = min(idle, key=lambda c: c.last_activity)
            if victim is None:
                self.metrics.connections_rejected.inc()
                log.warning(
                    "master %s refused: %d connections open (server.max_connections)",
                    connection.peer,
                    len(self._connections),
                )
                return False
            log.info("master %s: closed to make room for %s", victim.peer, connection.peer)
            victim.close("evicted")
        self._connections[connection] = None
        self.metrics.connections_accepted.inc()
        self.metrics.connections_open.set(len(self._connections))
        log.info("master %s connected", connection.peer)
        return True

    def forget(self, connection: MasterConnection, reason: str) -> None:
        """Drop a closed connection from the books (once)."""
        if self._connections.pop(connection, False) is None:
            self.metrics.connections_closed.labels(reason).inc()
            self.metrics.connections_open.set(len(self._connections))
            log.info("master %s disconnected (%s)", connection.peer, reason)
