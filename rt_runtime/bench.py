"""Benchmarks behind ``excavator-rt bench ...``: distributions, not single numbers.

Each benchmark returns one JSON-ready dict with stable keys (documented in the README). Timing
goals are checked here and reported, never asserted in tests: the machines are shared and noisy.
Percentile groups carry ``p50`` and ``p99``. The papers' figures are given under ``paper``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely

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
        ``paths`` (problems per path of :class:`rt_runtime.planning.pinn.PlanStatus`: ``retimed``,
        ``raw``, ``time_scaled``, ``repaired_fast``, ``refined``, ``teacher``, ``library`` and
        ``refused``;
        counts, not fractions), ``types`` (the same per type), ``goals``, ``paper``.
    """
    from pathlib import Path

    from rt_runtime.errors import PlanningError
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, PinnPlanner, PlanStatus

    directory = Path(model_dir) if model_dir is not None else DEFAULT_MODEL_DIR
    planner = PinnPlanner(rig, directory)
    verify_only = PinnPlanner(rig, directory, retime=False, refine=False)
    verify_us: list[float] = []
    out: dict[str, Any] = {
        "rig": rig.name,
        "verifier": planner.verifier.backend,
        "verifier_build": planner.verifier.build,
        "types": {},
    }
    all_infer: list[float] = []
    all_plan: list[float] = []
    all_gap: list[float] = []
    all_raw_gap: list[float] = []
    counts = {"n": 0, "raw": 0, "verified": 0, "refused": 0, "executed_ok": 0, "returned": 0}
    path_names = {
        PlanStatus.RETIMED: "retimed",
        PlanStatus.RAW: "raw",
        PlanStatus.TIME_SCALED: "time_scaled",
        PlanStatus.REPAIRED: "repaired_fast",
        PlanStatus.REFINED: "refined",
        PlanStatus.TEACHER: "teacher",
        PlanStatus.LIBRARY: "library",
    }
    path_keys = (*path_names.values(), "refused")
    all_paths = dict.fromkeys(path_keys, 0)
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
        # only (DESIGN.md's "inference + verification"), refusals not timed.
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
        paths = dict.fromkeys(path_keys, 0)
        for pl in returned:
            paths[path_names[pl.status]] += 1
        paths["refused"] = len(refused)
        for key, value in paths.items():
            all_paths[key] += value
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
            "plan_raw": paths["raw"] / n,
            "time_scaled": paths["time_scaled"] / n,
            "repaired_fast": paths["repaired_fast"] / n,
            "refined": paths["refined"] / n,
            "refused": len(refused) / n,
            "paths": paths,
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
            "paths": all_paths,
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
    """Whole-trench planning on Yao's Table 3 tasks: PINN timed, PSO beside it.

    Each task is planned ``passes`` times with the PINN planner (the plans are deterministic;
    the times are the distribution) and, with ``pso``, once with the PSO teacher as the one-shot
    planner. Reported per task: digs (with T, V_p, W_E, theta_p), coverage error, maximum
    over-dig, whole-plan time (p50/p99) and where it goes (``stage_us``, medians per stage),
    the PSO plan's totals and the ratio of the totals, and (``same_problems``) both planners
    on the PINN plan's own dig problems, summed.

    The reference measured in the same run: the same planner with its geometry in numpy
    (``geometry="numpy"``, the reference of the C screening geometry), its passes interleaved
    with the timed ones; ``numpy_geometry_same_plan`` says whether it planned the same digs.

    Returns:
        JSON-ready dict: ``tasks`` (per name), ``trench.plan_us`` (p50/p99 over all tasks and
        passes) and ``trench.numpy_geometry_plan_us``, ``goals``, ``paper``.
    """
    from rt_runtime.planning.trench import YAO_FIG14, TrenchPlanner, load_task

    pinn = TrenchPlanner(rig, "pinn", model_dir=model_dir)
    ref = TrenchPlanner(rig, "pinn", model_dir=model_dir, geometry="numpy")
    geometry = "c" if pinn.geo_kernel is not None else "numpy"
    out: dict[str, Any] = {}
    all_us: list[float] = []
    all_ref: list[float] = []
    for name in tasks:
        task = load_task(name, rig)
        times: list[float] = []
        ref_times: list[float] = []
        stages: list[dict[str, float]] = []
        plan = ref_plan = None
        for _ in range(max(1, passes)):
            plan = pinn.plan(task)
            times.append(plan.plan_total_us)
            stages.append(plan.stage_us)
            ref_plan = ref.plan(task)
            ref_times.append(ref_plan.plan_total_us)
        assert plan is not None and ref_plan is not None
        report = plan.to_json()  # the plans are deterministic: the last pass's
        all_us += times
        all_ref += ref_times
        task_time = report["dig_time_s"] + report["transition_time_s"]
        before = FIRST_DESIGN_TASK_TIME_S.get(name)
        entry: dict[str, Any] = {
            "pinn": report,
            "plan_us": percentiles(times),
            "plan_per_dig_ms": percentiles([t / 1e3 / max(len(plan.digs), 1) for t in times]),
            "fill_L": [d["volume_L"] for d in report["digs"]],
            "finishing": sum(d["finishing"] for d in report["digs"]),
            "travel_moves": len(report["travel"]),
            "task_time_s": task_time,
            "task_time_vs_first_design": task_time / before if before else None,
            "stage_us": {k: float(np.median([st[k] for st in stages])) for k in stages[0]},
            "numpy_geometry_plan_us": percentiles(ref_times),
            "speedup_vs_numpy_geometry": float(np.median(ref_times) / np.median(times)),
            "numpy_geometry_same_plan": len(ref_plan.digs) == len(plan.digs)
            and abs(ref_plan.coverage_error - plan.coverage_error) <= 1e-9,
            "totals": _plan_totals(report),
        }
        if pso:
            assert plan is not None
            entry["same_problems"] = _same_problems(rig, pinn, plan.digs, pso_options or {})
            t0 = time.perf_counter()
            pso_plan = TrenchPlanner(rig, "pso", model_dir=model_dir, pso_options=pso_options).plan(
                task
            )
            pso_report = pso_plan.to_json()
            entry["pso"] = pso_report
            entry["pso_plan_s"] = time.perf_counter() - t0
            entry["pso_totals"] = _plan_totals(pso_report)
            entry["pinn_vs_pso"] = {
                k: (entry["totals"][k] / v - 1.0) if v else None
                for k, v in entry["pso_totals"].items()
            }
        entry["yao"] = YAO_FIG14.get(name)
        entry["_plan"] = plan
        out[name] = entry
    per_dig = [e["plan_per_dig_ms"]["p50"] for e in out.values()]
    plans = {name: e.pop("_plan") for name, e in out.items()}
    first = next(
        (
            (name, d.index, d.problem)
            for name, plan in plans.items()
            for d in plan.digs
            if d.status == "filled"
        ),
        None,
    )
    reference = _pinn_reference(pinn, first)
    return {
        "rig": rig.name,
        "tasks": out,
        "trench": {
            "geometry": geometry,
            "plan_us": percentiles(all_us),
            "numpy_geometry_plan_us": percentiles(all_ref),
            "plan_per_dig_ms": percentiles(per_dig) if per_dig else None,
            "reference": reference,
            "plan_per_dig_over_pinn_plan": (
                float(np.median(per_dig) / reference["pinn_plan_ms"]["p50"])
                if reference and per_dig
                else None
            ),
        },
        "goals": {
            "coverage_error_max": 0.02,
            "overdig_max_mm": 5.0,
            "digs_max": {k: v["digs"] + 1 for k, v in YAO_FIG14.items()},
            "transition_penetration_max_mm": 5.0,
            "task_time_vs_first_design_max": 0.6,
            "plan_per_dig_ms": {"p50": 5.0, "p99": 20.0},
            "pinn_vs_pso_totals_max": 0.05,
        },
        "paper": {"yao_fig14": YAO_FIG14, "yao_plan_ms_per_dig": [4.2, 4.5]},
    }


