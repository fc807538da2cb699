"""Command-line interface: ``excavator-rt <command> ...``.

Each command is a function taking parsed arguments and returning an exit code; every command
that reports numbers has ``--json`` (one JSON object on stdout). Degrees and millimetres appear
only here, at the edge; the library is SI.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any

import numpy as np

from rt_runtime import __version__
from rt_runtime.errors import ConfigurationError, ExcavatorRtError
from rt_runtime.rig import DEFAULT_RIG, Rig, load_rig, profile_names
from rt_runtime.service.config import PLANNERS

if TYPE_CHECKING:
    from rt_runtime.bench import LongTrenches, RandomSuite, TaskPlanBench, TrenchBench
    from rt_runtime.reports import Distribution

#: Entry-point group of the commands other packages add to ``excavator-rt`` (a callable taking
#: the sub-parsers): the HIL's ``hil`` and ``demo``.
COMMANDS_GROUP = "excavator_rt.commands"
#: Entry-point group of ``bench`` subcommands from outside the runtime; each entry point is
#: called with the ``bench`` subparsers.
BENCH_GROUP = "excavator_rt.bench"

Handler = Callable[[argparse.Namespace], int]


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, sort_keys=False))


def _deg(x: float) -> float:
    return round(math.degrees(x), 6)


def rig_summary(rig: Rig, samples: int = 200_000, seed: int = 0) -> dict[str, Any]:
    """A JSON-ready description of a rig: profile, reach envelope and cylinder stroke ranges."""
    from rt_runtime import actuation, workspace

    env = workspace.envelope(rig, samples=samples, seed=seed)
    lo = np.array([j.min_rad for j in rig.joints])
    hi = np.array([j.max_rad for j in rig.joints])
    s_lo = actuation.joint_to_stroke(rig, lo)
    s_hi = actuation.joint_to_stroke(rig, hi)
    s_min, s_max = actuation.stroke_limits(rig)
    cyl_kind = rig.cylinders.kind
    joints = [
        {
            "name": j.name,
            "min_deg": _deg(j.min_rad),
            "max_deg": _deg(j.max_rad),
            "velocity_max_deg_s": _deg(j.velocity_max_rad_s),
            "acceleration_max_deg_s2": _deg(j.acceleration_max_rad_s2),
            "jerk_max_deg_s3": _deg(j.jerk_max_rad_s3),
            "torque_max_nm": j.torque_max_nm,
        }
        for j in ((rig.swing.joint,) if rig.swing is not None else ()) + rig.joints
    ]
    links = [
        {
            "name": lk.name,
            "length_m": lk.length_m,
            "mass_kg": lk.mass_kg,
            "com_m": list(lk.com_m),
            "inertia_kgm2": lk.inertia_kgm2,
        }
        for lk in rig.links
    ]
    cylinders = [
        {
            "name": name,
            "kind": cyl_kind,
            "stroke_at_joint_min_mm": round(float(s_lo[i]) * 1e3, 3),
            "stroke_at_joint_max_mm": round(float(s_hi[i]) * 1e3, 3),
            "stroke_limits_mm": [round(float(s_min[i]) * 1e3, 3), round(float(s_max[i]) * 1e3, 3)],
        }
        for i, name in enumerate(("boom", "stick", "bucket"))
    ]
    out: dict[str, Any] = {
        "name": rig.name,
        "description": rig.description,
        "sources": list(rig.sources),
        "dof": rig.dof,
        "ground_y_m": rig.ground_y_m,
        "joints": joints,
        "links": links,
        "bucket": {
            "width_m": rig.bucket.width_m,
            "capacity_L": round(rig.bucket.capacity_m3 * 1e3, 6),
        },
        "envelope": {
            "max_height_m": env.max_height_m,
            "max_radius_m": env.max_radius_m,
            "max_reach_x_m": env.max_reach_x_m,
            "max_depth_m": env.max_depth_m,
            "max_depth_below_ground_m": env.max_depth_below_ground_m,
            "samples": env.samples,
            "seed": env.seed,
        },
        "cylinders": cylinders,
        "assumed": [{"key": k, "reason": r} for k, r in rig.assumed],
    }
    if rig.swing is not None:
        out["swing"] = {
            "base_offset_m": rig.swing.base_offset_m,
            "base_height_m": rig.swing.base_height_m,
        }
    return out


def _print_rig(summary: dict[str, Any]) -> None:
    print(f"rig {summary['name']}: {summary['description']}")
    for s in summary["sources"]:
        print(f"  source: {s}")
    print(f"  degrees of freedom: {summary['dof']}; ground at y = {summary['ground_y_m']:+.3f} m")
    print("  joint     range [deg]          vel [deg/s]  acc [deg/s2]  jerk [deg/s3]  torque [N m]")
    for j in summary["joints"]:
        print(
            f"  {j['name']:<8} [{j['min_deg']:8.2f}, {j['max_deg']:7.2f}]  {j['velocity_max_deg_s']:10.2f}"
            f"  {j['acceleration_max_deg_s2']:12.2f}  {j['jerk_max_deg_s3']:13.2f}  {j['torque_max_nm']:12.1f}"
        )
    print("  link      length [m]  mass [kg]  com [m]            inertia [kg m2]")
    for lk in summary["links"]:
        com = ", ".join(f"{c:.4f}" for c in lk["com_m"])
        print(
            f"  {lk['name']:<8} {lk['length_m']:10.4f} {lk['mass_kg']:10.3f}  ({com})  {lk['inertia_kgm2']:14.5f}"
        )
    b = summary["bucket"]
    print(f"  bucket: width {b['width_m']:.3f} m, struck capacity {b['capacity_L']:.2f} L")
    e = summary["envelope"]
    print(
        f"  reach envelope (Monte Carlo, {e['samples']} samples, seed {e['seed']}): "
        f"max height {e['max_height_m']:.3f} m, max radius {e['max_radius_m']:.3f} m, "
        f"max depth {e['max_depth_m']:.3f} m below the boom pin "
        f"({e['max_depth_below_ground_m']:.3f} m below ground)"
    )
    print("  cylinder  stroke at joint min..max [mm]   stroke limits [mm]")
    for c in summary["cylinders"]:
        print(
            f"  {c['name']:<8} {c['stroke_at_joint_min_mm']:10.2f} .. {c['stroke_at_joint_max_mm']:<10.2f}"
            f"        {c['stroke_limits_mm'][0]:.1f} .. {c['stroke_limits_mm'][1]:.1f} ({c['kind']})"
        )
    print(f"  assumed values ({len(summary['assumed'])}, no source gives them):")
    for a in summary["assumed"]:
        print(f"    {a['key']}: {a['reason']}")


def cmd_rig_show(args: argparse.Namespace) -> int:
    """``excavator-rt rig show NAME [--json]``."""
    rig = load_rig(args.name)
    summary = rig_summary(rig, samples=args.samples, seed=args.seed)
    table = kinematics_table(rig)
    if args.json:
        _print_json({**summary, "kinematics": table})
    else:
        _print_rig(summary)
        print()
        _print_kinematics(rig, table)
    return 0


def cmd_rig_list(args: argparse.Namespace) -> int:
    """``excavator-rt rig list``."""
    names = profile_names()
    if args.json:
        _print_json({"rigs": names, "default": DEFAULT_RIG})
    else:
        for n in names:
            mark = " (default)" if n == DEFAULT_RIG else ""
            print(f"{n}{mark}: {load_rig(n).description}")
    return 0


def kinematics_table(rig: Rig) -> list[dict[str, Any]]:
    """Tip pose, cylinder strokes and static gravity torques at representative poses.

    The poses are the joint-range midpoint and, per joint, that joint at its limits with the
    others at mid-range: the table a rig integrator checks against the machine with a tape.
    """
    from rt_runtime import actuation, dynamics, kinematics

    lo, hi = rig.q_min_rad, rig.q_max_rad
    mid = 0.5 * (lo + hi)
    poses = [("mid-range", mid)]
    for i, j in enumerate(rig.joints):
        for label, v in (("min", lo[i]), ("max", hi[i])):
            q = mid.copy()
            q[i] = v
            poses.append((f"{j.name} {label}", q))
    q_all = np.array([q for _, q in poses])
    tip = kinematics.forward(rig, q_all)
    stroke = actuation.joint_to_stroke(rig, q_all)
    tau_g = dynamics.gravity_torque(rig, q_all)
    rows = []
    for k, (label, q) in enumerate(poses):
        rows.append(
            {
                "pose": label,
                "q_deg": [_deg(v) for v in q],
                "tip_x_m": round(float(tip[k, 0]), 6),
                "tip_y_m": round(float(tip[k, 1]), 6),
                "attitude_deg": _deg(float(tip[k, 2])),
                "stroke_mm": [round(float(s) * 1e3, 3) for s in stroke[k]],
                "gravity_torque_nm": [round(float(t), 3) for t in tau_g[k]],
            }
        )
    return rows


def _print_kinematics(rig: Rig, table: list[dict[str, Any]]) -> None:
    """The kinematics table as text."""
    print(f"kinematics of {rig.name} (tip in the arm frame, strokes, static gravity torques)")
    print(
        "  pose          q [deg]                     tip x,y [m]       attitude [deg]  stroke [mm]               gravity torque [N m]"
    )
    for r in table:
        q = ", ".join(f"{v:7.2f}" for v in r["q_deg"])
        s = ", ".join(f"{v:7.1f}" for v in r["stroke_mm"])
        t = ", ".join(f"{v:9.2f}" for v in r["gravity_torque_nm"])
        print(
            f"  {r['pose']:<13} ({q})  ({r['tip_x_m']:6.3f}, {r['tip_y_m']:6.3f})  {r['attitude_deg']:10.2f}"
            f"      ({s})  ({t})"
        )


def cmd_oneshot(args: argparse.Namespace) -> int:
    """``excavator-rt oneshot``: plan one dig with the PSO teacher (or the DE reference)."""
    from rt_runtime.planning import oneshot

    rig = load_rig(args.rig)
    problem = oneshot.Problem(
        q_start_rad=tuple(math.radians(v) for v in args.start_deg),  # type: ignore[arg-type]
        q_end_rad=tuple(math.radians(v) for v in args.end_deg),  # type: ignore[arg-type]
        surface_y_m=args.surface_m,
        dig_type=oneshot.DigType[args.type.upper()],
    )
    if args.method == "de":
        sol = oneshot.solve_de(rig, problem, seed=args.seed)
    else:
        sol = oneshot.solve_pso(rig, [problem], seed=args.seed)[0]
    out = {
        "rig": rig.name,
        "type": args.type,
        "method": sol.method,
        "feasible": sol.feasible,
        "T_s": sol.T_s,
        "a6": list(sol.a6),
        "volume_L": sol.volume_m3 * 1e3,
        "energy_Wh": sol.energy_j / 3600.0,
        "theta_p_deg": math.degrees(sol.theta_p_rad),
        "objective": sol.objective,
        "margins": dict(sol.margins),
        "solve_s": sol.solve_s,
    }
    if args.json:
        _print_json(out)
    else:
        verdict = "feasible" if sol.feasible else "INFEASIBLE (do not execute)"
        print(f"{args.type} dig on {rig.name} by {sol.method}: {verdict}")
        print(
            f"  T = {sol.T_s:.3f} s, V_p = {out['volume_L']:.3f} L, W_E = {out['energy_Wh']:.4f} Wh, "
            f"theta_p = {out['theta_p_deg']:.2f} deg"
        )
        print(
            f"  objective (Yao eq 11) = {sol.objective:.4f}; a6 = "
            + ", ".join(f"{a:.4e}" for a in sol.a6)
            + " rad/s^6"
        )
        print(f"  solve time {sol.solve_s:.3f} s")
        print("  constraint margins (normalised, >= 0 holds):")
        for name, m in sol.margins:
            flag = "" if m >= 0 else "   <- violated"
            print(f"    {name:<22} {m:+.4f}{flag}")
    return 0 if sol.feasible else 1


def cmd_bench(args: argparse.Namespace) -> int:
    """``excavator-rt bench``: the full suite (planning latency, loop timing, CAN) in one run."""
    from rt_runtime.bench import (
        LOOP_LATENESS_P99_GOAL_US,
        YAO_PINN_PLAN_MS,
        YAO_PSO_SOLVE_S,
        BenchSizes,
        bench_full,
        plot_bench,
    )
    from rt_runtime.control import RtSettings

    rig = load_rig(args.rig)
    try:
        rates = tuple(float(r) for r in args.rates.split(",") if r.strip())
    except ValueError:
        raise ConfigurationError(
            f"--rates {args.rates!r}: allowed a comma-separated list of rates in Hz, e.g. 500,1000"
        ) from None
    if not rates or any(not 0 < r <= 10_000 for r in rates):
        raise ConfigurationError(f"--rates {args.rates!r}: every rate must be in (0, 10000] Hz")
    if args.seconds is not None and args.seconds <= 0:
        raise ConfigurationError(f"--seconds {args.seconds}: allowed a number of seconds > 0")
    sizes = BenchSizes.quick() if args.quick else BenchSizes()
    if args.seconds is not None:
        sizes = dataclasses.replace(sizes, loop_seconds=args.seconds)
    rt = (
        RtSettings(sched_fifo_priority=None, lock_memory=False, timer_slack_ns=None)
        if args.no_rt
        else RtSettings(cpu=args.cpu)
    )
    r, raw = bench_full(
        rig, sizes=sizes, rates_hz=rates, rt=rt, model_dir=args.models, hil_rig=args.rig
    )
    if args.plot:
        r = dataclasses.replace(r, plot=str(plot_bench(raw, args.plot)))
    if args.json:
        _print_json(r.to_json())
        return 0
    pinn, pso, ratios = r.pinn, r.pso, r.ratios
    print(f"excavator-rt bench on {rig.name} ({'quick' if args.quick else 'full'} sizes, {r.wall_s:.0f} s)")
    print(f"  PINN per dig: inference p50 {pinn.infer_us.p50:.1f} us, p99 {pinn.infer_us.p99:.1f} us; "
          f"plan (inference + verification) p50 {pinn.plan_us.p50:.1f} us, p99 {pinn.plan_us.p99:.1f} us, "
          f"max {pinn.plan_us.max:.0f} us  (Yao {YAO_PINN_PLAN_MS[0]}-{YAO_PINN_PLAN_MS[1]} ms)")
    print(f"  PSO per dig (same problems): p50 {pso.solve_s.p50:.3f} s  (Yao {YAO_PSO_SOLVE_S[0]:.0f}-"
          f"{YAO_PSO_SOLVE_S[1]:.0f} s); PSO / PINN plan = {ratios['pso_over_pinn_plan']:.0f}x "
          f"(Yao's own ratio {ratios['yao_pso_over_yao_pinn']:.0f}x)")
    print(f"  trench task A, whole plan ({r.trench.digs} digs): p50 {r.trench.plan_us.p50 / 1e3:.2f} ms")
    for rate, e in (r.loop or {}).items():
        lat, jit, rtt = e.lateness_us, e.jitter_us, e.sync_rtt_us
        refused = [i.item for i in e.rt.refused]
        if lat is not None and jit is not None:
            print(f"  loop {rate} Hz, {e.cycles} cycles: lateness p50 {lat.p50:.1f} / p99 {lat.p99:.1f} / "
                  f"p99.9 {lat.p999:.1f} / max {lat.max:.0f} us; |period jitter| p99 {jit.p99:.1f} us; "
                  f"overruns {e.overruns} (skipped {e.skipped})")
        if rtt is not None:
            print(f"      SYNC -> TPDO1 p50 {rtt.p50:.0f} / p99 {rtt.p99:.0f} / max {rtt.max:.0f} us, "
                  f"stale {e.stale_cycles}; bus load {e.bus_load.realistic:.1%} "
                  f"(nominal {e.bus_load.nominal:.1%}, worst {e.bus_load.worst:.1%})"
                  + (f"; RT refused: {', '.join(refused)}" if refused else ""))
    met = r.lateness_goal_met
    if met is not None:
        print(f"  goal 500 Hz lateness p99 <= {LOOP_LATENESS_P99_GOAL_US:.0f} us: {'met' if met else 'NOT met'}")
    if r.plot is not None:
        print(f"  histograms: {r.plot}")
    return 0


def cmd_bench_oneshot(args: argparse.Namespace) -> int:
    """``excavator-rt bench oneshot``: PSO solve time and quality against DE."""
    from rt_runtime.bench import YAO_MEAN_OBJECTIVE, bench_oneshot

    rig = load_rig(args.rig)
    r = bench_oneshot(
        rig, n_problems=args.problems, seed=args.seed, de=not args.no_de, workers=args.workers
    )
    if args.json:
        _print_json(r.to_json())
        return 0
    print(
        f"one-shot PSO on {rig.name}: {r.problems} seeded problems (half downward, half backward)"
    )
    print(
        f"  solve time single: p50 {r.solve_s.p50:.3f} s, p99 {r.solve_s.p99:.3f} s "
        f"(goal p50 <= 0.3 s; Yao's PSO 69-71 s: {r.speedup_vs_yao_pso:.0f}x faster)"
    )
    print(f"  batched: {r.batch_problems_per_s:.1f} problems/s over {r.batch_workers} processes (goal >= 20)")
    print(f"  feasible: {r.feasible:.0%} single, {r.batch_feasible:.0%} batched")
    if r.de is not None:
        print(
            f"  DE reference: p50 {r.de.de_solve_s.p50:.2f} s per problem; PSO within 1 % of DE "
            f"on {r.de.within_1pct_of_de:.0%} (goal >= 95 %); gap p50 {r.de.gap_to_de.p50:+.2%}, "
            f"max {r.de.gap_to_de.max:+.2%}"
        )
    for kind, v in r.results.items():
        print(
            f"  {kind:<8} T {v.T_s[0]:.2f}..{v.T_s[1]:.2f} s, V_p {v.volume_L[0]:.2f}..{v.volume_L[1]:.2f} L, "
            f"W_E {v.energy_Wh[0]:.4f}..{v.energy_Wh[1]:.4f} Wh, mean objective {v.objective_mean:.3f} "
            f"(Yao {YAO_MEAN_OBJECTIVE[kind]:.3f})"
        )
    return 0


def cmd_bench_pinn(args: argparse.Namespace) -> int:
    """``excavator-rt bench pinn``: the shipped PINN on its held-out sets against the teacher."""
    from rt_runtime.bench import PINN_GOALS, YAO_TABLE4_MEAN, bench_pinn

    rig = load_rig(args.rig)
    r = bench_pinn(
        rig, args.models, limit=args.limit, passes=args.passes, pso_problems=args.pso_problems
    )
    if args.json:
        _print_json(r.to_json())
        return 0
    g = PINN_GOALS
    print(f"PINN planner on {rig.name}: {r.samples} held-out problems (verifier: {r.verifier})")
    print(f"  objective gap to PSO: mean {r.gap_mean:+.2%}, max {r.gap_max:+.2%} (goal mean <= {g['gap_mean_max']:.0%}; Yao about 5 %)")
    print(f"  raw network answers: gap mean {r.raw_gap_mean:+.2%}, feasible {r.raw_feasible:.1%} (goal >= {g['raw_feasible_min']:.0%})")
    print(f"  plans returned (verified) {r.verified_feasible:.1%}, refused {r.refused:.1%}; returned plans feasible by the numpy reference: {r.executed_feasible:.1%}")
    if r.paths:
        print("  paths: " + ", ".join(f"{k} {v}" for k, v in r.paths.items()))
    print(f"  inference: p50 {r.infer_us.p50:.1f} us, p99 {r.infer_us.p99:.1f} us")
    print(f"  plan (inference + fill + retime + verification): p50 {r.plan_us.p50:.1f} us, p99 {r.plan_us.p99:.1f} us (goals {g['plan_us_p50_max']:.0f} / {g['plan_us_p99_max']:.0f} us; Yao 4.2-4.5 ms)")
    if r.verify_only_plan_us is not None:
        v = r.verify_only_plan_us
        print(f"  plan without fill and retime (inference + verification of the raw answer): p50 {v.p50:.1f} us, p99 {v.p99:.1f} us")
    print(f"  PSO teacher in the same run: p50 {r.pso_solve_s.p50:.3f} s per dig ({r.speedup_vs_pso:.0f}x slower than the PINN plan)")
    print("  Table 4 form (means):          T [s]   V_p [L]  W_E [Wh]  planning")
    for kind, t in r.table4.items():
        pso_s = t.pso.plan_s if t.pso.plan_s is not None else float("nan")
        pinn_ms = t.pinn.plan_ms if t.pinn.plan_ms is not None else float("nan")
        print(f"    {kind:<8} PSO               {t.pso.T_s:6.2f}  {t.pso.volume_L:7.2f}  {t.pso.energy_Wh:8.4f}  {pso_s:.3f} s")
        print(f"    {kind:<8} PINN              {t.pinn.T_s:6.2f}  {t.pinn.volume_L:7.2f}  {t.pinn.energy_Wh:8.4f}  {pinn_ms * 1e3:.1f} us")
    y = YAO_TABLE4_MEAN
    print(f"    Yao (A-D)  PSO               {y['pso']['T_s']:6.2f}  {y['pso']['volume_L']:7.2f}  {y['pso']['energy_Wh']:8.4f}  69-71 s")
    print(f"    Yao (A-D)  PINN              {y['pinn']['T_s']:6.2f}  {y['pinn']['volume_L']:7.2f}  {y['pinn']['energy_Wh']:8.4f}  4.2-4.5 ms")
    return 0


def _types(choice: str) -> list[str]:
    return ["downward", "backward"] if choice == "both" else [choice]


def cmd_train(args: argparse.Namespace) -> int:
    """``excavator-rt train``: physics-informed training of the planner networks."""
    from pathlib import Path

    from rt_runtime.planning.oneshot import DigType
    from rt_runtime.training.train import TrainConfig, plot_losses, save_checkpoint, train

    rig = load_rig(args.rig)
    out = Path(args.out)
    report: dict[str, Any] = {"rig": rig.name, "types": {}}
    for kind in _types(args.type):
        cfg = TrainConfig(
            hidden=tuple(args.hidden or ()),
            epochs=args.epochs,
            batch_size=args.batch_size,
            lr=args.lr,
            margin=args.margin,
            seed=args.seed,
            lambda_c=args.lambda_c,
            lambda_d=args.lambda_d,
            dir_infeasible_slope=args.dir_infeasible_slope,
            ema_decay=args.ema_decay,
            target_feasible=args.target_feasible,
            patience_evals=args.patience_evals,
            init_checkpoint=str(Path(args.init_from) / f"pinn_{kind}.pt") if args.init_from else "",
        )
        log = None if args.json or args.quiet else (lambda line: print(f"  {line}", file=sys.stderr))
        res = train(
            rig,
            Path(args.data) / f"{kind}.npz",
            DigType[kind.upper()],
            cfg,
            progress=not (args.json or args.quiet),
            log=log,
        )
        ckpt = out / f"pinn_{kind}.pt"
        save_checkpoint(res, ckpt)
        png = out / f"pinn_{kind}_losses.png"
        plot_losses(res.history, png, f"PINN training, {kind} digs ({rig.name})")
        report["types"][kind] = {
            "checkpoint": str(ckpt),
            "plot": str(png),
            "hidden": list(res.hidden),
            "epochs_run": res.epochs_run,
            "best_epoch": res.best_epoch,
            "stop_reason": res.stop_reason,
            "val_feasible": res.val_feasible,
            "val_gap_mean": res.val_gap_mean,
            "train_s": res.train_s,
        }
    if args.json:
        _print_json(report)
        return 0
    for kind, r in report["types"].items():
        print(
            f"{kind}: {r['epochs_run']} epochs ({r['stop_reason']}), best at {r['best_epoch']}: "
            f"validation feasible {r['val_feasible']:.1%}, gap to PSO {r['val_gap_mean']:+.2%}; "
            f"{r['train_s']:.0f} s; {r['checkpoint']}, {r['plot']}"
        )
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """``excavator-rt export``: ONNX models with their cards and held-out sets."""
    from pathlib import Path

    from rt_runtime.training.export import export, record_planned_heldout

    out = Path(args.out)
    report: dict[str, Any] = {"types": {}}
    for kind in _types(args.type):
        data = Path(args.data) / f"{kind}.npz" if args.data else None
        model = out / f"pinn_{kind}.onnx"
        card = export(
            Path(args.checkpoints) / f"pinn_{kind}.pt",
            model,
            dataset_path=data,
            library=args.library,
            library_keep_scale=args.library_keep_scale,
        )
        held = out / card["heldout_file"]["name"]
        report["types"][kind] = {
            "model": str(model),
            "card": str(model.with_suffix(".json")),
            "heldout": str(held),
            "parity_max_rel": card["parity_max_rel"],
            **{k: card["heldout"][k] for k in ("samples", "raw_feasible", "gap_mean", "gap_max")},
        }
    if (out / "pinn_downward.json").is_file() and (out / "pinn_backward.json").is_file():
        rig = load_rig(json.loads((out / "pinn_downward.json").read_text())["rig"])
        for kind, block in record_planned_heldout(rig, out).items():
            report["types"].setdefault(kind, {})["planned"] = block
    if args.json:
        _print_json(report)
        return 0
    for kind, r in report["types"].items():
        if "model" not in r:
            continue
        print(
            f"{kind}: {r['model']} (+ card, held-out set); parity with torch {r['parity_max_rel']:.2g}; "
            f"held-out {r['samples']}: raw feasible {r['raw_feasible']:.1%}, gap mean "
            f"{r['gap_mean']:+.2%}, max {r['gap_max']:+.2%}"
        )
        if "planned" in r:
            p = r["planned"]
            print(
                f"  planned by the runtime: returned {p['returned']:.1%}, refused {p['refused']:.1%}, "
                f"gap mean {p['gap_mean']:+.2%}, max {p['gap_max']:+.2%}"
            )
    return 0


def _triples(items: Sequence[str], flag: str) -> list[tuple[float, float, float]]:
    out = []
    for it in items:
        parts = it.split(",")
        try:
            vals = tuple(float(p) for p in parts)
        except ValueError:
            vals = ()
        if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
            raise ConfigurationError(f"{flag} takes a,b,c triples of finite numbers; got {it!r}")
        out.append((vals[0], vals[1], vals[2]))
    return out


def cmd_interp(args: argparse.Namespace) -> int:
    """``excavator-rt interp``: mixed-order interpolation through key points (Gao/Yang)."""
    from rt_runtime import actuation, kinematics
    from rt_runtime.trajectory import mixed_order

    rig = load_rig(args.rig)
    if args.points:
        pts = np.array(_triples(args.points, "--points"))
        q_key = kinematics.inverse(rig, pts[:, 0], pts[:, 1], np.radians(pts[:, 2]))
    else:
        q_key = np.radians(_triples(args.joints_deg, "--joints-deg") if args.joints_deg else mixed_order.GAO_TABLE2_JOINTS_DEG)
    n_seg = len(q_key) - 1
    durations = args.durations or [3.0] * n_seg
    if len(durations) != n_seg:
        raise ConfigurationError(f"--durations needs {n_seg} values (one per segment); got {len(durations)}")
    times = np.concatenate([[0.0], np.cumsum(durations)])
    strategies = mixed_order.PAPER_STRATEGIES if args.orders == "auto" else (args.orders,)
    cmp = mixed_order.compare_strategies(times, q_key, strategies)
    if not cmp.results:
        raise ConfigurationError(
            "no order pattern applies: " + "; ".join(f"{n}: {why}" for n, why in cmp.skipped)
        )
    best = mixed_order.choose_smoothest(cmp) if args.orders == "auto" else cmp.results[0]
    traj = best.trajectory
    t = np.linspace(0.0, traj.duration_s, 1201)
    q = traj.sample(t)
    qd = traj.sample(t, 1)
    stroke = actuation.joint_to_stroke(rig, q)
    sd = actuation.stroke_velocity(rig, q, qd)
    names = [j.name for j in rig.joints]
    deg = 180.0 / math.pi
    out = {
        "rig": rig.name,
        "knots_s": times.tolist(),
        "key_points_deg": (q_key * deg).round(6).tolist(),
        "chosen": best.name,
        "rule": "smallest worst-joint peak jerk relative to the best strategy per joint; ties by acceleration",
        "strategies": {
            r.name: {
                "peak_velocity_deg_s": dict(zip(names, (r.peak_velocity * deg).tolist(), strict=True)),
                "peak_acceleration_deg_s2": dict(zip(names, (r.peak_acceleration * deg).tolist(), strict=True)),
                "peak_jerk_deg_s3": dict(zip(names, (r.peak_jerk * deg).tolist(), strict=True)),
            }
            for r in cmp.results
        },
        "skipped": dict(cmp.skipped),
        "coefficients_deg": {
            name: [(traj.coefficients(seg, j) * deg).tolist() for seg in range(traj.n_segments)]
            for j, name in enumerate(names)
        },
        "stroke_mm": {
            name: {"min": float(stroke[:, j].min() * 1e3), "max": float(stroke[:, j].max() * 1e3),
                   "peak_velocity_mm_s": float(np.abs(sd[:, j]).max() * 1e3)}
            for j, name in enumerate(names)
        },
    }
    if args.plot:
        _plot_interp(args.plot, rig.name, best.name, t, q, qd, traj.sample(t, 2), stroke, names)
        out["plot"] = args.plot
    if args.json:
        _print_json(out)
        return 0
    print(f"mixed-order interpolation on {rig.name}: {len(q_key)} key points, segments {durations} s")
    for r in cmp.results:
        mark = "  <- chosen" if r.name == best.name else ""
        print(f"  {r.name:<12} peak |v| " + ", ".join(f"{v * deg:7.2f}" for v in r.peak_velocity)
              + " deg/s   |a| " + ", ".join(f"{v * deg:7.2f}" for v in r.peak_acceleration)
              + " deg/s2   |j| " + ", ".join(f"{v * deg:7.2f}" for v in r.peak_jerk) + f" deg/s3{mark}")
    for n, why in cmp.skipped:
        print(f"  {n:<12} skipped: {why}")
    print(f"  coefficients of {best.name} (deg, global time t in s, highest power first):")
    for j, name in enumerate(names):
        for seg in range(traj.n_segments):
            c = traj.coefficients(seg, j) * deg
            print(f"    {name:<7} segment {seg + 1}: " + " ".join(f"{v:+.6g}" for v in c))
    for name, v in out["stroke_mm"].items():
        print(f"  {name} cylinder: {v['min']:.1f} .. {v['max']:.1f} mm, peak {v['peak_velocity_mm_s']:.1f} mm/s")
    if args.plot:
        print(f"  plot: {args.plot}")
    return 0


def _plot_interp(path: str, rig: str, name: str, t, q, qd, qdd, stroke, names) -> None:  # type: ignore[no-untyped-def]
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:
        raise ConfigurationError("--plot needs matplotlib: pip install 'excavator-rt[plot]'") from e
    deg = 180.0 / math.pi
    fig, axes = plt.subplots(4, 1, figsize=(8, 10), sharex=True)
    for data, ax, label in ((q * deg, axes[0], "angle [deg]"), (qd * deg, axes[1], "velocity [deg/s]"),
                            (qdd * deg, axes[2], "acceleration [deg/s2]"), (stroke * 1e3, axes[3], "stroke [mm]")):
        for j, n in enumerate(names):
            ax.plot(t, data[:, j], label=n)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].legend()
    axes[0].set_title(f"{name} interpolation on {rig} (Gao Fig. 8-10)")
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _timejerk_waypoints(rig: Rig, items: Sequence[str]) -> np.ndarray:
    """``--waypoints-deg`` of ``timejerk`` as ``(n, rig.dof)`` radians, checked against the rig.

    Raises:
        ConfigurationError: Fewer than two waypoints, a wrong number of values, a value that is
            not a finite number, a waypoint outside a joint's range or out of the cylinders'
            reach; the message names the waypoint (1-based), the joint and what is allowed.
    """
    from rt_runtime import actuation
    from rt_runtime.errors import KinematicsError

    joints = ((rig.swing.joint,) if rig.swing is not None else ()) + rig.joints
    names = [j.name for j in joints]
    form = ",".join({"swing": "SW", "boom": "B", "stick": "S", "bucket": "K"}[n] for n in names)
    if len(items) < 2:
        raise ConfigurationError(f"--waypoints-deg: at least two waypoints are needed; got {len(items)}")
    rows: list[np.ndarray] = []
    for k, item in enumerate(items, 1):
        parts = item.split(",")
        if len(parts) != len(joints):
            raise ConfigurationError(
                f"--waypoints-deg: waypoint {k} ({item!r}) has {len(parts)} values; rig {rig.name} has "
                f"{len(joints)} joints ({', '.join(names)}): give {form} in degrees"
            )
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise ConfigurationError(f"--waypoints-deg: waypoint {k} ({item!r}) must be {len(joints)} numbers in degrees") from None
        for name, v in zip(names, vals, strict=True):
            if not math.isfinite(v):
                raise ConfigurationError(f"--waypoints-deg: waypoint {k}: {name} is {v}; angles must be finite numbers in degrees")
        for j, v in zip(joints, vals, strict=True):
            lo, hi = math.degrees(j.min_rad), math.degrees(j.max_rad)
            if not lo <= v <= hi:
                raise ConfigurationError(
                    f"--waypoints-deg: waypoint {k}: {j.name} at {v:g} deg is outside its range; allowed [{lo:g}, {hi:g}] deg on {rig.name}"
                )
        if rows and np.array_equal(np.radians(vals), rows[-1]):
            raise ConfigurationError(f"--waypoints-deg: waypoints {k - 1} and {k} are the same pose; consecutive waypoints must differ (remove one)")
        rows.append(np.radians(vals))
    q = np.array(rows)
    arm = q[:, -3:]
    try:
        actuation.joint_to_stroke(rig, arm)
    except KinematicsError as e:
        raise ConfigurationError(f"--waypoints-deg: a waypoint is out of the cylinders' reach: {e}") from None
    return q


def _weight(value: float, flag: str, *, positive: bool) -> float:
    if not math.isfinite(value) or value < 0.0 or (positive and value == 0.0):
        allowed = "a finite number > 0" if positive else "a finite number >= 0"
        why = " (with no weight on time the jerk integral falls without bound as T grows)" if positive and value == 0.0 else ""
        raise ConfigurationError(f"{flag} {value:g}: allowed {allowed}{why}")
    return value


def cmd_timejerk(args: argparse.Namespace) -> int:
    """``excavator-rt timejerk``: a minimum time-jerk trajectory through waypoints (Zhao eq 3)."""
    from rt_runtime.trajectory.timejerk import TimeJerkProblem, plan

    rig = load_rig(args.rig)
    q = _timejerk_waypoints(rig, args.waypoints_deg)
    w_jerk = _weight(args.w_jerk, "--w-jerk", positive=False)
    w_time = _weight(args.w_time, "--w-time", positive=True)
    problem = TimeJerkProblem.for_rig(rig, q, w_jerk=w_jerk, w_time=w_time)
    traj = plan(problem)
    exact = traj.limit_check()
    sampled = traj.sampled_limit_check(1000.0)
    names = list(rig.joint_names)
    waypoint_knots = problem.waypoint_knots
    deg = 180.0 / math.pi

    def knot(k: int) -> str:
        return f"waypoint {waypoint_knots.index(k) + 1}" if k in waypoint_knots else "free knot"

    out: dict[str, Any] = {
        "rig": rig.name,
        "joints": names,
        "waypoints_deg": (q * deg).round(9).tolist(),
        "w_jerk": w_jerk,
        "w_time": w_time,
        "T_s": traj.duration_s,
        "jerk_integral_rad2_s5": traj.jerk_integral,
        "objective": traj.objective,
        "iterations": traj.iterations,
        "waypoint_times_s": traj.waypoint_times_s.tolist(),
        "segments": [
            {
                "from": knot(i),
                "to": knot(i + 1),
                "start_s": float(traj.knots_s[i]),
                "duration_s": float(traj.piece_durations_s[i]),
                "coefficients": traj.coefficients[i].tolist(),
            }
            for i in range(traj.n_pieces)
        ],
        "peaks": {
            name: {
                "velocity_ratio": float(exact.velocity_ratio[j]),
                "acceleration_ratio": float(exact.acceleration_ratio[j]),
                "velocity_deg_s": float(exact.velocity_peak_rad_s[j] * deg),
                "acceleration_deg_s2": float(exact.acceleration_peak_rad_s2[j] * deg),
                "range_deg": [float(exact.position_low_rad[j] * deg), float(exact.position_high_rad[j] * deg)],
            }
            for j, name in enumerate(names)
        },
        "within_limits": {"exact": exact.within_limits, "resample_1khz": sampled.within_limits},
        "coefficients_rule": "per segment one list per joint: rad, highest power first, time in s from the segment's start",
    }
    if args.plot:
        _plot_timejerk(args.plot, traj, names, rig.name)
        out["plot"] = args.plot
    if args.json:
        _print_json(out)
        return 0
    print(f"minimum time-jerk trajectory on {rig.name} (Zhao eq 3): {len(q)} waypoints, joints {', '.join(names)}; w_jerk {w_jerk:g}, w_time {w_time:g}")
    print("  segment  from -> to                    duration [s]")
    for i, seg in enumerate(out["segments"], 1):
        print(f"  {i:7d}  {seg['from']:<12} -> {seg['to']:<12}  {seg['duration_s']:12.4f}")
    print(f"  T = {traj.duration_s:.4f} s; jerk integral {traj.jerk_integral:.6g} rad^2/s^5; objective {traj.objective:.6g}; {traj.iterations} iterations")
    print("  joint     peak |v| / V   peak |a| / A   range reached [deg]")
    for name, pk in out["peaks"].items():
        lo, hi = pk["range_deg"]
        print(f"  {name:<8} {pk['velocity_ratio']:13.6f}  {pk['acceleration_ratio']:13.6f}   [{lo:.3f}, {hi:.3f}]")
    print(f"  within every limit: exact check {'yes' if exact.within_limits else 'NO'}, 1 kHz resample {'yes' if sampled.within_limits else 'NO'}")
    if args.plot:
        print(f"  plot: {args.plot}")
    return 0


def _plot_timejerk(path: str, traj: Any, names: list[str], rig: str) -> None:
    """Angles, velocity over V and acceleration over A against time, waypoints marked."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:
        raise ConfigurationError("--plot needs matplotlib: pip install 'excavator-rt[plot]'") from e
    p = traj.problem
    t = np.linspace(0.0, traj.duration_s, 2001)
    rows = (
        (np.degrees(traj.sample(t, 0)), "angle [deg]"),
        (traj.sample(t, 1) / p.velocity_max_rad_s, "velocity / V"),
        (traj.sample(t, 2) / p.acceleration_max_rad_s2, "acceleration / A"),
    )
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for (data, label), ax in zip(rows, axes, strict=True):
        for j, n in enumerate(names):
            ax.plot(t, data[:, j], label=n)
        for tw in traj.waypoint_times_s:
            ax.axvline(tw, color="k", lw=0.5, alpha=0.4)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    for ax in axes[1:]:
        ax.axhline(1.0, color="r", lw=0.8, ls="--")
        ax.axhline(-1.0, color="r", lw=0.8, ls="--")
    axes[0].legend()
    axes[0].set_title(f"minimum time-jerk trajectory on {rig}: T {traj.duration_s:.3f} s (waypoints: vertical lines)")
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def cmd_bench_timejerk(args: argparse.Namespace) -> int:
    """``excavator-rt bench timejerk``: the generator against CasADi/IPOPT and toppra."""
    from rt_runtime.bench_timejerk import bench_timejerk

    n = args.problems if args.problems is not None else (8 if args.quick else 200)
    n_way = args.waypoints if args.waypoints is not None else (5 if args.quick else 10)
    if n < 1 or n_way < 2:
        raise ConfigurationError(f"--problems {n} --waypoints {n_way}: allowed >= 1 problem and >= 2 waypoints")
    reference = not args.no_reference
    if reference:
        try:
            import casadi  # noqa: F401
            import toppra  # noqa: F401
        except ImportError:
            raise ConfigurationError(
                "bench timejerk's references need casadi and toppra: pip install 'excavator-rt[reference]' (or pass --no-reference)"
            ) from None
    r = bench_timejerk(n, args.seed, n_way, reference=reference)
    r["sizes"] = "quick" if args.quick else "full"
    if args.json:
        _print_json(r)
        return 0
    sm = r["solve_ms"]
    print(f"minimum time-jerk generator (Zhao eq 3): {r['problems']} seeded problems, {r['waypoints']} waypoints, every rig (seed {r['seed']})")
    if sm:
        print(f"  solve p50 {sm['p50']:.1f} ms, p99 {sm['p99']:.1f} ms, max {sm['max']:.1f} ms (goals {r['goals']['solve_ms_p50_max']:.0f} / {r['goals']['solve_ms_p99_max']:.0f} ms)")
        for j, v in r["solve_ms_by_joints"].items():
            print(f"    {j} joints: p50 {v['p50']:.1f} ms, p99 {v['p99']:.1f} ms")
        cpu = r["solve_cpu_ms"]
        print(f"    process CPU time p50 {cpu['p50']:.1f} ms, p99 {cpu['p99']:.1f} ms (load average {r['load_average'][0]:.2f})")
    print(f"  feasible {r['feasible']:.1%} (exact check and 1 kHz resample; goal >= 99 %); largest ratio exact {r['exact_ratio_max']:.12f}, resampled {r['sampled_ratio_max']:.12f}")
    for f in r["failures"]:
        print(f"    problem {f['problem']} ({f['rig']}): {f['error']}")
    g = r["gap_to_reference"]
    if g is not None:
        ref = r["reference"]
        print(f"  objective gap to CasADi/IPOPT (full NLP): p50 {g['p50']:+.2e}, max {g['max']:+.2e}, min {g['min']:+.2e} (goal <= 1e-3) on {ref['solved']} problems; {len(ref['failed'])} reference failures")
        if ref["solve_ms"]:
            print(f"  IPOPT in the same run: p50 {ref['solve_ms']['p50']:.1f} ms ({ref['reference_over_ours_solve_p50']:.1f}x ours)")
    t = r["t_over_toppra"]
    if t is not None:
        print(f"  T over toppra's feasible time-optimal T of the same path: p50 {t['p50']:.3f}, max {t['max']:.3f}, min {t['min']:.3f}; toppra slow-down to feasibility p50 {r['toppra']['slowdown']['p50']:.4f}")
    return 0


