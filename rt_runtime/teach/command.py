"""``excavator-rt teach``: demonstrations in, the taught trench out (report, plots, taught job).

Role: the command's edge. Reads and validates every demonstration first (nothing is planned from
a set with one bad file), runs :func:`rt_runtime.teach.pipeline.teach`, prints the report (or
``--json``), writes ``DIR/taught.json`` with ``--out`` (the report, which is the taught job's
format: :mod:`rt_runtime.teach.taught`) and the figures with ``--plot DIR`` (Zhao Fig. 4-5).
Degrees and millimetres only here.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rt_runtime import kinematics
from rt_runtime.errors import ConfigurationError
from rt_runtime.fileio import atomic_write
from rt_runtime.rig import Rig, load_rig
from rt_runtime.teach import pipeline
from rt_runtime.teach.demos import DemoRecord, read_demo
from rt_runtime.teach.taught import TAUGHT_FILE, segments_json, taught_from_json

__all__ = ["ZHAO_CYCLES", "ZHAO_TRENCH_S", "add_parser", "cmd_teach", "teach_report"]

#: Zhao et al., IV: the field test's 7-cycle trench with swing to dump took 80.8 s.
ZHAO_TRENCH_S = 80.8
ZHAO_CYCLES = 7
#: Spacing of the tip paths compared by the discrete Frechet distance, m.
FRECHET_SPACING_M = 0.02


def _deg(a: Any) -> Any:
    return np.degrees(np.asarray(a, dtype=np.float64)).round(6).tolist()


def planned_tip_path(rig: Rig, traj: Any, rate_hz: float = 200.0) -> np.ndarray:
    """The tip path of a trajectory sampled at ``rate_hz``, ``(N, 3)`` m."""
    t = np.linspace(0.0, traj.duration_s, max(2, math.ceil(traj.duration_s * rate_hz) + 1))
    return pipeline.tip_path(rig, traj.sample(t))


def frechet_m(a: np.ndarray, b: np.ndarray) -> float:
    """Discrete Frechet distance of two tip paths resampled every 2 cm of arc length."""
    return pipeline.frechet_distance(
        pipeline.resample_by_length(a, FRECHET_SPACING_M),
        pipeline.resample_by_length(b, FRECHET_SPACING_M),
    )


def teach_report(
    rig: Rig,
    records: Sequence[DemoRecord],
    taught: pipeline.Taught,
    *,
    timing_ms: dict[str, float],
) -> dict[str, Any]:
    """The ``teach --json`` report, which is also the taught job (``taught.json``)."""
    s = taught.settings
    names = list(rig.joint_names)
    cyc = taught.cycle
    pose = np.asarray(kinematics.forward_3d(rig, taught.waypoints_rad), dtype=np.float64)
    trench_cycles = []
    start = 0.0
    for c in taught.trench.cycles:
        tr = c.trajectory
        trench_cycles.append(
            {
                "index": c.index,
                "offset_m": c.offset_m,
                "start_s": start,
                "T_s": tr.duration_s,
                "w_jerk": tr.problem.w_jerk,
                "waypoints_deg": _deg(c.waypoints_rad),
                "segments": segments_json(tr.piece_durations_s, tr.coefficients),
            }
        )
        start += tr.duration_s
    total = taught.trench.total_s
    # Exact peaks over the whole trench, against the rig's limits.
    joints = ((rig.swing.joint,) if rig.swing is not None else ()) + rig.joints
    v_ratio, a_ratio, exact_ok = pipeline.peak_ratios(taught.trench, taught.settings)
    mean_tip = pipeline.tip_path(rig, taught.mean_q_rad)
    planned = planned_tip_path(rig, cyc)
    op_mean = taught.operator_mean_cycle_s
    return {
        "rig": rig.name,
        "joints": names,
        "demos": [
            {"path": r.path, "samples": int(r.t_s.shape[0]), "duration_s": r.duration_s,
             "cycle_s": pipeline.trim_rest(r).duration_s}
            for r in records
        ],
        "waypoints_deg": _deg(taught.waypoints_rad),
        "waypoint_poses": [
            {"x_m": float(p[0]), "y_m": float(p[1]), "z_m": float(p[2]),
             "attitude_deg": float(math.degrees(p[3]))}
            for p in pose
        ],
        "waypoint_samples": taught.waypoint_indices.tolist(),
        "operator_mean_cycle_s": op_mean,
        "operator_cycle_s": taught.operator_cycle_s.tolist(),
        "cycle": {
            "T_s": cyc.duration_s,
            "w_jerk": cyc.problem.w_jerk,
            "waypoint_times_s": cyc.waypoint_times_s.tolist(),
            "segments": segments_json(cyc.piece_durations_s, cyc.coefficients),
            "coefficients_rule": (
                "per segment one list per joint (swing first): rad, highest power first, "
                "time in s from the segment's start"
            ),
        },
        "cycle_over_operator": cyc.duration_s / op_mean,
        "cycles_total_s": total,
        "cycle_s": [c.trajectory.duration_s for c in taught.trench.cycles],
        "trench": {
            "cycles": trench_cycles,
            "step_m": s.step_m,
            "axis": "horizontal heading of the swing frame at the first waypoint's swing angle; "
            "offsets are along it (negative: towards the machine)",
        },
        "paper": {"zhao_trench_s": ZHAO_TRENCH_S, "zhao_cycles": ZHAO_CYCLES},
        "total_over_zhao": total / ZHAO_TRENCH_S,
        "peaks": {
            name: {"velocity_ratio": float(v_ratio[j]), "acceleration_ratio": float(a_ratio[j]),
                   "velocity_max_deg_s": math.degrees(joints[j].velocity_max_rad_s),
                   "acceleration_max_deg_s2": math.degrees(joints[j].acceleration_max_rad_s2)}
            for j, name in enumerate(names)
        },
        "within_limits": {"exact": exact_ok},
        "frechet_to_mean_m": frechet_m(planned, mean_tip),
        "epsilon_mm": s.epsilon_m * 1e3,
        "settings": {
            "epsilon_mm": s.epsilon_m * 1e3, "window_s": s.window_s, "w_jerk": s.w_jerk,
            "w_time": s.w_time, "cycles": s.cycles, "step_m": s.step_m,
            "dtw_rate_hz": s.dtw_rate_hz, "dba_passes": s.dba_passes, "refine": s.refine,
            "limit_fraction": s.limit_fraction,
        },
        "timing_ms": timing_ms,
    }


def _plot(rig: Rig, records: Sequence[DemoRecord], taught: pipeline.Taught, out: Path) -> list[str]:
    """Zhao Fig. 4 (the trench's tip paths in pose space) and Fig. 5 (joint angles over the
    trench), and the demonstrations with their mean and waypoints."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:
        raise ConfigurationError("--plot needs matplotlib: pip install 'excavator-rt[plot]'") from e
    out.mkdir(parents=True, exist_ok=True)
    files = []
    # 1. Demonstrations, their mean and the waypoints, in pose space.
    fig = plt.figure(figsize=(9, 7))
    ax = fig.add_subplot(projection="3d")
    for q in pipeline.unwrap_swing(rig, [r.q_rad for r in records]):
        p = pipeline.tip_path(rig, q)
        ax.plot(p[:, 0], -p[:, 2], p[:, 1], color="0.7", lw=0.5)
    m = pipeline.tip_path(rig, taught.mean_q_rad)
    ax.plot(m[:, 0], -m[:, 2], m[:, 1], color="C0", lw=1.5, label="operator's mean path")
    w = pipeline.tip_path(rig, taught.waypoints_rad)
    ax.scatter(w[:, 0], -w[:, 2], w[:, 1], color="C3", s=18, label="waypoints")
    pl = planned_tip_path(rig, taught.cycle)
    ax.plot(pl[:, 0], -pl[:, 2], pl[:, 1], color="C2", lw=1.2, label="taught cycle")
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m]")
    ax.set_zlabel("Z [m]")
    ax.legend()
    ax.set_title(f"{len(records)} demonstrations, mean path and taught cycle on {rig.name}")
    f = out / "teach_demos.png"
    fig.savefig(f, dpi=100)
    plt.close(fig)
    files.append(str(f))
    # 2. Zhao Fig. 4: the trench's cycles in pose space.
    fig = plt.figure(figsize=(9, 7))
    ax = fig.add_subplot(projection="3d")
    for c in taught.trench.cycles:
        p = planned_tip_path(rig, c.trajectory)
        ax.plot(p[:, 0], -p[:, 2], p[:, 1], lw=1.0, label=f"cycle {c.index + 1}")
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m]")
    ax.set_zlabel("Z [m]")
    ax.legend(fontsize=7)
    ax.set_title(f"trench of {len(taught.trench.cycles)} cycles: {taught.trench.total_s:.1f} s "
                 f"(Zhao Fig. 4: {ZHAO_TRENCH_S} s)")
    f = out / "teach_trench.png"
    fig.savefig(f, dpi=100)
    plt.close(fig)
    files.append(str(f))
    # 3. Zhao Fig. 5: joint angles over the trench.
    fig, axes = plt.subplots(len(rig.joint_names), 1, figsize=(9, 9), sharex=True)
    t0 = 0.0
    for c in taught.trench.cycles:
        tr = c.trajectory
        t = np.linspace(0.0, tr.duration_s, 400)
        q = np.degrees(tr.sample(t))
        for j, axj in enumerate(axes):
            axj.plot(t0 + t, q[:, j], color="C0")
        t0 += tr.duration_s
    for j, axj in enumerate(axes):
        axj.set_ylabel(f"{rig.joint_names[j]} [deg]")
        axj.grid(True, alpha=0.3)
    axes[0].set_title("planned joint angles over the trench (Zhao Fig. 5)")
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    f = out / "teach_joints.png"
    fig.savefig(f, dpi=100)
    plt.close(fig)
    files.append(str(f))
    return files


