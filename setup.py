"""The optional compiled build: the hot path through mypyc, when asked for.

The gateway is plain Python and installs as such everywhere (no compiler needed).
With ``MODBUS_GATEWAY_COMPILE=1`` the modules every transaction runs through are
compiled to C extensions by mypyc (the mypy project's compiler for type-annotated
Python, the one black and mypy ship their own wheels with); the same source, the
same behaviour, about half the interpreter time per transaction. It needs mypy
and a C compiler at build time only, nothing more at run time::

    pip install mypy setuptools wheel
    MODBUS_GATEWAY_COMPILE=1 pip install --no-build-isolation .

or, in a checkout (the extensions are built next to the sources and take precedence)::

    MODBUS_GATEWAY_COMPILE=1 python setup.py build_ext --inplace

``modbus-gateway --version`` says which build runs. Everything else is in pyproject.toml.
"""

from __future__ import annotations

import os

from setuptools import setup

#: The modules a transaction runs through. The rest stays interpreted: it runs once per
#: connection or reload, or it uses what mypyc does not compile (enum flags, ctypes,
#: subclasses of built-in exceptions).
COMPILED_MODULES = [
    "gateway/core/ascii.py",
    "gateway/core/crc.py",
    "gateway/core/framing.py",
    "gateway/core/line/__init__.py",
    "gateway/core/line/ends.py",
    "gateway/core/line/fair_queue.py",
    "gateway/core/line/flights.py",
    "gateway/core/line/health.py",
    "gateway/core/line/late.py",
    "gateway/core/line/machine.py",
    "gateway/core/line/order.py",
    "gateway/core/line/pipelined.py",
    "gateway/core/line/records.py",
    "gateway/core/line/sending.py",
    "gateway/core/line/sharing.py",
    "gateway/core/line/wire.py",
    "gateway/core/mbap.py",
    "gateway/core/outcome.py",
    "gateway/core/pdu.py",
    "gateway/core/rtu.py",
    "gateway/core/timing.py",
    "gateway/io/bus.py",
    "gateway/io/clock.py",
    "gateway/io/line_notes.py",
    "gateway/io/rtu_listener.py",
    "gateway/io/serial_port.py",
    "gateway/io/tcp.py",
    "gateway/metrics.py",
]


def _extensions() -> list[object]:
    if os.environ.get("MODBUS_GATEWAY_COMPILE", "") not in ("1", "true", "yes"):
        return []
    try:
        from mypyc.build import mypycify
    except ImportError as error:  # a clear error, not a silently interpreted build
        raise SystemExit(
            "MODBUS_GATEWAY_COMPILE=1 needs mypy in the build environment: "
            "pip install mypy setuptools wheel, then build with --no-build-isolation"
        ) from error
    return list(mypycify(COMPILED_MODULES, opt_level="3", group_name="gateway"))


setup(ext_modules=_extensions())
