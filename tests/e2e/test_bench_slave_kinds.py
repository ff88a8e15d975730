"""``python -m bench --tiny slave-kinds``: tcp and tls lines measured end to end.

Only that the scenario works (a second gateway process as the Modbus TCP and TLS slave,
every answer checked); figures come from ``python -m bench slave-kinds``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_tiny_slave_kinds_scenario_reports_its_figures(tmp_path: Path) -> None:
    output = tmp_path / "results.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", "slave-kinds", "--output", str(output)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    results = json.loads(output.read_text())
    assert results["failures"] == {}
    figures = results["scenarios"]["slave-kinds"]
    kinds = ["rtu"] + [f"{kind} (simulator)" for kind in ("tcp", "tls")]
    kinds += [f"{kind} (simulator), in flight 4" for kind in ("tcp", "tls")]
    kinds += [f"{kind} (slave gateway)" for kind in ("tcp", "tls")]
    assert sorted(figures) == sorted(kinds)
    for kind in kinds:
        assert figures[kind]["run"]["load"]["ok"] > 0
        assert figures[kind]["run"]["load"]["wrong_answers"] == 0
        assert figures[kind]["gateway_cpu_us_per_tx"] > 0
