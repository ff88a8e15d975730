"""One request matrix through every listener kind: the same admission on every path.

A gateway in front of one simulated RTU line (a PLC at 1 and one at 2, also
reachable as the aliases 11 and 12) listens as Modbus TCP, Modbus/TCP Security
(TLS, a client certificate from the test PKI), RTU over TCP and a serial slave
(a real pty: the test is the RTU master on the other end). Each request of the
matrix (reads, writes, FC 8 echo, restart and force-listen-only, FC 43, a user
function code, a refused function, broadcasts, aliases, unrouted units, an
invalid request) is sent through each listener, with and without rules. What
reached the line (every request the simulated slaves executed) must be the
same through every listener, and so must the answers, but for the documented
silences: RTU masters never get an answer to a broadcast, and the serial slave
stays silent for units it does not stand for, as an absent slave would.
"""

from __future__ import annotations

import os
import select
import socket
import ssl
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import pytest

from gateway.core.crc import append_crc, check_crc
from gateway.sim import PtyPair, open_pty_pair, plc
from gateway.sim.device import SimulatedDevice
from gateway.sim.pki import Pki
from tests.helpers import (
    DEADLINE_S,
    GatewayFactory,
    RunningGateway,
    SimFactory,
    client_context,
    h,
    mbap,
)

BAUD = 19200
#: Long beside t3.5 and the simulated line's answer: nothing coming within it is a silence.
QUIET_S = 0.15
MARKER = bytes.fromhex("03 0001 0001")  # a read of unit 1 after each request: the line is done
MARKER_ANSWER = bytes.fromhex("03 02 0002")

Traffic = list[tuple[int, bytes, bool]]  # (slave address, PDU, broadcast) as the slaves saw it


class Recorder(SimulatedDevice):
    """A simulated slave that notes each request it executes, then executes it as ``inner``."""

    def __init__(self, inner: SimulatedDevice, address: int, traffic: Traffic) -> None:
        super().__init__(name=inner.name)
        self.inner = inner
        self.address = address
        self.traffic = traffic

    def handle(self, pdu: bytes, *, broadcast: bool = False) -> bytes | None:
        self.traffic.append((self.address, bytes(pdu), broadcast))
        return self.inner.handle(pdu, broadcast=broadcast)


# --------------------------------------------------------------------------- the matrix


def device_answer(pdu: bytes) -> bytes:
    """What a PLC of the simulator answers to ``pdu`` itself."""
    answer = plc(1).handle(pdu)
    assert answer is not None
    return answer


DEVICE_ID = device_answer(h("2B 0E 01 00"))


@dataclass(frozen=True)
class Case:
    """One request, and the Modbus TCP answer without rules (``open``) and with ``RULES``.

    An answer is the reply PDU; ``reaches`` says whether the request reaches the line.
    """

    name: str
    unit: int
    pdu: bytes
    open: tuple[bytes, bool]
    rules: tuple[bytes, bool]


