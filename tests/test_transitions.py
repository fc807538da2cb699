"""The moves between digs (issues 23 and 26): every lift, dump, approach and enter, rest to rest
or blended into one cycle, keeps the bucket out of the material left, checked here
independently of the planner's own check.

The independent measure: the move resampled with ruckig's own ``at_time`` (200 samples), a
blended cycle every 5 ms of its trajectory, the bucket outline (``rig.bucket.profile_m``, every
2.5 mm) placed with :func:`kinematics.forward`, and each point's depth as its distance to the
boundary of the session's material polygon where the polygon contains it (shapely), against
the material as it is when the move runs. The planner measures on its 1 mm height field with
its own sampling; the two agree to ~1.5 mm.

The allowances are the planner's documented ones: the lift out of a pose (and a first move
that leaves it without a lift; in a blended cycle, up to its first corner) may cross the
material straight above the bucket's outline at that pose; during ``enter`` (in a blended
cycle, from the pose above the entry on) each point of the bucket may be as deep as at the
entry pose.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import pytest
import shapely
from shapely.geometry import Polygon

from rt_runtime import kinematics
from rt_runtime.bench import random_tasks
from rt_runtime.control.planner_worker import SessionDriver, chain
from rt_runtime.control.setpoints import KIND_PHASE, connect_motion, sample_cycle
from rt_runtime.errors import PlanningError
from rt_runtime.planning.trench import (
    GRID_STEP_M,
    Cycle,
    PlannedDig,
    Transition,
    TransitionKind,
    TravelMove,
    TrenchPlanner,
    TrenchSession,
    joint_move,
    load_task,
)
from rt_runtime.planning.trench import cycles as cycles_module
from rt_runtime.rig import load_rig

RIG = load_rig("scale_model")
SAMPLES = 200
#: The requirement (m): no move takes the bucket deeper into the material left.
LIMIT_M = 0.005
#: How far the planner's measure may lie from this one (m): its height field and sampling.
AGREE_M = 1.5e-3


@pytest.fixture(scope="module")
def planner() -> TrenchPlanner:
    return TrenchPlanner(RIG)


def _outline(step_m: float = 0.0025) -> np.ndarray:
    corners = np.asarray(RIG.bucket.profile_m, dtype=np.float64)
    points = [corners[:1]]
    for a, b in itertools.pairwise(corners):
        k = max(1, math.ceil(float(np.hypot(*(b - a))) / step_m))
        points.append(a + (b - a) * (np.arange(1, k + 1) / k)[:, None])
    return np.concatenate(points)


OUTLINE = _outline()


def _bucket(q: np.ndarray, machine_x_m: float) -> np.ndarray:
    """The outline's points ``(n, m, 2)`` (work-site frame) of joint poses ``(n, 3)``."""
    tip = kinematics.forward(RIG, q)
    z = tip[:, 2:3]
    a, b = OUTLINE[:, 0], OUTLINE[:, 1]
    x = tip[:, 0:1] + np.cos(z) * a - np.sin(z) * b + machine_x_m
    y = tip[:, 1:2] + np.sin(z) * a + np.cos(z) * b
    return np.stack([x, y], axis=-1)


def _depth(material: Any, points: np.ndarray) -> np.ndarray:
    x, y = points[..., 0].ravel(), points[..., 1].ravel()
    inside = shapely.contains_xy(material, x, y)
    d = np.zeros(x.shape)
    if inside.any():
        d[inside] = shapely.distance(shapely.points(x[inside], y[inside]), material.boundary)
    return d.reshape(points.shape[:-1])


def _carried(material: Any, q: np.ndarray, machine_x_m: float) -> Any:
    """``material`` without what lies straight above the bucket's outline at pose ``q``."""
    pts = _bucket(np.asarray(q, dtype=np.float64)[None], machine_x_m)[0]
    strips = [
        Polygon([tuple(a), tuple(b), (b[0], 10.0), (a[0], 10.0)])
        for a, b in itertools.pairwise(pts)
        if abs(a[0] - b[0]) > 1e-12
    ]
    return material.difference(shapely.union_all(strips))


def _poses(move: Transition) -> np.ndarray:
    traj, _ = joint_move(RIG, move.q_from_rad, move.q_to_rad)
    at = traj.at_time
    return np.array([at(float(t))[0] for t in np.linspace(0.0, traj.duration, SAMPLES)])


