"""The status page in a real headless Chromium: loads clean, shows the line, sees a slave die."""

from __future__ import annotations

from pathlib import Path

from cdp import Browser
from conftest import GatewayOnSim, require_tool

from gateway.sim import plc, zl69x

READ_2 = bytes.fromhex("03 0000 0002")


def _state(line: str, unit: int) -> str:
    return (
        f'(document.querySelector(\'#slaves tr[data-line="{line}"][data-unit="{unit}"] '
        "td.state') || {}).textContent"
    )


def test_the_status_page_in_chromium(gateway_with: GatewayOnSim, tmp_path: Path) -> None:
    chromium = require_tool("chromium")
    sim, gw = gateway_with(
        {1: plc(1), 2: zl69x(2)},
        line={
            # Slave 1 must stay "up" on one answer: a timeout far above what a busy machine
            # delays the simulator by (only slave 2's two timeouts wait it out).
            "timeout": 1.0,
            "retries": 0,
            "dead_after": 2,
            "probe_interval": 60,
            "late_answer_window": 0,
        },  # silent: nothing comes late
    )
    assert gw.gateway.metrics_address is not None
    host, port = gw.gateway.metrics_address
    browser = Browser(chromium)
    screenshot = tmp_path / "status-page.png"
    try:
        for domain in ("Runtime", "Log", "Page"):
            browser.command(f"{domain}.enable")
        browser.command("Page.navigate", url=f"http://{host}:{port}/")
        browser.wait_for("!!document.querySelector('#lines tr[data-line=\"a\"]')", "line a")
        assert (
            browser.evaluate(
                "document.querySelector('#lines tr[data-line=\"a\"] td.state').textContent"
            )
            == "up"
        )
        assert browser.wait_for(_state("a", 1), "slave 1") == "up"
        assert browser.evaluate(_state("a", 2)) == "up"
        browser.wait_for("document.getElementById('tracestate').textContent === 'streaming'",
                         "the live trace to connect")  # fmt: skip
        with gw.connect() as master:
            master.request(1, READ_2)
            master.request(2, READ_2)
            browser.wait_for(
                "document.getElementById('trace').textContent.includes('unit=2 [a slave 2]')",
                "the request to unit 2 in the live trace",
            )
            browser.wait_for("document.querySelectorAll('#masters tbody tr td').length >= 4",
                             "the connected master")  # fmt: skip
            sim.faults(2).silent = True  # the slave falls silent
            for _ in range(2):
                master.request(2, READ_2)  # two timeouts in a row: isolated (dead_after 2)
            browser.wait_for(f"{_state('a', 2)} === 'down'", "slave 2 shown down")
            assert browser.evaluate(_state("a", 1)) == "up"
            assert browser.evaluate(
                "getComputedStyle(document.querySelector("
                "'#slaves tr[data-unit=\"2\"] td.state')).color"
            ) == "rgb(207, 34, 46)"  # shown in red  # fmt: skip
            browser.wait_for(
                "document.getElementById('trace').textContent.includes('target_failed')",
                "the failed requests in the live trace",
            )
        browser.screenshot(screenshot)
        print(f"status page screenshot: {screenshot}")
        assert browser.errors() == []
        external = browser.evaluate(
            "performance.getEntriesByType('resource').map(e => e.name)"
            f".filter(n => !n.startsWith('http://{host}:{port}/'))"
        )
        assert external == []  # nothing loaded from anywhere but the gateway
    finally:
        browser.close()
    assert screenshot.stat().st_size > 10_000
