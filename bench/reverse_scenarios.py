"""Reverse mode: a master on the gateway's ``serial-slave`` line, RTU and ASCII.

``reverse`` puts one master (a serial line has one) on a pty the gateway answers
on as a slave (``--serial-slave``), in RTU and then in ASCII, with the simulated
RTU line behind the gateway unpaced. The master sends FC03 x 10 across the 4
slaves back to back, each as soon as the previous answer is whole, and checks
every answer against ``bench.values``. RTU frames are framed by t3.5 of silence
(1.75 ms above 19200 baud, met by the precise clock): the listener cannot know a
request ended sooner, so a master there waits at least that per transaction; an
ASCII frame ends at its LF. The gateway's CPU per transaction is read from
``/proc`` over the window. ptys refuse 7 data bits, so the ASCII run is 8N1 (the
same 10 bits a character).

Like the load generator, this master keeps its own reading of the protocol
(CRC, LRC): nothing of the gateway is imported.
"""

from __future__ import annotations

import binascii
import os
import select
import tempfile
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .loadgen import machine_busy_seconds, percentile, process_cpu_seconds
from .procs import PYTHON, Server, SimOptions, Simulator, free_port
from .scenarios import HEALTHY_UNITS, UNPACED_BAUDRATE, Bench, Check, ScenarioResult, Table, _fmt
from .values import FIRST_REGISTER, register_block

QUANTITY = 10
_ANSWER_TIMEOUT_S = 1.0


def _crc16(data: bytes) -> bytes:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def _lrc(data: bytes) -> int:
    return -sum(data) & 0xFF


def encode(framing: str, unit: int, pdu: bytes) -> bytes:
    """A request frame as a master writes it."""
    body = bytes((unit,)) + pdu
    if framing == "ascii":
        return b":" + binascii.hexlify(body + bytes((_lrc(body),))).upper() + b"\r\n"
    return body + _crc16(body)


def decode(framing: str, frame: bytes) -> bytes | None:
    """Unit and PDU of a whole answer, ``None`` when its check fails."""
    if framing == "ascii":
        raw = binascii.unhexlify(frame[1:-2])
        return raw[:-1] if _lrc(raw[:-1]) == raw[-1] else None
    return frame[:-2] if _crc16(frame[:-2]) == frame[-2:] else None


@dataclass
class MasterResult:
    """What the master on the serial-slave line measured in its window."""

    framing: str
    answers: int = 0
    wrong: int = 0
    lost: int = 0
    window_s: float = 0.0
    gateway_cpu_s: float = 0.0
    machine_cpu_s: float = 0.0
    latencies_ms: list[float] = field(default_factory=list)

    @property
    def tx_per_s(self) -> float:
        return self.answers / self.window_s if self.window_s else 0.0

    @property
    def cpu_us_per_tx(self) -> float:
        return 1e6 * self.gateway_cpu_s / self.answers if self.answers else 0.0

    @property
    def other_load(self) -> float:
        """Cores busy with other work than the gateway during the window (the master's too)."""
        return max(0.0, (self.machine_cpu_s - self.gateway_cpu_s) / (self.window_s or 1.0))

    def as_json(self) -> dict[str, Any]:
        ordered = sorted(self.latencies_ms)
        return {
            "framing": self.framing, "tx_per_s": self.tx_per_s, "answers": self.answers,
            "wrong_answers": self.wrong, "lost": self.lost, "window_s": self.window_s,
            "gateway_cpu_us_per_tx": self.cpu_us_per_tx, "other_load_cores": self.other_load,
            "latency_ms": {"p50": percentile(ordered, 0.5), "p99": percentile(ordered, 0.99)},
        }  # fmt: skip


class LineMaster:
    """One master on the master end of a pty: a request, then its whole answer."""

    def __init__(self, fd: int, framing: str) -> None:
        self.fd = fd
        self.framing = framing
        self.expected_length = 3 + 2 + 2 * QUANTITY  # RTU: unit, FC, count, data, CRC

    def transact(self, unit: int, address: int) -> bytes | None:
        """Send FC03 x 10 to ``unit``; the answer's PDU, ``None`` if lost or damaged."""
        pdu = bytes((3,)) + address.to_bytes(2, "big") + QUANTITY.to_bytes(2, "big")
        os.write(self.fd, encode(self.framing, unit, pdu))
        frame = b""
        deadline = time.monotonic() + _ANSWER_TIMEOUT_S
        while not self._whole(frame):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                return None
            frame += os.read(self.fd, 1024)
        decoded = decode(self.framing, frame)
        if decoded is None or decoded[0] != unit:
            return None
        return decoded[1:]

    def _whole(self, frame: bytes) -> bool:
        if self.framing == "ascii":
            return frame.endswith(b"\r\n")
        return len(frame) >= self.expected_length


