"""The example alert rules under ``promtool test rules``: unrouted traffic is not a failing line.

The scenarios live in ``alert_rules.test.yml`` beside this file, so that an operator who
tunes the rules can run the same check with ``promtool test rules`` on that file.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

from tests.helpers import require_tool

SCENARIOS = Path(__file__).with_name("alert_rules.test.yml")


def test_unrouted_requests_are_labelled_not_counted_against_a_line() -> None:
    promtool = require_tool("promtool")
    checked = subprocess.run(
        [promtool, "test", "rules", str(SCENARIOS)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert "SUCCESS" in checked.stdout
