"""Batched constrained PSO and its DE reference on problems with known constrained optima."""

from __future__ import annotations

import numpy as np
import pytest

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning.pso import (
    OptimResult,
    PsoResult,
    Topology,
    deb_better,
    pso_minimize,
    slsqp_polish,
)
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

    def constraints(self, rows: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The polish interface: problems ``rows`` at points ``X (n, S, d)``, one constraint."""
        f = np.sum((X - self.c[rows][:, None, :]) ** 2, axis=-1)
        g = self.beta[rows][:, None] - np.einsum("nsd,nd->ns", X, self.a[rows])
        return f, g[..., None]

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


# --- ring topology, per-problem streams ---------------------------------------------------


def test_ring_guide_is_the_deb_best_of_each_particle_and_its_two_neighbours() -> None:
    from rt_runtime.planning.pso import _ring_best

    rng = np.random.default_rng(21)
    B, P, d = 4, 7, 3
    p_x = rng.normal(size=(B, P, d))
    p_f = rng.normal(size=(B, P))
    p_v = np.where(rng.random((B, P)) < 0.4, rng.random((B, P)), 0.0)
    guide = _ring_best(p_x, p_f, p_v, 0.0)
    for b in range(B):
        for i in range(P):
            hood = [(i - 1) % P, i, (i + 1) % P]
            best = i
            for j in hood:
                if deb_better(p_f[b, j], p_v[b, j], p_f[b, best], p_v[b, best], 0.0):
                    best = j
            np.testing.assert_array_equal(guide[b, i], p_x[b, best], err_msg=f"b={b} i={i}")


def test_ring_topology_finds_the_boundary_optima() -> None:
    B, d = 10, 4
    problems = HalfspaceSpheres(seed=17, n_problems=B, d=d)
    res = pso_minimize(problems, -5.0 * np.ones(d), 5.0 * np.ones(d), n_problems=B,
                       n_particles=40, n_iterations=300, seed=3, topology=Topology.RING)
    gbest = pso_minimize(problems, -5.0 * np.ones(d), 5.0 * np.ones(d), n_problems=B,
                         n_particles=40, n_iterations=300, seed=3)
    assert not np.array_equal(res.history_f_best, gbest.history_f_best)
    # The ring spreads information slowly: on one basin it converges later than gbest, hence a
    # looser tolerance here; the polish then lands on the boundary optimum.
    polished = slsqp_polish(problems.constraints, -5.0 * np.ones(d), 5.0 * np.ones(d),
                            res.x_best[:, None, :])
    for b in range(B):
        assert res.feasible[b], _report(res, problems, b)
        assert res.f_best[b] - problems.f_star[b] <= 1e-2 * max(1.0, problems.f_star[b]), (
            _report(res, problems, b)
        )
        assert polished.feasible[b, 0], _report(res, problems, b)
        # Within what the constraint margin of 1e-7 costs (df/dg = 2 delta <= 4).
        assert abs(polished.f_best[b, 0] - problems.f_star[b]) <= 1e-6, (
            f"polished f={polished.f_best[b, 0]!r}; " + _report(res, problems, b)
        )
    # The swarm memory comes back: every personal best, the best of them is x_best.
    assert res.swarm_x is not None and res.swarm_f is not None
    assert res.swarm_x.shape == (B, 40, d)
    np.testing.assert_array_equal(np.min(res.swarm_f, axis=1), res.f_best)


def test_a_problems_result_does_not_depend_on_its_batch() -> None:
    # Each problem has its own stream; with an evaluate that computes rows independently, a
    # problem solved alone with its stream gives bitwise the batch's answer.
    problems = HalfspaceSpheres(seed=18, n_problems=5, d=3)
    streams = [np.random.default_rng(100 + b) for b in range(5)]
    kwargs = dict(n_particles=12, n_iterations=40, topology=Topology.RING)
    together = pso_minimize(problems, -5 * np.ones(3), 5 * np.ones(3), n_problems=5,
                            seed=[np.random.default_rng(100 + b) for b in range(5)], **kwargs)
    for b in range(5):
        alone = pso_minimize(problems.one(b), -5 * np.ones(3), 5 * np.ones(3), n_problems=1,
                             seed=[streams[b]], **kwargs)
        np.testing.assert_array_equal(alone.x_best[0], together.x_best[b], err_msg=f"b={b}")
        np.testing.assert_array_equal(alone.history_f_best[:, 0], together.history_f_best[:, b])
    with pytest.raises(ValueError, match="2 random streams for 5 problems"):
        pso_minimize(problems, -5 * np.ones(3), 5 * np.ones(3), n_problems=5,
                     seed=streams[:2], **kwargs)


# --- SLSQP polish ---------------------------------------------------------------------------


class VertexLPs:
    """B problems: min c.x s.t. A x <= b, box [-5, 5]^4, optimum at a vertex of 4 constraints.

    The four constraint normals a_i are random and c = -sum lambda_i a_i with lambda_i > 0, so
    x* (where all four are active) satisfies KKT and is the unique minimum: c.x >= c.x* on the
    feasible cone. A few extra constraints are slack at x*. The feasible descent directions at
    x* form a narrow cone, the situation where a swarm creeps.
    """

    def __init__(self, seed: int, n_problems: int) -> None:
        rng = np.random.default_rng(seed)
        B, d = n_problems, 4
        self.x_star = rng.uniform(-2.0, 2.0, (B, d))
        a = rng.normal(size=(B, d, d))
        self.A = np.concatenate([a, rng.normal(size=(B, 2, d))], axis=1)  # (B, 6, d)
        lam = rng.uniform(0.5, 2.0, (B, d))
        self.c = -np.einsum("bi,bid->bd", lam, a)
        slack = np.concatenate([np.zeros((B, d)), rng.uniform(0.5, 1.0, (B, 2))], axis=1)
        self.b = np.einsum("bid,bd->bi", self.A, self.x_star) + slack
        self.f_star = np.einsum("bd,bd->b", self.c, self.x_star)
        self.calls = 0

    def constraints(self, rows: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.calls += 1
        f = np.einsum("nd,nsd->ns", self.c[rows], X)
        g = np.einsum("nid,nsd->nsi", self.A[rows], X) - self.b[rows][:, None, :]
        return f, g

    def total(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f, g = self.constraints(np.arange(self.c.shape[0]), X)
        return f, np.sum(np.maximum(g, 0.0), axis=-1)


def test_polish_lands_on_the_vertex_the_swarm_only_approaches() -> None:
    B = 8
    lps = VertexLPs(seed=31, n_problems=B)
    lo, hi = -5.0 * np.ones(4), 5.0 * np.ones(4)
    swarm = pso_minimize(lps.total, lo, hi, n_problems=B, n_particles=30, n_iterations=60,
                         seed=2)
    swarm_gap = swarm.f_best - lps.f_star
    # The plain swarm is feasible but short of the vertex on most problems.
    assert swarm.feasible.all()
    assert np.sum(swarm_gap > 1e-3 * np.maximum(1.0, np.abs(lps.f_star))) >= B // 2, swarm_gap
    res = slsqp_polish(lps.constraints, lo, hi, swarm.x_best[:, None, :])
    assert res.x_best.shape == (B, 1, 4) and res.f_best.shape == (B, 1)
    for b in range(B):
        case = (f"problem {b}: start {swarm.x_best[b].tolist()} f={swarm.f_best[b]!r}; got "
                f"{res.x_best[b, 0].tolist()} f={res.f_best[b, 0]!r}; want "
                f"{lps.x_star[b].tolist()} f={lps.f_star[b]!r}")
        assert res.feasible[b, 0] and res.violation_best[b, 0] == 0.0, case
        assert res.improved[b, 0], case
        assert abs(res.f_best[b, 0] - lps.f_star[b]) <= 1e-6 * max(1.0, abs(lps.f_star[b])), case
        np.testing.assert_allclose(res.x_best[b, 0], lps.x_star[b], atol=1e-5, err_msg=case)
        # Reported values are those of the returned point.
        f, g = lps.constraints(np.array([b]), res.x_best[b][None])
        assert f[0, 0] == res.f_best[b, 0] and np.all(g <= 0.0)
    assert np.all(res.evaluations % 5 == 0)  # a point and its 4 probes per request


def test_polish_batches_starts_in_lockstep_with_the_answers_of_solo_runs() -> None:
    B, k = 5, 3
    lps = VertexLPs(seed=32, n_problems=B)
    lo, hi = -5.0 * np.ones(4), 5.0 * np.ones(4)
    starts = np.random.default_rng(4).uniform(-5.0, 5.0, (B, k, 4))  # infeasible ones too
    together = slsqp_polish(lps.constraints, lo, hi, starts)
    calls_together = lps.calls
    again = slsqp_polish(lps.constraints, lo, hi, starts)
    for field in ("x_best", "f_best", "violation_best", "improved", "evaluations"):
        np.testing.assert_array_equal(getattr(together, field), getattr(again, field))
    # One evaluate call per round, not per start: far fewer calls than points requested.
    assert calls_together <= int(np.max(together.evaluations)) // 5 + 1
    for b in range(B):
        for j in range(k):

            def one(rows: np.ndarray, X: np.ndarray, b: int = b) -> tuple[np.ndarray, np.ndarray]:
                return lps.constraints(np.full_like(rows, b), X)

            solo = slsqp_polish(one, lo, hi, starts[b : b + 1, j : j + 1])
            np.testing.assert_array_equal(solo.x_best[0, 0], together.x_best[b, j])
            # Never worse than the start under Deb's rules.
            f0, g0 = lps.constraints(np.array([b]), starts[b : b + 1, j : j + 1])
            v0 = np.sum(np.maximum(g0, 0.0))
            assert not deb_better(f0[0, 0], v0, together.f_best[b, j],
                                  together.violation_best[b, j], 0.0)
    # Random starts, even infeasible ones, end on the vertex (the problem is convex).
    np.testing.assert_allclose(together.f_best, np.repeat(lps.f_star[:, None], k, 1),
                               rtol=1e-6, atol=1e-6)


def test_polish_releases_every_thread_when_evaluate_fails() -> None:
    import threading

    lps = VertexLPs(seed=33, n_problems=4)
    before = threading.active_count()

    def failing(rows: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if lps.calls >= 2:
            raise RuntimeError("model broke")
        return lps.constraints(rows, X)

    with pytest.raises(RuntimeError, match="model broke"):
        slsqp_polish(failing, -5 * np.ones(4), 5 * np.ones(4), np.zeros((4, 2, 4)))
    assert threading.active_count() == before
    with pytest.raises(ValueError, match=r"objective \(4, 5\)"):
        slsqp_polish(lambda rows, X: (np.zeros(3), np.zeros((3, 1))), -np.ones(4), np.ones(4),
                     np.zeros((4, 1, 4)))


def test_polish_refuses_bad_arguments() -> None:
    lps = VertexLPs(seed=34, n_problems=2)
    lo, hi = -5 * np.ones(4), 5 * np.ones(4)
    with pytest.raises(ValueError, match=r"x0 must be \(B, k, d\)"):
        slsqp_polish(lps.constraints, lo, hi, np.zeros((2, 4)))
    with pytest.raises(ConfigurationError, match=r"x0\[1, 0\] lies outside the bounds"):
        slsqp_polish(lps.constraints, lo, hi, np.array([[[0.0] * 4], [[6.0, 0, 0, 0]]]))
    with pytest.raises(ConfigurationError, match="step"):
        slsqp_polish(lps.constraints, lo, hi, np.zeros((2, 1, 4)), step=0.0)
    with pytest.raises(ConfigurationError, match="max_iterations"):
        slsqp_polish(lps.constraints, lo, hi, np.zeros((2, 1, 4)), max_iterations=0)


# --- the one-shot teacher -------------------------------------------------------------------


def test_polish_model_splits_peaks_and_keeps_feasibility_identical() -> None:
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.oneshot import _polish_model
    from rt_runtime.rig import load_rig

    rig = load_rig("scale_model")
    problems = oneshot.sample_problems(rig, 3, oneshot.DigType.BACKWARD, seed=7)
    qs = np.array([p.q_start_rad for p in problems])
    qe = np.array([p.q_end_rad for p in problems])
    h = np.array([p.surface_y_m for p in problems])
    kind = np.array([int(p.dig_type) for p in problems])
    lo, hi = oneshot.search_bounds(rig)
    X = lo + np.random.default_rng(8).random((3, 200, 4)) * (hi - lo)
    f, c = _polish_model(rig, qs, qe, h, kind, X, 51)
    a6, T = oneshot.a6_from_particle(X)
    ev = oneshot.evaluate(rig, qs, qe, h, kind, a6, T, 51)
    np.testing.assert_array_equal(f, ev.objective)
    assert c.shape == (3, 200, 28)
    # max(positive peak, negative peak) is the peak magnitude that evaluate constrains.
    np.testing.assert_allclose(np.maximum(c[..., 6:9], c[..., 9:12]), ev.violations[..., 6:9],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.maximum(c[..., 12:15], c[..., 15:18]),
                               ev.violations[..., 9:12], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(c[..., :6], ev.violations[..., :6])
    np.testing.assert_array_equal(c[..., 18:], ev.violations[..., 12:])
    feasible = np.all(c <= 0.0, axis=-1)
    np.testing.assert_array_equal(feasible, ev.feasible)
    assert 0 < feasible.sum() < feasible.size  # both kinds occur


def test_solve_pso_polish_never_worse_deterministic_and_independent_of_workers() -> None:
    from rt_runtime.planning import oneshot
    from rt_runtime.rig import load_rig

    rig = load_rig("scale_model")
    problems = (oneshot.sample_problems(rig, 2, oneshot.DigType.DOWNWARD, seed=11)
                + oneshot.sample_problems(rig, 1, oneshot.DigType.BACKWARD, seed=12))
    small = dict(n_particles=16, n_iterations=15, seed=5)
    swarm_only = oneshot.solve_pso(rig, problems, polish_starts=0, **small)
    polished = oneshot.solve_pso(rig, problems, **small)
    again = oneshot.solve_pso(rig, problems, **small)
    split = oneshot.solve_pso(rig, problems, workers=2, **small)
    alone = oneshot.solve_pso(rig, problems[1:2], **small)[0]
    for i, (s0, s1, s2, s3) in enumerate(zip(swarm_only, polished, again, split, strict=True)):
        case = f"problem {i}: {s1.problem}"
        assert s1.method == "pso" and s1.feasible, case
        # The polish adds candidates to the same swarm's: never worse on the default grid.
        assert s1.objective <= s0.objective or not s0.feasible, case
        # Feasible means feasible on the default grid, checked there.
        assert all(m >= 0.0 for _, m in s1.margins), case
        assert (s1.a6, s1.T_s) == (s2.a6, s2.T_s), case
        assert s3.objective == pytest.approx(s1.objective, rel=1e-6), case
    assert alone.objective == pytest.approx(polished[1].objective, rel=1e-6)
    for bad, match in (
        (dict(search_samples=1), "search_samples"),
        (dict(polish_starts=17), "polish_starts"),
        (dict(workers=0), "workers"),
        (dict(seed=-1), "seed"),
    ):
        with pytest.raises(ConfigurationError, match=match):
            oneshot.solve_pso(rig, problems, **{**small, **bad})
