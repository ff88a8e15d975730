"""Configuration: a TOML file and command-line overrides, as frozen, validated dataclasses.

Theory of operation: ``read_config_file`` parses the file, the CLI merges
its flags into the raw tables, and ``build_config`` validates
everything at once, so that one ``ConfigError`` lists every fault with its
file, key and fix instead of stopping at the first. Nothing here opens a port.
"""

from __future__ import annotations

import difflib
import ipaddress
import math
import os
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .core import pdu as fc
from .core.framing import is_mbap
from .core.line import MAX_IN_FLIGHT
from .core.policy import Access, IPNetwork, Rule, lint, merge_ranges
from .core.timing import character_time, t35, transmission_time

DEFAULT_LISTEN = "0.0.0.0:502"
DEFAULT_METRICS = "127.0.0.1:9502"
VALID_PARITIES = ("N", "E", "O")
#: Downstream line kinds (``kind`` under ``[lines.NAME]``); the first is the default.
#: ``rtu-over-tcp``: RTU frames over a TCP connection to a serial device server (raw socket).
#: ``tcp``: a Modbus TCP slave (MBAP under the gateway's own transaction ids).
#: ``tls``: a Modbus/TCP Security slave (the same MBAP framing, over TLS 1.2 or newer).
VALID_LINE_KINDS = ("rtu", "ascii", "rtu-over-tcp", "tcp", "tls")
VALID_WHEN_FULL = ("close_oldest_idle", "refuse")
VALID_LOG_FORMATS = ("text", "json")
VALID_LOG_LEVELS = ("debug", "info", "warning", "error")
VALID_PROTOCOLS = ("tcp", "tls", "rtu-over-tcp", "serial-slave")
#: What the masters on a ``serial-slave`` listener's line speak (its ``framing``); the first
#: is the default. Named like ``--framing``: on a listener, ``kind`` would read as ``protocol``.
VALID_SLAVE_FRAMINGS = ("rtu", "ascii")
#: Line kinds reached over the network rather than through a device node.
NETWORK_LINE_KINDS = frozenset({"rtu-over-tcp", "tcp", "tls"})
#: Silence that ends a frame of unknown length on a network link (segments, device servers).
NETWORK_SILENCE_S = 0.05
#: Added to the automatic response timeout of a network line: the round trip and the device
#: server's own buffering.
NETWORK_ALLOWANCE_S = 0.1
#: The IANA port of Modbus/TCP Security.
DEFAULT_TLS_PORT = 802
URL_SCHEMES = ("socket://", "rfc2217://", "loop://", "spy://")


class ConfigError(Exception):
    """Every problem found in one configuration, each naming file, key and fix."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = problems
        lines = "\n".join(f"  - {problem}" for problem in problems)
        super().__init__(f"{source}: {len(problems)} configuration problem(s):\n{lines}")


@dataclass(frozen=True)
class ServerConfig:
    """The Modbus TCP side."""

    host: str = "0.0.0.0"
    port: int = 502
    max_connections: int = 100
    when_full: str = "close_oldest_idle"
    idle_timeout: float = 300.0
    max_pipeline: int = 16
    backlog: int = 1024
    broadcast_reply: bool = False
    refuse_functions: frozenset[int] = frozenset()
    #: Source networks every listener accepts (empty: any); a listener's own list applies too.
    allow: tuple[IPNetwork, ...] = ()
    #: Every listener refuses anything but reads.
    read_only: bool = False
    #: The policy of the ``listen`` shorthand listener.
    policy: str | None = None
    max_connections_per_source: int = 16
    evict_min_idle: float = 10.0
    send_timeout: float = 10.0
    #: Seconds a TLS master has to complete its handshake before it is disconnected.
    tls_handshake_timeout: float = 10.0


@dataclass(frozen=True)
class ListenerConfig:
    """One listening address: ``tcp`` (Modbus TCP), ``tls`` (Modbus/TCP Security) or
    ``rtu-over-tcp`` (RTU frames over TCP)."""

    name: str
    protocol: str = "tcp"
    host: str = "0.0.0.0"
    port: int = 502
    cert: str | None = None  #: the server's certificate chain (PEM), tls only
    key: str | None = None  #: its private key (PEM), tls only
    ca: str | None = None  #: the CAs client certificates must chain to (PEM), tls only
    allow: tuple[IPNetwork, ...] = ()  #: source networks accepted (empty: any)
    read_only: bool = False
    policy: str | None = None  #: a name in ``GatewayConfig.policies``; None: no rules
    key_prefix: str = "server."  #: where it was configured, for messages
    #: ``serial-slave``: the serial line the gateway answers on as a slave (its device and
    #: format), and the units it answers for (empty: every routed unit).
    serial: LineConfig | None = None
    units: tuple[int, ...] = ()

    @property
    def tls(self) -> bool:
        """True for a Modbus/TCP Security listener."""
        return self.protocol == "tls"


@dataclass(frozen=True)
class MetricsConfig:
    """The HTTP endpoint for /metrics, /healthz and /readyz."""

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 9502
    max_connections: int = 32
    header_timeout: float = 5.0


@dataclass(frozen=True)
class LoggingConfig:
    """Log level and format."""

    level: str = "info"
    format: str = "text"


@dataclass(frozen=True)
class CacheRule:
    """Reads of ``unit`` in a range, answered from a response at most ``max_age`` seconds old."""

    unit: int
    function: int
    start: int
    count: int
    max_age: float

    def covers(self, unit: int, function: int, address: int, quantity: int) -> bool:
        """True when the read lies wholly inside this rule's range."""
        return (
            unit == self.unit
            and function == self.function
            and self.start <= address
            and address + quantity <= self.start + self.count
        )


