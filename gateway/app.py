"""Composition and lifecycle: config → lines, router, TCP server, metrics; start, stop, reload.

The application owns no protocol logic. ``start`` opens the lines and binds
the listener, then sets ``ready``; ``stop`` stops accepting, lets each line
finish the transaction on the wire within the grace period, answers what is
still queued with 0x0A and closes every connection; ``reload`` swaps routes,
timeouts and limits in place and reopens only lines whose port settings changed.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import resource
import signal
import ssl
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry

from . import __version__, build
from .config import (
    LINE_PORT_SETTINGS,
    ConfigError,
    GatewayConfig,
    LineConfig,
    ListenerConfig,
    build_config,
    read_config_file,
)
from .core.line import Handover, LineRequest
from .core.reasons import CloseReason
from .io.audit import AuditLog, note_config, start_audit
from .io.clock import PreciseClock
from .io.frame_trace import FrameTrace
from .io.http.endpoint import HttpEndpoint, role_route, start_http
from .io.http.guard import RouteAccess
from .io.http.live import LiveView
from .io.line.bus import Alone, Bus, PlannedBlock, PollBlockView, poll_block_status
from .io.links.serial_port import check_devices_usable
from .io.links.tls import client_context
from .io.listeners.rtu_over_tcp import rtu_over_tcp_server
from .io.listeners.serial_slave import SerialSlave
from .io.listeners.spine import LineTarget, Router, listener_policy
from .io.listeners.status_unit import StatusUnit
from .io.listeners.tcp import ModbusTcpServer
from .io.listeners.tls import HandshakeFailure, ServerTls, server_context
from .io.status import LineStatus, MasterStatus, PairStatus, PollBlockStatus
from .io.systemd import SystemdNotifier
from .io.tls_setup import TlsSetupError
from .metrics import GatewayMetrics
from .reload_summary import summarize
from .restart_keys import keep_restart_settings
from .trace import Tracer

if TYPE_CHECKING:
    from .io.pair.role import Pair

log = logging.getLogger("gateway")


def _port_changed(old: LineConfig, new: LineConfig) -> bool:
    """True when a setting whose change reopens the port differs (the schema says which)."""
    return any(getattr(old, key) != getattr(new, key) for key in LINE_PORT_SETTINGS)


#: File descriptors needed besides one per master and per HTTP connection: lines, timers,
#: listeners, logs.
_FDS_BESIDES_MASTERS = 64


def ensure_file_descriptors(needed: int) -> None:
    """Raise the soft open-file limit towards ``needed`` (up to the hard limit).

    Each master costs one descriptor; the common soft limit of 1024 would refuse
    connections well before a ``max_connections`` of 1000 plus lines and scrapes.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= needed:
        return
    target = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
    if target > soft:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    if target < needed:
        log.warning(
            "open-file limit %d is below the %d that server.max_connections needs; "
            "raise it (systemd: LimitNOFILE=, docker: --ulimit nofile=)",
            target,
            needed,
        )


def bind_error(error: OSError, key: str, host: str, port: int) -> OSError:
    """A listener that cannot bind, explained: which key, and what grants a port below 1024."""
    where = f"cannot listen on {host}:{port} ({key})"
    if error.errno in (errno.EACCES, errno.EPERM) and 0 < port < 1024:
        return PermissionError(
            f"{where}: permission denied: ports below 1024 need the CAP_NET_BIND_SERVICE "
            "capability. The systemd unit modbus-gateway@.service grants it (and nothing "
            "else); otherwise listen on a port from 1024 up (e.g. --listen 0.0.0.0:5020) and "
            "point the masters at it (or redirect 502 there in the firewall). Never grant it "
            "to the system Python, which every Python program runs: give it to a copy of the "
            'interpreter, `cp "$(realpath .venv/bin/python)" .venv/bin/python-bind && sudo '
            "setcap cap_net_bind_service=+ep .venv/bin/python-bind`, and start the gateway "
            "with `.venv/bin/python-bind -m gateway`."
        )
    if error.errno == errno.EADDRINUSE:
        return OSError(
            f"{where}: address already in use: another program listens there "
            f"(ss -ltnp 'sport = :{port}'); stop it, or choose another port with "
            f"{_key_terms(key)}."
        )
    return OSError(f"{where}: {error.strerror or error}.")


