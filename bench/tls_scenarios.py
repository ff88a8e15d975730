"""What Modbus/TCP Security costs: connection set-up, and CPU per transaction over TLS.

``tls`` makes a throwaway PKI (``gateway.sim.pki``), then

- opens connections one after the other to a gateway that serves the same line on
  a plain and a ``tls`` listener, each connection timed from ``connect()`` to the
  answer of its first read (so a TLS 1.3 handshake is complete: the server checks
  the client's certificate after the client thinks it is done), for plain TCP, TLS 1.2
  and TLS 1.3, with the gateway's CPU per connection;
- runs 10 unpaced masters over TLS 1.3 against the gateway on an unpaced pty, between
  two runs of the same masters over plain TCP, and compares CPU per transaction.
"""

from __future__ import annotations

import socket
import ssl
import struct
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from gateway.sim.pki import make_pki

from .loadgen import process_cpu_seconds
from .procs import PYTHON, Server, SimOptions, Simulator, Stack, free_port
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
    gateway_server,
)

MASTERS = 10
CONNECTIONS = (200, 60, 15)  #: full, --quick, --tiny
WARMUP_CONNECTIONS = 5
_READ = struct.pack(">HHHB", 1, 0, 6, 1) + bytes.fromhex("03 03E8 000A")  # 10 registers at 1000
_ANSWER_LENGTH = 7 + 2 + 20


def tls_gateway_server(files: dict[str, str], plain_port: int | None = None) -> ServerFactory:
    """``python -m gateway`` with a tls listener on the run's port (and a plain one if asked)."""

    def make(workdir: Path, link: str, port: int) -> Server:
        command = [PYTHON, "-m", "gateway", "--serial", link, "--baudrate", str(UNPACED_BAUDRATE)]
        command += ["--frame-gap", "0", "--metrics", "off", "--log-level", "info"]
        command += ["--tls-listen", f"127.0.0.1:{port}", "--tls-cert", files["server_cert"]]
        command += ["--tls-key", files["server_key"], "--tls-ca", files["ca"]]
        if plain_port is not None:
            command += ["--listen", f"127.0.0.1:{plain_port}"]
        config = workdir / "gateway.toml"
        config.write_text("[server]\nmax_connections_per_source = 0\n")
        command += ["--config", str(config)]
        return Server(command, workdir, "server")

    return make


def _client(files: dict[str, str], version: ssl.TLSVersion) -> ssl.SSLContext:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(cafile=files["ca"])
    context.load_cert_chain(files["cert"], files["key"])
    context.minimum_version = context.maximum_version = version
    return context


def _first_answer(port: int, context: ssl.SSLContext | None) -> float:
    """Seconds from ``connect()`` to the complete answer of one read; the connection is closed."""
    started = time.perf_counter()
    sock: socket.socket = socket.create_connection(("127.0.0.1", port), timeout=10.0)
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if context is not None:
            sock = context.wrap_socket(sock, server_hostname="localhost")
        sock.sendall(_READ)
        answer = b""
        while len(answer) < _ANSWER_LENGTH:
            chunk = sock.recv(_ANSWER_LENGTH - len(answer))
            if not chunk:
                raise ConnectionError(f"closed after {answer.hex()}")
            answer += chunk
        if answer[7] != 0x03:
            raise ConnectionError(f"exception answer {answer.hex()}")
        return time.perf_counter() - started
    finally:
        sock.close()


def _percentile(values: list[float], share: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(share * (len(ordered) - 1)))]


def _connection_setup(
    bench: Bench, files: dict[str, str], workdir: Path
) -> tuple[Table, dict[str, dict[str, float]]]:
    count = int(bench.timing.pick(*CONNECTIONS))
    plain_port = free_port()
    simulator = Simulator(SimOptions(units=HEALTHY_UNITS), workdir)
    tls_port = free_port()
    server = tls_gateway_server(files, plain_port)(workdir, str(simulator.link), tls_port)
    kinds: list[tuple[str, int, ssl.SSLContext | None]] = [
        ("plain TCP", plain_port, None),
        ("TLS 1.2", tls_port, _client(files, ssl.TLSVersion.TLSv1_2)),
        ("TLS 1.3", tls_port, _client(files, ssl.TLSVersion.TLSv1_3)),
    ]
    table = Table(
        f"Connection set-up: connect() to the first read's answer, {count} connections one "
        "after the other (EC P-256 certificates, client certificate checked)",
        ["protocol", "p50 ms", "p99 ms", "gateway CPU ms/connection"],
    )
    figures: dict[str, dict[str, float]] = {}
    bench.progress(f"  connection set-up, {count} connections each ...")
    with Stack(simulator, server):
        for label, port, context in kinds:
            for _ in range(WARMUP_CONNECTIONS):
                _first_answer(port, context)
            cpu_before = process_cpu_seconds(server.pid) or 0.0
            times = [_first_answer(port, context) for _ in range(count)]
            cpu = (process_cpu_seconds(server.pid) or 0.0) - cpu_before
            figures[label] = {
                "p50_ms": 1000 * _percentile(times, 0.5),
                "p99_ms": 1000 * _percentile(times, 0.99),
                "gateway_cpu_ms_per_connection": 1000 * cpu / count,
            }
            table.rows.append([
                label, f"{figures[label]['p50_ms']:.2f}", f"{figures[label]['p99_ms']:.2f}",
                f"{figures[label]['gateway_cpu_ms_per_connection']:.2f}",
            ])  # fmt: skip
    return table, figures


