"""A stop with trace streams and status fetches open, under polling masters: no ERROR.

The real CLI (the demo's three lines) in a subprocess; masters poll as fast as they are
answered, two trace streams read the live trace and a reader fetches ``/status`` in a loop,
as the status page does. SIGTERM then ends the process with exit 0 and a log free of
ERROR records and tracebacks: every open HTTP exchange is closed by the gateway itself,
none is left for the event loop's shutdown to cancel.
"""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable

import pytest

from tests.helpers import DEADLINE_S, mbap, release

#: Stops per test: the ERROR came on most stops, not on every one.
STOPS = 3
LISTENING = re.compile(r"listening on ([\d.]+):(\d+)")
METRICS_AT = re.compile(r"metrics on http://([\d.]+):(\d+)/metrics")
READ_ONE = bytes.fromhex("03 0000 0001")

pytestmark = pytest.mark.slow


class _Load:
    """Masters, trace readers and a status reader, each a thread until ``stop``."""

    def __init__(self, modbus: tuple[str, int], http: tuple[str, int]) -> None:
        self._modbus, self._http = modbus, http
        self.stopping = threading.Event()
        self.answers = threading.Semaphore(0)  # one release per Modbus answer
        self.trace_bytes = threading.Semaphore(0)  # one release per chunk a stream read
        self.status_reads = threading.Semaphore(0)
        self._threads = [
            *(self._thread(self._master, unit) for unit in (1, 4, 5)),  # rtu, ascii, tcp
            *(self._thread(self._trace) for _ in range(2)),
            self._thread(self._status),
        ]

    def _thread(self, target: Callable[..., None], *args: object) -> threading.Thread:
        thread = threading.Thread(target=target, args=args, daemon=True)
        thread.start()
        return thread

    def _master(self, unit: int) -> None:
        with socket.create_connection(self._modbus, timeout=DEADLINE_S) as sock:
            tid = 0
            while not self.stopping.is_set():
                tid = (tid + 1) & 0xFFFF
                frame = mbap(tid, unit, READ_ONE)
                try:
                    sock.sendall(frame)
                    if not sock.recv(260):
                        return
                except OSError:
                    return
                self.answers.release()

    def _get(self, path: str) -> socket.socket:
        sock = socket.create_connection(self._http, timeout=DEADLINE_S)
        sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
        return sock

    def _trace(self) -> None:
        with self._get("/trace?format=sse") as sock:
            try:
                while sock.recv(65536):
                    self.trace_bytes.release()
            except OSError:
                return

    def _status(self) -> None:
        while not self.stopping.is_set():
            try:
                with self._get("/status") as sock:
                    while sock.recv(65536):
                        pass
            except OSError:
                return
            self.status_reads.release()

    def running(self) -> None:
        """Wait until every kind of load is under way."""
        for semaphore, count in ((self.answers, 30), (self.trace_bytes, 4),
                                 (self.status_reads, 2)):  # fmt: skip
            for _ in range(count):
                assert semaphore.acquire(timeout=DEADLINE_S), "the load did not start"

    def stop(self) -> None:
        self.stopping.set()
        for thread in self._threads:
            thread.join(DEADLINE_S)


def _wait_for(lines: list[str], pipe: object, pattern: re.Pattern[str]) -> re.Match[str]:
    for line in pipe:  # type: ignore[attr-defined]
        lines.append(line)
        if match := pattern.search(line):
            return match
    raise AssertionError(f"exited before {pattern.pattern!r}: {''.join(lines)}")


def _stop_under_load(*flags: str) -> tuple[int, str]:
    """One gateway, loaded, stopped by SIGTERM: its exit code and its whole log."""
    process = subprocess.Popen(
        [sys.executable, "-m", "gateway", "--demo", "--listen", "127.0.0.1:0",
         "--metrics", "127.0.0.1:0", *flags],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lines: list[str] = []
    load: _Load | None = None
    try:
        modbus = _wait_for(lines, process.stderr, LISTENING)
        http = _wait_for(lines, process.stderr, METRICS_AT)
        load = _Load((modbus[1], int(modbus[2])), (http[1], int(http[2])))
        load.running()
        process.send_signal(signal.SIGTERM)
        code = process.wait(DEADLINE_S)
        assert process.stderr is not None
        lines.append(process.stderr.read())
        return code, "".join(lines)
    finally:
        if load is not None:
            load.stop()
        if process.poll() is None:
            process.kill()
        release(process)


@pytest.mark.parametrize("flags", [(), ("--no-uvloop",)], ids=["uvloop", "asyncio"])
def test_a_stop_with_trace_streams_and_status_reads_open_logs_no_error(
    flags: tuple[str, ...],
) -> None:
    for _ in range(STOPS):
        code, log = _stop_under_load(*flags)
        assert code == 0, log
        assert "stopped" in log
        errors = [line for line in log.splitlines() if " ERROR " in line or "Traceback" in line]
        assert errors == [], log[-4000:]
