"""Rigid-body dynamics of the planar excavator arm (Yao eq 5-7), joint power and energy.

The arm is a planar chain of three links (boom, stick, bucket) in the arm frame (origin at the
boom foot pin, x forward, y up), gravity ``rig.gravity_m_s2`` along -y. Link i has its origin at
joint i and its x axis along the absolute angle ``phi_i = theta1 + ... + theta_i``; its centre of
mass is ``rig.links[i].com_m = (along, normal)`` in that frame and its inertia
``rig.links[i].inertia_kgm2`` is about the centre of mass. With the Lagrangian ``E_k - E_p``
(eq 5), the Euler-Lagrange equations (eq 6, read with dL/dq_i where the paper repeats
dE_k/dq-dot_i) give eq 7::

    M(q) qdd + C(q, qd) qd + G(q) = tau - F_L,    F_L = -J(q)^T f_tip

where ``f_tip = (fx_n, fy_n, mz_nm)`` is the wrench the environment (soil) applies to the bucket
at the tip, in the arm frame, and ``J`` is :func:`rt_runtime.kinematics.jacobian` (rows x, y,
attitude). ``C`` is the Christoffel form, so ``M_dot - 2 C`` is skew-symmetric.

For the swing rig (``field_excavator``) the dynamics is over the three arm joints with the swing
held still: the arm frame is then inertial and the planar model is exact; swing motion would add
centrifugal and gyroscopic terms that are not modelled here.

How it is computed: in absolute angles ``phi = T q`` (``T`` lower-triangular ones) the kinetic
energy is ``1/2 phid^T D(phi) phid`` where ``D_jk`` (j != k) depends only on ``phi_j - phi_k``.
That makes the absolute-angle Christoffel matrix ``C_phi[j, k] = -W_jk phid_k`` with
``W_jk = dD_jk/dphi_j``; joint quantities follow from ``M = T^T D T``, ``C = T^T C_phi T``,
``tau = T^T Q_phi``. :func:`inverse_dynamics` evaluates this closed form per component on
cache-sized blocks without forming any 3x3 matrix, several times faster on planning batches
than ``M qdd + C qd + G - J^T f`` by batched matrix products (design notes, P9).

Energy: Yao's energy consumption W_E is taken as the integral of the positive joint powers
(drives that do not regenerate: braking a joint costs nothing and returns nothing); the
``absolute`` and ``net`` modes of :func:`energy_j` are the alternatives.

All functions are pure numpy, batched over leading axes, and raise ``ValueError`` for wrong
shapes. They are for planning, training and the HIL plant, not for the fixed-rate loop: they
raise instead of returning status, allocate temporaries, and a single-sample
:func:`inverse_dynamics` call costs tens of microseconds.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.rig import Rig

FloatArray = NDArray[np.float64]
EnergyMode = Literal["positive", "absolute", "net"]
ENERGY_MODES: tuple[str, ...] = ("positive", "absolute", "net")


def _vec3(name: str, value: ArrayLike) -> FloatArray:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3) (boom, stick, bucket); got {a.shape}")
    return a


class _Chain:
    """Constant mass parameters of the chain, in absolute-angle coordinates.

    ``h[k], b[k]``: first moment (along, normal), in link k's frame about joint k, of everything
    link k carries (link k itself plus the mass of the links beyond it, lumped at joint k+1).
    ``d[k]``: diagonal of ``D``. ``l0, l1``: boom and stick lengths.
    """

    __slots__ = ("b", "d", "g", "h", "l0", "l1", "lengths")

    def __init__(self, rig: Rig) -> None:
        links = rig.links
        lengths = [lk.length_m for lk in links]
        beyond = [links[1].mass_kg + links[2].mass_kg, links[2].mass_kg, 0.0]
        self.h = [
            lk.mass_kg * lk.com_m[0] + m * lk.length_m
            for lk, m in zip(links, beyond, strict=True)
        ]
        self.b = [lk.mass_kg * lk.com_m[1] for lk in links]
        self.d = [
            lk.inertia_kgm2 + lk.mass_kg * (lk.com_m[0] ** 2 + lk.com_m[1] ** 2)
            + m * lk.length_m**2
            for lk, m in zip(links, beyond, strict=True)
        ]
        self.g = rig.gravity_m_s2
        self.l0, self.l1 = lengths[0], lengths[1]
        self.lengths = lengths


class _Trig(NamedTuple):
    """Cosines and sines the chain needs, from one cos and one sin of the joint angles.

    ``c2, s2, c3, s3, c23, s23``: of q2, q3 and q2+q3 (``phi_j - phi_k`` up to sign);
    ``cp0 .. sp2``: of the absolute angles phi1, phi2, phi3.
    """

    c2: FloatArray
    s2: FloatArray
    c3: FloatArray
    s3: FloatArray
    c23: FloatArray
    s23: FloatArray
    cp0: FloatArray
    sp0: FloatArray
    cp1: FloatArray
    sp1: FloatArray
    cp2: FloatArray
    sp2: FloatArray


def _trig(q1: FloatArray, q2: FloatArray, q3: FloatArray) -> _Trig:
    # Angle-addition products are cheaper than four more transcendental calls per sample.
    c1, s1, c2, s2, c3, s3 = np.cos(q1), np.sin(q1), np.cos(q2), np.sin(q2), np.cos(q3), np.sin(q3)
    c12 = c1 * c2 - s1 * s2
    s12 = s1 * c2 + c1 * s2
    return _Trig(
        c2, s2, c3, s3, c2 * c3 - s2 * s3, s2 * c3 + c2 * s3,
        c1, s1, c12, s12, c12 * c3 - s12 * s3, s12 * c3 + c12 * s3,
    )


def _coupling(ch: _Chain, tr: _Trig) -> tuple[FloatArray, ...]:
    """Off-diagonal ``D_jk`` and ``W_jk = dD_jk/dphi_j`` (j < k) for (0,1), (0,2), (1,2).

    ``phi_j - phi_k`` is ``-q2``, ``-(q2+q3)``, ``-q3``; ``W_kj = -W_jk``.
    """
    h, b = ch.h, ch.b
    d01 = ch.l0 * (h[1] * tr.c2 - b[1] * tr.s2)
    w01 = ch.l0 * (b[1] * tr.c2 + h[1] * tr.s2)
    d02 = ch.l0 * (h[2] * tr.c23 - b[2] * tr.s23)
    w02 = ch.l0 * (b[2] * tr.c23 + h[2] * tr.s23)
    d12 = ch.l1 * (h[2] * tr.c3 - b[2] * tr.s3)
    w12 = ch.l1 * (b[2] * tr.c3 + h[2] * tr.s3)
    return d01, w01, d02, w02, d12, w12


def _trig_of(q: FloatArray) -> _Trig:
    return _trig(q[..., 0], q[..., 1], q[..., 2])


def _joint_from_absolute(d_abs: FloatArray) -> FloatArray:
    """``T^T D T`` for ``(..., 3, 3)``: entry (i, j) sums ``D[a, b]`` over a >= i, b >= j."""
    m = np.cumsum(d_abs[..., ::-1, :], axis=-2)[..., ::-1, :]
    return np.cumsum(m[..., :, ::-1], axis=-1)[..., :, ::-1]


def _absolute_matrices(rig: Rig, q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``D`` and ``W`` in absolute angles, each ``(..., 3, 3)``; ``D`` exactly symmetric."""
    ch = _Chain(rig)
    d01, w01, d02, w02, d12, w12 = _coupling(ch, _trig_of(q))
    shape = (*q.shape[:-1], 3, 3)
    d_abs = np.empty(shape)
    w_abs = np.zeros(shape)
    for i in range(3):
        d_abs[..., i, i] = ch.d[i]
    for (j, k), dv, wv in (((0, 1), d01, w01), ((0, 2), d02, w02), ((1, 2), d12, w12)):
        d_abs[..., j, k] = d_abs[..., k, j] = dv
        w_abs[..., j, k] = wv
        w_abs[..., k, j] = -wv
    return d_abs, w_abs


