"""The benchmark's simulated RTU line: ``python -m bench.slaves --unit 1 --unit 2 ...``.

The line itself is the gateway's simulator (``gateway.sim.SimulatedLine``: real-line
pacing, t3.5 and collision counters, silent slaves, bad CRCs), serving slaves whose
holding registers 1000..9999 hold ``bench.values.register_value(unit, address)``, so
the load generator can tell every request's answer from every other's. On top of it,
what the benchmark needs and a demo does not:

- ``--late UNIT:SHARE:MIN:MAX``: that share of the unit's reads is answered MIN..MAX
  seconds (uniform) after the request, like a slave whose response time sometimes
  exceeds the master's timeout. The slave is busy meanwhile: requests it receives
  before its late answer has gone are ignored, as a single-threaded device does.
  Other slaves keep answering; a late answer is written whole at the instant its
  last byte would leave the wire, by a thread of its own. Its wire time is not
  counted in the line's ``early_requests``: the master cannot foresee it.
  ``UNIT:SHARE:MIN:MAX:first``: the unit's first read is one of them too.
- ``--die-on-signal UNIT``: on SIGUSR1 the unit falls silent for good (a slave that
  dies in the middle of a run; the load generator sends the signal and notes when).
- ``--log-requests``: every request a slave executes is kept with its arrival time
  (``time.monotonic``, the same clock in every process) and its function, address and
  quantity, and printed with the counters (``requests_log``, up to 200,000 per slave):
  what reached the wire, counted where the wire ends.
- ``--response-time UNITS:PHASES``: one device answering the unit ids ``UNITS``
  (``1,2,3,4``) with a response time drawn per answer, by phase: ``5@0.005-0.038``
  draws the device's first 5 answers (over all its unit ids) uniformly from 5-38 ms,
  then the next phase; the last phase has no count and lasts (``1:30@0.01:0.4``: 30
  answers after 10 ms, then every one after 400 ms). The response time runs from
  the request's arrival to the first byte of the answer; the device is deaf on every
  one of its unit ids until its answer has gone, as a single-threaded device that
  scans its port once per cycle is, and the answer is written by the late-answer
  thread. The time each phase began (``time.perf_counter``) is reported.

Prints ``READY <path>`` once served, serves until SIGTERM or SIGINT, then prints the
line's counters and the late answers' as one JSON line.

``--modbus-tcp-listen HOST:PORT`` serves the same slaves as one Modbus TCP slave
(``gateway.sim.SimulatedTcpSlave``) instead of a pty: ``READY HOST:PORT``, then its
counters; ``--silent`` and ``--die-on-signal`` apply, the serial-line options do not.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import heapq
import json
import os
import random
import signal
import ssl
import sys
import threading
import time
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any

from gateway.config import parse_host_port
from gateway.core.rtu import encode_rtu
from gateway.sim import DataBank, SimulatedDevice, SimulatedLine, SimulatedTcpSlave, open_pty_pair
from gateway.sim.line import DEFAULT_TURNAROUND_S

from .values import END_REGISTER, FIRST_REGISTER, register_value

_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}
_READS = frozenset((1, 2, 3, 4))
_WAIT_CAP_S = 0.5  # the late-answer thread re-checks for a stop at least this often
_LOG_LIMIT = 200_000  # ``--log-requests``: requests kept per slave


@dataclass(frozen=True)
class LateRule:
    """``share`` of the unit's reads are answered ``min_s``..``max_s`` after the request."""

    unit: int
    share: float
    min_s: float
    max_s: float
    first: bool = False  #: the unit's first read is slow too


@dataclass
class LateStats:
    """What the late-answer thread did."""

    scheduled: int = 0  #: reads chosen to be answered late
    sent: int = 0  #: late answers written to the line
    ignored_busy: int = 0  #: requests that arrived while their slave prepared a late answer
    by_unit: dict[str, int] = field(default_factory=dict)  #: late answers sent, per unit


