"""A taught trench (``teach --out DIR``) as a prescribed path for the executor.

Role: the one adapter between the taught job's file (:func:`rt_runtime.teach.load_taught`, joints
swing first, verified against the rig when loaded) and the control stack, whose joint vectors are
in axis order (boom, stick, bucket, swing: :mod:`rt_runtime.axes`). The HIL's ``hil --teach`` and
the daemon's taught jobs (``job submit --teach DIR``) run it the same way: one
:class:`~rt_runtime.control.planner_worker.PathJob` whose motions are the trench's cycles (each
starts and ends at rest), whose jerk the limit guard bounds
(:attr:`~rt_runtime.control.planner_worker.PathJob.jerk_by_guard`: the minimum time-jerk cycle
of Zhao eq 3 is a cubic spline within the velocity and acceleration limits, its jerk piecewise
constant and not limited by its planner).

Resuming. The cycles are the job's steps (:attr:`~rt_runtime.control.planner_worker.PathJob.steps`):
each one streamed to its end is recorded, and a job cut short (a fault, a shutdown) resumes at
the cycle it was in (:func:`taught_path`'s ``first_cycle``), which starts again from its
start. The arm gets there from wherever it stopped: first :func:`lift_out` raises the bucket
tip straight up (:class:`VerticalLift`), at its attitude, to the height the cycle starts at (a
stop in the middle of a dig leaves the bucket in the ground, and a joint move would drag it
through the trench wall: 13 cm off the vertical on the field excavator), then a CONNECT move
takes it to the cycle's start pose.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime import axes, kinematics
from rt_runtime.control.planner_worker import PathJob
from rt_runtime.errors import ConfigurationError, ExcavatorRtError, PlanningError
from rt_runtime.rig import Rig
from rt_runtime.teach import TaughtJob, load_taught

__all__ = [
    "CYCLE_STEP",
    "LIFT_TOLERANCE_M",
    "TaughtMotion",
    "VerticalLift",
    "lift_out",
    "load_taught_path",
    "taught_path",
]

FloatArray = NDArray[np.float64]

#: The kind of a taught trench's steps (its cycles) in their records (a dig's ``dig_type``).
CYCLE_STEP = "cycle"

#: A held bucket tip more than this below the height the next cycle starts at is lifted to it
#: before the move to the cycle's start (m).
LIFT_TOLERANCE_M = 0.02
#: Fractions of the way up tried, in order, where the full lift is out of reach.
_LIFT_FRACTIONS = (1.0, 0.75, 0.5, 0.25)


class TaughtMotion:
    """A :class:`~rt_runtime.teach.TaughtJob`, or its stretch ``[start_s, end_s]``, as a
    :class:`~rt_runtime.control.planner_worker.JointMotion` in axis order (loop-safe sampling:
    three small vectorised evaluations). Time 0 is ``start_s``.

    Raises:
        ConfigurationError: The rig has no swing, the job is for other joints, or the stretch
            is not within the job with ``start_s < end_s``.
    """

    __slots__ = ("_perm", "end_s", "job", "start_s")

    def __init__(
        self, job: TaughtJob, rig: Rig, start_s: float = 0.0, end_s: float | None = None
    ) -> None:
        if rig.swing is None or tuple(job.joint_names) != tuple(rig.joint_names):
            raise ConfigurationError(
                f"a taught job of joints {list(job.joint_names)} cannot run on rig {rig.name} "
                f"(axes {', '.join(axes.names(rig))})"
            )
        end = job.duration_s if end_s is None else float(end_s)
        if not 0.0 <= start_s < end <= job.duration_s:
            raise ConfigurationError(
                f"taught stretch [{start_s}, {end}] s; allowed: 0 <= start < end <= "
                f"{job.duration_s} s (the trench's length)"
            )
        self.job = job
        self.start_s = float(start_s)
        self.end_s = end
        # Axis k takes joint _perm[k] of the swing-first order.
        self._perm = [1, 2, 3, 0]

    @property
    def duration_s(self) -> float:
        """The stretch's length (s)."""
        return self.end_s - self.start_s

    def sample(self, t_s: float) -> tuple[Any, Any, Any]:
        """``(q, qd, qdd)`` in axis order at ``t_s`` (rad, rad/s, rad/s^2), clamped to the
        stretch."""
        p = self._perm
        job = self.job
        t = self.start_s + min(max(t_s, 0.0), self.end_s - self.start_s)
        return job.sample(t, 0)[p], job.sample(t, 1)[p], job.sample(t, 2)[p]