def cmd_bench_inputs(args: argparse.Namespace) -> int:
    """``excavator-rt bench inputs``: property-based inputs into every entry point; exit 1 on
    any traceback."""
    try:
        from rt_runtime.inputs_fuzz import bench_inputs
    except ImportError as exc:
        if exc.name != "hypothesis":
            raise
        raise ConfigurationError(
            "bench inputs needs hypothesis: pip install hypothesis (or 'excavator-rt[test]')"
        ) from exc
    if args.examples < 1:
        raise ConfigurationError(f"--examples {args.examples}; allowed: an integer >= 1")

    def progress(e: Any) -> None:
        if not args.json:
            first = f"  first: {e.first_traceback[:160]}" if e.tracebacks else ""
            print(f"{e.name:<16} {e.examples:>7} {e.refused:>8} {e.accepted:>8} {e.tracebacks:>10} {e.wall_s:>8.1f}{first}", flush=True)

    if not args.json:
        print(f"excavator-rt bench inputs: {args.examples} examples per entry point, seed {args.seed}")
        print(f"{'entry point':<16} {'examples':>7} {'refused':>8} {'accepted':>8} {'tracebacks':>10} {'wall s':>8}")
    r = bench_inputs(args.examples, args.seed, progress=progress)
    if args.json:
        _print_json(r.to_json())
    else:
        print(f"tracebacks: {r.tracebacks} (goal 0); {r.wall_s:.0f} s")
    return 1 if r.tracebacks else 0


