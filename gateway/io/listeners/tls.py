"""Modbus/TCP Security on a listener: the server's TLS context, the client's role, the handshake.

Theory of operation. ``server_context`` builds an ``ssl.SSLContext`` that speaks
TLS 1.2 or newer only and requires a client certificate chaining to the
configured CAs (mutual authentication, as the Modbus/TCP Security
specification requires); an expired or not-yet-valid server certificate, a key
that does not match it, or an unreadable file is a ``TlsSetupError`` naming the
listener's key and the fix. It is built again on every SIGHUP, so renewed
certificates are picked up without a restart; connections already open keep
the session they negotiated, but ``ssl`` cannot verify it again: each keeps
the chain its handshake verified (``peer_chain``), and a reload judges that
chain against the CAs read again (``certificate_facts``, with ``cryptography``)
through ``core.connection_admission``.

The TCP server (``gateway.io.listeners.tcp``) accepts on a ``tls`` listener itself: it
screens the source address (allow list) and admits the connection before a
single byte is read, runs the handshake (``server.tls_handshake_timeout``) so that a
failure can be counted by reason (``handshake_failure_reason``), and only then
hands the connection to the Modbus side, which takes the role once from the
client certificate (``role_of``). ``ssl`` never shows a certificate's private
extensions, so the role (extension OID 1.3.6.1.4.1.50316.802.1, an ASN.1
UTF8String) is read from the DER with ``cryptography``.

Suites: TLS 1.3's, the ECDHE ones, then the specification's required
TLS_RSA_WITH_AES_128_CBC_SHA256 unless ``forward_secrecy_only``; never NULL.
Resumption is off unless ``session_resumption`` (no tickets, no session-id
cache), so every session is checked in full, the ``crl`` included
(``VERIFY_CRL_CHECK_LEAF``; a reload judges open sessions against it through
``certificate_facts``). ``ssl`` shows nothing of a refused handshake's
certificate: a listener's context (``ListenerContext``) has OpenSSL's message
callback note the subject of the client's Certificate message in the
connection's ``HandshakeNote`` (reached through ``contextvars``: the setup task
runs in a context of its own), for the failure's log line; a session that is
set up moves to the unobserved twin context, so records cost nothing more.
"""

from __future__ import annotations

import _ssl
import asyncio
import contextvars
import ctypes
import enum
import logging
import ssl
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any, TypeVar

from ...config import ListenerConfig
from ...core.connection_admission import CertificateFacts
from ...core.policy import ROLE_OID, decode_role
from ..tls_setup import (
    EXPIRY_VERIFY_CODES,
    CertificateInfo,
    TlsSetupError,
    check_chain,
    cipher_string,
    load_authorities,
    load_key_pair,
    read_pem_certificates,
    subject_of,
)

if TYPE_CHECKING:  # ``cryptography`` loads with the first certificate: TLS configurations only
    from cryptography import x509

log = logging.getLogger("gateway.tls")


class HandshakeFailure(enum.StrEnum):
    """Why a TLS handshake failed: the ``reason`` label of ``tls_handshake_failures_total``."""

    PROTOCOL_VERSION = "protocol_version"  # TLS 1.1 or older, SSL
    NOT_TLS = "not_tls"  # bytes that are no TLS record: a plain Modbus TCP master, a scanner
    NO_CERTIFICATE = "no_certificate"  # the client sent no certificate
    UNTRUSTED_CERTIFICATE = "untrusted_certificate"  # does not chain to the configured CAs
    EXPIRED_CERTIFICATE = "expired_certificate"  # expired or not yet valid
    REVOKED_CERTIFICATE = "revoked_certificate"  # listed in the listener's crl
    TIMEOUT = "timeout"  # no complete handshake within server.tls_handshake_timeout
    CLOSED = "closed"  # the client went away during the handshake
    OTHER = "other"  # anything else (no common cipher, garbage instead of a ClientHello, ...)


