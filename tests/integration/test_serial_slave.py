"""The ``serial-slave`` listener: RTU masters on a serial line of the gateway's reach its routes.

The master's line is a real pty: a raw master in the test writes requests on
its end and checks the silence rules byte for byte (no answer for other units,
bad CRCs or broadcasts; nothing before t3.5), and mbpoll in RTU mode is the
independent master on a socat pty pair. Behind the gateway the slaves are the
simulated RTU line, as everywhere else.
"""

from __future__ import annotations

import os
import re
import select
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gateway.core.crc import append_crc, check_crc
from gateway.core.timing import t35
from gateway.sim import open_pty_pair, plc, zl69x
from gateway.sim.device import pack_registers
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    RunningGateway,
    SimBus,
    SimFactory,
    h,
    require_tool,
)
from tests.integration.test_sim import FUNCTION_VECTORS

BAUD = 19200
T35 = t35(BAUD)


class RtuMaster:
    """The master end of the gateway's slave-side pty: RTU frames out, whole frames in."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def send(self, unit: int, pdu: bytes, crc_ok: bool = True) -> float:
        frame = append_crc(bytes((unit,)) + pdu)
        if not crc_ok:
            frame = frame[:-1] + bytes((frame[-1] ^ 0xFF,))
        os.write(self.fd, frame)
        return time.monotonic()

    def receive(self, length: int, timeout: float = DEADLINE_S) -> bytes:
        deadline = time.monotonic() + timeout
        data = b""
        while len(data) < length:
            left = deadline - time.monotonic()
            assert left > 0, f"no whole answer: {data.hex(' ')}"
            readable, _, _ = select.select([self.fd], [], [], left)
            if readable:
                data += os.read(self.fd, length - len(data))
        assert check_crc(data), data.hex(" ")
        return data[:-2]

    def silent_for(self, seconds: float) -> None:
        """Assert that nothing comes back for ``seconds`` (which also ends the frame sent)."""
        readable, _, _ = select.select([self.fd], [], [], seconds)
        assert not readable, f"unexpected answer: {os.read(self.fd, 512).hex(' ')}"

    def request(self, unit: int, pdu: bytes, reply_pdu_length: int) -> bytes:
        self.send(unit, pdu)
        reply = self.receive(reply_pdu_length + 3)
        assert reply[0] == unit, reply.hex(" ")
        return reply[1:]


Setup = tuple[SimBus, RunningGateway, RtuMaster]


@pytest.fixture
def reverse(make_sim: SimFactory, make_gateway: GatewayFactory) -> Iterator[Any]:
    """``reverse(devices=None, **listener)``: a PLC (1) and ZL-69X (2), or ``devices``, on
    line a, and a serial-slave listener."""
    pairs = []

    def factory(devices: dict[int, Any] | None = None, **listener: Any) -> Setup:
        sim = make_sim(devices if devices is not None else {1: plc(1), 2: zl69x(2)})
        pair = open_pty_pair()
        pairs.append(pair)
        entry = {"name": "field", "protocol": "serial-slave", "device": pair.path,
                 "baudrate": BAUD, **listener}  # fmt: skip
        units = sorted(devices) if devices is not None else [1, 2]
        gateway = make_gateway({"lines": {"a": sim.line_table(units)}, "listeners": [entry]})
        slave = next(s for s in gateway.gateway.serial_slaves if s.name == "field")
        deadline = time.monotonic() + DEADLINE_S
        while not gateway.call(lambda: slave.up):
            assert time.monotonic() < deadline
            time.sleep(0.01)
        return sim, gateway, RtuMaster(pair.sim_fd)

    yield factory
    for pair in pairs:
        pair.close()


def test_masters_on_the_serial_line_reach_the_routed_slaves(reverse: Any) -> None:
    sim, gateway, master = reverse()
    assert master.request(1, h("03 0000 000A"), 22) == h("03 14") + pack_registers(
        [0, 2, 4, 6, 8, 10, 0, 0, 0, 0]
    )
    assert master.request(1, h("10 0BB8 0002 04 1234 5678"), 5) == h("10 0BB8 0002")
    assert sim.device(1).holding.read(3000, 2) == [0x1234, 0x5678]
    assert master.request(2, h("03 0000 0002"), 6) == h("03 04 0113 FF9D")
    assert master.request(1, h("08 0000 A537"), 5) == h("08 0000 A537")
    assert master.request(1, h("03 FFFF 0002"), 2) == h("83 02")  # the device's exception
    # The Modbus TCP side still serves the same slaves.
    with gateway.connect() as client:
        assert client.request(1, h("03 0BB8 0002")) == h("03 04 1234 5678")


def test_silence_for_other_units_bad_crcs_broadcasts_and_answers_of_other_slaves(
    reverse: Any,
) -> None:
    sim, gateway, master = reverse()
    quiet = 0.1  # far longer than t3.5 and than the simulated line's answer
    master.send(9, h("03 0000 0001"))  # not routed: another slave on this line may answer
    master.silent_for(quiet)
    master.send(1, h("03 0000 0001"), crc_ok=False)
    master.silent_for(quiet)
    master.send(0, h("06 0007 0077"))  # broadcast: executed, never answered
    master.silent_for(quiet)
    # A frame shaped like another slave's answer to unit 1 (03, byte count): not a request.
    os.write(master.fd, append_crc(h("01 03 02 0000")))
    master.silent_for(quiet)
    # Two requests with no gap between them are one garbled frame: silence too.
    os.write(master.fd, append_crc(h("01 03 0000 0001")) + append_crc(h("01 03 0000 0001")))
    master.silent_for(quiet)
    assert master.request(1, h("03 0007 0001"), 4) == h("03 02 0077")
    assert sim.stats().broadcasts == 1
    # Counted as on every listener (``spine.broadcast``): once, under line "broadcast".
    labels = {"line": "broadcast", "unit": "0", "function": "write_single_register"}
    registry = gateway.gateway.metrics.registry
    sent = gateway.call(
        lambda: registry.get_sample_value(
            "modbus_gateway_requests_total", {**labels, "outcome": "broadcast"}
        )
    )
    assert sent == 1


def test_a_babbling_line_is_bounded_and_the_next_request_is_answered(reverse: Any) -> None:
    _, gateway, master = reverse()
    for _ in range(6):  # 600 bytes of noise without a gap: more than two RTU frames
        os.write(master.fd, bytes(range(100)))
    master.silent_for(0.1)
    assert master.request(1, h("03 0000 0001"), 4) == h("03 02 0000")
    slave = gateway.gateway.serial_slaves[0]
    assert gateway.call(lambda: slave.ignored) >= 1


def test_the_answer_waits_for_t35_after_the_request(reverse: Any) -> None:
    _, _, master = reverse()
    for _ in range(5):
        sent = master.send(1, h("03 0000 0001"))
        master.receive(7)
        assert time.monotonic() - sent >= T35


def test_units_limit_which_slaves_the_gateway_stands_for(reverse: Any) -> None:
    _, _, master = reverse(units=[2])
    master.send(1, h("03 0000 0001"))  # routed, but not listed for this listener: silence
    master.silent_for(0.1)
    assert master.request(2, h("03 0000 0001"), 4) == h("03 02 0113")


def test_read_only_listener_refuses_writes(reverse: Any) -> None:
    sim, _, master = reverse(read_only=True)
    assert master.request(1, h("06 0000 0001"), 2) == h("86 01")
    assert sim.device(1).holding[0] == 0
    assert master.request(1, h("03 0000 0001"), 4) == h("03 02 0000")


# --------------------------------------------------------------------------- mbpoll as master


@pytest.fixture
def socat_ptys(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """Two linked pty paths (a null-modem cable) made by socat."""
    socat = require_tool("socat")
    left, right = tmp_path / "gateway", tmp_path / "master"
    process = subprocess.Popen(
        [socat, "-d", "-d", f"pty,raw,echo=0,link={left}", f"pty,raw,echo=0,link={right}"],
        stderr=subprocess.PIPE,
    )
    assert process.stderr is not None
    seen = b""
    deadline = time.monotonic() + DEADLINE_S
    while b"starting data transfer loop" not in seen:
        assert time.monotonic() < deadline, seen
        readable, _, _ = select.select([process.stderr], [], [], 0.5)
        if readable:
            chunk = os.read(process.stderr.fileno(), 4096)
            assert chunk, seen
            seen += chunk
    try:
        yield str(left), str(right)
    finally:
        process.kill()
        process.wait(DEADLINE_S)
        process.stderr.close()


def mbpoll(*args: Any) -> str:
    tool = require_tool("mbpoll")
    done = subprocess.run(
        [tool, *map(str, args)], capture_output=True, text=True, timeout=30, check=False
    )
    assert done.returncode == 0, f"mbpoll failed ({done.returncode}): {done.stdout}{done.stderr}"
    return done.stdout


def values(output: str) -> dict[int, int]:
    return {
        int(ref): int(value) for ref, value in re.findall(r"^\[(\d+)\]:\s+(-?\d+)", output, re.M)
    }


def test_mbpoll_as_rtu_master_in_reverse_mode(
    make_sim: SimFactory, make_gateway: GatewayFactory, socat_ptys: tuple[str, str]
) -> None:
    require_tool("mbpoll")
    gateway_end, master_end = socat_ptys
    sim = make_sim({1: plc(1), 2: zl69x(2)})
    entry = {"name": "field", "protocol": "serial-slave", "device": gateway_end, "baudrate": BAUD}
    gateway = make_gateway({"lines": {"a": sim.line_table([1, 2])}, "listeners": [entry]})
    slave = gateway.gateway.serial_slaves[0]
    deadline = time.monotonic() + DEADLINE_S
    while not gateway.call(lambda: slave.up):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    common = ("-m", "rtu", "-b", BAUD, "-P", "none", "-d", 8, "-s", 1, "-o", 2)
    out = mbpoll(*common, "-a", 1, "-r", 1001, "-c", 5, "-t", 4, "-1", master_end)
    assert values(out) == {1001 + i: 1000 + i for i in range(5)}
    out = mbpoll(*common, "-a", 2, "-r", 1, "-c", 2, "-t", 4, "-1", master_end)
    assert values(out) == {1: 275, 2: 0xFF9D}
    mbpoll(*common, "-a", 1, "-r", 501, "-t", 4, master_end, 11, 22, 33)
    assert sim.device(1).holding.read(500, 3) == [11, 22, 33]
    mbpoll(*common, "-a", 1, "-r", 41, "-t", 0, master_end, 1)
    assert sim.device(1).coils[40] == 1


def test_every_function_code_through_an_rtu_serial_slave(reverse: Any) -> None:
    """The simulator's vectors, each to a fresh device (its own unit), answered byte-exact."""
    units = range(1, len(FUNCTION_VECTORS) + 1)
    _, _, master = reverse(devices={unit: plc(unit) for unit in units})
    for unit, (request_hex, response_hex) in zip(units, FUNCTION_VECTORS, strict=True):
        answer = master.request(unit, h(request_hex), len(h(response_hex)))
        assert answer == h(response_hex), request_hex
