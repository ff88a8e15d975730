"""``python -m bench --tiny tls``: the Modbus/TCP Security scenario runs and reports its figures.

Only that the scenario works end to end (PKI, TLS listener, load generator over TLS,
every answer checked); the figures themselves are measured with ``python -m bench tls``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_tiny_tls_scenario_reports_its_figures(tmp_path: Path) -> None:
    output = tmp_path / "results.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", "tls", "--output", str(output)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    results = json.loads(output.read_text())
    assert results["failures"] == {}
    figures = results["scenarios"]["tls"]
    setup = figures["connection_setup"]
    assert set(setup) == {"plain TCP", "TLS 1.2", "TLS 1.3"}
    assert all(kind["p50_ms"] > 0 for kind in setup.values())
    assert figures["tls_run"]["load"]["ok"] > 0
    assert figures["tls_run"]["load"]["wrong_answers"] == 0
    assert figures["tls_cpu_us_per_tx"] > 0
