"""How a line puts a PDU on the wire and finds the answer in what comes back.

Theory of operation: ``LineCore`` decides *when* and *what* to send; a ``Framing``
says *how*: ``encode(unit, pdu)`` gives the bytes of one request, and
``decoder(unit, request_pdu)`` builds the object that collects the answer and checks
it against the request (see ``ResponseDecoder``). The timing a framing implies (the
gap before a request, the silence that ends or abandons a frame) reaches the core
through the line's policy (``gap``, ``silence``), which knows the line's kind.

The core binds ``encode`` and ``decoder`` once: for RTU they are ``encode_rtu`` and
the ``RtuResponseDecoder`` class themselves, so the RTU path costs what it did
before framings existed.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Final, Protocol

from .ascii import AsciiResponseDecoder, encode_ascii
from .mbap import TransactionIds
from .rtu import RtuFrame, RtuResponseDecoder, encode_rtu


class LineKind(StrEnum):
    """What a downstream line speaks (``kind`` under ``[lines.NAME]``): a fixed label set."""

    RTU = "rtu"
    ASCII = "ascii"
    TCP = "tcp"  # Modbus TCP slaves: MBAP under the gateway's own transaction ids
    TLS = "tls"  # Modbus/TCP Security slaves: the same MBAP framing, over TLS
    RTU_OVER_TCP = "rtu-over-tcp"  # RTU frames over TCP to a serial device server


class ResponseDecoder(Protocol):
    """Collects one answer and checks it against the request on the wire.

    ``feed`` returns the checked frame once complete, ``None`` while incomplete, and
    raises ``ResponseError`` for a frame that must not be passed on; bytes after the
    frame (or after the point of the error) are left in ``leftover``.
    """

    leftover: bytes

    @property
    def buffered(self) -> int: ...

    @property
    def waits_for_silence(self) -> bool: ...

    @property
    def looks_like_answer(self) -> bool: ...

    def feed(self, data: bytes | bytearray | memoryview) -> RtuFrame | None: ...

    def end_of_frame(self) -> RtuFrame: ...

    def reset(self) -> None: ...


class DecoderFactory(Protocol):
    """Builds the decoder for the answer to ``request_pdu`` from ``unit``."""

    def __call__(self, unit: int, request_pdu: bytes) -> ResponseDecoder: ...


class EncodeFunction(Protocol):
    """Builds the bytes of one request frame."""

    def __call__(self, unit: int, pdu: bytes) -> bytes: ...


class Framing:
    """A framing: its kind, its encoder and its answer decoder's factory."""

    __slots__ = ("decoder", "encode", "kind", "transaction_ids")

    def __init__(
        self,
        kind: LineKind,
        encode: EncodeFunction,
        decoder: DecoderFactory,
        transaction_ids: TransactionIds | None = None,
    ) -> None:
        self.kind = kind
        self.encode = encode
        self.decoder = decoder
        #: MBAP only: the counter that numbers this line's requests. Answers then name
        #: their request, so several may be outstanding (``max_in_flight``).
        self.transaction_ids = transaction_ids

    def __repr__(self) -> str:
        return f"Framing({self.kind.value})"


#: Modbus RTU: binary, CRC16, frames delimited by t3.5 of silence (or predicted length).
RTU: Final = Framing(LineKind.RTU, encode_rtu, RtuResponseDecoder)
#: Modbus ASCII: ':' hex characters, LRC, CR LF.
ASCII: Final = Framing(LineKind.ASCII, encode_ascii, AsciiResponseDecoder)

_BY_KIND: Final = {LineKind.RTU: RTU, LineKind.ASCII: ASCII, LineKind.RTU_OVER_TCP: RTU}


def mbap_framing(first_transaction_id: int = 0, kind: LineKind = LineKind.TCP) -> Framing:
    """A new MBAP framing for one downstream TCP line (it numbers that line's requests)."""
    ids = TransactionIds(first_transaction_id)
    return Framing(kind, ids.encode, ids.decoder, ids)


def is_mbap(kind: str) -> bool:
    """True for a line kind framed by MBAP (answers named by transaction id)."""
    try:
        return framing_for(kind).transaction_ids is not None
    except ValueError:
        return False


def framing_for(kind: str) -> Framing:
    """The framing of a line kind (``ValueError`` for a kind without one).

    ``tcp`` and ``tls`` get a framing of their own each time: its transaction ids
    belong to one line. A ``tls`` line's framing is the MBAP framing itself (its
    ``kind`` is ``tcp``): TLS changes the transport, not a byte of the frames.
    """
    try:
        line_kind = LineKind(kind)
    except ValueError:
        raise ValueError(f"line kind {kind!r} has no framing") from None
    if line_kind is LineKind.TCP or line_kind is LineKind.TLS:
        return mbap_framing()
    framing = _BY_KIND.get(line_kind)
    if framing is None:
        raise ValueError(f"line kind {kind!r} has no framing")
    return framing
