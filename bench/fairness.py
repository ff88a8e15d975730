"""A polite master beside 17 deep pipelines on a 9600-baud line: how long its one read waits.

docs/architecture.md promises that a master with nothing waiting goes next after the
transaction on the wire. Here 17 masters each keep 16 reads of 125 registers in flight
(272 requests offered against the line's ``max_queue`` of 256, so the full line pushes
requests out) and one master sends a one-register read every 0.5 s. Over real sockets, the
gateway process and the simulator on a paced pty, the polite master's wait must stay within
one long transaction: p99 <= 0.35 s and worst <= 0.6 s (a 125-register transaction takes
about 0.28 s at 9600 baud). The deep masters' share of the wire and its spread between them
are printed beside it.

    python -m bench fairness                   # in the benchmark's report
    python -m bench.fairness [--duration S]    # on its own: exit 1 when a target is missed
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .loadgen import GATEWAY_BUSY, PATH_UNAVAILABLE, LoadSpec
from .procs import BenchError, gateway_build
from .report import render_checks, render_table
from .scenarios import (
    HEALTHY_UNITS,
    Bench,
    Check,
    Run,
    ScenarioResult,
    Table,
    Timing,
    gateway_server,
    paced_sim,
)
from .wire import fc03_budget

DEEP_MASTERS = 17
DEEP_PIPELINE = 16
DEEP_QUANTITY = 125
BAUDRATE = 9600
POLITE_PERIOD_S = 0.5
POLITE_QUANTITY = 1
P99_TARGET_S = 0.35
WORST_TARGET_S = 0.6
WARMUP_S = 2.0  #: the deep queues fill and push-out starts before the window
REFUSED_PAUSE_S = 0.1  #: a deep master sends a refused request again this much later
LONG_WAIT_S = 120.0
DEFAULT_WINDOW_S = 25.0


def _spec(window: float, warmup: float) -> LoadSpec:
    polite = {"name": "polite", "masters": 1, "units": [1], "mode": "slow",
              "period": POLITE_PERIOD_S, "quantity": POLITE_QUANTITY}  # fmt: skip
    return LoadSpec(
        port=0, masters=DEEP_MASTERS, units=list(HEALTHY_UNITS), pipeline=DEEP_PIPELINE,
        quantity=DEEP_QUANTITY, warmup=warmup, duration=window, drain=1.0,
        request_timeout=LONG_WAIT_S, tolerate=[PATH_UNAVAILABLE, GATEWAY_BUSY],
        exception_pause=REFUSED_PAUSE_S, groups=[polite],
    )  # fmt: skip


def _figures(run: Run) -> dict[str, Any]:
    """The polite master's waits and the deep masters' share of the wire, from one run."""
    load = run.load
    window = load.window_s or 1.0
    polite = load.groups.get("polite", {})
    deep = load.groups.get("main", {})
    latency = polite.get("latency_ms", {})
    per_master = deep.get("ok_by_master", [])
    deep_tx = fc03_budget(BAUDRATE, DEEP_QUANTITY).transaction_s
    polite_tx = fc03_budget(BAUDRATE, POLITE_QUANTITY).transaction_s
    return {
        "polite_sent": polite.get("sent", 0),
        "polite_answers": polite.get("answers", 0),
        "polite_ok": polite.get("ok", 0),
        "polite_exceptions": polite.get("exceptions", {}),
        "polite_wait_s": {key: latency.get(key, 0.0) / 1000 for key in ("p50", "p99", "max")},
        "deep_ok": deep.get("ok", 0),
        "deep_wire_share": deep.get("ok_per_s", 0.0) * deep_tx,
        "polite_wire_share": polite.get("ok", 0) * polite_tx / window,
        "deep_ok_per_master": {
            "min": min(per_master, default=0),
            "max": max(per_master, default=0),
            "masters": len(per_master),
        },
        "deep_refused": deep.get("tolerated", {}),
        "wrong_answers": run.faults,
        "run": run.as_json(),
    }


def _table(figures: dict[str, Any]) -> Table:
    wait = figures["polite_wait_s"]
    spread = figures["deep_ok_per_master"]
    refused = ", ".join(f"{k} {v}" for k, v in sorted(figures["deep_refused"].items())) or "0"
    table = Table(
        f"Fair by wire time: {DEEP_MASTERS} masters x {DEEP_PIPELINE} reads of {DEEP_QUANTITY} "
        f"registers at {BAUDRATE} baud, one master reading {POLITE_QUANTITY} register every "
        f"{POLITE_PERIOD_S:g} s",
        ["polite sent", "good", "wait p50 ms", "p99 ms", "worst ms", "deep wire share",
         "deep good per master (min-max)", "deep refused (expected)", "wrong"],
    )  # fmt: skip
    table.rows.append([
        str(figures["polite_sent"]), str(figures["polite_ok"]), f"{1000 * wait['p50']:.0f}",
        f"{1000 * wait['p99']:.0f}", f"{1000 * wait['max']:.0f}",
        f"{figures['deep_wire_share']:.3f}", f"{spread['min']}-{spread['max']}", refused,
        str(figures["wrong_answers"]),
    ])  # fmt: skip
    return table


def checks_of(figures: dict[str, Any]) -> list[Check]:
    """The targets: the polite master's wait, every one of its answers good."""
    wait = figures["polite_wait_s"]
    answered = figures["polite_answers"] > 0 and figures["polite_ok"] == figures["polite_answers"]
    return [
        Check("fairness: polite master's wait p99", wait["p99"], f"<= {P99_TARGET_S:g}",
              answered and wait["p99"] <= P99_TARGET_S, " s"),
        Check("fairness: polite master's worst wait", wait["max"], f"<= {WORST_TARGET_S:g}",
              answered and wait["max"] <= WORST_TARGET_S, " s"),
    ]  # fmt: skip


