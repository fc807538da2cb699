"""Constrained particle swarm optimisation, vectorised over the swarm and over many problems.

This is the offline teacher of Yao section 4.2: it minimises eq 12 over the 4-dim particle
``(a16, a26, a36, T)``, but it is written for any dimension d and any number B of independent
problems (e.g. many dig entry/exit pose pairs), solved in lockstep. The caller supplies one
batched function ``evaluate(X) -> (objective, violation)`` with ``X`` shaped ``(B, P, d)`` and
both outputs ``(B, P)``; each iteration calls it once for every particle of every problem.

The method (Yao gives no PSO settings, so these are the standard global-best PSO with the
Shi-Eberhart linearly decreasing inertia weight):

* 40 particles and 100 iterations by default (Yao's Fig. 7 converges by iteration 38 of 50);
* velocity ``v <- w v + c1 r1 (pbest - x) + c2 r2 (gbest - x)`` with ``r1, r2 ~ U(0, 1)`` drawn
  per particle and dimension; ``w`` falls linearly from 0.9 to 0.4 over the run (broad search
  first, then refinement); ``c1 = c2 = 2.0``;
* each velocity component is clamped to ``+-0.2 (upper - lower)`` so that no particle crosses
  the box in fewer than five steps;
* bounds by clipping with absorbing walls: a coordinate that leaves the box is put on the bound
  and its velocity component is zeroed. Optima of the dig problem often sit on a bound (the
  shortest allowed T), which clipping reaches exactly and reflection only approaches;
* constraints by feasibility-first ranking (Deb's rules): a feasible point (total violation
  ``<= violation_tol``) beats an infeasible one; two feasible points compare by objective; two
  infeasible points compare by total violation. Unlike a penalty, this needs no weight to tune
  against objectives of different scales, never lets a cheap infeasible point outrank a feasible
  one, and leaves the objective of feasible points untouched, so the optimum found is the
  constrained optimum rather than a compromise shifted by the penalty. A point whose objective
  is not finite, or whose violation is NaN, counts as infinitely violating.

The result says per problem whether a feasible point was found; an infeasible best is returned
flagged (``feasible`` False), never silently, and :meth:`OptimResult.require_feasible` raises.

Random numbers come from one ``numpy.random.Generator``: a run is reproducible for a fixed seed
and batch, but a problem's result depends on the other problems of its batch, because they
share the stream. Everything here runs outside the loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import ConfigurationError, PlanningError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

BatchEvaluate = Callable[[FloatArray], tuple[ArrayLike, ArrayLike]]
"""``evaluate(X (B, P, d)) -> (objective (B, P), total violation (B, P) >= 0)``."""


@dataclass(frozen=True, slots=True, eq=False)
class OptimResult:
    """Best points of B independent constrained minimisations (PSO or the DE reference).

    Attributes:
        x_best: ``(B, d)`` best point per problem under Deb's ranking.
        f_best: ``(B,)`` objective at ``x_best`` (meaningful for ranking only where feasible).
        violation_best: ``(B,)`` total constraint violation at ``x_best``; for an infeasible
            problem, the smallest violation found.
        feasible: ``(B,)`` whether ``violation_best <= violation_tol``.
        iterations: Iterations (PSO swarm updates, DE generations) performed.
        evaluations: Points evaluated per problem, including the initial swarm/population.
        history_f_best: ``(iterations, B)`` objective of the best point after each iteration.
        history_violation_best: ``(iterations, B)`` its total violation.
    """

    x_best: FloatArray
    f_best: FloatArray
    violation_best: FloatArray
    feasible: BoolArray
    iterations: int
    evaluations: int
    history_f_best: FloatArray
    history_violation_best: FloatArray

    def require_feasible(self) -> OptimResult:
        """Return self if every problem has a feasible best point.

        Raises:
            PlanningError: Naming the infeasible problems' indices and their smallest total
                violation.
        """
        bad = np.flatnonzero(~self.feasible)
        if bad.size:
            shown = ", ".join(
                f"problem {i} (smallest total violation {self.violation_best[i]:.6g})"
                for i in bad[:5]
            )
            more = f" and {bad.size - 5} more" if bad.size > 5 else ""
            raise PlanningError(
                f"no feasible solution for {bad.size} of {self.feasible.size} problems: "
                f"{shown}{more}"
            )
        return self


PsoResult = OptimResult
"""Name used by the PSO teacher's callers; the same class as the DE reference returns."""


