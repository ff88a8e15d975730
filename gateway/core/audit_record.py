"""Audit records and their hash chain: what a write did, and proof that no line went missing.

Theory of operation. The audit log holds one JSON object per line. A listener notes
each request that is **not a read** (``policy.classify``: its access includes a write,
so FC 8 subfunctions other than the counters, FC 21-23, FC 43 other than 14 and
unknown or user function codes count) and that either reached a line or was denied by
the policy. Its record says who (listener, peer, TLS role), where (unit → line and
slave), what (function, subfunction, addresses, values: at most ``MAX_VALUES`` shown,
with the count) and what became of it (``AuditOutcome``):

- ``answered``: the slave answered normally; ``exception``: the slave answered with an
  exception (``code``); ``denied``: the policy refused it (0x01, never sent);
- ``unknown``: it went on the wire and no usable answer came (timeout or garbage: the
  master got 0x0B, or the line was lost mid-request): it may have executed;
- ``broadcast``: sent to unit 0, where no answer is expected.

A write answered without reaching the wire (0x0A: no route, line down or full; 0x06:
the master's queue full; 0x0B for an isolated slave; the master left before its turn)
is **not recorded**: it did nothing to the plant. Invalid requests and the gateway's own
refusals (``refuse_functions``) are not recorded either: they are protocol errors, in
the metrics. Reads are never recorded.

Chain. Each line is the canonical JSON of its record (sorted keys, no spaces, UTF-8)
with ``"hash"`` appended last: ``hash = sha256(previous hash + canonical JSON)`` in hex.
Every file (and every restart appending to it) begins with an ``audit_opened`` record
whose ``prev`` names the hash it chains from: ``GENESIS`` for a new log, the last hash
of the file when appending, the previous file's last hash after a reopen (logrotate).
So a changed, removed, inserted or reordered line breaks the chain at that line, and a
file's first line names the file it follows. An ``audit_opened`` record also says
whether it starts its file (``starts_file``: the file was empty when opened) and how
many records the file held before it (``records_before``, counted by the writer): a
file whose first record continues a file had its head cut, and a count that does not
match the lines before it means lines were cut (``Verifier``). The chain has no
secret key: it detects edits by anyone who does not rewrite every later line (see
docs/audit.md).

Nothing here does I/O or reads a clock: times come in as POSIX seconds.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

from . import pdu as fc
from .outcome import Outcome
from .policy import Access, classify

#: The hash a new log chains from.
GENESIS = "0" * 64
#: Values shown in a record at most (registers or coils); ``count`` says how many there were.
MAX_VALUES = 16
#: Bytes of a function's data shown (hex) when its values cannot be read as registers.
MAX_DATA = 32
#: Function codes that only read: skipped before ``classify`` (the hot path's common case).
_PURE_READS = frozenset({0x01, 0x02, 0x03, 0x04, 0x07, 0x0B, 0x0C, 0x11, 0x14, 0x18})
_HASH_KEY = ',"hash":"'

Record = dict[str, Any]


class AuditEvent(StrEnum):
    """What a record is about (its ``event`` field)."""

    REQUEST = "request"  # a request that is not a read
    CONFIG = "config"  # the configuration was loaded or a reload was tried
    CONNECTION_REFUSED = "connection_refused"  # closed by the listener's door (``RefusedAt``)
    OPENED = "audit_opened"  # the gateway opened this file (start, or reopen)
    DROPPED = "records_dropped"  # records lost (queue full, disk full) before this one


class RefusedAt(StrEnum):
    """When a listener's door closed a connection (a ``connection_refused`` record's ``at``)."""

    ACCEPT = "accept"  # at accept, before a byte was read: outside an allow list
    RELOAD = "reload"  # open, and no longer admitted by a reload (allow list, CA, CRL, dates)


class AuditOutcome(StrEnum):
    """What became of an audited request (see the module docstring)."""

    ANSWERED = "answered"
    EXCEPTION = "exception"
    DENIED = "denied"
    UNKNOWN = "unknown"
    BROADCAST = "broadcast"


def is_audited(pdu: bytes) -> bool:
    """True when ``pdu`` is not a read by the policy's own classification."""
    if pdu and pdu[0] in _PURE_READS:
        return False
    return bool(classify(pdu).access & Access.WRITE)


