"""The executor: one job (a trench task dug dig by dig, or a prescribed path) run to its end on the
drives, the way a test, the HIL scenarios and the benchmarks run one.

:class:`Executor` wires the parts of :mod:`rt_runtime.control` together for a single job: the
drives in SI units (:class:`~rt_runtime.control.hardware.DriveInterface`), the limit guard
(:class:`~rt_runtime.control.controllers.GuardFilter`), the job controller
(:class:`~rt_runtime.control.job.JobController`) with its planner link, and a controller
manager (:class:`~rt_runtime.control.manager.ControllerManager`) that runs them in the given
fixed-rate loop until the job ends. The daemon runs the same parts with one manager for its
whole life (:mod:`rt_runtime.service.daemon`).

Planning. ``next_dig`` screens candidates for ~0.5 s: far beyond a cycle, and a thread would
hold the interpreter lock. On a real-time clock the trench planner lives in a planner process
(:class:`~rt_runtime.control.planner_worker.ProcessPlanner`); the loop only queues requests and
takes replies from a queue. On a simulated clock (``clock.realtime`` False: the lockstep HIL) it
plans in-process between cycles (:class:`~rt_runtime.control.planner_worker.InlinePlanner`,
served by the loop's idle hook): time stands still, runs repeat exactly.
``ExecutorConfig.plan_in_worker`` overrides the choice. A prescribed path's motions are sampled
when the run starts.

Stops and the end. Every stop is the guard's jerk-limited stop from the commanded state. The
master's own fault reaction is switched off (``react_to_faults=False``): it would quick-stop
the healthy drives with the drive's ramp, which is not within the guard's limits. At the end the
drives are disabled in the last cycle (``disable_at_end``, default True: between the loop's last
SYNC and whatever the caller does next the drives' SYNC watchdog would fault them otherwise);
with ``disable_at_end=False`` they stay enabled and the caller must resume SYNC and RPDO1 within
``rig.drives.sync_timeout_s``.

Threads. :meth:`Executor.request_stop`, :meth:`Executor.pause`, :meth:`Executor.resume` and
:meth:`Executor.progress` are safe from any thread. ``on_dig_done`` is called on the loop's
thread on a simulated clock and on a separate callback thread on a real-time clock (a job
store's fsync must not land in a cycle); either way every call has returned when :meth:`run`
returns.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime import axes
from rt_runtime.canbus import CanMaster, Emcy
from rt_runtime.control.controllers import GuardFilter
from rt_runtime.control.guard import DEFAULT_MARGIN, LimitGuard, StrokeLimits
from rt_runtime.control.hardware import DriveInterface, per_axis_gain
from rt_runtime.control.job import (
    DigRecord,
    ExecStatus,
    JobController,
    JobLimits,
    StopRequest,
)
from rt_runtime.control.loop import FixedRateLoop, LoopStats
from rt_runtime.control.manager import EXECUTOR_COLUMNS, ControllerManager, executor_telemetry
from rt_runtime.control.planner_worker import (
    InlinePlanner,
    JointMotion,
    PathJob,
    PathLink,
    PlannerLink,
    ProcessPlanner,
    SurfaceSource,
)
from rt_runtime.control.setpoints import Phase
from rt_runtime.errors import ConfigurationError, DriveFault, PlanningError
from rt_runtime.planning.trench import TrenchSession
from rt_runtime.rig import Rig

__all__ = [
    "EXECUTOR_COLUMNS",
    "DigRecord",
    "ExecStatus",
    "Executor",
    "ExecutorConfig",
    "ExecutorResult",
    "Phase",
    "StopRequest",
    "executor_telemetry",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class ExecutorConfig:
    """How the executor runs a job.

    Attributes:
        feedforward: Send the stroke rate as velocity offset 0x60B1 (else 0).
        correction_gain_1_s: Gain of the host's proportional displacement loop added to the
            velocity offset (1/s; see :class:`~rt_runtime.control.hardware.DriveInterface`),
            one for every axis or a tuple of one per axis (axis order); 0: none.
        plan_in_worker: Plan in a separate process; None: when the loop's clock is real time.
        following_error_m: Largest |demand - reported stroke| (m); None: 0.8 of the drives'
            following-error window (the executor stops the job before the drive faults). The
            swing's bound (rad) is the same fraction of its drive's window.
        following_error_cycles: Consecutive cycles beyond it that count as a fault (>= 1).
        stale_cycles: Consecutive cycles without a drive's TPDO1 that count as a fault (>= 1).
        read_timeout_s: Longest wait for a missing TPDO when the cycle reads the answers to the
            last SYNC (a period after it); None: 0, take what arrived.
        stop_timeout_s: Longest stop (command and drives to rest) before giving up (s).
        rest_velocity_m_s: A drive reporting less counts as at rest.
        settle_s: Least hold at the end of a job before DONE (s).
        max_digs: Stop after this many digs of this run (None: until the task is done).
        guard_margin: Headroom of the guard's limits over the joint limits' image.
        disable_at_end: Disable the drives in the last cycle (see the module docstring).
        velocity_lead_s: Per axis (axis order) the lead of the velocity offset
            (:class:`~rt_runtime.control.hardware.DriveInterface`'s ``lead_s``: the offset is
            ``rate + lead * acceleration``), the lag of the axis's valve and load as its
            commissioning measured it; None: the rate alone.
        velocity_lead2_s2: Per axis the second-order term of that lead (``DriveInterface``'s
            ``lead2_s2``: ``+ lead2 * jerk``), for an axis behind a spring-mass mode; None:
            none. Needs ``velocity_lead_s``.

    Raises:
        ConfigurationError: A value outside its range (the message names it).
    """

    feedforward: bool = True
    correction_gain_1_s: float | tuple[float, ...] = 0.0
    plan_in_worker: bool | None = None
    following_error_m: float | None = None
    following_error_cycles: int = 3
    stale_cycles: int = 10
    read_timeout_s: float | None = None
    stop_timeout_s: float = 5.0
    rest_velocity_m_s: float = 1e-3
    settle_s: float = 0.05
    max_digs: int | None = None
    guard_margin: float = DEFAULT_MARGIN
    disable_at_end: bool = True
    velocity_lead_s: tuple[float, ...] | None = None
    velocity_lead2_s2: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        positive = {
            "stop_timeout_s": self.stop_timeout_s,
            "rest_velocity_m_s": self.rest_velocity_m_s,
        }
        if self.following_error_m is not None:
            positive["following_error_m"] = self.following_error_m
        for key, value in positive.items():
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigurationError(f"executor {key} = {value}; allowed: a finite value > 0")
        optional: tuple[tuple[str, float | None], ...] = (
            ("read_timeout_s", self.read_timeout_s),
            ("settle_s", self.settle_s),
            ("guard_margin", self.guard_margin),
        )
        for key, opt in optional:
            if opt is not None and not (math.isfinite(opt) and opt >= 0.0):
                raise ConfigurationError(f"executor {key} = {opt}; allowed: a finite value >= 0")
        per_axis_gain(self.correction_gain_1_s)
        for key, count in (
            ("following_error_cycles", self.following_error_cycles),
            ("stale_cycles", self.stale_cycles),
        ):
            if count < 1:
                raise ConfigurationError(f"executor {key} = {count}; allowed: an integer >= 1")
        lead = self.velocity_lead_s
        if lead is not None and not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in lead):
            raise ConfigurationError(
                f"executor velocity_lead_s = {lead}; allowed: one value in [0, 1] s per axis"
            )
        lead2 = self.velocity_lead2_s2
        if lead2 is not None and (
            lead is None or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in lead2)
        ):
            raise ConfigurationError(
                f"executor velocity_lead2_s2 = {lead2}; allowed: with velocity_lead_s, one "
                "value in [0, 1] s^2 per axis"
            )
        if self.max_digs is not None and self.max_digs < 1:
            raise ConfigurationError(
                f"executor max_digs = {self.max_digs}; allowed: None or an integer >= 1"
            )

    def limits(self, rig: Rig) -> JobLimits:
        """The job controller's monitors and endings on ``rig``."""
        window = rig.drives.following_error_window_m
        following = self.following_error_m if self.following_error_m is not None else 0.8 * window
        return JobLimits(
            following_error_m=following,
            following_error_cycles=self.following_error_cycles,
            stale_cycles=self.stale_cycles,
            stop_timeout_s=self.stop_timeout_s,
            rest_velocity_m_s=self.rest_velocity_m_s,
            settle_s=self.settle_s,
            max_digs=self.max_digs,
            # The swing's window in the same proportion to its drive's window (0x6065).
            swing_following_error_rad=following / window * axes.SWING_FOLLOWING_ERROR_WINDOW_RAD,
        )


