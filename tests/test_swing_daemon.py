"""The daemon on a rig with swing takes a taught job like a trench job (``job submit --teach
DIR``): verified and kept at submit, run by the runner on four axes to its end; a trench task or
a broken taught job is refused and nothing is queued."""

from __future__ import annotations

import contextlib
import io
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from hil_sim.harness.campaign import lockstep_config
from hil_sim.harness.lockstep import LockstepHil
from hil_sim.operator import demonstrate, write_csv
from rt_runtime import axes
from rt_runtime.cli import main
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import load_rig
from rt_runtime.service.config import load_planning
from rt_runtime.service.control import ControlServer
from rt_runtime.service.daemon import Service
from rt_runtime.service.jobstore import JobStatus, JobStore
from rt_runtime.service.runner import RigRunner
from rt_runtime.teach import load_taught


class _Clock:
    """The lockstep clock as the runner's loop sees it."""

    realtime = False

    def __init__(self, hil: LockstepHil) -> None:
        self.hil = hil

    def now(self) -> float:
        return self.hil.clock.now()

    def sleep_until(self, t_s: float) -> None:
        self.hil.clock.sleep_until(t_s)


def _wait(pred: Callable[[], bool], what: str, limit_s: float = 120.0) -> None:
    end = time.monotonic() + limit_s
    while not pred():
        assert time.monotonic() < end, f"{what}: not within {limit_s} s"
        time.sleep(0.005)


@pytest.fixture(scope="module")
def taught_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rig = load_rig("field_excavator")
    demos = tmp_path_factory.mktemp("demos")
    files = []
    for seed in range(3):
        path = demos / f"demo_{seed}.csv"
        write_csv(demonstrate(rig, seed=seed), path)
        files.append(str(path))
    out = tmp_path_factory.mktemp("taught")
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        code = main(["teach", "--rig", "field_excavator", "--cycles", "1", "--out", str(out),
                     "--demos", *files])  # fmt: skip
    assert code == 0, text.getvalue()[-2000:]
    return out


@pytest.fixture
def service(tmp_path: Path, taught_dir: Path) -> Iterator[tuple[Service, JobStore, Any]]:
    cfg = lockstep_config(tmp_path, "field_excavator")
    rig, planner = load_planning(cfg)
    assert planner is None  # a rig with swing: no trench planner, taught jobs only
    q0 = axes.from_joint_order(rig, load_taught(taught_dir, rig).q0_rad)
    with LockstepHil(rig, q0, vcu=False) as hil:
        store = JobStore(cfg.paths.state_dir)
        store.start()
        runner = RigRunner(cfg, rig, planner, hil.master_bus, store, _Clock(hil))
        server = ControlServer(cfg.paths.socket, {})
        svc = Service(cfg, rig, store, server, runner)
        try:
            runner.start()
            _wait(lambda: runner.health()[0], "the runner holding")
            yield svc, store, hil
        finally:
            runner.shutdown(30.0)
            store.close()


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
