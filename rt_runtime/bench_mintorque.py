"""``excavator-rt mintorque`` and ``excavator-rt bench mintorque``: the minimum-torque dig
optimiser of :mod:`rt_runtime.planning.mintorque` (Yang/Pan) at the command line and against
its CasADi/IPOPT reference.

The benchmark solves seeded problems on ``yang_pan_excavator`` (soils alternating, the surface,
the entry window and the volume band drawn around Experiment I), re-checks every answer on the
exact model at 1 ms, and solves the same problem with :class:`~rt_runtime.planning.mintorque.
CasadiReference` from the start our answer came from (``reference`` extra; skipped without
it). It also reports Yang/Pan's two comparisons from the same start: hard against soft soil
(Fig. 9) and variable against fixed time (Fig. 8). Degrees appear only in the printed text and
the command's JSON keypoints.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from typing import Any

import numpy as np

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import mintorque as mt
from rt_runtime.reports import Distribution
from rt_runtime.rig import Rig, load_rig

#: Goals of issue 29 for this benchmark (reported, never asserted: design note B1).
GOALS = {
    "solve_s_p50_max": 1.0,
    "solve_s_p99_max": 5.0,
    "feasible_min": 1.0,
    "gap_to_reference_max": 0.01,
}
RIG = "yang_pan_excavator"
SOILS = ("soft", "hard")


#: Problems solved again by the numpy model (the solve time's same-run reference).
TWIN_PROBLEMS = 4


def random_problems(rig: Rig, n: int, seed: int = 0) -> list[mt.MinTorqueProblem]:
    """Seeded problems around Yang/Pan Experiment I: soils in turn, the surface within
    +-0.3 m of the ground, the entry window shifted by up to +-0.3 m, the band's lower edge
    0.7-0.85 m^3 (upper 1.0)."""
    if n < 1:
        raise ConfigurationError(f"need at least 1 problem; got {n}")
    rng = np.random.default_rng(seed)
    base = mt.make_problem(rig, "soft")
    out = []
    for k in range(n):
        u = rng.uniform(-1.0, 1.0, 3)
        shift = 0.3 * float(u[1])
        out.append(
            mt.make_problem(
                rig,
                SOILS[k % 2],
                volume_m3=(0.775 + 0.075 * float(u[2]), 1.0),
                surface_y_m=rig.ground_y_m + 0.3 * float(u[0]),
                entry_x_m=(base.entry_x_m[0] + shift, base.entry_x_m[1] + shift),
            )
        )
    return out


def _path(sol: mt.Solution) -> dict[str, Any]:
    return {
        "keypoints_x_m": sol.tip_poses[:, 0].tolist(),
        "keypoints_y_m": sol.tip_poses[:, 1].tolist(),
        "intervals_s": sol.intervals_s.tolist(),
    }


def bench_mintorque(
    n_problems: int = 20, seed: int = 0, *, reference: bool = True, n_starts: int = 3
) -> dict[str, Any]:
    """The optimiser on :func:`random_problems`, the comparisons, and (with ``reference``) the
    gap to IPOPT from the same start on the same smoothed model and grid.

    Returns:
        JSON-ready dict: ``problems``, ``solve_s`` (p50, p99, max), ``feasible`` (fraction,
        exact model at 1 ms), ``gap_to_reference`` (p50, max of ``(ours - IPOPT) / IPOPT``
        costs; null without reference), ``soil`` (per soil: ``max_depth_m``, ``T_s``, ``cost``
        and the path), ``time`` (``variable`` and ``fixed``: ``T_s``, ``cost``), and more.
        ``n_starts`` kinematic starts per solve (3, the optimiser's default; fewer for a quick
        look).
    """
    rig = load_rig(RIG)
    problems = random_problems(rig, n_problems, seed)
    mt.solve(rig, problems[0], n_starts=1)  # warm-up (imports, caches)
    solutions = [mt.solve(rig, p, n_starts=n_starts) for p in problems]
    solve_s = np.array([s.solve_s for s in solutions])
    feasible = [s.feasible for s in solutions]
    in_band = [
        p.volume_m3[0] <= s.volume_m3 <= p.volume_m3[1]
        for p, s in zip(problems, solutions, strict=True)
    ]
    model_gap = [abs(s.cost_model - s.cost) / s.cost for s in solutions]
    twin = _numpy_twin(rig, problems[:TWIN_PROBLEMS], solutions[:TWIN_PROBLEMS], n_starts)

    # Yang/Pan's comparisons on Experiment I, from the same kinematic starts.
    comp: dict[str, mt.Solution] = {}
    for name in SOILS:
        comp[name] = mt.solve(rig, mt.make_problem(rig, name), n_starts=n_starts)
    comp["fixed"] = mt.solve(rig, mt.make_problem(rig, "soft", fixed_time=True), n_starts=n_starts)

    out: dict[str, Any] = {
        "problems": n_problems,
        "seed": seed,
        "rig": RIG,
        "n_starts": n_starts,
        "solve_s": Distribution.spread(solve_s).to_json(),
        "load_average": list(os.getloadavg()),
        "feasible": float(np.mean(feasible)),
        "volume_in_band": float(np.mean(in_band)),
        "smoothed_vs_exact_cost": {
            "p50": float(np.median(model_gap)),
            "max": float(np.max(model_gap)),
        },
        "gap_to_reference": None,
        "twin": twin,
        "soil": {
            name: {
                "max_depth_m": comp[name].max_depth_m,
                "T_s": comp[name].T_s,
                "cost": comp[name].cost,
                "volume_m3": comp[name].volume_m3,
                "feasible": comp[name].feasible,
                "path": _path(comp[name]),
            }
            for name in SOILS
        },
        "time": {
            "variable": {
                "T_s": comp["soft"].T_s,
                "cost": comp["soft"].cost,
                "feasible": comp["soft"].feasible,
            },
            "fixed": {
                "T_s": comp["fixed"].T_s,
                "cost": comp["fixed"].cost,
                "feasible": comp["fixed"].feasible,
            },
        },
        "failures": [
            {
                "problem": k,
                "soil": p.soil.name,
                "margins_below_zero": {n: v for n, v in s.margins.items() if v < 0.0},
            }
            for k, (p, s) in enumerate(zip(problems, solutions, strict=True))
            if not s.feasible
        ],
        "paper": {"solve_s": 150.0, "T_variable_s": 5.5, "T_fixed_s": 6.4, "volume_m3": [0.8, 1.0]},
    }
    if reference:
        out.update(_reference(rig, problems, solutions))
    out["goals"] = GOALS
    gap = out["gap_to_reference"]
    hard, soft = out["soil"]["hard"], out["soil"]["soft"]
    var, fix = out["time"]["variable"], out["time"]["fixed"]
    out["met"] = {
        "solve_s_p50": out["solve_s"]["p50"] <= GOALS["solve_s_p50_max"],
        "solve_s_p99": out["solve_s"]["p99"] <= GOALS["solve_s_p99_max"],
        "feasible": out["feasible"] >= GOALS["feasible_min"],
        "gap_to_reference": None
        if gap is None
        else bool(gap["max"] <= GOALS["gap_to_reference_max"]),
        "hard_shallower": hard["max_depth_m"] < soft["max_depth_m"],
        "variable_cheaper_and_shorter": var["cost"] < fix["cost"] and var["T_s"] < fix["T_s"],
        "volume_in_band": out["volume_in_band"] >= 1.0,
    }
    return out


def _numpy_twin(
    rig: Rig, problems: list[mt.MinTorqueProblem], ours: list[mt.Solution], n_starts: int
) -> dict[str, Any]:
    """The first problems solved again with the numpy model in place of the compiled kernel:
    the same-run reference of the solve time, and the cost difference (rounding only)."""
    backend = "numpy" if mt.kernel_for("auto") is None else "c"
    twin = [mt.solve(rig, p, n_starts=n_starts, backend="numpy") for p in problems]
    ours_p50 = float(np.median([s.solve_s for s in ours]))
    twin_p50 = float(np.median([s.solve_s for s in twin]))
    return {
        "backend": backend,
        "problems": len(problems),
        "solve_s_p50": twin_p50,
        "ours_solve_s_p50": ours_p50,
        "twin_over_ours_solve_p50": twin_p50 / ours_p50,
        "cost_difference_max": float(
            max(abs(a.cost - b.cost) / b.cost for a, b in zip(ours, twin, strict=True))
        ),
    }


def _reference(
    rig: Rig, problems: list[mt.MinTorqueProblem], solutions: list[mt.Solution]
) -> dict[str, Any]:
    """IPOPT on each problem from the start our answer came from, same limits and grid."""
    ref = mt.CasadiReference(rig)
    gaps: list[float] = []
    ref_s: list[float] = []
    failed: list[dict[str, Any]] = []
    per_problem: list[dict[str, Any]] = []
    for k, (p, sol) in enumerate(zip(problems, solutions, strict=True)):
        r = ref.solve(p, sol.start, sol.limit_scale)
        ev = mt.Evaluator(rig, p, limit_scale=sol.limit_scale).evaluate(r.x[None, :])
        if not r.ok or float(np.max(ev.constraints[0])) > 1e-6:
            failed.append({"problem": k, "status": r.status})
            continue
        ref_s.append(r.solve_s)
        gaps.append((sol.cost_model - r.cost_model) / r.cost_model)
        per_problem.append(
            {
                "problem": k,
                "soil": p.soil.name,
                "cost": sol.cost_model,
                "reference_cost": r.cost_model,
                "gap": gaps[-1],
            }
        )
    ours_p50 = float(np.median([s.solve_s for s in solutions]))
    return {
        "gap_to_reference": {
            "p50": float(np.percentile(gaps, 50)),
            "max": float(np.max(gaps)),
            "min": float(np.min(gaps)),
        }
        if gaps
        else None,
        "reference": {
            "solver": "casadi ipopt, one constraint per sample, exact derivatives",
            "solved": len(gaps),
            "failed": failed,
            "solve_s": Distribution.spread(ref_s).to_json() if ref_s else None,
            "reference_over_ours_solve_p50": float(np.median(ref_s)) / ours_p50 if ref_s else None,
            "per_problem": per_problem,
        },
    }


# --------------------------------------------------------------------------------------------
# Commands.


def _volume_band(text: str) -> tuple[float, float]:
    parts = text.split(",")
    try:
        lo, hi = (float(v) for v in parts)
    except ValueError:
        raise ConfigurationError(
            f"--volume-m3 {text!r}: expected LO,HI in m^3 (e.g. 0.8,1.0)"
        ) from None
    return lo, hi


def solution_json(rig: Rig, sol: mt.Solution, problem: mt.MinTorqueProblem) -> dict[str, Any]:
    """The ``mintorque --json`` report of a solution."""
    deg = 180.0 / math.pi
    return {
        "feasible": sol.feasible,
        "rig": rig.name,
        "soil": problem.soil.name,
        "fixed_time": problem.fixed_time,
        "keypoints": [
            {
                "name": name,
                "q_deg": (sol.keypoints_rad[k] * deg).tolist(),
                "x_m": float(sol.tip_poses[k, 0]),
                "y_m": float(sol.tip_poses[k, 1]),
                "attitude_deg": float(sol.tip_poses[k, 2] * deg),
            }
            for k, name in enumerate(mt.KEYPOINT_NAMES)
        ],
        "intervals_s": sol.intervals_s.tolist(),
        "T_s": sol.T_s,
        "cost": sol.cost,
        "cost_model": sol.cost_model,
        "volume_m3": sol.volume_m3,
        "volume_band_m3": list(problem.volume_m3),
        "max_depth_m": sol.max_depth_m,
        "surface_y_m": problem.surface_y_m,
        "margins": sol.margins,
        "solve_s": sol.solve_s,
        "iterations": sol.iterations,
    }


def cmd_mintorque(args: argparse.Namespace) -> int:
    """``excavator-rt mintorque``: one minimum-torque dig; exit 1 when none is feasible."""
    rig = load_rig(args.rig)
    problem = mt.make_problem(
        rig, args.soil, volume_m3=_volume_band(args.volume_m3), fixed_time=args.fixed_time
    )
    sol = mt.solve(rig, problem)
    out = solution_json(rig, sol, problem)
    if args.plot:
        _plot(args.plot, rig, problem, sol)
        out["plot"] = args.plot
    if args.json:
        print(json.dumps(out, indent=2))
        return 0 if sol.feasible else 1
    print(
        f"minimum-torque dig on {rig.name}, {problem.soil.name} soil, "
        f"{'fixed' if problem.fixed_time else 'variable'} time (Yang/Pan eq 6-18): "
        f"{'feasible' if sol.feasible else 'NOT feasible'}"
    )
    print("  keypoint   boom    stick   bucket [deg]   tip x [m]  y [m]  attitude [deg]")
    for kp in out["keypoints"]:
        b, s, k = kp["q_deg"]
        print(
            f"  {kp['name']:<9} {b:7.2f} {s:7.2f} {k:7.2f}        {kp['x_m']:7.3f} {kp['y_m']:7.3f} {kp['attitude_deg']:9.2f}"
        )
    print(f"  intervals {', '.join(f'{h:.3f}' for h in sol.intervals_s)} s; T = {sol.T_s:.3f} s")
    print(
        f"  cost {sol.cost:.6g} s (exact model, 1 ms; smoothed {sol.cost_model:.6g}); volume {sol.volume_m3:.3f} m^3 (band {problem.volume_m3[0]:g}..{problem.volume_m3[1]:g}); max depth {sol.max_depth_m:.3f} m"
    )
    tight = sorted(sol.margins.items(), key=lambda kv: kv[1])[:6]
    print("  tightest margins (>= 0 holds): " + ", ".join(f"{n} {v:.4f}" for n, v in tight))
    print(f"  solve {sol.solve_s:.2f} s, {sol.iterations} SLSQP iterations")
    return 0 if sol.feasible else 1


def _plot(path: str, rig: Rig, problem: mt.MinTorqueProblem, sol: mt.Solution) -> None:
    """Side view of the tip path with the keypoints, and the joint torques over their limits."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:
        raise ConfigurationError(f"--plot needs matplotlib (the plot extra): {e}") from None
    from rt_runtime import kinematics

    chk = mt.exact_check(rig, problem, sol.keypoints_rad, sol.intervals_s)
    q, _, _ = sol.sample(chk.t_s)
    tip = kinematics.forward(rig, q)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    a.plot(tip[:, 0], tip[:, 1], label="tip path")
    a.plot(sol.tip_poses[:, 0], sol.tip_poses[:, 1], "o", label="keypoints")
    a.axhline(problem.surface_y_m, color="brown", label="surface")
    a.set_xlabel("x [m]")
    a.set_ylabel("y [m]")
    a.set_aspect("equal")
    a.legend()
    for j, name in enumerate(mt.JOINTS):
        b.plot(chk.t_s, chk.tau_nm[:, j] / rig.tau_max_nm[j], label=name)
    b.set_xlabel("t [s]")
    b.set_ylabel("torque / limit")
    b.legend()
    fig.suptitle(f"{rig.name}, {problem.soil.name} soil: cost {sol.cost:.4g} s, T {sol.T_s:.2f} s")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def cmd_bench_mintorque(args: argparse.Namespace) -> int:
    """``excavator-rt bench mintorque``: solve time, feasibility, gap to CasADi/IPOPT, soils, time."""
    n = args.problems if args.problems is not None else (4 if args.quick else 20)
    reference = not args.no_reference
    if reference:
        try:
            import casadi  # noqa: F401
        except ImportError:
            reference = False
    try:
        r = bench_mintorque(n, args.seed, reference=reference, n_starts=1 if args.quick else 3)
    except PlanningError as e:
        raise ConfigurationError(f"bench mintorque: {e}") from None
    r["sizes"] = "quick" if args.quick else "full"
    r["reference_skipped"] = not reference
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    sv = r["solve_s"]
    print(
        f"minimum-torque dig optimiser (Yang/Pan) on {r['rig']}: {r['problems']} seeded problems (seed {r['seed']})"
    )
    print(
        f"  solve p50 {sv['p50']:.2f} s, p99 {sv['p99']:.2f} s, max {sv['max']:.2f} s (goals 1 / 5 s; paper ~150 s); load average {r['load_average'][0]:.2f}"
    )
    tw = r["twin"]
    print(
        f"  model evaluated by {tw['backend']}; the numpy model on the first {tw['problems']} problems: solve p50 {tw['solve_s_p50']:.2f} s against {tw['ours_solve_s_p50']:.2f} s ({tw['twin_over_ours_solve_p50']:.1f}x), costs within {tw['cost_difference_max']:.1e}"
    )
    print(
        f"  feasible on the exact model at 1 ms {r['feasible']:.0%}; volume in band {r['volume_in_band']:.0%}"
    )
    gap = r["gap_to_reference"]
    if gap is not None:
        ref = r["reference"]
        print(
            f"  gap to CasADi/IPOPT from the same start: p50 {gap['p50']:+.2%}, max {gap['max']:+.2%}, min {gap['min']:+.2%} ({ref['solved']} solved; IPOPT p50 {ref['solve_s']['p50']:.2f} s, {ref['reference_over_ours_solve_p50']:.1f}x ours)"
        )
    elif r["reference_skipped"]:
        print("  gap to CasADi/IPOPT: skipped (needs the reference extra)")
    for name, s in r["soil"].items():
        print(
            f"  {name} soil: max depth {s['max_depth_m']:.3f} m, T {s['T_s']:.2f} s, cost {s['cost']:.5g}"
        )
    v, f = r["time"]["variable"], r["time"]["fixed"]
    print(
        f"  variable time T {v['T_s']:.2f} s cost {v['cost']:.5g}; fixed (1.25 s intervals) T {f['T_s']:.2f} s cost {f['cost']:.5g} (paper 5.5 vs 6.4 s)"
    )
    print(
        "  met: "
        + ", ".join(
            f"{k} {'yes' if m else ('n/a' if m is None else 'NO')}" for k, m in r["met"].items()
        )
    )
    return 0


