"""The ``serial-slave`` listener in Modbus ASCII, and with an echoing adapter (RTU and ASCII).

The master's line is a real pty. A raw master in the test writes ASCII frames on
its end and reads the gateway's answers byte for byte; pymodbus's serial client in
ASCII mode is the independent master on a socat pty pair. Behind the gateway the
slaves are the simulated RTU line, as everywhere else. ptys refuse 7 data bits
(FIELD-NOTES), so the ASCII line here runs 8N1; 7E1 is the default for real ports.

An echoing adapter is imitated by the test's end of the pty: every byte the
gateway writes is written straight back to it, as a half-duplex adapter without
echo suppression hands the gateway its own transmission.
"""

from __future__ import annotations

import logging
import os
import select
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from gateway.config import build_config
from gateway.core.ascii import MAX_ASCII_FRAME, decode_ascii, encode_ascii
from gateway.core.crc import append_crc, check_crc
from gateway.io.listeners.serial_slave import SerialSlave
from gateway.sim import open_pty_pair, plc, zl69x
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    LogCollector,
    RunningGateway,
    SimBus,
    SimFactory,
    h,
    wait_until,
)
from tests.integration.metrics_harness import samples, series
from tests.integration.test_live import status, stream
from tests.integration.test_serial_slave import socat_ptys  # noqa: F401  (a fixture)
from tests.integration.test_sim import FUNCTION_VECTORS

BAUD = 19200
#: ptys refuse 7 data bits and some parities (FIELD-NOTES): ASCII lines in tests run 8N1.
ASCII_ON_PTY = {"framing": "ascii", "data_bits": 8, "parity": "N"}


def write_all(fd: int, data: bytes) -> None:
    """Write ``data`` on the non-blocking pty end, waiting for room as the gateway reads."""
    deadline = time.monotonic() + DEADLINE_S
    view = memoryview(data)
    while view:
        left = deadline - time.monotonic()
        assert left > 0, f"{len(view)} bytes not taken"
        _, writable, _ = select.select([], [fd], [], left)
        if writable:
            view = view[os.write(fd, view) :]


class LineMaster:
    """The master end of the gateway's slave-side pty, RTU or ASCII, optionally echoing.

    With ``echo``, whatever the gateway writes is written back to it at once (the
    adapter hears itself); the master still sees the answer.
    """

    def __init__(self, fd: int, framing: str = "ascii", echo: bool = False) -> None:
        self.fd = fd
        self.framing = framing
        self.echo = echo
        self.echoed = 0

    def encode(self, unit: int, pdu: bytes) -> bytes:
        if self.framing == "ascii":
            return encode_ascii(unit, pdu)
        return append_crc(bytes((unit,)) + pdu)

    def send(self, unit: int, pdu: bytes) -> float:
        os.write(self.fd, self.encode(unit, pdu))
        return time.monotonic()

    def _read(self, timeout: float) -> bytes:
        readable, _, _ = select.select([self.fd], [], [], timeout)
        if not readable:
            return b""
        data = os.read(self.fd, 1024)
        if self.echo:
            os.write(self.fd, data)
            self.echoed += len(data)
        return data

    def receive_frame(self, length: int | None = None, timeout: float = DEADLINE_S) -> bytes:
        """One whole answer: to CR LF (ASCII) or ``length`` bytes (RTU)."""
        deadline = time.monotonic() + timeout
        data = b""
        while not (data.endswith(b"\r\n") if length is None else len(data) >= length):
            left = deadline - time.monotonic()
            assert left > 0, f"no whole answer: {data!r}"
            data += self._read(left)
        return data

    def request(self, unit: int, pdu: bytes, rtu_reply_pdu: int = 0) -> bytes:
        """Send a request and return the answer's PDU (checked: unit, LRC or CRC)."""
        self.send(unit, pdu)
        if self.framing == "ascii":
            answer_unit, answer = decode_ascii(self.receive_frame())
        else:
            frame = self.receive_frame(rtu_reply_pdu + 3)
            assert check_crc(frame), frame.hex(" ")
            answer_unit, answer = frame[0], frame[1:-2]
        assert answer_unit == unit
        return answer

    def silent_for(self, seconds: float) -> None:
        """Assert that nothing comes back for ``seconds``."""
        data = self._read(seconds)
        assert not data, f"unexpected answer: {data!r}"


