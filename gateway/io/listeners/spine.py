"""Where every listener carries out admission's decision: the routing table's shell side
and the one execution of a request (a line's, a broadcast, a local answer).

``core.admission`` decides what becomes of a request; this module does it, the same way
for every listener (Modbus TCP, TLS, RTU over TCP, serial slave): the audit record, the
request handed to its line with the reply that settles that record and counts the
request, a broadcast to every line that takes one, the counts of a local answer. The
listeners differ only in how an answer is written and which of their requests they still
wait for: that is what they pass in (``deliver``, ``done``). A rule written here holds on
every listener.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from ...config import GatewayConfig, ListenerConfig
from ...core import pdu as fc
from ...core.admission import Admission, Admitter, AnswerLocally
from ...core.errors import ExceptionCode
from ...core.line import LineRequest
from ...core.outcome import Outcome
from ...core.policy import Policy, Principal
from ...core.routes import Target
from ...metrics import UNIT_LABELS, GatewayMetrics, LoopHistogram
from ..audit import AuditLog, AuditTicket
from ..frame_trace import FrameTrace

if TYPE_CHECKING:
    from ..line.bus import Bus


class LineService(Protocol):
    """What a listener needs of a line it submits to: a ``Bus``, or a line the gateway
    answers itself (``status_unit.StatusUnit``). Listeners know lines by this alone."""

    @property
    def name(self) -> str:
        """The line's name: its ``line`` label in the metrics."""
        ...

    @property
    def up(self) -> bool:
        """True while it takes requests (a broadcast goes only to lines that are up)."""
        ...

    @property
    def request_duration(self) -> LoopHistogram:
        """The latency series the listener observes each answer in."""
        ...

    def submit(self, request: LineRequest) -> bool:
        """Take ``request``; its answer comes through ``request.reply`` (perhaps at once)."""
        ...

    def cancel(self, master: Hashable) -> None:
        """``master`` left: drop what of it still waits."""
        ...


@dataclass(frozen=True, slots=True)
class LineTarget:
    """Where a TCP unit id goes on the running lines: the line and the slave address."""

    bus: LineService
    slave: int


class Router:
    """The core's routing table (``Admitter``) beside the running line of each line name.

    Built from the lines' buses (``Gateway._build_router``) and replaced as a whole on
    reload; admission reads only the pure table, the listeners execute on the buses.
    ``own`` routes the units the gateway answers itself (the status unit) to lines of
    their own: admitted as any unit, but unrouted to the policy (``Admitter``).
    """

    def __init__(
        self,
        routes: Mapping[int, LineTarget],
        broadcast_buses: list[Bus],
        own: Mapping[int, LineTarget] | None = None,
    ) -> None:
        self.routes = dict(routes)
        self.broadcast_buses = broadcast_buses
        lines: dict[str, LineService] = {t.bus.name: t.bus for t in self.routes.values()}
        lines.update((bus.name, bus) for bus in broadcast_buses)
        #: The lines a leaving master's requests are cancelled on (not the own units':
        #: nothing waits there).
        self.buses = list(lines.values())
        own = dict(own or {})
        self.routes.update(own)
        lines.update((target.bus.name, target.bus) for target in own.values())
        #: The running line of each line name (``bus``; read directly once per request).
        self.by_line = lines
        self.admitter = Admitter.of(
            {unit: Target(target.bus.name, target.slave) for unit, target in routes.items()},
            [bus.name for bus in broadcast_buses],
            {unit: Target(target.bus.name, target.slave) for unit, target in own.items()},
        )

    def lookup(self, unit: int) -> LineTarget | None:
        """The route for ``unit``, ``None`` when there is none."""
        return self.routes.get(unit)

    def bus(self, line: str) -> LineService:
        """The running line called ``line`` (a name from the routing table)."""
        return self.by_line[line]


def listener_policy(config: GatewayConfig, listener: ListenerConfig) -> Policy:
    """What a listener's masters may do: its rules, read-only, and the gateway's refusals."""
    rules = config.policies[listener.policy] if listener.policy is not None else None
    read_only = listener.read_only or config.server.read_only
    return Policy(rules, read_only, listener.tls, config.routes, config.server.refuse_functions)


