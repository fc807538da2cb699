"""Arm dynamics (rt_runtime.dynamics) against an independent symbolic Lagrangian and identities.

The reference derives the Lagrangian of the same planar 3-link chain with sympy (centre-of-mass
positions from the link frames, translational and rotational kinetic energy, potential energy,
Euler-Lagrange), once per module, with the rig parameters as symbols so one derivation serves
every rig.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest
import sympy as sp

from rt_runtime import dynamics as dyn
from rt_runtime.kinematics import forward, jacobian
from rt_runtime.rig import Rig, load_rig, profile_names

RIGS = profile_names()
# Every profile plus one whose links all have their centre of mass off the link axis (the
# profiles have it only on the bucket), so every normal-offset term is exercised.
OFFSET = "scale_model+offset_com"
CASES = [*RIGS, OFFSET]
N_STATES = 64


def _rig(name: str) -> Rig:
    if name != OFFSET:
        return load_rig(name)
    base = load_rig("scale_model")
    normals = (0.05, -0.04, 0.06)
    links = tuple(
        replace(lk, com_m=(lk.com_m[0], n), mass_kg=lk.mass_kg * (1.0 + 0.3 * i))
        for i, (lk, n) in enumerate(zip(base.links, normals, strict=True))
    )
    return replace(base, links=links)


@dataclass(frozen=True)
class Reference:
    """Lambdified symbolic model: each takes (q(3), qd(3), qdd(3), params) as flat arrays."""

    tau: Callable[..., Any]
    mass: Callable[..., Any]
    cqd: Callable[..., Any]
    grav: Callable[..., Any]
    ke: Callable[..., Any]
    pe: Callable[..., Any]


def _params(rig: Rig) -> list[float]:
    out: list[float] = [rig.gravity_m_s2]
    for lk in rig.links:
        out += [lk.length_m, lk.mass_kg, lk.com_m[0], lk.com_m[1], lk.inertia_kgm2]
    return out


@pytest.fixture(scope="module")
def reference() -> Reference:
    t = sp.Symbol("t")
    g = sp.Symbol("g")
    par = [sp.symbols(f"l{i} m{i} a{i} b{i} I{i}") for i in range(3)]
    qf = [sp.Function(f"q{i}")(t) for i in range(3)]
    q = sp.symbols("q0:3")
    qd = sp.symbols("qd0:3")
    qdd = sp.symbols("qdd0:3")

    def rot(angle: sp.Expr) -> sp.Matrix:
        return sp.Matrix([[sp.cos(angle), -sp.sin(angle)], [sp.sin(angle), sp.cos(angle)]])

    ke = sp.Integer(0)
    pe = sp.Integer(0)
    origin = sp.Matrix([0, 0])
    angle = sp.Integer(0)
    for i in range(3):
        length, mass, a, b, inertia = par[i]
        angle = angle + qf[i]
        com = origin + rot(angle) * sp.Matrix([a, b])
        vel = com.diff(t)
        half = sp.Rational(1, 2)
        ke += half * mass * (vel.T * vel)[0] + half * inertia * angle.diff(t) ** 2
        pe += mass * g * com[1]
        origin = origin + rot(angle) * sp.Matrix([length, 0])
    lag = ke - pe

    subs_dd = {qf[i].diff(t, 2): qdd[i] for i in range(3)}
    subs_d = {qf[i].diff(t): qd[i] for i in range(3)}
    subs_q = {qf[i]: q[i] for i in range(3)}

    def plain(expr: sp.Expr) -> sp.Expr:
        return expr.subs(subs_dd).subs(subs_d).subs(subs_q)

    tau = [
        plain(lag.diff(qf[i].diff(t)).diff(t) - lag.diff(qf[i])) for i in range(3)
    ]
    mass_m = sp.Matrix(3, 3, lambda i, j: sp.diff(tau[i], qdd[j]))
    grav = [plain(pe).diff(q[i]) for i in range(3)]
    zero_acc = {qdd[i]: 0 for i in range(3)}
    cqd = [tau[i].subs(zero_acc) - grav[i] for i in range(3)]

    flat_par = [g, *[s for p in par for s in p]]
    args = [q, qd, qdd, flat_par]

    def fn(expr: Any) -> Callable[..., Any]:
        return sp.lambdify(args, expr, modules="numpy", cse=True)

    return Reference(
        tau=fn(tau), mass=fn(mass_m), cqd=fn(cqd), grav=fn(grav), ke=fn(plain(ke)),
        pe=fn(plain(pe)),
    )


def _states(rig: Rig, rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    q = rng.uniform(rig.q_min_rad, rig.q_max_rad, size=(n, 3))
    qd = rng.uniform(-2.0, 2.0, size=(n, 3))
    qdd = rng.uniform(-5.0, 5.0, size=(n, 3))
    return q, qd, qdd


def _close(actual: np.ndarray, expected: np.ndarray, rtol: float, what: str, case: Any) -> None:
    """Relative to the largest magnitude of ``expected`` in the case (cancellation-safe)."""
    scale = max(float(np.max(np.abs(expected))), 1e-300)
    err = float(np.max(np.abs(actual - expected)))
    assert err <= rtol * scale, f"{what}: error {err:.3e} > {rtol:g} x {scale:.3e} at {case}"


@pytest.mark.parametrize("name", CASES)
def test_matches_symbolic_lagrangian(name: str, reference: Reference) -> None:
    rig = _rig(name)
    rng = np.random.default_rng(1000 + CASES.index(name))
    par = _params(rig)
    q, qd, qdd = _states(rig, rng, N_STATES)
    tau = dyn.inverse_dynamics(rig, q, qd, qdd)
    m = dyn.mass_matrix(rig, q)
    cqd = np.einsum("nij,nj->ni", dyn.coriolis_matrix(rig, q, qd), qd)
    grav = dyn.gravity_torque(rig, q)
    ke = dyn.kinetic_energy(rig, q, qd)
    pe = dyn.potential_energy(rig, q)
    for n in range(N_STATES):
        case = f"rig={name} q={q[n].tolist()} qd={qd[n].tolist()} qdd={qdd[n].tolist()}"
        ref = (q[n], qd[n], qdd[n], par)
        _close(tau[n], np.array(reference.tau(*ref), float), 1e-9, "tau", case)
        _close(m[n], np.array(reference.mass(*ref), float), 1e-9, "M", case)
        _close(cqd[n], np.array(reference.cqd(*ref), float), 1e-9, "C qd", case)
        _close(grav[n], np.array(reference.grav(*ref), float), 1e-9, "G", case)
        _close(ke[n], np.array(reference.ke(*ref), float), 1e-9, "E_k", case)
        _close(pe[n], np.array(reference.pe(*ref), float), 1e-9, "E_p", case)


@pytest.mark.parametrize("name", CASES)
def test_fast_path_equals_matrix_form(name: str) -> None:
    rig = _rig(name)
    rng = np.random.default_rng(2000 + CASES.index(name))
    q, qd, qdd = _states(rig, rng, N_STATES)
    f = rng.normal(0.0, 1000.0, size=(N_STATES, 3))
    m = dyn.mass_matrix(rig, q)
    c = dyn.coriolis_matrix(rig, q, qd)
    jac = jacobian(rig, q)
    expected = (
        np.einsum("nij,nj->ni", m, qdd)
        + np.einsum("nij,nj->ni", c, qd)
        + dyn.gravity_torque(rig, q)
        - np.einsum("nji,nj->ni", jac, f)
    )
    tau = dyn.inverse_dynamics(rig, q, qd, qdd, f)
    for n in range(N_STATES):
        _close(tau[n], expected[n], 1e-12, "tau", f"rig={name} q={q[n].tolist()}")
    ke = 0.5 * np.einsum("ni,nij,nj->n", qd, m, qd)
    np.testing.assert_allclose(dyn.kinetic_energy(rig, q, qd), ke, rtol=1e-12)


@pytest.mark.parametrize("name", CASES)
def test_mass_matrix_spd_and_skew_identity(name: str) -> None:
    rig = _rig(name)
    rng = np.random.default_rng(3000 + CASES.index(name))
    q, qd, _ = _states(rig, rng, N_STATES)
    m = dyn.mass_matrix(rig, q)
    np.testing.assert_array_equal(m, np.swapaxes(m, -1, -2))
    eig = np.linalg.eigvalsh(m)
    bad = np.flatnonzero(eig.min(axis=-1) <= 0.0)
    assert bad.size == 0, f"rig={name}: M not positive definite at q={q[bad[0]].tolist()}"

    h = 1e-6
    m_dot = (dyn.mass_matrix(rig, q + h * qd) - dyn.mass_matrix(rig, q - h * qd)) / (2.0 * h)
    n_mat = m_dot - 2.0 * dyn.coriolis_matrix(rig, q, qd)
    sym = n_mat + np.swapaxes(n_mat, -1, -2)
    scale = np.abs(m_dot).max(axis=(-1, -2)) + np.abs(m).max(axis=(-1, -2)) * 1e-6
    worst = int(np.argmax(np.abs(sym).max(axis=(-1, -2)) / scale))
    assert np.abs(sym[worst]).max() <= 1e-7 * scale[worst], (
        f"rig={name}: M_dot - 2C not skew at q={q[worst].tolist()} qd={qd[worst].tolist()}: "
        f"{sym[worst].tolist()}"
    )


def _trajectory(rig: Rig, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sums of sines inside the joint limits, with analytic derivatives; shape (n, 3) each."""
    mid = 0.5 * (rig.q_min_rad + rig.q_max_rad)
    half = 0.5 * (rig.q_max_rad - rig.q_min_rad)
    amps = np.array([0.5, 0.3])[:, None] * half  # peak 0.8 of the half range
    freqs = np.array([[1.1, 1.7, 2.3], [2.9, 0.7, 3.1]])
    phases = np.array([[0.0, 1.0, 2.0], [0.5, 1.5, 2.5]])
    arg = freqs[None] * t[:, None, None] + phases[None]
    q = mid + np.sum(amps * np.sin(arg), axis=1)
    qd = np.sum(amps * freqs * np.cos(arg), axis=1)
    qdd = np.sum(-amps * freqs**2 * np.sin(arg), axis=1)
    return q, qd, qdd


