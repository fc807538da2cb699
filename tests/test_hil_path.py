"""Prescribed joint paths on the executor against the lockstep HIL (issue 8 item 3).

Gao Table 2's key points, interpolated with the smoothest of Gao's order patterns and 3 s
segments, run on the hydraulic ``test_bench`` through the executor (CONNECT from a start pose
away from the path, then phase PATH) and the master against the emulated valve drives and arm.
Checked: the job completes at rest, the commanded strokes pass exactly through every key point's
cylinder stroke at its key time (the guard passes the verified path through), tracking on the
plant's truth is within Gao's +-3 mm, feed-forward off tracks worse, and a path the rig cannot
follow is refused before any frame is sent.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import hil_sim.harness.scenario as scenario_mod
from hil_sim.harness.lockstep import LockstepHil
from hil_sim.harness.reports import HilReport
from hil_sim.harness.scenario import (
    GAO_TABLE2_JOINTS_DEG,
    NO_RT,
    PathScenario,
    key_point_path,
    run_path_scenario,
)
from rt_runtime import actuation
from rt_runtime.actuation import AXES
from rt_runtime.canbus import CanMaster
from rt_runtime.control import FixedRateLoop, LoopConfig
from rt_runtime.control.executor import Executor, executor_telemetry
from rt_runtime.control.planner_worker import PathJob, PathLink, PathPlan, PolynomialMotion
from rt_runtime.errors import JointLimitError, PlanningError
from rt_runtime.rig import Rig, load_rig
from rt_runtime.trajectory.mixed_order import interpolate

PERIOD_S = 0.002
#: Start pose away from the path's first key point (34.83, -40.32, -56.16): a real CONNECT move.
START_DEG = (30.0, -45.0, -52.0)
#: Three of Gao's key points: a reduced path.
REDUCED_GAO = tuple((float(b), float(s), float(k)) for b, s, k in GAO_TABLE2_JOINTS_DEG[2:5])


@pytest.fixture(scope="module")
def bench() -> Rig:
    return load_rig("test_bench")


@pytest.fixture(scope="module")
def gao_ff_on() -> HilReport:
    return run_path_scenario(PathScenario(path="gao", rig="test_bench", start_deg=START_DEG)).report


@pytest.fixture(scope="module")
def gao_ff_off() -> HilReport:
    return run_path_scenario(PathScenario(path="gao", rig="test_bench", feedforward=False)).report


def test_gao_path_completes_and_passes_every_key_point(gao_ff_on: HilReport, bench: Rig) -> None:
    r = gao_ff_on
    assert r.status == "done", r.fault
    assert r.overruns == 0
    assert r.emcys == ()
    path = r.path
    assert path is not None
    assert path.name == "gao"
    assert path.orders == "3-4-5-4-3"  # the smoothest by interp's rule on Table 2
    assert path.scaled_from == ""
    np.testing.assert_allclose(path.knots_s, np.arange(6) * 3.0)
    np.testing.assert_allclose(path.key_points_deg, GAO_TABLE2_JOINTS_DEG, atol=1e-9)
    key_strokes = actuation.joint_to_stroke(bench, np.radians(GAO_TABLE2_JOINTS_DEG))
    np.testing.assert_allclose(np.array(path.key_strokes_mm) * 1e-3, key_strokes, atol=1e-12)
    # Commanded stroke at each key time = the key point's stroke (guard passthrough, ~1e-16 m).
    errors = path.cmd_at_key_error_um
    assert errors is not None and len(errors) == 6
    assert max(errors) < 1e-3, errors  # < 1 nm
    # The path streamed whole (15 s at 2 ms), after a connect move from the start pose.
    assert r.tracking_path is not None and r.tracking_path.cycles == 7500
    assert r.cycles > 7500 + 100


def test_gao_path_tracks_within_3_mm_on_truth(gao_ff_on: HilReport) -> None:
    goal = gao_ff_on.goal.max_mm
    assert goal == 3.0
    assert gao_ff_on.tracking_path is not None
    for block in (gao_ff_on.tracking, gao_ff_on.tracking_path.tracking):
        for axis in AXES:
            fig = block[axis]
            assert 0.0 < fig.max_mm <= goal, (axis, fig)
            assert fig.reported.max_mm <= goal, (axis, fig)
    # The tip follows within a few mm as well (1.9 m of arm).
    assert gao_ff_on.tracking_path.tip_error_max_mm < 10.0


def test_feedforward_off_tracks_worse(gao_ff_on: HilReport, gao_ff_off: HilReport) -> None:
    assert gao_ff_off.status == "done", gao_ff_off.fault
    assert gao_ff_on.tracking_path is not None and gao_ff_off.tracking_path is not None
    on = gao_ff_on.tracking_path.tracking
    off = gao_ff_off.tracking_path.tracking
    for axis in AXES:
        assert off[axis].max_mm > 2.0 * on[axis].max_mm, (axis, on[axis], off[axis])
        assert off[axis].rms_mm > 2.0 * on[axis].rms_mm, (axis, on[axis], off[axis])


def test_a_drive_commissioned_for_the_real_valves_tracks_on_the_ideal_hil(
    gao_ff_on: HilReport, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The master writes the profile's overlap compensation (0x2100) whatever HIL it boots, as
    the daemon does; the ideal HIL's valves then have exactly the overlap their drives
    compensate, so the path tracks as on uncompensated ideal valves (a compensated valve
    without overlap would throw its spool across zero flow at every sign change)."""
    monkeypatch.setattr(scenario_mod, "_uncompensated", lambda rig: rig)
    sc = PathScenario(path="joints", joints_deg=REDUCED_GAO, rig="test_bench")
    compensated = run_path_scenario(sc).report
    monkeypatch.undo()
    plain = run_path_scenario(sc).report
    assert compensated.status == plain.status == "done"
    for axis, fig in compensated.tracking.items():
        assert fig.max_mm <= max(0.3, 2.0 * plain.tracking[axis].max_mm), (axis, fig)
        assert fig.max_mm <= 1.5 * gao_ff_on.tracking[axis].max_mm + 0.1, (axis, fig)


