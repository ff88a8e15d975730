"""``python -m bench --tiny in-flight``: a tcp line with max_in_flight 1 and 4, end to end.

Only that the scenario works (every answer checked); figures come from
``python -m bench in-flight``.
"""

from __future__ import annotations

from tests.helpers import TinyBench


def test_tiny_in_flight_scenario_reports_its_figures(tiny_bench: TinyBench) -> None:
    run = tiny_bench("in-flight")
    results = run.results
    figures = results["scenarios"]["in-flight"]
    for limit in (1, 4):
        run = figures[f"max_in_flight_{limit}"]
        assert run["run"]["load"]["ok"] > 0
        assert run["run"]["load"]["wrong_answers"] == 0
        assert run["gateway_cpu_us_per_tx"] > 0
