"""A simulated RTU bus: Modbus devices from vendor profiles served on a pty with real-line timing.

Used by ``modbus-gateway --demo``, the integration tests and the benchmark;
``python -m gateway.sim`` runs one in its own process.
"""

from .device import DataBank, SimulatedDevice
from .line import LineStats, SimulatedLine, UnitFaults
from .profiles import PROFILES, plc, power_controller, zl69x
from .pty import PtyPair, close_pty_pair, open_pty_pair

__all__ = [
    "PROFILES",
    "DataBank",
    "LineStats",
    "PtyPair",
    "SimulatedDevice",
    "SimulatedLine",
    "UnitFaults",
    "close_pty_pair",
    "open_pty_pair",
    "plc",
    "power_controller",
    "zl69x",
]
