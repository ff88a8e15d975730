"""A reload judges every open connection again: allow lists, CAs and certificate dates.

Over real loopback TCP and TLS: a master from 127.0.0.2 (a distinct source
without namespaces) is closed when a reload's allow list leaves it out, while a
master from 127.0.0.1 goes on being served; a TLS master whose CA a reload
withdraws is closed, one of a CA still trusted stays. What a closed master had
queued never reaches the line and is answered 0x0A on its own connection only;
the close is counted by reason and logged once with the peer. Certificate expiry
between handshake and reload is decided with literal times in
``tests/unit/test_connection_admission.py``; here the chain's facts are checked
on real certificates.
"""

from __future__ import annotations

import datetime as dt
import json
import socket
import ssl
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization

from gateway.config import build_config
from gateway.core.crc import append_crc, check_crc
from gateway.io.audit import verify_files
from gateway.io.listeners.tls import certificate_facts
from gateway.sim import plc
from gateway.sim.line import UnitFaults
from gateway.sim.pki import Pki
from tests.helpers import (
    DEADLINE_S,
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
NO_PATH = bytes.fromhex("83 0A")


def sample(gw: RunningGateway, name: str, labels: dict[str, str] | None = None) -> float:
    value = gw.call(lambda: gw.gateway.metrics.registry.get_sample_value(name, labels or {}))
    return 0.0 if value is None else value


def closed_at_reload(gw: RunningGateway) -> float:
    labels = {"reason": "no_longer_admitted"}
    return sample(gw, "modbus_gateway_connections_closed_total", labels)


def refusals(gw: RunningGateway, path: Path) -> list[dict[str, Any]]:
    """The audit log's ``connection_refused`` records, once the writer caught up."""
    audit = gw.gateway.audit
    assert audit is not None and audit.flush(DEADLINE_S)
    records = [json.loads(line) for line in path.read_text().splitlines()]
    return [r for r in records if r["event"] == "connection_refused"]


def reload(gw: RunningGateway, tables: dict[str, Any]) -> None:
    gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))


def address_of(gw: RunningGateway, name: str) -> tuple[str, int]:
    return gw.call(lambda: gw.gateway.listener_address(name))


# -- allow lists -----------------------------------------------------------------------


def test_a_narrowed_allow_list_closes_the_banned_master_and_spares_the_other(
    make_sim: SimFactory, make_gateway: GatewayFactory, access_log: LogCollector
) -> None:
    sim = make_sim({1: plc(1)})
    tables: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0"},
        "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1])},
    }
    gw = make_gateway(tables)
    with RawClient(gw.address, source="127.0.0.2") as banned, RawClient(gw.address) as kept:
        assert banned.request(1, READ) == READ_ANSWER
        assert kept.request(1, READ) == READ_ANSWER
        tables["server"]["allow"] = ["127.0.0.1/32"]
        reload(gw, tables)
        assert banned.is_closed_by_peer()
        for _ in range(3):  # the other master is untouched, and keeps being served
            assert kept.request(1, READ) == READ_ANSWER
    with RawClient(gw.address, source="127.0.0.2") as again:  # and a new one is refused at accept
        assert again.is_closed_by_peer()
    assert closed_at_reload(gw) == 1
    assert sample(gw, "modbus_gateway_connections_denied_total", {"listener": "tcp"}) == 1
    closes = [m for m in access_log.messages if "no longer admitted" in m]
    assert len(closes) == 1, closes
    assert "127.0.0.2:" in closes[0] and "source_not_allowed" in closes[0]


def test_a_master_closed_at_a_reload_is_in_the_audit_log(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    """One ``connection_refused`` record per connection the reload closed, with the
    reason, beside the one at accept; the chain still verifies."""
    sim = make_sim({1: plc(1)})
    path = tmp_path / "audit.jsonl"
    tables: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0"},
        "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1])},
        "audit": {"path": str(path)},
    }
    gw = make_gateway(tables)
    with RawClient(gw.address, source="127.0.0.2") as banned, RawClient(gw.address) as kept:
        assert banned.request(1, READ) == READ_ANSWER
        tables["server"]["allow"] = ["127.0.0.1/32"]
        reload(gw, tables)
        assert banned.is_closed_by_peer()
        assert kept.request(1, READ) == READ_ANSWER
    with RawClient(gw.address, source="127.0.0.2") as again:
        assert again.is_closed_by_peer()
    closed, refused = refusals(gw, path)
    assert (closed["at"], closed["listener"], closed["source"]) == ("reload", "tcp", "127.0.0.2")
    assert closed["reason"] == "source_not_allowed" and closed["peer"].startswith("127.0.0.2:")
    assert "role" not in closed and "subject" not in closed  # plain TCP: no certificate
    assert (refused["at"], refused["source"]) == ("accept", "127.0.0.2")
    ok, message = verify_files([str(path)])
    assert ok, message


