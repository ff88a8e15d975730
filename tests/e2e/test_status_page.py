"""The status page in a real headless Chromium: loads clean, shows the line, sees a slave die.

Screenshots go to ``tmp_path``, or to ``$STATUS_SCREENSHOTS`` when set (to look at them).
"""

from __future__ import annotations

import base64
import io
import ipaddress
import json
import os
import subprocess
from pathlib import Path
from typing import Any

from gateway.pcap import PcapngWriter
from gateway.sim import plc, zl69x
from gateway.trace_client import TraceCapture
from tests.e2e.cdp import Browser
from tests.helpers import GatewayFactory, GatewayOnSim, SimFactory, require_tool

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
        assert browser.evaluate("document.getElementById('blocksection').hidden")  # no [[poll]]
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


def test_the_poll_blocks_in_chromium(
    make_sim: SimFactory, make_gateway: GatewayFactory, tmp_path: Path
) -> None:
    """Agent mode's blocks: range, pace, age and state, failing in red; none: no table."""
    chromium = require_tool("chromium")
    sim = make_sim({1: plc(1)})
    raw: dict[str, Any] = {
        "lines": {"a": sim.line_table([1, 2], timeout=0.1, retries=0)},
        "poll": [
            {"unit": 1, "function": 3, "address": 0, "count": 10, "every": 0.1},
            {"unit": 2, "function": 1, "address": 16, "count": 8, "every": 0.1},
        ],
    }
    gw = make_gateway(raw)
    assert gw.gateway.metrics_address is not None
    host, port = gw.gateway.metrics_address
    browser = Browser(chromium)
    try:
        for domain in ("Runtime", "Log", "Page"):
            browser.command(f"{domain}.enable")
        browser.command("Page.navigate", url=f"http://{host}:{port}/")
        fresh, failing = '#blocks tr[data-block="1:3:0-9"]', '#blocks tr[data-block="2:1:16-23"]'
        browser.wait_for(f"{_text(fresh + ' td.state')} === 'fresh'", "block 1:3:0-9 fresh")
        browser.wait_for(f"{_text(failing + ' td.state')} === 'failing'", "block 2 failing")
        assert not browser.evaluate("document.getElementById('blocksection').hidden")
        assert browser.evaluate(_text(f"{fresh} td.range")) == "0\u20139"
        assert browser.evaluate(_text(f"{fresh} td.every")) == "0.10 s"
        assert browser.evaluate(_text(f"{fresh} td.age")).endswith(" s")
        assert browser.evaluate(_text(f"{failing} td.age")) == "never"
        browser.wait_for(f"{_text(fresh + ' td.period')} !== '\u2013'", "the achieved period")
        assert (
            browser.evaluate(
                f"getComputedStyle(document.querySelector('{failing} td.state')).color"
            )
            == "rgb(207, 34, 46)"
        )  # failing, in red
        assert browser.evaluate(_text(f"{failing} td.failed")) != "0"
        browser.screenshot(tmp_path / "blocks.png")
        assert browser.errors() == []
    finally:
        browser.close()


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
        turn = "#lines tr[data-line='a'] td.turn"
        assert browser.evaluate(_text(turn)) == "\u2013"  # nothing answered: no turn learned
        assert "fair queue" in browser.evaluate(f'document.querySelector("{turn}").title')
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
            _refused_and_recent(browser, master, peer)
            _pause_and_download(browser, master, shots / "console-trace.pcapng", host)
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


def _refused_and_recent(browser: Browser, master: Any, peer: str) -> None:
    """Unrouted and denied requests counted per master and for the gateway; latency labelled
    with the window it covers; the utilisation chart with its scale."""
    assert master.request(200, READ_2) == b"\x83\x0a"  # no line serves unit 200
    assert master.request(1, bytes.fromhex("08 0004 0000")) == b"\x88\x01"  # listen only: denied
    master_row = f'#masters tr[data-peer="{peer}"]'
    browser.wait_for(f"{_text(master_row + ' td.unrouted')} === '1'", "the unrouted request")
    assert browser.evaluate(_text(f"{master_row} td.denied")) == "1"
    browser.wait_for("document.getElementById('unrouted').dataset.count === '1'",
                     "the gateway's count of requests with no route")  # fmt: skip
    assert browser.evaluate(_text("#lines tr[data-line='a'] td.unavailable")) == "0"
    window = browser.evaluate(_text("#latencywindow"))
    assert window.startswith("latency: p50 and p99 as masters see it, last "), window
    assert browser.evaluate(_text("#lines tr[data-line='a'] td.p50")).endswith(" ms")
    turn = browser.evaluate(_text("#lines tr[data-line='a'] td.turn"))
    assert turn.endswith(" ms") and float(turn.split()[0]) > 0, turn  # learned from the answers
    scale = browser.evaluate("document.querySelector('#lines svg.spark').dataset.scale")
    assert float(scale) in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)
    top = browser.evaluate(_text("#lines svg.spark text.top"))
    assert top == f"{float(scale) * 100:g} %", top


def _pause_and_download(browser: Browser, master: Any, capture: Path, host: str) -> None:
    """Paused, the trace shows nothing new and says how much waits; resumed, it shows it.
    What it holds downloads as the same pcapng ``trace --pcap`` writes, byte for byte."""
    trace = "document.getElementById('trace').textContent"
    browser.evaluate("document.getElementById('pause').click()")
    assert browser.evaluate(_text("#pause")) == "resume"
    assert master.request(1, bytes.fromhex("03 0007 0001"))[:2] == b"\x03\x02"
    browser.wait_for(f"{_text('#held')}.includes('paused, 2 new waiting')", "events held back")
    assert "address=7" not in browser.evaluate(trace)
    browser.evaluate("document.getElementById('pause').click()")
    browser.wait_for(f"{trace}.includes('address=7')", "the held-back request after resume")
    assert browser.evaluate(_text("#pause")) == "pause"
    events = json.loads(browser.evaluate("JSON.stringify(held)"))
    page = base64.b64decode(browser.evaluate(
        "(() => { const b = pcapng(held); let s = ''; "
        "for (const x of b) s += String.fromCharCode(x); return btoa(s); })()"
    ))  # fmt: skip
    expected = io.BytesIO()
    writer = PcapngWriter(expected, ipaddress.ip_address(host))
    capture_of = TraceCapture(writer)
    for event in events:
        capture_of.add(event)
    assert writer.packets > 0
    assert page == expected.getvalue()
    browser.evaluate("document.getElementById('download').click()")  # no error on the page
    capture.write_bytes(page)
    tshark = require_tool("tshark")
    decoded = subprocess.run(
        [tshark, "-r", str(capture), "-Y", "mbtcp || mbrtu", "-T", "fields", "-e", "frame.number"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert decoded.returncode == 0, decoded.stderr
    assert len(decoded.stdout.split()) == writer.packets, decoded.stdout
