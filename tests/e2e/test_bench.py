"""The benchmark runs end to end, and its load generator really catches wrong answers.

``python -m bench --quick --scenario bad-crc`` starts the simulator (paced at
19200 baud, 5 % bad CRCs), the gateway and the load generator as separate
processes, exactly as the full benchmark does, and must finish with zero wrong
answers. The second test points the load generator at a deliberately broken
server so that a benchmark reporting "0 wrong" is known to mean something.
"""

from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.loadgen import LoadSpec, run

REPO = Path(__file__).resolve().parents[2]
SMOKE_BUDGET_S = 20.0


def test_quick_scenario_completes_with_zero_wrong_answers(tmp_path: Path) -> None:
    output = tmp_path / "results.json"
    started = time.monotonic()
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "bench",
            "--quick",
            "--scenario",
            "bad-crc",
            "--output",
            str(output),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    elapsed = time.monotonic() - started
    assert done.returncode == 0, done.stdout + done.stderr
    results = json.loads(output.read_text())
    assert results["wrong_answers"] == 0
    assert results["failures"] == {}
    run_figures = results["scenarios"]["bad-crc"]["run"]
    assert run_figures["load"]["wrong_answers"] == 0
    assert run_figures["load"]["ok"] > 0
    assert run_figures["simulator"]["crc_errors_out"] > 0  # the faults were injected
    assert "Targets" in done.stdout
    assert elapsed <= SMOKE_BUDGET_S, f"took {elapsed:.1f} s"


class _LyingServer(asyncio.Protocol):
    """Answers FC03 with every register off by one, under the request's own transaction id."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        while len(data) >= 12:
            tid, _protocol, _length, unit, _function, address, quantity = struct.unpack(
                ">HHHBBHH", data[:12]
            )
            data = data[12:]
            values = struct.pack(f">{quantity}H", *range(address + 1, address + 1 + quantity))
            pdu = bytes((3, 2 * quantity)) + values
            self.transport.write(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)


@pytest.fixture
def lying_server() -> Iterator[int]:
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    stop = asyncio.Event()
    ports: list[int] = []

    async def serve() -> None:
        server = await loop.create_server(_LyingServer, "127.0.0.1", 0)
        ports.append(server.sockets[0].getsockname()[1])
        ready.set()
        await stop.wait()
        server.close()
        await server.wait_closed()

    thread = threading.Thread(target=loop.run_until_complete, args=(serve(),), daemon=True)
    thread.start()
    assert ready.wait(10)
    yield ports[0]
    loop.call_soon_threadsafe(stop.set)
    thread.join(10)
    loop.close()


def test_load_generator_counts_wrong_answers(lying_server: int) -> None:
    spec = LoadSpec(port=lying_server, masters=2, pipeline=2, warmup=0.1, duration=0.3, drain=0.5)
    result = asyncio.run(run(spec))
    assert result.ok == 0
    assert result.wrong_answers > 0
    assert set(result.wrong_kinds) == {"payload"}
