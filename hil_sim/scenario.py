"""Scenario runner: a trench task on a rig, executed by the executor through the master on the HIL.

Role: what ``excavator-rt hil`` and the HIL tests run. A :class:`Scenario` names the task, the
rig, the transport (lockstep or real time), the feed-forward, faults to inject and where to write
the trace; :func:`run_scenario` returns the report (:mod:`hil_sim.report` keys).

Flow (closed loop, Yao Fig. 5): the :class:`~rt_runtime.control.executor.Executor` runs the
trench session in the fixed-rate loop: it plans one dig at a time from the material the session
believes is left, streams lead-in, approach, enter, the dig, lift-out and dump through the limit
guard, and records the tip path reconstructed from the drives' reported strokes into the session
(``session.record``). After each recorded dig (``on_dig_done``) the HIL cuts its own terrain with
the *true* tip path of the dig's SYNCs, which is what the report's ``coverage_error`` and
``overdig_max_mm`` measure. The arm starts at the planner's dump pose, or at the first dig's entry
with ``start_at_entry`` (short tests: the first dig is planned before the HIL starts and left
pending in the session, so the executor digs it at once).

Lockstep runs plan in-process on simulated time (deterministic); real-time runs use the
executor's planner process and the default RT settings, applied before the drives boot (each
refusal is in ``loop.rt``).

The report is built from the executor's telemetry: each motion (telemetry ``segment``) and each
run of holding or stopping becomes one :class:`~hil_sim.report.Segment`, joined with the HIL's
truth by SYNC count; ``tracking`` counts the cycles that streamed a motion.

Faults (:class:`FaultSpec`) are switched on ``at_s`` seconds after the executor's first cycle,
from its per-cycle hook, on the HIL's drive node (:mod:`hil_sim.drives`).
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import can
import numpy as np
from numpy.typing import NDArray

from hil_sim.report import (
    AXES,
    Segment,
    plot_report,
    profile_errors,
    tip_reference,
    tracking_figures,
)
from hil_sim.sim import FaultKind, LockstepHil, Truth
from hil_sim.terrain import Terrain
from rt_runtime.canbus import CanMaster
from rt_runtime.control import (
    Clock,
    FixedRateLoop,
    LoopConfig,
    RtReport,
    RtSettings,
    apply_rt,
    restore_rt,
)
from rt_runtime.control.executor import (
    DigRecord,
    Executor,
    ExecutorConfig,
    ExecutorResult,
    Phase,
    executor_telemetry,
)
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.rig import Rig, load_rig

__all__ = ["FaultSpec", "Scenario", "run_scenario"]

FloatArray = NDArray[np.float64]

#: RT settings of a lockstep run: simulated time needs none of them.
_NO_RT = RtSettings(
    sched_fifo_priority=None, lock_memory=False, cpu=None, timer_slack_ns=None, freeze_gc=False
)

#: Goals of issue 6 (mm), for the report's ``goal`` block.
GOALS_MM = {"electric": {"max_mm": 1.0, "rms_mm": 0.3}, "hydraulic": {"max_mm": 3.0}}


@dataclass(frozen=True, slots=True)
class FaultSpec:
    """A fault to inject.

    Attributes:
        kind: What fails (:class:`~hil_sim.sim.FaultKind`).
        axis: Axis name (``boom``, ``stick``, ``bucket``).
        at_s: Seconds after the first motion starts.
    """

    kind: FaultKind
    axis: str
    at_s: float

    def axis_index(self) -> int:
        """Index of :attr:`axis`.

        Raises:
            ConfigurationError: Unknown axis name.
        """
        if self.axis not in AXES:
            raise ConfigurationError(f"fault axis {self.axis!r}; allowed: {', '.join(AXES)}")
        return AXES.index(self.axis)


@dataclass(frozen=True, slots=True)
class Scenario:
    """One HIL run.

    Attributes:
        task: Task name (``A``..``D``) or TOML file.
        rig: Rig profile name or file.
        feedforward: Velocity feed-forward 0x60B1 on.
        realtime: Real-time HIL in its own process over 127.0.0.1 instead of lockstep.
        trace_path: Write the CAN trace (``.blf`` / ``.asc``), or None.
        max_digs: Stop after this many digs (None: the whole task).
        start_at_entry: Start the arm at the first dig's entry pose (skip the first approach).
        faults: Faults to inject.
        period_s: SYNC period.
        planner: One-shot planner (``pinn`` or ``pso``).
        plot_dir: Write the figures here, or None.
        keep_frames: Keep every bus frame in the report object (lockstep; determinism tests).
        vcu: Put the VCU model on the bus.
    """

    task: str = "A"
    rig: str = "scale_model"
    feedforward: bool = True
    realtime: bool = False
    trace_path: str | None = None
    max_digs: int | None = None
    start_at_entry: bool = False
    faults: tuple[FaultSpec, ...] = field(default_factory=tuple)
    period_s: float = 0.002
    planner: str = "pinn"
    plot_dir: str | None = None
    keep_frames: bool = False
    vcu: bool = True


class _Hil(Protocol):
    clock: Any
    master_bus: can.BusABC

    def inject(self, kind: FaultKind, axis: int) -> None: ...

    def cut(self, sync_from: int, sync_to: int) -> float: ...

    def finish(self) -> tuple[Truth, Any, list[tuple[int, bytes]], dict[str, Any]]: ...

    def close(self) -> None: ...


class _LockstepAdapter:
    """The lockstep HIL behind the scenario's small interface."""

    def __init__(self, hil: LockstepHil) -> None:
        self.hil = hil
        self.clock = hil.clock
        self.master_bus: can.BusABC = hil.master_bus

    def inject(self, kind: FaultKind, axis: int) -> None:
        self.hil.inject(kind, axis)

    def cut(self, sync_from: int, sync_to: int) -> float:
        return self.hil.core.cut(sync_from, sync_to)

    def finish(self) -> tuple[Truth, Any, list[tuple[int, bytes]], dict[str, Any]]:
        core = self.hil.core
        material = core.terrain.material if core.terrain is not None else None
        return core.truth(), material, list(core.frames), {}

    def close(self) -> None:
        self.hil.close()


