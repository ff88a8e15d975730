"""A simulated RTU bus: Modbus devices from vendor profiles served on a pty with real-line timing.

The same devices can also be a Modbus TCP slave (``gateway.sim.tcp``). Used by
``modbus-gateway --demo``, the integration tests and the benchmark;
``python -m gateway.sim`` runs either in its own process. ``MultidropBus`` joins
several gateways and the simulated slaves on one simulated RS-485 bus.
"""

from .device import DataBank, SimulatedDevice
from .line import SimulatedLine, SimulatedLineStats, UnitFaults
from .multidrop import BusCollision, BusFrame, BusNode, BusStats, BusTimeline, MultidropBus
from .profiles import PROFILES, plc, power_controller, r6, zl69x
from .pty import PtyPair, close_pty_pair, open_pty_pair
from .tcp import SimulatedTcpSlave, TcpSlaveServer, TcpSlaveStats

__all__ = [
    "PROFILES",
    "BusCollision",
    "BusFrame",
    "BusNode",
    "BusStats",
    "BusTimeline",
    "DataBank",
    "MultidropBus",
    "PtyPair",
    "SimulatedDevice",
    "SimulatedLine",
    "SimulatedLineStats",
    "SimulatedTcpSlave",
    "TcpSlaveServer",
    "TcpSlaveStats",
    "UnitFaults",
    "close_pty_pair",
    "open_pty_pair",
    "plc",
    "power_controller",
    "r6",
    "zl69x",
]
