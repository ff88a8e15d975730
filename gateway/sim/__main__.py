"""Run a simulated RTU bus in its own process: ``python -m gateway.sim --profile plc:1``.

Prints ``READY <path>`` once the pty is served (the path the gateway should
open: the ``--link`` symlink when given), serves until SIGTERM or SIGINT, then
prints the line's counters as one JSON line, so a benchmark can read both.
With ``--modbus-tcp-listen HOST:PORT`` the devices are a Modbus TCP slave
instead (``python -m gateway.sim --modbus-tcp-listen 127.0.0.1:1502 --profile r6``):
``READY HOST:PORT`` names the address bound (port 0 picks one); ``--tls-cert`` and
``--tls-key`` (and ``--tls-ca`` for client certificates) make it Modbus/TCP Security.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import ssl
import sys
from collections.abc import Sequence

from gateway.config import parse_host_port

from .device import SimulatedDevice
from .line import DEFAULT_TURNAROUND_S, SimulatedLine
from .profiles import PROFILES
from .pty import open_pty_pair
from .tcp import SimulatedTcpSlave

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
        description="Serve simulated Modbus RTU or ASCII devices on a pty, or a Modbus TCP slave.",
    )
    _add_tcp_options(parser)
    parser.add_argument(
        "--profile",
        action="append",
        type=_profile,
        required=True,
        metavar="NAME:UNIT",
        help=f"a device to simulate ({', '.join(sorted(PROFILES))}); repeat for more",
    )
    _add_line_options(parser)
    _add_fault_options(parser)
    return parser


def _add_tcp_options(parser: argparse.ArgumentParser) -> None:
    """Options of the Modbus TCP (and Modbus/TCP Security) slave, instead of a pty."""
    parser.add_argument(
        "--modbus-tcp-listen",
        type=_listen_address,
        metavar="HOST:PORT",
        help="serve the devices as a Modbus TCP slave here instead of on a pty "
        "(one device also answers unit id 255)",
    )
    parser.add_argument(
        "--tls-cert",
        metavar="FILE",
        help="with --modbus-tcp-listen: serve Modbus/TCP Security (TLS) with this certificate "
        "chain, PEM",
    )
    parser.add_argument("--tls-key", metavar="FILE", help="the private key of --tls-cert, PEM")
    parser.add_argument(
        "--tls-ca",
        metavar="FILE",
        help="require client certificates issued by this CA (Modbus/TCP Security's mutual "
        "authentication)",
    )


def _add_line_options(parser: argparse.ArgumentParser) -> None:
    """Options of the simulated serial line: pacing, framing, the device path."""
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


def _add_fault_options(parser: argparse.ArgumentParser) -> None:
    """Fault injection: dead units and corrupted answers."""
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


def _listen_address(text: str) -> tuple[str, int]:
    try:
        return parse_host_port(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT ({error})") from None


_SERIAL_ONLY = ("baudrate", "link", "echo", "strict_baudrate", "realtime", "crc_error_rate")


def _serve_tcp(args: argparse.Namespace, devices: dict[int, SimulatedDevice]) -> int:
    """Serve ``devices`` as one Modbus TCP slave until SIGTERM/SIGINT."""
    for name in _SERIAL_ONLY:
        if getattr(args, name):
            _parser().error(f"--{name.replace('_', '-')} is for pty lines, not --modbus-tcp-listen")
    if args.framing != "rtu":
        _parser().error("--framing is for pty lines, not --modbus-tcp-listen")
    host, port = args.modbus_tcp_listen
    slave = SimulatedTcpSlave(devices, host=host, port=port, ssl=_tls_context(args))
    for unit in args.silent:
        if unit not in devices:
            _parser().error(f"--silent {unit}: no such unit")
        slave.faults(unit).silent = True
    with slave:
        print(f"READY {slave.host_port}", flush=True)
        signal.sigwait(_STOP_SIGNALS)
    print(json.dumps(dataclasses.asdict(slave.stats())), flush=True)
    return 0


def _tls_context(args: argparse.Namespace) -> ssl.SSLContext | None:
    """The server context of ``--tls-cert/--tls-key/--tls-ca``, None for plain Modbus TCP."""
    if not (args.tls_cert or args.tls_key or args.tls_ca):
        return None
    if not (args.tls_cert and args.tls_key):
        _parser().error("--tls-cert and --tls-key go together")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2  # Modbus/TCP Security: TLS 1.2 or later
    try:
        context.load_cert_chain(args.tls_cert, args.tls_key)
        if args.tls_ca:
            context.load_verify_locations(cafile=args.tls_ca)
            context.verify_mode = ssl.CERT_REQUIRED
    except (OSError, ssl.SSLError) as error:
        _parser().error(f"TLS files: {error}")
    return context


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
    if args.modbus_tcp_listen is not None:
        return _serve_tcp(args, devices)
    if args.tls_cert or args.tls_key or args.tls_ca:
        _parser().error("--tls-cert, --tls-key and --tls-ca need --modbus-tcp-listen")
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
