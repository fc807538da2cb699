"""The daemon's runner: the thread that owns the drives, one controller manager for its life.

:class:`RigRunner` boots and enables the drives, then runs one
:class:`~rt_runtime.control.manager.ControllerManager` on one fixed-rate loop until the daemon
stops. Between jobs the :class:`~rt_runtime.control.controllers.HoldController` holds every axis
at its last commanded stroke (the drives' SYNC watchdog never starves) and quick-stops them on
a fault. A preparation thread builds each job off the loop (its planner session, new or
restored from the job store; its planner process; its
:class:`~rt_runtime.control.job.JobController` started at the held stroke, and the job's
telemetry); once the drives stand on the held target the runner switches to the job at a cycle
boundary, and when the job ends, back to the hold at the next: the SYNC stream never pauses.

The job's outcome goes into the job store (in memory; its writer thread persists), its report
(log lines, the telemetry file in the state directory) to a thread.

Threads: the preparation and the work after a job (its report, closing a controller that never
ran) run on two threads started with the runner (:class:`_Worker`), which the loop's thread
hands work through a queue; the loop's thread starts no thread (``Thread.start`` waits until the
new thread runs, and the new thread's stack is mapped with the interpreter lock held).

Real time: the RT settings are applied once to the runner thread for its life. The heap is
frozen after boot and when a job is prepared (``gc.freeze`` is O(1)), and the collector is off
while a job runs (switched at the boundaries); cyclic garbage made before a freeze is never
collected while the daemon runs (a restart frees it).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import os
import queue
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import can
import numpy as np

from rt_runtime import actuation
from rt_runtime.canbus import CanMaster
from rt_runtime.control.clock import Clock, MonotonicClock
from rt_runtime.control.controllers import Command, GuardFilter, HoldController
from rt_runtime.control.executor import ExecutorConfig
from rt_runtime.control.guard import LimitGuard, StrokeLimits
from rt_runtime.control.hardware import DriveInterface
from rt_runtime.control.job import DigRecord, ExecStatus, JobController, StopRequest
from rt_runtime.control.loop import FixedRateLoop, LoopConfig, OverrunPolicy
from rt_runtime.control.manager import ControllerManager, executor_telemetry
from rt_runtime.control.planner_worker import ProcessPlanner
from rt_runtime.control.rt import RtSettings, apply_rt, restore_rt
from rt_runtime.control.setpoints import Phase
from rt_runtime.control.telemetry import Telemetry
from rt_runtime.errors import CommunicationError, ExcavatorRtError
from rt_runtime.planning.trench import TrenchPlanner, TrenchSession, make_task
from rt_runtime.service.config import DaemonConfig
from rt_runtime.service.jobstore import ACTIVE, DIG_KEYS, Job, JobError, JobStatus, JobStore
from rt_runtime.service.preflight import loop_rt_settings, timing_self_test

if TYPE_CHECKING:
    from rt_runtime.planning.trench import TrenchTask
    from rt_runtime.rig import Rig

__all__ = ["JOB_TELEMETRY_ROWS", "SETTLED_M", "SETTLE_TIMEOUT_S", "STALE_LOOP_S", "RigRunner"]

log = logging.getLogger("excavator-rtd")

#: The runner's loop must have cycled within this long for WATCHDOG=1 (s).
STALE_LOOP_S = 0.5
#: Before a job starts, the drives must stand within this of the held target (m) ...
SETTLED_M = 1e-6
#: ... or this long must have passed (s).
SETTLE_TIMEOUT_S = 2.0
#: Longest wait for the drives to leave OPERATION_ENABLED when the runner stops (s).
POWER_DOWN_TIMEOUT_S = 0.5
#: Telemetry rows of a job's run (the last 32 s at 500 Hz go to the state directory).
JOB_TELEMETRY_ROWS = 16_384


def _task_of(job: Job, rig: Rig) -> TrenchTask:
    t = job.task
    return make_task(
        rig, t["length_m"], t["depth_m"], t["beta1_deg"], t["beta2_deg"], t["start_x_m"],
        name=t["name"],
    )  # fmt: skip


@dataclass(slots=True)
class _PreparedJob:
    """A job ready to run: its controller (started at the held stroke), first command and
    telemetry."""

    job: Job
    controller: JobController
    first: Command
    telemetry: Telemetry
    started_s: float = math.nan


@dataclass(frozen=True, slots=True)
class _Parts:
    """What the runner builds once for its life."""

    drives: DriveInterface
    guard: GuardFilter
    hold: HoldController
    manager: ControllerManager
    hold_telemetry: Telemetry


class _Worker:
    """A thread started once that runs the calls queued to it, in order (see the module
    docstring); a call that raises is logged and the thread goes on.

    Args:
        name: The thread's name.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._queue: queue.SimpleQueue[tuple[Any, tuple[Any, ...]]] = queue.SimpleQueue()
        threading.Thread(target=self._run, name=name, daemon=True).start()

    def submit(self, fn: Any, *args: Any) -> None:
        """Queue ``fn(*args)`` (loop safe: a queue put)."""
        self._queue.put((fn, args))

    def _run(self) -> None:
        while True:
            fn, args = self._queue.get()
            try:
                fn(*args)
            except Exception:
                log.exception("%s: %s failed", self.name, getattr(fn, "__name__", fn))


