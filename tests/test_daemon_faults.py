"""Faults latch and the daemon lives; a crashed daemon resumes: ``excavator-rtd`` in its own
process against the real-time HIL in another, over 127.0.0.1.

Each run starts the HIL process and the daemon as ``test_daemon_e2e.py`` does (its ``Daemon``
helper: a fake ``NOTIFY_SOCKET``, python-can's ``remote`` interface to the HIL's port), submits
Yao's task A with a small ``max_digs`` and acts in the middle of a dig:

* the bus is lost (the HIL process killed), frozen (the HIL stopped with SIGSTOP for a few
  seconds, then SIGCONT), or the job's planner process is killed: a fault is latched naming
  what happened, the daemon stays up and answers, keeps sending WATCHDOG=1, refuses ``resume``
  with the code ``faulted`` and queues a submitted job; ``reset-fault`` (after a new HIL on the
  same port where the old one died) re-boots bus and drives, the failed job is queued again,
  resumes at its next undone dig and finishes;
* the daemon is killed (SIGKILL, SIGABRT as systemd's watchdog sends it): the restarted daemon
  boots the drives from whatever state they are in and resumes the job at the interrupted dig,
  every time. ``EXCAVATOR_RT_RESTART_RUNS`` sets how many kills one run makes (default 2, one
  of each signal; the issue's goal is measured with 10).

The rig is the shipped ``scale_model`` with the drives' SYNC watchdog, heartbeat timeout and
following-error window widened as in ``test_daemon_e2e.py`` (the subject is the daemon's
fault handling, not this shared machine's scheduling), and the same loop and executor
patience. Bounded waits everywhere; the HIL processes stop by themselves after
:data:`MAX_WALL_S`. Timings are printed, never asserted. Skipped, with the reason, only if the
HIL cannot start.
"""

from __future__ import annotations

import contextlib
import gc
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from test_daemon_e2e import Daemon
from test_daemon_e2e import _until as until

from hil_sim.harness.realtime import HIL_RT_PRIORITY, RealtimeHilProcess
from rt_runtime.canbus import (
    CanMaster,
    CycleStatus,
    DriveState,
    EmcyCode,
    WriteStatus,
    emcy_meaning,
    emcy_message,
)
from rt_runtime.control.clock import MonotonicClock
from rt_runtime.control.hardware import DriveInterface
from rt_runtime.errors import CommunicationError
from rt_runtime.planning.trench import TrenchPlanner
from rt_runtime.rig import Rig, load_rig
from rt_runtime.rig.loader import PROFILE_DIR
from rt_runtime.service.config import DaemonConfig, load_config
from rt_runtime.service.control import request
from rt_runtime.service.jobstore import JobStatus, JobStore, read_store
from rt_runtime.service.runner import RigRunner

RIG = "scale_model"
PERIOD_S = 0.002
#: A HIL process stops by itself after this long, whatever happens to the test.
MAX_WALL_S = 1800.0
#: Kills of the restart test (SIGKILL and SIGABRT alternating).
RESTART_RUNS = int(os.environ.get("EXCAVATOR_RT_RESTART_RUNS", "2"))
#: How long after the job reports a dig the restart test kills the daemon (s; task A's digs
#: last 5-9 s).
INTO_DIG_S = 2.0
#: How long after the job reports its first dig (8.9 s long) the fault tests act (s): early,
#: the bucket entering tip first, where the resumed job's lift out is hardest to plan.
INTO_FIRST_DIG_S = 1.0
#: Longest wait for a dig to begin, for a job to end (s): bounds, not expectations.
DIG_WAIT_S = 300.0
JOB_WAIT_S = 300.0


# -- without the HIL process: the bus's exceptions, the messages, the runner on the lockstep HIL


