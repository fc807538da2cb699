"""The limit guard: a ruckig online filter in cylinder-stroke space between the plan and the bus.

Role: the last thing every setpoint passes before it becomes an RPDO1 (DESIGN.md "Loop, HIL and
time"). Each cycle the executor hands the guard the next plan sample in stroke space
(position, velocity, acceleration, for the time one period ahead); the guard answers with the
setpoint to send. When the plan is within the limits the answer *is* the sample (to rounding,
~1e-16 m): a verified plan passes through unchanged. When the target steps beyond a limit (a jump,
a plan faster than the rig) the answer is the first period of ruckig's time-optimal, jerk-limited
approach to it, re-planned every cycle (online). :meth:`LimitGuard.stop` switches to ruckig's
velocity interface with target velocity 0: a jerk-limited stop from the current commanded state
(never from the measured one, so the command stays continuous), streamed until at rest. Every
output is a state on one continuous trajectory whose velocity, acceleration and jerk stay within
:class:`StrokeLimits`, so no frame ever commands a step beyond a limit.

How passthrough is exact. ruckig (``Ruckig(n, period_s)`` over the n axes, ``update`` per
cycle, no intermediate waypoints) plans from the guard's previous output to the target state; with
``minimum_duration = period_s`` and time synchronisation its trajectory takes exactly one period
whenever that is feasible within the limits, so the state after one period is the target. Only
when the target cannot be reached in one period does the trajectory take longer, and the output
falls behind (limited). A target whose velocity or acceleration exceeds a limit is clamped before
ruckig sees it (ruckig refuses such targets); a target ruckig still refuses (a velocity near the
limit with an acceleration pointing outwards) is retried with zero target acceleration, then as a
velocity-interface move to the clamped velocity.

Limits (:meth:`StrokeLimits.from_rig`, where the rig gives joint limits and Yao gives no stroke
limits). Each stroke depends on its own joint only, s_i = f_i(q_i), so along any joint motion
``sd = J qd``, ``sdd = J qdd + J' qd^2``, ``sddd = J qddd + 3 J' qd qdd + J'' qd^3`` with
``J = df/dq`` (the centripetal term ``dJ/dt qd = J' qd^2`` included). A joint motion within the
joint limits therefore has stroke derivatives bounded by the maxima over the joint range of
``|J| qd_max``, ``|J| qdd_max + |J'| qd_max^2`` and
``|J| qddd_max + 3 |J'| qd_max qdd_max + |J''| qd_max^3``: these (times ``1 + margin``, so that a
verified plan never touches them) are the guard's limits; the velocity is also capped by the
actuator's ``velocity_max_m_s``. They are conservative towards the plan (a verified plan passes)
and bounded towards the rig (never more than the joint limits allow at the least favourable pose).

Cost: one ``update`` plus list conversions, ~15-25 us per cycle (``benchmarks/`` and the test
print it). Safe inside the loop: allocates only the small lists ruckig's binding takes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray
from ruckig import (
    ControlInterface,
    InputParameter,
    OutputParameter,
    Result,
    Ruckig,
    RuckigError,
    Synchronization,
)

from rt_runtime import actuation
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig

__all__ = [
    "GuardState",
    "LimitGuard",
    "StrokeLimits",
    "TraceCheck",
    "check_setpoint_trace",
    "rpdo1_setpoints",
]

FloatArray = NDArray[np.float64]

#: Default headroom of the guard's limits over what a plan within the joint limits can need.
DEFAULT_MARGIN = 0.02
#: Below this commanded speed and acceleration an axis counts as at rest (m/s, m/s^2).
REST_VELOCITY_M_S = 1e-9
REST_ACCELERATION_M_S2 = 1e-9
_OK = (Result.Working, Result.Finished)


@dataclass(frozen=True, slots=True)
class StrokeLimits:
    """Per-axis limits of the commanded actuator position, in axis order (boom, stick, bucket
    strokes in m; the swing angle in rad on a rig with swing, :mod:`rt_runtime.axes`). The
    ``_m`` names hold the swing's values in rad.

    Attributes:
        velocity_m_s: Largest rate ``(n,)``.
        acceleration_m_s2: Largest acceleration ``(n,)``.
        jerk_m_s3: Largest jerk ``(n,)``.

    Raises:
        ConfigurationError: A limit is not finite and > 0, or not three or four of each, or
            not as many of each.
    """

    velocity_m_s: tuple[float, ...]
    acceleration_m_s2: tuple[float, ...]
    jerk_m_s3: tuple[float, ...]

    def __post_init__(self) -> None:
        n = len(self.velocity_m_s)
        for name in ("velocity_m_s", "acceleration_m_s2", "jerk_m_s3"):
            values = getattr(self, name)
            if (
                len(values) != n
                or n not in (3, 4)
                or not all(math.isfinite(v) and v > 0.0 for v in values)
            ):
                raise ConfigurationError(
                    f"stroke limit {name} = {values}; allowed: three (or four, with swing) "
                    "finite values > 0, as many of each"
                )

    @property
    def n(self) -> int:
        """Number of axes."""
        return len(self.velocity_m_s)

    @classmethod
    def from_rig(cls, rig: Rig, margin: float = DEFAULT_MARGIN, n_grid: int = 4001) -> StrokeLimits:
        """The stroke-space image of the rig's joint limits (see the module docstring).

        Args:
            rig: The rig (joint ranges and velocity/acceleration/jerk limits, cylinders,
                actuator speed).
            margin: Relative headroom over the bound (>= 0).
            n_grid: Samples of each joint range for the maxima.

        Raises:
            ConfigurationError: ``margin`` negative or ``n_grid`` below 16.
        """
        if not (margin >= 0.0 and math.isfinite(margin)):
            raise ConfigurationError(f"guard margin {margin}; allowed: a finite number >= 0")
        if n_grid < 16:
            raise ConfigurationError(f"guard n_grid {n_grid}; allowed: >= 16")
        q = np.linspace(rig.q_min_rad, rig.q_max_rad, n_grid)  # (n, 3)
        step = (rig.q_max_rad - rig.q_min_rad) / (n_grid - 1)
        j = actuation.stroke_jacobian(rig, q, check_limits=False)
        dj = _gradient(j, step)
        ddj = _gradient(dj, step)
        vq, aq, jq = rig.qd_max_rad_s, rig.qdd_max_rad_s2, rig.qddd_max_rad_s3
        # Maxima of the sums over the range (not sums of maxima): tighter, still a bound.
        vel = np.abs(j).max(axis=0) * vq
        acc = (np.abs(j) * aq + np.abs(dj) * vq**2).max(axis=0)
        jerk = (np.abs(j) * jq + 3.0 * np.abs(dj) * vq * aq + np.abs(ddj) * vq**3).max(axis=0)
        f = 1.0 + margin
        vel = np.minimum(vel * f, rig.actuators.velocity_max_m_s)
        vel, acc, jerk = _triple(vel), _triple(acc * f), _triple(jerk * f)
        if rig.swing is not None:  # the swing drive's position is the joint angle itself
            sw = rig.swing.joint
            vel += (sw.velocity_max_rad_s * f,)
            acc += (sw.acceleration_max_rad_s2 * f,)
            jerk += (sw.jerk_max_rad_s3 * f,)
        return cls(vel, acc, jerk)

    def as_arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(velocity, acceleration, jerk)`` as ``(n,)`` arrays."""
        return (
            np.array(self.velocity_m_s),
            np.array(self.acceleration_m_s2),
            np.array(self.jerk_m_s3),
        )


