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

Two collaborators keep ``Bus`` to the pump, the masters' side and the hand-over:
``LinePort`` (``port.py``) opens and reopens the link, and ``LineNotes``
(``notes.py``) turns the core's notes into metrics and log lines.

The driver holds its gateway's role (``LineRole``): asked before every frame, told what
the line hears. A gateway alone plays ``Alone``; a redundancy pair plays its own
(``io.pair``), which the driver knows only through this protocol. The pair stands the
line by (``stand_by``: nothing sent, every request forwarded) and activates it again.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
from collections.abc import Callable, Hashable, Iterable, Mapping
from typing import NamedTuple, Protocol

from ...config import LineConfig, PollConfig
from ...core import pdu as fc
from ...core.errors import ExceptionCode
from ...core.framing import framing_for
from ...core.line import Delivery, Handover, LineRequest, Transmit, new_line_core, no_reply
from ...core.outcome import BlockState, Outcome, SlaveState
from ...metrics import GatewayMetrics
from ..clock import PreciseClock, wait_until
from ..links.link import Link, LinkError, TlsLink
from ..links.serial_port import SerialLink
from ..links.tls import LineTlsFailure
from ..status import LineState, LineStatus, PollBlockStatus, SlaveStatus
from .notes import LineNotes
from .port import REOPEN_FIRST_DELAY, REOPEN_MAX_DELAY, LinePort
from .tally import LineTally, wall_clock

log = logging.getLogger("gateway.bus")
_OK = Outcome.OK  # a module global: read once per answer


class LineRole(Protocol):
    """What the driver asks of the role its gateway plays, and tells it: all it knows of a
    redundancy pair."""

    @property
    def quiet_open(self) -> bool:
        """Open the port driving nothing (RTS, DTR, RS485 receive): the bus may be another's."""
        ...

    def may_transmit(self) -> bool:
        """Asked right before every frame. No: the frame is not written and the line pauses
        (``Bus.refused``) until ``activate``; what it held on the wire, never written, is
        answered 0x0A at once, not 0x0B after its timeout, nor charged to its slave."""
        ...

    def heard(self, master_frame: bool) -> None:
        """Bytes came in: the bus is busy; ``master_frame``: they ended a master frame this
        gateway did not send."""
        ...

    def cancel(self, master: Hashable) -> None:
        """``master`` left: what was forwarded for it (``Bus.stand_by``) is dropped too."""
        ...


class PollBlockView(Protocol):
    """What the io side reads of one block of a line's poll plan (agent mode's
    ``core.line.polling.PollBlock``), and never writes: its freshness and counters."""

    @property
    def period(self) -> float | None:
        """The achieved period between polls (a moving mean), ``None`` before two."""
        ...

    @property
    def served(self) -> int:
        """Reads answered from the block's memory."""
        ...

    @property
    def outcomes(self) -> Mapping[Outcome, int]:
        """The block's polls by outcome."""
        ...

    def age(self, now: float) -> float | None: ...

    def state(self, now: float) -> BlockState: ...

    def status_registers(self, now: float) -> tuple[int, int]: ...


class PlannedBlock(NamedTuple):
    """One poll block of a running line: its ``[[poll]]`` entry and its live state."""

    config: PollConfig
    block: PollBlockView


class Alone:
    """The role of a gateway alone: every frame may go; what the line hears is its own."""

    quiet_open = False

    def may_transmit(self) -> bool:
        return True

    def heard(self, master_frame: bool) -> None:
        """Nobody to tell."""

    def cancel(self, master: Hashable) -> None:
        """Nothing was forwarded."""


