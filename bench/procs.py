"""The processes of one benchmark run: simulator, gateway (or reference forwarder), load generator.

Each runs as its own Python process, started with the interpreter running the
benchmark. Readiness is waited for on what the process says (the simulator's
``READY`` line, the server's "listening on" log line), never with a sleep.
Logs go to files in the run's temporary directory, never to a pipe nobody
reads (a full pipe would stall the gateway in the middle of a measurement).
Every process is stopped by its own pid: SIGTERM first, SIGKILL after a grace.
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from types import TracebackType
from typing import Any

from .loadgen import LoadResult, LoadSpec, result_from_json

PYTHON = sys.executable
READY_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 8.0
_POLL_S = 0.02
_TAIL_CHARS = 2000


class BenchError(RuntimeError):
    """A process of the benchmark failed to start or to report."""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def read_status_kib(pid: int, key: str) -> int | None:
    """A ``/proc/PID/status`` value in KiB (``VmHWM``, ``VmRSS``), None when unavailable."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as status:
            for line in status:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


def _tail(path: Path) -> str:
    try:
        return path.read_text(errors="replace")[-_TAIL_CHARS:]
    except OSError:
        return ""


def _stop(process: subprocess.Popen[Any], grace: float = STOP_TIMEOUT_S) -> None:
    """SIGTERM, then SIGKILL after the grace; returns once it is gone."""
    if process.poll() is not None:
        return
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(grace)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


@dataclass
class SimOptions:
    """How the simulated RTU line is run."""

    units: Sequence[int] = (1, 2, 3, 4)
    baudrate: int | None = None  #: None: unpaced (answers at once)
    turnaround: float = 0.0  #: seconds from the request's end to the answer's start
    silent: Sequence[int] = ()
    crc_error_rates: dict[int, float] = field(default_factory=dict)
    seed: int = 1
    realtime: bool = False  #: SCHED_FIFO for the simulator's thread (a real slave has its own CPU)
    late: Sequence[tuple[int, float, float, float]] = ()  #: (unit, share, min s, max s)
    late_first: Sequence[int] = ()  #: units of ``late`` whose first read is late too
    die_on_signal: Sequence[int] = ()  #: units that fall silent when the simulator gets SIGUSR1
    #: ``--response-time`` arguments: devices answering after a response time by phase
    #: (``bench.slaves.response_profile_argument``).
    response_time: Sequence[str] = ()
    log_requests: bool = False  #: the simulator reports every request it executed, timed
    framing: str = "rtu"  #: "ascii": the slaves speak Modbus ASCII
    modbus_tcp_listen: str | None = None  #: HOST:PORT: a Modbus TCP slave instead of a pty
    #: With ``modbus_tcp_listen``: (certificate chain, key, CA) files: a Modbus/TCP Security
    #: slave instead, client certificates required.
    tls_files: tuple[str, str, str] | None = None


