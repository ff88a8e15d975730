"""Repeats of one refusal or denial from one source: counted, not written one by one (no I/O).

Theory of operation. A host outside an allow list, or a read-only master sending
writes, can cause thousands of identical audit records a second. What an auditor
needs is the event and how often it happened, so ``Repeats`` sits in front of the
writer for those two kinds of record only (a ``connection_refused`` at accept and a
``request`` whose outcome is ``denied``); a write that reaches a slave never comes
here. Each event arrives as an ``Occurrence``: its source (the address), its
*kind* (the fields that make two events the same: listener, reason, role, unit,
function...) and its *detail* (what may differ between two such events: the peer's
port, the request's bytes).

Time is cut into intervals of ``interval`` seconds (``floor(time / interval)``,
the caller's clock). Within one interval, per source:

- the first event of a kind is written at once, as an ordinary record;
- the next ones of that kind are counted in a tally; when the interval is over,
  the tally becomes one record: the first counted event's record with
  ``repeats`` (how many events it stands for), ``first`` and ``last`` (their
  times; ``time`` is ``last``) and ``source``; when their details differ, the
  fields that describe one request (``DETAIL_FIELDS``) are left out;
- a source that has shown ``kinds_per_source`` kinds already has every further
  kind counted in one tally per family (``connection_refused``, denied
  ``request``), without a record written at once; a field of the kind that
  differs between its events is left out of its record.

Invariants: every occurrence is either written at once (it stands for one event)
or counted in exactly one tally, and every tally is written once (``due`` when its
interval is over, ``flush`` at the end): the ``repeats`` of a source's records,
counting 1 for a record without ``repeats``, add up to its events. A source gets at
most ``2 * kinds_per_source + families`` records per interval (12 kinds: 26 per
second), whatever it does. Records come out in the order written: a tally after the
record written at once of its kind.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from .audit_record import Record, timestamp

#: Seconds per interval: a tally is written at most this long after its first event.
INTERVAL_S: Final = 1.0
#: Kinds of event per source and interval written at once and tallied apart.
KINDS_PER_SOURCE: Final = 12
#: Fields of a request record that describe the one request, not its kind.
DETAIL_FIELDS: Final = ("peer", "addresses", "values", "data", "count", "subfunction")

Kind = tuple[tuple[str, object], ...]


@dataclass(frozen=True, slots=True)
class Occurrence:
    """One refusal or denial, as the aggregation sees it."""

    source: str  #: the source address (no port): what "from the same source" means
    family: str  #: ``connection_refused`` or ``request``: a source's tallies beyond its kinds
    kind: Kind  #: the fields (name, value) that make two events the same
    detail: object  #: what may differ between events of one kind (peer, request bytes)
    time: float  #: POSIX seconds


@dataclass(slots=True)
class _Tally:
    """Events of one kind (or one family, past the kinds) from one source, counted."""

    record: Record  #: the first counted event's record
    names: frozenset[str]  #: the names of the kind's fields
    kind: dict[str, object]  #: the kind's fields still common to every counted event
    detail: object  #: the first counted event's detail
    first: float
    last: float = 0.0
    repeats: int = 0
    same_detail: bool = True

    @classmethod
    def of(cls, occurrence: Occurrence, record: Record) -> _Tally:
        kind = dict(occurrence.kind)
        return cls(record, frozenset(kind), kind, occurrence.detail, occurrence.time)

    def add(self, occurrence: Occurrence) -> None:
        self.repeats += 1
        self.last = occurrence.time
        if self.same_detail and occurrence.detail != self.detail:
            self.same_detail = False
        kind = self.kind
        if len(kind) != len(occurrence.kind) or any(kind.get(k) != v for k, v in occurrence.kind):
            common = dict(occurrence.kind)
            self.kind = {k: v for k, v in kind.items() if k in common and common[k] == v}

    def sealed(self, source: str) -> Record:
        """The record this tally stands for."""
        record = dict(self.record)
        if not self.same_detail:
            for name in DETAIL_FIELDS:
                record.pop(name, None)
        for name in self.names - self.kind.keys():  # differed between its events
            record.pop(name, None)
            if name == "function":
                record.pop("function_name", None)
        record.update(
            source=source,
            repeats=self.repeats,
            first=timestamp(self.first),
            last=timestamp(self.last),
            time=timestamp(self.last),
        )
        return record


@dataclass(slots=True)
class _Source:
    """One source's kinds in the running interval."""

    #: Per kind: ``None`` once its first event was written, then its tally.
    kinds: dict[Kind, _Tally | None] = field(default_factory=dict)
    overflow: dict[str, _Tally] = field(default_factory=dict)  #: per family, past the kinds


class Repeats:
    """Counts repeated refusals and denials per source and interval (module docstring)."""

    def __init__(
        self, interval: float = INTERVAL_S, kinds_per_source: int = KINDS_PER_SOURCE
    ) -> None:
        self.interval = interval
        self.kinds_per_source = kinds_per_source
        self._tick: int | None = None
        self._sources: dict[str, _Source] = {}

    def note(self, occurrence: Occurrence, build: Callable[[], Record]) -> list[Record]:
        """Count ``occurrence``; return the records to write now, in order (``build``
        makes its record, called only when it is written or starts a tally)."""
        records = self.due(occurrence.time)
        self._tick = self._tick_of(occurrence.time)
        state = self._sources.get(occurrence.source)
        if state is None:
            state = self._sources[occurrence.source] = _Source()
        kinds = state.kinds
        if occurrence.kind in kinds:
            tally = kinds[occurrence.kind]
            if tally is None:
                tally = kinds[occurrence.kind] = _Tally.of(occurrence, build())
            tally.add(occurrence)
        elif len(kinds) < self.kinds_per_source:
            kinds[occurrence.kind] = None
            records.append(build())
        else:
            tally = state.overflow.get(occurrence.family)
            if tally is None:
                tally = state.overflow[occurrence.family] = _Tally.of(occurrence, build())
            tally.add(occurrence)
        return records

    def due(self, now: float) -> list[Record]:
        """The tallies of an interval that is over by ``now``, as records."""
        if self._tick is None or self._tick_of(now) == self._tick:
            return []
        return self.flush()

    def flush(self) -> list[Record]:
        """Every tally as a record, now (at the end, or once its interval is over)."""
        records = [
            tally.sealed(source)
            for source, state in self._sources.items()
            for tally in (*state.kinds.values(), *state.overflow.values())
            if tally is not None
        ]
        self._sources.clear()
        self._tick = None
        return records

    def _tick_of(self, now: float) -> int:
        return math.floor(now / self.interval)
