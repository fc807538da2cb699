"""The daemon's jobs and their store on disk, written atomically so a restart resumes them.

A job is a trench task to dig: its task (the resolved numbers), the one-shot planner, a status
(:data:`STATUSES`), a summary of every dig done and, until the job is done or cancelled, the
planner session's state after the last dig (``TrenchSession.state()``), from which a restarted
daemon resumes at the next undone dig. A taught job (a rig with swing: ``job submit --teach
DIR``) has ``taught``, the path of its taught trench (copied into the state directory when it
was submitted) and the task ``{"name": "taught"}``; each of its cycles streamed to its end is
one of its ``digs`` (``dig_type`` ``"cycle"``, volumes null, ``session_state``
``{"steps_done": n}``), and a restart resumes it at its first undone cycle.

Store format (``<state_dir>/jobs.json``, UTF-8 JSON)::

    {"format": "excavator-rtd-jobs/1", "next_id": 4,
     "jobs": [{"id": 3, "status": "running", "planner": "pinn",
               "task": {"name": "A", "length_m": 0.6, "depth_m": 0.15, "beta1_deg": 60.0,
                        "beta2_deg": 60.0, "start_x_m": 1.05},
               "submitted_unix_s": ..., "updated_unix_s": ..., "fault": "", "max_digs": null,
               "digs": [{"index": 0, "dig_type": "downward", "T_s": 4.2, "plan_us": 3100.0,
                         "planned_volume_m3": 0.0041, "measured_volume_m3": 0.0039}],
               "session_state": {...}}, ...]}

Atomic writes (:func:`atomic_write_json`): the new content goes to a temporary file in the same
directory, is flushed and fsynced, renamed over the store (``os.replace`` is atomic on POSIX),
and the directory is fsynced so the rename itself survives a power cut. A crash at any point
leaves either the old or the new file, never a mix; a temporary file left behind by a crash is
ignored and removed on the next load.

Threads: :class:`JobStore` is shared by the control socket (main thread) and the job runner
(the loop's thread). Every method takes the store's lock for a short in-memory update; the file
is written by a writer thread (:meth:`JobStore.sync` waits for it), so no file I/O or fsync ever
runs on the loop's thread.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

from rt_runtime.errors import ConfigurationError
from rt_runtime.fileio import atomic_write
from rt_runtime.service.config import check_directory

__all__ = [
    "ACTIVE",
    "FINAL",
    "STATUSES",
    "STORE_FORMAT",
    "TAUGHT_TASK",
    "Job",
    "JobError",
    "JobStatus",
    "JobStore",
    "atomic_write_json",
    "read_store",
]

STORE_FORMAT = "excavator-rtd-jobs/1"


class JobStatus(IntEnum):
    """Where a job is (JSON, the store and the control socket: the lower-case name)."""

    QUEUED = 0
    RUNNING = 1
    PAUSED = 2
    DONE = 3
    CANCELLED = 4
    FAILED = 5

    @property
    def label(self) -> str:
        """The JSON spelling: ``queued``, ``running``, ``paused``, ``done``, ``cancelled``,
        ``failed``."""
        return self.name.lower()

    @classmethod
    def parse(cls, text: Any) -> JobStatus:
        """The status spelt ``text`` (or a JobStatus itself).

        Raises:
            ValueError: Not a status (names the allowed ones).
        """
        if isinstance(text, JobStatus):
            return text
        if isinstance(text, str) and text.upper() in cls.__members__ and text == text.lower():
            return cls[text.upper()]
        raise ValueError(f"status {text!r} is not one of {', '.join(STATUSES)}")

    def __str__(self) -> str:
        return self.label

    def __format__(self, spec: str) -> str:
        return format(self.label, spec)


#: Every status's JSON spelling.
STATUSES = tuple(s.label for s in JobStatus)
#: Statuses a job never leaves (``failed`` may be resumed by the operator).
FINAL = (JobStatus.DONE, JobStatus.CANCELLED)
#: Statuses the runner picks up, in this priority (a job found ``running`` after a crash first).
ACTIVE = (JobStatus.RUNNING, JobStatus.QUEUED)
STORE_NAME = "jobs.json"
_TASK_KEYS = ("name", "length_m", "depth_m", "beta1_deg", "beta2_deg", "start_x_m")
#: The task of a taught job (its trench is its file's).
TAUGHT_TASK: dict[str, Any] = {"name": "taught"}
#: Keys of a dig summary in a job record (the daemon builds them from the executor's record).
DIG_KEYS = ("index", "dig_type", "T_s", "plan_us", "planned_volume_m3", "measured_volume_m3")


class JobError(ConfigurationError):
    """A request about a job cannot be done (unknown id, wrong status); nothing changed."""


@dataclass(frozen=True, slots=True)
class Job:
    """One trench job.

    Attributes:
        id: Job id (1, 2, ... in submission order).
        status: Its :class:`JobStatus`.
        task: The resolved task (:data:`_TASK_KEYS`: name, m and deg).
        planner: One-shot planner (``pinn``, ``pso``).
        submitted_unix_s: Submission time (Unix s).
        updated_unix_s: Time of the last change (Unix s).
        digs: Summaries of the digs done, in order.
        session_state: ``TrenchSession.state()`` after the last dig done, or None before.
        fault: Why the job failed or was cancelled (empty otherwise).
        max_digs: The job is done after this many digs (None: when the task is dug).
        taught: A taught job's file (``taught.json`` in the state directory), else None.
    """

    id: int
    status: JobStatus
    task: dict[str, Any]
    planner: str
    submitted_unix_s: float
    updated_unix_s: float
    digs: tuple[dict[str, Any], ...] = ()
    session_state: dict[str, Any] | None = None
    fault: str = ""
    max_digs: int | None = None
    taught: str | None = None

    def to_json(self, *, with_state: bool = True) -> dict[str, Any]:
        """JSON-able form (the store's; ``with_state=False`` leaves out the session state)."""
        out: dict[str, Any] = {
            "id": self.id,
            "status": self.status.label,
            "planner": self.planner,
            "task": dict(self.task),
            "submitted_unix_s": self.submitted_unix_s,
            "updated_unix_s": self.updated_unix_s,
            "fault": self.fault,
            "max_digs": self.max_digs,
            "digs": [dict(d) for d in self.digs],
        }
        if self.taught is not None:
            out["taught"] = self.taught
        if with_state:
            out["session_state"] = self.session_state
        return out

    @classmethod
    def from_json(cls, raw: Any) -> Job:
        """Parse a stored job.

        Raises:
            ValueError: A key is missing or has the wrong type.
        """
        if not isinstance(raw, dict):
            raise ValueError(f"a job must be an object, got {type(raw).__name__}")
        try:
            status = JobStatus.parse(raw["status"])
            task = raw["task"]
            taught = raw.get("taught")
            if taught is not None:
                if not isinstance(taught, str) or task != TAUGHT_TASK:
                    raise ValueError(
                        f"a taught job has a file path under taught and the task {TAUGHT_TASK}"
                    )
            elif not isinstance(task, dict) or set(task) != set(_TASK_KEYS):
                raise ValueError(f"task must have keys {', '.join(_TASK_KEYS)}")
            digs = raw["digs"]
            if not isinstance(digs, list) or not all(
                isinstance(d, dict) and set(DIG_KEYS) <= set(d) for d in digs
            ):
                raise ValueError(f"digs must be a list of objects with {', '.join(DIG_KEYS)}")
            state = raw.get("session_state")
            if state is not None and not isinstance(state, dict):
                raise ValueError("session_state must be an object or null")
            job_id = raw["id"]
            if isinstance(job_id, bool) or not isinstance(job_id, int) or job_id < 1:
                raise ValueError(f"id must be an integer >= 1, got {job_id!r}")
            max_digs = raw.get("max_digs")
            if max_digs is not None and (
                isinstance(max_digs, bool) or not isinstance(max_digs, int) or max_digs < 1
            ):
                raise ValueError(f"max_digs must be an integer >= 1 or null, got {max_digs!r}")
            return cls(
                id=job_id,
                status=status,
                task=task,
                planner=str(raw["planner"]),
                submitted_unix_s=float(raw["submitted_unix_s"]),
                updated_unix_s=float(raw["updated_unix_s"]),
                digs=tuple(digs),
                session_state=state,
                fault=str(raw.get("fault", "")),
                max_digs=max_digs,
                taught=taught,
            )
        except KeyError as exc:
            raise ValueError(f"missing key {exc.args[0]!r}") from exc
        except (TypeError, ValueError) as exc:
            job = raw.get("id", "?")
            raise ValueError(f"job {job}: {exc}") from exc


def atomic_write_json(path: Path, obj: Any) -> None:
    """Replace ``path`` with ``obj`` as JSON, atomically and durably.

    Write a temporary file in the same directory, flush and fsync it, ``os.replace`` it over
    ``path``, fsync the directory. A crash leaves the old or the new file whole.

    Args:
        path: The file (its directory must exist).
        obj: A JSON-able object.

    Raises:
        OSError: The write failed (the old file is untouched; the temporary file is removed).
    """
    data = json.dumps(obj, separators=(",", ":"), allow_nan=False).encode("utf-8")
    atomic_write(path, lambda f: f.write(data), mode=0o600)


def _stale_temps(path: Path) -> Iterator[Path]:
    return path.parent.glob(f".{path.name}.*.tmp")


def read_store(path: Path) -> tuple[int, list[Job]]:
    """Read a store file.

    Returns:
        ``(next_id, jobs)``; ``(1, [])`` when the file does not exist.

    Raises:
        ConfigurationError: The file is not a valid store (named, with what is wrong).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return 1, []
    except OSError as exc:
        raise ConfigurationError(f"job store {path}: cannot read: {exc.strerror or exc}") from exc
    hint = "; move it aside to start with an empty store"
    try:
        raw = json.loads(text)
    except ValueError as exc:
        raise ConfigurationError(f"job store {path} is not valid JSON: {exc}{hint}") from exc
    if not isinstance(raw, dict) or raw.get("format") != STORE_FORMAT:
        raise ConfigurationError(f"job store {path}: format must be {STORE_FORMAT!r}{hint}")
    try:
        jobs = [Job.from_json(j) for j in raw["jobs"]]
        next_id = int(raw["next_id"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigurationError(f"job store {path}: {exc}{hint}") from exc
    ids = [j.id for j in jobs]
    if len(set(ids)) != len(ids) or (ids and next_id <= max(ids)):
        raise ConfigurationError(f"job store {path}: duplicate job ids or next_id too small{hint}")
    return next_id, jobs


@dataclass
class _Writer:
    version: int = 0
    written: int = 0
    error: str = ""
    stop: bool = False
    cond: threading.Condition = field(default_factory=threading.Condition)


class JobStore:
    """The daemon's jobs, persisted atomically by a writer thread.

    Args:
        state_dir: Directory of ``jobs.json`` (created 0700 when missing).
        keep_finished: Finished jobs (done, cancelled) kept; older ones are dropped.

    Raises:
        ConfigurationError: The directory cannot be made, or the store there is corrupt.
    """

    @staticmethod
    def check(state_dir: Path) -> tuple[int, int]:
        """What opening the store in ``state_dir`` checks, changing nothing
        (``excavator-rtd --check``): the directory is writable or can be made, the store file
        (when there is one) is valid.

        Returns:
            ``(jobs in the store, temporary files a crash left)`` (a start removes the latter).

        Raises:
            ConfigurationError: The directory cannot be written or made (``paths.state_dir``),
                or the store is not valid (the file named).
        """
        path = Path(state_dir) / STORE_NAME
        existed = check_directory(path.parent, "paths.state_dir", create=False)
        if not existed:
            return 0, 0
        _next_id, jobs = read_store(path)
        return len(jobs), sum(1 for _ in _stale_temps(path))

    def __init__(self, state_dir: Path, keep_finished: int = 100) -> None:
        self.path = Path(state_dir) / STORE_NAME
        try:
            self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigurationError(
                f"config key paths.state_dir: cannot create {self.path.parent}: "
                f"{exc.strerror or exc}"
            ) from exc
        for stale in _stale_temps(self.path):
            with contextlib.suppress(OSError):
                stale.unlink()
        self._next_id, jobs = read_store(self.path)
        self._jobs: dict[int, Job] = {j.id: j for j in jobs}
        self.keep_finished = keep_finished
        self._lock = threading.RLock()
        self._w = _Writer()
        self._thread: threading.Thread | None = None
        self.changed = threading.Event()  # set on every change; the runner waits on it

    # -- the writer -----------------------------------------------------------------------------

    def start(self) -> None:
        """Start the writer thread and write the store once (so a fresh store exists)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._write_loop, name="jobstore", daemon=True)
            self._thread.start()
        self._dirty()

    def _document(self) -> dict[str, Any]:
        return {
            "format": STORE_FORMAT,
            "next_id": self._next_id,
            "jobs": [j.to_json() for j in self._jobs.values()],
        }

    def _write_loop(self) -> None:
        w = self._w
        while True:
            with w.cond:
                while w.written == w.version and not w.stop:
                    w.cond.wait()
                if w.written == w.version and w.stop:
                    return
                target = w.version
            with self._lock:
                doc = self._document()
            try:
                atomic_write_json(self.path, doc)
                err = ""
            except Exception as exc:  # reported by sync(); the thread never ends on one
                err = f"job store {self.path}: write failed: {type(exc).__name__}: {exc}"
            with w.cond:
                w.written = max(w.written, target)
                w.error = err
                w.cond.notify_all()

    def _dirty(self) -> None:
        with self._w.cond:
            self._w.version += 1
            self._w.cond.notify_all()
        self.changed.set()

    def sync(self, timeout_s: float = 5.0) -> bool:
        """Wait until every change so far is on disk.

        Returns:
            True when written; False on timeout or a failed write (see :attr:`write_error`).
        """
        w = self._w
        with w.cond:
            target = w.version
            if self._thread is None:
                return w.written >= target
            ok = w.cond.wait_for(lambda: w.written >= target, timeout_s)
            return ok and not w.error

    def rewrite(self, timeout_s: float = 5.0) -> bool:
        """Write the store again now (after a failed write: is its disk back?) and wait.

        Returns:
            True when written (:attr:`write_error` is then empty).
        """
        self._dirty()
        return self.sync(timeout_s)

    @property
    def write_error(self) -> str:
        """The last write's error, empty when it succeeded."""
        return self._w.error

    def close(self, timeout_s: float = 5.0) -> bool:
        """Write what is pending and stop the writer thread.

        Returns:
            True when everything was written.
        """
        ok = self.sync(timeout_s)
        with self._w.cond:
            self._w.stop = True
            self._w.cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        return ok

    # -- reading --------------------------------------------------------------------------------

    def get(self, job_id: int) -> Job:
        """The job ``job_id``.

        Raises:
            JobError: No such job.
        """
        with self._lock:
            job = self._jobs.get(job_id)
        if job is None:
            raise JobError(f"no job {job_id}")
        return job

    def jobs(self) -> list[Job]:
        """Every job, in id order."""
        with self._lock:
            return sorted(self._jobs.values(), key=lambda j: j.id)

    def next_runnable(self) -> Job | None:
        """The job the runner should run next: one found ``running`` (a restart), else the
        oldest ``queued``; None when there is none."""
        with self._lock:
            for status in ACTIVE:
                for job in sorted(self._jobs.values(), key=lambda j: j.id):
                    if job.status is status:
                        return job
        return None

    # -- changes --------------------------------------------------------------------------------

    def _put(self, job: Job) -> Job:
        if job.status in FINAL and job.session_state is not None:
            # A finished job keeps its summary (task, status, digs), not the planner's state
            # (tens of kB a job): nothing resumes it.
            job = dataclasses.replace(job, session_state=None)
        with self._lock:
            self._jobs[job.id] = job
            finished = [j for j in self._jobs.values() if j.status in FINAL]
            excess = max(0, len(finished) - self.keep_finished)
            for old in sorted(finished, key=lambda j: j.id)[:excess]:
                del self._jobs[old.id]
        self._dirty()
        return job

    def _change(self, job_id: int, **changes: Any) -> Job:
        with self._lock:
            job = self.get(job_id)
            return self._put(dataclasses.replace(job, updated_unix_s=time.time(), **changes))

    def submit(
        self,
        task: dict[str, Any],
        planner: str,
        max_digs: int | None = None,
        *,
        taught: str | None = None,
    ) -> Job:
        """Queue a new job (the task already validated; a taught job: its file, already
        verified, and the task :data:`TAUGHT_TASK`)."""
        with self._lock:
            now = time.time()
            job = Job(
                self._next_id,
                JobStatus.QUEUED,
                dict(TAUGHT_TASK) if taught is not None else dict(task),
                planner,
                now,
                now,
                max_digs=max_digs,
                taught=taught,
            )
            self._next_id += 1
            return self._put(job)

    def set_status(self, job_id: int, status: JobStatus | str, fault: str = "") -> Job:
        """Set a job's status (the runner's transitions: running, done, failed, ...); a status
        or its JSON spelling.

        Raises:
            JobError: Unknown job or status.
        """
        try:
            new = JobStatus.parse(status)
        except ValueError as exc:
            raise JobError(str(exc)) from None
        return self._change(job_id, status=new, fault=fault)

    def mark_running(self, job_id: int) -> Job:
        """The runner starts the job: ``running`` unless it was paused meanwhile (atomic).

        Returns:
            The job as it is now (``paused`` stays paused).
        """
        with self._lock:
            job = self.get(job_id)
            if job.status is JobStatus.PAUSED:
                return job
            return self._change(job_id, status=JobStatus.RUNNING, fault="")

    def record_dig(self, job_id: int, dig: dict[str, Any], session_state: dict[str, Any]) -> Job:
        """Append a dig's summary and the session state after it (cheap: no I/O here)."""
        with self._lock:
            job = self.get(job_id)
            return self._change(job_id, digs=(*job.digs, dict(dig)), session_state=session_state)

    def pause(self, job_id: int) -> Job:
        """Mark a queued or running job paused.

        Raises:
            JobError: The job is not queued or running.
        """
        with self._lock:
            job = self.get(job_id)
            if job.status not in (JobStatus.QUEUED, JobStatus.RUNNING):
                raise JobError(f"job {job_id} is {job.status}; only a queued or running job pauses")
            return self._change(job_id, status=JobStatus.PAUSED)

    def resume(self, job_id: int, running: bool) -> Job:
        """Resume a paused job (``running``: it is the one the runner holds) or retry a failed
        one from its last recorded dig.

        Raises:
            JobError: The job is neither paused nor failed.
        """
        with self._lock:
            job = self.get(job_id)
            if job.status not in (JobStatus.PAUSED, JobStatus.FAILED):
                raise JobError(
                    f"job {job_id} is {job.status}; only a paused job resumes (or a failed one "
                    "retries from its last dig)"
                )
            status = JobStatus.RUNNING if running else JobStatus.QUEUED
            return self._change(job_id, status=status, fault="")

    def cancel(self, job_id: int, reason: str = "cancelled by request") -> Job:
        """Cancel a job that is not running (the runner cancels the running one).

        Raises:
            JobError: The job is already done or cancelled.
        """
        with self._lock:
            job = self.get(job_id)
            if job.status in FINAL:
                raise JobError(f"job {job_id} is already {job.status}")
            return self._change(job_id, status=JobStatus.CANCELLED, fault=reason)