def settle(outcome: str, response: bytes, sent: bool) -> tuple[AuditOutcome, int | None] | None:
    """The audit outcome of a line's answer (``None``: never on the wire, not recorded)."""
    if outcome == Outcome.OK:
        return AuditOutcome.ANSWERED, None
    if outcome == Outcome.SLAVE_EXCEPTION:
        return AuditOutcome.EXCEPTION, response[1] if len(response) > 1 else None
    if outcome == Outcome.BROADCAST:
        return AuditOutcome.BROADCAST, None
    return (AuditOutcome.UNKNOWN, None) if sent else None


def timestamp(now: float) -> str:
    """``now`` (POSIX seconds) as UTC ISO 8601 with milliseconds: ``2026-11-26T16:47:49.123Z``."""
    return datetime.fromtimestamp(now, UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


@dataclass(frozen=True, slots=True)
class Pending:
    """An audited request on its way to a line: all a record needs but the outcome."""

    time: float
    listener: str
    peer: str
    role: str | None
    unit: int
    pdu: bytes
    line: str | tuple[str, ...] | None  #: a broadcast names every line it goes to
    slave: int | None

    def record(
        self, outcome: AuditOutcome, code: int | None = None, reason: str | None = None
    ) -> Record:
        """The record of this request, once its outcome is known."""
        operation = classify(self.pdu)
        line = list(self.line) if isinstance(self.line, tuple) else self.line
        record: Record = {
            "event": AuditEvent.REQUEST.value,
            "time": timestamp(self.time),
            "listener": self.listener,
            "peer": self.peer,
            "role": self.role,
            "unit": self.unit,
            "line": line,
            "slave": self.slave,
            "function": operation.function,
            "function_name": fc.function_name(operation.function),
            "subfunction": operation.subfunction,
            "addresses": [list(span) for span in operation.ranges],
            "outcome": outcome.value,
        }
        record.update(values_of(self.pdu))
        if code is not None:
            record["code"] = code
        if reason is not None:
            record["reason"] = reason
        return record


def _words(data: bytes) -> list[int]:
    return [(data[i] << 8) | data[i + 1] for i in range(0, len(data) - 1, 2)]


def _bits(data: bytes, count: int) -> list[int]:
    return [(data[i // 8] >> (i % 8)) & 1 for i in range(min(count, 8 * len(data)))]


def values_of(pdu: bytes) -> Record:
    """What a write carries, bounded: ``values`` (at most ``MAX_VALUES``) and ``count``;
    ``data`` (hex, at most ``MAX_DATA`` bytes) for functions whose values are not known."""
    function = pdu[0] if pdu else 0
    body = pdu[1:]
    values: list[int]
    if function == fc.WRITE_SINGLE_COIL and len(body) >= 4:
        values = [1 if body[2] == 0xFF else 0]
    elif function == fc.WRITE_SINGLE_REGISTER and len(body) >= 4:
        values = _words(body[2:4])
    elif function in (fc.WRITE_MULTIPLE_COILS, fc.WRITE_MULTIPLE_REGISTERS) and len(body) >= 5:
        count = (body[2] << 8) | body[3]
        data = body[5 : 5 + min(body[4], MAX_VALUES * 2)]
        values = _bits(data, count) if function == fc.WRITE_MULTIPLE_COILS else _words(data)
        return {"values": values[:MAX_VALUES], "count": count}
    elif function == fc.MASK_WRITE_REGISTER and len(body) >= 6:
        values = _words(body[2:6])  # the AND mask, then the OR mask
    elif function == fc.READ_WRITE_MULTIPLE_REGISTERS and len(body) >= 9:
        count = (body[6] << 8) | body[7]
        values = _words(body[9 : 9 + min(body[8], MAX_VALUES * 2)])
        return {"values": values[:MAX_VALUES], "count": count}
    else:
        return {"data": body[:MAX_DATA].hex(), "count": len(body)}
    return {"values": values, "count": len(values)}


def config_record(
    now: float,
    action: str,
    path: str,
    digest: str | None,
    changed: Iterable[str] | None,
    accepted: bool,
    error: str | None = None,
) -> Record:
    """A configuration load (``action`` "load") or reload, accepted or rejected."""
    record: Record = {
        "event": AuditEvent.CONFIG.value,
        "time": timestamp(now),
        "action": action,
        "path": path,
        "sha256": digest,
        "result": "accepted" if accepted else "rejected",
    }
    if changed is not None:
        record["changed"] = sorted(changed)
    if error is not None:
        record["error"] = error[:2000]
    return record


def refused_record(
    now: float,
    listener: str,
    source: str,
    reason: str,
    at: RefusedAt = RefusedAt.ACCEPT,
    peer: str | None = None,
    role: str | None = None,
    subject: str | None = None,
) -> Record:
    """A connection the listener's door closed: at accept (an allow list), or at a reload
    that no longer admits it (``reason``: ``core.connection_admission.NotAdmitted``).
    ``peer``, TLS ``role`` and certificate ``subject`` appear when known."""
    record: Record = {
        "event": AuditEvent.CONNECTION_REFUSED.value,
        "time": timestamp(now),
        "listener": listener,
        "source": source,
        "reason": reason,
        "at": at.value,
    }
    for key, value in (("peer", peer), ("role", role), ("subject", subject)):
        if value is not None:
            record[key] = value
    return record


def opened_record(now: float, prev: str, reason: str) -> Record:
    """The first record the gateway writes to a file it opened (``reason``: start, reopen);
    ``Chain.seal`` sets its ``prev`` to the head it really follows, and the writer adds
    ``starts_file`` and ``records_before`` (what the file held when it was written)."""
    return {
        "event": AuditEvent.OPENED.value,
        "time": timestamp(now),
        "prev": prev,
        "reason": reason,
    }


def dropped_record(now: float, count: int) -> Record:
    """``count`` records were lost since the previous one (queue or disk full)."""
    return {"event": AuditEvent.DROPPED.value, "time": timestamp(now), "count": count}


# --------------------------------------------------------------------------- configuration


def flatten(value: object, prefix: str = "") -> dict[str, str]:
    """Every leaf of a configuration (dataclasses, mappings, sequences) by dotted key, as text;
    items of a sequence that have a ``name`` are keyed by it, others by their index."""
    fields = getattr(value, "__dataclass_fields__", None)
    if fields is not None:
        items: Iterable[tuple[str, object]] = ((k, getattr(value, k)) for k in fields)
    elif isinstance(value, Mapping):
        items = ((str(k), v) for k, v in value.items())
    elif isinstance(value, list | tuple) and value and hasattr(value[0], "__dataclass_fields__"):
        items = ((str(getattr(v, "name", i)), v) for i, v in enumerate(value))
    elif isinstance(value, set | frozenset):  # in a stable order: equal sets, equal text
        return {prefix: repr(sorted(value, key=repr))}
    else:
        return {prefix: repr(value)}
    flat: dict[str, str] = {}
    for key, item in items:
        flat.update(flatten(item, f"{prefix}.{key}" if prefix else key))
    return flat


def changed_keys(old: Mapping[str, str], new: Mapping[str, str]) -> list[str]:
    """The keys whose value differs, appeared or disappeared between two ``flatten``s."""
    return sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))


# --------------------------------------------------------------------------- chain


def canonical(record: Mapping[str, Any]) -> str:
    """The one JSON text of ``record`` the hash covers."""
    return json.dumps(
        record, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    )


def link(previous: str, body: str) -> str:
    """The hash of a record whose canonical JSON is ``body``, after ``previous``."""
    return hashlib.sha256((previous + body).encode()).hexdigest()


@dataclass(slots=True)
class Chain:
    """The running head of a hash chain; ``seal`` turns a record into its line."""

    head: str = GENESIS

    def seal(self, record: Mapping[str, Any]) -> str:
        """The line of ``record`` (with its hash and a newline); the head moves on. An
        ``audit_opened`` record gets the head it follows as its ``prev``."""
        if record.get("event") == AuditEvent.OPENED:
            record = {**record, "prev": self.head}
        body = canonical(record)
        self.head = link(self.head, body)
        return f'{body[:-1]}{_HASH_KEY}{self.head}"}}\n'


def hash_of_line(line: str) -> str | None:
    """The hash a sealed line carries, ``None`` when it carries none."""
    at = line.rfind(_HASH_KEY)
    text = line.rstrip("\r\n")
    if at < 0 or not text.endswith('"}') or len(text) != at + len(_HASH_KEY) + 66:
        return None
    return text[at + len(_HASH_KEY) : -2]


@dataclass(slots=True)
class Verifier:
    """Checks lines one by one (``check``); ``problem`` says what broke, first, and where."""

    head: str | None = None  #: ``None`` until the first line (it must be ``audit_opened``)
    lines: int = 0
    problem: str | None = field(default=None)
    #: Records of the current file before the line checked (a file read alone, or one of
    #: several files concatenated, each starting with ``starts_file``).
    in_file: int = 0

    def start_file(self) -> None:
        """The next line is the first of another file."""
        self.lines = 0
        self.in_file = 0

    def check(self, line: str) -> bool:
        """Check the next line; False (and ``problem`` set) at the first bad one."""
        self.lines += 1
        problem = self._problem(line)
        if problem is not None:
            self.problem = f"line {self.lines}: {problem}"
            return False
        self.in_file += 1
        return True

    def _problem(self, line: str) -> str | None:
        sealed = hash_of_line(line)
        if sealed is None:
            return "not a sealed audit record (no hash at its end)"
        text = line.rstrip("\r\n")
        body = text[: text.rfind(_HASH_KEY)] + "}"
        try:
            record = json.loads(body)
        except ValueError:
            return "not valid JSON"
        if not isinstance(record, dict) or canonical(record) != body:
            return "not in canonical form: the line was edited"
        if record.get("event") == AuditEvent.OPENED:
            cut = self._cut_before(record)
            if cut is not None:
                return cut
            prev = record.get("prev")
            if self.head is not None and prev != self.head:
                return "audit_opened does not follow the line before it (a line was removed?)"
            if self.head is None and isinstance(prev, str):
                self.head = prev
        if self.head is None:
            return "the file does not begin with an audit_opened record (lines removed?)"
        if link(self.head, body) != sealed:
            return "hash mismatch: this line, or one before it, was changed or removed"
        self.head = sealed
        return None

    def _cut_before(self, record: Record) -> str | None:
        """What an ``audit_opened`` record's count shows was cut before it (``None``: nothing;
        records written before the count existed say nothing)."""
        starts, before = record.get("starts_file"), record.get("records_before")
        if starts is True and before == 0:
            self.in_file = 0  # a file of its own (several files concatenated)
            return None
        if starts is not False or not isinstance(before, int):
            return None
        if self.in_file == 0:
            return (
                f"the file's first record continues a file that held {before} records before "
                "it: its head was cut, or check it after the file it continues"
            )
        if before != self.in_file:
            return (
                f"audit_opened counts {before} records before it in its file, but "
                f"{self.in_file} are there: records were cut"
            )
        return None
