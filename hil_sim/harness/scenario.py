"""Scenario runner: a trench task on a rig, executed by the executor through the master on the HIL.

Role: what ``excavator-rt hil`` and the HIL tests run. A :class:`Scenario` names the task, the
rig, the transport (lockstep or real time), the feed-forward, faults to inject and where to write
the trace; :func:`run_scenario` returns the run with its report
(:class:`~hil_sim.harness.reports.HilReport`).

Flow (closed loop, Yao Fig. 5): the :class:`~rt_runtime.control.executor.Executor` runs the
trench session in the fixed-rate loop: it plans one dig at a time from the material the session
believes is left, streams the cycle into each dig (lift out, dump, approach, enter) and the dig
through the limit guard (after the last dig its lift-out and dump), and records the tip path
reconstructed from the drives' reported strokes into the session (``session.record``). After
each recorded dig (``on_dig_done``) the HIL cuts its own terrain with the *true* tip path of the
dig's SYNCs, which is what the report's ``coverage_error`` and ``overdig_max_mm`` measure. The
arm starts at the planner's home pose (in the rig's spoil zone), or at the first dig's entry
with ``start_at_entry`` (short tests: the first dig is planned before the HIL starts and left
pending in the session, so the executor digs it at once).

Lockstep runs plan in-process on simulated time (deterministic); real-time runs use the
executor's planner process and the default RT settings, applied before the drives boot (each
refusal is in ``loop.rt``).

The report is built from the executor's telemetry: each motion (telemetry ``segment``) and each
run of holding or stopping becomes one :class:`~hil_sim.report.Segment`, joined with the HIL's
truth by SYNC count; ``tracking`` counts the cycles that streamed a motion.

Faults (:class:`FaultSpec`, ``docs/faults.md``) are switched on ``at_s`` seconds after the
executor's first cycle, from its per-cycle hook: a drive fault on the HIL's drive node
(:mod:`hil_sim.drives`), a bus fault on the transport's wire (:mod:`hil_sim.busfaults`: in
the lockstep transport, or in the real-time HIL's process), a loop stall by moving the lockstep
clock on with the executor's thread held. The real-time HIL takes the drive and wire faults but
the adapter's bus-off (the master's); a killed planner process and an unwritable job store are
the campaign's (:mod:`hil_sim.harness.campaign`, on the daemon's
runner).

Prescribed paths (:class:`PathScenario`, :func:`run_path_scenario`). A joint
path through key points (Gao/Yang's mixed-order interpolation, :mod:`rt_runtime.trajectory.
mixed_order`) runs on the executor as a :class:`~rt_runtime.control.planner_worker.PathJob`:
from the arm's start pose a CONNECT move to the path's start, the path (phase PATH), settle, DONE.
No terrain and no soil (a free arm). ``path="gao"`` is Gao Table 2's six joint key points with
3 s segments and the smoothest order pattern of Gao's three (the rule of ``excavator-rt interp``,
:func:`~rt_runtime.trajectory.mixed_order.choose_smoothest`). On a rig whose joint ranges do not
hold Table 2's angles they are mapped linearly from ``test_bench``'s ranges into the rig's
(:func:`scale_key_points`; the report says so under ``path.scaled_from``). The report has the
same tracking keys as a task's, ``tracking_path`` (the same figures over the path alone, without
the connect move), and ``path`` (orders, knots, key points, their cylinder strokes and the
largest difference between the commanded stroke and the key point's stroke at each key time).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import queue
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import can
import numpy as np
from numpy.typing import NDArray

from hil_sim.harness.lockstep import LockstepCost, LockstepHil
from hil_sim.harness.reports import (
    CanFigures,
    DigResult,
    EmcyRecord,
    HilProcessFigures,
    HilReport,
    MaterialFigures,
    PathFigures,
    PlanFigures,
    StrategyPeaks,
    Table6,
    TrackingGoal,
)
from hil_sim.report import (
    AXES,
    Segment,
    plot_report,
    profile_errors,
    tip_reference,
    tracking_figures,
)
from hil_sim.scanner import ProfileScanner
from hil_sim.sim import FaultKind, Truth
from hil_sim.terrain import Terrain
from rt_runtime import actuation
from rt_runtime import axes as rig_axes
from rt_runtime.canbus import BusLoad, CanMaster
from rt_runtime.control import Clock, FixedRateLoop, LoopConfig, RtSettings
from rt_runtime.control.executor import (
    DigRecord,
    Executor,
    ExecutorConfig,
    ExecutorResult,
    Phase,
    executor_telemetry,
)
from rt_runtime.control.hardware import per_axis_gain
from rt_runtime.control.planner_worker import PathJob, PendingScan, PolynomialMotion
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.reports import BusLoadFigures, Distribution
from rt_runtime.rig import Rig, load_rig
from rt_runtime.trajectory.mixed_order import GAO_TABLE2_JOINTS_DEG

if TYPE_CHECKING:
    from hil_sim.harness.realtime import RealtimeHilProcess

__all__ = [
    "GAO_TABLE2_JOINTS_DEG",
    "NO_RT",
    "STALL_MS",
    "FaultSpec",
    "HilRun",
    "KeyPointPath",
    "PathScenario",
    "Scenario",
    "key_point_path",
    "load_key_points",
    "run_path_scenario",
    "run_scenario",
    "scale_key_points",
]

FloatArray = NDArray[np.float64]

#: RT settings of a lockstep run: simulated time needs none of them.
NO_RT = RtSettings(
    sched_fifo_priority=None, lock_memory=False, cpu=None, timer_slack_ns=None, freeze_gc=False
)

#: Tracking goals per cylinder kind (the report's ``goal``).
GOALS_MM = {
    "electric": TrackingGoal(max_mm=1.0, rms_mm=0.3),
    "hydraulic": TrackingGoal(max_mm=3.0),
}


@dataclass(frozen=True, slots=True)
class FaultSpec:
    """A fault to inject (``--inject KIND:TARGET:AT_S[:PARAM]``).

    Attributes:
        kind: What fails (:class:`~hil_sim.sim.FaultKind`).
        axis: The target: an axis name (``boom``, ``stick``, ``bucket``), ``bus`` or ``host``
            (what the kind takes: :attr:`FaultKind.targets`).
        at_s: Seconds after the first motion starts.
        param: The kind's parameter (a loss rate, a delay in ms, a glitch in mm, a stall in ms,
            ...); None: its default.
    """

    kind: FaultKind
    axis: str
    at_s: float
    param: float | None = None

    def axis_index(self) -> int:
        """Index of :attr:`axis`, -1 for ``bus`` and ``host``.

        Raises:
            ConfigurationError: A target the kind does not take, or a parameter that is not
                a finite number.
        """
        targets = self.kind.targets
        if self.axis not in targets:
            raise ConfigurationError(
                f"fault {self.kind.label}: target {self.axis!r}; allowed: {', '.join(targets)}"
            )
        if self.param is not None and not math.isfinite(self.param):
            raise ConfigurationError(f"fault {self.kind.label}: parameter {self.param} not finite")
        return AXES.index(self.axis) if self.axis in AXES else -1


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
        keep_frames: Keep every bus frame in the run (:attr:`HilRun.frames`; lockstep;
            determinism tests).
        vcu: Put the VCU model on the bus.
        imperfect: Apply the profile's ``[hil]`` imperfections (True), the ideal HIL
            (False), or the profile's own ``hil.enabled`` (None).
        controller: ``csp`` (target stroke with velocity feed-forward when ``feedforward``)
            or ``p`` (Gao's plain proportional displacement loop: no feed-forward).
        host_gain_1_s: Gain of the host's proportional displacement loop over the bus, added
            to the velocity offset (1/s; 0: none; see ``ExecutorConfig.correction_gain_1_s``):
            one for every axis, or a tuple as :func:`host_gains` takes it.
        scanner: Emulate the rig's profile scanner (``[hil.scanner]``) and plan each dig on
            the surface it measured after the last (lockstep: over the HIL's terrain at the
            record; real time: the HIL process's look, fetched off the loop's thread while the
            arm holds at the exit); False: plan on the measured tip paths alone.
        material: The granular material in the pit, one of the profile's
            ``[hil.materials]``; None: the profile's ``hil.material``.
        hil_seed: Seed of the HIL's stroke sensors (linearity phase and noise, ``hil.seed``);
            None: the profile's.
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
    imperfect: bool | None = None
    controller: str = "csp"
    host_gain_1_s: float | tuple[float, ...] = 0.0
    scanner: bool = False
    material: str | None = None
    hil_seed: int | None = None


@dataclass(frozen=True, slots=True, eq=False)
class _HilEnd:
    """What a HIL hands back when it stops: the truth, the terrain, frames and its own cost."""

    truth: Truth
    material: Any
    frames: list[tuple[int, bytes]]
    hil_lockstep: LockstepCost | None = None
    hil_process: HilProcessFigures | None = None
    terrain: _TerrainEnd | None = None


@dataclass(frozen=True, slots=True, eq=False)
class _TerrainEnd:
    """The HIL's terrain at the end of a run: its sampled surface (m) and what its cuts swept,
    kept, let fall back and slumped (m^3)."""

    x_m: FloatArray
    y_m: FloatArray
    swept_m3: float
    load_m3: float
    fallback_m3: float
    slumped_m3: float

    @classmethod
    def of(cls, terrain: Terrain) -> _TerrainEnd:
        return cls(
            terrain.surface_x_m,
            terrain.surface_y_m,
            terrain.swept_m3,
            terrain.load_m3,
            terrain.fallback_m3,
            terrain.slumped_m3,
        )


class _Hil(Protocol):
    clock: Any
    master_bus: can.BusABC

    def inject(self, kind: FaultKind, axis: int, param: float | None) -> None: ...

    def cut(self, sync_from: int, sync_to: int) -> float: ...

    def finish(self) -> _HilEnd: ...

    def close(self) -> None: ...


class _LockstepAdapter:
    """The lockstep HIL behind the scenario's small interface."""

    def __init__(self, hil: LockstepHil) -> None:
        self.hil = hil
        self.clock = hil.clock
        self.master_bus: can.BusABC = hil.master_bus

    def inject(self, kind: FaultKind, axis: int, param: float | None) -> None:
        if kind is FaultKind.LOOP_STALL:  # the executor's thread, between two cycles
            clock = self.hil.clock
            clock.sleep_until(clock.now() + (STALL_MS if param is None else param) * 1e-3)
        else:
            self.hil.inject(kind, axis, param)

    def cut(self, sync_from: int, sync_to: int) -> float:
        return self.hil.core.cut(sync_from, sync_to)

    def finish(self) -> _HilEnd:
        core = self.hil.core
        material = core.terrain.material if core.terrain is not None else None
        return _HilEnd(
            core.truth(),
            material,
            list(core.frames),
            hil_lockstep=self.hil.cost.summary(),
            terrain=_TerrainEnd.of(core.terrain) if core.terrain is not None else None,
        )

    def close(self) -> None:
        self.hil.close()


