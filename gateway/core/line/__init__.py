"""The line as a pure state machine: every decision about the wire, no I/O.

Theory of operation. ``LineCore`` owns one line: which request goes next and
when, the attempt on the wire, retries, late answers, dead-slave isolation,
coalescing and the read cache. It never reads a clock or touches a port: every
entry point takes ``now`` (seconds on one monotonic clock), ``get_timer()`` says
when it next wants ``handle_timer``, and its decisions come out as actions the
driver executes in order: ``transmits`` (write this frame now), ``deliveries``
(this request's answer and outcome) and ``notes`` (events for metrics and logs).
How frames look on the wire is the line's ``Framing`` (``gateway.core.framing``:
RTU by default, ASCII); the decisions are the same for every framing.

Invariants, each checked by the stateful tests in ``tests/property``:

* **Exactly once.** Every submitted request gets exactly one ``Delivery``.
* **Only its own answer.** A frame is delivered to a request only when it can be
  the answer to the attempt on the wire (unit, function, length, echo: see the
  framing's response decoder, e.g. ``RtuResponseDecoder``). After an attempt fails
  without its answer (timeout, or garbage that was not the answer itself), the
  slave's answer may still come, however late: for that slave's *late-answer window*
  no request that could be confused with the lost one (same slave and answer
  signature) is sent; other slaves are served meanwhile. The window lasts until proof
  that the lost answer cannot come (or ``late_answer_window`` seconds, when set): the
  lost answer heard, or the slave answering a request sent after the loss that could
  not be confused with it (a slave answers one request at a time, in order). A request
  held for proof makes the line send a *proof read* of its own (``late``). The retry
  of the lost request itself is exempt: any answer to it is its answer.
* **Quiet line.** Nothing is transmitted before ``gap`` seconds of silence after
  the last byte seen on the line or the end of the gateway's own transmission
  (plus the turnaround after a broadcast).
* **Safe retries.** Only requests without side effects (``pdu.is_safe_to_retry``)
  are sent again after a failed attempt, unless ``retry_unsafe`` says otherwise.
* **Order.** One master's requests to one slave keep read-after-write order: a
  request that may change the slave (a write, any code but a plain read; a broadcast
  changes every slave) passes none of its master's earlier requests to it, and nothing
  of that master passes it, also through the isolated slaves' lane. A read joins another
  master's identical queued read only when no change to that slave was submitted after
  that read and none of its own master's waits; the cache keeps no answer older than a
  change still to run.
* **Fair share.** Masters are served in start-time fair order, charged with the
  wire time their transactions actually took (timeouts included), so a master
  provoking timeouts spends its own share. Each master has its own queue bound
  (0x06 beyond it); the line-wide bound pushes out the longest queue's newest
  request before refusing a master with a shorter queue.
* **Isolation.** A timeout counts against a slave only for a function it has
  answered before (or when it never answered anything), so a master sending a
  code the slave ignores cannot isolate it. After a counted timeout the slave is
  *suspect*: at most one of its requests waits, behind the healthy slaves', and
  others are answered 0x0B at once. ``dead_after`` counted timeouts in a row mark
  it *down*: 0x0B at once, one probe per back-off interval. Suspect and down
  slaves share ``probe_share`` of the line's time; they also go whenever no
  healthy request is waiting.
* **Own echo.** With ``echo`` (a half-duplex adapter that hears itself), the bytes
  of the frame just sent are dropped when they come back, exactly those; bytes that
  are not the echo are the line's, and the echo is still expected after them (until
  the next frame is sent).
* **Another master.** On a shared medium, a request frame the line did not send (its
  own echo and its own answers excepted) is a foreign master's (``foreign``): noted, the
  line *shared* for a while. Until that request's answer is heard or it expires, no
  request whose answer would look the same (same slave, answer signature) is sent, and
  an answer that looks like it is never delivered to one of ours (a request of ours
  already on the wire when the foreign one came is retried, or answered 0x0B).
* **Bounded noise.** If no usable gap appears for ``noisy_after`` seconds while
  requests wait, they are answered 0x0B and the line is *noisy* (new requests are
  answered 0x0B at once) until a gap appears.

The package, by concern (each part keeps its state and answers questions; only the
machine changes what becomes of a request and emits actions):

* ``records``: requests, actions, the policy read, the attempt record;
* ``fair_queue``: the masters' fair order and the queue bounds;
* ``health``: slave health (up, suspect, down) and the probe lane with its share;
* ``late``: late-answer windows;
* ``sharing``: read coalescing and the read cache;
* ``order``: read-after-write questions over the parts above;
* ``wire``: the wire strategy, and ``SerialWire`` (one attempt at a time);
  ``flights``: ``FlightWire`` (several attempts by transaction id on a TCP line). A wire
  decodes and returns what it found (``Finding``); it never calls the machine;
* ``polling``: agent mode's poll plan, the blocks' memory and their freshness;
* ``foreign``: frames heard that no attempt asked for, other masters' requests among
  them, and those requests awaiting their answers;
* ``machine``: ``LineCore``, the one class that makes every transition (its module
  opens with the table of them), and ``pipelined`` (``LineCore`` holding a
  ``FlightWire``).
"""

from __future__ import annotations

from .flights import MAX_IN_FLIGHT
from .machine import LineCore
from .pipelined import PipelinedLineCore, new_line_core
from .records import (
    DISCARD_KINDS,
    FRAME_CACHE_SIZE,
    INFINITY,
    CacheRulePolicy,
    Delivery,
    Handover,
    LateWindow,
    LinePolicy,
    LineRequest,
    LineStats,
    Note,
    Transmit,
    answer_signature,
    may_change,
    no_reply,
)

__all__ = [
    "DISCARD_KINDS",
    "FRAME_CACHE_SIZE",
    "INFINITY",
    "MAX_IN_FLIGHT",
    "CacheRulePolicy",
    "Delivery",
    "Handover",
    "LateWindow",
    "LineCore",
    "LinePolicy",
    "LineRequest",
    "LineStats",
    "Note",
    "PipelinedLineCore",
    "Transmit",
    "answer_signature",
    "may_change",
    "new_line_core",
    "no_reply",
]
