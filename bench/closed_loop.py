"""Masters that poll as fast as they are answered, and a periodic master beside absent units.

``closed-loop``: N masters each keep exactly one read outstanding, sending the next read
of 10 registers of a random slave 1-10 as soon as the last is answered. At 19200 baud
(10 and 30 masters, the simulator pacing answers like the wire) and on an unpaced pty
(100 masters), the gateway at its defaults and the bare forwarder (first come, first
served) run one after the other in the same invocation. Each request's wait, from its
sending to its answer, is held against the round a fair line gives it: first come, first
served makes every master wait for the N - 1 others, so p99 <= 1.5 x N x the mean
transaction time and worst <= 2 x N x it + 0.2 s, where the mean transaction time is the
server's own (the window over its good answers).

``absent-periodic``: a master reading 10 registers of unit 1 every 0.2 s (one read
outstanding, the next at its tick or at the answer, whichever is later: a SCADA poll
cycle), alone and then beside one connection that keeps 4 reads in flight to random unit
ids 100-247 (routed, no slave behind them). Its median wait may grow to max(10 x the
quiet median, 100 ms), its poll rate may fall to half the quiet one. A second master
reads unit 1 on a fixed 0.2 s clock, whether answered or not: its reads queue behind a
long wait where the cycle master's poll rate drops, so its median shows a hold-up that
the cycle master's median passes over while fewer than half its polls meet one.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .loadgen import GATEWAY_BUSY, PATH_UNAVAILABLE, TARGET_FAILED, LoadSpec
from .procs import SimOptions
from .scenarios import (
    UNPACED_BAUDRATE,
    Bench,
    Check,
    Run,
    ScenarioResult,
    ServerFactory,
    Table,
    bare_server,
    gateway_server,
    paced_sim,
)
from .wire import fc03_budget

BAUDRATE = 19200
UNITS = tuple(range(1, 11))
PACED_MASTERS = (10, 30)
UNPACED_MASTERS = 100
LINE_USE_TARGET = 0.9
P99_ROUNDS = 1.5  #: p99 <= this x N x the mean transaction time
WORST_ROUNDS = 2.0  #: worst <= this x N x the mean transaction time + WORST_SLACK_S
WORST_SLACK_S = 0.2
LONG_WAIT_S = 120.0  #: no answer counts as lost before this: a starved request is a wait
PERIODIC_PERIOD_S = 0.2
PERIODIC_UNIT = 1
ABSENT_UNITS = list(range(100, 248))
ABSENT_IN_FLIGHT = 4
#: The absent-unit connection sends a read answered with an exception again this much
#: later: at once would be a busy loop between the load generator and the gateway on 2
#: shared cores (what the gateway answers at once costs nothing on the line).
REFUSED_PAUSE_S = 0.1
MEDIAN_FACTOR = 10.0
MEDIAN_FLOOR_S = 0.1
RATE_SHARE = 0.5


def _spec(bench: Bench, window: float, **fields: Any) -> LoadSpec:
    spec = LoadSpec(port=0, **fields)
    spec.warmup = bench.timing.pick(2.0, 1.0, 0.5)
    spec.duration = window
    spec.drain = bench.timing.pick(2.0, 1.0, 0.5)
    spec.request_timeout = LONG_WAIT_S
    return spec


# -- closed loop -------------------------------------------------------------------------


def _closed_figures(run: Run, masters: int, paced: bool) -> dict[str, Any]:
    """One server's figures and targets at one number of masters."""
    load = run.load
    mean_tx = 1.0 / load.ok_per_s if load.ok_per_s else float("inf")
    line_use = load.ok_per_s / fc03_budget(BAUDRATE).max_per_s if paced else None
    wait = {key: load.latency_ms.get(key, 0.0) / 1000 for key in ("p50", "p99", "max")}
    # A read still unanswered when the window closed has waited at least this long.
    unanswered = load.groups.get("main", {}).get("oldest_unanswered_ms", 0.0) / 1000
    wait["max"] = max(wait["max"], unanswered)
    p99_limit = P99_ROUNDS * masters * mean_tx
    worst_limit = WORST_ROUNDS * masters * mean_tx + WORST_SLACK_S
    failures = sum(load.exceptions.values()) + load.lost + load.disconnects
    met = {
        "p99": load.ok > 0 and wait["p99"] <= p99_limit,
        "worst": load.ok > 0 and wait["max"] <= worst_limit,
        "exceptions": failures == 0,
    }
    if line_use is not None:
        met["line_use"] = line_use >= LINE_USE_TARGET
    per_master = load.groups.get("main", {}).get("ok_by_master", [])
    return {
        "masters": masters,
        "paced": paced,
        "tx_per_s": load.ok_per_s,
        "line_use": line_use,
        "mean_transaction_s": mean_tx,
        "wait_s": wait,
        "oldest_unanswered_s": unanswered,
        "good_per_master": {
            "min": min(per_master, default=0),
            "max": max(per_master, default=0),
            "masters": len(per_master),
        },
        "p99_limit_s": p99_limit,
        "worst_limit_s": worst_limit,
        "exceptions": dict(load.exceptions),
        "lost": load.lost,
        "disconnects": load.disconnects,
        "wrong_answers": run.faults,
        "early_requests": run.early_requests,
        "targets_met": met,
        "run": run.as_json(),
    }


