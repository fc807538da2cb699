"""Task-oriented continuous trench planning (Yao 4.4, Fig. 5) with exact profile accounting.

A trench task is a cross-section in the arm's plane: a trapezoid of top length L on the ground,
depth D, far wall slope beta1 (at ``start_x_m``, the end the digging starts from) and near wall
slope beta2 (towards the machine), as in Yao Fig. 13 and Table 3. The planner follows Fig. 5:
downward digs until the depth is reached, then backward digs, and crawler travel when the rest
is out of reach, each dig planned by a one-shot planner (the PINN by default, the PSO teacher as
the alternative) between an entry pose on the material surface and an exit pose towards the
machine.

Material model. The material is a shapely polygon of the cross-section in the work-site frame
(the arm frame of the machine's first position; the machine's travel shifts the arm frame by
``machine_x_m``). A dig removes the region its bucket sweeps: everything above the tip path's
lower envelope over the x-span of the path (the bucket carries what lies above its cutting edge
out with it; the path's closing curl lies above the envelope). The same region is kept as a
height field on a 1 mm grid for screening candidates quickly; the polygon is the record that the
accounting uses (every removed cubic centimetre is the area difference of two polygons times the
bucket width, and the sum over digs equals the total removed). This needs the material to stay
y-monotone (a surface function of x), which holds because every cut is "everything above a
curve".

Choosing a dig (where Yao is silent). Each roughing dig is the best of a grid of candidate
problems: entry x near the far edge of the remaining design material on the current surface
(``H`` = the surface height there), entry and exit attitudes, dig lengths and rises from the
PINN's domain, and bulge caps. The grid goes through the network in one batch, but not through
the kernel: a candidate's tip path is known before the kernel fills and retimes it (the fill
scales the bulge ``K`` along its direction, the retiming keeps the path), so each path is
computed on a coarse grid of samples at a few bulge scales, and the fill's scale (the largest
with V_min <= V_p <= V_max against H), the over-dig and the real cut on the height field are
interpolated between them. The score is the design material removed minus twice the material
removed outside it. Only the best few are planned for real by the one-shot planner (one plan
in the usual case), and the plan's own path is checked on the verifier's full grid: over-dig
beyond the limit, a real cut above the bucket's V_max or a cut that removes almost no design
material sends the next candidate. When no roughing dig is left, straight profile passes trace
the design (:meth:`TrenchSession._finishing`), fitted by Gauss-Newton on the bulge ``K``.

Volumes. The one-shot model's V_p is measured against a flat surface y = H (Yao 3.3); on a
partly dug surface the real cut differs. Each dig reports both: ``volume_m3`` is the real
material removed (polygon accounting), ``predicted_volume_m3`` the one-shot V_p that the
verifier bounded. The bucket capacity V_max is enforced on the real cut.

Closed loop: :class:`TrenchSession` plans one dig at a time; :meth:`TrenchSession.record` takes
the measured tip path of the executed dig and updates the material from it, so the next dig is
planned from the true surface. :meth:`TrenchPlanner.plan` runs the session on the predicted paths.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar, cast

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray
from shapely.errors import GEOSException
from shapely.geometry import Polygon

from rt_runtime import kinematics
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType, Problem
from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, PinnPlanner
from rt_runtime.planning.verify import (
    COL_ENERGY_J,
    COL_THETA_P_RAD,
    COL_TOTAL,
    COL_VOLUME_M3,
    N_OUT,
    PLAN_C_RANGE,
    VerifyResult,
    pack_inputs,
)
from rt_runtime.rig import Rig

FloatArray = NDArray[np.float64]

#: Yao Table 3: (L m, D m, beta1 deg, beta2 deg).
BUILTIN_TASKS: dict[str, tuple[float, float, float, float]] = {
    "A": (0.60, 0.15, 60.0, 60.0),
    "B": (0.70, 0.10, 65.0, 40.0),
    "C": (0.55, 0.15, 60.0, 50.0),
    "D": (0.65, 0.20, 50.0, 60.0),
}
#: Yao Fig. 14: number of trajectories and the profile error per task (for the reports).
YAO_FIG14: dict[str, dict[str, float]] = {
    "A": {"digs": 4, "coverage_error": 0.087},
    "B": {"digs": 3, "coverage_error": 0.037},
    "C": {"digs": 3, "coverage_error": 0.012},
    "D": {"digs": 5, "coverage_error": 0.033},
}
#: No dig may cut below the design profile by more than this (m).
OVERDIG_LIMIT_M = 0.005
#: A dig must remove at least this fraction of the design's area of design material; when no
#: candidate does, the task is finished with what is left reported as coverage error.
MIN_USEFUL_FRACTION = 0.004
#: Grid step of the height field (m).
GRID_STEP_M = 0.001
# Thinner parts of a polygon difference are rounding, not ground (see TrenchSession.finish).
_SLIVER_M = 1e-6
#: Second difference (m) below which an envelope's grid point is on a straight piece of it
#: (:func:`_swept_polygon` drops it).
_COLLINEAR_M = 1e-12
# Reach figures of the scale model (m), scaled by the rig's l1 + l2 + l3 against 1.31 m: where
# digs may enter (the PINN's domain, oneshot.SAMPLER_RANGES), the deepest trench the backward
# digs' domain serves, and the default far edge of a trench.
_SCALE_REACH_M = 1.31
_ENTRY_X_M = (0.55, 1.10)
_MAX_DEPTH_M = 0.30
_DEFAULT_START_X_M = 1.05
# Transition poses (scale model, m / deg), assumed: Yao gives none. The bucket dumps at
# _DUMP_POSE (tip x, height above ground, attitude; bucket opened, beside the machine). The
# poses between are chosen from the surface (TrenchSession.exit_transitions and
# entry_transitions): the lift pose puts the whole bucket _LIFT_CLEAR_M above the material under
# it, the approach pose backs off from the entry by the first of _APPROACH_M that puts the bucket
# _LIFT_CLEAR_M above the material.
_LIFT_CLEAR_M = 0.02
_DUMP_POSE = (0.60, 0.25, -80.0)
_APPROACH_M = (0.03, 0.05, 0.08, 0.12, 0.18, 0.25)
#: Deepest a transition may take the bucket into the material left (m): every move is checked
#: on its samples and refused beyond it (:meth:`TrenchSession.exit_transitions`).
TRANSITION_PENETRATION_M = 0.005
# Sampling of a move's check (m, every rig; TrenchSession._move_depth): from one sample to the
# next no point of the bucket outline moves farther than _MOVE_STEP_M where the bucket is near
# the material, _COARSE_STEP_M where it is not; the outline's points lie _OUTLINE_STEP_M apart.
_MOVE_STEP_M = 0.002
_OUTLINE_STEP_M = 0.005
_COARSE_STEP_M = 0.01
# Depth into the material beyond which a move's check stops measuring (m): it is refused anyway.
_DEPTH_CAP_M = 0.05


# -- the task -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TrenchTask:
    """A trench cross-section to dig (Yao Fig. 13, Table 3).

    Attributes:
        name: Task name (``A``..``D`` or the file's stem).
        length_m: Top length L on the ground.
        depth_m: Depth D below the ground.
        beta1_rad: Slope of the far wall (at ``start_x_m``), from the horizontal.
        beta2_rad: Slope of the near wall (towards the machine).
        start_x_m: x of the far top edge in the arm frame of the machine's first position.
    """

    name: str
    length_m: float
    depth_m: float
    beta1_rad: float
    beta2_rad: float
    start_x_m: float

    @property
    def bottom_length_m(self) -> float:
        """Length of the flat bottom."""
        return (
            self.length_m
            - self.depth_m / math.tan(self.beta1_rad)
            - self.depth_m / math.tan(self.beta2_rad)
        )


def _reach_scale(rig: Rig) -> float:
    return float(np.sum(rig.lengths_m)) / _SCALE_REACH_M


def task_limits(rig: Rig) -> dict[str, tuple[float, float]]:
    """The allowed ranges of a task's values on ``rig`` (m, deg), as the validation uses them."""
    s = _reach_scale(rig)
    return {
        "depth_m": (0.0, _MAX_DEPTH_M * s),
        "start_x_m": (_ENTRY_X_M[0] * s, _ENTRY_X_M[1] * s),
        "beta_deg": (0.0, 90.0),
    }


def make_task(
    rig: Rig,
    length_m: float,
    depth_m: float,
    beta1_deg: float,
    beta2_deg: float,
    start_x_m: float | None = None,
    name: str = "task",
) -> TrenchTask:
    """A validated task.

    Raises:
        ConfigurationError: A value is not finite, out of its range (naming the key and what is
            allowed), the slopes meet above the depth, or the trench lies behind the machine.
    """
    limits = task_limits(rig)
    values = {
        "length_m": length_m,
        "depth_m": depth_m,
        "beta1_deg": beta1_deg,
        "beta2_deg": beta2_deg,
    }
    if start_x_m is not None:
        values["start_x_m"] = start_x_m
    for key, v in values.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ConfigurationError(f"task {name}: {key} must be a number; got {v!r}")
        if not math.isfinite(v):
            raise ConfigurationError(f"task {name}: {key} = {v} is not finite")
    if length_m <= 0.0:
        raise ConfigurationError(f"task {name}: length_m = {length_m:g} must be > 0")
    lo, hi = limits["depth_m"]
    if not lo < depth_m <= hi:
        raise ConfigurationError(
            f"task {name}: depth_m = {depth_m:g} is outside ({lo:g}, {hi:.3g}] m, the depth "
            f"{rig.name}'s digs reach below the ground"
        )
    for key in ("beta1_deg", "beta2_deg"):
        b = values[key]
        if not 0.0 < b < 90.0:
            raise ConfigurationError(
                f"task {name}: {key} = {b:g} must lie in (0, 90) deg (a wall slope from the "
                "horizontal)"
            )
    if start_x_m is None:
        start_x_m = _DEFAULT_START_X_M * _reach_scale(rig)
    lo, hi = limits["start_x_m"]
    if start_x_m <= 0.0:
        raise ConfigurationError(
            f"task {name}: start_x_m = {start_x_m:g} puts the trench behind the machine; the "
            f"far edge must lie in front of it, within [{lo:.3g}, {hi:.3g}] m"
        )
    if not lo <= start_x_m <= hi:
        raise ConfigurationError(
            f"task {name}: start_x_m = {start_x_m:g} is outside the reach [{lo:.3g}, {hi:.3g}] m "
            f"where {rig.name}'s digs can start"
        )
    task = TrenchTask(
        name=name,
        length_m=float(length_m),
        depth_m=float(depth_m),
        beta1_rad=math.radians(beta1_deg),
        beta2_rad=math.radians(beta2_deg),
        start_x_m=float(start_x_m),
    )
    if task.bottom_length_m < 0.0:
        need = depth_m / math.tan(task.beta1_rad) + depth_m / math.tan(task.beta2_rad)
        raise ConfigurationError(
            f"task {name}: the walls (beta1 {beta1_deg:g}, beta2 {beta2_deg:g} deg) meet above "
            f"depth_m = {depth_m:g}; length_m must be >= {need:.4g} m for that depth"
        )
    return task


#: Keys of a task file or object: the four sizes (required), then start_x_m (optional).
TASK_KEYS = ("length_m", "depth_m", "beta1_deg", "beta2_deg", "start_x_m")


def read_task_file(path: str | Path) -> dict[str, Any]:
    """The top-level keys of a task TOML file (:func:`check_task_keys`; values not yet checked).

    Raises:
        ConfigurationError: Unreadable file, unknown or missing keys.
    """
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigurationError(f"task file {path}: cannot read: {e}") from e
    check_task_keys(data, f"task file {path}")
    return data


def check_task_keys(data: Mapping[str, Any], source: str, extra: tuple[str, ...] = ()) -> None:
    """Refuse unknown task keys and missing required ones (values are :func:`make_task`'s).

    Args:
        data: ``length_m``, ``depth_m``, ``beta1_deg``, ``beta2_deg``, optional ``start_x_m``.
        source: Where the keys came from, the start of every message.
        extra: Further keys the caller allows (a submitted job's ``name``).

    Raises:
        ConfigurationError: Unknown or missing keys, each named with what is allowed.
    """
    allowed = (*extra, *TASK_KEYS)
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise ConfigurationError(
            f"{source}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(allowed)}"
        )
    missing = [k for k in TASK_KEYS[:4] if k not in data]
    if missing:
        raise ConfigurationError(f"{source}: missing key(s) {', '.join(missing)}")


def load_task(spec: str | Path, rig: Rig) -> TrenchTask:
    """A built-in task (``A``..``D``, Yao Table 3) or one from a TOML file.

    The file holds ``length_m``, ``depth_m``, ``beta1_deg``, ``beta2_deg`` and optionally
    ``start_x_m`` at its top level.

    Raises:
        ConfigurationError: Unknown name, unreadable file, unknown or missing keys, bad values.
    """
    text = str(spec)
    if text.upper() in BUILTIN_TASKS and not Path(text).exists():
        L, D, b1, b2 = BUILTIN_TASKS[text.upper()]
        return make_task(rig, L, D, b1, b2, name=text.upper())
    path = Path(text)
    if not path.is_file():
        raise ConfigurationError(
            f"task {text!r}: not a built-in task ({', '.join(BUILTIN_TASKS)}) and no such file"
        )
    data = read_task_file(path)
    return make_task(
        rig,
        data["length_m"],
        data["depth_m"],
        data["beta1_deg"],
        data["beta2_deg"],
        data.get("start_x_m"),
        name=path.stem,
    )


def design_polygon(task: TrenchTask, ground_y_m: float) -> Polygon:
    """The designed cross-section: the trapezoid below the ground (work-site frame)."""
    g, D, xf = ground_y_m, task.depth_m, task.start_x_m
    xn = xf - task.length_m
    return Polygon(
        [
            (xf, g),
            (xn, g),
            (xn + D / math.tan(task.beta2_rad), g - D),
            (xf - D / math.tan(task.beta1_rad), g - D),
        ]
    )


# -- one-shot planners ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class OneShotResult:
    """A verified one-shot dig from a planner adapter."""

    a6: tuple[float, float, float]
    T_s: float
    evaluation: FloatArray
    plan_us: float
    status: str


class OneShotPlanner(Protocol):
    """What the trench planner needs of a one-shot planner."""

    name: str

    def plan_dig(self, problem: Problem, c_max: float) -> OneShotResult:
        """A verified dig for ``problem``; ``c_max`` caps the bulge scale where supported.

        Raises:
            PlanningError: No verified plan.
        """
        ...


class PinnOneShot:
    """The PINN planner (default): what :meth:`PinnPlanner.plan` returns, bulge capped.

    Without the solution library (:mod:`rt_runtime.planning.pinn`, step 4a): the screening
    predicts each candidate's cut from the network's bulge direction (only its scale changes
    in the plan), and a library path would cut elsewhere.
    """

    name = "pinn"

    def __init__(self, planner: Any) -> None:
        self.planner = planner

    def plan_dig(self, problem: Problem, c_max: float) -> OneShotResult:
        p = self.planner.plan(
            problem.q_start_rad,
            problem.q_end_rad,
            problem.surface_y_m,
            problem.dig_type,
            c_max=c_max,
            library=False,
        )
        return OneShotResult(p.a6, p.T_s, p.evaluation, p.plan_us, p.status.name.lower())


class PsoOneShot:
    """The PSO teacher (seconds per dig): Yao's reference, same interface."""

    name = "pso"

    def __init__(self, rig: Rig, verifier: Any, **pso_options: Any) -> None:
        self.rig = rig
        self.verifier = verifier
        self.options = pso_options

    def plan_dig(self, problem: Problem, c_max: float) -> OneShotResult:
        t0 = time.perf_counter()
        sol = oneshot.solve_pso(self.rig, [problem], **self.options)[0]
        a6 = tuple(float(v) for v in sol.a6)
        p = problem
        row = pack_inputs(p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type, a6, sol.T_s)
        out = np.zeros((1, N_OUT))
        self.verifier.evaluate_into(row, out)
        if out[0, COL_TOTAL] > 0.0:
            raise PlanningError(
                f"PSO plan fails verification (total violation {out[0, COL_TOTAL]:.3g})"
            )
        return OneShotResult(
            (a6[0], a6[1], a6[2]),
            float(sol.T_s),
            out[0].copy(),
            (time.perf_counter() - t0) * 1e6,
            "pso",
        )


# -- the plan -------------------------------------------------------------------------------------


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
        energy_j, theta_p_rad: W_E and the initial digging angle of the verified plan.
        overdig_m: Deepest cut below the design profile (0 if none).
        plan_us: Time the one-shot planner took for this dig (excluding screening).
        select_us: Time of this dig's candidate screening and selection.
        planner: ``pinn`` or ``pso``; status: how the one-shot planner got the plan.
        evaluation: The verifier's row for the plan.
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


@dataclass(frozen=True, slots=True)
class Transition:
    """A state-to-state joint motion between digs (ruckig, rest to rest, no waypoints).

    Attributes:
        kind: ``lift_out``, ``dump``, ``approach`` or ``enter``: the phase of the cycle it is
            part of (a phase may take several moves: a lift in pieces).
        q_from_rad, q_to_rad: End poses (arm frame).
        duration_s: Time-optimal duration within the joint velocity/acceleration/jerk limits.
        machine_x_m: The machine's travel from its first position.
        penetration_m: How far the bucket (its tip, bottom and back plate) goes into the
            material left, as a distance, beyond what the move is allowed at a dig's pose
            (:meth:`TrenchSession.exit_transitions`, :meth:`TrenchSession.entry_transitions`);
            0 if clear, at most :data:`TRANSITION_PENETRATION_M` in a plan.
    """

    kind: str
    q_from_rad: tuple[float, float, float]
    q_to_rad: tuple[float, float, float]
    duration_s: float
    machine_x_m: float
    penetration_m: float

    def trajectory(self, rig: Rig) -> Any:
        """The ruckig trajectory (``ruckig.Trajectory``), recomputed from the end poses."""
        return joint_move(rig, self.q_from_rad, self.q_to_rad)[0]


@dataclass(frozen=True, slots=True)
class TravelMove:
    """Crawler travel through the VCU (+x away from the trench's far end is negative)."""

    distance_m: float
    machine_x_from_m: float
    machine_x_to_m: float


@dataclass(frozen=True, slots=True)
class TrenchPlan:
    """A frozen plan for one trench task.

    Attributes:
        task: The task.
        rig: Rig name.
        planner: One-shot planner name.
        steps: Digs, transitions and travel moves in execution order.
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
        stage_us: Where that time went (us): ``screen`` (choosing each dig's poses),
            ``oneshot`` (the one-shot planner's calls), ``checks`` (each planned dig's
            verification, over-dig and polygon checks), ``passes`` (fitting the profile
            passes), ``transitions`` (the ruckig moves and their ground checks), ``record``
            (the material update), ``finish`` (this plan's coverage and over-dig), ``other``
            (the rest: entries, the remaining design, relocation).
    """

    task: TrenchTask
    rig: str
    planner: str
    steps: tuple[PlannedDig | Transition | TravelMove, ...]
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
            }
            for d in self.digs
        ]
        transitions = [s for s in self.steps if isinstance(s, Transition)]
        travels = [s for s in self.steps if isinstance(s, TravelMove)]
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
            "digs": digs,
            "n_digs": len(digs),
            "coverage_error": self.coverage_error,
            "overdig_max_mm": self.overdig_max_m * 1e3,
            "removed_L": self.removed_m3 * 1e3,
            "design_L": self.design_m3 * 1e3,
            "plan_total_us": self.plan_total_us,
            "stage_us": dict(self.stage_us),
            "dig_time_s": sum(d.T_s for d in self.digs),
            "transition_time_s": sum(t.duration_s for t in transitions),
            "transition_penetration_max_mm": max(
                (t.penetration_m * 1e3 for t in transitions), default=0.0
            ),
            "travel": [t.distance_m for t in travels],
            "energy_Wh": sum(d.energy_j for d in self.digs) / 3600.0,
            "yao_fig14": YAO_FIG14.get(self.task.name),
        }