@dataclass(frozen=True)
class LineConfig:
    """One serial line (RS485 bus) and how to talk on it."""

    name: str
    device: str
    baudrate: int = 9600
    data_bits: int = 8
    parity: str = "N"
    stop_bits: float = 1
    timeout: float = 0.367  # auto_timeout(9600): "auto" is computed from the line's settings
    retries: int = 1
    retry_unsafe: bool = False
    frame_gap: float | None = None
    broadcast: bool = True
    broadcast_turnaround: float = 0.1
    max_queue: int = 256
    max_queue_per_master: int = 32
    late_answer_window: float | None = None
    noisy_after: float | None = None
    probe_share: float = 0.05
    rs485: bool = False
    rs485_rts_level_for_tx: bool = True
    rs485_rts_level_for_rx: bool = False
    rs485_delay_before_tx: float = 0.0
    rs485_delay_after_tx: float = 0.0
    units: tuple[int, ...] = ()
    dead_after: int = 3
    probe_interval: float = 1.0
    probe_max_interval: float = 30.0
    slave_timeouts: Mapping[int, float] = field(default_factory=dict)
    coalesce: bool = True
    cache: tuple[CacheRule, ...] = ()
    #: ``rtu``, ``ascii`` (serial devices) or ``rtu-over-tcp`` (``device`` is then ``HOST:PORT``).
    kind: str = "rtu"
    inter_char_timeout: float = 1.0  # ASCII: a frame whose characters stop this long is dropped
    echo: bool = False  # the adapter echoes what the gateway sends: drop it
    #: The device server's or slave's address (network kinds; from ``address = "HOST:PORT"``;
    #: a ``tls`` line's address without a port means 802, Modbus/TCP Security's port).
    host: str = ""
    port: int = 0
    #: Seconds to wait after a connection is made before the first request (some device
    #: servers drop what arrives while they set up their serial side).
    connect_delay: float = 0.0
    #: Seconds a connection attempt to the device server may take.
    connect_timeout: float = 3.0
    #: ``silence`` when set: the quiet time that ends an answer of unpredictable length.
    silence_setting: float | None = None
    #: ``kind = "tls"``: the gateway's client certificate chain, its key, and the CAs the
    #: slave's certificate must chain to (PEM files).
    cert: str | None = None
    key: str | None = None
    ca: str | None = None
    #: ``kind = "tls"``: the name the slave's certificate must carry (the address's host
    #: unless set); ``check_server_name = false`` skips only that check, never the chain's.
    server_name: str = ""
    check_server_name: bool = True
    #: ``kind = "tls"``: seconds the TLS handshake with the slave may take.
    tls_handshake_timeout: float = 10.0
    #: Requests outstanding at once on the connection of an MBAP line (``tcp``, ``tls``);
    #: 1 elsewhere.
    max_in_flight: int = 1

    def timeout_for(self, slave: int) -> float:
        """The response timeout of ``slave``: its override, else the line's."""
        return self.slave_timeouts.get(slave, self.timeout)

    def late_window_for(self, slave: int) -> float:
        """How long a lost answer of ``slave`` may still arrive: 2 x its timeout by default."""
        if self.late_answer_window is not None:
            return self.late_answer_window
        return 2 * self.timeout_for(slave)

    @property
    def noisy_deadline(self) -> float:
        """How long requests wait for a usable gap before the line is declared noisy."""
        if self.noisy_after is not None:
            return self.noisy_after
        return 3 * max(self.timeout, *self.slave_timeouts.values(), 0.0)

    @property
    def is_url(self) -> bool:
        """True for a pyserial URL (a serial server over the network) rather than a device node."""
        return "://" in self.device or self.networked

    @property
    def networked(self) -> bool:
        """True for a line reached over a TCP connection (``kind = "rtu-over-tcp"``)."""
        return self.kind in NETWORK_LINE_KINDS

    @property
    def gap(self) -> float:
        """Silence kept before every request: ``frame_gap`` when set, else t3.5 (0 over TCP).

        ASCII frames end at their CR LF, not on silence: one character time is
        kept, a turnaround for the slave's transceiver.
        """
        if self.frame_gap is not None:
            return self.frame_gap
        if self.networked:  # the device server keeps t3.5 on its serial side itself
            return 0.0
        if self.kind == "ascii":
            return character_time(self.baudrate, self.data_bits, self.parity, self.stop_bits)
        return t35(self.baudrate, self.data_bits, self.parity, self.stop_bits)

    @property
    def silence(self) -> float:
        """Line silence that ends a frame whose length cannot be predicted.

        For ASCII, the inter-character timeout that abandons a frame.
        """
        if self.silence_setting is not None:
            return self.silence_setting
        if self.kind == "ascii":
            return self.inter_char_timeout
        floor = NETWORK_SILENCE_S if self.is_url else 0.0
        return max(t35(self.baudrate, self.data_bits, self.parity, self.stop_bits), floor)


@dataclass(frozen=True)
class Route:
    """Where one TCP unit id goes: a line and the slave address on it."""

    unit: int
    line: str
    slave: int


