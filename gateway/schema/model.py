"""The vocabulary of the schema: tables, value types, reload effects, flags and keys."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class Table(enum.Enum):
    """Where a key is written in the file."""

    SERVER = "server"
    LISTENERS = "listeners"
    METRICS = "metrics"
    LOGGING = "logging"
    AUDIT = "audit"
    REDUNDANCY = "redundancy"
    LINES = "lines"
    CACHE = "cache"
    ROUTES = "routes"
    POLL = "poll"
    POLLING = "polling"
    POLICIES = "policies"
    RULES = "rules"

    @property
    def heading(self) -> str:
        """The table as written in TOML."""
        return _HEADINGS[self]

    @property
    def prefix(self) -> str:
        """The start of a key's name in messages (``lines.NAME.``)."""
        return _PREFIXES[self]


_HEADINGS = {
    Table.SERVER: "[server]",
    Table.LISTENERS: "[[listeners]]",
    Table.METRICS: "[metrics]",
    Table.LOGGING: "[logging]",
    Table.AUDIT: "[audit]",
    Table.REDUNDANCY: "[redundancy]",
    Table.LINES: "[lines.NAME]",
    Table.CACHE: "[[lines.NAME.cache]]",
    Table.ROUTES: "[[routes]]",
    Table.POLL: "[[poll]]",
    Table.POLLING: "[polling]",
    Table.POLICIES: "[policies.NAME]",
    Table.RULES: "[[policies.NAME.rules]]",
}
_PREFIXES = {
    Table.SERVER: "server.",
    Table.LISTENERS: "listeners[N].",
    Table.METRICS: "metrics.",
    Table.LOGGING: "logging.",
    Table.AUDIT: "audit.",
    Table.REDUNDANCY: "redundancy.",
    Table.LINES: "lines.NAME.",
    Table.CACHE: "lines.NAME.cache[N].",
    Table.ROUTES: "routes[N].",
    Table.POLL: "poll[N].",
    Table.POLLING: "polling.",
    Table.POLICIES: "policies.NAME.",
    Table.RULES: "policies.NAME.rules[N].",
}

#: The tables at the top of the file, in the order the parser reads them.
TOP_LEVEL = (
    "server",
    "metrics",
    "logging",
    "audit",
    "redundancy",
    "lines",
    "routes",
    "poll",
    "polling",
    "listeners",
    "policies",
)


class Type(enum.Enum):
    """What a key's value is; the parser's check and the reference page follow from it."""

    INTEGER = "integer"
    SECONDS = "seconds"
    NUMBER = "number"
    BOOLEAN = "boolean"
    CHOICE = "choice"  # one of the strings in ``choices``
    ONE_OF = "one of"  # one of the numbers in ``choices``
    TEXT = "string"
    FILE = "file path"
    ADDRESS = "HOST:PORT"
    ADDRESS_OR_OFF = 'HOST:PORT, "auto" or "off"'
    UNITS = "unit ids"
    NETWORKS = "networks"
    FUNCTION_CODES = "function codes"
    FUNCTIONS = "functions"
    RANGES = "ranges"
    TIMEOUTS = "table"
    NAMES = "table of names"
    TABLES = "tables"


class Reload(enum.Enum):
    """What a reload (SIGHUP) does when the key's value changed."""

    APPLIED = "applied"
    REOPENS = "reopens the line"
    RESTART = "needs a restart"


class Scope(enum.Enum):
    """What a command-line flag sets."""

    TABLE = "its table"  # [server], [metrics], [logging]
    EVERY_LINE = "every line"
    MBAP_LINES = 'every kind = "tcp" or "tls" line'
    TLS_LINES = 'every kind = "tls" line'
    TLS_LISTENER = "the listener named tls"


class Show(enum.Enum):
    """How the example configuration shows a key."""

    SET = "set"  # written with its default
    COMMENTED = "commented"  # written commented out
    BLOCK = "block"  # only in an example block (a line kind, a listener, a rule)


@dataclass(frozen=True, kw_only=True)
class Flag:
    """A command-line flag that overrides a key."""

    name: str
    help: str
    scope: Scope = Scope.TABLE
    metavar: str | None = None
    #: Narrower than the key's: what the flag accepts (ints or strings).
    choices: tuple[int | str, ...] = ()
    repeat: bool = False

    @property
    def dest(self) -> str:
        """The attribute argparse stores the value in."""
        return self.name.lstrip("-").replace("-", "_")


@dataclass(frozen=True, kw_only=True, eq=False)
class Key:
    """One configuration key, declared once (its identity is its equality)."""

    table: Table
    name: str
    type: Type
    help: str
    #: The value when the key is left out; ``None``: none (required, or derived: see ``auto``).
    default: object = None
    low: float | None = None
    high: float | None = None
    choices: tuple[int | float | str, ...] = ()
    #: What the default is when it is derived from other keys (``"auto"``).
    auto: str = ""
    #: Which entries of the table take the key (``kind = "tls"``); empty: every one.
    only: str = ""
    reload: Reload = Reload.APPLIED
    flag: Flag | None = None
    #: Former names, still accepted with a warning naming this key.
    aliases: tuple[str, ...] = ()
    show: Show = Show.SET
    #: The value written in the example configuration, as TOML (empty: the default).
    example: str = ""

    @property
    def path(self) -> str:
        """The key's full name, like ``lines.NAME.baudrate``."""
        return self.table.prefix + self.name

    def int_range(self) -> tuple[int, int]:
        """``low`` and ``high`` of an integer key."""
        assert self.low is not None and self.high is not None, self.name
        return int(self.low), int(self.high)

    def float_range(self) -> tuple[float, float]:
        """``low`` and ``high`` of a number key."""
        assert self.low is not None and self.high is not None, self.name
        return float(self.low), float(self.high)