@pytest.mark.parametrize("name", CASES)
def test_free_arm_power_balance(name: str) -> None:
    rig = _rig(name)
    t = np.linspace(0.0, 4.0, 401)
    h = 1e-5

    def energy(ts: np.ndarray) -> np.ndarray:
        q, qd, _ = _trajectory(rig, ts)
        return dyn.kinetic_energy(rig, q, qd) + dyn.potential_energy(rig, q)

    de_dt = (energy(t + h) - energy(t - h)) / (2.0 * h)
    q, qd, qdd = _trajectory(rig, t)
    power = dyn.joint_power(dyn.inverse_dynamics(rig, q, qd, qdd), qd)
    scale = np.abs(power).max()
    worst = int(np.argmax(np.abs(de_dt - power.sum(axis=-1))))
    err = abs(de_dt[worst] - power[worst].sum())
    assert err <= 1e-6 * scale, f"rig={name}: dE/dt - tau.qd = {err:.3e} at t={t[worst]}"

    # Integrated form through energy_j: the net work of the drives is the energy change.
    work = dyn.energy_j(t, power, mode="net")
    change = energy(t[-1:])[0] - energy(t[:1])[0]
    assert abs(work - change) <= 1e-4 * dyn.energy_j(t, power, mode="absolute"), (
        f"rig={name}: net work {work} vs energy change {change}"
    )


