"""A listener's door: the source allow lists at accept, and failed TLS handshakes.

A connection from a source outside an allow list is closed as soon as it is
accepted, before a byte of it is read (so before any TLS handshake), counted in
``connections_denied_total{listener}`` and logged at a bounded rate: one line
for the first, then one summary a minute however many a scanner sends. The
decision is core's (``core.connection_admission``), the same one a reload asks
for every open connection; a connection closed then is logged once, by name.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
from collections.abc import Sequence
from typing import Protocol

from ...core.audit_record import RefusedAt
from ...core.connection_admission import Door, NotAdmitted
from ...core.policy import IPAddress, IPNetwork, Principal
from ...logs import RateLimitedLogger
from ...metrics import GatewayMetrics
from ..audit import AuditLog
from .tls import HandshakeFailure, leaf_subject

log = logging.getLogger("gateway.access")


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


_REASON_TEXT = {
    NotAdmitted.SOURCE_NOT_ALLOWED: ": its address is outside the allow list",
    NotAdmitted.CA_NOT_TRUSTED: ": its certificate chains to no CA in the listener's ca",
    NotAdmitted.CERTIFICATE_EXPIRED: ": its client certificate has expired",
    NotAdmitted.CERTIFICATE_NOT_YET_VALID: ": its client certificate is not valid yet",
    NotAdmitted.NO_CERTIFICATE: ": it showed no client certificate",
    NotAdmitted.CERTIFICATE_REVOKED: ": its client certificate is revoked (listener's crl)",
}


class ClosingConnection(Protocol):
    """What a reload closing a connection tells of it (``tcp.MasterConnection`` has it)."""

    peer: str
    principal: Principal
    role_text: str | None
    chain: tuple[bytes, ...]


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

    def door(self, tls: bool) -> Door:
        """The listener's door as it stands now, for ``core.connection_admission.admit``."""
        return Door(self.allow_lists, tls)

    def closed_at_reload(
        self, connection: ClosingConnection, reason: NotAdmitted, audit: AuditLog | None = None
    ) -> None:
        """Log (and audit, when configured), once per connection, one closed because it
        is no longer admitted."""
        peer = connection.peer
        log.warning(
            "listener %s: master %s closed: no longer admitted (%s)%s",
            self.listener,
            peer,
            reason.value,
            _REASON_TEXT.get(reason, ""),
        )
        if audit is not None:
            source = connection.principal.source
            audit.refused(
                self.listener,
                str(source if source is not None else peer),
                reason.value,
                RefusedAt.RELOAD,
                peer,
                connection.role_text,
                leaf_subject(connection.chain),
            )

    def refuse(self, source: IPAddress | None, audit: AuditLog | None = None) -> None:
        """Count, log (and audit, when configured) a connection closed at accept."""
        self._metrics.connections_denied.labels(self.listener).inc()
        if audit is not None:
            audit.refused(
                self.listener, str(source), NotAdmitted.SOURCE_NOT_ALLOWED.value, RefusedAt.ACCEPT
            )
        if self._log is not None:
            self._log.note(
                f"listener {self.listener}",
                "connection from outside the allow list",
                f"{source} closed at accept",
                plural="connections from outside the allow list",
            )

    def handshake_failed(
        self,
        reason: HandshakeFailure,
        error: BaseException,
        peer: str,
        source: IPAddress | None,
        subject: str | None = None,
    ) -> None:
        """Count a failed TLS handshake by reason; log it at a bounded rate per source.

        The line names the peer (address and port) and, when one is known, the client
        certificate's subject; further failures of the same kind from the same address
        within the window are summed in one line.
        """
        self._metrics.tls_handshake_failures.labels(self.listener, reason.value).inc()
        if self._log is not None:
            certificate = f", certificate {subject!r}" if subject else ""
            self._log.note(
                f"listener {self.listener}: master {source if source is not None else peer}",
                f"TLS handshake failed ({reason.value})",
                f"peer {peer}{certificate}: {str(error) or type(error).__name__}",
                plural=f"TLS handshakes failed ({reason.value})",
            )
