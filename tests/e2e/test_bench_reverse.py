"""``python -m bench --tiny reverse``: the reverse-mode scenario runs and reports its figures.

Only that the scenario works end to end (a master on the serial-slave pty in RTU and in
ASCII, every answer checked); the figures are measured with ``python -m bench reverse``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_tiny_reverse_scenario_reports_its_figures(tmp_path: Path) -> None:
    output = tmp_path / "results.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", "reverse", "--output", str(output)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    results = json.loads(output.read_text())
    assert results["failures"] == {}
    figures = results["scenarios"]["reverse"]
    for framing in ("rtu", "ascii"):
        assert figures[framing]["answers"] > 0
        assert figures[framing]["wrong_answers"] == 0
        assert figures[framing]["gateway_cpu_us_per_tx"] > 0