@dataclass(frozen=True)
class GatewayConfig:
    """The whole validated configuration."""

    server: ServerConfig = field(default_factory=ServerConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    lines: tuple[LineConfig, ...] = ()
    routes: Mapping[int, Route] = field(default_factory=dict)
    source: str = "<defaults>"
    #: Every listener; the ``[server] listen`` shorthand is the first when present.
    listeners: tuple[ListenerConfig, ...] = ()
    #: Named rule lists (``[[policies.NAME.rules]]``), in the order written.
    policies: Mapping[str, tuple[Rule, ...]] = field(default_factory=dict)

    def line(self, name: str) -> LineConfig:
        """The line called ``name``."""
        for line in self.lines:
            if line.name == name:
                return line
        raise KeyError(name)


def parse_host_port(text: str) -> tuple[str, int]:
    """Split ``HOST:PORT`` (``[v6]:PORT`` too); raise ValueError with the fix."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not port_text.isdigit():
        raise ValueError(f"{text!r} is not HOST:PORT; write it like 0.0.0.0:502")
    port = int(port_text)
    if not 0 <= port <= 65535:
        raise ValueError(f"port {port} outside 0..65535")
    host = host.strip("[]") or "0.0.0.0"
    return host, port


def _has_port(address: str) -> bool:
    """True when ``address`` ends in ``:PORT`` (``[v6]`` alone, or a bare host, has none)."""
    _, sep, tail = address.rpartition(":")
    return bool(sep) and tail.isdigit() and not address.endswith("]")


def parse_units(value: Any) -> list[int]:
    """Units as a list of ints and ``"A-B"`` ranges; raise ValueError with the fix."""
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list):
        raise ValueError('write units as a list, like [1, 2, "10-20"]')
    units: list[int] = []
    for item in value:
        if isinstance(item, bool):
            raise ValueError(f"{item!r} is not a unit id")
        if isinstance(item, int):
            units.append(item)
        elif isinstance(item, str) and "-" in item:
            low_text, _, high_text = item.partition("-")
            if not (low_text.strip().isdigit() and high_text.strip().isdigit()):
                raise ValueError(f'{item!r} is not a range like "10-20"')
            low, high = int(low_text), int(high_text)
            if low > high:
                raise ValueError(f"range {item!r} runs backwards")
            units.extend(range(low, high + 1))
        elif isinstance(item, str) and item.strip().isdigit():
            units.append(int(item))
        else:
            raise ValueError(f'{item!r} is not a unit id or a range like "10-20"')
    for unit in units:
        if not 1 <= unit <= 247:
            raise ValueError(f"unit {unit} outside 1..247 (0 is broadcast, 248..255 are reserved)")
    return units


class _Checker:
    """Reads typed values out of raw TOML tables, collecting problems instead of raising."""

    def __init__(self) -> None:
        self.problems: list[str] = []

    def fail(self, key: str, message: str) -> None:
        self.problems.append(f"{key}: {message}")

    def unknown_keys(self, table: Mapping[str, Any], known: set[str], prefix: str) -> None:
        for key in table:
            if key not in known:
                close = difflib.get_close_matches(str(key), sorted(known), n=1, cutoff=0.6)
                if close:
                    self.fail(f"{prefix}{key}", f"unknown key; did you mean {close[0]!r}?")
                    continue
                choices = ", ".join(sorted(known))
                self.fail(f"{prefix}{key}", f"unknown key; known keys here are: {choices}")

    def integer(
        self, table: Mapping[str, Any], key: str, prefix: str, default: int, low: int, high: int
    ) -> int:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(
                f"{prefix}{key}",
                f"{value!r} is not an integer; write a whole number from {low} to {high}",
            )
            return default
        if not low <= value <= high:
            self.fail(f"{prefix}{key}", f"{value} outside {low}..{high}")
            return default
        return value

    def number(
        self,
        table: Mapping[str, Any],
        key: str,
        prefix: str,
        default: float,
        low: float,
        high: float,
    ) -> float:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
            self.fail(
                f"{prefix}{key}", f"{value!r} is not a number of seconds; write e.g. {default}"
            )
            return default
        if not low <= value <= high:
            self.fail(f"{prefix}{key}", f"{value} outside {low}..{high}")
            return default
        return float(value)

    def boolean(self, table: Mapping[str, Any], key: str, prefix: str, default: bool) -> bool:
        value = table.get(key, default)
        if not isinstance(value, bool):
            self.fail(f"{prefix}{key}", f"{value!r} is not true or false")
            return default
        return value

    def choice(
        self,
        table: Mapping[str, Any],
        key: str,
        prefix: str,
        default: str,
        choices: tuple[str, ...],
        *,
        upper: bool = False,
    ) -> str:
        value = table.get(key, default)
        if not isinstance(value, str) or (value.upper() if upper else value.lower()) not in choices:
            self.fail(f"{prefix}{key}", f"{value!r} is not one of: {', '.join(choices)}")
            return default
        return value.upper() if upper else value.lower()

    def address(
        self, table: Mapping[str, Any], key: str, prefix: str, default: str
    ) -> tuple[str, int] | None:
        value = table.get(key, default)
        if not isinstance(value, str):
            self.fail(f"{prefix}{key}", f'{value!r} is not a string like "0.0.0.0:502"')
            return parse_host_port(default)
        if value.lower() == "off":
            return None
        try:
            return parse_host_port(value)
        except ValueError as error:
            self.fail(f"{prefix}{key}", str(error))
            return parse_host_port(default)

    def table(self, raw: Mapping[str, Any], key: str) -> Mapping[str, Any]:
        value = raw.get(key, {})
        if not isinstance(value, dict):
            self.fail(key, f"must be a table ([{key}]), not {type(value).__name__}")
            return {}
        return value


_SERVER_KEYS = {
    "listen",
    "max_connections",
    "when_full",
    "idle_timeout",
    "max_pipeline",
    "backlog",
    "broadcast_reply",
    "refuse_functions",
    "allow",
    "read_only",
    "policy",
    "max_connections_per_source",
    "evict_min_idle",
    "send_timeout",
    "tls_handshake_timeout",
}
_LINE_KEYS = {
    "device",
    "baudrate",
    "data_bits",
    "parity",
    "stop_bits",
    "timeout",
    "retries",
    "retry_unsafe",
    "retry_writes",
    "max_queue_per_master",
    "late_answer_window",
    "noisy_after",
    "probe_share",
    "frame_gap",
    "broadcast",
    "broadcast_turnaround",
    "max_queue",
    "rs485",
    "rs485_rts_level_for_tx",
    "rs485_rts_level_for_rx",
    "rs485_delay_before_tx",
    "rs485_delay_after_tx",
    "units",
    "dead_after",
    "probe_interval",
    "probe_max_interval",
    "slave_timeouts",
    "coalesce",
    "cache",
    "kind",
    "inter_char_timeout",
    "echo",
    "address",
    "connect_delay",
    "connect_timeout",
    "silence",
    "cert",
    "key",
    "ca",
    "server_name",
    "check_server_name",
    "tls_handshake_timeout",
    "max_in_flight",
}
#: Keys only a ``kind = "tls"`` line takes.
_TLS_LINE_KEYS = ("cert", "key", "ca", "server_name", "check_server_name", "tls_handshake_timeout")


def _build_server(check: _Checker, raw: Mapping[str, Any]) -> ServerConfig:
    table = check.table(raw, "server")
    prefix = "server."
    check.unknown_keys(table, _SERVER_KEYS, prefix)
    listen = check.address(table, "listen", prefix, DEFAULT_LISTEN) or parse_host_port(
        DEFAULT_LISTEN
    )
    refuse_raw = table.get("refuse_functions", [])
    refuse: set[int] = set()
    if not isinstance(refuse_raw, list) or not all(
        isinstance(code, int) and not isinstance(code, bool) and 1 <= code <= 127
        for code in refuse_raw
    ):
        check.fail(
            f"{prefix}refuse_functions", "write a list of function codes 1..127, like [8, 17]"
        )
    else:
        refuse = set(refuse_raw)
    return ServerConfig(
        host=listen[0],
        port=listen[1],
        max_connections=check.integer(table, "max_connections", prefix, 100, 1, 100_000),
        when_full=check.choice(table, "when_full", prefix, "close_oldest_idle", VALID_WHEN_FULL),
        idle_timeout=check.number(table, "idle_timeout", prefix, 300.0, 0.0, 86_400.0),
        max_pipeline=check.integer(table, "max_pipeline", prefix, 16, 1, 256),
        backlog=check.integer(table, "backlog", prefix, 1024, 1, 65_535),
        broadcast_reply=check.boolean(table, "broadcast_reply", prefix, False),
        refuse_functions=frozenset(refuse),
        allow=_networks(check, table, "allow", prefix),
        read_only=check.boolean(table, "read_only", prefix, False),
        policy=_policy_name(check, table, prefix),
        max_connections_per_source=check.integer(
            table, "max_connections_per_source", prefix, 16, 0, 100_000
        ),
        evict_min_idle=check.number(table, "evict_min_idle", prefix, 10.0, 0.0, 86_400.0),
        send_timeout=check.number(table, "send_timeout", prefix, 10.0, 0.0, 3600.0),
        tls_handshake_timeout=check.number(
            table, "tls_handshake_timeout", prefix, 10.0, 0.1, 600.0
        ),
    )


def _build_line(check: _Checker, name: str, table: Mapping[str, Any]) -> LineConfig | None:
    prefix = f"lines.{name}."
    if not isinstance(table, dict):
        check.fail(f"lines.{name}", "must be a table ([lines.NAME]) with at least a device")
        return None
    check.unknown_keys(table, _LINE_KEYS, prefix)
    kind = check.choice(table, "kind", prefix, "rtu", VALID_LINE_KINDS)
    host, port = "", 0
    device = table.get("device")
    if kind in NETWORK_LINE_KINDS:
        host, port, device = _network_address(check, table, prefix, kind)
    elif "address" in table:
        check.fail(f"{prefix}address", 'only a network line takes it (kind = "rtu-over-tcp", '
                   f'"tcp" or "tls"); a {kind} line names its serial port with device')  # fmt: skip
    if kind not in NETWORK_LINE_KINDS and (not isinstance(device, str) or not device):
        check.fail(
            f"{prefix}device",
            'missing; set the serial device or URL, like "/dev/ttyUSB0" '
            'or "socket://10.0.0.5:4001"',
        )
    if not isinstance(device, str):
        device = ""
    stop_bits_raw = table.get("stop_bits", 1)
    if stop_bits_raw not in (1, 1.5, 2) or isinstance(stop_bits_raw, bool):
        check.fail(f"{prefix}stop_bits", f"{stop_bits_raw!r} is not 1, 1.5 or 2")
        stop_bits_raw = 1
    frame_gap_raw = table.get("frame_gap")
    frame_gap: float | None = None
    if frame_gap_raw is not None and frame_gap_raw != "auto":
        frame_gap = check.number(table, "frame_gap", prefix, 0.0, 0.0, 1.0)
    units: tuple[int, ...] = ()
    if "units" in table:
        try:
            units = tuple(parse_units(table["units"]))
        except ValueError as error:
            check.fail(f"{prefix}units", str(error))
    ascii_line = kind == "ascii"  # 7E1 by default (Modbus over Serial Line 2.5.2.1)
    baudrate = check.integer(table, "baudrate", prefix, 9600, 50, 4_000_000)
    data_bits = check.integer(table, "data_bits", prefix, 7 if ascii_line else 8, 7, 8)
    default_parity = "E" if ascii_line else "N"
    parity = check.choice(table, "parity", prefix, default_parity, VALID_PARITIES, upper=True)
    stop_bits = float(stop_bits_raw)
    longest = MAX_ASCII_FRAME if ascii_line else MAX_RTU_FRAME
    timeout = auto_timeout(baudrate, data_bits, parity, stop_bits, longest)
    if kind in NETWORK_LINE_KINDS:
        timeout = round(timeout + NETWORK_ALLOWANCE_S, 3)
    if table.get("timeout", "auto") != "auto":
        timeout = check.number(table, "timeout", prefix, timeout, 0.001, 60.0)
    return LineConfig(
        dead_after=check.integer(table, "dead_after", prefix, 3, 0, 1000),
        probe_interval=check.number(table, "probe_interval", prefix, 1.0, 0.01, 3600.0),
        probe_max_interval=check.number(table, "probe_max_interval", prefix, 30.0, 0.01, 86_400.0),
        slave_timeouts=_slave_timeouts(check, table, prefix),
        coalesce=check.boolean(table, "coalesce", prefix, True),
        cache=_cache_rules(check, table, prefix),
        name=name,
        device=device,
        baudrate=baudrate,
        data_bits=data_bits,
        parity=parity,
        stop_bits=stop_bits,
        timeout=timeout,
        retries=check.integer(table, "retries", prefix, 1, 0, 10),
        retry_unsafe=_retry_unsafe(check, table, prefix),
        frame_gap=frame_gap,
        broadcast=check.boolean(table, "broadcast", prefix, True),
        broadcast_turnaround=check.number(table, "broadcast_turnaround", prefix, 0.1, 0.0, 10.0),
        max_queue=check.integer(table, "max_queue", prefix, 256, 1, 100_000),
        max_queue_per_master=check.integer(table, "max_queue_per_master", prefix, 32, 1, 10_000),
        late_answer_window=_optional_number(check, table, "late_answer_window", prefix, 60.0),
        noisy_after=_optional_number(check, table, "noisy_after", prefix, 3600.0),
        probe_share=check.number(table, "probe_share", prefix, 0.05, 0.0, 1.0),
        rs485=check.boolean(table, "rs485", prefix, False),
        rs485_rts_level_for_tx=check.boolean(table, "rs485_rts_level_for_tx", prefix, True),
        rs485_rts_level_for_rx=check.boolean(table, "rs485_rts_level_for_rx", prefix, False),
        rs485_delay_before_tx=check.number(table, "rs485_delay_before_tx", prefix, 0.0, 0.0, 1.0),
        rs485_delay_after_tx=check.number(table, "rs485_delay_after_tx", prefix, 0.0, 0.0, 1.0),
        units=units,
        kind=kind,
        inter_char_timeout=check.number(table, "inter_char_timeout", prefix, 1.0, 0.001, 60.0),
        echo=check.boolean(table, "echo", prefix, False),
        host=host,
        port=port,
        connect_delay=check.number(table, "connect_delay", prefix, 0.0, 0.0, 60.0),
        connect_timeout=check.number(table, "connect_timeout", prefix, 3.0, 0.01, 600.0),
        silence_setting=_optional_number(check, table, "silence", prefix, 10.0),
        max_in_flight=_max_in_flight(check, table, prefix, kind),
        **_tls_line(check, table, prefix, kind, host),
    )


def _usable_server_name(name: str) -> bool:
    """True for a name TLS can check: an IP address, or a host name IDNA can encode."""
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        pass
    if any(character.isspace() or not character.isprintable() for character in name):
        return False
    try:
        name.encode("idna")
    except UnicodeError:
        return False
    return True


def _tls_line(
    check: _Checker, table: Mapping[str, Any], prefix: str, kind: str, host: str
) -> dict[str, Any]:
    """The TLS keys of a ``kind = "tls"`` line (refused on any other kind)."""
    if kind != "tls":
        for key in _TLS_LINE_KEYS:
            if key in table:
                check.fail(f"{prefix}{key}", f'only a kind = "tls" line takes it; remove it '
                           f"from this {kind} line")  # fmt: skip
        return {}
    what = {
        "cert": "the gateway's client certificate chain (PEM, leaf first)",
        "key": "the private key of that certificate (PEM, unencrypted)",
        "ca": "the CA certificates the slave's certificate must chain to (PEM)",
    }
    files: dict[str, str | None] = {}
    for key, description in what.items():
        value = table.get(key)
        if not isinstance(value, str) or not value:
            fix = "write a file path as a string" if key in table else "missing"
            check.fail(f"{prefix}{key}", f"{fix}; a tls line needs {description}"
                       f" (or --modbus-tls-{key} FILE)")  # fmt: skip
            value = None
        files[key] = value
    server_name = table.get("server_name", host)
    if not isinstance(server_name, str) or not server_name:
        check.fail(f"{prefix}server_name", "write the name the slave's certificate carries, "
                   'like "plc-7.plant.example" (default: the address\'s host)')  # fmt: skip
        server_name = host
    elif not _usable_server_name(server_name):
        check.fail(f"{prefix}server_name", f"{server_name!r} is not a host name or address; "
                   "write the name the slave's certificate carries, like "
                   '"plc-7.plant.example"')  # fmt: skip
        server_name = host
    return {
        **files,
        "server_name": server_name,
        "check_server_name": check.boolean(table, "check_server_name", prefix, True),
        "tls_handshake_timeout": check.number(
            table, "tls_handshake_timeout", prefix, 10.0, 0.1, 600.0
        ),
    }


def _max_in_flight(check: _Checker, table: Mapping[str, Any], prefix: str, kind: str) -> int:
    """Requests outstanding at once: only where answers carry their request's number (MBAP)."""
    if "max_in_flight" not in table:
        return 1
    if not is_mbap(kind):
        check.fail(
            f"{prefix}max_in_flight",
            f'only a Modbus TCP line (kind = "tcp" or "tls") takes it: a {kind} line\'s '
            "answers carry no transaction id, so it has one request on the wire; remove the key",
        )
        return 1
    return check.integer(table, "max_in_flight", prefix, 1, 1, MAX_IN_FLIGHT)


def _network_address(
    check: _Checker, table: Mapping[str, Any], prefix: str, kind: str
) -> tuple[str, int, str]:
    """``address = "HOST:PORT"`` of a network line: host, port and the text shown as its device."""
    if "device" in table:
        check.fail(f"{prefix}device", f'a {kind} line is reached at address = "HOST:PORT", '
                   "not a device; rename the key to address")  # fmt: skip
    value = table.get("address")
    if kind == "tls" and isinstance(value, str) and value and not _has_port(value):
        value = f"{value}:{DEFAULT_TLS_PORT}"  # Modbus/TCP Security's own port
    if not isinstance(value, str) or not value:
        check.fail(f"{prefix}address", f'missing; a {kind} line needs the device server\'s '
                   'address, like "10.0.0.5:4001"')  # fmt: skip
        return "", 0, ""
    try:
        host, port = parse_host_port(value)
    except ValueError as error:
        check.fail(f"{prefix}address", str(error))
        return "", 0, ""
    if port == 0 or host in ("0.0.0.0", "::"):
        check.fail(f"{prefix}address", f"{value!r} is not a place to connect to; "
                   'write the device server\'s address, like "10.0.0.5:4001"')  # fmt: skip
        return "", 0, ""
    shown = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    return host, port, shown


#: Time a slave is given to start its answer, on top of the longest answer's transmission.
SLAVE_TURNAROUND_S = 0.1
#: The longest RTU frame (Modbus over Serial Line 2.5.1): 256 bytes.
MAX_RTU_FRAME = 256
#: The longest ASCII frame (2.5.2.1): 513 characters.
MAX_ASCII_FRAME = 513


def auto_timeout(
    baudrate: int,
    data_bits: int = 8,
    parity: str = "N",
    stop_bits: float = 1,
    longest_frame: int = MAX_RTU_FRAME,
) -> float:
    """The default response timeout (``timeout = "auto"``) of a line with these settings.

    The timeout runs from the end of the request to the end of the answer, so it must hold
    the longest answer's transmission (256 characters) plus the slave's turnaround (0.1 s):
    0.367 s at 9600 8N1, 0.393 s at 9600 8E1. Two attempts (``retries = 1``) then end before
    a master's common 1 s timeout at 9600 baud and faster, so the master gets the gateway's
    0x0B rather than a timeout of its own; slower lines get proportionally longer. ASCII
    lines hold 513 characters instead: 0.634 s at 9600 7E1.
    """
    longest = transmission_time(longest_frame, baudrate, data_bits, parity, stop_bits)
    return round(SLAVE_TURNAROUND_S + longest, 3)


def _retry_unsafe(check: _Checker, table: Mapping[str, Any], prefix: str) -> bool:
    """``retry_unsafe``, or its former name ``retry_writes`` (it now covers more than writes)."""
    if "retry_unsafe" in table and "retry_writes" in table:
        check.fail(
            f"{prefix}retry_writes",
            "is the former name of retry_unsafe; keep only retry_unsafe",
        )
    key = "retry_writes" if "retry_writes" in table else "retry_unsafe"
    return check.boolean(table, key, prefix, False)


def _optional_number(
    check: _Checker, table: Mapping[str, Any], key: str, prefix: str, high: float
) -> float | None:
    """A number of seconds, or ``None`` (the default derived from the timeouts) when absent."""
    if key not in table or table[key] == "auto":
        return None
    return check.number(table, key, prefix, 0.0, 0.0, high)


def _slave_timeouts(check: _Checker, table: Mapping[str, Any], prefix: str) -> dict[int, float]:
    raw = table.get("slave_timeouts", {})
    key = f"{prefix}slave_timeouts"
    if not isinstance(raw, dict):
        check.fail(key, 'write a table of slave = seconds, like { "5" = 0.3 }')
        return {}
    timeouts: dict[int, float] = {}
    for slave_text in raw:
        if not slave_text.isdigit() or not 1 <= int(slave_text) <= 247:
            check.fail(f"{key}.{slave_text}", "the key must be a slave address 1..247, quoted")
            continue
        timeouts[int(slave_text)] = check.number(raw, slave_text, f"{key}.", 1.0, 0.001, 60.0)
    return timeouts


_CACHE_FUNCTIONS = (1, 2, 3, 4)


def _cache_rules(check: _Checker, table: Mapping[str, Any], prefix: str) -> tuple[CacheRule, ...]:
    raw = table.get("cache", [])
    key = f"{prefix}cache"
    if not isinstance(raw, list):
        check.fail(
            key, "write [[lines.NAME.cache]] tables with unit, function, start, count, max_age"
        )
        return ()
    rules: list[CacheRule] = []
    for index, entry in enumerate(raw):
        entry_key = f"{key}[{index}]."
        if not isinstance(entry, dict):
            check.fail(
                f"{key}[{index}]", "must be a table with unit, function, start, count, max_age"
            )
            continue
        check.unknown_keys(entry, {"unit", "function", "start", "count", "max_age"}, entry_key)
        function = check.integer(entry, "function", entry_key, 3, 1, 4)
        if function not in _CACHE_FUNCTIONS:
            continue
        rules.append(
            CacheRule(
                unit=check.integer(entry, "unit", entry_key, 1, 1, 247),
                function=function,
                start=check.integer(entry, "start", entry_key, 0, 0, 65535),
                count=check.integer(entry, "count", entry_key, 1, 1, 65536),
                max_age=check.number(entry, "max_age", entry_key, 1.0, 0.0, 3600.0),
            )
        )
    return tuple(rules)


def _build_routes(
    check: _Checker, raw: Mapping[str, Any], lines: tuple[LineConfig, ...]
) -> dict[int, Route]:
    routes: dict[int, Route] = {}
    names = {line.name for line in lines}
    for line in lines:
        taken: dict[str, list[int]] = {}  # earlier line -> units this line repeats
        for unit in line.units:
            if unit in routes:
                taken.setdefault(routes[unit].line, []).append(unit)
                continue
            routes[unit] = Route(unit, line.name, unit)
        for other, units in taken.items():  # one message per pair of lines, as ranges
            check.fail(
                f"lines.{line.name}.units",
                f"{'unit' if len(units) == 1 else 'units'} {format_units(units)} already "
                f"routed to line {other!r}; give each unit one line",
            )
    raw_routes = raw.get("routes", [])
    if not isinstance(raw_routes, list):
        check.fail("routes", "write routes as [[routes]] tables with unit, line and slave")
        return routes
    for index, entry in enumerate(raw_routes):
        key = f"routes[{index}]"
        if not isinstance(entry, dict):
            check.fail(key, "must be a table with unit, line and slave")
            continue
        check.unknown_keys(entry, {"unit", "line", "slave"}, f"{key}.")
        unit = check.integer(entry, "unit", f"{key}.", -1, 1, 255) if "unit" in entry else -1
        if "unit" not in entry:
            check.fail(f"{key}.unit", "missing; the TCP unit id (1..255) this route answers for")
        line_name = entry.get("line")
        if not isinstance(line_name, str) or line_name not in names:
            known = ", ".join(sorted(names)) or "(none defined)"
            check.fail(f"{key}.line", f"{line_name!r} is not a configured line; lines are: {known}")
            continue
        slave = check.integer(entry, "slave", f"{key}.", unit if 1 <= unit <= 247 else 1, 1, 247)
        if unit < 1:
            continue
        if unit in routes:
            check.fail(
                f"{key}.unit", f"unit {unit} is already routed to line {routes[unit].line!r}"
            )
            continue
        routes[unit] = Route(unit, line_name, slave)
    return routes


def format_units(units: Iterable[int]) -> str:
    """Unit ids as compact ranges: ``[1, 2, 3, 7, 9, 10]`` -> ``"1-3, 7, 9-10"``."""
    parts: list[str] = []
    ordered = sorted(set(units))
    start = 0
    for index, unit in enumerate(ordered):
        if index + 1 < len(ordered) and ordered[index + 1] == unit + 1:
            continue
        low = ordered[start]
        parts.append(str(low) if low == unit else f"{low}-{unit}")
        start = index + 1
    return ", ".join(parts)


def _device_identity(device: str) -> str:
    """What makes two ``device`` values the same port: the resolved path (by-id symlinks)."""
    return device if "://" in device else os.path.realpath(device)


def _check_shared_devices(check: _Checker, lines: tuple[LineConfig, ...]) -> None:
    """Two lines on one device would interleave their frames on the wire: an error."""
    owners: dict[str, str] = {}
    for line in lines:
        if not line.device:
            continue
        identity = line.device if line.is_url else _device_identity(line.device)
        owner = owners.setdefault(identity, line.name)
        if owner != line.name:
            check.fail(
                f"lines.{line.name}.device",
                f"{line.device!r} is the device of line {owner!r} too; one serial device "
                f"serves one line: merge the two lines' units into lines.{owner}",
            )


def _check_serial_slave_devices(
    check: _Checker, lines: tuple[LineConfig, ...], listeners: Iterable[ListenerConfig]
) -> None:
    """A serial-slave listener's device is its own: not a line's, not another listener's."""
    owners = {
        (line.device if line.is_url else _device_identity(line.device)): f"line {line.name!r}"
        for line in lines
        if line.device
    }
    for listener in listeners:
        serial = listener.serial
        if serial is None or not serial.device:
            continue
        identity = serial.device if serial.is_url else _device_identity(serial.device)
        owner = owners.setdefault(identity, f"listener {listener.name!r}")
        if owner != f"listener {listener.name!r}":
            check.fail(
                f"{listener.key_prefix}device",
                f"{serial.device!r} is the device of {owner} too; a serial-slave listener "
                "needs a serial line of its own",
            )


def _hosts_overlap(first: str, second: str) -> bool:
    wildcard = ("0.0.0.0", "::", "")
    return first == second or first in wildcard or second in wildcard


def config_warnings(config: GatewayConfig) -> list[str]:
    """Things that are legal but probably wrong, each naming its key (check-config, start).

    Warnings, not errors: a USB adapter may be plugged in after the gateway starts, and a
    line may be kept ready for units routed to it later.
    """
    warnings: list[str] = []
    routed_lines = {route.line for route in config.routes.values()}
    for line in config.lines:
        prefix = f"lines.{line.name}"
        if not line.is_url and not os.path.exists(line.device):
            warnings.append(
                f"{prefix}.device: {line.device} does not exist (yet); the gateway retries "
                "opening it, check the path (ls /dev/serial/by-id/)"
            )
        if line.kind == "tls" and not line.check_server_name:
            warnings.append(
                f"{prefix}.check_server_name: false: the slave's certificate must still chain "
                f"to {prefix}.ca, but any certificate that CA issued is taken for this slave; "
                "keep it only with a CA that issues this one device's certificate, else set "
                "server_name to the name in the slave's certificate"
            )
        if line.name not in routed_lines:
            warnings.append(
                f"{prefix}.units: no unit is routed to this line; add units = [...] or a "
                f'[[routes]] entry with line = "{line.name}"'
            )
    server, metrics = config.server, config.metrics
    if (
        metrics.enabled
        and server.port == metrics.port
        and server.port != 0
        and _hosts_overlap(server.host, metrics.host)
    ):
        warnings.append(
            f"metrics.listen: port {metrics.port} is also server.listen's (Modbus TCP); "
            "the second to bind fails: give one of them another port (the defaults are "
            "502 and 9502)"
        )
    return warnings


def _networks(
    check: _Checker, table: Mapping[str, Any], key: str, prefix: str
) -> tuple[IPNetwork, ...]:
    """A list of addresses or CIDR networks (a single string is a list of one)."""
    raw = table.get(key, [])
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list):
        check.fail(f"{prefix}{key}", 'write a list of addresses or networks, like ["10.1.2.0/24"]')
        return ()
    networks: list[IPNetwork] = []
    for item in raw:
        try:
            networks.append(ipaddress.ip_network(str(item), strict=False))
        except ValueError:
            check.fail(
                f"{prefix}{key}",
                f"{item!r} is not an IP address or network; write it like "
                '"10.1.2.0/24", "192.168.1.7" or "fd00::/8"',
            )
    return tuple(networks)