def _key_terms(key: str) -> str:
    """``metrics.listen, --metrics`` → ``metrics.listen (or --metrics)``."""
    first, _, flag = key.partition(", ")
    return f"{first} (or {flag})" if flag else first


def http_url(host: str, port: int, path: str = "/") -> str:
    """A URL a browser opens: an IPv6 address goes in brackets (``http://[::1]:9502/``)."""
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}{path}"


class Gateway:
    """The running gateway; also the ``GatewayView`` that /status and the live trace read."""

    def __init__(
        self,
        config: GatewayConfig,
        registry: CollectorRegistry | None = None,
        tracer: Tracer | None = None,
    ) -> None:
        self.config = config
        self.tracer = tracer  #: the ``--trace`` logger, subscribed to ``trace`` for good
        #: The one frame trace every listener holds from its construction on.
        self.trace = FrameTrace() if tracer is None else FrameTrace(tracer)
        self.metrics = GatewayMetrics(registry)
        self.metrics.watch_poll_blocks(self.poll_block_status)
        self.ready = asyncio.Event()
        self.stopped = asyncio.Event()
        self.buses: dict[str, Bus] = {}
        self.server: ModbusTcpServer | None = None  #: the first listener
        self.servers: list[ModbusTcpServer] = []  #: every listener, in configuration order
        self.serial_slaves: list[SerialSlave] = []  #: ``serial-slave`` listeners
        self._clocks: dict[str, PreciseClock] = {}  # one per bus: a clock has one sleeper
        self._line_tls: dict[str, ssl.SSLContext] = {}  # tls lines' client contexts
        self._reload_lock = asyncio.Lock()
        self._http: HttpEndpoint | None = None
        self.live: LiveView | None = None  # trace stream, /status and the status page
        self._stopping = False
        self.audit: AuditLog | None = None  #: the audit log (``[audit] path``)
        self.pair: Pair | None = None  #: one gateway of an active/standby pair

    # -- addresses ---------------------------------------------------------------------

    @property
    def address(self) -> tuple[str, int]:
        """The Modbus TCP listening address (after ``start``)."""
        assert self.server is not None
        return self.server.sockets[0]

    def addresses(self) -> list[tuple[str, int]]:
        """Every Modbus listener's address (after ``start``)."""
        return [server.sockets[0] for server in self.servers if server.sockets]

    def listener_address(self, name: str) -> tuple[str, int]:
        """Where listener ``name`` listens (after ``start``)."""
        for server in self.servers:
            if server.name == name:
                return server.sockets[0]
        raise KeyError(name)

    @property
    def metrics_address(self) -> tuple[str, int] | None:
        """The HTTP endpoint's address, ``None`` when disabled."""
        return self._http.address if self._http is not None else None

    # -- what /status and the live trace read (``GatewayView``) ---------------------------

    def route(self, unit: int) -> tuple[str, int] | None:
        """The line and slave address ``unit`` goes to now, ``None`` without a route."""
        target = self.server.router.lookup(unit) if self.server is not None else None
        return None if target is None else (target.bus.name, target.slave)

    def line_states(self) -> list[LineStatus]:
        """Each line's own status with the slaves routed to it, sorted by line name."""
        routed: dict[str, set[int]] = {}
        for route in self.config.routes.values():
            routed.setdefault(route.line, set()).add(route.slave)
        return [
            bus.status(sorted(routed.get(name, ()))) for name, bus in sorted(self.buses.items())
        ]

    def poll_blocks(self) -> list[PlannedBlock]:
        """Every line's poll blocks (agent mode), in configuration order."""
        blocks = [planned for bus in self.buses.values() for planned in bus.poll_blocks()]
        blocks.sort(key=lambda planned: planned.config.index)
        return blocks

    def poll_block_status(self) -> list[PollBlockStatus]:
        """Every line's poll blocks as ``/status`` shows them, now (what the metrics read)."""
        now = time.monotonic()
        return [
            status
            for bus in self.buses.values()
            for status in poll_block_status(bus.name, bus.poll_blocks(), now)
        ]

    def _block_freshness(self) -> list[PollBlockView]:
        """What the status unit reads: block N of the configuration at place N."""
        return [planned.block for planned in self.poll_blocks()]

    def masters(self) -> tuple[MasterStatus, ...]:
        """The masters connected now: TCP listeners first, then serial-slave lines."""
        masters = [master for server in self.servers for master in server.masters()]
        masters += [master for slave in self.serial_slaves for master in slave.masters()]
        return tuple(masters)

    def listen(self) -> str:
        """``host:port`` of the first Modbus listener (empty before it listens)."""
        if self.server is None or not self.server.sockets:
            return ""
        return "{}:{}".format(*self.server.sockets[0])

    # -- lifecycle ---------------------------------------------------------------------

    async def start(self) -> None:
        """Open lines, bind the TCP listener and the HTTP endpoint, then set ``ready``."""
        log.info("modbus-gateway %s (%s)", __version__, build())
        loop = asyncio.get_running_loop()
        config = self.config
        listeners = tuple(lst for lst in config.listeners if lst.serial is None) or (
            ListenerConfig("tcp", host=config.server.host, port=config.server.port),
        )
        tls = self._build_tls(config)  # before anything opens: a bad certificate stops here
        self.audit = start_audit(config.audit.path, self.metrics.audit_records_dropped.inc)
        note_config(self.audit, "load", config.source, config)
        self._line_tls = self._build_line_tls(config)
        http_connections = config.metrics.max_connections if config.metrics.enabled else 0
        ensure_file_descriptors(
            config.server.max_connections * len(listeners) + http_connections + _FDS_BESIDES_MASTERS
        )
        check_devices_usable(config, quiet=config.redundancy.paired)  # held or unusable: stop
        if config.redundancy.paired:  # before the lines open: they open listening
            from .io.pair.build import build_pair  # a gateway alone loads none of the pair

            self.pair = build_pair(config, self.buses, self.metrics)
        for line in config.lines:
            self._open_bus(line, loop)
        self.metrics.describe_lines([line.name for line in config.lines])
        router = self._build_router()
        if self.pair is not None:
            self.pair.start()
        self._build_servers(listeners, router, tls)
        self._start_serial_slaves(router, loop)
        self.live = LiveView(self, self.metrics, self.trace)
        await self._bind()
        log_listening(self.servers, len(self.buses), self.metrics_address)
        self.ready.set()

    def _build_servers(
        self, listeners: tuple[ListenerConfig, ...], router: Router, tls: dict[str, ServerTls]
    ) -> None:
        """One server per TCP listener, each given the gateway's frame trace as it is built."""
        for listener in listeners:
            built = tls.get(listener.name)
            kind = rtu_over_tcp_server if listener.protocol == "rtu-over-tcp" else ModbusTcpServer
            server = kind(
                self.config.server,
                router,
                self.metrics,
                listener,
                listener_policy(self.config, listener),
                built.context if built else None,
            )
            server.tracer, server.audit = self.trace, self.audit
            server.pair_sources = self.config.redundancy.peer_hosts
            self.servers.append(server)
        self.server = self.servers[0]

    def _start_serial_slaves(self, router: Router, loop: asyncio.AbstractEventLoop) -> None:
        """Open each ``serial-slave`` listener's line (or keep trying in the background)."""
        for listener in self.config.listeners:
            if listener.serial is not None:
                slave = SerialSlave(
                    listener, router, self.metrics, listener_policy(self.config, listener), loop
                )
                slave.tracer, slave.audit = self.trace, self.audit
                self.serial_slaves.append(slave)
                slave.start()

    async def _bind(self) -> None:
        """Bind every TCP listener, then the HTTP endpoint; a port refused names its key."""
        for server in self.servers:
            listener = server.listener
            try:
                await server.start()
            except OSError as error:
                key = f"{listener.key_prefix}listen" + (
                    ", --listen" if listener.key_prefix == "server." else ""
                )
                raise bind_error(error, key, listener.host, listener.port) from error
        metrics = self.config.metrics
        if metrics.enabled:
            try:
                self._http = await self._start_http()
            except OSError as error:
                raise bind_error(
                    error, "metrics.listen, --metrics", metrics.host, metrics.port
                ) from error

    async def _start_http(self) -> HttpEndpoint:
        routes = dict(self.live.routes) if self.live is not None else {}
        routes["/role"] = (role_route(self._role), RouteAccess.STATUS)
        return await start_http(
            self.config.metrics,
            self.metrics.exposition_registry(),
            self.is_ready,
            routes,
            self.metrics.http_refusals,
        )

    def pair_status(self) -> PairStatus | None:
        """This gateway's role in its pair, ``None`` without one (``GatewayView``)."""
        return None if self.pair is None else self.pair.status()

    def _role(self) -> tuple[int, bytes]:
        """``GET /role``'s status and body: this gateway's role in its pair."""
        if self.pair is not None:
            return self.pair.role_body()
        from .io.pair.channel import alone_role_body

        return alone_role_body(self.config.redundancy.priority)

    def is_ready(self) -> tuple[bool, str]:
        """Readiness for /readyz: the listener is up and every line is open."""
        if self.server is None or self._stopping:
            return False, "not listening"
        return readiness(self.buses, self.pair)

    async def stop(self, grace: float = 5.0) -> None:
        """Graceful stop: see the module docstring."""
        if self._stopping:
            return
        self._stopping = True
        log.info("stopping: no new connections, finishing the transactions on the wire")
        for server in self.servers:
            server.stop_accepting()
        for slave in self.serial_slaves:
            slave.stop()
        if self.pair is not None:
            await self.pair.stop()
        await asyncio.gather(*(bus.stop(grace) for bus in self.buses.values()))
        for server in self.servers:
            server.close_all(CloseReason.SHUTDOWN)
        for server in self.servers:
            await server.wait_closed()
        if self.live is not None:
            self.live.close()
        if self._http is not None:
            await self._http.close()
        for clock in self._clocks.values():
            clock.close()
        self._clocks.clear()
        if self.audit is not None:
            await asyncio.to_thread(self.audit.close)  # what is queued is written first
        log.info("stopped")
        self.stopped.set()

    async def reload(self, config: GatewayConfig) -> None:
        """Apply a new configuration without dropping connections or in-flight transactions."""
        async with self._reload_lock:  # SIGHUPs in a row: one reload after the other
            if self._stopping or not self.ready.is_set():
                log.warning(
                    "reload ignored: the gateway is %s",
                    "stopping" if self._stopping else "still starting",
                )
                return
            refused = await self._apply(config)
            applied = self.config if refused is None else None
            note_config(self.audit, "reload", config.source, applied, refused)

    async def _apply(self, config: GatewayConfig) -> str | None:
        """Certificates first (a bad one rejects the reload), then lines, then listeners;
        why it was not applied, or ``None``."""
        assert self.server is not None
        try:
            tls = self._build_tls(config)  # certificates, keys and CAs are read again
            line_tls = self._build_line_tls(config)
        except TlsSetupError as error:
            log.error("reload rejected, the running configuration stays: %s", error)
            return "TLS files refused (see log)"
        self._line_tls = line_tls  # a line's next handshake uses its renewed files
        running, wanted = self.config, config
        if not await self._apply_lines(config, line_tls):
            return "stopped while a line was reopened"
        config = self._keep_restart_settings(config)
        self.config = config
        router = self._build_router()
        # A listener left running under another protocol than the file's takes no context.
        running_tls = {listener.name for listener in config.listeners if listener.tls}
        tls = {name: built for name, built in tls.items() if name in running_tls}
        self._apply_listeners(config, router, tls)
        self.metrics.describe_lines([line.name for line in config.lines])
        log.info(
            "reload: configuration from %s applied: %s",
            config.source,
            summarize(running, wanted, config, LINE_PORT_SETTINGS),
        )
        return None

    async def _apply_lines(
        self, config: GatewayConfig, line_tls: dict[str, ssl.SSLContext]
    ) -> bool:
        """Remove, retune, reopen and add lines; ``False`` when a stop came meanwhile."""
        loop = asyncio.get_running_loop()
        new_names = {line.name for line in config.lines}
        for name in list(self.buses):
            if name not in new_names:
                log.info("reload: line %s removed", name)
                await self._close_bus(name, grace=5.0)
        for line in config.lines:
            bus = self.buses.get(line.name)
            if bus is not None and not _port_changed(bus.config, line):
                bus.reconfigure(line)
                bus.tls_context = line_tls.get(line.name)
            elif not await self._reopen_bus(line, bus, loop):
                return False
        return True

    async def _reopen_bus(
        self, line: LineConfig, bus: Bus | None, loop: asyncio.AbstractEventLoop
    ) -> bool:
        """Open ``line`` anew, handing over ``bus``'s queue; ``False`` when a stop came."""
        queued: list[LineRequest] = []
        handover: Handover | None = None
        if bus is not None:
            log.info("reload: line %s port settings changed, reopening", line.name)
            # The queue, and what masters send while the transaction on the wire finishes,
            # wait for the reopened line; so do the wire's turnaround and late-answer windows.
            del self.buses[line.name]  # a stop meanwhile leaves it to us
            clock = self._clocks.pop(line.name)
            queued, handover = await bus.hand_over(grace=5.0)
            clock.close()
        else:
            log.info("reload: line %s added", line.name)
        if self._stopping:  # a stop signal came while the old line finished its transaction
            Bus.answer_unavailable(queued)
            return False
        reopened = self._open_bus(line, loop)
        if bus is not None:
            bus.hand_to(reopened)
        reopened.adopt(queued, handover)
        return True

    def _keep_restart_settings(self, config: GatewayConfig) -> GatewayConfig:
        """``config`` with the running value of every key a reload cannot change (warned)."""
        applied, kept = keep_restart_settings(self.config, config)
        for owner in dict.fromkeys(k.owner for k in kept):
            log.warning(
                "reload: %s changes need a restart; keeping the running %s",
                owner,
                ", ".join(k.path for k in kept if k.owner == owner),
            )
        running = {s.name: s.listener.protocol for s in self.servers}
        running |= {slave.name: slave.listener.protocol for slave in self.serial_slaves}
        wanted = {listener.name: listener.protocol for listener in config.listeners}
        if config.listeners and wanted != running:
            log.warning(
                "reload: adding or removing listeners, or changing their protocol, needs a "
                "restart; the listeners stay as they are (their policies and certificates reload)"
            )
        return applied

    def _apply_listeners(
        self, config: GatewayConfig, router: Router, tls: dict[str, ServerTls]
    ) -> None:
        """New routes, settings, policies, allow lists and certificates for every listener."""
        now = time.time()  # one reload, one moment: every open connection is judged at it
        for server in self.servers:
            server.reconfigure(config, router, tls.get(server.name), now)
        for slave in self.serial_slaves:
            slave.reconfigure(config, router)

    # -- helpers -----------------------------------------------------------------------

    def _open_bus(self, line: LineConfig, loop: asyncio.AbstractEventLoop) -> Bus:
        """Start a bus for ``line`` with a clock of its own (a clock serves one sleeper)."""
        clock = PreciseClock(loop)
        role = Alone() if self.pair is None else self.pair.line_role()
        bus = Bus(line, self.metrics, loop, clock, role, self._line_tls.get(line.name))
        self.buses[line.name] = bus
        self._clocks[line.name] = clock
        if self.pair is not None:
            self.pair.attach(bus)
        bus.start()
        return bus

    async def _close_bus(self, name: str, grace: float) -> None:
        """Stop the bus of line ``name`` (see ``Bus.stop``) and release its clock."""
        await self.buses.pop(name).stop(grace)
        self._clocks.pop(name).close()

    def _build_tls(self, config: GatewayConfig) -> dict[str, ServerTls]:
        """Every tls listener's context, built from its files now (raises ``TlsSetupError``)."""
        built = {
            listener.name: server_context(listener) for listener in config.listeners if listener.tls
        }
        self.metrics.set_certificates(info for tls in built.values() for info in tls.certificates)
        self.metrics.set_crls(crl for tls in built.values() for crl in tls.crls)
        for name in built:
            self.metrics.prepare_tls_listener(name, (reason.value for reason in HandshakeFailure))
        return built

    def _build_line_tls(self, config: GatewayConfig) -> dict[str, ssl.SSLContext]:
        """Every tls line's client context, from its files now (raises ``TlsSetupError``)."""
        built = {line.name: client_context(line) for line in config.lines if line.kind == "tls"}
        self.metrics.set_line_certificates(
            info for tls in built.values() for info in tls.certificates
        )
        return {name: tls.context for name, tls in built.items()}

    def _build_router(self) -> Router:
        """The routing table of every listener's admission and of a standby's forwarding."""
        routes = {
            unit: LineTarget(self.buses[route.line], route.slave)
            for unit, route in self.config.routes.items()
        }
        broadcast = [bus for bus in self.buses.values() if bus.config.broadcast]
        self.metrics.prepare_units((r.line, r.slave) for r in self.config.routes.values())
        status_unit = self.config.polling.status_unit
        own = {}
        if status_unit:  # answered here, from the blocks of the lines running at each read
            own[status_unit] = LineTarget(
                StatusUnit(self._block_freshness, self.metrics), status_unit
            )
        router = Router(routes, broadcast, own)
        if self.pair is not None:  # a standby forwards by the table the active admits by
            self.pair.reroute(router.admitter.table)
        return router