def add_parsers(sub: Any, bench_sub: Any) -> None:
    """Register ``mintorque`` and ``bench mintorque``."""
    mp = sub.add_parser(
        "mintorque",
        help="minimum-torque, time-variable dig with the soil in the loop (Yang/Pan); exit 1 when none is feasible",
    )
    mp.add_argument("--rig", default=RIG)
    mp.add_argument(
        "--soil", required=True, help="fluid soil of the rig (Yang/Pan Table 2: soft, hard)"
    )
    mp.add_argument(
        "--fixed-time",
        action="store_true",
        help="keep the four intervals at 1.25 s (Yang/Pan Experiment I has 1 s; design note Y1)",
    )
    mp.add_argument(
        "--volume-m3",
        default="0.8,1.0",
        metavar="LO,HI",
        help="swept-volume band (default 0.8,1.0)",
    )
    mp.add_argument(
        "--plot",
        metavar="FILE.png",
        help="tip path and torques over their limits (needs the plot extra)",
    )
    mp.add_argument("--json", action="store_true")
    mp.set_defaults(handler=cmd_mintorque)

    bp = bench_sub.add_parser(
        "mintorque",
        help="minimum-torque optimiser: solve time, feasibility at 1 ms, gap to CasADi/IPOPT, hard vs soft, variable vs fixed time",
    )
    bp.add_argument("--problems", type=int, help="seeded problems (default 20; 4 with --quick)")
    bp.add_argument("--seed", type=int, default=0)
    bp.add_argument(
        "--quick",
        action="store_true",
        help="4 problems, one start per solve (a first look, the tests)",
    )
    bp.add_argument(
        "--no-reference",
        action="store_true",
        help="skip CasADi/IPOPT (skipped anyway without the reference extra)",
    )
    bp.add_argument("--json", action="store_true")
    bp.set_defaults(handler=cmd_bench_mintorque)
