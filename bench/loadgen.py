"""The load generator: many Modbus TCP masters in one process, every answer verified.

Run by the benchmark as its own process (``python -m bench.loadgen SPEC_JSON``)
so that it competes with the gateway and the simulator for the CPU the way a
remote client would not, but never shares an interpreter with them. It speaks
Modbus TCP with raw asyncio protocols (uvloop when importable) and does not
import the gateway: its reading of the protocol is its own.

Every request reads (FC03) or writes (FC06) holding registers 1000..9999 of
the benchmark's slaves (``bench.slaves``), which hold
``bench.values.register_value(unit, address)``, so every answer can be checked
byte for byte: transaction id (it must be one this connection has outstanding),
protocol id, length, unit id, function, byte count and every register value.
Polling requests take their address from one counter per unit shared by every
master: no two requests to a unit among the last 900 read the same block, so an
answer delivered to another request (a late answer taken for the next one, a
reply under the wrong transaction id, another unit's data) is a wrong answer,
and identical requests never wait together (coalescing cannot inflate a figure).

Modes:

``poll``      each master polls round robin over ``units`` as fast as answers come.
``coalesce``  ``masters`` readers poll one block of unit ``units[0]``; one more
              master writes an increasing value into that block, then reads it.
              Every read is checked against the writes: it must show at least the
              last write acknowledged before the read was sent (read-after-write),
              and nothing newer than the last write sent before the answer came.
``slow``      each master sends one request every ``period`` seconds (random phase).
``cycle``     each master polls every ``period`` seconds with one request outstanding:
              the next goes at the later of its tick and the previous answer (a SCADA
              poll cycle; a slow answer lowers its poll rate).

``random_units`` picks each poll's unit at random from ``units`` instead of in
turn; ``max_requests`` stops each master of a group after that many requests, and
the window ends once every such master has had its answers; ``record`` keeps, per
group, every request's send and answer time (``time.perf_counter``, the system's
monotonic clock, which the simulator's stamps share), unit and outcome.

``groups`` adds masters that behave differently beside the main ones (a polite
master among greedy ones, a live one among masters polling absent units); each
group's answers are also counted on their own. Exception codes in ``tolerate``
(and 0x0B from ``flaky_units``) are outcomes the scenario expects (a full queue,
a slave answering late): counted, not errors. ``kill_after`` sends SIGUSR1 to the
simulator that many seconds into the window (``bench.slaves --die-on-signal``);
``timeline`` keeps each unit's correct answers in 0.1 s buckets of the window.

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
import signal
import ssl
import struct
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any, cast

from .values import END_REGISTER, FIRST_REGISTER, identify_block, register_block, register_value

READ_HOLDING = 3
WRITE_SINGLE = 6
FIRST_SELF_CHECKING = FIRST_REGISTER
MAX_QUANTITY = 125  #: FC03's limit
_MAX_STRIDE = 10  #: registers between the starts of two polled blocks of a unit, at most
TIMELINE_BUCKET_S = 0.1
GATEWAY_BUSY = 0x06
PATH_UNAVAILABLE = 0x0A
TARGET_FAILED = 0x0B
_HEADER = struct.Struct(">HHHB")
_HEADER_SIZE = 7
_MAX_EXAMPLES = 8
_MAX_SEARCHED_UNITS = 16  # whose data a wrong answer carried: search this many units at most
_REAPER_PERIOD = 0.25
_DONE_POLL_S = 0.05  #: how often the window checks whether every limited master is done
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
    flaky_units: list[int] = field(default_factory=list)  #: 0x0B or data, both correct
    tolerate: list[int] = field(default_factory=list)  #: exception codes the main group expects
    groups: list[dict[str, Any]] = field(default_factory=list)  #: see ``GroupSpec``
    kill_after: float | None = None  #: SIGUSR1 to the simulator this far into the window
    timeline: bool = False  #: keep per-unit correct answers in 0.1 s buckets
    exception_pause: float = 0.0  #: poll mode: wait this long after an exception to resend
    random_units: bool = False  #: the main group picks each poll's unit at random
    max_requests: int = 0  #: the main group: each master stops after this many (0: no limit)
    record: bool = False  #: the main group keeps every request's times and outcome
    watch_pids: dict[str, int] = field(default_factory=dict)
    request_timeout: float = 10.0  #: an answer later than this counts as lost
    connect_timeout: float = 10.0
    drain: float = 2.0  #: after the window, wait this long for answers still outstanding
    seed: int = 1
    #: Modbus/TCP Security: ``{"ca": FILE, "cert": FILE, "key": FILE}`` (empty: plain TCP).
    tls: dict[str, str] = field(default_factory=dict)


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
    tolerated: dict[str, int] = field(default_factory=dict)  #: expected exceptions, whole run
    groups: dict[str, dict[str, Any]] = field(default_factory=dict)  #: per group of masters
    timeline: dict[str, list[int]] = field(default_factory=dict)  #: unit -> ok per 0.1 s
    killed_at: float | None = None  #: seconds into the window the simulator was signalled

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


def _client_tls(files: dict[str, str]) -> ssl.SSLContext:
    """A Modbus/TCP Security client context: trust ``ca``, present ``cert`` with ``key``."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(cafile=files["ca"])
    context.load_cert_chain(files["cert"], files["key"])
    return context


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


