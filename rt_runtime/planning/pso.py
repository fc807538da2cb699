"""Constrained particle swarm optimisation, vectorised over the swarm and over many problems.

This is the offline teacher of Yao section 4.2: it minimises eq 12 over the 4-dim particle
``(a16, a26, a36, T)``, but it is written for any dimension d and any number B of independent
problems (e.g. many dig entry/exit pose pairs), solved in lockstep. The caller supplies one
batched function ``evaluate(X) -> (objective, violation)`` with ``X`` shaped ``(B, P, d)`` and
both outputs ``(B, P)``; each iteration calls it once for every particle of every problem.

The method (Yao gives no PSO settings, so these are the standard PSO with the Shi-Eberhart
linearly decreasing inertia weight):

* 40 particles and 100 iterations by default (Yao's Fig. 7 converges by iteration 38 of 50);
* velocity ``v <- w v + c1 r1 (pbest - x) + c2 r2 (guide - x)`` with ``r1, r2 ~ U(0, 1)`` drawn
  per particle and dimension; ``w`` falls linearly from 0.9 to 0.4 over the run (broad search
  first, then refinement); ``c1 = c2 = 2.0``;
* the guide is the best personal best of the whole swarm (:attr:`Topology.GLOBAL`, the default)
  or of the particle and its two ring neighbours (:attr:`Topology.RING`, Kennedy and Mendes'
  local best). Information spreads around the ring one neighbour per iteration, so the swarm
  keeps several candidate regions alive for longer instead of collapsing on the first good one:
  slower on a single basin, much less prone to premature convergence on multimodal landscapes
  such as the dig problem, where different shape regions give different local optima;
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

Each problem draws its random numbers from its own stream (children spawned from the seed, one
per problem in batch order, or given explicitly), so a problem's result does not depend on the
other problems of its batch as far as ``evaluate`` computes each problem's row bitwise
independently of the others: a batch can then be split over processes, each given its
problems' streams, with the same answers. (Matrix products may round differently for other
batch shapes; the answers then differ by rounding, or rarely by a solve steered elsewhere.)

:func:`slsqp_polish` is an engineering addition beyond Yao's method, run after the swarm: the
constrained optima of the dig problem sit on several constraint boundaries at once, where a
swarm (which only sees the total violation) converges slowly and then creeps along the
boundary; a few SQP steps on the individual constraints land on the vertex. Everything here
runs outside the loop.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from rt_runtime.errors import ConfigurationError, PlanningError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

BatchEvaluate = Callable[[FloatArray], tuple[ArrayLike, ArrayLike]]
"""``evaluate(X (B, P, d)) -> (objective (B, P), total violation (B, P) >= 0)``."""

ConstraintEvaluate = Callable[[NDArray[np.intp], FloatArray], tuple[ArrayLike, ArrayLike]]
"""``evaluate(rows (n,), X (n, S, d)) -> (objective (n, S), constraints (n, S, m))`` of the
problems ``rows`` (indices into the batch), each constraint ``<= 0`` where it holds."""

Seed = int | np.random.Generator | Sequence[np.random.Generator]
"""A seed, a Generator to spawn per-problem streams from, or one Generator per problem."""


class Topology(IntEnum):
    """Whose personal best guides a particle (the social term)."""

    GLOBAL = 0
    """The best of the whole swarm (gbest)."""
    RING = 1
    """The best of the particle and its two neighbours on a ring of particle indices (lbest)."""


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
        swarm_x: ``(B, P, d)`` every particle's personal best at the end (PSO only, else None):
            candidates for a refinement, e.g. re-ranked on a finer model.
        swarm_f: ``(B, P)`` their objectives (PSO only).
        swarm_violation: ``(B, P)`` their total violations (PSO only).
    """

    x_best: FloatArray
    f_best: FloatArray
    violation_best: FloatArray
    feasible: BoolArray
    iterations: int
    evaluations: int
    history_f_best: FloatArray
    history_violation_best: FloatArray
    swarm_x: FloatArray | None = None
    swarm_f: FloatArray | None = None
    swarm_violation: FloatArray | None = None

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
    return np.asarray(np.where(np.any(feas, axis=-1), best_feasible, least_violating))


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
    seed: Seed = 0,
    topology: Topology = Topology.GLOBAL,
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
        seed: An int or Generator, from which one child stream per problem is spawned (in batch
            order), or a sequence of B Generators, one per problem, used as they are.
        topology: Whose personal best guides each particle, see :class:`Topology`.
        inertia_start: Inertia weight w at the first update.
        inertia_end: Inertia weight at the last update (linear in between).
        cognitive: c1, pull towards the particle's own best.
        social: c2, pull towards the best personal best of the particle's neighbourhood (the
            whole swarm for :attr:`Topology.GLOBAL`).
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
        :class:`OptimResult` with the final personal bests in ``swarm_*``; check ``feasible``
        or call ``require_feasible()``.

    Raises:
        ValueError: Wrong shapes of bounds, ``x0`` or ``evaluate``'s outputs; a negative
            violation; a sequence of streams whose length is not B.
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
    streams = _problem_streams(seed, B)

    lo3 = lo[:, np.newaxis, :]
    hi3 = hi[:, np.newaxis, :]
    span = hi3 - lo3
    v_max = velocity_max_fraction * span
    start = _draw(streams, (2, P, d))
    X = lo3 + start[:, 0] * span
    if guesses is not None:
        _place_guesses(X, guesses, lo, hi)
    V = v_max * (2.0 * start[:, 1] - 1.0)

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
        r = _draw(streams, (2, P, d))
        if topology == Topology.RING:
            guide = _ring_best(p_x, p_f, p_v, violation_tol)
        else:
            guide = g_x[:, np.newaxis, :]
        V = w * V + cognitive * r[:, 0] * (p_x - X) + social * r[:, 1] * (guide - X)
        np.clip(V, -v_max, v_max, out=V)
        X = X + V
        outside = (lo3 > X) | (hi3 < X)
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
        swarm_x=p_x,
        swarm_f=p_f,
        swarm_violation=p_v,
    )