def _settings(args: argparse.Namespace) -> pipeline.TeachSettings:
    checks = (
        ("--epsilon-mm", args.epsilon_mm, args.epsilon_mm > 0.0, "a number > 0"),
        ("--w-jerk", args.w_jerk, args.w_jerk >= 0.0, "a finite number >= 0"),
        ("--w-time", args.w_time, args.w_time > 0.0, "a finite number > 0 (with no weight on "
         "time the jerk integral falls without bound as T grows)"),
        ("--window-ms", args.window_ms, args.window_ms >= 0.0, "a number >= 0"),
        ("--step-mm", args.step_mm, abs(args.step_mm) <= 5000.0, "within +-5000"),
        ("--limit-fraction", args.limit_fraction, 0.0 < args.limit_fraction <= 1.0,
         "a number in (0, 1]"),
    )
    for flag, value, ok, allowed in checks:
        if not (math.isfinite(value) and ok):
            raise ConfigurationError(f"{flag} {value:g}: allowed {allowed}")
    if not 1 <= args.cycles <= 1000:
        raise ConfigurationError(f"--cycles {args.cycles}: allowed 1..1000")
    return pipeline.TeachSettings(
        epsilon_m=args.epsilon_mm / 1e3,
        window_s=args.window_ms / 1e3,
        w_jerk=args.w_jerk,
        w_time=args.w_time,
        cycles=args.cycles,
        step_m=args.step_mm / 1e3,
        limit_fraction=args.limit_fraction,
    )


