"""The configuration schema: one declaration per key, and every copy of it in agreement.

The example configuration (gateway/data and its link in conf/) and docs/configuration.md are
rendered from the schema; a copy edited by hand, or a schema changed without regenerating,
fails here with the command that fixes it.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

import pytest

from gateway import config, schema
from gateway.cli import apply_overrides, build_parser
from gateway.config import (
    CacheRule,
    ConfigError,
    LineConfig,
    LoggingConfig,
    MetricsConfig,
    ServerConfig,
    build_config,
    config_warnings,
    load_config,
    policies,
)
from gateway.schema import Reload, Scope, Table, Type
from gateway.schema.__main__ import main as schema_main
from gateway.schema.examples import EXAMPLES
from gateway.schema.render import REGENERATE, drifted, example_toml, rendered

ROOT = Path(__file__).resolve().parents[2]
LINE = {"device": "/dev/null", "units": [1]}


def test_the_committed_copies_are_what_the_schema_renders() -> None:
    stale = drifted(ROOT)
    assert stale == [], f"{', '.join(stale)} drifted from gateway/schema; run: {REGENERATE}"


def test_the_check_command_finds_a_drifted_copy_and_write_mends_it(tmp_path: Path) -> None:
    for path in rendered():
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
    assert schema_main(["--write", "--root", str(tmp_path)]) == 0
    assert schema_main(["--check", "--root", str(tmp_path)]) == 0
    page = tmp_path / "docs" / "configuration.md"
    page.write_text(page.read_text() + "edited by hand\n")
    assert schema_main(["--check", "--root", str(tmp_path)]) == 1
    assert schema_main(["--write", "--root", str(tmp_path)]) == 0
    assert schema_main(["--check", "--root", str(tmp_path)]) == 0


def test_the_example_configuration_loads_and_shows_every_default() -> None:
    built = load_config(ROOT / "conf" / "gateway.example.toml")
    assert built.server == ServerConfig()
    assert built.metrics == MetricsConfig()
    assert built.logging == LoggingConfig()
    parsed = tomllib.loads(example_toml())
    for key in schema.KEYS:
        if key.show is schema.Show.SET and key.table is Table.LINES:
            assert key.name in parsed["lines"]["a"], key.path


def _merge(into: dict[str, Any], block: dict[str, Any]) -> None:
    for name, value in block.items():
        if isinstance(value, dict) and isinstance(into.get(name), dict):
            _merge(into[name], value)
        else:
            into[name] = value


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda example: example.intro[:30])
def test_every_example_block_is_a_configuration_the_parser_takes(example: Any) -> None:
    raw: dict[str, Any] = {"lines": {"a": dict(LINE)}, "policies": {"plant": {"rules": []}}}
    _merge(raw, tomllib.loads(example.body))
    build_config(raw, "example")


_DATACLASSES = {
    Table.SERVER: ServerConfig,
    Table.METRICS: MetricsConfig,
    Table.LOGGING: LoggingConfig,
    Table.LINES: LineConfig,
    Table.CACHE: CacheRule,
}


@pytest.mark.parametrize("table", list(_DATACLASSES), ids=lambda table: table.value)
def test_the_dataclass_defaults_are_the_schemas(table: Table) -> None:
    defaults = {
        f.name: f.default
        for f in dataclasses.fields(_DATACLASSES[table])
        if f.default is not dataclasses.MISSING
    }
    for key in schema.keys_of(table).values():
        if key.name in defaults and key.default not in (None, "auto") and key.type in (
            Type.INTEGER, Type.SECONDS, Type.NUMBER, Type.BOOLEAN, Type.CHOICE, Type.ONE_OF,
        ):  # fmt: skip
            assert defaults[key.name] == key.default, key.path


def test_a_line_left_to_its_defaults_has_the_schemas() -> None:
    line = build_config({"lines": {"a": dict(LINE)}}).line("a")
    for key in schema.keys_of(Table.LINES).values():
        scalar = key.type in (Type.INTEGER, Type.SECONDS, Type.NUMBER, Type.BOOLEAN, Type.CHOICE)
        if scalar and key.default not in (None, "auto") and not key.only.startswith("kind ="):
            assert getattr(line, key.name) == key.default, key.path


def test_the_keys_that_reopen_a_line_are_those_the_reload_compares() -> None:
    reopens = {
        "device" if key.name == "address" else key.name
        for key in schema.keys_of(Table.LINES).values()
        if key.reload is Reload.REOPENS
    }
    assert reopens == set(config.LINE_PORT_SETTINGS)


def test_every_range_holds_its_default_and_every_choice_list_its_default() -> None:
    for key in schema.KEYS:
        default = key.default
        number = isinstance(default, int | float) and not isinstance(default, bool)
        if isinstance(default, int | float) and number and key.low is not None:
            assert key.high is not None and key.low <= default <= key.high, key.path
        if key.choices and key.default is not None:
            assert key.default in key.choices, key.path


def test_the_rule_keys_the_parser_takes_are_documented() -> None:
    documented = set(schema.keys_of(Table.RULES))
    assert policies._RULE_KEYS - documented == set()


# ------------------------------------------------------------------------ former names


def test_a_former_name_is_taken_with_a_warning_naming_the_new_key() -> None:
    built = build_config({"lines": {"a": {**LINE, "retry_writes": True}}}, "plant.toml")
    assert built.line("a").retry_unsafe is True
    assert config_warnings(built)[0] == (
        "lines.a.retry_writes: the former name of retry_unsafe, still accepted; rename it "
        "to retry_unsafe"
    )
    current = build_config({"lines": {"a": {**LINE, "retry_unsafe": True}}}, "plant.toml")
    assert current.renamed == () and current.line("a").retry_unsafe


def test_a_former_name_beside_the_new_one_is_an_error() -> None:
    with pytest.raises(ConfigError) as caught:
        build_config({"lines": {"a": {**LINE, "retry_writes": True, "retry_unsafe": False}}})
    assert caught.value.problems == [
        "lines.a.retry_writes: is the former name of retry_unsafe; keep only retry_unsafe"
    ]


def test_a_fault_in_a_key_written_under_its_former_name_names_what_was_written() -> None:
    with pytest.raises(ConfigError) as caught:
        build_config({"lines": {"a": {**LINE, "retry_writes": "yes"}}})
    assert caught.value.problems == ["lines.a.retry_writes: 'yes' is not true or false"]


def test_a_typo_is_never_pointed_at_a_former_name() -> None:
    with pytest.raises(ConfigError) as caught:
        build_config({"lines": {"a": {**LINE, "retry_writs": True}}})
    (problem,) = caught.value.problems
    assert problem.startswith("lines.a.retry_writs: unknown key; did you mean ")
    assert "retry_writes" not in problem


def test_every_configuration_file_of_the_repository_loads() -> None:
    for path in sorted((ROOT / "conf").glob("*.toml")):
        assert load_config(path).lines, path


# ------------------------------------------------------------------------ flags


def test_every_flag_of_the_schema_is_a_flag_of_the_parser_with_its_help() -> None:
    actions = {option: action for action in build_parser()._actions
               for option in action.option_strings}  # fmt: skip
    for key in schema.flagged():
        assert key.flag is not None
        assert actions[key.flag.name].help == key.flag.help, key.flag.name


@pytest.mark.parametrize(
    ("argv", "where", "expected"),
    [
        (["--retries", "3"], ("lines", "retries"), 3),
        (["--timeout", "0.5"], ("lines", "timeout"), 0.5),
        (["--stopbits", "2"], ("lines", "stop_bits"), 2.0),
        (["--parity", "E"], ("lines", "parity"), "E"),
        (["--framing", "ascii"], ("lines", "kind"), "ascii"),
        (["--frame-gap", "0"], ("lines", "frame_gap"), 0.0),
        (["--listen", "127.0.0.1:1502"], ("server", "port"), 1502),
        (["--read-only"], ("server", "read_only"), True),
        (["--metrics", "off"], ("metrics", "enabled"), False),
        (["--log-level", "debug"], ("logging", "level"), "debug"),
    ],
)
def test_a_flag_sets_its_key(argv: list[str], where: tuple[str, str], expected: object) -> None:
    built = build_config(
        apply_overrides({"lines": {"a": dict(LINE)}}, build_parser().parse_args(argv))
    )
    section, name = where
    target = built.line("a") if section == "lines" else getattr(built, section)
    assert getattr(target, name) == expected


def test_flag_scopes_name_what_they_set() -> None:
    scopes = {key.flag.name: key.flag.scope for key in schema.flagged() if key.flag}
    assert scopes["--baudrate"] is Scope.EVERY_LINE
    assert scopes["--max-in-flight"] is Scope.MBAP_LINES
    assert scopes["--tls-cert"] is Scope.TLS_LISTENER
    assert scopes["--modbus-tls-ca"] is Scope.TLS_LINES