class _RealtimeAdapter:
    """The real-time HIL process behind the scenario's small interface."""

    def __init__(self, hil: RealtimeHilProcess) -> None:
        self.hil = hil
        self.clock = hil.clock
        self.master_bus: can.BusABC = hil.master_bus

    def inject(self, kind: FaultKind, axis: int, param: float | None) -> None:
        self.hil.inject(kind, axis, param)

    def cut(self, sync_from: int, sync_to: int) -> float:
        return self.hil.cut(sync_from, sync_to)

    def finish(self) -> _HilEnd:
        truth, material, frames, extra = self.hil.finish()
        process = extra.get("hil_process")
        ground = extra.get("terrain")
        return _HilEnd(
            truth,
            material,
            frames,
            hil_process=HilProcessFigures.from_json(process) if process is not None else None,
            terrain=_TerrainEnd(**ground) if ground is not None else None,
        )

    def close(self) -> None:
        self.hil.close()


def _open_hil(
    sc: Scenario | PathScenario, rig: Rig, q0: FloatArray, terrain: Terrain | None
) -> _Hil:
    if sc.realtime:
        from hil_sim.harness.realtime import RealtimeHilProcess

        return _RealtimeAdapter(
            RealtimeHilProcess.start(
                rig_name=sc.rig,
                q0_rad=q0,
                terrain=terrain,
                period_s=sc.period_s,
                vcu=sc.vcu,
                trace_path=sc.trace_path,
                scanner=bool(getattr(sc, "scanner", False)),
            )
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
    Phase.PATH: "path",
}


_OnCycle = Callable[[int, float], None]


#: A loop stall's default length (ms).
STALL_MS = 50.0


