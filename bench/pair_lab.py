"""Two gateway processes on one simulated RS-485 bus: the redundancy tests' and benchmark's lab.

``PairLab`` starts a ``MultidropBus`` at 9600 baud with the simulator's slaves as one node,
and gateways (``python -m gateway --config FILE``) each on a node of its own, each on its
own loopback address (127.0.0.2, 127.0.0.3, ...) so that a pair's addresses are known
before either starts. The pair's network channel may run through ``Proxy``, which the
lab cuts and heals to partition the two. ``Poller`` is a master polling one gateway with
raw Modbus TCP, classifying every answer: good (the simulated values), an exception, or
wrong (anything else: the one outcome that must never happen). The bus's own timestamps
count collisions and the seconds with two writers.
"""

from __future__ import annotations

import contextlib
import http.client
import itertools
import json
import re
import selectors
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from gateway.sim import plc
from gateway.sim.multidrop import MultidropBus

from .hostile import read_exactly

BAUDRATE = 9600
UNITS = (1, 2)
#: The PLC profile's holding registers 0..9 (``gateway.sim.plc``).
PLC_10 = bytes([0x03, 20]) + struct.pack(">10H", 0, 2, 4, 6, 8, 10, 0, 0, 0, 0)
READ_10 = bytes([0x03, 0x00, 0x00, 0x00, 0x0A])
DEADLINE_S = 15.0


def free_ports(host: str, count: int) -> list[int]:
    """``count`` distinct ports free on ``host`` now (held together while chosen)."""
    with contextlib.ExitStack() as stack:
        probes = [stack.enter_context(socket.socket()) for _ in range(count)]
        for probe in probes:
            probe.bind((host, 0))
        return [int(probe.getsockname()[1]) for probe in probes]


class Proxy:
    """A TCP relay from ``listen`` to ``target``; ``cut()`` partitions, ``heal()`` mends."""

    def __init__(self, host: str, target: tuple[str, int]) -> None:
        self.target = target
        self._server = socket.create_server((host, 0))
        self.address: tuple[str, int] = self._server.getsockname()[:2]
        self._cut = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self._thread = threading.Thread(target=self._accept, name="pair-proxy", daemon=True)
        self._thread.start()

    def cut(self) -> None:
        """Refuse new connections and drop every open one."""
        self._cut.set()
        with self._lock:
            for sock in list(self._open):
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)

    def heal(self) -> None:
        self._cut.clear()

    def close(self) -> None:
        self._stop.set()
        self.cut()
        self._server.close()
        self._thread.join(5)

    def _accept(self) -> None:
        self._server.settimeout(0.1)
        while not self._stop.is_set():
            try:
                client, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if self._cut.is_set():
                client.close()
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=1.0)
            except OSError:
                client.close()
                continue
            threading.Thread(target=self._relay, args=(client, upstream), daemon=True).start()

    def _relay(self, client: socket.socket, upstream: socket.socket) -> None:
        with self._lock:
            self._open |= {client, upstream}
        selector = selectors.DefaultSelector()
        selector.register(client, selectors.EVENT_READ, upstream)
        selector.register(upstream, selectors.EVENT_READ, client)
        try:
            while not self._stop.is_set() and not self._cut.is_set():
                for key, _ in selector.select(0.1):
                    data = key.fileobj.recv(65536)  # type: ignore[union-attr]
                    if not data:
                        return
                    key.data.sendall(data)
        except OSError:
            return
        finally:
            selector.close()
            with self._lock:
                self._open -= {client, upstream}
            client.close()
            upstream.close()


