"""A trench plan: its digs, the moves between digs (cycles) and travel moves (frozen
dataclasses), its honest status against the goals, and its report (``excavator-rt plan
--json``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
from shapely.geometry import Polygon

from rt_runtime.errors import PlanningError
from rt_runtime.planning.oneshot import DigType, Problem
from rt_runtime.planning.trench.geometry import OVERDIG_LIMIT_M, FloatArray
from rt_runtime.planning.trench.motion import joint_move
from rt_runtime.planning.trench.task import YAO_FIG14, TrenchTask
from rt_runtime.planning.verify import (
    VerifyResult,
)
from rt_runtime.rig import Rig
from rt_runtime.trajectory.timejerk import TimeJerkProblem, TimeJerkTrajectory, interpolate


@dataclass(frozen=True, slots=True)
class PlannedDig:
    """One verified dig of a trench plan.

    Attributes:
        index: 0-based position in the plan.
        problem: Entry/exit poses (arm frame at the machine's position) and H.
        a6, T_s: The verified sextic.
        machine_x_m: The machine's travel from its first position when this dig runs.
        tip_path_m: Planned tip path in the work-site frame, ``(n, 2)``.
        volume_m3: Real material the dig removes (polygon accounting, planned path).
        design_volume_m3: Of that, the part inside the design.
        predicted_volume_m3: V_p of the one-shot model (flat surface at H), bounded by the
            verifier.
        energy_j, theta_p_rad: W_E and the initial digging angle of the verified plan (of
            a joined dig, which has no entry, the angle of its first direction, not bounded).
        overdig_m: Deepest cut below the design profile (0 if none).
        plan_us: Time the one-shot planner took for this dig (excluding screening).
        select_us: Time of this dig's candidate screening and selection.
        planner: ``pinn`` or ``pso``; status: how the one-shot planner got the plan
            (``filled``: the network's path filled on the material left; ``profile``: a
            full dig along the design's outline; ``profile_pass``: a finishing pass).
        evaluation: The verifier's row for the plan.
        finishing: Whether the dig is a finishing pass (exempt from the fill rule).
        section: The section of the trench the dig belongs to (0 at the far end).
        joined: The dig continues the bucket of the dig before it: it starts at that dig's
            exit, at rest in the material, with no moves between them. A dig and the digs
            joined to it are one bucket (one fill, one dump): they fill the band together,
            or are one finishing pass together. Every hard limit holds on it as on any dig;
            the dig types' theta_p ranges, which bound an entry into the ground, do not
            apply (except to a carried dig).
        carried: A joined dig that enters the ground at its own entry: the bucket of the dig
            before it, light, is carried there by a cycle without a dump (the cycle before
            it in the steps), at attitudes that hold the load. Its theta_p range applies.
        pass_window: Timed and verified in the finishing passes' time window: a finishing
            pass, or a piece of a joined dig planned as one before the dig joined to it
            filled the bucket.
    """

    index: int
    problem: Problem
    a6: tuple[float, float, float]
    T_s: float
    machine_x_m: float
    tip_path_m: FloatArray
    volume_m3: float
    design_volume_m3: float
    predicted_volume_m3: float
    energy_j: float
    theta_p_rad: float
    overdig_m: float
    plan_us: float
    select_us: float
    planner: str
    status: str
    evaluation: FloatArray = field(repr=False)
    finishing: bool = False
    section: int = 0
    joined: bool = False
    pass_window: bool = False
    carried: bool = False

    @property
    def dig_type(self) -> DigType:
        """Downward or backward."""
        return self.problem.dig_type

    @property
    def verification(self) -> VerifyResult:
        """The verifier's result for the plan."""
        return VerifyResult.from_row(self.evaluation)

    def trajectory(self) -> Any:
        """The joint trajectory (:class:`rt_runtime.trajectory.sextic.SexticTrajectory`)."""
        from rt_runtime.trajectory.sextic import SexticTrajectory

        return SexticTrajectory(
            np.asarray(self.problem.q_start_rad),
            np.asarray(self.problem.q_end_rad),
            np.asarray(self.a6),
            self.T_s,
        )


class TransitionKind(IntEnum):
    """The part of a dig cycle a transition belongs to (JSON: the lower-case name)."""

    LIFT_OUT = 0
    DUMP = 1
    APPROACH = 2
    ENTER = 3

    @property
    def label(self) -> str:
        """The JSON spelling: ``lift_out``, ``dump``, ``approach``, ``enter``."""
        return self.name.lower()

    @classmethod
    def parse(cls, text: str) -> TransitionKind:
        """The kind spelt ``text``.

        Raises:
            ValueError: Not a kind (names the allowed ones).
        """
        try:
            return cls[str(text).upper()]
        except KeyError:
            allowed = ", ".join(k.label for k in cls)
            raise ValueError(f"transition kind {text!r}; allowed: {allowed}") from None


@dataclass(frozen=True, slots=True)
class Transition:
    """A state-to-state joint motion between digs (ruckig, rest to rest, no waypoints).

    Attributes:
        kind: :class:`TransitionKind` (lift-out, dump, approach or enter): the phase of the
            cycle it is part of (a phase may take several moves: a lift in pieces).
        q_from_rad, q_to_rad: End poses (arm frame).
        duration_s: Time-optimal duration within the joint velocity/acceleration/jerk limits.
        machine_x_m: The machine's travel from its first position.
        penetration_m: How far the bucket (its tip, bottom and back plate) goes into the
            material left, as a distance, beyond what the move is allowed at a dig's pose
            (:meth:`TrenchSession.exit_transitions`, :meth:`TrenchSession.entry_transitions`);
            0 if clear, at most :data:`TRANSITION_PENETRATION_M` in a plan.
    """

    kind: TransitionKind
    q_from_rad: tuple[float, float, float]
    q_to_rad: tuple[float, float, float]
    duration_s: float
    machine_x_m: float
    penetration_m: float

    def trajectory(self, rig: Rig) -> Any:
        """The ruckig trajectory (``ruckig.Trajectory``), recomputed from the end poses."""
        return joint_move(rig, self.q_from_rad, self.q_to_rad)[0]


@dataclass(frozen=True, slots=True)
class Cycle:
    """The moves into a dig from where the arm is: after a dig (lift out, dump, approach,
    enter; no dump into a carried dig) or from the home pose (approach, enter), through their
    corners.

    Blended (:attr:`piece_durations_s` given): one minimum time-jerk trajectory through the
    corners (Zhao eq 3, :mod:`rt_runtime.trajectory.timejerk`) at rest only at both ends, within
    the rig's joint velocity, acceleration and jerk limits and ranges; where a blend from the
    start was not clear but one from the lift's top is, the lift's rest-to-rest moves
    :attr:`moves` come first and the blend starts at rest at the lift's top (waypoint
    ``len(moves)``). Otherwise the rest-to-rest ruckig moves :attr:`moves` through the same
    kind of corners, where no blend was clear of the material (the cycle's fallback).

    Attributes:
        waypoints_rad: The corners in order, ``(n + 1)`` poses (arm frame): the start (a dig's
            exit, the home pose or a measured pose), the lift's poses, the dump, the pose above
            the entry, poses on the enter's line (where a blend needs them), the dig's entry.
        kinds: ``(n,)`` the phase of the move between waypoint ``i`` and ``i + 1``.
        piece_durations_s: The blended trajectory's cubic pieces (empty when not blended).
        shape_knots: ``(n,)`` the blended trajectory's shape knots in each waypoint interval.
        shape_positions_rad: Their positions (arm frame), in order.
        w_jerk: The weight of the jerk integral it was planned with (s^6/rad^2, w_time = 1).
        moves: The rest-to-rest moves: all of them where not blended; where blended, the lift's
            before the blend (usually none).
        duration_s: The cycle's move time (s), its rest-to-rest moves and blend together.
        bound_s: The time if each joint stopped only where it reverses through the same
            waypoints (:func:`rt_runtime.trajectory.timejerk.reversal_bound_s`).
        machine_x_m: The machine's travel from its first position.
        penetration_m: The deepest the bucket goes into the material left, beyond what its
            moves are allowed at the start and entry poses (at most
            :data:`TRANSITION_PENETRATION_M` in a plan).
        after_dig: It starts at the previous dig's exit (a dig cycle).
    """

    waypoints_rad: tuple[tuple[float, float, float], ...]
    kinds: tuple[TransitionKind, ...]
    piece_durations_s: tuple[float, ...]
    shape_knots: tuple[int, ...]
    shape_positions_rad: tuple[tuple[float, float, float], ...]
    w_jerk: float
    moves: tuple[Transition, ...]
    duration_s: float
    bound_s: float
    machine_x_m: float
    penetration_m: float
    after_dig: bool

    @property
    def blended(self) -> bool:
        """One trajectory through the corners (not the rest-to-rest fallback)."""
        return bool(self.piece_durations_s)

    @property
    def blend_from(self) -> int:
        """The waypoint the blended trajectory starts at (after the rest-to-rest moves)."""
        return len(self.moves)

    @property
    def waypoint_times_s(self) -> tuple[float, ...]:
        """When the cycle passes each waypoint (s from its start)."""
        ends = np.cumsum([m.duration_s for m in self.moves])
        lead = (0.0, *(float(t) for t in ends))
        if not self.blended:
            return lead
        knots = lead[-1] + np.concatenate([[0.0], np.cumsum(self.piece_durations_s)])
        kinds = TimeJerkProblem.knot_kinds_of(self.shape_knots)
        return lead[:-1] + tuple(float(knots[i]) for i, c in enumerate(kinds) if c == "W")

    def trajectory(self, rig: Rig) -> TimeJerkTrajectory:
        """The blended trajectory (:class:`~rt_runtime.trajectory.timejerk.TimeJerkTrajectory`)
        rebuilt from its corners and piece durations (one linear solve, the same numbers): from
        waypoint :attr:`blend_from` on, its time from there.

        Raises:
            PlanningError: The cycle is not blended.
        """
        if not self.blended:
            raise PlanningError("a cycle of rest-to-rest moves has no blended trajectory")
        problem = cycle_problem(
            rig, self.waypoints_rad[self.blend_from :], self.w_jerk, self.shape_knots
        )
        return interpolate(problem, self.piece_durations_s, self.shape_positions_rad or None)


def cycle_problem(
    rig: Rig, waypoints_rad: Any, w_jerk: float, shape_knots: int | tuple[int, ...] = 0
) -> TimeJerkProblem:
    """The minimum time-jerk problem of a cycle through ``waypoints_rad`` ``(n + 1, 3)``: the
    rig's joint velocity, acceleration and jerk limits and ranges, rest at both ends, the
    given shape knots."""
    return TimeJerkProblem.for_rig(
        rig,
        np.asarray(waypoints_rad, dtype=np.float64),
        jerk_limits=True,
        w_jerk=w_jerk,
        shape_knots=shape_knots,
    )


def iter_moves(steps: Any) -> list[Transition | Cycle]:
    """The moves of ``steps`` one by one: every :class:`Transition`, a blended :class:`Cycle`
    as itself (with any rest-to-rest lift before its blend) and a fallback cycle as its
    rest-to-rest moves."""
    out: list[Transition | Cycle] = []
    for st in steps:
        if isinstance(st, Transition):
            out.append(st)
        elif isinstance(st, Cycle):
            out.extend(st.moves if not st.blended else (st,))
    return out


@dataclass(frozen=True, slots=True)
class TravelMove:
    """Crawler travel through the VCU (+x away from the trench's far end is negative)."""

    distance_m: float
    machine_x_from_m: float
    machine_x_to_m: float


class PlanStatus(IntEnum):
    """Whether a plan digs its task: ``DONE`` when it meets every goal of :func:`plan_goals`."""

    DONE = 0
    INCOMPLETE = 1


#: A plan is done only when its coverage error (:attr:`TrenchPlan.coverage_error`) is at most
#: this fraction of the design's area.
COVERAGE_GOAL = 0.02

#: ... and its deepest cut below the design (:attr:`TrenchPlan.overdig_max_m`) at most this (m),
#: the limit every dig is planned to.
OVERDIG_GOAL_M = OVERDIG_LIMIT_M


@dataclass(frozen=True, slots=True)
class TrenchPlan:
    """A frozen plan for one trench task.

    Its :attr:`status` is ``DONE`` only when it meets every goal of :func:`plan_goals`; an
    ``INCOMPLETE`` plan says why in :attr:`reason` and how much design material it leaves in
    :attr:`volume_left_m3`.

    Attributes:
        task: The task.
        rig: Rig name.
        planner: One-shot planner name.
        steps: Digs, cycles (the moves into each dig), transitions (the moves of a session
            restored from an older state) and travel moves in execution order.
        digs: The digs alone.
        design: The designed cross-section polygon.
        dug: The region the plan removes (initial material minus final material).
        final_surface_m: The final surface over the task's x range, ``(n, 2)``.
        coverage_error: Area of the symmetric difference of dug and design over the design.
        overdig_max_m: Deepest cut below the design profile.
        removed_m3: Total removed volume; equals the sum of the digs' ``volume_m3``.
        design_m3: Designed volume (area x bucket width).
        plan_total_us: Wall time of the whole plan (from the task to this frozen plan, its
            coverage and over-dig measured).
        stage_us: Where that time went (us): ``screen`` (choosing the network's digs),
            ``oneshot`` (the one-shot planner's calls), ``checks`` (each planned dig's
            verification, over-dig and polygon checks), ``passes`` (fitting digs along the
            design's outline: the layers' columns, the walls' digs, finishing passes),
            ``transitions`` (the moves between digs and their checks), ``record`` (the
            material update), ``finish`` (this plan's coverage and over-dig), ``other`` (the
            rest: entries, layers, the remaining design).
        dig_plan_us: Each dig's planning (its choice, plan and checks in
            :meth:`TrenchSession.next_dig`, without the moves into it) (us), in the order of
            the digs planned since the plan's start (after a resume from a state: those
            planned after it).
        planning_error: What stopped the planning before the planner found the task finished
            (the message of the PlanningError: no dig removes the rest, the bound on the digs),
            or None when it ran to its end; the plan then holds the digs before it.
        screening: ``network`` or ``geometric``: what gave the rough stage's candidates their
            bulge (:class:`~rt_runtime.planning.trench.planner.TrenchPlanner`).
        soil: The minimum-torque planner's fluid soil (None with another planner).
    """

    task: TrenchTask
    rig: str
    planner: str
    steps: tuple[PlannedDig | Cycle | Transition | TravelMove, ...]
    digs: tuple[PlannedDig, ...]
    design: Polygon
    dug: Any
    final_surface_m: FloatArray
    coverage_error: float
    overdig_max_m: float
    removed_m3: float
    design_m3: float
    plan_total_us: float
    stage_us: dict[str, float] = field(default_factory=dict)
    planning_error: str | None = None
    screening: str = "network"
    dig_plan_us: tuple[float, ...] = ()
    soil: str | None = None

    @property
    def buckets(self) -> tuple[tuple[PlannedDig, ...], ...]:
        """The digs by bucket, in order: each a dig and the digs joined to it
        (:attr:`PlannedDig.joined`), which fill one bucket and are dumped once."""
        out: list[list[PlannedDig]] = []
        for d in self.digs:
            if d.joined and out:
                out[-1].append(d)
            else:
                out.append([d])
        return tuple(tuple(b) for b in out)

    @property
    def bucket_volumes_m3(self) -> tuple[float, ...]:
        """The real material of each of :attr:`buckets` (m^3): its pieces' together."""
        return tuple(sum(d.volume_m3 for d in b) for b in self.buckets)

    @property
    def status(self) -> PlanStatus:
        """``DONE`` when :func:`plan_goals` finds no goal unmet, else ``INCOMPLETE``."""
        return PlanStatus.INCOMPLETE if plan_goals(self) else PlanStatus.DONE

    @property
    def reason(self) -> str | None:
        """Why the plan is incomplete (the unmet goals, ``; ``-joined), None when done."""
        unmet = plan_goals(self)
        return "; ".join(unmet) if unmet else None

    @property
    def volume_left_m3(self) -> float:
        """Design material the plan leaves (m^3): the design's volume times the part of its
        area not dug."""
        left = float(self.design.difference(self.dug).area)
        return self.design_m3 * left / float(self.design.area)

    def to_json(self) -> dict[str, Any]:
        """The report of ``excavator-rt plan --json`` (keys in DESIGN.md "Reports")."""
        digs = [
            {
                "type": d.dig_type.name.lower(),
                "T_s": d.T_s,
                "volume_L": d.volume_m3 * 1e3,
                "predicted_volume_L": d.predicted_volume_m3 * 1e3,
                "design_volume_L": d.design_volume_m3 * 1e3,
                "energy_Wh": d.energy_j / 3600.0,
                "theta_p_deg": math.degrees(d.theta_p_rad),
                "plan_us": d.plan_us,
                "select_us": d.select_us,
                "overdig_mm": d.overdig_m * 1e3,
                "machine_x_m": d.machine_x_m,
                "status": d.status,
                "finishing": d.finishing,
                "section": d.section,
                "joined": d.joined,
                "carried": d.carried,
                "bucket": k,
                "pass_window": d.pass_window,
            }
            for k, bucket in enumerate(self.buckets)
            for d in bucket
        ]
        moves = iter_moves(self.steps)
        travels = [s for s in self.steps if isinstance(s, TravelMove)]
        cycles = [s for s in self.steps if isinstance(s, Cycle) and s.after_dig]
        return {
            "task": {
                "name": self.task.name,
                "length_m": self.task.length_m,
                "depth_m": self.task.depth_m,
                "beta1_deg": math.degrees(self.task.beta1_rad),
                "beta2_deg": math.degrees(self.task.beta2_rad),
                "start_x_m": self.task.start_x_m,
            },
            "rig": self.rig,
            "planner": self.planner,
            "screening": self.screening,
            "soil": self.soil,
            "status": self.status.name.lower(),
            "reason": self.reason,
            "volume_left_L": self.volume_left_m3 * 1e3,
            "digs": digs,
            "n_digs": len(self.buckets),
            "n_pieces": len(digs),
            "bucket_L": [v * 1e3 for v in self.bucket_volumes_m3],
            "coverage_error": self.coverage_error,
            "overdig_max_mm": self.overdig_max_m * 1e3,
            "removed_L": self.removed_m3 * 1e3,
            "design_L": self.design_m3 * 1e3,
            "plan_total_us": self.plan_total_us,
            "stage_us": dict(self.stage_us),
            "dig_plan_us": list(self.dig_plan_us),
            "dig_time_s": sum(d.T_s for d in self.digs),
            "transition_time_s": sum(t.duration_s for t in moves),
            "transition_penetration_max_mm": max(
                (t.penetration_m * 1e3 for t in moves), default=0.0
            ),
            "cycles": [
                {
                    "waypoints_deg": [[math.degrees(v) for v in q] for q in c.waypoints_rad],
                    "kinds": [k.label for k in c.kinds],
                    "moves_s": c.duration_s,
                    "bound_s": c.bound_s,
                    "blended": c.blended,
                    "penetration_mm": c.penetration_m * 1e3,
                }
                for c in cycles
            ],
            "moves_per_cycle_s": (
                sum(c.duration_s for c in cycles) / len(cycles) if cycles else None
            ),
            "cycle_fallbacks": sum(1 for c in cycles if not c.blended),
            "travel": [t.distance_m for t in travels],
            "energy_Wh": sum(d.energy_j for d in self.digs) / 3600.0,
            "yao_fig14": YAO_FIG14.get(self.task.name),
        }


def plan_goals(plan: TrenchPlan) -> list[str]:
    """The goals ``plan`` does not meet, each a sentence with its numbers; empty when done.

    Goals: the planning ran to its end (no :attr:`TrenchPlan.planning_error`), the coverage
    error is at most :data:`COVERAGE_GOAL` and the deepest over-dig at most
    :data:`OVERDIG_GOAL_M`. Every goal a plan must meet to be done belongs here.
    """
    unmet = []
    if plan.planning_error is not None:
        unmet.append(f"planning stopped: {plan.planning_error}")
    if not plan.coverage_error <= COVERAGE_GOAL:
        unmet.append(
            f"coverage error {plan.coverage_error:.2%} is above the goal {COVERAGE_GOAL:.0%}"
        )
    if not plan.overdig_max_m <= OVERDIG_GOAL_M:
        unmet.append(
            f"over-dig {plan.overdig_max_m * 1e3:.2f} mm is beyond the goal "
            f"{OVERDIG_GOAL_M * 1e3:g} mm"
        )
    return unmet
