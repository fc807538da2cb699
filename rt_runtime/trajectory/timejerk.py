"""Minimum time-jerk trajectories through waypoints (Zhao et al., section III, eq 3).

A joint-space trajectory of ``J`` joints through ``n + 1`` waypoints that minimises

    w_jerk * sum_j integral_0^T (d^3 q_j / dt^3)^2 dt  +  w_time * T

subject to ``|qd_j(t)| <= V_j`` and ``|qdd_j(t)| <= A_j`` at every instant, with position,
velocity and acceleration given at both ends (rest by default) and position, velocity and
acceleration continuous at every knot. Eq 3 prints the second derivative inside the integral;
the text (and Flash & Hogan, Zhao ref [10]) means jerk, which is what is minimised here.

Pieces. Every piece is a cubic, as in the paper (k = 3). A C2 cubic spline through ``n + 1``
points with velocity and acceleration fixed at both ends has ``4n`` unknowns for ``4n + 2``
conditions. The two missing degrees of freedom come from two free knots: one inside the first
waypoint interval and one inside the last (for two waypoints, both inside the one interval),
whose positions are unknowns of the linear solve and whose times are optimised like the others.
So the trajectory has ``m = n + 2`` cubic pieces (the CLI's segments) and ``m + 1`` knots; the
waypoints sit at knots ``0, 2, 3, ..., m - 2, m``. Jerk is constant on each piece, acceleration
linear, velocity quadratic, which makes the limit check exact and cheap (below).

Shape knots (optional, not in eq 3 as printed: ``shape_knots``). One cubic piece per waypoint
interval cannot follow a joint's time-optimal profile (full acceleration, then full speed, then
full deceleration): a rest-to-rest cubic needs ``sqrt(6 d / A)`` where the acceleration limit
allows ``sqrt(4 d / A)``, 22 % more. With ``k_i`` knots inside waypoint interval ``i`` the
trajectory has ``m = n + 2 + sum k_i`` pieces; the shape knots' positions (per joint) are
variables of the search like the durations, the rest is the same linear solve (its right-hand
side is linear in them). The search starts from the optimum without shape knots, sampled at
the shape knots' times (the same trajectory, so a feasible start that it only improves); where
the search with them does not converge, that start is the answer.

For fixed piece durations ``h`` (s) the spline is one linear solve: with the knot accelerations
``M_k`` (moments) and knot positions ``y_k`` every piece is fixed, C0 and C2 hold by
construction, and C1 at the ``m - 1`` interior knots plus the two end velocities give ``m + 1``
linear equations in the ``m - 1`` interior moments and the two free knot positions. The matrix
depends on ``h`` only, so all joints share it (one solve with ``J`` right-hand sides; the search
inverts it once per step for the sensitivities).

Optimisation. :func:`plan` minimises the objective over the ``m`` durations (and the shape
knots' positions) with scipy's SLSQP, with analytic gradients of the objective and of every
constraint (implicit differentiation of the linear solve). Every duration is at least
:data:`MIN_DURATION_S`; shape knots stay within the position bounds where the problem has
them. Constraints, all exact:

* acceleration is linear on a piece, so ``|M_k| <= A`` at the knots bounds it everywhere;
* velocity is quadratic on a piece: its extremes are at the piece's ends or at the root of the
  acceleration inside it. Each piece contributes the velocity at its vertex clipped to the piece
  (the end nearest the vertex when the vertex lies outside), a continuous function of ``h``
  whose gradient is the partial derivative at the fixed clipped point (the velocity is
  stationary there, or the point is an end);
* an optional jerk limit (not in eq 3; the trench's dig cycles set the rig's, which the limit
  guard keeps): jerk is constant on a piece, ``(M_{k+1} - M_k) / h_k``, so ``|jerk| <= J`` on
  every piece is exact;
* optional position bounds (not in eq 3; :meth:`TimeJerkProblem.for_rig` sets the joint
  ranges): position extremes are at piece ends or at roots of the velocity; each piece
  contributes the position at both roots of its velocity quadratic clipped to the piece (at the
  velocity's vertex where the roots are complex, which keeps the slots continuous). Eq 3 is
  solved first without them; only if that optimum leaves a bound is the search repeated with
  them. Durations are the only freedom, so a waypoint near a bound that the joint passes
  without turning can leave no trajectory inside the bounds: that is a ``PlanningError``.

With ``w_jerk = 0`` nothing penalises jerk, and the optimum shortens the two end pieces to
:data:`MIN_DURATION_S`: the acceleration rises from its end value within 1 ms (the limit guard's
jerk limit then shapes it). Any positive ``w_jerk`` gives end pieces of finite jerk.

After SLSQP the durations are scaled up by the smallest factor that puts every ratio within the
limits (exactly feasible up to rounding; for rest-to-rest ends a uniform time scaling divides
velocities by the factor, accelerations by its square and jerks by its cube), and the result is
checked exactly (:meth:`TimeJerkTrajectory.limit_check`). A problem with no feasible
trajectory, or one SLSQP does not solve, raises :class:`~rt_runtime.errors.PlanningError`
with the reason; nothing infeasible is ever returned.

Units: rad, rad/s, rad/s^2, rad/s^3, s. The jerk integral is in rad^2/s^5; the weights' units
are whatever makes ``w_jerk * jerk_integral + w_time * T`` consistent (``w_time`` = 1 and
``w_jerk`` in s^6/rad^2 give an objective in s). Zhao's experiment uses ``w_jerk = 0``,
``w_time = 1`` (pure minimum time), the default here. ``w_time`` must be positive: with
``w_time = 0`` the jerk integral falls without bound as the durations grow.

Errors: a malformed problem (shapes, non-finite numbers, non-positive limits, negative weights,
two equal consecutive waypoints, end states beyond the limits, waypoints outside the position
bounds) raises :class:`~rt_runtime.errors.ConfigurationError` naming the value and what is
allowed; a well-formed problem without a trajectory raises
:class:`~rt_runtime.errors.PlanningError`. :func:`plan` and :func:`interpolate` run outside the
loop (milliseconds); :meth:`TimeJerkTrajectory.sample` is vectorised over any time array and is
loop-safe at small sizes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.rig import Rig

FloatArray = NDArray[np.float64]

MIN_DURATION_S = 1e-3
"""Shortest piece (s): one period of the 1 kHz loop, the finest the executor streams."""
LIMIT_TOLERANCE = 1e-9
"""Relative tolerance of the limit check: ``|v| / V`` and ``|a| / A`` must be ``<= 1 + this``."""
DEFAULT_MAX_ITERATIONS = 400
"""SLSQP iteration cap of :func:`plan`."""
FTOL = 1e-9
"""SLSQP's tolerance on the scaled objective (the start's objective is 1)."""
_FEASIBLE_SCALINGS = 60
_MARGIN = 1e-12
"""Relative margin of the feasibility scaling and of the position constraints: above the
rounding of the spline's solve (pieces of 1 ms beside pieces of seconds), far below
:data:`LIMIT_TOLERANCE`."""


def _readonly(a: FloatArray) -> FloatArray:
    a.setflags(write=False)
    return a


def _vector(value: ArrayLike | None, n_joints: int, name: str, default: float) -> FloatArray:
    if value is None:
        return _readonly(np.full(n_joints, default))
    a = np.array(value, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(n_joints, float(a))
    if a.shape != (n_joints,):
        raise ConfigurationError(
            f"{name} must have one value per joint, shape ({n_joints},); got shape {a.shape}"
        )
    if not np.all(np.isfinite(a)):
        raise ConfigurationError(f"{name} must be finite (no NaN or inf); got {a.tolist()}")
    return _readonly(a)


@dataclass(frozen=True, slots=True, eq=False)
class TimeJerkProblem:
    """One minimum time-jerk problem (Zhao eq 3), validated on construction.

    Build it with :meth:`create` (defaults: rest at both ends, ``w_jerk = 0``, ``w_time = 1``)
    or :meth:`for_rig` (limits and position bounds from a rig profile). Equality is identity.

    Attributes:
        waypoints_rad: ``(n + 1, J)`` joint angles, rad, ``n >= 1``; no two consecutive equal.
        velocity_max_rad_s: ``(J,)`` V, > 0.
        acceleration_max_rad_s2: ``(J,)`` A, > 0.
        w_jerk: Weight of the jerk integral, >= 0.
        w_time: Weight of the duration T, > 0.
        start_velocity_rad_s, end_velocity_rad_s: ``(J,)``, within ``[-V, V]``.
        start_acceleration_rad_s2, end_acceleration_rad_s2: ``(J,)``, within ``[-A, A]``.
        position_min_rad, position_max_rad: ``(J,)`` bounds the whole trajectory must keep, or
            None for no bound (eq 3 has none); every waypoint must lie within them.
        jerk_max_rad_s3: ``(J,)`` jerk limit, > 0, or None for none (eq 3 has none).
        shape_knots: ``(n,)`` knots inside each waypoint interval whose positions the search
            chooses (all 0: eq 3's pieces; see the module); an integer gives every interval
            as many.

    Raises:
        ConfigurationError: Any of the rules above is broken; the message names the value.
    """

    waypoints_rad: FloatArray
    velocity_max_rad_s: FloatArray
    acceleration_max_rad_s2: FloatArray
    w_jerk: float
    w_time: float
    start_velocity_rad_s: FloatArray
    end_velocity_rad_s: FloatArray
    start_acceleration_rad_s2: FloatArray
    end_acceleration_rad_s2: FloatArray
    position_min_rad: FloatArray | None = None
    position_max_rad: FloatArray | None = None
    jerk_max_rad_s3: FloatArray | None = None
    shape_knots: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        put = object.__setattr__
        q = np.array(self.waypoints_rad, dtype=np.float64)
        if q.ndim != 2 or q.shape[0] < 2 or q.shape[1] < 1:
            raise ConfigurationError(
                "waypoints_rad must have shape (n_waypoints, n_joints) with at least 2 waypoints "
                f"and 1 joint; got shape {q.shape}"
            )
        if not np.all(np.isfinite(q)):
            bad = np.argwhere(~np.isfinite(q))[0]
            raise ConfigurationError(
                f"waypoint {int(bad[0])}, joint {int(bad[1])} is {q[bad[0], bad[1]]}: "
                "waypoints must be finite"
            )
        same = np.flatnonzero(np.all(q[1:] == q[:-1], axis=1))
        if same.size:
            i = int(same[0])
            raise ConfigurationError(
                f"waypoints {i} and {i + 1} are the same pose; consecutive waypoints must differ "
                "in at least one joint (remove the repeated one)"
            )
        n_joints = q.shape[1]
        put(self, "waypoints_rad", _readonly(q))
        for name in ("velocity_max_rad_s", "acceleration_max_rad_s2"):
            a = _vector(getattr(self, name), n_joints, name, math.nan)
            if not np.all(a > 0.0):
                raise ConfigurationError(f"{name} must be > 0 for every joint; got {a.tolist()}")
            put(self, name, a)
        for name in ("w_jerk", "w_time"):
            w = float(getattr(self, name))
            if not math.isfinite(w) or w < 0.0:
                raise ConfigurationError(f"{name} must be a finite number >= 0; got {w}")
            put(self, name, w)
        if self.w_time <= 0.0:
            raise ConfigurationError(
                f"w_time must be > 0; got {self.w_time} (with no weight on time the jerk "
                "integral falls without bound as the durations grow: there is no optimum)"
            )
        for name, limit in (
            ("start_velocity_rad_s", self.velocity_max_rad_s),
            ("end_velocity_rad_s", self.velocity_max_rad_s),
            ("start_acceleration_rad_s2", self.acceleration_max_rad_s2),
            ("end_acceleration_rad_s2", self.acceleration_max_rad_s2),
        ):
            a = _vector(getattr(self, name), n_joints, name, 0.0)
            if np.any(np.abs(a) > limit):
                j = int(np.argmax(np.abs(a) / limit))
                raise ConfigurationError(
                    f"{name}[{j}] = {a[j]:.6g} is beyond the joint's limit; allowed "
                    f"[{-limit[j]:.6g}, {limit[j]:.6g}]"
                )
            put(self, name, a)
        lo, hi = self.position_min_rad, self.position_max_rad
        if (lo is None) != (hi is None):
            raise ConfigurationError("position_min_rad and position_max_rad go together")
        if lo is not None and hi is not None:
            lo_a = _vector(lo, n_joints, "position_min_rad", 0.0)
            hi_a = _vector(hi, n_joints, "position_max_rad", 0.0)
            if not np.all(hi_a > lo_a):
                raise ConfigurationError("position_max_rad must exceed position_min_rad per joint")
            out = (q < lo_a) | (q > hi_a)
            if np.any(out):
                i, j = (int(v) for v in np.argwhere(out)[0])
                raise ConfigurationError(
                    f"waypoint {i}, joint {j} at {math.degrees(q[i, j]):.4f} deg is outside the "
                    f"position bounds [{math.degrees(lo_a[j]):.4f}, "
                    f"{math.degrees(hi_a[j]):.4f}] deg"
                )
            put(self, "position_min_rad", lo_a)
            put(self, "position_max_rad", hi_a)
        if self.jerk_max_rad_s3 is not None:
            jm = _vector(self.jerk_max_rad_s3, n_joints, "jerk_max_rad_s3", math.nan)
            if not np.all(jm > 0.0):
                raise ConfigurationError(
                    f"jerk_max_rad_s3 must be > 0 for every joint; got {jm.tolist()}"
                )
            put(self, "jerk_max_rad_s3", jm)
        n = q.shape[0] - 1
        k_raw: Any = self.shape_knots
        if isinstance(k_raw, int | np.integer):
            ks = [k_raw] * n
        elif isinstance(k_raw, tuple | list):
            ks = list(k_raw) or [0] * n
        else:
            ks = [k_raw]
        if len(ks) != n or not all(
            isinstance(k, int | np.integer) and not isinstance(k, bool) and 0 <= k <= 16 for k in ks
        ):
            raise ConfigurationError(
                f"shape_knots must be an integer in 0..16 or one per waypoint interval ({n}); "
                f"got {k_raw!r}"
            )
        put(self, "shape_knots", tuple(int(k) for k in ks))

    @classmethod
    def create(
        cls,
        waypoints_rad: ArrayLike,
        velocity_max_rad_s: ArrayLike,
        acceleration_max_rad_s2: ArrayLike,
        *,
        w_jerk: float = 0.0,
        w_time: float = 1.0,
        start_velocity_rad_s: ArrayLike | None = None,
        end_velocity_rad_s: ArrayLike | None = None,
        start_acceleration_rad_s2: ArrayLike | None = None,
        end_acceleration_rad_s2: ArrayLike | None = None,
        position_min_rad: ArrayLike | None = None,
        position_max_rad: ArrayLike | None = None,
        jerk_max_rad_s3: ArrayLike | None = None,
        shape_knots: int | tuple[int, ...] = 0,
    ) -> TimeJerkProblem:
        """A validated problem; end states default to rest. Args as the attributes."""
        return cls(
            waypoints_rad=waypoints_rad,  # type: ignore[arg-type]
            velocity_max_rad_s=velocity_max_rad_s,  # type: ignore[arg-type]
            acceleration_max_rad_s2=acceleration_max_rad_s2,  # type: ignore[arg-type]
            w_jerk=w_jerk,
            w_time=w_time,
            start_velocity_rad_s=start_velocity_rad_s,  # type: ignore[arg-type]
            end_velocity_rad_s=end_velocity_rad_s,  # type: ignore[arg-type]
            start_acceleration_rad_s2=start_acceleration_rad_s2,  # type: ignore[arg-type]
            end_acceleration_rad_s2=end_acceleration_rad_s2,  # type: ignore[arg-type]
            position_min_rad=position_min_rad,  # type: ignore[arg-type]
            position_max_rad=position_max_rad,  # type: ignore[arg-type]
            jerk_max_rad_s3=jerk_max_rad_s3,  # type: ignore[arg-type]
            shape_knots=shape_knots,  # type: ignore[arg-type]
        )

    @classmethod
    def for_rig(
        cls,
        rig: Rig,
        waypoints_rad: ArrayLike,
        *,
        position_bounds: bool = True,
        jerk_limits: bool = False,
        limit_fraction: float = 1.0,
        **kwargs: Any,
    ) -> TimeJerkProblem:
        """A problem over a rig's joints (swing first where the rig has one, then boom, stick,
        bucket: :attr:`Rig.joint_names`), with the rig's velocity and acceleration limits and,
        with ``position_bounds``, its joint ranges as position bounds, with ``jerk_limits`` its
        jerk limits (what the limit guard keeps).

        Args:
            rig: The rig profile.
            waypoints_rad: ``(n + 1, rig.dof)`` joint angles, rad.
            position_bounds: Keep the whole trajectory inside the joint ranges.
            jerk_limits: Keep every joint's jerk within its limit.
            limit_fraction: Share of the velocity and acceleration limits planned to, in
                (0, 1] (the rest is the tracking loop's headroom).
            **kwargs: Weights and end states, as :meth:`create`.

        Raises:
            ConfigurationError: The waypoints do not have ``rig.dof`` joints, a limit fraction
                outside (0, 1], or as :class:`TimeJerkProblem`.
        """
        if not 0.0 < limit_fraction <= 1.0:
            raise ConfigurationError(f"limit_fraction {limit_fraction!r}: allowed (0, 1]")
        joints = ((rig.swing.joint,) if rig.swing is not None else ()) + rig.joints
        q = np.asarray(waypoints_rad, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != len(joints):
            raise ConfigurationError(
                f"rig {rig.name} has {len(joints)} joints ({', '.join(j.name for j in joints)}); "
                f"waypoints must have shape (n_waypoints, {len(joints)}); got shape {q.shape}"
            )
        bounds: dict[str, Any] = {}
        if position_bounds:
            bounds = {
                "position_min_rad": [j.min_rad for j in joints],
                "position_max_rad": [j.max_rad for j in joints],
            }
        if jerk_limits:
            bounds["jerk_max_rad_s3"] = [j.jerk_max_rad_s3 for j in joints]
        return cls.create(
            q,
            [limit_fraction * j.velocity_max_rad_s for j in joints],
            [limit_fraction * j.acceleration_max_rad_s2 for j in joints],
            **bounds,
            **kwargs,
        )

    @property
    def n_joints(self) -> int:
        """Number of joints J."""
        return int(self.waypoints_rad.shape[1])

    @property
    def n_pieces(self) -> int:
        """Number of cubic pieces ``m = n + 2 + sum k_i`` (n waypoint intervals, two free
        knots, the shape knots)."""
        n = int(self.waypoints_rad.shape[0]) - 1
        return n + 2 + sum(self.shape_knots)

    @property
    def knot_kinds(self) -> str:
        """One letter a knot: ``W`` waypoint, ``F`` free knot (solved), ``S`` shape knot
        (searched): ``W F S..S W S..S W ... W S..S F W``."""
        return self.knot_kinds_of(self.shape_knots)

    @staticmethod
    def knot_kinds_of(shape_knots: tuple[int, ...]) -> str:
        """:attr:`knot_kinds` of a problem with ``shape_knots`` ``(n,)``."""
        n = len(shape_knots)
        out = "WF"
        for i, k in enumerate(shape_knots):
            out += "S" * k + ("F" if i == n - 1 else "") + "W"
        return out

    @property
    def waypoint_knots(self) -> tuple[int, ...]:
        """Knot index of each waypoint (``0, 2, 3, ..., m - 2, m`` without shape knots)."""
        return tuple(i for i, c in enumerate(self.knot_kinds) if c == "W")

    @property
    def shape_knot_indices(self) -> tuple[int, ...]:
        """Knot index of each shape knot, in order."""
        return tuple(i for i, c in enumerate(self.knot_kinds) if c == "S")

    def without_shape_knots(self) -> TimeJerkProblem:
        """The same problem with eq 3's pieces only (no shape knots)."""
        return dataclasses.replace(self, shape_knots=0)  # type: ignore[arg-type]


@dataclass(frozen=True, slots=True, eq=False)
class LimitCheck:
    """Peak velocity and acceleration of a trajectory against its limits.

    Attributes:
        velocity_peak_rad_s: ``(J,)`` max |velocity| per joint.
        acceleration_peak_rad_s2: ``(J,)`` max |acceleration| per joint.
        velocity_ratio: ``(J,)`` peak over V.
        acceleration_ratio: ``(J,)`` peak over A.
        position_low_rad, position_high_rad: ``(J,)`` lowest and highest angle reached.
        jerk_peak_rad_s3: ``(J,)`` max |jerk| per joint.
        jerk_ratio: ``(J,)`` peak over the jerk limit (NaN where the problem has none).
        exact: True when the peaks are the exact extremes of the polynomials, False when they are
            maxima over samples.
        within_limits: Every ratio ``<= 1 + LIMIT_TOLERANCE`` and, where the problem has
            position bounds, every angle within them (``LIMIT_TOLERANCE`` of the range) and,
            where it has a jerk limit, every jerk ratio ``<= 1 + LIMIT_TOLERANCE``.
    """

    velocity_peak_rad_s: FloatArray
    acceleration_peak_rad_s2: FloatArray
    velocity_ratio: FloatArray
    acceleration_ratio: FloatArray
    position_low_rad: FloatArray
    position_high_rad: FloatArray
    jerk_peak_rad_s3: FloatArray
    jerk_ratio: FloatArray
    exact: bool
    within_limits: bool


@dataclass(frozen=True, slots=True, eq=False)
class TimeJerkTrajectory:
    """A minimum time-jerk trajectory: ``m`` cubic pieces per joint. Made by :func:`plan` or
    :func:`interpolate`; equality is identity; every array is read-only.

    Attributes:
        problem: The problem it solves.
        piece_durations_s: ``(m,)`` piece durations, s.
        coefficients: ``(m, J, 4)``: piece ``i`` of joint ``j`` is
            ``c[0] tau^3 + c[1] tau^2 + c[2] tau + c[3]`` in local time ``tau = t - knots_s[i]``
            (s), rad; highest power first.
        jerk_integral: ``sum_j integral (d^3 q_j/dt^3)^2 dt`` in rad^2/s^5.
        objective: ``w_jerk * jerk_integral + w_time * duration_s``.
        iterations: SLSQP iterations (0 for :func:`interpolate`).
        shape_positions_rad: ``(f, J)`` the shape knots' positions (``f = n k``; empty without
            shape knots); with the durations they rebuild the trajectory (:func:`interpolate`).
        knots_s: ``(m + 1,)`` knot times from 0, s.
    """

    problem: TimeJerkProblem
    piece_durations_s: FloatArray
    coefficients: FloatArray
    jerk_integral: float
    objective: float
    iterations: int = 0
    shape_positions_rad: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    knots_s: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        put = object.__setattr__
        shape_a = np.array(self.shape_positions_rad, dtype=np.float64)
        shape_a = shape_a.reshape(-1, self.problem.n_joints)
        put(self, "shape_positions_rad", _readonly(shape_a))
        durations = np.array(self.piece_durations_s, dtype=np.float64)
        put(self, "piece_durations_s", _readonly(durations))
        put(self, "coefficients", _readonly(np.array(self.coefficients, dtype=np.float64)))
        knots = np.concatenate(([0.0], np.cumsum(self.piece_durations_s)))
        put(self, "knots_s", _readonly(knots))

    @property
    def duration_s(self) -> float:
        """Total duration, s."""
        return float(self.knots_s[-1])

    @property
    def n_pieces(self) -> int:
        """Number of cubic pieces m."""
        return int(self.piece_durations_s.shape[0])

    @property
    def waypoint_times_s(self) -> FloatArray:
        """``(n + 1,)`` times at which the trajectory passes the waypoints, s."""
        return _readonly(self.knots_s[list(self.problem.waypoint_knots)].copy())

    def sample(self, t_s: ArrayLike, derivative: int = 0) -> FloatArray:
        """Position (0), velocity (1), acceleration (2) or jerk (3) at times ``t_s``.

        Args:
            t_s: Times, any shape, s; times outside ``[0, duration_s]`` read the state at the
                nearer end (jerk: the end piece's).
            derivative: 0..3.

        Returns:
            ``(*t_s.shape, J)`` in rad/s**derivative.

        Raises:
            ValueError: ``derivative`` not in 0..3 or a non-finite time.
        """
        return self._at(np.asarray(t_s, dtype=np.float64), derivative)

    def states(self, t_s: ArrayLike) -> FloatArray:
        """Position, velocity, acceleration and jerk at times ``t_s``: ``(*t_s.shape, 4, J)``."""
        t = np.asarray(t_s, dtype=np.float64)
        return np.stack([self._at(t, d) for d in range(4)], axis=-2)

    def _at(self, t: FloatArray, derivative: int) -> FloatArray:
        if derivative not in (0, 1, 2, 3):
            raise ValueError(f"derivative must be 0, 1, 2 or 3; got {derivative!r}")
        if not np.all(np.isfinite(t)):
            raise ValueError("t_s must be finite")
        knots = self.knots_s
        seg = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, self.n_pieces - 1)
        tau = (np.clip(t, 0.0, knots[-1]) - knots[seg])[..., None]
        c = self.coefficients[seg]  # (*t, J, 4), highest power first
        if derivative == 0:
            return np.asarray(((c[..., 0] * tau + c[..., 1]) * tau + c[..., 2]) * tau + c[..., 3])
        if derivative == 1:
            return np.asarray((3.0 * c[..., 0] * tau + 2.0 * c[..., 1]) * tau + c[..., 2])
        if derivative == 2:
            return np.asarray(6.0 * c[..., 0] * tau + 2.0 * c[..., 1])
        return np.asarray(6.0 * c[..., 0] + 0.0 * tau)

    def limit_check(self) -> LimitCheck:
        """Exact peaks per piece: acceleration at the knots (it is linear), velocity at the
        piece ends and at the root of the acceleration inside the piece, position at the piece
        ends and the roots of the velocity inside it, jerk (constant on a piece)."""
        c = self.coefficients
        h = self.piece_durations_s[:, None]
        c3, c2, c1, c0 = c[..., 0], c[..., 1], c[..., 2], c[..., 3]
        acc = np.concatenate([2.0 * c2, 6.0 * c3 * h + 2.0 * c2])
        vel_end = 3.0 * c3 * h**2 + 2.0 * c2 * h + c1
        with np.errstate(divide="ignore", invalid="ignore"):
            t_vertex = np.where(c3 != 0.0, -c2 / (3.0 * c3), 0.0)
        inside = (t_vertex > 0.0) & (t_vertex < h)
        t_v = np.where(inside, t_vertex, 0.0)
        vel_vertex = np.where(inside, (3.0 * c3 * t_v + 2.0 * c2) * t_v + c1, 0.0)
        vel = np.concatenate([c1, vel_end, vel_vertex])
        pos_end = ((c3 * h + c2) * h + c1) * h + c0
        roots = _quadratic_roots(3.0 * c3, 2.0 * c2, c1)  # (2, m, J), NaN where none
        with np.errstate(invalid="ignore"):
            in_piece = np.isfinite(roots) & (roots > 0.0) & (roots < h)
        t_r = np.where(in_piece, roots, 0.0)
        pos_root = np.where(in_piece, ((c3 * t_r + c2) * t_r + c1) * t_r + c0, c0)
        pos = np.concatenate([c0, pos_end, pos_root[0], pos_root[1]])
        return self._check(vel, acc, pos, 6.0 * c3, exact=True)

    def sampled_limit_check(self, rate_hz: float = 1000.0) -> LimitCheck:
        """The peaks over samples at ``rate_hz`` (from 0, plus the end time)."""
        if not rate_hz > 0.0:
            raise ValueError(f"rate_hz must be > 0; got {rate_hz}")
        t = np.append(np.arange(0.0, self.duration_s, 1.0 / rate_hz), self.duration_s)
        return self._check(
            self.sample(t, 1), self.sample(t, 2), self.sample(t, 0), self.sample(t, 3), exact=False
        )

    def _check(
        self, vel: FloatArray, acc: FloatArray, pos: FloatArray, jerk: FloatArray, *, exact: bool
    ) -> LimitCheck:
        p = self.problem
        v_peak = np.max(np.abs(vel), axis=0)
        a_peak = np.max(np.abs(acc), axis=0)
        j_peak = np.max(np.abs(jerk), axis=0)
        v_ratio = v_peak / p.velocity_max_rad_s
        a_ratio = a_peak / p.acceleration_max_rad_s2
        j_ratio = j_peak / p.jerk_max_rad_s3 if p.jerk_max_rad_s3 is not None else j_peak * np.nan
        low, high = np.min(pos, axis=0), np.max(pos, axis=0)
        ok = bool(
            np.all(v_ratio <= 1.0 + LIMIT_TOLERANCE) and np.all(a_ratio <= 1.0 + LIMIT_TOLERANCE)
        )
        if p.jerk_max_rad_s3 is not None:
            ok = ok and bool(np.all(j_ratio <= 1.0 + LIMIT_TOLERANCE))
        if p.position_min_rad is not None and p.position_max_rad is not None:
            slack = LIMIT_TOLERANCE * (p.position_max_rad - p.position_min_rad)
            ok = ok and bool(
                np.all(low >= p.position_min_rad - slack)
                and np.all(high <= p.position_max_rad + slack)
            )
        return LimitCheck(
            _readonly(v_peak),
            _readonly(a_peak),
            _readonly(v_ratio),
            _readonly(a_ratio),
            _readonly(low),
            _readonly(high),
            _readonly(j_peak),
            _readonly(j_ratio),
            exact,
            ok,
        )