def cmd_teach(args: argparse.Namespace) -> int:
    """``excavator-rt teach``; exit 0, or 2 (raised) on bad input or no plan."""
    rig = load_rig(args.rig)
    if rig.swing is None:
        raise ConfigurationError(
            f"teach plans trenching cycles with swing (Zhao eq 1); rig {rig.name} has no swing "
            "joint: use --rig field_excavator"
        )
    settings = _settings(args)
    t0 = time.perf_counter()
    records = [read_demo(rig, p) for p in args.demos]
    t1 = time.perf_counter()
    mean_t, mean_q, idx, _ = pipeline.learn_waypoints(rig, records, settings)
    t2 = time.perf_counter()
    idx, wps, cycle = pipeline.refine_cycle(rig, mean_q, idx, settings)
    trench = pipeline.plan_trench(rig, wps, settings, cycle)
    t3 = time.perf_counter()
    taught = pipeline.Taught(
        mean_t_s=mean_t, mean_q_rad=mean_q, waypoint_indices=idx, waypoints_rad=wps,
        cycle=cycle, trench=trench,
        operator_cycle_s=pipeline.cycle_times_s(records), settings=settings,
    )
    timing = {"read": (t1 - t0) * 1e3, "waypoints": (t2 - t1) * 1e3, "plan": (t3 - t2) * 1e3}
    report = teach_report(rig, records, taught, timing_ms=timing)
    if args.plot:
        report["plots"] = _plot(rig, records, taught, Path(args.plot))
    if args.out:
        out = Path(args.out)
        text = json.dumps(report, indent=1)
        # Verified as the executor will load it, before the file exists.
        taught_from_json(json.loads(text), rig, out / TAUGHT_FILE)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write(out / TAUGHT_FILE, lambda f: f.write(text.encode()))
        report["out"] = str(out / TAUGHT_FILE)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    _print(report)
    return 0


