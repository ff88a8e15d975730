"""The load generator: many Modbus TCP masters in one process, every answer verified.

Run by the benchmark as its own process (``python -m bench.loadgen SPEC_JSON``)
so that it competes with the gateway and the simulator for the CPU the way a
remote client would not, but never shares an interpreter with them. It speaks
Modbus TCP with raw asyncio protocols (uvloop when importable) and does not
import the gateway: its reading of the protocol is its own.

Every request reads (FC03) or writes (FC06) holding registers of the
simulator's ``plc`` profile, whose registers 1000..9999 hold their own address,
so every answer can be checked byte for byte: transaction id (it must be one
this connection has outstanding), protocol id, length, unit id, function, byte
count and every register value. Masters keep ``pipeline`` requests in flight,
each with a different unit and address, so a reply given under the wrong
transaction id is caught.

Modes:

``poll``      each master polls round robin over ``units`` as fast as answers come.
``coalesce``  ``masters`` readers poll one block of unit ``units[0]``; one more
              master writes an increasing value into that block, then reads it.
              Every read is checked against the writes: it must show at least the
              last write acknowledged before the read was sent (read-after-write),
              and nothing newer than the last write sent before the answer came.
``slow``      each master sends one request every ``period`` seconds (random phase).

Throughput is measured between the first and last answer inside the window
(``(n - 1) / (t_last - t_first)``), which removes the +-1 answer quantisation
of a short window on a slow line. CPU time of the watched processes (the
gateway, the simulator) is read from ``/proc/PID/stat`` at the window's edges.
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import resource
import struct
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any, cast

READ_HOLDING = 3
WRITE_SINGLE = 6
FIRST_SELF_CHECKING = 1000  # plc profile: registers 1000..9999 hold their own address
MASTER_AREAS = 100  # registers 1000..9899 split into one area per master
AREA_SIZE = 89
AREA_SLOTS = 8  # blocks of ``quantity`` (<= 11) registers per area
_HEADER = struct.Struct(">HHHB")
_HEADER_SIZE = 7
_MAX_EXAMPLES = 8
_REAPER_PERIOD = 0.25
_WRITE_REGISTER_OFFSET = 5
_FIRST_WRITTEN_VALUE = 20000


@dataclass
class LoadSpec:
    """What to run; passed to the process as one JSON argument."""

    port: int
    host: str = "127.0.0.1"
    mode: str = "poll"
    masters: int = 10
    pipeline: int = 1
    units: list[int] = field(default_factory=lambda: [1])
    quantity: int = 10
    warmup: float = 1.0
    duration: float = 5.0
    period: float = 2.0  #: slow mode: seconds between one master's requests
    writer_period: float = 0.25  #: coalesce mode: pause between the writer's write+read rounds
    dead_units: list[int] = field(default_factory=list)  #: units expected to answer 0x0B
    watch_pids: dict[str, int] = field(default_factory=dict)
    request_timeout: float = 10.0  #: an answer later than this counts as lost
    connect_timeout: float = 10.0
    drain: float = 2.0  #: after the window, wait this long for answers still outstanding
    seed: int = 1


@dataclass
class LoadResult:
    """What happened; printed by the process as one JSON line."""

    window_s: float = 0.0
    answers: int = 0  #: answers of any kind received inside the window
    ok: int = 0  #: correct normal answers inside the window
    ok_per_s: float = 0.0
    ok_by_unit: dict[str, int] = field(default_factory=dict)
    ok_per_s_by_unit: dict[str, float] = field(default_factory=dict)
    expected_exceptions: int = 0  #: 0x0B from ``dead_units`` inside the window
    reads_ok: int = 0  #: coalesce mode: correct FC03 answers inside the window
    reads_per_s: float = 0.0
    writes_ok: int = 0
    exceptions: dict[str, int] = field(default_factory=dict)  #: unexpected, whole run
    wrong_answers: int = 0  #: whole run, warm-up and drain included
    wrong_kinds: dict[str, int] = field(default_factory=dict)
    wrong_examples: list[str] = field(default_factory=list)
    read_after_write_violations: int = 0
    lost: int = 0  #: requests never answered within ``request_timeout``
    connect_failures: int = 0
    disconnects: int = 0
    requests_sent: int = 0
    latency_ms: dict[str, float] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)  #: per watched process, in the window
    loadgen_cpu_s: float = 0.0
    machine_cpu_s: float = 0.0  #: busy CPU time of the whole machine in the window (all CPUs)
    connected: int = 0

    @property
    def errors(self) -> int:
        """Everything that should never happen in a healthy run."""
        return (
            self.wrong_answers
            + self.read_after_write_violations
            + self.lost
            + self.connect_failures
            + self.disconnects
            + sum(self.exceptions.values())
        )


def _clock_ticks() -> int:
    return os.sysconf("SC_CLK_TCK")


def process_cpu_seconds(pid: int) -> float | None:
    """utime + stime of ``pid`` in seconds, or None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            raw = stat.read()
    except OSError:
        return None
    fields = raw[raw.rindex(b")") + 2 :].split()
    # fields[0] is field 3 (state): utime and stime are fields 14 and 15.
    return (int(fields[11]) + int(fields[12])) / _clock_ticks()


