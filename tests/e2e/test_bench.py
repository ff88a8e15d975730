"""The benchmark runs end to end, and its load generator really catches wrong answers.

``python -m bench --quick --scenario bad-crc`` starts the simulator (paced at
19200 baud, 5 % bad CRCs), the gateway and the load generator as separate
processes, exactly as the full benchmark does, and must finish with zero wrong
answers. The line scenarios (late answers, a slave dying, greedy masters, absent
units, the bare-forwarder floor, the paced lines' ceiling) run in their tiny
configuration: each must run to its figures with its faults really injected, and the
gateway must give no
wrong answer (the line without its late-answer protection gave one or two even in
these 2-second runs); whether it meets the throughput and share targets is the
benchmark's report, not this test's. Two broken servers show that
a benchmark reporting "0 wrong" means something: one lies about the values, one
answers each request with the previous request's data (a late answer taken for
the next one), and the load generator must say whose data it got.
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

from bench.__main__ import select
from bench.instruction_scenarios import count
from bench.loadgen import LoadSpec, run
from bench.scenarios import Bench, Timing, bare_server
from bench.values import register_block
from tests.helpers import TinyBench, mbap, require_tool

REPO = Path(__file__).resolve().parents[2]
SMOKE_BUDGET_S = 20.0
TINY_BUDGET_S = 30.0  # several tiny runs, each paying for three process starts


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
            self.transport.write(mbap(tid, unit, pdu))


def _serve(factory: type[asyncio.Protocol]) -> Iterator[int]:
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    stop = asyncio.Event()
    ports: list[int] = []

    async def serve() -> None:
        server = await loop.create_server(factory, "127.0.0.1", 0)
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


@pytest.fixture
def lying_server() -> Iterator[int]:
    yield from _serve(_LyingServer)


@pytest.fixture
def stale_server() -> Iterator[int]:
    yield from _serve(_StaleServer)


def test_load_generator_counts_wrong_answers(lying_server: int) -> None:
    spec = LoadSpec(port=lying_server, masters=2, pipeline=2, warmup=0.1, duration=0.3, drain=0.5)
    result = asyncio.run(run(spec))
    assert result.ok == 0
    assert result.wrong_answers > 0
    assert set(result.wrong_kinds) == {"payload"}


def test_tiny_late_and_dead_slave_scenarios_report_their_figures(tiny_bench: TinyBench) -> None:
    started = time.monotonic()
    run = tiny_bench("late", "dead-default", ok=(0, 1))
    results = run.results
    elapsed = time.monotonic() - started
    scenarios = results["scenarios"]
    assert set(scenarios) == {"late-few", "late-all", "dead-default"}
    late_all = scenarios["late-all"]["run"]
    assert late_all["simulator"]["late"]["sent"] > 0  # late answers really reached the line
    for run_figures in scenarios["late-few"].values():
        assert run_figures["simulator"]["late"]["scheduled"] > 0
        assert run_figures["load"]["ok"] > 0
    dead = scenarios["dead-default"]
    assert dead["run"]["simulator"]["died_at_monotonic"] is not None
    assert dead["run"]["load"]["killed_at"] is not None
    assert dead["baseline_tx_per_s"] > 0
    assert 0 <= dead["first_ratio"] <= 1.5
    assert "wrong answers + read-after-write" in run.stdout
    assert results["wrong_answers"] == 0, run.stdout
    assert elapsed <= TINY_BUDGET_S, f"took {elapsed:.1f} s"


def test_tiny_fairness_and_floor_scenarios_report_their_figures(tiny_bench: TinyBench) -> None:
    started = time.monotonic()
    run = tiny_bench("greedy", "absent", "floor", ok=(0, 1))
    results = run.results
    elapsed = time.monotonic() - started
    scenarios = results["scenarios"]
    greedy = scenarios["greedy"]["groups"]
    assert greedy["polite"]["sent"] > 0
    assert greedy["main"]["sent"] > greedy["polite"]["sent"]
    absent = scenarios["absent"]
    assert absent["fair_share"] == pytest.approx(1 / 9)
    assert absent["groups"]["live"]["sent_total"] > 0
    assert absent["groups"]["main"]["sent_total"] >= 8
    for masters in ("1", "10"):
        floor = scenarios["floor"][masters]
        assert floor["cpu_ratio"] > 0
        assert floor["bare_tx_per_s"][0] > 0
        assert floor["bare_runs"][0]["load"]["wrong_answers"] == 0  # the floor is a real one
    assert "gateway / mean bare" in run.stdout
    assert results["wrong_answers"] == 0, run.stdout
    assert elapsed <= TINY_BUDGET_S, f"took {elapsed:.1f} s"


def test_tiny_paced_scenario_measures_the_ceiling_beside_the_gateway(tiny_bench: TinyBench) -> None:
    started = time.monotonic()
    run = tiny_bench("paced", ok=(0, 1))
    results = run.results
    elapsed = time.monotonic() - started
    for baudrate in ("9600", "115200"):
        paced = results["scenarios"]["paced"][baudrate]
        ceiling = paced["ceiling_run"]
        assert ceiling["load"]["ok"] > 0, run.stdout  # the simulator answered it: right speed
        assert ceiling["load"]["wrong_answers"] == 0
        assert paced["ceiling_early_requests"] == 0  # it keeps t3.5: a ceiling, not a shortcut
        assert 0 < paced["ceiling_utilisation"] <= 1.0
    assert "of ceiling" in run.stdout
    assert elapsed <= TINY_BUDGET_S, f"took {elapsed:.1f} s"


def test_callgrind_counts_a_servers_instructions_per_transaction() -> None:
    """The ``instructions`` scenario's measurement, on the bare forwarder (it starts fast
    under valgrind; the gateway takes ~20 s): two windows, two counts, one cost."""
    require_tool("valgrind")
    bench = Bench(Timing.make(quick=True, tiny=True), lambda _line: None)
    counted = count(bench, "bare forwarder", bare_server(), (0.5, 1.5))
    assert counted.transactions[1] > counted.transactions[0] > 0
    assert counted.instructions[1] > counted.instructions[0] > 10**7  # a Python process
    # Measured here: ~63,000 per transaction. A start-up that did not cancel out, or a
    # count of another process, lands far outside this range.
    assert 20_000 < counted.per_transaction < 400_000, counted
    assert all(run.load.wrong_answers == 0 for run in counted.runs)


def test_scenario_names_select_by_prefix() -> None:
    assert select(["late"]) == ["late-few", "late-all"]
    assert select(["paced", "dead"]) == ["paced", "dead-slave", "dead-default"]
    assert select(["floor", "floor"]) == ["floor"]
    with pytest.raises(ValueError, match="no scenario 'nope'"):
        select(["nope"])


class _StaleServer(asyncio.Protocol):
    """Answers each FC03 with the data of the previous request it got (the first one correctly)."""

    previous: tuple[int, int, int] | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        while len(data) >= 12:
            tid, _protocol, _length, unit, _function, address, quantity = struct.unpack(
                ">HHHBBHH", data[:12]
            )
            data = data[12:]
            source = _StaleServer.previous or (unit, address, quantity)
            _StaleServer.previous = (unit, address, quantity)
            pdu = bytes((3, 2 * quantity)) + register_block(source[0], source[1], quantity)
            self.transport.write(mbap(tid, unit, pdu))


def test_load_generator_names_whose_data_a_wrong_answer_carried(stale_server: int) -> None:
    spec = LoadSpec(port=stale_server, masters=2, units=[1, 2], warmup=0.1, duration=0.3, drain=0.5)
    result = asyncio.run(run(spec))
    assert result.wrong_answers > 0
    assert set(result.wrong_kinds) == {"payload"}
    assert any("(the data of unit " in example for example in result.wrong_examples)