@pytest.mark.slow  # about 3 s or more
def test_a_queued_request_of_a_closed_master_never_reaches_the_line_nor_another_master(
    make_sim: SimFactory, make_gateway: GatewayFactory, access_log: LogCollector
) -> None:
    """The banned master's request on the wire finishes unseen; its queued writes are
    answered 0x0A on its own connection (as at a stop), and never sent."""
    sim = make_sim({1: plc(1)}, faults={1: UnitFaults(reply_delay=1.0)})
    tables: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0"},
        "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1], timeout=3.0)},
    }
    gw = make_gateway(tables)
    write_a, write_b = bytes.fromhex("06 0009 0077"), bytes.fromhex("06 000A 0088")
    with RawClient(gw.address, source="127.0.0.2") as banned, RawClient(gw.address) as kept:
        before = sim.stats().requests
        on_wire = banned.send(1, READ, tid=0x0101)
        wait_until(lambda: sim.stats().requests == before + 1, "the first request on the wire")
        queued = {banned.send(1, write_a, tid=0x0102), banned.send(1, write_b, tid=0x0103)}
        other = kept.send(1, bytes.fromhex("03 0009 0002"), tid=0x0101)  # the same tid
        # Every request is in: the banned master's writes wait in its queue on the line.
        wait_until(lambda: gw.call(lambda: in_flight(gw)) == 4, "four requests in flight")
        tables["server"]["allow"] = ["127.0.0.1/32"]
        reload(gw, tables)
        answers = [banned.receive() for _ in queued]
        assert {(a.transaction_id, a.pdu) for a in answers} == {(t, b"\x86\x0a") for t in queued}
        assert banned.is_closed_by_peer()
        unwritten = bytes.fromhex("03 04 0000 0000")  # registers 9 and 10 as they were
        reply = kept.receive()  # the kept master gets its own answer, once, and nothing else
        assert (reply.transaction_id, reply.pdu) == (other, unwritten)
        assert kept.request(1, bytes.fromhex("03 0009 0002")) == unwritten
        assert not kept_has_more(kept)
    assert on_wire == 0x0101
    assert sim.stats().requests == before + 3  # the read on the wire, and the kept master's two
    assert closed_at_reload(gw) == 1
    closes = [m for m in access_log.messages if "no longer admitted" in m]
    assert len(closes) == 1 and "127.0.0.2:" in closes[0]


def in_flight(gw: RunningGateway) -> int:
    """Requests the masters of the first listener have in flight, as the status page shows."""
    assert gw.gateway.server is not None
    return sum(master.in_flight for master in gw.gateway.server.masters())


def kept_has_more(master: RawClient) -> bool:
    """True when bytes arrive unasked within a short while (a stray answer)."""
    master.sock.settimeout(0.3)
    try:
        return bool(master.sock.recv(1))
    except (TimeoutError, ConnectionResetError):
        return False


def test_a_narrowed_policy_holds_from_the_open_connections_next_request(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    tables: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0", "policy": "p"},
        "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1])},
        "policies": {"p": {"rules": [{"units": [1]}]}},
    }
    gw = make_gateway(tables)
    write = bytes.fromhex("06 0009 0001")
    with RawClient(gw.address, source="127.0.0.2") as master:
        assert master.request(1, write) == write
        tables["policies"] = {"p": {"rules": [{"units": [1], "access": "read"}]}}
        reload(gw, tables)
        assert master.request(1, write) == bytes.fromhex("86 01")  # the same connection
        assert master.request(1, READ) == READ_ANSWER
    assert closed_at_reload(gw) == 0  # rights are per request: the connection stays


def rtu_request(sock: socket.socket, unit: int, pdu: bytes, length: int) -> bytes:
    sock.sendall(append_crc(bytes((unit,)) + pdu))
    data = b""
    while len(data) < length:
        chunk = sock.recv(length - len(data))
        assert chunk, data.hex(" ")
        data += chunk
    assert check_crc(data)
    return data[1:-2]


