"""The job store: job transitions, persistence, and atomic writes that survive a kill.

The crash test runs a writer in a subprocess that replaces the store as fast as it can and
kills it with SIGKILL at seeded random moments: the file must always parse and be one whole
version (its payload checks itself). A temporary file left by a crash must be ignored.
"""

from __future__ import annotations

import json
import os
import random
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from rt_runtime.errors import ConfigurationError
from rt_runtime.service import jobstore
from rt_runtime.service.jobstore import (
    STORE_FORMAT,
    JobError,
    JobStore,
    atomic_write_json,
    read_store,
)

TASK = {
    "name": "A",
    "length_m": 0.6,
    "depth_m": 0.15,
    "beta1_deg": 60.0,
    "beta2_deg": 60.0,
    "start_x_m": 1.05,
}
DIG = {
    "index": 0,
    "dig_type": "downward",
    "T_s": 4.0,
    "plan_us": 3000.0,
    "planned_volume_m3": 0.004,
    "measured_volume_m3": 0.0038,
}


def _on_disk(store: JobStore) -> dict[str, Any]:
    assert store.sync()
    doc: dict[str, Any] = json.loads(store.path.read_text())
    return doc


def test_atomic_write_fsyncs_file_then_renames_then_fsyncs_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        kind = "dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file"
        calls.append(f"fsync {kind}")
        real_fsync(fd)

    def replace(a: Any, b: Any) -> None:
        calls.append("replace")
        real_replace(a, b)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    path = tmp_path / "jobs.json"
    atomic_write_json(path, {"a": 1})
    assert calls == ["fsync file", "replace", "fsync dir"]
    assert json.loads(path.read_text()) == {"a": 1}
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left


def test_failed_write_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "jobs.json"
    atomic_write_json(path, {"v": 1})
    with pytest.raises(ValueError):
        atomic_write_json(path, {"v": float("nan")})  # not JSON: refused before any write
    assert json.loads(path.read_text()) == {"v": 1}
    assert list(tmp_path.iterdir()) == [path]


_WRITER = """
import hashlib, sys
from pathlib import Path
from rt_runtime.service.jobstore import STORE_FORMAT, atomic_write_json
path = Path(sys.argv[1])
task = {"name": "A", "length_m": 0.6, "depth_m": 0.15, "beta1_deg": 60.0, "beta2_deg": 60.0,
        "start_x_m": 1.05}
i = 0
print("started", flush=True)
while True:
    i += 1
    pad = "x" * (i * 7919 % 50000)
    job = {"id": i, "status": "running", "planner": "pinn", "task": task, "submitted_unix_s": 0.0,
           "updated_unix_s": 0.0, "fault": pad, "digs": [],
           "session_state": {"sha": hashlib.sha256(pad.encode()).hexdigest()}}
    atomic_write_json(path, {"format": STORE_FORMAT, "next_id": i + 1, "jobs": [job]})
"""


def test_killed_writer_leaves_a_whole_file(tmp_path: Path) -> None:
    import hashlib

    path = tmp_path / "jobs.json"
    rng = random.Random(7)
    seen = []
    for _ in range(6):
        proc = subprocess.Popen(
            [sys.executable, "-c", _WRITER, str(path)], stdout=subprocess.PIPE, text=True
        )
        assert proc.stdout is not None and proc.stdout.readline().strip() == "started"
        time.sleep(rng.uniform(0.02, 0.25))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        next_id, jobs = read_store(path)  # parses: never half-written
        (job,) = jobs
        assert job.session_state is not None
        assert hashlib.sha256(job.fault.encode()).hexdigest() == job.session_state["sha"]
        assert next_id == job.id + 1
        seen.append(job.id)
    assert all(n >= 1 for n in seen), seen
    # Whatever temporary file a kill left is ignored, then removed by the next load.
    store = JobStore(tmp_path)
    assert [j.id for j in store.jobs()] == [seen[-1]]
    assert not list(tmp_path.glob(".jobs.json.*.tmp"))
    print(f"\nversions found after each SIGKILL: {seen}")


