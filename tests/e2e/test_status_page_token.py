"""The status page behind tokens in a real headless Chromium: a ``?token=`` link sets the
cookies, and the page's own ``fetch('/status')`` and ``EventSource('/trace')`` then pass."""

from __future__ import annotations

from gateway.sim import plc
from tests.e2e.cdp import Browser
from tests.helpers import GatewayFactory, SimFactory, require_tool

STATUS_TOKEN = "status-0123456789abcdef"
TRACE_TOKEN = "trace-0123456789abcdef"
#: What the page's scripts can do from its origin, whatever the page's design.
FETCH_STATUS = "fetch('/status').then(r => r.status)"
TRACE_OPENS = (
    "new Promise(done => { const s = new EventSource('/trace');"
    " s.onopen = () => { s.close(); done('open'); };"
    " s.onerror = () => { s.close(); done('refused'); }; })"
)


def test_a_token_link_lets_the_page_fetch_status_and_open_the_trace(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    chromium = require_tool("chromium")
    sim = make_sim({1: plc(1)})
    gw = make_gateway({
        "lines": {"a": sim.line_table([1])},
        "metrics": {"status_token": STATUS_TOKEN, "trace_token": TRACE_TOKEN},
    })  # fmt: skip
    assert gw.gateway.metrics_address is not None
    host, port = gw.gateway.metrics_address
    base = f"http://{host}:{port}"
    browser = Browser(chromium)
    try:
        browser.command("Page.enable")
        browser.command("Page.navigate", url=f"{base}/?token={STATUS_TOKEN}")
        browser.wait_for("document.readyState === 'complete'", "the page")
        assert browser.evaluate(FETCH_STATUS) == 200
        assert browser.evaluate(TRACE_OPENS) == "refused"  # the status token is not enough
        assert browser.evaluate("document.cookie") == ""  # HttpOnly: no script reads them
        browser.command("Page.navigate", url=f"{base}/?token={STATUS_TOKEN}&token={TRACE_TOKEN}")
        browser.wait_for("document.readyState === 'complete' && location.search.includes('trace-')",
                         "the page opened by the link with both tokens")  # fmt: skip
        assert browser.evaluate(TRACE_OPENS) == "open"
        browser.command("Page.navigate", url=f"{base}/")  # the cookies open the page itself
        browser.wait_for("document.readyState === 'complete' && location.search === ''", "page")
        assert browser.evaluate(FETCH_STATUS) == 200
        assert browser.evaluate(TRACE_OPENS) == "open"
    finally:
        browser.close()