def _gradient(values: FloatArray, step: FloatArray) -> FloatArray:
    """Per-column derivative on a uniform grid (second-order accurate)."""
    out = np.empty_like(values)
    for axis in range(values.shape[1]):
        out[:, axis] = np.gradient(values[:, axis], float(step[axis]), edge_order=2)
    return out


def _triple(a: FloatArray) -> tuple[float, ...]:
    return tuple(float(x) for x in a)


class GuardState(IntEnum):
    """What the last :class:`LimitGuard` cycle did."""

    #: The output is the target (within rounding).
    PASSTHROUGH = 0
    #: The target was beyond a limit; the output approaches it within the limits.
    LIMITED = 1
    #: A stop is under way.
    STOPPING = 2
    #: Stopped: velocity and acceleration are zero.
    AT_REST = 3
    #: ruckig refused every form of the target; the output holds the previous state's
    #: trajectory towards rest (a stop was started).
    ERROR = 4


class LimitGuard:
    """Online ruckig filter in stroke space (see the module docstring).

    Args:
        limits: Stroke limits.
        period_s: Cycle period (ruckig's ``delta_time``).

    Attributes:
        position_m, velocity_m_s, acceleration_m_s2: The commanded state after the last cycle
            (the setpoint to send), ``(n,)`` arrays owned by the guard (overwritten each
            cycle).
        stopping: :meth:`stop` was called and :meth:`reset` not since.
        state: :class:`GuardState` of the last cycle.

    Raises:
        ConfigurationError: ``period_s`` not finite and > 0.
    """

    def __init__(self, limits: StrokeLimits, period_s: float) -> None:
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ConfigurationError(f"guard period_s {period_s}; allowed: a finite number > 0")
        self.limits = limits
        self.period_s = float(period_s)
        self._v_max, self._a_max, _ = limits.as_arrays()
        self.n = n = limits.n
        self._otg = Ruckig(n, self.period_s)
        self._inp = InputParameter(n)
        self._out = OutputParameter(n)
        inp = self._inp
        inp.max_velocity = list(limits.velocity_m_s)
        inp.max_acceleration = list(limits.acceleration_m_s2)
        inp.max_jerk = list(limits.jerk_m_s3)
        self.position_m = np.zeros(n)
        self.velocity_m_s = np.zeros(n)
        self.acceleration_m_s2 = np.zeros(n)
        self._zeros: list[float] = [0.0] * n
        self._v_list: list[float] = self._v_max.tolist()
        self._a_list: list[float] = self._a_max.tolist()
        self.stopping = False
        self.state = GuardState.AT_REST
        self._track_mode()

    # -- modes ----------------------------------------------------------------------------------

    def _track_mode(self) -> None:
        inp = self._inp
        inp.control_interface = ControlInterface.Position
        inp.synchronization = Synchronization.Time
        inp.minimum_duration = self.period_s

    def reset(
        self,
        position_m: ArrayLike,
        velocity_m_s: ArrayLike | None = None,
        acceleration_m_s2: ArrayLike | None = None,
    ) -> None:
        """Set the commanded state (the start of a run: the measured strokes, at rest) and leave
        stop mode.

        Args:
            position_m: Strokes ``(n,)``.
            velocity_m_s: Stroke rates ``(n,)``, default 0.
            acceleration_m_s2: Stroke accelerations ``(n,)``, default 0.

        Raises:
            ConfigurationError: A value is not finite or not three.
        """
        p = np.asarray(position_m, dtype=np.float64).reshape(-1)
        n = self.n
        v = np.zeros(n) if velocity_m_s is None else np.asarray(velocity_m_s, np.float64)
        a = np.zeros(n) if acceleration_m_s2 is None else np.asarray(acceleration_m_s2, np.float64)
        for name, x in (("position_m", p), ("velocity_m_s", v), ("acceleration_m_s2", a)):
            if x.shape != (n,) or not np.isfinite(x).all():
                raise ConfigurationError(
                    f"guard reset {name} = {x}; allowed: {n} finite values (one per axis)"
                )
        self.position_m[:] = p
        self.velocity_m_s[:] = v
        self.acceleration_m_s2[:] = a
        self._set_current()
        self.stopping = False
        self._track_mode()
        self.state = GuardState.AT_REST if self.at_rest else GuardState.PASSTHROUGH

    def stop(self) -> None:
        """Switch to a jerk-limited stop from the current commanded state (idempotent).

        Safe inside the loop. Each following :meth:`step_stop` advances the stop one period.
        """
        if self.stopping:
            return
        self.stopping = True
        inp = self._inp
        inp.control_interface = ControlInterface.Velocity
        inp.synchronization = Synchronization.No
        inp.minimum_duration = None
        inp.target_velocity = list(self._zeros)
        inp.target_acceleration = list(self._zeros)
        self.state = GuardState.STOPPING

    @property
    def at_rest(self) -> bool:
        """Commanded velocity and acceleration are zero on every axis."""
        return bool(
            np.all(np.abs(self.velocity_m_s) <= REST_VELOCITY_M_S)
            and np.all(np.abs(self.acceleration_m_s2) <= REST_ACCELERATION_M_S2)
        )

    # -- per cycle ------------------------------------------------------------------------------

    def _set_current(self) -> None:
        inp = self._inp
        inp.current_position = self.position_m.tolist()
        inp.current_velocity = self.velocity_m_s.tolist()
        inp.current_acceleration = self.acceleration_m_s2.tolist()

    def _take_output(self) -> None:
        out = self._out
        self.position_m[:] = out.new_position
        self.velocity_m_s[:] = out.new_velocity
        self.acceleration_m_s2[:] = out.new_acceleration
        out.pass_to_input(self._inp)

    def _update(self) -> Result:
        """One ruckig update; a refusal the binding raises comes back as its error code."""
        try:
            result: Result = self._otg.update(self._inp, self._out)
        except RuckigError:
            return Result.ErrorInvalidInput
        return result

    def _aim(
        self,
        position_m: list[float],
        velocity_m_s: list[float],
        acceleration_m_s2: list[float],
        horizon_s: float | None,
    ) -> bool:
        """One ruckig update towards a target state; True when it is reached after exactly
        ``horizon_s`` (None: time-optimal, True when ruckig accepted the input)."""
        inp = self._inp
        inp.minimum_duration = horizon_s
        inp.target_position = position_m
        inp.target_velocity = velocity_m_s
        inp.target_acceleration = acceleration_m_s2
        try:
            result = self._otg.update(inp, self._out)
        except RuckigError:
            # The binding raises for some refused inputs (a target whose acceleration points
            # beyond a velocity limit it is near) where others return an error code: the same
            # refusal, and the caller's retries are the same.
            return False
        if result not in _OK:
            return False
        if horizon_s is None:
            return True
        return bool(self._out.trajectory.duration <= horizon_s * (1.0 + 1e-9))

    def track(
        self, position_m: FloatArray, velocity_m_s: FloatArray, acceleration_m_s2: FloatArray
    ) -> GuardState:
        """One cycle towards a target state (the plan sample one period ahead).

        Exactly the target when it is reachable in one period within the limits (passthrough).
        Otherwise (limited) the first period of ruckig's time-optimal approach to it, re-planned
        every cycle: a static target is reached time-optimally; a moving one is trailed (a
        pursuit lags its target by roughly the approach time) and rejoined exactly once it comes
        to rest. The executor never hands the guard a gap (it bridges every gap with a
        connecting move), so only a plan beyond the limits is ever limited.

        In stop mode the target is ignored and the stop advances (as :meth:`step_stop`).

        Args:
            position_m, velocity_m_s, acceleration_m_s2: Target stroke state ``(n,)``.

        Returns:
            PASSTHROUGH (output = target), LIMITED, STOPPING/AT_REST (stop mode), or ERROR
            (ruckig refused the target in every form: a stop was started).

        Safe inside the loop.
        """
        if self.stopping:
            return self.step_stop()
        T = self.period_s
        # The target's rate and acceleration within the limits (plain floats: three axes).
        p = position_m.tolist()
        v = velocity_m_s.tolist()
        a = acceleration_m_s2.tolist()
        clamped = False
        for i, (v_max, a_max) in enumerate(zip(self._v_list, self._a_list, strict=True)):
            vi, ai = v[i], a[i]
            if not -v_max <= vi <= v_max:
                v[i] = max(-v_max, min(v_max, vi))
                clamped = True
            if not -a_max <= ai <= a_max:
                a[i] = max(-a_max, min(a_max, ai))
                clamped = True
        if self._aim(p, v, a, T) and not clamped:
            self._take_output()
            self.state = GuardState.PASSTHROUGH
            return self.state
        if self._aim(p, v, a, None) or self._aim(p, v, self._zeros, None):
            self._take_output()
            self.state = GuardState.LIMITED
            return self.state
        # Last resort before a stop: move towards the clamped velocity, position ignored.
        inp = self._inp
        inp.control_interface = ControlInterface.Velocity
        inp.synchronization = Synchronization.No
        inp.minimum_duration = None
        result = self._update()
        self._track_mode()
        if result not in _OK:
            self.stop()
            self.step_stop()
            self.state = GuardState.ERROR
            return self.state
        self._take_output()
        self.state = GuardState.LIMITED
        return self.state

    def step_stop(self) -> GuardState:
        """One cycle of the stop (starts one if none is under way).

        Returns:
            STOPPING, or AT_REST once velocity and acceleration are zero.

        Safe inside the loop.
        """
        if not self.stopping:
            self.stop()
        if self.at_rest:
            self.velocity_m_s[:] = 0.0
            self.acceleration_m_s2[:] = 0.0
            self.state = GuardState.AT_REST
            return self.state
        result = self._update()
        if result in _OK:
            self._take_output()
            if result is Result.Finished:
                self.velocity_m_s[:] = 0.0
                self.acceleration_m_s2[:] = 0.0
                self._set_current()
        self.state = GuardState.AT_REST if self.at_rest else GuardState.STOPPING
        return self.state


