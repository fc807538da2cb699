"""Joint angles <-> cylinder strokes (Yang, Gao et al. 2023, eq 5-13), batched.

Role: the drive-space side of the arm. The executor turns sampled joint trajectories into
cylinder stroke and stroke-rate setpoints (:func:`joint_to_stroke`, :func:`stroke_velocity`);
the HIL maps drive feedback back (:func:`stroke_to_joint`, :func:`joint_velocity`) and drives the
arm with cylinder forces (:func:`torque_from_force`); the rig loader calls
:func:`validate_cylinders` so that no profile whose cylinders cannot cover its joint ranges loads.

Stroke is the cylinder's pin-to-pin length minus its retracted length: 0 fully retracted,
``stroke_max_m`` fully extended. Each stroke depends on its own joint only, so every Jacobian
here is diagonal and returned as its diagonal ``(..., 3)`` (boom, stick, bucket). The directions
are those of Gao Fig. 4: the boom stroke grows with theta1, the stick stroke grows as theta2
decreases, the bucket stroke grows as theta3 decreases.

Boom and stick (Gao eq 5-8). The cylinder is the third side of a triangle whose other sides are
the pin distances ``a``, ``b`` from the joint axis::

    L = sqrt(a^2 + b^2 - 2 a b cos(phi)),   phi = sign * theta + offset

with ``sign = +1`` for the boom (eq 6: phi = theta1 + BAX + CAD) and ``-1`` for the stick (eq 8:
phi = pi - theta2 - ADE - FDG). The validation keeps phi inside (0, pi) over the whole cylinder
travel, so L is strictly monotonic and its inverse unique. The inverse uses the half-angle form
tan^2(phi/2) = (L^2 - (a-b)^2) / ((a+b)^2 - L^2), which keeps full precision near the ends of the
travel where arccos loses digits.

Bucket (Gao eq 9-13). The cylinder H-J drives the four-bar G-I-J-K: ground G-I on the stick,
rocker I-J, link J-K, bucket lever G-K. Points are worked in the stick frame shifted to G (x from
the stick pivot D towards G, y its counter-clockwise normal, the side the bucket cylinder is on).
Gao Fig. 3 is not available, so the side each printed angle opens to is fixed here, chosen so
that Gao eq 10 and the first line of eq 13 hold as printed:

* ray G->I is ray G->D turned clockwise by IGD: I = l_IG (-cos IGD, sin IGD);
* ray I->H is ray I->G turned counter-clockwise by HIG (measured through J, so it may exceed
  180 deg; HIJ = HIG - JIG, eq 10);
* ray G->K is the bucket axis G->L (at theta3) turned counter-clockwise by LGK, hence the angle
  from G->K counter-clockwise to G->I is IGK = pi - IGD - LGK - theta3 (eq 13).

The assembly branch is the backhoe layout: J lies left of the directed line I->K, clockwise of H
seen from I, and K clockwise of J seen from G. Each of these sides can change only where H-I-J,
I-J-K or G-K-J become collinear (the linkage's dead points), which the validation keeps out of the
travel, so one fixed branch serves every stroke. Forward: K = l_GK e(theta3 + LGK); J is the
intersection of the circles (I, l_IJ) and (K, l_JK) on that branch; L = |HJ|. Inverse: |HJ| gives
the angle HIJ (eq 9), hence the rocker angle and J (eq 10); the circles (G, l_GK) and (J, l_JK)
give K (eq 11-12) and theta3 (eq 13). The printed equations carry typos (eq 9 and 13: L_II for
L_IJ, and L_HI for L_HJ inside eq 13; eq 11: 2 L_IG L_IG for 2 L_IG L_JG), and eq 13 chains
unsigned arccos terms IGK = IGJ + JGK, which assumes ray G->J lies inside the angle IGK; over
bucket ranges near 180 deg that fails, so angles here come from atan2 of points instead.

Dead points. The stroke rate is ds/dtheta3 = dL/dpsi * dpsi/dtheta3 with psi the rocker angle;
dL/dpsi vanishes when H, I, J are collinear, dpsi/dtheta3 vanishes when G, K, J are and becomes
infinite when I, J, K are. :func:`transmission_angles_rad` reports the three angles (HJI, IJK,
GKJ); the validation requires each within [20, 160] deg over the travel, the usual
transmission-angle rule for linkages that must carry load.

Limits. With ``check_limits=True`` (the default) a joint outside the rig's limits raises
:class:`~rt_runtime.errors.JointLimitError` and a stroke outside ``[0, stroke_max_m]`` raises
:class:`~rt_runtime.errors.KinematicsError`, both naming the axis. The cylinder travel covers the
joint range with a small margin, so a stroke inside the travel may map to a joint angle just
beyond the joint limits. With ``check_limits=False`` nothing is checked; wherever the geometry
still assembles the mapping is exact, elsewhere the result is NaN. That is the mode for the HIL
and for the fixed-rate loop, which must not use exceptions as control flow.

All functions are pure, allocate only their outputs and temporaries, and are safe in the loop at
small batch sizes with ``check_limits=False``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import JointLimitError, KinematicsError, RigProfileError
from rt_runtime.rig import Rig
from rt_runtime.rig.cylinders import BucketLinkage, PinCylinder

FloatArray = NDArray[np.float64]

AXES: tuple[str, str, str] = ("boom", "stick", "bucket")

#: Smallest distance of the boom and stick triangles' included angle from 0 and pi over the
#: cylinder travel. The moment arm a b sin(phi) / L vanishes at both; 2 deg keeps the inverse
#: well conditioned while admitting the scale model's 170 deg stick range.
INCLUDED_ANGLE_MARGIN_RAD: float = math.radians(2.0)

#: Smallest allowed transmission angle of the bucket linkage (and 180 deg minus it the largest).
TRANSMISSION_ANGLE_MIN_RAD: float = math.radians(20.0)

# Assembly branch of the backhoe layout (see the module docstring): the sign of the turn from
# the known ray to the solved one.
_BRANCH_J_FROM_IK = 1.0  # J left of I->K
_BRANCH_J_FROM_IH = -1.0  # J clockwise of H, seen from I
_BRANCH_K_FROM_GJ = -1.0  # K clockwise of J, seen from G

# A value this close outside a limit is the limit reached through rounding, not a violation.
_LIMIT_TOL_RAD = 1e-9
_LIMIT_TOL_M = 1e-12

# Joint-angle samples per range for the loader's dead-point check (0.25 deg steps on 180 deg).
_CHECK_SAMPLES = 721


@dataclass(frozen=True, slots=True)
class LinkagePoints:
    """Pin positions of the bucket linkage in the stick link frame (origin D, x towards G).

    Each field has shape ``(..., 2)`` holding (x_m, y_m).

    Attributes:
        g_m: Bucket pivot G (fixed at (l2, 0)).
        h_m: Bucket-cylinder base pin H on the stick (fixed).
        i_m: Rocker pivot I on the stick (fixed).
        j_m: Rocker/link/cylinder-rod joint J.
        k_m: Link pin K on the bucket.
    """

    g_m: FloatArray
    h_m: FloatArray
    i_m: FloatArray
    j_m: FloatArray
    k_m: FloatArray


@dataclass(frozen=True, slots=True)
class _Linkage:
    """The bucket linkage's fixed points, in the stick frame shifted to G, as plain floats."""

    i_x: float
    i_y: float
    h_x: float
    h_y: float
    alpha_ih: float  # direction of ray I->H
    l_hi: float
    l_ij: float
    l_jk: float
    l_gk: float
    lgk: float
    wrap_low: float  # theta3 results are reported in [wrap_low, wrap_low + 2 pi)


