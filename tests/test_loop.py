"""Fixed-rate loop: deadlines, overrun counting/skipping/re-phase, safe stop, RT apply/restore.

Every timing test runs on a fake clock that the test controls (stalls injected by making
``sleep_until`` wake late or the step take time), so counts are exact. One short run on the real
monotonic clock checks only counts and consistency, never wall time.
"""

from __future__ import annotations

import gc
import logging
import os
import tracemalloc
from typing import Any

import numpy as np
import pytest

from rt_runtime.control import (
    Column,
    CycleInfo,
    FixedRateLoop,
    LoopAction,
    LoopConfig,
    MonotonicClock,
    OverrunPolicy,
    RtSettings,
    Telemetry,
    apply_rt,
    restore_rt,
)
from rt_runtime.control.rt import MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT, HelperThreads
from rt_runtime.errors import ConfigurationError

PERIOD = 0.002
NO_RT = RtSettings(
    sched_fifo_priority=None, lock_memory=False, cpu=None, timer_slack_ns=None, freeze_gc=False
)


class FakeClock:
    """Simulated time: ``sleep_until`` wakes exactly on time unless a stall is scheduled.

    ``stalls[n]`` delays the wake-up of the n-th ``sleep_until`` call (n from 0) by that many
    seconds; :meth:`advance` lets a step take time.
    """

    realtime = False

    def __init__(self, t0: float = 100.0, stalls: dict[int, float] | None = None) -> None:
        self.t = t0
        self.stalls = stalls or {}
        self.sleeps = 0

    def now(self) -> float:
        return self.t

    def sleep_until(self, t_s: float) -> None:
        if t_s > self.t:
            self.t = t_s
        self.t += self.stalls.get(self.sleeps, 0.0)
        self.sleeps += 1

    def advance(self, dt_s: float) -> None:
        self.t += dt_s


class Recorder:
    """A step that copies each CycleInfo and can take time or stop."""

    def __init__(
        self,
        clock: FakeClock,
        exec_s: dict[int, float] | None = None,
        stop_after_safe: int | None = None,
    ) -> None:
        self.clock = clock
        self.exec_s = exec_s or {}
        self.stop_after_safe = stop_after_safe
        self.rows: list[dict[str, Any]] = []
        self.safe_since: int | None = None

    def __call__(self, info: CycleInfo) -> LoopAction:
        self.rows.append({name: getattr(info, name) for name in CycleInfo.__slots__})
        self.clock.advance(self.exec_s.get(info.count, 0.0))
        if info.safe_stop and self.stop_after_safe is not None:
            if self.safe_since is None:
                self.safe_since = info.count
            if info.count - self.safe_since >= self.stop_after_safe:
                return LoopAction.STOP
        return LoopAction.CONTINUE


def make_loop(clock: FakeClock, **overrun: float | int) -> FixedRateLoop:
    policy = OverrunPolicy(**overrun)  # type: ignore[arg-type]
    return FixedRateLoop(clock, LoopConfig(period_s=PERIOD, spin_s=0.0, rt=NO_RT, overrun=policy))


def test_on_time_cycles_follow_the_absolute_grid() -> None:
    clock = FakeClock(t0=5.0)
    step = Recorder(clock, exec_s={k: 0.0003 for k in range(100)})
    stats = make_loop(clock).run(step, max_cycles=100)
    assert stats.cycles == 100 and stats.overruns == 0 and stats.skipped == 0
    assert not stats.stopped_by_step and not stats.safe_stop
    assert [r["index"] for r in step.rows] == list(range(100))
    assert [r["count"] for r in step.rows] == list(range(100))
    np.testing.assert_allclose([r["deadline_s"] for r in step.rows], 5.0 + PERIOD * np.arange(100))
    assert all(r["lateness_s"] == 0.0 for r in step.rows)
    np.testing.assert_allclose(stats.exec_s, 0.0003)
    np.testing.assert_allclose(stats.period_jitter_s(), 0.0, atol=1e-12)
    assert stats.max_lateness_s == 0.0


