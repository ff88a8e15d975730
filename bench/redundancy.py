"""An active/standby pair on one simulated 9600-baud bus: takeovers, collisions, forwarding cost.

Two gateway processes share a ``MultidropBus`` with the simulator's slaves
(``bench.pair_lab``), at the defaults (a 1 s lease, a takeover after 1.5 s of quiet).
A master polls through the standby; the active is killed (``kill -9``), the standby
takes over, the killed one is restarted (it stays standby) and the master moves to it;
then again, ``kills`` times. Reported: the longest gap between good answers for that
master at each kill (target: the worst <= 3 s), collisions and seconds with two writers
on the bus's own timestamps (target: 0), wrong answers (target: 0), and what forwarding
through the standby adds to a read's latency (p50, p99) against the same reads sent to
the active.

    python -m bench redundancy          # in the benchmark's report
    python -m bench.redundancy [--kills N]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from .pair_lab import GatewayProc, PairLab, Poller
from .report import render_checks, render_table
from .scenarios import Bench, Check, ScenarioResult, Table

WORST_GAP_TARGET_S = 3.0
LATENCY_READS = 200


def _quantile(values: Sequence[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


def _roles(a: GatewayProc, b: GatewayProc) -> tuple[GatewayProc, GatewayProc]:
    """(active, standby), once both say so."""
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
        found = a.role(), b.role()
        if found == ("active", "standby"):
            return a, b
        if found == ("standby", "active"):
            return b, a
        time.sleep(0.05)  # polling HTTP endpoints
    raise RuntimeError(f"no active/standby pair:\n{a.log}\n{b.log}")


def _latency(lab: PairLab, active: GatewayProc, standby: GatewayProc) -> dict[str, float]:
    """p50 and p99 of the same reads sent to the active and through the standby."""
    figures: dict[str, float] = {}
    for label, gateway in (("direct", active), ("forwarded", standby)):
        poller = Poller(gateway.modbus, period=0.0)
        deadline = time.monotonic() + 60.0
        while len(poller.latencies) < LATENCY_READS and time.monotonic() < deadline:
            time.sleep(0.05)  # sampling a thread's progress
        poller.stop()
        figures[f"{label}_p50_ms"] = 1000 * _quantile(poller.latencies, 0.5)
        figures[f"{label}_p99_ms"] = 1000 * _quantile(poller.latencies, 0.99)
    figures["added_p50_ms"] = figures["forwarded_p50_ms"] - figures["direct_p50_ms"]
    figures["added_p99_ms"] = figures["forwarded_p99_ms"] - figures["direct_p99_ms"]
    return figures


def _kill_once(lab: PairLab, active: GatewayProc, standby: GatewayProc, poller: Poller) -> float:
    """Kill the active while ``poller`` polls through the standby; the gap it saw."""
    poller.retarget(standby.modbus)
    lab.bus.wait_for(lambda s: len(s.frames_of(active.name)) > 0, timeout=15.0)
    good_before = poller.tally.good
    deadline = time.monotonic() + 15.0
    while poller.tally.good < good_before + 5:  # served through the standby first
        if time.monotonic() > deadline:
            raise RuntimeError(f"no answers through the standby:\n{standby.log}")
        time.sleep(0.02)
    killed = time.monotonic()
    active.kill()
    good_at_kill = poller.tally.good
    deadline = time.monotonic() + 20.0
    while poller.tally.good < good_at_kill + 5:
        if time.monotonic() > deadline:
            raise RuntimeError(f"no takeover:\n{standby.log}")
        time.sleep(0.02)
    gap = poller.tally.longest_gap(killed, time.monotonic())
    lab.restart(active)  # the old active returns: it stays standby
    active.wait_role("standby", timeout=20.0)
    return gap


def measure(workdir: Path, kills: int) -> dict[str, object]:
    lab = PairLab(workdir)
    try:
        a, b = lab.pair()
        active, standby = _roles(a, b)
        latency = _latency(lab, active, standby)
        poller = Poller(standby.modbus)
        gaps = []
        for _ in range(kills):
            gaps.append(_kill_once(lab, active, standby, poller))
            active, standby = standby, active
        tally = poller.stop()
        stats = lab.bus.stats()
        return {
            "kills": kills,
            "gaps_s": [round(gap, 3) for gap in gaps],
            "worst_gap_s": max(gaps) if gaps else 0.0,
            "median_gap_s": statistics.median(gaps) if gaps else 0.0,
            "collisions": stats.collisions,
            "two_writer_s": stats.two_writer_s,
            "wrong_answers": len(tally.wrong),
            "good_answers": tally.good,
            "exceptions": {f"0x{code:02X}": count for code, count in tally.exceptions.items()},
            **latency,
        }
    finally:
        lab.close()


def result(figures: dict[str, object]) -> ScenarioResult:
    worst = float(figures["worst_gap_s"])  # type: ignore[arg-type]
    collisions = float(figures["collisions"])  # type: ignore[arg-type]
    two_writers = float(figures["two_writer_s"])  # type: ignore[arg-type]
    wrong = int(figures["wrong_answers"])  # type: ignore[call-overload]
    checks = [
        Check("worst gap after a kill -9 of the active", worst, f"<= {WORST_GAP_TARGET_S} s",
              worst <= WORST_GAP_TARGET_S, " s"),
        Check("collisions on the bus", collisions, "0", collisions == 0),
        Check("seconds with two writers", two_writers, "0", two_writers == 0, " s"),
        Check("wrong answers", wrong, "0", wrong == 0),
    ]  # fmt: skip
    table = Table("Redundant pair on one 9600-baud bus", ["figure", "value"])
    for key in ("kills", "median_gap_s", "worst_gap_s", "good_answers", "exceptions",
                "direct_p50_ms", "forwarded_p50_ms", "added_p50_ms", "direct_p99_ms",
                "forwarded_p99_ms", "added_p99_ms"):  # fmt: skip
        value = figures[key]
        table.rows.append([key, f"{value:.3f}" if isinstance(value, float) else str(value)])
    return ScenarioResult("redundancy", figures, [table], checks, wrong)


def run(bench: Bench) -> ScenarioResult:
    kills = int(bench.timing.pick(20, 5, 2))
    with tempfile.TemporaryDirectory(prefix="bench-pair-") as workdir:
        return result(measure(Path(workdir), kills))


SCENARIOS = {"redundancy": run}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.redundancy", description=__doc__)
    parser.add_argument("--kills", type=int, default=20)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-pair-") as workdir:
        figures = measure(Path(workdir), args.kills)
    scenario = result(figures)
    for table in scenario.tables:
        print(render_table(table))
    print(render_checks(scenario.checks))
    print(json.dumps(figures))
    return 0 if all(check.met for check in scenario.checks) else 1


if __name__ == "__main__":
    sys.exit(main())
