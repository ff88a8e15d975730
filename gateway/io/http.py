"""The HTTP endpoint: /metrics (Prometheus text or OpenMetrics), /healthz and /readyz.

A deliberately small asyncio HTTP/1.0-style server (one request per
connection, GET and HEAD only, bounded request size) on the gateway's own
loop, so that scraping needs no thread and no web framework.

``/healthz`` answers 200 while the event loop runs (liveness: restart me if
this fails); ``/readyz`` answers 200 only while the TCP listener is up and
every configured line is open, else 503 with the reason, naming the lines
that are down (readiness: do not send me traffic). ``/metrics`` speaks
OpenMetrics when the scraper's Accept header asks for it, else text 0.0.4.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable, Mapping
from http import HTTPStatus

from prometheus_client import CollectorRegistry
from prometheus_client.exposition import choose_encoder

from ..config import MetricsConfig

log = logging.getLogger("gateway.http")

_MAX_REQUEST_HEAD = 8192
_READ_TIMEOUT = 5.0
_INDEX = b"modbus-gateway: /metrics /healthz /readyz\n"

#: An extra route (gateway.live): method, target with query, lower-case headers, the streams.
Route = Callable[
    [str, str, Mapping[str, str], asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]
]


class HttpEndpoint:
    """A running HTTP endpoint."""

    def __init__(
        self,
        registry: CollectorRegistry,
        readiness: Callable[[], tuple[bool, str]],
        routes: Mapping[str, Route] | None = None,
    ) -> None:
        self._registry = registry
        self._readiness = readiness
        self._routes = dict(routes or {})
        self._server: asyncio.Server | None = None

    @property
    def address(self) -> tuple[str, int]:
        """The bound address."""
        assert self._server is not None
        host, port = self._server.sockets[0].getsockname()[:2]
        return str(host), int(port)

    async def start(self, host: str, port: int) -> None:
        """Bind and serve."""
        self._server = await asyncio.start_server(
            self._serve, host, port, reuse_address=True, limit=_MAX_REQUEST_HEAD
        )

    async def close(self) -> None:
        """Stop serving."""
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), _READ_TIMEOUT)
        except asyncio.LimitOverrunError:
            await self._respond(writer, 431, "text/plain", b"request header too large\n")
            return
        except (asyncio.IncompleteReadError, TimeoutError, ConnectionError):
            writer.close()
            return
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split()
        headers = {
            name.strip().lower(): value.strip()
            for name, _, value in (line.partition(":") for line in lines[1:] if line)
        }
        if len(parts) < 2 or parts[0] not in ("GET", "HEAD"):
            await self._respond(writer, 405, "text/plain", b"only GET is served\n")
            return
        path = parts[1].split("?", 1)[0]
        route = self._routes.get(path)
        if route is not None:
            await route(parts[0], parts[1], headers, reader, writer)
        elif path == "/metrics":
            encoder, content_type = choose_encoder(headers.get("accept", ""))
            await self._respond(writer, 200, content_type, encoder(self._registry), parts[0])
        elif path == "/healthz":
            await self._respond(writer, 200, "text/plain", b"ok\n", parts[0])
        elif path == "/readyz":
            ready, why = self._readiness()
            await self._respond(writer, 200 if ready else 503, "text/plain",
                                (why + "\n").encode(), parts[0])  # fmt: skip
        elif path == "/":
            await self._respond(writer, 200, "text/plain", _INDEX, parts[0])
        else:
            await self._respond(writer, 404, "text/plain", b"not found\n", parts[0])

    @staticmethod
    async def _respond(writer: asyncio.StreamWriter, status: int, content_type: str,
                       body: bytes, method: str = "GET") -> None:  # fmt: skip
        reason = HTTPStatus(status).phrase
        head = (
            f"HTTP/1.1 {status} {reason}\r\nContent-Type: {content_type}\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
        ).encode()
        try:
            writer.write(head if method == "HEAD" else head + body)
            await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()


async def start_http(
    config: MetricsConfig,
    registry: CollectorRegistry,
    readiness: Callable[[], tuple[bool, str]],
    routes: Mapping[str, Route] | None = None,
) -> HttpEndpoint:
    """Start the endpoint on the configured address."""
    endpoint = HttpEndpoint(registry, readiness, routes)
    await endpoint.start(config.host, config.port)
    return endpoint