def mass_matrix(rig: Rig, q_rad: ArrayLike) -> FloatArray:
    """Joint-space mass matrix M(q) of eq 7.

    Args:
        rig: The rig (its three arm links).
        q_rad: Arm joint angles (theta1, theta2, theta3), shape ``(..., 3)``.

    Returns:
        ``(..., 3, 3)`` in kg*m^2, exactly symmetric and positive definite.

    Raises:
        ValueError: ``q_rad`` is not shaped ``(..., 3)``.
    """
    q = _vec3("q_rad", q_rad)
    ch = _Chain(rig)
    d01, _, d02, _, d12, _ = _coupling(ch, _trig_of(q))
    d0, d1, d2 = ch.d
    # M = T^T D T written out, each off-diagonal value stored twice so M is exactly symmetric.
    m = np.empty((*q.shape[:-1], 3, 3))
    m[..., 2, 2] = d2
    m[..., 1, 2] = m[..., 2, 1] = d2 + d12
    m[..., 0, 2] = m[..., 2, 0] = d2 + d12 + d02
    m[..., 1, 1] = d1 + d2 + 2.0 * d12
    m[..., 0, 1] = m[..., 1, 0] = d1 + d2 + 2.0 * d12 + d01 + d02
    m[..., 0, 0] = d0 + d1 + d2 + 2.0 * (d01 + d02 + d12)
    return m