def cmd_plan(args: argparse.Namespace) -> int:
    """``excavator-rt plan``: a trench task planned dig by dig.

    Exit 0 when the plan is done, 1 when it is incomplete (the report is printed either way),
    2 on bad input (a task outside the domain is refused before anything is planned).
    """
    from rt_runtime.planning.trench import (
        COVERAGE_GOAL,
        OVERDIG_GOAL_M,
        PlanStatus,
        TrenchPlanner,
        load_task,
    )

    rig = load_rig(args.rig)
    task = load_task(args.task, rig)
    plan = TrenchPlanner(
        rig, args.planner, model_dir=args.models, screening=args.screening, soil=args.soil
    ).plan(task)
    code = 0 if plan.status is PlanStatus.DONE else 1
    report = plan.to_json()
    if args.plot:
        plot_trench(plan, args.plot)
        report["plot"] = args.plot
    if args.json:
        _print_json(report)
        return code
    t = report["task"]
    print(f"Trench task {t['name']} on {rig.name}: L {t['length_m']:.3g} m, D {t['depth_m']:.3g} m, beta1 {t['beta1_deg']:.0f} deg, beta2 {t['beta2_deg']:.0f} deg, far edge at x {t['start_x_m']:.3g} m ({args.planner}, {report['screening']} screening)")
    print(f"  {report['n_digs']} digs ({report['n_pieces']} pieces; + marks a piece joined to the one before it, the same bucket; ~ a piece the bucket is carried to, without a dump)")
    print("   #  type       T [s]  V real [L]  V_p [L]  W_E [Wh]  theta_p [deg]  over [mm]  plan [us]  how")
    for d in report["digs"]:
        mark = "~" if d["carried"] else "+" if d["joined"] else " "
        print(f"  {d['bucket'] + 1:2d}{mark} {d['type']:<9} {d['T_s']:6.2f}  {d['volume_L']:10.2f}  {d['predicted_volume_L']:7.2f}  {d['energy_Wh']:8.4f}  {d['theta_p_deg']:13.1f}  {d['overdig_mm']:9.1f}  {d['plan_us']:9.0f}  {d['status']}")
    yao = report.get("yao_fig14")
    yao_text = f"; Yao {yao['coverage_error']:.1%}" if yao else ""
    print(f"  coverage error {report['coverage_error']:.2%} (goal <= {COVERAGE_GOAL:.0%}{yao_text}), over-dig max {report['overdig_max_mm']:.1f} mm (goal <= {OVERDIG_GOAL_M * 1e3:g} mm)")
    print(f"  removed {report['removed_L']:.2f} L of a {report['design_L']:.2f} L design; dig time {report['dig_time_s']:.1f} s + transitions {report['transition_time_s']:.1f} s; energy {report['energy_Wh']:.3f} Wh")
    cycles = report["cycles"]
    if cycles:
        blended = sum(c["blended"] for c in cycles)
        over = max(c["moves_s"] / c["bound_s"] for c in cycles)
        print(f"  {len(cycles)} dig cycles, {report['moves_per_cycle_s']:.2f} s of moves a cycle ({blended} blended, {len(cycles) - blended} rest-to-rest); at most {over:.2f}x the bound of each joint stopping only where it reverses")
    print(f"  whole plan in {report['plan_total_us'] / 1e3:.1f} ms")
    if args.plot:
        print(f"  plot: {args.plot}")
    if code:
        print(f"  status: incomplete, {report['volume_left_L']:.2f} L of the design left: {report['reason']}")
    else:
        print("  status: done")
    return code


