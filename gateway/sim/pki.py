"""A throwaway PKI for TLS tests and the benchmark, made with ``cryptography`` on the spot.

No key is ever committed or shipped: every run makes its own.

``make_pki(directory)`` writes PEM files: a root CA, an intermediate CA, the
server's chain (leaf + intermediate) and key, and client certificates (each
file the client's certificate followed by the intermediate) with the role
``operator``, ``viewer``, no role, two role extensions, an INTEGER instead of a
UTF8String, an expired one and one from another CA. Keys are EC P-256 by default:
quick to make, and what small Modbus devices use. ``make_pki(directory,
KeyAlgorithm.RSA)`` makes the same PKI with RSA 2048 keys: the key exchange of
the specification's required suite TLS_RSA_WITH_AES_128_CBC_SHA256 needs an RSA
server certificate. ``Pki.write_crl`` writes a revocation list of the
intermediate CA (the issuer of the clients) naming some clients.
"""

from __future__ import annotations

import datetime as dt
import enum
import ipaddress
from dataclasses import dataclass, field
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, padding, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

ROLE_OID = x509.ObjectIdentifier("1.3.6.1.4.1.50316.802.1")
#: Same encoded length as ROLE_OID: written, then patched into a second role extension.
_PLACEHOLDER_OID = x509.ObjectIdentifier("1.3.6.1.4.1.50316.802.9")
DAY = dt.timedelta(days=1)


def utf8_string(text: str) -> bytes:
    """DER of an ASN.1 UTF8String (short form length: roles are short)."""
    data = text.encode()
    assert len(data) < 128
    return bytes([0x0C, len(data)]) + data


def der_integer(value: int) -> bytes:
    """DER of a small non-negative ASN.1 INTEGER."""
    assert 0 <= value < 128
    return bytes([0x02, 0x01, value])


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


class KeyAlgorithm(enum.StrEnum):
    """The kind of every key of a test PKI."""

    EC = "ec"  #: P-256
    RSA = "rsa"  #: 2048 bits


PrivateKey = ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey


def _key(algorithm: KeyAlgorithm = KeyAlgorithm.EC) -> PrivateKey:
    if algorithm == KeyAlgorithm.RSA:
        return rsa.generate_private_key(public_exponent=65537, key_size=2048)
    return ec.generate_private_key(ec.SECP256R1())


def _sign(key: PrivateKey, data: bytes) -> bytes:
    """A SHA-256 signature of ``data`` (ECDSA, or RSA PKCS#1 v1.5 as certificates use)."""
    if isinstance(key, rsa.RSAPrivateKey):
        return key.sign(data, padding.PKCS1v15(), hashes.SHA256())
    return key.sign(data, ec.ECDSA(hashes.SHA256()))


def _key_pem(key: PrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _pem(*certificates: x509.Certificate) -> bytes:
    return b"".join(c.public_bytes(serialization.Encoding.PEM) for c in certificates)


@dataclass
class Authority:
    """A CA: its certificate and key."""

    certificate: x509.Certificate
    key: PrivateKey


def _ca(
    common_name: str,
    issuer: Authority | None,
    now: dt.datetime,
    path_length: int | None,
    algorithm: KeyAlgorithm = KeyAlgorithm.EC,
) -> Authority:
    key = _key(algorithm)
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(issuer.certificate.subject if issuer else _name(common_name))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - DAY)
        .not_valid_after(now + 3650 * DAY)
        .add_extension(x509.BasicConstraints(ca=True, path_length=path_length), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
    )
    signer = issuer.key if issuer else key
    return Authority(builder.sign(signer, hashes.SHA256()), key)


def _leaf_builder(
    common_name: str,
    issuer: Authority,
    key: PrivateKey,
    not_before: dt.datetime,
    not_after: dt.datetime,
    usage: x509.ObjectIdentifier,
) -> x509.CertificateBuilder:
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(issuer.certificate.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before)
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
    )
    if usage == ExtendedKeyUsageOID.SERVER_AUTH:
        builder = builder.add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
    return builder


