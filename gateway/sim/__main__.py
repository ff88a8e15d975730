"""Run a simulated RTU bus in its own process: ``python -m gateway.sim --profile plc:1``.

Prints ``READY <path>`` once the pty is served (the path the gateway should
open: the ``--link`` symlink when given), serves until SIGTERM or SIGINT, then
prints the line's counters as one JSON line, so a benchmark can read both.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
from collections.abc import Sequence

from .device import SimulatedDevice
from .line import DEFAULT_TURNAROUND_S, SimulatedLine
from .profiles import PROFILES
from .pty import open_pty_pair

_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


def _profile(text: str) -> tuple[str, int]:
    name, _, unit = text.partition(":")
    if name not in PROFILES:
        raise argparse.ArgumentTypeError(
            f"unknown profile {name!r}; choose from {', '.join(sorted(PROFILES))}"
        )
    try:
        address = int(unit or "1")
    except ValueError:
        raise argparse.ArgumentTypeError(f"unit {unit!r} is not a number") from None
    if not 1 <= address <= 247:
        raise argparse.ArgumentTypeError(f"unit {address} outside 1..247")
    return name, address


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m gateway.sim",
        description="Serve simulated Modbus RTU or ASCII devices on a pty.",
    )
    parser.add_argument(
        "--profile",
        action="append",
        type=_profile,
        required=True,
        metavar="NAME:UNIT",
        help=f"a device to simulate ({', '.join(sorted(PROFILES))}); repeat for more",
    )
    parser.add_argument("--baudrate", type=int, help="pace answers like a line at this speed")
    parser.add_argument(
        "--turnaround",
        type=float,
        default=DEFAULT_TURNAROUND_S,
        help="seconds between a request's end and the answer's start (paced lines)",
    )
    parser.add_argument(
        "--strict-baudrate",
        action="store_true",
        help="answer only while the master's side is set to --baudrate (as a real slave)",
    )
    parser.add_argument("--link", help="make this symlink point at the pty device")
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="serve under SCHED_FIFO when permitted, for timing that ignores other load",
    )
    parser.add_argument(
        "--framing", choices=("rtu", "ascii"), default="rtu", help="the line's framing"
    )
    parser.add_argument(
        "--echo",
        action="store_true",
        help="echo every byte the master sends (a half-duplex adapter without echo suppression)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault injection")
    parser.add_argument(
        "--silent",
        action="append",
        type=int,
        default=[],
        metavar="UNIT",
        help="this unit never answers (a dead slave); repeat for more",
    )
    parser.add_argument(
        "--crc-error-rate",
        action="append",
        type=_unit_rate,
        default=[],
        metavar="UNIT:RATE",
        help="send this fraction of the unit's answers with a bad CRC; repeat for more",
    )
    return parser


def _unit_rate(text: str) -> tuple[int, float]:
    unit, _, rate = text.partition(":")
    try:
        pair = int(unit), float(rate)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not UNIT:RATE") from None
    if not 0.0 <= pair[1] <= 1.0:
        raise argparse.ArgumentTypeError(f"rate {pair[1]} outside 0..1")
    return pair


def _replace_symlink(target: str, link: str) -> None:
    """Point ``link`` at ``target`` atomically, replacing a stale link from an earlier run."""
    temporary = f"{link}.{os.getpid()}.tmp"
    os.symlink(target, temporary)
    os.replace(temporary, link)


def main(argv: Sequence[str] | None = None) -> int:
    """Serve until SIGTERM/SIGINT; return the exit status."""
    args = _parser().parse_args(argv)
    devices: dict[int, SimulatedDevice] = {}
    for name, unit in args.profile:
        if unit in devices:
            _parser().error(f"unit {unit} given twice")
        devices[unit] = PROFILES[name](unit)
    # Block the stop signals before the serving thread starts, so it inherits
    # the mask and only sigwait below sees them.
    signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    with open_pty_pair() as pair:
        line = SimulatedLine(
            pair.sim_fd,
            devices,
            baudrate=args.baudrate,
            turnaround=args.turnaround,
            seed=args.seed,
            realtime=args.realtime,
            strict_baudrate=args.strict_baudrate,
            framing=args.framing,
            echo=args.echo,
        )
        for unit in args.silent:
            if unit not in devices:
                _parser().error(f"--silent {unit}: no such unit")
            line.faults(unit).silent = True
        for unit, rate in args.crc_error_rate:
            if unit not in devices:
                _parser().error(f"--crc-error-rate {unit}: no such unit")
            line.faults(unit).crc_error_rate = rate
        path = pair.path
        if args.link:
            _replace_symlink(pair.path, args.link)
            path = args.link
        try:
            with line:
                print(f"READY {path}", flush=True)
                signal.sigwait(_STOP_SIGNALS)
        finally:
            if args.link and os.path.islink(args.link):
                os.unlink(args.link)
        print(json.dumps(dataclasses.asdict(line.stats())), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
