"""Latency of the one-shot verifier: :meth:`rt_runtime.planning.verify.Verifier.evaluate_into`
and :meth:`~rt_runtime.planning.verify.Verifier.retime_into`.

Times single calls, for one candidate (N = 1, what the PINN planner verifies per dig) and for a
batch of N = 32, with the C kernel and with the numpy reference backend, and prints the
distributions as JSON: per-call p50/p90/p99/max in microseconds and the per-candidate p50/p99.
Retiming is timed at N = 1 on PSO plans whose T is scaled up by 1.0-1.4 (what a conservative
network gives; about a second of PSO to make them), next to a plain evaluation of the same
rows, and on random particles. It also times the C call on a row the kernel rejects before any
arithmetic (T < 0): that is the per-call overhead (argument parsing, buffer checks, the Python
method).

Candidates are random particles of the PSO search box on sampled problems of both dig types,
cycled through so that the branch predictor does not learn one path. The garbage collector is
off while timing. Run on a quiet machine; the numbers are wall time::

    .venv/bin/python benchmarks/verify_latency.py --calls 20000 --numpy-calls 300
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import gc
import json
import platform
import sys
import time
from collections.abc import Sequence

import numpy as np

from rt_runtime.planning import oneshot, verify
from rt_runtime.planning.oneshot import DigType
from rt_runtime.rig import load_rig


def candidates(rig_name: str, n: int, seed: int) -> np.ndarray:
    """``n`` input rows: random particles on sampled problems, half downward, half backward."""
    rig = load_rig(rig_name)
    rng = np.random.default_rng(seed)
    lo, hi = oneshot.search_bounds(rig)
    rows = []
    half = (n + 1) // 2
    for kind in DigType:
        for p in oneshot.sample_problems(rig, half, kind, seed=seed + int(kind)):
            a6, T = oneshot.a6_from_particle(rng.uniform(lo, hi))
            rows.append(
                verify.pack_inputs(p.q_start_rad, p.q_end_rad, p.surface_y_m, kind, a6, T)[0]
            )
    return np.ascontiguousarray(np.array(rows[:n]))


def retime_candidates(rig_name: str, n: int, seed: int) -> np.ndarray:
    """``n`` input rows like the PINN's: PSO teacher plans (both dig types) slowed down.

    A few problems are solved with a small PSO (about a second); each plan's path is kept and
    its T scaled by 1.0 to 1.4 (capped at t_max), so retiming has to find the plan's own T
    again, as it does for a network whose T is conservative.
    """
    rig = load_rig(rig_name)
    planning = oneshot.require_planning(rig)
    rows = []
    for kind in DigType:
        problems = oneshot.sample_problems(rig, 4, kind, seed=seed + int(kind))
        plans = oneshot.solve_pso(rig, problems, n_particles=20, n_iterations=20, seed=seed)
        for p, plan in zip(problems, plans, strict=True):
            K = -np.asarray(plan.a6) * plan.T_s**6
            for f in np.linspace(1.0, 1.4, 8):
                T = min(plan.T_s * f, planning.t_max_s)
                rows.append(
                    verify.pack_inputs(
                        p.q_start_rad, p.q_end_rad, p.surface_y_m, kind, -K / T**6, T
                    )[0]
                )
    x = np.array(rows)
    return np.ascontiguousarray(np.resize(x, (max(n, 1), x.shape[1])))


def time_calls(
    verifier: verify.Verifier,
    rows: np.ndarray,
    batch: int,
    calls: int,
    with_path: bool,
    retime: bool = False,
) -> np.ndarray:
    """Wall time in ns of ``calls`` calls of ``batch`` rows each, cycling through ``rows``.

    ``retime`` times :meth:`~rt_runtime.planning.verify.Verifier.retime_into` instead of
    :meth:`~rt_runtime.planning.verify.Verifier.evaluate_into`.
    """
    n_sets = max(1, rows.shape[0] // batch)
    sets = [np.ascontiguousarray(rows[i * batch : (i + 1) * batch]) for i in range(n_sets)]
    out = np.empty((batch, verify.N_OUT))
    path = np.empty((batch, verifier.n_samples, 2)) if with_path else None
    retimed = np.empty((batch, verify.N_RETIMED))
    run = verifier.evaluate_into
    run_retime = verifier.retime_into
    for s in sets[: min(len(sets), 50)]:  # warm-up
        run(s, out, path)
        run_retime(s, out, retimed, path)
    times = np.empty(calls, dtype=np.int64)
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for k in range(calls):
            s = sets[k % n_sets]
            # The branch stays outside the timed region.
            if retime:
                t0 = clock()
                run_retime(s, out, retimed, path)
                t1 = clock()
            else:
                t0 = clock()
                run(s, out, path)
                t1 = clock()
            times[k] = t1 - t0
    finally:
        gc.enable()
    return times


def summary(times_ns: np.ndarray, batch: int) -> dict[str, float | int]:
    """Percentiles in microseconds, per call and per candidate."""
    us = times_ns / 1e3
    p50, p90, p99 = np.percentile(us, [50, 90, 99])
    return {
        "batch": batch,
        "calls": int(us.size),
        "p50_us": round(float(p50), 3),
        "p90_us": round(float(p90), 3),
        "p99_us": round(float(p99), 3),
        "max_us": round(float(us.max()), 3),
        "mean_us": round(float(us.mean()), 3),
        "per_candidate_p50_us": round(float(p50) / batch, 3),
        "per_candidate_p99_us": round(float(p99) / batch, 3),
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rig", default="scale_model")
    parser.add_argument("--n-samples", type=int, default=oneshot.DEFAULT_SAMPLES)
    parser.add_argument("--calls", type=int, default=20000, help="timed calls per C case")
    parser.add_argument("--numpy-calls", type=int, default=300, help="timed calls per numpy case")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 32])
    parser.add_argument("--path", action="store_true", help="also write the tip path")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    rig = load_rig(args.rig)
    rows = candidates(args.rig, 512, args.seed)
    report: dict[str, object] = {
        "rig": args.rig,
        "n_samples": args.n_samples,
        "with_path": args.path,
        "python": sys.version.split()[0],
        "machine": platform.machine(),
        "processor": platform.processor() or platform.machine(),
        "cases": [],
    }
    cases: list[dict[str, object]] = []
    for backend, calls in (("c", args.calls), ("numpy", args.numpy_calls)):
        verifier = verify.Verifier(rig, args.n_samples, backend=backend)
        for batch in args.batches:
            times = time_calls(verifier, rows, batch, calls, args.path)
            cases.append({"backend": verifier.backend, **summary(times, batch)})
    # Retiming (N = 1, what the PINN planner does per dig) on slowed-down PSO plans, against
    # a plain evaluation of the same rows; random particles exercise the slow paths (no T in
    # range works: scan and least-violation grid).
    plans = retime_candidates(args.rig, 64, args.seed)
    for backend, calls in (("c", args.calls), ("numpy", max(1, args.numpy_calls // 20))):
        verifier = verify.Verifier(rig, args.n_samples, backend=backend)
        for name, x, retime in (
            ("evaluate, slowed PSO plans", plans, False),
            ("retime, slowed PSO plans", plans, True),
            ("retime, random particles", rows, True),
        ):
            if backend == "numpy" and not retime:
                continue
            times = time_calls(verifier, x, 1, calls, args.path, retime=retime)
            cases.append({"backend": verifier.backend, "case": name, **summary(times, 1)})
    c_verifier = verify.Verifier(rig, args.n_samples, backend="c")
    rejected = rows[:1].copy()
    rejected[0, verify.IN_T] = -1.0
    overhead = summary(time_calls(c_verifier, rejected, 1, args.calls, args.path), 1)
    cases.append({"backend": "c", "case": "call overhead (row rejected before arithmetic)",
                  **overhead})
    report["cases"] = cases
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