def _checked_faults(sc: Scenario | PathScenario) -> list[tuple[FaultSpec, int]]:
    """Each fault with its target's index, checked before anything moves.

    Raises:
        ConfigurationError: A target the kind does not take, a kind this transport cannot
            inject (the real-time HIL takes the drive and wire faults; the adapter's bus-off,
            a loop stall and a killed planner process run in lockstep or in ``hil campaign``).
    """
    out = []
    for f in sc.faults:
        index = f.axis_index()
        if f.kind in (
            FaultKind.PLANNER_KILLED,
            FaultKind.STORE_UNWRITABLE,
            FaultKind.MODEL_CHANGED,
            FaultKind.DAEMON_CRASH,
        ):
            raise ConfigurationError(
                f"{f.kind.label} needs the daemon's runner (its planner process, its job "
                f"store): run it with `excavator-rt hil campaign --kinds {f.kind.label}`"
            )
        if sc.realtime and f.kind.on_rig_pc:
            raise ConfigurationError(
                f"{f.kind.label} acts on the rig PC's side (the master's adapter or loop): the "
                "real-time HIL injects drive and wire faults; run it in lockstep (without "
                "--realtime) or in `hil campaign`"
            )
        out.append((f, index))
    return out


def _fault_injector(hil: _Hil, faults: list[tuple[FaultSpec, int]]) -> _OnCycle:
    """The executor's per-cycle hook that switches each fault on ``at_s`` after the first cycle."""
    start: list[float] = []
    injected: set[int] = set()

    def on_cycle(_sync: int, now_s: float) -> None:
        if not start:
            start.append(now_s)
        for i, (spec, axis) in enumerate(faults):
            if i not in injected and now_s - start[0] >= spec.at_s:
                injected.add(i)
                hil.inject(spec.kind, axis, spec.param)

    return on_cycle


def _execute(
    sc: Scenario | PathScenario,
    rig: Rig,
    hil: _Hil,
    faults: list[tuple[FaultSpec, int]],
    run_s: float,
    make_executor: Callable[[CanMaster, FixedRateLoop, _OnCycle], Executor],
) -> tuple[ExecutorResult, BusLoad]:
    """Boot and enable the drives on ``hil``'s bus and run the executor ``make_executor`` builds.

    The executor is built before boot: on a real-time clock it starts the planner process (not
    at a real-time priority, and not in the gap between enable and the first cycle). The RT
    settings are acquired before boot too (:meth:`FixedRateLoop.acquire_rt`): mlockall and the
    garbage collection of a process with the planner loaded take ~0.1 s, which between enable
    and the first cycle would trip the drives' SYNC watchdog and heartbeat consumer. Lockstep
    runs on simulated time and asks the OS for nothing.

    Returns:
        The executor's result and the master's bus load.
    """
    clock: Clock = hil.clock
    master = CanMaster(
        hil.master_bus, _master_rig(sc, rig), period_s=sc.period_s, react_to_faults=False
    )
    loop = FixedRateLoop(
        clock,
        LoopConfig(period_s=sc.period_s, rt=RtSettings() if sc.realtime else NO_RT),
        executor_telemetry(int(run_s / sc.period_s)),
    )
    executor = make_executor(master, loop, _fault_injector(hil, faults))
    if sc.realtime:
        loop.acquire_rt()
    try:
        master.boot(clock.now, 2.0)
        master.enable(clock.now, 2.0)
        result = executor.run()
    finally:
        executor.close()
        loop.release_rt()
    return result, master.bus_load(vcu=sc.vcu)


