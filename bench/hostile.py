"""The ``hostile`` scenario: an honest master's latency and the gateway's memory beside attackers.

One gateway (``python -m gateway`` on an unpaced simulated line with every
address 1..247 routed, as ``--serial`` does, its HTTP endpoint on) serves an
honest master that polls unit 1 back to back from this process; each phase
adds one attacker, a process of its own (``python -m bench.hostile ATTACK
...``) connecting from 127.0.0.2:

- ``flood-unread``: pipelined requests the gateway answers itself (no route),
  never reading a reply;
- ``flood-read``: the same, reading every reply;
- ``bad-framing``: connections that send 2,000 such requests and then a broken
  MBAP header, held open and never read;
- ``bursts``: more connections than ``max_connections`` every 0.5 s, held
  0.5 s; beside it a second honest master (127.0.0.3) connects anew for every
  poll;
- ``churn``: connects that reset at once, broken headers, bad lengths, and
  connections past the per-address limit, as fast as it can (the log's load);
- ``scrape``: four clients fetching /metrics in a loop.

For each phase: the honest master's p50/p99, the gateway's RSS at the start and
its peak during the phase, the gateway's log lines per second, and what the
attacker achieved. Last, a client asks every unit 1..255 for 28 function codes
and the size of /metrics is compared with before.
"""

from __future__ import annotations

import argparse
import json
import select
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import ExitStack, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .procs import PYTHON, BenchError, Server, SimOptions, Simulator, free_port, read_status_kib
from .scenarios import KIB_PER_MB, Bench, Check, ScenarioResult, Table

ATTACKER = "127.0.0.2"
OTHER_HONEST = "127.0.0.3"
UNITS = (1, 2, 3, 4)
MAX_CONNECTIONS = 100
UNROUTED = 250  #: reserved, never routed by --serial: answered 0x0A by the gateway itself
READ_1 = bytes.fromhex("03 0000 0001")
ATTACKS = ("flood-unread", "flood-read", "bad-framing", "bursts", "churn", "scrape")
SCAN_FUNCTIONS = (*range(1, 25), 43, 65, 100, 127)


def mbap(tid: int, unit: int, pdu: bytes, protocol_id: int = 0) -> bytes:
    """A Modbus TCP ADU."""
    return struct.pack(">HHHB", tid & 0xFFFF, protocol_id, len(pdu) + 1, unit) + pdu


def connect(port: int, source: str = "127.0.0.1", timeout: float = 5.0) -> socket.socket:
    """A connection to the gateway from loopback address ``source``."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind((source, 0))
    sock.settimeout(timeout)
    sock.connect(("127.0.0.1", port))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def read_reply(sock: socket.socket) -> bytes:
    """One reply's PDU (blocking)."""
    header = read_exactly(sock, 7)
    return read_exactly(sock, struct.unpack(">H", header[4:6])[0] - 1)


