"""The HTTP endpoint's cost to the Modbus path: trace streams and /status pollers.

``python -m bench.http_endpoint [--window S]`` starts the hostile scenario's
simulator and gateway (``bench.hostile.HostileRun``: an unpaced line, every unit
routed) and an honest master polling unit 1 back to back, then runs three phases:

- ``baseline``: the honest master alone;
- ``trace16``: 16 ``/trace`` streams, each with a filter of 64 values (63 masters
  that never connect, and the honest master's host) so every event reaches every
  stream, read by one process under ``nice -n 19``;
- ``status4``: 4 clients polling ``/status`` in a loop, in one process under
  ``nice -n 19``.

For each: the honest master's p50/p99, and the gateway's CPU time (utime + stime
from ``/proc/PID/stat``) per honest transaction. The gateway CPU per traced event
is the trace phase's CPU per transaction less the baseline's, over the two events
(request, reply) each transaction makes, each sent to the 16 streams. Prints one
JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import selectors
import socket
import subprocess
import tempfile
import threading
import time
import urllib.request
from contextlib import ExitStack, suppress
from pathlib import Path
from typing import Any

from .hostile import HostileRun, Phase
from .procs import PYTHON

STREAMS = 16
POLLERS = 4
FILTER = "master=" + ",".join([f"10.9.{i // 200}.{i % 200}" for i in range(63)] + ["127.0.0.1"])


def cpu_seconds(pid: int) -> float:
    """utime + stime of process ``pid`` from ``/proc/PID/stat``."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        fields = stat.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _streams(metrics_port: int, duration: float) -> dict[str, Any]:
    """Open STREAMS filtered trace streams and read them for ``duration``; count events."""
    selector = selectors.DefaultSelector()
    refused = 0
    for index in range(STREAMS):  # from 127.0.0.10.. (the endpoint caps connections per source)
        sock = socket.create_connection(
            ("127.0.0.1", metrics_port), timeout=5, source_address=(f"127.0.0.{10 + index}", 0)
        )
        sock.sendall(f"GET /trace?{FILTER} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode())
        head = sock.recv(4096)
        if not head.startswith(b"HTTP/1.1 200"):
            refused += 1
            sock.close()
            continue
        sock.setblocking(False)
        selector.register(sock, selectors.EVENT_READ)
    events = 0
    deadline = time.monotonic() + duration
    while (left := deadline - time.monotonic()) > 0:
        for key, _ in selector.select(min(left, 0.5)):
            with suppress(BlockingIOError):
                events += key.fileobj.recv(1 << 20).count(b"\n")  # type: ignore[union-attr]
    for key in list(selector.get_map().values()):
        key.fileobj.close()  # type: ignore[union-attr]
    return {"streams": STREAMS - refused, "refused": refused, "events_received": events}


def _status_pollers(metrics_port: int, duration: float) -> dict[str, Any]:
    """POLLERS clients asking /status in a loop for ``duration``."""
    counts = [0] * POLLERS

    def poll(index: int) -> None:
        deadline = time.monotonic() + duration
        while time.monotonic() < deadline:
            with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/status", timeout=5) as r:
                r.read()
            counts[index] += 1

    threads = [threading.Thread(target=poll, args=(i,)) for i in range(POLLERS)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return {"pollers": POLLERS, "answers": sum(counts), "answers_per_s": sum(counts) / duration}


def _phase(run: HostileRun, name: str, window: float) -> dict[str, Any]:
    attacker = None
    if name != "baseline":
        attacker = subprocess.Popen(
            ["nice", "-n", "19", PYTHON, "-m", "bench.http_endpoint", "--attack", name,
             "--metrics-port", str(run.metrics_port), "--window", f"{window:.3f}"],
            stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        time.sleep(0.5)  # the attacker connects: pacing, the measurement starts after
    phase = Phase(name, window=window)
    cpu_before = cpu_seconds(run.server.pid)
    started = time.monotonic()
    while time.monotonic() - started < window:
        phase.latencies.append(run.poll())
    cpu = cpu_seconds(run.server.pid) - cpu_before
    elapsed = time.monotonic() - started
    result: dict[str, Any] = {
        "transactions": len(phase.latencies),
        "tx_per_s": len(phase.latencies) / elapsed,
        "p50_ms": round(phase.quantile(0.5), 3),
        "p99_ms": round(phase.quantile(0.99), 3),
        "gateway_cpu_share": round(cpu / elapsed, 3),
        "gateway_cpu_us_per_tx": round(1e6 * cpu / max(1, len(phase.latencies)), 1),
    }
    if attacker is not None:
        out, _ = attacker.communicate(timeout=window + 30)
        result["attacker"] = json.loads(out.strip().splitlines()[-1])
    return result


def main(argv: list[str] | None = None) -> int:
    """Run the phases (or, with ``--attack``, be the attacker of one)."""
    parser = argparse.ArgumentParser(prog="python -m bench.http_endpoint")
    parser.add_argument("--window", type=float, default=10.0)
    parser.add_argument("--attack", choices=("trace16", "status4"))
    parser.add_argument("--metrics-port", type=int, default=0)
    args = parser.parse_args(argv)
    if args.attack == "trace16":
        print(json.dumps(_streams(args.metrics_port, args.window + 0.5)), flush=True)
        return 0
    if args.attack == "status4":
        print(json.dumps(_status_pollers(args.metrics_port, args.window + 0.5)), flush=True)
        return 0
    with tempfile.TemporaryDirectory(prefix="modbus-bench-") as temp, ExitStack() as stack:
        run = HostileRun(Path(temp), stack)
        phases = {
            name: _phase(run, name, args.window) for name in ("baseline", "trace16", "status4")
        }
    base, traced = phases["baseline"], phases["trace16"]
    extra_us = traced["gateway_cpu_us_per_tx"] - base["gateway_cpu_us_per_tx"]
    summary = {
        "gateway_cpu_us_per_traced_event": round(extra_us / 2, 1),
        "gateway_cpu_us_per_event_per_stream": round(extra_us / 2 / STREAMS, 2),
        "honest_p99_ms": {name: phase["p99_ms"] for name, phase in phases.items()},
    }
    print(json.dumps({"phases": phases, "summary": summary}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