def machine_busy_seconds() -> float:
    """Busy CPU time of every CPU since boot (``/proc/stat``: all but idle and iowait)."""
    with open("/proc/stat", "rb") as stat:
        fields = stat.readline().split()[1:]
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(f) for f in fields[:8])
    return (user + nice + system + irq + softirq + steal) / _clock_ticks()


def percentile(sorted_values: list[float], fraction: float) -> float:
    """The nearest-rank percentile of an ascending list (0 when empty)."""
    if not sorted_values:
        return 0.0
    rank = max(0, min(len(sorted_values) - 1, round(fraction * len(sorted_values)) - 1))
    return sorted_values[rank]


def expected_registers(address: int, quantity: int) -> bytes:
    """The register bytes the plc profile holds at ``address`` (self-checking area)."""
    return b"".join(value.to_bytes(2, "big") for value in range(address, address + quantity))


class Recorder:
    """Counts answers and keeps the window's bookkeeping, shared by every master."""

    def __init__(self, spec: LoadSpec) -> None:
        self.spec = spec
        self.measuring = False
        self.stopping = False
        self.window_start = 0.0
        self.window_end = 0.0
        self.first_answer = 0.0
        self.last_answer = 0.0
        self.answers = 0
        self.ok = 0
        self.first_ok = 0.0
        self.last_ok = 0.0
        self.ok_by_unit: Counter[int] = Counter()
        self.unit_first: dict[int, float] = {}
        self.unit_last: dict[int, float] = {}
        self.expected_exceptions = 0
        self.reads_ok = 0
        self.first_read = 0.0
        self.last_read = 0.0
        self.writes_ok = 0
        self.exceptions: Counter[str] = Counter()
        self.wrong_kinds: Counter[str] = Counter()
        self.wrong_examples: list[str] = []
        self.raw_violations = 0
        self.lost = 0
        self.connect_failures = 0
        self.disconnects = 0
        self.requests_sent = 0
        self.latencies: list[float] = []
        self.dead_units = frozenset(spec.dead_units)

    def wrong(self, kind: str, detail: str) -> None:
        """Record a wrong answer."""
        self.wrong_kinds[kind] += 1
        if len(self.wrong_examples) < _MAX_EXAMPLES:
            self.wrong_examples.append(f"{kind}: {detail}")

    def answered(self, now: float, sent_at: float, unit: int, ok: bool, read: bool) -> None:
        """Account one verified answer received at ``now``."""
        if not self.measuring:
            return
        self.answers += 1
        self.latencies.append(now - sent_at)
        if not ok:
            return
        self.ok += 1
        if not self.first_ok:
            self.first_ok = now
        self.last_ok = now
        self.ok_by_unit[unit] += 1
        self.unit_first.setdefault(unit, now)
        self.unit_last[unit] = now
        if read:
            self.reads_ok += 1
            if not self.first_read:
                self.first_read = now
            self.last_read = now
        else:
            self.writes_ok += 1


