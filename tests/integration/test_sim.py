"""The simulated RTU bus, driven over a real pty with raw bytes, and cross-checked by pymodbus.

Synchronisation is by data: a request whose answer must not come is followed
by one whose answer must, and the simulator serves frames in order, so the
first bytes read tell whether anything was sent in between.
"""

from __future__ import annotations

import json
import os
import select
import signal
import statistics
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest

from gateway.core.crc import check_crc
from gateway.core.rtu import NEED_MORE, encode_rtu, response_length
from gateway.core.timing import character_time, t35
from gateway.sim import (
    PROFILES,
    DataBank,
    SimulatedDevice,
    SimulatedLine,
    open_pty_pair,
    plc,
    power_controller,
    zl69x,
)
from tests.helpers import h

REPO = Path(__file__).resolve().parents[2]
TIMEOUT_S = 2.0


def read_exactly(fd: int, count: int, timeout: float = TIMEOUT_S) -> bytes:
    """Wait for exactly ``count`` bytes (select with a deadline, never a sleep)."""
    data = bytearray()
    deadline = time.monotonic() + timeout
    while len(data) < count:
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"timed out with {data.hex(' ')!r} of {count} bytes"
        if select.select([fd], [], [], remaining)[0]:
            data += os.read(fd, count - len(data))
    return bytes(data)


class Bus:
    """The master's end of a pty whose other end a ``SimulatedLine`` serves."""

    def __init__(self, fd: int, line: SimulatedLine, sim_fd: int) -> None:
        self.fd = fd
        self.line = line
        self.sim_fd = sim_fd  # the simulator's end, for measuring the pty itself

    def send(self, frame: bytes) -> float:
        """Write a raw frame; return the instant just before the write."""
        now = time.perf_counter()
        os.write(self.fd, frame)
        return now

    def read_exactly(self, count: int, timeout: float = TIMEOUT_S) -> bytes:
        return read_exactly(self.fd, count, timeout)

    def read_response(self, request_pdu: bytes, timeout: float = TIMEOUT_S) -> bytes:
        """Read one response frame, its length told by the core's length prediction."""
        data = bytearray(self.read_exactly(2, timeout))
        while True:
            expected = response_length(request_pdu, data)
            assert expected is not None, "test requests must have a predictable response length"
            if expected != NEED_MORE and len(data) >= expected:
                return bytes(data)
            missing = expected - len(data) if expected != NEED_MORE else 1
            data += self.read_exactly(missing, timeout)

    def transact(self, unit: int, pdu: bytes) -> bytes:
        """Send a request; return the whole response frame."""
        self.send(encode_rtu(unit, pdu))
        return self.read_response(pdu)


BusFactory = Callable[..., Bus]


