"""``agent``: agent mode on a 19200-baud line, against the same masters without it.

The simulator (``bench.slaves --log-requests``, paced at 19200 baud 8N1) keeps every
request it executes with its arrival time, so wire traffic is counted where the wire
ends. The gateway runs as its own process with a ``[[poll]]`` block of unit 1's holding
registers 1000-1049 polled every second (``max_age`` 3 s, the default), and its metrics
endpoint on, for ``requests_total{outcome="memory"}``. The masters are asyncio Modbus
TCP connections in this process, one read outstanding each; the next read goes at its
0.1 s tick or at the answer, whichever is later. Four runs, each on a fresh simulator
and gateway:

1. **memory**: 10 masters, each reading a random sub-range (random first register and
   length) of the 50-register block 10 times a second. Every answer is checked byte for
   byte against the slave's data (``bench.values``); p50 and p99 of the masters' wait;
   wire transactions per second in the window against the poll plan (1 / ``every``).
2. **wire**: the same masters, the gateway without the ``[[poll]]`` block (wire-bound).
3. **freshness**: the masters of run 1; after a few seconds the slave falls silent
   (SIGUSR1, ``--die-on-signal``). Its last good poll is the last poll in its log. A
   normal answer to a read sent more than ``max_age`` after that poll arrived could only
   come from memory older than promised: counted, and it must be 0 (the poll's frame left
   the gateway before it arrived, and the gateway answered after the read was sent, so
   the count can only err towards 0 by the frame's transmission time). Reported: when
   the block turns stale (that poll + ``max_age``), and when the gateway's status unit
   (``[polling] status_unit``) shows it failing and its age past ``max_age``; the last
   answer from memory, the first 0x0B, and from when 0x0B comes at once (under 10 ms).
4. **write**: 4 writers, 250 times each (1,000 in all), write a holding register (FC 6)
   of a second block (1050-1059, polled every second too) and, once it is answered, read
   that register back at once; the 10 masters of run 1 read the first block meanwhile.
   An answer carrying any value but the one just written is counted (old value: one the
   register held before); must be 0.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import signal
import socket
import struct
import tempfile
import time
import urllib.request
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .procs import PYTHON, BenchError, Server, SimOptions, Simulator, Stack, free_port
from .scenarios import Bench, Check, ScenarioResult, Table
from .values import FIRST_REGISTER, register_block, register_value
from .wire import fc03_budget

BAUDRATE = 19200
UNIT = 1
BLOCK = (FIRST_REGISTER, 50)  #: the masters' block: first register, count
WRITE_BLOCK = (FIRST_REGISTER + 50, 10)  #: the writers' block, beside it
EVERY_S = 1.0
MAX_AGE_S = 3.0  #: the default, 3 x every
MASTERS = 10
READ_PERIOD_S = 0.1
WRITERS = 4
WRITE_CYCLES = 1000
MEMORY_P99_TARGET_S = 0.010  #: reads answered from memory (the issue's target)
PLAN_TOLERANCE = 0.10
AT_ONCE_S = 0.010  #: a 0x0B answered this fast did not wait for the wire
#: The slave logs a poll when its frame has arrived; the gateway dated it when it began to
#: send it (a 50-register read's request takes 4 ms at 19200 baud).
FRAME_SLACK_S = 0.05
ANSWER_TIMEOUT_S = 10.0  #: a master gives up on an answer after this (counted as lost)
#: The unit the gateway answers with each block's age and state (``[polling]``); 248-255
#: are never routed by ``--serial``.
STATUS_UNIT = 250
STATUS_PERIOD_S = 0.05
EXCEPTION_0B = bytes((0x83, 0x0B))


def _mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def _read_pdu(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 3, address, count)


def _registers_answer(data: bytes) -> bytes:
    return bytes((3, len(data))) + data


@dataclass
class Read:
    """One master's read: when it was sent and answered, and what came back."""

    sent: float
    answered: float
    outcome: str  #: "ok", "wrong", "lost" or the exception ("0x83/0x0b")