def _rate(count: int, first: float, last: float, window: float) -> float:
    """Answers per second from the spacing of the first and last one (count/window if too few)."""
    if count >= 3 and last > first:
        return (count - 1) / (last - first)
    return count / window if window > 0 else 0.0


class Master(asyncio.Protocol):
    """One Modbus TCP master connection."""

    def __init__(self, index: int, recorder: Recorder, shared: SharedState) -> None:
        self.index = index
        self.recorder = recorder
        self.shared = shared
        spec = recorder.spec
        self.units = spec.units
        if not 1 <= spec.quantity <= AREA_SIZE // AREA_SLOTS:
            raise ValueError(f"quantity {spec.quantity} outside 1..{AREA_SIZE // AREA_SLOTS}")
        self.quantity = spec.quantity
        self.transport: asyncio.Transport | None = None
        self.buffer = bytearray()
        # tid -> (sent_at, unit, expected pdu or None (checked by the caller), lower bound)
        self.outstanding: dict[int, tuple[float, int, bytes | None, int]] = {}
        self.next_tid = (index * 7919) & 0xFFFF
        self.sequence = index
        self.closed = asyncio.get_running_loop().create_future()
        self.on_write_ack: asyncio.Future[None] | None = None
        self.writer_read: asyncio.Future[None] | None = None

    # -- asyncio.Protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.recorder.stopping:
            self.recorder.disconnects += 1
            self.recorder.lost += len(self.outstanding)
            self.outstanding.clear()
        if not self.closed.done():
            self.closed.set_result(None)
        for waiter in (self.on_write_ack, self.writer_read):
            if waiter is not None and not waiter.done():
                waiter.set_exception(ConnectionError("connection lost"))

    def data_received(self, data: bytes) -> None:
        buffer = self.buffer
        if buffer:
            buffer += data
            data = bytes(buffer)
            buffer.clear()
        offset = 0
        end = len(data)
        now = time.perf_counter()
        while end - offset >= _HEADER_SIZE:
            length = (data[offset + 4] << 8) | data[offset + 5]
            size = 6 + length
            if length < 2 or length > 254:
                self.recorder.wrong("framing", f"MBAP length {length}")
                if self.transport is not None:
                    self.transport.abort()
                return
            if end - offset < size:
                break
            self.on_frame(data[offset : offset + size], now)
            offset += size
        if offset < end:
            self.buffer += data[offset:]

    # -- requests

    def _take_tid(self) -> int:
        tid = self.next_tid
        self.next_tid = (tid + 1) & 0xFFFF
        return tid

    def send_read(self, unit: int, address: int, lower: int = 0) -> None:
        """Send FC03 for ``quantity`` registers; ``lower`` is the read-after-write bound."""
        if self.transport is None or self.transport.is_closing():
            return
        tid = self._take_tid()
        pdu = struct.pack(">BHH", READ_HOLDING, address, self.quantity)
        if self.shared.coalesce_address is not None:
            expected = None
        elif unit in self.recorder.dead_units:
            expected = b"\x83\x0b"
        else:
            expected = self.shared.expected_reply(address)
        self.outstanding[tid] = (time.perf_counter(), unit, expected, lower)
        self.transport.write(_HEADER.pack(tid, 0, len(pdu) + 1, unit) + pdu)
        self.recorder.requests_sent += 1

    def send_write(self, unit: int, address: int, value: int) -> None:
        """Send FC06 (the answer must echo it)."""
        if self.transport is None or self.transport.is_closing():
            return
        tid = self._take_tid()
        pdu = struct.pack(">BHH", WRITE_SINGLE, address, value)
        self.outstanding[tid] = (time.perf_counter(), unit, pdu, -1)
        self.transport.write(_HEADER.pack(tid, 0, len(pdu) + 1, unit) + pdu)
        self.recorder.requests_sent += 1

    def send_next_poll(self) -> None:
        """The next request of a polling master: rotate units and addresses.

        Each of the first ``MASTER_AREAS`` masters reads its own address area, so no
        two masters ever send the same request and coalescing cannot inflate the
        figures of the polling scenarios; a master's pipelined requests differ too.
        """
        sequence = self.sequence
        self.sequence = sequence + 1
        unit = self.units[sequence % len(self.units)]
        area = FIRST_SELF_CHECKING + (self.index % MASTER_AREAS) * AREA_SIZE
        self.send_read(unit, area + (sequence % AREA_SLOTS) * self.quantity)

    # -- answers

    def on_frame(self, frame: bytes, now: float) -> None:
        recorder = self.recorder
        tid, protocol, _length, unit = _HEADER.unpack_from(frame)
        entry = self.outstanding.pop(tid, None)
        if entry is None:
            recorder.wrong("unknown_tid", f"master {self.index} tid {tid} {frame.hex()}")
            return
        sent_at, sent_unit, expected, lower = entry
        pdu = frame[_HEADER_SIZE:]
        ok = False
        read = pdu[:1] == b"\x03"
        if protocol != 0:
            recorder.wrong("protocol_id", f"{protocol} in {frame.hex()}")
        elif unit != sent_unit:
            recorder.wrong("unit", f"sent unit {sent_unit}, answer {frame.hex()}")
        elif expected is not None and pdu == expected:
            ok = expected[0] < 0x80
            if not ok and recorder.measuring:
                recorder.expected_exceptions += 1
        elif pdu and pdu[0] & 0x80:
            if len(pdu) != 2:
                recorder.wrong("exception_length", frame.hex())
            else:
                recorder.exceptions[f"{pdu[0]:#04x}/{pdu[1]:#04x}"] += 1
        elif expected is None:
            ok = self.shared.check_coalesced(pdu, lower, recorder)
        else:
            recorder.wrong("payload", f"unit {unit} expected {expected.hex()} got {pdu.hex()}")
        recorder.answered(now, sent_at, unit, ok, read)
        self.after_answer(lower, pdu, ok)

    def after_answer(self, lower: int, pdu: bytes, ok: bool) -> None:
        """Keep the pipeline full (poll and coalesce readers); writers override."""
        if self.shared.role(self) == "writer":
            waiter = self.on_write_ack if lower == -1 else self.writer_read
            if waiter is not None and not waiter.done():
                waiter.set_result(None)
            return
        if self.shared.slow or self.recorder.stopping:
            return
        if self.shared.coalesce_address is not None:
            self.send_read(self.units[0], self.shared.coalesce_address, self.shared.last_acked)
        else:
            self.send_next_poll()

    def reap(self, now: float, timeout: float) -> None:
        """Count requests outstanding for longer than ``timeout`` as lost."""
        expired = [tid for tid, entry in self.outstanding.items() if now - entry[0] > timeout]
        for tid in expired:
            del self.outstanding[tid]
            self.recorder.lost += 1


