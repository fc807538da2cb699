"""Forward and inverse kinematics of the excavator arm, and the tip Jacobian (Yao eq 1-4).

Planar functions work on the three arm joints ``q_rad = (theta1, theta2, theta3)`` shaped
``(..., 3)`` in the arm frame (origin at the boom foot pin, x forward, y up); every rig digs in
such a plane. The pose of the bucket tip is ``(x_m, y_m, attitude_rad)`` with
``attitude = theta1 + theta2 + theta3`` (Yao eq 2). All functions are batched over leading axes,
allocate only their outputs, and are safe to call outside the loop; ``forward`` and ``jacobian``
are cheap enough for the loop at batch size 1.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.rig import Rig

FloatArray = NDArray[np.float64]


def _arm_q(q_rad: ArrayLike) -> FloatArray:
    q = np.asarray(q_rad, dtype=np.float64)
    if q.ndim == 0 or q.shape[-1] != 3:
        raise ValueError(f"q_rad must have shape (..., 3) (boom, stick, bucket); got {q.shape}")
    return q


def absolute_angles(q_rad: ArrayLike) -> FloatArray:
    """Absolute link angles from +x: (theta1, theta1+theta2, theta1+theta2+theta3), ``(..., 3)``."""
    return np.cumsum(_arm_q(q_rad), axis=-1)


def forward(rig: Rig, q_rad: ArrayLike) -> FloatArray:
    """Bucket tip pose from the arm joint angles (Yao eq 3).

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.

    Returns:
        ``(..., 3)``: tip ``x_m``, ``y_m`` in the arm frame and ``attitude_rad``.
    """
    phi = absolute_angles(q_rad)
    lengths = rig.lengths_m
    out = np.empty(phi.shape, dtype=np.float64)
    out[..., 0] = np.cos(phi) @ lengths
    out[..., 1] = np.sin(phi) @ lengths
    out[..., 2] = phi[..., 2]
    return out


def joint_positions(rig: Rig, q_rad: ArrayLike) -> FloatArray:
    """Positions of the boom foot, stick pivot, bucket pivot and tip.

    Returns:
        ``(..., 4, 2)``: (x_m, y_m) of the four points in the arm frame.
    """
    phi = absolute_angles(q_rad)
    seg = np.stack([np.cos(phi), np.sin(phi)], axis=-1) * rig.lengths_m[:, None]
    out = np.zeros((*phi.shape[:-1], 4, 2), dtype=np.float64)
    out[..., 1:, :] = np.cumsum(seg, axis=-2)
    return out


def jacobian(rig: Rig, q_rad: ArrayLike) -> FloatArray:
    """Tip Jacobian d(x_m, y_m, attitude_rad)/d(theta1, theta2, theta3).

    Returns:
        ``(..., 3, 3)``; row i is the derivative of pose component i.
    """
    phi = absolute_angles(q_rad)
    lengths = rig.lengths_m
    # Column j moves every segment from j on: sum over k >= j of l_k * (-sin, cos)(phi_k).
    sx = np.cumsum((-np.sin(phi) * lengths)[..., ::-1], axis=-1)[..., ::-1]
    sy = np.cumsum((np.cos(phi) * lengths)[..., ::-1], axis=-1)[..., ::-1]
    jac = np.empty((*phi.shape[:-1], 3, 3), dtype=np.float64)
    jac[..., 0, :] = sx
    jac[..., 1, :] = sy
    jac[..., 2, :] = 1.0
    return jac


def tip_velocity(rig: Rig, q_rad: ArrayLike, qd_rad_s: ArrayLike) -> FloatArray:
    """Tip twist (vx_m_s, vy_m_s, omega_rad_s) from joint angles and velocities, ``(..., 3)``."""
    return np.einsum("...ij,...j->...i", jacobian(rig, q_rad), np.asarray(qd_rad_s, np.float64))