def tls_overhead(bench: Bench) -> ScenarioResult:
    """Modbus/TCP Security: connection set-up, and CPU per transaction over TLS vs TCP."""
    with tempfile.TemporaryDirectory(prefix="modbus-bench-pki-") as temp:
        pki = make_pki(Path(temp))
        cert, key = pki.client("operator")
        files = {
            "ca": str(pki.ca), "cert": cert, "key": key,
            "server_cert": str(pki.server_chain), "server_key": str(pki.server_key),
        }  # fmt: skip
        setup_table, setup = _connection_setup(bench, files, Path(temp))
        plain_before = bench.unpaced(MASTERS)
        tls_spec = bench._poll_spec(
            MASTERS, HEALTHY_UNITS, tls={k: files[k] for k in ("ca", "cert", "key")}
        )
        over_tls = bench._run(
            f"gateway over TLS 1.3, unpaced, {MASTERS} masters x 1",
            SimOptions(units=HEALTHY_UNITS), tls_gateway_server(files), tls_spec,
        )  # fmt: skip
        plain_after = bench._run(
            f"gateway, unpaced, {MASTERS} masters x 1, after the TLS run",
            SimOptions(units=HEALTHY_UNITS), gateway_server(UNPACED_BAUDRATE, frame_gap=0.0),
            bench._poll_spec(MASTERS, HEALTHY_UNITS),
        )  # fmt: skip
    table = Table(
        f"Modbus/TCP Security vs plain Modbus TCP: {MASTERS} masters, unpaced pty, --frame-gap 0 "
        "(plain runs before and after)",
        ["transport", "tx/s", "p50 ms", "p99 ms", "gw CPU us/tx", "other load", "wrong",
         "errors"],
    )  # fmt: skip
    rows: list[tuple[str, Run]] = [
        ("plain TCP (before)", plain_before),
        ("TLS 1.3", over_tls),
        ("plain TCP (after)", plain_after),
    ]
    for label, run in rows:
        load = run.load
        table.rows.append([
            label, _fmt(load.ok_per_s, 0), _fmt(load.latency_ms["p50"], 2),
            _fmt(load.latency_ms["p99"], 2), _fmt(run.cpu_us_per_tx),
            f"{run.background_cores:.2f}", str(load.wrong_answers), _errors_text(load),
        ])  # fmt: skip
    plain_cpu = (plain_before.cpu_us_per_tx + plain_after.cpu_us_per_tx) / 2
    ratio = over_tls.cpu_us_per_tx / plain_cpu if plain_cpu else 0.0
    table.rows.append(["TLS / plain (mean)", "", "", "", f"{ratio:.2f}x", "", "", ""])
    wrong = over_tls.load.wrong_answers + plain_after.load.wrong_answers
    figures = {
        "connection_setup": setup,
        "plain_cpu_us_per_tx": [plain_before.cpu_us_per_tx, plain_after.cpu_us_per_tx],
        "tls_cpu_us_per_tx": over_tls.cpu_us_per_tx,
        "tls_over_plain_cpu": ratio,
        "tls_tx_per_s": over_tls.load.ok_per_s,
        "tls_run": over_tls.as_json(),
        "plain_after_run": plain_after.as_json(),
    }
    checks = [
        Check("TLS: wrong answers", over_tls.load.wrong_answers, "0",
              over_tls.load.wrong_answers == 0),
    ]  # fmt: skip
    notes = [
        "set-up time includes one read's round trip through the line (about 0.3 ms here), the "
        "same for every protocol; TLS sessions are not resumed (each connection is a full "
        "handshake, the worst case for masters that reconnect)",
        "other load = CPU cores used by everything else on the machine during the window",
    ]
    return ScenarioResult("tls", figures, [setup_table, table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"tls": tls_overhead}
