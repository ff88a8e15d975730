"""The ``serial-slave`` listener (reverse mode): RTU or ASCII masters on a line reach the router.

Theory of operation: the gateway opens a serial device of its own and behaves on
it as the slaves it routes, so a master there (a PLC, an old SCADA port)
reaches Modbus TCP slaves, other lines, anything the router knows. It keeps the
slave-side rules of Modbus over Serial Line:

* RTU (``framing = "rtu"``): a frame is what lies between two silences of t3.5
  (the bus may carry other slaves' answers and requests for them, so a
  predicted length alone cannot frame it), timed by the lines' precise clock;
  ASCII (``framing = "ascii"``): a
  frame runs from ':' to CR LF, a ':' restarts it, at most 513 characters, and
  the inter-character timeout abandons it (``core.slave_side``);
* a frame is served only when its CRC (LRC) is right and its length is the one
  its function code implies (an answer of another slave is not a request);
* only units the router knows (and, when ``units`` is set, only those) are
  answered; anything else is ignored in silence, as an absent slave would;
* a broadcast (unit 0) is executed on the lines that take broadcasts and never
  answered;
* the answer goes out no sooner than a turnaround after the last character on
  the line (t3.5 for RTU, one character time for ASCII); a master that sends
  its next request before the answer came has given up on the previous one,
  whose answer is then dropped;
* with ``echo = true`` (an adapter that hears itself) the answer's own bytes
  are dropped when they come back, never taken for a request or for noise.

The master on the line appears in the status views (peer: the device) once it
sent a request, and its requests and answers in the trace, numbered in order as
RTU and ASCII carry no transaction id.

Requests go through the same admission as a TCP master's (``core.admission``:
routing, policy, with no source address here, so only rules without ``source``
or ``role`` grant, read-only, ``refuse_functions``, validation), then the same
queues and metrics. The silences above are how this listener executes
admission's answer for an unrouted unit and for unit 0, not checks of its own.

A reload gives it the new routes and policy (from the next request on). There is
no connection to judge again as on a TCP listener: no source address for an
allow list, no certificate; changes to its serial line need a restart.
"""

from __future__ import annotations

import asyncio
import logging
import time

from ...config import GatewayConfig, ListenerConfig
from ...core.admission import AnswerLocally, Broadcast, Submit
from ...core.ascii import encode_ascii
from ...core.line import LineRequest
from ...core.outcome import Outcome
from ...core.policy import Policy, Principal
from ...core.routes import Target
from ...core.rtu import MAX_RTU_FRAME
from ...core.rtu_stream import encode_rtu_reply, heard_request
from ...core.slave_side import AsciiRequestReader, FrameFault, Heard, OwnEcho, heard_ascii_request
from ...core.timing import character_time, t35
from ...logs import RateLimitedLogger
from ...metrics import GatewayMetrics
from ..audit import AuditLog, AuditTicket
from ..clock import PreciseClock
from ..frame_trace import FrameTrace
from ..links.serial_port import SerialLink, SerialPortError, open_serial
from ..status import MasterStatus
from . import spine
from .spine import Router, listener_policy

log = logging.getLogger("gateway.serial_slave")

_REOPEN_FIRST_DELAY = 0.05
_REOPEN_MAX_DELAY = 0.5
#: Timers of the event loop may fire up to a millisecond early: added to t3.5 to be sure.
_TIMER_MARGIN_S = 0.001
#: Who sends on a serial line: no source address, no role (only rules without either grant).
_NO_ONE = Principal(None)


