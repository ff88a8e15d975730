"""The HTTP endpoint: /metrics (Prometheus text or OpenMetrics), /healthz, /readyz, and more routes.

A deliberately small asyncio HTTP/1.0-style server (one request per
connection, GET and HEAD only, bounded request head) on the gateway's own
loop, so that scraping needs no thread and no web framework. Other modules
add paths (``routes``, ``HttpEndpoint.add_route``: ``gateway.io.http.live``'s trace
stream and status page); every route is served under the same limits:

- at most ``max_connections`` connections at once, streams included; at the
  cap the oldest connection still sending its request head is closed to make
  room (a client that opens connections and sends nothing cannot lock out a
  scraper), and when every connection is past its head the new one is closed;
- the request head must arrive within ``header_timeout``; a handler that
  streams its answer (``/trace``) runs as long as it likes once the head is in.

``/metrics`` is rendered by ``ScrapeRenderer``: fresh for every scrape (never
a cached copy), at most ``SAMPLES_PER_TURN`` samples per turn of the event
loop, and scrapes
spaced so that rendering takes at most 5 % of the loop's time, however
many clients scrape in a loop. Scrapes waiting at the same time share one
rendering.

Who may read what is ``http_guard``'s: ``/metrics``, ``/healthz`` and ``/readyz``
are open; the page, ``/status`` and ``/trace`` check the Host (421) and, when
configured, a token (401/403). One source address holds at most
``max_connections_per_source`` connections. With ``tls_cert`` the endpoint
speaks HTTPS only (TLS 1.2 or newer, forward-secret suites), and with ``tls_ca``
every client must present a certificate.

``/healthz`` answers 200 while the event loop runs (liveness: restart me if
this fails); a missing or noisy serial device does not change it, because a
restart cannot fix hardware and the gateway reopens the device by itself.
``/readyz`` answers 200 only while the TCP listener is up and every configured
line is open, else 503 naming the lines that are down (readiness: the device
is missing). A noisy line is open and ready: its faults are in the metrics; so is
a shared line (another master's frames heard), which ``/readyz`` names.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import copy
import logging
import socket
import ssl
import time
from collections.abc import Awaitable, Callable, Coroutine, Iterator, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from http import HTTPStatus
from typing import Any, Protocol

from prometheus_client import Counter
from prometheus_client.exposition import choose_encoder
from prometheus_client.metrics_core import Metric
from prometheus_client.registry import Collector

from ...config import MetricsConfig
from ...logs import RateLimitedLogger
from ..tls_setup import check_chain, cipher_string, load_authorities, load_key_pair
from .guard import Guard, HttpRefusal, RouteAccess

log = logging.getLogger("gateway.http")

_MAX_REQUEST_HEAD = 8192
#: Seconds a stop waits for the connections' exchanges to end, then for the cancelled rest.
_CLOSE_WAIT_S = 1.0
#: Headers every answer of the current request carries (cookies a ``?token=`` set, ...);
#: each connection is served in a task of its own, so this is per request.
_EXTRA_HEADERS: contextvars.ContextVar[str] = contextvars.ContextVar("extra", default="")
#: Sent with every answer: a ``?token=`` link's token does not leak through a Referer.
_ALWAYS = "Referrer-Policy: no-referrer\r\n"
_INDEX = b"modbus-gateway: /metrics /healthz /readyz\n"
_OPENMETRICS_EOF = b"# EOF\n"
#: Share of the event loop's time that rendering /metrics may take, however often it is asked.
SCRAPE_LOOP_SHARE = 0.05
#: Samples encoded per turn of the event loop: a family of 247 slaves' series is several slices.
SAMPLES_PER_TURN = 32


#: A route: method, target with query, lower-case headers, the streams. It answers on the
#: writer, a whole body or a stream, and closes it.
Route = Callable[
    [str, str, Mapping[str, str], asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]
]
#: A route and what guards it.
GuardedRoute = tuple[Route, RouteAccess]


def extra_headers() -> str:
    """Header lines (each ending in CRLF) that a route's own response head must carry."""
    return _ALWAYS + _EXTRA_HEADERS.get()