def _linkage(rig: Rig) -> _Linkage:
    b: BucketLinkage = rig.cylinders.bucket
    i_x = -b.l_ig_m * math.cos(b.angle_igd_rad)
    i_y = b.l_ig_m * math.sin(b.angle_igd_rad)
    alpha_ih = math.atan2(-i_y, -i_x) + b.angle_hig_rad
    joint = rig.joints[2]
    return _Linkage(
        i_x=i_x,
        i_y=i_y,
        h_x=i_x + b.l_hi_m * math.cos(alpha_ih),
        h_y=i_y + b.l_hi_m * math.sin(alpha_ih),
        alpha_ih=alpha_ih,
        l_hi=b.l_hi_m,
        l_ij=b.l_ij_m,
        l_jk=b.l_jk_m,
        l_gk=b.l_gk_m,
        lgk=b.angle_lgk_rad,
        # The 2 pi window centred on the joint range holds the range and the travel beyond it.
        wrap_low=0.5 * (joint.min_rad + joint.max_rad) - math.pi,
    )


def _triangle_angle(
    side_1: FloatArray | float, side_2: FloatArray | float, opposite: FloatArray | float
) -> FloatArray:
    """Angle between sides 1 and 2 of a triangle, in [0, pi]; NaN where it cannot close.

    Half-angle form tan^2(x/2) = (c^2 - (a-b)^2) / ((a+b)^2 - c^2) in factored differences:
    exact to rounding near 0 and pi, where arccos of the cosine rule loses half the digits.
    """
    diff = np.subtract(side_1, side_2)
    total = np.add(side_1, side_2)
    with np.errstate(invalid="ignore"):
        num = np.sqrt((opposite - diff) * (opposite + diff))
        den = np.sqrt((total - opposite) * (total + opposite))
    return np.asarray(2.0 * np.arctan2(num, den), dtype=np.float64)


