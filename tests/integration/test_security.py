"""Modbus/TCP Security and access control, over real TLS and real TCP on loopback.

A throwaway PKI (``tests/pki.py``) gives the server its chain and the masters
their certificates. What is checked: the handshake rules (TLS 1.2 or newer,
mutual authentication against the configured CA), the role taken from the
client certificate (NULL for no, two or a wrongly encoded role extension),
each role's rights request by request (served, or 0x01 with nothing on the
line: the simulator's frame count does not move), source address rules, the
allow list and read-only from 127.0.0.2 / 127.0.0.3, and the metrics.
"""

from __future__ import annotations

import asyncio
import functools
import socket
import ssl
import subprocess
import time
from typing import Any

import pytest

from gateway.config import build_config
from gateway.sim import plc
from gateway.sim.pki import Pki
from tests.helpers import (
    DEADLINE_S,
    ConnectionClosedError,
    GatewayFactory,
    GatewayOnSim,
    LogCollector,
    RawClient,
    RunningGateway,
    SimBus,
    SimFactory,
    client_context,
    require_tool,
    wait_until,
)

PLANT_RULES: list[dict[str, Any]] = [
    {"role": "operator", "units": [1], "functions": [3, "write_single_register", 16],
     "addresses": ["0-99"]},
    {"role": "viewer", "units": [1, 2], "access": "read"},
    {"role": "operator", "units": [0], "functions": [6]},
]  # fmt: skip


def tls_listener(pki: Pki, **options: Any) -> dict[str, Any]:
    table = {
        "name": "tls", "protocol": "tls", "listen": "127.0.0.1:0", "cert": str(pki.server_chain),
        "key": str(pki.server_key), "ca": str(pki.ca),
    }  # fmt: skip
    table.update(options)
    return table


def sample(gw: RunningGateway, name: str, labels: dict[str, str] | None = None) -> float:
    value = gw.call(lambda: gw.gateway.metrics.registry.get_sample_value(name, labels or {}))
    return 0.0 if value is None else value


def denials(gw: RunningGateway, listener: str, role: str, function: str) -> float:
    labels = {"listener": listener, "role": role, "function": function}
    return sample(gw, "modbus_gateway_denied_requests_total", labels)


def listener_address(gw: RunningGateway, name: str) -> tuple[str, int]:
    return gw.call(lambda: gw.gateway.listener_address(name))


@pytest.fixture
def plant(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki
) -> tuple[SimBus, RunningGateway]:
    """Units 1 and 2 behind a plain listener (no rules) and a tls listener with PLANT_RULES."""
    sim = make_sim({1: plc(1), 2: plc(2)})
    gw = make_gateway({
        "server": {"broadcast_reply": True},
        "lines": {"a": sim.line_table([1, 2], broadcast_turnaround=0.0)},
        "listeners": [tls_listener(pki, policy="plant")],
        "policies": {"plant": {"rules": PLANT_RULES}},
    })  # fmt: skip
    return sim, gw


def exception(function: int, code: int = 1) -> bytes:
    return bytes([function | 0x80, code])


# Role x function x unit x range: True = served by the slave, False = 0x01 and nothing on the line.
MATRIX: list[tuple[str, int, str, bool]] = [
    ("operator", 1, "03 0000 000A", True),
    ("operator", 1, "03 005A 000A", True),  # 90..99: the end of the granted range
    ("operator", 1, "03 005B 000A", False),  # 91..100: one register outside
    ("operator", 1, "06 0063 0007", True),
    ("operator", 1, "06 0064 0007", False),
    ("operator", 1, "10 0000 0002 04 00010002", True),
    ("operator", 1, "05 0000 FF00", False),  # a function no rule names
    ("operator", 2, "03 0000 0001", False),  # a unit no rule names
    ("operator", 0, "06 0001 0009", True),  # broadcast, named explicitly
    ("operator", 1, "08 0004 0000", False),  # Force Listen Only Mode
    ("viewer", 1, "03 005B 000A", True),
    ("viewer", 2, "04 0000 0005", True),
    ("viewer", 1, "01 0000 0010", True),
    ("viewer", 1, "08 0000 1234", True),  # Return Query Data: a read
    ("viewer", 1, "06 0000 0001", False),
    ("viewer", 1, "10 0000 0001 02 0001", False),
    ("viewer", 1, "17 0000 0001 0000 0001 02 0000", False),
    ("viewer", 0, "06 0000 0001", False),
    ("viewer", 1, "08 0004 0000", False),
    ("norole", 1, "03 0000 0001", False),
    ("tworoles", 1, "03 0000 0001", False),
    ("integer", 1, "03 0000 0001", False),
    ("admin", 1, "03 0000 0001", False),  # a role no rule names
]