_REVOKED_VERIFY_CODE = 23  # X509_V_ERR_CERT_REVOKED


def handshake_failure_reason(error: BaseException) -> HandshakeFailure:
    """Map an exception from the handshake to its ``HandshakeFailure``."""
    if isinstance(error, ssl.SSLCertVerificationError):
        if error.verify_code in EXPIRY_VERIFY_CODES:
            return HandshakeFailure.EXPIRED_CERTIFICATE
        if error.verify_code == _REVOKED_VERIFY_CODE:
            return HandshakeFailure.REVOKED_CERTIFICATE
        return HandshakeFailure.UNTRUSTED_CERTIFICATE
    if isinstance(error, ssl.SSLError):
        reason = (error.reason or "").upper()
        if reason in (
            "WRONG_VERSION_NUMBER",
            "HTTP_REQUEST",
            "HTTPS_PROXY_REQUEST",
            "PACKET_LENGTH_TOO_LONG",
            "RECORD_LAYER_FAILURE",
        ):
            return HandshakeFailure.NOT_TLS
        if "VERSION" in reason or "UNSUPPORTED_PROTOCOL" in reason:
            return HandshakeFailure.PROTOCOL_VERSION
        if "CERTIFICATE_REQUIRED" in reason or "DID_NOT_RETURN_A_CERTIFICATE" in reason:
            return HandshakeFailure.NO_CERTIFICATE
        if "EXPIRED" in reason:
            return HandshakeFailure.EXPIRED_CERTIFICATE
        if "CERTIFICATE" in reason or "UNKNOWN_CA" in reason:
            return HandshakeFailure.UNTRUSTED_CERTIFICATE
        if isinstance(error, ssl.SSLEOFError):
            return HandshakeFailure.CLOSED
        return HandshakeFailure.OTHER
    if isinstance(error, TimeoutError) or "longer than" in str(error):
        return HandshakeFailure.TIMEOUT
    if isinstance(error, ConnectionError | OSError):
        return HandshakeFailure.CLOSED
    return HandshakeFailure.OTHER


# --------------------------------------------------------------------------- certificates


@dataclass(frozen=True, slots=True)
class CrlInfo:
    """One revocation list a listener checks, for the nextUpdate metric: once it passes,
    OpenSSL refuses every new TLS master (``untrusted_certificate``)."""

    listener: str
    issuer: str
    next_update: datetime

    def seconds_left(self, now: float | None = None) -> float:
        """Seconds until ``nextUpdate`` (negative once passed)."""
        return self.next_update.timestamp() - (time.time() if now is None else now)


def _issuer_name(crl: x509.CertificateRevocationList) -> str:
    from cryptography.x509.oid import NameOID

    names = crl.issuer.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else crl.issuer.rfc4514_string()


def _next_update(crl: x509.CertificateRevocationList) -> datetime:
    """When the CRL's issuer promises the next one (a CRL without a date: never expires)."""
    return crl.next_update_utc or datetime.max.replace(tzinfo=UTC)


#: A CRL whose nextUpdate is this close when it is read is warned about.
CRL_WARNING = timedelta(days=1)