Setup = tuple[SimBus, RunningGateway, LineMaster, SerialSlave]


def wait_for(gateway: RunningGateway, condition: Callable[[], bool]) -> None:
    """Wait until ``condition`` holds, evaluated on the gateway's loop."""
    wait_until(lambda: gateway.call(condition))


@pytest.fixture
def reverse(make_sim: SimFactory, make_gateway: GatewayFactory) -> Iterator[Any]:
    """``reverse(devices, master_echo=False, **listener)``: a serial-slave listener on a pty."""
    pairs = []

    def factory(
        devices: dict[int, Any] | None = None, master_echo: bool = False, **listener: Any
    ) -> Setup:
        devices = devices or {1: plc(1), 2: zl69x(2)}
        sim = make_sim(devices)
        pair = open_pty_pair()
        pairs.append(pair)
        entry = {"name": "field", "protocol": "serial-slave", "device": pair.path,
                 "baudrate": BAUD, **ASCII_ON_PTY, **listener}  # fmt: skip
        gateway = make_gateway(
            {"lines": {"a": sim.line_table(sorted(devices))}, "listeners": [entry]}
        )
        slave = next(s for s in gateway.gateway.serial_slaves if s.name == "field")
        wait_for(gateway, lambda: slave.up)
        master = LineMaster(pair.sim_fd, entry["framing"], master_echo)
        return sim, gateway, master, slave

    yield factory
    for pair in pairs:
        pair.close()


# --------------------------------------------------------------------------- ASCII


def test_the_specification_vector_byte_for_byte(reverse: Any) -> None:
    sim, _, master, _ = reverse()
    sim.device(1).coils[2] = 1
    sim.device(1).coils[11] = 1
    os.write(master.fd, b":010100020010EC\r\n")  # unit 1, FC 1, start 2, quantity 16
    assert master.receive_frame() == b":0101020102F9\r\n"


VECTOR_UNITS = range(1, len(FUNCTION_VECTORS) + 1)


def test_every_function_code_through_an_ascii_serial_slave(reverse: Any) -> None:
    """The simulator's vectors, each to a fresh device (its own unit), answered byte-exact."""
    _, _, master, _ = reverse({unit: plc(unit) for unit in VECTOR_UNITS})
    for unit, (request_hex, response_hex) in zip(VECTOR_UNITS, FUNCTION_VECTORS, strict=True):
        master.send(unit, h(request_hex))
        assert master.receive_frame() == encode_ascii(unit, h(response_hex)), request_hex


def test_answers_reads_writes_and_exceptions_and_keeps_tcp_working(reverse: Any) -> None:
    sim, gateway, master, slave = reverse()
    assert master.request(1, h("10 0BB8 0002 04 1234 5678")) == h("10 0BB8 0002")
    assert sim.device(1).holding.read(3000, 2) == [0x1234, 0x5678]
    assert master.request(2, h("03 0000 0002")) == h("03 04 0113 FF9D")
    assert master.request(1, h("03 FFFF 0002")) == h("83 02")  # the device's exception
    assert master.request(1, h("03 0000 007E")) == h("83 03")  # refused by the gateway
    # Lower-case hexadecimal is accepted; the answer is upper case.
    os.write(master.fd, encode_ascii(1, h("03 0BB8 0001")).lower())
    assert master.receive_frame() == encode_ascii(1, h("03 02 1234"))
    with gateway.connect() as client:
        assert client.request(1, h("03 0BB8 0002")) == h("03 04 1234 5678")
    assert gateway.call(lambda: (slave.requests, slave.ignored)) == (5, 0)