class SharedState:
    """What the masters of one run share: expected answers and the writer's progress."""

    def __init__(self, spec: LoadSpec) -> None:
        self.spec = spec
        self.slow = spec.mode == "slow"
        self.coalesce_address: int | None = FIRST_SELF_CHECKING if spec.mode == "coalesce" else None
        self._expected: dict[int, bytes] = {}
        self.writer: Master | None = None
        self.initial_value = FIRST_SELF_CHECKING + _WRITE_REGISTER_OFFSET
        self.last_acked = self.initial_value  #: last written value whose ack has arrived
        self.last_issued = self.initial_value  #: last written value sent to the gateway

    def role(self, master: Master) -> str:
        return "writer" if master is self.writer else "reader"

    def expected_reply(self, address: int) -> bytes:
        """The FC03 answer PDU for ``address`` (cached per address)."""
        reply = self._expected.get(address)
        if reply is None:
            quantity = self.spec.quantity
            reply = bytes((READ_HOLDING, 2 * quantity)) + expected_registers(address, quantity)
            self._expected[address] = reply
        return reply

    def check_coalesced(self, pdu: bytes, lower: int, recorder: Recorder) -> bool:
        """Check a read of the written block: fixed registers and the written one's bounds."""
        quantity = self.spec.quantity
        base = FIRST_SELF_CHECKING
        if len(pdu) != 2 + 2 * quantity or pdu[0] != READ_HOLDING or pdu[1] != 2 * quantity:
            recorder.wrong("payload", f"block read answered {pdu.hex()}")
            return False
        values = struct.unpack_from(f">{quantity}H", pdu, 2)
        for offset, value in enumerate(values):
            if offset == _WRITE_REGISTER_OFFSET:
                continue
            if value != base + offset:
                recorder.wrong("payload", f"register {base + offset} = {value}")
                return False
        written = values[_WRITE_REGISTER_OFFSET]
        valid = written == self.initial_value or (
            _FIRST_WRITTEN_VALUE <= written <= self.last_issued
        )
        if not valid:
            recorder.wrong("payload", f"written register = {written}, never written")
            return False
        if written < lower:
            recorder.raw_violations += 1
            if len(recorder.wrong_examples) < _MAX_EXAMPLES:
                recorder.wrong_examples.append(
                    f"read_after_write: saw {written}, {lower} was acknowledged before the read"
                )
            return False
        return True