def run_master(master: LineMaster, server_pid: int, warmup: float, window: float) -> MasterResult:
    """Back-to-back requests for ``warmup`` then ``window`` seconds, measured in the window."""
    result = MasterResult(master.framing)
    started = time.monotonic()
    measuring = False
    cpu_before = machine_before = window_start = 0.0
    index = 0
    while True:
        now = time.monotonic()
        if not measuring and now - started >= warmup:
            measuring = True
            window_start = now
            cpu_before = process_cpu_seconds(server_pid) or 0.0
            machine_before = machine_busy_seconds()
        if measuring and now - window_start >= window:
            break
        unit = HEALTHY_UNITS[index % len(HEALTHY_UNITS)]
        address = FIRST_REGISTER + (index * 7) % 8000
        index += 1
        sent = time.perf_counter()
        pdu = master.transact(unit, address)
        elapsed_ms = 1000 * (time.perf_counter() - sent)
        if not measuring:
            continue
        if pdu is None:
            result.lost += 1
        elif pdu != bytes((3, 2 * QUANTITY)) + register_block(unit, address, QUANTITY):
            result.wrong += 1
        else:
            result.answers += 1
            result.latencies_ms.append(elapsed_ms)
    result.window_s = time.monotonic() - window_start
    result.gateway_cpu_s = (process_cpu_seconds(server_pid) or 0.0) - cpu_before
    result.machine_cpu_s = machine_busy_seconds() - machine_before
    return result


def measure(framing: str, bench: Bench) -> MasterResult:
    """The simulator, the gateway with a serial-slave listener on a pty, and the master."""
    bench.progress(f"  reverse mode, {framing} master ...")
    with tempfile.TemporaryDirectory(prefix="modbus-bench-") as temp:
        workdir = Path(temp)
        simulator = Simulator(SimOptions(units=HEALTHY_UNITS), workdir)
        master_fd, slave_fd = os.openpty()
        tty.setraw(master_fd)
        tty.setraw(slave_fd)
        device = os.ttyname(slave_fd)
        command = [PYTHON, "-m", "gateway", "--serial", str(simulator.link)]
        command += ["--baudrate", str(UNPACED_BAUDRATE), "--frame-gap", "0"]
        command += ["--serial-slave", device, "--serial-slave-framing", framing]
        command += ["--data-bits", "8", "--parity", "N"]  # ptys refuse 7 data bits
        command += ["--listen", f"127.0.0.1:{free_port()}", "--metrics", "off"]
        server = Server(command, workdir, "server")
        simulator.start()
        try:
            server.start("answering as a slave on")
            result = run_master(
                LineMaster(master_fd, framing), server.pid, bench.timing.warmup,
                bench.timing.window,
            )  # fmt: skip
        finally:
            server.stop()
            simulator.stop()
            os.close(master_fd)
            os.close(slave_fd)
    bench.progress(
        f"  reverse mode, {framing} master: {result.tx_per_s:,.1f} tx/s, {result.wrong} wrong, "
        f"{result.lost} lost, {result.cpu_us_per_tx:.1f} us gateway CPU/tx"
    )
    return result


def reverse(bench: Bench) -> ScenarioResult:
    """Issue 11: one master on the serial-slave line, RTU then ASCII, every answer checked."""
    results = [measure(framing, bench) for framing in ("rtu", "ascii")]
    table = Table(
        "Reverse mode: one master on the --serial-slave pty, FC03 x 10 across 4 slaves back to "
        f"back, unpaced simulated RTU line behind ({UNPACED_BAUDRATE:,} baud on both ptys)",
        ["master", "tx/s", "p50 ms", "p99 ms", "gw CPU us/tx", "other load", "wrong", "lost"],
    )
    for result in results:
        ordered = sorted(result.latencies_ms)
        table.rows.append([
            result.framing, _fmt(result.tx_per_s, 0), _fmt(percentile(ordered, 0.5), 2),
            _fmt(percentile(ordered, 0.99), 2), _fmt(result.cpu_us_per_tx),
            f"{result.other_load:.2f}", str(result.wrong), str(result.lost),
        ])  # fmt: skip
    wrong = sum(result.wrong for result in results)
    figures = {result.framing: result.as_json() for result in results}
    checks = [Check("reverse mode: wrong answers", wrong, "0", wrong == 0)]
    notes = [
        "RTU requests end on t3.5 of silence (1.75 ms above 19200 baud), which bounds an RTU "
        "master's rate; ASCII frames end at their LF (turnaround: one character time)",
        "the master runs in the benchmark's own process; other load includes it",
    ]
    return ScenarioResult("reverse", figures, [table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"reverse": reverse}
