"""Line kinds end to end: raw Modbus TCP in, an ASCII line (or an echoing adapter) on a pty out.

Every function code goes through an ASCII line and through an RTU line to twin devices:
the answers must be the same bytes, and the same as the simulator's own vectors. The
echo of a half-duplex adapter is dropped when the line says ``echo = true``.
"""

from __future__ import annotations

from typing import Any

import pytest

from gateway.config import build_config
from gateway.sim import UnitFaults, plc
from tests.helpers import GatewayFactory, SimFactory, h
from tests.integration.metrics_harness import samples, series
from tests.integration.test_sim import FUNCTION_VECTORS

#: ptys refuse some parities (FIELD-NOTES): ASCII lines in tests run 8N1.
ASCII_ON_PTY = {"kind": "ascii", "data_bits": 8, "parity": "N"}


@pytest.mark.parametrize(("request_hex", "response_hex"), FUNCTION_VECTORS)
def test_every_function_code_through_an_ascii_line(
    make_sim: SimFactory, make_gateway: GatewayFactory, request_hex: str, response_hex: str
) -> None:
    ascii_sim = make_sim({7: plc(7)}, framing="ascii")
    rtu_sim = make_sim({7: plc(7)})
    gw = make_gateway(
        {
            "lines": {
                "a": ascii_sim.line_table([7], **ASCII_ON_PTY),
                "r": rtu_sim.line_table([], timeout=0.5),
            },
            "routes": [{"unit": 8, "line": "r", "slave": 7}],
        }
    )
    with gw.connect() as master:
        through_ascii = master.request(7, h(request_hex))
        through_rtu = master.request(8, h(request_hex))
    assert through_ascii == h(response_hex)
    assert through_rtu == through_ascii


def test_ascii_line_metrics_and_a_damaged_lrc(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)}, framing="ascii", faults={1: UnitFaults(crc_error_rate=1.0)})
    gw = make_gateway({"lines": {"a": sim.line_table([1], retries=1, **ASCII_ON_PTY)}})
    with gw.connect() as master:
        assert master.request(1, h("03 0000 0002")) == h("83 0B")  # both attempts: bad LRC
    sim.faults(1).crc_error_rate = 0.0
    with gw.connect() as master:
        assert master.request(1, h("03 0000 0002")) == h("03 04 0000 0002")
    found = samples(gw)
    assert found[series("modbus_gateway_line_info", line="a", kind="ascii")] == 1
    assert found[series("modbus_gateway_crc_errors_total", line="a", unit="1")] == 2


@pytest.mark.parametrize("framing", ["rtu", "ascii"])
def test_an_echoing_adapter_with_echo_set(
    make_sim: SimFactory, make_gateway: GatewayFactory, framing: str
) -> None:
    sim = make_sim({1: plc(1)}, framing=framing, echo=True)
    options: dict[str, Any] = {"echo": True, "retries": 0}
    if framing == "ascii":
        options.update(ASCII_ON_PTY)
    gw = make_gateway({"lines": {"a": sim.line_table([1], **options)}})
    with gw.connect() as master:
        for value in range(20):
            assert master.request(1, h("06 0064") + value.to_bytes(2, "big")) == h(
                "06 0064"
            ) + value.to_bytes(2, "big")
            assert master.request(1, h("03 0064 0001")) == h("03 02") + value.to_bytes(2, "big")
    found = samples(gw)
    assert found[series("modbus_gateway_crc_errors_total", line="a", unit="1")] == 0
    assert found[series("modbus_gateway_discarded_frames_total", line="a", reason="late")] == 0


def test_an_echoing_adapter_without_echo_set_fails_reads(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    """What ``echo = true`` is for: the echo of a read is taken for a damaged answer."""
    sim = make_sim({1: plc(1)}, echo=True)
    gw = make_gateway({"lines": {"a": sim.line_table([1], retries=0)}})
    with gw.connect() as master:
        assert master.request(1, h("03 0000 0002")) == h("83 0B")


def test_a_reload_that_changes_the_kind_reopens_the_line(
    make_sim: SimFactory, make_gateway: GatewayFactory
) -> None:
    sim = make_sim({1: plc(1)}, framing="ascii")
    tables: dict[str, Any] = {"lines": {"a": sim.line_table([1], retries=0, timeout=0.1)}}
    gw = make_gateway(tables)
    with gw.connect() as master:
        assert master.request(1, h("03 0000 0002")) == h("83 0B")  # RTU to an ASCII slave
        raw = {
            "server": {"listen": "127.0.0.1:0"},
            "metrics": {"listen": "127.0.0.1:0"},
            "lines": {"a": sim.line_table([1], retries=0, **ASCII_ON_PTY)},
        }
        gw.run(gw.gateway.reload(build_config(raw, "<reload>")))
        assert master.request(1, h("03 0000 0002")) == h("03 04 0000 0002")
    found = samples(gw)
    assert found[series("modbus_gateway_line_info", line="a", kind="ascii")] == 1
    assert series("modbus_gateway_line_info", line="a", kind="rtu") not in found