class _Preparation:
    """Builds each job off the loop's thread (see the module docstring) and takes its dig
    records off the loop's thread into the store.

    Args:
        runner: The runner (rig, configuration, store).
        planner: The configured trench planner (more are built by name when a job asks).
    """

    def __init__(self, runner: RigRunner, planner: TrenchPlanner) -> None:
        self.runner = runner
        self.planners: dict[str, TrenchPlanner] = {runner.config.planner: planner}
        #: Feed-forward and stale-cycle limit for the next job (SIGHUP reload).
        self.options = (runner.config.feedforward, runner.config.stale_cycles)
        self.prepared: _PreparedJob | None = None
        self._preparing = False
        self._worker = _Worker("prepare")
        #: Work after a job: its report, closing a controller that never ran.
        self.after = _Worker("job-after")
        self.records: queue.SimpleQueue[tuple[int, DigRecord]] = queue.SimpleQueue()
        threading.Thread(target=self._record_loop, name="dig-records", daemon=True).start()

    def busy(self) -> bool:
        """A preparation is queued or runs."""
        return self._preparing

    def start(self, job: Job, held_m: Any, parts: _Parts) -> None:
        """Prepare ``job`` on the preparation thread, its controller starting at the held
        stroke (loop safe: a queue put)."""
        self._preparing = True
        self._worker.submit(self._prepare_once, job, held_m, parts)

    def _prepare_once(self, job: Job, held_m: Any, parts: _Parts) -> None:
        try:
            self._prepare(job, held_m, parts)
        finally:
            self._preparing = False

    def _planner(self, name: str) -> TrenchPlanner:
        if name not in self.planners:
            r = self.runner
            self.planners[name] = TrenchPlanner(r.rig, name, model_dir=r.config.models_dir)
        return self.planners[name]

    def _prepare(self, job: Job, held_m: Any, parts: _Parts) -> None:
        """The job's session (new, or restored at the next undone dig), its planner process
        and its controller started at the held stroke."""
        r = self.runner
        rig, period = r.rig, r.period_s
        done = len(job.digs)
        if job.max_digs is not None and done >= job.max_digs:
            r.store.set_status(job.id, JobStatus.DONE)
            r.job_prepared(None)
            return
        try:
            planner = self._planner(job.planner)
            task = _task_of(job, rig)
            if job.session_state is None:
                session = planner.start(task)
            else:
                session = TrenchSession.restore(planner, task, job.session_state)
            options = ExecutorConfig(
                feedforward=self.options[0],
                stale_cycles=self.options[1],
                max_digs=None if job.max_digs is None else job.max_digs - done,
            )
            t_max = rig.planning.t_max_s if rig.planning is not None else 10.0
            records = self.records
            controller = JobController(
                ProcessPlanner(session, period_s=period),
                parts.guard,
                options.limits(rig),
                rig,
                parts.drives.axes,
                parts.drives.describe,
                lambda rec: records.put((job.id, rec)),
                int(2.0 * t_max / period) + 16,
            )
            first = controller.start(held_m)
            telemetry = executor_telemetry(JOB_TELEMETRY_ROWS)
        except (ExcavatorRtError, KeyError, TypeError, ValueError) as exc:
            log.error("job %d cannot start: %s", job.id, exc)
            r.store.set_status(job.id, JobStatus.FAILED, f"cannot start: {exc}")
            r.job_prepared(None)
            return
        # Everything alive now moves out of the collector's reach: O(1) here, and the job runs
        # with the collector off (see the module docstring).
        gc.freeze()
        self.prepared = _PreparedJob(job, controller, first, telemetry)

    def _record_loop(self) -> None:
        """Each dig's record: its summary and the session state into the store (its writer
        thread persists), the log line."""
        store = self.runner.store
        while True:
            job_id, rec = self.records.get()
            store.record_dig(job_id, {k: getattr(rec, k) for k in DIG_KEYS}, rec.session_state)
            log.info(
                "job %d: dig %d done (%s, planned %.2f L, measured %.2f L)",
                job_id,
                rec.index,
                rec.dig_type,
                rec.planned_volume_m3 * 1e3,
                rec.measured_volume_m3 * 1e3,
            )