@pytest.fixture
def make_bus() -> Iterator[BusFactory]:
    """Build pty + line + master fd; everything is stopped and closed at teardown."""
    with ExitStack() as stack:

        def factory(devices: Mapping[int, SimulatedDevice], **options: Any) -> Bus:
            pair = open_pty_pair()
            stack.callback(pair.close)
            fd = os.open(pair.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            stack.callback(os.close, fd)
            tty.setraw(fd)
            line = SimulatedLine(pair.sim_fd, devices, **options)
            line.start()
            stack.callback(line.stop)
            return Bus(fd, line, pair.sim_fd)

        yield factory


def wait_until(deadline: float) -> None:
    """Pace the master like a real one (t3.5 between frames); not a synchronisation."""
    while (remaining := deadline - time.perf_counter()) > 0:
        time.sleep(remaining / 2 if remaining > 0.001 else 0)


# --------------------------------------------------------------------------- reference vectors


def test_plc_answers_the_manuals_rtu_example_byte_for_byte(make_bus: BusFactory) -> None:
    bus = make_bus({1: plc(1)})
    bus.send(h("01 03 00 00 00 0A C5 CD"))
    # The manual prints one stray 00 too many; with 20 data bytes the CRC 5B 02 checks.
    expected = h("01 03 14 00 00 00 02 00 04 00 06 00 08 00 0A 00 00 00 00 00 00 00 00 5B 02")
    assert bus.read_exactly(len(expected)) == expected


def test_power_controller_answers_its_sheets_example(make_bus: BusFactory) -> None:
    bus = make_bus({1: power_controller(1)})
    bus.send(h("01 03 00 03 00 03 F5 CB"))
    expected = h("01 03 06 00 00 00 B7 00 00 91 53")
    assert bus.read_exactly(len(expected)) == expected


# Every function code on the PLC profile, mostly the Modbus specification's own examples.
FUNCTION_VECTORS = [
    ("01 0013 0013", "01 03 CD6B05"),
    ("02 00C4 0016", "02 03 ACDB35"),
    ("03 0000 0003", "03 06 0000 0002 0004"),
    ("04 0008 0001", "04 02 000A"),
    ("05 00AC FF00", "05 00AC FF00"),
    ("06 0001 0003", "06 0001 0003"),
    ("07", "07 6D"),
    ("08 0000 A537", "08 0000 A537"),
    ("08 0001 0000", "08 0001 0000"),
    ("08 000E 0000", "08 000E 0001"),
    ("0B", "0B 0000 0000"),
    ("0C", "0C 07 0000 0000 0001 80"),
    ("0F 0013 000A 02 CD01", "0F 0013 000A"),
    ("10 0001 0002 04 000A 0102", "10 0001 0002"),
    ("11", "11 06 5A51363030 FF"),
    ("14 0E 06 0004 0001 0002 06 0003 0009 0002", "14 0C 05 06 0DFE 0020 05 06 33CD 0040"),
    ("15 0D 06 0004 0007 0003 06AF 04BE 100D", "15 0D 06 0004 0007 0003 06AF 04BE 100D"),
    ("16 0004 00F2 0025", "16 0004 00F2 0025"),
    ("17 0003 0006 000E 0003 06 00FF 00FF 00FF", "17 0C 0006 0008 000A 0000 0000 0000"),
    ("18 04DE", "18 0006 0002 01B8 1284"),
    (
        "2B 0E 01 00",
        "2B 0E 01 81 00 00 03 00 0E"
        + b"Nietz Electric".hex()
        + "01 05"
        + b"ZQ600".hex()
        + "02 08"
        + b"V1.0.1.1".hex(),
    ),
    ("2B 0E 04 01", "2B 0E 04 81 00 00 01 01 05" + b"ZQ600".hex()),
]


@pytest.mark.parametrize(("request_hex", "response_hex"), FUNCTION_VECTORS)
def test_every_function_code(make_bus: BusFactory, request_hex: str, response_hex: str) -> None:
    bus = make_bus({7: plc(7)})
    assert bus.transact(7, h(request_hex)) == encode_rtu(7, h(response_hex))


def test_writes_reach_the_tables_and_tables_are_settable(make_bus: BusFactory) -> None:
    device = plc(1)
    bus = make_bus({1: device})
    device.holding[20] = 0xBEEF
    assert bus.transact(1, h("03 0014 0001")) == encode_rtu(1, h("03 02 BEEF"))
    bus.transact(1, h("10 0002 0003 06 1122 3344 5566"))
    assert [device.holding[a] for a in (2, 3, 4)] == [0x1122, 0x3344, 0x5566]
    bus.transact(1, h("0F 0006 0009 02 1101"))
    assert [device.coils[a] for a in range(6, 15)] == [1, 0, 0, 0, 1, 0, 0, 0, 1]
    bus.transact(1, h("16 0004 00F2 0025"))  # (0x5566 AND 0xF2) OR (0x25 AND NOT 0xF2)
    assert device.holding[4] == (0x5566 & 0xF2) | (0x25 & 0x0D)
    bus.transact(1, h("15 0D 06 0004 0007 0003 06AF 04BE 100D"))
    assert device.files[4][7:10] == [0x06AF, 0x04BE, 0x100D]
    with pytest.raises(IndexError):
        device.holding[10000] = 1
    with pytest.raises(ValueError, match="outside"):
        device.coils[0] = 2


EXCEPTION_VECTORS = [
    (1, "41", "C1 01"),  # unknown function
    (1, "03 270F 0002", "83 02"),  # 9999..10000 passes the end of the map
    (1, "03 0000 007E", "83 03"),  # 126 registers
    (1, "05 0000 1234", "85 03"),  # coil value neither FF00 nor 0000
    (1, "14 07 06 0009 0000 0001", "94 02"),  # no file 9
    (1, "18 0001", "98 02"),  # no FIFO there
    (1, "2B 0E 04 05", "AB 02"),  # no object 5
    (1, "2B 0D 00", "AB 01"),  # MEI type other than 14
    (2, "02 0000 0001", "82 01"),  # the ZL-69X knows FC 1, 3, 6, 16, 43 only
    (2, "05 0000 FF00", "85 01"),
    (2, "03 0000 0031", "83 03"),  # reads at most 48 registers
    (2, "01 0000 0021", "81 03"),  # reads at most 32 coils
    (2, "03 002F 0002", "83 02"),  # 47..48: past the map
    (2, "06 0000 0001", "86 04"),  # room temperature is read-only
    (2, "2B 0E 04 00", "AB 03"),  # stream access only (conformity level 0x01)
    (2, "2B 0E 02 00", "AB 03"),  # only the basic category
    (3, "03 0000 0006", "83 03"),  # the power controller caps reads at 5
    (3, "01 0000 0001", "81 01"),
]


@pytest.mark.parametrize(("unit", "request_hex", "response_hex"), EXCEPTION_VECTORS)
def test_exception_responses(
    make_bus: BusFactory, unit: int, request_hex: str, response_hex: str
) -> None:
    bus = make_bus({1: plc(1), 2: zl69x(2), 3: power_controller(3)})
    assert bus.transact(unit, h(request_hex)) == encode_rtu(unit, h(response_hex))


def test_profiles_readable_at_their_limits(make_bus: BusFactory) -> None:
    bus = make_bus({1: plc(1), 2: zl69x(2), 3: power_controller(3)})
    zl = bus.transact(2, h("03 0000 0030"))
    assert zl[2] == 96 and zl[3:7] == h("0113 FF9D")  # 27.5 C and -9.9 C, as the document shows
    assert bus.transact(2, h("06 0008 00FA")) == encode_rtu(2, h("06 0008 00FA"))
    assert bus.transact(3, h("04 0003 0005"))[2] == 10
    assert bus.transact(1, h("03 2690 007D"))[3:5] == (0x2690).to_bytes(2, "big")
    assert set(PROFILES) == {"plc", "zl69x", "power_controller", "r6"}


# --------------------------------------------------------------------------- line behaviour


def test_dropped_frames_are_silent_and_counted(make_bus: BusFactory) -> None:
    bus = make_bus({1: plc(1), 2: plc(2)})
    read = h("03 0000 0001")
    bus.line.faults(1).silent = True
    bus.send(encode_rtu(1, read))  # silent unit
    bus.send(encode_rtu(9, read))  # a unit the line does not have
    bus.send(encode_rtu(2, read)[:-1] + b"\x00")  # bad CRC
    # Nothing came back before the answer to the next request:
    assert bus.transact(2, read) == encode_rtu(2, h("03 02 0000"))
    stats = bus.line.stats()
    assert (stats.silent_drops, stats.foreign_frames, stats.crc_errors_in) == (1, 1, 1)
    assert (stats.requests, stats.responses) == (3, 1)


def test_broadcast_runs_on_every_device_and_is_never_answered(make_bus: BusFactory) -> None:
    first, second = plc(1), plc(2)
    bus = make_bus({1: first, 2: second})
    bus.send(encode_rtu(0, h("06 0007 1234")))
    assert bus.transact(2, h("03 0007 0001")) == encode_rtu(2, h("03 02 1234"))
    assert first.holding[7] == second.holding[7] == 0x1234
    assert bus.line.stats().broadcasts == 1


def test_crc_fault_injection_is_deterministic(make_bus: BusFactory) -> None:
    read = h("03 0000 0001")

    def pattern(seed: int) -> list[bool]:
        bus = make_bus({1: plc(1)}, seed=seed)
        bus.line.faults(1).crc_error_rate = 0.5
        good = [check_crc(bus.transact(1, read)) for _ in range(24)]
        assert bus.line.stats().crc_errors_out == good.count(False)
        return good

    first = pattern(7)
    assert first == pattern(7)
    assert True in first and False in first

    bus = make_bus({1: plc(1)})
    bus.line.faults(1).crc_error_rate = 1.0
    frame = bus.transact(1, read)
    assert not check_crc(frame) and frame[:-2] == encode_rtu(1, h("03 02 0000"))[:-2]


def test_wrong_unit_then_right_unit(make_bus: BusFactory) -> None:
    bus = make_bus({1: plc(1)})
    bus.line.faults(1).wrong_unit_reply = True
    read = h("03 0001 0001")
    bus.send(encode_rtu(1, read))
    impostor = bus.read_response(read)
    assert impostor[0] != 1 and check_crc(impostor) and impostor[1:-2] == h("03 02 0002")
    assert bus.read_response(read) == encode_rtu(1, h("03 02 0002"))


def test_garbage_before_reply(make_bus: BusFactory) -> None:
    bus = make_bus({1: plc(1)})
    bus.line.faults(1).garbage_before_reply = h("FF 00 55")
    bus.send(encode_rtu(1, h("03 0001 0001")))
    assert bus.read_exactly(3) == h("FF 00 55")
    assert bus.read_response(h("03 0001 0001")) == encode_rtu(1, h("03 02 0002"))


def test_reply_delay(make_bus: BusFactory) -> None:
    bus = make_bus({1: plc(1)})
    bus.line.faults(1).reply_delay = 0.05
    sent = bus.send(encode_rtu(1, h("03 0000 0001")))
    bus.read_response(h("03 0000 0001"))
    assert time.perf_counter() - sent >= 0.05


def test_stop_returns_promptly_with_a_reply_pending(make_bus: BusFactory) -> None:
    bus = make_bus({1: plc(1)}, baudrate=9600)
    bus.line.faults(1).reply_delay = 30.0
    bus.send(encode_rtu(1, h("03 0000 0001")))
    bus.send(encode_rtu(1, h("03 0000 0001"))[:4])  # and a frame half received
    began = time.perf_counter()
    bus.line.stop()
    assert time.perf_counter() - began < 0.5


# --------------------------------------------------------------------------- line timing


@contextmanager
def realtime_master() -> Iterator[None]:
    """Run the test's own thread under SCHED_FIFO when permitted, restoring it afterwards.

    The master's wake-up latency is part of what a timing test measures; on a
    loaded machine it reaches milliseconds, which says nothing about the simulator.
    """
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (OSError, AttributeError):
        yield
        return
    try:
        yield
    finally:
        os.sched_setscheduler(0, before[0], before[1])


def delivery_delays(bus: Bus, samples: int = 30) -> list[float]:
    """How late a byte written on the simulator's end at a known instant reaches the test,
    through the same pty and the same reads, on this machine now: the floor under every
    pacing error (it drifts between days and machines)."""
    delays = []
    for _ in range(samples):
        at = time.perf_counter() + 0.002

        def write(at: float = at) -> None:
            with realtime_master():  # like the simulator's own thread
                wait_until(at)
                os.write(bus.sim_fd, b"\x00")

        writer = threading.Thread(target=write)
        writer.start()
        bus.read_exactly(1)
        delays.append(time.perf_counter() - at)
        writer.join()
    return delays


def test_pacing_at_9600_baud(make_bus: BusFactory) -> None:
    turnaround = 0.0005
    bus = make_bus({1: plc(1)}, baudrate=9600, turnaround=turnaround, realtime=True)
    char, gap = character_time(9600), t35(9600)
    errors = []
    cases = [h("03 0000 000A"), h("08 0000 A537")]  # length by byte count; length by silence
    with realtime_master():
        for index in range(30):
            pdu = cases[index % 2]
            request = encode_rtu(1, pdu)
            sent = bus.send(request)
            response = bus.read_response(pdu)
            arrived = time.perf_counter()
            # A frame of unknown length (FC 8) is only known to be over after t3.5 of silence.
            known = len(request) * char + (gap if pdu[0] == 0x08 else 0)
            errors.append(arrived - (sent + known + turnaround + len(response) * char))
            wait_until(arrived + gap + 0.0002)
        floor = statistics.quantiles(delivery_delays(bus), n=4)[0]
    # Never before the modelled end, and after it by what the pty adds each way: the
    # simulator times the request from its arrival, and its answer takes the same way
    # back (0.1 ms to a few tenths each way on these machines, depending on the day).
    # Delivery noise only ever delays (on a machine busy with other jobs, by
    # milliseconds), so the lower quartiles estimate the schedule and the pty's delay;
    # the test exposes any systematic error of 0.5 ms or more beyond two such delays,
    # measured in the same run.
    errors.sort()
    assert errors[0] >= 0, errors
    assert statistics.quantiles(errors, n=4)[0] <= 2 * floor + 0.0005, (floor, errors)
    stats = bus.line.stats()
    assert (stats.early_requests, stats.collisions, stats.responses) == (0, 0, 30)
    assert stats.min_gap_s is not None and stats.min_gap_s >= gap


def test_early_requests_and_collisions_are_counted(make_bus: BusFactory) -> None:
    # At 1200 baud t3.5 is 29 ms: a busy machine's wake-up delays cannot make
    # an immediate request look timely.
    bus = make_bus({1: plc(1)}, baudrate=1200)
    char, gap = character_time(1200), t35(1200)
    read = h("03 0000 0001")
    bus.transact(1, read)
    bus.transact(1, read)  # sent at once after the answer: less than t3.5 of silence
    assert bus.line.stats().early_requests == 1
    wait_until(time.perf_counter() + gap + 0.001)
    bus.transact(1, read)
    assert bus.line.stats().early_requests == 1

    wait_until(time.perf_counter() + gap + 0.001)
    bus.line.faults(1).reply_delay = 0.05
    sent = bus.send(encode_rtu(1, read))
    wait_until(sent + 8 * char + 0.01)  # the first request is over, its answer pending
    bus.send(encode_rtu(1, h("03 0001 0001")))
    assert bus.read_response(read) == encode_rtu(1, h("03 02 0000"))
    assert bus.read_response(read) == encode_rtu(1, h("03 02 0002"))  # still served after
    stats = bus.line.stats()
    assert (stats.collisions, stats.early_requests) == (1, 2)


# --------------------------------------------------------------------------- independent checks


def test_pymodbus_reads_the_simulator(make_bus: BusFactory) -> None:
    from pymodbus.client import ModbusSerialClient

    device = plc(1)
    bus = make_bus({1: device, 2: zl69x(2)}, baudrate=19200)
    path = os.ttyname(bus.fd)
    client: Any = ModbusSerialClient(path, baudrate=19200, timeout=1, retries=0)
    assert client.connect()
    try:
        result = client.read_holding_registers(0, count=10, device_id=1)
        assert not result.isError() and result.registers == [0, 2, 4, 6, 8, 10, 0, 0, 0, 0]
        assert not client.write_registers(100, [7, 8, 9], device_id=1).isError()
        assert [device.holding[a] for a in (100, 101, 102)] == [7, 8, 9]
        coils = client.read_coils(19, count=19, device_id=1)
        assert coils.bits[:19] == [bool((0x056BCD >> i) & 1) for i in range(19)]
        temperatures = client.read_holding_registers(0, count=2, device_id=2)
        assert temperatures.registers == [275, 0xFF9D]
        identity = client.read_device_information(read_code=1, object_id=0, device_id=2)
        assert identity.information[1] == b"ZL-69X"
        assert client.read_discrete_inputs(0, count=1, device_id=2).isError()
    finally:
        client.close()
    assert bus.line.stats().crc_errors_in == 0


def test_device_handles_pdus_without_a_line() -> None:
    device = SimulatedDevice(holding=DataBank([range(10, 20)], {10: 1}), max_read_registers=2)
    assert device.handle(h("03 000A 0002")) == h("03 04 0001 0000")
    assert device.handle(h("03 000A 0003")) == h("83 03")
    assert device.handle(h("03 0009 0001")) == h("83 02")
    assert device.handle(h("06 000B 0005"), broadcast=True) is None
    assert device.holding[11] == 5


def test_module_entry_point_serves_until_sigterm(tmp_path: Path) -> None:
    link = tmp_path / "simbus"
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "gateway.sim",
            "--profile",
            "plc:1",
            "--profile",
            "zl69x:2",
            "--baudrate",
            "115200",
            "--link",
            str(link),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        ready = process.stdout.readline().split()
        assert ready == ["READY", str(link)]
        fd = os.open(link, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            tty.setraw(fd)
            os.write(fd, h("01 03 00 00 00 0A C5 CD"))
            assert read_exactly(fd, 25)[-2:] == h("5B 02")
        finally:
            os.close(fd)
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=5)
    finally:
        with process:  # closes its pipe and waits
            if process.poll() is None:
                process.kill()
    assert process.returncode == 0
    stats = json.loads(output.strip().splitlines()[-1])
    assert stats["requests"] == 1 and stats["responses"] == 1
    assert not link.exists()