class BreakableBus(can.BusABC):
    """A bus that raises what python-can-remote's client raises once its peer is gone
    (``ConnectionResetError``, not a ``can.CanError``) while :attr:`broken` is set.

    ``recv`` goes to the inner bus in one call: python-can's own ``recv`` would repeat an empty
    receive until the *wall* clock passed the timeout, and each empty receive of the lockstep
    bus advances its simulated clock by the whole timeout."""

    def __init__(self, inner: can.BusABC) -> None:
        self.inner = inner
        self.broken = False
        super().__init__(channel="breakable")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.broken:
            raise ConnectionResetError(104, "Connection reset by peer")
        self.inner.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg, _filtered = self._recv_internal(timeout)
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.broken:
            raise ConnectionResetError(104, "Connection reset by peer")
        return self.inner.recv(timeout), False

    def shutdown(self) -> None:
        super().shutdown()


def test_any_exception_out_of_the_bus_is_a_bus_error_never_a_raise() -> None:
    rig = load_rig(RIG)
    bus = BreakableBus(can.Bus(interface="virtual", channel=f"faults-{os.getpid()}"))
    master = CanMaster(bus, rig)
    bus.broken = True
    assert master.write_setpoints([0, 0, 0], [0, 0, 0]) is WriteStatus.BUS_ERROR
    fb = master.read_feedback(0.0, 0.0)
    assert fb.status is CycleStatus.BUS_ERROR
    assert master.heartbeat(10.0) is WriteStatus.BUS_ERROR
    assert master.quick_stop() is WriteStatus.BUS_ERROR
    assert isinstance(master.cycle.bus_exception, ConnectionResetError)
    with pytest.raises(CommunicationError, match=r"boot: .*ConnectionResetError"):
        master.boot(time.monotonic, 0.1)
    bus.inner.shutdown()


def test_fault_messages_name_axis_node_code_and_meaning() -> None:
    assert emcy_meaning(EmcyCode.RPDO_TIMEOUT).startswith("SYNC/RPDO watchdog")
    assert "following error" in emcy_meaning(0x8611)
    assert emcy_meaning(0x8F42) == "unknown code of class: monitoring or communication error"
    assert emcy_meaning(0xFF17) == "manufacturer-specific error"
    rig = load_rig(RIG)
    bus = can.Bus(interface="virtual", channel=f"describe-{os.getpid()}")
    try:
        master = CanMaster(bus, rig)
        drives = DriveInterface(master, MonotonicClock(), 0.0)
        fb = master.feedback
        fb.state[:] = [int(DriveState.FAULT), int(DriveState.OPERATION_ENABLED), -1]
        fb.stale[:] = False
        fb.error_code[1] = 0x8611
        master.router.dispatch(emcy_message(1, EmcyCode.RPDO_TIMEOUT, 0x11), 0.0)
        text = drives.describe(CycleStatus.DRIVE_FAULT)
    finally:
        bus.shutdown()
    assert text.startswith("cycle status DRIVE_FAULT; boom (node 1): FAULT, EMCY RPDO_TIMEOUT ")
    assert "(0x8250): SYNC/RPDO watchdog" in text
    assert "stick (node 2): OPERATION_ENABLED, error code 0x8611: following error" in text
    assert "bucket (node 3): undecodable" in text


def _lockstep_bench(tmp_path: Path) -> tuple[Rig, DaemonConfig, Any]:
    """The rig, a daemon configuration without real-time settings (state under ``tmp_path``)
    and a lockstep HIL at the home pose, for a runner in this process."""
    from hil_sim.harness.lockstep import LockstepHil

    rig = load_rig(RIG)
    cfg_path = tmp_path / "d.toml"
    cfg_path.write_text(
        '[bus]\ninterface = "virtual"\nchannel = "unused"\nboot_timeout_s = 1.0\n'
        '[rig]\nprofile = "scale_model"\n[loop]\nsched_fifo_priority = 0\n'
        'lock_memory = false\n[paths]\nstate_dir = "state"\nsocket = "run/c.sock"\n'
    )
    return rig, load_config(cfg_path), LockstepHil(rig, TrenchPlanner(rig).home_pose_rad, vcu=False)