def plot_trench(plan: Any, path: str) -> None:
    """Yao Fig. 14 style: the design contour, each dig's tip path and the dug profile."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:
        raise ConfigurationError("--plot needs matplotlib: pip install 'excavator-rt[plot]'") from e
    fig, ax = plt.subplots(figsize=(9, 4.5))
    x, y = plan.design.exterior.xy
    ax.plot(x, y, "k--", lw=1.5, label="the task contour")
    for i, d in enumerate(plan.digs, 1):
        ax.plot(d.tip_path_m[:, 0], d.tip_path_m[:, 1], lw=1, label=f"trajectory #{i} ({d.dig_type.name.lower()}, {d.status})")
    s = plan.final_surface_m
    ax.plot(s[:, 0], s[:, 1], "k-", lw=2, label="dug profile")
    xf = plan.task.start_x_m
    ax.set_xlim(xf - plan.task.length_m - 0.1, xf + 0.1)
    ax.set_ylim(min(y) - 0.05, max(y) + 0.12)
    ax.set_aspect("equal")
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.set_title(f"Trenching task ({plan.task.name}): coverage error {plan.coverage_error:.2%}, over-dig {plan.overdig_max_m * 1e3:.1f} mm")
    ax.legend(fontsize=6, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def cmd_bench_plan(args: argparse.Namespace) -> int:
    """``excavator-rt bench plan``: tasks A-D planned with the PINN (timed) and the PSO; with
    ``--random N`` the random suite over the task domain (and the named tasks only if given)."""
    from rt_runtime.bench import PlanBenchReport, bench_plan, bench_plan_long, bench_plan_random

    rig = load_rig(args.rig)
    if args.random is not None and args.random < 1:
        raise ConfigurationError(f"--random {args.random}: allowed a number of tasks >= 1")
    alone = args.random or args.long
    spec = args.tasks if args.tasks is not None else ("" if alone else "A,B,C,D")
    tasks = tuple(t.strip() for t in spec.split(",") if t.strip())
    r = PlanBenchReport(rig.name)
    if tasks:
        r = bench_plan(rig, tasks, passes=args.passes, pso=not args.no_pso, model_dir=args.models)
    if args.random:
        r = dataclasses.replace(r, random=bench_plan_random(rig, args.random, args.seed, model_dir=args.models))
    if args.long:
        r = dataclasses.replace(r, long=bench_plan_long(rig, model_dir=args.models))
    if args.json:
        _print_json(r.to_json())
        return 0
    if r.tasks is not None and r.trench is not None:
        _print_bench_plan(r.tasks, r.trench, rig_name=rig.name, passes=args.passes)
    if r.random is not None:
        _print_bench_random(r.random)
    if r.long is not None:
        _print_bench_long(r.long)
    return 0


def _print_bench_long(q: LongTrenches) -> None:
    """The long trenches' summary as text."""
    print("Long trenches, section by section (walls 60/60 deg):")
    print("  trench  sections  travels  one-way  coverage  worst section  over-dig  digs  finishing/section  plan      per metre")
    for name, t in q.trenches.items():
        print(f"  {name:<6}  {t.sections:8d}  {t.travel_moves:7d}  {t.travel_one_way!s:>7}  {t.coverage_error:7.2%}  {t.section_coverage_max:12.2%}  {t.overdig_max_mm:5.2f} mm  {t.digs:4d}  {t.finishing_per_section_max:17d}  {t.plan_s:6.2f} s  {t.plan_s_per_m:.3f} s/m")


