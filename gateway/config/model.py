"""Configuration: a TOML file and command-line overrides, as frozen, validated dataclasses.

Theory of operation: ``read_config_file`` parses the file, the CLI merges
its flags into the raw tables, and ``build_config`` validates
everything at once, so that one ``ConfigError`` lists every fault with its
file, key and fix instead of stopping at the first. Which keys each table takes, their
defaults, ranges, choices and former names come from the schema (``gateway.schema``); the
builders here add what the schema cannot say (a key one line kind takes, cross-checks).
Nothing here opens a port.
"""

from __future__ import annotations

import difflib
import ipaddress
import math
import os
import string
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from .. import schema
from ..core import pdu as fc
from ..core.ascii import MAX_ASCII_FRAME
from ..core.framing import is_mbap
from ..core.policy import Access, IPNetwork, Rule, lint, merge_ranges
from ..core.redundancy import HEARING_DELAY_S
from ..core.rtu import MAX_RTU_FRAME
from ..core.status_unit import STATUS_LINE
from ..core.timing import character_time, t35, transmission_time
from ..schema import Key, Table, Type

_LINE_KEYS_BY_NAME = schema.keys_of(Table.LINES)


def _default(table: Table, name: str) -> Any:
    """The schema's default for key ``name`` of ``table``: the dataclasses below take their
    defaults from the keys rather than restating them (the schema is the model)."""
    return schema.key(table, name).default


DEFAULT_LISTEN = str(schema.key(Table.SERVER, "listen").default)
#: ``server.max_connections_per_source`` before fair share: a file that still sets it is warned.
OLD_PER_SOURCE_DEFAULT = 16
#: Line kinds reached over the network rather than through a device node.
NETWORK_LINE_KINDS = frozenset({"rtu-over-tcp", "tcp", "tls"})
#: Silence that ends a frame of unknown length on a network link (segments, device servers).
NETWORK_SILENCE_S = 0.05
#: Added to the automatic response timeout of a network line: the round trip and the device
#: server's own buffering.
NETWORK_ALLOWANCE_S = 0.1
#: The IANA port of Modbus/TCP Security.
DEFAULT_TLS_PORT = 802


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
    max_connections: int = _default(Table.SERVER, "max_connections")
    when_full: str = _default(Table.SERVER, "when_full")
    idle_timeout: float = _default(Table.SERVER, "idle_timeout")
    max_pipeline: int = _default(Table.SERVER, "max_pipeline")
    backlog: int = _default(Table.SERVER, "backlog")
    broadcast_reply: bool = _default(Table.SERVER, "broadcast_reply")
    refuse_functions: frozenset[int] = frozenset()
    #: Source networks every listener accepts (empty: any); a listener's own list applies too.
    allow: tuple[IPNetwork, ...] = ()
    #: Every listener refuses anything but reads.
    read_only: bool = _default(Table.SERVER, "read_only")
    #: The policy of the ``listen`` shorthand listener.
    policy: str | None = None
    max_connections_per_source: int = _default(Table.SERVER, "max_connections_per_source")
    evict_min_idle: float = _default(Table.SERVER, "evict_min_idle")
    send_timeout: float = _default(Table.SERVER, "send_timeout")
    #: Seconds a TLS master has to complete its handshake before it is disconnected.
    tls_handshake_timeout: float = _default(Table.SERVER, "tls_handshake_timeout")


@dataclass(frozen=True)
class ListenerConfig:
    """One listening address: ``tcp`` (Modbus TCP), ``tls`` (Modbus/TCP Security) or
    ``rtu-over-tcp`` (RTU frames over TCP)."""

    name: str
    protocol: str = _default(Table.LISTENERS, "protocol")
    host: str = "0.0.0.0"
    port: int = 502
    cert: str | None = None  #: the server's certificate chain (PEM), tls only
    key: str | None = None  #: its private key (PEM), tls only
    ca: str | None = None  #: the CAs client certificates must chain to (PEM), tls only
    crl: str | None = None  #: revocation lists of client certificates (PEM), tls only
    forward_secrecy_only: bool = _default(
        Table.LISTENERS, "forward_secrecy_only"
    )  #: tls: drop the required RSA key-exchange suite
    session_resumption: bool = _default(
        Table.LISTENERS, "session_resumption"
    )  #: tls: session tickets (OpenSSL's 7,200 s lifetime)
    allow: tuple[IPNetwork, ...] = ()  #: source networks accepted (empty: any)
    read_only: bool = _default(Table.LISTENERS, "read_only")
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


#: Where ``metrics.listen = "auto"`` binds, on a port the OS chooses.
AUTO_METRICS_HOST = "127.0.0.1"


@dataclass(frozen=True)
class MetricsConfig:
    """The HTTP endpoint for /metrics, /healthz and /readyz."""

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 9502
    max_connections: int = _default(Table.METRICS, "max_connections")
    header_timeout: float = _default(Table.METRICS, "header_timeout")
    max_connections_per_source: int = _default(Table.METRICS, "max_connections_per_source")
    allowed_hosts: tuple[str, ...] = ()
    status_token: str | None = None
    trace_token: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    tls_ca: str | None = None


@dataclass(frozen=True)
class LoggingConfig:
    """Log level and format."""

    level: str = _default(Table.LOGGING, "level")
    format: str = _default(Table.LOGGING, "format")


@dataclass(frozen=True)
class AuditConfig:
    """Where the audit log goes (``None``: no audit log; ``-``: standard error)."""

    path: str | None = None


@dataclass(frozen=True)
class RedundancyConfig:
    """An active/standby pair on one bus (``peer is None``: the gateway runs alone)."""

    peer: tuple[str, int] | None = None
    peer_modbus: tuple[str, int] | None = None
    priority: int = _default(Table.REDUNDANCY, "priority")
    lease: float = _default(Table.REDUNDANCY, "lease")
    takeover_after: float = _default(Table.REDUNDANCY, "takeover_after")
    #: ``None``: off; ``(0, 0)``: "auto"; else (slave address, holding register).
    keepalive: tuple[int, int] | None = (0, 0)

    @property
    def paired(self) -> bool:
        return self.peer is not None

    @property
    def peer_hosts(self) -> frozenset[str]:
        """The peer's addresses (``peer``'s and ``peer_modbus``'s): where its links come from."""
        return frozenset(address[0] for address in (self.peer, self.peer_modbus) if address)


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
class PollConfig:
    """One ``[[poll]]`` block, resolved through the routes to its line and slave address."""

    unit: int
    function: int
    address: int
    count: int
    every: float
    max_age: float
    line: str = ""
    slave: int = 0
    #: Its place among the ``[[poll]]`` entries (the status unit's registers 2N and 2N+1).
    index: int = 0

    @property
    def key_prefix(self) -> str:
        return f"poll[{self.index}]."

    @property
    def label(self) -> str:
        """How metrics and ``/status`` name the block: ``UNIT:FUNCTION:FIRST-LAST``."""
        return f"{self.unit}:{self.function}:{self.address}-{self.address + self.count - 1}"