class LateAnswers:
    """Writes late answers at their time, from a thread of its own (the line thread never waits).

    One ``os.write`` per frame: the pty writes each call whole, so a late answer and
    the line thread's answers never interleave byte by byte.
    """

    def __init__(self, fd: int, character_time: float, turnaround: float, seed: int) -> None:
        self._fd = fd
        self._character_time = character_time
        self._turnaround = turnaround
        self.rng = random.Random(seed ^ 0x5EED)
        self._heap: list[tuple[float, int, Hashable, int, bytes]] = []
        self._sequence = 0
        self._busy: set[Hashable] = set()
        self._wake = threading.Condition()
        self._stopping = False
        self.stats = LateStats()
        self._thread = threading.Thread(target=self._run, name="late-answers", daemon=True)

    def start(self) -> None:
        """Start the writer thread."""
        self._thread.start()

    def stop(self) -> None:
        """Stop the writer thread; answers still pending are never sent."""
        with self._wake:
            self._stopping = True
            self._wake.notify()
        self._thread.join(5.0)

    def busy(self, key: Hashable, *, count: bool = True) -> bool:
        """Whether ``key`` (a unit, or a device's ``busy_key``) is still preparing a late answer
        (and so deaf); ``count``: count the request it ignores in ``ignored_busy``."""
        if key in self._busy:
            if count:
                self.stats.ignored_busy += 1
            return True
        return False

    def decide(self, rule: LateRule, first: bool = False) -> float | None:
        """The delay for this read (``first``: the unit's first), or None to answer it on time."""
        if self.rng.random() >= rule.share and not (first and rule.first):
            return None
        return self.rng.uniform(rule.min_s, rule.max_s)

    def schedule(
        self,
        unit: int,
        response: bytes,
        delay: float,
        *,
        busy_key: Hashable = None,
        at: float | None = None,
        after_turnaround: bool = True,
    ) -> None:
        """Send ``response`` (a PDU) from ``unit`` ``delay`` seconds after ``at`` (now), plus
        the line's turnaround unless ``after_turnaround`` is False, paced; ``busy_key`` (the
        unit by default) is deaf until it has gone."""
        frame = encode_rtu(unit, response)
        start = (time.perf_counter() if at is None else at) + delay
        if after_turnaround:
            start += self._turnaround
        due = start + len(frame) * self._character_time
        key = unit if busy_key is None else busy_key
        with self._wake:
            self._busy.add(key)
            self._sequence += 1
            heapq.heappush(self._heap, (due, self._sequence, key, unit, frame))
            self.stats.scheduled += 1
            self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                if self._stopping:
                    return
                if not self._heap:
                    self._wake.wait(_WAIT_CAP_S)
                    continue
                due, _, key, unit, frame = self._heap[0]
                remaining = due - time.perf_counter()
                if remaining > 0:
                    self._wake.wait(min(remaining, _WAIT_CAP_S))
                    continue
                heapq.heappop(self._heap)
            # OSError: nobody has the other end open; the answer is lost, as on a dead line.
            with contextlib.suppress(OSError):
                os.write(self._fd, frame)
            with self._wake:
                self._busy.discard(key)
                self.stats.sent += 1
                key = str(unit)
                self.stats.by_unit[key] = self.stats.by_unit.get(key, 0) + 1


@dataclass(frozen=True)
class ResponsePhase:
    """``answers`` answers (None: every later one) after ``min_s``..``max_s`` (uniform)."""

    answers: int | None
    min_s: float
    max_s: float


class ResponseProfile:
    """One device's response time by phase, shared by the unit ids it answers.

    Used by the line thread only (``next_delay``); the answers it times are written by
    ``LateAnswers``, which keeps the device deaf (``busy_key``) until each has gone.
    """

    def __init__(self, units: tuple[int, ...], phases: tuple[ResponsePhase, ...]) -> None:
        if not phases or phases[-1].answers is not None:
            raise ValueError("the last phase of a response-time profile has no count")
        if any(phase.answers is None or phase.answers < 1 for phase in phases[:-1]):
            raise ValueError("every phase but the last needs a count of at least 1")
        self.units = units
        self.phases = phases
        self.busy_key = ("device", units)
        self.answers = 0  #: answers timed so far, over every unit id
        self.ignored_busy = 0  #: requests that arrived while the device prepared an answer
        self.phase_started_at: list[float] = []  #: perf_counter of each phase's first answer

    def phase_index(self, answer: int) -> int:
        """The phase the ``answer``-th answer (0-based) falls in."""
        start = 0
        for index, phase in enumerate(self.phases):
            if phase.answers is None or answer < start + phase.answers:
                return index
            start += phase.answers
        raise AssertionError("the last phase has no count")

    def next_delay(self, rng: random.Random, now: float) -> float:
        """The response time of the next answer; counts it and stamps a phase's start."""
        index = self.phase_index(self.answers)
        self.answers += 1
        if index == len(self.phase_started_at):
            self.phase_started_at.append(now)
        phase = self.phases[index]
        return rng.uniform(phase.min_s, phase.max_s)

    def stats(self) -> dict[str, Any]:
        """What the profile did, for the simulator's JSON line."""
        return {
            "units": list(self.units),
            "answers": self.answers,
            "ignored_busy": self.ignored_busy,
            "phase_started_at": self.phase_started_at,
        }


