"""What ``tcp`` and ``tls`` lines cost: the gateway in front of a Modbus TCP / TLS slave.

``slave-kinds`` runs 10 unpaced masters against the gateway three ways over the
same simulated line: the line on its pty (``kind = "rtu"``, the baseline), then
reached through a second gateway process that serves the pty as a Modbus TCP
slave (``--modbus-tcp``) and as a Modbus/TCP Security slave on its ``tls``
listener (``--modbus-tls``, with client certificates from a throwaway PKI made
for the run), with one request in flight on that connection, then four. The
second gateway is the slave, like socat in ``transports``: its CPU is not
counted, only the measured gateway's CPU per transaction compares.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path

from gateway.sim.pki import Pki, make_pki

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


class SlaveBehindGateway(Server):
    """A slave gateway on the simulator's pty (plain and tls listeners), then the gateway."""

    def __init__(self, command: list[str], workdir: Path, slave_command: list[str]) -> None:
        super().__init__(command, workdir, "server")
        self._slave = Server(slave_command, workdir, "slave")

    def start(self, ready_text: str = "connected to") -> None:
        """Start the slave gateway, then the gateway; wait until its line is connected."""
        self._slave.start("listening on")
        try:
            super().start(ready_text)
        except BenchError:
            self._slave.stop()
            raise

    def stop(self) -> int | None:
        """Stop the gateway, then the slave."""
        status = super().stop()
        self._slave.stop()
        return status


def slave_server(kind: str, pki: Pki, in_flight: int = 1) -> ServerFactory:
    """``python -m gateway --modbus-tcp`` / ``--modbus-tls`` to a gateway serving the pty."""

    def make(workdir: Path, link: str, port: int) -> Server:
        ca, chain, key = pki.ca, pki.server_chain, pki.server_key
        plain, tls = free_port(), free_port()
        slave = [PYTHON, "-m", "gateway", "--serial", link, "--baudrate", str(UNPACED_BAUDRATE)]
        slave += ["--frame-gap", "0", "--listen", f"127.0.0.1:{plain}"]
        slave += ["--tls-listen", f"127.0.0.1:{tls}", "--tls-cert", str(chain)]
        slave += ["--tls-key", str(key), "--tls-ca", str(ca), "--metrics", "off"]
        slave += ["--log-level", "info"]
        command = [PYTHON, "-m", "gateway", "--listen", f"127.0.0.1:{port}", "--metrics", "off"]
        command += ["--log-level", "info", "--timeout", "0.5"]
        if kind == "tcp":
            command += ["--modbus-tcp", f"127.0.0.1:{plain}"]
        else:
            cert, client_key = pki.client("operator")
            command += ["--modbus-tls", f"127.0.0.1:{tls}", "--modbus-tls-cert", cert]
            command += ["--modbus-tls-key", client_key, "--modbus-tls-ca", str(ca)]
        # The load generator's masters all connect from 127.0.0.1: no per-address limit.
        config = workdir / "gateway.toml"
        config.write_text(
            "[server]\nmax_connections_per_source = 0\n"
            f'[lines.default]\nunits = ["1-247"]\nmax_in_flight = {in_flight}\n'
        )
        command += ["--config", str(config)]
        slave_config = workdir / "slave.toml"
        slave_config.write_text("[server]\nmax_connections_per_source = 0\n")
        slave += ["--config", str(slave_config)]
        return SlaveBehindGateway(command, workdir, slave)

    return make


def slave_kinds(bench: Bench) -> ScenarioResult:
    """Transactions/s and gateway CPU per transaction: rtu vs tcp vs tls lines, 10 masters."""
    serial = bench.unpaced(MASTERS)
    runs: list[tuple[str, Run]] = [("rtu", serial)]
    with tempfile.TemporaryDirectory(prefix="bench-pki-") as directory:
        pki = make_pki(Path(directory))
        for in_flight in (1, 4):
            for kind in ("tcp", "tls"):
                run = bench._run(
                    f"gateway, {kind} line (max_in_flight {in_flight}) to a slave gateway, "
                    f"unpaced, {MASTERS} masters x 1",
                    SimOptions(units=HEALTHY_UNITS), slave_server(kind, pki, in_flight),
                    bench._poll_spec(MASTERS, HEALTHY_UNITS),
                )  # fmt: skip
                runs.append((kind if in_flight == 1 else f"{kind}, in flight {in_flight}", run))
    table = Table(
        f"Slave kinds: {MASTERS} masters, FC03 x 10 across 4 slaves, unpaced simulator "
        "(tcp, tls: a second gateway serves the same pty as the Modbus TCP / TLS slave)",
        ["kind", "tx/s", "p50 ms", "p99 ms", "gw CPU us/tx", "other load", "wrong", "errors"],
    )
    for label, run in runs:
        load = run.load
        table.rows.append([
            label, _fmt(load.ok_per_s, 0), _fmt(load.latency_ms["p50"], 2),
            _fmt(load.latency_ms["p99"], 2), _fmt(run.cpu_us_per_tx),
            f"{run.background_cores:.2f}", str(load.wrong_answers), _errors_text(load),
        ])  # fmt: skip
    figures = {
        kind: {"tx_per_s": run.load.ok_per_s, "gateway_cpu_us_per_tx": run.cpu_us_per_tx,
               "latency_ms": run.load.latency_ms, "run": run.as_json()}
        for kind, run in runs
    }  # fmt: skip
    wrong = sum(run.load.wrong_answers for kind, run in runs if kind != "rtu")
    checks = [Check("tcp and tls lines: wrong answers", wrong, "0", wrong == 0)]
    notes = [
        "tcp, tls: one request in flight on the slave connection unless the row says more "
        "(max_in_flight); the slave gateway's CPU is not counted; the load starts once the "
        "gateway has logged its connection",
    ]
    return ScenarioResult("slave-kinds", figures, [table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"slave-kinds": slave_kinds}