def _same_problems(
    rig: Rig, planner: Any, digs: Any, pso_options: dict[str, Any]
) -> dict[str, Any]:
    """PINN and PSO on the very dig problems of the PINN's trench plan (Yao Table 4's pairing).

    Two whole-trench plans, one per one-shot planner, drift apart after the first dig (each
    leaves its own material, so later digs are different problems; the counts differ too).
    The like-for-like comparison of the two planners is per problem: every roughing dig of the
    PINN's plan (its entry and exit poses, surface height and type; the digs along the
    design's outline are fitted, not one-shot planned, and are the same for both) is planned by
    the PINN one-shot planner and by the PSO teacher, and T, V_p and W_E are summed over the
    task.
    """
    from rt_runtime.planning import oneshot

    sums = {"pinn": [0.0, 0.0, 0.0], "pso": [0.0, 0.0, 0.0]}
    n = 0
    pso_s: list[float] = []
    for d in digs:
        if d.status in ("profile", "profile_pass"):
            continue
        problem = d.problem
        plan = planner.pinn.plan(
            problem.q_start_rad, problem.q_end_rad, problem.surface_y_m, problem.dig_type
        )
        v = plan.verification
        t0 = time.perf_counter()
        sol = oneshot.solve_pso(rig, [problem], **pso_options)[0]
        pso_s.append(time.perf_counter() - t0)
        for key, (T, vol, e) in (
            ("pinn", (plan.T_s, v.volume_m3, v.energy_j)),
            ("pso", (sol.T_s, sol.volume_m3, sol.energy_j)),
        ):
            sums[key][0] += T
            sums[key][1] += vol * 1e3
            sums[key][2] += e / 3600.0
        n += 1
    totals = {
        k: {"digs": float(n), "T_s": t[0], "volume_L": t[1], "energy_Wh": t[2]}
        for k, t in sums.items()
    }
    return {
        **totals,
        "pso_solve_s": percentiles(pso_s) if pso_s else None,
        "pinn_vs_pso": {
            k: (totals["pinn"][k] / totals["pso"][k] - 1.0) if totals["pso"][k] else None
            for k in ("T_s", "volume_L", "energy_Wh")
        },
    }