def test_each_roles_rights_request_by_request(
    plant: tuple[SimBus, RunningGateway], pki: Pki
) -> None:
    sim, gw = plant
    address = listener_address(gw, "tls")
    masters = {
        name: RawClient(address, context=client_context(pki, name))
        for name in ("operator", "viewer", "norole", "tworoles", "integer", "admin")
    }
    expected = sim.stats().requests
    try:
        for role, unit, text, served in MATRIX:
            pdu = bytes.fromhex(text)
            answer = masters[role].request(unit, pdu)
            case = f"{role} unit {unit} {text}"
            if served:
                assert not answer[0] & 0x80, f"{case}: {answer.hex()}"
                expected += 1
            else:
                assert answer == exception(pdu[0]), f"{case}: {answer.hex()}"
            # A broadcast is answered once it is on the wire, maybe before the slave counted it.
            wait_until(functools.partial(line_has_seen, sim, expected), case)
            assert sim.stats().requests == expected, f"{case}: a denied request reached the line"
    finally:
        for master in masters.values():
            master.close()
    denied = {
        (role, unit, text) for role, unit, text, served in MATRIX if not served
    }  # counted by listener, role (bounded) and function
    assert denials(gw, "tls", "viewer", "write_single_register") == 2
    assert denials(gw, "tls", "none", "read_holding_registers") == 3
    assert denials(gw, "tls", "other", "read_holding_registers") == 1
    assert sum(
        sample(gw, "modbus_gateway_requests_total",
               {"line": "none", "unit": "other", "function": function, "outcome": "denied"})
        for function in ("read_holding_registers", "write_single_register", "write_single_coil",
                         "write_multiple_registers", "read_write_multiple_registers",
                         "diagnostics")
    ) == len(denied)  # fmt: skip


def test_the_plain_listener_beside_it_serves_as_before(
    plant: tuple[SimBus, RunningGateway],
) -> None:
    _, gw = plant
    with gw.connect() as master:
        assert master.request(1, bytes.fromhex("06 0500 0001")) == bytes.fromhex("06 0500 0001")
        assert master.request(2, bytes.fromhex("03 0000 0001"))[0] == 3


@pytest.mark.parametrize(
    ("client", "maximum", "reason"),
    [
        (None, None, "no_certificate"),
        ("otherca", None, "untrusted_certificate"),
        ("expired", None, "expired_certificate"),
        ("operator", ssl.TLSVersion.TLSv1_1, "protocol_version"),
    ],
)
@pytest.mark.filterwarnings("ignore:ssl.TLSVersion:DeprecationWarning")
def test_handshakes_that_fail(
    plant: tuple[SimBus, RunningGateway],
    pki: Pki,
    client: str | None,
    maximum: ssl.TLSVersion | None,
    reason: str,
) -> None:
    sim, gw = plant
    address = listener_address(gw, "tls")
    before = sim.stats().requests
    # TLS 1.3 completes the client's side before the server checks its certificate: the
    # refusal then arrives as an alert on the first read.
    with (
        pytest.raises((ssl.SSLError, ConnectionClosedError, ConnectionResetError, OSError)),
        RawClient(address, context=client_context(pki, client, maximum=maximum)) as master,
    ):
        master.request(1, bytes.fromhex("03 0000 0001"))
    assert sim.stats().requests == before
    labels = {"listener": "tls", "reason": reason}
    wait_for_sample(gw, "modbus_gateway_tls_handshake_failures_total", labels, 1.0)


