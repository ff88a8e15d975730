"""Revocation: a tls listener's ``crl``, at the handshake and at every reload, over loopback.

A client revoked by a CRL the test writes while it is connected and served is
closed at the reload that brings the list (counted ``no_longer_admitted``,
logged once with its reason), a new connection of it is refused at the
handshake (counted ``revoked_certificate``), and another client goes on being
served. An unreadable or expired list is a start-up and reload error naming the
key and the fix; the running configuration stays on a rejected reload.
"""

from __future__ import annotations

import datetime as dt
import logging
import ssl
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.x509.oid import NameOID

from gateway.config import build_config
from gateway.io.listeners.tls import certificate_facts, server_context
from gateway.io.tls_setup import TlsSetupError
from gateway.sim import plc
from gateway.sim.pki import DAY, Pki
from tests.helpers import (
    ConnectionClosedError,
    GatewayFactory,
    LogCollector,
    RawClient,
    RunningGateway,
    SimFactory,
    client_context,
    wait_until,
)

READ = bytes.fromhex("03 0000 0001")
READ_ANSWER = bytes.fromhex("03 02 0000")


def tables_with(make_sim: SimFactory, pki: Pki, crl: Path) -> dict[str, Any]:
    sim = make_sim({1: plc(1)})
    listener: dict[str, Any] = {
        "name": "tls", "protocol": "tls", "listen": "127.0.0.1:0", "cert": str(pki.server_chain),
        "key": str(pki.server_key), "ca": str(pki.ca), "crl": str(crl),
    }  # fmt: skip
    return {
        "server": {"listen": "127.0.0.1:0"}, "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1])}, "listeners": [listener],
    }  # fmt: skip


def sample(gw: RunningGateway, name: str, labels: dict[str, str]) -> float:
    value = gw.call(lambda: gw.gateway.metrics.registry.get_sample_value(name, labels))
    return 0.0 if value is None else value


def test_a_client_revoked_in_mid_session_is_closed_at_the_reload_and_refused_after(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path,
    access_log: LogCollector,
) -> None:  # fmt: skip
    crl = pki.write_crl(tmp_path / "crl.pem")  # nobody revoked yet
    tables = tables_with(make_sim, pki, crl)
    gw = make_gateway(tables)
    address = gw.call(lambda: gw.gateway.listener_address("tls"))
    with (
        RawClient(address, context=client_context(pki, "operator")) as revoked,
        RawClient(address, context=client_context(pki, "viewer")) as kept,
    ):
        assert revoked.request(1, READ) == READ_ANSWER
        assert kept.request(1, READ) == READ_ANSWER
        pki.write_crl(crl, revoked=("operator",))
        gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))
        assert revoked.is_closed_by_peer()
        for _ in range(3):
            assert kept.request(1, READ) == READ_ANSWER
    with (
        pytest.raises((ssl.SSLError, ConnectionError, ConnectionClosedError)),
        RawClient(address, context=client_context(pki, "operator")) as again,
    ):
        again.request(1, READ)  # TLS 1.3: the refusal may come after the handshake
    closed = {"reason": "no_longer_admitted"}
    assert sample(gw, "modbus_gateway_connections_closed_total", closed) == 1
    refused = {"listener": "tls", "reason": "revoked_certificate"}
    name = "modbus_gateway_tls_handshake_failures_total"
    wait_until(lambda: sample(gw, name, refused) == 1, "the new handshake refused as revoked")
    closes = [m for m in access_log.messages if "no longer admitted" in m]
    assert len(closes) == 1 and "certificate_revoked" in closes[0], closes
    failures = [m for m in access_log.messages if "TLS handshake failed" in m]
    assert any(
        "revoked" in m and "peer 127.0.0.1:" in m and "master-operator" in m for m in failures
    ), failures