def parse_response_profile(text: str) -> ResponseProfile:
    """``UNITS:PHASES`` (see the module docstring) as a profile; ValueError names the fault."""
    units_text, _, phases_text = text.partition(":")
    if not phases_text:
        raise ValueError(f"{text!r} is not UNITS:PHASES")
    try:
        units = tuple(int(unit) for unit in units_text.split(","))
    except ValueError:
        raise ValueError(f"{text!r}: the units are not numbers") from None
    if not all(1 <= unit <= 247 for unit in units) or len(set(units)) != len(units):
        raise ValueError(f"{text!r}: units must be distinct, 1..247")
    phases: list[ResponsePhase] = []
    for part in phases_text.split(":"):
        count_text, _, range_text = part.rpartition("@")
        low_text, _, high_text = range_text.partition("-")
        try:
            count = int(count_text) if count_text else None
            low = float(low_text)
            high = float(high_text) if high_text else low
        except ValueError:
            raise ValueError(f"{text!r}: phase {part!r} is not [COUNT@]MIN[-MAX]") from None
        if not 0.0 <= low <= high:
            raise ValueError(f"{text!r}: phase {part!r} needs 0 <= MIN <= MAX")
        phases.append(ResponsePhase(count, low, high))
    return ResponseProfile(units, tuple(phases))


def response_profile_argument(
    units: Sequence[int], phases: Sequence[tuple[int | None, float, float]]
) -> str:
    """The ``--response-time`` argument for ``units`` and (count or None, min s, max s) phases."""
    parts = [
        f"{'' if count is None else f'{count}@'}{low:g}-{high:g}" for count, low, high in phases
    ]
    return ",".join(str(unit) for unit in units) + ":" + ":".join(parts)


class BenchSlave(SimulatedDevice):
    """A slave with the self-checking register block; some of its reads may be answered late."""

    def __init__(self, unit: int) -> None:
        holding = {address: register_value(unit, address) for address in range(
            FIRST_REGISTER, END_REGISTER)}  # fmt: skip
        super().__init__(name=f"bench@{unit}", holding=DataBank(END_REGISTER, holding))
        self.unit = unit
        self.late_rule: LateRule | None = None
        self.late: LateAnswers | None = None
        self.profile: ResponseProfile | None = None
        self.reads = 0  #: reads answered so far
        #: ``--log-requests``: (arrival, function, address, quantity) of each request executed.
        self.log: list[tuple[float, int, int, int]] | None = None

    def handle(self, pdu: bytes, *, broadcast: bool = False) -> bytes | None:
        """Answer now, or hand the answer to the late-answer thread (the line sends nothing)."""
        log = self.log
        if log is not None and len(log) < _LOG_LIMIT and len(pdu) >= 5:
            address, quantity = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big")
            log.append((time.monotonic(), pdu[0], address, quantity))
        late, rule, profile = self.late, self.late_rule, self.profile
        if profile is not None and late is not None and not broadcast:
            self._answer_in_time(pdu, profile, late)
            return None  # the late-answer thread sends it
        if broadcast or late is None or rule is None:
            return super().handle(pdu, broadcast=broadcast)
        if late.busy(self.unit):
            return None
        response = super().handle(pdu)
        if response is None or not pdu or pdu[0] not in _READS:
            return response
        delay = late.decide(rule, first=self.reads == 0)
        self.reads += 1
        if delay is None:
            return response
        late.schedule(self.unit, response, delay)
        return None

    def _answer_in_time(self, pdu: bytes, profile: ResponseProfile, late: LateAnswers) -> None:
        """Answer after the profile's next response time; deaf while the device is busy."""
        if late.busy(profile.busy_key, count=False):
            profile.ignored_busy += 1
            return
        response = super().handle(pdu)
        if response is not None:
            now = time.perf_counter()
            delay = profile.next_delay(late.rng, now)
            late.schedule(self.unit, response, delay, busy_key=profile.busy_key, at=now,
                          after_turnaround=False)  # fmt: skip