def _quadratic_roots(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
    """Real roots of ``a x^2 + b x + c``, ``(2, *shape)``, the smaller first, NaN where there is
    none (the stable form: no cancellation between ``b`` and the discriminant's root)."""
    disc = b * b - 4.0 * a * c
    real = disc >= 0.0
    sq = np.sqrt(np.where(real, disc, 0.0))
    q = -0.5 * (b + np.where(b >= 0.0, sq, -sq))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(a != 0.0, q / a, np.where(b != 0.0, -c / b, np.nan))
        r2 = np.where(q != 0.0, c / q, np.nan)
    r2 = np.where(a != 0.0, r2, np.nan)
    return np.sort(np.stack([np.where(real, r1, np.nan), np.where(real, r2, np.nan)]), axis=0)


class _Layout:
    """Constants of one problem the spline solve reuses: sizes, index arrays, end states."""

    __slots__ = (
        "a0",
        "an",
        "ar",
        "flat",
        "free",
        "inv_a",
        "inv_j",
        "inv_v",
        "m",
        "n_j",
        "n_par",
        "p",
        "shape",
        "v0",
        "vn",
        "way",
        "y_base",
    )

    def __init__(self, p: TimeJerkProblem) -> None:
        self.p = p
        self.m = m = p.n_pieces
        self.n_j = p.n_joints
        self.way = np.array(p.waypoint_knots)
        self.free = np.array([1, m - 1])
        self.shape = np.array(p.shape_knot_indices, dtype=np.int64)
        #: The search's variables: m durations, then the shape knots' positions (joint last).
        self.n_par = m + self.shape.shape[0] * self.n_j
        self.ar = np.arange(m)
        # Flat indices of the matrix entries :class:`_Spline` fills, in the order of its values:
        # column k - 1 holds M_k's coefficients in rows k - 1, k, k + 1; the last two columns
        # the free knots' positions in the rows of the equations they enter.
        k = np.arange(1, m)
        rows = np.concatenate([k - 1, k, k + 1, [0, 1, 2], [m - 2, m - 1, m]])
        cols = np.concatenate([k - 1, k - 1, k - 1, [m - 1] * 3, [m] * 3])
        self.flat = rows * (m + 1) + cols
        y = np.zeros((m + 1, self.n_j))
        y[self.way] = p.waypoints_rad
        self.y_base = y
        self.a0, self.an = p.start_acceleration_rad_s2, p.end_acceleration_rad_s2
        self.v0, self.vn = p.start_velocity_rad_s, p.end_velocity_rad_s
        self.inv_v = 1.0 / p.velocity_max_rad_s
        self.inv_a = 1.0 / p.acceleration_max_rad_s2
        self.inv_j = None if p.jerk_max_rad_s3 is None else 1.0 / p.jerk_max_rad_s3


class _Spline:
    """The spline of one problem for given durations ``h`` (s), with the derivatives the
    optimiser needs.

    Unknowns per joint: the interior knot accelerations ``M_1..M_{m-1}`` and the free knot
    positions ``y_1``, ``y_{m-1}``. Equation ``k`` (``k = 0..m``) is
    ``E_k = 6 (velocity just left of knot k - velocity just right of it) = 0``, the given end
    velocities standing left of knot 0 and right of knot m:
    ``E_k = h_{k-1} M_{k-1} + 2 (h_{k-1} + h_k) M_k + h_k M_{k+1} + s_{k-1} - s_k`` with
    ``s_i = 6 (y_{i+1} - y_i) / h_i`` (terms of pieces outside ``0..m-1`` absent), plus
    ``6 v_0`` in ``E_0`` and ``-6 v_n`` in ``E_m``.

    Shape knots' positions ``shape`` ``(f, J)`` are known positions like the waypoints.

    Knot arrays are ``(m + 1, J)`` (positions ``y``, accelerations ``M``), piece arrays
    ``(m, J)``. Gradients carry the search's variables first (:attr:`_Layout.n_par`: the
    durations, then the shape knots' positions, joint last):
    ``d_X[l, i, j] = dX[i, j] / dx_l``.
    """

    __slots__ = ("M", "d_M", "d_v", "d_y", "dm", "dy", "h", "v", "y")

    def __init__(self, lay: _Layout, h: FloatArray, shape: FloatArray, *, gradient: bool) -> None:
        m = lay.m
        g = 6.0 / h
        mat = np.zeros((m + 1, m + 1))
        mat.reshape(-1)[lay.flat] = np.concatenate(
            [
                h[:-1],
                2.0 * (h[:-1] + h[1:]),
                h[1:],
                (-g[0], g[0] + g[1], -g[1], -g[m - 2], g[m - 2] + g[m - 1], -g[m - 1]),
            ]
        )
        y_known = lay.y_base.copy()
        y_known[lay.shape] = shape
        s_known = (y_known[1:] - y_known[:-1]) * g[:, None]
        rhs = np.zeros((m + 1, lay.n_j))
        rhs[:-1] = s_known
        rhs[1:] -= s_known
        rhs[0] -= 2.0 * h[0] * lay.a0 + 6.0 * lay.v0
        rhs[1] -= h[0] * lay.a0
        rhs[m - 1] -= h[m - 1] * lay.an
        rhs[m] -= 2.0 * h[m - 1] * lay.an - 6.0 * lay.vn
        # The search needs the inverse for the sensitivities; the final spline a plain solve.
        inv = np.asarray(np.linalg.inv(mat) if gradient else np.empty((0, 0)), dtype=np.float64)
        z = np.asarray(inv @ rhs if gradient else np.linalg.solve(mat, rhs), dtype=np.float64)
        M = np.empty((m + 1, lay.n_j))
        M[0], M[m], M[1:m] = lay.a0, lay.an, z[: m - 1]
        y = y_known
        y[lay.free] = z[m - 1 :]
        dy = y[1:] - y[:-1]
        dm = M[1:] - M[:-1]
        hc = h[:, None]
        v = dy / hc - hc * (2.0 * M[:-1] + M[1:]) / 6.0
        self.h, self.y, self.M, self.dy, self.dm, self.v = h, y, M, dy, dm, v
        if not gradient:
            return
        # dE/dh_l at fixed unknowns touches rows l and l + 1 only.
        d6 = 6.0 * dy / hc**2
        top = 2.0 * M[:-1] + M[1:] + d6
        bottom = M[:-1] + 2.0 * M[1:] - d6
        inv_t = inv.T
        dz = -(inv_t[:-1, :, None] * top[:, None, :] + inv_t[1:, :, None] * bottom[:, None, :])
        d_M = np.zeros((lay.n_par, m + 1, lay.n_j))
        d_M[:m, 1:m] = dz[:, : m - 1]
        d_y = np.zeros((lay.n_par, m + 1, lay.n_j))
        d_y[:m, lay.free] = dz[:, m - 1 :]
        if lay.shape.size:
            # A shape knot's position y_k enters s_{k-1} and s_k, so rows k - 1, k, k + 1 of
            # the right-hand side, the same for every joint (each joint its own variable).
            k = lay.shape
            e = np.zeros((m + 1, k.shape[0]))
            cols = np.arange(k.shape[0])
            e[k - 1, cols] = g[k - 1]
            e[k, cols] = -(g[k - 1] + g[k])
            e[k + 1, cols] = g[k]
            dz_s = inv @ e  # (m + 1, f)
            n_j = lay.n_j
            for j in range(n_j):
                rows = m + cols * n_j + j
                d_M[rows, 1:m, j] = dz_s[: m - 1].T
                d_y[rows[:, None], lay.free[None, :], j] = dz_s[m - 1 :].T
                d_y[rows, k, j] = 1.0
        h3 = h[None, :, None]
        d_v = (d_y[:, 1:] - d_y[:, :-1]) / h3 - h3 * (2.0 * d_M[:, :-1] + d_M[:, 1:]) / 6.0
        d_v[lay.ar, lay.ar] -= dy / hc**2 + (2.0 * M[:-1] + M[1:]) / 6.0
        self.d_M, self.d_y, self.d_v = d_M, d_y, d_v

    def coefficients(self) -> FloatArray:
        """``(m, J, 4)`` local-time coefficients, highest power first."""
        hc = self.h[:, None]
        return np.stack([self.dm / (6.0 * hc), self.M[:-1] / 2.0, self.v, self.y[:-1]], axis=-1)

    def jerk_integral(self) -> float:
        """``sum over pieces and joints of (M_{i+1} - M_i)^2 / h_i``, rad^2/s^5."""
        return float(np.sum(self.dm**2 / self.h[:, None]))

    def d_jerk_integral(self) -> FloatArray:
        """``(n_par,)`` gradient of :meth:`jerk_integral`."""
        d_dm = self.d_M[:, 1:] - self.d_M[:, :-1]
        out = np.einsum("ij,lij->l", 2.0 * self.dm / self.h[:, None], d_dm)
        m = self.h.shape[0]
        out[:m] -= np.sum(self.dm**2, axis=1) / self.h**2
        return np.asarray(out)

    def vertex_u(self) -> FloatArray:
        """``(m, J)`` normalised time of each piece's acceleration root, clipped to [0, 1]
        (0 where the acceleration is constant)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.dm != 0.0, np.clip(-self.M[:-1] / self.dm, 0.0, 1.0), 0.0)

    def velocity_slots(self) -> FloatArray:
        """``(m, J)`` velocity at :meth:`vertex_u`: each piece's velocity extreme inside it, or
        the end nearest the vertex."""
        u = self.vertex_u()
        return np.asarray(self.v + self.h[:, None] * (self.M[:-1] * u + self.dm * u * u / 2.0))

    def d_velocity_slots(self) -> FloatArray:
        """``(n_par, m, J)`` gradient of :meth:`velocity_slots`: the partial derivative at the fixed
        point (the velocity is stationary at an inside vertex; an end does not move in ``u``)."""
        u = self.vertex_u()
        hc = self.h[:, None]
        h3, u3 = hc[None], u[None]
        d_e = self.d_v + h3 * (
            self.d_M[:, :-1] * (u3 - u3 * u3 / 2.0) + self.d_M[:, 1:] * u3 * u3 / 2.0
        )
        ar = np.arange(self.h.shape[0])
        d_e[ar, ar] += self.M[:-1] * u + self.dm * u * u / 2.0
        return d_e

    def position_slots(self) -> tuple[FloatArray, FloatArray]:
        """Position at both roots of each piece's velocity clipped to the piece, ``(2, m, J)``,
        and the gradient ``(n_par, 2, m, J)``.

        Where the roots are complex (the piece is monotonic) both slots take the velocity's
        vertex clipped to the piece: the two roots merge there, so the slots stay continuous. At
        a root or an end the position is stationary in ``u`` or ``u`` is fixed, so the gradient
        is the partial derivative at fixed ``u``; at an inside vertex the term of ``du/dh`` is
        added.
        """
        hc = self.h[:, None]
        M0, dm, v = self.M[:-1], self.dm, self.v
        roots = _quadratic_roots(hc * dm / 2.0, hc * M0, v)
        with np.errstate(divide="ignore", invalid="ignore"):
            vertex = np.where(dm != 0.0, -M0 / dm, 0.0)
        complex_roots = ~np.isfinite(roots)
        u = np.clip(np.where(complex_roots, vertex, roots), 0.0, 1.0)
        h2 = hc * hc
        q = self.y[:-1] + hc * v * u + h2 * M0 * u**2 / 2.0 + h2 * dm * u**3 / 6.0
        hh, hh2, uu = hc[None, None], h2[None, None], u[None]
        d_q = (
            self.d_y[:, None, :-1]
            + hh * uu * self.d_v[:, None]
            + hh2 * (uu**2 / 2.0 - uu**3 / 6.0) * self.d_M[:, None, :-1]
            + hh2 * uu**3 / 6.0 * self.d_M[:, None, 1:]
        )
        ar = np.arange(self.h.shape[0])
        d_q[ar, :, ar] += np.moveaxis(v * u + hc * M0 * u**2 + hc * dm * u**3 / 3.0, 0, 1)
        moving = complex_roots & (vertex > 0.0)[None] & (vertex < 1.0)[None]
        if np.any(moving):
            # u = -M0 / dm: du = (M0 d(dm) - dm dM0) / dm^2; dq/du = h v(u).
            with np.errstate(divide="ignore", invalid="ignore"):
                d_u = (M0 * np.diff(self.d_M, axis=1) - dm * self.d_M[:, :-1]) / dm**2
            slope = hc * (v + hc * M0 * u + hc * dm * u**2 / 2.0)
            d_q += np.where(moving[None], slope[None] * d_u[:, None], 0.0)
        return q, d_q


class _Evaluator:
    """Objective and constraints of one problem as functions of the search's variables
    ``x = (h / s, shape positions)``, cached on the last ``x`` (SLSQP asks for the objective
    and the constraints at one point).

    Constraints (``>= 0``, normalised by the limits): ``1 -+ v/V`` at the interior knots,
    ``1 -+ M/A`` at the interior knots, ``1 -+ e/V`` at every piece's velocity slot, where the
    problem has a jerk limit ``1 -+ (dM / h) / J`` on every piece and, with ``positions``,
    ``1 -+ (q - mid) / half`` at every position slot and free knot.
    """

    def __init__(
        self, lay: _Layout, scale_s: float, objective_scale: float, *, positions: bool
    ) -> None:
        self.lay = lay
        self.scale = scale_s
        self.f_scale = objective_scale
        p = lay.p
        self.positions = positions and p.position_min_rad is not None
        if self.positions:
            assert p.position_min_rad is not None and p.position_max_rad is not None
            self.mid = 0.5 * (p.position_max_rad + p.position_min_rad)
            self.inv_half = 2.0 / (p.position_max_rad - p.position_min_rad) / (1.0 - _MARGIN)
        self._x: FloatArray | None = None
        self._out: tuple[float, FloatArray, FloatArray, FloatArray] = (0.0, *(np.empty(0),) * 3)

    def _eval(self, x: FloatArray) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        if self._x is not None and (x == self._x).all():
            return self._out
        lay, p = self.lay, self.lay.p
        m = lay.m
        h = np.maximum(x[:m] * self.scale, MIN_DURATION_S * 1e-3)
        s = _Spline(lay, h, x[m:].reshape(-1, lay.n_j), gradient=True)
        f = p.w_time * float(np.sum(h))
        df = np.zeros(lay.n_par)
        df[:m] = p.w_time
        if p.w_jerk > 0.0:
            f += p.w_jerk * s.jerk_integral()
            df += p.w_jerk * s.d_jerk_integral()
        vals = [s.v[1:] * lay.inv_v, s.M[1:-1] * lay.inv_a, s.velocity_slots() * lay.inv_v]
        grads = [
            s.d_v[:, 1:] * lay.inv_v,
            s.d_M[:, 1:-1] * lay.inv_a,
            s.d_velocity_slots() * lay.inv_v,
        ]
        if lay.inv_j is not None:
            hc = h[:, None]
            vals += [s.dm / hc * lay.inv_j]
            d_jerk = (s.d_M[:, 1:] - s.d_M[:, :-1]) / hc[None]
            d_jerk[lay.ar, lay.ar] -= s.dm / hc**2
            grads += [d_jerk * lay.inv_j]
        if self.positions:
            q, d_q = s.position_slots()
            vals += [(q.reshape(-1, lay.n_j) - self.mid) * self.inv_half]
            vals += [(s.y[lay.free] - self.mid) * self.inv_half]
            grads += [d_q.reshape(lay.n_par, -1, lay.n_j) * self.inv_half]
            grads += [s.d_y[:, lay.free] * self.inv_half]
        c = np.concatenate(vals).reshape(-1)
        # d/dx: the durations are scaled by s, the positions are not.
        dx = np.ones(lay.n_par)
        dx[:m] = self.scale
        dc = np.concatenate(grads, axis=1).reshape(lay.n_par, -1).T * dx
        self._x = x.copy()
        self._out = (
            f / self.f_scale,
            df * dx / self.f_scale,
            np.concatenate([1.0 - c, 1.0 + c]),
            np.concatenate([-dc, dc]),
        )
        return self._out

    def fun(self, x: FloatArray) -> tuple[float, FloatArray]:
        f, df, _, _ = self._eval(x)
        return f, df

    def cons(self, x: FloatArray) -> FloatArray:
        return self._eval(x)[2]

    def cons_jac(self, x: FloatArray) -> FloatArray:
        return self._eval(x)[3]


def _ratio(lay: _Layout, s: _Spline) -> float:
    """Time-scaling factor that would put the spline's exact peaks on the limits: the largest
    velocity ratio, square root of an acceleration ratio or cube root of a jerk ratio."""
    v_peak = np.max(np.abs(np.concatenate([s.v, s.velocity_slots(), lay.vn[None]])), axis=0)
    a_peak = np.max(np.abs(s.M), axis=0)
    r = max(float(np.max(v_peak * lay.inv_v)), math.sqrt(float(np.max(a_peak * lay.inv_a))))
    if lay.inv_j is not None:
        j_peak = np.max(np.abs(s.dm) / s.h[:, None], axis=0)
        r = max(r, float(np.max(j_peak * lay.inv_j)) ** (1.0 / 3.0))
    return r


def start_durations(problem: TimeJerkProblem) -> FloatArray:
    """The search's start: ``(m,)`` piece durations, s, within the velocity and acceleration
    limits wherever a time scaling reaches them (always for rest-to-rest ends).

    Per waypoint interval the slowest joint's time at its limits, ``max(d / V, 2 sqrt(d / A))``
    (at least 5 % of the longest interval's), the end intervals split 1:4 at their free knots
    (the short piece at the path's end: optima have short end pieces, ~2 iterations fewer than
    an even split); then scaled up until the exact peaks are within the limits.
    """
    p = problem
    d = np.abs(np.diff(p.waypoints_rad, axis=0))
    g = np.max(
        np.maximum(d / p.velocity_max_rad_s, 2.0 * np.sqrt(d / p.acceleration_max_rad_s2)), axis=1
    )
    g = np.maximum(g, 0.05 * float(np.max(g)))
    if g.shape[0] == 1:
        h = np.full(3, g[0] / 3.0)
    else:
        h = np.concatenate(
            [[g[0] * 0.05, g[0] * (1 - 0.05)], g[1:-1], [g[-1] * (1 - 0.05), g[-1] * 0.05]]
        )
    base = p.without_shape_knots()
    h = _scaled_feasible(_Layout(base), h, np.zeros((0, p.n_joints)))[0]
    if not any(p.shape_knots):
        return h
    return _with_shape_knots(p, _trajectory(base, h, np.zeros((0, p.n_joints)), 0))[0]


def _with_shape_knots(
    p: TimeJerkProblem, base: TimeJerkTrajectory
) -> tuple[FloatArray, FloatArray]:
    """``base`` (a trajectory of ``p`` without shape knots) in ``p``'s knots: each waypoint
    interval's pieces share its time evenly (the free knots' pieces kept), the shape knots at
    ``base``'s positions then. The same trajectory: ``base`` meets every condition of the
    finer spline, which is unique. Returns the durations ``(m,)`` and shape positions."""
    hb = base.piece_durations_s
    t_wp = base.waypoint_times_s
    n = len(p.shape_knots)
    h: list[float] = []
    times: list[float] = []
    for i, k in enumerate(p.shape_knots):
        a, b = float(t_wp[i]), float(t_wp[i + 1])
        lo = a + (float(hb[0]) if i == 0 else 0.0)  # the first free knot's piece kept
        hi = b - (float(hb[-1]) if i == n - 1 else 0.0)
        cuts = np.linspace(lo, hi, k + 2)
        times.extend(cuts[1:-1].tolist())
        if i == 0:
            h.append(lo - a)
        h.extend(np.diff(cuts).tolist())
        if i == n - 1:
            h.append(b - hi)
    shape = base.sample(np.asarray(times)).reshape(-1, p.n_joints)
    return np.asarray(h), shape


def _scaled_feasible(lay: _Layout, h: FloatArray, shape: FloatArray) -> tuple[FloatArray, bool]:
    """Durations scaled up until the velocity and acceleration peaks are within the limits, and
    whether that succeeded. For rest-to-rest ends one step is exact (a uniform time scaling
    divides velocities by the factor and accelerations by its square); with moving ends a few
    steps, stopping once a step no longer lowers the peaks (long end pieces then raise them)."""
    h = np.maximum(h, MIN_DURATION_S)
    best = math.inf
    for _ in range(_FEASIBLE_SCALINGS):
        r = _ratio(lay, _Spline(lay, h, shape, gradient=False))
        if r <= 1.0 + _MARGIN:
            return h, True
        if r >= best:
            return h, False
        best = r
        h = h * r * (1.0 + _MARGIN)
    return h, False


def _trajectory(
    p: TimeJerkProblem, h: FloatArray, shape: FloatArray, iterations: int
) -> TimeJerkTrajectory:
    s = _Spline(_Layout(p), h, shape, gradient=False)
    jerk = s.jerk_integral()
    return TimeJerkTrajectory(
        problem=p,
        piece_durations_s=h,
        coefficients=s.coefficients(),
        jerk_integral=jerk,
        objective=p.w_jerk * jerk + p.w_time * float(np.sum(h)),
        iterations=iterations,
        shape_positions_rad=shape,
    )


def interpolate(
    problem: TimeJerkProblem, durations_s: ArrayLike, shape_positions_rad: ArrayLike | None = None
) -> TimeJerkTrajectory:
    """The spline of ``problem`` for given piece durations (one linear solve, no optimisation,
    no limit enforcement: check it with :meth:`TimeJerkTrajectory.limit_check`).

    Args:
        problem: Waypoints, end states and weights (the weights give ``objective``).
        durations_s: ``(m,)`` = ``(n + 2 + n k,)`` piece durations, s, each >=
            ``MIN_DURATION_S``.
        shape_positions_rad: ``(n k, J)`` the shape knots' positions (required with shape
            knots, none without).

    Raises:
        ConfigurationError: Wrong number of durations or shape positions, or one non-finite or
            a duration too short.
    """
    h = np.array(durations_s, dtype=np.float64)
    m = problem.n_pieces
    if h.shape != (m,):
        raise ConfigurationError(
            f"{problem.waypoints_rad.shape[0]} waypoints need {m} piece durations "
            f"(two free knots, shape knots {list(problem.shape_knots)}); got shape {h.shape}"
        )
    if not np.all(np.isfinite(h)) or not np.all(h >= MIN_DURATION_S):
        raise ConfigurationError(
            f"piece durations must be finite and >= {MIN_DURATION_S} s; got {h.tolist()}"
        )
    f = len(problem.shape_knot_indices)
    shape = np.zeros((0, problem.n_joints)) if shape_positions_rad is None else shape_positions_rad
    shape_a = np.array(shape, dtype=np.float64)
    if shape_a.shape != (f, problem.n_joints) or not np.all(np.isfinite(shape_a)):
        raise ConfigurationError(
            f"{f} shape knots need finite positions of shape ({f}, {problem.n_joints}); got "
            f"shape {shape_a.shape}"
        )
    return _trajectory(problem, h, shape_a, 0)


def _search(
    lay: _Layout,
    h0: FloatArray,
    shape0: FloatArray,
    *,
    positions: bool,
    max_iterations: int,
    last_iterate: bool = False,
    ftol: float = FTOL,
) -> tuple[FloatArray, FloatArray, int]:
    """SLSQP over the durations (and shape knots) from ``h0`` (``shape0``); the optimum's
    durations, shape knots' positions and the iterations (with ``last_iterate``, where SLSQP
    stops without converging, its last iterate: the caller checks it)."""
    p = lay.p
    m = lay.m
    scale = float(np.sum(h0)) / m
    start = _Spline(lay, h0, shape0, gradient=False)
    f0 = p.w_jerk * start.jerk_integral() + p.w_time * float(np.sum(h0))
    ev = _Evaluator(lay, scale, f0, positions=positions)
    bounds: list[tuple[float | None, float | None]] = [(MIN_DURATION_S / scale, None)] * m
    for _ in range(shape0.shape[0]):
        if p.position_min_rad is not None and p.position_max_rad is not None:
            bounds += list(
                zip(p.position_min_rad.tolist(), p.position_max_rad.tolist(), strict=True)
            )
        else:
            bounds += [(None, None)] * lay.n_j
    res = scipy.optimize.minimize(
        ev.fun,
        np.concatenate([h0 / scale, shape0.reshape(-1)]),
        jac=True,
        method="SLSQP",
        bounds=bounds,
        constraints=[{"type": "ineq", "fun": ev.cons, "jac": ev.cons_jac}],
        options={"maxiter": max_iterations, "ftol": ftol},
    )
    x = np.asarray(res.x, dtype=np.float64)
    if not res.success and not (last_iterate and np.all(np.isfinite(x))):
        raise PlanningError(
            f"minimum time-jerk search did not converge ({res.message.strip()} after "
            f"{res.nit} iterations{' with position bounds' if positions else ''}): "
            f"{p.waypoints_rad.shape[0]} waypoints x {p.n_joints} joints, "
            f"w_jerk {p.w_jerk:g}, w_time {p.w_time:g}"
        )
    return np.maximum(x[:m] * scale, MIN_DURATION_S), x[m:].reshape(-1, lay.n_j), int(res.nit)


def plan(
    problem: TimeJerkProblem,
    *,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    shape_ftol: float = FTOL,
) -> TimeJerkTrajectory:
    """The minimum time-jerk trajectory of ``problem`` (module docstring: method, rules).

    Eq 3 is solved first without position bounds; where the problem has bounds and that optimum
    leaves them, the search goes on from it with the position constraints. With shape knots
    the search starts from the optimum without them (see the module).

    Args:
        problem: The problem.
        max_iterations: SLSQP iteration cap per search.
        shape_ftol: SLSQP's tolerance on the scaled objective in the search with shape knots
            (without them :data:`FTOL`).

    Returns:
        A trajectory within every limit by the exact check.

    Raises:
        PlanningError: SLSQP did not converge, or no duration scaling of its answer keeps
            every limit (the message says which and where it stopped).
    """
    if any(problem.shape_knots):
        return _plan_shaped(problem, max_iterations, shape_ftol)
    lay = _Layout(problem)
    h0, shape0 = start_durations(problem), np.zeros((0, problem.n_joints))
    h, shape, iterations = _search(lay, h0, shape0, positions=False, max_iterations=max_iterations)
    h, ok = _scaled_feasible(lay, h, shape)
    traj = _trajectory(problem, h, shape, iterations)
    check = traj.limit_check()
    if ok and not check.within_limits and problem.position_min_rad is not None:
        # Two starts with the position constraints: the bound-free optimum, then the first
        # start (the search from the optimum can stall where a bound cuts across it).
        errors = []
        for start, start_shape in ((h, shape), (h0, shape0)):
            try:
                h, shape, more = _search(
                    lay, start, start_shape, positions=True, max_iterations=max_iterations
                )
            except PlanningError as e:
                errors.append(str(e))
                continue
            h, ok = _scaled_feasible(lay, h, shape)
            traj = _trajectory(problem, h, shape, iterations + more)
            check = traj.limit_check()
            break
        else:
            raise PlanningError(
                "no trajectory within the position bounds found (the bound-free optimum "
                f"leaves them: {_describe(problem, check)}); {errors[-1]}"
            )
    if not (ok and check.within_limits):
        raise PlanningError(
            "the optimised trajectory breaks a limit that no time scaling removes: "
            + _describe(problem, check)
        )
    return traj


def _plan_shaped(problem: TimeJerkProblem, max_iterations: int, ftol: float) -> TimeJerkTrajectory:
    """:func:`plan` with shape knots: from the optimum without them (:func:`_with_shape_knots`),
    the search's answer where it is within every limit and better than that start, else the
    start. Where SLSQP stops at the iteration cap its last iterate, scaled to the limits, is
    the answer it gives; where that optimum leaves the position bounds the search goes on from
    it with the position constraints, and where the start already rides a bound (the optimum
    without shape knots needed them) it searches with them at once."""
    base = plan(problem.without_shape_knots(), max_iterations=max_iterations)
    lay = _Layout(problem)
    h, shape = _with_shape_knots(problem, base)
    best = _trajectory(problem, h, shape, base.iterations)
    iterations = base.iterations
    lo, hi = problem.position_min_rad, problem.position_max_rad
    riding = False
    if lo is not None and hi is not None:
        chk = base.limit_check()
        tol = 1e-6 * (hi - lo)
        riding = bool(
            np.any(chk.position_low_rad <= lo + tol) or np.any(chk.position_high_rad >= hi - tol)
        )
    for positions in (True,) if riding else (False, True):
        try:
            h, shape, more = _search(
                lay,
                h,
                shape,
                positions=positions,
                max_iterations=max_iterations,
                last_iterate=True,
                ftol=ftol,
            )
        except PlanningError:
            break
        iterations += more
        h, ok = _scaled_feasible(lay, h, shape)
        traj = _trajectory(problem, h, shape, iterations)
        check = traj.limit_check()
        if ok and check.within_limits:
            if traj.objective < best.objective:
                best = traj
            break
        if not ok or problem.position_min_rad is None:
            break
    return best


def _describe(p: TimeJerkProblem, check: LimitCheck) -> str:
    """The worst broken limit of ``check`` in words (degrees at this edge of the message)."""
    parts = []
    for j in range(p.n_joints):
        if check.velocity_ratio[j] > 1.0 + LIMIT_TOLERANCE:
            parts.append(f"joint {j} velocity at {check.velocity_ratio[j]:.6f} of its limit")
        if check.acceleration_ratio[j] > 1.0 + LIMIT_TOLERANCE:
            parts.append(
                f"joint {j} acceleration at {check.acceleration_ratio[j]:.6f} of its limit"
            )
        if check.jerk_ratio[j] > 1.0 + LIMIT_TOLERANCE:
            parts.append(f"joint {j} jerk at {check.jerk_ratio[j]:.6f} of its limit")
        if p.position_min_rad is not None and p.position_max_rad is not None:
            lo, hi = p.position_min_rad[j], p.position_max_rad[j]
            if check.position_low_rad[j] < lo or check.position_high_rad[j] > hi:
                parts.append(
                    f"joint {j} reaches [{math.degrees(check.position_low_rad[j]):.4f}, "
                    f"{math.degrees(check.position_high_rad[j]):.4f}] deg outside its bounds "
                    f"[{math.degrees(lo):.4f}, {math.degrees(hi):.4f}] deg"
                )
    return "; ".join(parts) or "none (the scaling did not converge)"


def rest_to_rest_time_s(
    distance_rad: ArrayLike,
    velocity_max_rad_s: ArrayLike,
    acceleration_max_rad_s2: ArrayLike,
    jerk_max_rad_s3: ArrayLike,
) -> FloatArray:
    """The shortest time of a rest-to-rest move of one joint over ``|distance|`` within the
    velocity, acceleration and jerk limits (the seven-piece jerk-limited profile, closed form;
    what ruckig's time-optimal rest-to-rest move of one joint takes).

    All arguments broadcast together; s. Vectorised here rather than one ruckig call a move: a
    dig cycle's dump candidates are ranked on hundreds of these (tests compare with ruckig).
    """
    d = np.abs(np.asarray(distance_rad, dtype=np.float64))
    v = np.asarray(velocity_max_rad_s, dtype=np.float64)
    a = np.asarray(acceleration_max_rad_s2, dtype=np.float64)
    j = np.asarray(jerk_max_rad_s3, dtype=np.float64)
    # Reaching V: the acceleration phase's length (with or without a stretch at A).
    t_acc = np.where(v * j >= a * a, a / j + v / a, 2.0 * np.sqrt(v / j))
    cruise = t_acc + d / v
    # Not reaching V: the peak speed where A is reached, else the pure jerk profile.
    peak = 0.5 * a * (np.sqrt((a / j) ** 2 + 4.0 * d / a) - a / j)
    with_a = 2.0 * (a / j + peak / a)
    jerk_only = 4.0 * np.cbrt(d / (2.0 * j))
    short = np.where(d >= 2.0 * a**3 / (j * j), with_a, jerk_only)
    out: FloatArray = np.where(d >= v * t_acc, cruise, short)
    return out


def reversal_bound_s(
    waypoints_rad: ArrayLike,
    velocity_max_rad_s: ArrayLike,
    acceleration_max_rad_s2: ArrayLike,
    jerk_max_rad_s3: ArrayLike,
) -> FloatArray:
    """The time through waypoints if each joint stopped only where it reverses: per joint the
    sum of the rest-to-rest times (:func:`rest_to_rest_time_s`) of its runs in one direction
    (consecutive steps of one sign, steps of zero joining the run they are in), the largest
    over the joints. A lower bound on any trajectory through the waypoints that comes to rest
    where a joint reverses; a blended trajectory is compared with it.

    Args:
        waypoints_rad: ``(..., n + 1, J)``; leading axes are independent problems.
        velocity_max_rad_s, acceleration_max_rad_s2, jerk_max_rad_s3: ``(J,)`` limits.

    Returns:
        ``(...)`` bounds, s.
    """
    w = np.asarray(waypoints_rad, dtype=np.float64)
    step = np.diff(w, axis=-2)  # (..., n, J)
    sign = np.sign(step)
    # A step of zero continues the run before it: carry the last non-zero sign forward.
    idx = np.where(sign != 0.0, np.arange(step.shape[-2])[:, None], -1)
    last = np.maximum.accumulate(idx, axis=-2)
    carried = np.take_along_axis(sign, np.maximum(last, 0), axis=-2) * (last >= 0)
    nxt = np.concatenate([carried[..., 1:, :], np.zeros_like(carried[..., :1, :])], axis=-2)
    ends = nxt != carried  # a run ends where the next step turns (or at the last step)
    cum = np.cumsum(np.abs(step), axis=-2)
    at_end = np.where(ends, cum, 0.0)
    before = np.concatenate([np.zeros_like(at_end[..., :1, :]), at_end[..., :-1, :]], axis=-2)
    start = np.maximum.accumulate(before, axis=-2)
    runs = np.where(ends, cum - start, 0.0)
    t = rest_to_rest_time_s(runs, velocity_max_rad_s, acceleration_max_rad_s2, jerk_max_rad_s3)
    out: FloatArray = np.max(np.sum(np.where(ends, t, 0.0), axis=-2), axis=-1)
    return out