# -- geometry helpers -----------------------------------------------------------------------------


def lower_envelope(path_xy: FloatArray, grid_x: FloatArray) -> FloatArray:
    """Lowest y of a polyline over each grid x it spans (+inf where it does not).

    Exact for the polyline: every segment is interpolated at the grid points inside its x-span.
    """
    x0 = float(grid_x[0])
    h = float(grid_x[1] - grid_x[0])
    n = grid_x.shape[0]
    env = np.full(n, np.inf)
    xa, xb = path_xy[:-1, 0], path_xy[1:, 0]
    ya, yb = path_xy[:-1, 1], path_xy[1:, 1]
    lo = np.minimum(xa, xb)
    i0 = np.clip(np.ceil((lo - x0) / h - 1e-9), 0, n).astype(np.int64)
    i1 = np.clip(np.floor((lo + np.abs(xb - xa) - x0) / h + 1e-9) + 1, 0, n).astype(np.int64)
    counts = np.maximum(i1 - i0, 0)
    total = int(counts.sum())
    if total:
        seg = np.repeat(np.arange(counts.shape[0]), counts)
        idx = np.arange(total) + np.repeat(i0 - (np.cumsum(counts) - counts), counts)
        dx = xb - xa
        flat = np.abs(dx) <= 1e-12
        slope = np.where(flat, 0.0, (yb - ya) / np.where(flat, 1.0, dx))
        y_lo = np.minimum(ya, yb)
        base = np.where(flat, y_lo, ya)
        y = base[seg] + slope[seg] * (grid_x[idx] - xa[seg])
        # Clipping y to the segment's range is clipping its parameter to [0, 1].
        y = np.minimum(np.maximum(y, y_lo[seg]), np.maximum(ya, yb)[seg])
        np.minimum.at(env, idx, y)
    return env


def _swept_polygon(
    path_xy: FloatArray,
    grid_x: FloatArray,
    top_y: float,
    env: FloatArray | None = None,
    envelope: Callable[[FloatArray, FloatArray], FloatArray] = lower_envelope,
) -> Polygon | None:
    """The region above the path's lower envelope over its span, up to ``top_y``.

    ``env``: the path's :func:`lower_envelope` on ``grid_x`` when the caller has it;
    ``envelope``: what computes it (the session's C kernel, else :func:`lower_envelope`).
    """
    if env is None:
        env = envelope(path_xy, grid_x)
    ok = np.flatnonzero(np.isfinite(env))
    if ok.shape[0] < 2:
        return None
    # The path is continuous, so the grid points it spans are one run: ok[0]..ok[-1].
    i0, i1 = int(ok[0]), int(ok[-1]) + 1
    # Keep the exact end points of the span (the grid may start inside it).
    x_lo = max(float(np.min(path_xy[:, 0])), float(grid_x[0]))
    x_hi = min(float(np.max(path_xy[:, 0])), float(grid_x[-1]))
    y = np.minimum(env[i0:i1], top_y)
    # Interior grid points on a straight piece of the envelope add nothing to the region: only
    # its kinks are kept (the envelope is linear between the path's samples, so ~3-4 of every
    # 4 points go). The region is the same to ~1e-8 m (1e-12 m per dropped point, k^2 / 8 of
    # it over a run of k), and every later polygon operation on the material, which would
    # accumulate these vertices dig after dig, costs that much less.
    keep = np.ones(y.shape[0], dtype=bool)
    keep[1:-1] = np.abs(y[2:] - 2.0 * y[1:-1] + y[:-2]) > _COLLINEAR_M
    m = int(np.count_nonzero(keep))
    coords = np.empty((m + 4, 2))
    coords[0] = (x_lo, top_y)
    coords[2 : m + 2, 0] = grid_x[i0:i1][keep]
    coords[2 : m + 2, 1] = y[keep]
    # The span's ends at the path's own lowest point there (its envelope on the two-point
    # grid of the ends), not at the nearest grid point's envelope: on a steep path that is up
    # to a grid step's worth of slope deeper than the path reaches at the end, which cut past
    # the design (5.15 mm by a dig whose path went 4.78 mm deep).
    ends = np.minimum(envelope(path_xy, np.array([x_lo, x_hi])), top_y)
    coords[1] = (x_lo, ends[0])
    coords[m + 2] = (x_hi, ends[1])
    coords[m + 3] = (x_hi, top_y)
    poly = shapely.polygons(coords)
    # Only a path reaching the top line makes the outline touch itself.
    if (np.any(y >= top_y) or np.any(ends >= top_y)) and not shapely.is_valid(poly):
        poly = poly.buffer(0)
    return poly


def joint_move(rig: Rig, q0: ArrayLike, q1: ArrayLike) -> tuple[Any, float]:
    """Time-optimal rest-to-rest joint move within the rig's joint limits (ruckig, no
    intermediate waypoints): ``(ruckig.Trajectory, duration_s)``; the transitions' motion.

    Raises:
        PlanningError: ruckig cannot plan it.
    """
    traj = _Mover(rig).move(np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64))
    return traj, float(traj.duration)


def _sextic_shapes(n: int) -> tuple[FloatArray, FloatArray]:
    """The sextic's shape functions on ``n`` uniform samples of [0, 1]: the joint blend
    ``10 s^3 - 15 s^4 + 6 s^5`` and the bulge profile ``s^3 (1 - s)^3``."""
    s = np.linspace(0.0, 1.0, n)
    return 10 * s**3 - 15 * s**4 + 6 * s**5, s**3 * (1 - s) ** 3


# -- the planner ----------------------------------------------------------------------------------