def test_silence_for_bad_lrc_unrouted_units_broadcasts_and_damaged_frames(reverse: Any) -> None:
    sim, gateway, master, slave = reverse()
    quiet = 0.1  # far longer than the simulated line's answer
    good = encode_ascii(1, h("03 0000 0001"))
    os.write(master.fd, good[:-4] + b"00\r\n")  # wrong LRC
    master.silent_for(quiet)
    master.send(9, h("03 0000 0001"))  # not routed: another slave on this line may answer
    master.silent_for(quiet)
    master.send(0, h("06 0007 0077"))  # broadcast: executed, never answered
    master.silent_for(quiet)
    master.send(1, h("03 02 0000"))  # shaped like another slave's answer: not a request
    master.silent_for(quiet)
    os.write(master.fd, good[:-2] + b"\n")  # LF without CR
    master.silent_for(quiet)
    os.write(master.fd, b":01030000000G\r\n")  # not hexadecimal
    master.silent_for(quiet)
    assert gateway.call(lambda: slave.ignored) == 5
    # A ':' in mid-frame abandons what came before it: the second frame is answered.
    os.write(master.fd, good[:7] + encode_ascii(1, h("03 0007 0001")))
    assert decode_ascii(master.receive_frame()) == (1, h("03 02 0077"))
    assert sim.stats().broadcasts == 1
    assert gateway.call(lambda: (slave.requests, slave.ignored)) == (1, 6)
    found = samples(gateway)
    errors = {kind: found.get(series("modbus_gateway_protocol_errors_total", kind=kind), 0)
              for kind in ("bad_crc", "bad_char", "restarted", "too_long")}  # fmt: skip
    assert errors == {"bad_crc": 1, "bad_char": 2, "restarted": 1, "too_long": 0}


def test_a_frame_whose_characters_stop_is_abandoned(reverse: Any) -> None:
    _, gateway, master, slave = reverse(inter_char_timeout=0.2)
    frame = encode_ascii(1, h("03 0000 0001"))
    os.write(master.fd, frame[:9])
    wait_for(gateway, lambda: slave.ignored == 1)  # the inter-character timeout fired
    os.write(master.fd, frame[9:])  # the rest, without its ':': outside any frame
    master.silent_for(0.1)
    assert master.request(1, h("03 0000 0001")) == h("03 02 0000")


def test_a_babbling_ascii_line_is_bounded_and_the_next_request_is_answered(
    reverse: Any,
) -> None:
    """Hostile input over the pty: endless frames, restarts and noise, bounded in count and time."""
    _, gateway, master, slave = reverse()
    reader = slave._ascii
    assert reader is not None
    endless = b":" + b"0" * 4000  # a frame that never ends: far past 513 characters
    restarts = b":0103" * 400  # a ':' every five characters
    noise = bytes(range(256)).replace(b":", b"") * 8  # no ':' at all: outside any frame
    started = time.monotonic()
    for chunk in (endless, restarts, noise) * 5:
        write_all(master.fd, chunk)
    wait_for(gateway, lambda: slave.ignored >= 5 * 399)
    assert time.monotonic() - started < DEADLINE_S
    assert gateway.call(lambda: reader.buffered) <= MAX_ASCII_FRAME
    master.silent_for(0.05)
    assert master.request(1, h("03 0000 0001")) == h("03 02 0000")
    assert gateway.call(lambda: slave.requests) == 1
    found = samples(gateway)
    assert found[series("modbus_gateway_protocol_errors_total", kind="too_long")] == 5


def test_the_answer_waits_one_character_after_the_request(reverse: Any) -> None:
    """ASCII frames end at their LF: the turnaround is one character time (33 ms at 300 baud)."""
    _, _, master, _ = reverse(baudrate=300)
    character = 10 / 300  # 8N1 on the pty
    for _ in range(3):
        sent = master.send(1, h("03 0000 0001"))
        master.receive_frame()
        assert time.monotonic() - sent >= character