async def _writer_loop(master: Master, shared: SharedState, recorder: Recorder) -> None:
    """Write an increasing value, wait for the ack, read the block back; repeat."""
    loop = asyncio.get_running_loop()
    unit = shared.spec.units[0]
    register = FIRST_SELF_CHECKING + _WRITE_REGISTER_OFFSET
    value = _FIRST_WRITTEN_VALUE
    while not recorder.stopping:
        master.on_write_ack = loop.create_future()
        shared.last_issued = value
        master.send_write(unit, register, value)
        await master.on_write_ack
        shared.last_acked = value
        master.writer_read = loop.create_future()
        master.send_read(unit, FIRST_SELF_CHECKING, shared.last_acked)
        await master.writer_read
        value = value + 1 if value < 0xFFFF else _FIRST_WRITTEN_VALUE
        if shared.spec.writer_period > 0:
            await asyncio.sleep(shared.spec.writer_period)


async def _slow_loop(
    master: Master, spec: LoadSpec, recorder: Recorder, rng: random.Random
) -> None:
    await asyncio.sleep(rng.uniform(0, spec.period))
    next_at = time.perf_counter()
    while not recorder.stopping:
        master.send_next_poll()
        next_at += spec.period
        await asyncio.sleep(max(0.0, next_at - time.perf_counter()))


def _raise_fd_limit(needed: int) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < needed:
        target = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))


def _cpu_snapshot(pids: dict[str, int]) -> dict[str, float | None]:
    return {name: process_cpu_seconds(pid) for name, pid in pids.items()}


async def run(spec: LoadSpec) -> LoadResult:
    """Connect, warm up, measure, drain; return the verified counts."""
    loop = asyncio.get_running_loop()
    recorder = Recorder(spec)
    shared = SharedState(spec)
    rng = random.Random(spec.seed)
    connections = spec.masters + (1 if spec.mode == "coalesce" else 0)
    _raise_fd_limit(connections + 256)

    async def connect(index: int) -> Master | None:
        try:
            _, protocol = await asyncio.wait_for(
                loop.create_connection(
                    lambda: Master(index, recorder, shared), spec.host, spec.port
                ),
                spec.connect_timeout,
            )
        except (OSError, TimeoutError):
            recorder.connect_failures += 1
            return None
        return protocol

    found = await asyncio.gather(*(connect(index) for index in range(connections)))
    masters = [master for master in found if master is not None]
    tasks: list[asyncio.Task[None]] = []
    if spec.mode == "coalesce" and masters:
        shared.writer = masters[-1]
        tasks.append(loop.create_task(_writer_loop(masters[-1], shared, recorder)))
        readers = masters[:-1]
    else:
        readers = masters
    for master in readers:
        if spec.mode == "slow":
            tasks.append(loop.create_task(_slow_loop(master, spec, recorder, rng)))
        elif spec.mode == "coalesce":
            for _ in range(spec.pipeline):
                master.send_read(spec.units[0], FIRST_SELF_CHECKING, shared.last_acked)
        else:
            for _ in range(spec.pipeline):
                master.send_next_poll()

    async def reaper() -> None:
        while True:
            await asyncio.sleep(_REAPER_PERIOD)
            now = time.perf_counter()
            for master in masters:
                master.reap(now, spec.request_timeout)

    reaper_task = loop.create_task(reaper())
    await asyncio.sleep(spec.warmup)
    cpu_before = _cpu_snapshot(spec.watch_pids)
    own_before = time.process_time()
    machine_before = machine_busy_seconds()
    recorder.window_start = time.perf_counter()
    recorder.measuring = True
    await asyncio.sleep(spec.duration)
    recorder.measuring = False
    recorder.window_end = time.perf_counter()
    cpu_after = _cpu_snapshot(spec.watch_pids)
    own_cpu = time.process_time() - own_before
    machine_cpu = machine_busy_seconds() - machine_before
    recorder.stopping = True
    for task in tasks:
        task.cancel()
    deadline = time.perf_counter() + spec.drain
    while any(master.outstanding for master in masters) and time.perf_counter() < deadline:
        await asyncio.sleep(0.02)
    reaper_task.cancel()
    for master in masters:
        if master.transport is not None:
            master.transport.close()
    if masters:
        await asyncio.wait([master.closed for master in masters], timeout=2.0)
    await asyncio.gather(*tasks, reaper_task, return_exceptions=True)
    result = _result(spec, recorder, len(masters), cpu_before, cpu_after, own_cpu)
    result.machine_cpu_s = machine_cpu
    return result


