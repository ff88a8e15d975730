"""What the tests share: builders of frames and configurations, a running gateway, a raw client.

Everything talks to real things: the gateway runs on its own event loop (uvloop) in a
background thread and listens on 127.0.0.1 port 0, the slaves are ``gateway.sim.SimulatedLine``
on a pseudo-terminal, and tests speak bytes over a plain socket. Synchronisation is by events
and data (``ready``, a reply arriving), never by sleeping. The fixtures that hand these out
are in ``conftest.py``; a test module imports the rest from here (``from tests.helpers import
RawClient``), each defined once.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import re
import shutil
import site
import socket
import ssl
import struct
import subprocess
import sys
import threading
import time
import venv
from collections.abc import Callable, Coroutine, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import pytest

from gateway.app import Gateway
from gateway.config import ConfigError, build_config
from gateway.core.errors import ResponseError
from gateway.core.framing import ResponseDecoder
from gateway.sim import PtyPair, SimulatedDevice, SimulatedLine, SimulatedLineStats, UnitFaults
from gateway.sim.pki import Pki

T = TypeVar("T")

#: How long a test waits for anything that should happen at once (a reply, readiness, a stop).
DEADLINE_S = 10.0
#: Gateway baud rate used for an unpaced simulator: t3.5 is then the fixed 1.75 ms.
UNPACED_BAUDRATE = 115200


def wait_until(condition: Callable[[], bool], what: str = "", timeout: float = DEADLINE_S) -> None:
    """Poll ``condition`` (a state the gateway reaches by itself) until it holds; fail naming
    ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what or condition}")
        time.sleep(0.002)


def release(process: subprocess.Popen[Any], *readers: threading.Thread) -> None:
    """Wait for ``process`` (stopped or about to stop) and close its pipes, once the
    ``readers`` (threads that read them to their end) are done: a pipe left to the garbage
    collector is a ResourceWarning, which fails the tests."""
    process.wait(DEADLINE_S)
    for reader in readers:
        reader.join(DEADLINE_S)
        assert not reader.is_alive(), f"{reader.name} still reads a pipe of pid {process.pid}"
    for pipe in (process.stdout, process.stderr):
        if pipe is not None:
            pipe.close()
    if process.stdin is not None:
        with contextlib.suppress(BrokenPipeError):
            process.stdin.close()


# --------------------------------------------------------------------------- log records


class LogCollector(logging.Handler):
    """Keeps every record handed to it, for tests that check what was logged."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    @property
    def messages(self) -> list[str]:
        """The records' messages, formatted."""
        return [record.getMessage() for record in self.records]


# --------------------------------------------------------------------------- external tools


#: Debian packages of the programs whose package has another name.
_PACKAGE_OF = {"promtool": "prometheus", "systemd-analyze": "systemd"}


def require_tool(name: str) -> str:
    """Path of an external program; skip when missing, but fail under CI (``CI`` is set)."""
    path = shutil.which(name)
    if path is None:
        package = _PACKAGE_OF.get(name, name)
        reason = f"{name} is not installed (apt-get install {package}; .ci/run installs it)"
        if os.environ.get("CI"):
            pytest.fail(f"{reason}; CI must run this test")
        pytest.skip(reason)
    return path


# --------------------------------------------------------------------------- simulated line


@dataclass
class SimBus:
    """A ``SimulatedLine`` serving devices on the simulator end of a pty pair."""

    pty: PtyPair
    line: SimulatedLine

    @property
    def path(self) -> str:
        """The device path the gateway opens."""
        return self.pty.path

    @property
    def devices(self) -> Mapping[int, SimulatedDevice]:
        """The simulated devices by unit address."""
        return self.line.devices

    def device(self, unit: int) -> SimulatedDevice:
        """The device answering at ``unit``."""
        return self.line.devices[unit]

    def faults(self, unit: int) -> UnitFaults:
        """Live fault settings of ``unit``."""
        return self.line.faults(unit)

    def stats(self) -> SimulatedLineStats:
        """A snapshot of the line's counters."""
        return self.line.stats()

    def line_table(self, units: Sequence[int | str], **options: Any) -> dict[str, Any]:
        """A ``[lines.NAME]`` table for this line: device, a matching baud rate, ``units``.

        An unpaced simulator gets 115200 baud (t3.5 = 1.75 ms); ``options`` override anything.
        """
        table: dict[str, Any] = {
            "device": self.path,
            "baudrate": self.line.baudrate or UNPACED_BAUDRATE,
            "units": list(units),
        }
        table.update(options)
        return table