@dataclass(frozen=True, slots=True)
class HilRun:
    """One HIL run: its report and what a report does not carry.

    Attributes:
        report: The report (DESIGN.md "Reports" keys of ``excavator-rt hil --json`` plus
            extras).
        frames: Every bus frame ``(arbitration_id, data)`` when the scenario kept them, else None.
    """

    report: HilReport
    frames: list[tuple[int, bytes]] | None = None

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object."""
        return self.report.to_json()


def _emcys(result: ExecutorResult | None) -> tuple[EmcyRecord, ...]:
    return tuple(
        EmcyRecord(e.node_id, int(e.code), e.description)
        for e in (result.emcys if result is not None else ())
    )


def _can_figures(
    sc: Scenario | PathScenario, result: ExecutorResult | None, bus_load: BusLoad | None
) -> CanFigures:
    """Bus load as the master counted it; on a real-time run the SYNC round trip as well."""
    rtt_us: Distribution | None = None
    if result is not None and sc.realtime:
        rtt = result.telemetry["rtt_s"]
        rtt = rtt[np.isfinite(rtt)] * 1e6
        if rtt.size:
            rtt_us = Distribution.of(rtt, tails=True)
    load = (
        BusLoadFigures(nominal=bus_load.nominal, worst=bus_load.worst_case)
        if bus_load is not None
        else None
    )
    return CanFigures(bus_load=load, sync_rtt_us=rtt_us)


def _sim_s(truth: Truth) -> float:
    return float(truth.t_s[-1] - truth.t_s[0]) if len(truth.t_s) > 1 else 0.0


def run_scenario(sc: Scenario) -> HilRun:
    """Plan and execute ``sc`` with the executor against the HIL; return the report.

    Returns:
        The run: its report (a task's: ``tracking_digs``, the profile figures where the HIL
        has a terrain, ``plan_total_us``, ``plan``) and the bus frames when ``keep_frames``.

    Raises:
        ConfigurationError: Bad rig, task, or fault.
        PlanningError: The planner cannot plan the task's first dig (``start_at_entry``).
        CommunicationError, DriveFault: Boot or enable failed.
    """
    from rt_runtime.planning.trench import TrenchPlanner, load_task

    wall0 = time.perf_counter()
    rig = scenario_rig(sc)
    gains = host_gains(sc.host_gain_1_s, rig)  # refused here, before the HIL starts
    task = load_task(sc.task, rig)
    plan_t0 = time.perf_counter()
    planner = TrenchPlanner(rig, sc.planner)
    trench = planner.start(task)
    q0 = np.asarray(planner.home_pose_rad, dtype=np.float64)
    if sc.start_at_entry:
        # The trench keeps the dig pending: the executor digs it first, from its entry.
        first_dig = trench.next_dig()
        if first_dig is not None:
            q0 = np.asarray(first_dig.problem.q_start_rad, dtype=np.float64)
    plan_us = (time.perf_counter() - plan_t0) * 1e6
    imperfections = rig.hil.active() if rig.hil is not None else None
    terrain = Terrain(
        rig.ground_y_m,
        (float(trench.x_lo), float(trench.x_hi)),
        rig.bucket.width_m,
        material=imperfections.material if imperfections is not None else None,
    )
    initial_material = terrain.material
    faults = _checked_faults(sc)
    scanner = _scanner(sc, rig, terrain)
    hil = _open_hil(sc, rig, q0, terrain)
    cut_m3: dict[int, float] = {}
    result: ExecutorResult | None = None
    error = ""
    bus_load = None
    scanned = [0, 0.0]  # the last SYNC the terrain was cut to, the volume of that cut
    scan_volumes: queue.SimpleQueue[float] = queue.SimpleQueue()  # real time: each look's cut
    try:

        def on_dig_done(record: DigRecord) -> None:
            # The HIL's terrain loses what the true tip path cut, before the next dig runs
            # (with a scanner, it was cut when the scanner looked).
            if scanner is not None:
                cut_m3[record.index] = float(scanned[1])
                return
            if sc.scanner:  # the real-time HIL's scanner: its look precedes the record
                try:
                    cut_m3[record.index] = scan_volumes.get(timeout=2.0 * SCAN_WAIT_S)
                except queue.Empty:
                    cut_m3[record.index] = math.nan
                return
            cut_m3[record.index] = hil.cut(record.sync_first, record.sync_last)

        def scan_surface() -> tuple[FloatArray, FloatArray] | PendingScan:
            # After a dig is recorded: the terrain cut by the true tip path since the last
            # look, then scanned; the planner plans the next dig on it. On the loop's thread:
            # the real-time HIL's look is fetched later, on the planner link's sender thread.
            if not isinstance(hil, _LockstepAdapter):
                return PendingScan(fetch_scan)
            assert scanner is not None
            last = hil.hil.core.sync_count
            scanned[1] = hil.cut(int(scanned[0]) + 1, last)
            scanned[0] = last
            return scanner.scan()

        def fetch_scan() -> tuple[FloatArray, FloatArray] | None:
            assert isinstance(hil, _RealtimeAdapter)
            got = hil.hil.scan(int(scanned[0]), timeout_s=SCAN_WAIT_S)
            if got is None:
                scan_volumes.put(math.nan)
                return None
            last, volume, x, y = got
            scanned[0] = last
            scan_volumes.put(volume)
            return x, y

        def make_executor(master: CanMaster, loop: FixedRateLoop, on_cycle: _OnCycle) -> Executor:
            return Executor(
                master,
                rig,
                loop,
                trench,
                ExecutorConfig(
                    feedforward=_feedforward(sc),
                    correction_gain_1_s=gains,
                    max_digs=sc.max_digs,
                ),
                on_dig_done=on_dig_done,
                on_cycle=on_cycle,
                surface_source=scan_surface if sc.scanner else None,
            )

        result, bus_load = _execute(sc, rig, hil, faults, _MAX_RUN_S, make_executor)
        plan_us += result.plan_us
    except PlanningError as exc:
        error = str(exc)
    finally:
        end = hil.finish()
        hil.close()
    wall_s = time.perf_counter() - wall0
    truth, material = end.truth, end.material

    segments = _segments(rig, result, truth) if result is not None else []
    figures = tracking_figures(segments)
    profile = (
        profile_errors(initial_material, material, trench.design) if material is not None else None
    )
    plan_figures: PlanFigures | None = None
    try:
        plan = trench.finish(plan_us)
        plan_figures = PlanFigures(plan.coverage_error, plan.overdig_max_m * 1e3, len(plan.digs))
        design = plan.design
    except PlanningError:
        design = trench.design
    dig_energy_j = _dig_energy_j(segments, sc.period_s)
    material_figures = (
        _material_figures(rig, task, result, dig_energy_j, terrain.granular.name, end.terrain)
        if result is not None and terrain.granular is not None and end.terrain is not None
        else None
    )
    plots: tuple[str, ...] | None = None
    if sc.plot_dir is not None:
        surface = None
        if material is not None:
            xs = np.linspace(float(trench.x_lo), float(trench.x_hi), 600)
            surface = np.stack([xs, _surface_of(material, xs)], axis=1)
        files = plot_report(
            segments, sc.plot_dir, design=design, surface_m=surface, title=f"task {task.name}:"
        )
        plots = tuple(str(p) for p in files)
    report = HilReport(
        task=task.name,
        rig=rig.name,
        transport=_transport(sc),
        feedforward=_feedforward(sc),
        controller=sc.controller,
        host_gain_1_s=max(gains),
        host_gain_per_axis_1_s=dict(zip(rig_axes.names(rig), gains, strict=True)),
        imperfect=rig.hil is not None and rig.hil.enabled,
        period_s=sc.period_s,
        status=result.status.name.lower() if result is not None else "planning_error",
        fault=result.fault if result is not None else error,
        tracking=figures.tracking,
        tip_error_max_mm=figures.tip_error_max_mm,
        cycles=figures.cycles,
        digs=tuple(
            DigResult(
                index=r.index,
                type=r.dig_type,
                T_s=r.T_s,
                planned_volume_L=r.planned_volume_m3 * 1e3,
                measured_volume_L=r.measured_volume_m3 * 1e3,
                cut_volume_L=cut_m3.get(r.index, math.nan) * 1e3,
                planned_energy_Wh=r.planned_energy_j / 3600.0,
                plan_us=r.plan_us,
                planned_ahead=r.planned_ahead,
                joined=r.joined,
                carried=r.carried,
                energy_Wh=dig_energy_j.get(r.index, math.nan) / 3600.0,
            )
            for r in (result.digs if result is not None else ())
        ),
        energy_Wh=truth.energy_j / 3600.0,
        sim_s=_sim_s(truth),
        wall_s=wall_s,
        overruns=result.overruns if result is not None else 0,
        emcys=_emcys(result),
        goal=GOALS_MM.get(rig.cylinders.kind, TrackingGoal()),
        can=_can_figures(sc, result, bus_load),
        loop=result.loop if result is not None else None,
        tracking_digs=tracking_figures(segments, digs_only=True),
        coverage_error=profile.coverage_error if profile is not None else None,
        overdig_max_mm=profile.overdig_max_mm if profile is not None else None,
        removed_area_m2=profile.removed_area_m2 if profile is not None else None,
        plan_total_us=plan_us,
        plan=plan_figures,
        hil_lockstep=end.hil_lockstep,
        hil_process=end.hil_process,
        plots=plots,
        trace=str(Path(sc.trace_path)) if sc.trace_path is not None else None,
        material=material_figures,
        scanner=scanner is not None,
    )
    return HilRun(report, end.frames if sc.keep_frames else None)


def _scanner(sc: Scenario, rig: Rig, terrain: Terrain) -> ProfileScanner | None:
    """The scenario's profile scanner over the lockstep HIL's terrain, or None (none asked,
    or a real-time run: the HIL process emulates it over its own terrain).

    Raises:
        ConfigurationError: A scanner asked of a rig whose profile has no ``[hil.scanner]``.
    """
    if not sc.scanner:
        return None
    spec = rig.hil.scanner if rig.hil is not None else None
    if spec is None or rig.hil is None:
        raise ConfigurationError(f"rig {rig.name} has no [hil.scanner] in its profile")
    if sc.realtime:
        return None
    return ProfileScanner(terrain, spec, seed=rig.hil.seed)


def _dig_energy_j(segments: list[Segment], period_s: float) -> dict[int, float]:
    """The plant's drive energy over each dig's cycles (J), by dig index."""
    out: dict[int, float] = {}
    for seg in segments:
        if seg.kind == "dig":
            out[seg.index] = out.get(seg.index, 0.0) + float(np.nansum(seg.power_w)) * period_s
    return out


def _material_figures(
    rig: Rig,
    task: Any,
    result: ExecutorResult,
    dig_energy_j: dict[int, float],
    material: str,
    terrain: _TerrainEnd,
) -> MaterialFigures:
    """Yao's material-flow figures of a task run on granular material ``material``: bucket
    load against V_p, executed against planned energy per dig, the finished trench (Table 6)
    from the HIL's terrain at the end."""
    from hil_sim.report import trench_shape

    digs = result.digs
    planned_l = sum(r.planned_volume_m3 for r in digs) * 1e3
    executed = tuple(
        dig_energy_j.get(r.index, math.nan) / r.planned_energy_j - 1.0
        if r.planned_energy_j > 0.0
        else math.nan
        for r in digs
    )
    planned_e = sum(r.planned_energy_j for r in digs)
    executed_e = sum(dig_energy_j.get(r.index, math.nan) for r in digs)
    length, depth, b_far, b_near = trench_shape(terrain.x_m, terrain.y_m, rig.ground_y_m)
    table6 = Table6(
        L=abs(length - task.length_m) / task.length_m,
        D=abs(depth - task.depth_m) / task.depth_m,
        beta1=abs(b_far - task.beta1_rad) / task.beta1_rad,
        beta2=abs(b_near - task.beta2_rad) / task.beta2_rad,
    )
    return MaterialFigures(
        name=material,
        swept_L=terrain.swept_m3 * 1e3,
        load_L=terrain.load_m3 * 1e3,
        planned_L=planned_l,
        load_ratio=terrain.load_m3 * 1e3 / planned_l if planned_l > 0.0 else math.nan,
        energy_ratio=executed_e / planned_e - 1.0 if planned_e > 0.0 else math.nan,
        energy_ratio_digs=executed,
        fallback_L=terrain.fallback_m3 * 1e3,
        slumped_L=terrain.slumped_m3 * 1e3,
        table6=table6,
    )