def coriolis_matrix(rig: Rig, q_rad: ArrayLike, qd_rad_s: ArrayLike) -> FloatArray:
    """Christoffel-form Coriolis/centrifugal matrix C(q, qd) of eq 7.

    ``C qd`` is the velocity term of eq 7 and ``dM/dt - 2 C`` is skew-symmetric.

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.
        qd_rad_s: Arm joint velocities, shape ``(..., 3)`` (broadcast against ``q_rad``).

    Returns:
        ``(..., 3, 3)`` in kg*m^2/s.

    Raises:
        ValueError: An input is not shaped ``(..., 3)`` or the batch shapes do not broadcast.
    """
    q = _vec3("q_rad", q_rad)
    qd = _vec3("qd_rad_s", qd_rad_s)
    _, w_abs = _absolute_matrices(rig, q)
    phid = np.cumsum(qd, axis=-1)
    # C_phi[j, k] = -W_jk * phid_k (see the module docstring).
    return _joint_from_absolute(-w_abs * phid[..., None, :])


def gravity_torque(rig: Rig, q_rad: ArrayLike) -> FloatArray:
    """Gravity term G(q) = dE_p/dq of eq 7.

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.

    Returns:
        ``(..., 3)`` joint torques in N*m that hold the arm still against gravity.

    Raises:
        ValueError: ``q_rad`` is not shaped ``(..., 3)``.
    """
    q = _vec3("q_rad", q_rad)
    ch = _Chain(rig)
    phi = np.cumsum(q, axis=-1)
    g_abs = ch.g * (np.asarray(ch.h) * np.cos(phi) - np.asarray(ch.b) * np.sin(phi))
    return np.cumsum(g_abs[..., ::-1], axis=-1)[..., ::-1]


# Samples per block of the fast path: its ~40 temporaries then stay in cache, which measured
# about 2x faster than one pass over a (2000, 200, 3) batch on the 2-core build machine.
_BLOCK = 16384


def _rows(x: FloatArray) -> FloatArray:
    """``(n, 3)`` block as three contiguous ``(n,)`` rows (component-major)."""
    return np.ascontiguousarray(x.T)