@dataclass
class GroupSpec:
    """Masters that behave alike; ``LoadSpec.groups`` holds extra ones as dicts of these fields."""

    name: str
    masters: int
    units: list[int]
    mode: str = "poll"  #: ``poll``, ``slow`` or ``cycle``
    pipeline: int = 1
    period: float = 1.0  #: slow and cycle modes: seconds between one master's requests
    tolerate: list[int] = field(default_factory=list)
    quantity: int | None = None  #: registers per read (None: ``LoadSpec.quantity``)
    random_units: bool = False  #: each poll's unit at random from ``units``, not in turn
    max_requests: int = 0  #: each master stops after this many requests (0: no limit)
    record: bool = False  #: keep every request's (sent, answered, unit, outcome)


class Group:
    """A group's spec and what its masters saw (the window's counts, the whole run's faults)."""

    def __init__(self, spec: GroupSpec) -> None:
        self.spec = spec
        self.tolerate = frozenset(spec.tolerate)
        self.sent = 0  #: requests sent inside the window
        self.sent_total = 0  #: requests sent in the whole run
        self.answers = 0  #: answers of any kind inside the window
        self.ok = 0
        self.first_ok = 0.0
        self.last_ok = 0.0
        self.exceptions: Counter[str] = Counter()  #: unexpected, inside the window
        self.tolerated: Counter[str] = Counter()  #: expected, inside the window
        self.wrong = 0  #: whole run
        self.lost = 0  #: whole run
        self.latencies: list[float] = []
        self.ok_by_master: Counter[int] = Counter()  #: inside the window
        #: The longest any request of the group had waited, unanswered, when the window
        #: closed (its wait is at least that; its answer, if any, is not in ``latencies``).
        self.oldest_unanswered = 0.0
        #: With ``record``: [sent, answered or None, unit, outcome] per request, whole run;
        #: outcome "ok", "wrong", "lost" or an exception's key (``0x83/0x0b``).
        self.records: list[list[Any]] = []

    def summary(self, window: float) -> dict[str, Any]:
        """The group's figures for the result."""
        latencies = sorted(self.latencies)
        extra = {"records": self.records} if self.spec.record else {}
        return {
            **extra,
            "masters": self.spec.masters,
            "sent": self.sent,
            "sent_total": self.sent_total,
            "answers": self.answers,
            "ok": self.ok,
            "ok_per_s": _rate(self.ok, self.first_ok, self.last_ok, window),
            "ok_share": self.ok / self.answers if self.answers else 0.0,
            "exceptions": dict(self.exceptions),
            "tolerated": dict(self.tolerated),
            "wrong": self.wrong,
            "lost": self.lost,
            "ok_by_master": sorted(self.ok_by_master.values()),
            "oldest_unanswered_ms": 1000 * self.oldest_unanswered,
            "latency_ms": {
                "p50": 1000 * percentile(latencies, 0.50),
                "p90": 1000 * percentile(latencies, 0.90),
                "p99": 1000 * percentile(latencies, 0.99),
                "max": 1000 * (latencies[-1] if latencies else 0.0),
            },
        }