def _transport(sc: Scenario | PathScenario) -> str:
    return "realtime" if sc.realtime else "lockstep"


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


# -- prescribed paths -----------------------------------------------------------------------------

#: Gao's segment duration (s).
GAO_SEGMENT_S = 3.0
#: The rig Table 2's angles belong to (the source range of :func:`scale_key_points`).
GAO_RIG = "test_bench"


#: ``orders="auto"`` for fewer than Gao's five segments (his patterns need five): the lowest
#: orders that give a square system (sum of orders = 3 m + 2 for m segments, cubic ends), so
#: the path has zero velocity and acceleration at both ends and is C2 inside.
_SHORT_PATTERNS: dict[int, tuple[str, ...]] = {
    1: ("5",),
    2: ("4-4",),
    3: ("3-5-3",),
    4: ("3-4-4-3",),
}


@dataclass(frozen=True, slots=True)
class PathScenario:
    """One HIL run of a prescribed joint path.

    Attributes:
        path: ``gao`` (Table 2), a JSON file (see :func:`load_key_points`), or ``joints`` with
            :attr:`joints_deg`.
        rig: Rig profile name or file.
        joints_deg: Key points (deg: boom, stick, bucket) when ``path == "joints"``.
        orders: ``auto`` (the smoothest of Gao's three patterns; with fewer than five segments
            the lowest orders that fit, see ``_SHORT_PATTERNS``) or a pattern such as
            ``3-4-5-4-3`` (widened to the segment count as ``interp`` does).
        durations_s: Segment durations (s); None: the file's, else 3 s each.
        start_deg: The arm's start pose (deg); None: the path's first key point (the executor
            still connects the quantised measured pose to it).
        feedforward: Velocity feed-forward 0x60B1 on.
        realtime: Real-time HIL in its own process over 127.0.0.1 instead of lockstep.
        trace_path: Write the CAN trace (``.blf`` / ``.asc``), or None.
        period_s: SYNC period.
        plot_dir: Write the figures here, or None.
        keep_frames: Keep every bus frame in the run (:attr:`HilRun.frames`; lockstep).
        vcu: Put the VCU model on the bus (off: a bench arm has no travel or swing).
        faults: Faults to inject (as :class:`Scenario`).
        imperfect: As :class:`Scenario`.
        controller: As :class:`Scenario`.
        host_gain_1_s: As :class:`Scenario`.
        hil_seed: As :class:`Scenario`.
    """

    path: str = "gao"
    rig: str = "test_bench"
    joints_deg: tuple[tuple[float, float, float], ...] = ()
    orders: str = "auto"
    durations_s: tuple[float, ...] | None = None
    start_deg: tuple[float, float, float] | None = None
    feedforward: bool = True
    realtime: bool = False
    trace_path: str | None = None
    period_s: float = 0.002
    plot_dir: str | None = None
    keep_frames: bool = False
    vcu: bool = False
    faults: tuple[FaultSpec, ...] = field(default_factory=tuple)
    imperfect: bool | None = None
    controller: str = "csp"
    host_gain_1_s: float | tuple[float, ...] = 0.0
    hil_seed: int | None = None


def host_gains(gain_1_s: float | tuple[float, ...], rig: Rig) -> tuple[float, ...]:
    """The host loop's gain per driven axis of ``rig`` (1/s).

    Args:
        gain_1_s: One gain for every axis (a number or a 1-tuple); a tuple of one per arm
            axis (boom, stick, bucket: a swing takes the lowest of them); or one per driven
            axis.

    Raises:
        ConfigurationError: A gain that is negative or not finite, or a count that is none of
            these (the message names them).
    """
    names = rig_axes.names(rig)
    values = (gain_1_s,) if isinstance(gain_1_s, (int, float)) else tuple(gain_1_s)
    if len(values) == 3 < len(names):
        values = (*values, *(min(values),) * (len(names) - 3))
    try:
        return per_axis_gain(values, len(names))
    except ConfigurationError:
        raise ConfigurationError(
            f"host loop gain {gain_1_s!r}: allowed one finite gain >= 0 (1/s) for every axis, "
            f"or one per axis ({', '.join(names)}; a swing may take the arm's lowest)"
        ) from None