def test_small_lateness_is_not_an_overrun() -> None:
    clock = FakeClock(stalls={10: 0.4 * PERIOD})
    step = Recorder(clock)
    stats = make_loop(clock).run(step, max_cycles=20)
    assert stats.overruns == 0
    assert step.rows[10]["lateness_s"] == pytest.approx(0.4 * PERIOD)
    assert [r["index"] for r in step.rows] == list(range(20))
    assert stats.max_lateness_s == pytest.approx(0.4 * PERIOD)


def test_overrun_shorter_than_a_period_skips_nothing() -> None:
    clock = FakeClock(stalls={10: 0.7 * PERIOD})
    step = Recorder(clock)
    stats = make_loop(clock).run(step, max_cycles=20)
    assert stats.overruns == 1 and stats.skipped == 0
    row = step.rows[10]
    assert row["overrun"] and row["skipped"] == 0 and row["consecutive_overruns"] == 1
    assert [r["index"] for r in step.rows] == list(range(20))
    assert step.rows[11]["lateness_s"] == 0.0 and not step.rows[11]["overrun"]


@pytest.mark.parametrize(("stall_periods", "skipped"), [(1.0 + 1e-6, 1), (2.3, 2), (7.9, 7)])
def test_stall_skips_missed_deadlines_and_rephases_on_the_original_grid(
    stall_periods: float, skipped: int
) -> None:
    t0 = 1.0
    clock = FakeClock(t0=t0, stalls={10: stall_periods * PERIOD})
    step = Recorder(clock)
    stats = make_loop(clock).run(step, max_cycles=20)
    assert stats.cycles == 20 and stats.overruns == 1 and stats.skipped == skipped
    late = step.rows[10]
    assert late["index"] == 10 and late["overrun"] and late["skipped"] == skipped
    assert late["lateness_s"] == pytest.approx(stall_periods * PERIOD)
    nxt = step.rows[11]
    assert nxt["index"] == 11 + skipped
    # The next deadline is the first one after the late start, on the grid t0 + k * period.
    assert nxt["deadline_s"] == pytest.approx(t0 + (11 + skipped) * PERIOD)
    assert nxt["deadline_s"] > late["start_s"]
    assert nxt["deadline_s"] - late["start_s"] <= PERIOD
    assert nxt["lateness_s"] == 0.0 and not nxt["overrun"]
    assert step.rows[-1]["index"] == 19 + skipped
    assert stats.overrun_events[0].index == 10 and stats.overrun_events[0].skipped == skipped
    # Jitter leaves out the pair across the skip.
    assert stats.period_jitter_s().size == 20 - 1 - (1 if skipped else 0)
    cyc = stats.cycle
    assert np.all(np.diff(cyc) >= 1) and int(np.sum(np.diff(cyc) - 1)) == skipped


def test_long_steps_overrun_in_a_row_and_request_a_safe_stop() -> None:
    clock = FakeClock()
    # From step 3 on every step takes 1.6 periods: every next cycle starts late.
    step = Recorder(clock, exec_s={k: 1.6 * PERIOD for k in range(3, 1000)}, stop_after_safe=3)
    stats = make_loop(clock, max_consecutive=5).run(step)
    consecutive = [r["consecutive_overruns"] for r in step.rows]
    safe = [r["safe_stop"] for r in step.rows]
    assert consecutive[:5] == [0, 0, 0, 0, 1]
    first_safe = safe.index(True)
    assert consecutive[first_safe] == 5 and all(safe[first_safe:])
    assert stats.safe_stop and stats.stopped_by_step
    assert stats.cycles == first_safe + 4
    assert stats.max_consecutive_overruns == stats.overruns == stats.cycles - 4
    # Lateness builds up (the grid does not move) until a re-phase skips deadlines.
    assert all(float(r["lateness_s"]) > 0.5 * PERIOD for r in step.rows[4:])
    assert any(int(r["skipped"]) > 0 for r in step.rows)
    for r in step.rows:
        assert r["deadline_s"] == pytest.approx(100.0 + int(r["index"]) * PERIOD)


