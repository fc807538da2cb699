"""Scenario runner: a trench task on a rig, planned and executed through the master against the HIL.

Role: what ``excavator-rt hil`` and the HIL tests run. A :class:`Scenario` names the task, the
rig, the transport (lockstep or real time), the streamer's feed-forward, faults to inject and
where to write the trace; :func:`run_scenario` returns the report (:mod:`hil_sim.report` keys).

Flow (closed loop, Yao Fig. 5): the trench planner plans one dig at a time from the material it
believes is left; the streamer executes the transitions that lead to the dig's entry, then the
dig; the tip path reconstructed from the drives' reported strokes goes back to the planner
(``session.record``), while the HIL cuts its own terrain with the true tip path, which is what
the report's ``coverage_error`` and ``overdig_max_mm`` measure. The arm starts at the planner's
dump pose (or at the first dig's entry with ``start_at_entry``, for short tests).

Transitions: ``session.next_dig`` appends the transitions that lead into the dig (lift out,
dump, approach, enter; ruckig rest to rest, no waypoints) to ``session.steps``; the runner
streams them as they are, then the dig, so the arm never jumps.

Faults (:class:`FaultSpec`) are switched on ``at_s`` seconds after the first motion starts, from
the streamer's per-cycle hook, on the HIL's drive node (:mod:`hil_sim.drives`).
"""

from __future__ import annotations

import functools
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
    StreamResult,
    StreamStatus,
    TrajectoryStreamer,
    ruckig_motion,
    sextic_motion,
)
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.rig import Rig, load_rig

__all__ = ["FaultSpec", "Scenario", "run_scenario"]

FloatArray = NDArray[np.float64]

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


