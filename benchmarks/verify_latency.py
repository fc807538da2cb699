"""Latency of the one-shot verifier: :meth:`rt_runtime.planning.verify.Verifier.evaluate_into`.

Times single calls, for one candidate (N = 1, what the PINN planner verifies per dig) and for a
batch of N = 32, with the C kernel and with the numpy reference backend, and prints the
distributions as JSON: per-call p50/p90/p99/max in microseconds and the per-candidate p50/p99.
It also times the C call on a row the kernel rejects before any arithmetic (T < 0): that is the
per-call overhead (argument parsing, buffer checks, the Python method).

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


def time_calls(
    verifier: verify.Verifier, rows: np.ndarray, batch: int, calls: int, with_path: bool
) -> np.ndarray:
    """Wall time in ns of ``calls`` calls of ``batch`` rows each, cycling through ``rows``."""
    n_sets = max(1, rows.shape[0] // batch)
    sets = [np.ascontiguousarray(rows[i * batch : (i + 1) * batch]) for i in range(n_sets)]
    out = np.empty((batch, verify.N_OUT))
    path = np.empty((batch, verifier.n_samples, 2)) if with_path else None
    run = verifier.evaluate_into
    for s in sets[: min(len(sets), 50)]:  # warm-up
        run(s, out, path)
    times = np.empty(calls, dtype=np.int64)
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for k in range(calls):
            s = sets[k % n_sets]
            t0 = clock()
            run(s, out, path)
            times[k] = clock() - t0
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
