"""Start-up errors through the real command: a device that exists but cannot serve its line
stops the start with the fix (in the terms the user gave it), a device not plugged in yet
does not, permission is waited for while udev may still be setting it, and every message is
a complete sentence. Also what the start-up log names (the status page, an IPv6 URL) and
``trace --help``.
"""

from __future__ import annotations

import os
import queue
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.io.links.serial_port import PERMISSION_SETTLE_S
from gateway.sim import PtyPair, open_pty_pair
from tests.helpers import DEADLINE_S, release

REPO = Path(__file__).resolve().parents[2]
LISTENING = re.compile(r"listening on ([\d.]+):(\d+) \(Modbus TCP\)")
QUIET = ("--listen", "127.0.0.1:0", "--metrics", "off")


class Started:
    """The gateway in a subprocess (optionally under another user), stderr line by line."""

    def __init__(
        self, *args: str, prefix: tuple[str, ...] = (), env: dict[str, str] | None = None
    ) -> None:
        env = dict(os.environ, **(env or {}), PYTHONPATH=str(REPO), PYTHONDONTWRITEBYTECODE="1")
        self.process = subprocess.Popen(
            [*prefix, sys.executable, "-m", "gateway", *args], stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env, cwd="/",
        )  # fmt: skip
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.log: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.lines.put(line)
        self.lines.put(None)

    def wait_for(self, pattern: str, timeout: float = DEADLINE_S) -> re.Match[str]:
        """The first stderr line matching ``pattern``, within ``timeout``."""
        deadline = time.monotonic() + timeout
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                line = self.lines.get(timeout=remaining)
            except queue.Empty:
                break
            if line is None:
                raise AssertionError(f"exited before {pattern!r}: {''.join(self.log)}")
            self.log.append(line)
            if match := re.search(pattern, line):
                return match
        raise AssertionError(f"no {pattern!r} within {timeout} s: {''.join(self.log)}")

    def exit_code(self, timeout: float = DEADLINE_S) -> int:
        """Wait for the exit; collect the rest of stderr and close the pipe."""
        code = self.process.wait(timeout)
        if self.process.stderr is not None and not self.process.stderr.closed:
            while (line := self.lines.get(timeout=DEADLINE_S)) is not None:
                self.log.append(line)
            release(self.process, self.reader)
        return code

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        return self.exit_code()


def _failure(started: Started) -> str:
    """The error the failed start ended on; nothing was said to be retried before it."""
    assert started.exit_code() == 1, started.log
    errors = [line for line in started.log if "ERROR" in line]
    assert not any("retrying" in line for line in errors[:-1]), started.log
    error = errors[-1]
    message = error.split("cannot start: ", 1)[1].strip()
    assert message.endswith("."), message  # a complete sentence
    return message


@pytest.fixture
def pty() -> Iterator[PtyPair]:
    with open_pty_pair() as pair:
        yield pair


def _config(tmp_path: Path, device: str, extra: str = "") -> str:
    path = tmp_path / "plant.toml"
    path.write_text(f'[server]\nlisten = "127.0.0.1:0"\n[metrics]\nlisten = "off"\n'
                    f'[lines.plant]\ndevice = "{device}"\nunits = [1]\n{extra}')  # fmt: skip
    return str(path)


def test_a_regular_file_is_not_a_serial_device(tmp_path: Path) -> None:
    file = tmp_path / "ttyUSB0"
    file.write_text("")
    flagged = _failure(Started("--serial", str(file), *QUIET))
    assert f"line 'default': {file} is not a serial device (not a terminal)" in flagged
    assert "set --serial to the adapter's device" in flagged
    from_file = _failure(Started("--config", _config(tmp_path, str(file))))
    assert "set lines.plant.device to the adapter's device" in from_file


def test_seven_data_bits_on_a_device_that_cannot(pty: PtyPair, tmp_path: Path) -> None:
    flagged = _failure(Started("--serial", pty.path, "--data-bits", "7", *QUIET))
    assert f"{pty.path} cannot set data_bits = 7 (Invalid argument)" in flagged
    assert "choose a value the adapter supports with --data-bits" in flagged
    from_file = _failure(Started("--config", _config(tmp_path, pty.path, "data_bits = 7\n")))
    assert "with lines.plant.data_bits" in from_file
    # ASCII's 7E1 default on a flag-only run: the fix is still a flag, never a file's key.
    framed = _failure(Started("--serial", pty.path, "--framing", "ascii", *QUIET))
    assert "with --data-bits" in framed


def test_a_device_not_plugged_in_yet_is_waited_for(tmp_path: Path) -> None:
    started = Started("--serial", str(tmp_path / "ttyUSB9"), *QUIET)
    try:
        started.wait_for(LISTENING.pattern)
    finally:
        assert started.stop() == 0


def _slave_listener(device: str, extra: str = "") -> str:
    """A ``serial-slave`` listener in the file, the first ``[[listeners]]`` entry."""
    return (f'[[listeners]]\nname = "panel"\nprotocol = "serial-slave"\n'
            f'device = "{device}"\n{extra}')  # fmt: skip


