"""The audit log's cost: records per second sustained at a write rate, and records dropped.

``python -m bench.audit [--rate 1000] [--seconds 10] [--masters 8]`` starts the
simulated line unpaced (``bench.slaves`` on a pty, answering at once) and the gateway
in front of it (``--frame-gap 0`` at 4,000,000 baud, as the ``unpaced`` scenario) with
``--audit-log``, then masters on loopback send FC06 writes at ``--rate`` per second
in total (open loop: each master on its own schedule, up to 4 in flight). It prints the
writes answered per second in the window, the audit records written per second for
those writes, the records dropped (``modbus_gateway_audit_records_dropped_total``),
whether the file passes ``audit verify``, and the gateway's CPU per write beside a run
without the audit log.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import struct
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from gateway.io.audit import verify_files

from .loadgen import process_cpu_seconds
from .procs import PYTHON, Server, SimOptions, Simulator, free_port

UNITS = (1, 2, 3, 4)
IN_FLIGHT = 4
WARMUP_S = 1.0


@dataclass
class Window:
    start: float = 0.0  #: wall time the window opened
    end: float = 0.0
    answered: int = 0  #: correct FC06 echoes inside the window
    sent: int = 0
    wrong: int = 0
    cpu_s: float = 0.0  #: the gateway's CPU inside the window


async def master(
    port: int, index: int, interval: float, stop_at: float, window: Window, first: float
) -> None:
    """One master: an FC06 write every ``interval`` seconds, up to ``IN_FLIGHT`` in flight."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    unit = UNITS[index % len(UNITS)]
    pending: dict[int, tuple[bytes, float]] = {}
    slots = asyncio.Semaphore(IN_FLIGHT)
    loop = asyncio.get_running_loop()
    drained = asyncio.Event()  # every write sent has its answer

    async def receive() -> None:
        while True:
            header = await reader.readexactly(7)
            tid, _, length, _ = struct.unpack(">HHHB", header)
            pdu = await reader.readexactly(length - 1)
            expected, _sent = pending.pop(tid)
            slots.release()
            if not pending:
                drained.set()
            if pdu != expected:
                window.wrong += 1
            elif window.start and not window.end:  # inside the window
                window.answered += 1

    receiver = asyncio.create_task(receive())
    tid, due = 0, first + index * interval / 8
    while due < stop_at:
        await asyncio.sleep(max(0.0, due - loop.time()))
        await slots.acquire()
        tid = (tid + 1) & 0xFFFF
        pdu = struct.pack(">BHH", 6, 1000 + tid % 9000, tid)
        pending[tid] = (pdu, loop.time())
        drained.clear()
        writer.write(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)
        window.sent += 1
        due += interval
    await asyncio.wait_for(drained.wait(), 10.0)
    receiver.cancel()
    writer.close()


async def load(port: int, pid: int, rate: float, seconds: float, masters: int) -> Window:
    loop = asyncio.get_running_loop()
    window = Window()
    first = loop.time() + 0.2
    stop_at = first + WARMUP_S + seconds
    interval = masters / rate
    tasks = [asyncio.create_task(master(port, i, interval, stop_at, window, first))
             for i in range(masters)]  # fmt: skip
    await asyncio.sleep(first + WARMUP_S - loop.time())
    window.start = time.time()
    cpu0 = process_cpu_seconds(pid) or 0.0
    await asyncio.sleep(seconds)
    window.end = time.time()
    window.cpu_s = (process_cpu_seconds(pid) or 0.0) - cpu0
    await asyncio.gather(*tasks)
    return window


def dropped(metrics_port: int) -> float:
    url = f"http://127.0.0.1:{metrics_port}/metrics"
    with urllib.request.urlopen(url, timeout=10) as response:
        text = response.read().decode()
    for line in text.splitlines():
        if line.startswith("modbus_gateway_audit_records_dropped_total "):
            return float(line.split()[1])
    raise RuntimeError("no modbus_gateway_audit_records_dropped_total in /metrics")


def run(workdir: Path, audit: Path | None, args: argparse.Namespace) -> dict[str, float | str]:
    simulator = Simulator(SimOptions(units=UNITS), workdir)
    port, metrics_port = free_port(), free_port()
    command = [PYTHON, "-m", "gateway", "--serial", str(simulator.link), "--baudrate",
               "4000000", "--frame-gap", "0", "--listen", f"127.0.0.1:{port}",
               "--metrics", f"127.0.0.1:{metrics_port}"]  # fmt: skip
    if audit is not None:
        command += ["--audit-log", str(audit)]
    server = Server(command, workdir, "audit" if audit else "plain")
    simulator.start()
    try:
        server.start()
        window = asyncio.run(load(port, server.pid, args.rate, args.seconds, args.masters))
        lost = dropped(metrics_port) if audit is not None else 0.0
    finally:
        server.stop()
        simulator.stop()
    span = window.end - window.start
    result: dict[str, float | str] = {
        "writes_sent": window.sent,
        "writes_per_s": round(window.answered / span, 1),
        "wrong": window.wrong,
        "gateway_cpu_us_per_write": round(1e6 * window.cpu_s / max(window.answered, 1), 1),
    }
    if audit is not None:
        records = [json.loads(line) for line in audit.read_text().splitlines()]
        writes = [r for r in records if r["event"] == "request"]
        inside = [r for r in writes if window.start <= _seconds(r["time"]) <= window.end]
        ok, message = verify_files([str(audit)])
        result |= {
            "audit_records_per_s": round(len(inside) / span, 1),
            "audit_records": len(writes),
            "audit_records_dropped": lost,
            "audit_verify": "intact" if ok else message,
            "audit_bytes_per_record": round(audit.stat().st_size / max(len(records), 1)),
        }
    return result


def _seconds(text: str) -> float:
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.audit", description=__doc__)
    parser.add_argument("--rate", type=float, default=1000.0, help="writes per second in all")
    parser.add_argument("--seconds", type=float, default=10.0, help="the measurement window")
    parser.add_argument("--masters", type=int, default=8)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-audit-") as directory:
        workdir = Path(directory)
        plain = run(workdir, None, args)
        audited = run(workdir, workdir / "audit.jsonl", args)
    print(json.dumps({"rate": args.rate, "without_audit": plain, "with_audit": audited}, indent=2))
    return 0 if audited.get("audit_verify") == "intact" and not audited["wrong"] else 1


if __name__ == "__main__":
    sys.exit(main())
