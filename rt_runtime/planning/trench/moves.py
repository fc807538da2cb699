"""The moves between digs as rest-to-rest ruckig moves: lift out, dump, approach, enter (never
intermediate waypoints: the PyPI build sends those to a cloud service), whose poses come from the
material left, each checked on the whole bucket and refused where it would plough. They are
the corners of a blended cycle (``cycles``) and its fallback where the blend is not clear."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike

from rt_runtime import kinematics
from rt_runtime.errors import PlanningError
from rt_runtime.planning.trench.geometry import (
    GRID_STEP_M,
    FloatArray,
    _depth_below,
    _max_table,
    _range_max,
)
from rt_runtime.planning.trench.material import MaterialMixin
from rt_runtime.planning.trench.plan import PlannedDig, Transition, TransitionKind
from rt_runtime.planning.trench.state import _stage

# Transition poses (scale model, m), assumed: Yao gives none. The bucket dumps in the rig's
# spoil zone (cycles.py). The poses between are chosen from the surface
# (TrenchSession.exit_transitions and entry_transitions): the lift pose puts the whole bucket
# _LIFT_CLEAR_M above the material under it, the approach pose backs off from the entry by the
# first of _APPROACH_M that puts the bucket _LIFT_CLEAR_M above the material.
_LIFT_CLEAR_M = 0.02

# The last two for the domain's deepest trenches (0.25-0.3 m): a bucket entering the bottom at
# a steep far wall's foot overhangs the wall's slope and clears the ground only ~0.29 m above
# its entry, so no approach was clear and the far corner's columns were refused.
_APPROACH_M = (0.03, 0.05, 0.08, 0.12, 0.18, 0.25, 0.35, 0.45)

#: Deepest a transition may take the bucket into the material left (m): every move is checked
#: on its samples and refused beyond it (:meth:`TrenchSession.exit_transitions`).
TRANSITION_PENETRATION_M = 0.005

# Sampling of a move's check (m, every rig; TrenchSession._move_depth): from one sample to the
# next no point of the bucket outline moves farther than _MOVE_STEP_M where the bucket is near
# the material, _COARSE_STEP_M where it is not; the outline's points lie _OUTLINE_STEP_M apart.
_MOVE_STEP_M = 0.002

_COARSE_STEP_M = 0.01

# Outline points asked of the polygon at once (:meth:`MovesMixin._polygon_depth_beyond`).
_POLYGON_CHUNK = 256

# Depth into the material beyond which a move's check stops measuring (m): it is refused anyway.
_DEPTH_CAP_M = 0.05

# Lift heights a transition tries (TrenchSession._lift_heights).
_N_LIFT_HEIGHTS = 4

# Transitions kept for when they are asked for again (a dig's, its next dig's).
_N_CACHED_MOVES = 16


def _safe_ik(arm: kinematics.FastArm, x: float, y: float, attitude: float) -> FloatArray:
    """IK of a transition pose, trying attitudes nearer the middle when the first fails."""
    for att in (attitude, attitude + 0.3, attitude - 0.3, -math.pi / 2):
        q = arm.ik(x, y, att)
        if q is not None:
            return np.asarray(q)
    raise PlanningError(f"no reachable transition pose at x={x:.3f} m, y={y:.3f} m")


class MovesMixin(MaterialMixin):
    """The moves between a session's digs (see the module)."""

    def exit_transitions(
        self, q_from_rad: ArrayLike, *, after: PlannedDig | None = None
    ) -> tuple[Transition, ...]:
        """Lift out of the material and go to the home pose (:attr:`TrenchPlanner.home_pose_rad`,
        in the spoil zone), from any pose (arm frame): the moves after the last dig.

        ``lift_out`` goes straight up, the tip's x and attitude kept, until the whole bucket is
        :data:`_LIFT_CLEAR_M` above the material under it, or higher where the way to the dump
        pose needs it (the lowest clear one of :meth:`_lift_heights`: on A-D the lowest is
        always clear and a higher lift only adds time); a lift whose joint-space move strays
        from the vertical into the material is made in pieces through poses on it. ``dump``
        goes from there to the home pose. A pose already clear of the material goes there
        without a lift. The executor streams these after a dig no other dig follows, and they
        are the fallback of a cycle from a measured pose (:meth:`cycle`).

        Every move is checked on its samples (:meth:`_checked`) against the material as it is
        when it runs: the current material, or with ``after`` the material the pending dig
        ``after`` leaves (its planned path cut; the executor plans a dig's exit moves before it
        runs). The first move starts where the bucket is, possibly in the material (a dig's
        curled bucket hangs below its tip's path; a stopped dig leaves it deep): it may cross
        the material straight above the bucket's outline at its start, which the bucket carries
        out going straight up, and nothing else.

        Args:
            q_from_rad: Start pose ``(3,)``, e.g. a dig's exit or the measured pose.
            after: The pending dig the moves follow (None: they run now).

        Returns:
            The moves in order: ``lift_out`` (none, one or several) then ``dump``; the same
            moves :meth:`next_dig` puts before the next dig.

        Raises:
            PlanningError: No lift pose is reachable, ruckig cannot plan a move, or every
                candidate has a move deeper than :data:`TRANSITION_PENETRATION_M` in the
                material (the message names the move and the depth).
        """
        q0 = np.asarray(q_from_rad, dtype=np.float64)
        surface = self.surface if after is None else self._surface_after(after)
        key = ("exit", *q0.tolist(), self.machine_x)
        moves = self._cached(key, surface)
        if moves is None:
            moves = self._plan_exit(q0, surface, np.asarray(self.planner.home_pose_rad))
            self._remember(key, surface, moves)
        return moves

    def entry_transitions(self, dig: PlannedDig, q_from_rad: ArrayLike) -> tuple[Transition, ...]:
        """Approach ``dig``'s entry from ``q_from_rad`` (a dump pose) and enter the material.

        ``enter`` lowers the bucket straight down into the entry pose, or where no such move is
        clear slides it in along its own axis (pin to tip), from an approach pose backed off by
        the first of :data:`_APPROACH_M` (scaled) that puts the whole bucket
        :data:`_LIFT_CLEAR_M` above the material and whose moves are clear; ``approach`` goes
        there from ``q_from_rad``. Straight down first: on A-D it was clear at every entry and
        as fast or faster than along the axis. Checked against the material before the dig.
        The dig starts at its entry, on the surface or (a profile pass into a corner, a layer)
        below it, and the bucket's back may lie in a wall there: each point of the bucket may
        go as deep during ``enter`` as it is at the entry pose, plus the tolerance.

        Returns:
            ``(approach, enter)``.

        Raises:
            PlanningError: No reachable approach pose, ruckig cannot plan a move, or every
                candidate has a move deeper than :data:`TRANSITION_PENETRATION_M` in the
                material (the message names the move and the depth).
        """
        q_from = np.asarray(q_from_rad, dtype=np.float64)
        q_entry = np.asarray(dig.problem.q_start_rad, dtype=np.float64)
        key = ("entry", *q_from.tolist(), *q_entry.tolist(), self.machine_x)
        moves = self._cached(key, self.surface)
        if moves is None:
            moves = self._plan_entry(q_from, q_entry, self.surface)
            self._remember(key, self.surface, moves)
        return moves

    @_stage("transitions")
    def _check_transition_poses(self, dig: PlannedDig) -> None:
        """PlanningError unless the moves around ``dig`` can be made clear: into its entry from
        the home pose, and out of its exit over the material it leaves (a layer pass may end
        too near the machine to lift the bucket straight up, and that was only found when the
        next dig was planned, as an error). These are the cycles' last fallback
        (:meth:`cycle`); the moves are kept for when they are asked for."""
        self.entry_transitions(dig, self.planner.home_pose_rad)
        self.exit_transitions(dig.problem.q_end_rad, after=dig)

    def _cached(self, key: tuple[Any, ...], surface: FloatArray) -> tuple[Transition, ...] | None:
        """The moves planned for ``key`` on this very height field, if they are kept."""
        hit = self._moves.get(key)
        if hit is not None and np.array_equal(hit[0], surface):
            return hit[1]
        return None

    def _remember(
        self, key: tuple[Any, ...], surface: FloatArray, moves: tuple[Transition, ...]
    ) -> None:
        """Keep ``moves`` (planned for ``key`` on ``surface``), the oldest dropped."""
        self._moves[key] = (surface.copy(), moves)
        while len(self._moves) > _N_CACHED_MOVES:
            del self._moves[next(iter(self._moves))]

    def _surface_after(self, dig: PlannedDig) -> FloatArray:
        """The height field once ``dig``'s planned path has cut it."""
        planned = self._planned_region
        if planned is not None and planned[0] is dig.tip_path_m:
            env = planned[1]
        else:
            env = self._envelope(np.asarray(dig.tip_path_m, dtype=np.float64), self.grid)
        after: FloatArray = np.minimum(self.surface, env)
        return after

    def _carry(self, q0: FloatArray, surface: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``surface`` without the material straight above the bucket's outline at ``q0``: what
        the bucket carries out going straight up (the first move from a pose may cross it),
        with the allowance of each outline point ``(m,)`` (m): its depth at ``q0``.

        The height field is linear between its grid columns, so the carried column's side
        lies between the outline's last column and the next, and the outline's end beyond its
        last column can measure deep at ``q0`` itself: a bucket entering tip first, its steep
        edge ending between two columns, measures several mm. Each point may go that deep, as
        the enter's allowance; it is 0 for all others. A field that lowered the next column
        too would make the side up to a grid step wider than the bucket, and a move straying
        sideways out of it would measure up to a grid step shallower than it is."""
        bx, by = self.planner.mover.bucket_xy(q0)
        start = np.stack([bx + self.machine_x, by], axis=1)
        carry: FloatArray = np.minimum(surface, self._envelope(start, self.grid))
        return carry, self._bucket_depth(q0[None], carry, np.inf)[0]

    def _plan_exit(
        self, q0: FloatArray, surface: FloatArray, dump: FloatArray
    ) -> tuple[Transition, ...]:
        """:meth:`exit_transitions` on the height field ``surface``, to the pose ``dump``."""
        x0, y0, z0 = self.planner.mover.arm.tip(q0)
        carry = self._carry(q0, surface)
        refused: list[Transition] = []
        for lift in self._lifts(q0, surface, carry):
            moves = list(lift)
            q_top = np.asarray(lift[-1].q_to_rad) if lift else q0
            under = (surface, None) if moves else carry
            moves.append(self._checked(TransitionKind.DUMP, q_top, dump, *under))
            bad = [m for m in moves if m.penetration_m > TRANSITION_PENETRATION_M]
            if bad:
                refused.append(max(bad, key=lambda m: m.penetration_m))
                continue
            return tuple(moves)
        raise PlanningError(
            self._refusal("exit", (x0 + self.machine_x, y0, z0), refused, "no lift pose")
        )

    def _lifts(
        self, q0: FloatArray, surface: FloatArray, carry: tuple[FloatArray, FloatArray]
    ) -> Iterator[tuple[Transition, ...]]:
        """The ``lift_out`` moves from ``q0`` to each of :meth:`_lift_heights`, lowest first,
        that are reachable (none where ``q0`` is the height: the pose is clear already); a lift
        that is not clear comes too (its check refuses it where it is used)."""
        y0 = self.planner.mover.arm.tip(q0)[1]
        for y_lift in self._lift_heights(q0, surface):
            if y_lift <= y0 + 1e-6:
                yield ()
                continue
            lift = self._lift(q0, y_lift, carry)
            if lift is not None:
                yield lift

    def _lift_heights(self, q0: FloatArray, surface: FloatArray) -> list[float]:
        """Candidate tip heights of the lift from ``q0`` (arm frame, ascending): the whole
        bucket :data:`_LIFT_CLEAR_M` above the material within that distance of it, then
        higher in steps of twice that; the start's own height first where it is higher."""
        mover = self.planner.mover
        s = self.planner.scale
        clear = _LIFT_CLEAR_M * s
        y0 = mover.arm.tip(q0)[1]
        bx, by = mover.bucket_xy(q0)
        k = math.ceil(clear / GRID_STEP_M)
        i = np.rint((bx + self.machine_x - self.grid[0]) / GRID_STEP_M).astype(np.int64)
        cols = np.clip(i[:, None] + np.arange(-k, k + 1), 0, self.grid.shape[0] - 1)
        # Heights over the tip of the outline's points at the start attitude.
        need = float(np.max(np.max(surface[cols], axis=1) - (by - y0))) + clear
        return sorted({max(need + 2.0 * clear * j, y0) for j in range(_N_LIFT_HEIGHTS)})

    def _lift(
        self, q0: FloatArray, y_lift: float, carry: tuple[FloatArray, FloatArray]
    ) -> tuple[Transition, ...] | None:
        """``lift_out`` from ``q0`` straight up to tip height ``y_lift``: one move, or where it
        strays from the vertical into the material, pieces through poses on the vertical
        (the fewest that are clear; else the one move, to be refused). None: out of reach."""
        arm = self.planner.mover.arm
        x0, y0, z0 = arm.tip(q0)
        first: tuple[Transition, ...] | None = None
        for pieces in (1, 2, 3, 5, 8):
            poses = [q0]
            for y in np.linspace(y0, y_lift, pieces + 1)[1:].tolist():
                q = arm.ik(x0, y, z0)
                if q is None:
                    try:
                        q = tuple(_safe_ik(arm, x0, y, z0))
                    except PlanningError:
                        return first
                poses.append(np.asarray(q, dtype=np.float64))
            moves = tuple(
                self._checked(TransitionKind.LIFT_OUT, a, b, *carry)
                for a, b in itertools.pairwise(poses)
            )
            if first is None:
                first = moves
            if all(m.penetration_m <= TRANSITION_PENETRATION_M for m in moves):
                return moves
        return first

    def _plan_entry(
        self, q_from: FloatArray, q_entry: FloatArray, surface: FloatArray
    ) -> tuple[Transition, ...]:
        """:meth:`entry_transitions` on the height field ``surface``."""
        xe, ye, ze = self.planner.mover.arm.tip(q_entry)
        refused: list[Transition] = []
        for q_above, enter in self._entries(q_entry, surface, refused):
            approach = self._checked(TransitionKind.APPROACH, q_from, q_above, surface)
            if approach.penetration_m > TRANSITION_PENETRATION_M:
                refused.append(approach)
                continue
            return (approach, enter)
        raise PlanningError(
            self._refusal("entry", (xe + self.machine_x, ye, ze), refused, "no approach pose")
        )

    def _entry_allowance(
        self, q_entry: FloatArray, surface: FloatArray
    ) -> tuple[FloatArray, bool]:
        """How deep each point of the bucket outline ``(m,)`` may go on the enter into a dig
        (m): its depth at the entry pose ``q_entry`` on ``surface``; and whether the enter is
        measured on the material's polygon instead (with the allowance from it).

        A height field holds one surface a column, so a slot cut down a steep wall narrower
        than the bucket measures its sides deeper than they are (5.6 mm against 1.1 mm at a
        tip entering such a slot), and an allowance from it let the enter go 8.7 mm into the
        material. Where ``surface`` is the current height field and any point's depth on it
        exceeds that on the polygon by more than half a grid step, the enter is measured on
        the polygon (:meth:`_polygon_depth`)."""
        allow: FloatArray = self._bucket_depth(q_entry[None], surface, np.inf)[0]
        if surface is not self.surface:
            return allow, False
        exact = self._polygon_depth(q_entry[None])[0]
        if np.all(allow - exact <= 0.5 * GRID_STEP_M):
            return allow, False
        return exact, True

    def _polygon_depth(self, q: FloatArray) -> FloatArray:
        """How deep each point of the bucket outline is in the material's polygon, poses
        ``(n, 3)`` -> ``(n, m)`` (m: :meth:`_polygon_depth_at`)."""
        bx, by = self.planner.mover.bucket_xy(q)
        return self._polygon_depth_at(bx + self.machine_x, by)

    def _polygon_depth_at(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """How deep points (work-site frame, any shape) are in the material's polygon (m: the
        distance to its boundary, 0 outside)."""
        xf, yf = np.ravel(x), np.ravel(y)
        inside = shapely.contains_xy(self.material, xf, yf)
        depth = np.zeros(xf.shape)
        if np.any(inside):
            points = shapely.points(xf[inside], yf[inside])
            depth[inside] = shapely.distance(points, self.material.boundary)
        return depth.reshape(np.shape(x))

    def _entries(
        self, q_entry: FloatArray, surface: FloatArray, refused: list[Transition]
    ) -> Iterator[tuple[FloatArray, Transition]]:
        """The approach poses above ``q_entry`` in the order :meth:`entry_transitions` tries
        them, each with its clear ``enter`` move (refused enters go to ``refused``)."""
        mover = self.planner.mover
        arm = mover.arm
        s = self.planner.scale
        xe, ye, ze = arm.tip(q_entry)
        allow, exact = self._entry_allowance(q_entry, surface)
        clear = _LIFT_CLEAR_M * s
        # The enter's direction of travel: straight down, else along the bucket's axis.
        for ux, uy in ((0.0, -1.0), (math.cos(ze), math.sin(ze))):
            for d in _APPROACH_M:
                qa = arm.ik(xe - d * s * ux, ye - d * s * uy, ze)
                if qa is None:
                    continue
                q_above = np.asarray(qa, dtype=np.float64)
                bx, by = mover.bucket_xy(q_above)
                if np.any(by < np.interp(bx + self.machine_x, self.grid, surface) + clear):
                    continue
                enter = self._checked(
                    TransitionKind.ENTER, q_above, q_entry, surface, allow, exact
                )
                if enter.penetration_m > TRANSITION_PENETRATION_M:
                    refused.append(enter)
                    continue
                yield q_above, enter

    def _refusal(
        self, what: str, pose: tuple[float, float, float], refused: list[Transition], none: str
    ) -> str:
        """The message of a refused exit or entry: the least deep refused move, or ``none``."""
        where = f"x={pose[0]:.3f} m, y={pose[1]:.3f} m, attitude {math.degrees(pose[2]):.1f} deg"
        if not refused:
            return f"no clear {what} moves at {where}: {none} is reachable and clear"
        m = min(refused, key=lambda t: t.penetration_m)
        depth = f"{m.penetration_m * 1e3:.1f} mm"
        if m.penetration_m >= _DEPTH_CAP_M:
            depth = f"{_DEPTH_CAP_M * 1e3:.0f} mm or more"
        return (
            f"no clear {what} moves at {where}: the {m.kind.label} move goes {depth} into the "
            f"material at best (limit {TRANSITION_PENETRATION_M * 1e3:.0f} mm)"
        )

    def _checked(
        self,
        kind: TransitionKind,
        qa: FloatArray,
        qb: FloatArray,
        surface: FloatArray,
        allow: FloatArray | None = None,
        exact: bool = False,
    ) -> Transition:
        """The ruckig move ``qa -> qb`` with its penetration (:meth:`_move_depth`)."""
        traj = self.planner.mover.move(qa, qb)
        return Transition(
            kind=kind,
            q_from_rad=(float(qa[0]), float(qa[1]), float(qa[2])),
            q_to_rad=(float(qb[0]), float(qb[1]), float(qb[2])),
            duration_s=float(traj.duration),
            machine_x_m=self.machine_x,
            penetration_m=self._move_depth(traj, qa, qb, surface, allow, exact),
        )

    def _move_depth(
        self,
        traj: Any,
        qa: FloatArray,
        qb: FloatArray,
        surface: FloatArray,
        allow: FloatArray | None,
        exact: bool = False,
    ) -> float:
        """The deepest any point of the bucket outline goes into the material under
        ``surface`` (:func:`_depth_below`) on the move ``traj`` from ``qa`` to ``qb``, less
        ``allow`` ``(m,)`` per outline point where given (m, >= 0): :meth:`_depth_along` on
        samples that no point of the bucket moves :data:`_COARSE_STEP_M` between (``exact``:
        on the material's polygon)."""
        tables = self._piece_tables(traj)
        times = np.linspace(
            0.0, float(traj.duration), self.planner.mover.n_samples(qa, qb, _COARSE_STEP_M)
        )
        return self._depth_along(
            lambda t: self._move_poses(traj, tables, t), times, surface, allow, exact
        )

    def _depth_along(
        self,
        poses_at: Callable[[FloatArray], FloatArray],
        times: FloatArray,
        surface: FloatArray,
        allow: FloatArray | None,
        exact: bool = False,
    ) -> float:
        """The deepest any point of the bucket outline goes into the material under
        ``surface`` (:func:`_depth_below`) along a motion whose poses at times ``(n,)`` are
        ``poses_at(times)`` ``(n, 3)``, less ``allow`` ``(m,)`` per outline point where given
        (m, >= 0). ``times`` are coarse samples: no point of the bucket moves farther than
        :data:`_COARSE_STEP_M` from one to the next.

        Sampled where the bucket comes near the material: a stretch between coarse samples
        where the bucket's bounding box stays :data:`_COARSE_STEP_M` above the highest material
        under it (that far to either side) cannot touch it; the rest is sampled every
        :data:`_MOVE_STEP_M` of the bucket's travel with the whole outline. Between samples and
        outline points a point can be deeper by at most half their spacing (a point's depth
        changes no faster than the point moves). Depths beyond :data:`_DEPTH_CAP_M` (past
        ``allow``) count as that. ``exact``: the fine samples' depths on the material's
        polygon (:meth:`_polygon_depth_beyond`; ``surface`` the current height field, whose
        surface lies on or above the polygon's, so the coarse samples it clears are clear).
        """
        mover = self.planner.mover
        h = GRID_STEP_M
        last = self.grid.shape[0] - 1
        reach = _COARSE_STEP_M
        x, y = mover.bucket_xy(poses_at(times), corners=True)
        x = x + self.machine_x
        i0 = np.clip(np.floor((np.min(x, axis=1) - reach - self.grid[0]) / h), 0, last)
        i1 = np.clip(np.ceil((np.max(x, axis=1) + reach - self.grid[0]) / h), 0, last)
        if not np.array_equal(self._max_tables[0], surface):
            self._max_tables = (surface.copy(), _max_table(surface))
        top = _range_max(self._max_tables[1], i0.astype(np.int64), i1.astype(np.int64))
        far = np.min(y, axis=1) >= top + reach
        near = np.flatnonzero(~(far[:-1] | far[1:]))
        if near.size == 0:
            return 0.0
        k = math.ceil(reach / _MOVE_STEP_M)
        frac = np.arange(k + 1) / k
        fine = np.unique(times[near, None] + (times[near + 1] - times[near])[:, None] * frac)
        poses = poses_at(fine)
        if allow is None:
            depth = self._bucket_depth(poses, surface)
        else:
            depth = self._bucket_depth(poses, surface, allow + _DEPTH_CAP_M)
            depth -= allow
        if exact:
            return self._polygon_depth_beyond(poses, depth, allow)
        return max(0.0, float(np.max(depth)))

    def _polygon_depth_beyond(
        self, poses: FloatArray, field: FloatArray, allow: FloatArray | None
    ) -> float:
        """The deepest any point of the bucket outline at ``poses`` ``(n, 3)`` goes into the
        material's polygon less ``allow`` ``(m,)`` (m, >= 0), given each point's depth on the
        current height field less ``allow`` (``field``, ``(n, m)``, as :meth:`_depth_along`
        caps it). No point is deeper in the polygon than on the field by a grid step (the
        field's surface lies on or above the polygon's; its depths are sought on the grid's
        columns): the polygon is asked for the points in the order of that bound, in chunks,
        until no point left can be deeper than the deepest found (an enter into a slot had
        some 25,000 points near its allowance, 0.25 s a move asked all at once)."""
        bound = field.ravel() + GRID_STEP_M
        order = np.argsort(-bound, kind="stable")
        order = order[bound[order] > 0.0]
        bx, by = self.planner.mover.bucket_xy(poses)
        x, y = (bx + self.machine_x).ravel(), by.ravel()
        less = np.zeros(x.shape) if allow is None else np.broadcast_to(allow, bx.shape).ravel()
        deepest = 0.0
        for k in range(0, order.size, _POLYGON_CHUNK):
            idx = order[k : k + _POLYGON_CHUNK]
            if bound[idx[0]] <= deepest:
                break
            found = self._polygon_depth_at(x[idx], y[idx]) - less[idx]
            deepest = max(deepest, float(np.max(found)))
        return deepest

    def _piece_tables(self, traj: Any) -> FloatArray | None:
        """A rest-to-rest move's constant-jerk pieces as the C geometry's ``move_poses`` takes
        them (``(3, 5, 7)``: per joint the durations, jerk, and the acceleration, velocity and
        position where each piece starts); None without the C geometry or for a profile
        :meth:`_Mover.poses` evaluates through ruckig's ``at_time``."""
        if self.planner.geo_module is None:
            return None
        profiles = traj.profiles[0]
        if (
            len(traj.profiles) != 1
            or len(profiles) != 3
            or any(p.brake.duration > 0.0 or p.accel.duration > 0.0 for p in profiles)
        ):
            return None
        return np.array([[p.t, p.j, p.a[:7], p.v[:7], p.p[:7]] for p in profiles])

    def _move_poses(self, traj: Any, tables: FloatArray | None, times: FloatArray) -> FloatArray:
        """:meth:`_Mover.poses` of ``traj`` at ``times``; in C from its ``tables``
        (:meth:`_piece_tables`) where given, the same formulas."""
        if tables is None:
            return self.planner.mover.poses(traj, times)
        out = np.empty((times.shape[0], 3))
        self.planner.geo_module.move_poses(
            tables, np.ascontiguousarray(times, dtype=np.float64), out
        )
        return out

    def _bucket_depth(
        self, q: FloatArray, surface: FloatArray, cap_m: ArrayLike = _DEPTH_CAP_M
    ) -> FloatArray:
        """How deep each point of the bucket outline is in the material, poses ``(n, 3)`` ->
        ``(n, m)`` (m, up to ``cap_m``, :func:`_depth_below`; in C with the C geometry, the
        same formulas)."""
        mover = self.planner.mover
        geo = self.planner.geo_module
        if geo is None:
            x, y = mover.bucket_xy(q)
            return _depth_below(self.grid, surface, x + self.machine_x, y, cap_m)
        out = np.empty((q.shape[0], mover.outline.shape[0]))
        geo.bucket_depth(
            np.ascontiguousarray(q, dtype=np.float64),
            mover.arm.lengths,
            mover.outline,
            float(self.machine_x),
            self.grid,
            np.ascontiguousarray(surface, dtype=np.float64),
            np.ascontiguousarray(np.broadcast_to(cap_m, mover.outline.shape[:1]), dtype=np.float64),
            out,
        )
        return out
