"""Blended dig cycles (issue 26, part 3): one minimum time-jerk trajectory through a cycle's
corners, dumping in the rig's spoil zone, its rest-to-rest fallback, its setpoint tables and
its keys.

The bucket's clearance of the material on A-D is checked independently in
``tests/test_transitions.py``; the executor's stops during a blended cycle in
``tests/test_executor.py``. Here: the limits by the generator's exact check and on a 1 kHz
resample, the corners and rest at both ends to 1e-9, the dump within the zone and beside the
trench, the fallback when no blend is clear, the setpoint tables' phases and the guard's
pass-through, the session state's round trip, and the report's keys.
"""

from __future__ import annotations

import copy
import json
import math
from collections import deque
from typing import Any

import numpy as np
import pytest

from rt_runtime.control.guard import GuardState, LimitGuard, StrokeLimits
from rt_runtime.control.job import ExecStatus, _Planning
from rt_runtime.control.planner_worker import PlannerError
from rt_runtime.control.setpoints import Phase, sample_cycle
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning.trench import (
    TRANSITION_PENETRATION_M,
    Cycle,
    TransitionKind,
    TrenchPlan,
    TrenchPlanner,
    TrenchSession,
    load_task,
)
from rt_runtime.planning.trench.cycles import CyclesMixin, home_pose
from rt_runtime.rig import load_rig, parse_rig
from rt_runtime.rig.loader import PROFILE_DIR
from rt_runtime.trajectory.timejerk import reversal_bound_s

RIG = load_rig("scale_model")
PERIOD_S = 0.002


@pytest.fixture(scope="module")
def planner() -> TrenchPlanner:
    return TrenchPlanner(RIG)


@pytest.fixture(scope="module")
def plan_a(planner: TrenchPlanner) -> TrenchPlan:
    return planner.plan(load_task("A", RIG))


def _cycles(plan: TrenchPlan) -> list[Cycle]:
    return [s for s in plan.steps if isinstance(s, Cycle)]


def test_a_blended_cycle_holds_every_limit_and_passes_its_corners(plan_a: TrenchPlan) -> None:
    cycles = [c for c in _cycles(plan_a) if c.blended]
    assert len(cycles) >= 4
    limits = (RIG.qd_max_rad_s, RIG.qdd_max_rad_s2, RIG.qddd_max_rad_s3)
    for c in cycles:
        traj = c.trajectory(RIG)
        case = f"cycle {c.kinds}"
        exact = traj.limit_check()
        assert exact.exact and exact.within_limits, case
        # The jerk the limit guard keeps too, and the joint ranges.
        assert np.all(exact.jerk_ratio <= 1.0 + 1e-9), case
        assert np.all(exact.position_low_rad >= RIG.q_min_rad - 1e-9), case
        assert np.all(exact.position_high_rad <= RIG.q_max_rad + 1e-9), case
        assert traj.sampled_limit_check(1000.0).within_limits, case
        # Through every corner at its time, at rest at both ends only.
        b = c.blend_from
        waypoints = np.asarray(c.waypoints_rad[b:])
        np.testing.assert_allclose(traj.sample(traj.waypoint_times_s), waypoints, atol=1e-9)
        lead_s = sum(m.duration_s for m in c.moves)
        assert c.waypoint_times_s[:b] == pytest.approx(
            np.cumsum([0.0, *(m.duration_s for m in c.moves)])[:b], abs=1e-12
        )
        assert np.asarray(traj.waypoint_times_s) + lead_s == pytest.approx(
            c.waypoint_times_s[b:], abs=1e-12
        )
        for t in (0.0, traj.duration_s):
            assert np.abs(traj.sample(t, 1)).max() <= 1e-9
            assert np.abs(traj.sample(t, 2)).max() <= 1e-9
        speed = np.abs(traj.sample(np.asarray(traj.waypoint_times_s[1:-1]), 1)).max(axis=1)
        assert (speed > 1e-3).all(), case  # no stop at the corners
        assert c.duration_s == pytest.approx(lead_s + traj.duration_s, rel=1e-12)
        every = np.asarray(c.waypoints_rad)
        assert c.bound_s == pytest.approx(float(reversal_bound_s(every, *limits)))
        assert 0.0 <= c.penetration_m <= TRANSITION_PENETRATION_M
        assert len(c.kinds) == len(every) - 1 and c.kinds[-1] is TransitionKind.ENTER
        assert all(k is TransitionKind.LIFT_OUT for k in c.kinds[:b])


