"""The daemon's runner: the thread that owns the bus and the drives for the daemon's life.

:class:`RigRunner` boots and enables the drives, then runs one
:class:`~rt_runtime.control.manager.ControllerManager` on one fixed-rate loop. Between jobs the
:class:`~rt_runtime.control.controllers.HoldController` holds every axis at its last commanded
stroke (the drives' SYNC watchdog never starves) and quick-stops them on a fault. A preparation
thread builds each job off the loop (its planner session, new or restored from the job store;
its planner process; its :class:`~rt_runtime.control.job.JobController` started at the held
stroke, and the job's telemetry); once the drives stand on the held target the runner switches
to the job at a cycle boundary, and when the job ends, back to the hold at the next: the SYNC
stream never pauses.

Faults latch; the thread lives. A drive fault, EMCY or lost heartbeat, a following error, stale
feedback, an overrun stop, a bus error (any exception out of the bus), the job's planner process
ending, a failed write of the job store (a job whose digs cannot be kept does not go on digging;
a reset first writes the store again and fails while it cannot), or an exception out of the
loop itself latches a fault (:meth:`RigRunner.fault`, one
line naming what happened, with each axis's node, state and EMCY code and meaning where the
drives reported one). The running job stops with the guard's jerk-limited stop (where the bus
is gone, the drives' own SYNC watchdogs stop them) and is marked ``failed``; the hold then
disables the drives and the loop ends. The runner waits, the bus closed if it broke, until
:meth:`RigRunner.reset_fault`: then it reopens the bus if it broke (the ``reopen`` factory),
boots the drives from whatever state they are in (NMT reset node; enable steps through fault
reset), holds at the measured pose, clears the latch and sets the failed job back to
``queued``, so it resumes at its next undone dig. A reset that fails leaves the fault latched
with the reason. Each boot builds the master, the drives' interface, the guard, the hold and
the manager again; a job prepared for an earlier boot never runs.

The job's outcome goes into the job store (in memory; its writer thread persists), its report
(log lines, the telemetry file in the state directory) to a thread.

Threads: the preparation and the work after a job (its report, closing a controller that never
ran) run on two threads started with the runner (:class:`_Worker`), which the loop's thread
hands work through a queue; the loop's thread starts no thread (``Thread.start`` waits until the
new thread runs, and the new thread's stack is mapped with the interpreter lock held).

Real time: the RT settings are applied once to the runner thread for its life. The heap is
frozen after boot and when a job is prepared (``gc.freeze`` is O(1)), and the collector is off
while a job runs (switched at the boundaries). Each boot first unfreezes and collects the whole
heap (no loop runs then), so cyclic garbage frozen before it (a previous boot's parts, the jobs'
leftovers) goes at the next reset; between resets, cyclic garbage a job leaves before the next
job's freeze stays (a restart or a reset frees it).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import os
import queue
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING, Any

import can
import numpy as np

from rt_runtime import axes
from rt_runtime.canbus import CanMaster, RxCounts
from rt_runtime.canbus.cyclic import bus_error_text
from rt_runtime.control.clock import Clock, MonotonicClock
from rt_runtime.control.controllers import Command, GuardFilter, HoldController
from rt_runtime.control.executor import ExecutorConfig
from rt_runtime.control.guard import LimitGuard, StrokeLimits
from rt_runtime.control.hardware import DriveInterface
from rt_runtime.control.job import DigRecord, ExecStatus, JobController, StopRequest
from rt_runtime.control.loop import FixedRateLoop, LoopConfig, OverrunPolicy
from rt_runtime.control.manager import ControllerManager, executor_telemetry
from rt_runtime.control.planner_worker import MODELS_CHANGED_EXIT, PathLink, ProcessPlanner
from rt_runtime.control.rt import RtSettings, apply_rt, restore_rt
from rt_runtime.control.setpoints import Phase
from rt_runtime.control.taught_path import CYCLE_STEP, taught_path
from rt_runtime.control.telemetry import Telemetry
from rt_runtime.errors import CommunicationError, ConfigurationError, ExcavatorRtError
from rt_runtime.planning.trench import TrenchPlanner, TrenchSession, make_task
from rt_runtime.service.config import DaemonConfig
from rt_runtime.service.jobstore import ACTIVE, DIG_KEYS, Job, JobError, JobStatus, JobStore
from rt_runtime.service.preflight import loop_rt_settings, timing_self_test
from rt_runtime.teach import load_taught

if TYPE_CHECKING:
    from rt_runtime.planning.trench import TrenchTask
    from rt_runtime.rig import Rig

__all__ = [
    "BUS_CLOSE_TIMEOUT_S",
    "JOB_TELEMETRY_ROWS",
    "PLANNER_CHECK_CYCLES",
    "SETTLED_M",
    "SETTLE_TIMEOUT_S",
    "STALE_LOOP_S",
    "RigRunner",
    "RunnerPhase",
    "close_bus",
]

log = logging.getLogger("excavator-rtd")

#: The runner's loop must have cycled within this long for WATCHDOG=1 (s).
STALE_LOOP_S = 0.5
#: Before a job starts, the drives must stand within this of the held target (m) ...
SETTLED_M = 1e-6
#: ... or this long must have passed (s).
SETTLE_TIMEOUT_S = 2.0
#: Longest wait for the drives to leave OPERATION_ENABLED when the runner stops or a fault
#: latches (s).
POWER_DOWN_TIMEOUT_S = 0.5
#: Telemetry rows of a job's run (the last 32 s at 500 Hz go to the state directory).
JOB_TELEMETRY_ROWS = 16_384
#: A running job that stops with one of these latches the fault at once.
_LATCHING = (ExecStatus.FAULT, ExecStatus.OVERRUN_STOP, ExecStatus.BUS_ERROR)
#: A running job's planner process is checked every this many cycles (a power of two).
PLANNER_CHECK_CYCLES = 128
#: How long a reset waits for the job store to be written again after a failed write (s).
STORE_CHECK_TIMEOUT_S = 5.0
#: Longest wait for a bus's shutdown (s): a backend may block on a peer that does not answer.
BUS_CLOSE_TIMEOUT_S = 2.0
#: Longest wait of a reset for the previous boot's job report and preparation threads (s).
AFTERMATH_TIMEOUT_S = 5.0
#: While a fault is latched, the bus is read (and what came discarded) this often (s).
_FAULTED_POLL_S = 0.1


class RunnerPhase(IntEnum):
    """What the runner's thread is doing."""

    #: The first boot and enable.
    STARTING = 0
    #: The loop cycles: holding, or running a job (with a fault latched: stopping).
    CYCLING = 1
    #: A fault is latched and the loop has ended: waiting for :meth:`RigRunner.reset_fault`.
    FAULTED = 2
    #: A reset: the bus reopened if it broke, the drives booted and enabled again.
    RESETTING = 3
    #: The thread has ended.
    STOPPED = 4