class Bus:
    """One RS485 line: the core that decides and the port it drives."""

    def __init__(
        self,
        config: LineConfig,
        metrics: GatewayMetrics,
        loop: asyncio.AbstractEventLoop,
        clock: PreciseClock,
        role: LineRole,
        tls_context: ssl.SSLContext | None = None,
    ) -> None:
        self.config = config
        self.role = role  #: the gateway's role: ``Alone``, or its part in a pair
        #: A pair's role is asked before each frame and told what the line heard; ``Alone``
        #: needs neither, and the per-transaction path skips both.
        self._role_listens = not isinstance(role, Alone)
        #: ``kind = "tls"``: the context of the next handshake (a reload may renew it).
        self.tls_context = tls_context
        self.name = config.name
        self._metrics = metrics
        self._loop = loop
        self._clock = clock
        self._timer_at = 0.0  # the deadline the clock is armed for (``_on_timer``)
        #: When the core last took bytes or time (monotonic): the instant its answers were
        #: heard, for the tally (a clock read per event, not per answer).
        self._heard_at = 0.0
        self._core = new_line_core(
            config,
            time.monotonic(),
            metrics.line_counters(self.name),
            framing_for(config.kind),
            config.max_in_flight,
        )
        self._wire = self._core.wire  # the core's parts the pump reads (``core.idle``)
        self._queue = self._core.queue
        self._link: Link | None = None
        self._port = LinePort(self, metrics, loop)
        self._stopping = False
        self._pumping = False
        self.successor: Bus | None = None  #: the line that replaced this one (``hand_to``)
        self._redirect: Callable[[LineRequest], bool] | None = None  # hand_to's or stand_by's
        self.refused = False  #: paused: the role refused a frame (``LineRole.may_transmit``)
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
        self._m_line_up.set(0)
        metrics.prepare_line(self.name)
        core = self._core
        metrics.set_response_timeouts(self.name, lambda: core.timing.by_slave(core.health.slaves))
        metrics.set_line_kind(self.name, config.kind)
        if config.kind == "tls":
            metrics.prepare_line_tls(self.name, (reason.value for reason in LineTlsFailure))
        self._notes = LineNotes(self, metrics, loop)
        self.tally = LineTally()  #: per-slave requests, exceptions, last seen (status page)
        self._uart: dict[str, int] | None = None  # the last kernel error counts read
        metrics.watch_uart(self.name, self.uart_errors)

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
    def shared(self) -> bool:
        """True while another master's frames were heard on the line lately."""
        return self._core.shared

    @property
    def queued(self) -> int:
        """Requests waiting for the line."""
        return self._core.queued

    @property
    def idle(self) -> bool:
        """Nothing waits and nothing is on the wire."""
        return self._idle

    def slave_states(self) -> dict[int, SlaveState]:
        """The isolation state of every slave the line has an opinion on."""
        return self._core.slave_states()

    def poll_blocks(self) -> tuple[PlannedBlock, ...]:
        """The line's poll blocks (agent mode), in configuration order, to read: the status
        unit, ``/status`` and the metrics show them."""
        return tuple(
            PlannedBlock(block.spec, block)
            for block in self._core.plan.blocks
            if isinstance(block.spec, PollConfig)  # the plan keeps the entry it was given
        )

    def learned_timeouts(self, slaves: Iterable[int]) -> dict[int, float]:
        """The response timeouts learned for ``slaves`` (those with one)."""
        return self._core.timing.by_slave(slaves)

    def fair_turn(self) -> float | None:
        """The line time (seconds) one turn of the fair queue charges a master, learned from
        the line's typical answered transaction; ``None`` before anything was answered."""
        return self._core.queue.grain or None

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Open the port, or begin retrying (a network line connects in the background)."""
        self._port.start()

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
        calls ``hand_to`` before it next yields to the loop: later requests go there."""
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

    def hand_to(self, successor: Bus) -> None:
        """Requests go to ``successor``, the line that replaced this one, from now on."""
        self.successor = successor
        self._redirect = successor.submit

    def stand_by(self, forward: Callable[[LineRequest], bool]) -> None:
        """Send nothing and hand every request (those queued too) to ``forward``: the
        transaction on the wire finishes, and what is heard still teaches the core."""
        core = self._core
        core.pause(time.monotonic())
        core.set_listening(True)
        if self.successor is None:
            self._redirect = forward
        self._pump()
        for request in core.take_queued():
            forward(request)

    def activate(self) -> None:
        """Take the masters' requests and transmit again (``stand_by``, ``refused``)."""
        if self.successor is None:
            self._redirect = None
        self.refused = False
        core = self._core
        core.set_listening(False)
        core.resume(time.monotonic())
        self._pump()

    def _stop_taking(self) -> None:
        """No reopening and no more requests: the core answers what waits 0x0A."""
        self._stopping = True
        self._port.stop()
        self._core.stop(time.monotonic())
        self._pump()

    def _close(self) -> None:
        self._clock.disarm()
        if self._link is not None:
            self._link.close()
            self._link = None
        self._m_line_up.set(0)
        self._notes.flush()

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
        if self._redirect is not None:  # reopened by a reload, or standing by
            return self._redirect(request)
        self._core.submit(request, time.monotonic())
        self._pump()
        return True

    def cancel(self, master: Hashable) -> None:
        """``master`` left: its waiting requests are dropped (unless others joined them)."""
        if self.successor is not None:
            self.successor.cancel(master)
            return
        self.role.cancel(master)
        self._core.cancel(master, time.monotonic())
        self._pump()

    def adopt(self, requests: list[LineRequest], handover: Handover | None = None) -> None:
        """Queue requests taken from this line's previous incarnation (0x0A if it cannot),
        starting from the wire as it left it."""
        now = time.monotonic()
        if handover is not None:
            self._core.take_over(handover, now)
        for request in requests:
            self._core.submit(request, now, handed_over=True)
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

    @property
    def quiet_open(self) -> bool:
        """Open the serial port without a glitch (the role says: a pair's standby)."""
        return self.role.quiet_open

    def on_data(self, data: bytes) -> None:
        """Bytes read from the link: the core takes them, then the role its evidence."""
        self._heard_at = now = time.monotonic()
        core = self._core
        if not self._role_listens:
            core.receive(data, now)
            self._pump()
            return
        masters = core.last_master_frame_at
        core.receive(data, now)
        self._pump()
        self.role.heard(core.last_master_frame_at != masters)

    def _on_timer(self) -> None:
        # Armed ``ahead``: this may run just before the deadline. The core decides for the
        # deadline now, and the pump acts no earlier than it (the same inputs as deciding
        # after a spin: nothing else runs in between).
        at = self._timer_at
        now = time.monotonic()
        self._heard_at = now = at if now < at else now  # an answer ends on silence here
        self._core.handle_timer(now)
        self._pump(not_before=at)

    def on_lost(self, error: OSError) -> None:
        """The link went away: 0x0A for what waits, and reopen it (unless stopping)."""
        link = self._link
        refused = isinstance(link, TlsLink) and not link.confirmed
        if refused:  # TLS 1.3: the slave's verdict on the gateway's certificate comes late
            self._port.tls_failed(error)
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
            self._port.schedule_reopen(REOPEN_MAX_DELAY if refused else REOPEN_FIRST_DELAY)

    def reconnect(self, why: str) -> None:
        """The core decided to make the connection again (``LineEvent.RECONNECT``): close
        it and reopen it with back-off; the core keeps what waits meanwhile."""
        link = self._link
        if link is None or link.closed or self._stopping:
            return
        log.warning("line %s: %s: %s; reconnecting", self.name, self.config.device, why)
        link.close()
        self._link = None
        self._m_line_up.set(0)
        self._port.schedule_reopen()

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
                        self._notes.note(note)
                if core.deliveries:
                    deliveries, core.deliveries = core.deliveries, []
                    self._deliver(deliveries)
        finally:
            self._pumping = False
        deadline = core.get_timer()
        if deadline is None:
            self._clock.disarm()  # cheap when not armed: no test of ``deadline`` first
        else:
            self._timer_at = deadline
            self._clock.arm(deadline, self._on_timer, ahead=True)
        if self._watch_wire and not core.wire_busy:
            self._wire_free.set()
        # ``core.idle``, inline (a property costs a call, and this runs after every pump).
        if (not self._wire.outstanding and not self._queue.queued) is not self._idle:
            self._idle = idle = not self._idle
            if idle and self._idle_waiters:
                waiters, self._idle_waiters = self._idle_waiters, []
                for waiter in waiters:
                    if not waiter.done():
                        waiter.set_result(None)

    def _transmit(self, transmits: list[Transmit]) -> None:
        may_transmit = self.role.may_transmit if self._role_listens else None
        for frame, _request, queue_wait, retry in transmits:  # unpacked: no field look-ups
            link = self._link
            if link is None or link.closed:
                return  # the core has been told (port_lost) and answered 0x0A
            if may_transmit is not None and not may_transmit():  # not written (``refused``)
                self.refused = True
                now = time.monotonic()
                self._core.pause(now)
                self._core.abandon(now)
                return
            if not retry:
                self._m_queue_wait.observe(queue_wait)
            try:
                link.write(frame)
            except LinkError:
                return  # the link called ``_on_lost``: the core answered 0x0A

    def _deliver(self, deliveries: list[Delivery]) -> None:
        observe = self._m_wire.observe
        tallies = self.tally.slaves
        heard_at = self._heard_at
        for request, pdu, outcome, wire_time in deliveries:  # unpacked: no field look-ups
            if wire_time >= 0.0:
                observe(wire_time)
            # ``tally.count``, its usual case inline: once per answer.
            tally = tallies.get(request.slave)
            if tally is not None and outcome is _OK and not request.poll:
                tally.requests += 1
                tally.last_seen = heard_at
            else:
                self.tally.count(request.slave, pdu, outcome, heard_at, request.poll)
            # A second answer goes nowhere, and the request is freed at once: a master's
            # reply callback usually refers to its own request, a reference cycle the
            # garbage collector would otherwise have to find, one per transaction.
            reply, request.reply = request.reply, no_reply
            try:
                reply(pdu, outcome)
            except Exception:  # a boundary: one master's broken reply path must not cost
                # the rest of this batch their answers; logged in full, not swallowed
                log.exception("line %s: handing an answer back failed", self.name)

    # -- port state ----------------------------------------------------------------------

    def attach(self, link: Link) -> None:
        """The port is open (``LinePort``): the core takes requests from now on."""
        self._link = link
        self._m_line_up.set(1)
        self._core.port_opened(time.monotonic())
        self._pump()

    # -- status: the status page's only view of a line ------------------------------------

    def uart_errors(self) -> dict[str, int] | None:
        """The port's kernel error counters (``TIOCGICOUNT``): the last read while it is
        closed, ``None`` on a pty, a network line, or a driver that keeps none."""
        link = self._link
        if isinstance(link, SerialLink) and not link.closed:
            counts = link.uart_errors()
            self._uart = None if counts is None else {str(k): v for k, v in counts.items()}
        return self._uart

    def status(self, slaves: Iterable[int] = ()) -> LineStatus:
        """A snapshot of this line and of ``slaves`` (``line_status``)."""
        return line_status(self, slaves)


