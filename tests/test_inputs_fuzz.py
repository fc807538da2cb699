"""Bad input, by machine: property-based inputs into every entry point (rt_runtime.inputs_fuzz).

Each entry point gets 200 seeded inputs (hypothesis shrinks and prints any failing one); the
regressions below are inputs that once raised a traceback or gave a refusal naming nothing; the
last tests show that the properties fail on a master and a drive that misbehave.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("hypothesis")

from rt_runtime import inputs_fuzz
from rt_runtime.cli import main
from rt_runtime.errors import ConfigurationError, RigProfileError
from rt_runtime.inputs_fuzz import (
    HUGE_INT,
    InputEntry,
    PropertyViolation,
    run_entry,
    runtime_entries,
    toml_text,
)
from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, load_card
from rt_runtime.planning.trench.task import load_task
from rt_runtime.rig import load_rig
from rt_runtime.rig.loader import PROFILE_DIR
from rt_runtime.service.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def _entries() -> list[InputEntry]:
    from hil_sim.harness.inputs import entries

    return runtime_entries() + entries()


@pytest.mark.parametrize("entry", _entries(), ids=lambda e: e.name)
def test_every_entry_point_refuses_bad_input_clearly(entry: InputEntry) -> None:
    r = run_entry(entry, 200, seed=0, raise_failures=True)
    assert r.tracebacks == 0
    assert r.examples >= 200
    assert r.refused > 0  # the inputs reach the refusals, not only the valid path


# -- regressions ---------------------------------------------------------------------------------

_DIGITS = "9" * 5000  # more digits than Python converts to an int by default


def _write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def _rig_doc() -> dict[str, Any]:
    import tomllib

    return tomllib.loads((PROFILE_DIR / "scale_model.toml").read_text())


def test_files_that_are_not_utf8_are_refused_naming_the_file(tmp_path: Path) -> None:
    rig = load_rig("scale_model")
    task = _write(tmp_path, "t.toml", b'length_m = 0.6\n# \xff\n')
    with pytest.raises(ConfigurationError, match=r"task file .*t.toml"):
        load_task(task, rig)
    with pytest.raises(RigProfileError, match=r"rig.toml is not UTF-8"):
        load_rig(_write(tmp_path, "rig.toml", b"\xa9\xb3"))
    with pytest.raises(ConfigurationError, match=r"d.toml: not UTF-8"):
        load_config(_write(tmp_path, "d.toml", b"\xa9\xb3"))


def test_integers_beyond_the_float_range_are_refused_naming_the_key(tmp_path: Path) -> None:
    doc = _rig_doc()
    doc["gravity_m_s2"] = 10**400
    with pytest.raises(RigProfileError, match=r"gravity_m_s2: must be a finite number"):
        load_rig(_write(tmp_path, "rig.toml", toml_text(doc).encode()))
    cfg = (
        '[bus]\ninterface = "virtual"\nchannel = "x"\n[rig]\nprofile = "scale_model"\n'
        '[paths]\nstate_dir = "s"\nsocket = "r/c.sock"\n[loop]\nperiod_s = 1' + "0" * 400
    )
    with pytest.raises(ConfigurationError, match=r"loop.period_s: must be finite"):
        load_config(_write(tmp_path, "d.toml", cfg.encode()))


def test_integers_of_more_digits_than_python_converts_are_refused(tmp_path: Path) -> None:
    doc = _rig_doc()
    doc["gravity_m_s2"] = HUGE_INT
    text = toml_text(doc).replace(f'"{HUGE_INT}"', _DIGITS)
    with pytest.raises(RigProfileError, match=r"not valid TOML.*digits"):
        load_rig(_write(tmp_path, "rig.toml", text.encode()))
    with pytest.raises(ConfigurationError, match=r"not valid TOML.*digits"):
        load_config(_write(tmp_path, "d.toml", f"[loop]\nperiod_s = {_DIGITS}\n".encode()))
    with pytest.raises(ConfigurationError, match=r"cannot read.*digits"):
        load_task(_write(tmp_path, "t.toml", f"length_m = {_DIGITS}\n".encode()), load_rig())
    with pytest.raises(ConfigurationError, match=r"not valid JSON.*digits"):
        load_card(_write(tmp_path, "c.json", f'{{"format": {_DIGITS}}}'.encode()))


def test_a_bucket_point_refusal_names_the_profile_file(tmp_path: Path) -> None:
    doc = _rig_doc()
    doc["bucket"]["profile_m"][2] = [0.1, False]
    path = _write(tmp_path, "rig.toml", toml_text(doc).encode())
    with pytest.raises(RigProfileError, match=r"rig.toml: bucket.profile_m\[2\].point\[1\]"):
        load_rig(path)


def _card(tmp_path: Path, **changes: Any) -> Path:
    raw = json.loads((Path(DEFAULT_MODEL_DIR) / "pinn_downward.json").read_text())
    for key, value in changes.items():
        node = raw
        *parents, last = key.split(".")
        for k in parents:
            node = node[k]
        node[last] = value
    return _write(tmp_path, "card.json", json.dumps(raw).encode())


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        ("domain.max", [[1.0]] * 7, "domain.max must be 7 finite numbers"),
        ("domain.min", [None] * 7, "domain.min must be 7 finite numbers"),
        ("domain.max", [float("inf")] * 7, "domain.max must be 7 finite numbers"),
        ("dig_type", "sideways", "dig_type must be one of downward, backward"),
        ("rig", 5, "rig must be a non-empty string"),
        ("model_sha256", None, "model_sha256 must be a non-empty string"),
    ],
)
def test_a_model_card_refusal_names_the_key(
    tmp_path: Path, key: str, value: Any, named: str
) -> None:
    with pytest.raises(ConfigurationError, match=named):
        load_card(_card(tmp_path, **{key: value}))


def test_a_library_entry_refusal_names_the_key(tmp_path: Path) -> None:
    from rt_runtime.planning.pinn import _Library

    for key, value, named in (
        ("library.k", [2], "library k must be an integer"),
        ("library.trigger_bulge_scale", "x", "library trigger_bulge_scale must be a finite"),
        ("library", [1], "library must be an object"),
        ("library.name", None, "library: name must be a non-empty string"),
    ):
        with pytest.raises(ConfigurationError, match=named):
            _Library(load_card(_card(tmp_path, **{key: value})))


# -- the properties can fail ---------------------------------------------------------------------


def _entry(name: str) -> InputEntry:
    return next(e for e in _entries() if e.name == name)


def test_a_master_that_sends_a_setpoint_from_its_receive_path_fails(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from rt_runtime.canbus.cyclic import CyclicExchange

    original = CyclicExchange.read_feedback

    def leaky(self: CyclicExchange, now_s: float, timeout_s: float) -> Any:
        fb = original(self, now_s, timeout_s)
        self.tx(self._rpdo1[0])
        return fb

    monkeypatch.setattr(CyclicExchange, "read_feedback", leaky)
    with pytest.raises(PropertyViolation, match=r"only quick stop may go out"):
        run_entry(_entry("master_frames"), 20, seed=0, raise_failures=True)


def test_a_drive_that_applies_a_short_rpdo_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    from firmware_models.drive import DriveFirmware

    original = DriveFirmware._on_rpdo

    def padded(self: DriveFirmware, data: bytes, now_s: float, pdo: Any) -> Any:
        return original(self, data.ljust(pdo.codec.size, b"\x00"), now_s, pdo)

    monkeypatch.setattr(DriveFirmware, "_on_rpdo", padded)
    with pytest.raises(PropertyViolation, match=r"a refused frame"):
        run_entry(_entry("drive_frames"), 500, seed=0, raise_failures=True)


def test_a_refusal_that_names_nothing_fails() -> None:
    with pytest.raises(PropertyViolation, match=r"names none of"):
        inputs_fuzz._names("something went wrong", ("depth_m",))


# -- the benchmark -------------------------------------------------------------------------------


def _readme_keys() -> set[tuple[str, ...]]:
    from test_report_keys import _list_of, _paragraph, contract_keys

    readme = (ROOT / "README.md").read_text()
    return contract_keys(_list_of(_paragraph(readme, "`bench inputs --json`")))


def test_bench_inputs_json_holds_every_documented_key() -> None:
    from test_report_keys import missing

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["bench", "inputs", "--examples", "5", "--seed", "3", "--json"])
    report = json.loads(out.getvalue())
    assert code == 0, report
    keys = _readme_keys()
    assert ("entries", "tracebacks") in keys
    assert missing(report, keys) == []
    names = [e["name"] for e in report["entries"]]
    assert names[: len(runtime_entries())] == [e.name for e in runtime_entries()]
    assert report["tracebacks"] == 0 and report["examples_per_entry"] == 5


def test_bench_inputs_without_hypothesis_says_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "hypothesis", None)
    monkeypatch.delitem(sys.modules, "rt_runtime.inputs_fuzz")
    assert main(["bench", "inputs", "--examples", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install hypothesis" in err[0]

