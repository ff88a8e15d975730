"""The wire strategies' findings: the one built without ``Finding``'s Python-level
constructor on the per-transaction path is the same tuple the constructor makes."""

from __future__ import annotations

from gateway.core.line.records import tuple_new
from gateway.core.line.wire import _NO_DETAIL, Finding, Found


def test_a_complete_finding_built_inline_equals_the_constructors() -> None:
    attempt = object()
    frame = object()
    built = tuple_new(Finding, (Found.COMPLETE, attempt, frame, *_NO_DETAIL))
    made = Finding(Found.COMPLETE, attempt, frame)  # type: ignore[arg-type]
    assert built == made
    assert type(built) is Finding
    assert built.slave == -1 and built.data == b"" and built.error is None