def test_corrupt_temp_file_is_ignored_and_removed(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    store.start()
    store.submit(TASK, "pinn")
    store.close()
    stale = tmp_path / ".jobs.json.4242.1.tmp"
    stale.write_text('{"format": "excavator-rtd-jobs/1", "jobs": [{"id": ')  # a crash mid-write
    again = JobStore(tmp_path)
    assert [j.id for j in again.jobs()] == [1]
    assert not stale.exists()


def test_corrupt_store_is_refused_with_its_path(tmp_path: Path) -> None:
    (tmp_path / "jobs.json").write_text("{not json")
    with pytest.raises(ConfigurationError, match=r"jobs\.json is not valid JSON.*move it aside"):
        JobStore(tmp_path)
    (tmp_path / "jobs.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(ConfigurationError, match="format must be"):
        read_store(tmp_path / "jobs.json")
    bad_job = {"format": STORE_FORMAT, "next_id": 2, "jobs": [{"id": 1, "status": "flying"}]}
    (tmp_path / "jobs.json").write_text(json.dumps(bad_job))
    with pytest.raises(ConfigurationError, match="status 'flying'"):
        read_store(tmp_path / "jobs.json")


def test_state_dir_is_created_owner_only(tmp_path: Path) -> None:
    store = JobStore(tmp_path / "a" / "state")
    assert stat.S_IMODE((tmp_path / "a" / "state").stat().st_mode) == 0o700
    store.start()
    doc = _on_disk(store)
    assert doc == {"format": STORE_FORMAT, "next_id": 1, "jobs": []}
    store.close()


def test_transitions_and_persistence(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    store.start()
    a = store.submit(TASK, "pinn")
    b = store.submit({**TASK, "name": "B"}, "pso")
    assert (a.id, b.id) == (1, 2) and a.status.label == "queued"
    assert store.next_runnable() == a

    store.set_status(1, "running")
    store.record_dig(1, DIG, {"digs_done": 1, "material_wkt": "POLYGON EMPTY"})
    store.record_dig(1, {**DIG, "index": 1}, {"digs_done": 2})
    with pytest.raises(JobError, match="only a paused job resumes"):
        store.resume(1, running=True)
    store.pause(2)
    with pytest.raises(JobError, match="job 2 is paused; only a queued or running job pauses"):
        store.pause(2)
    store.cancel(2, "no longer needed")
    with pytest.raises(JobError, match="already cancelled"):
        store.cancel(2)
    with pytest.raises(JobError, match="no job 9"):
        store.get(9)

    doc = _on_disk(store)
    assert doc["next_id"] == 3
    job1 = doc["jobs"][0]
    assert job1["status"] == "running" and [d["index"] for d in job1["digs"]] == [0, 1]
    assert job1["session_state"] == {"digs_done": 2}
    assert doc["jobs"][1]["status"] == "cancelled"
    assert doc["jobs"][1]["fault"] == "no longer needed"
    store.close()

    # A restart finds the running job first and continues the ids.
    again = JobStore(tmp_path)
    job = again.next_runnable()
    assert job is not None and job.id == 1 and job.session_state == {"digs_done": 2}
    assert again.submit(TASK, "pinn").id == 3
    assert again.get(1).to_json(with_state=False).keys() >= {"id", "status", "digs", "task"}
    assert "session_state" not in again.get(1).to_json(with_state=False)


def test_runner_priority_and_retry_of_a_failed_job(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    for _ in range(3):
        store.submit(TASK, "pinn")
    store.set_status(3, "running")
    job = store.next_runnable()
    assert job is not None and job.id == 3  # a job found running (a restart) goes first
    store.set_status(3, "failed", "drive fault")
    job = store.next_runnable()
    assert job is not None and job.id == 1
    retried = store.resume(3, running=False)
    assert retried.status.label == "queued" and retried.fault == ""
    store.pause(1)
    store.pause(2)
    job = store.next_runnable()
    assert job is not None and job.id == 3


def test_mark_running_keeps_a_pause_and_max_digs_persists(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    store.start()
    store.submit(TASK, "pinn", max_digs=3)
    assert store.mark_running(1).status.label == "running"
    store.pause(1)
    assert store.mark_running(1).status.label == "paused"  # paused while it was being prepared
    store.close()
    job = JobStore(tmp_path).get(1)
    assert job.max_digs == 3 and job.status.label == "paused"
    doc = json.loads((tmp_path / "jobs.json").read_text())
    doc["jobs"][0]["max_digs"] = 0
    (tmp_path / "jobs.json").write_text(json.dumps(doc))
    with pytest.raises(ConfigurationError, match="max_digs must be an integer >= 1"):
        JobStore(tmp_path)


def test_old_finished_jobs_are_dropped(tmp_path: Path) -> None:
    store = JobStore(tmp_path, keep_finished=2)
    for _ in range(4):
        job = store.submit(TASK, "pinn")
        store.set_status(job.id, "done")
    store.submit(TASK, "pinn")
    assert [j.id for j in store.jobs()] == [3, 4, 5]


def test_finished_jobs_keep_their_summary_not_the_planner_state(tmp_path: Path) -> None:
    store = JobStore(tmp_path)
    store.start()
    state = {"material_wkt": "x" * 50_000}
    jobs = [store.submit(TASK, "pinn") for _ in range(3)]
    dig = {"index": 0, "dig_type": "downward", "T_s": 5.0, "plan_us": 3000.0,
           "planned_volume_m3": 0.004, "measured_volume_m3": 0.0039}  # fmt: skip
    for job in jobs:
        store.record_dig(job.id, dig, state)
    store.set_status(jobs[0].id, "done")
    store.cancel(jobs[1].id)
    store.set_status(jobs[2].id, "failed", "bus lost")
    assert store.close()
    again = JobStore(tmp_path)
    done, cancelled, failed = (again.get(j.id) for j in jobs)
    assert done.session_state is None and done.digs == (dig,)
    assert cancelled.session_state is None and cancelled.digs == (dig,)
    assert failed.session_state == state  # a failed job retries from its last dig
    assert (tmp_path / "jobs.json").stat().st_size < 60_000


def test_changes_are_written_off_the_callers_thread(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import threading

    writers: list[str] = []
    real = jobstore.atomic_write_json

    def spy(path: Path, obj: Any) -> None:
        writers.append(threading.current_thread().name)
        real(path, obj)

    monkeypatch.setattr(jobstore, "atomic_write_json", spy)
    store = JobStore(tmp_path)
    store.start()
    store.submit(TASK, "pinn")
    assert store.sync()
    store.close()
    assert writers and set(writers) == {"jobstore"}
