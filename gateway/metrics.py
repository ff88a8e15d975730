"""Every Prometheus metric of the gateway, on an injected ``CollectorRegistry``.

Naming follows Prometheus practice: one ``modbus_gateway_`` prefix, base units
in names, ``_total`` counters, and bounded label values only: ``line`` and
``unit`` for configured ones, ``function`` from the known set or ``other``,
``outcome`` and ``reason`` from fixed lists. Never a client address or a
transaction id. The hot path calls small methods that cache labelled children,
so a request costs dictionary look-ups, not label resolution.

``unit`` is always the slave address on the line (what goes on the wire), so
``requests_total`` joins ``timeouts_total`` on ``(line, unit)``; with the usual
one-to-one routes it is also the unit id the master sent. Requests answered
without a line (no route, rejected locally) carry ``line="none", unit="other"``,
broadcasts ``line="broadcast", unit="0"``, the status unit's answers (agent mode)
``line="status"`` and its unit id. docs/metrics.md lists every metric.

A remote client chooses the unit and function of its requests, so
``requests_total`` names a unit only once that slave has answered on its line
(a routed address where a device is present); requests to a slave never heard
from count under ``unit="other"``. With ``--serial`` every address 1..247 is
routed, and a scan of every unit and function code would otherwise add
thousands of series for good. Likewise a row's outcomes are created at 0 together only
once its slave answered that function (``_ROW_OUTCOMES``); before that, and for requests
no line took, each outcome's series comes with its first request: what a master sends
adds a series per function name and outcome it meets, not a row of seven. The
exposition leaves out ``_created`` series (``exposition_registry``): they double the
output and say nothing a restart counter does not.
"""

from __future__ import annotations

import math
import time
from bisect import bisect_left
from collections.abc import Callable, Iterable, Iterator, Mapping
from itertools import accumulate
from typing import Protocol

from prometheus_client import CollectorRegistry, Counter, Gauge, Info
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector

from . import __version__, build
from .core.line import LineStats
from .core.outcome import DiscardReason, Outcome, ReconnectReason, SlaveState
from .core.pdu import function_name
from .core.reasons import CloseReason, MasterFault, RejectReason
from .core.status_unit import STATUS_LINE
from .io.status import PollBlockStatus

#: ``function`` label by function code (``other`` when unknown): an index, not a call.
_FUNCTION_LABELS = tuple(function_name(code) for code in range(256))

#: The outcomes a ``requests_total`` row can take, by where the request was answered: its
#: series are created at 0 together, with the row's first request (see ``count_request``).
LINE_OUTCOMES = (
    Outcome.OK,
    Outcome.SLAVE_EXCEPTION,
    Outcome.NO_ROUTE,
    Outcome.TARGET_FAILED,
    Outcome.BUSY,
    Outcome.DROPPED,
    Outcome.CACHED,
    Outcome.MEMORY,
)
#: Answered by the gateway without a line (``line="none"``).
LOCAL_OUTCOMES = (Outcome.NO_ROUTE, Outcome.REJECTED, Outcome.DENIED)
#: Broadcasts (``line="broadcast"``).
BROADCAST_OUTCOMES = (Outcome.BROADCAST, Outcome.NO_ROUTE)
#: Answered by the status unit (``line="status"``): its registers, or its exceptions.
STATUS_OUTCOMES = (Outcome.OK, Outcome.SLAVE_EXCEPTION)
#: ``line`` label of the requests answered without a line, and of broadcasts.
NO_LINE = "none"
BROADCAST_LINE = "broadcast"

#: Outcomes that show a slave is present: its unit gets its own label in ``requests_total``.
_HEARD_OUTCOMES = frozenset({Outcome.OK, Outcome.SLAVE_EXCEPTION, Outcome.CACHED, Outcome.MEMORY})
#: Outcomes that show a row is in use (the slave answered that function normally, or a
#: broadcast went out): only then is every outcome of its row created at 0. Any other
#: outcome creates its own series alone: a master that sends every function to every
#: unit adds one series per function and outcome it meets, not the row's whole set.
_ROW_OUTCOMES = frozenset({Outcome.OK, Outcome.CACHED, Outcome.MEMORY, Outcome.BROADCAST})
#: The ``unit`` label of requests to a slave never heard from, and of those without a line.
OTHER_UNIT = "other"
#: Unit labels that are always their own: no slave, and broadcast.
_FIXED_UNITS = frozenset({OTHER_UNIT, "0"})
#: Slave states counted by ``slaves_isolated`` (the others are up).
ISOLATED_STATES = (SlaveState.SUSPECT, SlaveState.DOWN)

