"""Authorization: which master may do what, on which unit and address range (no I/O).

Theory of operation. Every request is first *classified* (``classify``): its
function (with the subfunction of FC 8 and the MEI type of FC 43), whether it
reads or writes, and the address ranges it touches. A listener's ``Policy``
then *decides* for a ``Principal`` (the master's source address and, on a TLS
listener, the role from its client certificate):

- A listener without rules (``rules is None``) serves everything, as before
  rules existed, except: FC 8 subfunction 4 (Force Listen Only Mode, which
  silences a slave until it is restarted), which no rule names there; writes on
  a read-only listener; and, on a TLS listener, clients with the NULL role.
- With rules, **rules only grant**: a request is served when at least one rule
  that matches the principal grants all of it (unit, function, access, every
  address of every range). Anything no rule grants is denied. There are no
  deny rules, so the order of the rules never changes a decision (the first
  granting rule is reported, for the trace) and adding a rule can only add
  rights. Broadcast (unit 0) is granted only by a rule that lists unit 0, and
  FC 8 subfunction 4 only by a rule that names ``8:4``.
- ``read_only`` refuses every write first, whatever the rules say.

**Rules follow the slave, not the unit id.** A policy is built with the routing
table (``core.routes``), and each rule's ``units`` are resolved through it to
the targets (line, slave address) they reach. ``decide`` gets the unit id the
master sent *and* its routed target (``None`` when unrouted, and for
broadcast), and a rule covers the request when the target is one of the rule's
targets or the unit sent is listed. So a routed alias (two unit ids, one slave)
inherits its target's rules whichever unit id names it: no unit id reaches a
slave with more or fewer rights than another. A rule may also name ``line`` and
``slave``: it then covers only routed requests whose target is on those lines
and slave addresses (never an unrouted unit, never a broadcast).

A denied request is answered with exception 0x01 (Illegal Function), as the
Modbus/TCP Security specification prescribes, and never reaches the line.

Invariants: ``decide`` is total (any PDU, any principal: no exception), pure,
and monotone in the rules (more rules never deny more).
"""

from __future__ import annotations

import ipaddress
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Flag, StrEnum

from . import pdu as fc
from .routes import RouteLike, Target, targets_of

#: The Modbus/TCP Security role extension (an ASN.1 UTF8String in the client certificate).
ROLE_OID = "1.3.6.1.4.1.50316.802.1"

IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address


class Access(Flag):
    """What a request does to the slave's data."""

    READ = 1
    WRITE = 2
    READ_WRITE = READ | WRITE


class DenyReason(StrEnum):
    """Why a request was refused (the log and trace vocabulary)."""

    NO_RULE = "no_rule"  # no rule grants it
    READ_ONLY = "read_only"  # a write on a read-only listener
    LISTEN_ONLY_MODE = "listen_only_mode"  # FC 8/4 without a rule naming it
    NULL_ROLE = "null_role"  # a TLS client without a valid role on a listener without rules


#: FC 8 (Diagnostics) subfunctions that only read counters or echo: everything else resets,
#: restarts or changes the slave's communication state.
DIAGNOSTIC_READS = frozenset({0x00, 0x02, *range(0x0B, 0x13)})
FORCE_LISTEN_ONLY = 0x04
#: FC 43 MEI type 14 (Read Device Identification) reads; other MEI types may act.
MEI_READ_DEVICE_ID = 0x0E

#: Functions that read and have no address (or one the policy does not look at).
_READS_WITHOUT_ADDRESS = frozenset({0x07, 0x0B, 0x0C, 0x11, 0x14})

#: Functions whose access is known; any other function code counts as a write (its effect
#: cannot be known, so a read-only grant must not let it through).
FunctionKey = tuple[int, int | None]


@dataclass(frozen=True, slots=True)
class Operation:
    """A classified request: function (and subfunction), access, inclusive address ranges."""

    function: int
    subfunction: int | None
    access: Access
    ranges: tuple[tuple[int, int], ...] = ()


def _u16(pdu: bytes, offset: int) -> int | None:
    if len(pdu) < offset + 2:
        return None
    return (pdu[offset] << 8) | pdu[offset + 1]


