"""Sextic joint trajectories (Yao eq 9-10, corrected): identities, finite differences, errors."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp
from numpy.polynomial import polynomial as npoly

from rt_runtime.errors import PlanningError
from rt_runtime.trajectory.sextic import (
    SexticTrajectory,
    evaluate,
    sextic_coefficients,
)

N_CASES = 300


def _random_cases(seed: int, n_cases: int = N_CASES, n_joints: int = 3):
    """Start/end poses within +-3 rad, T in [0.5, 12] s, shape term K = -a6 T^6 within +-4 rad."""
    rng = np.random.default_rng(seed)
    qs = rng.uniform(-3.0, 3.0, (n_cases, n_joints))
    qe = rng.uniform(-3.0, 3.0, (n_cases, n_joints))
    T = rng.uniform(0.5, 12.0, n_cases)
    K = rng.uniform(-4.0, 4.0, (n_cases, n_joints))
    a6 = -K / T[:, None] ** 6
    return qs, qe, a6, T


def _closed_form(qs, qe, a6, T):
    """Corrected eq 10, written out term by term."""
    D = qe - qs
    T = T[..., None]
    return np.stack(
        [
            qs,
            np.zeros_like(qs),
            np.zeros_like(qs),
            10 * D / T**3 - a6 * T**3,
            -15 * D / T**4 + 3 * a6 * T**2,
            6 * D / T**5 - 3 * a6 * T,
            a6,
        ],
        axis=-1,
    )


def _assert_close(actual, expected, atol, rtol, what, cases):
    err = np.abs(actual - expected) - (atol + rtol * np.abs(expected))
    if np.any(err > 0):
        idx = np.unravel_index(np.argmax(err), err.shape)
        case = idx[0]
        qs, qe, a6, T = (c[case] for c in cases)
        pytest.fail(
            f"{what}: {actual[idx]!r} != {expected[idx]!r} at index {idx}; case "
            f"q_start={qs.tolist()}, q_end={qe.tolist()}, a6={a6.tolist()}, T={T!r}"
        )


def test_boundary_conditions_hold_for_random_cases() -> None:
    cases = _random_cases(1)
    qs, qe, a6, T = cases
    C = sextic_coefficients(qs, qe, a6, T)
    assert C.shape == (N_CASES, 3, 7)
    # Through the batched evaluator...
    t, q, qd, qdd, _ = evaluate(C, T, n_samples=2)
    _assert_close(t[:, 0], np.zeros(N_CASES), 0, 0, "t(0)", cases)
    _assert_close(t[:, 1], T, 0, 1e-15, "t(end)", cases)
    _assert_close(q[:, 0], qs, 1e-9, 0, "q(0)", cases)
    _assert_close(q[:, 1], qe, 1e-9, 0, "q(T)", cases)
    for name, x in (("qd", qd), ("qdd", qdd)):
        _assert_close(x[:, 0], np.zeros_like(qs), 1e-9, 0, f"{name}(0)", cases)
        _assert_close(x[:, 1], np.zeros_like(qs), 1e-9, 0, f"{name}(T)", cases)
    # ...and independently through numpy's polynomial tools in t.
    for j, expected_start, expected_end in ((0, qs, qe), (1, 0 * qs, 0 * qs), (2, 0 * qs, 0 * qs)):
        dC = npoly.polyder(C, m=j, axis=-1) if j else C
        at0 = dC[..., 0]
        atT = np.sum(dC * T[:, None, None] ** np.arange(dC.shape[-1]), axis=-1)
        _assert_close(at0, expected_start, 1e-9, 0, f"d{j} at 0 (polyval)", cases)
        _assert_close(atT, expected_end, 1e-9, 1e-12, f"d{j} at T (polyval)", cases)


def test_coefficients_match_corrected_eq10_and_q_p_form() -> None:
    cases = _random_cases(2)
    qs, qe, a6, T = cases
    C = sextic_coefficients(qs, qe, a6, T)
    expected = _closed_form(qs, qe, a6, T)
    _assert_close(C, expected, 1e-12, 1e-12, "coefficient vs corrected eq 10", cases)

    # theta = theta1 + D q(s) + K p(s) with K = -a6 T^6, at random interior s.
    s = np.random.default_rng(3).uniform(0.0, 1.0, 17)
    _, q, *_ = evaluate(C, T, s_grid=s)
    D = (qe - qs)[:, None, :]
    K = (-a6 * T[:, None] ** 6)[:, None, :]
    S = s[None, :, None]
    qp = qs[:, None, :] + D * (10 * S**3 - 15 * S**4 + 6 * S**5) + K * S**3 * (1 - S) ** 3
    _assert_close(q, qp, 1e-10, 1e-10, "q vs theta1 + D q(s) + K p(s)", cases)


def test_corrected_eq10_is_the_q_p_family_symbolically() -> None:
    t, T, th1, th2, a6 = sp.symbols("t T theta1 theta2 a6", positive=True)
    D = th2 - th1
    s = t / T
    theta = th1 + D * (10 * s**3 - 15 * s**4 + 6 * s**5) + (-a6 * T**6) * s**3 * (1 - s) ** 3
    poly = sp.Poly(sp.expand(theta), t)
    got = [sp.simplify(poly.coeff_monomial(t**k)) for k in range(7)]
    want = [
        th1,
        0,
        0,
        10 * D / T**3 - a6 * T**3,
        -15 * D / T**4 + 3 * a6 * T**2,
        6 * D / T**5 - 3 * a6 * T,
        a6,
    ]
    for k in range(7):
        assert sp.simplify(got[k] - want[k]) == 0, f"a{k}: {got[k]} != {want[k]}"
    for expr, at in ((theta, 0), (theta, T)):
        for j in (1, 2):
            assert sp.simplify(sp.diff(expr, t, j).subs(t, at)) == 0
    assert sp.simplify(theta.subs(t, T) - th2) == 0


def test_derivatives_match_central_finite_differences() -> None:
    cases = _random_cases(4, n_cases=100)
    qs, qe, a6, T = cases
    C = sextic_coefficients(qs, qe, a6, T)
    s = np.linspace(0.05, 0.95, 19)
    h = 1e-4  # s step; per-candidate time step h*T
    grid = s[None, :] + np.array([-h, 0.0, h])[:, None, None]  # (3, 1, m)
    grid = np.broadcast_to(grid, (3, 100, s.size))
    samples = [evaluate(C, T, s_grid=g) for g in grid]
    dt = (h * T)[:, None, None]
    pairs = (
        ("qd", samples[1].qd_rad_s, samples[0].q_rad, samples[2].q_rad),
        ("qdd", samples[1].qdd_rad_s2, samples[0].qd_rad_s, samples[2].qd_rad_s),
        ("qddd", samples[1].qddd_rad_s3, samples[0].qdd_rad_s2, samples[2].qdd_rad_s2),
    )
    for name, analytic, lo, hi in pairs:
        fd = (hi - lo) / (2 * dt)
        scale = np.max(np.abs(analytic), axis=1, keepdims=True)
        _assert_close(analytic, fd, 1e-6 * scale, 0, f"{name} vs central difference", cases)


def test_shared_and_per_candidate_grids_agree_and_broadcast() -> None:
    cases = _random_cases(5, n_cases=40)
    qs, qe, a6, T = cases
    # One start/end pose against many candidate (a6, T): leading axes broadcast.
    C = sextic_coefficients(qs[0], qe[0], a6, T)
    assert C.shape == (40, 3, 7)
    shared = evaluate(C, T, n_samples=11)
    per = evaluate(C, T, s_grid=np.broadcast_to(np.linspace(0, 1, 11), (40, 11)))
    for a, b in zip(shared, per, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    assert shared.q_rad.shape == (40, 11, 3)
    assert shared.t_s.shape == (40, 11)
    # Extra leading axes: (2, 20) candidates.
    C2 = C.reshape(2, 20, 3, 7)
    two = evaluate(C2, T.reshape(2, 20), n_samples=11)
    np.testing.assert_allclose(two.qdd_rad_s2.reshape(40, 11, 3), shared.qdd_rad_s2, atol=0)
    # The optimiser's hot shape.
    big = _random_cases(6, n_cases=2000)
    out = evaluate(sextic_coefficients(*big), big[3], n_samples=101)
    assert out.q_rad.shape == out.qddd_rad_s3.shape == (2000, 101, 3)


def test_trajectory_sample_agrees_with_batched_evaluate() -> None:
    qs, qe, a6, T = _random_cases(7, n_cases=25)
    s = np.linspace(0.0, 1.0, 23)
    for i in range(25):
        traj = SexticTrajectory(qs[i], qe[i], a6[i], float(T[i]))
        batch = evaluate(traj.coefficients, traj.T_s, s_grid=s)
        for k, t in enumerate(batch.t_s):
            q, qd, qdd = traj.sample(float(t))
            case = f"case {i}: q_start={qs[i].tolist()}, q_end={qe[i].tolist()}, t={t}"
            np.testing.assert_allclose(q, batch.q_rad[k], atol=1e-9, err_msg=case)
            np.testing.assert_allclose(qd, batch.qd_rad_s[k], atol=1e-9, err_msg=case)
            np.testing.assert_allclose(qdd, batch.qdd_rad_s2[k], atol=1e-9, err_msg=case)


def test_trajectory_holds_end_poses_outside_its_duration() -> None:
    traj = SexticTrajectory(np.array([0.1, -1.0]), np.array([0.5, -0.2]), np.array([1e-4, 0]), 4.0)
    for t, pose in ((-1.0, traj.q_start_rad), (0.0, traj.q_start_rad), (4.0, traj.q_end_rad),
                    (9.0, traj.q_end_rad)):
        q, qd, qdd = traj.sample(t)
        np.testing.assert_array_equal(q, pose)
        np.testing.assert_array_equal(qd, 0.0)
        np.testing.assert_array_equal(qdd, 0.0)
    np.testing.assert_allclose(
        traj.coefficients, sextic_coefficients(traj.q_start_rad, traj.q_end_rad, traj.a6, 4.0)
    )
    assert not traj.coefficients.flags.writeable
    assert traj.n_joints == 2


@pytest.mark.parametrize(
    ("args", "error", "match"),
    [
        (([0.0], [1.0], [0.0], 0.0), PlanningError, "T_s"),
        (([0.0], [1.0], [0.0], -2.0), PlanningError, "T_s"),
        (([0.0], [1.0], [0.0], np.inf), PlanningError, "T_s"),
        (([0.0], [1.0], [0.0], np.nan), PlanningError, "T_s"),
        (([np.nan], [1.0], [0.0], 1.0), PlanningError, "q_start_rad"),
        (([0.0], [np.inf], [0.0], 1.0), PlanningError, "q_end_rad"),
        (([0.0], [1.0], [np.nan], 1.0), PlanningError, "a6"),
        (([0.0, 1.0], [1.0], [0.0], 1.0), ValueError, "number of joints"),
        ((np.zeros((4, 3)), np.zeros((5, 3)), np.zeros(3), 1.0), ValueError, "broadcast"),
        ((np.zeros((4, 3)), np.zeros(3), np.zeros(3), np.ones(5)), ValueError, "broadcast"),
        ((0.0, 1.0, 0.0, 1.0), ValueError, "scalar"),
    ],
)
def test_coefficients_reject_bad_input(args, error, match) -> None:
    with pytest.raises(error, match=match):
        sextic_coefficients(*args)


def test_evaluate_and_trajectory_reject_bad_input() -> None:
    C = sextic_coefficients(np.zeros((4, 3)), np.ones((4, 3)), np.zeros((4, 3)), np.ones(4))
    with pytest.raises(ValueError, match="exactly one"):
        evaluate(C, np.ones(4))
    with pytest.raises(ValueError, match="exactly one"):
        evaluate(C, np.ones(4), 5, s_grid=[0.0, 1.0])
    with pytest.raises(ValueError, match=">= 2"):
        evaluate(C, np.ones(4), 1)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        evaluate(C, np.ones(4), s_grid=[0.0, 1.5])
    with pytest.raises(ValueError, match=r"\(\.\.\., n_joints, 7\)"):
        evaluate(C[..., :6], np.ones(4), 5)
    with pytest.raises(ValueError, match="broadcast"):
        evaluate(C, np.ones(3), 5)
    with pytest.raises(PlanningError, match="T_s"):
        evaluate(C, np.array([1.0, 1.0, 0.0, 1.0]), 5)
    with pytest.raises(PlanningError, match="coeffs"):
        evaluate(np.full((4, 3, 7), np.nan), np.ones(4), 5)
    with pytest.raises(PlanningError, match="T_s"):
        SexticTrajectory(np.zeros(3), np.ones(3), np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="q_end_rad"):
        SexticTrajectory(np.zeros(3), np.ones((1, 3)), np.zeros(3), 1.0)
    with pytest.raises(ValueError, match="number of joints"):
        SexticTrajectory(np.zeros(3), np.ones(2), np.zeros(3), 1.0)
    traj = SexticTrajectory(np.zeros(3), np.ones(3), np.zeros(3), 1.0)
    with pytest.raises(ValueError, match="finite"):
        traj.sample(float("nan"))
