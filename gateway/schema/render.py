"""The committed copies of the schema: the example configuration and the reference page.

``python -m gateway.schema --write`` writes them; ``--check`` (and tests/unit/test_schema.py)
says which drifted. Rendering is pure: text in, text out.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

from .examples import EXAMPLES, Example
from .keys import KEYS
from .model import TOP_LEVEL, Key, Show, Table

REGENERATE = "python -m gateway.schema --write"
WIDTH = 99
#: Where the committed copies live, relative to the checkout's root.
EXAMPLE_PATHS = ("gateway/data/gateway.example.toml", "conf/gateway.example.toml")
REFERENCE_PATH = "docs/configuration.md"

_EXAMPLE_HEADER = f"""\
# modbus-gateway configuration. Every key is shown with its default; docs/configuration.md
# is the reference of every key. Generated from gateway/schema: {REGENERATE}
# Validate a file with:  modbus-gateway check-config /etc/modbus-gateway/gateway.toml
"""

#: What each table of the example file opens with, besides its heading.
_EXAMPLE_TABLES = (
    (Table.SERVER, "[server]", ""),
    (Table.METRICS, "[metrics]", ""),
    (Table.LOGGING, "[logging]", ""),
    (Table.AUDIT, "[audit]", ""),
    (
        Table.REDUNDANCY,
        "[redundancy]",
        "An active/standby pair on one bus (docs/redundancy.md); "
        "without peer, the gateway runs alone.",
    ),
    (
        Table.LINES,
        "[lines.a]",
        'One table per line. The name ("a") is used in logs, metrics and routes.',
    ),
    (Table.ROUTES, "", ""),
    (
        Table.POLLING,
        "[polling]",
        "Agent mode (docs/agent-mode.md): the [[poll]] blocks below are polled by the gateway "
        "and masters' reads inside them answered from memory.",
    ),
)


def toml_value(value: object) -> str:
    """``value`` as TOML."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(item) for item in value) + "]"
    if isinstance(value, dict) and not value:
        return "{}"
    raise TypeError(f"no TOML for {value!r}")


def _comment(text: str, indent: str = "# ") -> list[str]:
    return textwrap.wrap(
        text,
        WIDTH - len(indent),
        initial_indent=indent,
        subsequent_indent=indent,
        break_on_hyphens=False,
    )


def _key_help(key: Key) -> str:
    """The key's help with its derived default and former names."""
    text = key.help
    if key.auto:
        text += (
            f' Default "auto": {key.auto}.' if key.default == "auto" else f" Default: {key.auto}."
        )
    if key.aliases:
        names = ", ".join(key.aliases)
        text += f" (Former name: {names}, still accepted.)"
    return text


def _example_key(key: Key) -> list[str]:
    value = key.example or toml_value(key.default)
    setting = f"{key.name} = {value}"
    return [*_comment(_key_help(key)), f"# {setting}" if key.show is Show.COMMENTED else setting]


def _example_block(example: Example) -> list[str]:
    body = example.body.rstrip("\n").split("\n")
    if example.commented:
        body = [f"# {line}" for line in body]
    return ["", *_comment(example.intro), *body]


def example_toml() -> str:
    """The example configuration: every key shown with its default, and example blocks."""
    out = _EXAMPLE_HEADER.rstrip("\n").split("\n")
    for table, heading, intro in _EXAMPLE_TABLES:
        if heading:
            out.append("")
        if intro:
            out += _comment(intro)
        if heading:
            out.append(heading)
        for key in KEYS:
            if key.table is table and key.show is not Show.BLOCK:
                out += _example_key(key)
        for example in EXAMPLES:
            if example.after is table:
                out += _example_block(example)
    return "\n".join(out) + "\n"


_REFERENCE_HEADER = f"""\
# Configuration reference

<!-- Generated from the schema (gateway/schema) by `{REGENERATE}`: change the
schema, not this page. tests/unit/test_schema.py fails when it drifts. -->

The gateway reads one TOML file (`--config FILE`). `modbus-gateway check-config FILE` lists
every problem with its key and the fix (unknown keys get a "did you mean"), and
`modbus-gateway example-config` prints the example (`conf/gateway.example.toml` in the
source tree), every key with its default. Flags override the file ([below](#command-line-flags)).

*On reload* says what SIGHUP does when the key's value changed: **applied** (from the next
request or connection on), **reopens the line** (its queue and the transaction on the wire are
handed over to the reopened line) or **needs a restart** (the running value stays, with a
warning in the log).
"""