def close_bus(bus: can.BusABC, timeout_s: float = BUS_CLOSE_TIMEOUT_S) -> bool:
    """Shut ``bus`` down on a helper thread, waiting at most ``timeout_s``.

    A backend's shutdown may block on a peer that does not answer (python-can-remote waits for
    the far end to close), and may raise when the connection is already gone: neither may stop
    the caller. Returns True when the shutdown returned in time (raised or not).
    """

    def shut() -> None:
        try:
            bus.shutdown()
        except Exception as exc:  # a broken bus may fail to close: it is dropped either way
            log.debug("bus shutdown: %s", bus_error_text(exc))

    thread = threading.Thread(target=shut, name="bus-close", daemon=True)
    thread.start()
    thread.join(timeout_s)
    return not thread.is_alive()


def _task_of(job: Job, rig: Rig) -> TrenchTask:
    t = job.task
    return make_task(
        rig, t["length_m"], t["depth_m"], t["beta1_deg"], t["beta2_deg"], t["start_x_m"],
        name=t["name"],
    )  # fmt: skip


def _exit_text(code: int) -> str:
    """An exit code of a process as words (a negative code is the signal that ended it)."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


def _planner_end(planner: ProcessPlanner, code: int | None) -> str:
    """A planner process that ended (``code``: its exit code, None while not yet reaped), as
    the latch says it: with its last words (why it ended on its own) when it left any."""
    text = "the planner process ended"
    if code is not None:
        text += f" ({_exit_text(code)})"
    if planner.last_words:
        text += f": {planner.last_words}"
    elif code == MODELS_CHANGED_EXIT:
        text += ": its model files changed on disk since they were verified"
    return text


@dataclass(slots=True)
class _PreparedJob:
    """A job ready to run: its controller (started at the held stroke), its planner process,
    first command and telemetry, and the boot it was prepared for."""

    job: Job
    controller: JobController
    planner: ProcessPlanner | PathLink
    first: Command
    telemetry: Telemetry
    boot: int
    started_s: float = math.nan


@dataclass(frozen=True, slots=True)
class _Parts:
    """What the runner builds once for each boot of the drives."""

    master: CanMaster
    drives: DriveInterface
    guard: GuardFilter
    hold: HoldController
    manager: ControllerManager
    hold_telemetry: Telemetry
    boot: int


class _Worker:
    """A thread started once that runs the calls queued to it, in order (see the module
    docstring); a call that raises is logged and the thread goes on.

    Args:
        name: The thread's name.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._queue: queue.SimpleQueue[tuple[Any, tuple[Any, ...]] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Any, *args: Any) -> None:
        """Queue ``fn(*args)`` (loop safe: a queue put)."""
        self._queue.put((fn, args))

    def drain(self, timeout_s: float) -> bool:
        """Wait until every call queued so far has run (at most ``timeout_s``); True if so."""
        done = threading.Event()
        self.submit(done.set)
        return done.wait(timeout_s)

    def stop(self, timeout_s: float) -> bool:
        """Run what is queued, then end the thread (at most ``timeout_s``); True if it ended.
        Nothing may be submitted after."""
        self._queue.put(None)
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            fn, args = item
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

    def __init__(self, runner: RigRunner, planner: TrenchPlanner | None) -> None:
        self.runner = runner
        self.planners: dict[str, TrenchPlanner] = (
            {runner.config.planner: planner} if planner is not None else {}
        )
        #: Feed-forward and stale-cycle limit for the next job (SIGHUP reload).
        self.options = (runner.config.feedforward, runner.config.stale_cycles)
        self.prepared: _PreparedJob | None = None
        self._preparing = False
        self.worker = _Worker("prepare")
        #: Work after a job: its report, closing a controller that never ran.
        self.after = _Worker("job-after")
        #: Each dig's record into the store (:meth:`_record`), off the loop's thread.
        self.recorder = _Worker("dig-records")

    def stop(self, timeout_s: float) -> bool:
        """Record the dig records queued, run the work queued after jobs and before them, and
        end the three threads (at most ``timeout_s`` in all); True if they ended. Their
        references (the planners, the store) go with them."""
        end = time.monotonic() + timeout_s
        ended = True
        for worker in (self.recorder, self.after, self.worker):
            ended = worker.stop(max(end - time.monotonic(), 0.0)) and ended
        return ended

    def busy(self) -> bool:
        """A preparation is queued or runs."""
        return self._preparing

    def start(self, job: Job, held_m: Any, parts: _Parts) -> None:
        """Prepare ``job`` on the preparation thread, its controller starting at the held
        stroke (loop safe: a queue put)."""
        self._preparing = True
        self.worker.submit(self._prepare_once, job, held_m, parts)

    def _prepare_once(self, job: Job, held_m: Any, parts: _Parts) -> None:
        try:
            self._prepare(job, held_m, parts)
        finally:
            self._preparing = False

    def take(self) -> _PreparedJob | None:
        """The prepared job, handed over once (the loop's thread)."""
        prepared, self.prepared = self.prepared, None
        return prepared

    def _planner(self, name: str) -> TrenchPlanner:
        if self.runner.rig.swing is not None:
            raise ConfigurationError(
                f"rig {self.runner.rig.name} has a swing axis: it runs taught jobs "
                "(job submit --teach DIR); the trench planner plans the arm plane only"
            )
        if name not in self.planners:
            r = self.runner
            self.planners[name] = TrenchPlanner(r.rig, name, model_dir=r.config.models_dir)
        return self.planners[name]

    def _prepare(self, job: Job, held_m: Any, parts: _Parts) -> None:
        """The job's session (new, or restored at the next undone dig), its planner process
        and its controller started at the held stroke. Never raises: a job that cannot start
        fails in the store, a bug is logged and fails it too."""
        r = self.runner
        try:
            self._prepare_job(job, held_m, parts)
        except Exception as exc:  # a bug must not end the thread silently
            log.exception("job %d: preparation failed", job.id)
            with contextlib.suppress(JobError):
                r.store.set_status(
                    job.id, JobStatus.FAILED, f"preparation failed: {type(exc).__name__}: {exc}"
                )
            r.job_prepared(None)

    def _prepare_job(self, job: Job, held_m: Any, parts: _Parts) -> None:
        r = self.runner
        rig, period = r.rig, r.period_s
        done = len(job.digs)
        if job.max_digs is not None and done >= job.max_digs:
            r.store.set_status(job.id, JobStatus.DONE)
            r.job_prepared(None)
            return
        try:
            options = ExecutorConfig(
                feedforward=self.options[0],
                stale_cycles=self.options[1],
                max_digs=None if job.max_digs is None else job.max_digs - done,
            )
            t_max = rig.planning.t_max_s if rig.planning is not None else 10.0
            recorder = self.recorder
            link: ProcessPlanner | PathLink
            if job.taught is not None:
                # A taught trench resumes at its first undone cycle (each cycle streamed to
                # its end is a dig of the job); the path lifts the bucket out of the ground
                # and connects the held pose to that cycle's start.
                taught = load_taught(job.taught, rig)
                if done >= taught.n_cycles:
                    r.store.set_status(job.id, JobStatus.DONE)
                    r.job_prepared(None)
                    return
                path = taught_path(taught, rig, done)
                path.check(rig)
                link = PathLink(path, rig, period)
            else:
                planner = self._planner(job.planner)
                task = _task_of(job, rig)
                if job.session_state is None:
                    trench = planner.start(task)
                else:
                    trench = TrenchSession.restore(planner, task, job.session_state)
                link = ProcessPlanner(trench, period_s=period)
            controller = JobController(
                link,
                parts.guard,
                options.limits(rig),
                rig,
                parts.drives.axes,
                parts.drives.describe,
                lambda rec: recorder.submit(self._record, job.id, rec),
                int(2.0 * t_max / period) + 16,
            )
            first = controller.start(held_m)
            telemetry = executor_telemetry(JOB_TELEMETRY_ROWS, axes.count(rig))
        except (ExcavatorRtError, KeyError, TypeError, ValueError) as exc:
            log.error("job %d cannot start: %s", job.id, exc)
            r.store.set_status(job.id, JobStatus.FAILED, f"cannot start: {exc}")
            r.job_prepared(None)
            return
        # Everything alive now moves out of the collector's reach: O(1) here, and the job runs
        # with the collector off (see the module docstring).
        gc.freeze()
        self.prepared = _PreparedJob(job, controller, link, first, telemetry, parts.boot)

    def _record(self, job_id: int, rec: DigRecord) -> None:
        """One dig's record (on :attr:`recorder`'s thread): its summary and the session state
        into the store (its writer thread persists), the log line. A failure is logged."""
        try:
            # A taught cycle has no material accounting: its volumes are null.
            fields = {k: _null_if_nan(getattr(rec, k)) for k in DIG_KEYS}
            fields["planned_ahead"] = rec.planned_ahead
            self.runner.store.record_dig(job_id, fields, rec.session_state)
        except Exception:  # a bug must not end the thread silently
            log.exception("job %d: dig %d not recorded", job_id, rec.index)
            return
        if rec.dig_type == CYCLE_STEP:
            log.info("job %d: taught cycle %d done (%.1f s)", job_id, rec.index + 1, rec.T_s)
            return
        log.info(
            "job %d: dig %d done (%s, planned %.2f L, measured %.2f L; planned in %.0f ms%s)",
            job_id,
            rec.index,
            rec.dig_type,
            rec.planned_volume_m3 * 1e3,
            rec.measured_volume_m3 * 1e3,
            rec.plan_us / 1e3,
            ", ahead" if rec.planned_ahead else "",
        )


