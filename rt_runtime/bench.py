"""Benchmarks behind ``excavator-rt bench ...``: distributions, not single numbers.

Each benchmark returns one JSON-ready dict with stable keys (documented in the README). Timing
goals are checked here and reported, never asserted in tests: the machines are shared and noisy.
Percentile groups carry ``p50`` and ``p99``. The papers' figures are given under ``paper``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from rt_runtime.rig import Rig

YAO_PSO_SOLVE_S = (69.0, 71.0)  # Yao Table 4: PSO planning time per dig
YAO_RANGES = {"T_s": (5.0, 10.0), "volume_L": (3.74, 5.72), "energy_Wh": (0.025, 0.110)}
YAO_MEAN_OBJECTIVE = {"downward": 0.403, "backward": 0.303}  # Yao 5.2, PSO sample averages


def percentiles(values: list[float] | np.ndarray, *, tails: bool = False) -> dict[str, float]:
    """``{"p50", "p99"}`` (and ``"p999"``, ``"max"`` with ``tails``) of ``values``."""
    a = np.asarray(values, dtype=np.float64)
    out = {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99))}
    if tails:
        out["p999"] = float(np.percentile(a, 99.9))
        out["max"] = float(np.max(a))
    return out


def bench_oneshot(
    rig: Rig, n_problems: int = 50, seed: int = 0, de: bool = True, workers: int = 2
) -> dict[str, Any]:
    """PSO teacher: solve time single and batched, quality against differential evolution.

    Half the problems are downward digs, half backward, drawn by
    :func:`rt_runtime.planning.oneshot.sample_problems` with ``seed``. Each problem is solved
    alone (timed, one process), then all together in one batch over ``workers`` processes
    (timed), then by the DE reference (timed).

    Returns:
        JSON-ready dict: ``problems``, ``solve_s`` (p50, p99), ``batch_problems_per_s``,
        ``de_solve_s`` (p50), ``within_1pct_of_de``, ``gap_to_de`` (p50, max), ``feasible``
        (fraction), ``results`` (T_s, volume_L, energy_Wh, objective ranges and means per
        type), ``goals``, ``paper``.
    """
    from rt_runtime.planning import oneshot

    n_down = n_problems // 2
    problems = oneshot.sample_problems(rig, n_down, oneshot.DigType.DOWNWARD, seed=seed)
    problems += oneshot.sample_problems(
        rig, n_problems - n_down, oneshot.DigType.BACKWARD, seed=seed + 1
    )

    single_s = []
    singles = []
    for p in problems:
        t0 = time.perf_counter()
        singles.append(oneshot.solve_pso(rig, [p], seed=seed)[0])
        single_s.append(time.perf_counter() - t0)

    t0 = time.perf_counter()
    batch = oneshot.solve_pso(rig, problems, seed=seed, workers=workers)
    batch_s = time.perf_counter() - t0

    out: dict[str, Any] = {
        "rig": rig.name,
        "problems": len(problems),
        "solve_s": percentiles(single_s),
        "batch_problems_per_s": len(problems) / batch_s,
        "batch_workers": workers,
        "feasible": float(np.mean([s.feasible for s in singles])),
        "batch_feasible": float(np.mean([s.feasible for s in batch])),
    }
    by_type: dict[str, Any] = {}
    for kind in oneshot.DigType:
        sols = [s for s in singles if s.problem.dig_type == kind and s.feasible]
        if not sols:
            continue
        by_type[kind.name.lower()] = {
            "n": len(sols),
            "T_s": [min(s.T_s for s in sols), max(s.T_s for s in sols)],
            "volume_L": [
                min(s.volume_m3 for s in sols) * 1e3,
                max(s.volume_m3 for s in sols) * 1e3,
            ],
            "energy_Wh": [
                min(s.energy_j for s in sols) / 3600,
                max(s.energy_j for s in sols) / 3600,
            ],
            "objective_mean": float(np.mean([s.objective for s in sols])),
        }
    out["results"] = by_type

    if de:
        de_s = []
        gaps = []
        rows = []
        for p, s in zip(problems, singles, strict=True):
            t0 = time.perf_counter()
            d = oneshot.solve_de(rig, p, seed=seed)
            de_s.append(time.perf_counter() - t0)
            if s.feasible and d.feasible:
                gap = (s.objective - d.objective) / abs(d.objective)
            elif s.feasible:
                gap = -1.0  # PSO found a feasible dig the reference did not
            else:
                gap = float("inf")
            gaps.append(gap)
            rows.append({"pso": s.objective, "de": d.objective, "gap": gap})
        finite = np.array([g for g in gaps if np.isfinite(g)])
        out["de_solve_s"] = percentiles(de_s)
        out["within_1pct_of_de"] = float(np.mean(np.array(gaps) <= 0.01))
        out["gap_to_de"] = {
            "p50": float(np.percentile(finite, 50)) if finite.size else float("nan"),
            "max": float(np.max(gaps)),
        }
        out["speedup_vs_de"] = out["de_solve_s"]["p50"] / out["solve_s"]["p50"]
        out["per_problem"] = rows
    out["goals"] = {
        "solve_s_p50_max": 0.3,
        "within_1pct_of_de_min": 0.95,
        "batch_problems_per_s_min": 20.0,
    }
    out["paper"] = {
        "yao_pso_solve_s": list(YAO_PSO_SOLVE_S),
        "yao_ranges": {k: list(v) for k, v in YAO_RANGES.items()},
        "yao_mean_objective": YAO_MEAN_OBJECTIVE,
        "speedup_vs_yao_pso": YAO_PSO_SOLVE_S[0] / out["solve_s"]["p50"],
    }
    return out