def _policy_name(check: _Checker, table: Mapping[str, Any], prefix: str) -> str | None:
    value = table.get("policy")
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        check.fail(f"{prefix}policy", "write the name of a [policies.NAME] table, as a string")
        return None
    return value


_ACCESS = {"read": Access.READ, "write": Access.WRITE, "read_write": Access.READ_WRITE}
_RULE_KEYS = {"role", "source", "units", "functions", "addresses", "access"}


def parse_function_key(item: Any) -> tuple[int, int | None]:
    """``3``, ``"0x10"``, ``"write_single_register"``, ``"8:4"`` or ``"diagnostics:0"``.

    FC 8 takes a subfunction (0..65535), FC 43 a MEI type (0..255); raise ValueError with the fix.
    """
    if isinstance(item, int) and not isinstance(item, bool):
        if not 1 <= item <= 127:
            raise ValueError(f"function code {item} outside 1..127")
        return item, None
    if not isinstance(item, str):
        raise ValueError(f"{item!r} is not a function code or name")
    text, sep, sub_text = item.strip().lower().partition(":")
    code = next((c for c, name in fc.FUNCTION_NAMES.items() if name == text), None)
    if code is None:
        try:
            code = int(text, 0)
        except ValueError:
            raise ValueError(
                f"{item!r} is not a function: write a code (3), a name (read_holding_registers) "
                'or "8:4" for a diagnostics subfunction'
            ) from None
        if not 1 <= code <= 127:
            raise ValueError(f"function code {code} outside 1..127")
    if not sep:
        return code, None
    limit = {fc.DIAGNOSTICS: 0xFFFF, fc.ENCAPSULATED_INTERFACE: 0xFF}.get(code)
    try:
        sub = int(sub_text, 0)
    except ValueError:
        sub = -1
    if limit is None or not 0 <= sub <= limit:
        raise ValueError(
            f"{item!r}: only diagnostics (8:0..65535) and encapsulated_interface (43:0..255) "
            "take a subfunction after the colon"
        )
    return code, sub