def _print(r: dict[str, Any]) -> None:
    print(f"teach and plan on {r['rig']} (Zhao et al.): {len(r['demos'])} demonstrations, "
          f"operator's mean cycle {r['operator_mean_cycle_s']:.2f} s")
    print(f"  waypoints (Douglas-Peucker, epsilon {r['epsilon_mm']:g} mm): "
          f"{len(r['waypoints_deg'])}   [deg: {', '.join(r['joints'])}]")
    for k, (w, p) in enumerate(zip(r["waypoints_deg"], r["waypoint_poses"], strict=True), 1):
        print(f"   {k:3d}  " + "  ".join(f"{v:8.2f}" for v in w)
              + f"   tip ({p['x_m']:.3f}, {p['y_m']:.3f}, {p['z_m']:.3f}) m")
    c = r["cycle"]
    print(f"  taught cycle {c['T_s']:.2f} s = {r['cycle_over_operator']:.0%} of the operator's "
          f"mean (goal <= 70 %)")
    print("  trench: " + ", ".join(f"{t:.2f}" for t in r["cycle_s"])
          + f" s; total {r['cycles_total_s']:.1f} s for {len(r['cycle_s'])} cycles "
          f"(Zhao: {ZHAO_TRENCH_S} s for {ZHAO_CYCLES})")
    print("  joint    peak |v| / V   peak |a| / A  (exact, whole trench)")
    for name, pk in r["peaks"].items():
        print(f"  {name:<7} {pk['velocity_ratio']:13.4f}  {pk['acceleration_ratio']:13.4f}")
    print(f"  within every limit: {'yes' if r['within_limits']['exact'] else 'NO'}; "
          f"Frechet distance of the planned tip path from the operator's mean path "
          f"{r['frechet_to_mean_m'] * 1e3:.1f} mm")
    t = r["timing_ms"]
    print(f"  time: read {t['read']:.0f} ms, demonstrations to waypoints {t['waypoints']:.0f} ms, "
          f"planning {t['plan']:.0f} ms")
    if "plots" in r:
        print("  plots: " + ", ".join(r["plots"]))
    if "out" in r:
        print(f"  taught job: {r['out']}")


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Add ``teach`` to the ``excavator-rt`` subparsers."""
    p: argparse.ArgumentParser = sub.add_parser(
        "teach",
        help="teach and plan (Zhao): operator demonstrations to a minimum time-jerk trench cycle",
    )
    p.add_argument("--rig", default="field_excavator", help="rig profile (with swing)")
    p.add_argument("--demos", nargs="+", required=True, metavar="FILE",
                   help="demonstrations: CSV (t_s, swing_deg, boom_deg, stick_deg, bucket_deg) "
                   "or CAN traces (.blf, .asc)")
    p.add_argument("--epsilon-mm", type=float, default=50.0, metavar="E",
                   help="Douglas-Peucker tolerance in pose space [mm] (default 50)")
    p.add_argument("--w-jerk", type=float, default=0.0, metavar="W1",
                   help="weight of the jerk integral (default 0: minimum time, Zhao's test)")
    p.add_argument("--w-time", type=float, default=1.0, metavar="W2",
                   help="weight of the total time (> 0)")
    p.add_argument("--cycles", type=int, default=7, help="cycles of the trench (default 7)")
    p.add_argument("--step-mm", type=float, default=150.0,
                   help="shift of each cycle along the trench axis, towards the machine [mm]")
    p.add_argument("--window-ms", type=float, default=150.0,
                   help="width of the centred moving average [ms] (0: none)")
    p.add_argument("--limit-fraction", type=float, default=0.9, metavar="F",
                   help="share of the joints' velocity and acceleration limits the cycles are "
                   "planned to, in (0, 1] (default 0.9: the rest is the drives' tracking "
                   "headroom)")
    p.add_argument("--out", metavar="DIR", help="write DIR/taught.json (the taught job)")
    p.add_argument("--plot", metavar="DIR", help="figures like Zhao Fig. 4-5 (needs matplotlib)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_teach)
    return p
