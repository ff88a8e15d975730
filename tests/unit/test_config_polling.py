"""``[[poll]]`` and ``[polling]``: agent mode's blocks, how they resolve, and their mistakes."""

from __future__ import annotations

from typing import Any

import pytest

from gateway.config import (
    ConfigError,
    PollConfig,
    build_config,
    config_warnings,
    policy_warnings,
    poll_plan_share,
)
from tests import helpers

LINES = {"a": {"device": "/dev/ttyUSB0", "units": [1, 2]}, "b": {"device": "/dev/ttyUSB1"}}
ROUTES = [{"unit": 100, "line": "b", "slave": 7}]


def raw_config(polls: list[dict[str, Any]], **polling: Any) -> dict[str, Any]:
    raw: dict[str, Any] = {"lines": LINES, "routes": ROUTES, "poll": polls}
    if polling:
        raw["polling"] = polling
    return raw


def config(polls: list[dict[str, Any]], **polling: Any) -> Any:
    return build_config(raw_config(polls, **polling), "plant.toml")


def problems(polls: list[dict[str, Any]], **polling: Any) -> list[str]:
    return helpers.problems(raw_config(polls, **polling))


def test_a_block_resolves_to_its_line_and_slave_through_the_routes() -> None:
    built = config(
        [
            {"unit": 1, "function": 3, "address": 0, "count": 50, "every": 1.0},
            {
                "unit": 100,
                "function": 1,
                "address": 10,
                "count": 2000,
                "every": 0.5,
                "max_age": 0.5,
            },
        ]
    )
    first, second = built.polls
    assert first == PollConfig(1, 3, 0, 50, 1.0, 3.0, "a", 1, 0)  # max_age: 3 x every
    assert second == PollConfig(100, 1, 10, 2000, 0.5, 0.5, "b", 7, 1)
    assert built.line("a").polls == (first,) and built.line("b").polls == (second,)
    assert built.polling.status_unit == 0 and built.polling.max_blocks == 256


def test_a_block_of_an_unrouted_unit_names_the_key_and_the_fix() -> None:
    (problem,) = problems([{"unit": 5, "count": 10}])
    assert problem.startswith("plant.toml: poll[0].unit: unit 5 is not routed") or (
        "poll[0].unit: unit 5 is not routed" in problem
    )
    assert "[[routes]]" in problem


@pytest.mark.parametrize(
    ("block", "key", "words"),
    [
        ({"unit": 1, "function": 3, "count": 126}, "poll[0].count", "125 registers"),
        ({"unit": 1, "function": 4, "count": 200}, "poll[0].count", "split the block"),
        ({"unit": 1, "function": 1, "count": 2001}, "poll[0].count", "2000"),
        ({"unit": 1, "address": 65530, "count": 10}, "poll[0].count", "past 65535"),
        ({"unit": 1, "count": 10, "every": 2.0, "max_age": 1.0}, "poll[0].max_age", ">= every"),
        ({"unit": 1, "function": 5, "count": 1}, "poll[0].function", ""),
        ({"unit": 1}, "poll[0].count", "missing"),
        ({"count": 3}, "poll[0].unit", "missing"),
        ({"unit": 1, "count": 1, "start": 3}, "poll[0].start", ""),
    ],
)
def test_a_faulty_block_names_its_key(block: dict[str, Any], key: str, words: str) -> None:
    found = [problem for problem in problems([block]) if key in problem]
    assert found, problems([block])
    assert words in found[0]


def test_overlapping_blocks_of_one_slave_and_function_are_an_error() -> None:
    found = problems(
        [
            {"unit": 1, "address": 0, "count": 10},
            {"unit": 1, "address": 5, "count": 10},
        ]
    )
    assert any("poll[1].address" in p and "overlaps poll[0]" in p for p in found), found
    # Adjacent blocks, another function or another slave: no overlap.
    config(
        [
            {"unit": 1, "address": 0, "count": 10},
            {"unit": 1, "address": 10, "count": 10},
            {"unit": 1, "function": 4, "address": 0, "count": 10},
            {"unit": 2, "address": 0, "count": 10},
        ]
    )


def test_the_status_unit_may_not_be_a_routed_unit_and_blocks_are_bounded() -> None:
    found = problems([], status_unit=100)
    assert any("polling.status_unit" in p and "routed to line 'b'" in p for p in found), found
    assert config([], status_unit=250).polling.status_unit == 250
    many = [{"unit": 1, "address": 10 * i, "count": 10} for i in range(5)]
    assert any("polling.max_blocks" in p for p in problems(many, max_blocks=4))


def test_a_plan_above_half_the_wire_time_is_warned_about() -> None:
    light = config([{"unit": 1, "count": 10, "every": 1.0}])
    assert poll_plan_share(light.line("a")) == pytest.approx(
        (8 + 25) * 10 / 9600 + 2 * 3.5 * 10 / 9600,
        rel=1e-6,  # 8N1: 10 bits a character
    )
    assert not [w for w in config_warnings(light) if w.startswith("poll:")]
    heavy = config([{"unit": 1, "count": 125, "every": 0.3}])
    (warning,) = [w for w in config_warnings(heavy) if w.startswith("poll:")]
    assert "line 'a'" in warning and "9600 baud" in warning and "raise every" in warning


def test_the_status_units_line_label_is_no_real_lines_name() -> None:
    raw: dict[str, Any] = {
        "lines": {"status": {"device": "/dev/ttyUSB0", "units": [1]}},
        "polling": {"status_unit": 250},
    }
    with pytest.raises(ConfigError) as caught:
        build_config(raw, "plant.toml")
    (problem,) = caught.value.problems
    assert "lines.status" in problem and "rename the line" in problem
    raw["polling"] = {"status_unit": 0}
    assert build_config(raw, "plant.toml").line("status").name == "status"  # off: no clash


def test_a_rule_may_name_the_status_unit_alone() -> None:
    raw: dict[str, Any] = {
        "lines": LINES,
        "server": {"policy": "p"},
        "policies": {"p": {"rules": [{"units": [250], "access": "read"}]}},
        "polling": {"status_unit": 250},
    }
    assert policy_warnings(build_config(raw, "p.toml")) == []
    raw["polling"] = {"status_unit": 0}
    (warning,) = policy_warnings(build_config(raw, "p.toml"))
    assert "none of its units is routed" in warning