#: Whole task time (digs + moves, s) of A-D with the first trench planner design, which the
#: second design's task-time goal is measured against (<= 60 % of it).
FIRST_DESIGN_TASK_TIME_S = {"A": 158.0, "B": 113.0, "C": 137.0, "D": 216.0}
#: Long trenches of `bench plan --long` (scale model: length m, depth m; scaled by reach).
LONG_TRENCHES = ((3.0, 0.15), (8.0, 0.10), (20.0, 0.20))


def bench_plan_long(
    rig: Rig,
    trenches: tuple[tuple[float, float], ...] = LONG_TRENCHES,
    *,
    planner: Any = None,
    model_dir: str | None = None,
) -> dict[str, Any]:
    """Long trenches dug section by section: each planned once (walls 60/60 deg, far edge at
    the default start). Reported per trench (key ``"<L>m"``): sections, travel moves and
    whether every one goes back along the trench, coverage (whole and worst section),
    over-dig, digs, finishing passes per section (max), fill band, status, plan time and plan
    time per metre (linear in length when the per-metre figures agree).

    Returns:
        JSON-ready dict: ``trenches`` and ``plan_s_per_m`` {min, max}.
    """
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.trench import TravelMove, TrenchPlanner, make_task

    if planner is None:
        planner = TrenchPlanner(rig, "pinn", model_dir=model_dir)
    scale = float(np.sum(rig.lengths_m)) / 1.31
    planning = oneshot.require_planning(rig)
    lo, hi = planning.volume_min_m3, planning.volume_max_m3
    out: dict[str, Any] = {}
    per_m: list[float] = []
    for length, depth in trenches:
        task = make_task(rig, length * scale, depth * scale, 60.0, 60.0, name=f"long-{length:g}m")
        trench = planner.start(task)
        t0 = time.perf_counter()
        plan = planner.plan(task)
        wall = time.perf_counter() - t0
        travels = [s.distance_m for s in plan.steps if isinstance(s, TravelMove)]
        sections = []
        for k, (x0, x1) in enumerate(trench.sections):
            box = shapely.box(x0, -1e3, x1, 1e3)
            design = plan.design.intersection(box)
            dug = plan.dug.intersection(box)
            digs = [d for d in plan.digs if d.section == k]
            sections.append(
                {
                    "coverage_error": float(dug.symmetric_difference(design).area)
                    / float(design.area),
                    "digs": len(digs),
                    "finishing": sum(d.finishing for d in digs),
                }
            )
        full = [d.volume_m3 for d in plan.digs if not d.finishing]
        per_m.append(wall / task.length_m)
        out[f"{length:g}m"] = {
            "length_m": task.length_m,
            "depth_m": task.depth_m,
            "sections": len(trench.sections),
            "travel_moves": len(travels),
            "travel_one_way": all(t < 0.0 for t in travels),
            "coverage_error": plan.coverage_error,
            "section_coverage_max": max(s["coverage_error"] for s in sections),
            "overdig_max_mm": plan.overdig_max_m * 1e3,
            "digs": len(plan.digs),
            "finishing_per_section_max": max(s["finishing"] for s in sections),
            "fill_within_band": (
                sum(lo - 1e-12 <= v <= hi + 1e-12 for v in full) / len(full) if full else None
            ),
            "status": plan.status.name.lower(),
            "plan_s": wall,
            "plan_s_per_m": wall / task.length_m,
        }
    return {"trenches": out, "plan_s_per_m": {"min": min(per_m), "max": max(per_m)}}


def _plan_totals(report: dict[str, Any]) -> dict[str, float]:
    digs = report["digs"]
    return {
        "digs": float(len(digs)),
        "T_s": float(sum(d["T_s"] for d in digs)),
        "volume_L": float(sum(d["volume_L"] for d in digs)),
        "energy_Wh": float(sum(d["energy_Wh"] for d in digs)),
    }


# ---------------------------------------------------------------------------------------------
# The random suite: `excavator-rt bench plan --random N --seed S`.

#: Lengths of the random suite's tasks (scale model, m; scaled by reach): from the domain's
#: shortest trench to one that takes two or three stands of the machine.
RANDOM_LENGTH_M = (0.30, 1.50)
#: The random suite's goals on the coverage error (fractions within which it counts tasks).
RANDOM_COVERAGE_BANDS = {"within_2pct": 0.02, "within_4pct": 0.04}
#: Tasks listed under ``worst`` in the random suite's report.
RANDOM_WORST = 5
#: Calls of the PINN planner on one dig problem for the suite's same-run reference.
RANDOM_REFERENCE_CALLS = 100