def _pin_length(c: PinCylinder, theta: FloatArray) -> FloatArray:
    """Pin-to-pin length of a boom or stick cylinder (Gao eq 6, 8)."""
    phi = c.angle_sign * theta + c.angle_offset_rad
    ab = c.pin_a_m * c.pin_b_m
    return np.sqrt(c.pin_a_m**2 + c.pin_b_m**2 - 2.0 * ab * np.cos(phi))


def _pin_slope(c: PinCylinder, theta: FloatArray) -> FloatArray:
    """d L / d theta of a boom or stick cylinder: sign * a b sin(phi) / L, the moment arm."""
    phi = c.angle_sign * theta + c.angle_offset_rad
    ab = c.pin_a_m * c.pin_b_m
    length = np.sqrt(c.pin_a_m**2 + c.pin_b_m**2 - 2.0 * ab * np.cos(phi))
    return (c.angle_sign * ab) * np.sin(phi) / length


def _pin_angle(c: PinCylinder, length: FloatArray) -> FloatArray:
    """Joint angle of a boom or stick cylinder at a pin-to-pin length (phi taken in [0, pi])."""
    phi = _triangle_angle(c.pin_a_m, c.pin_b_m, length)
    return np.asarray(c.angle_sign * (phi - c.angle_offset_rad), dtype=np.float64)


