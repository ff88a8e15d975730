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
``r6`` -- R6 robot controller, a Modbus TCP slave, reference 003. FC 1, 3, 4, 5, 6, 16.
    Answers unit id 0x01 and 0xFF (served by ``gateway.sim.tcp``). Holding registers,
    read by FC 3 and FC 4 alike, as the document's examples print them: 0 = version
    length in bytes (0x29), 1..21 = the version string (two characters a register,
    the last low byte 0), 0x82 = number of counters (2), 0x83..0x882 = counter ids,
    32-bit each, unused slots 0xFFFF. 32-bit values take two registers, 64-bit values
    four, the most significant word at the lowest address (the document's data format).
    The document's address table (its section 4) is not in the reference extract: the
    rest of the map is the simulator's own, at 0x0900 and up (``R6_*`` constants below).
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


def words32(value: int) -> tuple[int, int]:
    """A 32-bit value (two's complement if negative) as the R6 stores it: high word first."""
    value &= 0xFFFF_FFFF
    return value >> 16, value & 0xFFFF


def words64(value: int) -> tuple[int, int, int, int]:
    """A 64-bit value (two's complement if negative) as four registers, most significant first."""
    value &= 0xFFFF_FFFF_FFFF_FFFF
    return (value >> 48, (value >> 32) & 0xFFFF, (value >> 16) & 0xFFFF, value & 0xFFFF)


# R6 robot controller (reference 003). The document's own addresses:
R6_VERSION = b"AM8-QC-RXE-7.8.02-bate7_FAKE_TGF_ENCODER\x00"  # 0x29 bytes, as printed
R6_VERSION_LENGTH = 0x0000
R6_VERSION_START = 0x0001
R6_COUNTER_COUNT = 0x0082
R6_COUNTER_IDS = 0x0083  # 2 registers per counter id, up to 0x0882
R6_COUNTER_IDS_END = 0x0883
R6_COUNTERS = (0, 1)  # the document's example: two counters, ids 0 and 1
#: The simulator's own addresses (the document's address table is not in the extract).
R6_MODE = 0x0900  # current mode: 0 manual, 1 auto, 2 remote
R6_AXIS_COUNT = 0x0901
R6_ALARM = 0x0902  # current alarm number, 0 = none
R6_GLOBAL_SPEED = 0x0903  # percent, written by FC 6 (the document's section 3.2.2)
R6_COMMAND = 0x0904  # command register, written by FC 6 (section 3.2.1)
R6_AXIS_POSITIONS = 0x0910  # 6 x int32, 0.001 degree
R6_WORLD_POSITION = 0x0920  # X, Y, Z (0.001 mm), A, B, C (0.001 degree), int32 each
R6_CYCLE_COUNT = 0x0930  # uint64
R6_RUN_TIME_MS = 0x0934  # uint64
R6_COUNTER_VALUES = 0x0A00  # int64 per counter id: 0x0A00 + 4 x id
R6_MAP_END = 0x0A10
R6_AXES = (-123456, 45000, 90000, -1500, 30000, 0)
R6_WORLD = (512250, -100500, 800000, 180000, 0, -90000)
R6_CYCLES = 0x1_2345_6789
R6_RUN_TIME = 0x0000_0123_4567_89AB
R6_COUNTER_START = (-2, 0x7FFF_FFFF_FFFF)
R6_OUTPUTS = 128  # coils 0..127: IO board outputs (FC 1 reads, FC 5 writes)


def _r6_holding() -> dict[int, int]:
    padded = R6_VERSION + b"\x00" * (len(R6_VERSION) % 2)
    holding = {R6_VERSION_LENGTH: len(R6_VERSION)}
    for index in range(0, len(padded), 2):
        holding[R6_VERSION_START + index // 2] = (padded[index] << 8) | padded[index + 1]
    holding[R6_COUNTER_COUNT] = len(R6_COUNTERS)
    for address in range(R6_COUNTER_IDS, R6_COUNTER_IDS_END):
        holding[address] = 0xFFFF  # the document: slots past the last counter read 0xFF
    for slot, counter in enumerate(R6_COUNTERS):
        for offset, word in enumerate(words32(counter)):
            holding[R6_COUNTER_IDS + 2 * slot + offset] = word
    holding.update({R6_MODE: 1, R6_AXIS_COUNT: len(R6_AXES), R6_ALARM: 0, R6_GLOBAL_SPEED: 50})
    for base, values in ((R6_AXIS_POSITIONS, R6_AXES), (R6_WORLD_POSITION, R6_WORLD)):
        for index, value in enumerate(values):
            holding[base + 2 * index], holding[base + 2 * index + 1] = words32(value)
    for base, value in (
        (R6_CYCLE_COUNT, R6_CYCLES),
        (R6_RUN_TIME_MS, R6_RUN_TIME),
        *(
            (R6_COUNTER_VALUES + 4 * c, v)
            for c, v in zip(R6_COUNTERS, R6_COUNTER_START, strict=True)
        ),
    ):
        for offset, word in enumerate(words64(value)):
            holding[base + offset] = word
    return holding


def r6(unit: int = 1) -> SimulatedDevice:
    """R6 robot controller: a Modbus TCP slave with 32- and 64-bit values, high word first."""
    writable = {R6_GLOBAL_SPEED, R6_COMMAND, *range(R6_COUNTER_VALUES, R6_MAP_END)}
    registers = DataBank(
        (range(0, R6_COUNTER_IDS_END), range(R6_MODE, R6_MAP_END)),
        _r6_holding(),
        read_only=[a for a in range(R6_MAP_END) if a not in writable],
    )
    return SimulatedDevice(
        name=f"r6@{unit}",
        coils=DataBank(R6_OUTPUTS, {0: 1, 3: 1}, bits=True),
        holding=registers,
        input_registers=registers,  # the document's table serves FC 3 and FC 4 alike
        functions=(
            fc.READ_COILS,
            fc.READ_HOLDING_REGISTERS,
            fc.READ_INPUT_REGISTERS,
            fc.WRITE_SINGLE_COIL,
            fc.WRITE_SINGLE_REGISTER,
            fc.WRITE_MULTIPLE_REGISTERS,
        ),
    )


#: Profile name -> factory taking the unit address.
PROFILES: Mapping[str, Callable[[int], SimulatedDevice]] = MappingProxyType(
    {"plc": plc, "zl69x": zl69x, "power_controller": power_controller, "r6": r6}
)