def random_tasks(rig: Rig, n: int, seed: int) -> list[Any]:
    """``n`` trench tasks drawn uniformly over the task domain of ``rig``.

    Each value is drawn uniformly and independently, in this order: length
    (:data:`RANDOM_LENGTH_M` scaled by reach, within the domain), depth, far wall, near wall
    and far edge ``start_x_m``, each over its whole range of
    :func:`rt_runtime.planning.trench.task_limits`. A draw whose walls meet above its depth is
    drawn again, all five values, from the same generator, so the suite is a function of
    ``(rig, n, seed)``.

    Returns:
        ``n`` :class:`~rt_runtime.planning.trench.TrenchTask`, named ``random-<seed>-<i>``.
    """
    from rt_runtime.planning.trench import make_task, task_limits
    from rt_runtime.rig.model import SCALE_MODEL_REACH_M

    rng = np.random.default_rng(seed)
    limits = task_limits(rig)
    s = float(np.sum(rig.lengths_m)) / SCALE_MODEL_REACH_M
    lo_l, hi_l = limits["length_m"]
    ranges = (
        (max(lo_l, RANDOM_LENGTH_M[0] * s), min(hi_l, RANDOM_LENGTH_M[1] * s)),
        limits["depth_m"],
        limits["beta1_deg"],
        limits["beta2_deg"],
        limits["start_x_m"],
    )
    tasks = []
    for i in range(n):
        while True:
            L, D, b1, b2, x = (float(rng.uniform(lo, hi)) for lo, hi in ranges)
            bottom = L - D / math.tan(math.radians(b1)) - D / math.tan(math.radians(b2))
            if bottom >= 0.0:
                break
        tasks.append(make_task(rig, L, D, b1, b2, x, name=f"random-{seed}-{i}"))
    return tasks


def _group(values: list[float], keys: tuple[str, ...]) -> dict[str, float] | None:
    """The named statistics (``min``, ``p50``, ``p99``, ``max``) of ``values``; None if empty."""
    if not values:
        return None
    a = np.asarray(values, dtype=np.float64)
    every = {
        "min": float(np.min(a)),
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "max": float(np.max(a)),
    }
    return {k: every[k] for k in keys}


def bench_plan_random(
    rig: Rig,
    n: int,
    seed: int = 0,
    *,
    model_dir: str | None = None,
    planner: Any = None,
) -> dict[str, Any]:
    """The random suite: ``n`` seeded tasks over the whole domain (:func:`random_tasks`),
    each planned with the PINN planner.

    An exception while planning a task is caught and kept with the task (``error``: its type
    and message) instead of ending the run; such a task counts as neither within a coverage
    band nor done. The same-run reference is the PINN planner's own call on one dig problem
    (the first roughing dig of the first task that has one, planned
    :data:`RANDOM_REFERENCE_CALLS` times as the trench planner calls it), beside the whole
    plans' time per dig.

    Args:
        rig: The rig.
        n: Number of tasks.
        seed: Seed of the task generator.
        model_dir: PINN model directory (default: the shipped ``onnx/``).
        planner: A :class:`~rt_runtime.planning.trench.TrenchPlanner` to use (default: a PINN
            planner built for ``rig``).

    Returns:
        JSON-ready dict (README "bench plan --random"): ``tasks``, ``seed``, ``within_2pct``,
        ``within_4pct``, ``coverage_error`` {p50, p99, max}, ``overdig_max_mm`` {p50, max},
        ``digs`` {p50, max}, ``fill`` (real volume per roughing dig in L {min, p50, max},
        ``band_L``, ``within_band``, ``n``), ``finishing_per_section_max``,
        ``transition_penetration_max_mm`` {p50, max}, ``plan_ms`` {p50, p99} per task,
        ``plan_per_dig_ms`` {p50, p99}, ``status_done``, ``errors``, ``error_tasks``,
        ``worst``, ``reference`` and ``per_task``. Groups over no task are None.
    """
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.trench import TrenchPlanner

    if planner is None:
        planner = TrenchPlanner(rig, "pinn", model_dir=model_dir)
    planning = oneshot.require_planning(rig)
    band_l = (planning.volume_min_m3 * 1e3, planning.volume_max_m3 * 1e3)
    tasks = random_tasks(rig, n, seed)
    records: list[dict[str, Any]] = []
    fills: list[float] = []
    finishing_max = 0
    first_problem: Any = None
    for task in tasks:
        rec: dict[str, Any] = {
            "name": task.name,
            "length_m": task.length_m,
            "depth_m": task.depth_m,
            "beta1_deg": math.degrees(task.beta1_rad),
            "beta2_deg": math.degrees(task.beta2_rad),
            "start_x_m": task.start_x_m,
        }
        try:
            plan = planner.plan(task)
            report = plan.to_json()
        except Exception as e:  # every failure is a result of the suite, kept with its task
            rec["error"] = f"{type(e).__name__}: {e}"
            records.append(rec)
            continue
        digs = report["digs"]
        roughing = [d for d in digs if not d["finishing"]]
        fills += [d["volume_L"] for d in roughing]
        per_section: dict[int, int] = {}
        for d in digs:
            if d["finishing"]:
                per_section[d["section"]] = per_section.get(d["section"], 0) + 1
        finishing_max = max(finishing_max, *per_section.values(), 0)
        if first_problem is None:
            first = next((d for d in plan.digs if d.status == "filled"), None)
            if first is not None:
                first_problem = (task.name, first.index, first.problem)
        rec.update(
            coverage_error=report["coverage_error"],
            overdig_max_mm=report["overdig_max_mm"],
            digs=len(digs),
            status=report["status"],
            reason=report["reason"],
            volume_left_L=report["volume_left_L"],
            transition_penetration_max_mm=report["transition_penetration_max_mm"],
            plan_ms=report["plan_total_us"] / 1e3,
        )
        records.append(rec)
    planned = [r for r in records if "error" not in r]
    coverage = [r["coverage_error"] for r in planned]
    per_dig = [r["plan_ms"] / r["digs"] for r in planned if r["digs"]]
    reference = _pinn_reference(planner, first_problem)
    out: dict[str, Any] = {
        "rig": rig.name,
        "tasks": n,
        "seed": seed,
        **{k: sum(c <= v for c in coverage) / max(n, 1) for k, v in RANDOM_COVERAGE_BANDS.items()},
        "coverage_error": _group(coverage, ("p50", "p99", "max")),
        "overdig_max_mm": _group([r["overdig_max_mm"] for r in planned], ("p50", "max")),
        "digs": _group([float(r["digs"]) for r in planned], ("p50", "max")),
        "fill": {
            **(_group(fills, ("min", "p50", "max")) or {"min": None, "p50": None, "max": None}),
            "band_L": list(band_l),
            "within_band": (
                sum(band_l[0] <= v <= band_l[1] for v in fills) / len(fills) if fills else None
            ),
            "n": len(fills),
        },
        "finishing_per_section_max": finishing_max,
        "transition_penetration_max_mm": _group(
            [r["transition_penetration_max_mm"] for r in planned], ("p50", "max")
        ),
        "plan_ms": _group([r["plan_ms"] for r in planned], ("p50", "p99")),
        "plan_per_dig_ms": _group(per_dig, ("p50", "p99")),
        "status_done": sum(r["status"] == "done" for r in planned) / max(n, 1),
        "errors": n - len(planned),
        "error_tasks": [r for r in records if "error" in r],
        "worst": sorted(planned, key=lambda r: -r["coverage_error"])[:RANDOM_WORST],
        "reference": reference,
        "per_task": records,
    }
    if reference is not None and per_dig:
        out["plan_per_dig_over_pinn_plan"] = float(
            np.median(per_dig) / reference["pinn_plan_ms"]["p50"]
        )
    else:
        out["plan_per_dig_over_pinn_plan"] = None
    return out


