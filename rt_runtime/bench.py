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


YAO_PINN_PLAN_MS = (4.2, 4.5)  # Yao Table 4: PINN planning time per dig
#: Yao Table 4: mean of the four task averages (Ave-A..Ave-D; t s, V_p 10^3 cm^3 = L, W_E Wh).
YAO_TABLE4_MEAN = {
    "pso": {"T_s": 6.875, "volume_L": 4.9125, "energy_Wh": 0.05925},
    "pinn": {"T_s": 6.995, "volume_L": 4.9125, "energy_Wh": 0.062},
}


def load_heldout(path: Any) -> dict[str, np.ndarray]:
    """A held-out set written by :func:`rt_runtime.training.export.export`."""
    from pathlib import Path

    from rt_runtime.errors import ConfigurationError

    p = Path(path)
    if not p.is_file():
        raise ConfigurationError(
            f"held-out set {p} does not exist (written by `excavator-rt export`)"
        )
    with np.load(p) as z:
        return {k: z[k] for k in z.files}


def bench_pinn(
    rig: Rig,
    model_dir: Any = None,
    *,
    limit: int | None = None,
    passes: int = 5,
    pso_problems: int = 10,
    seed: int = 0,
) -> dict[str, Any]:
    """PINN planner on the held-out sets: quality against the PSO teacher, latency.

    For each dig type, every held-out problem is planned by
    :meth:`rt_runtime.planning.pinn.PinnPlanner.plan` (domain check, inference, verification,
    repair or refusal). Quality is judged twice: the network's raw answers by the numpy
    reference evaluation (``raw_feasible``, objective gap to the teacher), and every returned
    plan again by the numpy reference (``executed_feasible``, which must be 1.0). Latency is
    measured over ``passes`` passes over the problems; inference alone over as many bare
    onnxruntime calls. The PSO teacher solves ``pso_problems`` of them per type in the same run.

    Returns:
        JSON-ready dict with ``samples``, ``gap_mean``, ``gap_max`` (objective gap of the
        returned plans to the teacher, fractions of the teacher's objective; refused problems
        are counted in ``refused``, not here), ``raw_gap_mean``, ``raw_gap_max`` (the network's
        raw answers, feasible or not), ``raw_feasible``, ``verified_feasible`` (a verified plan
        was returned, raw or repaired), ``refused`` (fractions), ``executed_feasible``,
        ``infer_us`` and ``plan_us`` (p50, p99, p999, max), ``verify_only_plan_us`` (the same
        problems planned with fill and retime off, raw answers that verify: inference plus
        verification alone), ``pso_solve_s`` (p50, p99),
        ``speedup_vs_pso``, ``table4`` (per type: PSO vs PINN mean T, V_p, W_E and planning time),
        ``types`` (the same per type), ``goals``, ``paper``.
    """
    from pathlib import Path

    from rt_runtime.errors import PlanningError
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, PinnPlanner, PlanStatus

    directory = Path(model_dir) if model_dir is not None else DEFAULT_MODEL_DIR
    planner = PinnPlanner(rig, directory)
    verify_only = PinnPlanner(rig, directory, retime=False, refine=False)
    verify_us: list[float] = []
    out: dict[str, Any] = {"rig": rig.name, "verifier": planner.verifier.backend, "types": {}}
    all_infer: list[float] = []
    all_plan: list[float] = []
    all_gap: list[float] = []
    all_raw_gap: list[float] = []
    counts = {"n": 0, "raw": 0, "verified": 0, "refused": 0, "executed_ok": 0, "returned": 0}
    pso_s: list[float] = []
    table4: dict[str, Any] = {}
    for kind in oneshot.DigType:
        name = kind.name.lower()
        held = load_heldout(directory / f"pinn_{name}_heldout.npz")
        X = held["X"][:limit]
        n = X.shape[0]
        # Raw answers, judged by the numpy reference.
        Y = planner.infer(kind, X)
        ev = oneshot.evaluate(
            rig, X[:, 0:3], X[:, 3:6], X[:, 6], int(kind), Y[:, None, :3], Y[:, None, 3]
        )
        teacher = held["objective"][:n]
        raw_gap = (ev.objective[:, 0] - teacher) / np.abs(teacher)
        all_raw_gap.extend(raw_gap.tolist())
        plans: list[Any] = []
        refused: list[str] = []
        plan_us: list[float] = []
        for p in range(passes):
            for i in range(n):
                try:
                    plan = planner.plan(X[i, 0:3], X[i, 3:6], float(X[i, 6]), kind)
                except PlanningError as exc:
                    if p == 0:
                        refused.append(str(exc))
                        plans.append(None)
                    continue
                plan_us.append(plan.plan_us)
                if p == 0:
                    plans.append(plan)
        # The same problems planned without fill and retime: verification of the raw answer
        # only (the "inference + verification"), refusals not timed.
        for i in range(n):
            try:
                vplan = verify_only.plan(X[i, 0:3], X[i, 3:6], float(X[i, 6]), kind)
            except PlanningError:
                continue
            if vplan.status == PlanStatus.RAW:
                verify_us.append(vplan.plan_us)
        # Inference alone: the bare bound session call.
        sess = planner._sessions[kind]
        infer_us = []
        for i in range(n * passes):
            sess.x[0] = X[i % n]
            t0 = time.perf_counter()
            sess.run()
            infer_us.append((time.perf_counter() - t0) * 1e6)
        returned = [pl for pl in plans if pl is not None]
        ok = 0
        if returned:
            a6 = np.array([pl.a6 for pl in returned])
            T = np.array([pl.T_s for pl in returned])
            idx = np.array([i for i, pl in enumerate(plans) if pl is not None])
            ev_exec = oneshot.evaluate(
                rig, X[idx, 0:3], X[idx, 3:6], X[idx, 6], int(kind), a6[:, None, :], T[:, None]
            )
            ok = int(np.sum(ev_exec.feasible[:, 0]))
            gap = (ev_exec.objective[:, 0] - teacher[idx]) / np.abs(teacher[idx])
            all_gap.extend(gap.tolist())
        else:
            gap = np.array([np.nan])
        n_raw = sum(1 for pl in returned if pl.status == PlanStatus.RAW)
        # The teacher on a few of the same problems, in the same run.
        sub = [
            oneshot.Problem(
                q_start_rad=(float(X[i, 0]), float(X[i, 1]), float(X[i, 2])),
                q_end_rad=(float(X[i, 3]), float(X[i, 4]), float(X[i, 5])),
                surface_y_m=float(X[i, 6]),
                dig_type=kind,
            )
            for i in range(min(pso_problems, n))
        ]
        for prob in sub:
            t0 = time.perf_counter()
            oneshot.solve_pso(rig, [prob], seed=seed)
            pso_s.append(time.perf_counter() - t0)
        table4[name] = {
            "pso": {
                "T_s": float(np.mean(held["T_s"][:n])),
                "volume_L": float(np.mean(held["volume_m3"][:n]) * 1e3),
                "energy_Wh": float(np.mean(held["energy_j"][:n]) / 3600.0),
                "plan_s": float(np.median(pso_s[-len(sub) :])) if sub else float("nan"),
            },
            "pinn": {
                "T_s": float(np.mean([pl.T_s for pl in returned])) if returned else float("nan"),
                "volume_L": float(np.mean([pl.verification.volume_m3 for pl in returned]) * 1e3)
                if returned
                else float("nan"),
                "energy_Wh": float(np.mean([pl.verification.energy_j for pl in returned]) / 3600.0)
                if returned
                else float("nan"),
                "plan_ms": float(np.median(plan_us) / 1e3) if plan_us else float("nan"),
            },
        }
        out["types"][name] = {
            "samples": n,
            "gap_mean": float(np.mean(gap)),
            "gap_max": float(np.max(gap)),
            "raw_gap_mean": float(np.mean(raw_gap)),
            "raw_feasible": float(np.mean(ev.feasible[:, 0])),
            "plan_raw": n_raw / n,
            "time_scaled": sum(1 for pl in returned if pl.status == PlanStatus.TIME_SCALED) / n,
            "refined": sum(1 for pl in returned if pl.status == PlanStatus.REFINED) / n,
            "refused": len(refused) / n,
            "refusals": refused[:5],
            "plan_us": percentiles(plan_us, tails=True) if plan_us else None,
            "infer_us": percentiles(infer_us, tails=True),
        }
        counts["n"] += n
        counts["raw"] += int(np.sum(ev.feasible[:, 0]))
        counts["verified"] += len(returned)
        counts["refused"] += len(refused)
        counts["returned"] += len(returned)
        counts["executed_ok"] += ok
        all_infer.extend(infer_us)
        all_plan.extend(plan_us)
    out.update(
        {
            "samples": counts["n"],
            "gap_mean": float(np.mean(all_gap)) if all_gap else float("nan"),
            "gap_max": float(np.max(all_gap)) if all_gap else float("nan"),
            "raw_gap_mean": float(np.mean(all_raw_gap)),
            "raw_gap_max": float(np.max(all_raw_gap)),
            "raw_feasible": counts["raw"] / counts["n"],
            "verified_feasible": counts["verified"] / counts["n"],
            "refused": counts["refused"] / counts["n"],
            "executed_feasible": counts["executed_ok"] / counts["returned"]
            if counts["returned"]
            else float("nan"),
            "infer_us": percentiles(all_infer, tails=True),
            "plan_us": percentiles(all_plan, tails=True),
            "verify_only_plan_us": percentiles(verify_us, tails=True) if verify_us else None,
            "pso_solve_s": percentiles(pso_s),
            "table4": table4,
        }
    )
    out["speedup_vs_pso"] = out["pso_solve_s"]["p50"] / (out["plan_us"]["p50"] * 1e-6)
    out["goals"] = {
        "gap_mean_max": 0.03,
        "raw_feasible_min": 0.95,
        "executed_feasible": 1.0,
        "plan_us_p50_max": 20.0,
        "plan_us_p99_max": 100.0,
    }
    out["paper"] = {
        "yao_pinn_plan_ms": list(YAO_PINN_PLAN_MS),
        "yao_pso_solve_s": list(YAO_PSO_SOLVE_S),
        "yao_gap_approx": 0.05,
        "yao_table4_mean": YAO_TABLE4_MEAN,
        "speedup_vs_yao_pinn": YAO_PINN_PLAN_MS[0] * 1e3 / out["plan_us"]["p50"],
    }
    return out


