"""Scenarios of the serial line under stress: late answers, a slave dying, greedy masters.

Each measures what issue 8 ("the line as a pure state machine") asks of the line,
end to end through the real gateway, and reports zero wrong answers as a figure,
not an assumption: the slaves' registers encode (unit, address) and every poll
reads a block no recent request to that unit read (``bench.values``), so an
answer handed to the wrong request is caught. ``floor`` compares the gateway's
CPU per transaction with a bare forwarder (``bench.bare_forwarder``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from .loadgen import GATEWAY_BUSY, PATH_UNAVAILABLE, TARGET_FAILED, TIMELINE_BUCKET_S, LoadSpec
from .procs import SimOptions, gateway_build
from .scenarios import (
    FAULT_BAUDRATE,
    HEALTHY_UNITS,
    REFERENCE_BAUDRATE,
    UNPACED_BAUDRATE,
    UNPACED_MASTERS,
    Bench,
    Check,
    Run,
    ScenarioResult,
    Table,
    _errors_text,
    _fmt,
    bare_server,
    forwarder_server,
    gateway_server,
    paced_sim,
)
from .wire import fc03_budget

FLOOR_TARGET = 1.3  #: gateway CPU per transaction at most this many times the bare forwarder's
LATE_TIMEOUT_S = 0.5  #: the gateway's --timeout in the late scenarios
LATE_DELAY = (1.1, 2.6)  #: late answers come this many timeouts after the request (0.55-1.3 s)
LATE_SHARE = 0.05
LATE_SHARE_TINY = 0.3  #: --tiny: a 2 s run must still see late answers
DEAD_FIRST_S = 16.0  #: "the first 16 s after it dies"
GREEDY_MASTERS = 17
GREEDY_PIPELINE = 16
GREEDY_BAUDRATE = 9600
POLITE_PERIOD_S = 1.0
ABSENT_MASTERS = 8
ABSENT_UNITS = list(range(100, 248))  #: never on the line; each needs 3 timeouts to be isolated
#: A master whose request was refused (0x0A, 0x06, 0x0B) sends its next one this much later:
#: at once would be a busy loop between the load generator and the gateway on 2 shared cores.
REFUSED_PAUSE_S = 0.1
LONG_WAIT_S = 120.0  #: no answer counts as lost before this (queues here hold answers for long)


def _spec(
    bench: Bench, masters: int, units: Sequence[int], window: float, **extra: Any
) -> LoadSpec:
    spec = LoadSpec(port=0, masters=masters, units=list(units))
    spec.warmup = bench.timing.pick(2.0, 1.0, 0.3)
    spec.duration = window
    spec.drain = bench.timing.pick(1.0, 1.0, 0.3)
    spec.request_timeout = LONG_WAIT_S
    for key, value in extra.items():
        setattr(spec, key, value)
    return spec


def _wrong(run: Run) -> int:
    return run.load.wrong_answers + run.load.read_after_write_violations


def _tolerated(run: Run) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(run.load.tolerated.items())) or "0"


def _fault_checks(name: str, runs: Sequence[Run]) -> list[Check]:
    wrong = sum(_wrong(run) for run in runs)
    early = sum(run.early_requests for run in runs)
    return [
        Check(f"{name}: wrong answers + read-after-write", wrong, "0", wrong == 0),
        Check(f"{name}: early requests", early, "0", early == 0),
    ]


# -- the floor --------------------------------------------------------------------------


def floor(bench: Bench) -> ScenarioResult:
    """The gateway's CPU per transaction against the bare forwarder's, unpaced, 1/10/100 masters.

    Gateway and bare forwarder alternate (3 + 2 runs per number of masters, 2 + 1 with
    ``--quick``, 1 + 1 with ``--tiny``) and each side's runs are averaged, so a change in
    the machine's other load weighs on both sides alike.
    """
    masters_list = (1, 10) if bench.timing.tiny else UNPACED_MASTERS
    table = Table(
        f"The floor: gateway ({gateway_build()}) vs a bare forwarder (bench/bare_forwarder.py), "
        "unpaced pty, --frame-gap 0, FC03 x 10 across 4 slaves",
        ["masters", "server", "tx/s", "p99 ms", "CPU us/tx", "other load", "wrong", "errors"],
    )
    figures: dict[str, Any] = {}
    checks: list[Check] = []
    for masters in masters_list:
        ours: list[Run] = [bench.unpaced(masters)]
        bare: list[Run] = []
        rows: list[tuple[str, Run]] = [("gateway", ours[0])]
        rounds = 1 if bench.timing.tiny else (2 if bench.timing.quick else 3)
        for index in range(1, 2 * rounds):  # gateway, bare, gateway, bare, gateway ...
            if index % 2:
                bare.append(bench._run(
                    f"bare forwarder, unpaced, {masters} masters",
                    SimOptions(units=HEALTHY_UNITS),
                    bare_server(),
                    bench._poll_spec(masters, HEALTHY_UNITS),
                    reference=True,
                ))  # fmt: skip
                rows.append(("bare forwarder", bare[-1]))
            else:
                ours.append(bench._run(
                    f"gateway, unpaced, {masters} masters, again",
                    SimOptions(units=HEALTHY_UNITS),
                    gateway_server(UNPACED_BAUDRATE, frame_gap=0.0),
                    bench._poll_spec(masters, HEALTHY_UNITS),
                ))  # fmt: skip
                rows.append(("gateway", ours[-1]))
        if masters == 10 and not bench.timing.tiny:
            pymodbus = bench._run(
                "pymodbus forwarder, unpaced, 10 masters",
                SimOptions(units=HEALTHY_UNITS),
                forwarder_server(REFERENCE_BAUDRATE),
                bench._poll_spec(masters, HEALTHY_UNITS),
                reference=True,
            )
            rows.append(("pymodbus forwarder", pymodbus))
        for label, run in rows:
            load = run.load
            table.rows.append([
                str(masters), label, _fmt(load.ok_per_s, 0), _fmt(load.latency_ms["p99"], 2),
                _fmt(run.cpu_us_per_tx), f"{run.background_cores:.2f}",
                str(load.wrong_answers), _errors_text(load),
            ])  # fmt: skip
        ours_cpu = sum(run.cpu_us_per_tx for run in ours) / len(ours)
        bare_cpu = sum(run.cpu_us_per_tx for run in bare) / len(bare)
        ratio = ours_cpu / bare_cpu if bare_cpu else 0.0
        table.rows.append([str(masters), "mean gateway / mean bare, CPU per tx", "", "",
                           f"{ratio:.2f}x", "", "", ""])  # fmt: skip
        figures[str(masters)] = {
            "gateway_cpu_us_per_tx": [run.cpu_us_per_tx for run in ours],
            "bare_cpu_us_per_tx": [run.cpu_us_per_tx for run in bare],
            "gateway_tx_per_s": [run.load.ok_per_s for run in ours],
            "bare_tx_per_s": [run.load.ok_per_s for run in bare],
            "cpu_ratio": ratio,
            "bare_runs": [run.as_json() for run in bare],
            "gateway_runs_again": [run.as_json() for run in ours[1:]],
        }
        checks.append(
            Check(f"floor: gateway/bare CPU per tx, {masters} masters", ratio,
                  f"<= {FLOOR_TARGET}x", 0 < ratio <= FLOOR_TARGET, "x")
        )  # fmt: skip
        checks.append(
            Check(f"floor: {masters} masters wrong answers", sum(_wrong(r) for r in ours), "0",
                  sum(_wrong(r) for r in ours) == 0)
        )  # fmt: skip
    notes = [
        "the bare forwarder has no validation, metrics, fairness, retries or frame gap; it is "
        "the floor a Python gateway on asyncio + uvloop can reach on this machine today, so "
        "the ratio, not the microseconds, is the figure to compare across days",
    ]
    wrong = sum(_wrong(run) for run in bench.runs if not run.reference and "unpaced" in run.label)
    return ScenarioResult("floor", figures, [table], checks, wrong, notes)


# -- late answers ------------------------------------------------------------------------


def _late_table(title: str) -> Table:
    return Table(
        title,
        ["run", "good tx/s", "late sent", "ignored busy", "0x0B (expected)", "wrong",
         "read-after-write", "early req.", "collisions", "other errors"],
    )  # fmt: skip


def _late_row(label: str, run: Run) -> list[str]:
    late = run.sim.get("late", {})
    return [
        label, _fmt(run.load.ok_per_s), str(late.get("sent", 0)), str(late.get("ignored_busy", 0)),
        _tolerated(run), str(run.load.wrong_answers), str(run.load.read_after_write_violations),
        str(run.early_requests), str(run.sim.get("collisions", 0)), _errors_text(run.load),
    ]  # fmt: skip


def _late_delays() -> tuple[float, float]:
    return LATE_DELAY[0] * LATE_TIMEOUT_S, LATE_DELAY[1] * LATE_TIMEOUT_S


def late_few(bench: Bench) -> ScenarioResult:
    """Unit 1 answers 5 % of its reads just past the timeout; retries 0 and the default.

    ``--tiny`` runs ``--retries 0`` only, with 30 % of the reads late.
    """
    low, high = _late_delays()
    window = bench.timing.pick(30.0, 12.0, 2.0)
    share = LATE_SHARE_TINY if bench.timing.tiny else LATE_SHARE
    table = _late_table(
        f"A slave answering {share:.0%} of reads {low:g}-{high:g} s late (timeout "
        f"{LATE_TIMEOUT_S:g} s), {FAULT_BAUDRATE} baud, 10 masters polling units 1 and 2"
    )
    runs: dict[str, Run] = {}
    for retries in (0,) if bench.timing.tiny else (0, None):
        label = "retries 0" if retries == 0 else "default retries"
        run = bench._run(
            f"late answers ({share:.0%}), {label}",
            paced_sim(FAULT_BAUDRATE, (1, 2), late=[(1, share, low, high)]),
            gateway_server(FAULT_BAUDRATE, timeout=LATE_TIMEOUT_S, retries=retries),
            _spec(bench, 10, (1, 2), window, flaky_units=[1]),
        )
        runs[label] = run
        table.rows.append(_late_row(label, run))
    notes = [
        "the late slave is busy until its late answer has gone: requests to it meanwhile are "
        "ignored (a single-threaded device); 0x0B for its reads is expected, wrong data never",
        "late answers are written whole when their last byte would leave the wire; the line's "
        "early-request counter does not count their wire time (the master cannot foresee it)",
    ]
    figures = {label: run.as_json() for label, run in runs.items()}
    checks = _fault_checks(f"late {share:.0%}", list(runs.values()))
    wrong = sum(_wrong(run) for run in runs.values())
    return ScenarioResult("late-few", figures, [table], checks, wrong, notes)


def late_all(bench: Bench) -> ScenarioResult:
    """Unit 3 answers every read late, beside two healthy slaves."""
    low, high = _late_delays()
    window = bench.timing.pick(30.0, 12.0, 2.0)
    table = _late_table(
        f"A slave answering every read {low:g}-{high:g} s late (timeout {LATE_TIMEOUT_S:g} s), "
        f"{FAULT_BAUDRATE} baud, 10 masters polling units 1, 2 and 3"
    )
    run = bench._run(
        "every answer of unit 3 late",
        paced_sim(FAULT_BAUDRATE, (1, 2, 3), late=[(3, 1.0, low, high)]),
        gateway_server(FAULT_BAUDRATE, timeout=LATE_TIMEOUT_S),
        _spec(bench, 10, (1, 2, 3), window, flaky_units=[3]),
    )
    table.rows.append(_late_row("default retries", run))
    healthy = sum(run.load.ok_per_s_by_unit.get(str(unit), 0.0) for unit in (1, 2))
    figures = {"healthy_tx_per_s": healthy, "run": run.as_json()}
    notes = [f"healthy units 1 and 2: {healthy:.1f} good answers/s together"]
    checks = _fault_checks("late, every answer", [run])
    return ScenarioResult("late-all", figures, [table], checks, _wrong(run), notes)


# -- a slave dies at the default settings -------------------------------------------------


def _window_sum(timeline: dict[str, list[int]], units: Sequence[int], start: float,
                end: float) -> int:  # fmt: skip
    first, last = round(start / TIMELINE_BUCKET_S), round(end / TIMELINE_BUCKET_S)
    return sum(sum(timeline.get(str(unit), [])[first:last]) for unit in units)


def _dead_run(bench: Bench, timeout: float | None) -> tuple[Run, dict[str, Any]]:
    """One run: 5 slaves, unit 5 dies ``before`` seconds into the window; the ratios."""
    before = bench.timing.pick(6.0, 4.0, 1.0)
    first = bench.timing.pick(DEAD_FIRST_S, DEAD_FIRST_S, 1.5)
    settle = bench.timing.pick(14.0, 0.0, 0.0)
    steady = bench.timing.pick(40.0, 8.0, 1.0)
    units = (*HEALTHY_UNITS, 5)
    spec = _spec(bench, 10, units, before + first + settle + steady, flaky_units=[5])
    spec.timeline = True
    spec.kill_after = before
    setting = "default timeout" if timeout is None else f"timeout {timeout:g} s"
    run = bench._run(
        f"{FAULT_BAUDRATE} baud, unit 5 dies after {before:g} s, {setting}, default retries",
        paced_sim(FAULT_BAUDRATE, units, die_on_signal=(5,)),
        gateway_server(FAULT_BAUDRATE, timeout=timeout),
        spec,
    )
    timeline = run.load.timeline
    killed = run.load.killed_at if run.load.killed_at is not None else before
    baseline = _window_sum(timeline, units, 0.0, killed) / killed if killed else 0.0
    first_rate = _window_sum(timeline, HEALTHY_UNITS, killed, killed + first) / first
    steady_start = killed + first + settle
    steady_end = min(run.load.window_s, steady_start + steady)
    steady_rate = (
        _window_sum(timeline, HEALTHY_UNITS, steady_start, steady_end) / (steady_end - steady_start)
        if steady_end > steady_start
        else 0.0
    )
    return run, {
        "baseline_tx_per_s": baseline,
        "first_tx_per_s": first_rate,
        "steady_tx_per_s": steady_rate,
        "first_ratio": first_rate / baseline if baseline else 0.0,
        "steady_ratio": steady_rate / baseline if baseline else 0.0,
        "killed_at_s": killed,
        "steady_s": [steady_start, steady_end],
        "windows_s": {"first": first, "settle": settle, "steady": steady},
    }


def dead_default(bench: Bench) -> ScenarioResult:
    """One slave of 5 dies mid-run at 19200 baud, at the gateway's default timeout and retries.

    Run again with ``--timeout 1`` (the default when issue 8 was filed; ``timeout = "auto"``
    is shorter at 19200 baud), except with ``--tiny``.
    """
    variants: tuple[float | None, ...] = (None,) if bench.timing.tiny else (None, 1.0)
    table = Table(
        f"A slave dies: 5 slaves at {FAULT_BAUDRATE} baud, 10 masters polling each in turn, unit 5 "
        "falls silent; the gateway's default retries",
        ["gateway timeout", "period", "seconds", "healthy tx/s", "ratio"],
    )
    figures: dict[str, Any] = {}
    checks: list[Check] = []
    runs: list[Run] = []
    for timeout in variants:
        run, found = _dead_run(bench, timeout)
        runs.append(run)
        name = "default" if timeout is None else f"{timeout:g} s"
        killed, first = found["killed_at_s"], found["windows_s"]["first"]
        steady_start, steady_end = found["steady_s"]
        table.rows += [
            [name, "before (all 5 alive, every answer)", f"0-{killed:.1f}",
             _fmt(found["baseline_tx_per_s"]), "1.000"],
            [name, f"first {first:g} s after it dies", f"{killed:.1f}-{killed + first:.1f}",
             _fmt(found["first_tx_per_s"]), f"{found['first_ratio']:.3f}"],
            [name, "steady state", f"{steady_start:.1f}-{steady_end:.1f}",
             _fmt(found["steady_tx_per_s"]), f"{found['steady_ratio']:.3f}"],
            [name, f"wrong {run.load.wrong_answers}, read-after-write "
             f"{run.load.read_after_write_violations}, early {run.early_requests}, "
             f"0x0B {_tolerated(run)}, other errors {_errors_text(run.load)}", "", "", ""],
        ]  # fmt: skip
        if timeout is None:
            figures.update(found)
            figures["run"] = run.as_json()
        else:
            figures[f"timeout_{timeout:g}s"] = {**found, "run": run.as_json()}
        checks += [
            Check(f"dead slave ({name} timeout): first {first:g} s", found["first_ratio"],
                  ">= 0.85", found["first_ratio"] >= 0.85, "x"),
            Check(f"dead slave ({name} timeout): steady state", found["steady_ratio"],
                  ">= 0.97", found["steady_ratio"] >= 0.97, "x"),
        ]  # fmt: skip
    checks += _fault_checks("dead slave (defaults)", runs)
    after = figures["windows_s"]["first"] + figures["windows_s"]["settle"]
    notes = [
        "ratio = the healthy slaves' good answers per second / every slave's before the death "
        "(the whole wire, the same polling), measured in the same run; the steady state starts "
        f"{after:g} s after the death"
        + (" (quick and tiny runs: right after the first window)" if bench.timing.quick else ""),
        'the default timeout is the gateway\'s ("auto" since it was introduced: the longest '
        "answer at the line's settings + 0.1 s, about 0.23 s at 19200 baud); 1 s was the "
        "default when issue 8 was filed",
    ]
    wrong = sum(_wrong(run) for run in runs)
    return ScenarioResult("dead-default", figures, [table], checks, wrong, notes)


# -- masters that take more than their share ---------------------------------------------


def greedy(bench: Bench) -> ScenarioResult:
    """17 masters x 16 pipelined reads at 9600 baud, and one master polling once a second."""
    window = bench.timing.pick(30.0, 12.0, 2.5)
    polite = {"name": "polite", "masters": 1, "units": [1], "mode": "slow",
              "period": POLITE_PERIOD_S}  # fmt: skip
    spec = _spec(
        bench, GREEDY_MASTERS, HEALTHY_UNITS, window, pipeline=GREEDY_PIPELINE,
        tolerate=[PATH_UNAVAILABLE, GATEWAY_BUSY], groups=[polite],
        exception_pause=REFUSED_PAUSE_S,
    )  # fmt: skip
    run = bench._run(
        f"{GREEDY_MASTERS} greedy masters x {GREEDY_PIPELINE} + 1 polite, {GREEDY_BAUDRATE} baud",
        paced_sim(GREEDY_BAUDRATE),
        gateway_server(GREEDY_BAUDRATE),
        spec,
    )
    groups = run.load.groups
    table = Table(
        f"Greedy masters: {GREEDY_MASTERS} masters x {GREEDY_PIPELINE} pipelined reads at "
        f"{GREEDY_BAUDRATE} baud, plus one master polling once a second",
        ["masters", "sent", "answers", "good", "good share", "p50 ms", "p99 ms",
         "busy/unavailable (expected)", "other exceptions", "wrong", "lost"],
    )  # fmt: skip
    for name in ("main", "polite"):
        group = groups.get(name, {})
        table.rows.append([
            "greedy" if name == "main" else "polite", str(group.get("sent", 0)),
            str(group.get("answers", 0)), str(group.get("ok", 0)),
            f"{group.get('ok_share', 0.0):.3f}", _fmt(group.get("latency_ms", {}).get("p50", 0)),
            _fmt(group.get("latency_ms", {}).get("p99", 0)),
            ", ".join(f"{k} {v}" for k, v in sorted(group.get("tolerated", {}).items())) or "0",
            ", ".join(f"{k} {v}" for k, v in sorted(group.get("exceptions", {}).items())) or "0",
            str(group.get("wrong", 0)), str(group.get("lost", 0)),
        ])  # fmt: skip
    share = float(groups.get("polite", {}).get("ok_share", 0.0))
    figures = {"polite_good_share": share, "groups": groups, "run": run.as_json()}
    checks = [
        Check("greedy masters: polite master's good answers", share, ">= 0.95", share >= 0.95),
        *_fault_checks("greedy masters", [run]),
    ]
    notes = [
        "the greedy masters' 0x0A (line queue full) and 0x06 (their own queue full) are "
        f"expected; the polite master's are not. A refused greedy request is sent again "
        f"{REFUSED_PAUSE_S:g} s later (the others stay in flight)",
    ]
    return ScenarioResult("greedy", figures, [table], checks, _wrong(run), notes)


def absent(bench: Bench) -> ScenarioResult:
    """8 masters polling absent units, one polling a live slave: the live one's wire share."""
    window = bench.timing.pick(30.0, 15.0, 2.0)
    live = {"name": "live", "masters": 1, "units": [1]}
    spec = _spec(
        bench, ABSENT_MASTERS, ABSENT_UNITS, window,
        tolerate=[TARGET_FAILED, PATH_UNAVAILABLE, GATEWAY_BUSY], groups=[live],
        exception_pause=REFUSED_PAUSE_S,
    )  # fmt: skip
    run = bench._run(
        f"{ABSENT_MASTERS} masters polling absent units + 1 polling unit 1, {FAULT_BAUDRATE} baud",
        paced_sim(FAULT_BAUDRATE, (1,)),
        gateway_server(FAULT_BAUDRATE),
        spec,
    )
    budget = fc03_budget(FAULT_BAUDRATE)
    group = run.load.groups.get("live", {})
    ok = int(group.get("ok", 0))
    window_s = run.load.window_s or window
    share = ok * budget.transaction_s / window_s
    fair = 1.0 / (ABSENT_MASTERS + 1)
    table = Table(
        f"Masters polling absent units: {ABSENT_MASTERS} masters rotating over units 100-247 "
        f"(none on the line), one polling unit 1; {FAULT_BAUDRATE} baud, default timeout and "
        "retries",
        ["live master", "good answers", "window s", "wire share", "fair share", "share / fair",
         "p50 ms", "max ms", "wrong", "early req."],
    )  # fmt: skip
    table.rows.append([
        "unit 1", str(ok), f"{window_s:.1f}", f"{share:.4f}", f"{fair:.4f}",
        f"{share / fair:.3f}", _fmt(group.get("latency_ms", {}).get("p50", 0)),
        _fmt(group.get("latency_ms", {}).get("max", 0)), str(run.load.wrong_answers),
        str(run.early_requests),
    ])  # fmt: skip
    figures = {"live_wire_share": share, "fair_share": fair, "groups": run.load.groups,
               "run": run.as_json()}  # fmt: skip
    checks = [
        Check("absent units: live master's wire share / fair share", share / fair, ">= 1.0",
              share >= fair, "x"),
        *_fault_checks("absent units", [run]),
    ]  # fmt: skip
    notes = [
        "wire share = the live master's good answers x one FC03 transaction's wire time "
        f"({1000 * budget.transaction_s:.1f} ms) / the window; fair share = 1 / "
        f"{ABSENT_MASTERS + 1} masters",
    ]
    return ScenarioResult("absent", figures, [table], checks, _wrong(run), notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {
    "floor": floor,
    "late-few": late_few,
    "late-all": late_all,
    "dead-default": dead_default,
    "greedy": greedy,
    "absent": absent,
}