#: Why bytes from the line were thrown away (``DiscardReason``: a bad CRC is counted in
#: ``crc_errors_total`` instead).
DISCARD_REASONS = tuple(reason.value for reason in DiscardReason)

#: Label values for units, made once: ``str(unit)`` per request would allocate.
UNIT_LABELS = tuple(str(unit) for unit in range(256))

# 1 ms (a short answer at 115200 baud) to 5 s (the longest sensible timeout with retries).
_LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)
# The same, with a 0 bucket: most requests find the line free and do not wait at all.
_WAIT_BUCKETS = (0.0, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)


class _LineStatsCollector(Collector):
    """Exports every line's ``LineStats`` at scrape time: per-line traffic counts kept as plain
    integers by the line core, read only when scraped (a Prometheus child's ``inc`` takes a
    lock and microseconds, an integer add nanoseconds)."""

    def __init__(self, lines: dict[str, LineStats]) -> None:
        self._lines = lines

    def collect(self) -> Iterator[Metric]:
        p = "modbus_gateway_"
        families = (
            (
                CounterMetricFamily,
                p + "rtu_frames_sent",
                "RTU frames written to the line.",
                "frames_sent",
            ),
            (
                CounterMetricFamily,
                p + "rtu_frames_received",
                "RTU frames received that answered a request.",
                "frames_received",
            ),
            (
                CounterMetricFamily,
                p + "serial_written_bytes",
                "Bytes written to the serial line.",
                "bytes_written",
            ),
            (
                CounterMetricFamily,
                p + "serial_read_bytes",
                "Bytes read from the serial line.",
                "bytes_read",
            ),
            (
                GaugeMetricFamily,
                p + "queue_depth",
                "Requests waiting for the serial line.",
                "queue_depth",
            ),
        )
        for family_type, name, documentation, field in families:
            family = family_type(name, documentation, labels=["line"])
            for line, counters in sorted(self._lines.items()):
                family.add_metric([line], getattr(counters, field))
            yield family


#: Reads a line's kernel UART error counters by kind, ``None`` where there are none.
UartReader = Callable[[], "dict[str, int] | None"]


class _UartErrorsCollector(Collector):
    """Exports the kernel's UART error counters (``TIOCGICOUNT``) of each serial line."""

    def __init__(self, readers: dict[str, UartReader]) -> None:
        self._readers = readers

    def collect(self) -> Iterator[Metric]:
        family = CounterMetricFamily(
            "modbus_gateway_uart_errors",
            "Errors the serial port's driver counted (frame, parity, overrun, break); only "
            "lines whose driver keeps them.",
            labels=["line", "kind"],
        )
        for line, read in sorted(self._readers.items()):
            for kind, count in sorted((read() or {}).items()):
                family.add_metric([line, kind], count)
        yield family


#: What a standby's forwarding did, by outcome, read at scrape time (``io.pair``).
ForwardCounts = Callable[[], Mapping[str, int]]


class _ForwardedCollector(Collector):
    """Exports the standby's forwarded requests by outcome (nothing without a pair)."""

    def __init__(self, sources: list[ForwardCounts]) -> None:
        self._sources = sources

    def collect(self) -> Iterator[Metric]:
        family = CounterMetricFamily(
            "modbus_gateway_redundancy_forwarded",
            "Requests this gateway forwarded to its active peer while standing by, by what "
            "became of them (answered by the peer, or answered here 0x0A, 0x0B or 0x06), "
            "and the peer's frames it discarded or dropped as late.",
            labels=["outcome"],
        )
        for read in self._sources[-1:]:  # the pair's forwarder; none without a pair
            for outcome, count in sorted(read().items()):
                family.add_metric([outcome], count)
        yield family


#: A line's learned response timeouts by slave, read at scrape time (``Bus``).
ResponseTimeouts = Callable[[], Mapping[int, float]]


class _ResponseTimeoutCollector(Collector):
    """Exports every line's learned response timeouts at scrape time."""

    def __init__(self, lines: dict[str, ResponseTimeouts]) -> None:
        self._lines = lines

    def collect(self) -> Iterator[Metric]:
        family = GaugeMetricFamily(
            "modbus_gateway_slave_response_timeout_seconds",
            'The learned response timeout (timeout = "auto") of the slave: the turnaround '
            "allowed to its first attempts, the longest of its functions'.",
            labels=["line", "unit"],
        )
        for line, learned in sorted(self._lines.items()):
            for slave, seconds in sorted(learned().items()):
                family.add_metric([line, UNIT_LABELS[slave]], seconds)
        yield family


