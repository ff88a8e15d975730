"""``python -m bench --tiny agent``: agent mode's four runs, end to end.

Only that the scenario runs (the simulator, the gateway and their masters as processes)
and that what would make its figures meaningless holds: in agent mode the window's wire
carries the polls alone while the masters are answered, without it every read is a
frame; the slave really falls silent and the masters really meet the block's end (0x0B);
every write's read-back really went to the wire. Whether the gateway meets the targets
is the benchmark's report (``python -m bench agent``).
"""

from __future__ import annotations

from tests.helpers import TinyBench


def test_tiny_agent_scenario_measures_memory_wire_freshness_and_writes(
    tiny_bench: TinyBench,
) -> None:
    # 1: a target missed on a busy machine is the benchmark's report, not this test's.
    run = tiny_bench("agent", ok=(0, 1), timeout=180)
    stdout, results = run.stdout, run.results
    assert results["wrong_answers"] == 0, stdout
    figures = results["scenarios"]["agent"]
    memory, wire = figures["memory"], figures["wire"]
    assert memory["good"] > 0 and memory["polls"] >= 2, stdout
    assert memory["other_frames"] == 0, stdout
    assert memory["requests_total"]["memory"] > 0
    assert wire["good"] > 0 and wire["polls"] == 0
    # Every frame is a master's read (the window's edges cut reads and frames apart).
    assert wire["other_frames"] == wire["wire_frames"] > 0.8 * wire["reads"], stdout
    assert wire["requests_total"].get("memory", 0) == 0
    fresh = figures["freshness"]
    assert fresh["answers_from_memory_after_death"] > 0, stdout
    assert fresh["outcomes_after_death"].get("0x83/0x0b", 0) > 0, stdout
    assert fresh["stale_at_s"] > 0
    written = figures["write"]
    assert written["cycles"] == written["read_back_ok"] == 40, stdout
    assert written["read_backs_on_the_wire"] == 40
    assert "Freshness: the slave falls silent" in stdout
