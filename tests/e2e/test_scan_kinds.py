"""`modbus-gateway scan --config F --line NAME` on every line kind, through the real command.

rtu and ascii: the simulator on a pty. rtu-over-tcp: socat as the serial device server in
front of that pty. tcp and tls: the simulator's Modbus TCP slave, plain and behind TLS
with the test PKI.
"""

from __future__ import annotations

import json
import socket
import ssl
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.sim import plc, zl69x
from gateway.sim.pki import Pki
from gateway.sim.tcp import SimulatedTcpSlave
from tests.helpers import DEADLINE_S, UNPACED_BAUDRATE, SimFactory, require_tool, wait_until


def _scan(config: Path, line: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", "scan", "--config", str(config), "--line", line,
         "--range", "1-6", "--timeout", "0.2", "--json", *args],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip


def _found(done: subprocess.CompletedProcess[str]) -> dict[int, dict[int, str]]:
    """Address → its device identification, from the scan's JSON."""
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    return {
        slave["address"]: {int(k): v for k, v in slave["identification"].items()}
        for slave in result["slaves"]
    }


def _config(tmp_path: Path, table: str) -> Path:
    """A file with a decoy line first, so ``--line`` has to choose."""
    path = tmp_path / "gateway.toml"
    path.write_text('[lines.decoy]\ndevice = "/dev/null"\nunits = [9]\n\n' + table)
    return path


def test_scan_an_rtu_line(make_sim: SimFactory, tmp_path: Path) -> None:
    sim = make_sim({2: plc(2), 5: zl69x(5)})
    config = _config(tmp_path, f'[lines.plant]\ndevice = "{sim.path}"\n'
                     f"baudrate = {UNPACED_BAUDRATE}\nunits = [2]\n")  # fmt: skip
    found = _found(_scan(config, "plant"))
    assert sorted(found) == [2, 5]
    assert "ZL-69X" in " ".join(found[5].values())


def test_scan_an_ascii_line(make_sim: SimFactory, tmp_path: Path) -> None:
    sim = make_sim({4: zl69x(4)}, framing="ascii")
    # A pty takes 8N1 only (ASCII's default is 7E1).
    config = _config(tmp_path, f'[lines.meters]\nkind = "ascii"\ndevice = "{sim.path}"\n'
                     f'baudrate = {UNPACED_BAUDRATE}\ndata_bits = 8\nparity = "N"\n'
                     "units = [4]\n")  # fmt: skip
    found = _found(_scan(config, "meters"))
    assert sorted(found) == [4]
    assert "ZL-69X" in " ".join(found[4].values())


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _listening(port: int) -> bool:
    shown = subprocess.run(["ss", "-ltnH", f"sport = :{port}"], capture_output=True, text=True,
                           check=False)  # fmt: skip
    return f":{port}" in shown.stdout


@pytest.fixture
def device_server(make_sim: SimFactory) -> Iterator[int]:
    """socat as a serial device server (raw TCP ↔ the simulator's pty): its port."""
    socat = require_tool("socat")
    require_tool("ss")
    sim = make_sim({3: plc(3), 6: plc(6)})
    port = _free_port()
    server = subprocess.Popen(
        [socat, f"TCP-LISTEN:{port},bind=127.0.0.1,reuseaddr", f"FILE:{sim.path},raw,echo=0"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        # Without fork socat serves one connection: a probe that connects would use it up.
        wait_until(lambda: _listening(port), "socat listening")
        yield port
    finally:
        server.terminate()
        server.wait(DEADLINE_S)
        if server.stderr is not None:
            server.stderr.close()


def test_scan_an_rtu_over_tcp_line(device_server: int, tmp_path: Path) -> None:
    config = _config(tmp_path, '[lines.remote]\nkind = "rtu-over-tcp"\n'
                     f'address = "127.0.0.1:{device_server}"\nunits = [3]\n')  # fmt: skip
    done = _scan(config, "remote", "--no-identify")
    assert sorted(_found(done)) == [3, 6]
    auto = _scan(config, "remote", "--baudrate", "auto")
    assert auto.returncode == 2
    assert "line 'remote' is a rtu-over-tcp line" in auto.stderr
    assert "serial" not in auto.stderr.replace("serial side", "")  # no dialout advice


def test_scan_a_modbus_tcp_line(tmp_path: Path) -> None:
    with SimulatedTcpSlave({1: plc(1), 2: zl69x(2)}, direct_unit=False) as slave:
        config = _config(tmp_path, f'[lines.tcp]\nkind = "tcp"\naddress = "{slave.host_port}"\n'
                         "units = [1]\n")  # fmt: skip
        done = _scan(config, "tcp")
        table = subprocess.run(
            [sys.executable, "-m", "gateway", "scan", "--config", str(config), "--line", "tcp",
             "--range", "1-3", "--no-identify"],
            stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
    found = _found(done)
    assert sorted(found) == [1, 2]  # unit 3 answers 0x0B (nobody there): not a slave
    assert "ZL-69X" in " ".join(found[2].values())
    assert table.stdout.splitlines()[0] == f"{slave.host_port} (tcp): 2 slave(s)"


def test_scan_a_modbus_tcp_security_line(tmp_path: Path, pki: Pki) -> None:
    server = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    server.load_cert_chain(pki.server_chain, pki.server_key)
    server.load_verify_locations(pki.ca)
    server.verify_mode = ssl.CERT_REQUIRED  # the gateway's client certificate is checked
    with SimulatedTcpSlave({7: plc(7)}, ssl=server, direct_unit=False) as slave:

        def line(client: str) -> str:
            cert, key = pki.client(client)
            return (f'[lines.secure]\nkind = "tls"\naddress = "{slave.host_port}"\n'
                    f'cert = "{cert}"\nkey = "{key}"\nca = "{pki.ca}"\nunits = [7]\n')  # fmt: skip

        done = _scan(_config(tmp_path, line("operator")), "secure", "--range", "7")
        refused = _scan(_config(tmp_path, line("otherca")), "secure", "--range", "7")
    found = _found(done)
    assert sorted(found) == [7]
    assert found[7]  # the device identification came over TLS too
    assert refused.returncode == 1  # the slave does not trust that client certificate
    assert f"line 'secure': no tls connection with {slave.host_port}" in refused.stderr


def test_scan_says_which_connection_failed(tmp_path: Path) -> None:
    port = _free_port()  # nothing listens there
    config = _config(tmp_path, f'[lines.tcp]\nkind = "tcp"\naddress = "127.0.0.1:{port}"\n'
                     "units = [1]\n")  # fmt: skip
    done = _scan(config, "tcp")
    assert done.returncode == 1
    assert f"line 'tcp': no tcp connection with 127.0.0.1:{port}" in done.stderr
    assert "dialout" not in done.stderr
