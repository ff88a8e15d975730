"""Our own echo: a half-duplex adapter without echo suppression hands back every byte the
gateway writes. The echo is dropped exactly, wherever it is split; bytes that are not it
are the line's.

Noise can precede the echo and happen to match its first bytes. Those bytes are then taken
for the echo's start, and the echo itself, no longer matching, would pass for the line's:
the echo of an FC 5 or 6 frame reads as that frame's answer on a line, and as a request on
a serial-slave listener. So when the whole frame begins where the rest of it was expected,
the bytes taken before were the line's, and the echo starts again there.
"""

from __future__ import annotations


def strip_echo(data: bytes, left: bytes, frame: bytes) -> tuple[bytes, bytes]:
    """``data`` as the line sent it, without the echo of ``frame`` (of which ``left`` is
    still to come back); and what of the echo is still to come after ``data``."""
    count = min(len(left), len(data))
    if data[:count] == left[:count]:
        return data[count:], left[count:]
    taken = len(frame) - len(left)
    count = min(len(frame), len(data))
    if taken and data[:count] == frame[:count]:
        return frame[:taken] + data[count:], frame[count:]  # the bytes taken were noise
    # Not our echo: a slave talking over our frame (its answer to an earlier request), a
    # master, or noise. Those bytes are the line's; the echo may still follow them.
    return data, left
