"""What ``tcp`` and ``tls`` lines cost: the gateway in front of a Modbus TCP / TLS slave.

``slave-kinds`` runs 10 unpaced masters against the gateway: first with its line
on the simulator's pty (``kind = "rtu"``, the baseline); then on a ``tcp`` and a
``tls`` line to the simulator's own Modbus TCP listener (``bench.slaves
--modbus-tcp-listen``, with ``--tls-cert/--tls-key/--tls-ca`` for Modbus/TCP
Security; client certificates from a throwaway PKI made for the run), with one
request in flight on that connection, then four; then through a second gateway
process serving the pty as the Modbus TCP slave and on its ``tls`` listener. The
slaves' CPU is not counted: the measured gateway's CPU per transaction compares.
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
from .transport_scenarios import ConnectedGateway

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


def sim_slave_server(kind: str, pki: Pki, slave_port: int, in_flight: int) -> ServerFactory:
    """``python -m gateway --modbus-tcp`` / ``--modbus-tls`` to the simulator's own listener."""

    def make(workdir: Path, _link: str, port: int) -> Server:
        command = [PYTHON, "-m", "gateway", "--listen", f"127.0.0.1:{port}", "--metrics", "off"]
        command += ["--log-level", "info", "--timeout", "0.5"]
        if kind == "tcp":
            command += ["--modbus-tcp", f"127.0.0.1:{slave_port}"]
        else:
            cert, key = pki.client("operator")
            command += ["--modbus-tls", f"127.0.0.1:{slave_port}", "--modbus-tls-cert", cert]
            command += ["--modbus-tls-key", key, "--modbus-tls-ca", str(pki.ca)]
        config = workdir / "gateway.toml"
        config.write_text(
            "[server]\nmax_connections_per_source = 0\n"
            f'[lines.default]\nunits = ["1-247"]\nmax_in_flight = {in_flight}\n'
        )
        command += ["--config", str(config)]
        return ConnectedGateway(command, workdir, "server")

    return make


def slave_kinds(bench: Bench) -> ScenarioResult:
    """Transactions/s and gateway CPU per transaction: rtu vs tcp vs tls lines, 10 masters."""
    serial = bench.unpaced(MASTERS)
    runs: list[tuple[str, Run]] = [("rtu", serial)]
    with tempfile.TemporaryDirectory(prefix="bench-pki-") as directory:
        pki = make_pki(Path(directory))
        files = (str(pki.server_chain), str(pki.server_key), str(pki.ca))
        for in_flight in (1, 4):
            for kind in ("tcp", "tls"):
                slave_port = free_port()
                options = SimOptions(
                    units=HEALTHY_UNITS, modbus_tcp_listen=f"127.0.0.1:{slave_port}",
                    tls_files=files if kind == "tls" else None,
                )  # fmt: skip
                run = bench._run(
                    f"gateway, {kind} line (max_in_flight {in_flight}) to the simulator's "
                    f"{kind} slave, {MASTERS} masters x 1",
                    options, sim_slave_server(kind, pki, slave_port, in_flight),
                    bench._poll_spec(MASTERS, HEALTHY_UNITS),
                )  # fmt: skip
                suffix = "" if in_flight == 1 else f", in flight {in_flight}"
                runs.append((f"{kind} (simulator){suffix}", run))
        for kind in ("tcp", "tls"):
            run = bench._run(
                f"gateway, {kind} line to a slave gateway on the pty, {MASTERS} masters x 1",
                SimOptions(units=HEALTHY_UNITS), slave_server(kind, pki),
                bench._poll_spec(MASTERS, HEALTHY_UNITS),
            )  # fmt: skip
            runs.append((f"{kind} (slave gateway)", run))
    table = Table(
        f"Slave kinds: {MASTERS} masters, FC03 x 10 across 4 slaves, unpaced simulator "
        "(tcp, tls: the simulator's own Modbus TCP / TLS listener, or a second gateway "
        "serving the pty)",
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
        "(max_in_flight); the simulator's and the slave gateway's CPU is not counted; the load "
        "starts once the gateway has logged its connection",
    ]
    return ScenarioResult("slave-kinds", figures, [table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"slave-kinds": slave_kinds}
