"""Floods of refusals and denials over loopback: the audit log records events, not floods.

A host outside a listener's allow list (127.0.0.2) connects as fast as it can, and a
master on a read-only listener (127.0.0.3) pipelines writes to 30 units with four
write functions, each for ``ATTACK_S``. Meanwhile an honest master writes through an
open listener. The file then holds every honest write as its own record, at most 50
records a second from each flooding source (most of its events counted in
``repeats``), and the ``repeats`` add up to what the source did.
"""

from __future__ import annotations

import json
import socket
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from gateway.io.audit import verify_files
from gateway.sim import plc
from tests.helpers import DEADLINE_S, GatewayFactory, RawClient, RunningGateway, SimFactory, mbap
from tests.integration.test_hostile import connect_from

#: How long each flood runs at most, and how many events it may cause at most.
ATTACK_S = 1.5
MAX_EVENTS = 60_000
FENCED_HOST, READ_ONLY_HOST = "127.0.0.2", "127.0.0.3"
#: Records a second one source may cause at most.
RECORDS_PER_SOURCE_S = 50


@dataclass
class Flooded:
    gateway: RunningGateway
    path: Path

    def records(self) -> list[dict[str, Any]]:
        audit = self.gateway.gateway.audit
        assert audit is not None and audit.flush(DEADLINE_S)
        return [json.loads(line) for line in self.path.read_text().splitlines()]

    def address(self, listener: str) -> tuple[str, int]:
        return self.gateway.gateway.listener_address(listener)


@pytest.fixture
def flooded(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> Iterator[Flooded]:
    sim = make_sim({1: plc(1)})
    path = tmp_path / "audit.jsonl"
    listeners = [
        {"name": "open", "protocol": "tcp", "listen": "127.0.0.1:0"},
        {"name": "ro", "protocol": "tcp", "listen": "127.0.0.1:0", "read_only": True},
        {"name": "fenced", "protocol": "tcp", "listen": "127.0.0.1:0", "allow": ["127.0.0.1/32"]},
    ]  # fmt: skip
    gateway = make_gateway({
        "lines": {"a": sim.line_table(["1-30"], timeout=1.0, retries=0)},
        "listeners": listeners,
        "audit": {"path": str(path)},
    })  # fmt: skip
    yield Flooded(gateway, path)


def from_source(records: list[dict[str, Any]], source: str) -> list[dict[str, Any]]:
    """The records a source caused: by ``source``, or by the address in ``peer``."""
    return [
        r for r in records
        if r.get("source") == source or str(r.get("peer", "")).startswith(source + ":")
    ]  # fmt: skip


def rates(records: list[dict[str, Any]], seconds: float) -> tuple[float, int]:
    """Records a second over the attack, and the most in any one second of their times."""
    per_second = Counter(r["time"][:19] for r in records)
    return len(records) / seconds, max(per_second.values(), default=0)


def honest_writes(flooded: Flooded, count: int) -> None:
    with RawClient(flooded.address("open")) as master:
        for n in range(count):
            assert master.request(1, bytes((6, 0, 1, 0, n))) == bytes((6, 0, 1, 0, n))


def assert_bounded(flooded: Flooded, event: str, source: str, events: int, seconds: float) -> None:
    """Every event counted once, at most ``RECORDS_PER_SOURCE_S`` records a second."""
    deadline = time.monotonic() + DEADLINE_S
    while True:  # the last interval's tallies are written once it is over (1 s)
        records = flooded.records()
        mine = [r for r in from_source(records, source) if r["event"] == event]
        counted = sum(r.get("repeats", 1) for r in mine)
        if counted >= events or time.monotonic() > deadline:
            break
    average, worst = rates(mine, seconds)
    figures = (
        f"{events} events in {seconds:.2f} s: {len(mine)} records, {average:.0f}/s, "
        f"worst second {worst}"
    )
    print(f"\n{event} flood from {source}: {figures}")
    assert counted == events, figures  # nothing lost, nothing counted twice
    assert average <= RECORDS_PER_SOURCE_S and worst <= RECORDS_PER_SOURCE_S, figures
    honest = [r for r in records if r["event"] == "request" and r["outcome"] == "answered"]
    assert len(honest) == 5 and not any("repeats" in r for r in honest)  # never aggregated
    assert verify_files([str(flooded.path)])[0]


def test_a_host_outside_the_allow_list_adds_a_bounded_number_of_records(
    flooded: Flooded,
) -> None:
    address = flooded.address("fenced")
    honest_writes(flooded, 3)
    connects = 0
    started = time.monotonic()
    while time.monotonic() - started < ATTACK_S and connects < MAX_EVENTS:
        try:
            sock = connect_from(FENCED_HOST, address)
        except OSError:
            continue
        sock.close()
        connects += 1
    seconds = time.monotonic() - started
    honest_writes(flooded, 2)
    assert connects > 200
    assert_bounded(flooded, "connection_refused", FENCED_HOST, connects, seconds)


def test_a_read_only_master_sending_writes_adds_a_bounded_number_of_records(
    flooded: Flooded,
) -> None:
    honest_writes(flooded, 3)
    writes = [
        mbap(n, 1 + n % 30, pdu)
        for n, pdu in enumerate(
            [bytes.fromhex("05 0001 FF00"), bytes.fromhex("06 0001 0007"),
             bytes.fromhex("0F 0001 0001 01 01"), bytes.fromhex("10 0001 0001 02 0007")] * 30
        )
    ]  # fmt: skip
    batch = 16  # max_pipeline: every request in flight at once
    sent = 0
    with socket.create_connection(flooded.address("ro"), DEADLINE_S,
                                  source_address=(READ_ONLY_HOST, 0)) as sock:  # fmt: skip
        stream = sock.makefile("rb")
        started = time.monotonic()
        while time.monotonic() - started < ATTACK_S and sent < MAX_EVENTS:
            chunk = [writes[(sent + n) % len(writes)] for n in range(batch)]
            sock.sendall(b"".join(chunk))
            for _ in chunk:
                header = stream.read(7)
                body = stream.read(int.from_bytes(header[4:6]) - 1)
                assert body[1:] == b"\x01", body  # denied: 0x01, never sent
            sent += batch
        seconds = time.monotonic() - started
    honest_writes(flooded, 2)
    assert sent > 1000
    assert_bounded(flooded, "request", READ_ONLY_HOST, sent, seconds)


def test_a_file_cut_at_its_head_fails_verify(flooded: Flooded) -> None:
    honest_writes(flooded, 3)
    audit = flooded.gateway.gateway.audit
    assert audit is not None
    audit.reopen()  # SIGHUP without a rotation: the same file goes on
    honest_writes(flooded, 2)
    assert audit.flush(DEADLINE_S)  # the writer's thread may not have written them yet
    lines = flooded.path.read_text().splitlines(keepends=True)
    assert verify_files([str(flooded.path)])[0]
    reopen = next(n for n, line in enumerate(lines) if '"reason":"reopen"' in line)
    opened = json.loads(lines[reopen])
    assert (opened["starts_file"], opened["records_before"]) == (False, reopen)
    assert json.loads(lines[0])["starts_file"] is True
    cut = flooded.path.with_name("cut.jsonl")
    cut.write_text("".join(lines[reopen:]))  # the head cut up to the reopen
    ok, message = verify_files([str(cut)])
    print(f"\naudit verify on the head-cut file: {message}")
    assert not ok and "intact" not in message, message
    assert "first record continues a file" in message