def line_status(bus: Bus, slaves: Iterable[int] = ()) -> LineStatus:
    """A snapshot of ``bus`` and of ``slaves`` (plus any slave it has an opinion on, has
    answered for or has a name for), from what the line shows of itself."""
    config = bus.config
    states = bus.slave_states()
    tallies = bus.tally.slaves
    names = config.names
    learned = bus.learned_timeouts(states)
    listed = tuple(
        _slave_status(bus, slave, states.get(slave, SlaveState.UP), learned.get(slave))
        for slave in sorted(set(slaves) | set(states) | set(tallies) | set(names))
        if slave  # a broadcast is no slave
    )
    return LineStatus(
        name=bus.name,
        kind=config.kind if config.networked else "url" if config.is_url else "serial",
        device=config.device,
        state=_line_state(bus.up, bus.noisy, bus.shared),
        queued=bus.queued,
        slaves=listed,
        settings=line_settings(config),
        uart_errors=bus.uart_errors(),
        not_heard=sum(1 for slave in listed if not slave.heard),
        fair_turn_s=_rounded(bus.fair_turn()),
        blocks=poll_block_status(bus.name, bus.poll_blocks(), time.monotonic()),
    )


def poll_block_status(
    line: str, blocks: Iterable[PlannedBlock], now: float
) -> tuple[PollBlockStatus, ...]:
    """A snapshot of a line's poll blocks at ``now`` (monotonic), as ``/status`` shows them."""
    return tuple(
        PollBlockStatus(
            block=config.label,
            line=line,
            unit=config.unit,
            slave=config.slave,
            function=config.function,
            first=config.address,
            last=config.address + config.count - 1,
            every=config.every,
            max_age=config.max_age,
            state=block.state(now),
            period=_rounded(block.period),
            age=_rounded(block.age(now)),
            served=block.served,
            polls={outcome.value: count for outcome, count in block.outcomes.items()},
        )
        for config, block in blocks
    )


