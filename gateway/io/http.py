"""The HTTP endpoint: /metrics (Prometheus text or OpenMetrics), /healthz, /readyz, and more routes.

A deliberately small asyncio HTTP/1.0-style server (one request per
connection, GET and HEAD only, bounded request head) on the gateway's own
loop, so that scraping needs no thread and no web framework. Other modules
add paths (``routes``, ``HttpEndpoint.add_route``: ``gateway.live``'s trace
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

``/healthz`` answers 200 while the event loop runs (liveness: restart me if
this fails); a missing or noisy serial device does not change it, because a
restart cannot fix hardware and the gateway reopens the device by itself.
``/readyz`` answers 200 only while the TCP listener is up and every configured
line is open, else 503 naming the lines that are down (readiness: the device
is missing). A noisy line is open and ready: its faults are in the metrics.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import logging
import time
from collections.abc import Awaitable, Callable, Iterator, Mapping
from dataclasses import dataclass
from http import HTTPStatus

from prometheus_client.exposition import choose_encoder
from prometheus_client.metrics_core import Metric
from prometheus_client.registry import Collector

from ..config import MetricsConfig
from ..logs import RateLimitedLogger

log = logging.getLogger("gateway.http")

_MAX_REQUEST_HEAD = 8192
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


async def respond(
    writer: asyncio.StreamWriter, status: int, content_type: str, body: bytes, method: str = "GET"
) -> None:
    """Write a whole response (head only for HEAD) and close the connection.

    Every answer here is a snapshot of now (metrics, health, status): never cached.
    """
    reason = HTTPStatus(status).phrase
    head = (
        f"HTTP/1.1 {status} {reason}\r\nContent-Type: {content_type}\r\n"
        f"Content-Length: {len(body)}\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n"
    ).encode()
    try:
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


class ScrapeRenderer:
    """Renders /metrics fresh for each scrape at a bounded cost to the event loop.

    Rendering the exposition is the one thing on the Modbus loop whose cost
    grows with the number of series. Each slice of a family's samples is encoded
    in a turn of its own, so a master's reply waits for one slice at most; the next
    rendering starts no sooner than ``(1 / share - 1)`` times the last one's
    cost after it, so scraping in a loop takes at most ``share`` of the loop.
    Scrapes that arrive before a rendering starts all get that rendering.
    """

    def __init__(self, registry: Collector, share: float = SCRAPE_LOOP_SHARE) -> None:
        self._registry = registry
        self._share = share
        self._next: dict[str, asyncio.Future[bytes]] = {}  # by content type, not started yet
        self._lock = asyncio.Lock()
        self._not_before = 0.0
        self.last_cost = 0.0  #: seconds the last rendering held the loop, all turns together
        self.renderings = 0

    @property
    def not_before(self) -> float:
        """The loop time before which the next rendering does not start."""
        return self._not_before

    async def render(self, accept: str) -> tuple[bytes, str]:
        """The exposition for a scraper's Accept header, rendered after this call: body, type."""
        encoder, content_type = choose_encoder(accept)
        future = self._next.get(content_type)
        if future is None:
            loop = asyncio.get_running_loop()
            future = self._next[content_type] = loop.create_future()
            task = loop.create_task(self._run(content_type, encoder, future))
            task.add_done_callback(_log_failure)
        return await asyncio.shield(future), content_type

    async def _run(
        self,
        content_type: str,
        encoder: Callable[[Collector], bytes],
        future: asyncio.Future[bytes],
    ) -> None:
        loop = asyncio.get_running_loop()
        async with self._lock:
            delay = self._not_before - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            del self._next[content_type]  # scrapes from now on wait for the next rendering
            try:
                body = await self._render(encoder, content_type)
            except Exception as error:  # a collector's bug must not hang every scraper
                future.set_exception(error)
                raise
            future.set_result(body)
            self._not_before = loop.time() + self.last_cost * (1.0 / self._share - 1.0)

    async def _render(self, encoder: Callable[[Collector], bytes], content_type: str) -> bytes:
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
        self.last_cost = cost
        self.renderings += 1
        return b"".join(parts)


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
        log.error("rendering /metrics failed: %r", error, exc_info=error)


@dataclass(eq=False, slots=True)
class _Connection:
    writer: asyncio.StreamWriter
    opened: float
    reading_head: bool = True


