"""One simulated Modbus server (slave): its data tables and its answers to request PDUs.

Theory of operation: ``SimulatedDevice.handle`` takes a request PDU and returns
the response PDU a conforming server would send, following the checks of the
Modbus Application Protocol v1.1b3 in their order: function supported (else
0x01), quantity and structure (else 0x03, via ``gateway.core.pdu.validate_request``
plus the device's own caps), addresses mapped (else 0x02), then execution
(0x04 when a write hits a read-only register). The four data tables are
``DataBank`` objects: sparse, with configurable address ranges, and indexable
from Python so tests can set and check values (``device.holding[0] = 5``).
No I/O and no clock: the line (``gateway.sim.line``) owns timing.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from gateway.core import pdu as fc
from gateway.core.errors import ExceptionCode, ModbusError
from gateway.core.pdu import exception_pdu, validate_request

#: Every function code the simulator implements: all those the core knows by name.
ALL_FUNCTIONS = frozenset(fc.FUNCTION_NAMES)

# Device identification: the individual access code and the last object id of each category.
_DEVICE_ID_INDIVIDUAL = 4
_DEVICE_ID_CATEGORY_LAST = {1: 0x02, 2: 0x7F, 3: 0xFF}  # last object id of each category

_MAX_FIFO_COUNT = 31
_MAX_FILE_RECORD = 0x270F
_EVENT_LOG_SIZE = 64

# Diagnostics (FC 8) sub-functions that return a counter instead of echoing.
_DIAG_CLEAR_COUNTERS = 0x0A
_DIAG_BUS_MESSAGES = 0x0B
_DIAG_BUS_COMM_ERRORS = 0x0C
_DIAG_EXCEPTIONS = 0x0D
_DIAG_SERVER_MESSAGES = 0x0E
_DIAG_NO_RESPONSE = 0x0F
_DIAG_LAST_COUNTER = 0x12


def _u16(data: bytes, offset: int) -> int:
    return (data[offset] << 8) | data[offset + 1]


def _fail(code: ExceptionCode, reason: str) -> ModbusError:
    return ModbusError(code, reason)


def pack_bits(values: Sequence[int]) -> bytes:
    """Bits packed as Modbus sends them: first bit in the low bit of the first byte."""
    out = bytearray((len(values) + 7) // 8)
    for index, value in enumerate(values):
        if value:
            out[index >> 3] |= 1 << (index & 7)
    return bytes(out)


def unpack_bits(data: bytes, count: int) -> list[int]:
    """Inverse of ``pack_bits`` for ``count`` bits."""
    return [(data[index >> 3] >> (index & 7)) & 1 for index in range(count)]


def pack_registers(values: Iterable[int]) -> bytes:
    """Registers big-endian, as on the wire."""
    out = bytearray()
    for value in values:
        out += value.to_bytes(2, "big")
    return bytes(out)


class DataBank:
    """One Modbus table (coils, discrete inputs, holding or input registers).

    Sparse storage (unset addresses read 0) over explicit address ranges, so a
    device can model a map with holes: a request touching an address outside
    every range is answered 0x02, as real devices do. ``read_only`` addresses
    refuse Modbus writes with 0x04 (Python assignment still works).
    """

    __slots__ = ("_max_value", "_ranges", "_read_only", "_values")

    def __init__(
        self,
        ranges: Iterable[range] | int = 0,
        initial: Mapping[int, int] | None = None,
        *,
        bits: bool = False,
        read_only: Iterable[int] = (),
    ) -> None:
        spans = [range(ranges)] if isinstance(ranges, int) else list(ranges)
        merged: list[range] = []
        for span in sorted((s for s in spans if len(s)), key=lambda s: s.start):
            if span.step != 1 or span.start < 0 or span.stop > 0x10000:
                raise ValueError(f"address range {span} must be contiguous within 0..65535")
            if merged and span.start <= merged[-1].stop:
                merged[-1] = range(merged[-1].start, max(merged[-1].stop, span.stop))
            else:
                merged.append(span)
        self._ranges = tuple(merged)
        self._max_value = 1 if bits else 0xFFFF
        self._values: dict[int, int] = {}
        self._read_only = frozenset(read_only)
        for address, value in (initial or {}).items():
            self[address] = value

    @property
    def ranges(self) -> tuple[range, ...]:
        """The mapped address ranges, merged and sorted."""
        return self._ranges

    @property
    def read_only(self) -> frozenset[int]:
        """Addresses that Modbus writes may not change."""
        return self._read_only

    def contains(self, address: int, count: int = 1) -> bool:
        """True when ``address .. address+count-1`` lies inside one mapped range."""
        return any(span.start <= address and address + count <= span.stop for span in self._ranges)

    def __getitem__(self, address: int) -> int:
        if not self.contains(address):
            raise IndexError(f"address {address} is not mapped")
        return self._values.get(address, 0)

    def __setitem__(self, address: int, value: int) -> None:
        if not self.contains(address):
            raise IndexError(f"address {address} is not mapped")
        if isinstance(value, bool):
            value = int(value)
        if not 0 <= value <= self._max_value:
            raise ValueError(f"value {value} outside 0..{self._max_value}")
        self._values[address] = value

    def read(self, address: int, count: int) -> list[int]:
        """Values of a block; the caller checked ``contains``."""
        get = self._values.get
        return [get(a, 0) for a in range(address, address + count)]

    def write(self, address: int, values: Sequence[int]) -> None:
        """Store a block; the caller checked ``contains`` and ``writable``."""
        for offset, value in enumerate(values):
            self._values[address + offset] = value

    def writable(self, address: int, count: int) -> bool:
        """True when no address of the block is read-only."""
        if not self._read_only:
            return True
        return not any(a in self._read_only for a in range(address, address + count))


@dataclass
class DeviceCounters:
    """The diagnostic counters of Modbus over Serial Line (FC 8 sub-functions 0x0B..0x12)."""

    bus_messages: int = 0
    bus_comm_errors: int = 0
    exceptions: int = 0
    server_messages: int = 0
    no_response: int = 0
    events: int = 0  # the FC 11 event counter: successful completions


def _ascii(value: str | bytes) -> bytes:
    return value.encode("ascii") if isinstance(value, str) else bytes(value)


class SimulatedDevice:
    """A Modbus server answering request PDUs from its data tables.

    Everything a profile needs is a constructor argument: which function codes
    exist (others answer 0x01), read/write caps below the protocol maxima
    (answered 0x03, like devices that read at most N registers), identification
    objects for 43/14, server id for FC 17, files for FC 20/21 and FIFOs for FC 24.
    """

    def __init__(
        self,
        *,
        name: str = "device",
        coils: DataBank | None = None,
        discrete_inputs: DataBank | None = None,
        holding: DataBank | None = None,
        input_registers: DataBank | None = None,
        functions: Iterable[int] | None = None,
        max_read_bits: int = 2000,
        max_read_registers: int = 125,
        max_write_bits: int = 1968,
        max_write_registers: int = 123,
        identification: Mapping[int, str | bytes] | None = None,
        individual_access: bool = True,
        server_id: bytes = b"\x01",
        exception_status: int = 0,
        files: Mapping[int, Sequence[int]] | None = None,
        fifos: Mapping[int, Sequence[int]] | None = None,
    ) -> None:
        self.name = name
        self.coils = coils if coils is not None else DataBank(bits=True)
        self.discrete_inputs = (
            discrete_inputs if discrete_inputs is not None else DataBank(bits=True)
        )
        self.holding = holding if holding is not None else DataBank()
        self.input_registers = input_registers if input_registers is not None else DataBank()
        self.functions = frozenset(ALL_FUNCTIONS if functions is None else functions)
        self.max_read_bits = max_read_bits
        self.max_read_registers = max_read_registers
        self.max_write_bits = max_write_bits
        self.max_write_registers = max_write_registers
        self.identification = {k: _ascii(v) for k, v in (identification or {}).items()}
        self.individual_access = individual_access
        self.server_id = server_id
        self.run_indicator = True
        self.exception_status = exception_status
        self.files: dict[int, list[int]] = {k: list(v) for k, v in (files or {}).items()}
        self.fifos: dict[int, list[int]] = {k: list(v) for k, v in (fifos or {}).items()}
        self.counters = DeviceCounters()
        self.event_log: deque[int] = deque(maxlen=_EVENT_LOG_SIZE)
        self._handlers = self._handler_table()

    def _handler_table(self) -> dict[int, Callable[[bytes], bytes]]:
        """Each function code's handler, looked up once per request by ``handle``."""
        return {
            fc.READ_COILS: self._read_coils,
            fc.READ_DISCRETE_INPUTS: self._read_discrete_inputs,
            fc.READ_HOLDING_REGISTERS: self._read_holding,
            fc.READ_INPUT_REGISTERS: self._read_input_registers,
            fc.WRITE_SINGLE_COIL: self._write_single_coil,
            fc.WRITE_SINGLE_REGISTER: self._write_single_register,
            fc.READ_EXCEPTION_STATUS: self._read_exception_status,
            fc.DIAGNOSTICS: self._diagnostics,
            fc.GET_COMM_EVENT_COUNTER: self._comm_event_counter,
            fc.GET_COMM_EVENT_LOG: self._comm_event_log,
            fc.WRITE_MULTIPLE_COILS: self._write_multiple_coils,
            fc.WRITE_MULTIPLE_REGISTERS: self._write_multiple_registers,
            fc.REPORT_SERVER_ID: self._report_server_id,
            fc.READ_FILE_RECORD: self._read_file_record,
            fc.WRITE_FILE_RECORD: self._write_file_record,
            fc.MASK_WRITE_REGISTER: self._mask_write_register,
            fc.READ_WRITE_MULTIPLE_REGISTERS: self._read_write_registers,
            fc.READ_FIFO_QUEUE: self._read_fifo_queue,
            fc.ENCAPSULATED_INTERFACE: self._encapsulated_interface,
        }

    def __repr__(self) -> str:
        return f"SimulatedDevice({self.name!r})"

    # ------------------------------------------------------------------ entry point

    def handle(self, pdu: bytes, *, broadcast: bool = False) -> bytes | None:
        """Execute a request PDU; return the response PDU, or ``None`` for a broadcast.

        A broadcast is executed like any request (only writes have a lasting
        effect) but never answered, as the serial-line specification requires.
        """
        counters = self.counters
        counters.bus_messages += 1
        counters.server_messages += 1
        self.event_log.appendleft(0x80 | (0x40 if broadcast else 0))  # receive event
        response = self._dispatch(pdu)
        function = pdu[0] if pdu else 0
        if broadcast:
            counters.no_response += 1
            return None
        if response[0] & fc.EXCEPTION_FLAG:
            counters.exceptions += 1
            code = response[1]
            self.event_log.appendleft(
                0x40
                | (0x01 if code <= 3 else 0)
                | (0x02 if code == 4 else 0)
                | (0x04 if code in (5, 6) else 0)
            )
        else:
            if function not in (fc.GET_COMM_EVENT_COUNTER, fc.GET_COMM_EVENT_LOG):
                counters.events += 1
            self.event_log.appendleft(0x40)
        return response

    def _dispatch(self, pdu: bytes) -> bytes:
        if not pdu:
            return exception_pdu(0, ExceptionCode.ILLEGAL_FUNCTION)
        function = pdu[0]
        handler = self._handlers.get(function) if function in self.functions else None
        if handler is None:
            return exception_pdu(function, ExceptionCode.ILLEGAL_FUNCTION)
        try:
            validate_request(pdu)
            return handler(pdu)
        except ModbusError as error:
            return exception_pdu(function, error.code)

    # ------------------------------------------------------------------ helpers

    def _check_quantity(self, quantity: int, limit: int, what: str) -> None:
        if quantity > limit:
            raise _fail(
                ExceptionCode.ILLEGAL_DATA_VALUE, f"{what} quantity {quantity} exceeds {limit}"
            )

    @staticmethod
    def _check_mapped(bank: DataBank, address: int, count: int, what: str) -> None:
        if not bank.contains(address, count):
            raise _fail(
                ExceptionCode.ILLEGAL_DATA_ADDRESS,
                f"{what} {address}..{address + count - 1} not mapped",
            )

    @staticmethod
    def _check_writable(bank: DataBank, address: int, count: int) -> None:
        if not bank.writable(address, count):
            raise _fail(
                ExceptionCode.SERVER_DEVICE_FAILURE,
                f"registers {address}..{address + count - 1} are read-only",
            )

    def _read_bits(self, pdu: bytes, bank: DataBank, what: str) -> bytes:
        address, quantity = _u16(pdu, 1), _u16(pdu, 3)
        self._check_quantity(quantity, self.max_read_bits, what)
        self._check_mapped(bank, address, quantity, what)
        data = pack_bits(bank.read(address, quantity))
        return bytes((pdu[0], len(data))) + data

    def _read_registers(self, pdu: bytes, bank: DataBank, what: str) -> bytes:
        address, quantity = _u16(pdu, 1), _u16(pdu, 3)
        self._check_quantity(quantity, self.max_read_registers, what)
        self._check_mapped(bank, address, quantity, what)
        return bytes((pdu[0], 2 * quantity)) + pack_registers(bank.read(address, quantity))

    # ------------------------------------------------------------------ bit and register access

    def _read_coils(self, pdu: bytes) -> bytes:
        return self._read_bits(pdu, self.coils, "coils")

    def _read_discrete_inputs(self, pdu: bytes) -> bytes:
        return self._read_bits(pdu, self.discrete_inputs, "discrete inputs")

    def _read_holding(self, pdu: bytes) -> bytes:
        return self._read_registers(pdu, self.holding, "holding registers")

    def _read_input_registers(self, pdu: bytes) -> bytes:
        return self._read_registers(pdu, self.input_registers, "input registers")

    def _write_single_coil(self, pdu: bytes) -> bytes:
        address = _u16(pdu, 1)
        self._check_mapped(self.coils, address, 1, "coil")
        self._check_writable(self.coils, address, 1)
        self.coils.write(address, [1 if pdu[3] == 0xFF else 0])
        return pdu

    def _write_single_register(self, pdu: bytes) -> bytes:
        address = _u16(pdu, 1)
        self._check_mapped(self.holding, address, 1, "holding register")
        self._check_writable(self.holding, address, 1)
        self.holding.write(address, [_u16(pdu, 3)])
        return pdu

    def _write_multiple_coils(self, pdu: bytes) -> bytes:
        address, quantity = _u16(pdu, 1), _u16(pdu, 3)
        self._check_quantity(quantity, self.max_write_bits, "coils")
        self._check_mapped(self.coils, address, quantity, "coils")
        self._check_writable(self.coils, address, quantity)
        self.coils.write(address, unpack_bits(pdu[6:], quantity))
        return pdu[:5]

    def _write_multiple_registers(self, pdu: bytes) -> bytes:
        address, quantity = _u16(pdu, 1), _u16(pdu, 3)
        self._check_quantity(quantity, self.max_write_registers, "holding registers")
        self._check_mapped(self.holding, address, quantity, "holding registers")
        self._check_writable(self.holding, address, quantity)
        self.holding.write(address, [_u16(pdu, 6 + 2 * i) for i in range(quantity)])
        return pdu[:5]

    def _mask_write_register(self, pdu: bytes) -> bytes:
        address, and_mask, or_mask = _u16(pdu, 1), _u16(pdu, 3), _u16(pdu, 5)
        self._check_mapped(self.holding, address, 1, "holding register")
        self._check_writable(self.holding, address, 1)
        current = self.holding.read(address, 1)[0]
        self.holding.write(address, [(current & and_mask) | (or_mask & ~and_mask & 0xFFFF)])
        return pdu

    def _read_write_registers(self, pdu: bytes) -> bytes:
        read_address, read_quantity = _u16(pdu, 1), _u16(pdu, 3)
        write_address, write_quantity = _u16(pdu, 5), _u16(pdu, 7)
        self._check_quantity(read_quantity, self.max_read_registers, "read")
        self._check_quantity(write_quantity, min(121, self.max_write_registers), "write")
        self._check_mapped(self.holding, read_address, read_quantity, "read registers")
        self._check_mapped(self.holding, write_address, write_quantity, "write registers")
        self._check_writable(self.holding, write_address, write_quantity)
        # The write is performed before the read (MB Application Protocol 6.17).
        self.holding.write(write_address, [_u16(pdu, 10 + 2 * i) for i in range(write_quantity)])
        data = pack_registers(self.holding.read(read_address, read_quantity))
        return bytes((pdu[0], len(data))) + data

    # ------------------------------------------------------------------ serial-line diagnostics

    def _read_exception_status(self, pdu: bytes) -> bytes:
        return bytes((pdu[0], self.exception_status & 0xFF))

    def _diagnostics(self, pdu: bytes) -> bytes:
        """Sub-functions 0x0B..0x12 return a counter; everything else echoes the request."""
        sub_function = _u16(pdu, 1)
        counters = self.counters
        if sub_function == _DIAG_CLEAR_COUNTERS:
            self.counters = DeviceCounters()
            self.event_log.clear()
        elif _DIAG_BUS_MESSAGES <= sub_function <= _DIAG_LAST_COUNTER and len(pdu) == 5:
            value = {
                _DIAG_BUS_MESSAGES: counters.bus_messages,
                _DIAG_BUS_COMM_ERRORS: counters.bus_comm_errors,
                _DIAG_EXCEPTIONS: counters.exceptions,
                _DIAG_SERVER_MESSAGES: counters.server_messages,
                _DIAG_NO_RESPONSE: counters.no_response,
            }.get(sub_function, 0)
            return pdu[:3] + (value & 0xFFFF).to_bytes(2, "big")
        return pdu

    def _comm_event_counter(self, pdu: bytes) -> bytes:
        return bytes((pdu[0], 0, 0)) + (self.counters.events & 0xFFFF).to_bytes(2, "big")

    def _comm_event_log(self, pdu: bytes) -> bytes:
        counters = self.counters
        body = (
            b"\x00\x00"  # status: not busy
            + (counters.events & 0xFFFF).to_bytes(2, "big")
            + (counters.bus_messages & 0xFFFF).to_bytes(2, "big")
            + bytes(self.event_log)
        )
        return bytes((pdu[0], len(body))) + body

    def _report_server_id(self, pdu: bytes) -> bytes:
        body = self.server_id + (b"\xff" if self.run_indicator else b"\x00")
        return bytes((pdu[0], len(body))) + body

    # ------------------------------------------------------------------ files and FIFOs

    def _file_span(self, pdu: bytes, offset: int) -> tuple[list[int], int, int]:
        """The file, record number and record length of one sub-request, checked (else 0x02)."""
        file_number, record, length = (
            _u16(pdu, offset + 1),
            _u16(pdu, offset + 3),
            _u16(pdu, offset + 5),
        )
        records = self.files.get(file_number)
        if records is None or record > _MAX_FILE_RECORD or record + length > len(records):
            raise _fail(
                ExceptionCode.ILLEGAL_DATA_ADDRESS,
                f"file {file_number} records {record}..{record + length - 1} not mapped",
            )
        return records, record, length

    def _read_file_record(self, pdu: bytes) -> bytes:
        out = bytearray()
        for offset in range(2, len(pdu), 7):
            records, record, length = self._file_span(pdu, offset)
            data = pack_registers(records[record : record + length])
            out += bytes((len(data) + 1, 6)) + data
        if len(out) + 2 > fc.MAX_PDU:
            raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, "file record response too long")
        return bytes((pdu[0], len(out))) + bytes(out)

    def _write_file_record(self, pdu: bytes) -> bytes:
        spans: list[tuple[list[int], int, list[int]]] = []
        offset = 2
        while offset < len(pdu):
            records, record, length = self._file_span(pdu, offset)
            values = [_u16(pdu, offset + 7 + 2 * i) for i in range(length)]
            spans.append((records, record, values))
            offset += 7 + 2 * length
        for records, record, values in spans:  # all-or-nothing: checked before written
            records[record : record + len(values)] = values
        return pdu

    def _read_fifo_queue(self, pdu: bytes) -> bytes:
        address = _u16(pdu, 1)
        queue = self.fifos.get(address)
        if queue is None:
            raise _fail(ExceptionCode.ILLEGAL_DATA_ADDRESS, f"no FIFO at {address}")
        if len(queue) > _MAX_FIFO_COUNT:
            raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, f"FIFO holds {len(queue)} > 31 values")
        data = len(queue).to_bytes(2, "big") + pack_registers(queue)
        return bytes((pdu[0],)) + len(data).to_bytes(2, "big") + data

    # ------------------------------------------------------------------ 43/14 identification

    def _encapsulated_interface(self, pdu: bytes) -> bytes:
        if pdu[1] != fc.MEI_READ_DEVICE_ID or not self.identification:
            raise _fail(ExceptionCode.ILLEGAL_FUNCTION, f"MEI type {pdu[1]} not supported")
        code, object_id = pdu[2], pdu[3]
        objects = self.identification
        top = max(objects)
        category = 1 if top <= 0x02 else 2 if top <= 0x7F else 3
        conformity = category | (0x80 if self.individual_access else 0)
        header = bytes((pdu[0], pdu[1], code, conformity))
        if code == _DEVICE_ID_INDIVIDUAL:
            if not self.individual_access:
                raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, "individual access not supported")
            if object_id not in objects:
                raise _fail(ExceptionCode.ILLEGAL_DATA_ADDRESS, f"no object {object_id}")
            value = objects[object_id]
            return header + bytes((0, 0, 1, object_id, len(value))) + value
        if code > category:
            raise _fail(ExceptionCode.ILLEGAL_DATA_VALUE, f"category {code} not supported")
        last = _DEVICE_ID_CATEGORY_LAST[code]
        wanted = sorted(i for i in objects if i <= last)
        if object_id not in wanted:
            object_id = 0  # the specification: restart at the beginning
        body = bytearray()
        count = 0
        more, next_id = 0, 0
        for index in (i for i in wanted if i >= object_id):
            value = objects[index]
            if len(header) + 3 + len(body) + 2 + len(value) > fc.MAX_PDU:
                more, next_id = 0xFF, index
                break
            body += bytes((index, len(value))) + value
            count += 1
        return header + bytes((more, next_id, count)) + bytes(body)