def _slave_status(bus: Bus, slave: int, state: SlaveState, learned: float | None) -> SlaveStatus:
    tally = bus.tally.slaves.get(slave)
    name = bus.config.names.get(slave)
    learned_timeout = _rounded(learned)
    if tally is None:
        return SlaveStatus(bus.name, slave, state, name=name, learned_timeout=learned_timeout)
    return SlaveStatus(
        bus.name,
        slave,
        state,
        name=name,
        learned_timeout=learned_timeout,
        heard=tally.last_seen is not None,
        requests=tally.requests,
        exceptions=dict(tally.exceptions),
        last_seen=wall_clock(tally.last_seen),
    )


def line_settings(config: LineConfig) -> str:
    """The line's settings as an operator reads them: ``rtu 9600 8E1, timeout 0.367 s``."""
    timeout = (
        f"timeout learned ({config.initial_timeout:g} s at first, {config.max_timeout:g} s at most)"
        if config.learn_timeouts
        else f"timeout {config.timeout:g} s"
    )
    if config.networked or config.is_url:
        return f"{config.kind}, {timeout}"
    parity = str(config.parity)[:1].upper()
    stop = f"{config.stop_bits:g}"
    form = f"{config.baudrate} {config.data_bits}{parity}{stop}"
    return f"{config.kind} {form}, {timeout}"


def _line_state(up: bool, noisy: bool, shared: bool) -> LineState:
    """The line's state word: down, noisy (0x0B for all), shared (another master heard), up."""
    if not up:
        return LineState.DOWN
    if noisy:
        return LineState.NOISY
    return LineState.SHARED if shared else LineState.UP


def _rounded(seconds: float | None) -> float | None:
    """Milliseconds are enough for a person reading /status."""
    return None if seconds is None else round(seconds, 3)
