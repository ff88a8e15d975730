"""``python -m bench --tiny hostile`` runs every attacker beside the honest master and reports.

The figures themselves depend on the machine and live in bench/README.md; this
checks that each phase ran for real (the attacker achieved something, the honest
master was served) and that the report carries every figure of issue 9.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from bench.hostile import ATTACKS

REPO = Path(__file__).resolve().parents[2]


def test_tiny_hostile_scenario_reports_every_attacker(tmp_path: Path) -> None:
    output = tmp_path / "results.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", "hostile", "--output", str(output)],
        cwd=REPO, capture_output=True, text=True, timeout=150, check=False,
    )  # fmt: skip
    assert done.returncode in (0, 1), done.stdout + done.stderr
    results: dict[str, Any] = json.loads(output.read_text())
    assert results["failures"] == {}, results["failures"]
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
    assert "Hostile clients" in done.stdout
