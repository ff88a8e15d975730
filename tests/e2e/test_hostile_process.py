"""Memory and descriptors of the gateway process (the real CLI) while attackers work on it.

The attacks are those of ``tests/integration/test_hostile.py``, bounded in time
(a few seconds each); here the gateway runs as ``python -m gateway`` in a
subprocess so that its resident set and open descriptors are its own, read from
``/proc/PID``. An honest master polls throughout and must stay served.
"""

from __future__ import annotations

import os
import re
import select
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.sim import plc
from tests.e2e.test_cli import GatewayProcess
from tests.helpers import DEADLINE_S, RawClient, SimFactory, mbap

READ_1 = bytes.fromhex("03 0000 0001")
ATTACKER = "127.0.0.2"
METRICS = re.compile(r"metrics on http://([0-9.]+):(\d+)/metrics")
#: The issue's bound on the growth of the gateway's resident set under a flood.
RSS_GROWTH_LIMIT_KIB = 20 * 1024


def rss_kib(pid: int) -> int:
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise AssertionError("no VmRSS")


def open_fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def connect_from(source: str, address: tuple[str, int]) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind((source, 0))
    sock.settimeout(DEADLINE_S)
    sock.connect(address)
    return sock


def closed_by_peer(socks: list[socket.socket], enough: int) -> int:
    """Wait (within the deadline) until the other end has closed ``enough`` of ``socks``;
    return how many it closed."""
    pending = set(socks)
    closed = 0
    for _ in until(DEADLINE_S):
        if closed >= enough:
            break
        readable, _, _ = select.select(list(pending), [], [], 0.05)
        for sock in readable:
            try:
                data = sock.recv(4096, socket.MSG_DONTWAIT)
            except BlockingIOError:
                continue
            except OSError:  # reset: aborted by the gateway
                data = b""
            if not data:
                pending.discard(sock)
                closed += 1
    return closed


def until(seconds: float) -> Iterator[None]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        yield


class Honest:
    """Polls unit 1 in a thread; every reply must come, and be right."""

    def __init__(self, address: tuple[str, int]) -> None:
        self.client = RawClient(address)
        self.polls = 0
        self.errors: list[BaseException] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        try:
            while not self.stop.is_set():
                assert self.client.request(1, READ_1)[0] == 0x03
                self.polls += 1
        except BaseException as error:  # reported by finish()
            self.errors.append(error)

    def finish(self) -> None:
        self.stop.set()
        self.thread.join(DEADLINE_S)
        self.client.close()
        assert not self.errors, self.errors
        assert self.polls >= 10


@pytest.fixture
def gateway(tmp_path: Path, make_sim: SimFactory) -> Iterator[GatewayProcess]:
    sim = make_sim({1: plc(1)})
    config = tmp_path / "gateway.toml"
    config.write_text(
        f"""
[server]
listen = "127.0.0.1:0"
send_timeout = 1.0

[metrics]
listen = "127.0.0.1:0"
max_connections = 8
header_timeout = 1.0

[lines.a]
device = "{sim.path}"
baudrate = 115200
units = [1]
"""
    )
    process = GatewayProcess("--config", str(config))
    try:
        yield process
        assert process.terminate() == 0
    finally:
        process.kill()


def test_floods_and_broken_connections_leave_memory_and_descriptors_bounded(
    gateway: GatewayProcess,
) -> None:
    address = gateway.address()
    pid = gateway.process.pid
    honest = Honest(address)
    while honest.polls < 3 and not honest.errors:  # the honest master is connected
        select.select([], [], [], 0.01)
    fds, rss = open_fds(pid), rss_kib(pid)
    peak = rss
    # 1. A flood of requests the gateway answers itself (unit 99 has no route), never read.
    flood = b"".join(mbap(tid, 99, READ_1) for tid in range(4096))
    attacker = connect_from(ATTACKER, address)
    attacker.setblocking(False)
    closed = False
    for _ in until(4.0):
        try:
            attacker.send(flood)
        except BlockingIOError:
            select.select([], [attacker], [], 0.05)
            peak = max(peak, rss_kib(pid))
        except OSError:  # closed after send_timeout of unread replies
            closed = True
            break
    attacker.close()
    assert closed, "a master that reads none of its replies was kept"
    # 2. Connections with unsent replies, closed for a broken header, held open by the client.
    broken = b"".join(mbap(tid, 99, READ_1) for tid in range(2000)) + mbap(1, 1, READ_1, 9)
    held = [connect_from(ATTACKER, address) for _ in range(3)]
    for sock in held:
        sock.sendall(broken)
    try:
        for _ in until(DEADLINE_S):  # the gateway frees their descriptors at once
            if open_fds(pid) <= fds:
                break
            select.select([], [], [], 0.02)
        assert open_fds(pid) <= fds
    finally:
        for sock in held:
            sock.close()
    peak = max(peak, rss_kib(pid))
    honest.finish()
    assert peak - rss <= RSS_GROWTH_LIMIT_KIB, f"RSS grew by {(peak - rss) / 1024:.1f} MB"


def test_idle_http_connections_cost_at_most_the_cap_in_descriptors(
    gateway: GatewayProcess,
) -> None:
    address = gateway.address()
    match = gateway.wait_for(METRICS)
    metrics = (match.group(1), int(match.group(2)))
    pid = gateway.process.pid
    fds = open_fds(pid)
    idle = []
    try:
        for _ in range(200):
            try:
                idle.append(connect_from(ATTACKER, metrics))
            except OSError:  # the kernel's accept queue is full: also a refusal
                break
        # The cap (8), once the connections being turned away have been closed: those past
        # it are accepted and aborted at once, whatever the client does with its end. A
        # client sees its end closed only once the gateway's descriptor is gone, so when all
        # but 8 have been closed no more than 8 descriptors can remain, whatever is still
        # in the kernel's accept queue (counting before that races the accepts under way).
        closed = closed_by_peer(idle, len(idle) - 8)
        assert closed >= len(idle) - 8, f"only {closed} of {len(idle)} connections closed"
        now_open = open_fds(pid)
        assert now_open <= fds + 8, f"{now_open} descriptors, {fds} before"
        with RawClient(address) as master:  # Modbus masters are not locked out
            assert master.request(1, READ_1)[0] == 0x03
        with socket.create_connection(metrics, timeout=DEADLINE_S) as scrape:
            scrape.sendall(b"GET /healthz HTTP/1.0\r\n\r\n")
            assert scrape.recv(64).startswith(b"HTTP/1.1 200")
    finally:
        for sock in idle:
            sock.close()