def _pinn_reference(planner: Any, first: Any) -> dict[str, Any] | None:
    """The PINN planner's own time on one dig problem (``(task, dig index, problem)``), called
    as the trench planner calls it (no solution library); None without a problem or when the
    call fails."""
    from rt_runtime.errors import PlanningError

    if first is None:
        return None
    name, index, p = first
    times: list[float] = []
    try:
        for _ in range(RANDOM_REFERENCE_CALLS):
            t0 = time.perf_counter()
            planner.pinn.plan(p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type, library=False)
            times.append((time.perf_counter() - t0) * 1e3)
    except PlanningError:
        return None
    return {
        "pinn_plan_ms": percentiles(times),
        "calls": len(times),
        "problem": {"task": name, "dig": index, "type": p.dig_type.name.lower()},
    }


# ---------------------------------------------------------------------------------------------
# The full suite: `excavator-rt bench` without a subcommand.

#: Goal: loop lateness at 500 Hz, p99 (us).
LOOP_LATENESS_P99_GOAL_US = 50.0
#: A comfortable pose of the scale model for holding (boom 30, stick -90, bucket -60 deg).
_HOLD_POSE_DEG = (30.0, -90.0, -60.0)


@dataclass(frozen=True, slots=True)
class BenchSizes:
    """How much work each part of :func:`bench_full` does.

    Attributes:
        pinn_limit: Held-out problems per dig type (None: all).
        pinn_passes: Timed passes of the PINN planner over them.
        pso_problems: Problems per dig type the PSO solves in the same run.
        trench_passes: Timed whole-trench plans of task A.
        loop_seconds: Loop run per rate (s).
    """

    pinn_limit: int | None = None
    pinn_passes: int = 5
    pso_problems: int = 5
    trench_passes: int = 3
    loop_seconds: float = 10.0

    @classmethod
    def quick(cls, loop_seconds: float = 1.0) -> BenchSizes:
        """Tiny sizes for tests and a first look (seconds, not minutes)."""
        return cls(
            pinn_limit=8, pinn_passes=1, pso_problems=1, trench_passes=1, loop_seconds=loop_seconds
        )


def _group_us(values_s: np.ndarray) -> dict[str, float] | None:
    """Percentile group with tails of values in seconds, reported in microseconds."""
    a = np.asarray(values_s, dtype=np.float64)
    a = a[np.isfinite(a)]
    return percentiles(a * 1e6, tails=True) if a.size else None


#: Entry-point group of what the HIL provides to the runtime's benchmark (``realtime``: the
#: real-time HIL process class).
HIL_GROUP = "excavator_rt.hil"