def exception_key(function: int, code: int) -> str:
    """How exceptions are counted: ``0x83/0x0b``."""
    return f"{function:#04x}/{code:#04x}"


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
        self.flaky_units = frozenset(spec.flaky_units)
        self.tolerated: Counter[str] = Counter()
        self.timeline: dict[int, list[int]] | None = {} if spec.timeline else None
        self.groups: list[Group] = []
        self.group_units = [unit for extra in spec.groups for unit in extra.get("units", [])]
        self.killed_at: float | None = None

    def wrong(self, kind: str, detail: str, group: Group | None = None) -> None:
        """Record a wrong answer."""
        if group is not None:
            group.wrong += 1
        self.wrong_kinds[kind] += 1
        if len(self.wrong_examples) < _MAX_EXAMPLES:
            self.wrong_examples.append(f"{kind}: {detail}")

    def answered(
        self, now: float, sent_at: float, unit: int, ok: bool, read: bool, group: Group
    ) -> None:
        """Account one verified answer received at ``now``."""
        if not self.measuring:
            return
        self.answers += 1
        self.latencies.append(now - sent_at)
        group.answers += 1
        group.latencies.append(now - sent_at)
        if not ok:
            return
        group.ok += 1
        if not group.first_ok:
            group.first_ok = now
        group.last_ok = now
        if self.timeline is not None:
            buckets = self.timeline.setdefault(unit, [])
            index = int((now - self.window_start) / TIMELINE_BUCKET_S)
            if index >= len(buckets):
                buckets.extend([0] * (index + 1 - len(buckets)))
            buckets[index] += 1
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

    def __init__(self, index: int, recorder: Recorder, shared: SharedState, group: Group) -> None:
        self.index = index
        self.recorder = recorder
        self.shared = shared
        self.group = group
        spec = recorder.spec
        self.units = group.spec.units
        quantity = group.spec.quantity or spec.quantity
        if not 1 <= quantity <= MAX_QUANTITY:
            raise ValueError(f"quantity {quantity} outside 1..{MAX_QUANTITY}")
        self.quantity = quantity
        self.transport: asyncio.Transport | None = None
        self.buffer = bytearray()
        # tid -> (sent_at, unit, expected pdu or None (checked by the caller), lower bound)
        self.outstanding: dict[int, tuple[float, int, bytes | None, int]] = {}
        self.next_tid = (index * 7919) & 0xFFFF
        self.sequence = index
        self.closed = asyncio.get_running_loop().create_future()
        self.on_write_ack: asyncio.Future[None] | None = None
        self.writer_read: asyncio.Future[None] | None = None
        self.answer_waiter: asyncio.Future[None] | None = None  #: cycle mode: the next answer
        self.rng = random.Random(spec.seed * 1_000_003 + index)  #: ``random_units``
        self.polls = 0  #: polls sent (``max_requests``)

    # -- asyncio.Protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.recorder.stopping:
            self.recorder.disconnects += 1
            self.recorder.lost += len(self.outstanding)
            self.group.lost += len(self.outstanding)
            self._record_lost(list(self.outstanding.values()))
            self.outstanding.clear()
        if not self.closed.done():
            self.closed.set_result(None)
        if self.answer_waiter is not None and not self.answer_waiter.done():
            self.answer_waiter.set_result(None)
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
            expected = self.shared.expected_reply(unit, address, self.quantity)
        self.outstanding[tid] = (time.perf_counter(), unit, expected, lower)
        self.transport.write(_HEADER.pack(tid, 0, len(pdu) + 1, unit) + pdu)
        self.recorder.requests_sent += 1
        self.group.sent_total += 1
        if self.recorder.measuring:
            self.group.sent += 1

    def send_write(self, unit: int, address: int, value: int) -> None:
        """Send FC06 (the answer must echo it)."""
        if self.transport is None or self.transport.is_closing():
            return
        tid = self._take_tid()
        pdu = struct.pack(">BHH", WRITE_SINGLE, address, value)
        self.outstanding[tid] = (time.perf_counter(), unit, pdu, -1)
        self.transport.write(_HEADER.pack(tid, 0, len(pdu) + 1, unit) + pdu)
        self.recorder.requests_sent += 1
        self.group.sent_total += 1
        if self.recorder.measuring:
            self.group.sent += 1

    @property
    def done(self) -> bool:
        """Whether this master has sent its ``max_requests`` and had every answer."""
        limit = self.group.spec.max_requests
        return bool(limit) and self.polls >= limit and not self.outstanding

    def send_next_poll(self) -> None:
        """The next request of a polling master: the next unit (in turn, or at random with
        ``random_units``); the unit's next address. Nothing once ``max_requests`` are sent.

        The address comes from one counter per unit shared by every master, so no two
        recent requests to a unit are the same (see the module docstring).
        """
        limit = self.group.spec.max_requests
        if limit and self.polls >= limit:
            return
        self.polls += 1
        if self.group.spec.random_units:
            unit = self.rng.choice(self.units)
        else:
            sequence = self.sequence
            self.sequence = sequence + 1
            unit = self.units[sequence % len(self.units)]
        self.send_read(unit, self.shared.next_address(unit))

    def _record_lost(self, entries: list[tuple[float, int, bytes | None, int]]) -> None:
        if self.group.spec.record:
            self.group.records += [[sent_at, None, unit, "lost"] for sent_at, unit, *_ in entries]

    # -- answers

    def on_frame(self, frame: bytes, now: float) -> None:
        recorder = self.recorder
        tid, protocol, _length, unit = _HEADER.unpack_from(frame)
        group = self.group
        entry = self.outstanding.pop(tid, None)
        if entry is None:
            recorder.wrong("unknown_tid", f"master {self.index} tid {tid} {frame.hex()}", group)
            return
        sent_at, sent_unit, expected, lower = entry
        pdu = frame[_HEADER_SIZE:]
        ok = False
        read = pdu[:1] == b"\x03"
        outcome = "wrong"
        if protocol != 0:
            recorder.wrong("protocol_id", f"{protocol} in {frame.hex()}", group)
        elif unit != sent_unit:
            recorder.wrong("unit", f"sent unit {sent_unit}, answer {frame.hex()}", group)
        elif expected is not None and pdu == expected:
            ok = expected[0] < 0x80
            outcome = "ok" if ok else exception_key(pdu[0], pdu[1])
            if not ok and recorder.measuring:
                recorder.expected_exceptions += 1
        elif pdu and pdu[0] & 0x80:
            if len(pdu) != 2:
                recorder.wrong("exception_length", frame.hex(), group)
            else:
                key = outcome = exception_key(pdu[0], pdu[1])
                if pdu[1] in group.tolerate or (
                    pdu[1] == TARGET_FAILED and sent_unit in recorder.flaky_units
                ):
                    recorder.tolerated[key] += 1
                    if recorder.measuring:
                        group.tolerated[key] += 1
                else:
                    recorder.exceptions[key] += 1
                    if recorder.measuring:
                        group.exceptions[key] += 1
        elif expected is None:
            ok = self.shared.check_coalesced(pdu, lower, recorder)
            outcome = "ok" if ok else "wrong"
        else:
            recorder.wrong("payload", _payload_detail(unit, expected, pdu, recorder), group)
        if group.spec.record:
            group.records.append([sent_at, now, sent_unit, outcome])
        recorder.answered(now, sent_at, unit, ok, read, group)
        if ok and recorder.measuring:
            group.ok_by_master[self.index] += 1
        self.after_answer(lower, pdu, ok)

    def after_answer(self, lower: int, pdu: bytes, ok: bool) -> None:
        """Keep the pipeline full (poll and coalesce readers); writers override."""
        if self.shared.role(self) == "writer":
            waiter = self.on_write_ack if lower == -1 else self.writer_read
            if waiter is not None and not waiter.done():
                waiter.set_result(None)
            return
        if self.group.spec.mode == "cycle":
            if self.answer_waiter is not None and not self.answer_waiter.done():
                self.answer_waiter.set_result(None)
            return
        if self.group.spec.mode == "slow" or self.recorder.stopping:
            return
        if self.shared.coalesce_address is not None:
            self.send_read(self.units[0], self.shared.coalesce_address, self.shared.last_acked)
        elif pdu[:1] and pdu[0] & 0x80 and self.recorder.spec.exception_pause > 0:
            asyncio.get_running_loop().call_later(
                self.recorder.spec.exception_pause, self._poll_again
            )
        else:
            self.send_next_poll()

    def _poll_again(self) -> None:
        if not self.recorder.stopping:
            self.send_next_poll()

    def reap(self, now: float, timeout: float) -> None:
        """Count requests outstanding for longer than ``timeout`` as lost."""
        expired = [tid for tid, entry in self.outstanding.items() if now - entry[0] > timeout]
        for tid in expired:
            self._record_lost([self.outstanding.pop(tid)])
            self.recorder.lost += 1
            self.group.lost += 1
        if expired and self.answer_waiter is not None and not self.answer_waiter.done():
            self.answer_waiter.set_result(None)


