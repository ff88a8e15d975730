"""``--metrics auto``: each instance takes a free port and logs its status page's URL."""

from __future__ import annotations

import json
import os
import queue
import re
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

from conftest import DEADLINE_S

REPO = Path(__file__).resolve().parents[2]
STATUS_PAGE = re.compile(r"metrics on (http://127\.0\.0\.1:(\d+)/metrics), status page on (\S+)$")


class Instance:
    """One gateway process; its stderr read line by line on a thread."""

    def __init__(self, *args: str) -> None:
        env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONDONTWRITEBYTECODE="1")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "gateway", *args], stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env, cwd="/",
        )  # fmt: skip
        self.lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def wait_for(self, pattern: re.Pattern[str]) -> re.Match[str]:
        """The first stderr line matching ``pattern``."""
        deadline = time.monotonic() + DEADLINE_S
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                line = self.lines.get(timeout=remaining)
            except queue.Empty:
                break
            if line is None:
                raise AssertionError(f"the gateway exited with {self.process.wait()}")
            match = pattern.search(line)
            if match:
                return match
        raise AssertionError(f"no line matching {pattern.pattern}")

    def stop(self) -> int:
        """SIGTERM, and the exit code."""
        if self.process.poll() is None:
            self.process.terminate()
        return self.process.wait(DEADLINE_S)


def test_two_instances_side_by_side_with_metrics_auto(tmp_path: Path) -> None:
    instances = [
        Instance(
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