# -- checking a setpoint trace (tests, the daemon's end-to-end check) ----------------------------


@dataclass(frozen=True, slots=True)
class TraceCheck:
    """How close a setpoint trace comes to the limits (1.0 = at the limit).

    Finite differences over ``span`` frames of a trajectory with bounded derivatives are bounded
    by the same limit (they are averages of the derivative against a B-spline kernel), so the
    ratios below are exact tests of the trace, up to the integer micrometre rounding of the
    frames, which is allowed for.

    Attributes:
        velocity: Per axis, largest |first difference| / (v_max T).
        acceleration: Per axis, from second differences of the target over ``span_acc_frames``,
            and first differences of the velocity offset when given: the larger.
        jerk: Per axis, from third differences of the target over ``span_jerk_frames``, and
            second differences of the velocity offset when given: the larger.
        frames: Setpoints checked per axis.
    """

    velocity: tuple[float, ...]
    acceleration: tuple[float, ...]
    jerk: tuple[float, ...]
    frames: int

    @property
    def ok(self) -> bool:
        """Every ratio is at most 1."""
        return max(*self.velocity, *self.acceleration, *self.jerk) <= 1.0


def _ratio(diff: FloatArray, allowance: float, limit: FloatArray) -> FloatArray:
    if diff.shape[0] == 0:
        return np.zeros(diff.shape[1])
    return np.asarray(np.maximum(np.abs(diff).max(axis=0) - allowance, 0.0) / limit)