def _print_bench_random(q: RandomSuite) -> None:
    """The random suite's summary as text."""
    print(f"Random suite on {q.rig}: {q.tasks} tasks, seed {q.seed} (PINN planner)")
    if q.errors:
        first_error = q.error_tasks[0]
        print(f"  errors: {q.errors} (first: {first_error.name}: {first_error.error})")
    c, o, d, tp = q.coverage_error, q.overdig_max_mm, q.digs, q.transition_penetration_max_mm
    if c is None or o is None or d is None or tp is None or q.plan_ms is None:
        return
    print(f"  done {q.status_done:.0%}; coverage error within 2 % {q.within_2pct:.0%}, within 4 % {q.within_4pct:.0%}; p50 {c.p50:.2%}, p99 {c.p99:.2%}, max {c.max:.2%}")
    within_goal = "-" if q.sections_within_finishing_goal is None else f"{q.sections_within_finishing_goal:.0%}"
    print(f"  over-dig p50 {o.p50:.2f} mm, max {o.max:.2f} mm; digs p50 {d.p50:.0f}, max {d.max:.0f}; finishing passes per section max {q.finishing_per_section_max}, sections within the goal {within_goal}")
    f = q.fill
    if f.n:
        print(f"  roughing fill {f.min:.2f} / {f.p50:.2f} / {f.max:.2f} L (min / p50 / max), {f.within_band:.0%} of {f.n} digs within {f.band_L[0]:.2f}-{f.band_L[1]:.2f} L")
    print(f"  transitions into the material p50 {tp.p50:.1f} mm, max {tp.max:.1f} mm")
    cy = q.cycles
    if cy is not None and cy.cycles and cy.moves_vs_bound_mean is not None and cy.moves_vs_bound_max is not None:
        print(f"  {cy.cycles} dig cycles, {cy.moves_per_cycle_s:.2f} s of moves a cycle; moves / bound mean {cy.moves_vs_bound_mean:.3f}, max {cy.moves_vs_bound_max:.3f}; {cy.fallbacks} rest-to-rest")
    ref = q.reference
    ref_text = f"; PINN plan of one dig p50 {ref.pinn_plan_ms.p50:.2f} ms, plan per dig / PINN plan {q.plan_per_dig_over_pinn_plan:.1f}x" if ref is not None and q.plan_per_dig_over_pinn_plan is not None else ""
    per_dig = f"{q.plan_per_dig_ms.p50:.2f} ms" if q.plan_per_dig_ms is not None else "-"
    dig_part = q.dig_plan_per_dig_ms
    dig_text = f" (without the dig cycles {dig_part.p50:.2f} ms, p99 {dig_part.p99:.2f} ms)" if dig_part is not None else ""
    print(f"  plan per task p50 {q.plan_ms.p50:.1f} ms, p99 {q.plan_ms.p99:.1f} ms; per dig p50 {per_dig}{dig_text}{ref_text}")
    _print_each_dig(q.dig_plan_each_ms)
    print("  worst:  task              L [m]  D [m]  beta1  beta2  x [m]  coverage  over [mm]  digs  status")
    for w in q.worst:
        if w.planned is not None:
            wp = w.planned
            print(f"          {w.name:<16} {w.length_m:6.3f} {w.depth_m:6.3f} {w.beta1_deg:6.1f} {w.beta2_deg:6.1f} {w.start_x_m:6.3f}  {wp.coverage_error:7.2%}  {wp.overdig_max_mm:9.2f}  {wp.digs:4d}  {wp.status}")


