"""Batched constrained PSO and its DE reference on problems with known constrained optima."""

from __future__ import annotations

import numpy as np
import pytest

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning.pso import OptimResult, PsoResult, pso_minimize
from rt_runtime.planning.reference import de_minimize
from rt_runtime.trajectory.sextic import evaluate as sextic_evaluate
from rt_runtime.trajectory.sextic import sextic_coefficients


class HalfspaceSpheres:
    """B problems: min |x - c_b|^2 s.t. a_b . x >= beta_b, box [-5, 5]^d.

    The centre c_b is infeasible by delta_b along the unit normal a_b, so the optimum is the
    projection onto the plane, x* = c + delta a, f* = delta^2: on the constraint boundary.
    """

    def __init__(self, seed: int, n_problems: int, d: int) -> None:
        rng = np.random.default_rng(seed)
        self.c = rng.uniform(-2.5, 2.5, (n_problems, d))
        a = rng.normal(size=(n_problems, d))
        self.a = a / np.linalg.norm(a, axis=1, keepdims=True)
        self.delta = rng.uniform(0.5, 2.0, n_problems)
        self.beta = np.einsum("bd,bd->b", self.a, self.c) + self.delta
        self.x_star = self.c + self.delta[:, None] * self.a
        self.f_star = self.delta**2
        self.shapes: list[tuple[int, ...]] = []

    def __call__(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.shapes.append(X.shape)
        f = np.sum((X - self.c[:, None, :]) ** 2, axis=-1)
        g = self.beta[:, None] - np.einsum("bpd,bd->bp", X, self.a)
        return f, np.maximum(g, 0.0)

    def one(self, b: int):
        """Problem b alone, through the same (1, S, d) interface."""

        def ev(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            assert X.shape[0] == 1
            f = np.sum((X - self.c[b]) ** 2, axis=-1)
            return f, np.maximum(self.beta[b] - X @ self.a[b], 0.0)

        return ev


def _report(res: OptimResult, problems: HalfspaceSpheres, b: int) -> str:
    return (
        f"problem {b}: c={problems.c[b].tolist()}, a={problems.a[b].tolist()}, "
        f"delta={problems.delta[b]!r}; got x={res.x_best[b].tolist()} f={res.f_best[b]!r} "
        f"violation={res.violation_best[b]!r}; want x={problems.x_star[b].tolist()} "
        f"f={problems.f_star[b]!r}"
    )


def test_batch_of_twenty_boundary_optima_in_one_call() -> None:
    B, d, P = 20, 4, 60
    problems = HalfspaceSpheres(seed=11, n_problems=B, d=d)
    res = pso_minimize(
        problems, -5.0 * np.ones(d), 5.0 * np.ones(d),
        n_problems=B, n_particles=P, n_iterations=300, seed=3,
    )
    # One evaluate call per iteration plus the initial swarm, each with every particle of
    # every problem.
    assert problems.shapes == [(B, P, d)] * (res.iterations + 1)
    assert res.iterations == 300
    assert res.evaluations == P * 301
    assert res.x_best.shape == (B, d)
    assert res.history_f_best.shape == res.history_violation_best.shape == (300, B)
    # Stated tolerances: objective within 1e-3 * max(1, f*), point within 0.05, feasible.
    for b in range(B):
        assert res.feasible[b], _report(res, problems, b)
        assert res.violation_best[b] == 0.0, _report(res, problems, b)
        assert res.f_best[b] >= problems.f_star[b] - 1e-12, _report(res, problems, b)
        assert res.f_best[b] - problems.f_star[b] <= 1e-3 * max(1.0, problems.f_star[b]), (
            _report(res, problems, b)
        )
        assert np.linalg.norm(res.x_best[b] - problems.x_star[b]) <= 0.05, (
            _report(res, problems, b)
        )
    assert res.require_feasible() is res


def test_best_never_gets_worse_under_deb_ranking() -> None:
    problems = HalfspaceSpheres(seed=12, n_problems=8, d=3)
    res = pso_minimize(problems, -5.0 * np.ones(3), 5.0 * np.ones(3), n_problems=8,
                       n_particles=10, n_iterations=80, seed=5)
    f, v = res.history_f_best, res.history_violation_best
    assert np.all(np.diff(v, axis=0) <= 0.0)
    both_feasible = (v[1:] == 0.0) & (v[:-1] == 0.0)
    assert np.all(np.diff(f, axis=0)[both_feasible] <= 0.0)


def test_same_seed_same_result_other_seed_other_path() -> None:
    problems = HalfspaceSpheres(seed=13, n_problems=5, d=4)
    kwargs = dict(n_problems=5, n_particles=20, n_iterations=50)
    r1 = pso_minimize(problems, -5 * np.ones(4), 5 * np.ones(4), seed=42, **kwargs)
    r2 = pso_minimize(problems, -5 * np.ones(4), 5 * np.ones(4), seed=42, **kwargs)
    r3 = pso_minimize(problems, -5 * np.ones(4), 5 * np.ones(4), seed=43, **kwargs)
    for field in ("x_best", "f_best", "violation_best", "feasible", "history_f_best"):
        np.testing.assert_array_equal(getattr(r1, field), getattr(r2, field), err_msg=field)
    assert not np.array_equal(r1.history_f_best, r3.history_f_best)
    r4 = pso_minimize(problems, -5 * np.ones(4), 5 * np.ones(4),
                      seed=np.random.default_rng(42), **kwargs)
    np.testing.assert_array_equal(r1.x_best, r4.x_best)


def test_infeasible_problems_are_reported_not_hidden() -> None:
    # Problem 1 asks for x0 >= 10 inside [-5, 5]^2: nothing is feasible, the least violation
    # is 5 at the bound (which the absorbing walls reach exactly). Problems 0 and 2 are fine.
    shift = np.array([0.0, 10.0, 1.0])

    def evaluate(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = np.sum(X**2, axis=-1)
        return f, np.maximum(shift[:, None] - X[..., 0], 0.0)

    res = pso_minimize(evaluate, [-5.0, -5.0], [5.0, 5.0], n_problems=3, n_particles=20,
                       n_iterations=60, seed=1)
    np.testing.assert_array_equal(res.feasible, [True, False, True])
    assert res.violation_best[1] == pytest.approx(5.0, abs=1e-12)
    assert res.x_best[1, 0] == 5.0
    with pytest.raises(PlanningError, match=r"1 of 3 problems: problem 1 \(smallest total "
                                            r"violation 5\)"):
        res.require_feasible()


def test_initial_guesses_are_used_and_validated() -> None:
    problems = HalfspaceSpheres(seed=14, n_problems=4, d=3)
    # The known optimum as a guess: the result is at least as good (feasible within 1e-12).
    res = pso_minimize(problems, -5 * np.ones(3), 5 * np.ones(3), n_particles=8,
                       n_iterations=5, seed=0, x0=problems.x_star[:, None, :],
                       violation_tol=1e-12)
    assert res.feasible.all()
    assert np.all(res.f_best <= problems.f_star * (1 + 1e-12))
    with pytest.raises(ConfigurationError, match="outside the bounds"):
        pso_minimize(problems, -5 * np.ones(3), 5 * np.ones(3), n_particles=8,
                     x0=np.full((4, 1, 3), 6.0))
    with pytest.raises(ValueError, match="only 8 particles"):
        pso_minimize(problems, -5 * np.ones(3), 5 * np.ones(3), n_particles=8,
                     x0=np.zeros((4, 9, 3)))


def test_non_finite_objectives_rank_last() -> None:
    # The objective is NaN on half the box; the optimum (x = 1) lies in the other half.
    def evaluate(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f = np.where(X[..., 0] < 0.0, np.nan, (X[..., 0] - 1.0) ** 2)
        return f, np.zeros(X.shape[:2])

    res = pso_minimize(evaluate, [-3.0], [3.0], n_particles=10, n_iterations=100, seed=2)
    assert res.feasible[0]
    assert res.x_best[0, 0] == pytest.approx(1.0, abs=1e-4)
    assert np.all(np.isfinite(res.history_f_best))


def test_early_stop_after_patience_iterations_without_progress() -> None:
    problems = HalfspaceSpheres(seed=16, n_problems=2, d=2)
    full = pso_minimize(problems, -5 * np.ones(2), 5 * np.ones(2), n_problems=2,
                        n_particles=20, n_iterations=400, seed=8)
    res = pso_minimize(problems, -5 * np.ones(2), 5 * np.ones(2), n_problems=2,
                       n_particles=20, n_iterations=400, seed=8, tol=1e-9, patience=10)
    assert res.iterations < 400
    assert res.history_f_best.shape == (res.iterations, 2)
    assert res.evaluations == 20 * (res.iterations + 1)
    # Same seed: the stopped run is a prefix of the full one.
    np.testing.assert_array_equal(res.history_f_best, full.history_f_best[: res.iterations])
    # Every problem's best moved by at most tol over the last `patience` iterations.
    tail = res.history_f_best[-11:]
    assert np.all(tail[0] - tail[-1] <= 10 * 1e-9)


def test_bad_arguments_are_refused() -> None:
    def ok(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(X.shape[:2]), np.zeros(X.shape[:2])

    with pytest.raises(ConfigurationError, match="lower > upper"):
        pso_minimize(ok, [0.0, 1.0], [1.0, 0.0])
    with pytest.raises(ConfigurationError, match="finite"):
        pso_minimize(ok, [0.0, -np.inf], [1.0, 0.0])
    with pytest.raises(ValueError, match="broadcast"):
        pso_minimize(ok, [0.0, 0.0], [1.0, 1.0, 1.0])
    with pytest.raises(ConfigurationError, match="n_particles"):
        pso_minimize(ok, [0.0], [1.0], n_particles=1)
    with pytest.raises(ConfigurationError, match="velocity_max_fraction"):
        pso_minimize(ok, [0.0], [1.0], velocity_max_fraction=0.0)
    with pytest.raises(ValueError, match=r"shaped \(1, 40\)"):
        pso_minimize(lambda X: (np.zeros(3), np.zeros(3)), [0.0], [1.0])
    with pytest.raises(ValueError, match="negative violation"):
        pso_minimize(lambda X: (np.zeros(X.shape[:2]), -np.ones(X.shape[:2])), [0.0], [1.0])
    with pytest.raises(ValueError, match="one problem"):
        de_minimize(ok, np.zeros((2, 1)), np.ones((2, 1)))
    assert PsoResult is OptimResult


def test_de_reference_agrees_with_pso_and_the_known_optimum() -> None:
    problems = HalfspaceSpheres(seed=15, n_problems=3, d=4)
    pso = pso_minimize(problems, -5 * np.ones(4), 5 * np.ones(4), n_problems=3,
                       n_particles=60, n_iterations=300, seed=7)
    for b in range(3):
        de = de_minimize(problems.one(b), -5 * np.ones(4), 5 * np.ones(4), seed=b)
        assert de.feasible[0], _report(de, problems, b)
        assert de.history_f_best.shape == (de.iterations, 1)
        np.testing.assert_allclose(de.x_best[0], problems.x_star[b], atol=1e-3)
        assert abs(de.f_best[0] - pso.f_best[b]) <= 1e-3 * max(1.0, problems.f_star[b]), (
            f"DE f={de.f_best[0]!r}, PSO f={pso.f_best[b]!r}; " + _report(pso, problems, b)
        )
        assert np.linalg.norm(de.x_best[0] - pso.x_best[b]) <= 0.05


def test_de_reports_infeasibility_like_pso() -> None:
    def evaluate(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.sum(X**2, axis=-1), np.maximum(10.0 - X[..., 0], 0.0)

    de = de_minimize(evaluate, [-5.0, -5.0], [5.0, 5.0], seed=0, maxiter=30)
    assert not de.feasible[0]
    assert de.violation_best[0] == pytest.approx(5.0, abs=1e-3)
    with pytest.raises(PlanningError, match="problem 0"):
        de.require_feasible()


def test_pso_and_de_agree_on_a_minimum_time_sextic() -> None:
    """A Yao-shaped problem: particles (K1, K2, T) of two rest-to-rest sextics.

    Minimise T + 0.01 sum(K^2) subject to |qd| <= 0.5 rad/s and |qdd| <= 0.4 rad/s^2 on a
    101-sample grid; the shape terms K = -a6 T^6 (rad) keep the search box well scaled.
    """
    qs, qe = np.array([0.2, -1.0]), np.array([1.1, -0.3])
    qd_max, qdd_max = 0.5, 0.4

    def evaluate(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        K, T = X[..., :2], X[..., 2]
        a6 = -K / T[..., None] ** 6
        samples = sextic_evaluate(sextic_coefficients(qs, qe, a6, T), T, 101)
        vel = np.max(np.abs(samples.qd_rad_s), axis=-2) - qd_max
        acc = np.max(np.abs(samples.qdd_rad_s2), axis=-2) - qdd_max
        violation = np.sum(np.maximum(vel, 0.0) + np.maximum(acc, 0.0), axis=-1)
        return T + 0.01 * np.sum(K**2, axis=-1), violation

    lower, upper = [-3.0, -3.0, 1.0], [3.0, 3.0, 10.0]
    pso = pso_minimize(evaluate, lower, upper, n_particles=40, n_iterations=200, seed=4)
    de = de_minimize(evaluate, lower, upper, seed=4, maxiter=300)
    pso.require_feasible()
    de.require_feasible()
    # The quintic alone (K = 0) needs T >= max(1.875 D / qd_max, sqrt(5.7735 D / qdd_max));
    # shaping must not make it slower than that.
    D = np.max(np.abs(qe - qs))
    quintic_T = max(1.875 * D / qd_max, np.sqrt(10 / np.sqrt(3) * D / qdd_max))
    assert de.f_best[0] <= quintic_T + 1e-6
    assert abs(pso.f_best[0] - de.f_best[0]) <= 2e-3 * de.f_best[0], (
        f"PSO {pso.x_best[0].tolist()} f={pso.f_best[0]!r}; "
        f"DE {de.x_best[0].tolist()} f={de.f_best[0]!r}"
    )