class RigRunner:
    """The runner thread on a real bus (see the module docstring).

    Args:
        config: The daemon's configuration (loop, executor options).
        rig: The rig.
        planner: The trench planner of ``config.planner`` (models loaded and checked).
        bus: The bus (traced or not); the runner's master becomes its only reader.
        store: The job store.
        clock: Wall clock (``MonotonicClock``).

    Attributes:
        error: Why the thread ended when it ended on its own (empty otherwise).
        enable_syncs: SYNCs the master had sent when the drives were enabled.
    """

    def __init__(
        self,
        config: DaemonConfig,
        rig: Rig,
        planner: TrenchPlanner,
        bus: can.BusABC,
        store: JobStore,
        clock: Clock | None = None,
    ) -> None:
        self.config = config
        self.rig = rig
        self.bus = bus
        self.store = store
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self.period_s = config.loop.period_s
        self._prep = _Preparation(self, planner)
        self.error = ""
        self.enable_syncs = 0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._stop = False
        self._job: _PreparedJob | None = None  # running
        self._job_id: int | None = None
        self._beat_s = -math.inf
        self._fault = ""
        self._state = "starting"
        self._parts: _Parts | None = None

    # -- the service's side -------------------------------------------------------------------

    def start(self) -> None:
        """See :meth:`Runner.start`."""
        self._thread = threading.Thread(target=self._main, name="runner", daemon=True)
        self._thread.start()
        timeout_s = 4.0 * self.config.bus.boot_timeout_s + 30.0
        if not self._ready.wait(timeout_s):
            raise CommunicationError(f"the drives did not boot and enable within {timeout_s} s")
        if self._start_error is not None:
            raise self._start_error

    def shutdown(self, timeout_s: float) -> bool:
        """See :meth:`Runner.shutdown`."""
        with self._lock:
            self._stop = True
            running = self._job
        if running is not None:
            running.controller.request_stop(StopRequest.SHUTDOWN)
        if self._thread is None:
            return True
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def alive(self) -> bool:
        """See :meth:`Runner.alive`."""
        return self._thread is not None and self._thread.is_alive()

    def health(self) -> tuple[bool, str]:
        """See :meth:`Runner.health`."""
        if self._fault:
            return False, f"fault latched: {self._fault}"
        age = self.clock.now() - self._beat_s
        if age > STALE_LOOP_S:
            return False, f"the loop has not cycled for {age:.3f} s"
        return True, ""

    def state(self) -> str:
        """See :meth:`Runner.state` (a running job that is paused says so)."""
        if self._fault:
            return f"fault: {self._fault}"
        running = self._job
        if running is not None and running.controller.paused:
            return f"job {self._job_id} paused, holding position"
        return self._state

    def current_job(self) -> int | None:
        """See :meth:`Runner.current_job`."""
        return self._job_id

    def progress(self) -> dict[str, Any] | None:
        """See :meth:`Runner.progress`."""
        running = self._job
        return None if running is None else dict(running.controller.progress())

    def pause(self) -> None:
        """See :meth:`Runner.pause` (a job still being prepared: its store status decides)."""
        with self._lock:
            if self._job is not None:
                self._job.controller.pause()

    def resume(self) -> None:
        """See :meth:`Runner.resume`."""
        with self._lock:
            if self._job is not None:
                self._job.controller.resume()

    def cancel(self) -> None:
        """See :meth:`Runner.cancel` (a job still being prepared is cancelled in the store and
        never starts)."""
        with self._lock:
            running, job_id = self._job, self._job_id
        if running is not None:
            running.controller.request_stop(StopRequest.CANCEL)
        elif job_id is not None:
            with contextlib.suppress(JobError):
                self.store.cancel(job_id)

    def configure(self, feedforward: bool, stale_cycles: int) -> None:
        """See :meth:`Runner.configure` (from the next job on)."""
        self._prep.options = (feedforward, stale_cycles)

    # -- the thread ---------------------------------------------------------------------------

    def _main(self) -> None:
        report = apply_rt(loop_rt_settings(self.config))
        _reset_rt_on_fork()
        # Before the bus: what this host holds, in numbers, where the drives' watchdogs and the
        # overrun stop would trip later (preflight's module docstring).
        timing = timing_self_test(
            self.clock,
            self.period_s,
            report,
            sync_watchdog_s=self.rig.drives.sync_timeout_s,
            max_consecutive_overruns=self.config.loop.max_consecutive_overruns,
        )
        log.info("%s", timing.summary())
        for warning in timing.warnings:
            log.warning("host: %s", warning)
        master: CanMaster | None = None
        try:
            try:
                self._state = "booting the drives"
                master = CanMaster(self.bus, self.rig, period_s=self.period_s)
                timeout_s = self.config.bus.boot_timeout_s
                infos = master.boot(self.clock.now, timeout_s)
                log.info(
                    "drives booted: %s",
                    ", ".join(f"{i.axis} node {i.node_id} {i.device_name!r}" for i in infos),
                )
                # Keep what boot built out of later collections: the loop's first cycles, right
                # after enable, must be short (the drives' SYNC watchdog runs from enable on).
                gc.collect()
                gc.freeze()
                manager, hold = self._build(master)
                master.enable(self.clock.now, timeout_s)
                self.enable_syncs = master.feedback.sync_count
                self._state = self._idle_state()
            except BaseException as exc:
                self._start_error = exc
                return
            finally:
                self._ready.set()
            s0 = master.last_target_um().astype(np.float64) * 1e-6
            self._hold_at(s0)
            self._store_changed()
            manager.run(hold, hold.command, s0, hold.command.q_rad)
            self._state = "stopped"
        except Exception as exc:
            self.error = f"runner failed: {type(exc).__name__}: {exc}"
            log.exception("runner failed")
            with contextlib.suppress(Exception):
                if master is not None:
                    master.quick_stop()
        finally:
            restore_rt(report)

    def _build(self, master: CanMaster) -> tuple[ControllerManager, HoldController]:
        """The drives, the guard, the hold and the manager, once for the runner's life."""
        cfg = self.config.loop
        loop = FixedRateLoop(
            self.clock,
            LoopConfig(
                period_s=self.period_s,
                spin_s=min(2e-4, 0.25 * self.period_s),
                rt=RtSettings(None, False, None, None, False),
                overrun=OverrunPolicy(max_consecutive=cfg.max_consecutive_overruns),
            ),
            executor_telemetry(1024),
        )
        drives = DriveInterface(master, self.clock, 0.0, self._prep.options[0])
        drives.react_to_faults(False)
        guard = GuardFilter(LimitGuard(StrokeLimits.from_rig(self.rig), self.period_s))
        hold = HoldController(np.zeros(3), np.zeros(3), SETTLED_M)
        manager = ControllerManager(
            drives, guard, loop, on_cycle=self._on_cycle, on_ended=self._job_ended
        )
        self._parts = _Parts(drives, guard, hold, manager, manager.loop.telemetry)
        return manager, hold

    def _hold_at(self, stroke_m: Any) -> None:
        """Hold ``stroke_m`` from the next cycle (the guard leaves any stop there)."""
        assert self._parts is not None
        guard, hold = self._parts.guard, self._parts.hold
        s = np.asarray(stroke_m, dtype=np.float64)
        guard.guard.reset(s)
        q = actuation.stroke_to_joint(self.rig, s, check_limits=False)
        hold.command.hold(s, q, Phase.WAIT)

    def _store_changed(self) -> None:
        self.store.changed.set()  # look for work once on entry

    def _on_cycle(self, _sync: int, now_s: float) -> None:
        """Every cycle, on the loop's thread: liveness; while holding, the fault latch, the
        stop, the next job's preparation and the switch to it."""
        self._beat_s = now_s
        assert self._parts is not None
        hold, manager = self._parts.hold, self._parts.manager
        if manager.controller is not hold:
            return
        if hold.fault and not self._fault:
            self._fault = hold.fault
        if self._stop:
            if self._state != "stopping: disabling the drives":
                self._state = "stopping: disabling the drives"
                hold.power_down(POWER_DOWN_TIMEOUT_S)
            return
        prepared = self._prep.prepared
        if prepared is not None:
            if math.isnan(prepared.started_s):
                prepared.started_s = now_s
            late = now_s - prepared.started_s >= SETTLE_TIMEOUT_S
            if hold.settled or late:
                if not hold.settled:
                    log.warning(
                        "job start: drives not on the held target after %.1f s", SETTLE_TIMEOUT_S
                    )
                self._switch_to(prepared)
            return
        changed = self.store.changed
        if changed.is_set() and not self._fault and not self._prep.busy():
            changed.clear()
            self._start_preparation()

    def _switch_to(self, prepared: _PreparedJob) -> None:
        """Hand the drives to a prepared job at this cycle's boundary (loop thread)."""
        assert self._parts is not None
        drives, manager = self._parts.drives, self._parts.manager
        self._prep.prepared = None
        job = prepared.job
        if self.store.get(job.id).status not in ACTIVE or self._fault:
            self._prep.after.submit(prepared.controller.close)
            self._job_id = None
            self.store.changed.set()
            return
        with self._lock:
            self._job = prepared
            if self._stop:
                prepared.controller.request_stop(StopRequest.SHUTDOWN)
            if self.store.mark_running(job.id).status is JobStatus.PAUSED:
                prepared.controller.pause()  # paused while prepared: it holds at the start
        drives.feedforward = self._prep.options[0]
        manager.use_telemetry(prepared.telemetry)
        gc.disable()
        manager.switch(prepared.controller, prepared.first)
        self._state = f"running job {job.id}"
        log.info(  # once a job, at its switch
            "job %d: running (task %s, %d dig(s) done)", job.id, job.task["name"], len(job.digs)
        )

    def _job_ended(self, controller: Any) -> tuple[Any, Command] | None:
        """The running job ended (loop thread): its outcome into the store, back to the hold."""
        assert self._parts is not None
        parts = self._parts
        guard, hold, manager = parts.guard, parts.hold, parts.manager
        running = self._job
        if running is None or controller is not running.controller:
            return None  # the hold powered down: the loop ends
        gc.enable()
        manager.use_telemetry(parts.hold_telemetry)
        self._hold_at(guard.position_m)
        job_ctl = running.controller
        status = job_ctl.status if job_ctl.status is not None else ExecStatus.DONE
        self._record_outcome(running.job, status, job_ctl.fault)
        with self._lock:
            self._job, self._job_id = None, None
        self._state = self._idle_state()
        self._prep.after.submit(self._report_run, running, status)
        self.store.changed.set()
        return hold, hold.command

    def _idle_state(self) -> str:
        queued = sum(1 for j in self.store.jobs() if j.status in ACTIVE)
        return f"idle, holding position; {queued} job(s) waiting"

    def _start_preparation(self) -> None:
        job = self.store.next_runnable()
        if job is None:
            self._state = self._idle_state()
            return
        self._job_id = job.id
        self._state = f"preparing job {job.id}"
        assert self._parts is not None
        self._prep.start(job, self._parts.hold.command.stroke_m.copy(), self._parts)

    def job_prepared(self, prepared: _PreparedJob | None) -> None:
        """A preparation ended without a job to run (done already, or it cannot start)."""
        if prepared is None:
            self._job_id = None
            self.store.changed.set()

    def _record_outcome(self, job: Job, st: ExecStatus, fault: str) -> None:
        """The job's status from the run's (the store in memory; its writer thread persists)."""
        if st is ExecStatus.DONE:
            self.store.set_status(job.id, JobStatus.DONE)
        elif st is ExecStatus.CANCELLED:
            self.store.set_status(job.id, JobStatus.CANCELLED, "cancelled by request")
        elif st is ExecStatus.STOPPED:
            # Shut down mid-job: resumable at the next undone dig after the restart.
            paused = self.store.get(job.id).status is JobStatus.PAUSED
            self.store.set_status(job.id, JobStatus.PAUSED if paused else JobStatus.QUEUED)
        else:
            text = f"{st.name.lower()}: {fault or 'no detail'}"
            self.store.set_status(job.id, JobStatus.FAILED, text)
            if st is not ExecStatus.PLANNING_ERROR:
                self._fault = f"job {job.id}: {text}"

    def _report_run(self, running: _PreparedJob, status: ExecStatus) -> None:
        """Off the loop's thread: close the planner, log the run and its digs, write its
        telemetry to the state directory."""
        ctl = running.controller
        ctl.close()
        job = running.job
        tel = running.telemetry.snapshot()
        overrun = tel.get("overrun", np.zeros(0, bool))
        lateness = tel.get("lateness_s", np.zeros(0))
        log.info(
            "job %d: %s after %d dig(s) this run, %d overrun(s), max lateness %.0f us%s",
            job.id,
            status.name.lower(),
            len(ctl.digs),
            int(np.sum(overrun)),
            float(np.max(lateness)) * 1e6 if lateness.size else 0.0,
            f"; {ctl.fault}" if ctl.fault else "",
        )
        path = self.config.paths.state_dir / "telemetry" / f"job-{job.id}.npz"
        try:
            path.parent.mkdir(mode=0o700, exist_ok=True)
            savez: Any = np.savez  # numpy's stubs read ** as its allow_pickle flag
            savez(path, **tel)
        except OSError as exc:
            log.warning("telemetry %s not written: %s", path, exc)


def _reset_rt_on_fork() -> None:
    """Keep SCHED_FIFO from passing to processes this thread starts.

    A child inherits the scheduling policy, and a planner importing numpy and onnxruntime at
    SCHED_FIFO starves everything else on the CPU (the drives' answers too) until it lowers
    itself. SCHED_RESET_ON_FORK makes every child start as SCHED_OTHER.
    """
    try:
        policy = os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK
        if policy == os.SCHED_FIFO:
            param = os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, param)
    except OSError as exc:
        log.warning("SCHED_RESET_ON_FORK refused: %s", exc)
