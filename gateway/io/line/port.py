"""Opening a line's link, and reopening it with back-off: the port side of a ``Bus``.

Theory of operation. A serial line opens its port at once (retried with back-off while
it cannot); a networked line (``rtu-over-tcp``, ``tcp``, ``tls``) connects in the
background, then waits ``connect_delay``. A failure is logged once per reason until
the line works again; a TLS failure is counted by reason. When a link is ready it is
handed to the bus (``Bus.attach``), which tells the line core; this module decides
nothing about Modbus.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import ssl
from typing import Protocol

from ...config import LineConfig
from ...metrics import GatewayMetrics
from ..links.link import Link, TcpLink, TlsLink, connect_tcp, connect_tls
from ..links.serial_port import SerialLink, SerialPortError, open_serial
from ..links.tls import line_failure_message, line_failure_reason

log = logging.getLogger("gateway.bus")

REOPEN_FIRST_DELAY = 0.05
REOPEN_MAX_DELAY = 0.5


class PortOwner(Protocol):
    """What the port side needs of the driver it opens links for (``bus.Bus``), defined
    here so that this module does not import the driver."""

    @property
    def name(self) -> str: ...
    @property
    def config(self) -> LineConfig: ...
    @property
    def tls_context(self) -> ssl.SSLContext | None: ...
    @property
    def quiet_open(self) -> bool:
        """Open the serial port without a glitch on its lines (a pair's standby)."""
        ...

    def on_data(self, data: bytes) -> None: ...
    def on_lost(self, error: OSError) -> None: ...
    def attach(self, link: Link) -> None: ...


class LinePort:
    """Opens and reopens one bus's link (see the module docstring)."""

    def __init__(
        self, bus: PortOwner, metrics: GatewayMetrics, loop: asyncio.AbstractEventLoop
    ) -> None:
        self._bus = bus
        self._metrics = metrics
        self._loop = loop
        self._reopener: asyncio.Task[None] | None = None
        self._stopped = False
        #: The last failure said (a new one is logged; ``""`` once the line works).
        self.open_error = ""

    def start(self) -> None:
        """Open the port, or begin retrying (a network line connects in the background)."""
        if self._bus.config.networked:
            self.schedule_reopen(first_delay=0.0)
        elif not self._try_open():
            self.schedule_reopen()

    def stop(self) -> None:
        """No more reopening."""
        self._stopped = True
        if self._reopener is not None:
            self._reopener.cancel()

    def _failed(self, reason: str) -> None:
        if reason != self.open_error:  # first failure, or a new reason: say it once
            self.open_error = reason
            log.error("%s; retrying", reason)

    def _try_open(self) -> bool:
        bus = self._bus
        try:
            port = open_serial(bus.config, quiet=bus.quiet_open)
        except SerialPortError as error:
            self._failed(str(error))
            return False
        self.open_error = ""
        log.info("line %s: %s open at %d baud", bus.name, bus.config.device, bus.config.baudrate)
        bus.attach(SerialLink(port, self._loop, bus.on_data, bus.on_lost))
        return True

    async def _try_connect(self) -> bool:
        """Connect to the device server (then wait ``connect_delay``); False on failure."""
        bus = self._bus
        config = bus.config
        try:
            sock = await connect_tcp(config.host, config.port, config.connect_timeout)
        except OSError as error:
            self._failed(f"line {bus.name!r}: cannot connect to {config.device}: {error}")
            return False
        lost: list[OSError] = []
        link: TcpLink | TlsLink
        if config.kind == "tls":
            handshaken = await self._handshake(sock, lost)
            if handshaken is None:
                return False
            link = handshaken
        else:
            link = TcpLink(sock, config.device, self._loop, _discard, lost.append)
        if config.connect_delay > 0:
            # Some device servers drop what arrives while they set up their serial side:
            # nothing is sent (the line stays down, 0x0A) and nothing read counts.
            try:
                await asyncio.sleep(config.connect_delay)
            except asyncio.CancelledError:
                link.close()
                raise
        if lost or link.closed:
            self._failed(f"line {bus.name!r}: {config.device} closed the connection at once")
            return False
        link.on_data, link.on_lost = bus.on_data, bus.on_lost
        if isinstance(link, TlsLink) and self.open_error:
            # After a TLS failure the slave's first answer says it took the certificate:
            # until then a reconnect is not news (the failure was logged once).
            link.on_confirmed = self._tls_confirmed
            log.debug("line %s: TLS handshake with %s done", bus.name, config.device)
        else:
            self.open_error = ""
            log.info("line %s: connected to %s (%s)", bus.name, config.device, config.kind)
        bus.attach(link)
        return True

    async def _handshake(self, sock: socket.socket, lost: list[OSError]) -> TlsLink | None:
        """The TLS handshake of a ``tls`` line on a connected socket; None on failure."""
        bus = self._bus
        config = bus.config
        assert bus.tls_context is not None, "a tls line is opened with its context"
        try:
            tls = await connect_tls(
                sock, bus.tls_context, config.server_name, config.tls_handshake_timeout
            )
        except OSError as error:
            self.tls_failed(error)
            return None
        return TlsLink(tls, config.device, self._loop, _discard, lost.append)

    def tls_failed(self, error: OSError) -> None:
        """Count a TLS failure by reason; log it when the reason is new."""
        reason = line_failure_reason(error)
        self._metrics.line_tls_failures.labels(self._bus.name, reason.value).inc()
        key = f"tls:{reason.value}"
        if key != self.open_error:
            self.open_error = key
            log.error("%s; retrying", line_failure_message(self._bus.config, reason, error))

    def _tls_confirmed(self) -> None:
        self.open_error = ""
        log.info(
            "line %s: TLS session with %s accepted, back up",
            self._bus.name,
            self._bus.config.device,
        )

    def schedule_reopen(self, first_delay: float = REOPEN_FIRST_DELAY) -> None:
        if self._reopener is None or self._reopener.done():
            self._reopener = self._loop.create_task(
                self._reopen(first_delay), name=f"reopen-{self._bus.name}"
            )

    async def _reopen(self, first_delay: float = REOPEN_FIRST_DELAY) -> None:
        delay = first_delay
        while not self._stopped:
            if delay > 0:
                await asyncio.sleep(delay)
            if self._stopped:
                return
            networked = self._bus.config.networked
            opened = await self._try_connect() if networked else self._try_open()
            if opened:
                if delay > 0 and not self.open_error:  # a TLS session: when confirmed
                    log.info("line %s: back up", self._bus.name)
                self._reopener = None
                return
            delay = min(max(delay * 2, REOPEN_FIRST_DELAY), REOPEN_MAX_DELAY)


def _discard(_data: bytes) -> None:
    """Bytes read during the connect delay: not an answer to anything."""
