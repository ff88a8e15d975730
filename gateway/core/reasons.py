"""Why a master's connection ended, was refused, or what its bytes did wrong.

Part of the core's one vocabulary (``gateway.core.outcome`` re-exports it): the
listeners name a reason with these members, metrics use their values as the
``reason`` and ``kind`` label values, so each label's set is fixed, small, and
every series of it can be created at 0 before the first event.
"""

from __future__ import annotations

from enum import StrEnum


class CloseReason(StrEnum):
    """Why a master's connection closed: the ``reason`` label of ``connections_closed_total``."""

    PEER_CLOSED = "peer_closed"  # the master closed it
    ERROR = "error"  # the socket failed (reset, timeout)
    PROTOCOL_ERROR = "protocol_error"  # a malformed MBAP header
    IDLE = "idle"  # no complete request for server.idle_timeout
    EVICTED = "evicted"  # closed to make room for a new master
    STALLED = "stalled"  # left its replies unread for server.send_timeout
    SHUTDOWN = "shutdown"  # the gateway stopped
    NO_LONGER_ADMITTED = "no_longer_admitted"  # a reload's allow lists, CAs or dates refuse it


class RejectReason(StrEnum):
    """Why a connection was refused at accept: ``connections_rejected_total``'s ``reason``."""

    MAX_CONNECTIONS = "max_connections"  # full, and the fair share found nothing to evict
    MAX_PER_SOURCE = "max_per_source"  # that source address has all it may have


class MasterFault(StrEnum):
    """Malformed input from a master: the ``kind`` label of ``protocol_errors_total``.

    The same value means the same fault on every listener (a wrong LRC is ``bad_crc``
    as a wrong CRC is). ``gateway.core.slave_side.FrameFault`` names the serial-slave
    listener's subset.
    """

    BAD_PROTOCOL_ID = "bad_protocol_id"  # MBAP: protocol id not 0 (the connection closes)
    BAD_LENGTH = "bad_length"  # MBAP: length outside 2..254 (the connection closes)
    BAD_CRC = "bad_crc"  # RTU or ASCII: the CRC (LRC) is wrong
    TOO_LONG = "too_long"  # RTU or ASCII: no end of frame within a frame's worth
    INVALID_REQUEST = "invalid_request"  # a well-framed request no slave could accept
    BAD_CHAR = "bad_char"  # ASCII: a character that is not hex, or LF without CR
    RESTARTED = "restarted"  # ASCII: a ':' inside a frame
    INCOMPLETE = "incomplete"  # ASCII: the characters stopped for inter_char_timeout
