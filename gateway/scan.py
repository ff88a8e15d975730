"""``modbus-gateway scan``: commission a line by finding who answers, and at which settings.

One harmless read per address (FC 3, one holding register at address 0; any
answer, an exception included, shows a slave is there), a short timeout, then
for every slave found its device identification (FC 43/14, basic objects) and
server id (FC 17) where it answers them. ``--baudrate auto`` tries the common
baud rates and parities, most common first, until one gets an answer.

The port is opened exactly as the gateway opens it (``open_serial``), so a
device a running gateway holds is refused the same way, naming the holder.
This runs without an event loop: it is a short, interactive command.
"""

from __future__ import annotations

import argparse
import contextlib
import enum
import json
import re
import socket
import ssl
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Protocol, TextIO, cast

import serial

from .config import NETWORK_LINE_KINDS, ConfigError, LineConfig, build_config, read_config_file
from .core import pdu as fc
from .core.errors import ResponseError
from .core.framing import framing_for
from .core.timing import character_time
from .io.links.serial_port import DeviceBusyError, SerialPortError, open_serial
from .io.links.tls import client_context
from .io.tls_setup import TlsSetupError

#: Baud rates ``--baudrate auto`` tries, the most common on Modbus lines first.
AUTO_BAUDRATES = (9600, 19200, 38400, 57600, 115200, 4800, 2400, 1200)
#: Parity and stop bits it tries at each rate: 8E1 is the Modbus default, 8N2 its no-parity form.
AUTO_FORMATS = (("E", 1), ("N", 1), ("O", 1), ("N", 2))
#: The harmless read: one holding register at address 0.
PROBE = bytes.fromhex("03 0000 0001")
_MAX_IDENTIFICATION_REQUESTS = 8
_READ_CHUNK = 4096
#: Exceptions a gateway answers for a unit nobody serves (gateway path unavailable, target
#: failed to respond): a Modbus TCP slave that is itself a gateway says "nobody" this way.
_NOBODY_THERE = frozenset({0x0A, 0x0B})


class Answer(enum.Enum):
    """What came back to one request."""

    NORMAL = "ok"
    EXCEPTION = "exception"  # a Modbus exception: the slave is there
    GARBLED = "garbled"  # bytes that are no answer: wrong settings, noise, two slaves
    SILENT = "silent"


@dataclass(frozen=True, slots=True)
class Settings:
    """A line format."""

    baudrate: int
    parity: str
    stop_bits: int

    def __str__(self) -> str:
        return f"{self.baudrate} 8{self.parity}{self.stop_bits}"


@dataclass(slots=True)
class Slave:
    """One address that answered."""

    address: int
    answer: Answer
    detail: str  # "ok", or the exception code
    identification: dict[int, str] = field(default_factory=dict)  # FC 43/14 object id → text
    server_id: str | None = None  # FC 17, printable text or hex


@dataclass(slots=True)
class Tried:
    """One line format tried by ``--baudrate auto``."""

    settings: Settings
    result: str  # "answers", "no answer", "garbled answers", "cannot set: ..."


@dataclass(slots=True)
class ScanResult:
    """Everything the scan found."""

    device: str
    settings: Settings | None  # None when no format got an answer
    slaves: list[Slave]
    tried: list[Tried]
    garbled: list[int]  # addresses that got bytes that were no answer
    kind: str = "rtu"  # the line's kind: a network kind has no serial format of its own

    @property
    def where(self) -> str:
        """``/dev/ttyUSB0 at 9600 8E1``, or ``10.0.0.5:502 (tcp)`` on a network line."""
        if self.kind in NETWORK_LINE_KINDS:
            return f"{self.device} ({self.kind})"
        return f"{self.device} at {self.settings}"