def run_scenario(sc: Scenario) -> dict[str, Any]:
    """Plan and execute ``sc`` through the master against the HIL; return the report.

    Returns:
        The report (DESIGN.md "Reports" keys for ``excavator-rt hil --json`` plus extras; the
        bus frames under ``_frames`` when ``keep_frames``, to be dropped before JSON output).

    Raises:
        ConfigurationError: Bad rig, task, or fault.
        PlanningError: The planner cannot plan the task.
        CommunicationError, DriveFault: Boot or enable failed.
    """
    from rt_runtime.planning.trench import Transition, TravelMove, TrenchPlanner, load_task

    wall0 = time.perf_counter()
    rig = load_rig(sc.rig)
    task = load_task(sc.task, rig)
    plan_t0 = time.perf_counter()
    planner = TrenchPlanner(rig, sc.planner)
    session = planner.start(task)
    q_dump = np.asarray(planner.dump_pose_rad, dtype=np.float64)
    plan_us = (time.perf_counter() - plan_t0) * 1e6
    t0 = time.perf_counter()
    first_dig = session.next_dig()
    plan_us += (time.perf_counter() - t0) * 1e6
    q0 = np.asarray(first_dig.problem.q_start_rad) if (sc.start_at_entry and first_dig) else q_dump
    terrain = Terrain(
        rig.ground_y_m, (float(session.x_lo), float(session.x_hi)), rig.bucket.width_m
    )
    initial_material = terrain.material
    faults = [(f, f.axis_index()) for f in sc.faults]
    hil = _open_hil(sc, rig, q0, terrain)
    segments: list[Segment] = []
    results: list[tuple[str, int, StreamResult, float]] = []
    status = StreamStatus.DONE
    fault_text = ""
    error = ""
    done_digs: list[dict[str, Any]] = []
    try:
        clock: Clock = hil.clock
        master = CanMaster(hil.master_bus, rig, period_s=sc.period_s)
        exec_start: list[float] = []
        injected: set[int] = set()

        def on_cycle(_sync: int, now_s: float) -> None:
            if not exec_start:
                exec_start.append(now_s)
            for i, (spec, axis) in enumerate(faults):
                if i not in injected and now_s - exec_start[0] >= spec.at_s:
                    injected.add(i)
                    hil.inject(spec.kind, axis)

        streamer = TrajectoryStreamer(
            master, rig, clock, feedforward=sc.feedforward, on_cycle=on_cycle
        )
        streamer.start(timeout_s=2.0)
        machine_x = 0.0
        seen = 0  # session.steps[seen:] are the transitions leading into ``dig``
        dig = first_dig
        first = True
        while dig is not None and status is StreamStatus.DONE:
            new_steps = [] if (first and sc.start_at_entry) else session.steps[seen:]
            moves: list[tuple[str, Any]] = []
            for step in new_steps:
                if isinstance(step, TravelMove):
                    raise ConfigurationError(
                        f"task {task.name} needs crawler travel ({step.distance_m:+.3f} m); "
                        "the HIL streamer does not drive the VCU yet"
                    )
                if isinstance(step, Transition):
                    moves.append((step.kind, ruckig_motion(step.trajectory(rig))))
            first = False
            for kind, motion in moves:
                res = streamer.stream(motion)
                results.append((kind, -1, res, machine_x))
                if res.status is not StreamStatus.DONE:
                    status, fault_text = res.status, res.fault
                    break
            if status is not StreamStatus.DONE:
                break
            res = streamer.stream(sextic_motion(dig.trajectory()))
            results.append(("dig", dig.index, res, machine_x))
            if res.status is not StreamStatus.DONE:
                status, fault_text = res.status, res.fault
                break
            cut_m3 = streamer.hold_while(
                functools.partial(hil.cut, int(res.sync_index[0]), int(res.sync_index[-1]))
            )
            path = res.tip_path_m.copy()
            path[:, 0] += machine_x
            recorded_m3 = session.record(dig, path)
            seen = len(session.steps)
            done_digs.append(
                {
                    "index": dig.index,
                    "type": dig.dig_type.name.lower(),
                    "T_s": dig.T_s,
                    "planned_volume_L": dig.volume_m3 * 1e3,
                    "measured_volume_L": recorded_m3 * 1e3,
                    "cut_volume_L": cut_m3 * 1e3,
                    "planned_energy_Wh": dig.energy_j / 3600.0,
                }
            )
            if sc.max_digs is not None and len(done_digs) >= sc.max_digs:
                break
            t0 = time.perf_counter()
            dig = streamer.hold_while(session.next_dig)
            plan_us += (time.perf_counter() - t0) * 1e6
        if status is StreamStatus.DONE:
            results.append(("hold", -1, streamer.hold(0.05), machine_x))
            streamer.shutdown()
        bus_load = master.bus_load()
    except PlanningError as exc:
        error = str(exc)
        bus_load = None
    finally:
        truth, material, frames, extra = hil.finish()
        hil.close()
    wall_s = time.perf_counter() - wall0

    index = {int(s): i for i, s in enumerate(truth.sync_index)}
    for kind, dig_index, res, mx in results:
        sel = np.array([index.get(int(s), -1) for s in res.sync_index], dtype=np.int64)
        ok = sel >= 0
        selc = np.where(ok, sel, 0)
        nan3 = np.full((len(sel), 3), np.nan)
        s_true = np.where(ok[:, None], truth.stroke_m[selc], nan3)
        q_true = np.where(ok[:, None], truth.q_rad[selc], nan3)
        tip_true = np.where(ok[:, None], truth.tip_xy_m[selc], np.nan)
        power = np.where(ok, truth.power_w[selc] if len(truth.power_w) else 0.0, np.nan)
        segments.append(
            Segment(
                kind=kind,
                index=dig_index,
                sync_index=res.sync_index,
                t_s=np.where(ok, truth.t_s[selc], np.nan),
                tracking=res.tracking & ok,
                q_ref_rad=res.q_ref_rad,
                stroke_ref_m=res.stroke_ref_m,
                stroke_true_m=s_true,
                q_true_rad=q_true,
                stroke_reported_m=res.stroke_reported_m,
                velocity_reported_m_s=res.velocity_reported_m_s,
                tip_ref_m=tip_reference(rig, res.q_ref_rad, np.full(len(sel), mx)),
                tip_true_m=tip_true,
                power_w=power,
            )
        )
    report: dict[str, Any] = {}
    report.update(tracking_figures(segments))
    digs_fig = tracking_figures(segments, digs_only=True)
    report["tracking_digs"] = {
        "tracking": digs_fig["tracking"],
        "tip_error_max_mm": digs_fig["tip_error_max_mm"],
    }
    if material is not None:
        report.update(profile_errors(initial_material, material, session.design))
    report["digs"] = done_digs
    report["energy_Wh"] = truth.energy_j / 3600.0
    report["wall_s"] = wall_s
    report["overruns"] = int(sum(r.overruns for _, _, r, _ in results))
    report["status"] = status.name.lower() if not error else "planning_error"
    report["fault"] = fault_text or error
    report["emcys"] = [
        {"node_id": e.node_id, "code": f"0x{int(e.code):04X}", "description": e.description}
        for _, _, r, _ in results
        for e in r.emcys
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
    rtt = np.concatenate([r.rtt_s for _, _, r, _ in results]) if results else np.zeros(0)
    rtt = rtt[np.isfinite(rtt)] * 1e6
    can_block: dict[str, Any] = {}
    if bus_load is not None:
        can_block["bus_load"] = {"nominal": bus_load.nominal, "worst_case": bus_load.worst_case}
    if rtt.size and sc.realtime:
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