def read_crl(path: str, key: str, now: datetime) -> tuple[x509.CertificateRevocationList, ...]:
    """The CRLs in a PEM file (one per issuing CA); ``TlsSetupError`` when unusable or expired.

    An expired list (past its ``nextUpdate``) refuses start-up and the reload: OpenSSL would
    refuse every client certificate against it (``CRL has expired``), so it is a fault to fix
    before it locks every master out, not a warning.
    """
    from cryptography import x509

    try:
        with open(path, "rb") as handle:
            data = handle.read()
    except OSError as error:
        raise TlsSetupError(f"{key} = {path!r}: cannot read: {error.strerror or error}") from None
    blocks = [
        b"-----BEGIN X509 CRL-----" + part for part in data.split(b"-----BEGIN X509 CRL-----")[1:]
    ]
    try:
        crls = tuple(x509.load_pem_x509_crl(block) for block in blocks)
    except ValueError:
        crls = ()
    if not crls:
        raise TlsSetupError(
            f"{key} = {path!r}: no PEM CRL in it (expected -----BEGIN X509 CRL-----; convert a DER "
            "list with: openssl crl -inform DER -in FILE -out FILE.pem)"
        )
    for crl in crls:
        if now > _next_update(crl):
            raise TlsSetupError(
                f"{key} = {path!r}: the CRL of {_issuer_name(crl)!r} expired on "
                f"{_next_update(crl):%Y-%m-%d %H:%M:%S} UTC (its nextUpdate); fetch the current "
                "one from the CA, then reload (SIGHUP)"
            )
        if now + CRL_WARNING > _next_update(crl):
            log.warning(
                "%s = %r: the CRL of %r expires on %s UTC (its nextUpdate): once it has, every "
                "client certificate is refused; fetch the next one and reload (SIGHUP)",
                key,
                path,
                _issuer_name(crl),
                f"{_next_update(crl):%Y-%m-%d %H:%M:%S}",
            )
    return crls


@dataclass
class ServerTls:
    """A listener's built TLS context and the certificates it rests on."""

    context: ssl.SSLContext
    certificates: list[CertificateInfo]
    #: The CAs client certificates must chain to, for judging open connections at a reload.
    authorities: tuple[x509.Certificate, ...] = ()
    #: The listener's revocation lists (``crl``), for the same judgement.
    revocations: tuple[x509.CertificateRevocationList, ...] = ()
    #: Those lists' nextUpdate, for the metric (a list without one is left out).
    crls: tuple[CrlInfo, ...] = ()


def server_context(listener: ListenerConfig, now: datetime | None = None) -> ServerTls:
    """Build the TLS context of a ``tls`` listener; raise ``TlsSetupError`` naming the fault."""
    assert listener.cert and listener.key and listener.ca
    prefix = listener.key_prefix
    moment = now or datetime.now(UTC)
    chain = check_chain(listener.cert, f"{prefix}cert", moment)
    infos = [
        CertificateInfo(
            listener.name,
            "server" if index == 0 else "chain",
            subject_of(certificate),
            certificate.not_valid_after_utc,
        )
        for index, certificate in enumerate(chain)
    ]
    authorities = read_pem_certificates(listener.ca, f"{prefix}ca")
    for authority in authorities:
        info = CertificateInfo(
            listener.name, "ca", subject_of(authority), authority.not_valid_after_utc
        )
        if moment > authority.not_valid_after_utc:
            log.warning(
                "listener %s: CA certificate %r in %s expired on %s: no client certificate "
                "chaining to it is accepted any more",
                listener.name,
                info.subject,
                listener.ca,
                f"{authority.not_valid_after_utc:%Y-%m-%d}",
            )
        infos.append(info)
    revocations = read_crl(listener.crl, f"{prefix}crl", moment) if listener.crl else ()
    context = _context(listener, ListenerContext)
    _load_files(context, listener)
    context.settled = _context(listener, ssl.SSLContext)
    _load_files(context.settled, listener)
    context._msg_callback = _observe  # type: ignore[attr-defined]
    crls = tuple(
        CrlInfo(listener.name, _issuer_name(crl), crl.next_update_utc)
        for crl in revocations
        if crl.next_update_utc is not None
    )
    return ServerTls(context, infos, tuple(authorities), revocations, crls)


class ListenerContext(ssl.SSLContext):
    """A listener's context: its handshakes are observed (``HandshakeNote``); a session
    that is set up moves to ``settled``, the same settings unobserved (``role_of``), so
    the observation costs nothing once the handshake is done."""

    settled: ssl.SSLContext | None = None


_C = TypeVar("_C", bound=ssl.SSLContext)