def test_the_runner_latches_a_bus_error_lives_and_resets_on_a_reopened_bus(
    tmp_path: Path,
) -> None:
    """The runner on the lockstep HIL: the bus starts raising while it holds; the fault
    latches (naming the exception and the nodes), the loop ends, the thread waits and feeds
    the watchdog; a reset reopens the bus, boots the drives again and holds."""
    rig, config, hil = _lockstep_bench(tmp_path)
    opened: list[BreakableBus] = []

    def reopen() -> can.BusABC:
        bus = BreakableBus(hil.master_bus)
        opened.append(bus)
        return bus

    first = BreakableBus(hil.master_bus)
    store = JobStore(config.paths.state_dir)
    runner = RigRunner(config, rig, TrenchPlanner(rig), first, store, hil.clock, reopen)

    def wait(pred: Callable[[], bool], what: str) -> None:
        end = time.monotonic() + 60.0
        while not pred():
            assert time.monotonic() < end, f"{what}: {runner.state()}"
            time.sleep(0.01)

    try:
        runner.start()
        wait(lambda: runner.health()[0], "holding")
        first.broken = True
        wait(lambda: runner.state().endswith("waiting for reset-fault"), "the latch")
        fault = runner.fault()
        assert fault.startswith("while holding: cycle status BUS_ERROR (ConnectionResetError")
        assert "boom (node 1)" in fault and "bucket (node 3)" in fault
        assert runner.alive() and runner.watchdog() == (True, "")
        assert not runner.health()[0]
        number = runner.reset_fault()
        wait(lambda: runner.resets_done >= number, "the reset")
        assert runner.fault() == "" and len(opened) == 1 and runner.bus is opened[0]
        wait(lambda: runner.health()[0], "holding again")
        assert runner.state().startswith("idle, holding position")
    finally:
        assert runner.shutdown(10.0)
        hil.close()
        gc.unfreeze()


def test_a_job_keeps_the_words_its_fault_latched_with(tmp_path: Path) -> None:
    """A job's fault latches when its stop begins, with the drives' report of then (a stale
    axis "its last report"); by the time the stop ends the drives may answer again. The job
    keeps the latched words: its stored fault is the latch's, not a second report (the
    daemon's end-to-end test found the two apart after a host stall)."""
    from types import SimpleNamespace

    from rt_runtime.canbus import CycleStatus
    from rt_runtime.control.job import ExecStatus

    rig, config, hil = _lockstep_bench(tmp_path)
    store = JobStore(config.paths.state_dir)
    runner = RigRunner(config, rig, TrenchPlanner(rig), hil.master_bus, store, hil.clock)
    try:
        job = store.submit({"name": "A"}, "pinn")
        cause = "stale feedback: no TPDO1 from the boom drive for 10 cycles"
        then = "cycle status STALE; boom (node 1): OPERATION_ENABLED (its last report)"
        now = SimpleNamespace(
            describe=lambda status: "cycle status OK; boom (node 1): OPERATION_ENABLED",
            feedback=SimpleNamespace(status=CycleStatus.OK),
        )
        runner._parts = SimpleNamespace(drives=now)  # type: ignore[assignment]
        latched = f"job {job.id}: fault: {cause}; drives: {then}"
        runner._latch(latched, job.id)
        running = SimpleNamespace(job=job, planner=None)
        runner._record_outcome(running, ExecStatus.FAULT, cause)  # type: ignore[arg-type]
        stored = store.get(job.id)
        assert stored.status is JobStatus.FAILED
        assert stored.fault == f"fault: {cause}; drives: {then}"
        assert runner.fault() == latched
        # A job that failed with no fault latched for it latches its own words.
        other = store.submit({"name": "B"}, "pinn")
        runner._fault, runner._fault_job = "", None
        runner._record_outcome(
            SimpleNamespace(job=other, planner=None), ExecStatus.FAULT, cause  # type: ignore[arg-type]
        )
        words = f"fault: {cause}; drives: cycle status OK; boom (node 1): OPERATION_ENABLED"
        assert store.get(other.id).fault == words
        assert runner.fault() == f"job {other.id}: {words}"
    finally:
        store.close()
        hil.close()


