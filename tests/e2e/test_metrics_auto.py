"""``--metrics auto``: each instance takes a free port and logs its status page's URL."""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

from tests.e2e.test_startup_messages import Started
from tests.helpers import DEADLINE_S

STATUS_PAGE = r"metrics on (http://127\.0\.0\.1:(\d+)/metrics), status page on (\S+)$"


def test_two_instances_side_by_side_with_metrics_auto(tmp_path: Path) -> None:
    instances = [
        Started(
            *("--serial", str(tmp_path / f"ttyUSB{n}")),
            *("--listen", "127.0.0.1:0", "--metrics", "auto"),
        )
        for n in (1, 2)
    ]
    try:
        pages = [instance.wait_for(STATUS_PAGE) for instance in instances]
        assert pages[0][2] != pages[1][2]  # two free ports, neither the default 9502
        for match, device in zip(pages, ("ttyUSB1", "ttyUSB2"), strict=True):
            assert match[3] == match[1].removesuffix("metrics")
            with urllib.request.urlopen(match[3] + "status", timeout=DEADLINE_S) as reply:
                (line,) = json.loads(reply.read())["lines"]
            assert line["device"].endswith(device)
            with urllib.request.urlopen(match[3], timeout=DEADLINE_S) as reply:
                assert b"modbus-gateway" in reply.read()
    finally:
        codes = [instance.stop() for instance in instances]
    assert codes == [0, 0]