#: Longest wait for the real-time HIL's scanner to answer a look (s): the planner plans the
#: next dig on the tip paths where none came (the arm holds at the exit meanwhile).
SCAN_WAIT_S = 5.0
#: The controllers a scenario can run: ours (CSP with velocity feed-forward) and Gao's.
CONTROLLERS = ("csp", "p")
#: Gains of Gao's proportional displacement loop in the PC per cylinder (boom, stick, bucket;
#: 1/s), each on top of the drive's own 10 1/s. Gao gives neither gain nor his valves'
#: overlap; on valves of 20 % overlap these put each cylinder in the middle of his +-3 mm
#: (Fig. 12) on the imperfect bench over the stroke sensors' seeds: the boom's error is its lag
#: plus the dead band's and takes the highest gain, the bucket's is the dead band's alone
#: (design notes, H8). The dead band keeps the loop from ringing (the ideal bench rings from
#: ~20 1/s).
GAO_HOST_GAIN_1_S: tuple[float, float, float] = (22.0, 17.0, 12.0)
#: Gain of the host loop beside our CSP and feed-forward on the imperfect bench (1/s): with the
#: drive's 10 1/s the 20 1/s loop that stays below the ideal bench's ringing (design notes,
#: H8).
CSP_HOST_GAIN_1_S = 10.0


def scenario_rig(sc: Scenario | PathScenario) -> Rig:
    """The scenario's rig with its ``[hil]`` imperfections switched as the scenario asks.

    Raises:
        ConfigurationError: Unknown rig or controller, imperfections or a HIL seed asked of a
            rig whose profile has no ``[hil]`` table, or a seed out of range.
    """
    if sc.controller not in CONTROLLERS:
        raise ConfigurationError(f"controller {sc.controller!r}; allowed: {', '.join(CONTROLLERS)}")
    rig = load_rig(sc.rig)
    material = getattr(sc, "material", None)
    if material is not None:
        if rig.hil is None:
            raise ConfigurationError(f"rig {rig.name} has no [hil] table: no materials")
        rig = dataclasses.replace(rig, hil=rig.hil.with_material(material))
    if sc.hil_seed is not None:
        if rig.hil is None:
            raise ConfigurationError(f"rig {rig.name} has no [hil] table: no HIL seed to set")
        if sc.realtime:
            raise ConfigurationError(
                "the real-time HIL process loads the profile by name and takes its own "
                f"hil.seed ({rig.hil.seed}); set it in the profile"
            )
        if not 0 <= sc.hil_seed <= 2**31 - 1:
            raise ConfigurationError(f"HIL seed {sc.hil_seed}; allowed: 0 .. 2^31 - 1")
        rig = dataclasses.replace(rig, hil=dataclasses.replace(rig.hil, seed=sc.hil_seed))
    if sc.imperfect is None:
        return rig if rig.hil is None or rig.hil.enabled else _uncompensated(rig)
    if rig.hil is None:
        if sc.imperfect:
            raise ConfigurationError(
                f"rig {rig.name} has no [hil] table: no imperfections to switch on"
            )
        return rig
    if sc.realtime and sc.imperfect != rig.hil.enabled:
        raise ConfigurationError(
            "the real-time HIL process loads the profile by name and applies its own "
            f"hil.enabled ({str(rig.hil.enabled).lower()}); switch it in the profile"
        )
    rig = dataclasses.replace(rig, hil=dataclasses.replace(rig.hil, enabled=sc.imperfect))
    return rig if sc.imperfect else _uncompensated(rig)


def _uncompensated(rig: Rig) -> Rig:
    """``rig`` with its valve drives' overlap compensation (``drives.valve_overlap_
    compensation``) off: for the ideal HIL, so that it runs the floats of an ideal valve
    without a jump (with one, its valves take the overlap their drives compensate; design
    notes, H8), and for Gao's plain proportional loop."""
    if rig.drives.valve_overlap_compensation == 0.0:
        return rig
    return dataclasses.replace(
        rig, drives=dataclasses.replace(rig.drives, valve_overlap_compensation=0.0)
    )


def _master_rig(sc: Scenario | PathScenario, rig: Rig) -> Rig:
    """The rig as the master configures its drives: Gao's plain proportional loop has no
    overlap compensation, so under ``p`` the master writes 0 to the valve drives' 0x2100."""
    return rig if sc.controller == "csp" else _uncompensated(rig)


def _feedforward(sc: Scenario | PathScenario) -> bool:
    """Velocity feed-forward on the bus: CSP's, never Gao's proportional loop."""
    return sc.feedforward and sc.controller == "csp"


@dataclass(frozen=True, slots=True, eq=False)
class KeyPointPath:
    """Key points interpolated into a path job.

    Attributes:
        job: The executor's job (one :class:`PolynomialMotion`).
        knots_s: Key times from the path's start ``(n,)``.
        q_key_rad: Key points ``(n, 3)``.
        orders: The order pattern used, e.g. ``3-4-5-4-3``.
        strategies: Peak |velocity|/|acceleration|/|jerk| per compared pattern.
        scaled_from: The rig whose ranges the key points were mapped from, or "".
    """

    job: PathJob
    knots_s: FloatArray
    q_key_rad: FloatArray
    orders: str
    strategies: Mapping[str, StrategyPeaks]
    scaled_from: str = ""


def scale_key_points(q_deg: Any, from_rig: Rig, to_rig: Rig) -> FloatArray:
    """Map joint key points linearly from one rig's joint ranges into another's (deg -> deg).

    Args:
        q_deg: Key points ``(n, 3)`` in degrees, within ``from_rig``'s ranges.
        from_rig: The rig the key points were made for.
        to_rig: The rig to run them on.

    Returns:
        ``(n, 3)`` degrees: ``lo' + (q - lo) (hi' - lo') / (hi - lo)`` per joint.
    """
    q = np.asarray(q_deg, dtype=np.float64).reshape(-1, 3)
    lo, hi = np.degrees(from_rig.q_min_rad[:3]), np.degrees(from_rig.q_max_rad[:3])
    lo2, hi2 = np.degrees(to_rig.q_min_rad[:3]), np.degrees(to_rig.q_max_rad[:3])
    out: FloatArray = lo2 + (q - lo) * (hi2 - lo2) / (hi - lo)
    return out


