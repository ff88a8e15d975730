"""`modbus-gateway trace --url` attached to a running gateway process; its pcap read by tshark."""

from __future__ import annotations

import json
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway.sim import plc, zl69x
from tests.helpers import DEADLINE_S, RawClient, SimFactory, release, require_tool

READ_10 = bytes.fromhex("03 0000 000A")


class Process:
    """A subprocess whose stderr (and stdout) lines are collected by threads."""

    def __init__(self, *args: str) -> None:
        self.popen = subprocess.Popen(
            [sys.executable, "-m", "gateway", *args], stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        self.out: queue.Queue[str] = queue.Queue()
        self.err: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        self._readers = [
            threading.Thread(target=self._lines, args=(pipe, into), daemon=True)
            for pipe, into in ((self.popen.stdout, self.out), (self.popen.stderr, self.err))
        ]
        for reader in self._readers:
            reader.start()

    @staticmethod
    def _lines(pipe: object, into: queue.Queue[str]) -> None:
        for line in pipe:  # type: ignore[attr-defined]
            into.put(line.rstrip("\n"))

    def wait_for(self, pattern: str, stream: str = "err") -> re.Match[str]:
        lines = self.err if stream == "err" else self.out
        deadline = time.monotonic() + DEADLINE_S
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                line = lines.get(timeout=remaining)
            except queue.Empty:
                break
            self.seen.append(line)
            match = re.search(pattern, line)
            if match:
                return match
        raise AssertionError(f"no line matching {pattern!r} in:\n" + "\n".join(self.seen))

    def stop(self) -> int:
        """SIGTERM if it still runs; close its pipes; the exit code."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
        release(self.popen, *self._readers)
        return self.popen.returncode


@pytest.fixture
def running(make_sim: SimFactory, tmp_path: Path) -> Iterator[tuple[Process, str, tuple[str, int]]]:
    """A gateway process on a simulated line; unit 100 is remapped to slave 2."""
    sim = make_sim({1: plc(1), 2: zl69x(2)})
    config = tmp_path / "gateway.toml"
    config.write_text(
        f'[server]\nlisten = "127.0.0.1:0"\n[metrics]\nlisten = "127.0.0.1:0"\n'
        f'[lines.a]\ndevice = "{sim.path}"\nbaudrate = 115200\nunits = [1, 2]\n'
        '[[routes]]\nunit = 100\nline = "a"\nslave = 2\n'
    )
    gateway = Process("--config", str(config))
    try:
        modbus = gateway.wait_for(r"listening on ([\d.]+):(\d+) \(Modbus TCP\)")
        http = gateway.wait_for(r"metrics on (http://[\d.]+:\d+)/metrics")
        yield gateway, http[1], (modbus[1], int(modbus[2]))
    finally:
        assert gateway.stop() == 0


def test_trace_attaches_to_a_running_gateway(
    running: tuple[Process, str, tuple[str, int]],
) -> None:
    _gateway, url, address = running
    trace = Process("trace", "--url", url, "--unit", "100", "--count", "2")
    try:
        trace.wait_for(r"^tracing http://")
        with RawClient(address) as master:
            master.request(1, READ_10)  # not unit 100: filtered out
            tid = master.send(100, bytes.fromhex("03 0000 0002"))
            master.receive()
        request = trace.wait_for(r"-> ([\d.:]+) tid=(\d+) unit=100 \[line a slave 2\] (.*)$", "out")
        assert int(request[2]) == tid
        assert request[3] == (
            "read_holding_registers(3) address=0 quantity=2  [03 00 00 00 02]"
        )  # fmt: skip
        reply = trace.wait_for(r"<- \S+ tid=\d+ unit=100 \[line a slave 2\] (.*)$", "out")
        assert re.fullmatch(r"read_holding_registers\(3\) byte_count=4 ok \d+\.\d\d ms", reply[1])
        assert trace.popen.wait(DEADLINE_S) == 0  # --count 2: done
    finally:
        trace.stop()


def test_trace_refuses_a_bad_filter_and_an_unreachable_gateway(
    running: tuple[Process, str, tuple[str, int]],
) -> None:
    _gateway, url, _address = running
    bad = Process("trace", "--url", url, "--outcome", "fine")
    assert bad.popen.wait(DEADLINE_S) == 2
    bad.wait_for(r"answered 400: outcome=fine: expected one of")
    bad.stop()
    nobody = Process("trace", "--url", "http://127.0.0.1:1")
    assert nobody.popen.wait(DEADLINE_S) == 1
    nobody.wait_for(r"cannot reach http://127.0.0.1:1")
    nobody.stop()


def test_the_pcap_decodes_as_modbus_tcp_and_modbus_rtu(
    running: tuple[Process, str, tuple[str, int]], tmp_path: Path
) -> None:
    tshark = require_tool("tshark")
    _gateway, url, address = running
    capture = tmp_path / "trace.pcapng"
    trace = Process("trace", "--url", url, "--pcap", str(capture), "--json")
    try:
        trace.wait_for(r"^tracing http://")
        with RawClient(address) as master:
            master.request(100, bytes.fromhex("03 0000 0002"))  # remapped to slave 2
            master.request(1, bytes.fromhex("06 0001 0007"))
            master.request(1, bytes.fromhex("03 2710 0002"))  # the PLC answers 0x02
            master.request(1, bytes.fromhex("03 FFFF 0002"))  # answered by the gateway: 0x02
        for _ in range(8):
            json.loads(trace.wait_for(r"^\{.*\}$", "out")[0])
    finally:
        assert trace.stop() == 0
    trace.wait_for(r"wrote .*trace\.pcapng")
    fields = subprocess.run(
        [tshark, "-r", str(capture), "-T", "fields", "-E", "separator=|",
         "-e", "frame.interface_name", "-e", "frame.protocols", "-e", "tcp.srcport",
         "-e", "tcp.dstport", "-e", "mbtcp.trans_id", "-e", "mbtcp.unit_id",
         "-e", "mbrtu.unit_id", "-e", "modbus.func_code", "-e", "modbus.exception_code",
         "-e", "modbus.regval_uint16", "-e", "_ws.expert.message"],
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout.splitlines()  # fmt: skip
    rows = [line.split("|") for line in fields]
    tcp = [row for row in rows if row[0] == "modbus-tcp"]
    rtu = [row for row in rows if row[0] == "line a"]
    assert len(tcp) == 8 and len(rtu) == 6, fields
    assert all(row[1].endswith("ip:tcp:mbtcp:modbus") for row in tcp), fields
    assert all(row[1] == "exported_pdu:mbrtu:modbus" for row in rtu), fields
    # requests go to port 502, replies come from it; the remapped unit on each side
    assert [(row[3] == "502", row[5], row[7]) for row in tcp] == [
        (True, "100", "3"), (False, "100", "3"), (True, "1", "6"), (False, "1", "6"),
        (True, "1", "3"), (False, "1", "3"), (True, "1", "3"), (False, "1", "3"),
    ]  # fmt: skip
    assert [(row[6], row[7]) for row in rtu] == [
        ("2", "3"), ("2", "3"), ("1", "6"), ("1", "6"), ("1", "3"), ("1", "3"),
    ]  # fmt: skip
    assert tcp[5][8] == "2" and rtu[5][8] == "2"  # the slave's exception, on both sides
    assert tcp[7][8] == "2"  # the gateway's own answer: nothing on the line
    assert rtu[1][9] == tcp[1][9] != ""  # the registers read, decoded on both sides
    assert not [row for row in rows if row[10]], fields  # no malformed or TCP analysis warnings
