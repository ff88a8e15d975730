"""The HTTP endpoint's guard on its own: Host names, tokens and the cookies a link sets."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.config import MetricsConfig, is_loopback
from gateway.io.http.guard import Guard, HttpRefusal, RouteAccess, host_name

STATUS = "s" * 20
TRACE = "t" * 20


@pytest.mark.parametrize(
    ("header", "name"),
    [
        ("localhost:9502", "localhost"),
        ("[::1]:9502", "::1"),
        ("[::1]", "::1"),
        ("Gw.Example.", "gw.example"),
        ("10.0.0.5", "10.0.0.5"),
        ("::1", "::1"),
    ],
)
def test_host_names(header: str, name: str) -> None:
    assert host_name(header) == name


def test_loopback_names_and_rebinding_names() -> None:
    assert all(map(is_loopback, ("localhost", "127.0.0.1", "127.3.2.1", "::1", "a.localhost")))
    # Names a rebinding page uses resolve to loopback, but are not loopback names.
    assert not any(map(is_loopback, ("127.0.0.1.nip.io", "localtest.me", "attacker.example")))


def guard(**config: object) -> Guard:
    return Guard(MetricsConfig(**config))  # type: ignore[arg-type]


def test_the_host_check_guards_status_and_trace_only() -> None:
    check = guard(host="0.0.0.0", allowed_hosts=("gw.example",))
    foreign = {"host": "attacker.example"}
    assert check.judge(RouteAccess.OPEN, "/metrics", foreign, "10.0.0.5").refusal is None
    assert (
        check.judge(RouteAccess.STATUS, "/status", foreign, "10.0.0.5").refusal is HttpRefusal.HOST
    )
    assert check.judge(RouteAccess.TRACE, "/trace", foreign, "10.0.0.5").status == 421
    for host in ("gw.example:9502", "10.0.0.5:9502", "localhost", "[::1]:1"):
        assert check.judge(RouteAccess.STATUS, "/", {"host": host}, "10.0.0.5").refusal is None
    assert check.judge(RouteAccess.STATUS, "/", {}, "10.0.0.5").refusal is None  # no browser
    # 0.0.0.0 is no name a browser can be sent to by a rebinding page: not in the list.
    assert check.judge(RouteAccess.STATUS, "/", {"host": "0.0.0.0"}, "10.0.0.5").status == 421


def test_tokens_and_the_cookies_a_link_sets() -> None:
    check = guard(status_token=STATUS, trace_token=TRACE, tls_cert="c", tls_key="k")
    local = {"host": "localhost"}
    assert check.judge(RouteAccess.STATUS, "/status", local, "").status == 401
    wrong = {**local, "authorization": "Bearer x"}
    assert check.judge(RouteAccess.STATUS, "/status", wrong, "").status == 403
    right = {**local, "authorization": f"Bearer {STATUS}"}
    assert check.judge(RouteAccess.STATUS, "/status", right, "").refusal is None
    assert check.judge(RouteAccess.TRACE, "/trace", right, "").status == 403
    link = check.judge(RouteAccess.STATUS, f"/?token={STATUS}&token={TRACE}", local, "")
    assert link.refusal is None and len(link.set_cookies) == 2
    assert all(
        "HttpOnly" in c and "SameSite=Strict" in c and "Secure" in c for c in link.set_cookies
    )
    cookie = {**local, "cookie": f"other=1; mbgw_trace={TRACE}"}
    assert check.judge(RouteAccess.TRACE, "/trace?unit=1", cookie, "").refusal is None
    assert check.judge(RouteAccess.STATUS, "/status", cookie, "").status == 401


@given(st.text(alphabet="abcdefghijklmnop0123456789-._~", min_size=1, max_size=40))
def test_only_the_token_itself_opens(given_token: str) -> None:
    check = guard(status_token=STATUS)
    headers = {"authorization": f"Bearer {given_token}"}
    verdict = check.judge(RouteAccess.STATUS, "/status", headers, "")
    assert (verdict.refusal is None) == (given_token == STATUS)