def read_exactly(sock: socket.socket, count: int) -> bytes:
    """``count`` bytes from a blocking socket (``ConnectionError`` when it closes first)."""
    data = b""
    while len(data) < count:
        chunk = sock.recv(count - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data


# --------------------------------------------------------------------------- the attackers


def _until(seconds: float) -> Iterator[None]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        yield


def _flood(port: int, duration: float, read: bool) -> dict[str, Any]:
    payload = b"".join(mbap(tid, UNROUTED, READ_1) for tid in range(4096))
    stats = {"bytes_sent": 0, "replies": 0, "closed_by_gateway": 0}
    sock = connect(port, ATTACKER)
    stop = threading.Event()

    def reader(current: socket.socket) -> None:  # the socket is non-blocking: wait, then read
        with suppress(OSError):
            while not stop.is_set():
                select.select([current], [], [], 0.1)
                try:
                    chunk = current.recv(65536)
                except BlockingIOError:
                    continue
                if not chunk:
                    return
                stats["replies"] += len(chunk) // 9  # an exception reply is 9 bytes

    threads = []
    if read:
        threads.append(threading.Thread(target=reader, args=(sock,), daemon=True))
        threads[-1].start()
    sock.setblocking(False)
    for _ in _until(duration):
        try:
            stats["bytes_sent"] += sock.send(payload)
        except BlockingIOError:
            select.select([], [sock], [], 0.05)
        except OSError:
            stats["closed_by_gateway"] += 1
            sock.close()
            sock = connect(port, ATTACKER)
            if read:
                threads.append(threading.Thread(target=reader, args=(sock,), daemon=True))
                threads[-1].start()
            sock.setblocking(False)
    stop.set()
    sock.close()
    return stats


def _bad_framing(port: int, duration: float) -> dict[str, Any]:
    payload = b"".join(mbap(tid, UNROUTED, READ_1) for tid in range(2000)) + mbap(1, 1, READ_1, 7)
    held: list[socket.socket] = []
    stats = {"connections": 0}
    for _ in _until(duration):
        try:
            sock = connect(port, ATTACKER)
            sock.sendall(payload)
        except OSError:
            continue
        stats["connections"] += 1
        held.append(sock)
        if len(held) > 12:  # under the per-address limit: every one reaches the gateway
            held.pop(0).close()
    for sock in held:
        sock.close()
    return stats


def _bursts(port: int, duration: float) -> dict[str, Any]:
    stats = {"bursts": 0, "connected": 0, "refused": 0}
    for _ in _until(duration):
        started = time.monotonic()
        burst: list[socket.socket] = []
        for _ in range(MAX_CONNECTIONS + 10):
            with suppress(OSError):
                burst.append(connect(port, ATTACKER, 1.0))
        stats["bursts"] += 1
        stats["connected"] += len(burst)
        rest = 0.5 - (time.monotonic() - started)
        if rest > 0:
            readable, _, _ = select.select(burst, [], [], rest)  # the gateway's refusals
            stats["refused"] += len(readable)
            time.sleep(max(0.0, 0.5 - (time.monotonic() - started)))  # pacing the attack
        for sock in burst:
            sock.close()
    return stats


def _churn(port: int, duration: float) -> dict[str, Any]:
    stats = {"attempts": 0}
    linger = struct.pack("ii", 1, 0)
    for _ in _until(duration):
        with suppress(OSError):
            sock = connect(port, ATTACKER, 1.0)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, linger)
            sock.close()  # reset at once
        for frame in (mbap(1, 1, READ_1, 5), b"\x00\x01\x00\x00\x04\x00\x01"):
            with suppress(OSError), connect(port, ATTACKER, 1.0) as sock:
                sock.sendall(frame)
                sock.recv(1)
        held = []
        for _ in range(20):  # past the per-address limit
            with suppress(OSError):
                held.append(connect(port, ATTACKER, 1.0))
        for sock in held:
            sock.close()
        stats["attempts"] += 23
    return stats


