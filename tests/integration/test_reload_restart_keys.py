"""A reload keeps the running value of every key the schema marks restart-only.

A real gateway with a listen backlog and an audit file is reloaded from a configuration
that changes both and one key a reload applies: the gateway's configuration, the audit
record of the reload and the reload's summary line agree that the backlog and the audit
path stay as they started (the socket and the file took them at start), while the other
key is applied. The audit log goes on in its first file; the second is never created.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pytest

from gateway.config import build_config
from gateway.restart_keys import fields_of, restart_keys
from gateway.sim import plc
from tests.helpers import DEADLINE_S, GatewayFactory, SimFactory


def test_every_restart_only_key_names_the_fields_it_keeps() -> None:
    for key in restart_keys():
        fields_of(key)  # LookupError: a reload would apply a key the schema says it cannot


def test_a_reload_keeps_the_backlog_and_the_audit_path(
    make_sim: SimFactory,
    make_gateway: GatewayFactory,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    sim = make_sim({1: plc(1)})
    first, second = tmp_path / "first.jsonl", tmp_path / "second.jsonl"
    raw: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0", "backlog": 64, "max_pipeline": 8},
        "metrics": {"listen": "127.0.0.1:0"},
        "lines": {"a": sim.line_table([1])},
        "audit": {"path": str(first)},
    }
    gateway = make_gateway(raw)
    changed = {
        **raw,
        "server": {**raw["server"], "backlog": 128, "max_pipeline": 4},
        "audit": {"path": str(second)},
    }
    with caplog.at_level(logging.INFO, logger="gateway"):
        gateway.run(gateway.gateway.reload(build_config(changed, "<test>")))

    config = gateway.call(lambda: gateway.gateway.config)
    assert (config.server.backlog, config.audit.path) == (64, str(first))
    assert config.server.max_pipeline == 4  # applied: the reload itself went through
    summary = next(r.getMessage() for r in caplog.records if "configuration from" in r.message)
    assert summary.endswith(
        "needs a restart, kept at its running value: "
        f"audit.path {str(first)!r} → {str(second)!r}; server.backlog 64 → 128"
    ), summary
    assert "[server] changes need a restart; keeping the running server.backlog" in caplog.text
    assert "[audit] changes need a restart; keeping the running audit.path" in caplog.text

    audit = gateway.gateway.audit
    assert audit is not None and audit.flush(DEADLINE_S)
    records = [json.loads(line) for line in first.read_text().splitlines()]
    reload = [r for r in records if r["event"] == "config" and r["action"] == "reload"]
    assert [(r["result"], r["changed"]) for r in reload] == [("accepted", ["server.max_pipeline"])]
    assert not second.exists()