class Progress:
    """A progress bar on stderr when it is a terminal, one line per format otherwise."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.live = stream.isatty()

    def step(self, settings: Settings, done: int, total: int, found: int) -> None:
        if not self.live:
            return
        width = 30
        filled = width * done // max(total, 1)
        self.stream.write(
            f"\r{settings} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}, {found} found "
        )
        self.stream.flush()

    def note(self, text: str) -> None:
        if self.live:
            self.stream.write("\r\033[K")
        self.stream.write(text + "\n")
        self.stream.flush()


class ScanWire(Protocol):
    """The bytes of one line, whatever carries them: a serial port or a TCP/TLS connection."""

    def write(self, data: bytes) -> None: ...

    def read(self, timeout: float) -> bytes:
        """What arrives within ``timeout`` seconds (at least one byte), or ``b""``."""
        ...

    def discard_input(self) -> None: ...

    def close(self) -> None: ...


class SerialScanWire:
    """A serial device or pyserial URL, opened exactly as the gateway opens it."""

    def __init__(self, line: LineConfig) -> None:
        # Every port type pyserial opens (device, socket://, rfc2217://) has these methods.
        self.port = cast(serial.Serial, open_serial(line))

    def write(self, data: bytes) -> None:
        self.port.write(data)

    def read(self, timeout: float) -> bytes:
        port = self.port
        port.timeout = timeout
        data = bytes(port.read(1))
        if data:
            port.timeout = 0
            data += port.read(port.in_waiting or 0)
        return data

    def discard_input(self) -> None:
        self.port.reset_input_buffer()

    def close(self) -> None:
        self.port.close()


class SocketScanWire:
    """A TCP connection (``rtu-over-tcp``, ``tcp``) or a TLS session (``tls``) to the line."""

    def __init__(self, line: LineConfig) -> None:
        sock = socket.create_connection((line.host, line.port), timeout=line.connect_timeout)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if line.kind == "tls":
            context = client_context(line).context
            sock.settimeout(line.tls_handshake_timeout)
            try:
                sock = context.wrap_socket(sock, server_hostname=line.server_name or line.host)
            except BaseException:
                sock.close()
                raise
        self.sock = sock
        self.where = line.device

    def write(self, data: bytes) -> None:
        self.sock.settimeout(None)
        self.sock.sendall(data)

    def read(self, timeout: float) -> bytes:
        self.sock.settimeout(max(timeout, 0.001))
        try:
            data = self.sock.recv(_READ_CHUNK)
        except TimeoutError:
            return b""
        if not data:
            raise ConnectionError(f"{self.where} closed the connection")
        return data

    def discard_input(self) -> None:
        """Drop a late answer still buffered, so it is never taken for the next one."""
        self.sock.setblocking(False)
        with contextlib.suppress(BlockingIOError, ssl.SSLWantReadError):
            while self.sock.recv(_READ_CHUNK):
                pass

    def close(self) -> None:
        self.sock.close()


def open_wire(line: LineConfig) -> ScanWire:
    """The line's wire: a connection for a network kind, else its serial port."""
    return SocketScanWire(line) if line.networked else SerialScanWire(line)


class Port:
    """An open line: one request at a time in the line's framing, the frame gap kept before each."""

    def __init__(self, line: LineConfig, timeout: float) -> None:
        self.line = line
        self.timeout = timeout
        self.framing = framing_for(line.kind)
        self.wire = open_wire(line)
        self._char = 0.0
        if not line.networked:  # the request's own transmission time counts on a serial line
            self._char = character_time(line.baudrate, line.data_bits, line.parity, line.stop_bits)
        self._gap = line.gap
        self._silence = line.silence

    def close(self) -> None:
        self.wire.close()

    def transact(self, address: int, pdu: bytes) -> tuple[Answer, bytes]:
        """Send ``pdu`` to ``address`` and wait for its answer (or the timeout)."""
        wire = self.wire
        if self._gap:
            time.sleep(self._gap)  # the line must be silent for t3.5 before a request
        wire.discard_input()
        frame = self.framing.encode(address, pdu)
        wire.write(frame)
        decoder = self.framing.decoder(address, pdu)
        deadline = time.monotonic() + len(frame) * self._char + self.timeout
        received = False
        while (remaining := deadline - time.monotonic()) > 0:
            ends_on_silence = decoder.buffered and decoder.waits_for_silence
            data = wire.read(min(remaining, self._silence) if ends_on_silence else remaining)
            try:
                if not data:
                    result = decoder.end_of_frame() if ends_on_silence else None
                else:
                    received = True
                    result = decoder.feed(data)
            except ResponseError:
                return Answer.GARBLED, b""
            if result is not None:
                return _answer(result.pdu)
        return (Answer.GARBLED if received else Answer.SILENT), b""