def _scrape(metrics_port: int, duration: float) -> dict[str, Any]:
    stats = {"scrapes": 0, "bytes": 0, "errors": 0}
    lock = threading.Lock()

    def loop() -> None:
        for _ in _until(duration):
            try:
                with urllib.request.urlopen(
                    f"http://127.0.0.1:{metrics_port}/metrics", timeout=5
                ) as r:
                    size = len(r.read())
                with lock:
                    stats["scrapes"] += 1
                    stats["bytes"] += size
            except OSError:
                with lock:
                    stats["errors"] += 1

    threads = [threading.Thread(target=loop) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return stats


def _per_poll(port: int, duration: float) -> dict[str, Any]:
    stats = {"polls": 0, "served": 0}
    for _ in _until(duration):
        stats["polls"] += 1
        with suppress(OSError), connect(port, OTHER_HONEST, 2.0) as sock:
            sock.sendall(mbap(7, 1, READ_1))
            if read_reply(sock)[:1] == b"\x03":
                stats["served"] += 1
        time.sleep(0.02)  # a poll every ~20 ms: pacing, not synchronisation
    return stats


def attack_main(argv: list[str] | None = None) -> int:
    """``python -m bench.hostile ATTACK --port P --metrics-port M --duration S``: print stats."""
    parser = argparse.ArgumentParser(prog="python -m bench.hostile")
    parser.add_argument("attack", choices=(*ATTACKS, "per-poll"))
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--metrics-port", type=int, default=0)
    parser.add_argument("--duration", type=float, required=True)
    args = parser.parse_args(argv)
    runs: dict[str, Callable[[], dict[str, Any]]] = {
        "flood-unread": lambda: _flood(args.port, args.duration, read=False),
        "flood-read": lambda: _flood(args.port, args.duration, read=True),
        "bad-framing": lambda: _bad_framing(args.port, args.duration),
        "bursts": lambda: _bursts(args.port, args.duration),
        "churn": lambda: _churn(args.port, args.duration),
        "scrape": lambda: _scrape(args.metrics_port, args.duration),
        "per-poll": lambda: _per_poll(args.port, args.duration),
    }
    print(json.dumps(runs[args.attack]()), flush=True)
    return 0


# --------------------------------------------------------------------------- the scenario


@dataclass
class Phase:
    """What one phase measured."""

    name: str
    latencies: list[float] = field(default_factory=list)
    errors: int = 0
    rss_start_kib: int = 0
    rss_peak_kib: int = 0
    log_lines: int = 0
    window: float = 0.0
    attacker: dict[str, Any] = field(default_factory=dict)
    per_poll: dict[str, Any] = field(default_factory=dict)

    def quantile(self, q: float) -> float:
        """A latency quantile in ms (0 without samples)."""
        if not self.latencies:
            return 0.0
        ordered = sorted(self.latencies)
        return 1000 * ordered[min(len(ordered) - 1, int(q * len(ordered)))]

    @property
    def log_rate(self) -> float:
        """Gateway log lines per second during the phase."""
        return self.log_lines / self.window if self.window else 0.0

    def as_json(self) -> dict[str, Any]:
        """The figures, for results.json."""
        return {
            "polls": len(self.latencies), "errors": self.errors,
            "p50_ms": self.quantile(0.5), "p99_ms": self.quantile(0.99),
            "rss_start_mb": self.rss_start_kib / KIB_PER_MB,
            "rss_peak_mb": self.rss_peak_kib / KIB_PER_MB,
            "log_lines_per_s": self.log_rate, "attacker": self.attacker,
            "per_poll": self.per_poll,
        }  # fmt: skip


class HostileRun:
    """The simulator, the gateway and the honest master, for the phases one after the other."""

    def __init__(self, workdir: Path, stack: ExitStack) -> None:
        self.workdir = workdir
        simulator = Simulator(SimOptions(units=UNITS), workdir)
        simulator.start()
        stack.callback(simulator.stop)
        self.port, self.metrics_port = free_port(), free_port()
        # Every address routed, as with --serial; absent slaves time out fast (the scan
        # visits 243 of them), the simulated ones get a generous timeout.
        config = workdir / "gateway.toml"
        config.write_text(
            f"[server]\nmax_connections = {MAX_CONNECTIONS}\n\n"
            f'[lines.a]\ndevice = "{simulator.link}"\nbaudrate = 115200\nframe_gap = 0.0\n'
            'units = ["1-247"]\ntimeout = 0.02\nretries = 0\n'
            'slave_timeouts = { "1" = 1.0, "2" = 1.0, "3" = 1.0, "4" = 1.0 }\n'
        )
        command = [
            PYTHON, "-m", "gateway", "--config", str(config),
            "--listen", f"127.0.0.1:{self.port}",
            "--metrics", f"127.0.0.1:{self.metrics_port}", "--log-level", "info",
        ]  # fmt: skip
        self.server = Server(command, workdir, "server")
        self.server.start()
        stack.callback(self.server.stop)
        self.honest = connect(self.port)
        stack.callback(self.honest.close)
        self._tid = 0

    def rss_kib(self) -> int:
        """The gateway's resident set now."""
        return read_status_kib(self.server.pid, "VmRSS") or 0

    def log_lines(self) -> int:
        """Lines the gateway has logged so far."""
        return self.server.log.read_text(errors="replace").count("\n")

    def poll(self) -> float:
        """One honest request; its round trip in seconds."""
        self._tid = (self._tid + 1) & 0xFFFF
        started = time.perf_counter()
        self.honest.sendall(mbap(self._tid, 1, READ_1))
        reply = read_reply(self.honest)
        elapsed = time.perf_counter() - started
        if reply[:1] != b"\x03":
            raise ConnectionError(f"honest master got {reply.hex()}")
        return elapsed

    def attacker(self, attack: str, duration: float) -> subprocess.Popen[str]:
        """Start an attacker process."""
        return subprocess.Popen(
            [PYTHON, "-m", "bench.hostile", attack, "--port", str(self.port),
             "--metrics-port", str(self.metrics_port), "--duration", f"{duration:.3f}"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip

    def phase(self, name: str, window: float) -> Phase:
        """Poll for ``window`` seconds beside attacker ``name`` (none for the baseline)."""
        phase = Phase(name, rss_start_kib=self.rss_kib(), window=window)
        lines_before = self.log_lines()
        processes: dict[str, subprocess.Popen[str]] = {}
        if name != "baseline":
            processes["attacker"] = self.attacker(name, window)
        if name == "bursts":
            processes["per_poll"] = self.attacker("per-poll", window)
        started = time.monotonic()
        last_sample = started
        phase.rss_peak_kib = phase.rss_start_kib
        while (now := time.monotonic()) - started < window:
            try:
                phase.latencies.append(self.poll())
            except OSError:
                phase.errors += 1
                self.honest.close()
                self.honest = connect(self.port)
            if now - last_sample >= 0.05:
                phase.rss_peak_kib = max(phase.rss_peak_kib, self.rss_kib())
                last_sample = now
        for role, process in processes.items():
            out, _ = process.communicate(timeout=window + 30)
            lines = [line for line in out.splitlines() if line.startswith("{")]
            setattr(phase, role, json.loads(lines[-1]) if lines else {"failed": process.returncode})
        phase.rss_peak_kib = max(phase.rss_peak_kib, self.rss_kib())
        phase.log_lines = self.log_lines() - lines_before
        return phase

    def metrics_size(self) -> int:
        """Bytes of one /metrics scrape."""
        url = f"http://127.0.0.1:{self.metrics_port}/metrics"
        with urllib.request.urlopen(url, timeout=10) as response:
            return len(response.read())

    def scan(self) -> tuple[int, int]:
        """/metrics size before and after asking every unit for every function code in the list."""
        before = self.metrics_size()
        with connect(self.port, ATTACKER, 30.0) as sock:
            for unit in range(1, 256):
                sock.sendall(
                    b"".join(mbap(f, unit, bytes((f, 0, 0, 0, 1))) for f in SCAN_FUNCTIONS)
                )
                for _ in SCAN_FUNCTIONS:
                    read_reply(sock)
        return before, self.metrics_size()


def hostile(bench: Bench) -> ScenarioResult:
    """Issue 9: the honest master and the gateway's RSS without and with each attacker."""
    window = bench.timing.pick(5.0, 2.0, 1.0)
    phases: list[Phase] = []
    with tempfile.TemporaryDirectory(prefix="modbus-bench-") as temp, ExitStack() as stack:
        bench.progress("  hostile: starting the simulator and the gateway ...")
        try:
            run = HostileRun(Path(temp), stack)
        except OSError as error:
            raise BenchError(f"hostile: {error}") from error
        for name in ("baseline", *ATTACKS):
            bench.progress(f"  hostile: {name} ...")
            phase = run.phase(name, window)
            phases.append(phase)
            bench.progress(
                f"  hostile: {name}: honest p50 {phase.quantile(0.5):.2f} ms, "
                f"p99 {phase.quantile(0.99):.2f} ms, RSS peak {phase.rss_peak_kib / 1024:.1f} MB"
            )
        bench.progress("  hostile: scanning every unit x function code ...")
        size_before, size_after = run.scan()
        final_rss = run.rss_kib()
        gateway_log = run.server.log.read_text(errors="replace")
    base = phases[0]
    table = Table(
        f"Hostile clients: an honest master polling unit 1 back to back (unpaced line), "
        f"{window:g} s per phase, each attacker from {ATTACKER}",
        ["attacker", "honest polls", "p50 ms", "p99 ms", "p99 / baseline", "errors",
         "RSS start MB", "RSS peak MB", "log lines/s", "attacker achieved"],
    )  # fmt: skip
    for phase in phases:
        ratio = phase.quantile(0.99) / base.quantile(0.99) if base.quantile(0.99) else 0.0
        achieved = ", ".join(f"{k} {v}" for k, v in {**phase.attacker, **phase.per_poll}.items())
        table.rows.append([
            phase.name, str(len(phase.latencies)), f"{phase.quantile(0.5):.2f}",
            f"{phase.quantile(0.99):.2f}", f"{ratio:.2f}x", str(phase.errors),
            f"{phase.rss_start_kib / KIB_PER_MB:.1f}", f"{phase.rss_peak_kib / KIB_PER_MB:.1f}",
            f"{phase.log_rate:.1f}", achieved or "-",
        ])  # fmt: skip
    by_name = {phase.name: phase for phase in phases}
    flood_p99 = max(by_name[n].quantile(0.99) for n in ("flood-unread", "flood-read"))
    rss_growth = max(p.rss_peak_kib for p in phases) / KIB_PER_MB - base.rss_start_kib / KIB_PER_MB
    per_poll = by_name["bursts"].per_poll
    per_poll_share = per_poll.get("served", 0) / per_poll["polls"] if per_poll.get("polls") else 0.0
    kept_errors = by_name["bursts"].errors
    log_rate = max(phase.log_rate for phase in phases[1:])
    scrape_ratio = by_name["scrape"].quantile(0.99) / base.quantile(0.99) if base.latencies else 0.0
    size_ratio = size_after / size_before if size_before else 0.0
    checks = [
        Check("floods: honest p99", flood_p99, "<= 100 ms", flood_p99 <= 100, " ms"),
        Check("floods and the rest: gateway RSS growth", rss_growth, "<= 20 MB",
              rss_growth <= 20, " MB"),
        Check("bursts: kept connection's polls lost", kept_errors, "0", kept_errors == 0),
        Check("bursts: per-poll master served", per_poll_share, ">= 0.9", per_poll_share >= 0.9),
        Check("log lines/s one client causes", log_rate, "<= 10", log_rate <= 10),
        Check("4 scrapers: honest p99 vs without", scrape_ratio, "<= 2x", scrape_ratio <= 2,
              "x"),
        Check("/metrics after a unit x function scan", size_ratio, "<= 1.5x", size_ratio <= 1.5,
              "x"),
    ]  # fmt: skip
    figures = {
        "window_s": window,
        "phases": {phase.name: phase.as_json() for phase in phases},
        "rss_growth_mb": rss_growth,
        "rss_end_mb": final_rss / KIB_PER_MB,
        "per_poll_served_share": per_poll_share,
        "max_log_lines_per_s": log_rate,
        "scrape_p99_ratio": scrape_ratio,
        "metrics_bytes_before_scan": size_before,
        "metrics_bytes_after_scan": size_after,
        "metrics_size_ratio": size_ratio,
        "gateway_log_tail": gateway_log[-2000:],
    }
    notes = [
        "the log-lines figure counts every line the gateway wrote during the phase (its INFO "
        "summaries come once a minute, so a phase shorter than that shows the first lines "
        "of each fault only); the RSS growth is the highest peak of any phase over the "
        "baseline's start",
        f"/metrics: {size_before:,} bytes before the scan of units 1..255 x "
        f"{len(SCAN_FUNCTIONS)} function codes, {size_after:,} after",
    ]
    return ScenarioResult("hostile", figures, [table], checks, 0, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"hostile": hostile}


if __name__ == "__main__":
    sys.exit(attack_main())