def _print_bench_plan(
    tasks: Mapping[str, TaskPlanBench], tr: TrenchBench, *, rig_name: str, passes: int
) -> None:
    """The report of ``bench plan`` on named tasks as text."""
    from rt_runtime.bench import PLAN_PER_DIG_GOAL_MS, CycleFigures

    print(f"Trench planning on {rig_name} (Yao Table 3 tasks); PINN plan times over {passes} passes")
    print("  task  digs  coverage  Yao     over-dig  plan p50     plan p99     PSO plan   totals T / V / W_E vs PSO")
    for name, e in tasks.items():
        p = e.pinn
        yao = e.yao or {}
        vs = e.pinn_vs_pso
        cmp = " / ".join(_signed_pct(vs[k]) for k in ("T_s", "volume_L", "energy_Wh")) if vs else "-"
        pso_s = f"{e.pso.pso_plan_s:.0f} s" if e.pso is not None else "-"
        print(f"  {name:<4}  {len(p.digs):4d}  {p.coverage_error:7.2%}  {yao.get('coverage_error', float('nan')):5.1%}  {p.overdig_max_m * 1e3:6.1f} mm  {e.plan_us.p50 / 1e3:8.1f} ms  {e.plan_us.p99 / 1e3:8.1f} ms  {pso_s:>8}   {cmp}")
    if any(e.pso is not None for e in tasks.values()):
        print("  PINN vs PSO on the same dig problems (the PINN plan's roughing digs), totals T / V_p / W_E:")
        for name, e in tasks.items():
            if e.pso is not None:
                sp = e.pso.same_problems
                vs = sp.pinn_vs_pso
                cmp = " / ".join(_signed_pct(vs[k]) for k in ("T_s", "volume_L", "energy_Wh"))
                print(f"    {name:<4} {sp.pinn.digs:3.0f} digs  PINN {sp.pinn.T_s:.1f} s / {sp.pinn.volume_L:.2f} L / {sp.pinn.energy_Wh:.3f} Wh  PSO {sp.pso.T_s:.1f} s / {sp.pso.volume_L:.2f} L / {sp.pso.energy_Wh:.3f} Wh  ({cmp})")
    print("  where the whole plan's time goes (ms, medians): " + ", ".join(tasks[next(iter(tasks))].stage_us))
    for name, e in tasks.items():
        ref_ms = e.numpy_geometry_plan_us.p50 / 1e3
        print(f"    {name:<4} " + "  ".join(f"{v / 1e3:5.1f}" for v in e.stage_us.values()) + f"   (numpy geometry: {ref_ms:.1f} ms, {e.speedup_vs_numpy_geometry:.1f}x)")
    print(f"  whole plan, all tasks ({tr.geometry} geometry): p50 {tr.plan_us.p50 / 1e3:.1f} ms, p99 {tr.plan_us.p99 / 1e3:.1f} ms; numpy geometry p50 {tr.numpy_geometry_plan_us.p50 / 1e3:.1f} ms")
    ref = tr.reference
    ratio = f"; one PINN plan call p50 {ref.pinn_plan_ms.p50:.3f} ms, ratio {tr.plan_per_dig_over_pinn_plan:.0f}x" if ref is not None and tr.plan_per_dig_over_pinn_plan else ""
    pd = tr.plan_per_dig_ms
    if pd is not None:
        print(f"  planning per dig p50 {pd.p50:.1f} ms, p99 {pd.p99:.1f} ms (goal {PLAN_PER_DIG_GOAL_MS.p50:.0f} / {PLAN_PER_DIG_GOAL_MS.p99:.0f} ms){ratio}")
    dd = tr.dig_plan_per_dig_ms
    if dd is not None:
        print(f"  of it the dig's choice, plan and checks (without the dig cycles): p50 {dd.p50:.1f} ms, p99 {dd.p99:.1f} ms")
    _print_each_dig(tr.dig_plan_each_ms)
    print("  task  fill of each dig [L] (* finishing)                      finishing  travels  digs+moves  vs first design (goal <= 60 %)")
    for name, e in tasks.items():
        fills = " ".join(f"{v:.2f}{'*' if d[0].finishing else ''}" for v, d in zip(e.fill_L, e.pinn.buckets, strict=True))
        vs_first = e.task_time_vs_first_design
        print(f"  {name:<4}  {fills:<55} {e.finishing:9d}  {e.travel_moves:7d}  {e.task_time_s:8.1f} s  {'-' if vs_first is None else f'{vs_first:.0%}'}")
    print("  task  dig cycles  moves a cycle  moves / bound mean  max    rest-to-rest (goal: mean <= 1.10, max <= 1.20)")
    for name, e in tasks.items():
        cf = CycleFigures.of(e.pinn.to_json()["cycles"])
        if cf.cycles and cf.moves_per_cycle_s is not None and cf.moves_vs_bound_mean is not None and cf.moves_vs_bound_max is not None:
            print(f"  {name:<4}  {cf.cycles:10d}  {cf.moves_per_cycle_s:11.2f} s  {cf.moves_vs_bound_mean:18.3f}  {cf.moves_vs_bound_max:5.3f}  {cf.fallbacks:12d}")


