"""The simulator as a Modbus TCP slave, and the R6 robot controller profile (reference 003).

Requests are the reference's own MBAP examples, byte for byte, over real TCP on
loopback; pymodbus is an independent master (its own MBAP and its own 32/64-bit
decoding). The document prints two of its examples one byte short; the tests
follow the document's rules there and say which byte it dropped.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import ssl
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gateway.sim import SimulatedTcpSlave, r6
from gateway.sim.pki import make_pki
from gateway.sim.profiles import (
    R6_AXES,
    R6_AXIS_POSITIONS,
    R6_COUNTER_START,
    R6_COUNTER_VALUES,
    R6_CYCLE_COUNT,
    R6_CYCLES,
    R6_GLOBAL_SPEED,
    R6_RUN_TIME,
    R6_WORLD,
    R6_WORLD_POSITION,
    plc,
    zl69x,
)
from tests.helpers import DEADLINE_S, RawClient, h, mbap

REPO = Path(__file__).resolve().parents[2]


VERSION_TEXT = (
    "41 4d 38 2d 51 43 2d 52 58 45 2d 37 2e 38 2e 30 32 2d 62 61 74 65 37 5f 46 41 4b "
    "45 5f 54 47 46 5f 45 4e 43 4f 44 45 52 00"
)

#: (request, response) exactly as reference 003 prints them, or as its rules make them.
R6_EXAMPLES = [
    # 3.1.1 version number length: 0x29 bytes
    ("00 00 00 00 00 06 01 03 00 00 00 01", "00 00 00 00 00 05 01 03 02 00 29"),
    # 3.1.2 version number: 21 registers. The document prints 41 data bytes under a byte
    # count of 0x2a and an MBAP length of 0x2c; its own rule (an odd length's last
    # register has its low byte filled with 0) gives the 42nd byte, and length 0x2d.
    ("00 00 00 00 00 06 01 03 00 01 00 15", f"00 00 00 00 00 2d 01 03 2a {VERSION_TEXT} 00"),
    # 3.1.3 number of counters: 2
    ("00 00 00 00 00 06 01 03 00 82 00 01", "00 00 00 00 00 05 01 03 02 00 02"),
    # 3.1.3 counter list from counter 0: ids 0 and 1, high word first. The document prints
    # seven data bytes under a byte count of 8 and MBAP length 0x0b: one 00 dropped.
    ("00 00 00 00 00 06 01 03 00 83 00 04", "00 00 00 00 00 0b 01 03 08 00 00 00 00 00 00 00 01"),
    # 3.1.3 example 2, from counter 1: id 1, then a slot past the last counter (0xFF filled)
    ("00 00 00 00 00 06 01 03 00 85 00 04", "00 00 00 00 00 0b 01 03 08 00 00 00 01 ff ff ff ff"),
    # 2 (4) the request APU example: transaction id 0x1501, unit id 0xFF, register 5 ("XE")
    ("15 01 00 00 00 06 ff 03 00 05 00 01", "15 01 00 00 00 05 ff 03 02 58 45"),
]


@pytest.fixture
def r6_slave() -> Iterator[SimulatedTcpSlave]:
    with SimulatedTcpSlave({1: r6(1)}) as slave:
        yield slave


def _read(sock: socket.socket, count: int) -> bytes:
    data = bytearray()
    while len(data) < count:
        chunk = sock.recv(count - len(data))
        if not chunk:
            raise AssertionError(f"closed after {bytes(data).hex(' ')}")
        data += chunk
    return bytes(data)


def _connect(slave: SimulatedTcpSlave) -> socket.socket:
    sock = socket.create_connection(slave.address, timeout=DEADLINE_S)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


@pytest.mark.parametrize(("request_hex", "response_hex"), R6_EXAMPLES)
def test_the_reference_examples_are_answered_byte_for_byte(
    r6_slave: SimulatedTcpSlave, request_hex: str, response_hex: str
) -> None:
    expected = h(response_hex)
    with _connect(r6_slave) as sock:
        sock.sendall(h(request_hex))
        assert _read(sock, len(expected)) == expected


def test_the_version_string_reads_as_the_document_says(r6_slave: SimulatedTcpSlave) -> None:
    with RawClient(r6_slave.address) as client:
        length = int.from_bytes(client.request(1, h("03 0000 0001"))[2:], "big")
        registers = (length + 1) // 2  # the document's rule
        data = client.request(1, h("03 0001") + registers.to_bytes(2, "big"))[2:]
    assert data[:length].rstrip(b"\x00").decode() == "AM8-QC-RXE-7.8.02-bate7_FAKE_TGF_ENCODER"


@pytest.mark.parametrize("chunk", [1, 5, 1000])
def test_pipelined_requests_are_all_answered_in_order_whatever_the_chunking(
    r6_slave: SimulatedTcpSlave, chunk: int
) -> None:
    """Several requests in flight on one connection, sent as one stream in any segments."""
    stream = b"".join(h(request) for request, _ in R6_EXAMPLES) * 3
    expected = b"".join(h(response) for _, response in R6_EXAMPLES) * 3
    with _connect(r6_slave) as sock:
        for start in range(0, len(stream), chunk):
            sock.sendall(stream[start : start + chunk])
        assert _read(sock, len(expected)) == expected
    assert r6_slave.stats().max_in_flight >= (2 if chunk == 1000 else 1)


def test_unit_ids_01_and_ff_reach_the_same_controller_and_others_get_0x0b(
    r6_slave: SimulatedTcpSlave,
) -> None:
    with RawClient(r6_slave.address) as client:
        speed = R6_GLOBAL_SPEED.to_bytes(2, "big")
        assert client.request(0xFF, h("06") + speed + h("0023")) == h("06") + speed + h("0023")
        assert client.request(0x01, h("03") + speed + h("0001")) == h("03 02 00 23")
        assert client.request(0x02, h("03") + speed + h("0001")) == h("83 0b")
        assert client.request(0x00, h("03 0000 0001")) == h("83 0b")
    assert r6_slave.stats().unknown_units == 2


def test_the_r6_refuses_what_it_does_not_do(r6_slave: SimulatedTcpSlave) -> None:
    with RawClient(r6_slave.address) as client:
        assert client.request(1, h("02 0000 0001")) == h("82 01")  # no discrete inputs
        assert client.request(1, h("03 0883 0001")) == h("83 02")  # hole in the map
        assert client.request(1, h("06 0000 0001")) == h("86 04")  # version is read-only
        assert client.request(1, h("04 0082 0001")) == h("04 02 00 02")  # FC 4: same table


def test_a_bad_header_closes_the_connection_and_others_keep_working(
    r6_slave: SimulatedTcpSlave,
) -> None:
    with RawClient(r6_slave.address) as bad, RawClient(r6_slave.address) as good:
        bad.send_raw(mbap(1, 1, h("03 0000 0001"), protocol_id=7))
        assert bad.is_closed_by_peer()
        assert good.request(1, h("03 0000 0001")) == h("03 02 00 29")
    assert r6_slave.stats().bad_headers == 1


def test_a_slow_unit_is_overtaken_by_a_quick_one_on_the_same_connection() -> None:
    """reply_delay holds a unit's answers back: answers leave out of order, each with its tid."""
    with SimulatedTcpSlave({1: plc(1), 2: zl69x(2)}) as slave:
        slave.faults(1).reply_delay = 0.2
        with RawClient(slave.address) as client:
            client.send(1, h("03 0000 0002"), tid=0x0101)
            client.send(2, h("03 0000 0001"), tid=0x0202)
            first, second = client.receive(), client.receive()
        assert (first.transaction_id, first.unit, first.pdu) == (0x0202, 2, h("03 02 01 13"))
        assert (second.transaction_id, second.unit, second.pdu) == (0x0101, 1, h("03 04 0000 0002"))
        assert slave.stats().max_in_flight == 2
        assert 0xFF not in slave.units  # two devices: no direct-addressing alias


