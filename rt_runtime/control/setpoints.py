"""Motions as setpoint tables: a joint motion sampled on the loop's period grid and mapped to
cylinder strokes, built by the planner side so that a cycle only reads rows of arrays.

A :class:`SampledMotion` holds, for the samples ``j = 0 .. n-1`` at ``t = (j + 1) T`` (``T`` the
loop's period; the last sample is the motion's end pose, reached at or before ``n T``), the
joint reference (rad) and the stroke, stroke rate and stroke acceleration (m, m/s, m/s^2) the
limit guard tracks: ``s(q)``, ``J qd`` and ``J qdd + J' qd^2`` with ``J' = d^2 s / dq^2`` by a
central second difference of step :data:`H_RAD`. The cycle that streams sample ``j`` sends it
with SYNC ``k`` for ``t_k + T`` (see :mod:`rt_runtime.control.manager`).

A motion streams in one phase, or where it passes through several (a blended dig cycle: lift
out, dump, approach, enter without stopping between them) in one phase a run of samples
(:attr:`SampledMotion.phase_runs`).

On a rig with swing every array is in axis order over four axes (boom, stick, bucket, swing;
:mod:`rt_runtime.axes`): the swing's "stroke" is its angle (rad), its Jacobian 1.

Every queued motion starts where the one before it ends: the planner side inserts a
:data:`Phase.CONNECT` move (a rest-to-rest ruckig move within the rig's joint limits) where two
motions, or the measured pose and the first motion, are further apart than
:data:`CONNECT_TOLERANCE_M` of stroke. No cycle plans a move.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime import axes
from rt_runtime.errors import PlanningError
from rt_runtime.planning.trench import Cycle, TransitionKind, joint_move
from rt_runtime.rig import Rig

__all__ = [
    "CONNECT_TOLERANCE_M",
    "H_RAD",
    "KIND_PHASE",
    "Phase",
    "SampledMotion",
    "connect_motion",
    "sample_cycle",
    "sample_motion",
    "stroke_gap_m",
]

FloatArray = NDArray[np.float64]

#: Step of the second difference for J' = d^2 s / dq^2 (rad): truncation ~h^2, rounding ~1e-8.
H_RAD = 1e-4
#: Commanded-pose gap (largest stroke difference, m) above which a connecting move bridges it:
#: the guard passes a step through exactly only while it fits in one period within the jerk
#: limit (~j_max T^3 / 32, 4e-11 m at 2 ms), and trails the plan after a larger one.
CONNECT_TOLERANCE_M = 1e-11


class Phase(IntEnum):
    """What a job streams in a cycle (telemetry column ``phase``)."""

    #: Holding: waiting for a plan, or paused.
    WAIT = 0
    #: A ruckig move bridging the commanded pose and the next motion's start.
    CONNECT = 1
    LIFT_OUT = 2
    DUMP = 3
    APPROACH = 4
    ENTER = 5
    DIG = 6
    #: Holding at the end of the job until the drives report rest.
    SETTLE = 7
    #: The guard's jerk-limited stop.
    STOP = 8
    #: A prescribed path's motion (:class:`~rt_runtime.control.planner_worker.PathJob`).
    PATH = 9


#: The phase of a trench transition's ``kind``.
KIND_PHASE = {
    TransitionKind.LIFT_OUT: Phase.LIFT_OUT,
    TransitionKind.DUMP: Phase.DUMP,
    TransitionKind.APPROACH: Phase.APPROACH,
    TransitionKind.ENTER: Phase.ENTER,
}


@dataclass(frozen=True, slots=True, eq=False)
class SampledMotion:
    """A motion on the loop's period grid (see the module docstring).

    Attributes:
        phase: The phase it streams in.
        q_start_rad: Its start pose (rad), ``(a,)`` over the rig's ``a`` axes, and
            ``stroke_start_m`` its actuator positions (m; the swing's rad).
        q_rad: Joint reference of sample ``j`` (at ``(j + 1) T``), ``(n, a)``.
        stroke_m, rate_m_s, accel_m_s2: Actuator position, rate and acceleration of sample
            ``j``, ``(n, a)``.
        dig_index: The dig's index (phase DIG), else -1.
        duration_s: The motion's length (s).
        phase_runs: Where the motion passes through several phases: ``(j, phase)`` pairs in
            order, sample ``j`` on streaming in ``phase`` (the first is ``(0, phase)``); empty
            when the whole motion streams in :attr:`phase`.
    """

    phase: Phase
    q_start_rad: FloatArray
    stroke_start_m: FloatArray
    q_rad: FloatArray
    stroke_m: FloatArray
    rate_m_s: FloatArray
    accel_m_s2: FloatArray
    dig_index: int
    duration_s: float
    phase_runs: tuple[tuple[int, Phase], ...] = ()

    @property
    def n(self) -> int:
        """Number of samples (cycles it streams)."""
        return int(self.q_rad.shape[0])


def _n_samples(duration_s: float, period_s: float) -> int:
    """Samples until ``(j + 1) T >= duration - 1e-12`` (at least one)."""
    n = max(1, math.ceil((duration_s - 1e-12) / period_s))
    while n > 1 and (n - 1) * period_s >= duration_s - 1e-12:
        n -= 1
    while n * period_s < duration_s - 1e-12:
        n += 1
    return n


def sample_motion(
    rig: Rig,
    period_s: float,
    phase: Phase,
    duration_s: float,
    sample: Callable[[float], tuple[Any, Any, Any]],
    *,
    q_end_rad: Any = None,
    dig_index: int = -1,
) -> SampledMotion:
    """Sample ``sample(t) -> (q, qd, qdd)`` at ``(j + 1) T`` (clamped to the motion) and map it
    to strokes (outside the loop: allocates).

    Args:
        rig: The rig (stroke mapping).
        period_s: The loop's period ``T`` (s).
        phase: The phase it streams in.
        duration_s: The motion's length (s).
        sample: Joint position, velocity and acceleration at a time in ``[0, duration_s]``.
        q_end_rad: The exact end pose (at rest) for samples at or past the end, or None to use
            ``sample(duration_s)``.
        dig_index: The dig's index for a dig.
    """
    duration = float(duration_s)
    n = _n_samples(duration, period_s)
    k = axes.count(rig)
    q = np.empty((n, k))
    qd = np.empty((n, k))
    qdd = np.empty((n, k))
    for j in range(n):
        t = min(max((j + 1) * period_s, 0.0), duration)
        if q_end_rad is not None and t >= duration:
            q[j] = q_end_rad
            qd[j] = 0.0
            qdd[j] = 0.0
            continue
        a, b, c = sample(t)
        q[j] = a
        qd[j] = b
        qdd[j] = c
    q0 = np.asarray(sample(0.0)[0], dtype=np.float64).copy()
    return _tables(rig, phase, q0, q, qd, qdd, dig_index, duration)


def _tables(
    rig: Rig,
    phase: Phase,
    q0: FloatArray,
    q: FloatArray,
    qd: FloatArray,
    qdd: FloatArray,
    dig_index: int,
    duration: float,
    phase_runs: tuple[tuple[int, Phase], ...] = (),
) -> SampledMotion:
    """The joint samples ``(n, a)`` mapped to actuator position, rate and acceleration (module
    docstring)."""
    s0 = axes.joint_to_actuator(rig, q0, check_limits=False)
    q3 = np.repeat(q[:, None, :], 3, axis=1)
    q3[:, 0] -= H_RAD
    q3[:, 2] += H_RAD
    s3 = axes.joint_to_actuator(rig, q3, check_limits=False)
    jac = axes.actuator_jacobian(rig, q, check_limits=False)
    dj = (s3[:, 2] - 2.0 * s3[:, 1] + s3[:, 0]) * (1.0 / (H_RAD * H_RAD))
    stroke = np.ascontiguousarray(s3[:, 1])
    rate = jac * qd
    accel = jac * qdd + dj * qd * qd
    return SampledMotion(
        phase, q0, s0, q, stroke, rate, accel, int(dig_index), duration, phase_runs
    )


def sample_cycle(rig: Rig, period_s: float, cycle: Cycle) -> SampledMotion:
    """A blended dig cycle's blend (:class:`~rt_runtime.planning.trench.Cycle`, from waypoint
    :attr:`~rt_runtime.planning.trench.Cycle.blend_from`: its rest-to-rest moves before it
    stream with :func:`connect_motion`) sampled like :func:`sample_motion` (its trajectory
    evaluated at all sample times at once; the last sample is exactly its last waypoint, at
    rest), each sample in the phase of the waypoint interval it lies in
    (:attr:`SampledMotion.phase_runs`).

    Raises:
        PlanningError: The cycle is not blended (stream its moves with
            :func:`connect_motion`).
    """
    traj = cycle.trajectory(rig)
    duration = float(traj.duration_s)
    n = _n_samples(duration, period_s)
    t = np.minimum((np.arange(n) + 1.0) * period_s, duration)
    states = traj.states(t)  # (n, 4, 3)
    q = np.ascontiguousarray(states[:, 0])
    qd = np.ascontiguousarray(states[:, 1])
    qdd = np.ascontiguousarray(states[:, 2])
    end = t >= duration
    q[end] = cycle.waypoints_rad[-1]
    qd[end] = 0.0
    qdd[end] = 0.0
    # Sample j (at (j + 1) T) belongs to the waypoint interval its time lies in.
    b = cycle.blend_from
    times = np.asarray(cycle.waypoint_times_s[b:])
    starts = times[1:-1] - times[0]
    first = np.searchsorted(t, starts, side="left").tolist()
    phases = [KIND_PHASE[k] for k in cycle.kinds[b:]]
    runs: list[tuple[int, Phase]] = [(0, phases[0])]
    for j, ph in zip(first, phases[1:], strict=True):
        if ph is runs[-1][1]:
            continue
        if j <= runs[-1][0]:
            runs[-1] = (runs[-1][0], ph)
        elif j < n:
            runs.append((j, ph))
    q0 = np.asarray(cycle.waypoints_rad[b], dtype=np.float64)
    return _tables(rig, runs[0][1], q0, q, qd, qdd, -1, duration, tuple(runs))


def connect_motion(
    rig: Rig, period_s: float, q_from_rad: Any, q_to_rad: Any, phase: Phase = Phase.CONNECT
) -> SampledMotion:
    """A rest-to-rest ruckig move ``q_from -> q_to`` within the rig's joint limits, sampled;
    its last sample is exactly ``q_to``.

    Raises:
        PlanningError: ruckig cannot plan it.
    """
    q_to = np.asarray(q_to_rad, dtype=np.float64)
    if rig.swing is None:
        traj, duration = joint_move(rig, q_from_rad, q_to)
    else:
        traj, duration = _axis_move(rig, q_from_rad, q_to)
    motion = sample_motion(rig, period_s, phase, duration, traj.at_time, q_end_rad=q_to)
    return motion


def _axis_move(rig: Rig, q_from_rad: Any, q_to_rad: FloatArray) -> tuple[Any, float]:
    """Rest-to-rest ruckig move over every axis (axis order) within the joint limits (no
    intermediate waypoints): ``(ruckig.Trajectory, duration_s)``.

    Raises:
        PlanningError: ruckig cannot plan it.
    """
    from ruckig import InputParameter, Result, Ruckig, Trajectory

    n = axes.count(rig)
    _, _, v, a, j = axes.joint_limits(rig)
    inp = InputParameter(n)
    inp.max_velocity = v.tolist()
    inp.max_acceleration = a.tolist()
    inp.max_jerk = j.tolist()
    inp.current_position = np.asarray(q_from_rad, dtype=np.float64).tolist()
    inp.target_position = q_to_rad.tolist()
    traj = Trajectory(n)
    result = Ruckig(n).calculate(inp, traj)
    if result not in (Result.Working, Result.Finished):
        raise PlanningError(
            f"no rest-to-rest move from ({axes.degrees_text(rig, inp.current_position)}) deg to "
            f"({axes.degrees_text(rig, q_to_rad)}) deg: ruckig {result}"
        )
    return traj, float(traj.duration)


def stroke_gap_m(rig: Rig, q_a_rad: Any, q_b_rad: Any) -> float:
    """Largest actuator difference between two poses (m; the swing's rad)."""
    s_a = axes.joint_to_actuator(rig, np.asarray(q_a_rad, dtype=np.float64), check_limits=False)
    s_b = axes.joint_to_actuator(rig, np.asarray(q_b_rad, dtype=np.float64), check_limits=False)
    return float(np.max(np.abs(s_a - s_b)))