def deb_better(
    f_a: FloatArray, v_a: FloatArray, f_b: FloatArray, v_b: FloatArray, violation_tol: float
) -> BoolArray:
    """Elementwise "a strictly beats b" under Deb's feasibility rules.

    Args:
        f_a: Objectives of a.
        v_a: Total violations of a (>= 0).
        f_b: Objectives of b, broadcastable with a.
        v_b: Total violations of b.
        violation_tol: Largest total violation that counts as feasible.

    Returns:
        Boolean array, the broadcast shape.
    """
    feas_a = v_a <= violation_tol
    feas_b = v_b <= violation_tol
    return np.asarray((feas_a & (~feas_b | (f_a < f_b))) | (~feas_a & ~feas_b & (v_a < v_b)))


def deb_argbest(f: FloatArray, v: FloatArray, violation_tol: float) -> NDArray[np.intp]:
    """Index of the best entry along the last axis under Deb's rules, shape ``f.shape[:-1]``."""
    feas = v <= violation_tol
    best_feasible = np.argmin(np.where(feas, f, np.inf), axis=-1)
    least_violating = np.argmin(v, axis=-1)
    return np.where(np.any(feas, axis=-1), best_feasible, least_violating)


def checked_evaluation(
    result: tuple[ArrayLike, ArrayLike], shape: tuple[int, ...]
) -> tuple[FloatArray, FloatArray]:
    """Validate and sanitise one ``evaluate`` output.

    A point whose objective is not finite or whose violation is NaN gets an infinite violation:
    it ranks below every point with a number, and never counts as feasible.

    Args:
        result: ``(objective, violation)`` as returned by the user's ``evaluate``.
        shape: Expected shape of both, ``(B, P)``.

    Returns:
        ``(objective, violation)`` as float arrays of ``shape``.

    Raises:
        ValueError: Wrong shapes or a negative violation.
    """
    try:
        f_raw, v_raw = result
    except (TypeError, ValueError):
        raise ValueError("evaluate must return a pair (objective, violation)") from None
    f = np.asarray(f_raw, dtype=np.float64)
    v = np.asarray(v_raw, dtype=np.float64)
    if f.shape != shape or v.shape != shape:
        raise ValueError(
            f"evaluate must return objective and violation shaped {shape} (B, P); "
            f"got {f.shape} and {v.shape}"
        )
    if np.any(v < 0.0):
        raise ValueError("evaluate returned a negative violation; it must be a total >= 0")
    bad = ~np.isfinite(f) | np.isnan(v)
    return f, np.where(bad, np.inf, v)