@dataclass(frozen=True)
class PollingConfig:
    """``[polling]``: what agent mode's blocks share."""

    status_unit: int = _default(Table.POLLING, "status_unit")
    max_blocks: int = _default(Table.POLLING, "max_blocks")


@dataclass(frozen=True)
class LineConfig:
    """One serial line (RS485 bus) and how to talk on it."""

    name: str
    device: str
    baudrate: int = _default(Table.LINES, "baudrate")
    data_bits: int = _default(Table.LINES, "data_bits")
    parity: str = _default(Table.LINES, "parity")
    stop_bits: float = _default(Table.LINES, "stop_bits")
    timeout: float = 0.367  # auto_timeout(9600): the fixed timeout unless ``learn_timeouts``
    #: ``timeout = "auto"`` (the file's default): each slave's timeout is learned
    #: (``core.line.response_timing``); a line built directly keeps ``timeout`` fixed.
    learn_timeouts: bool = False
    #: Learned timing: the wait for a slave or function never heard from, and the most.
    initial_timeout: float = _default(Table.LINES, "initial_timeout")
    max_timeout: float = _default(Table.LINES, "max_timeout")
    retries: int = _default(Table.LINES, "retries")
    retry_unsafe: bool = _default(Table.LINES, "retry_unsafe")
    frame_gap: float | None = None
    broadcast: bool = _default(Table.LINES, "broadcast")
    broadcast_turnaround: float = _default(Table.LINES, "broadcast_turnaround")
    max_queue: int = _default(Table.LINES, "max_queue")
    max_queue_per_master: int = _default(Table.LINES, "max_queue_per_master")
    #: Seconds a request may wait unsent before it is answered 0x0B (0: no limit).
    max_queue_wait: float = _default(Table.LINES, "max_queue_wait")
    late_answer_window: float | None = None
    noisy_after: float | None = None
    probe_share: float = _default(Table.LINES, "probe_share")
    rs485: bool = _default(Table.LINES, "rs485")
    rs485_rts_level_for_tx: bool = _default(Table.LINES, "rs485_rts_level_for_tx")
    rs485_rts_level_for_rx: bool = _default(Table.LINES, "rs485_rts_level_for_rx")
    rs485_delay_before_tx: float = _default(Table.LINES, "rs485_delay_before_tx")
    rs485_delay_after_tx: float = _default(Table.LINES, "rs485_delay_after_tx")
    units: tuple[int, ...] = ()
    dead_after: int = _default(Table.LINES, "dead_after")
    reconnect_after: int = _default(Table.LINES, "reconnect_after")
    probe_interval: float = _default(Table.LINES, "probe_interval")
    probe_max_interval: float = _default(Table.LINES, "probe_max_interval")
    slave_timeouts: Mapping[int, float] = field(default_factory=dict)
    #: Slave address → the name the status page shows (``names``).
    names: Mapping[int, str] = field(default_factory=dict)
    coalesce: bool = _default(Table.LINES, "coalesce")
    cache: tuple[CacheRule, ...] = ()
    #: Agent mode's blocks on this line (from the top-level ``[[poll]]`` entries).
    polls: tuple[PollConfig, ...] = ()
    #: ``rtu``, ``ascii`` (serial devices) or ``rtu-over-tcp`` (``device`` is then ``HOST:PORT``).
    kind: str = _default(Table.LINES, "kind")
    inter_char_timeout: float = _default(
        Table.LINES, "inter_char_timeout"
    )  # ASCII: a frame whose characters stop this long is dropped
    echo: bool = _default(Table.LINES, "echo")  # the adapter echoes what the gateway sends: drop it
    #: The device server's or slave's address (network kinds; from ``address = "HOST:PORT"``;
    #: a ``tls`` line's address without a port means 802, Modbus/TCP Security's port).
    host: str = ""
    port: int = 0
    #: Seconds to wait after a connection is made before the first request (some device
    #: servers drop what arrives while they set up their serial side).
    connect_delay: float = _default(Table.LINES, "connect_delay")
    #: Seconds a connection attempt to the device server may take.
    connect_timeout: float = _default(Table.LINES, "connect_timeout")
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
    check_server_name: bool = _default(Table.LINES, "check_server_name")
    #: ``kind = "tls"``: seconds the TLS handshake with the slave may take.
    tls_handshake_timeout: float = _default(Table.LINES, "tls_handshake_timeout")
    #: Requests outstanding at once on the connection of an MBAP line (``tcp``, ``tls``);
    #: 1 elsewhere.
    max_in_flight: int = _default(Table.LINES, "max_in_flight")

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
    #: Keys written under a former name: one warning each, naming the new key.
    renamed: tuple[str, ...] = ()
    audit: AuditConfig = field(default_factory=AuditConfig)
    redundancy: RedundancyConfig = field(default_factory=RedundancyConfig)
    #: Agent mode: every ``[[poll]]`` block in the order written, and ``[polling]``.
    polls: tuple[PollConfig, ...] = ()
    polling: PollingConfig = field(default_factory=PollingConfig)

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
        self.renamed: list[str] = []
        #: A key's full name -> the former name it was written under (messages name that).
        self.written_as: dict[str, str] = {}

    def fail(self, key: str, message: str) -> None:
        self.problems.append(f"{self.written_as.get(key, key)}: {message}")

    def unknown_keys(
        self,
        table: Mapping[str, Any],
        known: set[str] | frozenset[str],
        prefix: str,
        suggest: Iterable[str] | None = None,
    ) -> None:
        """Every key not in ``known``, with the closest of ``suggest`` (default: ``known``)."""
        names = sorted(known if suggest is None else suggest)
        for key in table:
            if key not in known:
                close = difflib.get_close_matches(str(key), names, n=1, cutoff=0.6)
                if close:
                    self.fail(f"{prefix}{key}", f"unknown key; did you mean {close[0]!r}?")
                    continue
                choices = ", ".join(names)
                self.fail(f"{prefix}{key}", f"unknown key; known keys here are: {choices}")

    def entry(self, where: Table, table: Mapping[str, Any], prefix: str) -> dict[str, Any]:
        """``table`` checked against the schema's keys of ``where``, former names renamed."""
        self.unknown_keys(table, schema.known_names(where), prefix, schema.keys_of(where))
        entry = dict(table)
        for declared in schema.keys_of(where).values():
            for alias in declared.aliases:
                if alias not in entry:
                    continue
                value = entry.pop(alias)
                if declared.name in entry:
                    self.fail(
                        f"{prefix}{alias}",
                        f"is the former name of {declared.name}; keep only {declared.name}",
                    )
                    continue
                entry[declared.name] = value
                self.written_as[f"{prefix}{declared.name}"] = f"{prefix}{alias}"
                self.renamed.append(
                    f"{prefix}{alias}: the former name of {declared.name}, "
                    f"still accepted; rename it to {declared.name}"
                )
        return entry

    def read(self, key: Key, table: Mapping[str, Any], prefix: str, default: Any = None) -> Any:
        """The value of a scalar ``key``, checked against its type and range or choices."""
        fallback: Any = key.default if default is None else default
        if key.type is Type.INTEGER:
            return self.integer(table, key.name, prefix, fallback, *key.int_range())
        if key.type in (Type.SECONDS, Type.NUMBER):
            return self.number(table, key.name, prefix, fallback, *key.float_range())
        if key.type is Type.BOOLEAN:
            return self.boolean(table, key.name, prefix, fallback)
        if key.type is Type.CHOICE:
            choices = tuple(map(str, key.choices))
            upper = all(choice.isupper() for choice in choices)
            return self.choice(table, key.name, prefix, fallback, choices, upper=upper)
        if key.type is Type.ONE_OF:
            return self.one_of(table, key, prefix)
        if key.type in (Type.ADDRESS, Type.ADDRESS_OR_OFF):
            return self.address(table, key.name, prefix, fallback)
        raise TypeError(f"{key.path}: a {key.type.value} is read by its own parser")

    def optional(self, key: Key, table: Mapping[str, Any], prefix: str) -> float | None:
        """A number of seconds, or ``None`` (the default derived from others) when "auto"."""
        if key.name not in table or table[key.name] == "auto":
            return None
        return self.number(table, key.name, prefix, 0.0, *key.float_range())

    def one_of(self, table: Mapping[str, Any], key: Key, prefix: str) -> float:
        """One of the numbers ``key.choices`` (stop bits)."""
        value = table.get(key.name, key.default)
        if value not in key.choices or isinstance(value, bool):
            *most, last = (f"{choice:g}" for choice in map(float, key.choices))
            self.fail(f"{prefix}{key.name}", f"{value!r} is not {', '.join(most)} or {last}")
            return float(str(key.default))
        return float(value)

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


