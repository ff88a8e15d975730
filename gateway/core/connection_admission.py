"""Whether a listener admits a connection: at accept, and again at every reload (no I/O).

Theory of operation. A connection is judged on *facts* the listener gathers
(``ConnectionFacts``: its source address and, once a TLS handshake is done, what
its client certificate chain shows) against a *door* (``Door``: the listener's
allow lists and whether it speaks TLS), at a moment ``now`` the caller passes
in. ``admit`` returns ``None`` (admitted) or why not (``NotAdmitted``), in one
documented order:

1. the source lies in every allow list (no list: any source; no IP source:
   refused whenever a list exists);
2. on a TLS listener, once the handshake is done: a client certificate exists;
3. it still chains to a CA the listener trusts now;
4. it is not revoked (the listener's ``crl`` lists it);
5. ``now`` lies inside its validity window (the latest ``notBefore`` and the
   earliest ``notAfter`` along the chain up to that CA).

At accept nothing but the source is known (``established`` false): the listener
closes a refused source before a byte is read, so before any handshake, and the
handshake itself checks the certificate against the same CAs. At a reload every
open connection is judged again with the new door, the new CAs and the current
time, so a narrowed allow list, a withdrawn CA or a certificate that expired
since its handshake closes the connection. Rights per request (policies, roles)
are not admission: the policy decides each request as it comes, so a narrowed
rule holds from the open connection's next request.

A revocation list (CRL) is one more fact of the same kind as ``trusted``: io
reads the list and tells whether the leaf's serial number is revoked
(``revoked``); step 4 makes it hold at every reload, as OpenSSL's CRL check does
at the handshake, without a second mechanism.

Invariants: ``admit`` is pure and total; a wider door (more networks in each
list, more trusted CAs) never refuses a connection a narrower one admits.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

from .policy import IPAddress, IPNetwork


class NotAdmitted(StrEnum):
    """Why a listener does not (or no longer) admit a connection: the log's vocabulary."""

    SOURCE_NOT_ALLOWED = "source_not_allowed"  # outside an allow list
    NO_CERTIFICATE = "no_certificate"  # a TLS connection without a client certificate
    CA_NOT_TRUSTED = "ca_not_trusted"  # its chain reaches none of the CAs trusted now
    CERTIFICATE_REVOKED = "certificate_revoked"  # the listener's crl lists it
    CERTIFICATE_NOT_YET_VALID = "certificate_not_yet_valid"  # before its notBefore
    CERTIFICATE_EXPIRED = "certificate_expired"  # past its notAfter


@dataclass(frozen=True, slots=True)
class Door:
    """What a listener asks of a connection: its allow lists, and TLS or not."""

    allow_lists: tuple[tuple[IPNetwork, ...], ...] = ()
    tls: bool = False


@dataclass(frozen=True, slots=True)
class CertificateFacts:
    """What a client certificate chain shows; times in seconds since the epoch (UTC)."""

    not_before: float  #: the latest notBefore along the chain
    not_after: float  #: the earliest notAfter along the chain
    trusted: bool  #: it chains to one of the CAs the listener trusts now (worked out in io)
    revoked: bool = False  #: the listener's CRL lists the leaf (worked out in io)


@dataclass(frozen=True, slots=True)
class ConnectionFacts:
    """What is known of one connection when it is judged."""

    source: IPAddress | None
    #: The TLS handshake is done (always true on a plain listener once accepted): only then
    #: is ``certificate`` known. At accept it is false: the source alone is judged.
    established: bool = False
    certificate: CertificateFacts | None = None


def source_allowed(allow_lists: Sequence[Sequence[IPNetwork]], source: IPAddress | None) -> bool:
    """True when ``source`` lies in every non-empty allow list (no list: any source)."""
    lists = [networks for networks in allow_lists if networks]
    if not lists:
        return True
    if source is None:
        return False
    return all(any(source in network for network in networks) for networks in lists)


def admit(door: Door, facts: ConnectionFacts, now: float) -> NotAdmitted | None:
    """Admit the connection (``None``) or say why not, in the module docstring's order."""
    if not source_allowed(door.allow_lists, facts.source):
        return NotAdmitted.SOURCE_NOT_ALLOWED
    if not door.tls or not facts.established:
        return None
    certificate = facts.certificate
    if certificate is None:
        return NotAdmitted.NO_CERTIFICATE
    if not certificate.trusted:
        return NotAdmitted.CA_NOT_TRUSTED
    if certificate.revoked:
        return NotAdmitted.CERTIFICATE_REVOKED
    if now < certificate.not_before:
        return NotAdmitted.CERTIFICATE_NOT_YET_VALID
    if now > certificate.not_after:
        return NotAdmitted.CERTIFICATE_EXPIRED
    return None
