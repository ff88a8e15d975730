"""``python -m bench --tiny slave-kinds``: tcp and tls lines measured end to end.

Only that the scenario works (a second gateway process as the Modbus TCP and TLS slave,
every answer checked); figures come from ``python -m bench slave-kinds``.
"""

from __future__ import annotations

from tests.helpers import TinyBench


def test_tiny_slave_kinds_scenario_reports_its_figures(tiny_bench: TinyBench) -> None:
    run = tiny_bench("slave-kinds")
    results = run.results
    figures = results["scenarios"]["slave-kinds"]
    kinds = ["rtu"] + [f"{kind} (simulator)" for kind in ("tcp", "tls")]
    kinds += [f"{kind} (simulator), in flight 4" for kind in ("tcp", "tls")]
    kinds += [f"{kind} (slave gateway)" for kind in ("tcp", "tls")]
    assert sorted(figures) == sorted(kinds)
    for kind in kinds:
        assert figures[kind]["run"]["load"]["ok"] > 0
        assert figures[kind]["run"]["load"]["wrong_answers"] == 0
        assert figures[kind]["gateway_cpu_us_per_tx"] > 0
