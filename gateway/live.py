"""Watching a running gateway: the live trace stream, ``GET /status`` and the status page.

Theory of operation: ``TraceHub`` takes the TCP server's tracer seat (in front
of the ``--trace`` logging tracer, if any) only while somebody watches: a
trace stream is open, or the status page asked for ``/status`` in the last
``WATCH_S`` seconds. Nobody watching costs the frame path nothing more than
before. Each event is matched against each stream's filters and appended to
that stream's own bounded queue; a stream whose client reads too slowly loses
events (counted in ``trace_dropped_events_total`` and announced to the client
as a gap) rather than slowing the gateway: the frame path never waits for a
socket. Serialising to JSON happens in the stream's writer task, off the
frame path.

A request event carries its PDU in hex and, looked up in the router at that
moment, the line and slave address it goes to (so a remapped unit shows where
it went). Reply latencies per slave are kept over the last ``LATENCY_SAMPLES``
answers while watched; line latencies come from the request-duration histogram.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from importlib import resources
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs

from prometheus_client.registry import Collector

from . import __version__
from .core import pdu as fc
from .io.http import Route, respond
from .metrics import OUTCOMES
from .status import GatewayStatus, LineState, quantile, to_json
from .trace import Tracer, parse_function

if TYPE_CHECKING:
    from .app import Gateway

log = logging.getLogger("gateway.live")

#: Events a stream may have waiting before new ones are dropped for it.
QUEUE_LIMIT = 1024
#: Trace streams open at once; more are answered 503 (each holds a queue and a socket).
MAX_STREAMS = 16
#: After a ``/status`` request, per-slave latencies are gathered for this long.
WATCH_S = 30.0
#: Recent answers per slave kept for its p50/p99.
LATENCY_SAMPLES = 512
#: Requests remembered for their reply's latency and route.
MAX_PENDING = 4096
#: Bytes of a stream buffered in the process and in the kernel's send buffer, each.
STREAM_BUFFER = 64 * 1024
#: A comment line keeps idle event streams (and proxies) from timing out.
HEARTBEAT_S = 15.0

#: Outcomes of a reply that came from the slave, used for its latency.
_ANSWERED = frozenset({"ok", "slave_exception"})
_OUTCOME_BY_CODE = {0x0A: "no_route", 0x0B: "target_failed"}


@dataclass(slots=True)  # not frozen: a frozen dataclass costs ~1 us more to build
class TraceEvent:
    """One frame to or from a master, with where it went on the line side."""

    time: float  # wall-clock seconds
    direction: str  # "request", "reply" or "dropped" (the master left before its answer)
    master: str
    transaction_id: int
    unit: int
    function: int
    pdu: bytes
    line: str | None = None
    slave: int | None = None
    outcome: str | None = None
    latency_ms: float | None = None
    listener: str | None = None  # requests: the listener it came in on
    role: str | None = None  # requests on a tls listener: the client's role ("NULL" for none)

    def to_json(self) -> dict[str, Any]:
        """The event as the stream sends it."""
        event: dict[str, Any] = {
            "type": self.direction,
            "time": round(self.time, 6),
            "master": self.master,
            "tid": self.transaction_id,
            "unit": self.unit,
            "function": fc.function_name(self.function),
            "fc": self.function,
            "hex": self.pdu.hex(" "),
            "line": self.line,
            "slave": self.slave,
        }
        if self.direction == "request":
            event["detail"] = fc.describe_request(self.pdu) if self.pdu else ""
        elif self.pdu:
            echoed = self.function in fc.ECHOED_WRITES and not fc.is_exception(self.pdu)
            event["detail"] = (fc.describe_request if echoed else fc.describe_response)(self.pdu)
        if self.outcome is not None:
            event["outcome"] = self.outcome
        if self.latency_ms is not None:
            event["latency_ms"] = round(self.latency_ms, 3)
        if self.listener is not None:
            event["listener"] = self.listener
        if self.role is not None:
            event["role"] = self.role
        return event


@dataclass(frozen=True, slots=True)
class TraceFilter:
    """Which events a stream wants; an empty set lets everything through."""

    lines: frozenset[str] = frozenset()
    units: frozenset[int] = frozenset()
    functions: frozenset[int] = frozenset()
    outcomes: frozenset[str] = frozenset()
    masters: tuple[str, ...] = ()

    @classmethod
    def from_query(cls, query: Mapping[str, list[str]]) -> TraceFilter:
        """From ``?line=a&unit=1,2&function=3&outcome=target_failed&master=10.0.0.5``.

        Each parameter may repeat or hold a comma-separated list; ``ValueError`` names
        the parameter and the accepted values.
        """

        def values(name: str) -> list[str]:
            return [v.strip() for raw in query.get(name, ()) for v in raw.split(",") if v.strip()]

        units: set[int] = set()
        for text in values("unit"):
            try:
                unit = int(text, 0)
            except ValueError:
                raise ValueError(f"unit={text!r}: expected a unit id 0..255") from None
            if not 0 <= unit <= 255:
                raise ValueError(f"unit={unit}: expected a unit id 0..255")
            units.add(unit)
        functions: set[int] = set()
        for text in values("function"):
            try:
                functions.add(parse_function(text))
            except ValueError as error:
                raise ValueError(f"function={text!r}: {error}") from None
        outcomes = set(values("outcome"))
        known = {*OUTCOMES, "exception"}
        unknown = outcomes - known
        if unknown:
            raise ValueError(
                f"outcome={','.join(sorted(unknown))}: expected one of {', '.join(sorted(known))}"
            )
        return cls(frozenset(values("line")), frozenset(units), frozenset(functions),
                   frozenset(outcomes), tuple(values("master")))  # fmt: skip

    def matches(self, event: TraceEvent) -> bool:
        """True when ``event`` passes every filter (an outcome filter passes replies only)."""
        return (
            (not self.units or event.unit in self.units)
            and (not self.functions or (event.function & 0x7F) in self.functions)
            and (not self.lines or event.line in self.lines)
            and (not self.outcomes or event.outcome in self.outcomes)
            and (not self.masters or any(_master_matches(m, event.master) for m in self.masters))
        )


def _master_matches(wanted: str, peer: str) -> bool:
    """``10.0.0.5`` matches every port of that host; ``10.0.0.5:4711`` one connection."""
    return peer == wanted or peer.rpartition(":")[0].strip("[]") == wanted.strip("[]")


class TraceStream:
    """One client's bounded queue of events."""

    def __init__(self, trace_filter: TraceFilter) -> None:
        self.filter = trace_filter
        self.events: deque[TraceEvent] = deque()
        self.dropped = 0  # since the last gap notice
        self.dropped_total = 0
        self.ready = asyncio.Event()
        self.closed = False

    def offer(self, event: TraceEvent) -> bool:
        """Queue ``event``; ``False`` (dropped) when the client has fallen behind."""
        if len(self.events) >= QUEUE_LIMIT:
            self.dropped += 1
            self.dropped_total += 1
            return False
        self.events.append(event)
        self.ready.set()
        return True