def test_consecutive_counter_resets_on_an_on_time_cycle() -> None:
    clock = FakeClock()
    slow = {k: 1.6 * PERIOD for k in [*range(2, 6), *range(7, 11)]}
    step = Recorder(clock, exec_s=slow)
    stats = make_loop(clock, max_consecutive=5).run(step, max_cycles=20)
    assert stats.overruns == 8 and stats.max_consecutive_overruns == 4
    assert not stats.safe_stop and not any(r["safe_stop"] for r in step.rows)
    assert step.rows[7]["consecutive_overruns"] == 0
    assert step.rows[-1]["overruns"] == 8


def test_safe_stop_with_max_consecutive_one() -> None:
    clock = FakeClock(stalls={4: 3.5 * PERIOD})
    step = Recorder(clock, stop_after_safe=0)
    stats = make_loop(clock, max_consecutive=1).run(step, max_cycles=50)
    assert stats.safe_stop and stats.stopped_by_step and stats.cycles == 5 and stats.skipped == 3


def test_late_fraction_sets_the_threshold() -> None:
    clock = FakeClock(stalls={3: 0.3 * PERIOD})
    stats = make_loop(clock, late_fraction=0.25).run(Recorder(clock), max_cycles=6)
    assert stats.overruns == 1


def test_step_stop_and_max_cycles() -> None:
    clock = FakeClock()
    stats = make_loop(clock).run(lambda info: LoopAction.STOP, max_cycles=10)
    assert stats.cycles == 1 and stats.stopped_by_step
    stats = make_loop(clock).run(lambda info: LoopAction.CONTINUE, max_cycles=0)
    assert stats.cycles == 0 and stats.lateness_s.size == 0
    with pytest.raises(ConfigurationError, match="max_cycles"):
        make_loop(clock).run(lambda info: LoopAction.CONTINUE, max_cycles=-1)


def test_overruns_are_logged_with_their_size(caplog: pytest.LogCaptureFixture) -> None:
    clock = FakeClock(stalls={5: 2.5 * PERIOD})
    with caplog.at_level(logging.WARNING, logger="rt_runtime.control.loop"):
        make_loop(clock).run(Recorder(clock), max_cycles=10)
    text = caplog.text
    assert "overrun at cycle 5: 5000.0 us late" in text and "2 deadline(s) skipped" in text
    assert "1 overrun(s) in 10 cycles" in text