class HttpEndpoint:
    """A running HTTP endpoint."""

    def __init__(
        self,
        registry: Collector,
        readiness: Callable[[], tuple[bool, str]],
        routes: Mapping[str, Route] | None = None,
        max_connections: int = 32,
        header_timeout: float = 5.0,
    ) -> None:
        self._readiness = readiness
        self.max_connections = max_connections
        self.header_timeout = header_timeout
        self.renderer = ScrapeRenderer(registry)
        self._server: asyncio.Server | None = None
        self._open: dict[_Connection, None] = {}  # in opening order
        self.refused = 0  #: connections closed at once at the cap
        self._faults: RateLimitedLogger | None = None  # bound to the loop in start()
        self._routes: dict[str, Route] = {
            "/metrics": self._metrics,
            "/healthz": self._healthz,
            "/readyz": self._readyz,
            "/": self._index,
        }
        self._routes.update(routes or {})

    def add_route(self, path: str, route: Route) -> None:
        """Serve ``path`` (without query) with ``route``, under the endpoint's limits."""
        self._routes[path] = route

    @property
    def address(self) -> tuple[str, int]:
        """The bound address."""
        assert self._server is not None
        host, port = self._server.sockets[0].getsockname()[:2]
        return str(host), int(port)

    @property
    def connections(self) -> int:
        """HTTP connections open now."""
        return len(self._open)

    async def start(self, host: str, port: int) -> None:
        """Bind and serve."""
        self._faults = RateLimitedLogger(log, asyncio.get_running_loop())
        self._server = await asyncio.start_server(
            self._serve, host, port, reuse_address=True, limit=_MAX_REQUEST_HEAD
        )

    async def close(self) -> None:
        """Stop serving."""
        if self._server is not None:
            self._server.close()
            for connection in list(self._open):
                connection.writer.transport.abort()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)

    # -- admission ---------------------------------------------------------------------

    def _admit(self, writer: asyncio.StreamWriter) -> _Connection | None:
        """Register a new connection, making room at the cap; ``None`` when it is refused."""
        if len(self._open) >= self.max_connections:
            waiting = next((c for c in self._open if c.reading_head), None)
            if self._faults is not None:
                self._faults.note(
                    "HTTP endpoint", "connection limit",
                    f"{self.max_connections} connections open (metrics.max_connections); "
                    + ("closing the oldest still sending its request"
                       if waiting is not None else "refusing new ones"),
                    plural="connections past the limit",
                )  # fmt: skip
            if waiting is None:
                self.refused += 1
                writer.transport.abort()
                return None
            waiting.writer.transport.abort()  # its _serve forgets it
            self._open.pop(waiting, None)
        connection = _Connection(writer, time.monotonic())
        self._open[connection] = None
        return connection

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        connection = self._admit(writer)
        if connection is None:
            return
        try:
            await self._serve_admitted(connection, reader, writer)
        finally:
            self._open.pop(connection, None)
            if not writer.transport.is_closing():
                writer.close()

    async def _serve_admitted(
        self, connection: _Connection, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), self.header_timeout)
        except asyncio.LimitOverrunError:
            connection.reading_head = False
            await respond(writer, 431, "text/plain", b"request header too large\n")
            return
        except (asyncio.IncompleteReadError, TimeoutError, ConnectionError):
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
        route = self._routes.get(target.split("?", 1)[0])
        if route is None:
            await respond(writer, 404, "text/plain", b"not found\n", method)
            return
        with contextlib.suppress(ConnectionError):
            await route(method, target, headers, reader, writer)

    # -- routes ------------------------------------------------------------------------

    async def _metrics(
        self, method: str, _target: str, headers: Mapping[str, str],
        _reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
    ) -> None:  # fmt: skip
        body, content_type = await self.renderer.render(headers.get("accept", ""))
        await respond(writer, 200, content_type, body, method)

    async def _healthz(
        self, method: str, _target: str, _headers: Mapping[str, str],
        _reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
    ) -> None:  # fmt: skip
        await respond(writer, 200, "text/plain", b"ok\n", method)

    async def _readyz(
        self, method: str, _target: str, _headers: Mapping[str, str],
        _reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
    ) -> None:  # fmt: skip
        ready, why = self._readiness()
        await respond(writer, 200 if ready else 503, "text/plain", (why + "\n").encode(), method)

    async def _index(
        self, method: str, _target: str, _headers: Mapping[str, str],
        _reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
    ) -> None:  # fmt: skip
        await respond(writer, 200, "text/plain", _INDEX, method)


async def start_http(
    config: MetricsConfig,
    registry: Collector,
    readiness: Callable[[], tuple[bool, str]],
    routes: Mapping[str, Route] | None = None,
) -> HttpEndpoint:
    """Start the endpoint on the configured address."""
    endpoint = HttpEndpoint(
        registry, readiness, routes, config.max_connections, config.header_timeout
    )
    await endpoint.start(config.host, config.port)
    return endpoint
