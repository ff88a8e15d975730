"""One serial line: a fair queue and exactly one transaction on the wire at a time.

Theory of operation: masters ``submit`` requests; each master has its own FIFO
and the worker takes one request from each master in turn, so a deep pipeline
cannot starve the others. For each request the worker keeps at least the
frame gap (t3.5 by default) of silence after the last byte seen on the line
(measured with ``time.monotonic`` and waited for with ``PreciseClock``), drops
whatever arrived unasked, writes unit + PDU + CRC, and feeds the answer to the
core's ``RtuResponseDecoder``, which knows from the function code when the
answer is complete. Timeouts and bad CRCs are retried (writes only when the
line allows it); a frame from another unit or for another request is
discarded and the wait goes on. After a timeout or a garbled answer the line
must be silent for a frame gap before anything is sent, and bytes arriving
while no transaction waits are discarded, so a late answer is never taken for
the next one. While the port is down every request is answered 0x0A at once
and the port is reopened with back-off.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from ..config import LineConfig
from ..core import pdu as fc
from ..core.errors import ExceptionCode, ResponseError
from ..core.rtu import RtuFrame, RtuResponseDecoder, encode_rtu
from ..core.timing import character_time
from ..logs import RateLimitedLogger
from ..metrics import UNIT_LABELS, GatewayMetrics
from ..status import LineState, LineStatus, SlaveState, SlaveStatus
from .clock import PreciseClock
from .serial_port import SerialLink, SerialPortError, open_serial

log = logging.getLogger("gateway.bus")

#: Called once per request with the response PDU (normal or exception) and its outcome.
ReplyCallback = Callable[[bytes, str], None]

_DISCARD_KINDS = frozenset({"unexpected_unit", "unexpected_function", "mismatch"})
_REOPEN_FIRST_DELAY = 0.05
_REOPEN_MAX_DELAY = 0.5


@dataclass(slots=True, eq=False)
class Request:
    """A request waiting for, or on, the line."""

    slave: int
    pdu: bytes
    client: object
    reply: ReplyCallback
    enqueued_at: float = 0.0
    broadcast: bool = False
    cancelled: bool = False
    answered: bool = False
    probe: bool = False
    epoch: int = 0
    followers: list[Request] = field(default_factory=list)

    def answer(self, pdu: bytes, outcome: str) -> None:
        """Deliver the answer exactly once, to this request and those that joined it."""
        if not self.answered:
            self.answered = True
            self.reply(pdu, outcome)
        for follower in self.followers:
            follower.answer(pdu, outcome)
        self.followers.clear()

    @property
    def wanted(self) -> bool:
        """False when nobody is waiting for the answer any more."""
        return not self.cancelled or any(not f.cancelled for f in self.followers)


@dataclass(slots=True)
class SlaveHealth:
    """Dead-slave isolation state of one slave address."""

    consecutive_timeouts: int = 0
    down: bool = False
    backoff: float = 0.0
    next_probe_at: float = 0.0
    probing: bool = False


class FairQueue:
    """Per-master FIFOs served round robin."""

    __slots__ = ("_queues", "_ready", "size")

    def __init__(self) -> None:
        self._queues: dict[object, deque[Request]] = {}
        self._ready: deque[object] = deque()
        self.size = 0

    def push(self, request: Request) -> None:
        """Queue ``request`` behind its master's earlier ones."""
        queue = self._queues.get(request.client)
        if queue is None:
            queue = self._queues[request.client] = deque()
            self._ready.append(request.client)
        queue.append(request)
        self.size += 1

    def pop(self) -> Request | None:
        """The next master's oldest request, or ``None`` when empty."""
        while self._ready:
            client = self._ready.popleft()
            queue = self._queues[client]
            request = queue.popleft()
            self.size -= 1
            if queue:
                self._ready.append(client)
            else:
                del self._queues[client]
            return request
        return None

    def drain(self) -> list[Request]:
        """Remove and return everything queued."""
        requests = [request for queue in self._queues.values() for request in queue]
        self._queues.clear()
        self._ready.clear()
        self.size = 0
        return requests