def _closed_row(server: str, found: dict[str, Any]) -> list[str]:
    wait, met, spread = found["wait_s"], found["targets_met"], found["good_per_master"]
    exceptions = ", ".join(f"{k} {v}" for k, v in sorted(found["exceptions"].items()))
    for name in ("lost", "disconnects"):
        if found[name]:
            exceptions += f"{', ' if exceptions else ''}{name} {found[name]}"
    missed = [name for name, ok in met.items() if not ok]
    line_use = found["line_use"]
    return [
        str(found["masters"]), server, "-" if line_use is None else f"{line_use:.3f}",
        f"{found['tx_per_s']:,.1f}", f"{1000 * found['mean_transaction_s']:.2f}",
        f"{1000 * wait['p50']:,.0f}", f"{1000 * wait['p99']:,.0f}", f"{1000 * wait['max']:,.0f}",
        f"{1000 * found['p99_limit_s']:,.0f} / {1000 * found['worst_limit_s']:,.0f}",
        f"{spread['min']}-{spread['max']}", exceptions or "0", str(found["wrong_answers"]),
        "all" if not missed else "missed: " + ", ".join(missed),
    ]  # fmt: skip


def closed_loop(bench: Bench) -> ScenarioResult:
    """10 and 30 masters at 19200 baud, 100 unpaced: the gateway, then the bare forwarder."""
    window = bench.timing.pick(20.0, 6.0, 1.5)
    shapes: list[tuple[int, bool]] = [(masters, True) for masters in PACED_MASTERS]
    shapes.append((UNPACED_MASTERS, False))
    if bench.timing.tiny:
        shapes = [(PACED_MASTERS[0], True), (UNPACED_MASTERS, False)]
    table = Table(
        f"Closed loop: N masters, each with one read of 10 registers of a random slave 1-10 "
        f"outstanding, the next sent at its answer; {BAUDRATE} baud (paced) or unpaced, "
        "defaults; wait = sending to answer",
        ["masters", "server", "line use", "tx/s", "mean tx ms", "wait p50 ms", "p99 ms",
         "worst ms", "p99 / worst limit ms", "good per master", "exceptions", "wrong",
         "targets"],
    )  # fmt: skip
    figures: dict[str, Any] = {}
    checks: list[Check] = []
    wrong = 0
    for masters, paced in shapes:
        servers: list[tuple[str, ServerFactory, bool]]
        if paced:
            sim = paced_sim(BAUDRATE, UNITS)
            servers = [("gateway", gateway_server(BAUDRATE), False),
                       ("bare forwarder", bare_server(BAUDRATE), True)]  # fmt: skip
        else:
            sim = SimOptions(units=UNITS)
            servers = [("gateway", gateway_server(UNPACED_BAUDRATE, frame_gap=0.0), False),
                       ("bare forwarder", bare_server(), True)]  # fmt: skip
        line = f"{BAUDRATE} baud" if paced else "unpaced"
        key = f"{masters}_{'paced' if paced else 'unpaced'}"
        figures[key] = {}
        for server, factory, reference in servers:
            run = bench._run(
                f"closed loop, {masters} masters, {line}, {server}",
                sim,
                factory,
                _spec(bench, window, masters=masters, units=list(UNITS), random_units=True),
                reference=reference,
            )
            found = _closed_figures(run, masters, paced)
            figures[key]["gateway" if not reference else "bare_forwarder"] = found
            table.rows.append(_closed_row(server, found))
            if reference:
                continue
            wrong += run.faults
            met = found["targets_met"]
            wait = found["wait_s"]
            name = f"closed loop, {masters} masters, {line}"
            if paced:
                checks.append(Check(f"{name}: line use", found["line_use"],
                                    f">= {LINE_USE_TARGET:g}", met["line_use"]))  # fmt: skip
            checks += [
                Check(f"{name}: wait p99", wait["p99"],
                      f"<= {P99_ROUNDS:g} x N x mean tx = {found['p99_limit_s']:.3f} s",
                      met["p99"], " s"),
                Check(f"{name}: worst wait", wait["max"],
                      f"<= {WORST_ROUNDS:g} x N x mean tx + {WORST_SLACK_S:g} s = "
                      f"{found['worst_limit_s']:.3f} s", met["worst"], " s"),
                Check(f"{name}: exceptions and lost requests",
                      sum(found["exceptions"].values()) + found["lost"], "0",
                      met["exceptions"]),
                Check(f"{name}: wrong answers", run.faults, "0", run.faults == 0),
            ]  # fmt: skip
    notes = [
        "mean tx = the window over the server's good answers (its own, so a server is held to "
        "the round it makes); line use = good answers/s over the wire's maximum "
        f"({fc03_budget(BAUDRATE).max_per_s:.1f} FC03 x 10 transactions/s at {BAUDRATE} baud); "
        "exceptions: every exception answered in the whole run, warm-up included",
        "the bare forwarder serves first come, first served and keeps t3.5 by spinning; the "
        f"unpaced runs tell the gateway {UNPACED_BAUDRATE:,} baud with --frame-gap 0, as the "
        "other unpaced scenarios do",
    ]
    return ScenarioResult("closed-loop", figures, [table], checks, wrong, notes)


