"""Minimum-torque, time-variable dig optimisation with the soil in the loop (Yang/Pan eq 6-18).

One dig is five bucket keypoints in joint space, ``k0 .. k4`` = entry a, end of penetration b,
end of drag c, one rotation keypoint, exit d, and the four intervals between them (eq 6-7).
The objective is ``sum_i integral ||tau(t) / tau_max||^2 dt`` over a smooth interpolation
between the keypoints, with the joint torques from the arm's inverse dynamics (eq 3) plus the
soil's wrench of the fluid model (eq 13-18, Table 2 soils); the constraints are those of
eq 8-12, each named, signed and normalised as :mod:`rt_runtime.planning.oneshot` does with
Yao's eq 12: a value ``<= 0`` holds. SciPy's SLSQP solves it from a few kinematic starts with
forward-difference gradients; the answer is then re-checked on the exact soil model at 1 ms.
The model is written once (:class:`_Model`) for numpy, batched over points, and CasADi (the
benchmark's reference); the compiled kernel (``kernel/mintorque.c``) evaluates the same
formulas where it is built, each forward difference only on the intervals its variable moves,
and the numpy model is its reference (``Evaluator(backend=...)``).

Choices where the paper is silent or wrong (design note Y1 gives the numbers):

* Interpolation. Eq 5-6 interpolate linearly and difference twice, which makes the
  acceleration a spike of height ``jump / dt`` at every keypoint, so the torque cost grows as
  the step shrinks. Here each joint follows one quintic Hermite piece per interval with zero
  acceleration at the keypoints and keypoint velocities from the three-point (Bessel) slope
  estimate, zero at both ends: C2, rest to rest, and the cost converges with the step.
* Samples and time. ``Q_i = T_i / dt`` (eq 7) is an integer and not differentiable. Each
  interval has a fixed count of samples (``samples_per_interval + 1``, ends included) and each
  sample is weighted by its share of the interval's time (trapezoid rule); an unweighted sum
  would count the same number of samples for a shorter interval and so reward slowing down.
* Torque normalisation. The cost and the limits use ``tau_j / tau_max_j``: the boom's limit is
  three times the bucket's, so an unnormalised sum would spend the budget on the boom alone; the
  normalised sum is dimensionless per second and weighs each joint by its share of capacity.
* Eq 12 prints vector norms ``||qd|| < v_max``, ``||tau|| < tau_max`` where Table 1 gives one
  limit per joint: the limits hold per joint, ``|qd_j| <= v_max_j``, ``|tau_j| <= tau_max_j``.
  The rig's joint acceleration and jerk limits hold too (``acceleration_*``, ``jerk_*``;
  eq 12 has neither, but the executor refuses a path beyond them, so a dig without them could
  not be run).
* Eq 10 runs ``i = 0 .. M`` over M + 1 keypoints and so reads one keypoint past the end: the
  heading turns are taken between consecutive keypoints (four pairs), the travel turns between
  consecutive keypoint chords (three pairs).
* Eq 8 names ``k0, k1, k2, k4``: the quadrilateral abcd skips the rotation keypoint ``k3``;
  ``d = k4`` is the exit. Its signed area (shoelace) counts positive for a dig towards the
  machine, so a path wound the wrong way has a negative volume and fails ``volume_min``.
* ``R90`` of eq 10-11 is the rotation by +90 deg about the axis out of the arm plane (z): for
  a dig towards the machine (tip x decreasing) the heading and the travel direction both turn
  clockwise, and ``d_{i+1} . R90 d_i = sin(angle_{i+1} - angle_i) <= 0`` says so. A dig away
  from the machine mirrors the path and needs ``R(-90)``; only digs towards the machine are
  planned here.
* Eq 15-16 divide by ``|v_n|`` and ``|v_t|`` (zero at rest, at both ends of every dig) and
  switch a plate on as its centre crosses the surface. The optimiser uses a smoothed model:
  ``max(d, 0)`` becomes ``(d + sqrt(d^2 + eps^2)) / 2``, the step ``[d > 0]`` becomes
  ``(1 + d / sqrt(d^2 + eps^2)) / 2``, ``v / |v|`` becomes ``v / sqrt(v^2 + r^2)`` and
  ``|v_n|`` becomes ``sqrt(v_n^2 + r^2) - r``. The answer is re-checked on the exact model
  (:func:`rt_runtime.soil.fluid_resistance` with its 1 mm/s regularisation, on a 1 ms
  resample); sampled limits are tightened by ``LIMIT_MARGIN`` in the optimiser to cover the
  difference, and further where the exact re-check still finds a violation.

Everything here runs outside the fixed-rate loop: it allocates, and a solve takes about half a
second.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime import dynamics, kinematics, soil
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.rig import FluidSoil, Rig

FloatArray = NDArray[np.float64]

DEFAULT_N_ELEMENTS = soil.DEFAULT_N_ELEMENTS

KEYPOINT_NAMES: tuple[str, ...] = ("a", "b", "c", "rotation", "d")
N_KEY = len(KEYPOINT_NAMES)
N_INTERVALS = N_KEY - 1
JOINTS: tuple[str, ...] = ("boom", "stick", "bucket")

#: Optimiser smoothing of the soil model: depth scale (m) and speed scale (m/s).
SMOOTH_DEPTH_M = 0.02
SMOOTH_SPEED_M_S = 0.02
#: Share of the velocity, acceleration, jerk and torque limits the optimiser keeps in reserve
#: for the exact model
#: and the 1 ms resample (design note Y1).
LIMIT_MARGIN = 0.02
#: Every normalised constraint is held to ``<= -CONSTRAINT_OFFSET`` in the optimiser, so that
#: SLSQP's answer, which sits on its active constraints up to ~1e-8, keeps margins >= 0.
CONSTRAINT_OFFSET = 1e-4
#: Summed violation of the offset constraints up to which an answer counts as feasible when
#: the starts' answers are ranked: SLSQP's answers sit on their active constraints to ~1e-8,
#: and ranking those raw prefers a dearer answer at 0 to a cheaper one at 1e-9.
FEASIBLE_VIOLATION = 1e-6
#: Sharpness of the smooth maximum over an interval's samples (normalised units).
KS_RHO = 1000.0
#: Up to this many rows the soil's plates are one axis of the arrays (:meth:`_Model._soil`).
_PLATE_AXIS_ROWS = 2
#: Re-check step on the exact model (s).
RECHECK_DT_S = 1e-3
#: Forward-difference step of the batched gradients (rad for keypoints, s for intervals).
FD_STEP = 1e-6

SAMPLE_CONSTRAINTS: tuple[str, ...] = (
    *(f"angle_min_{j}" for j in JOINTS),
    *(f"angle_max_{j}" for j in JOINTS),
    *(f"velocity_{j}" for j in JOINTS),
    *(f"acceleration_{j}" for j in JOINTS),
    *(f"jerk_{j}" for j in JOINTS),
    *(f"torque_{j}" for j in JOINTS),
)
KEYPOINT_CONSTRAINTS: tuple[str, ...] = (
    "volume_min",
    "volume_max",
    "depth_min_b",
    "depth_max_b",
    "depth_min_c",
    "depth_max_c",
    "entry_height_min",
    "entry_height_max",
    "entry_x_min",
    "entry_x_max",
    "exit_height_min",
    "exit_height_max",
    "heading_entry_1",
    "heading_entry_2",
    "heading_lift_1",
    "heading_lift_2",
    "travel_penetration",
    "travel_drag",
    "travel_lift",
    *(f"heading_turn_{i}" for i in range(N_KEY - 1)),
    *(f"travel_turn_{i}" for i in range(N_KEY - 2)),
)
#: Every constraint of eq 8-12, in the order of :attr:`Solution.margins`.
CONSTRAINT_NAMES: tuple[str, ...] = SAMPLE_CONSTRAINTS + KEYPOINT_CONSTRAINTS
#: Columns of :attr:`Evaluation.split`: a smooth maximum per interval and per-sample column
#: (10 sides x 3 joints), then the keypoint constraints.
N_SPLIT = N_INTERVALS * 30 + len(KEYPOINT_CONSTRAINTS)
#: Who evaluates the model: ``auto`` (the compiled kernel, ``kernel/mintorque.c``, where it is
#: built), ``c`` or ``numpy`` (the reference).
BACKENDS: tuple[str, ...] = ("auto", "c", "numpy")
_N_KERNEL_PARAMS = 64
#: The surface height H's place in the kernel's constants (``kernel.h``, ``MT_SURFACE``).
KERNEL_SURFACE = 18
_BASIS_ORDER = ("h0", "h5", "h1", "h4", "d0", "d1", "d4", "a0", "a1", "a4", "j0", "j1", "j4", "w")


@dataclass(frozen=True, slots=True)
class MinTorqueProblem:
    """One dig to optimise (arm frame, flat surface).

    Attributes:
        soil: The fluid soil (Table 2 ``soft`` or ``hard``, or the rig's own).
        surface_y_m: Height H of the soil surface.
        volume_m3: Swept-volume band ``(V_min, V_max)`` of eq 8.
        depth_m: Depth band ``(Z1, Z2)`` of keypoints b and c below H.
        entry_x_m: Window of the entry tip x.
        surface_band_m: Entry a lies in ``[H - band, H]``, exit d in ``[H, H + band]``.
        entry_heading_deg: Half-angle of the cone around straight down the entry heading keeps.
        lift_heading_deg: Half-angle of the cone around straight up the exit heading keeps.
        intervals_s: Start intervals (and the intervals of a fixed-time solve): 1.25 s, where
            Yang/Pan's Experiment I has 1 s (within the rig's jerk limits 1 s intervals leave
            the volume band out of reach; design note Y1).
        interval_bounds_s: Bounds of each interval in a variable-time solve.
        fixed_time: Keep the intervals at ``intervals_s``.
        samples_per_interval: Trapezoid steps per interval (the cost's time step is
            ``T_i / samples_per_interval``).
        n_elements: Plates per bucket outline segment in the soil model.
    """

    soil: FluidSoil
    surface_y_m: float
    volume_m3: tuple[float, float]
    depth_m: tuple[float, float]
    entry_x_m: tuple[float, float]
    surface_band_m: float = 0.1
    entry_heading_deg: float = 45.0
    lift_heading_deg: float = 50.0
    intervals_s: tuple[float, ...] = (1.25, 1.25, 1.25, 1.25)
    interval_bounds_s: tuple[float, float] = (0.3, 3.0)
    fixed_time: bool = False
    samples_per_interval: int = 32
    n_elements: int = DEFAULT_N_ELEMENTS


def make_problem(
    rig: Rig,
    soil_name: str,
    *,
    volume_m3: tuple[float, float] = (0.8, 1.0),
    fixed_time: bool = False,
    entry_x_m: tuple[float, float] | None = None,
    surface_y_m: float | None = None,
    depth_m: tuple[float, float] | None = None,
    samples_per_interval: int = 32,
) -> MinTorqueProblem:
    """A checked problem on ``rig``: Yang/Pan Experiment I by default (0.8-1.0 m^3).

    Defaults scale with the rig: surface at the rig's ground, entry window 60-72 % of the reach
    (boom + stick + bucket), depth band 10 %-100 % of the bucket length l3, surface band
    (entry and exit heights) 0.1 l3.

    Raises:
        ConfigurationError: An unknown soil (the message lists the rig's), a volume band that
            is empty, not positive or above the bucket's capacity, or another bad value.
    """
    try:
        fs = rig.soil.fluid_named(soil_name)
    except KeyError:
        known = ", ".join(s.name for s in rig.soil.fluid)
        raise ConfigurationError(
            f"rig {rig.name!r} has no fluid soil {soil_name!r} (Yang/Pan Table 2); "
            f"its soils: {known}"
        ) from None
    lo, hi = (float(v) for v in volume_m3)
    cap = rig.bucket.capacity_m3
    if not (math.isfinite(lo) and math.isfinite(hi)) or not 0.0 < lo < hi:
        raise ConfigurationError(
            f"volume band {lo:g}..{hi:g} m^3 is empty or not positive; give 0 < LO < HI"
        )
    if hi > cap + 1e-12:
        raise ConfigurationError(
            f"volume band {lo:g}..{hi:g} m^3 exceeds the bucket capacity of {rig.name} "
            f"({cap:g} m^3); give HI <= {cap:g}"
        )
    reach = float(np.sum(rig.lengths_m))
    l3 = float(rig.lengths_m[2])
    problem = MinTorqueProblem(
        soil=fs,
        surface_y_m=rig.ground_y_m if surface_y_m is None else float(surface_y_m),
        volume_m3=(lo, hi),
        depth_m=depth_m if depth_m is not None else (0.1 * l3, 1.0 * l3),
        entry_x_m=entry_x_m if entry_x_m is not None else (0.60 * reach, 0.72 * reach),
        surface_band_m=0.1 * l3,
        fixed_time=fixed_time,
        samples_per_interval=samples_per_interval,
    )
    validate_problem(problem)
    return problem


def validate_problem(p: MinTorqueProblem) -> None:
    """Check a problem's numbers.

    Raises:
        ConfigurationError: A value that is not finite, an empty band, a bad count.
    """
    values = (p.surface_y_m, *p.volume_m3, *p.depth_m, *p.entry_x_m, p.surface_band_m)
    if not all(math.isfinite(v) for v in (*values, *p.intervals_s, *p.interval_bounds_s)):
        raise ConfigurationError("min-torque problem has a value that is not finite")
    for label, (a, b) in (
        ("volume_m3", p.volume_m3),
        ("depth_m", p.depth_m),
        ("entry_x_m", p.entry_x_m),
        ("interval_bounds_s", p.interval_bounds_s),
    ):
        if not a < b:
            raise ConfigurationError(f"{label} band {a:g}..{b:g} is empty; give LO < HI")
    if p.depth_m[0] < 0.0 or p.interval_bounds_s[0] <= 0.0 or p.surface_band_m <= 0.0:
        raise ConfigurationError("depth_m, interval_bounds_s and surface_band_m must be > 0")
    if len(p.intervals_s) != N_INTERVALS or min(p.intervals_s) <= 0.0:
        raise ConfigurationError(f"intervals_s needs {N_INTERVALS} values > 0 s")
    if p.samples_per_interval < 2 or p.n_elements < 1:
        raise ConfigurationError("samples_per_interval must be >= 2 and n_elements >= 1")


# --------------------------------------------------------------------------------------------
# The model, written once for numpy (batched rows) and for CasADi (the benchmark's reference).


class _NumpyOps:
    """Array operations of the model on numpy rows ``(B,)`` -> samples ``(B, S)``."""

    sin = staticmethod(np.sin)
    cos = staticmethod(np.cos)
    sqrt = staticmethod(np.sqrt)

    @staticmethod
    def scaled(a: Any, basis: FloatArray) -> Any:
        return np.asarray(a)[..., None] * basis

    @staticmethod
    def cat(parts: Sequence[Any]) -> Any:
        return np.concatenate(parts, axis=-1)

    @staticmethod
    def total(a: Any) -> Any:
        return np.sum(a, axis=-1)


class _CasadiOps:
    """The same operations on CasADi SX scalars -> column vectors ``(S, 1)``."""

    def __init__(self) -> None:
        import casadi

        self.ca = casadi
        self.sin = casadi.sin
        self.cos = casadi.cos
        self.sqrt = casadi.sqrt

    def scaled(self, a: Any, basis: FloatArray) -> Any:
        return a * self.ca.DM(basis)

    def cat(self, parts: Sequence[Any]) -> Any:
        return self.ca.vertcat(*parts)

    def total(self, a: Any) -> Any:
        return self.ca.sum1(a)


def _hermite_basis(Q: int) -> dict[str, FloatArray]:
    """Quintic Hermite shape functions (zero end accelerations) and trapezoid weights on
    ``u = 0, 1/Q, .., 1``."""
    u = np.linspace(0.0, 1.0, Q + 1)
    u2, u3, u4, u5 = u**2, u**3, u**4, u**5
    w = np.full(Q + 1, 1.0 / Q)
    w[[0, -1]] *= 0.5
    return {
        "h0": 1.0 - 10 * u3 + 15 * u4 - 6 * u5,
        "h5": 10 * u3 - 15 * u4 + 6 * u5,
        "h1": u - 6 * u3 + 8 * u4 - 3 * u5,
        "h4": -4 * u3 + 7 * u4 - 3 * u5,
        "d0": -30 * u2 + 60 * u3 - 30 * u4,
        "d1": 1.0 - 18 * u2 + 32 * u3 - 15 * u4,
        "d4": -12 * u2 + 28 * u3 - 15 * u4,
        "a0": -60 * u + 180 * u2 - 120 * u3,
        "a1": -36 * u + 96 * u2 - 60 * u3,
        "a4": -24 * u + 84 * u2 - 60 * u3,
        "j0": -60 + 360 * u - 360 * u2,
        "j1": -36 + 192 * u - 180 * u2,
        "j4": -24 + 168 * u - 180 * u2,
        "w": w,
    }


def knot_velocities(keys: Sequence[Sequence[Any]], h: Sequence[Any]) -> list[list[Any]]:
    """Keypoint velocities (rad/s): zero at both ends, the three-point slope estimate
    ``(h_k s_{k-1} + h_{k-1} s_k) / (h_{k-1} + h_k)`` inside (``s`` the chord slopes)."""
    n = len(keys)
    s = [[(keys[k + 1][j] - keys[k][j]) / h[k] for j in range(3)] for k in range(n - 1)]
    inner = [
        [(h[k] * s[k - 1][j] + h[k - 1] * s[k][j]) / (h[k - 1] + h[k]) for j in range(3)]
        for k in range(1, n - 1)
    ]
    return [[0.0 * h[0]] * 3, *inner, [0.0 * h[0]] * 3]


@dataclass(frozen=True, slots=True)
class _Chain:
    """Lumped mass parameters of the arm in absolute angles (as :mod:`rt_runtime.dynamics`)."""

    h: tuple[float, float, float]
    b: tuple[float, float, float]
    d: tuple[float, float, float]
    lengths: tuple[float, float, float]
    g: float

    @classmethod
    def of(cls, rig: Rig) -> _Chain:
        links = rig.links
        beyond = (links[1].mass_kg + links[2].mass_kg, links[2].mass_kg, 0.0)
        hh = [
            lk.mass_kg * lk.com_m[0] + m * lk.length_m for lk, m in zip(links, beyond, strict=True)
        ]
        bb = [lk.mass_kg * lk.com_m[1] for lk in links]
        dd = [
            lk.inertia_kgm2
            + lk.mass_kg * (lk.com_m[0] ** 2 + lk.com_m[1] ** 2)
            + m * lk.length_m**2
            for lk, m in zip(links, beyond, strict=True)
        ]
        ll = [lk.length_m for lk in links]
        return cls(
            (hh[0], hh[1], hh[2]),
            (bb[0], bb[1], bb[2]),
            (dd[0], dd[1], dd[2]),
            (ll[0], ll[1], ll[2]),
            rig.gravity_m_s2,
        )


@dataclass(frozen=True, slots=True)
class _Plate:
    """One plate: centre, normal and tangent in the bucket frame relative to the tip, area."""

    cx: float
    cy: float
    nx: float
    ny: float
    tx: float
    ty: float
    area: float


def _plates(rig: Rig, n: int) -> tuple[_Plate, ...]:
    """The bucket outline cut into plates, as :func:`rt_runtime.soil.fluid_resistance` cuts it."""
    pts = np.asarray(rig.bucket.profile_m, dtype=np.float64)
    out = []
    for p0, p1 in itertools.pairwise(pts):
        seg = p1 - p0
        length = float(np.hypot(*seg))
        t = seg / length
        for k in range(n):
            c = p0 + (k + 0.5) / n * seg
            out.append(
                _Plate(
                    float(c[0]),
                    float(c[1]),
                    float(-t[1]),
                    float(t[0]),
                    float(t[0]),
                    float(t[1]),
                    length / n * rig.bucket.width_m,
                )
            )
    return tuple(out)


@dataclass(frozen=True, slots=True)
class _Samples:
    """Per-sample model quantities, each a per-joint list of ``(B, S)`` (or ``(S, 1)``)."""

    q: list[Any]
    qd: list[Any]
    qdd: list[Any]
    jerk: list[Any]
    tau: list[Any]
    weight: Any
    tip_y: Any


def _keys_of(x: Any, row: Callable[[Any, int], Any]) -> list[list[Any]]:
    return [[row(x, 3 * k + j) for j in range(3)] for k in range(N_KEY)]


class _Model:
    """The smoothed objective and constraints on keypoints and intervals."""

    def __init__(self, rig: Rig, problem: MinTorqueProblem, ops: Any) -> None:
        self.rig = rig
        self.p = problem
        self.ops = ops
        self.basis = _hermite_basis(problem.samples_per_interval)
        self.chain = _Chain.of(rig)
        self.plates = _plates(rig, problem.n_elements)
        #: The plates' fields as ``(P, 1, 1)`` arrays (the plate axis of few rows' soil).
        self.plate_axis = {
            f: np.array([getattr(pl, f) for pl in self.plates])[:, None, None]
            for f in ("cx", "cy", "nx", "ny", "tx", "ty", "area")
        }
        self.tau_max = [float(v) for v in rig.tau_max_nm]

    def samples(self, keys: list[list[Any]], h: Sequence[Any]) -> _Samples:
        ops, B = self.ops, self.basis
        vel = knot_velocities(keys, h)
        q: list[Any] = []
        qd: list[Any] = []
        qdd: list[Any] = []
        qddd: list[Any] = []
        for j in range(3):
            qs, vs, acs, js = [], [], [], []
            for i in range(N_INTERVALS):
                p0, p1, v0, v1, hi = keys[i][j], keys[i + 1][j], vel[i][j], vel[i + 1][j], h[i]
                qs.append(
                    ops.scaled(p0, B["h0"])
                    + ops.scaled(p1, B["h5"])
                    + ops.scaled(hi * v0, B["h1"])
                    + ops.scaled(hi * v1, B["h4"])
                )
                vs.append(
                    ops.scaled((p1 - p0) / hi, -B["d0"])
                    + ops.scaled(v0, B["d1"])
                    + ops.scaled(v1, B["d4"])
                )
                acs.append(
                    ops.scaled((p0 - p1) / (hi * hi), B["a0"])
                    + ops.scaled(v0 / hi, B["a1"])
                    + ops.scaled(v1 / hi, B["a4"])
                )
                js.append(
                    ops.scaled((p0 - p1) / (hi * hi * hi), B["j0"])
                    + ops.scaled(v0 / (hi * hi), B["j1"])
                    + ops.scaled(v1 / (hi * hi), B["j4"])
                )
            q.append(ops.cat(qs))
            qd.append(ops.cat(vs))
            qdd.append(ops.cat(acs))
            qddd.append(ops.cat(js))
        weight = ops.cat([ops.scaled(h[i], B["w"]) for i in range(N_INTERVALS)])
        tau, tip_y = self._torques(q, qd, qdd)
        return _Samples(q, qd, qdd, qddd, tau, weight, tip_y)

    def _torques(self, q: list[Any], qd: list[Any], qdd: list[Any]) -> tuple[list[Any], Any]:
        ops, ch = self.ops, self.chain
        l0, l1, l2 = ch.lengths
        phi0 = q[0]
        phi1 = phi0 + q[1]
        phi2 = phi1 + q[2]
        cp0, sp0, cp1, sp1 = ops.cos(phi0), ops.sin(phi0), ops.cos(phi1), ops.sin(phi1)
        cp2, sp2 = ops.cos(phi2), ops.sin(phi2)
        w0 = qd[0]
        w1 = w0 + qd[1]
        w2 = w1 + qd[2]
        a0 = qdd[0]
        a1 = a0 + qdd[1]
        a2 = a1 + qdd[2]
        # Tip pose and twist (Yao eq 3; the Jacobian of rt_runtime.kinematics).
        x = l0 * cp0 + l1 * cp1 + l2 * cp2
        y = l0 * sp0 + l1 * sp1 + l2 * sp2
        vx = -(l0 * sp0 * w0 + l1 * sp1 * w1 + l2 * sp2 * w2)
        vy = l0 * cp0 * w0 + l1 * cp1 * w1 + l2 * cp2 * w2
        fx, fy, mz = self._soil(x, y, cp2, sp2, vx, vy, w2)
        # Closed-form inverse dynamics in absolute angles (rt_runtime.dynamics, module docstring).
        c2, s2 = ops.cos(q[1]), ops.sin(q[1])
        c3, s3 = ops.cos(q[2]), ops.sin(q[2])
        c23, s23 = ops.cos(q[1] + q[2]), ops.sin(q[1] + q[2])
        h, b, d, g = ch.h, ch.b, ch.d, ch.g
        d01 = l0 * (h[1] * c2 - b[1] * s2)
        w01 = l0 * (b[1] * c2 + h[1] * s2)
        d02 = l0 * (h[2] * c23 - b[2] * s23)
        w02 = l0 * (b[2] * c23 + h[2] * s23)
        d12 = l1 * (h[2] * c3 - b[2] * s3)
        w12 = l1 * (b[2] * c3 + h[2] * s3)
        ww0, ww1, ww2 = w0 * w0, w1 * w1, w2 * w2
        t0 = d[0] * a0 + d01 * a1 + d02 * a2 - w01 * ww1 - w02 * ww2
        t0 = t0 + g * (h[0] * cp0 - b[0] * sp0) - l0 * (cp0 * fy - sp0 * fx)
        t1 = d01 * a0 + d[1] * a1 + d12 * a2 + w01 * ww0 - w12 * ww2
        t1 = t1 + g * (h[1] * cp1 - b[1] * sp1) - l1 * (cp1 * fy - sp1 * fx)
        t2 = d02 * a0 + d12 * a1 + d[2] * a2 + w02 * ww0 + w12 * ww1
        t2 = t2 + g * (h[2] * cp2 - b[2] * sp2) - l2 * (cp2 * fy - sp2 * fx) - mz
        t1 = t1 + t2
        t0 = t0 + t1
        return [t0, t1, t2], y

    def _soil(
        self, x: Any, y: Any, c: Any, s: Any, vx: Any, vy: Any, om: Any
    ) -> tuple[Any, Any, Any]:
        """Smoothed eq 13-18: the soil's wrench at the tip (arm frame), module docstring."""
        ops, fs = self.ops, self.p.soil
        eps, r = SMOOTH_DEPTH_M, SMOOTH_SPEED_M_S
        rho_g = fs.kp * fs.density_kg_m3 * self.rig.gravity_m_s2
        u = c * vx + s * vy
        w = c * vy - s * vx
        if ops is _NumpyOps and np.ndim(x) == 2 and x.shape[0] <= _PLATE_AXIS_ROWS:
            # Few rows (a line-search point): one pass with a plate axis, (P, B, S), costs
            # fewer numpy calls than the loop, whose calls then cost more than their work.
            pa = self.plate_axis
            cx, cy, nx, ny, tx, ty = (pa[f] for f in ("cx", "cy", "nx", "ny", "tx", "ty"))
            depth = self.p.surface_y_m - (y + cx * s + cy * c)
            root = np.sqrt(depth * depth + eps * eps)
            arm_n = cx * ny - cy * nx
            arm_t = cx * ty - cy * tx
            vn = u * nx + w * ny + om * arm_n
            vt = u * tx + w * ty + om * arm_t
            rn = np.sqrt(vn * vn + r * r)
            rt = np.sqrt(vt * vt + r * r)
            mag = (rho_g * 0.5 * (depth + root) + fs.kv * (rn - r)) * (
                pa["area"] * 0.5 * (1.0 + depth / root)
            )
            un = mag * (vn / rn)
            ut = mag * (fs.ks * vt / rt)
            fxp = -np.sum(un * nx + ut * tx, axis=0)
            fyp = -np.sum(un * ny + ut * ty, axis=0)
            mzp = -np.sum(un * arm_n + ut * arm_t, axis=0)
            return c * fxp - s * fyp, s * fxp + c * fyp, mzp
        # Many rows: a loop over the plates on (B, S) arrays, measured faster than one pass
        # with a plate axis (P, B, S), whose temporaries leave the cache; CasADi needs the loop.
        fxb: Any = 0.0
        fyb: Any = 0.0
        mz: Any = 0.0
        for pl in self.plates:
            depth = self.p.surface_y_m - (y + pl.cx * s + pl.cy * c)
            root = ops.sqrt(depth * depth + eps * eps)
            vn = u * pl.nx + w * pl.ny + om * (pl.cx * pl.ny - pl.cy * pl.nx)
            vt = u * pl.tx + w * pl.ty + om * (pl.cx * pl.ty - pl.cy * pl.tx)
            rn = ops.sqrt(vn * vn + r * r)
            rt = ops.sqrt(vt * vt + r * r)
            mag = (rho_g * 0.5 * (depth + root) + fs.kv * (rn - r)) * (
                pl.area * 0.5 * (1.0 + depth / root)
            )
            un = vn / rn
            ut = fs.ks * vt / rt
            fxb = fxb - mag * (un * pl.nx + ut * pl.tx)
            fyb = fyb - mag * (un * pl.ny + ut * pl.ty)
            mz = mz - mag * (
                un * (pl.cx * pl.ny - pl.cy * pl.nx) + ut * (pl.cx * pl.ty - pl.cy * pl.tx)
            )
        return c * fxb - s * fyb, s * fxb + c * fyb, mz

    def cost(self, smp: _Samples) -> Any:
        """``sum_i integral ||tau / tau_max||^2 dt`` (trapezoid, s)."""
        sq = sum((smp.tau[j] / self.tau_max[j]) ** 2 for j in range(3))
        return self.ops.total(smp.weight * sq)

    def keypoint_constraints(self, keys: list[list[Any]]) -> list[Any]:
        """Values of :data:`KEYPOINT_CONSTRAINTS` (<= 0 holds), in that order."""
        ops, p = self.ops, self.p
        l0, l1, l2 = self.chain.lengths
        tip = []
        for kq in keys:
            a0 = kq[0]
            a1 = a0 + kq[1]
            a2 = a1 + kq[2]
            tip.append(
                (
                    l0 * ops.cos(a0) + l1 * ops.cos(a1) + l2 * ops.cos(a2),
                    l0 * ops.sin(a0) + l1 * ops.sin(a1) + l2 * ops.sin(a2),
                    ops.cos(a2),
                    ops.sin(a2),
                )
            )
        H = p.surface_y_m
        quad = [tip[0], tip[1], tip[2], tip[4]]
        twice = sum(
            quad[i][0] * quad[(i + 1) % 4][1] - quad[(i + 1) % 4][0] * quad[i][1] for i in range(4)
        )
        # Clockwise (negative shoelace) for a dig towards the machine.
        volume = -0.5 * twice * self.rig.bucket.width_m
        v_lo, v_hi = p.volume_m3
        z_lo, z_hi = p.depth_m
        x_lo, x_hi = p.entry_x_m
        band = p.surface_band_m
        out: list[Any] = [
            (v_lo - volume) / (v_hi - v_lo),
            (volume - v_hi) / (v_hi - v_lo),
        ]
        for k in (1, 2):
            depth = H - tip[k][1]
            out += [(z_lo - depth) / (z_hi - z_lo), (depth - z_hi) / (z_hi - z_lo)]
        out += [
            (H - band - tip[0][1]) / band,
            (tip[0][1] - H) / band,
            (x_lo - tip[0][0]) / (x_hi - x_lo),
            (tip[0][0] - x_hi) / (x_hi - x_lo),
            (H - tip[4][1]) / band,
            (tip[4][1] - H - band) / band,
        ]
        # Heading cones as two half-planes each (eq 9, Fig. 4b): d_h . n <= 0 with the normals
        # n = R(+-(90 deg + half-angle)) c around the cone's axis c.
        for (hx, hy), axis, half in (
            ((tip[0][2], tip[0][3]), (0.0, -1.0), math.radians(p.entry_heading_deg)),
            ((tip[4][2], tip[4][3]), (0.0, 1.0), math.radians(p.lift_heading_deg)),
        ):
            for sign in (1.0, -1.0):
                ang = sign * (0.5 * math.pi + half)
                nx = math.cos(ang) * axis[0] - math.sin(ang) * axis[1]
                ny = math.sin(ang) * axis[0] + math.cos(ang) * axis[1]
                out.append(hx * nx + hy * ny)
        chords = []
        for k in range(N_KEY - 1):
            dx = tip[k + 1][0] - tip[k][0]
            dy = tip[k + 1][1] - tip[k][1]
            norm = ops.sqrt(dx * dx + dy * dy + 1e-12)
            chords.append((dx / norm, dy / norm))
        # Travel half-planes (eq 9): penetration goes down, the drag towards the machine, the
        # lift up.
        out += [chords[0][1], chords[1][0], -chords[3][1]]
        # Monotonic turns (eq 10-11): d_{i+1} . R90 d_i = cross(d_i, d_{i+1}) <= 0.
        for k in range(N_KEY - 1):
            out.append(tip[k][2] * tip[k + 1][3] - tip[k][3] * tip[k + 1][2])
        for k in range(N_KEY - 2):
            out.append(chords[k][0] * chords[k + 1][1] - chords[k][1] * chords[k + 1][0])
        return out


# --------------------------------------------------------------------------------------------
# The numpy evaluation and its batched gradients.


@dataclass(frozen=True, slots=True)
class Evaluation:
    """The smoothed model at a batch of points.

    Attributes:
        cost: ``(B,)`` objective (s).
        constraints: ``(B, n)`` values of :data:`CONSTRAINT_NAMES` (<= 0 holds).
        split: ``(B, m)`` what SLSQP sees: the sampled limits as one smooth maximum per
            interval, joint and side (the peaks themselves have kinks where two samples or
            both signs are equal; the smooth maximum lies above the peak by at most
            ``log(samples_per_interval + 1) / KS_RHO``), then the keypoint constraints.
    """

    cost: FloatArray
    constraints: FloatArray
    split: FloatArray


class Evaluator:
    """Objective and constraints of a problem on the smoothed model, batched over points.

    A point is ``x = (k0 .. k4 joint angles (15,), intervals (4,))``; in a fixed-time solve
    the intervals are the problem's.
    """

    def __init__(
        self,
        rig: Rig,
        problem: MinTorqueProblem,
        *,
        limit_scale: FloatArray | None = None,
        backend: str = "auto",
    ) -> None:
        validate_problem(problem)
        module = kernel_for(backend)
        self.rig = rig
        self.problem = problem
        self.model = _Model(rig, problem, _NumpyOps)
        #: Per-joint scale (<= 1) of the velocity, acceleration, jerk and torque limits:
        #: ``(4, 3)``.
        self.limit_scale = (
            np.ones((4, 3)) if limit_scale is None else np.asarray(limit_scale, np.float64)
        )
        #: The compiled kernel's module (``mintorque``), None for the numpy model.
        self.module = module
        #: ``"c"`` or ``"numpy"``: who evaluates.
        self.backend = "numpy" if module is None else "c"
        if module is not None:
            self._packed = _pack_kernel(self.model, self.limit_scale)

    def evaluate(self, X: ArrayLike) -> Evaluation:
        """Evaluate points ``X`` shaped ``(B, 19)`` (``(B, 15)`` in a fixed-time problem)."""
        if self.module is not None:
            xc = np.ascontiguousarray(np.atleast_2d(np.asarray(X, dtype=np.float64)))
            B = xc.shape[0]
            cost = np.empty(B)
            named = np.empty((B, len(CONSTRAINT_NAMES)))
            split = np.empty((B, N_SPLIT))
            params, basis, plates = self._packed
            self.module.mintorque(xc, params, basis, plates, cost, named, split)
            return Evaluation(cost, named, split)
        return self.evaluate_numpy(X)

    def evaluate_numpy(self, X: ArrayLike) -> Evaluation:
        """:meth:`evaluate` by the numpy model (the reference of the compiled kernel)."""
        x = np.atleast_2d(np.asarray(X, dtype=np.float64))
        keys = _keys_of(x, lambda a, i: a[:, i])
        if x.shape[1] > 3 * N_KEY:
            h = [x[:, 3 * N_KEY + i] for i in range(N_INTERVALS)]
        else:
            h = [np.full(x.shape[0], v) for v in self.problem.intervals_s]
        m = self.model
        smp = m.samples(keys, h)
        rig = self.rig
        q = np.stack(smp.q, axis=-1)  # (B, S, 3)
        qd = np.stack(smp.qd, axis=-1)
        qdd = np.stack(smp.qdd, axis=-1)
        jerk = np.stack(smp.jerk, axis=-1)
        tau = np.stack(smp.tau, axis=-1)
        span = rig.q_max_rad - rig.q_min_rad
        v_lim = rig.qd_max_rad_s * self.limit_scale[0]
        a_lim = rig.qdd_max_rad_s2 * self.limit_scale[1]
        j_lim = _jerk_max(rig) * self.limit_scale[2]
        t_lim = rig.tau_max_nm * self.limit_scale[3]
        B = x.shape[0]
        per_sample = np.concatenate(
            [
                (rig.q_min_rad - q) / span,
                (q - rig.q_max_rad) / span,
                qd / v_lim - 1.0,
                -qd / v_lim - 1.0,
                qdd / a_lim - 1.0,
                -qdd / a_lim - 1.0,
                jerk / j_lim - 1.0,
                -jerk / j_lim - 1.0,
                tau / t_lim - 1.0,
                -tau / t_lim - 1.0,
            ],
            axis=-1,
        )  # (B, S, 30)
        peak = np.max(per_sample, axis=1).reshape(B, 10, 3)
        kp = np.stack(m.keypoint_constraints(keys), axis=-1)
        # Per interval, joint and side the smooth maximum (Kreisselmeier-Steinhauser) of the
        # interval's samples: above the true peak by at most log(Q + 1) / KS_RHO.
        g = per_sample.reshape(B, N_INTERVALS, -1, per_sample.shape[-1])
        top = np.max(g, axis=2, keepdims=True)
        ks = top[:, :, 0] + np.log(np.sum(np.exp(KS_RHO * (g - top)), axis=2)) / KS_RHO
        split = np.concatenate([ks.reshape(B, -1), kp], axis=1)
        named = np.concatenate(
            [
                peak[:, 0],
                peak[:, 1],
                np.maximum(peak[:, 2], peak[:, 3]),
                np.maximum(peak[:, 4], peak[:, 5]),
                np.maximum(peak[:, 6], peak[:, 7]),
                np.maximum(peak[:, 8], peak[:, 9]),
                kp,
            ],
            axis=1,
        )
        return Evaluation(np.asarray(m.cost(smp)), named, split)

    def gradients(
        self, x: ArrayLike, at_x: tuple[float, FloatArray] | None = None
    ) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        """Cost, its gradient ``(n,)``, the optimiser's constraints ``(m,)`` and their Jacobian
        ``(m, n)`` at one point, by forward differences of step :data:`FD_STEP`: numpy
        evaluates the point and its ``n`` perturbations in one batched pass (only the
        perturbations where ``at_x``, the cost and constraints at ``x`` already evaluated, is
        given); the kernel evaluates each perturbation on the intervals its variable moves."""
        xa = np.asarray(x, dtype=np.float64)
        n = xa.size
        if self.module is not None:
            # The kernel evaluates each perturbation on the intervals it moves only.
            if at_x is None:
                e0 = self.evaluate(xa[None, :])
                at_x = (float(e0.cost[0]), e0.split[0])
            f0, c0 = at_x
            cost = np.empty(n)
            split = np.empty((n, N_SPLIT))
            params, basis, plates = self._packed
            self.module.mintorque_perturbed(
                np.ascontiguousarray(xa), FD_STEP, params, basis, plates, cost, split
            )
            return f0, (cost - f0) / FD_STEP, c0, ((split - c0) / FD_STEP).T
        if at_x is None:
            X = np.repeat(xa[None, :], n + 1, axis=0)
            X[1:] += FD_STEP * np.eye(n)
            e = self.evaluate(X)
            f0, c0 = float(e.cost[0]), e.split[0]
            cost, split = e.cost[1:], e.split[1:]
        else:
            f0, c0 = at_x
            e = self.evaluate(xa[None, :] + FD_STEP * np.eye(n))
            cost, split = e.cost, e.split
        return f0, (cost - f0) / FD_STEP, c0, ((split - c0) / FD_STEP).T


@functools.cache
def _kernel_module() -> Any:
    """The compiled kernel's module when it is built and has the model, else None."""
    from rt_runtime.planning.verify import _load_extension

    module = _load_extension()
    return module if module is not None and hasattr(module, "mintorque") else None


def kernel_for(backend: str) -> Any:
    """The compiled kernel's module for ``backend`` (:data:`BACKENDS`): the module for ``c``,
    the module or None (not built) for ``auto``, None for ``numpy``.

    Raises:
        ConfigurationError: An unknown backend; ``c`` where the kernel is not built.
    """
    if backend not in BACKENDS:
        raise ConfigurationError(f"unknown backend {backend!r}; allowed: {', '.join(BACKENDS)}")
    module = None if backend == "numpy" else _kernel_module()
    if backend == "c" and module is None:
        from rt_runtime.planning.verify import BUILD_HINT

        raise ConfigurationError(f"the compiled kernel is not built; {BUILD_HINT}")
    return module


def _pack_kernel(model: _Model, limit_scale: FloatArray) -> tuple[FloatArray, ...]:
    """The compiled model's constants ``(64,)`` (``kernel/kernel.h``, ``enum mt_param``), shape
    functions ``(14, Q + 1)`` and plates ``(P, 7)``."""
    rig, p, ch = model.rig, model.p, model.chain
    fs = p.soil
    heading = []
    for axis, half in (
        ((0.0, -1.0), math.radians(p.entry_heading_deg)),
        ((0.0, 1.0), math.radians(p.lift_heading_deg)),
    ):
        for sign in (1.0, -1.0):
            ang = sign * (0.5 * math.pi + half)
            heading += [
                math.cos(ang) * axis[0] - math.sin(ang) * axis[1],
                math.sin(ang) * axis[0] + math.cos(ang) * axis[1],
            ]
    fields = [
        ch.lengths, ch.h, ch.b, ch.d, [ch.g],
        [fs.kp * fs.density_kg_m3 * rig.gravity_m_s2, fs.kv, fs.ks],
        [SMOOTH_DEPTH_M, SMOOTH_SPEED_M_S, p.surface_y_m],
        rig.q_min_rad, rig.q_max_rad, rig.q_max_rad - rig.q_min_rad,
        rig.qd_max_rad_s * limit_scale[0], rig.qdd_max_rad_s2 * limit_scale[1],
        _jerk_max(rig) * limit_scale[2], rig.tau_max_nm * limit_scale[3],
        model.tau_max, [KS_RHO],
        p.volume_m3, p.depth_m, p.entry_x_m, [p.surface_band_m, rig.bucket.width_m],
        heading, p.intervals_s,
    ]  # fmt: skip
    params = np.concatenate([np.asarray(f, dtype=np.float64) for f in fields])
    assert params.shape == (_N_KERNEL_PARAMS,) and params[KERNEL_SURFACE] == p.surface_y_m
    basis = np.ascontiguousarray(np.stack([model.basis[k] for k in _BASIS_ORDER]))
    plates = np.array(
        [[pl.cx, pl.cy, pl.nx, pl.ny, pl.tx, pl.ty, pl.area] for pl in model.plates],
        dtype=np.float64,
    )
    return params, basis, plates


# --------------------------------------------------------------------------------------------
# Starts, solve and the exact re-check.


def _template(
    rig: Rig, p: MinTorqueProblem, entry_x: float, depth: float, drag: float
) -> FloatArray | None:
    """Keypoint joint angles ``(5, 3)`` of a kinematic dig template, or None when unreachable.

    Tip poses (lengths in bucket lengths l3): a on the surface with the teeth down, b
    ``depth`` below and 0.3 l3 nearer the machine, c ``drag`` further at the same depth, the
    rotation keypoint 0.4 l3 on and half-way up, d 0.3 l3 on, just above the surface with the
    bucket curled; attitudes -95, -120, -160, -210, -250 deg.
    """
    H = p.surface_y_m
    l3 = float(rig.lengths_m[2])
    xb = entry_x - 0.3 * l3
    xc = xb - drag
    xr = xc - 0.4 * l3
    poses = (
        (entry_x, H - 0.25 * p.surface_band_m, -95.0),
        (xb, H - depth, -120.0),
        (xc, H - depth, -160.0),
        (xr, H - 0.5 * depth, -210.0),
        (xr - 0.3 * l3, H + 0.5 * p.surface_band_m, -250.0),
    )
    arm = kinematics.FastArm(rig)
    out = []
    for x, y, att in poses:
        q = arm.ik(x, y, math.radians(att))
        if q is None:
            return None
        out.append(q)
    return np.asarray(out, dtype=np.float64)


def kinematic_starts(rig: Rig, p: MinTorqueProblem, n: int) -> list[FloatArray]:
    """Up to ``n`` starts ``(15,)`` from a coarse reachability search over dig templates.

    The templates (entry x over the window, depth over the band, drag length 0.4-1.3 bucket
    lengths) whose keypoints
    the arm reaches within its joint limits are ranked by how far their quadrilateral's volume
    lies from the middle of the band; the best ``n`` with distinct (depth, drag) are kept.
    Depends on kinematics only, so every soil gets the same starts.
    """
    z_lo, z_hi = p.depth_m
    cands: list[tuple[float, float, float, FloatArray]] = []
    target = 0.5 * sum(p.volume_m3)
    for ex in np.linspace(*p.entry_x_m, 3):
        for depth in np.linspace(z_lo + 0.25 * (z_hi - z_lo), z_hi - 0.1 * (z_hi - z_lo), 3):
            for drag in np.array([0.4, 0.7, 1.0, 1.3]) * float(rig.lengths_m[2]):
                keys = _template(rig, p, float(ex), float(depth), float(drag))
                if keys is None:
                    continue
                pos = kinematics.forward(rig, keys)
                quad = pos[[0, 1, 2, 4], :2]
                twice = np.sum(
                    quad[:, 0] * np.roll(quad[:, 1], -1) - np.roll(quad[:, 0], -1) * quad[:, 1]
                )
                vol = -0.5 * twice * rig.bucket.width_m
                cands.append((abs(vol - target), float(depth), float(drag), keys.reshape(-1)))
    cands.sort(key=lambda c: c[0])
    out: list[FloatArray] = []
    seen: set[tuple[float, float]] = set()
    for _, depth, drag, keys in cands:
        if (depth, drag) in seen:
            continue
        seen.add((depth, drag))
        out.append(keys)
        if len(out) == n:
            break
    return out


@dataclass(frozen=True, slots=True, eq=False)
class Solution:
    """An optimised dig, re-checked on the exact model.

    Attributes:
        feasible: Every margin of the exact re-check is >= 0.
        keypoints_rad: ``(5, 3)`` joint angles of a, b, c, the rotation keypoint, d.
        tip_poses: ``(5, 3)`` tip ``x_m``, ``y_m``, ``attitude_rad`` at the keypoints.
        intervals_s: ``(4,)``.
        T_s: Total time.
        cost: Objective on the exact model at 1 ms (s).
        cost_model: Objective on the optimiser's smoothed model and grid.
        volume_m3: Swept volume of eq 8.
        max_depth_m: Largest depth of the tip below the surface on the 1 ms resample.
        margins: Name to margin (``-`` the normalised constraint; >= 0 holds) on the exact
            model at 1 ms, every name of :data:`CONSTRAINT_NAMES`.
        solve_s: Wall time of the solve (starts, SLSQP, re-checks; not the one-time import of
            SciPy's optimisers).
        start: The start the answer came from, ``(15,)`` (or ``(19,)``), for a reference.
        x: The optimiser's point.
        iterations: SLSQP iterations of the answer's start.
        message: SLSQP's message for that start.
    """

    feasible: bool
    keypoints_rad: FloatArray
    tip_poses: FloatArray
    intervals_s: FloatArray
    T_s: float
    cost: float
    cost_model: float
    volume_m3: float
    max_depth_m: float
    margins: dict[str, float]
    solve_s: float
    start: FloatArray
    x: FloatArray
    iterations: int
    message: str
    limit_scale: FloatArray = field(default_factory=lambda: np.ones((4, 3)))

    def sample(self, t_s: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Joint angles, velocities and accelerations ``(n, 3)`` each at times ``t_s`` (s)."""
        return sample_path(self.keypoints_rad, self.intervals_s, t_s)


def _pieces(
    keypoints_rad: ArrayLike, intervals_s: ArrayLike, t_s: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Each time's piece of the interpolation: its end keypoints ``p0``, ``p1`` and knot
    velocities ``v0``, ``v1`` (``(n, 3)``), its duration ``hs`` and the normalised time ``u``
    in it (``(n, 1)``); times clipped to ``[0, T]``."""
    keys = np.asarray(keypoints_rad, dtype=np.float64)
    h = np.asarray(intervals_s, dtype=np.float64)
    t = np.clip(np.atleast_1d(np.asarray(t_s, dtype=np.float64)), 0.0, float(np.sum(h)))
    knots = np.concatenate([[0.0], np.cumsum(h)])
    seg = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(h) - 1)
    vel = np.asarray(knot_velocities(keys.tolist(), h.tolist()), dtype=np.float64)
    hs = h[seg][:, None]
    u = ((t - knots[seg]) / h[seg])[:, None]
    return keys[seg], keys[seg + 1], vel[seg], vel[seg + 1], hs, u


def sample_path(
    keypoints_rad: ArrayLike, intervals_s: ArrayLike, t_s: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The interpolation between keypoints (module docstring) at times ``t_s`` (clipped to
    ``[0, T]``): ``q``, ``qd``, ``qdd`` shaped ``(n, 3)``."""
    p0, p1, v0, v1, hs, u = _pieces(keypoints_rad, intervals_s, t_s)
    u2, u3, u4, u5 = u**2, u**3, u**4, u**5
    q = (
        p0 * (1 - 10 * u3 + 15 * u4 - 6 * u5)
        + p1 * (10 * u3 - 15 * u4 + 6 * u5)
        + hs * v0 * (u - 6 * u3 + 8 * u4 - 3 * u5)
        + hs * v1 * (-4 * u3 + 7 * u4 - 3 * u5)
    )
    qd = (
        (p1 - p0) / hs * (30 * u2 - 60 * u3 + 30 * u4)
        + v0 * (1 - 18 * u2 + 32 * u3 - 15 * u4)
        + v1 * (-12 * u2 + 28 * u3 - 15 * u4)
    )
    qdd = (
        (p1 - p0) / hs**2 * (60 * u - 180 * u2 + 120 * u3)
        + v0 / hs * (-36 * u + 96 * u2 - 60 * u3)
        + v1 / hs * (-24 * u + 84 * u2 - 60 * u3)
    )
    return q, qd, qdd


def path_jerk(keypoints_rad: ArrayLike, intervals_s: ArrayLike, t_s: ArrayLike) -> FloatArray:
    """Joint jerk ``(n, 3)`` (rad/s^3) of the interpolation at times ``t_s``."""
    p0, p1, v0, v1, hs, u = _pieces(keypoints_rad, intervals_s, t_s)
    jerk: FloatArray = (
        (p0 - p1) / hs**3 * (-60 + 360 * u - 360 * u**2)
        + v0 / hs**2 * (-36 + 192 * u - 180 * u**2)
        + v1 / hs**2 * (-24 + 168 * u - 180 * u**2)
    )
    return jerk


def _jerk_max(rig: Rig) -> FloatArray:
    return np.array([j.jerk_max_rad_s3 for j in rig.joints], dtype=np.float64)


@dataclass(frozen=True, slots=True)
class ExactCheck:
    """The exact model on a resample: cost, named constraint values, deepest tip, torques."""

    cost: float
    constraints: FloatArray
    max_depth_m: float
    t_s: FloatArray
    tau_nm: FloatArray


def exact_check(
    rig: Rig,
    problem: MinTorqueProblem,
    keypoints_rad: ArrayLike,
    intervals_s: ArrayLike,
    dt_s: float = RECHECK_DT_S,
) -> ExactCheck:
    """Re-evaluate a dig on the exact model: :func:`rt_runtime.dynamics.inverse_dynamics` with
    :func:`rt_runtime.soil.fluid_resistance` (unsmoothed) on a ``dt_s`` resample, limits not
    tightened. Constraint values in the order of :data:`CONSTRAINT_NAMES` (<= 0 holds)."""
    keys = np.asarray(keypoints_rad, dtype=np.float64)
    h = np.asarray(intervals_s, dtype=np.float64)
    T = float(np.sum(h))
    n = max(2, math.ceil(T / dt_s) + 1)
    t = np.linspace(0.0, T, n)
    q, qd, qdd = sample_path(keys, h, t)
    pose, twist = kinematics.tip_state(rig, q, qd)
    f = soil.fluid_resistance(
        rig, problem.soil, pose, twist, problem.surface_y_m, n_elements=problem.n_elements
    )
    tau = dynamics.inverse_dynamics(rig, q, qd, qdd, f)
    sq = np.sum((tau / rig.tau_max_nm) ** 2, axis=-1)
    cost = float(np.sum(0.5 * (sq[1:] + sq[:-1]) * np.diff(t)))
    span = rig.q_max_rad - rig.q_min_rad
    sampled = np.concatenate(
        [
            (rig.q_min_rad - q.min(axis=0)) / span,
            (q.max(axis=0) - rig.q_max_rad) / span,
            np.abs(qd).max(axis=0) / rig.qd_max_rad_s - 1.0,
            np.abs(qdd).max(axis=0) / rig.qdd_max_rad_s2 - 1.0,
            np.abs(path_jerk(keys, h, t)).max(axis=0) / _jerk_max(rig) - 1.0,
            np.abs(tau).max(axis=0) / rig.tau_max_nm - 1.0,
        ]
    )
    kp = np.asarray(
        _Model(rig, problem, _NumpyOps).keypoint_constraints(keys.tolist()), dtype=np.float64
    )
    depth = float(np.max(problem.surface_y_m - pose[:, 1]))
    return ExactCheck(cost, np.concatenate([sampled, kp]), depth, t, tau)


def _slsqp(
    ev: Evaluator,
    x0: FloatArray,
    bounds: list[tuple[float, float]],
    max_iterations: int,
    ftol: float = 1e-7,
) -> Any:
    """SLSQP with the forward-difference gradients of ``ev`` (:meth:`Evaluator.gradients`)."""
    from scipy.optimize import minimize

    # The point SLSQP asked about last: its cost and constraints (one row), and their
    # derivatives once asked for. About half the points are line-search trials whose
    # derivatives are never asked for: a row costs a quarter of the batch of n + 1.
    last: dict[str, Any] = {"key": None, "value": None, "grad": None}
    # The cost is scaled to 1 at the start, so that SLSQP's ftol is a relative tolerance.
    f_scale = 1.0 / max(float(ev.evaluate(x0[None, :]).cost[0]), 1e-12)

    def value(x: FloatArray) -> tuple[float, FloatArray]:
        key = x.tobytes()
        if last["key"] != key:
            e = ev.evaluate(x[None, :])
            last.update(key=key, value=(float(e.cost[0]), e.split[0]), grad=None)
        return last["value"]  # type: ignore[no-any-return]

    def grad(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        at_x = value(x)
        if last["grad"] is None:
            _, df, _, dc = ev.gradients(x, at_x)
            last["grad"] = (df, dc)
        return last["grad"]  # type: ignore[no-any-return]

    # SLSQP: fun(x) >= 0 holds.
    return minimize(
        lambda x: f_scale * value(x)[0],
        x0,
        jac=lambda x: f_scale * grad(x)[0],
        method="SLSQP",
        bounds=bounds,
        constraints=[
            {
                "type": "ineq",
                "fun": lambda x: -(value(x)[1] + CONSTRAINT_OFFSET),
                "jac": lambda x: -grad(x)[1],
            }
        ],
        options={"maxiter": max_iterations, "ftol": ftol},
    )


def variable_bounds(rig: Rig, problem: MinTorqueProblem) -> list[tuple[float, float]]:
    """Bounds of the optimiser's variables: joint ranges, then (variable time) the intervals."""
    b = [
        (float(lo), float(hi))
        for _ in range(N_KEY)
        for lo, hi in zip(rig.q_min_rad, rig.q_max_rad, strict=True)
    ]
    if not problem.fixed_time:
        b += [problem.interval_bounds_s] * N_INTERVALS
    return b


def initial_point(problem: MinTorqueProblem, start: FloatArray) -> FloatArray:
    """The optimiser's point for a keypoint start ``(15,)``: plus the start intervals when the
    time is variable."""
    s = np.asarray(start, dtype=np.float64)[: 3 * N_KEY]
    if problem.fixed_time:
        return s.copy()
    return np.concatenate([s, np.asarray(problem.intervals_s, dtype=np.float64)])


def solve(
    rig: Rig,
    problem: MinTorqueProblem,
    *,
    n_starts: int = 3,
    starts: Sequence[ArrayLike] | None = None,
    max_iterations: int = 150,
    rechecks: int = 2,
    backend: str = "auto",
) -> Solution:
    """Optimise one dig (module docstring) and re-check it on the exact model at 1 ms.

    Each start is solved by SLSQP; the best by Deb's rule (feasible on the smoothed model
    first, a summed violation up to :data:`FEASIBLE_VIOLATION` counting as feasible, then
    cost) is re-checked on the exact model. Where a sampled velocity, acceleration,
    jerk or torque margin is negative there, that limit is tightened by the excess (plus 0.5 %) and
    the solve repeated from the answer, at most ``rechecks`` times.

    Args:
        rig: The rig.
        problem: The dig (:func:`make_problem`).
        n_starts: Kinematic starts (:func:`kinematic_starts`) when ``starts`` is None.
        starts: Explicit starts: ``(15,)`` keypoint angles or full points.
        max_iterations: SLSQP iterations per start.
        rechecks: Tighten-and-resolve rounds after the exact re-check.
        backend: Who evaluates the smoothed model (:data:`BACKENDS`; the answers agree to
            rounding, the compiled kernel is ~5x faster on a whole solve).

    Returns:
        The :class:`Solution`; ``feasible`` False when the best answer fails the exact re-check
        (it must not be executed).

    Raises:
        ConfigurationError: Bad problem or settings.
        PlanningError: No start reachable within the joint limits.
    """
    validate_problem(problem)
    if n_starts < 1 or max_iterations < 1 or rechecks < 0:
        raise ConfigurationError("n_starts and max_iterations must be >= 1, rechecks >= 0")
    # Imported before the clock starts: a process's first import of SciPy's optimisers (which
    # the kernel's loader pulls in too) takes ~1 s once, and is not the solve's time.
    import scipy.optimize  # noqa: F401

    _kernel_module()
    t0 = time.perf_counter()
    if starts is None:
        start_list = kinematic_starts(rig, problem, n_starts)
    else:
        start_list = [np.asarray(s, dtype=np.float64) for s in starts]
    if not start_list:
        raise PlanningError(
            f"no kinematic start for {rig.name}: no dig template between entry x "
            f"{problem.entry_x_m[0]:.3g}..{problem.entry_x_m[1]:.3g} m and depths "
            f"{problem.depth_m[0]:.3g}..{problem.depth_m[1]:.3g} m is reachable"
        )
    bounds = variable_bounds(rig, problem)
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    scale = np.full((4, 3), 1.0 - LIMIT_MARGIN)
    ev = Evaluator(rig, problem, limit_scale=scale, backend=backend)
    best: tuple[tuple[float, float], FloatArray, FloatArray, Any] | None = None
    for s in start_list:
        x0 = np.clip(s if s.size == lo.size else initial_point(problem, s), lo, hi)
        res = _slsqp(ev, x0, bounds, max_iterations)
        e = ev.evaluate(res.x[None, :])
        viol = float(np.sum(np.maximum(e.split[0] + CONSTRAINT_OFFSET, 0.0)))
        key = (viol if viol > FEASIBLE_VIOLATION else 0.0, float(e.cost[0]))
        if best is None or key < best[0]:
            best = (key, res.x, x0, res)
    assert best is not None
    _, x, x0, res = best
    for _ in range(rechecks + 1):
        keys, h = _split_point(problem, x)
        chk = exact_check(rig, problem, keys, h)
        # Velocity, acceleration, jerk, torque: peak / limit - 1.
        worst = chk.constraints[6:18].reshape(4, 3)
        if np.all(chk.constraints <= 0.0) or not np.any(worst > 0.0):
            break
        scale = np.where(worst > 0.0, scale / (1.0 + worst) - 0.005, scale)
        ev = Evaluator(rig, problem, limit_scale=scale, backend=backend)
        res = _slsqp(ev, np.clip(x, lo, hi), bounds, max_iterations)
        x = res.x
    keys, h = _split_point(problem, x)
    chk = exact_check(rig, problem, keys, h)
    model_cost = float(ev.evaluate(x[None, :]).cost[0])
    margins = {n: float(-v) for n, v in zip(CONSTRAINT_NAMES, chk.constraints, strict=True)}
    pose = kinematics.forward(rig, keys)
    quad = pose[[0, 1, 2, 4], :2]
    twice = np.sum(quad[:, 0] * np.roll(quad[:, 1], -1) - np.roll(quad[:, 0], -1) * quad[:, 1])
    return Solution(
        feasible=bool(np.all(chk.constraints <= 0.0)),
        keypoints_rad=keys,
        tip_poses=pose,
        intervals_s=h,
        T_s=float(np.sum(h)),
        cost=chk.cost,
        cost_model=model_cost,
        volume_m3=float(-0.5 * twice * rig.bucket.width_m),
        max_depth_m=chk.max_depth_m,
        margins=margins,
        solve_s=time.perf_counter() - t0,
        start=x0,
        x=np.asarray(x, dtype=np.float64),
        iterations=int(res.nit),
        message=str(res.message),
        limit_scale=scale,
    )


def _split_point(problem: MinTorqueProblem, x: ArrayLike) -> tuple[FloatArray, FloatArray]:
    xa = np.asarray(x, dtype=np.float64)
    keys = xa[: 3 * N_KEY].reshape(N_KEY, 3)
    if problem.fixed_time:
        return keys, np.asarray(problem.intervals_s, dtype=np.float64)
    return keys, xa[3 * N_KEY :].copy()


# --------------------------------------------------------------------------------------------
# The CasADi/IPOPT formulation (the benchmark's reference; needs the ``reference`` extra).


@dataclass(frozen=True, slots=True)
class ReferenceSolution:
    """IPOPT's answer: its point, the smoothed cost there, success and wall time."""

    ok: bool
    status: str
    x: FloatArray
    cost_model: float
    solve_s: float


class CasadiReference:
    """The same problem as one NLP for IPOPT through CasADi (the benchmark's reference).

    The objective and the keypoint constraints are the smoothed model's, built from the same
    code on CasADi expressions; the sampled limits are one constraint per sample, joint and
    side (the exact peaks, where the optimiser holds a smooth maximum per interval that is
    at most 0.35 % of a limit more conservative), with the same tightening and offset. Exact
    derivatives by CasADi's automatic differentiation. One solver is built per problem
    structure (fixed or variable time, samples, plates, heading cones, surface band); the
    problem's numbers (surface, bands, soil, limit scales, fixed intervals) are parameters.
    Needs casadi (the ``reference`` extra).
    """

    def __init__(self, rig: Rig, tolerance: float = 1e-10, max_iterations: int = 500) -> None:
        import casadi

        self.ca = casadi
        self.rig = rig
        self.opts = {
            "ipopt.tol": tolerance,
            "ipopt.max_iter": max_iterations,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "print_time": False,
        }
        self._solvers: dict[tuple[Any, ...], Any] = {}

    @staticmethod
    def _key(p: MinTorqueProblem) -> tuple[Any, ...]:
        return (
            p.fixed_time,
            p.samples_per_interval,
            p.n_elements,
            p.entry_heading_deg,
            p.lift_heading_deg,
            p.surface_band_m,
        )

    def _build(self, p: MinTorqueProblem) -> Any:
        ca, rig = self.ca, self.rig
        par = ca.SX.sym("p", 11 + 12 + N_INTERVALS)
        sym = dataclasses.replace(
            p,
            soil=FluidSoil(p.soil.name, par[0], par[1], par[2], par[3]),
            surface_y_m=par[4],
            volume_m3=(par[5], par[6]),
            depth_m=(par[7], par[8]),
            entry_x_m=(par[9], par[10]),
        )
        scale = [[par[11 + 3 * r + j] for j in range(3)] for r in range(4)]
        m = _Model(rig, sym, _CasadiOps())
        n = 3 * N_KEY + (0 if p.fixed_time else N_INTERVALS)
        xs = ca.SX.sym("x", n)
        keys = _keys_of(xs, lambda a, i: a[i])
        if p.fixed_time:
            h: list[Any] = [par[23 + i] for i in range(N_INTERVALS)]
        else:
            h = [xs[3 * N_KEY + i] for i in range(N_INTERVALS)]
        smp = m.samples(keys, h)
        g: list[Any] = []
        for j in range(3):
            lo, hi = float(rig.q_min_rad[j]), float(rig.q_max_rad[j])
            g += [(lo - smp.q[j]) / (hi - lo), (smp.q[j] - hi) / (hi - lo)]
            v = float(rig.qd_max_rad_s[j]) * scale[0][j]
            a = float(rig.qdd_max_rad_s2[j]) * scale[1][j]
            jm = float(_jerk_max(rig)[j]) * scale[2][j]
            t = float(rig.tau_max_nm[j]) * scale[3][j]
            g += [smp.qd[j] / v - 1.0, -smp.qd[j] / v - 1.0]
            g += [smp.qdd[j] / a - 1.0, -smp.qdd[j] / a - 1.0]
            g += [smp.jerk[j] / jm - 1.0, -smp.jerk[j] / jm - 1.0]
            g += [smp.tau[j] / t - 1.0, -smp.tau[j] / t - 1.0]
        g += list(m.keypoint_constraints(keys))
        f = m.cost(smp)
        gv = ca.vertcat(*g) + CONSTRAINT_OFFSET
        nlp = {"x": xs, "p": par, "f": f, "g": gv}
        return (
            ca.nlpsol("mintorque_reference", "ipopt", nlp, self.opts),
            ca.Function("mintorque_reference_fg", [xs, par], [f, gv]),
        )

    def _prepared(
        self, problem: MinTorqueProblem, limit_scale: ArrayLike | None
    ) -> tuple[Any, Any, FloatArray]:
        """The solver and the (f, g) function of ``problem``'s structure, and its parameters."""
        validate_problem(problem)
        key = self._key(problem)
        if key not in self._solvers:
            self._solvers[key] = self._build(problem)
        solver, fg = self._solvers[key]
        fs = problem.soil
        scale = np.ones((4, 3)) if limit_scale is None else np.asarray(limit_scale, np.float64)
        par = np.concatenate(
            [
                [fs.density_kg_m3, fs.kp, fs.kv, fs.ks, problem.surface_y_m],
                problem.volume_m3,
                problem.depth_m,
                problem.entry_x_m,
                scale.reshape(-1),
                problem.intervals_s,
            ]
        )
        return solver, fg, par

    def evaluate(
        self, problem: MinTorqueProblem, x: ArrayLike, limit_scale: ArrayLike | None = None
    ) -> tuple[float, FloatArray]:
        """The NLP's objective and constraints (``<= 0`` holds, offset included) at ``x``."""
        _, fg, par = self._prepared(problem, limit_scale)
        f, g = fg(np.asarray(x, dtype=np.float64), par)
        return float(f), np.asarray(g, dtype=np.float64).reshape(-1)

    def solve(
        self, problem: MinTorqueProblem, x0: ArrayLike, limit_scale: ArrayLike | None = None
    ) -> ReferenceSolution:
        """Solve ``problem`` from the optimiser's point ``x0`` with the limits scaled by
        ``limit_scale`` ``(4, 3)`` (velocity, acceleration, jerk, torque; default 1)."""
        solver, _, par = self._prepared(problem, limit_scale)
        bounds = variable_bounds(self.rig, problem)
        t0 = time.perf_counter()
        res = solver(
            x0=np.asarray(x0, dtype=np.float64),
            p=par,
            lbx=[b[0] for b in bounds],
            ubx=[b[1] for b in bounds],
            lbg=-np.inf,
            ubg=0.0,
        )
        solve_s = time.perf_counter() - t0
        stats = solver.stats()
        return ReferenceSolution(
            bool(stats["success"]),
            str(stats["return_status"]),
            np.asarray(res["x"], dtype=np.float64).reshape(-1),
            float(res["f"]),
            solve_s,
        )