def check_setpoint_trace(
    target_um: ArrayLike,
    limits: StrokeLimits,
    period_s: float,
    *,
    velocity_um_s: ArrayLike | None = None,
    span_acc_frames: int = 10,
    span_jerk_frames: int = 25,
) -> TraceCheck:
    """Check consecutive RPDO1 setpoints (one per SYNC) against the stroke limits.

    Args:
        target_um: Target positions per frame, integer millionths (um, urad), ``(n, axes)``.
        limits: The limits.
        period_s: SYNC period (the time between consecutive setpoints).
        velocity_um_s: Velocity offsets per frame (um/s) when feed-forward was on, ``(n, axes)``.
        span_acc_frames: Span of the acceleration differences (frames).
        span_jerk_frames: Span of the jerk differences (frames).

    Returns:
        The ratios to the limits (:attr:`TraceCheck.ok` when none exceeds 1).
    """
    k = limits.n
    s = np.asarray(target_um, dtype=np.float64).reshape(-1, k) * 1e-6
    v_max, a_max, j_max = limits.as_arrays()
    T = period_s
    q = 1e-6  # one micrometre of rounding per frame
    vel = _ratio(np.diff(s, axis=0), q, v_max * T)
    m = span_acc_frames
    d2 = s[2 * m :] - 2.0 * s[m:-m] + s[: -2 * m] if len(s) > 2 * m else np.zeros((0, k))
    acc = _ratio(d2, 2.0 * q, a_max * (m * T) ** 2)
    m = span_jerk_frames
    if len(s) > 3 * m:
        d3 = s[3 * m :] - 3.0 * s[2 * m : -m] + 3.0 * s[m : -2 * m] - s[: -3 * m]
    else:
        d3 = np.zeros((0, k))
    jerk = _ratio(d3, 4.0 * q, j_max * (m * T) ** 3)
    if velocity_um_s is not None:
        v = np.asarray(velocity_um_s, dtype=np.float64).reshape(-1, k) * 1e-6
        vel = np.maximum(vel, _ratio(v, 0.5 * q, v_max))
        acc = np.maximum(acc, _ratio(np.diff(v, axis=0), q, a_max * T))
        m = max(1, span_acc_frames // 2)
        dv2 = v[2 * m :] - 2.0 * v[m:-m] + v[: -2 * m] if len(v) > 2 * m else np.zeros((0, k))
        jerk = np.maximum(jerk, _ratio(dv2, 2.0 * q, j_max * (m * T) ** 2))
    return TraceCheck(_triple(vel), _triple(acc), _triple(jerk), int(s.shape[0]))


def rpdo1_setpoints(
    frames: Iterable[tuple[int, bytes]], node_ids: Sequence[int]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The RPDO1 setpoints of each drive from a bus trace, in bus order.

    Args:
        frames: ``(arbitration id, data)`` of every frame, in bus order.
        node_ids: Drive node ids in axis order.

    Returns:
        ``(target_um, velocity_um_s)``, each ``(n, len(node_ids))``, n the fewest RPDO1s any
        drive got (the master sends one to every drive per SYNC).
    """
    from rt_runtime.canbus.pdo import RPDO1

    cobs = {RPDO1.cob_id(node): axis for axis, node in enumerate(node_ids)}
    per_axis: list[list[tuple[int, int]]] = [[] for _ in node_ids]
    for cob, data in frames:
        axis = cobs.get(cob)
        if axis is not None and len(data) == RPDO1.size:
            per_axis[axis].append(RPDO1.codec.unpack(bytes(data)))
    n = min(len(rows) for rows in per_axis)
    target = np.array([[rows[k][0] for rows in per_axis] for k in range(n)], dtype=np.int64)
    velocity = np.array([[rows[k][1] for rows in per_axis] for k in range(n)], dtype=np.int64)
    return target.reshape(n, len(node_ids)), velocity.reshape(n, len(node_ids))
