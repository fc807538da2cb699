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
import numbers
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
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
    VerifyResult,
    pack_inputs,
)
from rt_runtime.rig import Rig
from rt_runtime.rig.model import SCALE_MODEL_REACH_M

FloatArray = NDArray[np.float64]


class Stage(IntEnum):
    """Where a section's digging is; a section goes through them in this order.

    The design is cut in horizontal layers, top first (:meth:`TrenchSession._choose_layers`).
    In each layer above the bottom one: ``ROUGH``, the network's digs (Yao Fig. 5: downward,
    then backward), each filled on the material left and judged against the layer's floor;
    then ``LAYER``, digs along the layer's floor (and the walls above it) take the rest of
    the layer in columns, far to near, each a full bucket. In the bottom layer: ``FAR_WALL``,
    the far wall's dig (it takes what the layers left on the wall); ``BOTTOM``, columns along
    the design's bottom, straight, far to near; ``NEAR_WALL``, the near wall's dig.
    ``FINISH``: finishing passes trim what is left. Digs that do not fill the bucket (the
    walls' mostly) are finishing passes, at most :data:`MAX_FINISHING_PER_SECTION` a section.
    """

    ROUGH = 0
    LAYER = 1
    FAR_WALL = 2
    BOTTOM = 3
    NEAR_WALL = 4
    FINISH = 5


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
_SCALE_REACH_M = SCALE_MODEL_REACH_M
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


# The task domain's minimums on the scale model (m), scaled by reach like the planner's other
# figures: a trench shorter than about 1.4 bucket lengths (l3 = 0.22 m) is a hole one scoop
# takes, and one shallower than four over-dig limits (OVERDIG_LIMIT_M) is grading within the
# tolerance of the profile, neither a trench this planner digs.
_TASK_LENGTH_MIN_M = 0.30
_TASK_DEPTH_MIN_M = 0.02
#: Wall slopes (deg from the horizontal) a task may have: the domain the planner is measured on
#: (``excavator-rt bench plan --random`` draws its walls from it), and nothing wider: a task
#: accepted is one the planner's measured results cover. Flatter than 30 deg a wall runs out
#: more than 1.7 D (a slope more than a trench wall), steeper than 85 deg it is a vertical cut;
#: neither is measured, and 0 or 90 deg is no trench at all.
WALL_SLOPE_DEG = (30.0, 85.0)


def task_limits(rig: Rig) -> dict[str, tuple[float, float]]:
    """The allowed range of every task value on ``rig``, closed at both ends, as
    :func:`make_task` checks them (units as the key names say: m, deg).

    ``length_m``: from 0.30 m (scale model, scaled by reach) to the profile's
    ``trench.length_max_m``. ``depth_m``: from 0.02 m (scaled) to the deepest trench the
    backward digs' domain serves (0.30 m scaled). ``beta1_deg``, ``beta2_deg``:
    :data:`WALL_SLOPE_DEG`. ``start_x_m``: where the rig's digs may enter, the PINN's domain
    (0.55..1.10 m scaled). A valid task also needs its walls to meet no higher than its depth.
    """
    s = _reach_scale(rig)

    def scaled(lo_m: float, hi_m: float) -> tuple[float, float]:
        # To the nanometre: the scale model's own scale is 1 - 2e-16, and a depth of 0.3 m
        # must not be refused for lying 5e-17 m beyond 0.3 x that.
        return round(lo_m * s, 9), round(hi_m * s, 9)

    return {
        "length_m": (scaled(_TASK_LENGTH_MIN_M, 0.0)[0], rig.trench.length_max_m),
        "depth_m": scaled(_TASK_DEPTH_MIN_M, _MAX_DEPTH_M),
        "beta1_deg": WALL_SLOPE_DEG,
        "beta2_deg": WALL_SLOPE_DEG,
        "start_x_m": scaled(*_ENTRY_X_M),
    }


def _limit_text(rig: Rig, key: str, lo: float, hi: float) -> str:
    """``[lo, hi] unit`` of a task key and what the range is."""
    unit = key.rsplit("_", 1)[1]
    why = {
        "length_m": f"the trench lengths {rig.name} takes (its profile's trench.length_max_m)",
        "depth_m": f"the depths {rig.name}'s digs reach below the ground",
        "beta1_deg": "the wall slopes from the horizontal the planner is measured on",
        "beta2_deg": "the wall slopes from the horizontal the planner is measured on",
        "start_x_m": f"the reach where {rig.name}'s digs can start",
    }[key]
    return f"[{lo:.4g}, {hi:.4g}] {unit}, {why}"


def _task_value(rig: Rig, name: str, key: str, value: object) -> float:
    """``value`` as a float inside ``task_limits(rig)[key]``.

    Raises:
        ConfigurationError: Not a real number (a bool, a string), not finite, or outside the
            range; the message names the task, the key, the value and the range with units.
    """
    lo, hi = task_limits(rig)[key]
    allowed = _limit_text(rig, key, lo, hi)
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise ConfigurationError(f"task {name}: {key} must be a number in {allowed}; got {value!r}")
    try:
        x = float(value)
    except OverflowError as e:  # an integer beyond the float range
        raise ConfigurationError(
            f"task {name}: {key} is beyond the float range; allowed {allowed}"
        ) from e
    if not math.isfinite(x):
        raise ConfigurationError(f"task {name}: {key} = {x:g} is not finite; allowed {allowed}")
    if not lo <= x <= hi:
        raise ConfigurationError(f"task {name}: {key} = {x:g} is outside {allowed}")
    return x