def _context(listener: ListenerConfig, kind: type[_C]) -> _C:
    """The settings of a listener's context: versions, suites, resumption (module docstring)."""
    context = kind(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2  # the specification: never 1.1, 1.0 or SSL
    context.verify_mode = ssl.CERT_REQUIRED  # mutual authentication
    context.options |= ssl.OP_NO_RENEGOTIATION | ssl.OP_NO_COMPRESSION
    context.options |= ssl.OP_CIPHER_SERVER_PREFERENCE
    context.set_ciphers(cipher_string(listener.forward_secrecy_only))
    if not listener.session_resumption:
        context.options |= ssl.OP_NO_TICKET  # no TLS 1.2 ticket (nor stateless 1.3 ones)
        context.num_tickets = 0  # no TLS 1.3 ticket of any kind
        if not session_cache_off(context):
            log.warning(
                "listener %s: this Python cannot turn off OpenSSL's session cache: TLS 1.2 "
                "masters may resume sessions by id for up to 7,200 s",
                listener.name,
            )
    return context


_SSL_CTRL_SET_SESS_CACHE_MODE = 44
_SSL_CTRL_GET_SESS_CACHE_MODE = 45
_SSL_SESS_CACHE_SERVER = 2  # OpenSSL's default mode for a server context


def session_cache_off(context: ssl.SSLContext) -> bool:
    """Turn off the server's session-id cache (TLS 1.2 resumption by id); ``True`` if done.

    Python's ``ssl`` has no call for ``SSL_CTX_set_session_cache_mode``: it is reached
    through the ``SSL_CTX`` pointer that CPython's context object holds right after its
    object header, and libssl as ``_ssl`` loaded it. The mode is read first, and set only
    when it is OpenSSL's documented default, so a layout this does not expect is left alone.
    """
    if sys.implementation.name != "cpython" or not isinstance(context, ssl.SSLContext):
        return False
    try:
        control = ctypes.PyDLL(_ssl.__file__).SSL_CTX_ctrl
    except (OSError, AttributeError):
        return False
    control.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_long, ctypes.c_void_p]
    control.restype = ctypes.c_long
    pointer = ctypes.c_void_p.from_address(id(context) + object.__basicsize__).value
    if not pointer or control(pointer, _SSL_CTRL_GET_SESS_CACHE_MODE, 0, None) != (
        _SSL_SESS_CACHE_SERVER
    ):
        return False
    control(pointer, _SSL_CTRL_SET_SESS_CACHE_MODE, 0, None)
    return bool(control(pointer, _SSL_CTRL_GET_SESS_CACHE_MODE, 0, None) == 0)


def _load_files(context: ssl.SSLContext, listener: ListenerConfig) -> None:
    """Load the key pair, the CAs and the CRL; raise ``TlsSetupError`` naming the key."""
    assert listener.cert and listener.key and listener.ca
    prefix = listener.key_prefix
    load_key_pair(context, listener.cert, listener.key, (f"{prefix}cert", f"{prefix}key"))
    load_authorities(context, listener.ca, f"{prefix}ca")
    if listener.crl:
        try:  # checked above with cryptography; OpenSSL reads the same PEM
            context.load_verify_locations(cafile=listener.crl)
        except (ssl.SSLError, OSError) as error:
            raise TlsSetupError(
                f"{prefix}crl = {listener.crl!r}: cannot be used: {error}"
            ) from None
        context.verify_flags |= ssl.VERIFY_CRL_CHECK_LEAF


def role_from_certificate(der: bytes | None) -> str | None:
    """The Modbus/TCP Security role in a DER client certificate; ``None`` is the NULL role.

    No role extension, two of them, or one that is not a single UTF8String gives the
    NULL role; so does a certificate ``cryptography`` cannot parse. Never raises.
    """
    from cryptography import x509

    if not der:
        return None
    try:
        certificate = x509.load_der_x509_certificate(der)
        values = [
            extension.value
            for extension in certificate.extensions
            if extension.oid.dotted_string == ROLE_OID
        ]
    except (ValueError, TypeError, x509.DuplicateExtension, x509.UnsupportedGeneralNameType):
        return None
    if len(values) != 1 or not isinstance(values[0], x509.UnrecognizedExtension):
        return None
    return decode_role(values[0].value)