def test_a_shutdown_right_after_a_job_keeps_its_report(tmp_path: Path) -> None:
    """The runner on the lockstep HIL digs one dig and is shut down the moment the job is done:
    the job's report (its telemetry file) is written before the shutdown returns, not cut
    short with the process."""
    rig, config, hil = _lockstep_bench(tmp_path)
    store = JobStore(config.paths.state_dir)
    runner = RigRunner(config, rig, TrenchPlanner(rig), hil.master_bus, store, hil.clock)
    task = {"name": "A", "length_m": 0.6, "depth_m": 0.15, "beta1_deg": 60.0,
            "beta2_deg": 60.0, "start_x_m": 1.05}  # fmt: skip
    try:
        runner.start()
        job = store.submit(task, "pinn", max_digs=1)
        store.changed.set()
        end = time.monotonic() + JOB_WAIT_S
        while store.get(job.id).status is not JobStatus.DONE:
            assert time.monotonic() < end, runner.state()
            time.sleep(0.005)
    finally:
        assert runner.shutdown(30.0)
        hil.close()
        gc.unfreeze()
    assert (config.paths.state_dir / "telemetry" / f"job-{job.id}.npz").is_file()
    # The shutdown ends the runner's helper threads too: nothing holds the planner after it.
    prep = runner._prep
    threads = (prep.recorder._thread, prep.worker._thread, prep.after._thread)
    assert not any(t.is_alive() for t in threads), [t.name for t in threads if t.is_alive()]


@pytest.fixture
def rig_file(tmp_path: Path) -> Path:
    """``scale_model`` with the drives' watchdogs widened for a shared machine."""
    text = (PROFILE_DIR / f"{RIG}.toml").read_text()
    for old, new in (
        ("heartbeat_timeout_ms = 150", "heartbeat_timeout_ms = 3000"),
        ("sync_timeout_ms = 20", "sync_timeout_ms = 500"),
        ("following_error_window_mm = 5.0", "following_error_window_mm = 20.0"),
    ):
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "rig" / f"{RIG}.toml"
    path.parent.mkdir()
    path.write_text(text)
    return path


def start_hil(rig_file: Path, port: int = 0) -> RealtimeHilProcess:
    """The real-time HIL process at the home pose on ``port`` of 127.0.0.1 (0: any free one),
    as :meth:`RealtimeHilProcess.start` starts it; its own bus end is closed (the daemon is the
    master)."""
    q0 = TrenchPlanner(load_rig(rig_file)).home_pose_rad
    tmp = tempfile.TemporaryDirectory(prefix="excavator-hil-")
    out = Path(tmp.name) / "truth.npz"
    cmd = [
        sys.executable, "-m", "hil_sim.harness.realtime",
        "--rig", str(rig_file),
        "--q0", *(repr(float(v)) for v in q0),
        "--period", repr(PERIOD_S),
        "--max-wall-s", repr(MAX_WALL_S),
        "--out", str(out),
        "--port", str(port),
        "--rt-priority", str(HIL_RT_PRIORITY),
    ]  # fmt: skip
    proc = subprocess.Popen(
        cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1
    )
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 30.0)
    line = proc.stdout.readline() if ready else ""
    if not line.startswith("READY "):
        proc.kill()
        proc.wait()
        tmp.cleanup()
        raise CommunicationError(f"the real-time HIL did not start (said {line!r})")
    hil = RealtimeHilProcess(proc, int(line.split()[1]), out, tmp, PERIOD_S)
    hil.master_bus.shutdown()
    return hil


