"""Which connection makes room when a listener is full: fair share between sources (no I/O).

Theory of operation. A listener holds at most ``max_connections`` masters. While a
slot is free every newcomer is admitted (``has_free_slot``), unless an explicit
``max_per_source`` cap (0: none, the default) says its source address has all it
may have. At the limit, ``admit_connection`` looks at a snapshot of the open
connections (``OpenConnection``: source, seconds idle, requests in flight, whether
it ever sent a request; the caller reads its clock, this module never does) and
returns ``Admit``, ``Evict(index)`` (close that connection, then admit) or
``Refuse(reason)``.

A connection that has never sent a complete request (*never used*) costs a slot
and serves no one; one that has sent a request is a master at work. So at the
limit, under both ``when_full`` policies, never-used connections go first:

1. *Fair share.* Let ``held`` be what the newcomer's own source holds and
   ``sources`` the number of sources open, the newcomer's counted. A newcomer
   whose source holds less than its fair share (``held < max_connections /
   sources``) takes the place of the *longest-open never-used* connection of the
   heaviest other source that holds more than ``held`` and has one (equal
   counts: the one whose never-used connection is oldest). Under ``when_full =
   "refuse"`` this is the only eviction: otherwise the newcomer is refused.
2. Under ``"close_oldest_idle"``, when step 1 finds nothing, the share rule
   below applies: to the never-used connections alone while any is open, to
   the others only once none is.

The share rule (``close_oldest_idle``): the source holding the most connections
yields. Candidate sources are walked heaviest first (equal counts: the one
whose best candidate has been idle longest first):

- every *other* source holding more than ``held``, then the newcomer's own
  source; a source holding ``held`` or fewer (other than its own) is never
  touched: a newcomer never takes a slot from a source no heavier than its own;
- the first of them whose longest-idle candidate with nothing in flight
  *qualifies* gives it up. It qualifies when idle for ``evict_min_idle``, or,
  whatever its age, when its source is another one holding at least
  ``held + 2`` (*over the newcomer's share*: after the swap it still holds at
  least as many as the newcomer's source; without the margin of two, two
  sources one apart would evict each other in turn);
- when none qualifies, the newcomer is refused. So a newcomer from the
  heaviest source gets in only in place of one of its own connections idle for
  ``evict_min_idle``; a newcomer from a lighter source gets in in place of the
  heaviest source's longest-idle connection, however young, as long as that
  source holds two more than the newcomer's (if all its connections have
  requests in flight, the next heaviest is tried, and so on down to the
  newcomer's own source).

Why the share rule does not wait for ``evict_min_idle``: a host that opens bursts
of fresh connections would otherwise fill the table with connections too young
to evict, and starve every other host's master that connects for each poll.
``evict_min_idle`` still shields a master from the churn of its own source and
of sources no more than one heavier, so a kept master polling faster than it
keeps its slot unless its source holds two more than the newcomer's. Why
never-used connections go first: connections that say nothing, from one host or
from many, would otherwise displace masters at work (the share rule sees a busy
host with three connections as heavier than twenty silent hosts with one each),
and under ``"refuse"`` fill the table for good.

The redundancy peer's links. A standby forwards its masters' requests to the active
over links, one per master address, opened from its own address (``pair``: the
addresses of the configured peer). The standby has admitted those masters at its own
listener, with this same rule, so the active does not make them compete as one source:
the peer's connections have a budget of their own, ``max_connections`` of them, outside
the count the other sources share. A newcomer from the peer is admitted while the peer
holds fewer, whatever the others hold (``max_per_source`` does not apply to it), and
is never evicted for another source's newcomer; the others' decisions are made as if
the peer's connections were not there. Only the configured peer's address is believed:
the listener's address screen decides who may connect at all.

Invariants: the count of the other sources' connections never exceeds
``max_connections`` (an eviction frees the slot it fills), nor does the peer's; a
connection with a request in flight is never closed; while any never-used connection
is open, no connection that has sent a request is closed; a newcomer whose source
holds less than its fair share is never refused, under either policy, while another
source holding more than its own has a never-used connection; under ``"refuse"``
only a never-used connection is ever closed, and only for such a newcomer. With no
never-used connection open (``close_oldest_idle``): an evicted connection of the
newcomer's own source or of a source only one heavier was idle for
``evict_min_idle``; a newcomer is never refused while another source holding two
more than its own has a connection with nothing in flight, hence one whose source
stays within its fair share once
admitted (``held + 1 <= max_connections // sources``, the newcomer's counted) is
never refused while the others have nothing in flight.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum


class Refusal(StrEnum):
    """Why a newcomer is refused: the values of ``connections_rejected_total``'s ``reason``."""

    MAX_CONNECTIONS = "max_connections"  # full, and nothing this newcomer may displace
    MAX_PER_SOURCE = "max_per_source"  # its source holds the explicit cap