def _unit(text: str) -> int:
    try:
        unit = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"unit {text!r} is not a number") from None
    if not 1 <= unit <= 247:
        raise argparse.ArgumentTypeError(f"unit {unit} outside 1..247")
    return unit


def _unit_rate(text: str) -> tuple[int, float]:
    unit, _, rate = text.partition(":")
    try:
        pair = _unit(unit), float(rate)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not UNIT:RATE") from None
    if not 0.0 <= pair[1] <= 1.0:
        raise argparse.ArgumentTypeError(f"rate {pair[1]} outside 0..1")
    return pair


def _late_rule(text: str) -> LateRule:
    parts = text.split(":")
    first = parts[-1] == "first"
    if first:
        parts.pop()
    try:
        unit, share, low, high = _unit(parts[0]), *(float(part) for part in parts[1:])
    except (ValueError, TypeError, IndexError):
        raise argparse.ArgumentTypeError(f"{text!r} is not UNIT:SHARE:MIN:MAX") from None
    if not 0.0 <= share <= 1.0 or not 0.0 <= low <= high:
        raise argparse.ArgumentTypeError(f"{text!r}: need 0 <= SHARE <= 1 and 0 <= MIN <= MAX")
    return LateRule(unit, share, low, high, first)


def _response_profile(text: str) -> ResponseProfile:
    try:
        return parse_response_profile(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m bench.slaves", description=__doc__.splitlines()[0] if __doc__ else None
    )
    parser.add_argument("--unit", action="append", type=_unit, required=True, metavar="UNIT")
    parser.add_argument("--baudrate", type=int, help="pace answers like a line at this speed")
    parser.add_argument("--turnaround", type=float, default=DEFAULT_TURNAROUND_S)
    parser.add_argument("--link", help="make this symlink point at the pty device")
    parser.add_argument("--realtime", action="store_true", help="SCHED_FIFO when permitted")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--framing", choices=("rtu", "ascii"), default="rtu")
    parser.add_argument("--silent", action="append", type=_unit, default=[], metavar="UNIT")
    parser.add_argument(
        "--crc-error-rate", action="append", type=_unit_rate, default=[], metavar="UNIT:RATE"
    )
    parser.add_argument(
        "--late", action="append", type=_late_rule, default=[], metavar="UNIT:SHARE:MIN:MAX"
    )
    parser.add_argument(
        "--die-on-signal", action="append", type=_unit, default=[], metavar="UNIT",
        help="this unit falls silent on SIGUSR1",
    )  # fmt: skip
    parser.add_argument(
        "--log-requests",
        action="store_true",
        help="keep every request executed, with its arrival time, and print them at the end",
    )
    parser.add_argument(
        "--response-time", action="append", type=_response_profile, default=[],
        metavar="UNITS:PHASES",
        help="one device answering UNITS (1,2,3,4) after a response time drawn by phase: "
        "COUNT@MIN-MAX for its next COUNT answers, the last phase MIN-MAX for good",
    )  # fmt: skip
    parser.add_argument(
        "--modbus-tcp-listen", metavar="HOST:PORT", help="serve as a Modbus TCP slave, no pty"
    )
    parser.add_argument("--tls-cert", metavar="FILE",
                        help="with --modbus-tcp-listen: serve Modbus/TCP Security with this "
                        "certificate chain (and --tls-key, --tls-ca; client certificates "
                        "required)")  # fmt: skip
    parser.add_argument("--tls-key", metavar="FILE")
    parser.add_argument("--tls-ca", metavar="FILE")
    return parser


def _tls_context(args: argparse.Namespace) -> ssl.SSLContext | None:
    """The server context of ``--tls-cert/--tls-key/--tls-ca`` (None without them)."""
    if args.tls_cert is None:
        return None
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_cert_chain(args.tls_cert, args.tls_key)
    context.load_verify_locations(cafile=args.tls_ca)
    context.verify_mode = ssl.CERT_REQUIRED
    return context


