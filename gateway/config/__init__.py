"""Configuration: a TOML file and command-line overrides, as frozen, validated dataclasses.

Callers import from here. The modules are cut by table: ``model`` (the dataclasses, their
defaults the schema's), ``reading`` (the file, and typed values out of raw tables),
``lines``, ``routes``, ``polling``, ``listeners`` (with ``[server]``), ``policies``,
``services`` (endpoint, log, audit log, pair), ``warnings`` (``check-config``'s) and
``build`` (the whole, cross-checked).
"""

from .build import build_config, load_config
from .lines import LINE_PORT_SETTINGS, auto_timeout
from .model import (
    NETWORK_LINE_KINDS,
    CacheRule,
    GatewayConfig,
    LineConfig,
    ListenerConfig,
    LoggingConfig,
    MetricsConfig,
    PollConfig,
    RedundancyConfig,
    ServerConfig,
)
from .policies import parse_function_key
from .reading import ConfigError, parse_host_port, parse_units, read_config_file
from .routes import format_units
from .services import is_loopback
from .warnings import config_warnings, policy_warnings, poll_plan_share

__all__ = [
    "LINE_PORT_SETTINGS",
    "NETWORK_LINE_KINDS",
    "CacheRule",
    "ConfigError",
    "GatewayConfig",
    "LineConfig",
    "ListenerConfig",
    "LoggingConfig",
    "MetricsConfig",
    "PollConfig",
    "RedundancyConfig",
    "ServerConfig",
    "auto_timeout",
    "build_config",
    "config_warnings",
    "format_units",
    "is_loopback",
    "load_config",
    "parse_function_key",
    "parse_host_port",
    "parse_units",
    "policy_warnings",
    "poll_plan_share",
    "read_config_file",
]