def _ranges(value: Any, low: int, high: int) -> list[tuple[int, int]]:
    """``[0, "100-199"]`` as inclusive ranges; ValueError with the fix."""
    if isinstance(value, int | str) and not isinstance(value, bool):
        value = [value]
    if not isinstance(value, list):
        raise ValueError(f'write a list of numbers and ranges, like [{low}, "{low + 10}-{high}"]')
    spans: list[tuple[int, int]] = []
    for item in value:
        if isinstance(item, int) and not isinstance(item, bool):
            first = last = item
        elif isinstance(item, str) and "-" in item:
            first_text, _, last_text = item.partition("-")
            if not (first_text.strip().isdigit() and last_text.strip().isdigit()):
                raise ValueError(f'{item!r} is not a range like "{low}-{high}"')
            first, last = int(first_text), int(last_text)
        elif isinstance(item, str) and item.strip().isdigit():
            first = last = int(item)
        else:
            raise ValueError(f"{item!r} is not a number or a range")
        if not (low <= first <= last <= high):
            raise ValueError(f"{item!r} outside {low}..{high} (or backwards)")
        spans.append((first, last))
    return spans


def _build_rule(check: _Checker, entry: Any, key: str) -> Rule | None:
    if not isinstance(entry, dict):
        check.fail(key, "must be a table with role, source, units, functions, addresses, access")
        return None
    prefix = f"{key}."
    check.unknown_keys(entry, _RULE_KEYS, prefix)
    role = entry.get("role")
    if role is not None and (not isinstance(role, str) or not role):
        check.fail(f"{prefix}role", 'write the role as a non-empty string, like "operator"')
        role = None
    units: frozenset[int] | None = None
    if "units" in entry:
        try:
            units = frozenset(first for a, b in _ranges(entry["units"], 0, 255) for first in
                              range(a, b + 1))  # fmt: skip
        except ValueError as error:
            check.fail(f"{prefix}units", f"{error} (0 is broadcast, 1..255 unit ids)")
    functions: frozenset[tuple[int, int | None]] | None = None
    if "functions" in entry:
        raw_functions = entry["functions"]
        if not isinstance(raw_functions, list):
            raw_functions = [raw_functions]
        keys = set()
        for item in raw_functions:
            try:
                keys.add(parse_function_key(item))
            except ValueError as error:
                check.fail(f"{prefix}functions", str(error))
        functions = frozenset(keys)
    addresses = None
    if "addresses" in entry:
        try:
            addresses = merge_ranges(_ranges(entry["addresses"], 0, 65535))
        except ValueError as error:
            check.fail(f"{prefix}addresses", str(error))
    access = _ACCESS[check.choice(entry, "access", prefix, "read_write", tuple(_ACCESS))]
    return Rule(
        key=key,
        role=role,
        sources=_networks(check, entry, "source", prefix),
        units=units,
        functions=functions,
        addresses=addresses,
        access=access,
    )