def test_a_silent_unit_never_answers_but_the_connection_stays() -> None:
    with SimulatedTcpSlave({1: plc(1), 2: zl69x(2)}) as slave:
        slave.faults(1).silent = True
        with RawClient(slave.address) as client:
            client.send(1, h("03 0000 0001"), tid=1)
            assert client.request(2, h("03 0000 0001"), tid=2) == h("03 02 01 13")
        assert slave.stats().silent_drops == 1


def test_pymodbus_as_an_independent_master_decodes_32_and_64_bit_values_high_word_first(
    r6_slave: SimulatedTcpSlave,
) -> None:
    from pymodbus.client import ModbusTcpClient

    host, port = r6_slave.address
    client: Any = ModbusTcpClient(host, port=port, timeout=5, retries=0)  # partly untyped
    assert client.connect()
    try:
        int32, uint64, int64 = (client.DATATYPE.INT32, client.DATATYPE.UINT64,
                                client.DATATYPE.INT64)  # fmt: skip

        def values(device_id: int, address: int, count: int, kind: Any, width: int) -> list[Any]:
            reply = client.read_holding_registers(address, count=count, device_id=device_id)
            assert not reply.isError(), reply
            regs = reply.registers
            return [
                client.convert_from_registers(regs[i : i + width], kind, word_order="big")
                for i in range(0, count, width)
            ]

        assert values(1, R6_AXIS_POSITIONS, 12, int32, 2) == list(R6_AXES)
        assert values(0xFF, R6_WORLD_POSITION, 12, int32, 2) == list(R6_WORLD)
        assert values(1, R6_CYCLE_COUNT, 8, uint64, 4) == [R6_CYCLES, R6_RUN_TIME]
        assert values(1, R6_COUNTER_VALUES, 8, int64, 4) == list(R6_COUNTER_START)
        # A 64-bit counter written with FC 16 reads back; FC 4 reads the same table.
        words = client.convert_to_registers(-5_000_000_000, int64, word_order="big")
        assert not client.write_registers(R6_COUNTER_VALUES, words, device_id=1).isError()
        reply = client.read_input_registers(R6_COUNTER_VALUES, count=4, device_id=0xFF)
        assert client.convert_from_registers(reply.registers, int64) == -5_000_000_000
        # IO outputs: FC 5 then FC 1
        assert not client.write_coil(5, True, device_id=1).isError()
        bits = client.read_coils(0, count=8, device_id=1).bits[:8]
        assert bits == [True, False, False, True, False, True, False, False]
    finally:
        client.close()