SimFactory = Callable[..., SimBus]


# --------------------------------------------------------------------------- running gateway


class RunningGateway:
    """A ``Gateway`` started on its own uvloop event loop in a background thread."""

    def __init__(self, raw: Mapping[str, Any]) -> None:
        config = build_config(raw, "<test>")
        try:
            import uvloop

            self.loop: asyncio.AbstractEventLoop = uvloop.new_event_loop()
        except ImportError:  # pragma: no cover - uvloop is a dependency on Linux
            self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._serve, name="gateway-loop", daemon=True)
        self._thread.start()
        self._stopped = False
        try:
            self.gateway: Gateway = self.run(self._start(config))
        except BaseException:
            self._stopped = True
            self._end_loop()
            raise

    def _serve(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_forever()

    @staticmethod
    async def _start(config: Any) -> Gateway:
        gateway = Gateway(config)
        await gateway.start()
        await asyncio.wait_for(gateway.ready.wait(), DEADLINE_S)
        return gateway

    @property
    def address(self) -> tuple[str, int]:
        """Where the Modbus TCP listener is."""
        host, port = self.gateway.address
        return host, port

    @property
    def port(self) -> int:
        """The Modbus TCP port."""
        return self.address[1]

    def run(self, coro: Coroutine[Any, Any, T], timeout: float = DEADLINE_S) -> T:
        """Run ``coro`` on the gateway's loop (e.g. ``gateway.reload(config)``) and wait for it."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def call(self, function: Callable[[], T], timeout: float = DEADLINE_S) -> T:
        """Call ``function`` on the gateway's loop thread (to read state without races)."""

        async def wrapper() -> T:
            return function()

        return self.run(wrapper(), timeout)

    def connect(self, timeout: float = DEADLINE_S) -> RawClient:
        """A new raw Modbus TCP connection to the gateway."""
        return RawClient(self.address, timeout)

    def stop(self, grace: float = 2.0) -> None:
        """Graceful stop, then end the loop and its thread; safe to call twice."""
        if self._stopped:
            return
        self._stopped = True
        try:
            self.run(self.gateway.stop(grace), DEADLINE_S + grace)
        finally:
            self._end_loop()

    def _end_loop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(DEADLINE_S)
        if not self._thread.is_alive():
            self.loop.close()


GatewayFactory = Callable[[Mapping[str, Any]], RunningGateway]


GatewayOnSim = Callable[..., tuple[SimBus, RunningGateway]]


# --------------------------------------------------------------------------- raw Modbus TCP client


def mbap(transaction_id: int, unit: int, pdu: bytes, protocol_id: int = 0) -> bytes:
    """A Modbus TCP ADU built by hand (independent of ``gateway.core``)."""
    return struct.pack(">HHHB", transaction_id, protocol_id, len(pdu) + 1, unit) + pdu


@dataclass(frozen=True)
class Reply:
    """One Modbus TCP reply as it came off the socket."""

    transaction_id: int
    unit: int
    pdu: bytes


class ConnectionClosedError(AssertionError):
    """The gateway closed the connection while a reply was awaited."""


class RawClient:
    """A blocking Modbus TCP master on a plain socket: exact bytes out, exact bytes in."""

    def __init__(
        self,
        address: tuple[str, int],
        timeout: float = DEADLINE_S,
        *,
        source: str | None = None,
        context: ssl.SSLContext | None = None,
        session: ssl.SSLSession | None = None,
    ) -> None:
        """Connect from loopback ``source`` (if given); over TLS when given a ``context``,
        resuming ``session`` (if given)."""
        sock = socket.create_connection(
            address, timeout=timeout, source_address=(source, 0) if source else None
        )
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if context is not None:
            sock = context.wrap_socket(sock, server_hostname="localhost", session=session)
        self.sock = sock
        self.timeout = timeout
        self._next_tid = 1

    def __enter__(self) -> RawClient:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()

    def next_tid(self) -> int:
        """A fresh transaction id."""
        tid = self._next_tid
        self._next_tid = (tid + 1) & 0xFFFF
        return tid

    def send_raw(self, data: bytes) -> None:
        """Write bytes as they are."""
        self.sock.sendall(data)

    def send(self, unit: int, pdu: bytes, tid: int | None = None) -> int:
        """Send one request; return its transaction id."""
        tid = self.next_tid() if tid is None else tid
        self.sock.sendall(mbap(tid, unit, pdu))
        return tid

    def _read_exactly(self, count: int, timeout: float) -> bytes:
        self.sock.settimeout(timeout)
        data = bytearray()
        while len(data) < count:
            try:
                chunk = self.sock.recv(count - len(data))
            except ConnectionResetError:
                chunk = b""
            if not chunk:
                raise ConnectionClosedError(f"connection closed after {bytes(data).hex(' ')!r}")
            data += chunk
        return bytes(data)

    def receive(self, timeout: float | None = None) -> Reply:
        """Read one reply, checking the MBAP header (protocol id 0, consistent length)."""
        wait = self.timeout if timeout is None else timeout
        header = self._read_exactly(7, wait)
        tid, protocol_id, length, unit = struct.unpack(">HHHB", header)
        assert protocol_id == 0, f"reply with protocol id {protocol_id}"
        assert 2 <= length <= 254, f"reply with MBAP length {length}"
        return Reply(tid, unit, self._read_exactly(length - 1, wait))

    def request(self, unit: int, pdu: bytes, tid: int | None = None) -> bytes:
        """Send a request and return the reply's PDU, checking it echoes tid and unit."""
        tid = self.send(unit, pdu, tid)
        reply = self.receive()
        assert (reply.transaction_id, reply.unit) == (tid, unit), reply
        return reply.pdu

    def is_closed_by_peer(self, timeout: float | None = None) -> bool:
        """True when the gateway closes the connection (EOF or reset) within ``timeout``.

        Raises ``AssertionError`` if bytes arrive instead.
        """
        self.sock.settimeout(self.timeout if timeout is None else timeout)
        try:
            data = self.sock.recv(1)
        except ConnectionResetError:
            return True
        except TimeoutError:
            return False
        assert not data, f"expected the connection to close, got {data.hex()}"
        return True


def client_context(
    pki: Pki, name: str | None = "operator", *, maximum: ssl.TLSVersion | None = None
) -> ssl.SSLContext:
    """A client context trusting the test CA, presenting client ``name``'s chain (if any);
    with ``maximum``, any protocol version up to it and every suite, for downgrade tests."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(cafile=str(pki.ca))
    if name is not None:
        context.load_cert_chain(*pki.client(name))
    if maximum is not None:
        context.set_ciphers("DEFAULT:@SECLEVEL=0")
        context.minimum_version = ssl.TLSVersion.TLSv1
        context.maximum_version = maximum
    return context


def decode_as_the_core_does(decoder: ResponseDecoder, chunks: list[bytes]) -> list[object]:
    """Feed ``chunks`` and, when the decoder waits for it, the line's silence; after an
    error feed what was left over again. What happened, in order: error kinds, frames."""
    happened: list[object] = []
    pending = list(chunks)
    while pending:
        try:
            frame = decoder.feed(pending.pop(0))
        except ResponseError as error:
            happened.append(error.kind)
        else:
            if frame is not None:
                happened.append(frame)
                return happened
            if pending or not decoder.waits_for_silence:
                continue
            try:
                happened.append(decoder.end_of_frame())
                return happened
            except ResponseError as error:
                happened.append(error.kind)
        rest = decoder.leftover
        decoder.reset()
        if rest:
            pending.insert(0, rest)
    return happened


def environment_with_our_dependencies(env_dir: Path, wheel: Path) -> Path:
    """A fresh venv with ``wheel`` installed that sees this environment's packages (offline),
    but not this checkout; its python.

    ``venv --system-site-packages`` would inherit the *base* interpreter's packages, which
    inside a venv are not the ones the tests run with. A ``.pth`` file listing this
    environment's site directories puts its installed dependencies on the new venv's
    path, after the venv's own site-packages, so the wheel installed there wins over any
    copy of the package here; ``.pth`` files in those directories (an editable install
    of this checkout) are not processed.
    """
    venv.create(env_dir, with_pip=False)
    python = env_dir / "bin" / "python"
    inner_site = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    outer_sites = [path for path in site.getsitepackages() if Path(path).is_dir()]
    (Path(inner_site) / "outer-environment.pth").write_text("\n".join(outer_sites) + "\n")
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
         "--no-index", "-q", str(wheel)],
        check=True, timeout=120,
    )  # fmt: skip
    return python


# --------------------------------------------------------------------------- processes


class LoggedProcess:
    """``python -m gateway ARGS`` in a subprocess, its log (stderr, or stdout and stderr
    together) collected line by line by a thread; ``wait_for`` waits on what it logs."""

    def __init__(self, *args: str, merge_stdout: bool = False) -> None:
        self.lines: list[str] = []
        self._eof = False
        self._changed = threading.Condition()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", *args],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE if merge_stdout else subprocess.DEVNULL,
            stderr=subprocess.STDOUT if merge_stdout else subprocess.PIPE,
            text=True,
        )
        pipe = self.proc.stdout if merge_stdout else self.proc.stderr
        assert pipe is not None
        self._reader = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self._reader.start()

    def _read(self, pipe: Iterable[str]) -> None:
        for line in pipe:
            with self._changed:
                self.lines.append(line.rstrip("\n"))
                self._changed.notify_all()
        with self._changed:
            self._eof = True
            self._changed.notify_all()

    @property
    def log(self) -> str:
        """Everything logged so far."""
        with self._changed:
            return "\n".join(self.lines)

    def mark(self) -> int:
        """A position in the log: ``wait_for(..., start=mark)`` looks only at later lines."""
        with self._changed:
            return len(self.lines)

    def wait_for(self, pattern: str, start: int = 0, timeout: float = DEADLINE_S) -> re.Match[str]:
        """The first log line from ``start`` on that matches ``pattern``, waiting for it."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        index = start
        with self._changed:
            while True:
                while index < len(self.lines):
                    match = regex.search(self.lines[index])
                    index += 1
                    if match is not None:
                        return match
                remaining = deadline - time.monotonic()
                if self._eof or remaining <= 0:
                    why = "the gateway exited" if self._eof else f"{timeout} s passed"
                    log = "\n".join(self.lines)
                    raise AssertionError(f"{why} before a log line matching {pattern!r}:\n{log}")
                self._changed.wait(remaining)

    def count(self, pattern: str) -> int:
        """Log lines matching ``pattern`` so far."""
        regex = re.compile(pattern)
        with self._changed:
            return sum(1 for line in self.lines if regex.search(line))

    def release(self) -> None:
        """Wait for the process (it must be ending), its log's last line and its pipes."""
        release(self.proc, self._reader)


# ----------------------------------------------------------------- bytes and configurations


def h(text: str) -> bytes:
    """Bytes written as hex, spaces allowed: ``h("03 0000 0001")``."""
    return bytes.fromhex(text)


def read(address: int, quantity: int = 1, function: int = 3) -> bytes:
    """A read request PDU (FC 3 unless ``function`` says another read)."""
    return struct.pack(">BHH", function, address, quantity)


def problems(raw: Mapping[str, Any], source: str = "plant.toml") -> list[str]:
    """The problems ``build_config`` finds in ``raw`` (it must find some)."""
    with pytest.raises(ConfigError) as caught:
        build_config(raw, source)
    return caught.value.problems


# --------------------------------------------------------------------------- the benchmark

#: The top of the source tree: where ``python -m bench`` runs.
REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class BenchRun:
    """One run of ``python -m bench --tiny``: what it printed and its ``--output`` figures."""

    stdout: str
    results: dict[str, Any]


#: ``tiny_bench("tls", ok=(0, 1), timeout=150)``: run the named scenarios (the fixture).
TinyBench = Callable[..., BenchRun]


def run_tiny_bench(
    output: Path, *names: str, ok: tuple[int, ...] = (0,), timeout: float = 120
) -> BenchRun:
    """Run the benchmark's tiny scenarios ``names`` as a process; it must exit with one of
    ``ok`` (1: a figure missed its target; 2: a process failed) and record no failure."""
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", *names, "--output", str(output)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert done.returncode in ok, done.stdout + done.stderr
    results: dict[str, Any] = json.loads(output.read_text())
    assert results["failures"] == {}, results["failures"]
    return BenchRun(done.stdout, results)
