"""The audit log through the real command line: start, SIGHUP (logrotate and reload), stop,
and ``modbus-gateway audit verify`` on the files, intact and edited.

Readiness is the gateway's own log lines on stderr (listening, reopened, applied,
rejected), never a sleep.
"""

from __future__ import annotations

import hashlib
import json
import re
import signal
import subprocess
from pathlib import Path
from typing import Any

from gateway.sim import plc
from tests.e2e.test_cli import GatewayProcess, RunGateway, gateway_command
from tests.e2e.test_cli import run_gateway as run_gateway  # a fixture
from tests.helpers import DEADLINE_S, RawClient, SimFactory, h

REOPENED = re.compile(r"audit log .* reopened")
APPLIED = re.compile(r"reload: configuration from .* applied")
REJECTED = re.compile(r"reload rejected")


def wait_all(gateway: GatewayProcess, *patterns: re.Pattern[str]) -> None:
    """Wait for a line matching each of ``patterns``, in any order."""
    left = list(patterns)
    while left:
        gateway.wait_for(re.compile("|".join(pattern.pattern for pattern in left)))
        left = [pattern for pattern in left if not pattern.search(gateway.log[-1])]


def verify(*files: Path) -> subprocess.CompletedProcess[str]:
    command = gateway_command("audit", "verify", *map(str, files))
    return subprocess.run(command, capture_output=True, text=True, timeout=DEADLINE_S)


def records(*files: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for path in files for line in path.read_text().splitlines()]


def config_text(device: str, audit: Path, pipeline: int) -> str:
    return f"""
[server]
listen = "127.0.0.1:0"
max_pipeline = {pipeline}

[metrics]
listen = "off"

[audit]
path = "{audit}"

[lines.a]
device = "{device}"
baudrate = 115200
units = [1]
"""


def test_logrotate_reload_and_verify(
    tmp_path: Path, make_sim: SimFactory, run_gateway: RunGateway
) -> None:
    sim = make_sim({1: plc(1)})
    config, audit, rotated = tmp_path / "g.toml", tmp_path / "audit.jsonl", tmp_path / "audit.1"
    config.write_text(config_text(sim.path, audit, 16))
    loaded_hash = hashlib.sha256(config.read_bytes()).hexdigest()
    gateway = run_gateway("--config", str(config))
    with RawClient(gateway.address()) as client:
        assert client.request(1, h("06 0002 0011")) == h("06 0002 0011")
        audit.rename(rotated)  # logrotate moves the file, then signals
        config.write_text(config_text(sim.path, audit, 4))
        reloaded_hash = hashlib.sha256(config.read_bytes()).hexdigest()
        gateway.process.send_signal(signal.SIGHUP)
        wait_all(gateway, REOPENED, APPLIED)
        assert client.request(1, h("06 0003 0022")) == h("06 0003 0022")
        assert client.request(1, h("03 0003 0001")) == h("03 02 0022")
        config.write_text("[server\n")  # broken: the reload is rejected, the file reopened
        gateway.process.send_signal(signal.SIGHUP)
        wait_all(gateway, REOPENED, REJECTED)
    assert gateway.terminate() == 0
    assert records(audit)[0]["event"] == "audit_opened"
    assert records(audit)[0]["prev"] == records(rotated)[-1]["hash"]
    every = records(rotated, audit)
    writes = [(r["addresses"], r["values"]) for r in every if r["event"] == "request"]
    assert writes == [([[2, 2]], [0x11]), ([[3, 3]], [0x22])]
    configs = [r for r in every if r["event"] == "config"]
    assert [(c["action"], c["result"], c["sha256"]) for c in configs] == [
        ("load", "accepted", loaded_hash),
        ("reload", "accepted", reloaded_hash),
        ("reload", "rejected", hashlib.sha256(b"[server\n").hexdigest()),
    ]
    assert configs[1]["changed"] == ["server.max_pipeline"]
    assert "TOML" in configs[2]["error"]
    intact = verify(rotated, audit)
    assert intact.returncode == 0, intact.stderr
    assert "chain intact" in intact.stdout
    assert verify(audit).returncode == 0  # a rotated file alone verifies too

    # Both files in one: still one chain (the second file names the first's last hash).
    lines = (rotated.read_text() + audit.read_text()).splitlines(keepends=True)
    edited = tmp_path / "edited"
    at = next(n for n, line in enumerate(lines) if '"values":[17]' in line)
    edited.write_text("".join(lines).replace('"values":[17]', '"values":[18]'))
    bad = verify(edited)
    assert bad.returncode == 1, bad.stdout
    assert f"line {at + 1}: hash mismatch" in bad.stderr, bad.stderr
    removed = tmp_path / "removed"
    removed.write_text("".join(lines[:1] + lines[2:]))
    bad = verify(removed)
    assert bad.returncode == 1 and "line 2: hash mismatch" in bad.stderr, bad.stderr
    bad = verify(audit, rotated)  # out of order: the second file does not follow the first
    assert bad.returncode == 1 and "line 1: audit_opened does not follow" in bad.stderr

    # The file after the rotation, its head cut up to the rejected reload's reopen: the
    # reopen says the file held records before it, so the cut shows.
    kept = audit.read_text().splitlines(keepends=True)
    reopen = max(n for n, line in enumerate(kept) if '"event":"audit_opened"' in line)
    assert reopen > 0 and json.loads(kept[reopen])["records_before"] == reopen
    headless = tmp_path / "headless"
    headless.write_text("".join(kept[reopen:]))
    bad = verify(headless)
    assert bad.returncode == 1 and "intact" not in bad.stdout + bad.stderr, bad.stdout
    assert "line 1: the file's first record continues a file" in bad.stderr, bad.stderr


def test_an_unwritable_audit_path_stops_the_start_with_the_fix(
    tmp_path: Path, run_gateway: RunGateway
) -> None:
    missing = tmp_path / "no-such-directory" / "audit.jsonl"
    gateway = run_gateway("--demo", "--listen", "127.0.0.1:0", "--metrics", "off",
                          "--audit-log", str(missing))  # fmt: skip
    error = gateway.wait_for(re.compile(r"cannot start: audit.path, --audit-log: cannot open.*"))
    assert "make its directory writable by the gateway's user" in error.group(0)
    assert gateway.process.wait(DEADLINE_S) == 1
