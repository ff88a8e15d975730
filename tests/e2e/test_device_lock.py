"""One owner per serial device: TIOCEXCL and advisory locks, and errors that name the holder.

Two gateways (real CLI subprocesses) on one pseudo-terminal: the second fails at
start naming the first's pid and command line, the first keeps serving. A holder
that takes only a ``flock`` (pyserial's ``exclusive=True``) is named through
``/proc/locks``. A line reopened on reload while another program holds its device
says who holds it and comes up when the device is released.
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import struct
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gateway.config import build_config
from gateway.io.links.serial_port import DeviceBusyError
from gateway.sim import plc
from tests.e2e.test_cli import GatewayProcess, RunGateway, gateway_command
from tests.helpers import (
    DEADLINE_S,
    UNPACED_BAUDRATE,
    GatewayFactory,
    RawClient,
    SimFactory,
    release,
)

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="needs Linux ptys and locks")

READ_2 = bytes([0x03, 0x00, 0x00, 0x00, 0x02])
#: ``TIOCGEXCL`` (Linux 3.8+): is the terminal in exclusive mode? Not in Python's termios.
TIOCGEXCL = 0x80045440


def gateway_args(device: str) -> tuple[str, ...]:
    return ("--serial", device, "--baudrate", str(UNPACED_BAUDRATE),
            "--listen", "127.0.0.1:0", "--metrics", "off")  # fmt: skip


class FlockHolder:
    """Another program holding a device the way pyserial's ``exclusive=True`` does."""

    def __init__(self, device: str) -> None:
        script = (
            "import serial, sys\n"
            f"port = serial.Serial({device!r}, exclusive=True)\n"
            "print('locked', flush=True)\n"
            "sys.stdin.read()\n"
        )
        self.process = subprocess.Popen(
            [sys.executable, "-c", script],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert self.process.stdout is not None
        line = self.process.stdout.readline()  # blocks until the lock is held (or it died)
        assert line == "locked\n", f"holder failed: {line!r}"
        self.pid = self.process.pid

    def release(self) -> None:
        """Close its stdin: it exits, and the kernel drops its lock."""
        if self.process.poll() is None:
            assert self.process.stdin is not None
            self.process.stdin.close()
        release(self.process)


@pytest.fixture
def run_gateway() -> Iterator[RunGateway]:
    """``run_gateway(*args)`` → a ``GatewayProcess``, killed at teardown if still alive."""
    processes: list[GatewayProcess] = []

    def start(*args: str) -> GatewayProcess:
        processes.append(GatewayProcess(*args))
        return processes[-1]

    yield start
    for process in processes:
        process.kill()


@pytest.fixture
def flock_holder() -> Iterator[type[FlockHolder]]:
    holders: list[FlockHolder] = []

    class Tracked(FlockHolder):
        def __init__(self, device: str) -> None:
            super().__init__(device)
            holders.append(self)

    yield Tracked
    for holder in holders:
        holder.release()


def test_a_second_gateway_on_the_same_device_fails_naming_the_first(
    make_sim: SimFactory, run_gateway: RunGateway
) -> None:
    sim = make_sim({1: plc(1)})
    first = run_gateway(*gateway_args(sim.path))
    address = first.address()

    second = subprocess.run(
        gateway_command(*gateway_args(sim.path)),
        capture_output=True, text=True, timeout=DEADLINE_S * 3, check=False,
    )  # fmt: skip
    assert second.returncode == 1, second
    assert f"{sim.path} is in use by pid {first.process.pid} (" in second.stderr, second.stderr
    assert f"-m gateway --serial {sim.path}" in second.stderr, second.stderr
    assert "listening on" not in second.stderr  # it failed before binding anything

    with RawClient(address) as client:  # the first one is untouched
        assert client.request(1, READ_2)[:2] == bytes([0x03, 4])
    assert first.terminate() == 0

    third = run_gateway(*gateway_args(sim.path))  # the lock went with the first process
    with RawClient(third.address()) as client:
        assert client.request(1, READ_2)[:2] == bytes([0x03, 4])
    assert third.terminate() == 0


def test_the_gateway_holds_the_terminal_in_exclusive_mode(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    gateway = make_gateway({"lines": {"a": sim.line_table([1])}})

    def exclusive() -> bool:
        try:
            fd = os.open(sim.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as error:  # not root: TIOCEXCL refuses the open itself
            assert error.errno == 16, error
            return True
        try:
            flag = fcntl.ioctl(fd, TIOCGEXCL, b"\0\0\0\0")
            return bool(struct.unpack("i", flag)[0])
        finally:
            os.close(fd)

    assert exclusive()
    gateway.stop()
    assert not exclusive(), "the exclusive mode must be cleared when the gateway lets go"


def test_a_flock_holder_is_named_from_proc_locks(
    make_sim: SimFactory, make_gateway: GatewayFactory, flock_holder: type[FlockHolder]
) -> None:
    sim = make_sim({1: plc(1)})
    holder = flock_holder(sim.path)
    with pytest.raises(DeviceBusyError) as caught:
        make_gateway({"lines": {"a": sim.line_table([1])}})
    message = str(caught.value)
    assert message.startswith(f"line 'a': {sim.path} is in use by pid {holder.pid} ("), message
    assert "exclusive=True" in message  # its command line
    assert "lines.a.device" in message


class LogWaiter(logging.Handler):
    """Sets an event when a record matching a pattern is logged."""

    def __init__(self, pattern: str) -> None:
        super().__init__()
        self.pattern = re.compile(pattern)
        self.seen = threading.Event()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        self.messages.append(message)
        if self.pattern.search(message):
            self.seen.set()


def test_a_line_reopened_on_a_held_device_names_the_holder_and_waits_for_it(
    make_sim: SimFactory, make_gateway: GatewayFactory, flock_holder: type[FlockHolder]
) -> None:
    first, second = make_sim({1: plc(1)}), make_sim({1: plc(1)})
    gateway = make_gateway({"lines": {"a": first.line_table([1])}})
    holder = flock_holder(second.path)

    busy = LogWaiter(rf"{re.escape(second.path)} is in use by pid {holder.pid} ")
    back = LogWaiter(rf"line a: {re.escape(second.path)} open")
    logger = logging.getLogger("gateway")
    level = logger.level
    logger.setLevel(logging.INFO)
    for handler in (busy, back):
        logger.addHandler(handler)
    try:
        raw: dict[str, Any] = {
            "server": {"listen": "127.0.0.1:0"},
            "metrics": {"listen": "off"},
            "lines": {"a": second.line_table([1])},
        }
        gateway.run(gateway.gateway.reload(build_config(raw, "<reload>")))
        assert busy.seen.wait(DEADLINE_S), busy.messages
        assert not gateway.call(lambda: gateway.gateway.buses["a"].up)
        holder.release()
        assert back.seen.wait(DEADLINE_S), back.messages
    finally:
        logger.setLevel(level)
        for handler in (busy, back):
            logger.removeHandler(handler)
    with RawClient(gateway.address) as client:
        assert client.request(1, READ_2)[:2] == bytes([0x03, 4])


def test_check_config_reports_devices_units_and_ports(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(
        "[server]\nlisten = \"0.0.0.0:9502\"\n"
        "[lines.a]\ndevice = \"/dev/serial/by-id/not-plugged-in\"\nunits = [\"1-10\"]\n"
        "[lines.spare]\ndevice = \"/dev/null\"\n"
    )  # fmt: skip
    done = subprocess.run(
        gateway_command("check-config", str(path)),
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done
    assert "3 warning(s)" in done.stdout
    for key in ("lines.a.device", "lines.spare.units", "metrics.listen"):
        assert f"{path}: warning: {key}: " in done.stderr, (key, done.stderr)
    strict = subprocess.run(
        gateway_command("check-config", "--strict", str(path)),
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert strict.returncode == 2, strict

    path.write_text(
        "[lines.a]\ndevice = \"/dev/null\"\nunits = [\"1-100\"]\nbaudate = 9600\n"
        "[lines.b]\ndevice = \"/dev/null\"\nunits = [\"50-247\"]\n"
    )  # fmt: skip
    done = subprocess.run(
        gateway_command("check-config", str(path)),
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert done.returncode == 2, done
    assert done.stderr.count("\n  - ") == 3, done.stderr
    assert "lines.a.baudate: unknown key; did you mean 'baudrate'?" in done.stderr
    assert "lines.b.device: '/dev/null' is the device of line 'a' too" in done.stderr
    assert "lines.b.units: units 50-100 already routed to line 'a'" in done.stderr
