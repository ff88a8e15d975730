"""``python -m bench --tiny closed-loop absent-periodic learning``: the scenarios measure.

Only that each scenario runs end to end and measures what it says (the simulator, the
gateway or the bare forwarder and the load generator as processes); the figures and
whether the gateway meets their targets are the benchmark's report. What would make a
figure meaningless is checked: a first-come-first-served forwarder's closed-loop wait is
about one round of N transactions (each master really keeps one read outstanding); the
absent unit ids were really polled and refused; the simulated devices really changed
their response times, and every poll was recorded.
"""

from __future__ import annotations

from typing import Any

from tests.helpers import TinyBench


def _bench(tiny_bench: TinyBench, *names: str) -> tuple[str, dict[str, Any]]:
    run = tiny_bench(*names, ok=(0, 1), timeout=180)  # 2: a process failed
    results = run.results
    assert results["wrong_answers"] == 0, run.stdout
    return run.stdout, results["scenarios"]


def test_closed_loop_and_absent_periodic_measure_both_servers_and_both_runs(
    tiny_bench: TinyBench,
) -> None:
    stdout, scenarios = _bench(tiny_bench, "closed-loop", "absent-periodic")
    closed = scenarios["closed-loop"]
    assert set(closed) == {"10_paced", "100_unpaced"}
    for shape in closed.values():
        for server in ("gateway", "bare_forwarder"):
            found = shape[server]
            assert found["tx_per_s"] > 0, stdout
            assert found["wrong_answers"] == 0
            # Every master has a read outstanding when the window closes: the worst counts it.
            assert 0 < found["oldest_unanswered_s"] <= found["wait_s"]["max"]
            assert found["run"]["simulator"]["early_requests"] == 0 or not found["paced"]
    bare = closed["10_paced"]["bare_forwarder"]
    # First come, first served: each read waits for the other 9 masters' reads, so the
    # median wait is about one round of 10 transactions.
    round_s = 10 * bare["mean_transaction_s"]
    assert 0.5 * round_s <= bare["wait_s"]["p50"] <= 1.5 * round_s, bare["wait_s"]
    assert 0.85 <= bare["line_use"] <= 1.0
    assert "wait p99" in stdout and "p99 / worst limit ms" in stdout
    absent = scenarios["absent-periodic"]
    for run in ("quiet", "beside_absent"):
        assert absent[run]["ok"] > 0 and absent[run]["clock"]["ok"] > 0
    assert absent["quiet"]["absent_sent"] == 0
    assert absent["beside_absent"]["absent_sent"] > 0
    assert absent["beside_absent"]["absent_answers"].get("0x83/0x0b", 0) > 0
    assert absent["median_limit_s"] >= 0.1


def test_learning_devices_change_their_response_times(tiny_bench: TinyBench) -> None:
    stdout, scenarios = _bench(tiny_bench, "learning")
    figures = scenarios["learning"]
    plc, turn = figures["soft_plc"], figures["turns_slow"]
    assert plc["polls"] == 12
    assert plc["device"]["units"] == [1, 2, 3, 4]
    assert len(plc["device"]["phase_started_at"]) == 2  # fast first, then slow
    plc_records = plc["run"]["load"]["groups"]["main"]["records"]
    assert {record[2] for record in plc_records} == {1, 2, 3, 4}  # round robin
    assert turn["polls"] == 17 and turn["changed"]
    records = sorted(turn["run"]["load"]["groups"]["main"]["records"])
    changed_at = turn["device"]["phase_started_at"][1]
    fast = [r[1] - r[0] for r in records if r[1] is not None and r[1] < changed_at and r[3] == "ok"]
    assert fast and sorted(fast)[len(fast) // 2] < 0.1  # 10 ms answers
    assert turn["wait_after_change_s"]["p50"] >= 0.4  # then 400 ms ones
    assert "exceptions after the change" in stdout