#: Every running line's poll blocks (agent mode), read at scrape time (``Gateway``).
PollBlocks = Callable[[], Iterable[PollBlockStatus]]
#: The outcomes every block's ``polls_total`` shows from the start (others as they come).
POLL_OUTCOMES = (Outcome.OK, Outcome.SLAVE_EXCEPTION, Outcome.TARGET_FAILED, Outcome.NO_ROUTE)


class _PollBlockCollector(Collector):
    """Exports each poll block's freshness, pace and counts at scrape time (agent mode):
    the blocks of the lines running now, so a block a reload removed goes with it."""

    def __init__(self, sources: list[PollBlocks]) -> None:
        self._sources = sources

    def collect(self) -> Iterator[Metric]:
        p = "modbus_gateway_poll_block_"
        labels = ["line", "block"]
        age = GaugeMetricFamily(
            p + "age_seconds",
            "Age of the block's data: seconds since the poll that read it was sent (+Inf "
            "before its first good poll). Masters are never answered from older than max_age.",
            labels=labels,
        )
        state = GaugeMetricFamily(
            p + "state",
            "The block's state: 0 fresh, 1 stale (older than max_age, or never polled), 2 "
            "failing (its last poll got an exception, a timeout or a garbled answer).",
            labels=labels,
        )
        period = GaugeMetricFamily(
            p + "period_seconds",
            "The block's achieved period between polls, a moving mean (NaN before two "
            "polls); well above its every, the line is too busy for the plan.",
            labels=labels,
        )
        served = CounterMetricFamily(
            p + "served",
            "Masters' reads answered from the block's memory.",
            labels=labels,
        )
        polls = CounterMetricFamily(
            "modbus_gateway_polls",
            "The gateway's own polls of the block, by outcome.",
            labels=[*labels, "outcome"],
        )
        for read in self._sources[-1:]:  # the gateway's; none before it starts
            for block in read():
                key = [block.line, block.block]
                age.add_metric(key, math.inf if block.age is None else block.age)
                state.add_metric(key, block.state.code)
                period.add_metric(key, math.nan if block.period is None else block.period)
                served.add_metric(key, block.served)
                counts = {outcome.value: 0 for outcome in POLL_OUTCOMES}
                counts.update(block.polls)
                for outcome, count in sorted(counts.items()):
                    polls.add_metric([*key, outcome], count)
        yield from (age, state, period, served, polls)


class CertificateExpiry(Protocol):
    """What the expiry metric needs to know of a certificate."""

    @property
    def listener(self) -> str: ...

    @property
    def kind(self) -> str: ...

    @property
    def subject(self) -> str: ...

    def seconds_left(self, now: float | None = None) -> float: ...


class _CertificateExpiryCollector(Collector):
    """``tls_certificate_expiry_seconds``: computed at scrape time from each ``notAfter``.

    Also ``line_tls_certificate_expiry_seconds`` (``owner`` = "line"): a tls line's
    certificates, whose ``listener`` field then holds the line's name.
    """

    def __init__(self, certificates: list[CertificateExpiry], owner: str = "listener") -> None:
        self._certificates = certificates
        self._owner = owner

    def collect(self) -> Iterator[Metric]:
        if self._owner == "line":
            family = GaugeMetricFamily(
                "modbus_gateway_line_tls_certificate_expiry_seconds",
                "Seconds until the certificate's notAfter (negative once expired), per tls "
                "line: kind is client (the gateway's), chain (an intermediate it sends) or ca.",
                labels=["line", "kind", "subject"],
            )
        else:
            family = GaugeMetricFamily(
                "modbus_gateway_tls_certificate_expiry_seconds",
                "Seconds until the certificate's notAfter (negative once expired), per tls "
                "listener: kind is server, chain (an intermediate sent to clients) or ca.",
                labels=["listener", "kind", "subject"],
            )
        now = time.time()
        for certificate in self._certificates:
            family.add_metric(
                [certificate.listener, certificate.kind, certificate.subject],
                certificate.seconds_left(now),
            )
        yield family


class CrlNextUpdate(Protocol):
    """What the CRL metric needs to know of a revocation list."""

    @property
    def listener(self) -> str: ...

    @property
    def issuer(self) -> str: ...

    def seconds_left(self, now: float | None = None) -> float: ...