def _print_each_dig(each: Distribution | None) -> None:
    """The line of each dig's own planning time over every dig (``dig_plan_each_ms``)."""
    if each is not None and each.max is not None:
        print(f"  each dig's choice, plan and checks over all digs: p50 {each.p50:.2f} ms, p99 {each.p99:.2f} ms, max {each.max:.1f} ms")


def _signed_pct(value: float | None) -> str:
    return "-" if value is None else f"{value:+.1%}"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    p = argparse.ArgumentParser(prog="excavator-rt", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"excavator-rt {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    rig = sub.add_parser("rig", help="rig profiles")
    rig_sub = rig.add_subparsers(dest="rig_command", required=True, metavar="SUBCOMMAND")
    show = rig_sub.add_parser("show", help="print a profile, its reach envelope and strokes")
    show.add_argument("name", help=f"profile name ({', '.join(profile_names())}) or a TOML path")
    show.add_argument("--samples", type=int, default=200_000, help="Monte Carlo samples")
    show.add_argument("--seed", type=int, default=0)
    show.add_argument("--json", action="store_true")
    show.set_defaults(handler=cmd_rig_show)
    lst = rig_sub.add_parser("list", help="list the shipped profiles")
    lst.add_argument("--json", action="store_true")
    lst.set_defaults(handler=cmd_rig_list)

    one = sub.add_parser("oneshot", help="plan one digging cycle (Yao 4.2) with the PSO teacher")
    one.add_argument("--rig", default=DEFAULT_RIG)
    one.add_argument("--type", choices=("downward", "backward"), required=True)
    one.add_argument(
        "--start-deg",
        type=float,
        nargs=3,
        required=True,
        metavar=("B", "S", "K"),
        help="entry pose: boom, stick, bucket [deg]",
    )
    one.add_argument(
        "--end-deg",
        type=float,
        nargs=3,
        required=True,
        metavar=("B", "S", "K"),
        help="exit pose: boom, stick, bucket [deg]",
    )
    one.add_argument(
        "--surface-m",
        type=float,
        required=True,
        help="material surface height H in the arm frame [m]",
    )
    one.add_argument("--method", choices=("pso", "de"), default="pso")
    one.add_argument("--seed", type=int, default=0)
    one.add_argument("--json", action="store_true")
    one.set_defaults(handler=cmd_oneshot)

    bench = sub.add_parser(
        "bench",
        help="benchmarks (distributions, against the papers); no subcommand: the full suite",
    )
    bench.add_argument("--rig", default=DEFAULT_RIG)
    bench.add_argument("--models", help="model directory (default: the shipped onnx/)")
    bench.add_argument("--seconds", type=float, help="loop run per rate [s] (default 10; 1 with --quick)")
    bench.add_argument("--rates", default="500,1000", help="loop rates in Hz, comma-separated")
    bench.add_argument("--plot", metavar="FILE.png", help="histograms of loop lateness and CAN round trip")
    bench.add_argument("--quick", action="store_true", help="tiny sizes (a first look, the tests)")
    bench.add_argument("--cpu", type=int, help="pin the loop's thread to this CPU")
    bench.add_argument("--no-rt", action="store_true", help="ask for no SCHED_FIFO, mlockall or timer slack")
    bench.add_argument("--json", action="store_true")
    bench.set_defaults(handler=cmd_bench)
    bench_sub = bench.add_subparsers(dest="bench_command", required=False, metavar="BENCHMARK")
    b1 = bench_sub.add_parser("oneshot", help="PSO solve time and quality against DE")
    b1.add_argument("--rig", default=DEFAULT_RIG)
    b1.add_argument("--problems", type=int, default=50)
    b1.add_argument("--seed", type=int, default=0)
    b1.add_argument("--no-de", action="store_true", help="skip the (slow) DE reference")
    b1.add_argument("--workers", type=int, default=2, help="processes for the batched solve")
    b1.add_argument("--json", action="store_true")
    b1.set_defaults(handler=cmd_bench_oneshot)

    from rt_runtime.training import dataset as _dataset

    _dataset.add_parser(sub)

    tr = sub.add_parser("train", help="physics-informed training of the PINN (needs the train extra)")
    tr.add_argument("--rig", default=DEFAULT_RIG)
    tr.add_argument("--data", default="data/pinn", help="dataset directory of `excavator-rt dataset`")
    tr.add_argument("--type", choices=("downward", "backward", "both"), default="both")
    tr.add_argument("--out", default="runs/train", help="directory for checkpoints and loss plots")
    tr.add_argument("--epochs", type=int, default=1500)
    tr.add_argument("--hidden", type=int, nargs="+", help="hidden widths (default: Yao's per type)")
    tr.add_argument("--batch-size", type=int, default=0, help="0: Yao's per type")
    tr.add_argument("--lr", type=float, default=2e-3)
    tr.add_argument("--margin", type=float, default=0.03, help="hinge margin of the constraint losses")
    tr.add_argument("--lambda-c", type=float, default=40.0, help="weight of the constraint losses (eq 19's lambda_C)")
    tr.add_argument("--lambda-d", type=float, default=10.0, help="weight of the direction loss (first-order gap of the runtime's plan; 0: off)")
    tr.add_argument("--dir-infeasible-slope", type=float, default=5.0, help="direction loss: least slope (per rad) of a tilt the runtime cannot plan")
    tr.add_argument("--ema-decay", type=float, default=0.995, help="moving average of the weights that is scored and kept (0: off)")
    tr.add_argument("--target-feasible", type=float, default=0.95, help="early stopping: raw and planned feasibility target on the validation split")
    tr.add_argument("--patience-evals", type=int, default=30, help="early stopping: scorings without improvement")
    tr.add_argument("--init-from", help="directory with pinn_<type>.pt checkpoints to start from (same depth, widths >= theirs)")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--quiet", action="store_true")
    tr.add_argument("--json", action="store_true")
    tr.set_defaults(handler=cmd_train)

    ex = sub.add_parser("export", help="export trained networks to ONNX with model cards")
    ex.add_argument("--checkpoints", default="runs/train", help="directory of `excavator-rt train`")
    ex.add_argument("--data", help="dataset directory (default: the path recorded at training)")
    ex.add_argument("--type", choices=("downward", "backward", "both"), default="both")
    ex.add_argument("--out", default="onnx")
    ex.add_argument(
        "--library",
        action="store_true",
        help="also write the solution library (the training split's teacher answers) that "
        "the runtime tries where the network's bulge is filled far up (pinn.py, step 4a)",
    )
    ex.add_argument(
        "--library-keep-scale",
        type=float,
        help="the library keeps the training problems whose network plan fills the bulge by "
        "this scale or more (default: export.LIBRARY_KEEP_BULGE_SCALE; 0: all of them)",
    )
    ex.add_argument("--json", action="store_true")
    ex.set_defaults(handler=cmd_export)

    b2 = bench_sub.add_parser("pinn", help="PINN planner on the held-out sets: gap, feasibility, latency")
    b2.add_argument("--rig", default=DEFAULT_RIG)
    b2.add_argument("--models", help="model directory (default: the shipped onnx/)")
    b2.add_argument("--limit", type=int, help="held-out problems per type (default: all)")
    b2.add_argument("--passes", type=int, default=5, help="timed passes over the problems")
    b2.add_argument("--pso-problems", type=int, default=10, help="problems per type the PSO solves for timing")
    b2.add_argument("--json", action="store_true")
    b2.set_defaults(handler=cmd_bench_pinn)

    ip = sub.add_parser("interp", help="mixed-order interpolation through key points (Gao/Yang)")
    ip.add_argument("--rig", default="test_bench")
    src = ip.add_mutually_exclusive_group()
    src.add_argument("--points", nargs="+", metavar="X,Y,ATT_DEG", help="Cartesian key points (IK)")
    src.add_argument("--joints-deg", nargs="+", metavar="B,S,K",
                     help="joint-space key points (default: Gao Table 2)")
    ip.add_argument("--orders", default="auto", help="e.g. 3-4-5-4-3, or auto (compare, choose smoothest)")
    ip.add_argument("--durations", type=float, nargs="+", help="segment durations [s] (default 3 each)")
    ip.add_argument("--plot", metavar="FILE.png")
    ip.add_argument("--json", action="store_true")
    ip.set_defaults(handler=cmd_interp)

    tj = sub.add_parser("timejerk", help="minimum time-jerk trajectory through waypoints (Zhao eq 3)")
    tj.add_argument("--rig", default=DEFAULT_RIG)
    tj.add_argument("--waypoints-deg", nargs="+", required=True, metavar="B,S,K",
                    help="joint angles of each waypoint in degrees (swing first on a rig with swing: SW,B,S,K)")
    tj.add_argument("--w-jerk", type=float, default=0.0, metavar="W1", help="weight of the jerk integral (default 0: minimum time, as Zhao's experiment)")
    tj.add_argument("--w-time", type=float, default=1.0, metavar="W2", help="weight of the total time (> 0)")
    tj.add_argument("--plot", metavar="FILE.png", help="angles, velocity / V, acceleration / A (needs the plot extra)")
    tj.add_argument("--json", action="store_true")
    tj.set_defaults(handler=cmd_timejerk)

    from rt_runtime.teach import command as _teach

    _teach.add_parser(sub)

    b4 = bench_sub.add_parser("timejerk", help="minimum time-jerk generator: solve time, feasibility, gap to CasADi/IPOPT, T over toppra")
    b4.add_argument("--problems", type=int, help="seeded random problems (default 200; 8 with --quick)")
    b4.add_argument("--waypoints", type=int, help="waypoints per problem (default 10; 5 with --quick)")
    b4.add_argument("--seed", type=int, default=0)
    b4.add_argument("--quick", action="store_true", help="small sizes (a first look, the tests)")
    b4.add_argument("--no-reference", action="store_true", help="skip CasADi/IPOPT and toppra (they need the reference extra)")
    b4.add_argument("--json", action="store_true")
    b4.set_defaults(handler=cmd_bench_timejerk)

    from rt_runtime.bench_mintorque import add_parsers as add_mintorque_parsers

    add_mintorque_parsers(sub, bench_sub)

    b5 = bench_sub.add_parser("inputs", help="property-based inputs (hypothesis) into every entry point: task files, rig profiles, daemon config, control requests, model cards, CAN frames")
    b5.add_argument("--examples", type=int, default=10_000, help="inputs per entry point (default 10000)")
    b5.add_argument("--seed", type=int, default=0, help="hypothesis seed")
    b5.add_argument("--json", action="store_true")
    b5.set_defaults(handler=cmd_bench_inputs)

    pl = sub.add_parser("plan", help="plan a trench task dig by dig (Yao Fig. 5, Table 3); exit 1 when the plan is incomplete")
    pl.add_argument("--task", required=True, help="A, B, C, D (Yao Table 3) or a TOML file")
    pl.add_argument("--rig", default=DEFAULT_RIG)
    pl.add_argument("--planner", choices=PLANNERS, default="pinn")
    pl.add_argument("--models", help="model directory (default: the shipped onnx/)")
    pl.add_argument(
        "--screening",
        choices=("auto", "network", "geometric"),
        default="auto",
        help="the rough stage's candidate bulges: the PINN's answers (network), a closed form per dig type needing no network (geometric), or auto (the network where its models load for the rig; pso and min_torque then plan without one)",
    )
    pl.add_argument("--soil", help="the min_torque planner's fluid soil, one of the rig's (Yang/Pan Table 2: soft, hard; default soft)")
    pl.add_argument("--plot", metavar="FILE.png", help="design contour, tip paths, dug profile (Yao Fig. 14)")
    pl.add_argument("--json", action="store_true")
    pl.set_defaults(handler=cmd_plan)

    b3 = bench_sub.add_parser("plan", help="whole-trench planning on tasks A-D: coverage, over-dig, time, PINN vs PSO")
    b3.add_argument("--rig", default=DEFAULT_RIG)
    b3.add_argument("--tasks", help="named tasks, comma-separated (default A,B,C,D; none with --random)")
    b3.add_argument("--random", type=int, metavar="N", help="the random suite: N seeded tasks over the whole task domain, PINN planner")
    b3.add_argument("--seed", type=int, default=0, help="seed of the random suite's tasks")
    b3.add_argument("--long", action="store_true", help="long trenches (3, 8 and 20 m) dug section by section, one-way travel, plan time per metre")
    b3.add_argument("--passes", type=int, default=3, help="timed PINN plans per task")
    b3.add_argument("--no-pso", action="store_true", help="skip the PSO plans (minutes)")
    b3.add_argument("--models", help="model directory (default: the shipped onnx/)")
    b3.add_argument("--json", action="store_true")
    b3.set_defaults(handler=cmd_bench_plan)

    # Commands from outside the runtime (the HIL's ``hil`` and ``demo``) register themselves
    # through entry points: rt_runtime never imports hil_sim.
    for ep in sorted(entry_points(group=COMMANDS_GROUP), key=lambda e: e.name):
        ep.load()(sub)
    # Benchmarks from outside the runtime (the HIL's ``bench hil``) likewise, as bench subcommands.
    for ep in sorted(entry_points(group=BENCH_GROUP), key=lambda e: e.name):
        ep.load()(bench_sub)

    from rt_runtime.service import client as job_client

    job_client.add_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``excavator-rt``; returns the exit code."""
    args = build_parser().parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except ExcavatorRtError as e:
        print(f"excavator-rt: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
