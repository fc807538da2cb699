"""Blended dig cycles: the moves into a dig as one minimum time-jerk trajectory through their
corners (Zhao eq 3, :mod:`rt_runtime.trajectory.timejerk`), dumping in the rig's spoil zone at
the point and attitude that make the cycle shortest.

A cycle runs from where the arm is (the previous dig's exit, the home pose, a measured pose) to
the next dig's entry through the corners the rest-to-rest moves (``moves``) stop at: the top of
the lift straight up out of the material, a dump pose in the spoil zone, the pose above the
entry. Blended, it is at rest only at both ends; position, velocity and acceleration are
continuous, every joint keeps its velocity, acceleration and jerk limits and its range at every
instant (the generator's exact check), so the limit guard passes it through unchanged. Waypoint
intervals that take a fifth of the cycle or more (:data:`_LONG_SHARE`, on the rest-to-rest
times) get :data:`_SHAPE_KNOTS` shape knots: one cubic a corner-to-corner stretch would be as
slow as stopping at the corners.

Rules (arm frame, m, rad, s):

* Corners. The lift and the pose above the entry are the rest-to-rest moves' own
  (:meth:`~MovesMixin.exit_transitions`, :meth:`~MovesMixin.entry_transitions`): the lowest
  clear lift, the first clear approach pose; where the cycle through them goes into the
  material, the next lift (a lift in pieces with its intermediate poses as corners, then the
  next height) or the next approach pose (higher), by where it went in (:meth:`cycle`). A
  clear blend more than :data:`_NEAR_BOUND` times its bound (mostly one made clear only
  without shape knots) does not end that search: the next corner sets are tried, and the
  shortest clear cycle is taken.
* Further blends. Where the corner sets give no clear blend, or only one over
  :data:`_NEAR_BOUND` times its bound, the search goes on (:meth:`_further_blends`) until
  one is within that: the same sets with shape knots in every interval, then the lowest
  clear lift split into 2 and 3 equal rises on its vertical as corners (a blend that leaves
  the vertical early goes into the material beside the bucket), then the enter's straight
  line split likewise (a blend that reaches the line late goes in beside the entry), then
  the straight lift below; the shortest clear cycle is taken.
* Gain. A blend no shorter than the rest-to-rest moves through its own corners is not used
  (many close corners, a lift in pieces, can make it so).
* Dump. Candidates on a grid over the spoil zone (:class:`~rt_runtime.rig.SpoilZone`:
  :data:`_SPOIL_GRID` x, heights and attitudes), each nearer the machine by the zone's
  ``edge_gap_m`` than the near edge of the section being dug, reachable, and with the whole
  bucket :data:`_LIFT_CLEAR_M` above the material. They are ranked by the bound through the
  cycle's corners (:func:`~rt_runtime.trajectory.timejerk.reversal_bound_s`: each joint
  stopping only where it reverses); the best are planned (at most :data:`_N_PLANNED`, while
  a candidate's bound is below the shortest clear cycle found; each with its shape knots, and
  without them where that is not clear) and the shortest clear cycle is taken.
* Check. The whole bucket outline, sampled as a move's (:meth:`MovesMixin._depth_along`),
  stays within :data:`TRANSITION_PENETRATION_M` less :data:`_BLEND_MARGIN_M` of the material
  left, with the moves' allowances: up to the lift's top (its last corner; the first corner
  where there is no lift) the material straight above the bucket at the start is what it
  carries out; from the pose
  above the entry on, each point of the bucket may be as deep as at the entry. Between those,
  the tip stays :data:`_GROUND_CLEAR_M` above the ground where it is outside the trench's top
  edges.
* Straight lift. The last of the further blends (deep corners: a blend through the lift's
  top leaves the vertical while still in the material): the lowest clear lift is made
  rest-to-rest, straight up, and the blend starts at rest at its top (the cycle's
  :attr:`~rt_runtime.planning.trench.Cycle.moves` before its blend), with the first two
  approach poses.
* Fallback. Where that is not clear either, the rest-to-rest moves through the best
  candidate's corners (each checked), else through the home pose (the moves every dig's choice
  checked: :meth:`MovesMixin._check_transition_poses`).

ruckig plans the rest-to-rest moves and, in the executor, the guard and every stop; never its
intermediate waypoints (the PyPI build sends those to a cloud service).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rt_runtime import kinematics
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning.trench.geometry import FloatArray, sextic_bulge
from rt_runtime.planning.trench.moves import (
    _COARSE_STEP_M,
    _LIFT_CLEAR_M,
    TRANSITION_PENETRATION_M,
    MovesMixin,
)
from rt_runtime.planning.trench.plan import (
    Cycle,
    PlannedDig,
    Transition,
    TransitionKind,
    cycle_problem,
)
from rt_runtime.planning.trench.state import _stage
from rt_runtime.rig import Rig
from rt_runtime.trajectory.timejerk import (
    TimeJerkTrajectory,
    plan,
    rest_to_rest_time_s,
    reversal_bound_s,
)

#: Weight of the jerk integral in a cycle's objective (s^6/rad^2, with w_time = 1): small, so a
#: cycle is within ~0.1 % of the shortest through its corners, and positive, so its ends ramp
#: the acceleration (together with the jerk limit) rather than jump it.
CYCLE_W_JERK = 1e-3

#: Candidates of the spoil zone a cycle chooses its dump from: x, tip heights, attitudes.
_SPOIL_GRID = (5, 4, 5)

#: Dump candidates planned for real per cycle, best bound first.
_N_PLANNED = 2

#: Shape knots of a long waypoint interval, and what makes one long: its rest-to-rest time's
#: share of the cycle's (the slowest joint's, :func:`rest_to_rest_time_s`).
_SHAPE_KNOTS = 2
_LONG_SHARE = 0.2

#: Corner sets a cycle tries before its fallback (:meth:`CyclesMixin.cycle`): of the lowest
#: :data:`_N_LIFTS` clear lifts and the first :data:`_N_ABOVE` clear approach poses.
_ATTEMPTS = 5
_N_LIFTS = 2
_N_ABOVE = 3

#: The parts of a cycle (:meth:`CyclesMixin._cycle_depth`) up to which a cycle that goes into
#: the material tries a higher lift rather than a higher approach pose.
_EARLY = 1

#: A clear blend within this factor of its bound (each joint stopping only where it reverses)
#: ends the search over corner sets; a slower one (mostly without shape knots, those with them
#: having gone into the material) is kept while the next corner sets, then the further blends
#: (:meth:`CyclesMixin._further_blends`), are tried for a shorter.
_NEAR_BOUND = 1.15

#: SLSQP's tolerance on the scaled objective for a cycle with shape knots: 1e-6 of a cycle is
#: ~10 us.
_SHAPE_FTOL = 1e-6

#: SLSQP's iteration cap for a cycle with shape knots (its last iterate, scaled to the limits,
#: where it stops there): A-D's cycles are as with 100 (times within 0.1 %) on a fifth fewer
#: evaluations, with 40 up to 3 % longer.
_MAX_ITERATIONS = 60

#: Height the tip keeps above the ground outside the trench between the lift and the approach
#: (scale model, m; scaled by reach).
_GROUND_CLEAR_M = 0.01

#: A blend is taken only this far inside :data:`TRANSITION_PENETRATION_M` (m): chosen among
#: several, it tends to sit at the limit, where the planner's measure (1 mm height field) and an
#: exact one on the material polygon (tests/test_transitions.py) disagree slightly (A-D's
#: blends above 4 mm: the exact one 0.03-0.54 mm lower; a lead-in from a measured pose 0.005 mm
#: higher, at 5.002 mm); a rest-to-rest fallback keeps the limit itself.
_BLEND_MARGIN_M = 0.1e-3

#: The further blends a cycle tries, in order, where its corner sets give none clear or only
#: one slower than :data:`_NEAR_BOUND` times its bound (:meth:`CyclesMixin._further_blends`).
_FURTHER_BLENDS = ("more_knots", "vertical", "enter", "straight")

# Two corners closer than this in every joint are one (rad): the generator refuses repeats.
_SAME_POSE_RAD = 1e-9

#: A bucket carrying a load from one dig to the next (a carried dig) keeps its attitude this
#: far below the spoil zone's lowest (rad). The profiles' lowest dump attitude (-100 deg) is
#: where the bucket empties: its floor slopes down to the cutting edge by 45 deg. A light load
#: (below the fill band: the only one carried) lies on the floor and slides out where the
#: floor slopes more than soil's friction on steel (~30 deg); 25 deg more curled leaves it a
#: 20 deg slope at most (-125 deg; the backward digs' entry tables reach -135 to -150 deg, the
#: downward digs' only -100 to -120 deg, so no load is carried to a downward dig).
_CARRY_ATTITUDE_MARGIN_RAD = math.radians(25.0)

#: The largest load a bucket carries, as a fraction of its struck volume: the attitude rule
#: holds for a layer on the bucket's floor, not for a bucket near full.
_CARRY_LOAD_MAX = 0.5

# Samples of a carry cycle's blended trajectory and of each of its moves in the load check.
_CARRY_SAMPLES = 200


def spoil_poses(
    rig: Rig, arm: kinematics.FastArm, x_max_m: float = math.inf
) -> tuple[FloatArray, FloatArray]:
    """The spoil zone's candidate dump poses: a grid of :data:`_SPOIL_GRID` tip x (up to
    ``x_max_m``), tip heights above the ground and attitudes over ``rig.trench.spoil``, those
    the arm reaches within its joint ranges.

    Returns:
        Joint poses ``(k, 3)`` (rad) and their tip x ``(k,)`` (m, arm frame); ``k`` may be 0.
    """
    zone = rig.trench.spoil
    nx, nh, nz = _SPOIL_GRID
    x_hi = min(zone.x_m[1], x_max_m)
    if x_hi < zone.x_m[0]:
        return np.empty((0, 3)), np.empty(0)
    poses: list[tuple[float, float, float]] = []
    xs: list[float] = []
    for x in np.linspace(zone.x_m[0], x_hi, nx).tolist():
        for h in np.linspace(zone.height_m[0], zone.height_m[1], nh).tolist():
            for z in np.linspace(zone.attitude_rad[0], zone.attitude_rad[1], nz).tolist():
                q = arm.ik(x, rig.ground_y_m + h, z)
                if q is not None:
                    poses.append(q)
                    xs.append(x)
    return np.asarray(poses, dtype=np.float64).reshape(-1, 3), np.asarray(xs, dtype=np.float64)


def home_pose(rig: Rig, arm: kinematics.FastArm) -> FloatArray:
    """The home pose: the spoil zone's candidate nearest the machine, the lowest there, with the
    bucket most open; where a task starts and the moves after its last dig end.

    Raises:
        ConfigurationError: The arm reaches no point of the zone (names the profile's table).
    """
    q, x = spoil_poses(rig, arm)
    if q.shape[0] == 0:
        zone = rig.trench.spoil
        raise ConfigurationError(
            f"rig {rig.name}: trench.spoil: the arm reaches no point of the spoil zone (x "
            f"{zone.x_m[0]:g}..{zone.x_m[1]:g} m, {zone.height_m[0]:g}..{zone.height_m[1]:g} m "
            f"above the ground, attitude {math.degrees(zone.attitude_rad[0]):g}.."
            f"{math.degrees(zone.attitude_rad[1]):g} deg) within its joint ranges"
        )
    tip = kinematics.forward(rig, q)
    order = np.lexsort((-tip[:, 2], tip[:, 1], x))
    out: FloatArray = q[order[0]]
    return out


class CyclesMixin(MovesMixin):
    """The blended cycles between a session's digs (see the module)."""

    #: The carry cycle into the carried dig last checked (:meth:`_carry_cycle`).
    _carry_checked: tuple[PlannedDig, Cycle] | None = None

    @_stage("transitions")
    def _append_transitions(self, dig: PlannedDig) -> None:
        """The moves into ``dig``: a dig cycle from the previous dig's exit (without the dump
        into a carried dig: the one its check planned), or the approach from the home pose
        (the start of a task or section)."""
        checked = self._carry_checked
        self._carry_checked = None
        if dig.carried:
            if checked is None or checked[0] is not dig:
                raise PlanningError("a carried dig's cycle was not checked with the dig")
            self.steps.append(checked[1])
        elif self.q_now is not None:
            self.steps.append(self.cycle(self.q_now, dig, after_dig=True))
        else:
            self.steps.append(self.cycle(self.planner.home_pose_rad, dig, dump=False))

    def carry_attitude_max(self) -> float:
        """The largest bucket attitude (rad, the joints' sum) that holds a carried load: the
        spoil zone's lowest less :data:`_CARRY_ATTITUDE_MARGIN_RAD`."""
        return self.rig.trench.spoil.attitude_rad[0] - _CARRY_ATTITUDE_MARGIN_RAD

    def carry_load_max_m3(self) -> float:
        """The largest load a bucket carries to a carried dig (m^3): :data:`_CARRY_LOAD_MAX`
        of the struck volume."""
        return _CARRY_LOAD_MAX * self.rig.bucket.capacity_m3

    def holds_load(self, q: FloatArray) -> bool:
        """Whether the bucket holds a carried load at every joint pose ``(n, 3)``: its
        attitude at most :meth:`carry_attitude_max`."""
        return bool(np.all(np.sum(q, axis=-1) <= self.carry_attitude_max()))

    @_stage("transitions")
    def _carry_cycle(self, dig: PlannedDig) -> Cycle:
        """The cycle that carries the last dig's bucket from its exit (:attr:`q_now`) into the
        carried ``dig``'s entry without a dump (:meth:`cycle`), its sampled poses and the
        dig's holding the load (:meth:`holds_load`); kept for :meth:`_append_transitions`.

        Raises:
            PlanningError: No clear cycle, or one or the dig tilts the bucket past the
                attitudes that hold the load.
        """
        if self.q_now is None:
            raise PlanningError("a carried dig needs the exit of the dig before it")
        cyc = self.cycle(self.q_now, dig, dump=False, after_dig=True)
        if cyc.penetration_m > TRANSITION_PENETRATION_M:
            raise PlanningError(
                f"the carry into dig {dig.index + 1} goes {cyc.penetration_m * 1e3:.1f} mm into "
                "the material"
            )
        mover = self.planner.mover
        poses = [np.asarray(cyc.waypoints_rad, dtype=np.float64)]
        for m in cyc.moves:
            traj = mover.move(m.q_from_rad, m.q_to_rad)
            poses.append(mover.poses(traj, np.linspace(0.0, traj.duration, _CARRY_SAMPLES)))
        if cyc.blended:
            traj = cyc.trajectory(self.rig)
            poses.append(traj.sample(np.linspace(0.0, traj.duration_s, _CARRY_SAMPLES)))
        q1 = np.asarray(dig.problem.q_start_rad, dtype=np.float64)
        q2 = np.asarray(dig.problem.q_end_rad, dtype=np.float64)
        poses.append(self.planner.sextic_path(q1, q2, sextic_bulge(dig.a6, dig.T_s)))
        if not self.holds_load(np.concatenate(poses)):
            raise PlanningError(f"the carry into dig {dig.index + 1} would spill its load")
        self._carry_checked = (dig, cyc)
        return cyc

    def cycle(
        self,
        q_from_rad: ArrayLike,
        dig: PlannedDig,
        *,
        dump: bool = True,
        after_dig: bool = False,
    ) -> Cycle:
        """The moves from ``q_from_rad`` (at rest) into ``dig``'s entry on the current material
        (see the module): blended where a blend is clear, else rest-to-rest.

        The corners tried, at most :data:`_ATTEMPTS` sets: the lowest clear lift and the first
        clear approach pose first; where the best dump's cycle goes into the material in its
        first half the next lift (its intermediate poses as corners, then the next height),
        in its second half the next approach pose (higher above the entry). Where none is
        clear, or the shortest is over :data:`_NEAR_BOUND` times its bound, the further blends
        (:meth:`_further_blends`), the last of them the lowest lift made straight with the
        blend from its top.

        Args:
            q_from_rad: Start pose ``(3,)``: a dig's exit, the home pose or a measured pose.
            dig: The dig to enter.
            dump: Go through the spoil zone (False: the arm is there already, or the bucket's
                load is carried to a carried dig).
            after_dig: The start is the previous dig's exit (a dig cycle, in the report).

        Raises:
            PlanningError: Not even the fallback's moves are clear (as
                :meth:`exit_transitions` and :meth:`entry_transitions`).
        """
        q0 = np.asarray(q_from_rad, dtype=np.float64)
        qe = np.asarray(dig.problem.q_start_rad, dtype=np.float64)
        surface = self.surface
        carry = self._carry(q0, surface)
        lifts = list(
            itertools.islice((m for m in self._lifts(q0, surface, carry) if _clear(m)), _N_LIFTS)
        )
        aboves = list(itertools.islice(self._entries(qe, surface, []), _N_ABOVE))
        dumps = self._dump_candidates(surface) if dump else np.empty((0, 3))
        if lifts and aboves and (dumps.shape[0] or not dump):
            lift_sets: list[list[FloatArray]] = []
            for lift in lifts:
                tops = [np.asarray(m.q_to_rad) for m in lift]
                lift_sets.append(tops[-1:])
                if len(tops) > 1:
                    lift_sets.append(tops)
            li = aj = 0
            found: Cycle | None = None
            tried: list[tuple[list[FloatArray], FloatArray]] = []
            for attempt in range(_ATTEMPTS):
                tried.append((lift_sets[li], aboves[aj][0]))
                best, part = self._blend(
                    q0,
                    lift_sets[li],
                    dumps,
                    aboves[aj][0],
                    qe,
                    dump,
                    after_dig,
                    _N_PLANNED if attempt == 0 else 1,
                )
                if best is not None:
                    if found is None or best.duration_s < found.duration_s:
                        found = best
                    if found.duration_s <= _NEAR_BOUND * found.bound_s:
                        return found
                if part <= _EARLY and li + 1 < len(lift_sets):
                    li += 1
                elif aj + 1 < len(aboves):
                    aj += 1
                elif li + 1 < len(lift_sets):
                    li += 1
                else:
                    break
            if found is None or found.duration_s > _NEAR_BOUND * found.bound_s:
                further = self._further_blends(
                    q0,
                    qe,
                    lifts[0],
                    tried,
                    [a[0] for a in aboves[:2]],
                    dumps,
                    dump,
                    after_dig,
                )
                for best in further:
                    if best is not None and (found is None or best.duration_s < found.duration_s):
                        found = best
                        if found.duration_s <= _NEAR_BOUND * found.bound_s:
                            break
            if found is not None:
                return found
        return self._fallback(
            q0,
            qe,
            lifts[0] if lifts else None,
            aboves[0] if aboves else None,
            dumps,
            dump,
            after_dig,
        )

    def _further_blends(
        self,
        q0: FloatArray,
        qe: FloatArray,
        lift: tuple[Transition, ...],
        tried: list[tuple[list[FloatArray], FloatArray]],
        aboves: list[FloatArray],
        dumps: FloatArray,
        dump: bool,
        after_dig: bool,
    ) -> Iterator[Cycle | None]:
        """The blends :meth:`cycle` tries where the corner sets ``tried`` (lift corners, pose
        above the entry) gave none clear or only a slow one, by the steps of
        :data:`_FURTHER_BLENDS` in order: ``more_knots``, those sets again with shape knots in
        every interval; ``vertical``, the lowest clear lift ``lift`` split into 2, then 3,
        equal rises on its vertical (as corners: the blend keeps nearer the vertical);
        ``enter``, the sets again with the enter's straight line from the pose above the entry
        split into 2, then 3, equal parts (as corners, each move an enter); ``straight``, the
        lift straight, at rest at its top, and the blend from there (``aboves``: the approach
        poses to try). Each is the best clear cycle of its corners, or None."""

        def again(enter_pieces: int, knots_everywhere: bool) -> Iterator[Cycle | None]:
            """The tried sets again, the enter's line split into ``enter_pieces`` (0: not)."""
            for attempt, (lift_poses, above) in enumerate(tried):
                poses = self._line_poses(above, qe, enter_pieces) if enter_pieces else []
                if poses is not None:
                    yield self._blend(
                        q0,
                        lift_poses,
                        dumps,
                        above,
                        qe,
                        dump,
                        after_dig,
                        _N_PLANNED if attempt == 0 else 1,
                        knots_everywhere=knots_everywhere,
                        enter_poses=tuple(poses),
                    )[0]

        for step in _FURTHER_BLENDS:
            if step == "more_knots":
                yield from again(0, True)
            elif step == "vertical" and lift:
                top = np.asarray(lift[-1].q_to_rad)
                for pieces in (2, 3):
                    poses = self._line_poses(q0, top, pieces) if pieces > len(lift) else None
                    if poses is not None:
                        yield self._blend(
                            q0, [*poses, top], dumps, tried[0][1], qe, dump, after_dig, _N_PLANNED
                        )[0]
            elif step == "enter":
                for pieces in (2, 3):
                    yield from again(pieces, False)
            elif step == "straight" and lift:
                for above in aboves:
                    yield self._blend(
                        q0, [], dumps, above, qe, dump, after_dig, _N_PLANNED, lead=lift
                    )[0]

    def _line_poses(self, qa: FloatArray, qb: FloatArray, pieces: int) -> list[FloatArray] | None:
        """The poses that split the tip's straight line from ``qa``'s tip to ``qb``'s into
        ``pieces`` equal parts (ends excluded), at ``qa``'s attitude (the lift's and the
        enter's lines keep it); None where one is out of reach."""
        arm = self.planner.mover.arm
        xa, ya, za = arm.tip(qa)
        xb, yb, _ = arm.tip(qb)
        out: list[FloatArray] = []
        for f in np.linspace(0.0, 1.0, pieces + 1)[1:-1].tolist():
            q = arm.ik(xa + f * (xb - xa), ya + f * (yb - ya), za)
            if q is None:
                return None
            out.append(np.asarray(q, dtype=np.float64))
        return out

    def _dump_candidates(self, surface: FloatArray) -> FloatArray:
        """The spoil zone's dump poses for the section being dug (see the module): ``(k, 3)``."""
        zone = self.rig.trench.spoil
        x_max = self.section_lo - self.machine_x - zone.edge_gap_m
        key = round(x_max, 9)
        cached = self._spoil.get(key)
        if cached is None:
            cached = spoil_poses(self.rig, self.planner.arm, x_max)[0]
            self._spoil[key] = cached
        if cached.shape[0] == 0:
            return cached
        bx, by = self.planner.mover.bucket_xy(cached)
        clear = _LIFT_CLEAR_M * self.planner.scale
        ok = np.all(by >= np.interp(bx + self.machine_x, self.grid, surface) + clear, axis=1)
        out: FloatArray = cached[ok]
        return out

    def _blend(
        self,
        q0: FloatArray,
        lift_poses: list[FloatArray],
        dumps: FloatArray,
        q_above: FloatArray,
        qe: FloatArray,
        dump: bool,
        after_dig: bool,
        n_planned: int,
        lead: tuple[Transition, ...] = (),
        knots_everywhere: bool = False,
        enter_poses: tuple[FloatArray, ...] = (),
    ) -> tuple[Cycle | None, int]:
        """The shortest clear blended cycle through ``q0``, ``lift_poses``, one of ``dumps``
        (the best ``n_planned`` by the bound), ``q_above`` and ``qe``, or None; and where the
        first candidate's first trajectory went deepest into the material (a part of
        :meth:`_cycle_depth`, as :meth:`_clear_trajectory` gives it). With
        ``lead`` (a clear lift from ``q0``) the blend starts at rest at the lift's top, after
        its rest-to-rest moves."""
        rig = self.rig
        limits = (rig.qd_max_rad_s, rig.qdd_max_rad_s2, rig.qddd_max_rad_s3)
        lead_poses = [np.asarray(m.q_to_rad) for m in lead]
        q_blend = lead_poses[-1] if lead else q0
        lead_s = sum(m.duration_s for m in lead)
        head = [q_blend, *lift_poses]
        kinds_head = [TransitionKind.LIFT_OUT] * len(lift_poses)
        tail = [q_above, *enter_poses, qe]
        kinds_tail = [TransitionKind.APPROACH, *[TransitionKind.ENTER] * (len(enter_poses) + 1)]
        if dump:
            corners = np.array([[*head, d, *tail] for d in dumps])
            kinds = [*kinds_head, TransitionKind.DUMP, *kinds_tail]
        else:
            corners = np.array([[*head, *tail]])
            kinds = [*kinds_head, *kinds_tail]
        bounds = reversal_bound_s(corners, *limits)
        best: Cycle | None = None
        first_part = -1
        for i in np.argsort(bounds, kind="stable")[:n_planned].tolist():
            if best is not None and bounds[i] >= best.duration_s:
                break
            waypoints, wp_kinds = _distinct(corners[i], kinds)
            n_lift, n_enter = _lift_and_enter(wp_kinds)
            traj, depth, part = self._clear_trajectory(
                waypoints, q_blend, qe, n_lift, n_enter, knots_everywhere
            )
            if first_part < 0:
                first_part = part
            if traj is None or traj.duration_s >= self._stopping_s(waypoints):
                continue
            if best is None or lead_s + traj.duration_s < best.duration_s:
                every = np.array([q0, *lead_poses, *waypoints[1:]])
                cycle = Cycle(
                    waypoints_rad=tuple(_triple(q) for q in every),
                    kinds=(*(m.kind for m in lead), *wp_kinds),
                    piece_durations_s=tuple(float(h) for h in traj.piece_durations_s),
                    shape_knots=traj.problem.shape_knots,
                    shape_positions_rad=tuple(_triple(q) for q in traj.shape_positions_rad),
                    w_jerk=CYCLE_W_JERK,
                    moves=lead,
                    duration_s=lead_s + traj.duration_s,
                    bound_s=float(reversal_bound_s(every, *limits)),
                    machine_x_m=self.machine_x,
                    penetration_m=max([depth, *(m.penetration_m for m in lead)]),
                    after_dig=after_dig,
                )
                best = cycle
        return best, first_part

    def blend_clear(self, cycle: Cycle) -> float | None:
        """A blended cycle's depth into the current material beyond its allowances (m), as
        :meth:`cycle` checks it, where it is within what :meth:`cycle` takes (the limit less
        :data:`_BLEND_MARGIN_M`); None otherwise, or where it is not blended or lifts
        rest-to-rest before its blend (a cycle planned on other material, checked again)."""
        if not cycle.blended or cycle.moves:
            return None
        waypoints = np.asarray(cycle.waypoints_rad, dtype=np.float64)
        n_lift, n_enter = _lift_and_enter(cycle.kinds)
        traj = cycle.trajectory(self.rig)
        depth, _ = self._cycle_depth(traj, waypoints[0], waypoints[-1], n_lift, n_enter)
        return depth if depth <= TRANSITION_PENETRATION_M - _BLEND_MARGIN_M else None

    def _stopping_s(self, waypoints: FloatArray) -> float:
        """The time of the rest-to-rest moves through ``waypoints`` (ruckig, stopping at every
        corner): a blend no shorter is no gain."""
        mover = self.planner.mover
        return sum(float(mover.move(a, b).duration) for a, b in itertools.pairwise(waypoints))

    def _clear_trajectory(
        self,
        waypoints: FloatArray,
        q0: FloatArray,
        qe: FloatArray,
        n_lift: int,
        n_enter: int,
        knots_everywhere: bool = False,
    ) -> tuple[TimeJerkTrajectory | None, float, int]:
        """The blended trajectory through ``waypoints``, with shape knots in its long
        intervals, else without, the first that is clear (None where neither is), its depth
        and the part where the first trajectory planned went deepest (:meth:`_cycle_depth`; -1
        where none could be planned)."""
        rig = self.rig
        step = np.abs(np.diff(waypoints, axis=0))
        r2r = np.max(
            rest_to_rest_time_s(step, rig.qd_max_rad_s, rig.qdd_max_rad_s2, rig.qddd_max_rad_s3),
            axis=1,
        )
        long = r2r >= _LONG_SHARE * float(np.sum(r2r))
        knots = tuple(_SHAPE_KNOTS if x or knots_everywhere else 0 for x in long.tolist())
        first_part = -1
        shapes = (knots,) if knots_everywhere else (knots, 0) if any(knots) else (0,)
        for shape in shapes:
            try:
                traj = plan(
                    cycle_problem(rig, waypoints, CYCLE_W_JERK, shape),
                    max_iterations=_MAX_ITERATIONS,
                    shape_ftol=_SHAPE_FTOL,
                )
            except PlanningError:
                continue
            depth, part = self._cycle_depth(traj, q0, qe, n_lift, n_enter)
            if depth <= TRANSITION_PENETRATION_M - _BLEND_MARGIN_M:
                return traj, depth, first_part if first_part >= 0 else part
            if first_part < 0:
                first_part = part
        return None, math.inf, first_part

    def _cycle_depth(
        self,
        traj: TimeJerkTrajectory,
        q0: FloatArray,
        qe: FloatArray,
        n_lift: int,
        n_enter: int,
    ) -> tuple[float, int]:
        """How deep the blended ``traj`` takes the bucket into the material left beyond its
        allowances (m; see the module), ``inf`` where the tip comes nearer the ground than
        :data:`_GROUND_CLEAR_M` outside the trench; and the part where it is deepest: 0 up to
        the lift's top (its ``n_lift``-th corner; the first corner where it has none), 1 the
        first half from there to the pose above the entry (:data:`_EARLY`), 2 the second
        half, 3 the enter (the last ``n_enter`` moves, from the pose above the entry)."""
        surface = self.surface
        mover = self.planner.mover
        t_wp = traj.waypoint_times_s
        t2, t_end = float(t_wp[-1 - n_enter]), traj.duration_s
        t1 = min(float(t_wp[max(n_lift, 1)]), t2)
        # No point of the bucket moves faster than the joints' peak speeds allow.
        speed = float(traj.limit_check().velocity_peak_rad_s @ mover.radius_m)

        def times(a: float, b: float) -> FloatArray:
            n = min(max(math.ceil((b - a) * speed / _COARSE_STEP_M) + 1, 2), 200_000)
            return np.linspace(a, b, n)

        def poses(t: FloatArray) -> FloatArray:
            out: FloatArray = traj.sample(t)
            return out

        allow, exact = self._entry_allowance(qe, surface)
        depths = [self._depth_along(poses, times(0.0, t1), *self._carry(q0, surface))]
        if t2 > t1:
            for a, b in ((t1, 0.5 * (t1 + t2)), (0.5 * (t1 + t2), t2)):
                middle = times(a, b)
                depth = self._depth_along(poses, middle, surface, None)
                depths.append(depth if self._ground_clear(poses(middle)) else math.inf)
        else:
            depths += [0.0, 0.0]
        enter = times(max(t1, t2), t_end)
        depths.append(self._depth_along(poses, enter, surface, allow, exact))
        part = int(np.argmax(depths))
        return float(depths[part]), part

    def _ground_clear(self, q: FloatArray) -> bool:
        """Whether the tip of every pose ``(n, 3)`` outside the trench's top edges is at least
        :data:`_GROUND_CLEAR_M` (scaled) above the ground."""
        x, y = self.planner.mover.arm.tip_xy(q)
        xf = self.task.start_x_m
        xn = xf - self.task.length_m
        x = x + self.machine_x
        outside = (x < xn) | (x > xf)
        low = y < self.ground_y + _GROUND_CLEAR_M * self.planner.scale
        return not bool(np.any(outside & low))

    def _fallback(
        self,
        q0: FloatArray,
        qe: FloatArray,
        lift: tuple[Transition, ...] | None,
        above: tuple[FloatArray, Transition] | None,
        dumps: FloatArray,
        dump: bool,
        after_dig: bool,
    ) -> Cycle:
        """The cycle as rest-to-rest moves (see the module)."""
        moves: list[Transition] | None = None
        if lift is not None and above is not None and (dumps.shape[0] or not dump):
            q_above, enter = above
            moves = list(lift)
            q = np.asarray(lift[-1].q_to_rad) if lift else q0
            if dump:
                rig = self.rig
                head = [q0, *(np.asarray(m.q_to_rad) for m in lift)]
                corners = np.array([[*head, d, q_above, qe] for d in dumps])
                limits = (rig.qd_max_rad_s, rig.qdd_max_rad_s2, rig.qddd_max_rad_s3)
                d0 = dumps[int(np.argmin(reversal_bound_s(corners, *limits)))]
                under = (self.surface, None) if lift else self._carry(q0, self.surface)
                moves.append(self._checked(TransitionKind.DUMP, q, d0, *under))
                q = d0
            moves.append(self._checked(TransitionKind.APPROACH, q, q_above, self.surface))
            moves.append(enter)
            if not all(_clear((m,)) for m in moves):
                moves = None
        if moves is None:
            home = np.asarray(self.planner.home_pose_rad, dtype=np.float64)
            out = self._plan_exit(q0, self.surface, home) if dump else ()
            moves = [*out, *self._plan_entry(home if dump else q0, qe, self.surface)]
        rig = self.rig
        waypoints = [q0, *(np.asarray(m.q_to_rad) for m in moves)]
        return Cycle(
            waypoints_rad=tuple(_triple(q) for q in waypoints),
            kinds=tuple(m.kind for m in moves),
            piece_durations_s=(),
            shape_knots=(),
            shape_positions_rad=(),
            w_jerk=CYCLE_W_JERK,
            moves=tuple(moves),
            duration_s=sum(m.duration_s for m in moves),
            bound_s=float(
                reversal_bound_s(
                    np.asarray(waypoints), rig.qd_max_rad_s, rig.qdd_max_rad_s2, rig.qddd_max_rad_s3
                )
            ),
            machine_x_m=self.machine_x,
            penetration_m=max(m.penetration_m for m in moves),
            after_dig=after_dig,
        )


def _lift_and_enter(kinds: Sequence[TransitionKind]) -> tuple[int, int]:
    """The moves a cycle's lift takes (those of ``kinds`` before the first that is not a
    lift) and its enter takes (those after the last that is not an enter)."""
    n_lift = sum(1 for _ in itertools.takewhile(lambda k: k is TransitionKind.LIFT_OUT, kinds))
    n_enter = sum(
        1 for _ in itertools.takewhile(lambda k: k is TransitionKind.ENTER, reversed(kinds))
    )
    return n_lift, n_enter


def _clear(moves: tuple[Transition, ...]) -> bool:
    return all(m.penetration_m <= TRANSITION_PENETRATION_M for m in moves)


def _triple(q: Any) -> tuple[float, float, float]:
    return (float(q[0]), float(q[1]), float(q[2]))


def _distinct(
    corners: FloatArray, kinds: list[TransitionKind]
) -> tuple[FloatArray, list[TransitionKind]]:
    """``corners`` ``(n + 1, 3)`` without a corner equal to the one before it (the generator
    refuses repeats), with the kind of each remaining move."""
    keep = [0]
    out_kinds: list[TransitionKind] = []
    for i in range(1, corners.shape[0]):
        if np.all(np.abs(corners[i] - corners[keep[-1]]) <= _SAME_POSE_RAD):
            continue
        keep.append(i)
        out_kinds.append(kinds[i - 1])
    out: FloatArray = corners[keep]
    return out, out_kinds
