"""The HIL report: what one run of ``excavator-rt hil`` (and the demo) reports, typed.

:class:`HilReport` holds every figure of a run; its :meth:`HilReport.to_json` is the JSON of
``excavator-rt hil --json`` and of the demo's ``report.json``. Attribute names are the JSON keys.
The contract keys (DESIGN.md "Reports"): ``tracking`` (per axis ``max_mm``, ``rms_mm`` on the
plant's truth and ``reported`` the same on drive feedback), ``tip_error_max_mm``,
``coverage_error``, ``overdig_max_mm``, ``digs``, ``energy_Wh``, ``wall_s``, ``overruns``; on the
lockstep HIL ``hil_lockstep`` (README ``bench hil``); on a prescribed path ``tracking_path`` and
``path``. Further keys: ``status``, ``fault``, ``feedforward``, ``rig``, ``task``,
``transport``, ``period_s``, ``cycles``, ``sim_s``, ``tracking_digs`` (the tracking figures over
the digs only), ``goal`` (the rig's tracking goal), ``plan`` (the planner's own figures of the
closed loop), ``plan_total_us``, ``loop``, ``can`` (bus load, SYNC round trip), ``emcys``,
``removed_area_m2``, ``hil_process`` (the real-time HIL's own view), ``plots``, ``trace``.

A key whose attribute is None is left out of the JSON (a task's report has no ``path``, a path's
no ``coverage_error``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from hil_sim.report import AxisTracking, TrackingFigures
from rt_runtime.reports import BusLoadFigures, Distribution

if TYPE_CHECKING:
    from hil_sim.harness.lockstep import LockstepCost
    from rt_runtime.control import LoopStats

__all__ = [
    "CanFigures",
    "DigResult",
    "EmcyRecord",
    "HilProcessFigures",
    "HilReport",
    "MaterialFigures",
    "PathFigures",
    "PlanFigures",
    "StrategyPeaks",
    "Table6",
    "TrackingGoal",
]


@dataclass(frozen=True, slots=True)
class DigResult:
    """One dig the executor ran, as planned and as measured.

    Attributes:
        index: Dig index in the task.
        type: ``downward`` or ``backward``.
        T_s: Duration of the dig (s).
        planned_volume_L: Volume the plan fills (L).
        measured_volume_L: Volume of the tip path the drives reported (L).
        cut_volume_L: Volume the HIL's terrain lost to the true tip path (L; NaN when not cut).
        planned_energy_Wh: Energy of the plan (Wh).
        plan_us: Planning time of the dig (us): with ``planned_ahead``, the check of the plan
            made while the dig before it ran against the measured material.
        planned_ahead: Planned while the dig before it ran (a planner process only).
        energy_Wh: The plant's drive energy over the dig's cycles (Wh; Yao's W_E reading, as
            the plan's), NaN where the truth no longer holds them.
        joined, carried: The dig continues the bucket of the one before it, from its exit or
            (``carried``) carried to its own entry without a dump.
    """

    index: int
    type: str
    T_s: float
    planned_volume_L: float
    measured_volume_L: float
    cut_volume_L: float
    planned_energy_Wh: float
    plan_us: float
    planned_ahead: bool = False
    energy_Wh: float = math.nan
    joined: bool = False
    carried: bool = False

    def to_json(self) -> dict[str, Any]:
        """The dig's keys, as the attributes."""
        return {
            "index": self.index,
            "type": self.type,
            "T_s": self.T_s,
            "planned_volume_L": self.planned_volume_L,
            "measured_volume_L": self.measured_volume_L,
            "cut_volume_L": self.cut_volume_L,
            "planned_energy_Wh": self.planned_energy_Wh,
            "plan_us": self.plan_us,
            "planned_ahead": self.planned_ahead,
            "energy_Wh": self.energy_Wh,
            "joined": self.joined,
            "carried": self.carried,
        }


@dataclass(frozen=True, slots=True)
class EmcyRecord:
    """An emergency message the master received.

    Attributes:
        node_id: The drive's node id.
        code: The CiA 301 error code (JSON: ``"0x8611"``).
        description: What the code means.
    """

    node_id: int
    code: int
    description: str

    def to_json(self) -> dict[str, Any]:
        """``{"node_id", "code", "description"}``, the code as four hex digits."""
        return {
            "node_id": self.node_id,
            "code": f"0x{self.code:04X}",
            "description": self.description,
        }


@dataclass(frozen=True, slots=True)
class TrackingGoal:
    """The tracking goal of a rig's cylinder kind (mm; None: no goal on that figure).

    Attributes:
        max_mm: Largest stroke error allowed.
        rms_mm: RMS stroke error allowed.
    """

    max_mm: float | None = None
    rms_mm: float | None = None

    def to_json(self) -> dict[str, float]:
        """The goals set (``{}`` for a cylinder kind without goals)."""
        out: dict[str, float] = {}
        if self.max_mm is not None:
            out["max_mm"] = self.max_mm
        if self.rms_mm is not None:
            out["rms_mm"] = self.rms_mm
        return out


@dataclass(frozen=True, slots=True)
class CanFigures:
    """The bus as the master saw it.

    Attributes:
        bus_load: Bus load of the cyclic frames (``nominal``, ``worst``), None when no drive
            booted.
        sync_rtt_us: SYNC -> last TPDO1 round trip (us; real-time runs only, else None).
    """

    bus_load: BusLoadFigures | None = None
    sync_rtt_us: Distribution | None = None

    def to_json(self) -> dict[str, Any]:
        """``{"bus_load", "sync_rtt_us"}``, each where measured."""
        out: dict[str, Any] = {}
        if self.bus_load is not None:
            out["bus_load"] = self.bus_load.to_json()
        if self.sync_rtt_us is not None:
            out["sync_rtt_us"] = self.sync_rtt_us.to_json()
        return out


@dataclass(frozen=True, slots=True)
class PlanFigures:
    """The trench planner's own figures of the closed loop (from the measured tip paths).

    Attributes:
        coverage_error: The planner's coverage error (fraction).
        overdig_max_mm: The planner's deepest over-dig (mm).
        digs: Digs recorded.
    """

    coverage_error: float
    overdig_max_mm: float
    digs: int

    def to_json(self) -> dict[str, Any]:
        """``{"coverage_error", "overdig_max_mm", "digs"}``."""
        return {
            "coverage_error": self.coverage_error,
            "overdig_max_mm": self.overdig_max_mm,
            "digs": self.digs,
        }


@dataclass(frozen=True, slots=True)
class StrategyPeaks:
    """Peak joint rates of one interpolation order pattern, per joint (deg units).

    Attributes:
        peak_velocity_deg_s: Largest |velocity| per joint.
        peak_acceleration_deg_s2: Largest |acceleration| per joint.
        peak_jerk_deg_s3: Largest |jerk| per joint.
    """

    peak_velocity_deg_s: tuple[float, ...]
    peak_acceleration_deg_s2: tuple[float, ...]
    peak_jerk_deg_s3: tuple[float, ...]

    def to_json(self) -> dict[str, list[float]]:
        """The three peaks as lists."""
        return {
            "peak_velocity_deg_s": list(self.peak_velocity_deg_s),
            "peak_acceleration_deg_s2": list(self.peak_acceleration_deg_s2),
            "peak_jerk_deg_s3": list(self.peak_jerk_deg_s3),
        }


@dataclass(frozen=True, slots=True)
class PathFigures:
    """A prescribed path (``path`` of the report): its key points and how the commands met them.

    Attributes:
        name: The path's name (``gao``, ``joints`` or the file's stem).
        orders: The order pattern used, e.g. ``3-4-5-4-3``.
        knots_s: Key times from the path's start (s).
        key_points_deg: Key points, rows of (boom, stick, bucket) in deg.
        key_strokes_mm: The key points' cylinder strokes, rows per key point (mm).
        strategies: Peaks per compared order pattern.
        scaled_from: The rig whose joint ranges the key points were mapped from, or "".
        cmd_at_key_error_um: Largest |commanded - key stroke| at each key time (um; NaN where
            not streamed), None when the path never streamed.
    """

    name: str
    orders: str
    knots_s: tuple[float, ...]
    key_points_deg: tuple[tuple[float, ...], ...]
    key_strokes_mm: tuple[tuple[float, ...], ...]
    strategies: Mapping[str, StrategyPeaks]
    scaled_from: str
    cmd_at_key_error_um: tuple[float, ...] | None = None

    def to_json(self) -> dict[str, Any]:
        """The path's keys, as the attributes (``cmd_at_key_error_um`` where streamed)."""
        out: dict[str, Any] = {
            "name": self.name,
            "orders": self.orders,
            "knots_s": list(self.knots_s),
            "key_points_deg": [list(row) for row in self.key_points_deg],
            "key_strokes_mm": [list(row) for row in self.key_strokes_mm],
            "strategies": {name: s.to_json() for name, s in self.strategies.items()},
            "scaled_from": self.scaled_from,
        }
        if self.cmd_at_key_error_um is not None:
            out["cmd_at_key_error_um"] = list(self.cmd_at_key_error_um)
        return out


@dataclass(frozen=True, slots=True)
class HilProcessFigures:
    """The real-time HIL process's own view of a run (``hil_process``).

    Attributes:
        wall_s: The process's run time (s).
        frames_sent: Frames it sent.
        frames_dropped: Frames a client that did not read lost.
        syncs: SYNCs it handled.
        missed_syncs: SYNCs answered more than one period after their stamp.
        sync_handling_us: SYNC stamp to its answers leaving (us; p50, p99, max).
        sync_work_us: The HIL's own work on a SYNC (us; p50, p99, max).
    """

    wall_s: float
    frames_sent: int
    frames_dropped: int
    syncs: int
    missed_syncs: int
    sync_handling_us: Distribution
    sync_work_us: Distribution

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> HilProcessFigures:
        """The figures from the process's JSON (what the process class's ``finish`` returns
        under ``hil_process``).

        Raises:
            KeyError: A key is missing.
        """

        def dist(group: Mapping[str, float]) -> Distribution:
            return Distribution(group["p50"], group["p99"], max=group["max"])

        return cls(
            wall_s=float(data["wall_s"]),
            frames_sent=int(data["frames_sent"]),
            frames_dropped=int(data["frames_dropped"]),
            syncs=int(data["syncs"]),
            missed_syncs=int(data["missed_syncs"]),
            sync_handling_us=dist(data["sync_handling_us"]),
            sync_work_us=dist(data["sync_work_us"]),
        )

    def to_json(self) -> dict[str, Any]:
        """The figures' keys, as the attributes."""
        return {
            "wall_s": self.wall_s,
            "frames_sent": self.frames_sent,
            "frames_dropped": self.frames_dropped,
            "syncs": self.syncs,
            "missed_syncs": self.missed_syncs,
            "sync_handling_us": self.sync_handling_us.to_json(),
            "sync_work_us": self.sync_work_us.to_json(),
        }


@dataclass(frozen=True, slots=True)
class Table6:
    """The finished trench against its design in Yao Table 6's form: relative errors.

    Attributes:
        L: Top length |L_dug - L| / L.
        D: Depth |D_dug - D| / D.
        beta1: Near wall slope |beta1_dug - beta1| / beta1.
        beta2: Far wall slope |beta2_dug - beta2| / beta2.
    """

    L: float
    D: float
    beta1: float
    beta2: float

    def to_json(self) -> dict[str, float]:
        """``L``, ``D``, ``beta1``, ``beta2`` as fractions."""
        return {"L": self.L, "D": self.D, "beta1": self.beta1, "beta2": self.beta2}


@dataclass(frozen=True, slots=True)
class MaterialFigures:
    """What the granular material did in a task's run (Yao's material-flow figures).

    Attributes:
        name: The material.
        swept_L: Material the tip paths swept (L).
        load_L: Material the bucket kept (L).
        planned_L: Volume the planner planned, sum of V_p (L).
        load_ratio: Bucket load over planned V_p (Yao: 4.63 / 5.07 L = 91 %).
        energy_ratio: Executed over planned drive energy of the digs, minus 1 (Yao: +13 %).
        energy_ratio_digs: The same per dig.
        fallback_L: Spill that fell back into the trench (L).
        slumped_L: Material the faces' slumps moved (L).
        table6: The finished trench against the design (Yao Table 6), or None.
    """

    name: str
    swept_L: float
    load_L: float
    planned_L: float
    load_ratio: float
    energy_ratio: float
    energy_ratio_digs: tuple[float, ...]
    fallback_L: float
    slumped_L: float
    table6: Table6 | None

    def to_json(self) -> dict[str, Any]:
        """The figures under their attribute names."""
        return {
            "name": self.name,
            "swept_L": self.swept_L,
            "load_L": self.load_L,
            "planned_L": self.planned_L,
            "load_ratio": self.load_ratio,
            "energy_ratio": self.energy_ratio,
            "energy_ratio_digs": list(self.energy_ratio_digs),
            "fallback_L": self.fallback_L,
            "slumped_L": self.slumped_L,
            "table6": self.table6.to_json() if self.table6 is not None else None,
        }


@dataclass(frozen=True, slots=True)
class HilReport:
    """One HIL run's report (see the module docstring for the keys).

    Attributes:
        task: Task name, or ``path <name>`` for a prescribed path.
        rig: Rig profile name.
        transport: ``lockstep`` or ``realtime``.
        feedforward: Velocity feed-forward 0x60B1 was on.
        period_s: SYNC period (s).
        status: How the run ended: the executor's status in lower case (``done``, ``fault``,
            ...) or ``planning_error`` when the first dig could not be planned.
        fault: What went wrong ("" when done).
        tracking: Per axis name (boom, stick, bucket), over the cycles that streamed a motion.
        tip_error_max_mm: Largest tip error over the same cycles (mm).
        cycles: Cycles that streamed a motion.
        digs: The digs run.
        energy_Wh: The plant's drive energy (Wh; Yao's W_E reading).
        sim_s: Machine time of the run (s).
        wall_s: Wall time of the whole run, planning included (s).
        overruns: Loop overruns.
        emcys: Emergencies received.
        goal: The rig's tracking goal.
        can: Bus load and SYNC round trip.
        loop: The loop's statistics (JSON: its counters), None when nothing ran.
        tracking_digs: Tracking over the digs alone (a task's run), else None.
        tracking_path: Tracking over the path alone (a path's run), else None.
        path: The prescribed path, else None.
        coverage_error: Removed material against the design (a task's run with a terrain).
        overdig_max_mm: Deepest over-dig of the removed material (mm), same runs.
        removed_area_m2: Area removed (m^2), same runs.
        plan_total_us: Planning time of the run (us; a task's run).
        plan: The planner's own figures (a task's run whose plan finished).
        hil_lockstep: Whose time the periods were (lockstep runs).
        hil_process: The real-time HIL process's own figures (real-time runs).
        plots: Figures written, when asked for.
        trace: The CAN trace written, when asked for.
        controller: ``csp`` (ours) or ``p`` (Gao's proportional displacement loop).
        imperfect: The profile's ``[hil]`` imperfections were applied.
        material: Granular figures of a task's run on imperfect material, else None.
        scanner: The trench planner planned on a profile scanner's measured surface.
        host_gain_1_s: Gain of the host's proportional loop over the bus (1/s; 0: none), the
            highest over the axes.
        host_gain_per_axis_1_s: That loop's gain per axis (1/s).
    """

    task: str
    rig: str
    transport: str
    feedforward: bool
    period_s: float
    status: str
    fault: str
    tracking: Mapping[str, AxisTracking]
    tip_error_max_mm: float
    cycles: int
    digs: tuple[DigResult, ...]
    energy_Wh: float
    sim_s: float
    wall_s: float
    overruns: int
    emcys: tuple[EmcyRecord, ...]
    goal: TrackingGoal
    can: CanFigures
    loop: LoopStats | None = field(default=None, compare=False)
    tracking_digs: TrackingFigures | None = None
    tracking_path: TrackingFigures | None = None
    path: PathFigures | None = None
    coverage_error: float | None = None
    overdig_max_mm: float | None = None
    removed_area_m2: float | None = None
    plan_total_us: float | None = None
    plan: PlanFigures | None = None
    hil_lockstep: LockstepCost | None = None
    hil_process: HilProcessFigures | None = None
    plots: tuple[str, ...] | None = None
    trace: str | None = None
    controller: str = "csp"
    imperfect: bool = False
    material: MaterialFigures | None = None
    scanner: bool = False
    host_gain_1_s: float = 0.0
    host_gain_per_axis_1_s: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object (``json.dumps`` takes it as it is)."""
        out: dict[str, Any] = {
            "tracking": {name: fig.to_json() for name, fig in self.tracking.items()},
            "tip_error_max_mm": self.tip_error_max_mm,
            "cycles": self.cycles,
        }
        if self.tracking_digs is not None:
            out["tracking_digs"] = self.tracking_digs.to_json()
        if self.tracking_path is not None:
            out["tracking_path"] = self.tracking_path.to_json()
        if self.path is not None:
            out["path"] = self.path.to_json()
        if self.coverage_error is not None:
            out["coverage_error"] = self.coverage_error
        if self.overdig_max_mm is not None:
            out["overdig_max_mm"] = self.overdig_max_mm
        if self.removed_area_m2 is not None:
            out["removed_area_m2"] = self.removed_area_m2
        out["digs"] = [d.to_json() for d in self.digs]
        out["energy_Wh"] = self.energy_Wh
        out["wall_s"] = self.wall_s
        out["overruns"] = self.overruns
        out["status"] = self.status
        out["fault"] = self.fault
        if self.loop is not None:
            out["loop"] = self.loop.summary()  # its ``rt``: what the OS granted and refused
        out["emcys"] = [e.to_json() for e in self.emcys]
        out["rig"] = self.rig
        out["feedforward"] = self.feedforward
        out["transport"] = self.transport
        out["period_s"] = self.period_s
        out["sim_s"] = self.sim_s
        out["goal"] = self.goal.to_json()
        out["can"] = self.can.to_json()
        out["task"] = self.task
        if self.plan_total_us is not None:
            out["plan_total_us"] = self.plan_total_us
        if self.hil_lockstep is not None:
            out["hil_lockstep"] = self.hil_lockstep.to_json()
        if self.hil_process is not None:
            out["hil_process"] = self.hil_process.to_json()
        if self.plan is not None:
            out["plan"] = self.plan.to_json()
        if self.plots is not None:
            out["plots"] = list(self.plots)
        if self.trace is not None:
            out["trace"] = self.trace
        out["controller"] = self.controller
        out["imperfect"] = self.imperfect
        if self.material is not None:
            out["material"] = self.material.to_json()
        out["scanner"] = self.scanner
        out["host_gain_1_s"] = self.host_gain_1_s
        out["host_gain_per_axis_1_s"] = dict(self.host_gain_per_axis_1_s)
        return out