def _answer(pdu: bytes) -> tuple[Answer, bytes]:
    if fc.is_exception(pdu) and len(pdu) > 1 and pdu[1] in _NOBODY_THERE:
        return Answer.SILENT, b""  # a gateway on the way says no slave answers at that unit
    return (Answer.EXCEPTION if fc.is_exception(pdu) else Answer.NORMAL), pdu


def _printable(data: bytes) -> str:
    text = data.decode("latin-1")
    if data and all(32 <= byte < 127 for byte in data):
        return text
    return data.hex(" ")


def identify(port: Port, slave: Slave) -> None:
    """Ask ``slave`` for FC 43/14 (basic objects) and FC 17; keep what it answers."""
    next_object = 0
    for _ in range(_MAX_IDENTIFICATION_REQUESTS):
        answer, pdu = port.transact(slave.address, bytes((0x2B, 0x0E, 0x01, next_object)))
        if answer is not Answer.NORMAL or len(pdu) < 7:
            break
        more, next_object, count = pdu[4], pdu[5], pdu[6]
        position = 7
        for _ in range(count):
            if position + 2 > len(pdu):
                break
            object_id, length = pdu[position], pdu[position + 1]
            slave.identification[object_id] = _printable(pdu[position + 2 : position + 2 + length])
            position += 2 + length
        if more != 0xFF:
            break
    answer, pdu = port.transact(slave.address, bytes((fc.REPORT_SERVER_ID,)))
    if answer is Answer.NORMAL and len(pdu) >= 2:
        data = pdu[2 : 2 + pdu[1]]
        run = ""
        if data and data[-1] in (0x00, 0xFF):
            run = " (running)" if data[-1] == 0xFF else " (stopped)"
            data = data[:-1]
        slave.server_id = _printable(data) + run


def _line_with(line: LineConfig, settings: Settings) -> LineConfig:
    return replace(
        line, baudrate=settings.baudrate, parity=settings.parity, stop_bits=settings.stop_bits
    )


def scan(
    line: LineConfig,
    addresses: Sequence[int],
    timeout: float,
    candidates: Sequence[Settings] | None,
    progress: Progress,
    identification: bool = True,
) -> ScanResult:
    """Scan ``addresses`` on ``line``; with ``candidates``, find the format first."""
    tried: list[Tried] = []
    chosen = Settings(line.baudrate, line.parity, int(line.stop_bits))
    answers: dict[int, tuple[Answer, bytes]] = {}
    if candidates is not None:
        found = None
        for settings in candidates:
            result, answers = _probe(line, settings, addresses, timeout, progress)
            tried.append(Tried(settings, result))
            progress.note(f"{settings}: {result}")
            if result == "answers":
                found = settings
                break
        if found is None:
            return ScanResult(line.device, None, [], tried, [], line.kind)
        chosen = found
    port = Port(_line_with(line, chosen), timeout)
    try:
        slaves: list[Slave] = []
        garbled: list[int] = []
        for done, address in enumerate(addresses, 1):
            answer, pdu = answers.get(address) or port.transact(address, PROBE)
            if answer in (Answer.NORMAL, Answer.EXCEPTION):
                detail = "ok" if answer is Answer.NORMAL else f"exception 0x{pdu[1]:02X}"
                slaves.append(Slave(address, answer, detail))
            elif answer is Answer.GARBLED:
                garbled.append(address)
            progress.step(chosen, done, len(addresses), len(slaves))
        if identification:
            for slave in slaves:
                identify(port, slave)
    finally:
        port.close()
    scanned = ScanResult(line.device, chosen, slaves, tried, garbled, line.kind)
    progress.note(f"{scanned.where}: {len(slaves)} slave(s) answer")
    return scanned