def log_listening(
    servers: list[ModbusTcpServer], lines: int, metrics_address: tuple[str, int] | None
) -> None:
    """One line per listener (the CLI's tests and operators wait for it), then metrics."""
    for server in servers:
        host, port = server.sockets[0]
        listener = server.listener
        if listener.tls:
            protocol = "Modbus/TCP Security"
        elif listener.protocol == "rtu-over-tcp":
            protocol = "RTU over TCP"
        else:
            protocol = "Modbus TCP"
        log.info(
            "listening on %s:%d (%s), listener %s, %d line(s)",
            host,
            port,
            protocol,
            listener.name,
            lines,
        )
    if metrics_address is not None:
        mhost, mport = metrics_address
        log.info(
            "metrics on %s, status page on %s",
            http_url(mhost, mport, "/metrics"),
            http_url(mhost, mport),
        )


def readiness(buses: Mapping[str, Bus], pair: Pair | None) -> tuple[bool, str]:
    """Every line open: ready; noisy, shared and standing by are said, still ready (see the
    health semantics in docs/observability.md)."""
    down = [name for name, bus in buses.items() if not bus.up]
    if down:
        return False, "line(s) down: " + ", ".join(down)
    noisy = [name for name, bus in buses.items() if bus.noisy]
    shared = [name for name, bus in buses.items() if bus.shared]
    notes = []
    if noisy:
        notes.append("noisy line(s), requests answered 0x0B: " + ", ".join(noisy))
    if shared:
        notes.append("shared line(s), another master heard: " + ", ".join(shared))
    if pair is not None and pair.standing_by:
        notes.append("standby: requests are forwarded to the active peer")
    return True, "; ".join(["ok", *notes])