def _build_policies(check: _Checker, raw: Mapping[str, Any]) -> dict[str, tuple[Rule, ...]]:
    table = check.table(raw, "policies")
    policies: dict[str, tuple[Rule, ...]] = {}
    for name, body in table.items():
        key = f"policies.{name}"
        if not isinstance(body, dict):
            check.fail(key, "must be a table; write rules as [[policies.NAME.rules]]")
            continue
        check.unknown_keys(body, {"rules"}, f"{key}.")
        entries = body.get("rules", [])
        if not isinstance(entries, list):
            check.fail(f"{key}.rules", "write rules as [[policies.NAME.rules]] tables")
            continue
        rules = [_build_rule(check, entry, f"{key}.rules[{i}]") for i, entry in enumerate(entries)]
        policies[name] = tuple(rule for rule in rules if rule is not None)
    return policies


_LISTENER_KEYS = {"name", "protocol", "listen", "cert", "key", "ca", "allow", "read_only", "policy"}
#: Keys of a ``serial-slave`` listener only: its serial line, and the units it answers for.
_SERIAL_SLAVE_KEYS = {
    "device", "baudrate", "data_bits", "parity", "stop_bits", "units",
    "framing", "echo", "inter_char_timeout",
}  # fmt: skip


def _serial_slave_line(
    check: _Checker, entry: Mapping[str, Any], prefix: str, name: str
) -> tuple[LineConfig, tuple[int, ...]]:
    """The serial line of a ``serial-slave`` listener, and the units it answers for."""
    device = entry.get("device")
    if not isinstance(device, str) or not device:
        check.fail(f"{prefix}device", 'missing; a serial-slave listener answers on a serial '
                   'device, like "/dev/ttyUSB1" (or --serial-slave DEVICE)')  # fmt: skip
        device = ""
    if "listen" in entry:
        check.fail(f"{prefix}listen", "a serial-slave listener has a device, not an address")
    stop_bits = entry.get("stop_bits", 1)
    if stop_bits not in (1, 1.5, 2) or isinstance(stop_bits, bool):
        check.fail(f"{prefix}stop_bits", f"{stop_bits!r} is not 1, 1.5 or 2")
        stop_bits = 1
    units: tuple[int, ...] = ()
    if "units" in entry:
        try:
            units = tuple(parse_units(entry["units"]))
        except ValueError as error:
            check.fail(f"{prefix}units", str(error))
    framing = check.choice(entry, "framing", prefix, "rtu", VALID_SLAVE_FRAMINGS)
    ascii_line = framing == "ascii"  # 7E1 by default (Modbus over Serial Line 2.5.2.1)
    default_parity = "E" if ascii_line else "N"
    line = LineConfig(
        name=f"listener {name}",
        device=device,
        baudrate=check.integer(entry, "baudrate", prefix, 9600, 50, 4_000_000),
        data_bits=check.integer(entry, "data_bits", prefix, 7 if ascii_line else 8, 7, 8),
        parity=check.choice(entry, "parity", prefix, default_parity, VALID_PARITIES, upper=True),
        stop_bits=float(stop_bits),
        kind=framing,
        inter_char_timeout=check.number(entry, "inter_char_timeout", prefix, 1.0, 0.001, 60.0),
        echo=check.boolean(entry, "echo", prefix, False),
    )
    if "inter_char_timeout" in entry and not ascii_line:
        check.fail(f"{prefix}inter_char_timeout", 'only an ASCII line has one (framing = '
                   '"ascii"); an RTU frame ends on t3.5 of silence')  # fmt: skip
    return line, units


