"""``excavator-rt bench hil``: how fast the lockstep HIL runs, and whose time a period is.

Registered as a ``bench`` subcommand through the ``excavator_rt.bench`` entry point ``hil``::

    excavator-rt bench hil [--task A] [--rig scale_model] [--max-digs N] [--seconds S]
                           [--cpu] [--json]

Two measurements, each wall clock (``time.perf_counter_ns``) unless ``--cpu``:

* ``task``: the task's digs executed by the runtime (loop, executor, master) against the
  lockstep HIL (:func:`hil_sim.harness.scenario.run_scenario`), as ``excavator-rt hil`` runs them.
  Reported: machine time (simulated seconds of SYNCs) over wall time, and per SYNC period the
  HIL's own time (frame handling, the nodes' answers, the servo sub-steps, its bus end;
  :class:`hil_sim.harness.lockstep.HilCost`) apart from the rest of the period, the runtime's
  share (its loop, controllers, master and bus end, and planning between digs).
* ``step``: the HIL's models alone, without a bus: :class:`hil_sim.sim.HilCore` fed by direct
  calls with what the master sends each period (three RPDO1s, ``VCU_Command``, SYNC), replaying
  held-out verified digs of the scale model (``onnx/pinn_downward_heldout.npz``) through the
  soil of a terrain for ``--seconds`` of machine time. Per period: ``frames`` (the frames
  delivered to every node, their TPDOs and the VCU's status, and the nodes' time supervision)
  and ``advance`` (the servo sub-steps: three drive cascades, the plant, the VCU).

Numbers depend on the machine and its load: compare runs on the same machine, in the same run.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil_sim.sim import COB_SYNC, HilCore
from hil_sim.terrain import Terrain
from rt_runtime import actuation
from rt_runtime.actuation import AXES
from rt_runtime.canbus.vcu import VcuClient, VcuCommand
from rt_runtime.reports import Distribution
from rt_runtime.rig import Rig, load_rig
from rt_runtime.trajectory import sextic

__all__ = [
    "BenchHilReport",
    "GaoCalibration",
    "StepCost",
    "TaskCalibration",
    "TaskSpeed",
    "add_parser",
    "bench_hil",
    "bench_step",
    "calibrate_gao",
    "calibrate_task",
    "format_report",
    "run",
]

#: SYNC period of both measurements (the demo's).
PERIOD_S = 2e-3
#: The held-out digs replayed by the step measurement (planned for the scale model).
HELDOUT = Path(__file__).resolve().parents[2] / "onnx" / "pinn_downward_heldout.npz"
_STEP_RIG = "scale_model"
#: Seeds of the test bench's stroke sensors over which ``bench hil`` runs Gao's path again:
#: the calibration holds for a sensor, not for one draw of its linearity phase and noise.
GAO_SEEDS = tuple(range(1, 11))
_COB_NMT = 0x000
_RPDO1 = struct.Struct("<ii")
_CONTROLWORD_MODE = struct.Struct("<Hb")


def add_parser(bench_sub: Any) -> argparse.ArgumentParser:
    """Add ``hil`` to the ``bench`` subparsers (the ``excavator_rt.bench`` entry point)."""
    p: argparse.ArgumentParser = bench_sub.add_parser(
        "hil",
        help="lockstep HIL speed: machine time / wall time, HIL and runtime time per period",
        description=__doc__.split("\n")[0] if __doc__ else None,
    )
    p.add_argument("--task", default="A", help="task A..D or a task TOML file (default A)")
    p.add_argument("--rig", default="scale_model", help="rig profile for the task run")
    p.add_argument("--max-digs", type=int, default=None, help="stop the task run after N digs")
    p.add_argument(
        "--seconds",
        type=float,
        default=10.0,
        help="machine time of the model-only step measurement [s] (0: skip it)",
    )
    p.add_argument(
        "--cpu", action="store_true", help="step measurement in thread CPU time (loaded hosts)"
    )
    p.add_argument(
        "--no-calibration",
        dest="calibration",
        action="store_false",
        help="skip the calibration runs against the papers (gao, task_a; ~2 min)",
    )
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Handler of ``excavator-rt bench hil``; 0 when the task run finished, 1 otherwise."""
    if not (math.isfinite(args.seconds) and args.seconds >= 0.0):
        print(f"excavator-rt bench hil: --seconds {args.seconds} must be >= 0")
        return 2
    report = bench_hil(
        task=args.task,
        rig=args.rig,
        max_digs=args.max_digs,
        step_seconds=args.seconds,
        cpu=args.cpu,
        calibration=args.calibration,
    )
    print(json.dumps(report.to_json()) if args.json else format_report(report))
    return 0 if report.task.status == "done" else 1


