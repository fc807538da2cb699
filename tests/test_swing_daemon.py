"""The daemon on a rig with swing takes a taught job like a trench job (``job submit --teach
DIR``): verified and kept at submit, run by the runner on four axes to its end, each cycle
recorded, and after a fault resumed at the cycle it was in with the bucket lifted out of the
ground first; a trench task or a broken taught job is refused and nothing is queued."""

from __future__ import annotations

import contextlib
import io
import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_sim.harness.campaign import lockstep_config
from hil_sim.harness.lockstep import LockstepHil
from hil_sim.operator import demonstrate, write_csv
from hil_sim.sim import FaultKind
from rt_runtime import axes, kinematics
from rt_runtime.cli import main
from rt_runtime.control.planner_worker import PathLink, PlannerError, Recorded
from rt_runtime.control.taught_path import VerticalLift, taught_path
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig, load_rig
from rt_runtime.service.config import DaemonConfig, load_planning
from rt_runtime.service.control import ControlServer
from rt_runtime.service.daemon import Service
from rt_runtime.service.jobstore import JobStatus, JobStore
from rt_runtime.service.runner import RigRunner
from rt_runtime.teach import load_taught


class _Clock:
    """The lockstep clock as the runner's loop sees it; ``hook(now)``, when set, runs on the
    loop's thread after every sleep (where a fault is injected)."""

    realtime = False

    def __init__(self, hil: LockstepHil) -> None:
        self.hil = hil
        self.hook: Callable[[float], None] | None = None

    def now(self) -> float:
        return self.hil.clock.now()

    def sleep_until(self, t_s: float) -> None:
        self.hil.clock.sleep_until(t_s)
        if self.hook is not None:
            self.hook(self.hil.clock.now())


def _wait(pred: Callable[[], bool], what: str, limit_s: float = 120.0) -> None:
    end = time.monotonic() + limit_s
    while not pred():
        assert time.monotonic() < end, f"{what}: not within {limit_s} s"
        time.sleep(0.005)