class VerticalLift:
    """The bucket tip straight up from a held pose to a height, at its attitude, the swing
    still: a :class:`~rt_runtime.control.planner_worker.JointMotion` in axis order.

    The height follows a rest-to-rest ruckig profile; the joints are the closed-form inverse
    kinematics (excavator branch) of the tip on the vertical, their rates and accelerations
    the chain rule through central differences of it (``h`` = 0.1 mm). The profile's limits are
    the joint limits over the largest ``|dq/dy|`` on the way (50 heights), times ``fraction``;
    :func:`lift_out` halves ``fraction`` until a 10 ms sampling is within the joint limits.

    Args:
        rig: A rig with swing.
        q_from_rad: The held pose (axis order, rad).
        y_to_m: The tip's height to rise to (arm frame, m), above the held tip's.
        fraction: Share of the joint limits the lift may use, in (0, 1].

    Raises:
        ExcavatorRtError: A height on the way is out of reach or outside a joint's range
            (UnreachableError, JointLimitError), or ruckig cannot plan the profile.
    """

    __slots__ = ("_attitude", "_swing", "_traj", "_x", "rig", "y_from_m", "y_to_m")

    _H = 1e-4

    def __init__(self, rig: Rig, q_from_rad: Any, y_to_m: float, fraction: float = 0.5) -> None:
        from ruckig import InputParameter, Result, Ruckig, Trajectory

        self.rig = rig
        q = axes.to_joint_order(rig, np.asarray(q_from_rad, dtype=np.float64))
        x, y, attitude = (float(v) for v in kinematics.forward(rig, q[1:]))
        self._x, self._attitude, self._swing = x, attitude, float(q[0])
        self.y_from_m, self.y_to_m = y, float(y_to_m)
        heights = np.linspace(y, self.y_to_m, 50)
        slope = np.abs(self._dq(heights))  # (50, 3): |dq/dy| per arm joint
        _, _, v, a, j = axes.joint_limits(rig)  # axis order: the arm joints first
        worst = np.maximum(slope.max(axis=0), 1e-9)
        inp = InputParameter(1)
        inp.current_position = [y]
        inp.target_position = [self.y_to_m]
        inp.max_velocity = [fraction * float(np.min(v[:3] / worst))]
        inp.max_acceleration = [fraction * float(np.min(a[:3] / worst))]
        inp.max_jerk = [fraction * float(np.min(j[:3] / worst))]
        self._traj = Trajectory(1)
        if Ruckig(1).calculate(inp, self._traj) not in (Result.Working, Result.Finished):
            raise PlanningError(f"no lift profile from {y:.3f} m to {self.y_to_m:.3f} m")

    def _ik(self, y: Any) -> FloatArray:
        return kinematics.inverse(self.rig, self._x, y, self._attitude)

    def _dq(self, y: Any) -> FloatArray:
        h = self._H
        return (self._ik(np.asarray(y) + h) - self._ik(np.asarray(y) - h)) / (2.0 * h)

    @property
    def duration_s(self) -> float:
        """The lift's length (s)."""
        return float(self._traj.duration)

    def sample(self, t_s: float) -> tuple[Any, Any, Any]:
        """``(q, qd, qdd)`` in axis order at ``t_s`` (clamped to the lift)."""
        t = min(max(t_s, 0.0), self.duration_s)
        (y,), (yd,), (ydd,) = self._traj.at_time(t)
        h = self._H
        ik = self._ik(np.array([y - h, y, y + h]))
        dq = (ik[2] - ik[0]) / (2.0 * h)
        d2q = (ik[2] - 2.0 * ik[1] + ik[0]) / (h * h)
        rig = self.rig
        return (
            axes.from_joint_order(rig, np.concatenate(([self._swing], ik[1]))),
            axes.from_joint_order(rig, np.concatenate(([0.0], dq * yd))),
            axes.from_joint_order(rig, np.concatenate(([0.0], d2q * yd * yd + dq * ydd))),
        )