class TraceHub:
    """Sits in the TCP server's tracer seat while watched; fans events out to streams."""

    def __init__(self, gateway: Gateway, clock: Callable[[], float] = time.monotonic) -> None:
        self._gateway = gateway
        self._clock = clock
        self.inner: Tracer | None = gateway.tracer  # the --trace logger keeps working
        self.streams: set[TraceStream] = set()
        self._pending: dict[tuple[str, int, int], tuple[float, str | None, int | None]] = {}
        self._latencies: dict[tuple[str, int], deque[float]] = {}
        self._watched_until = 0.0
        self._unwatch: asyncio.TimerHandle | None = None
        metrics = gateway.metrics
        self._m_dropped = metrics.trace_dropped
        self._m_streams = metrics.trace_streams

    # -- who watches ---------------------------------------------------------------------

    @property
    def attached(self) -> bool:
        """True while the hub sees the frames."""
        server = self._gateway.server
        return server is not None and server.tracer is self

    def watch(self) -> None:
        """The status page is open: gather per-slave latencies for ``WATCH_S`` more seconds."""
        self._watched_until = self._clock() + WATCH_S
        self._update()
        if self._unwatch is None:
            loop = asyncio.get_running_loop()
            self._unwatch = loop.call_later(WATCH_S + 0.1, self._expire)

    def _expire(self) -> None:
        self._unwatch = None
        remaining = self._watched_until - self._clock()
        if remaining > 0:
            self._unwatch = asyncio.get_running_loop().call_later(remaining + 0.1, self._expire)
        self._update()

    def add(self, stream: TraceStream) -> None:
        """Start sending events to ``stream``."""
        self.streams.add(stream)
        self._m_streams.set(len(self.streams))
        self._update()

    def remove(self, stream: TraceStream) -> None:
        """Stop sending events to ``stream``."""
        stream.closed = True
        stream.ready.set()
        self.streams.discard(stream)
        self._m_streams.set(len(self.streams))
        self._update()

    def _update(self) -> None:
        wanted = bool(self.streams) or self._clock() < self._watched_until
        for server in self._gateway.servers:  # every listener
            if wanted:
                server.tracer = self
            elif server.tracer is self:
                server.tracer = self.inner
                self._pending.clear()
        for slave in self._gateway.serial_slaves:  # masters on serial lines too
            if wanted:
                slave.tracer = self
            elif slave.tracer is self:
                slave.tracer = self.inner

    def slave_latency(self, line: str, slave: int) -> tuple[float | None, float | None]:
        """p50 and p99 in seconds over the slave's recent answers (``None`` without any)."""
        samples = self._latencies.get((line, slave))
        if not samples:
            return None, None
        ordered = sorted(samples)
        last = len(ordered) - 1
        return ordered[round(0.5 * last)], ordered[round(0.99 * last)]

    # -- the tracer seat -----------------------------------------------------------------

    def request(
        self,
        peer: str,
        transaction_id: int,
        unit: int,
        pdu: bytes,
        listener: str | None = None,
        role: str | None = None,
    ) -> None:
        """A request arrived from ``peer`` (on ``listener``, with ``role`` on TLS)."""
        if self.inner is not None:
            self.inner.request(peer, transaction_id, unit, pdu, listener, role)
        line: str | None = None
        slave: int | None = None
        server = self._gateway.server
        if server is not None and unit:
            target = server.router.lookup(unit)
            if target is not None:
                line, slave = target.bus.name, target.slave
        pending = self._pending
        if len(pending) >= MAX_PENDING:
            del pending[next(iter(pending))]
        pending[(peer, transaction_id, unit)] = (self._clock(), line, slave)
        if self.streams:
            function = pdu[0] if pdu else 0
            self._publish(TraceEvent(time.time(), "request", peer, transaction_id, unit,
                                     function, pdu, line, slave, listener=listener,
                                     role=role))  # fmt: skip

    def reply(
        self, peer: str, transaction_id: int, unit: int, pdu: bytes, outcome: str | None = None
    ) -> None:
        """A reply is going out to ``peer``."""
        if self.inner is not None:
            self.inner.reply(peer, transaction_id, unit, pdu, outcome)
        if outcome is None:
            outcome = _derive_outcome(pdu)
        arrived, line, slave = self._pending.pop((peer, transaction_id, unit), (None, None, None))
        latency = None if arrived is None else self._clock() - arrived
        if latency is not None and line is not None and slave is not None and outcome in _ANSWERED:
            samples = self._latencies.get((line, slave))
            if samples is None:
                samples = self._latencies[(line, slave)] = deque(maxlen=LATENCY_SAMPLES)
            samples.append(latency)
        if self.streams:
            function = pdu[0] & 0x7F if pdu else 0
            self._publish(TraceEvent(time.time(), "reply", peer, transaction_id, unit, function,
                                     pdu, line, slave, outcome,
                                     None if latency is None else latency * 1000.0))  # fmt: skip

    def dropped(self, peer: str, transaction_id: int, unit: int, function: int) -> None:
        """The answer came after its master had left."""
        if self.inner is not None:
            self.inner.dropped(peer, transaction_id, unit, function)
        arrived, line, slave = self._pending.pop((peer, transaction_id, unit), (None, None, None))
        if self.streams:
            latency = None if arrived is None else (self._clock() - arrived) * 1000.0
            self._publish(TraceEvent(time.time(), "dropped", peer, transaction_id, unit,
                                     function, b"", line, slave, "dropped", latency))  # fmt: skip

    def _publish(self, event: TraceEvent) -> None:
        for stream in self.streams:
            if stream.filter.matches(event) and not stream.offer(event):
                self._m_dropped.inc()

    def close(self) -> None:
        """End every stream (the gateway stops)."""
        for stream in list(self.streams):
            self.remove(stream)
        if self._unwatch is not None:
            self._unwatch.cancel()
            self._unwatch = None