def _clear_cycles_within_bound(planner: TrenchPlanner, task: Any, most: float) -> list[Cycle]:
    """``task``'s cycles, each asserted clear of the material and at most ``most`` times its
    bound (each joint stopping only where it reverses)."""
    cycles = _cycles(planner.plan(task))
    assert cycles, task.name
    ratios = [c.duration_s / c.bound_s for c in cycles]
    assert max(ratios) <= most, (task.name, [round(r, 3) for r in ratios])
    assert all(0.0 <= c.penetration_m <= TRANSITION_PENETRATION_M for c in cycles), task.name
    return cycles


def test_a_blend_made_clear_only_without_shape_knots_does_not_end_the_search(
    planner: TrenchPlanner,
) -> None:
    """Two seeded random tasks (the bench's suite, seed 7) where the first corner set's blend
    with shape knots goes into the material and the one without is 1.32 and 1.28 times its
    bound: the planner goes on to the next corner sets and takes a clear blend with shape knots.
    Every cycle of both stays within issue 26's worst case, 1.2 times its bound."""
    from rt_runtime.bench import random_tasks

    tasks = {t.name: t for t in random_tasks(RIG, 32, 7)}
    for name in ("random-7-17", "random-7-31"):
        _clear_cycles_within_bound(planner, tasks[name], 1.2)


def test_a_slow_or_refused_search_goes_on_with_more_shape_knots_and_a_lift_split_on_its_vertical(
    planner: TrenchPlanner,
) -> None:
    """Seeded random tasks (the bench's suite, seed 7) where every corner set's blend with
    shape knots in its long intervals went into the material: random-7-15's and random-7-26's
    cycles took a clear one without knots at 1.30 times their bound, random-7-111's a straight
    lift and a blend from its top at 1.26 times. Shape knots in every interval (15, 26) and the
    lift's vertical split into two rises as corners (111) give clear blends within 1.2 times."""
    from rt_runtime.bench import random_tasks

    tasks = {t.name: t for t in random_tasks(RIG, 112, 7)}
    for name in ("random-7-15", "random-7-26", "random-7-111"):
        cycles = _clear_cycles_within_bound(planner, tasks[name], 1.2)
        assert all(c.blended for c in cycles), name


def test_every_dump_lies_in_the_spoil_zone_beside_the_trench(
    planner: TrenchPlanner, plan_a: TrenchPlan
) -> None:
    zone = RIG.trench.spoil
    task = plan_a.task
    near_edge = task.start_x_m - task.length_m
    dumps = 0
    for c in _cycles(plan_a):
        for q, kind in zip(c.waypoints_rad[1:], c.kinds, strict=True):
            if kind is not TransitionKind.DUMP:
                continue
            dumps += 1
            x, y, z = planner.arm.tip(np.asarray(q))
            assert zone.x_m[0] - 1e-9 <= x <= zone.x_m[1] + 1e-9
            assert x + c.machine_x_m <= near_edge - zone.edge_gap_m + 1e-9
            h = y - RIG.ground_y_m
            assert zone.height_m[0] - 1e-9 <= h <= zone.height_m[1] + 1e-9
            assert zone.attitude_rad[0] - 1e-9 <= z <= zone.attitude_rad[1] + 1e-9
    assert dumps >= len(plan_a.buckets) - 1 >= 3  # a dump after every dig but the last
    # The home pose (where a task starts) is a point of the zone too.
    x, y, z = planner.arm.tip(np.asarray(planner.home_pose_rad))
    assert zone.x_m[0] - 1e-9 <= x <= zone.x_m[1] + 1e-9
    assert zone.height_m[0] - 1e-9 <= y - RIG.ground_y_m <= zone.height_m[1] + 1e-9
    assert zone.attitude_rad[0] - 1e-9 <= z <= zone.attitude_rad[1] + 1e-9


