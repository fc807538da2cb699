"""``excavator-rtd``: the rig daemon that runs trench jobs under systemd.

Start-up, in this order (nothing reaches the bus before the configuration, the rig and the
models have been checked)::

    load_config (keys)  ->  load_planning (rig, PINN models vs. their cards)  ->  job store
    ->  control socket bound  ->  bus opened  ->  runner thread: CanMaster.boot + enable,
    then holds position every period  ->  sd_notify READY=1  ->  serve requests

Threads: the **main thread** serves the control socket, the signals (through a wake-up pipe)
and the systemd notifications in one ``selectors`` loop. The **runner thread**
(:class:`~rt_runtime.service.runner.RigRunner`) owns the bus, the master and one controller
manager on one fixed-rate loop for the daemon's whole life: between jobs the hold controller
holds every axis at its last commanded stroke at the period (the drives' SYNC watchdog never
starves while they are enabled), and each job's controller takes over at a cycle boundary once
a **preparation thread** has built it (its planner session, new or restored from the job
store, and its planner process) and the drives stand on the held target; the hold takes over
again at the boundary after the job ends. The job store writes on its own thread; the trace
(``paths.trace``) too.

Real time (where DESIGN.md leaves the daemon's share open): RT settings (SCHED_FIFO with
SCHED_RESET_ON_FORK, mlockall, CPU, timer slack) are applied once to the runner thread for its
life. The collector: the heap is frozen after boot and when a job is prepared (``gc.freeze``
is O(1)), and the collector is off while a job runs. The price: cyclic garbage made before a
freeze is never collected while the daemon runs (a restart frees it). The interpreter's switch
interval is lowered to 0.2 ms so the loop's thread gets the interpreter back quickly from the
main and helper threads, and those run SCHED_FIFO :data:`HELPER_PRIORITY` (below the loop's;
:class:`~rt_runtime.control.rt.HelperThreads`), so none is preempted by other work while it
holds the interpreter lock. Before it boots the drives, the runner's timing self-test logs what
this host holds (:mod:`rt_runtime.service.preflight`); ``--check`` runs it too.

Signals: SIGTERM / SIGINT (and the ``stop`` request) -> STOPPING=1, the executor's jerk-limited
stop (``StopRequest.SHUTDOWN``), drives disabled (controlword 0x0000), the job left resumable
(``queued`` with its last recorded dig), store, trace and logs flushed, exit 0. SIGHUP ->
RELOADING=1, re-read the file, apply :data:`~rt_runtime.service.config.RELOADABLE_KEYS` (log
level; feed-forward and planner for the next job; trace reopened), log the keys that need a
restart, READY=1. An invalid file on SIGHUP is logged and the running configuration kept.

Faults: a latched fault (drive fault, EMCY, lost heartbeat, following error, stale feedback,
overrun stop, bus error of any kind, the planner process ending) stops the arm and the
running job (``failed``), and the daemon stays up: it answers on the socket, reports the fault
(``status``, STATUS=) and refuses what would move (``resume``: error code ``faulted``; a
submitted job waits) until the ``reset-fault`` request, on which the runner reopens the bus if
it broke, boots and enables the drives from whatever state they are in, holds at the measured
pose and queues the failed job again (:mod:`rt_runtime.service.runner`).

Watchdog: WATCHDOG=1 every ``$WATCHDOG_USEC / 2`` while the runner's loop has cycled within
:data:`STALE_LOOP_S`, or while the runner waits for a reset with the fault latched or runs one:
a latched fault is reported and waits for ``reset-fault``, it is no reason for systemd to
restart the daemon; a loop that stops cycling (a hang) is. Crashes (SIGKILL, SIGABRT from
systemd's watchdog): ``faulthandler`` writes every thread's stack to stderr on SIGABRT (and
SIGSEGV, SIGFPE, SIGBUS, SIGILL), best effort (walking a thread inside C code may end the dump
in SIGSEGV); the restart boots the drives from whatever state they are in and resumes the job
at its next undone dig.

Exit codes: :data:`EXIT_OK` 0, :data:`EXIT_RUNTIME` 1 (the runner died), :data:`EXIT_CONFIG` 2
(configuration, rig, models, job store, socket; nothing was sent on the bus), :data:`EXIT_BUS`
3 (the bus did not open, or the drives did not boot or enable).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import faulthandler
import gc
import glob
import logging
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

from rt_runtime.canbus.traced import TracedBus
from rt_runtime.control.rt import HelperThreads
from rt_runtime.errors import (
    CommunicationError,
    ConfigurationError,
    DriveFault,
)
from rt_runtime.service.config import (
    PLANNERS,
    DaemonConfig,
    load_config,
    load_planning,
)
from rt_runtime.service.control import ControlServer, RefusedError
from rt_runtime.service.jobstore import Job, JobError, JobStore
from rt_runtime.service.notify import Notifier, watchdog_interval_s
from rt_runtime.service.preflight import check_start
from rt_runtime.service.runner import STALE_LOOP_S, RigRunner, close_bus

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
#: SCHED_FIFO priority of the daemon's threads other than the loop's: below the loop and below
#: a HIL process standing in for drive firmware (30), above every normal process.
HELPER_PRIORITY = 10
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
    never happen on the loop's thread). The file rotates (python-can's
    ``SizedRotatingLogger``) when it reaches ``max_mb``: it is kept as ``<stem>.<n><suffix>``
    (``n`` counting up), as is a file a previous start left; of those the newest ``keep`` stay
    and older ones are deleted, so the traces' disk use is bounded by ``(keep + 1) * max_mb``.

    Args:
        path: The file (``.blf`` or ``.asc``); None: record nothing until :meth:`reopen`.
        max_mb: Size at which the file rotates (MB, 10^6 bytes).
        keep: Rotated files kept.
    """

    _REOPEN = object()

    def __init__(self, path: Path | None, max_mb: float = 64.0, keep: int = 8) -> None:
        self.queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.path: Path | None = None
        self.max_mb = float(max_mb)
        self.keep = int(keep)
        self.active = False
        self.frames = 0
        self._logger: can.Listener | None = None
        self._thread = threading.Thread(target=self._run, name="trace", daemon=True)
        self._opened = threading.Event()
        self._thread.start()
        self.reopen(path)

    @staticmethod
    def _rotated(path: Path) -> list[tuple[int, Path]]:
        """The rotated files of ``path`` (``<stem>.<n><suffix>``), oldest first."""
        found = []
        for p in path.parent.glob(f"{glob.escape(path.stem)}.*{glob.escape(path.suffix)}"):
            n = p.name[len(path.stem) + 1 : len(p.name) - len(path.suffix)]
            if n.isdigit():
                found.append((int(n), p))
        return sorted(found)

    def _next_name(self, path: Path) -> Path:
        rotated = self._rotated(path)
        n = rotated[-1][0] + 1 if rotated else 1
        return path.with_name(f"{path.stem}.{n}{path.suffix}")

    def _rotate(self, source: str | os.PathLike[str], dest: str | os.PathLike[str]) -> None:
        """python-can's rotator: keep the full file under its number, delete the oldest."""
        if os.path.exists(source):
            os.replace(source, dest)
        self._prune(Path(source))

    def _prune(self, path: Path) -> None:
        rotated = self._rotated(path)
        for _n, old in rotated[: max(0, len(rotated) - self.keep)]:
            with contextlib.suppress(OSError):
                old.unlink()

    def reopen(
        self, path: Path | None, max_mb: float | None = None, keep: int | None = None
    ) -> None:
        """Close the current file and start ``path`` (None: stop recording), with new
        rotation settings where given."""
        self._opened.clear()
        self.queue.put((self._REOPEN, path, max_mb, keep))
        self._opened.wait(10.0)

    def _open(self, path: Path | None, max_mb: float | None, keep: int | None) -> None:
        if self._logger is not None:
            self._logger.stop()
            self._logger = None
        if max_mb is not None:
            self.max_mb = float(max_mb)
        if keep is not None:
            self.keep = int(keep)
        self.active = False
        self.path = path
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                if path.exists():
                    self._rotate(str(path), str(self._next_name(path)))
                else:
                    self._prune(path)
                logger = can.SizedRotatingLogger(str(path), max_bytes=round(self.max_mb * 1e6))
                logger.namer = lambda _default: str(self._next_name(path))
                logger.rotator = self._rotate
                self._logger = logger
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
                self._open(item[1], item[2], item[3])
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
                try:
                    self._logger.on_message_received(msg)
                    self.frames += 1
                except Exception as exc:  # a full disk: the daemon goes on, without a trace
                    log.error("trace %s: write failed, recording stopped: %s", self.path, exc)
                    self.active = False
                    with contextlib.suppress(Exception):
                        self._logger.stop()
                    self._logger = None

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is queued, close the file and stop the thread."""
        self.queue.put(None)
        self._thread.join(timeout_s)
        self.active = False


# -- the runner ---------------------------------------------------------------------------------


class Runner(Protocol):
    """What the service needs from the thread that owns the drives (the real one is
    :class:`RigRunner`; the tests use a fake).

    Attributes:
        resets_done: Resets of a latched fault that have ended, succeeded or not.
    """

    resets_done: int

    def start(self) -> None:
        """Boot and enable the drives and start holding; return once they are enabled.

        Raises:
            CommunicationError, DriveFault: Boot or enable failed (the bus was used).
        """
        ...

    def shutdown(self, timeout_s: float) -> bool:
        """Stop safely (a running job: jerk-limited stop, left resumable), disable the drives,
        end the thread, and let the last job's report finish (a few seconds at most). True
        when the thread ended in time."""
        ...

    def alive(self) -> bool:
        """The runner's thread is running."""
        ...

    def health(self) -> tuple[bool, str]:
        """``(healthy, why not)``: the loop cycles and no fault is latched."""
        ...

    def watchdog(self) -> tuple[bool, str]:
        """``(ok, why not)`` for WATCHDOG=1: the runner works as designed (its loop cycles,
        or it waits for a reset with the fault latched, or runs one)."""
        ...

    def fault(self) -> str:
        """The latched fault (one line), empty when none is latched."""
        ...

    def reset_fault(self) -> int:
        """Ask for a reset of the latched fault (any thread; returns at once). Returns the
        number the reset will have: it has ended, succeeded or not, once ``resets_done``
        reaches it."""
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
                "reset-fault": self.cmd_reset_fault,
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
        """``submit {task, planner?, max_digs?}`` or ``submit {teach}``: validate the task (or
        the taught job) and queue a job (nothing moves on a refusal)."""
        unknown = sorted(set(req) - {"cmd", "task", "planner", "max_digs", "teach"})
        if unknown:
            raise ConfigurationError(
                f"submit: unknown key(s) {', '.join(unknown)}; allowed: task, planner, "
                "max_digs, teach"
            )
        if "teach" in req:
            return self._submit_taught(req)
        if self.rig.swing is not None:
            raise ConfigurationError(
                f"rig {self.rig.name} has a swing axis: it takes taught jobs "
                '(submit {"teach": DIR}, `job submit --teach DIR`); the trench planner plans '
                "the arm plane only"
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
        out = self._synced(job)
        fault = self.runner.fault()
        if fault:
            out["fault"] = fault  # queued; nothing starts before a reset-fault
        return out

    def _submit_taught(self, req: dict[str, Any]) -> dict[str, Any]:
        """A taught job: ``teach`` is the directory ``teach --out`` wrote (or its
        ``taught.json``), on this machine. It is verified against the rig (the exact limit
        check) and copied into the state directory, under its SHA-256, so the job does not
        depend on the original staying; nothing moves on a refusal."""
        import hashlib
        import json

        from rt_runtime.control.taught_path import load_taught_path
        from rt_runtime.service.jobstore import atomic_write_json

        extra = sorted(set(req) - {"cmd", "teach"})
        if extra:
            raise ConfigurationError(
                f"submit with teach takes no {', '.join(extra)}: a taught job runs its trench"
            )
        spec = req["teach"]
        if not isinstance(spec, str) or not spec:
            raise ConfigurationError('submit "teach" must be the path of a taught job directory')
        src = Path(spec)
        if not src.is_absolute():
            raise ConfigurationError(
                f"submit teach {spec!r}: the daemon needs an absolute path (the client sends one)"
            )
        path_job, taught = load_taught_path(src, self.rig)
        path_job.check(self.rig)
        file = src / "taught.json" if src.is_dir() else src
        data = json.loads(file.read_text(encoding="utf-8"))
        digest = hashlib.sha256(file.read_bytes()).hexdigest()[:16]
        keep = self.store.path.parent / f"taught-{digest}.json"
        atomic_write_json(keep, data)
        job = self.store.submit({}, self.config.planner, taught=str(keep))
        log.info(
            "job %d submitted: taught trench of %d cycles (%.1f s) from %s",
            job.id,
            taught.n_cycles,
            taught.duration_s,
            file,
        )
        out = self._synced(job)
        fault = self.runner.fault()
        if fault:
            out["fault"] = fault
        return out

    def _refuse_if_faulted(self, what: str) -> None:
        fault = self.runner.fault()
        if fault:
            raise RefusedError(
                "faulted",
                f"{what} refused: a fault is latched ({fault}); nothing moves until "
                "`excavator-rt job reset-fault`",
            )

    def daemon_status(self) -> dict[str, Any]:
        """The daemon's part of a ``status`` reply."""
        healthy, why = self.runner.health()
        return {
            "state": self.runner.state(),
            "healthy": healthy,
            "unhealthy_because": why,
            "fault": self.runner.fault(),
            "resets_done": self.runner.resets_done,
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
        self._refuse_if_faulted(f"resume of job {job_id}")
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

    def cmd_reset_fault(self, _req: dict[str, Any]) -> dict[str, Any]:
        """``reset-fault``: reopen the bus if it broke, boot and enable the drives again, hold
        at the measured pose, clear the latch and queue the failed job again (the runner does
        it; the reply comes at once with the reset's number: ``status`` says when
        ``daemon.resets_done`` reaches it, and ``daemon.fault`` is then empty or says why
        the reset failed)."""
        fault = self.runner.fault()
        if not fault:
            raise JobError("reset-fault: no fault is latched")
        number = self.runner.reset_fault()
        log.info("reset-fault requested (reset %d): %s", number, fault)
        return {"resetting": True, "reset": number, "fault": fault}

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
        old, got = self.config.paths, new.paths
        trace = (got.trace, got.trace_max_mb, got.trace_keep)
        if self.recorder is not None and trace != (old.trace, old.trace_max_mb, old.trace_keep):
            self.recorder.reopen(*trace)
        self.config = dataclasses.replace(
            self.config,
            feedforward=new.feedforward,
            planner=new.planner,
            stale_cycles=new.stale_cycles,
            log_level=new.log_level,
            paths=dataclasses.replace(
                old, trace=got.trace, trace_max_mb=got.trace_max_mb, trace_keep=got.trace_keep
            ),
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
            if self.watchdog_s is not None and time.monotonic() >= next_ping:
                next_ping = time.monotonic() + self.watchdog_s
                ok, why = self.runner.watchdog()
                if ok:
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
        help="check everything a start checks that needs no bus (configuration, rig, models, "
        "job store, socket and trace directories, RT settings, a timing self-test), change no "
        "file, exit",
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
        if args.check:
            checked = check_start(config, rig)
        else:
            store = JobStore(config.paths.state_dir)
    except ConfigurationError as exc:
        print(f"excavator-rtd: error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    if args.check:
        print(
            f"excavator-rtd: {args.config} is valid: rig {rig.name}, period "
            f"{config.loop.period_s * 1e3:g} ms; nothing was changed"
        )
        for line in checked:
            print(f"  {line}")
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
    # Every other thread that takes the interpreter lock runs above normal work and below the
    # loop, so none is preempted while the loop waits for the lock (HelperThreads).
    helpers = _helper_threads(config)
    # A crash or systemd's watchdog (SIGABRT) leaves every thread's stack in the journal.
    with contextlib.suppress(ValueError, OSError):  # a stderr without a file descriptor
        faulthandler.enable(all_threads=True)
    try:
        raw_bus = open_bus(config, rig)
    except CommunicationError as exc:
        if helpers is not None:
            helpers.restore()
        server.close()
        print(f"excavator-rtd: error: {exc}", file=sys.stderr)
        return EXIT_BUS
    recorder = TraceRecorder(
        config.paths.trace, config.paths.trace_max_mb, config.paths.trace_keep
    )

    def reopen() -> can.BusABC:
        """The bus again, from the configuration, into the same trace (a reset-fault)."""
        return TracedBus(open_bus(config, rig), recorder)

    runner = RigRunner(
        config, rig, planner, TracedBus(raw_bus, recorder), store, reopen=reopen
    )
    try:
        service = Service(config, rig, store, server, runner, recorder=recorder)
        return service.run()
    finally:
        if not close_bus(runner.bus):
            log.warning("the bus did not shut down within its timeout")
        recorder.close()
        if helpers is not None:
            helpers.restore()
        # What was frozen is garbage now: collect it, so the native extensions' objects
        # (ruckig's) are freed before the interpreter tears their modules down.
        gc.unfreeze()
        gc.collect()
        for h in logging.getLogger().handlers:
            h.flush()


def _helper_threads(config: DaemonConfig) -> HelperThreads | None:
    """SCHED_FIFO :data:`HELPER_PRIORITY` (below the loop's) for the daemon's other threads;
    None when the loop's priority is left alone or is 1."""
    loop_priority = config.loop.sched_fifo_priority or 0
    if loop_priority < 2:
        return None
    helpers = HelperThreads(min(HELPER_PRIORITY, loop_priority - 1))
    if not helpers.item.applied:
        log.warning("SCHED_FIFO for the daemon's other threads refused: %s", helpers.item.reason)
    return helpers


if __name__ == "__main__":
    sys.exit(main())