def _open_hil(sc: Scenario, rig: Rig, q0: FloatArray, terrain: Terrain | None) -> _Hil:
    if sc.realtime:
        from hil_sim.realtime import RealtimeHilProcess

        return RealtimeHilProcess.start(
            rig_name=sc.rig,
            q0_rad=q0,
            terrain=terrain,
            period_s=sc.period_s,
            vcu=sc.vcu,
            trace_path=sc.trace_path,
        )
    hil = LockstepHil(
        rig,
        q0,
        terrain,
        period_s=sc.period_s,
        vcu=sc.vcu,
        keep_frames=sc.keep_frames,
        trace_path=sc.trace_path,
    )
    return _LockstepAdapter(hil)


#: Telemetry rows are kept for this much simulated time (every cycle of a whole task).
_MAX_RUN_S = 400.0
#: Kinds of the telemetry's phases in the report's segments.
_PHASE_KIND = {
    Phase.WAIT: "hold",
    Phase.SETTLE: "hold",
    Phase.STOP: "stop",
}


def run_scenario(sc: Scenario) -> dict[str, Any]:
    """Plan and execute ``sc`` with the executor against the HIL; return the report.

    Returns:
        The report (DESIGN.md "Reports" keys for ``excavator-rt hil --json`` plus extras; the
        bus frames under ``_frames`` when ``keep_frames``, to be dropped before JSON output).

    Raises:
        ConfigurationError: Bad rig, task, or fault.
        PlanningError: The planner cannot plan the task's first dig (``start_at_entry``).
        CommunicationError, DriveFault: Boot or enable failed.
    """
    from rt_runtime.planning.trench import TrenchPlanner, load_task

    wall0 = time.perf_counter()
    rig = load_rig(sc.rig)
    task = load_task(sc.task, rig)
    plan_t0 = time.perf_counter()
    planner = TrenchPlanner(rig, sc.planner)
    session = planner.start(task)
    q_dump = np.asarray(planner.dump_pose_rad, dtype=np.float64)
    q0 = q_dump
    if sc.start_at_entry:
        # The session keeps the dig pending: the executor digs it first, from its entry.
        first_dig = session.next_dig()
        if first_dig is not None:
            q0 = np.asarray(first_dig.problem.q_start_rad, dtype=np.float64)
    plan_us = (time.perf_counter() - plan_t0) * 1e6
    terrain = Terrain(
        rig.ground_y_m, (float(session.x_lo), float(session.x_hi)), rig.bucket.width_m
    )
    initial_material = terrain.material
    faults = [(f, f.axis_index()) for f in sc.faults]
    hil = _open_hil(sc, rig, q0, terrain)
    cut_m3: dict[int, float] = {}
    result: ExecutorResult | None = None
    rt_report: RtReport | None = None
    error = ""
    bus_load = None
    try:
        clock: Clock = hil.clock
        master = CanMaster(hil.master_bus, rig, period_s=sc.period_s, react_to_faults=False)
        # RT settings are applied here, before boot, not by the loop: mlockall and the garbage
        # collection of a process with the planner loaded take ~0.1 s, which between enable and
        # the first cycle would trip the drives' SYNC watchdog and heartbeat consumer.
        loop = FixedRateLoop(
            clock,
            LoopConfig(period_s=sc.period_s, rt=_NO_RT),
            executor_telemetry(int(_MAX_RUN_S / sc.period_s)),
        )
        exec_start: list[float] = []
        injected: set[int] = set()

        def on_cycle(_sync: int, now_s: float) -> None:
            if not exec_start:
                exec_start.append(now_s)
            for i, (spec, axis) in enumerate(faults):
                if i not in injected and now_s - exec_start[0] >= spec.at_s:
                    injected.add(i)
                    hil.inject(spec.kind, axis)

        def on_dig_done(record: DigRecord) -> None:
            # The HIL's terrain loses what the true tip path cut, before the next dig runs.
            cut_m3[record.index] = hil.cut(record.sync_first, record.sync_last)

        # Built before boot: on a real-time clock it starts the planner process (not at a
        # real-time priority, and not in the gap between enable and the first cycle).
        executor = Executor(
            master,
            rig,
            loop,
            session,
            ExecutorConfig(feedforward=sc.feedforward, max_digs=sc.max_digs),
            on_dig_done=on_dig_done,
            on_cycle=on_cycle,
        )
        rt_report = apply_rt(RtSettings()) if sc.realtime else None
        try:
            master.boot(clock.now, 2.0)
            master.enable(clock.now, 2.0)
            result = executor.run()
        finally:
            executor.close()
            if rt_report is not None:
                restore_rt(rt_report)
        plan_us += result.plan_us
        bus_load = master.bus_load()
    except PlanningError as exc:
        error = str(exc)
    finally:
        truth, material, frames, extra = hil.finish()
        hil.close()
    wall_s = time.perf_counter() - wall0

    segments = _segments(rig, result, truth) if result is not None else []
    report: dict[str, Any] = {}
    report.update(tracking_figures(segments))
    digs_fig = tracking_figures(segments, digs_only=True)
    report["tracking_digs"] = {
        "tracking": digs_fig["tracking"],
        "tip_error_max_mm": digs_fig["tip_error_max_mm"],
    }
    if material is not None:
        report.update(profile_errors(initial_material, material, session.design))
    records = result.digs if result is not None else ()
    report["digs"] = [
        {
            "index": r.index,
            "type": r.dig_type,
            "T_s": r.T_s,
            "planned_volume_L": r.planned_volume_m3 * 1e3,
            "measured_volume_L": r.measured_volume_m3 * 1e3,
            "cut_volume_L": cut_m3.get(r.index, math.nan) * 1e3,
            "planned_energy_Wh": r.planned_energy_j / 3600.0,
            "plan_us": r.plan_us,
        }
        for r in records
    ]
    report["energy_Wh"] = truth.energy_j / 3600.0
    report["wall_s"] = wall_s
    report["overruns"] = result.overruns if result is not None else 0
    if result is not None:
        report["status"] = result.status.name.lower()
        report["fault"] = result.fault
        report["loop"] = result.loop.summary()
        if rt_report is not None:
            report["loop"]["rt"] = rt_report.as_dict()
    else:
        report["status"] = "planning_error"
        report["fault"] = error
    report["emcys"] = [
        {"node_id": e.node_id, "code": f"0x{int(e.code):04X}", "description": e.description}
        for e in (result.emcys if result is not None else ())
    ]
    report["rig"] = rig.name
    report["task"] = task.name
    report["feedforward"] = sc.feedforward
    report["transport"] = "realtime" if sc.realtime else "lockstep"
    report["period_s"] = sc.period_s
    report["sim_s"] = float(truth.t_s[-1] - truth.t_s[0]) if len(truth.t_s) > 1 else 0.0
    report["plan_total_us"] = plan_us
    kind = rig.cylinders.kind
    report["goal"] = GOALS_MM.get(kind, {})
    can_block: dict[str, Any] = {}
    if bus_load is not None:
        can_block["bus_load"] = {"nominal": bus_load.nominal, "worst_case": bus_load.worst_case}
    if result is not None and sc.realtime:
        rtt = result.telemetry["rtt_s"]
        rtt = rtt[np.isfinite(rtt)] * 1e6
        if rtt.size:
            can_block["sync_rtt_us"] = {
                "p50": float(np.percentile(rtt, 50)),
                "p99": float(np.percentile(rtt, 99)),
                "p999": float(np.percentile(rtt, 99.9)),
                "max": float(np.max(rtt)),
            }
    report["can"] = can_block
    report.update(extra)
    try:
        plan = session.finish(plan_us)
        report["plan"] = {
            "coverage_error": plan.coverage_error,
            "overdig_max_mm": plan.overdig_max_m * 1e3,
            "digs": len(plan.digs),
        }
        design = plan.design
    except PlanningError:
        design = session.design
    if sc.plot_dir is not None:
        surface = None
        if material is not None:
            xs = np.linspace(float(session.x_lo), float(session.x_hi), 600)
            surface = np.stack([xs, _surface_of(material, xs)], axis=1)
        files = plot_report(
            segments, sc.plot_dir, design=design, surface_m=surface, title=f"task {task.name}:"
        )
        report["plots"] = [str(p) for p in files]
    if sc.trace_path is not None:
        report["trace"] = str(Path(sc.trace_path))
    if sc.keep_frames:
        report["_frames"] = frames
    return report