def test_a_regular_file_is_not_a_serial_slave_device(tmp_path: Path) -> None:
    """The serial-slave listener's device is checked as a line's is, in the user's terms."""
    file, missing = tmp_path / "ttyUSB1", str(tmp_path / "ttyUSB9")
    file.write_text("")
    flagged = _failure(Started("--serial", missing, "--serial-slave", str(file), *QUIET))
    assert f"listener 'serial-slave': {file} is not a serial device (not a terminal)" in flagged
    assert "set --serial-slave to the adapter's device" in flagged
    from_file = _failure(Started("--config", _config(tmp_path, missing,
                                                     _slave_listener(str(file)))))  # fmt: skip
    assert f"listener 'panel': {file} is not a serial device" in from_file
    assert "set listeners[0].device to the adapter's device" in from_file


def test_seven_data_bits_on_a_serial_slave_device_that_cannot(pty: PtyPair, tmp_path: Path) -> None:
    missing = str(tmp_path / "ttyUSB9")
    flagged = _failure(Started("--serial", missing, "--serial-slave", pty.path,
                               "--data-bits", "7", *QUIET))  # fmt: skip
    assert f"listener 'serial-slave': {pty.path} cannot set data_bits = 7" in flagged
    assert "choose a value the adapter supports with --data-bits" in flagged
    from_file = _failure(Started("--config", _config(
        tmp_path, missing, _slave_listener(pty.path, "data_bits = 7\n"))))  # fmt: skip
    assert "with listeners[0].data_bits" in from_file


def test_a_serial_slave_device_not_plugged_in_yet_is_waited_for(tmp_path: Path) -> None:
    started = Started("--serial", str(tmp_path / "ttyUSB9"),
                      "--serial-slave", str(tmp_path / "ttyUSB8"), *QUIET)  # fmt: skip
    try:
        started.wait_for(r"listener serial-slave: .*ttyUSB8.*; retrying")
        started.wait_for(LISTENING.pattern)
    finally:
        assert started.stop() == 0


def _as_nobody() -> tuple[str, ...]:
    """Run as ``nobody`` when root (root opens any device node whatever its mode)."""
    if os.geteuid() != 0:
        return ()
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("setpriv (util-linux) is needed to drop root for a permission test")
    return (setpriv, "--reuid=65534", "--regid=65534", "--clear-groups")


def test_permission_denied_is_waited_for_then_fails(pty: PtyPair) -> None:
    os.chmod(pty.path, 0o000 if os.geteuid() else 0o600)
    started = Started("--serial", pty.path, *QUIET, prefix=_as_nobody())
    started.wait_for(r"permission denied opening .*; trying again")
    message = _failure(started)
    assert f"permission denied opening {pty.path} (still after {PERMISSION_SETTLE_S:g} s)" in (
        message
    )
    assert "usermod -aG dialout USER" in message and "set --serial to a device" in message


def test_permission_granted_while_waiting_starts(pty: PtyPair) -> None:
    """udev sets the mode a moment after the device appears: the start goes on."""
    os.chmod(pty.path, 0o000 if os.geteuid() else 0o600)
    started = Started("--serial", pty.path, *QUIET, prefix=_as_nobody())
    try:
        started.wait_for(r"permission denied opening .*; trying again")
        os.chmod(pty.path, 0o666)
        started.wait_for(LISTENING.pattern)
    finally:
        assert started.stop() == 0


def test_metrics_port_in_use_is_one_sentence(tmp_path: Path) -> None:
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        started = Started("--serial", str(tmp_path / "ttyUSB9"), "--listen", "127.0.0.1:0",
                          "--metrics", f"127.0.0.1:{port}")  # fmt: skip
        assert started.exit_code() == 1
        message = started.log[-1].split("cannot start: ", 1)[1].strip()
    assert message.endswith(
        "stop it, or choose another port with metrics.listen (or --metrics)."
    ), message


def test_an_ipv6_metrics_address_is_logged_as_a_url(tmp_path: Path) -> None:
    try:
        socket.create_server(("::1", 0), family=socket.AF_INET6).close()
    except OSError:
        pytest.skip("no IPv6 loopback here")
    started = Started("--serial", str(tmp_path / "ttyUSB9"), "--listen", "127.0.0.1:0",
                      "--metrics", "[::1]:0")  # fmt: skip
    try:
        match = started.wait_for(r"metrics on (\S+), status page on (\S+)")
    finally:
        assert started.stop() == 0
    assert re.fullmatch(r"http://\[::1\]:\d+/metrics", match[1]), match[0]
    assert match[2] == match[1].removesuffix("metrics")


def test_the_demo_names_its_status_page() -> None:
    started = Started("--demo", "--listen", "127.0.0.1:0", "--metrics", "127.0.0.1:0")
    try:
        match = started.wait_for(r"status page on (http://127\.0\.0\.1:(\d+)/)$")
        page = urllib.request.urlopen(match[1], timeout=DEADLINE_S)
        assert page.status == 200 and "text/html" in page.headers["Content-Type"]
    finally:
        assert started.stop() == 0


def test_trace_help_describes_the_trace_subcommand() -> None:
    shown = subprocess.run(
        [sys.executable, "-m", "gateway", "trace", "--help"], env=dict(os.environ,
        PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=DEADLINE_S, check=False,
    )  # fmt: skip
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.startswith("usage: modbus-gateway trace ")
    assert "--url http://HOST:PORT" in shown.stdout and "--serial" not in shown.stdout
