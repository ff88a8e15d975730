"""``python -m bench --tiny hostile`` runs every attacker beside the honest master and reports.

The figures themselves depend on the machine and live in bench/README.md; this
checks that each phase ran for real (the attacker achieved something, the honest
master was served) and that the report carries every figure of issue 9.
"""

from __future__ import annotations

from bench.hostile import ATTACKS
from tests.helpers import TinyBench


def test_tiny_hostile_scenario_reports_every_attacker(tiny_bench: TinyBench) -> None:
    run = tiny_bench("hostile", ok=(0, 1), timeout=150)
    results = run.results
    hostile = results["scenarios"]["hostile"]
    phases = hostile["phases"]
    assert list(phases) == ["baseline", *ATTACKS]
    for name, phase in phases.items():
        assert phase["polls"] > 0 and phase["errors"] == 0, (name, phase)
        assert phase["rss_peak_mb"] >= phase["rss_start_mb"] > 0
    assert phases["flood-unread"]["attacker"]["bytes_sent"] > 0
    assert phases["flood-read"]["attacker"]["replies"] > 0
    assert phases["bad-framing"]["attacker"]["connections"] > 0
    assert phases["bursts"]["attacker"]["refused"] > 0  # past the per-address limit
    assert phases["bursts"]["per_poll"]["polls"] > 0
    assert phases["scrape"]["attacker"]["scrapes"] > 0
    assert hostile["metrics_bytes_after_scan"] >= hostile["metrics_bytes_before_scan"] > 0
    figures = {check["figure"] for check in results["checks"]}
    assert {"floods: honest p99", "log lines/s one client causes",
            "/metrics after a unit x function scan"} <= figures  # fmt: skip
    assert "Hostile clients" in run.stdout
