"""``python -m bench --tiny in-flight``: a tcp line with max_in_flight 1 and 4, end to end.

Only that the scenario works (every answer checked); figures come from
``python -m bench in-flight``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_tiny_in_flight_scenario_reports_its_figures(tmp_path: Path) -> None:
    output = tmp_path / "results.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", "in-flight", "--output", str(output)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    results = json.loads(output.read_text())
    assert results["failures"] == {}
    figures = results["scenarios"]["in-flight"]
    for limit in (1, 4):
        run = figures[f"max_in_flight_{limit}"]
        assert run["run"]["load"]["ok"] > 0
        assert run["run"]["load"]["wrong_answers"] == 0
        assert run["gateway_cpu_us_per_tx"] > 0