# -- a certificate with the role extension twice: cryptography refuses to build one, so the
#    second is written under a placeholder OID of the same length, patched, and signed again.


def _der_length(data: bytes, offset: int) -> tuple[int, int]:
    """(length, offset of the content) of the DER element whose length byte is at ``offset``."""
    first = data[offset]
    if first < 0x80:
        return first, offset + 1
    count = first & 0x7F
    return int.from_bytes(data[offset + 1 : offset + 1 + count], "big"), offset + 1 + count


def _der_header(tag: int, length: int) -> bytes:
    if length < 0x80:
        return bytes([tag, length])
    size = (length.bit_length() + 7) // 8
    return bytes([tag, 0x80 | size]) + length.to_bytes(size, "big")


def _oid_der(oid: x509.ObjectIdentifier) -> bytes:
    arcs = [int(arc) for arc in oid.dotted_string.split(".")]
    body = bytearray([40 * arcs[0] + arcs[1]])
    for arc in arcs[2:]:
        chunk = [arc & 0x7F]
        arc >>= 7
        while arc:
            chunk.append(0x80 | (arc & 0x7F))
            arc >>= 7
        body += bytes(reversed(chunk))
    return _der_header(0x06, len(body)) + bytes(body)


def _with_duplicated_role(certificate: x509.Certificate, issuer: Authority) -> x509.Certificate:
    der = certificate.public_bytes(serialization.Encoding.DER)
    _, tbs_start = _der_length(der, 1)  # inside the outer SEQUENCE
    tbs_length, tbs_content = _der_length(der, tbs_start + 1)
    tbs_end = tbs_content + tbs_length
    algorithm_length, algorithm_content = _der_length(der, tbs_end + 1)
    algorithm = der[tbs_end : algorithm_content + algorithm_length]
    old, new = _oid_der(_PLACEHOLDER_OID), _oid_der(ROLE_OID)
    tbs = der[tbs_start:tbs_end]
    assert len(old) == len(new) and tbs.count(old) == 1
    tbs = tbs.replace(old, new)
    signature = _sign(issuer.key, tbs)
    bit_string = _der_header(0x03, len(signature) + 1) + b"\x00" + signature
    body = tbs + algorithm + bit_string
    patched = x509.load_der_x509_certificate(_der_header(0x30, len(body)) + body)
    return patched


@dataclass
class Pki:
    """The files of a throwaway PKI (paths), and its CAs for further certificates."""

    directory: Path
    root: Authority
    intermediate: Authority
    other_root: Authority
    ca: Path  #: the root CA: what the server trusts for client certificates
    server_chain: Path
    server_key: Path
    clients: dict[str, tuple[Path, Path]] = field(default_factory=dict)  #: name → (chain, key)
    algorithm: KeyAlgorithm = KeyAlgorithm.EC

    def serial_of(self, name: str) -> int:
        """The serial number of client ``name``'s certificate."""
        chain, _ = self.clients[name]
        return x509.load_pem_x509_certificates(chain.read_bytes())[0].serial_number

    def write_crl(
        self,
        path: Path,
        revoked: tuple[str, ...] = (),
        next_update: dt.timedelta = 7 * DAY,
        last_update: dt.datetime | None = None,
    ) -> Path:
        """Write the intermediate CA's CRL (PEM) revoking clients ``revoked``; return ``path``.

        A negative ``next_update`` makes an expired list.
        """
        now = last_update or dt.datetime.now(dt.UTC)
        builder = (
            x509.CertificateRevocationListBuilder()
            .issuer_name(self.intermediate.certificate.subject)
            .last_update(min(now, now + next_update) - DAY)
            .next_update(now + next_update)
        )
        for name in revoked:
            builder = builder.add_revoked_certificate(
                x509.RevokedCertificateBuilder()
                .serial_number(self.serial_of(name))
                .revocation_date(now - dt.timedelta(seconds=1))
                .build()
            )
        crl = builder.sign(self.intermediate.key, hashes.SHA256())
        path.write_bytes(crl.public_bytes(serialization.Encoding.PEM))
        return path

    def client(self, name: str) -> tuple[str, str]:
        """(certificate chain file, key file) of client ``name``, as strings."""
        chain, key = self.clients[name]
        return str(chain), str(key)

    def server_certificate(
        self, name: str, not_before: dt.datetime, not_after: dt.datetime
    ) -> tuple[Path, Path]:
        """Another server chain and key, with the given validity (expired, not yet valid)."""
        key = _key(self.algorithm)
        certificate = _leaf_builder(
            "modbus-gateway",
            self.intermediate,
            key,
            not_before,
            not_after,
            ExtendedKeyUsageOID.SERVER_AUTH,
        ).sign(self.intermediate.key, hashes.SHA256())
        chain = self.directory / f"{name}.chain.pem"
        chain.write_bytes(_pem(certificate, self.intermediate.certificate))
        key_path = self.directory / f"{name}.key"
        key_path.write_bytes(_key_pem(key))
        return chain, key_path


