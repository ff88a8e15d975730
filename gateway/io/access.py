"""A listener's door: the source allow lists at accept, and failed TLS handshakes.

A connection from a source outside an allow list is closed as soon as it is
accepted, before a byte of it is read (so before any TLS handshake), counted in
``connections_denied_total{listener}`` and logged at a bounded rate: one line
for the first, then one summary a minute however many a scanner sends.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
from collections.abc import Sequence

from ..core.policy import IPAddress, IPNetwork
from ..logs import RateLimitedLogger
from ..metrics import GatewayMetrics
from .tls import HandshakeFailure

log = logging.getLogger("gateway.access")


def peer_address(transport: asyncio.BaseTransport) -> IPAddress | None:
    """The peer's IP address (an IPv4-mapped IPv6 address as IPv4), ``None`` if not IP."""
    return peer_address_of(transport.get_extra_info("peername"))


def peer_address_of(peer: object) -> IPAddress | None:
    """The IP address in a ``peername`` / ``accept()`` address tuple, ``None`` if not IP."""
    if not isinstance(peer, tuple) or not peer:
        return None
    try:
        address = ipaddress.ip_address(peer[0])
    except ValueError:
        return None
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


class SourceScreen:
    """Admits sources inside every configured allow list; counts and logs the rest."""

    def __init__(
        self, listener: str, allow_lists: Sequence[Sequence[IPNetwork]], metrics: GatewayMetrics
    ) -> None:
        self.listener = listener
        self.allow_lists = tuple(tuple(networks) for networks in allow_lists if networks)
        self._metrics = metrics
        self._log: RateLimitedLogger | None = None
        metrics.prepare_listener(listener)

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Bind the rate-limited log to the running loop."""
        self._log = RateLimitedLogger(log, loop)

    def allows(self, source: IPAddress | None) -> bool:
        """True when ``source`` lies in every allow list (no list: any source)."""
        if not self.allow_lists:
            return True
        if source is None:
            return False
        return all(any(source in network for network in networks) for networks in self.allow_lists)

    def refuse(self, source: IPAddress | None) -> None:
        """Count and log a connection closed at accept."""
        self._metrics.connections_denied.labels(self.listener).inc()
        if self._log is not None:
            self._log.note(
                f"listener {self.listener}",
                "connection from outside the allow list",
                f"{source} closed at accept",
                plural="connections from outside the allow list",
            )

    def handshake_failed(self, reason: HandshakeFailure, error: BaseException) -> None:
        """Count a failed TLS handshake by reason; log it at a bounded rate."""
        self._metrics.tls_handshake_failures.labels(self.listener, reason.value).inc()
        if self._log is not None:
            self._log.note(
                f"listener {self.listener}",
                f"TLS handshake failed ({reason.value})",
                str(error) or type(error).__name__,
                plural=f"TLS handshakes failed ({reason.value})",
            )