def _penetration(move: Transition, material: Any) -> float:
    """The move's depth in ``material`` beyond the enter's allowance (m)."""
    pts = _bucket(_poses(move), move.machine_x_m)
    d = _depth(material, pts)
    if move.kind.label == "enter":
        d = d - d[-1]
    return max(0.0, float(d.max()))


def _check_moves(
    moves: tuple[Transition, ...] | list[Transition], material: Any, exit_from: Any = None
) -> list[float]:
    """Every move's independent penetration; ``exit_from``: the pose an exit sequence starts
    at (its lift and a first move without a lift get the carried material)."""
    out = []
    carried = None
    if exit_from is not None:
        carried = _carried(material, exit_from, moves[0].machine_x_m)
    for i, m in enumerate(moves):
        lifting = m.kind is TransitionKind.LIFT_OUT or i == 0
        mat = carried if carried is not None and lifting else material
        p = _penetration(m, mat)
        assert p <= LIMIT_M, (m.kind, i, p)
        assert abs(p - m.penetration_m) <= AGREE_M, (m.kind, i, p, m.penetration_m)
        out.append(p)
    return out


#: Sampling step of a blended cycle (s).
CYCLE_STEP_S = 0.005


def _enter_moves(kinds: tuple[TransitionKind, ...]) -> int:
    """The moves of a cycle's enter, from the pose above the entry: those after its last move
    that is not an enter (more than one where the blend passes poses on the enter's line)."""
    return next(i for i, k in enumerate(reversed(kinds)) if k is not TransitionKind.ENTER)


def _check_cycle(cycle: Cycle, material: Any) -> float:
    """A blended cycle's independent penetration (m), with its allowances: up to its lift's
    top (its first corner without a lift) the material carried out from its start pose, from
    the pose above the entry (the corner before its enter moves, :func:`_enter_moves`) on each
    outline point's depth at the entry; a straight lift before the blend as rest-to-rest moves
    (:func:`_check_moves`), the blend from its top."""
    lead = max(_check_moves(cycle.moves, material, cycle.waypoints_rad[0])) if cycle.moves else 0.0
    traj = cycle.trajectory(RIG)
    t_wp = traj.waypoint_times_s
    kinds = cycle.kinds[cycle.blend_from :]
    n_lift = next((i for i, k in enumerate(kinds) if k is not TransitionKind.LIFT_OUT), 0)
    t2, t_end = float(t_wp[-1 - _enter_moves(kinds)]), traj.duration_s
    t1 = min(float(t_wp[max(n_lift, 1)]), t2)
    q0 = np.asarray(cycle.waypoints_rad[cycle.blend_from])
    x = cycle.machine_x_m
    t = np.linspace(0.0, t_end, max(int(t_end / CYCLE_STEP_S), 2) + 1)
    pts = _bucket(traj.sample(t), x)
    lift, enter = t <= t1, t >= t2
    worst = 0.0
    if lift.any():
        worst = float(_depth(_carried(material, q0, x), pts[lift]).max())
    middle = ~lift & ~enter
    if middle.any():
        worst = max(worst, float(_depth(material, pts[middle]).max()))
    entry = _depth(material, _bucket(np.asarray(cycle.waypoints_rad[-1:]), x))[0]
    worst = max(worst, float((_depth(material, pts[enter]) - entry).max()))
    p = max(0.0, worst, lead)
    assert p <= LIMIT_M, (cycle.kinds, p)
    assert abs(p - cycle.penetration_m) <= AGREE_M, (p, cycle.penetration_m)
    return p


def _assert_straight_up(moves: tuple[Transition, ...] | list[Transition]) -> None:
    for m in moves:
        if m.kind.label != "lift_out":
            continue
        a = kinematics.forward(RIG, np.asarray(m.q_from_rad))
        b = kinematics.forward(RIG, np.asarray(m.q_to_rad))
        assert b[0] == pytest.approx(a[0], abs=1e-9) and b[2] == pytest.approx(a[2], abs=1e-9)
        assert b[1] > a[1]


