"""Digging resistance: the soil's wrench on the bucket (Yao eq 8; Yang/Pan fluid model eq 13-18).

Two models, both batched over leading axes and both returning the wrench the soil applies to
the bucket *at the tip*, in the arm frame (origin at the boom foot pin, x forward, y up):
``(fx_n, fy_n, mz_nm)`` shaped ``(..., 3)``, ``mz`` counter-clockwise positive. This is the
``f_tip`` the dynamics subtract as ``J^T f_tip`` with the tip Jacobian of
:func:`rt_runtime.kinematics.jacobian` (rows x, y, attitude).

* :func:`yao_resistance` -- Yao eq 8: a point force at the tip, tangential ``W_Q = K0 b h``
  against the tip velocity and normal ``W_f = mu W_Q`` across it.
* :func:`fluid_resistance` -- Yang/Pan section 3: the bucket outline discretised into small
  plates, each feeling a depth-dependent pressure and a velocity term against its normal
  velocity and friction against its tangential velocity, summed into a force and a moment
  about the tip (eq 18).

Inputs are the tip pose ``(x_m, y_m, attitude_rad)`` (``attitude = theta1 + theta2 + theta3``,
the bucket link's x axis from its pivot to the tip) and the tip twist
``(vx_m_s, vy_m_s, omega_rad_s)`` from :func:`rt_runtime.kinematics.tip_velocity`, plus the
terrain as a :class:`SurfaceProfile` (or a plain height in m for flat ground).

Velocity regularisation (both models; the papers are silent): a resistance whose direction
follows a velocity has no direction at zero velocity. Every such unit vector ``v/|v|`` is
replaced by ``v / max(|v|, speed_reg_m_s)``, so the force ramps linearly to zero below
``speed_reg_m_s`` (default 1 mm/s) and is exactly the papers' above it. A resting bucket
therefore feels no resistance: the static contact force is a reaction (anything up to the
yield value, set by what the arm applies), which no explicit force law can know, and a
non-zero force at rest would push the bucket along it and do work. The ramp keeps every
output finite (never NaN) and continuous through rest, and the soil never pushes the bucket
along its motion (power ``F . v + M omega <= 0``). Below ``speed_reg_m_s`` the force acts as a
viscous damper of gain ``|F| / speed_reg_m_s``; an explicit integrator (the HIL plant) needs a
step below about ``2 m / gain`` for the effective mass m, or a larger ``speed_reg_m_s``.

Errors: wrong array shapes raise ``ValueError``; non-finite values, a non-increasing surface,
an unknown soil name or a bad option raise :class:`~rt_runtime.errors.ConfigurationError`.
The functions allocate arrays proportional to the batch (the fluid model times the number of
elements), so they belong to planning and simulation, not to the fixed-rate control loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import FluidSoil, Rig

FloatArray = NDArray[np.float64]

DEFAULT_SPEED_REG_M_S = 1e-3
DEFAULT_N_ELEMENTS = 10


@dataclass(frozen=True, slots=True, eq=False)
class SurfaceProfile:
    """Terrain height along x in the arm frame: a polyline y(x).

    Heights between the points are linearly interpolated; beyond the first and last point the
    end height continues (constant extrapolation). Construction copies the arrays and makes
    them read-only, so a caller may keep mutating its own terrain buffer. Equality is identity
    (``eq=False``): comparing array fields element-wise has no single truth value.

    Attributes:
        x_m: Abscissae in m, shape ``(n,)``, ``n >= 1``, strictly increasing.
        y_m: Surface heights in m at ``x_m`` (arm frame, y up), shape ``(n,)``.

    Raises:
        ValueError: ``x_m`` or ``y_m`` is not 1-D, they differ in length, or they are empty.
        ConfigurationError: A value is not finite, or ``x_m`` is not strictly increasing.
    """

    x_m: FloatArray
    y_m: FloatArray

    def __post_init__(self) -> None:
        x = np.array(self.x_m, dtype=np.float64)
        y = np.array(self.y_m, dtype=np.float64)
        if x.ndim != 1 or y.ndim != 1 or x.shape != y.shape or x.size == 0:
            raise ValueError(
                f"SurfaceProfile x_m and y_m must be 1-D arrays of the same length n >= 1; "
                f"got shapes {x.shape} and {y.shape}"
            )
        if not (np.isfinite(x).all() and np.isfinite(y).all()):
            raise ConfigurationError("SurfaceProfile x_m and y_m must be finite (no NaN or inf)")
        steps = np.diff(x)
        if (steps <= 0.0).any():
            i = int(np.argmax(steps <= 0.0))
            raise ConfigurationError(
                f"SurfaceProfile x_m must be strictly increasing; x_m[{i + 1}] = {x[i + 1]!r} "
                f"follows x_m[{i}] = {x[i]!r}"
            )
        x.setflags(write=False)
        y.setflags(write=False)
        object.__setattr__(self, "x_m", x)
        object.__setattr__(self, "y_m", y)

    @classmethod
    def flat(cls, h_m: float) -> SurfaceProfile:
        """Flat ground at height ``h_m`` (arm frame) everywhere.

        Raises:
            ConfigurationError: ``h_m`` is not finite.
        """
        if not math.isfinite(h_m):
            raise ConfigurationError(f"flat surface height h_m must be finite; got {h_m!r}")
        return cls(np.zeros(1), np.array([h_m], dtype=np.float64))

    def height_at(self, x_m: ArrayLike) -> FloatArray:
        """Surface height in m above (any shape of) ``x_m``; same shape as ``x_m``.

        Non-finite ``x_m`` gives non-finite heights; the force models reject such input first.
        """
        return np.interp(np.asarray(x_m, dtype=np.float64), self.x_m, self.y_m)


def yao_resistance(
    rig: Rig,
    tip_pose: ArrayLike,
    tip_twist: ArrayLike,
    surface: SurfaceProfile | ArrayLike,
    *,
    speed_reg_m_s: float = DEFAULT_SPEED_REG_M_S,
) -> FloatArray:
    """Digging resistance of Yao eq 8 as a point force at the bucket tip.

    ``h = max(0, surface height above the tip - tip y)`` is the vertical depth of the tip
    below the surface directly above it. ``W_Q = K0 b h`` (``rig.soil.yao.k0_n_m2``,
    ``rig.bucket.width_m``) acts against the tip's linear velocity; ``W_f = mu W_Q`` acts
    perpendicular to it, on the side that pushes the cutting edge out of the cut: the
    perpendicular with a non-negative y component. When the tip moves exactly vertically both
    perpendiculars are horizontal; the one towards -x (towards the machine) is taken, which
    is the limit of a backhoe dig (tip moving towards the machine) as it turns vertical, so
    the force is continuous along every such dig. The force magnitude is
    ``sqrt(1 + mu^2) W_Q`` for tip speeds of at least ``speed_reg_m_s`` and ramps linearly to
    zero below it (see the module docstring). The bucket's rotation plays no part in this
    model and the moment about the tip is zero.

    Sanity check on the scale model: K0 = 5 N/cm^2, b = 0.22 m, h = 0.05 m gives W_Q = 550 N.

    Args:
        rig: The rig (its Yao soil and bucket width).
        tip_pose: ``(..., 3)``: tip ``x_m``, ``y_m`` (arm frame) and ``attitude_rad``.
        tip_twist: ``(..., 3)``: ``vx_m_s``, ``vy_m_s``, ``omega_rad_s``; its batch axes
            broadcast against ``tip_pose``'s.
        surface: Terrain profile, or flat ground at a height (m, arm frame): a float, or an
            array of heights broadcastable to the batch axes (one flat surface per state, as
            the batched one-shot planner needs for many problems at once).
        speed_reg_m_s: Speed below which the force ramps to zero; > 0.

    Returns:
        ``(..., 3)``: ``(fx_n, fy_n, mz_nm)`` the soil applies to the bucket at the tip, arm
        frame; ``mz_nm`` is zero. Batch axes are those of ``tip_pose`` and ``tip_twist``
        broadcast together.

    Raises:
        ValueError: ``tip_pose`` or ``tip_twist`` is not shaped ``(..., 3)``, or their batch
            axes do not broadcast.
        ConfigurationError: Non-finite pose, twist or surface height, or a bad
            ``speed_reg_m_s``.
    """
    pose, twist = _tip_state(tip_pose, tip_twist)
    reg = _speed_reg(speed_reg_m_s)
    if isinstance(surface, SurfaceProfile):
        ground = surface.height_at(pose[..., 0])
    else:
        ground = np.asarray(surface, dtype=np.float64)
        if not np.isfinite(ground).all():
            raise ConfigurationError(
                "surface height h_m has non-finite values (NaN or inf); give finite heights"
            )
    depth = np.maximum(ground - pose[..., 1], 0.0)
    w_q = (rig.soil.yao.k0_n_m2 * rig.bucket.width_m) * depth
    vx = twist[..., 0]
    vy = twist[..., 1]
    # W_Q times the regularised unit tangent v / max(|v|, reg).
    gain = w_q / np.maximum(np.hypot(vx, vy), reg)
    tx = gain * vx
    ty = gain * vy
    # Normal = side * (-t_y, t_x): its y component side * t_x is >= 0; t_x == 0 counts as a dig
    # towards the machine (side -1).
    side_mu = np.where(vx > 0.0, rig.soil.yao.mu, -rig.soil.yao.mu)
    out = np.zeros((*depth.shape, 3), dtype=np.float64)
    out[..., 0] = -tx - side_mu * ty
    out[..., 1] = -ty + side_mu * tx
    return out


def fluid_resistance(
    rig: Rig,
    soil: FluidSoil | str,
    tip_pose: ArrayLike,
    tip_twist: ArrayLike,
    surface: SurfaceProfile | float,
    *,
    n_elements: int = DEFAULT_N_ELEMENTS,
    speed_reg_m_s: float = DEFAULT_SPEED_REG_M_S,
) -> FloatArray:
    """Soil-tool wrench of the Yang/Pan fluid model (their eq 13-18), resolved at the tip.

    The bucket is its outline ``rig.bucket.profile_m``: points (along, normal) in the bucket
    link frame shifted to the tip, the tip first; segment 1 is the separation plane, segment
    2 the back plane (further points, where a profile has them, add further plates). Each
    segment is cut into ``n_elements`` equal plates of area ``S = length / n_elements * b``.
    A plate takes part when its centre lies below the surface, at depth ``h`` (vertical, m);
    its centre velocity is ``v_i = v_B + omega x r_i`` with ``r_i`` from the tip, split into
    ``v_n`` along the plate normal and ``v_t`` along the plate. Per plate (eq 13, 15, 16)::

        P = rho g h
        N = -(Kp P + Kv |v_n|) S v_n / |v_n|
        F = -Ks |N| v_t / |v_t|,   |N| = (Kp P + Kv |v_n|) S

    and the resultant is ``F = sum(N + F)``, ``M = sum(r_i x (N + F))`` about the tip (eq 18).

    Choices where the paper is silent or misprinted:

    * Eq 17 prints ``v_i = r_i x omega + v_B``; the rigid-body velocity is ``v_B + omega x r_i``
      (the printed cross product has the wrong sign). Eq 16 prints ``K_s N`` with the vector
      N and names the coefficient ``K_f``; the magnitude ``K_s |N|`` is meant.
    * ``v / |v|`` becomes ``v / max(|v|, speed_reg_m_s)`` (module docstring). For N this makes
      the normal force of a plate vanish as ``v_n -> 0``: a thin plate buried in soil has soil
      on both faces, so the static pressures cancel and only the resistance to moving
      through the soil remains. The friction uses the eq 15 magnitude ``(Kp P + Kv |v_n|) S``,
      which is defined at every ``v_n``, so a plate sliding along its own plane (the
      separation plane during a drag) still feels friction ``Ks Kp P S``. A resting bucket
      feels no wrench.
    * Plates above the surface feel nothing, including the velocity term.

    Args:
        rig: The rig (bucket outline and width, gravity).
        soil: A fluid soil, or the name of one of ``rig.soil.fluid`` (``"soft"``, ``"hard"``).
        tip_pose: ``(..., 3)``: tip ``x_m``, ``y_m`` (arm frame) and ``attitude_rad``.
        tip_twist: ``(..., 3)``: ``vx_m_s``, ``vy_m_s``, ``omega_rad_s``; its batch axes
            broadcast against ``tip_pose``'s.
        surface: Terrain profile, or a float for flat ground at that height (m, arm frame).
        n_elements: Plates per outline segment, >= 1.
        speed_reg_m_s: Speed below which a plate's force direction ramps to zero; > 0.

    Returns:
        ``(..., 3)``: ``(fx_n, fy_n, mz_nm)`` the soil applies to the bucket, force in the arm
        frame and moment about the tip (counter-clockwise positive).

    Raises:
        ValueError: ``tip_pose`` or ``tip_twist`` is not shaped ``(..., 3)``, or their batch
            axes do not broadcast.
        ConfigurationError: Non-finite input, an unknown soil name, or a bad ``n_elements``
            or ``speed_reg_m_s``.
    """
    fs = _fluid_soil(rig, soil)
    pose, twist = _tip_state(tip_pose, tip_twist)
    reg = _speed_reg(speed_reg_m_s)
    if isinstance(n_elements, bool) or not isinstance(n_elements, int | np.integer):
        raise ConfigurationError(f"n_elements must be an int >= 1; got {n_elements!r}")
    if n_elements < 1:
        raise ConfigurationError(f"n_elements must be >= 1; got {n_elements}")
    surf = _as_surface(surface)
    el = _plates(rig.bucket.profile_m, rig.bucket.width_m, int(n_elements))

    # Work in the bucket link frame, where the plate geometry is constant; matrix products
    # against the constant plate maps replace per-plate temporaries (the batch x plates arrays
    # dominate the cost). Only the depths need the plate centres in the arm frame.
    att = pose[..., 2]
    c = np.cos(att)
    s = np.sin(att)
    x_i = np.stack([pose[..., 0], c, s], axis=-1) @ el.x_map
    y_i = np.stack([pose[..., 1], s, c], axis=-1) @ el.y_map
    depth = surf.height_at(x_i)
    depth -= y_i
    submerged = depth > 0.0
    np.maximum(depth, 0.0, out=depth)

    vx = twist[..., 0]
    vy = twist[..., 1]
    # Body twist in the bucket frame: (u, w) = R(attitude)^T v_B, and omega.
    body = np.stack([c * vx + s * vy, c * vy - s * vx, twist[..., 2]], axis=-1)
    v_n = body @ el.normal_map.T
    v_t = body @ el.tangent_map.T
    abs_vn = np.abs(v_n)
    # |N| of eq 15 per plate, zero for plates above the surface.
    mag = depth  # depth is not needed again: build |N| in its buffer
    mag *= fs.kp * fs.density_kg_m3 * rig.gravity_m_s2
    mag += fs.kv * abs_vn
    mag *= el.area
    mag *= submerged
    np.maximum(abs_vn, reg, out=abs_vn)
    v_n /= abs_vn
    v_n *= mag
    abs_vt = np.abs(v_t)
    np.maximum(abs_vt, reg, out=abs_vt)
    v_t /= abs_vt
    v_t *= mag
    # Sum over plates: (fx, fy, mz) in the bucket frame; the moment is frame-independent.
    local = v_n @ el.normal_map
    local += fs.ks * (v_t @ el.tangent_map)
    local *= -1.0
    out = np.empty_like(local)
    out[..., 0] = c * local[..., 0] - s * local[..., 1]
    out[..., 1] = s * local[..., 0] + c * local[..., 1]
    out[..., 2] = local[..., 2]
    return out


@dataclass(frozen=True, slots=True, eq=False)
class _Plates:
    """Constant plate geometry of a bucket outline, ``m`` plates, as maps for matrix products.

    Attributes:
        area: Plate areas S in m^2, ``(m,)``.
        x_map: ``(3, m)``; ``(x_tip, cos a, sin a) @ x_map`` are the plate centres' x (arm frame).
        y_map: ``(3, m)``; ``(y_tip, sin a, cos a) @ y_map`` are the plate centres' y.
        normal_map: ``(m, 3)``; rows (n_x, n_y, r x n) in the bucket frame: the body twist
            ``(u, w, omega) @ normal_map.T`` is each plate's normal velocity, and per-plate
            coefficients along the normal ``@ normal_map`` sum to (fx, fy, mz) about the tip.
        tangent_map: ``(m, 3)``; the same along the plate.
    """

    area: FloatArray
    x_map: FloatArray
    y_map: FloatArray
    normal_map: FloatArray
    tangent_map: FloatArray


@lru_cache(maxsize=32)
def _plates(profile_m: tuple[tuple[float, float], ...], width_m: float, n: int) -> _Plates:
    pts = np.asarray(profile_m, dtype=np.float64)
    seg = np.diff(pts, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    if (length <= 0.0).any():
        raise ConfigurationError("bucket.profile_m has two equal consecutive points")
    frac = (np.arange(n) + 0.5) / n
    centre = (pts[:-1, None, :] + frac[None, :, None] * seg[:, None, :]).reshape(-1, 2)
    tangent = np.repeat(seg / length[:, None], n, axis=0)
    # Either normal sign gives the same forces: eq 15 uses v_n as a vector.
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=-1)
    cx = centre[:, 0]
    cy = centre[:, 1]
    ones = np.ones_like(cx)
    plates = _Plates(
        area=np.repeat(length / n * width_m, n),
        x_map=np.stack([ones, cx, -cy]),
        y_map=np.stack([ones, cx, cy]),
        normal_map=np.column_stack([normal, cx * normal[:, 1] - cy * normal[:, 0]]),
        tangent_map=np.column_stack([tangent, cx * tangent[:, 1] - cy * tangent[:, 0]]),
    )
    for a in (plates.area, plates.x_map, plates.y_map, plates.normal_map, plates.tangent_map):
        a.setflags(write=False)
    return plates


def _tip_state(tip_pose: ArrayLike, tip_twist: ArrayLike) -> tuple[FloatArray, FloatArray]:
    pose = np.asarray(tip_pose, dtype=np.float64)
    twist = np.asarray(tip_twist, dtype=np.float64)
    if pose.ndim == 0 or pose.shape[-1] != 3:
        raise ValueError(
            f"tip_pose must have shape (..., 3) (x_m, y_m, attitude_rad); got {pose.shape}"
        )
    if twist.ndim == 0 or twist.shape[-1] != 3:
        raise ValueError(
            f"tip_twist must have shape (..., 3) (vx_m_s, vy_m_s, omega_rad_s); got {twist.shape}"
        )
    try:
        batch = np.broadcast_shapes(pose.shape[:-1], twist.shape[:-1])
    except ValueError:
        raise ValueError(
            f"batch axes of tip_pose {pose.shape[:-1]} and tip_twist {twist.shape[:-1]} "
            "do not broadcast"
        ) from None
    if not np.isfinite(pose).all():
        raise ConfigurationError("tip_pose has non-finite values (NaN or inf)")
    if not np.isfinite(twist).all():
        raise ConfigurationError("tip_twist has non-finite values (NaN or inf)")
    return np.broadcast_to(pose, (*batch, 3)), np.broadcast_to(twist, (*batch, 3))


def _speed_reg(speed_reg_m_s: float) -> float:
    reg = float(speed_reg_m_s)
    if not (math.isfinite(reg) and reg > 0.0):
        raise ConfigurationError(f"speed_reg_m_s must be finite and > 0; got {speed_reg_m_s!r}")
    return reg


def _as_surface(surface: SurfaceProfile | float) -> SurfaceProfile:
    if isinstance(surface, SurfaceProfile):
        return surface
    return SurfaceProfile.flat(float(surface))


def _fluid_soil(rig: Rig, soil: FluidSoil | str) -> FluidSoil:
    if isinstance(soil, FluidSoil):
        return soil
    try:
        return rig.soil.fluid_named(soil)
    except KeyError as exc:
        raise ConfigurationError(f"fluid soil: {exc.args[0]}") from None