WRITE_3000 = h("06 0BB8 0BB8")  # holding 3000 holds 3000 on both PLCs: the write changes nothing
WRITE_3000_16 = h("10 0BB8 0001 02 0BB8")
CASES = [
    Case("read", 1, h("03 0000 0002"), (h("03 04 0000 0002"), True), (h("03 04 0000 0002"), True)),
    Case("read alias", 11, h("03 0000 0002"), (h("03 04 0000 0002"), True),
         (h("03 04 0000 0002"), True)),
    Case("write", 1, WRITE_3000, (WRITE_3000, True), (WRITE_3000, True)),
    Case("write alias", 11, WRITE_3000_16, (h("10 0BB8 0001"), True), (h("10 0BB8 0001"), True)),
    Case("8/0 echo", 1, h("08 0000 A537"), (h("08 0000 A537"), True), (h("08 0000 A537"), True)),
    Case("8/1 restart", 1, h("08 0001 0000"), (h("08 0001 0000"), True),
         (h("08 0001 0000"), True)),
    Case("8/4 listen only", 1, h("08 0004 0000"), (h("88 01"), False), (h("88 01"), False)),
    Case("43/14", 1, h("2B 0E 01 00"), (DEVICE_ID, True), (DEVICE_ID, True)),
    Case("user function", 1, h("41 0102"), (h("C1 01"), True), (h("C1 01"), True)),
    Case("refused", 1, h("11"), (h("91 01"), False), (h("91 01"), False)),
    Case("read slave 2", 2, h("03 0000 0001"), (h("03 02 0000"), True), (h("03 02 0000"), True)),
    Case("read alias 12", 12, h("03 0000 0001"), (h("03 02 0000"), True),
         (h("03 02 0000"), True)),
    Case("write slave 2", 2, WRITE_3000, (WRITE_3000, True), (h("86 01"), False)),
    Case("write alias 12", 12, WRITE_3000, (WRITE_3000, True), (h("86 01"), False)),
    Case("broadcast", 0, WRITE_3000, (WRITE_3000, True), (WRITE_3000, True)),
    Case("broadcast 16", 0, WRITE_3000_16, (h("10 0BB8 0001"), True), (h("90 01"), False)),
    Case("broadcast read", 0, h("03 0000 0001"), (h("83 01"), False), (h("83 01"), False)),
    Case("unrouted, named", 9, h("03 0000 0001"), (h("83 0A"), False), (h("83 0A"), False)),
    Case("unrouted", 8, h("03 0000 0001"), (h("83 0A"), False), (h("83 01"), False)),
    Case("invalid", 1, h("03 0000 0000"), (h("83 03"), False), (h("83 03"), False)),
]  # fmt: skip

#: Slave 1 under any unit id (named by unit 1 only), slave 2 read only (named by unit 2 only):
#: the aliases 11 and 12 inherit their slave's rules. Broadcast of FC 6; unit 9 unrouted.
RULES: list[dict[str, Any]] = [
    {"units": [1]},
    {"units": [2], "access": "read"},
    {"units": [0], "functions": [6]},
    {"units": [9], "access": "read"},
]
ROUTES = [{"unit": 11, "line": "a", "slave": 1}, {"unit": 12, "line": "a", "slave": 2}]


def silent_on(kind: str, unit: int) -> bool:
    """The documented silences: no RTU master hears about a broadcast, and the serial slave
    says nothing for a unit it does not stand for."""
    if kind in ("rtu-over-tcp", "serial-slave") and unit == 0:
        return True
    return kind == "serial-slave" and unit in (8, 9)


def expected_traffic(case: Case, reaches: bool) -> Traffic:
    if not reaches:
        return []
    if case.unit == 0:
        return [(1, case.pdu, True), (2, case.pdu, True)]
    slave = {11: 1, 12: 2}.get(case.unit, case.unit)
    return [(slave, case.pdu, False)]


# --------------------------------------------------------------------------- the masters


class Master(Protocol):
    def exchange(self, unit: int, pdu: bytes, silent: bool) -> bytes | None: ...

    def close(self) -> None: ...


def _read(ready: Callable[[float], bool], read: Callable[[int], bytes], count: int) -> bytes:
    deadline = time.monotonic() + DEADLINE_S
    data = b""
    while len(data) < count:
        left = deadline - time.monotonic()
        assert left > 0, f"no whole answer: {data.hex(' ')}"
        if ready(left):
            chunk = read(count - len(data))
            assert chunk, f"closed after {data.hex(' ')}"
            data += chunk
    return data