@dataclass(frozen=True, slots=True)
class ShareLimits:
    """A listener's limits, as ``[server]`` gives them."""

    max_connections: int
    max_per_source: int = 0  #: 0: no cap per source address
    evict: bool = True  #: ``when_full = "close_oldest_idle"``; false: ``"refuse"``
    evict_min_idle: float = 10.0  #: seconds idle before a connection of a peer source yields


@dataclass(frozen=True, slots=True)
class OpenConnection:
    """What the decision needs of one open connection, read at one moment."""

    source: str
    #: Seconds since its last complete request or answer; for a never-used connection,
    #: since it was opened.
    idle: float
    in_flight: int  #: its requests queued or on the wire
    used: bool = True  #: it has sent at least one complete request


@dataclass(frozen=True, slots=True)
class Admit:
    """A slot is free: take it."""


@dataclass(frozen=True, slots=True)
class Evict:
    """Close the snapshot's connection at ``index``, then admit the newcomer."""

    index: int
    #: True when it was taken for being over the newcomer's share, younger than
    #: ``evict_min_idle`` (the log says so).
    over_share: bool = False
    #: True when it was taken as the heaviest source's never-used connection for a
    #: newcomer under its fair share (step 1).
    never_used: bool = False


@dataclass(frozen=True, slots=True)
class Refuse:
    """Turn the newcomer away."""

    reason: Refusal


Verdict = Admit | Evict | Refuse
ADMIT: Admit = Admit()


def has_free_slot(limits: ShareLimits, total: int, held: int) -> bool:
    """True when a newcomer whose source holds ``held`` of ``total`` is admitted outright."""
    if limits.max_per_source and held >= limits.max_per_source:
        return False
    return total < limits.max_connections


def admit_connection(
    source: str,
    limits: ShareLimits,
    connections: Sequence[OpenConnection],
    pair: Collection[str] = (),
) -> Verdict:
    """Admit, evict one of ``connections`` or refuse a newcomer from ``source``; the
    connections of ``pair`` (the redundancy peer's addresses) have their own budget."""
    if pair:
        if source in pair:
            held = sum(1 for connection in connections if connection.source in pair)
            return ADMIT if held < limits.max_connections else Refuse(Refusal.MAX_CONNECTIONS)
        others = [i for i, connection in enumerate(connections) if connection.source not in pair]
        if len(others) < len(connections):
            verdict = admit_connection(source, limits, [connections[i] for i in others])
            return (
                replace(verdict, index=others[verdict.index])
                if isinstance(verdict, Evict)
                else verdict
            )
    counts: dict[str, int] = {}
    oldest_unused: dict[str, int] = {}  # per source: its longest-open never-used connection
    for index, connection in enumerate(connections):
        key = connection.source
        counts[key] = counts.get(key, 0) + 1
        if not connection.used:
            known = oldest_unused.get(key)
            if known is None or connection.idle > connections[known].idle:
                oldest_unused[key] = index
    held = counts.get(source, 0)
    if limits.max_per_source and held >= limits.max_per_source:
        return Refuse(Refusal.MAX_PER_SOURCE)
    if len(connections) < limits.max_connections:
        return ADMIT
    sources = len(counts) + (source not in counts)
    if held * sources < limits.max_connections:  # under its fair share
        heavier = [key for key in oldest_unused if key != source and counts[key] > held]
        if heavier:
            key = max(heavier, key=lambda k: (counts[k], connections[oldest_unused[k]].idle))
            return Evict(oldest_unused[key], never_used=True)
    if not limits.evict:
        return Refuse(Refusal.MAX_CONNECTIONS)
    if oldest_unused:  # never-used connections open: no master at work is closed
        return _share_rule(source, held, limits, connections, counts, used=False)
    return _share_rule(source, held, limits, connections, counts, used=True)


def _share_rule(
    source: str,
    held: int,
    limits: ShareLimits,
    connections: Sequence[OpenConnection],
    counts: dict[str, int],
    used: bool,
) -> Verdict:
    """The share rule over the connections whose ``used`` is ``used`` (module docstring)."""
    best: dict[str, int] = {}  # per source: its longest-idle candidate with nothing in flight
    for index, connection in enumerate(connections):
        if connection.in_flight == 0 and connection.used == used:
            key = connection.source
            known = best.get(key)
            if known is None or connection.idle > connections[known].idle:
                best[key] = index
    heavier = [key for key, count in counts.items() if count > held and key != source]
    heavier.sort(key=lambda key: (-counts[key], -_idle_of(best.get(key), connections), key))
    for key in (*heavier, source):
        candidate = best.get(key)
        if candidate is None:
            continue
        if connections[candidate].idle >= limits.evict_min_idle:
            return Evict(candidate)
        if key != source and counts[key] >= held + 2:
            return Evict(candidate, over_share=True)
    return Refuse(Refusal.MAX_CONNECTIONS)


def _idle_of(index: int | None, connections: Sequence[OpenConnection]) -> float:
    """The idle seconds of the connection at ``index``; -1 for none (sorted last)."""
    return -1.0 if index is None else connections[index].idle