@dataclass(frozen=True, slots=True, eq=False)
class PolishResult:
    """Outcome of :func:`slsqp_polish` for k starts of each of B problems.

    Attributes:
        x_best: ``(B, k, d)`` per start, the Deb-best point its solve evaluated, the start
            included, so it is never worse than the start.
        f_best: ``(B, k)`` its objective.
        violation_best: ``(B, k)`` its total violation (sum of the constraints' positive parts).
        feasible: ``(B, k)`` whether ``violation_best <= violation_tol``.
        improved: ``(B, k)`` whether ``x_best`` strictly beats the start under Deb's rules.
        evaluations: ``(B, k)`` points evaluated per start (finite-difference probes included).
    """

    x_best: FloatArray
    f_best: FloatArray
    violation_best: FloatArray
    feasible: BoolArray
    improved: BoolArray
    evaluations: NDArray[np.int64]


def slsqp_polish(
    evaluate: ConstraintEvaluate,
    lower: ArrayLike,
    upper: ArrayLike,
    x0: ArrayLike,
    *,
    max_iterations: int = 30,
    step: float = 1e-6,
    margin: float = 1e-7,
    violation_tol: float = 0.0,
    max_concurrent: int = 256,
) -> PolishResult:
    """Refine k starting points of each of B problems with scipy's SLSQP, batched in lockstep.

    An engineering addition beyond Yao's PSO (see the module docstring): where the swarm ends
    near an optimum on several constraint boundaries, SQP steps on the linearised individual
    constraints reach the vertex that the swarm only creeps towards. It is local: each start
    keeps its basin, so polishing several distinct swarm members is a cheap multi-start.

    Each start is an independent SLSQP solve in the unit cube of its box. Gradients are forward
    differences of ``step`` (backward at the upper bound); the point and its d probes are
    evaluated together. SLSQP is sequential, so the solves run in threads that only wait for
    points: every round, the pending points of all waiting solves go to ``evaluate`` in one
    batched call (no numerical work is done in parallel; the batching amortises the per-call
    cost of ``evaluate``, which dominates for a handful of points). The rounds are formed the
    same way on every run, so the result is reproducible; a solve's path depends on the other
    solves only as far as ``evaluate`` rounds a row differently in another batch. Every
    constraint is tightened by ``margin`` for SLSQP, so that its tolerance cannot leave the
    result a hair infeasible; the answer is the Deb-best of every point the solve evaluated,
    under the untightened constraints. SLSQP's failures (iteration limit, an incompatible
    linearisation from an infeasible start) therefore cost time, never quality.

    Constraints must be smooth for the gradients to mean something: a constraint that is the
    maximum of smooth pieces (e.g. a peak ``|q''|`` reached with either sign) has a kink where
    they cross, where SLSQP stalls; pass the pieces as separate constraints.

    Args:
        evaluate: ``evaluate(rows (n,), X (n, S, d)) -> (objective (n, S), constraints (n, S,
            m))``: problem ``rows[i]`` (an index into the B problems, repeated for several
            starts of one problem) at the S points ``X[i]``; a constraint holds where ``<= 0``.
            Non-finite objectives and NaN constraints count as infinitely violating.
        lower: ``(d,)`` or ``(B, d)`` lower bounds.
        upper: ``(d,)`` or ``(B, d)`` upper bounds.
        x0: ``(B, k, d)`` starting points inside the bounds.
        max_iterations: SLSQP iterations per start, >= 1.
        step: Finite-difference step as a fraction of each bound's span, in (0, 0.1].
        margin: Tightening of every constraint seen by SLSQP, >= 0, in the constraints' units.
        violation_tol: Largest total violation counted as feasible.
        max_concurrent: Largest number of solves (threads) in flight, >= 1; more starts are
            polished in successive groups.

    Returns:
        :class:`PolishResult`.

    Raises:
        ValueError: Wrong shapes of bounds, ``x0`` or ``evaluate``'s outputs.
        ConfigurationError: Invalid bounds or settings, or ``x0`` outside the bounds.
        Any exception ``evaluate`` raises, after every solve has stopped.
    """
    start = np.asarray(x0, dtype=np.float64)
    lo2, hi2 = bounds_array(lower, upper)
    if start.ndim != 3 or start.shape[2] != lo2.shape[1] or lo2.shape[0] not in (1, start.shape[0]):
        raise ValueError(f"x0 must be (B, k, d) matching bounds {lo2.shape}; got {start.shape}")
    if max_iterations < 1:
        raise ConfigurationError(f"max_iterations must be >= 1; got {max_iterations}")
    if not (0.0 < step <= 0.1):
        raise ConfigurationError(f"step must be in (0, 0.1]; got {step!r}")
    for name, value in (("margin", margin), ("violation_tol", violation_tol)):
        if not (np.isfinite(value) and value >= 0.0):
            raise ConfigurationError(f"{name} must be finite and >= 0; got {value!r}")
    if max_concurrent < 1:
        raise ConfigurationError(f"max_concurrent must be >= 1; got {max_concurrent}")
    B, k, d = start.shape
    lo = np.broadcast_to(lo2[:, np.newaxis, :], (B, k, d)).reshape(B * k, d)
    hi = np.broadcast_to(hi2[:, np.newaxis, :], (B, k, d)).reshape(B * k, d)
    flat = start.reshape(B * k, d)
    if not np.all(np.isfinite(flat)):
        raise ConfigurationError("x0 must be finite")
    outside = np.argwhere((flat < lo) | (flat > hi))
    if outside.size:
        s, j = outside[0]
        raise ConfigurationError(
            f"x0[{s // k}, {s % k}] lies outside the bounds in dimension {j}: {flat[s, j]!r} "
            f"not in [{lo[s, j]!r}, {hi[s, j]!r}]"
        )

    settings = _SolveSettings(max_iterations, step, margin, violation_tol)
    rows = np.repeat(np.arange(B), k)
    solved: list[tuple[FloatArray, float, float, bool, int]] = []
    for first in range(0, B * k, max_concurrent):
        group = np.arange(first, min(first + max_concurrent, B * k))
        solved.extend(
            _Lockstep(evaluate, rows[group], lo[group], hi[group], flat[group], settings).run()
        )
    x_best = np.array([s[0] for s in solved]).reshape(B, k, d)
    v_best = np.array([s[2] for s in solved]).reshape(B, k)
    return PolishResult(
        x_best=x_best,
        f_best=np.array([s[1] for s in solved]).reshape(B, k),
        violation_best=v_best,
        feasible=v_best <= violation_tol,
        improved=np.array([s[3] for s in solved]).reshape(B, k),
        evaluations=np.array([s[4] for s in solved], dtype=np.int64).reshape(B, k),
    )