def _dig_checking_every_move(planner: TrenchPlanner, s: TrenchSession) -> list[Cycle]:
    """Dig ``s`` to its end, every cycle checked independently on the material as it is when
    the cycle runs; the cycles, in order."""
    cycles = []
    while True:
        n0 = len(s.steps)
        dig = s.next_dig()
        if dig is None:
            break
        new = [st for st in s.steps[n0:] if not isinstance(st, TravelMove)]
        if dig.joined and not dig.carried:
            # No moves: it starts where the dig before it ended.
            assert new == [] and dig.problem.q_start_rad == s.digs[-1].problem.q_end_rad
            s.record(dig, dig.tip_path_m)
            continue
        assert len(new) == 1 and isinstance(new[0], Cycle)
        cycle = new[0]
        cycles.append(cycle)
        assert cycle.waypoints_rad[-1] == dig.problem.q_start_rad
        n_enter = _enter_moves(cycle.kinds)
        assert n_enter >= 1 and cycle.kinds[-1 - n_enter] is TransitionKind.APPROACH
        if cycle.after_dig:  # the moves out of the previous dig, on the material it left
            assert cycle.waypoints_rad[0] == s.digs[-1].problem.q_end_rad
            # A carried dig's cycle takes the bucket's load to it: no dump.
            assert (TransitionKind.DUMP in cycle.kinds) is not dig.carried
            if cycle.kinds[0] is not TransitionKind.LIFT_OUT:  # no lift: clear already
                q0 = np.asarray(cycle.waypoints_rad[0])[None]
                assert _depth(s.material, _bucket(q0, cycle.machine_x_m)).max() == 0.0
        else:  # from the home pose, in the spoil zone already
            assert np.allclose(cycle.waypoints_rad[0], planner.home_pose_rad, atol=0.0)
            assert TransitionKind.DUMP not in cycle.kinds
        if cycle.blended:
            _assert_straight_up(cycle.moves)
            assert all(m.kind is TransitionKind.LIFT_OUT for m in cycle.moves)
            _check_cycle(cycle, s.material)
        else:
            exit_moves = [t for t in cycle.moves if t.kind.label in ("lift_out", "dump")]
            entry_moves = [t for t in cycle.moves if t.kind.label in ("approach", "enter")]
            assert list(cycle.moves) == exit_moves + entry_moves
            if exit_moves:
                _assert_straight_up(exit_moves)
                _check_moves(exit_moves, s.material, s.q_now)
            _check_moves(entry_moves, s.material)
        s.record(dig, dig.tip_path_m)
    report = s.finish(0.0).to_json()
    assert report["transition_penetration_max_mm"] <= LIMIT_M * 1e3
    return cycles


@pytest.mark.parametrize("name", list("ABCD"))
def test_every_move_of_a_plan_keeps_the_bucket_out_of_the_material(
    planner: TrenchPlanner, name: str
) -> None:
    cycles = _dig_checking_every_move(planner, planner.start(load_task(name, RIG)))
    assert {"lift_out", "dump", "approach", "enter"} <= {k.label for c in cycles for k in c.kinds}
    assert any(c.blended for c in cycles)


