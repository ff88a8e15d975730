"""The fixtures: a simulated RTU line on a real pty, a running gateway, the test PKI; the test
tiers and the hypothesis profile. What the fixtures build is in ``tests/helpers.py``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Mapping
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives import serialization
from hypothesis import settings as hypothesis_settings

from gateway.sim import SimulatedDevice, SimulatedLine, UnitFaults
from gateway.sim import open_pty_pair as _open_pty_pair
from gateway.sim.pki import Pki, make_pki
from tests.helpers import (
    BenchRun,
    GatewayFactory,
    GatewayOnSim,
    LogCollector,
    RunningGateway,
    SimBus,
    SimFactory,
    TinyBench,
    run_tiny_bench,
)

# --------------------------------------------------------------------------- hypothesis

# Under CI (``CI`` set) the property tests draw the same examples on every run: a run that
# gates a change answers for that change, not for whatever a random draw finds that day.
# Elsewhere each run draws anew (and keeps what failed in .hypothesis/): that is where new
# sequences are looked for.
hypothesis_settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI", "").lower() not in ("", "0", "false", "no"):
    hypothesis_settings.load_profile("ci")


# --------------------------------------------------------------------------- test tiers

#: Every test under this directory is marked ``e2e`` (see ``pytest_collection_modifyitems``).
E2E_DIRECTORY = Path(__file__).resolve().parent / "e2e"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark the tests under tests/e2e ``e2e`` before ``-m`` selects, so that a new file
    there cannot join the fast tier by forgetting its marker."""
    e2e = pytest.mark.e2e
    for item in items:
        if item.path.resolve().is_relative_to(E2E_DIRECTORY):
            item.add_marker(e2e)


@pytest.fixture
def access_log() -> Iterator[LogCollector]:
    """The records of the ``gateway.access`` logger while the test runs."""
    collector = LogCollector()
    logger = logging.getLogger("gateway.access")
    logger.addHandler(collector)
    try:
        yield collector
    finally:
        logger.removeHandler(collector)


@pytest.fixture
def make_sim() -> Iterator[SimFactory]:
    """``make_sim({1: plc(1)}, faults={1: UnitFaults(silent=True)}, baudrate=None, ...)``.

    Returns a started ``SimBus``; other keywords go to ``SimulatedLine``. Lines are
    stopped (re-raising any error of the simulator thread) and ptys closed at teardown.
    """
    with ExitStack() as stack:

        def factory(
            devices: Mapping[int, SimulatedDevice],
            *,
            faults: Mapping[int, UnitFaults] | None = None,
            **options: Any,
        ) -> SimBus:
            pair = _open_pty_pair()
            stack.callback(pair.close)
            line = SimulatedLine(pair.sim_fd, devices, **options)
            for unit, unit_faults in (faults or {}).items():
                line.set_faults(unit, unit_faults)
            line.start()
            stack.callback(line.stop)
            return SimBus(pair, line)

        yield factory


@pytest.fixture
def make_gateway(make_sim: SimFactory) -> Iterator[GatewayFactory]:
    """``make_gateway(raw_config_tables)`` → a ready ``RunningGateway``, stopped at teardown.

    ``server.listen`` and ``metrics.listen`` default to 127.0.0.1:0. Depends on
    ``make_sim`` so that gateways stop before the simulated lines they talk to.
    """
    gateways: list[RunningGateway] = []

    def factory(raw: Mapping[str, Any]) -> RunningGateway:
        tables = {
            key: dict(value) if isinstance(value, dict) else value for key, value in raw.items()
        }
        tables.setdefault("server", {}).setdefault("listen", "127.0.0.1:0")
        tables.setdefault("metrics", {}).setdefault("listen", "127.0.0.1:0")
        running = RunningGateway(tables)
        gateways.append(running)
        return running

    yield factory
    for running in reversed(gateways):
        running.stop()


@pytest.fixture
def gateway_with(make_sim: SimFactory, make_gateway: GatewayFactory) -> GatewayOnSim:
    """The common case in one call: one simulated line (``a``) and a gateway in front of it.

    ``gateway_with({1: plc(1)}, sim={"baudrate": 19200}, line={"timeout": 0.1},
    server={"max_pipeline": 4}, routes=[...])`` routes every simulated unit to
    line ``a`` and returns ``(sim, gateway)``.
    """

    def factory(
        devices: Mapping[int, SimulatedDevice],
        *,
        sim: Mapping[str, Any] | None = None,
        line: Mapping[str, Any] | None = None,
        server: Mapping[str, Any] | None = None,
        routes: list[dict[str, Any]] | None = None,
    ) -> tuple[SimBus, RunningGateway]:
        bus = make_sim(devices, **(sim or {}))
        raw: dict[str, Any] = {
            "server": dict(server or {}),
            "lines": {"a": bus.line_table(sorted(devices), **(line or {}))},
        }
        if routes:
            raw["routes"] = routes
        return bus, make_gateway(raw)

    return factory


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    """A test PKI (roots, intermediate, server and client chains, and ``other-ca.pem``: a
    root that signed none of them), made once per module."""
    pki = make_pki(tmp_path_factory.mktemp("pki"))
    other = pki.directory / "other-ca.pem"
    other.write_bytes(pki.other_root.certificate.public_bytes(serialization.Encoding.PEM))
    return pki


@pytest.fixture
def tiny_bench(tmp_path: Path) -> TinyBench:
    """The benchmark's smoke run: ``tiny_bench("tls")`` → its output and figures."""

    def run(*names: str, ok: tuple[int, ...] = (0,), timeout: float = 120) -> BenchRun:
        return run_tiny_bench(tmp_path / "results.json", *names, ok=ok, timeout=timeout)

    return run