def _bucket_points(
    k: _Linkage, theta3: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """K and J (x, y each, frame at G) and the rocker angle psi for bucket angles theta3."""
    gamma = theta3 + k.lgk
    k_x = k.l_gk * np.cos(gamma)
    k_y = k.l_gk * np.sin(gamma)
    d_x = k_x - k.i_x
    d_y = k_y - k.i_y
    beta = _triangle_angle(k.l_ij, np.hypot(d_x, d_y), k.l_jk)
    psi = np.arctan2(d_y, d_x) + _BRANCH_J_FROM_IK * beta
    j_x = k.i_x + k.l_ij * np.cos(psi)
    j_y = k.i_y + k.l_ij * np.sin(psi)
    return k_x, k_y, j_x, j_y, psi


def _cylinder_hj(k: _Linkage, psi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Signed angle HIJ (Gao eq 10) and the cylinder length |HJ| (eq 9) at rocker angle psi."""
    hij = k.alpha_ih - psi
    return hij, np.sqrt(k.l_hi**2 + k.l_ij**2 - 2.0 * k.l_hi * k.l_ij * np.cos(hij))


def _bucket_length(k: _Linkage, theta3: FloatArray) -> FloatArray:
    """Bucket-cylinder length |HJ| at bucket angles theta3."""
    return _cylinder_hj(k, _bucket_points(k, theta3)[4])[1]


def _bucket_slope(k: _Linkage, theta3: FloatArray) -> FloatArray:
    """d|HJ| / d theta3 of the bucket linkage."""
    k_x, k_y, j_x, j_y, psi = _bucket_points(k, theta3)
    hij, length = _cylinder_hj(k, psi)
    dlength_dpsi = -k.l_hi * k.l_ij * np.sin(hij) / length
    # d/dt |J - K|^2 = 0 with J = I + l_IJ e(psi), K = l_GK e(gamma), e' the left normal of e:
    # (J - K) . (l_IJ e'(psi) psi' - l_GK e'(gamma) gamma') = 0.
    gamma = theta3 + k.lgk
    r_x = j_x - k_x
    r_y = j_y - k_y
    on_lever = r_y * np.cos(gamma) - r_x * np.sin(gamma)
    on_rocker = r_y * np.cos(psi) - r_x * np.sin(psi)
    dpsi_dtheta3 = (k.l_gk * on_lever) / (k.l_ij * on_rocker)
    return np.asarray(dlength_dpsi * dpsi_dtheta3, dtype=np.float64)


def _bucket_angle(k: _Linkage, length: FloatArray) -> FloatArray:
    """Bucket angle theta3 at a bucket-cylinder length |HJ| (inverse of :func:`_bucket_length`)."""
    hij = _triangle_angle(k.l_hi, k.l_ij, length)  # Gao eq 9
    psi = k.alpha_ih + _BRANCH_J_FROM_IH * hij  # eq 10
    j_x = k.i_x + k.l_ij * np.cos(psi)
    j_y = k.i_y + k.l_ij * np.sin(psi)
    jgk = _triangle_angle(k.l_gk, np.hypot(j_x, j_y), k.l_jk)  # eq 11-12
    theta3 = np.arctan2(j_y, j_x) + _BRANCH_K_FROM_GJ * jgk - k.lgk  # eq 13
    return np.asarray(
        theta3 - 2.0 * math.pi * np.floor((theta3 - k.wrap_low) / (2.0 * math.pi)),
        dtype=np.float64,
    )


def _arm(x: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3) (boom, stick, bucket); got {a.shape}")
    return a


def _pair(x: ArrayLike, x_name: str, y: ArrayLike, y_name: str) -> tuple[FloatArray, FloatArray]:
    a, b = _arm(x, x_name), _arm(y, y_name)
    try:
        a, b = np.broadcast_arrays(a, b)
    except ValueError as exc:
        raise ValueError(
            f"{x_name} {a.shape} and {y_name} {b.shape} must broadcast together"
        ) from exc
    return a, b


def _first_bad(bad: NDArray[np.bool_]) -> tuple[int, int]:
    """(flat batch index, axis) of the first True in a ``(..., 3)`` mask."""
    rows = bad.reshape(-1, 3)
    i = int(np.argmax(rows.any(axis=-1)))
    return i, int(np.argmax(rows[i]))


def _batch_index(flat: int, shape: tuple[int, ...]) -> str:
    return f" at batch index {tuple(int(v) for v in np.unravel_index(flat, shape[:-1]))}"


def _check_joints(rig: Rig, q: FloatArray) -> None:
    ok = (q >= rig.q_min_rad - _LIMIT_TOL_RAD) & (q <= rig.q_max_rad + _LIMIT_TOL_RAD)
    if not np.all(ok):
        i, axis = _first_bad(~ok)
        err = JointLimitError(
            AXES[axis],
            float(q.reshape(-1, 3)[i, axis]),
            float(rig.q_min_rad[axis]),
            float(rig.q_max_rad[axis]),
        )
        if q.ndim > 1:
            err.add_note(_batch_index(i, q.shape).strip())
        raise err


def _check_strokes(rig: Rig, s: FloatArray) -> None:
    _, hi = stroke_limits(rig)
    ok = (s >= -_LIMIT_TOL_M) & (s <= hi + _LIMIT_TOL_M)
    if not np.all(ok):
        i, axis = _first_bad(~ok)
        where = _batch_index(i, s.shape) if s.ndim > 1 else ""
        raise KinematicsError(
            f"{AXES[axis]} cylinder stroke {float(s.reshape(-1, 3)[i, axis]) * 1e3:.3f} mm{where} "
            f"is outside its travel [0, {float(hi[axis]) * 1e3:.3f}] mm"
        )


def _lengths(rig: Rig, q: FloatArray) -> FloatArray:
    """Pin-to-pin lengths, ``(..., 3)``."""
    cyl = rig.cylinders
    length = np.empty(q.shape, dtype=np.float64)
    length[..., 0] = _pin_length(cyl.boom, q[..., 0])
    length[..., 1] = _pin_length(cyl.stick, q[..., 1])
    length[..., 2] = _bucket_length(_linkage(rig), q[..., 2])
    return length


def _slopes(rig: Rig, q: FloatArray) -> FloatArray:
    """d length / d theta, ``(..., 3)``."""
    cyl = rig.cylinders
    slope = np.empty(q.shape, dtype=np.float64)
    slope[..., 0] = _pin_slope(cyl.boom, q[..., 0])
    slope[..., 1] = _pin_slope(cyl.stick, q[..., 1])
    slope[..., 2] = _bucket_slope(_linkage(rig), q[..., 2])
    return slope


def _retracted(rig: Rig) -> FloatArray:
    cyl = rig.cylinders
    return np.array(
        [cyl.boom.retracted_length_m, cyl.stick.retracted_length_m, cyl.bucket.retracted_length_m]
    )


def stroke_limits(rig: Rig) -> tuple[FloatArray, FloatArray]:
    """Cylinder travel: ``(lo_m, hi_m)``, each shape ``(3,)``; lo is 0, hi is ``stroke_max_m``."""
    cyl = rig.cylinders
    hi = np.array([cyl.boom.stroke_max_m, cyl.stick.stroke_max_m, cyl.bucket.stroke_max_m])
    return np.zeros(3), hi


def joint_to_stroke(rig: Rig, q_rad: ArrayLike, *, check_limits: bool = True) -> FloatArray:
    """Cylinder strokes from arm joint angles (Gao eq 6, 8 and 9-13 forward).

    Args:
        rig: The rig.
        q_rad: Arm joint angles (theta1, theta2, theta3), shape ``(..., 3)``.
        check_limits: Raise for joints outside the rig's limits.

    Returns:
        Strokes in m, ``(..., 3)``; NaN where the linkage cannot assemble (unchecked input only).

    Raises:
        ValueError: ``q_rad`` is not shaped ``(..., 3)``.
        JointLimitError: A joint lies outside its limits (only with ``check_limits``).
    """
    q = _arm(q_rad, "q_rad")
    if check_limits:
        _check_joints(rig, q)
    return _lengths(rig, q) - _retracted(rig)


def stroke_to_joint(rig: Rig, stroke_m: ArrayLike, *, check_limits: bool = True) -> FloatArray:
    """Arm joint angles from cylinder strokes, in closed form (Gao eq 6, 8 and 9-13 inverse).

    Args:
        rig: The rig.
        stroke_m: Strokes (boom, stick, bucket), shape ``(..., 3)``.
        check_limits: Raise for strokes outside ``[0, stroke_max_m]``.

    Returns:
        Joint angles in rad, ``(..., 3)``; the bucket angle is reported in the 2 pi window
        centred on its joint range. NaN where the geometry cannot close (unchecked input only).

    Raises:
        ValueError: ``stroke_m`` is not shaped ``(..., 3)``.
        KinematicsError: A stroke lies outside the cylinder's travel (only with
            ``check_limits``); the message names the axis.
    """
    s = _arm(stroke_m, "stroke_m")
    if check_limits:
        _check_strokes(rig, s)
    length = s + _retracted(rig)
    cyl = rig.cylinders
    q = np.empty(s.shape, dtype=np.float64)
    q[..., 0] = _pin_angle(cyl.boom, length[..., 0])
    q[..., 1] = _pin_angle(cyl.stick, length[..., 1])
    q[..., 2] = _bucket_angle(_linkage(rig), length[..., 2])
    return q


def stroke_jacobian(rig: Rig, q_rad: ArrayLike, *, check_limits: bool = True) -> FloatArray:
    """Diagonal of d stroke / d q: ``(..., 3)`` in m/rad (boom > 0, stick and bucket < 0).

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.
        check_limits: Raise for joints outside the rig's limits.

    Raises:
        ValueError: ``q_rad`` is not shaped ``(..., 3)``.
        JointLimitError: A joint lies outside its limits (only with ``check_limits``).
    """
    q = _arm(q_rad, "q_rad")
    if check_limits:
        _check_joints(rig, q)
    return _slopes(rig, q)


def stroke_velocity(
    rig: Rig, q_rad: ArrayLike, qd_rad_s: ArrayLike, *, check_limits: bool = True
) -> FloatArray:
    """Cylinder stroke rates from joint angles and rates: ``sd = (d s / d q) * qd``.

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.
        qd_rad_s: Joint rates, shape ``(..., 3)``, broadcastable with ``q_rad``.
        check_limits: Raise for joints outside the rig's limits.

    Returns:
        Stroke rates in m/s, the broadcast shape ``(..., 3)``.

    Raises:
        ValueError: Wrong or incompatible shapes.
        JointLimitError: A joint lies outside its limits (only with ``check_limits``).
    """
    q, qd = _pair(q_rad, "q_rad", qd_rad_s, "qd_rad_s")
    return stroke_jacobian(rig, q, check_limits=check_limits) * qd


def joint_velocity(
    rig: Rig, stroke_m: ArrayLike, sd_m_s: ArrayLike, *, check_limits: bool = True
) -> FloatArray:
    """Joint rates from cylinder strokes and stroke rates: ``qd = sd / (d s / d q)``.

    Args:
        rig: The rig.
        stroke_m: Strokes, shape ``(..., 3)``.
        sd_m_s: Stroke rates, shape ``(..., 3)``, broadcastable with ``stroke_m``.
        check_limits: Raise for strokes outside ``[0, stroke_max_m]``.

    Returns:
        Joint rates in rad/s, the broadcast shape ``(..., 3)``.

    Raises:
        ValueError: Wrong or incompatible shapes.
        KinematicsError: A stroke lies outside the travel (only with ``check_limits``).
    """
    s, sd = _pair(stroke_m, "stroke_m", sd_m_s, "sd_m_s")
    q = stroke_to_joint(rig, s, check_limits=check_limits)
    return sd / _slopes(rig, q)


def torque_from_force(
    rig: Rig, q_rad: ArrayLike, force_n: ArrayLike, *, check_limits: bool = True
) -> FloatArray:
    """Joint torques of cylinder forces by virtual work: ``tau_i = F_i * d s_i / d theta_i``.

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.
        force_n: Cylinder forces along the cylinder, positive pushing (extending), ``(..., 3)``,
            broadcastable with ``q_rad``.
        check_limits: Raise for joints outside the rig's limits.

    Returns:
        Torques in N*m acting on each joint in its positive (counter-clockwise) sense,
        the broadcast shape ``(..., 3)``.

    Raises:
        ValueError: Wrong or incompatible shapes.
        JointLimitError: A joint lies outside its limits (only with ``check_limits``).
    """
    q, f = _pair(q_rad, "q_rad", force_n, "force_n")
    return stroke_jacobian(rig, q, check_limits=check_limits) * f


def bucket_linkage_points(rig: Rig, theta3_rad: ArrayLike) -> LinkagePoints:
    """Pin positions of the bucket linkage at bucket angles ``theta3_rad`` (any shape ``(...)``).

    Unchecked: positions are NaN where the four-bar cannot assemble.
    """
    theta3 = np.asarray(theta3_rad, dtype=np.float64)
    k = _linkage(rig)
    k_x, k_y, j_x, j_y, _ = _bucket_points(k, theta3)
    l2 = float(rig.lengths_m[1])

    def fixed(x: float, y: float) -> FloatArray:
        return np.broadcast_to(np.array([x + l2, y]), (*theta3.shape, 2)).copy()

    return LinkagePoints(
        g_m=fixed(0.0, 0.0),
        h_m=fixed(k.h_x, k.h_y),
        i_m=fixed(k.i_x, k.i_y),
        j_m=np.stack([j_x + l2, j_y], axis=-1),
        k_m=np.stack([k_x + l2, k_y], axis=-1),
    )


def transmission_angles_rad(rig: Rig, theta3_rad: ArrayLike) -> FloatArray:
    """Transmission angles of the bucket linkage, ``(..., 3)`` in [0, pi].

    Columns: HJI (cylinder to rocker), IJK (rocker to link), GKJ (link to bucket lever). The
    linkage is at a dead point where any of them is 0 or pi. Unchecked; NaN where it cannot
    assemble.
    """
    theta3 = np.asarray(theta3_rad, dtype=np.float64)
    k = _linkage(rig)
    k_x, k_y, j_x, j_y, _ = _bucket_points(k, theta3)

    def angle(ax: FloatArray, ay: FloatArray, bx: FloatArray, by: FloatArray) -> FloatArray:
        return np.asarray(np.abs(np.arctan2(ax * by - ay * bx, ax * bx + ay * by)))

    ji_x, ji_y = k.i_x - j_x, k.i_y - j_y
    jk_x, jk_y = k_x - j_x, k_y - j_y
    out = np.empty((*theta3.shape, 3), dtype=np.float64)
    out[..., 0] = angle(k.h_x - j_x, k.h_y - j_y, ji_x, ji_y)
    out[..., 1] = angle(ji_x, ji_y, jk_x, jk_y)
    out[..., 2] = angle(-k_x, -k_y, -jk_x, -jk_y)
    return out


def validate_cylinders(rig: Rig) -> None:
    """Check that the cylinder geometry covers the rig's joint ranges; the loader calls this.

    For each cylinder: every joint angle in the joint range maps to a stroke in
    ``[0, stroke_max_m]``, and every stroke of that travel maps back to a joint angle away from
    the dead points (boom and stick: included angle phi at least 2 deg inside (0, pi); bucket:
    the three transmission angles within [20, 160] deg at 721 samples of each interval). Together
    these make each stroke strictly monotonic in its joint over the whole travel, in the
    directions of Gao Fig. 4, and :func:`stroke_to_joint` exact on it.

    Raises:
        RigProfileError: Naming ``cylinders.<boom|stick|bucket>`` (or one of its keys) and what
            is wrong.
    """
    for axis, cyl in ((0, rig.cylinders.boom), (1, rig.cylinders.stick)):
        _validate_pin(rig, axis, cyl)
    _validate_bucket(rig)


def _profile_error(rig: Rig, key: str, message: str) -> RigProfileError:
    return RigProfileError(f"cylinders.{key}", message, rig.source_path)


def _deg(x: float) -> str:
    return f"{math.degrees(x):.2f} deg"


def _mm(x: float) -> str:
    return f"{x * 1e3:.2f} mm"


def _check_travel_covers(
    rig: Rig, axis: int, length_lo: float, length_hi: float, at_lo: str, at_hi: str
) -> None:
    """Joint range's pin-to-pin lengths [length_lo, length_hi] must lie inside the travel."""
    name = AXES[axis]
    retracted = float(_retracted(rig)[axis])
    stroke_max = float(stroke_limits(rig)[1][axis])
    if length_lo < retracted - _LIMIT_TOL_M:
        raise _profile_error(
            rig,
            f"{name}.retracted_length_m",
            f"{_mm(retracted)} is longer than the pin-to-pin length {_mm(length_lo)} at {at_lo}; "
            f"the cylinder cannot reach that joint limit",
        )
    if length_hi > retracted + stroke_max + _LIMIT_TOL_M:
        raise _profile_error(
            rig,
            f"{name}.stroke_max_m",
            f"{_mm(stroke_max)} is too short: {at_hi} needs a pin-to-pin length of "
            f"{_mm(length_hi)}, the cylinder extends to {_mm(retracted + stroke_max)}",
        )


def _validate_pin(rig: Rig, axis: int, cyl: PinCylinder) -> None:
    name = AXES[axis]
    joint = rig.joints[axis]
    margin = INCLUDED_ANGLE_MARGIN_RAD
    ends = np.array([joint.min_rad, joint.max_rad])
    phi = cyl.angle_sign * ends + cyl.angle_offset_rad
    if phi.min() < margin or phi.max() > math.pi - margin:
        raise _profile_error(
            rig,
            f"{name}.angle_offset_deg",
            f"the included angle phi = {cyl.angle_sign:+d} * theta + offset spans "
            f"[{_deg(phi.min())}, {_deg(phi.max())}] over the joint range "
            f"[{_deg(joint.min_rad)}, {_deg(joint.max_rad)}]; it must stay within "
            f"[{_deg(margin)}, {_deg(math.pi - margin)}] for a strictly monotonic stroke",
        )
    length = _pin_length(cyl, ends)
    # Boom lengths grow with theta, stick lengths shrink: order the ends by length.
    lo_i, hi_i = (0, 1) if length[0] <= length[1] else (1, 0)
    _check_travel_covers(
        rig,
        axis,
        float(length[lo_i]),
        float(length[hi_i]),
        f"the joint limit {_deg(float(ends[lo_i]))}",
        f"the joint limit {_deg(float(ends[hi_i]))}",
    )
    a, b = cyl.pin_a_m, cyl.pin_b_m
    near = math.sqrt(a * a + b * b - 2.0 * a * b * math.cos(margin))
    far = math.sqrt(a * a + b * b - 2.0 * a * b * math.cos(math.pi - margin))
    retracted, stroke_max = cyl.retracted_length_m, cyl.stroke_max_m
    if retracted < near:
        raise _profile_error(
            rig,
            f"{name}.retracted_length_m",
            f"{_mm(retracted)} is shorter than {_mm(near)}, the pin-to-pin length "
            f"{_deg(margin)} from the dead point of pins {a:g} m and {b:g} m: the travel must "
            f"stay clear of it",
        )
    if retracted + stroke_max > far:
        raise _profile_error(
            rig,
            f"{name}.stroke_max_m",
            f"full extension {_mm(retracted + stroke_max)} exceeds {_mm(far)}, the pin-to-pin "
            f"length {_deg(margin)} from the dead point of pins {a:g} m and {b:g} m: the travel "
            f"must stay clear of it",
        )


def _validate_bucket(rig: Rig) -> None:
    joint = rig.joints[2]
    link = rig.cylinders.bucket
    k = _linkage(rig)
    theta = np.linspace(joint.min_rad, joint.max_rad, _CHECK_SAMPLES)
    _check_transmission(rig, theta, "over the joint range")
    length = _bucket_length(k, theta)
    if not _bucket_slope(k, theta[_CHECK_SAMPLES // 2]) < 0.0:
        raise _profile_error(
            rig,
            "bucket",
            "the bucket stroke must grow as theta3 decreases (Gao Fig. 4); this linkage "
            "extends the cylinder as the bucket opens",
        )
    # Transmission angles inside the bounds at every sample make the length strictly monotonic.
    _check_travel_covers(
        rig,
        2,
        float(length[-1]),
        float(length[0]),
        f"the joint limit {_deg(joint.max_rad)}",
        f"the joint limit {_deg(joint.min_rad)}",
    )
    travel = np.array([link.retracted_length_m, link.retracted_length_m + link.stroke_max_m])
    ends = _bucket_angle(k, travel)
    back = _bucket_length(k, ends)
    if not np.allclose(back, travel, rtol=0.0, atol=1e-9):
        raise _profile_error(
            rig,
            "bucket",
            f"the linkage does not assemble in the backhoe layout at the ends of the travel "
            f"(cylinder {_mm(float(travel[0]))} .. {_mm(float(travel[1]))}); shorten the travel "
            f"or change the four-bar",
        )
    if not (
        ends[1] <= joint.min_rad + _LIMIT_TOL_RAD and ends[0] >= joint.max_rad - _LIMIT_TOL_RAD
    ):
        raise _profile_error(
            rig,
            "bucket",
            f"the cylinder travel maps to theta3 {_deg(float(ends[1]))} .. {_deg(float(ends[0]))} "
            f"in the backhoe layout, which does not contain the joint range "
            f"[{_deg(joint.min_rad)}, {_deg(joint.max_rad)}]",
        )
    beyond = np.linspace(float(ends[1]), float(ends[0]), _CHECK_SAMPLES)
    _check_transmission(rig, beyond, "over the cylinder travel")


def _check_transmission(rig: Rig, theta: FloatArray, where: str) -> None:
    angles = transmission_angles_rad(rig, theta)
    low, high = TRANSMISSION_ANGLE_MIN_RAD, math.pi - TRANSMISSION_ANGLE_MIN_RAD
    ok = (angles >= low) & (angles <= high)  # NaN (cannot assemble) fails too
    if np.all(ok):
        return
    i = int(np.argmax(~ok.all(axis=-1)))
    c = int(np.argmax(~ok[i]))
    value = float(angles[i, c])
    what = ("HJI (cylinder to rocker)", "IJK (rocker to link)", "GKJ (link to bucket lever)")[c]
    problem = (
        "the four-bar cannot assemble (|IK| outside |l_ij - l_jk| .. l_ij + l_jk)"
        if math.isnan(value)
        else f"transmission angle {what} is {_deg(value)}, outside "
        f"[{_deg(low)}, {_deg(high)}] (too close to a dead point)"
    )
    raise _profile_error(rig, "bucket", f"at theta3 = {_deg(float(theta[i]))} {where}: {problem}")