def test_an_rtu_over_tcp_master_outside_a_narrowed_allow_list_is_closed(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    rtu: dict[str, Any] = {"name": "rtu", "protocol": "rtu-over-tcp", "listen": "127.0.0.1:0"}
    tables: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0"},
        "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1])},
        "listeners": [rtu],
    }
    gw = make_gateway(tables)
    address = address_of(gw, "rtu")
    with socket.create_connection(address, DEADLINE_S, ("127.0.0.2", 0)) as banned:
        assert rtu_request(banned, 1, READ, 7) == READ_ANSWER
        with RawClient(gw.address, source="127.0.0.2") as plain:  # another listener: no change
            rtu["allow"] = ["127.0.0.1"]
            reload(gw, tables)
            assert banned.recv(1) == b""
            assert plain.request(1, READ) == READ_ANSWER
    assert closed_at_reload(gw) == 1


# -- TLS: a withdrawn CA -----------------------------------------------------------------


def pem(*certificates: x509.Certificate) -> bytes:
    return b"".join(c.public_bytes(serialization.Encoding.PEM) for c in certificates)


def tls_tables(make_sim: SimFactory, pki: Pki, ca: Path | str) -> dict[str, Any]:
    """The tables of a gateway with one tls listener (``tls``) trusting the CA file ``ca``."""
    sim = make_sim({1: plc(1)})
    listener: dict[str, Any] = {
        "name": "tls", "protocol": "tls", "listen": "127.0.0.1:0", "cert": str(pki.server_chain),
        "key": str(pki.server_key), "ca": str(ca),
    }  # fmt: skip
    return {
        "server": {"listen": "127.0.0.1:0"},
        "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1])},
        "listeners": [listener],
    }


def gateway_trusting_two_cas(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path,
    audit: Path | None = None,
) -> tuple[RunningGateway, Callable[[], None]]:  # fmt: skip
    """A gateway whose tls listener trusts CA-A (the test root) and CA-B (another root), and
    the reload that trusts only CA-B; with ``audit``, an audit log there."""
    both, only_b = tmp_path / "both.pem", tmp_path / "b.pem"
    both.write_bytes(pem(pki.root.certificate, pki.other_root.certificate))
    only_b.write_bytes(pem(pki.other_root.certificate))
    tables = tls_tables(make_sim, pki, both)
    if audit is not None:
        tables["audit"] = {"path": str(audit)}
    gw = make_gateway(tables)

    def withdraw_ca_a() -> None:
        tables["listeners"][0]["ca"] = str(only_b)
        reload(gw, tables)

    return gw, withdraw_ca_a


def test_a_withdrawn_ca_closes_its_clients_and_spares_the_other_cas(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path,
    access_log: LogCollector,
) -> None:  # fmt: skip
    """CA-A (the test root, through its intermediate) and CA-B (another root) trusted;
    a reload trusts only CA-B: the CA-A client is closed, the CA-B client stays."""
    gw, withdraw_ca_a = gateway_trusting_two_cas(make_sim, make_gateway, pki, tmp_path)
    address = address_of(gw, "tls")
    with (
        RawClient(address, context=client_context(pki, "operator")) as of_a,
        RawClient(address, context=client_context(pki, "otherca")) as of_b,
    ):
        assert of_a.request(1, READ) == READ_ANSWER
        assert of_b.request(1, READ) == READ_ANSWER
        withdraw_ca_a()
        assert of_a.is_closed_by_peer()
        assert of_b.request(1, READ) == READ_ANSWER
    with (
        pytest.raises((ssl.SSLError, ConnectionError, ConnectionClosedError)),
        RawClient(address, context=client_context(pki, "operator")) as again,
    ):
        again.request(1, READ)  # TLS 1.3: the refusal may come after the handshake
    assert closed_at_reload(gw) == 1
    closes = [m for m in access_log.messages if "no longer admitted" in m]
    assert len(closes) == 1 and "ca_not_trusted" in closes[0] and "127.0.0.1:" in closes[0]


def test_a_tls_master_closed_at_a_reload_is_audited_with_its_role_and_subject(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path
) -> None:
    """A reload withdraws the CA of a TLS master: its record names its role and subject."""
    path = tmp_path / "audit.jsonl"
    gw, withdraw_ca_a = gateway_trusting_two_cas(make_sim, make_gateway, pki, tmp_path, path)
    with RawClient(address_of(gw, "tls"), context=client_context(pki, "operator")) as master:
        assert master.request(1, READ) == READ_ANSWER
        withdraw_ca_a()
        assert master.is_closed_by_peer()
    [closed] = refusals(gw, path)
    assert (closed["at"], closed["reason"]) == ("reload", "ca_not_trusted")
    assert (closed["role"], closed["subject"]) == ("operator", "master-operator")
    ok, message = verify_files([str(path)])
    assert ok, message


