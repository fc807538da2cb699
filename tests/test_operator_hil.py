"""The operator in the HIL: manual mode by lever, demonstrations recorded as CSV and CAN trace
(the same waypoints from either), ``hil --operator`` and ``hil --teach`` with their JSON keys,
and a taught job refused before anything moves."""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_sim.harness.fouraxis import DemoFiles, run_operator_demo
from rt_runtime import axes
from rt_runtime.cli import main
from rt_runtime.control.controllers import GuardFilter
from rt_runtime.control.guard import LimitGuard, StrokeLimits
from rt_runtime.control.hardware import DriveFeedback
from rt_runtime.control.manual import LeverController
from rt_runtime.rig import Rig, load_rig
from rt_runtime.teach.demos import read_csv, read_trace
from rt_runtime.teach.pipeline import TeachSettings, learn_waypoints

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()


@pytest.fixture(scope="module")
def field() -> Rig:
    return load_rig("field_excavator")


def _run(argv: list[str]) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(argv)
    return code, out.getvalue()


# -- manual mode ----------------------------------------------------------------------------------


def _lever_loop(rig: Rig, lever: np.ndarray, q0: np.ndarray, cycles: int) -> list[np.ndarray]:
    """The controller and the guard alone, the drives following the command exactly."""
    guard = LimitGuard(StrokeLimits.from_rig(rig), 0.002)
    s0 = axes.joint_to_actuator(rig, q0)
    guard.reset(s0)
    gf = GuardFilter(guard)
    c = LeverController(rig, gf, lambda t, q: lever, tick=5)
    c.first()
    fb = DriveFeedback(4)
    fb.fresh = True
    fb.stroke_m[:] = s0
    out = []
    for k in range(cycles):
        cmd, _ = c.update(k * 0.002, 0.002, fb)
        gf.apply(cmd)
        fb.stroke_m[:] = guard.position_m
        out.append(axes.actuator_to_joint(rig, guard.position_m).copy())
    return out


def test_a_held_lever_moves_its_joint_its_way_within_the_limits(field: Rig) -> None:
    q0 = np.radians([20.0, -90.0, -60.0, 0.0])
    lever = np.radians([-30.0, 20.0, 0.0, 50.0])  # axis order: boom down, stick out, swing left
    q = np.array(_lever_loop(field, lever, q0, 600))
    dq = np.diff(q, axis=0) / 0.002
    # Never the wrong way, and at the lever's speed once ramped up.
    assert np.all(dq[:, 0] <= 1e-9) and np.all(dq[:, 1] >= -1e-9) and np.all(dq[:, 3] >= -1e-9)
    np.testing.assert_allclose(dq[-1], lever, atol=1e-5)
    _, _, v, a, _ = axes.joint_limits(field)
    assert np.all(np.abs(dq) <= v * (1 + 1e-6))
    assert np.all(np.abs(np.diff(dq, axis=0)) / 0.002 <= a * 1.02)


def test_a_lever_held_into_a_joint_limit_stops_before_it(field: Rig) -> None:
    q0 = np.radians([60.0, -90.0, -60.0, 0.0])
    lever = np.radians([45.0, 0.0, 0.0, 0.0])  # the boom's limit is 65 deg
    q = np.array(_lever_loop(field, lever, q0, 1500))
    hi = field.q_max_rad[0]
    assert float(np.max(q[:, 0])) <= hi
    assert float(q[-1, 0]) >= hi - math.radians(5.0)  # the stop is conservative, not far
    assert abs(float(q[-1, 0] - q[-2, 0])) < 1e-9  # at rest


# -- recordings ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def demos(field: Rig, tmp_path_factory: pytest.TempPathFactory) -> list[DemoFiles]:
    out = tmp_path_factory.mktemp("demos")
    return [run_operator_demo(field, seed, out) for seed in (0, 1, 3)]


def test_a_demonstration_is_recorded_as_csv_and_trace_with_its_intended_path(
    field: Rig, demos: list[DemoFiles]
) -> None:
    d = demos[0]
    assert d.status == "done", d.fault
    assert d.csv.is_file() and d.trace.is_file() and d.intended.is_file()
    csv, trace = read_csv(field, d.csv), read_trace(field, d.trace)
    # One row per SYNC of manual mode in both: the drives' reports, to the CSV's rounding.
    assert csv.q_rad.shape == trace.q_rad.shape
    assert float(np.max(np.abs(csv.q_rad - trace.q_rad))) < math.radians(1e-5)
    intended = json.loads(d.intended.read_text())
    q_int = np.radians(np.array(intended["q_deg"]))
    # The operator dug his cycle: it reached the dump swing and came back to the start pose.
    assert float(np.max(csv.q_rad[:, 0])) > math.radians(60.0)
    assert float(np.max(np.abs(csv.q_rad[-1] - q_int[-1]))) < math.radians(3.0)
    # The pace differs from one demonstration to the next.
    assert max(x.speed for x in demos) / min(x.speed for x in demos) > 1.3
    assert max(x.duration_s for x in demos) / min(x.duration_s for x in demos) > 1.2