@pytest.mark.parametrize("name", CASES)
def test_tip_wrench_virtual_work_and_static_balance(name: str) -> None:
    rig = _rig(name)
    rng = np.random.default_rng(4000 + CASES.index(name))
    q, _, _ = _states(rig, rng, N_STATES)
    f = rng.normal(0.0, 1000.0, size=(N_STATES, 3))
    zero = np.zeros_like(q)
    tau_f = dyn.inverse_dynamics(rig, q, zero, zero, f)
    tau_0 = dyn.inverse_dynamics(rig, q, zero, zero)
    # Virtual work: the generalised force of a constant wrench is d(f . pose)/dq.
    h = 1e-6
    grad = np.empty_like(q)
    for i in range(3):
        step = np.zeros(3)
        step[i] = h
        dpose = forward(rig, q + step) - forward(rig, q - step)
        grad[:, i] = np.sum(f * dpose, axis=-1) / (2 * h)
    scale = np.abs(f).max() * rig.lengths_m.sum()
    worst = int(np.argmax(np.abs(tau_0 - tau_f - grad).max(axis=-1)))
    assert np.abs(tau_0 - tau_f - grad)[worst].max() <= 1e-7 * scale, (
        f"rig={name}: J^T f vs virtual work at q={q[worst].tolist()} f={f[worst].tolist()}"
    )
    # Static balance with qd = qdd = 0: tau = G - J^T f.
    expected = dyn.gravity_torque(rig, q) - np.einsum("nji,nj->ni", jacobian(rig, q), f)
    for n in range(N_STATES):
        _close(tau_f[n], expected[n], 1e-12, "static tau", f"rig={name} q={q[n].tolist()}")