class Listener(Protocol):
    """What the spine reads of a listener (``ModbusTcpServer``, ``SerialSlave``); a reload
    may replace any of these, so they are read per request."""

    @property
    def name(self) -> str: ...
    @property
    def metrics(self) -> GatewayMetrics: ...
    @property
    def tracer(self) -> FrameTrace: ...
    @property
    def audit(self) -> AuditLog | None: ...
    @property
    def policy(self) -> Policy: ...
    @property
    def router(self) -> Router: ...


def admit(
    listener: Listener,
    principal: Principal,
    peer: str,
    role: str | None,
    unit: int,
    pdu: bytes,
    serves: frozenset[int] | None = None,
) -> tuple[Admission, AuditTicket | None]:
    """Admission's decision for one request, and its audit ticket (``None`` unless the
    audit log is on and the request is audited)."""
    result = listener.router.admitter.admit(principal, unit, pdu, listener.policy, serves)
    audit = listener.audit
    ticket = None if audit is None else audit.admitted(listener.name, peer, role, unit, pdu, result)
    return result, ticket


def line_request(
    listener: Listener,
    line: LineService,
    slave: int,
    pdu: bytes,
    master: Hashable,
    ticket: AuditTicket | None,
    deliver: Callable[[LineRequest, bytes, Outcome], Outcome],
) -> LineRequest:
    """The request for ``line`` (the caller submits it). Its answer settles the audit
    record, goes to ``deliver`` (which writes it, or says ``DROPPED`` when the master no
    longer waits), and is counted under the line and slave."""
    metrics = listener.metrics
    function = pdu[0]
    name = line.name
    unit_label = UNIT_LABELS[slave]  # the slave address, as in the line's metrics

    def reply(response: bytes, outcome: Outcome) -> None:
        if ticket is not None:  # an audited write: what became of it
            ticket.settle(request.sent, response, outcome)
        outcome = deliver(request, response, outcome)
        metrics.count_request(name, unit_label, function, outcome)

    request = LineRequest(slave, pdu, master, reply)
    return request


def unsubmitted(listener: Listener, line: LineService, slave: int, function: int) -> bytes:
    """A line refused the request outright: its 0x0A answer, counted."""
    listener.metrics.count_request(line.name, UNIT_LABELS[slave], function, Outcome.NO_ROUTE)
    return fc.exception_pdu(function, ExceptionCode.GATEWAY_PATH_UNAVAILABLE)


def broadcast(
    listener: Listener,
    lines: list[LineService],
    pdu: bytes,
    master: Hashable,
    ticket: AuditTicket | None,
    done: Callable[[Outcome], None],
) -> list[LineRequest] | None:
    """Send a write to every line that takes broadcasts and is up. When every line has
    sent it or refused it, the audit record is settled (sent if any line sent it), the
    broadcast counted once, and ``done`` told the outcome (``BROADCAST`` if any line sent
    it). Returns the requests handed to lines (the caller drops them when its master
    leaves); ``None`` when no line is up: counted as 0x0A, the caller answers it."""
    metrics = listener.metrics
    function = pdu[0]
    up = [line for line in lines if line.up]
    if not up:
        metrics.count_request("none", "other", function, Outcome.NO_ROUTE)
        return None
    remaining = len(up)
    went = False

    def sent(response: bytes, outcome: Outcome) -> None:
        nonlocal remaining, went
        went = went or outcome is Outcome.BROADCAST
        remaining -= 1
        if remaining:
            return
        final = Outcome.BROADCAST if went else outcome
        if ticket is not None:  # an audited broadcast: sent, or refused by every line
            ticket.settle(went, response, final)
        metrics.count_request("broadcast", "0", function, final)
        done(final)

    submitted: list[LineRequest] = []
    for line in up:
        request = LineRequest(0, pdu, master, sent, broadcast=True)
        if line.submit(request):
            submitted.append(request)
        else:
            sent(b"", Outcome.NO_ROUTE)
    return submitted


def answer_locally(
    listener: Listener, role: str | None, pdu: bytes, answer: AnswerLocally
) -> bytes:
    """The exception admission chose, counted as every listener counts it: nothing
    reaches a line."""
    function = pdu[0] if pdu else 0
    metrics = listener.metrics
    if answer.outcome is Outcome.DENIED:
        metrics.count_denial(listener.name, listener.policy.role_label(role), function)
    elif answer.outcome is Outcome.REJECTED:
        metrics.protocol_errors.labels("invalid_request").inc()
    metrics.count_request("none", "other", function, answer.outcome)
    return fc.exception_pdu(function, answer.code)
