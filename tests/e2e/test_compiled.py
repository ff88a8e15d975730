"""The compiled build, the default where a C compiler exists (see setup.py): built from this
checkout with ``MODBUS_GATEWAY_COMPILE`` unset, it says it is compiled, every module of the
list is an extension, and it passes the line's own tests and real exchanges with independent
masters. A failed C build falls back to pure Python (and fails when forced); an editable
install stays pure Python unless forced.

mypyc compiles the same source, but a compiled class is stricter than a Python one (a
subclass defined in interpreted code, an attribute of another type than declared): what
differs shows here, not in the field.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path
from typing import NamedTuple

import pytest

from tests.helpers import environment_with_our_dependencies

#: Building takes mypyc a minute or more on a busy machine, the tests several.
pytestmark = [pytest.mark.compiled, pytest.mark.timeout(1800)]

ROOT = Path(__file__).resolve().parents[2]

#: Run again on the compiled build: the core with literal times and its state machines,
#: every framing's codec, and the Modbus TCP, RTU-over-TCP and serial paths end to end
#: with pymodbus, mbpoll and libmodbus as the masters.
AGAIN = [
    "tests/unit",
    "tests/property",
    "tests/integration/test_clock.py",
    "tests/integration/test_gateway.py",
    "tests/integration/test_independent_peers.py",
    "tests/integration/test_line_policies.py",
    "tests/integration/test_rtu_over_tcp_listener.py",
    "tests/integration/test_serial_port.py",
    "tests/integration/test_tcp_pipelining.py",
]


def compiled_modules() -> list[str]:
    """``COMPILED_MODULES`` from setup.py, as module names."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
            isinstance(target, ast.Name) and target.id == "COMPILED_MODULES"
            for target in node.targets
        ):
            paths: list[str] = ast.literal_eval(node.value)
            return [
                path.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
                for path in paths
            ]
    raise AssertionError("setup.py has no COMPILED_MODULES")


def why_it_cannot_build() -> str | None:
    """What this machine lacks to build the compiled gateway, or None."""
    compiler = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(compiler) is None:
        return f"no C compiler ({compiler})"
    if not (Path(sysconfig.get_paths()["include"]) / "Python.h").is_file():
        return "no Python headers (apt-get install python3-dev)"
    if importlib.util.find_spec("mypyc") is None:
        return "mypy (mypyc) is not installed"
    return None


class CompiledInstall(NamedTuple):
    """A fresh venv with the compiled wheel installed, and a copy of the tests to run."""

    python: Path
    env_dir: Path
    tests_tree: Path


SKIP = shutil.ignore_patterns("__pycache__", "*.so", ".hypothesis", "build")


def needs_a_build() -> None:
    """Skip (fail under CI) where the compiled build cannot be made."""
    missing = why_it_cannot_build()
    if missing is not None:
        if os.environ.get("CI"):
            pytest.fail(f"CI must test the compiled build: {missing}")
        pytest.skip(missing)


def source_copy(where: Path) -> Path:
    """What an sdist holds: the package and the build files."""
    shutil.copytree(ROOT / "gateway", where / "gateway", ignore=SKIP)
    for name in ("setup.py", "pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, where / name)
    return where


def build_wheel(source: Path, out: Path, **env: str) -> subprocess.CompletedProcess[str]:
    """``pip wheel`` with ``MODBUS_GATEWAY_COMPILE`` unset unless given (the default build),
    against this environment's mypy (build isolation would download it)."""
    base = {k: v for k, v in os.environ.items() if k != "MODBUS_GATEWAY_COMPILE"}
    return subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-v",
         "-w", str(out), str(source)],
        env=base | env, capture_output=True, text=True, timeout=900, check=False,
    )  # fmt: skip


@pytest.fixture(scope="module")
def compiled(tmp_path_factory: pytest.TempPathFactory) -> CompiledInstall:
    """The default install, from a copy of this checkout, in a fresh venv: compiled."""
    needs_a_build()
    source = source_copy(tmp_path_factory.mktemp("source"))
    out = tmp_path_factory.mktemp("wheel")
    built = build_wheel(source, out)
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-4000:]
    assert "modbus-gateway build: compiled" in built.stderr + built.stdout
    (wheel,) = out.glob("modbus_gateway-*.whl")
    assert not wheel.name.endswith("-none-any.whl"), f"not a compiled wheel: {wheel.name}"
    env_dir = tmp_path_factory.mktemp("venv")
    python = environment_with_our_dependencies(env_dir, wheel)
    # The tests with the sources beside them (the layering test reads them), imported from
    # nowhere but the venv: PYTHONSAFEPATH keeps the working directory off sys.path.
    tests_tree = tmp_path_factory.mktemp("tree")
    for name in ("tests", "conf", "docs", "gateway"):
        shutil.copytree(ROOT / name, tests_tree / name, ignore=SKIP)
    shutil.copytree(ROOT / "bench", tests_tree / BENCH_PATH / "bench", ignore=SKIP)
    shutil.copy(ROOT / "pyproject.toml", tests_tree / "pyproject.toml")
    return CompiledInstall(python, env_dir, tests_tree)


#: Where the copy of ``bench`` goes (on PYTHONPATH, alone: ``gateway`` must come from the venv).
BENCH_PATH = "importable"