def test_energy_modes_against_analytic_integrals() -> None:
    t = np.linspace(0.0, 2.0, 21)
    p = np.stack([3.0 * t - 3.0, np.full_like(t, 2.0), np.full_like(t, -1.0)], axis=-1)
    # Joint 0 crosses zero at t = 1 (a sample), so the trapezoid rule is exact piecewise.
    assert dyn.energy_j(t, p) == pytest.approx(1.5 + 4.0 + 0.0, rel=1e-12)
    assert dyn.energy_j(t, p, mode="positive") == pytest.approx(5.5, rel=1e-12)
    assert dyn.energy_j(t, p, mode="absolute") == pytest.approx(3.0 + 4.0 + 2.0, rel=1e-12)
    assert dyn.energy_j(t, p, mode="net") == pytest.approx(0.0 + 4.0 - 2.0, abs=1e-12)

    # Batched power with per-row time grids (..., n_samples) and a shared grid (n_samples,).
    rng = np.random.default_rng(5)
    durations = rng.uniform(1.0, 5.0, size=(4, 5))
    grids = durations[..., None] * np.linspace(0.0, 1.0, 11)
    const = rng.uniform(0.5, 3.0, size=(4, 5, 1, 3))
    power = np.broadcast_to(const, (4, 5, 11, 3))
    e = dyn.energy_j(grids, power)
    assert e.shape == (4, 5)
    np.testing.assert_allclose(e, const[..., 0, :].sum(-1) * durations, rtol=1e-12)
    e_shared = dyn.energy_j(grids[0, 0], power)
    np.testing.assert_allclose(e_shared, const[..., 0, :].sum(-1) * durations[0, 0], rtol=1e-12)


def test_energy_rejects_bad_input() -> None:
    t = np.linspace(0.0, 1.0, 5)
    p = np.ones((5, 3))
    with pytest.raises(ValueError, match="positive, absolute, net"):
        dyn.energy_j(t, p, mode="regenerative")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="power_w"):
        dyn.energy_j(t, np.ones((5, 2)))
    with pytest.raises(ValueError, match="power_w"):
        dyn.energy_j(t, np.ones(3))
    with pytest.raises(ValueError, match="t_s"):
        dyn.energy_j(np.linspace(0.0, 1.0, 4), p)


def test_shapes_and_shape_errors() -> None:
    rig = load_rig(RIGS[0])
    rng = np.random.default_rng(6)
    for batch in [(), (4, 5)]:
        q = rng.uniform(rig.q_min_rad, rig.q_max_rad, size=(*batch, 3))
        qd = rng.normal(size=(*batch, 3))
        assert dyn.inverse_dynamics(rig, q, qd, qd).shape == (*batch, 3)
        assert dyn.inverse_dynamics(rig, q, qd, qd, qd).shape == (*batch, 3)
        assert dyn.mass_matrix(rig, q).shape == (*batch, 3, 3)
        assert dyn.coriolis_matrix(rig, q, qd).shape == (*batch, 3, 3)
        assert dyn.gravity_torque(rig, q).shape == (*batch, 3)
        assert dyn.kinetic_energy(rig, q, qd).shape == batch
        assert dyn.potential_energy(rig, q).shape == batch
        assert dyn.joint_power(q, qd).shape == (*batch, 3)
    # Batch values do not depend on the batch around them.
    q = rng.uniform(rig.q_min_rad, rig.q_max_rad, size=(4, 5, 3))
    qd = rng.normal(size=(4, 5, 3))
    batched = dyn.inverse_dynamics(rig, q, qd, qd)
    single = dyn.inverse_dynamics(rig, q[2, 3], qd[2, 3], qd[2, 3])
    np.testing.assert_allclose(batched[2, 3], single, rtol=1e-14)
    # Inputs broadcast against each other: one wrench for the whole batch.
    wrench = np.array([100.0, -50.0, 5.0])
    np.testing.assert_allclose(
        dyn.inverse_dynamics(rig, q, qd, qd, wrench),
        dyn.inverse_dynamics(rig, q, qd, qd, np.broadcast_to(wrench, q.shape).copy()),
        rtol=1e-14,
    )

    good = np.zeros(3)
    bad = np.zeros((4, 2))
    calls: list[Callable[[], object]] = [
        lambda: dyn.inverse_dynamics(rig, bad, good, good),
        lambda: dyn.inverse_dynamics(rig, good, bad, good),
        lambda: dyn.inverse_dynamics(rig, good, good, bad),
        lambda: dyn.inverse_dynamics(rig, good, good, good, bad),
        lambda: dyn.mass_matrix(rig, bad),
        lambda: dyn.coriolis_matrix(rig, good, bad),
        lambda: dyn.gravity_torque(rig, 0.0),
        lambda: dyn.kinetic_energy(rig, bad, good),
        lambda: dyn.potential_energy(rig, bad),
        lambda: dyn.joint_power(good, bad),
    ]
    for call in calls:
        with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
            call()