def _probe(
    line: LineConfig,
    settings: Settings,
    addresses: Sequence[int],
    timeout: float,
    progress: Progress,
) -> tuple[str, dict[int, tuple[Answer, bytes]]]:
    """Try one format until an address answers; the answers so far are kept for the scan."""
    try:
        port = Port(_line_with(line, settings), timeout)
    except SerialPortError as error:
        if "cannot set" in str(error):
            return "not supported by this port", {}
        raise
    answers: dict[int, tuple[Answer, bytes]] = {}
    garbled = False
    try:
        for done, address in enumerate(addresses, 1):
            answer, _pdu = answers[address] = port.transact(address, PROBE)
            progress.step(settings, done, len(addresses), 0)
            if answer in (Answer.NORMAL, Answer.EXCEPTION):
                return "answers", answers
            garbled = garbled or answer is Answer.GARBLED
    finally:
        port.close()
    return ("garbled answers" if garbled else "no answer"), {}


def format_table(result: ScanResult) -> str:
    """The table printed at the end."""
    out = []
    if result.settings is None:
        out.append(f"{result.device}: no slave answered at any format tried:")
        out.extend(f"  {tried.settings}: {tried.result}" for tried in result.tried)
        return "\n".join(out)
    out.append(f"{result.where}: {len(result.slaves)} slave(s)")
    rows = [("address", "answer", "device identification (FC 43/14)", "server id (FC 17)")]
    for slave in result.slaves:
        ident = " ".join(result_text for _, result_text in sorted(slave.identification.items()))
        rows.append((str(slave.address), slave.detail, ident or "-", slave.server_id or "-"))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    for row in rows:
        out.append(
            "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        )
    if result.garbled:
        out.append(
            "garbled answers (noise, or two slaves at one address) from: "
            + ", ".join(map(str, result.garbled))
        )
    if result.tried:
        out.append("formats tried (--baudrate auto):")
        out.extend(f"  {tried.settings}: {tried.result}" for tried in result.tried)
    return "\n".join(out)


def _addresses(text: str) -> list[int]:
    addresses: set[int] = set()
    for part in text.split(","):
        low, _, high = part.strip().partition("-")
        try:
            first, last = int(low), int(high or low)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{part!r} is not an address or a range like 1-247"
            ) from None
        if not 1 <= first <= last <= 247:
            raise argparse.ArgumentTypeError(f"{part!r}: slave addresses are 1..247")
        addresses.update(range(first, last + 1))
    return sorted(addresses)


def _baudrate(text: str) -> int | None:
    if text == "auto":
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a baud rate, or 'auto'") from None