def bench_plan(
    rig: Rig,
    tasks: tuple[str, ...] = ("A", "B", "C", "D"),
    *,
    passes: int = 3,
    pso: bool = True,
    pso_options: dict[str, Any] | None = None,
    model_dir: str | None = None,
) -> dict[str, Any]:
    """Whole-trench planning (issue 5) on Yao's Table 3 tasks: PINN timed, PSO beside it.

    Each task is planned ``passes`` times with the PINN planner (the plans are deterministic;
    the times are the distribution) and, with ``pso``, once with the PSO teacher as the one-shot
    planner. Reported per task: digs (with T, V_p, W_E, theta_p), coverage error, maximum
    over-dig, whole-plan time (p50/p99), the PSO plan's totals and the ratio of the totals.

    Returns:
        JSON-ready dict: ``tasks`` (per name), ``trench.plan_us`` (p50/p99 over all tasks and
        passes), ``goals``, ``paper``.
    """
    from rt_runtime.planning.trench import YAO_FIG14, TrenchPlanner, load_task

    pinn = TrenchPlanner(rig, "pinn", model_dir=model_dir)
    out: dict[str, Any] = {}
    all_us: list[float] = []
    for name in tasks:
        task = load_task(name, rig)
        times: list[float] = []
        report: dict[str, Any] = {}
        for _ in range(max(1, passes)):
            plan = pinn.plan(task)
            times.append(plan.plan_total_us)
            report = plan.to_json()
        all_us += times
        entry: dict[str, Any] = {
            "pinn": report,
            "plan_us": percentiles(times),
            "totals": _plan_totals(report),
        }
        if pso:
            t0 = time.perf_counter()
            pso_plan = TrenchPlanner(
                rig, "pso", model_dir=model_dir, pso_options=pso_options
            ).plan(task)
            pso_report = pso_plan.to_json()
            entry["pso"] = pso_report
            entry["pso_plan_s"] = time.perf_counter() - t0
            entry["pso_totals"] = _plan_totals(pso_report)
            entry["pinn_vs_pso"] = {
                k: (entry["totals"][k] / v - 1.0) if v else None
                for k, v in entry["pso_totals"].items()
            }
        entry["yao"] = YAO_FIG14.get(name)
        out[name] = entry
    return {
        "rig": rig.name,
        "tasks": out,
        "trench": {"plan_us": percentiles(all_us)},
        "goals": {"coverage_error_max": 0.02, "overdig_max_mm": 5.0, "plan_us_p50_max": 1000.0,
                  "pinn_vs_pso_totals_max": 0.05},
        "paper": {"yao_fig14": YAO_FIG14, "yao_plan_ms_per_dig": [4.2, 4.5]},
    }


def _plan_totals(report: dict[str, Any]) -> dict[str, float]:
    digs = report["digs"]
    return {
        "digs": float(len(digs)),
        "T_s": float(sum(d["T_s"] for d in digs)),
        "volume_L": float(sum(d["volume_L"] for d in digs)),
        "energy_Wh": float(sum(d["energy_Wh"] for d in digs)),
    }