@pytest.fixture(scope="module")
def demo_files(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    rig = load_rig("field_excavator")
    demos = tmp_path_factory.mktemp("demos")
    files = []
    for seed in range(3):
        path = demos / f"demo_{seed}.csv"
        write_csv(demonstrate(rig, seed=seed), path)
        files.append(str(path))
    return files


def _teach(out: Path, files: list[str], cycles: int) -> Path:
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        code = main(["teach", "--rig", "field_excavator", "--cycles", str(cycles),
                     "--out", str(out), "--demos", *files])  # fmt: skip
    assert code == 0, text.getvalue()[-2000:]
    return out


@pytest.fixture(scope="module")
def taught_dir(tmp_path_factory: pytest.TempPathFactory, demo_files: list[str]) -> Path:
    return _teach(tmp_path_factory.mktemp("taught"), demo_files, 1)


@pytest.fixture(scope="module")
def taught3_dir(tmp_path_factory: pytest.TempPathFactory, demo_files: list[str]) -> Path:
    return _teach(tmp_path_factory.mktemp("taught3"), demo_files, 3)


def _into_second_cycle(
    store: JobStore, job_id: int, into_s: float, act: Callable[[], None]
) -> Callable[[float], None]:
    """A clock hook that calls ``act`` once, ``into_s`` simulated seconds after the job's first
    cycle was recorded (the second cycle under way)."""
    marks: dict[str, float] = {}

    def hook(now: float) -> None:
        if "cycle1" not in marks and len(store.get(job_id).digs) >= 1:
            marks["cycle1"] = now
        elif "acted" not in marks and now >= marks.get("cycle1", np.inf) + into_s:
            marks["acted"] = now
            act()

    return hook


def _wait_job_end(store: JobStore, job_id: int, what: str) -> None:
    _wait(lambda: store.get(job_id).status in (JobStatus.DONE, JobStatus.FAILED), what, 240.0)


@contextlib.contextmanager
def _taught_hil(state: Path, taught: Path) -> Iterator[tuple[DaemonConfig, Rig, Any, _Clock]]:
    """The lockstep daemon's configuration on the field excavator with its state in ``state``,
    the rig, and the lockstep HIL started at the taught trench's first pose, with its clock."""
    cfg = lockstep_config(state, "field_excavator")
    rig, planner = load_planning(cfg)
    assert planner is None  # a rig with swing: no trench planner, taught jobs only
    q0 = axes.from_joint_order(rig, load_taught(taught, rig).q0_rad)
    with LockstepHil(rig, q0, vcu=False) as hil:
        yield cfg, rig, hil, _Clock(hil)


def _open_store(cfg: DaemonConfig) -> JobStore:
    store = JobStore(cfg.paths.state_dir)
    store.start()
    return store


def _start(runner: RigRunner) -> None:
    runner.start()
    _wait(lambda: runner.health()[0], "the runner holding")


@contextlib.contextmanager
def _daemon(
    cfg: DaemonConfig, rig: Rig, hil: Any, clock: _Clock
) -> Iterator[tuple[Service, JobStore, RigRunner]]:
    """The daemon's service, store and runner on the HIL's bus, holding; shut down after."""
    store = _open_store(cfg)
    runner = RigRunner(cfg, rig, None, hil.master_bus, store, clock)
    svc = Service(cfg, rig, store, ControlServer(cfg.paths.socket, {}), runner)
    try:
        _start(runner)
        yield svc, store, runner
    finally:
        runner.shutdown(30.0)
        store.close()


@contextlib.contextmanager
def _service(state: Path, taught: Path) -> Iterator[tuple[Service, JobStore, Any, _Clock]]:
    with (
        _taught_hil(state, taught) as (cfg, rig, hil, clock),
        _daemon(cfg, rig, hil, clock) as (svc, store, _),
    ):
        yield svc, store, hil, clock


@pytest.fixture
def service(tmp_path: Path, taught_dir: Path) -> Iterator[tuple[Service, JobStore, Any]]:
    with _service(tmp_path, taught_dir) as (svc, store, hil, _):
        yield svc, store, hil


def test_the_daemon_runs_a_taught_job_on_four_axes(
    service: tuple[Service, JobStore, Any], taught_dir: Path
) -> None:
    svc, store, hil = service
    reply = svc.cmd_submit({"cmd": "submit", "teach": str(taught_dir)})
    job = reply["job"]
    assert job["task"] == {"name": "taught"}
    kept = Path(job["taught"])
    assert kept.parent == store.path.parent and kept.is_file()  # the daemon's own copy
    store.changed.set()

    def ended() -> bool:
        return store.get(job["id"]).status in (JobStatus.DONE, JobStatus.FAILED)

    _wait(ended, "the taught job ending")
    final = store.get(job["id"])
    assert final.status is JobStatus.DONE, final.fault
    # It moved the swing on its drive (node 4) through the dump and back.
    swing = hil.core.truth().swing_rad
    assert float(swing.max()) > 0.9  # rad: the taught cycle swings ~70 deg to dump
    assert abs(float(swing[-1])) < 0.05


def test_a_trench_task_or_a_broken_taught_job_is_refused_on_a_swing_rig(
    service: tuple[Service, JobStore, Any], taught_dir: Path, tmp_path: Path
) -> None:
    svc, store, _ = service
    with pytest.raises(ConfigurationError, match="swing"):
        svc.cmd_submit({"cmd": "submit", "task": "A"})
    data = json.loads((taught_dir / "taught.json").read_text())
    data["trench"]["cycles"][0]["segments"][0]["coefficients"][1][2] = 0.5  # moving at start
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "taught.json").write_text(json.dumps(data))
    with pytest.raises(ConfigurationError, match=r"jumps|rest"):
        svc.cmd_submit({"cmd": "submit", "teach": str(bad)})
    with pytest.raises(ConfigurationError, match="absolute"):
        svc.cmd_submit({"cmd": "submit", "teach": "relative/dir"})
    assert store.jobs() == []  # nothing was queued