@dataclass(frozen=True, slots=True)
class TaskSpeed:
    """The task run on the lockstep HIL (``task`` of the report).

    Attributes:
        task: Task name.
        rig: Rig profile name.
        status: How the run ended (the HIL report's ``status``).
        digs: Digs run.
        sim_s: Machine time (s).
        wall_s: Wall time of the run (s).
        period_s: SYNC period (s).
        hil_us: The HIL's own time per period (us; p50, p99, max).
        runtime_us: The runtime's time per period (us; p50, p99, max).
        hil_s: The HIL's time summed over the periods (s).
        runtime_s: The runtime's time summed (s).
        periods_wall_s: The periods' wall time summed (s; the denominator of ``hil_share``).
    """

    task: str
    rig: str
    status: str
    digs: int
    sim_s: float
    wall_s: float
    period_s: float
    hil_us: Distribution
    runtime_us: Distribution
    hil_s: float
    runtime_s: float
    periods_wall_s: float

    @property
    def speed(self) -> float:
        """Machine time over wall time (NaN for no wall time)."""
        return self.sim_s / self.wall_s if self.wall_s > 0.0 else math.nan

    @property
    def hil_share(self) -> float:
        """The HIL's share of the periods' wall time (NaN for no period)."""
        return self.hil_s / self.periods_wall_s if self.periods_wall_s > 0 else math.nan

    def to_json(self) -> dict[str, Any]:
        """The keys of README ``bench hil --json`` ``task``."""
        return {
            "task": self.task,
            "rig": self.rig,
            "status": self.status,
            "digs": self.digs,
            "sim_s": self.sim_s,
            "wall_s": self.wall_s,
            "speed": self.speed,
            "period_s": self.period_s,
            "hil_us": self.hil_us.to_json(),
            "runtime_us": self.runtime_us.to_json(),
            "hil_s": self.hil_s,
            "runtime_s": self.runtime_s,
            "hil_share": self.hil_share,
        }


@dataclass(frozen=True, slots=True)
class StepCost:
    """The HIL's models alone, per period (``step`` of the report).

    Attributes:
        periods: Periods replayed.
        digs: Held-out digs replayed (the last one possibly in part).
        clock: ``wall`` or ``cpu`` (thread CPU time).
        frames_us: Frame handling per period (us; p50, p99, max).
        advance_us: Servo sub-steps per period (us).
        total_us: Both (us).
    """

    periods: int
    digs: int
    clock: str
    frames_us: Distribution
    advance_us: Distribution
    total_us: Distribution

    def to_json(self) -> dict[str, Any]:
        """The keys of README ``bench hil --json`` ``step``."""
        return {
            "periods": self.periods,
            "digs": self.digs,
            "clock": self.clock,
            "frames_us": self.frames_us.to_json(),
            "advance_us": self.advance_us.to_json(),
            "total_us": self.total_us.to_json(),
        }


