"""A tls listener's suites, resumption, failure log lines and descriptors, over loopback.

Real clients: ``openssl s_client`` offering only the suite the specification
requires (TLS_RSA_WITH_AES_128_CBC_SHA256) against an RSA server certificate,
with and without ``forward_secrecy_only``; Python's ssl for session resumption
(off by default, on with ``session_resumption``); clients from distinct loopback
sources for the per-source failure lines; and raw TCP clients that never send a
ClientHello, evicted or closed while in their handshake, for the descriptors.
"""

from __future__ import annotations

import os
import shutil
import socket
import ssl
import subprocess
from pathlib import Path
from typing import Any

import pytest

from gateway.config import build_config
from gateway.io.listeners.tls import ListenerContext
from gateway.sim import plc
from gateway.sim.pki import KeyAlgorithm, Pki, make_pki
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
OPENSSL = shutil.which("openssl")
NEEDS_OPENSSL = pytest.mark.skipif(OPENSSL is None, reason="needs the openssl command")


def tls_of(client: RawClient) -> ssl.SSLSocket:
    """The TLS socket of a master."""
    assert isinstance(client.sock, ssl.SSLSocket)
    return client.sock


@pytest.fixture(scope="module")
def rsa_pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("rsa-pki"), KeyAlgorithm.RSA)


@pytest.fixture(scope="module")
def ec_pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("ec-pki"))


def tls_tables(make_sim: SimFactory, pki: Pki, **options: Any) -> dict[str, Any]:
    """The tables of a gateway with one tls listener (``options``: its keys, and ``server``)."""
    sim = make_sim({1: plc(1)})
    server = options.pop("server", {})
    listener: dict[str, Any] = {
        "name": "tls", "protocol": "tls", "listen": "127.0.0.1:0", "cert": str(pki.server_chain),
        "key": str(pki.server_key), "ca": str(pki.ca), **options,
    }  # fmt: skip
    return {
        "server": {"listen": "127.0.0.1:0", **server}, "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1])}, "listeners": [listener],
    }  # fmt: skip


def tls_gateway(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, **options: Any
) -> RunningGateway:
    return make_gateway(tls_tables(make_sim, pki, **options))


def tls_address(gw: RunningGateway) -> tuple[str, int]:
    host, port = gw.call(lambda: gw.gateway.listener_address("tls"))
    return str(host), int(port)


def s_client(address: tuple[str, int], pki: Pki, *options: str) -> str:
    """Run ``openssl s_client`` with the operator's certificate; its whole output."""
    assert OPENSSL is not None
    chain, key = pki.client("operator")
    command = [
        OPENSSL, "s_client", "-connect", f"{address[0]}:{address[1]}", "-cert", chain,
        "-cert_chain", chain, "-key", key, "-CAfile", str(pki.ca), *options,
    ]  # fmt: skip
    done = subprocess.run(command, input=b"", capture_output=True, timeout=DEADLINE_S, check=False)
    return done.stdout.decode(errors="replace") + done.stderr.decode(errors="replace")


def over_tls12(gw: RunningGateway, pki: Pki, *options: str) -> str:
    """``openssl s_client -tls1_2 options`` against the gateway's tls listener; its output."""
    return s_client(tls_address(gw), pki, "-tls1_2", *options)


# -- suites ---------------------------------------------------------------------------------


@NEEDS_OPENSSL
def test_a_client_offering_only_the_required_suite_connects(
    make_sim: SimFactory, make_gateway: GatewayFactory, rsa_pki: Pki
) -> None:
    gw = tls_gateway(make_sim, make_gateway, rsa_pki)
    out = over_tls12(gw, rsa_pki, "-cipher", "AES128-SHA256")
    assert "Cipher is AES128-SHA256" in out, out
    default = over_tls12(gw, rsa_pki)  # the ECDHE suites come first
    assert "Cipher is ECDHE-RSA-AES256-GCM-SHA384" in default, default
    context = client_context(rsa_pki)  # and such a master is served
    context.maximum_version = ssl.TLSVersion.TLSv1_2
    context.set_ciphers("AES128-SHA256")
    with RawClient(tls_address(gw), context=context) as master:
        assert master.request(1, READ) == READ_ANSWER
        cipher = tls_of(master).cipher()
        assert cipher is not None and cipher[0] == "AES128-SHA256"


@NEEDS_OPENSSL
def test_forward_secrecy_only_refuses_the_required_suite(
    make_sim: SimFactory, make_gateway: GatewayFactory, rsa_pki: Pki
) -> None:
    gw = tls_gateway(make_sim, make_gateway, rsa_pki, forward_secrecy_only=True)
    out = over_tls12(gw, rsa_pki, "-cipher", "AES128-SHA256")
    assert "Cipher is (NONE)" in out and "Cipher is AES128" not in out, out
    default = over_tls12(gw, rsa_pki)
    assert "Cipher is ECDHE-RSA-AES256-GCM-SHA384" in default, default