# --------------------------------------------------------------------------- the handshake


@dataclass(slots=True)
class HandshakeNote:
    """What a handshake under way has shown: the client certificate's subject, for the log
    line of a failure (``ssl`` does not show the certificate of a refused handshake)."""

    subject: str | None = None


#: The note of the handshake that runs in the current ``contextvars`` context.
_HANDSHAKE: contextvars.ContextVar[HandshakeNote | None] = contextvars.ContextVar(
    "gateway_tls_handshake", default=None
)
_HANDSHAKE_RECORD = 22  # TLS ContentType handshake
_CERTIFICATE_MESSAGE = 11  # HandshakeType certificate
_TLS13 = 0x0304


def observed(note: HandshakeNote) -> contextvars.Context:
    """A context to run a connection's setup in: its handshake writes into ``note``."""
    context = contextvars.copy_context()
    context.run(_HANDSHAKE.set, note)
    return context


def _observe(
    _conn: object, direction: str, version: int, content_type: int, message: int, data: bytes
) -> None:
    """OpenSSL's message callback during a handshake: note the client certificate's subject."""
    if direction != "read" or content_type != _HANDSHAKE_RECORD or message != _CERTIFICATE_MESSAGE:
        return
    note = _HANDSHAKE.get()
    if note is not None and note.subject is None:
        note.subject = certificate_message_subject(data, int(version) == _TLS13)


def certificate_message_subject(message: bytes, tls13: bool) -> str | None:
    """The subject of the first certificate of a Certificate handshake message (with its
    4-byte header); TLS 1.3 puts a request context before the list. ``None``: none."""
    from cryptography import x509

    for form in (tls13, not tls13):
        offset = 4 + (1 + message[4] if form and len(message) > 4 else 0) + 3
        length = int.from_bytes(message[offset : offset + 3], "big")
        try:
            der = message[offset + 3 : offset + 3 + length]
            return subject_of(x509.load_der_x509_certificate(der)) if der else None
        except ValueError:
            continue
    return None


def leaf_subject(chain: Sequence[bytes]) -> str | None:
    """The subject of a verified chain's leaf (DER), for the audit log; ``None``: none."""
    if not chain:
        return None
    from cryptography import x509

    try:
        return subject_of(x509.load_der_x509_certificate(chain[0]))
    except ValueError:
        return None


def role_of(transport: asyncio.BaseTransport) -> tuple[bool, str | None]:
    """(is TLS, role) of an accepted transport: the role read once from the client certificate.

    The handshake is done: the session moves to its listener's unobserved twin context.
    """
    ssl_object: Any = transport.get_extra_info("ssl_object")
    if ssl_object is None:
        return False, None
    settled = getattr(ssl_object.context, "settled", None)
    if isinstance(settled, ssl.SSLContext):
        ssl_object.context = settled
    return True, role_from_certificate(ssl_object.getpeercert(binary_form=True))


def peer_chain(transport: asyncio.BaseTransport) -> tuple[bytes, ...]:
    """The client's chain as the handshake verified it (DER, leaf first); ``()`` if not TLS.

    Kept per connection so that a reload can judge it again against new CAs (``ssl``
    cannot verify an open session again). Python 3.13 names the call
    ``get_verified_chain``; before, the ``_ssl`` object under the ``SSLObject`` has it.
    OpenSSL keeps no verified chain on a TLS 1.2 server session: then the chain the
    client sent (which that handshake verified); without either, the leaf alone.
    """
    ssl_object: Any = transport.get_extra_info("ssl_object")
    if ssl_object is None:
        return ()
    for name in ("get_verified_chain", "get_unverified_chain"):
        chain = getattr(ssl_object, name, None)
        if chain is None:
            chain = getattr(getattr(ssl_object, "_sslobj", None), name, None)
        try:
            certificates = chain() if chain is not None else None
            if certificates:
                return tuple(_der_of(certificate) for certificate in certificates)
        except (ssl.SSLError, ValueError, AttributeError, TypeError):
            continue
    leaf = ssl_object.getpeercert(binary_form=True)
    return (leaf,) if leaf else ()


