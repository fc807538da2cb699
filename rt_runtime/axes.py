"""The drive axes of a rig: joint angles <-> actuator positions, in bus (axis) order, batched.

Role: the one map between the joints the controllers plan and the positions the drives are
commanded and report. Every rig has the three arm axes, driven by cylinders: their actuator
position is the cylinder stroke (m, :mod:`rt_runtime.actuation`). A rig with swing
(``rig.swing`` set) has a fourth axis, the swing, driven by a rotary drive on node 4 (DESIGN.md
"CAN protocol"): its actuator position is the swing angle itself (rad), so its map is the
identity. The bus carries every actuator position in millionths of its SI unit (micrometres of
stroke, microradians of swing) in the same RPDO1/TPDO1 objects.

Axis order is the bus order of the drives, ``boom, stick, bucket`` then ``swing``: the arm's
three axes keep their indices 0-2 on every rig and the swing is appended as index 3. This differs
from the joint order of :mod:`rt_runtime.kinematics` and the trajectory generators on a rig with
swing (swing first, Zhao eq 1); :func:`from_joint_order` and :func:`to_joint_order` convert.
Every array here is in axis order unless its name says otherwise.

All functions are pure and take leading batch axes ``(..., n)`` with ``n`` :func:`count`; with
``check_limits=False`` they are safe in the loop at small batch sizes.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime import actuation
from rt_runtime.errors import JointLimitError, KinematicsError
from rt_runtime.rig import Rig

__all__ = [
    "ARM_AXES",
    "SWING",
    "SWING_FOLLOWING_ERROR_WINDOW_RAD",
    "actuator_jacobian",
    "actuator_limits",
    "actuator_to_joint",
    "actuator_velocity_max",
    "count",
    "from_joint_order",
    "joint_limits",
    "joint_to_actuator",
    "names",
    "to_joint_order",
    "units",
]

FloatArray = NDArray[np.float64]

#: The arm's axes, indices 0-2 on every rig.
ARM_AXES = ("boom", "stick", "bucket")
#: The swing axis's name (index 3 on a rig with swing).
SWING = "swing"
_SWING_TOL_RAD = 1e-9
#: The swing drive's following-error window (rad): ten times the swing's 0.3 deg tracking goal,
#: as the cylinders' window is ten times their 3 mm goal.
SWING_FOLLOWING_ERROR_WINDOW_RAD = math.radians(3.0)


def names(rig: Rig) -> tuple[str, ...]:
    """Axis names in bus order: the arm's three, then ``swing`` where the rig has one."""
    return (*ARM_AXES, SWING) if rig.swing is not None else ARM_AXES


def count(rig: Rig) -> int:
    """Number of drive axes: 3 (planar) or 4 (with swing)."""
    return 4 if rig.swing is not None else 3


def units(rig: Rig) -> tuple[str, ...]:
    """The SI unit of each axis's actuator position: ``m`` (stroke) or ``rad`` (swing)."""
    return ("m", "m", "m", "rad") if rig.swing is not None else ("m", "m", "m")


def joint_limits(rig: Rig) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """``(q_min, q_max, qd_max, qdd_max, qddd_max)`` per axis in axis order (rad, rad/s, ...)."""
    arrays = [
        np.asarray(a, dtype=np.float64)
        for a in (
            rig.q_min_rad,
            rig.q_max_rad,
            rig.qd_max_rad_s,
            rig.qdd_max_rad_s2,
            rig.qddd_max_rad_s3,
        )
    ]
    if rig.swing is not None:
        j = rig.swing.joint
        extra = (
            j.min_rad,
            j.max_rad,
            j.velocity_max_rad_s,
            j.acceleration_max_rad_s2,
            j.jerk_max_rad_s3,
        )
        arrays = [np.append(a, v) for a, v in zip(arrays, extra, strict=True)]
    a0, a1, a2, a3, a4 = arrays
    return a0, a1, a2, a3, a4


def actuator_limits(rig: Rig) -> tuple[FloatArray, FloatArray]:
    """Travel of every actuator ``(lo, hi)``, each ``(n,)``: the cylinder travel (m), then the
    swing's joint range (rad)."""
    lo, hi = actuation.stroke_limits(rig)
    if rig.swing is not None:
        j = rig.swing.joint
        return np.append(lo, j.min_rad), np.append(hi, j.max_rad)
    return lo, hi


