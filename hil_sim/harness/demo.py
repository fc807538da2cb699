"""``excavator-rt demo``: the main job, end to end, as a newcomer first meets the product.

Role: trench task A on the default rig (``scale_model``) with the shipped PINN models, executed by
the real-time executor (fixed-rate loop, ruckig limit guard, CiA 402 master) against the HIL:
lockstep in this process by default (deterministic, faster than real time), or ``--realtime``
against the HIL in its own process over 127.0.0.1 at wall-clock speed. It prints one summary
(digs, planning latency, tracking error, coverage error, energy, wall time, against
:data:`GOALS`) and writes a run directory::

    runs/<stamp>/report.json   the HIL report (DESIGN.md "Reports" keys) plus ``demo`` (set-up and
                               run wall time) and ``goals`` (each goal and whether it was met)
    runs/<stamp>/can.blf       the CAN trace (python-can BLF; opens in standard tools)
    runs/<stamp>/*.png         profile, tracking (Yao Fig. 17-21 manner) and timing histogram

Wall time is split: ``setup_s`` (imports, model loading) and ``run_s`` (planning and execution,
the goal of <= 40 s), measured with ``time.perf_counter``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["add_parser", "run", "run_demo", "summary_text"]

#: Goals the summary checks (trench, tracking, run time).
GOALS = {
    "coverage_error_max": 0.02,
    "overdig_max_mm": 5.0,
    "tracking_max_mm": 1.0,
    "tracking_rms_mm": 0.3,
    "run_wall_s_max": 40.0,
}


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``demo`` subcommand to ``excavator-rt``'s subparsers."""
    p: argparse.ArgumentParser = sub.add_parser(
        "demo",
        help="the main job: trench task A executed by the real-time loop against the HIL",
    )
    p.add_argument("--task", default="A", help="task name (A-D) or TOML file (default A)")
    p.add_argument("--rig", default="scale_model", help="rig profile (default scale_model)")
    p.add_argument(
        "--realtime",
        action="store_true",
        help="the HIL in its own process over 127.0.0.1 at wall-clock speed",
    )
    p.add_argument("--out", default="runs", help="parent of the run directory (default runs/)")
    p.add_argument("--max-digs", type=int, default=None, help="stop after N digs")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.set_defaults(handler=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Handler of ``excavator-rt demo``; exit 0 when the run completed, 1 when it stopped short."""
    report, run_dir = run_demo(
        task=args.task,
        rig=args.rig,
        realtime=args.realtime,
        out_dir=args.out,
        max_digs=args.max_digs,
        plots=not args.no_plots,
    )
    if args.json:
        print(json.dumps(report))
    else:
        print(summary_text(report, run_dir))
    return 0 if report.get("status") == "done" else 1


def _run_dir(parent: str | Path) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = Path(parent) / stamp
    n = 1
    while path.exists():
        n += 1
        path = Path(parent) / f"{stamp}-{n}"
    path.mkdir(parents=True)
    return path


def run_demo(
    *,
    task: str = "A",
    rig: str = "scale_model",
    realtime: bool = False,
    out_dir: str | Path = "runs",
    max_digs: int | None = None,
    plots: bool = True,
) -> tuple[dict[str, Any], Path]:
    """Run the demo and write its run directory.

    Returns:
        The report (JSON-able) and the run directory.

    Raises:
        ConfigurationError: Bad task or rig.
        CommunicationError, DriveFault: The drives did not boot or enable.
    """
    t0 = time.perf_counter()
    from hil_sim.harness.scenario import Scenario, run_scenario  # imports the planner stack

    run_dir = _run_dir(out_dir)
    setup_s = time.perf_counter() - t0
    scenario = Scenario(
        task=task,
        rig=rig,
        realtime=realtime,
        trace_path=str(run_dir / "can.blf"),
        max_digs=max_digs,
        plot_dir=str(run_dir) if plots else None,
    )
    t1 = time.perf_counter()
    run = run_scenario(scenario)
    run_s = time.perf_counter() - t1
    report, loop_stats = run.report, run.loop_stats
    report["demo"] = {"setup_s": setup_s, "run_s": run_s, "run_dir": str(run_dir)}
    report["goals"] = goal_check(report)
    if plots:
        png = plot_timing(report, loop_stats, run_dir / "timing.png")
        if png is not None:
            report.setdefault("plots", []).append(str(png))
    (run_dir / "report.json").write_text(json.dumps(report, indent=1) + "\n")
    return report, run_dir


def _worst(report: dict[str, Any], key: str) -> float:
    values = [axis[key] for axis in report.get("tracking", {}).values()]
    return max(values) if values else math.nan


def goal_check(report: dict[str, Any]) -> dict[str, Any]:
    """Each goal with the measured value and whether it was met."""
    measured = {
        "coverage_error_max": report.get("coverage_error", math.nan),
        "overdig_max_mm": report.get("overdig_max_mm", math.nan),
        "tracking_max_mm": _worst(report, "max_mm"),
        "tracking_rms_mm": _worst(report, "rms_mm"),
        "run_wall_s_max": report.get("demo", {}).get("run_s", math.nan),
    }
    return {
        name: {"goal": GOALS[name], "value": value, "met": bool(value <= GOALS[name])}
        for name, value in measured.items()
    }


def summary_text(report: dict[str, Any], run_dir: Path) -> str:
    """The one summary the demo prints."""
    digs = report.get("digs", [])
    plan = np.array([d.get("plan_us", math.nan) for d in digs], dtype=np.float64)
    plan = plan[np.isfinite(plan)]
    demo = report.get("demo", {})
    goals = report.get("goals", {})

    def mark(name: str) -> str:
        g = goals.get(name)
        return "" if g is None else ("  [goal met]" if g["met"] else "  [goal MISSED]")

    lines = [
        f"excavator-rt demo: task {report.get('task')} on {report.get('rig')}, "
        f"{report.get('transport')} HIL, status {report.get('status')}",
    ]
    if report.get("fault"):
        lines.append(f"  stopped: {report['fault']}")
    lines.append(
        f"  digs                {len(digs)}  ({report.get('sim_s', 0.0):.1f} s of machine time)"
    )
    if plan.size:
        lines.append(
            f"  planning per dig    median {np.median(plan) / 1e3:.0f} ms, max "
            f"{plan.max() / 1e3:.0f} ms (screening + PINN + verification; Yao 4.2 ms per "
            "PINN plan, 69 s per PSO)"
        )
    for axis, fig in report.get("tracking", {}).items():
        lines.append(
            f"  tracking {axis:<7}    max {fig['max_mm']:.3f} mm, RMS {fig['rms_mm']:.4f} mm "
            "(plant truth)"
        )
    lines.append(
        f"  worst tracking      max {_worst(report, 'max_mm'):.3f} mm (goal 1.0)"
        f"{mark('tracking_max_mm')}, RMS {_worst(report, 'rms_mm'):.4f} mm (goal 0.3)"
        f"{mark('tracking_rms_mm')}"
    )
    if "coverage_error" in report:
        lines.append(
            f"  coverage error      {report['coverage_error']:.2%} (goal 2 %; Yao 8.7 % on A)"
            f"{mark('coverage_error_max')}"
        )
        lines.append(
            f"  over-dig            {report['overdig_max_mm']:.1f} mm (goal 5 mm)"
            f"{mark('overdig_max_mm')}"
        )
    lines.append(f"  energy              {report.get('energy_Wh', math.nan):.3f} Wh")
    load = report.get("can", {}).get("bus_load")
    if load:
        lines.append(
            f"  CAN bus load        {load['nominal']:.1%} nominal, {load['worst_case']:.1%} worst"
        )
    lines.append(f"  overruns            {report.get('overruns', 0)}")
    lines.append(
        f"  wall time           {demo.get('run_s', math.nan):.1f} s run (goal 40 s)"
        f"{mark('run_wall_s_max')}, {demo.get('setup_s', math.nan):.1f} s set-up"
    )
    lines.append(f"  written             {run_dir}/report.json, can.blf, *.png")
    return "\n".join(lines)


def plot_timing(report: dict[str, Any], loop_stats: Any, path: Path) -> Path | None:
    """Timing histogram: planning latency per dig, and loop lateness/step time per cycle.

    In lockstep the loop runs on simulated time (lateness is zero by construction), so the
    per-cycle panel shows the step's wall cost only on a real-time run; lockstep shows the
    per-dig planning latencies alone. Returns None without matplotlib.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    plan_ms = [d["plan_us"] / 1e3 for d in report.get("digs", []) if math.isfinite(d["plan_us"])]
    ax = axes[0]
    ax.bar(range(1, len(plan_ms) + 1), plan_ms, color="tab:blue")
    ax.set_xlabel("dig")
    ax.set_ylabel("planning time [ms]")
    ax.set_title("next-dig planning (screening + PINN + verification)")
    ax = axes[1]
    realtime = report.get("transport") == "realtime"
    if realtime and loop_stats is not None and len(loop_stats.lateness_s):
        late_us = np.asarray(loop_stats.lateness_s) * 1e6
        exec_us = np.asarray(loop_stats.exec_s) * 1e6
        bins = np.logspace(0, 4.5, 60)
        ax.hist(np.clip(late_us, 1, None), bins=bins, alpha=0.6, label="lateness")
        ax.hist(np.clip(exec_us, 1, None), bins=bins, alpha=0.6, label="step time")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("µs")
        ax.set_ylabel("cycles")
        ax.legend()
        ax.set_title(f"loop at {1 / report['period_s']:.0f} Hz (real time)")
    else:
        ax.axis("off")
        ax.text(
            0.5,
            0.5,
            "lockstep: the loop runs on simulated time\n(no lateness); run with --realtime\n"
            "or `excavator-rt bench` for loop timing",
            ha="center",
            va="center",
        )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