def _derive_outcome(pdu: bytes) -> str:
    if not pdu:
        return "broadcast"
    if not fc.is_exception(pdu):
        return "ok"
    return _OUTCOME_BY_CODE.get(pdu[1] if len(pdu) > 1 else 0, "exception")


# --------------------------------------------------------------------------- status


class StatusView:
    """Builds ``GatewayStatus`` from each part's snapshot and the metrics."""

    def __init__(self, gateway: Gateway, hub: TraceHub) -> None:
        self._gateway = gateway
        self._hub = hub
        self._started = time.monotonic()
        # line → (time, wire seconds, CRC errors, utilisation) at the previous snapshot
        self._last: dict[str, tuple[float, float, float, float | None]] = {}

    def snapshot(self) -> GatewayStatus:
        """The gateway's state now."""
        gateway = self._gateway
        metrics = gateway.metrics
        errors = _per_slave_totals(metrics.timeouts, metrics.crc_errors)
        crc_by_line: dict[str, float] = {}
        for (line, _unit), count in _per_slave_totals(metrics.crc_errors).items():
            crc_by_line[line] = crc_by_line.get(line, 0.0) + count
        slaves_by_line: dict[str, set[int]] = {}
        for route in gateway.config.routes.values():
            slaves_by_line.setdefault(route.line, set()).add(route.slave)
        now = time.monotonic()
        lines = []
        for name, bus in sorted(gateway.buses.items()):
            status = bus.status(sorted(slaves_by_line.get(name, ())))
            wire = metrics.wire_duration.labels(name)
            faults = crc_by_line.get(name, 0.0)
            previous = self._last.get(name)
            noisy = previous is not None and faults > previous[2]
            utilisation = previous[3] if previous is not None else None
            if previous is None or now - previous[0] > 0.05:  # too short an interval says little
                if previous is not None:
                    busy = (wire.sum - previous[1]) / (now - previous[0])
                    utilisation = min(1.0, max(0.0, busy))
                self._last[name] = (now, wire.sum, faults, utilisation)
            else:
                self._last[name] = (*previous[:2], faults, utilisation)
            state = status.state
            if noisy and state is LineState.UP:
                state = LineState.NOISY
            histogram = metrics.request_duration.labels(name)
            slaves = tuple(
                replace(
                    slave,
                    p50=slave.p50 if slave.p50 is not None else latency[0],
                    p99=slave.p99 if slave.p99 is not None else latency[1],
                    errors=int(errors.get((name, str(slave.unit)), 0)),
                )
                for slave in status.slaves
                for latency in (self._hub.slave_latency(name, slave.unit),)
            )
            lines.append(
                replace(
                    status,
                    state=state,
                    utilisation=status.utilisation
                    if status.utilisation is not None
                    else utilisation,
                    slaves=slaves,
                    p50=quantile(histogram.upper_bounds, histogram.counts, 0.5),
                    p99=quantile(histogram.upper_bounds, histogram.counts, 0.99),
                )
            )
        server = gateway.server
        masters = tuple(master for listener in gateway.servers for master in listener.masters())
        masters += tuple(m for slave in gateway.serial_slaves for m in slave.masters())
        return GatewayStatus(
            version=__version__,
            uptime=round(now - self._started, 3),
            lines=tuple(lines),
            masters=masters,
            listen="{}:{}".format(*gateway.address) if server is not None else "",
            trace_clients=len(self._hub.streams),
            trace_dropped=int(_sample_total(metrics.trace_dropped)),
        )


