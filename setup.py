"""The compiled build by default: the hot path through mypyc where it can be built.

``pip install .`` compiles the modules every transaction runs through to C extensions with
mypyc (the mypy project's compiler for type-annotated Python): the same source, the same
behaviour, less than half the interpreter's instructions per transaction. mypy and the
packages type-checking needs come through build isolation (pyproject.toml's
``[build-system] requires``); a C compiler and the Python headers must be on the machine.

Whatever stops the compiled build (no compiler, no headers, a mypyc error) falls back to the
pure-Python build, which installs everywhere. ``MODBUS_GATEWAY_COMPILE`` decides:

- unset: automatic, compiled when it builds, else pure Python; pure Python for editable
  installs (``pip install -e``), where extensions beside the sources would hide edits;
- ``1``: compiled, and a failure stops the install;
- ``0``: pure Python, without running mypyc.

pip hides this script's output: ``modbus-gateway --version``, the start-up log and the
``modbus_gateway_build_info{build}`` metric say which build runs. docs/deployment-build.md
has the measured install times.
"""

from __future__ import annotations

import enum
import os
import shutil
import sys
import sysconfig

from setuptools import setup
from setuptools.command.build_ext import build_ext

#: The modules a transaction runs through. The rest stays interpreted: it runs once per
#: connection or reload, or it uses what mypyc does not compile (enum flags, ctypes,
#: subclasses of built-in exceptions).
COMPILED_MODULES = [
    "gateway/core/admission.py",
    "gateway/core/ascii.py",
    "gateway/core/crc.py",
    "gateway/core/framing.py",
    "gateway/core/line/__init__.py",
    "gateway/core/line/fair_queue.py",
    "gateway/core/line/flights.py",
    "gateway/core/line/foreign.py",
    "gateway/core/line/health.py",
    "gateway/core/line/late.py",
    "gateway/core/line/machine.py",
    "gateway/core/line/order.py",
    "gateway/core/line/pipelined.py",
    "gateway/core/line/polling.py",
    "gateway/core/line/records.py",
    "gateway/core/line/response_timing.py",
    "gateway/core/line/sharing.py",
    "gateway/core/line/wire.py",
    "gateway/core/mbap.py",
    "gateway/core/outcome.py",
    "gateway/core/pdu.py",
    "gateway/core/reasons.py",
    "gateway/core/routes.py",
    "gateway/core/rtu.py",
    "gateway/core/timing.py",
    "gateway/io/line/bus.py",
    "gateway/io/clock.py",
    "gateway/io/line/notes.py",
    "gateway/io/listeners/rtu_over_tcp.py",
    "gateway/io/listeners/spine.py",
    "gateway/io/links/serial_port.py",
    "gateway/io/line/tally.py",
    "gateway/io/listeners/tcp.py",
    "gateway/metrics.py",
]

#: The commands that build what gets installed (the metadata hooks run none of them).
BUILD_COMMANDS = frozenset(
    {"build", "build_ext", "bdist_wheel", "install", "editable_wheel", "develop"}
)
#: Editable installs: the sources are imported in place, so automatic means interpreted.
EDITABLE_COMMANDS = frozenset({"editable_wheel", "develop"})


class Compile(enum.Enum):
    """What ``MODBUS_GATEWAY_COMPILE`` asks for."""

    AUTOMATIC = ""
    FORCED = "1"
    OFF = "0"


def _asked() -> Compile:
    """The choice from the environment; an unknown value stops the build rather than guess."""
    value = os.environ.get("MODBUS_GATEWAY_COMPILE", "").strip().lower()
    words = {"": Compile.AUTOMATIC, "1": Compile.FORCED, "0": Compile.OFF}
    words |= {
        "true": Compile.FORCED,
        "yes": Compile.FORCED,
        "false": Compile.OFF,
        "no": Compile.OFF,
    }
    if value not in words:
        raise SystemExit(
            f"MODBUS_GATEWAY_COMPILE={value!r}: use 1 (compiled), 0 (pure Python) or unset"
        )
    return words[value]


def _say(message: str) -> None:
    """One line that names the build (seen with ``pip -v`` or ``python setup.py``)."""
    print(f"modbus-gateway build: {message}", file=sys.stderr, flush=True)


def _missing_tool() -> str | None:
    """What the C build surely lacks (no compiler, no headers), or None: worth trying."""
    compiler = (os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(compiler) is None:
        return f"no C compiler ({compiler})"
    if not os.path.isfile(os.path.join(sysconfig.get_paths()["include"], "Python.h")):
        return "no Python headers (Debian: apt-get install python3-dev)"
    return None


def _extensions(commands: frozenset[str]) -> list[object]:
    """The mypyc extensions, or none: pure Python when not asked, editable or not buildable."""
    asked = _asked()
    if asked is Compile.OFF or not commands & BUILD_COMMANDS:
        return []
    if asked is Compile.AUTOMATIC and commands & EDITABLE_COMMANDS:
        _say("editable install, pure Python (MODBUS_GATEWAY_COMPILE=1 compiles it in place)")
        return []
    missing = _missing_tool()
    if asked is Compile.AUTOMATIC and missing:
        _say(f"{missing}, installing pure Python")  # without a minute of mypyc first
        return []
    try:
        from mypyc.build import mypycify

        return list(mypycify(COMPILED_MODULES, opt_level="3", group_name="gateway"))
    except (Exception, SystemExit) as error:  # mypyc exits on a type error
        if asked is Compile.FORCED:
            raise SystemExit(f"MODBUS_GATEWAY_COMPILE=1 but mypyc failed: {error!r}") from error
        _say(f"mypyc failed ({error!r}), installing pure Python")
        return []


class BuildOrFallBack(build_ext):
    """Compiles the extensions; on any failure (no compiler, no headers, a C error) leaves
    them out and marks the wheel pure Python, unless the compiled build was forced."""

    def run(self) -> None:
        if not self.extensions:
            super().run()
            return
        try:
            super().run()
        except Exception as error:
            if _asked() is Compile.FORCED:
                raise
            self._fall_back(error)
        else:
            _say(f"compiled {len(COMPILED_MODULES)} modules with mypyc")

    def _fall_back(self, error: Exception) -> None:
        _say(f"C build failed ({error!r}), installing pure Python")
        for extension in self.extensions:  # what did link must not ship without the rest
            built = self.get_ext_fullpath(extension.name)
            if os.path.exists(built):
                os.remove(built)
        self.extensions = []
        self.distribution.ext_modules = []
        wheel = self.distribution.command_obj.get("bdist_wheel")
        if wheel is not None:
            wheel.root_is_pure = True  # tagged py3-none-any, as a pure build is


setup(
    ext_modules=_extensions(frozenset(sys.argv[1:])),
    cmdclass={"build_ext": BuildOrFallBack},
)
