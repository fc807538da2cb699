"""Forward and inverse kinematics of the excavator arm and its tip Jacobian (Yao, Gao, Zhao).

Planar functions work on the three arm joints ``q_rad = (theta1, theta2, theta3)`` shaped
``(..., 3)`` in the arm frame (origin at the boom foot pin, x forward, y up); every rig digs in
such a plane, including the arm of a rig with swing. The pose of the bucket tip is
``(x_m, y_m, attitude_rad)`` with ``attitude = theta1 + theta2 + theta3`` (Yao eq 2).

Rigs with swing (``rig.swing`` set) also have 3-D functions on ``q_rad = (theta0, theta1,
theta2, theta3)`` shaped ``(..., 4)`` (Zhao eq 1). Their swing frame has its origin on the swing
axis at the D-H base of Zhao Table I (d1 below the boom foot pin), y up the axis, x forward at
theta0 = 0 and z = x cross y; theta0 is counter-clockwise seen from above, i.e. positive about
+y. Zhao's base frame (X, Y, Z) has Z up, so ``(x, y, z) = (X, Z, -Y)``. The boom foot pin sits
at ``(a1, d1, 0)`` for theta0 = 0 (``rig.swing.base_offset_m``, ``rig.swing.base_height_m``).

All functions are batched over leading axes, allocate only their outputs and temporaries, and
are safe to call outside the loop; ``forward`` and ``jacobian`` are cheap enough for the loop at
batch size 1. The inverse functions raise on unreachable targets, so they belong to planning,
not to the loop.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import ConfigurationError, JointLimitError, UnreachableError
from rt_runtime.rig import Rig, Swing

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
    v = np.einsum("...ij,...j->...i", jacobian(rig, q_rad), np.asarray(qd_rad_s, np.float64))
    return np.asarray(v, dtype=np.float64)


_TWO_PI = 2.0 * np.pi
# A pose computed by forward() at full extension or full fold lands a few ulp outside the
# boom+stick annulus; this much (relative to l1 + l2) is rounding, anything more is a miss.
_REACH_REL_TOL = 1e-9
# Likewise a solution this close outside a joint limit is a pose on the limit, not a violation.
_LIMIT_TOL_RAD = 1e-9


def _targets(values: Mapping[str, ArrayLike]) -> dict[str, FloatArray]:
    """Broadcast the named target components together as float64; reject non-finite values."""
    arrays = {name: np.asarray(v, dtype=np.float64) for name, v in values.items()}
    try:
        shaped = np.broadcast_arrays(*arrays.values())
    except ValueError as exc:
        shapes = ", ".join(f"{name} {a.shape}" for name, a in arrays.items())
        raise ValueError(f"target components must broadcast together; got {shapes}") from exc
    out = dict(zip(arrays, shaped, strict=True))
    for name, a in out.items():
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite; got {a[~np.isfinite(a)].flat[0]}")
    return out


def _describe(targets: Mapping[str, FloatArray], flat_index: int) -> str:
    """One target of a batch as text, with its batch index when there is a batch."""
    shape = next(iter(targets.values())).shape
    values = ", ".join(f"{name}={a.flat[flat_index]:.6g}" for name, a in targets.items())
    if not shape:
        return f"target ({values})"
    index = tuple(int(i) for i in np.unravel_index(flat_index, shape))
    return f"target ({values}) at batch index {index}"


def _wrap_to_range(q: FloatArray, q_min: FloatArray, q_max: FloatArray) -> FloatArray:
    """Representative of ``q`` modulo 2*pi in the 2*pi window centred on ``[q_min, q_max]``.

    That window holds the whole range, and a value outside the range lands on the side it is
    nearer to: a bucket range of -160..5 deg turns +190 deg into -170 deg, not +190.
    Values already in the window come back bit-identical.
    """
    low = 0.5 * (q_min + q_max) - np.pi
    return q - _TWO_PI * np.floor((q - low) / _TWO_PI)


def _enforce_limits(
    q: FloatArray,
    q_min: FloatArray,
    q_max: FloatArray,
    names: tuple[str, ...],
    targets: Mapping[str, FloatArray],
) -> FloatArray:
    """Raise for the first joint outside its limits; clip rounding-sized excursions onto them."""
    bad = (q < q_min - _LIMIT_TOL_RAD) | (q > q_max + _LIMIT_TOL_RAD)
    if np.any(bad):
        rows = bad.reshape(-1, q.shape[-1])
        i = int(np.argmax(rows.any(axis=-1)))
        j = int(np.argmax(rows[i]))
        err = JointLimitError(
            names[j], float(q.reshape(-1, q.shape[-1])[i, j]), float(q_min[j]), float(q_max[j])
        )
        err.add_note(f"inverse kinematics of {_describe(targets, i)}")
        raise err
    return np.clip(q, q_min, q_max)


def _solve_arm(
    rig: Rig,
    x_m: FloatArray,
    y_m: FloatArray,
    attitude_rad: FloatArray,
    targets: Mapping[str, FloatArray],
) -> FloatArray:
    """Planar IK on the excavator branch, neither wrapped nor checked against limits.

    ``targets`` only serves the error message (the caller's own coordinates).
    """
    l1, l2, l3 = (float(v) for v in rig.lengths_m)
    q, r = _arm_angles(l1, l2, l3, x_m, y_m, attitude_rad)
    outer = l1 + l2
    inner = abs(l1 - l2)
    tol = _REACH_REL_TOL * outer
    miss = (r > outer + tol) | (r < inner - tol)
    if np.any(miss):
        i = int(np.argmax(miss.reshape(-1)))
        raise UnreachableError(
            f"bucket pivot of {_describe(targets, i)} is {float(r.flat[i]):.6g} m from the boom "
            f"foot pin; boom and stick reach [{inner:.6g}, {outer:.6g}] m"
        )
    return q


def _arm_angles(
    l1: float, l2: float, l3: float, x_m: FloatArray, y_m: FloatArray, attitude_rad: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Excavator-branch joint angles ``(..., 3)``, neither wrapped nor checked, and the bucket
    pivot's distance r from the boom foot pin (the angles mean nothing where r is outside the
    annulus ``[|l1 - l2|, l1 + l2]``; they are finite there).
    """
    pivot_x = x_m - l3 * np.cos(attitude_rad)
    pivot_y = y_m - l3 * np.sin(attitude_rad)
    r = np.hypot(pivot_x, pivot_y)
    outer = l1 + l2
    inner = abs(l1 - l2)
    # Law of cosines in half-angle form: tan^2(theta2 / 2) = ((l1+l2)^2 - r^2) / (r^2 - (l1-l2)^2).
    # The factored differences stay exact near full extension and full fold, where acos of the
    # cosine loses half the digits; clipping only absorbs a tolerance the caller admits.
    far = np.sqrt(np.maximum((outer - r) * (outer + r), 0.0))
    near = np.sqrt(np.maximum((r - inner) * (r + inner), 0.0))
    theta2 = -2.0 * np.arctan2(far, near)
    elbow = np.arctan2(l2 * np.sin(theta2), l1 + l2 * np.cos(theta2))
    theta1 = np.arctan2(pivot_y, pivot_x) - elbow
    q = np.empty((*r.shape, 3), dtype=np.float64)
    q[..., 0] = theta1
    q[..., 1] = theta2
    q[..., 2] = attitude_rad - theta1 - theta2
    return q, r


def inverse(
    rig: Rig,
    x_m: ArrayLike,
    y_m: ArrayLike,
    attitude_rad: ArrayLike,
    *,
    check_limits: bool = True,
) -> FloatArray:
    """Arm joint angles that put the bucket tip at a pose (closed form; Yao eq 4, Gao eq 4).

    The bucket pivot is ``tip - l3 * (cos, sin)(attitude)``; boom and stick then form a
    two-link arm reaching it. Of its two solutions this returns the excavator branch
    ``theta2 in [-pi, 0]`` (Yao eq 4: theta2 = angle O1 O2 O3 - pi): the stick folds clockwise
    from the boom, so the boom-stick joint lies above the line from the boom foot to the bucket
    pivot. (Gao eq 4 prints ``2 a1 a1`` where ``2 a1 a2`` belongs; this derivation, half-angle
    law of cosines plus atan2, does not use it.) A rig whose stick range
    reaches above 0 (the scale model's, to +10 deg) has poses only the other branch reaches
    within limits; for those this returns the mirrored configuration.

    Angles come back wrapped into the 2*pi window centred on each joint's range, so a value
    outside the range is the representative nearest to it (bucket -160..5 deg: -170, not +190).

    Args:
        rig: The rig (a swing rig's arm joints, in its arm plane).
        x_m: Tip x in the arm frame; broadcasts with the others.
        y_m: Tip y in the arm frame.
        attitude_rad: Tip attitude theta1 + theta2 + theta3 (any multiple of 2*pi).
        check_limits: Raise for a solution outside the joint limits. Values within 1e-9 rad
            outside a limit count as on it and are clipped onto it.

    Returns:
        ``(..., 3)`` joint angles (boom, stick, bucket), ``...`` the broadcast input shape.

    Raises:
        UnreachableError: A bucket pivot lies outside the annulus ``[|l1 - l2|, l1 + l2]``
            (beyond a 1e-9 relative tolerance); names the first such target, its batch index,
            the distance and the reachable range.
        JointLimitError: With ``check_limits``, the first target (in C order) whose solution
            leaves a joint's range; names that joint, and a note gives the target and index.
        ValueError: Inputs that do not broadcast, or are not finite.
    """
    targets = _targets({"x_m": x_m, "y_m": y_m, "attitude_rad": attitude_rad})
    q = _solve_arm(rig, targets["x_m"], targets["y_m"], targets["attitude_rad"], targets)
    q = _wrap_to_range(q, rig.q_min_rad, rig.q_max_rad)
    if check_limits:
        names = tuple(j.name for j in rig.joints)
        q = _enforce_limits(q, rig.q_min_rad, rig.q_max_rad, names, targets)
    return q


class FastArm:
    """The planar arm's kinematics for hot paths (planners screening thousands of poses).

    The formulas of :func:`inverse` (excavator branch, angles wrapped into each joint's 2 pi
    window) and :func:`forward`, scalar and batched, without their input validation and error
    reporting: an unreachable or out-of-limit pose gives None (scalar) or a False flag (batch)
    instead of an exception. About 6 us per scalar IK against ~40 us for :func:`inverse`.
    Answers agree with those functions to rounding (tested).

    Args:
        rig: The rig (its arm; a swing rig's arm plane).
    """

    def __init__(self, rig: Rig) -> None:
        self.l1, self.l2, self.l3 = (float(v) for v in rig.lengths_m)
        self.lengths = np.asarray(rig.lengths_m, dtype=np.float64)
        self.q_min = np.asarray(rig.q_min_rad, dtype=np.float64)
        self.q_max = np.asarray(rig.q_max_rad, dtype=np.float64)
        self.low = 0.5 * (self.q_min + self.q_max) - math.pi
        self._lim = [
            (float(a), float(b), float(c))
            for a, b, c in zip(self.q_min, self.q_max, self.low, strict=True)
        ]
        self.outer = self.l1 + self.l2
        self.inner = abs(self.l1 - self.l2)

    def ik(self, x: float, y: float, attitude: float) -> tuple[float, float, float] | None:
        """Joint angles of one tip pose, or None when out of reach or out of the limits."""
        l1, l2 = self.l1, self.l2
        px = x - self.l3 * math.cos(attitude)
        py = y - self.l3 * math.sin(attitude)
        r = math.hypot(px, py)
        if not self.inner + 1e-9 < r < self.outer - 1e-9:
            return None
        far = math.sqrt(max((self.outer - r) * (self.outer + r), 0.0))
        near = math.sqrt(max((r - self.inner) * (r + self.inner), 0.0))
        t2 = -2.0 * math.atan2(far, near)
        t1 = math.atan2(py, px) - math.atan2(l2 * math.sin(t2), l1 + l2 * math.cos(t2))
        out = []
        for q, (lo, hi, low) in zip((t1, t2, attitude - t1 - t2), self._lim, strict=True):
            q -= 2.0 * math.pi * math.floor((q - low) / (2.0 * math.pi))
            if not lo - 1e-9 <= q <= hi + 1e-9:
                return None
            out.append(min(max(q, lo), hi))
        return (out[0], out[1], out[2])

    def ik_many(
        self, x: FloatArray, y: FloatArray, attitude: FloatArray
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Joint angles of many poses ``(N, 3)`` and which are reachable within the limits."""
        q, r = _arm_angles(self.l1, self.l2, self.l3, x, y, attitude)
        reach = (r < self.outer - 1e-9) & (r > self.inner + 1e-9)
        q = _wrap_to_range(q, self.q_min, self.q_max)
        ok = reach & np.all((q >= self.q_min) & (q <= self.q_max), axis=1)
        return q, ok

    def tip_xy(self, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Tip x and y of joint angles ``(..., 3)``."""
        p0 = q[..., 0]
        p1 = p0 + q[..., 1]
        p2 = p1 + q[..., 2]
        x = self.l1 * np.cos(p0) + self.l2 * np.cos(p1) + self.l3 * np.cos(p2)
        y = self.l1 * np.sin(p0) + self.l2 * np.sin(p1) + self.l3 * np.sin(p2)
        return x, y

    def tip(self, q: tuple[float, float, float] | FloatArray) -> tuple[float, float, float]:
        """Tip pose (x, y, attitude) of one joint pose."""
        p0 = float(q[0])
        p1 = p0 + float(q[1])
        p2 = p1 + float(q[2])
        return (
            self.l1 * math.cos(p0) + self.l2 * math.cos(p1) + self.l3 * math.cos(p2),
            self.l1 * math.sin(p0) + self.l2 * math.sin(p1) + self.l3 * math.sin(p2),
            p2,
        )


def _swing(rig: Rig, function: str) -> Swing:
    if rig.swing is None:
        raise ConfigurationError(
            f"{function} needs a rig with a swing joint; rig {rig.name!r} is planar "
            "(3 DOF): use the planar functions, or a profile with a [swing] table"
        )
    return rig.swing


def forward_3d(rig: Rig, q_rad: ArrayLike) -> FloatArray:
    """Bucket tip pose in the swing frame from swing and arm joint angles (Zhao eq 1).

    Args:
        rig: A rig with swing.
        q_rad: ``(..., 4)``: theta0 (swing), theta1, theta2, theta3.

    Returns:
        ``(..., 4)``: tip ``x_m``, ``y_m`` (up), ``z_m`` in the swing frame (see the module
        docstring) and ``attitude_rad`` = theta1 + theta2 + theta3.

    Raises:
        ConfigurationError: The rig has no swing joint.
        ValueError: ``q_rad`` is not shaped ``(..., 4)``.
    """
    swing = _swing(rig, "forward_3d")
    q = np.asarray(q_rad, dtype=np.float64)
    if q.ndim == 0 or q.shape[-1] != 4:
        raise ValueError(
            f"q_rad must have shape (..., 4) (swing, boom, stick, bucket); got {q.shape}"
        )
    arm = forward(rig, q[..., 1:])
    radial = swing.base_offset_m + arm[..., 0]
    out = np.empty(q.shape, dtype=np.float64)
    out[..., 0] = radial * np.cos(q[..., 0])
    out[..., 1] = swing.base_height_m + arm[..., 1]
    out[..., 2] = -radial * np.sin(q[..., 0])
    out[..., 3] = arm[..., 2]
    return out


def inverse_3d(
    rig: Rig,
    x_m: ArrayLike,
    y_m: ArrayLike,
    z_m: ArrayLike,
    attitude_rad: ArrayLike,
    *,
    check_limits: bool = True,
) -> FloatArray:
    """Swing and arm joint angles that put the bucket tip at a pose in the swing frame.

    The swing angle turns the arm plane through the tip: ``theta0 = atan2(-z, x)``, with the
    tip in front of the swing axis (its horizontal distance from the axis along the arm's
    heading is >= 0). A tip the arm could also reach folded back over the axis (theta0 + pi,
    tip behind the boom foot by more than a1) comes back as the front solution, or as
    UnreachableError when the front one does not exist. On the axis itself every swing angle
    solves and 0 is returned. The arm angles are those of :func:`inverse` (excavator branch,
    wrapped to the ranges) at arm-frame ``(hypot(x, z) - a1, y - d1)``.

    Args:
        rig: A rig with swing.
        x_m, y_m, z_m: Tip position in the swing frame; broadcast together.
        attitude_rad: Tip attitude theta1 + theta2 + theta3.
        check_limits: As for :func:`inverse`; the swing joint is checked first.

    Returns:
        ``(..., 4)``: theta0 (swing), theta1, theta2, theta3.

    Raises:
        ConfigurationError: The rig has no swing joint.
        UnreachableError: As for :func:`inverse`.
        JointLimitError: As for :func:`inverse` (joint ``swing`` included).
        ValueError: Inputs that do not broadcast, or are not finite.
    """
    swing = _swing(rig, "inverse_3d")
    targets = _targets({"x_m": x_m, "y_m": y_m, "z_m": z_m, "attitude_rad": attitude_rad})
    x, z = targets["x_m"], targets["z_m"]
    radial = np.hypot(x, z)
    q_min = np.concatenate(([swing.joint.min_rad], rig.q_min_rad))
    q_max = np.concatenate(([swing.joint.max_rad], rig.q_max_rad))
    q = np.empty((*radial.shape, 4), dtype=np.float64)
    q[..., 0] = np.where(radial > 0.0, np.arctan2(-z, x), 0.0)
    q[..., 1:] = _solve_arm(
        rig,
        radial - swing.base_offset_m,
        targets["y_m"] - swing.base_height_m,
        targets["attitude_rad"],
        targets,
    )
    q = _wrap_to_range(q, q_min, q_max)
    if check_limits:
        q = _enforce_limits(q, q_min, q_max, rig.joint_names, targets)
    return q


def tip_state(rig: Rig, q_rad: ArrayLike, qd_rad_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Tip pose and twist together, sharing the trigonometry (the planners' hot path).

    Equals ``(forward(rig, q), tip_velocity(rig, q, qd))`` at about a third of the cost: the
    twist is sum_k l_k (-sin, cos)(phi_k) * phi_dot_k with phi_dot the cumulative joint rates.

    Returns:
        ``(pose (..., 3), twist (..., 3))``: (x_m, y_m, attitude_rad) and
        (vx_m_s, vy_m_s, omega_rad_s).
    """
    phi = absolute_angles(q_rad)
    phid = np.cumsum(np.asarray(qd_rad_s, dtype=np.float64), axis=-1)
    lengths = rig.lengths_m
    lc = np.cos(phi) * lengths
    ls = np.sin(phi) * lengths
    pose = np.empty(phi.shape, dtype=np.float64)
    twist = np.empty(np.broadcast_shapes(phi.shape, phid.shape), dtype=np.float64)
    pose[..., 0] = lc.sum(axis=-1)
    pose[..., 1] = ls.sum(axis=-1)
    pose[..., 2] = phi[..., 2]
    twist[..., 0] = -(ls * phid).sum(axis=-1)
    twist[..., 1] = (lc * phid).sum(axis=-1)
    twist[..., 2] = phid[..., 2]
    return pose, twist
