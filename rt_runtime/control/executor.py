"""The executor: a trench job, dig by dig, in the fixed-rate loop, through the limit guard, on CAN.

Role: the product's inner loop. :meth:`Executor.run` hands one step function to
:class:`~rt_runtime.control.loop.FixedRateLoop`; each cycle it

1. takes the feedback read at the end of the previous cycle and the stop requests (cancel,
   shutdown, the loop's overrun policy ``info.safe_stop``);
2. computes the next setpoint: the current motion sampled one period ahead (joint q, qd, qdd) ->
   stroke s, sd, sdd (:mod:`rt_runtime.actuation`; ``sdd = J qdd + J' qd^2``) -> the ruckig limit
   guard (:mod:`rt_runtime.control.guard`), or the guard's jerk-limited stop;
3. writes RPDO1 (target stroke, stroke-rate feed-forward) to every drive and SYNC;
4. reads the drives' TPDOs answering that SYNC (waiting at most ``read_timeout_s``: the round
   trip is measured, and the monitors act on feedback one period old instead of two);
5. runs the monitors on it: following error (|demand - reported| beyond ``following_error_m``
   for ``following_error_cycles``), stale feedback (no TPDO1 for ``stale_cycles``), drive state
   / EMCY / heartbeat (the master's :class:`~rt_runtime.canbus.CycleStatus`), bus errors;
6. sends the master heartbeat when due and writes the cycle's telemetry row
   (:data:`EXECUTOR_COLUMNS`).

SYNC timing. In cycle ``k`` (SYNC ``k`` at ``t_k``) the RPDO1
carries the setpoint for ``t_k + T``: the drive latches it at SYNC ``k`` and reaches it one
period later (CSP interpolation), so the drive's demand at ``t_k`` is the setpoint sent with
SYNC ``k - 1``; the TPDO1 answering SYNC ``k`` reports the stroke at ``t_k``. Telemetry row ``k``
therefore holds ``stroke_ref_m`` (the demand at ``t_k``, i.e. the previous command), the
feedback answering SYNC ``k`` and ``stroke_cmd_m`` (the setpoint for ``t_k + T``); the
following-error monitor and the HIL report compare the first two. The velocity offset 0x60B1 is
the guard's stroke rate at ``t_k + T`` (feed-forward), or 0 without feed-forward.

The job. From the measured pose (the drives' position after ``enable``) the executor asks the
planner for the first dig (:class:`~rt_runtime.control.planner_worker.DigPlan`) and streams:
lead-in (lift out straight up when the bucket is in or near the material, then to the dump pose;
nothing when the arm is already at the dig's entry), approach, enter, the dig, lift-out, dump.
Each of these is one or more rest-to-rest ruckig moves that the session checked against the
material (:meth:`TrenchSession.exit_transitions`; a lift may come in pieces), streamed in the
phase of its ``kind``. The reported strokes of the dig's SYNCs go back to the session
(``record``: the measured tip path updates the surface) and the next dig is planned while
lift-out and dump stream; at the dump pose the arm holds until the plan is there. When the
session has no dig left (or ``max_digs`` digs ran) the job ends at the dump pose (status DONE).
Any gap between the commanded pose and the next motion's start (a resumed job, a measured pose)
is bridged by a ruckig joint-space move (phase CONNECT), as the trench planner's transitions
are; in a trench job every move starts where the one before ends and the lead-in at the
measured pose, so these gaps are within ``AT_ENTRY_TOLERANCE_M`` of stroke (the bridge is not
checked against the material).
A dig that was cut short by a stop is not recorded: a restart plans it again from the session's
state (:meth:`TrenchSession.restore`), the next undone dig.

Prescribed paths. The same executor runs a :class:`~rt_runtime.control.
planner_worker.PathJob` (a fixed sequence of joint motions, e.g. Gao's mixed-order interpolation
through key points) when it is given one in place of the session (:meth:`Executor.for_path` is
the same call with a clearer name). Its planner link is :class:`~rt_runtime.control.
planner_worker.PathLink`: the first plan request is answered with every motion at once, each
queued as phase PATH; there is nothing to record, no planner process and no dig. From the
measured pose the first motion's start is reached by the usual CONNECT move, then the motions
stream through the same guard, monitors, stops and telemetry, and the job ends at the last
motion's end pose at rest (status DONE). The path is checked when the executor is built
(:meth:`PathJob.check`: joint ranges -> JointLimitError, joint velocity/acceleration/jerk ->
PlanningError), so a path the rig cannot follow is refused before any frame. A stopped path is
not resumable: run the rest as a new path. The trench code path does not depend on it.

Planning inside the slack (where the paper is silent). ``next_dig`` takes several loop periods
(milliseconds a dig), and a thread would hold the interpreter lock (design notes, L3). On a
real-time clock the session lives in a planner process (:class:`~rt_runtime.control.planner_worker.
ProcessPlanner`); the loop only queues requests and polls a pipe, so planning never costs a cycle.
On a simulated clock (``clock.realtime`` False: the lockstep HIL) it plans synchronously in-process
(:class:`~rt_runtime.control.planner_worker.InlinePlanner`): time stands still, runs repeat
exactly. ``ExecutorConfig.plan_in_worker`` overrides the choice.

Stops. Every stop (cancel, shutdown, fault, overrun policy, bus error) is the guard's
jerk-limited stop from the current *commanded* state, streamed until the command is at rest and
every drive that still answers reports rest (or ``stop_timeout_s``). The master is switched to
``react_to_faults=False``: its fault reaction would quick-stop the healthy drives with the drive's
own ramp, which is not within the guard's limits. A faulted drive runs its own fault reaction and
ignores the setpoints; the others get the ruckig stop. No frame ever commands a step beyond the
guard's limits. At the end the drives are disabled in the last cycle (``disable_at_end``, default
True: between the loop's last SYNC and whatever the caller does next the drives' SYNC watchdog
would fault them otherwise); with ``disable_at_end=False`` they stay enabled and the caller must
resume SYNC and RPDO1 within ``rig.drives.sync_timeout_s``.

Time inside a motion advances one period per cycle. After an overrun whose re-phase skipped
deadlines the motion is stretched by the skipped periods instead of jumping ahead: the setpoint
sequence stays the plan's, sampled one period per SYNC (the overrun policy stops the job if it
repeats).

Threads. :meth:`Executor.request_stop`, :meth:`Executor.pause`, :meth:`Executor.resume` and
:meth:`Executor.progress` are safe from any thread: flags and one snapshot tuple, each a single
assignment read once per cycle. A pause takes effect at the next motion boundary (every motion
ends at rest: after the current transition or dig), the arm holds there until resumed; the
planner keeps planning meanwhile. ``on_dig_done`` is called on the loop's thread on a simulated
clock and on a separate callback thread on a real-time clock (a job store's fsync must not land
in a cycle); either way every call has returned when :meth:`run` returns.
"""