def _span(first: int | None, count: int | None) -> tuple[tuple[int, int], ...]:
    if first is None or count is None or count < 1:
        return ()
    return ((first, min(first + count - 1, 0xFFFF)),)


def classify(pdu: bytes) -> Operation:
    """What the request ``pdu`` does; total for any bytes (a short PDU gets no ranges)."""
    function = pdu[0] if pdu else 0
    if function in (0x01, 0x02, 0x03, 0x04):
        return Operation(function, None, Access.READ, _span(_u16(pdu, 1), _u16(pdu, 3)))
    if function in (0x05, 0x06, 0x16):
        return Operation(function, None, Access.WRITE, _span(_u16(pdu, 1), 1))
    if function in (0x0F, 0x10):
        return Operation(function, None, Access.WRITE, _span(_u16(pdu, 1), _u16(pdu, 3)))
    if function == 0x17:
        ranges = _span(_u16(pdu, 1), _u16(pdu, 3)) + _span(_u16(pdu, 5), _u16(pdu, 7))
        return Operation(function, None, Access.READ_WRITE, ranges)
    if function == 0x18:
        return Operation(function, None, Access.READ, _span(_u16(pdu, 1), 1))
    if function in _READS_WITHOUT_ADDRESS:
        return Operation(function, None, Access.READ)
    if function == fc.DIAGNOSTICS:
        sub = _u16(pdu, 1)
        access = Access.READ if sub in DIAGNOSTIC_READS else Access.WRITE
        return Operation(function, sub, access)
    if function == fc.ENCAPSULATED_INTERFACE:
        mei = pdu[1] if len(pdu) > 1 else None
        access = Access.READ if mei == MEI_READ_DEVICE_ID else Access.WRITE
        return Operation(function, mei, access)
    return Operation(function, None, Access.WRITE)


def merge_ranges(ranges: Iterable[tuple[int, int]]) -> tuple[tuple[int, int], ...]:
    """Sorted, non-overlapping ranges; adjacent ones joined (``0-9`` and ``10-19`` → ``0-19``)."""
    merged: list[tuple[int, int]] = []
    for first, last in sorted(ranges):
        if merged and first <= merged[-1][1] + 1:
            merged[-1] = (merged[-1][0], max(merged[-1][1], last))
        else:
            merged.append((first, last))
    return tuple(merged)


def _inside(span: tuple[int, int], ranges: Sequence[tuple[int, int]]) -> bool:
    return any(first <= span[0] and span[1] <= last for first, last in ranges)


#: Units a rule covers when it names none: every unit but broadcast.
ALL_UNITS = frozenset(range(1, 256))


@dataclass(frozen=True)
class Rule:
    """One grant. ``None`` (or empty ``sources``) means "any" for that dimension.

    ``units`` ``None`` covers 1..255, never broadcast; ``functions`` ``None`` covers
    every function whose access the rule grants, except FC 8 subfunction 4; a
    function key ``(8, None)`` covers every diagnostic subfunction except 4.
    ``addresses`` (merged, inclusive) restricts the rule to requests whose every
    range lies inside it, so it never grants functions without addresses.
    ``lines`` and ``slaves`` (``line`` and ``slave`` in the configuration) restrict
    it to routed requests whose target is on one of those lines and slave addresses.
    """

    key: str = "rule"  #: where it was written, for messages: ``policies.plant.rules[0]``
    role: str | None = None
    sources: tuple[IPNetwork, ...] = ()
    units: frozenset[int] | None = None
    functions: frozenset[FunctionKey] | None = None
    addresses: tuple[tuple[int, int], ...] | None = None
    access: Access = Access.READ_WRITE
    lines: frozenset[str] | None = None
    slaves: frozenset[int] | None = None

    @property
    def by_target(self) -> bool:
        """True when the rule names ``line`` or ``slave``: it covers routed requests only."""
        return self.lines is not None or self.slaves is not None

    def matches(self, principal: Principal) -> bool:
        """True when the rule speaks of this master (role and source)."""
        if self.role is not None and principal.role != self.role:
            return False
        if self.sources:
            source = principal.source
            return source is not None and any(source in network for network in self.sources)
        return True

    def names_function(self, operation: Operation) -> bool:
        """True when the rule's functions cover the operation's function."""
        function, sub = operation.function, operation.subfunction
        listen_only = function == fc.DIAGNOSTICS and sub == FORCE_LISTEN_ONLY
        if self.functions is None:
            return not listen_only
        if (function, sub) in self.functions:
            return True
        return (function, None) in self.functions and not listen_only

    def grants(self, operation: Operation) -> bool:
        """True when the rule allows this operation (principal and unit already matched)."""
        if operation.access & ~self.access:
            return False
        if not self.names_function(operation):
            return False
        if self.addresses is None:
            return True
        ranges = operation.ranges
        return bool(ranges) and all(_inside(span, self.addresses) for span in ranges)