class Simulator:
    """``python -m bench.slaves`` (the gateway's simulated line) on a pty, behind a symlink."""

    def __init__(self, options: SimOptions, workdir: Path) -> None:
        self.options = options
        self.link = workdir / "line"
        self._log = workdir / "sim.log"
        self._process: subprocess.Popen[str] | None = None
        self.stats: dict[str, Any] = {}

    @property
    def pid(self) -> int:
        """The simulator's pid."""
        assert self._process is not None
        return self._process.pid

    def command(self) -> list[str]:
        """The command line."""
        options = self.options
        if options.modbus_tcp_listen is not None:  # no pty: the slaves' own listener
            command = [
                PYTHON,
                "-m",
                "bench.slaves",
                "--modbus-tcp-listen",
                options.modbus_tcp_listen,
            ]
            for unit in options.units:
                command += ["--unit", str(unit)]
            for unit in options.silent:
                command += ["--silent", str(unit)]
            for unit in options.die_on_signal:
                command += ["--die-on-signal", str(unit)]
            if options.tls_files is not None:
                cert, key, ca = options.tls_files
                command += ["--tls-cert", cert, "--tls-key", key, "--tls-ca", ca]
            return command
        command = [PYTHON, "-m", "bench.slaves", "--link", str(self.link)]
        command += ["--seed", str(options.seed)]
        for unit in options.units:
            command += ["--unit", str(unit)]
        if options.baudrate is not None:
            command += ["--baudrate", str(options.baudrate)]
            command += ["--turnaround", f"{options.turnaround:.6f}"]
        if options.realtime:
            command.append("--realtime")
        for unit in options.silent:
            command += ["--silent", str(unit)]
        for unit, rate in options.crc_error_rates.items():
            command += ["--crc-error-rate", f"{unit}:{rate}"]
        for unit, share, low, high in options.late:
            first = ":first" if unit in options.late_first else ""
            command += ["--late", f"{unit}:{share}:{low}:{high}{first}"]
        for unit in options.die_on_signal:
            command += ["--die-on-signal", str(unit)]
        for profile in options.response_time:
            command += ["--response-time", profile]
        if options.log_requests:
            command.append("--log-requests")
        if options.framing != "rtu":
            command += ["--framing", options.framing]
        return command

    def start(self) -> None:
        """Start and wait for ``READY``."""
        with open(self._log, "w") as log:
            self._process = subprocess.Popen(
                self.command(), stdout=subprocess.PIPE, stderr=log, text=True
            )
        assert self._process.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(self._process.stdout, selectors.EVENT_READ)
            if not selector.select(READY_TIMEOUT_S):
                raise BenchError(f"simulator not ready in {READY_TIMEOUT_S} s: {_tail(self._log)}")
        line = self._process.stdout.readline()
        if not line.startswith("READY"):
            self._process.wait(STOP_TIMEOUT_S)
            raise BenchError(f"simulator did not start: {line!r} {_tail(self._log)}")

    def stop(self) -> dict[str, Any]:
        """SIGTERM; return the counters it prints on the way out."""
        process = self._process
        if process is None:
            return self.stats
        self._process = None
        # Its counters are read while it exits: a line longer than the pipe's buffer
        # (``--log-requests``) would otherwise hold it until it is killed.
        output = ""
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
        try:
            output, _ = process.communicate(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            output, _ = process.communicate()
        for line in output.splitlines():
            if line.startswith("{"):
                self.stats = json.loads(line)
        return self.stats


class Server:
    """A Modbus TCP server process (the gateway or the reference forwarder)."""

    def __init__(self, command: list[str], workdir: Path, name: str) -> None:
        self.command = command
        self.name = name
        self.log = workdir / f"{name}.log"
        self._process: subprocess.Popen[bytes] | None = None
        self.ready_timeout = READY_TIMEOUT_S  #: longer under valgrind (instruction counts)
        self.stop_timeout = STOP_TIMEOUT_S

    @property
    def pid(self) -> int:
        """The server's pid."""
        assert self._process is not None
        return self._process.pid

    def start(self, ready_text: str = "listening on") -> None:
        """Start and wait for ``ready_text`` in its log."""
        with open(self.log, "wb") as log:
            self._process = subprocess.Popen(
                self.command, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + self.ready_timeout
        while time.monotonic() < deadline:
            if ready_text in _tail(self.log) or ready_text in self.log.read_text(errors="replace"):
                return
            if self._process.poll() is not None:
                raise BenchError(f"{self.name} exited at start: {_tail(self.log)}")
            time.sleep(_POLL_S)
        raise BenchError(f"{self.name} not ready in {self.ready_timeout} s: {_tail(self.log)}")

    def memory_kib(self) -> dict[str, int | None]:
        """Current and peak resident set (KiB)."""
        return {
            "rss_kib": read_status_kib(self.pid, "VmRSS"),
            "peak_rss_kib": read_status_kib(self.pid, "VmHWM"),
        }

    def stop(self) -> int | None:
        """SIGTERM (SIGKILL after the grace); the exit status."""
        process = self._process
        if process is None:
            return None
        self._process = None
        _stop(process, self.stop_timeout)
        return process.returncode

    def log_tail(self) -> str:
        """The end of its log (for error reports)."""
        return _tail(self.log)


def run_loadgen(spec: LoadSpec, workdir: Path) -> LoadResult:
    """Run the load generator process to completion and parse its result."""
    budget = spec.warmup + spec.duration + spec.drain + spec.connect_timeout + 30.0
    log = workdir / "loadgen.log"
    with open(log, "w") as errors:
        done = subprocess.run(
            [PYTHON, "-m", "bench.loadgen", json.dumps(spec.__dict__)],
            stdout=subprocess.PIPE,
            stderr=errors,
            text=True,
            timeout=budget,
            check=False,
        )
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        raise BenchError(f"load generator failed ({done.returncode}): {_tail(log)}")
    return result_from_json(lines[-1])


class Stack:
    """Simulator + server, started together and always stopped (context manager)."""

    def __init__(self, simulator: Simulator, server: Server) -> None:
        self.simulator = simulator
        self.server = server
        self.sim_stats: dict[str, Any] = {}

    def __enter__(self) -> Stack:
        self.simulator.start()
        try:
            self.server.start()
        except BaseException:
            self.simulator.stop()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        try:
            self.server.stop()
        finally:
            self.sim_stats = self.simulator.stop()


def gateway_build() -> str:
    """``compiled`` or ``interpreted``: the gateway the server processes run (this checkout's,
    as they import it; ``MODBUS_GATEWAY_COMPILE=1 python setup.py build_ext --inplace``
    compiles it, see the README's "Compiled build")."""
    from gateway import build  # the servers' own import path: the bench runs from the root

    return build()


def environment_summary() -> dict[str, Any]:
    """What machine and code produced the figures."""
    summary: dict[str, Any] = {"python": sys.version.split()[0], "cpus": os.cpu_count()}
    summary["gateway_build"] = gateway_build()
    try:
        summary["uvloop"] = metadata.version("uvloop")
    except metadata.PackageNotFoundError:
        summary["uvloop"] = None
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=False,
            cwd=Path(__file__).resolve().parent,
        )
        summary["commit"] = commit.stdout.strip() or None
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "gateway"],
            capture_output=True,
            text=True,
            check=False,
            cwd=Path(__file__).resolve().parent,
        )
        summary["gateway_tree_modified"] = bool(dirty.stdout.strip())
    except OSError:
        summary["commit"] = None
    return summary
