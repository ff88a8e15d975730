"""Warnings for configurations that load but defeat a documented protection."""

from __future__ import annotations

from typing import Any

import pytest

from gateway.config import build_config, config_warnings

LINE = {"a": {"device": "/dev/null", "units": [1]}}
TOKEN_A, TOKEN_B = "3f1c9a0d5e7b2c4a8f6d1e0b9c7a5d3e", "b8e2d4f6a1c3e5d7f9a0b2c4d6e8f0a1"


def warnings_of(raw: dict[str, Any]) -> list[str]:
    return config_warnings(build_config({"lines": LINE, **raw}, "plant.toml"))


def about(warnings: list[str], key: str) -> list[str]:
    return [w for w in warnings if w.startswith(key + ":")]


PAIR = {"peer": "192.0.2.12:9502", "peer_modbus": "192.0.2.12:502"}
REACHABLE = {"server": {"listen": "0.0.0.0:502"}}


def test_a_pair_without_keepalive_is_warned_and_with_it_not() -> None:
    metrics = {"listen": "0.0.0.0:9502", "status_token": TOKEN_A, "trace_token": TOKEN_B}
    off = warnings_of({**REACHABLE, "metrics": metrics, "redundancy": {**PAIR, "keepalive": "off"}})
    assert about(off, "redundancy.keepalive") and "steps down" in off[0], off
    for value in ("auto", "1:0"):
        kept = {**REACHABLE, "metrics": metrics, "redundancy": {**PAIR, "keepalive": value}}
        assert warnings_of(kept) == []
    assert warnings_of({"redundancy": {"keepalive": "off"}}) == []  # no pair: nothing to keep


def test_a_status_token_without_a_trace_token_is_warned() -> None:
    warned = warnings_of({"metrics": {"status_token": TOKEN_A}})
    assert about(warned, "metrics.trace_token") and "/trace" in warned[0], warned
    assert warnings_of({"metrics": {"status_token": TOKEN_A, "trace_token": TOKEN_B}}) == []
    assert warnings_of({"metrics": {"trace_token": TOKEN_B}}) == []  # /trace is the secret one


@pytest.mark.parametrize(
    ("metrics", "warned"),
    [
        ({"listen": "0.0.0.0:9502"}, True),
        ({"listen": "192.0.2.7:9502"}, True),
        ({"listen": "127.0.0.1:9502"}, False),
        ({"listen": "[::1]:9502"}, False),
        ({"listen": "off"}, False),
        ({"listen": "0.0.0.0:9502", "status_token": TOKEN_A, "trace_token": TOKEN_B}, False),
        ({"listen": "0.0.0.0:9502", "tls_cert": "/etc/g/c.pem", "tls_key": "/etc/g/k.pem"}, False),
    ],
)
def test_an_endpoint_open_to_the_network_without_tokens_or_https_is_warned(
    metrics: dict[str, str], warned: bool
) -> None:
    warnings = about(warnings_of({"metrics": metrics}), "metrics.listen")
    assert bool(warnings) == warned, warnings
    if warned:
        assert "neither status_token nor trace_token nor HTTPS" in warnings[0]
