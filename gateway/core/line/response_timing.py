"""Learned response timing: how long an attempt waits for its answer.

Theory of operation. A slave's *turnaround* is the time from the end of a request to the
first byte of its answer. Serial, ASCII and RTU-over-TCP lines learn it per slave and
function code (a slave may answer reads in 5 ms and an unknown code only after 0.5 s);
``tcp`` and ``tls`` lines, whose slaves sit behind one connection, learn it per function
for the whole line. The estimate is a decaying peak: the longest turnaround seen, which
forgets ``DECAY_PER_ANSWER`` of itself per attempt (applied every ``DECAY_EVERY`` attempts
to its slave and function; an answer no slower than the peak costs the machine one
comparison: ``Attempt.learn_above``). It is an upper quantile of the last few
hundred answers, not a mean: a slave slow on 1 request in 10 refreshes it long before it
forgets, so the bound keeps covering the slow request. The *bound* is that peak times
``MARGIN``, never below the floor (``FLOOR_S``, ``NETWORK_FLOOR_S``: the scheduling and
network jitter a fast slave's answer meets, on a busy CPU too) nor above ``max_timeout``.
Learning starts cautious: until ``EVIDENCE`` answers of a slave and function have been
heard, the bound stays at ``initial_timeout`` at least (a soft PLC may answer its first
requests fast and later ones anywhere within its cycle); it grows at once on a slower or
late answer, and shrinks only by the slow decay.

An attempt's timeout is the predicted answer's transmission time (the longest frame when
its length cannot be predicted) plus the bound, doubled for each earlier attempt of the
request, up to ``max_timeout``. A slave or function never heard from gets
``initial_timeout``; a request to a slave that never answered is not retried (``ends``),
and beside absent slaves its first contact is a probe (``health``). An answer recognised
as late raises the peak to its turnaround, so the next request is not timed out the same
way. A silent slave teaches nothing: a
timeout never raises the bound.

A number for ``timeout`` (or a ``slave_timeouts`` entry for its slave) is fixed: the
time from the end of the request to the end of the answer, as before, with no back-off.
``noisy_after`` (3 x the line's longest bound) follows the learned values unless set. The
late-answer window does not: a lost answer is waited for until proof that it cannot come
(``late``), whatever was learned, unless ``late_answer_window`` sets a number. The
estimates live as long as the line's core: a reload that reopens the line starts afresh,
as does a restart.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Final

from .. import pdu as fc
from ..ascii import MAX_ASCII_FRAME
from ..framing import Framing, LineKind
from ..rtu import MAX_RTU_FRAME
from .records import INFINITY, LinePolicy

#: The least bound on a serial line: room for the gateway's own scheduling delay on a
#: busy CPU (a fast slave's answer read late is not a slow answer).
FLOOR_S: Final = 0.25
#: The least bound on a network line (RTU over TCP, tcp, tls): the round trip too.
NETWORK_FLOOR_S: Final = 0.3
#: Answers of a slave and function before its bound may fall below ``initial_timeout``:
#: a few fast first answers are no evidence that later ones will be as fast.
EVIDENCE: Final = 10
#: The bound is the peak turnaround times this: room for a slower answer than any yet.
MARGIN: Final = 1.5
#: The peak keeps this much of itself per answer (halved after ~350 answers).
DECAY_PER_ANSWER: Final = 0.998
#: Attempts to a slave and function between two steps of its peak's decay.
DECAY_EVERY: Final = 32
_DECAY_STEP: Final = DECAY_PER_ANSWER**DECAY_EVERY
#: Predicted answer times kept per line (a bound, not an LRU: polling refills it).
PREDICTIONS_KEPT: Final = 256

_BIT_READS: Final = frozenset({fc.READ_COILS, fc.READ_DISCRETE_INPUTS})
_REGISTER_READS: Final = frozenset(
    {fc.READ_HOLDING_REGISTERS, fc.READ_INPUT_REGISTERS, fc.READ_WRITE_MULTIPLE_REGISTERS}
)


def answer_pdu_length(request: bytes) -> int | None:
    """The length of a normal answer's PDU to ``request``, ``None`` when unpredictable."""
    function = request[0]
    if len(request) >= 5:
        if function in _BIT_READS:
            return 2 + (((request[3] << 8) | request[4]) + 7) // 8
        if function in _REGISTER_READS:
            return 2 + 2 * ((request[3] << 8) | request[4])
    if function in fc.ECHOED_WRITES:
        return len(fc.write_response(request))
    return None