def run_fairness(bench: Bench, window: float, warmup: float = WARMUP_S) -> ScenarioResult:
    """One run of the setup; its figures, table and targets."""
    run = bench._run(
        f"{DEEP_MASTERS} deep masters x {DEEP_PIPELINE} + 1 polite every "
        f"{POLITE_PERIOD_S:g} s, {BAUDRATE} baud",
        paced_sim(BAUDRATE),
        gateway_server(BAUDRATE),
        _spec(window, warmup),
    )
    figures = _figures(run)
    notes = [
        "wait = from the polite master's request to its answer, over TCP through the gateway; "
        "one 125-register transaction takes "
        f"{fc03_budget(BAUDRATE, DEEP_QUANTITY).transaction_s * 1000:.0f} ms of wire",
        "the deep masters' 0x0A (line queue full: pushed out) and 0x06 (their own queue full) "
        f"are expected; a refused request is sent again {REFUSED_PAUSE_S:g} s later",
    ]
    return ScenarioResult(
        "fairness", figures, [_table(figures)], checks_of(figures), run.faults, notes
    )


def fairness(bench: Bench) -> ScenarioResult:
    """The scenario as ``python -m bench`` runs it (window by its timing)."""
    window = bench.timing.pick(DEFAULT_WINDOW_S, 12.0, 4.0)
    return run_fairness(bench, window, bench.timing.pick(WARMUP_S, WARMUP_S, 1.0))


SCENARIOS = {"fairness": fairness}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m bench.fairness", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--duration",
        type=float,
        default=DEFAULT_WINDOW_S,
        help=f"measurement window, seconds (default {DEFAULT_WINDOW_S:g})",
    )
    parser.add_argument(
        "--warmup",
        type=float,
        default=WARMUP_S,
        help=f"before the window, seconds (default {WARMUP_S:g})",
    )
    parser.add_argument("--output", type=Path, help="also write the figures here as JSON")
    return parser  # fmt: skip


def main(argv: Sequence[str] | None = None) -> int:
    """Run once; 0 when both targets are met with no wrong answer, 1 if not, 2 on a failure."""
    args = _parser().parse_args(argv)
    root = str(Path(__file__).resolve().parent.parent)  # children import this checkout
    os.environ["PYTHONPATH"] = os.pathsep.join(
        [root, *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    )
    os.chdir(root)
    bench = Bench(Timing.make(False), lambda message: print(message, file=sys.stderr))
    print(f"gateway build: {gateway_build()}", file=sys.stderr)
    try:
        result = run_fairness(bench, args.duration, args.warmup)
    except BenchError as error:
        print(f"fairness: a process failed: {error}", file=sys.stderr)
        return 2
    print(render_table(result.tables[0]))
    for note in result.notes:
        print(f"  note: {note}")
    print()
    print(render_checks(result.checks))
    if args.output is not None:
        args.output.write_text(json.dumps(result.figures, indent=2) + "\n")
    met = all(check.met for check in result.checks) and result.wrong_answers == 0
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
