"""The TLS flags in a real ``modbus-gateway`` process: serve, reload certificates, refuse bad ones.

The line's device does not exist, so every request is answered 0x0A by the
gateway itself: these tests are about the listener, not the line.
"""

from __future__ import annotations

import datetime as dt
import http.client
import os
import re
import shutil
import signal
import socket
import ssl
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding

from gateway.io.listeners.tls import role_from_certificate
from gateway.sim.pki import DAY, Pki
from tests.helpers import LoggedProcess, mbap, require_tool

DEADLINE_S = 10.0
READ = bytes.fromhex("03 0000 0001")


class Gateway(LoggedProcess):
    """``python -m gateway ARGS`` with its log (stdout and stderr) collected line by line."""

    def __init__(self, *args: str) -> None:
        super().__init__(*args, merge_stdout=True)

    def close(self) -> int:
        """SIGTERM if it still runs; close its pipe; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        self.release()
        return self.proc.returncode


def context(pki: Pki, client: str) -> ssl.SSLContext:
    result = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    result.load_verify_locations(cafile=str(pki.ca))
    result.load_cert_chain(*pki.client(client))
    return result


def request(sock: ssl.SSLSocket, tid: int, pdu: bytes) -> bytes:
    sock.sendall(mbap(tid, 1, pdu))
    header = sock.recv(7)
    while len(header) < 7:
        header += sock.recv(7 - len(header))
    length = struct.unpack(">HHHB", header)[2]
    body = sock.recv(length - 1)
    return body


def connect(address: tuple[str, int], pki: Pki, client: str = "operator") -> ssl.SSLSocket:
    raw = socket.create_connection(address, timeout=DEADLINE_S)
    return context(pki, client).wrap_socket(raw, server_hostname="localhost")


def serial_of(sock: ssl.SSLSocket) -> int:
    der = sock.getpeercert(binary_form=True)
    assert der is not None
    return x509.load_der_x509_certificate(der).serial_number


def config_file(tmp_path: Path, extra: str = "") -> Path:
    path = tmp_path / "gateway.toml"
    path.write_text(f'[lines.a]\ndevice = "{tmp_path}/no-such-adapter"\nunits = [1]\n{extra}')
    return path


def metric(address: tuple[str, int], name: str, labels: str) -> float:
    connection = http.client.HTTPConnection(*address, timeout=DEADLINE_S)
    try:
        connection.request("GET", "/metrics")
        text = connection.getresponse().read().decode()
    finally:
        connection.close()
    match = re.search(rf"^{name}\{{{labels}\}} (\S+)$", text, re.MULTILINE)
    assert match, f"{name}{{{labels}}} not in /metrics"
    return float(match[1])


def install(pki: Pki, chain: Path, key: Path, tmp_path: Path) -> None:
    """Put a server chain and key where the gateway reads them (one rename each)."""
    for source, target in ((chain, tmp_path / "live.pem"), (key, tmp_path / "live.key")):
        shutil.copy(source, target.with_suffix(".tmp"))
        os.replace(target.with_suffix(".tmp"), target)


@pytest.fixture(params=["file", "flags only"])
def running(request: pytest.FixtureRequest, tmp_path: Path, pki: Pki) -> Iterator[Gateway]:
    """A gateway serving TLS from the flags, with a configuration file or flags alone."""
    install(pki, pki.server_chain, pki.server_key, tmp_path)
    if request.param == "file":
        line = ["--config", str(config_file(tmp_path))]
    else:
        line = ["--serial", str(tmp_path / "no-such-adapter")]
    gateway = Gateway(
        *line, "--metrics", "127.0.0.1:0",
        "--tls-listen", "127.0.0.1:0", "--tls-cert", str(tmp_path / "live.pem"),
        "--tls-key", str(tmp_path / "live.key"), "--tls-ca", str(pki.ca),
        "--allow", "127.0.0.0/8", "--read-only",
    )  # fmt: skip
    try:
        yield gateway
    finally:
        gateway.close()


def test_tls_flags_serve_and_certificates_reload_on_sighup(
    running: Gateway, pki: Pki, tmp_path: Path
) -> None:
    match = running.wait_for(r"listening on ([\d.]+):(\d+) \(Modbus/TCP Security\), listener tls")
    address = (match[1], int(match[2]))
    metrics = running.wait_for(r"metrics on http://([\d.]+):(\d+)/metrics")
    metrics_address = (metrics[1], int(metrics[2]))
    assert "listener tcp" not in "\n".join(running.lines)  # --tls-listen alone: TLS only
    first = connect(address, pki)
    original = serial_of(first)
    assert request(first, 1, READ) == bytes([0x83, 0x0A])  # served (the line is down)
    assert request(first, 2, bytes.fromhex("06 0000 0001")) == bytes([0x86, 0x01])  # --read-only
    left = metric(metrics_address, "modbus_gateway_tls_certificate_expiry_seconds",
                  'kind="server",listener="tls",subject="modbus-gateway"')  # fmt: skip
    assert 364 * 86400 < left <= 365 * 86400

    now = dt.datetime.now(dt.UTC)
    renewed = pki.server_certificate("renewed", now - DAY, now + 30 * DAY)
    install(pki, *renewed, tmp_path)
    mark = running.mark()
    running.proc.send_signal(signal.SIGHUP)
    running.wait_for(r"reload: configuration from .* applied", mark)  # file or command line
    second = connect(address, pki)
    assert serial_of(second) != original
    assert request(second, 1, READ) == bytes([0x83, 0x0A])
    assert request(first, 3, READ) == bytes([0x83, 0x0A])  # the open session goes on
    left = metric(metrics_address, "modbus_gateway_tls_certificate_expiry_seconds",
                  'kind="server",listener="tls",subject="modbus-gateway"')  # fmt: skip
    assert 29 * 86400 < left <= 30 * 86400

    expired = pki.server_certificate("expired-server", now - 10 * DAY, now - DAY)
    install(pki, *expired, tmp_path)
    mark = running.mark()
    running.proc.send_signal(signal.SIGHUP)
    line = running.wait_for(r"reload rejected.*", mark)[0]
    assert "live.pem" in line and "expired on" in line and "renew it" in line
    third = connect(address, pki)
    assert serial_of(third) == serial_of(second)  # the running certificate stays
    for sock in (first, second, third):
        sock.close()
    assert running.close() == 0


def test_an_expired_server_certificate_stops_the_start(tmp_path: Path, pki: Pki) -> None:
    now = dt.datetime.now(dt.UTC)
    chain, key = pki.server_certificate("old", now - 10 * DAY, now - DAY)
    gateway = Gateway(
        "--config", str(config_file(tmp_path)), "--metrics", "off", "--tls-listen",
        "127.0.0.1:0", "--tls-cert", str(chain), "--tls-key", str(key), "--tls-ca", str(pki.ca),
    )  # fmt: skip
    assert gateway.proc.wait(DEADLINE_S) == 1
    gateway.wait_for(rf"cannot start: .*cert = '{re.escape(str(chain))}'.* expired on")
    assert not [line for line in gateway.lines if "listening on" in line]
    assert gateway.close() == 1


def test_check_config_validates_tls_files_and_warns_about_rules(tmp_path: Path, pki: Pki) -> None:
    tls = f"""