@NEEDS_OPENSSL
def test_null_suites_are_refused(
    make_sim: SimFactory, make_gateway: GatewayFactory, rsa_pki: Pki
) -> None:
    gw = tls_gateway(make_sim, make_gateway, rsa_pki)
    out = over_tls12(gw, rsa_pki, "-cipher", "NULL-SHA256:@SECLEVEL=0")
    assert "Cipher is NULL" not in out and "Cipher is (NONE)" in out, out


def test_the_ec_pki_is_served_with_forward_secrecy(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki
) -> None:
    gw = tls_gateway(make_sim, make_gateway, ec_pki)
    with RawClient(tls_address(gw), context=client_context(ec_pki)) as master:
        assert master.request(1, READ) == READ_ANSWER
        cipher = tls_of(master).cipher()
        assert cipher is not None and (cipher[1] == "TLSv1.3" or "ECDHE" in cipher[0])


# -- session resumption ---------------------------------------------------------------------


def resumed(gw: RunningGateway, pki: Pki, version: ssl.TLSVersion) -> bool:
    """Connect, take the session (after a request: TLS 1.3 tickets come after the
    handshake), connect again offering it; whether the second one was resumed."""
    context = client_context(pki)
    context.minimum_version = context.maximum_version = version
    with RawClient(tls_address(gw), context=context) as first:
        assert first.request(1, READ) == READ_ANSWER
        session = tls_of(first).session
    with RawClient(tls_address(gw), context=context, session=session) as second:
        assert second.request(1, READ) == READ_ANSWER
        return bool(tls_of(second).session_reused)


@pytest.mark.parametrize("version", [ssl.TLSVersion.TLSv1_2, ssl.TLSVersion.TLSv1_3])
def test_sessions_are_not_resumed_by_default(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki, version: ssl.TLSVersion
) -> None:
    gw = tls_gateway(make_sim, make_gateway, ec_pki)
    assert not resumed(gw, ec_pki, version)


@pytest.mark.parametrize("version", [ssl.TLSVersion.TLSv1_2, ssl.TLSVersion.TLSv1_3])
def test_session_resumption_turns_tickets_on(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki, version: ssl.TLSVersion
) -> None:
    gw = tls_gateway(make_sim, make_gateway, ec_pki, session_resumption=True)
    assert resumed(gw, ec_pki, version)


# -- failure log lines ----------------------------------------------------------------------


def failing_handshake(
    gw: RunningGateway, pki: Pki, source: str, version: ssl.TLSVersion = ssl.TLSVersion.TLSv1_3
) -> None:
    """A client whose certificate chains to a CA the listener does not trust."""
    context = client_context(pki, "otherca")
    context.maximum_version = version
    with (
        pytest.raises((ssl.SSLError, ConnectionError, ConnectionClosedError, OSError)),
        RawClient(tls_address(gw), context=context, source=source) as master,
    ):
        master.request(1, READ)  # TLS 1.3: the refusal may come after the handshake


def test_a_failed_handshake_is_logged_with_peer_and_subject_once_per_source(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki, access_log: LogCollector
) -> None:
    """The subject comes from the Certificate message the handshake saw (TLS 1.3 and 1.2);
    three failures from 127.0.0.2 give one line (the rest wait for the minute's summary)."""
    gw = tls_gateway(make_sim, make_gateway, ec_pki)
    server = next(s for s in gw.gateway.servers if s.name == "tls")
    for source in ("127.0.0.2", "127.0.0.2", "127.0.0.2"):
        failing_handshake(gw, ec_pki, source)
    failing_handshake(gw, ec_pki, "127.0.0.3", ssl.TLSVersion.TLSv1_2)
    labels = {"listener": "tls", "reason": "untrusted_certificate"}
    name = "modbus_gateway_tls_handshake_failures_total"
    wait_until(
        lambda: gw.call(lambda: server.metrics.registry.get_sample_value(name, labels)) == 4,
        "four failures counted",
    )
    lines = [m for m in access_log.messages if "TLS handshake failed" in m]
    assert len(lines) == 2, lines
    first, other = sorted(lines)
    assert "master 127.0.0.2" in first and "peer 127.0.0.2:" in first, first
    assert "untrusted_certificate" in first and "certificate verify failed" in first, first
    assert "certificate 'master-otherca'" in first, first
    assert "master 127.0.0.3" in other and "peer 127.0.0.3:" in other, other
    assert "certificate 'master-otherca'" in other, other


