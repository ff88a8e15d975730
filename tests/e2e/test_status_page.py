"""The status page in a real headless Chromium: loads clean, shows the line, sees a slave die.

Screenshots go to ``tmp_path``, or to ``$STATUS_SCREENSHOTS`` when set (to look at them).
"""

from __future__ import annotations

import os
from pathlib import Path

from cdp import Browser
from conftest import GatewayFactory, GatewayOnSim, SimFactory, require_tool

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
            # Listed before they answer: the page lists named slaves and those heard from.
            "names": {"1": "plc", "2": "meter"},
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


WIDE, PHONE = (1400, 900), (390, 844)


def _text(selector: str) -> str:
    return f"(document.querySelector({selector!r}) || {{}}).textContent"


def _shoot(browser: Browser, path: Path, size: tuple[int, int]) -> None:
    """A screenshot of the viewport at ``size`` (a laptop's window, a phone's)."""
    width, height = size
    browser.command("Emulation.setDeviceMetricsOverride", width=width, height=height,
                    deviceScaleFactor=1, mobile=width < 600)  # fmt: skip
    browser.wait_for(f"window.innerWidth === {width}", "the new window width")
    browser.screenshot(path)
    print(f"status page screenshot {width}x{height}: {path}")


def test_the_console_in_chromium(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    """Slaves by the unit id masters use, with names; a not-heard count; masters with their
    listener; the trace's answers decoded; the figures greyed out once the gateway is gone."""
    chromium = require_tool("chromium")
    shots = Path(os.environ.get("STATUS_SCREENSHOTS", str(tmp_path)))
    shots.mkdir(parents=True, exist_ok=True)
    sim = make_sim({1: plc(1), 2: zl69x(2)})
    line = sim.line_table([1, "3-30"], timeout=1.0, retries=0, names={"2": "meter"})
    gw = make_gateway({"lines": {"a": line}, "routes": [{"unit": 100, "line": "a", "slave": 2}]})
    assert gw.gateway.metrics_address is not None
    host, port = gw.gateway.metrics_address
    browser = Browser(chromium)
    try:
        for domain in ("Runtime", "Log", "Page"):
            browser.command(f"{domain}.enable")
        browser.command("Page.navigate", url=f"http://{host}:{port}/")
        # Named, not heard yet: listed under the unit id masters use, with its address.
        row = '#slaves tr[data-unit="100"]'
        assert browser.wait_for(_text(f"{row} td.name"), "the named slave") == "meter"
        assert browser.evaluate(f"document.querySelector('{row}').dataset.address") == "2"
        assert browser.evaluate(_text(f"{row} td.seen")) == "never"
        # Units 1 and 3..30 are routed, none has answered: counted, not listed.
        assert browser.evaluate("document.getElementById('notheard').dataset.count") == "29"
        assert browser.evaluate("document.querySelectorAll('#slaves tbody tr').length") == 1
        browser.wait_for("document.getElementById('tracestate').textContent === 'streaming'",
                         "the live trace to connect")  # fmt: skip
        with gw.connect() as master:
            assert master.request(100, READ_2) == bytes.fromhex("03 04 0113 FF9D")
            assert master.request(1, bytes.fromhex("03 FFF0 0002")) == b"\x83\x02"
            assert master.request(1, bytes.fromhex("01 0000 000A"))[:2] == b"\x01\x02"
            assert master.request(1, bytes.fromhex("06 0001 002A"))[:1] == b"\x06"
            trace = "document.getElementById('trace').textContent"
            browser.wait_for(f"{trace}.includes('= @0 [275, 65437]')", "registers decoded")
            browser.wait_for(f"{trace}.includes('exception 0x02 illegal data address')",
                             "the exception named")  # fmt: skip
            browser.wait_for(f"{trace}.includes('= @0 0000000000')", "coils decoded")
            browser.wait_for(f"{trace}.includes('echo address=1 value=0x002A')", "the echo")
            plc_row = '#slaves tr[data-unit="1"]'
            browser.wait_for(f"{_text(plc_row + ' td.requests')} === '3'", "unit 1 counted")
            assert browser.evaluate(_text(f"{plc_row} td.exceptions")) == (
                "0x02 illegal data address \u00d71"
            )
            assert browser.evaluate(_text(f"{row} td.seen")) != "never"
            assert browser.evaluate("document.getElementById('notheard').dataset.count") == "28"
            peer = "{}:{}".format(*master.sock.getsockname())
            master_row = f'#masters tr[data-peer="{peer}"]'
            listener = browser.wait_for(_text(f"{master_row} td.listener"), "the master")
            assert listener == f"tcp {gw.address[0]}:{gw.port}"
            options = "[...document.querySelectorAll('#dl-unit option')].map(o => o.value)"
            assert "100" in browser.evaluate(options)
            functions = "[...document.querySelectorAll('#dl-function option')].map(o => o.value)"
            assert "read_holding_registers" in browser.evaluate(functions)
            _shoot(browser, shots / "console-1400x900.png", WIDE)
            _shoot(browser, shots / "console-390x844.png", PHONE)
            _shoot(browser, shots / "console-1400x900.png", WIDE)
        gw.stop()  # the gateway goes away: the page says so and greys its figures out
        banner = browser.wait_for(
            "document.body.classList.contains('stale') && "
            "document.getElementById('banner').textContent",
            "the unreachable state",
        )
        assert banner.startswith("gateway unreachable since ")
        assert browser.evaluate(
            "getComputedStyle(document.getElementById('figures')).opacity"
        ) == "0.45"  # fmt: skip
        _shoot(browser, shots / "console-unreachable-1400x900.png", WIDE)
        # The trace stream's reconnect attempts are the browser's own network log, not errors
        # of the page.
        errors = [e for e in browser.errors() if "ERR_CONNECTION_REFUSED" not in e]
        assert errors == []
    finally:
        browser.close()