@dataclass(frozen=True, slots=True)
class _SolveSettings:
    max_iterations: int
    step: float
    margin: float
    violation_tol: float


class _Lockstep:
    """SLSQP solves in threads whose point requests are batched into one call per round.

    The main thread evaluates; a solve thread only runs SLSQP's bookkeeping between requests.
    A round starts once every unfinished solve waits for its points; each solve waits on its
    own event, so a round wakes each thread once. If ``evaluate`` raises, the waiting solves
    are released with the exception and stop; ``run`` then re-raises it.
    """

    def __init__(
        self,
        evaluate: ConstraintEvaluate,
        rows: NDArray[np.intp],
        lo: FloatArray,
        hi: FloatArray,
        x0: FloatArray,
        settings: _SolveSettings,
    ) -> None:
        self._evaluate = evaluate
        self._rows = rows
        self._lo, self._hi, self._x0 = lo, hi, x0
        self._settings = settings
        n = rows.size
        self._ready = threading.Condition()  # guards the fields below; only run() waits on it
        self._pending: dict[int, FloatArray] = {}
        self._finished = 0
        self._answered = [threading.Event() for _ in range(n)]
        self._answers: list[tuple[FloatArray, FloatArray] | BaseException | None] = [None] * n
        self._results: list[tuple[FloatArray, float, float, bool, int] | None] = [None] * n
        self._errors: list[BaseException] = []

    def run(self) -> list[tuple[FloatArray, float, float, bool, int]]:
        n = self._rows.size
        threads = [threading.Thread(target=self._solve, args=(i,), daemon=True) for i in range(n)]
        for t in threads:
            t.start()
        failure: BaseException | None = None
        while True:
            with self._ready:
                self._ready.wait_for(lambda: len(self._pending) + self._finished == n)
                if self._finished == n:
                    break
                batch = sorted(self._pending)
                points = np.stack([self._pending.pop(i) for i in batch])
            try:
                f, c = _checked_constraints(
                    self._evaluate(self._rows[batch], points.copy()), points.shape[:2]
                )
                answers: list[tuple[FloatArray, FloatArray] | BaseException] = [
                    (f[j], c[j]) for j in range(len(batch))
                ]
            except Exception as exc:  # released to the solves, re-raised below
                failure = exc
                answers = [exc] * len(batch)
            for i, answer in zip(batch, answers, strict=True):
                self._answers[i] = answer
                self._answered[i].set()
        for t in threads:
            t.join()
        if failure is not None:
            raise failure
        if self._errors:
            raise self._errors[0]
        return [r for r in self._results if r is not None]

    def _points(self, i: int, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        with self._ready:
            self._pending[i] = X
            self._ready.notify()
        self._answered[i].wait()
        self._answered[i].clear()
        answer = self._answers[i]
        self._answers[i] = None
        if answer is None or isinstance(answer, BaseException):
            raise _Stop from answer
        return answer

    def _solve(self, i: int) -> None:
        try:
            self._results[i] = _polish_one(
                lambda X: self._points(i, X),
                self._lo[i],
                self._hi[i],
                self._x0[i],
                self._settings,
            )
        except _Stop:
            pass
        except Exception as exc:  # a failure inside SLSQP's bookkeeping; raised by run()
            self._errors.append(exc)
        finally:
            with self._ready:
                self._finished += 1
                self._ready.notify()


class _Stop(Exception):
    """Ends a solve whose evaluation failed (the failure itself is raised by ``run``)."""


def _polish_one(
    points: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
    lo: FloatArray,
    hi: FloatArray,
    x0: FloatArray,
    settings: _SolveSettings,
) -> tuple[FloatArray, float, float, bool, int]:
    """SLSQP from ``x0``: ``(x, f, violation, improved, evaluations)``."""
    d = lo.size
    step, margin, tol = settings.step, settings.margin, settings.violation_tol
    fixed = hi <= lo  # a degenerate dimension keeps its value: SLSQP bounds (0, 0)
    span = np.where(fixed, 1.0, hi - lo)
    upper_z = np.where(fixed, 0.0, 1.0)
    cache: dict[bytes, tuple[float, FloatArray, FloatArray, FloatArray]] = {}
    seen: list[tuple[FloatArray, FloatArray, FloatArray]] = []
    z0 = np.clip((x0 - lo) / span, 0.0, upper_z)

    def model(z: FloatArray) -> tuple[float, FloatArray, FloatArray, FloatArray]:
        z = np.clip(z, 0.0, upper_z)
        key = z.tobytes()
        if key not in cache:
            h = np.where(z + step > upper_z, -step, step)
            # The start is evaluated exactly as given (the unit-cube round trip may move it by
            # an ulp), so that "never worse than the start" holds for x0 itself.
            base = x0 if np.array_equal(z, z0) else lo + z * span
            X = base + np.vstack([np.zeros(d), np.diag(np.where(fixed, 0.0, h * span))])
            f, c = points(X)
            seen.append((X, f, c))
            # SLSQP cannot use infinities; a huge finite value keeps it away from such points.
            f_s = np.where(np.isfinite(f), f, 1e300)
            c_s = np.where(np.isnan(c), 1e300, np.clip(c, -1e300, 1e300)) + margin
            cache[key] = (
                float(f_s[0]),
                (f_s[1:] - f_s[0]) / h,
                -c_s[0],
                -((c_s[1:] - c_s[0]) / h[:, np.newaxis]).T,
            )
        return cache[key]

    minimize(
        lambda z: model(z)[0],
        z0,
        jac=lambda z: model(z)[1],
        method="SLSQP",
        bounds=list(zip(np.zeros(d), upper_z, strict=True)),
        constraints=[{"type": "ineq", "fun": lambda z: model(z)[2], "jac": lambda z: model(z)[3]}],
        options={"maxiter": settings.max_iterations, "ftol": 1e-12},
    )
    X = np.concatenate([s[0] for s in seen])
    f = np.concatenate([s[1] for s in seen])
    c = np.concatenate([s[2] for s in seen])
    total = np.sum(np.maximum(c, 0.0), axis=-1)
    total = np.where(~np.isfinite(f) | np.isnan(total), np.inf, total)
    i = int(deb_argbest(f, total, tol))
    # Row 0 is the start: SLSQP evaluates its initial point first.
    better = bool(deb_better(f[i : i + 1], total[i : i + 1], f[:1], total[:1], tol)[0])
    if not better:
        i = 0
    return X[i], float(f[i]), float(total[i]), better, int(f.size)


def _checked_constraints(
    result: tuple[ArrayLike, ArrayLike], shape: tuple[int, ...]
) -> tuple[FloatArray, FloatArray]:
    try:
        f_raw, c_raw = result
    except (TypeError, ValueError):
        raise ValueError("evaluate must return a pair (objective, constraints)") from None
    f = np.asarray(f_raw, dtype=np.float64)
    c = np.asarray(c_raw, dtype=np.float64)
    if f.shape != shape or c.shape[:-1] != shape or c.ndim != len(shape) + 1:
        raise ValueError(
            f"evaluate must return objective {shape} and constraints (*{shape}, m); "
            f"got {f.shape} and {c.shape}"
        )
    return f, c


def _problem_streams(seed: Seed, n_problems: int) -> list[np.random.Generator]:
    """One random stream per problem, see the ``seed`` argument of :func:`pso_minimize`.

    Raises:
        ValueError: A sequence of streams whose length is not ``n_problems``.
    """
    if isinstance(seed, (int, np.integer)):
        return np.random.default_rng(int(seed)).spawn(n_problems)
    if isinstance(seed, np.random.Generator):
        return seed.spawn(n_problems)
    streams = list(seed)
    if len(streams) != n_problems:
        raise ValueError(f"got {len(streams)} random streams for {n_problems} problems")
    return streams


def _draw(streams: list[np.random.Generator], shape: tuple[int, ...]) -> FloatArray:
    # One call per problem and iteration (not per sample): per-problem streams make a problem's
    # result independent of its batch, and cost microseconds against an evaluation of the swarm.
    return np.stack([g.random(shape) for g in streams])


def _ring_best(
    p_x: FloatArray, p_f: FloatArray, p_v: FloatArray, violation_tol: float
) -> FloatArray:
    """Deb-best personal best among each particle and its ring neighbours, ``(B, P, d)``."""
    P = p_f.shape[1]
    shifts = np.array([0, 1, -1])  # self first: ties keep a particle on its own best
    f = np.stack([np.roll(p_f, k, axis=1) for k in shifts], axis=-1)
    v = np.stack([np.roll(p_v, k, axis=1) for k in shifts], axis=-1)
    source = (np.arange(P) - shifts[deb_argbest(f, v, violation_tol)]) % P
    return np.take_along_axis(p_x, source[..., np.newaxis], axis=1)


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
