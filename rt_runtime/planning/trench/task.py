"""The trench task: its cross-section (Yao Fig. 13, Table 3), the task domain of a rig and
the validation of every value against it, task files, and the design polygon.

Lengths in m, wall slopes in rad inside (deg at the edges: files, keys, messages); x in the
work-site frame (the arm frame of the machine's first position)."""

from __future__ import annotations

import math
import numbers
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from shapely.geometry import Polygon

from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig
from rt_runtime.rig.model import SCALE_MODEL_REACH_M

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

# Reach figures of the scale model (m), scaled by the rig's l1 + l2 + l3 against 1.31 m: where
# digs may enter (the PINN's domain, oneshot.SAMPLER_RANGES), the deepest trench the backward
# digs' domain serves, and the default far edge of a trench.
_SCALE_REACH_M = SCALE_MODEL_REACH_M

_ENTRY_X_M = (0.55, 1.10)

_MAX_DEPTH_M = 0.30

_DEFAULT_START_X_M = 1.05


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
    # ValueError: not UTF-8, not TOML, or an integer of more than 4300 digits.
    except (OSError, ValueError) as e:
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