def test_an_unreachable_spoil_zone_is_refused() -> None:
    import tomllib

    doc = tomllib.loads((PROFILE_DIR / "scale_model.toml").read_text())
    doc = copy.deepcopy(doc)
    doc["trench"]["spoil"]["x_m"] = [-0.20, -0.10]  # behind the boom pin
    rig = parse_rig(doc)
    with pytest.raises(ConfigurationError, match=r"trench\.spoil: the arm reaches no point"):
        home_pose(rig, TrenchPlanner(RIG).arm)


def test_a_cycle_that_cannot_be_blended_falls_back_to_checked_rest_to_rest_moves(
    planner: TrenchPlanner, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refuse(self: Any, *args: Any) -> tuple[None, float, int]:
        return None, math.inf, 1

    monkeypatch.setattr(CyclesMixin, "_clear_trajectory", refuse)
    s = planner.start(load_task("A", RIG))
    dig = s.next_dig()
    assert dig is not None
    s.record(dig, dig.tip_path_m)
    n0 = len(s.steps)
    s.next_dig()
    cycle = s.steps[n0]
    assert isinstance(cycle, Cycle) and not cycle.blended and cycle.after_dig
    labels = [m.kind.label for m in cycle.moves]
    assert labels[0] == "lift_out" and labels[-2:] == ["approach", "enter"] and "dump" in labels
    assert all(m.penetration_m <= TRANSITION_PENETRATION_M for m in cycle.moves)
    assert cycle.penetration_m == max(m.penetration_m for m in cycle.moves)
    assert cycle.duration_s == pytest.approx(sum(m.duration_s for m in cycle.moves))
    # Each move starts where the one before it ends: the cycle's corners.
    for (a, b), m in zip(
        zip(cycle.waypoints_rad[:-1], cycle.waypoints_rad[1:], strict=True),
        cycle.moves,
        strict=True,
    ):
        assert m.q_from_rad == a and m.q_to_rad == b
    report = s.finish(0.0).to_json()
    assert report["cycle_fallbacks"] == 1 and report["cycles"][0]["blended"] is False
    with pytest.raises(PlanningError, match="no blended trajectory"):
        cycle.trajectory(RIG)


def test_a_cycle_streams_in_its_phases_and_passes_the_guard_unchanged(
    plan_a: TrenchPlan,
) -> None:
    cycle = next(c for c in _cycles(plan_a) if c.blended and c.after_dig)
    motion = sample_cycle(RIG, PERIOD_S, cycle)
    t = (np.arange(motion.n) + 1) * PERIOD_S
    # One run a waypoint interval, in the cycle's order, each from the first sample at or
    # past the interval's start.
    runs = motion.phase_runs
    assert [ph for _, ph in runs] == [Phase.LIFT_OUT, Phase.DUMP, Phase.APPROACH, Phase.ENTER]
    starts = cycle.waypoint_times_s[1:-1]
    for (j, _), t0 in zip(runs[1:], starts, strict=True):
        assert t[j] >= t0 - 1e-12 > t[j - 1]
    assert motion.phase is Phase.LIFT_OUT and motion.dig_index == -1
    np.testing.assert_array_equal(motion.q_rad[-1], cycle.waypoints_rad[-1])
    np.testing.assert_array_equal(motion.q_start_rad, cycle.waypoints_rad[0])
    guard = LimitGuard(StrokeLimits.from_rig(RIG), PERIOD_S)
    guard.reset(motion.stroke_start_m)
    states = []
    err = 0.0
    for k in range(motion.n):
        states.append(guard.track(motion.stroke_m[k], motion.rate_m_s[k], motion.accel_m_s2[k]))
        err = max(err, float(np.abs(guard.position_m - motion.stroke_m[k]).max()))
    assert err <= 1e-9
    assert all(st == GuardState.PASSTHROUGH for st in states)


def test_a_cycle_survives_the_session_state_and_rebuilds_the_same_trajectory(
    planner: TrenchPlanner,
) -> None:
    s = planner.start(load_task("A", RIG))
    for _ in range(2):
        dig = s.next_dig()
        assert dig is not None
        s.record(dig, dig.tip_path_m)
    state = json.loads(json.dumps(s.state()))
    again = TrenchSession.restore(planner, s.task, state)
    before = [c for c in s.steps if isinstance(c, Cycle)]
    after = [c for c in again.steps if isinstance(c, Cycle)]
    assert after == before
    for a, b in zip(before, after, strict=True):
        if a.blended:
            np.testing.assert_array_equal(
                a.trajectory(RIG).coefficients, b.trajectory(RIG).coefficients
            )
    # A state written before cycles existed (version 2, transitions only) still reads.
    old = {**state, "version": 2, "steps": [st for st in state["steps"] if st["type"] == "dig"]}
    TrenchSession.restore(planner, s.task, old)


def test_the_plan_reports_its_dig_cycles(plan_a: TrenchPlan) -> None:
    report = plan_a.to_json()
    cycles = report["cycles"]
    dig_cycles = [c for c in _cycles(plan_a) if c.after_dig]
    # One cycle into each dig but the first (a dig's joined pieces have none between them).
    assert len(cycles) == len(dig_cycles) == len(plan_a.buckets) - 1
    for entry, c in zip(cycles, dig_cycles, strict=True):
        assert set(entry) >= {"waypoints_deg", "moves_s", "bound_s", "blended", "kinds"}
        assert len(entry["waypoints_deg"]) == len(c.waypoints_rad)
        assert all(len(q) == 3 for q in entry["waypoints_deg"])
        assert entry["waypoints_deg"][0] == pytest.approx(np.degrees(c.waypoints_rad[0]))
        assert entry["moves_s"] == c.duration_s and entry["bound_s"] == c.bound_s
    assert report["moves_per_cycle_s"] == pytest.approx(np.mean([c["moves_s"] for c in cycles]))
    assert report["cycle_fallbacks"] == sum(not c["blended"] for c in cycles)
    # Every move of the plan counts in its move time, the cycles and the first approach.
    moves = sum(c.duration_s for c in _cycles(plan_a))
    assert report["transition_time_s"] == pytest.approx(moves)


def test_the_last_dig_s_exit_streams_where_the_planner_fails() -> None:
    planning = _Planning(link=None)  # type: ignore[arg-type]
    exit_moves = (object(), object())
    planning.exit = exit_moves  # type: ignore[assignment]
    motions: deque[Any] = deque()
    planning.take(PlannerError("no dig"), motions, stopping=False)
    assert tuple(motions) == exit_moves and planning.exit == ()
    assert planning.final == (ExecStatus.PLANNING_ERROR, "no dig")
    # While stopping, nothing more streams.
    planning = _Planning(link=None)  # type: ignore[arg-type]
    planning.exit = exit_moves  # type: ignore[assignment]
    motions.clear()
    planning.take(PlannerError("no dig"), motions, stopping=True)
    assert not motions


def test_a_planner_error_in_place_of_the_last_dig_s_record_ends_the_job_with_it() -> None:
    # The last dig (max_digs) ran and the job would end done once its record is back; the
    # planner process ends instead (its models changed on disk, a slow process noticing only
    # at that record): the job is not done, its last dig is not recorded.
    planning = _Planning(link=None)  # type: ignore[arg-type]
    planning.final = (ExecStatus.DONE, "")
    planning.record_out = True
    planning.take(PlannerError("the planner process ended"), deque(), stopping=False)
    assert planning.final == (ExecStatus.PLANNING_ERROR, "the planner process ended")
    assert not planning.record_out
    # With the record back first, the job is done and a later error changes nothing.
    planning = _Planning(link=None)  # type: ignore[arg-type]
    planning.final = (ExecStatus.DONE, "")
    planning.take(PlannerError("the planner process ended"), deque(), stopping=False)
    assert planning.final == (ExecStatus.DONE, "")