def test_an_expired_or_unreadable_crl_refuses_start_and_reload(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path
) -> None:
    expired = pki.write_crl(tmp_path / "expired.pem", next_update=-DAY)
    tables = tables_with(make_sim, pki, expired)
    listener = build_config(tables, "<test>").listeners[-1]
    with pytest.raises(TlsSetupError, match=r"crl = .*expired on .*fetch the current one"):
        server_context(listener)
    missing = build_config(tables_with(make_sim, pki, tmp_path / "none.pem"), "<test>")
    with pytest.raises(TlsSetupError, match=r"crl = .*none\.pem.*cannot read"):
        server_context(missing.listeners[-1])
    garbage = tmp_path / "garbage.pem"
    garbage.write_text("not a CRL\n")
    with pytest.raises(TlsSetupError, match=r"crl = .*no PEM CRL in it"):
        server_context(build_config(tables_with(make_sim, pki, garbage), "<t>").listeners[-1])
    good = pki.write_crl(tmp_path / "good.pem")
    gw = make_gateway(tables_with(make_sim, pki, good))
    address = gw.call(lambda: gw.gateway.listener_address("tls"))
    with RawClient(address, context=client_context(pki, "operator")) as master:
        assert master.request(1, READ) == READ_ANSWER
        gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))  # rejected: expired
        assert master.request(1, READ) == READ_ANSWER
    with RawClient(
        address, context=client_context(pki, "operator")
    ) as again:  # the running list still serves
        assert again.request(1, READ) == READ_ANSWER


def test_a_crl_close_to_its_next_update_is_warned_about(
    make_sim: SimFactory, pki: Pki, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    soon = pki.write_crl(tmp_path / "soon.pem", next_update=dt.timedelta(hours=1))
    with caplog.at_level(logging.WARNING, logger="gateway.tls"):
        server_context(build_config(tables_with(make_sim, pki, soon), "<t>").listeners[-1])
    assert any("soon.pem" in m and "nextUpdate" in m for m in caplog.messages), caplog.messages


def test_the_facts_of_a_revoked_chain(pki: Pki, tmp_path: Path) -> None:
    crl_path = pki.write_crl(tmp_path / "crl.pem", revoked=("viewer",))
    crl = x509.load_pem_x509_crl(crl_path.read_bytes())
    root = pki.root.certificate

    def chain(name: str) -> tuple[bytes, ...]:
        pem = Path(pki.client(name)[0]).read_bytes()
        return tuple(
            c.public_bytes(serialization.Encoding.DER) for c in x509.load_pem_x509_certificates(pem)
        )

    viewer = certificate_facts(chain("viewer"), [root], [crl])
    operator = certificate_facts(chain("operator"), [root], [crl])
    assert viewer is not None and viewer.revoked and viewer.trusted
    assert operator is not None and not operator.revoked
    # A list naming the serial but not signed by the leaf's issuer does not revoke it.
    other = (
        x509.CertificateRevocationListBuilder()
        .issuer_name(pki.intermediate.certificate.subject)
        .last_update(dt.datetime.now(dt.UTC) - DAY)
        .next_update(dt.datetime.now(dt.UTC) + DAY)
    )
    other = other.add_revoked_certificate(
        x509.RevokedCertificateBuilder()
        .serial_number(pki.serial_of("operator"))
        .revocation_date(dt.datetime.now(dt.UTC) - DAY)
        .build()
    )
    forged = other.sign(pki.other_root.key, hashes.SHA256())
    facts = certificate_facts(chain("operator"), [root], [forged])
    assert facts is not None and not facts.revoked


def crl_samples(gw: RunningGateway) -> dict[tuple[str, str], float]:
    """``tls_crl_next_update_seconds`` by (listener, issuer), as a scrape reads them."""

    def read() -> dict[tuple[str, str], float]:
        return {
            (sample.labels["listener"], sample.labels["issuer"]): sample.value
            for family in gw.gateway.metrics.registry.collect()
            if family.name == "modbus_gateway_tls_crl_next_update_seconds"
            for sample in family.samples
        }

    return gw.call(read)


def test_the_crls_next_update_is_counted_down_and_read_again_at_a_reload(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path
) -> None:
    crl = pki.write_crl(tmp_path / "crl.pem", next_update=7 * DAY)
    tables = tables_with(make_sim, pki, crl)
    gw = make_gateway(tables)
    names = pki.intermediate.certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    issuer = str(names[0].value)
    [(labels, left)] = crl_samples(gw).items()
    assert labels == ("tls", issuer)
    assert 7 * 86400 - 120 < left <= 7 * 86400
    pki.write_crl(crl, next_update=2 * DAY)  # the next list is due sooner
    gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))
    [(labels, left)] = crl_samples(gw).items()
    assert labels == ("tls", issuer) and 2 * 86400 - 120 < left <= 2 * 86400
