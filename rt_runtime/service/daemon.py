"""``excavator-rtd``: the rig daemon that runs trench jobs under systemd.

Start-up, in this order (nothing reaches the bus before the configuration, the rig and the
models have been checked)::

    load_config (keys)  ->  load_planning (rig, PINN models vs. their cards)  ->  job store
    ->  control socket bound  ->  bus opened  ->  runner thread: CanMaster.boot + enable,
    then holds position every period  ->  sd_notify READY=1  ->  serve requests

Threads: the **main thread** serves the control socket, the signals (through a wake-up pipe)
and the systemd notifications in one ``selectors`` loop. The **runner thread** owns the bus,
the master and the fixed-rate loop for the daemon's whole life: between jobs it holds every
axis at its last commanded stroke at the period (the drives' SYNC watchdog must never starve
while they are enabled), and it runs each job with the :class:`~rt_runtime.control.executor.
Executor` (built with ``disable_at_end=False``: the hold takes over). A **preparation thread**
builds each job's planner session (new, or restored from the job store) and its executor while
the runner holds; the hold hands over once the drives stand on the held target, so the
executor's start from the measured pose is no step. The job store writes on its own thread; the
trace (``paths.trace``) too.

Real time (where the issue leaves the daemon's share open): RT settings (SCHED_FIFO with
SCHED_RESET_ON_FORK, mlockall, CPU, timer slack) are applied once to the runner thread for its
life, not per loop run, so no hand-over pays for them. The collector: the heap is frozen after
start-up, after boot, and when a job is prepared (``gc.freeze`` is O(1)); a job's loop then
collects nothing at its start and runs with the collector off; the hold loop starts without a
collect. The price: cyclic garbage made before a freeze is never collected while the daemon
runs (a restart frees it). The interpreter's switch interval is lowered to 0.2 ms so the loop's
thread gets the interpreter back quickly from the main and helper threads. Each hand-over
logs its longest time without a cycle against the drives' SYNC watchdog.

Signals: SIGTERM / SIGINT (and the ``stop`` request) -> STOPPING=1, the executor's jerk-limited
stop (``StopRequest.SHUTDOWN``), drives disabled (controlword 0x0000), the job left resumable
(``queued`` with its last recorded dig), store, trace and logs flushed, exit 0. SIGHUP ->
RELOADING=1, re-read the file, apply :data:`~rt_runtime.service.config.RELOADABLE_KEYS` (log
level; feed-forward and planner for the next job; trace reopened), log the keys that need a
restart, READY=1. An invalid file on SIGHUP is logged and the running configuration kept.

Watchdog: WATCHDOG=1 every ``$WATCHDOG_USEC / 2`` only while the runner's loop has cycled within
:data:`STALE_LOOP_S` and no fault is latched. A latched fault (drive fault, bus error, overrun
stop) stops the pings, so systemd restarts the daemon (``Restart=on-failure``); the restart
boots and enables the drives again and holds, and the failed job waits for ``resume``.

Exit codes: :data:`EXIT_OK` 0, :data:`EXIT_RUNTIME` 1 (the runner died), :data:`EXIT_CONFIG` 2
(configuration, rig, models, job store, socket; nothing was sent on the bus), :data:`EXIT_BUS`
3 (the bus did not open, or the drives did not boot or enable).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import logging
import math
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import can
import numpy as np

from rt_runtime.canbus import CanMaster, CycleStatus, DriveState
from rt_runtime.canbus.traced import TracedBus
from rt_runtime.control.clock import Clock, MonotonicClock
from rt_runtime.control.executor import (
    DigRecord,
    ExecStatus,
    Executor,
    ExecutorConfig,
    ExecutorResult,
    StopRequest,
    executor_telemetry,
)
from rt_runtime.control.loop import (
    CycleInfo,
    FixedRateLoop,
    LoopAction,
    LoopConfig,
    OverrunPolicy,
)
from rt_runtime.control.rt import RtSettings, apply_rt, restore_rt
from rt_runtime.control.telemetry import Telemetry
from rt_runtime.errors import (
    CommunicationError,
    ConfigurationError,
    DriveFault,
    ExcavatorRtError,
)
from rt_runtime.planning.trench import TrenchPlanner, TrenchSession
from rt_runtime.service.config import (
    PLANNERS,
    DaemonConfig,
    load_config,
    load_planning,
)
from rt_runtime.service.control import ControlServer
from rt_runtime.service.jobstore import ACTIVE, DIG_KEYS, Job, JobError, JobStore
from rt_runtime.service.notify import Notifier, watchdog_interval_s

if TYPE_CHECKING:
    from rt_runtime.planning.trench import TrenchTask
    from rt_runtime.rig import Rig

__all__ = [
    "EXIT_BUS",
    "EXIT_CONFIG",
    "EXIT_OK",
    "EXIT_RUNTIME",
    "STALE_LOOP_S",
    "RigRunner",
    "Runner",
    "Service",
    "TraceRecorder",
    "TracedBus",
    "main",
    "open_bus",
    "resolve_task",
]

log = logging.getLogger("excavator-rtd")

EXIT_OK = 0
EXIT_RUNTIME = 1
EXIT_CONFIG = 2
EXIT_BUS = 3
#: The runner's loop must have cycled within this long for WATCHDOG=1 (s).
STALE_LOOP_S = 0.5
#: Before a job starts, the drives must stand within this of the held target (um) ...
SETTLED_UM = 1
#: ... or this long must have passed (s).
SETTLE_TIMEOUT_S = 2.0
#: Telemetry rows of a job's run (the last 32 s at 500 Hz go to the state directory).
JOB_TELEMETRY_ROWS = 16_384
#: Main-thread poll interval: status lines, runner liveness (s).
_POLL_S = 0.1


# -- tasks ------------------------------------------------------------------------------------


def resolve_task(spec: Any, rig: Rig) -> tuple[TrenchTask, dict[str, Any]]:
    """Validate a submitted task with the trench planner's own checks.

    Args:
        spec: A built-in name (``"A"`` .. ``"D"``, Yao Table 3) or an object with
            ``length_m``, ``depth_m``, ``beta1_deg``, ``beta2_deg``, optional ``start_x_m`` and
            ``name``. File paths are refused: the daemon never reads a client's paths.
        rig: The rig the task must fit.

    Returns:
        ``(task, numbers)``: the validated task and what the job store keeps (name, m, deg).

    Raises:
        ConfigurationError: Unknown name, unknown or missing keys, values out of range (the
            planner's message, naming the key and the allowed range).
    """
    from rt_runtime.planning.trench import BUILTIN_TASKS, TASK_KEYS, check_task_keys, make_task

    if isinstance(spec, str):
        name = spec.strip().upper()
        if name not in BUILTIN_TASKS:
            raise ConfigurationError(
                f"task {spec!r}: not a built-in task; allowed: {', '.join(BUILTIN_TASKS)}, or an "
                f"object with {', '.join(TASK_KEYS)} (start_x_m optional)"
            )
        length, depth, b1, b2 = BUILTIN_TASKS[name]
        spec = {"name": name, "length_m": length, "depth_m": depth, "beta1_deg": b1,
                "beta2_deg": b2}  # fmt: skip
    if not isinstance(spec, dict):
        raise ConfigurationError(
            f"task must be a built-in name or an object, got {type(spec).__name__}"
        )
    check_task_keys(spec, "task", extra=("name",))
    name = spec.get("name", "custom")
    if not isinstance(name, str) or not 0 < len(name) <= 64:
        raise ConfigurationError(f"task: name must be a string of 1..64 characters, got {name!r}")
    task = make_task(
        rig,
        spec["length_m"],
        spec["depth_m"],
        spec["beta1_deg"],
        spec["beta2_deg"],
        spec.get("start_x_m"),
        name=name,
    )
    numbers = {
        "name": name,
        "length_m": task.length_m,
        "depth_m": task.depth_m,
        "beta1_deg": float(spec["beta1_deg"]),
        "beta2_deg": float(spec["beta2_deg"]),
        "start_x_m": task.start_x_m,
    }
    return task, numbers


def _task_of(job: Job, rig: Rig) -> TrenchTask:
    from rt_runtime.planning.trench import make_task

    t = job.task
    return make_task(
        rig, t["length_m"], t["depth_m"], t["beta1_deg"], t["beta2_deg"], t["start_x_m"],
        name=t["name"],
    )  # fmt: skip


# -- the bus and its trace ----------------------------------------------------------------------


def open_bus(config: DaemonConfig, rig: Rig) -> can.BusABC:
    """Open the configured python-can bus.

    Raises:
        CommunicationError: The bus did not open (the message names ``bus.interface`` and
            ``bus.channel`` and quotes python-can).
    """
    b = config.bus
    bitrate = b.bitrate if b.bitrate is not None else rig.can.bitrate
    try:
        return can.Bus(interface=b.interface, channel=b.channel, bitrate=bitrate)
    except Exception as exc:  # python-can backends raise assorted types for a bad channel
        raise CommunicationError(
            f"config keys bus.interface = {b.interface!r}, bus.channel = {b.channel!r}: the bus "
            f"does not open: {type(exc).__name__}: {exc}"
        ) from exc


class TraceRecorder:
    """Writes frames to a BLF/ASC file with python-can's logger on its own thread.

    The loop's thread only puts ``(unix_s, id, data, is_rx)`` tuples on a queue; the writer
    thread builds messages and writes them (the BLF writer compresses in blocks, which must
    never happen on the loop's thread).

    Args:
        path: The file (``.blf`` or ``.asc``); an existing one is kept as ``<stem>.<n><suffix>``;
            None: record nothing until :meth:`reopen`.
    """

    _REOPEN = object()

    def __init__(self, path: Path | None) -> None:
        self.queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.path: Path | None = None
        self.active = False
        self.frames = 0
        self._logger: can.Listener | None = None
        self._thread = threading.Thread(target=self._run, name="trace", daemon=True)
        self._opened = threading.Event()
        self._thread.start()
        self.reopen(path)

    @staticmethod
    def _keep_old(path: Path) -> None:
        if not path.exists():
            return
        n = 1
        while (old := path.with_name(f"{path.stem}.{n}{path.suffix}")).exists():
            n += 1
        path.rename(old)

    def reopen(self, path: Path | None) -> None:
        """Close the current file and start ``path`` (None: stop recording)."""
        self._opened.clear()
        self.queue.put((self._REOPEN, path))
        self._opened.wait(10.0)

    def _open(self, path: Path | None) -> None:
        if self._logger is not None:
            self._logger.stop()
            self._logger = None
        self.active = False
        self.path = path
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                self._keep_old(path)
                self._logger = can.Logger(str(path))
                self.active = True
            except (OSError, ValueError) as exc:
                log.error("trace %s cannot be written: %s; recording nothing", path, exc)
        self._opened.set()

    def _run(self) -> None:
        while True:
            item = self.queue.get()
            if item is None:
                if self._logger is not None:
                    self._logger.stop()
                    self._logger = None
                return
            if isinstance(item, can.Message):
                # One bus, channel 0 as for sent frames: the interface's channel name may not
                # map to a BLF channel number (python-can parses digits out of a name like
                # "trace-1f3e99", which overflowed the field and killed this thread).
                msg = can.Message(
                    timestamp=item.timestamp,
                    arbitration_id=item.arbitration_id,
                    data=item.data,
                    is_extended_id=item.is_extended_id,
                    is_remote_frame=item.is_remote_frame,
                    is_error_frame=item.is_error_frame,
                    is_rx=item.is_rx,
                    dlc=item.dlc,
                    channel=0,
                    check=False,
                )
            elif item[0] is self._REOPEN:
                self._open(item[1])
                continue
            else:
                t, arbitration_id, data, is_rx = item
                msg = can.Message(
                    timestamp=t,
                    arbitration_id=arbitration_id,
                    data=data,
                    is_extended_id=arbitration_id > 0x7FF,
                    is_rx=is_rx,
                    channel=0,
                )
            if self._logger is not None:
                self._logger.on_message_received(msg)
                self.frames += 1

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is queued, close the file and stop the thread."""
        self.queue.put(None)
        self._thread.join(timeout_s)
        self.active = False


# -- the runner ---------------------------------------------------------------------------------


class Runner(Protocol):
    """What the service needs from the thread that owns the drives (the real one is
    :class:`RigRunner`; the tests use a fake)."""

    def start(self) -> None:
        """Boot and enable the drives and start holding; return once they are enabled.

        Raises:
            CommunicationError, DriveFault: Boot or enable failed (the bus was used).
        """
        ...

    def shutdown(self, timeout_s: float) -> bool:
        """Stop safely (a running job: jerk-limited stop, left resumable), disable the drives,
        end the thread. True when all of that happened in time."""
        ...

    def alive(self) -> bool:
        """The runner's thread is running."""
        ...

    def health(self) -> tuple[bool, str]:
        """``(healthy, why not)``: the loop cycles and no fault is latched."""
        ...

    def state(self) -> str:
        """One line for STATUS= and ``status``."""
        ...

    def current_job(self) -> int | None:
        """The id of the job being prepared or run, or None."""
        ...

    def progress(self) -> dict[str, Any] | None:
        """The executor's progress snapshot of the current job, or None."""
        ...

    def pause(self) -> None:
        """Pause the current job (no effect without one)."""
        ...

    def resume(self) -> None:
        """Resume the current job (no effect without one)."""
        ...

    def cancel(self) -> None:
        """Cancel the current job with a jerk-limited stop (no effect without one)."""
        ...

    def configure(self, feedforward: bool, stale_cycles: int) -> None:
        """Executor options for the next job (SIGHUP reload)."""
        ...


class RigRunner:
    """The runner thread on a real bus: boot, hold between jobs, jobs through the Executor.

    Args:
        config: The daemon's configuration (loop, executor options).
        rig: The rig.
        planner: The trench planner of ``config.planner`` (models loaded and checked).
        bus: The bus (traced or not); the runner's master becomes its only reader.
        store: The job store.
        clock: Wall clock (``MonotonicClock``).

    Attributes:
        error: Why the thread ended when it ended on its own (empty otherwise).
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
        self._planners: dict[str, TrenchPlanner] = {config.planner: planner}
        self._feedforward = config.feedforward
        self._stale_cycles = config.stale_cycles
        self._rt_settings = RtSettings(
            sched_fifo_priority=config.loop.sched_fifo_priority,
            lock_memory=config.loop.lock_memory,
            cpu=config.loop.cpu,
            timer_slack_ns=1,
            freeze_gc=False,
        )
        # The thread keeps its RT settings for life. A job's loop freezes the collector (its
        # collect finds nothing: the preparation froze the heap); the hold loop starts without a
        # collect, so the hand-over after a job costs no collection pause.
        overrun = OverrunPolicy(max_consecutive=config.loop.max_consecutive_overruns)
        spin_s = min(2e-4, 0.25 * self.period_s)
        self._loop_config = LoopConfig(
            period_s=self.period_s,
            spin_s=spin_s,
            rt=RtSettings(None, False, None, None, True),
            overrun=overrun,
        )
        hold_config = LoopConfig(
            period_s=self.period_s,
            spin_s=spin_s,
            rt=RtSettings(None, False, None, None, False),
            overrun=overrun,
        )
        self.error = ""
        #: SYNCs the master had sent when the drives were enabled (boot and enable's own).
        self.enable_syncs = 0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._stop = False
        self._executor: Executor | None = None
        self._job_id: int | None = None
        self._beat_s = -math.inf
        self._gap_s = -1.0  # the last hand-over's time without a cycle (s)
        self._fault = ""
        self._state = "starting"
        self._master: CanMaster | None = None
        self._hold_um = np.zeros(3, np.int32)
        self._zero_um = np.zeros(3, np.int32)
        self._prep_thread: threading.Thread | None = None
        self._prepared: tuple[Job, Executor] | None = None
        # One hold loop for the daemon's life (no allocation between jobs).
        self._hold_loop = FixedRateLoop(self.clock, hold_config, Telemetry(1024))

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
            ex = self._executor
        if ex is not None:
            ex.request_stop(StopRequest.SHUTDOWN)
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
        """See :meth:`Runner.state`."""
        return f"fault: {self._fault}" if self._fault else self._state

    def current_job(self) -> int | None:
        """See :meth:`Runner.current_job`."""
        return self._job_id

    def progress(self) -> dict[str, Any] | None:
        """See :meth:`Runner.progress`."""
        ex = self._executor
        return None if ex is None else dict(ex.progress())

    def pause(self) -> None:
        """See :meth:`Runner.pause` (a job still being prepared: its store status decides)."""
        with self._lock:
            if self._executor is not None:
                self._executor.pause()

    def resume(self) -> None:
        """See :meth:`Runner.resume`."""
        with self._lock:
            if self._executor is not None:
                self._executor.resume()

    def cancel(self) -> None:
        """See :meth:`Runner.cancel` (a job still being prepared is cancelled in the store and
        never starts)."""
        with self._lock:
            ex, job_id = self._executor, self._job_id
        if ex is not None:
            ex.request_stop(StopRequest.CANCEL)
        elif job_id is not None:
            with contextlib.suppress(JobError):
                self.store.cancel(job_id)

    def configure(self, feedforward: bool, stale_cycles: int) -> None:
        """See :meth:`Runner.configure`."""
        self._feedforward = feedforward
        self._stale_cycles = stale_cycles

    # -- the thread ---------------------------------------------------------------------------

    def _main(self) -> None:
        report = apply_rt(self._rt_settings)
        for item in report.refused:
            log.warning("RT setting %s refused: %s", item.item, item.reason)
        _reset_rt_on_fork()
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
                # Keep what boot built out of later collections: the hold loop's collect, right
                # after enable, must be short (the drives' SYNC watchdog runs from enable on).
                gc.collect()
                gc.freeze()
                master.enable(self.clock.now, timeout_s)
                self._master = master
                np.copyto(self._hold_um, master.last_target_um())
                self.enable_syncs = master.feedback.sync_count
                self._state = self._idle_state()
            except BaseException as exc:
                self._start_error = exc
                return
            finally:
                self._ready.set()
            self._serve(master)
        except Exception as exc:
            self.error = f"runner failed: {type(exc).__name__}: {exc}"
            log.exception("runner failed")
            with contextlib.suppress(Exception):
                if self._master is not None:
                    self._master.quick_stop()
        finally:
            restore_rt(report)

    def _serve(self, master: CanMaster) -> None:
        while True:
            self._hold(master)
            if self._stop:
                break
            prepared, self._prepared = self._prepared, None
            if prepared is None:
                continue
            job, executor = prepared
            if self.store.get(job.id).status not in ACTIVE or self._fault:
                self._job_id = None
                continue
            self._run_job(master, job, executor)
        self._state = "stopping: disabling the drives"
        master.disable()
        self._settle(master)
        self._state = "stopped"

    def _beat(self, _sync: int, now_s: float) -> None:
        if self._gap_s < 0.0:
            self._gap_s = now_s - self._beat_s
        self._beat_s = now_s

    def _hold(self, master: CanMaster) -> None:
        """Hold at the last commanded stroke at the period until a job is prepared or the
        runner stops; start the preparation of the next job when the store changed."""
        clock = self.clock
        read_timeout_s = 0.5 * self.period_s
        hold_um, zero = self._hold_um, self._zero_um
        changed = self.store.changed
        changed.set()  # look for work once on entry
        settle_until = [clock.now() + SETTLE_TIMEOUT_S]

        def step(info: CycleInfo) -> LoopAction:
            if info.count == 0:
                self._gap_s = info.start_s - self._beat_s
            master.write_setpoints(hold_um, zero)
            fb = master.read_feedback(clock.now(), read_timeout_s)
            master.heartbeat(clock.now())
            self._beat_s = info.start_s
            if not self._fault and fb.status >= CycleStatus.EMCY:
                # The executor switched the master's own reaction off; stop every drive here.
                self._fault = f"while holding: {fb.status.name}"
                master.quick_stop()
            if self._stop:
                return LoopAction.STOP
            if self._prepared is not None:
                # The executor starts from the measured pose: hand over once the drives stand
                # on the held target, so its first setpoint is no step from this one.
                settled = not fb.stale.any() and bool(
                    (np.abs(fb.position_um - hold_um) <= SETTLED_UM).all()
                )
                if settled or info.start_s >= settle_until[0]:
                    if not settled:
                        log.warning(
                            "job start: drives %s um off the held target after %.1f s",
                            (fb.position_um - hold_um).tolist(),
                            SETTLE_TIMEOUT_S,
                        )
                    return LoopAction.STOP
            else:
                settle_until[0] = info.start_s + SETTLE_TIMEOUT_S
            prep = self._prep_thread
            if changed.is_set() and not self._fault and (prep is None or not prep.is_alive()):
                changed.clear()
                self._start_preparation()
            return LoopAction.CONTINUE

        if not self._job_id:
            self._state = self._idle_state()
        self._hold_loop.run(step)
        self._log_gap("-> hold", self._gap_s)

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
        self._prep_thread = threading.Thread(
            target=self._prepare, args=(job,), name="prepare", daemon=True
        )
        self._prep_thread.start()

    def _planner(self, name: str) -> TrenchPlanner:
        if name not in self._planners:
            self._planners[name] = TrenchPlanner(self.rig, name, model_dir=self.config.models_dir)
        return self._planners[name]

    def _prepare(self, job: Job) -> None:
        """Off the loop's thread: the job's session (new, or restored at the next undone dig)
        and its executor, so the hold hands over to the executor within one period."""
        done = len(job.digs)
        if job.max_digs is not None and done >= job.max_digs:
            self.store.set_status(job.id, "done")
            self._job_id = None
            return
        try:
            planner = self._planner(job.planner)
            task = _task_of(job, self.rig)
            if job.session_state is None:
                session = planner.start(task)
            else:
                session = TrenchSession.restore(planner, task, job.session_state)
            loop = FixedRateLoop(
                self.clock, self._loop_config, executor_telemetry(JOB_TELEMETRY_ROWS)
            )
            executor = Executor(
                self._master_or_fail(),
                self.rig,
                loop,
                session,
                ExecutorConfig(
                    feedforward=self._feedforward,
                    max_digs=None if job.max_digs is None else job.max_digs - done,
                    stale_cycles=self._stale_cycles,
                    disable_at_end=False,  # the runner holds between jobs
                ),
                on_dig_done=lambda rec: self._dig_done(job.id, rec),
                on_cycle=self._beat,
            )
        except (ExcavatorRtError, KeyError, TypeError, ValueError) as exc:
            log.error("job %d cannot start: %s", job.id, exc)
            self.store.set_status(job.id, "failed", f"cannot start: {exc}")
            self._job_id = None
            return
        # Everything alive now (the session, the executor) moves out of the collector's reach, so
        # the job loop's collect at its start scans nothing: O(1) here, no pause there. Cyclic
        # garbage made before this point is never collected (see the module docstring).
        gc.freeze()
        self._prepared = (job, executor)

    def _master_or_fail(self) -> CanMaster:
        if self._master is None:
            raise CommunicationError("the drives are not enabled")
        return self._master

    def _dig_done(self, job_id: int, rec: DigRecord) -> None:
        """``on_dig_done``: the dig's summary and the session state into the store (no I/O)."""
        self.store.record_dig(job_id, {k: getattr(rec, k) for k in DIG_KEYS}, rec.session_state)
        log.info(
            "job %d: dig %d done (%s, planned %.2f L, measured %.2f L)",
            job_id,
            rec.index,
            rec.dig_type,
            rec.planned_volume_m3 * 1e3,
            rec.measured_volume_m3 * 1e3,
        )

    def _run_job(self, master: CanMaster, job: Job, ex: Executor) -> None:
        with self._lock:
            self._executor = ex
            self._job_id = job.id
            if self._stop:
                ex.request_stop(StopRequest.SHUTDOWN)
            if self.store.mark_running(job.id).status == "paused":
                ex.pause()  # paused while it was being prepared: it holds at the start
        self._state = f"running job {job.id}"
        log.info(
            "job %d: running (task %s, %d dig(s) done)", job.id, job.task["name"], len(job.digs)
        )
        self._gap_s = -1.0  # set by the executor's first cycle (_beat)
        result: ExecutorResult | None = None  # None: the executor raised
        try:
            result = ex.run()
        except Exception as exc:
            log.exception("job %d: the executor failed", job.id)
            master.quick_stop()
            self._fault = f"executor failed: {type(exc).__name__}: {exc}"
        # Straight back to holding: only what the next cycles need happens here; the reports
        # (logs, telemetry file) go to a thread.
        np.copyto(self._hold_um, master.last_target_um())
        if result is None:
            self.store.set_status(job.id, "failed", self._fault)
        else:
            self._record_outcome(job, result)
        with self._lock:
            self._executor, self._job_id = None, None
        if result is None:
            return
        threading.Thread(
            target=self._report_run, args=(job, result, self._gap_s), name="job-report",
            daemon=True,
        ).start()  # fmt: skip

    def _log_gap(self, what: str, gap_s: float) -> None:
        """Log a hand-over's longest time without a cycle (the drives' SYNC watchdog's view)."""
        if gap_s < 0.0 or not math.isfinite(gap_s):
            return
        limit_s = self.rig.drives.sync_timeout_s
        level = logging.WARNING if gap_s > 0.5 * limit_s else logging.INFO
        log.log(level, "hand-over %s: %.1f ms between cycles (SYNC watchdog %.0f ms)", what,
                gap_s * 1e3, limit_s * 1e3)  # fmt: skip

    def _record_outcome(self, job: Job, result: ExecutorResult) -> None:
        """The job's status from the run's (the store in memory; its writer thread persists)."""
        st = result.status
        if st is ExecStatus.DONE:
            self.store.set_status(job.id, "done")
        elif st is ExecStatus.CANCELLED:
            self.store.set_status(job.id, "cancelled", "cancelled by request")
        elif st is ExecStatus.STOPPED:
            # Shut down mid-job: resumable at the next undone dig after the restart.
            paused = self.store.get(job.id).status == "paused"
            self.store.set_status(job.id, "paused" if paused else "queued")
        else:
            fault = f"{st.name.lower()}: {result.fault or 'no detail'}"
            self.store.set_status(job.id, "failed", fault)
            if st is not ExecStatus.PLANNING_ERROR:
                self._fault = f"job {job.id}: {fault}"

    def _report_run(self, job: Job, result: ExecutorResult, gap_s: float) -> None:
        """Off the loop's thread: log the run, write its telemetry to the state directory."""
        self._log_gap(f"hold -> job {job.id}", gap_s)
        log.info(
            "job %d: %s after %d dig(s) this run, %d overrun(s), max lateness %.0f us%s",
            job.id,
            result.status.name.lower(),
            len(result.digs),
            result.overruns,
            result.loop.max_lateness_s * 1e6,
            f"; {result.fault}" if result.fault else "",
        )
        path = self.config.paths.state_dir / "telemetry" / f"job-{job.id}.npz"
        try:
            path.parent.mkdir(mode=0o700, exist_ok=True)
            savez: Any = np.savez  # numpy's stubs read ** as its allow_pickle flag
            savez(path, **result.telemetry)
        except OSError as exc:
            log.warning("telemetry %s not written: %s", path, exc)

    def _settle(self, master: CanMaster, timeout_s: float = 0.5) -> None:
        """Keep cycling (hold, SYNC) until no drive reports OPERATION_ENABLED or time is up."""
        end = self.clock.now() + timeout_s
        next_s = self.clock.now()
        while self.clock.now() < end:
            self.clock.sleep_until(next_s)
            next_s += self.period_s
            master.write_setpoints(self._hold_um, self._zero_um)
            fb = master.read_feedback(self.clock.now(), 0.5 * self.period_s)
            master.heartbeat(self.clock.now())
            if not (fb.state == int(DriveState.OPERATION_ENABLED)).any():
                break


def _reset_rt_on_fork() -> None:
    """Keep SCHED_FIFO from passing to processes this thread starts.

    The executor starts its planner process from the loop's thread; a child inherits the
    scheduling policy, and a planner importing numpy and onnxruntime at SCHED_FIFO starves
    everything else on the CPU (the drives' answers too) until it lowers itself.
    SCHED_RESET_ON_FORK makes every child start as SCHED_OTHER.
    """
    try:
        policy = os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK
        if policy == os.SCHED_FIFO:
            param = os.sched_getparam(0)
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, param)
    except OSError as exc:
        log.warning("SCHED_RESET_ON_FORK refused: %s", exc)


# -- the service --------------------------------------------------------------------------------


class Service:
    """The main thread: control socket, signals, systemd notifications, the runner's life.

    Args:
        config: The configuration.
        rig: The rig (task validation).
        store: The job store (not yet started).
        server: The bound control socket (its commands are set here).
        runner: The runner (not yet started).
        notifier: systemd notifications.
        recorder: The bus trace recorder, or None.
        watchdog_s: Interval of WATCHDOG=1; default from ``$WATCHDOG_USEC``.
    """

    def __init__(
        self,
        config: DaemonConfig,
        rig: Rig,
        store: JobStore,
        server: ControlServer,
        runner: Runner,
        notifier: Notifier | None = None,
        recorder: TraceRecorder | None = None,
        watchdog_s: float | None = None,
    ) -> None:
        self.config = config
        self.rig = rig
        self.store = store
        self.server = server
        self.runner = runner
        self.notifier = notifier if notifier is not None else Notifier()
        self.recorder = recorder
        self.watchdog_s = watchdog_s if watchdog_s is not None else watchdog_interval_s()
        self._stop_reason = ""
        self._reload = False
        self._status = ""
        self._wake_r, self._wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        server.commands.update(
            {
                "submit": self.cmd_submit,
                "status": self.cmd_status,
                "list": self.cmd_list,
                "pause": self.cmd_pause,
                "resume": self.cmd_resume,
                "cancel": self.cmd_cancel,
                "stop": self.cmd_stop,
            }
        )

    # -- commands (main thread) ---------------------------------------------------------------

    def _job_id(self, req: dict[str, Any], default_current: bool) -> int:
        job_id = req.get("id")
        if job_id is None and default_current:
            job_id = self.runner.current_job()
            if job_id is None:
                raise JobError("no job is running; give an id")
        if isinstance(job_id, bool) or not isinstance(job_id, int):
            raise JobError(f'"id" must be a job id (an integer), got {job_id!r}')
        return job_id

    def _synced(self, job: Job) -> dict[str, Any]:
        if not self.store.sync():
            raise CommunicationError(
                f"the job store could not be written: {self.store.write_error}"
            )
        return {"job": job.to_json(with_state=False)}

    def cmd_submit(self, req: dict[str, Any]) -> dict[str, Any]:
        """``submit {task, planner?, max_digs?}``: validate the task and queue a job (nothing
        moves on a refusal)."""
        unknown = sorted(set(req) - {"cmd", "task", "planner", "max_digs"})
        if unknown:
            raise ConfigurationError(
                f"submit: unknown key(s) {', '.join(unknown)}; allowed: task, planner, max_digs"
            )
        planner = req.get("planner", self.config.planner)
        if planner not in PLANNERS:
            raise ConfigurationError(f"planner {planner!r}; allowed: {', '.join(PLANNERS)}")
        max_digs = req.get("max_digs")
        if max_digs is not None and (
            isinstance(max_digs, bool) or not isinstance(max_digs, int) or not 1 <= max_digs <= 1000
        ):
            raise ConfigurationError(f"max_digs {max_digs!r}; allowed: an integer in [1, 1000]")
        if "task" not in req:
            raise ConfigurationError('submit needs "task": a built-in name or an object')
        _task, numbers = resolve_task(req["task"], self.rig)
        job = self.store.submit(numbers, str(planner), max_digs)
        log.info("job %d submitted: task %s, planner %s", job.id, numbers["name"], planner)
        return self._synced(job)

    def daemon_status(self) -> dict[str, Any]:
        """The daemon's part of a ``status`` reply."""
        healthy, why = self.runner.health()
        return {
            "state": self.runner.state(),
            "healthy": healthy,
            "unhealthy_because": why,
            "rig": self.rig.name,
            "period_s": self.config.loop.period_s,
            "current_job": self.runner.current_job(),
            "pid": os.getpid(),
            "config": str(self.config.source),
        }

    def cmd_status(self, req: dict[str, Any]) -> dict[str, Any]:
        """``status {id?}``: the daemon, and the job (default: the current one)."""
        out: dict[str, Any] = {"daemon": self.daemon_status(), "job": None, "progress": None}
        job_id = req.get("id", self.runner.current_job())
        if job_id is not None:
            job = self.store.get(self._job_id({"id": job_id}, False))
            out["job"] = job.to_json(with_state=False)
            if job.id == self.runner.current_job():
                out["progress"] = self.runner.progress()
        return out

    def cmd_list(self, _req: dict[str, Any]) -> dict[str, Any]:
        """``list``: every job kept (without session states)."""
        return {"jobs": [j.to_json(with_state=False) for j in self.store.jobs()]}

    def cmd_pause(self, req: dict[str, Any]) -> dict[str, Any]:
        """``pause {id?}``: pause a queued job, or the running one (the executor decides when
        the arm comes to rest)."""
        job_id = self._job_id(req, True)
        job = self.store.pause(job_id)
        if job_id == self.runner.current_job():
            self.runner.pause()
        return self._synced(job)

    def cmd_resume(self, req: dict[str, Any]) -> dict[str, Any]:
        """``resume {id}``: resume a paused job or retry a failed one from its last dig."""
        job_id = self._job_id(req, False)
        current = job_id == self.runner.current_job()
        job = self.store.resume(job_id, running=current)
        if current:
            self.runner.resume()
        return self._synced(job)

    def cmd_cancel(self, req: dict[str, Any]) -> dict[str, Any]:
        """``cancel {id}``: drop a waiting job, or stop the running one (jerk-limited)."""
        job_id = self._job_id(req, False)
        if job_id == self.runner.current_job():
            self.runner.cancel()
            return {"job": self.store.get(job_id).to_json(with_state=False), "cancelling": True}
        return self._synced(self.store.cancel(job_id))

    def cmd_stop(self, _req: dict[str, Any]) -> dict[str, Any]:
        """``stop``: shut the daemon down as SIGTERM does (safe stop, drives disabled)."""
        self._stop_reason = "stop requested on the control socket"
        return {"stopping": True}

    # -- signals ------------------------------------------------------------------------------

    def _on_signal(self, signum: int, _frame: Any) -> None:
        if signum == signal.SIGHUP:
            self._reload = True
        else:
            self._stop_reason = f"signal {signal.Signals(signum).name}"

    def _drain_wakeup(self) -> None:
        with contextlib.suppress(BlockingIOError):
            while os.read(self._wake_r, 512):
                pass

    def reload(self) -> None:
        """Re-read the configuration file and apply what may change while running."""
        self.notifier.reloading()
        try:
            new = load_config(self.config.source)
        except ConfigurationError as exc:
            log.error("reload refused, the running configuration stays: %s", exc)
            self.notifier.ready(self.runner.state())
            return
        reloadable, restart = self.config.changes(new)
        _set_log_level(new.log_level)
        self.runner.configure(new.feedforward, new.stale_cycles)
        if self.recorder is not None and new.paths.trace != self.config.paths.trace:
            self.recorder.reopen(new.paths.trace)
        self.config = dataclasses.replace(
            self.config,
            feedforward=new.feedforward,
            planner=new.planner,
            stale_cycles=new.stale_cycles,
            log_level=new.log_level,
            paths=dataclasses.replace(self.config.paths, trace=new.paths.trace),
        )
        log.info("reloaded: %s", ", ".join(reloadable) or "nothing changed that reloads")
        if restart:
            log.warning("reload: %s changed; these apply at the next restart", ", ".join(restart))
        self.notifier.ready(self.runner.state())

    # -- the main loop ------------------------------------------------------------------------

    def run(self) -> int:
        """Start the runner, serve until a stop, stop safely; the exit code."""
        handled = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
        previous = {s: signal.signal(s, self._on_signal) for s in handled}
        old_wakeup = signal.set_wakeup_fd(self._wake_w, warn_on_full_buffer=False)
        self.server.add_reader(self._wake_r, self._drain_wakeup)
        self.store.start()
        code = EXIT_OK
        try:
            self.notifier.status("booting the drives")
            try:
                self.runner.start()
            except (CommunicationError, DriveFault, OSError, can.CanError) as exc:
                print(f"excavator-rtd: error: drives not enabled: {exc}", file=sys.stderr)
                log.error("drives not enabled: %s", exc)
                self.notifier.stopping(f"drives not enabled: {exc}")
                self.runner.shutdown(10.0)
                return EXIT_BUS
            self._status = self.runner.state()
            self.notifier.ready(self._status)
            log.info(
                "ready: %s; drives enabled after %d SYNC(s); control socket %s",
                self._status,
                getattr(self.runner, "enable_syncs", 0),
                self.server.path,
            )
            code = self._serve()
        finally:
            self.notifier.stopping(f"stopping ({self._stop_reason or 'error'})")
            if not self.runner.shutdown(30.0):
                log.error("the runner did not stop within 30 s")
                code = code or EXIT_RUNTIME
            if not self.store.close():
                log.error("job store not written: %s", self.store.write_error)
            self.server.close()
            signal.set_wakeup_fd(old_wakeup)
            for s, h in previous.items():
                signal.signal(s, h)
            os.close(self._wake_r)
            os.close(self._wake_w)
        log.info("stopped (%s)", self._stop_reason or "runner ended")
        return code

    def _serve(self) -> int:
        next_ping = time.monotonic()
        while True:
            timeout = _POLL_S
            if self.watchdog_s is not None:
                timeout = max(0.0, min(timeout, next_ping - time.monotonic()))
            self.server.poll(timeout)
            if self._stop_reason:
                log.info("stopping: %s", self._stop_reason)
                return EXIT_OK
            if self._reload:
                self._reload = False
                self.reload()
            if not self.runner.alive():
                err = getattr(self.runner, "error", "") or "the runner thread ended"
                log.error("%s", err)
                self._stop_reason = err
                return EXIT_RUNTIME
            healthy, why = self.runner.health()
            if self.watchdog_s is not None and time.monotonic() >= next_ping:
                next_ping = time.monotonic() + self.watchdog_s
                if healthy:
                    self.notifier.watchdog()
                else:
                    log.warning("no WATCHDOG=1: %s", why)
            state = self.runner.state()
            if state != self._status:
                self._status = state
                self.notifier.status(state)
                log.info("%s", state)


# -- entry point --------------------------------------------------------------------------------

_handler_installed = False


def _set_log_level(level: str) -> None:
    logging.getLogger("excavator-rtd").setLevel(level.upper())
    if _handler_installed:
        logging.getLogger().setLevel(level.upper())


def _setup_logging(level: str) -> None:
    global _handler_installed
    root = logging.getLogger()
    if not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        # journald stamps each line itself.
        fmt = "%(levelname)s %(name)s: %(message)s"
        if not os.environ.get("JOURNAL_STREAM"):
            fmt = "%(asctime)s " + fmt
        handler.setFormatter(logging.Formatter(fmt))
        root.addHandler(handler)
        _handler_installed = True
    _set_log_level(level)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        "excavator-rtd", description="The rig daemon: runs trench jobs (docs/daemon.md)."
    )
    p.add_argument("--config", required=True, help="TOML configuration file")
    p.add_argument(
        "--check",
        action="store_true",
        help="validate the configuration, rig, models and job store, then exit (no bus)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``excavator-rtd --config FILE [--check]``; returns the exit code."""
    args = _parser().parse_args(argv)
    _setup_logging("info")
    try:
        config = load_config(args.config)
        _set_log_level(config.log_level)
        rig, planner = load_planning(config)
        store = JobStore(config.paths.state_dir)
    except ConfigurationError as exc:
        print(f"excavator-rtd: error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    if args.check:
        print(
            f"excavator-rtd: {args.config} is valid: rig {rig.name}, period "
            f"{config.loop.period_s * 1e3:g} ms, bus {config.bus.interface} "
            f"{config.bus.channel}, {len(store.jobs())} job(s) in {store.path}"
        )
        return EXIT_OK
    server = ControlServer(config.paths.socket, {})
    try:
        server.bind()
    except ConfigurationError as exc:
        print(f"excavator-rtd: error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    # Everything the process has built so far lives for the daemon's life: keep it out of
    # every later collection so a loop run's collect is short.
    gc.collect()
    gc.freeze()
    # The runner thread must get the interpreter back within a fraction of a period when a
    # request or a job's preparation runs Python on another thread.
    sys.setswitchinterval(min(sys.getswitchinterval(), 2e-4))
    recorder: TraceRecorder | None = None
    try:
        raw_bus = open_bus(config, rig)
    except CommunicationError as exc:
        server.close()
        print(f"excavator-rtd: error: {exc}", file=sys.stderr)
        return EXIT_BUS
    recorder = TraceRecorder(config.paths.trace)
    bus = TracedBus(raw_bus, recorder)
    try:
        runner = RigRunner(config, rig, planner, bus, store)
        service = Service(config, rig, store, server, runner, recorder=recorder)
        return service.run()
    finally:
        recorder.close()
        with contextlib.suppress(Exception):
            bus.shutdown()
        for h in logging.getLogger().handlers:
            h.flush()


if __name__ == "__main__":
    sys.exit(main())
