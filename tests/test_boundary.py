"""The package boundary of DESIGN.md: rt_runtime never imports hil_sim (not even through
importlib); the HIL's commands and its real-time process reach the runtime through entry
points; firmware_models imports nothing of the runtime, and the HIL reports the models' own
error as the runtime's."""

from __future__ import annotations

import ast
import dataclasses
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


def _hil_references(path: Path) -> list[str]:
    """Where a module imports hil_sim or names it as a string a call takes (importlib)."""
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
        found += [f"{path}:{node.lineno}: {n}" for n in names if n.split(".")[0] == "hil_sim"]
    return found


def test_runtime_never_imports_hil_sim() -> None:
    found = [r for p in sorted(ROOT.rglob("*.py")) for r in _hil_references(p)]
    assert found == []


def test_the_check_sees_an_import_through_importlib(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text('import importlib\nm = importlib.import_module("hil_sim.realtime")\n')
    assert len(_hil_references(bad)) == 1
    bad.write_text("from hil_sim import cli\n")
    assert len(_hil_references(bad)) == 1


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


def _runtime_imports(path: Path) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""]
        else:
            continue
        found += [f"{path}:{node.lineno}: {n}" for n in names if n.split(".")[0] == "rt_runtime"]
    return found


def test_firmware_models_import_nothing_of_the_runtime() -> None:
    package = Path(firmware_models.__file__).parent
    assert [r for p in sorted(package.rglob("*.py")) for r in _runtime_imports(p)] == []


def test_the_hil_reports_a_firmware_refusal_as_a_configuration_error() -> None:
    rig = load_rig("scale_model")
    bad = dataclasses.replace(rig, drives=dataclasses.replace(rig.drives, position_gain_1_s=0.0))
    with pytest.raises(FirmwareConfigurationError, match="position_gain_1_s"):
        DriveFirmware(1, bad, "boom")
    with pytest.raises(ConfigurationError, match="position_gain_1_s") as caught:
        HilCore(bad, (0.5, -1.5, -1.0))
    assert isinstance(caught.value.__cause__, FirmwareConfigurationError)