def make_task(
    rig: Rig,
    length_m: float,
    depth_m: float,
    beta1_deg: float,
    beta2_deg: float,
    start_x_m: float | None = None,
    name: str = "task",
) -> TrenchTask:
    """A validated task: every value inside :func:`task_limits` and the walls meeting no
    higher than the depth.

    Args:
        rig: The rig whose domain applies.
        length_m, depth_m, beta1_deg, beta2_deg: The trench (m, deg).
        start_x_m: The far top edge (m, arm frame); None: 1.05 m scaled by reach.
        name: The task's name, the start of every message.

    Raises:
        ConfigurationError: A value is not a real number, not finite or out of its range (the
            message names the key, the value and the allowed range with units), or the walls
            meet above the depth.
    """
    if start_x_m is None:
        start_x_m = _DEFAULT_START_X_M * _reach_scale(rig)
    length, depth, beta1, beta2, start_x = (
        _task_value(rig, name, key, value)
        for key, value in zip(
            TASK_KEYS, (length_m, depth_m, beta1_deg, beta2_deg, start_x_m), strict=True
        )
    )
    task = TrenchTask(
        name=name,
        length_m=length,
        depth_m=depth,
        beta1_rad=math.radians(beta1),
        beta2_rad=math.radians(beta2),
        start_x_m=start_x,
    )
    if task.bottom_length_m < 0.0:
        need = depth / math.tan(task.beta1_rad) + depth / math.tan(task.beta2_rad)
        raise ConfigurationError(
            f"task {name}: the walls (beta1 {beta1:g}, beta2 {beta2:g} deg) meet above "
            f"depth_m = {depth:g}; length_m must be >= {need:.4g} m for that depth"
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

    def plan_scaled(
        self, problem: Problem, K_rad: FloatArray, T_s: float, c: float
    ) -> OneShotResult:
        """The network's path for ``problem`` with its bulge ``K_rad`` (``(3,)``, rad, the
        network's answer at ``T_s``) scaled by ``c``, retimed to the shortest feasible time.

        The trench planner chooses ``c`` so that the real cut on the material left fills the
        bucket (the fill rule); the one-shot volume window against a flat surface at H does
        not apply and is not checked here (the caller checks the real cut), every other limit
        of Yao eq 12 is.

        Raises:
            PlanningError: No time in the range makes the scaled path feasible.
        """
        t0 = time.perf_counter()
        verifier = self.planner.verifier
        a6 = -c * np.asarray(K_rad, dtype=np.float64) / T_s**6
        row = pack_inputs(
            problem.q_start_rad, problem.q_end_rad, problem.surface_y_m, problem.dig_type,
            a6, T_s,
        )  # fmt: skip
        out = np.zeros((1, N_OUT))
        retimed = np.zeros((1, 4))
        verifier.retime_into(row, out, retimed)
        if not np.isfinite(retimed[0, 3]) or _total_without_volume(out[0]) > 0.0:
            raise PlanningError("the scaled network path has no feasible time")
        r = retimed[0]
        return OneShotResult(
            (float(r[0]), float(r[1]), float(r[2])),
            float(r[3]),
            out[0].copy(),
            (time.perf_counter() - t0) * 1e6,
            "filled",
        )


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


# -- candidates -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Candidate:
    """A dig chosen on its geometry, before it is planned for real and checked.

    Attributes:
        kind: Downward or backward.
        x7: ``(7,)`` entry pose and exit pose (rad, arm frame at the machine's position) and H
            (m, the surface the one-shot model and the soil model take).
        useful_m2: Design material it is estimated to remove (cross-section area, m^2).
        total_m2: Material it is estimated to remove in all (m^2).
        score: The ranking's score (larger first).
        K_rad: A network dig's bulge ``(3,)`` (rad, the network's answer at ``T_s``), which
            ``c`` scales; None for a dig fitted along the outline.
        c: The bulge scale that fills the bucket on the material left.
        T_s: The network's time (network digs), or the retimed time (fitted digs).
        a6: A fitted dig's retimed sixth-order coefficients (rad/s^6); None for network digs.
        fit_rms_m: RMS distance of a fitted dig's path from its outline (m).
        may_underfill: Planned even where its real cut is below the fill band (then it is a
            finishing pass); a dig without it is refused outside the band.
    """

    kind: DigType
    x7: FloatArray
    useful_m2: float
    total_m2: float
    score: float
    K_rad: FloatArray | None = None
    c: float = 1.0
    T_s: float = 0.0
    a6: tuple[float, float, float] | None = None
    fit_rms_m: float = math.nan
    may_underfill: bool = False


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
        planner: ``pinn`` or ``pso``; status: how the one-shot planner got the plan
            (``filled``: the network's path filled on the material left; ``profile``: a
            full dig along the design's outline; ``profile_pass``: a finishing pass).
        evaluation: The verifier's row for the plan.
        finishing: Whether the dig is a finishing pass (exempt from the fill rule).
        section: The section of the trench the dig belongs to (0 at the far end).
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
        planning_error: What stopped the planning before the planner found the task finished
            (the message of the PlanningError: no dig removes the rest, the bound on the digs),
            or None when it ran to its end; the plan then holds the digs before it.
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
    planning_error: str | None = None

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
            "status": self.status.name.lower(),
            "reason": self.reason,
            "volume_left_L": self.volume_left_m3 * 1e3,
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
        max_digs: Safety bound on the number of digs of one task (None: 20 a section).
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
        max_digs: int | None = None,
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

        A PlanningError mid-way (no verified dig removes the rest, the bound on the digs) does
        not propagate: the plan holds the digs before it, ends after the last of them (the
        moves towards the dig that failed are dropped) and is incomplete with that error as
        its :attr:`TrenchPlan.planning_error`. Check :attr:`TrenchPlan.status`.
        """
        t0 = time.perf_counter()
        session = self.start(task)
        error: str | None = None
        try:
            while True:
                dig = session.next_dig()
                if dig is None:
                    break
                session.record(dig, dig.tip_path_m)
        except PlanningError as e:
            error = str(e)
        plan = session.finish(plan_total_us=0.0)
        total = (time.perf_counter() - t0) * 1e6
        stages = dict(session.stage_us)
        stages["other"] = max(0.0, total - sum(stages.values()))
        if error is None:
            return dataclasses.replace(plan, plan_total_us=total, stage_us=stages)
        last = max((i for i, st in enumerate(plan.steps) if isinstance(st, PlannedDig)), default=-1)
        return dataclasses.replace(
            plan,
            steps=plan.steps[: last + 1],
            plan_total_us=total,
            stage_us=stages,
            planning_error=error,
        )


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
        self.finishing_used = 0
        #: The sections (work-site x ranges, far first) and where the machine stands for each.
        self.sections, self.stands = self._plan_sections()
        self.section = 0
        self.section_lo, self.section_hi = self.sections[0]
        self.layer_floors: tuple[float, ...] = ()
        self.layer = 0
        self.stage = Stage.ROUGH
        self._wall_piece = 0
        self._begin_section(0)
        #: Time spent per stage so far (us; TrenchPlan.stage_us).
        self.stage_us: dict[str, float] = dict.fromkeys(_STAGES, 0.0)
        #: The pending dig's planned tip path, its envelope and swept region (for record()).
        self._planned_region: tuple[FloatArray, FloatArray, Any] | None = None
        #: Transitions planned lately: key -> (the height field they were checked on, moves).
        self._moves: dict[tuple[Any, ...], tuple[FloatArray, tuple[Transition, ...]]] = {}
        #: The sparse max table of the height field the last move was checked on.
        self._max_tables: tuple[FloatArray, FloatArray] = (np.empty(0), np.empty((0, 0)))

    def _plan_sections(self) -> tuple[list[tuple[float, float]], list[float]]:
        """The trench's sections, far first, and the machine's position (travel from its
        first position) for each: one section where the trench lies within reach of the
        first stand; else equal sections, each within ``[_STAND_NEAR_X_M, _STAND_FAR_X_M]``
        (scaled) of the arm from its stand, the machine travelling back by one section each
        time (first back to put the far edge at _STAND_FAR_X_M where it lies nearer)."""
        s = self.planner.scale
        t = self.task
        xf = t.start_x_m
        near = _STAND_NEAR_X_M * s
        if xf - t.length_m >= near - 1e-9:
            return [(xf - t.length_m, xf)], [0.0]
        m0 = min(0.0, xf - _STAND_FAR_X_M * s)
        n = math.ceil(t.length_m / (xf - m0 - near) - 1e-9)
        step = t.length_m / n
        sections = [(xf - (k + 1) * step, xf - k * step) for k in range(n)]
        return sections, [m0 - k * step for k in range(n)]

    def _begin_section(self, k: int) -> None:
        """Start section ``k``: travel to its stand, choose its layers, first stage."""
        self.section = k
        self.section_lo, self.section_hi = self.sections[k]
        move = self.stands[k] - self.machine_x
        if abs(move) > 1e-9:
            self._travel(move)
        self.finishing_used = 0
        self.layer_floors = self._choose_layers()
        self.layer = 0
        self.stage = Stage.ROUGH if self.layer_floors else Stage.FAR_WALL
        self.phase = DigType.DOWNWARD
        self._wall_piece = 0
        self._set_layer()

    def _set_layer(self) -> None:
        """The current layer's design (the design above its floor) as the screening and the
        columns take it: ``layer_y``, its floor on the grid, half-planes, edges and polygon
        (the bottom layer's are the design's)."""
        upper = self.layer < len(self.layer_floors)
        y = self.layer_floors[self.layer] if upper else self.bottom_y
        self.layer_y = y
        self._layer_floor = np.maximum(self.design_floor, min(y, self.ground_y))
        self._layer_walls = self._walls.copy()
        self._layer_walls[2, 2] = -y
        top = shapely.box(self.x_lo, y, self.x_hi, self.top_y)
        part = self.design.intersection(top)
        self.layer_design: Any = part if not part.is_empty else self.design
        ring = np.asarray(shapely.get_exterior_ring(shapely.normalize(self.layer_design)).coords)
        edge = ring[1:] - ring[:-1]
        self._layer_edges = np.column_stack([ring[:-1], edge, np.sum(edge * edge, axis=1)])

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

    def _design_arrays(self, layer: bool) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The design's floor on the grid, its half-planes and its edges (the layer's design
        above the profile layer with ``layer``: what the network's digs are judged on)."""
        if layer:
            return self._layer_floor, self._layer_walls, self._layer_edges
        return self.design_floor, self._walls, self._design_edges

    def _geometry_args(
        self, layer: bool = False
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The height field and design as the C geometry takes them: ``field`` (surface and
        design floor on the grid), ``frame`` (grid start and step, machine x, the trench's far
        and near x, the ground), ``walls`` and ``edges``."""
        xf = self.task.start_x_m
        frame = np.array(
            [self.grid[0], GRID_STEP_M, self.machine_x, xf, xf - self.task.length_m, self.ground_y]
        )
        floor, walls, edges = self._design_arrays(layer)
        return np.stack([self.surface, floor]), frame, walls, edges

    def _overdig_many(self, paths: FloatArray) -> FloatArray:
        """Over-dig of many paths ``(N, n, 2)`` at once (m, 0 where none); in C with the C
        geometry (:meth:`_overdig_many_numpy` is the reference)."""
        geo = self.planner.geo_module
        if geo is None:
            return self._overdig_many_numpy(paths)
        out = np.empty(paths.shape[0])
        geo.overdig(np.ascontiguousarray(paths, dtype=np.float64), *self._geometry_args(), out)
        return out

    def _overdig_many_numpy(self, paths: FloatArray, layer: bool = False) -> FloatArray:
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
        _, w, e = self._design_arrays(layer)
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
        part counts where its mean thickness (2 area / perimeter) is at least _SLIVER_M, and a
        vertex beside the trench counts by its depth below the ground."""
        over = region.difference(self.design)
        parts = [
            g
            for g in getattr(over, "geoms", [over])
            if g.area > 0.0 and 2.0 * g.area >= _SLIVER_M * g.length
        ]
        if not parts:
            return 0.0
        coords = np.concatenate([shapely.get_coordinates(g) for g in parts])
        # Beside the trench the ground is the design's surface: a vertex there is as deep as
        # it lies below the ground (one on the ground line, where a polygon difference leaves
        # a sliver joined to a real cut, is at 0 however far it lies from the trapezoid).
        dist = shapely.distance(shapely.points(coords), self.design)
        depth = np.maximum(self.ground_y - coords[:, 1], 0.0)
        return float(np.max(np.minimum(dist, depth)))

    def _cut_areas(self, env: FloatArray) -> tuple[float, float]:
        """(total, inside-design) area a path envelope removes from the height field."""
        total = np.maximum(self.surface - env, 0.0)
        inside = np.maximum(self.surface - np.maximum(env, self.design_floor), 0.0)
        return float(np.sum(total) * GRID_STEP_M), float(np.sum(inside) * GRID_STEP_M)

    # -- choosing a dig -----------------------------------------------------------------------

    def _phase(self) -> DigType:
        """Fig. 5: downward until the depth is reached, then backward."""
        floor_y = self.layer_y if self.stage is Stage.ROUGH else self.bottom_y
        if (
            self.phase is DigType.DOWNWARD
            and float(np.min(self.surface)) <= floor_y + OVERDIG_LIMIT_M
        ):
            self.phase = DigType.BACKWARD
        return self.phase

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
        bound = self.planner.max_digs or _MAX_DIGS_PER_SECTION * len(self.sections)
        if len(self.digs) >= bound:
            raise PlanningError(
                f"task {self.task.name}: {left / self.design_area:.1%} of the design is left "
                f"after {len(self.digs)} digs (the bound)"
            )
        t0 = time.perf_counter()
        dig = self._next_in_section(remaining, t0)
        while dig is None and self.section + 1 < len(self.sections):
            self._begin_section(self.section + 1)
            dig = self._next_in_section(remaining, t0)
        if dig is None:
            return None
        self._append_transitions(dig)
        self.pending = dig
        return dig

    def _next_in_section(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The section's next dig through its stages (:class:`Stage`), or None when the
        section is done."""
        dig: PlannedDig | None = None
        while dig is None and self.stage is not Stage.FINISH:
            stage = self.stage
            if stage is Stage.ROUGH:
                dig = self._next_rough(t0)
            elif stage is Stage.LAYER:
                dig = self._next_layer_column(remaining, t0)
            elif stage is Stage.BOTTOM:
                dig = self._next_column(remaining, t0)
            else:
                dig = self._next_wall(stage is Stage.FAR_WALL, remaining, t0)
            if dig is None:
                self._advance()
        if dig is None:
            dig = self._next_finishing(remaining, t0)
        return dig

    def _next_rough(self, t0: float) -> PlannedDig | None:
        """The network's next dig above the profile layer (Fig. 5), filled on the material
        left, or None when none carries a full bucket there."""
        layer_left = self.layer_design.intersection(self.material)
        if float(layer_left.area) <= 0.005 * self.design_area:
            return None
        xe = self._rough_entries()
        if xe.size == 0:
            return None
        H = np.interp(xe, self.grid, self.surface)
        ranked = self._screen(xe, H)
        if not ranked and self.phase is DigType.DOWNWARD:
            self.phase = DigType.BACKWARD
            ranked = self._screen(xe, H)
        return self._first_plannable(ranked, self.remaining_design(), t0)

    def _area_above(self, depth_m: float) -> float:
        """Cross-section area of the section's design above ``depth_m`` below the ground
        (m^2; on the grid)."""
        x = self.grid
        inside = (x >= self.section_lo) & (x <= self.section_hi)
        floor = np.maximum(self.design_floor[inside], self.ground_y - depth_m)
        return float(np.sum(self.ground_y - floor)) * GRID_STEP_M

    def _digs_for(self, area: float, spare: float) -> float:
        """Full buckets an area takes (``spare``: the fraction of the fill band's ends kept
        free, for what the digs' shapes miss); inf when no whole number of them fits."""
        lo_a, hi_a = self._fill_band()
        n = max(1, math.ceil(area / (hi_a * (1.0 - spare))))
        return float(n) if area / n >= lo_a * (1.0 + spare) else math.inf

    def _advance(self) -> None:
        """The next stage (:class:`Stage`): after a layer's columns the next layer's network
        digs, after the last the bottom layer's far wall."""
        self._wall_piece = 0
        if self.stage is Stage.LAYER and self.layer + 1 < len(self.layer_floors):
            self.layer += 1
            self.stage = Stage.ROUGH
            self.phase = DigType.DOWNWARD
        else:
            if self.stage is Stage.LAYER:
                self.layer = len(self.layer_floors)
            self.stage = Stage(self.stage + 1)
        self._set_layer()

    def _choose_layers(self) -> tuple[float, ...]:
        """The floors of the layers above the bottom one (work-site y, top first).

        The bottom layer is cut by straight columns along the bottom, the layers above by
        the network's digs and columns along their floors; no layer is thicker than the
        boom's torque allows through a full cut (:data:`_LAYER_RANGE_M`,
        :data:`_UPPER_LAYER_MAX_M`). Among the bottom layer's thicknesses on a 2.5 mm grid
        (scaled; the whole depth when that is thin enough), the one whose layers split into
        the fewest full buckets (each layer's area in as few as the fill band allows with a
        spare at its ends; walls aside) is taken, ties to the thicker bottom layer.
        """
        s = self.planner.scale
        t = self.task
        lo, hi = (v * s for v in _LAYER_RANGE_M)
        up_max = _UPPER_LAYER_MAX_M * s
        options = [float(v) for v in np.arange(lo, hi + 1e-9, 0.0025 * s) if v < t.depth_m]
        if t.depth_m <= hi:
            options.append(t.depth_m)
        best: tuple[float, float, tuple[float, ...]] = (math.inf, 0.0, ())
        for bottom_layer in options or [t.depth_m]:
            rest = t.depth_m - bottom_layer
            n_up = math.ceil(rest / up_max - 1e-9) if rest > 1e-9 else 0
            depths = [rest * k / n_up for k in range(1, n_up + 1)] if n_up else []
            digs = 0.0
            top = 0.0
            for d in depths:
                digs += self._digs_for(self._area_above(d) - self._area_above(top), _ROUGH_SPARE)
                top = d
            b_lo, b_hi = self._bottom_span()
            cols = max(b_hi - b_lo, 0.0) * (bottom_layer - _COLUMN_SKIN_M * s)
            n_cols = self._digs_for(cols, _FILL_MARGIN)
            if cols / max(n_cols, 1.0) > bottom_layer * _COLUMN_MAX_M * s:
                n_cols = math.inf  # a column longer than a straight dig follows
            key = (digs + n_cols, -bottom_layer, tuple(self.ground_y - d for d in depths))
            if key[:2] < best[:2]:
                best = key
        if not math.isfinite(best[0]):
            # No split fills every bucket: layers of the thickest the torque allows.
            rest = max(t.depth_m - hi, 0.0)
            n_up = math.ceil(rest / up_max - 1e-9) if rest > 1e-9 else 0
            return tuple(self.ground_y - rest * k / n_up for k in range(1, n_up + 1))
        return best[2]

    def _rest_estimate(self, surface: FloatArray) -> tuple[int, int]:
        """What the current layer still takes were the surface ``surface``: per run of its
        material thicker than 1 cm (scaled), the full buckets its area fills; and the runs
        that fill none but are too big for the walls' digs and the finishing passes to take
        (a quarter of V_min or more): ``(buckets, awkward runs)``."""
        s = self.planner.scale
        lo_a, hi_a = self._fill_band()
        x = self.grid
        t = np.clip(surface - self._layer_floor, 0.0, None)
        t[(x < self.section_lo) | (x > self.section_hi)] = 0.0
        on = np.zeros(x.shape[0] + 2, dtype=np.int8)
        on[1:-1] = t > 0.01 * s
        change = np.diff(on)
        buckets = awkward = 0
        for i0, i1 in zip(np.flatnonzero(change == 1), np.flatnonzero(change == -1), strict=True):
            area = float(np.sum(t[i0:i1])) * GRID_STEP_M
            if area < 0.25 * lo_a:
                continue
            n = math.ceil(area / (hi_a * (1.0 - _ROUGH_SPARE)))
            if area / n >= lo_a * (1.0 + _FILL_MARGIN):
                buckets += n
            else:
                awkward += 1
        return buckets, awkward

    def _next_wall(self, far: bool, remaining: Any, t0: float) -> PlannedDig | None:
        """The next piece of the far (``far``) or near wall's profile dig: the wall's line from
        its top edge to the bottom, in pieces no longer than :data:`_COLUMN_MAX_M` (scaled),
        top first; a full dig where it fills the bucket, else a finishing pass. None when the
        wall is done or nothing is left on it."""
        t = self.task
        g = self.ground_y
        xf = t.start_x_m
        xn = xf - t.length_m
        if far:
            if self.section != 0:
                return None
            top = np.array([xf, g])
            foot = np.array([xf - t.depth_m / math.tan(t.beta1_rad), self.bottom_y])
            beta = t.beta1_rad
        else:
            if self.section_lo > xn + 1e-9:
                return None
            top = np.array([xn, g])
            foot = np.array([xn + t.depth_m / math.tan(t.beta2_rad), self.bottom_y])
            beta = t.beta2_rad
        n = max(1, math.ceil(abs(top[0] - foot[0]) / (_COLUMN_MAX_M * self.planner.scale)))
        lo_d, hi_d = oneshot.theta_p_range(self.planning, int(DigType.DOWNWARD))
        kind = DigType.DOWNWARD if float(lo_d) + 0.02 <= beta <= float(hi_d) else DigType.BACKWARD
        atts = _WALL_ATTITUDES_DEG[kind]
        # The last piece stops short of the corner: a path that reaches into it cuts past the
        # bottom before the bottom's columns have opened it (and the columns start there).
        span = foot - top
        short = foot - span * (_CORNER_GAP_M * self.planner.scale / float(np.hypot(*span)))
        while self._wall_piece < n:
            k = self._wall_piece
            self._wall_piece += 1
            a = top + (short - top) * k / n
            b = top + (short - top) * (k + 1) / n
            # Nothing on this piece: skip it.
            xs = np.linspace(min(a[0], b[0]), max(a[0], b[0]), 16)
            above = np.interp(xs, self.grid, self.surface) - np.interp(
                xs, self.grid, self.design_floor
            )
            if float(np.max(above)) < _COLUMN_EDGE_M * self.planner.scale:
                continue
            found = self._fit_pass(kind, np.array([a, b]), atts)
            if found is None:
                continue
            dig = self._plan_profile(found, remaining, t0)
            if dig is not None:
                return dig
        return None

    def _plan_profile(self, found: Candidate, remaining: Any, t0: float) -> PlannedDig | None:
        """A fitted profile dig planned as a full dig, or else (when the section's finishing
        passes allow) as a finishing pass."""
        dig = self._first_plannable([found], remaining, t0)
        if dig is None:
            dig = self._first_plannable(
                [dataclasses.replace(found, may_underfill=True)], remaining, t0
            )
            if dig is not None and dig.finishing:
                self.finishing_used += 1
        return dig

    def _rough_entries(self) -> FloatArray:
        """Where the network's digs may enter (x, work-site frame): from the far edge of the
        material above the profile layer, and from the far end of each run of its bulk (where
        it is at least half its thickest), :data:`_N_ENTRY_X` of each 4 cm apart (scaled)
        towards the machine, within the entries' reach from where the machine stands and within the
        section."""
        s = self.planner.scale
        lo, hi = self.planner.entry_x_range
        m = self.machine_x
        x = self.grid
        t = self.surface - self._layer_floor
        sec = (x >= max(self.section_lo, m + lo)) & (x <= min(self.section_hi, m + hi))
        idx = np.flatnonzero((t > _ENTRY_MIN_THICKNESS_M * s) & sec)
        if not idx.size:
            return np.empty(0)
        edges = [float(x[idx[-1]])]
        # The far ends of the runs of bulk at least 3 cm long (scaled), farthest first.
        bulk = np.zeros(x.shape[0] + 2, dtype=np.int8)
        bulk[1:-1][idx[t[idx] >= 0.5 * float(np.max(t[idx]))]] = 1
        change = np.diff(bulk)
        starts, ends = np.flatnonzero(change == 1), np.flatnonzero(change == -1)
        for i0, i1 in sorted(zip(starts, ends, strict=True), reverse=True):
            if (i1 - i0) * GRID_STEP_M >= 0.03 * s and float(x[i1 - 1]) < edges[-1] - 0.02 * s:
                edges.append(float(x[i1 - 1]))
        lo_x = float(x[idx[0]])
        step = 0.04 * s
        xs = [float(v) for e in edges for v in np.arange(e, lo_x - 1e-9, -step)[:_N_ENTRY_X]]
        return np.asarray(xs)

    # -- profile digs -------------------------------------------------------------------------

    def _bottom_span(self) -> tuple[float, float]:
        """The design's flat bottom within the section (x range, work-site frame)."""
        t = self.task
        xf = t.start_x_m
        bx = xf - t.depth_m / math.tan(t.beta1_rad)
        cx = xf - t.length_m + t.depth_m / math.tan(t.beta2_rad)
        return max(cx, self.section_lo), min(bx, self.section_hi)

    def _column_ends(
        self, floor: FloatArray, x_lo: float, x_hi: float, partial: bool = False
    ) -> list[float]:
        """The next column of the material above ``floor`` (on the grid) within ``[x_lo,
        x_hi]``: its start (just beyond the far edge of that material, at most ``x_hi``) and
        where it may end (x, work-site frame), best first. The material (less a skin) from the
        far edge towards the machine is split into as few full buckets as the fill band
        allows, equal in area, and the column is the far one; what no bucket would fill is
        taken with the last. Empty when what is left cannot fill one bucket, unless
        ``partial``: then the rest in as few columns as the bucket and the longest dig allow
        (under-filled: finishing passes)."""
        lo_a, hi_a = self._fill_band()
        s = self.planner.scale
        x = self.grid
        t = np.clip(self.surface - floor - _COLUMN_SKIN_M * s, 0.0, None)
        t[(x < x_lo - 1e-9) | (x > x_hi + 1e-9)] = 0.0
        # The far edge of the material a dig along the floor leaves (its fit and offset leave
        # a few mm on the outline: the finishing passes' part), thick over a few mm (the grid
        # point beside a wall's foot can stand alone).
        thick = np.convolve(t > _COLUMN_EDGE_M * s, np.ones(5), mode="same") >= 5
        # Runs too small to count (a quarter of V_min) are left to the walls' digs and the
        # finishing passes: a column that starts at one would carry little else.
        on = np.zeros(x.shape[0] + 2, dtype=np.int8)
        on[1:-1] = thick
        change = np.diff(on)
        for i0, i1 in zip(np.flatnonzero(change == 1), np.flatnonzero(change == -1), strict=True):
            if float(np.sum(t[i0:i1])) * GRID_STEP_M < 0.25 * lo_a:
                thick[i0:i1] = False
        idx = np.flatnonzero(thick)
        if not idx.size:
            return []
        i_lo = int(np.searchsorted(x, x_lo - 1e-9))
        # The column enters just beyond the face (on dug ground, so that it enters from the
        # air), at most at the span's far end.
        i_hi = int(np.searchsorted(x, x_hi + 1e-9)) - 1
        i_start = min(int(idx[-1]) + 2 + int(_FACE_GAP_M * s / GRID_STEP_M), i_hi)
        cum = np.cumsum(t[i_lo : i_start + 1][::-1]) * GRID_STEP_M  # from the far edge
        total = float(cum[-1])
        w_max = round(_COLUMN_MAX_M * s / GRID_STEP_M)
        if partial:
            n = max(math.ceil(total / (hi_a * _FILL_AIM)), math.ceil(cum.shape[0] / w_max), 1)
            k = min(int(np.searchsorted(cum, total / n)), cum.shape[0] - 1, w_max)
            return [float(x[i_start]), float(x[i_start - k])]
        if total < lo_a * (1.0 + _FILL_MARGIN):
            return []
        n = max(1, math.ceil(total / (hi_a * _FILL_AIM)))
        if n > 1 and total / n < lo_a:
            n -= 1  # no even split fills every bucket: this one full, the rest left over
        target = total / n
        ends: list[float] = []
        last = min(cum.shape[0] - 1, w_max)
        if n == 1 and total <= hi_a:
            ends.append(float(x[i_start - last]))  # the whole rest in one bucket
        for f in (1.0, 1.06, 0.94, 1.12, 0.88):
            area = min(target * f, hi_a * (1.0 - _FILL_MARGIN))
            if area < lo_a:
                continue
            k = min(int(np.searchsorted(cum, area)), last)
            # What would be left behind this column that no bucket fills goes with it.
            if float(cum[-1] - cum[k]) < lo_a and total <= hi_a:
                k = last
            x_end = float(x[i_start - k])
            if all(abs(x_end - e) > 2.0 * GRID_STEP_M for e in ends):
                ends.append(x_end)
        return [float(x[i_start]), *ends]

    def _next_layer_column(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The next column of the current layer (above the bottom one): a dig along the
        layer's floor, and down the far wall or up the near wall where the column reaches
        them (:meth:`_fit_profile` on the layer's outline), carrying a full bucket; where
        what is left fills none but is too much to leave to the next layer (a quarter of
        V_min), the rest under-filled. None when the layer is done."""
        floor = self._layer_floor
        y_floor = self.layer_y
        walls = self._layer_walls
        lo_d, hi_d = oneshot.theta_p_range(self.planning, int(DigType.DOWNWARD))
        steep = float(lo_d) + 0.02 <= self.task.beta1_rad <= float(hi_d)
        rise = 0.005 * self.planner.scale
        for partial in (False, True):
            ends = self._column_ends(floor, self.section_lo, self.section_hi, partial)
            if not ends:
                continue
            if partial and not self._layer_must_be_taken():
                return None
            x_start = ends[0]
            a = np.array([x_start, float(np.interp(x_start, self.grid, floor))])
            on_wall = a[1] > y_floor + rise
            kind = DigType.DOWNWARD if on_wall and steep else DigType.BACKWARD
            if not on_wall:
                a[1] += 0.002  # enters descending (theta_p >= 0)
            for x_end in ends[1:]:
                b = np.array([x_end, float(np.interp(x_end, self.grid, floor))])
                rows = [0] if on_wall else []
                rows.append(2)
                if b[1] > y_floor + rise:
                    rows.append(1)
                found = self._fit_profile(
                    kind, a, b, walls[rows], _LAYER_ATTITUDES_DEG[kind], _PASS_OFFSETS_M
                )
                dig = self._plan_column(found, partial, remaining, t0)
                if dig is not None:
                    return dig
        return None

    def _layer_must_be_taken(self) -> bool:
        """Whether what is left above the current layer's floor must be taken under-filled:
        left to the layer below, it would make that layer thicker anywhere than the boom's
        torque cuts through (:data:`_CUT_MAX_M`, scaled)."""
        if self.layer >= len(self.layer_floors):
            return True  # the bottom layer: nothing below takes it
        x = self.grid
        inside = (x >= self.section_lo) & (x <= self.section_hi)
        nxt = self.layer + 1
        below = self.layer_floors[nxt] if nxt < len(self.layer_floors) else self.bottom_y
        floor = np.maximum(self.design_floor[inside], below)
        return bool(np.any(self.surface[inside] - floor > _CUT_MAX_M * self.planner.scale))

    def _next_column(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The next bottom column (:meth:`_column_ends`): a straight backward dig along the
        bottom over its span (:meth:`_fit_pass`), carrying a full bucket of real material;
        where what is left fills none, the rest under-filled (finishing passes). None when
        nothing thicker than the skin is left on the bottom."""
        x_lo, x_hi = self._bottom_span()
        atts = _COLUMN_ATTITUDES_DEG[DigType.BACKWARD]
        for partial in (False, True):
            ends = self._column_ends(self.design_floor, x_lo, x_hi, partial)
            if not ends:
                continue
            a = (ends[0], self.bottom_y + 0.002)  # enters descending (theta_p >= 0)
            for x_end in ends[1:]:
                line = np.array([a, (x_end, self.bottom_y)])
                found = self._fit_pass(DigType.BACKWARD, line, atts)
                dig = self._plan_column(found, partial, remaining, t0)
                if dig is not None:
                    return dig
        # No straight column enters (a steep far wall whose dig could not open the face, or
        # a column whose moves would plough): one down the wall and along the bottom.
        return self._next_layer_column(remaining, t0)

    def _plan_column(
        self, found: Candidate | None, partial: bool, remaining: Any, t0: float
    ) -> PlannedDig | None:
        """A fitted column planned: a full dig, or with ``partial`` a finishing pass."""
        if found is None:
            return None
        dig = self._first_plannable(
            [dataclasses.replace(found, may_underfill=partial)], remaining, t0
        )
        if dig is not None and dig.finishing:
            self.finishing_used += 1
        return dig

    @_stage("passes")
    def _next_finishing(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The finishing pass that removes the most design material of the section's
        (:meth:`_finishing_lines`); None when the section's design is dug (within half a
        percent), no pass removes a useful amount, or :data:`MAX_FINISHING_HARD` passes are
        spent. Passes beyond :data:`MAX_FINISHING_PER_SECTION` are taken only where the
        section would otherwise miss the coverage goal: a finished trench comes first."""
        if self.finishing_used >= MAX_FINISHING_HARD:
            return None
        box = shapely.box(self.section_lo, self.bottom_y - 1.0, self.section_hi, self.top_y)
        part = self.design.intersection(box)
        left = float(part.intersection(self.material).area)
        if left <= 0.005 * float(part.area):
            return None
        if self.finishing_used >= MAX_FINISHING_PER_SECTION and left <= 0.015 * float(part.area):
            return None
        found: list[Candidate] = []
        for kind, line, atts in self._finishing_lines():
            fit = self._fit_pass(kind, line, atts)
            if fit is not None:
                found.append(dataclasses.replace(fit, may_underfill=True))
        found.sort(key=lambda c: -c.useful_m2)
        dig = self._first_plannable(found, remaining, t0)
        if dig is not None and dig.finishing:
            self.finishing_used += 1
        return dig

    def _finishing_lines(self) -> list[_Pass]:
        """The section's finishing passes: the far wall (in the first section), the bottom in
        pieces (:meth:`_bottom_passes`), the near wall (in the last), and where the material
        left is thicker than a dig cuts through, lines across it every :data:`_LAYER_M`
        (scaled) from the top (the bottom-like passes at those heights); each only where
        material is left on it."""
        t = self.task
        g = self.ground_y
        s = self.planner.scale
        xf, xn = t.start_x_m, t.start_x_m - t.length_m
        lo, hi = self.section_lo, self.section_hi
        far_foot = xf - t.depth_m / math.tan(t.beta1_rad)
        near_foot = xn + t.depth_m / math.tan(t.beta2_rad)
        x = self.grid
        inside = (x >= lo) & (x <= hi)
        thick = np.where(inside, self.surface - self.design_floor, 0.0)
        passes: list[_Pass] = []
        if self.section == 0:
            passes.append(
                (DigType.DOWNWARD, np.array([(xf, g), (far_foot, self.bottom_y)]), _FAR_WALL_ATTS)
            )
        b_hi, b_lo = min(far_foot, hi), max(near_foot, lo)
        if b_hi > b_lo:
            passes += self._bottom_passes((b_hi, self.bottom_y), (b_lo, self.bottom_y))
        if lo <= xn + 1e-9:
            passes.append(
                (DigType.DOWNWARD, np.array([(xn, g), (near_foot, self.bottom_y)]), _NEAR_WALL_ATTS)
            )
        top = float(np.max(thick)) if thick.size else 0.0
        if top > _CUT_MAX_M * s:
            n = math.ceil(top / (_LAYER_M * s))
            for k in range(1, n):
                y = self.bottom_y + top * (1.0 - k / n)
                far = (min(xf - (g - y) / math.tan(t.beta1_rad), hi), y)
                near = (max(xn + (g - y) / math.tan(t.beta2_rad), lo), y)
                if far[0] > near[0]:
                    passes += self._bottom_passes(far, near)
        keep = []
        for kind, line, atts in passes:
            order = np.argsort(line[:, 0])
            xs = np.linspace(float(line[order[0], 0]), float(line[order[-1], 0]), 16)
            above = np.interp(xs, x, self.surface) - np.interp(xs, line[order, 0], line[order, 1])
            if float(np.max(above)) > _FINISH_MIN_M * s:
                keep.append((kind, line, atts))
        return keep

    def _first_plannable(
        self, ranked: list[Candidate], remaining: Any, t0: float
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

    def _travel(self, move: float) -> None:
        """Crawler travel by ``move`` (m along the trench, negative: back, away from the dug
        part); the arm's pose is unknown after."""
        self.steps.append(TravelMove(move, self.machine_x, self.machine_x + move))
        self.machine_x += move
        self.q_now = None

    @_stage("screen")
    def _screen(self, xe: FloatArray, H: FloatArray) -> list[Candidate]:
        """The best candidates of the phase's dig types, best first, entering at ``xe``
        (:meth:`_entry_x_candidates`) where the surface is at ``H``."""
        kinds = [DigType.DOWNWARD] if self._phase() is DigType.DOWNWARD else list(DigType)
        found = [b for k in kinds for b in self._screen_kind(xe, H, k)]
        return sorted(found, key=lambda b: -b.score)[:_N_RANKED]

    def _screen_kind(self, xe: FloatArray, H: FloatArray, kind: DigType) -> list[Candidate]:
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
        self._screen_kind_now = kind
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
        _, over, total, useful = self._screen_paths(X, K)
        # The fill on the material left: the largest bulge scale whose real cut stays inside
        # the bucket (V_max) and whose over-dig stays within the screening limit; kept when
        # that cut carries at least V_min (the fill rule).
        lo_area, hi_area = self._fill_band()
        c_cut = _largest_scale_below(total, hi_area * (1.0 - _FILL_MARGIN), G)
        c_over = _largest_scale_below(over, _SCREEN_OVERDIG_M, G)
        c = self._path_feasible_scale(X, K, np.minimum(c_cut, c_over))
        r = np.arange(X.shape[0])
        kc = np.clip(np.searchsorted(G, c), 1, G.shape[0] - 1)
        w = np.clip((c - G[kc - 1]) / (G[kc] - G[kc - 1]), 0.0, 1.0)
        o, t, u = (a[r, kc - 1] * (1.0 - w) + a[r, kc] * w for a in (over, total, useful))
        min_useful = MIN_USEFUL_FRACTION * self.design_area
        good = np.flatnonzero(
            (c >= G[0]) & (o <= _SCREEN_OVERDIG_M) & (t >= lo_area * (1.0 + _FILL_MARGIN))
            & (u >= min_useful)
        )  # fmt: skip
        u, t, cs = u[good], t[good], c[good]
        score = u - 2.0 * (t - u)
        best = np.argsort(-score, kind="stable")[:_N_LOOKAHEAD]
        if self.stage is Stage.ROUGH and best.shape[0] > 1:
            # Look ahead: the fewest full digs the material above the layer still takes after
            # the dig, then the fullest bucket, then the score.
            rest = [
                self._rest_estimate(
                    self._screened_surface_after(X[good[b]], K[good[b]], float(cs[b]))
                )
                for b in best
            ]
            # A dig that leaves part of the layer no bucket fills is not taken: the layer's
            # columns would have to take it under-filled.
            order = sorted(
                (i for i in range(best.shape[0]) if rest[i][1] == 0),
                key=lambda i: (rest[i][0], -t[best[i]], -score[best[i]]),
            )
            best = best[order]
        best = best[:_N_RANKED]
        return [
            Candidate(
                kind=kind,
                x7=X[good[b]],
                useful_m2=float(u[b]),
                total_m2=float(t[b]),
                score=float(score[b]),
                K_rad=K[good[b]],
                c=float(cs[b]),
                T_s=float(Y[good[b], 3]),
            )
            for b in best
        ]

    def _path_feasible_scale(self, X: FloatArray, K: FloatArray, c_top: FloatArray) -> FloatArray:
        """The largest bulge scale ``<= c_top`` (per candidate row of ``X`` ``(N, 7)`` with
        bulge ``K`` ``(N, 3)``) at which the path-only limits hold: every joint within its
        range at the screening samples (each angle is linear in the scale: an interval in
        closed form) and theta_p, the entry direction ``J(q1) (10 D + c K)``, in the dig
        type's range (on a grid of scales 1/40 apart below ``c_top``). 0 where none does."""
        arm = self.planner.arm
        qf, pf = self.planner.screen_qf, self.planner.screen_pf
        q1, q2 = X[:, 0:3], X[:, 3:6]
        base = q1[:, None] + qf[None, :, None] * (q2 - q1)[:, None]
        slope = pf[None, :, None] * K[:, None, :]
        margin = 1e-6
        lo_q = arm.q_min + margin - base
        hi_q = arm.q_max - margin - base
        with np.errstate(divide="ignore", invalid="ignore"):
            up = np.where(slope > 0, hi_q / slope, np.where(slope < 0, lo_q / slope, np.inf))
            down = np.where(slope > 0, lo_q / slope, np.where(slope < 0, hi_q / slope, -np.inf))
        inside = np.all((lo_q <= 0.0) | (slope != 0.0), axis=(1, 2)) & np.all(
            (hi_q >= 0.0) | (slope != 0.0), axis=(1, 2)
        )
        c_hi = np.where(inside, np.min(up, axis=(1, 2)), -np.inf)
        c_lo = np.max(down, axis=(1, 2))
        # theta_p on a grid of scales from c_top down (the entry direction is linear in c).
        phi = np.cumsum(q1, axis=1)
        lengths = arm.lengths
        sn = np.sin(phi) * lengths
        cs = np.cos(phi) * lengths
        jx = -np.cumsum(sn[:, ::-1], axis=1)[:, ::-1]
        jy = np.cumsum(cs[:, ::-1], axis=1)[:, ::-1]
        D10 = 10.0 * (q2 - q1)
        ux, uy = np.sum(jx * D10, axis=1), np.sum(jy * D10, axis=1)
        vx, vy = np.sum(jx * K, axis=1), np.sum(jy * K, axis=1)
        top = np.minimum(c_top, c_hi)
        steps = np.arange(_N_SCALE_STEPS + 1) / _N_SCALE_STEPS
        cg = top[:, None] * (1.0 - steps[None, :])  # from top down to 0
        ang = np.arctan2(-(uy[:, None] + cg * vy[:, None]), np.abs(ux[:, None] + cg * vx[:, None]))
        kind = X.shape[0] and int(self._screen_kind_now)
        tp_lo, tp_hi = (float(v) for v in oneshot.theta_p_range(self.planning, kind))
        ok = (ang >= tp_lo + 1e-3) & (ang <= tp_hi - 1e-3) & (cg >= c_lo[:, None])
        first = np.argmax(ok, axis=1)
        found = ok[np.arange(X.shape[0]), first]
        return np.where(found & (top > 0.0), cg[np.arange(X.shape[0]), first], 0.0)

    def _screened_surface_after(self, x7: FloatArray, K: FloatArray, c: float) -> FloatArray:
        """The height field after a screened dig (poses and H ``x7``, bulge ``K`` scaled by
        ``c``), its path on the screening's samples."""
        pl = self.planner
        q1, q2 = x7[0:3], x7[3:6]
        q = q1 + pl.screen_qf[:, None] * (q2 - q1) + c * pl.screen_pf[:, None] * K
        px, py = pl.arm.tip_xy(q)
        path = np.stack([px + self.machine_x, py], axis=1)
        after: FloatArray = np.minimum(self.surface, self._envelope(path, self.grid))
        return after

    def _fill_band(self) -> tuple[float, float]:
        """The fill rule as cross-section areas (m^2): a dig carries between V_min and V_max of
        real material (Yao's V_p range, 0.8-1.2 x the struck volume on ``scale_model``)."""
        return (
            self.planning.volume_min_m3 / self.width_m,
            self.planning.volume_max_m3 / self.width_m,
        )

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
        layer = self.stage is Stage.ROUGH
        if kernel is None:
            return self._screen_paths_numpy(X, K, layer)
        pl = self.planner
        out = np.empty((4, X.shape[0], pl.screen_c.shape[0]))
        kernel.screen(
            np.ascontiguousarray(X),
            np.ascontiguousarray(K),
            pl.screen_shapes,
            pl.screen_c,
            *self._geometry_args(layer),
            out,
        )
        return out

    def _screen_paths_numpy(self, X: FloatArray, K: FloatArray, layer: bool = False) -> FloatArray:
        """:meth:`_screen_paths` in numpy (the reference of the C kernel; ``layer``: judged
        against the layer's design, :meth:`_design_arrays`)."""
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
        over = self._overdig_many_numpy(np.stack([x, y], axis=-1), layer)
        total, useful = self._cut_estimate(x, y, layer)
        return np.stack([vp, over, total, useful])

    def _on_grid(self, x: FloatArray, *fields: FloatArray) -> list[FloatArray]:
        """``np.interp`` of fields on the uniform grid at ``x`` (clamped at the ends)."""
        u = np.clip((x - self.grid[0]) / GRID_STEP_M, 0.0, self.grid.shape[0] - 1.000001)
        i = u.astype(np.int64)
        w = u - i
        return [f[i] * (1.0 - w) + f[i + 1] * w for f in fields]

    def _cut_estimate(
        self, x: FloatArray, y: FloatArray, layer: bool = False
    ) -> tuple[FloatArray, FloatArray]:
        """(total, inside-design) area sampled paths ``(..., n)`` cut from the height field,
        integrated along each path (exact for a path that does not turn back in x)."""
        xm = 0.5 * (x[..., 1:] + x[..., :-1])
        ym = 0.5 * (y[..., 1:] + y[..., :-1])
        dx = np.abs(np.diff(x, axis=-1))
        surf, floor = self._on_grid(xm, self.surface, self._design_arrays(layer)[0])
        total = np.sum(np.maximum(surf - ym, 0.0) * dx, axis=-1)
        useful = np.sum(np.maximum(surf - np.maximum(ym, floor), 0.0) * dx, axis=-1)
        return total, useful

    # -- finishing passes ---------------------------------------------------------------------

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
    ) -> Candidate | None:
        """Fit one straight profile pass ``poly`` (2 points, work-site frame): the line as a
        half-plane, inwards towards the design's centroid (:meth:`_fit_profile`)."""
        a, b = np.asarray(poly[0], dtype=np.float64), np.asarray(poly[-1], dtype=np.float64)
        seg = b - a
        normal = np.array([-seg[1], seg[0]]) / math.hypot(seg[0], seg[1])
        c = self.design.centroid
        if (c.x - a[0]) * normal[0] + (c.y - a[1]) * normal[1] < 0.0:
            normal = -normal
        # Outward normal and offset: inside is -normal . p <= -normal . a.
        edge = np.array([[-normal[0], -normal[1], -float(normal @ a)]])
        return self._fit_profile(kind, a, b, edge, atts, _PASS_OFFSETS_M)

    def _fit_profile(
        self,
        kind: DigType,
        a: FloatArray,
        b: FloatArray,
        edges: FloatArray,
        atts: tuple[tuple[float, ...], tuple[float, ...]],
        offsets: tuple[float, ...],
        good_cost: float | None = None,
    ) -> Candidate | None:
        """Fit a profile dig from ``a`` to ``b`` (work-site frame) along the boundary of the
        half-planes ``edges`` (rows ``(nx, ny, c)``, unit outward normal, inside where
        ``nx x + ny y <= c``; a convex piece of the design's outline: a wall, the bottom, or
        a wall and the bottom).

        For each pair of end attitudes of ``atts`` the sextic's path is linear in its bulge
        ``K`` in joint space, so the inward distances of the path samples from the outline
        (the least over the half-planes, exact for a convex outline) are fitted in ``K`` by
        Gauss-Newton (:meth:`_fit_bulge`, 3 x 3 systems, microseconds); a pair whose fit
        leaves the joint limits or the theta_p range is skipped. The first pair that fits
        within ``good_cost`` (m^2 on 101 samples; :data:`_GOOD_FIT_COST`, ~1 mm RMS, by
        default), or else the best, is taken; the outline
        is shifted inwards by ``offsets`` in turn (the ends with it, along the inward normal
        of the half-plane they lie on) until the over-dig limit holds. Returns the candidate
        of :meth:`_pass_candidate` with the fit's RMS distance (``fit_rms_m``), or None.
        """
        arm = self.planner.arm
        m = self.machine_x
        qf, pf = self.planner.fit_qf, self.planner.fit_pf
        margin = math.radians(0.5)
        lo_q, hi_q = arm.q_min + margin, arm.q_max - margin
        tp_lo, tp_hi = (float(v) for v in oneshot.theta_p_range(self.planning, int(kind)))
        qf_full, pf_full = self.planner.full_qf, self.planner.full_pf
        good = (_GOOD_FIT_COST if good_cost is None else good_cost) * qf.shape[0] / 101.0

        def inward(p: FloatArray) -> FloatArray:
            k = int(np.argmin(edges[:, 2] - edges[:, 0:2] @ p))
            return -edges[k, 0:2]

        n_a, n_b = inward(a), inward(b)

        def candidate(
            q1: FloatArray, q2: FloatArray, K: FloatArray, cost: float
        ) -> Candidate | None:
            qp = q1 + qf_full[:, None] * (q2 - q1) + pf_full[:, None] * K
            px, py = arm.tip_xy(qp)
            tip = np.stack([px + m, py], axis=1)
            if self.overdig_of(tip) > OVERDIG_LIMIT_M:
                return None
            found = self._pass_candidate(kind, q1, q2, K, tip)
            if found is not None:
                found = dataclasses.replace(found, fit_rms_m=math.sqrt(cost / qf.shape[0]))
            return found

        def fitted(
            q1: FloatArray, q2: FloatArray, offset: float
        ) -> tuple[float, FloatArray] | None:
            """The bulge fitted for end poses ``q1``, ``q2``; None outside the joint limits
            or theta_p's range."""
            base = q1 + qf[:, None] * (q2 - q1)
            K, cost = self._fit_bulge(base, q1, q2, edges, offset, kind)
            q = base + pf[:, None] * K
            if np.any(q < lo_q) or np.any(q > hi_q):
                return None
            # theta_p: the entry direction J(q1) (10 D + K) in the type's range.
            jac = kinematics.jacobian(self.rig, q1)[:2]
            d0 = jac @ (10.0 * (q2 - q1) + K)
            ang = math.atan2(-d0[1], abs(d0[0]))
            if not tp_lo + 0.01 <= ang <= tp_hi - 0.01:
                return None
            return cost, K

        # Every table pair fitted on the outline itself; the best few shifted inwards just
        # enough that the path's farthest sample outside the outline is _FIT_OUTSIDE_M out
        # (a least-squares path crosses the outline both ways), and refitted.
        mid = [(v[0], v[-1], *np.linspace(v[0], v[-1], 5)[1:-1].tolist()) for v in atts]
        found = self._fit_shifted(kind, a, b, n_a, n_b, mid, edges, fitted, candidate)
        if found is not None:
            return found
        # Fixed shifts as before where the adaptive one found nothing.
        for offset in offsets:
            a_s = a + offset * n_a
            b_s = b + offset * n_b
            starts = [self._pass_pose(a_s, mid[0]), self._pass_pose(b_s, mid[1])]
            fits = []
            # Table pairs first; a good fit is tried at once, the others by cost at the end.
            for qs in starts[0]:
                for qe in starts[1]:
                    q1, q2 = np.asarray(qs), np.asarray(qe)
                    got = fitted(q1, q2, offset)
                    if got is None:
                        continue
                    cost, K = got
                    if cost < good:
                        found = candidate(q1, q2, K, cost)
                        if found is not None:
                            return found
                    else:
                        fits.append((cost, q1, q2, K))
            for cost, q1, q2, K in sorted(fits, key=lambda f: f[0]):
                found = candidate(q1, q2, K, cost)
                if found is not None:
                    return found
        return None

    def _fit_shifted(
        self,
        kind: DigType,
        a: FloatArray,
        b: FloatArray,
        n_a: FloatArray,
        n_b: FloatArray,
        table: list[tuple[float, ...]],
        edges: FloatArray,
        fitted: Callable[[FloatArray, FloatArray, float], tuple[float, FloatArray] | None],
        candidate: Callable[..., Candidate | None],
    ) -> Candidate | None:
        """:meth:`_fit_profile`'s adaptive shift on one attitude table: every pair fitted on
        the outline itself (``fitted`` at offset 0), the best :data:`_N_FIT_SHIFTS` by cost
        shifted inwards (the ends along their inward normals ``n_a``, ``n_b``) just enough
        that the path's farthest sample outside the outline is :data:`_FIT_OUTSIDE_M` out,
        refitted there, and the first that ``candidate`` plans returned."""
        arm = self.planner.arm
        m = self.machine_x
        qf_full, pf_full = self.planner.full_qf, self.planner.full_pf
        starts = [self._pass_pose(a, table[0]), self._pass_pose(b, table[1])]
        fits: list[tuple[float, FloatArray, FloatArray, FloatArray]] = []
        for qs in starts[0]:
            for qe in starts[1]:
                got = fitted(qs, qe, 0.0)
                if got is not None:
                    fits.append((got[0], qs, qe, got[1]))
        fits.sort(key=lambda f: f[0])
        for cost, q1, q2, K in fits[:_N_FIT_SHIFTS]:
            qp = q1 + qf_full[:, None] * (q2 - q1) + pf_full[:, None] * K
            px, py = arm.tip_xy(qp)
            x = px + m
            inside = np.min(
                edges[:, 2, None] - edges[:, 0, None] * x - edges[:, 1, None] * py, axis=0
            )
            shift = max(0.0, -float(np.min(inside)) - _FIT_OUTSIDE_M)
            if shift > 0.0:
                q1s = arm.ik(
                    float(a[0] + shift * n_a[0] - m),
                    float(a[1] + shift * n_a[1]),
                    float(np.sum(q1)),
                )
                q2s = arm.ik(
                    float(b[0] + shift * n_b[0] - m),
                    float(b[1] + shift * n_b[1]),
                    float(np.sum(q2)),
                )
                if q1s is None or q2s is None:
                    continue
                q1, q2 = np.asarray(q1s), np.asarray(q2s)
                got = fitted(q1, q2, shift)
                if got is None:
                    continue
                cost, K = got
            found = candidate(q1, q2, K, cost)
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
        edges: FloatArray,
        offset: float,
        kind: DigType,
    ) -> tuple[FloatArray, float]:
        """Damped Gauss-Newton fit of the bulge ``K`` (3) of a profile dig: the inward
        distances of the path samples from the outline ``edges`` (:meth:`_fit_profile`) less
        ``offset`` (weighted 21x where the path crosses the outline outwards by > 3 mm) and,
        while it is violated, the entry direction's theta_p bound as a heavily weighted row.
        Returns ``(K, cost)``, the cost that of the K returned (the best one evaluated)."""
        arm = self.planner.arm
        pf = self.planner.fit_pf
        lengths = arm.lengths
        m = self.machine_x
        n = pf.shape[0]
        rows_n = np.arange(n)
        tp_lo, tp_hi = (float(v) for v in oneshot.theta_p_range(self.planning, int(kind)))
        jac0 = kinematics.jacobian(self.rig, q1)[:2]
        d_ent = jac0 @ (10.0 * (q2 - q1))
        mu = 1e-7
        K = np.zeros(3)
        step = np.zeros(3)
        cost = math.inf
        best_K = K
        for _ in range(9):
            q = base + pf[:, None] * K
            phi = np.cumsum(q, axis=1)
            cs, sn = np.cos(phi) * lengths, np.sin(phi) * lengths
            x = cs.sum(axis=1) + m
            y = sn.sum(axis=1)
            inside = edges[:, 2, None] - edges[:, 0, None] * x - edges[:, 1, None] * y
            k = np.argmin(inside, axis=0)
            d = inside[k, rows_n]
            w = np.where(d < -0.003, 21.0, 1.0)
            r = w * (d - offset)
            jx = -np.cumsum(sn[:, ::-1], axis=1)[:, ::-1]
            jy = np.cumsum(cs[:, ::-1], axis=1)[:, ::-1]
            J = -(edges[k, 0, None] * jx + edges[k, 1, None] * jy) * (pf * w)[:, None]
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
                step = 0.5 * step
                mu *= 10.0
                continue
            cost = new_cost
            best_K = K
            if float(step @ step) < 1e-6 and _ > 0:
                break  # converged: the cost is that of the K returned
            A = np.concatenate(rows)
            b = np.concatenate(rhs)
            step = np.linalg.solve(A.T @ A + mu * np.eye(3), A.T @ b - mu * K)
            K = K + step
        return best_K, cost

    def _pass_candidate(
        self, kind: DigType, qs: FloatArray, qe: FloatArray, K: FloatArray, tip: FloatArray
    ) -> Candidate | None:
        """A fitted profile pass retimed and checked, as a ranked candidate (None: refused)."""
        # The verifier's soil model takes depth below a flat H; here the material over the
        # path is a layer along it, so H is set for the thickest chip the path cuts: the
        # material's thickness across the path's direction (its depth above the path times
        # the cosine of the path's slope: a wall's pass cuts the wedge beside the wall, not
        # the wedge's height), above the path's lowest point.
        depth = np.clip(np.interp(tip[:, 0], self.grid, self.surface) - tip[:, 1], 0.0, None)
        step = np.gradient(tip, axis=0)
        across = np.abs(step[:, 0]) / np.maximum(np.hypot(step[:, 0], step[:, 1]), 1e-12)
        H = float(np.min(tip[:, 1]) + float(np.max(depth * across)))
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
        r = retimed[0]
        return Candidate(
            kind=kind,
            x7=x7,
            useful_m2=useful,
            total_m2=total,
            score=useful,
            T_s=float(r[3]),
            a6=(float(r[0]), float(r[1]), float(r[2])),
        )

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
    def _plan_chosen(self, best: Candidate, remaining: Any, select_us: float) -> PlannedDig:
        """Plan ``best`` for real and check it; ``remaining`` is :meth:`remaining_design` (the
        caller's, the material being unchanged since)."""
        x7 = best.x7
        problem = Problem(
            q_start_rad=(float(x7[0]), float(x7[1]), float(x7[2])),
            q_end_rad=(float(x7[3]), float(x7[4]), float(x7[5])),
            surface_y_m=float(x7[6]),
            dig_type=best.kind,
        )
        oneshot_planner = self.planner.oneshot
        fitted = best.a6 is not None
        # Judged on the material left (the fill band on the real cut), not on V_p against H.
        real_fill = fitted or isinstance(oneshot_planner, PinnOneShot)
        if best.a6 is not None:
            res = OneShotResult(best.a6, best.T_s, np.zeros(N_OUT), 0.0, "profile")
        else:
            t_plan = time.perf_counter()
            if isinstance(oneshot_planner, PinnOneShot) and best.K_rad is not None:
                res = oneshot_planner.plan_scaled(problem, best.K_rad, best.T_s, best.c)
            else:
                res = oneshot_planner.plan_dig(problem, best.c)
            spent = (time.perf_counter() - t_plan) * 1e6
            self.stage_us["oneshot"] += spent
            self.stage_us["checks"] -= spent
        a6, T_s = self._fine_grid_time(problem, res.a6, res.T_s)
        pb = problem
        row = pack_inputs(pb.q_start_rad, pb.q_end_rad, pb.surface_y_m, pb.dig_type, a6, T_s)
        out = np.zeros((1, N_OUT))
        path = np.zeros((1, self.planner.verifier.n_samples, 2))
        self.planner.verifier.evaluate_into(row, out, path=path)
        violation = _total_without_volume(out[0]) if real_fill else out[0, COL_TOTAL]
        if violation > 0.0 and T_s != res.T_s:  # the slower plan fails: keep the verified one
            a6, T_s = res.a6, res.T_s
            row[0, 8:11] = a6
            row[0, 11] = T_s
            self.planner.verifier.evaluate_into(row, out, path=path)
            violation = _total_without_volume(out[0]) if real_fill else out[0, COL_TOTAL]
        if violation > 0.0:
            raise PlanningError("one-shot plan fails verification; nothing was planned")
        p = path[0].copy()
        p[:, 0] += self.machine_x
        over = self.overdig_of(p)
        env = self._envelope(p, self.grid)
        total, useful = self._cut_areas(env)
        if not fitted and useful < 0.5 * MIN_USEFUL_FRACTION * self.design_area:
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
        lo_a, hi_a = self._fill_band()
        # A dig allowed out of the fill band is a finishing pass only where it is out of it.
        finishing_pass = best.may_underfill and not lo_a <= total <= hi_a
        if not best.may_underfill and not lo_a <= total <= hi_a:
            raise PlanningError(
                f"the {self.planner.oneshot.name} plan of dig {len(self.digs) + 1} carries "
                f"{total * self.width_m * 1e3:.2f} L of material, outside the fill band "
                f"{lo_a * self.width_m * 1e3:.2f}-{hi_a * self.width_m * 1e3:.2f} L"
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
            status="profile_pass" if finishing_pass else res.status,
            evaluation=out[0].copy(),
            finishing=finishing_pass,
            section=self.section,
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
        (``downward``/``backward``), ``section``, ``stage``, ``layer``, ``layer_floors_m``,
        ``wall_piece``, ``finishing_used`` (where the section's digging is), ``digs_done``,
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
            "section": int(self.section),
            "stage": self.stage.name.lower(),
            "layer": int(self.layer),
            "layer_floors_m": [float(v) for v in self.layer_floors],
            "wall_piece": int(self._wall_piece),
            "finishing_used": int(self.finishing_used),
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
            section = int(state["section"])
            if not 0 <= section < len(self.sections):
                raise ConfigurationError(
                    f"session state key 'section' is {section}; allowed: "
                    f"0..{len(self.sections) - 1}"
                )
            stage = Stage[str(state["stage"]).upper()]
            layer_floors = tuple(float(v) for v in state["layer_floors_m"])
            layer = int(state["layer"])
            wall_piece = int(state["wall_piece"])
            finishing_used = int(state["finishing_used"])
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
        self.section = section
        self.section_lo, self.section_hi = self.sections[section]
        self.layer_floors = layer_floors
        self.layer = layer
        self._set_layer()
        self.stage = stage
        self._wall_piece = wall_piece
        self.finishing_used = finishing_used

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


_STATE_VERSION = 2


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
            "finishing": step.finishing,
            "section": step.section,
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
            finishing=bool(item.get("finishing", False)),
            section=int(item.get("section", 0)),
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
_SCREEN_SAMPLES = 17
# Over-dig a screened path may show at its coarse samples (the plan's own check is exact).
_SCREEN_OVERDIG_M = 0.8 * OVERDIG_LIMIT_M
#: Safety bound on a task's digs per section (TrenchPlanner max_digs=None).
_MAX_DIGS_PER_SECTION = 20
#: Finishing passes a section may take (they need not fill the bucket).
MAX_FINISHING_PER_SECTION = 2
#: Finishing passes a section takes at most where its design is not dug otherwise.
MAX_FINISHING_HARD = 8
#: Least material on a finishing pass's line for the pass to be tried (scale model, m).
_FINISH_MIN_M = 0.002
#: Attitude tables of the walls' finishing passes (deg; first and last of each end).
_FAR_WALL_ATTS = ((-80.0, -100.0), (-95.0, -120.0))
_NEAR_WALL_ATTS = ((-80.0, -100.0), (-100.0, -130.0))
#: Range of the profile layer's thickness (scale model, m): thin enough for the boom's torque
#: through a full cut along the bottom (a 0.25 m column verifies up to ~0.11 m), thick
#: enough that a column of it no longer than _COLUMN_MAX_M fills the bucket.
_LAYER_RANGE_M = (0.045, 0.10)
#: Thickest material a dig along the floor cuts through in one pass (scale model, m; a
#: 0.25 m column verifies up to ~0.11 m).
_CUT_MAX_M = 0.105
#: Thickest layer above the bottom one (scale model, m): what the layer's columns cut, with
#: room for what the network's digs leave above the layer's floor.
_UPPER_LAYER_MAX_M = 0.09
#: Spare fraction of the fill band's ends for the upper layers in the layer choice (the
#: network's scoops do not follow the layer's floor).
_ROUGH_SPARE = 0.04
#: Where a stand puts the far edge of its section, and the nearest the section reaches
#: (arm frame, scale model, m): the entries' far end less 5 cm, and the near edge of Yao's
#: task B from its default start (0.35 m: the nearest a 0.10 m trench was dug to).
_STAND_FAR_X_M = 1.05
_STAND_NEAR_X_M = 0.35
#: How far short of the design's bottom corners the walls' digs stop (scale model, m).
_CORNER_GAP_M = 0.005
#: How far beyond the face of the material a bottom column enters (scale model, m).
_FACE_GAP_M = 0.004
#: End attitudes of wall digs (deg; the table's first and last of each end).
_WALL_ATTITUDES_DEG = {
    DigType.DOWNWARD: ((-80.0, -100.0), (-95.0, -130.0)),
    DigType.BACKWARD: ((-100.0, -125.0), (-120.0, -160.0)),
}
#: Material within this of the design's floor is not counted for a column (scale model, m).
_COLUMN_SKIN_M = 0.003
#: A column starts where the material above the design's floor is thicker than this (scale
#: model, m).
_COLUMN_EDGE_M = 0.012
#: Longest profile dig (scale model, m).
_COLUMN_MAX_M = 0.45
#: Fraction of V_max a column aims at.
_FILL_AIM = 0.93
#: End attitudes of a layer's columns (deg; the table's first and last of each end).
_LAYER_ATTITUDES_DEG = {
    DigType.DOWNWARD: ((-60.0, -120.0), (-110.0, -190.0)),
    DigType.BACKWARD: ((-100.0, -140.0), (-140.0, -200.0)),
}
#: End attitudes of bottom columns (deg; the table's first and last of each end).
_COLUMN_ATTITUDES_DEG = {DigType.BACKWARD: ((-110.0, -135.0), (-150.0, -175.0))}
# Steps of the bulge scale searched for theta_p in the screening (from the top down to 0).
_N_SCALE_STEPS = 40
# Fraction of the fill band kept free at each end in the screening (its cut is interpolated).
_FILL_MARGIN = 0.03
# Candidates kept per screening, tried in order when the one-shot planner's plan fails.
_N_RANKED = 8
# Screened candidates whose material left is estimated (the look-ahead), best score first.
_N_LOOKAHEAD = 32
# Lift heights a transition tries (TrenchSession._lift_heights).
_N_LIFT_HEIGHTS = 4
# Transitions kept for when they are asked for again (a dig's, its next dig's).
_N_CACHED_MOVES = 16
#: Least material above the design floor where an entry may be placed (m, scale model).
_ENTRY_MIN_THICKNESS_M = 0.01
# Profile fits shifted adaptively (the best by cost), and how far outside the outline the
# shifted path's farthest sample may lie (m; the over-dig limit is 5 mm).
_N_FIT_SHIFTS = 4
_FIT_OUTSIDE_M = 0.0025
# Inward shifts of a profile pass's line tried in turn where the adaptive shift fails (m).
_PASS_OFFSETS_M = (0.0, 0.002, 0.004, 0.007)
# A profile fit this good (least-squares cost, m^2: ~1 mm RMS) ends the search of starts.
_GOOD_FIT_COST = 2e-4
# Samples of a profile pass's path in its fit.
_FIT_SAMPLES = 41
# Longest straight profile pass (scale model, m).
_PASS_LENGTH_M = 0.30
#: Thickest layer of a layer pass (:meth:`TrenchSession._finishing`), m on the scale model.
_LAYER_M = 0.05
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


def _largest_scale_below(f: FloatArray, limit: float, G: FloatArray) -> FloatArray:
    """Per row of ``f`` ``(N, len(G))`` (a value growing with the bulge scale, sampled at the
    scales ``G``): the largest scale at which it is still ``<= limit``, linear between the
    samples; ``G[-1]`` where no sample exceeds it, and 0 where even ``G[0]`` does."""
    above = f > limit
    k = np.where(above.any(axis=1), np.argmax(above, axis=1), G.shape[0])
    kk = np.clip(k, 1, G.shape[0] - 1)
    r = np.arange(f.shape[0])
    f0, f1 = f[r, kk - 1], f[r, kk]
    frac = np.clip((limit - f0) / np.where(f1 > f0, f1 - f0, 1.0), 0.0, 1.0)
    c = G[kk - 1] + frac * (G[kk] - G[kk - 1])
    c = np.where(k == G.shape[0], G[-1], c)
    return np.where(k == 0, 0.0, c)


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
    "COVERAGE_GOAL",
    "OVERDIG_GOAL_M",
    "OVERDIG_LIMIT_M",
    "TRANSITION_PENETRATION_M",
    "WALL_SLOPE_DEG",
    "OneShotPlanner",
    "OneShotResult",
    "PinnOneShot",
    "PlanStatus",
    "PlannedDig",
    "PsoOneShot",
    "Stage",
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
    "plan_goals",
    "plan_task",
    "task_limits",
)
