"""The audit writer against files that fail: a full disk (/dev/full) and a slow reader (a
FIFO nobody drains). Records are dropped and counted, never waited for, and the gap shows
in the chain as a ``records_dropped`` record."""

from __future__ import annotations

import json
import logging
import os
import select
import time
from pathlib import Path

import pytest

from gateway.core.audit_record import refused_record
from gateway.io.audit import AuditLog
from tests.helpers import DEADLINE_S

T0 = 1_800_000_000.0


def test_a_full_disk_drops_and_counts_and_logs_once(caplog: pytest.LogCaptureFixture) -> None:
    dropped: list[int] = []
    audit = AuditLog("/dev/full", dropped.append)
    with caplog.at_level(logging.WARNING, logger="gateway.audit"):
        for n in range(3):
            audit.put(refused_record(T0, "tcp", f"10.0.0.{n}", "source_not_allowed"))
            assert audit.flush(DEADLINE_S)
    audit.close()
    assert sum(dropped) == 4  # the audit_opened record and three more
    warnings = [r.getMessage() for r in caplog.records if r.name == "gateway.audit"]
    assert len(warnings) == 1 and "No space left on device" in warnings[0], warnings


def test_a_slow_file_never_blocks_the_caller_and_the_gap_is_recorded(tmp_path: Path) -> None:
    fifo = tmp_path / "audit.fifo"
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    dropped: list[int] = []
    audit = AuditLog(str(fifo), dropped.append, limit=100)
    try:
        started = time.monotonic()
        for n in range(5000):  # far more than the pipe holds: the writer blocks
            audit.put(refused_record(T0, "tcp", f"10.0.{n // 256}.{n % 256}", "x"))
        assert time.monotonic() - started < 1.0  # the caller never waited for the file
        assert sum(dropped) > 0
        data = b""
        while b"records_dropped" not in data:  # drain the pipe: the writer goes on
            readable, _, _ = select.select([reader], [], [], DEADLINE_S)
            assert readable, "the writer never wrote again"
            data += os.read(reader, 1 << 16)
            if b"records_dropped" not in data:
                audit.put(refused_record(T0, "tcp", "10.1.1.1", "x"))
    finally:
        audit.close(timeout=0.1)
        os.close(reader)
    lines = data.decode().splitlines()
    gap = next(json.loads(line) for line in lines if '"records_dropped"' in line)
    assert 0 < gap["count"] <= sum(dropped)  # told at the first record written after them
