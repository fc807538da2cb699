"""Latency of the one-shot verifier: :meth:`rt_runtime.planning.verify.Verifier.evaluate_into`,
:meth:`~rt_runtime.planning.verify.Verifier.retime_into` and
:meth:`~rt_runtime.planning.verify.Verifier.plan_into`.

Times single calls, for one candidate (N = 1, what the PINN planner verifies per dig) and for a
batch of N = 32, with the C kernel (and evaluation with the numpy reference backend), and prints the
distributions as JSON: per-call p50/p90/p99/max in microseconds and the per-candidate p50/p99.
Retiming is timed at N = 1 on PSO plans whose T is scaled up by 1.0-1.4 (what a conservative
network gives; about a second of PSO to make them), next to a plain evaluation of the same
rows, and on random particles. Planning (the volume-filling path scale, then retiming) is timed
at N = 1 on network-like rows: PSO plans with their bulge scaled per joint by a seeded factor
around 0.8 (log-normal, sigma 0.15) and T 10 % longer, what an imprecise network gives, next to
retiming the same rows; ``plan_outcomes`` says how many of them plan feasibly against retiming
alone, fill the volume cap, or take the back-off. ``pinn_plan`` times planning on the PINN's own
answers to its held-out problems (``--models``, default the shipped ``onnx/``): per row the
least time over ``--pinn-reps`` passes, summarised by outcome (filled, backed off, own path,
failed). It also times the C call on a row the kernel rejects before any arithmetic (T < 0):
that is the per-call overhead (argument parsing, buffer checks, the Python method).

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


def network_candidates(rig_name: str, n: int, seed: int) -> np.ndarray:
    """``n`` input rows like an imprecise network's: PSO plans (both dig types) with their
    bulge ``K`` scaled per joint by ``0.8 exp(0.15 N(0, 1))`` (seeded) and T 10 % longer."""
    rig = load_rig(rig_name)
    planning = oneshot.require_planning(rig)
    rng = np.random.default_rng(seed)
    rows = []
    for kind in DigType:
        problems = oneshot.sample_problems(rig, 8, kind, seed=seed + 10 + int(kind))
        plans = oneshot.solve_pso(rig, problems, n_particles=20, n_iterations=20, seed=seed)
        for p, plan in zip(problems, plans, strict=True):
            K = -np.asarray(plan.a6) * plan.T_s**6
            T = min(1.1 * plan.T_s, planning.t_max_s)
            for _ in range(4):
                f = 0.8 * np.exp(0.15 * rng.standard_normal(3))
                rows.append(
                    verify.pack_inputs(
                        p.q_start_rad, p.q_end_rad, p.surface_y_m, kind, -(K * f) / T**6, T
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
    plan: bool = False,
) -> np.ndarray:
    """Wall time in ns of ``calls`` calls of ``batch`` rows each, cycling through ``rows``.

    ``retime`` times :meth:`~rt_runtime.planning.verify.Verifier.retime_into` instead of
    :meth:`~rt_runtime.planning.verify.Verifier.evaluate_into`, ``plan``
    :meth:`~rt_runtime.planning.verify.Verifier.plan_into` (default range, with the scale).
    """
    n_sets = max(1, rows.shape[0] // batch)
    sets = [np.ascontiguousarray(rows[i * batch : (i + 1) * batch]) for i in range(n_sets)]
    out = np.empty((batch, verify.N_OUT))
    path = np.empty((batch, verifier.n_samples, 2)) if with_path else None
    retimed = np.empty((batch, verify.N_RETIMED))
    scale = np.empty(batch)
    c_range = verify.PLAN_C_RANGE
    run = verifier.evaluate_into
    run_retime = verifier.retime_into
    run_plan = verifier.plan_into
    for s in sets[: min(len(sets), 50 if verifier.backend == "c" else 1)]:  # warm-up
        run(s, out, path)
        run_retime(s, out, retimed, path)
        run_plan(s, out, retimed, c_range, path, scale)
    times = np.empty(calls, dtype=np.int64)
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for k in range(calls):
            s = sets[k % n_sets]
            # The branch stays outside the timed region.
            if plan:
                t0 = clock()
                run_plan(s, out, retimed, c_range, path, scale)
                t1 = clock()
            elif retime:
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


def plan_classes(verifier: verify.Verifier, rows: np.ndarray) -> dict[str, np.ndarray]:
    """What plan_into does with each of ``rows`` (boolean masks): ``filled`` (feasible, the
    path scaled, no time-dependent limit decided), ``backed_off`` (feasible and scaled, yet a
    0.2 % larger bulge still passes every path-only limit: a time-dependent limit decided,
    the back-off's rows), ``own_path`` (feasible, the row's own path), ``failed`` (nothing
    feasible: step 4), plus ``at_volume_cap`` and ``feasible_retime_only`` (the own path
    retimed is feasible)."""
    n = rows.shape[0]
    out, planned, scale = np.empty((n, verify.N_OUT)), np.empty((n, 4)), np.empty(n)
    verifier.plan_into(rows, out, planned, verify.PLAN_C_RANGE, None, scale)
    own = np.empty((n, verify.N_OUT))
    verifier.retime_into(rows, own, np.empty((n, 4)))
    planning = oneshot.require_planning(verifier.rig)
    ok = out[:, verify.COL_TOTAL] <= 0.0
    bigger = rows.copy()
    bigger[:, verify.IN_A6 : verify.IN_A6 + 3] *= (scale * 1.002)[:, None]
    path_out = np.empty((n, verify.N_OUT))
    verifier.evaluate_into(bigger, path_out)
    slack = np.max(path_out[:, [*range(6), 16, 17, 18, 19]], axis=1) < 0.0
    v_span = planning.volume_max_m3 - planning.volume_min_m3
    capped = out[:, verify.COL_VOLUME_M3] >= planning.volume_max_m3 - verify.PLAN_TOL * v_span
    scaled = scale != 1.0
    return {
        "filled": ok & scaled & ~slack,
        "backed_off": ok & scaled & slack,
        "own_path": ok & ~scaled,
        "failed": ~ok,
        "at_volume_cap": ok & capped,
        "feasible_retime_only": own[:, verify.COL_TOTAL] <= 0.0,
    }


def plan_outcomes(verifier: verify.Verifier, rows: np.ndarray) -> dict[str, int]:
    """Counts of :func:`plan_classes`: feasible against retiming alone, how many fill the volume
    cap, take the back-off or report the own path."""
    cls = plan_classes(verifier, rows)
    return {
        "rows": int(rows.shape[0]),
        "feasible": int(rows.shape[0] - np.sum(cls["failed"])),
        "feasible_retime_only": int(np.sum(cls["feasible_retime_only"])),
        "at_volume_cap": int(np.sum(cls["at_volume_cap"])),
        "backed_off": int(np.sum(cls["backed_off"])),
        "own_path_reported": int(np.sum(cls["own_path"] | cls["failed"])),
    }


def pinn_rows(rig_name: str, model_dir: str | None) -> np.ndarray | None:
    """The PINN's answers on its held-out problems (both dig types) as input rows: what
    :meth:`rt_runtime.planning.pinn.PinnPlanner.plan` hands to plan_into. None when the model
    directory has no held-out sets."""
    from pathlib import Path

    from rt_runtime.bench import load_heldout
    from rt_runtime.errors import ConfigurationError
    from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, PinnPlanner

    directory = Path(model_dir) if model_dir is not None else DEFAULT_MODEL_DIR
    try:
        planner = PinnPlanner(load_rig(rig_name), directory)
        rows = []
        for kind in DigType:
            X = load_heldout(directory / f"pinn_{kind.name.lower()}_heldout.npz")["X"]
            Y = planner.infer(kind, X)
            rows.append(verify.pack_inputs(X[:, 0:3], X[:, 3:6], X[:, 6], kind, Y[:, 0:3], Y[:, 3]))
    except ConfigurationError:
        return None
    return np.ascontiguousarray(np.concatenate(rows))


def per_row_plan_us(verifier: verify.Verifier, rows: np.ndarray, reps: int) -> np.ndarray:
    """Per row, the least wall time (us) of one plan_into call over ``reps`` passes through all
    rows (a row's cost without the machine's noise; the passes keep the caches as cold as a
    planner's between digs)."""
    n = rows.shape[0]
    ns = time_calls(verifier, rows, 1, reps * n, False, plan=True)
    return np.asarray(ns.reshape(reps, n).min(axis=0) / 1e3)


def pinn_plan_report(verifier: verify.Verifier, rows: np.ndarray, reps: int) -> dict[str, object]:
    """plan_into on the PINN's held-out answers: per class of :func:`plan_classes`, the rows
    and the p50/p90/max of their per-row least times; all rows' p50/p99."""
    us = per_row_plan_us(verifier, rows, reps)
    cls = plan_classes(verifier, rows)
    report: dict[str, object] = {
        "rows": int(rows.shape[0]),
        "reps": reps,
        "all_p50_us": round(float(np.percentile(us, 50)), 2),
        "all_p99_us": round(float(np.percentile(us, 99)), 2),
    }
    for name in ("filled", "backed_off", "own_path", "failed"):
        m = cls[name]
        if np.any(m):
            p50, p90 = np.percentile(us[m], [50, 90])
            report[name] = {"rows": int(np.sum(m)), "p50_us": round(float(p50), 2),
                            "p90_us": round(float(p90), 2),
                            "max_us": round(float(us[m].max()), 2)}
    return report


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
    parser.add_argument("--models", default=None,
                        help="PINN model directory for the held-out plan case (default: the "
                        "shipped onnx/)")
    parser.add_argument("--pinn-reps", type=int, default=20,
                        help="passes over the PINN's held-out rows (per-row least time)")
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
    # (Retiming and planning are the C kernel's only.)
    plans = retime_candidates(args.rig, 64, args.seed)
    c_verifier = verify.Verifier(rig, args.n_samples, backend="c")
    for name, x, retime in (
        ("evaluate, slowed PSO plans", plans, False),
        ("retime, slowed PSO plans", plans, True),
        ("retime, random particles", rows, True),
    ):
        times = time_calls(c_verifier, x, 1, args.calls, args.path, retime=retime)
        cases.append({"backend": "c", "case": name, **summary(times, 1)})
    # Planning (N = 1) on network-like rows, next to retiming the same rows.
    net = network_candidates(args.rig, 64, args.seed)
    for name, x, retime, plan in (
        ("retime, network-like rows", net, True, False),
        ("plan, network-like rows", net, False, True),
        ("plan, random particles", rows, False, True),
    ):
        times = time_calls(c_verifier, x, 1, args.calls, args.path, retime=retime, plan=plan)
        cases.append({"backend": "c", "case": name, **summary(times, 1)})
    report["plan_outcomes"] = plan_outcomes(c_verifier, net)
    # Planning the PINN's own answers on its held-out problems, per row and by outcome.
    held = pinn_rows(args.rig, args.models) if args.n_samples == oneshot.DEFAULT_SAMPLES else None
    if held is not None:
        report["pinn_plan"] = pinn_plan_report(c_verifier, held, args.pinn_reps)
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
