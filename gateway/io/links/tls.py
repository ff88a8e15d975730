"""Modbus/TCP Security on a line: the client side of a ``kind = "tls"`` line.

Theory of operation. ``client_context`` builds the ``ssl.SSLContext`` a tls line
connects to its slave with: TLS 1.2 or newer, the gateway's own certificate
presented, the slave's verified against the line's ``ca`` and (unless
``check_server_name = false``) its ``server_name``. It is built again on every
SIGHUP; the line's next handshake uses it. A handshake that fails is mapped to a
``LineTlsFailure`` (a metric label) and to one log line that names the key to
fix (``line_failure_message``).
"""

from __future__ import annotations

import enum
import ssl
from dataclasses import dataclass
from datetime import UTC, datetime

from ...config import LineConfig
from ..tls_setup import (
    EXPIRY_VERIFY_CODES,
    CertificateInfo,
    TlsSetupError,
    read_pem_certificates,
    subject_of,
)


class LineTlsFailure(enum.StrEnum):
    """Why a ``kind = "tls"`` line could not set up TLS with its slave.

    The ``reason`` label of ``line_tls_failures_total``; the line's log says it once.
    """

    UNTRUSTED_CERTIFICATE = "untrusted_certificate"  # the slave's does not chain to the line's ca
    EXPIRED_CERTIFICATE = "expired_certificate"  # the slave's expired (or is not yet valid)
    NAME_MISMATCH = "name_mismatch"  # the slave's certificate is not for server_name
    CERTIFICATE_REFUSED = "certificate_refused"  # the slave refused the gateway's certificate
    PROTOCOL_VERSION = "protocol_version"  # no TLS version in common (1.2 and 1.3 only)
    NOT_TLS = "not_tls"  # the slave answered, but not in TLS (a plain Modbus TCP port?)
    TIMEOUT = "timeout"  # no complete handshake within tls_handshake_timeout
    CLOSED = "closed"  # the slave closed the connection during the handshake
    OTHER = "other"


# OpenSSL's X509_V_ERR_HOSTNAME_MISMATCH and X509_V_ERR_IP_ADDRESS_MISMATCH.
_NAME_VERIFY_CODES = frozenset({62, 64})


def line_failure_reason(error: BaseException) -> LineTlsFailure:
    """Map an error from a tls line's handshake (or its first read) to its ``LineTlsFailure``."""
    if isinstance(error, ssl.SSLCertVerificationError):
        if error.verify_code in _NAME_VERIFY_CODES:
            return LineTlsFailure.NAME_MISMATCH
        if error.verify_code in EXPIRY_VERIFY_CODES:
            return LineTlsFailure.EXPIRED_CERTIFICATE
        return LineTlsFailure.UNTRUSTED_CERTIFICATE
    if isinstance(error, ssl.SSLError):
        reason = (error.reason or "").upper()
        if reason in ("WRONG_VERSION_NUMBER", "PACKET_LENGTH_TOO_LONG", "RECORD_LAYER_FAILURE"):
            return LineTlsFailure.NOT_TLS
        if "VERSION" in reason or "UNSUPPORTED_PROTOCOL" in reason:
            return LineTlsFailure.PROTOCOL_VERSION
        if "ALERT" in reason and any(
            word in reason for word in ("CERTIFICATE", "UNKNOWN_CA", "ACCESS_DENIED")
        ):  # the slave's verdict on the gateway's certificate (TLS 1.3: after the handshake)
            return LineTlsFailure.CERTIFICATE_REFUSED
        if isinstance(error, ssl.SSLEOFError):
            return LineTlsFailure.CLOSED
        return LineTlsFailure.OTHER
    if isinstance(error, TimeoutError) or "longer than" in str(error):
        return LineTlsFailure.TIMEOUT
    if isinstance(error, OSError):
        return LineTlsFailure.CLOSED
    return LineTlsFailure.OTHER


