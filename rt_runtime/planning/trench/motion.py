"""Rest-to-rest joint moves within a rig's joint limits (ruckig, no intermediate waypoints:
the PyPI build sends those to a cloud service, which a rig controller must never do).

Joint angles in rad; durations in s. Used outside the control loop (planning the moves between
digs) and by the executor's connecting moves.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from rt_runtime import kinematics
from rt_runtime.errors import PlanningError
from rt_runtime.planning.trench.geometry import FloatArray
from rt_runtime.rig import Rig

_OUTLINE_STEP_M = 0.005


def joint_move(rig: Rig, q0: ArrayLike, q1: ArrayLike) -> tuple[Any, float]:
    """Time-optimal rest-to-rest joint move within the rig's joint limits (ruckig, no
    intermediate waypoints): ``(ruckig.Trajectory, duration_s)``; the transitions' motion.

    Raises:
        PlanningError: ruckig cannot plan it.
    """
    traj = _Mover(rig).move(np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64))
    return traj, float(traj.duration)


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