def _inverse_block(
    ch: _Chain, q: FloatArray, qd: FloatArray, qdd: FloatArray, f: FloatArray | None,
    out: FloatArray,
) -> None:
    """:func:`inverse_dynamics` on ``(n, 3)`` inputs, written into ``out`` ``(n, 3)``."""
    q1, q2, q3 = _rows(q)
    tr = _trig(q1, q2, q3)
    d01, w01, d02, w02, d12, w12 = _coupling(ch, tr)
    w0, w1, w2 = np.cumsum(_rows(qd), axis=0)
    a0, a1, a2 = np.cumsum(_rows(qdd), axis=0)
    ww0, ww1, ww2 = w0 * w0, w1 * w1, w2 * w2
    h, b, g, d = ch.h, ch.b, ch.g, ch.d
    # Generalised forces on the absolute angles: D a - W w^2 + dE_p/dphi.
    t0 = d[0] * a0 + d01 * a1 + d02 * a2 - w01 * ww1 - w02 * ww2
    t0 += g * (h[0] * tr.cp0 - b[0] * tr.sp0)
    t1 = d01 * a0 + d[1] * a1 + d12 * a2 + w01 * ww0 - w12 * ww2
    t1 += g * (h[1] * tr.cp1 - b[1] * tr.sp1)
    t2 = d02 * a0 + d12 * a1 + d[2] * a2 + w02 * ww0 + w12 * ww1
    t2 += g * (h[2] * tr.cp2 - b[2] * tr.sp2)
    if f is not None:
        fx, fy, mz = _rows(f)
        lens = ch.lengths
        # J^T f on the absolute angles: l_k (-sin phi_k, cos phi_k) . (fx, fy), plus mz on phi3.
        t0 -= lens[0] * (tr.cp0 * fy - tr.sp0 * fx)
        t1 -= lens[1] * (tr.cp1 * fy - tr.sp1 * fx)
        t2 -= lens[2] * (tr.cp2 * fy - tr.sp2 * fx) + mz
    # tau = T^T Q_phi: joint i carries the generalised forces of links i and beyond.
    t1 += t2
    t0 += t1
    out[:, 0] = t0
    out[:, 1] = t1
    out[:, 2] = t2


def inverse_dynamics(
    rig: Rig,
    q_rad: ArrayLike,
    qd_rad_s: ArrayLike,
    qdd_rad_s2: ArrayLike,
    f_tip: ArrayLike | None = None,
) -> FloatArray:
    """Joint torques tau = M qdd + C qd + G - J^T f_tip (eq 7 with F_L = -J^T f_tip).

    The fast path for planning: the closed form of the module docstring evaluated per
    component on blocks of samples; no 3x3 matrix is formed.

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.
        qd_rad_s: Joint velocities, shape ``(..., 3)``.
        qdd_rad_s2: Joint accelerations, shape ``(..., 3)``.
        f_tip: Wrench the environment applies to the bucket at the tip, ``(fx_n, fy_n, mz_nm)``
            in the arm frame, shape ``(..., 3)``; None for a free arm.

    Returns:
        ``(..., 3)`` joint torques in N*m (the broadcast batch shape of the inputs); positive
        torque drives its joint counter-clockwise.

    Raises:
        ValueError: An input is not shaped ``(..., 3)`` or the batch shapes do not broadcast.
    """
    named = [("q_rad", q_rad), ("qd_rad_s", qd_rad_s), ("qdd_rad_s2", qdd_rad_s2)]
    if f_tip is not None:
        named.append(("f_tip", f_tip))
    arrays = [_vec3(name, value) for name, value in named]
    shape = np.broadcast_shapes(*(a.shape for a in arrays))
    flat = [np.broadcast_to(a, shape).reshape(-1, 3) for a in arrays]
    out = np.empty(shape)
    out_flat = out.reshape(-1, 3)
    ch = _Chain(rig)
    # Blocks, not samples: at most a few dozen iterations for the planner's largest batches.
    for start in range(0, out_flat.shape[0], _BLOCK):
        rows = slice(start, start + _BLOCK)
        _inverse_block(
            ch, flat[0][rows], flat[1][rows], flat[2][rows],
            flat[3][rows] if f_tip is not None else None, out_flat[rows],
        )
    return out


