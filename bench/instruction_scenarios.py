"""``instructions``: user-space instructions per transaction, counted by valgrind, not timed.

CPU time on a shared VM moves with the neighbours (steal, a system call's cost on the
day): the floor's ratio spreads by about ±0.2 from one run to the next. valgrind's
callgrind counts the instructions a process executes in user space, the same on a busy
machine as on a quiet one. Each server runs twice under callgrind with one master polling,
for a short and a long window; the difference of the two counts over the difference of
the transactions served is the cost of one transaction, start-up and shut-down cancelled
out. One master keeps one transaction at a time, so the count does not depend on how
requests happen to batch under valgrind's slowdown. The kernel's instructions are not
counted: both servers make the same system calls per transaction (two reads, two writes,
the waits), so their kernel time is alike and the user-space difference is the gateway's.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .procs import Server, SimOptions, gateway_build
from .scenarios import (
    HEALTHY_UNITS,
    UNPACED_BAUDRATE,
    Bench,
    Run,
    ScenarioResult,
    ServerFactory,
    Table,
    _fmt,
    bare_server,
    gateway_server,
)

#: valgrind runs a Python process 20-50 times slower: its start and its stop take seconds.
VALGRIND_START_S = 180.0
VALGRIND_STOP_S = 120.0
_SUMMARY = re.compile(r"^(?:summary|totals):\s*(\d+)", re.MULTILINE)


def valgrind() -> str | None:
    """valgrind's path, or None when it is not installed."""
    return shutil.which("valgrind")


def under_callgrind(factory: ServerFactory, out_file: Path) -> ServerFactory:
    """``factory``'s server, run under callgrind writing its counts to ``out_file``."""
    path = valgrind()
    if path is None:
        raise FileNotFoundError("valgrind is not installed (apt-get install valgrind)")

    def make(workdir: Path, link: str, port: int) -> Server:
        server = factory(workdir, link, port)
        server.command[:0] = [path, "--tool=callgrind", f"--callgrind-out-file={out_file}"]
        server.ready_timeout = VALGRIND_START_S
        server.stop_timeout = VALGRIND_STOP_S
        return server

    return make


def instructions_in(out_file: Path) -> int:
    """The instructions a callgrind output file counts for the whole process."""
    match = _SUMMARY.search(out_file.read_text(errors="replace"))
    if match is None:
        raise ValueError(f"{out_file}: no 'summary:' or 'totals:' line (did the process exit?)")
    return int(match[1])


def per_transaction(short: tuple[int, int], long: tuple[int, int]) -> float:
    """Instructions per transaction from two runs of (transactions, instructions) each."""
    transactions = long[0] - short[0]
    if transactions <= 0:
        raise ValueError(f"the long run served {long[0]} transactions, the short {short[0]}")
    return (long[1] - short[1]) / transactions


@dataclass
class Counted:
    """One server's two runs under callgrind."""

    runs: list[Run]
    transactions: list[int]
    instructions: list[int]

    @property
    def per_transaction(self) -> float:
        """Instructions per transaction (see the module docstring)."""
        return per_transaction(
            (self.transactions[0], self.instructions[0]),
            (self.transactions[1], self.instructions[1]),
        )


def count(
    bench: Bench, label: str, factory: ServerFactory, windows: tuple[float, float]
) -> Counted:
    """Run ``factory``'s server under callgrind for each window, one master polling."""
    counted = Counted([], [], [])
    with tempfile.TemporaryDirectory(prefix="modbus-bench-callgrind-") as temp:
        for index, window in enumerate(windows):
            out_file = Path(temp) / f"run{index}.out"
            spec = bench._poll_spec(1, HEALTHY_UNITS, warmup=0.0, duration=window, drain=1.0)
            spec.connect_timeout = VALGRIND_START_S
            run = bench._run(
                f"{label} under callgrind, {window:g} s",
                SimOptions(units=HEALTHY_UNITS),
                under_callgrind(factory, out_file),
                spec,
                reference=label != "gateway",
            )
            counted.runs.append(run)
            counted.transactions.append(run.load.requests_sent - run.load.lost)
            counted.instructions.append(instructions_in(out_file))
    return counted


def instructions(bench: Bench) -> ScenarioResult:
    """The gateway's and the bare forwarder's user-space instructions per transaction."""
    if valgrind() is None:
        note = "valgrind is not installed (apt-get install valgrind): nothing counted"
        bench.progress(f"  instructions: {note}")
        return ScenarioResult("instructions", {"skipped": note}, [], [], 0, [note])
    windows = (
        (1.0, 2.5) if bench.timing.tiny else ((1.5, 4.0) if bench.timing.quick else (2.0, 8.0))
    )
    sides: dict[str, Counted] = {
        "gateway": count(
            bench, "gateway", gateway_server(UNPACED_BAUDRATE, frame_gap=0.0), windows
        ),
        "bare forwarder": count(bench, "bare forwarder", bare_server(), windows),
    }
    table = Table(
        f"User-space instructions per transaction (valgrind callgrind), gateway "
        f"({gateway_build()}) vs bare forwarder, unpaced pty, 1 master, FC03 x 10 across 4 slaves",
        ["server", "windows s", "transactions", "instructions", "per transaction", "wrong"],
    )
    figures: dict[str, Any] = {"windows_s": list(windows)}
    for label, counted in sides.items():
        table.rows.append([
            label, " / ".join(f"{w:g}" for w in windows),
            " / ".join(f"{t:,}" for t in counted.transactions),
            " / ".join(f"{i:,}" for i in counted.instructions),
            _fmt(counted.per_transaction, 0),
            str(sum(run.load.wrong_answers for run in counted.runs)),
        ])  # fmt: skip
        figures[label] = {
            "transactions": counted.transactions,
            "instructions": counted.instructions,
            "per_transaction": counted.per_transaction,
            "runs": [run.as_json() for run in counted.runs],
        }
    ratio = sides["gateway"].per_transaction / sides["bare forwarder"].per_transaction
    figures["ratio"] = ratio
    table.rows.append(["gateway / bare forwarder", "", "", "", f"{ratio:.2f}x", ""])
    wrong = sum(run.load.wrong_answers for run in sides["gateway"].runs)
    notes = [
        "counted, not timed: the same on a busy machine as on a quiet one; the kernel's "
        "instructions are left out (both servers make the same system calls per transaction), "
        "so this is the floor's ratio for the user-space part alone",
    ]
    return ScenarioResult("instructions", figures, [table], [], wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {
    "instructions": instructions,
}