def _per_slave_totals(*families: Collector) -> dict[tuple[str, str], float]:
    """Sum of ``*_total`` samples per ``(line, unit)`` over counter families."""
    totals: dict[tuple[str, str], float] = {}
    for family in families:
        for metric in family.collect():
            for sample in metric.samples:
                if sample.name.endswith("_total"):
                    key = (sample.labels["line"], sample.labels["unit"])
                    totals[key] = totals.get(key, 0.0) + sample.value
    return totals


def _sample_total(family: Collector) -> float:
    return sum(
        float(sample.value)
        for metric in family.collect()
        for sample in metric.samples
        if sample.name.endswith("_total")
    )


# --------------------------------------------------------------------------- HTTP routes


def status_page() -> bytes:
    """The self-contained status page (no external script, style or font)."""
    return resources.files("gateway").joinpath("data/status.html").read_bytes()


class LiveView:
    """The hub, the status builder and their HTTP routes, for one gateway."""

    def __init__(self, gateway: Gateway) -> None:
        self.hub = TraceHub(gateway)
        self.status = StatusView(gateway, self.hub)
        self._page = status_page()
        self._tasks: set[asyncio.Task[None]] = set()

    @property
    def routes(self) -> dict[str, Route]:
        """Path → handler, for the HTTP endpoint."""
        return {"/": self._index, "/status": self._status, "/trace": self._trace}

    def close(self) -> None:
        """End every trace stream."""
        self.hub.close()

    async def _index(
        self,
        method: str,
        _target: str,
        _headers: Mapping[str, str],
        _reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        await respond(writer, 200, "text/html; charset=utf-8", self._page, method)

    async def _status(
        self,
        method: str,
        _target: str,
        _headers: Mapping[str, str],
        _reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        self.hub.watch()
        body = json.dumps(to_json(self.status.snapshot()), separators=(",", ":")).encode()
        await respond(writer, 200, "application/json", body, method)

    async def _trace(
        self,
        method: str,
        target: str,
        headers: Mapping[str, str],
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        query = parse_qs(target.partition("?")[2])
        try:
            trace_filter = TraceFilter.from_query(query)
        except ValueError as error:
            await respond(writer, 400, "text/plain", f"{error}\n".encode(), method)
            return
        if len(self.hub.streams) >= MAX_STREAMS:
            busy = f"{MAX_STREAMS} trace streams are open already\n".encode()
            await respond(writer, 503, "text/plain", busy, method)
            return
        sse = "sse" in query.get("format", ()) or "text/event-stream" in headers.get("accept", "")
        content_type = "text/event-stream" if sse else "application/x-ndjson"
        head = (
            f"HTTP/1.1 200 OK\r\nContent-Type: {content_type}\r\nCache-Control: no-store\r\n"
            "Connection: close\r\nX-Accel-Buffering: no\r\n\r\n"
        ).encode()
        if method == "HEAD":
            writer.write(head)
            writer.close()
            return
        _bound_buffers(writer)
        stream = TraceStream(trace_filter)
        self.hub.add(stream)
        watcher = asyncio.ensure_future(_wait_for_close(reader, stream))
        try:
            writer.write(head)
            if sse:
                writer.write(b": modbus-gateway trace\n\n")
            await writer.drain()
            await _pump(stream, writer, sse)
        except (ConnectionError, OSError):
            pass
        finally:
            self.hub.remove(stream)
            watcher.cancel()
            writer.close()


def _bound_buffers(writer: asyncio.StreamWriter) -> None:
    """Keep what a slow client can hold up small: the rest waits in its bounded queue."""
    writer.transport.set_write_buffer_limits(high=STREAM_BUFFER)
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, STREAM_BUFFER)


async def _wait_for_close(reader: asyncio.StreamReader, stream: TraceStream) -> None:
    """End the stream when the client closes its side."""
    with contextlib.suppress(ConnectionError, OSError):
        while await reader.read(512):
            pass
    stream.closed = True
    stream.ready.set()


async def _pump(stream: TraceStream, writer: asyncio.StreamWriter, sse: bool) -> None:
    """Write the stream's events as they come, at the pace the client reads them."""
    while True:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stream.ready.wait(), HEARTBEAT_S)
        stream.ready.clear()
        if stream.closed:
            return
        chunks: list[bytes] = []
        if stream.dropped:
            chunks.append(_encode({"type": "gap", "dropped": stream.dropped}, sse))
            stream.dropped = 0
        events = stream.events
        while events:
            chunks.append(_encode(events.popleft().to_json(), sse))
        if not chunks:  # quiet for HEARTBEAT_S: show the client (and proxies) we are alive
            chunks.append(b": keep-alive\n\n" if sse else b'{"type":"heartbeat"}\n')
        writer.write(b"".join(chunks))
        await writer.drain()  # a slow client holds only its own writer; its queue fills


def _encode(event: Mapping[str, Any], sse: bool) -> bytes:
    data = json.dumps(event, separators=(",", ":"))
    return f"data: {data}\n\n".encode() if sse else f"{data}\n".encode()