class Bench:
    """One HIL process (replaced when it dies), the daemon's configuration and its socket."""

    def __init__(self, rig_file: Path, tmp: Path) -> None:
        self.rig_file = rig_file
        self.tmp = tmp
        try:
            self.hil = start_hil(rig_file)
        except (CommunicationError, OSError) as exc:
            pytest.skip(f"the real-time HIL process cannot start here: {exc}")
        self.hils = [self.hil]
        self.port = self.hil.port
        self.state = tmp / "state"
        self.sock = tmp / "run" / "c.sock"
        self.store = self.state / "jobs.json"
        self.config = tmp / "rtd.toml"
        self.config.write_text(
            f'[bus]\ninterface = "remote"\nchannel = "ws://127.0.0.1:{self.port}/"\n'
            f'boot_timeout_s = 2.0\n[rig]\nprofile = "{rig_file}"\n'
            f"[loop]\nperiod_s = {PERIOD_S}\nsched_fifo_priority = 50\nlock_memory = false\n"
            "max_consecutive_overruns = 20\n[executor]\nstale_cycles = 250\n"
            f'[paths]\nstate_dir = "{self.state}"\nsocket = "{self.sock}"\n'
            f'trace = "{tmp / "trace" / "can.blf"}"\n'
        )
        self.daemons: list[Daemon] = []

    def daemon(self) -> Daemon:
        """A new daemon process, READY."""
        d = Daemon(self.config, self.tmp, len(self.daemons) + 1)
        self.daemons.append(d)
        d.wait_for("READY=1", 120.0)
        return d

    def new_hil(self) -> None:
        """A new HIL process on the old one's port (the old one is gone)."""
        self.hil = start_hil(self.rig_file, self.port)
        self.hils.append(self.hil)

    def ask(self, **req: Any) -> dict[str, Any]:
        return request(self.sock, req)

    def job(self, job_id: int = 1) -> dict[str, Any]:
        _next, jobs = read_store(self.store)
        return next(j for j in jobs if j.id == job_id).to_json(with_state=False)

    def close(self) -> None:
        for d in self.daemons:
            d.close()
        for hil in self.hils:
            if hil.proc.poll() is None:
                with contextlib.suppress(OSError):
                    os.kill(hil.proc.pid, signal.SIGCONT)
            hil.close()


@pytest.fixture
def bench(rig_file: Path, tmp_path: Path) -> Iterator[Bench]:
    r = Bench(rig_file, tmp_path)
    try:
        yield r
    finally:
        r.close()


def in_dig(
    bench: Bench, daemon: Daemon, index: int | None = None, into_s: float = INTO_DIG_S
) -> int:
    """Wait until the job digs (dig ``index``, or any), then ``into_s`` more; the dig's
    index."""
    found: list[int] = []

    def digging() -> bool:
        st = bench.ask(cmd="status")
        job = st["job"]
        if job is not None and job["status"] == "failed":
            pytest.fail(f"job failed: {job['fault']}\n{daemon.log()}")
        progress = st.get("progress") or {}
        dig = progress.get("dig", -1)
        if progress.get("phase") == "dig" and (index is None or dig == index):
            found.append(int(dig))
            return True
        return False

    until(digging, DIG_WAIT_S, f"dig {index}", daemon)
    daemon.idle(into_s)
    return found[0]


