"""``excavator-rt demo``: the main job, end to end, as a newcomer first meets the product.

Role: trench task A on the default rig (``scale_model``) with the shipped PINN models, executed by
the real-time executor (fixed-rate loop, ruckig limit guard, CiA 402 master) against the HIL:
lockstep in this process by default (deterministic, faster than real time), or ``--realtime``
against the HIL in its own process over 127.0.0.1 at wall-clock speed. It prints one summary
(digs, planning latency, tracking error, coverage error, energy, wall time, against
:data:`GOALS`) and writes a run directory::

    runs/<stamp>/report.json   the HIL report (DESIGN.md "Reports" keys) plus ``demo`` (set-up and
                               run wall time) and ``goals`` (each goal and whether it was met):
                               :class:`DemoReport`
    runs/<stamp>/can.blf       the CAN trace (python-can BLF; opens in standard tools)
    runs/<stamp>/*.png         profile, tracking (Yao Fig. 17-21 manner) and timing histogram

Wall time is split: ``setup_s`` (imports, model loading) and ``run_s`` (planning and execution,
the goal of <= 40 s), measured with ``time.perf_counter``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from hil_sim.harness.reports import HilReport

__all__ = [
    "DemoReport",
    "DemoTiming",
    "GoalCheck",
    "add_parser",
    "goal_check",
    "run",
    "run_demo",
    "summary_text",
]

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
        print(json.dumps(report.to_json()))
    else:
        print(summary_text(report, run_dir))
    return 0 if report.hil.status == "done" else 1


@dataclass(frozen=True, slots=True)
class DemoTiming:
    """The demo's wall time (``demo`` of the report).

    Attributes:
        setup_s: Imports and loading before the run (s).
        run_s: Planning and execution (s).
        run_dir: The run directory.
    """

    setup_s: float
    run_s: float
    run_dir: str

    def to_json(self) -> dict[str, Any]:
        """``{"setup_s", "run_s", "run_dir"}``."""
        return {"setup_s": self.setup_s, "run_s": self.run_s, "run_dir": self.run_dir}


@dataclass(frozen=True, slots=True)
class GoalCheck:
    """One goal of :data:`GOALS` against the run.

    Attributes:
        goal: The largest value that meets the goal.
        value: The value measured (NaN where the run has none).
        met: ``value <= goal``.
    """

    goal: float
    value: float
    met: bool

    def to_json(self) -> dict[str, Any]:
        """``{"goal", "value", "met"}``."""
        return {"goal": self.goal, "value": self.value, "met": self.met}


@dataclass(frozen=True, slots=True)
class DemoReport:
    """The demo's report: the HIL report, the demo's wall time and the goals checked.

    Attributes:
        hil: The run's HIL report.
        demo: Set-up and run wall time.
        goals: Per goal name of :data:`GOALS`, the check.
    """

    hil: HilReport
    demo: DemoTiming
    goals: Mapping[str, GoalCheck]

    def to_json(self) -> dict[str, Any]:
        """The HIL report's keys plus ``demo`` and ``goals`` (``report.json``)."""
        return {
            **self.hil.to_json(),
            "demo": self.demo.to_json(),
            "goals": {name: g.to_json() for name, g in self.goals.items()},
        }


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
) -> tuple[DemoReport, Path]:
    """Run the demo and write its run directory.

    Returns:
        The report and the run directory.

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
    hil = run_scenario(scenario).report
    run_s = time.perf_counter() - t1
    if plots:
        png = plot_timing(hil, run_dir / "timing.png")
        if png is not None:
            hil = dataclasses.replace(hil, plots=(*(hil.plots or ()), str(png)))
    report = DemoReport(hil, DemoTiming(setup_s, run_s, str(run_dir)), goal_check(hil, run_s=run_s))
    (run_dir / "report.json").write_text(json.dumps(report.to_json(), indent=1) + "\n")
    return report, run_dir


def _worst(report: HilReport, figure: str) -> float:
    values = [fig.max_mm if figure == "max_mm" else fig.rms_mm for fig in report.tracking.values()]
    return max(values) if values else math.nan


def goal_check(report: HilReport, *, run_s: float) -> dict[str, GoalCheck]:
    """Each goal of :data:`GOALS` with the measured value and whether it was met.

    Args:
        report: The run's HIL report.
        run_s: The run's wall time (s), planning and execution.
    """
    measured = {
        "coverage_error_max": _or_nan(report.coverage_error),
        "overdig_max_mm": _or_nan(report.overdig_max_mm),
        "tracking_max_mm": _worst(report, "max_mm"),
        "tracking_rms_mm": _worst(report, "rms_mm"),
        "run_wall_s_max": run_s,
    }
    return {
        name: GoalCheck(GOALS[name], value, bool(value <= GOALS[name]))
        for name, value in measured.items()
    }


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else value


def summary_text(report: DemoReport, run_dir: Path) -> str:
    """The one summary the demo prints."""
    hil = report.hil
    plan = np.array([d.plan_us for d in hil.digs], dtype=np.float64)
    plan = plan[np.isfinite(plan)]

    def mark(name: str) -> str:
        g = report.goals.get(name)
        return "" if g is None else ("  [goal met]" if g.met else "  [goal MISSED]")

    lines = [
        f"excavator-rt demo: task {hil.task} on {hil.rig}, "
        f"{hil.transport} HIL, status {hil.status}",
    ]
    if hil.fault:
        lines.append(f"  stopped: {hil.fault}")
    lines.append(f"  digs                {len(hil.digs)}  ({hil.sim_s:.1f} s of machine time)")
    if plan.size:
        lines.append(
            f"  planning per dig    median {np.median(plan) / 1e3:.0f} ms, max "
            f"{plan.max() / 1e3:.0f} ms (screening + PINN + verification; Yao 4.2 ms per "
            "PINN plan, 69 s per PSO)"
        )
    for axis, fig in hil.tracking.items():
        lines.append(
            f"  tracking {axis:<7}    max {fig.max_mm:.3f} mm, RMS {fig.rms_mm:.4f} mm "
            "(plant truth)"
        )
    lines.append(
        f"  worst tracking      max {_worst(hil, 'max_mm'):.3f} mm (goal 1.0)"
        f"{mark('tracking_max_mm')}, RMS {_worst(hil, 'rms_mm'):.4f} mm (goal 0.3)"
        f"{mark('tracking_rms_mm')}"
    )
    if hil.coverage_error is not None:
        lines.append(
            f"  coverage error      {hil.coverage_error:.2%} (goal 2 %; Yao 8.7 % on A)"
            f"{mark('coverage_error_max')}"
        )
        lines.append(
            f"  over-dig            {_or_nan(hil.overdig_max_mm):.1f} mm (goal 5 mm)"
            f"{mark('overdig_max_mm')}"
        )
    lines.append(f"  energy              {hil.energy_Wh:.3f} Wh")
    load = hil.can.bus_load
    if load is not None:
        lines.append(f"  CAN bus load        {load.nominal:.1%} nominal, {load.worst:.1%} worst")
    lines.append(f"  overruns            {hil.overruns}")
    lines.append(
        f"  wall time           {report.demo.run_s:.1f} s run (goal 40 s)"
        f"{mark('run_wall_s_max')}, {report.demo.setup_s:.1f} s set-up"
    )
    lines.append(f"  written             {run_dir}/report.json, can.blf, *.png")
    return "\n".join(lines)


def plot_timing(report: HilReport, path: Path) -> Path | None:
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
    plan_ms = [d.plan_us / 1e3 for d in report.digs if math.isfinite(d.plan_us)]
    ax = axes[0]
    ax.bar(range(1, len(plan_ms) + 1), plan_ms, color="tab:blue")
    ax.set_xlabel("dig")
    ax.set_ylabel("planning time [ms]")
    ax.set_title("next-dig planning (screening + PINN + verification)")
    ax = axes[1]
    loop_stats = report.loop
    if report.transport == "realtime" and loop_stats is not None and len(loop_stats.lateness_s):
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
        ax.set_title(f"loop at {1 / report.period_s:.0f} Hz (real time)")
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