def test_deep_corners_blend_through_the_lift_pieces_or_lift_straight_first(
    planner: TrenchPlanner, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Deep random tasks (0.25 / 0.28 m; the straight lift on a third, 0.29 m). Out of a
    # deep corner the lift is clear only in pieces: the blend goes through the pieces' poses
    # (checked against the material it carries out up to the lift's top). Where no blend
    # through the corner sets, nor the further blends before it, is clear (none of these
    # tasks' cycles since the further blends; here those are switched off), the lift is made
    # straight, at rest at its top, and the blend starts there; that streams as the lift's
    # moves and then the blend, one chain.
    tasks = random_tasks(RIG, 17, 7)
    pieces = []
    for i in (11, 16):
        cycles = _dig_checking_every_move(planner, planner.start(tasks[i]))
        lifts = [sum(k is TransitionKind.LIFT_OUT for k in c.kinds) for c in cycles]
        through = [c.blended and not c.moves and n > 1 for c, n in zip(cycles, lifts, strict=True)]
        pieces += [c for c, ok in zip(cycles, through, strict=True) if ok]
    assert pieces, "no cycle blended through a lift in pieces"
    monkeypatch.setattr(cycles_module, "_FURTHER_BLENDS", ("straight",))
    straight = [
        c
        for c in _dig_checking_every_move(planner, planner.start(tasks[15]))
        if c.blended and c.moves
    ]
    assert straight, "no cycle lifted straight before its blend"
    for c in straight:
        b = c.blend_from
        traj = c.trajectory(RIG)
        assert np.abs(traj.sample(0.0, 1)).max() <= 1e-9  # the blend starts at rest
        assert c.waypoints_rad[b] == c.moves[-1].q_to_rad
        assert c.duration_s == pytest.approx(
            sum(m.duration_s for m in c.moves) + traj.duration_s, rel=1e-12
        )
        motion = sample_cycle(RIG, 0.002, c)
        np.testing.assert_array_equal(motion.q_start_rad, c.waypoints_rad[b])
        assert motion.phase is KIND_PHASE[c.kinds[b]]
        # As the planner process streams it: no connecting move is needed anywhere.
        lift = [
            connect_motion(RIG, 0.002, m.q_from_rad, m.q_to_rad, KIND_PHASE[m.kind])
            for m in c.moves
        ]
        chained, end = chain(RIG, 0.002, np.asarray(c.waypoints_rad[0]), [*lift, motion])
        assert len(chained) == len(lift) + 1
        np.testing.assert_array_equal(end, c.waypoints_rad[-1])
        # The planned moves against their bound through the same corners (no clock here).
        moves_over_bound = c.duration_s / c.bound_s
        assert moves_over_bound < 1.6


def test_a_blend_that_goes_in_on_its_enter_passes_poses_on_the_enter_line(
    planner: TrenchPlanner,
) -> None:
    # A deep random task (0.30 m, seed 5, 8 digs) with a cycle whose blends through the
    # corner sets go into the material on the enter or the lift: with poses on the enter's
    # straight line as corners the blend is clear (checked independently here on the
    # material's polygon, the enter's allowance from the pose above the entry), and every
    # cycle is blended within 1.25 times its bound (the slowest, 1.21, enters the slot the
    # far wall's pass cut beside the bottom, which the height field measured 4.5 mm deeper
    # than it is).
    task = random_tasks(RIG, 58, 5)[57]
    cycles = _dig_checking_every_move(planner, planner.start(task))
    split = [c for c in cycles if sum(k is TransitionKind.ENTER for k in c.kinds) > 1]
    assert split, "no blend through poses on the enter's line"
    assert all(c.blended for c in cycles)
    ratios = [c.duration_s / c.bound_s for c in cycles]
    assert max(ratios) <= 1.25, [round(r, 3) for r in ratios]


def _partly_dug(planner: TrenchPlanner, digs: int = 3) -> TrenchSession:
    s = planner.start(load_task("A", RIG))
    for _ in range(digs):
        d = s.next_dig()
        assert d is not None
        s.record(d, d.tip_path_m)
    return s


def test_exit_from_a_pose_inside_the_material_lifts_straight_up_and_is_clear(
    planner: TrenchPlanner,
) -> None:
    s = _partly_dug(planner)
    t = s.task
    rng = np.random.default_rng(23)
    home = np.asarray(planner.home_pose_rad)
    done = 0
    while done < 20:
        x = rng.uniform(t.start_x_m - t.length_m, t.start_x_m)
        depth = rng.uniform(0.0, 0.08)
        y = float(np.interp(x, s.grid, s.surface)) - depth
        att = math.radians(rng.uniform(-175.0, -75.0))
        q = planner.arm.ik(x - s.machine_x, y, att)
        if q is None:
            continue
        case = (round(x, 4), round(depth, 4), round(math.degrees(att), 1))
        moves = s.exit_transitions(q)
        assert [m.kind.label for m in moves[:-1]] == ["lift_out"] * (len(moves) - 1), case
        assert moves[0].q_from_rad == pytest.approx(q, abs=0.0)
        assert np.allclose(moves[-1].q_to_rad, home, atol=0.0), case
        _assert_straight_up(moves)
        _check_moves(moves, s.material, q)
        done += 1


@pytest.mark.parametrize("task", ["A", "B", "C", "D"])
def test_exit_from_anywhere_along_a_dig_is_clear(planner: TrenchPlanner, task: str) -> None:
    # A dig stopped anywhere (a fault, a stop request) leaves the bucket where it was: its
    # entry tip first, steep, with the tip between two columns of the height field.
    s = planner.start(load_task(task, RIG))
    for _ in range(2):
        dig = s.next_dig()
        assert isinstance(dig, PlannedDig)
        traj = dig.trajectory()
        for t in np.linspace(0.0, dig.T_s, 13):
            q = np.asarray(traj.sample(float(t))[0])
            moves = s.exit_transitions(q)
            _check_moves(moves, s.material, q)
        s.record(dig, dig.tip_path_m)


def test_exit_moves_planned_before_the_dig_are_clear_of_what_it_leaves(
    planner: TrenchPlanner,
) -> None:
    # As the executor gets them: the planner side plans a dig's exit before the dig runs.
    s = _partly_dug(planner)
    plan = SessionDriver(s).plan()
    assert plan.dig is not None and plan.exit and plan.exit[-1].kind.label == "dump"
    s.record(plan.dig, plan.dig.tip_path_m)
    _check_moves(plan.exit, s.material, plan.dig.problem.q_end_rad)
    # The next dig's cycle starts where they do, at the dig's exit, on the material it left.
    n0 = len(s.steps)
    s.next_dig()
    cycle = s.steps[n0]
    assert isinstance(cycle, Cycle) and cycle.waypoints_rad[0] == plan.exit[0].q_from_rad


def test_lead_in_from_a_measured_pose_in_the_material_lifts_out_first(
    planner: TrenchPlanner,
) -> None:
    s = _partly_dug(planner, digs=1)
    q_end = np.asarray(s.digs[0].problem.q_end_rad)
    x, y, att = planner.arm.tip(q_end)
    q_in = planner.arm.ik(x, y - 0.03, att)  # stopped 3 cm deeper than the exit
    assert q_in is not None
    plan = SessionDriver(s).plan(np.asarray(q_in))
    cycle = plan.cycle
    assert cycle is not None and np.allclose(cycle.waypoints_rad[0], q_in, atol=0.0)
    assert cycle.kinds[0] is TransitionKind.LIFT_OUT and TransitionKind.DUMP in cycle.kinds
    if cycle.blended:
        _check_cycle(cycle, s.material)
    else:
        _check_moves(cycle.moves, s.material, q_in)


def test_a_move_that_cannot_be_made_clear_is_refused(planner: TrenchPlanner) -> None:
    s = _partly_dug(planner, digs=1)
    dig = s.next_dig()
    assert isinstance(dig, PlannedDig)
    # Material heaped over the home pose: every way to it ends in the material. (Only the
    # height field, which the moves are checked on, is changed.)
    x_dump, y_dump, _ = planner.arm.tip(np.asarray(planner.home_pose_rad))
    heap = np.abs(s.grid - (x_dump + s.machine_x)) < 0.1
    s.surface = np.where(heap, y_dump + 0.1, s.surface)
    with pytest.raises(PlanningError, match=r"exit moves .*: the dump move goes .*mm.* into"):
        s.exit_transitions(dig.problem.q_end_rad)
    with pytest.raises(PlanningError, match=r"entry moves .*: the approach move goes .*mm.* into"):
        s.entry_transitions(dig, planner.home_pose_rad)


def test_numpy_sampling_of_ruckig_moves_equals_at_time(planner: TrenchPlanner) -> None:
    mover = planner.mover
    rng = np.random.default_rng(5)
    lo, hi = RIG.q_min_rad, RIG.q_max_rad
    for i in range(300):
        q0 = rng.uniform(lo, hi)
        q1 = q0 + rng.normal(0.0, 0.01, 3) if i % 3 == 0 else rng.uniform(lo, hi)
        traj = mover.move(q0, q1)
        times = np.linspace(0.0, traj.duration, 97)
        ref = np.array([traj.at_time(float(t))[0] for t in times])
        assert np.abs(mover.poses(traj, times) - ref).max() <= 1e-12, (q0, q1)
        # Each joint turns one way (the samples' spacing relies on it).
        step = np.diff(ref, axis=0) * np.sign(q1 - q0)
        assert np.all(step >= -1e-12), (q0, q1)


def test_depth_is_the_distance_into_the_material_not_the_height_over_it() -> None:
    from rt_runtime.planning.trench.geometry import _depth_below

    grid = np.arange(0.0, 0.2 + GRID_STEP_M / 2, GRID_STEP_M)
    surface = np.where(grid < 0.1, -0.02, -0.10)  # an 8 cm step at x = 0.1
    x = np.array([0.098, 0.05, 0.15, 0.0995])
    y = np.array([-0.06, -0.03, -0.09, -0.099])
    d = _depth_below(grid, surface, x, y, np.inf)
    # 2 mm into the face of the step (the surface is 4 cm over it), 1 cm below the top, above
    # the low side, and 0.5 mm into the face near its foot.
    assert d == pytest.approx([0.002, 0.01, 0.0, 0.0005], abs=GRID_STEP_M / 2)
    assert _depth_below(grid, surface, x, y, 0.005) == pytest.approx(np.minimum(d, 0.005))
