"""``excavator-rt hil soak``: jobs back to back on the daemon's runner in the lockstep HIL, with
faults mixed in at random, for hours.

Usage::

    excavator-rt hil soak [--hours H | --minutes M | --seconds S] [--fault-every-s S]
                          [--seed S] [--warmup-s S] [--rig scale_model] [--json]

One :class:`~rt_runtime.service.runner.RigRunner` (the daemon's runner) on one
:class:`~hil_sim.harness.lockstep.LockstepHil` with its job store in a temporary state
directory, for the wall time given. Jobs (task A's trench, two digs each) are submitted one
after the other; faults of every kind but the killed planner (a random kind, target and
parameter default, drawn with :class:`random.Random` from ``--seed``) are switched on at
exponentially distributed simulated times (mean ``--fault-every-s``; each clears the last
one's cause first) on the runner's thread between two cycles; when one latches, the soak clears
the cause and resets the fault, and the failed job resumes at its next undone dig, as an
operator would with ``reset-fault``.

Checked all along:

* after every dig and every reset the job store is written
  (:meth:`~rt_runtime.service.jobstore.JobStore.sync`) and read back from its file
  (:func:`~rt_runtime.service.jobstore.read_store`): a file that does not read, or a job whose
  digs on disk are not those in memory, is a corrupt record;
* at the end every job submitted is in the store and done (a job failed for another reason
  than a latched fault, or missing, is lost);
* the process's resident memory (``VmRSS``) at the end against its value after ``--warmup-s``
  of wall time (:data:`GROWTH_GOAL`, reported, not an exit status);
* the loop: simulated and wall time, the runtime's and the HIL's wall time per SYNC period
  (p50 and p99 of each run of :data:`COST_PERIODS` periods: the harness's own record of them
  stays bounded).

The truth ring is small (:data:`TRUTH_ROWS`): the soak keeps no trace.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from hil_sim.harness.campaign import CASE_TASK, lockstep_config, wait_for
from hil_sim.harness.lockstep import HilCost, LockstepHil
from hil_sim.harness.realtime import process_memory_mb
from hil_sim.harness.scenario import STALL_MS
from hil_sim.sim import FaultKind
from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.trench import TrenchPlanner
from rt_runtime.rig import load_rig
from rt_runtime.service.jobstore import JobStatus, JobStore, read_store
from rt_runtime.service.runner import RigRunner

__all__ = ["COST_PERIODS", "GROWTH_GOAL", "TRUTH_ROWS", "add_parser", "soak"]

#: Goal: resident memory at the end within this fraction above its value after the warm-up.
GROWTH_GOAL = 0.05
#: Truth rows the soak's HIL keeps (its report needs none).
TRUTH_ROWS = 1 << 14
#: The per-period wall times kept at once (then summarised and dropped).
COST_PERIODS = 1 << 16
#: Digs of each job.
JOB_DIGS = 2
#: Kinds mixed in: all but the killed planner and the changed model (both wait on the wall
#: clock for the planner process), the unwritable store (the soak's own checks read the store)
#: and the daemon's crash (the soak measures one runner's memory).
SOAK_KINDS = tuple(
    k
    for k in FaultKind
    if k
    not in (
        FaultKind.PLANNER_KILLED,
        FaultKind.STORE_UNWRITABLE,
        FaultKind.MODEL_CHANGED,
        FaultKind.DAEMON_CRASH,
    )
)


class _SoakClock:
    """The lockstep clock for the runner's loop; between two cycles it switches the next fault
    on when its simulated time has come (on the loop's thread: nothing races the loop)."""

    realtime = False

    def __init__(self, hil: LockstepHil, rng: random.Random, mean_s: float) -> None:
        self.hil = hil
        self.rng = rng
        self.mean_s = mean_s
        self.next_s = rng.expovariate(1.0 / mean_s)
        self.injected: list[tuple[float, str, str]] = []
        self.paused = False

    def now(self) -> float:
        return self.hil.clock.now()

    def sleep_until(self, t_s: float) -> None:
        self.hil.clock.sleep_until(t_s)
        now = self.hil.clock.now()
        if self.paused or now < self.next_s:
            return
        kind = self.rng.choice(SOAK_KINDS)
        target = self.rng.choice(kind.targets)
        self.next_s = now + self.rng.expovariate(1.0 / self.mean_s)
        self.hil.clear_faults()  # the last one's cause (a loss that would go on for ever)
        if kind is FaultKind.LOOP_STALL:
            self.hil.clock.sleep_until(now + STALL_MS * 1e-3)
        else:
            axis = ("boom", "stick", "bucket").index(target) if target != "bus" else -1
            self.hil.inject(kind, axis)
        self.injected.append((now, kind.label, target))


def soak(
    wall_s: float,
    fault_every_s: float = 20.0,
    seed: int = 0,
    warmup_s: float = 60.0,
    rig_name: str = "scale_model",
) -> dict[str, Any]:
    """Run the soak (see the module docstring); the report (README: ``hil soak --json``)."""
    rig = load_rig(rig_name)
    planner = TrenchPlanner(rig)
    rng = random.Random(seed)
    wall0 = time.monotonic()
    jobs: list[int] = []
    checks = corrupt = resets = 0
    problems: list[str] = []
    costs: list[tuple[float, float, float, float]] = []
    rss_warm = math.nan
    with tempfile.TemporaryDirectory(prefix="excavator-soak-") as tmp:
        cfg = lockstep_config(Path(tmp), rig_name)
        hil = LockstepHil(
            rig, planner.home_pose_rad, vcu=False, fault_seed=seed, truth_rows=TRUTH_ROWS
        )
        clock = _SoakClock(hil, rng, fault_every_s)
        store = JobStore(cfg.paths.state_dir)
        store.start()  # its writer thread: the file is what the checks read
        runner = RigRunner(cfg, rig, planner, hil.master_bus, store, clock, hil.reopen_master_bus)
        seen_digs: dict[int, int] = {}
        try:
            runner.start()
            wait_for(lambda: runner.health()[0], "the runner holding")
            while time.monotonic() - wall0 < wall_s:
                if math.isnan(rss_warm) and time.monotonic() - wall0 >= warmup_s:
                    rss_warm = process_memory_mb()[0]
                if len(hil.cost.hil_ns) >= COST_PERIODS:  # the harness's own record, bounded
                    costs.append(_cost(hil.cost))
                    hil.cost = HilCost()
                if runner.fault():
                    if not runner.state().endswith("waiting for reset-fault"):
                        time.sleep(0.002)
                        continue
                    clock.paused = True
                    hil.clear_faults()
                    _reset(runner)
                    clock.paused = False
                    resets += 1
                    if runner.fault():
                        problems.append(f"reset failed: {runner.fault()}")
                        break
                    store.changed.set()
                    checks += 1
                    corrupt += _check_store(store, problems)
                ended = not jobs or store.get(jobs[-1]).status in (JobStatus.DONE, JobStatus.FAILED)
                if ended and not runner.fault():  # a failed job with no fault latched is lost
                    job = store.submit(dict(CASE_TASK), "pinn", max_digs=JOB_DIGS)
                    jobs.append(job.id)
                    store.changed.set()
                current = store.get(jobs[-1])
                if len(current.digs) != seen_digs.get(current.id, 0):
                    seen_digs[current.id] = len(current.digs)
                    checks += 1
                    corrupt += _check_store(store, problems)
                time.sleep(0.01)
        finally:
            runner.shutdown(30.0)
            store.close()
            rss_end = process_memory_mb()[0]
            costs.append(_cost(hil.cost))
            sim_s = hil.clock.now()
            final = {j.id: j for j in read_store(store.path)[1]}
            hil.close()
    lost = 0
    for job_id in jobs[:-1]:  # the last one may still run when the time is up
        kept = final.get(job_id)
        if kept is None or kept.status is not JobStatus.DONE:
            lost += 1
            problems.append(f"job {job_id}: {'missing' if kept is None else kept.status.label}")
    if math.isnan(rss_warm):
        rss_warm = rss_end
    wall = time.monotonic() - wall0
    arr = np.array(costs) if costs else np.zeros((0, 4))
    return {
        "wall_s": wall,
        "sim_s": sim_s,
        "seed": seed,
        "jobs": len(jobs),
        "digs": sum(len(j.digs) for j in final.values()),
        "faults_injected": len(clock.injected),
        "faults_by_kind": _count(k for _, k, _ in clock.injected),
        "resets": resets,
        "lost_jobs": lost,
        "store_checks": checks,
        "corrupt_records": corrupt,
        "memory_mb": {"warm": rss_warm, "end": rss_end},
        "memory_growth": (rss_end - rss_warm) / rss_warm if rss_warm > 0 else math.nan,
        "goal_memory_growth": GROWTH_GOAL,
        "loop": {
            "speed": sim_s / wall if wall > 0 else math.nan,
            "runtime_us_p50": float(np.median(arr[:, 0])) if len(arr) else math.nan,
            "runtime_us_p99_max": float(np.max(arr[:, 1])) if len(arr) else math.nan,
            "hil_us_p50": float(np.median(arr[:, 2])) if len(arr) else math.nan,
            "hil_us_p99_max": float(np.max(arr[:, 3])) if len(arr) else math.nan,
        },
        "problems": problems[:20],
    }


def _reset(runner: RigRunner) -> None:
    """Request a reset and wait for it to end."""
    number = runner.reset_fault()
    wait_for(lambda: runner.resets_done >= number, "the reset")


def _cost(cost: HilCost) -> tuple[float, float, float, float]:
    s = cost.summary()
    return (s.runtime_us.p50, s.runtime_us.p99, s.hil_us.p50, s.hil_us.p99)


def _count(items: Any) -> dict[str, int]:
    out: dict[str, int] = {}
    for item in items:
        out[item] = out.get(item, 0) + 1
    return out


def _check_store(store: JobStore, problems: list[str]) -> int:
    """The store written and read back: 1 when the file does not read or a job's digs on disk
    are not those in memory, else 0."""
    if not store.sync(10.0):
        problems.append(f"store not written: {store.write_error}")
        return 1
    try:
        _, on_disk = read_store(store.path)
    except ConfigurationError as exc:
        problems.append(str(exc))
        return 1
    disk = {j.id: j for j in on_disk}
    for job in store.jobs():
        other = disk.get(job.id)
        if other is None or len(other.digs) < len(job.digs):
            problems.append(f"job {job.id}: {len(job.digs)} digs in memory, not on disk")
            return 1
    return 0


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``soak`` to the ``hil`` command's sub-commands."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "soak",
        help="jobs back to back on the daemon's runner in the lockstep HIL, faults mixed in",
        description="Jobs back to back with random faults, resets and resumes: memory growth, "
        "the job store after every dig, loop timing.",
    )
    length = p.add_mutually_exclusive_group()
    length.add_argument("--hours", type=float, default=None)
    length.add_argument("--minutes", type=float, default=None)
    length.add_argument("--seconds", type=float, default=None)
    p.add_argument("--fault-every-s", type=float, default=20.0, help="mean simulated s between")
    p.add_argument("--warmup-s", type=float, default=60.0, help="wall s before the memory base")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rig", default="scale_model")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.set_defaults(handler=main)
    return p


