"""The audit log's writer: a bounded queue the listeners append to, a thread that writes.

The Modbus path never waits for the file: a listener only appends to a bounded
in-memory queue (``AuditLog.admitted`` / ``AuditTicket.settle``); one writer thread
builds the records, seals them into the hash chain (``core.audit_record``) and
writes them. When the queue is full (a slow file) or a write fails (a full disk),
records are dropped, counted (``audit_records_dropped_total``), logged at most once a
minute, and the next record written is a ``records_dropped`` record with the count, so
the gap shows in the chain. ``reopen`` (SIGHUP) makes the thread close and open the
path again, for logrotate; the new file's first record chains from the old file's last.

Refusals at accept and denied requests go through ``core.audit_repeats`` first (on
the loop, under a lock the writer shares): repeats of one from one source are
counted and written as one record per interval, so a flood costs the file a bounded
number of records a second per source, and the queue is not filled by it. Every
``audit_opened`` record says whether it starts its file and how many records the
file held before it (the writer counts them), so a file cut at its head fails
``audit verify``.
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import stat
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Final

from ..core.admission import Admission, AnswerLocally, Broadcast, Submit
from ..core.audit_record import (
    GENESIS,
    AuditEvent,
    AuditOutcome,
    Chain,
    Pending,
    Record,
    RefusedAt,
    Verifier,
    changed_keys,
    config_record,
    dropped_record,
    flatten,
    hash_of_line,
    is_audited,
    opened_record,
    refused_record,
    settle,
)
from ..core.audit_repeats import Occurrence, Repeats
from ..core.outcome import Outcome

log = logging.getLogger("gateway.audit")

#: Records waiting for the writer at most; more are dropped and counted.
QUEUE_LIMIT: Final = 65536
#: Seconds the writer sleeps between two batches: waking it for each record would cost the
#: loop more than the record itself (a thread switch per write); a burst wakes it sooner.
WRITE_INTERVAL_S: Final = 0.05
#: Records queued that wake the writer before its interval is over.
WAKE_AT: Final = 1024
#: Seconds between two log lines about dropped records.
DROP_LOG_INTERVAL_S: Final = 60.0
#: Bytes read from the end of an existing file to find the hash it ends with.
_TAIL: Final = 65536
STDERR: Final = "-"

Item = Record | tuple[Pending, AuditOutcome, int | None, str | None]
Entry = Item | threading.Event


class AuditOpenError(OSError):
    """The audit log cannot be opened: the message says how to fix it."""


def open_path(path: str) -> int:
    """A descriptor appending to ``path`` (standard error for ``-``); raise with the fix."""
    if path == STDERR:
        return 2
    try:
        return os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o640)
    except OSError as error:
        raise AuditOpenError(
            f"audit.path, --audit-log: cannot open {path!r} for appending: "
            f"{error.strerror or error}; make its directory writable by the gateway's user "
            "(the systemd unit's LogsDirectory= gives /var/log/modbus-gateway), or point "
            "audit.path elsewhere ('-' writes to standard error)"
        ) from error


def last_hash(path: str) -> str:
    """The hash the file at ``path`` ends with (``GENESIS`` when it is new or ends with none)."""
    try:
        if path == STDERR or not stat.S_ISREG(os.stat(path).st_mode):
            return GENESIS  # standard error, a pipe, a device: nothing to read back
        with open(path, "rb") as file:
            size = file.seek(0, os.SEEK_END)
            file.seek(max(0, size - _TAIL))
            tail = file.read().decode("utf-8", "replace").splitlines()
    except OSError:
        return GENESIS
    for line in reversed(tail):
        if line.strip():
            return hash_of_line(line) or GENESIS
    return GENESIS


class AuditTicket:
    """One audited request on its way to a line: ``settle`` it from the reply callback."""

    __slots__ = ("_log", "_pending")

    def __init__(self, audit: AuditLog, pending: Pending) -> None:
        self._log = audit
        self._pending = pending

    def settle(self, sent: bool, response: bytes, outcome: str) -> None:
        """The line answered (or gave up): record it, unless it never reached the wire."""
        settled = settle(outcome, response, sent)
        if settled is not None:
            self._log.put((self._pending, settled[0], settled[1], None))


class AuditLog:
    """The audit log of one gateway: ``open`` it at start, ``close`` it at stop."""

    def __init__(
        self,
        path: str,
        on_drop: Callable[[int], None] | None = None,
        limit: int = QUEUE_LIMIT,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.path = path
        self._on_drop = on_drop
        self._limit = limit
        self._clock = clock
        self._queue: deque[Entry] = deque()
        self._wake = threading.Event()
        self._fd = open_path(path)
        self._chain = Chain(last_hash(path))
        self._queue.append(opened_record(clock(), self._chain.head, "start"))
        self._reopen = False
        self._closing = False
        self._queued_lost = 0  # dropped on the listeners' side (queue full); written by them
        self._lost_seen = 0  # how many of those the writer has accounted for
        self._unreported = 0  # lost records not yet told in a records_dropped record
        self._last_drop_log = -DROP_LOG_INTERVAL_S
        self._config: dict[str, str] | None = None
        #: Repeated refusals and denials, counted (the loop notes, the writer writes tallies).
        self._repeats = Repeats()
        self._repeats_lock = threading.Lock()
        #: Records in the file open now (the writer counts; read at open for an old file).
        self._in_file: int | None = None
        self.written = 0  #: records written (the writer thread counts)
        self._thread = threading.Thread(target=self._run, name="audit-writer", daemon=True)
        self._thread.start()

    # -- the listeners' side (the event loop) -------------------------------------------

    def put(self, entry: Entry) -> None:
        """Queue one record; drop and count it when the queue is full."""
        if len(self._queue) >= self._limit:
            self._queued_lost += 1
            if self._on_drop is not None:
                self._on_drop(1)
        else:
            self._queue.append(entry)
            if len(self._queue) == WAKE_AT:
                self._wake.set()

    def admitted(
        self, listener: str, peer: str, role: str | None, unit: int, pdu: bytes, result: Admission
    ) -> AuditTicket | None:
        """Note an admitted request: a denial is recorded now; a request going to a line
        gets a ticket to settle with its answer. Reads and local refusals: nothing."""
        if not is_audited(pdu):
            return None
        if isinstance(result, AnswerLocally):
            if result.outcome is Outcome.DENIED:
                self._denied(listener, peer, role, unit, pdu, result)
            return None
        if isinstance(result, Submit):
            line: str | tuple[str, ...] = result.target.line
            slave: int | None = result.target.slave
        else:
            assert isinstance(result, Broadcast)
            line, slave = result.lines, 0
        pending = Pending(self._clock(), listener, peer, role, unit, pdu, line, slave)
        return AuditTicket(self, pending)

    def _denied(
        self,
        listener: str,
        peer: str,
        role: str | None,
        unit: int,
        pdu: bytes,
        result: AnswerLocally,
    ) -> None:
        """A denied write: one record, or counted among its repeats from its source."""
        reason = None if result.denied is None else result.denied.value
        code = result.code.value
        pending = Pending(self._clock(), listener, peer, role, unit, pdu, None, None)
        kind = (
            ("listener", listener),
            ("role", role),
            ("outcome", AuditOutcome.DENIED.value),
            ("reason", reason),
            ("code", code),
            ("unit", unit),
            ("function", pdu[0]),
        )
        occurrence = Occurrence(
            source_of(peer), AuditEvent.REQUEST.value, kind, (peer, pdu), pending.time
        )
        self._counted(occurrence, lambda: pending.record(AuditOutcome.DENIED, code, reason))

    def refused(
        self,
        listener: str,
        source: str,
        reason: str,
        at: RefusedAt = RefusedAt.ACCEPT,
        peer: str | None = None,
        role: str | None = None,
        subject: str | None = None,
    ) -> None:
        """A connection closed by the listener's door: at accept (repeats from one source
        counted), or at a reload (once per open connection: always written)."""
        now = self._clock()
        if at is not RefusedAt.ACCEPT:
            self.put(refused_record(now, listener, source, reason, at, peer, role, subject))
            return
        kind = (("listener", listener), ("reason", reason), ("at", at.value))
        occurrence = Occurrence(source, AuditEvent.CONNECTION_REFUSED.value, kind, None, now)
        self._counted(occurrence, lambda: refused_record(now, listener, source, reason, at))

    def _counted(self, occurrence: Occurrence, build: Callable[[], Record]) -> None:
        """Write ``occurrence`` now, or count it among its repeats (``core.audit_repeats``)."""
        with self._repeats_lock:  # the writer takes the tallies under the same lock
            for record in self._repeats.note(occurrence, build):
                self.put(record)

    def configured(
        self, action: str, path: str, config: object | None, error: str | None = None
    ) -> None:
        """A configuration load or reload: accepted (``config``) or rejected (``error``)."""
        digest = _file_digest(path)
        changed = None
        if config is not None:
            flat = flatten(config)
            changed = changed_keys(self._config, flat) if self._config is not None else None
            self._config = flat
        self.put(
            config_record(self._clock(), action, path, digest, changed, config is not None, error)
        )

    def reopen(self) -> None:
        """Close and open the path again at the writer's next turn (logrotate, SIGHUP)."""
        self._reopen = True
        self._wake.set()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until what is queued now is written (or dropped); False on timeout."""
        marker = threading.Event()
        self._queue.append(marker)
        self._wake.set()
        return marker.wait(timeout)

    def close(self, timeout: float = 5.0) -> None:
        """Write what is queued, then stop the writer and close the file."""
        self._closing = True
        self._wake.set()
        self._thread.join(timeout)

    # -- the writer thread ---------------------------------------------------------------

    def _run(self) -> None:
        self._in_file = count_records(self.path)
        while True:
            self._wake.wait(WRITE_INTERVAL_S)
            self._wake.clear()
            closing = self._closing
            self._take_tallies(closing)
            if self._reopen:  # what was queued before the signal goes to the old file
                self._reopen = False
                self._drain()
                self._reopen_file()
            self._drain()
            if closing and not self._queue:
                break
        if self._fd != 2:
            os.close(self._fd)

    def _take_tallies(self, everything: bool) -> None:
        """Queue the tallies of repeats whose interval is over (all of them at the end)."""
        with self._repeats_lock:
            repeats = self._repeats
            records = repeats.flush() if everything else repeats.due(self._clock())
            self._queue.extend(records)  # bounded per source and second: past the limit too

    def _drain(self) -> None:
        queue = self._queue
        while queue:
            batch = [queue.popleft() for _ in range(min(len(queue), 1024))]
            markers = [entry for entry in batch if isinstance(entry, threading.Event)]
            self._write([entry for entry in batch if not isinstance(entry, threading.Event)])
            for marker in markers:
                marker.set()

    def _write(self, batch: list[Item]) -> None:
        now = self._clock()
        lost = self._queued_lost - self._lost_seen
        self._lost_seen += lost
        self._unreported += lost
        if lost:
            self._dropped(lost, "the audit queue is full (the file is slower than the writes)")
        records = [_record(entry) for entry in batch]
        if not records:
            return
        if self._unreported:
            records.insert(0, dropped_record(now, self._unreported))
        head = self._chain.head
        in_file = self._in_file or 0
        for index, record in enumerate(records):
            if record.get("event") == AuditEvent.OPENED:  # says what came before it
                records[index] = {
                    **record,
                    "starts_file": in_file + index == 0,
                    "records_before": in_file + index,
                }
        data = "".join(self._chain.seal(record) for record in records).encode()
        try:
            _write_all(self._fd, data)
        except OSError as error:
            self._chain.head = head  # the chain goes on from the last line written
            self._unreported += len(batch)
            if self._on_drop is not None:
                self._on_drop(len(batch))
            self._dropped(len(batch), f"writing {self.path} failed: {error.strerror or error}")
            return
        self._unreported = 0
        self.written += len(records)
        self._in_file = in_file + len(records)

    def _reopen_file(self) -> None:
        try:
            fd = open_path(self.path)
        except OSError as error:
            log.error("%s; the audit log stays on the file already open", error)
            return
        same = _same_file(self._fd, fd)
        if self._fd != 2:
            os.close(self._fd)
        self._fd = fd
        if not same:  # rotated: a new file (empty, or what someone put there)
            self._in_file = count_records(self.path)
        self._queue.appendleft(opened_record(self._clock(), self._chain.head, "reopen"))
        log.info("audit log %s reopened", self.path)

    def _dropped(self, count: int, why: str) -> None:
        now = time.monotonic()
        if now - self._last_drop_log >= DROP_LOG_INTERVAL_S:
            self._last_drop_log = now
            log.warning("audit log: %d record(s) dropped: %s", count, why)


def source_of(peer: str) -> str:
    """The address in a peer text (``10.0.0.7:50312``, ``[::1]:502``); a device as it is."""
    if peer.startswith("["):
        return peer[1 : peer.find("]")] if "]" in peer else peer
    host, colon, port = peer.rpartition(":")
    return host if colon and port.isdigit() and ":" not in host else peer


def count_records(path: str) -> int:
    """The records (lines) a regular file at ``path`` holds now; 0 for none, or for
    standard error, a pipe or a device, where every start begins a new stream."""
    try:
        if path == STDERR or not stat.S_ISREG(os.stat(path).st_mode):
            return 0
        count = 0
        last = b"\n"
        with open(path, "rb") as file:
            while chunk := file.read(1 << 20):
                count += chunk.count(b"\n")
                last = chunk[-1:]
        return count + (last != b"\n")  # a last line cut short counts too
    except OSError:
        return 0


def _same_file(old: int, new: int) -> bool:
    """True when two descriptors name the same file (a reopen without a rotation)."""
    try:
        before, after = os.fstat(old), os.fstat(new)
    except OSError:
        return False
    return (before.st_dev, before.st_ino) == (after.st_dev, after.st_ino)


def _record(entry: Item) -> Record:
    if isinstance(entry, dict):
        return entry
    pending, outcome, code, reason = entry
    return pending.record(outcome, code, reason)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        written = os.write(fd, view)
        if written == 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        view = view[written:]


def _file_digest(path: str) -> str | None:
    """SHA-256 of the file at ``path`` as it is now; ``None`` when it cannot be read."""
    try:
        with open(path, "rb") as file:
            return hashlib.file_digest(file, "sha256").hexdigest()
    except OSError:
        return None


def start_audit(path: str | None, on_drop: Callable[[int], None]) -> AuditLog | None:
    """The audit log at ``path`` (``None``: none configured); raise ``AuditOpenError``."""
    return None if path is None else AuditLog(path, on_drop)


def note_config(
    audit: AuditLog | None,
    action: str,
    source: str,
    config: object | None,
    error: str | None = None,
) -> None:
    """Record a configuration load or reload when an audit log is configured."""
    if audit is not None:
        audit.configured(action, source, config, None if config is not None else error)


def verify_files(paths: list[str]) -> tuple[bool, str]:
    """Check the hash chain of ``paths``, read in order as one log (rotated files oldest
    first); ``(ok, message)``, the message naming the first bad line."""
    verifier = Verifier()
    for path in paths:
        verifier.start_file()
        try:
            with open(path, encoding="utf-8", errors="replace", newline="") as file:
                for line in file:
                    if not verifier.check(line):
                        return False, f"{path}: {verifier.problem}"
        except OSError as error:
            return False, f"{path}: cannot read: {error.strerror or error}"
        if verifier.lines == 0:
            return False, f"{path}: empty: an audit log begins with an audit_opened record"
    return True, f"{', '.join(paths)}: chain intact, ends with hash {verifier.head}"