def _serve_tcp(
    parser: argparse.ArgumentParser, args: argparse.Namespace, slaves: dict[int, BenchSlave]
) -> int:
    """The slaves as one Modbus TCP slave until SIGTERM/SIGINT (SIGUSR1: ``--die-on-signal``)."""
    serial_only = args.late or args.crc_error_rate or args.response_time
    if args.baudrate or args.link or serial_only or args.framing != "rtu":
        parser.error("--modbus-tcp-listen takes only --unit, --silent and --die-on-signal")
    try:
        host, port = parse_host_port(args.modbus_tcp_listen)
    except ValueError as error:
        parser.error(f"--modbus-tcp-listen: {error}")
    waited = _STOP_SIGNALS | {signal.SIGUSR1}
    died_at: float | None = None
    slave = SimulatedTcpSlave(
        dict(slaves), host=host, port=port, direct_unit=False, ssl=_tls_context(args)
    )
    for unit in args.silent:
        slave.faults(unit).silent = True
    with slave:
        print(f"READY {slave.host_port}", flush=True)
        while signal.sigwait(waited) == signal.SIGUSR1:
            for unit in args.die_on_signal:
                slave.faults(unit).silent = True
            if died_at is None:
                died_at = time.monotonic()
    stats: dict[str, Any] = dataclasses.asdict(slave.stats())
    stats["died_at_monotonic"] = died_at
    print(json.dumps(stats), flush=True)
    return 0


def _replace_symlink(target: str, link: str) -> None:
    temporary = f"{link}.{os.getpid()}.tmp"
    os.symlink(target, temporary)
    os.replace(temporary, link)


def main(argv: Sequence[str] | None = None) -> int:
    """Serve until SIGTERM/SIGINT; return the exit status."""
    parser = _parser()
    args = parser.parse_args(argv)
    if len(set(args.unit)) != len(args.unit):
        parser.error("a unit is given twice")
    slaves = {unit: BenchSlave(unit) for unit in args.unit}
    if args.log_requests:
        for slave in slaves.values():
            slave.log = []
    profiled = [unit for profile in args.response_time for unit in profile.units]
    for unit in [*args.silent, *(u for u, _ in args.crc_error_rate), *args.die_on_signal,
                 *(rule.unit for rule in args.late), *profiled]:  # fmt: skip
        if unit not in slaves:
            parser.error(f"unit {unit} is not served (add --unit {unit})")
    if len(set(profiled)) != len(profiled):
        parser.error("a unit is in two --response-time devices")
    if set(profiled) & {rule.unit for rule in args.late}:
        parser.error("a unit takes --late or --response-time, not both")
    tls = (args.tls_cert, args.tls_key, args.tls_ca)
    if any(tls) and (not all(tls) or args.modbus_tcp_listen is None):
        parser.error("--tls-cert, --tls-key and --tls-ca go together, with --modbus-tcp-listen")
    waited = _STOP_SIGNALS | {signal.SIGUSR1}
    signal.pthread_sigmask(signal.SIG_BLOCK, waited)  # threads inherit the mask
    if args.modbus_tcp_listen is not None:
        return _serve_tcp(parser, args, slaves)
    died_at: float | None = None
    with open_pty_pair() as pair:
        line = SimulatedLine(
            pair.sim_fd,
            dict(slaves),
            baudrate=args.baudrate,
            turnaround=args.turnaround,
            seed=args.seed,
            realtime=args.realtime,
            framing=args.framing,
        )
        for unit in args.silent:
            line.faults(unit).silent = True
        for unit, rate in args.crc_error_rate:
            line.faults(unit).crc_error_rate = rate
        late = LateAnswers(
            pair.sim_fd,
            line.character_time,
            args.turnaround if args.baudrate else 0.0,
            args.seed,
        )
        for rule in args.late:
            slaves[rule.unit].late_rule = rule
            slaves[rule.unit].late = late
        for profile in args.response_time:
            for unit in profile.units:
                slaves[unit].profile = profile
                slaves[unit].late = late
        path = pair.path
        if args.link:
            _replace_symlink(pair.path, args.link)
            path = args.link
        try:
            with line:
                late.start()
                print(f"READY {path}", flush=True)
                while signal.sigwait(waited) == signal.SIGUSR1:
                    for unit in args.die_on_signal:
                        line.faults(unit).silent = True
                    if died_at is None:
                        died_at = time.monotonic()
                late.stop()
        finally:
            if args.link and os.path.islink(args.link):
                os.unlink(args.link)
        stats: dict[str, Any] = dataclasses.asdict(line.stats())
        stats["late"] = dataclasses.asdict(late.stats)
        stats["response_time"] = [profile.stats() for profile in args.response_time]
        stats["died_at_monotonic"] = died_at
        if args.log_requests:
            stats["requests_log"] = {str(unit): slave.log for unit, slave in slaves.items()}
        print(json.dumps(stats), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
