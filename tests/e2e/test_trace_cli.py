"""`modbus-gateway trace` from the command line: demo line, one master, the trace on stderr."""

from __future__ import annotations

import queue
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

from tests.helpers import mbap, release

DEADLINE_S = 10.0


def _lines(stream: object, into: queue.Queue[str]) -> None:
    for line in stream:  # type: ignore[attr-defined]
        into.put(line.rstrip("\n"))


def _wait_for(lines: queue.Queue[str], pattern: str, seen: list[str]) -> re.Match[str]:
    deadline = time.monotonic() + DEADLINE_S
    while (remaining := deadline - time.monotonic()) > 0:
        try:
            line = lines.get(timeout=remaining)
        except queue.Empty:
            break
        seen.append(line)
        match = re.search(pattern, line)
        if match:
            return match
    raise AssertionError(f"no line matching {pattern!r} in:\n" + "\n".join(seen))


def test_trace_subcommand_prints_requests_and_replies_decoded() -> None:
    command = [
        sys.executable, "-m", "gateway", "trace", "--demo", "--listen", "127.0.0.1:0",
        "--metrics", "off", "--trace-unit", "1", "--trace-function", "read_holding_registers",
    ]  # fmt: skip
    process = subprocess.Popen(
        command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    seen: list[str] = []
    reader = threading.Thread(target=_lines, args=(process.stderr, lines), daemon=True)
    reader.start()
    try:
        match = _wait_for(lines, r"listening on ([\d.]+):(\d+) \(Modbus TCP\)", seen)
        with socket.create_connection((match[1], int(match[2])), timeout=DEADLINE_S) as sock:
            for tid, unit, pdu in (
                (41, 2, bytes.fromhex("03 0000 0002")),  # another unit: not traced
                (42, 1, bytes.fromhex("06 0000 0001")),  # another function: not traced
                (43, 1, bytes.fromhex("03 0000 000A")),
            ):
                sock.sendall(mbap(tid, unit, pdu))
                header = sock.recv(7, socket.MSG_WAITALL)
                sock.recv(struct.unpack(">HHHB", header)[2] - 1, socket.MSG_WAITALL)
        request = _wait_for(lines, r"gateway\.trace: -> (\S+) tid=(\d+) unit=1 (.*)$", seen)
        assert (request[2], request[3]) == (
            "43", "read_holding_registers(3) address=0 quantity=10 via tcp"
        )  # fmt: skip
        reply = _wait_for(lines, r"gateway\.trace: <- (\S+) tid=43 unit=1 (.*)$", seen)
        assert re.fullmatch(r"read_holding_registers\(3\) byte_count=20 ok \d+\.\d\d ms", reply[2])
        assert reply[1] == request[1]  # the master's address
        assert not [line for line in seen if "tid=41" in line or "tid=42" in line]
    finally:
        process.send_signal(signal.SIGTERM)
        release(process, reader)
    assert process.returncode == 0
