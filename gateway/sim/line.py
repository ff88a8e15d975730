"""The slave side of a simulated RS485 line: frames requests, answers them with real-line timing.

Theory of operation: one daemon thread (never the gateway's event loop, so the
simulator's timing does not depend on the code under test) reads the line's fd
and splits the byte stream into frames with ``gateway.core.rtu.request_length``,
falling back to t3.5 of silence when the length cannot be told. A frame with a
bad CRC or for a unit the line does not have is dropped silently, as on a real
bus; unit 0 is executed by every device and never answered.

Pacing: bytes cross a pty instantly, so the wire is modelled in time. A request
whose first byte arrived at T occupies the wire until T + n x character time;
the slave answers ``turnaround`` seconds later and its m-byte response would
end m character times after that: the whole response is written at that end
instant (coarse wait, then a short spin for ~20 us accuracy). Every request
starting less than t3.5 after the previous frame's end is an ``early_request``;
one arriving while a response is pending is also a ``collision``.
With ``strict_baudrate`` a request is answered only while the master's end of
the pty is set to the line's own baud rate (``wrong_baudrate`` counts the others). Colliding
requests are still served afterwards, so a benchmark keeps running and the
counters tell what a real bus would have garbled.

``framing="ascii"`` speaks Modbus ASCII instead: requests are split at ':' and CR LF
(a frame whose characters stop for ``inter_char_timeout`` is dropped), checked by
LRC, and answered in ASCII. ``echo=True`` imitates a half-duplex adapter without
echo suppression: every byte the master writes comes straight back to it.
"""

from __future__ import annotations

import ctypes
import errno
import os
import random
import select
import sys
import termios
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from types import TracebackType

from gateway.core.ascii import decode_ascii, encode_ascii
from gateway.core.crc import check_crc
from gateway.core.errors import ResponseError
from gateway.core.rtu import MAX_RTU_FRAME, MIN_RTU_FRAME, NEED_MORE, encode_rtu, request_length
from gateway.core.timing import FIXED_T35_S, character_time, t35

from .device import SimulatedDevice

BROADCAST_UNIT = 0
DEFAULT_TURNAROUND_S = 0.0005
_SPIN_S = 0.0003  # the last stretch before a deadline is spun, not slept: select overshoots
_HANGUP_RETRY_S = 0.01
_READ_SIZE = 4096
_MAX_BUFFER = 4 * MAX_RTU_FRAME
_JOIN_TIMEOUT_S = 5.0
_PR_SET_TIMERSLACK = 29


@dataclass
class UnitFaults:
    """Faults injected for one unit; attributes may be changed while the line runs."""

    silent: bool = False  #: never answer (the request is not executed either: device absent)
    crc_error_rate: float = 0.0  #: fraction of responses sent with a corrupted CRC (seeded)
    reply_delay: float = 0.0  #: extra seconds before answering (late replies after a timeout)
    wrong_unit_reply: bool = False  #: first send the answer from another unit, then the right one
    garbage_before_reply: bytes = b""  #: bytes sent, then t3.5 of silence, before the answer


@dataclass(frozen=True)
class SimulatedLineStats:
    """A snapshot of what the simulated line saw and did."""

    requests: int  #: frames with a good CRC, for any unit (broadcasts included)
    responses: int  #: answers sent (an answer with injected faults counts once)
    crc_errors_in: int  #: frames dropped for a bad CRC
    broadcasts: int  #: unit 0 requests executed
    early_requests: int  #: requests starting less than t3.5 after the previous frame's end
    collisions: int  #: requests arriving while a response was pending
    foreign_frames: int  #: good frames for units this line does not have
    silent_drops: int  #: requests to a unit injected ``silent``
    crc_errors_out: int  #: responses sent with a corrupted CRC on purpose
    incomplete_frames: int  #: byte runs that never became a frame before t3.5 of silence
    wrong_baudrate: int  #: requests ignored because the master's side was at another speed
    min_gap_s: float | None  #: shortest silence before a request (paced lines; None before any)
    max_lateness_s: float  #: worst delay of a response write behind its computed end time


@dataclass
class _Counters:
    requests: int = 0
    responses: int = 0
    crc_errors_in: int = 0
    broadcasts: int = 0
    early_requests: int = 0
    collisions: int = 0
    foreign_frames: int = 0
    silent_drops: int = 0
    crc_errors_out: int = 0
    incomplete_frames: int = 0
    wrong_baudrate: int = 0
    min_gap_s: float = field(default=float("inf"))
    max_lateness_s: float = 0.0


