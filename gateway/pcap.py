"""A pcapng writer for the live trace: Modbus/TCP on one interface, each RTU line on its own.

Choices, so Wireshark and tshark decode the file without any settings:

- The TCP side is interface ``modbus-tcp`` with link type RAW (101): each
  request and reply becomes one IPv4 (or IPv6) + TCP segment between the
  master's real address and port and the gateway's address on port 502, the
  port Wireshark's Modbus/TCP dissector listens on (whatever port the gateway
  really uses). Sequence numbers run on per connection, so TCP analysis is clean.
- Each serial line is interface ``line NAME`` with link type
  WIRESHARK_UPPER_PDU (252): every frame carries the tag "dissector name =
  mbrtu", so it is decoded as Modbus RTU (unit, PDU, CRC). Port tags tell
  requests from answers (the gateway's side is port 1, the slaves' side 502,
  which is how the dissector tells a query from a response).

The line side is rebuilt from the gateway's trace events: the request as
written (slave address + PDU + CRC) when the master's request arrived and the
slave's answer when the reply went back. Retries, timeouts and requests served
by the read cache are not on it; a read shared by coalescing appears once per
master.
"""

from __future__ import annotations

import ipaddress
import struct
from typing import BinaryIO

from .core.mbap import encode_mbap
from .core.rtu import encode_rtu

LINKTYPE_RAW = 101
LINKTYPE_WIRESHARK_UPPER_PDU = 252
MODBUS_TCP_PORT = 502
_LINE_MASTER_PORT = 1  # the gateway's side of a serial line, in the port tags

_BT_SHB = 0x0A0D0D0A
_BT_IDB = 0x00000001
_BT_EPB = 0x00000006
_OPT_END = 0
_OPT_IF_NAME = 2
_OPT_IF_DESCRIPTION = 3
_TAG_END = 0
_TAG_DISSECTOR_NAME = 12
_TAG_PORT_TYPE = 24
_TAG_SRC_PORT = 25
_TAG_DST_PORT = 26
_PORT_TYPE_TCP = 2
_TCP_PSH_ACK = 0x18

IpAddress = ipaddress.IPv4Address | ipaddress.IPv6Address


def _pad4(data: bytes) -> bytes:
    return data + b"\0" * (-len(data) % 4)


def _block(block_type: int, body: bytes) -> bytes:
    body = _pad4(body)
    total = 12 + len(body)
    return struct.pack("<II", block_type, total) + body + struct.pack("<I", total)


def _option(code: int, value: bytes) -> bytes:
    return struct.pack("<HH", code, len(value)) + _pad4(value)


def _tag(code: int, value: bytes) -> bytes:
    """An exported-PDU tag: big-endian, its length including the padding."""
    value = _pad4(value)
    return struct.pack(">HH", code, len(value)) + value


def _checksum(data: bytes) -> int:
    if len(data) % 2:
        data += b"\0"
    total: int = sum(struct.unpack(f"!{len(data) // 2}H", data))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def parse_peer(peer: str) -> tuple[IpAddress, int]:
    """``"10.0.0.5:4711"`` or ``"::1:4711"`` → (address, port); ``ValueError`` otherwise."""
    host, _, port = peer.rpartition(":")
    return ipaddress.ip_address(host.strip("[]")), int(port)


def ip_tcp_segment(
    source: IpAddress,
    source_port: int,
    destination: IpAddress,
    destination_port: int,
    seq: int,
    ack: int,
    payload: bytes,
) -> bytes:
    """An IPv4 or IPv6 packet carrying one TCP segment (PSH, ACK) with correct checksums."""
    tcp = struct.pack(
        "!HHIIBBHHH",
        source_port,
        destination_port,
        seq & 0xFFFFFFFF,
        ack & 0xFFFFFFFF,
        5 << 4,
        _TCP_PSH_ACK,
        65535,
        0,
        0,
    )
    length = len(tcp) + len(payload)
    if isinstance(source, ipaddress.IPv4Address) and isinstance(destination, ipaddress.IPv4Address):
        pseudo = source.packed + destination.packed + struct.pack("!BBH", 0, 6, length)
        tcp = tcp[:16] + struct.pack("!H", _checksum(pseudo + tcp + payload)) + tcp[18:]
        header = struct.pack(
            "!BBHHHBBH4s4s",
            0x45,
            0,
            20 + length,
            0,
            0x4000,
            64,
            6,
            0,
            source.packed,
            destination.packed,
        )
        header = header[:10] + struct.pack("!H", _checksum(header)) + header[12:]
        return header + tcp + payload
    src6 = _as_v6(source)
    dst6 = _as_v6(destination)
    pseudo = src6.packed + dst6.packed + struct.pack("!I3xB", length, 6)
    tcp = tcp[:16] + struct.pack("!H", _checksum(pseudo + tcp + payload)) + tcp[18:]
    header = struct.pack("!IHBB16s16s", 6 << 28, length, 6, 64, src6.packed, dst6.packed)
    return header + tcp + payload