class Bus:
    """One RS485 line and the worker that owns it."""

    def __init__(
        self,
        config: LineConfig,
        metrics: GatewayMetrics,
        loop: asyncio.AbstractEventLoop,
        clock: PreciseClock,
    ) -> None:
        self.config = config
        self.name = config.name
        self._metrics = metrics
        self._loop = loop
        self._clock = clock
        self._queue = FairQueue()
        self._wakeup = asyncio.Event()
        self._link: SerialLink | None = None
        self._worker: asyncio.Task[None] | None = None
        self._reopener: asyncio.Task[None] | None = None
        self._stopping = False
        self._quiet_since = 0.0  # monotonic time of the last activity on the line
        self._decoder: RtuResponseDecoder | None = None
        self._waiter: asyncio.Future[RtuFrame | ResponseError | None] | None = None
        self._silence_timer: asyncio.TimerHandle | None = None
        self._garbled: ResponseError | None = None
        self._garbled_timer: asyncio.TimerHandle | None = None
        self._current_unit = "0"
        self._open_error = ""
        self._char_time = character_time(
            config.baudrate, config.data_bits, config.parity, config.stop_bits
        )
        self._garbled_wait = max(2 * config.silence, 0.003)
        self._health: dict[int, SlaveHealth] = {}
        self._waiting_reads: dict[tuple[int, bytes], Request] = {}
        self._write_epoch: dict[int, int] = {}  # per slave: writes queued so far
        self._broadcast_epoch = 0  # broadcasts queued so far (they write to every slave)
        self._cache: dict[tuple[int, bytes], tuple[float, bytes]] = {}
        self.idle = asyncio.Event()
        self.idle.set()
        self._counters = metrics.line_counters(self.name)
        self._m_queue_wait = metrics.queue_wait.labels(self.name)
        self._m_wire = metrics.wire_duration.labels(self.name)
        self._m_line_up = metrics.line_up.labels(self.name)
        self._m_coalesced = metrics.coalesced.labels(self.name)
        self._m_line_up.set(0)
        metrics.prepare_line(self.name)
        self._fault_log = RateLimitedLogger(log, loop)  # first fault at once, then counts

    # -- lifecycle ---------------------------------------------------------------------

    @property
    def up(self) -> bool:
        """True while the serial port is open."""
        return self._link is not None and not self._link.closed

    @property
    def queued(self) -> int:
        """Requests waiting for the line."""
        return self._queue.size

    def start(self) -> None:
        """Open the port (or begin retrying) and start the worker."""
        self._try_open()
        if not self.up:
            self._schedule_reopen()
        self._start_worker()

    def _start_worker(self) -> None:
        self._worker = self._loop.create_task(self._run(), name=f"bus-{self.name}")
        self._worker.add_done_callback(self._worker_ended)

    def _worker_ended(self, worker: asyncio.Task[None]) -> None:
        """A worker only ends when the line stops; anything else is a bug to report loudly."""
        if worker.cancelled() or self._stopping:
            return
        error = worker.exception()
        log.critical("line %s: worker failed, restarting it", self.name, exc_info=error)
        self._fail_queued()
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)
        self._decoder = None
        self._waiter = None
        self._start_worker()

    async def stop(self, grace: float) -> None:
        """Finish the transaction on the wire (within ``grace``), answer the rest 0x0A, close."""
        self._stopping = True
        self._fail_queued()
        self._wakeup.set()
        if self._reopener is not None:
            self._reopener.cancel()
        if self._worker is not None:
            try:
                await asyncio.wait_for(asyncio.shield(self._worker), grace)
            except TimeoutError:
                # Grace over: give up the transaction on the wire so its master still gets
                # an answer (0x0A, as for a lost line) rather than a closed connection.
                if self._link is not None:
                    self._link.close()  # nothing more goes out
                waiter = self._waiter
                if waiter is not None and not waiter.done():
                    waiter.set_result(None)
                try:
                    await asyncio.wait_for(asyncio.shield(self._worker), 0.1)
                except TimeoutError:
                    self._worker.cancel()
            except asyncio.CancelledError:
                pass
        if self._link is not None:
            self._link.close()
            self._link = None
        self._m_line_up.set(0)
        self._fault_log.flush()

    def reconfigure(self, config: LineConfig) -> None:
        """Take new timeouts, retries and limits; the port settings must be unchanged."""
        self.config = config
        if config.dead_after <= 0:  # isolation switched off: every slave is served again
            for slave in [slave for slave, health in self._health.items() if health.down]:
                self._metrics.slave_up.labels(self.name, UNIT_LABELS[slave]).set(1)
            self._health.clear()
        if not config.cache:
            self._cache.clear()

    # -- the master's side -------------------------------------------------------------

    def submit(self, request: Request) -> bool:
        """Queue a request; ``False`` (answer 0x0A) when the line is down, stopping or full.

        A request may also be answered at once, before this returns: 0x0B for a slave
        isolated as dead, a cached read, or a read joining an identical queued one.
        """
        if self._stopping or not self.up or self._queue.size >= self.config.max_queue:
            return False
        now = time.monotonic()
        request.enqueued_at = now
        if request.broadcast:
            # A broadcast writes to every slave: no later read may share a transaction
            # queued before it, and nothing cached may survive it.
            self._broadcast_epoch += 1
            self._cache.clear()
        elif not self._admit(request, now):
            return True
        self._queue.push(request)
        self._counters.queue_depth = self._queue.size
        self._wakeup.set()
        return True

    def _admit(self, request: Request, now: float) -> bool:
        """Isolation, cache and coalescing; ``False`` when the request is already answered."""
        slave = request.slave
        health = self._health.get(slave)
        if health is not None and health.down:
            if health.probing or now < health.next_probe_at:
                request.answer(self._exception(request, ExceptionCode.GATEWAY_TARGET_FAILED),
                               "target_failed")  # fmt: skip
                return False
            health.probing = True
            request.probe = True
        function = request.pdu[0]
        if function not in fc.READ_FUNCTIONS:
            # Anything but a plain read may change the slave: later reads must not be
            # served by a response from before it.
            self._write_epoch[slave] = self._write_epoch.get(slave, 0) + 1
            self._invalidate_cache(slave)
            return True
        key = (slave, request.pdu)
        if self.config.cache:
            cached = self._cache.get(key)
            if cached is not None and now <= cached[0]:
                request.answer(cached[1], "cached")
                return False
        epoch = self._write_epoch.get(slave, 0) + self._broadcast_epoch
        if self.config.coalesce and not request.probe:
            leader = self._waiting_reads.get(key)
            if leader is not None and leader.epoch == epoch and not leader.answered:
                leader.followers.append(request)
                self._m_coalesced.inc()
                return False
            request.epoch = epoch
            self._waiting_reads[key] = request
        return True

    # -- the worker --------------------------------------------------------------------

    async def _run(self) -> None:
        while not self._stopping:
            request = self._queue.pop()
            if request is None:
                self.idle.set()
                self._wakeup.clear()
                await self._wakeup.wait()
                continue
            self.idle.clear()
            self._counters.queue_depth = self._queue.size
            if not request.wanted:
                self._close_to_joiners(request)
                for dropped in (request, *request.followers):  # reads that joined it too
                    self._metrics.count_request(
                        self.name, UNIT_LABELS[dropped.slave], dropped.pdu[0], "dropped"
                    )
                self._end_probe(request)
                continue
            health = self._health.get(request.slave)
            if health is not None and health.down and not request.probe:
                self._close_to_joiners(request)
                request.answer(self._exception(request, ExceptionCode.GATEWAY_TARGET_FAILED),
                               "target_failed")  # fmt: skip
                continue
            self._m_queue_wait.observe(time.monotonic() - request.enqueued_at)
            try:
                if request.broadcast:
                    await self._broadcast(request)
                else:
                    await self._transact(request)
            except SerialPortError as error:
                request.answer(
                    self._exception(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE), "no_route"
                )
                log.warning("line %s: %s", self.name, error)
        self.idle.set()

    async def _transact(self, request: Request) -> None:
        config = self.config
        retry_allowed = request.pdu[0] not in fc.WRITE_FUNCTIONS or config.retry_writes
        attempts = 1 if request.probe else 1 + (config.retries if retry_allowed else 0)
        timeout = config.timeout_for(request.slave)
        unit = UNIT_LABELS[request.slave]
        frame = encode_rtu(request.slave, request.pdu)
        transmit_time = len(frame) * self._char_time
        for attempt in range(attempts):
            if attempt:
                self._metrics.retries.labels(self.name, unit).inc()
            link = await self._ready_to_send()
            if link is None:
                self._close_to_joiners(request)
                request.answer(
                    self._exception(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE), "no_route"
                )
                return
            self._decoder = RtuResponseDecoder(request.slave, request.pdu)
            self._current_unit = unit
            self._garbled = None
            waiter: asyncio.Future[RtuFrame | ResponseError | None] = self._loop.create_future()
            self._waiter = waiter
            if not attempt:
                self._close_to_joiners(request)
            link.write(frame)
            sent_at = time.monotonic()
            self._quiet_since = sent_at + transmit_time
            counters = self._counters
            counters.frames_sent += 1
            counters.bytes_written += len(frame)
            timer = self._loop.call_later(transmit_time + timeout, self._on_timeout, waiter)
            try:
                result = await waiter
            finally:
                timer.cancel()
                self._decoder = None
                self._waiter = None
                if self._silence_timer is not None:
                    self._silence_timer.cancel()
                    self._silence_timer = None
                if self._garbled_timer is not None:
                    self._garbled_timer.cancel()
                    self._garbled_timer = None
                self._garbled = None
            if isinstance(result, RtuFrame):
                done_at = time.monotonic()
                self._m_wire.observe(done_at - sent_at)
                self._counters.frames_received += 1
                self._slave_answered(request)
                if fc.is_exception(result.pdu):
                    outcome = "slave_exception"
                elif request.pdu[0] in fc.READ_FUNCTIONS:
                    self._store_cache(request, result.pdu, done_at)
                    outcome = "ok"
                else:
                    self._invalidate_cache(request.slave)
                    outcome = "ok"
                # The line is the bottleneck: put the next request on the wire first
                # (when no gap has to be waited for), then send this answer to its masters.
                self._loop.call_soon(request.answer, result.pdu, outcome)
                return
            if not self.up:
                break  # the port went away under this transaction: not the slave's fault
            subject = f"unit {unit} on line {self.name}"
            if result is None:
                self._metrics.timeouts.labels(self.name, unit).inc()
                self._fault_log.note(subject, "timeout", f"no answer within {timeout:g} s")
            elif result.kind == "crc":  # counted when it arrived
                self._fault_log.note(subject, "CRC error", result.reason)
            else:
                self._fault_log.note(subject, "garbled answer", result.reason)
            if not self.up:
                break
        if not self.up:
            self._end_probe(request)
            request.answer(
                self._exception(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE), "no_route"
            )
            return
        if result is None:
            self._slave_timed_out(request)
        else:
            self._end_probe(request)
        request.answer(
            self._exception(request, ExceptionCode.GATEWAY_TARGET_FAILED), "target_failed"
        )

    async def _broadcast(self, request: Request) -> None:
        link = await self._ready_to_send()
        if link is None:
            request.answer(
                self._exception(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE), "no_route"
            )
            return
        frame = encode_rtu(0, request.pdu)
        link.write(frame)
        sent_at = time.monotonic()
        self._counters.frames_sent += 1
        self._counters.bytes_written += len(frame)
        end = sent_at + len(frame) * self._char_time + self.config.broadcast_turnaround
        self._quiet_since = end
        self._cache.clear()  # what was read while it waited in the queue is stale now
        request.answer(b"", "broadcast")
        await asyncio.sleep(max(0.0, end - time.monotonic()))

    async def _ready_to_send(self) -> SerialLink | None:
        """Wait for the frame gap of silence, then drop unasked bytes; ``None`` if down."""
        gap = self.config.gap
        while True:
            link = self._link
            if link is None or link.closed:
                return None
            deadline = self._quiet_since + gap
            if time.monotonic() >= deadline:
                break
            await self._clock.sleep_until(deadline)
        dropped = link.discard_input()
        if dropped:
            self._note_discarded("late", dropped)
        return link if not link.closed else None

    # -- line events -------------------------------------------------------------------

    def _on_data(self, data: bytes) -> None:
        now = time.monotonic()
        self._quiet_since = now
        self._counters.bytes_read += len(data)
        decoder = self._decoder
        waiter = self._waiter
        if decoder is None or waiter is None or waiter.done():
            self._note_discarded("late", len(data))
            return
        if self._garbled is not None:
            self._arm_garbled_timer(waiter)  # the line is not quiet yet
        while True:
            try:
                frame = decoder.feed(data)
            except ResponseError as error:
                if error.kind in _DISCARD_KINDS:
                    # Another unit's frame, or a late answer to an earlier request: drop
                    # it and keep decoding whatever followed it in the same read.
                    self._metrics.discarded_frames.labels(self.name, error.kind).inc()
                else:
                    self._note_garbled(error, waiter, decoder.looks_like_answer)
                    if waiter.done():  # the attempt failed: the rest is drained as late
                        self._decoder = None
                        return
                data = decoder.leftover
                decoder.reset()
                if data:
                    continue
                return
            break
        if frame is not None:
            if decoder.leftover:
                self._note_discarded("trailing", len(decoder.leftover))
            waiter.set_result(frame)
        elif decoder.waits_for_silence:
            if self._silence_timer is not None:
                self._silence_timer.cancel()
            self._silence_timer = self._loop.call_later(self.config.silence, self._on_silence)

    def _note_garbled(
        self,
        error: ResponseError,
        waiter: asyncio.Future[RtuFrame | ResponseError | None],
        damaged_answer: bool,
    ) -> None:
        """A garbled frame: count it; fail the attempt, or listen a little longer first.

        A frame with the awaited unit, function and length is the answer itself,
        damaged: the attempt fails at once and the retry follows after the frame gap.
        Anything else may be noise in front of the slave's real answer; retrying at
        once would put the retry on the wire while that answer comes, and the slave's
        answer to the retry would be left over for the next request. So then the
        attempt fails only after the line has stayed quiet for ``_garbled_wait``
        (2 x t3.5, at least 3 ms), and a valid answer arriving meanwhile is taken.
        """
        if error.kind == "crc":
            self._metrics.crc_errors.labels(self.name, self._current_unit).inc()
        else:
            self._metrics.discarded_frames.labels(self.name, error.kind).inc()
        self._garbled = error
        if damaged_answer:
            waiter.set_result(error)
        else:
            self._arm_garbled_timer(waiter)

    def _arm_garbled_timer(self, waiter: asyncio.Future[RtuFrame | ResponseError | None]) -> None:
        if self._garbled_timer is not None:
            self._garbled_timer.cancel()
        self._garbled_timer = self._loop.call_later(
            self._garbled_wait, self._on_garbled_silence, waiter
        )

    def _on_garbled_silence(self, waiter: asyncio.Future[RtuFrame | ResponseError | None]) -> None:
        self._garbled_timer = None
        if not waiter.done() and self._garbled is not None:
            waiter.set_result(self._garbled)

    def _on_silence(self) -> None:
        self._silence_timer = None
        decoder = self._decoder
        waiter = self._waiter
        if decoder is None or waiter is None or waiter.done():
            return
        try:
            waiter.set_result(decoder.end_of_frame())
        except ResponseError as error:
            if error.kind in _DISCARD_KINDS:
                self._metrics.discarded_frames.labels(self.name, error.kind).inc()
            else:
                self._note_garbled(error, waiter, decoder.looks_like_answer)
            decoder.reset()

    def _on_timeout(self, waiter: asyncio.Future[RtuFrame | ResponseError | None]) -> None:
        if not waiter.done():
            if self._decoder is not None and self._decoder.buffered:
                self._note_discarded("incomplete", self._decoder.buffered)
            waiter.set_result(self._garbled)  # None: a plain timeout

    def _note_discarded(self, reason: str, count: int) -> None:
        self._metrics.discarded_frames.labels(self.name, reason).inc()
        self._fault_log.note(
            f"line {self.name}", "discarded input", f"{count} {reason} byte(s)", level=logging.INFO
        )

    # -- slave health and cache ---------------------------------------------------------

    def _close_to_joiners(self, request: Request) -> None:
        """From now on (its frame goes on the wire) no other read may join ``request``.

        Identical reads keep joining while it waits for the frame gap: that is
        consistent (nothing was sent yet) and is where most of the sharing happens.
        """
        key = (request.slave, request.pdu)
        if self._waiting_reads.get(key) is request:
            del self._waiting_reads[key]

    def _slave_answered(self, request: Request) -> None:
        health = self._health.get(request.slave)
        if health is None:
            return
        if health.down:
            log.info("line %s: slave %d answers again", self.name, request.slave)
            self._metrics.slave_up.labels(self.name, UNIT_LABELS[request.slave]).set(1)
        del self._health[request.slave]

    def _slave_timed_out(self, request: Request) -> None:
        dead_after = self.config.dead_after
        if dead_after <= 0:
            return
        health = self._health.setdefault(request.slave, SlaveHealth())
        health.consecutive_timeouts += 1
        now = time.monotonic()
        if health.down:
            health.probing = False
            health.backoff = min(health.backoff * 2, self.config.probe_max_interval)
            health.next_probe_at = now + health.backoff
        elif health.consecutive_timeouts >= dead_after:
            health.down = True
            health.backoff = self.config.probe_interval
            health.next_probe_at = now + health.backoff
            self._metrics.slave_up.labels(self.name, UNIT_LABELS[request.slave]).set(0)
            log.warning(
                "line %s: slave %d silent %d times in a row; answering 0x0B at once, "
                "probing every %.1f s or more",
                self.name, request.slave, health.consecutive_timeouts, health.backoff,
            )  # fmt: skip

    def _end_probe(self, request: Request) -> None:
        """A probe ended without showing the slave dead or alive (garbled, dropped)."""
        if request.probe:
            health = self._health.get(request.slave)
            if health is not None:
                health.probing = False

    def _store_cache(self, request: Request, response: bytes, now: float) -> None:
        rules = self.config.cache
        if not rules:
            return
        pdu = request.pdu
        address = (pdu[1] << 8) | pdu[2]
        quantity = (pdu[3] << 8) | pdu[4]
        for rule in rules:
            if rule.covers(request.slave, pdu[0], address, quantity):
                self._cache[(request.slave, pdu)] = (now + rule.max_age, response)
                return

    def _invalidate_cache(self, slave: int) -> None:
        if self._cache:
            for key in [key for key in self._cache if key[0] == slave]:
                del self._cache[key]

    # -- port state --------------------------------------------------------------------

    def _try_open(self) -> bool:
        try:
            port = open_serial(self.config)
        except SerialPortError as error:
            reason = str(error)
            if reason != self._open_error:  # first failure, or a new reason: say it once
                self._open_error = reason
                log.error("%s; retrying", reason)
            return False
        self._open_error = ""
        self._link = SerialLink(port, self._loop, self._on_data, self._on_lost)
        self._quiet_since = time.monotonic()
        self._m_line_up.set(1)
        log.info("line %s: %s open at %d baud", self.name, self.config.device, self.config.baudrate)
        return True

    def _on_lost(self, error: OSError) -> None:
        log.error(
            "line %s: %s lost: %s; answering 0x0A until it returns",
            self.name,
            self.config.device,
            error,
        )
        self._m_line_up.set(0)
        self._metrics.line_lost.labels(self.name).inc()
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)
        self._fail_queued()
        if not self._stopping:
            self._schedule_reopen()

    def _schedule_reopen(self) -> None:
        if self._reopener is None or self._reopener.done():
            self._reopener = self._loop.create_task(self._reopen(), name=f"reopen-{self.name}")

    async def _reopen(self) -> None:
        delay = _REOPEN_FIRST_DELAY
        while not self._stopping:
            await asyncio.sleep(delay)
            if self._try_open():
                log.info("line %s: back up", self.name)
                self._reopener = None
                return
            delay = min(delay * 2, _REOPEN_MAX_DELAY)

    def take_queued(self) -> list[Request]:
        """Hand over every queued request unanswered: a reload moves them to the reopened line."""
        self._waiting_reads.clear()
        requests = self._queue.drain()
        for request in requests:
            self._end_probe(request)
            request.probe = False
        self._counters.queue_depth = 0
        return requests

    def adopt(self, requests: list[Request]) -> None:
        """Queue requests taken from this line's previous incarnation (0x0A if it cannot)."""
        self.answer_unavailable([request for request in requests if not self.submit(request)])

    @staticmethod
    def answer_unavailable(requests: list[Request]) -> None:
        """Answer each request 0x0A (gateway path unavailable)."""
        for request in requests:
            request.answer(
                Bus._exception(request, ExceptionCode.GATEWAY_PATH_UNAVAILABLE), "no_route"
            )

    def _fail_queued(self) -> None:
        """Answer everything queued with 0x0A (the line is going away)."""
        self.answer_unavailable(self.take_queued())

    @staticmethod
    def _exception(request: Request, code: ExceptionCode) -> bytes:
        return fc.exception_pdu(request.pdu[0], code)

    # -- status: the status page's only view of a line --------------------------------

    def status(self, slaves: Iterable[int] = ()) -> LineStatus:
        """A snapshot of this line and of ``slaves`` (plus any slave it keeps health for)."""
        config = self.config
        listed = []
        for slave in sorted(set(slaves) | set(self._health)):
            health = self._health.get(slave)
            if health is not None and health.down:
                state = SlaveState.DOWN
            elif health is not None and health.consecutive_timeouts:
                state = SlaveState.SUSPECT
            else:
                state = SlaveState.UP
            listed.append(SlaveStatus(self.name, slave, state))
        return LineStatus(
            name=self.name,
            kind="url" if config.is_url else "serial",
            device=config.device,
            state=LineState.UP if self.up else LineState.DOWN,
            queued=self.queued,
            slaves=tuple(listed),
        )