class _CrlNextUpdateCollector(Collector):
    """``tls_crl_next_update_seconds``: computed at scrape time from each CRL's nextUpdate."""

    def __init__(self, crls: list[CrlNextUpdate]) -> None:
        self._crls = crls

    def collect(self) -> Iterator[Metric]:
        family = GaugeMetricFamily(
            "modbus_gateway_tls_crl_next_update_seconds",
            "Seconds until the nextUpdate of each revocation list (crl) a tls listener checks "
            "(negative once passed: every new TLS master is then refused until a current "
            "list is read at a reload); issuer is the list's issuer.",
            labels=["listener", "issuer"],
        )
        now = time.time()
        for crl in self._crls:
            family.add_metric([crl.listener, crl.issuer], crl.seconds_left(now))
        yield family


class LoopHistogram:
    """One histogram series updated only from the event loop: no lock, a bisect and two adds.

    prometheus-client's ``Histogram.observe`` takes a lock per bucket update; three
    observations per transaction cost more than the rest of the metrics together.
    Scrapes run on the same loop (the HTTP endpoint is asyncio), so no update is torn.
    """

    __slots__ = ("_upper_bounds", "counts", "sum")

    def __init__(self, upper_bounds: tuple[float, ...]) -> None:
        self._upper_bounds = upper_bounds
        self.counts = [0] * (len(upper_bounds) + 1)  # the last one is +Inf
        self.sum = 0.0

    @property
    def upper_bounds(self) -> tuple[float, ...]:
        """The finite bucket bounds (``counts`` has one more entry, for +Inf)."""
        return self._upper_bounds

    def observe(self, value: float) -> None:
        """Record one observation (``le`` is inclusive, as Prometheus defines it)."""
        self.counts[bisect_left(self._upper_bounds, value)] += 1
        self.sum += value


class LoopCount:
    """One counter series updated only from the event loop: an integer add, no lock."""

    __slots__ = ("value",)

    def __init__(self) -> None:
        self.value = 0

    def inc(self, amount: int = 1) -> None:
        """Count ``amount`` more (what prometheus-client's ``Counter`` children offer)."""
        self.value += amount


class LoopCounter(Collector):
    """A counter family of ``LoopCount`` series, exported at scrape time.

    prometheus-client's ``Counter.inc`` takes a lock; ``requests_total`` is counted once
    per request, on the loop, where scrapes run too (so no update is torn).
    """

    def __init__(self, name: str, documentation: str, labelnames: tuple[str, ...]) -> None:
        self.name = name
        self.documentation = documentation
        self._labelnames = labelnames
        self._children: dict[tuple[str, ...], LoopCount] = {}

    def labels(self, *values: str) -> LoopCount:
        """The series of these label values (created at 0 on first use)."""
        child = self._children.get(values)
        if child is None:
            child = self._children[values] = LoopCount()
        return child

    def inc(self, amount: int = 1) -> None:
        """Count on the family's only series (a family without labels)."""
        self.labels().inc(amount)

    def series(self) -> Iterator[tuple[tuple[str, ...], int]]:
        """Each series' label values and count: what status reads, without a scrape."""
        for values, child in list(self._children.items()):
            yield values, child.value

    def collect(self) -> Iterator[Metric]:
        family = CounterMetricFamily(self.name, self.documentation, labels=self._labelnames)
        for values, count in self.series():
            family.add_metric(list(values), count)
        yield family


class LineHistogram(Collector):
    """A histogram family with one ``LoopHistogram`` per line, exported at scrape time."""

    def __init__(self, name: str, documentation: str, upper_bounds: tuple[float, ...]) -> None:
        self.name = name
        self.documentation = documentation
        self._upper_bounds = upper_bounds
        self._children: dict[str, LoopHistogram] = {}

    def labels(self, line: str) -> LoopHistogram:
        """The series of ``line`` (created empty on first use, kept across reloads)."""
        child = self._children.get(line)
        if child is None:
            child = self._children[line] = LoopHistogram(self._upper_bounds)
        return child

    def collect(self) -> Iterator[Metric]:
        family = HistogramMetricFamily(self.name, self.documentation, labels=["line"])
        for line, child in sorted(self._children.items()):
            cumulative = list(accumulate(child.counts))
            buckets = [
                (repr(float(bound)), count)
                for bound, count in zip(self._upper_bounds, cumulative, strict=False)
            ]
            buckets.append(("+Inf", cumulative[-1]))
            family.add_metric([line], buckets, child.sum)
        yield family


