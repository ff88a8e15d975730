"""``python -m bench --tiny reverse``: the reverse-mode scenario runs and reports its figures.

Only that the scenario works end to end (a master on the serial-slave pty in RTU and in
ASCII, every answer checked); the figures are measured with ``python -m bench reverse``.
"""

from __future__ import annotations

from tests.helpers import TinyBench


def test_tiny_reverse_scenario_reports_its_figures(tiny_bench: TinyBench) -> None:
    run = tiny_bench("reverse")
    results = run.results
    figures = results["scenarios"]["reverse"]
    for framing in ("rtu", "ascii"):
        assert figures[framing]["answers"] > 0
        assert figures[framing]["wrong_answers"] == 0
        assert figures[framing]["gateway_cpu_us_per_tx"] > 0