# --------------------------------------------------------------------------- pymodbus as master


def test_pymodbus_as_ascii_master(
    make_sim: SimFactory,
    make_gateway: GatewayFactory,
    socat_ptys: tuple[str, str],  # noqa: F811
) -> None:
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    gateway_end, master_end = socat_ptys
    sim = make_sim({1: plc(1), 2: zl69x(2)})
    entry = {"name": "field", "protocol": "serial-slave", "device": gateway_end,
             "baudrate": BAUD, **ASCII_ON_PTY}  # fmt: skip
    gateway = make_gateway({"lines": {"a": sim.line_table([1, 2])}, "listeners": [entry]})
    slave = gateway.gateway.serial_slaves[0]
    wait_for(gateway, lambda: slave.up)
    client = ModbusSerialClient(
        master_end, framer=FramerType.ASCII, baudrate=BAUD, bytesize=8, parity="N", timeout=2,
        retries=0,
    )  # fmt: skip
    assert client.connect()
    try:
        read = client.read_holding_registers(1000, count=5, device_id=1)
        assert not read.isError() and read.registers == [1000 + i for i in range(5)]
        assert not client.write_registers(500, [11, 22, 33], device_id=1).isError()
        assert sim.device(1).holding.read(500, 3) == [11, 22, 33]
        assert not client.write_coils(40, [True, False, True], device_id=1).isError()
        coils = client.read_coils(40, count=3, device_id=1)
        assert coils.bits[:3] == [True, False, True]
        zl = client.read_holding_registers(0, count=2, device_id=2)
        assert zl.registers == [0x0113, 0xFF9D]
        refused = client.read_discrete_inputs(0, count=1, device_id=2)  # not a ZL-69X code
        assert refused.isError() and refused.exception_code == 1
    finally:
        client.close()  # type: ignore[no-untyped-call]


# --------------------------------------------------------------------------- echoing adapter


@pytest.mark.parametrize("framing", ["rtu", "ascii"])
def test_an_echoing_adapter_with_echo_set(reverse: Any, framing: str) -> None:
    """The answer's own bytes come back at once: dropped, neither a request nor noise."""
    sim, gateway, master, slave = reverse(master_echo=True, echo=True, framing=framing)
    for value in range(20):
        word = value.to_bytes(2, "big")
        # A write's answer is the request itself: its echo, taken for a request, would be
        # executed and answered again.
        assert master.request(1, h("06 0064") + word, 5) == h("06 0064") + word
        master.silent_for(0.02)
        assert master.request(1, h("03 0064 0001"), 4) == h("03 02") + word
    assert sim.device(1).holding[100] == 19
    wait_for(gateway, lambda: slave.echoes == master.echoed)
    assert gateway.call(lambda: (slave.requests, slave.ignored)) == (40, 0)


def test_an_echoing_adapter_without_echo_set_repeats_writes(reverse: Any) -> None:
    """What ``echo = true`` is for: the echo of a write's answer is the same write again."""
    _, gateway, master, slave = reverse(master_echo=True, framing="rtu")
    assert master.request(1, h("06 0064 0007"), 5) == h("06 0064 0007")
    master.echo = False  # one echo only, or the gateway and the adapter go round forever
    second = master.receive_frame(8)  # the gateway answered its own echo
    assert second == append_crc(h("01 06 0064 0007"))
    master.silent_for(0.02)
    assert gateway.call(lambda: slave.requests) == 2


# --------------------------------------------------------------------------- status and trace