def bounds_array(lower: ArrayLike, upper: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Broadcast box bounds to ``(B, d)`` and validate them.

    Args:
        lower: ``(d,)`` or ``(B, d)`` lower bounds.
        upper: ``(d,)`` or ``(B, d)`` upper bounds.

    Returns:
        ``(lower, upper)``, both ``(B, d)`` (B = 1 when both are ``(d,)``).

    Raises:
        ValueError: Shapes that are not ``(d,)``/``(B, d)`` or do not broadcast.
        ConfigurationError: Non-finite bounds or ``lower > upper``.
    """
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    if lo.ndim not in (1, 2) or hi.ndim not in (1, 2):
        raise ValueError(f"lower and upper must be (d,) or (B, d); got {lo.shape}, {hi.shape}")
    try:
        shape = np.broadcast_shapes(np.atleast_2d(lo).shape, np.atleast_2d(hi).shape)
    except ValueError:
        raise ValueError(f"lower {lo.shape} and upper {hi.shape} do not broadcast") from None
    lo2 = np.array(np.broadcast_to(np.atleast_2d(lo), shape))
    hi2 = np.array(np.broadcast_to(np.atleast_2d(hi), shape))
    if shape[-1] < 1:
        raise ValueError("the search space needs at least one dimension")
    if not (np.all(np.isfinite(lo2)) and np.all(np.isfinite(hi2))):
        raise ConfigurationError("lower and upper bounds must be finite")
    bad = np.argwhere(lo2 > hi2)
    if bad.size:
        b, j = bad[0]
        raise ConfigurationError(
            f"lower > upper for problem {b}, dimension {j}: {lo2[b, j]!r} > {hi2[b, j]!r}"
        )
    return lo2, hi2


def pso_minimize(
    evaluate: BatchEvaluate,
    lower: ArrayLike,
    upper: ArrayLike,
    *,
    n_particles: int = 40,
    n_iterations: int = 100,
    seed: int | np.random.Generator = 0,
    inertia_start: float = 0.9,
    inertia_end: float = 0.4,
    cognitive: float = 2.0,
    social: float = 2.0,
    velocity_max_fraction: float = 0.2,
    violation_tol: float = 0.0,
    tol: float = 0.0,
    patience: int | None = None,
    x0: ArrayLike | None = None,
    n_problems: int | None = None,
) -> OptimResult:
    """Minimise B box-bounded constrained problems at once with a particle swarm.

    Args:
        evaluate: ``evaluate(X) -> (objective, violation)``, ``X (B, P, d)``, outputs
            ``(B, P)``; the violation is a total (e.g. a sum of positive parts), 0 when feasible.
            Called once with the initial swarm and once per iteration.
        lower: ``(d,)`` or ``(B, d)`` lower bounds; B comes from the bounds, ``x0`` or
            ``n_problems``.
        upper: ``(d,)`` or ``(B, d)`` upper bounds.
        n_particles: Particles P per problem, >= 2.
        n_iterations: Largest number of swarm updates, >= 1.
        seed: Seed or Generator for reproducibility.
        inertia_start: Inertia weight w at the first update.
        inertia_end: Inertia weight at the last update (linear in between).
        cognitive: c1, pull towards the particle's own best.
        social: c2, pull towards the problem's global best.
        velocity_max_fraction: Velocity clamp per dimension as a fraction of ``upper - lower``.
        violation_tol: Largest total violation counted as feasible.
        tol: Smallest change of a problem's best (objective while feasible, violation while
            not; becoming feasible always counts) that resets its patience counter.
        patience: Stop once every problem went this many iterations without such a change;
            None runs all ``n_iterations``. The inertia schedule spans ``n_iterations``, so a
            stop while w is still large returns an unrefined best: size ``patience`` (and
            ``n_iterations``) for the refinement phase, not only for plateaus.
        x0: Initial guesses placed in the first k particles, ``(B, k, d)`` or ``(k, d)`` for all
            problems, ``k <= n_particles``, inside the bounds.
        n_problems: B, for problems that share ``(d,)`` bounds; None takes B from the
            bounds or ``x0``.

    Returns:
        :class:`OptimResult`; check ``feasible`` or call ``require_feasible()``.

    Raises:
        ValueError: Wrong shapes of bounds, ``x0`` or ``evaluate``'s outputs; a negative
            violation.
        ConfigurationError: Invalid bounds or settings, or ``x0`` outside the bounds.
    """
    lo, hi = bounds_array(lower, upper)
    _check_settings(
        n_particles=n_particles,
        n_iterations=n_iterations,
        inertia_start=inertia_start,
        inertia_end=inertia_end,
        cognitive=cognitive,
        social=social,
        velocity_max_fraction=velocity_max_fraction,
        violation_tol=violation_tol,
        tol=tol,
        patience=patience,
    )
    guesses = None if x0 is None else np.asarray(x0, dtype=np.float64)
    if n_problems is None and guesses is not None and guesses.ndim == 3:
        n_problems = guesses.shape[0]
    if n_problems is not None:
        if n_problems < 1:
            raise ConfigurationError(f"n_problems must be >= 1; got {n_problems}")
        if lo.shape[0] not in (1, n_problems):
            raise ValueError(f"bounds for {lo.shape[0]} problems but n_problems={n_problems}")
        lo = np.repeat(lo, n_problems // lo.shape[0], axis=0)
        hi = np.repeat(hi, n_problems // hi.shape[0], axis=0)
    B, d = lo.shape
    P = n_particles
    rng = np.random.default_rng(seed)

    lo3 = lo[:, np.newaxis, :]
    hi3 = hi[:, np.newaxis, :]
    span = hi3 - lo3
    v_max = velocity_max_fraction * span
    X = lo3 + rng.random((B, P, d)) * span
    if guesses is not None:
        _place_guesses(X, guesses, lo, hi)
    V = v_max * (2.0 * rng.random((B, P, d)) - 1.0)

    f, v = checked_evaluation(evaluate(X.copy()), (B, P))
    p_x, p_f, p_v = X.copy(), f, v
    rows = np.arange(B)
    g = deb_argbest(p_f, p_v, violation_tol)
    g_x, g_f, g_v = p_x[rows, g], p_f[rows, g], p_v[rows, g]

    stall = np.zeros(B, dtype=np.int64)
    hist_f: list[FloatArray] = []
    hist_v: list[FloatArray] = []
    last = max(n_iterations - 1, 1)
    iterations = 0
    for it in range(n_iterations):
        w = inertia_start + (inertia_end - inertia_start) * (it / last)
        r1 = rng.random((B, P, d))
        r2 = rng.random((B, P, d))
        V = w * V + cognitive * r1 * (p_x - X) + social * r2 * (g_x[:, np.newaxis, :] - X)
        np.clip(V, -v_max, v_max, out=V)
        X = X + V
        outside = (X < lo3) | (X > hi3)
        np.clip(X, lo3, hi3, out=X)
        V[outside] = 0.0

        f, v = checked_evaluation(evaluate(X.copy()), (B, P))
        improved = deb_better(f, v, p_f, p_v, violation_tol)
        p_x = np.where(improved[..., np.newaxis], X, p_x)
        p_f = np.where(improved, f, p_f)
        p_v = np.where(improved, v, p_v)

        g = deb_argbest(p_f, p_v, violation_tol)
        new_x, new_f, new_v = p_x[rows, g], p_f[rows, g], p_v[rows, g]
        significant = _significant_change(g_f, g_v, new_f, new_v, violation_tol, tol)
        stall = np.where(significant, 0, stall + 1)
        g_x, g_f, g_v = new_x, new_f, new_v
        hist_f.append(g_f)
        hist_v.append(g_v)
        iterations = it + 1
        if patience is not None and np.all(stall >= patience):
            break

    return OptimResult(
        x_best=g_x,
        f_best=g_f,
        violation_best=g_v,
        feasible=g_v <= violation_tol,
        iterations=iterations,
        evaluations=P * (iterations + 1),
        history_f_best=np.array(hist_f),
        history_violation_best=np.array(hist_v),
    )


def _significant_change(
    f_old: FloatArray,
    v_old: FloatArray,
    f_new: FloatArray,
    v_new: FloatArray,
    violation_tol: float,
    tol: float,
) -> BoolArray:
    feas_old = v_old <= violation_tol
    feas_new = v_new <= violation_tol
    became_feasible = feas_new & ~feas_old
    better_f = feas_old & feas_new & (f_old - f_new > tol)
    better_v = ~feas_old & ~feas_new & (v_old - v_new > tol)
    return np.asarray(became_feasible | better_f | better_v)


def _place_guesses(X: FloatArray, guesses: FloatArray, lo: FloatArray, hi: FloatArray) -> None:
    B, P, d = X.shape
    if guesses.ndim == 2:
        guesses = np.broadcast_to(guesses, (B, *guesses.shape))
    if guesses.ndim != 3 or guesses.shape[0] != B or guesses.shape[2] != d:
        raise ValueError(f"x0 must be (B, k, d) = ({B}, k, {d}) or (k, {d}); got {guesses.shape}")
    k = guesses.shape[1]
    if k > P:
        raise ValueError(f"x0 holds {k} guesses per problem but there are only {P} particles")
    if not np.all(np.isfinite(guesses)):
        raise ConfigurationError("x0 must be finite")
    outside = (guesses < lo[:, np.newaxis, :]) | (guesses > hi[:, np.newaxis, :])
    if np.any(outside):
        b, i, j = np.argwhere(outside)[0]
        raise ConfigurationError(
            f"x0[{b}, {i}] lies outside the bounds in dimension {j}: {guesses[b, i, j]!r} "
            f"not in [{lo[b, j]!r}, {hi[b, j]!r}]"
        )
    X[:, :k, :] = guesses


def _check_settings(
    *,
    n_particles: int,
    n_iterations: int,
    inertia_start: float,
    inertia_end: float,
    cognitive: float,
    social: float,
    velocity_max_fraction: float,
    violation_tol: float,
    tol: float,
    patience: int | None,
) -> None:
    if n_particles < 2:
        raise ConfigurationError(f"n_particles must be >= 2; got {n_particles}")
    if n_iterations < 1:
        raise ConfigurationError(f"n_iterations must be >= 1; got {n_iterations}")
    for name, value in (
        ("inertia_start", inertia_start),
        ("inertia_end", inertia_end),
        ("cognitive", cognitive),
        ("social", social),
        ("violation_tol", violation_tol),
        ("tol", tol),
    ):
        if not (np.isfinite(value) and value >= 0.0):
            raise ConfigurationError(f"{name} must be finite and >= 0; got {value!r}")
    if not (0.0 < velocity_max_fraction <= 1.0):
        raise ConfigurationError(
            f"velocity_max_fraction must be in (0, 1]; got {velocity_max_fraction!r}"
        )
    if patience is not None and patience < 1:
        raise ConfigurationError(f"patience must be >= 1 or None; got {patience}")
