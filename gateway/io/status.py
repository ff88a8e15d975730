"""Typed snapshots of the gateway's state for the status page and ``GET /status``.

The line, the TCP server and the metrics each hand out one of these small
frozen records instead of having their private fields read: the status page
depends on this vocabulary, not on how a line or a connection keeps its books.
``to_json`` turns a snapshot into the plain dictionaries the page fetches.

``GatewayView`` is all the status page and the live trace read of a running
gateway: the application provides it, so neither needs to know the application.
This vocabulary sits in ``gateway/io/``, below the rooms that hand a record out
(the line driver, the listeners, the pair) and the one that reads them (``http/live``).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

from ..core.outcome import BlockState as BlockState  # the status vocabulary is the core's
from ..core.outcome import SlaveState as SlaveState


class LineState(enum.Enum):
    """How a serial line is doing."""

    UP = "up"  # the port is open and answers come back clean
    DOWN = "down"  # the port is closed (unplugged, wrong device): requests get 0x0A
    NOISY = "noisy"  # open, but no usable gap for noisy_after: requests get 0x0B
    SHARED = "shared"  # open, and another master's frames were heard lately (served, guarded)


@dataclass(frozen=True, slots=True)
class SlaveStatus:
    """One slave address on a line; latency and errors are filled from the metrics."""

    line: str
    unit: int
    state: SlaveState
    p50: float | None = None  # seconds, over the answers of the last 5 minutes; None before any
    p99: float | None = None
    errors: int = 0  # timeouts and CRC errors since start
    units: tuple[int, ...] = ()  # the unit ids masters use for it (``unit`` is its address)
    name: str | None = None  # from the line's ``names``
    heard: bool = False  # it has answered (normally or with an exception) since start
    requests: int = 0  # requests of masters answered for it since start, however
    exceptions: Mapping[int, int] = field(default_factory=dict)  # exception code → count
    timeouts: int = 0
    crc_errors: int = 0
    last_seen: float | None = None  # wall-clock seconds of its last answer
    #: Seconds: the learned response timeout (``timeout = "auto"``), its slowest function's;
    #: None where the timeout is fixed or before the slave's first answer.
    learned_timeout: float | None = None


@dataclass(frozen=True, slots=True)
class PollBlockStatus:
    """One poll block of a line (agent mode): what it reads, its pace and its freshness."""

    block: str  # ``UNIT:FUNCTION:FIRST-LAST``, as the metrics' ``block`` label names it
    line: str
    unit: int  # the unit id of its ``[[poll]]`` entry
    slave: int  # the slave address on the line
    function: int
    first: int  # the first address it reads
    last: int  # and the last
    every: float  # seconds between polls, as set
    max_age: float  # seconds: older data is never answered from memory
    state: BlockState
    period: float | None = None  # the achieved period (a moving mean); None before two polls
    age: float | None = None  # seconds since its data was read; None: never polled
    served: int = 0  # reads answered from its memory since start
    polls: Mapping[str, int] = field(default_factory=dict)  # its polls by outcome


@dataclass(frozen=True, slots=True)
class LineStatus:
    """One serial line and the slaves routed to it."""

    name: str
    kind: str  # "serial" for a device node, "url" for a serial server (socket://, rfc2217://)
    device: str
    state: LineState
    queued: int  # requests waiting for the line now
    utilisation: float | None = None  # share of the last interval the wire was busy, 0..1
    slaves: tuple[SlaveStatus, ...] = ()
    p50: float | None = None  # request latency as masters see it, seconds, recent
    p99: float | None = None
    #: Seconds the p50 and p99 cover: the last 5 minutes, or less while the page has been
    #: watching for less (0: nothing yet).
    latency_window_s: float = 0.0
    settings: str = ""  # the port's settings as an operator reads them: "9600 8E1"
    history: tuple[float | None, ...] = ()  # utilisation per ``history_s``, oldest first
    history_s: float = 0.0
    uart_errors: Mapping[str, int] | None = None  # kernel counters (TIOCGICOUNT), by kind
    not_heard: int = 0  # routed slaves in ``slaves`` that have not answered
    unavailable: int = 0  # requests for it answered 0x0A since start: the line down or full
    blocks: tuple[PollBlockStatus, ...] = ()  # its poll blocks, in configuration order
    #: Seconds of line time one turn of the fair queue charges a master, learned from the
    #: line's typical answered transaction; None before the line's first answer.
    fair_turn_s: float | None = None


@dataclass(frozen=True, slots=True)
class MasterStatus:
    """One connected TCP master."""

    peer: str
    listener: str
    in_flight: int
    requests: int
    role: str | None = None  # on a tls listener, the client certificate's role ("NULL": none)
    denied: int = 0  # requests its listener's policy refused
    unrouted: int = 0  # requests to a unit with no route (answered 0x0A)


@dataclass(frozen=True, slots=True)
class PairStatus:
    """This gateway's place in an active/standby pair (docs/redundancy.md)."""

    role: str  # "active" (it transmits) or "standby" (it listens and forwards)
    lease_remaining: float  # seconds left of the active's lease; 0 while standby
    priority: int
    peer: str  # the peer's HTTP endpoint
    peer_role: str | None  # what the peer's /role said last; None while unreachable