def test_a_reload_with_the_same_cas_closes_no_tls_client(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki
) -> None:
    """The chain the handshake verified (leaf, intermediate, root) still reaches the CA file."""
    tables = tls_tables(make_sim, pki, pki.ca)
    gw = make_gateway(tables)
    with RawClient(address_of(gw, "tls"), context=client_context(pki, "viewer")) as master:
        reload(gw, tables)
        reload(gw, tables)
        assert master.request(1, READ) == READ_ANSWER
    assert closed_at_reload(gw) == 0


# -- the chain's facts on real certificates --------------------------------------------


def chain_of(pki: Pki, name: str) -> tuple[bytes, ...]:
    """The chain as a handshake verifies it: leaf, its issuers from the file, the root."""
    path, _key = pki.client(name)
    certificates = x509.load_pem_x509_certificates(Path(path).read_bytes())
    anchor = pki.other_root if name == "otherca" else pki.root
    return tuple(
        c.public_bytes(serialization.Encoding.DER) for c in (*certificates, anchor.certificate)
    )


def renewed(pki: Pki) -> x509.Certificate:
    """The test root issued again: same name and key, a new validity and serial number."""
    old = pki.root.certificate
    now = dt.datetime.now(dt.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(old.subject)
        .issuer_name(old.subject)
        .public_key(pki.root.key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(days=1))
        .not_valid_after(now + dt.timedelta(days=7))
    )
    for extension in old.extensions:
        builder = builder.add_extension(extension.value, extension.critical)
    return builder.sign(pki.root.key, hashes.SHA256())


def trusted(chain: tuple[bytes, ...], authorities: list[x509.Certificate] | None) -> bool:
    facts = certificate_facts(chain, authorities)
    assert facts is not None
    return facts.trusted


def test_certificate_facts_of_real_chains(pki: Pki) -> None:
    root, other, middle = pki.root.certificate, pki.other_root.certificate, pki.intermediate
    operator = chain_of(pki, "operator")
    assert trusted(operator, [root])
    assert trusted(operator, [other, middle.certificate])  # an intermediate in the CA file
    assert not trusted(operator, [other])
    assert trusted(operator, [renewed(pki)])  # the root issued again with the same key
    assert trusted(operator, None)  # CAs not known yet: the handshake's verdict stands
    assert trusted(chain_of(pki, "otherca"), [other])
    facts = certificate_facts(operator, [renewed(pki)])
    assert facts is not None  # the renewed root's 7 days bound the window
    soon = dt.datetime.now(dt.UTC) + dt.timedelta(days=8)
    assert facts.not_after < soon.timestamp()
    expired = certificate_facts(chain_of(pki, "expired"), [root])
    assert expired is not None and expired.not_after < dt.datetime.now(dt.UTC).timestamp()
    assert certificate_facts((), [root]) is None
    assert certificate_facts((b"not a certificate",), [root]) is None


def test_a_handshake_under_way_at_the_reload_is_judged_when_it_ends(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path
) -> None:
    """Accepted before the reload, its handshake runs with the old CAs: it is closed as soon
    as it is done, since the new CAs no longer admit it."""
    gw, withdraw_ca_a = gateway_trusting_two_cas(make_sim, make_gateway, pki, tmp_path)
    server = next(s for s in gw.gateway.servers if s.name == "tls")
    with socket.create_connection(address_of(gw, "tls"), DEADLINE_S) as raw:
        wait_until(lambda: gw.call(lambda: server.connections) == 1, "accepted, no hello yet")
        withdraw_ca_a()
        assert gw.call(lambda: server.connections) == 1  # its certificate is not known yet
        with client_context(pki, "operator").wrap_socket(raw, server_hostname="localhost") as tls:
            assert closed_by_peer(tls)  # the handshake succeeded (old CAs); then the door shut
    assert closed_at_reload(gw) == 1


def closed_by_peer(sock: socket.socket) -> bool:
    """True when the gateway ends the connection within the deadline, sending nothing."""
    sock.settimeout(DEADLINE_S)
    try:
        data = sock.recv(1)
    except (ConnectionResetError, ssl.SSLEOFError, ssl.SSLZeroReturnError):
        return True
    except TimeoutError:
        return False
    assert not data, data.hex()
    return True