class RtuOverWire:
    """An RTU master on a byte stream: a socket (RTU over TCP) or a pty (serial slave)."""

    def __init__(
        self,
        fd: int,
        write: Callable[[bytes], object],
        read: Callable[[int], bytes],
        close: Callable[[], None] = lambda: None,
    ) -> None:
        self.fd = fd
        self.write = write
        self.read = read
        self.close = close
        self.expected = b""  #: the normal answer's PDU, for its length (set before exchanges)

    def ready(self, timeout: float) -> bool:
        readable, _, _ = select.select([self.fd], [], [], timeout)
        return bool(readable)

    def exchange(self, unit: int, pdu: bytes, silent: bool) -> bytes | None:
        self.write(append_crc(bytes((unit,)) + pdu))
        if silent:
            assert not self.ready(QUIET_S), f"unexpected answer: {self.read(512).hex(' ')}"
            return None
        head = _read(self.ready, self.read, 2)
        assert head[0] == unit, head.hex(" ")
        # An exception is 5 bytes; a normal answer as long as the TCP side's (checked there).
        rest = 3 if head[1] & 0x80 else len(self.expected) + 1
        frame = head + _read(self.ready, self.read, rest)
        while not check_crc(frame) and len(frame) < 256 and self.ready(QUIET_S):
            frame += self.read(256)  # not the answer expected: the rest of it, to show it
        assert check_crc(frame), f"unit {unit}: {frame.hex(' ')}"
        return frame[1:-2]