@dataclass
class GatewayProc:
    """One gateway of the lab: its addresses, configuration file and process."""

    name: str
    host: str
    modbus_port: int
    http_port: int
    config: Path
    proc: subprocess.Popen[str] | None = None
    lines: list[str] = field(default_factory=list)
    _reader: threading.Thread | None = None
    _changed: threading.Condition = field(default_factory=threading.Condition)

    @property
    def modbus(self) -> tuple[str, int]:
        return self.host, self.modbus_port

    def start(self) -> None:
        self.lines.clear()
        command = [sys.executable, "-m", "gateway", "--config", str(self.config), "--grace", "1"]
        self.proc = subprocess.Popen(command, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     text=True)  # fmt: skip
        self._reader = threading.Thread(target=self._read, args=(self.proc,), daemon=True)
        self._reader.start()
        self.wait_for(r"listening on .* \(Modbus TCP\)")

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            with self._changed:
                self.lines.append(line.rstrip("\n"))
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def wait_for(self, pattern: str, timeout: float = DEADLINE_S, start: int = 0) -> str:
        """The first log line from ``start`` on matching ``pattern``."""
        compiled = re.compile(pattern)
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                for line in self.lines[start:]:
                    if compiled.search(line):
                        return line
                if (
                    self.proc is not None
                    and self.proc.poll() is not None
                    and not any(compiled.search(line) for line in self.lines[start:])
                ):
                    raise RuntimeError(f"gateway {self.name} exited:\n" + self.log)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"gateway {self.name}: no {pattern!r}:\n{self.log}")
                self._changed.wait(min(remaining, 0.2))

    @property
    def log(self) -> str:
        with self._changed:
            return "\n".join(self.lines[-200:])

    def role(self, timeout: float = 1.0) -> str | None:
        """What ``GET /role`` says now (``None``: no answer)."""
        connection = http.client.HTTPConnection(self.host, self.http_port, timeout=timeout)
        try:
            connection.request("GET", "/role")
            document = json.loads(connection.getresponse().read())
            return str(document["role"])
        except (OSError, ValueError, KeyError):
            return None
        finally:
            connection.close()

    def wait_role(self, role: str, timeout: float = DEADLINE_S) -> None:
        deadline = time.monotonic() + timeout
        while self.role() != role:
            if time.monotonic() > deadline:
                raise TimeoutError(f"gateway {self.name} is not {role}:\n{self.log}")
            time.sleep(0.05)  # polling an HTTP endpoint: there is no event to wait on

    def readyz(self) -> str:
        connection = http.client.HTTPConnection(self.host, self.http_port, timeout=2.0)
        try:
            connection.request("GET", "/readyz")
            return connection.getresponse().read().decode()
        finally:
            connection.close()

    def signal(self, signum: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(signum)

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait(10)
        self._release()

    def _release(self) -> None:
        """The dead process's log pipe, once its reader has read it to the end."""
        if self._reader is not None:
            self._reader.join(10)
        if self.proc is not None and self.proc.stderr is not None:
            self.proc.stderr.close()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._release()


@dataclass
class Tally:
    """What one poller's master got."""

    good: int = 0
    exceptions: dict[int, int] = field(default_factory=dict)
    errors: int = 0  # no answer (connection lost or refused, timed out)
    wrong: list[str] = field(default_factory=list)
    good_at: list[float] = field(default_factory=list)

    def longest_gap(self, start: float, end: float) -> float:
        """The longest time without a good answer between ``start`` and ``end``."""
        times = [start] + [t for t in self.good_at if start <= t <= end] + [end]
        return max(b - a for a, b in itertools.pairwise(times))


class Poller:
    """A master polling one gateway: a read of registers 0..9 of ``unit`` every ``period``."""

    def __init__(self, address: tuple[str, int], unit: int = 1, period: float = 0.05) -> None:
        self.address = address
        self.unit = unit
        self.period = period
        self.tally = Tally()
        self.latencies: list[float] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="poller", daemon=True)
        self._thread.start()

    def retarget(self, address: tuple[str, int]) -> None:
        with self._lock:
            self.address = address

    def stop(self) -> Tally:
        self._stop.set()
        self._thread.join(10)
        return self.tally

    def _run(self) -> None:
        tid = 0
        sock: socket.socket | None = None
        connected_to: tuple[str, int] | None = None
        while not self._stop.is_set():
            with self._lock:
                address = self.address
            try:
                if sock is None or connected_to != address:
                    if sock is not None:
                        sock.close()
                    sock = socket.create_connection(address, timeout=2.0)
                    sock.settimeout(6.0)
                    connected_to = address
                tid = (tid + 1) & 0xFFFF
                sent = time.monotonic()
                sock.sendall(struct.pack(">HHHB", tid, 0, len(READ_10) + 1, self.unit) + READ_10)
                answer_tid, pdu = _read_answer(sock)
                self._classify(tid, answer_tid, pdu, time.monotonic(), sent)
            except OSError:
                self.tally.errors += 1
                if sock is not None:
                    sock.close()
                sock = None
                self._stop.wait(0.1)
                continue
            self._stop.wait(self.period)
        if sock is not None:
            sock.close()

    def _classify(self, tid: int, answer_tid: int, pdu: bytes, now: float, sent: float) -> None:
        tally = self.tally
        if answer_tid == tid and pdu == PLC_10:
            tally.good += 1
            tally.good_at.append(now)
            self.latencies.append(now - sent)
        elif answer_tid == tid and len(pdu) == 2 and pdu[0] == 0x83:
            tally.exceptions[pdu[1]] = tally.exceptions.get(pdu[1], 0) + 1
        else:
            tally.wrong.append(f"tid {answer_tid} for {tid}: {pdu.hex()}")