def test_taught_cycles_are_steps_and_a_resume_lifts_the_bucket_out_first(
    taught3_dir: Path,
) -> None:
    rig = load_rig("field_excavator")
    job = load_taught(taught3_dir, rig)
    path = taught_path(job, rig, 1)
    assert path.steps and path.first_step == 1 and len(path.motions) == 2
    starts = [*job.cycle_starts_s, job.duration_s]
    for motion, k in zip(path.motions, (1, 2), strict=True):
        assert motion.duration_s == pytest.approx(starts[k + 1] - starts[k])
        q, qd, _ = motion.sample(0.0)
        assert q == pytest.approx(axes.from_joint_order(rig, job.sample(starts[k], 0)))
        assert np.abs(qd).max() < 1e-9  # every cycle starts at rest
    path.check(rig)
    for bad in (-1, 3, True):
        with pytest.raises(ConfigurationError, match=r"first cycle .* allowed: an integer"):
            taught_path(job, rig, bad)
    # The PathLink records the steps in order, numbered from the first one, then refuses.
    link = PathLink(path)
    for index in (1, 2):
        link.request_record(np.zeros((0, 3)), False)
        link.service()
        rec = link.poll()
        assert isinstance(rec, Recorded), rec
        assert (rec.index, rec.step, rec.state) == (index, "cycle", {"steps_done": index + 1})
    link.request_record(np.zeros((0, 3)), False)
    link.service()
    assert isinstance(link.poll(), PlannerError)
    # lift_out: a tip in the ground rises to the start's height, same swing, reach and attitude.
    start = path.motions[0].sample(0.0)[0]
    retreat = path.retreat
    assert retreat is not None and retreat(start) is None
    deep = axes.from_joint_order(rig, job.sample(starts[1] + 1.5, 0))
    below = kinematics.forward(rig, axes.to_joint_order(rig, deep)[1:])
    top = kinematics.forward(rig, axes.to_joint_order(rig, start)[1:])
    assert below[1] < top[1] - 0.5, (below, top)  # 1.5 s into the cycle: in the trench
    lift = retreat(deep)
    assert isinstance(lift, VerticalLift)
    ts = np.linspace(0.0, lift.duration_s, 200)
    rows = [lift.sample(float(t)) for t in ts]
    q = np.array([r[0] for r in rows])
    tips = kinematics.forward(rig, axes.to_joint_order(rig, q)[:, 1:])
    assert q[0] == pytest.approx(deep, abs=1e-9) and tips[-1, 1] == pytest.approx(top[1])
    assert np.abs(tips[:, 0] - below[0]).max() < 1e-6  # straight up ...
    assert np.abs(tips[:, 2] - below[2]).max() < 1e-9  # ... at the bucket's attitude ...
    assert np.all(q[:, 3] == deep[3])  # ... the swing still
    assert np.all(np.diff(tips[:, 1]) >= -1e-12)
    _, _, v_max, a_max, _ = axes.joint_limits(rig)
    assert np.all(np.abs([r[1] for r in rows]) <= v_max)
    assert np.all(np.abs([r[2] for r in rows]) <= a_max)
    # Its rates are the derivative of its positions (the chain rule through the IK).
    dq = np.gradient(q, ts, axis=0)
    assert np.abs(dq - np.array([r[1] for r in rows]))[2:-2].max() < 1e-3


