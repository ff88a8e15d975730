"""``python -m bench --tiny ascii``: the ASCII line scenario runs and reports its figures.

Only that the scenario works end to end (an ASCII simulator, the gateway with
``--framing ascii``, every answer checked); the figures are measured with ``python -m bench ascii``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_tiny_ascii_scenario_reports_its_figures(tmp_path: Path) -> None:
    output = tmp_path / "results.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", "ascii", "--output", str(output)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode in (0, 1), done.stdout + done.stderr  # 1: a target missed under load
    results = json.loads(output.read_text())
    assert results["failures"] == {}
    figures = results["scenarios"]["ascii"]
    assert figures["unpaced_ascii_tx_per_s"] > 0
    assert figures["unpaced_rtu_tx_per_s"] > 0
    assert figures["ascii_over_rtu_cpu"] > 0
    assert figures["paced_9600_tx_per_s"] > 0
    assert all(run["load"]["wrong_answers"] == 0 for run in figures["runs"])
    assert all(run["simulator"]["crc_errors_in"] == 0 for run in figures["runs"])
