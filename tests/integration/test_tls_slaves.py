"""``kind = "tls"``: Modbus/TCP Security slaves behind the gateway (the plain-to-802 bridge).

Real TLS on loopback with a PKI the test makes (``gateway.sim.pki``). The slave is
another gateway's ``tls`` listener in front of a simulated serial line, so its access
rules see the first gateway's client certificate and role; pymodbus's TLS server is an
independent slave. A slave whose certificate is untrusted, expired or for another name,
or that refuses the gateway's certificate, leaves the line down (0x0A), counted by
reason and logged once.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import socket
import ssl
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gateway.sim import plc
from gateway.sim.device import pack_registers
from gateway.sim.pki import Pki
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    LogCollector,
    RunningGateway,
    SimFactory,
    h,
    wait_until,
)
from tests.integration.pymodbus_harness import PymodbusServerThread, sim_device
from tests.integration.test_sim import FUNCTION_VECTORS

#: The slave gateway's rules: the operator may do anything on unit 7, the viewer may read.
RULES: list[dict[str, Any]] = [
    {"role": "operator", "units": [7]},
    {"role": "viewer", "units": [7], "access": "read"},
]


def tls_listener(pki: Pki, **options: Any) -> dict[str, Any]:
    table = {
        "name": "tls", "protocol": "tls", "listen": "127.0.0.1:0", "cert": str(pki.server_chain),
        "key": str(pki.server_key), "ca": str(pki.ca), "policy": "plant",
    }  # fmt: skip
    table.update(options)
    return table


def tls_line(pki: Pki, port: int, client: str = "operator", **options: Any) -> dict[str, Any]:
    cert, key = pki.client(client)
    table: dict[str, Any] = {
        "kind": "tls", "address": f"127.0.0.1:{port}", "cert": cert, "key": key,
        "ca": str(pki.ca), "units": [7], "timeout": 1.0,
    }  # fmt: skip
    table.update(options)
    return table


def slave_gateway(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, **listener: Any
) -> RunningGateway:
    """Gateway B: a tls listener with RULES in front of a simulated PLC at unit 7."""
    sim = make_sim({7: plc(7)})
    return make_gateway({
        "lines": {"a": sim.line_table([7])},
        "listeners": [tls_listener(pki, **listener)],
        "policies": {"plant": {"rules": RULES}},
    })  # fmt: skip


def tls_port(gw: RunningGateway) -> int:
    return gw.call(lambda: gw.gateway.listener_address("tls"))[1]


def sample(gw: RunningGateway, name: str, **labels: str) -> float:
    value = gw.call(lambda: gw.gateway.metrics.registry.get_sample_value(name, labels))
    return 0.0 if value is None else value


def line_up(gw: RunningGateway, line: str = "plc") -> bool:
    return gw.call(lambda: gw.gateway.buses[line].up)


@pytest.fixture
def bus_log() -> Iterator[LogCollector]:
    collector = LogCollector()
    logger = logging.getLogger("gateway.bus")
    level = logger.level
    logger.setLevel(logging.INFO)  # "connected" and "back up" too
    logger.addHandler(collector)
    try:
        yield collector
    finally:
        logger.removeHandler(collector)
        logger.setLevel(level)


def test_a_gateway_bridges_plain_masters_to_another_gateways_tls_listener(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki
) -> None:
    slave = slave_gateway(make_sim, make_gateway, pki)
    port = tls_port(slave)
    operator = make_gateway({"lines": {"plc": tls_line(pki, port, "operator")}})
    viewer = make_gateway({"lines": {"plc": tls_line(pki, port, "viewer")}})
    wait_until(lambda: line_up(operator) and line_up(viewer), "the tls lines never came up")
    with operator.connect() as master:
        tid = master.send(7, h("06 0010 1234"), tid=0xBEEF)
        reply = master.receive()
        assert (reply.transaction_id, reply.pdu) == (tid, h("06 0010 1234"))
        assert master.request(7, h("03 0010 0001")) == h("03 02 1234")
    with viewer.connect() as master:
        assert master.request(7, h("03 0010 0001")) == h("03 02 1234")
        assert master.request(7, h("06 0010 0001")) == h("86 01")  # B's rules: a viewer reads
    with operator.connect() as master:
        assert master.request(7, h("03 0010 0001")) == h("03 02 1234")  # the write was refused
    denied, write = "modbus_gateway_denied_requests_total", "write_single_register"
    assert sample(slave, denied, listener="tls", role="viewer", function=write) == 1
    assert sample(slave, denied, listener="tls", role="operator", function=write) == 0
    info = sample(operator, "modbus_gateway_line_info", line="plc", kind="tls")
    assert info == 1
    expiry = "modbus_gateway_line_tls_certificate_expiry_seconds"
    left = sample(operator, expiry, line="plc", kind="client", subject="master-operator")
    assert 364 * 86400 < left <= 365 * 86400
    assert sample(operator, expiry, line="plc", kind="ca", subject="Test Root CA") > 0
    for reason in ("untrusted_certificate", "certificate_refused", "name_mismatch"):
        assert (
            sample(operator, "modbus_gateway_line_tls_failures_total", line="plc", reason=reason)
            == 0
        )


def test_the_tls_line_needs_tls_1_2_or_newer_and_verifies_the_name_by_default(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki
) -> None:
    slave = slave_gateway(make_sim, make_gateway, pki)
    port = tls_port(slave)
    gw = make_gateway({"lines": {"plc": tls_line(pki, port, address=f"localhost:{port}")}})
    wait_until(lambda: line_up(gw), "the tls line never came up")
    context = gw.call(lambda: gw.gateway.buses["plc"].tls_context)
    assert context is not None
    assert context.check_hostname and context.minimum_version.name == "TLSv1_2"
    with gw.connect() as master:
        assert master.request(7, h("03 0000 0002")) == h("03 04 0000 0002")


FAILURES = [
    ("untrusted_certificate", {"ca": "other-ca.pem"}, "does not chain to lines.plc.ca"),
    ("name_mismatch", {"server_name": "plc-9.plant.example"}, "set lines.plc.server_name"),
    # The gateway's tls listener (asyncio's and uvloop's TLS servers alike) closes without
    # sending its alert: under TLS 1.3 the refusal is a close before the first answer.
    ("closed", {"client": "otherca"}, "it may refuse the gateway's certificate"),
]


@pytest.mark.parametrize(("reason", "options", "message"), FAILURES, ids=[f[0] for f in FAILURES])
def test_a_tls_failure_leaves_the_line_down_counted_and_logged_once(
    make_sim: SimFactory,
    make_gateway: GatewayFactory,
    pki: Pki,
    bus_log: LogCollector,
    reason: str,
    options: dict[str, Any],
    message: str,
) -> None:
    slave = slave_gateway(make_sim, make_gateway, pki)
    options = dict(options)
    client = options.pop("client", "operator")
    if "ca" in options:
        options["ca"] = str(pki.directory / options["ca"])
    gw = make_gateway({"lines": {"plc": tls_line(pki, tls_port(slave), client, **options)}})
    failures = "modbus_gateway_line_tls_failures_total"
    wait_until(lambda: sample(gw, failures, line="plc", reason=reason) >= 3,
               f"no three {reason} failures")  # fmt: skip
    with gw.connect() as master:
        for _ in range(3):
            assert master.request(7, h("03 0000 0001")) == h("83 0A")
    logged = [text for text in bus_log.messages if message in text]
    assert len(logged) == 1, bus_log.messages
    assert "line 'plc'" in logged[0] and "retrying" in logged[0]
    # The line never worked: no "back up"; "connected" at most for the first TCP + TLS 1.3
    # handshake, before the slave's refusal (a closed connection) arrived.
    assert not any("back up" in text for text in bus_log.messages)
    connected = [text for text in bus_log.messages if "connected to" in text]
    assert len(connected) == (1 if reason == "closed" else 0), bus_log.messages
    assert sample(gw, "modbus_gateway_line_up", line="plc") == 0


def test_a_slave_with_an_expired_certificate(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path,
    bus_log: LogCollector,
) -> None:  # fmt: skip
    now = dt.datetime.now(dt.UTC)
    chain, key = pki.server_certificate("old", now - dt.timedelta(days=30), now - dt.timedelta(1))
    slave = slave_gateway(make_sim, make_gateway, pki)
    # A gateway refuses to start with an expired certificate: it is swapped in afterwards,
    # as if it had expired while running (new handshakes get it; a reload is not needed).
    listener = slave.call(lambda: slave.gateway.servers[-1])
    context = slave.call(lambda: listener.ssl_context)
    assert context is not None
    context.load_cert_chain(str(chain), str(key))
    gw = make_gateway({"lines": {"plc": tls_line(pki, tls_port(slave))}})
    failures = "modbus_gateway_line_tls_failures_total"
    wait_until(lambda: sample(gw, failures, line="plc", reason="expired_certificate") >= 2,
               "no expired_certificate failures")  # fmt: skip
    with gw.connect() as master:
        assert master.request(7, h("03 0000 0001")) == h("83 0A")
    logged = [text for text in bus_log.messages if "expired or not yet valid" in text]
    assert len(logged) == 1, bus_log.messages


class StdlibTlsSlave:
    """A bare TLS server (Python's blocking ``ssl``) that refuses or accepts handshakes.

    Unlike the event loops' TLS servers it sends its alert, so a refusal of the
    gateway's certificate reaches the gateway as ``unknown ca``.
    """

    def __init__(self, pki: Pki, version: ssl.TLSVersion | None = None) -> None:
        self.context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        self.context.load_cert_chain(str(pki.server_chain), str(pki.server_key))
        self.context.load_verify_locations(cafile=str(pki.ca))
        self.context.verify_mode = ssl.CERT_REQUIRED
        if version is not None:  # this version only (TLS 1.1: deprecated, on purpose)
            self.context.set_ciphers("DEFAULT:@SECLEVEL=0")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                self.context.minimum_version = self.context.maximum_version = version
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.2)
        self.port: int = self._listener.getsockname()[1]
        self.refused = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="tls-slave", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                connection, _ = self._listener.accept()
            except TimeoutError:
                continue
            connection.settimeout(DEADLINE_S)
            try:
                self.context.wrap_socket(connection, server_side=True).close()
            except (ssl.SSLError, OSError):
                self.refused += 1
                connection.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(DEADLINE_S)
        self._listener.close()


@pytest.mark.parametrize(
    "version", [None, ssl.TLSVersion.TLSv1_2], ids=["after the handshake", "tls 1.2"]
)
def test_a_slave_that_refuses_the_gateways_certificate_with_an_alert(
    make_gateway: GatewayFactory, pki: Pki, bus_log: LogCollector, version: ssl.TLSVersion | None
) -> None:
    """TLS 1.3: the alert is the first thing read; TLS 1.2: it ends the handshake."""
    slave = StdlibTlsSlave(pki, version)
    try:
        gw = make_gateway({"lines": {"plc": tls_line(pki, slave.port, "otherca")}})
        failures = "modbus_gateway_line_tls_failures_total"
        wait_until(lambda: sample(gw, failures, line="plc", reason="certificate_refused") >= 2,
                   "no certificate_refused failures")  # fmt: skip
        with gw.connect() as master:
            assert master.request(7, h("03 0000 0001")) == h("83 0A")
    finally:
        slave.close()
    logged = [text for text in bus_log.messages if "refused the gateway's certificate" in text]
    assert len(logged) == 1, bus_log.messages
    assert "UNKNOWN_CA" in logged[0] and "otherca.chain.pem" in logged[0]


# --------------------------------------------------------------------------- independent slave


class PymodbusTlsSlave(PymodbusServerThread):
    """pymodbus's Modbus/TCP Security server (unit 7), client certificates required."""

    def __init__(self, pki: Pki) -> None:
        from pymodbus.server import ModbusTlsServer

        device = sim_device(7, [i % 3 == 0 for i in range(32)], [10 * i for i in range(32)])
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.load_cert_chain(str(pki.server_chain), str(pki.server_key))
        context.load_verify_locations(cafile=str(pki.ca))
        context.verify_mode = ssl.CERT_REQUIRED
        super().__init__(
            lambda: ModbusTlsServer(device, address=("127.0.0.1", 0), sslctx=context),
            "pymodbus-tls-slave",
        )


def test_pymodbus_tls_server_as_an_independent_slave(
    make_gateway: GatewayFactory, pki: Pki
) -> None:
    slave = PymodbusTlsSlave(pki)
    gw = make_gateway({"lines": {"plc": tls_line(pki, slave.port)}})
    try:
        wait_until(lambda: line_up(gw), "the tls line never came up")
        with gw.connect() as master:
            tid = master.send(7, h("03 0000 0004"), tid=0x4242)
            reply = master.receive()
            assert (reply.transaction_id, reply.pdu) == (
                tid,
                h("03 08") + pack_registers([0, 10, 20, 30]),
            )
            assert master.request(7, h("10 0002 0002 04 1111 2222")) == h("10 0002 0002")
            assert master.request(7, h("03 0001 0003")) == h("03 06") + pack_registers(
                [10, 0x1111, 0x2222]
            )
            assert master.request(7, h("01 0000 000A")) == h("01 02 49 02")
            assert master.request(7, h("05 0001 FF00")) == h("05 0001 FF00")
            assert master.request(7, h("01 0000 000A")) == h("01 02 4B 02")
            assert master.request(7, h("03 0100 0001")) == h("83 02")  # pymodbus's exception
    finally:
        # The gateway first: it reconnects at once when its slave goes, and a connection
        # still in its handshake as pymodbus shuts down is never closed by pymodbus.
        gw.stop()
        slave.close()


# --------------------------------------------------------------------------- every function code


@pytest.mark.parametrize(("request_hex", "response_hex"), FUNCTION_VECTORS)
def test_every_function_code_through_tcp_and_tls_lines(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, request_hex: str,
    response_hex: str,
) -> None:  # fmt: skip
    """Gateway A's unit 7 goes over a tcp line, unit 8 over a tls line, to twin PLCs behind B."""
    twin_a, twin_b = make_sim({7: plc(7)}), make_sim({7: plc(7)})
    slave = make_gateway({
        "lines": {"x": twin_a.line_table([7]), "y": twin_b.line_table([])},
        "routes": [{"unit": 8, "line": "y", "slave": 7}],
        "listeners": [tls_listener(pki, policy="all")],
        "policies": {"all": {"rules": [{"role": "operator", "units": [7, 8]}]}},
    })  # fmt: skip
    plain = slave.address[1]
    gw = make_gateway({
        "lines": {
            "t": {"kind": "tcp", "address": f"127.0.0.1:{plain}", "units": [7], "timeout": 1.0},
            "s": tls_line(pki, tls_port(slave), units=[8]),
        },
    })  # fmt: skip
    wait_until(lambda: line_up(gw, "t") and line_up(gw, "s"), "the lines never came up")
    with gw.connect() as master:
        through_tcp = master.request(7, h(request_hex))
        through_tls = master.request(8, h(request_hex))
    assert through_tcp == h(response_hex)
    assert through_tls == through_tcp


# --------------------------------------------------------------------------- kill and restart


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


class SlaveProcess:
    """Gateway B as a real process (Modbus TCP and Modbus/TCP Security), to SIGKILL and restart."""

    def __init__(self, device: str, pki: Pki) -> None:
        self.plain, self.tls = free_port(), free_port()
        self.argv = [
            sys.executable, "-m", "gateway", "--serial", device, "--baudrate", "115200",
            "--timeout", "0.5", "--listen", f"127.0.0.1:{self.plain}",
            "--tls-listen", f"127.0.0.1:{self.tls}", "--tls-cert", str(pki.server_chain),
            "--tls-key", str(pki.server_key), "--tls-ca", str(pki.ca), "--metrics", "off",
            "--log-level", "warning",
        ]  # fmt: skip
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.process = subprocess.Popen(self.argv, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + DEADLINE_S
        for port in (self.plain, self.tls):
            while True:
                try:
                    socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                    break
                except OSError:
                    assert self.process.poll() is None, "the slave gateway exited"
                    assert time.monotonic() < deadline, "the slave gateway never listened"
                    time.sleep(0.02)

    def kill(self) -> None:
        assert self.process is not None
        self.process.kill()
        self.process.wait(DEADLINE_S)

    def close(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.kill()


@pytest.mark.slow  # kills and restarts slaves under load, ~4 s per case
@pytest.mark.parametrize("in_flight", [1, 4])
def test_tcp_and_tls_slaves_killed_and_restarted_under_load_give_no_wrong_answer(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, in_flight: int
) -> None:
    """Six masters (three through each kind) check every answer; B is SIGKILLed three times.

    With ``max_in_flight = 4`` several requests are lost with each connection.
    """
    sim = make_sim({1: plc(1)})
    slave = SlaveProcess(sim.path, pki)
    slave.start()
    gw = make_gateway({
        "lines": {
            "t": {"kind": "tcp", "address": f"127.0.0.1:{slave.plain}", "units": [1],
                  "timeout": 1.0, "max_in_flight": in_flight},
            "s": tls_line(pki, slave.tls, units=[], timeout=1.0, max_in_flight=in_flight),
        },
        "routes": [{"unit": 2, "line": "s", "slave": 1}],
    })  # fmt: skip
    masters = 6
    stop = threading.Event()
    wrong: list[str] = []
    answered = [0] * masters
    unavailable = [0] * masters

    def master(index: int) -> None:
        unit = 1 if index % 2 == 0 else 2  # even masters through tcp, odd through tls
        try:
            with gw.connect() as client:
                round_ = 0
                while not stop.is_set():
                    if round_ % 4 == 3:  # a write of this master's own register and value
                        register, value = 1000 + index, (index << 12) | (round_ & 0xFFF)
                        pdu = h("06") + register.to_bytes(2, "big") + value.to_bytes(2, "big")
                        expected = pdu
                    else:
                        address = 2000 + 100 * index + round_ % 50
                        quantity = 1 + (round_ + index) % 40
                        pdu = h("03") + address.to_bytes(2, "big") + quantity.to_bytes(2, "big")
                        expected = bytes((3, 2 * quantity)) + pack_registers(
                            list(range(address, address + quantity))
                        )
                    reply = client.request(unit, pdu)
                    if reply == expected:
                        answered[index] += 1
                    elif reply in (bytes((pdu[0] | 0x80, 0x0A)), bytes((pdu[0] | 0x80, 0x0B))):
                        unavailable[index] += 1
                    else:
                        wrong.append(f"master {index} {pdu.hex()}: {reply.hex()}")
                    round_ += 1
        except (AssertionError, OSError) as error:
            wrong.append(f"master {index}: {error!r}")

    def progress() -> None:
        before = list(answered)
        wait_until(lambda: all(answered[i] >= before[i] + 10 for i in range(masters)),
                   f"masters stalled: {answered}")  # fmt: skip

    threads = [threading.Thread(target=master, args=(i,)) for i in range(masters)]
    try:
        wait_until(lambda: line_up(gw, "t") and line_up(gw, "s"), "the lines never came up")
        for thread in threads:
            thread.start()
        for _ in range(3):
            progress()
            slave.kill()
            wait_until(lambda: not line_up(gw, "t") and not line_up(gw, "s"), "no line went down")
            slave.start()
            wait_until(lambda: line_up(gw, "t") and line_up(gw, "s"), "the lines never came back")
        progress()
        lost = [sample(gw, "modbus_gateway_line_lost_total", line=line) for line in ("t", "s")]
    finally:
        stop.set()
        for thread in threads:
            thread.join(DEADLINE_S)
        slave.close()
    assert wrong == []
    assert sum(unavailable) > 0  # the kills were felt
    assert lost == [3, 3]
    assert sample(gw, "modbus_gateway_line_info", line="s", kind="tls") == 1
    for reason in ("untrusted_certificate", "name_mismatch", "certificate_refused"):
        assert sample(gw, "modbus_gateway_line_tls_failures_total", line="s", reason=reason) == 0


def test_a_plain_modbus_tcp_port_and_a_silent_one(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, bus_log: LogCollector
) -> None:
    slave = slave_gateway(make_sim, make_gateway, pki)
    silent = socket.create_server(("127.0.0.1", 0))  # connections wait in its backlog, unread
    try:
        gw = make_gateway({
            "lines": {
                "plain": tls_line(pki, slave.address[1], units=[7]),
                "silent": tls_line(pki, silent.getsockname()[1], units=[8],
                                   tls_handshake_timeout=0.2),
            },
        })  # fmt: skip
        failures = "modbus_gateway_line_tls_failures_total"
        wait_until(lambda: sample(gw, failures, line="plain", reason="closed") >= 2
                   and sample(gw, failures, line="silent", reason="timeout") >= 2,
                   "no closed and timeout failures")  # fmt: skip
        with gw.connect() as master:
            assert master.request(7, h("03 0000 0001")) == h("83 0A")
            assert master.request(8, h("03 0000 0001")) == h("83 0A")
    finally:
        silent.close()
    (plain,) = [text for text in bus_log.messages if "line 'plain'" in text]
    assert "not speak TLS on this port" in plain
    (timeout,) = [text for text in bus_log.messages if "line 'silent'" in text]
    assert "no complete handshake within 0.2 s (lines.silent.tls_handshake_timeout)" in timeout


def test_a_reload_with_another_client_certificate_reopens_the_line(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path
) -> None:
    from gateway.config import build_config

    slave = slave_gateway(make_sim, make_gateway, pki)
    port = tls_port(slave)
    raw: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0"}, "metrics": {"listen": "127.0.0.1:0"},
        "lines": {"plc": tls_line(pki, port, "operator")},
    }  # fmt: skip
    gw = make_gateway(raw)
    wait_until(lambda: line_up(gw), "the tls line never came up")
    with gw.connect() as master:
        assert master.request(7, h("06 0020 0001")) == h("06 0020 0001")
    # A missing file: the reload is refused, the running line and its session stay.
    broken = dict(raw, lines={"plc": tls_line(pki, port, "operator", ca=str(tmp_path / "no"))})
    gw.run(gw.gateway.reload(build_config(broken, "<test>")))
    with gw.connect() as master:
        assert master.request(7, h("06 0020 0002")) == h("06 0020 0002")
    viewer = dict(raw, lines={"plc": tls_line(pki, port, "viewer")})
    gw.run(gw.gateway.reload(build_config(viewer, "<test>")))
    wait_until(lambda: line_up(gw), "the tls line never came back")
    with gw.connect() as master:
        assert master.request(7, h("06 0020 0003")) == h("86 01")  # B now sees the viewer
        assert master.request(7, h("03 0020 0001")) == h("03 02 0002")


def test_a_tls_slave_sending_garbage_is_reconnected(make_gateway: GatewayFactory, pki: Pki) -> None:
    """20 KiB of bytes no Modbus TCP slave sends, in several TLS records: the connection is
    dropped and remade, and the read on the wire is sent again on the new one."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(str(pki.server_chain), str(pki.server_key))
    context.load_verify_locations(cafile=str(pki.ca))
    context.verify_mode = ssl.CERT_REQUIRED
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(DEADLINE_S)
    connections: list[int] = []

    def slave() -> None:
        for number in (1, 2):
            raw, _ = listener.accept()
            raw.settimeout(DEADLINE_S)
            with context.wrap_socket(raw, server_side=True) as conn:
                connections.append(number)
                request = conn.recv(260)
                if number == 1:
                    conn.sendall(b"\xff" * 20_480)
                    with contextlib.suppress(OSError):  # until the gateway closes it
                        conn.recv(260)
                    continue
                with contextlib.suppress(OSError):  # every request, until the gateway stops
                    while request:
                        conn.sendall(request[:4] + b"\x00\x05\x07\x03\x02\x12\x34")
                        request = conn.recv(260)
        listener.close()

    thread = threading.Thread(target=slave, daemon=True)
    thread.start()
    gw = make_gateway({"lines": {"plc": tls_line(pki, listener.getsockname()[1], retries=0)}})
    wait_until(lambda: line_up(gw), "the tls line never came up")
    with gw.connect() as master:
        # The stream was dropped; the read went again on the new connection.
        assert master.request(7, h("03 0000 0001")) == h("03 02 1234")
        assert connections == [1, 2]
        assert master.request(7, h("03 0000 0001")) == h("03 02 1234")
    discarded = "modbus_gateway_discarded_frames_total"
    assert sample(gw, discarded, line="plc", reason="bad_header") == 1
    reconnects = "modbus_gateway_line_reconnects_total"
    assert sample(gw, reconnects, line="plc", reason="out_of_step") == 1
    gw.stop()
    thread.join(DEADLINE_S)


def test_a_refused_line_comes_back_when_the_slave_trusts_its_certificate(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, bus_log: LogCollector
) -> None:
    from cryptography.hazmat.primitives import serialization

    from gateway.config import build_config

    sim = make_sim({7: plc(7)})
    listener = tls_listener(pki)
    del listener["policy"]  # no rules: every role may do anything
    raw: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0"}, "metrics": {"listen": "127.0.0.1:0"},
        "lines": {"a": sim.line_table([7])}, "listeners": [listener],
    }  # fmt: skip
    slave = make_gateway(raw)
    gw = make_gateway({"lines": {"plc": tls_line(pki, tls_port(slave), "otherca")}})
    failures = "modbus_gateway_line_tls_failures_total"
    wait_until(lambda: sample(gw, failures, line="plc", reason="closed") >= 2, "not refused")
    both = pki.directory / "both-roots.pem"
    both.write_bytes(
        pki.ca.read_bytes() + pki.other_root.certificate.public_bytes(serialization.Encoding.PEM)
    )
    raw["listeners"][0]["ca"] = str(both)
    slave.run(slave.gateway.reload(build_config(raw, "<test>")))
    with gw.connect() as master:
        deadline = time.monotonic() + DEADLINE_S
        while master.request(7, h("03 0000 0002")) != h("03 04 0000 0002"):
            assert time.monotonic() < deadline, "the line never came back"
    refusals = [text for text in bus_log.messages if "may refuse the gateway's certificate" in text]
    back = [text for text in bus_log.messages if "accepted, back up" in text]
    assert (len(refusals), len(back)) == (1, 1), bus_log.messages


def test_a_slave_that_speaks_only_tls_1_1(
    make_gateway: GatewayFactory, pki: Pki, bus_log: LogCollector
) -> None:
    slave = StdlibTlsSlave(pki, ssl.TLSVersion.TLSv1_1)
    try:
        gw = make_gateway({"lines": {"plc": tls_line(pki, slave.port)}})
        failures = "modbus_gateway_line_tls_failures_total"
        wait_until(lambda: sample(gw, failures, line="plc", reason="protocol_version") >= 2,
                   "no protocol_version failures")  # fmt: skip
        with gw.connect() as master:
            assert master.request(7, h("03 0000 0001")) == h("83 0A")
    finally:
        slave.close()
    (logged,) = [text for text in bus_log.messages if "no TLS version in common" in text]
    assert "TLS 1.2 or newer" in logged
