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
from collections.abc import Sequence
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
        self._rng = random.Random(seed ^ 0x5EED)
        self._heap: list[tuple[float, int, int, bytes]] = []
        self._sequence = 0
        self._busy: set[int] = set()
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

    def busy(self, unit: int) -> bool:
        """Whether ``unit`` is still preparing a late answer (and so deaf)."""
        if unit in self._busy:
            self.stats.ignored_busy += 1
            return True
        return False

    def decide(self, rule: LateRule, first: bool = False) -> float | None:
        """The delay for this read (``first``: the unit's first), or None to answer it on time."""
        if self._rng.random() >= rule.share and not (first and rule.first):
            return None
        return self._rng.uniform(rule.min_s, rule.max_s)

    def schedule(self, unit: int, response: bytes, delay: float) -> None:
        """Send ``response`` (a PDU) from ``unit`` ``delay`` seconds after now, paced."""
        frame = encode_rtu(unit, response)
        due = time.perf_counter() + self._turnaround + delay + len(frame) * self._character_time
        with self._wake:
            self._busy.add(unit)
            self._sequence += 1
            heapq.heappush(self._heap, (due, self._sequence, unit, frame))
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
                due, _, unit, frame = self._heap[0]
                remaining = due - time.perf_counter()
                if remaining > 0:
                    self._wake.wait(min(remaining, _WAIT_CAP_S))
                    continue
                heapq.heappop(self._heap)
            # OSError: nobody has the other end open; the answer is lost, as on a dead line.
            with contextlib.suppress(OSError):
                os.write(self._fd, frame)
            with self._wake:
                self._busy.discard(unit)
                self.stats.sent += 1
                key = str(unit)
                self.stats.by_unit[key] = self.stats.by_unit.get(key, 0) + 1


class BenchSlave(SimulatedDevice):
    """A slave with the self-checking register block; some of its reads may be answered late."""

    def __init__(self, unit: int) -> None:
        holding = {address: register_value(unit, address) for address in range(
            FIRST_REGISTER, END_REGISTER)}  # fmt: skip
        super().__init__(name=f"bench@{unit}", holding=DataBank(END_REGISTER, holding))
        self.unit = unit
        self.late_rule: LateRule | None = None
        self.late: LateAnswers | None = None
        self.reads = 0  #: reads answered so far

    def handle(self, pdu: bytes, *, broadcast: bool = False) -> bytes | None:
        """Answer now, or hand the answer to the late-answer thread (the line sends nothing)."""
        late, rule = self.late, self.late_rule
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
    if args.baudrate or args.link or args.late or args.crc_error_rate or args.framing != "rtu":
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
    for unit in [*args.silent, *(u for u, _ in args.crc_error_rate), *args.die_on_signal,
                 *(rule.unit for rule in args.late)]:  # fmt: skip
        if unit not in slaves:
            parser.error(f"unit {unit} is not served (add --unit {unit})")
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
        stats["died_at_monotonic"] = died_at
        print(json.dumps(stats), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