#: Keys only a ``kind = "tls"`` line takes.
_TLS_LINE_KEYS = tuple(k.name for k in _LINE_KEYS_BY_NAME.values() if k.only == 'kind = "tls"')
#: Line keys with a parser of their own (the rest are read as the schema declares them).
_LINE_SPECIAL = frozenset(
    {
        "kind",
        "device",
        "address",
        "baudrate",
        "data_bits",
        "parity",
        "stop_bits",
        "timeout",
        "units",
        "slave_timeouts",
        "names",
        "cache",
        "max_in_flight",
        *_TLS_LINE_KEYS,
    }
)
#: Line keys stored in a field of another name.
_LINE_FIELDS = {"silence": "silence_setting"}
#: ``LineConfig`` fields whose change makes a reload reopen the line (the schema's
#: ``Reload.REOPENS``; ``address`` shows in ``device``).
LINE_PORT_SETTINGS = tuple(
    "device" if k.name == "address" else _LINE_FIELDS.get(k.name, k.name)
    for k in _LINE_KEYS_BY_NAME.values()
    if k.reload is schema.Reload.REOPENS
)


def _scalars(
    check: _Checker, where: Table, table: Mapping[str, Any], prefix: str, skip: Iterable[str]
) -> dict[str, Any]:
    """Every key of ``where`` not in ``skip``, read as the schema declares it."""
    values: dict[str, Any] = {}
    for declared in schema.keys_of(where).values():
        if declared.name in skip:
            continue
        if declared.default == "auto":
            values[declared.name] = check.optional(declared, table, prefix)
        else:
            values[declared.name] = check.read(declared, table, prefix)
    return values


def _function_codes(
    check: _Checker, table: Mapping[str, Any], key: Key, prefix: str
) -> frozenset[int]:
    """A list of function codes (``refuse_functions``)."""
    raw = table.get(key.name, key.default)
    low, high = key.int_range()
    if not isinstance(raw, list) or not all(
        isinstance(code, int) and not isinstance(code, bool) and low <= code <= high for code in raw
    ):
        check.fail(
            f"{prefix}{key.name}", f"write a list of function codes {low}..{high}, like [8, 17]"
        )
        return frozenset()
    return frozenset(raw)


def _build_server(check: _Checker, raw: Mapping[str, Any]) -> ServerConfig:
    prefix = "server."
    table = check.entry(Table.SERVER, check.table(raw, "server"), prefix)
    keys = schema.keys_of(Table.SERVER)
    listen = check.read(keys["listen"], table, prefix) or parse_host_port(DEFAULT_LISTEN)
    return ServerConfig(
        host=listen[0],
        port=listen[1],
        refuse_functions=_function_codes(check, table, keys["refuse_functions"], prefix),
        allow=_networks(check, table, "allow", prefix),
        policy=_policy_name(check, table, prefix),
        **_scalars(
            check, Table.SERVER, table, prefix, ("listen", "refuse_functions", "allow", "policy")
        ),
    )


def _line_kind(check: _Checker, table: Mapping[str, Any], prefix: str) -> tuple[str, str, str, int]:
    """The line's kind, its device (or shown address), and a network line's host and port."""
    kind: str = check.read(_LINE_KEYS_BY_NAME["kind"], table, prefix)
    host, port = "", 0
    device = table.get("device")
    if kind in NETWORK_LINE_KINDS:
        host, port, device = _network_address(check, table, prefix, kind)
    elif "address" in table:
        check.fail(
            f"{prefix}address",
            'only a network line takes it (kind = "rtu-over-tcp", '
            f'"tcp" or "tls"); a {kind} line names its serial port with device',
        )
    if kind not in NETWORK_LINE_KINDS and (not isinstance(device, str) or not device):
        check.fail(
            f"{prefix}device",
            'missing; set the serial device or URL, like "/dev/ttyUSB0" '
            'or "socket://10.0.0.5:4001"',
        )
    return kind, device if isinstance(device, str) else "", host, port


def _serial_format(
    check: _Checker, where: Table, table: Mapping[str, Any], prefix: str, ascii_line: bool
) -> dict[str, Any]:
    """Baud rate, data bits, parity and stop bits (7E1 by default on an ASCII line:
    Modbus over Serial Line 2.5.2.1)."""
    keys = schema.keys_of(where)
    return {
        "baudrate": check.read(keys["baudrate"], table, prefix),
        "data_bits": check.read(keys["data_bits"], table, prefix, 7 if ascii_line else 8),
        "parity": check.read(keys["parity"], table, prefix, "E" if ascii_line else "N"),
        "stop_bits": check.read(keys["stop_bits"], table, prefix),
    }


def _line_timeout(
    check: _Checker, table: Mapping[str, Any], prefix: str, kind: str, form: Mapping[str, Any]
) -> float:
    """``timeout``: the seconds written, or "auto" (see ``auto_timeout``)."""
    longest = MAX_ASCII_FRAME if kind == "ascii" else MAX_RTU_FRAME
    timeout = auto_timeout(
        form["baudrate"], form["data_bits"], form["parity"], form["stop_bits"], longest
    )
    if kind in NETWORK_LINE_KINDS:
        timeout = round(timeout + NETWORK_ALLOWANCE_S, 3)
    if table.get("timeout", "auto") != "auto":
        timeout = check.read(_LINE_KEYS_BY_NAME["timeout"], table, prefix, timeout)
    return timeout