def test_a_handshake_without_a_certificate_names_no_subject(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki, access_log: LogCollector
) -> None:
    gw = tls_gateway(make_sim, make_gateway, ec_pki)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(cafile=str(ec_pki.ca))
    with (
        pytest.raises((ssl.SSLError, ConnectionError, ConnectionClosedError, OSError)),
        RawClient(tls_address(gw), context=context) as master,
    ):
        master.request(1, READ)
    wait_until(lambda: any("TLS handshake failed" in m for m in access_log.messages), "logged")
    line = next(m for m in access_log.messages if "TLS handshake failed" in m)
    assert "no_certificate" in line and "certificate '" not in line, line


def test_a_settled_session_is_no_longer_observed(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki
) -> None:
    """Once set up, a session moves to the listener's unobserved twin context: OpenSSL's
    message callback then costs nothing per record."""
    gw = tls_gateway(make_sim, make_gateway, ec_pki)
    server = next(s for s in gw.gateway.servers if s.name == "tls")
    with RawClient(tls_address(gw), context=client_context(ec_pki)) as master:
        assert master.request(1, READ) == READ_ANSWER
        transports = gw.call(lambda: [c._transport for c in server._connections])
        contexts = [t.get_extra_info("ssl_object").context for t in transports if t is not None]
    listener_context = gw.call(lambda: server.ssl_context)
    assert isinstance(listener_context, ListenerContext)
    assert contexts == [listener_context.settled]
    assert getattr(listener_context.settled, "_msg_callback", None) is None


# -- descriptors ----------------------------------------------------------------------------


#: Descriptors the loop may open on its own meanwhile (none is a connection's).
SLACK = 2


def open_descriptors() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc")
def test_connections_evicted_or_closed_in_their_handshake_free_their_descriptors(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki
) -> None:
    """Stalled clients that never send a ClientHello, far more than ``max_connections``:
    each newcomer evicts the longest idle (``evict_min_idle = 0``); the gateway (in this
    process) holds no more descriptors than connections it keeps, long before the
    handshake timeout. A reload whose allow list shuts the door on their source frees
    the rest the same way."""
    limit, stalled = 4, 40
    tables = tls_tables(make_sim, ec_pki, server={
        "max_connections": limit, "evict_min_idle": 0.0, "tls_handshake_timeout": 120.0,
    })  # fmt: skip
    gw = make_gateway(tables)
    server = next(s for s in gw.gateway.servers if s.name == "tls")
    baseline = open_descriptors()
    clients: list[socket.socket] = []
    try:
        for _ in range(stalled):
            clients.append(socket.create_connection(tls_address(gw), DEADLINE_S, ("127.0.0.2", 0)))
            wait_until(lambda: gw.call(lambda: server.connections) >= 1, "accepted")
        wait_until(
            lambda: open_descriptors() - baseline - len(clients) <= limit + SLACK,
            f"at most {limit} descriptors held for {stalled} stalled handshakes",
            timeout=5.0,
        )
        assert gw.call(lambda: server.connections) <= limit
        tables["listeners"][0]["allow"] = ["127.0.0.1/32"]
        gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))
        wait_until(
            lambda: open_descriptors() - baseline - len(clients) <= SLACK,
            "every descriptor of a closed handshake freed",
            timeout=5.0,
        )
        assert gw.call(lambda: server.connections) == 0
    finally:
        for client in clients:
            client.close()


def test_a_resumed_session_is_judged_on_its_full_chain_at_a_reload(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki
) -> None:
    """A resumed session shows only its leaf (issued by an intermediate the ``ca`` file
    does not hold): the chain its first handshake verified keeps it trusted at a reload."""
    tables = tls_tables(make_sim, ec_pki, session_resumption=True)
    gw = make_gateway(tables)
    context = client_context(ec_pki)
    with RawClient(tls_address(gw), context=context) as first:
        assert first.request(1, READ) == READ_ANSWER
        session = tls_of(first).session
    with RawClient(tls_address(gw), context=context, session=session) as second:
        assert second.request(1, READ) == READ_ANSWER
        assert tls_of(second).session_reused
        gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))
        assert second.request(1, READ) == READ_ANSWER


def test_a_reload_ends_resumption_of_earlier_sessions(
    make_sim: SimFactory, make_gateway: GatewayFactory, ec_pki: Pki
) -> None:
    tables = tls_tables(make_sim, ec_pki, session_resumption=True)
    gw = make_gateway(tables)
    context = client_context(ec_pki)
    with RawClient(tls_address(gw), context=context) as first:
        assert first.request(1, READ) == READ_ANSWER
        session = tls_of(first).session
    gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))
    with RawClient(tls_address(gw), context=context, session=session) as second:
        assert second.request(1, READ) == READ_ANSWER
        assert not tls_of(second).session_reused