def _payload_detail(unit: int, expected: bytes, pdu: bytes, recorder: Recorder) -> str:
    """Whose data a wrong answer carried, for the first few (the search is slow)."""
    detail = f"unit {unit} expected {expected.hex()} got {pdu.hex()}"
    if len(recorder.wrong_examples) >= _MAX_EXAMPLES or len(pdu) < 2 or pdu[0] != READ_HOLDING:
        return detail
    candidates = list(dict.fromkeys([*recorder.spec.units, *recorder.group_units]))
    source = identify_block(pdu[2:], candidates[:_MAX_SEARCHED_UNITS])
    if source is None:
        return detail + " (no slave holds this block)"
    return detail + f" (the data of unit {source[0]}, registers {source[1]}..)"


class SharedState:
    """What the masters of one run share: expected answers and the writer's progress."""

    def __init__(self, spec: LoadSpec) -> None:
        self.spec = spec
        self.coalesce_address: int | None = FIRST_SELF_CHECKING if spec.mode == "coalesce" else None
        self._expected: dict[tuple[int, int, int], bytes] = {}
        self._next_slot: Counter[int] = Counter()
        # Blocks start ``quantity`` registers apart (at most ``_MAX_STRIDE``: long reads
        # overlap, and still differ), and the longest read of any group fits after the last.
        longest = max([spec.quantity, *(extra.get("quantity") or 0 for extra in spec.groups)])
        self._stride = min(spec.quantity, _MAX_STRIDE)
        self._slots = (END_REGISTER - FIRST_REGISTER - longest) // self._stride + 1
        self.writer: Master | None = None
        self.block_unit = spec.units[0]
        self.block = register_block(self.block_unit, FIRST_SELF_CHECKING, spec.quantity)
        self.initial_value = register_value(
            self.block_unit, FIRST_SELF_CHECKING + _WRITE_REGISTER_OFFSET
        )
        #: last written value whose ack has arrived (0: none yet; written values are >= 20000)
        self.last_acked = 0
        self.last_issued = 0  #: last written value sent to the gateway

    def next_address(self, unit: int) -> int:
        """The unit's next block: a counter per unit, shared by every master."""
        slot = self._next_slot[unit]
        self._next_slot[unit] = slot + 1
        return FIRST_REGISTER + (slot % self._slots) * self._stride

    def role(self, master: Master) -> str:
        return "writer" if master is self.writer else "reader"

    def expected_reply(self, unit: int, address: int, quantity: int) -> bytes:
        """The FC03 answer PDU for ``quantity`` registers from ``address`` of ``unit`` (cached)."""
        key = (unit, address, quantity)
        reply = self._expected.get(key)
        if reply is None:
            reply = bytes((READ_HOLDING, 2 * quantity)) + register_block(unit, address, quantity)
            self._expected[key] = reply
        return reply

    def check_coalesced(self, pdu: bytes, lower: int, recorder: Recorder) -> bool:
        """Check a read of the written block: fixed registers and the written one's bounds."""
        quantity = self.spec.quantity
        if len(pdu) != 2 + 2 * quantity or pdu[0] != READ_HOLDING or pdu[1] != 2 * quantity:
            recorder.wrong("payload", f"block read answered {pdu.hex()}")
            return False
        at = 2 + 2 * _WRITE_REGISTER_OFFSET
        if pdu[2:at] != self.block[: at - 2] or pdu[at + 2 :] != self.block[at:]:
            recorder.wrong("payload", f"block read answered {pdu.hex()}")
            return False
        written = (pdu[at] << 8) | pdu[at + 1]
        if _FIRST_WRITTEN_VALUE <= written <= self.last_issued:
            seen = written
        elif written == self.initial_value:
            seen = 0  # the value before any write: older than every acknowledged one
        else:
            recorder.wrong("payload", f"written register = {written}, never written")
            return False
        if seen < lower:
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