async def respond(
    writer: asyncio.StreamWriter,
    status: int,
    content_type: str,
    body: bytes,
    method: str = "GET",
    headers: str = "",
) -> None:
    """Write a whole response (head only for HEAD) and close the connection.

    Every answer here is a snapshot of now (metrics, health, status): never cached.
    """
    reason = HTTPStatus(status).phrase
    head = (
        f"HTTP/1.1 {status} {reason}\r\nContent-Type: {content_type}\r\n"
        f"Content-Length: {len(body)}\r\nCache-Control: no-store\r\nConnection: close\r\n"
        f"{extra_headers()}{headers}\r\n"
    ).encode()
    try:
        if writer.transport.is_closing():  # closed meanwhile (a stop): uvloop raises on write
            return
        writer.write(head if method == "HEAD" else head + body)
        await writer.drain()
    except ConnectionError:
        pass
    finally:
        writer.close()


class _Single(Collector):
    """One metric family as a registry, for the encoders."""

    def __init__(self, metric: Metric) -> None:
        self._metric = metric

    def collect(self) -> Iterator[Metric]:
        yield self._metric


class PacedRenderer:
    """Answers rendered fresh for the requests that wait for them, at a bounded share of the loop.

    Requests that arrive before a rendering starts all get that rendering (one per
    ``key``); the next rendering starts no sooner than ``(1 / share - 1)`` times the
    last one's cost after it, so asking in a loop takes at most ``share`` of the loop.
    """

    def __init__(self, share: float = SCRAPE_LOOP_SHARE) -> None:
        self._share = share
        self._next: dict[str, asyncio.Future[bytes]] = {}  # by key, not started yet
        self._lock = asyncio.Lock()
        self._not_before = 0.0
        self.last_cost = 0.0  #: seconds the last rendering held the loop, all turns together
        self.renderings = 0

    @property
    def not_before(self) -> float:
        """The loop time before which the next rendering does not start."""
        return self._not_before

    async def shared(
        self, key: str, produce: Callable[[], Awaitable[tuple[bytes, float]]]
    ) -> bytes:
        """The body ``produce`` (body, cost in seconds) renders after this call for ``key``."""
        future = self._next.get(key)
        if future is None:
            loop = asyncio.get_running_loop()
            future = self._next[key] = loop.create_future()
            task = loop.create_task(self._run(key, produce, future))
            task.add_done_callback(_log_failure)
        return await asyncio.shield(future)

    async def _run(
        self,
        key: str,
        produce: Callable[[], Awaitable[tuple[bytes, float]]],
        future: asyncio.Future[bytes],
    ) -> None:
        loop = asyncio.get_running_loop()
        async with self._lock:
            delay = self._not_before - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            del self._next[key]  # requests from now on wait for the next rendering
            try:
                body, self.last_cost = await produce()
            except Exception as error:  # a renderer's bug must not hang every client
                future.set_exception(error)
                raise
            self.renderings += 1
            future.set_result(body)
            self._not_before = loop.time() + self.last_cost * (1.0 / self._share - 1.0)