class _Mover:
    """Rest-to-rest ruckig moves with the rig's limits, reusing one generator (the transitions'
    hot path: ~2 us a move instead of ~15 us building the objects each time), and the bucket
    outline the transitions' checks sample along them.

    The outline is ``rig.bucket.profile_m`` (the cutting edge, the bottom and the back plate)
    at points at most :data:`_OUTLINE_STEP_M` apart, the tip first: ``outline`` ``(m, 2)``,
    (along, normal) in the bucket link frame shifted to the tip.
    """

    def __init__(self, rig: Rig) -> None:
        from ruckig import InputParameter, Result, Ruckig, Trajectory

        self._ok = (Result.Working, Result.Finished)
        self._otg = Ruckig(3)
        self._inp = InputParameter(3)
        self._inp.max_velocity = [float(v) for v in rig.qd_max_rad_s]
        self._inp.max_acceleration = [float(v) for v in rig.qdd_max_rad_s2]
        self._inp.max_jerk = [float(v) for v in rig.qddd_max_rad_s3]
        self._traj = Trajectory(3)
        self.arm = kinematics.FastArm(rig)
        corners = np.asarray(rig.bucket.profile_m, dtype=np.float64)
        points = [corners[:1]]
        for a, b in itertools.pairwise(corners):
            k = max(1, math.ceil(float(np.hypot(*(b - a))) / _OUTLINE_STEP_M))
            points.append(a + (b - a) * (np.arange(1, k + 1) / k)[:, None])
        self.outline = np.concatenate(points)
        #: Where the profile's corners are in ``outline``: the outline lies in their hull.
        self.corners = np.cumsum([0] + [p.shape[0] for p in points[1:]])
        # How far a point of the outline can be from each joint: a joint's turn moves it at
        # most that far per radian (the samples' spacing).
        l1, l2, l3 = (float(v) for v in rig.lengths_m)
        r3 = float(np.max(np.hypot(self.outline[:, 0] + l3, self.outline[:, 1])))
        self.radius_m = np.array([l1 + l2 + r3, l2 + r3, r3])

    def move(self, q0: Sequence[float] | FloatArray, q1: Sequence[float] | FloatArray) -> Any:
        """The move's trajectory (valid until the next call).

        Raises:
            PlanningError: ruckig cannot plan it.
        """
        self._inp.current_position = [float(v) for v in q0]
        self._inp.target_position = [float(v) for v in q1]
        result = self._otg.calculate(self._inp, self._traj)
        if result not in self._ok:
            raise PlanningError(f"ruckig could not plan a transition: {result}")
        return self._traj

    def n_samples(self, q0: FloatArray, q1: FloatArray, step_m: float) -> int:
        """Uniform time samples of a move from ``q0`` to ``q1`` so many that no point of the
        bucket moves more than ``step_m`` from one to the next (a rest-to-rest ruckig move
        turns each joint one way, so a joint turns ``|q1 - q0|`` in all)."""
        travel = float(np.abs(np.asarray(q1) - np.asarray(q0)) @ self.radius_m)
        return min(max(math.ceil(travel / step_m) + 1, 2), 20000)

    @staticmethod
    def poses(traj: Any, times_s: FloatArray) -> FloatArray:
        """Joint poses ``(n, 3)`` of a ruckig trajectory at ``times_s`` ``(n,)`` (within it).

        A rest-to-rest move is one section of seven constant-jerk pieces per joint
        (``Profile.t, j, a, v, p``: durations and the state where each starts), evaluated
        here in numpy: ruckig's ``at_time`` takes one time per call, ~0.5 us each, and the
        checks sample hundreds (tests/test_trench.py compares the two). A profile with a
        braking or accelerating lead-in (not a rest-to-rest move) goes through ``at_time``.
        """
        profiles = traj.profiles[0]
        if len(traj.profiles) != 1 or any(
            p.brake.duration > 0.0 or p.accel.duration > 0.0 for p in profiles
        ):
            at = traj.at_time
            return np.array([at(t)[0] for t in times_s.tolist()])
        out = np.empty((times_s.shape[0], len(profiles)))
        for k, p in enumerate(profiles):
            starts = np.concatenate([[0.0], np.cumsum(p.t)])
            i = np.clip(np.searchsorted(starts, times_s, side="right") - 1, 0, 6)
            dt = times_s - starts[i]
            jerk, acc = np.asarray(p.j)[i], np.asarray(p.a)[i]
            vel, pos = np.asarray(p.v)[i], np.asarray(p.p)[i]
            out[:, k] = pos + dt * (vel + dt * (0.5 * acc + dt * jerk / 6.0))
        return out

    def bucket_xy(self, q: FloatArray, *, corners: bool = False) -> tuple[FloatArray, FloatArray]:
        """The outline's points (or only its corners) of joint poses ``(..., 3)``: x and y
        ``(..., m)``, arm frame."""
        x, y = self.arm.tip_xy(q)
        z = q[..., 0] + q[..., 1] + q[..., 2]
        c, s = np.cos(z)[..., None], np.sin(z)[..., None]
        pts = self.outline[self.corners] if corners else self.outline
        a, b = pts[:, 0], pts[:, 1]
        return x[..., None] + c * a - s * b, y[..., None] + s * a + c * b


@dataclass(frozen=True, slots=True)
class _Candidates:
    """The candidate grid of one dig type (arm-frame values relative to the entry)."""

    entry_attitude_deg: tuple[float, ...]
    length_m: tuple[float, ...]
    exit_rise_m: tuple[float, ...]
    exit_attitude_deg: tuple[float, ...]
    c_max: tuple[float, ...]


_CANDIDATES: dict[DigType, _Candidates] = {
    DigType.DOWNWARD: _Candidates(
        entry_attitude_deg=(-75.0, -90.0, -105.0, -118.0),
        length_m=(0.22, 0.34, 0.39),
        exit_rise_m=(0.01, 0.05, 0.15),
        exit_attitude_deg=(-145.0, -160.0, -175.0),
        c_max=(2.0, 1.0, 0.6, 0.3),
    ),
    DigType.BACKWARD: _Candidates(
        entry_attitude_deg=(-102.0, -115.0, -128.0),
        length_m=(0.28, 0.40, 0.46),
        exit_rise_m=(0.01, 0.05),
        exit_attitude_deg=(-152.0, -165.0, -180.0),
        c_max=(2.0, 1.0, 0.6, 0.3),
    ),
}
#: Entry x candidates per screening: from the far edge of the remaining design inwards.
_N_ENTRY_X = 4


class TrenchPlanner:
    """Plans trench tasks dig by dig (Yao Fig. 5).

    Args:
        rig: The rig (needs planning thresholds and shipped PINN models for screening).
        planner: ``pinn`` (default), ``pso``, or an object with ``plan_dig``.
        model_dir: PINN model directory (default: the shipped ``onnx/``).
        pso_options: Keyword arguments for :func:`rt_runtime.planning.oneshot.solve_pso`.
        max_digs: Safety bound on the number of digs of one task.
        geometry: Who computes the screening geometry, the over-dig of sampled paths and the
            envelopes: ``"c"`` (the verifier's compiled kernel, ``_verify.c``), ``"numpy"``
            (the reference) or ``"auto"`` (C where the verifier runs on C). The plans are the
            same (tests/test_trench.py compares them); C is ~2x faster on a whole plan.

    Raises:
        ConfigurationError: Unknown planner name or geometry; models that do not load for the
            rig; ``geometry="c"`` where the verifier has no compiled kernel.
    """

    def __init__(
        self,
        rig: Rig,
        planner: str | OneShotPlanner = "pinn",
        *,
        model_dir: Path | str | None = None,
        pso_options: dict[str, Any] | None = None,
        max_digs: int = 40,
        geometry: str = "auto",
    ) -> None:

        oneshot.require_planning(rig)
        self.rig = rig
        #: What built this planner (a planner process rebuilds it from these).
        self.model_dir = Path(model_dir or DEFAULT_MODEL_DIR)
        self.pso_options = dict(pso_options or {})
        self.pinn = PinnPlanner(rig, self.model_dir, refine=True)
        self.verifier = self.pinn.verifier
        if geometry not in ("auto", "c", "numpy"):
            raise ConfigurationError(f"unknown geometry {geometry!r}; allowed: auto, c, numpy")
        if geometry == "c" and self.verifier.module is None:
            raise ConfigurationError(
                "geometry 'c' needs the verifier's compiled kernel, which is not in use here "
                f"(verifier backend {self.verifier.backend!r})"
            )
        use_c = geometry != "numpy" and self.verifier.module is not None
        #: The compiled kernel and its module for the geometry (None: the numpy reference).
        self.geo_kernel: Any = self.verifier.kernel if use_c else None
        self.geo_module: Any = self.verifier.module if use_c else None
        if isinstance(planner, str):
            if planner == "pinn":
                self.oneshot: OneShotPlanner = PinnOneShot(self.pinn)
            elif planner == "pso":
                self.oneshot = PsoOneShot(rig, self.verifier, **(pso_options or {}))
            else:
                raise ConfigurationError(f"unknown planner {planner!r}; allowed: pinn, pso")
        else:
            self.oneshot = planner
        self.max_digs = max_digs
        s = _reach_scale(rig)
        self.scale = s
        self.entry_x_range = (_ENTRY_X_M[0] * s, _ENTRY_X_M[1] * s)
        self.arm = kinematics.FastArm(rig)
        self.screen_qf, self.screen_pf = _sextic_shapes(_SCREEN_SAMPLES)
        self.screen_shapes = np.stack([self.screen_qf, self.screen_pf])
        self.screen_c = np.asarray(_SCREEN_C)
        # Second derivatives of the sextic's shape functions on a 1001-point grid.
        t = np.linspace(0.0, 1.0, 1001)
        self.fine_qf2 = 60 * t - 180 * t**2 + 120 * t**3
        self.fine_pf2 = 6 * t - 36 * t**2 + 60 * t**3 - 30 * t**4
        self.qdd_max = np.asarray(rig.qdd_max_rad_s2, dtype=np.float64)
        self.fit_qf, self.fit_pf = _sextic_shapes(_FIT_SAMPLES)
        # On the verifier's grid: the profile passes' paths as the verifier samples them.
        self.full_qf, self.full_pf = _sextic_shapes(self.verifier.n_samples)
        self.mover = _Mover(rig)
        #: Each dig type's exit candidates relative to the entry, flat: (length, rise, attitude).
        self.exit_grid = {
            kind: tuple(
                g.ravel()
                for g in np.meshgrid(
                    np.asarray(cand.length_m) * s,
                    np.asarray(cand.exit_rise_m) * s,
                    np.radians(cand.exit_attitude_deg),
                    indexing="ij",
                )
            )
            for kind, cand in _CANDIDATES.items()
        }
        self.domain = {
            k: (np.asarray(c.domain_min), np.asarray(c.domain_max))
            for k, c in self.pinn.cards.items()
        }
        #: Where the bucket dumps (and where the arm starts a task), joint angles.
        self.dump_pose_rad = kinematics.inverse(
            rig,
            _DUMP_POSE[0] * s,
            rig.ground_y_m + _DUMP_POSE[1] * s,
            math.radians(_DUMP_POSE[2]),
        )

    def start(self, task: TrenchTask) -> TrenchSession:
        """A closed-loop session for ``task`` (plan a dig, execute it, record its path)."""
        return TrenchSession(self, task)

    def plan(self, task: TrenchTask) -> TrenchPlan:
        """The whole plan for ``task`` on the predicted paths (open loop).

        Raises:
            PlanningError: A dig cannot be planned (no verified candidate removes material).
        """
        t0 = time.perf_counter()
        session = self.start(task)
        while True:
            dig = session.next_dig()
            if dig is None:
                break
            session.record(dig, dig.tip_path_m)
        plan = session.finish(plan_total_us=0.0)
        total = (time.perf_counter() - t0) * 1e6
        stages = dict(session.stage_us)
        stages["other"] = max(0.0, total - sum(stages.values()))
        return dataclasses.replace(plan, plan_total_us=total, stage_us=stages)


#: The stages of TrenchPlan.stage_us that TrenchSession times (``other`` is the rest).
_STAGES = ("screen", "oneshot", "checks", "passes", "transitions", "record", "finish")

_Method = TypeVar("_Method", bound=Callable[..., Any])