[[listeners]]
name = "secure"
protocol = "tls"
listen = "127.0.0.1:8802"
cert = "{pki.server_chain}"
key = "{pki.server_key}"
ca = "{pki.ca}"
policy = "plant"

[[policies.plant.rules]]
role = "operator"
units = [1, 77]

[[policies.plant.rules]]
role = "operator"
units = [1]
access = "read"
"""
    good = config_file(tmp_path, tls)
    checked = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(good)],
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert checked.returncode == 0, checked.stderr
    assert "policies.plant.rules[1] (listener 'secure'): adds nothing to " in checked.stderr
    assert "listening on 127.0.0.1:8802 (secure, tls)" in checked.stdout
    broken = config_file(tmp_path, tls.replace(str(pki.server_key), str(tmp_path / "gone.key")))
    checked = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(broken)],
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert checked.returncode == 2
    assert f"listeners[0].key = '{tmp_path / 'gone.key'}': cannot read" in checked.stderr


def check_metrics_tls(
    tmp_path: Path, cert: Path, key: Path, ca: Path
) -> subprocess.CompletedProcess[str]:
    """``modbus-gateway check-config`` on a file whose HTTP endpoint has these TLS files."""
    metrics = f'[metrics]\nlisten = "127.0.0.1:0"\ntls_cert = "{cert}"\ntls_key = "{key}"\n'
    return subprocess.run(
        [sys.executable, "-m", "gateway", "check-config",
         str(config_file(tmp_path, metrics + f'tls_ca = "{ca}"\n'))],
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip


def test_check_config_validates_the_http_endpoints_tls_files(tmp_path: Path, pki: Pki) -> None:
    """The ``[metrics]`` TLS files are checked as a listener's are: key, file and fix."""
    assert check_metrics_tls(tmp_path, pki.server_chain, pki.server_key, pki.ca).returncode == 0
    gone = tmp_path / "gone.pem"
    checked = check_metrics_tls(tmp_path, gone, pki.server_key, pki.ca)
    assert checked.returncode == 2
    assert f"metrics.tls_cert = '{gone}': cannot read: No such file" in checked.stderr
    assert "check the path, and that the gateway's user may read the file" in checked.stderr
    now = dt.datetime.now(dt.UTC)
    chain, key = pki.server_certificate("old-https", now - 10 * DAY, now - DAY)
    checked = check_metrics_tls(tmp_path, chain, key, pki.ca)
    assert checked.returncode == 2
    assert f"metrics.tls_cert = '{chain}': the server certificate" in checked.stderr
    assert "renew it" in checked.stderr
    checked = check_metrics_tls(tmp_path, pki.server_chain, pki.ca, pki.ca)  # not its key
    assert checked.returncode == 2 and f"metrics.tls_key = '{pki.ca}': cannot be" in checked.stderr
    checked = check_metrics_tls(tmp_path, pki.server_chain, pki.server_key, pki.server_key)
    assert checked.returncode == 2
    assert f"metrics.tls_ca = '{pki.server_key}': no PEM certificate" in checked.stderr


