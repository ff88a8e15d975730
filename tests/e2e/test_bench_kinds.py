"""``python -m bench --tiny ascii``: the ASCII line scenario runs and reports its figures.

Only that the scenario works end to end (an ASCII simulator, the gateway with
``--framing ascii``, every answer checked); the figures are measured with ``python -m bench ascii``.
"""

from __future__ import annotations

from tests.helpers import TinyBench


def test_tiny_ascii_scenario_reports_its_figures(tiny_bench: TinyBench) -> None:
    run = tiny_bench("ascii", ok=(0, 1))  # 1: a target missed under load
    results = run.results
    figures = results["scenarios"]["ascii"]
    assert figures["unpaced_ascii_tx_per_s"] > 0
    assert figures["unpaced_rtu_tx_per_s"] > 0
    assert figures["ascii_over_rtu_cpu"] > 0
    assert figures["paced_9600_tx_per_s"] > 0
    assert all(run["load"]["wrong_answers"] == 0 for run in figures["runs"])
    assert all(run["simulator"]["crc_errors_in"] == 0 for run in figures["runs"])