from __future__ import annotations

import logging
import math
import queue
import sys
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime import actuation
from rt_runtime.canbus import CanMaster, CycleStatus, DriveState, Emcy, WriteStatus
from rt_runtime.control.guard import DEFAULT_MARGIN, GuardState, LimitGuard, StrokeLimits
from rt_runtime.control.loop import CycleInfo, FixedRateLoop, LoopAction, LoopStats
from rt_runtime.control.planner_worker import (
    DigPlan,
    InlinePlanner,
    JointMotion,
    PathJob,
    PathLink,
    PathPlan,
    PlannerError,
    PlannerLink,
    ProcessPlanner,
    Recorded,
)
from rt_runtime.control.telemetry import LOOP_COLUMNS, Column, Telemetry
from rt_runtime.errors import ConfigurationError, DriveFault, PlanningError
from rt_runtime.planning.trench import PlannedDig, Transition, TrenchSession, joint_move
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


class ExecStatus(IntEnum):
    """How a run ended (every status but DONE came through a jerk-limited stop or at rest)."""

    DONE = 0
    #: :meth:`Executor.request_stop` with CANCEL.
    CANCELLED = 1
    #: :meth:`Executor.request_stop` with SHUTDOWN (SIGTERM, daemon stop).
    STOPPED = 2
    #: A monitor tripped: drive fault, EMCY, heartbeat, following error, stale feedback.
    FAULT = 3
    #: The loop's overrun policy asked for a safe stop.
    OVERRUN_STOP = 4
    #: The bus refused frames.
    BUS_ERROR = 5
    #: The planner could not plan or record (the arm finished its current moves first).
    PLANNING_ERROR = 6


class StopRequest(IntEnum):
    """Why a stop is requested from outside."""

    NONE = 0
    CANCEL = 1
    #: SIGTERM / daemon stop.
    SHUTDOWN = 2


class Phase(IntEnum):
    """What the executor streams in a cycle (telemetry column ``phase``)."""

    #: Holding: waiting for a plan, or paused.
    WAIT = 0
    #: A ruckig move bridging the commanded pose and the next motion's start.
    CONNECT = 1
    LIFT_OUT = 2
    DUMP = 3
    APPROACH = 4
    ENTER = 5
    DIG = 6
    #: Holding at the end of the job until the drives report rest.
    SETTLE = 7
    #: The guard's jerk-limited stop.
    STOP = 8
    #: A prescribed path's motion (:class:`~rt_runtime.control.planner_worker.PathJob`).
    PATH = 9


_KIND_PHASE = {
    "lift_out": Phase.LIFT_OUT,
    "dump": Phase.DUMP,
    "approach": Phase.APPROACH,
    "enter": Phase.ENTER,
}
#: Phases that stream a plan's motion (telemetry ``tracking``).
_TRACKING = frozenset(
    {Phase.CONNECT, Phase.LIFT_OUT, Phase.DUMP, Phase.APPROACH, Phase.ENTER, Phase.DIG, Phase.PATH}
)
# Severity when several stop causes come together: the worst is reported.
_SEVERITY = {
    ExecStatus.DONE: 0,
    ExecStatus.CANCELLED: 1,
    ExecStatus.STOPPED: 2,
    ExecStatus.PLANNING_ERROR: 3,
    ExecStatus.OVERRUN_STOP: 4,
    ExecStatus.FAULT: 5,
    ExecStatus.BUS_ERROR: 6,
}
_STOPPING_STATES = (int(DriveState.QUICK_STOP_ACTIVE), int(DriveState.FAULT_REACTION_ACTIVE))
# Step of the second difference for J' = d^2 s / dq^2 (rad): truncation ~h^2, rounding ~1e-8.
_H_RAD = 1e-4
#: Commanded-pose gap (largest stroke difference, m) above which a connecting move bridges it:
#: the guard passes a step through exactly only while it fits in one period within the jerk
#: limit (~j_max T^3 / 32, 4e-11 m at 2 ms), and trails the plan after a larger one.
CONNECT_TOLERANCE_M = 1e-11
#: Setpoints mapped to strokes per batch (see :meth:`Executor._fill_chunk`).
SAMPLE_CHUNK = 32

#: The executor's telemetry columns (after the loop's): build the loop's Telemetry with them
#: (:func:`executor_telemetry`).
EXECUTOR_COLUMNS: tuple[Column, ...] = (
    Column("sync", np.int64, (), -1),  # SYNC count of this cycle's SYNC
    Column("phase", np.int8, (), -1),  # Phase
    Column("segment", np.int32, (), -1),  # motion number (-1 while holding or stopping)
    Column("dig", np.int16, (), -1),  # dig index during a dig
    Column("tracking", np.bool_, (), False),  # streaming a plan's motion
    Column("q_ref_rad", np.float64, (3,)),  # joint reference at this SYNC
    Column("stroke_ref_m", np.float64, (3,)),  # demand at this SYNC (last cycle's command)
    Column("stroke_cmd_m", np.float64, (3,)),  # RPDO1 target with this SYNC (for one period on)
    Column("vel_cmd_m_s", np.float64, (3,)),  # RPDO1 velocity offset
    Column("guard", np.int8, (), -1),  # GuardState
    Column("stroke_fb_m", np.float64, (3,)),  # TPDO1 answering this SYNC (NaN: stale)
    Column("vel_fb_m_s", np.float64, (3,)),
    Column("drive_state", np.int8, (3,), -1),
    Column("cycle_status", np.int8, (), -1),
    Column("rtt_s", np.float64),  # SYNC sent -> every TPDO1 in (clock), NaN if one was missing
)