def docs_block(marker: str) -> str:
    """The first ```sh block after ``marker`` in the manual's security page."""
    docs = Path(__file__).resolve().parents[2] / "docs"
    text = (docs / "listeners-and-security.md").read_text(encoding="utf-8")
    after = text[text.index(marker) :]
    start = after.index("```sh\n") + len("```sh\n")
    return after[start : after.index("```", start)]


def test_the_manuals_tls_setup_works(tmp_path: Path) -> None:
    """The manual's openssl commands make a PKI the gateway, Python and s_client accept."""
    openssl = require_tool("openssl")
    made = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", docs_block("<!-- tls-setup -->")],
        cwd=tmp_path, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    tls = tmp_path / "tls"
    for role in ("operator", "viewer"):
        der = x509.load_pem_x509_certificate((tls / f"{role}.pem").read_bytes())
        assert role_from_certificate(der.public_bytes(Encoding.DER)) == role
    gateway = Gateway(
        "--serial", str(tmp_path / "no-such-adapter"), "--metrics", "off", "--tls-listen",
        "127.0.0.1:0", "--tls-cert", str(tls / "server.pem"), "--tls-key",
        str(tls / "server.key"), "--tls-ca", str(tls / "ca.pem"), "--trace",
    )  # fmt: skip
    try:
        match = gateway.wait_for(r"listening on ([\d.]+):(\d+) \(Modbus/TCP Security\)")
        context = ssl.create_default_context(cafile=str(tls / "ca.pem"))  # checks the name too
        context.load_cert_chain(str(tls / "viewer.pem"), str(tls / "viewer.key"))
        raw = socket.create_connection((match[1], int(match[2])), timeout=DEADLINE_S)
        with context.wrap_socket(raw, server_hostname="localhost") as sock:
            assert request(sock, 7, READ) == bytes([0x83, 0x0A])  # served; the line is down
        gateway.wait_for(r"-> \S+ tid=7 unit=1 read_holding_registers\(3\) .* via tls role=viewer")
        checked = subprocess.run(
            [openssl, "s_client", "-connect", f"{match[1]}:{match[2]}", "-CAfile",
             str(tls / "ca.pem"), "-cert", str(tls / "operator.pem"), "-key",
             str(tls / "operator.key"), "-brief"],
            input="", capture_output=True, text=True, timeout=DEADLINE_S, check=False,
        )  # fmt: skip
        assert "Verification: OK" in checked.stderr, checked.stderr
    finally:
        assert gateway.close() == 0
