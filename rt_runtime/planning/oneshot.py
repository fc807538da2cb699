"""One-shot digging cycle: evaluation of candidate sextic trajectories (Yao section 4.2).

A dig goes from an entry pose to an exit pose along one sextic per joint (Yao eq 9-10, corrected
in DESIGN.md); the free parameters are ``(a16, a26, a36, T)``. This module evaluates many
candidates at once, batched over problems and candidates ``(B, P)``: the tip path, joint torques
from the arm dynamics plus Yao's digging resistance (eq 7-8), driving power and energy W_E, the
excavated volume V_p, the initial digging angle theta_p, the normalised objective of eq 11 and
every constraint of eq 12 as a signed, normalised violation (<= 0 satisfied).

Choices where the paper is silent (each also stated where it is computed):

- Power is the sum over joints of the positive mechanical power max(tau_i qd_i, 0): servo drives
  do not recover energy, so braking a joint costs nothing and earns nothing. W_E integrates it.
- V_p is the area between the tip path and the material surface y = H, computed exactly for the
  sampled (piecewise linear) path with Green's theorem on the path clipped at y = H, times the
  bucket width b.
- theta_p is the angle below the horizontal of the tip's direction of motion where it enters the
  material. When the dig starts on the surface, velocity and acceleration are zero there, so the
  direction is the limit of the motion direction: J(q0) * a3 (the cubic term leads).
- The digging depth h of eq 8 is the tip's depth below the surface H.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime import dynamics, kinematics, soil
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.rig import Planning, Rig
from rt_runtime.trajectory import sextic

FloatArray = NDArray[np.float64]

DEFAULT_SAMPLES = 101


class DigType(IntEnum):
    """The two trajectory types of Yao 4.2, told apart by theta_p."""

    DOWNWARD = 0
    BACKWARD = 1


CONSTRAINT_NAMES: tuple[str, ...] = (
    "angle_min_boom",
    "angle_min_stick",
    "angle_min_bucket",
    "angle_max_boom",
    "angle_max_stick",
    "angle_max_bucket",
    "velocity_boom",
    "velocity_stick",
    "velocity_bucket",
    "acceleration_boom",
    "acceleration_stick",
    "acceleration_bucket",
    "torque_boom",
    "torque_stick",
    "torque_bucket",
    "power",
    "theta_p_min",
    "theta_p_max",
    "volume_min",
    "volume_max",
    "time_min",
    "time_max",
)


@dataclass(frozen=True, slots=True)
class Problem:
    """One one-shot planning problem (the PINN's input).

    Attributes:
        q_start_rad: Entry pose (3,).
        q_end_rad: Exit pose (3,).
        surface_y_m: Material surface height H in the arm frame.
        dig_type: Downward or backward (sets the theta_p range).
    """

    q_start_rad: tuple[float, float, float]
    q_end_rad: tuple[float, float, float]
    surface_y_m: float
    dig_type: DigType


@dataclass(frozen=True, slots=True)
class Evaluation:
    """Everything computed for a batch of candidates, arrays shaped ``(B, P)`` unless noted.

    Attributes:
        T_s: Digging time.
        volume_m3: Excavated volume V_p.
        energy_j: Energy W_E.
        theta_p_rad: Initial digging angle.
        peak_power_w: Largest total positive power.
        peak_torque_nm: Largest |torque| per joint, ``(B, P, 3)``.
        objective: Yao eq 11.
        violations: Signed normalised constraint values ``(B, P, n)``, names in
            :data:`CONSTRAINT_NAMES`; <= 0 is satisfied.
        total_violation: Sum of the positive parts of ``violations``.
    """

    T_s: FloatArray
    volume_m3: FloatArray
    energy_j: FloatArray
    theta_p_rad: FloatArray
    peak_power_w: FloatArray
    peak_torque_nm: FloatArray
    objective: FloatArray
    violations: FloatArray
    total_violation: FloatArray

    @property
    def feasible(self) -> NDArray[np.bool_]:
        """Whether every constraint holds, ``(B, P)``."""
        return self.total_violation <= 0.0


def require_planning(rig: Rig) -> Planning:
    """The rig's planning thresholds.

    Raises:
        ConfigurationError: The profile has no ``[planning]`` table.
    """
    if rig.planning is None:
        raise ConfigurationError(
            f"rig {rig.name!r} has no [planning] table (thresholds of Yao Table 2); "
            "one-shot planning needs one"
        )
    return rig.planning


def theta_p_range(planning: Planning, dig_type: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Lower and upper theta_p bound per problem for the dig types given."""
    t = np.asarray(dig_type)
    down = np.asarray(planning.theta_p_downward_rad)
    back = np.asarray(planning.theta_p_backward_rad)
    is_down = t == DigType.DOWNWARD
    return np.where(is_down, down[0], back[0]), np.where(is_down, down[1], back[1])


def validate_problem(rig: Rig, q_start_rad: ArrayLike, q_end_rad: ArrayLike, surface_y_m: ArrayLike) -> None:
    """Check poses and surface of a batch of problems before planning.

    Raises:
        PlanningError: A NaN, a pose outside the joint limits (naming the joint and problem), or
            a surface that is not finite.
    """
    qs = np.asarray(q_start_rad, dtype=np.float64)
    qe = np.asarray(q_end_rad, dtype=np.float64)
    h = np.asarray(surface_y_m, dtype=np.float64)
    for label, q in (("start", qs), ("end", qe)):
        if q.shape[-1:] != (3,):
            raise PlanningError(f"{label} pose must have shape (..., 3); got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise PlanningError(f"{label} pose contains NaN or infinity")
        bad = (q < rig.q_min_rad - 1e-12) | (q > rig.q_max_rad + 1e-12)
        if np.any(bad):
            idx = np.argwhere(bad)[0]
            j = rig.joints[int(idx[-1])]
            where = f" (problem {tuple(int(i) for i in idx[:-1])})" if q.ndim > 1 else ""
            raise PlanningError(
                f"{label} pose{where}: {j.name} at {np.degrees(q[tuple(idx)]):.3f} deg is outside "
                f"[{np.degrees(j.min_rad):.3f}, {np.degrees(j.max_rad):.3f}] deg"
            )
    if not np.all(np.isfinite(h)):
        raise PlanningError("surface height H contains NaN or infinity")


def excavated_area_m2(x_m: FloatArray, y_m: FloatArray, surface_y_m: ArrayLike) -> FloatArray:
    """Area between a sampled tip path and the surface y = H, exact for the polyline.

    The path is clipped to the half-plane y <= H (crossings interpolated exactly) and closed along
    the surface; Green's theorem gives the area as |sum of integral (H - y) dx| over the clipped
    segments (the closing segment on y = H adds nothing).

    Args:
        x_m: Path x, ``(..., m)``.
        y_m: Path y, ``(..., m)``.
        surface_y_m: H, broadcastable to ``(...)``.

    Returns:
        Area in m^2, ``(...)``.
    """
    h = np.asarray(surface_y_m, dtype=np.float64)[..., None]
    d0 = h - y_m[..., :-1]  # depth below the surface at the segment ends (> 0 inside material)
    d1 = h - y_m[..., 1:]
    dx = x_m[..., 1:] - x_m[..., :-1]
    p0 = np.maximum(d0, 0.0)
    p1 = np.maximum(d1, 0.0)
    both = (d0 >= 0.0) & (d1 >= 0.0)
    # One end inside: only the fraction f of the segment below the surface counts, a triangle.
    denom = np.where(both, 1.0, np.abs(d0) + np.abs(d1))
    denom = np.where(denom > 0.0, denom, 1.0)
    frac = np.where(both, 1.0, np.maximum(d0, d1) / denom)
    seg = np.where(both, 0.5 * (p0 + p1) * dx, 0.5 * (p0 + p1) * frac * dx)
    return np.abs(np.sum(seg, axis=-1))


def _entry_angle(
    rig: Rig,
    q_start: FloatArray,
    a3: FloatArray,
    x: FloatArray,
    y: FloatArray,
    surface_y: FloatArray,
) -> FloatArray:
    """theta_p: angle below the horizontal of the motion direction where the tip enters."""
    below = y < surface_y[..., None]
    starts_inside = ~np.any(below[..., :1], axis=-1) & below[..., 1]
    has_entry = np.any(below, axis=-1)
    k = np.argmax(below, axis=-1)  # first sample inside the material
    k = np.clip(k, 1, y.shape[-1] - 1)
    dx = np.take_along_axis(x, k[..., None], -1)[..., 0] - np.take_along_axis(x, k[..., None] - 1, -1)[..., 0]
    dy = np.take_along_axis(y, k[..., None], -1)[..., 0] - np.take_along_axis(y, k[..., None] - 1, -1)[..., 0]
    # On the surface at t = 0 the direction is the limit J(q0) a3 (qd = qdd = 0 there).
    jac = kinematics.jacobian(rig, q_start)  # (..., 3, 3)
    d0 = np.einsum("...ij,...pj->...pi", jac[..., :2, :], a3)
    start_on_surface = starts_inside | (np.abs(y[..., 0] - surface_y) < 1e-9)
    dx = np.where(start_on_surface, d0[..., 0], dx)
    dy = np.where(start_on_surface, d0[..., 1], dy)
    angle = np.arctan2(-dy, np.abs(dx))
    return np.where(has_entry, angle, -np.pi / 2)  # never enters: maximally wrong, violates both
