"""One serial line's driver: moves bytes and time between the port and the line core.

Theory of operation: every decision lives in ``gateway.core.line.LineCore``. This
driver feeds it the port's bytes (``receive``), the precise clock's deadline
(``handle_timer``), requests from masters (``submit``) and port events, each with
``time.monotonic()``; then one pump executes what the core decided, in order:
frames to write, answers to hand back, notes to count and log; and arms the one
deadline ``get_timer()`` names through ``PreciseClock``. It also reopens a lost
port with back-off.

What carries the bytes is a ``Link``: the serial port (``kind = "rtu"``), or a TCP
connection to a serial device server (``kind = "rtu-over-tcp"``) or slave (``tcp``),
or a TLS session with a slave (``tls``), connected without blocking the loop and
reconnected with the same back-off as a port is reopened. While the link is down
the core answers 0x0A, whatever the kind. A TLS failure is counted by reason and
logged once per reason until the line works again.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import ssl
import time
from collections.abc import Hashable, Iterable

from ..config import LineConfig
from ..core import pdu as fc
from ..core.errors import ExceptionCode
from ..core.framing import framing_for
from ..core.line import Delivery, Handover, LineRequest, Note, Transmit, new_line_core, no_reply
from ..core.outcome import LineEvent, Outcome, SlaveState
from ..logs import RateLimitedLogger
from ..metrics import UNIT_LABELS, GatewayMetrics
from ..status import LineState, LineStatus, SlaveStatus
from .clock import PreciseClock, wait_until
from .link import Link, LinkError, TcpLink, TlsLink, connect_tcp, connect_tls
from .serial_port import SerialLink, SerialPortError, open_serial
from .tls import LineTlsFailure, line_failure_message, line_failure_reason

log = logging.getLogger("gateway.bus")

#: A request as the masters' side builds it: ``Request(slave, pdu, master, reply)``.
Request = LineRequest


_REOPEN_FIRST_DELAY = 0.05
_REOPEN_MAX_DELAY = 0.5


class Bus:
    """One RS485 line: the core that decides and the port it drives."""

    def __init__(
        self,
        config: LineConfig,
        metrics: GatewayMetrics,
        loop: asyncio.AbstractEventLoop,
        clock: PreciseClock,
        tls_context: ssl.SSLContext | None = None,
    ) -> None:
        self.config = config
        #: ``kind = "tls"``: the context of the next handshake (a reload may renew it).
        self.tls_context = tls_context
        self.name = config.name
        self._metrics = metrics
        self._loop = loop
        self._clock = clock
        self._timer_at = 0.0  # the deadline the clock is armed for (``_on_timer``)
        self._core = new_line_core(
            config,
            time.monotonic(),
            metrics.line_counters(self.name),
            framing_for(config.kind),
            config.max_in_flight,
        )
        self._link: Link | None = None
        self._reopener: asyncio.Task[None] | None = None
        self._stopping = False
        self._pumping = False
        self._open_error = ""
        #: The line that replaced this one (``hand_over``): requests go there from now on.
        self.successor: Bus | None = None
        self._watch_wire = False  # ``hand_over`` waits for ``_wire_free``
        self._wire_free = asyncio.Event()
        # The core had nothing to do at the last pump. A bool, and futures made only while
        # ``stop`` waits, not an ``asyncio.Event``: the pump flips it twice per transaction.
        self._idle = True
        self._idle_waiters: list[asyncio.Future[None]] = []
        #: The line's request latency series, for the masters' side to observe.
        self.request_duration = metrics.request_duration_for(self.name)
        self._m_queue_wait = metrics.queue_wait.labels(self.name)
        self._m_wire = metrics.wire_duration.labels(self.name)
        self._m_line_up = metrics.line_up.labels(self.name)
        self._m_coalesced = metrics.coalesced.labels(self.name)
        self._m_noisy = metrics.line_noisy.labels(self.name)
        self._m_line_up.set(0)
        self._m_noisy.set(0)
        metrics.prepare_line(self.name)
        metrics.set_line_kind(self.name, config.kind)
        if config.kind == "tls":
            metrics.prepare_line_tls(self.name, (reason.value for reason in LineTlsFailure))
        self._fault_log = RateLimitedLogger(log, loop)  # first fault at once, then counts

    # -- state ---------------------------------------------------------------------------

    @property
    def up(self) -> bool:
        """True while the serial port is open."""
        return self._link is not None and not self._link.closed

    @property
    def noisy(self) -> bool:
        """True while the line has had no usable gap for too long."""
        return self._core.noisy

    @property
    def queued(self) -> int:
        """Requests waiting for the line."""
        return self._core.queued

    def slave_states(self) -> dict[int, SlaveState]:
        """The isolation state of every slave the line has an opinion on."""
        return self._core.slave_states()

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Open the port, or begin retrying (a network line connects in the background)."""
        if self.config.networked:
            self._schedule_reopen(first_delay=0.0)
        elif not self._try_open():
            self._schedule_reopen()

    async def stop(self, grace: float) -> None:
        """Finish the transaction on the wire (within ``grace``), answer the rest 0x0A, close."""
        self._stop_taking()
        if not self._idle:
            waiter: asyncio.Future[None] = self._loop.create_future()
            self._idle_waiters.append(waiter)
            try:
                await asyncio.wait_for(waiter, grace)
            except TimeoutError:
                # Grace over: give up the transaction on the wire so its master still gets
                # an answer (0x0A, as for a lost line) rather than a closed connection.
                self._core.abandon(time.monotonic())
                self._pump()
            finally:
                if waiter in self._idle_waiters:
                    self._idle_waiters.remove(waiter)
        self._close()

    async def hand_over(self, grace: float) -> tuple[list[LineRequest], Handover]:
        """Give the line up to the one that reopens it (a reload changed its port): send
        nothing more, finish the transaction on the wire (within ``grace``) while requests
        keep queuing, then return the queue and the wire's state and close. The caller
        sets ``successor`` before it next yields to the loop: later requests go there."""
        core = self._core
        core.pause(time.monotonic())
        self._pump()
        if core.wire_busy:
            self._wire_free.clear()
            self._watch_wire = True
            try:
                await asyncio.wait_for(self._wire_free.wait(), grace)
            except TimeoutError:
                core.abandon(time.monotonic())  # its master gets 0x0A, as at a stop
                self._pump()
            self._watch_wire = False
        queued = core.take_queued()
        handover = core.handover()
        self._stop_taking()
        self._close()
        return queued, handover

    def _stop_taking(self) -> None:
        """No reopening and no more requests: the core answers what waits 0x0A."""
        self._stopping = True
        if self._reopener is not None:
            self._reopener.cancel()
        self._core.stop(time.monotonic())
        self._pump()

    def _close(self) -> None:
        self._clock.disarm()
        if self._link is not None:
            self._link.close()
            self._link = None
        self._m_line_up.set(0)
        self._fault_log.flush()

    def reconfigure(self, config: LineConfig) -> None:
        """Take new timeouts, retries and limits; the port settings must be unchanged."""
        self.config = config
        self._core.reconfigure(config, time.monotonic())
        self._pump()

    # -- the masters' side ---------------------------------------------------------------

    def submit(self, request: LineRequest) -> bool:
        """Hand a request to the line; its answer comes through ``request.reply``.

        Always ``True``: the core answers at once what cannot be queued (0x0A line
        down or full, 0x06 the master's queue full, 0x0B isolated slave or noisy line).
        """
        if self.successor is not None:  # reopened by a reload: routes may still name us
            return self.successor.submit(request)
        self._core.submit(request, time.monotonic())
        self._pump()
        return True

    def cancel(self, master: Hashable) -> None:
        """``master`` left: its waiting requests are dropped (unless others joined them)."""
        if self.successor is not None:
            self.successor.cancel(master)
            return
        self._core.cancel(master, time.monotonic())
        self._pump()

    def adopt(self, requests: list[LineRequest], handover: Handover | None = None) -> None:
        """Queue requests taken from this line's previous incarnation (0x0A if it cannot),
        starting from the wire as it left it."""
        now = time.monotonic()
        if handover is not None:
            self._core.take_over(handover, now)
        for request in requests:
            self._core.submit(request, now)
        self._pump()

    @staticmethod
    def answer_unavailable(requests: list[LineRequest]) -> None:
        """Answer each request 0x0A (gateway path unavailable)."""
        for request in requests:
            request.answered = True
            reply, request.reply = request.reply, no_reply  # see ``_deliver``
            reply(
                fc.exception_pdu(request.pdu[0], ExceptionCode.GATEWAY_PATH_UNAVAILABLE),
                Outcome.NO_ROUTE,
            )

    # -- events from the port and the clock ----------------------------------------------

    def _on_data(self, data: bytes) -> None:
        self._core.receive(data, time.monotonic())
        self._pump()

    def _on_timer(self) -> None:
        # Armed ``ahead``: this may run just before the deadline. The core decides for the
        # deadline now, and the pump acts no earlier than it (the same inputs as deciding
        # after a spin: nothing else runs in between).
        at = self._timer_at
        now = time.monotonic()
        self._core.handle_timer(at if now < at else now)
        self._pump(not_before=at)

    def _on_lost(self, error: OSError) -> None:
        link = self._link
        refused = isinstance(link, TlsLink) and not link.confirmed
        if refused:  # TLS 1.3: the slave's verdict on the gateway's certificate comes late
            self._tls_failed(error)
        else:
            log.error(
                "line %s: %s lost: %s; answering 0x0A until it returns",
                self.name,
                self.config.device,
                error,
            )
            self._metrics.line_lost.labels(self.name).inc()
        self._m_line_up.set(0)
        self._core.port_lost(time.monotonic())
        self._pump()
        if not self._stopping:
            self._schedule_reopen(_REOPEN_MAX_DELAY if refused else _REOPEN_FIRST_DELAY)

    def _resync(self) -> None:
        """Drop a connection whose byte stream can no longer be split into frames."""
        link = self._link
        if link is None or link.closed or self._stopping:
            return
        link.close()
        self._on_lost(ConnectionError("a frame header no Modbus TCP slave sends; reconnecting"))

    # -- the pump ------------------------------------------------------------------------

    def _pump(self, not_before: float = 0.0) -> None:
        """Execute the core's actions in order (none before ``not_before``), then arm its
        next deadline."""
        if self._pumping:
            return  # an answer's callback submitted more: the outer pump takes it
        self._pumping = True
        core = self._core
        try:
            while core.transmits or core.deliveries or core.notes:
                if not_before:
                    wait_until(not_before)
                    not_before = 0.0
                if core.transmits:
                    transmits, core.transmits = core.transmits, []
                    self._transmit(transmits)
                if core.notes:  # before the answers: a master that sees its answer sees them
                    notes, core.notes = core.notes, []
                    for note in notes:
                        self._note(note)
                if core.deliveries:
                    deliveries, core.deliveries = core.deliveries, []
                    self._deliver(deliveries)
        finally:
            self._pumping = False
        deadline = core.get_timer()
        if deadline is None:
            if self._clock.deadline:
                self._clock.disarm()
        else:
            self._timer_at = deadline
            self._clock.arm(deadline, self._on_timer, ahead=True)
        if self._watch_wire and not core.wire_busy:
            self._wire_free.set()
        if core.idle is not self._idle:
            self._idle = idle = not self._idle
            if idle and self._idle_waiters:
                waiters, self._idle_waiters = self._idle_waiters, []
                for waiter in waiters:
                    if not waiter.done():
                        waiter.set_result(None)

    def _transmit(self, transmits: list[Transmit]) -> None:
        for transmit in transmits:
            link = self._link
            if link is None or link.closed:
                return  # the core has been told (port_lost) and answered 0x0A
            if not transmit.retry:
                self._m_queue_wait.observe(transmit.queue_wait)
            try:
                link.write(transmit.frame)
            except LinkError:
                return  # the link called ``_on_lost``: the core answered 0x0A

    def _deliver(self, deliveries: list[Delivery]) -> None:
        observe = self._m_wire.observe
        for delivery in deliveries:
            if delivery.wire_time >= 0.0:
                observe(delivery.wire_time)
            request = delivery.request
            # A second answer goes nowhere, and the request is freed at once: a master's
            # reply callback usually refers to its own request, a reference cycle the
            # garbage collector would otherwise have to find, one per transaction.
            reply, request.reply = request.reply, no_reply
            try:
                reply(delivery.pdu, delivery.outcome)
            except Exception:  # a boundary: one master's broken reply path must not cost
                # the rest of this batch their answers; logged in full, not swallowed
                log.exception("line %s: handing an answer back failed", self.name)

    def _note(self, note: Note) -> None:
        event = note.event
        if event is LineEvent.COALESCED:  # the only note on the hot path
            self._m_coalesced.inc()
            return
        metrics = self._metrics
        unit = UNIT_LABELS[note.slave]
        subject = f"unit {unit} on line {self.name}"
        if event is LineEvent.TIMEOUT:
            metrics.timeouts.labels(self.name, unit).inc()
            self._fault_log.note(subject, "timeout", note.detail)
        elif event is LineEvent.CRC_ERROR:
            metrics.crc_errors.labels(self.name, unit).inc()
            self._fault_log.note(subject, "CRC error", note.detail)
        elif event is LineEvent.GARBLED:
            self._fault_log.note(subject, "garbled answer", note.detail)
        elif event is LineEvent.RETRY:
            metrics.retries.labels(self.name, unit).inc()
        elif event is LineEvent.DISCARDED:
            metrics.discarded_frames.labels(self.name, note.detail).inc()
            if note.detail == "bad_header":  # a Modbus TCP stream out of step: reconnect
                self._loop.call_soon(self._resync)
            self._fault_log.note(
                f"line {self.name}",
                "discarded input",
                f"{note.amount} {note.detail} byte(s) or frame(s)",
                level=logging.INFO,
            )
        elif event is LineEvent.LATE_WINDOW:
            metrics.late_windows.labels(self.name).inc()
        elif event is LineEvent.SLAVE_STATE:
            self._slave_state(note)
        elif event is LineEvent.LINE_NOISY:
            self._m_noisy.set(1)
            metrics.line_noisy_total.labels(self.name).inc()
            self._fault_log.note(
                f"line {self.name}",
                "noisy line",
                f"{note.detail}; waiting requests answered 0x0B until a gap appears",
            )
        elif event is LineEvent.LINE_QUIET:
            self._m_noisy.set(0)
            log.info("line %s: quiet again, serving requests", self.name)

    def _slave_state(self, note: Note) -> None:
        unit = UNIT_LABELS[note.slave]
        state = note.state
        metrics = self._metrics
        states = list(self._core.slave_states().values())
        for counted in (SlaveState.SUSPECT, SlaveState.DOWN):
            metrics.slaves_isolated.labels(self.name, counted.value).set(states.count(counted))
        # Per-slave series only for slaves that have answered: a scan of every routed
        # address (all 247 with --serial) must not add two series per absent unit.
        if metrics.heard(self.name, unit):
            metrics.slave_up.labels(self.name, unit).set(0 if state is SlaveState.DOWN else 1)
            metrics.slave_suspect.labels(self.name, unit).set(
                1 if state is SlaveState.SUSPECT else 0
            )
        if state is SlaveState.DOWN:
            log.warning(
                "line %s: slave %d silent %d times in a row; answering 0x0B at once, "
                "probing every %.1f s or more",
                self.name, note.slave, note.amount, self.config.probe_interval,
            )  # fmt: skip
        elif state is SlaveState.SUSPECT:
            self._fault_log.note(
                f"unit {unit} on line {self.name}",
                "suspect slave",
                "missed an answer; its requests wait behind the others, one at a time",
                level=logging.INFO,
            )
        else:
            log.info("line %s: slave %d answers again", self.name, note.slave)

    # -- port state ----------------------------------------------------------------------

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
        self._m_line_up.set(1)
        log.info("line %s: %s open at %d baud", self.name, self.config.device, self.config.baudrate)
        self._core.port_opened(time.monotonic())
        self._pump()
        return True

    async def _try_connect(self) -> bool:
        """Connect to the device server (then wait ``connect_delay``); False on failure."""
        config = self.config
        try:
            sock = await connect_tcp(config.host, config.port, config.connect_timeout)
        except OSError as error:
            reason = f"line {self.name!r}: cannot connect to {config.device}: {error}"
            if reason != self._open_error:  # first failure, or a new reason: say it once
                self._open_error = reason
                log.error("%s; retrying", reason)
            return False
        lost: list[OSError] = []
        link: TcpLink | TlsLink
        if config.kind == "tls":
            handshaken = await self._handshake(sock, lost)
            if handshaken is None:
                return False
            link = handshaken
        else:
            link = TcpLink(sock, config.device, self._loop, self._discard, lost.append)
        if config.connect_delay > 0:
            # Some device servers drop what arrives while they set up their serial side:
            # nothing is sent (the line stays down, 0x0A) and nothing read counts.
            try:
                await asyncio.sleep(config.connect_delay)
            except asyncio.CancelledError:
                link.close()
                raise
        if lost or link.closed:
            reason = f"line {self.name!r}: {config.device} closed the connection at once"
            if reason != self._open_error:
                self._open_error = reason
                log.error("%s; retrying", reason)
            return False
        link.on_data, link.on_lost = self._on_data, self._on_lost
        self._link = link
        self._m_line_up.set(1)
        if isinstance(link, TlsLink) and self._open_error:
            # After a TLS failure the slave's first answer says it took the certificate:
            # until then a reconnect is not news (the failure was logged once).
            link.on_confirmed = self._tls_confirmed
            log.debug("line %s: TLS handshake with %s done", self.name, config.device)
        else:
            self._open_error = ""
            log.info("line %s: connected to %s (%s)", self.name, config.device, config.kind)
        self._core.port_opened(time.monotonic())
        self._pump()
        return True

    async def _handshake(self, sock: socket.socket, lost: list[OSError]) -> TlsLink | None:
        """The TLS handshake of a ``tls`` line on a connected socket; None on failure."""
        config = self.config
        assert self.tls_context is not None, "a tls line is opened with its context"
        try:
            tls = await connect_tls(
                sock, self.tls_context, config.server_name, config.tls_handshake_timeout
            )
        except OSError as error:
            self._tls_failed(error)
            return None
        return TlsLink(tls, config.device, self._loop, self._discard, lost.append)

    def _tls_failed(self, error: OSError) -> None:
        """Count a TLS failure by reason; log it when the reason is new."""
        reason = line_failure_reason(error)
        self._metrics.line_tls_failures.labels(self.name, reason.value).inc()
        key = f"tls:{reason.value}"
        if key != self._open_error:
            self._open_error = key
            log.error("%s; retrying", line_failure_message(self.config, reason, error))

    def _tls_confirmed(self) -> None:
        self._open_error = ""
        log.info("line %s: TLS session with %s accepted, back up", self.name, self.config.device)

    @staticmethod
    def _discard(_data: bytes) -> None:
        """Bytes read during the connect delay: not an answer to anything."""

    def _schedule_reopen(self, first_delay: float = _REOPEN_FIRST_DELAY) -> None:
        if self._reopener is None or self._reopener.done():
            self._reopener = self._loop.create_task(
                self._reopen(first_delay), name=f"reopen-{self.name}"
            )

    async def _reopen(self, first_delay: float = _REOPEN_FIRST_DELAY) -> None:
        delay = first_delay
        while not self._stopping:
            if delay > 0:
                await asyncio.sleep(delay)
            if self._stopping:
                return
            opened = await self._try_connect() if self.config.networked else self._try_open()
            if opened:
                if delay > 0 and not self._open_error:  # a TLS session: when confirmed
                    log.info("line %s: back up", self.name)
                self._reopener = None
                return
            delay = min(max(delay * 2, _REOPEN_FIRST_DELAY), _REOPEN_MAX_DELAY)

    # -- status: the status page's only view of a line ------------------------------------

    def status(self, slaves: Iterable[int] = ()) -> LineStatus:
        """A snapshot of this line and of ``slaves`` (plus any slave it has an opinion on)."""
        config = self.config
        states = self._core.slave_states()
        listed = tuple(
            SlaveStatus(self.name, slave, states.get(slave, SlaveState.UP))
            for slave in sorted(set(slaves) | set(states))
        )
        if not self.up:
            state = LineState.DOWN
        elif self._core.noisy:
            state = LineState.NOISY
        else:
            state = LineState.UP
        return LineStatus(
            name=self.name,
            kind=config.kind if config.networked else "url" if config.is_url else "serial",
            device=config.device,
            state=state,
            queued=self.queued,
            slaves=listed,
        )
