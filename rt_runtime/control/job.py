"""The job controller: a trench job (or a prescribed path) dig by dig, one cycle at a time.

:class:`JobController` is a :class:`~rt_runtime.control.controllers.Controller`. From the pose
the drives hold at its start it asks its planner link for the first dig
(:class:`~rt_runtime.control.planner_worker.DigPlan`) and streams the plan's motions, each a
setpoint table built outside the loop (:mod:`rt_runtime.control.setpoints`): the cycle into the
dig (lift out, dump, approach, enter: one blended motion, or rest-to-rest moves), then the dig,
with CONNECT moves where two do not meet. The reported strokes of the dig's SYNCs go back to the
session (``record``: the measured tip path updates the surface) and the next dig is planned
with its cycle from this dig's exit, where the arm holds (at rest) until the plan is there.
Where no dig follows (the session has none left, ``max_digs`` digs ran, the planner failed)
the arm streams the plan's exit moves (lift out, dump to the home pose), then the job settles
at rest and ends. A dig cut short by a stop is not recorded: a restart plans it again from the
session's state. A prescribed path whose motions are steps (a taught trench's cycles,
:attr:`~rt_runtime.control.planner_worker.PathJob.steps`) records each step when its last
sample is sent, the same way; a step cut short is not recorded and a restart streams it again.

Each update, on the feedback answering this cycle's SYNC:

1. the dig's measured path takes the reported strokes; a motion whose last sample was sent
   ends (a dig's feedback one SYNC later, then its record is requested);
2. the monitors: following error (|demand - reported| beyond ``following_error_m`` for
   ``following_error_cycles``), stale feedback (no TPDO1 for ``stale_cycles``), drive state /
   EMCY / heartbeat (the cycle status), bus errors, a guard that refused its target;
3. the end: settled at rest, or the stop at rest;
4. stop requests from other threads, the planner's reply;
5. the next command: the current motion's next sample, a hold, or the guard's stop.

Job states (:class:`JobState`, transitions in :data:`TRANSITIONS`): RUNNING (streaming or
holding for a plan or a pause), SETTLING (nothing left: hold until the drives rest),
STOPPING (the guard's jerk-limited stop from the commanded state), ENDED. Every stop (cancel,
shutdown, fault, overrun policy, bus error) is the guard's stop; a faulted drive runs its own
fault reaction and ignores the setpoints. Stop causes that come together report the worst
(:data:`SEVERITY`).

Nothing in an update plans, blocks or raises: replies come from a planner process, or from an
in-process link whose work runs in :meth:`JobController.service` between cycles. A motion
that does not start at the commanded pose (the planner side chains every motion) is a fault,
never a move planned in the cycle.

Threads. :meth:`request_stop`, :meth:`pause`, :meth:`resume` and :meth:`progress` are safe
from any thread (single assignments read once per update; progress is a snapshot published
every 64 cycles and at every phase change, also within a motion that passes through several
phases). A pause takes effect at the next motion boundary (every motion ends at rest).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime import axes as rig_axes
from rt_runtime.canbus import CycleStatus, DriveState, Emcy, WriteStatus
from rt_runtime.control.controllers import Command, ControllerStatus, GuardFilter, Mode
from rt_runtime.control.guard import GuardState
from rt_runtime.control.hardware import DriveFeedback
from rt_runtime.control.planner_worker import (
    DigPlan,
    PathPlan,
    PlannerError,
    PlannerLink,
    Recorded,
)
from rt_runtime.control.setpoints import CONNECT_TOLERANCE_M, Phase, SampledMotion

__all__ = [
    "SEVERITY",
    "TRANSITIONS",
    "DigRecord",
    "ExecStatus",
    "JobController",
    "JobLimits",
    "JobProgress",
    "JobState",
    "StopRequest",
]

FloatArray = NDArray[np.float64]


class ExecStatus(IntEnum):
    """How a job ended (every status but DONE came through a jerk-limited stop or at rest)."""

    DONE = 0
    #: :meth:`JobController.request_stop` with CANCEL.
    CANCELLED = 1
    #: :meth:`JobController.request_stop` with SHUTDOWN (SIGTERM, daemon stop).
    STOPPED = 2
    #: A monitor tripped: drive fault, EMCY, heartbeat, following error, stale feedback.
    FAULT = 3
    #: The loop's overrun policy asked for a safe stop.
    OVERRUN_STOP = 4
    #: The bus refused frames.
    BUS_ERROR = 5
    #: The planner could not plan or record (the arm finished its current moves first, and
    #: after a dig lifted out and dumped).
    PLANNING_ERROR = 6


class StopRequest(IntEnum):
    """Why a stop is requested from outside."""

    NONE = 0
    CANCEL = 1
    #: SIGTERM / daemon stop.
    SHUTDOWN = 2


class JobState(IntEnum):
    """Where a job is (see the module docstring)."""

    RUNNING = 0
    SETTLING = 1
    STOPPING = 2
    ENDED = 3


#: The job's state machine: the states each state may go to.
TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    JobState.RUNNING: frozenset({JobState.SETTLING, JobState.STOPPING}),
    JobState.SETTLING: frozenset({JobState.STOPPING, JobState.ENDED}),
    JobState.STOPPING: frozenset({JobState.ENDED}),
    JobState.ENDED: frozenset(),
}

#: Severity when several stop causes come together: the worst is reported.
SEVERITY = {
    ExecStatus.DONE: 0,
    ExecStatus.CANCELLED: 1,
    ExecStatus.STOPPED: 2,
    ExecStatus.PLANNING_ERROR: 3,
    ExecStatus.OVERRUN_STOP: 4,
    ExecStatus.FAULT: 5,
    ExecStatus.BUS_ERROR: 6,
}
_STOPPING_STATES = (int(DriveState.QUICK_STOP_ACTIVE), int(DriveState.FAULT_REACTION_ACTIVE))


@dataclass(frozen=True, slots=True)
class JobLimits:
    """The job's monitors and endings (see :class:`~rt_runtime.control.executor.ExecutorConfig`
    for the meaning of each)."""

    following_error_m: float
    following_error_cycles: int
    stale_cycles: int
    stop_timeout_s: float
    rest_velocity_m_s: float
    settle_s: float
    max_digs: int | None
    swing_following_error_rad: float = math.inf


@dataclass(frozen=True, slots=True)
class DigRecord:
    """One dig executed and recorded (handed to ``on_dig_done``).

    Attributes:
        index: Dig index in the task.
        dig_type: ``downward`` or ``backward``.
        T_s: Planned duration.
        plan_us: Planning time of the dig (the planner's wall time for the request).
        planned_volume_m3: Material the planned path removes.
        measured_volume_m3: Material the measured path removed (the trench's own accounting).
        tip_path_m: Measured tip path, work-site frame, ``(n, 2)``.
        session_state: ``TrenchSession.state()`` after the record (JSON-able): persist it to
            resume at the next dig.
        sync_first: SYNC count of the dig's first SYNC.
        sync_last: SYNC count of the SYNC after its last setpoint (the dig's end pose).
        planned_energy_j: W_E of the verified plan.
        planned_ahead: The dig was planned while the one before it ran
            (:attr:`~rt_runtime.control.planner_worker.DigPlan.planned_ahead`; ``plan_us`` is
            then the check against the measured material).
        joined, carried: The dig continues the bucket of the one before it
            (:attr:`~rt_runtime.planning.trench.PlannedDig.joined`, ``carried``).
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
    planned_ahead: bool = False
    joined: bool = False
    carried: bool = False


@dataclass(frozen=True, slots=True)
class JobProgress:
    """A snapshot of a job (see :meth:`JobController.progress`)."""

    phase: str = "idle"
    dig: int = -1
    digs_done: int = 0
    stopping: bool = False
    planning: bool = False
    status: str = ""
    cycles: int = 0


class _Stream:
    """The queued motions and the one streaming: the next sample, the hold pose between."""

    __slots__ = (
        "current",
        "hold_q",
        "hold_s",
        "j",
        "motions",
        "phase",
        "run",
        "segment",
        "segments",
    )

    def __init__(self, q0: FloatArray, s0: FloatArray) -> None:
        self.motions: deque[SampledMotion] = deque()
        self.current: SampledMotion | None = None
        self.j = 0
        self.run = 0  # the current motion's next phase run (SampledMotion.phase_runs)
        self.hold_q = q0.copy()
        self.hold_s = s0.copy()
        self.phase = Phase.WAIT
        self.segment = -1
        self.segments = 0


class _Collector:
    """The reported strokes of a dig's SYNCs (``first .. last``), for its record."""

    __slots__ = ("active", "buf", "dig", "first", "last", "n")

    def __init__(self, capacity: int, n: int = 3) -> None:
        self.buf = np.zeros((capacity, n))
        self.active = False
        self.n = 0
        self.first = -1
        self.last = -1
        self.dig = -1


class _Planning:
    """The planner link and what is outstanding on it."""

    __slots__ = (
        "digs_started",
        "exit",
        "final",
        "last_state",
        "link",
        "plan_out",
        "plan_us",
        "plans",
        "record_out",
        "sync_ranges",
        "task_done",
    )

    def __init__(self, link: PlannerLink) -> None:
        self.link = link
        self.plan_out = False
        self.record_out = False
        self.task_done = False
        #: End at the next rest with this status instead of a stop.
        self.final: tuple[ExecStatus, str] | None = None
        self.last_state: dict[str, Any] | None = None
        self.plan_us = 0.0
        self.plans: dict[int, DigPlan] = {}
        self.sync_ranges: dict[int, tuple[int, int]] = {}
        self.digs_started = 0
        #: The last dig's exit moves, streamed where no dig follows it.
        self.exit: tuple[SampledMotion, ...] = ()

    def release_exit(self, motions: deque[SampledMotion]) -> None:
        """No dig follows the last one: queue its exit moves onto ``motions`` (once)."""
        motions.extend(self.exit)
        self.exit = ()

    def take(self, reply: Any, motions: deque[SampledMotion], stopping: bool) -> DigRecord | None:
        """Book a reply: a plan's motions onto ``motions`` (none while ``stopping`` or ending),
        a record as the :class:`DigRecord` returned, an error as the job's final status (after
        the last dig's exit moves). An error in place of the last dig's record ends the job
        with it, not ``done``: the dig ran but is not recorded (a restart digs it again)."""
        if isinstance(reply, PlannerError):
            lost = self.record_out and self.final is not None and self.final[0] is ExecStatus.DONE
            self.plan_out = False
            self.record_out = False
            if self.final is None or lost:
                if not stopping:
                    self.release_exit(motions)
                self.final = (ExecStatus.PLANNING_ERROR, reply.message)
            return None
        if isinstance(reply, Recorded):
            self.record_out = False
            self.last_state = reply.state
            plan = self.plans.get(reply.index)
            dig = plan.dig if plan is not None else None
            first, last = self.sync_ranges.get(reply.index, (-1, -1))
            return DigRecord(
                index=reply.index,
                dig_type=dig.dig_type.name.lower() if dig is not None else reply.step,
                T_s=dig.T_s if dig is not None else reply.duration_s,
                plan_us=plan.plan_us if plan is not None else math.nan,
                planned_volume_m3=dig.volume_m3 if dig is not None else math.nan,
                measured_volume_m3=reply.measured_volume_m3,
                tip_path_m=reply.tip_path_m,
                session_state=reply.state,
                sync_first=first,
                sync_last=last,
                planned_energy_j=dig.energy_j if dig is not None else math.nan,
                planned_ahead=plan.planned_ahead if plan is not None else False,
                joined=dig.joined if dig is not None else False,
                carried=dig.carried if dig is not None else False,
            )
        self.plan_out = False
        self.plan_us += reply.plan_us
        if isinstance(reply, PathPlan):
            if not (stopping or self.final is not None):
                motions.extend(reply.sampled)
            self.task_done = True
            return None
        assert isinstance(reply, DigPlan)
        if stopping or self.final is not None:
            return None
        if reply.travel:
            self.release_exit(motions)
            self.final = (
                ExecStatus.PLANNING_ERROR,
                f"the task needs crawler travel ({reply.travel[0].distance_m:+.3f} m); the "
                "executor does not drive the VCU yet",
            )
            return None
        motions.extend(reply.sampled)
        if reply.dig is None:
            self.task_done = True
            motions.extend(reply.exit_sampled)
            self.exit = ()
        else:
            self.plans[reply.dig.index] = reply
            self.exit = reply.exit_sampled
        return None


class _Monitors:
    """Following error, stale feedback, drive faults and bus errors (see the module
    docstring): the causes to stop for, in the order found. Per-axis counts in plain Python
    (three axes: cheaper than numpy's per-call cost)."""

    __slots__ = (
        "axes",
        "causes",
        "describe",
        "fe_count",
        "limits",
        "prev_status",
        "stale_count",
        "windows",
    )

    def __init__(
        self, limits: JobLimits, axes: tuple[str, ...], describe: Callable[[CycleStatus], str]
    ) -> None:
        self.limits = limits
        self.axes = axes
        self.describe = describe
        self.fe_count = [0] * len(axes)
        self.stale_count = [0] * len(axes)
        # The swing (axis 3, rad) has its own window; the cylinders share one (m).
        self.windows = [limits.following_error_m] * 3 + [limits.swing_following_error_rad] * (
            len(axes) - 3
        )
        self.prev_status = CycleStatus.OK
        self.causes: list[tuple[ExecStatus, str]] = []

    def check(
        self, fb: DriveFeedback, s_ref: FloatArray, stopping: bool
    ) -> list[tuple[ExecStatus, str]]:
        """The stop causes of this feedback against the demand ``s_ref`` at its SYNC."""
        causes = self.causes
        causes.clear()
        status = fb.status
        if fb.write_status is WriteStatus.BUS_ERROR or status is CycleStatus.BUS_ERROR:
            causes.append((ExecStatus.BUS_ERROR, "the bus refused frames"))
            return causes
        if fb.write_status is WriteStatus.OUT_OF_RANGE:
            causes.append((ExecStatus.FAULT, "a setpoint does not fit its RPDO1 field"))
            return causes
        if status >= CycleStatus.EMCY and status != self.prev_status:
            causes.append((ExecStatus.FAULT, self.describe(status)))
            stopping = True
        self.prev_status = status
        limits = self.limits
        stale = fb.stale.tolist()
        count = self.stale_count
        worst = 0
        for i, gone in enumerate(stale):
            count[i] = count[i] + 1 if gone else 0
            if count[i] > count[worst]:
                worst = i
        if count[worst] >= limits.stale_cycles and not stopping:
            causes.append(
                (
                    ExecStatus.FAULT,
                    f"stale feedback: no TPDO1 from the {self.axes[worst]} drive for "
                    f"{count[worst]} cycles",
                )
            )
            stopping = True
        pos = fb.stroke_m.tolist()
        ref = s_ref.tolist()
        enabled = (fb.state == DriveState.OPERATION_ENABLED).tolist()
        windows = self.windows
        fe = self.fe_count
        worst = 0
        for i, gone in enumerate(stale):
            over = abs(pos[i] - ref[i]) > windows[i] and not gone and enabled[i]
            fe[i] = fe[i] + 1 if over else 0
            if fe[i] > fe[worst]:
                worst = i
        if fe[worst] >= limits.following_error_cycles and not stopping:
            err = abs(pos[worst] - ref[worst])
            scale, unit = (math.degrees(1.0), "deg") if worst == 3 else (1e3, "mm")
            causes.append(
                (
                    ExecStatus.FAULT,
                    f"following error on the {self.axes[worst]} axis: {err * scale:.2f} {unit} "
                    f"> {windows[worst] * scale:.2f} {unit} for {fe[worst]} cycles",
                )
            )
        return causes


class JobController:
    """A trench job or a prescribed path as a controller (see the module docstring).

    Args:
        link: The planner link (inline, process or path).
        guard: The guard filter the manager passes every command through (the job reads its
            state and commanded stroke).
        limits: Monitors and endings.
        rig: The rig (stroke mapping of the start pose).
        axes: The axes' names (messages).
        describe: Text of the drives' state for a fault message (outside the hot path).
        on_record: Called with each :class:`DigRecord` on the loop's thread (hand it to
            another thread for slow work); must not raise.
        dig_capacity: Samples a dig's measured path can hold.
    """

    def __init__(
        self,
        link: PlannerLink,
        guard: GuardFilter,
        limits: JobLimits,
        rig: Any,
        axes: tuple[str, ...],
        describe: Callable[[CycleStatus], str],
        on_record: Callable[[DigRecord], None],
        dig_capacity: int,
    ) -> None:
        self.guard = guard
        self.limits = limits
        self.rig = rig
        self.monitors = _Monitors(limits, axes, describe)
        self._on_record = on_record
        self.planning = _Planning(link)
        n = len(axes)
        self.collector = _Collector(dig_capacity, n)
        self.stream: _Stream | None = None
        self.command = Command(n)
        self.state = JobState.RUNNING
        self.status: ExecStatus | None = None
        self.fault = ""
        self.digs: list[DigRecord] = []
        self.emcys: list[Emcy] = []
        self._stop_request = StopRequest.NONE
        self._paused = False
        self._progress = JobProgress()
        self._s_ref = np.zeros(n)  # the demand at the SYNC the next feedback answers
        self._t0_s = -1.0  # when the settle or the stop began (-1: at the next update)
        self._updates = 0

    # -- any thread -----------------------------------------------------------------------------

    def request_stop(self, why: StopRequest) -> None:
        """Ask for a jerk-limited stop (any thread; SHUTDOWN wins over CANCEL)."""
        if int(why) > int(self._stop_request):
            self._stop_request = StopRequest(why)

    def pause(self) -> None:
        """Hold at the next motion boundary (any thread)."""
        self._paused = True

    def resume(self) -> None:
        """Continue after :meth:`pause` (any thread)."""
        self._paused = False

    @property
    def paused(self) -> bool:
        """A pause is requested."""
        return self._paused

    def progress(self) -> dict[str, Any]:
        """A JSON-able snapshot (any thread): ``phase``, ``dig`` (index streaming or -1),
        ``digs_done``, ``paused``, ``stopping``, ``status`` (empty while running), ``cycles``,
        ``planning`` (a plan request is outstanding)."""
        p = self._progress
        return {
            "phase": p.phase,
            "dig": p.dig,
            "digs_done": p.digs_done,
            "paused": self._paused,
            "stopping": p.stopping,
            "status": p.status,
            "cycles": p.cycles,
            "planning": p.planning,
        }

    def publish(self, status: str = "", cycles: int = -1) -> None:
        """Publish the progress snapshot."""
        stream = self.stream
        phase = stream.phase if stream is not None else Phase.WAIT
        current = stream.current if stream is not None else None
        self._progress = JobProgress(
            phase=phase.name.lower(),
            dig=current.dig_index if current is not None and phase is Phase.DIG else -1,
            digs_done=len(self.digs),
            stopping=self.state is JobState.STOPPING,
            planning=self.planning.plan_out,
            status=status,
            cycles=self._progress.cycles if cycles < 0 else cycles,
        )

    # -- outside the loop -----------------------------------------------------------------------

    def start(self, s0_m: FloatArray) -> Command:
        """Begin at the commanded stroke ``s0_m`` (the drives stand on it): the first plan
        request, answered in-process here when the link answers in-process; the first
        command. Outside the loop (any thread, before the switch to this controller)."""
        s0 = np.asarray(s0_m, dtype=np.float64).copy()
        q0 = rig_axes.actuator_to_joint(self.rig, s0, check_limits=False)
        self.stream = _Stream(q0, s0)
        self._s_ref[:] = s0
        self.planning.plan_out = True
        self.planning.link.request_plan(q0.copy())
        self.planning.link.service()
        self._poll()
        self._next_command()
        self.publish()
        return self.command

    def service(self) -> None:
        """In-process planner work (between cycles)."""
        self.planning.link.service()

    def close(self) -> None:
        """Release the planner link."""
        self.planning.link.close()

    # -- the cycle ------------------------------------------------------------------------------

    def _go(self, state: JobState) -> bool:
        if state not in TRANSITIONS[self.state]:
            return False
        self.state = state
        self._t0_s = -1.0
        return True

    def overrun(self, consecutive: int, lateness_s: float) -> None:
        """The loop's overrun policy asks for a safe stop."""
        if self._escalates(ExecStatus.OVERRUN_STOP):
            self._begin_stop(
                ExecStatus.OVERRUN_STOP,
                f"{consecutive} consecutive loop overruns (last {lateness_s * 1e6:.0f} us late)",
            )

    def update(
        self, t_s: float, period_s: float, feedback: DriveFeedback
    ) -> tuple[Command, ControllerStatus]:
        """The command for the next SYNC (see the module docstring). Loop safe."""
        fb = feedback
        stream = self.stream
        assert stream is not None
        if fb.emcys:
            self.emcys.extend(fb.emcys)
        col = self.collector
        if col.active and col.first < 0:
            col.first = fb.sync_count  # the SYNC that carried the dig's first sample
        if col.active and fb.fresh and col.n < len(col.buf):
            col.buf[col.n] = fb.stroke_m
            col.n += 1
        current = stream.current
        if current is not None and stream.j >= current.n:
            self._finish_motion(fb.sync_count)
        if col.active and col.last > 0 and fb.sync_count >= col.last:
            self._finish_collecting()
        if self.guard.guard.state is GuardState.ERROR and self.state is JobState.RUNNING:
            self._begin_stop(ExecStatus.FAULT, "the limit guard refused the setpoint")
        causes = self.monitors.check(fb, self._s_ref, self.state is JobState.STOPPING)
        for status, text in causes:
            self._begin_stop(status, text)
        if self._ending_reached(t_s, fb):
            self.state = JobState.ENDED
            self.publish(self.status.name.lower() if self.status is not None else "")
            return self.command, ControllerStatus.ENDED
        if self.state is not JobState.STOPPING:
            request = self._stop_request
            if request is StopRequest.SHUTDOWN:
                self._begin_stop(ExecStatus.STOPPED, "shutdown requested")
            elif request is StopRequest.CANCEL:
                self._begin_stop(ExecStatus.CANCELLED, "cancelled")
        self._poll()
        self._s_ref[:] = self.guard.position_m
        self._next_command()
        self._updates += 1
        if (self._updates & 63) == 0:
            self.publish(cycles=self._updates)
        return self.command, ControllerStatus.RUNNING

    def fail(self, text: str) -> tuple[Command, ControllerStatus]:
        """The update raised (a bug): the guard's stop, or the end when it was stopping."""
        if self.state is JobState.STOPPING:
            self.status = ExecStatus.FAULT
            self.fault += f"; {text} during the stop"
            self.state = JobState.ENDED
            return self.command, ControllerStatus.ENDED
        self._begin_stop(ExecStatus.FAULT, text)
        self._next_command()
        return self.command, ControllerStatus.RUNNING

    def _poll(self) -> None:
        reply = self.planning.link.poll()
        if reply is None:
            return
        stream = self.stream
        assert stream is not None
        record = self.planning.take(reply, stream.motions, self.state is JobState.STOPPING)
        if record is not None:
            self.digs.append(record)
            self._on_record(record)

    def _next_command(self) -> None:
        """The next sample, a hold, or the stop, into :attr:`command`."""
        cmd = self.command
        stream = self.stream
        assert stream is not None
        cmd.quick_stop = False
        if self.state is JobState.STOPPING:
            cmd.mode = Mode.STOP
            cmd.q_rad[:] = stream.hold_q
            cmd.phase = int(Phase.STOP)
            cmd.segment = -1
            cmd.dig = -1
            cmd.tracking = False
            return
        if stream.current is None and not self._start_next():
            self._next_command()  # the next motion began a stop
            return
        motion = stream.current
        if motion is None:
            if stream.phase is Phase.WAIT and self._nothing_left():
                stream.phase = Phase.SETTLE
                self._go(JobState.SETTLING)
            cmd.hold(stream.hold_s, stream.hold_q, stream.phase)
            return
        j = stream.j
        runs = motion.phase_runs
        if stream.run < len(runs) and j >= runs[stream.run][0]:
            stream.phase = runs[stream.run][1]
            stream.run += 1
            self.publish()
        cmd.mode = Mode.TRACK
        cmd.stroke_m[:] = motion.stroke_m[j]
        cmd.rate_m_s[:] = motion.rate_m_s[j]
        cmd.accel_m_s2[:] = motion.accel_m_s2[j]
        cmd.q_rad[:] = motion.q_rad[j]
        cmd.phase = int(stream.phase)
        cmd.segment = stream.segment
        cmd.dig = motion.dig_index if stream.phase is Phase.DIG else -1
        cmd.tracking = True
        stream.j = j + 1

    def _start_next(self) -> bool:
        """At a motion boundary: start the next queued motion; False when that began a stop."""
        stream = self.stream
        assert stream is not None
        if self._paused or not stream.motions:
            if stream.phase is not Phase.WAIT and stream.phase is not Phase.SETTLE:
                stream.phase = Phase.WAIT
                self.publish()
            return True
        motion = stream.motions[0]
        if float(np.max(np.abs(motion.stroke_start_m - stream.hold_s))) > CONNECT_TOLERANCE_M:
            # The planner side chains every motion: a gap is a bug, never planned here.
            self._begin_stop(
                ExecStatus.FAULT,
                f"the next motion ({motion.phase.name.lower()}) does not start at the "
                "commanded pose",
            )
            return False
        stream.motions.popleft()
        stream.current = motion
        stream.j = 0
        stream.run = 1
        stream.phase = motion.phase
        stream.segment = stream.segments
        stream.segments += 1
        if motion.phase is Phase.DIG:
            col = self.collector
            plan = self.planning
            plan.digs_started += 1
            if self.limits.max_digs is not None and plan.digs_started >= self.limits.max_digs:
                plan.release_exit(stream.motions)  # the job's last dig: its exit follows it
            col.active = True
            col.n = 0
            col.first = -1  # the SYNC of its first sample, taken at the next update
            col.last = -1
            col.dig = motion.dig_index
        self.publish()
        return True

    def _finish_motion(self, sync_count: int) -> None:
        """The current motion sent its end pose: hold it; a dig's feedback ends one SYNC later,
        a path's step (:attr:`~rt_runtime.control.planner_worker.PathJob.steps`) is recorded
        now."""
        stream = self.stream
        assert stream is not None and stream.current is not None
        motion = stream.current
        stream.hold_q[:] = motion.q_rad[-1]
        stream.hold_s[:] = motion.stroke_m[-1]
        if stream.phase is Phase.DIG:
            self.collector.last = sync_count + 1
        elif motion.phase is Phase.PATH and motion.dig_index >= 0:
            plan = self.planning
            plan.sync_ranges[motion.dig_index] = (-1, sync_count + 1)
            plan.record_out = True
            plan.link.request_record(self.collector.buf[:0], False)
        stream.current = None
        stream.segment = -1

    def _finish_collecting(self) -> None:
        col = self.collector
        col.active = False
        plan = self.planning
        last = self.limits.max_digs is not None and plan.digs_started >= self.limits.max_digs
        plan_next = not (
            last or self.state is JobState.STOPPING or plan.final is not None or plan.task_done
        )
        plan.sync_ranges[col.dig] = (col.first, col.last)
        plan.record_out = True
        plan.plan_out = plan_next
        plan.link.request_record(col.buf[: col.n], plan_next)
        if last and plan.final is None:
            plan.final = (ExecStatus.DONE, "")

    # -- stops and endings ----------------------------------------------------------------------

    def _escalates(self, status: ExecStatus) -> bool:
        return (
            self.state is not JobState.STOPPING
            or self.status is None
            or SEVERITY[status] > SEVERITY[self.status]
        )

    def _begin_stop(self, status: ExecStatus, text: str) -> None:
        """Start the guard's stop (or, during one, report a more severe cause)."""
        if self.state is JobState.STOPPING:
            if self._escalates(status):
                self.status = status
                self.fault = f"{self.fault}; then {text}" if self.fault else text
            return
        if not self._go(JobState.STOPPING):
            return
        col = self.collector
        if col.active and col.last < 0:
            col.active = False  # the dig was cut short: not recorded, a restart plans it again
        self.status = status
        self.fault = text
        stream = self.stream
        assert stream is not None
        stream.current = None
        stream.motions.clear()
        stream.phase = Phase.STOP
        stream.segment = -1
        self.publish()

    def _nothing_left(self) -> bool:
        """Nothing left to stream and nothing coming: the job is over."""
        stream = self.stream
        plan = self.planning
        assert stream is not None
        if stream.motions or stream.current is not None or plan.record_out:
            return False
        if plan.final is not None:
            return True
        return plan.task_done and not plan.plan_out

    def _drives_at_rest(self, fb: DriveFeedback) -> bool:
        # A stale axis counts with its last report; only a lost one (its own watchdogs stop it)
        # is not waited for.
        known = ~fb.heartbeat_lost
        slow = np.abs(fb.last_velocity_m_s) < self.limits.rest_velocity_m_s
        state = fb.state
        ramping = (state == _STOPPING_STATES[0]) | (state == _STOPPING_STATES[1])
        return bool(((slow & ~ramping) | ~known).all())

    def _ending_reached(self, now: float, fb: DriveFeedback) -> bool:
        """The job ends with this cycle: the stop or the settle is at rest."""
        limits = self.limits
        if self.state is JobState.STOPPING:
            if self._t0_s < 0.0:
                self._t0_s = now
            done = self.guard.at_rest and self._drives_at_rest(fb)
            timeout_s = limits.stop_timeout_s
            if done and self.planning.record_out and now - self._t0_s < timeout_s:
                return False  # a finished dig's record is on its way: keep it
            if not done and now - self._t0_s >= timeout_s:
                self.fault += f"; the stop did not reach rest within {timeout_s} s"
                done = True
            return done and self._go(JobState.ENDED)
        if self.state is not JobState.SETTLING:
            return False
        if self._t0_s < 0.0:
            self._t0_s = now
        if now - self._t0_s + 1e-12 >= limits.settle_s and self._drives_at_rest(fb):
            final = self.planning.final
            self.status, self.fault = final if final is not None else (ExecStatus.DONE, "")
            return self._go(JobState.ENDED)
        return False