class GatewayMetrics:
    """The metric families and cached children the I/O layer updates.

    Every label whose values come from a fixed vocabulary (close and reject reasons,
    faults, slave states, a line's discard reasons and handshake failures) has all its
    series created at 0 as soon as its owner exists, so ``rate()`` and alerts see the
    first event; docs/metrics.md says which series appear only with their first event.
    """

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        self.registry = registry if registry is not None else CollectorRegistry()
        self._request_families()
        self._line_families()
        self._slave_families()
        self._connection_families()
        self._security_families()
        self._exported_state()

    def _request_families(self) -> None:
        r, p = self.registry, "modbus_gateway_"
        self.requests = LoopCounter(
            p + "requests",
            "Requests from TCP masters by outcome.",
            ("line", "unit", "function", "outcome"),
        )
        self.request_duration = LineHistogram(
            p + "request_duration_seconds",
            "Time from a request's arrival to its reply, as the master sees it.",
            _LATENCY_BUCKETS,
        )
        self.wire_duration = LineHistogram(
            p + "wire_duration_seconds",
            "Time a transaction occupied the serial line, request written to response complete.",
            _LATENCY_BUCKETS,
        )
        self.queue_wait = LineHistogram(
            p + "queue_wait_seconds", "Time requests waited for the serial line.", _WAIT_BUCKETS
        )
        for family in (self.requests, self.request_duration, self.wire_duration, self.queue_wait):
            r.register(family)
        self._request_children: dict[tuple[str, str, str, str], LoopCount] = {}
        self._rows: set[tuple[str, str, str]] = set()  #: (line, unit, function) created at 0
        self._heard: set[tuple[str, str]] = set()  #: (line, unit) of slaves that answered

    def _line_families(self) -> None:
        r, p = self.registry, "modbus_gateway_"
        self.discarded_frames = Counter(
            p + "discarded_frames",
            "Answers or bytes thrown away: late, incomplete, from another unit or function.",
            ["line", "reason"],
            registry=r,
        )
        self.line_lost = Counter(
            p + "line_lost",
            "Times the serial port went away (unplugged, I/O error), however briefly.",
            ["line"],
            registry=r,
        )
        self.line_info = Gauge(
            p + "line_info",
            "1 for each line, labelled with its kind (rtu, ascii, ...).",
            ["line", "kind"],
            registry=r,
        )
        self.line_up = Gauge(
            p + "line_up",
            "1 when the serial line is open, 0 when it is down.",
            ["line"],
            registry=r,
        )
        self.line_noisy = Gauge(
            p + "line_noisy",
            "1 while the line has had no usable gap for too long (requests answered 0x0B).",
            ["line"],
            registry=r,
        )
        self.line_noisy_total = Counter(
            p + "line_noisy_episodes",
            "Times the line was declared noisy (no usable gap within noisy_after).",
            ["line"],
            registry=r,
        )
        self.late_windows = Counter(
            p + "late_answer_windows",
            "Late-answer windows opened: an attempt failed and its answer may still arrive.",
            ["line"],
            registry=r,
        )
        self.line_reconnects = Counter(
            p + "line_reconnects",
            "Times a network line's connection was closed and opened again by the line's "
            "decision, by reason (out_of_step: a header no Modbus TCP slave sends; silent: "
            "answers missed in a row with nothing heard on it).",
            ["line", "reason"],
            registry=r,
        )
        self.proof_reads = Counter(
            p + "proof_reads",
            "Reads the gateway sent of its own to prove that a slave's lost answer can no "
            "longer arrive (a request like the lost one waited for that proof).",
            ["line", "unit"],
            registry=r,
        )
        self.coalesced = Counter(
            p + "coalesced_requests",
            "Read requests served by another master's identical transaction.",
            ["line"],
            registry=r,
        )
        self.foreign_master_frames = Counter(
            p + "foreign_master_frames",
            "Request frames heard on the line that this gateway did not send (another master).",
            ["line"],
            registry=r,
        )

    def _slave_families(self) -> None:
        r, p = self.registry, "modbus_gateway_"
        self.crc_errors = LoopCounter(
            p + "crc_errors", "Responses with a bad CRC, per slave.", ("line", "unit")
        )
        self.timeouts = LoopCounter(
            p + "timeouts", "Attempts the slave did not answer in time.", ("line", "unit")
        )
        self.retries = LoopCounter(
            p + "retries", "Requests sent again after a timeout or bad CRC.", ("line", "unit")
        )
        for family in (self.crc_errors, self.timeouts, self.retries):
            r.register(family)
        self.slave_up = Gauge(
            p + "slave_up",
            "1 when the slave answers, 0 while it is isolated as dead.",
            ["line", "unit"],
            registry=r,
        )
        self.slave_suspect = Gauge(
            p + "slave_suspect",
            "1 while the slave is suspect (missed its last answer): its requests wait behind "
            "the healthy slaves', one at a time.",
            ["line", "unit"],
            registry=r,
        )
        self.slaves_isolated = Gauge(
            p + "slaves_isolated",
            "Slaves of the line that are suspect or down now, heard from or not (slave_up and "
            "slave_suspect name only slaves that have answered).",
            ["line", "state"],
            registry=r,
        )

    def _connection_families(self) -> None:
        r, p = self.registry, "modbus_gateway_"
        self.connections_open = Gauge(
            p + "connections_open",
            "TCP connections from masters open now, by listener.",
            ["listener"],
            registry=r,
        )
        self.connections_accepted = Counter(
            p + "connections_accepted", "TCP connections accepted.", registry=r
        )
        self.connections_rejected = Counter(
            p + "connections_rejected",
            "TCP connections refused at accept, by reason.",
            ["reason"],
            registry=r,
        )
        self.connections_closed = Counter(
            p + "connections_closed", "TCP connections closed, by reason.", ["reason"], registry=r
        )
        self.protocol_errors = Counter(
            p + "protocol_errors", "Malformed input from masters, by kind.", ["kind"], registry=r
        )
        self.trace_dropped = LoopCounter(
            p + "trace_dropped_events",
            "Live trace events not sent because the client read too slowly.",
            (),
        )
        r.register(self.trace_dropped)
        self.trace_streams = Gauge(
            p + "trace_streams", "Live trace streams open now (GET /trace).", registry=r
        )
        self.trace_streams_closed = Counter(
            p + "trace_streams_closed",
            "Live trace streams the gateway ended, by reason: stalled (the client read "
            "nothing for several seconds) or stopping (the gateway stops).",
            ["reason"],
            registry=r,
        )
        self.http_refusals = Counter(
            p + "http_refusals",
            "HTTP connections closed at accept and requests refused, by reason: "
            "max_connections, max_per_source, host (421), no_token (401), wrong_token (403).",
            ["reason"],
            registry=r,
        )
        for close in CloseReason:
            self.connections_closed.labels(close)
        for reject in RejectReason:
            self.connections_rejected.labels(reject)
        for fault in MasterFault:
            self.protocol_errors.labels(fault)
        self.trace_dropped.labels()

    def _security_families(self) -> None:
        r, p = self.registry, "modbus_gateway_"
        self.denied_requests = Counter(
            p + "denied_requests",
            "Requests refused by a listener's policy (answered 0x01), by listener, role and "
            "function; role is one the rules name, none (NULL role or plain TCP) or other.",
            ["listener", "role", "function"],
            registry=r,
        )
        self.redundancy_role = Gauge(
            p + "redundancy_role",
            "1 while this gateway is the active one of its pair (it transmits), 0 while it "
            "stands by; 1 for a gateway without a pair.",
            registry=r,
        )
        self.redundancy_role.set(1)
        self.redundancy_takeovers = Counter(
            p + "redundancy_takeovers",
            "Times this gateway became the active one of its pair.",
            registry=r,
        )
        self.redundancy_refused_frames = Counter(
            p + "redundancy_refused_frames",
            "Frames not written because this gateway held no valid lease at that instant.",
            registry=r,
        )
        self.audit_records_dropped = Counter(
            p + "audit_records_dropped",
            "Audit records lost: the audit queue was full (a slow file) or a write failed.",
            registry=r,
        )
        self.connections_denied = Counter(
            p + "connections_denied",
            "Connections closed at accept: the source is outside the listener's allow list.",
            ["listener"],
            registry=r,
        )
        self.tls_handshake_failures = Counter(
            p + "tls_handshake_failures",
            "Failed TLS handshakes on tls listeners, by reason.",
            ["listener", "reason"],
            registry=r,
        )
        self.line_tls_failures = Counter(
            p + "line_tls_failures",
            "Failed TLS set-ups with the slave of a tls line (handshake, or the slave's refusal "
            "of the gateway's certificate), by reason.",
            ["line", "reason"],
            registry=r,
        )
        self._denial_children: dict[tuple[str, str, int], Counter] = {}

    def _exported_state(self) -> None:
        """The collectors that read state kept elsewhere (certificates, line counters)."""
        r = self.registry
        self._certificates: list[CertificateExpiry] = []
        r.register(_CertificateExpiryCollector(self._certificates))
        self._line_certificates: list[CertificateExpiry] = []
        r.register(_CertificateExpiryCollector(self._line_certificates, owner="line"))
        self._crls: list[CrlNextUpdate] = []
        r.register(_CrlNextUpdateCollector(self._crls))
        self.info = Info(
            "modbus_gateway_build",
            "Version, build (compiled or interpreted) and lines.",
            registry=r,
        )
        self.describe_lines([])
        self._line_counters: dict[str, LineStats] = {}
        self._line_kinds: dict[str, str] = {}  # line -> its kind in line_info
        r.register(_LineStatsCollector(self._line_counters))
        self._uart_readers: dict[str, UartReader] = {}
        r.register(_UartErrorsCollector(self._uart_readers))
        self._response_timeouts: dict[str, ResponseTimeouts] = {}
        r.register(_ResponseTimeoutCollector(self._response_timeouts))
        self._forward_counts: list[ForwardCounts] = []
        r.register(_ForwardedCollector(self._forward_counts))
        self._poll_blocks: list[PollBlocks] = []
        r.register(_PollBlockCollector(self._poll_blocks))

    def watch_poll_blocks(self, read: PollBlocks) -> None:
        """Export the ``poll_block_*`` and ``polls_total`` series from ``read``."""
        self._poll_blocks[:] = [read]

    def watch_forwarding(self, read: ForwardCounts) -> None:
        """Export ``redundancy_forwarded_total`` from ``read`` (a paired gateway's)."""
        self._forward_counts.append(read)

    def watch_uart(self, line: str, read: UartReader) -> None:
        """Export ``uart_errors_total`` of ``line`` from ``read`` (the line's latest port)."""
        self._uart_readers[line] = read

    def describe_lines(self, names: list[str]) -> None:
        """Record the configured lines in the build info metric."""
        self.info.info({"version": __version__, "build": build(), "lines": ",".join(names)})

    def set_line_kind(self, line: str, kind: str) -> None:
        """Label ``line`` with its kind in ``line_info`` (one series per line)."""
        old = self._line_kinds.get(line)
        if old is not None and old != kind:
            self.line_info.remove(line, old)
        self._line_kinds[line] = kind
        self.line_info.labels(line, kind).set(1)

    def prepare_line(self, line: str) -> None:
        """Create a line's series at 0, so that ``rate()`` and alerts see the first fault."""
        for reason in DISCARD_REASONS:
            self.discarded_frames.labels(line, reason)
        self.line_lost.labels(line)
        self.line_noisy_total.labels(line)
        for state in ISOLATED_STATES:
            self.slaves_isolated.labels(line, state).set(0)
        self.late_windows.labels(line)
        self.foreign_master_frames.labels(line)
        for reason in ReconnectReason:
            self.line_reconnects.labels(line, reason)

    def prepare_units(self, targets: Iterable[tuple[str, int]]) -> None:
        """Create the per-slave fault series at 0 for each routed ``(line, slave)``."""
        for line, slave in targets:
            unit = UNIT_LABELS[slave]
            self.crc_errors.labels(line, unit)
            self.timeouts.labels(line, unit)
            self.retries.labels(line, unit)
            self.proof_reads.labels(line, unit)

    def line_counters(self, line: str) -> LineStats:
        """The traffic counters of ``line``; the same object across reloads (counters only grow)."""
        counters = self._line_counters.get(line)
        if counters is None:
            counters = self._line_counters[line] = LineStats()
        return counters

    def set_response_timeouts(self, line: str, learned: ResponseTimeouts) -> None:
        """Where ``line``'s learned response timeouts are read (a reopened line's core)."""
        self._response_timeouts[line] = learned

    def request_duration_for(self, line: str) -> LoopHistogram:
        """The latency histogram of ``line``."""
        return self.request_duration.labels(line)

    def prepare_listener(self, listener: str) -> None:
        """Create a listener's door counters at 0."""
        self.connections_denied.labels(listener)

    def prepare_tls_listener(self, listener: str, reasons: Iterable[str]) -> None:
        """Create a TLS listener's handshake failure series at 0."""
        for reason in reasons:
            self.tls_handshake_failures.labels(listener, reason)

    def prepare_line_tls(self, line: str, reasons: Iterable[str]) -> None:
        """Create a tls line's failure series at 0."""
        for reason in reasons:
            self.line_tls_failures.labels(line, reason)

    def set_certificates(self, certificates: Iterable[CertificateExpiry]) -> None:
        """The certificates whose ``notAfter`` is exported (replaced on every reload)."""
        self._certificates[:] = list(certificates)

    def set_crls(self, crls: Iterable[CrlNextUpdate]) -> None:
        """The tls listeners' revocation lists whose nextUpdate is exported (replaced on
        every reload)."""
        self._crls[:] = list(crls)

    def set_line_certificates(self, certificates: Iterable[CertificateExpiry]) -> None:
        """The tls lines' certificates whose ``notAfter`` is exported (replaced on reload)."""
        self._line_certificates[:] = list(certificates)

    def count_denial(self, listener: str, role: str, function: int) -> None:
        """Count one request refused by policy (``role`` already bounded by the policy)."""
        key = (listener, role, function)
        child = self._denial_children.get(key)
        if child is None:
            child = self.denied_requests.labels(listener, role, function_name(function))
            self._denial_children[key] = child
        child.inc()

    def count_request(self, line: str, unit: str, function: int, outcome: Outcome) -> None:
        """Count one request's outcome (children cached: this runs per request).

        ``function`` is the request's code. ``unit`` is counted as ``other`` until that
        slave has answered (module docstring).
        """
        key = (line, unit, _FUNCTION_LABELS[function & 0xFF], outcome)
        child = self._request_children.get(key)
        if child is None:
            child = self._request_child(key)
        child.value += 1

    def heard(self, line: str, unit: str) -> bool:
        """True once the slave ``unit`` on ``line`` has answered a request (its labels exist)."""
        return (line, unit) in self._heard

    def _request_child(self, key: tuple[str, str, str, str]) -> LoopCount:
        line, unit, function, outcome = key
        if unit not in _FIXED_UNITS and (line, unit) not in self._heard:
            if outcome not in _HEARD_OUTCOMES:
                # Not cached: the slave may be heard from later, and then has its own label.
                return self.requests.labels(line, OTHER_UNIT, function, outcome)
            self._heard.add((line, unit))
        if outcome in _ROW_OUTCOMES:  # the row is in use: every outcome it can take at 0
            self._prepare_row(line, unit, function)
        child = self.requests.labels(line, unit, function, outcome)
        self._request_children[key] = child
        return child

    def _prepare_row(self, line: str, unit: str, function: str) -> None:
        """Create at 0 every outcome a ``(line, unit, function)`` row can take, once."""
        row = (line, unit, function)
        if row in self._rows:
            return
        self._rows.add(row)
        if line == NO_LINE:
            outcomes: tuple[Outcome, ...] = LOCAL_OUTCOMES
        elif line == BROADCAST_LINE:
            outcomes = BROADCAST_OUTCOMES
        elif line == STATUS_LINE:
            outcomes = STATUS_OUTCOMES
        else:
            outcomes = LINE_OUTCOMES
        for outcome in outcomes:
            self.requests.labels(line, unit, function, outcome)

    def slave_errors(self, line: str) -> dict[int, int]:
        """Timeouts and CRC errors per slave address of ``line`` since start (for /status)."""
        errors: dict[int, int] = {}
        for family in (self.timeouts, self.crc_errors):
            for (series_line, unit), count in family.series():
                if series_line == line and unit.isdigit():
                    errors[int(unit)] = errors.get(int(unit), 0) + count
        return errors

    def crc_errors_on(self, line: str) -> int:
        """CRC errors on ``line`` since start, every slave together."""
        return sum(count for (name, _unit), count in self.crc_errors.series() if name == line)

    def trace_events_dropped(self) -> int:
        """Live trace events dropped since start (slow readers)."""
        return sum(count for _labels, count in self.trace_dropped.series())

    def exposition_registry(self) -> Collector:
        """What the HTTP endpoint exposes: every metric, without ``_created`` series."""
        return WithoutCreated(self.registry)


class WithoutCreated(Collector):
    """A view of a registry that drops the ``_created`` samples of counters and histograms."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self._registry = registry

    def collect(self) -> Iterator[Metric]:
        for metric in self._registry.collect():
            if any(sample.name.endswith("_created") for sample in metric.samples):
                metric.samples = [s for s in metric.samples if not s.name.endswith("_created")]
            yield metric
