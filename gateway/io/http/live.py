"""Watching a running gateway: the live trace stream, ``GET /status`` and the status page.

Theory of operation: every listener holds the gateway's one ``FrameTrace`` from
the moment it is built; ``TraceHub`` subscribes to it (beside the ``--trace``
logging tracer, if any) only while somebody watches: a trace stream is open, or
the status page asked for ``/status`` in the last ``WATCH_S`` seconds. Nobody
watching costs the frame path one attribute test (the trace is not active).
Each event is matched against each stream's filters (sets compiled once per
stream, at most ``MAX_FILTER_VALUES`` values: a set lookup per event whatever
the filter) and appended to that stream's own bounded queue; a stream whose
client reads too slowly loses events (counted in ``trace_dropped_events_total``
and announced to the client as a gap) rather than slowing the gateway: the frame
path never waits for a socket. Serialising to JSON happens in the streams'
writer tasks, off the frame path, once per event however many streams send it.
A stream whose client reads nothing for ``STALL_S`` (its socket's buffers stay
full) is closed and counted (``trace_streams_closed_total{reason="stalled"}``),
so streams that never read cannot hold every stream slot. ``GET /status`` is
rendered for the requests waiting for it together, at most ``STATUS_LOOP_SHARE``
of the loop's time however many clients poll.

A request event carries its PDU in hex and, looked up in the router at that
moment, the line and slave address it goes to (so a remapped unit shows where
it went). Reply latencies per slave are kept over the last ``LATENCY_SAMPLES``
answers while watched; line latencies come from the request-duration histogram.

What this module reads of the gateway is ``GatewayView`` (gateway/io/status.py),
which the application provides, and the metrics' own counters, read as numbers:
it never imports the application, and never parses an exposition.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import json
import logging
import socket
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from importlib import resources
from typing import Any
from urllib.parse import parse_qs

from ... import __version__
from ...answer_values import answer_values
from ...core import pdu as fc
from ...core.outcome import Outcome
from ...metrics import NO_LINE, GatewayMetrics
from ..frame_trace import FrameTrace, parse_function, reply_outcome
from ..status import GatewayStatus, GatewayView, LineState, LineStatus, quantile, to_json
from .endpoint import GuardedRoute, PacedRenderer, extra_headers, respond
from .guard import RouteAccess

log = logging.getLogger("gateway.live")

#: Events a stream may have waiting before new ones are dropped for it.
QUEUE_LIMIT = 1024
#: Trace streams open at once; more are answered 503 (each holds a queue and a socket).
MAX_STREAMS = 16
#: After a ``/status`` request, per-slave latencies are gathered for this long.
WATCH_S = 30.0
#: Recent answers per slave kept for its p50/p99 (those of the last ``LATENCY_WINDOW_S``).
LATENCY_SAMPLES = 512
#: The latency figures of the status page cover this much of the recent past, not since start.
LATENCY_WINDOW_S = 300.0
#: Requests remembered for their reply's latency and route.
MAX_PENDING = 4096
#: Bytes of a stream buffered in the process and in the kernel's send buffer, each.
STREAM_BUFFER = 64 * 1024
#: A comment line keeps idle event streams (and proxies) from timing out.
HEARTBEAT_S = 15.0
#: A stream whose client has read nothing for this long (its buffers stay full) is closed.
STALL_S = 10.0
#: Values one stream's filters may hold, all parameters together: more is answered 400.
MAX_FILTER_VALUES = 64
#: Events that come within this long of the first are written to a stream together: one
#: wake-up and one write for many, however fast the frames come (a person reads the trace).
BATCH_S = 0.05
#: Share of the event loop's time that rendering /status may take, however often it is asked.
STATUS_LOOP_SHARE = 0.05


class StreamEnd(enum.StrEnum):
    """Why the gateway ended a trace stream (``trace_streams_closed_total``'s reason)."""

    STALLED = "stalled"  #: the client read nothing for STALL_S
    STOPPING = "stopping"  #: the gateway stops


#: Seconds per sample of a line's utilisation chart, and the samples kept (5 minutes).
HISTORY_S = 5.0
HISTORY_SAMPLES = 60

#: Outcomes of a reply that came from the slave, used for its latency.
_ANSWERED = frozenset({Outcome.OK, Outcome.SLAVE_EXCEPTION})

#: A request awaiting its reply: (arrival, line, slave address, its PDU).
_Pending = tuple[float | None, str | None, int | None, bytes | None]
_UNKNOWN: _Pending = (None, None, None, None)


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
    outcome: Outcome | None = None
    latency_ms: float | None = None
    listener: str | None = None  # requests: the listener it came in on
    role: str | None = None  # requests on a tls listener: the client's role ("NULL" for none)
    request: bytes | None = None  # replies: the request's PDU, to number the values returned
    ndjson: bytes | None = None  # as NDJSON, made by the first stream that sends it
    sse_frame: bytes | None = None  # as a server-sent event, the same

    def encoded(self, sse: bool) -> bytes:
        """The event as a stream sends it, serialised once for every stream that does."""
        if self.ndjson is None:
            self.ndjson = json.dumps(self.to_json(), separators=(",", ":")).encode() + b"\n"
        if not sse:
            return self.ndjson
        if self.sse_frame is None:
            self.sse_frame = b"data: " + self.ndjson + b"\n"
        return self.sse_frame

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
        if self.direction == "reply":
            values = answer_values(self.request, self.pdu)
            if values is not None:
                event["values"] = values
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
    outcomes: frozenset[Outcome] = frozenset()
    #: ``host:port`` peers (one connection each) and bare hosts (every port), compiled once.
    peers: frozenset[str] = frozenset()
    hosts: frozenset[str] = frozenset()

    @classmethod
    def from_query(cls, query: Mapping[str, list[str]]) -> TraceFilter:
        """From ``?line=a&unit=1,2&function=3&outcome=target_failed&master=10.0.0.5``.

        Each parameter may repeat or hold a comma-separated list; ``ValueError`` names
        the parameter and the accepted values.
        """

        def values(name: str) -> list[str]:
            return [v.strip() for raw in query.get(name, ()) for v in raw.split(",") if v.strip()]

        given = sum(len(values(name)) for name in ("line", "unit", "function", "outcome", "master"))
        if given > MAX_FILTER_VALUES:
            raise ValueError(
                f"{given} filter values: at most {MAX_FILTER_VALUES} per stream; open the "
                "stream with fewer, or with none and filter on your side"
            )

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
        wanted = set(values("outcome"))
        unknown = wanted - set(Outcome)
        if unknown:
            known = ", ".join(sorted(Outcome))
            raise ValueError(f"outcome={','.join(sorted(unknown))}: expected one of {known}")
        outcomes = {Outcome(value) for value in wanted}
        masters = values("master")
        return cls(
            frozenset(values("line")),
            frozenset(units),
            frozenset(functions),
            frozenset(outcomes),
            frozenset(masters),
            frozenset(m.strip("[]") for m in masters),
        )

    def matches(self, event: TraceEvent) -> bool:
        """True when ``event`` passes every filter (an outcome filter passes replies only)."""
        return (
            (not self.units or event.unit in self.units)
            and (not self.functions or (event.function & 0x7F) in self.functions)
            and (not self.lines or event.line in self.lines)
            and (not self.outcomes or event.outcome in self.outcomes)
            and (not self.hosts or self._master_matches(event.master))
        )

    def _master_matches(self, peer: str) -> bool:
        """``10.0.0.5`` matches every port of that host; ``10.0.0.5:4711`` one connection."""
        return peer in self.peers or peer.rpartition(":")[0].strip("[]") in self.hosts


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
    """Subscribes to the gateway's frame trace while watched; fans events out to streams."""

    def __init__(
        self,
        trace: FrameTrace,
        view: GatewayView,
        metrics: GatewayMetrics,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._trace = trace
        self._view = view
        self._clock = clock
        self.streams: set[TraceStream] = set()
        self._pending: dict[tuple[str, int, int], _Pending] = {}
        self._latencies: dict[tuple[str, int], deque[tuple[float, float]]] = {}
        self._watched_until = 0.0
        self._unwatch: asyncio.TimerHandle | None = None
        self._m_dropped = metrics.trace_dropped.labels()
        self._m_streams = metrics.trace_streams
        self._m_ended = {end: metrics.trace_streams_closed.labels(end) for end in StreamEnd}

    # -- who watches ---------------------------------------------------------------------

    @property
    def attached(self) -> bool:
        """True while the hub sees the frames."""
        return self in self._trace.subscribers

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

    def remove(self, stream: TraceStream, end: StreamEnd | None = None) -> None:
        """Stop sending events to ``stream`` (the gateway ended it for ``end``)."""
        if end is not None and stream in self.streams:
            self._m_ended[end].inc()
        stream.closed = True
        stream.ready.set()
        self.streams.discard(stream)
        self._m_streams.set(len(self.streams))
        self._update()

    def _update(self) -> None:
        wanted = bool(self.streams) or self._clock() < self._watched_until
        if wanted:
            self._trace.subscribe(self)
        elif self.attached:
            self._trace.unsubscribe(self)
            self._pending.clear()

    def slave_latency(self, line: str, slave: int) -> tuple[float | None, float | None]:
        """p50 and p99 in seconds over the slave's answers of the last ``LATENCY_WINDOW_S``
        (at most ``LATENCY_SAMPLES``); ``None`` without any."""
        samples = self._latencies.get((line, slave))
        since = self._clock() - LATENCY_WINDOW_S
        ordered = sorted(latency for at, latency in samples or () if at >= since)
        if not ordered:
            return None, None
        last = len(ordered) - 1
        return ordered[round(0.5 * last)], ordered[round(0.99 * last)]

    # -- the frames, while subscribed ------------------------------------------------------

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
        line: str | None = None
        slave: int | None = None
        if unit:
            target = self._view.route(unit)
            if target is not None:
                line, slave = target
        pending = self._pending
        if len(pending) >= MAX_PENDING:
            del pending[next(iter(pending))]
        pending[(peer, transaction_id, unit)] = (self._clock(), line, slave, pdu)
        if self.streams:
            function = pdu[0] if pdu else 0
            self._publish(
                TraceEvent(
                    time.time(),
                    "request",
                    peer,
                    transaction_id,
                    unit,
                    function,
                    pdu,
                    line,
                    slave,
                    listener=listener,
                    role=role,
                )
            )

    def reply(
        self, peer: str, transaction_id: int, unit: int, pdu: bytes, outcome: Outcome | None = None
    ) -> None:
        """A reply is going out to ``peer``."""
        if outcome is None:
            outcome = reply_outcome(pdu)
        arrived, line, slave, asked = self._pending.pop((peer, transaction_id, unit), _UNKNOWN)
        now = self._clock()
        latency = None if arrived is None else now - arrived
        if latency is not None and line is not None and slave is not None and outcome in _ANSWERED:
            samples = self._latencies.get((line, slave))
            if samples is None:
                samples = self._latencies[(line, slave)] = deque(maxlen=LATENCY_SAMPLES)
            samples.append((now, latency))
        if self.streams:
            function = pdu[0] & 0x7F if pdu else 0
            self._publish(
                TraceEvent(
                    time.time(),
                    "reply",
                    peer,
                    transaction_id,
                    unit,
                    function,
                    pdu,
                    line,
                    slave,
                    outcome,
                    None if latency is None else latency * 1000.0,
                    request=asked,
                )
            )

    def dropped(self, peer: str, transaction_id: int, unit: int, function: int) -> None:
        """The answer came after its master had left."""
        arrived, line, slave, _asked = self._pending.pop((peer, transaction_id, unit), _UNKNOWN)
        if self.streams:
            latency = None if arrived is None else (self._clock() - arrived) * 1000.0
            self._publish(
                TraceEvent(
                    time.time(),
                    "dropped",
                    peer,
                    transaction_id,
                    unit,
                    function,
                    b"",
                    line,
                    slave,
                    Outcome.DROPPED,
                    latency,
                )
            )

    def _publish(self, event: TraceEvent) -> None:
        for stream in self.streams:
            if stream.filter.matches(event) and not stream.offer(event):
                self._m_dropped.inc()

    def close(self) -> None:
        """End every stream (the gateway stops)."""
        for stream in list(self.streams):
            self.remove(stream, StreamEnd.STOPPING)
        if self._unwatch is not None:
            self._unwatch.cancel()
            self._unwatch = None
        self._watched_until = 0.0
        self._update()


# --------------------------------------------------------------------------- status


class StatusView:
    """Builds ``GatewayStatus`` from the gateway's view, the hub and the metrics' counters."""

    def __init__(self, view: GatewayView, metrics: GatewayMetrics, hub: TraceHub) -> None:
        self._view = view
        self._metrics = metrics
        self._hub = hub
        self._started = time.monotonic()
        # line → (time, wire seconds, CRC errors, utilisation) at the previous snapshot
        self._last: dict[str, tuple[float, float, int, float | None]] = {}
        self._history: dict[str, UtilisationHistory] = {}
        self._latency: dict[str, LatencyWindow] = {}

    def snapshot(self) -> GatewayStatus:
        """The gateway's state now."""
        now = time.monotonic()
        view = self._view
        faults = _SlaveFaults(self._metrics)
        units = self._units()
        no_route = self._no_route()
        return GatewayStatus(
            version=__version__,
            uptime=round(now - self._started, 3),
            lines=tuple(
                self._line(status, now, faults, units, no_route) for status in view.line_states()
            ),
            masters=view.masters(),
            listen=view.listen(),
            trace_clients=len(self._hub.streams),
            trace_dropped=self._metrics.trace_events_dropped(),
            time=round(time.time(), 3),
            functions=self._functions(),
            pair=view.pair_status(),
            unrouted=no_route.get(NO_LINE, 0),
        )

    def _no_route(self) -> dict[str, int]:
        """Requests answered 0x0A without a slave, by line: that line was down or full;
        ``NO_LINE``: their unit has no route."""
        counts: dict[str, int] = {}
        for (line, _unit, _function, outcome), count in self._metrics.requests.series():
            if outcome == Outcome.NO_ROUTE.value and count:
                counts[line] = counts.get(line, 0) + count
        return counts

    def _units(self) -> dict[tuple[str, int], list[int]]:
        """(line, slave address) → the unit ids routed to it now."""
        units: dict[tuple[str, int], list[int]] = {}
        route = self._view.route
        for unit in range(1, 256):
            target = route(unit)
            if target is not None:
                units.setdefault(target, []).append(unit)
        return units

    def _functions(self) -> tuple[str, ...]:
        """The function names masters have sent (what the trace's filter can choose)."""
        seen = {labels[2] for labels, count in self._metrics.requests.series() if count}
        return tuple(sorted(seen))

    def _line(
        self,
        status: LineStatus,
        now: float,
        faults: _SlaveFaults,
        units: Mapping[tuple[str, int], list[int]],
        unavailable: Mapping[str, int],
    ) -> LineStatus:
        """One line's own status, with what the metrics and the hub know of it."""
        name = status.name
        slaves = tuple(
            replace(
                slave,
                p50=slave.p50 if slave.p50 is not None else latency[0],
                p99=slave.p99 if slave.p99 is not None else latency[1],
                errors=timeouts + crc,
                timeouts=timeouts,
                crc_errors=crc,
                units=tuple(units.get((name, slave.unit), ())),
            )
            for slave in status.slaves
            for latency in (self._hub.slave_latency(name, slave.unit),)
            for timeouts, crc in (faults.of(name, slave.unit),)
        )
        noisy, utilisation = self._activity(name, now)
        state = LineState.NOISY if noisy and status.state is LineState.UP else status.state
        histogram = self._metrics.request_duration.labels(name)
        history = self._history.get(name)
        if history is None:
            history = self._history[name] = UtilisationHistory()
        window = self._latency.get(name)
        if window is None:
            window = self._latency[name] = LatencyWindow()
        recent, window_s = window.recent(now, histogram.counts)
        return replace(
            status,
            state=state,
            utilisation=status.utilisation if status.utilisation is not None else utilisation,
            slaves=slaves,
            p50=quantile(histogram.upper_bounds, recent, 0.5),
            p99=quantile(histogram.upper_bounds, recent, 0.99),
            latency_window_s=round(window_s, 1),
            history=history.sample(now, self._metrics.wire_duration.labels(name).sum),
            history_s=HISTORY_S,
            unavailable=unavailable.get(name, 0),
        )

    def _activity(self, name: str, now: float) -> tuple[bool, float | None]:
        """Whether CRC errors grew since the last snapshot, and the wire's busy share."""
        wire = self._metrics.wire_duration.labels(name).sum
        faults = self._metrics.crc_errors_on(name)
        previous = self._last.get(name)
        noisy = previous is not None and faults > previous[2]
        utilisation = previous[3] if previous is not None else None
        if previous is None or now - previous[0] > 0.05:  # too short an interval says little
            if previous is not None:
                busy = (wire - previous[1]) / (now - previous[0])
                utilisation = min(1.0, max(0.0, busy))
            self._last[name] = (now, wire, faults, utilisation)
        else:
            self._last[name] = (*previous[:2], faults, utilisation)
        return noisy, utilisation


class _SlaveFaults:
    """Timeouts and CRC errors per (line, slave address), read once per snapshot."""

    def __init__(self, metrics: GatewayMetrics) -> None:
        self._timeouts = _per_slave(metrics.timeouts.series())
        self._crc = _per_slave(metrics.crc_errors.series())

    def of(self, line: str, slave: int) -> tuple[int, int]:
        """``(timeouts, crc_errors)`` of one slave since start."""
        key = (line, slave)
        return self._timeouts.get(key, 0), self._crc.get(key, 0)


def _per_slave(series: Iterable[tuple[tuple[str, ...], int]]) -> dict[tuple[str, int], int]:
    return {(line, int(unit)): count for (line, unit), count in series if unit.isdigit()}


class LatencyWindow:
    """A line's request-duration histogram as it stood at past snapshots, so that its p50
    and p99 cover the last ``LATENCY_WINDOW_S`` instead of the time since start.

    One snapshot per ``HISTORY_S`` is kept, taken when ``/status`` is read. The base is the
    newest snapshot at least the window old, else the oldest: a page that has watched for
    less than the window sees the figures since it began to, and the window it covers is
    returned with them. A snapshot much older than the window (nobody read ``/status`` in
    between) is no base: the figures would cover the unwatched time too.
    """

    def __init__(self) -> None:
        self._snapshots: deque[tuple[float, tuple[int, ...]]] = deque()

    def recent(self, now: float, counts: Iterable[int]) -> tuple[tuple[int, ...], float]:
        """The histogram's counts since the base, and the seconds since the base."""
        current = tuple(counts)
        snapshots = self._snapshots
        if not snapshots or now - snapshots[-1][0] >= HISTORY_S:
            snapshots.append((now, current))
        stale = LATENCY_WINDOW_S + 2 * HISTORY_S
        while len(snapshots) > 1 and (
            now - snapshots[1][0] >= LATENCY_WINDOW_S or now - snapshots[0][0] > stale
        ):
            snapshots.popleft()
        since, base = snapshots[0]
        return tuple(c - b for c, b in zip(current, base, strict=True)), now - since


class UtilisationHistory:
    """A small ring of a line's utilisation, one sample per ``HISTORY_S``, for its chart.

    Sampled when ``/status`` is read: an interval nobody watched is filled with its
    average (the wire's busy time over it is known), so the chart's time axis holds.
    """

    def __init__(self) -> None:
        self.samples: deque[float] = deque(maxlen=HISTORY_SAMPLES)
        self._since: tuple[float, float] | None = None  # (time, wire seconds) of the bucket

    def sample(self, now: float, wire: float) -> tuple[float, ...]:
        """Close every whole ``HISTORY_S`` since the last sample; the samples, oldest first."""
        since = self._since
        if since is None:
            self._since = (now, wire)
        elif now - since[0] >= HISTORY_S:
            buckets = min(HISTORY_SAMPLES, int((now - since[0]) / HISTORY_S))
            busy = min(1.0, max(0.0, (wire - since[1]) / (now - since[0])))
            self.samples.extend([round(busy, 4)] * buckets)
            self._since = (now, wire)
        return tuple(self.samples)


# --------------------------------------------------------------------------- HTTP routes


def status_page() -> bytes:
    """The self-contained status page (no external script, style or font)."""
    return resources.files("gateway").joinpath("data/status.html").read_bytes()


class LiveView:
    """The hub, the status builder and their HTTP routes, for one gateway."""

    def __init__(self, view: GatewayView, metrics: GatewayMetrics, trace: FrameTrace) -> None:
        self.hub = TraceHub(trace, view, metrics)
        self.status = StatusView(view, metrics, self.hub)
        self._page = status_page()
        self._tasks: set[asyncio.Task[None]] = set()
        self.status_renderer = PacedRenderer(STATUS_LOOP_SHARE)

    @property
    def routes(self) -> dict[str, GuardedRoute]:
        """Path → handler and what guards it, for the HTTP endpoint."""
        return {
            "/": (self._index, RouteAccess.STATUS),
            "/status": (self._status, RouteAccess.STATUS),
            "/trace": (self._trace, RouteAccess.TRACE),
        }

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
        body = await self.status_renderer.shared("status", self._render_status)
        await respond(writer, 200, "application/json", body, method)

    async def _render_status(self) -> tuple[bytes, float]:
        """The /status body now, and what it cost the loop."""
        started = time.perf_counter()
        body = json.dumps(to_json(self.status.snapshot()), separators=(",", ":")).encode()
        return body, time.perf_counter() - started

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
            f"Connection: close\r\nX-Accel-Buffering: no\r\n{extra_headers()}\r\n"
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
        except TimeoutError:  # the client read nothing for STALL_S: its slot is freed
            self.hub.remove(stream, StreamEnd.STALLED)
            log.info("trace stream to %s closed: it read nothing for %g s", _peer(writer), STALL_S)
            writer.transport.abort()  # close() would wait for a buffer nobody reads
        except (ConnectionError, OSError):
            pass
        finally:
            self.hub.remove(stream)
            watcher.cancel()
            writer.close()


def _peer(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    return f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "?"


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
        if stream.events and len(stream.events) < QUEUE_LIMIT // 4 and not stream.closed:
            await asyncio.sleep(BATCH_S)  # gather what comes next: one write for many
        stream.ready.clear()
        if stream.closed or writer.transport.is_closing():  # uvloop raises on a closed one
            return
        chunks: list[bytes] = []
        if stream.dropped:
            chunks.append(_encode({"type": "gap", "dropped": stream.dropped}, sse))
            stream.dropped = 0
        events = stream.events
        while events:
            chunks.append(events.popleft().encoded(sse))
        if not chunks:  # quiet for HEARTBEAT_S: show the client (and proxies) we are alive
            chunks.append(b": keep-alive\n\n" if sse else b'{"type":"heartbeat"}\n')
        writer.write(b"".join(chunks))
        # A slow client holds only its own writer; its queue fills. One that reads nothing
        # for STALL_S (the buffer stays above its mark) ends with TimeoutError.
        if writer.transport.get_write_buffer_size() > STREAM_BUFFER:
            await asyncio.wait_for(writer.drain(), STALL_S)
        else:
            await writer.drain()  # returns at once, or raises if the client has gone


def _encode(event: Mapping[str, Any], sse: bool) -> bytes:
    data = json.dumps(event, separators=(",", ":"))
    return f"data: {data}\n\n".encode() if sse else f"{data}\n".encode()
