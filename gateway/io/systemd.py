"""systemd readiness and watchdog (sd_notify(3)) without libsystemd.

The protocol is one datagram per notification, ``KEY=VALUE`` lines, sent to the
AF_UNIX socket named by ``$NOTIFY_SOCKET`` (a leading ``@`` is the abstract
namespace). Under ``Type=notify`` the unit is started when ``READY=1`` arrives,
which the gateway sends once its listeners are bound, so ``systemctl start``
and units ordered after it wait for a gateway that serves. With ``WatchdogSec=``
systemd sets ``$WATCHDOG_USEC``; ``WATCHDOG=1`` is then sent from an event-loop
timer at half that period, so a loop that stops turning is restarted. Outside
systemd (no ``$NOTIFY_SOCKET``) every call does nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import time
from collections.abc import Mapping

log = logging.getLogger("gateway")


class SystemdNotifier:
    """Sends sd_notify messages; a no-op when not started by systemd with a notify socket."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self._address: str | bytes | None = None
        self._socket: socket.socket | None = None
        self.watchdog_interval: float | None = None
        self._watchdog: asyncio.TimerHandle | None = None
        address = env.get("NOTIFY_SOCKET", "")
        if not address or address[0] not in "/@":
            return
        self._address = "\0" + address[1:] if address.startswith("@") else address
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_interval = int(usec) / 1e6

    @property
    def enabled(self) -> bool:
        """True when a notify socket was given."""
        return self._socket is not None

    def notify(self, *fields: str) -> None:
        """Send ``KEY=VALUE`` fields in one datagram; failures are logged, never raised."""
        if self._socket is None or self._address is None:
            return
        try:
            self._socket.sendto("\n".join(fields).encode(), self._address)
        except OSError as error:  # systemd gone or the socket unreachable: keep serving
            log.warning("systemd notification %s not sent: %s", fields[0], error)

    def ready(self, status: str) -> None:
        """The gateway serves: listeners bound, lines opened (or being retried)."""
        self.notify("READY=1", f"STATUS={status}", f"MAINPID={os.getpid()}")

    def reloading(self) -> None:
        """A reload began (``READY=1`` ends it)."""
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        self.notify("RELOADING=1", "STATUS=reloading the configuration", f"MONOTONIC_USEC={usec}")

    def stopping(self) -> None:
        """A graceful stop began."""
        self.notify("STOPPING=1", "STATUS=stopping: finishing the transactions on the wire")

    def start_watchdog(self, loop: asyncio.AbstractEventLoop) -> None:
        """Ping the watchdog from ``loop`` every half period while the loop turns."""
        interval = self.watchdog_interval
        if interval is None or self._socket is None:
            return

        def ping() -> None:
            self.notify("WATCHDOG=1")
            self._watchdog = loop.call_later(interval / 2, ping)

        ping()

    def close(self) -> None:
        """Stop the watchdog pings and close the socket."""
        if self._watchdog is not None:
            self._watchdog.cancel()
            self._watchdog = None
        if self._socket is not None:
            with contextlib.suppress(OSError):
                self._socket.close()
            self._socket = None
