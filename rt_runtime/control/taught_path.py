"""A taught trench (``teach --out DIR``) as a prescribed path for the executor.

Role: the one adapter between the taught job's file (:func:`rt_runtime.teach.load_taught`, joints
swing first, verified against the rig when loaded) and the control stack, whose joint vectors are
in axis order (boom, stick, bucket, swing: :mod:`rt_runtime.axes`). The HIL's ``hil --teach`` and
the daemon's taught jobs (``job submit --teach DIR``) run it the same way: one
:class:`~rt_runtime.control.planner_worker.PathJob` of one motion, the whole trench, whose jerk
the limit guard bounds (:attr:`~rt_runtime.control.planner_worker.PathJob.jerk_by_guard`: the
minimum time-jerk cycle of Zhao eq 3 is a cubic spline within the velocity and acceleration
limits, its jerk piecewise constant and not limited by its planner).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rt_runtime import axes
from rt_runtime.control.planner_worker import PathJob
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig
from rt_runtime.teach import TaughtJob, load_taught

__all__ = ["TaughtMotion", "load_taught_path", "taught_path"]


class TaughtMotion:
    """A :class:`~rt_runtime.teach.TaughtJob` as a
    :class:`~rt_runtime.control.planner_worker.JointMotion` in axis order (loop-safe sampling:
    three small vectorised evaluations).

    Raises:
        ConfigurationError: The rig has no swing, or the job is for other joints.
    """

    __slots__ = ("_perm", "job")

    def __init__(self, job: TaughtJob, rig: Rig) -> None:
        if rig.swing is None or tuple(job.joint_names) != tuple(rig.joint_names):
            raise ConfigurationError(
                f"a taught job of joints {list(job.joint_names)} cannot run on rig {rig.name} "
                f"(axes {', '.join(axes.names(rig))})"
            )
        self.job = job
        # Axis k takes joint _perm[k] of the swing-first order.
        self._perm = [1, 2, 3, 0]

    @property
    def duration_s(self) -> float:
        """The taught trench's length (s)."""
        return float(self.job.duration_s)

    def sample(self, t_s: float) -> tuple[Any, Any, Any]:
        """``(q, qd, qdd)`` in axis order at ``t_s`` (rad, rad/s, rad/s^2)."""
        p = self._perm
        job = self.job
        return job.sample(t_s, 0)[p], job.sample(t_s, 1)[p], job.sample(t_s, 2)[p]


def taught_path(job: TaughtJob, rig: Rig) -> PathJob:
    """The taught trench as a path job (see the module docstring)."""
    return PathJob(
        (TaughtMotion(job, rig),),
        name=f"taught trench ({job.n_cycles} cycles)",
        jerk_by_guard=True,
    )


def load_taught_path(directory: str | Path, rig: Rig) -> tuple[PathJob, TaughtJob]:
    """Load and verify ``directory``'s taught job for ``rig`` and make it a path job.

    Raises:
        ConfigurationError: Missing or malformed file, other joints (nothing moves).
        PlanningError: The trench breaks a limit of the rig (nothing moves).
    """
    job = load_taught(directory, rig)
    return taught_path(job, rig), job