def test_a_trace_written_by_the_hil_operator_and_its_csv_give_the_same_waypoints(
    field: Rig, demos: list[DemoFiles]
) -> None:
    settings = TeachSettings()
    from_csv = learn_waypoints(field, [read_csv(field, d.csv) for d in demos], settings)[3]
    from_trace = learn_waypoints(field, [read_trace(field, d.trace) for d in demos], settings)[3]
    assert from_csv.shape == from_trace.shape and from_csv.shape[0] >= 4
    np.testing.assert_allclose(from_csv, from_trace, atol=math.radians(1e-4))


# -- the commands ----------------------------------------------------------------------------------


def _keys(head: str) -> set[tuple[str, ...]]:
    from test_report_keys import _list_of, _paragraph, contract_keys

    return contract_keys(_list_of(_paragraph(README, head)))


def test_hil_operator_writes_n_demonstrations_and_its_documented_keys(tmp_path: Path) -> None:
    from test_report_keys import missing

    code, out = _run(
        ["hil", "--operator", "--demos", "1", "--seed", "5", "--out", str(tmp_path), "--json"]
    )
    assert code == 0, out[-2000:]
    report = json.loads(out)
    assert missing(report, _keys("`hil --operator --json`")) == []
    assert len(report["demos"]) == 1
    assert Path(report["demos"][0]["csv"]).is_file()
    assert Path(report["demos"][0]["trace"]).is_file()
    code, out = _run(["hil", "--operator", "--out", str(tmp_path), "--json"])
    assert code == 2 and "--demos" in json.loads(out)["error"]


@pytest.fixture(scope="module")
def taught_dir(
    field: Rig, demos: list[DemoFiles], tmp_path_factory: pytest.TempPathFactory
) -> Path:
    out = tmp_path_factory.mktemp("taught")
    code, text = _run(
        ["teach", "--rig", "field_excavator", "--cycles", "2", "--out", str(out), "--demos"]
        + [str(d.csv) for d in demos]
    )
    assert code == 0, text[-2000:]
    return out


def test_hil_teach_runs_the_taught_trench_on_four_axes(taught_dir: Path, tmp_path: Path) -> None:
    from test_report_keys import missing

    trace = tmp_path / "taught.blf"
    code, out = _run(["hil", "--teach", str(taught_dir), "--trace", str(trace), "--json"])
    report = json.loads(out)
    assert code == 0, report
    assert missing(report, _keys("`hil --teach --json`")) == []
    assert report["status"] == "done" and report["cycles_total"] == 2
    print("hil --teach:", json.dumps(report["tracking"]), report["swing"])
    sw = report["swing"]
    assert 0.0 < sw["max_deg"] < 3.0 and sw["overshoot_deg"] >= 0.0
    # Gao's band on every cylinder: the valve drives scale their flow gain to the load and
    # the executor leads each cylinder's oil-column mode (without either the boom is off by
    # 6-10 mm lowering and lifting).
    for axis, fig in report["tracking"].items():
        assert fig["max_mm"] <= 3.0, (axis, fig)
    assert trace.is_file()
    # The trace is the run's: its swing drive (node 4) answered every SYNC.
    rig = load_rig("field_excavator")
    assert read_trace(rig, trace).q_rad.shape[0] > 1000


def test_a_broken_taught_job_is_refused_and_nothing_moves(
    taught_dir: Path, tmp_path: Path
) -> None:
    data: dict[str, Any] = json.loads((taught_dir / "taught.json").read_text())
    seg = data["trench"]["cycles"][0]["segments"][1]
    seg["coefficients"][0][3] += 0.2  # a jump of the swing between two segments
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "taught.json").write_text(json.dumps(data))
    trace = tmp_path / "none.blf"
    code, out = _run(["hil", "--teach", str(bad), "--trace", str(trace), "--json"])
    assert code == 2
    assert "jumps" in json.loads(out)["error"]
    assert not trace.exists()  # refused before the HIL was built: no frame was sent
    code, out = _run(["hil", "--teach", str(tmp_path / "nowhere"), "--json"])
    assert code == 2 and "no taught job" in json.loads(out)["error"]


def test_hil_teach_with_a_fault_on_the_swing_drive_stops(taught_dir: Path) -> None:
    code, out = _run(["hil", "--teach", str(taught_dir), "--inject", "overcurrent:swing:2",
                      "--json"])  # fmt: skip
    report = json.loads(out)
    assert code == 1, report
    assert report["status"] == "fault" and "swing" in report["fault"], report["fault"]
    code, out = _run(["hil", "--teach", str(taught_dir), "--inject", "frame_loss:bus:1:0.1",
                      "--json"])  # fmt: skip
    assert code == 2 and "one drive fault" in json.loads(out)["error"]
