"""The package boundary of DESIGN.md: rt_runtime never imports hil_sim (not even through
importlib); the HIL's commands and its real-time process reach the runtime through entry
points; firmware_models imports nothing of the runtime, and the HIL reports the models' own
error as the runtime's."""

from __future__ import annotations

import ast
import dataclasses
import json
import os
import subprocess
import sys
import tomllib
from importlib.metadata import entry_points
from pathlib import Path

import pytest

import firmware_models
import rt_runtime
from firmware_models.drive import DriveFirmware
from firmware_models.errors import FirmwareConfigurationError
from hil_sim.sim import HilCore
from rt_runtime.bench import HIL_GROUP, realtime_hil_process
from rt_runtime.cli import BENCH_GROUP, COMMANDS_GROUP, build_parser
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import load_rig

ROOT = Path(rt_runtime.__file__).parent


def _references(path: Path, package: str = "hil_sim") -> list[str]:
    """Where a module imports ``package`` or names it as a string a call takes (importlib)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""]
        elif isinstance(node, ast.Call):
            names = [
                a.value
                for a in node.args
                if isinstance(a, ast.Constant) and isinstance(a.value, str)
            ]
        else:
            continue
        found += [f"{path}:{node.lineno}: {n}" for n in names if n.split(".")[0] == package]
    return found


def test_runtime_never_imports_hil_sim() -> None:
    found = [r for p in sorted(ROOT.rglob("*.py")) for r in _references(p)]
    assert found == []


def test_the_check_sees_an_import_through_importlib(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text('import importlib\nm = importlib.import_module("hil_sim.realtime")\n')
    assert len(_references(bad)) == 1
    bad.write_text("from hil_sim import cli\n")
    assert len(_references(bad)) == 1


def test_hil_commands_and_process_come_through_entry_points() -> None:
    names = {ep.name for ep in entry_points(group=COMMANDS_GROUP)}
    assert {"hil", "demo"} <= names
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert {"hil", "demo"} <= set(sub.choices)
    assert any(ep.name == "realtime" for ep in entry_points(group=HIL_GROUP))
    assert callable(realtime_hil_process().start)
    assert "hil" in {ep.name for ep in entry_points(group=BENCH_GROUP)}
    bench = sub.choices["bench"]
    bench_sub = next(a for a in bench._actions if a.dest == "bench_command")
    assert "hil" in bench_sub.choices


# -- the import contracts (import-linter, pyproject.toml) ------------------------------------------

LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")
FORBIDDEN = [
    c
    for c in tomllib.loads((ROOT.parent / "pyproject.toml").read_text(encoding="utf-8"))["tool"][
        "importlinter"
    ]["contracts"]
    if c["type"] == "forbidden" and all("." not in m for m in c["source_modules"])
]


def _tree(tmp_path: Path, imports: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """A tree of the three packages, each ``__init__`` with the given source, checked by
    import-linter against the project's forbidden-import contracts."""
    for package in ("rt_runtime", "hil_sim", "firmware_models"):
        (tmp_path / package).mkdir(parents=True)
        (tmp_path / package / "__init__.py").write_text(imports.get(package, ""))
    roots = ["rt_runtime", "hil_sim", "firmware_models"]
    lines = ["[tool.importlinter]", f"root_packages = {json.dumps(roots)}"]
    for contract in FORBIDDEN:
        lines += ["[[tool.importlinter.contracts]]"]
        lines += [f"{k} = {json.dumps(v)}" for k, v in contract.items()]
    (tmp_path / "pyproject.toml").write_text("\n".join(lines) + "\n")
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache", "pyproject.toml"],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(tmp_path)},
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.mark.skipif(not LINT_IMPORTS.exists(), reason="import-linter is not installed")
@pytest.mark.parametrize(
    ("package", "source", "broken"),
    [
        ("rt_runtime", "import hil_sim\n", "rt_runtime never imports hil_sim"),
        ("firmware_models", "from rt_runtime import x\n", "firmware_models depends on nothing"),
    ],
)
def test_a_forbidden_import_breaks_its_contract(
    tmp_path: Path, package: str, source: str, broken: str
) -> None:
    assert len(FORBIDDEN) >= 2
    clean = _tree(tmp_path / "clean", {})
    assert clean.returncode == 0, clean.stdout + clean.stderr
    bad = _tree(tmp_path / "bad", {package: source})
    assert bad.returncode != 0, bad.stdout
    assert broken in bad.stdout and "BROKEN" in bad.stdout, bad.stdout


def test_firmware_models_import_nothing_of_the_runtime() -> None:
    package = Path(firmware_models.__file__).parent
    assert [r for p in sorted(package.rglob("*.py")) for r in _references(p, "rt_runtime")] == []


def test_the_hil_reports_a_firmware_refusal_as_a_configuration_error() -> None:
    rig = load_rig("scale_model")
    bad = dataclasses.replace(rig, drives=dataclasses.replace(rig.drives, position_gain_1_s=0.0))
    with pytest.raises(FirmwareConfigurationError, match="position_gain_1_s"):
        DriveFirmware(1, bad, "boom")
    with pytest.raises(ConfigurationError, match="position_gain_1_s") as caught:
        HilCore(bad, (0.5, -1.5, -1.0))
    assert isinstance(caught.value.__cause__, FirmwareConfigurationError)


def test_every_hil_module_outside_the_harness_is_under_the_physics_contract() -> None:
    """DESIGN.md: hil_sim outside harness/ imports only the runtime's physics; the contract
    names its modules one by one, so a new module must join it."""
    contracts = tomllib.loads((ROOT.parent / "pyproject.toml").read_text(encoding="utf-8"))
    physics = next(
        c
        for c in contracts["tool"]["importlinter"]["contracts"]
        if c["name"].startswith("hil_sim outside its harness")
    )
    hil = ROOT.parent / "hil_sim"
    modules = {f"hil_sim.{p.stem}" for p in hil.glob("*.py") if p.stem != "__init__"}
    assert modules == set(physics["source_modules"])
    assert "hil_sim.harness" in physics["forbidden_modules"]