def from_the_venv(install: CompiledInstall) -> dict[str, str]:
    """An environment in which ``gateway`` is the venv's, in subprocesses too."""
    paths = str(install.tests_tree / BENCH_PATH)
    return {**os.environ, "PYTHONSAFEPATH": "1", "PYTHONPATH": paths}


def test_every_listed_module_is_compiled_and_says_so(compiled: CompiledInstall) -> None:
    modules = compiled_modules()
    assert "gateway.core.line" in modules and "gateway.io.listeners.tcp" in modules
    probe = (
        "import importlib, sys, gateway\n"
        "for name in sys.argv[1:]:\n"
        "    print(name, importlib.import_module(name).__file__)\n"
        "print('build', gateway.build())\n"
    )
    found = subprocess.run(
        [compiled.python, "-c", probe, *modules],
        cwd=compiled.tests_tree, env=from_the_venv(compiled),
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout.splitlines()  # fmt: skip
    files = dict(line.split(" ", 1) for line in found)
    assert files.pop("build") == "compiled"
    for name, file in files.items():
        assert Path(file).is_relative_to(compiled.env_dir), (name, file)
        assert file.endswith(".so"), f"{name} is interpreted: {file}"
    command = compiled.env_dir / "bin" / "modbus-gateway"
    version = subprocess.run(
        [command, "--version"], cwd=compiled.tests_tree, env=from_the_venv(compiled),
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout.strip()  # fmt: skip
    assert version.endswith("(compiled)"), version


def test_the_compiled_build_passes_the_line_tests(compiled: CompiledInstall) -> None:
    """The same tests, on the compiled modules (the gateways they start included)."""
    # `-m ''`: every tier of these tests, the slow stateful machines included.
    run_them = (
        "import sys, gateway, pytest\n"
        "assert gateway.build() == 'compiled', gateway.__file__\n"
        "sys.exit(pytest.main(sys.argv[1:]))\n"
    )
    done = subprocess.run(
        [compiled.python, "-c", run_them, "-q", "-p", "no:cacheprovider", "-x", "-m", "", *AGAIN],
        cwd=compiled.tests_tree, env={**from_the_venv(compiled), "LINE_MACHINE_EXAMPLES": "50"},
        capture_output=True, text=True, timeout=900, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-2000:]
    assert " passed" in done.stdout.splitlines()[-1], done.stdout[-2000:]


def test_a_failed_c_build_installs_pure_python_unless_forced(tmp_path: Path) -> None:
    """No working compiler (``CC=false``): the default build still installs, pure Python;
    ``MODBUS_GATEWAY_COMPILE=1`` stops with the error instead."""
    needs_a_build()
    source = source_copy(tmp_path / "source")
    fell_back = build_wheel(source, tmp_path / "auto", CC="false")
    assert fell_back.returncode == 0, fell_back.stdout[-2000:] + fell_back.stderr[-4000:]
    assert "installing pure Python" in fell_back.stderr + fell_back.stdout
    (wheel,) = (tmp_path / "auto").glob("modbus_gateway-*.whl")
    assert wheel.name.endswith("-py3-none-any.whl"), wheel.name
    with zipfile.ZipFile(wheel) as archive:
        assert not [name for name in archive.namelist() if name.endswith(".so")]
    forced = build_wheel(source, tmp_path / "forced", CC="false", MODBUS_GATEWAY_COMPILE="1")
    assert forced.returncode != 0
    assert not list((tmp_path / "forced").glob("*.whl"))


def test_without_a_compiler_the_default_build_is_pure_python_without_mypyc(
    tmp_path: Path,
) -> None:
    """No compiler at all: pure Python at once, without a minute of mypyc first."""
    source = source_copy(tmp_path / "source")
    built = build_wheel(source, tmp_path / "out", CC="/nonexistent/cc")
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-4000:]
    assert "no C compiler (/nonexistent/cc), installing pure Python" in built.stderr + built.stdout
    (wheel,) = (tmp_path / "out").glob("modbus_gateway-*.whl")
    assert wheel.name.endswith("-py3-none-any.whl"), wheel.name
    assert not (source / "build" / "__native_gateway.c").exists()  # mypyc did not run


def test_an_editable_install_stays_pure_python_unless_forced(tmp_path: Path) -> None:
    """Extensions beside the sources would hide every edit to them: automatic means
    interpreted for ``pip install -e`` (no mypyc run, nothing written into the tree)."""
    source = source_copy(tmp_path / "source")
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=False)
    python = env_dir / "bin" / "python"
    base = {k: v for k, v in os.environ.items() if k != "MODBUS_GATEWAY_COMPILE"}
    build = "import sys; from setuptools import build_meta; build_meta.build_editable(sys.argv[1])"
    subprocess.run(
        [sys.executable, "-c", build, str(tmp_path)], cwd=source, env=base,
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    (editable,) = tmp_path.glob("modbus_gateway-*.whl")
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
         "--no-index", "-q", str(editable)],
        capture_output=True, text=True, timeout=300, check=True,
    )  # fmt: skip
    assert not list(source.rglob("*.so"))
    alone = {k: v for k, v in base.items() if k != "PYTHONPATH"} | {"PYTHONSAFEPATH": "1"}
    said = subprocess.run(
        [python, "-c", "import gateway; print(gateway.__file__, gateway.build())"],
        cwd=tmp_path, env=alone,
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout.split()  # fmt: skip
    assert said == [str(source / "gateway" / "__init__.py"), "interpreted"]