def test_the_master_on_the_line_is_listed_and_traced(reverse: Any) -> None:
    _, gateway, master, slave = reverse()
    device = slave.listener.serial.device if slave.listener.serial else ""
    assert status(gateway)["masters"] == []  # no request heard yet: no master known
    with stream(gateway, "?unit=1") as trace:
        assert master.request(1, h("03 0000 0002")) == h("03 04 0000 0002")
        request, reply = trace.event(), trace.event()
        master.send(2, h("03 0000 0001"))  # another unit: filtered out of this stream
        master.receive_frame()
        assert master.request(1, h("06 0000 0005")) == h("06 0000 0005")
        second = trace.event()
    assert request == {
        **request,
        "type": "request", "master": device, "listener": "field", "tid": 0, "unit": 1,
        "line": "a", "slave": 1, "fc": 3, "hex": "03 00 00 00 02",
    }  # fmt: skip
    assert (reply["type"], reply["tid"], reply["outcome"]) == ("reply", 0, "ok")
    assert bytes.fromhex(reply["hex"]) == h("03 04 0000 0002")
    assert (second["type"], second["tid"], second["fc"]) == ("request", 2, 6)
    (entry,) = status(gateway)["masters"]
    assert entry == {
        "peer": device, "listener": f"field {device} (ascii)", "in_flight": 0, "requests": 3,
        "role": None, "denied": 0, "unrouted": 0,
    }  # fmt: skip


# --------------------------------------------------------------------------- reload


def test_a_reload_applies_the_policy_and_keeps_the_serial_line_until_a_restart(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)})
    pair = open_pty_pair()
    collector = LogCollector()
    logger = logging.getLogger("gateway")
    logger.addHandler(collector)
    try:
        entry = {"name": "field", "protocol": "serial-slave", "device": pair.path,
                 "baudrate": BAUD, **ASCII_ON_PTY}  # fmt: skip
        tables: dict[str, Any] = {
            "server": {"listen": "127.0.0.1:0"}, "metrics": {"listen": "127.0.0.1:0"},
            "lines": {"a": sim.line_table([1])}, "listeners": [entry],
        }  # fmt: skip
        gateway = make_gateway(tables)
        slave = gateway.gateway.serial_slaves[0]
        wait_for(gateway, lambda: slave.up)
        master = LineMaster(pair.sim_fd)
        assert master.request(1, h("06 0000 0001")) == h("06 0000 0001")
        tables["listeners"] = [{**entry, "read_only": True}]
        gateway.run(gateway.gateway.reload(build_config(tables, "<reload>")))
        assert master.request(1, h("06 0000 0002")) == h("86 01")  # the new policy applies
        assert not [m for m in collector.messages if "serial-slave listener" in m]
        tables["listeners"] = [{**entry, "framing": "rtu"}]
        gateway.run(gateway.gateway.reload(build_config(tables, "<reload>")))
        (warning,) = [m for m in collector.messages if "serial-slave listener" in m]
        assert "field" in warning and "framing" in warning and "restart" in warning
        assert master.request(1, h("03 0000 0001")) == h("03 02 0001")  # still ASCII
    finally:
        logger.removeHandler(collector)
        pair.close()


def test_a_reload_gives_the_serial_slave_the_new_routes(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    """A unit a reload routes is answered on the serial line from then on; before, the
    listener kept the silence of an absent slave."""
    sim = make_sim({1: plc(1), 2: plc(2)})
    pair = open_pty_pair()
    try:
        entry = {"name": "field", "protocol": "serial-slave", "device": pair.path,
                 "baudrate": BAUD, **ASCII_ON_PTY}  # fmt: skip
        tables: dict[str, Any] = {
            "server": {"listen": "127.0.0.1:0"}, "metrics": {"listen": "127.0.0.1:0"},
            "lines": {"a": sim.line_table([1])}, "listeners": [entry],
        }  # fmt: skip
        gateway = make_gateway(tables)
        slave = gateway.gateway.serial_slaves[0]
        wait_for(gateway, lambda: slave.up)
        master = LineMaster(pair.sim_fd)
        master.send(2, h("03 0000 0001"))
        master.silent_for(0.2)  # no route for unit 2: the silence of an absent slave
        tables["lines"] = {"a": sim.line_table([1, 2])}
        gateway.run(gateway.gateway.reload(build_config(tables, "<reload>")))
        assert master.request(2, h("03 0001 0001")) == h("03 02 0002")
    finally:
        pair.close()