def _within_limits(rig: Rig, motion: VerticalLift, step_s: float = 0.01) -> bool:
    """The lift sampled every ``step_s`` keeps every joint within its velocity and acceleration
    limit (the guard bounds the jerk)."""
    _, _, v, a, _ = axes.joint_limits(rig)
    ts = np.arange(0.0, motion.duration_s + step_s, step_s)
    rows = [motion.sample(float(t)) for t in ts]
    qd = np.abs(np.array([r[1] for r in rows]))
    qdd = np.abs(np.array([r[2] for r in rows]))
    return bool((qd <= v).all() and (qdd <= a).all())


def lift_out(rig: Rig, q_to_rad: Any) -> Callable[[FloatArray], VerticalLift | None]:
    """The retreat of a taught path (:attr:`~rt_runtime.control.planner_worker.PathJob.retreat`)
    whose first motion starts at ``q_to_rad`` (axis order, rad).

    From a held pose whose bucket tip is more than :data:`LIFT_TOLERANCE_M` below the tip's
    height at ``q_to_rad``, it gives the :class:`VerticalLift` to that height; where the top is
    out of reach or outside a joint's range, to the highest of 3/4, 1/2 and 1/4 of the way up
    that is within them. None: no lift (the tip is high enough, or no lift is reachable and
    within the joint limits: the CONNECT move goes straight).
    """
    swing = rig.swing
    if swing is None:
        raise ConfigurationError(f"rig {rig.name} has no swing: a taught path needs one")
    q_to = axes.to_joint_order(rig, np.asarray(q_to_rad, dtype=np.float64))
    y_to = float(kinematics.forward(rig, q_to[1:])[1])  # arm frame

    def retreat(q_rad: FloatArray) -> VerticalLift | None:
        q = axes.to_joint_order(rig, np.asarray(q_rad, dtype=np.float64))
        y = float(kinematics.forward(rig, q[1:])[1])
        if y >= y_to - LIFT_TOLERANCE_M:
            return None
        for share in _LIFT_FRACTIONS:
            fraction = 0.5
            for _ in range(4):
                try:
                    lift = VerticalLift(rig, q_rad, y + share * (y_to - y), fraction)
                except ExcavatorRtError:
                    break
                if _within_limits(rig, lift):
                    return lift
                fraction *= 0.5
        return None

    return retreat


def taught_path(job: TaughtJob, rig: Rig, first_cycle: int = 0) -> PathJob:
    """The taught trench from cycle ``first_cycle`` (0-based) to its end as a path job of one
    motion per cycle, the cycles its steps, lifting out first (see the module docstring).

    Raises:
        ConfigurationError: ``first_cycle`` is not a cycle of the job; as :class:`TaughtMotion`.
    """
    n = job.n_cycles
    if (
        isinstance(first_cycle, bool)
        or not isinstance(first_cycle, int)
        or not 0 <= first_cycle < n
    ):
        raise ConfigurationError(
            f"taught trench: first cycle {first_cycle!r}; allowed: an integer in [0, {n - 1}]"
        )
    bounds = [*(float(t) for t in job.cycle_starts_s), job.duration_s]
    motions = tuple(TaughtMotion(job, rig, bounds[k], bounds[k + 1]) for k in range(first_cycle, n))
    name = f"taught trench ({n} cycles)"
    if first_cycle:
        name = f"taught trench (cycles {first_cycle + 1}-{n} of {n})"
    return PathJob(
        motions,
        name=name,
        jerk_by_guard=True,
        steps=True,
        first_step=first_cycle,
        step_name=CYCLE_STEP,
        retreat=lift_out(rig, motions[0].sample(0.0)[0]),
    )


def load_taught_path(
    directory: str | Path, rig: Rig, first_cycle: int = 0
) -> tuple[PathJob, TaughtJob]:
    """Load and verify ``directory``'s taught job for ``rig`` and make it a path job from
    ``first_cycle`` (:func:`taught_path`).

    Raises:
        ConfigurationError: Missing or malformed file, other joints, no such cycle (nothing
            moves).
        PlanningError: The trench breaks a limit of the rig (nothing moves).
    """
    job = load_taught(directory, rig)
    return taught_path(job, rig, first_cycle), job