def build_parser() -> argparse.ArgumentParser:
    """The ``modbus-gateway scan`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="modbus-gateway scan",
        description="Find the slaves that answer on a serial line (and its settings).",
    )
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--serial", metavar="DEVICE_OR_URL", help="the serial device to scan")
    where.add_argument("--config", metavar="FILE", help="take the line from this file (--line)")
    parser.add_argument("--line", metavar="NAME", help="the line of --config to scan")
    parser.add_argument(
        "--baudrate",
        type=_baudrate,
        default=argparse.SUPPRESS,
        metavar="N|auto",
        help="baud rate, or 'auto' to try the common ones "
        "(default: the line's, 9600 with --serial)",
    )
    parser.add_argument("--parity", choices=["N", "E", "O"], help="parity (default: the line's)")
    parser.add_argument("--stopbits", type=int, choices=[1, 2], help="stop bits")
    parser.add_argument(
        "--range",
        type=_addresses,
        default=list(range(1, 248)),
        metavar="1-247",
        help="addresses to try, e.g. 1-20,100 (default 1-247)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=0.1,
        metavar="SECONDS",
        help="wait per address (default 0.1)",
    )
    parser.add_argument(
        "--no-identify", action="store_true", help="skip FC 43/14 and FC 17 for the slaves found"
    )
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    return parser


def _line(args: argparse.Namespace) -> LineConfig:
    if args.serial:
        line = LineConfig(name="scan", device=args.serial)
    else:
        config = build_config(read_config_file(args.config), args.config)
        lines = {line.name: line for line in config.lines}
        if args.line is None and len(lines) == 1:
            line = next(iter(lines.values()))
        elif args.line in lines:
            line = lines[args.line]
        else:
            raise ConfigError(
                args.config,
                [f"--line {args.line!r}: choose one of {', '.join(sorted(lines))}"],
            )
    changes: dict[str, Any] = {}
    if getattr(args, "baudrate", None):
        changes["baudrate"] = args.baudrate
    if args.parity:
        changes["parity"] = args.parity
    if args.stopbits:
        changes["stop_bits"] = args.stopbits
    return replace(line, **changes)


def main(argv: Sequence[str], stderr: TextIO | None = None) -> int:
    """Run the scan; 0 when a slave answered, 1 when none did or the port failed, 2 on bad input."""
    args = build_parser().parse_args(argv)
    errors = stderr or sys.stderr
    if args.config and not args.line:
        args.line = None
    try:
        line = _line(args)
        candidates = _candidates(args, line)
    except ConfigError as error:
        print(f"modbus-gateway scan: {error}", file=errors)
        return 2
    progress = Progress(errors)
    progress.note(
        f"scanning {line.device}: addresses {_ranges(args.range)}, {args.timeout:g} s each"
    )
    result = _scan_reporting_errors(line, args, candidates, progress)
    if result is None:
        return 1
    report: Callable[[ScanResult], str] = _json if args.json else format_table
    print(report(result))
    return 0 if result.slaves else 1


def _candidates(args: argparse.Namespace, line: LineConfig) -> list[Settings] | None:
    """The formats ``--baudrate auto`` tries; None without it. Only a serial line has them."""
    if not hasattr(args, "baudrate") or args.baudrate is not None:
        return None
    if line.networked:
        where = "the device server's serial side" if line.kind == "rtu-over-tcp" else "nothing"
        raise ConfigError(
            "--baudrate auto",
            [
                f"line {line.name!r} is a {line.kind} line, whose baud rate is set on {where}: "
                "scan it without --baudrate"
            ],
        )
    formats = [
        (p, s)
        for p, s in AUTO_FORMATS
        if (args.parity is None or p == args.parity)
        and (args.stopbits is None or s == args.stopbits)
    ]
    if not formats:
        formats = [(args.parity or "N", args.stopbits or 1)]
    return [Settings(b, p, s) for b in AUTO_BAUDRATES for p, s in formats]


def _scan_reporting_errors(
    line: LineConfig,
    args: argparse.Namespace,
    candidates: list[Settings] | None,
    progress: Progress,
) -> ScanResult | None:
    """The scan's result, or None once its failure is told as a sentence with the fix."""
    try:
        return scan(line, args.range, args.timeout, candidates, progress, not args.no_identify)
    except DeviceBusyError as error:
        held = re.search(r" is in use by (.*?); ", str(error))
        holder = held[1] if held else "another program"
        progress.note(
            f"modbus-gateway scan: {line.device} is in use by {holder}; a scan is a second "
            "master on the line: stop the gateway (or that program) first."
        )
    except TlsSetupError as error:
        progress.note(f"modbus-gateway scan: {error}.")
    except (SerialPortError, serial.SerialException) as error:
        progress.note(f"modbus-gateway scan: {error}")
    except OSError as error:
        if not line.networked:
            progress.note(f"modbus-gateway scan: {error}")
        else:
            progress.note(
                f"modbus-gateway scan: line {line.name!r}: no {line.kind} connection with "
                f"{line.device}: {error}. Check the address, and that nothing else holds the "
                "device server's only connection (a running gateway may)."
            )
    except KeyboardInterrupt:
        progress.note("modbus-gateway scan: interrupted")
    return None


def _json(result: ScanResult) -> str:
    plain = asdict(result)
    for slave in plain["slaves"]:
        slave["answer"] = slave["answer"].value
    return json.dumps(plain, indent=2)


def _ranges(addresses: Sequence[int]) -> str:
    """``[1, 2, 3, 7]`` → ``1-3,7``."""
    parts: list[str] = []
    start = previous = addresses[0]
    for address in [*addresses[1:], -1]:
        if address != previous + 1:
            parts.append(str(start) if start == previous else f"{start}-{previous}")
            start = address
        previous = address
    return ",".join(parts)
