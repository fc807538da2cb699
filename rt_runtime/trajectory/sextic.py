"""Sextic joint trajectories with rest-to-rest boundary conditions (Yao eq 9-10, corrected).

Each joint follows ``theta(t) = sum_k a_k t^k`` for ``k = 0..6`` on ``0 <= t <= T`` (Yao eq 9).
Zero velocity and acceleration at both ends leave two free parameters per joint, the leading
coefficient ``a6`` and the shared duration ``T``. Yao's printed eq 10 is wrong in ``a5`` and ``a4``
(DESIGN.md errata); the correct family is

    theta(t) = theta1 + D q(s) + K p(s),   s = t / T,   D = theta2 - theta1,   K = -a6 T^6,
    q(s) = 10 s^3 - 15 s^4 + 6 s^5,        p(s) = s^3 (1 - s)^3,

because ``q`` is the quintic that moves 0 -> 1 at rest and ``p`` has triple roots at both ends,
so it adds shape without touching the boundary conditions. Expanding gives

    a0 = theta1,  a1 = a2 = 0,
    a3 = 10 D / T^3 - a6 T^3,
    a4 = -15 D / T^4 + 3 a6 T^2,
    a5 = 6 D / T^5 - 3 a6 T,
    a6 = a6.

Coefficient arrays store ``a0..a6`` along the last axis, lowest power first, in rad/s^k.
``a6`` is tiny for multi-second digs (``|a6| = |K| / T^6``, about 1e-5 rad/s^6 for K = 1 rad and
T = 7 s); a search over the shape term K in rad is better scaled than one over a6 itself.

Two paths: :func:`sextic_coefficients` and :func:`evaluate` are batched over leading axes for the
planners (thousands of candidates x hundreds of samples in one numpy pass, outside the loop);
:meth:`SexticTrajectory.sample` is the cheap per-cycle step for the fixed-rate loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import PlanningError

FloatArray = NDArray[np.float64]

N_COEFFICIENTS = 7
"""Number of polynomial coefficients per joint (a0..a6)."""

_POWERS = np.arange(N_COEFFICIENTS, dtype=np.float64)


class SexticSamples(NamedTuple):
    """Samples of a batch of sextic trajectories (unpacks as ``t, q, qd, qdd, qddd``).

    Attributes:
        t_s: Sample times, ``(..., m)``, from 0 to each candidate's own T.
        q_rad: Joint angles, ``(..., m, n)``.
        qd_rad_s: Joint velocities, ``(..., m, n)``.
        qdd_rad_s2: Joint accelerations, ``(..., m, n)``.
        qddd_rad_s3: Joint jerks, ``(..., m, n)``.
    """

    t_s: FloatArray
    q_rad: FloatArray
    qd_rad_s: FloatArray
    qdd_rad_s2: FloatArray
    qddd_rad_s3: FloatArray


def _finite(name: str, values: ArrayLike) -> FloatArray:
    a = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise PlanningError(f"{name} must be finite; got non-finite values in an array {a.shape}")
    return a


def _duration(T_s: ArrayLike) -> FloatArray:
    T = _finite("T_s", T_s)
    if not np.all(T > 0.0):
        raise PlanningError(f"T_s must be > 0 s; got min {float(np.min(T))!r} s")
    return T


def _joint_vector(name: str, values: ArrayLike) -> FloatArray:
    a = _finite(name, values)
    if a.ndim == 0:
        raise ValueError(f"{name} must have shape (..., n_joints); got a scalar")
    return a


def sextic_coefficients(
    q_start_rad: ArrayLike, q_end_rad: ArrayLike, a6: ArrayLike, T_s: ArrayLike
) -> FloatArray:
    """Coefficients of rest-to-rest sextics through given end poses (corrected Yao eq 10).

    Args:
        q_start_rad: Start joint angles theta1, ``(..., n)``, rad.
        q_end_rad: End joint angles theta2, ``(..., n)``, rad.
        a6: Leading coefficients, ``(..., n)``, rad/s^6.
        T_s: Durations, ``(...)``, s, finite and > 0.

    The leading axes of all four broadcast against each other (e.g. one start/end pose ``(n,)``
    with P candidates ``a6 (P, n)``, ``T_s (P,)``).

    Returns:
        ``(..., n, 7)``: ``a0..a6`` per joint, lowest power first, in rad/s^k.

    Raises:
        ValueError: An argument has no joint axis, the joint counts differ, or the leading
            axes do not broadcast.
        PlanningError: A value is non-finite, or a duration is not > 0.

    Allocates its output; outside the loop.
    """
    qs = _joint_vector("q_start_rad", q_start_rad)
    qe = _joint_vector("q_end_rad", q_end_rad)
    c6 = _joint_vector("a6", a6)
    T = _duration(T_s)
    n = qs.shape[-1]
    if qe.shape[-1] != n or c6.shape[-1] != n:
        raise ValueError(
            "q_start_rad, q_end_rad and a6 must have the same number of joints (last axis); "
            f"got shapes {qs.shape}, {qe.shape}, {c6.shape}"
        )
    try:
        lead = np.broadcast_shapes(qs.shape[:-1], qe.shape[:-1], c6.shape[:-1], T.shape)
    except ValueError:
        raise ValueError(
            "leading axes do not broadcast: q_start_rad (..., n), q_end_rad (..., n), "
            f"a6 (..., n), T_s (...) got {qs.shape}, {qe.shape}, {c6.shape}, {T.shape}"
        ) from None
    D = qe - qs
    Tc = T[..., np.newaxis]
    T2 = Tc * Tc
    T3 = T2 * Tc
    out = np.zeros((*lead, n, N_COEFFICIENTS))
    out[..., 0] = qs
    out[..., 3] = 10.0 * D / T3 - c6 * T3
    out[..., 4] = -15.0 * D / (T3 * Tc) + 3.0 * c6 * T2
    out[..., 5] = 6.0 * D / (T3 * T2) - 3.0 * c6 * Tc
    out[..., 6] = c6
    return out


def _derivative_basis(s: FloatArray) -> FloatArray:
    """``(..., 4, m, 7)``: d^j/ds^j of ``s^k`` for j = 0..3 (value, first, second, third)."""
    k = _POWERS
    basis = np.zeros((*s.shape[:-1], 4, s.shape[-1], N_COEFFICIENTS))
    sk = s[..., np.newaxis]
    for j in range(4):
        # Falling factorial k (k-1) ... (k-j+1); zero where the power is gone.
        factor = np.ones(N_COEFFICIENTS)
        for i in range(j):
            factor = factor * (k - i)
        basis[..., j, :, :] = factor * sk ** np.maximum(k - j, 0.0)
    return basis


def evaluate(
    coeffs: ArrayLike,
    T_s: ArrayLike,
    n_samples: int | None = None,
    *,
    s_grid: ArrayLike | None = None,
) -> SexticSamples:
    """Sample a batch of sextics on a normalised time grid, with three derivatives.

    Each candidate is sampled at ``t = s * T`` for the same normalised ``s`` in [0, 1], so every
    candidate gets the same number of samples over its own duration. The polynomial is
    rescaled to ``s`` (``b_k = a_k T^k``) before the product with the powers of ``s``, which keeps
    the numbers O(range of motion) whatever T is; the j-th derivative is then divided by T^j.

    Args:
        coeffs: ``(..., n, 7)`` coefficients ``a0..a6`` (rad/s^k), as from
            :func:`sextic_coefficients`.
        T_s: ``(...)`` durations, s, finite and > 0; broadcasts with ``coeffs.shape[:-2]``.
        n_samples: Number of evenly spaced samples ``m >= 2`` including both ends; give this or
            ``s_grid``.
        s_grid: Normalised sample points in [0, 1]: ``(m,)`` shared by all candidates (fast path,
            one matrix product) or ``(..., m)`` per candidate.

    Returns:
        :class:`SexticSamples` ``(t_s (..., m), q_rad, qd_rad_s, qdd_rad_s2, qddd_rad_s3)``, the
        last four ``(..., m, n)``. With a shared grid they are views into one buffer laid out
        ``(4, m, ..., n)``, which keeps the reductions over samples that planners do (max over
        axis -2) cheap; copy them if you need C-contiguous arrays.

    Raises:
        ValueError: Wrong shapes, both or neither of ``n_samples`` and ``s_grid``,
            ``n_samples < 2``, or ``s_grid`` outside [0, 1].
        PlanningError: Non-finite coefficients or a duration not finite and > 0.

    Shapes (2000, 101, 3) take about 1-3 ms with single-threaded BLAS (a multi-threaded OpenBLAS
    on an oversubscribed machine can be several times slower); allocates its outputs; outside
    the loop.
    """
    C = _finite("coeffs", coeffs)
    if C.ndim < 2 or C.shape[-1] != N_COEFFICIENTS:
        raise ValueError(f"coeffs must have shape (..., n_joints, 7); got {C.shape}")
    T = _duration(T_s)
    try:
        lead = np.broadcast_shapes(C.shape[:-2], T.shape)
    except ValueError:
        raise ValueError(
            f"T_s {T.shape} does not broadcast with the leading axes of coeffs {C.shape}"
        ) from None
    if (n_samples is None) == (s_grid is None):
        raise ValueError("give exactly one of n_samples and s_grid")
    if n_samples is not None:
        if isinstance(n_samples, bool) or not isinstance(n_samples, int | np.integer):
            raise ValueError(f"n_samples must be an int >= 2; got {n_samples!r}")
        if n_samples < 2:
            raise ValueError(f"n_samples must be >= 2; got {n_samples}")
        s: FloatArray = np.linspace(0.0, 1.0, int(n_samples), dtype=np.float64)
    else:
        s = np.asarray(s_grid, dtype=np.float64)
        if s.ndim == 0 or s.shape[-1] < 1:
            raise ValueError(f"s_grid must have shape (m,) or (..., m); got {s.shape}")
        if not np.all((s >= 0.0) & (s <= 1.0)):
            raise ValueError("s_grid must lie in [0, 1] (normalised time t / T)")

    n = C.shape[-2]
    m = s.shape[-1]
    C = np.broadcast_to(C, (*lead, n, N_COEFFICIENTS))
    T = np.broadcast_to(T, lead)
    Tpow = T[..., np.newaxis] ** _POWERS
    b = C * Tpow[..., np.newaxis, :]
    inv_T = 1.0 / T

    if s.ndim == 1:
        # One GEMM (4m, 7) x (7, batch*n): the hot path of the optimiser.
        basis = _derivative_basis(s).reshape(4 * m, N_COEFFICIENTS)
        flat = basis @ b.reshape(-1, N_COEFFICIENTS).T
        out = flat.reshape(4, m, flat.shape[1])
        # Per-column scale with a contiguous inner axis (batch*n) is the cheap broadcast.
        inv_col = np.repeat(inv_T.reshape(-1), n)
        out[1] *= inv_col
        out[2] *= inv_col * inv_col
        out[3] *= inv_col * inv_col * inv_col
        derivs = np.moveaxis(out.reshape(4, m, *lead, n), 1, -2)
    else:
        try:
            s_lead = np.broadcast_shapes(s.shape[:-1], lead)
        except ValueError:
            raise ValueError(
                f"s_grid {s.shape} does not broadcast with the candidates' leading axes {lead}"
            ) from None
        if s_lead != lead:
            raise ValueError(
                f"s_grid {s.shape} would enlarge the candidates' leading axes {lead}; "
                "broadcast coeffs/T_s first"
            )
        basis = _derivative_basis(s)
        # (..., 4, m, 7) @ (..., 1, 7, n) -> (..., 4, m, n)
        vals = basis @ np.swapaxes(b, -1, -2)[..., np.newaxis, :, :]
        scale = inv_T[..., np.newaxis] ** np.arange(4.0)
        vals = vals * scale[..., np.newaxis, np.newaxis]
        derivs = np.moveaxis(vals, -3, 0)
    t = s * T[..., np.newaxis]
    return SexticSamples(t, derivs[0], derivs[1], derivs[2], derivs[3])


def _readonly(a: FloatArray) -> FloatArray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, slots=True, eq=False)
class SexticTrajectory:
    """One rest-to-rest sextic per joint, ready to be sampled in the loop.

    Construction validates and precomputes the coefficients and their derivative coefficients
    (outside the loop). Equality is identity: the fields are arrays.

    Attributes:
        q_start_rad: Start pose theta1, ``(n,)``, rad.
        q_end_rad: End pose theta2, ``(n,)``, rad.
        a6: Leading coefficients, ``(n,)``, rad/s^6.
        T_s: Duration, s, finite and > 0.

    Raises:
        ValueError: The three vectors are not 1-D of the same length.
        PlanningError: A value is non-finite or ``T_s <= 0``.
    """

    q_start_rad: FloatArray
    q_end_rad: FloatArray
    a6: FloatArray
    T_s: float
    _c: FloatArray = field(init=False, repr=False)
    _cd: FloatArray = field(init=False, repr=False)
    _cdd: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        put = object.__setattr__
        if np.ndim(self.T_s) != 0:
            raise ValueError(f"T_s must be a scalar duration in s; got shape {np.shape(self.T_s)}")
        vectors: dict[str, FloatArray] = {}
        for name in ("q_start_rad", "q_end_rad", "a6"):
            v = np.array(getattr(self, name), dtype=np.float64)
            if v.ndim != 1:
                raise ValueError(f"{name} must have shape (n_joints,); got {v.shape}")
            vectors[name] = v
        c = sextic_coefficients(
            vectors["q_start_rad"], vectors["q_end_rad"], vectors["a6"], self.T_s
        )
        for name, v in vectors.items():
            put(self, name, _readonly(v))
        put(self, "T_s", float(self.T_s))
        k = _POWERS
        put(self, "_c", _readonly(c))
        put(self, "_cd", _readonly(c[:, 1:] * k[1:]))
        put(self, "_cdd", _readonly(c[:, 2:] * (k[2:] * (k[2:] - 1.0))))

    @property
    def coefficients(self) -> FloatArray:
        """``(n, 7)`` read-only coefficients ``a0..a6`` per joint, lowest power first, rad/s^k."""
        return self._c

    @property
    def n_joints(self) -> int:
        """Number of joints n."""
        return int(self._c.shape[0])

    def sample(self, t_s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Joint angle, velocity and acceleration at one time.

        Outside ``[0, T]`` the arm holds the nearer end pose at rest: ``t < 0`` gives the start
        pose, ``t > T`` the end pose, both with zero velocity and acceleration.

        Args:
            t_s: Time since the start of the trajectory, s.

        Returns:
            ``(q_rad, qd_rad_s, qdd_rad_s2)``, each a new ``(n,)`` array.

        Raises:
            ValueError: ``t_s`` is not finite (a caller bug, not a control-flow status).

        Loop-safe: a 7-element power vector and three ``(n,)`` results are all it allocates.
        """
        t = float(t_s)
        if not math.isfinite(t):
            raise ValueError(f"t_s must be finite; got {t_s!r}")
        if t <= 0.0:
            z = np.zeros(self._c.shape[0])
            return self.q_start_rad.copy(), z, z.copy()
        if t >= self.T_s:
            z = np.zeros(self._c.shape[0])
            return self.q_end_rad.copy(), z, z.copy()
        t2 = t * t
        t3 = t2 * t
        t4 = t3 * t
        tp = np.array((1.0, t, t2, t3, t4, t4 * t, t3 * t3))
        return self._c @ tp, self._cd @ tp[:6], self._cdd @ tp[:5]