def line_has_seen(sim: SimBus, requests: int) -> bool:
    """True once the simulated line has counted at least ``requests`` frames."""
    return sim.stats().requests >= requests


def wait_for_sample(gw: RunningGateway, name: str, labels: dict[str, str], value: float) -> None:
    """Wait until the metric reaches ``value`` (the server may count after the client's error)."""
    wait_until(lambda: sample(gw, name, labels) >= value, f"{name}{labels} >= {value}")


# --------------------------------------------------------------------------- independent peers


def test_pymodbus_tls_client_with_a_client_certificate(
    plant: tuple[SimBus, RunningGateway], pki: Pki
) -> None:
    """pymodbus's own Modbus/TCP Security client as master: operator writes, viewer may not."""
    from pymodbus.client import AsyncModbusTlsClient

    sim, gw = plant
    host, port = listener_address(gw, "tls")

    async def session(name: str) -> tuple[Any, Any, Any]:
        context = client_context(pki, name)
        client: Any = AsyncModbusTlsClient(host, port=port, sslctx=context, timeout=5, retries=0)
        assert await client.connect()
        sock = client.ctx.transport.get_extra_info("socket")
        try:
            read = await client.read_holding_registers(10, count=3, device_id=1)
            write = await client.write_register(20, 0x1234, device_id=1)
            far = await client.read_holding_registers(200, count=1, device_id=2)
        finally:
            client.close()
            # close() only starts the TLS shutdown: let it close the socket before the loop ends.
            deadline = time.monotonic() + DEADLINE_S
            while sock.fileno() != -1 and time.monotonic() < deadline:
                await asyncio.sleep(0.005)
        return read, write, far

    expected = sim.device(1).holding.read(10, 3)
    read, write, far = asyncio.run(session("operator"))
    assert read.registers == expected
    assert not write.isError() and sim.device(1).holding[20] == 0x1234
    assert far.isError() and far.exception_code == 1  # unit 2 is not the operator's
    before = sim.stats().requests
    read, write, far = asyncio.run(session("viewer"))
    assert read.registers == expected
    assert write.isError() and write.exception_code == 1
    assert not far.isError()
    assert sim.device(1).holding[20] == 0x1234
    assert sim.stats().requests == before + 2  # the refused write never reached the line


def s_client(pki: Pki, port: int, *options: str) -> subprocess.CompletedProcess[str]:
    """``openssl s_client`` against the tls listener; stdin is empty, so it ends at once."""
    openssl = require_tool("openssl")
    command = [openssl, "s_client", "-connect", f"127.0.0.1:{port}", "-CAfile", str(pki.ca),
               "-verify_return_error", "-brief", *options]  # fmt: skip
    return subprocess.run(
        command, input="", capture_output=True, text=True, timeout=DEADLINE_S, check=False
    )


def test_openssl_s_client_sees_the_handshake_rules(
    plant: tuple[SimBus, RunningGateway], pki: Pki
) -> None:
    _, gw = plant
    port = listener_address(gw, "tls")[1]
    cert, key = pki.client("operator")
    identity = ("-cert", cert, "-cert_chain", cert, "-key", key)  # the chain: the intermediate
    ok = s_client(pki, port, *identity)
    assert ok.returncode == 0, ok.stderr
    assert "Verification: OK" in ok.stderr and "Protocol version: TLSv1.3" in ok.stderr
    # The cipher suite the specification requires for ECDSA certificates, on TLS 1.2.
    ok12 = s_client(pki, port, *identity, "-tls1_2", "-cipher", "ECDHE-ECDSA-AES128-GCM-SHA256")
    assert ok12.returncode == 0 and "Protocol version: TLSv1.2" in ok12.stderr, ok12.stderr
    assert "Ciphersuite: ECDHE-ECDSA-AES128-GCM-SHA256" in ok12.stderr
    no_cert = s_client(pki, port, "-tls1_2")  # TLS 1.2: the refusal comes in the handshake
    assert no_cert.returncode != 0
    assert "alert" in no_cert.stderr.lower() or "error" in no_cert.stderr.lower()
    old = s_client(pki, port, *identity, "-tls1_1", "-cipher", "DEFAULT@SECLEVEL=0")
    assert old.returncode != 0
    assert sample(gw, "modbus_gateway_tls_handshake_failures_total",
                  {"listener": "tls", "reason": "no_certificate"}) >= 1  # fmt: skip
    wait_for_sample(gw, "modbus_gateway_tls_handshake_failures_total",
                           {"listener": "tls", "reason": "protocol_version"}, 1)  # fmt: skip