@dataclass(frozen=True, slots=True)
class GaoCalibration:
    """Gao's path on the imperfect test bench, his controller and ours (``gao``).

    Attributes:
        p: Per axis ``max_mm`` (and ``rms_mm``) with Gao's proportional loop (``--controller
            p``); the paper measured +-3 mm (Fig. 12).
        csp: The same with ours: CSP with velocity feed-forward, the valve drives' overlap
            compensation and the host's loop.
        host_gain_1_s: The host loop's gain with Gao's loop (1/s), the highest over the axes.
        path: ``gao`` (Table 2, 3 s segments) or the reduced path's name.
        host_gain_csp_1_s: The host loop's gain with ours (1/s), the highest over the axes.
        host_gains_1_s: Per controller (``p``, ``csp``) the host loop's gain per axis (1/s).
        seeds: Over other seeds of the stroke sensors (``seeds``: the list), per controller
            and axis the smallest and largest ``max_mm`` (``min_mm``, ``max_mm``); empty when
            none were run.
    """

    p: dict[str, dict[str, float]]
    csp: dict[str, dict[str, float]]
    host_gain_1_s: float
    path: str
    host_gain_csp_1_s: float = 0.0
    host_gains_1_s: dict[str, dict[str, float]] = field(default_factory=dict)
    seeds: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The keys of README ``bench hil --json`` ``gao``."""
        return {"p": self.p, "csp": self.csp, "host_gain_1_s": self.host_gain_1_s,
                "host_gain_csp_1_s": self.host_gain_csp_1_s, "path": self.path,
                "host_gains_1_s": self.host_gains_1_s, "seeds": self.seeds}  # fmt: skip


@dataclass(frozen=True, slots=True)
class TaskCalibration:
    """Task A on the imperfect scale model against Yao's measurements (``task_a``).

    Attributes:
        energy_ratio: Executed over planned drive energy of the digs, minus 1 (Yao: 0.13).
        energy_ratio_digs: The same per dig.
        load_ratio: Bucket load over planned V_p (Yao: 4.63 / 5.07 L = 0.91).
        table6_open: Yao Table 6 errors (fractions) with the planner fed the tip paths only.
        table6_closed: The same with the planner on the profile scanner's surface.
        coverage_open: The HIL's coverage error, open loop.
        coverage_closed: The same, closed loop.
        tracking_max_mm: Largest tracking error over the axes and both runs (truth, mm).
        tracking_rms_mm: Largest RMS tracking error over the axes and both runs (mm).
        digs_open: Digs of the open-loop run.
        digs_closed: Digs of the closed-loop run.
    """

    energy_ratio: float
    energy_ratio_digs: tuple[float, ...]
    load_ratio: float
    table6_open: dict[str, float]
    table6_closed: dict[str, float]
    coverage_open: float
    coverage_closed: float
    tracking_max_mm: float
    tracking_rms_mm: float
    digs_open: int
    digs_closed: int

    def to_json(self) -> dict[str, Any]:
        """The keys of README ``bench hil --json`` ``task_a``."""
        return {
            "energy_ratio": self.energy_ratio,
            "energy_ratio_digs": list(self.energy_ratio_digs),
            "load_ratio": self.load_ratio,
            "table6_open": self.table6_open,
            "table6_closed": self.table6_closed,
            "coverage_open": self.coverage_open,
            "coverage_closed": self.coverage_closed,
            "tracking_max_mm": self.tracking_max_mm,
            "tracking_rms_mm": self.tracking_rms_mm,
            "digs_open": self.digs_open,
            "digs_closed": self.digs_closed,
        }


@dataclass(frozen=True, slots=True)
class BenchHilReport:
    """The report of ``excavator-rt bench hil``.

    Attributes:
        task: The task run on the lockstep HIL.
        step: The models alone, None when skipped (``--seconds 0``).
        gao: Gao's path on the imperfect bench, None when skipped (``--no-calibration``).
        task_a: Task A on the imperfect scale model, None when skipped.
    """

    task: TaskSpeed
    step: StepCost | None = None
    gao: GaoCalibration | None = None
    task_a: TaskCalibration | None = None

    def to_json(self) -> dict[str, Any]:
        """``{"task", "step", "gao", "task_a"}`` (each but ``task`` where measured)."""
        out: dict[str, Any] = {"task": self.task.to_json()}
        if self.step is not None:
            out["step"] = self.step.to_json()
        if self.gao is not None:
            out["gao"] = self.gao.to_json()
        if self.task_a is not None:
            out["task_a"] = self.task_a.to_json()
        return out


def calibrate_gao(
    joints_deg: tuple[tuple[float, float, float], ...] = (),
    host_gain_1_s: float | tuple[float, ...] | None = None,
    host_gain_csp_1_s: float | tuple[float, ...] | None = None,
    seeds: tuple[int, ...] = (),
) -> GaoCalibration:
    """Gao's path (or the key points ``joints_deg``, a reduced path) on the imperfect test
    bench with Gao's proportional loop and with ours, each with its own host loop gains (one
    for every axis or one per axis; None:
    :data:`~hil_sim.harness.scenario.GAO_HOST_GAIN_1_S` for Gao's,
    :data:`~hil_sim.harness.scenario.CSP_HOST_GAIN_1_S` for ours); with ``seeds`` both
    again with each of those seeds of the stroke sensors (``hil.seed``: linearity phase and
    noise), their spread in :attr:`GaoCalibration.seeds`.

    Raises:
        ConfigurationError: Bad key points or seed.
    """
    from hil_sim.harness.scenario import (
        CSP_HOST_GAIN_1_S,
        GAO_HOST_GAIN_1_S,
        PathScenario,
        run_path_scenario,
    )

    gains = {
        "p": GAO_HOST_GAIN_1_S if host_gain_1_s is None else host_gain_1_s,
        "csp": CSP_HOST_GAIN_1_S if host_gain_csp_1_s is None else host_gain_csp_1_s,
    }
    path = "joints" if joints_deg else "gao"
    out: dict[str, dict[str, dict[str, float]]] = {}
    per_axis: dict[str, dict[str, float]] = {}
    spread: dict[str, Any] = {"seeds": list(seeds)} if seeds else {}
    for controller, gain in gains.items():
        for seed in (None, *seeds):
            sc = PathScenario(
                path=path,
                joints_deg=joints_deg,
                imperfect=True,
                controller=controller,
                host_gain_1_s=gain,
                hil_seed=seed,
            )
            report = run_path_scenario(sc).report
            if seed is None:
                per_axis[controller] = dict(report.host_gain_per_axis_1_s)
                out[controller] = {
                    axis: {"max_mm": fig.max_mm, "rms_mm": fig.rms_mm}
                    for axis, fig in report.tracking.items()
                }
                continue
            figs = spread.setdefault(controller, {})
            for axis, fig in report.tracking.items():
                lo_hi = figs.setdefault(axis, {"min_mm": math.inf, "max_mm": -math.inf})
                lo_hi["min_mm"] = min(lo_hi["min_mm"], fig.max_mm)
                lo_hi["max_mm"] = max(lo_hi["max_mm"], fig.max_mm)
    return GaoCalibration(
        out["p"],
        out["csp"],
        max(per_axis["p"].values()),
        path,
        max(per_axis["csp"].values()),
        per_axis,
        spread,
    )


def calibrate_task(task: str = "A", max_digs: int | None = None) -> TaskCalibration:
    """Task ``task`` on the imperfect scale model, the planner on the tip paths (open loop)
    and on the profile scanner's surface (closed loop).

    Raises:
        ConfigurationError: Bad task.
        RuntimeError: A run on which the granular material was not modelled.
    """
    from hil_sim.harness.scenario import Scenario, run_scenario

    runs = []
    for scanner in (False, True):
        sc = Scenario(task=task, max_digs=max_digs, imperfect=True, scanner=scanner)
        runs.append(run_scenario(sc).report)
    open_r, closed_r = runs
    mat_open, mat_closed = open_r.material, closed_r.material
    if mat_open is None or mat_closed is None or mat_open.table6 is None:
        raise RuntimeError("the calibration runs carry no material figures")
    table6_closed = mat_closed.table6
    assert table6_closed is not None
    figs = [fig for r in runs for fig in r.tracking.values()]
    return TaskCalibration(
        energy_ratio=mat_open.energy_ratio,
        energy_ratio_digs=mat_open.energy_ratio_digs,
        load_ratio=mat_open.load_ratio,
        table6_open=mat_open.table6.to_json(),
        table6_closed=table6_closed.to_json(),
        coverage_open=math.nan if open_r.coverage_error is None else open_r.coverage_error,
        coverage_closed=math.nan if closed_r.coverage_error is None else closed_r.coverage_error,
        tracking_max_mm=max(f.max_mm for f in figs),
        tracking_rms_mm=max(f.rms_mm for f in figs),
        digs_open=len(open_r.digs),
        digs_closed=len(closed_r.digs),
    )


def bench_hil(
    *,
    task: str = "A",
    rig: str = "scale_model",
    max_digs: int | None = None,
    step_seconds: float = 10.0,
    cpu: bool = False,
    calibration: bool = False,
) -> BenchHilReport:
    """Both measurements (see the module docstring), and with ``calibration`` the runs
    against the papers (:func:`calibrate_gao`, :func:`calibrate_task`).

    Raises:
        ConfigurationError: Bad task or rig.
        CommunicationError, DriveFault: The drives did not boot or enable.
        RuntimeError: The task ran on a HIL that is not the lockstep one.
    """
    from hil_sim.harness.scenario import Scenario, run_scenario

    t0 = time.perf_counter()
    report = run_scenario(Scenario(task=task, rig=rig, max_digs=max_digs)).report
    run_s = time.perf_counter() - t0
    cost = report.hil_lockstep
    if cost is None:
        raise RuntimeError("the task run carries no lockstep cost: it did not run in lockstep")
    speed = TaskSpeed(
        task=report.task,
        rig=report.rig,
        status=report.status,
        digs=len(report.digs),
        sim_s=report.sim_s,
        wall_s=run_s,
        period_s=report.period_s,
        hil_us=cost.hil_us,
        runtime_us=cost.runtime_us,
        hil_s=cost.hil_s,
        runtime_s=cost.runtime_s,
        periods_wall_s=cost.wall_s,
    )
    step = bench_step(load_rig(_STEP_RIG), step_seconds, cpu=cpu) if step_seconds > 0.0 else None
    if not calibration:
        return BenchHilReport(speed, step)
    return BenchHilReport(speed, step, calibrate_gao(seeds=GAO_SEEDS), calibrate_task())


def _reference(rig: Rig, dig: int) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                             NDArray[np.float64], float]:  # fmt: skip
    """Per-period joint start, stroke targets and stroke rates of one held-out dig, and its
    ground height."""
    data = np.load(HELDOUT)
    x, y = data["X"][dig], data["Y"][dig]
    coeffs = sextic.sextic_coefficients(x[:3], x[3:6], y[:3], y[3])
    t = np.arange(0.0, float(y[3]) + 0.2, PERIOD_S)
    _, q, qd, _, _ = sextic.evaluate(coeffs, y[3], s_grid=np.clip(t / y[3], 0.0, 1.0))
    s_ref = actuation.joint_to_stroke(rig, q, check_limits=False)
    v_ref = actuation.stroke_jacobian(rig, q, check_limits=False) * qd
    return q[0], s_ref, v_ref, float(x[6])


def bench_step(rig: Rig, seconds: float, *, cpu: bool = False) -> StepCost:
    """The models alone, replaying held-out digs for ``seconds`` of machine time.

    Raises:
        RuntimeError: A drive left OPERATION ENABLED (the replay is then not a valid run).
    """
    ids = [dict(rig.can.node_ids)[name] for name in AXES]
    vcu_frame = VcuClient(rig.can.vcu_node_id).command_frame(VcuCommand(enable=True))
    clock = time.thread_time_ns if cpu else time.perf_counter_ns
    n_periods = max(1, round(seconds / PERIOD_S))
    frames_ns = np.zeros(n_periods, dtype=np.int64)
    advance_ns = np.zeros(n_periods, dtype=np.int64)
    k = 0
    dig = 0
    n_digs = len(np.load(HELDOUT)["X"])
    while k < n_periods:
        q0, s_ref, v_ref, ground_y_m = _reference(rig, dig % n_digs)
        terrain = Terrain(ground_y_m, (-0.5, 1.5), rig.bucket.width_m)
        m = HilCore(rig, q0, terrain, period_s=PERIOD_S)
        now = 0.0
        m.pending_frames(now)  # boot-up
        m.on_frame(_COB_NMT, bytes([0x01, 0x00]), now)  # start all nodes
        for word in (0x06, 0x07, 0x0F):
            for node_id in ids:
                m.on_frame(0x300 + node_id, _CONTROLWORD_MODE.pack(word, 8), now)
        m.on_frame(*vcu_frame, now)
        m.advance(PERIOD_S)
        now += PERIOD_S
        rpdo = [
            [_RPDO1.pack(*pair) for pair in zip(s_axis, v_axis, strict=True)]
            for s_axis, v_axis in zip(
                np.round(s_ref * 1e6).astype(np.int64).T.tolist(),
                np.round(v_ref * 1e6).astype(np.int64).T.tolist(),
                strict=True,
            )
        ]
        for i in range(min(len(s_ref), n_periods - k)):
            t0 = clock()
            for axis, node_id in enumerate(ids):
                m.on_frame(0x200 + node_id, rpdo[axis][i], now)
            m.on_frame(*vcu_frame, now)
            m.on_frame(COB_SYNC, b"", now)
            m.pending_frames(now)
            t1 = clock()
            m.advance(PERIOD_S)
            t2 = clock()
            frames_ns[k] = t1 - t0
            advance_ns[k] = t2 - t1
            k += 1
            now += PERIOD_S
        if not all(n.firmware.state.name == "OPERATION_ENABLED" for n in m.nodes):
            raise RuntimeError(f"dig {dig}: a drive left OPERATION ENABLED; the run is not valid")
        dig += 1
    return StepCost(
        periods=n_periods,
        digs=dig,
        clock="cpu" if cpu else "wall",
        frames_us=Distribution.spread(frames_ns * 1e-3),
        advance_us=Distribution.spread(advance_ns * 1e-3),
        total_us=Distribution.spread((frames_ns + advance_ns) * 1e-3),
    )


def format_report(report: BenchHilReport) -> str:
    """The report as text."""
    t = report.task
    lines = [
        f"excavator-rt bench hil: task {t.task} on {t.rig}, lockstep, {t.status}",
        f"  {t.digs} digs, {t.sim_s:.1f} s machine time in {t.wall_s:.1f} s wall: "
        f"{t.speed:.2f}x real time",
        f"  per {t.period_s * 1e3:g} ms period (p50 / p99 us): HIL {t.hil_us.p50:.0f} / "
        f"{t.hil_us.p99:.0f}, runtime {t.runtime_us.p50:.0f} / {t.runtime_us.p99:.0f}",
        f"  HIL {t.hil_s:.1f} s, runtime {t.runtime_s:.1f} s (HIL share {t.hil_share:.0%})",
    ]
    step = report.step
    if step is not None:
        lines.append(
            f"  models alone ({step.clock} clock, {step.periods} periods of "
            f"{PERIOD_S * 1e3:g} ms, p50 / p99 us): advance {step.advance_us.p50:.0f} / "
            f"{step.advance_us.p99:.0f}, frames {step.frames_us.p50:.0f} / "
            f"{step.frames_us.p99:.0f}, total {step.total_us.p50:.0f} / {step.total_us.p99:.0f}"
        )
    gao = report.gao
    if gao is not None:
        for name, figs, controller in (
            ("p (Gao)", gao.p, "p"),
            ("csp (ours)", gao.csp, "csp"),
        ):
            gains = gao.host_gains_1_s.get(controller, {})
            gain_text = ", ".join(f"{axis} {g:g}" for axis, g in gains.items())
            lines.append(
                f"  Gao path, imperfect bench, {name}, host loop ({gain_text}) 1/s: max "
                + ", ".join(f"{axis} {f['max_mm']:.2f}" for axis, f in figs.items())
                + " mm (paper +-3 mm)"
            )
            spread = gao.seeds.get(controller)
            if spread:
                lines.append(
                    f"    over sensor seeds {gao.seeds['seeds'][0]}-{gao.seeds['seeds'][-1]}: "
                    + ", ".join(
                        f"{axis} {f['min_mm']:.2f}-{f['max_mm']:.2f}" for axis, f in spread.items()
                    )
                    + " mm"
                )
    ta = report.task_a
    if ta is not None:
        lines.append(
            f"  task A, imperfect scale model: energy {ta.energy_ratio:+.1%} against the plan "
            f"(Yao +13 %), bucket load {ta.load_ratio:.1%} of V_p (Yao 91 %), tracking max "
            f"{ta.tracking_max_mm:.2f} mm"
        )
        for name, t6, cov in (
            ("open", ta.table6_open, ta.coverage_open),
            ("closed", ta.table6_closed, ta.coverage_closed),
        ):
            lines.append(
                f"  Table 6 {name} loop: "
                + ", ".join(f"{k} {v:.1%}" for k, v in t6.items())
                + f" (Yao L 6.7, D 6.7, beta1 5.0, beta2 11.7 %), coverage {cov:.1%}"
            )
    return "\n".join(lines)
