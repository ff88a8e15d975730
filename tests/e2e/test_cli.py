"""The real command line in a subprocess: ``python -m gateway ...`` answering a real client.

Readiness is the gateway's own log line ("listening on HOST:PORT"), read from
its stderr with a deadline; the port is 0 wherever the test can, and taken
from that line. Stops are SIGTERM, and the exit code is checked.
"""

from __future__ import annotations

import os
import queue
import re
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from gateway import __version__, build
from gateway.core.ascii import encode_ascii
from gateway.sim import open_pty_pair, plc, zl69x
from gateway.sim.device import pack_registers
from tests.helpers import DEADLINE_S, RawClient, Reply, SimFactory, h, release

LISTENING = re.compile(r"listening on ([0-9.]+):(\d+)")


def gateway_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "gateway", *args]


class GatewayProcess:
    """``modbus-gateway`` running in a subprocess, its stderr collected line by line."""

    def __init__(self, *args: str) -> None:
        self.process = subprocess.Popen(
            gateway_command(*args),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.log: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.lines.put(line)
        self.lines.put(None)

    def wait_for(self, pattern: re.Pattern[str], timeout: float = DEADLINE_S) -> re.Match[str]:
        """The first stderr line matching ``pattern``, within ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"no {pattern.pattern!r} on stderr: {''.join(self.log)}")
            try:
                line = self.lines.get(timeout=remaining)
            except queue.Empty:
                continue
            if line is None:
                code = self.process.wait(DEADLINE_S)
                raise AssertionError(f"exited with {code} before {pattern.pattern!r}: {self.log}")
            self.log.append(line)
            match = pattern.search(line)
            if match:
                return match

    def address(self) -> tuple[str, int]:
        """Wait for the gateway to listen; return where."""
        match = self.wait_for(LISTENING)
        return match.group(1), int(match.group(2))

    def terminate(self) -> int:
        """SIGTERM, then the exit code."""
        self.process.send_signal(signal.SIGTERM)
        return self.process.wait(DEADLINE_S)

    def kill(self) -> None:
        """Kill it if it still runs; close its pipes."""
        if self.process.poll() is None:
            self.process.kill()
        release(self.process, self._reader)


RunGateway = Callable[..., GatewayProcess]


@pytest.fixture
def run_gateway() -> Iterator[RunGateway]:
    """``run_gateway(*args)`` → a started ``GatewayProcess``, killed at teardown if still alive."""
    processes: list[GatewayProcess] = []

    def start(*args: str) -> GatewayProcess:
        process = GatewayProcess(*args)
        processes.append(process)
        return process

    yield start
    for process in processes:
        process.kill()


def test_config_file_serves_a_simulated_line(
    tmp_path: Path, make_sim: SimFactory, run_gateway: RunGateway
) -> None:
    sim = make_sim({1: plc(1), 2: zl69x(2)}, baudrate=19200)
    config = tmp_path / "gateway.toml"
    config.write_text(
        f"""
[server]
listen = "127.0.0.1:0"
max_pipeline = 4

[metrics]
listen = "off"

[lines.field]
device = "{sim.path}"
baudrate = 19200
timeout = 0.3
units = [1, 2]

[[routes]]
unit = 100
line = "field"
slave = 2
"""
    )
    gateway = run_gateway("--config", str(config))
    with RawClient(gateway.address()) as client:
        tid = client.send(1, h("03 0000 000A"), tid=0x2A2A)
        assert client.receive() == Reply(
            tid, 1, h("03 14") + pack_registers([0, 2, 4, 6, 8, 10, 0, 0, 0, 0])
        )
        assert client.request(100, h("03 0000 0002")) == h("03 04 0113 FF9D")
        assert client.request(2, h("06 0008 00F0")) == h("06 0008 00F0")
        assert client.request(3, h("03 0000 0001")) == h("83 0A")
    assert sim.device(2).holding[8] == 0xF0
    assert gateway.terminate() == 0
    stats = sim.stats()
    assert (stats.requests, stats.early_requests, stats.collisions) == (3, 0, 0)


def test_demo_answers_a_client_and_stops_on_sigterm(run_gateway: RunGateway) -> None:
    gateway = run_gateway("--demo", "--listen", "127.0.0.1:0", "--metrics", "off")
    host, port = gateway.address()
    assert host == "127.0.0.1" and port > 0
    with RawClient((host, port)) as client:
        # The PLC's manual example, the ZL-69X's temperatures, the power controller's current.
        assert client.request(1, h("03 0000 000A")) == h("03 14") + pack_registers(
            [0, 2, 4, 6, 8, 10, 0, 0, 0, 0]
        )
        assert client.request(2, h("03 0000 0002")) == h("03 04 0113 FF9D")
        assert client.request(3, h("03 0003 0003")) == h("03 06 0000 00B7 0000")
        assert client.request(3, h("03 0000 0006")) == h("83 03")
    assert gateway.terminate() == 0


def test_serial_flag_without_config_routes_every_unit(
    make_sim: SimFactory, run_gateway: RunGateway
) -> None:
    sim = make_sim({1: plc(1), 17: plc(17), 247: zl69x(247)})
    gateway = run_gateway(
        "--serial", sim.path, "--baudrate", "115200", "--timeout", "0.2", "--retries", "0",
        "--listen", "127.0.0.1:0", "--metrics", "off",
    )  # fmt: skip
    with RawClient(gateway.address()) as client:
        assert client.request(1, h("03 03E8 0002")) == h("03 04 03E8 03E9")
        assert client.request(17, h("06 0005 0011")) == h("06 0005 0011")
        assert client.request(247, h("03 0000 0001")) == h("03 02 0113")
        # Routed, but nobody answers at 200: the gateway tried (0x0B), it did not refuse (0x0A).
        assert client.request(200, h("03 0000 0001")) == h("83 0B")
        assert client.request(255, h("03 0000 0001")) == h("83 0A")
    assert sim.device(17).holding[5] == 0x11
    assert sim.stats().foreign_frames == 1  # the request to 200 went on the line
    assert gateway.terminate() == 0


def test_check_config_lists_every_problem_with_its_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(
        """
[server]
listen = "127.0.0.1:502"
max_pipeline = 0

[lines.a]
baudrate = "fast"
parity = "X"
units = [1, 300]
"""
    )
    done = subprocess.run(
        gateway_command("check-config", str(bad)),
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert done.returncode == 2, done
    for key in (
        "server.max_pipeline",
        "lines.a.device",
        "lines.a.baudrate",
        "lines.a.parity",
        "lines.a.units",
    ):
        assert key in done.stderr, (key, done.stderr)
    assert str(bad) in done.stderr

    good = tmp_path / "good.toml"
    good.write_text('[lines.a]\ndevice = "/dev/ttyUSB0"\nunits = ["1-10"]\n')
    done = subprocess.run(
        gateway_command("check-config", str(good)),
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done
    assert "OK" in done.stdout and "10 routed unit(s)" in done.stdout


def test_check_config_names_a_serial_slave_listeners_device_and_framing(tmp_path: Path) -> None:
    config = tmp_path / "reverse.toml"
    config.write_text(
        '[lines.a]\ndevice = "/dev/ttyUSB0"\nunits = [1]\n\n[[listeners]]\nname = "field"\n'
        'protocol = "serial-slave"\ndevice = "/dev/ttyUSB1"\nframing = "ascii"\n'
    )
    done = subprocess.run(
        gateway_command("check-config", str(config)),
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done
    assert "/dev/ttyUSB1 (field, serial-slave, ascii)" in done.stdout, done.stdout


def test_version() -> None:
    done = subprocess.run(
        gateway_command("--version"), capture_output=True, text=True, timeout=30, check=False
    )
    assert done.returncode == 0
    assert done.stdout.strip() == f"modbus-gateway {__version__} ({build()})"


@pytest.mark.parametrize(
    ("content", "expected"),
    [(None, "cannot read"), (b"\xff\xfe[server]\n", "not UTF-8")],
    ids=["a_directory", "not_utf8"],
)
def test_check_config_on_an_unreadable_file_names_the_fault(
    tmp_path: Path, content: bytes | None, expected: str
) -> None:
    path = tmp_path / "gateway.toml"
    if content is None:
        path.mkdir()
    else:
        path.write_bytes(content)
    checked = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(path)],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert checked.returncode == 2
    assert str(path) in checked.stderr and expected in checked.stderr


# --------------------------------------------------------------------------- line kinds


def test_serial_with_framing_ascii(make_sim: SimFactory, run_gateway: RunGateway) -> None:
    """ASCII lines default to 7E1; ptys refuse 7 data bits, so 8N1 here."""
    sim = make_sim({9: plc(9)}, framing="ascii")
    gateway = run_gateway(
        "--serial", sim.path, "--framing", "ascii", "--data-bits", "8", "--parity", "N",
        "--baudrate", "115200", "--listen", "127.0.0.1:0", "--metrics", "off",
    )  # fmt: skip
    with RawClient(gateway.address()) as client:
        assert client.request(9, h("03 03E8 0002")) == h("03 04 03E8 03E9")
        assert client.request(9, h("06 0005 0011")) == h("06 0005 0011")
    assert sim.device(9).holding[5] == 0x11
    assert sim.stats().crc_errors_in == 0
    assert gateway.terminate() == 0


def test_serial_slave_in_ascii(make_sim: SimFactory, run_gateway: RunGateway) -> None:
    """An ASCII master on the --serial-slave line reaches the RTU line's slave (8N1 on ptys)."""
    sim = make_sim({9: plc(9)})
    pair = open_pty_pair()
    try:
        gateway = run_gateway(
            "--serial", sim.path, "--serial-slave", pair.path, "--serial-slave-framing", "ascii",
            "--data-bits", "8", "--parity", "N", "--baudrate", "115200",
            "--listen", "127.0.0.1:0", "--metrics", "off",
        )  # fmt: skip
        gateway.wait_for(re.compile(r"answering as a slave on .* at 115200 baud \(ASCII\)"))
        os.write(pair.sim_fd, b":0903" + b"03E80002" + b"07\r\n")
        answer = b""
        deadline = time.monotonic() + DEADLINE_S
        while not answer.endswith(b"\r\n"):
            assert time.monotonic() < deadline, answer
            if select.select([pair.sim_fd], [], [], 0.1)[0]:
                answer += os.read(pair.sim_fd, 256)
        assert answer == encode_ascii(9, h("03 04 03E8 03E9"))
        assert gateway.terminate() == 0
    finally:
        pair.close()


def test_demo_has_an_ascii_device(run_gateway: RunGateway) -> None:
    gateway = run_gateway("--demo", "--listen", "127.0.0.1:0", "--metrics", "off")
    with RawClient(gateway.address()) as client:
        # The ZL-69X's temperatures, over Modbus ASCII at 9600 7E1 (unit 4).
        assert client.request(4, h("03 0000 0002")) == h("03 04 0113 FF9D")
        assert client.request(1, h("03 0000 0001")) == h("03 02 0000")  # the RTU line too
    assert gateway.terminate() == 0


METRICS_AT = re.compile(r"metrics on http://([\d.]+):(\d+)/metrics")


def test_demo_has_a_modbus_tcp_slave_the_r6_controller(run_gateway: RunGateway) -> None:
    """Unit 5 is the R6 robot controller behind a ``kind = "tcp"`` line (its unit id 0x01)."""
    import json
    import urllib.request

    gateway = run_gateway("--demo", "--listen", "127.0.0.1:0", "--metrics", "127.0.0.1:0")
    address = gateway.address()
    metrics_host, metrics_port = gateway.wait_for(METRICS_AT).groups()
    connected = re.compile(r"line demo-tcp: connected to 127\.0\.0\.1:\d+ \(tcp\)")
    if not any(connected.search(line) for line in gateway.log):  # it may precede the metrics line
        gateway.wait_for(connected)
    with RawClient(address) as client:
        # The R6 document's first example: the version number is 0x29 bytes long.
        assert client.request(5, h("03 0000 0001")) == h("03 02 0029")
        # Axis 1 and 2 positions, 32-bit, high word first: -123456 and 45000 (0.001 degree).
        assert client.request(5, h("03 0910 0004")) == h("03 08 FFFE 1DC0 0000 AFC8")
        # Global speed written with FC 6, read back with FC 4 (the same table).
        assert client.request(5, h("06 0903 0028")) == h("06 0903 0028")
        assert client.request(5, h("04 0903 0001")) == h("04 02 0028")
        assert client.request(1, h("03 0000 0001")) == h("03 02 0000")  # the RTU line too
    base = f"http://{metrics_host}:{metrics_port}"
    with urllib.request.urlopen(f"{base}/metrics", timeout=DEADLINE_S) as reply:
        metrics = reply.read().decode()
    assert 'modbus_gateway_line_info{kind="tcp",line="demo-tcp"} 1.0' in metrics
    with urllib.request.urlopen(f"{base}/status", timeout=DEADLINE_S) as reply:
        status = json.loads(reply.read())
    lines = {line["name"]: line for line in status["lines"]}
    assert lines["demo-tcp"]["kind"] == "tcp"
    assert [(s["unit"], s["state"]) for s in lines["demo-tcp"]["slaves"]] == [(1, "up")]
    assert gateway.terminate() == 0


def test_the_demo_starts_beside_whatever_holds_port_9502(run_gateway: RunGateway) -> None:
    """Without ``--metrics`` the demo's endpoint takes a free port and logs its URL."""
    import contextlib
    import socket
    import urllib.request

    with contextlib.ExitStack() as stack:
        holder = stack.enter_context(socket.socket())
        with contextlib.suppress(OSError):  # already held by something else: as good
            holder.bind(("127.0.0.1", 9502))
            holder.listen()
        gateway = run_gateway("--demo", "--listen", "127.0.0.1:0")
        gateway.address()
        host, port = gateway.wait_for(METRICS_AT).groups()
        assert (host, port) != ("127.0.0.1", "9502")
        with urllib.request.urlopen(f"http://{host}:{port}/healthz", timeout=DEADLINE_S) as reply:
            assert reply.status == 200
        assert gateway.terminate() == 0