# --------------------------------------------------------------------------- plain TCP: addresses


def test_source_rules_and_read_only_from_other_loopback_addresses(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    """127.0.0.2 may write unit 1; 127.0.0.3 may only read; a read-only listener refuses both."""
    sim = make_sim({1: plc(1)})
    gw = make_gateway({
        "server": {"policy": "by_source"},
        "lines": {"a": sim.line_table([1])},
        "listeners": [{"name": "ro", "listen": "127.0.0.1:0", "read_only": True}],
        "policies": {"by_source": {"rules": [
            {"source": "127.0.0.2", "units": [1]},
            {"source": ["127.0.0.3/32"], "units": [1], "access": "read"},
        ]}},
    })  # fmt: skip
    write, read = bytes.fromhex("06 0007 0042"), bytes.fromhex("03 0007 0001")
    with (
        RawClient(gw.address, source="127.0.0.2") as writer,
        RawClient(gw.address, source="127.0.0.3") as reader,
        RawClient(gw.address) as stranger,
    ):
        assert writer.request(1, write) == write
        assert reader.request(1, read) == bytes.fromhex("03 02 0042")
        before = sim.stats().requests
        assert reader.request(1, write) == exception(6)
        assert stranger.request(1, read) == exception(3)  # 127.0.0.1: no rule names it
        assert sim.stats().requests == before
    read_only = listener_address(gw, "ro")
    with RawClient(read_only, source="127.0.0.2") as writer:
        before = sim.stats().requests
        assert writer.request(1, write) == exception(6)
        assert sim.stats().requests == before
        assert writer.request(1, read) == bytes.fromhex("03 02 0042")
    assert denials(gw, "ro", "none", "write_single_register") == 1
    assert denials(gw, "tcp", "none", "write_single_register") == 1


def test_allow_list_closes_other_sources_at_accept(
    make_sim: SimFactory, make_gateway: GatewayFactory, access_log: LogCollector
) -> None:
    sim = make_sim({1: plc(1)})
    gw = make_gateway({
        "server": {"allow": ["127.0.0.2/32", "10.0.0.0/8"]},
        "lines": {"a": sim.line_table([1])},
    })  # fmt: skip
    read = bytes.fromhex("03 0000 0001")
    with RawClient(gw.address, source="127.0.0.2") as inside:
        assert inside.request(1, read) == bytes.fromhex("03 02 0000")
    for _ in range(5):
        with RawClient(gw.address, source="127.0.0.3") as outside:
            outside.send(1, read)  # the bytes are never read: the connection is already closed
            assert outside.is_closed_by_peer()
    assert sample(gw, "modbus_gateway_connections_denied_total", {"listener": "tcp"}) == 5
    assert sample(gw, "modbus_gateway_connections_accepted_total") == 1
    refusals = [m for m in access_log.messages if "outside the allow list" in m]
    assert len(refusals) == 1 and "127.0.0.3" in refusals[0]  # then counted, not logged


def test_a_reload_changes_rights_and_allow_lists_of_open_listeners(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    tables: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0", "policy": "p"},
        "metrics": {"listen": "off"},
        "lines": {"a": sim.line_table([1])},
        "policies": {"p": {"rules": [{"units": [1], "access": "read"}]}},
    }
    gw = make_gateway(tables)
    write = bytes.fromhex("06 0009 0001")
    with RawClient(gw.address, source="127.0.0.2") as master:
        assert master.request(1, write) == exception(6)
        tables["policies"] = {"p": {"rules": [{"units": [1]}]}}
        tables["server"]["allow"] = ["127.0.0.2"]
        gw.run(gw.gateway.reload(build_config(tables, "<reloaded>")))
        assert master.request(1, write) == write  # the open connection has the new rights
    with RawClient(gw.address, source="127.0.0.3") as outsider:
        assert outsider.is_closed_by_peer()
    assert sample(gw, "modbus_gateway_connections_denied_total", {"listener": "tcp"}) == 1


def test_garbage_instead_of_a_client_hello_is_counted_and_closed(
    plant: tuple[SimBus, RunningGateway], pki: Pki
) -> None:
    """Plain Modbus (and noise) sent to the tls port: closed, counted, honest masters served."""
    _, gw = plant
    address = listener_address(gw, "tls")
    with RawClient(address, context=client_context(pki, "viewer")) as honest:
        for noise in (bytes.fromhex("0001 0000 0006 01 03 0000 0001"), b"GET / HTTP/1.0\r\n\r\n"):
            for _ in range(10):
                with RawClient(address) as confused:  # a plain Modbus TCP master on port 802
                    confused.send_raw(noise)
                    assert closed_soon(confused.sock)
                assert honest.request(1, bytes.fromhex("03 0000 0001"))[0] == 3
    labels = {"listener": "tls", "reason": "not_tls"}
    wait_for_sample(gw, "modbus_gateway_tls_handshake_failures_total", labels, 20)


def closed_soon(sock: socket.socket) -> bool:
    """True when the peer closes within the deadline (whatever it sent first: an alert)."""
    sock.settimeout(DEADLINE_S)
    try:
        while sock.recv(4096):
            pass
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False
    return True


def test_silent_tls_clients_are_cut_off_at_the_handshake_timeout(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki
) -> None:
    """Connections that never send a ClientHello hold nothing past tls_handshake_timeout."""
    sim = make_sim({1: plc(1)})
    gw = make_gateway({
        "server": {"tls_handshake_timeout": 0.5},
        "lines": {"a": sim.line_table([1])},
        "listeners": [tls_listener(pki)],
    })  # fmt: skip
    address = listener_address(gw, "tls")
    silent = [socket.create_connection(address, timeout=DEADLINE_S) for _ in range(8)]
    try:
        started = time.monotonic()
        with RawClient(address, context=client_context(pki, "operator")) as honest:
            assert honest.request(1, bytes.fromhex("03 0000 0001"))[0] == 3
        assert all(closed_soon(sock) for sock in silent)
        waited = time.monotonic() - started
        assert 0.4 < waited < 5.0, waited  # the timeout, not the default 10 s
    finally:
        for sock in silent:
            sock.close()
    labels = {"listener": "tls", "reason": "timeout"}
    wait_for_sample(gw, "modbus_gateway_tls_handshake_failures_total", labels, 8)
    assert sample(gw, "modbus_gateway_connections_open", {"listener": "tls"}) == 0


def test_force_listen_only_mode_is_refused_on_a_listener_without_rules(
    gateway_with: GatewayOnSim,
) -> None:
    sim, gw = gateway_with({1: plc(1)})
    with gw.connect() as master:
        before = sim.stats().requests
        assert master.request(1, bytes.fromhex("08 0004 0000")) == exception(8)
        assert sim.stats().requests == before  # the slave was never told to fall silent
        assert master.request(1, bytes.fromhex("08 0000 A537")) == bytes.fromhex("08 0000 A537")
        assert master.request(1, bytes.fromhex("06 0000 0001")) == bytes.fromhex("06 0000 0001")
    assert denials(gw, "tcp", "none", "diagnostics") == 1


def test_a_denied_request_gets_0x01_even_when_it_is_malformed(
    plant: tuple[SimBus, RunningGateway], pki: Pki
) -> None:
    """A master without the right learns nothing: not even that its request was invalid."""
    _, gw = plant
    with RawClient(listener_address(gw, "tls"), context=client_context(pki, "viewer")) as viewer:
        assert viewer.request(1, bytes.fromhex("06 0000")) == exception(6)  # short: 0x01
        assert viewer.request(1, bytes.fromhex("03 0000 0000")) == exception(3, 3)  # granted
