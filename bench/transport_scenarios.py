"""What a line kind costs: an ``rtu-over-tcp`` line against the same line on a serial port.

``transports`` runs 10 unpaced masters against the gateway twice over the same
simulated line: once with the line on its pty (``kind = "rtu"``), once reached
through a serial device server (socat ``TCP-LISTEN`` bridged to the pty, as a
Moxa NPort in raw socket mode) with ``--rtu-over-tcp``. The device server's own
CPU is not the gateway's: the gateway's CPU per transaction is what compares.
A third run puts the same slaves behind the simulator's Modbus TCP slave
(``bench.slaves --modbus-tcp-listen``) and the gateway on a ``kind = "tcp"``
line to it (``--modbus-tcp``): TCP-to-TCP proxying.
"""

from __future__ import annotations

import shutil
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

from .procs import PYTHON, BenchError, Server, SimOptions, free_port
from .scenarios import (
    HEALTHY_UNITS,
    UNPACED_BAUDRATE,
    Bench,
    Check,
    Run,
    ScenarioResult,
    ServerFactory,
    Table,
    _errors_text,
    _fmt,
)

MASTERS = 10
_SOCAT_READY_S = 10.0


class DeviceServerGateway(Server):
    """socat as a serial device server in front of the simulator's pty, then the gateway."""

    def __init__(self, command: list[str], workdir: Path, device_port: int, link: str) -> None:
        super().__init__(command, workdir, "server")
        self._device_port = device_port
        self._link = link
        self._socat: subprocess.Popen[bytes] | None = None

    def start(self, ready_text: str = "connected to") -> None:
        """Start socat, then the gateway, and wait until the gateway has connected."""
        socat = shutil.which("socat")
        if socat is None:
            raise BenchError("socat is not installed (apt-get install socat)")
        self._socat = subprocess.Popen(
            [socat, f"TCP-LISTEN:{self._device_port},bind=127.0.0.1,reuseaddr,nodelay",
             f"FILE:{self._link},raw,echo=0"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        deadline = time.monotonic() + _SOCAT_READY_S
        while not _listening(self._device_port):
            if self._socat.poll() is not None or time.monotonic() > deadline:
                raise BenchError("socat did not listen")
            time.sleep(0.02)
        super().start(ready_text)

    def stop(self) -> int | None:
        """Stop the gateway, then the device server."""
        status = super().stop()
        if self._socat is not None:
            self._socat.kill()
            self._socat.wait()
            self._socat = None
        return status


def _listening(port: int) -> bool:
    """True when something listens on 127.0.0.1:``port`` (read from /proc, no connection made)."""
    wanted = f"0100007F:{port:04X}"
    try:
        with open("/proc/net/tcp", encoding="ascii") as table:
            rows = table.read().splitlines()[1:]
    except OSError:
        return False
    return any(row.split()[1] == wanted and row.split()[3] == "0A" for row in rows)


def rtu_over_tcp_server() -> ServerFactory:
    """``python -m gateway --rtu-over-tcp`` to a socat device server on the simulator's pty."""

    def make(workdir: Path, link: str, port: int) -> Server:
        device_port = free_port()
        command = [PYTHON, "-m", "gateway", "--rtu-over-tcp", f"127.0.0.1:{device_port}"]
        command += ["--baudrate", str(UNPACED_BAUDRATE), "--listen", f"127.0.0.1:{port}"]
        command += ["--metrics", "off", "--log-level", "info"]
        config = workdir / "gateway.toml"
        config.write_text("[server]\nmax_connections_per_source = 0\n")
        command += ["--config", str(config)]
        return DeviceServerGateway(command, workdir, device_port, link)

    return make


class ConnectedGateway(Server):
    """The gateway, ready once its network line has connected (not merely listening)."""

    def start(self, ready_text: str = "connected to") -> None:
        """Start and wait for the line's connection."""
        super().start(ready_text)


def tcp_line_server(slave_port: int) -> ServerFactory:
    """``python -m gateway --modbus-tcp`` to the simulator's Modbus TCP slave on ``slave_port``."""

    def make(workdir: Path, _link: str, port: int) -> Server:
        command = [PYTHON, "-m", "gateway", "--modbus-tcp", f"127.0.0.1:{slave_port}"]
        command += ["--listen", f"127.0.0.1:{port}", "--metrics", "off", "--log-level", "info"]
        config = workdir / "gateway.toml"
        config.write_text("[server]\nmax_connections_per_source = 0\n")
        command += ["--config", str(config)]
        return ConnectedGateway(command, workdir, "server")

    return make


def transports(bench: Bench) -> ScenarioResult:
    """Transactions/s and gateway CPU per transaction: rtu vs rtu-over-tcp, 10 masters."""
    serial = bench.unpaced(MASTERS)
    over_tcp = bench._run(
        f"gateway, rtu-over-tcp through socat, unpaced, {MASTERS} masters x 1",
        SimOptions(units=HEALTHY_UNITS), rtu_over_tcp_server(),
        bench._poll_spec(MASTERS, HEALTHY_UNITS),
    )  # fmt: skip
    slave_port = free_port()
    tcp = bench._run(
        f"gateway, tcp to the simulator's Modbus TCP slave, {MASTERS} masters x 1",
        SimOptions(units=HEALTHY_UNITS, modbus_tcp_listen=f"127.0.0.1:{slave_port}"),
        tcp_line_server(slave_port), bench._poll_spec(MASTERS, HEALTHY_UNITS),
    )  # fmt: skip
    table = Table(
        f"Line kinds: {MASTERS} masters, FC03 x 10 across 4 slaves, unpaced simulator "
        "(rtu-over-tcp: socat as the device server in front of the same pty; "
        "tcp: the simulator's Modbus TCP slave)",
        ["kind", "tx/s", "p50 ms", "p99 ms", "gw CPU us/tx", "other load", "wrong", "errors"],
    )
    rows: list[tuple[str, Run]] = [
        ("rtu (pty)", serial), ("rtu-over-tcp", over_tcp), ("tcp", tcp)
    ]  # fmt: skip
    for label, run in rows:
        load = run.load
        table.rows.append([
            label, _fmt(load.ok_per_s, 0), _fmt(load.latency_ms["p50"], 2),
            _fmt(load.latency_ms["p99"], 2), _fmt(run.cpu_us_per_tx),
            f"{run.background_cores:.2f}", str(load.wrong_answers), _errors_text(load),
        ])  # fmt: skip
    figures = {
        kind: {"tx_per_s": run.load.ok_per_s, "gateway_cpu_us_per_tx": run.cpu_us_per_tx,
               "latency_ms": run.load.latency_ms, "run": run.as_json()}
        for kind, run in (("rtu", serial), ("rtu-over-tcp", over_tcp), ("tcp", tcp))
    }  # fmt: skip
    wrong = over_tcp.load.wrong_answers + tcp.load.wrong_answers
    checks = [
        Check("rtu-over-tcp: wrong answers", over_tcp.load.wrong_answers, "0",
              over_tcp.load.wrong_answers == 0),
        Check("tcp: wrong answers", tcp.load.wrong_answers, "0", tcp.load.wrong_answers == 0),
    ]  # fmt: skip
    notes = [
        "rtu-over-tcp: frame_gap 0 (the default of the kind); the load starts once the gateway "
        "has logged its connection to the device server; socat's CPU is not counted",
        "tcp: one request in flight on the gateway's connection to the slave (the default); "
        "the simulator's CPU is not counted",
    ]
    return ScenarioResult("transports", figures, [table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"transports": transports}
