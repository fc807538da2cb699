"""Direction targets for training: how much objective a wrong bulge direction costs.

The runtime (:meth:`rt_runtime.planning.verify.Verifier.plan_into`) keeps only the DIRECTION
of the network's bulge ``K = -a6 T^6``: it scales the bulge to the largest volume within V_max
(fill) and runs the path at its smallest feasible T (retime). Fed the PSO teacher's own
``(K, T)`` it reproduces the teacher's objective, so every bit of the planned objective gap is
the network's error in the direction of K. This module measures, per training sample, what that
error costs, so that the loss can be the benchmark itself.

The post-pipeline objective has a kink at the teacher's direction, not a smooth minimum: the
retimed T is the largest of several limit-induced times (torque, power, velocity per joint),
and the teacher balances several of them. The gap is therefore first order in the tilt angle
(a cone) and strongly anisotropic over the tilt directions; a quadratic model
``(d - d*)^T H (d - d*)`` would be zero to first order and miss it. The teacher already sits at
the kink, so its targets are kept as they are (numbers: design notes, N5).

:func:`direction_targets` samples the cone: per sample, the teacher's unit direction ``u*``,
an orthonormal basis ``(e1, e2)`` of its tangent plane and the relative gap slope ``s(phi_j)``
(per radian of tilt, as a fraction of the teacher's objective) in ``n_dirs`` directions
``phi_j = 2 pi j / n_dirs`` at the tilt ``radius_rad``. A tilt whose plan the runtime cannot make
feasible gets the sample's largest finite slope times :data:`INFEASIBLE_SLOPE_FACTOR` (a
refusal or repair costs at least as much as the worst measured direction), and at least
``infeasible_slope`` per radian. The training loss
(:func:`cone_gap`) is then ``theta * s(phi)`` with ``theta`` the angle between the predicted
and the teacher's direction and ``s`` interpolated linearly (periodically) between the sampled
directions: the objective gap to first order, i.e. the benchmark's ``gap_mean`` where the
network lands near the teacher.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.oneshot import DigType
from rt_runtime.rig import Rig

FloatArray = NDArray[np.float64]

#: Slope given to a tilt the runtime cannot plan, as a multiple of the sample's worst finite one.
INFEASIBLE_SLOPE_FACTOR = 2.0
#: Default least slope (per radian, fraction of the objective) of an unplannable tilt.
FALLBACK_SLOPE_PER_RAD = 5.0
# Rows per plan_into call (bounds the scratch arrays).
_CHUNK = 4096


@dataclass(frozen=True, slots=True)
class DirectionTargets:
    """The teacher's bulge directions and the sampled cost cone around each.

    Attributes:
        u: Teacher unit directions ``K / |K|`` ``(N, 3)``.
        e1, e2: Orthonormal bases of the tangent planes ``(N, 3)`` each.
        slopes: Relative objective gap per radian of tilt toward ``phi_j`` ``(N, n_dirs)``,
            >= 0, ``phi_j = 2 pi j / n_dirs`` measured from ``e1`` toward ``e2``.
        base_objective: The planned objective at the teacher's own direction ``(N,)`` (NaN
            where the runtime cannot plan it).
        radius_rad: The tilt at which the slopes were measured.
        infeasible_fraction: Fraction of tilts the runtime could not plan.
    """

    u: FloatArray
    e1: FloatArray
    e2: FloatArray
    slopes: FloatArray
    base_objective: FloatArray
    radius_rad: float
    infeasible_fraction: float


def tangent_basis(u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Orthonormal ``(e1, e2)`` ``(N, 3)`` with ``u, e1, e2`` right-handed, for unit ``u`` (N, 3).

    ``e1`` is ``u`` crossed with the coordinate axis least aligned with ``u`` (well conditioned
    for every ``u``), ``e2 = u x e1``.
    """
    axis = np.eye(3)[np.argmin(np.abs(u), axis=1)]
    e1 = np.cross(u, axis)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return e1, e2