@dataclass(frozen=True, slots=True)
class Principal:
    """Who sends the requests of one connection: source address, and role (TLS only).

    ``role`` is ``None`` for the NULL role: no, a duplicated or a wrongly encoded role
    extension, or a plain TCP connection.
    """

    source: IPAddress | None
    role: str | None = None


class Reach:
    """Where one rule applies, its ``units`` resolved through the routes (see the module)."""

    __slots__ = ("by_target", "lines", "slaves", "targets", "units")

    def __init__(self, rule: Rule, routes: Mapping[int, Target]) -> None:
        self.units = ALL_UNITS if rule.units is None else rule.units
        self.lines = rule.lines
        self.slaves = rule.slaves
        self.by_target = rule.by_target
        self.targets = frozenset(
            target for unit, target in routes.items() if unit in self.units and self._on(target)
        )

    def _on(self, target: Target) -> bool:
        lines, slaves = self.lines, self.slaves
        on_line = lines is None or target.line in lines
        return on_line and (slaves is None or target.slave in slaves)

    def covers(self, unit: int, target: Target | None) -> bool:
        """True when a request for ``unit`` (routed to ``target``) is within the rule's reach."""
        if target is not None and target in self.targets:
            return True
        if self.by_target:
            return target is not None and self._on(target) and unit in self.units
        return unit in self.units

    def keys(self, routes: Mapping[int, Target]) -> frozenset[Target | int]:
        """Everything the rule reaches: targets, and unrouted unit ids (for the lint)."""
        unrouted = () if self.by_target else (u for u in self.units if u not in routes)
        return self.targets | frozenset(unrouted)


@dataclass(frozen=True, slots=True)
class Decision:
    """The outcome of ``Policy.decide``: ``denied`` is ``None`` when the request is served."""

    denied: DenyReason | None
    rule: Rule | None = None  #: the granting rule, when rules exist

    @property
    def allowed(self) -> bool:
        """True when the request may go on to routing."""
        return self.denied is None


ALLOWED = Decision(None)