def main(args: argparse.Namespace) -> int:
    """``excavator-rt hil soak``: 0 with no lost job and no corrupt record, 1 otherwise."""
    wall_s = (
        args.hours * 3600.0
        if args.hours is not None
        else args.minutes * 60.0
        if args.minutes is not None
        else args.seconds
        if args.seconds is not None
        else 600.0
    )
    if not (math.isfinite(wall_s) and wall_s > 0.0):
        print(f"excavator-rt hil soak: the length {wall_s} s must be > 0", file=sys.stderr)
        return 2
    if not (math.isfinite(args.fault_every_s) and args.fault_every_s > 0.0):
        print("excavator-rt hil soak: --fault-every-s must be > 0", file=sys.stderr)
        return 2
    try:
        report = soak(wall_s, args.fault_every_s, args.seed, args.warmup_s, args.rig)
    except ConfigurationError as exc:
        print(f"excavator-rt hil soak: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(report))
    else:
        print(
            f"{report['jobs']} jobs, {report['digs']} digs, {report['faults_injected']} faults, "
            f"{report['resets']} resets in {report['wall_s']:.0f} s ({report['sim_s']:.0f} s "
            f"simulated); lost jobs {report['lost_jobs']}, corrupt records "
            f"{report['corrupt_records']} of {report['store_checks']} checks; memory "
            f"{report['memory_mb']['warm']:.0f} -> {report['memory_mb']['end']:.0f} MB "
            f"({report['memory_growth'] * 100:+.1f} %, goal < {GROWTH_GOAL * 100:.0f} %)"
        )
        for line in report["problems"]:
            print(f"  {line}")
    return 0 if report["lost_jobs"] == 0 and report["corrupt_records"] == 0 else 1