#: ``_ssl.ENCODING_DER``: the private chain call (before 3.13) gives PEM unless told.
_ENCODING_DER = 2


def _der_of(certificate: Any) -> bytes:
    if isinstance(certificate, bytes):
        return certificate  # 3.13's public call gives DER bytes
    return bytes(certificate.public_bytes(_ENCODING_DER))


def _anchor(
    certificate: x509.Certificate, authorities: Sequence[x509.Certificate]
) -> x509.Certificate | None:
    """The CA among ``authorities`` that is ``certificate`` or signed it, if any."""
    from cryptography.exceptions import InvalidSignature

    for authority in authorities:
        if certificate == authority:
            return authority
        if certificate.issuer != authority.subject:
            continue
        try:
            certificate.verify_directly_issued_by(authority)
        except (ValueError, TypeError, InvalidSignature):
            continue
        return authority
    return None


def certificate_facts(
    chain: Sequence[bytes],
    authorities: Sequence[x509.Certificate] | None,
    revocations: Sequence[x509.CertificateRevocationList] = (),
) -> CertificateFacts | None:
    """What a verified chain (DER, leaf first) shows against ``authorities``; ``None``: none.

    Trusted when a certificate of the chain is one of the CAs, or is signed by one
    (a CA renewed with the same key still anchors it). The validity window is the
    intersection of the windows along the chain up to that CA (the CA included).
    ``authorities`` ``None`` (not known): the handshake's verdict stands, the whole
    chain's window counts. Revoked: the leaf's serial is in a CRL of ``revocations``
    signed by the leaf's issuer (the leaf alone, as the handshake checks it).
    """
    from cryptography import x509

    try:
        certificates = [x509.load_der_x509_certificate(der) for der in chain]
    except ValueError:
        return None
    if not certificates:
        return None
    revoked = _revoked(certificates, authorities or (), revocations)
    if authorities is None:
        return _facts(certificates, trusted=True, revoked=revoked)
    for index, certificate in enumerate(certificates):
        anchor = _anchor(certificate, authorities)
        if anchor is not None:
            return _facts([*certificates[: index + 1], anchor], trusted=True, revoked=revoked)
    return _facts(certificates[:1], trusted=False, revoked=revoked)  # the leaf's own window


def _revoked(
    chain: Sequence[x509.Certificate],
    authorities: Sequence[x509.Certificate],
    revocations: Sequence[x509.CertificateRevocationList],
) -> bool:
    """True when a CRL of the leaf's issuer, signed by it, lists the leaf's serial."""
    leaf = chain[0]
    issuers = [c for c in (*chain[1:], *authorities) if c.subject == leaf.issuer]
    for crl in revocations:
        if crl.issuer != leaf.issuer:
            continue
        if crl.get_revoked_certificate_by_serial_number(leaf.serial_number) is None:
            continue
        for issuer in issuers:
            try:
                if crl.is_signature_valid(issuer.public_key()):  # type: ignore[arg-type]
                    return True
            except (TypeError, ValueError):
                continue
    return False


def _facts(
    path: Sequence[x509.Certificate], *, trusted: bool, revoked: bool = False
) -> CertificateFacts:
    return CertificateFacts(
        max(c.not_valid_before_utc for c in path).timestamp(),
        min(c.not_valid_after_utc for c in path).timestamp(),
        trusted,
        revoked,
    )
