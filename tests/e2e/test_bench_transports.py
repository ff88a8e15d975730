"""``python -m bench --tiny transports``: the line-kind scenario runs and reports its figures.

Only that the scenario works end to end (socat as device server, the gateway's
rtu-over-tcp line; the simulator's Modbus TCP slave behind a tcp line; every answer
checked); figures come from ``python -m bench transports``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from conftest import require_tool

REPO = Path(__file__).resolve().parents[2]


def test_tiny_transports_scenario_reports_its_figures(tmp_path: Path) -> None:
    require_tool("socat")
    output = tmp_path / "results.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench", "--tiny", "transports", "--output", str(output)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    results = json.loads(output.read_text())
    assert results["failures"] == {}
    figures = results["scenarios"]["transports"]
    for kind in ("rtu", "rtu-over-tcp", "tcp"):
        assert figures[kind]["run"]["load"]["ok"] > 0
        assert figures[kind]["run"]["load"]["wrong_answers"] == 0
        assert figures[kind]["gateway_cpu_us_per_tx"] > 0
    assert figures["tcp"]["run"]["simulator"]["responses"] >= figures["tcp"]["run"]["load"]["ok"]