def test_a_taught_job_stopped_by_a_fault_resumes_at_its_cycle(
    tmp_path: Path, taught3_dir: Path
) -> None:
    rig = load_rig("field_excavator")
    job_file = load_taught(taught3_dir, rig)
    into_cycle_s = 1.5  # into the dig of the second cycle: the bucket in the trench
    with _service(tmp_path, taught3_dir) as (svc, store, hil, clock):
        runner = svc.runner
        job_id = svc.cmd_submit({"cmd": "submit", "teach": str(taught3_dir)})["job"]["id"]
        clock.hook = _into_second_cycle(
            store, job_id, into_cycle_s, lambda: hil.inject(FaultKind.OVERCURRENT, 0)
        )
        store.changed.set()
        _wait(lambda: bool(runner.fault()), "the fault", 240.0)
        _wait(lambda: runner.state().endswith("waiting for reset-fault"), "the latch")
        stopped = store.get(job_id)
        assert stopped.status is JobStatus.FAILED
        assert [d["index"] for d in stopped.digs] == [0]  # the cut-short cycle not recorded
        assert stopped.digs[0]["dig_type"] == "cycle"
        assert stopped.digs[0]["measured_volume_m3"] is None
        assert stopped.session_state == {"steps_done": 1}
        truth = hil.core.truth()
        held = len(truth.t_s) - 1  # the stop's end, where the arm waits for the reset
        tip_held = kinematics.forward(rig, truth.q_rad[held])
        clock.hook = None
        hil.clear_faults()
        number = runner.reset_fault()
        _wait(lambda: runner.resets_done >= number, "the reset")
        assert not runner.fault()
        store.changed.set()
        _wait_job_end(store, job_id, "the resumed job ending")
        final = store.get(job_id)
        assert final.status is JobStatus.DONE, final.fault
        assert [d["index"] for d in final.digs] == [0, 1, 2]
        # Out of the trench first: while the tip rose to the cycle's start height it kept its
        # distance from the swing axis within 5 cm and the swing stood still. The tip tracks
        # the commanded vertical within this rig's tracking (tip error up to 37 mm on the
        # taught trench); a joint move there strays 13 cm, no lift 1.5 m.
        truth = hil.core.truth()
        after = truth.t_s > truth.t_s[held]
        tip = kinematics.forward(rig, truth.q_rad[after])
        start_height = kinematics.forward(rig, job_file.sample(job_file.cycle_starts_s[1])[1:])[1]
        assert tip_held[1] < start_height - 0.5  # the stop left the bucket in the trench
        top = np.flatnonzero(tip[:, 1] >= start_height - 0.05)
        assert top.size
        # The lift: from 0.2 m above where the tip stood after the reset (past the pull onto
        # the commanded hold, which the arm on its hydraulic hold may be a few cm off) to 5 cm
        # below the cycle's start height.
        base = int(np.flatnonzero(tip[: top[0], 1] < tip[0, 1] + 0.2)[-1]) + 1
        up = slice(base, int(top[0]) + 1)
        assert tip[top[0], 1] - tip[base, 1] > 0.8
        assert np.abs(tip[up, 0] - tip[top[0], 0]).max() < 0.05
        swing = truth.swing_rad
        assert swing is not None
        assert np.abs(swing[after][up] - swing[after][base]).max() < 0.01


def test_a_taught_job_shut_down_mid_cycle_resumes_there_after_a_restart(
    tmp_path: Path, taught3_dir: Path
) -> None:
    """The daemon stopped (SIGTERM) in the second cycle and started again on its store: the
    job resumes at the second cycle, the first kept and not dug again."""
    with _taught_hil(tmp_path, taught3_dir) as (cfg, rig, hil, clock):
        with _daemon(cfg, rig, hil, clock) as (svc, store, runner):
            job_id = svc.cmd_submit({"cmd": "submit", "teach": str(taught3_dir)})["job"]["id"]
            in_second = threading.Event()
            clock.hook = _into_second_cycle(store, job_id, 1.5, in_second.set)
            store.changed.set()
            _wait(in_second.is_set, "the second cycle", 240.0)
            clock.hook = None
            assert runner.shutdown(30.0)
        stopped = _open_store(cfg)  # the store as the restarted daemon reads it
        job = stopped.get(job_id)
        assert job.status is JobStatus.QUEUED and [d["index"] for d in job.digs] == [0]
        again = RigRunner(cfg, rig, None, hil.master_bus, stopped, clock)
        try:
            _start(again)
            stopped.changed.set()
            _wait_job_end(stopped, job_id, "the resumed job ending")
            final = stopped.get(job_id)
            assert final.status is JobStatus.DONE, final.fault
            assert [d["index"] for d in final.digs] == [0, 1, 2]
            assert final.digs[0] == job.digs[0]  # the first cycle's record kept as it was
        finally:
            again.shutdown(30.0)
            stopped.close()