def bench_loop(
    rig: Rig,
    rates_hz: tuple[float, ...] = (500.0, 1000.0),
    seconds: float = 10.0,
    *,
    rt: Any = None,
    sync_timeout_s: float = 0.1,
    hil_rig: str | None = None,
) -> tuple[dict[str, Any], dict[str, dict[str, np.ndarray]]]:
    """Loop timing against the real-time HIL in its own process, one run per rate.

    For each rate: start the real-time HIL process (:func:`realtime_hil_process`; 127.0.0.1),
    boot and enable the drives through a :class:`~rt_runtime.canbus.CanMaster` on its bus, run the
    :class:`~rt_runtime.control.FixedRateLoop` for ``seconds`` with a step that holds position
    (RPDO1 of the reported stroke + SYNC, read the TPDOs, heartbeat), with ``rt`` applied.
    Then disable the drives and stop the process.

    Args:
        rig: Rig profile (its CAN ids, bitrate and drive set-up).
        rates_hz: Loop rates (Hz).
        seconds: Run per rate (s).
        rt: :class:`~rt_runtime.control.RtSettings` (default: all of them requested).
        sync_timeout_s: The HIL drives' SYNC/RPDO watchdog (a shared test machine stalls longer
            than a rig PC; the loop's own overruns are what is measured).
        hil_rig: Rig profile name for the HIL process (default ``rig.name``).

    Returns:
        ``(summary, raw)``: the JSON-ready ``loop`` section keyed by the rate as a string
        (``"500"``), and per rate the raw arrays ``lateness_s``, ``jitter_s``, ``exec_s``,
        ``rtt_s`` for plots.

    Raises:
        CommunicationError, DriveFault: The HIL did not start or the drives did not enable.
    """
    from rt_runtime.control import RtSettings

    hil_process = realtime_hil_process()
    settings = rt if rt is not None else RtSettings()
    summary: dict[str, Any] = {}
    raw: dict[str, dict[str, np.ndarray]] = {}
    for rate in rates_hz:
        key = f"{rate:g}"
        summary[key], raw[key] = _bench_rate(
            hil_process, rig, float(rate), seconds, settings, sync_timeout_s, hil_rig or rig.name
        )
    return summary, raw


def realtime_hil_process() -> Any:
    """The real-time HIL process class (``start(rig_name, q0_rad, period_s, max_wall_s,
    sync_timeout_s)``), found through the ``excavator_rt.hil`` entry point ``realtime``: the
    runtime never imports ``hil_sim``.

    Raises:
        ConfigurationError: No package provides it (the HIL is not installed).
    """
    from importlib.metadata import entry_points

    from rt_runtime.errors import ConfigurationError

    found = [ep for ep in entry_points(group=HIL_GROUP) if ep.name == "realtime"]
    if not found:
        raise ConfigurationError(
            f"no real-time HIL installed: entry point {HIL_GROUP} 'realtime' not found "
            "(install the project with its hil_sim package)"
        )
    return found[0].load()