class _Signals:
    """The signals a running gateway handles, in one place: stop (twice: exit), and reload."""

    def __init__(
        self,
        gateway: Gateway,
        reload_source: Callable[[], GatewayConfig] | None,
        notifier: SystemdNotifier,
        loop: asyncio.AbstractEventLoop,
    ) -> None:
        self._gateway = gateway
        self._reload_source = reload_source
        self._notifier = notifier
        self._loop = loop
        self.stop_requested = asyncio.Event()
        self._signals_seen = 0
        self._reloads: set[asyncio.Task[None]] = set()

    def install(self) -> None:
        """Handle SIGTERM and SIGINT (stop) and SIGHUP (reload) on the loop."""
        for signum in (signal.SIGTERM, signal.SIGINT):
            self._loop.add_signal_handler(signum, self._on_stop_signal, signum)
        self._loop.add_signal_handler(signal.SIGHUP, self._on_reload_signal)

    def serving(self) -> str:
        """What systemd's status line says while the gateway serves."""
        addresses = ", ".join(f"{host}:{port}" for host, port in self._gateway.addresses())
        return f"listening on {addresses}, {len(self._gateway.buses)} line(s)"

    def _on_stop_signal(self, signum: int) -> None:
        self._signals_seen += 1
        if self._signals_seen > 1:
            log.warning("second %s: exiting at once", signal.Signals(signum).name)
            raise SystemExit(1)
        log.info("%s received", signal.Signals(signum).name)
        self.stop_requested.set()

    def _on_reload_signal(self) -> None:
        if self._reload_source is None:
            log.warning("SIGHUP: no configuration file to reload")
            return
        log.info("SIGHUP received: reloading the configuration file")
        if self._gateway.audit is not None:
            self._gateway.audit.reopen()  # logrotate: even when the reload is rejected
        self._notifier.reloading()
        try:
            config = self._reload_source()
        except ConfigError as error:
            log.error("reload rejected, the running configuration stays: %s", error)
            note_config(self._gateway.audit, "reload", error.source, None, str(error))
            self._notifier.ready("reload rejected: " + self.serving())
            return
        task = self._loop.create_task(self._gateway.reload(config))
        self._reloads.add(task)
        task.add_done_callback(self._reload_done)

    def _reload_done(self, task: asyncio.Task[None]) -> None:
        self._reloads.discard(task)
        if not task.cancelled() and (error := task.exception()) is not None:
            log.error("reload failed: %r", error, exc_info=error)
        if not self.stop_requested.is_set():
            self._notifier.ready(self.serving())


async def run_until_signalled(
    gateway: Gateway,
    reload_source: Callable[[], GatewayConfig] | None,
    grace: float,
    notifier: SystemdNotifier | None = None,
) -> None:
    """Run until SIGTERM/SIGINT (a second one exits at once); SIGHUP reloads the file.

    systemd (``Type=notify``) hears READY=1 once the listeners are bound, RELOADING=1 and
    READY=1 around a reload, STOPPING=1 at a stop, and WATCHDOG=1 while the loop turns.
    """
    loop = asyncio.get_running_loop()
    notifier = SystemdNotifier() if notifier is None else notifier
    signals = _Signals(gateway, reload_source, notifier, loop)
    signals.install()
    try:
        await gateway.start()
        notifier.ready(signals.serving())
        notifier.start_watchdog(loop)
        await signals.stop_requested.wait()
        notifier.stopping()
        await gateway.stop(grace)
    finally:
        notifier.close()


def reloader(
    path: str, apply: Callable[[dict[str, Any]], dict[str, Any]]
) -> Callable[[], GatewayConfig]:
    """A function that re-reads ``path`` with the command line's overrides applied."""

    def load() -> GatewayConfig:
        return build_config(apply(read_config_file(path)), path)

    return load