def actuator_velocity_max(rig: Rig) -> FloatArray:
    """Largest actuator speed per axis ``(n,)``: the cylinders' ``velocity_max_m_s`` (m/s),
    then the swing's joint velocity limit (rad/s)."""
    v = np.full(3, rig.actuators.velocity_max_m_s)
    if rig.swing is not None:
        return np.append(v, rig.swing.joint.velocity_max_rad_s)
    return v


def _split(rig: Rig, x: ArrayLike, name: str) -> tuple[FloatArray, FloatArray | None]:
    a = np.asarray(x, dtype=np.float64)
    n = count(rig)
    if a.ndim < 1 or a.shape[-1] != n:
        raise ValueError(
            f"{name} must have shape (..., {n}) ({', '.join(names(rig))}); got {a.shape}"
        )
    if n == 3:
        return a, None
    return a[..., :3], a[..., 3]


def _check_swing(rig: Rig, theta0: FloatArray) -> None:
    assert rig.swing is not None
    j = rig.swing.joint
    bad = ~((theta0 >= j.min_rad - _SWING_TOL_RAD) & (theta0 <= j.max_rad + _SWING_TOL_RAD))
    if bad.any():
        value = float(np.asarray(theta0).reshape(-1)[int(np.flatnonzero(bad.reshape(-1))[0])])
        raise JointLimitError(SWING, value, j.min_rad, j.max_rad)


def joint_to_actuator(rig: Rig, q_rad: ArrayLike, *, check_limits: bool = True) -> FloatArray:
    """Actuator positions from joint angles, both in axis order ``(..., n)``.

    Raises:
        ValueError: ``q_rad`` is not shaped ``(..., n)``.
        JointLimitError: A joint outside its limits (only with ``check_limits``).
    """
    arm, swing = _split(rig, q_rad, "q_rad")
    s = actuation.joint_to_stroke(rig, arm, check_limits=check_limits)
    if swing is None:
        return s
    if check_limits:
        _check_swing(rig, swing)
    return np.concatenate([s, swing[..., None]], axis=-1)


def actuator_to_joint(rig: Rig, position: ArrayLike, *, check_limits: bool = True) -> FloatArray:
    """Joint angles from actuator positions, both in axis order ``(..., n)``.

    Raises:
        ValueError: ``position`` is not shaped ``(..., n)``.
        KinematicsError: A stroke outside its travel or a swing angle outside its range (only
            with ``check_limits``).
    """
    arm, swing = _split(rig, position, "position")
    q = actuation.stroke_to_joint(rig, arm, check_limits=check_limits)
    if swing is None:
        return q
    if check_limits:
        try:
            _check_swing(rig, swing)
        except JointLimitError as exc:
            raise KinematicsError(f"swing drive position: {exc}") from exc
    return np.concatenate([q, swing[..., None]], axis=-1)


def actuator_jacobian(rig: Rig, q_rad: ArrayLike, *, check_limits: bool = True) -> FloatArray:
    """Diagonal of d actuator / d joint ``(..., n)``: the stroke slopes (m/rad), 1 for swing."""
    arm, swing = _split(rig, q_rad, "q_rad")
    j = actuation.stroke_jacobian(rig, arm, check_limits=check_limits)
    if swing is None:
        return j
    if check_limits:
        _check_swing(rig, swing)
    return np.concatenate([j, np.ones_like(swing)[..., None]], axis=-1)


def from_joint_order(rig: Rig, q: ArrayLike) -> FloatArray:
    """Joint-order values (swing first on a rig with swing, as kinematics) in axis order."""
    a = np.asarray(q, dtype=np.float64)
    if rig.swing is None:
        return a
    if a.shape[-1] != 4:
        raise ValueError(f"joint-order values of a rig with swing have 4 columns; got {a.shape}")
    return np.concatenate([a[..., 1:], a[..., :1]], axis=-1)


def to_joint_order(rig: Rig, q: ArrayLike) -> FloatArray:
    """Axis-order values in joint order (swing first on a rig with swing)."""
    a = np.asarray(q, dtype=np.float64)
    if rig.swing is None:
        return a
    if a.shape[-1] != 4:
        raise ValueError(f"axis-order values of a rig with swing have 4 columns; got {a.shape}")
    return np.concatenate([a[..., 3:], a[..., :3]], axis=-1)


def degrees_text(rig: Rig, q_rad: ArrayLike) -> str:
    """``name value`` pairs in degrees, axis order (for messages)."""
    q = np.asarray(q_rad, dtype=np.float64).reshape(-1)
    return ", ".join(f"{n} {math.degrees(v):.2f}" for n, v in zip(names(rig), q, strict=False))