@dataclass(frozen=True)
class Policy:
    """A listener's authorization: its rules (``None``: none written), read-only, TLS or not."""

    rules: tuple[Rule, ...] | None = None
    read_only: bool = False
    tls: bool = False
    #: The routing table the rules' ``units`` are resolved through (``config.routes``).
    routes: Mapping[int, RouteLike] = field(default_factory=dict, repr=False, compare=False)
    #: Function codes the gateway refuses on this listener (``server.refuse_functions``),
    #: whatever the rules say: not a grant or a denial, checked by admission after ``decide``.
    refuse_functions: frozenset[int] = frozenset()
    roles: frozenset[str] = field(init=False)
    #: True when only FC 8/4 can be refused: callers may skip ``decide`` for other codes.
    #: Worked out once, not per request: every request's path reads it.
    open: bool = field(init=False, repr=False, compare=False)
    #: Each rule with its reach, resolved through ``routes`` once, when the policy is built.
    reaches: tuple[tuple[Rule, Reach], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        roles = frozenset(rule.role for rule in self.rules or () if rule.role is not None)
        object.__setattr__(self, "roles", roles)
        is_open = self.rules is None and not self.read_only and not self.tls
        object.__setattr__(self, "open", is_open)
        targets = targets_of(self.routes)
        reaches = tuple((rule, Reach(rule, targets)) for rule in self.rules or ())
        object.__setattr__(self, "reaches", reaches)

    def decide(
        self, principal: Principal, unit: int, pdu: bytes, target: Target | None = None
    ) -> Decision:
        """Serve or deny one request for ``unit``, routed to ``target`` (``None``: unrouted)."""
        operation = classify(pdu)
        if self.read_only and operation.access & Access.WRITE:
            return Decision(DenyReason.READ_ONLY)
        if self.rules is None:
            if operation.function == fc.DIAGNOSTICS and operation.subfunction == FORCE_LISTEN_ONLY:
                return Decision(DenyReason.LISTEN_ONLY_MODE)
            if self.tls and principal.role is None:
                return Decision(DenyReason.NULL_ROLE)
            return ALLOWED
        for rule, reach in self.reaches:
            if rule.matches(principal) and reach.covers(unit, target) and rule.grants(operation):
                return Decision(None, rule)
        if operation.function == fc.DIAGNOSTICS and operation.subfunction == FORCE_LISTEN_ONLY:
            return Decision(DenyReason.LISTEN_ONLY_MODE)
        return Decision(DenyReason.NO_RULE)

    def role_label(self, role: str | None) -> str:
        """A bounded metric label for ``role``: a role the rules name, ``none`` or ``other``."""
        if role is None:
            return "none"
        return role if role in self.roles else "other"


# --------------------------------------------------------------------------- role extension


def decode_role(value: bytes) -> str | None:
    """The role from the extension's DER value: one UTF8String, else ``None`` (NULL role).

    Anything else (another ASN.1 type such as an INTEGER, a length that does not fit,
    trailing bytes, invalid UTF-8, an empty string) gives the NULL role, never an error.
    """
    if len(value) < 2 or value[0] != 0x0C:  # UTF8String, universal, primitive
        return None
    length = value[1]
    offset = 2
    if length & 0x80:
        count = length & 0x7F
        if count == 0 or count > 2 or len(value) < 2 + count:
            return None
        length = int.from_bytes(value[2 : 2 + count], "big")
        offset = 2 + count
    if offset + length != len(value) or length == 0:
        return None
    try:
        return value[offset:].decode("utf-8")
    except UnicodeDecodeError:
        return None


# --------------------------------------------------------------------------- configuration lint


def _covers(earlier: Rule, later: Rule, reach: Callable[[Rule], frozenset[Target | int]]) -> bool:
    """True when every request ``later`` grants, to anyone it matches, ``earlier`` grants too.

    Units are compared by ``reach``: the targets and unrouted unit ids a rule covers, so a
    rule that names an alias of a slave another rule names is compared as the same slave.
    """
    if earlier.role is not None and earlier.role != later.role:
        return False
    if earlier.sources and not (
        later.sources
        and all(
            any(
                network.version == wider.version and network.subnet_of(wider)  # type: ignore[arg-type]
                for wider in earlier.sources
            )
            for network in later.sources
        )
    ):
        return False
    if not reach(later) <= reach(earlier):
        return False
    if later.access & ~earlier.access:
        return False
    if earlier.functions is not None:
        if later.functions is None or not later.functions <= earlier.functions:
            return False
    elif later.functions is not None and (fc.DIAGNOSTICS, FORCE_LISTEN_ONLY) in later.functions:
        return False
    if earlier.addresses is not None:
        if later.addresses is None:
            return False
        return all(_inside(span, earlier.addresses) for span in later.addresses)
    return True


def _function_access(key: FunctionKey) -> Access:
    function, sub = key
    if sub is None and function in (fc.DIAGNOSTICS, fc.ENCAPSULATED_INTERFACE):
        return Access.READ_WRITE  # some subfunctions read, others write
    pdu = bytes([function]) + (
        sub.to_bytes(2, "big")
        if function == 8 and sub is not None
        else bytes([sub])
        if sub is not None
        else b""
    )
    return classify(pdu).access


#: Functions that carry an address range the ``addresses`` of a rule can match.
ADDRESSED_FUNCTIONS = frozenset({0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x10, 0x16, 0x17, 0x18})


def lint(
    rules: Sequence[Rule],
    *,
    listener: str,
    tls: bool,
    read_only: bool,
    allow: Sequence[IPNetwork],
    routes: Mapping[int, RouteLike],
    own_units: frozenset[int] = frozenset(),
) -> list[str]:
    """Warnings about rules that can never grant anything on ``listener`` (empty when sound),
    or that reach a slave under more unit ids than they name (aliases). ``own_units`` are
    the units the gateway answers itself (the status unit): a rule may name them alone."""
    targets = targets_of(routes)
    reaches = {id(rule): Reach(rule, targets).keys(targets) for rule in rules}

    def reach(rule: Rule) -> frozenset[Target | int]:
        return reaches[id(rule)]

    warnings: list[str] = []
    for index, rule in enumerate(rules):
        where = f"{rule.key} (listener {listener!r})"
        warnings += [f"{where}: {text}" for text in _rule_warnings(rule, tls, read_only, allow)]
        warnings += [f"{where}: {text}" for text in _reach_warnings(rule, targets, own_units)]
        for earlier in rules[:index]:
            if _covers(earlier, rule, reach):
                warnings.append(f"{where}: adds nothing to {earlier.key}, which grants all of it")
                break
    return warnings


def _rule_warnings(rule: Rule, tls: bool, read_only: bool, allow: Sequence[IPNetwork]) -> list[str]:
    """What makes one rule useless whatever the routes."""
    warnings: list[str] = []
    if rule.role is not None and not tls:
        warnings.append(
            f"role {rule.role!r} never matches on a plain tcp listener (roles come "
            "only from TLS client certificates); use it on a tls listener or write source ="
        )
    if rule.sources and allow:
        outside = [
            str(net)
            for net in rule.sources
            if not any(net.version == a.version and net.overlaps(a) for a in allow)
        ]
        if len(outside) == len(rule.sources):
            warnings.append(
                f"source {', '.join(outside)} is outside the listener's allow list, "
                "whose connections are closed at accept; widen allow or fix source"
            )
    if read_only and not rule.access & Access.READ:
        warnings.append("grants only writes, which the read-only listener refuses")
    if rule.functions is not None:
        useful = [key for key in rule.functions if _function_access(key) & rule.access]
        if not useful:
            warnings.append(
                f"access {rule.access.name!s} covers none of its functions "
                "(a read function needs access read, a write needs write); fix access"
            )
        if rule.addresses is not None and not any(
            function in ADDRESSED_FUNCTIONS for function, _ in rule.functions
        ):
            warnings.append(
                "addresses is set but none of its functions has an address, so "
                "it never grants anything; remove addresses or name an addressed function"
            )
    return warnings


def _reach_warnings(
    rule: Rule, targets: Mapping[int, Target], own_units: frozenset[int] = frozenset()
) -> list[str]:
    """Rules whose units or line/slave no route serves, and rules that name an alias."""
    reach = Reach(rule, targets)
    if rule.by_target:
        if not reach.targets:
            return [
                "no route reaches its line and slave; fix line/slave (and units) or add a route"
            ]
    elif rule.units is not None and not rule.units & (frozenset(targets) | {0} | own_units):
        return ["none of its units is routed to a line; fix units or add a route"]
    if rule.units is None:
        return []
    warnings = []
    aliases: dict[Target, list[int]] = {}
    for unit, target in targets.items():
        aliases.setdefault(target, []).append(unit)
    for target in sorted(reach.targets):
        units = sorted(aliases[target])
        named = [unit for unit in units if unit in rule.units]
        if len(named) < len(units):
            warnings.append(
                f"line {target.line!r} slave {target.slave} is reached by "
                f"{_plural('unit', units)}, and the rule names only {_plural('unit', named)}: "
                "rules follow the slave, so it grants that slave under each of them; list "
                "them all, or name line and slave"
            )
    return warnings


def _plural(word: str, numbers: Sequence[int]) -> str:
    """``unit 2`` or ``units 2, 12``."""
    return f"{word}{'s' if len(numbers) > 1 else ''} {', '.join(map(str, numbers))}"