async def _slow_loop(master: Master, recorder: Recorder, rng: random.Random) -> None:
    """One request every ``period``; in cycle mode, also never before the last one's answer."""
    period = master.group.spec.period
    cycle = master.group.spec.mode == "cycle"
    loop = asyncio.get_running_loop()
    await asyncio.sleep(rng.uniform(0, period))
    next_at = time.perf_counter()
    while not recorder.stopping:
        waiter: asyncio.Future[None] = loop.create_future()
        if cycle:
            master.answer_waiter = waiter
        master.send_next_poll()
        if cycle and master.outstanding:
            await waiter  # set by the answer, the reaper or the disconnection
        next_at = max(next_at + period, time.perf_counter()) if cycle else next_at + period
        await asyncio.sleep(max(0.0, next_at - time.perf_counter()))


def _groups(spec: LoadSpec) -> list[Group]:
    """The main masters (``spec``'s own fields), then ``spec.groups``."""
    main = GroupSpec(
        name="main",
        masters=spec.masters,
        units=list(spec.units),
        mode=spec.mode if spec.mode in ("slow", "cycle") else "poll",
        pipeline=spec.pipeline,
        period=spec.period,
        tolerate=list(spec.tolerate),
        random_units=spec.random_units,
        max_requests=spec.max_requests,
        record=spec.record,
    )
    return [Group(main)] + [Group(GroupSpec(**extra)) for extra in spec.groups]


