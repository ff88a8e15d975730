"""systemd Type=notify readiness and watchdog, against a real datagram socket and the real CLI.

The test plays systemd's part: it binds an AF_UNIX datagram socket, passes it as
``$NOTIFY_SOCKET`` (a path, and the abstract ``@name`` form) with a short
``$WATCHDOG_USEC``, and reads what ``python -m gateway --config FILE`` sends:
READY=1 only when a master can already be served, WATCHDOG=1 at half the
period, RELOADING=1 then READY=1 around a SIGHUP reload, STOPPING=1 on SIGTERM.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.io.systemd import SystemdNotifier
from gateway.sim import plc
from tests.helpers import DEADLINE_S, UNPACED_BAUDRATE, RawClient, SimFactory

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="needs AF_UNIX and ptys")

READ_2 = bytes([0x03, 0x00, 0x00, 0x00, 0x02])
WATCHDOG_USEC = 200_000  # pings every 0.1 s


class FakeSystemd:
    """The receiving end of sd_notify: one datagram per notification, fields by line."""

    def __init__(self, address: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        bind = "\0" + address[1:] if address.startswith("@") else address
        self.sock.bind(bind)
        self.address = address
        self.watchdog_pings = 0

    def next(self, timeout: float = DEADLINE_S) -> dict[str, str]:
        """The next notification other than a watchdog ping (those are counted)."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError("no notification in time")
            self.sock.settimeout(remaining)
            fields = dict(line.split("=", 1) for line in self.sock.recv(4096).decode().splitlines())
            if fields == {"WATCHDOG": "1"}:
                self.watchdog_pings += 1
                continue
            return fields

    def wait_for_pings(self, count: int, timeout: float = DEADLINE_S) -> None:
        """Wait until ``count`` more watchdog pings arrived."""
        target = self.watchdog_pings + count
        deadline = time.monotonic() + timeout
        while self.watchdog_pings < target:
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"only {self.watchdog_pings} watchdog pings"
            self.sock.settimeout(remaining)
            message = self.sock.recv(4096).decode()
            assert message == "WATCHDOG=1", message
            self.watchdog_pings += 1

    def close(self) -> None:
        self.sock.close()


@pytest.fixture(params=["path", "abstract"])
def systemd(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[FakeSystemd]:
    if request.param == "path":
        address = str(tmp_path / "notify")
    else:
        address = f"@modbus-gateway-test-{os.getpid()}-{time.monotonic_ns()}"
    fake = FakeSystemd(address)
    yield fake
    fake.close()


def test_ready_watchdog_reload_and_stop(
    systemd: FakeSystemd, make_sim: SimFactory, tmp_path: Path
) -> None:
    sim = make_sim({1: plc(1)})
    config = tmp_path / "plant.toml"
    config.write_text(
        f'[lines.a]\ndevice = "{sim.path}"\nbaudrate = {UNPACED_BAUDRATE}\nunits = [1]\n'
    )
    env = dict(os.environ, NOTIFY_SOCKET=systemd.address, WATCHDOG_USEC=str(WATCHDOG_USEC))
    env.pop("WATCHDOG_PID", None)
    log = (tmp_path / "gateway.log").open("w")
    gateway = subprocess.Popen(
        [sys.executable, "-m", "gateway", "--config", str(config),
         "--listen", "127.0.0.1:0", "--metrics", "off"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log, env=env,
    )  # fmt: skip
    try:
        ready = systemd.next()
        assert ready["READY"] == "1", ready
        assert ready["MAINPID"] == str(gateway.pid)
        match = re.fullmatch(r"listening on 127\.0\.0\.1:(\d+), 1 line\(s\)", ready["STATUS"])
        assert match, ready
        with RawClient(("127.0.0.1", int(match[1]))) as client:  # READY=1 means it serves
            assert client.request(1, READ_2)[:2] == bytes([0x03, 4])

        systemd.wait_for_pings(3)  # 0.1 s apart: a deadline of seconds is ample

        gateway.send_signal(signal.SIGHUP)
        reloading = systemd.next()
        assert reloading["RELOADING"] == "1", reloading
        assert int(reloading["MONOTONIC_USEC"]) > 0
        again = systemd.next()
        assert again["READY"] == "1" and again["STATUS"].startswith("listening on"), again

        gateway.send_signal(signal.SIGTERM)
        stopping = systemd.next()
        assert stopping["STOPPING"] == "1", stopping
        assert gateway.wait(DEADLINE_S) == 0
    finally:
        if gateway.poll() is None:
            gateway.kill()
            gateway.wait(DEADLINE_S)
        log.close()


def test_a_start_that_fails_never_says_ready(systemd: FakeSystemd, tmp_path: Path) -> None:
    """A refused start exits 1 without READY=1, so systemd marks the unit failed."""
    env = dict(os.environ, NOTIFY_SOCKET=systemd.address)
    done = subprocess.run(
        [sys.executable, "-m", "gateway", "--serial", "/dev/null", "--listen", "300.1.1.1:5020",
         "--metrics", "off"],
        capture_output=True, text=True, env=env, timeout=DEADLINE_S * 3, check=False,
    )  # fmt: skip
    assert done.returncode != 0, done
    systemd.sock.settimeout(0)
    with pytest.raises(BlockingIOError):
        systemd.sock.recv(4096)


def test_the_notifier_is_silent_outside_systemd_and_for_another_pid() -> None:
    assert not SystemdNotifier({}).enabled
    assert not SystemdNotifier({"NOTIFY_SOCKET": "relative/path"}).enabled
    for_us = SystemdNotifier({"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "2000000"})
    assert for_us.enabled and for_us.watchdog_interval == 2.0
    for_someone_else = SystemdNotifier(
        {"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}
    )
    assert for_someone_else.watchdog_interval is None
    for notifier in (for_us, for_someone_else):
        notifier.close()