def test_telemetry_gets_loop_and_step_columns() -> None:
    clock = FakeClock(stalls={3: 1.5 * PERIOD})
    tel = Telemetry(16, [Column("phase", np.int8, (), -1)])
    phase = tel.column("phase")

    def step(info: CycleInfo) -> LoopAction:
        phase[tel.slot] = info.count % 3
        clock.advance(1e-4)
        return LoopAction.CONTINUE

    loop = FixedRateLoop(clock, LoopConfig(period_s=PERIOD, spin_s=0.0, rt=NO_RT), tel)
    stats = loop.run(step, max_cycles=8)
    snap = tel.snapshot()
    np.testing.assert_array_equal(snap["cycle"], [0, 1, 2, 3, 5, 6, 7, 8])
    np.testing.assert_array_equal(snap["overrun"], [0, 0, 0, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(snap["phase"], np.arange(8) % 3)
    np.testing.assert_allclose(snap["exec_s"], 1e-4)
    np.testing.assert_array_equal(stats.lateness_s, snap["lateness_s"])


def test_loop_cycle_does_not_allocate() -> None:
    clock = FakeClock()
    loop = make_loop(clock)

    def step(info: CycleInfo) -> LoopAction:
        return LoopAction.CONTINUE

    loop.run(step, max_cycles=1000)
    tracemalloc.start()
    try:
        loop.run(step, max_cycles=100)
        small, _ = tracemalloc.get_traced_memory()
        loop.run(step, max_cycles=10_100)
        big, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # Stats arrays scale with the cycles (snapshot after the run); the cycles themselves not.
    per_cycle_bytes = (big - small) / 10_000
    assert per_cycle_bytes < 5 * 8 + 8, f"{per_cycle_bytes:.1f} bytes kept per cycle"


def test_config_validation_names_the_field() -> None:
    with pytest.raises(ConfigurationError, match="period_s"):
        LoopConfig(period_s=0.0)
    with pytest.raises(ConfigurationError, match="spin_s"):
        LoopConfig(period_s=0.001, spin_s=0.001)
    with pytest.raises(ConfigurationError, match="late_fraction"):
        OverrunPolicy(late_fraction=0.0)
    with pytest.raises(ConfigurationError, match="max_consecutive"):
        OverrunPolicy(max_consecutive=0)
    with pytest.raises(ConfigurationError, match=r"rt\.cpu"):
        RtSettings(cpu=-1)
    with pytest.raises(ConfigurationError, match="timer_slack_ns"):
        RtSettings(timer_slack_ns=0)


class FakePlatform:
    """An OS that refuses what it is told to and records every call."""

    def __init__(self, refuse: set[str]) -> None:
        self.refuse = refuse
        self.calls: list[tuple[str, object]] = []
        self.policy = (os.SCHED_OTHER, 0)
        self.cpus = {0, 1}
        self.slack = 50_000

    def _maybe_refuse(self, what: str, arg: object) -> None:
        self.calls.append((what, arg))
        if what in self.refuse:
            raise PermissionError(1, f"{what} not permitted")

    def get_scheduler(self) -> tuple[int, int]:
        return self.policy

    def set_scheduler(self, policy: int, priority: int) -> None:
        self._maybe_refuse("set_scheduler", (policy, priority))
        self.policy = (policy, priority)

    def fifo_priority_range(self) -> tuple[int, int]:
        return 1, 99

    def get_affinity(self) -> set[int]:
        return set(self.cpus)

    def set_affinity(self, cpus: set[int]) -> None:
        self._maybe_refuse("set_affinity", cpus)
        self.cpus = set(cpus)

    def mlockall(self, flags: int) -> None:
        self._maybe_refuse("mlockall", flags)

    def munlockall(self) -> None:
        self._maybe_refuse("munlockall", None)

    def get_timer_slack_ns(self) -> int:
        return self.slack

    def set_timer_slack_ns(self, slack_ns: int) -> None:
        self._maybe_refuse("set_timer_slack_ns", slack_ns)
        self.slack = slack_ns


ALL_RT = RtSettings(sched_fifo_priority=80, lock_memory=True, cpu=1, timer_slack_ns=1)


class NoOnFaultPlatform(FakePlatform):
    """A kernel before Linux 4.4: mlockall refuses MCL_ONFAULT."""

    def mlockall(self, flags: int) -> None:
        self.calls.append(("mlockall", flags))
        if flags & MCL_ONFAULT:
            raise OSError(22, "Invalid argument")


def test_mlockall_locks_the_future_on_fault_and_falls_back_without_it() -> None:
    report = apply_rt(RtSettings(None, True, None, None, False), FakePlatform(refuse=set()))
    assert report.memory_locked and report.items[0].requested.endswith("MCL_FUTURE|MCL_ONFAULT")
    plat = NoOnFaultPlatform(refuse=set())
    report = apply_rt(RtSettings(None, True, None, None, False), plat)
    assert report.memory_locked and "no MCL_ONFAULT" in report.items[0].requested
    assert [c[1] for c in plat.calls] == [
        MCL_CURRENT,
        MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT,
        MCL_CURRENT | MCL_FUTURE,
    ]


def test_refusals_are_reported_and_only_applied_items_are_undone() -> None:
    plat = FakePlatform(refuse={"set_scheduler", "mlockall"})
    report = apply_rt(ALL_RT, plat)
    try:
        status = {i.item: i.applied for i in report.items}
        assert status == {
            "sched_fifo": False,
            "mlockall": False,
            "affinity": True,
            "timer_slack": True,
            "gc_freeze": True,
        }
        reasons = {i.item: i.reason for i in report.refused}
        assert "not permitted" in reasons["sched_fifo"] and "errno 1" in reasons["mlockall"]
        assert report.as_dict()["affinity"] == {
            "requested": "cpu 1",
            "applied": True,
            "reason": "",
        }
        assert not gc.isenabled()
        assert plat.cpus == {1} and plat.slack == 1
    finally:
        restore_rt(report)
    assert gc.isenabled()
    assert plat.cpus == {0, 1} and plat.slack == 50_000
    assert ("munlockall", None) not in plat.calls
    assert [c for c in plat.calls if c[0] == "set_scheduler"] == [
        ("set_scheduler", (os.SCHED_FIFO, 80))
    ]


def test_priority_out_of_range_is_refused_with_the_allowed_range() -> None:
    report = apply_rt(
        RtSettings(sched_fifo_priority=150, lock_memory=False, timer_slack_ns=None, freeze_gc=False)
    )
    restore_rt(report)
    (item,) = report.items
    assert item.item == "sched_fifo" and not item.applied
    assert "150" in item.reason and "[1, 99]" in item.reason
    assert os.sched_getscheduler(0) != os.SCHED_FIFO


def test_loop_runs_when_everything_is_refused_and_restores_after_a_raising_step() -> None:
    plat = FakePlatform(refuse={"set_scheduler", "mlockall", "set_affinity", "set_timer_slack_ns"})
    clock = FakeClock()
    loop = FixedRateLoop(clock, LoopConfig(period_s=PERIOD, rt=ALL_RT), rt_platform=plat)
    stats = loop.run(lambda info: LoopAction.CONTINUE, max_cycles=5)
    assert stats.cycles == 5 and len(stats.rt.refused) == 4
    assert gc.isenabled()

    plat = FakePlatform(refuse=set())
    loop = FixedRateLoop(clock, LoopConfig(period_s=PERIOD, rt=ALL_RT), rt_platform=plat)

    def boom(info: CycleInfo) -> LoopAction:
        assert not gc.isenabled()
        raise RuntimeError("step failed")

    with pytest.raises(RuntimeError, match="step failed"):
        loop.run(boom)
    assert gc.isenabled()
    assert plat.policy == (os.SCHED_OTHER, 0) and plat.cpus == {0, 1} and plat.slack == 50_000
    assert ("munlockall", None) in plat.calls


def test_real_os_apply_and_restore_bounded() -> None:
    """Apply SCHED_FIFO, affinity, slack and gc freeze on this thread, check, restore.

    Nothing spins while the thread is SCHED_FIFO; mlockall is left out (it would pin the whole
    test process's memory on a shared machine).
    """
    before_policy = os.sched_getscheduler(0)
    before_cpus = os.sched_getaffinity(0)
    cpu = min(before_cpus)
    settings = RtSettings(sched_fifo_priority=10, lock_memory=False, cpu=cpu, timer_slack_ns=1)
    report = apply_rt(settings)
    try:
        applied = {i.item: i.applied for i in report.items}
        for item in report.refused:
            assert item.reason, item
        if applied["sched_fifo"]:
            assert os.sched_getscheduler(0) == os.SCHED_FIFO
            assert os.sched_getparam(0).sched_priority == 10
        if applied["affinity"]:
            assert os.sched_getaffinity(0) == {cpu}
        assert not gc.isenabled()
    finally:
        restore_rt(report)
    assert os.sched_getscheduler(0) == before_policy
    assert os.sched_getaffinity(0) == before_cpus
    assert gc.isenabled()


def test_real_clock_short_run_is_consistent() -> None:
    clock = MonotonicClock()
    tel = Telemetry(256)
    loop = FixedRateLoop(clock, LoopConfig(period_s=PERIOD, spin_s=2e-4, rt=NO_RT), tel)
    seen: list[int] = []

    def step(info: CycleInfo) -> LoopAction:
        seen.append(info.index)
        return LoopAction.CONTINUE

    stats = loop.run(step, max_cycles=200)
    snap = tel.snapshot()
    assert stats.cycles == 200 == tel.count
    np.testing.assert_array_equal(snap["cycle"], seen)
    assert np.all(snap["lateness_s"] >= 0.0)  # sleep_until never returns early
    assert stats.overruns == int(np.sum(snap["overrun"]))
    # The deadlines skipped at the last cycle lie after it: they are counted, never run.
    last_skipped = int(snap["lateness_s"][-1] // PERIOD) if snap["overrun"][-1] else 0
    assert int(np.sum(np.diff(snap["cycle"]) - 1)) == stats.skipped - last_skipped
    assert stats.period_jitter_s().size == int(np.sum(np.diff(snap["cycle"]) == 1))
    assert stats.max_lateness_s == pytest.approx(float(np.max(snap["lateness_s"])))
    assert clock.spin_s == 2e-4
    print(
        f"real clock 500 Hz x 200: lateness p99 "
        f"{np.percentile(snap['lateness_s'], 99) * 1e6:.1f} us, overruns {stats.overruns}"
    )


def test_acquired_rt_stays_across_runs_until_released() -> None:
    plat = FakePlatform(refuse=set())
    clock = FakeClock()
    loop = FixedRateLoop(clock, LoopConfig(period_s=PERIOD, rt=ALL_RT), rt_platform=plat)
    report = loop.acquire_rt()
    try:
        assert loop.acquire_rt() is report
        assert plat.policy == (os.SCHED_FIFO, 80) and not gc.isenabled()
        for _ in range(2):
            stats = loop.run(lambda info: LoopAction.CONTINUE, max_cycles=3)
            assert stats.rt is report
            assert plat.policy == (os.SCHED_FIFO, 80) and not gc.isenabled()
        # Locked once: the current pages, then the future ones as they are touched.
        assert [c[1] for c in plat.calls if c[0] == "mlockall"] == [
            MCL_CURRENT,
            MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT,
        ]
    finally:
        loop.release_rt()
    assert plat.policy == (os.SCHED_OTHER, 0) and gc.isenabled()
    assert ("munlockall", None) in plat.calls
    loop.release_rt()  # no-op


def test_helper_threads_run_fifo_below_the_loop_and_their_processes_do_not() -> None:
    """Threads started while ``HelperThreads`` is in force run SCHED_FIFO at its priority; a
    process one of them starts runs at normal priority; after ``restore`` new threads do not."""
    import subprocess
    import sys
    import threading

    before = os.sched_getscheduler(0)
    helpers = HelperThreads(10)
    if not helpers.item.applied:
        pytest.skip(f"SCHED_FIFO refused here: {helpers.item.reason}")
    seen: dict[str, object] = {}

    def helper() -> None:
        seen["policy"] = os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK
        seen["priority"] = os.sched_getparam(0).sched_priority
        child = subprocess.run(
            [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        seen["child"] = int(child.stdout)

    try:
        t = threading.Thread(target=helper)
        t.start()
        t.join()
    finally:
        helpers.restore()
    assert seen == {"policy": os.SCHED_FIFO, "priority": 10, "child": os.SCHED_OTHER}
    assert os.sched_getscheduler(0) == before
    after: list[int] = []
    t = threading.Thread(target=lambda: after.append(os.sched_getscheduler(0)))
    t.start()
    t.join()
    assert after == [before]
