"""The validated configuration: frozen dataclasses, one per table, that the rest of the
gateway reads.

Their defaults are the schema's (``_default``): a key's default is declared once, in
``gateway/schema/keys.py``, and a dataclass built directly gets the value a file that
leaves the key out gets. What a dataclass adds to the keys is what follows from them: a
line's gap and silence from its format, a listener's ``tls``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .. import schema
from ..core.policy import IPNetwork, Rule
from ..core.timing import character_time, t35
from ..schema import Table


def _default(table: Table, name: str) -> Any:
    """The schema's default for key ``name`` of ``table``: the dataclasses below take their
    defaults from the keys rather than restating them (the schema is the model)."""
    return schema.key(table, name).default


#: Line kinds reached over the network rather than through a device node.
NETWORK_LINE_KINDS = frozenset({"rtu-over-tcp", "tcp", "tls"})


#: Silence that ends a frame of unknown length on a network link (segments, device servers).
NETWORK_SILENCE_S = 0.05


#: The IANA port of Modbus/TCP Security.
DEFAULT_TLS_PORT = 802


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