class MbapMaster:
    """A Modbus TCP master on a plain or TLS socket."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.tid = 0

    def exchange(self, unit: int, pdu: bytes, silent: bool) -> bytes | None:
        self.tid += 1
        self.sock.sendall(mbap(self.tid, unit, pdu))
        header = self._read(7)
        tid, protocol, length, reply_unit = struct.unpack(">HHHB", header)
        assert (tid, protocol, reply_unit) == (self.tid, 0, unit), header.hex(" ")
        return self._read(length - 1)

    def _read(self, count: int) -> bytes:
        data = b""
        while len(data) < count:
            chunk = self.sock.recv(count - len(data))
            assert chunk, f"closed after {data.hex(' ')}"
            data += chunk
        return data

    def close(self) -> None:
        self.sock.close()


def tcp_master(address: tuple[str, int], context: ssl.SSLContext | None = None) -> MbapMaster:
    sock = socket.create_connection(address, timeout=DEADLINE_S)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    if context is not None:
        sock = context.wrap_socket(sock, server_hostname="localhost")
    return MbapMaster(sock)


def serial_slave_master(gateway: RunningGateway, pair: PtyPair) -> RtuOverWire:
    """The RTU master on the far end of ``pair``, once the gateway's serial slave ``field``
    listens on it (it opens the pty in the background)."""
    slave = next(s for s in gateway.gateway.serial_slaves if s.name == "field")
    deadline = time.monotonic() + DEADLINE_S
    while not gateway.call(lambda: slave.up):
        assert time.monotonic() < deadline, "the serial-slave listener did not open"
        time.sleep(0.01)
    return RtuOverWire(
        pair.sim_fd, lambda data: os.write(pair.sim_fd, data), lambda n: os.read(pair.sim_fd, n)
    )


def masters_by_listener(gateway: RunningGateway, pair: PtyPair, pki: Pki) -> dict[str, Master]:
    """A master on each of the listeners ``tcp``, ``tls`` (the operator's certificate), ``rtu``
    (RTU over TCP) and ``field`` (the serial slave on ``pair``), by listener name."""
    serial = serial_slave_master(gateway, pair)
    address = gateway.gateway.listener_address
    return {
        "tcp": tcp_master(gateway.address),
        "tls": tcp_master(address("tls"), client_context(pki)),
        "rtu": rtu_over_tcp_master(address("rtu")),
        "field": serial,
    }


def rtu_over_tcp_master(address: tuple[str, int]) -> RtuOverWire:
    sock = socket.create_connection(address, timeout=DEADLINE_S)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return RtuOverWire(sock.fileno(), sock.sendall, sock.recv, sock.close)


# --------------------------------------------------------------------------- the gateway

#: The kind of each listener of the matrix, by name.
KIND_OF = {"tcp": "tcp", "tls": "tls", "rtu": "rtu-over-tcp", "field": "serial-slave"}


@dataclass
class Setup:
    gateway: RunningGateway
    traffic: Traffic
    masters: dict[str, Master]


@pytest.fixture
def every_listener(
    make_sim: SimFactory, make_gateway: GatewayFactory, pki: Pki
) -> Iterator[Callable[[bool], Setup]]:
    """``every_listener(rules)``: the gateway with its four listeners and a master on each."""
    opened: list[Any] = []

    def factory(rules: bool) -> Setup:
        traffic: Traffic = []
        sim = make_sim({unit: Recorder(plc(unit), unit, traffic) for unit in (1, 2)})
        pair = open_pty_pair()
        opened.append(pair)
        policy = {"policy": "matrix"} if rules else {}
        listeners = [
            {"name": "tls", "protocol": "tls", "listen": "127.0.0.1:0", "ca": str(pki.ca),
             "cert": str(pki.server_chain), "key": str(pki.server_key), **policy},
            {"name": "rtu", "protocol": "rtu-over-tcp", "listen": "127.0.0.1:0", **policy},
            {"name": "field", "protocol": "serial-slave", "device": pair.path, "baudrate": BAUD,
             **policy},
        ]  # fmt: skip
        raw: dict[str, Any] = {
            "server": {"broadcast_reply": True, "refuse_functions": [0x11], **policy},
            "lines": {"a": sim.line_table([1, 2], broadcast_turnaround=0.0)},
            "routes": ROUTES,
            "listeners": listeners,
        }
        if rules:
            raw["policies"] = {"matrix": {"rules": RULES}}
        gateway = make_gateway(raw)
        by_listener = masters_by_listener(gateway, pair, pki)
        masters = {KIND_OF[name]: master for name, master in by_listener.items()}
        opened.extend(masters.values())
        return Setup(gateway, traffic, masters)

    yield factory
    for thing in opened:
        thing.close()


def run_matrix(setup: Setup, rules: bool) -> dict[tuple[str, str], tuple[bytes | None, Traffic]]:
    """Each case through each listener: (answer, what reached the line)."""
    seen: dict[tuple[str, str], tuple[bytes | None, Traffic]] = {}
    for kind, master in setup.masters.items():
        for case in CASES:
            answer_expected = (case.rules if rules else case.open)[0]
            if isinstance(master, RtuOverWire):
                master.expected = answer_expected
            start = len(setup.traffic)
            answer = master.exchange(case.unit, case.pdu, silent_on(kind, case.unit))
            if isinstance(master, RtuOverWire):
                master.expected = MARKER_ANSWER
            assert master.exchange(1, MARKER, False) == MARKER_ANSWER, (kind, case.name)
            traffic = setup.traffic[start:]
            assert traffic[-1:] == [(1, MARKER, False)], (kind, case.name, traffic)
            seen[kind, case.name] = (answer, traffic[:-1])
    return seen


@pytest.mark.parametrize("rules", [False, True], ids=["no rules", "rules"])
def test_every_listener_admits_alike(every_listener: Callable[[bool], Setup], rules: bool) -> None:
    setup = every_listener(rules)
    seen = run_matrix(setup, rules)
    problems = []
    for kind in setup.masters:
        for case in CASES:
            answer, reaches = case.rules if rules else case.open
            wanted = (None if silent_on(kind, case.unit) else answer,
                      expected_traffic(case, reaches))  # fmt: skip
            got = seen[kind, case.name]
            if got != wanted:
                problems.append(f"{kind:>13} {case.name}: got {_show(got)}, wanted {_show(wanted)}")
    assert not problems, "\n".join(problems)


def _show(result: tuple[bytes | None, Traffic]) -> str:
    answer, traffic = result
    line = ", ".join(f"{'bcast' if b else s}:{p.hex(' ')}" for s, p, b in traffic) or "nothing"
    return f"answer {'none' if answer is None else answer.hex(' ')} / line {line}"
