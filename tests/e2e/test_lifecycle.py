"""Lifecycle of the daemon against the real CLI: stop signals, SIGHUP reload, serial-port loss.

Each test runs ``python -m gateway --config FILE`` in a subprocess, waits for its
"listening on" log line, keeps requests flowing from client threads on raw
sockets (several in flight, distinct transaction ids) while the event happens,
and then checks that every request sent before the event got exactly one answer
carrying its own transaction id: a reply or an exception, none lost, none
duplicated. The slaves are ``SimulatedLine`` on pseudo-terminals in the test
process; the gateway opens them by path, as it would a USB adapter.

Synchronisation is by log lines, answers and counters, each with a deadline.
``LIFECYCLE_GATEWAY_ARGS="--trace"`` adds flags to every gateway started, to see
each request and reply in a failing test's log.
"""

from __future__ import annotations

import asyncio
import http.client
import os
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from gateway.config import build_config
from gateway.io.links.serial_port import SerialLink, SerialPortError, open_serial
from gateway.sim import PtyPair, SimulatedLine, open_pty_pair, plc
from tests.helpers import LoggedProcess, mbap, wait_until

DEADLINE_S = 10.0
READ_10 = bytes([0x03, 0x00, 0x00, 0x00, 0x0A])  # read holding registers 0..9
#: The PLC profile's holding registers 0..9 are 0, 2, 4, 6, 8, 10, then 0.
PLC_10 = bytes([0x03, 20]) + struct.pack(">10H", 0, 2, 4, 6, 8, 10, 0, 0, 0, 0)
PATH_UNAVAILABLE = bytes([0x83, 0x0A])
#: What ``Master.tally`` files a correct reply under.
GOOD = b"good"
TARGET_FAILED = bytes([0x83, 0x0B])

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="needs Linux ptys and signals")


# --------------------------------------------------------------------------- configuration


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    raise TypeError(f"no TOML for {value!r}")


def write_config(
    path: Path,
    lines: Mapping[str, Mapping[str, Any]],
    routes: Sequence[Mapping[str, Any]] = (),
    level: str = "info",
) -> None:
    """Write a configuration file atomically (the gateway never reads half a file)."""
    text = [f'[logging]\nlevel = "{level}"\n']
    for name, table in lines.items():
        text.append(f"[lines.{name}]")
        text.extend(f"{key} = {_toml_value(value)}" for key, value in table.items())
        text.append("")
    for route in routes:
        text.append("[[routes]]")
        text.extend(f"{key} = {_toml_value(value)}" for key, value in route.items())
        text.append("")
    write_text(path, "\n".join(text))