def planned_objective(
    rig_or_verifier: Rig | Any,
    X: FloatArray,
    dig_type: DigType,
    K_rad: FloatArray,
    T_s: FloatArray,
) -> FloatArray:
    """Objective of the plans the runtime makes from ``(K, T)``, NaN where it cannot plan.

    Args:
        rig_or_verifier: The rig, or a :class:`rt_runtime.planning.verify.Verifier` to reuse.
        X: Problems ``(N, 7)``.
        dig_type: Their dig type.
        K_rad: Bulges ``(N, 3)``.
        T_s: Times ``(N,)`` (the runtime retimes; T only converts K to a6).

    Returns:
        ``(N,)`` Yao eq 11 of the filled and retimed plan, NaN where that plan is infeasible.
    """
    from rt_runtime.planning.verify import COL_OBJECTIVE, COL_TOTAL, N_OUT, Verifier, pack_inputs

    verifier = (
        rig_or_verifier if isinstance(rig_or_verifier, Verifier) else Verifier(rig_or_verifier)
    )
    n = X.shape[0]
    result = np.full(n, np.nan)
    for a in range(0, n, _CHUNK):
        b = min(n, a + _CHUNK)
        T = T_s[a:b]
        a6 = -K_rad[a:b] / T[:, None] ** 6
        rows = pack_inputs(X[a:b, 0:3], X[a:b, 3:6], X[a:b, 6], int(dig_type), a6, T)
        out = np.zeros((b - a, N_OUT))
        verifier.plan_into(rows, out, np.zeros((b - a, 4)))
        ok = out[:, COL_TOTAL] <= 0.0
        result[a:b] = np.where(ok, out[:, COL_OBJECTIVE], np.nan)
    return result


def direction_targets(
    rig: Rig,
    X: FloatArray,
    dig_type: DigType,
    K_rad: FloatArray,
    T_s: FloatArray,
    *,
    n_dirs: int = 16,
    radius_rad: float = math.radians(1.0),
    infeasible_slope: float = FALLBACK_SLOPE_PER_RAD,
) -> DirectionTargets:
    """Sample the objective-gap cone around each teacher direction (module docstring).

    ``n_dirs + 1`` planner calls per sample (~20-40 us each): seconds for thousands.

    Args:
        rig: The rig the teacher solved for.
        X: Problems ``(N, 7)``.
        dig_type: Their dig type.
        K_rad: The teacher's bulges ``(N, 3)`` (non-zero).
        T_s: The teacher's times ``(N,)``.
        n_dirs: Tilt directions per sample, >= 4.
        radius_rad: Tilt angle, in (0, 0.2] rad.
        infeasible_slope: Least slope (per rad) of a tilt the runtime cannot plan (module
            docstring), > 0.

    Returns:
        The :class:`DirectionTargets`.

    Raises:
        ConfigurationError: Bad ``n_dirs`` or ``radius_rad``, mismatched shapes, or a zero
            bulge.
    """
    from rt_runtime.planning.verify import Verifier

    if n_dirs < 4:
        raise ConfigurationError(f"n_dirs must be >= 4; got {n_dirs}")
    if not infeasible_slope > 0.0:
        raise ConfigurationError(f"infeasible_slope must be > 0 per rad; got {infeasible_slope!r}")
    if not 0.0 < radius_rad <= 0.2:
        raise ConfigurationError(f"radius_rad must be in (0, 0.2] rad; got {radius_rad!r}")
    X = np.asarray(X, dtype=np.float64)
    K = np.asarray(K_rad, dtype=np.float64)
    T = np.asarray(T_s, dtype=np.float64)
    n = X.shape[0]
    if X.shape != (n, 7) or K.shape != (n, 3) or T.shape != (n,):
        raise ConfigurationError(
            f"X, K_rad, T_s must be (N, 7), (N, 3), (N,); got {X.shape}, {K.shape}, {T.shape}"
        )
    mag = np.linalg.norm(K, axis=1)
    if n and not np.all(mag > 0.0):
        raise ConfigurationError("every teacher bulge K must be non-zero to have a direction")
    verifier = Verifier(rig)
    u = K / mag[:, None]
    e1, e2 = tangent_basis(u)
    base = planned_objective(verifier, X, dig_type, K, T)
    phi = 2.0 * np.pi * np.arange(n_dirs) / n_dirs
    c, s = math.cos(radius_rad), math.sin(radius_rad)
    # All tilts of all samples in one batch: row j * n + i is sample i tilted toward phi_j.
    tilt = c * u[None] + s * (
        np.cos(phi)[:, None, None] * e1[None] + np.sin(phi)[:, None, None] * e2[None]
    )
    f = planned_objective(
        verifier,
        np.tile(X, (n_dirs, 1)),
        dig_type,
        (tilt * mag[None, :, None]).reshape(-1, 3),
        np.tile(T, n_dirs),
    ).reshape(n_dirs, n)
    ref = np.where(np.isfinite(base), base, np.nanmin(np.vstack([f, base[None]]), axis=0))
    slopes = ((f - ref[None]) / (np.abs(ref[None]) * radius_rad)).T  # (N, n_dirs)
    slopes = np.maximum(slopes, 0.0)
    finite = np.isfinite(slopes)
    worst = np.where(
        finite.any(axis=1), np.max(np.where(finite, slopes, 0.0), axis=1), infeasible_slope
    )
    fill = np.maximum(INFEASIBLE_SLOPE_FACTOR * worst, infeasible_slope)
    slopes = np.where(finite, slopes, fill[:, None])
    return DirectionTargets(
        u=u,
        e1=e1,
        e2=e2,
        slopes=slopes,
        base_objective=base,
        radius_rad=float(radius_rad),
        infeasible_fraction=float(1.0 - finite.mean()) if n else 0.0,
    )