@dataclass(frozen=True, slots=True)
class GatewayStatus:
    """Everything ``GET /status`` reports."""

    version: str
    uptime: float
    lines: tuple[LineStatus, ...]
    masters: tuple[MasterStatus, ...]
    listen: str = ""  # the Modbus TCP address
    trace_clients: int = 0
    trace_dropped: int = 0
    time: float = 0.0  # wall-clock seconds of the snapshot (``last_seen`` is relative to it)
    functions: tuple[str, ...] = ()  # function names masters have sent (trace filters)
    pair: PairStatus | None = None  # None for a gateway without a pair
    unrouted: int = 0  # requests to units with no route since start, every listener (0x0A)


class GatewayView(Protocol):
    """What ``/status`` and the live trace read of the running gateway (the app provides it)."""

    def route(self, unit: int) -> tuple[str, int] | None:
        """The line and slave address ``unit`` goes to now, ``None`` without a route."""

    def line_states(self) -> list[LineStatus]:
        """Each line's own status with its routed slaves, sorted by line name."""

    def masters(self) -> tuple[MasterStatus, ...]:
        """The masters connected now, on every listener."""

    def listen(self) -> str:
        """``host:port`` of the first Modbus listener (empty before it listens)."""

    def pair_status(self) -> PairStatus | None:
        """This gateway's role in its pair, ``None`` without one."""


def _plain(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(item) for item in value]
    return value


def to_json(status: GatewayStatus) -> dict[str, Any]:
    """The snapshot as JSON-ready dictionaries (enums as their string values)."""
    plain: dict[str, Any] = _plain(asdict(status))
    return plain


def quantile(upper_bounds: Sequence[float], counts: Sequence[int], q: float) -> float | None:
    """The ``q`` quantile of a histogram, interpolated within its bucket as Prometheus does.

    ``counts`` are per bucket (not cumulative), one more than ``upper_bounds`` (+Inf last).
    ``None`` when the histogram is empty; the highest finite bound when the quantile
    falls in +Inf.
    """
    total = sum(counts)
    if total == 0:
        return None
    rank = q * total
    seen = 0
    for index, count in enumerate(counts):
        if seen + count >= rank and count:
            if index >= len(upper_bounds):
                return upper_bounds[-1]
            lower = upper_bounds[index - 1] if index else 0.0
            upper = upper_bounds[index]
            # Within the bucket, never past its bound: 0.01 + 0.09 * 25/25 is 0.10000000000000002.
            return min(upper, lower + (upper - lower) * (rank - seen) / count)
        seen += count
    return upper_bounds[-1]