def _build_listeners(
    check: _Checker,
    raw: Mapping[str, Any],
    server: ServerConfig,
    policies: Mapping[str, tuple[Rule, ...]],
) -> tuple[ListenerConfig, ...]:
    """``[server] listen`` (the shorthand tcp listener) and every ``[[listeners]]`` entry.

    The shorthand listener exists when ``[server] listen`` is written (or ``--listen``
    given), or when no other network listener is configured: as before listeners existed
    (a ``serial-slave`` listener does not replace it).
    """
    server_table = check.table(raw, "server")
    entries = raw.get("listeners", [])
    if not isinstance(entries, list):
        check.fail("listeners", "write listeners as [[listeners]] tables")
        entries = []
    listeners: list[ListenerConfig] = []
    networked = [
        e for e in entries if not (isinstance(e, dict) and e.get("protocol") == "serial-slave")
    ]
    if "listen" in server_table or not networked:
        listeners.append(
            ListenerConfig(
                name="tcp", protocol="tcp", host=server.host, port=server.port,
                read_only=server.read_only, policy=server.policy,
            )
        )  # fmt: skip
    for index, entry in enumerate(entries):
        key = f"listeners[{index}]"
        if not isinstance(entry, dict):
            check.fail(key, "must be a table with name, protocol and listen")
            continue
        prefix = f"{key}."
        check.unknown_keys(entry, _LISTENER_KEYS | _SERIAL_SLAVE_KEYS, prefix)
        protocol = check.choice(entry, "protocol", prefix, "tcp", VALID_PROTOCOLS)
        name = entry.get("name", protocol)
        if not isinstance(name, str) or not name.replace("-", "_").isidentifier():
            check.fail(f"{prefix}name", f"{name!r}: write a short name of letters, digits, - or _")
            name = f"listener{index}"
        if protocol == "serial-slave":
            serial, units = _serial_slave_line(check, entry, prefix, name)
            for other in ("cert", "key", "ca", "allow"):
                if other in entry:
                    check.fail(f"{prefix}{other}", "a serial-slave listener has no network "
                               "peers: remove it")  # fmt: skip
            listeners.append(
                ListenerConfig(
                    name=name, protocol=protocol, host="", port=0,
                    read_only=check.boolean(entry, "read_only", prefix, False) or server.read_only,
                    policy=_policy_name(check, entry, prefix), key_prefix=prefix,
                    serial=serial, units=units,
                )
            )  # fmt: skip
            continue
        for serial_key in sorted(_SERIAL_SLAVE_KEYS & set(entry)):
            check.fail(f"{prefix}{serial_key}", 'only a protocol = "serial-slave" listener '
                       "takes it")  # fmt: skip
        default_port = DEFAULT_TLS_PORT if protocol == "tls" else 502
        address = check.address(entry, "listen", prefix, f"0.0.0.0:{default_port}")
        if address is None:
            check.fail(
                f"{prefix}listen", 'a listener needs an address; write it like "0.0.0.0:802"'
            )
            address = ("0.0.0.0", default_port)
        files: dict[str, str | None] = {}
        for file_key in ("cert", "key", "ca"):
            value = entry.get(file_key)
            if value is not None and (not isinstance(value, str) or not value):
                check.fail(f"{prefix}{file_key}", "write a file path as a string")
                value = None
            if protocol == "tls" and value is None:
                what = {
                    "cert": "the server's certificate chain (PEM)",
                    "key": "the server's private key (PEM)",
                    "ca": "the CA certificates client certificates must chain to (PEM)",
                }
                check.fail(f"{prefix}{file_key}", f"missing; a tls listener needs {what[file_key]}"
                           f" (or --tls-{file_key} FILE)")  # fmt: skip
            if protocol != "tls" and value is not None:
                check.fail(f"{prefix}{file_key}", 'only a protocol = "tls" listener takes it')
            files[file_key] = value
        listeners.append(
            ListenerConfig(
                name=name, protocol=protocol, host=address[0], port=address[1],
                cert=files["cert"], key=files["key"], ca=files["ca"],
                allow=_networks(check, entry, "allow", prefix),
                read_only=check.boolean(entry, "read_only", prefix, False) or server.read_only,
                policy=_policy_name(check, entry, prefix), key_prefix=prefix,
            )
        )  # fmt: skip
    seen: dict[str, ListenerConfig] = {}
    for listener in listeners:
        if listener.name in seen:
            check.fail(f"{listener.key_prefix}name", f"{listener.name!r} is used by another "
                       "listener; give each listener its own name")  # fmt: skip
        seen[listener.name] = listener
        if listener.policy is not None and listener.policy not in policies:
            known = ", ".join(sorted(policies)) or "(none defined)"
            check.fail(f"{listener.key_prefix}policy", f"{listener.policy!r} is not a "
                       f"[policies.NAME] table; policies are: {known}")  # fmt: skip
    addresses = [(lst.host, lst.port) for lst in listeners if lst.port != 0]
    for address in set(addresses):
        if addresses.count(address) > 1:
            check.fail("listeners", f"two listeners on {address[0]}:{address[1]}; "
                       "give each its own port")  # fmt: skip
    return tuple(listeners)