def write_text(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` in one rename."""
    temporary = path.with_suffix(".tmp")
    temporary.write_text(text)
    os.replace(temporary, path)


# --------------------------------------------------------------------------- the gateway process


class GatewayProcess(LoggedProcess):
    """``python -m gateway`` in a subprocess; its stderr log is collected line by line."""

    def __init__(self, config: Path, *, grace: float = 5.0, metrics: bool = False) -> None:
        super().__init__(
            "--config", str(config), "--listen", "127.0.0.1:0",
            "--metrics", "127.0.0.1:0" if metrics else "off",
            "--grace", str(grace), *os.environ.get("LIFECYCLE_GATEWAY_ARGS", "").split(),
        )  # fmt: skip
        match = self.wait_for(r"listening on ([\d.]+):(\d+) \(Modbus TCP\)")
        self.address = (match[1], int(match[2]))
        self.metrics_address: tuple[str, int] | None = None
        if metrics:
            match = self.wait_for(r"metrics on http://([\d.]+):(\d+)/metrics")
            self.metrics_address = (match[1], int(match[2]))

    def signal(self, signum: int) -> float:
        """Send ``signum``; return the monotonic time just before it was sent."""
        sent_at = time.monotonic()
        self.proc.send_signal(signum)
        return sent_at

    def wait_exit(self, timeout: float) -> tuple[int, float]:
        """The exit code and the monotonic time the exit was seen."""
        code = self.proc.wait(timeout)
        return code, time.monotonic()

    def readyz(self) -> tuple[int, str]:
        """GET /readyz on the metrics endpoint."""
        assert self.metrics_address is not None
        connection = http.client.HTTPConnection(*self.metrics_address, timeout=DEADLINE_S)
        try:
            connection.request("GET", "/readyz")
            response = connection.getresponse()
            return response.status, response.read().decode()
        finally:
            connection.close()

    def close(self) -> None:
        """Kill the process if it still runs; collect the rest of its log."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.release()


# --------------------------------------------------------------------------- masters


class Master(threading.Thread):
    """One TCP master keeping ``window`` requests in flight, each with a fresh transaction id.

    Request ``tid`` reads holding register 1000 + tid % 9000, which the PLC profile holds
    at that same value: every request differs (the gateway cannot fold them into one) and
    a reply proves it belongs to its request. Records when each request was handed to
    the kernel and every answer, and flags answers that repeat or that carry a
    transaction id never sent. Stops sending on ``finish()`` (then waits for what is
    outstanding) or when the gateway closes (then reads what is left until EOF).
    """

    def __init__(
        self,
        address: tuple[str, int],
        unit: int,
        *,
        window: int = 4,
        first_tid: int = 1,
        interval: float = 0.0,
    ) -> None:
        super().__init__(name=f"master-{unit}-{first_tid}", daemon=True)
        self.sock = socket.create_connection(address, timeout=DEADLINE_S)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.unit = unit
        self.window = window
        self.interval = interval
        self._next_tid = first_tid
        self.sent: dict[int, float] = {}
        self.answers: dict[int, tuple[float, bytes]] = {}
        self.duplicates: list[int] = []
        self.strangers: list[int] = []
        self.closed_at: float | None = None
        self.error: BaseException | None = None
        self._outstanding: set[int] = set()
        self._stop_sending = threading.Event()
        self._progress = threading.Condition()
        self._buffer = bytearray()

    # -- the thread ----------------------------------------------------------------------

    def run(self) -> None:
        try:
            while True:
                if not self._stop_sending.is_set():
                    while len(self._outstanding) < self.window and self._send():
                        pass
                if not self._outstanding:
                    if self._stop_sending.is_set():
                        break
                    continue
                if not self._receive():
                    break
        except BaseException as error:  # reported by check()
            self.error = error
        finally:
            self.sock.close()
            with self._progress:
                self._progress.notify_all()

    def _send(self) -> bool:
        if self.interval:
            time.sleep(self.interval)
        tid = self._next_tid
        try:
            self.sock.sendall(mbap(tid, self.unit, struct.pack(">BHH", 3, register(tid), 1)))
        except (BrokenPipeError, ConnectionResetError):
            # The gateway closed: no more requests, but answers may still wait in the buffer.
            self._stop_sending.set()
            return False
        with self._progress:
            self.sent[tid] = time.monotonic()
            self._outstanding.add(tid)
        self._next_tid = tid + 1
        return True

    def _receive(self) -> bool:
        """Read one answer; False when the gateway closed the connection."""
        while True:
            if len(self._buffer) >= 6:
                length = struct.unpack_from(">H", self._buffer, 4)[0]
                if len(self._buffer) >= 6 + length:
                    break
            try:
                chunk = self.sock.recv(4096)
            except ConnectionResetError:
                chunk = b""
            except TimeoutError:
                raise AssertionError(f"no answer in {DEADLINE_S} s") from None
            if not chunk:
                self.closed_at = time.monotonic()
                assert not self._buffer, f"a partial answer: {self._buffer.hex()}"
                return False
            self._buffer += chunk
        tid, protocol, length, unit = struct.unpack_from(">HHHB", self._buffer)
        pdu = bytes(self._buffer[7 : 6 + length])
        del self._buffer[: 6 + length]
        assert (protocol, unit) == (0, self.unit), (protocol, unit)
        now = time.monotonic()
        with self._progress:
            if tid in self.answers:
                self.duplicates.append(tid)
            elif tid not in self._outstanding:
                self.strangers.append(tid)
            else:
                self._outstanding.discard(tid)
                self.answers[tid] = (now, pdu)
            self._progress.notify_all()
        return True

    # -- the test's side ---------------------------------------------------------------

    def wait_answers(self, count: int) -> None:
        """Wait until ``count`` answers arrived."""
        deadline = time.monotonic() + DEADLINE_S
        with self._progress:
            while len(self.answers) < count:
                remaining = deadline - time.monotonic()
                assert remaining > 0 and self.is_alive(), (
                    f"{self.name}: {len(self.answers)} answers, wanted {count} ({self.error!r})"
                )
                self._progress.wait(remaining)

    def finish(self) -> None:
        """Stop sending, wait for the outstanding answers (or the close), end the thread."""
        self._stop_sending.set()
        self.join(DEADLINE_S)
        assert not self.is_alive(), f"{self.name} still waiting for {sorted(self._outstanding)}"

    def answers_sent_before(self, moment: float) -> dict[int, bytes | None]:
        """Each request sent before ``moment``, with its answer kind (``None``: none came).

        A correct reply is ``GOOD``; an exception its PDU; anything else as it came.
        """
        with self._progress:
            return {
                tid: classify(tid, self.answers[tid][1]) if tid in self.answers else None
                for tid, sent_at in self.sent.items()
                if sent_at < moment
            }

    def check(self, *allowed: bytes, before: float = float("inf")) -> None:
        """Every request sent before ``before`` got exactly one answer: ``GOOD`` or ``allowed``."""
        assert self.error is None, f"{self.name}: {self.error!r}"
        assert not self.duplicates, f"{self.name}: answered twice: {self.duplicates}"
        assert not self.strangers, f"{self.name}: answers to unsent ids: {self.strangers}"
        answers = self.answers_sent_before(before)
        lost = [tid for tid, pdu in answers.items() if pdu is None]
        assert not lost, (
            f"{self.name}: {len(lost)} of {len(answers)} requests lost: {lost} {answers}"
        )
        kinds = {GOOD, *allowed}
        wrong = {tid: pdu.hex() for tid, pdu in answers.items() if pdu and pdu not in kinds}
        assert not wrong, f"{self.name}: unexpected answers {wrong}"

    def tally(self) -> dict[bytes, int]:
        """How many answers of each kind (see ``answers_sent_before``)."""
        counts: dict[bytes, int] = {}
        with self._progress:
            for tid, (_, pdu) in self.answers.items():
                kind = classify(tid, pdu)
                counts[kind] = counts.get(kind, 0) + 1
        return counts


def register(tid: int) -> int:
    """The holding register request ``tid`` of a ``Master`` reads."""
    return 1000 + tid % 9000


def classify(tid: int, pdu: bytes) -> bytes:
    """``GOOD`` for the right value of ``register(tid)``, else the PDU itself."""
    return GOOD if pdu == struct.pack(">BBH", 3, 2, register(tid)) else pdu


def request(address: tuple[str, int], unit: int, tid: int) -> tuple[bytes, float]:
    """One request on a new connection: its answer and how long it took."""
    with socket.create_connection(address, timeout=DEADLINE_S) as sock:
        return transact(sock, unit, tid)


def transact(sock: socket.socket, unit: int, tid: int, pdu: bytes = READ_10) -> tuple[bytes, float]:
    """One request on ``sock``: the answer's PDU (checked for tid and unit) and the latency."""
    started = time.monotonic()
    sock.sendall(mbap(tid, unit, pdu))
    data = b""
    while len(data) < 6 or len(data) < 6 + struct.unpack_from(">H", data, 4)[0]:
        chunk = sock.recv(4096)
        assert chunk, "the gateway closed the connection"
        data += chunk
    elapsed = time.monotonic() - started
    answer_tid, _, length, answer_unit = struct.unpack_from(">HHHB", data)
    assert (answer_tid, answer_unit) == (tid, unit)
    assert len(data) == 6 + length, "more than one answer"
    return data[7:], elapsed


# --------------------------------------------------------------------------- fixtures


class Lab:
    """Simulated lines, gateway processes and masters of one test, all torn down at the end."""

    def __init__(self, stack: ExitStack, tmp_path: Path) -> None:
        self._stack = stack
        self.dir = tmp_path
        self.config = tmp_path / "gateway.toml"
        self.masters: list[Master] = []

    def sim(
        self, units: Sequence[int], baudrate: int | None = None
    ) -> tuple[PtyPair, SimulatedLine]:
        """A started simulated line with a PLC at each of ``units``."""
        pair = open_pty_pair()
        self._stack.callback(pair.close)
        line = SimulatedLine(pair.sim_fd, {unit: plc(unit) for unit in units}, baudrate=baudrate)
        line.start()
        self._stack.callback(line.stop)
        return pair, line

    def gateway(self, *, grace: float = 5.0, metrics: bool = False) -> GatewayProcess:
        """Start the CLI on ``self.config``; killed at teardown if still running."""
        process = GatewayProcess(self.config, grace=grace, metrics=metrics)
        self._stack.callback(process.close)
        return process

    def master(self, gateway: GatewayProcess, unit: int, **options: Any) -> Master:
        """A started master; its thread is stopped before the gateway at teardown."""
        options.setdefault("first_tid", 1 + 1000 * len(self.masters))
        master = Master(gateway.address, unit, **options)
        self.masters.append(master)
        self._stack.callback(master.join, DEADLINE_S)
        self._stack.callback(master._stop_sending.set)
        master.start()
        return master


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    with ExitStack() as stack:
        yield Lab(stack, tmp_path)


def line_table(device: str, units: list[int], **options: Any) -> dict[str, Any]:
    """A ``[lines.NAME]`` table.

    Its timeout is 1 s unless given: the simulated slaves answer from a thread of the test
    process, which a loaded machine can hold past 115200 baud's automatic timeout (0.12 s);
    one such timeout makes the slave suspect and its next requests 0x0B, which the tests
    that expect only replies would report as a fault of the gateway. Tests that time out on
    purpose give their own."""
    return {"device": device, "baudrate": 115200, "units": units, "timeout": 1.0, **options}


# --------------------------------------------------------------------------- stop signals


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_stop_signal_drains_and_exits_0(lab: Lab, signum: int) -> None:
    """Listener closed, wire transaction finished, queue answered 0x0A, exit 0 within the grace."""
    pair, sim = lab.sim([1], baudrate=9600)  # ~40 ms per transaction: a queue forms
    write_config(lab.config, {"a": line_table(pair.path, [1], baudrate=9600)})
    grace = 5.0
    gateway = lab.gateway(grace=grace)
    masters = [lab.master(gateway, 1, window=6) for _ in range(3)]
    for master in masters:
        master.wait_answers(2)
    # A transaction on the wire when the signal comes: the slave takes 0.5 s over the
    # next one. The second request served from now on was surely served after the change.
    sim.faults(1).reply_delay = 0.5
    served = sim.stats().requests
    wait_until(lambda: sim.stats().requests >= served + 2, "a slow answer on the wire")

    signalled_at = gateway.signal(signum)
    code, exited_at = gateway.wait_exit(grace + DEADLINE_S)
    for master in masters:
        master.join(DEADLINE_S)

    assert code == 0, gateway.log
    assert exited_at - signalled_at < grace
    gateway.wait_for(rf"{signal.Signals(signum).name} received")
    gateway.wait_for("stopped")
    good = unavailable = 0
    for master in masters:
        assert master.closed_at is not None, "the gateway did not close the connection"
        master.check(PATH_UNAVAILABLE, before=signalled_at)
        before = list(master.answers_sent_before(signalled_at).values())
        good += before.count(GOOD)
        unavailable += before.count(PATH_UNAVAILABLE)
    # The queue (up to 17 requests) was answered 0x0A, and the transaction on the wire was
    # completed: every request the slave answered reached its master (later requests were
    # all refused at once, so every reply went to a request sent before the signal).
    assert unavailable >= 5
    assert sim.stats().responses == good
    print(f"\n{signal.Signals(signum).name}: exit 0 after {exited_at - signalled_at:.3f} s, "
          f"{good} replies and {unavailable} x 0x0A to the requests sent before it")  # fmt: skip


def test_second_stop_signal_exits_at_once(lab: Lab) -> None:
    """During a long grace (a silent slave holds the wire) a second SIGTERM exits at once."""
    pair, sim = lab.sim([1])
    sim.faults(1).silent = True
    write_config(lab.config, {"a": line_table(pair.path, [1], timeout=5.0, retries=0)})
    gateway = lab.gateway(grace=30.0)
    master = lab.master(gateway, 1, window=3)
    deadline = time.monotonic() + DEADLINE_S
    while sim.stats().silent_drops < 1:  # the first request is on the wire
        assert time.monotonic() < deadline
        time.sleep(0.005)

    mark = gateway.mark()
    signalled_at = gateway.signal(signal.SIGTERM)
    gateway.wait_for("stopping: no new connections", start=mark)
    master.wait_answers(2)  # the two queued requests: 0x0A at once
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(gateway.address, timeout=DEADLINE_S).close()
    assert gateway.proc.poll() is None, "the first signal must wait for the wire"

    again_at = gateway.signal(signal.SIGTERM)
    code, exited_at = gateway.wait_exit(DEADLINE_S)
    master.join(DEADLINE_S)
    # Documented: the second signal exits with status 1 without waiting for the wire; the
    # request on the wire gets no answer (its connection is closed by the exit).
    assert code == 1, gateway.log
    assert exited_at - again_at < 1.0
    assert "second SIGTERM: exiting at once" in gateway.log
    answers = master.answers_sent_before(signalled_at)
    assert sorted(pdu for pdu in answers.values() if pdu is not None) == [PATH_UNAVAILABLE] * 2
    assert master.closed_at is not None and not master.duplicates and not master.strangers
    print(f"\nsecond SIGTERM: exit 1 after {exited_at - again_at:.3f} s")


def test_a_grace_shorter_than_the_wire_transaction_still_answers_it(lab: Lab) -> None:
    """When the grace runs out the transaction on the wire is given up and answered 0x0A,
    like everything still queued: the gateway left, not the slave."""
    pair, sim = lab.sim([1])
    sim.faults(1).silent = True
    write_config(lab.config, {"a": line_table(pair.path, [1], timeout=5.0, retries=0)})
    grace = 0.3
    gateway = lab.gateway(grace=grace)
    master = lab.master(gateway, 1, window=3)
    deadline = time.monotonic() + DEADLINE_S
    while sim.stats().silent_drops < 1:  # the first request is on the wire
        assert time.monotonic() < deadline
        time.sleep(0.005)

    signalled_at = gateway.signal(signal.SIGTERM)
    code, exited_at = gateway.wait_exit(DEADLINE_S)
    master.join(DEADLINE_S)
    assert code == 0, gateway.log
    assert grace <= exited_at - signalled_at < grace + 1.0
    master.check(PATH_UNAVAILABLE, TARGET_FAILED, before=signalled_at)
    answers = sorted(a for a in master.answers_sent_before(signalled_at).values() if a)
    assert answers == [PATH_UNAVAILABLE] * 3, answers
    print(f"\ngrace {grace} s over: exit 0 after {exited_at - signalled_at:.3f} s")


# --------------------------------------------------------------------------- SIGHUP reload


def test_reload_changes_routes_and_timeouts_without_dropping_connections(lab: Lab) -> None:
    pair, sim = lab.sim([1, 2])
    sim.faults(2).silent = True  # unit 2's answers show which timeout is in force
    options = {"timeout": 0.4, "retries": 0}
    write_config(lab.config, {"a": line_table(pair.path, [1, 2], **options)})
    gateway = lab.gateway()
    master = lab.master(gateway, 1, window=4)
    master.wait_answers(5)
    with socket.create_connection(gateway.address, timeout=DEADLINE_S) as probe:
        assert transact(probe, 5, 1)[0] == PATH_UNAVAILABLE  # unit 5 has no route yet
        answer, before = transact(probe, 2, 2)
        assert answer == TARGET_FAILED and before >= 0.4

        options["timeout"] = 0.2  # not less: unit 1 must still answer in time on a busy machine
        routes = [{"unit": 5, "line": "a", "slave": 1}]
        # The log level needs a restart: kept (else the "applied" line below would be missing).
        lines = {"a": line_table(pair.path, [1, 2], **options)}
        write_config(lab.config, lines, routes, level="error")
        mark = gateway.mark()
        gateway.signal(signal.SIGHUP)
        gateway.wait_for(r"WARNING .*\[logging\] changes need a restart", start=mark)
        gateway.wait_for(r"configuration from .* applied", start=mark)

        assert transact(probe, 5, 3)[0] == PLC_10  # the new route, on the same connection
        answer, after = transact(probe, 2, 4)
        assert answer == TARGET_FAILED and 0.2 <= after < 0.4
        answered = len(master.answers)
        master.wait_answers(answered + 5)
    master.finish()
    master.check()
    assert master.closed_at is None, "the reload dropped the connection"
    assert gateway.count("reopening|line a: .* open at") == 1
    assert gateway.proc.poll() is None


def test_reload_of_a_baud_rate_reopens_only_that_line(lab: Lab) -> None:
    pair_a, _ = lab.sim([1])
    pair_b, _ = lab.sim([2])
    lines = {"a": line_table(pair_a.path, [1]), "b": line_table(pair_b.path, [2])}
    write_config(lab.config, lines)
    gateway = lab.gateway()
    master_a = lab.master(gateway, 1, window=4)
    master_b = lab.master(gateway, 2, window=4)
    master_a.wait_answers(5)
    master_b.wait_answers(5)

    lines["a"] = line_table(pair_a.path, [1], baudrate=57600)
    write_config(lab.config, lines)
    mark = gateway.mark()
    gateway.signal(signal.SIGHUP)
    gateway.wait_for(r"line a port settings changed, reopening", start=mark)
    gateway.wait_for(r"line a: .* open at 57600 baud", start=mark)
    gateway.wait_for(r"configuration from .* applied", start=mark)
    master_a.wait_answers(len(master_a.answers) + 5)
    master_b.wait_answers(len(master_b.answers) + 5)
    master_a.finish()
    master_b.finish()

    # Line a's queue, and what master a sends while the reopen waits for the transaction on
    # the wire, wait for the reopened port: every request is answered; line b never notices.
    master_a.check()
    master_b.check()
    assert master_a.closed_at is None and master_b.closed_at is None
    assert gateway.count(r"line b: .* open at") == 1
    assert gateway.count(r"line b port settings") == 0


def test_a_reload_says_in_one_line_what_changed_and_what_that_did(lab: Lab) -> None:
    """Each key by its full name with its old and new value, then what it did: a line
    reopened, a line retuned in place, a restart-only key kept at its running value."""
    pair_a, _ = lab.sim([1])
    pair_b, _ = lab.sim([2])
    lines = {"a": line_table(pair_a.path, [1], timeout=0.5), "b": line_table(pair_b.path, [2])}
    write_config(lab.config, lines)
    gateway = lab.gateway()
    lines["a"]["timeout"] = 0.7
    lines["b"]["baudrate"] = 57600
    write_config(lab.config, lines, [{"unit": 5, "line": "a", "slave": 1}], level="error")
    mark = gateway.mark()
    gateway.signal(signal.SIGHUP)
    summary = gateway.wait_for(r"reload: configuration from \S+ applied: (.*)", start=mark)[1]
    changes = summary.split("; ")
    assert "lines.a.timeout 0.5 → 0.7" in changes
    assert "lines.b.baudrate 115200 → 57600" in changes
    assert "routes.5 added" in changes
    assert "line b reopened" in changes and "line a retuned in place" in changes
    assert "needs a restart, kept at its running value: logging.level 'info' → 'error'" in (
        changes
    ), summary
    assert request(gateway.address, 5, 1)[0] == PLC_10  # the new route serves

    write_config(lab.config, lines, [{"unit": 5, "line": "a", "slave": 1}])  # what runs
    mark = gateway.mark()
    gateway.signal(signal.SIGHUP)
    again = gateway.wait_for(r"reload: configuration from \S+ applied: (.*)", start=mark)[1]
    assert again.startswith("no key changed")


def test_a_sighup_during_a_reload_waits_for_it(lab: Lab) -> None:
    """Reloads never overlap: a line reopened by one is not opened a second time by the next."""
    pair, sim = lab.sim([1, 2])
    sim.faults(2).silent = True  # its requests hold the wire, so the reopen has to wait
    lines = {"a": line_table(pair.path, [1, 2], timeout=0.3, retries=0, dead_after=0)}
    write_config(lab.config, lines)
    gateway = lab.gateway()
    master = lab.master(gateway, 1, window=2)
    master.wait_answers(5)
    slow = lab.master(gateway, 2, window=1)
    deadline = time.monotonic() + DEADLINE_S
    while sim.stats().silent_drops < 1:  # unit 2's request is on the wire
        assert time.monotonic() < deadline
        time.sleep(0.005)

    lines["a"]["baudrate"] = 57600
    write_config(lab.config, lines)
    mark = gateway.mark()
    gateway.signal(signal.SIGHUP)
    gateway.wait_for(r"line a port settings changed, reopening", start=mark)
    gateway.signal(signal.SIGHUP)  # while the first reload waits for the wire
    gateway.wait_for(r"configuration from .* applied", start=mark)
    applied = [i for i, line in enumerate(gateway.lines) if i >= mark and "applied" in line]
    gateway.wait_for(r"configuration from .* applied", start=applied[0] + 1)
    slow.finish()
    master.wait_answers(len(master.answers) + 5)
    master.finish()
    master.check(PATH_UNAVAILABLE)
    slow.check(PATH_UNAVAILABLE, TARGET_FAILED)
    log = gateway.lines[mark:]
    second = [i for i, line in enumerate(log) if "SIGHUP received" in line][1]
    reopened = next(i for i, line in enumerate(log) if "open at 57600" in line)
    assert second < reopened, "the second SIGHUP came after the first reload: nothing tested"
    assert gateway.count(r"line a: .* open at") == 2, gateway.log  # at start, and once again
    assert gateway.count(r"reopening|line a added") == 1, gateway.log


def test_invalid_reload_is_rejected_and_the_old_configuration_keeps_serving(lab: Lab) -> None:
    pair, _ = lab.sim([1])
    write_config(lab.config, {"a": line_table(pair.path, [1])})
    gateway = lab.gateway()
    master = lab.master(gateway, 1, window=4)
    master.wait_answers(5)

    broken = {
        "syntax": "[lines.a\ndevice = 'x'\n",
        "semantics": f'[lines.a]\ndevice = "{pair.path}"\nbaudrate = -5\nunits = [7]\n',
    }
    for kind, text in broken.items():
        write_text(lab.config, text)
        mark = gateway.mark()
        gateway.signal(signal.SIGHUP)
        gateway.wait_for(r"ERROR .*reload rejected, the running configuration stays: ", start=mark)
        gateway.wait_for("TOML syntax" if kind == "syntax" else "baudrate", start=mark)
        master.wait_answers(len(master.answers) + 5)  # unit 1 still routed: the old config

    # A good file afterwards is applied as usual.
    routes = [{"unit": 5, "line": "a", "slave": 1}]
    write_config(lab.config, {"a": line_table(pair.path, [1])}, routes)
    mark = gateway.mark()
    gateway.signal(signal.SIGHUP)
    gateway.wait_for(r"configuration from .* applied", start=mark)
    assert request(gateway.address, 5, 77)[0] == PLC_10
    master.finish()
    master.check()
    assert master.closed_at is None


# --------------------------------------------------------------------------- serial-port loss


def test_serial_port_loss_answers_0x0a_at_once_and_recovers_within_a_second(lab: Lab) -> None:
    link = lab.dir / "ttyBUS"  # the gateway opens the symlink, like a /dev/serial/by-id name
    pair, sim = lab.sim([1])
    other, _ = lab.sim([2])  # line b: served all along, without stalls
    os.symlink(pair.path, link)
    lines = {"a": line_table(str(link), [1], timeout=1.0), "b": line_table(other.path, [2])}
    write_config(lab.config, lines)
    gateway = lab.gateway(metrics=True)
    assert gateway.readyz() == (200, "ok\n")
    master = lab.master(gateway, 1, window=2, interval=0.002)
    master_b = lab.master(gateway, 2, window=2, interval=0.002)
    master.wait_answers(5)

    # Unplug: the node disappears and the far end hangs up.
    mark = gateway.mark()
    lost_at = time.monotonic()
    link.unlink()
    sim.stop()
    pair.close()
    gateway.wait_for(r"line a: .* lost: .*answering 0x0A until it returns", start=mark)
    status, body = gateway.readyz()
    assert status == 503 and "line(s) down: a" in body
    with socket.create_connection(gateway.address, timeout=DEADLINE_S) as probe:
        latencies = []
        for tid in range(1, 11):
            answer, latency = transact(probe, 1, tid)
            assert answer == PATH_UNAVAILABLE
            latencies.append(latency)
    assert max(latencies) < 0.05, latencies  # the response timeout is 1 s
    # Let the reopen back-off reach its ceiling, so the recovery below is the worst case.
    time.sleep(max(0.0, lost_at + 1.3 - time.monotonic()))
    assert gateway.proc.poll() is None

    # Plug back: a new pty behind the same name.
    new_pair, _ = lab.sim([1])
    os.symlink(new_pair.path, lab.dir / "ttyBUS.new")
    mark = gateway.mark()
    returned_at = time.monotonic()
    os.replace(lab.dir / "ttyBUS.new", link)
    with socket.create_connection(gateway.address, timeout=DEADLINE_S) as probe:
        tid = 100
        while True:
            answer, _ = transact(probe, 1, tid)
            if answer == PLC_10:
                break
            assert answer == PATH_UNAVAILABLE
            assert time.monotonic() - returned_at < DEADLINE_S
            tid += 1
            time.sleep(0.002)
    # The read on the wire when the port went away may still be answered once the port is
    # back, so reads that look like it wait out slave 1's late-answer window (2 x its 1 s
    # timeout, from the loss): recovery is within a second of the later of the two.
    recovered = time.monotonic() - max(returned_at, lost_at + 2.0)
    assert recovered < 1.0
    gateway.wait_for(r"line a: back up", start=mark)
    assert gateway.readyz() == (200, "ok\n")
    master.wait_answers(len(master.answers) + 5)
    master.finish()
    master_b.finish()
    master_b.check()
    slowest_b = max(master_b.answers[tid][0] - sent for tid, sent in master_b.sent.items())
    # Far below line a's 1 s timeout: nothing in the loss or the reopen blocks the event loop
    # (the bound leaves room for a loaded 2-core machine).
    assert slowest_b < 0.5, "line b stalled while line a was lost and reopened"
    # The request on the wire when the port went away may be 0x0B; everything else is a
    # reply, or 0x0A while the line was down.
    master.check(PATH_UNAVAILABLE, TARGET_FAILED)
    assert master.closed_at is None
    tally = master.tally()
    assert tally.get(PATH_UNAVAILABLE, 0) > 0 and tally.get(TARGET_FAILED, 0) <= 1
    print(f"\nport loss: 0x0A in at most {max(latencies) * 1000:.1f} ms; "
          f"first good answer {recovered * 1000:.0f} ms after the device returned; "
          f"line b's slowest answer {slowest_b * 1000:.1f} ms")  # fmt: skip


def test_a_write_to_a_vanished_port_is_a_serial_port_error() -> None:
    """The worker answers ``SerialPortError`` with 0x0A; a bare ``OSError`` would kill it."""
    pair = open_pty_pair()
    config = build_config({"lines": {"a": {"device": pair.path, "units": [1]}}})
    port = open_serial(config.lines[0])
    loop = asyncio.new_event_loop()
    lost: list[OSError] = []
    link = SerialLink(port, loop, lambda _data: None, lost.append)
    try:
        pair.close()  # the far end hangs up: writes fail with EIO
        with pytest.raises(SerialPortError, match="write failed"):
            link.write(bytes([1, 3, 0, 0, 0, 1, 0x84, 0x0A]))
        assert link.closed and len(lost) == 1
    finally:
        link.close()
        loop.close()