def _null_if_nan(value: Any) -> Any:
    """A record's value for the store (JSON has no NaN): None for a NaN float."""
    return None if isinstance(value, float) and math.isnan(value) else value


class RigRunner:
    """The runner thread on a real bus (see the module docstring).

    Args:
        config: The daemon's configuration (loop, executor options, boot timeout).
        rig: The rig.
        planner: The trench planner of ``config.planner`` (models loaded and checked).
        bus: The bus (traced or not), opened; the runner's master becomes its only reader and
            the runner owns it from here (:attr:`bus` is the current one).
        store: The job store.
        clock: Wall clock (``MonotonicClock``).
        reopen: Opens the bus again (from the configuration, traced as the first) when a reset
            finds it broken; None: a broken bus cannot be reopened and a reset fails.

    Attributes:
        bus: The bus in use (a reset may have replaced the one given); whoever ends the
            daemon shuts it down (:func:`close_bus`) after :meth:`shutdown`.
        error: Why the thread ended when it ended on its own (empty otherwise).
        enable_syncs: SYNCs the master had sent when the drives were (last) enabled.
        fault_at_s: The runner's clock when the latest fault latched (NaN before the first).
        resets_done: Resets that ended, succeeded or not (:meth:`reset_fault` returns the
            number the requested one will have).
    """

    def __init__(
        self,
        config: DaemonConfig,
        rig: Rig,
        planner: TrenchPlanner | None,
        bus: can.BusABC,
        store: JobStore,
        clock: Clock | None = None,
        reopen: Callable[[], can.BusABC] | None = None,
    ) -> None:
        self.config = config
        self.rig = rig
        self.bus = bus
        self.store = store
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self.period_s = config.loop.period_s
        self._reopen = reopen
        self._prep = _Preparation(self, planner)
        self.error = ""
        self.enable_syncs = 0
        self.resets_done = 0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._wake = threading.Event()
        self._start_error: BaseException | None = None
        self._stop = False
        self._job: _PreparedJob | None = None  # running
        self._job_id: int | None = None
        self._beat_s = -math.inf
        self._fault = ""
        self.fault_at_s = math.nan
        self._fault_job: int | None = None  # the job that failed with the fault ...
        self._fault_job_paused = False  # ... and whether it was paused then
        self._resets_requested = 0
        self._reset_error = ""  # why the latest reset failed
        self._bus_broken = False
        self._powering_down = False
        self._boots = 0
        self._phase = RunnerPhase.STARTING
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
        """See :meth:`Runner.shutdown` (a latched fault: the drives are off already)."""
        with self._lock:
            self._stop = True
            running = self._job
        self._wake.set()
        if running is not None:
            running.controller.request_stop(StopRequest.SHUTDOWN)
        if self._thread is None:
            return True
        end = time.monotonic() + timeout_s
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            return False
        # The last dig records and the last job's report (its planner closed, its telemetry
        # file) run on helper threads that the process's exit would cut short; a preparation
        # still running is waited for as long as the time left allows.
        left = min(max(end - time.monotonic(), 0.0), AFTERMATH_TIMEOUT_S)
        if not self._prep.stop(left):
            log.warning(
                "the dig records, the last job's report or a preparation did not finish "
                "within %.1f s",
                left,
            )
        return True

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

    def watchdog(self) -> tuple[bool, str]:
        """See :meth:`Runner.watchdog`: the loop cycles, or the thread waits for a reset or
        runs one (a latched fault is reported, not a reason to be restarted)."""
        if not self.alive():
            return False, "the runner thread ended"
        if self._phase in (RunnerPhase.FAULTED, RunnerPhase.RESETTING):
            return True, ""
        age = self.clock.now() - self._beat_s
        if age > STALE_LOOP_S:
            return False, f"the loop has not cycled for {age:.3f} s"
        return True, ""

    def fault(self) -> str:
        """See :meth:`Runner.fault` (with why the latest reset failed, when one did)."""
        text = self._fault
        if text and self._reset_error:
            text += f" (the latest reset failed: {self._reset_error})"
        return text

    def reset_fault(self) -> int:
        """See :meth:`Runner.reset_fault`."""
        with self._lock:
            if self._resets_requested <= self.resets_done:
                self._resets_requested = self.resets_done + 1
            number = self._resets_requested
        self._wake.set()
        return number

    def state(self) -> str:
        """See :meth:`Runner.state` (a running job that is paused says so)."""
        phase = self._phase
        if phase is RunnerPhase.RESETTING:
            return f"resetting the fault: {self._state}"
        if self._fault:
            if phase is RunnerPhase.FAULTED:
                return f"fault: {self.fault()}; waiting for reset-fault"
            return f"fault: {self._fault}; stopping"
        running = self._job
        if running is not None and running.controller.paused:
            return f"job {self._job_id} paused, holding position"
        return self._state

    def current_job(self) -> int | None:
        """See :meth:`Runner.current_job`."""
        return self._job_id

    def rx_counts(self) -> RxCounts | None:
        """What the current boot's master rode through on its receive side (a copy; None
        before the first boot)."""
        parts = self._parts
        return None if parts is None else parts.drives.master.feedback.copy().counts

    def planner_pid(self) -> int | None:
        """The running job's planner process id (None without a running job)."""
        running = self._job
        if running is None or not isinstance(running.planner, ProcessPlanner):
            return None
        return running.planner.pid

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
        """Apply the RT settings, boot and run: the first time, then once for each reset of a
        latched fault, until a stop. Nothing out of a boot or a loop ends the thread."""
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
        try:
            if not self._run_boot(first=True):
                return
            while not self._stop and self._fault:
                self._await_reset()
                if self._stop:
                    break
                self._run_boot(first=False)
            self._state = "stopped"
        except Exception as exc:  # a bug in the runner itself: reported, never silent
            self.error = f"runner failed: {type(exc).__name__}: {exc}"
            log.exception("runner failed")
        finally:
            self._phase = RunnerPhase.STOPPED
            self._ready.set()
            restore_rt(report)

    def _run_boot(self, first: bool) -> bool:
        """One boot and its loop: the bus reopened if it broke (a reset), the drives booted and
        enabled, held at their measured pose, the loop run until it ends (a stop, or a fault
        latched and the drives off). True when the drives were enabled."""
        self._boots += 1
        self._phase = RunnerPhase.STARTING if first else RunnerPhase.RESETTING
        self._powering_down = False
        if not first:
            # The failed job's report (planner shutdown, telemetry file) and a preparation of
            # the previous boot finish first: none of it competes with the first cycles.
            for worker in (self._prep.after, self._prep.worker):
                worker.drain(AFTERMATH_TIMEOUT_S)
            if self.store.write_error and not self.store.rewrite(STORE_CHECK_TIMEOUT_S):
                self._reset_error = f"the job store is still not written: {self.store.write_error}"
                log.error("reset failed, the fault stays latched: %s", self._reset_error)
                self._reset_ended()
                return False
        try:
            parts = self._boot(retry=not first)
        except Exception as exc:
            if first:
                self._start_error = exc
                self._ready.set()
            else:
                self._reset_error = str(exc)
                log.error("reset failed, the fault stays latched: %s", exc)
                self._reset_ended()
            return False
        master = parts.master
        s0 = master.last_target_um().astype(np.float64) * 1e-6
        self._hold_at(s0)
        self._phase = RunnerPhase.CYCLING
        self._state = self._idle_state()
        if first:
            self._ready.set()
        else:
            self._clear_fault()
            self._reset_ended()
        self._store_changed()
        try:
            parts.manager.run(parts.hold, parts.hold.command, s0, parts.hold.command.q_rad)
        except Exception as exc:  # a bug in a cycle: the fault is the report, with its trace
            log.exception("the runner's loop failed")
            self._latch(f"the runner's loop failed: {type(exc).__name__}: {exc}")
            with contextlib.suppress(Exception):
                master.quick_stop()
        finally:
            self._end_boot(parts)
        return True

    def _boot(self, retry: bool) -> _Parts:
        """Open the bus again if it broke; boot and enable the drives; this boot's parts.
        With ``retry``, a boot that fails on an exception out of a kept bus reopens it and
        boots once more.

        Raises:
            CommunicationError, DriveFault: Boot or enable failed.
        """
        timeout_s = self.config.bus.boot_timeout_s
        for attempt in range(2 if retry else 1):
            if self._bus_broken:
                self._reopen_bus()
            self._state = "booting the drives"
            master = CanMaster(self.bus, self.rig, period_s=self.period_s)
            try:
                infos = master.boot(self.clock.now, timeout_s)
            except CommunicationError:
                if master.cycle.bus_exception is not None:
                    self._bus_broken = True
                    if attempt == 0 and retry and self._reopen is not None:
                        continue
                raise
            log.info(
                "drives booted: %s",
                ", ".join(f"{i.axis} node {i.node_id} {i.device_name!r}" for i in infos),
            )
            # Keep what boot built out of later collections: the loop's first cycles, right
            # after enable, must be short (the drives' SYNC watchdog runs from enable on).
            # Unfrozen first, so the whole heap is collected: what earlier boots and jobs froze
            # and has become garbage since (a previous boot's parts) goes now, and a daemon
            # that resets again and again does not grow (no loop runs during a boot).
            gc.unfreeze()
            gc.collect()
            gc.freeze()
            parts = self._build(master)
            self._state = "enabling the drives"
            try:
                master.enable(self.clock.now, timeout_s)
            except CommunicationError:
                if master.cycle.bus_exception is not None:
                    self._bus_broken = True
                raise
            self.enable_syncs = master.feedback.sync_count
            self._beat_s = self.clock.now()  # the loop starts now: liveness from here
            return parts
        raise AssertionError("unreachable: the last attempt returns or raises")

    def _reopen_bus(self) -> None:
        """Replace the broken bus with a new one from the configuration.

        Raises:
            CommunicationError: No way to reopen it, or it does not open.
        """
        if self._reopen is None:
            raise CommunicationError("the bus broke and this runner cannot reopen it")
        self._state = "reopening the bus"
        close_bus(self.bus)
        self.bus = self._reopen()
        self._bus_broken = False
        log.info("bus reopened")

    def _build(self, master: CanMaster) -> _Parts:
        """The drives, the guard, the hold and the manager of one boot."""
        cfg = self.config.loop
        loop = FixedRateLoop(
            self.clock,
            LoopConfig(
                period_s=self.period_s,
                spin_s=min(2e-4, 0.25 * self.period_s),
                rt=RtSettings(None, False, None, None, False),
                overrun=OverrunPolicy(max_consecutive=cfg.max_consecutive_overruns),
            ),
            executor_telemetry(1024, axes.count(self.rig)),
        )
        drives = DriveInterface(master, self.clock, 0.0, self._prep.options[0])
        drives.react_to_faults(False)
        guard = GuardFilter(LimitGuard(StrokeLimits.from_rig(self.rig), self.period_s))
        n = axes.count(self.rig)
        hold = HoldController(np.zeros(n), np.zeros(n), SETTLED_M, drives.describe)
        manager = ControllerManager(
            drives, guard, loop, on_cycle=self._on_cycle, on_ended=self._job_ended
        )
        self._parts = _Parts(
            master, drives, guard, hold, manager, manager.loop.telemetry, self._boots
        )
        return self._parts

    def _end_boot(self, parts: _Parts) -> None:
        """After the loop: a job it left running failed, a job prepared for it dropped, a
        broken bus closed."""
        gc.enable()
        with self._lock:
            running, self._job = self._job, None
        if running is not None:
            self._latch("the loop ended during a job")
            self._fail_job(running.job, self._fault)
            threading.Thread(target=running.controller.close, daemon=True).start()
        prepared = self._prep.take()
        if prepared is not None:
            self._prep.after.submit(prepared.controller.close)
        self._job_id = None
        if parts.master.cycle.bus_exception is not None:
            self._bus_broken = True
        if self._bus_broken and not self._stop:
            close_bus(self.bus)  # release it now; a reset opens a new one

    def _await_reset(self) -> None:
        """With a fault latched and the loop ended: wait for a reset request or a stop; read
        what arrives on a working bus meanwhile (and drop it) so no backlog builds."""
        self._phase = RunnerPhase.FAULTED
        log.error("fault latched: %s; waiting for reset-fault", self._fault)
        while not self._stop:
            with self._lock:
                requested = self._resets_requested > self.resets_done
            if requested:
                return
            self._wake.wait(_FAULTED_POLL_S)
            self._wake.clear()
            if not self._bus_broken:
                try:
                    while self.bus.recv(timeout=0.0) is not None:
                        pass
                except Exception as exc:  # the bus broke while faulted: reopened at the reset
                    log.warning("bus error while faulted: %s", bus_error_text(exc))
                    self._bus_broken = True
                    close_bus(self.bus)

    def _latch(self, text: str, job_id: int | None = None) -> None:
        """Latch a fault (the first cause stays), for job ``job_id`` when one failed with it."""
        if not self._fault:
            self._fault = text
            self.fault_at_s = self.clock.now()
            if job_id is not None and self._fault_job is None:
                self._fault_job = job_id
                with contextlib.suppress(JobError):
                    self._fault_job_paused = self.store.get(job_id).status is JobStatus.PAUSED

    def _reset_ended(self) -> None:
        with self._lock:
            self.resets_done += 1

    def _clear_fault(self) -> None:
        """A reset succeeded: clear the latch, the failed job back to ``queued`` (``paused``
        when it was paused)."""
        text, job_id = self._fault, self._fault_job
        self._fault, self._fault_job, self._reset_error = "", None, ""
        requeued = ""
        if job_id is not None:
            with contextlib.suppress(JobError):
                if self.store.get(job_id).status is JobStatus.FAILED:
                    status = JobStatus.PAUSED if self._fault_job_paused else JobStatus.QUEUED
                    self.store.set_status(job_id, status)
                    requeued = f"; job {job_id} {status.label} again at its next undone dig"
        log.info("fault reset (was: %s): drives enabled%s", text, requeued)

    def _hold_at(self, stroke_m: Any) -> None:
        """Hold ``stroke_m`` from the next cycle (the guard leaves any stop there)."""
        assert self._parts is not None
        guard, hold = self._parts.guard, self._parts.hold
        s = np.asarray(stroke_m, dtype=np.float64)
        guard.guard.reset(s)
        q = axes.actuator_to_joint(self.rig, s, check_limits=False)
        hold.command.hold(s, q, Phase.WAIT)

    def _store_changed(self) -> None:
        self.store.changed.set()  # look for work once on entry

    def _on_cycle(self, sync: int, now_s: float) -> None:
        """Every cycle, on the loop's thread: liveness; while a job runs, its planner process;
        while holding, the fault latch and the power-down after it, the stop, the next job's
        preparation and the switch to it."""
        self._beat_s = now_s
        parts = self._parts
        assert parts is not None
        hold, manager = parts.hold, parts.manager
        if manager.controller is not hold:
            running = self._job
            if running is None:
                return
            ctl = running.controller
            if ctl.status is not None and ctl.status in _LATCHING and not self._fault:
                # Latched when the job begins its stop, not when the stop ends (a stop on a
                # gone bus waits for the drives' lost heartbeats).
                job = running.job.id
                self._latch(f"job {job}: {self._job_fault_text(ctl.status, ctl.fault)}", job)
            if sync & (PLANNER_CHECK_CYCLES - 1) == 0:
                self._check_planner(running)
                self._check_store(running)
            return
        if hold.fault and not self._fault:
            self._latch(hold.fault)
        if sync & (PLANNER_CHECK_CYCLES - 1) == 0 and not self._fault:
            self._check_store(None)
        if self._stop or self._fault:
            if not self._powering_down:
                self._powering_down = True
                self._state = "stopping: disabling the drives"
                hold.power_down(POWER_DOWN_TIMEOUT_S)
            return
        prepared = self._prep.prepared
        if prepared is not None:
            if prepared.boot != parts.boot:
                self._drop_prepared()
                return
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
        if changed.is_set() and not self._prep.busy():
            changed.clear()
            self._start_preparation()

    def _check_planner(self, running: _PreparedJob) -> None:
        """A running job whose planner process has ended: latch the fault and stop the job
        (the guard's stop). Loop thread, every :data:`PLANNER_CHECK_CYCLES` cycles."""
        if self._fault or self._stop or not isinstance(running.planner, ProcessPlanner):
            return
        code = running.planner.exit_code()
        if code is None:
            return
        job = running.job.id
        self._latch(f"job {job}: {_planner_end(running.planner, code)}", job)
        running.controller.request_stop(StopRequest.SHUTDOWN)

    def _check_store(self, running: _PreparedJob | None) -> None:
        """The job store's last write failed (its disk full or read-only, its directory gone):
        latch the fault and stop the running job (the guard's stop); a job whose digs cannot be
        kept must not go on digging. Loop thread, every :data:`PLANNER_CHECK_CYCLES` cycles
        (one attribute read)."""
        error = self.store.write_error
        if not error or self._fault or self._stop:
            return
        if running is None:
            self._latch(f"the job store is not written: {error}")
            return
        job = running.job.id
        self._latch(f"job {job}: the job store is not written: {error}", job)
        running.controller.request_stop(StopRequest.SHUTDOWN)

    def _drop_prepared(self) -> None:
        """A prepared job that must not run (a fault, an earlier boot, no longer active): its
        planner closed off the loop's thread, the store looked at again."""
        prepared = self._prep.take()
        if prepared is not None:
            self._prep.after.submit(prepared.controller.close)
        self._job_id = None
        self.store.changed.set()

    def _switch_to(self, prepared: _PreparedJob) -> None:
        """Hand the drives to a prepared job at this cycle's boundary (loop thread)."""
        assert self._parts is not None
        drives, manager = self._parts.drives, self._parts.manager
        job = prepared.job
        if self.store.get(job.id).status not in ACTIVE or self._fault:
            self._drop_prepared()
            return
        self._prep.take()
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
        self._record_outcome(running, status, job_ctl.fault)
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

    def _fail_job(self, job: Job, text: str) -> None:
        """``job`` failed with a latched fault: a reset queues it again (paused if it was)."""
        with contextlib.suppress(JobError):
            if self._fault_job is None:
                self._fault_job = job.id
                self._fault_job_paused = self.store.get(job.id).status is JobStatus.PAUSED
            self.store.set_status(job.id, JobStatus.FAILED, text)

    def _record_outcome(self, running: _PreparedJob, st: ExecStatus, fault: str) -> None:
        """The job's status from the run's (the store in memory; its writer thread persists);
        a fault latched for it. A job stopped for a latched fault (its planner process ended,
        say) failed with that fault; a planning error whose planner process has ended is one."""
        job = running.job
        if st is ExecStatus.DONE:
            self.store.set_status(job.id, JobStatus.DONE)
            return
        if st is ExecStatus.CANCELLED:
            self.store.set_status(job.id, JobStatus.CANCELLED, "cancelled by request")
            return
        stopping = self._stop  # a stop ends the planner process too (SIGINT to the group)
        if (
            st in (ExecStatus.STOPPED, ExecStatus.PLANNING_ERROR)
            and not (self._fault or stopping)
            and isinstance(running.planner, ProcessPlanner)
        ):
            code = running.planner.exit_code()
            if code is not None or running.planner.last_words:
                self._latch(f"job {job.id}: {_planner_end(running.planner, code)}", job.id)
        if st is ExecStatus.STOPPED and not self._fault:
            # Shut down mid-job: resumable at the next undone dig after the restart.
            paused = self.store.get(job.id).status is JobStatus.PAUSED
            self.store.set_status(job.id, JobStatus.PAUSED if paused else JobStatus.QUEUED)
            return
        if st is ExecStatus.PLANNING_ERROR and not self._fault:
            self.store.set_status(job.id, JobStatus.FAILED, f"planning_error: {fault}")
            return
        if st in (ExecStatus.STOPPED, ExecStatus.PLANNING_ERROR):
            self._fail_job(job, self._fault)
            return
        prefix = f"job {job.id}: "
        if self._fault_job == job.id and self._fault.startswith(prefix):
            # Latched when the job began its stop (:meth:`_on_cycle`), with the drives' report
            # of then: the job keeps the same words (the drives may answer again by now).
            text = self._fault[len(prefix) :]
        else:
            text = self._job_fault_text(st, fault)
            self._latch(prefix + text, job.id)
        self._fail_job(job, text)

    def _job_fault_text(self, st: ExecStatus, fault: str) -> str:
        """A job's fault as the store and the latch say it (outside the hot path: once)."""
        text = f"{st.name.lower()}: {fault or 'no detail'}"
        assert self._parts is not None
        drives = self._parts.drives
        if "cycle status" not in text:
            # The monitor's own words name the axis; the drives' report adds nodes and codes.
            text += f"; drives: {drives.describe(drives.feedback.status)}"
        return text

    def _report_run(self, running: _PreparedJob, status: ExecStatus) -> None:
        """Off the loop's thread: close the planner, log the run and its digs, write its
        telemetry to the state directory. A failure is logged; nothing raises."""
        try:
            self._write_report(running, status)
        except Exception:  # a bug must not end the thread silently
            log.exception("job %d: run report failed", running.job.id)

    def _write_report(self, running: _PreparedJob, status: ExecStatus) -> None:
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