def build_config(raw: Mapping[str, Any], source: str = "<command line>") -> GatewayConfig:
    """Validate raw tables into a ``GatewayConfig``; raise ``ConfigError`` listing every fault."""
    check = _Checker()
    check.unknown_keys(
        raw, {"server", "metrics", "logging", "lines", "routes", "listeners", "policies"}, ""
    )
    server = _build_server(check, raw)
    metrics_table = check.table(raw, "metrics")
    check.unknown_keys(metrics_table, {"listen", "max_connections", "header_timeout"}, "metrics.")
    metrics_address = check.address(metrics_table, "listen", "metrics.", DEFAULT_METRICS)
    http_cap = check.integer(metrics_table, "max_connections", "metrics.", 32, 1, 1024)
    header_timeout = check.number(metrics_table, "header_timeout", "metrics.", 5.0, 0.1, 60.0)
    metrics = (
        MetricsConfig(True, metrics_address[0], metrics_address[1], http_cap, header_timeout)
        if metrics_address is not None
        else MetricsConfig(False, max_connections=http_cap, header_timeout=header_timeout)
    )
    logging_table = check.table(raw, "logging")
    check.unknown_keys(logging_table, {"level", "format"}, "logging.")
    log = LoggingConfig(
        level=check.choice(logging_table, "level", "logging.", "info", VALID_LOG_LEVELS),
        format=check.choice(logging_table, "format", "logging.", "text", VALID_LOG_FORMATS),
    )
    lines_table = check.table(raw, "lines")
    lines = tuple(
        line
        for name, table in lines_table.items()
        if (line := _build_line(check, name, table)) is not None
    )
    if not lines:
        check.fail(
            "lines",
            'no serial line configured; add [lines.a] with device = "/dev/ttyUSB0" '
            "(or run with --serial DEVICE, or --demo)",
        )
    routes = _build_routes(check, raw, lines)
    policies = _build_policies(check, raw)
    listeners = _build_listeners(check, raw, server, policies)
    _check_shared_devices(check, lines)
    _check_serial_slave_devices(check, lines, listeners)
    if check.problems:
        raise ConfigError(source, check.problems)
    return GatewayConfig(server, metrics, log, lines, routes, source, listeners, policies)


def policy_warnings(config: GatewayConfig) -> list[str]:
    """Rules that can never grant anything, unused policies, tls listeners without a policy."""
    warnings: list[str] = []
    used = {listener.policy for listener in config.listeners}
    for name in config.policies:
        if name not in used:
            warnings.append(f"policies.{name}: no listener uses it; set policy = {name!r} on "
                            "a listener ([server] or [[listeners]]) or remove it")  # fmt: skip
    for listener in config.listeners:
        if listener.policy is None:
            if listener.tls:
                warnings.append(
                    f"{listener.key_prefix}policy: tls listener {listener.name!r} has no policy: "
                    "every client certificate with a role has every right (the NULL role none)"
                )
            continue
        rules = config.policies.get(listener.policy, ())
        if not rules:
            warnings.append(f"policies.{listener.policy}: no rules, so listener "
                            f"{listener.name!r} refuses every request")  # fmt: skip
        warnings += lint(
            rules,
            listener=listener.name,
            tls=listener.tls,
            read_only=listener.read_only or config.server.read_only,
            allow=listener.allow or config.server.allow,
            routed_units=config.routes,
        )
    return warnings


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; raise ``ConfigError`` naming the file and the syntax fault."""
    source = str(path)
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(source, ["file not found; pass an existing file with --config"]) from None
    except PermissionError:
        raise ConfigError(
            source, ["permission denied; make the file readable by the gateway's user"]
        ) from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(source, [f"TOML syntax: {error}"]) from None
    except UnicodeDecodeError:
        raise ConfigError(source, ["not UTF-8 text; save the file as UTF-8"]) from None
    except OSError as error:  # a directory, an I/O error on the medium, ...
        raise ConfigError(source, [f"cannot read: {error.strerror or error}"]) from None


def load_config(path: str | Path) -> GatewayConfig:
    """Read and validate a configuration file."""
    return build_config(read_config_file(path), str(path))