def _read_answer(sock: socket.socket) -> tuple[int, bytes]:
    head = read_exactly(sock, 7)
    tid, _protocol, length, _unit = struct.unpack(">HHHB", head)
    return tid, read_exactly(sock, length - 1)


class PairLab:
    """A bus with the simulator's slaves and gateways on it (see the module doc)."""

    def __init__(self, workdir: Path, *, baudrate: int = BAUDRATE) -> None:
        self.workdir = workdir
        self.bus = MultidropBus(baudrate)
        self.bus.start()
        self.slaves = self.bus.attach_slaves({unit: plc(unit) for unit in UNITS})
        self.gateways: dict[str, GatewayProc] = {}
        self.proxies: list[Proxy] = []
        self._hosts = iter(f"127.0.0.{index}" for index in range(2, 250))

    def gateway(self, name: str) -> GatewayProc:
        host = next(self._hosts)
        modbus_port, http_port = free_ports(host, 2)
        gateway = GatewayProc(name, host, modbus_port, http_port, self.workdir / f"{name}.toml")
        self.gateways[name] = gateway
        return gateway

    def configure(self, gateway: GatewayProc, peer: GatewayProc | None = None,
                  priority: int = 100, proxy: bool = False, extra: str = "",
                  routes: Mapping[int, int] | None = None) -> None:  # fmt: skip
        """Write ``gateway``'s file: its node on the bus, its addresses, and its peer.

        ``routes`` (unit id -> slave address) replaces the line's own units (each unit to
        the slave of its number). Written again, the file keeps the gateway's node.
        """
        node = self.bus.nodes.get(gateway.name) or self.bus.node(gateway.name)
        text = [
            f'[server]\nlisten = "{gateway.host}:{gateway.modbus_port}"\n'
            "max_connections_per_source = 0\n",
            f'[metrics]\nlisten = "{gateway.host}:{gateway.http_port}"\n',
            '[logging]\nlevel = "info"\n',
        ]
        if peer is not None:
            http_address: tuple[str, int] = (peer.host, peer.http_port)
            modbus_address: tuple[str, int] = peer.modbus
            if proxy:  # the pair's network runs through relays the lab can cut
                relays = Proxy(gateway.host, http_address), Proxy(gateway.host, modbus_address)
                self.proxies += relays
                http_address, modbus_address = relays[0].address, relays[1].address
            text.append(
                f'[redundancy]\npeer = "{http_address[0]}:{http_address[1]}"\n'
                f'peer_modbus = "{modbus_address[0]}:{modbus_address[1]}"\n'
                f"priority = {priority}\n"
            )
        units = list(UNITS) if routes is None else []
        text.append(f'[lines.a]\ndevice = "{node.path}"\nbaudrate = {self.bus.baudrate}\n'
                    f"units = {units}\n{extra}")  # fmt: skip
        text += [f'[[routes]]\nunit = {unit}\nline = "a"\nslave = {slave}\n'
                 for unit, slave in (routes or {}).items()]  # fmt: skip
        gateway.config.write_text("\n".join(text))

    def pair(self, proxy: bool = False) -> tuple[GatewayProc, GatewayProc]:
        """Two paired gateways, started together; the first has the higher priority."""
        first, second = self.gateway("a"), self.gateway("b")
        self.configure(first, second, priority=200, proxy=proxy)
        self.configure(second, first, priority=100, proxy=proxy)
        first.start()
        second.start()
        return first, second

    def restart(self, gateway: GatewayProc) -> None:
        """Start ``gateway`` again on its node (freed of what a killed process left)."""
        self.bus.replug(gateway.name)
        gateway.start()

    def cut_network(self) -> None:
        """Partition the pair: neither reaches the other's endpoint or listener."""
        for relay in self.proxies:
            relay.cut()

    def heal_network(self) -> None:
        for relay in self.proxies:
            relay.heal()

    def close(self) -> None:
        for gateway in self.gateways.values():
            gateway.stop()
        for relay in self.proxies:
            relay.close()
        self.bus.close()


__all__ = ["PLC_10", "GatewayProc", "PairLab", "Poller", "Proxy", "Tally"]
