"""``python -m bench --tiny transports``: the line-kind scenario runs and reports its figures.

Only that the scenario works end to end (socat as device server, the gateway's
rtu-over-tcp line; the simulator's Modbus TCP slave behind a tcp line; every answer
checked); figures come from ``python -m bench transports``.
"""

from __future__ import annotations

from tests.helpers import TinyBench, require_tool


def test_tiny_transports_scenario_reports_its_figures(tiny_bench: TinyBench) -> None:
    require_tool("socat")
    run = tiny_bench("transports")
    results = run.results
    figures = results["scenarios"]["transports"]
    for kind in ("rtu", "rtu-over-tcp", "tcp"):
        assert figures[kind]["run"]["load"]["ok"] > 0
        assert figures[kind]["run"]["load"]["wrong_answers"] == 0
        assert figures[kind]["gateway_cpu_us_per_tx"] > 0
    assert figures["tcp"]["run"]["simulator"]["responses"] >= figures["tcp"]["run"]["load"]["ok"]