@dataclass(frozen=True, slots=True)
class ExecutorResult:
    """What :meth:`Executor.run` did.

    Attributes:
        status: How it ended.
        fault: What went wrong (empty when DONE).
        digs: Digs executed and recorded in this run.
        overruns: Loop overruns.
        loop: The loop's statistics.
        telemetry: Snapshot of the telemetry (cycle order; :data:`EXECUTOR_COLUMNS` and the
            loop's columns).
        emcys: Emergencies received.
        plan_us: Planning time of every plan request of this run (us, sum).
    """

    status: ExecStatus
    fault: str
    digs: tuple[DigRecord, ...]
    overruns: int
    loop: LoopStats
    telemetry: dict[str, NDArray[Any]]
    emcys: tuple[Emcy, ...] = field(default_factory=tuple)
    plan_us: float = 0.0


class Executor:
    """Runs one job in the fixed-rate loop (see the module docstring).

    Order of use on a real-time clock: build the executor (it starts the planner process and
    the callback thread here, ~20 ms, at normal priority), apply the RT settings, boot and enable
    the drives, :meth:`run`. Nothing between ``enable`` and :meth:`run` may take longer than the
    drives' SYNC watchdog (``rig.drives.sync_timeout_s``). The trench state is copied to the
    planner process here: do not change it before :meth:`run`. An executor that will
    not run is released with :meth:`close`.

    Args:
        master: The CAN master, booted and enabled by the caller before :meth:`run` (its
            ``react_to_faults`` is switched off: the job controller owns the fault reaction).
        rig: The rig.
        loop: The fixed-rate loop; its clock paces the run. Its telemetry is replaced by one
            with :data:`EXECUTOR_COLUMNS` added (same capacity) when it lacks them.
        work: The :class:`TrenchSession` to dig (fresh, restored from a state, or with a
            pending dig), or a prescribed path
            (:class:`~rt_runtime.control.planner_worker.PathJob`: checked here, never planned
            in a process).
        config: Executor settings.
        on_dig_done: Called with each :class:`DigRecord` (see the module docstring for the
            thread); must not raise.
        on_cycle: Called at the end of every cycle with ``(sync_index, now_s)`` on the loop's
            thread (fault injection in tests); must be cheap and must not raise.
        surface_source: A profile scanner's measured surface, asked after each dig is
            recorded, on which the next dig is planned (see
            :class:`~rt_runtime.control.planner_worker.SessionDriver`); asked on the loop's
            thread (it returns the scan it holds), in-process or in the planner process. None:
            the trench is planned from the measured tip paths.

    Raises:
        ConfigurationError: A bad configuration, a loop period other than the master's, a
            trench planner that cannot run in a planner process when one is asked for.
        JointLimitError: A path leaves a joint's range (nothing was sent).
        PlanningError: A path is faster than the rig's joint limits or does not start and end
            at rest (nothing was sent).
    """

    def __init__(
        self,
        master: CanMaster,
        rig: Rig,
        loop: FixedRateLoop,
        work: TrenchSession | PathJob,
        config: ExecutorConfig | None = None,
        *,
        on_dig_done: Callable[[DigRecord], None] | None = None,
        on_cycle: Callable[[int, float], None] | None = None,
        surface_source: SurfaceSource | None = None,
    ) -> None:
        self.master = master
        self.rig = rig
        self.loop = loop
        self.work = work
        self.config = cfg = config if config is not None else ExecutorConfig()
        self.on_dig_done = on_dig_done
        period = loop.config.period_s
        if abs(period - master.config.period_s) > 1e-12:
            raise ConfigurationError(
                f"loop period {period} s differs from the master's {master.config.period_s} s "
                "(0x1006/0x60C2 were configured for the master's)"
            )
        self.period_s = period
        self.realtime = bool(loop.clock.realtime)
        self.plan_in_worker = self.realtime if cfg.plan_in_worker is None else cfg.plan_in_worker
        if master.n != axes.count(rig):
            raise ConfigurationError(
                f"the master drives {master.n} axes ({', '.join(master.config.axes)}); rig "
                f"{rig.name} has {axes.count(rig)} ({', '.join(axes.names(rig))})"
            )
        if rig.swing is not None and not isinstance(work, PathJob):
            raise ConfigurationError(
                f"rig {rig.name} has a swing axis: the trench planner plans the arm plane only, "
                "so a trench job cannot run on it; allowed: a prescribed path over all four "
                "axes (a taught job, a path job)"
            )
        if isinstance(work, PathJob):
            # Checked before anything is sent; a path has nothing to plan in a process.
            work.check(rig)
            self.plan_in_worker = False
        self.guard = LimitGuard(StrokeLimits.from_rig(rig, margin=cfg.guard_margin), period)
        read_timeout_s = 0.0 if cfg.read_timeout_s is None else cfg.read_timeout_s
        lead = None if cfg.velocity_lead_s is None else np.asarray(cfg.velocity_lead_s)
        lead2 = None if cfg.velocity_lead2_s2 is None else np.asarray(cfg.velocity_lead2_s2)
        for values in (lead, lead2):
            if values is not None and values.shape != (master.n,):
                raise ConfigurationError(
                    f"executor velocity lead has {values.size} values; the master drives "
                    f"{master.n} axes ({', '.join(master.config.axes)})"
                )
        self.drives = DriveInterface(
            master,
            loop.clock,
            read_timeout_s,
            cfg.feedforward,
            cfg.correction_gain_1_s,
            lead_s=lead,
            lead2_s2=lead2,
        )
        self.drives.react_to_faults(False)
        # Started here, before the caller enables the drives and applies RT settings: spawning
        # takes ~20 ms (no SYNC meanwhile) and must not inherit a real-time policy.
        link: PlannerLink
        if isinstance(work, PathJob):
            link = PathLink(work, rig, period)
        elif self.plan_in_worker:
            link = ProcessPlanner(work, period_s=period, surface_source=surface_source)
        else:
            link = InlinePlanner(work, period, surface_source)
        self._callbacks: queue.SimpleQueue[DigRecord | None] | None = None
        self._cb_thread: threading.Thread | None = None
        if self.realtime and on_dig_done is not None:
            self._callbacks = queue.SimpleQueue()
            self._cb_thread = threading.Thread(
                target=self._callback_loop,
                args=(self._callbacks,),
                name="executor-dig-done",
                daemon=True,
            )
            self._cb_thread.start()
        t_max = rig.planning.t_max_s if rig.planning is not None else 10.0
        self.job = JobController(
            link,
            GuardFilter(self.guard),
            cfg.limits(rig),
            rig,
            self.drives.axes,
            self.drives.describe,
            self._record,
            int(2.0 * t_max / period) + 16,
        )
        self.manager = ControllerManager(self.drives, self.job.guard, loop, on_cycle=on_cycle)
        self._ran = False
        self._link_closed = False

    @classmethod
    def for_path(
        cls,
        master: CanMaster,
        rig: Rig,
        loop: FixedRateLoop,
        path: PathJob | JointMotion,
        config: ExecutorConfig | None = None,
        *,
        on_cycle: Callable[[int, float], None] | None = None,
    ) -> Executor:
        """An executor for a prescribed path (one motion or a :class:`PathJob`).

        Args:
            master, rig, loop, config, on_cycle: As the constructor.
            path: The path: a :class:`PathJob`, or one motion (``duration_s`` and
                ``sample(t) -> (q, qd, qdd)``) made a one-motion job.

        Raises:
            As the constructor (JointLimitError, PlanningError for a path the rig cannot
            follow; nothing was sent).
        """
        job = path if isinstance(path, PathJob) else PathJob((path,))
        return cls(master, rig, loop, job, config, on_cycle=on_cycle)

    # -- thread-safe control --------------------------------------------------------------------

    def request_stop(self, why: StopRequest) -> None:
        """Ask for a jerk-limited stop (any thread; SHUTDOWN wins over CANCEL)."""
        self.job.request_stop(why)

    def pause(self) -> None:
        """Hold at the next motion boundary (any thread)."""
        self.job.pause()

    def resume(self) -> None:
        """Continue after :meth:`pause` (any thread)."""
        self.job.resume()

    def progress(self) -> dict[str, Any]:
        """A JSON-able snapshot (any thread; see :meth:`JobController.progress`)."""
        return self.job.progress()

    # -- the run --------------------------------------------------------------------------------

    def run(self) -> ExecutorResult:
        """Run the job from the measured pose until done or stopped.

        Returns:
            The result; every axis is at rest (the drives disabled when ``disable_at_end``).

        Raises:
            DriveFault: A drive is not OPERATION_ENABLED when the run starts.
            PlanningError: :meth:`run` was called before on this executor.
        """
        if self._ran:
            raise PlanningError("an Executor runs once; build a new one for the next run")
        self._ran = True
        drives = self.drives
        if not drives.operation_enabled():
            raise DriveFault(
                f"run() needs every drive OPERATION_ENABLED (master.enable() first); drive "
                f"states: {drives.drive_states()}"
            )
        s0 = drives.measured_stroke_m()
        self.guard.reset(s0)
        q0 = axes.actuator_to_joint(self.rig, s0, check_limits=False)
        job = self.job
        try:
            first = job.start(s0)
            stats = self.manager.run(job, first, s0, q0)
            if self.config.disable_at_end:
                drives.disable()
        finally:
            self.close()
        if not stats.stopped_by_step and job.status is None:
            job.status, job.fault = ExecStatus.STOPPED, "the loop ended (max_cycles)"
        last_state = job.planning.last_state
        work = self.work
        if self.plan_in_worker and last_state is not None and isinstance(work, TrenchSession):
            work.apply_state(last_state)
        status = job.status if job.status is not None else ExecStatus.DONE
        job.publish(status.name.lower(), stats.cycles)
        if status is not ExecStatus.DONE:  # logged here, outside the loop
            log.warning("executor: %s: %s", status.name, job.fault)
        return ExecutorResult(
            status=status,
            fault=job.fault,
            digs=tuple(job.digs),
            overruns=stats.overruns,
            loop=stats,
            telemetry=self.loop.telemetry.snapshot(),
            emcys=tuple(job.emcys),
            plan_us=job.planning.plan_us,
        )

    def close(self) -> None:
        """Release the planner process and the callback thread (:meth:`run` does this at its
        end; call it for an executor that will not run). Every ``on_dig_done`` call has
        returned when this returns; the planner process is stopped in the background."""
        if not self._link_closed:
            self._link_closed = True
            link = self.job.planning.link
            if isinstance(link, ProcessPlanner):
                threading.Thread(target=link.close, name="planner-close", daemon=True).start()
        callbacks, self._callbacks = self._callbacks, None
        if callbacks is not None and self._cb_thread is not None:
            callbacks.put(None)
            self._cb_thread.join()

    def _record(self, record: DigRecord) -> None:
        if self._callbacks is not None:
            self._callbacks.put(record)
        else:
            self._call_dig_done(record)

    def _callback_loop(self, callbacks: queue.SimpleQueue[DigRecord | None]) -> None:
        while (record := callbacks.get()) is not None:
            self._call_dig_done(record)

    def _call_dig_done(self, record: DigRecord) -> None:
        if self.on_dig_done is None:
            return
        try:
            self.on_dig_done(record)
        except Exception:  # a callback's bug must not end the job; it is logged
            log.exception("on_dig_done raised for dig %d", record.index)