def load_key_points(path: str | Path) -> tuple[FloatArray, tuple[float, ...] | None]:
    """Key points from a JSON file: ``{"joints_deg": [[b, s, k], ...], "durations_s": [...]}``
    (``durations_s`` optional).

    Returns:
        Key points in degrees ``(n, 3)`` and the durations or None.

    Raises:
        ConfigurationError: Unreadable file or malformed content (the message says what).
    """
    import json

    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ConfigurationError(f"path file {path}: {exc}") from exc
    if not isinstance(data, dict) or "joints_deg" not in data:
        raise ConfigurationError(
            f"path file {path}: expected an object with 'joints_deg' ([[boom, stick, bucket], "
            "...] in deg) and optional 'durations_s'"
        )
    try:
        q = np.asarray(data["joints_deg"], dtype=np.float64)
        dur = data.get("durations_s")
        durations = None if dur is None else tuple(float(d) for d in dur)
    except (TypeError, ValueError) as exc:
        raise ConfigurationError(f"path file {path}: {exc}") from exc
    if q.ndim != 2 or q.shape[1] != 3 or q.shape[0] < 2:
        raise ConfigurationError(
            f"path file {path}: joints_deg must be at least two [boom, stick, bucket] rows; got "
            f"shape {q.shape}"
        )
    return q, durations


def key_point_path(
    rig: Rig,
    q_key_deg: Any,
    durations_s: Any = None,
    orders: str = "auto",
    name: str = "path",
) -> KeyPointPath:
    """Interpolate joint key points (Gao/Yang mixed orders) into a checked path job.

    Args:
        rig: The rig (the job is checked against it).
        q_key_deg: Key points ``(n, 3)``, deg.
        durations_s: ``n - 1`` segment durations (s); None: 3 s each.
        orders: ``auto`` (compare Gao's three patterns, take the smoothest; fewer than five
            segments: the lowest orders that fit) or one pattern.
        name: The job's name.

    Returns:
        The path.

    Raises:
        ConfigurationError: Wrong number of durations or key points.
        ValueError: Malformed key points or orders (from the interpolation).
        PlanningError: No pattern applies, or the path is faster than the rig's joint limits
            or does not start and end at rest.
        JointLimitError: The path leaves a joint range.
    """
    from rt_runtime.trajectory import mixed_order

    q_deg = np.asarray(q_key_deg, dtype=np.float64).reshape(-1, 3)
    n_seg = q_deg.shape[0] - 1
    if n_seg < 1:
        raise ConfigurationError(f"a path needs at least two key points; got {q_deg.shape[0]}")
    durations = [GAO_SEGMENT_S] * n_seg if durations_s is None else [float(d) for d in durations_s]
    if len(durations) != n_seg:
        raise ConfigurationError(
            f"{n_seg + 1} key points need {n_seg} segment durations; got {len(durations)}"
        )
    knots = np.concatenate([[0.0], np.cumsum(durations)])
    q_key = np.radians(q_deg)
    strategies: tuple[str, ...] = (orders,)
    if orders == "auto":
        strategies = mixed_order.PAPER_STRATEGIES if n_seg >= 5 else _SHORT_PATTERNS[n_seg]
    cmp = mixed_order.compare_strategies(knots, q_key, strategies)
    if not cmp.results:
        raise PlanningError(
            "no order pattern applies: " + "; ".join(f"{n}: {why}" for n, why in cmp.skipped)
        )
    best = mixed_order.choose_smoothest(cmp) if orders == "auto" else cmp.results[0]
    job = PathJob((PolynomialMotion(best.trajectory, name),), name)
    job.check(rig)
    deg = 180.0 / math.pi
    table = {
        r.name: StrategyPeaks(
            peak_velocity_deg_s=tuple((r.peak_velocity * deg).tolist()),
            peak_acceleration_deg_s2=tuple((r.peak_acceleration * deg).tolist()),
            peak_jerk_deg_s3=tuple((r.peak_jerk * deg).tolist()),
        )
        for r in cmp.results
    }
    return KeyPointPath(job, knots, q_key, "-".join(str(p) for p in best.orders), table)


def _scenario_path(sc: PathScenario, rig: Rig) -> KeyPointPath:
    """The scenario's key points -> path (Table 2 scaled into the rig's ranges when needed)."""
    scaled_from = ""
    durations: Any = sc.durations_s
    if sc.path == "gao":
        q_deg = np.array(GAO_TABLE2_JOINTS_DEG)
        lo, hi = np.degrees(rig.q_min_rad[:3]), np.degrees(rig.q_max_rad[:3])
        if not ((q_deg >= lo) & (q_deg <= hi)).all():
            q_deg = scale_key_points(q_deg, load_rig(GAO_RIG), rig)
            scaled_from = GAO_RIG
        name = "gao"
    elif sc.path == "joints":
        if len(sc.joints_deg) < 2:
            raise ConfigurationError("path 'joints' needs at least two key points (--joints-deg)")
        q_deg = np.asarray(sc.joints_deg, dtype=np.float64)
        name = "joints"
    else:
        q_deg, file_durations = load_key_points(sc.path)
        durations = durations if durations is not None else file_durations
        name = Path(sc.path).stem
    kp = key_point_path(rig, q_deg, durations, sc.orders, name)
    if scaled_from:
        kp = KeyPointPath(kp.job, kp.knots_s, kp.q_key_rad, kp.orders, kp.strategies, scaled_from)
    return kp


