"""What ``max_in_flight`` buys on a ``tcp`` line: several requests outstanding at once.

``in-flight`` runs 10 unpaced masters against the gateway with a ``kind = "tcp"`` line to
a second gateway process that serves the simulator's pty as a Modbus TCP slave (as in
``slave-kinds``; its CPU is not counted), once with ``max_in_flight = 1`` (the default)
and once with 4. With 4, the slave gateway already holds the next requests when an
answer leaves, so the round trip between the two gateways no longer idles its line.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from .procs import PYTHON, Server, SimOptions, free_port
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
from .slave_kind_scenarios import SlaveBehindGateway

MASTERS = 10
LIMITS = (1, 4)


def tcp_line_server(max_in_flight: int) -> ServerFactory:
    """The gateway with a tcp line (``max_in_flight``) to a gateway serving the pty."""

    def make(workdir: Path, link: str, port: int) -> Server:
        plain = free_port()
        slave_config = workdir / "slave.toml"
        slave_config.write_text("[server]\nmax_connections_per_source = 0\n")
        slave = [PYTHON, "-m", "gateway", "--serial", link, "--baudrate", str(UNPACED_BAUDRATE)]
        slave += ["--frame-gap", "0", "--listen", f"127.0.0.1:{plain}", "--metrics", "off"]
        slave += ["--log-level", "info", "--config", str(slave_config)]
        config = workdir / "gateway.toml"
        config.write_text(
            '[server]\nmax_connections_per_source = 0\n\n[lines.plc]\nkind = "tcp"\n'
            f'address = "127.0.0.1:{plain}"\nunits = ["1-247"]\ntimeout = 0.5\n'
            f"max_in_flight = {max_in_flight}\n"
        )
        command = [PYTHON, "-m", "gateway", "--listen", f"127.0.0.1:{port}", "--metrics", "off"]
        command += ["--log-level", "info", "--config", str(config)]
        return SlaveBehindGateway(command, workdir, slave)

    return make


def in_flight(bench: Bench) -> ScenarioResult:
    """Transactions/s and gateway CPU per transaction: a tcp line, max_in_flight 1 vs 4."""
    runs: list[tuple[int, Run]] = []
    for limit in LIMITS:
        run = bench._run(
            f"gateway, tcp line (max_in_flight {limit}) to a slave gateway, unpaced, "
            f"{MASTERS} masters x 1",
            SimOptions(units=HEALTHY_UNITS), tcp_line_server(limit),
            bench._poll_spec(MASTERS, HEALTHY_UNITS),
        )  # fmt: skip
        runs.append((limit, run))
    table = Table(
        f"Requests in flight on a tcp line: {MASTERS} masters, FC03 x 10 across 4 slaves, "
        "unpaced simulator behind a second gateway (the Modbus TCP slave)",
        ["max_in_flight", "tx/s", "p50 ms", "p99 ms", "gw CPU us/tx", "other load", "wrong",
         "errors"],
    )  # fmt: skip
    for limit, run in runs:
        load = run.load
        table.rows.append([
            str(limit), _fmt(load.ok_per_s, 0), _fmt(load.latency_ms["p50"], 2),
            _fmt(load.latency_ms["p99"], 2), _fmt(run.cpu_us_per_tx),
            f"{run.background_cores:.2f}", str(load.wrong_answers), _errors_text(load),
        ])  # fmt: skip
    figures = {
        f"max_in_flight_{limit}": {
            "tx_per_s": run.load.ok_per_s, "gateway_cpu_us_per_tx": run.cpu_us_per_tx,
            "latency_ms": run.load.latency_ms, "run": run.as_json(),
        }
        for limit, run in runs
    }  # fmt: skip
    wrong = sum(run.load.wrong_answers for _, run in runs)
    checks = [Check("tcp line, max_in_flight 1 and 4: wrong answers", wrong, "0", wrong == 0)]
    notes = ["the slave gateway's CPU is not counted; the load starts once the gateway has "
             "logged its connection"]  # fmt: skip
    return ScenarioResult("in-flight", figures, [table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"in-flight": in_flight}
