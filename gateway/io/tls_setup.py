"""Setting up TLS from files, for every side of the gateway that speaks it: the ``tls``
listeners and the HTTPS endpoint (servers), the ``kind = "tls"`` lines (clients).

A file that cannot be used is a ``TlsSetupError`` whose message names the
configuration key, the file and the fix; a certificate is checked for its dates
when it is read (``check_chain``), so an expired one refuses start-up and the
reload instead of failing every handshake later. ``cryptography`` is loaded with
the first certificate read: a configuration without TLS never imports it.
"""

from __future__ import annotations

import ssl
import time
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # ``cryptography`` loads with the first certificate: TLS configurations only
    from cryptography import x509


class TlsSetupError(Exception):
    """A certificate, key, CA or CRL file cannot be used; the message names the key and the fix."""


# OpenSSL's X509_V_ERR_CERT_NOT_YET_VALID and X509_V_ERR_CERT_HAS_EXPIRED.
EXPIRY_VERIFY_CODES = frozenset({9, 10})

#: The suites with forward secrecy (ECDHE), strongest first; TLS 1.3's own suites come
#: before them whatever this says. No NULL, anonymous, SHA-1 or CCM suite.
FORWARD_SECRET_SUITES = "ECDHE+AESGCM:ECDHE+CHACHA20:ECDHE+AES:!aNULL:!eNULL:!SHA1:!AESCCM"
#: TLS_RSA_WITH_AES_128_CBC_SHA256, the suite MB-TCP-Security v21 R-14 requires: RSA key
#: exchange (an RSA server certificate), no forward secrecy, so listed last.
REQUIRED_SUITE = "AES128-SHA256"


def cipher_string(forward_secrecy_only: bool) -> str:
    """The OpenSSL cipher list of a listener (the server's order is the one used)."""
    return (
        FORWARD_SECRET_SUITES
        if forward_secrecy_only
        else f"{FORWARD_SECRET_SUITES}:{REQUIRED_SUITE}"
    )


@dataclass(frozen=True, slots=True)
class CertificateInfo:
    """One certificate a listener or a tls line (``listener``: its name) uses, for the expiry
    metric."""

    listener: str
    kind: str  #: ``server`` (the leaf), ``chain`` (an intermediate it sends) or ``ca``
    subject: str
    not_after: datetime

    def seconds_left(self, now: float | None = None) -> float:
        """Seconds until ``notAfter`` (negative once expired)."""
        return self.not_after.timestamp() - (time.time() if now is None else now)


def subject_of(certificate: x509.Certificate) -> str:
    """A certificate's common name, else its whole subject: how logs and metrics name it."""
    from cryptography.x509.oid import NameOID

    names = certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if names:
        return str(names[0].value)
    return certificate.subject.rfc4514_string() or "(no subject)"


#: The fix of a TLS file the gateway cannot read.
_READ_FIX = "; check the path, and that the gateway's user may read the file"


def read_pem_certificates(path: str, key: str) -> list[x509.Certificate]:
    """Every certificate in the PEM file ``path`` (configuration key ``key``)."""
    from cryptography import x509

    try:
        with open(path, "rb") as handle:
            data = handle.read()
    except OSError as error:
        raise TlsSetupError(
            f"{key} = {path!r}: cannot read: {error.strerror or error}{_READ_FIX}"
        ) from None
    try:
        certificates = x509.load_pem_x509_certificates(data)
    except ValueError:
        raise TlsSetupError(
            f"{key} = {path!r}: no PEM certificate in it (expected -----BEGIN CERTIFICATE-----)"
        ) from None
    return certificates


def check_chain(path: str, key: str, moment: datetime) -> list[x509.Certificate]:
    """The certificates in the chain file ``path`` (configuration key ``key``), each valid at
    ``moment``; raise ``TlsSetupError`` naming the key, the file and the fix."""
    chain = read_pem_certificates(path, key)
    for index, certificate in enumerate(chain):
        kind = "server" if index == 0 else "chain"
        subject = subject_of(certificate)
        if moment < certificate.not_valid_before_utc:
            raise TlsSetupError(
                f"{key} = {path!r}: the {kind} certificate {subject!r} is not valid before "
                f"{certificate.not_valid_before_utc:%Y-%m-%d %H:%M:%S} UTC; check the clock or "
                "issue it again"
            )
        if moment > certificate.not_valid_after_utc:
            raise TlsSetupError(
                f"{key} = {path!r}: the {kind} certificate {subject!r} expired on "
                f"{certificate.not_valid_after_utc:%Y-%m-%d %H:%M:%S} UTC; renew it, then reload "
                "(SIGHUP)"
            )
    return chain


def load_key_pair(context: ssl.SSLContext, cert: str, key: str, names: tuple[str, str]) -> None:
    """Load the chain ``cert`` and its private ``key`` (their configuration keys: ``names``)
    into ``context``; raise ``TlsSetupError`` naming the key, the file and the fix."""
    cert_name, key_name = names
    try:
        context.load_cert_chain(cert, key)
    except ssl.SSLError as error:
        raise TlsSetupError(
            f"{key_name} = {key!r}: cannot be used with {cert_name} = {cert!r} "
            f"({error.reason or error}); give the private key of the certificate's first "
            "(leaf) entry, unencrypted PEM"
        ) from None
    except OSError as error:
        raise TlsSetupError(
            f"{key_name} = {key!r}: cannot read: {error.strerror or error}{_READ_FIX}"
        ) from None


def load_authorities(context: ssl.SSLContext, path: str, key: str) -> None:
    """Trust the CA certificates in ``path`` (configuration key ``key``) for client
    certificates; raise ``TlsSetupError`` naming the key and the file."""
    read_pem_certificates(path, key)  # a missing file or no PEM: the message with its fix
    try:
        context.load_verify_locations(cafile=path)
    except (ssl.SSLError, OSError) as error:
        raise TlsSetupError(f"{key} = {path!r}: cannot be used: {error}") from None