def _result(
    spec: LoadSpec,
    recorder: Recorder,
    connected: int,
    cpu_before: dict[str, float | None],
    cpu_after: dict[str, float | None],
    own_cpu: float,
) -> LoadResult:
    window = recorder.window_end - recorder.window_start
    latencies = sorted(recorder.latencies)
    cpu: dict[str, float] = {}
    for name, before in cpu_before.items():
        after = cpu_after.get(name)
        if before is not None and after is not None:
            cpu[name] = after - before
    return LoadResult(
        window_s=window,
        answers=recorder.answers,
        ok=recorder.ok,
        ok_per_s=_rate(recorder.ok, recorder.first_ok, recorder.last_ok, window),
        ok_by_unit={str(unit): count for unit, count in sorted(recorder.ok_by_unit.items())},
        ok_per_s_by_unit={
            str(unit): _rate(count, recorder.unit_first[unit], recorder.unit_last[unit], window)
            for unit, count in sorted(recorder.ok_by_unit.items())
        },
        expected_exceptions=recorder.expected_exceptions,
        reads_ok=recorder.reads_ok,
        reads_per_s=_rate(recorder.reads_ok, recorder.first_read, recorder.last_read, window),
        writes_ok=recorder.writes_ok,
        exceptions=dict(recorder.exceptions),
        wrong_answers=sum(recorder.wrong_kinds.values()),
        wrong_kinds=dict(recorder.wrong_kinds),
        wrong_examples=recorder.wrong_examples,
        read_after_write_violations=recorder.raw_violations,
        lost=recorder.lost,
        connect_failures=recorder.connect_failures,
        disconnects=recorder.disconnects,
        requests_sent=recorder.requests_sent,
        latency_ms={
            "p50": 1000 * percentile(latencies, 0.50),
            "p99": 1000 * percentile(latencies, 0.99),
            "max": 1000 * (latencies[-1] if latencies else 0.0),
        },
        cpu_s=cpu,
        loadgen_cpu_s=own_cpu,
        connected=connected,
    )


def spec_from_json(text: str) -> LoadSpec:
    """Build a spec from its JSON form (unknown keys are an error)."""
    raw: dict[str, Any] = json.loads(text)
    return LoadSpec(**raw)


def result_from_json(text: str) -> LoadResult:
    """Build a result from the JSON line the process printed."""
    raw: dict[str, Any] = json.loads(text)
    return LoadResult(**raw)


def main(argv: list[str] | None = None) -> int:
    """``python -m bench.loadgen SPEC_JSON``: run and print the result as one JSON line."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m bench.loadgen SPEC_JSON", file=sys.stderr)
        return 2
    spec = spec_from_json(args[0])
    try:
        import uvloop
    except ImportError:
        result = asyncio.run(run(spec))
    else:
        result = uvloop.run(run(spec))
    print(json.dumps(asdict(result)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
