"""The audit log over loopback: a write through every listener kind is recorded once.

A gateway in front of one simulated RTU line (PLCs at 1 and 2; unit 3 is routed
but nobody answers there) listens as Modbus TCP, Modbus/TCP Security (a client
certificate with the role ``operator``), RTU over TCP, a read-only Modbus TCP
listener and a serial slave on a real pty, with ``[audit] path`` set. Real
masters write and read through each; the file then holds exactly one record per
write, none for the reads, the denial as ``denied``, the write to the silent
slave as ``unknown``, a reload with its changed keys, and the chain verifies.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from gateway.config import build_config
from gateway.io.audit import verify_files
from gateway.sim import open_pty_pair, plc
from gateway.sim.pki import Pki
from tests.helpers import DEADLINE_S, GatewayFactory, RunningGateway, SimFactory, h
from tests.integration.test_admission_matrix import (
    Master,
    RtuOverWire,
    masters_by_listener,
    tcp_master,
)

BAUD = 19200


@dataclass
class Audited:
    gateway: RunningGateway
    path: Path
    masters: dict[str, Master]
    raw: dict[str, Any]

    def records(self) -> list[dict[str, Any]]:
        """Every record written so far (after the writer caught up)."""
        audit = self.gateway.gateway.audit
        assert audit is not None and audit.flush(DEADLINE_S)
        return [json.loads(line) for line in self.path.read_text().splitlines()]

    def requests(self) -> list[dict[str, Any]]:
        return [r for r in self.records() if r["event"] == "request"]


@pytest.fixture
def audited(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki, tmp_path: Path
) -> Iterator[Audited]:
    sim = make_sim({1: plc(1), 2: plc(2)})
    pair = open_pty_pair()
    path = tmp_path / "audit.jsonl"
    listeners = [
        {"name": "tls", "protocol": "tls", "listen": "127.0.0.1:0", "ca": str(pki.ca),
         "cert": str(pki.server_chain), "key": str(pki.server_key)},
        {"name": "rtu", "protocol": "rtu-over-tcp", "listen": "127.0.0.1:0"},
        {"name": "ro", "protocol": "tcp", "listen": "127.0.0.1:0", "read_only": True},
        {"name": "fenced", "protocol": "tcp", "listen": "127.0.0.1:0", "allow": ["10.0.0.0/8"]},
        {"name": "field", "protocol": "serial-slave", "device": pair.path, "baudrate": BAUD},
    ]  # fmt: skip
    raw: dict[str, Any] = {
        "lines": {"a": sim.line_table([1, 2, 3], timeout=0.05, retries=0)},
        "listeners": listeners,
        "audit": {"path": str(path)},
    }
    gateway = make_gateway(raw)
    masters = masters_by_listener(gateway, pair, pki)
    masters["ro"] = tcp_master(gateway.gateway.listener_address("ro"))
    yield Audited(gateway, path, masters, raw)
    for master in masters.values():
        master.close()
    pair.close()


def exchange(master: Master, unit: int, pdu: bytes, answer: bytes) -> bytes | None:
    if isinstance(master, RtuOverWire):
        master.expected = answer
    return master.exchange(unit, pdu, False)


def test_a_write_through_each_listener_is_recorded_once(audited: Audited) -> None:
    write_value = {"tcp": 0x0101, "tls": 0x0202, "rtu": 0x0303, "field": 0x0404}
    for name, value in write_value.items():
        master = audited.masters[name]
        write = h("06 0005") + value.to_bytes(2)
        assert exchange(master, 1, write, write) == write, name
        read = h("03 0005 0001")
        assert exchange(master, 1, read, h("03 02") + value.to_bytes(2)), name
    records = audited.requests()
    assert len(records) == len(write_value), records  # the reads left no record
    for record, (name, value) in zip(records, write_value.items(), strict=True):
        assert record["listener"] == name
        assert (record["unit"], record["line"], record["slave"]) == (1, "a", 1)
        assert (record["function"], record["subfunction"]) == (6, None)
        assert record["addresses"] == [[5, 5]]
        assert (record["values"], record["count"]) == ([value], 1)
        assert record["outcome"] == "answered" and "code" not in record
        assert record["role"] == ("operator" if name == "tls" else None)
    assert records[0]["peer"].startswith("127.0.0.1:")
    assert records[3]["peer"] == audited.raw["listeners"][4]["device"]
    ok, message = verify_files([str(audited.path)])
    assert ok, message


def test_denied_exception_and_silent_slave(audited: Audited) -> None:
    masters = audited.masters
    write = h("10 0000 0002 04 0001 0002")
    assert exchange(masters["ro"], 1, write, b"") == h("90 01")  # read-only: denied
    assert exchange(masters["ro"], 1, h("03 0000 0001"), b"") == h("03 02 0000")
    assert exchange(masters["tcp"], 3, write, b"") == h("90 0B")  # nobody answers at 3
    assert exchange(masters["tcp"], 2, h("06 FFFF 0001"), b"") == h("86 02")  # the PLC refuses
    assert exchange(masters["tcp"], 1, h("08 0001 0000"), h("08 0001 0000"))  # restart comms
    denied, unknown, exception, diagnostics = audited.requests()
    assert (denied["listener"], denied["outcome"], denied["code"]) == ("ro", "denied", 1)
    assert denied["reason"] == "read_only" and denied["line"] is None
    assert denied["values"] == [1, 2] and denied["addresses"] == [[0, 1]]
    assert (unknown["slave"], unknown["outcome"]) == (3, "unknown")
    assert (exception["outcome"], exception["code"]) == ("exception", 2)
    assert (diagnostics["function"], diagnostics["subfunction"]) == (8, 1)
    ok, message = verify_files([str(audited.path)])
    assert ok, message


def test_a_reload_is_recorded_with_the_keys_it_changed(audited: Audited) -> None:
    raw = dict(audited.raw)
    raw["server"] = {"listen": "127.0.0.1:0", "max_pipeline": 4}
    raw["metrics"] = {"listen": "127.0.0.1:0"}
    gateway = audited.gateway
    gateway.run(gateway.gateway.reload(build_config(raw, "<test>")))
    configs = [r for r in audited.records() if r["event"] == "config"]
    assert [(c["action"], c["result"]) for c in configs] == [
        ("load", "accepted"),
        ("reload", "accepted"),
    ]
    assert configs[1]["changed"] == ["server.max_pipeline"]
    assert configs[0]["sha256"] is None  # no file behind "<test>": the CLI test has one


def test_a_connection_refused_by_an_allow_list_is_recorded(audited: Audited) -> None:
    address = audited.gateway.gateway.listener_address("fenced")
    with socket.create_connection(address, timeout=DEADLINE_S) as sock:
        assert sock.recv(1) == b""  # closed at accept
    refused = [r for r in audited.records() if r["event"] == "connection_refused"]
    assert [(r["listener"], r["source"], r["reason"]) for r in refused] == [
        ("fenced", "127.0.0.1", "source_not_allowed")
    ]
