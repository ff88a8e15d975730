"""A reload keeps the running value of every key the schema marks restart-only.

A real gateway with a listen backlog and an audit file is reloaded from a configuration
that changes both and one key a reload applies: the gateway's configuration, the audit
record of the reload and the reload's summary line agree that the backlog and the audit
path stay as they started (the socket and the file took them at start), while the other
key is applied. The audit log goes on in its first file; the second is never created.
Listeners a reload adds, removes or gives another protocol stay as they run, and so does
the configuration's account of them, against which the next reload is compared.
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
from gateway.sim.pki import Pki
from tests.helpers import DEADLINE_S, GatewayFactory, RawClient, SimFactory, read


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


def test_listeners_a_reload_leaves_running_stay_in_the_configuration(
    make_sim: SimFactory,
    make_gateway: GatewayFactory,
    pki: Pki,
    caplog: pytest.LogCaptureFixture,
) -> None:
    sim = make_sim({1: plc(1)})
    raw: dict[str, Any] = {
        "server": {"listen": "127.0.0.1:0"},
        "metrics": {"listen": "127.0.0.1:0"},
        "lines": {"a": sim.line_table([1])},
        "listeners": [
            {"name": "extra", "listen": "127.0.0.1:0", "policy": "readers"},
            {"name": "plain", "listen": "127.0.0.1:0"},
        ],
        "policies": {"readers": {"rules": [{"access": "read"}]}},
    }
    gateway = make_gateway(raw)
    running = gateway.call(lambda: gateway.gateway.config)
    assert [(lst.name, lst.protocol) for lst in running.listeners] == [
        ("tcp", "tcp"),
        ("extra", "tcp"),
        ("plain", "tcp"),
    ]
    tls = {"cert": str(pki.server_chain), "key": str(pki.server_key), "ca": str(pki.ca)}
    changed = {
        **raw,
        "listeners": [  # extra removed, plain made tls, added added; the policy removed
            {"name": "plain", "protocol": "tls", "listen": "127.0.0.1:0", **tls},
            {"name": "added", "listen": "127.0.0.1:0"},
        ],
        "policies": {},
    }
    with caplog.at_level(logging.INFO, logger="gateway"):
        gateway.run(gateway.gateway.reload(build_config(changed, "<changed>")))
        config = gateway.call(lambda: gateway.gateway.config)
        assert config.listeners == running.listeners  # what runs, not what the file says
        assert config.policies == running.policies  # extra's, which it still applies
        assert config.source == "<changed>"
        summary = next(r.getMessage() for r in caplog.records if "from <changed>" in r.message)
        applied, _, kept = summary.partition("needs a restart, kept at its running value: ")
        assert applied == "reload: configuration from <changed> applied: ", summary
        for item in (
            "listeners.added added",
            "listeners.extra removed",
            "listeners.plain.protocol 'tcp' → 'tls'",
            "policies.readers removed",
        ):
            assert item in kept.split("; "), summary
        assert "adding or removing listeners" in caplog.text
        caplog.clear()

        for name in ("extra", "plain"):  # both still answer, plain in clear as before
            with RawClient(gateway.gateway.listener_address(name)) as master:
                assert master.request(1, read(1000)) == bytes.fromhex("030203E8"), name

        # Back to the file that describes what runs: nothing to change, nothing to warn of.
        gateway.run(gateway.gateway.reload(build_config(raw, "<back>")))
    summary = next(r.getMessage() for r in caplog.records if "from <back>" in r.message)
    assert summary.endswith("no key changed (certificate and key files were read again)")
    assert "adding or removing listeners" not in caplog.text