async def _kill_later(spec: LoadSpec, recorder: Recorder) -> None:
    """Signal the simulator ``kill_after`` seconds into the window (a slave dies)."""
    assert spec.kill_after is not None
    await asyncio.sleep(max(0.0, recorder.window_start + spec.kill_after - time.perf_counter()))
    pid = spec.watch_pids.get("simulator")
    if pid is not None:
        os.kill(pid, signal.SIGUSR1)
        recorder.killed_at = time.perf_counter() - recorder.window_start


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
    groups = _groups(spec)
    recorder.groups = groups
    if spec.mode == "coalesce":
        groups[0].spec.masters += 1  # the writer
    members = [group for group in groups for _ in range(group.spec.masters)]
    _raise_fd_limit(len(members) + 256)

    tls = _client_tls(spec.tls) if spec.tls else None

    async def connect(index: int, group: Group) -> Master | None:
        try:
            _, protocol = await asyncio.wait_for(
                loop.create_connection(
                    lambda: Master(index, recorder, shared, group), spec.host, spec.port,
                    ssl=tls, server_hostname="localhost" if tls else None,
                ),
                spec.connect_timeout,
            )  # fmt: skip
        except (OSError, TimeoutError):
            recorder.connect_failures += 1
            return None
        return protocol

    found = await asyncio.gather(*(connect(index, group) for index, group in enumerate(members)))
    masters = [master for master in found if master is not None]
    tasks: list[asyncio.Task[None]] = []
    readers = masters
    if spec.mode == "coalesce" and masters:
        writer = [master for master in masters if master.group is groups[0]][-1]
        shared.writer = writer
        tasks.append(loop.create_task(_writer_loop(writer, shared, recorder)))
        readers = [master for master in masters if master is not writer]
    for master in readers:
        if master.group.spec.mode in ("slow", "cycle"):
            tasks.append(loop.create_task(_slow_loop(master, recorder, rng)))
        elif spec.mode == "coalesce":
            for _ in range(spec.pipeline):
                master.send_read(spec.units[0], FIRST_SELF_CHECKING, shared.last_acked)
        else:
            for _ in range(master.group.spec.pipeline):
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
    if spec.kill_after is not None:
        tasks.append(loop.create_task(_kill_later(spec, recorder)))
    limited = [master for master in masters if master.group.spec.max_requests]
    if limited:  # the window ends when every limited master is done (``duration`` at most)
        end = recorder.window_start + spec.duration
        while not all(master.done for master in limited) and time.perf_counter() < end:
            await asyncio.sleep(_DONE_POLL_S)
    else:
        await asyncio.sleep(spec.duration)
    recorder.measuring = False
    recorder.window_end = time.perf_counter()
    for master in masters:
        for entry in master.outstanding.values():
            waited = recorder.window_end - entry[0]
            master.group.oldest_unanswered = max(master.group.oldest_unanswered, waited)
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
        tolerated=dict(recorder.tolerated),
        groups={group.spec.name: group.summary(window) for group in recorder.groups},
        timeline={str(unit): counts for unit, counts in sorted((recorder.timeline or {}).items())},
        killed_at=recorder.killed_at,
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