def executor_telemetry(capacity: int) -> Telemetry:
    """A telemetry ring buffer with the executor's columns (give it to the loop).

    Raises:
        ConfigurationError: ``capacity`` below 1.
    """
    return Telemetry(capacity, EXECUTOR_COLUMNS)


@dataclass(frozen=True, slots=True)
class ExecutorConfig:
    """How the executor runs a job.

    Attributes:
        feedforward: Send the stroke rate as velocity offset 0x60B1 (else 0).
        plan_in_worker: Plan in a separate process; None: when the loop's clock is real time.
        following_error_m: Largest |demand - reported stroke| (m); None: 0.8 of the drives'
            following-error window (the executor stops the job before the drive faults).
        following_error_cycles: Consecutive cycles beyond it that count as a fault (>= 1).
        stale_cycles: Consecutive cycles without a drive's TPDO1 that count as a fault (>= 1).
        read_timeout_s: Longest wait for the TPDOs after SYNC; None: half the period.
        stop_timeout_s: Longest stop (command and drives to rest) before giving up (s).
        rest_velocity_m_s: A drive reporting less counts as at rest.
        settle_s: Least hold at the end of a job before DONE (s).
        max_digs: Stop after this many digs of this run (None: until the task is done).
        guard_margin: Headroom of the guard's limits over the joint limits' image.
        disable_at_end: Disable the drives in the last cycle (see the module docstring).

    Raises:
        ConfigurationError: A value outside its range (the message names it).
    """

    feedforward: bool = True
    plan_in_worker: bool | None = None
    following_error_m: float | None = None
    following_error_cycles: int = 3
    stale_cycles: int = 25
    read_timeout_s: float | None = None
    stop_timeout_s: float = 5.0
    rest_velocity_m_s: float = 1e-3
    settle_s: float = 0.05
    max_digs: int | None = None
    guard_margin: float = DEFAULT_MARGIN
    disable_at_end: bool = True

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
        for key, count in (
            ("following_error_cycles", self.following_error_cycles),
            ("stale_cycles", self.stale_cycles),
        ):
            if count < 1:
                raise ConfigurationError(f"executor {key} = {count}; allowed: an integer >= 1")
        if self.max_digs is not None and self.max_digs < 1:
            raise ConfigurationError(
                f"executor max_digs = {self.max_digs}; allowed: None or an integer >= 1"
            )


@dataclass(frozen=True, slots=True)
class DigRecord:
    """One dig executed and recorded (handed to ``on_dig_done``).

    Attributes:
        index: Dig index in the task.
        dig_type: ``downward`` or ``backward``.
        T_s: Planned duration.
        plan_us: Planning time of the dig (the planner's wall time for the request).
        planned_volume_m3: Material the planned path removes.
        measured_volume_m3: Material the measured path removed (session accounting).
        tip_path_m: Measured tip path, work-site frame, ``(n, 2)``.
        session_state: ``TrenchSession.state()`` after the record (JSON-able): persist it to
            resume at the next dig.
        sync_first: SYNC count of the dig's first SYNC.
        sync_last: SYNC count of the SYNC after its last setpoint (the dig's end pose).
        planned_energy_j: W_E of the verified plan.
    """

    index: int
    dig_type: str
    T_s: float
    plan_us: float
    planned_volume_m3: float
    measured_volume_m3: float
    tip_path_m: FloatArray
    session_state: dict[str, Any]
    sync_first: int = -1
    sync_last: int = -1
    planned_energy_j: float = math.nan


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


class _Sampler:
    """A joint motion sampled at ``t`` (clamped to [0, duration]): ``(q, qd, qdd)``."""

    __slots__ = ("_fn", "duration_s")

    def __init__(self, duration_s: float, fn: Callable[[float], tuple[Any, Any, Any]]) -> None:
        self.duration_s = float(duration_s)
        self._fn = fn

    def sample(self, t_s: float) -> tuple[Any, Any, Any]:
        return self._fn(min(max(t_s, 0.0), self.duration_s))


def _ruckig_sampler(traj: Any, q_end_rad: Any) -> _Sampler:
    """A ruckig trajectory that ends exactly at ``q_end_rad`` (ruckig's integrated end state
    differs in the last digits; the next motion starts at the exact pose)."""
    duration = float(traj.duration)
    end = (np.asarray(q_end_rad, dtype=np.float64), np.zeros(3), np.zeros(3))

    def fn(t_s: float) -> tuple[Any, Any, Any]:
        return end if t_s >= duration else traj.at_time(t_s)

    return _Sampler(duration, fn)


@dataclass(frozen=True, slots=True)
class _Item:
    """A queued motion: built into a sampler when it starts."""

    phase: Phase
    q_start_rad: tuple[float, float, float]
    dig: PlannedDig | None = None
    transition: Transition | None = None
    motion: JointMotion | None = None


