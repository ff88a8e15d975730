"""``python -m bench``: run the scenarios, print the tables, write the JSON results.

    python -m bench                       # every scenario
    python -m bench --quick               # shorter windows
    python -m bench late dead greedy      # chosen scenarios: a name, or the start of names
    python -m bench --scenario paced      # the same, as a flag (repeat it for more)
    python -m bench --tiny floor          # the smallest runs (the smoke test's)
    python -m bench --output /tmp/r.json  # results elsewhere than bench/results.json

Exit status: 0 when every run completed with zero wrong answers and zero
read-after-write violations (targets missed are reported, not failed), 1 when
an answer was wrong, 2 when a process failed to start or report.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import Any

from . import (
    agent,
    closed_loop,
    fairness,
    hostile,
    inflight_scenarios,
    instruction_scenarios,
    kind_scenarios,
    learning,
    line_scenarios,
    redundancy,
    reverse_scenarios,
    scenarios,
    slave_kind_scenarios,
    timing_scenarios,
    tls_scenarios,
    transport_scenarios,
)
from .procs import BenchError, environment_summary, gateway_build
from .report import render_checks, render_table
from .scenarios import Bench, ScenarioResult, Timing

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / "results.json"

#: Every scenario by name, in the order a full run takes them; each module keeps its own.
SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {
    **scenarios.SCENARIOS,
    **line_scenarios.SCENARIOS,
    **instruction_scenarios.SCENARIOS,
    **tls_scenarios.SCENARIOS,
    **transport_scenarios.SCENARIOS,
    **hostile.SCENARIOS,
    **kind_scenarios.SCENARIOS,
    **slave_kind_scenarios.SCENARIOS,
    **reverse_scenarios.SCENARIOS,
    **inflight_scenarios.SCENARIOS,
    **timing_scenarios.SCENARIOS,
    **fairness.SCENARIOS,
    **redundancy.SCENARIOS,
    **closed_loop.SCENARIOS,
    **learning.SCENARIOS,
    **agent.SCENARIOS,
}


def select(names: Sequence[str]) -> list[str]:
    """Scenario names for the command line's: a full name, or the start of several."""
    chosen: list[str] = []
    for name in names:
        matches = [name] if name in SCENARIOS else [n for n in SCENARIOS if n.startswith(name)]
        if not matches:
            raise ValueError(f"no scenario {name!r}; choose from {', '.join(SCENARIOS)}")
        chosen += [match for match in matches if match not in chosen]
    return chosen


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short windows")
    parser.add_argument("--tiny", action="store_true", help="the smallest runs (smoke tests)")
    parser.add_argument(
        "names",
        nargs="*",
        metavar="SCENARIO",
        help=f"scenarios to run, by name or the start of names ({', '.join(SCENARIOS)}); "
        "default: all",
    )
    parser.add_argument(
        "--scenario",
        action="append",
        default=[],
        metavar="NAME",
        help="run this scenario (repeat for more); the same as naming it",
    )
    parser.add_argument(
        "--output",
        type=Path,
        default=DEFAULT_OUTPUT,
        help="JSON results file (default: bench/results.json)",
    )
    return parser


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _interrupt(signum: int, frame: FrameType | None) -> None:
    """SIGTERM unwinds like Ctrl-C, so every simulator, server and load generator is stopped."""
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    """Run the chosen scenarios; see the module docstring for the exit status."""
    signal.signal(signal.SIGTERM, _interrupt)
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        names = select([*args.scenario, *args.names]) or list(SCENARIOS)
    except ValueError as error:
        parser.error(str(error))
    # The child processes import ``bench`` and ``gateway`` from this checkout.
    root = str(BENCH_DIR.parent)
    os.environ["PYTHONPATH"] = os.pathsep.join(
        [root, *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    )
    os.chdir(root)
    bench = Bench(Timing.make(args.quick, args.tiny), _progress)
    _progress(f"gateway build: {gateway_build()}")
    started = time.monotonic()
    results: list[ScenarioResult] = []
    failures: dict[str, str] = {}
    for name in names:
        _progress(f"scenario {name}:")
        try:
            results.append(SCENARIOS[name](bench))
        except BenchError as error:
            failures[name] = str(error)
            _progress(f"scenario {name} FAILED: {error}")
    elapsed = time.monotonic() - started

    print()
    for result in results:
        for table in result.tables:
            print(render_table(table))
        for note in result.notes:
            print(f"  note: {note}")
        print()
    checks = [check for result in results for check in result.checks]
    if checks:
        print(render_checks(checks))
        print()
    for name, reason in failures.items():
        print(f"scenario {name} failed: {reason}")
    if bench.runs:
        busiest = max(bench.runs, key=lambda run: run.background_cores)
        print(
            f"other load on the machine during the measurement windows: up to "
            f"{busiest.background_cores:.2f} CPU cores ({busiest.label}); figures taken while "
            "other work runs are pessimistic"
        )
    wrong = bench.gateway_faults
    print(f"{len(results)} scenario(s) in {elapsed:.0f} s ({gateway_build()} gateway); "
          "gateway wrong answers and "
          f"read-after-write violations: {wrong}; "
          f"targets met: {sum(c.met for c in checks)}/{len(checks)}")  # fmt: skip

    document: dict[str, Any] = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "quick": args.quick,
        "tiny": args.tiny,
        "elapsed_s": elapsed,
        "environment": environment_summary(),
        "wrong_answers": wrong,
        "max_background_cores": max((run.background_cores for run in bench.runs), default=0.0),
        "scenarios": {result.name: result.figures for result in results},
        "checks": [check.__dict__ for check in checks],
        "notes": {result.name: result.notes for result in results},
        "failures": failures,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(document, indent=2) + "\n")
    print(f"results written to {args.output}")
    if failures:
        return 2
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main())