def line_failure_message(line: LineConfig, reason: LineTlsFailure, error: BaseException) -> str:
    """One line for the log: what failed with the slave, and the fix."""
    prefix = f"lines.{line.name}."
    detail = getattr(error, "verify_message", None) or getattr(error, "reason", None) or error
    where = f"line {line.name!r}: TLS with {line.device}"
    if reason is LineTlsFailure.UNTRUSTED_CERTIFICATE:
        return (
            f"{where}: the slave's certificate does not chain to {prefix}ca = {line.ca!r} "
            f"({detail}); give the CA that issued the slave's certificate"
        )
    if reason is LineTlsFailure.EXPIRED_CERTIFICATE:
        return (
            f"{where}: the slave's certificate is expired or not yet valid ({detail}); "
            "renew the slave's certificate, or check the gateway's clock"
        )
    if reason is LineTlsFailure.NAME_MISMATCH:
        return (
            f"{where}: the slave's certificate is not for {line.server_name!r} ({detail}); "
            f"set {prefix}server_name to a name its certificate carries"
        )
    if reason is LineTlsFailure.CERTIFICATE_REFUSED:
        return (
            f"{where}: the slave refused the gateway's certificate {prefix}cert = "
            f"{line.cert!r} ({detail}); the slave must trust its CA, and it must be "
            "valid now"
        )
    if reason is LineTlsFailure.PROTOCOL_VERSION:
        return (
            f"{where}: no TLS version in common ({detail}); Modbus/TCP Security needs "
            "TLS 1.2 or newer on the slave"
        )
    if reason is LineTlsFailure.NOT_TLS:
        return (
            f"{where}: the slave did not answer in TLS ({detail}); is this its Modbus/TCP "
            'Security port (802)? A plain Modbus TCP slave is kind = "tcp"'
        )
    if reason is LineTlsFailure.TIMEOUT:
        return (
            f"{where}: no complete handshake within {line.tls_handshake_timeout:g} s "
            f"({prefix}tls_handshake_timeout)"
        )
    if reason is LineTlsFailure.CLOSED:
        return (
            f"{where}: the slave closed the connection during the handshake, or after it "
            f"before answering anything ({detail}); it may refuse the gateway's certificate "
            f"{prefix}cert = {line.cert!r} or address, or not speak TLS on this port (a "
            "plain Modbus TCP port closes on the TLS hello)"
        )
    return f"{where}: handshake failed: {detail}"


@dataclass
class ClientTls:
    """A tls line's built TLS context and the certificates it rests on (``listener``: the line)."""

    context: ssl.SSLContext
    certificates: list[CertificateInfo]


def client_context(line: LineConfig, now: datetime | None = None) -> ClientTls:
    """The TLS context of a ``kind = "tls"`` line; ``TlsSetupError`` names the key and the fix.

    TLS 1.2 or newer, the gateway's client certificate presented, the slave's
    certificate verified against ``ca`` and, unless ``check_server_name = false``,
    for ``server_name``.
    """
    assert line.cert and line.key and line.ca
    prefix = f"lines.{line.name}."
    moment = now or datetime.now(UTC)
    infos: list[CertificateInfo] = []
    for index, certificate in enumerate(read_pem_certificates(line.cert, f"{prefix}cert")):
        kind = "client" if index == 0 else "chain"
        subject = subject_of(certificate)
        infos.append(CertificateInfo(line.name, kind, subject, certificate.not_valid_after_utc))
        if moment < certificate.not_valid_before_utc:
            raise TlsSetupError(
                f"{prefix}cert = {line.cert!r}: the {kind} certificate {subject!r} is not valid "
                f"before {certificate.not_valid_before_utc:%Y-%m-%d %H:%M:%S} UTC; check the "
                "clock or issue it again"
            )
        if moment > certificate.not_valid_after_utc:
            raise TlsSetupError(
                f"{prefix}cert = {line.cert!r}: the {kind} certificate {subject!r} expired on "
                f"{certificate.not_valid_after_utc:%Y-%m-%d %H:%M:%S} UTC; renew it, then reload "
                "(SIGHUP)"
            )
    for authority in read_pem_certificates(line.ca, f"{prefix}ca"):
        infos.append(
            CertificateInfo(line.name, "ca", subject_of(authority), authority.not_valid_after_utc)
        )
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)  # verifies the chain and the name
    context.minimum_version = ssl.TLSVersion.TLSv1_2  # the specification: never 1.1, 1.0 or SSL
    context.options |= ssl.OP_NO_RENEGOTIATION | ssl.OP_NO_COMPRESSION
    if not line.check_server_name:
        context.check_hostname = False  # the chain is still verified: verify_mode stays
    try:
        context.load_cert_chain(line.cert, line.key)
    except ssl.SSLError as error:
        raise TlsSetupError(
            f"{prefix}key = {line.key!r}: cannot be used with {prefix}cert = {line.cert!r} "
            f"({error.reason or error}); give the private key of the certificate's first "
            "(leaf) entry, unencrypted PEM"
        ) from None
    except OSError as error:
        raise TlsSetupError(
            f"{prefix}key = {line.key!r}: cannot read: {error.strerror or error}"
        ) from None
    try:
        context.load_verify_locations(cafile=line.ca)
    except (ssl.SSLError, OSError) as error:
        raise TlsSetupError(f"{prefix}ca = {line.ca!r}: cannot be used: {error}") from None
    return ClientTls(context, infos)