def cone_gap(K: Any, u: Any, e1: Any, e2: Any, slopes: Any) -> Any:
    """First-order objective gap of predicted bulges, differentiable (torch).

    ``theta * s(phi)``: ``theta`` the angle between ``K`` and ``u`` (0..pi), ``phi`` the
    direction of the tilt in the ``(e1, e2)`` plane, ``s`` the sampled slopes interpolated
    linearly and periodically in ``phi``.

    Args:
        K: Predicted bulges ``(B, 3)`` (any non-zero scale).
        u, e1, e2: :class:`DirectionTargets` rows ``(B, 3)``.
        slopes: :class:`DirectionTargets` rows ``(B, n_dirs)``.

    Returns:
        ``(B,)`` relative objective gap to first order in the angle.
    """
    import torch

    n_dirs = slopes.shape[1]
    a = (K * u).sum(dim=1)
    b1 = (K * e1).sum(dim=1)
    b2 = (K * e2).sum(dim=1)
    # |tangential part|, smoothed at 0 (its gradient is 0/0 exactly on the teacher's direction).
    rho = torch.sqrt(b1 * b1 + b2 * b2 + 1e-24 * (a * a + 1e-30))
    theta = torch.atan2(rho, a)
    phi = torch.remainder(torch.atan2(b2, b1), 2.0 * math.pi) * (n_dirs / (2.0 * math.pi))
    j0 = torch.clamp(torch.floor(phi).long(), 0, n_dirs - 1)
    w = (phi - j0.to(phi.dtype)).clamp(0.0, 1.0)
    j1 = torch.remainder(j0 + 1, n_dirs)
    s0 = slopes.gather(1, j0[:, None])[:, 0]
    s1 = slopes.gather(1, j1[:, None])[:, 0]
    return theta * ((1.0 - w) * s0 + w * s1)


__all__ = [
    "FALLBACK_SLOPE_PER_RAD",
    "INFEASIBLE_SLOPE_FACTOR",
    "DirectionTargets",
    "cone_gap",
    "direction_targets",
    "planned_objective",
    "tangent_basis",
]
