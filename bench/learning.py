"""Learning a slave's response time: a slave fast at first and slow later must not be failed.

Two devices whose response time changes under the gateway's default (learned) timeout,
each polled by one master that sends its next read as soon as the last is answered,
at 115200 baud (the simulator's response-time profiles, ``bench.slaves --response-time``;
a device is deaf until its answer has gone, as a device that scans its port once per
cycle is):

- ``soft PLC``: one device answering unit ids 1-4 whose first 5 answers (over all four)
  come within 40 ms and every later one anywhere in 20-480 ms (uniform), polled
  round-robin 200 times (60 with ``--quick``): no exception from the first poll on.
- ``turns slow``: one slave answering in 10 ms for its first 40 answers (20 ``--quick``),
  then in 400 ms, polled 40 (25) more times: at most 2 exceptions after the change and
  none in its last 20 polls.

Every poll's outcome is recorded with its times; "after the change" means answered (or,
when never answered, sent) after the simulator served its first slow answer, by the
clock both processes share.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

from .loadgen import LoadSpec, percentile
from .procs import SimOptions
from .scenarios import Bench, Check, Run, ScenarioResult, Table, gateway_server, paced_sim
from .slaves import response_profile_argument

BAUDRATE = 115200
PLC_UNITS = (1, 2, 3, 4)
PLC_FAST_ANSWERS = 5
PLC_FAST_S = (0.005, 0.037)  #: to the answer's first byte: its last leaves within 40 ms
PLC_SLOW_S = (0.020, 0.480)
TURN_UNIT = 1
TURN_FAST_S = 0.010
TURN_SLOW_S = 0.400
TURN_AFTER_TARGET = 2
LAST_POLLS = 20
SECONDS_PER_POLL_CAP = 2.5  #: the window's cap per poll (a poll that fails waits ~1-2 s)
LOST_AFTER_S = 10.0


def _polls(bench: Bench) -> dict[str, int]:
    """How many polls each case makes, by the kind of run."""
    return {
        "plc": int(bench.timing.pick(200, 60, 12)),
        "turn_fast": int(bench.timing.pick(40, 20, 12)),
        "turn_slow": int(bench.timing.pick(40, 25, 5)),
    }


def _run(bench: Bench, label: str, sim: SimOptions, units: Sequence[int], polls: int) -> Run:
    spec = LoadSpec(port=0, masters=1, units=list(units), max_requests=polls, record=True)
    spec.warmup = 0.0
    spec.duration = polls * SECONDS_PER_POLL_CAP + 5.0
    spec.drain = 1.0
    spec.request_timeout = LOST_AFTER_S
    return bench._run(label, sim, gateway_server(BAUDRATE), spec)


def _records(run: Run) -> list[list[Any]]:
    """Every poll as [sent, answered or None, unit, outcome], in the order sent."""
    records: list[list[Any]] = run.load.groups.get("main", {}).get("records", [])
    return sorted(records, key=lambda record: record[0])


def _records_of(figures: dict[str, Any]) -> list[list[Any]]:
    """The polls of a case's figures (kept once, in its run's load)."""
    records: list[list[Any]] = figures["run"]["load"]["groups"]["main"]["records"]
    return sorted(records, key=lambda record: record[0])


def _failures(records: Sequence[list[Any]]) -> Counter[str]:
    return Counter(record[3] for record in records if record[3] != "ok")


def _waits(records: Sequence[list[Any]]) -> dict[str, float]:
    waits = sorted(record[1] - record[0] for record in records if record[1] is not None)
    return {
        "p50": percentile(waits, 0.5),
        "p99": percentile(waits, 0.99),
        "max": waits[-1] if waits else 0.0,
    }


def _first_failure(records: Sequence[list[Any]]) -> int | None:
    return next((index + 1 for index, record in enumerate(records) if record[3] != "ok"), None)


def _profile_stats(run: Run) -> dict[str, Any]:
    profiles: list[dict[str, Any]] = run.sim.get("response_time", [])
    return profiles[0] if profiles else {}


def _text(counts: Counter[str] | dict[str, int]) -> str:
    return ", ".join(f"{key} {value}" for key, value in sorted(counts.items())) or "0"


def _plc(bench: Bench, polls: int) -> dict[str, Any]:
    profile = response_profile_argument(
        PLC_UNITS, [(PLC_FAST_ANSWERS, *PLC_FAST_S), (None, *PLC_SLOW_S)]
    )
    run = _run(
        bench,
        f"soft PLC on unit ids 1-4, {polls} polls, {BAUDRATE} baud",
        paced_sim(BAUDRATE, PLC_UNITS, response_time=[profile]),
        PLC_UNITS,
        polls,
    )
    records = _records(run)
    failures = _failures(records)
    return {
        "polls": len(records),
        "ok": sum(record[3] == "ok" for record in records),
        "failures": dict(failures),
        "first_failure_poll": _first_failure(records),
        "wait_s": _waits(records),
        "device": _profile_stats(run),
        "wrong_answers": run.faults,
        "run": run.as_json(),  #: its load's groups.main.records: every poll
    }


def _turn(bench: Bench, fast: int, slow: int) -> dict[str, Any]:
    profile = response_profile_argument(
        (TURN_UNIT,), [(fast, TURN_FAST_S, TURN_FAST_S), (None, TURN_SLOW_S, TURN_SLOW_S)]
    )
    run = _run(
        bench,
        f"a slave turning from {1000 * TURN_FAST_S:g} to {1000 * TURN_SLOW_S:g} ms after "
        f"{fast} answers, {fast + slow} polls, {BAUDRATE} baud",
        paced_sim(BAUDRATE, (TURN_UNIT,), response_time=[profile]),
        (TURN_UNIT,),
        fast + slow,
    )
    records = _records(run)
    device = _profile_stats(run)
    started = device.get("phase_started_at", [])
    changed_at: float | None = started[1] if len(started) > 1 else None

    def after(record: list[Any]) -> bool:
        when = record[1] if record[1] is not None else record[0]
        return changed_at is not None and when >= changed_at

    later = [record for record in records if after(record)]
    return {
        "polls": len(records),
        "ok": sum(record[3] == "ok" for record in records),
        "changed": changed_at is not None,
        "polls_after_change": len(later),
        "failures_before_change": dict(_failures([r for r in records if not after(r)])),
        "failures_after_change": dict(_failures(later)),
        "failures_last_polls": dict(_failures(records[-LAST_POLLS:])),
        "wait_after_change_s": _waits(later),
        "device": device,
        "wrong_answers": run.faults,
        "run": run.as_json(),  #: its load's groups.main.records: every poll
    }


def learning(bench: Bench) -> ScenarioResult:
    """The soft PLC and the slave that turns slow, each polled by one master."""
    polls = _polls(bench)
    plc = _plc(bench, polls["plc"])
    turn = _turn(bench, polls["turn_fast"], polls["turn_slow"])
    table = Table(
        f"Learning response times at {BAUDRATE} baud, defaults: one master polling as fast as "
        "it is answered",
        ["case", "polls", "good", "exceptions (all)", "first failed poll", "after the change",
         f"last {LAST_POLLS} polls", "wait p50 ms", "p99 ms", "worst ms", "wrong"],
    )  # fmt: skip
    wait = plc["wait_s"]
    table.rows.append([
        f"soft PLC: ids 1-4, first {PLC_FAST_ANSWERS} answers <= 40 ms, then "
        f"{1000 * PLC_SLOW_S[0]:g}-{1000 * PLC_SLOW_S[1]:g} ms",
        str(plc["polls"]), str(plc["ok"]), _text(plc["failures"]),
        str(plc["first_failure_poll"] or "-"), "-", "-", f"{1000 * wait['p50']:,.0f}",
        f"{1000 * wait['p99']:,.0f}", f"{1000 * wait['max']:,.0f}", str(plc["wrong_answers"]),
    ])  # fmt: skip
    records = _records_of(turn)
    wait = turn["wait_after_change_s"]
    all_failures = _failures(records)
    table.rows.append([
        f"turns slow: {1000 * TURN_FAST_S:g} ms for {polls['turn_fast']} answers, then "
        f"{1000 * TURN_SLOW_S:g} ms", str(turn["polls"]), str(turn["ok"]), _text(all_failures),
        str(_first_failure(records) or "-"),
        f"{_text(turn['failures_after_change'])} in {turn['polls_after_change']}",
        _text(turn["failures_last_polls"]), f"{1000 * wait['p50']:,.0f}",
        f"{1000 * wait['p99']:,.0f}", f"{1000 * wait['max']:,.0f}", str(turn["wrong_answers"]),
    ])  # fmt: skip
    plc_failed = sum(plc["failures"].values())
    after = sum(turn["failures_after_change"].values())
    last = sum(turn["failures_last_polls"].values())
    before = sum(turn["failures_before_change"].values())
    wrong = plc["wrong_answers"] + turn["wrong_answers"]
    checks = [
        Check("learning, soft PLC: exceptions and lost polls", plc_failed, "0",
              plc_failed == 0 and plc["polls"] == polls["plc"]),
        Check("learning, turns slow: exceptions after the change", after,
              f"<= {TURN_AFTER_TARGET}", turn["changed"] and after <= TURN_AFTER_TARGET),
        Check(f"learning, turns slow: exceptions in the last {LAST_POLLS} polls", last, "0",
              turn["changed"] and last == 0),
        Check("learning, turns slow: exceptions before the change", before, "0", before == 0),
        Check("learning: wrong answers", wrong, "0", wrong == 0),
    ]  # fmt: skip
    figures = {"soft_plc": plc, "turns_slow": turn}
    notes = [
        "response time = from the request's arrival at the device to the first byte of its "
        "answer; the device ignores requests (on any of its unit ids) until its answer has gone",
        "exceptions count every poll not answered with its data: exception answers and polls "
        f"never answered within {LOST_AFTER_S:g} s ('lost')",
    ]
    return ScenarioResult("learning", figures, [table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"learning": learning}