class _SimulationStoppedError(Exception):
    """Unwinds the serving thread when ``stop`` is called."""


def _reduce_timer_slack() -> None:
    """Ask Linux for 1 ns timer slack on this thread so sleeps end within ~20 us of their deadline.

    Best effort: elsewhere the spin before each deadline covers the difference.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0)
    except (OSError, AttributeError):
        return


def _enter_realtime() -> bool:
    """Run this thread under SCHED_FIFO when permitted, so other processes delay its wake-ups less.

    It cannot help with the pty's own delivery (~0.1 ms each way, done by a
    kernel worker) nor with a virtual machine whose CPUs are themselves descheduled.
    """
    try:
        policy = os.SCHED_FIFO
        os.sched_setscheduler(0, policy, os.sched_param(os.sched_get_priority_min(policy)))
    except (OSError, AttributeError):
        return False
    return True


class SimulatedLine:
    """Serves ``{unit: SimulatedDevice}`` on the slave end of a serial line (a pty master fd).

    ``baudrate=None`` answers at once (throughput tests); with a baud rate every
    response is paced like a real line. ``realtime`` asks for SCHED_FIFO for the
    serving thread (see ``realtime_active``). The fd is not closed by the line.
    """

    def __init__(
        self,
        fd: int,
        devices: Mapping[int, SimulatedDevice],
        *,
        baudrate: int | None = None,
        data_bits: int = 8,
        parity: str = "N",
        stop_bits: float = 1,
        turnaround: float = DEFAULT_TURNAROUND_S,
        seed: int = 0,
        realtime: bool = False,
        strict_baudrate: bool = False,
        framing: str = "rtu",
        echo: bool = False,
        inter_char_timeout: float = 1.0,
    ) -> None:
        if framing not in ("rtu", "ascii"):
            raise ValueError(f"framing {framing!r} is not rtu or ascii")
        self._ascii = framing == "ascii"
        self._encode = encode_ascii if self._ascii else encode_rtu
        self._echo = echo
        self._inter_char_timeout = inter_char_timeout
        for unit in devices:
            if not 1 <= unit <= 247:
                raise ValueError(f"unit {unit} outside 1..247")
        self._fd = fd
        self._devices = dict(devices)
        self._faults = {unit: UnitFaults() for unit in self._devices}
        self.baudrate = baudrate
        if baudrate is None:
            self._char_time = 0.0
            self._t35 = 0.0  # no line timing: nothing is early
            self._silence = FIXED_T35_S  # still needed to end frames of unknown length
            self._turnaround = 0.0
        else:
            self._char_time = character_time(baudrate, data_bits, parity, stop_bits)
            self._t35 = t35(baudrate, data_bits, parity, stop_bits)
            self._silence = self._t35
            self._turnaround = turnaround
        self._rng = random.Random(seed)
        self._realtime = realtime
        self._speed: int | None = None  # termios speed the master's side must be set to
        if strict_baudrate:
            if baudrate is None:
                raise ValueError("strict_baudrate needs a baudrate")
            self._speed = getattr(termios, f"B{baudrate}", None)
            if self._speed is None:
                raise ValueError(f"baud rate {baudrate} has no termios speed")
        self.realtime_active = False  # set by the serving thread once it runs
        self._counters = _Counters()
        self._buffer = bytearray()
        self._frame_start = 0.0  # arrival of the first byte of the frame being received
        self._rx_end = 0.0  # when the bytes received so far finish on the modelled wire
        self._line_free_at = float("-inf")  # end of the previous frame on the wire
        self._transmitting = False
        self._wake_r, self._wake_w = os.pipe()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: Exception | None = None

    # ------------------------------------------------------------------ public API

    @property
    def devices(self) -> Mapping[int, SimulatedDevice]:
        """The devices by unit address (their tables may be read and written while running)."""
        return self._devices

    @property
    def character_time(self) -> float:
        """Seconds per character on the modelled wire (0 when unpaced)."""
        return self._char_time

    @property
    def t35(self) -> float:
        """The inter-frame silence the line expects from the master (0 when unpaced)."""
        return self._t35

    def faults(self, unit: int) -> UnitFaults:
        """The live fault settings of ``unit``: set attributes on it to inject faults."""
        return self._faults[unit]

    def set_faults(self, unit: int, faults: UnitFaults) -> None:
        """Replace every fault setting of ``unit`` at once."""
        if unit not in self._faults:
            raise KeyError(unit)
        self._faults[unit] = faults

    def stats(self) -> SimulatedLineStats:
        """A snapshot of the counters (taken without locking; each field is consistent)."""
        values = asdict(self._counters)
        if values["min_gap_s"] == float("inf"):
            values["min_gap_s"] = None
        return SimulatedLineStats(**values)

    def start(self) -> None:
        """Start serving in a daemon thread."""
        if self._thread is not None or self._stopping.is_set():
            raise RuntimeError("a line is started once")
        self._thread = threading.Thread(target=self._run, name="simulated-rtu-line", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop serving and join the thread; re-raises an error the thread died of.

        The line cannot be started again; stopping twice is harmless.
        """
        if self._stopping.is_set():
            return
        self._stopping.set()
        os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join(_JOIN_TIMEOUT_S)
            if self._thread.is_alive():
                raise RuntimeError("simulated line thread did not stop")
        os.close(self._wake_r)
        os.close(self._wake_w)
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def __enter__(self) -> SimulatedLine:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()

    # ------------------------------------------------------------------ the serving thread

    def _run(self) -> None:
        _reduce_timer_slack()
        if self._realtime:
            self.realtime_active = _enter_realtime()
        try:
            while True:
                if not self._buffer:
                    self._poll(None)
                    continue
                taken = self._take_frame()
                if taken is not None:
                    self._serve_frame(*taken)
        except _SimulationStoppedError:
            return
        except Exception as error:  # kept for stop() to re-raise in the caller's thread
            self._error = error

    def _poll(self, timeout: float | None) -> bool:
        """Wait up to ``timeout`` for input and take it; True when bytes arrived."""
        readable, _, _ = select.select([self._fd, self._wake_r], [], [], timeout)
        if self._stopping.is_set():
            raise _SimulationStoppedError
        if self._fd in readable:
            return self._receive(time.perf_counter())
        return False

    def _receive(self, now: float) -> bool:
        try:
            chunk = os.read(self._fd, _READ_SIZE)
        except BlockingIOError:
            return False
        except OSError as error:
            if error.errno != errno.EIO:
                raise
            chunk = b""
        if not chunk:  # no process has the other end open: wait for one
            select.select([self._wake_r], [], [], _HANGUP_RETRY_S)
            return False
        if not self._buffer:
            self._frame_start = now
            self._rx_end = now
            if self._transmitting:
                self._counters.collisions += 1
        self._rx_end = max(self._rx_end, now) + len(chunk) * self._char_time
        if self._echo:
            self._write_all(chunk)
        self._buffer += chunk
        if len(self._buffer) > _MAX_BUFFER:  # no master sends this: drop it, stay bounded
            self._counters.incomplete_frames += 1
            self._buffer.clear()
        return True

    def _wait_until(self, deadline: float) -> None:
        """Sleep, then spin, until ``deadline``, taking any input that arrives meanwhile."""
        while True:
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                return
            self._poll(remaining - _SPIN_S if remaining > _SPIN_S else 0)

    def _take_frame(self) -> tuple[bytes, float, float, float] | None:
        """Split the next request off the buffer: (frame, start, wire end, time it was known).

        Returns None when the bytes never made a frame before t3.5 of silence.
        """
        if self._ascii:
            return self._take_ascii_frame()
        buffer = self._buffer
        while True:
            expected = request_length(buffer)
            if expected is not None and expected != NEED_MORE and len(buffer) >= expected:
                start = self._frame_start
                frame = bytes(buffer[:expected])
                del buffer[:expected]
                if buffer:  # the next frame was sent back to back with this one
                    end = start + expected * self._char_time
                    self._frame_start = end
                else:
                    end = self._rx_end
                return frame, start, end, end
            silence_at = self._rx_end + self._silence
            while (remaining := silence_at - time.perf_counter()) > 0:
                if self._poll(remaining):
                    break
            else:
                if expected is None:  # length unknown: the silence ended the frame
                    frame = bytes(buffer)
                    buffer.clear()
                    return frame, self._frame_start, self._rx_end, silence_at
                self._counters.incomplete_frames += 1
                buffer.clear()
                return None

    def _take_ascii_frame(self) -> tuple[bytes, float, float, float] | None:
        """Split the next ASCII request off the buffer (':' to LF), as ``_take_frame``.

        Characters before a ':' are dropped; a ':' before the LF starts the frame again;
        a frame whose characters stop for the inter-character timeout is dropped.
        """
        buffer = self._buffer
        while True:
            colon = buffer.find(b":")
            if colon < 0:
                buffer.clear()
                return None
            del buffer[:colon]
            end = buffer.find(b"\n")
            again = buffer.find(b":", 1)
            if again >= 0 and (end < 0 or again < end):
                self._counters.incomplete_frames += 1
                del buffer[:again]
                continue
            if end >= 0:
                frame = bytes(buffer[: end + 1])
                del buffer[: end + 1]
                start = self._frame_start
                if buffer:
                    finish = start + len(frame) * self._char_time
                    self._frame_start = finish
                else:
                    finish = self._rx_end
                return frame, start, finish, finish
            if not self._poll(self._inter_char_timeout):
                self._counters.incomplete_frames += 1
                buffer.clear()
                return None

    def _decode(self, frame: bytes) -> tuple[int, bytes] | None:
        """The unit and PDU of a request frame, ``None`` when its checksum (or form) is bad."""
        if self._ascii:
            try:
                unit, pdu = decode_ascii(frame)
            except ResponseError:
                return None
            return unit, pdu
        if len(frame) < MIN_RTU_FRAME or not check_crc(frame):
            return None
        return frame[0], frame[1:-2]

    def _serve_frame(self, frame: bytes, start: float, end: float, known_at: float) -> None:
        counters = self._counters
        if self._char_time:
            gap = start - self._line_free_at
            counters.min_gap_s = min(counters.min_gap_s, gap)
            if gap < self._t35:
                counters.early_requests += 1
        self._line_free_at = end
        decoded = self._decode(frame)
        if decoded is None:
            counters.crc_errors_in += 1
            return
        if self._speed is not None and not self._at_our_speed():
            # A slave hears only noise from a master at another speed: it stays silent.
            counters.wrong_baudrate += 1
            return
        counters.requests += 1
        unit, pdu = decoded
        if unit == BROADCAST_UNIT:
            counters.broadcasts += 1
            for address, member in self._devices.items():
                if not self._faults[address].silent:
                    member.handle(pdu, broadcast=True)
            return
        device = self._devices.get(unit)
        if device is None:
            counters.foreign_frames += 1
            return
        faults = self._faults[unit]
        if faults.silent:
            counters.silent_drops += 1
            return
        response = device.handle(pdu)
        if response is None:
            return
        frames: list[bytes] = []
        if faults.garbage_before_reply:
            frames.append(bytes(faults.garbage_before_reply))
        if faults.wrong_unit_reply:
            frames.append(self._encode(unit % 247 + 1, response))
        answer = self._encode(unit, response)
        if faults.crc_error_rate > 0 and self._rng.random() < faults.crc_error_rate:
            if self._ascii:  # another LRC character: the frame still ends in CR LF
                wrong = b"0" if answer[-3:-2] != b"0" else b"1"
                answer = answer[:-3] + wrong + answer[-2:]
            else:
                answer = answer[:-1] + bytes((answer[-1] ^ 0xFF,))
            counters.crc_errors_out += 1
        frames.append(answer)
        counters.responses += 1
        begin = (known_at if self._char_time else time.perf_counter()) + self._turnaround
        begin += faults.reply_delay
        for data in frames:
            finish = begin + len(data) * self._char_time
            self._transmit_at(data, finish)
            self._line_free_at = finish
            # Frames sent one after the other keep t3.5 apart, so the master can tell them apart.
            begin = (finish if self._char_time else time.perf_counter()) + self._silence

    def _at_our_speed(self) -> bool:
        """True when the other end of the pty is set to this line's baud rate.

        A pty keeps the speed (not parity or data bits) set from either end, so
        a simulator can refuse a master at the wrong rate, as a real slave would.
        """
        try:
            speed = termios.tcgetattr(self._fd)[4]
        except termios.error:
            return True  # not a terminal (a socket pair in a test): nothing to compare
        return bool(speed == self._speed)

    def _transmit_at(self, data: bytes, finish: float) -> None:
        """Write ``data`` at the instant its transmission would end on the wire."""
        self._transmitting = True
        try:
            self._wait_until(finish)
        finally:
            self._transmitting = False
        lateness = time.perf_counter() - finish
        if lateness > self._counters.max_lateness_s:
            self._counters.max_lateness_s = lateness
        self._write_all(data)

    def _write_all(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                written = os.write(self._fd, view)
            except BlockingIOError:
                written = 0
            except OSError as error:
                if error.errno != errno.EIO:
                    raise
                return  # nobody has the other end open: the answer is lost, as on a dead line
            view = view[written:]
            if view:
                select.select([self._wake_r], [self._fd], [], None)
                if self._stopping.is_set():
                    raise _SimulationStoppedError
