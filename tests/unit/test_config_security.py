"""Listeners, policies and their command-line flags: parsed, validated, every fault named."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Any

import pytest

from gateway.cli import apply_overrides, build_parser
from gateway.config import (
    ListenerConfig,
    build_config,
    load_config,
    parse_function_key,
    policy_warnings,
)
from gateway.core.policy import Access, Policy, Principal
from gateway.io.listeners.access import peer_address_of
from tests.helpers import problems

LINE = {"a": {"device": "/dev/null", "units": [1, 2]}}
TLS = {"protocol": "tls", "cert": "s.pem", "key": "s.key", "ca": "ca.pem"}


def config(**tables: Any) -> Any:
    return build_config({"lines": LINE, **tables}, "t.toml")


def problem_text(**tables: Any) -> str:
    return "\n".join(problems({"lines": LINE, **tables}, "t.toml"))


def test_without_listeners_the_server_listen_shorthand_is_the_one_tcp_listener() -> None:
    assert config().listeners == (ListenerConfig("tcp", "tcp", "0.0.0.0", 502),)
    listeners = config(server={"listen": "127.0.0.1:5020", "read_only": True}).listeners
    assert listeners == (ListenerConfig("tcp", "tcp", "127.0.0.1", 5020, read_only=True),)


def test_listeners_beside_the_shorthand_or_instead_of_it() -> None:
    both = config(server={"listen": "0.0.0.0:502"}, listeners=[{"name": "secure", **TLS}])
    assert [(lst.name, lst.protocol, lst.port) for lst in both.listeners] == [
        ("tcp", "tcp", 502), ("secure", "tls", 802),
    ]  # fmt: skip
    only = config(listeners=[TLS, {"name": "plant", "listen": "10.0.0.1:1502",
                                    "allow": ["10.0.0.0/24", "fd00::1"]}])  # fmt: skip
    assert [lst.name for lst in only.listeners] == ["tls", "plant"]
    assert only.listeners[1].allow == (
        ipaddress.ip_network("10.0.0.0/24"), ipaddress.ip_network("fd00::1/128"),
    )  # fmt: skip


def test_listener_faults_are_named() -> None:
    text = problem_text(
        server={"listen": "0.0.0.0:502", "allow": ["10.0.0.300"]},
        listeners=[
            {"protocol": "tls", "cert": "s.pem"},
            {"name": "tcp", "cert": "x.pem", "policy": "nope"},
            {"name": "b", "protocol": "udp", "listen": "0.0.0.0:502"},
        ],
    )
    assert "server.allow: '10.0.0.300' is not an IP address or network" in text
    assert "listeners[0].key: missing; a tls listener needs the server's private key" in text
    assert "listeners[0].ca: missing; a tls listener needs the CA certificates" in text
    assert 'listeners[1].cert: only a protocol = "tls" listener takes it' in text
    assert "listeners[1].policy: 'nope' is not a [policies.NAME] table" in text
    assert "listeners[1].name: 'tcp' is used by another listener" in text
    assert "listeners[2].protocol: 'udp' is not one of: tcp, tls, rtu-over-tcp" in text
    assert "two listeners on 0.0.0.0:502" in text


def test_rules_are_parsed() -> None:
    parsed = config(
        server={"policy": "p"},
        policies={"p": {"rules": [
            {"role": "operator", "source": "10.0.0.0/8", "units": [0, "1-3"],
             "functions": [3, "write_single_register", "0x10", "8:4", "diagnostics:0", "43:14"],
             "addresses": ["100-199", 0, "200-299"], "access": "write"},
            {},
        ]}},
    ).policies["p"]  # fmt: skip
    first, everything = parsed
    assert first.key == "policies.p.rules[0]"
    assert first.role == "operator"
    assert first.sources == (ipaddress.ip_network("10.0.0.0/8"),)
    assert first.units == frozenset({0, 1, 2, 3})
    assert first.functions == frozenset({(3, None), (6, None), (16, None), (8, 4), (8, 0),
                                         (43, 14)})  # fmt: skip
    assert first.addresses == ((0, 0), (100, 299))
    assert first.access is Access.WRITE
    assert (everything.units, everything.functions, everything.addresses) == (None, None, None)
    assert everything.access is Access.READ_WRITE


def test_rule_faults_are_named() -> None:
    text = problem_text(policies={"p": {"rules": [
        {"role": 5, "units": [256], "functions": ["read_everything", "3:1", 200],
         "addresses": ["10-5"], "access": "all", "when": "always", "source": "nowhere"},
    ]}})  # fmt: skip
    key = "policies.p.rules[0]."
    assert f"{key}role: write the role as a non-empty string" in text
    assert f"{key}units: 256 outside 0..255" in text
    assert f"{key}functions: 'read_everything' is not a function" in text
    assert f"{key}functions: '3:1': only diagnostics (8:0..65535)" in text
    assert f"{key}functions: function code 200 outside 1..127" in text
    assert f"{key}addresses: '10-5' outside 0..65535 (or backwards)" in text
    assert f"{key}access: 'all' is not one of: read, write, read_write" in text
    assert f"{key}when: unknown key" in text
    assert f"{key}source: 'nowhere' is not an IP address or network" in text


@pytest.mark.parametrize(
    ("item", "key"),
    [(3, (3, None)), ("0x03", (3, None)), ("Read_Coils", (1, None)), ("8:4", (8, 4)),
     ("diagnostics:0x0A", (8, 10)), ("encapsulated_interface:14", (43, 14))],
)  # fmt: skip
def test_function_keys(item: Any, key: tuple[int, int | None]) -> None:
    assert parse_function_key(item) == key


def test_flags_add_a_tls_listener_an_allow_list_and_read_only() -> None:
    args = build_parser().parse_args([
        "--tls-listen", "0.0.0.0:802", "--tls-cert", "s.pem", "--tls-key", "s.key",
        "--tls-ca", "ca.pem", "--allow", "10.0.0.0/8", "--allow", "192.168.1.7", "--read-only",
    ])  # fmt: skip
    built = build_config(apply_overrides({"lines": LINE}, args))
    assert [(lst.name, lst.protocol, lst.port, lst.cert) for lst in built.listeners] == [
        ("tls", "tls", 802, "s.pem")
    ]  # --tls-listen alone: no plain listener unless --listen or [server] listen asks for one
    assert built.server.read_only and built.listeners[0].read_only
    assert [str(n) for n in built.server.allow] == ["10.0.0.0/8", "192.168.1.7/32"]
    with_plain = build_config(apply_overrides(
        {"lines": LINE}, build_parser().parse_args(["--listen", "0.0.0.0:502",
                                                    "--tls-ca", "other.pem"])
    ) | {"listeners": [{"name": "tls", **TLS}]})  # fmt: skip
    assert [lst.name for lst in with_plain.listeners] == ["tcp", "tls"]


def test_flags_override_the_files_tls_listener() -> None:
    raw = {"lines": LINE, "listeners": [{"name": "tls", "policy": "p", **TLS}],
           "policies": {"p": {"rules": [{"role": "operator"}]}}}  # fmt: skip
    args = build_parser().parse_args(["--tls-cert", "new.pem", "--tls-listen", "127.0.0.1:8802"])
    (listener,) = build_config(apply_overrides(raw, args)).listeners
    assert (listener.cert, listener.key, listener.port, listener.policy) == (
        "new.pem", "s.key", 8802, "p",
    )  # fmt: skip


def test_warnings_for_rules_that_never_match() -> None:
    built = config(
        server={"listen": "0.0.0.0:502", "policy": "p", "allow": ["10.0.0.0/8"]},
        listeners=[TLS],
        policies={
            "p": {"rules": [{"role": "operator"}, {"source": "192.168.0.0/16"}]},
            "unused": {"rules": []},
        },
    )
    text = "\n".join(policy_warnings(built))
    assert "policies.unused: no listener uses it" in text
    assert "tls listener 'tls' has no policy" in text
    assert "policies.p.rules[0] (listener 'tcp'): role 'operator' never matches" in text
    assert "policies.p.rules[1] (listener 'tcp'): source 192.168.0.0/16 is outside" in text


def test_the_locked_down_example_means_what_its_comments_say() -> None:
    root = Path(__file__).resolve().parents[2]
    built = load_config(root / "conf" / "gateway.locked-down.toml")
    assert policy_warnings(built) == []
    tcp, tls = built.listeners
    assert (tcp.name, tcp.port, tls.name, tls.port, tls.protocol) == ("tcp", 502, "tls", 802, "tls")
    hmi = Policy(built.policies["legacy"])
    plant = Policy(built.policies["plant"], tls=True)

    def ip(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
        return ipaddress.ip_address(text)

    station = ip("10.1.2.50")
    cases = [
        (hmi, Principal(ip("10.1.2.20")), 3, "03 0000 0010", True),
        (hmi, Principal(ip("10.1.2.20")), 3, "06 0000 0001", False),
        (hmi, Principal(ip("10.1.2.21")), 3, "03 0000 0010", False),
        (plant, Principal(station, "operator"), 10, "10 03E6 0002 04 00010002", True),
        (plant, Principal(station, "operator"), 10, "10 03E7 0002 04 00010002", False),
        (plant, Principal(station, "operator"), 11, "03 0000 0001", False),
        (plant, Principal(station, "operator"), 1, "05 0063 FF00", True),
        (plant, Principal(station, "viewer"), 7, "04 0000 0010", True),
        (plant, Principal(station, "viewer"), 7, "06 0000 0001", False),
        (plant, Principal(station, "engineer"), 7, "08 000B 0000", True),
        (plant, Principal(station, "engineer"), 7, "08 0004 0000", False),
        (plant, Principal(station, "engineer"), 0, "10 2328 0004 08 0001000200030004", True),
        (plant, Principal(ip("10.1.2.51"), "engineer"), 0, "10 2328 0001 02 0001", False),
        (plant, Principal(station, None), 1, "03 0000 0001", False),
    ]
    for policy, principal, unit, pdu, served in cases:
        assert policy.decide(principal, unit, bytes.fromhex(pdu)).allowed is served, (
            principal, unit, pdu,
        )  # fmt: skip


@pytest.mark.parametrize(
    ("peer", "address"),
    [(("10.0.0.7", 5020), "10.0.0.7"), (("::ffff:10.0.0.7", 5020, 0, 0), "10.0.0.7"),
     (("fd00::1", 5020, 0, 0), "fd00::1"), ("/run/socket", None), ((), None)],
)  # fmt: skip
def test_peer_addresses_for_allow_lists_and_rules(peer: object, address: str | None) -> None:
    """An IPv4 master reaching a dual-stack listener matches IPv4 networks."""
    found = peer_address_of(peer)
    assert (str(found) if found is not None else None) == address
