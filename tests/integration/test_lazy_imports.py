"""A configuration loads only what it uses: memory on small gateways is the whole budget.

A gateway started from a plain Modbus TCP configuration, serving a serial line, in a
fresh interpreter (nothing else imported first): ``cryptography`` is not loaded (it
comes with the first certificate, on TLS listeners and lines), the simulator is not
loaded outside the demo, nor the redundancy pair's modules without a pair, and pymodbus,
a test and benchmark tool, is never loaded.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: Starts the gateway (the CLI's module, as ``modbus-gateway`` does) on a pty and reports
#: which of the watched packages are loaded while it serves.
STARTED = """
import asyncio, json, os, sys, tty
from gateway import cli  # what the command imports
from gateway.app import Gateway
from gateway.config import build_config

leader, follower = os.openpty()
tty.setraw(follower)
config = build_config({
    "server": {"listen": "127.0.0.1:0"},
    "metrics": {"listen": "127.0.0.1:0"},
    "lines": {"field": {"device": os.ttyname(follower), "units": [1]}},
})

async def serve() -> list[str]:
    gateway = Gateway(config)
    await gateway.start()
    await asyncio.wait_for(gateway.ready.wait(), 20)
    try:
        return sorted(sys.modules)
    finally:
        await gateway.stop(0)

print(json.dumps(asyncio.run(serve())))
"""


def _loaded_while_serving() -> set[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *sys.path])}
    done = subprocess.run(
        [sys.executable, "-c", STARTED], cwd=ROOT, env=env,
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    loaded: list[str] = json.loads(done.stdout.splitlines()[-1])
    return set(loaded)


def test_a_plain_tcp_gateway_loads_no_tls_library_no_simulator_no_pair_no_pymodbus() -> None:
    loaded = _loaded_while_serving()
    assert "gateway.io.listeners.tls" in loaded and "gateway.metrics" in loaded  # it did start
    unwanted = {name for name in loaded if name.split(".")[0] in ("cryptography", "pymodbus")}
    unwanted |= {name for name in loaded if name.startswith(("gateway.sim", "gateway.io.pair"))}
    assert not unwanted, sorted(unwanted)