def _bench_rate(
    hil_process: Any,
    rig: Rig,
    rate_hz: float,
    seconds: float,
    settings: Any,
    sync_timeout_s: float,
    hil_rig: str,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """One rate of :func:`bench_loop`: its JSON entry and raw arrays."""
    from rt_runtime import actuation
    from rt_runtime.canbus import CanMaster, CycleStatus
    from rt_runtime.control import (
        FixedRateLoop,
        LimitGuard,
        LoopConfig,
        MonotonicClock,
        StrokeLimits,
    )
    from rt_runtime.control.controllers import GuardFilter, HoldController
    from rt_runtime.control.hardware import DriveInterface
    from rt_runtime.control.manager import ControllerManager, executor_telemetry

    period = 1.0 / rate_hz
    n_cycles = max(1, round(seconds * rate_hz))
    hil = hil_process.start(
        rig_name=hil_rig,
        q0_rad=np.radians(np.array(_HOLD_POSE_DEG)),
        period_s=period,
        max_wall_s=seconds + 120.0,
        sync_timeout_s=sync_timeout_s,
    )
    clock = MonotonicClock()
    loop = FixedRateLoop(
        clock, LoopConfig(period_s=period, rt=settings), executor_telemetry(n_cycles)
    )
    try:
        # RT settings first: mlockall and gc.collect take longer than the drives' watchdog.
        loop.acquire_rt()
        master = CanMaster(hil.master_bus, rig, period_s=period)
        master.boot(clock.now, 5.0)
        master.enable(clock.now, 5.0)
        hold_um = master.feedback.position_um.copy()
        # The daemon's cycle between jobs: the hold controller, the guard, the drives in SI; the
        # answers to a SYNC are read a period later (nothing waits; a later one is stale).
        drives = DriveInterface(master, clock, 0.0)
        s0 = drives.measured_stroke_m()
        guard = GuardFilter(LimitGuard(StrokeLimits.from_rig(rig), period))
        guard.guard.reset(s0)
        q0 = actuation.stroke_to_joint(rig, s0, check_limits=False)
        hold = HoldController(s0, q0)
        manager = ControllerManager(drives, guard, loop)
        stats = manager.run(hold, hold.command, s0, q0, max_cycles=n_cycles)
        snap = loop.telemetry.snapshot()
        master.disable()
        load = master.bus_load(period)
        realistic = _realistic_bus_load(master, hold_um, period)
        hil_extra = hil.finish()[3]
    finally:
        loop.release_rt()
        hil.close()
    jitter = stats.period_jitter_s()
    status = snap["cycle_status"]
    wait = snap["wait_s"]
    send = snap["send_s"]
    entry: dict[str, Any] = {
        "period_us": period * 1e6,
        "cycles": stats.cycles,
        "seconds": seconds,
        "lateness_us": _group_us(stats.lateness_s),
        "jitter_us": _group_us(np.abs(jitter)),
        "jitter_signed_us": {
            "min": float(np.min(jitter) * 1e6) if jitter.size else None,
            "max": float(np.max(jitter) * 1e6) if jitter.size else None,
        },
        "exec_us": _group_us(stats.exec_s),
        # The step's parts: the transport's (sending the frames; waiting for the drives'
        # answers: bus, bridge, the HIL's response) and the runtime's own work (packing and
        # decoding, the controller, the guard, the telemetry).
        "send_us": _group_us(send),
        "wait_us": _group_us(wait),
        "transport_us": _group_us(send + wait),
        "own_us": _group_us(stats.exec_s - wait - send),
        "overruns": stats.overruns,
        "skipped": stats.skipped,
        "max_consecutive_overruns": stats.max_consecutive_overruns,
        "safe_stop": stats.safe_stop,
        "overrun_events": [
            {"cycle": e.index, "lateness_us": e.lateness_s * 1e6, "skipped": e.skipped}
            for e in stats.overrun_events[:10]
        ],
        "sync_rtt_us": _group_us(snap["rtt_s"]),
        "stale_cycles": int(np.sum(~np.isfinite(snap["rtt_s"]))),
        "fault_cycles": int(np.sum(status >= int(CycleStatus.EMCY))),
        "cycle_status": {
            CycleStatus(v).name: int(np.sum(status == v)) for v in np.unique(status) if v >= 0
        },
        "bus_load": {"nominal": load.nominal, "realistic": realistic, "worst": load.worst_case},
        "rt": stats.rt.as_dict(),
        "hil_process": hil_extra.get("hil_process"),
    }
    arrays = {
        "lateness_s": stats.lateness_s,
        "jitter_s": jitter,
        "exec_s": stats.exec_s,
        "rtt_s": snap["rtt_s"],
    }
    return entry, arrays


def _realistic_bus_load(master: Any, hold_um: np.ndarray, period_s: float) -> float:
    """Bus load of the cyclic frames as sent in the run, with their exact stuff bits.

    Per period: RPDO1 (the held target, zero velocity offset) per drive, SYNC (0x080), TPDO1
    (packed from the last feedback) per drive; heartbeats at their period with the worst-case
    length of a 1-byte frame (0.2 % of the frames at 500 Hz).
    """
    from rt_runtime.canbus import RPDO1, TPDO1
    from rt_runtime.canbus.busload import frame_bits_exact, frame_bits_worst

    cfg = master.config
    fb = master.feedback
    bits = float(frame_bits_exact(0x080, b""))
    for axis, node in enumerate(cfg.node_ids):
        rpdo = RPDO1.codec.pack(int(hold_um[axis]), 0)
        bits += frame_bits_exact(RPDO1.cob_base + node, rpdo)
        tpdo = TPDO1.codec.pack(int(fb.position_um[axis]), int(fb.velocity_um_s[axis]))
        bits += frame_bits_exact(TPDO1.cob_base + node, tpdo)
    bits += frame_bits_worst(1) * (len(cfg.node_ids) + 1) * period_s / cfg.heartbeat_period_s
    return float(bits / period_s / float(cfg.bitrate))


def bench_full(
    rig: Rig,
    *,
    sizes: BenchSizes | None = None,
    rates_hz: tuple[float, ...] = (500.0, 1000.0),
    rt: Any = None,
    model_dir: Any = None,
    hil_rig: str | None = None,
    loop: bool = True,
) -> tuple[dict[str, Any], dict[str, dict[str, np.ndarray]]]:
    """The whole suite of ``excavator-rt bench``: planning latency, loop timing, CAN.

    Planning: the PINN per dig on the held-out sets (:func:`bench_pinn`: inference alone and
    plan = inference + verification + repair), the PSO teacher on a few of the same problems in
    the same run, the whole trench plan of task A (:func:`bench_plan`, PINN, timed passes).
    Loop and CAN: :func:`bench_loop` at each rate against the real-time HIL. Ratios and Yao's
    figures beside ours.

    Args:
        rig: Rig profile.
        sizes: Work per part (default :class:`BenchSizes`; :meth:`BenchSizes.quick` for tests).
        rates_hz: Loop rates (Hz).
        rt: :class:`~rt_runtime.control.RtSettings` for the loop (default: all requested).
        model_dir: PINN model directory (default: the shipped ``onnx/``).
        hil_rig: Rig profile name for the HIL process (default ``rig.name``).
        loop: Run the loop and CAN part (False: planning only).

    Returns:
        ``(report, raw)``: the JSON-ready report (keys in the README, DESIGN.md "Reports") and
        the loop's raw arrays per rate (for :func:`plot_bench`).
    """
    sz = sizes if sizes is not None else BenchSizes()
    t_start = time.perf_counter()
    pinn = bench_pinn(
        rig,
        model_dir,
        limit=sz.pinn_limit,
        passes=sz.pinn_passes,
        pso_problems=sz.pso_problems,
    )
    trench = bench_plan(rig, ("A",), passes=sz.trench_passes, pso=False, model_dir=model_dir)
    task_a = trench["tasks"]["A"]
    pso_p50_s = pinn["pso_solve_s"]["p50"]
    plan_p50_s = pinn["plan_us"]["p50"] * 1e-6
    report: dict[str, Any] = {
        "rig": rig.name,
        "sizes": {
            "pinn_limit": sz.pinn_limit,
            "pinn_passes": sz.pinn_passes,
            "pso_problems_per_type": sz.pso_problems,
            "trench_passes": sz.trench_passes,
            "loop_seconds": sz.loop_seconds,
        },
        "pinn": {
            "infer_us": pinn["infer_us"],
            "plan_us": pinn["plan_us"],
            "verify_only_plan_us": pinn["verify_only_plan_us"],
            "samples": pinn["samples"],
            "refused": pinn["refused"],
            "executed_feasible": pinn["executed_feasible"],
            "gap_mean": pinn["gap_mean"],
        },
        "pso": {
            "solve_s": pinn["pso_solve_s"],
            "problems": sz.pso_problems * 2,
        },
        "trench": {
            "task": "A",
            "plan_us": trench["trench"]["plan_us"],
            "digs": len(task_a["pinn"]["digs"]),
            "coverage_error": task_a["pinn"].get("coverage_error"),
        },
        "paper": {
            "yao_pinn_plan_ms": list(YAO_PINN_PLAN_MS),
            "yao_pso_solve_s": list(YAO_PSO_SOLVE_S),
        },
        "ratios": {
            "pso_over_pinn_plan": pso_p50_s / plan_p50_s,
            "yao_pso_over_yao_pinn": YAO_PSO_SOLVE_S[0] / (YAO_PINN_PLAN_MS[1] * 1e-3),
            "yao_pinn_plan_over_ours": YAO_PINN_PLAN_MS[0] * 1e-3 / plan_p50_s,
            "yao_pso_over_ours": YAO_PSO_SOLVE_S[0] / pso_p50_s,
        },
        "goals": {"loop_500_lateness_p99_us_max": LOOP_LATENESS_P99_GOAL_US},
    }
    raw: dict[str, dict[str, np.ndarray]] = {}
    if loop:
        loop_summary, raw = bench_loop(rig, rates_hz, sz.loop_seconds, rt=rt, hil_rig=hil_rig)
        report["loop"] = loop_summary
        rtt_all = np.concatenate([r["rtt_s"] for r in raw.values()]) if raw else np.zeros(0)
        first = next(iter(loop_summary.values())) if loop_summary else None
        report["can"] = {
            "sync_rtt_us": _group_us(rtt_all),
            "bus_load": dict(first["bus_load"]) if first is not None else None,
            "bus_load_rate_hz": float(next(iter(loop_summary))) if loop_summary else None,
            "bitrate": rig.can.bitrate,
        }
        at_500 = loop_summary.get("500")
        report["goals"]["met"] = {
            "loop_500_lateness_p99": (
                at_500["lateness_us"]["p99"] <= LOOP_LATENESS_P99_GOAL_US
                if at_500 is not None and at_500["lateness_us"] is not None
                else None
            )
        }
    report["wall_s"] = time.perf_counter() - t_start
    return report, raw


def plot_bench(raw: dict[str, dict[str, np.ndarray]], path: Any) -> Any:
    """Histograms of loop lateness and SYNC -> TPDO round trip per rate (a PNG).

    Args:
        raw: The raw arrays of :func:`bench_full` / :func:`bench_loop`.
        path: Output file.

    Returns:
        The path written.

    Raises:
        ConfigurationError: matplotlib is not installed.
    """
    from pathlib import Path

    from rt_runtime.errors import ConfigurationError

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - the plot extra
        raise ConfigurationError(
            "--plot needs matplotlib: pip install 'excavator-rt[plot]'"
        ) from exc
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for rate, arrays in raw.items():
        for ax, name in zip(axes, ("lateness_s", "rtt_s"), strict=True):
            v = np.asarray(arrays[name], dtype=np.float64)
            v = v[np.isfinite(v)] * 1e6
            if v.size == 0:
                continue
            hi = max(float(np.max(v)), 1.0)
            bins = np.logspace(
                np.log10(max(float(np.min(v[v > 0])) if (v > 0).any() else 0.1, 0.1)),
                np.log10(hi * 1.01),
                60,
            )
            ax.hist(
                np.maximum(v, 0.1), bins=bins, histtype="step", label=f"{rate} Hz", linewidth=1.4
            )
    axes[0].axvline(LOOP_LATENESS_P99_GOAL_US, color="k", linestyle=":", label="goal p99 (500 Hz)")
    axes[0].set(
        xscale="log",
        yscale="log",
        xlabel="lateness (us)",
        ylabel="cycles",
        title="loop lateness (start - deadline)",
    )
    axes[1].set(
        xscale="log",
        yscale="log",
        xlabel="SYNC -> all TPDO1 (us)",
        ylabel="cycles",
        title="CAN round trip (real-time HIL, 127.0.0.1)",
    )
    for ax in axes:
        ax.legend()
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out
