"""The ``--demo`` line: simulated devices on a pseudo-terminal, served to the real gateway.

A newcomer with no RS485 hardware gets the gateway's real serial path (pyserial
on a pty, the same worker and timing) answering three devices from the vendor
documents: a PLC with a large register map at unit 1, a ZL-69X temperature
controller at unit 2 and a power controller capped at 5-register reads at unit 3.
The line is paced like a real 19200 baud line.
"""

from __future__ import annotations

import copy
from typing import Any

from .line import SimulatedLine
from .profiles import plc, power_controller, zl69x
from .pty import PtyPair, open_pty_pair

DEMO_BAUDRATE = 19200
DEMO_UNITS = {1: "plc", 2: "zl69x", 3: "power_controller"}


class DemoLine:
    """A pty pair with the demo devices on its simulator end."""

    def __init__(self) -> None:
        self.pty: PtyPair = open_pty_pair()
        self.line = SimulatedLine(
            self.pty.sim_fd,
            {1: plc(1), 2: zl69x(2), 3: power_controller(3)},
            baudrate=DEMO_BAUDRATE,
        )

    def configure(self, raw: dict[str, Any], listen: str) -> dict[str, Any]:
        """The configuration tables with the demo line (and the demo listen address) added."""
        raw = copy.deepcopy(raw)
        raw.setdefault("server", {}).setdefault("listen", listen)
        raw["lines"] = {
            "demo": {
                "device": self.pty.path,
                "baudrate": DEMO_BAUDRATE,
                "timeout": 0.5,
                "units": sorted(DEMO_UNITS),
            }
        }
        raw.pop("routes", None)
        return raw

    def start(self) -> None:
        """Start answering."""
        self.line.start()

    def stop(self) -> None:
        """Stop answering and release the pty."""
        self.line.stop()
        self.pty.close()