#: What each table is, above its keys on the reference page.
_REFERENCE_INTROS = {
    Table.SERVER: "The Modbus TCP side, and what every listener shares.",
    Table.LISTENERS: "More listeners besides the `[server] listen` shorthand (named `tcp`).",
    Table.METRICS: "The HTTP endpoint for /metrics, /healthz and /readyz.",
    Table.LOGGING: "Log level and format.",
    Table.AUDIT: "The audit log: one hash-chained JSON line per write, denial, configuration "
    "change and refused connection (docs/audit.md).",
    Table.REDUNDANCY: "Two gateways on one bus, one active at a time (docs/redundancy.md). "
    "Without `peer` the gateway runs alone and is always active.",
    Table.LINES: "One table per line; the name is used in logs, metrics and routes.",
    Table.CACHE: "Read cache rules of a line (see `cache`).",
    Table.ROUTES: "Remapping: a TCP unit id to a slave address on a line.",
    Table.POLL: "Agent mode's poll blocks (docs/agent-mode.md): the gateway reads each block "
    "every `every` seconds and answers masters' reads wholly inside it from memory while its "
    "data is younger than `max_age`. Reloadable: an unchanged block keeps its data.",
    Table.POLLING: "What agent mode shares across its blocks.",
    Table.POLICIES: "Named rule lists, used by a listener's `policy`.",
    Table.RULES: "Rules only grant: a request is served when one rule matching the master "
    "(role, source) grants its unit, function, access and whole address range; everything "
    "else gets 0x01. Omitted keys mean any. A rule that names a unit covers that slave "
    "whatever unit id reaches it; `line` names a line, `slave` a slave address on it.",
}


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _default_cell(key: Key) -> str:
    if key.default == "auto":
        return f'`"auto"`: {key.auto}'
    if key.auto:
        return key.auto
    return "(none)" if key.default is None else f"`{toml_value(key.default)}`"


def _number(value: float) -> str:
    return f"{int(value):,}" if float(value).is_integer() else f"{value:g}"


def _allowed_cell(key: Key) -> str:
    if key.choices:
        return ", ".join(f"`{toml_value(choice)}`" for choice in key.choices)
    if key.low is not None and key.high is not None:
        return f"{_number(key.low)} to {_number(key.high)}"
    return ""


def _reference_table(table: Table) -> list[str]:
    keys = [key for key in KEYS if key.table is table]
    out = [f"## `{table.heading}`", "", _REFERENCE_INTROS[table], ""]
    out += ["| key | type | default | allowed | on reload | flag |", "| --- " * 6 + "|"]
    for key in keys:
        flag = f"`{key.flag.name}`" if key.flag else ""
        cells = (
            f"`{key.name}`",
            key.type.value,
            _default_cell(key),
            _allowed_cell(key),
            key.reload.value,
            flag,
        )
        out.append("| " + " | ".join(_cell(cell) for cell in cells) + " |")
    out.append("")
    for key in keys:
        notes = [key.help]
        if key.only:
            notes.append(f"Only with {key.only}.")
        if key.aliases:
            notes.append(f"Former name: {', '.join(f'`{a}`' for a in key.aliases)}.")
        out.append(f"- `{key.name}`: " + " ".join(notes))
    return [*out, ""]


def _flags_section() -> list[str]:
    out = [
        "## Command-line flags",
        "",
        "Each of these flags sets a key for this run (the file is not changed):",
        "",
        "| flag | sets | on |",
        "| --- | --- | --- |",
    ]
    for key in KEYS:
        if key.flag is None:
            continue
        out.append(f"| `{key.flag.name}` | `{key.path}` | {_cell(key.flag.scope.value)} |")
    out += [
        "",
        "The other flags (`--serial`, `--rtu-over-tcp`, `--modbus-tcp`, `--modbus-tls`, "
        "`--rtu-over-tcp-listen`, `--serial-slave`, ...) add a line or a listener: "
        "`modbus-gateway --help` lists them.",
    ]
    return [*out, ""]


def _aliases_section() -> list[str]:
    out = [
        "## Former names",
        "",
        "Still accepted, with a warning naming the new key (`check-config --strict` refuses them):",
        "",
    ]
    for key in KEYS:
        out += [f"- `{key.table.prefix}{alias}`: now `{key.name}`" for alias in key.aliases]
    return [*out, ""]


def reference_markdown() -> str:
    """docs/configuration.md: every key, its type, default, range, reload effect and flag."""
    out = _REFERENCE_HEADER.split("\n")
    out.append(f"Top-level tables: {', '.join(f'`{name}`' for name in TOP_LEVEL)}.")
    out.append("")
    for table in Table:
        out += _reference_table(table)
    out += _flags_section() + _aliases_section()
    return "\n".join(out).rstrip("\n") + "\n"


def rendered() -> dict[str, str]:
    """Every committed copy, by its path in the checkout."""
    example = example_toml()
    return {**dict.fromkeys(EXAMPLE_PATHS, example), REFERENCE_PATH: reference_markdown()}


def drifted(root: Path) -> list[str]:
    """The committed copies under ``root`` that differ from what the schema renders."""
    stale: list[str] = []
    for path, text in rendered().items():
        target = root / path
        if not target.exists() or target.read_text(encoding="utf-8") != text:
            stale.append(path)
    return stale


def write(root: Path) -> list[str]:
    """Write every copy that drifted; the paths written."""
    stale = drifted(root)
    texts = rendered()
    for path in stale:
        (root / path).write_text(texts[path], encoding="utf-8")
    return stale
