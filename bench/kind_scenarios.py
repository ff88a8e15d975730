"""Scenarios per line kind: what a Modbus ASCII line costs and carries.

``ascii`` runs the unpaced benchmark (10 masters, FC03 x 10 across 4 slaves, the gateway's
overhead alone) on an ASCII line and on an RTU line in the same run, so the ratio holds
whatever else the machine does; then a paced 9600 baud ASCII line, whose utilisation is
measured against the wire's own budget: ':' + hex + CR LF is 17 characters for the request
and 51 for the answer, one character time of turnaround on each side (``ascii_budget``).
ptys refuse 7 data bits, so the lines run 8N1; 7E1 has the same 10 bits per character,
so the paced figures are those of 9600 7E1.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from gateway.core.timing import character_time

from .procs import SimOptions
from .scenarios import (
    HEALTHY_UNITS,
    REALTIME_SIMULATOR,
    UNPACED_BAUDRATE,
    Bench,
    Check,
    Run,
    ScenarioResult,
    Table,
    _errors_text,
    _fmt,
    gateway_server,
)
from .wire import SLAVE_PROCESSING_S, WireBudget

ASCII_MASTERS = 10
ASCII_PACED_BAUDRATE = 9600
ASCII_FC03_REQUEST_CHARS = 17  # ':' + 2 x (unit, function, address 2, quantity 2, LRC) + CR LF


def ascii_fc03_response_chars(quantity: int) -> int:
    """':' + 2 x (unit, function, byte count, 2 x quantity, LRC) + CR LF."""
    return 1 + 2 * (4 + 2 * quantity) + 2


def ascii_budget(
    baudrate: int, quantity: int = 10, processing: float = SLAVE_PROCESSING_S
) -> WireBudget:
    """The wire budget of FC03 x ``quantity`` on an ASCII line (10-bit characters).

    The gap on each side is one character time (the gateway's ASCII turnaround), in the
    place RTU's t3.5 takes in ``WireBudget``.
    """
    char = character_time(baudrate, 7, "E", 1)
    return WireBudget(
        baudrate=baudrate,
        request_s=ASCII_FC03_REQUEST_CHARS * char,
        response_s=ascii_fc03_response_chars(quantity) * char,
        t35_s=char,
        turnaround_s=processing,
    )


def _unpaced_row(label: str, run: Run) -> list[str]:
    load = run.load
    return [
        label, _fmt(load.ok_per_s, 0), _fmt(load.latency_ms["p50"], 2),
        _fmt(load.latency_ms["p99"], 2), _fmt(run.cpu_us_per_tx),
        f"{run.background_cores:.2f}", str(load.wrong_answers), _errors_text(load),
    ]  # fmt: skip


def ascii_line(bench: Bench) -> ScenarioResult:
    """Issue 11: an ASCII line unpaced (10 masters) beside RTU, and paced at 9600 baud."""
    unpaced = Table(
        f"Unpaced pty, --frame-gap 0, {ASCII_MASTERS} masters, FC03 x 10 across 4 slaves",
        ["line", "tx/s", "p50 ms", "p99 ms", "gw CPU us/tx", "other load", "wrong", "errors"],
    )
    runs: dict[str, Run] = {}
    for kind in ("ascii", "rtu", "ascii "):  # ASCII before and after RTU: averaged
        framing = kind.strip()
        run = bench._run(
            f"gateway, unpaced {framing} line, {ASCII_MASTERS} masters",
            SimOptions(units=HEALTHY_UNITS, framing=framing),
            gateway_server(UNPACED_BAUDRATE, frame_gap=0.0, framing=framing),
            bench._poll_spec(ASCII_MASTERS, HEALTHY_UNITS),
        )
        runs[kind] = run
        unpaced.rows.append(_unpaced_row(framing, run))
    first, rtu, second = runs["ascii"], runs["rtu"], runs["ascii "]
    ascii_cpu = (first.cpu_us_per_tx + second.cpu_us_per_tx) / 2
    ascii_tx = (first.load.ok_per_s + second.load.ok_per_s) / 2
    cpu_ratio = ascii_cpu / rtu.cpu_us_per_tx if rtu.cpu_us_per_tx else 0.0

    budget = ascii_budget(ASCII_PACED_BAUDRATE)
    spec = bench._poll_spec(ASCII_MASTERS, HEALTHY_UNITS, duration=bench.timing.paced_window)
    spec.warmup = max(spec.warmup, 1.0)
    paced = bench._run(
        f"paced ascii {ASCII_PACED_BAUDRATE} baud",
        SimOptions(
            units=HEALTHY_UNITS,
            baudrate=ASCII_PACED_BAUDRATE,
            turnaround=budget.sim_turnaround_s,
            realtime=REALTIME_SIMULATOR,
            framing="ascii",
        ),
        gateway_server(ASCII_PACED_BAUDRATE, framing="ascii"),
        spec,
    )
    utilisation = paced.load.ok_per_s / budget.max_per_s
    paced_table = Table(
        f"Paced ASCII line, {ASCII_PACED_BAUDRATE} baud (10-bit characters, as 7E1), "
        f"{ASCII_MASTERS} masters, FC03 x 10",
        ["tx/s", "wire max", "util.", "p50 ms", "p99 ms", "wrong", "errors"],
    )
    paced_table.rows.append([
        _fmt(paced.load.ok_per_s), _fmt(budget.max_per_s), f"{utilisation:.3f}",
        _fmt(paced.load.latency_ms["p50"]), _fmt(paced.load.latency_ms["p99"]),
        str(paced.load.wrong_answers), _errors_text(paced.load),
    ])  # fmt: skip
    all_runs = [first, rtu, second, paced]
    wrong = sum(run.load.wrong_answers for run in all_runs)
    figures: dict[str, Any] = {
        "unpaced_ascii_tx_per_s": ascii_tx,
        "unpaced_ascii_cpu_us_per_tx": ascii_cpu,
        "unpaced_rtu_tx_per_s": rtu.load.ok_per_s,
        "unpaced_rtu_cpu_us_per_tx": rtu.cpu_us_per_tx,
        "ascii_over_rtu_cpu": cpu_ratio,
        "paced_9600_tx_per_s": paced.load.ok_per_s,
        "paced_9600_wire_max_per_s": budget.max_per_s,
        "paced_9600_utilisation": utilisation,
        "runs": [run.as_json() for run in all_runs],
    }
    checks = [
        Check("ascii wrong answers", wrong, "0", wrong == 0),
        Check("paced ascii 9600 utilisation", utilisation, ">= 0.95", utilisation >= 0.95),
    ]
    notes = [
        f"ASCII CPU per transaction = {cpu_ratio:.2f} x RTU's in the same run "
        "(hex encoding, LRC, frames twice as long on the pty)",
        "the paced line runs 8N1 on the pty (ptys refuse 7 data bits): 10 bits per "
        "character, as 7E1",
    ]
    return ScenarioResult("ascii", figures, [unpaced, paced_table], checks, wrong, notes)


SCENARIOS: dict[str, Callable[[Bench], ScenarioResult]] = {"ascii": ascii_line}
