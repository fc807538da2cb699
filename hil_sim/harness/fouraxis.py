"""Four-axis HIL runs on a rig with swing: a prescribed path (a taught trench), the operator's
manual mode and its recordings, and their tracking figures.

Role: the harness side of the swing axis (DESIGN.md "CAN protocol": the swing is a CiA 402 drive
on node 4, streamed as a fourth axis). Every run is the lockstep HIL
(:class:`~hil_sim.harness.lockstep.LockstepHil`: deterministic, faster than real time) with the
runtime's master, limit guard and controller manager on its bus, so the same frames a rig would
carry cross it:

* :func:`run_path`: a :class:`~rt_runtime.control.planner_worker.PathJob` through the
  :class:`~rt_runtime.control.executor.Executor`; :func:`run_taught` loads a taught job
  (``teach --out DIR``, :func:`rt_runtime.control.taught_path.load_taught_path`) and runs it
  so;
* :func:`run_operator_demo`: the simulated operator (:class:`hil_sim.operator.Operator`) on the
  levers of manual mode (:class:`~rt_runtime.control.manual.LeverController`), recorded as the
  issue's CSV (the drives' reported positions mapped to joint angles at every lever tick, the
  lever commands beside them, the intended path in ``<stem>.intended.json``) and as the run's
  CAN trace (BLF), from which :func:`rt_runtime.teach.demos.read_trace` reads the same joints.

Tracking (:func:`four_axis_tracking`): per axis the true actuator position (the plant's truth at
each SYNC) against the demand at that SYNC (the setpoint the drives were sent for it) over the
cycles that streamed the motion; the cylinders in mm, the swing in degrees, with the swing's
overshoot: where the reference swing comes to rest or turns back, how far the true swing runs
past it in the direction it was moving. The tip error is the 3-D distance (Zhao eq 1) of the
true tip from the reference tip.

Joint order: the runtime's control stack is in axis order (boom, stick, bucket, swing;
:mod:`rt_runtime.axes`); the operator, the teach pipeline and the files are swing first; the
conversions are here.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil_sim.harness.lockstep import LockstepHil
from hil_sim.harness.scenario import NO_RT as _NO_RT
from hil_sim.sim import FaultKind, open_trace
from hil_sim.swing import velocity_lead2_s2, velocity_lead_s
from rt_runtime import axes, kinematics
from rt_runtime.canbus import CanMaster
from rt_runtime.control import FixedRateLoop, LoopConfig
from rt_runtime.control.controllers import GuardFilter
from rt_runtime.control.executor import (
    Executor,
    ExecutorConfig,
    ExecutorResult,
    executor_telemetry,
)
from rt_runtime.control.guard import LimitGuard, StrokeLimits
from rt_runtime.control.hardware import DriveInterface
from rt_runtime.control.manager import ControllerManager
from rt_runtime.control.manual import LeverController
from rt_runtime.control.planner_worker import PathJob
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig

__all__ = [
    "DemoFiles",
    "FourAxisRun",
    "SwingTracking",
    "four_axis_tracking",
    "run_operator_demo",
    "run_path",
    "run_taught",
]

FloatArray = NDArray[np.float64]

#: The SYNC period of every four-axis run (s).
PERIOD_S = 0.002


def _require_swing(rig: Rig) -> None:
    if rig.swing is None:
        raise ConfigurationError(
            f"rig {rig.name} has no swing axis; four-axis runs need a profile with a [swing] "
            "table (field_excavator)"
        )


@dataclass(frozen=True, slots=True)
class SwingTracking:
    """Tracking of a four-axis run (truth against demand; see the module docstring).

    Attributes:
        cylinders_mm: Per cylinder axis ``(max_mm, rms_mm)``.
        swing_max_deg, swing_rms_deg: The swing's tracking error (deg).
        swing_overshoot_deg: The largest overshoot of the swing past a stop or turn (deg).
        tip_error_max_mm: Largest 3-D tip error (mm).
        cycles: Cycles that counted.
    """

    cylinders_mm: dict[str, tuple[float, float]]
    swing_max_deg: float
    swing_rms_deg: float
    swing_overshoot_deg: float
    tip_error_max_mm: float
    cycles: int

    def to_json(self) -> dict[str, Any]:
        """``tracking`` per cylinder axis (``max_mm``, ``rms_mm``), ``swing`` (``max_deg``,
        ``rms_deg``, ``overshoot_deg``), ``tip_error_max_mm``, ``cycles``."""
        return {
            "tracking": {
                name: {"max_mm": mx, "rms_mm": rms}
                for name, (mx, rms) in self.cylinders_mm.items()
            },
            "swing": {
                "max_deg": self.swing_max_deg,
                "rms_deg": self.swing_rms_deg,
                "overshoot_deg": self.swing_overshoot_deg,
            },
            "tip_error_max_mm": self.tip_error_max_mm,
            "cycles": self.cycles,
        }


def four_axis_tracking(rig: Rig, telemetry: dict[str, Any], truth: Any) -> SwingTracking:
    """Tracking figures of a four-axis run from its telemetry and the HIL's truth.

    Raises:
        ConfigurationError: The rig has no swing.
    """
    _require_swing(rig)
    sync = np.asarray(telemetry["sync"], dtype=np.int64)
    tracking = np.asarray(telemetry["tracking"], dtype=bool)
    ref = np.asarray(telemetry["stroke_ref_m"], dtype=np.float64)
    t_sync = np.asarray(truth.sync_index, dtype=np.int64)
    index = {int(k): i for i, k in enumerate(t_sync.tolist())}
    rows = [(j, index[int(k)]) for j, k in enumerate(sync.tolist()) if tracking[j] and k in index]
    if not rows:
        nan = math.nan
        names = axes.ARM_AXES
        return SwingTracking({n: (nan, nan) for n in names}, nan, nan, nan, nan, 0)
    tj = np.array([r[0] for r in rows])
    ti = np.array([r[1] for r in rows])
    true = np.column_stack([truth.stroke_m[ti], truth.swing_rad[ti]])
    demand = ref[tj]
    err = true - demand
    cyl = {
        name: (
            float(np.max(np.abs(err[:, a])) * 1e3),
            float(np.sqrt(np.mean(err[:, a] ** 2)) * 1e3),
        )
        for a, name in enumerate(axes.ARM_AXES)
    }
    sw = err[:, 3]
    # Overshoot: where the reference swing stops or turns, the true swing past it.
    ref_sw = demand[:, 3]
    rate = np.gradient(ref_sw) / PERIOD_S
    limit = rig.swing.joint.velocity_max_rad_s if rig.swing is not None else 1.0
    moving = np.abs(rate) > 0.01 * limit
    overshoot = 0.0
    direction = 0.0
    for k in range(len(ref_sw)):
        if moving[k]:
            direction = math.copysign(1.0, rate[k])
        elif direction != 0.0:
            overshoot = max(overshoot, direction * float(sw[k]))
    q_true = axes.actuator_to_joint(rig, true, check_limits=False)
    q_ref = axes.actuator_to_joint(rig, demand, check_limits=False)
    tip_true = kinematics.forward_3d(rig, axes.to_joint_order(rig, q_true))[:, :3]
    tip_ref = kinematics.forward_3d(rig, axes.to_joint_order(rig, q_ref))[:, :3]
    tip = np.linalg.norm(tip_true - tip_ref, axis=1)
    return SwingTracking(
        cylinders_mm=cyl,
        swing_max_deg=math.degrees(float(np.max(np.abs(sw)))),
        swing_rms_deg=math.degrees(float(np.sqrt(np.mean(sw * sw)))),
        swing_overshoot_deg=math.degrees(overshoot),
        tip_error_max_mm=float(np.max(tip) * 1e3),
        cycles=len(rows),
    )


@dataclass(frozen=True, slots=True)
class FourAxisRun:
    """One four-axis run on the lockstep HIL.

    Attributes:
        result: The executor's result (a path run) or None (manual mode).
        status: ``done``, or how it ended (the executor's status name, or ``fault``).
        fault: What went wrong (empty when done).
        telemetry: The loop's telemetry (axis order).
        truth: The HIL's truth.
        frames: Every frame of the bus when kept (``keep_frames``), else empty.
        tracking: The tracking figures.
        wall_s: Wall time of the run.
    """

    result: ExecutorResult | None
    status: str
    fault: str
    telemetry: dict[str, Any]
    truth: Any
    frames: list[tuple[int, bytes]]
    tracking: SwingTracking
    wall_s: float


def _boot(hil: LockstepHil, rig: Rig) -> CanMaster:
    master = CanMaster(hil.master_bus, rig, period_s=PERIOD_S, react_to_faults=False)
    master.boot(hil.clock.now, 1.0)
    master.enable(hil.clock.now, 1.0)
    return master


def run_path(
    rig: Rig,
    job: PathJob,
    q0_rad: FloatArray,
    *,
    trace_path: str | Path | None = None,
    keep_frames: bool = False,
    fault: tuple[FaultKind, int, float] | None = None,
    config: ExecutorConfig | None = None,
) -> FourAxisRun:
    """Run a prescribed four-axis path from ``q0_rad`` (axis order) on the lockstep HIL.

    Args:
        rig: A rig with swing.
        job: The path (motions in axis order).
        q0_rad: Where the arm and the swing stand at the start (axis order).
        trace_path: Write the bus trace (``.blf``/``.asc``) here.
        keep_frames: Keep every frame in :attr:`FourAxisRun.frames`.
        fault: ``(kind, axis, seconds after the first cycle)``: a drive fault injected once.
        config: Executor settings.

    Raises:
        ConfigurationError: No swing, or what the executor refuses (nothing was sent then).
        JointLimitError, PlanningError: The path breaks a limit (nothing was sent).
    """
    _require_swing(rig)
    start: list[float] = []
    injected: list[float] = []
    t0 = time.perf_counter()
    with LockstepHil(rig, q0_rad, keep_frames=keep_frames, trace_path=trace_path) as hil:

        def on_cycle(_sync: int, now_s: float) -> None:
            if not start:
                start.append(now_s)
            if fault is not None and not injected and now_s - start[0] >= fault[2]:
                hil.inject(fault[0], fault[1])
                injected.append(now_s)

        master = _boot(hil, rig)
        rows = int(job_duration_s(job) / PERIOD_S) + 10_000
        loop = FixedRateLoop(
            hil.clock, LoopConfig(period_s=PERIOD_S, rt=_NO_RT), executor_telemetry(rows, 4)
        )
        result = Executor(master, rig, loop, job, config, on_cycle=on_cycle).run()
        truth = hil.core.truth()
        frames = list(hil.core.frames)
    return FourAxisRun(
        result=result,
        status=result.status.name.lower(),
        fault=result.fault,
        telemetry=result.telemetry,
        truth=truth,
        frames=frames,
        tracking=four_axis_tracking(rig, result.telemetry, truth),
        wall_s=time.perf_counter() - t0,
    )


def job_duration_s(job: PathJob) -> float:
    """Sum of the motions' durations (s)."""
    return float(sum(float(m.duration_s) for m in job.motions))


def run_taught(
    rig: Rig,
    directory: str | Path,
    *,
    trace_path: str | Path | None = None,
    fault: tuple[FaultKind, int, float] | None = None,
    lead: bool = True,
) -> tuple[FourAxisRun, Any]:
    """Load ``directory``'s taught job (verified against ``rig``) and run it on the HIL from its
    first pose; returns the run and the job. With ``lead`` the velocity offsets lead by each
    axis's lag in this plant (:func:`hil_sim.swing.velocity_lead_s`), as a commissioned rig's
    would.

    Raises:
        ConfigurationError: No swing, a missing or malformed taught job, one taught on other
            joints (nothing moves).
        PlanningError: The taught trench breaks a limit of the rig (nothing moves).
    """
    from rt_runtime.control.taught_path import load_taught_path

    _require_swing(rig)
    path, job = load_taught_path(directory, rig)
    q0 = axes.from_joint_order(rig, job.q0_rad)
    config = ExecutorConfig(
        velocity_lead_s=velocity_lead_s(rig) if lead else None,
        velocity_lead2_s2=velocity_lead2_s2(rig) if lead else None,
    )
    return run_path(rig, path, q0, trace_path=trace_path, fault=fault, config=config), job


@dataclass(frozen=True, slots=True)
class DemoFiles:
    """What one recorded demonstration wrote, and how it went.

    Attributes:
        csv: The CSV.
        trace: The CAN trace (BLF).
        intended: The intended path beside the CSV.
        seed: The operator's seed.
        speed: The operator's pace.
        duration_s: The recording's length.
        status: ``done`` or ``fault``.
        fault: Why it stopped early (empty when done).
        lever_ticks: Lever commands given.
    """

    csv: Path
    trace: Path
    intended: Path
    seed: int
    speed: float
    duration_s: float
    status: str
    fault: str
    lever_ticks: int

    def to_json(self) -> dict[str, Any]:
        """The entry of ``hil --operator --json``'s ``demos``."""
        return {
            "csv": str(self.csv),
            "trace": str(self.trace),
            "intended": str(self.intended),
            "seed": self.seed,
            "speed": self.speed,
            "duration_s": self.duration_s,
            "status": self.status,
            "fault": self.fault,
            "lever_ticks": self.lever_ticks,
        }


def run_operator_demo(
    rig: Rig,
    seed: int,
    out_dir: str | Path,
    *,
    name: str | None = None,
    rate_hz: float = 100.0,
    speed: float | None = None,
    jerks: bool = True,
    fault: tuple[FaultKind, int, float] | None = None,
) -> DemoFiles:
    """One demonstration by the simulated operator in the HIL's manual mode, recorded.

    The operator starts at rest on his cycle's first pose; every lever tick he reads the joint
    angles the drives report and moves the levers; the machine adds its hydraulic jerks to the
    lever command (:meth:`hil_sim.operator.Operator.hydraulic_jerk_rad_s`). Manual mode runs
    from the first cycle after the drives are enabled until the axes are at rest after the
    operator let go; the recording covers exactly that: the CAN trace ``<name>.blf`` every
    frame of it, the CSV ``<name>.csv`` (:func:`hil_sim.operator.write_csv`, with
    ``<name>.intended.json`` beside it) one row per SYNC with the joint angles the drives
    reported for it and the lever then held, as a rig's logger of the same feedback would.

    Args:
        rig: A rig with swing.
        seed: The operator's seed.
        out_dir: Where the files go (created).
        name: File stem (default ``demo_<seed>``).
        rate_hz: Lever tick rate; a whole number of SYNC periods (100 Hz: every 5th at 2 ms).
        speed: The operator's pace (default: drawn from the seed).
        jerks: Add the machine's hydraulic jerks.
        fault: ``(kind, axis, seconds)``: a drive fault injected once (axis order).

    Raises:
        ConfigurationError: No swing, a rate that is not a whole number of periods, or what
            the operator model refuses.
    """
    from hil_sim.operator import Demonstration, Operator, write_csv

    _require_swing(rig)
    tick = round(1.0 / (rate_hz * PERIOD_S))
    if tick < 1 or abs(tick * PERIOD_S * rate_hz - 1.0) > 1e-9:
        raise ConfigurationError(
            f"lever rate {rate_hz} Hz: allowed a whole number of {PERIOD_S * 1e3:g} ms SYNC "
            "periods per tick (500, 250, 100, 50 Hz, ...)"
        )
    op = Operator(rig, seed=seed, rate_hz=rate_hz, speed=speed)
    q0 = axes.from_joint_order(rig, op.intended_now())
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = name if name is not None else f"demo_{seed:02d}"
    trace = out / f"{stem}.blf"
    t_rec: list[float] = []
    q_rec: list[FloatArray] = []
    lever_rec: list[FloatArray] = []
    last_lever = np.zeros(4)
    limit_s = 40.0 * op.path.duration_s / op.params.speed + 60.0
    start: list[float] = []

    def source(t_s: float, q_axis: FloatArray) -> FloatArray | None:
        if not start:
            start.append(t_s)
        if op.finished or op.t_s > limit_s or not np.all(np.isfinite(q_axis)):
            return None
        q = axes.to_joint_order(rig, q_axis)
        lever = op.step(q)
        last_lever[:] = lever
        machine = lever + (op.hydraulic_jerk_rad_s(op.t_s) if jerks else 0.0)
        machine = np.clip(machine, -op.velocity_max_rad_s, op.velocity_max_rad_s)
        return axes.from_joint_order(rig, machine)

    with LockstepHil(rig, q0) as hil:
        master = _boot(hil, rig)
        drives = DriveInterface(master, hil.clock, 0.0, True)
        drives.react_to_faults(False)
        guard = LimitGuard(StrokeLimits.from_rig(rig), PERIOD_S)
        s0 = drives.measured_stroke_m()
        guard.reset(s0)
        gf = GuardFilter(guard)
        lever = LeverController(rig, gf, source, tick=tick, describe=drives.describe)
        injected: list[float] = []

        def on_cycle(_sync: int, now_s: float) -> None:
            if fault is not None and start and not injected and now_s - start[0] >= fault[2]:
                hil.inject(fault[0], fault[1])
                injected.append(now_s)
            q = lever.q_measured_rad
            if start and np.all(np.isfinite(q)):
                t_rec.append(now_s - start[0])
                q_rec.append(axes.to_joint_order(rig, q))
                lever_rec.append(last_lever.copy())

        rows = int(limit_s / PERIOD_S) + 1000
        loop = FixedRateLoop(
            hil.clock, LoopConfig(period_s=PERIOD_S, rt=_NO_RT), executor_telemetry(rows, 4)
        )
        manager = ControllerManager(drives, gf, loop, on_cycle=on_cycle)
        q_start = axes.actuator_to_joint(rig, s0, check_limits=False)
        logger = open_trace(trace)
        hil.core.trace = logger
        try:
            manager.run(lever, lever.first(), s0, q_start, max_cycles=rows)
            drives.disable()
        finally:
            hil.core.trace = None
            logger.stop()
    if len(t_rec) < 2:
        raise ConfigurationError(f"operator seed {seed}: no lever tick was recorded")
    it, iq = op.path.sampled(1.0 / PERIOD_S)
    q_arr = np.asarray(q_rec)
    demo = Demonstration(
        t_s=np.round(np.asarray(t_rec), 9),
        q_rad=q_arr,
        lever=np.asarray(lever_rec),
        intended_t_s=it,
        intended_q_rad=iq,
        seed=seed,
        params=op.params,
        q_true_rad=q_arr,
    )
    csv = out / f"{stem}.csv"
    intended = write_csv(demo, csv, tuple(rig.joint_names))
    return DemoFiles(
        csv=csv,
        trace=trace,
        intended=intended,
        seed=seed,
        speed=op.params.speed,
        duration_s=demo.duration_s,
        status="fault" if lever.fault else "done",
        fault=lever.fault,
        lever_ticks=lever.ticks,
    )


# -- the command line: hil --operator, hil --teach ---------------------------------------------


def add_arguments(p: Any) -> None:
    """The ``hil`` options of the operator's demonstrations and of a taught job's run."""
    g = p.add_argument_group("operator and taught jobs (a rig with swing: field_excavator)")
    g.add_argument(
        "--operator",
        action="store_true",
        help="the simulated operator digs by lever in manual mode; each demonstration is "
        "recorded as CSV and CAN trace (BLF) with its intended path beside it",
    )
    g.add_argument("--demos", type=int, default=None, metavar="N", help="demonstrations to record")
    g.add_argument("--out", default=None, metavar="DIR", help="where the demonstrations go")
    g.add_argument("--seed", type=int, default=0, help="first operator seed (default 0)")
    g.add_argument(
        "--teach",
        default=None,
        metavar="DIR",
        help="run the taught trench of DIR (teach --out DIR) on the HIL, four axes",
    )
    g.add_argument(
        "--no-lead",
        action="store_true",
        help="with --teach or --mintorque: the velocity offsets without the lead of each "
        "axis's lag",
    )


def _fault(args: Any, rig: Rig) -> tuple[FaultKind, int, float] | None:
    """The one drive fault ``--inject`` names for a four-axis run (None: none)."""
    faults = list(getattr(args, "inject", []) or [])
    if not faults:
        return None
    names = axes.names(rig)
    if len(faults) > 1 or faults[0].kind.layer != "drive" or faults[0].axis not in names:
        raise ConfigurationError(
            "a four-axis run takes one drive fault on an axis ("
            + ", ".join(names)
            + "), e.g. --inject overcurrent:swing:5"
        )
    spec = faults[0]
    return spec.kind, names.index(spec.axis), spec.at_s


def run_command(args: Any) -> int:
    """``hil --operator`` or ``hil --teach``: exit 0 done, 1 a fault stopped a run, 2 refused."""
    import json

    from rt_runtime.rig import load_rig

    try:
        if args.operator and args.teach is not None:
            raise ConfigurationError("--operator and --teach are two runs; give one")
        rig = load_rig(args.rig if args.rig is not None else "field_excavator")
        report = _operator(args, rig) if args.operator else _taught(args, rig)
    except (ConfigurationError, ValueError, OSError) as exc:
        _refuse(args, str(exc))
        return 2
    except Exception as exc:
        from rt_runtime.errors import ExcavatorRtError

        if not isinstance(exc, ExcavatorRtError):
            raise
        _refuse(args, str(exc))
        return 2
    print(json.dumps(report) if args.json else _text(report))
    return 0 if report["status"] == "done" else 1


def _refuse(args: Any, text: str) -> None:
    import json

    if args.json:
        print(json.dumps({"status": "error", "error": text}))
    else:
        print(f"excavator-rt hil: {text}")


def _operator(args: Any, rig: Rig) -> dict[str, Any]:
    if args.demos is None or args.out is None:
        raise ConfigurationError("--operator needs --demos N and --out DIR")
    if not 1 <= args.demos <= 1000:
        raise ConfigurationError(f"--demos {args.demos}: allowed 1..1000")
    t0 = time.perf_counter()
    demos = [
        run_operator_demo(rig, args.seed + k, args.out, fault=_fault(args, rig))
        for k in range(args.demos)
    ]
    durations = [d.duration_s for d in demos]
    return {
        "status": "done" if all(d.status == "done" for d in demos) else "fault",
        "rig": rig.name,
        "out": str(args.out),
        "demos": [d.to_json() for d in demos],
        "operator_mean_cycle_s": float(np.mean(durations)),
        "wall_s": time.perf_counter() - t0,
    }


def _taught(args: Any, rig: Rig) -> dict[str, Any]:
    lead = not args.no_lead
    run, job = run_taught(
        rig, args.teach, trace_path=args.trace, fault=_fault(args, rig), lead=lead
    )
    tr = run.tracking
    goal = {"cylinders_max_mm": 3.0, "swing_max_deg": 0.3}
    cyl_max = max(mx for mx, _ in tr.cylinders_mm.values())
    report: dict[str, Any] = {
        "status": run.status,
        "fault": run.fault,
        "rig": rig.name,
        "taught": str(args.teach),
        "cycles_total": job.n_cycles,
        "T_s": job.duration_s,
        "velocity_lead_s": list(velocity_lead_s(rig)) if lead else None,
        "velocity_lead2_s2": list(velocity_lead2_s2(rig)) if lead else None,
        **tr.to_json(),
        "goal": goal,
        "goal_met": {
            "cylinders": bool(cyl_max <= goal["cylinders_max_mm"]),
            "swing": bool(tr.swing_max_deg <= goal["swing_max_deg"]),
        },
        "sim_s": float(run.truth.t_s[-1] - run.truth.t_s[0]) if len(run.truth.t_s) else 0.0,
        "wall_s": run.wall_s,
        "overruns": run.result.overruns if run.result is not None else 0,
    }
    if args.trace:
        report["trace"] = str(args.trace)
    return report


def _text(report: dict[str, Any]) -> str:
    if "demos" in report:
        mean_s = report["operator_mean_cycle_s"]
        lines = [
            f"HIL operator on {report['rig']}: {len(report['demos'])} demonstrations in "
            f"{report['out']} ({report['status']}), mean cycle {mean_s:.2f} s"
        ]
        lines += [
            f"  seed {d['seed']}: pace {d['speed']:.2f}, {d['duration_s']:.2f} s, {d['csv']}, "
            f"{d['trace']}" + (f" ({d['fault']})" if d["fault"] else "")
            for d in report["demos"]
        ]
        return "\n".join(lines)
    t = report["tracking"]
    lines = [
        f"HIL taught trench on {report['rig']} ({report['cycles_total']} cycles, "
        f"{report['T_s']:.1f} s): {report['status']}"
        + (f" ({report['fault']})" if report["fault"] else ""),
    ]
    for name in axes.ARM_AXES:
        lines.append(f"  {name:6s} max {t[name]['max_mm']:.3f} mm, rms {t[name]['rms_mm']:.3f} mm")
    sw = report["swing"]
    lines.append(
        f"  swing  max {sw['max_deg']:.3f} deg, rms {sw['rms_deg']:.3f} deg, overshoot "
        f"{sw['overshoot_deg']:.3f} deg"
    )
    lines.append(f"  tip error max {report['tip_error_max_mm']:.1f} mm")
    met = report["goal_met"]
    lines.append(
        f"  goals: cylinders max <= 3 mm {'met' if met['cylinders'] else 'NOT met'}, "
        f"swing max <= 0.3 deg {'met' if met['swing'] else 'NOT met'}"
    )
    return "\n".join(lines)