class ResponseTiming:
    """The line's learned turnaround bounds and each attempt's timeout (see the module doc)."""

    def __init__(self, policy: LinePolicy, framing: Framing, char_time: float) -> None:
        kind = framing.kind
        #: ``tcp`` and ``tls`` lines learn for the whole line; others per slave.
        self.per_slave = kind not in (LineKind.TCP, LineKind.TLS)
        self.ascii = kind is LineKind.ASCII
        self.char_time = char_time
        self.floor = FLOOR_S if kind in (LineKind.RTU, LineKind.ASCII) else NETWORK_FLOOR_S
        self.bounds: dict[int, float] = {}  # key -> learned bound (``key``)
        #: key -> [decaying peak turnaround, attempts since its last decay step, bound,
        #: answers heard (counted up to ``EVIDENCE``)]
        self.peaks: dict[int, list[float]] = {}
        self.predicted: dict[bytes, float] = {}  # request PDU -> its answer's transmission
        self.longest = 0.0  # the longest bound (for ``noisy_after``)
        #: The zero-turnaround instant of the attempt ``deadline`` last timed, and the
        #: instant past which its answer teaches something (``INFINITY``: fixed timeout).
        self.expected_at = 0.0
        self.learn_above = INFINITY
        self.configure(policy, True, char_time)

    def configure(self, policy: LinePolicy, quiet_line: bool, char_time: float) -> None:
        """Take the line's settings; what was learned stays (a reload that keeps the line)."""
        if char_time != self.char_time:
            self.char_time = char_time
            self.predicted.clear()
        self.policy = policy
        self.learn = policy.learn_timeouts
        self.fixed: dict[int, float] = dict(policy.slave_timeouts)
        #: Learning per slave, no slave fixed: the wire may read ``bounds`` itself.
        self.plain = self.learn and self.per_slave and not self.fixed
        self.maximum = policy.max_timeout
        self.initial = min(policy.initial_timeout, self.maximum)
        self.floor_now = min(self.floor, self.maximum)
        self.quiet_line = quiet_line
        self._refresh_noisy()

    # -- questions -------------------------------------------------------------------------

    def key(self, slave: int, function: int) -> int:
        return (slave << 8 | function) if self.per_slave else function

    def learned(self, slave: int, function: int) -> float | None:
        """The learned bound for ``function`` of ``slave``, ``None`` before its first answer
        or where the timeout is fixed."""
        if not self.learn or slave in self.fixed:
            return None
        return self.bounds.get(self.key(slave, function))

    def slave_timeout(self, slave: int) -> float | None:
        """``slave``'s longest learned bound (its slowest function), ``None`` if none."""
        if not self.learn or slave in self.fixed:
            return None
        if not self.per_slave:
            return max(self.bounds.values(), default=None)
        found = [bound for key, bound in self.bounds.items() if key >> 8 == slave]
        return max(found, default=None)

    def first_contact(self, slave: int) -> bool:
        """True while ``slave`` is waited for ``initial_timeout``: learned timing, not fixed,
        and nothing learned of it yet (not even a late answer)."""
        return self.learn and slave not in self.fixed and self.slave_timeout(slave) is None

    def by_slave(self, heard: Iterable[int]) -> dict[int, float]:
        """Each learned slave's longest bound (on a line that learns per line: the line's,
        for each slave in ``heard``); none where the timeout is fixed."""
        if not self.learn:
            return {}
        if self.per_slave:
            learned: dict[int, float] = {}
            for key, bound in self.bounds.items():
                slave = key >> 8
                if slave not in self.fixed and bound > learned.get(slave, 0.0):
                    learned[slave] = bound
            return learned
        longest = max(self.bounds.values(), default=None)
        if longest is None:
            return {}
        return {slave: longest for slave in heard if slave not in self.fixed}

    def wait(self, slave: int, function: int, attempt: int) -> float:
        """The turnaround allowed for the ``attempt``-th attempt (1 = the first): the bound
        (``initial_timeout`` unknown), doubled per earlier attempt, up to ``max_timeout``;
        a fixed timeout as it is."""
        if not self.learn or slave in self.fixed:
            return self.policy.timeout_for(slave)
        bound = self.bounds.get(self.key(slave, function))
        if bound is None:
            bound = self.initial
        if attempt > 1:
            bound = min(self.maximum, bound * 2.0 ** (attempt - 1))
        return bound

    def deadline(self, slave: int, pdu: bytes, attempt: int, sent_by: float) -> float:
        """When the ``attempt``-th attempt of ``pdu``, sent by ``sent_by``, times out; sets
        ``expected_at`` and ``learn_above``, and counts the attempt for the decay. A fixed
        timeout runs from ``sent_by`` to the end of the answer."""
        if not self.learn or slave in self.fixed:
            self.expected_at = sent_by
            self.learn_above = INFINITY
            return sent_by + self.policy.timeout_for(slave)
        expected = self.expected_at = sent_by + self.answer_time(pdu)
        key = (slave << 8 | pdu[0]) if self.per_slave else pdu[0]
        state = self.peaks.get(key)
        if state is None or state[3] < EVIDENCE:
            self.learn_above = -INFINITY  # among the first answers: whatever it takes teaches
            if state is not None:
                state[1] += 1.0
        else:
            self.learn_above = expected + state[0]
            state[1] += 1.0
            if state[1] >= DECAY_EVERY:
                self.decay(key, state)
        return expected + self.wait(slave, pdu[0], attempt)

    def answer_time(self, pdu: bytes) -> float:
        """The predicted answer's transmission time (the longest frame when unpredictable)."""
        predicted = self.predicted.get(pdu)
        if predicted is None:
            length = answer_pdu_length(pdu)
            if length is None:
                chars = MAX_ASCII_FRAME if self.ascii else MAX_RTU_FRAME
            else:
                chars = 2 * (length + 2) + 3 if self.ascii else length + 3
            predicted = chars * self.char_time
            if len(self.predicted) >= PREDICTIONS_KEPT:
                self.predicted.clear()
            self.predicted[pdu] = predicted
        return predicted

    def longest_attempt(self, slave: int, function: int) -> float:
        """The most a first attempt may hold the line: its wait and two longest frames."""
        chars = MAX_ASCII_FRAME if self.ascii else MAX_RTU_FRAME
        return self.wait(slave, function, 1) + 2 * chars * self.char_time

    def late_window(self) -> float:
        """How long a lost answer may still come: ``late_answer_window`` when set, else
        until proof that it cannot (``INFINITY``: see ``late``), whatever was learned."""
        window = self.policy.late_answer_window
        return INFINITY if window is None else window

    # -- what the line learns --------------------------------------------------------------

    def answered(self, slave: int, function: int, turnaround: float) -> None:
        """An answer came ``turnaround`` seconds after its zero-turnaround instant."""
        key = (slave << 8 | function) if self.per_slave else function
        state = self.peaks.get(key)
        if state is None:
            self.peaks[key] = [turnaround, 0.0, 0.0, 1.0]
            self._set_bound(key, turnaround)
        elif state[3] < EVIDENCE:
            state[3] += 1.0
            if turnaround > state[0]:
                state[0] = turnaround
            self._set_bound(key, state[0])
        elif turnaround > state[0]:
            state[0] = turnaround
            self._set_bound(key, turnaround)

    def decay(self, key: int, state: list[float]) -> None:
        """``DECAY_EVERY`` attempts went to ``key``: its peak forgets a step."""
        state[1] = 0.0
        state[0] *= _DECAY_STEP
        self._set_bound(key, state[0])

    def late(self, slave: int, function: int, turnaround: float) -> None:
        """An answer recognised as late: its turnaround was at least ``turnaround``."""
        self.answered(slave, function, turnaround)

    def _set_bound(self, key: int, peak: float) -> None:
        """The bound for ``key`` from its peak: with the margin, the floor and the cap."""
        least = self.floor_now
        if self.peaks[key][3] < EVIDENCE and self.initial > least:
            least = self.initial  # no evidence yet: not below the first contact's wait
        bound = min(max(peak * MARGIN, least), self.maximum)
        before = self.bounds.get(key, 0.0)
        self.bounds[key] = self.peaks[key][2] = bound
        if bound > self.longest:
            self.longest = bound
            self._refresh_noisy()
        elif before == self.longest and bound < before:
            self.longest = max(self.bounds.values())
            self._refresh_noisy()

    def _refresh_noisy(self) -> None:
        """``noisy_after``: as set, else 3 x the longest wait (``initial_timeout`` until a
        first answer); never on a connection (its frames need no gap)."""
        setting = self.policy.noisy_after
        if not self.quiet_line:
            self.noisy_after = INFINITY
        elif setting is not None:
            self.noisy_after = setting
        elif not self.learn:
            self.noisy_after = self.policy.noisy_deadline
        else:
            learned = min(max(self.longest, self.initial), self.maximum)
            self.noisy_after = 3.0 * max([learned, *self.fixed.values()])