def _segments(rig: Rig, result: ExecutorResult, truth: Truth) -> list[Segment]:
    """The executor's telemetry cut into motions (one per segment or phase run), with truth."""
    tel = result.telemetry
    sync = tel["sync"]
    rows = np.flatnonzero(sync >= 1)
    if rows.size == 0:
        return []
    phase = tel["phase"][rows]
    segment = tel["segment"][rows]
    change = np.flatnonzero((np.diff(phase) != 0) | (np.diff(segment) != 0)) + 1
    bounds = np.concatenate([[0], change, [rows.size]])
    index = {int(s): i for i, s in enumerate(truth.sync_index)}
    out: list[Segment] = []
    for a, b in itertools.pairwise(bounds):
        sel_rows = rows[a:b]
        ph = Phase(int(phase[a]))
        kind = _PHASE_KIND.get(ph, ph.name.lower())
        sync_idx = sync[sel_rows].astype(np.int64)
        sel = np.array([index.get(int(s), -1) for s in sync_idx], dtype=np.int64)
        ok = sel >= 0
        selc = np.where(ok, sel, 0)
        nan3 = np.full((len(sel), 3), np.nan)
        q_ref = tel["q_ref_rad"][sel_rows]
        power = np.where(ok, truth.power_w[selc] if len(truth.power_w) else 0.0, np.nan)
        out.append(
            Segment(
                kind=kind,
                index=int(tel["dig"][sel_rows[0]]) if ph is Phase.DIG else -1,
                sync_index=sync_idx,
                t_s=np.where(ok, truth.t_s[selc], np.nan),
                tracking=tel["tracking"][sel_rows] & ok,
                q_ref_rad=q_ref,
                stroke_ref_m=tel["stroke_ref_m"][sel_rows],
                stroke_true_m=np.where(ok[:, None], truth.stroke_m[selc], nan3),
                q_true_rad=np.where(ok[:, None], truth.q_rad[selc], nan3),
                stroke_reported_m=tel["stroke_fb_m"][sel_rows],
                velocity_reported_m_s=tel["vel_fb_m_s"][sel_rows],
                tip_ref_m=tip_reference(rig, q_ref, np.zeros(len(sel))),
                tip_true_m=np.where(ok[:, None], truth.tip_xy_m[selc], np.nan),
                power_w=power,
            )
        )
    return out


def _surface_of(material: Any, xs: FloatArray) -> FloatArray:
    """Top of the material polygon above each x (NaN where there is none)."""
    import shapely

    top = float(material.bounds[3]) + 1.0
    bottom = float(material.bounds[1]) - 1.0
    lines = shapely.linestrings([[(x, bottom), (x, top)] for x in xs])
    out = np.full(len(xs), np.nan)
    for i, line in enumerate(lines):
        hit = material.intersection(line)
        if not hit.is_empty:
            out[i] = float(hit.bounds[3])
    return out
