"""Scenarios of learned response timing, at the gateway's default settings.

``bimodal``: a slave answering in a few milliseconds, but 0.5 s on 10 % of its reads and
on its very first one (a meter reading EEPROM, a controller computing a value): the
learned timeout must cover the slow answers, so no exception reaches the master.
``learned-dies``: a slave the gateway has learned to be fast falls silent: the master's
first 0x0B must arrive before its own 1 s timeout (the learned bound plus a backed-off
retry). The third figure the issue asks for, a dead slave among five, is
``dead-default`` (``line_scenarios``), at the default (now learned) timeout.
"""

from __future__ import annotations

from collections.abc import Callable

from .line_scenarios import _fault_checks, _spec, _tolerated, _wrong
from .scenarios import (
    FAULT_BAUDRATE,
    Bench,
    Check,
    Run,
    ScenarioResult,
    Table,
    _errors_text,
    _fmt,
    gateway_server,
    paced_sim,
)

SLOW_SHARE = 0.1  #: the bimodal slave's share of slow reads
SLOW_S = 0.5  #: ... and how slow they are
WARM_UP_S = 3.0  #: about 30 requests of one master at 19200 baud (10 % of them 0.5 s)
MASTER_TIMEOUT_S = 1.0  #: the master's own timeout the first 0x0B must beat
DIES_AFTER_S = 4.0
DIES_BAUDRATES = (19200, 115200)


def bimodal(bench: Bench) -> ScenarioResult:
    """One master polls a slave that is slow on 10 % of its reads; the gateway's defaults."""
    window = bench.timing.pick(60.0, 20.0, 3.0)
    run = bench._run(
        f"a slave slow ({SLOW_S:g} s) on {SLOW_SHARE:.0%} of its reads and its first one, "
        f"{FAULT_BAUDRATE} baud, default timeout and retries",
        paced_sim(FAULT_BAUDRATE, (1,), late=[(1, SLOW_SHARE, SLOW_S, SLOW_S)], late_first=(1,)),
        gateway_server(FAULT_BAUDRATE),
        _spec(bench, 1, (1,), window, warmup=WARM_UP_S if not bench.timing.tiny else 1.0),
    )
    exceptions = sum(run.load.exceptions.values())
    slow = run.sim.get("late", {}).get("sent", 0)
    table = Table(
        f"A bimodal slave: a few ms, {SLOW_S:g} s on {SLOW_SHARE:.0%} of reads and the first, "
        f"{FAULT_BAUDRATE} baud, one master, the gateway's defaults (timeout \"auto\": learned)",
        ["good answers", "slow answers sent", "exceptions (after warm-up)", "p99 ms", "max ms",
         "wrong", "other errors"],
    )  # fmt: skip
    table.rows.append([
        str(run.load.ok), str(slow), str(exceptions), _fmt(run.load.latency_ms.get("p99", 0.0)),
        _fmt(run.load.latency_ms.get("max", 0.0)), str(run.load.wrong_answers),
        _errors_text(run.load),
    ])  # fmt: skip
    checks = [
        Check("bimodal slave: exceptions after warm-up", exceptions, "0", exceptions == 0),
        *_fault_checks("bimodal slave", [run]),
    ]
    notes = [
        f"warm-up {WARM_UP_S:g} s (about 30 requests) before the window; the slave's slow "
        "reads are written whole when their last byte would leave the wire, and it ignores "
        "requests meanwhile (a single-threaded device)",
    ]
    figures = {"exceptions": exceptions, "slow_answers": slow, "run": run.as_json()}
    return ScenarioResult("bimodal", figures, [table], checks, _wrong(run), notes)


def _dies_run(bench: Bench, baudrate: int) -> Run:
    before = bench.timing.pick(DIES_AFTER_S, DIES_AFTER_S, 1.0)
    after = bench.timing.pick(6.0, 4.0, 1.0)
    spec = _spec(bench, 1, (1,), before + after, flaky_units=[1], exception_pause=0.1)
    spec.kill_after = before
    return bench._run(
        f"{baudrate} baud, the slave falls silent after {before:g} s, default timeout and retries",
        paced_sim(baudrate, (1,), die_on_signal=(1,)),
        gateway_server(baudrate),
        spec,
    )


def learned_dies(bench: Bench) -> ScenarioResult:
    """A slave learned fast dies: how long its master waits for the first 0x0B."""
    table = Table(
        "A learned slave dies: one master polls it; the longest wait for an answer is the "
        "first 0x0B's (two attempts: the learned bound, then twice it)",
        ["baud", "good answers", "0x0B", "longest wait ms", "wrong", "other errors"],
    )
    figures: dict[str, object] = {}
    checks: list[Check] = []
    runs: list[Run] = []
    for baudrate in DIES_BAUDRATES[:1] if bench.timing.tiny else DIES_BAUDRATES:
        run = _dies_run(bench, baudrate)
        runs.append(run)
        longest = run.load.latency_ms.get("max", 0.0)
        table.rows.append([
            str(baudrate), str(run.load.ok), _tolerated(run), _fmt(longest),
            str(run.load.wrong_answers), _errors_text(run.load),
        ])  # fmt: skip
        figures[str(baudrate)] = {"longest_wait_ms": longest, "run": run.as_json()}
        checks.append(
            Check(f"learned slave dies ({baudrate} baud): first 0x0B", longest,
                  f"< {1000 * MASTER_TIMEOUT_S:g}", longest < 1000 * MASTER_TIMEOUT_S, "ms")
        )  # fmt: skip
    checks += _fault_checks("learned slave dies", runs)
    notes = ["the longest wait of any answer in the window: every live answer is a few ms"]
    wrong = sum(_wrong(run) for run in runs)
    return ScenarioResult("learned-dies", figures, [table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {
    "bimodal": bimodal,
    "learned-dies": learned_dies,
}