@dataclass
class Writes:
    """What the writers saw."""

    cycles: int = 0
    read_back_ok: int = 0
    old_value: int = 0  #: the read after the write returned a value the register held before
    other_wrong: int = 0  #: a value it never held, or a malformed answer
    write_failed: dict[str, int] = field(default_factory=dict)
    read_failed: dict[str, int] = field(default_factory=dict)
    cycle_s: list[float] = field(default_factory=list)  #: write sent to read answered


class Master:
    """One Modbus TCP connection with one request outstanding (asyncio streams)."""

    def __init__(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, unit: int
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.unit = unit
        self.tid = 0

    @staticmethod
    async def connect(port: int, unit: int = UNIT) -> Master:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return Master(reader, writer, unit)

    async def ask(self, pdu: bytes) -> bytes | None:
        """The answer's PDU (checked: transaction id, protocol, length, unit), or None when
        none came within ``ANSWER_TIMEOUT_S`` or it was malformed."""
        self.tid = (self.tid + 1) & 0xFFFF
        self.writer.write(_mbap(self.tid, self.unit, pdu))
        try:
            header = await asyncio.wait_for(self.reader.readexactly(7), ANSWER_TIMEOUT_S)
            tid, protocol, length, unit = struct.unpack(">HHHB", header)
            if (tid, protocol, unit) != (self.tid, 0, self.unit) or not 2 <= length <= 254:
                return b""
            return await asyncio.wait_for(self.reader.readexactly(length - 1), ANSWER_TIMEOUT_S)
        except (TimeoutError, asyncio.IncompleteReadError, OSError):
            return None

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(OSError):
            await self.writer.wait_closed()


def _outcome(answer: bytes | None, expected: bytes) -> str:
    if answer is None:
        return "lost"
    if answer == expected:
        return "ok"
    if len(answer) == 2 and answer[0] == 0x83:
        return f"0x83/0x{answer[1]:02x}"
    return "wrong"


async def _reader(port: int, rng: random.Random, until: float, reads: list[Read]) -> None:
    """Random sub-ranges of the block at its tick or its answer, whichever is later."""
    master = await Master.connect(port)
    first, count = BLOCK
    tick = time.monotonic() + rng.uniform(0.0, READ_PERIOD_S)
    try:
        while tick < until:
            delay = tick - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            start = rng.randrange(count)
            length = rng.randint(1, count - start)
            address = first + start
            expected = _registers_answer(register_block(UNIT, address, length))
            sent = time.monotonic()
            answer = await master.ask(_read_pdu(address, length))
            reads.append(Read(sent, time.monotonic(), _outcome(answer, expected)))
            if answer is None:
                await master.close()
                master = await Master.connect(port)
            tick = max(tick + READ_PERIOD_S, time.monotonic())
    finally:
        await master.close()


async def _status(port: int, until: float, seen: list[tuple[float, int, int]]) -> None:
    """The status unit's two registers of the first block, every ``STATUS_PERIOD_S``:
    (time, age in tenths of a second, state)."""
    master = await Master.connect(port, STATUS_UNIT)
    try:
        while time.monotonic() < until:
            answer = await master.ask(_read_pdu(0, 2))
            if answer is not None and len(answer) == 6 and answer[:2] == b"\x03\x04":
                age, state = struct.unpack(">HH", answer[2:])
                seen.append((time.monotonic(), age, state))
            await asyncio.sleep(STATUS_PERIOD_S)
    finally:
        await master.close()


def _failure(answer: bytes | None) -> str:
    if answer is None:
        return "lost"
    if len(answer) == 2 and answer[0] & 0x80:
        return f"0x{answer[0]:02x}/0x{answer[1]:02x}"
    return "malformed"


async def _writer(port: int, index: int, cycles: int, writes: Writes) -> None:
    """Write a register of the second block, then read it back at once, ``cycles`` times."""
    master = await Master.connect(port)
    register = WRITE_BLOCK[0] + index
    initial = register_value(UNIT, register)
    held = {initial}  # every value the register has held before the one just written
    try:
        for cycle in range(cycles):
            value = 0x8000 | ((cycle * WRITERS + index) & 0x3FFF)  # unique among writers
            if value == initial:
                value ^= 0x4000
            write = struct.pack(">BHH", 6, register, value)
            started = time.monotonic()
            answer = await master.ask(write)
            writes.cycles += 1
            if answer != write:
                key = _failure(answer)
                writes.write_failed[key] = writes.write_failed.get(key, 0) + 1
                continue  # the register may or may not hold the value: no read-back
            answer = await master.ask(_read_pdu(register, 1))
            writes.cycle_s.append(time.monotonic() - started)
            found = int.from_bytes(answer[2:], "big") if answer and len(answer) == 4 else None
            if answer == _registers_answer(value.to_bytes(2, "big")):
                writes.read_back_ok += 1
            elif answer is None or (len(answer) == 2 and answer[0] & 0x80):
                key = _failure(answer)
                writes.read_failed[key] = writes.read_failed.get(key, 0) + 1
            elif found in held and answer[:2] == bytes((3, 2)):
                writes.old_value += 1
            else:
                writes.other_wrong += 1
            held.add(value)
    finally:
        await master.close()


def _run_loop(coroutine: Any) -> Any:
    try:
        import uvloop
    except ImportError:  # pragma: no cover - uvloop is a dependency on Linux
        return asyncio.run(coroutine)
    return uvloop.run(coroutine)


# -- one run: a simulator, a gateway, the masters ----------------------------------------


def _poll_table(first: int, count: int) -> str:
    return (
        f"[[poll]]\nunit = {UNIT}\nfunction = 3\naddress = {first}\ncount = {count}\n"
        f"every = {EVERY_S!r}\nmax_age = {MAX_AGE_S!r}\n\n"
    )


def _gateway(
    workdir: Path, link: str, port: int, metrics: int, blocks: Sequence[tuple[int, int]]
) -> Server:
    config = workdir / "gateway.toml"
    config.write_text(
        f"[server]\nmax_connections_per_source = 0\n\n[polling]\nstatus_unit = {STATUS_UNIT}\n\n"
        + "".join(_poll_table(first, count) for first, count in blocks)
    )
    command = [PYTHON, "-m", "gateway", "--serial", link, "--baudrate", str(BAUDRATE)]
    command += ["--listen", f"127.0.0.1:{port}", "--metrics", f"127.0.0.1:{metrics}"]
    command += ["--log-level", "info", "--config", str(config)]
    return Server(command, workdir, "server")


def _memory_answers(metrics_port: int) -> dict[str, float]:
    """``requests_total`` by outcome, summed over lines, units and functions."""
    url = f"http://127.0.0.1:{metrics_port}/metrics"
    with urllib.request.urlopen(url, timeout=5.0) as response:
        text = response.read().decode()
    totals: dict[str, float] = {}
    for line in text.splitlines():
        if not line.startswith("modbus_gateway_requests_total{"):
            continue
        labels, _, value = line.rpartition(" ")
        outcome = labels.partition('outcome="')[2].partition('"')[0]
        totals[outcome] = totals.get(outcome, 0.0) + float(value)
    return totals


@dataclass
class RunResult:
    """What one run gave: the masters' reads, the writers', the slave's log."""

    reads: list[Read]
    writes: Writes
    log: list[tuple[float, int, int, int]]
    requests_total: dict[str, float]
    died_at: float | None
    window: tuple[float, float]
    sim: dict[str, Any]


def _run(
    bench: Bench,
    label: str,
    blocks: Sequence[tuple[int, int]],
    masters: Callable[[int, int], Any],
    *,
    die: bool = False,
) -> RunResult:
    """Start the simulator and the gateway, run ``masters(port, simulator pid)``, stop."""
    bench.progress(f"  {label} ...")
    options = SimOptions(
        units=(UNIT,),
        baudrate=BAUDRATE,
        turnaround=fc03_budget(BAUDRATE).sim_turnaround_s,
        realtime=True,
        die_on_signal=(UNIT,) if die else (),
        log_requests=True,
    )
    with tempfile.TemporaryDirectory(prefix="modbus-bench-agent-") as temp:
        workdir = Path(temp)
        simulator = Simulator(options, workdir)
        port, metrics_port = free_port(), free_port()
        server = _gateway(workdir, str(simulator.link), port, metrics_port, blocks)
        stack = Stack(simulator, server)
        with stack:
            reads, writes, window, died_at = _run_loop(masters(port, simulator.pid))
            try:
                totals = _memory_answers(metrics_port)
            except OSError as error:
                raise BenchError(f"metrics endpoint: {error}: {server.log_tail()}") from None
        sim = stack.sim_stats
    log = [(t, f, a, c) for t, f, a, c in sim.pop("requests_log", {}).get(str(UNIT), [])]
    result = RunResult(reads, writes, log, totals, died_at, window, sim)
    ok = sum(read.outcome == "ok" for read in reads)
    bench.progress(f"  {label}: {ok} good reads of {len(reads)}, {len(log)} frames on the wire")
    return result


# -- the four runs -----------------------------------------------------------------------


def _quantile(values: Sequence[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


def _rate(times: Sequence[float]) -> float:
    """Events per second as ``(n - 1) / (last - first)`` (0 below two events)."""
    if len(times) < 2 or times[-1] <= times[0]:
        return 0.0
    return (len(times) - 1) / (times[-1] - times[0])


def _steady(
    bench: Bench, warmup: float, window: float, blocks: Sequence[tuple[int, int]], label: str
) -> dict[str, Any]:
    """Runs 1 and 2: the masters for ``warmup + window``, measured over the window."""

    def masters(port: int, _pid: int) -> Any:
        async def run() -> tuple[list[Read], Writes, tuple[float, float], None]:
            reads: list[Read] = []
            started = time.monotonic()
            until = started + warmup + window
            rng = random.Random(7)
            await asyncio.gather(
                *(_reader(port, random.Random(rng.random()), until, reads) for _ in range(MASTERS))
            )
            return reads, Writes(), (started + warmup, until), None

        return run()

    found = _run(bench, label, blocks, masters)
    start, end = found.window
    inside = [read for read in found.reads if start <= read.sent < end]
    waits = [read.answered - read.sent for read in inside if read.outcome == "ok"]
    frames = sorted(entry[0] for entry in found.log if start <= entry[0] < end)
    polls = sorted(
        entry[0]
        for entry in found.log
        if start <= entry[0] < end and (entry[1], entry[2], entry[3]) == (3, *BLOCK)
    )
    failures: dict[str, int] = {}
    for read in found.reads:
        if read.outcome != "ok":
            failures[read.outcome] = failures.get(read.outcome, 0) + 1
    plan = len(blocks) / EVERY_S
    return {
        "reads": len(inside),
        "reads_per_s": len(inside) / window,
        "good": len(waits),
        "wrong_answers": sum(read.outcome == "wrong" for read in found.reads),
        "failures": failures,
        "wait_s": {
            "p50": _quantile(waits, 0.5),
            "p99": _quantile(waits, 0.99),
            "max": max(waits, default=float("nan")),
        },
        "wire_frames": len(frames),
        "wire_tx_per_s": _rate(frames),
        "polls": len(polls),
        "poll_period_s": 1.0 / _rate(polls) if _rate(polls) else None,
        "other_frames": len(frames) - len(polls),
        "plan_tx_per_s": plan,
        "requests_total": found.requests_total,
        "early_requests": found.sim.get("early_requests", 0),
    }


def _freshness(bench: Bench, before: float, after: float) -> dict[str, Any]:
    """Run 3: the masters; the slave dies ``before`` s in; they go on ``after`` s past
    ``max_age``."""

    status: list[tuple[float, int, int]] = []  # the status unit's (time, age, state)

    def masters(port: int, pid: int) -> Any:
        async def run() -> tuple[list[Read], Writes, tuple[float, float], float]:
            reads: list[Read] = []
            started = time.monotonic()
            until = started + before + MAX_AGE_S + after
            rng = random.Random(11)
            tasks = [
                asyncio.create_task(_reader(port, random.Random(rng.random()), until, reads))
                for _ in range(MASTERS)
            ]
            tasks.append(asyncio.create_task(_status(port, until, status)))
            await asyncio.sleep(before)
            os.kill(pid, signal.SIGUSR1)
            died = time.monotonic()
            await asyncio.gather(*tasks)
            return reads, Writes(), (started, until), died

        return run()

    found = _run(bench, "freshness: the slave falls silent", [BLOCK], masters, die=True)
    died = found.sim.get("died_at_monotonic") or found.died_at
    assert died is not None
    polls = [entry[0] for entry in found.log if (entry[1], entry[2], entry[3]) == (3, *BLOCK)]
    last_poll = max((t for t in polls if t <= died), default=None)
    if last_poll is None:
        raise BenchError("freshness: the block was never polled before the slave fell silent")
    stale_at = last_poll + MAX_AGE_S
    after_death = [read for read in found.reads if read.sent >= died]
    normal = [read for read in found.reads if read.outcome == "ok" and read.answered > died]
    too_old = [read for read in normal if read.sent > stale_at]
    refused = [read for read in found.reads if read.outcome == "0x83/0x0b"]
    first_0b = min((read.answered for read in refused), default=None)
    slow = [read.answered for read in refused if read.answered - read.sent >= AT_ONCE_S]
    at_once = [
        read
        for read in refused
        if read.answered - read.sent < AT_ONCE_S and (not slow or read.sent > max(slow))
    ]
    outcomes: dict[str, int] = {}
    for read in after_death:
        outcomes[read.outcome] = outcomes.get(read.outcome, 0) + 1
    last_memory = max((read.answered for read in normal), default=None)
    # The gateway's own account (the status unit): failing, and an age past max_age.
    failing = min((t for t, _, state in status if t > died and state == 2), default=None)
    aged = min((t for t, age, _ in status if t > died and age >= 10 * MAX_AGE_S), default=None)

    def since_death(moment: float | None) -> float | None:
        return None if moment is None else moment - died

    return {
        "died_at": 0.0,
        "last_good_poll_s": last_poll - died,
        "stale_at_s": stale_at - died,
        "last_memory_answer_s": since_death(last_memory),
        "last_memory_answer_age_s": None if last_memory is None else last_memory - last_poll,
        "answers_from_memory_after_death": len(normal),
        "answers_older_than_max_age": len(too_old),
        "status_failing_s": since_death(failing),
        "status_aged_s": since_death(aged),
        "status_reads": len(status),
        "first_0x0b_s": since_death(first_0b),
        "0x0b_at_once_from_s": since_death(min((read.answered for read in at_once), default=None)),
        "0x0b_wait_s": {
            "p50": _quantile([r.answered - r.sent for r in refused], 0.5),
            "max": max((r.answered - r.sent for r in refused), default=float("nan")),
        },
        "outcomes_after_death": outcomes,
        "wrong_answers": sum(read.outcome == "wrong" for read in found.reads),
        "requests_total": found.requests_total,
    }


def _writes(bench: Bench, cycles: int) -> dict[str, Any]:
    """Run 4: the writers' cycles beside the masters; the masters stop with the writers."""

    def masters(port: int, _pid: int) -> Any:
        async def run() -> tuple[list[Read], Writes, tuple[float, float], None]:
            reads: list[Read] = []
            writes = Writes()
            started = time.monotonic()
            # The block is polled once before the writers start (a fresh gateway polls at once).
            await asyncio.sleep(1.0)
            rng = random.Random(13)
            readers = [
                asyncio.create_task(_reader(port, random.Random(rng.random()), float("inf"), reads))
                for _ in range(MASTERS)
            ]
            share, extra = divmod(cycles, WRITERS)
            await asyncio.gather(
                *(_writer(port, index, share + (index < extra), writes) for index in range(WRITERS))
            )
            ended = time.monotonic()
            for task in readers:
                task.cancel()
            await asyncio.gather(*readers, return_exceptions=True)
            return reads, writes, (started, ended), None

        return run()

    found = _run(
        bench, f"write then read, {cycles} times, beside the masters", [BLOCK, WRITE_BLOCK], masters
    )
    writes = found.writes
    start, end = found.window
    first, count = WRITE_BLOCK
    wire_read_backs = sum(
        1
        for entry in found.log
        if entry[1] == 3 and first <= entry[2] < first + count and entry[3] == 1
    )
    waits = [read.answered - read.sent for read in found.reads if read.outcome == "ok"]
    return {
        "cycles": writes.cycles,
        "read_back_ok": writes.read_back_ok,
        "old_values": writes.old_value,
        "other_wrong": writes.other_wrong,
        "write_failed": writes.write_failed,
        "read_failed": writes.read_failed,
        "cycle_s": {"p50": _quantile(writes.cycle_s, 0.5), "p99": _quantile(writes.cycle_s, 0.99)},
        "read_backs_on_the_wire": wire_read_backs,
        "seconds": end - start,
        "master_reads": len(found.reads),
        "master_wrong_answers": sum(read.outcome == "wrong" for read in found.reads),
        "master_wait_s": {"p50": _quantile(waits, 0.5), "p99": _quantile(waits, 0.99)},
        "requests_total": found.requests_total,
    }


def _ms(value: float | None) -> str:
    return "-" if value is None or value != value else f"{1000 * value:,.1f}"


def _s(value: float | None) -> str:
    return "-" if value is None else f"{value:+.2f} s"


def agent(bench: Bench) -> ScenarioResult:
    """Agent mode's figures (the module docstring): four runs at 19200 baud."""
    timing = bench.timing
    warmup = timing.pick(2.0, 2.0, 1.5)
    window = timing.pick(20.0, 8.0, 2.0)
    cycles = int(timing.pick(WRITE_CYCLES, WRITE_CYCLES, 40))
    memory = _steady(bench, warmup, window, [BLOCK], "10 masters, agent mode")
    wire = _steady(bench, warmup, window, [], "10 masters, no poll block (wire)")
    fresh = _freshness(bench, timing.pick(4.0, 3.0, 2.0), timing.pick(5.0, 3.0, 1.5))
    written = _writes(bench, cycles)

    steady = Table(
        f"Agent mode: {MASTERS} masters, each reading a random sub-range of holding registers "
        f"{BLOCK[0]}-{BLOCK[0] + BLOCK[1] - 1} of unit {UNIT} {1 / READ_PERIOD_S:g} times a "
        f"second (at its tick or its answer, whichever is later), {BAUDRATE} baud; "
        f"[[poll]] every = {EVERY_S:g} s, max_age = {MAX_AGE_S:g} s; {window:g} s window",
        [
            "run",
            "reads/s",
            "good",
            "wrong",
            "failures",
            "wait p50 ms",
            "p99 ms",
            "worst ms",
            "wire tx/s",
            "plan tx/s",
            "polls",
            "other frames",
            "answered from memory",
        ],
    )
    for name, found in (("agent mode", memory), ("no poll block", wire)):
        failures = ", ".join(f"{k} {v}" for k, v in sorted(found["failures"].items())) or "0"
        totals = found["requests_total"]
        steady.rows.append(
            [
                name,
                f"{found['reads_per_s']:.1f}",
                str(found["good"]),
                str(found["wrong_answers"]),
                failures,
                _ms(found["wait_s"]["p50"]),
                _ms(found["wait_s"]["p99"]),
                _ms(found["wait_s"]["max"]),
                f"{found['wire_tx_per_s']:.2f}",
                f"{found['plan_tx_per_s']:.2f}" if name == "agent mode" else "-",
                str(found["polls"]),
                str(found["other_frames"]),
                f"{totals.get('memory', 0):,.0f} of {sum(totals.values()):,.0f}",
            ]
        )
    freshness = Table(
        f"Freshness: the slave falls silent at 0 s (SIGUSR1); times from then; max_age = "
        f"{MAX_AGE_S:g} s",
        [
            "last good poll",
            "block stale",
            "status unit: failing / age >= max_age",
            "last answer from memory",
            "its data's age",
            "answers from memory after death",
            "older than max_age",
            "first 0x0B",
            "0x0B at once from",
            "0x0B wait p50 / worst ms",
            "reads after death",
        ],
    )
    outcomes = ", ".join(f"{k} {v}" for k, v in sorted(fresh["outcomes_after_death"].items()))
    age = fresh["last_memory_answer_age_s"]
    freshness.rows.append(
        [
            _s(fresh["last_good_poll_s"]),
            _s(fresh["stale_at_s"]),
            f"{_s(fresh['status_failing_s'])} / {_s(fresh['status_aged_s'])}",
            _s(fresh["last_memory_answer_s"]),
            "-" if age is None else f"{age:.3f} s",
            str(fresh["answers_from_memory_after_death"]),
            str(fresh["answers_older_than_max_age"]),
            _s(fresh["first_0x0b_s"]),
            _s(fresh["0x0b_at_once_from_s"]),
            f"{_ms(fresh['0x0b_wait_s']['p50'])} / {_ms(fresh['0x0b_wait_s']['max'])}",
            outcomes,
        ]
    )
    write_table = Table(
        f"Write then read: {WRITERS} writers write a holding register of a second block "
        f"({WRITE_BLOCK[0]}-{WRITE_BLOCK[0] + WRITE_BLOCK[1] - 1}, every = {EVERY_S:g} s) and "
        f"read it back as soon as the write is answered, {written['cycles']} times in all, "
        f"beside the {MASTERS} masters",
        [
            "cycles",
            "read back ok",
            "old values",
            "other wrong",
            "write failed",
            "read failed",
            "cycle p50 / p99 ms",
            "read-backs on the wire",
            "seconds",
            "masters' reads",
            "masters' wrong",
            "masters' wait p50 / p99 ms",
        ],
    )
    write_table.rows.append(
        [
            str(written["cycles"]),
            str(written["read_back_ok"]),
            str(written["old_values"]),
            str(written["other_wrong"]),
            str(sum(written["write_failed"].values())),
            str(sum(written["read_failed"].values())),
            f"{_ms(written['cycle_s']['p50'])} / {_ms(written['cycle_s']['p99'])}",
            str(written["read_backs_on_the_wire"]),
            f"{written['seconds']:.1f}",
            str(written["master_reads"]),
            str(written["master_wrong_answers"]),
            f"{_ms(written['master_wait_s']['p50'])} / {_ms(written['master_wait_s']['p99'])}",
        ]
    )

    plan = memory["plan_tx_per_s"]
    plan_error = abs(memory["wire_tx_per_s"] - plan) / plan
    wrong = (
        memory["wrong_answers"]
        + wire["wrong_answers"]
        + fresh["wrong_answers"]
        + written["master_wrong_answers"]
        + written["old_values"]
        + written["other_wrong"]
    )
    checks = [
        Check("agent: wrong answers (every run)", wrong, "0", wrong == 0),
        Check(
            "agent: masters' wait p99, answered from memory",
            memory["wait_s"]["p99"],
            f"<= {1000 * MEMORY_P99_TARGET_S:g} ms",
            memory["good"] > 0 and memory["wait_s"]["p99"] <= MEMORY_P99_TARGET_S,
            " s",
        ),
        Check(
            "agent: wire tx/s against the poll plan",
            memory["wire_tx_per_s"],
            f"{plan:g}/s within {PLAN_TOLERANCE:.0%}",
            plan_error <= PLAN_TOLERANCE,
            "/s",
        ),
        Check(
            "agent: answers from memory older than max_age",
            fresh["answers_older_than_max_age"],
            "0",
            fresh["answers_older_than_max_age"] == 0,
        ),
        Check(
            "agent: masters get 0x0B once the block is stale",
            fresh["first_0x0b_s"] if fresh["first_0x0b_s"] is not None else -1.0,
            f">= {fresh['stale_at_s']:.2f} s (stale)",
            fresh["first_0x0b_s"] is not None
            and fresh["first_0x0b_s"] >= fresh["stale_at_s"] - FRAME_SLACK_S,
            " s",
        ),
        Check(
            "agent: old values read after a write",
            written["old_values"],
            "0",
            written["old_values"] == 0 and written["other_wrong"] == 0,
        ),
    ]
    bench.other_faults += wrong
    notes = [
        "wire tx/s = (n - 1) / (last - first) over the frames the slave executed in the "
        "window (every frame, polls or not); plan = 1 / every per block",
        "wait = from the read's sending to its answer, at the master; answered from memory = "
        'the gateway\'s requests_total{outcome="memory"} over all its requests, whole run',
        "freshness: the last good poll is the last poll the slave executed; 'older than "
        "max_age' counts normal answers to reads sent more than max_age after it; the status "
        f"unit ({STATUS_UNIT}, read every {1000 * STATUS_PERIOD_S:g} ms) is the gateway's own "
        "account: when the block's state turned failing (its first poll without an answer) "
        "and when its age reached max_age",
    ]
    figures = {"memory": memory, "wire": wire, "freshness": fresh, "write": written}
    return ScenarioResult("agent", figures, [steady, freshness, write_table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"agent": agent}