def _stage(name: str) -> Callable[[_Method], _Method]:
    """Add a TrenchSession method's wall time to its ``stage_us[name]``."""

    def wrap(method: _Method) -> _Method:
        @functools.wraps(method)
        def timed(self: TrenchSession, *args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return method(self, *args, **kwargs)
            finally:
                self.stage_us[name] += (time.perf_counter() - t0) * 1e6

        return cast(_Method, timed)

    return wrap


class TrenchSession:
    """One task being dug: the material state and the steps so far (closed loop).

    Use :meth:`next_dig` to plan the next dig from the current material (``None`` when the task
    is done), execute it, then :meth:`record` the measured tip path (work-site frame); the
    material is updated from what was measured, not what was planned. ``next_dig`` also
    appends to :attr:`steps` the transitions that lead into the dig (from the previous dig's
    exit, or from the dump pose), checked against the material as it is before the dig; the
    dig itself joins :attr:`steps` when it is recorded.
    """

    def __init__(self, planner: TrenchPlanner, task: TrenchTask) -> None:
        self.planner = planner
        self.task = task
        rig = planner.rig
        self.rig = rig
        self.ground_y = rig.ground_y_m
        self.width_m = rig.bucket.width_m
        self.planning = oneshot.require_planning(rig)
        self.v_max_m3 = self.planning.volume_max_m3
        self.design = design_polygon(task, self.ground_y)
        xf = task.start_x_m
        xn = xf - task.length_m
        margin = 0.5 * planner.scale
        self.x_lo, self.x_hi = xn - margin, xf + margin
        self.grid = np.arange(self.x_lo, self.x_hi + GRID_STEP_M / 2, GRID_STEP_M)
        self.bottom_y = self.ground_y - task.depth_m
        box_bottom = self.bottom_y - 0.2 * planner.scale
        self.top_y = self.ground_y + 1.0
        self.initial = Polygon(
            [
                (self.x_lo, self.ground_y),
                (self.x_lo, box_bottom),
                (self.x_hi, box_bottom),
                (self.x_hi, self.ground_y),
            ]
        )
        self.material: Any = self.initial
        self.surface = np.full(self.grid.shape[0], self.ground_y)
        self.design_floor = self._design_floor()
        # Half-planes of the design's walls and bottom: n . p <= c inside (unit n).
        b1, b2 = task.beta1_rad, task.beta2_rad
        self._walls = np.array(
            [
                # far wall through (xf, g), inside is x <= ...: n = (sin b1, -cos b1)
                [math.sin(b1), -math.cos(b1), math.sin(b1) * xf - math.cos(b1) * self.ground_y],
                # near wall through (xn, g): n = (-sin b2, -cos b2)
                [-math.sin(b2), -math.cos(b2), -math.sin(b2) * xn - math.cos(b2) * self.ground_y],
                # bottom: n = (0, -1), -y <= -(bottom) -> y >= bottom
                [0.0, -1.0, -self.bottom_y],
            ]
        )
        # The design's edges for the over-dig distance, one row per edge: start point, vector,
        # squared length (ax, ay, abx, aby, |ab|^2; the C geometry takes the same rows).
        ring = np.asarray(self.design.exterior.coords)  # closed: last == first
        edge = ring[1:] - ring[:-1]
        self._design_edges = np.column_stack([ring[:-1], edge, np.sum(edge * edge, axis=1)])
        self.steps: list[PlannedDig | Transition | TravelMove] = []
        self.digs: list[PlannedDig] = []
        self.machine_x = 0.0
        self.q_now: FloatArray | None = None
        self.pending: PlannedDig | None = None
        self.design_area = float(self.design.area)
        self.phase = DigType.DOWNWARD
        self._finish_index = 0
        self._travels = 0
        #: Time spent per stage so far (us; TrenchPlan.stage_us).
        self.stage_us: dict[str, float] = dict.fromkeys(_STAGES, 0.0)
        #: The pending dig's planned tip path, its envelope and swept region (for record()).
        self._planned_region: tuple[FloatArray, FloatArray, Any] | None = None
        #: Transitions planned lately: key -> (the height field they were checked on, moves).
        self._moves: dict[tuple[Any, ...], tuple[FloatArray, tuple[Transition, ...]]] = {}
        #: The sparse max table of the height field the last move was checked on.
        self._max_tables: tuple[FloatArray, FloatArray] = (np.empty(0), np.empty((0, 0)))

    # -- state --------------------------------------------------------------------------------

    def _design_floor(self) -> FloatArray:
        """The design's lower boundary over the grid (the ground outside the trench)."""
        t = self.task
        g = self.ground_y
        x = self.grid
        far = g - (t.start_x_m - x) * math.tan(t.beta1_rad)
        near = g - (x - (t.start_x_m - t.length_m)) * math.tan(t.beta2_rad)
        floor = np.maximum(np.maximum(far, near), self.bottom_y)
        return np.minimum(floor, g)

    def remaining_design(self) -> Any:
        """Design material not dug yet."""
        return self.design.intersection(self.material)

    def overdig_of(self, path_xy: FloatArray) -> float:
        """Deepest point of a path below the design profile, where it is in the material."""
        return float(self._overdig_many(path_xy[None])[0])

    def _envelope(self, path_xy: FloatArray, grid_x: FloatArray) -> FloatArray:
        """:func:`lower_envelope`, in C with the C geometry (~3 us against ~90 us)."""
        geo = self.planner.geo_module
        if geo is None:
            return lower_envelope(path_xy, grid_x)
        env = np.empty(grid_x.shape[0])
        geo.envelope(np.ascontiguousarray(path_xy, dtype=np.float64), grid_x, env)
        return env

    def _geometry_args(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The height field and design as the C geometry takes them: ``field`` (surface and
        design floor on the grid), ``frame`` (grid start and step, machine x, the trench's far
        and near x, the ground), ``walls`` and ``edges``."""
        xf = self.task.start_x_m
        frame = np.array(
            [self.grid[0], GRID_STEP_M, self.machine_x, xf, xf - self.task.length_m, self.ground_y]
        )
        heights = np.stack([self.surface, self.design_floor])
        return heights, frame, self._walls, self._design_edges

    def _overdig_many(self, paths: FloatArray) -> FloatArray:
        """Over-dig of many paths ``(N, n, 2)`` at once (m, 0 where none); in C with the C
        geometry (:meth:`_overdig_many_numpy` is the reference)."""
        geo = self.planner.geo_module
        if geo is None:
            return self._overdig_many_numpy(paths)
        out = np.empty(paths.shape[0])
        geo.overdig(np.ascontiguousarray(paths, dtype=np.float64), *self._geometry_args(), out)
        return out

    def _overdig_many_numpy(self, paths: FloatArray) -> FloatArray:
        """Over-dig of many paths ``(N, n, 2)`` at once (m, 0 where none).

        A sample counts where it lies below the current surface (in material) and outside the
        design (one of its three lower half-planes, walls and bottom, violated; outside the
        trench's x range the ground is the design). Its over-dig is its Euclidean distance to
        the design polygon, the measure of the finished plan's ``overdig_max_m``. (The largest
        half-plane violation alone is that distance only where one is violated: below a
        corner it is a lower bound, and a dig 4.9 mm "deep" by it cut 5.15 mm into the
        corner.)
        """
        x = paths[..., 0]
        y = paths[..., 1]
        inside = y < self._on_grid(x, self.surface)[0]
        w = self._walls
        d = np.maximum(
            np.maximum(w[0, 0] * x + w[0, 1] * y - w[0, 2], w[1, 0] * x + w[1, 1] * y - w[1, 2]),
            w[2, 0] * x + w[2, 1] * y - w[2, 2],
        )
        xf, xn = self.task.start_x_m, self.task.start_x_m - self.task.length_m
        d = np.where((x > xf) | (x < xn), np.maximum(d, self.ground_y - y), d)
        out = inside & (d > 0.0)
        worst: FloatArray = np.zeros(x.shape[:-1])
        if np.any(out):
            px, py = x[out], y[out]
            e = self._design_edges
            a, ab, ab2 = e[:, 0:2], e[:, 2:4], e[:, 4]
            # distance to each edge (segment) of the convex design, the nearest one counts
            t = ((px[:, None] - a[:, 0]) * ab[:, 0] + (py[:, None] - a[:, 1]) * ab[:, 1]) / ab2
            t = np.clip(t, 0.0, 1.0)
            ex = px[:, None] - (a[:, 0] + t * ab[:, 0])
            ey = py[:, None] - (a[:, 1] + t * ab[:, 1])
            dist = np.sqrt(np.min(ex * ex + ey * ey, axis=1))
            full = np.zeros(x.shape)
            full[out] = dist
            worst = np.max(full, axis=-1)
        return worst

    def _overdig_of_region(self, region: Any) -> float:
        """Over-dig of a dug region (m): its farthest vertex outside the (convex) design,
        which is where the largest distance of a polygon from a convex set lies; the measure
        of the finished plan's ``overdig_max_m``. Slivers that polygon differences leave along
        the ground line (nanometres thick, up to the grid's whole length) are not material: a
        part counts where its mean thickness (2 area / perimeter) is at least _SLIVER_M."""
        over = region.difference(self.design)
        parts = [
            g
            for g in getattr(over, "geoms", [over])
            if g.area > 0.0 and 2.0 * g.area >= _SLIVER_M * g.length
        ]
        if not parts:
            return 0.0
        coords = np.concatenate([shapely.get_coordinates(g) for g in parts])
        return float(np.max(shapely.distance(shapely.points(coords), self.design)))

    def _cut_areas(self, env: FloatArray) -> tuple[float, float]:
        """(total, inside-design) area a path envelope removes from the height field."""
        total = np.maximum(self.surface - env, 0.0)
        inside = np.maximum(self.surface - np.maximum(env, self.design_floor), 0.0)
        return float(np.sum(total) * GRID_STEP_M), float(np.sum(inside) * GRID_STEP_M)

    # -- choosing a dig -----------------------------------------------------------------------

    def _phase(self) -> DigType:
        """Fig. 5: downward until the depth is reached, then backward."""
        if (
            self.phase is DigType.DOWNWARD
            and float(np.min(self.surface)) <= self.bottom_y + OVERDIG_LIMIT_M
        ):
            self.phase = DigType.BACKWARD
        return self.phase

    def _entry_x_candidates(self, remaining: Any) -> list[float]:
        """Where on the surface digs may enter: the far edge of the remaining design material
        within the entries' reach from where the machine stands.

        After a travel, the edge is taken on the height field, where the material left above
        the design floor is at least :data:`_ENTRY_MIN_THICKNESS_M` (scaled) thick: the profile
        passes dug from the previous stand leave slivers along the floor, and the polygon's
        bounds put the entries over dug ground (every candidate there over-digs, and a long
        trench's near part was never roughed out: 32-52 % left on 1.0-1.2 m trenches 0.10-0.15 m
        deep). Before any travel the polygon's bounds within reach are used, as they were: the
        height-field edge changes the plans of Yao's tasks, D for the worse (27 % left), a
        trade not made here.
        """
        s = self.planner.scale
        lo, hi = self.planner.entry_x_range
        m = self.machine_x
        grid = self.grid
        thick = (self.surface - self.design_floor > _ENTRY_MIN_THICKNESS_M * s) & (
            (grid >= m + lo) & (grid <= m + hi)
        )
        idx = np.flatnonzero(thick) if self._travels else np.empty(0, dtype=np.intp)
        step = 0.04 * s
        edges: list[float] = []
        if idx.size:
            minx, maxx = float(grid[idx[0]]), float(grid[idx[-1]])
            # The far edge of the bulk as well: where the previous stand's digs sloped the
            # material off, the thin edge lies on that slope, below the ground the bulk
            # behind it stands at, and every dig entering there would fill the bucket from
            # the face above its path (1.0 m x 0.15 m: 40 % left). The bulk's edge is where
            # the material is at least 90 % of its thickest within reach.
            t = self.surface[idx] - self.design_floor[idx]
            bulk = idx[t >= _ENTRY_BULK_FRACTION * float(np.max(t))]
            bulk_x = float(grid[bulk[-1]])
            if bulk_x < maxx - step:
                edges.append(bulk_x)
        else:
            reach = self._reachable(remaining)
            part = reach if reach.area >= 0.005 * self.design_area else remaining
            minx, _, maxx, _ = part.bounds
        xs = [
            float(x)
            for edge in (maxx, *edges)
            for x in np.arange(edge, minx + 0.05 * s, -step)[:_N_ENTRY_X]
        ]
        return xs or [maxx]

    def next_dig(self) -> PlannedDig | None:
        """Plan the next dig from the current material, or None when the task is done.

        Raises:
            PlanningError: Material is left but no verified dig removes any of it, or the
                safety bound on the number of digs is reached.
        """
        if self.pending is not None:
            raise PlanningError("record() the executed path of the previous dig first")
        remaining = self.remaining_design()
        left = float(remaining.area)
        if left <= 0.005 * self.design_area:
            return None
        if len(self.digs) >= self.planner.max_digs:
            raise PlanningError(
                f"task {self.task.name}: {left / self.design_area:.1%} of the design is left "
                f"after {len(self.digs)} digs (the bound)"
            )
        t0 = time.perf_counter()
        self._relocate_if_needed(remaining)
        # The entries do not depend on the dig type or the phase: computed once for both
        # screenings (nothing but the phase changes between them).
        xe = np.asarray(self._entry_x_candidates(remaining))
        H = np.interp(xe, self.grid, self.surface)
        ranked = self._screen(xe, H)
        if not ranked and self.phase is DigType.DOWNWARD:
            self.phase = DigType.BACKWARD
            ranked = self._screen(xe, H)
        dig = self._first_plannable(ranked, remaining, t0)
        exhausted = False
        if dig is None:
            dig, exhausted = self._next_pass(remaining, t0)
        # Nothing more from here: the rest within reach in layers (_finishing) before any
        # travel away from it, when it is more than a sliver (on Yao's B the ~1 % left are
        # slivers along the profile, which layers over-cut: 1.0 -> 1.4 %). (Travelling first
        # left a short deep trench 69 % undug: the travel was for a 4 % wedge by the near
        # wall, and from the new stand the bulk was out of reach.)
        layered = False
        min_left = _LAYER_MIN_LEFT * self.design_area
        if dig is None and exhausted and float(self._reachable(remaining).area) > min_left:
            dig, _ = self._next_pass(remaining, t0, layers=True)
            layered = True
        if dig is None and self._relocate_for_rest(remaining):
            return self.next_dig()
        # Nothing more from here or from another stand: the rest in layers.
        if dig is None and exhausted and not layered and left > min_left:
            dig, _ = self._next_pass(remaining, t0, layers=True)
        if dig is None and exhausted:
            return None
        if dig is None:
            raise PlanningError(
                f"task {self.task.name}: no verified dig removes the remaining "
                f"{left / self.design_area:.1%} of the design without over-digging"
            )
        self._append_transitions(dig)
        self.pending = dig
        return dig

    def _first_plannable(
        self, ranked: list[dict[str, Any]], remaining: Any, t0: float
    ) -> PlannedDig | None:
        """The best screened candidate the one-shot planner plans within the limits
        (``remaining``: :meth:`remaining_design` of the current material).

        The PINN plans exactly what was screened; another planner (the PSO) finds its own
        optimum for the same poses, which may cut too deep or take more than the bucket: then
        the next candidate is tried.
        """
        for best in ranked:
            try:
                dig = self._plan_chosen(best, remaining, (time.perf_counter() - t0) * 1e6)
                self._check_transition_poses(dig)
            except PlanningError:
                continue
            return dig
        return None

    def _next_pass(
        self, remaining: Any, t0: float, *, layers: bool = False
    ) -> tuple[PlannedDig | None, bool]:
        """The next plannable profile pass (:meth:`_finishing`, with ``layers``), and whether
        the passes ran out (False also when the bound :data:`_N_MAX_PASSES` stopped them)."""
        while self._finish_index < _N_MAX_PASSES:
            ranked = self._finishing(remaining, layers=layers)
            if not ranked:
                return None, True
            dig = self._first_plannable(ranked, remaining, t0)
            if dig is not None:
                return dig, False
        return None, False

    def _reachable(self, remaining: Any) -> Any:
        """The part of ``remaining`` between the nearest and farthest entries."""
        lo, hi = self.planner.entry_x_range
        m = self.machine_x
        return remaining.intersection(shapely.box(m + lo, self.bottom_y - 1.0, m + hi, self.top_y))

    def _relocate_for_rest(self, remaining: Any) -> bool:
        """Travel away from the trench when nothing more can be dug here and design material
        is left nearer to the machine than the nearest entry (a trench longer than the reach):
        the far edge of that part comes 5 cm inside the farthest entry. Returns whether the
        machine moved (at most :data:`_MAX_TRAVELS` times a task)."""
        if self._travels >= _MAX_TRAVELS:
            return False
        lo, hi = self.planner.entry_x_range
        s = self.planner.scale
        near = remaining.intersection(
            shapely.box(self.x_lo, self.bottom_y - 1.0, self.machine_x + lo, self.top_y)
        )
        if near.is_empty or near.area < 0.005 * self.design_area:
            return False
        move = (near.bounds[2] - self.machine_x) - (hi - 0.05 * s)
        if move >= -1e-3:
            return False
        self._travel(move)
        self.phase = DigType.DOWNWARD
        self._finish_index = 0
        return True

    def _relocate_if_needed(self, remaining: Any) -> None:
        """Crawler travel when the rest of the design is beyond the entries' reach."""
        lo, hi = self.planner.entry_x_range
        maxx = remaining.bounds[2] - self.machine_x  # arm frame
        if lo <= maxx <= hi:
            return
        if self._travels >= _MAX_TRAVELS:
            return
        if self._reachable(remaining).area >= 0.005 * self.design_area:
            return  # material is left within reach: dig that first
        # Travel so that the far edge of the rest comes 5 cm inside the farthest entry:
        # negative (backing away) when the rest is too close to the machine.
        self._travel(maxx - (hi - 0.05 * self.planner.scale))

    def _travel(self, move: float) -> None:
        """Crawler travel by ``move`` (m along the trench); the arm's pose is unknown after."""
        self.steps.append(TravelMove(move, self.machine_x, self.machine_x + move))
        self.machine_x += move
        self._travels += 1
        self.q_now = None

    @_stage("screen")
    def _screen(self, xe: FloatArray, H: FloatArray) -> list[dict[str, Any]]:
        """The best candidates of the phase's dig types, best first, entering at ``xe``
        (:meth:`_entry_x_candidates`) where the surface is at ``H``."""
        kinds = [DigType.DOWNWARD] if self._phase() is DigType.DOWNWARD else list(DigType)
        found = [b for k in kinds for b in self._screen_kind(xe, H, k)]
        return sorted(found, key=lambda b: -b["score"])[:_N_RANKED]

    def _screen_kind(self, xe: FloatArray, H: FloatArray, kind: DigType) -> list[dict[str, Any]]:
        """The best candidates of one dig type, best first, screened on their geometry.

        Every (entry, exit) pose of the grid goes through the network at once; the tip path of
        each answer is known before the kernel runs (the fill scales the bulge ``K`` along its
        direction and the retiming keeps the path), so each path is computed on a coarse grid
        of samples at a few bulge scales, and the fill's scale, V_p against H, the over-dig
        and the real cut on the height field are interpolated between them. Only the ranked
        few are planned for real (:meth:`_first_plannable`), and those are checked on the
        verifier's full grid.
        """
        arm = self.planner.arm
        cand = _CANDIDATES[kind]
        m = self.machine_x
        lo, hi = self.planner.domain[kind]
        # Every (entry, exit) pose of the grid at once: entries (x, attitude) x exits
        # (length, rise, attitude); poses out of reach or limits are dropped.
        ea = np.radians(cand.entry_attitude_deg)
        n_x, n_a = xe.shape[0], ea.shape[0]
        qs, ok_s = arm.ik_many(np.repeat(xe - m, n_a), np.repeat(H, n_a), np.tile(ea, n_x))
        L, R, A = self.planner.exit_grid[kind]
        n_e, n_x = qs.shape[0], L.size
        ex = (np.repeat(xe, n_a)[:, None] - L[None, :]).ravel()
        ey = (np.repeat(H, n_a)[:, None] + R[None, :]).ravel()
        qe, ok_e = arm.ik_many(ex - m, ey, np.tile(A, n_e))
        X = np.empty((n_e * n_x, 7))
        X[:, 0:3] = np.repeat(qs, n_x, axis=0)
        X[:, 3:6] = qe
        X[:, 6] = np.repeat(np.repeat(H, n_a), n_x)
        ok = np.repeat(ok_s, n_x) & ok_e
        ok &= np.all((lo <= X) & (hi >= X), axis=1)
        X = X[ok]
        if X.shape[0] == 0:
            return []
        Y = self.planner.pinn.infer(kind, X)
        K = -Y[:, 0:3] * Y[:, 3:4] ** 6
        G = self.planner.screen_c
        vp, over, total, useful = self._screen_paths(X, K)
        cap_area = self.v_max_m3 / self.width_m
        # The fill's scale: the largest c <= c_max with V_p <= V_max (linear between scales).
        above = vp > cap_area * (1.0 - 1e-3)
        k = np.where(above.any(axis=1), np.argmax(above, axis=1), G.shape[0])
        kk = np.clip(k, 1, G.shape[0] - 1)
        r = np.arange(X.shape[0])
        v0, v1 = vp[r, kk - 1], vp[r, kk]
        frac = np.clip((cap_area - v0) / np.where(v1 > v0, v1 - v0, 1.0), 0.0, 1.0)
        c_cap = np.where(k == G.shape[0], G[-1], G[kk - 1] + frac * (G[kk] - G[kk - 1]))
        c_cap = np.where(k == 0, G[0] * cap_area / np.maximum(vp[:, 0], 1e-12), c_cap)
        min_useful = MIN_USEFUL_FRACTION * self.design_area
        min_area = self.planning.volume_min_m3 / self.width_m * 1.02
        rows, caps, uses, totals = [], [], [], []
        for j, c_max in enumerate(sorted(cand.c_max, reverse=True)):
            c = np.minimum(c_max, c_cap)
            # A smaller cap than the fill reaches anyway is the same path: screened once.
            valid = c >= min(PLAN_C_RANGE[0], c_max)
            if j:
                valid &= c_cap >= c_max
            kc = np.clip(np.searchsorted(G, c), 1, G.shape[0] - 1)
            w = np.clip((c - G[kc - 1]) / (G[kc] - G[kc - 1]), 0.0, 1.0)
            o, t, u, v = (
                a[r, kc - 1] * (1.0 - w) + a[r, kc] * w for a in (over, total, useful, vp)
            )
            # Below V_min the fill finds no scale and falls back to the network's own path.
            valid &= v >= min_area
            good = np.flatnonzero(
                valid & (o <= _SCREEN_OVERDIG_M) & (t <= cap_area) & (u >= min_useful)
            )
            rows.append(good)
            caps.append(np.full(good.shape[0], c_max))
            uses.append(u[good])
            totals.append(t[good])
        idx, cm, u, t = (np.concatenate(a) for a in (rows, caps, uses, totals))
        score = u - 2.0 * (t - u)
        best = np.argsort(-score, kind="stable")[:_N_RANKED]
        return [
            {
                "kind": kind,
                "x7": X[idx[b]],
                "c_max": float(cm[b]),
                "useful": float(u[b]),
                "total": float(t[b]),
                "score": float(score[b]),
            }
            for b in best
        ]

    def _screen_paths(self, X: FloatArray, K: FloatArray) -> FloatArray:
        """The screening geometry of candidates ``X`` ``(N, 7)`` with bulge directions ``K``
        ``(N, 3)``: ``(4, N, G)``, for each of the G screening scales c the path's V_p against
        H, its over-dig (:meth:`_overdig_many`) and the total and design-inside cut on the
        height field (:meth:`_cut_estimate`), all m or m^2 on the coarse samples.

        The C kernel (``Kernel.screen`` in ``_verify.c``) computes it where the verifier runs
        on C (~0.3 ms for ~400 candidates against ~1.7 ms); :meth:`_screen_paths_numpy` is the
        reference and the fallback.
        """
        kernel = self.planner.geo_kernel
        if kernel is None:
            return self._screen_paths_numpy(X, K)
        pl = self.planner
        out = np.empty((4, X.shape[0], pl.screen_c.shape[0]))
        kernel.screen(
            np.ascontiguousarray(X),
            np.ascontiguousarray(K),
            pl.screen_shapes,
            pl.screen_c,
            *self._geometry_args(),
            out,
        )
        return out

    def _screen_paths_numpy(self, X: FloatArray, K: FloatArray) -> FloatArray:
        """:meth:`_screen_paths` in numpy (the reference of the C kernel)."""
        arm = self.planner.arm
        m = self.machine_x
        # Paths at the screening scales: q(s) = q1 + qf(s) (q2 - q1) + c pf(s) K.
        qf, pf = self.planner.screen_qf, self.planner.screen_pf
        base = X[:, None, 0:3] + qf[None, :, None] * (X[:, None, 3:6] - X[:, None, 0:3])
        G = self.planner.screen_c
        bulge = pf[None, :, None] * K[:, None, :]
        q = base[:, None] + G[None, :, None, None] * bulge[:, None]
        x, y = arm.tip_xy(q)
        x += m
        vp = oneshot.excavated_area_m2(x - m, y, X[:, 6, None])
        over = self._overdig_many_numpy(np.stack([x, y], axis=-1))
        total, useful = self._cut_estimate(x, y)
        return np.stack([vp, over, total, useful])

    def _on_grid(self, x: FloatArray, *fields: FloatArray) -> list[FloatArray]:
        """``np.interp`` of fields on the uniform grid at ``x`` (clamped at the ends)."""
        u = np.clip((x - self.grid[0]) / GRID_STEP_M, 0.0, self.grid.shape[0] - 1.000001)
        i = u.astype(np.int64)
        w = u - i
        return [f[i] * (1.0 - w) + f[i + 1] * w for f in fields]

    def _cut_estimate(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(total, inside-design) area sampled paths ``(..., n)`` cut from the height field,
        integrated along each path (exact for a path that does not turn back in x)."""
        xm = 0.5 * (x[..., 1:] + x[..., :-1])
        ym = 0.5 * (y[..., 1:] + y[..., :-1])
        dx = np.abs(np.diff(x, axis=-1))
        surf, floor = self._on_grid(xm, self.surface, self.design_floor)
        total = np.sum(np.maximum(surf - ym, 0.0) * dx, axis=-1)
        useful = np.sum(np.maximum(surf - np.maximum(ym, floor), 0.0) * dx, axis=-1)
        return total, useful

    # -- finishing passes ---------------------------------------------------------------------

    @_stage("passes")
    def _finishing(self, remaining: Any, *, layers: bool = False) -> list[dict[str, Any]]:
        """The next profile pass, or None when none is left or none removes enough.

        Roughing digs follow their own (PINN) path shape, which cannot reach into the design's
        corners; two passes then trace the profile: the far wall and the bottom (a downward
        dig), and the bottom and the near wall (a backward dig). Each is a sextic of the same
        family, its entry/exit attitudes and bulge K fitted by least squares to the profile
        polyline (shifted inwards until the over-dig limit holds), retimed and verified by the
        kernel like every dig, except for the one-shot volume window: V_p is defined against
        a flat surface at H, which a finishing pass does not have; the bucket capacity is
        enforced on the real cut instead.
        """
        t = self.task
        g = self.ground_y
        xf, xn = t.start_x_m, t.start_x_m - t.length_m
        A = (xf, g)
        B = (xf - t.depth_m / math.tan(t.beta1_rad), self.bottom_y)
        C = (xn + t.depth_m / math.tan(t.beta2_rad), self.bottom_y)
        D = (xn, g)
        passes: list[_Pass] = [
            (DigType.DOWNWARD, np.array([A, B]), ((-80.0, -100.0), (-95.0, -120.0)))
        ]
        passes += self._bottom_passes(B, C)
        passes.append((DigType.DOWNWARD, np.array([D, C]), ((-80.0, -100.0), (-100.0, -130.0))))
        # ``layers``: where those fail and no other stand helps (the boom's torque through a
        # thick face: a short trench whose roughing digs do not fit left up to 69 % of its
        # design), the rest is taken in layers from the top, each a bottom-like pass from
        # wall to wall at a fixed height, and the profile passes then run again under them.
        # The list only grows at its end, so _finish_index counts through both; a plan that
        # never needs the layers is unchanged.
        standard = len(passes)
        n_layers = math.ceil(t.depth_m / (_LAYER_M * self.planner.scale)) if layers else 0
        for k in range(1, n_layers):
            y = self.bottom_y + t.depth_m * (1.0 - k / n_layers)
            far = (xf - (g - y) / math.tan(t.beta1_rad), y)
            near = (xn + (g - y) / math.tan(t.beta2_rad), y)
            passes += self._bottom_passes(far, near)
        if len(passes) > standard:
            passes += passes[:standard]
        while self._finish_index < len(passes):
            kind, poly, atts = passes[self._finish_index]
            self._finish_index += 1
            fit = self._fit_pass(kind, poly, atts)
            if fit is not None:
                return [fit]
        return []

    def _bottom_passes(self, far: tuple[float, float], near: tuple[float, float]) -> list[_Pass]:
        """Backward passes along the straight line from ``far`` to ``near`` (the bottom, or a
        layer): a sextic follows a straight line within a few mm over ~0.3 m (scale model), so
        a longer line is cut in equal pieces, far to near, each starting 2 mm up so that it
        enters descending (theta_p >= 0)."""
        lift = np.array([0.0, 0.002])
        n = max(1, math.ceil((far[0] - near[0]) / (_PASS_LENGTH_M * self.planner.scale)))
        a, b = np.asarray(far), np.asarray(near)
        cuts = [a + (b - a) * k / n for k in range(n + 1)]
        atts = ((-110.0, -135.0), (-150.0, -175.0))
        return [(DigType.BACKWARD, np.array([cuts[k] + lift, cuts[k + 1]]), atts) for k in range(n)]

    def _fit_pass(
        self,
        kind: DigType,
        poly: FloatArray,
        atts: tuple[tuple[float, ...], tuple[float, ...]],
    ) -> dict[str, Any] | None:
        """Fit one straight profile pass ``poly`` (2 points, work-site frame).

        For each pair of end attitudes of ``atts`` the sextic's path is linear in its bulge
        ``K`` in joint space, so the signed distances of the path samples from the line are
        fitted in ``K`` by Gauss-Newton (two linearised least-squares steps of a 3 x 3 system,
        microseconds); a pair whose fit leaves the joint limits or the theta_p range is
        skipped. The first pair that fits within ~1 mm RMS, or else the best, is taken; the
        line is shifted inwards (0, 2, 4, 7 mm) until the over-dig limit holds.
        """
        arm = self.planner.arm
        m = self.machine_x
        a, b = np.asarray(poly[0], dtype=np.float64), np.asarray(poly[-1], dtype=np.float64)
        seg = b - a
        normal = np.array([-seg[1], seg[0]]) / math.hypot(seg[0], seg[1])
        # Inwards: towards the design's centroid.
        c = self.design.centroid
        if (c.x - a[0]) * normal[0] + (c.y - a[1]) * normal[1] < 0.0:
            normal = -normal
        qf, pf = self.planner.fit_qf, self.planner.fit_pf
        margin = math.radians(0.5)
        lo_q, hi_q = arm.q_min + margin, arm.q_max - margin
        tp_lo, tp_hi = (float(v) for v in oneshot.theta_p_range(self.planning, int(kind)))
        qf_full, pf_full = self.planner.full_qf, self.planner.full_pf
        good = _GOOD_FIT_COST * qf.shape[0] / 101.0

        def candidate(q1: FloatArray, q2: FloatArray, K: FloatArray) -> dict[str, Any] | None:
            qp = q1 + qf_full[:, None] * (q2 - q1) + pf_full[:, None] * K
            px, py = arm.tip_xy(qp)
            tip = np.stack([px + m, py], axis=1)
            if self.overdig_of(tip) > OVERDIG_LIMIT_M:
                return None
            return self._pass_candidate(kind, q1, q2, K, tip)

        for offset in (0.0, 0.002, 0.004, 0.007):
            a_s = a + offset * normal
            b_s = b + offset * normal
            mid = [(v[0], v[-1], *np.linspace(v[0], v[-1], 5)[1:-1].tolist()) for v in atts]
            starts = [self._pass_pose(a_s, mid[0]), self._pass_pose(b_s, mid[1])]
            fits: list[tuple[float, FloatArray, FloatArray, FloatArray]] = []
            # Table pairs first; a good fit is tried at once, the others by cost at the end.
            for qs in starts[0]:
                for qe in starts[1]:
                    q1, q2 = np.asarray(qs), np.asarray(qe)
                    base = q1 + qf[:, None] * (q2 - q1)
                    K, cost = self._fit_bulge(base, q1, q2, a_s, normal, offset, kind)
                    q = base + pf[:, None] * K
                    if np.any(q < lo_q) or np.any(q > hi_q):
                        continue
                    # theta_p: the entry direction J(q1) (10 D + K) in the type's range.
                    jac = kinematics.jacobian(self.rig, q1)[:2]
                    d0 = jac @ (10.0 * (q2 - q1) + K)
                    ang = math.atan2(-d0[1], abs(d0[0]))
                    if not tp_lo + 0.01 <= ang <= tp_hi - 0.01:
                        continue
                    if cost < good:
                        found = candidate(q1, q2, K)
                        if found is not None:
                            return found
                    else:
                        fits.append((cost, q1, q2, K))
            for _, q1, q2, K in sorted(fits, key=lambda f: f[0]):
                found = candidate(q1, q2, K)
                if found is not None:
                    return found
        return None

    def _pass_pose(self, point: FloatArray, attitudes_deg: tuple[float, ...]) -> list[FloatArray]:
        """Joint poses of a pass end at the table's attitudes; where one is out of reach or
        limits, the nearest attitude (5 deg steps, up to 45 deg away) that is not."""
        arm = self.planner.arm
        found: list[FloatArray] = []
        for att in attitudes_deg:
            for step in range(10):
                for sign in (1.0,) if step == 0 else (1.0, -1.0):
                    q = arm.ik(
                        float(point[0]) - self.machine_x,
                        float(point[1]),
                        math.radians(att + sign * 5.0 * step),
                    )
                    if q is not None:
                        break
                if q is not None:
                    found.append(np.asarray(q))
                    break
        return found

    def _fit_bulge(
        self,
        base: FloatArray,
        q1: FloatArray,
        q2: FloatArray,
        a_s: FloatArray,
        normal: FloatArray,
        offset: float,
        kind: DigType,
    ) -> tuple[FloatArray, float]:
        """Damped Gauss-Newton fit of the bulge ``K`` (3) of a profile pass: the signed
        distances of the path samples from the shifted line (weighted 21x where the path
        crosses the design line outwards by > 3 mm) and, while it is violated, the entry
        direction's theta_p bound as a heavily weighted row. Returns ``(K, cost)``."""
        arm = self.planner.arm
        pf = self.planner.fit_pf
        lengths = arm.lengths
        m = self.machine_x
        tp_lo, tp_hi = (float(v) for v in oneshot.theta_p_range(self.planning, int(kind)))
        jac0 = kinematics.jacobian(self.rig, q1)[:2]
        d_ent = jac0 @ (10.0 * (q2 - q1))
        mu = 1e-7
        K = np.zeros(3)
        step = np.zeros(3)
        cost = math.inf
        for _ in range(8):
            q = base + pf[:, None] * K
            phi = np.cumsum(q, axis=1)
            cs, sn = np.cos(phi) * lengths, np.sin(phi) * lengths
            d = (cs.sum(axis=1) + m - a_s[0]) * normal[0] + (sn.sum(axis=1) - a_s[1]) * normal[1]
            w = np.where(d + offset + 0.003 < 0.0, 21.0, 1.0)
            r = w * d
            jx = -np.cumsum(sn[:, ::-1], axis=1)[:, ::-1]
            jy = np.cumsum(cs[:, ::-1], axis=1)[:, ::-1]
            J = (normal[0] * jx + normal[1] * jy) * (pf * w)[:, None]
            # theta_p of the entry direction d0 = J(q1) (10 D + K), linear in K.
            d0 = d_ent + jac0 @ K
            ang = math.atan2(-d0[1], abs(d0[0]))
            sx = 1.0 if d0[0] >= 0.0 else -1.0
            rows, rhs = [J], [-r]
            pen = 0.0
            for bound, up in ((tp_lo + 0.02, False), (tp_hi - 0.02, True)):
                if (ang > bound) if up else (ang < bound):
                    # g(K) = -d0_y cos(b) - |d0_x| sin(b): zero on the bound.
                    gk = -jac0[1] * math.cos(bound) - sx * jac0[0] * math.sin(bound)
                    g = -d0[1] * math.cos(bound) - abs(d0[0]) * math.sin(bound)
                    rows.append(gk[None] * 0.5)
                    rhs.append(np.array([-g * 0.5]))
                    pen += (0.5 * g) ** 2
            new_cost = float(r @ r) + pen
            if new_cost > cost:  # the step made it worse: back off, damp harder
                K = K - 0.5 * step
                mu *= 10.0
                continue
            cost = new_cost
            A = np.concatenate(rows)
            b = np.concatenate(rhs)
            step = np.linalg.solve(A.T @ A + mu * np.eye(3), A.T @ b - mu * K)
            K = K + step
            if float(step @ step) < 1e-6:
                break
        return K, cost

    def _pass_candidate(
        self, kind: DigType, qs: FloatArray, qe: FloatArray, K: FloatArray, tip: FloatArray
    ) -> dict[str, Any] | None:
        """A fitted profile pass retimed and checked, as a ranked candidate (None: refused)."""
        # The verifier's soil model takes depth below a flat H; here the material over the
        # path is a thin layer, so H is the level of the deepest real cut: the real depth at
        # the path's lowest point, the layer's thickness elsewhere approximated by it.
        depth = np.interp(tip[:, 0], self.grid, self.surface) - tip[:, 1]
        H = float(np.min(tip[:, 1]) + max(0.0, float(np.max(depth))))
        T0 = 0.5 * (self.planning.t_min_s + self.planning.t_max_s)
        a6 = -K / T0**6
        row = pack_inputs(
            qs[None], qe[None], np.array([H]), np.array([int(kind)]), a6[None], np.array([T0])
        )
        out = np.zeros((1, N_OUT))
        retimed = np.zeros((1, 4))
        self.planner.verifier.retime_into(row, out, retimed)
        if not np.isfinite(retimed[0, 3]) or _total_without_volume(out[0]) > 0.0:
            return None
        total, useful = self._cut_areas(self._envelope(tip, self.grid))
        if (
            total > self.v_max_m3 / self.width_m
            or useful < 0.1 * MIN_USEFUL_FRACTION * self.design_area
        ):
            return None
        x7 = np.concatenate([qs, qe, [H]])
        return {
            "kind": kind,
            "x7": x7,
            "finishing": (tuple(float(v) for v in retimed[0, 0:3]), float(retimed[0, 3])),
            "c_max": 1.0,
            "useful": useful,
            "total": total,
            "score": useful,
        }

    def _fine_grid_time(
        self, problem: Problem, a6: tuple[float, float, float], T_s: float
    ) -> tuple[tuple[float, float, float], float]:
        """The same path, slowed just enough that the joint accelerations hold on a grid 10x
        finer than the verifier's (a retimed plan sits on the limit at the verifier's samples
        and may peak a few 1e-4 above it between them); unchanged when they already hold or
        the slower time would leave the time range. The caller verifies the result.
        """
        q1 = np.asarray(problem.q_start_rad)
        D = np.asarray(problem.q_end_rad) - q1
        K = -np.asarray(a6) * T_s**6
        qdd = self.planner.fine_qf2[:, None] * D + self.planner.fine_pf2[:, None] * K
        ratio = float(np.max(np.abs(qdd) / self.planner.qdd_max)) / T_s**2
        if ratio <= 1.0:
            return a6, T_s
        T_new = T_s * math.sqrt(ratio) * (1.0 + 1e-9)
        if T_new > self.planning.t_max_s:
            return a6, T_s
        a_new = -K / T_new**6
        return (float(a_new[0]), float(a_new[1]), float(a_new[2])), T_new

    @_stage("checks")
    def _plan_chosen(self, best: dict[str, Any], remaining: Any, select_us: float) -> PlannedDig:
        """Plan ``best`` for real and check it; ``remaining`` is :meth:`remaining_design` (the
        caller's, the material being unchanged since)."""
        x7 = best["x7"]
        problem = Problem(
            q_start_rad=(float(x7[0]), float(x7[1]), float(x7[2])),
            q_end_rad=(float(x7[3]), float(x7[4]), float(x7[5])),
            surface_y_m=float(x7[6]),
            dig_type=best["kind"],
        )
        finishing = best.get("finishing")
        if finishing is not None:
            res = OneShotResult(finishing[0], finishing[1], np.zeros(N_OUT), 0.0, "profile_pass")
        else:
            t_plan = time.perf_counter()
            res = self.planner.oneshot.plan_dig(problem, float(best["c_max"]))
            spent = (time.perf_counter() - t_plan) * 1e6
            self.stage_us["oneshot"] += spent
            self.stage_us["checks"] -= spent
        a6, T_s = self._fine_grid_time(problem, res.a6, res.T_s)
        pb = problem
        row = pack_inputs(pb.q_start_rad, pb.q_end_rad, pb.surface_y_m, pb.dig_type, a6, T_s)
        out = np.zeros((1, N_OUT))
        path = np.zeros((1, self.planner.verifier.n_samples, 2))
        self.planner.verifier.evaluate_into(row, out, path=path)
        violation = _total_without_volume(out[0]) if finishing else out[0, COL_TOTAL]
        if violation > 0.0 and T_s != res.T_s:  # the slower plan fails: keep the verified one
            a6, T_s = res.a6, res.T_s
            row[0, 8:11] = a6
            row[0, 11] = T_s
            self.planner.verifier.evaluate_into(row, out, path=path)
            violation = _total_without_volume(out[0]) if finishing else out[0, COL_TOTAL]
        if violation > 0.0:
            raise PlanningError("one-shot plan fails verification; nothing was planned")
        p = path[0].copy()
        p[:, 0] += self.machine_x
        over = self.overdig_of(p)
        env = self._envelope(p, self.grid)
        total, useful = self._cut_areas(env)
        if finishing is None and useful < 0.5 * MIN_USEFUL_FRACTION * self.design_area:
            raise PlanningError(
                f"the {self.planner.oneshot.name} plan of dig {len(self.digs) + 1} removes "
                f"{useful * self.width_m * 1e3:.3f} L of the design, less than the screening "
                "promised"
            )
        if over > OVERDIG_LIMIT_M or total > self.v_max_m3 / self.width_m:
            raise PlanningError(
                f"the {self.planner.oneshot.name} plan of dig {len(self.digs) + 1} over-digs "
                f"{over * 1e3:.1f} mm or exceeds the bucket ({total * self.width_m * 1e3:.2f} L)"
            )
        # The record: polygon areas (the height field above only screened and checked), and
        # the over-dig of the region the dig removes, as the finished plan measures it. The
        # samples' over-dig above counts a sample where the 1 mm height field says it is in
        # material; beside a steep face the polygon holds material the height field does not
        # (a 1.0 m x 0.12 m trench ended 5.9 mm deep with every dig's samples <= 4.9 mm).
        swept = _swept_polygon(p, self.grid, self.top_y, env, self._envelope)
        # record() of this very path (the open-loop plan) reuses the envelope and region.
        self._planned_region = (p, env, swept)
        if swept is not None:
            cut = self.material.intersection(swept)
            total = float(cut.area)
            useful = float(remaining.intersection(swept).area)
            over = max(over, self._overdig_of_region(cut))
            if over > OVERDIG_LIMIT_M:
                raise PlanningError(
                    f"the {self.planner.oneshot.name} plan of dig {len(self.digs) + 1} "
                    f"over-digs {over * 1e3:.1f} mm (the region it removes)"
                )
        return PlannedDig(
            index=len(self.digs),
            problem=problem,
            a6=a6,
            T_s=T_s,
            machine_x_m=self.machine_x,
            tip_path_m=p,
            volume_m3=total * self.width_m,
            design_volume_m3=useful * self.width_m,
            predicted_volume_m3=float(out[0, COL_VOLUME_M3]),
            energy_j=float(out[0, COL_ENERGY_J]),
            theta_p_rad=float(out[0, COL_THETA_P_RAD]),
            overdig_m=over,
            plan_us=res.plan_us,
            select_us=select_us,
            planner=self.planner.oneshot.name,
            status=res.status,
            evaluation=out[0].copy(),
        )

    # -- recording ----------------------------------------------------------------------------

    @_stage("record")
    def record(self, dig: PlannedDig, measured_path_m: ArrayLike) -> float:
        """Update the material from the executed dig's measured tip path (work-site frame).

        Returns:
            The volume (m^3) the measured path removed.

        Raises:
            PlanningError: ``dig`` is not the pending dig, or the path is not a finite
                ``(n >= 2, 2)`` array.
        """
        if self.pending is None or dig is not self.pending:
            raise PlanningError("record() takes the dig next_dig() returned last")
        path = np.asarray(measured_path_m, dtype=np.float64)
        if path.ndim != 2 or path.shape[1] != 2 or path.shape[0] < 2:
            raise PlanningError(f"measured path must have shape (n >= 2, 2); got {path.shape}")
        if not np.all(np.isfinite(path)):
            raise PlanningError("measured path has non-finite values")
        before = float(self.material.area)
        planned = self._planned_region
        if planned is not None and np.array_equal(path, planned[0]):
            env, swept = planned[1], planned[2]
        else:
            env = self._envelope(path, self.grid)
            swept = _swept_polygon(path, self.grid, self.top_y, env, self._envelope)
        self._planned_region = None
        if swept is not None:
            self.material = self.material.difference(swept)
        self.surface = np.minimum(self.surface, env)
        removed = (before - float(self.material.area)) * self.width_m
        self.steps.append(dig)
        self.digs.append(dig)
        self.q_now = np.asarray(dig.problem.q_end_rad)
        self.pending = None
        return removed

    # -- transitions --------------------------------------------------------------------------

    @_stage("transitions")
    def _append_transitions(self, dig: PlannedDig) -> None:
        """Dump the previous load and approach this dig's entry (ruckig, rest to rest)."""
        if self.q_now is not None:
            self.steps.extend(self.exit_transitions(self.q_now))
        self.steps.extend(self.entry_transitions(dig, self.planner.dump_pose_rad))

    def exit_transitions(
        self, q_from_rad: ArrayLike, *, after: PlannedDig | None = None
    ) -> tuple[Transition, ...]:
        """Lift out of the material and go to the dump pose, from any pose (arm frame).

        ``lift_out`` goes straight up, the tip's x and attitude kept, until the whole bucket is
        :data:`_LIFT_CLEAR_M` above the material under it, or higher where the way to the dump
        pose needs it (the lowest clear one of :meth:`_lift_heights`: on A-D the lowest is
        always clear and a higher lift only adds time); a lift whose joint-space move strays
        from the vertical into the material is made in pieces through poses on it. ``dump``
        goes from there to the dump pose. A pose already clear of the material goes to the
        dump pose without a lift. The executor streams these after each dig while the next one
        is planned, and from a measured pose inside the material when a run resumes.

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
            moves = self._plan_exit(q0, surface)
            self._remember(key, surface, moves)
        return moves

    def entry_transitions(self, dig: PlannedDig, q_from_rad: ArrayLike) -> tuple[Transition, ...]:
        """Approach ``dig``'s entry from ``q_from_rad`` (the dump pose) and enter the material.

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
        the dump pose, and out of its exit over the material it leaves (a layer pass may end
        too near the machine to lift the bucket straight up, and that was only found when the
        next dig was planned, as an error). The moves are kept for when they are asked for."""
        self.entry_transitions(dig, self.planner.dump_pose_rad)
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

    def _plan_exit(self, q0: FloatArray, surface: FloatArray) -> tuple[Transition, ...]:
        """:meth:`exit_transitions` on the height field ``surface``."""
        mover = self.planner.mover
        x0, y0, z0 = mover.arm.tip(q0)
        dump = np.asarray(self.planner.dump_pose_rad, dtype=np.float64)
        # The material straight above the bucket's outline at the start is what it carries
        # out going straight up.
        bx, by = mover.bucket_xy(q0)
        start = np.stack([bx + self.machine_x, by], axis=1)
        carry = np.minimum(surface, self._envelope(start, self.grid))
        refused: list[Transition] = []
        for y_lift in self._lift_heights(q0, surface):
            moves: list[Transition] = []
            q_top = q0
            if y_lift > y0 + 1e-6:
                lift = self._lift(q0, y_lift, carry)
                if lift is None:
                    continue
                moves.extend(lift)
                q_top = np.asarray(lift[-1].q_to_rad)
            moves.append(self._checked("dump", q_top, dump, surface if moves else carry))
            bad = [m for m in moves if m.penetration_m > TRANSITION_PENETRATION_M]
            if bad:
                refused.append(max(bad, key=lambda m: m.penetration_m))
                continue
            return tuple(moves)
        raise PlanningError(
            self._refusal("exit", (x0 + self.machine_x, y0, z0), refused, "no lift pose")
        )

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
        self, q0: FloatArray, y_lift: float, carry: FloatArray
    ) -> tuple[Transition, ...] | None:
        """``lift_out`` from ``q0`` straight up to tip height ``y_lift``: one move, or where it
        strays from the vertical into the material, pieces through poses on the vertical
        (the fewest that are clear; else the one move, to be refused). None: out of reach."""
        arm = self.planner.mover.arm
        x0, y0, z0 = arm.tip(q0)
        first: tuple[Transition, ...] | None = None
        for pieces in (1, 2, 3):
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
                self._checked("lift_out", a, b, carry) for a, b in itertools.pairwise(poses)
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
        mover = self.planner.mover
        arm = mover.arm
        s = self.planner.scale
        xe, ye, ze = arm.tip(q_entry)
        allow = self._bucket_depth(q_entry[None], surface, np.inf)[0]
        clear = _LIFT_CLEAR_M * s
        refused: list[Transition] = []
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
                enter = self._checked("enter", q_above, q_entry, surface, allow)
                if enter.penetration_m > TRANSITION_PENETRATION_M:
                    refused.append(enter)
                    continue
                approach = self._checked("approach", q_from, q_above, surface)
                if approach.penetration_m > TRANSITION_PENETRATION_M:
                    refused.append(approach)
                    continue
                return (approach, enter)
        raise PlanningError(
            self._refusal("entry", (xe + self.machine_x, ye, ze), refused, "no approach pose")
        )

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
            f"no clear {what} moves at {where}: the {m.kind} move goes {depth} into the "
            f"material at best (limit {TRANSITION_PENETRATION_M * 1e3:.0f} mm)"
        )

    def _checked(
        self,
        kind: str,
        qa: FloatArray,
        qb: FloatArray,
        surface: FloatArray,
        allow: FloatArray | None = None,
    ) -> Transition:
        """The ruckig move ``qa -> qb`` with its penetration (:meth:`_move_depth`)."""
        traj = self.planner.mover.move(qa, qb)
        return Transition(
            kind=kind,
            q_from_rad=(float(qa[0]), float(qa[1]), float(qa[2])),
            q_to_rad=(float(qb[0]), float(qb[1]), float(qb[2])),
            duration_s=float(traj.duration),
            machine_x_m=self.machine_x,
            penetration_m=self._move_depth(traj, qa, qb, surface, allow),
        )

    def _move_depth(
        self,
        traj: Any,
        qa: FloatArray,
        qb: FloatArray,
        surface: FloatArray,
        allow: FloatArray | None,
    ) -> float:
        """The deepest any point of the bucket outline goes into the material under
        ``surface`` (:func:`_depth_below`) on the move ``traj`` from ``qa`` to ``qb``, less
        ``allow`` ``(m,)`` per outline point where given (m, >= 0).

        Sampled where the bucket comes near the material: on samples that no point of the
        bucket moves :data:`_COARSE_STEP_M` between, a stretch where the bucket's bounding box
        stays that far above the highest material under it (that far to either side) cannot
        touch it; the rest is sampled every :data:`_MOVE_STEP_M` of the bucket's travel with
        the whole outline. Between samples and outline points a point can be deeper by at
        most half their spacing (a point's depth changes no faster than the point moves).
        Depths beyond :data:`_DEPTH_CAP_M` (past ``allow``) count as that.
        """
        mover = self.planner.mover
        h = GRID_STEP_M
        last = self.grid.shape[0] - 1
        reach = _COARSE_STEP_M
        times = np.linspace(0.0, float(traj.duration), mover.n_samples(qa, qb, reach))
        x, y = mover.bucket_xy(mover.poses(traj, times), corners=True)
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
        if allow is None:
            depth = self._bucket_depth(mover.poses(traj, fine), surface)
        else:
            depth = self._bucket_depth(mover.poses(traj, fine), surface, allow + _DEPTH_CAP_M)
            depth -= allow
        return max(0.0, float(np.max(depth)))

    def _bucket_depth(
        self, q: FloatArray, surface: FloatArray, cap_m: ArrayLike = _DEPTH_CAP_M
    ) -> FloatArray:
        """How deep each point of the bucket outline is in the material, poses ``(n, 3)`` ->
        ``(n, m)`` (m, up to ``cap_m``, :func:`_depth_below`)."""
        x, y = self.planner.mover.bucket_xy(q)
        return _depth_below(self.grid, surface, x + self.machine_x, y, cap_m)

    # -- persistence --------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """The session as JSON-able data (``json.dumps`` takes it as it is).

        Keys: ``version``, ``rig``, ``planner``, ``task`` (name and dimensions), ``material_wkt``
        (the material polygon as WKT, full precision), ``surface_m`` (height field on the 1 mm
        grid), ``machine_x_m``, ``q_now_rad`` (the last dig's exit or None), ``phase``
        (``downward``/``backward``), ``finish_index`` (profile passes tried), ``digs_done``,
        ``steps`` (every recorded dig, transition and travel move, each a dict with ``type``),
        and ``pending`` (the dig :meth:`next_dig` returned and :meth:`record` has not taken yet,
        or None; after :meth:`record` it is always None, which is the state to persist).
        """
        t = self.task
        return {
            "version": _STATE_VERSION,
            "rig": self.rig.name,
            "planner": self.planner.oneshot.name,
            "task": {
                "name": t.name,
                "length_m": t.length_m,
                "depth_m": t.depth_m,
                "beta1_rad": t.beta1_rad,
                "beta2_rad": t.beta2_rad,
                "start_x_m": t.start_x_m,
            },
            "material_wkt": shapely.to_wkt(self.material, rounding_precision=-1),
            "surface_m": [float(v) for v in self.surface],
            "machine_x_m": float(self.machine_x),
            "q_now_rad": None if self.q_now is None else [float(v) for v in self.q_now],
            "phase": self.phase.name.lower(),
            "finish_index": int(self._finish_index),
            "digs_done": len(self.digs),
            "steps": [_step_to_json(step) for step in self.steps],
            "pending": None if self.pending is None else _step_to_json(self.pending),
        }

    @classmethod
    def restore(
        cls, planner: TrenchPlanner, task: TrenchTask, state: dict[str, Any]
    ) -> TrenchSession:
        """A session continuing from :meth:`state` (a daemon restart resumes the next dig).

        Args:
            planner: The planner (same rig as the state's).
            task: The task (same as the state's).
            state: What :meth:`state` returned (after a JSON round trip or not).

        Raises:
            ConfigurationError: A key is missing or malformed, the version is unknown, or the
                rig or task differ from the state's (the message names the key).
        """
        session = cls(planner, task)
        session.apply_state(state)
        return session

    def apply_state(self, state: dict[str, Any]) -> None:
        """Replace this session's progress by ``state`` (see :meth:`restore`).

        Raises:
            ConfigurationError: As :meth:`restore`.
        """
        try:
            version = state["version"]
            if version != _STATE_VERSION:
                raise ConfigurationError(
                    f"session state version {version!r}; allowed: {_STATE_VERSION}"
                )
            if state["rig"] != self.rig.name:
                raise ConfigurationError(
                    f"session state key 'rig' is {state['rig']!r}; this planner's rig is "
                    f"{self.rig.name!r}"
                )
            t = state["task"]
            mine = self.task
            same = t["name"] == mine.name and all(
                abs(float(t[k]) - float(getattr(mine, k))) <= 1e-12
                for k in ("length_m", "depth_m", "beta1_rad", "beta2_rad", "start_x_m")
            )
            if not same:
                raise ConfigurationError(
                    f"session state key 'task' is {t}; the session's task is {mine}"
                )
            material = shapely.from_wkt(state["material_wkt"])
            surface = np.asarray(state["surface_m"], dtype=np.float64)
            if surface.shape != self.surface.shape or not np.isfinite(surface).all():
                raise ConfigurationError(
                    f"session state key 'surface_m' has shape {surface.shape}; allowed: "
                    f"{self.surface.shape} finite values (the task's 1 mm grid)"
                )
            steps = [_step_from_json(item) for item in state["steps"]]
            q_now = state["q_now_rad"]
            phase = DigType[str(state["phase"]).upper()]
            machine_x = float(state["machine_x_m"])
            finish_index = int(state["finish_index"])
            pending = state.get("pending")
            pending_dig = None if pending is None else _step_from_json(pending)
            if pending_dig is not None and not isinstance(pending_dig, PlannedDig):
                raise ConfigurationError("session state key 'pending' is not a dig")
        except ConfigurationError:
            raise
        except (KeyError, TypeError, ValueError, GEOSException) as exc:
            raise ConfigurationError(f"session state is malformed: {exc!r}") from exc
        self.material = material
        self.surface = surface
        self.steps = steps
        self.digs = [s for s in steps if isinstance(s, PlannedDig)]
        self.machine_x = machine_x
        self.q_now = None if q_now is None else np.asarray(q_now, dtype=np.float64)
        self.pending = pending_dig
        self.phase = phase
        self._finish_index = finish_index
        # The travels so far are the steps' travel moves (the entries and the travel bound
        # depend on them; a resumed session counted none before).
        self._travels = sum(isinstance(s, TravelMove) for s in steps)

    @_stage("finish")
    def finish(self, plan_total_us: float) -> TrenchPlan:
        """The frozen plan of everything recorded so far."""
        dug = self.initial.difference(self.material)
        sym = dug.symmetric_difference(self.design)
        coverage = float(sym.area) / self.design_area
        over_max = self._overdig_of_region(dug)
        final_surface = np.stack([self.grid, self.surface], axis=1)
        removed = (float(self.initial.area) - float(self.material.area)) * self.width_m
        return TrenchPlan(
            task=self.task,
            rig=self.rig.name,
            planner=self.planner.oneshot.name,
            steps=tuple(self.steps),
            digs=tuple(self.digs),
            design=self.design,
            dug=dug,
            final_surface_m=final_surface,
            coverage_error=coverage,
            overdig_max_m=over_max,
            removed_m3=removed,
            design_m3=self.design_area * self.width_m,
            plan_total_us=plan_total_us,
        )


_STATE_VERSION = 1


def _step_to_json(step: PlannedDig | Transition | TravelMove) -> dict[str, Any]:
    """One session step as JSON-able data (tagged with ``type``)."""
    if isinstance(step, PlannedDig):
        p = step.problem
        return {
            "type": "dig",
            "index": step.index,
            "problem": {
                "q_start_rad": list(p.q_start_rad),
                "q_end_rad": list(p.q_end_rad),
                "surface_y_m": p.surface_y_m,
                "dig_type": p.dig_type.name.lower(),
            },
            "a6": list(step.a6),
            "T_s": step.T_s,
            "machine_x_m": step.machine_x_m,
            "tip_path_m": np.asarray(step.tip_path_m, dtype=np.float64).tolist(),
            "volume_m3": step.volume_m3,
            "design_volume_m3": step.design_volume_m3,
            "predicted_volume_m3": step.predicted_volume_m3,
            "energy_j": step.energy_j,
            "theta_p_rad": step.theta_p_rad,
            "overdig_m": step.overdig_m,
            "plan_us": step.plan_us,
            "select_us": step.select_us,
            "planner": step.planner,
            "status": step.status,
            "evaluation": np.asarray(step.evaluation, dtype=np.float64).tolist(),
        }
    if isinstance(step, Transition):
        return {
            "type": "transition",
            "kind": step.kind,
            "q_from_rad": list(step.q_from_rad),
            "q_to_rad": list(step.q_to_rad),
            "duration_s": step.duration_s,
            "machine_x_m": step.machine_x_m,
            "penetration_m": step.penetration_m,
        }
    return {
        "type": "travel",
        "distance_m": step.distance_m,
        "machine_x_from_m": step.machine_x_from_m,
        "machine_x_to_m": step.machine_x_to_m,
    }


def _triple(values: Sequence[float]) -> tuple[float, float, float]:
    if len(values) != 3:
        raise ValueError(f"expected three values, got {len(values)}")
    return (float(values[0]), float(values[1]), float(values[2]))


def _step_from_json(item: dict[str, Any]) -> PlannedDig | Transition | TravelMove:
    """The inverse of :func:`_step_to_json` (raises KeyError/ValueError on bad data)."""
    kind = item["type"]
    if kind == "dig":
        p = item["problem"]
        path = np.asarray(item["tip_path_m"], dtype=np.float64).reshape(-1, 2)
        return PlannedDig(
            index=int(item["index"]),
            problem=Problem(
                q_start_rad=_triple(p["q_start_rad"]),
                q_end_rad=_triple(p["q_end_rad"]),
                surface_y_m=float(p["surface_y_m"]),
                dig_type=DigType[str(p["dig_type"]).upper()],
            ),
            a6=_triple(item["a6"]),
            T_s=float(item["T_s"]),
            machine_x_m=float(item["machine_x_m"]),
            tip_path_m=path,
            volume_m3=float(item["volume_m3"]),
            design_volume_m3=float(item["design_volume_m3"]),
            predicted_volume_m3=float(item["predicted_volume_m3"]),
            energy_j=float(item["energy_j"]),
            theta_p_rad=float(item["theta_p_rad"]),
            overdig_m=float(item["overdig_m"]),
            plan_us=float(item["plan_us"]),
            select_us=float(item["select_us"]),
            planner=str(item["planner"]),
            status=str(item["status"]),
            evaluation=np.asarray(item["evaluation"], dtype=np.float64),
        )
    if kind == "transition":
        return Transition(
            kind=str(item["kind"]),
            q_from_rad=_triple(item["q_from_rad"]),
            q_to_rad=_triple(item["q_to_rad"]),
            duration_s=float(item["duration_s"]),
            machine_x_m=float(item["machine_x_m"]),
            penetration_m=float(item["penetration_m"]),
        )
    if kind == "travel":
        return TravelMove(
            float(item["distance_m"]),
            float(item["machine_x_from_m"]),
            float(item["machine_x_to_m"]),
        )
    raise ValueError(f"unknown step type {kind!r}; allowed: dig, transition, travel")


# Bulge scales at which the screening computes each candidate's path; the fill's scale between
# them is interpolated.
_SCREEN_C = (0.3, 0.6, 1.0, 2.0)
# Samples per path in the screening (the plan is checked on the verifier's full grid).
_SCREEN_SAMPLES = 9
# Over-dig a screened path may show at its coarse samples (the plan's own check is exact).
_SCREEN_OVERDIG_M = 0.8 * OVERDIG_LIMIT_M
# Candidates kept per screening, tried in order when the one-shot planner's plan fails.
_N_RANKED = 4
# Lift heights a transition tries (TrenchSession._lift_heights).
_N_LIFT_HEIGHTS = 4
# Transitions kept for when they are asked for again (a dig's, its next dig's).
_N_CACHED_MOVES = 16
# Crawler travels per task at most.
_MAX_TRAVELS = 4
# Upper bound on profile passes (far wall, bottom pieces, near wall).
_N_MAX_PASSES = 40
#: Least material above the design floor where an entry may be placed (m, scale model).
_ENTRY_MIN_THICKNESS_M = 0.01
#: After a travel, entries also start at the far edge of the material at least this fraction of
#: its thickest within reach (:meth:`TrenchSession._entry_x_candidates`).
_ENTRY_BULK_FRACTION = 0.9
# A profile fit this good (least-squares cost, m^2: ~1 mm RMS) ends the search of starts.
_GOOD_FIT_COST = 2e-4
# Samples of a profile pass's path in its fit.
_FIT_SAMPLES = 41
# Longest straight profile pass (scale model, m).
_PASS_LENGTH_M = 0.30
#: Thickest layer of a layer pass (:meth:`TrenchSession._finishing`), m on the scale model.
_LAYER_M = 0.05
#: Least part of the design left (fraction) for which layer passes are tried.
_LAYER_MIN_LEFT = 0.03
#: A profile pass: its dig type, its line (2 points, work-site frame) and the attitude table of
#: its two ends (deg).
_Pass = tuple[DigType, FloatArray, tuple[tuple[float, ...], tuple[float, ...]]]
_VOLUME_COLUMNS = (
    oneshot.CONSTRAINT_NAMES.index("volume_min"),
    oneshot.CONSTRAINT_NAMES.index("volume_max"),
)


def _total_without_volume(row: FloatArray) -> float:
    """Total violation of a verifier row without the one-shot volume window."""
    v = row[0 : len(oneshot.CONSTRAINT_NAMES)].copy()
    v[list(_VOLUME_COLUMNS)] = 0.0
    return float(np.sum(np.maximum(v, 0.0)))


def _depth_below(
    grid: FloatArray, surface: FloatArray, x: FloatArray, y: FloatArray, cap_m: ArrayLike
) -> FloatArray:
    """How far points are inside the material under a height field (m, 0 outside it), up to
    ``cap_m``: ``min(depth, cap_m)``.

    The depth of a point ``(x, y)`` below ``surface`` (on the uniform ``grid``, linear between)
    is its distance to the nearest point above the surface, not the height of the surface over
    it: beside a steep face the two differ by the face's height (a tip 2 mm into the face of
    an 8 cm step is 2 mm deep, not 80 mm). The nearest point is sought in the grid columns
    within reach (the vertical depth, at most the cap), so the result is at most half a grid
    step too deep. Shapes: ``x``, ``y`` and the result alike; ``cap_m`` broadcasts to them.
    """
    h = float(grid[1] - grid[0])
    n = grid.shape[0]
    u = np.clip((x - grid[0]) / h, 0.0, n - 1.000001)
    i = u.astype(np.int64)
    w = u - i
    vertical = surface[i] * (1.0 - w) + surface[i + 1] * w - y
    out = np.zeros(np.shape(x))
    inside = vertical > 0.0
    if not np.any(inside):
        return out
    reach = np.minimum(vertical, np.broadcast_to(cap_m, np.shape(x)))[inside]
    px, py = x[inside], y[inside]
    col = np.rint((px - grid[0]) / h).astype(np.int64)
    depth = reach.copy()
    # Points in classes of reach (16 columns each): one window as wide as the deepest point's
    # costs ~10x more where a few points are deep (a bucket's back in a wall).
    cls = np.ceil(reach / (16.0 * h)).astype(np.int64)
    for j in np.unique(cls).tolist():
        m = cls == j
        k = 16 * j
        cols = np.clip(col[m, None] + np.arange(-k, k + 1), 0, n - 1)
        dx = grid[cols] - px[m, None]
        dy = np.maximum(surface[cols] - py[m, None], 0.0)
        depth[m] = np.minimum(np.sqrt(np.min(dx * dx + dy * dy, axis=1)), reach[m])
    out[inside] = depth
    return out


def _max_table(values: FloatArray) -> FloatArray:
    """A sparse table of ``values`` ``(n,)``: row j holds the maxima of the runs of 2^j
    starting at each index (the last 2^j - 1 entries of a row, where no full run starts, are
    not meaningful and :func:`_range_max` does not read them)."""
    rows = [values]
    j = 1
    while 2 * j <= values.shape[0]:
        prev = rows[-1]
        row = prev.copy()
        row[:-j] = np.maximum(prev[:-j], prev[j:])
        rows.append(row)
        j *= 2
    return np.stack(rows)


def _range_max(table: FloatArray, i0: NDArray[np.int64], i1: NDArray[np.int64]) -> FloatArray:
    """Maxima of ``values[i0 : i1 + 1]`` (index arrays alike, ``i0 <= i1``) from its
    :func:`_max_table`."""
    level = np.floor(np.log2(i1 - i0 + 1)).astype(np.int64)
    top: FloatArray = np.maximum(table[level, i0], table[level, i1 - (1 << level) + 1])
    return top


def _safe_ik(arm: kinematics.FastArm, x: float, y: float, attitude: float) -> FloatArray:
    """IK of a transition pose, trying attitudes nearer the middle when the first fails."""
    for att in (attitude, attitude + 0.3, attitude - 0.3, -math.pi / 2):
        q = arm.ik(x, y, att)
        if q is not None:
            return np.asarray(q)
    raise PlanningError(f"no reachable transition pose at x={x:.3f} m, y={y:.3f} m")


def plan_task(rig: Rig, task: TrenchTask | str, planner: str = "pinn", **kwargs: Any) -> TrenchPlan:
    """Convenience: load ``task`` if given by name/path and plan it."""
    t = load_task(task, rig) if isinstance(task, str) else task
    return TrenchPlanner(rig, planner, **kwargs).plan(t)


__all__: Sequence[str] = (
    "BUILTIN_TASKS",
    "OVERDIG_LIMIT_M",
    "TRANSITION_PENETRATION_M",
    "OneShotPlanner",
    "OneShotResult",
    "PinnOneShot",
    "PlannedDig",
    "PsoOneShot",
    "Transition",
    "TravelMove",
    "TrenchPlan",
    "TrenchPlanner",
    "TrenchSession",
    "TrenchTask",
    "design_polygon",
    "joint_move",
    "load_task",
    "lower_envelope",
    "make_task",
    "plan_task",
    "task_limits",
)