def assert_latched(
    bench: Bench, daemon: Daemon, words: str, t_event: float | None = None
) -> str:
    """The fault is latched and says ``words``; the daemon answers, refuses motion with
    ``faulted``, queues a submitted job, and keeps its watchdog fed; the fault text. Prints
    the time from the event (``time.monotonic()`` at ``t_event``) until the test saw the
    daemon waiting for the reset (the arm stopped, the drives off)."""
    until(
        lambda: "waiting for reset-fault" in bench.ask(cmd="status")["daemon"]["state"],
        60.0,
        "the fault latched",
        daemon,
    )
    st = bench.ask(cmd="status")
    fault = st["daemon"]["fault"]
    if t_event is not None:
        print(f"\n  waiting for reset-fault {time.monotonic() - t_event:.2f} s after the event: "
              f"{fault[:160]}")  # fmt: skip
    assert words in fault, fault
    assert any(m.startswith("STATUS=fault: ") for m in daemon.messages), daemon.messages
    assert not st["daemon"]["healthy"]
    # The runner fails the job in the store's memory before it waits for the reset; the file
    # this reads is written after that by the store's writer thread (a busy disk's fsync can
    # lag the daemon's state by a moment).
    until(lambda: bench.job()["status"] == "failed", 10.0, "the store file says failed", daemon)
    refused = bench.ask(cmd="resume", id=1)
    assert not refused["ok"] and refused["code"] == "faulted", refused
    assert "reset-fault" in refused["error"]
    queued = bench.ask(cmd="submit", task="A", max_digs=1)
    assert queued["ok"] and queued["fault"] == fault, queued
    assert bench.ask(cmd="cancel", id=queued["job"]["id"])["ok"]
    # WATCHDOG_USEC is 1 s: a ping every 0.5 s (later while a reply waits for the store's
    # fsync on a busy disk).
    daemon.messages.clear()
    until(lambda: "WATCHDOG=1" in daemon.messages, 10.0, "WATCHDOG=1 while faulted", daemon)
    assert daemon.proc.poll() is None
    return str(fault)


