"""`modbus-gateway scan` against the simulator: slaves found at a baud rate the scan must find."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import serial

from gateway.core.rtu import encode_rtu
from gateway.sim import plc, power_controller, zl69x
from tests.helpers import DEADLINE_S, GatewayOnSim, SimBus, SimFactory

SIM_BAUDRATE = 38400  # not the first the scan tries: it has to find it


def _scan(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", "scan", *args], stdin=subprocess.DEVNULL,
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip


def _line(make_sim: SimFactory) -> SimBus:
    return make_sim(
        {2: plc(2), 5: zl69x(5), 7: power_controller(7)},
        baudrate=SIM_BAUDRATE, strict_baudrate=True,
    )  # fmt: skip


def test_the_simulator_answers_only_at_its_own_baud_rate(make_sim: SimFactory) -> None:
    sim = make_sim({1: plc(1)}, baudrate=19200, strict_baudrate=True)
    request = encode_rtu(1, bytes.fromhex("03 0000 0001"))
    with serial.Serial(sim.path, 9600, timeout=0.3) as port:
        port.write(request)
        assert port.read(7) == b""
        assert sim.stats().wrong_baudrate == 1
        port.baudrate = 19200
        port.timeout = DEADLINE_S
        port.write(request)
        assert port.read(7) == encode_rtu(1, bytes.fromhex("03 02 0000"))
    assert sim.stats().requests == 1


def test_scan_finds_the_baud_rate_and_every_slave(make_sim: SimFactory) -> None:
    sim = _line(make_sim)
    done = _scan("--serial", sim.path, "--baudrate", "auto", "--range", "1-8",
                 "--timeout", "0.05")  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == f"{sim.path} at {SIM_BAUDRATE} 8N1: 3 slave(s)"
    table = {line.split()[0]: line for line in lines[2:5]}
    assert sorted(table) == ["2", "5", "7"]
    assert "Nietz Electric ZQ600 V1.0.1.1" in table["2"] and "ZQ600 (running)" in table["2"]
    assert "ZL-69X" in table["5"]  # identification only: it has no FC 17
    assert table["5"].rstrip().endswith("-")
    assert table["7"].split()[1:] == ["ok", "-", "-"]  # neither FC 43 nor FC 17
    assert "  9600 8N1: no answer" in lines and f"  {SIM_BAUDRATE} 8N1: answers" in lines
    # progress on stderr: one line per format when it is not a terminal
    assert "9600 8N1: no answer" in done.stderr
    assert f"{SIM_BAUDRATE} 8N1: 3 slave(s) answer" in done.stderr
    assert sim.stats().wrong_baudrate > 0  # the wrong rates were really refused


def test_scan_a_line_of_a_configuration_file(make_sim: SimFactory, tmp_path: Path) -> None:
    sim = _line(make_sim)
    config = tmp_path / "gateway.toml"
    config.write_text(
        f'[lines.other]\ndevice = "/dev/null"\nunits = [1]\n'
        f'[lines.plant]\ndevice = "{sim.path}"\nbaudrate = {SIM_BAUDRATE}\nunits = [2]\n'
    )
    done = _scan("--config", str(config), "--line", "plant", "--range", "1-3,5",
                 "--timeout", "0.05", "--no-identify", "--json")  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["settings"] == {"baudrate": SIM_BAUDRATE, "parity": "N", "stop_bits": 1}
    assert [(s["address"], s["answer"], s["identification"]) for s in result["slaves"]] == [
        (2, "ok", {}), (5, "ok", {}),
    ]  # fmt: skip
    wrong = _scan("--config", str(config), "--line", "nope")
    assert wrong.returncode == 2 and "--line 'nope': choose one of other, plant" in wrong.stderr


def test_scan_at_the_wrong_rate_finds_nobody_and_says_so(make_sim: SimFactory) -> None:
    sim = _line(make_sim)
    done = _scan("--serial", sim.path, "--baudrate", "9600", "--range", "1-3", "--timeout",
                 "0.05")  # fmt: skip
    assert done.returncode == 1
    assert done.stdout.splitlines()[0] == f"{sim.path} at 9600 8N1: 0 slave(s)"
    missing = _scan("--serial", os.path.join(os.path.dirname(sim.path), "nonexistent"),
                    "--range", "1")  # fmt: skip
    assert missing.returncode == 1 and "cannot open" in missing.stderr


def test_scan_refuses_a_line_a_running_gateway_holds(gateway_with: GatewayOnSim) -> None:
    sim, gw = gateway_with({1: plc(1)})
    with gw.connect() as master:
        master.request(1, bytes.fromhex("03 0000 0001"))  # the gateway has the line open
    requests = sim.stats().requests
    done = _scan("--serial", sim.path, "--range", "1", "--timeout", "0.05")
    assert done.returncode == 1
    assert f"{sim.path} is in use by pid {os.getpid()}" in done.stderr
    assert "stop the gateway (or that program) first" in done.stderr
    assert sim.stats().requests == requests  # nothing was sent on the gateway's line