def kinetic_energy(rig: Rig, q_rad: ArrayLike, qd_rad_s: ArrayLike) -> FloatArray:
    """Kinetic energy E_k = 1/2 qd^T M(q) qd of the three links, translation and rotation.

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.
        qd_rad_s: Joint velocities, shape ``(..., 3)``.

    Returns:
        ``(...)`` in J.

    Raises:
        ValueError: An input is not shaped ``(..., 3)`` or the batch shapes do not broadcast.
    """
    q = _vec3("q_rad", q_rad)
    qd = _vec3("qd_rad_s", qd_rad_s)
    d_abs, _ = _absolute_matrices(rig, q)
    w = np.cumsum(qd, axis=-1)
    ke: FloatArray = 0.5 * np.einsum("...j,...jk,...k->...", w, d_abs, w)
    return ke


def potential_energy(rig: Rig, q_rad: ArrayLike) -> FloatArray:
    """Gravitational potential energy E_p, zero with every centre of mass at y = 0 (arm frame).

    Args:
        rig: The rig.
        q_rad: Arm joint angles, shape ``(..., 3)``.

    Returns:
        ``(...)`` in J.

    Raises:
        ValueError: ``q_rad`` is not shaped ``(..., 3)``.
    """
    q = _vec3("q_rad", q_rad)
    ch = _Chain(rig)
    phi = np.cumsum(q, axis=-1)
    heights = np.sin(phi) @ np.asarray(ch.h) + np.cos(phi) @ np.asarray(ch.b)
    return np.asarray(ch.g * heights, dtype=np.float64)


def joint_power(tau_nm: ArrayLike, qd_rad_s: ArrayLike) -> FloatArray:
    """Mechanical power of each joint drive, ``tau_i * qd_i``.

    Args:
        tau_nm: Joint torques, shape ``(..., 3)``.
        qd_rad_s: Joint velocities, shape ``(..., 3)``.

    Returns:
        ``(..., 3)`` in W; positive while the drive does work on the arm.

    Raises:
        ValueError: An input is not shaped ``(..., 3)`` or the batch shapes do not broadcast.
    """
    return _vec3("tau_nm", tau_nm) * _vec3("qd_rad_s", qd_rad_s)


def energy_j(t_s: ArrayLike, power_w: ArrayLike, mode: EnergyMode = "positive") -> FloatArray:
    """Energy over time of the joint drives (Yao's W_E in the default mode), trapezoid rule.

    Args:
        t_s: Sample times, shape ``(n_samples,)`` or broadcastable to ``(..., n_samples)``.
        power_w: Joint powers, shape ``(..., n_samples, 3)`` (see :func:`joint_power`).
        mode: What is integrated at each sample before the trapezoid rule:
            ``"positive"`` the sum over joints of max(P_i, 0), the energy drawn by drives that do
            not regenerate (our reading of W_E); ``"absolute"`` the sum of |P_i|; ``"net"`` the
            plain sum (the change of the arm's energy plus the work done on the soil).

    Returns:
        ``(...)`` in J.

    Raises:
        ValueError: Unknown ``mode`` (the message lists the allowed ones), ``power_w`` not shaped
            ``(..., n_samples, 3)``, or ``t_s`` whose last axis is not ``n_samples``.
    """
    if mode not in ENERGY_MODES:
        raise ValueError(f"mode must be one of {', '.join(ENERGY_MODES)}; got {mode!r}")
    p = np.asarray(power_w, dtype=np.float64)
    if p.ndim < 2 or p.shape[-1] != 3:
        raise ValueError(f"power_w must have shape (..., n_samples, 3); got {p.shape}")
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim == 0 or t.shape[-1] != p.shape[-2]:
        raise ValueError(
            f"t_s must have shape (n_samples,) or (..., n_samples) with n_samples = "
            f"{p.shape[-2]} (from power_w); got {t.shape}"
        )
    if mode == "positive":
        total = np.maximum(p, 0.0).sum(axis=-1)
    elif mode == "absolute":
        total = np.abs(p).sum(axis=-1)
    else:
        total = p.sum(axis=-1)
    # By hand rather than np.trapezoid, which numpy < 2.0 (allowed by pyproject) lacks.
    energy: FloatArray = 0.5 * np.sum(
        (total[..., 1:] + total[..., :-1]) * np.diff(t, axis=-1), axis=-1
    )
    return energy