def reset_and_finish(bench: Bench, daemon: Daemon, digs: int) -> None:
    """``excavator-rt job reset-fault`` (the client, as an operator runs it): exit 0; the job
    queued again, resumed, done with ``digs`` digs."""
    t0 = time.monotonic()
    out = subprocess.run(
        [sys.executable, "-m", "rt_runtime.cli", "job", "reset-fault", "--socket",
         str(bench.sock), "--wait-s", "60"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr + daemon.log()
    assert "fault reset" in out.stdout, out.stdout
    print(f"  reset-fault took {time.monotonic() - t0:.2f} s (the client's wall time)")
    st = bench.ask(cmd="status")
    assert st["daemon"]["fault"] == "", st
    until(lambda: bench.job()["status"] == "done", JOB_WAIT_S, "job 1 done", daemon)
    job = bench.job()
    assert [d["index"] for d in job["digs"]] == list(range(digs)), job["digs"]
    assert "fault reset (was: " in daemon.log()
    assert "queued again at its next undone dig" in daemon.log()
    assert bench.ask(cmd="status")["daemon"]["healthy"]
    assert daemon.stop() == 0, daemon.log()


def test_bus_loss_latches_a_fault_and_reset_fault_resumes_the_job(bench: Bench) -> None:
    daemon = bench.daemon()
    assert bench.ask(cmd="submit", task="A", max_digs=1)["ok"]
    in_dig(bench, daemon, 0, INTO_FIRST_DIG_S)
    t_event = time.monotonic()
    bench.hil.proc.kill()  # the bus is gone: its connection resets under the daemon
    bench.hil.proc.wait()
    fault = assert_latched(bench, daemon, "BUS_ERROR", t_event)
    assert "node 1" in fault, fault
    assert "Traceback" not in daemon.log()
    refused = bench.ask(cmd="reset-fault")  # the old HIL is gone: the reset fails, latched
    assert refused["ok"], refused
    until(
        lambda: bench.ask(cmd="status")["daemon"]["resets_done"] >= refused["reset"],
        60.0,
        "the failed reset",
        daemon,
    )
    st = bench.ask(cmd="status")["daemon"]
    assert "the latest reset failed" in st["fault"], st
    assert daemon.proc.poll() is None
    bench.new_hil()
    reset_and_finish(bench, daemon, 1)


def test_frozen_bus_latches_a_fault_and_reset_fault_resumes_the_job(bench: Bench) -> None:
    daemon = bench.daemon()
    assert bench.ask(cmd="submit", task="A", max_digs=1)["ok"]
    in_dig(bench, daemon, 0, INTO_FIRST_DIG_S)
    t_event = time.monotonic()
    os.kill(bench.hil.proc.pid, signal.SIGSTOP)
    try:
        until(
            lambda: bench.ask(cmd="status")["daemon"]["fault"] != "",
            30.0,
            "a fault while frozen",
            daemon,
        )
        print(f"\n  fault latched {time.monotonic() - t_event:.2f} s after SIGSTOP")
        daemon.idle(2.0)  # frozen a few seconds in all
    finally:
        os.kill(bench.hil.proc.pid, signal.SIGCONT)
    assert_latched(bench, daemon, "stale feedback")
    reset_and_finish(bench, daemon, 1)


def _planner_pid(daemon_pid: int) -> int:
    """The daemon's planner process (multiprocessing's spawn child, not its resource tracker)."""
    for task in Path(f"/proc/{daemon_pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            cmdline = Path(f"/proc/{child}/cmdline").read_bytes()
            if b"spawn_main" in cmdline:
                return int(child)
    raise AssertionError("no planner process")


def test_killed_planner_latches_a_fault_and_reset_fault_resumes_the_job(bench: Bench) -> None:
    daemon = bench.daemon()
    assert bench.ask(cmd="submit", task="A", max_digs=1)["ok"]
    in_dig(bench, daemon, 0, INTO_FIRST_DIG_S)
    t_event = time.monotonic()
    os.kill(_planner_pid(daemon.proc.pid), signal.SIGKILL)
    fault = assert_latched(
        bench, daemon, "the planner process ended (killed by SIGKILL)", t_event
    )
    assert fault.startswith("job 1: "), fault
    reset_and_finish(bench, daemon, 1)


def _resumed(bench: Bench, daemon: Daemon, job_id: int, dig: int) -> str:
    """``resumed`` once the restarted daemon has redone dig ``dig`` of job ``job_id``, else
    what went wrong."""
    end = time.monotonic() + JOB_WAIT_S
    while time.monotonic() < end:
        if daemon.proc.poll() is not None:
            return f"daemon exited ({daemon.proc.returncode})"
        job = bench.job(job_id)
        if job["status"] == "failed":
            return f"job failed: {job['fault']}"
        if len(job["digs"]) > dig:
            return "resumed"
        daemon.drain(0.2)
    return f"dig {dig} not redone within {JOB_WAIT_S} s"


def _recover(bench: Bench, daemon: Daemon, job_id: int) -> None:
    """After a restart that did not resume: the fault reset or the job retried, so the next
    kill can be measured."""
    if bench.ask(cmd="status")["daemon"]["fault"]:
        number = bench.ask(cmd="reset-fault")["reset"]
        until(
            lambda: bench.ask(cmd="status")["daemon"]["resets_done"] >= number,
            60.0,
            "the reset",
            daemon,
        )
    if bench.job(job_id)["status"] == "failed":
        assert bench.ask(cmd="resume", id=job_id)["ok"]


def test_restart_after_sigkill_or_sigabrt_mid_dig_resumes_the_job(bench: Bench) -> None:
    """Each kill lands in the running job's next undone dig; the restarted daemon must redo
    that dig. Task A has five digs: a job that ends is followed by a new one; the last job's
    ``max_digs`` makes it end with the last restart's dig."""
    daemon = bench.daemon()
    outcomes: list[str] = []
    job_id, job_digs = 0, 0
    t0 = time.monotonic()
    for k in range(RESTART_RUNS):
        if job_id == 0 or len(bench.job(job_id)["digs"]) >= job_digs:
            if job_id:
                until(lambda j=job_id: bench.job(j)["status"] == "done", JOB_WAIT_S, "done",
                      daemon)  # fmt: skip
            job_digs = min(RESTART_RUNS - k, 5)  # task A has five digs
            reply = bench.ask(cmd="submit", task="A", max_digs=job_digs)
            assert reply["ok"], reply
            job_id = reply["job"]["id"]
        dig = in_dig(bench, daemon, len(bench.job(job_id)["digs"]))
        sig = signal.SIGKILL if k % 2 == 0 else signal.SIGABRT
        daemon.proc.send_signal(sig)
        code = daemon.proc.wait(30)
        if sig == signal.SIGKILL:
            assert code == -sig, code
        else:
            # faulthandler reports it and dumps the threads' stacks; walking a thread that is
            # inside C code can end the dump in SIGSEGV (best effort), which also kills.
            assert code in (-signal.SIGABRT, -signal.SIGSEGV), code
            assert "Fatal Python error: Aborted" in daemon.log(), daemon.log()
        daemon.close()
        assert bench.job(job_id)["status"] == "running"  # as the kill left it
        daemon = bench.daemon()
        outcome = _resumed(bench, daemon, job_id, dig)
        outcomes.append(f"{sig.name} in job {job_id} dig {dig}: {outcome}")
        if outcome != "resumed":
            _recover(bench, daemon, job_id)
        else:
            running = f"job {job_id}: running (task A, {dig} dig(s) done)"
            assert running in daemon.log(), daemon.log()
    resumed = sum(o.endswith(": resumed") for o in outcomes)
    print(f"\nrestart after a kill mid-dig: {resumed} of {RESTART_RUNS} resumed "
          f"({time.monotonic() - t0:.0f} s)")  # fmt: skip
    assert resumed == RESTART_RUNS, outcomes
    until(lambda: bench.job(job_id)["status"] == "done", JOB_WAIT_S, "the job done", daemon)
    _next, jobs = read_store(bench.store)
    assert all(j.status.label == "done" for j in jobs), [j.to_json() for j in jobs]
    assert daemon.stop() == 0, daemon.log()


@pytest.mark.parametrize("found", ["OPERATION_ENABLED", "FAULT_REACTION_ACTIVE", "FAULT"])
def test_a_new_master_boots_the_drives_from_whatever_state_they_are_in(found: str) -> None:
    """What a restarted daemon finds (lockstep HIL): the drives still OPERATION_ENABLED, in
    the fault reaction their SYNC/RPDO watchdog started, or in FAULT at its end; a new master
    boots and enables them, and its last target is where they stand."""
    from hil_sim.harness.lockstep import LockstepHil

    rig = load_rig(RIG)
    with LockstepHil(rig, TrenchPlanner(rig).home_pose_rad, vcu=False) as hil:
        old = CanMaster(hil.master_bus, rig, react_to_faults=False)
        old.boot(hil.clock.now, 1.0)
        old.enable(hil.clock.now, 1.0)
        if found == "FAULT_REACTION_ACTIVE":  # the master is gone: no SYNC, no RPDO1
            hil.clock.sleep_until(hil.clock.now() + 1.05 * rig.drives.sync_timeout_s)
        elif found == "FAULT":  # SYNCs without setpoints until the fault reaction has ended
            for _ in range(250):
                old.cycle.send_sync()
                hil.clock.sleep_until(hil.clock.now() + PERIOD_S)
        before = {node.firmware.state.name for node in hil.core.nodes}
        master = CanMaster(hil.master_bus, rig, react_to_faults=False)
        master.boot(hil.clock.now, 1.0)
        master.enable(hil.clock.now, 1.0)
        states = {DriveState(int(s)).name for s in master.feedback.state}
        gap_um = master.last_target_um() - master.feedback.position_um
    assert before == {found}, before
    assert states == {"OPERATION_ENABLED"}, states
    assert abs(gap_um).max() <= 2, gap_um
