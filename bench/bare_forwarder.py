"""The floor: the least a Python Modbus TCP -> RTU forwarder can do, to measure the gateway against.

asyncio on uvloop, ``add_reader`` on the pty, a table CRC, the answer's end
predicted from its function code and byte count, one FIFO for every master, one
transaction on the line at a time. Nothing else: no validation, no metrics, no
fairness, no retries, no frame gap; a timeout answers 0x0B so a lost answer
cannot stall it. The gateway's CPU per transaction is printed as a ratio to this.

With ``--spin-gap S`` it keeps S seconds of silence after each answer by spinning on
the clock, which no timer beats, whatever it costs in CPU: on a paced line that is the
utilisation ceiling a forwarder can reach on this machine, through the same pty hops.

    python -m bench.bare_forwarder --serial /dev/pts/5 --listen 127.0.0.1:5020
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import struct
import sys
import termios
import time
import tty
from collections import deque
from collections.abc import Sequence
from typing import cast

_TABLE: list[int] = []
for _byte in range(256):
    _crc = _byte
    for _ in range(8):
        _crc = (_crc >> 1) ^ 0xA001 if _crc & 1 else _crc >> 1
    _TABLE.append(_crc)
_HEADER = struct.Struct(">HHHB")
_FIXED = {5: 8, 6: 8, 15: 8, 16: 8}  # response length of the echoing writes


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS."""
    crc = 0xFFFF
    for byte in data:
        crc = (crc >> 8) ^ _TABLE[(crc ^ byte) & 0xFF]
    return crc


def response_length(buffer: bytearray) -> int | None:
    """The answer's length once its header is in, else None."""
    if len(buffer) < 3:
        return None
    function = buffer[1]
    if function & 0x80:
        return 5
    return _FIXED.get(function, 5 + buffer[2])


class Line:
    """The serial side: one FIFO, one transaction at a time."""

    def __init__(self, fd: int, timeout: float, spin_gap: float) -> None:
        self.fd = fd
        self.timeout = timeout
        self.spin_gap = spin_gap
        self.quiet_at = 0.0  # the last answer's arrival (with ``spin_gap``)
        self.loop = asyncio.get_running_loop()
        self.queue: deque[tuple[Master, bytes, bytes]] = deque()
        self.current: tuple[Master, bytes, bytes] | None = None
        self.buffer = bytearray()
        self.timer: asyncio.TimerHandle | None = None
        self.loop.add_reader(fd, self.readable)

    def submit(self, master: Master, header: bytes, adu: bytes) -> None:
        self.queue.append((master, header, adu))
        if self.current is None:
            self.send_next()

    def send_next(self) -> None:
        while self.queue:
            master, header, adu = self.queue.popleft()
            if master.transport.is_closing():
                continue
            crc = crc16(adu)
            self.current = (master, header, adu)
            self.buffer.clear()
            while time.monotonic() < self.quiet_at:
                pass
            os.write(self.fd, adu + bytes((crc & 0xFF, crc >> 8)))
            self.timer = self.loop.call_later(self.timeout, self.timed_out)
            return
        self.current = None

    def readable(self) -> None:
        try:
            self.buffer += os.read(self.fd, 512)
        except BlockingIOError:
            return
        if self.spin_gap:
            self.quiet_at = time.monotonic() + self.spin_gap
        length = response_length(self.buffer)
        if self.current is None or length is None or len(self.buffer) < length:
            return
        frame = bytes(self.buffer[:length])
        master, header, adu = self.current
        pdu = frame[1:-2] if crc16(frame) == 0 else bytes((adu[1] | 0x80, 0x0B))
        self.finish(master, header, pdu)

    def timed_out(self) -> None:
        if self.current is not None:
            master, header, adu = self.current
            self.finish(master, header, bytes((adu[1] | 0x80, 0x0B)))

    def finish(self, master: Master, header: bytes, pdu: bytes) -> None:
        if self.timer is not None:
            self.timer.cancel()
        self.current = None
        tid, protocol, _, unit = _HEADER.unpack(header)
        answer = _HEADER.pack(tid, protocol, len(pdu) + 1, unit) + pdu
        if self.spin_gap:  # the master first: the line waits out the gap anyway
            master.transport.write(answer)
            self.send_next()
        else:
            self.send_next()  # the line first: it is the bottleneck
            master.transport.write(answer)


class Master(asyncio.Protocol):
    """One Modbus TCP connection: split MBAP frames, hand them to the line."""

    def __init__(self, line: Line) -> None:
        self.line = line
        self.buffer = bytearray()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)

    def data_received(self, data: bytes) -> None:
        buffer = self.buffer
        buffer += data
        while len(buffer) >= 7:
            size = 6 + ((buffer[4] << 8) | buffer[5])
            if len(buffer) < size:
                return
            frame = bytes(buffer[:size])
            del buffer[:size]
            self.line.submit(self, frame[:7], frame[6:])  # ADU = unit + PDU


async def serve(
    device: str, host: str, port: int, timeout: float, spin_gap: float, baudrate: int | None
) -> None:
    """Open the line, listen, serve until cancelled."""
    fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    if baudrate:  # a paced simulator answers only a master at its own speed
        speed = getattr(termios, f"B{baudrate}")
        attributes = termios.tcgetattr(fd)
        attributes[4] = attributes[5] = speed
        termios.tcsetattr(fd, termios.TCSANOW, attributes)
    line = Line(fd, timeout, spin_gap)
    server = await line.loop.create_server(lambda: Master(line), host, port)
    print(f"bare forwarder listening on {host}:{port}", file=sys.stderr, flush=True)
    async with server:
        await server.serve_forever()


def main(argv: Sequence[str] | None = None) -> int:
    """Run until SIGTERM or Ctrl-C."""
    parser = argparse.ArgumentParser(prog="python -m bench.bare_forwarder")
    parser.add_argument("--serial", required=True)
    parser.add_argument("--listen", default="127.0.0.1:5020")
    parser.add_argument("--timeout", type=float, default=1.0)
    parser.add_argument("--spin-gap", type=float, default=0.0)
    parser.add_argument("--baudrate", type=int)
    args = parser.parse_args(argv)
    host, _, port = args.listen.rpartition(":")
    import uvloop

    with contextlib.suppress(KeyboardInterrupt):
        uvloop.run(serve(args.serial, host, int(port), args.timeout, args.spin_gap, args.baudrate))
    return 0


if __name__ == "__main__":
    sys.exit(main())