class ScrapeRenderer(PacedRenderer):
    """Renders /metrics fresh for each scrape at a bounded cost to the event loop.

    Rendering the exposition is the one thing on the Modbus loop whose cost
    grows with the number of series. Each slice of a family's samples is encoded
    in a turn of its own, so a master's reply waits for one slice at most; scrapes
    are shared and spaced as ``PacedRenderer`` says.
    """

    def __init__(self, registry: Collector, share: float = SCRAPE_LOOP_SHARE) -> None:
        super().__init__(share)
        self._registry = registry

    async def render(self, accept: str) -> tuple[bytes, str]:
        """The exposition for a scraper's Accept header, rendered after this call: body, type."""
        encoder, content_type = choose_encoder(accept)
        body = await self.shared(content_type, lambda: self._render(encoder, content_type))
        return body, content_type

    async def _render(
        self, encoder: Callable[[Collector], bytes], content_type: str
    ) -> tuple[bytes, float]:
        openmetrics = content_type.startswith("application/openmetrics-text")
        parts: list[bytes] = []
        cost = 0.0
        families = iter(self._registry.collect())
        while True:
            started = time.perf_counter()
            metric = next(families, None)
            cost += time.perf_counter() - started
            if metric is None:
                break
            samples = metric.samples
            for first in range(0, max(len(samples), 1), SAMPLES_PER_TURN):
                await asyncio.sleep(0)  # a master's reply waits for one slice at most
                started = time.perf_counter()
                part = encoder(_Single(_slice(metric, first)))
                if first:  # the family's HELP and TYPE lines come once
                    part = _without_comments(part)
                if openmetrics and part.endswith(_OPENMETRICS_EOF):
                    part = part[: -len(_OPENMETRICS_EOF)]
                parts.append(part)
                cost += time.perf_counter() - started
        if openmetrics:
            parts.append(_OPENMETRICS_EOF)
        return b"".join(parts), cost


def _slice(metric: Metric, first: int) -> Metric:
    """``metric`` with only samples ``first .. first + SAMPLES_PER_TURN``."""
    if first == 0 and len(metric.samples) <= SAMPLES_PER_TURN:
        return metric
    part = copy.copy(metric)
    part.samples = metric.samples[first : first + SAMPLES_PER_TURN]
    return part


def _without_comments(text: bytes) -> bytes:
    """An encoded family without its leading ``# HELP``/``# TYPE``/``# UNIT`` lines."""
    start = 0
    while text.startswith(b"# ", start):
        start = text.index(b"\n", start) + 1
    return text[start:]