def _build_line(check: _Checker, name: str, raw: Mapping[str, Any]) -> LineConfig | None:
    prefix = f"lines.{name}."
    if not isinstance(raw, dict):
        check.fail(f"lines.{name}", "must be a table ([lines.NAME]) with at least a device")
        return None
    table = check.entry(Table.LINES, raw, prefix)
    kind, device, host, port = _line_kind(check, table, prefix)
    form = _serial_format(check, Table.LINES, table, prefix, kind == "ascii")
    units: tuple[int, ...] = ()
    if "units" in table:
        try:
            units = tuple(parse_units(table["units"]))
        except ValueError as error:
            check.fail(f"{prefix}units", str(error))
    scalars = _scalars(check, Table.LINES, table, prefix, _LINE_SPECIAL)
    return LineConfig(
        name=name,
        device=device,
        kind=kind,
        host=host,
        port=port,
        units=units,
        timeout=_line_timeout(check, table, prefix, kind, form),
        learn_timeouts=table.get("timeout", "auto") == "auto",
        slave_timeouts=_slave_timeouts(check, table, prefix),
        names=_slave_names(check, table, prefix),
        cache=_cache_rules(check, table, prefix),
        max_in_flight=_max_in_flight(check, table, prefix, kind),
        **form,
        **{_LINE_FIELDS.get(key, key): value for key, value in scalars.items()},
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
                check.fail(
                    f"{prefix}{key}",
                    f'only a kind = "tls" line takes it; remove it from this {kind} line',
                )
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
            check.fail(
                f"{prefix}{key}",
                f"{fix}; a tls line needs {description} (or --modbus-tls-{key} FILE)",
            )
            value = None
        files[key] = value
    server_name = table.get("server_name", host)
    if not isinstance(server_name, str) or not server_name:
        check.fail(
            f"{prefix}server_name",
            "write the name the slave's certificate carries, "
            'like "plc-7.plant.example" (default: the address\'s host)',
        )
        server_name = host
    elif not _usable_server_name(server_name):
        check.fail(
            f"{prefix}server_name",
            f"{server_name!r} is not a host name or address; "
            "write the name the slave's certificate carries, like "
            '"plc-7.plant.example"',
        )
        server_name = host
    return {
        **files,
        "server_name": server_name,
        "check_server_name": check.read(_LINE_KEYS_BY_NAME["check_server_name"], table, prefix),
        "tls_handshake_timeout": check.read(
            _LINE_KEYS_BY_NAME["tls_handshake_timeout"], table, prefix
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
    return int(check.read(_LINE_KEYS_BY_NAME["max_in_flight"], table, prefix))


def _network_address(
    check: _Checker, table: Mapping[str, Any], prefix: str, kind: str
) -> tuple[str, int, str]:
    """``address = "HOST:PORT"`` of a network line: host, port and the text shown as its device."""
    if "device" in table:
        check.fail(
            f"{prefix}device",
            f'a {kind} line is reached at address = "HOST:PORT", '
            "not a device; rename the key to address",
        )
    value = table.get("address")
    if kind == "tls" and isinstance(value, str) and value and not _has_port(value):
        value = f"{value}:{DEFAULT_TLS_PORT}"  # Modbus/TCP Security's own port
    if not isinstance(value, str) or not value:
        check.fail(
            f"{prefix}address",
            f'missing; a {kind} line needs the device server\'s address, like "10.0.0.5:4001"',
        )
        return "", 0, ""
    try:
        host, port = parse_host_port(value)
    except ValueError as error:
        check.fail(f"{prefix}address", str(error))
        return "", 0, ""
    if port == 0 or host in ("0.0.0.0", "::"):
        check.fail(
            f"{prefix}address",
            f"{value!r} is not a place to connect to; "
            'write the device server\'s address, like "10.0.0.5:4001"',
        )
        return "", 0, ""
    shown = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    return host, port, shown


#: Time a slave is given to start its answer, on top of the longest answer's transmission.
SLAVE_TURNAROUND_S = 0.1


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
        low, high = _LINE_KEYS_BY_NAME["timeout"].float_range()
        timeouts[int(slave_text)] = check.number(raw, slave_text, f"{key}.", 1.0, low, high)
    return timeouts


#: The longest slave name ``names`` takes (a status page cell, not a document).
MAX_NAME_LENGTH = 64


def _slave_names(check: _Checker, table: Mapping[str, Any], prefix: str) -> dict[int, str]:
    """``names = { "1" = "plc" }``: keyed by slave address, as ``slave_timeouts`` is."""
    raw = table.get("names", {})
    key = f"{prefix}names"
    if not isinstance(raw, dict):
        check.fail(key, 'write a table of slave = name, like { "1" = "plc" }')
        return {}
    names: dict[int, str] = {}
    for slave_text, name in raw.items():
        if not slave_text.isdigit() or not 1 <= int(slave_text) <= 247:
            check.fail(f"{key}.{slave_text}", "the key must be a slave address 1..247, quoted")
        elif not isinstance(name, str) or not name.strip() or len(name) > MAX_NAME_LENGTH:
            check.fail(
                f"{key}.{slave_text}",
                f"{name!r} is not a name of 1..{MAX_NAME_LENGTH} characters in quotes",
            )
        else:
            names[int(slave_text)] = name.strip()
    return names


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
        entry = check.entry(Table.CACHE, entry, entry_key)
        values = _scalars(check, Table.CACHE, entry, entry_key, ())
        if values["function"] in _CACHE_FUNCTIONS:
            rules.append(CacheRule(**values))
    return tuple(rules)


#: The most items one read may ask for, by function (the application protocol's limits).
_READ_LIMITS = {1: 2000, 2: 2000, 3: 125, 4: 125}


def _build_polling(
    check: _Checker,
    raw: Mapping[str, Any],
    routes: Mapping[int, Route],
    lines: tuple[LineConfig, ...],
) -> PollingConfig:
    prefix = "polling."
    table = check.entry(Table.POLLING, check.table(raw, "polling"), prefix)
    config = PollingConfig(**_scalars(check, Table.POLLING, table, prefix, ()))
    if config.status_unit and config.status_unit in routes:
        route = routes[config.status_unit]
        check.fail(
            f"{prefix}status_unit",
            f"unit {config.status_unit} is routed to line "
            f"{route.line!r}; choose an unrouted unit id (248-255 are never routed by "
            "--serial) or 0 for off",
        )
    if config.status_unit and any(line.name == STATUS_LINE for line in lines):
        check.fail(
            f"lines.{STATUS_LINE}",
            f"the status unit's answers are counted as line {STATUS_LINE!r}; rename the "
            "line, or set polling.status_unit = 0",
        )
    return config


def _build_polls(
    check: _Checker, raw: Mapping[str, Any], routes: Mapping[int, Route], polling: PollingConfig
) -> tuple[PollConfig, ...]:
    """The ``[[poll]]`` blocks, each resolved to its line and slave through the routes."""
    entries = raw.get("poll", [])
    if not isinstance(entries, list):
        check.fail("poll", "write [[poll]] tables with unit, function, address, count, every")
        return ()
    if len(entries) > polling.max_blocks:
        check.fail(
            "poll",
            f"{len(entries)} blocks, more than polling.max_blocks = "
            f"{polling.max_blocks}; merge blocks or raise polling.max_blocks",
        )
    blocks: list[PollConfig] = []
    for index, entry in enumerate(entries):
        prefix = f"poll[{index}]."
        if not isinstance(entry, dict):
            check.fail(f"poll[{index}]", "must be a table with unit, function, address, count")
            continue
        entry = check.entry(Table.POLL, entry, prefix)
        for required in ("unit", "count"):
            if required not in entry:
                check.fail(
                    f"{prefix}{required}", "missing; " + schema.key(Table.POLL, required).help
                )
        if "unit" not in entry or "count" not in entry:
            continue
        values = _scalars(check, Table.POLL, entry, prefix, ())
        function, address, count = values["function"], values["address"], values["count"]
        if count is None or values["unit"] is None:
            continue  # out of its range: said already
        limit = _READ_LIMITS[function]
        if count > limit:
            items = "bits" if function in (1, 2) else "registers"
            check.fail(
                f"{prefix}count",
                f"{count} is more than function {function} reads at "
                f"once ({limit} {items}); split the block in two",
            )
            continue
        if address + count > 65536:
            check.fail(
                f"{prefix}count",
                f"address {address} + count {count} runs past 65535; lower count or address",
            )
            continue
        every = values["every"]
        max_age = values["max_age"] if values["max_age"] is not None else 3.0 * every
        if max_age < every:
            check.fail(
                f"{prefix}max_age",
                f"{max_age:g} s is shorter than every = {every:g} s: "
                "the block would be stale between polls; set max_age >= every",
            )
            continue
        route = routes.get(values["unit"])
        if route is None:
            check.fail(
                f"{prefix}unit",
                f"unit {values['unit']} is not routed; add it to a "
                "line's units or a [[routes]] entry, or poll a routed unit",
            )
            continue
        block = PollConfig(
            values["unit"], function, address, count, every, max_age, route.line, route.slave, index
        )
        for other in blocks:
            if (
                (other.line, other.slave, other.function) == (block.line, block.slave, function)
                and other.address < address + count
                and address < other.address + other.count
            ):
                check.fail(
                    f"{prefix}address",
                    f"the block overlaps poll[{other.index}] "
                    f"({other.label}) on the same slave and function; make them "
                    "adjacent or merge them",
                )
                break
        else:
            blocks.append(block)
    return tuple(blocks)


def _build_routes(
    check: _Checker, raw: Mapping[str, Any], lines: tuple[LineConfig, ...]
) -> dict[int, Route]:
    """Each line's ``units`` (the same slave address), then every ``[[routes]]`` entry."""
    routes: dict[int, Route] = {}
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
    names = {line.name for line in lines}
    for index, entry in enumerate(raw_routes):
        route = _route(check, entry, f"routes[{index}]", names)
        if route is None:
            continue
        if route.unit in routes:
            check.fail(
                f"routes[{index}].unit",
                f"unit {route.unit} is already routed to line {routes[route.unit].line!r}",
            )
            continue
        routes[route.unit] = route
    return routes


def _route(check: _Checker, raw: Any, key: str, names: set[str]) -> Route | None:
    """One ``[[routes]]`` entry (``None`` when it is faulty)."""
    if not isinstance(raw, dict):
        check.fail(key, "must be a table with unit, line and slave")
        return None
    prefix = f"{key}."
    entry = check.entry(Table.ROUTES, raw, prefix)
    keys = schema.keys_of(Table.ROUTES)
    unit = check.read(keys["unit"], entry, prefix, -1) if "unit" in entry else -1
    if "unit" not in entry:
        check.fail(f"{prefix}unit", "missing; the TCP unit id (1..255) this route answers for")
    line_name = entry.get("line")
    if not isinstance(line_name, str) or line_name not in names:
        known = ", ".join(sorted(names)) or "(none defined)"
        check.fail(f"{prefix}line", f"{line_name!r} is not a configured line; lines are: {known}")
        return None
    slave = check.read(keys["slave"], entry, prefix, unit if 1 <= unit <= 247 else 1)
    return Route(unit, line_name, slave) if unit >= 1 else None


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
    warnings = list(config.renamed)
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
    if server.max_connections_per_source == OLD_PER_SOURCE_DEFAULT:
        warnings.append(
            f"server.max_connections_per_source: {OLD_PER_SOURCE_DEFAULT} was the default "
            "(the example file spelled it out); the default is now 0, no cap: at "
            "max_connections the address holding the most connections yields its longest-idle "
            "one. A cap of 16 refuses SCADA and OPC servers that open one connection per "
            "device; delete the line unless you mean to cap each address"
        )
    warnings += _poll_plan_warnings(config)
    return warnings + _endpoint_warnings(metrics) + _pair_warnings(config)


def poll_plan_share(line: LineConfig) -> float:
    """The share of ``line``'s wire time its poll plan needs: each block's request and
    answer frames with the silences around them, times its polls a second. 0.0 on a Modbus
    TCP or TLS line: its frames take no serial time."""
    if is_mbap(line.kind):
        return 0.0
    form = (line.baudrate, line.data_bits, line.parity, line.stop_bits)
    gap = line.frame_gap if line.frame_gap is not None else t35(*form)
    share = 0.0
    for block in line.polls:
        answer_bytes = (block.count + 7) // 8 if block.function in (1, 2) else 2 * block.count
        request, answer = 6, 3 + answer_bytes  # unit, PDU; unit, function, byte count, data
        if line.kind == "ascii":  # ':', two hex digits a byte, the LRC's two, CR LF
            request, answer = 1 + 2 * (request + 1) + 2, 1 + 2 * (answer + 1) + 2
        else:
            request, answer = request + 2, answer + 2  # the CRC
        wire = transmission_time(request + answer, *form) + 2 * gap
        share += wire / block.every
    return share


def _poll_plan_warnings(config: GatewayConfig) -> list[str]:
    """A line whose poll plan needs more than half its wire time leaves masters little."""
    warnings: list[str] = []
    for line in config.lines:
        share = poll_plan_share(line)
        if share > 0.5:
            warnings.append(
                f"poll: the blocks on line {line.name!r} need {share:.0%} of its wire time at "
                f"{line.baudrate} baud (more than half): masters' requests that memory cannot "
                "answer wait behind the polls; raise every, merge blocks, or poll fewer"
            )
    return warnings


def _endpoint_warnings(metrics: MetricsConfig) -> list[str]:
    """An HTTP endpoint whose documented protections are half set up, or not at all."""
    warnings: list[str] = []
    if not metrics.enabled:
        return warnings
    if metrics.status_token is not None and metrics.trace_token is None:
        warnings.append(
            "metrics.trace_token: not set while status_token is: /status and the page ask "
            "for a token, /trace (which carries register values) asks for none; set "
            'trace_token too (docs/http-endpoint.md, "Tokens")'
        )
    tokens = metrics.status_token is not None or metrics.trace_token is not None
    if not is_loopback(metrics.host) and not tokens and metrics.tls_cert is None:
        shown = metrics.host or "every address"
        warnings.append(
            f"metrics.listen: {shown} is reachable from the network, with neither "
            "status_token nor trace_token nor HTTPS (tls_cert): anyone who reaches it reads "
            "/status and /trace (register values) in clear; set the tokens and tls_cert, "
            "tls_key, or listen on 127.0.0.1"
        )
    return warnings


def _pair_warnings(config: GatewayConfig) -> list[str]:
    """A pair whose gateways cannot reach each other, that names its peer by name, or
    whose active lets the bus fall silent."""
    pair = config.redundancy
    if pair.peer is None:
        return []
    warnings: list[str] = []
    if pair.keepalive is None:
        warnings.append(
            'redundancy.keepalive: "off": an active with nothing to send lets its lease end '
            "half a lease after its last frame, steps down, and the pair takes turns on an "
            'idle bus (each takeover costs masters 1.5 to 2.5 s); write "auto", or '
            '"SLAVE:REGISTER" to name the register it reads'
        )
    remote = not is_loopback(pair.peer[0])
    if remote and is_loopback(config.metrics.host):
        warnings.append(
            f"metrics.listen: {config.metrics.host} is a loopback address: the peer at "
            f"{pair.peer[0]} cannot poll this gateway's /role; listen on an address it "
            "reaches"
        )
    if remote and is_loopback(config.server.host):
        warnings.append(
            f"server.listen: {config.server.host} is a loopback address: the peer cannot "
            "forward its masters' requests here while it stands by; listen on an address it "
            "reaches"
        )
    for key, (host, _) in (("peer", pair.peer), ("peer_modbus", pair.peer_modbus or pair.peer)):
        try:
            ipaddress.ip_address(host)
        except ValueError:
            warnings.append(
                f"redundancy.{key}: {host} is a name: write the peer's IP address (a standby "
                "refuses to forward requests that come from its peer's address, which it "
                "compares as written)"
            )
    return warnings


#: Names that always mean this machine (a rebinding page cannot send them as its Host).
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost"})


def is_loopback(name: str) -> bool:
    """True for a loopback name or address (``127.0.0.0/8``, ``::1``, ``*.localhost``)."""
    if name in LOOPBACK_NAMES or name.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


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
_RULE_KEYS = {"role", "source", "units", "line", "slave", "functions", "addresses", "access"}


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


def _rule_numbers(
    check: _Checker, entry: Mapping[str, Any], key: str, prefix: str, low: int, high: int, what: str
) -> frozenset[int] | None:
    """A rule's ``units`` or ``slave``: numbers and ranges; ``None`` when not written."""
    if key not in entry:
        return None
    try:
        spans = _ranges(entry[key], low, high)
    except ValueError as error:
        check.fail(f"{prefix}{key}", f"{error} ({what})")
        return None
    return frozenset(number for first, last in spans for number in range(first, last + 1))


def _rule_lines(check: _Checker, entry: Mapping[str, Any], prefix: str) -> frozenset[str] | None:
    """A rule's ``line``: one line name or a list of them; ``None`` when not written."""
    if "line" not in entry:
        return None
    value = entry["line"]
    names = [value] if isinstance(value, str) else value
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        check.fail(f"{prefix}line", 'write a line name or a list of them, like "a" or ["a", "b"]')
        return None
    return frozenset(names)


def _build_rule(check: _Checker, entry: Any, key: str) -> Rule | None:
    if not isinstance(entry, dict):
        check.fail(
            key,
            "must be a table with role, source, units, line, slave, functions, addresses, access",
        )
        return None
    prefix = f"{key}."
    check.unknown_keys(entry, _RULE_KEYS, prefix)
    role = entry.get("role")
    if role is not None and (not isinstance(role, str) or not role):
        check.fail(f"{prefix}role", 'write the role as a non-empty string, like "operator"')
        role = None
    units = _rule_numbers(check, entry, "units", prefix, 0, 255, "0 is broadcast, 1..255 unit ids")
    slaves = _rule_numbers(check, entry, "slave", prefix, 1, 247, "slave addresses 1..247")
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
        lines=_rule_lines(check, entry, prefix),
        slaves=slaves,
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


_LISTENER_TABLE = schema.keys_of(Table.LISTENERS)
#: Keys of a ``serial-slave`` listener only: its serial line, and the units it answers for.
_SERIAL_SLAVE_KEYS = frozenset(
    k.name for k in _LISTENER_TABLE.values() if k.only.startswith('protocol = "serial-slave"')
)
#: What a tls listener's files hold, for the message when one is missing.
_LISTENER_FILES = {
    "cert": "the server's certificate chain (PEM)",
    "key": "the server's private key (PEM)",
    "ca": "the CA certificates client certificates must chain to (PEM)",
}


def _serial_slave_line(
    check: _Checker, entry: Mapping[str, Any], prefix: str, name: str
) -> tuple[LineConfig, tuple[int, ...]]:
    """The serial line of a ``serial-slave`` listener, and the units it answers for."""
    device = entry.get("device")
    if not isinstance(device, str) or not device:
        check.fail(
            f"{prefix}device",
            "missing; a serial-slave listener answers on a serial "
            'device, like "/dev/ttyUSB1" (or --serial-slave DEVICE)',
        )
        device = ""
    if "listen" in entry:
        check.fail(f"{prefix}listen", "a serial-slave listener has a device, not an address")
    units: tuple[int, ...] = ()
    if "units" in entry:
        try:
            units = tuple(parse_units(entry["units"]))
        except ValueError as error:
            check.fail(f"{prefix}units", str(error))
    framing: str = check.read(_LISTENER_TABLE["framing"], entry, prefix)
    ascii_line = framing == "ascii"
    line = LineConfig(
        name=f"listener {name}",
        device=device,
        kind=framing,
        inter_char_timeout=check.read(_LISTENER_TABLE["inter_char_timeout"], entry, prefix),
        echo=check.read(_LISTENER_TABLE["echo"], entry, prefix),
        **_serial_format(check, Table.LISTENERS, entry, prefix, ascii_line),
    )
    if "inter_char_timeout" in entry and not ascii_line:
        check.fail(
            f"{prefix}inter_char_timeout",
            'only an ASCII line has one (framing = "ascii"); an RTU frame ends on t3.5 of silence',
        )
    return line, units


def _shorthand_listener(
    check: _Checker, raw: Mapping[str, Any], server: ServerConfig, entries: list[Any]
) -> list[ListenerConfig]:
    """The ``[server] listen`` listener: when written (or ``--listen`` given), or when no
    other network listener is configured, as before listeners existed (a ``serial-slave``
    listener does not replace it)."""
    networked = [
        e for e in entries if not (isinstance(e, dict) and e.get("protocol") == "serial-slave")
    ]
    if "listen" not in check.table(raw, "server") and networked:
        return []
    return [
        ListenerConfig(
            name="tcp",
            protocol="tcp",
            host=server.host,
            port=server.port,
            read_only=server.read_only,
            policy=server.policy,
        )
    ]


def _listener_files(
    check: _Checker, entry: Mapping[str, Any], prefix: str, protocol: str
) -> dict[str, Any]:
    """``cert``, ``key`` and ``ca``: required on a tls listener, refused on any other."""
    files: dict[str, str | None] = {}
    for file_key, what in _LISTENER_FILES.items():
        value = entry.get(file_key)
        if value is not None and (not isinstance(value, str) or not value):
            check.fail(f"{prefix}{file_key}", "write a file path as a string")
            value = None
        if protocol == "tls" and value is None:
            check.fail(
                f"{prefix}{file_key}",
                f"missing; a tls listener needs {what} (or --tls-{file_key} FILE)",
            )
        if protocol != "tls" and value is not None:
            check.fail(f"{prefix}{file_key}", 'only a protocol = "tls" listener takes it')
        files[file_key] = value
    return files


def _listener(check: _Checker, raw: Any, index: int, server: ServerConfig) -> ListenerConfig | None:
    """One ``[[listeners]]`` entry (``None`` when it is not even a table)."""
    key = f"listeners[{index}]"
    if not isinstance(raw, dict):
        check.fail(key, "must be a table with name, protocol and listen")
        return None
    prefix = f"{key}."
    entry = check.entry(Table.LISTENERS, raw, prefix)
    protocol: str = check.read(_LISTENER_TABLE["protocol"], entry, prefix)
    name = entry.get("name", protocol)
    if not isinstance(name, str) or not name.replace("-", "_").isidentifier():
        check.fail(f"{prefix}name", f"{name!r}: write a short name of letters, digits, - or _")
        name = f"listener{index}"
    common: dict[str, Any] = {
        "name": name,
        "protocol": protocol,
        "key_prefix": prefix,
        "read_only": check.read(_LISTENER_TABLE["read_only"], entry, prefix) or server.read_only,
        "policy": _policy_name(check, entry, prefix),
    }
    if protocol == "serial-slave":
        serial, units = _serial_slave_line(check, entry, prefix, name)
        for other in ("cert", "key", "ca", "crl", "allow"):
            if other in entry:
                check.fail(
                    f"{prefix}{other}", "a serial-slave listener has no network peers: remove it"
                )
        return ListenerConfig(host="", port=0, serial=serial, units=units, **common)
    for serial_key in sorted(_SERIAL_SLAVE_KEYS & set(entry)):
        check.fail(f"{prefix}{serial_key}", 'only a protocol = "serial-slave" listener takes it')
    default_port = DEFAULT_TLS_PORT if protocol == "tls" else 502
    address = check.address(entry, "listen", prefix, f"0.0.0.0:{default_port}")
    if address is None:
        check.fail(f"{prefix}listen", 'a listener needs an address; write it like "0.0.0.0:802"')
        address = ("0.0.0.0", default_port)
    return ListenerConfig(
        host=address[0],
        port=address[1],
        allow=_networks(check, entry, "allow", prefix),
        **_listener_files(check, entry, prefix, protocol),
        **_listener_tls(check, entry, prefix, protocol),
        **common,
    )


def _listener_tls(
    check: _Checker, entry: Mapping[str, Any], prefix: str, protocol: str
) -> dict[str, Any]:
    """``crl``, ``forward_secrecy_only``, ``session_resumption``: a tls listener's options."""
    names = ("crl", "forward_secrecy_only", "session_resumption")
    if protocol != "tls":
        for name in names:
            if name in entry:
                check.fail(f"{prefix}{name}", 'only a protocol = "tls" listener takes it')
        return {}
    crl = entry.get("crl")
    if crl is not None and (not isinstance(crl, str) or not crl):
        check.fail(f"{prefix}crl", "write a file path as a string")
        crl = None
    return {
        "crl": crl,
        **{name: check.read(_LISTENER_TABLE[name], entry, prefix) for name in names[1:]},
    }


def _check_listeners(
    check: _Checker, listeners: list[ListenerConfig], policies: Mapping[str, tuple[Rule, ...]]
) -> None:
    """Names unique, policies defined, one listener per address."""
    seen: dict[str, ListenerConfig] = {}
    for listener in listeners:
        if listener.name in seen:
            check.fail(
                f"{listener.key_prefix}name",
                f"{listener.name!r} is used by another listener; give each listener its own name",
            )
        seen[listener.name] = listener
        if listener.policy is not None and listener.policy not in policies:
            known = ", ".join(sorted(policies)) or "(none defined)"
            check.fail(
                f"{listener.key_prefix}policy",
                f"{listener.policy!r} is not a [policies.NAME] table; policies are: {known}",
            )
    addresses = [(lst.host, lst.port) for lst in listeners if lst.port != 0]
    for address in set(addresses):
        if addresses.count(address) > 1:
            check.fail(
                "listeners", f"two listeners on {address[0]}:{address[1]}; give each its own port"
            )


def _build_listeners(
    check: _Checker,
    raw: Mapping[str, Any],
    server: ServerConfig,
    policies: Mapping[str, tuple[Rule, ...]],
) -> tuple[ListenerConfig, ...]:
    """``[server] listen`` (the shorthand tcp listener) and every ``[[listeners]]`` entry."""
    entries = raw.get("listeners", [])
    if not isinstance(entries, list):
        check.fail("listeners", "write listeners as [[listeners]] tables")
        entries = []
    listeners = _shorthand_listener(check, raw, server, entries)
    for index, entry in enumerate(entries):
        listener = _listener(check, entry, index, server)
        if listener is not None:
            listeners.append(listener)
    _check_listeners(check, listeners, policies)
    return tuple(listeners)


#: What a token may hold: it travels unencoded in a header, a cookie and a link.
_TOKEN_CHARACTERS = frozenset(string.ascii_letters + string.digits + "-._~")
#: The ``[metrics]`` keys that hold text: host names, tokens, file paths.
_METRICS_TEXT = ("allowed_hosts", "status_token", "trace_token", "tls_cert", "tls_key", "tls_ca")


def _metrics_text(check: _Checker, table: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """The endpoint's host names, tokens and TLS files, checked."""
    values: dict[str, Any] = {}
    hosts = table.get("allowed_hosts", [])
    if not isinstance(hosts, list) or not all(isinstance(h, str) and h for h in hosts):
        check.fail(f"{prefix}allowed_hosts", 'write a list of host names, like ["gw.example"]')
        hosts = []
    values["allowed_hosts"] = tuple(h.lower().rstrip(".") for h in hosts)
    for name in _METRICS_TEXT[1:]:
        value = table.get(name)
        if value is not None and (not isinstance(value, str) or not value):
            check.fail(f"{prefix}{name}", "write a non-empty string")
            value = None
        values[name] = value
    for name in ("status_token", "trace_token"):
        token = values[name]
        if token is not None and not all(c in _TOKEN_CHARACTERS for c in token):
            check.fail(
                f"{prefix}{name}",
                "use letters, digits and - . _ ~ only (it travels "
                "in a header, a cookie and a link unencoded)",
            )
        elif token is not None and len(token) < 16:
            check.fail(
                f"{prefix}{name}",
                "too short to resist guessing; use 16 characters "
                "or more, like the output of: openssl rand -hex 16",
            )
    if (values["tls_cert"] is None) != (values["tls_key"] is None):
        check.fail(f"{prefix}tls_cert", "HTTPS needs both tls_cert and tls_key")
    if values["tls_ca"] is not None and values["tls_cert"] is None:
        check.fail(f"{prefix}tls_ca", "client certificates need HTTPS: set tls_cert and tls_key")
    return values


def _build_metrics(check: _Checker, raw: Mapping[str, Any]) -> MetricsConfig:
    prefix = "metrics."
    table = check.entry(Table.METRICS, check.table(raw, "metrics"), prefix)
    values = _scalars(check, Table.METRICS, table, prefix, ("listen", *_METRICS_TEXT))
    values.update(_metrics_text(check, table, prefix))
    if str(table.get("listen", "")).lower() == "auto":  # a free port the OS picks, logged
        return MetricsConfig(True, AUTO_METRICS_HOST, 0, **values)
    address = check.read(schema.key(Table.METRICS, "listen"), table, prefix)
    if address is None:  # "off"
        return MetricsConfig(False, **values)
    return MetricsConfig(True, address[0], address[1], **values)


def _build_logging(check: _Checker, raw: Mapping[str, Any]) -> LoggingConfig:
    prefix = "logging."
    table = check.entry(Table.LOGGING, check.table(raw, "logging"), prefix)
    return LoggingConfig(**_scalars(check, Table.LOGGING, table, prefix, ()))


def _build_audit(check: _Checker, raw: Mapping[str, Any]) -> AuditConfig:
    prefix = "audit."
    table = check.entry(Table.AUDIT, check.table(raw, "audit"), prefix)
    path = table.get("path")
    if path is not None and (not isinstance(path, str) or not path):
        check.fail(f"{prefix}path", 'write a file path, as a string ("-": standard error)')
        path = None
    return AuditConfig(path)


def _build_redundancy(check: _Checker, raw: Mapping[str, Any]) -> RedundancyConfig:
    prefix = "redundancy."
    table = check.entry(Table.REDUNDANCY, check.table(raw, "redundancy"), prefix)
    values = _scalars(check, Table.REDUNDANCY, table, prefix, ("keepalive", "peer", "peer_modbus"))
    for name in ("peer", "peer_modbus"):
        if name in table:
            key = schema.key(Table.REDUNDANCY, name)
            values[name] = check.read(key, table, prefix, default="127.0.0.1:0")
    keepalive = _keepalive(check, table.get("keepalive", "auto"), prefix)
    config = RedundancyConfig(**values, keepalive=keepalive)
    if config.peer is not None and config.peer_modbus is None:
        check.fail(
            f"{prefix}peer_modbus",
            "set the peer's Modbus TCP listener, HOST:PORT, "
            "where a standby forwards its masters' requests",
        )
    if config.peer is None and config.peer_modbus is not None:
        check.fail(
            f"{prefix}peer",
            "set the peer's HTTP endpoint, HOST:PORT, or remove peer_modbus: a pair needs both",
        )
    if config.takeover_after <= config.lease + HEARING_DELAY_S:
        check.fail(
            f"{prefix}takeover_after",
            f"must be longer than the lease plus "
            f"{HEARING_DELAY_S:g} s ({config.lease + HEARING_DELAY_S:g} s): "
            "the active's frames must reach the standby before its wait ends",
        )
    return config


def _keepalive(check: _Checker, value: object, prefix: str) -> tuple[int, int] | None:
    """``"auto"``, ``"off"`` or ``"SLAVE:REGISTER"``."""
    if value == "off":
        return None
    if value == "auto":
        return (0, 0)
    if isinstance(value, str):
        slave, _, register = value.partition(":")
        digits = slave.isdigit() and register.isdigit()
        if digits and 1 <= int(slave) <= 247 and 0 <= int(register) <= 65535:
            return int(slave), int(register)
    check.fail(
        f"{prefix}keepalive",
        'write "auto", "off", or "SLAVE:REGISTER" with a slave '
        'address 1..247 and a holding register 0..65535, like "1:0"',
    )
    return (0, 0)


def build_config(raw: Mapping[str, Any], source: str = "<command line>") -> GatewayConfig:
    """Validate raw tables into a ``GatewayConfig``; raise ``ConfigError`` listing every fault."""
    check = _Checker()
    check.unknown_keys(raw, set(schema.TOP_LEVEL), "")
    server = _build_server(check, raw)
    metrics = _build_metrics(check, raw)
    log = _build_logging(check, raw)
    audit = _build_audit(check, raw)
    redundancy = _build_redundancy(check, raw)
    if redundancy.paired and not metrics.enabled:
        check.fail(
            "metrics.listen",
            "a redundancy pair polls each other's HTTP endpoint "
            "(GET /role): set it to an address the peer reaches, not off",
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
    polling = _build_polling(check, raw, routes, lines)
    polls = _build_polls(check, raw, routes, polling)
    lines = tuple(
        replace(line, polls=tuple(block for block in polls if block.line == line.name))
        for line in lines
    )
    policies = _build_policies(check, raw)
    listeners = _build_listeners(check, raw, server, policies)
    _check_shared_devices(check, lines)
    _check_serial_slave_devices(check, lines, listeners)
    if check.problems:
        raise ConfigError(source, check.problems)
    return GatewayConfig(
        server,
        metrics,
        log,
        lines,
        routes,
        source,
        listeners,
        policies,
        tuple(check.renamed),
        audit,
        redundancy,
        polls,
        polling,
    )


def policy_warnings(config: GatewayConfig) -> list[str]:
    """Rules that can never grant anything, unused policies, tls listeners without a policy."""
    warnings: list[str] = []
    status_unit = config.polling.status_unit
    own_units = frozenset({status_unit}) if status_unit else frozenset()
    used = {listener.policy for listener in config.listeners}
    for name in config.policies:
        if name not in used:
            warnings.append(
                f"policies.{name}: no listener uses it; set policy = {name!r} on "
                "a listener ([server] or [[listeners]]) or remove it"
            )
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
            warnings.append(
                f"policies.{listener.policy}: no rules, so listener "
                f"{listener.name!r} refuses every request"
            )
        warnings += lint(
            rules,
            listener=listener.name,
            tls=listener.tls,
            read_only=listener.read_only or config.server.read_only,
            allow=listener.allow or config.server.allow,
            routes=config.routes,
            own_units=own_units,
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
