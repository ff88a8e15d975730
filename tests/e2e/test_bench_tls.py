"""``python -m bench --tiny tls``: the Modbus/TCP Security scenario runs and reports its figures.

Only that the scenario works end to end (PKI, TLS listener, load generator over TLS,
every answer checked); the figures themselves are measured with ``python -m bench tls``.
"""

from __future__ import annotations

from tests.helpers import TinyBench


def test_tiny_tls_scenario_reports_its_figures(tiny_bench: TinyBench) -> None:
    run = tiny_bench("tls")
    results = run.results
    figures = results["scenarios"]["tls"]
    setup = figures["connection_setup"]
    assert set(setup) == {"plain TCP", "TLS 1.2", "TLS 1.3"}
    assert all(kind["p50_ms"] > 0 for kind in setup.values())
    assert figures["tls_run"]["load"]["ok"] > 0
    assert figures["tls_run"]["load"]["wrong_answers"] == 0
    assert figures["tls_cpu_us_per_tx"] > 0