def _as_v6(address: IpAddress) -> ipaddress.IPv6Address:
    if isinstance(address, ipaddress.IPv6Address):
        return address
    return ipaddress.IPv6Address(f"::ffff:{address}")


class PcapngWriter:
    """Writes trace frames as they come, each block flushed: a killed trace stays readable."""

    def __init__(self, stream: BinaryIO, gateway_address: IpAddress) -> None:
        self._out = stream
        self._gateway = gateway_address
        self._interfaces: dict[str, int] = {}
        self._seq: dict[tuple[str, bool], int] = {}  # (master, from_master) → next sequence
        self.packets = 0
        self._write(
            _block(_BT_SHB, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1) + _option(_OPT_END, b""))
        )

    def _write(self, data: bytes) -> None:
        self._out.write(data)
        self._out.flush()

    def _interface(self, name: str, link_type: int, description: str) -> int:
        index = self._interfaces.get(name)
        if index is None:
            index = self._interfaces[name] = len(self._interfaces)
            options = (
                _option(_OPT_IF_NAME, name.encode())
                + _option(_OPT_IF_DESCRIPTION, description.encode())
                + _option(_OPT_END, b"")
            )
            self._write(_block(_BT_IDB, struct.pack("<HHI", link_type, 0, 0) + options))
        return index

    def _packet(self, interface: int, timestamp: float, data: bytes) -> None:
        micros = round(timestamp * 1_000_000)
        body = (
            struct.pack(
                "<IIIII", interface, micros >> 32, micros & 0xFFFFFFFF, len(data), len(data)
            )
            + data
        )
        self._write(_block(_BT_EPB, body))
        self.packets += 1

    def tcp(
        self,
        timestamp: float,
        master: str,
        from_master: bool,
        transaction_id: int,
        unit: int,
        pdu: bytes,
    ) -> None:
        """One Modbus/TCP ADU between ``master`` (``host:port``) and the gateway."""
        try:
            address, port = parse_peer(master)
        except ValueError:
            return  # not an IP peer (a Unix socket): nothing to put in an IP header
        gateway = self._gateway
        if isinstance(address, ipaddress.IPv6Address) and isinstance(
            gateway, ipaddress.IPv4Address
        ):
            gateway = _as_v6(gateway)
        adu = encode_mbap(transaction_id, unit, pdu)
        forward = self._seq.get((master, True), 1)
        backward = self._seq.get((master, False), 1)
        if from_master:
            packet = ip_tcp_segment(address, port, gateway, MODBUS_TCP_PORT, forward, backward, adu)
            self._seq[(master, True)] = forward + len(adu)
        else:
            packet = ip_tcp_segment(gateway, MODBUS_TCP_PORT, address, port, backward, forward, adu)
            self._seq[(master, False)] = backward + len(adu)
        interface = self._interface("modbus-tcp", LINKTYPE_RAW, "Modbus/TCP masters")
        self._packet(interface, timestamp, packet)

    def rtu(self, timestamp: float, line: str, to_slave: bool, slave: int, pdu: bytes) -> None:
        """One RTU frame on ``line``: slave address, PDU and CRC."""
        frame = encode_rtu(slave, pdu)
        source, destination = (
            (_LINE_MASTER_PORT, MODBUS_TCP_PORT)
            if to_slave
            else (MODBUS_TCP_PORT, _LINE_MASTER_PORT)
        )
        tags = (
            _tag(_TAG_DISSECTOR_NAME, b"mbrtu")
            + _tag(_TAG_PORT_TYPE, struct.pack(">I", _PORT_TYPE_TCP))
            + _tag(_TAG_SRC_PORT, struct.pack(">I", source))
            + _tag(_TAG_DST_PORT, struct.pack(">I", destination))
            + struct.pack(">HH", _TAG_END, 0)
        )
        interface = self._interface(
            f"line {line}", LINKTYPE_WIRESHARK_UPPER_PDU, f"Modbus RTU line {line}"
        )
        self._packet(interface, timestamp, tags + frame)
