"""Reference optimiser for the PSO teacher: scipy's differential evolution on one problem.

An independent method behind the same ``evaluate(X (B, P, d)) -> (objective, violation)``
interface as :func:`rt_runtime.planning.pso.pso_minimize`, used to check the teacher's optima
(tests, benchmarks), not to plan digs.

Constraint handling matches the PSO's Deb rules exactly: the total violation is handed to
scipy as one ``NonlinearConstraint(violation <= violation_tol)``. scipy's DE then ranks by
Lampinen's rules, which with a single constraint component are Deb's: feasible beats
infeasible, feasible points compare by objective, infeasible ones by violation; and it only asks
for the objective of feasible points. A penalty would need a bound on the objective to be exact
for ranking, which the caller does not have.

scipy evaluates the constraint and the objective in separate calls (and re-probes the best
point's constraint after each generation), while ``evaluate`` returns both at once; each
population is therefore evaluated once, in the first call that meets it, and later calls look
their points up in that batch or in the best point. Polishing is off (``polish=False``): scipy's
constrained polish (trust-constr) ranks differently and may return a point the ranking would
not, so the result stays the DE population's Deb-best. Outside the loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import NonlinearConstraint, OptimizeResult, differential_evolution

from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.pso import (
    BatchEvaluate,
    FloatArray,
    OptimResult,
    bounds_array,
    checked_evaluation,
    deb_argbest,
    deb_better,
)


@dataclass(slots=True)
class _Evaluations:
    """Bridge from scipy's two calls per population to one ``evaluate`` call."""

    evaluate: BatchEvaluate
    violation_tol: float
    d: int
    count: int = 0
    batch: dict[bytes, tuple[float, float]] = field(default_factory=dict)
    best_x: FloatArray = field(init=False)
    best_f: FloatArray = field(default_factory=lambda: np.array([np.inf]))
    best_v: FloatArray = field(default_factory=lambda: np.array([np.inf]))

    def __post_init__(self) -> None:
        # NaN until a point with a finite violation turns up (Deb-better than "nothing").
        self.best_x = np.full(self.d, np.nan)

    def _points(self, x: FloatArray) -> FloatArray:
        # scipy passes (d, S) when vectorized, (d,) when probing one point.
        return np.ascontiguousarray(np.reshape(x, (self.d, -1)).T)

    def _run(self, pts: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Evaluate points ``(S, d)`` in one call and keep the Deb-best ever seen."""
        S = pts.shape[0]
        f, v = checked_evaluation(self.evaluate(pts[np.newaxis].copy()), (1, S))
        self.count += S
        i = int(deb_argbest(f, v, self.violation_tol)[0])
        f_i, v_i = f[0, i : i + 1], v[0, i : i + 1]
        if deb_better(f_i, v_i, self.best_f, self.best_v, self.violation_tol)[0]:
            self.best_x, self.best_f, self.best_v = pts[i].copy(), f_i.copy(), v_i.copy()
        return f[0], v[0]

    def _lookup(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        pts = self._points(x)
        known = dict(self.batch)
        known[self.best_x.tobytes()] = (float(self.best_f[0]), float(self.best_v[0]))
        found = [known.get(p.tobytes()) for p in pts]
        missing = [i for i, hit in enumerate(found) if hit is None]
        f = np.array([np.nan if hit is None else hit[0] for hit in found])
        v = np.array([np.nan if hit is None else hit[1] for hit in found])
        if missing:
            f[missing], v[missing] = self._run(pts[missing])
            self.batch = {
                p.tobytes(): (float(fi), float(vi)) for p, fi, vi in zip(pts, f, v, strict=True)
            }
        return f, v

    def violation(self, x: FloatArray) -> FloatArray:
        v = self._lookup(x)[1]
        return v[np.newaxis, :] if np.ndim(x) == 2 else v

    def objective(self, x: FloatArray) -> FloatArray:
        return self._lookup(x)[0]


def de_minimize(
    evaluate: BatchEvaluate,
    lower: ArrayLike,
    upper: ArrayLike,
    *,
    seed: int | np.random.Generator = 0,
    popsize: int = 15,
    maxiter: int = 1000,
    tol: float = 1e-8,
    atol: float = 0.0,
    mutation: float | tuple[float, float] = (0.5, 1.0),
    recombination: float = 0.7,
    strategy: str = "best1bin",
    violation_tol: float = 0.0,
) -> OptimResult:
    """Minimise one constrained problem with scipy's differential evolution (vectorised).

    Args:
        evaluate: The PSO interface, ``evaluate(X (1, S, d)) -> (objective (1, S),
            violation (1, S))``, S the points scipy asks for at once.
        lower: ``(d,)`` or ``(1, d)`` lower bounds.
        upper: ``(d,)`` or ``(1, d)`` upper bounds.
        seed: Seed or Generator (scipy's ``rng``).
        popsize: Population size multiplier (population ``popsize * d``).
        maxiter: Largest number of generations.
        tol: Relative convergence tolerance on the population's objective spread (scipy's
            ``tol``; the default is tighter than scipy's 0.01 for a reference).
        atol: Absolute convergence tolerance.
        mutation: Differential weight or dithering range.
        recombination: Crossover probability.
        strategy: scipy's strategy name.
        violation_tol: Largest total violation counted as feasible (as in the PSO).

    Returns:
        :class:`OptimResult` with B = 1; ``evaluations`` counts points, not calls.

    Raises:
        ValueError: Bounds for more than one problem, or wrong ``evaluate`` output shapes.
        ConfigurationError: Invalid bounds or ``violation_tol``.
    """
    lo, hi = bounds_array(lower, upper)
    if lo.shape[0] != 1:
        raise ValueError(f"de_minimize solves one problem; got bounds for {lo.shape[0]}")
    if not (np.isfinite(violation_tol) and violation_tol >= 0.0):
        raise ConfigurationError(f"violation_tol must be finite and >= 0; got {violation_tol!r}")
    d = lo.shape[1]
    ev = _Evaluations(evaluate, violation_tol, d)
    hist_f: list[float] = []
    hist_v: list[float] = []

    def record(intermediate_result: OptimizeResult) -> None:
        hist_f.append(float(ev.best_f[0]))
        hist_v.append(float(ev.best_v[0]))

    kwargs: dict[str, Any] = {
        "strategy": strategy,
        "maxiter": maxiter,
        "popsize": popsize,
        "tol": tol,
        "atol": atol,
        "mutation": mutation,
        "recombination": recombination,
        "rng": np.random.default_rng(seed),
        "callback": record,
        "polish": False,
        "init": "latinhypercube",
        "updating": "deferred",
        "vectorized": True,
        "constraints": NonlinearConstraint(ev.violation, -np.inf, violation_tol),
    }
    res = differential_evolution(ev.objective, list(zip(lo[0], hi[0], strict=True)), **kwargs)
    return OptimResult(
        x_best=ev.best_x[np.newaxis, :],
        f_best=ev.best_f,
        violation_best=ev.best_v,
        feasible=ev.best_v <= violation_tol,
        iterations=int(res.nit),
        evaluations=ev.count,
        history_f_best=np.array(hist_f).reshape(-1, 1),
        history_violation_best=np.array(hist_v).reshape(-1, 1),
    )