def _log_failure(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and (error := task.exception()) is not None:
        log.error("rendering an HTTP answer failed: %r", error, exc_info=error)


@dataclass(eq=False, slots=True)
class _Connection:
    transport: _Abortable  #: a transport, or an HTTPS connection's pending handshake
    opened: float
    source: str
    reading_head: bool = True


def endpoint_tls(config: MetricsConfig) -> ssl.SSLContext | None:
    """The endpoint's HTTPS context (``None`` without ``tls_cert``); ``TlsSetupError`` names
    the key at fault."""
    if config.tls_cert is None or config.tls_key is None:
        return None
    check_chain(config.tls_cert, "metrics.tls_cert", datetime.now(UTC))  # read, and in date
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.options |= ssl.OP_NO_RENEGOTIATION | ssl.OP_NO_COMPRESSION
    context.options |= ssl.OP_CIPHER_SERVER_PREFERENCE
    context.set_ciphers(cipher_string(forward_secrecy_only=True))  # browsers have ECDHE
    load_key_pair(context, config.tls_cert, config.tls_key, ("metrics.tls_cert", "metrics.tls_key"))
    if config.tls_ca is not None:
        load_authorities(context, config.tls_ca, "metrics.tls_ca")
        context.verify_mode = ssl.CERT_REQUIRED
    return context


class _Abortable(Protocol):
    """What a connection is closed through: its transport, or its pending handshake."""

    def abort(self) -> None: ...


class _Handshake:
    """An HTTPS connection admitted, its handshake under way: aborting cancels it."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.task: asyncio.Task[None] | None = None

    def abort(self) -> None:
        if self.task is not None:
            self.task.cancel()  # its finally closes the socket
        else:
            self.sock.close()


class _TlsListener:
    """The HTTPS endpoint's listening socket, accepted by hand: a connection is admitted
    before its handshake (the caps hold handshakes too), and the TLS layer gets the socket
    before any byte of it is read."""

    BATCH = 32  #: connections accepted per turn of the loop

    def __init__(self, accepted: Callable[[socket.socket, str], None]) -> None:
        self._accepted = accepted
        self.sock: socket.socket | None = None

    async def start(self, host: str, port: int) -> None:
        loop = asyncio.get_running_loop()
        infos = await loop.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        family, kind, proto, _, address = infos[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
            sock.listen(128)
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        self.sock = sock
        loop.add_reader(sock.fileno(), self._ready)

    def _ready(self) -> None:
        assert self.sock is not None
        for _ in range(self.BATCH):
            try:
                conn, peer = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as error:  # out of descriptors: the next turn tries again
                log.debug("HTTPS accept failed: %s", error)
                return
            self._accepted(conn, str(peer[0]))

    def close(self) -> None:
        if self.sock is not None:
            asyncio.get_running_loop().remove_reader(self.sock.fileno())
            self.sock.close()


@dataclass(frozen=True, slots=True)
class EndpointLimits:
    """How much of the endpoint one client, and all of them, may hold."""

    max_connections: int = 32
    header_timeout: float = 5.0
    max_per_source: int = 8  #: 0: no cap


class HttpEndpoint:
    """A running HTTP endpoint."""

    def __init__(
        self,
        registry: Collector,
        readiness: Callable[[], tuple[bool, str]],
        routes: Mapping[str, GuardedRoute] | None = None,
        limits: EndpointLimits | None = None,
        guard: Guard | None = None,
        refusals: Counter | None = None,
    ) -> None:
        self._readiness = readiness
        self.limits = limits or EndpointLimits()
        self.max_connections = self.limits.max_connections
        self.header_timeout = self.limits.header_timeout
        self.guard = guard or Guard(MetricsConfig())
        self._refusals = refusals
        if refusals is not None:
            for reason in HttpRefusal:
                refusals.labels(reason)
        self.renderer = ScrapeRenderer(registry)
        self._server: asyncio.Server | None = None
        self._tls: ssl.SSLContext | None = None
        self._tls_listener: _TlsListener | None = None
        self._open: dict[_Connection, None] = {}  # in opening order
        #: Every connection's task: ``close`` ends them, so none is left for the loop's
        #: shutdown to cancel (asyncio logs a cancelled stream handler as an ERROR).
        self._tasks: set[asyncio.Task[None]] = set()
        self._per_source: dict[str, int] = {}
        self.refused = 0  #: connections closed at once at the cap
        self._faults: RateLimitedLogger | None = None  # bound to the loop in start()
        self._routes: dict[str, GuardedRoute] = {
            "/metrics": (self._metrics, RouteAccess.OPEN),
            "/healthz": (self._healthz, RouteAccess.OPEN),
            "/readyz": (self._readyz, RouteAccess.OPEN),
            "/": (self._index, RouteAccess.OPEN),
        }
        self._routes.update(routes or {})

    def add_route(self, path: str, route: Route, access: RouteAccess = RouteAccess.STATUS) -> None:
        """Serve ``path`` (without query) with ``route``, under the endpoint's limits and
        guarded as ``access`` says (by default as the status page)."""
        self._routes[path] = (route, access)

    @property
    def address(self) -> tuple[str, int]:
        """The bound address."""
        if self._tls_listener is not None and self._tls_listener.sock is not None:
            host, port = self._tls_listener.sock.getsockname()[:2]
            return str(host), int(port)
        assert self._server is not None
        host, port = self._server.sockets[0].getsockname()[:2]
        return str(host), int(port)

    @property
    def connections(self) -> int:
        """HTTP connections open now."""
        return len(self._open)

    async def start(self, host: str, port: int, tls: ssl.SSLContext | None = None) -> None:
        """Bind and serve (HTTPS with ``tls``)."""
        self._faults = RateLimitedLogger(log, asyncio.get_running_loop())
        if tls is None:
            self._server = await asyncio.start_server(
                self._serve, host, port, reuse_address=True, limit=_MAX_REQUEST_HEAD
            )
            return
        self._tls = tls
        self._tls_listener = _TlsListener(self._accepted_tls)
        await self._tls_listener.start(host, port)

    async def close(self) -> None:
        """Stop serving."""
        if self._tls_listener is not None:
            self._tls_listener.close()
            for connection in list(self._open):
                connection.transport.abort()
        if self._server is not None:
            self._server.close()
            for connection in list(self._open):
                connection.transport.abort()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
        await self._end_tasks()

    async def _end_tasks(self) -> None:
        """Let each connection's task see its aborted transport (or its trace stream ended)
        and return; cancel what is still running after ``_CLOSE_WAIT_S`` and wait for it."""
        current = asyncio.current_task()
        tasks = {task for task in self._tasks if task is not current}
        if not tasks:
            return
        _done, pending = await asyncio.wait(tasks, timeout=_CLOSE_WAIT_S)
        for task in pending:
            task.cancel()
        if pending:
            await asyncio.wait(pending, timeout=_CLOSE_WAIT_S)

    # -- admission ---------------------------------------------------------------------

    def _note(self, what: str, detail: str) -> None:
        if self._faults is not None:
            self._faults.note("HTTP endpoint", what, detail, plural="connections past the limit")

    def _admit(self, transport: _Abortable, source: str) -> _Connection | None:
        """Register a new connection, making room at the cap; ``None`` when it is refused."""
        cap = self.limits.max_per_source
        if cap and self._per_source.get(source, 0) >= cap:
            self._note(
                "source limit",
                f"{source} holds {cap} connections "
                "(metrics.max_connections_per_source); refusing more",
            )
            self._refuse(transport, HttpRefusal.MAX_PER_SOURCE)
            return None
        if len(self._open) >= self.max_connections:
            waiting = next((c for c in self._open if c.reading_head), None)
            self._note(
                "connection limit",
                f"{self.max_connections} connections open (metrics.max_connections); "
                + (
                    "closing the oldest still sending its request"
                    if waiting is not None
                    else "refusing new ones"
                ),
            )
            if waiting is None:
                self._refuse(transport, HttpRefusal.MAX_CONNECTIONS)
                return None
            waiting.transport.abort()  # its _serve forgets it
            self._forget(waiting)
        connection = _Connection(transport, time.monotonic(), source)
        self._open[connection] = None
        self._per_source[source] = self._per_source.get(source, 0) + 1
        return connection

    def _refused(self, reason: HttpRefusal) -> None:
        if self._refusals is not None:
            self._refusals.labels(reason).inc()

    def _refuse(self, transport: _Abortable, reason: HttpRefusal) -> None:
        self.refused += 1
        self._refused(reason)
        transport.abort()

    def _forget(self, connection: _Connection) -> None:
        if self._open.pop(connection, False) is None:
            remaining = self._per_source.get(connection.source, 1) - 1
            if remaining > 0:
                self._per_source[connection.source] = remaining
            else:
                self._per_source.pop(connection.source, None)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        connection = self._admit(writer.transport, str(peer[0]) if peer else "")
        if connection is not None:
            await self._tracked(self._serve_connection(connection, reader, writer))

    async def _tracked(self, serving: Coroutine[Any, Any, None]) -> None:
        """Run one connection's exchange as a task ``close`` can end. A cancellation (by
        ``close`` after its wait, by the cap making room, or by the loop's shutdown) ends the
        exchange quietly: the task returns, and its transport is closed by its own finally."""
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            with contextlib.suppress(asyncio.CancelledError):
                await serving
        finally:
            self._tasks.discard(task)

    async def _serve_connection(
        self, connection: _Connection, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        try:
            await self._serve_admitted(connection, reader, writer)
        finally:
            self._forget(connection)
            if not writer.transport.is_closing():
                writer.close()

    def _accepted_tls(self, sock: socket.socket, source: str) -> None:
        """An HTTPS connection: admitted first, then its handshake in a task of its own."""
        pending = _Handshake(sock)
        connection = self._admit(pending, source)
        if connection is not None:
            serving = self._tracked(self._serve_tls(connection, sock))
            pending.task = asyncio.get_running_loop().create_task(serving)

    async def _serve_tls(self, connection: _Connection, sock: socket.socket) -> None:
        """The handshake within the header timeout, then the request as over HTTP."""
        assert self._tls is not None
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader(_MAX_REQUEST_HEAD, loop)
        protocol = asyncio.StreamReaderProtocol(reader, loop=loop)
        transport = None
        try:
            transport, _ = await loop.connect_accepted_socket(
                lambda: protocol, sock, ssl=self._tls, ssl_handshake_timeout=self.header_timeout
            )
        except (ssl.SSLError, OSError) as error:  # ConnectionError and TimeoutError too
            log.debug("HTTPS handshake with %s failed: %s", connection.source, error)
        finally:
            if transport is None:  # failed, or cancelled to make room
                self._forget(connection)
                sock.close()
        if transport is None:
            return
        connection.transport = transport
        writer = asyncio.StreamWriter(transport, protocol, reader, loop)
        await self._serve_connection(connection, reader, writer)

    async def _serve_admitted(
        self, connection: _Connection, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), self.header_timeout)
        except asyncio.LimitOverrunError:
            connection.reading_head = False
            await respond(writer, 431, "text/plain", b"request header too large\n")
            return
        except (asyncio.IncompleteReadError, TimeoutError, ConnectionError, ssl.SSLError):
            return
        connection.reading_head = False
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split()
        headers = {
            name.strip().lower(): value.strip()
            for name, _, value in (line.partition(":") for line in lines[1:] if line)
        }
        if len(parts) < 2 or parts[0] not in ("GET", "HEAD"):
            await respond(writer, 405, "text/plain", b"only GET is served\n")
            return
        method, target = parts[0], parts[1]
        served = self._routes.get(target.split("?", 1)[0])
        if served is None:
            await respond(writer, 404, "text/plain", b"not found\n", method)
            return
        route, access = served
        local = writer.get_extra_info("sockname")
        verdict = self.guard.judge(access, target, headers, str(local[0]) if local else "")
        if verdict.refusal is not None:
            self._refused(verdict.refusal)
            await respond(
                writer, verdict.status, "text/plain", verdict.message, method, verdict.challenge
            )
            return
        _EXTRA_HEADERS.set("".join(f"Set-Cookie: {c}\r\n" for c in verdict.set_cookies))
        with contextlib.suppress(ConnectionError):
            await route(method, target, headers, reader, writer)

    # -- routes ------------------------------------------------------------------------

    async def _metrics(
        self,
        method: str,
        _target: str,
        headers: Mapping[str, str],
        _reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        body, content_type = await self.renderer.render(headers.get("accept", ""))
        await respond(writer, 200, content_type, body, method)

    async def _healthz(
        self,
        method: str,
        _target: str,
        _headers: Mapping[str, str],
        _reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        await respond(writer, 200, "text/plain", b"ok\n", method)

    async def _readyz(
        self,
        method: str,
        _target: str,
        _headers: Mapping[str, str],
        _reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        ready, why = self._readiness()
        await respond(writer, 200 if ready else 503, "text/plain", (why + "\n").encode(), method)

    async def _index(
        self,
        method: str,
        _target: str,
        _headers: Mapping[str, str],
        _reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        await respond(writer, 200, "text/plain", _INDEX, method)


def role_route(answer: Callable[[], tuple[int, bytes]]) -> Route:
    """``GET /role`` (``io.pair.channel``): ``answer()`` gives its status and JSON body."""

    async def role(
        method: str,
        _target: str,
        _headers: Mapping[str, str],
        _reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        status, body = answer()
        await respond(writer, status, "application/json", body, method)

    return role


async def start_http(
    config: MetricsConfig,
    registry: Collector,
    readiness: Callable[[], tuple[bool, str]],
    routes: Mapping[str, GuardedRoute] | None = None,
    refusals: Counter | None = None,
) -> HttpEndpoint:
    """Start the endpoint on the configured address (HTTPS with ``tls_cert``)."""
    limits = EndpointLimits(
        config.max_connections, config.header_timeout, config.max_connections_per_source
    )
    endpoint = HttpEndpoint(registry, readiness, routes, limits, Guard(config), refusals)
    await endpoint.start(config.host, config.port, endpoint_tls(config))
    return endpoint