# -- a periodic master beside absent units -----------------------------------------------


def _master_figures(group: dict[str, Any]) -> dict[str, Any]:
    latency = group.get("latency_ms", {})
    return {
        "median_s": latency.get("p50", 0.0) / 1000,
        "p90_s": latency.get("p90", 0.0) / 1000,
        "p99_s": latency.get("p99", 0.0) / 1000,
        "worst_s": latency.get("max", 0.0) / 1000,
        "poll_rate_per_s": group.get("ok_per_s", 0.0),
        "sent": group.get("sent", 0),
        "ok": group.get("ok", 0),
        "exceptions": group.get("exceptions", {}),
    }


def _periodic_figures(run: Run) -> dict[str, Any]:
    load = run.load
    absent = load.groups.get("absent", {})
    return {
        **_master_figures(load.groups.get("main", {})),
        "clock": _master_figures(load.groups.get("clock", {})),
        "absent_sent": absent.get("sent", 0),
        "absent_answers": absent.get("tolerated", {}),
        "wrong_answers": run.faults,
        "early_requests": run.early_requests,
        "run": run.as_json(),
    }


def absent_periodic(bench: Bench) -> ScenarioResult:
    """A master polling unit 1 every 0.2 s, quiet and beside 4 reads in flight to absent ids."""
    window = bench.timing.pick(20.0, 8.0, 2.0)
    periodic = {"masters": 1, "units": [PERIODIC_UNIT], "mode": "cycle",
                "period": PERIODIC_PERIOD_S}  # fmt: skip
    clock = {"name": "clock", "masters": 1, "units": [PERIODIC_UNIT], "mode": "slow",
             "period": PERIODIC_PERIOD_S}  # fmt: skip
    absent = {"name": "absent", "masters": 1, "units": ABSENT_UNITS, "random_units": True,
              "pipeline": ABSENT_IN_FLIGHT,
              "tolerate": [TARGET_FAILED, PATH_UNAVAILABLE, GATEWAY_BUSY]}  # fmt: skip
    found: dict[str, dict[str, Any]] = {}
    for label, groups in (("quiet", [clock]), ("beside absent units", [clock, absent])):
        run = bench._run(
            f"a master polling unit {PERIODIC_UNIT} every {PERIODIC_PERIOD_S:g} s, {label}, "
            f"{BAUDRATE} baud",
            paced_sim(BAUDRATE, (PERIODIC_UNIT,)),
            gateway_server(BAUDRATE),
            _spec(bench, window, groups=groups, exception_pause=REFUSED_PAUSE_S, **periodic),
        )
        found[label] = _periodic_figures(run)
    quiet, loaded = found["quiet"], found["beside absent units"]
    median_limit = max(MEDIAN_FACTOR * quiet["median_s"], MEDIAN_FLOOR_S)
    clock_limit = max(MEDIAN_FACTOR * quiet["clock"]["median_s"], MEDIAN_FLOOR_S)
    rate_limit = RATE_SHARE * quiet["poll_rate_per_s"]
    table = Table(
        f"A master reading 10 registers of unit {PERIODIC_UNIT} every {PERIODIC_PERIOD_S:g} s "
        f"(one read outstanding), alone and beside one connection keeping {ABSENT_IN_FLIGHT} "
        f"reads in flight to random unit ids 100-247 (routed, none on the line); {BAUDRATE} "
        "baud, defaults",
        ["run", "master", "polls", "good", "poll rate /s", "median ms", "p90 ms", "p99 ms",
         "worst ms", "exceptions", "absent-unit reads sent", "their answers", "wrong"],
    )  # fmt: skip
    for label, figures in found.items():
        answers = ", ".join(f"{k} {v}" for k, v in sorted(figures["absent_answers"].items()))
        for name, master in (("cycle", figures), ("clock", figures["clock"])):
            exceptions = ", ".join(f"{k} {v}" for k, v in sorted(master["exceptions"].items()))
            table.rows.append([
                label, name, str(master["sent"]), str(master["ok"]),
                f"{master['poll_rate_per_s']:.2f}", f"{1000 * master['median_s']:,.1f}",
                f"{1000 * master['p90_s']:,.1f}", f"{1000 * master['p99_s']:,.1f}",
                f"{1000 * master['worst_s']:,.1f}", exceptions or "0",
                str(figures["absent_sent"]) if label != "quiet" else "-", answers or "-",
                str(figures["wrong_answers"]),
            ])  # fmt: skip
    wrong = quiet["wrong_answers"] + loaded["wrong_answers"]
    checks = [
        Check("absent-periodic: periodic master's median", loaded["median_s"],
              f"<= max(10 x quiet {1000 * quiet['median_s']:.1f} ms, 100 ms) = "
              f"{1000 * median_limit:.0f} ms", loaded["ok"] > 0
              and loaded["median_s"] <= median_limit, " s"),
        Check("absent-periodic: periodic master's poll rate", loaded["poll_rate_per_s"],
              f">= half the quiet {quiet['poll_rate_per_s']:.2f}/s",
              loaded["poll_rate_per_s"] >= rate_limit, "/s"),
        Check("absent-periodic: fixed-clock master's median", loaded["clock"]["median_s"],
              f"<= max(10 x quiet {1000 * quiet['clock']['median_s']:.1f} ms, 100 ms) = "
              f"{1000 * clock_limit:.0f} ms", loaded["clock"]["ok"] > 0
              and loaded["clock"]["median_s"] <= clock_limit, " s"),
        Check("absent-periodic: wrong answers", wrong, "0", wrong == 0),
    ]  # fmt: skip
    figures = {
        "quiet": quiet,
        "beside_absent": loaded,
        "median_limit_s": median_limit,
        "clock_median_limit_s": clock_limit,
        "rate_limit_per_s": rate_limit,
    }
    notes = [
        "poll rate = good answers per second; the cycle master (the periodic master of the "
        f"targets) sends its next read at its {PERIODIC_PERIOD_S:g} s tick or at the answer, "
        "whichever is later, so waits longer than the period lower its rate; the clock "
        f"master sends every {PERIODIC_PERIOD_S:g} s whatever, so its reads queue instead",
        "the absent-unit connection's exceptions are expected; it sends a read answered with "
        f"one again {REFUSED_PAUSE_S:g} s later (the other reads stay in flight)",
    ]
    return ScenarioResult("absent-periodic", figures, [table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {
    "closed-loop": closed_loop,
    "absent-periodic": absent_periodic,
}
