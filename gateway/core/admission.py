"""Admission: one decision per request, the same for every listener (no I/O).

Theory of operation. A listener (Modbus TCP, TLS, RTU over TCP, serial slave)
only frames bytes: it hands each decoded request (who sent it, the unit id it
carries, the PDU) to ``admit`` and executes the typed result. The decision is
taken in this order, and the first step that answers wins:

1. **Route** (no answer yet): the unit id sent is looked up in the routing
   table; unit 0 is broadcast and has no route. A listener may narrow the
   units it serves (``serves``: a serial-slave listener's ``units``): the
   others count as unrouted.
2. **Authorize** (``Policy.decide``, 0x01 ``DENIED``): the policy sees both the
   unit id sent and the routed target (line, slave address), ``None`` when the
   unit is unrouted: a rule then grants it only by listing the unit sent. So
   a denied request gets 0x01 whether or not its unit is routed, and a master
   learns nothing about a request it may not send: not whether the unit
   exists, not whether the request was malformed. FC 8/4 (Force Listen Only
   Mode) is refused here unless a rule names ``8:4``. A unit the gateway
   answers itself (``own``: the status unit) is routed to its own line, but
   the policy sees it as unrouted: only a rule that lists its unit id (or
   names no units) grants it; a rule naming a line or slave never does.
3. **The gateway's own refusals** (0x01 ``REJECTED``): a function in
   ``refuse_functions``; a broadcast of anything but a write.
4. **Validate** (``pdu.validate_request``, 0x01/0x02/0x03 ``REJECTED``).
5. **Answer**: 0x0A ``NO_ROUTE`` for an unrouted unit (or a broadcast no line
   takes); otherwise ``Broadcast`` to the broadcast lines, or ``Submit`` to the
   routed target.

So denied beats unrouted, refused beats invalid, and invalid beats unrouted.

Each result says how it must be executed, not how it is framed: a serial-slave
listener keeps silent for an unrouted unit and for anything sent to unit 0
(``AnswerLocally.routed`` is ``False``, or the unit is 0), as an absent slave
would, because another slave on its line may answer; RTU listeners never
answer a broadcast. Those silences are the listeners' mapping of the result,
not checks of their own.

Invariants: ``admit`` is total (any PDU, any unit 0..255: no exception), pure,
and never yields ``Submit`` or ``Broadcast`` for a request the policy denies,
a refused function or an invalid PDU.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from . import pdu as fc
from .errors import ExceptionCode, ModbusError
from .outcome import Outcome
from .policy import DenyReason, Policy, Principal
from .routes import RouteLike, RouteTable, Target


@dataclass(frozen=True, slots=True)
class Submit:
    """Send the request to ``target``'s line, for its slave address."""

    target: Target


@dataclass(frozen=True, slots=True)
class Broadcast:
    """Send the request (a write to unit 0) to each of ``lines``, answer expected from none."""

    lines: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class AnswerLocally:
    """Answer exception ``code`` at once; nothing reaches a line."""

    code: ExceptionCode
    outcome: Outcome  #: ``DENIED``, ``REJECTED`` or ``NO_ROUTE``
    reason: str  #: for logs and traces
    routed: bool  #: the unit sent has a route (or is 0): a serial slave answers only then
    denied: DenyReason | None = None  #: why the policy refused it, when it did


Admission = Submit | Broadcast | AnswerLocally

_REFUSED = "function refused by configuration (server.refuse_functions)"
_NOT_BROADCAST = "only writes can be broadcast"


class Admitter:
    """The routing table, with each route's ``Submit`` made once (the hot path allocates none)."""

    __slots__ = ("_broadcast", "_own", "_submits", "table")

    def __init__(self, table: RouteTable, own: Mapping[int, RouteLike] | None = None) -> None:
        self.table = table
        self._submits = {unit: Submit(target) for unit, target in table.routes.items()}
        #: Units the gateway answers itself (the status unit), beside the routes: not in
        #: ``table``, which a pair's forwarding reads, and unrouted to the policy.
        self._own = frozenset(own or ())
        for unit, route in (own or {}).items():
            self._submits[unit] = Submit(Target(route.line, route.slave))
        lines = table.broadcast_lines
        self._broadcast = Broadcast(lines) if lines else None

    @classmethod
    def of(
        cls,
        routes: Mapping[int, RouteLike],
        broadcast_lines: Iterable[str] = (),
        own: Mapping[int, RouteLike] | None = None,
    ) -> Admitter:
        """An admitter for ``routes`` (any mapping of unit ids to line and slave), and for
        ``own``, the units the gateway answers itself on lines of its own."""
        return cls(RouteTable(routes, broadcast_lines), own)

    def admit(
        self,
        principal: Principal,
        unit: int,
        pdu: bytes,
        policy: Policy,
        serves: frozenset[int] | None = None,
    ) -> Admission:
        """What to do with one request (see the module docstring for the order)."""
        function = pdu[0] if pdu else 0
        submit = self._submits.get(unit) if serves is None or unit in serves else None
        routed = submit is not None or unit == 0
        if not policy.open or function == fc.DIAGNOSTICS:
            target = None if submit is None or unit in self._own else submit.target
            decision = policy.decide(principal, unit, pdu, target)
            if decision.denied is not None:
                reason = f"denied by policy ({decision.denied})"
                return AnswerLocally(
                    ExceptionCode.ILLEGAL_FUNCTION, Outcome.DENIED, reason, routed, decision.denied
                )
        # The gateway's own refusals, whatever the rules grant (inline: once per request).
        if function in policy.refuse_functions:
            return AnswerLocally(ExceptionCode.ILLEGAL_FUNCTION, Outcome.REJECTED, _REFUSED, routed)
        if unit == 0 and function not in fc.BROADCAST_FUNCTIONS:
            return AnswerLocally(
                ExceptionCode.ILLEGAL_FUNCTION, Outcome.REJECTED, _NOT_BROADCAST, routed
            )
        try:
            fc.validate_request(pdu)
        except ModbusError as error:
            return AnswerLocally(error.code, Outcome.REJECTED, error.reason, routed)
        if submit is not None:
            return submit
        if unit == 0 and self._broadcast is not None:
            return self._broadcast
        what = "no line takes broadcasts" if unit == 0 else f"no route for unit {unit}"
        return AnswerLocally(ExceptionCode.GATEWAY_PATH_UNAVAILABLE, Outcome.NO_ROUTE, what, routed)
