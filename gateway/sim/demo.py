"""The ``--demo`` line: simulated devices on a pseudo-terminal, served to the real gateway.

A newcomer with no RS485 hardware gets the gateway's real serial path (pyserial
on a pty, the same worker and timing) answering three devices from the vendor
documents: a PLC with a large register map at unit 1, a ZL-69X temperature
controller at unit 2 and a power controller capped at 5-register reads at unit 3.
The line is paced like a real 19200 baud line. A second line, ``demo-ascii``,
speaks Modbus ASCII at 9600 baud with another ZL-69X at unit 4, as older meters
and wallboxes do; 8N1 rather than ASCII's usual 7E1, because ptys refuse 7 data bits.
A third line, ``demo-tcp`` (``kind = "tcp"``), reaches an R6 robot controller served
as a Modbus TCP slave on loopback: the gateway's unit 5 is its unit id 0x01.
"""

from __future__ import annotations

import copy
from typing import Any

from .line import SimulatedLine
from .profiles import plc, power_controller, r6, zl69x
from .pty import PtyPair, open_pty_pair
from .tcp import SimulatedTcpSlave

DEMO_BAUDRATE = 19200
DEMO_UNITS = {1: "plc", 2: "zl69x", 3: "power_controller"}
DEMO_ASCII_BAUDRATE = 9600
DEMO_ASCII_UNITS = {4: "zl69x"}
DEMO_TCP_UNITS = {5: "r6"}
DEMO_TCP_SLAVE_ID = 0x01  # the R6's own unit id (it answers 0xFF too)


class DemoLine:
    """Two pty pairs with the demo devices on their simulator ends (RTU and ASCII), and an R6.

    The R6's Modbus TCP listener is bound at once (port 0 on loopback) so that
    ``configure`` can name its address.
    """

    def __init__(self) -> None:
        self.pty: PtyPair = open_pty_pair()
        self.line = SimulatedLine(
            self.pty.sim_fd,
            {1: plc(1), 2: zl69x(2), 3: power_controller(3)},
            baudrate=DEMO_BAUDRATE,
        )
        self.ascii_pty: PtyPair = open_pty_pair()
        self.ascii_line = SimulatedLine(
            self.ascii_pty.sim_fd,
            {4: zl69x(4)},
            baudrate=DEMO_ASCII_BAUDRATE,
            framing="ascii",
        )
        self.tcp_slave = SimulatedTcpSlave({DEMO_TCP_SLAVE_ID: r6(DEMO_TCP_SLAVE_ID)})
        self.tcp_slave.start()

    def configure(self, raw: dict[str, Any], listen: str) -> dict[str, Any]:
        """The configuration tables with the demo lines added, and the demo's listen address
        and a free port for the HTTP endpoint (``auto``) unless the file or a flag says."""
        raw = copy.deepcopy(raw)
        raw.setdefault("server", {}).setdefault("listen", listen)
        raw.setdefault("metrics", {}).setdefault("listen", "auto")  # starts beside anything
        raw["lines"] = {
            "demo": {
                "device": self.pty.path,
                "baudrate": DEMO_BAUDRATE,
                "timeout": 0.5,
                "units": sorted(DEMO_UNITS),
                "names": {"1": "plc", "2": "zl69x recorder", "3": "power controller"},
            },
            "demo-ascii": {
                "device": self.ascii_pty.path,
                "kind": "ascii",
                "data_bits": 8,  # ptys refuse 7; ASCII lines default to 7E1
                "parity": "N",
                "baudrate": DEMO_ASCII_BAUDRATE,
                "units": sorted(DEMO_ASCII_UNITS),
                "names": {"4": "zl69x recorder (ascii)"},
            },
            "demo-tcp": {
                "kind": "tcp",
                "address": self.tcp_slave.host_port,
                "names": {str(DEMO_TCP_SLAVE_ID): "r6 robot controller"},
            },
        }
        raw["routes"] = [
            {"unit": unit, "line": "demo-tcp", "slave": DEMO_TCP_SLAVE_ID}
            for unit in DEMO_TCP_UNITS
        ]
        return raw

    def start(self) -> None:
        """Start answering."""
        self.line.start()
        self.ascii_line.start()

    def stop(self) -> None:
        """Stop answering and release the pty."""
        self.line.stop()
        self.pty.close()
        self.ascii_line.stop()
        self.ascii_pty.close()
        self.tcp_slave.stop()
