"""Device profiles built from the vendor documents in the project's reference folder.

Each factory returns a fresh ``SimulatedDevice`` whose map, limits and
function codes follow one real device, so the gateway is exercised against
the quirks it will meet in the field (a map with holes, a 5-register read cap,
a device that knows four function codes). The ``unit`` argument only names
the device; the line decides which address it answers on.

Maps (protocol addresses, 0-based):

``plc`` -- ZQ600 PLC (CODESYS), reference 000. Every function code.
    holding 0..9999: 0..5 = 0, 2, 4, 6, 8, 10 (the manual's ``ARR0`` example, so
    ``01 03 00 00 00 0A`` answers exactly as printed), 1000..9999 hold their own
    address (any block is self-checking), the rest 0; input registers 0..9999
    (register 8 = 0x000A, rest = address + 0x4000, read-only by nature);
    coils and discrete inputs 0..65535 (%QX/%IX0.0..8191.7) seeded with the
    Modbus specification's examples (coils 19..37 read ``CD 6B 05``, inputs
    196..217 read ``AC DB 35``); files 3 and 4 (FC 20/21) and a FIFO at 0x04DE
    (FC 24) also from the specification's examples; exception status 0x6D.
``zl69x`` -- ZL-69X temperature controller, reference 002. FC 1, 3, 6, 16, 43.
    coils 0..31 (alarms and relay states; the document's PLC addresses 1..32),
    holding 0..47 (PLC addresses 1..48; temperatures x10); reads capped at 32
    coils and 48 registers, writes at 40; measured values and reserved
    registers are read-only (write answers 0x04); identification stream-only.
``power_controller`` -- power controller, reference 001. FC 3, 4, 6, 16.
    "menus" 0..99 as holding registers, read by FC 3 and FC 4 alike; reads
    capped at 5 registers (0x03 beyond); 3..5 = output voltage 0, current 18.3
    (183), power 0, as in the document's example frame.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from types import MappingProxyType

from gateway.core import pdu as fc

from .device import DataBank, SimulatedDevice

# Modbus specification examples (MB Application Protocol v1.1b3), reused as seed values.
_SPEC_COILS = (19, bytes.fromhex("CD6B05"), 19)  # start, packed bits, count
_SPEC_INPUTS = (196, bytes.fromhex("ACDB35"), 22)


def _bits_from(start: int, packed: bytes, count: int) -> dict[int, int]:
    return {start + i: (packed[i >> 3] >> (i & 7)) & 1 for i in range(count)}


def plc(unit: int = 1) -> SimulatedDevice:
    """ZQ600 PLC: a large map and every function code the gateway may forward."""
    holding_initial = {i: 2 * i for i in range(6)}
    holding_initial.update({i: i for i in range(1000, 10000)})
    input_initial = {i: (i + 0x4000) & 0xFFFF for i in range(10000)}
    input_initial[8] = 0x000A
    return SimulatedDevice(
        name=f"plc@{unit}",
        coils=DataBank(0x10000, _bits_from(*_SPEC_COILS), bits=True),
        discrete_inputs=DataBank(0x10000, _bits_from(*_SPEC_INPUTS), bits=True),
        holding=DataBank(10000, holding_initial),
        input_registers=DataBank(10000, input_initial),
        identification={0x00: "Nietz Electric", 0x01: "ZQ600", 0x02: "V1.0.1.1"},
        server_id=b"ZQ600",
        exception_status=0x6D,
        files={
            3: [0] * 9 + [0x33CD, 0x0040] + [0] * 89,
            4: [0, 0x0DFE, 0x0020] + [0] * 97,
        },
        fifos={0x04DE: [0x01B8, 0x1284]},
    )


# ZL-69X registers, by protocol address (the document's PLC address - 1).
_ZL_HOLDING = {
    0: 275,  # room temperature 27.5 C (the document's example)
    1: 0xFF9D,  # evaporator temperature -9.9 C (the document's example)
    8: 250,  # setpoint for cooling 25.0 C
    9: 180,  # setpoint for heating 18.0 C
    10: 20,  # hysteresis 2.0 C
    11: 400,  # high temperature alarm point 40.0 C
    12: 50,  # low temperature alarm point 5.0 C
    13: 100,  # evaporator fan setpoint 10.0 C
    14: 20,  # evaporator fan hysteresis 2.0 C
    15: 30,  # evaporator protection point 3.0 C
    18: 0,  # room sensor calibration
    19: 0,  # evaporator sensor calibration
    20: 1,  # high temperature alarm enabled
    21: 1,  # low temperature alarm enabled
    22: 1,  # lack of freon alarm enabled
    29: 1,  # evaporator sensor works
    30: 0,  # compressor enabled
    31: 0,  # heater enabled
    32: 0,  # evaporator fan: temperature control
    34: 0,  # digital input: normally closed
    36: 1,  # buzzer enabled
    37: 3,  # compressor delay protection time, min
    38: 2,  # compressor minimum run time, min
    41: 0xFF00,  # on/off: on
}
_ZL_READ_ONLY = (0, 1, *range(2, 8), 16, 17, *range(23, 29), 33, 35, 39, 40, *range(42, 48))
_ZL_COILS = {16: 1, 19: 1}  # compressor on, evaporator fan on


def zl69x(unit: int = 1) -> SimulatedDevice:
    """ZL-69X temperature controller: small map, few function codes, tight read caps."""
    return SimulatedDevice(
        name=f"zl69x@{unit}",
        coils=DataBank(32, _ZL_COILS, bits=True, read_only=range(32)),
        holding=DataBank(48, _ZL_HOLDING, read_only=_ZL_READ_ONLY),
        functions=(
            fc.READ_COILS,
            fc.READ_HOLDING_REGISTERS,
            fc.WRITE_SINGLE_REGISTER,
            fc.WRITE_MULTIPLE_REGISTERS,
            fc.ENCAPSULATED_INTERFACE,
        ),
        max_read_bits=32,
        max_read_registers=48,
        max_write_registers=40,
        identification={0x00: "Companyidentification", 0x01: "ZL-69X", 0x02: "V2.11"},
        individual_access=False,  # conformity level 0x01 in the document's example
    )


def power_controller(unit: int = 1) -> SimulatedDevice:
    """Power controller that reads at most 5 registers per request (0x03 beyond)."""
    menus = DataBank(100, {3: 0, 4: 183, 5: 0})
    return SimulatedDevice(
        name=f"power_controller@{unit}",
        holding=menus,
        input_registers=menus,  # FC 4 reads the same menus, read-only by function
        functions=(
            fc.READ_HOLDING_REGISTERS,
            fc.READ_INPUT_REGISTERS,
            fc.WRITE_SINGLE_REGISTER,
            fc.WRITE_MULTIPLE_REGISTERS,
        ),
        max_read_registers=5,
    )


#: Profile name -> factory taking the unit address.
PROFILES: Mapping[str, Callable[[int], SimulatedDevice]] = MappingProxyType(
    {"plc": plc, "zl69x": zl69x, "power_controller": power_controller}
)