def run_path_scenario(sc: PathScenario) -> HilRun:
    """Execute a prescribed joint path with the executor against the HIL; return the report.

    The path is interpolated and checked before the HIL starts: a path the rig cannot follow
    raises here and no frame is ever sent.

    Returns:
        The run; its report holds the tracking figures of a task's (``tracking``,
        ``tip_error_max_mm``, ``cycles``), ``tracking_path`` (path only), ``path``, and no digs.

    Raises:
        ConfigurationError: Bad rig, key points, durations or fault.
        JointLimitError: The path leaves a joint range.
        PlanningError: The path is faster than the rig's joint limits.
        CommunicationError, DriveFault: Boot or enable failed.
    """
    wall0 = time.perf_counter()
    rig = scenario_rig(sc)
    gains = host_gains(sc.host_gain_1_s, rig)  # refused here, before the HIL starts
    kp = _scenario_path(sc, rig)
    q0 = kp.q_key_rad[0] if sc.start_deg is None else np.radians(np.asarray(sc.start_deg))
    q0 = np.asarray(q0, dtype=np.float64)
    actuation.joint_to_stroke(rig, q0, check_limits=True)  # the start pose must be reachable
    faults = _checked_faults(sc)
    hil = _open_hil(sc, rig, q0, None)
    try:

        def make_executor(master: CanMaster, loop: FixedRateLoop, on_cycle: _OnCycle) -> Executor:
            return Executor.for_path(
                master,
                rig,
                loop,
                kp.job,
                ExecutorConfig(
                    feedforward=_feedforward(sc),
                    correction_gain_1_s=gains,
                ),
                on_cycle=on_cycle,
            )

        run_s = kp.job.motions[0].duration_s + 60.0
        result, bus_load = _execute(sc, rig, hil, faults, run_s, make_executor)
    finally:
        end = hil.finish()
        hil.close()
    wall_s = time.perf_counter() - wall0
    truth = end.truth

    segments = _segments(rig, result, truth)
    figures = tracking_figures(segments)
    plots: tuple[str, ...] | None = None
    if sc.plot_dir is not None:
        files = plot_report(segments, sc.plot_dir, title=f"path {kp.job.name} ({kp.orders}):")
        files += _plot_path(rig, segments, kp, sc.plot_dir)
        plots = tuple(str(p) for p in files)
    report = HilReport(
        task=f"path {kp.job.name}",
        rig=rig.name,
        transport=_transport(sc),
        feedforward=_feedforward(sc),
        controller=sc.controller,
        host_gain_1_s=max(gains),
        host_gain_per_axis_1_s=dict(zip(rig_axes.names(rig), gains, strict=True)),
        imperfect=rig.hil is not None and rig.hil.enabled,
        period_s=sc.period_s,
        status=result.status.name.lower(),
        fault=result.fault,
        tracking=figures.tracking,
        tip_error_max_mm=figures.tip_error_max_mm,
        cycles=figures.cycles,
        digs=(),
        energy_Wh=truth.energy_j / 3600.0,
        sim_s=_sim_s(truth),
        wall_s=wall_s,
        overruns=result.overruns,
        emcys=_emcys(result),
        goal=GOALS_MM.get(rig.cylinders.kind, TrackingGoal()),
        can=_can_figures(sc, result, bus_load),
        loop=result.loop,
        tracking_path=tracking_figures([s for s in segments if s.kind == "path"]),
        path=_path_figures(rig, kp, result, sc.period_s),
        hil_lockstep=end.hil_lockstep,
        hil_process=end.hil_process,
        plots=plots,
        trace=str(Path(sc.trace_path)) if sc.trace_path is not None else None,
    )
    return HilRun(report, end.frames if sc.keep_frames else None)


def _path_figures(
    rig: Rig, kp: KeyPointPath, result: ExecutorResult, period_s: float
) -> PathFigures:
    """``path``: orders, knots, key points and their strokes, commanded strokes at key times.

    Row ``k`` of the PATH phase commands (``stroke_cmd_m``) the motion at ``(k + 1) T``; the row
    just before it (the end of the connect move, at the path's start pose) commands time 0.
    """
    deg = 180.0 / math.pi
    s_key = actuation.joint_to_stroke(rig, kp.q_key_rad, check_limits=False)
    tel = result.telemetry
    rows = np.flatnonzero(tel["phase"] == int(Phase.PATH))
    key_errors: tuple[float, ...] | None = None
    if rows.size and rows[0] > 0:
        cmd = tel["stroke_cmd_m"][np.concatenate([[rows[0] - 1], rows])]
        key_errors = tuple(_key_errors(cmd, kp.knots_s, s_key, period_s))
    return PathFigures(
        name=kp.job.name,
        orders=kp.orders,
        knots_s=tuple(kp.knots_s.tolist()),
        key_points_deg=_rows((kp.q_key_rad * deg).round(6)),
        key_strokes_mm=_rows(s_key * 1e3),
        strategies=kp.strategies,
        scaled_from=kp.scaled_from,
        cmd_at_key_error_um=key_errors,
    )


def _rows(a: FloatArray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(row) for row in a.tolist())


def _key_errors(
    cmd: FloatArray, knots_s: FloatArray, s_key: FloatArray, period_s: float
) -> list[float]:
    """Largest |commanded - key stroke| (um) at each key time (NaN when not streamed)."""
    out: list[float] = []
    for t, s in zip(knots_s, s_key, strict=True):
        k = round(float(t) / period_s) if math.isfinite(period_s) and period_s > 0 else -1
        if 0 <= k < len(cmd) and abs(k * period_s - float(t)) < 1e-9:
            out.append(float(np.max(np.abs(cmd[k] - s)) * 1e6))
        else:
            out.append(math.nan)
    return out


def _plot_path(rig: Rig, segments: list[Segment], kp: KeyPointPath, out_dir: str) -> list[Path]:
    """Cylinder strokes (reference, truth, key points) and the tip path of the path."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    path_segs = [s for s in segments if s.kind == "path"]
    if not path_segs:
        return []
    seg = path_segs[0]
    t = seg.t_s - seg.t_s[0]
    s_key = actuation.joint_to_stroke(rig, kp.q_key_rad, check_limits=False)
    files: list[Path] = []
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, name in enumerate(AXES):
        axes[i].plot(t, seg.stroke_ref_m[:, i] * 1e3, "k--", lw=1, label="reference")
        axes[i].plot(t, seg.stroke_true_m[:, i] * 1e3, lw=1, label="HIL truth")
        axes[i].plot(kp.knots_s, s_key[:, i] * 1e3, "o", ms=4, label="key points")
        axes[i].set_ylabel(f"{name} stroke (mm)")
    axes[0].legend(loc="best")
    axes[0].set_title(f"path {kp.job.name} ({kp.orders}) cylinder strokes (cf. Gao Fig. 11)")
    axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    out = Path(out_dir) / "path_strokes.png"
    fig.savefig(out, dpi=110)
    plt.close(fig)
    files.append(out)
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.plot(seg.tip_ref_m[:, 0], seg.tip_ref_m[:, 1], "k--", lw=1, label="reference tip")
    ax.plot(seg.tip_true_m[:, 0], seg.tip_true_m[:, 1], lw=1, label="HIL tip")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best")
    ax.set_title(f"path {kp.job.name}: bucket tip")
    fig.tight_layout()
    out = Path(out_dir) / "path_tip.png"
    fig.savefig(out, dpi=110)
    plt.close(fig)
    files.append(out)
    return files