def test_unreachable_path_is_refused_before_the_hil_starts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    opened: list[Any] = []
    monkeypatch.setattr(scenario_mod, "_open_hil", lambda *a: opened.append(a))
    beyond = ((34.83, -40.32, -56.16), (40.0, -60.0, -58.0), (70.0, -80.0, -60.0))
    with pytest.raises(JointLimitError, match="boom"):
        run_path_scenario(PathScenario(path="joints", joints_deg=beyond))
    with pytest.raises(PlanningError, match="exceeds the rig's limit"):
        run_path_scenario(PathScenario(path="gao", durations_s=(0.5,) * 5))
    assert opened == []


def test_executor_refuses_an_unreachable_path_before_any_frame(bench: Rig) -> None:
    q_key = np.radians(((34.83, -40.32, -56.16), (40.0, -60.0, -58.0), (70.0, -80.0, -60.0)))
    traj = interpolate(np.array([0.0, 3.0, 6.0]), q_key, "4-4")
    q0 = q_key[0]
    with LockstepHil(bench, q0, None, period_s=PERIOD_S, vcu=False, keep_frames=True) as hil:
        master = CanMaster(hil.master_bus, bench, period_s=PERIOD_S, react_to_faults=False)
        loop = FixedRateLoop(
            hil.clock, LoopConfig(period_s=PERIOD_S, rt=NO_RT), executor_telemetry(100)
        )
        booted = list(hil.core.frames)  # the drives' own boot-up messages (0x701..0x703)
        assert all(0x701 <= cob <= 0x703 for cob, _ in booted), booted
        with pytest.raises(JointLimitError, match="boom"):
            Executor.for_path(master, bench, loop, PolynomialMotion(traj))
        assert list(hil.core.frames) == booted  # the master sent nothing


def test_path_job_link_and_motion(bench: Rig) -> None:
    kp = key_point_path(bench, GAO_TABLE2_JOINTS_DEG)
    motion = kp.job.motions[0]
    assert motion.duration_s == pytest.approx(15.0)
    traj = motion.path  # type: ignore[attr-defined]
    for t in (0.0, 1.234, 3.0, 7.77, 12.0, 14.999, 15.0):
        q, qd, qdd = motion.sample(t)
        np.testing.assert_allclose(q, traj.sample(t), atol=1e-12)
        np.testing.assert_allclose(qd, traj.sample(t, 1), atol=1e-12)
        np.testing.assert_allclose(qdd, traj.sample(t, 2), atol=1e-12)
    link = PathLink(kp.job)
    link.request_plan(None)
    assert link.poll() is None  # answered between cycles, in service()
    link.service()
    reply = link.poll()
    assert isinstance(reply, PathPlan) and reply.motions == kp.job.motions
    link.request_plan(None)
    link.service()
    again = link.poll()
    assert isinstance(again, PathPlan) and again.motions == ()
    # A motion that does not end at rest is refused.
    half = interpolate(np.array([0.0, 3.0]), np.radians(GAO_TABLE2_JOINTS_DEG[:2]), "5")

    class Cut:
        duration_s = 1.5

        def sample(self, t_s: float) -> tuple[Any, Any, Any]:
            return half.sample(t_s), half.sample(t_s, 1), half.sample(t_s, 2)

    with pytest.raises(PlanningError, match="does not end at rest"):
        PathJob((Cut(),)).check(bench)
