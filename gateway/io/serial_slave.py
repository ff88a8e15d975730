"""The ``serial-slave`` listener (reverse mode): RTU masters on a serial line reach the router.

Theory of operation: the gateway opens a serial device of its own and behaves on
it as the slaves it routes, so an RTU master there (a PLC, an old SCADA port)
reaches Modbus TCP slaves, other lines, anything the router knows. It keeps the
slave-side rules of Modbus over Serial Line:

* a frame is what lies between two silences of t3.5 (the bus may carry other
  slaves' answers and requests for them, so a predicted length alone cannot
  frame it); it is served only when its CRC is right and its length is the one
  its function code implies (an answer of another slave is not a request);
* only units the router knows (and, when ``units`` is set, only those) are
  answered; anything else is ignored in silence, as an absent slave would;
* a broadcast (unit 0) is executed on the lines that take broadcasts and never
  answered;
* the answer goes out no sooner than t3.5 after the last byte on the line; a
  master that sends its next request before the answer came has given up on
  the previous one, whose answer is then dropped.

Requests go through the same validation, policy (no source address here: only
rules without ``source`` or ``role`` grant), read-only switch, routing, queues
and metrics as a TCP master's.
"""

from __future__ import annotations

import asyncio
import logging
import time

from ..config import ListenerConfig
from ..core import pdu as fc
from ..core.errors import ExceptionCode, ModbusError
from ..core.policy import Policy, Principal
from ..core.rtu import MAX_RTU_FRAME
from ..core.rtu_stream import encode_rtu_reply, heard_request
from ..core.timing import t35
from ..logs import RateLimitedLogger
from ..metrics import UNIT_LABELS, GatewayMetrics
from .bus import Request
from .serial_port import SerialLink, SerialPortError, open_serial
from .tcp import Router

log = logging.getLogger("gateway.serial_slave")

_REOPEN_FIRST_DELAY = 0.05
_REOPEN_MAX_DELAY = 0.5
#: Timers of the event loop may fire up to a millisecond early: added to t3.5 to be sure.
_TIMER_MARGIN_S = 0.001


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
        self._metrics = metrics
        self._loop = loop
        serial = self._serial
        self._t35 = t35(serial.baudrate, serial.data_bits, serial.parity, serial.stop_bits)
        self._buffer = bytearray()
        self._last_byte = 0.0
        self._silence: asyncio.TimerHandle | None = None
        self._link: SerialLink | None = None
        self._reopener: asyncio.Task[None] | None = None
        self._pending: Request | None = None
        self._stopping = False
        self._open_error = ""
        self.requests = 0  #: requests served (addressed to a routed unit)
        self.ignored = 0  #: frames ignored in silence (not for us, bad CRC, not a request)
        self._faults = RateLimitedLogger(log, loop)

    # -- lifecycle -----------------------------------------------------------------------

    @property
    def up(self) -> bool:
        """True while the serial port is open."""
        return self._link is not None and not self._link.closed

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
        self._drop_pending()
        if self._link is not None:
            self._link.close()
            self._link = None
        self._faults.flush()

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
        log.info("listener %s: answering as a slave on %s at %d baud", self.name,
                 self._serial.device, self._serial.baudrate)  # fmt: skip
        return True

    def _on_lost(self, error: OSError) -> None:
        log.error("listener %s: %s lost: %s; reopening", self.name, self._serial.device, error)
        self._drop_pending()
        self._buffer.clear()
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

    # -- framing by silence --------------------------------------------------------------

    def _on_data(self, data: bytes) -> None:
        self._last_byte = time.monotonic()
        if len(self._buffer) + len(data) > 2 * MAX_RTU_FRAME:
            self._buffer.clear()  # a babbling line: nothing here is one frame
            self._ignore("more than an RTU frame without a gap")
            return
        self._buffer += data
        if self._silence is not None:
            self._silence.cancel()
        self._silence = self._loop.call_later(self._t35 + _TIMER_MARGIN_S, self._frame_ended)

    def _frame_ended(self) -> None:
        self._silence = None
        quiet = time.monotonic() - self._last_byte
        if quiet < self._t35:  # woken early: wait for the rest of the silence
            self._silence = self._loop.call_later(
                self._t35 - quiet + _TIMER_MARGIN_S, self._frame_ended
            )
            return
        frame = bytes(self._buffer)
        self._buffer.clear()
        self._frame(frame)

    def _frame(self, frame: bytes) -> None:
        heard = heard_request(frame)
        if isinstance(heard, str):
            self._ignore(heard)
            return
        if heard is None:
            self.ignored += 1  # another slave's answer, or a request of another shape
            return
        unit, pdu = heard
        # A new request: whatever the master asked before, it no longer waits for.
        self._drop_pending()
        if unit == 0:
            self._broadcast(pdu)
            return
        if self.listener.units and unit not in self.listener.units:
            self.ignored += 1
            return
        target = self.router.lookup(unit)
        if target is None:
            self.ignored += 1  # not a slave the gateway stands for: silence
            return
        self.requests += 1
        function = pdu[0]
        try:
            fc.validate_request(pdu)
        except ModbusError as error:
            self._metrics.protocol_errors.labels("invalid_request").inc()
            self._answer(unit, fc.exception_pdu(function, error.code))
            self._metrics.count_request("none", "other", function, "rejected")
            return
        if not self.policy.open:
            decision = self.policy.decide(Principal(None), unit, pdu)
            if decision.denied is not None:
                self._answer(unit, fc.exception_pdu(function, ExceptionCode.ILLEGAL_FUNCTION))
                self._metrics.count_denial(self.name, self.policy.role_label(None), function)
                self._metrics.count_request("none", "other", function, "denied")
                return
        bus = target.bus
        line, unit_label = bus.name, UNIT_LABELS[target.slave]

        def reply(response: bytes, outcome: str) -> None:
            if self._pending is request:
                self._pending = None
                self._answer(unit, response)
            self._metrics.count_request(line, unit_label, function, outcome)

        request = Request(target.slave, pdu, self, reply)
        self._pending = request
        bus.submit(request)

    def _broadcast(self, pdu: bytes) -> None:
        """Executed on every line that takes broadcasts; never answered."""
        if pdu[0] not in fc.BROADCAST_FUNCTIONS:
            self.ignored += 1
            return
        try:
            fc.validate_request(pdu)
        except ModbusError:
            self.ignored += 1
            return
        if not self.policy.open and self.policy.decide(Principal(None), 0, pdu).denied:
            return
        for bus in self.router.broadcast_buses:
            if bus.up:
                bus.submit(Request(0, pdu, self, _ignore_reply, broadcast=True))

    def _answer(self, unit: int, pdu: bytes) -> None:
        """Write the answer, no sooner than t3.5 after the last byte on the line."""
        frame = encode_rtu_reply(unit, pdu)
        wait = self._last_byte + self._t35 - time.monotonic()
        if wait > 0:
            self._loop.call_later(wait + _TIMER_MARGIN_S, self._write, frame)
        else:
            self._write(frame)

    def _write(self, frame: bytes) -> None:
        link = self._link
        if link is None or link.closed:
            return
        try:
            link.write(frame)
        except SerialPortError:
            return  # the link called ``_on_lost``

    def _drop_pending(self) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.cancelled = True
            for bus in self.router.buses:
                bus.cancel(self)

    def _ignore(self, what: str) -> None:
        self.ignored += 1
        self._faults.note(f"listener {self.name}", "ignored frame", what, level=logging.INFO)


def _ignore_reply(_response: bytes, _outcome: str) -> None:
    """A broadcast has no answer."""
