"""``excavator-rt bench teach``: teach-and-plan on the simulated operator's demonstrations.

Role: the issue's goals for teach-and-plan (Zhao et al.), measured. The simulated operator
(:mod:`hil_sim.operator`) digs N demonstrations (15, ~10-18 s each at 100 Hz, seeds ``seed`` ..
``seed + N - 1``); the runtime's pipeline (:mod:`rt_runtime.teach.pipeline`) turns them into
waypoints and the taught trench. Measured:

* demonstrations to waypoints (alignment, moving average, average, FK, Douglas-Peucker, IK):
  wall and process CPU time over ``passes`` runs, p50 and p99, with the same pipeline aligned by
  uniform time scaling instead of DTW as the same-run reference, and the ratio;
* the discrete Frechet distance of the planned tip path from the operator's intended path (the
  ground truth the operator model keeps), against ``epsilon + 2 cm``; the same for the
  operator's mean path, with DTW and with uniform time scaling;
* the taught cycle's time against the operator's mean cycle time (goal <= 70 %);
* the trench's total against Zhao's 80.8 s for 7 cycles;
* the exact limit check of every cycle.

Timings are reported, never asserted (design note B1). It runs in the harness because it needs
the operator model (rt_runtime never imports hil_sim).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from typing import Any

import numpy as np

from hil_sim.operator import demonstrate
from rt_runtime.rig import load_rig
from rt_runtime.teach import pipeline
from rt_runtime.teach.command import ZHAO_CYCLES, ZHAO_TRENCH_S, frechet_m, planned_tip_path
from rt_runtime.teach.demos import validate

__all__ = ["GOALS", "add_parser", "bench_teach", "run"]

#: The issue's goals (times in ms; the Frechet goal is epsilon plus this, m).
GOALS = {
    "waypoints_ms_p50_max": 200.0,
    "frechet_over_epsilon_max_m": 0.02,
    "cycle_over_operator_max": 0.70,
}


def _pct(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max())}


def _timed(fn: Any, passes: int) -> tuple[list[float], list[float], Any]:
    wall, cpu = [], []
    out = None
    for _ in range(passes):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return wall, cpu, out


def bench_teach(
    *, demos: int = 15, seed: int = 0, passes: int = 10, epsilon_mm: float = 50.0,
    cycles: int = 7, rig_name: str = "field_excavator",
) -> dict[str, Any]:
    """Run the benchmark (module docstring); returns the ``bench teach --json`` report."""
    rig = load_rig(rig_name)
    t0 = time.perf_counter()
    ds = [demonstrate(rig, seed=seed + k) for k in range(demos)]
    demo_s = time.perf_counter() - t0
    records = [validate(rig, f"operator seed {d.seed}", d.t_s, d.q_rad) for d in ds]
    settings = pipeline.TeachSettings(epsilon_m=epsilon_mm / 1e3, cycles=cycles)
    linear = pipeline.TeachSettings(epsilon_m=epsilon_mm / 1e3, cycles=cycles,
                                    alignment="linear")
    wall, cpu, learned = _timed(lambda: pipeline.learn_waypoints(rig, records, settings), passes)
    ref_wall, ref_cpu, ref_learned = _timed(
        lambda: pipeline.learn_waypoints(rig, records, linear), passes
    )
    _, mean_q, idx, _ = learned
    t1 = time.perf_counter()
    idx, wps, cycle = pipeline.refine_cycle(rig, mean_q, idx, settings)
    trench = pipeline.plan_trench(rig, wps, settings, cycle)
    plan_s = time.perf_counter() - t1
    intended = pipeline.tip_path(rig, ds[0].intended_q_rad)
    planned = planned_tip_path(rig, cycle)
    frechet = frechet_m(planned, intended)
    mean_frechet = frechet_m(pipeline.tip_path(rig, mean_q), intended)
    linear_frechet = frechet_m(pipeline.tip_path(rig, ref_learned[1]), intended)
    durations = pipeline.cycle_times_s(records)
    op_mean = float(durations.mean())
    v_ratio, a_ratio, exact = pipeline.peak_ratios(trench, settings)
    names = list(rig.joint_names)
    peaks = {
        n: {"velocity_ratio": float(v_ratio[j]), "acceleration_ratio": float(a_ratio[j])}
        for j, n in enumerate(names)
    }
    wp = _pct(wall)
    ref = _pct(ref_wall)
    eps = epsilon_mm / 1e3
    ratio = cycle.duration_s / op_mean
    met = {
        "waypoints_ms_p50": wp["p50"] <= GOALS["waypoints_ms_p50_max"],
        "frechet": frechet <= eps + GOALS["frechet_over_epsilon_max_m"],
        "cycle_over_operator": ratio <= GOALS["cycle_over_operator_max"],
        "within_limits": exact,
    }
    return {
        "rig": rig.name,
        "demos": demos,
        "seed": seed,
        "passes": passes,
        "samples": int(sum(r.t_s.shape[0] for r in records)),
        "demo_duration_s": {"min": float(durations.min()), "mean": op_mean,
                            "max": float(durations.max())},
        "operator_speed": {"min": float(min(d.params.speed for d in ds)),
                           "max": float(max(d.params.speed for d in ds))},
        "demonstrate_s": demo_s,
        "waypoints_ms": wp,
        "waypoints_cpu_ms": _pct(cpu),
        "reference": {
            "name": "the same pipeline aligned by uniform time scaling instead of DTW",
            "waypoints_ms": ref,
            "waypoints_cpu_ms": _pct(ref_cpu),
            "dtw_over_reference_p50": wp["p50"] / ref["p50"],
        },
        "waypoints": int(idx.size),
        "epsilon_m": eps,
        "frechet_intended_m": frechet,
        "frechet_goal_m": eps + GOALS["frechet_over_epsilon_max_m"],
        "mean_path_frechet_intended_m": mean_frechet,
        "linear_mean_path_frechet_intended_m": linear_frechet,
        "plan_s": plan_s,
        "operator_mean_cycle_s": op_mean,
        "cycle_s": cycle.duration_s,
        "cycle_over_operator": ratio,
        "cycles": cycles,
        "cycles_total_s": trench.total_s,
        "paper": {"zhao_trench_s": ZHAO_TRENCH_S, "zhao_cycles": ZHAO_CYCLES},
        "total_over_zhao": trench.total_s / ZHAO_TRENCH_S,
        "within_limits": {"exact": exact},
        "peaks": peaks,
        "goals": GOALS,
        "met": met,
        "load_average": list(os.getloadavg()),
    }


def add_parser(bench_sub: Any) -> argparse.ArgumentParser:
    """Add ``teach`` to the ``bench`` subparsers (the ``excavator_rt.bench`` entry point)."""
    p: argparse.ArgumentParser = bench_sub.add_parser(
        "teach",
        help="teach and plan on the simulated operator: time to waypoints, Frechet to the "
        "intended path, cycle time against the operator's, the trench against Zhao's 80.8 s",
    )
    p.add_argument("--demos", type=int, default=15, help="demonstrations (default 15)")
    p.add_argument("--seed", type=int, default=0, help="first operator seed")
    p.add_argument("--passes", type=int, default=None,
                   help="timed runs of demonstrations -> waypoints (default 10; 2 with --quick)")
    p.add_argument("--epsilon-mm", type=float, default=50.0, help="Douglas-Peucker tolerance")
    p.add_argument("--cycles", type=int, default=None,
                   help="trench cycles (default 7; 2 with --quick)")
    p.add_argument("--quick", action="store_true", help="small sizes (a first look, the tests)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Handler of ``excavator-rt bench teach``; 0 (goals are reported, not an exit status)."""
    from rt_runtime.errors import ConfigurationError

    passes = args.passes if args.passes is not None else (2 if args.quick else 10)
    cycles = args.cycles if args.cycles is not None else (2 if args.quick else 7)
    if not 1 <= args.demos <= 200 or not 1 <= passes <= 1000 or not 1 <= cycles <= 100:
        raise ConfigurationError(
            f"--demos {args.demos} --passes {passes} --cycles {cycles}: allowed 1..200 "
            "demonstrations, 1..1000 passes, 1..100 cycles"
        )
    if not (math.isfinite(args.epsilon_mm) and args.epsilon_mm > 0.0):
        raise ConfigurationError(f"--epsilon-mm {args.epsilon_mm}: allowed a number > 0")
    r = bench_teach(demos=args.demos, seed=args.seed, passes=passes,
                    epsilon_mm=args.epsilon_mm, cycles=cycles)
    r["sizes"] = "quick" if args.quick else "full"
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    wp, ref = r["waypoints_ms"], r["reference"]["waypoints_ms"]
    print(f"teach and plan (Zhao) on {r['rig']}: {r['demos']} operator demonstrations "
          f"({r['demo_duration_s']['min']:.1f}-{r['demo_duration_s']['max']:.1f} s, "
          f"{r['samples']} samples at 100 Hz; pace {r['operator_speed']['min']:.2f}-"
          f"{r['operator_speed']['max']:.2f})")
    print(f"  demonstrations -> waypoints: p50 {wp['p50']:.0f} ms, p99 {wp['p99']:.0f} ms "
          f"(goal p50 <= {GOALS['waypoints_ms_p50_max']:.0f} ms); CPU p50 "
          f"{r['waypoints_cpu_ms']['p50']:.0f} ms; uniform-time reference p50 {ref['p50']:.0f} "
          f"ms (DTW / reference {r['reference']['dtw_over_reference_p50']:.1f}); load "
          f"{r['load_average'][0]:.1f}")
    print(f"  {r['waypoints']} waypoints; Frechet planned vs intended "
          f"{r['frechet_intended_m'] * 1e3:.1f} mm (goal <= {r['frechet_goal_m'] * 1e3:.0f} mm); "
          f"mean path vs intended {r['mean_path_frechet_intended_m'] * 1e3:.1f} mm (uniform "
          f"time: {r['linear_mean_path_frechet_intended_m'] * 1e3:.1f} mm)")
    print(f"  taught cycle {r['cycle_s']:.2f} s = {r['cycle_over_operator']:.0%} of the "
          f"operator's mean {r['operator_mean_cycle_s']:.2f} s (goal <= 70 %)")
    print(f"  trench of {r['cycles']} cycles: {r['cycles_total_s']:.1f} s (Zhao: "
          f"{ZHAO_TRENCH_S} s for {ZHAO_CYCLES}); within every limit (exact): "
          f"{'yes' if r['within_limits']['exact'] else 'NO'}")
    print("  goals met: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in r["met"].items()))
    return 0