class Executor:
    """Runs a trench session in the fixed-rate loop (see the module docstring).

    Order of use on a real-time clock: build the executor (it starts the planner process and
    the callback thread here, ~20 ms, at normal priority), apply the RT settings, boot and enable
    the drives, :meth:`run`. Nothing between ``enable`` and :meth:`run` may take longer than the
    drives' SYNC watchdog (``rig.drives.sync_timeout_s``). The session's state is copied to the
    planner process here: do not change the session before :meth:`run`. An executor that will
    not run is released with :meth:`close`.

    Args:
        master: The CAN master, booted and enabled by the caller before :meth:`run` (its
            ``react_to_faults`` is switched off: the executor owns the fault reaction).
        rig: The rig.
        loop: The fixed-rate loop; its clock paces the run. Its telemetry is replaced by one
            with :data:`EXECUTOR_COLUMNS` added (same capacity) when it lacks them.
        session: The trench session (fresh, restored from a state, or with a pending dig), or a
            prescribed path (:class:`~rt_runtime.control.planner_worker.PathJob`; see the
            module docstring: checked here, never planned in a process).
        config: Executor settings.
        on_dig_done: Called with each :class:`DigRecord` (see the module docstring for the
            thread); must not raise.
        on_cycle: Called at the end of every cycle with ``(sync_index, now_s)`` on the loop's
            thread (fault injection in tests); must be cheap and must not raise.

    Raises:
        ConfigurationError: A bad configuration, a loop period other than the master's, or a
            session planner that cannot run in a planner process when one is asked for.
        JointLimitError: A path leaves a joint's range (nothing was sent).
        PlanningError: A path is faster than the rig's joint limits or does not start and end
            at rest (nothing was sent).
    """

    def __init__(
        self,
        master: CanMaster,
        rig: Rig,
        loop: FixedRateLoop,
        session: TrenchSession | PathJob,
        config: ExecutorConfig | None = None,
        *,
        on_dig_done: Callable[[DigRecord], None] | None = None,
        on_cycle: Callable[[int, float], None] | None = None,
    ) -> None:
        self.master = master
        self.rig = rig
        self.loop = loop
        self.session = session
        self.config = config if config is not None else ExecutorConfig()
        self.on_dig_done = on_dig_done
        self.on_cycle = on_cycle
        period = loop.config.period_s
        if abs(period - master.config.period_s) > 1e-12:
            raise ConfigurationError(
                f"loop period {period} s differs from the master's {master.config.period_s} s "
                "(0x1006/0x60C2 were configured for the master's)"
            )
        self.period_s = period
        cfg = self.config
        self.realtime = bool(loop.clock.realtime)
        self.plan_in_worker = self.realtime if cfg.plan_in_worker is None else cfg.plan_in_worker
        if isinstance(session, PathJob):
            # Checked before anything is sent; a path has nothing to plan in a process.
            session.check(rig)
            self.plan_in_worker = False
        self.limits = StrokeLimits.from_rig(rig, margin=cfg.guard_margin)
        self.guard = LimitGuard(self.limits, period)
        self.following_error_m = (
            cfg.following_error_m
            if cfg.following_error_m is not None
            else 0.8 * rig.drives.following_error_window_m
        )
        self.read_timeout_s = 0.5 * period if cfg.read_timeout_s is None else cfg.read_timeout_s
        master.react_to_faults = False
        self._install_telemetry()
        # Started here, before the caller enables the drives and applies RT settings: spawning
        # takes ~20 ms (no SYNC meanwhile) and must not inherit a real-time policy.
        self._process: ProcessPlanner | None = (
            ProcessPlanner(session)
            if self.plan_in_worker and isinstance(session, TrenchSession)
            else None
        )
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
        self._dig_buf = np.zeros((int(2.0 * t_max / period) + 16, 3))
        # Requests from other threads (single assignments, read once per cycle).
        self._stop_request = StopRequest.NONE
        self._paused = False
        self._progress: tuple[Any, ...] = ("idle", -1, 0, False, False, "", 0)
        self._ran = False
        self._status: ExecStatus | None = None
        self._fault = ""
        self._plan_us = 0.0

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
        if int(why) > int(self._stop_request):
            self._stop_request = StopRequest(why)

    def pause(self) -> None:
        """Hold at the next motion boundary (any thread; see the module docstring)."""
        self._paused = True

    def resume(self) -> None:
        """Continue after :meth:`pause` (any thread)."""
        self._paused = False

    def progress(self) -> dict[str, Any]:
        """A JSON-able snapshot (any thread): ``phase``, ``dig`` (index streaming or -1),
        ``digs_done``, ``paused``, ``stopping``, ``status`` (empty while running), ``cycles``,
        ``planning`` (a plan request is outstanding)."""
        phase, dig, done, stopping, planning, status, cycles = self._progress
        return {
            "phase": phase,
            "dig": dig,
            "digs_done": done,
            "paused": self._paused,
            "stopping": stopping,
            "status": status,
            "cycles": cycles,
            "planning": planning,
        }

    # -- setup ----------------------------------------------------------------------------------

    def _install_telemetry(self) -> None:
        tel = self.loop.telemetry
        names = {c.name for c in tel.columns}
        if all(c.name in names for c in EXECUTOR_COLUMNS):
            return
        loop_names = {c.name for c in LOOP_COLUMNS}
        extra = [c for c in tel.columns if c.name not in loop_names]
        extra += [c for c in EXECUTOR_COLUMNS if c.name not in names]
        self.loop.telemetry = Telemetry(tel.capacity, extra)

    def _columns(self) -> None:
        tel = self.loop.telemetry
        self._tel = tel
        self._c_sync = tel.column("sync")
        self._c_phase = tel.column("phase")
        self._c_segment = tel.column("segment")
        self._c_dig = tel.column("dig")
        self._c_tracking = tel.column("tracking")
        self._c_q_ref = tel.column("q_ref_rad")
        self._c_s_ref = tel.column("stroke_ref_m")
        self._c_s_cmd = tel.column("stroke_cmd_m")
        self._c_v_cmd = tel.column("vel_cmd_m_s")
        self._c_guard = tel.column("guard")
        self._c_s_fb = tel.column("stroke_fb_m")
        self._c_v_fb = tel.column("vel_fb_m_s")
        self._c_state = tel.column("drive_state")
        self._c_status = tel.column("cycle_status")
        self._c_rtt = tel.column("rtt_s")

    # -- the run --------------------------------------------------------------------------------

    def run(self) -> ExecutorResult:
        """Run the job from the measured pose until done or stopped (see the module docstring).

        Returns:
            The result; every axis is at rest (the drives disabled when ``disable_at_end``).

        Raises:
            DriveFault: A drive is not OPERATION_ENABLED when the run starts.
            PlanningError: :meth:`run` was called before on this executor.
        """
        if self._ran:
            raise PlanningError("an Executor runs once; build a new one for the next run")
        self._ran = True
        fb = self.master.feedback
        if not (fb.state == DriveState.OPERATION_ENABLED).all():
            states = [fb.drive_state(a) for a in range(self.master.n)]
            raise DriveFault(
                f"run() needs every drive OPERATION_ENABLED (master.enable() first); drive "
                f"states: {[s.name if s is not None else 'undecodable' for s in states]}"
            )
        s0 = fb.position_um.astype(np.float64) * 1e-6
        self._columns()
        self._init_state(s0)
        link: PlannerLink
        if isinstance(self.session, PathJob):
            link = PathLink(self.session)
        elif self._process is not None:
            link = self._process
        else:
            link = InlinePlanner(self.session)
        self._link = link
        # Another thread of this process (the dig-done callback, the planner sender) holding the
        # interpreter lock delays the loop by up to the switch interval (5 ms by default): on a
        # real-time clock it is cut to a tenth of the period while the loop runs.
        old_switch = sys.getswitchinterval()
        if self.realtime:
            sys.setswitchinterval(min(old_switch, 0.1 * self.period_s))
        try:
            stats = self.loop.run(self._step)
        finally:
            sys.setswitchinterval(old_switch)
            self.close()
        if not stats.stopped_by_step and self._status is None:
            self._status, self._fault = ExecStatus.STOPPED, "the loop ended (max_cycles)"
        if (
            self.plan_in_worker
            and self._last_state is not None
            and isinstance(self.session, TrenchSession)
        ):
            self.session.apply_state(self._last_state)
        status = self._status if self._status is not None else ExecStatus.DONE
        self._publish(status.name.lower())
        if status is not ExecStatus.DONE:  # logged here, outside the loop
            log.warning("executor: %s: %s", status.name, self._fault)
        return ExecutorResult(
            status=status,
            fault=self._fault,
            digs=tuple(self._digs),
            overruns=stats.overruns,
            loop=stats,
            telemetry=self.loop.telemetry.snapshot(),
            emcys=tuple(self._emcys),
            plan_us=self._plan_us,
        )

    def close(self) -> None:
        """Release the planner process and the callback thread (:meth:`run` does this at its
        end; call it for an executor that will not run). Every ``on_dig_done`` call has
        returned when this returns; the planner process is stopped in the background."""
        process, self._process = self._process, None
        if process is not None:
            threading.Thread(target=process.close, name="planner-close", daemon=True).start()
        callbacks, self._callbacks = self._callbacks, None
        if callbacks is not None and self._cb_thread is not None:
            callbacks.put(None)
            self._cb_thread.join()

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

    def _init_state(self, s0: FloatArray) -> None:
        rig = self.rig
        self.guard.reset(s0)
        q0 = actuation.stroke_to_joint(rig, s0, check_limits=False)
        self._q_hold = q0.copy()
        self._s_hold = s0.copy()
        self._q_ref = q0.copy()  # joint reference at this cycle's SYNC
        self._s_ref = s0.copy()  # demand at this cycle's SYNC
        self._q_next = q0.copy()
        self._zero = np.zeros(3)
        self._cq = np.zeros((SAMPLE_CHUNK, 3))  # a chunk of the motion's joint setpoints
        self._cqd = np.zeros((SAMPLE_CHUNK, 3))
        self._cqdd = np.zeros((SAMPLE_CHUNK, 3))
        self._cq3 = np.zeros((SAMPLE_CHUNK, 3, 3))
        self._cs = np.zeros((SAMPLE_CHUNK, 3))  # ... and their strokes, rates, accelerations
        self._csd = np.zeros((SAMPLE_CHUNK, 3))
        self._csdd = np.zeros((SAMPLE_CHUNK, 3))
        self._chunk_end = 0  # motion samples [_chunk_end - SAMPLE_CHUNK, _chunk_end) are mapped
        self._s_t = np.zeros(3)
        self._sd_t = np.zeros(3)
        self._sdd_t = np.zeros(3)
        self._um = np.zeros(3)  # rounding buffer of both setpoints
        self._target_um = np.zeros(3, np.int32)
        self._vel_um = np.zeros(3, np.int32)
        self._fe_count = np.zeros(3, np.int64)
        self._stale_count = np.zeros(3, np.int64)
        self._queue: deque[_Item] = deque()
        self._motion: _Sampler | None = None
        self._motion_j = 0
        self._phase = Phase.WAIT
        self._segment = -1
        self._segments = 0
        self._dig_index = -1
        self._dig_plans: dict[int, DigPlan] = {}
        self._sync_ranges: dict[int, tuple[int, int]] = {}
        self._digs: list[DigRecord] = []
        self._digs_started = 0
        self._first_request = True
        self._plan_outstanding = False
        self._record_outstanding = False
        self._task_done = False
        self._final: tuple[ExecStatus, str] | None = None  # end at the next rest, not a stop
        self._collecting = False
        self._collect_n = 0
        self._collect_first = -1
        self._collect_last = -1
        self._collect_dig: PlannedDig | None = None
        self._stopping = False
        self._stop_t0 = 0.0
        self._settle_t0: float | None = None
        self._status = None
        self._fault = ""
        self._emcys: list[Emcy] = []
        self._last_state: dict[str, Any] | None = None
        self._plan_us = 0.0
        self._prev_status = CycleStatus.OK
        self._publish("")

    def _publish(self, status: str) -> None:
        self._progress = (
            self._phase.name.lower(),
            self._dig_index,
            len(self._digs),
            self._stopping,
            self._plan_outstanding,
            status,
            self._tel.count,
        )

    # -- stops and endings ----------------------------------------------------------------------

    def _escalates(self, status: ExecStatus) -> bool:
        """:meth:`_begin_stop` with ``status`` would change the status: no stop yet, or a more
        severe cause than the current one."""
        return (
            not self._stopping
            or self._status is None
            or _SEVERITY[status] > _SEVERITY[self._status]
        )

    def _begin_stop(self, status: ExecStatus, text: str) -> None:
        """Start the guard's stop (or, during one, report a more severe cause)."""
        if self._stopping:
            if self._escalates(status):
                self._status = status
                self._fault = f"{self._fault}; then {text}" if self._fault else text
            return
        self._stopping = True
        if self._collecting and self._collect_last < 0:
            # The dig was cut short: not recorded, the next run plans it again.
            self._collecting = False
            self._collect_dig = None
        self._status = status
        self._fault = text
        self._stop_t0 = self.loop.clock.now()
        self.guard.stop()
        self._motion = None
        self._queue.clear()
        self._phase = Phase.STOP
        self._segment = -1
        self._publish("")

    def _describe(self, status: CycleStatus) -> str:
        fb = self.master.feedback
        parts = [f"cycle status {status.name}"]
        for axis, name in enumerate(self.master.config.axes):
            state = fb.drive_state(axis)
            emcy = self.master.last_emcy[axis]
            text = f"{name}: {state.name if state is not None else 'undecodable'}"
            if fb.heartbeat_lost[axis]:
                text += ", heartbeat lost"
            if emcy is not None:
                text += f", EMCY {emcy.description}"
            parts.append(text)
        return "; ".join(parts)

    # -- the planner ----------------------------------------------------------------------------

    def _handle_reply(self, reply: Any) -> None:
        if isinstance(reply, PlannerError):
            self._plan_outstanding = False
            self._record_outstanding = False
            if self._final is None:
                self._final = (ExecStatus.PLANNING_ERROR, reply.message)
            return
        if isinstance(reply, Recorded):
            self._record_outstanding = False
            self._last_state = reply.state
            plan = self._dig_plans.get(reply.index)
            dig = plan.dig if plan is not None else None
            record = DigRecord(
                index=reply.index,
                dig_type=dig.dig_type.name.lower() if dig is not None else "",
                T_s=dig.T_s if dig is not None else math.nan,
                plan_us=plan.plan_us if plan is not None else math.nan,
                planned_volume_m3=dig.volume_m3 if dig is not None else math.nan,
                measured_volume_m3=reply.measured_volume_m3,
                tip_path_m=reply.tip_path_m,
                session_state=reply.state,
                sync_first=self._sync_ranges.get(reply.index, (-1, -1))[0],
                sync_last=self._sync_ranges.get(reply.index, (-1, -1))[1],
                planned_energy_j=dig.energy_j if dig is not None else math.nan,
            )
            self._digs.append(record)
            if self._callbacks is not None:
                self._callbacks.put(record)
            else:
                self._call_dig_done(record)
            return
        if isinstance(reply, PathPlan):
            self._plan_outstanding = False
            self._plan_us += reply.plan_us
            if not (self._stopping or self._final is not None):
                for motion in reply.motions:
                    q0, _, _ = motion.sample(0.0)
                    q_start = tuple(float(v) for v in np.asarray(q0, dtype=np.float64))
                    self._queue.append(
                        _Item(Phase.PATH, (q_start[0], q_start[1], q_start[2]), motion=motion)
                    )
            self._task_done = True
            return
        assert isinstance(reply, DigPlan)
        self._plan_outstanding = False
        self._plan_us += reply.plan_us
        if self._stopping or self._final is not None:
            return
        if reply.travel:
            self._final = (
                ExecStatus.PLANNING_ERROR,
                f"the task needs crawler travel ({reply.travel[0].distance_m:+.3f} m); the "
                "executor does not drive the VCU yet",
            )
            return
        for t in reply.lead_in + reply.entry:
            self._queue.append(_Item(_KIND_PHASE.get(t.kind, Phase.CONNECT), t.q_from_rad, None, t))
        if reply.dig is None:
            self._task_done = True
            return
        dig = reply.dig
        self._dig_plans[dig.index] = reply
        self._queue.append(_Item(Phase.DIG, dig.problem.q_start_rad, dig, None))
        for t in reply.exit:
            self._queue.append(_Item(_KIND_PHASE.get(t.kind, Phase.CONNECT), t.q_from_rad, None, t))

    # -- motions --------------------------------------------------------------------------------

    def _start_next(self) -> None:
        """At a motion boundary: start the next queued motion (or a connecting move to it)."""
        if self._paused or not self._queue:
            self._phase = Phase.WAIT
            return
        item = self._queue[0]
        q_start = np.asarray(item.q_start_rad, dtype=np.float64)
        s_start = actuation.joint_to_stroke(self.rig, q_start, check_limits=False)
        if float(np.max(np.abs(s_start - self._s_hold))) > CONNECT_TOLERANCE_M:
            traj, _ = joint_move(self.rig, self._q_hold, q_start)
            self._motion = _ruckig_sampler(traj, q_start)
            self._phase = Phase.CONNECT
        else:
            self._queue.popleft()
            if item.motion is not None:
                self._motion = _Sampler(item.motion.duration_s, item.motion.sample)
            elif item.dig is not None:
                self._motion = _Sampler(item.dig.T_s, item.dig.trajectory().sample)
                self._dig_index = item.dig.index
                self._digs_started += 1
                self._collecting = True
                self._collect_n = 0
                self._collect_first = self.master.feedback.sync_count + 1
                self._collect_last = -1
                self._collect_dig = item.dig
            else:
                assert item.transition is not None
                t = item.transition
                self._motion = _ruckig_sampler(t.trajectory(self.rig), t.q_to_rad)
            self._phase = item.phase
        self._motion_j = 0
        self._chunk_end = 0
        self._segments += 1
        self._segment = self._segments - 1
        self._publish("")

    def _sample(self) -> bool:
        """Next target from the current motion into ``_s_t/_sd_t/_sdd_t``; True at its end."""
        motion = self._motion
        assert motion is not None
        j = self._motion_j
        if j >= self._chunk_end:
            self._fill_chunk(motion, j)
        k = j - (self._chunk_end - SAMPLE_CHUNK)
        self._s_t[:] = self._cs[k]
        self._sd_t[:] = self._csd[k]
        self._sdd_t[:] = self._csdd[k]
        self._q_next[:] = self._cq[k]
        self._motion_j = j + 1
        return (j + 1) * self.period_s >= motion.duration_s - 1e-12

    def _fill_chunk(self, motion: _Sampler, j0: int) -> None:
        """Map the motion's next :data:`SAMPLE_CHUNK` setpoints (from sample ``j0``) to strokes.

        Per setpoint: stroke ``s(q)``, rate ``J qd`` and acceleration ``J qdd + J' qd^2``, with
        ``J' = d^2 s / dq^2`` by a central second difference of step :data:`_H_RAD`. The mapping
        is numpy on ``(SAMPLE_CHUNK, 3, 3)`` poses at once: a per-cycle call on three poses
        spent ~60-90 us in numpy's per-call overhead, a chunk costs about as much once per
        ``SAMPLE_CHUNK`` cycles (samples past the motion's end are its clamped end pose).
        """
        period = self.period_s
        cq, cqd, cqdd = self._cq, self._cqd, self._cqdd
        for k in range(SAMPLE_CHUNK):
            q, qd, qdd = motion.sample((j0 + k + 1) * period)
            cq[k] = q
            cqd[k] = qd
            cqdd[k] = qdd
        q3 = self._cq3
        q3[:] = cq[:, None, :]
        q3[:, 0] -= _H_RAD
        q3[:, 2] += _H_RAD
        s3 = actuation.joint_to_stroke(self.rig, q3, check_limits=False)
        jac = actuation.stroke_jacobian(self.rig, cq, check_limits=False)
        dj = (s3[:, 2] - 2.0 * s3[:, 1] + s3[:, 0]) * (1.0 / (_H_RAD * _H_RAD))
        self._cs[:] = s3[:, 1]
        np.multiply(jac, cqd, out=self._csd)
        self._csdd[:] = jac * cqdd + dj * cqd * cqd
        self._chunk_end = j0 + SAMPLE_CHUNK

    def _finish_motion(self) -> None:
        """The current motion sent its end pose: hold it; a dig's feedback ends one SYNC later."""
        self._q_hold[:] = self._q_next
        self._s_hold[:] = self._s_t
        if self._phase is Phase.DIG:
            self._collect_last = self.master.feedback.sync_count + 1
            self._dig_index = -1
        self._motion = None
        self._segment = -1

    def _finish_collecting(self) -> None:
        self._collecting = False
        dig = self._collect_dig
        self._collect_dig = None
        if dig is None:
            return
        cfg = self.config
        last = cfg.max_digs is not None and self._digs_started >= cfg.max_digs
        plan_next = not (last or self._stopping or self._final is not None or self._task_done)
        self._sync_ranges[dig.index] = (self._collect_first, self._collect_last)
        self._record_outstanding = True
        self._plan_outstanding = plan_next
        self._link.request_record(self._dig_buf[: self._collect_n], plan_next)
        if last and self._final is None:
            self._final = (ExecStatus.DONE, "")

    # -- the step -------------------------------------------------------------------------------

    def _step(self, info: CycleInfo) -> LoopAction:
        try:
            return self._cycle(info)
        except Exception as exc:  # a bug must still end in a stop, never a dead loop
            log.exception("executor step failed")
            if self._stopping:
                self._status = ExecStatus.FAULT
                self._fault += f"; executor error during the stop: {exc!r}"
                return LoopAction.STOP
            self._begin_stop(ExecStatus.FAULT, f"executor error: {exc!r}")
            return LoopAction.CONTINUE

    def _cycle(self, info: CycleInfo) -> LoopAction:
        master = self.master
        clock = self.loop.clock
        guard = self.guard
        slot = self._tel.slot
        # -- requests from outside and from the loop
        if not self._stopping:
            request = self._stop_request
            if request is StopRequest.SHUTDOWN:
                self._begin_stop(ExecStatus.STOPPED, "shutdown requested")
            elif request is StopRequest.CANCEL:
                self._begin_stop(ExecStatus.CANCELLED, "cancelled")
        if info.safe_stop and self._escalates(ExecStatus.OVERRUN_STOP):
            # safe_stop stays True: build the message only when it would change the status
            self._begin_stop(
                ExecStatus.OVERRUN_STOP,
                f"{info.consecutive_overruns} consecutive loop overruns (last "
                f"{info.lateness_s * 1e6:.0f} us late)",
            )
        # -- the planner: first request, then one reply per cycle
        if self._first_request:
            self._first_request = False
            self._plan_outstanding = True
            self._link.request_plan(self._q_hold.copy())
        reply = self._link.poll()
        if reply is not None:
            self._handle_reply(reply)
        # -- the next setpoint
        self._c_q_ref[slot] = self._q_ref
        self._c_s_ref[slot] = self._s_ref
        finished = False
        if self._stopping:
            gstate = guard.step_stop()
        else:
            if self._motion is None:
                self._start_next()
            if self._motion is not None:
                finished = self._sample()
                gstate = guard.track(self._s_t, self._sd_t, self._sdd_t)
            else:
                if self._phase is Phase.WAIT and self._ending():
                    self._phase = Phase.SETTLE
                gstate = guard.track(self._s_hold, self._zero, self._zero)
                self._q_next[:] = self._q_hold
            if gstate is GuardState.ERROR:
                self._begin_stop(ExecStatus.FAULT, "the limit guard refused the setpoint")
        um = self._um
        np.multiply(guard.position_m, 1e6, out=um)
        np.rint(um, out=um)
        self._target_um[:] = um
        if self.config.feedforward:
            np.multiply(guard.velocity_m_s, 1e6, out=um)
            np.rint(um, out=um)
            self._vel_um[:] = um
        # -- write, read
        w = master.write_setpoints(self._target_um, self._vel_um)
        sent_s = clock.now()
        fb = master.read_feedback(sent_s, self.read_timeout_s)
        fresh_all = not fb.stale.any()
        rtt = clock.now() - sent_s if fresh_all else math.nan
        master.heartbeat(clock.now())
        # -- telemetry
        self._c_sync[slot] = fb.sync_count
        self._c_phase[slot] = self._phase
        self._c_segment[slot] = self._segment
        self._c_dig[slot] = self._dig_index if self._phase is Phase.DIG else -1
        self._c_tracking[slot] = self._phase in _TRACKING and not self._stopping
        self._c_s_cmd[slot] = guard.position_m
        self._c_v_cmd[slot] = guard.velocity_m_s
        self._c_guard[slot] = gstate
        pos = self._c_s_fb[slot]
        pos[:] = fb.position_um
        pos *= 1e-6
        vel = self._c_v_fb[slot]
        vel[:] = fb.velocity_um_s
        vel *= 1e-6
        if not fresh_all:
            pos[fb.stale] = np.nan
            vel[fb.stale] = np.nan
        self._c_state[slot] = fb.state
        self._c_status[slot] = fb.status
        self._c_rtt[slot] = rtt
        if fb.emcys:
            self._emcys.extend(fb.emcys)
        # -- the dig's measured path
        if self._collecting and fresh_all and self._collect_n < len(self._dig_buf):
            self._dig_buf[self._collect_n] = pos
            self._collect_n += 1
        if finished:
            self._finish_motion()
        if self._collecting and self._collect_last > 0 and fb.sync_count >= self._collect_last:
            self._finish_collecting()
        # -- monitors (on the feedback answering this SYNC, against this SYNC's demand)
        self._monitor(w, fb, pos)
        # -- next cycle's reference: what was just commanded
        self._s_ref[:] = guard.position_m
        self._q_ref[:] = self._q_next
        if self.on_cycle is not None:
            self.on_cycle(int(fb.sync_count), clock.now())
        if (self._tel.count & 63) == 0:
            self._publish("")
        return self._maybe_end(fb)

    def _ending(self) -> bool:
        """Nothing left to stream and nothing coming: the job is over (at rest, at the end)."""
        if self._queue or self._motion is not None or self._record_outstanding:
            return False
        if self._final is not None:
            return True
        return self._task_done and not self._plan_outstanding

    def _monitor(self, w: WriteStatus, fb: Any, pos: FloatArray) -> None:
        status = fb.status
        if w is WriteStatus.BUS_ERROR or status is CycleStatus.BUS_ERROR:
            self._begin_stop(ExecStatus.BUS_ERROR, "the bus refused frames")
            return
        if w is WriteStatus.OUT_OF_RANGE:
            self._begin_stop(ExecStatus.FAULT, "a setpoint does not fit its RPDO1 field")
            return
        if status >= CycleStatus.EMCY and status != self._prev_status:
            self._begin_stop(ExecStatus.FAULT, self._describe(status))
        self._prev_status = status
        stale = fb.stale
        self._stale_count += 1
        self._stale_count[~stale] = 0
        axes = self.master.config.axes
        if (self._stale_count >= self.config.stale_cycles).any() and not self._stopping:
            axis = int(np.argmax(self._stale_count))
            self._begin_stop(
                ExecStatus.FAULT,
                f"stale feedback: no TPDO1 from the {axes[axis]} drive for "
                f"{int(self._stale_count[axis])} cycles",
            )
        err = np.abs(pos - self._s_ref)
        over = (err > self.following_error_m) & ~stale
        over &= fb.state == DriveState.OPERATION_ENABLED
        self._fe_count += 1
        self._fe_count[~over] = 0
        if (self._fe_count >= self.config.following_error_cycles).any() and not self._stopping:
            axis = int(np.argmax(self._fe_count))
            self._begin_stop(
                ExecStatus.FAULT,
                f"following error on the {axes[axis]} axis: {err[axis] * 1e3:.2f} mm > "
                f"{self.following_error_m * 1e3:.2f} mm for {int(self._fe_count[axis])} cycles",
            )

    def _drives_at_rest(self, fb: Any) -> bool:
        # A stale axis counts with its last report; only a lost one (its own watchdogs stop it)
        # is not waited for.
        known = ~fb.heartbeat_lost
        slow = np.abs(fb.velocity_um_s) * 1e-6 < self.config.rest_velocity_m_s
        state = fb.state
        ramping = (state == _STOPPING_STATES[0]) | (state == _STOPPING_STATES[1])
        return bool(((slow & ~ramping) | ~known).all())

    def _maybe_end(self, fb: Any) -> LoopAction:
        now = self.loop.clock.now()
        if self._stopping:
            done = self.guard.at_rest and self._drives_at_rest(fb)
            timeout_s = self.config.stop_timeout_s
            if done and self._record_outstanding and now - self._stop_t0 < timeout_s:
                return LoopAction.CONTINUE  # a finished dig's record is on its way: keep it
            if not done and now - self._stop_t0 >= timeout_s:
                self._fault += f"; the stop did not reach rest within {timeout_s} s"
                done = True
            if done:
                self._end()
                return LoopAction.STOP
            return LoopAction.CONTINUE
        if self._phase is not Phase.SETTLE:
            self._settle_t0 = None
            return LoopAction.CONTINUE
        if self._settle_t0 is None:
            self._settle_t0 = now
        if now - self._settle_t0 + 1e-12 >= self.config.settle_s and self._drives_at_rest(fb):
            self._status, self._fault = (
                self._final if self._final is not None else (ExecStatus.DONE, "")
            )
            self._end()
            return LoopAction.STOP
        return LoopAction.CONTINUE

    def _end(self) -> None:
        if self.config.disable_at_end:
            self.master.disable()
        self._publish(self._status.name.lower() if self._status is not None else "")
