"""What an operator meets first: a silent slave within the master's timeout, port 502, JSON logs.

Real things throughout: the CLI in a subprocess, mbpoll as the master (its
default timeout is 1 s), ``setpriv`` to take CAP_NET_BIND_SERVICE away from a
root test run, and the JSON log read line by line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from gateway.core.line.response_timing import EVIDENCE
from gateway.sim import UnitFaults, plc
from tests.helpers import DEADLINE_S, SimFactory, release, require_tool

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="needs Linux ptys")


def gateway(*args: str) -> list[str]:
    return [sys.executable, "-m", "gateway", *args]


def test_a_slave_that_falls_silent_is_0x0b_before_the_masters_1s_timeout_at_9600_baud(
    make_sim: SimFactory,
) -> None:
    """Default timeout and retries at 9600 8N1: mbpoll reports 0x0B, not a timeout of its own.

    The gateway has learned the slave's turnaround from its answers (10 of them: a few fast
    first answers are no evidence): two attempts (the learned bound, at least 0.25 s, then
    twice it) end within mbpoll's 1 s. A slave not yet learned gets ``initial_timeout``
    (1 s) instead: it may just be slow.
    """
    mbpoll = require_tool("mbpoll")
    sim = make_sim({1: plc(1)})
    process = subprocess.Popen(
        gateway("--serial", sim.path, "--baudrate", "9600", "--listen", "127.0.0.1:0",
                "--metrics", "off", "--log-format", "json"),
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert process.stderr is not None
        port = None
        for line in process.stderr:
            record = json.loads(line)
            if record["message"].startswith("listening on 127.0.0.1:"):
                port = record["message"].split(":")[1].split(" ")[0]
                break
        assert port is not None, "the gateway did not start"

        def poll(unit: int) -> subprocess.CompletedProcess[str]:
            return subprocess.run(
                [mbpoll, "-m", "tcp", "-p", str(port), "-a", str(unit), "-r", "1", "-c", "2",
                 "-t", "4", "-1", "127.0.0.1"],
                capture_output=True, text=True, timeout=DEADLINE_S, check=False,
            )  # fmt: skip

        for _ in range(EVIDENCE + 1):
            good = poll(1)
            assert good.returncode == 0, good.stdout + good.stderr
        sim.line.set_faults(1, UnitFaults(silent=True))
        silent = poll(1)
        output = silent.stdout + silent.stderr
        assert "Target device failed to respond" in output, output
        assert "timed out" not in output.lower(), output
    finally:
        process.terminate()
        release(process)


def _without_bind_capability() -> list[str]:
    """A prefix that runs a command without CAP_NET_BIND_SERVICE (root keeps every other)."""
    if os.geteuid() != 0:
        return []  # an ordinary user has no capability to drop
    setpriv = require_tool("setpriv")
    return [setpriv, "--bounding-set", "-net_bind_service", "--inh-caps", "-net_bind_service"]


def _unprivileged_port_start() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_unprivileged_port_start").read_text())
    except (OSError, ValueError):
        return 1024


@pytest.mark.parametrize("log_format", ["text", "json"])
def test_port_502_refused_explains_the_capability(log_format: str) -> None:
    if _unprivileged_port_start() <= 502:
        pytest.skip("net.ipv4.ip_unprivileged_port_start lets anyone bind 502 here")
    done = subprocess.run(
        [*_without_bind_capability(),
         *gateway("--demo", "--listen", "127.0.0.1:502", "--metrics", "off",
                  "--log-format", log_format)],
        capture_output=True, text=True, timeout=DEADLINE_S * 3, check=False,
    )  # fmt: skip
    assert done.returncode == 1, done
    errors = done.stderr.strip().splitlines()
    if log_format == "json":
        records = [json.loads(line) for line in errors]  # every line is a JSON object
        errors = [record["message"] for record in records if record["level"] == "error"]
    (error,) = [line for line in errors if "cannot listen" in line]
    assert "127.0.0.1:502 (server.listen, --listen): permission denied" in error
    assert "CAP_NET_BIND_SERVICE" in error
    assert "modbus-gateway@.service" in error
    assert "setcap cap_net_bind_service=+ep" in error
    assert "--listen 0.0.0.0:5020" in error


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--no-such-flag"], "unrecognized arguments: --no-such-flag"),
        (["--listen", "nowhere"], "argument --listen: 'nowhere' is not HOST:PORT"),
        (["--config", "/nonexistent/plant.toml"], "file not found"),
    ],
    ids=["usage", "bad_flag_value", "missing_file"],
)
def test_startup_errors_are_json_lines_with_log_format_json(args: list[str], expected: str) -> None:
    done = subprocess.run(
        gateway("--log-format", "json", *args),
        capture_output=True, text=True, timeout=DEADLINE_S * 3, check=False,
    )  # fmt: skip
    assert done.returncode == 2, done
    lines = done.stderr.strip().splitlines()
    assert lines, done
    records = [json.loads(line) for line in lines]  # no plain-text line at all
    assert any(r["level"] == "error" and expected in r["message"] for r in records), records


def test_a_configuration_asking_for_json_gets_its_errors_as_json(tmp_path: Path) -> None:
    config = tmp_path / "plant.toml"
    config.write_text('[logging]\nformat = "json"\n[lines.a]\ndevice = "/dev/null"\nbaud = 1\n')
    done = subprocess.run(
        gateway("--config", str(config)),
        capture_output=True, text=True, timeout=DEADLINE_S * 3, check=False,
    )  # fmt: skip
    assert done.returncode == 2, done
    (record,) = [json.loads(line) for line in done.stderr.strip().splitlines()]
    assert record["level"] == "error" and record["source"] == str(config)
    assert record["problems"] == ["lines.a.baud: unknown key; did you mean 'baudrate'?"]
