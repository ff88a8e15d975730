"""The simulator's response-time profiles: phases counted over every unit id of one device.

``bench.slaves --response-time`` times a device's answers by phase (the benchmark's
``learning`` scenario: a device fast for its first answers, slow later). The phase an
answer falls in, the time each phase began and the argument's form are pure logic.
"""

from __future__ import annotations

import random

import pytest

from bench.slaves import (
    ResponsePhase,
    ResponseProfile,
    parse_response_profile,
    response_profile_argument,
)


def test_phases_follow_the_device_count_and_the_last_lasts() -> None:
    profile = parse_response_profile("1,2,3,4:5@0.005-0.038:0.02-0.48")
    assert profile.units == (1, 2, 3, 4)
    assert profile.phases == (ResponsePhase(5, 0.005, 0.038), ResponsePhase(None, 0.02, 0.48))
    rng = random.Random(1)
    delays = [profile.next_delay(rng, now=float(answer)) for answer in range(200)]
    assert all(0.005 <= delay <= 0.038 for delay in delays[:5])
    assert all(0.02 <= delay <= 0.48 for delay in delays[5:])
    assert max(delays[5:]) > 0.4 and min(delays[5:]) < 0.1  # drawn over the whole range
    assert profile.phase_started_at == [0.0, 5.0]  # stamped at each phase's first answer
    assert profile.stats()["answers"] == 200


def test_a_single_value_is_a_fixed_response_time() -> None:
    profile = parse_response_profile("7:30@0.01:0.4")
    rng = random.Random(2)
    delays = [profile.next_delay(rng, now=0.0) for _ in range(31)]
    assert delays[:30] == [0.01] * 30
    assert delays[30] == 0.4


def test_the_argument_round_trips() -> None:
    text = response_profile_argument((1, 2), [(3, 0.01, 0.02), (None, 0.4, 0.4)])
    assert text == "1,2:3@0.01-0.02:0.4-0.4"
    assert parse_response_profile(text).phases[0] == ResponsePhase(3, 0.01, 0.02)


@pytest.mark.parametrize(
    ("text", "fault"),
    [
        ("1", "UNITS:PHASES"),
        ("x:0.1", "not numbers"),
        ("1,1:0.1", "distinct"),
        ("300:0.1", "1..247"),
        ("1:5@0.1", "last phase"),
        ("1:0.1:0.2", "count of at least 1"),
        ("1:0@0.1:0.2", "count of at least 1"),
        ("1:0.3-0.1", "MIN <= MAX"),
        ("1:fast", "COUNT@"),
    ],
)
def test_a_malformed_profile_is_refused_with_its_fault(text: str, fault: str) -> None:
    with pytest.raises(ValueError, match=fault):
        parse_response_profile(text)


def test_a_profile_needs_an_open_last_phase() -> None:
    with pytest.raises(ValueError, match="last phase"):
        ResponseProfile((1,), (ResponsePhase(3, 0.1, 0.1),))