def test_a_tls_context_serves_modbus_tcp_security_on_the_same_code(tmp_path: Path) -> None:
    """The ``ssl`` hook: the same slave behind TLS, spoken to by a verifying client."""
    pki = make_pki(tmp_path)
    server_context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    server_context.load_cert_chain(pki.server_chain, pki.server_key)
    client_context = ssl.create_default_context(cafile=str(pki.ca))
    client_context.check_hostname = False
    with SimulatedTcpSlave({1: r6(1)}, ssl=server_context) as slave:
        raw = socket.create_connection(slave.address, timeout=DEADLINE_S)
        with client_context.wrap_socket(raw) as sock:
            request, response = R6_EXAMPLES[0]
            sock.sendall(h(request))
            assert _read(sock, 11) == h(response)


def test_many_connections_at_once_each_get_their_own_answers(r6_slave: SimulatedTcpSlave) -> None:
    failures: list[str] = []

    def master(index: int) -> None:
        try:
            with RawClient(r6_slave.address) as client:
                for n in range(50):
                    tid = (index << 8) | n
                    assert client.request(1, h("03 0082 0001"), tid=tid) == h("03 02 00 02")
        except AssertionError as error:  # pragma: no cover - reported below
            failures.append(str(error))

    threads = [threading.Thread(target=master, args=(i,)) for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(DEADLINE_S)
    assert failures == []
    assert r6_slave.stats().connections == 8


def test_python_m_gateway_sim_serves_the_r6_over_modbus_tcp() -> None:
    process = subprocess.Popen(
        [sys.executable, "-m", "gateway.sim", "--modbus-tcp-listen", "127.0.0.1:0",
         "--profile", "r6"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    try:
        assert process.stdout is not None
        ready = process.stdout.readline().split()
        assert ready[0] == "READY", ready
        host, _, port = ready[1].rpartition(":")
        with RawClient((host, int(port))) as client:
            assert client.request(0xFF, h("03 0000 0001")) == h("03 02 00 29")
        process.send_signal(signal.SIGTERM)
        out, _ = process.communicate(timeout=DEADLINE_S)
        assert process.returncode == 0
        assert json.loads(out.strip().splitlines()[-1])["responses"] == 1
    finally:
        with process:  # closes its pipes and waits
            if process.poll() is None:
                process.kill()


def test_python_m_gateway_sim_refuses_serial_flags_with_modbus_tcp() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "gateway.sim", "--modbus-tcp-listen", "127.0.0.1:0",
         "--profile", "r6", "--baudrate", "9600"],
        cwd=REPO, capture_output=True, text=True, timeout=DEADLINE_S, check=False,
    )  # fmt: skip
    assert done.returncode == 2
    assert "--baudrate is for pty lines, not --modbus-tcp-listen" in done.stderr


def test_the_gateway_reaches_the_simulator_over_modbus_tcp_security(tmp_path: Path) -> None:
    """``python -m gateway.sim --tls-*`` as the TLS slave of a real ``--modbus-tls`` line."""
    pki = make_pki(tmp_path)
    cert, key = pki.client("operator")
    sim = subprocess.Popen(
        [sys.executable, "-m", "gateway.sim", "--modbus-tcp-listen", "127.0.0.1:0",
         "--profile", "r6", "--tls-cert", str(pki.server_chain), "--tls-key",
         str(pki.server_key), "--tls-ca", str(pki.ca)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    gateway: subprocess.Popen[str] | None = None
    try:
        assert sim.stdout is not None
        ready = sim.stdout.readline().split()
        assert ready[0] == "READY", ready
        # A client without a certificate is refused by the simulator (mutual authentication).
        anonymous = ssl.create_default_context(cafile=str(pki.ca))
        with socket.create_connection(_split(ready[1]), timeout=DEADLINE_S) as raw:
            try:  # TLS 1.3: the refusal may come after the client's handshake ends
                with anonymous.wrap_socket(raw, server_hostname="127.0.0.1") as sock:
                    sock.sendall(h(R6_EXAMPLES[0][0]))
                    answer = sock.recv(100)
            except (ssl.SSLError, ConnectionError):
                answer = b""
            assert answer == b""
        gateway = subprocess.Popen(
            [sys.executable, "-m", "gateway", "--modbus-tls", ready[1], "--modbus-tls-cert",
             cert, "--modbus-tls-key", key, "--modbus-tls-ca", str(pki.ca),
             "--listen", "127.0.0.1:0", "--metrics", "off"],
            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert gateway.stderr is not None
        listen: tuple[str, int] | None = None
        for line in gateway.stderr:
            if "listening on" in line:
                listen = _split(line.split("listening on ")[1].split()[0])
            if "connected to" in line:
                break
        assert listen is not None
        with RawClient(listen) as client:
            assert client.request(1, h("03 0000 0001")) == h("03 02 00 29")
            assert client.request(1, h("03 0082 0001")) == h("03 02 00 02")
    finally:
        for process in (gateway, sim):
            if process is None:
                continue
            with process:  # closes its pipes and waits
                if process.poll() is None:
                    process.kill()


def _split(address: str) -> tuple[str, int]:
    host, _, port = address.rpartition(":")
    return host, int(port)