class SerialSlave:
    """One ``serial-slave`` listener: a serial port on which the gateway answers as a slave."""

    def __init__(
        self,
        listener: ListenerConfig,
        router: Router,
        metrics: GatewayMetrics,
        policy: Policy,
        loop: asyncio.AbstractEventLoop,
    ) -> None:
        assert listener.serial is not None
        self.listener = listener
        self.name = listener.name
        self.router = router  #: replaced as a whole on reload
        self.policy = policy  #: replaced as a whole on reload
        self._serial = listener.serial
        self.metrics = metrics
        self._loop = loop
        serial = self._serial
        self._t35 = t35(serial.baudrate, serial.data_bits, serial.parity, serial.stop_bits)
        self._ascii = AsciiRequestReader() if serial.kind == "ascii" else None
        #: Quiet kept after the last character before answering: t3.5 (RTU) or one
        #: character time (ASCII, whose frames end at their LF, not on silence).
        self._turnaround = self._t35
        if self._ascii is not None:
            format_ = (serial.baudrate, serial.data_bits, serial.parity, serial.stop_bits)
            self._turnaround = character_time(*format_)
        self._encode = encode_ascii if self._ascii is not None else encode_rtu_reply
        self._echo = OwnEcho() if serial.echo else None
        self._buffer = bytearray()
        self._last_byte = 0.0
        self._silence: asyncio.TimerHandle | None = None  # ASCII: the inter-character timeout
        #: RTU: the t3.5 that ends a frame, met to a few microseconds (the loop's timers are
        #: millisecond-grained: t3.5 is 1.75 ms above 19200 baud).
        self._clock = PreciseClock(loop) if self._ascii is None else None
        self._link: SerialLink | None = None
        self._reopener: asyncio.Task[None] | None = None
        self._pending: LineRequest | None = None
        self._answering: asyncio.TimerHandle | None = None  # an answer waiting for turnaround
        self._stopping = False
        self._open_error = ""
        self.requests = 0  #: requests served (addressed to a routed unit)
        self.denied = 0  #: requests the listener's policy refused (answered 0x01)
        self.ignored = 0  #: frames ignored in silence (not for us, bad CRC, not a request)
        self.echoes = 0  #: bytes of our own answers dropped as their echo (``echo = true``)
        self.tracer = FrameTrace()  #: the gateway's, given at construction; used while active
        self.audit: AuditLog | None = None  #: the audit log, when configured (``Gateway``)
        self._sequence = 0  # numbers the requests for the trace (no transaction id on a line)
        self._faults = RateLimitedLogger(log, loop)

    # -- lifecycle -----------------------------------------------------------------------

    @property
    def up(self) -> bool:
        """True while the serial port is open."""
        return self._link is not None and not self._link.closed

    @property
    def framing(self) -> str:
        """``rtu`` or ``ascii``: what the masters on this line speak."""
        return "ascii" if self._ascii is not None else "rtu"

    def masters(self) -> list[MasterStatus]:
        """The master on the line, for the status views, once it sent a request."""
        if not self.requests:
            return []
        listener = f"{self.name} {self._serial.device} ({self.framing})"
        in_flight = 1 if self._pending is not None else 0
        return [
            MasterStatus(
                self._serial.device, listener, in_flight, self.requests, denied=self.denied
            )
        ]

    def start(self) -> None:
        """Open the port, or keep trying in the background."""
        if not self._try_open():
            self._schedule_reopen()

    def stop(self) -> None:
        """Close the port; a request under way is no longer answered."""
        self._stopping = True
        if self._reopener is not None:
            self._reopener.cancel()
        if self._silence is not None:
            self._silence.cancel()
            self._silence = None
        if self._clock is not None:
            self._clock.close()
        self._drop_pending()
        if self._link is not None:
            self._link.close()
            self._link = None
        self._faults.flush()

    def reconfigure(self, config: GatewayConfig, router: Router) -> None:
        """Take a reload's routes, and this listener's policy while its serial line is
        unchanged (a change there needs a restart: warned, the running line stays)."""
        self.router = router
        listener = next((lst for lst in config.listeners if lst.name == self.name), None)
        if listener is not None and listener.serial == self.listener.serial:
            self.policy = listener_policy(config, listener)
        else:
            log.warning(
                "reload: serial-slave listener %s: changes to its serial line "
                "(device, format, framing, echo) need a restart",
                self.name,
            )

    def _try_open(self) -> bool:
        try:
            port = open_serial(self._serial)
        except SerialPortError as error:
            reason = str(error)
            if reason != self._open_error:
                self._open_error = reason
                log.error("listener %s: %s; retrying", self.name, reason)
            return False
        self._open_error = ""
        self._link = SerialLink(port, self._loop, self._on_data, self._on_lost)
        log.info(
            "listener %s: answering as a slave on %s at %d baud (%s)",
            self.name,
            self._serial.device,
            self._serial.baudrate,
            self.framing.upper(),
        )
        return True

    def _on_lost(self, error: OSError) -> None:
        log.error("listener %s: %s lost: %s; reopening", self.name, self._serial.device, error)
        self._drop_pending()
        self._buffer.clear()
        if self._ascii is not None:
            self._ascii.reset()
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
                self._reopener = None
                return
            delay = min(delay * 2, _REOPEN_MAX_DELAY)

    @property
    def _serves(self) -> frozenset[int] | None:
        """The units this listener answers for (``units``); ``None``: every routed unit."""
        units = self.listener.units
        return frozenset(units) if units else None

    # -- framing -------------------------------------------------------------------------

    def _on_data(self, data: bytes) -> None:
        self._last_byte = time.monotonic()
        if self._echo is not None and self._echo.expected:
            own = len(data)
            data = self._echo.strip(data)
            self.echoes += own - len(data)
            if not data:
                return  # our own answer coming back: neither a request nor noise
        if self._ascii is not None:
            self._on_characters(data)
            return
        clock = self._clock
        assert clock is not None
        if len(self._buffer) + len(data) > 2 * MAX_RTU_FRAME:
            self._buffer.clear()  # a babbling line: nothing here is one frame
            self._damaged(FrameFault.OVERSIZE, "more than an RTU frame without a gap")
            clock.disarm()
            return
        self._buffer += data
        clock.arm(self._last_byte + self._t35, self._frame_ended)

    def _frame_ended(self) -> None:
        """t3.5 of silence since the last byte (the clock never fires early): a frame ended."""
        if not self._buffer:
            return
        frame = bytes(self._buffer)
        self._buffer.clear()
        self._serve(heard_request(frame))

    def _on_characters(self, data: bytes) -> None:
        """ASCII: whole frames from ':' to LF; the inter-character timeout runs inside one."""
        reader = self._ascii
        assert reader is not None
        for event in reader.feed(data):
            if isinstance(event, FrameFault):
                self._damaged(event)
            else:
                self._serve(heard_ascii_request(event))
        if self._silence is not None:
            self._silence.cancel()
            self._silence = None
        if reader.in_frame:
            self._silence = self._loop.call_later(
                self._serial.inter_char_timeout, self._characters_stopped
            )

    def _characters_stopped(self) -> None:
        self._silence = None
        assert self._ascii is not None
        fault = self._ascii.timed_out()
        if fault is not None:
            self._damaged(fault)

    def _serve(self, heard: Heard | str) -> None:
        """Admit one heard request (``core.admission``) and execute the result, keeping the
        serial line's silences: nothing for an unrouted unit, nothing for unit 0."""
        if isinstance(heard, FrameFault):
            self._damaged(heard)
            return
        if isinstance(heard, str):
            self._damaged(FrameFault.BAD_CHECK, heard)
            return
        if heard is None:
            self.ignored += 1  # another slave's answer, or a request of another shape
            return
        unit, pdu = heard
        # A new request: whatever the master asked before, it no longer waits for.
        self._drop_pending()
        device = self._serial.device
        result, ticket = spine.admit(self, _NO_ONE, device, None, unit, pdu, self._serves)
        if unit == 0:  # executed or not, a broadcast is never answered
            if isinstance(result, Broadcast):
                self._broadcast(pdu, result, ticket)
            else:
                self.ignored += 1
            return
        if isinstance(result, AnswerLocally) and not result.routed:
            self.ignored += 1  # not a slave the gateway stands for: silence
            return
        self.requests += 1
        number = self._sequence
        self._sequence = (number + 1) & 0xFFFF
        if self.tracer.active:
            self.tracer.request(self._serial.device, number, unit, pdu, self.name)
        if isinstance(result, Submit):
            self._submit(number, unit, pdu, result.target, ticket)
        elif isinstance(result, AnswerLocally):
            if result.outcome is Outcome.DENIED:
                self.denied += 1
            refusal = spine.answer_locally(self, None, pdu, result)
            self._answer(number, unit, refusal, result.outcome)

    def _submit(
        self, number: int, unit: int, pdu: bytes, target: Target, ticket: AuditTicket | None
    ) -> None:
        """Queue the request on its line; only the latest request of the master is answered."""
        peer = self._serial.device
        line = self.router.bus(target.line)

        def deliver(request: LineRequest, response: bytes, outcome: Outcome) -> Outcome:
            if self._pending is not request:  # the master gave up on it: a newer request came
                if self.tracer.active:
                    self.tracer.dropped(peer, number, unit, pdu[0])
                return Outcome.DROPPED
            self._pending = None
            self._answer(number, unit, response, outcome)
            return outcome

        request = spine.line_request(self, line, target.slave, pdu, self, ticket, deliver)
        self._pending = request
        line.submit(request)

    def _broadcast(self, pdu: bytes, result: Broadcast, ticket: AuditTicket | None) -> None:
        """Executed on every line that takes broadcasts and is up (``spine.broadcast``);
        never answered."""
        if self.tracer.active:
            number = self._sequence
            self._sequence = (number + 1) & 0xFFFF
            self.tracer.request(self._serial.device, number, 0, pdu, self.name)
        lines = [self.router.bus(line) for line in result.lines]
        spine.broadcast(self, lines, pdu, self, ticket, _unanswered)

    def _answer(self, number: int, unit: int, pdu: bytes, outcome: Outcome) -> None:
        """Write the answer, no sooner than the turnaround after the last byte on the line."""
        frame = self._encode(unit, pdu)
        tracer = self.tracer
        if tracer.active:
            tracer.reply(self._serial.device, number, unit, pdu, outcome)
        wait = self._last_byte + self._turnaround - time.monotonic()
        if wait > 0:
            self._answering = self._loop.call_later(wait + _TIMER_MARGIN_S, self._write, frame)
        else:
            self._write(frame)

    def _write(self, frame: bytes) -> None:
        self._answering = None
        link = self._link
        if link is None or link.closed:
            return
        if self._echo is not None:
            self._echo.sent(frame)  # before the write: the echo may come back at once
        try:
            link.write(frame)
        except SerialPortError:
            return  # the link called ``_on_lost``

    def _drop_pending(self) -> None:
        if self._answering is not None:  # the master asked again within the turnaround
            self._answering.cancel()
            self._answering = None
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.cancelled = True
            for bus in self.router.buses:
                bus.cancel(self)

    def _damaged(self, fault: FrameFault, what: str | None = None) -> None:
        """A damaged frame: ignored in silence, counted, logged at a bounded rate."""
        self.ignored += 1
        self.metrics.protocol_errors.labels(fault.value).inc()
        detail = what if what is not None else _FAULT_TEXT[fault]
        self._faults.note(f"listener {self.name}", "ignored frame", detail, level=logging.INFO)


def _unanswered(_outcome: Outcome) -> None:
    """A broadcast on a serial line is never answered."""


#: What the log says about a damaged ASCII frame.
_FAULT_TEXT = {
    FrameFault.BAD_CHECK: "a frame with a bad LRC (CRC), or too short",
    FrameFault.BAD_CHAR: "a frame with a non-hexadecimal character, or LF without CR",
    FrameFault.RESTARTED: "a frame cut short by a new ':'",
    FrameFault.OVERSIZE: "more than 513 characters without an end (ASCII)",
    FrameFault.INCOMPLETE: "a frame whose characters stopped (inter_char_timeout)",
}