#: Client certificates made by ``make_pki``: name → role extension value (DER), or a marker.
CLIENTS: dict[str, bytes | str | None] = {
    "operator": utf8_string("operator"),
    "viewer": utf8_string("viewer"),
    "admin": utf8_string("admin"),
    "norole": None,
    "tworoles": "duplicate",
    "integer": der_integer(5),
    "expired": utf8_string("operator"),
    "otherca": utf8_string("operator"),
}


def make_pki(directory: Path, algorithm: KeyAlgorithm = KeyAlgorithm.EC) -> Pki:
    """Write the whole PKI under ``directory`` (see the module docstring)."""
    now = dt.datetime.now(dt.UTC)
    root = _ca("Test Root CA", None, now, 1, algorithm)
    intermediate = _ca("Test Intermediate CA", root, now, 0, algorithm)
    other_root = _ca("Other Root CA", None, now, 0, algorithm)
    ca_file = directory / "ca.pem"
    ca_file.write_bytes(_pem(root.certificate))
    pki = Pki(directory, root, intermediate, other_root, ca_file, Path(), Path())
    pki.algorithm = algorithm
    pki.server_chain, pki.server_key = pki.server_certificate("server", now - DAY, now + 365 * DAY)
    for name, role in CLIENTS.items():
        key = _key(algorithm)
        issuer = other_root if name == "otherca" else intermediate
        not_before, not_after = now - DAY, now + 365 * DAY
        if name == "expired":
            not_before, not_after = now - 30 * DAY, now - DAY
        builder = _leaf_builder(
            f"master-{name}", issuer, key, not_before, not_after, ExtendedKeyUsageOID.CLIENT_AUTH
        )
        if isinstance(role, bytes):
            builder = builder.add_extension(x509.UnrecognizedExtension(ROLE_OID, role), False)
        elif role == "duplicate":
            builder = builder.add_extension(
                x509.UnrecognizedExtension(ROLE_OID, utf8_string("operator")), False
            ).add_extension(
                x509.UnrecognizedExtension(_PLACEHOLDER_OID, utf8_string("admin")), False
            )
        certificate = builder.sign(issuer.key, hashes.SHA256())
        if role == "duplicate":
            certificate = _with_duplicated_role(certificate, issuer)
        chain = directory / f"{name}.chain.pem"
        chain.write_bytes(
            _pem(certificate) + (b"" if issuer is other_root else _pem(intermediate.certificate))
        )
        key_path = directory / f"{name}.key"
        key_path.write_bytes(_key_pem(key))
        pki.clients[name] = (chain, key_path)
    return pki
