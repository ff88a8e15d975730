"""Every Prometheus metric of the gateway, on an injected ``CollectorRegistry``.

Naming follows Prometheus practice: one ``modbus_gateway_`` prefix, base units
in names, ``_total`` counters, and bounded label values only: ``line`` and
``unit`` for configured ones, ``function`` from the known set or ``other``,
``outcome`` and ``reason`` from fixed lists. Never a client address or a
transaction id. The hot path calls small methods that cache labelled children,
so a request costs dictionary look-ups, not label resolution.
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info

from . import __version__
from .core.pdu import function_name

#: Outcomes of a request from a TCP master, the ``outcome`` label's whole vocabulary.
OUTCOMES = (
    "ok",  # a normal response from the slave
    "slave_exception",  # the slave answered with a Modbus exception
    "no_route",  # 0x0A: no line for the unit, the line is down, or its queue is full
    "target_failed",  # 0x0B: slave silent or garbled after the retries
    "rejected",  # answered locally: a request no slave could accept
    "broadcast",  # sent to unit 0, no answer expected
    "dropped",  # the master left before its answer was ready
    "cached",  # answered from the read cache
)

_LATENCY_BUCKETS = (
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0,
)  # fmt: skip
_WAIT_BUCKETS = (0.0, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)


class GatewayMetrics:
    """The metric families and cached children the I/O layer updates."""

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        self.registry = registry if registry is not None else CollectorRegistry()
        r = self.registry
        p = "modbus_gateway_"
        self.requests = Counter(
            p + "requests", "Requests from TCP masters by outcome.",
            ["line", "unit", "function", "outcome"], registry=r,
        )  # fmt: skip
        self.request_duration = Histogram(
            p + "request_duration_seconds",
            "Time from a request's arrival to its reply, as the master sees it.",
            ["line"], buckets=_LATENCY_BUCKETS, registry=r,
        )  # fmt: skip
        self.wire_duration = Histogram(
            p + "wire_duration_seconds",
            "Time a transaction occupied the serial line, request written to response complete.",
            ["line"], buckets=_LATENCY_BUCKETS, registry=r,
        )  # fmt: skip
        self.queue_wait = Histogram(
            p + "queue_wait_seconds", "Time requests waited for the serial line.",
            ["line"], buckets=_WAIT_BUCKETS, registry=r,
        )  # fmt: skip
        self.queue_depth = Gauge(
            p + "queue_depth", "Requests waiting for the serial line.", ["line"], registry=r
        )
        self.frames_sent = Counter(
            p + "rtu_frames_sent", "RTU frames written to the line.", ["line"], registry=r
        )
        self.frames_received = Counter(
            p + "rtu_frames_received", "Valid RTU frames received.", ["line"], registry=r
        )
        self.crc_errors = Counter(
            p + "crc_errors", "Responses with a bad CRC.", ["line", "unit"], registry=r
        )
        self.timeouts = Counter(
            p + "timeouts", "Requests the slave did not answer in time.", ["line", "unit"],
            registry=r,
        )  # fmt: skip
        self.retries = Counter(
            p + "retries", "Requests sent again after a timeout or bad CRC.", ["line", "unit"],
            registry=r,
        )  # fmt: skip
        self.discarded_frames = Counter(
            p + "discarded_frames",
            "Frames or bytes discarded: late, from another unit, for another function.",
            ["line", "reason"], registry=r,
        )  # fmt: skip
        self.bytes_written = Counter(
            p + "serial_written_bytes", "Bytes written to the serial line.", ["line"], registry=r
        )
        self.bytes_read = Counter(
            p + "serial_read_bytes", "Bytes read from the serial line.", ["line"], registry=r
        )
        self.line_up = Gauge(
            p + "line_up", "1 when the serial line is open, 0 when it is down.", ["line"],
            registry=r,
        )  # fmt: skip
        self.slave_up = Gauge(
            p + "slave_up", "1 when the slave answers, 0 while it is isolated as dead.",
            ["line", "unit"], registry=r,
        )  # fmt: skip
        self.coalesced = Counter(
            p + "coalesced_requests",
            "Read requests served by another master's identical transaction.",
            ["line"], registry=r,
        )  # fmt: skip
        self.connections_open = Gauge(
            p + "connections_open", "TCP connections open now.", registry=r
        )
        self.connections_accepted = Counter(
            p + "connections_accepted", "TCP connections accepted.", registry=r
        )
        self.connections_rejected = Counter(
            p + "connections_rejected", "TCP connections refused because the limit was reached.",
            registry=r,
        )  # fmt: skip
        self.connections_closed = Counter(
            p + "connections_closed", "TCP connections closed, by reason.", ["reason"], registry=r
        )
        self.protocol_errors = Counter(
            p + "protocol_errors", "Malformed input from TCP masters, by kind.", ["kind"],
            registry=r,
        )  # fmt: skip
        self.info = Info(p + "build", "Version and configured lines.", registry=r)
        self.info.info({"version": __version__, "lines": ""})
        self._request_children: dict[tuple[str, str, int, str], Counter] = {}

    def describe_lines(self, names: list[str]) -> None:
        """Record the configured lines in the build info metric."""
        self.info.info({"version": __version__, "lines": ",".join(names)})

    def count_request(self, line: str, unit: str, function: int, outcome: str) -> None:
        """Count one request's outcome (children cached: this runs per request)."""
        key = (line, unit, function, outcome)
        child = self._request_children.get(key)
        if child is None:
            child = self.requests.labels(line, unit, function_name(function), outcome)
            self._request_children[key] = child
        child.inc()
