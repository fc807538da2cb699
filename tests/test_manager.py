"""The controller manager on the lockstep HIL: a switch between controllers happens at a cycle
boundary with no gap in the SYNC stream, and no cycle ever calls a planner (in-process planning
runs in the loop's idle hook, between cycles)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import restore_pending

from hil_sim.harness.lockstep import LockstepHil
from hil_sim.harness.scenario import NO_RT
from hil_sim.sim import COB_SYNC
from rt_runtime import actuation
from rt_runtime.canbus import CanMaster
from rt_runtime.control import FixedRateLoop, LoopConfig
from rt_runtime.control.controllers import ControllerStatus, GuardFilter, HoldController
from rt_runtime.control.executor import ExecStatus, Executor, ExecutorConfig, Phase
from rt_runtime.control.guard import LimitGuard, StrokeLimits
from rt_runtime.control.hardware import DriveInterface
from rt_runtime.control.job import JobController, JobLimits
from rt_runtime.control.manager import ControllerManager, executor_telemetry
from rt_runtime.control.planner_worker import InlinePlanner
from rt_runtime.planning.trench import TrenchPlanner, TrenchSession
from rt_runtime.rig import Rig, load_rig

PERIOD_S = 0.002


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


def _enabled(hil: LockstepHil, rig: Rig) -> tuple[CanMaster, FixedRateLoop]:
    """The HIL's drives booted and enabled by a master (its own fault reaction off), and a
    loop on the HIL's clock."""
    master = CanMaster(hil.master_bus, rig, period_s=PERIOD_S, react_to_faults=False)
    master.boot(hil.clock.now, 1.0)
    master.enable(hil.clock.now, 1.0)
    return master, FixedRateLoop(hil.clock, LoopConfig(rt=NO_RT), executor_telemetry(20_000))


def _record_syncs(hil: LockstepHil) -> list[float]:
    """The simulated times at which the HIL's drives receive each SYNC."""
    times: list[float] = []
    on_frame = hil.core.on_frame

    def spy(cob: int, data: bytes, now: float) -> Any:
        if cob == COB_SYNC:
            times.append(now)
        return on_frame(cob, data, now)

    hil.core.on_frame = spy  # type: ignore[method-assign]
    return times


def test_a_switch_hold_to_job_to_hold_keeps_the_sync_stream(rig: Rig, pending: Any) -> None:
    planner, task, state = pending
    session, q0 = restore_pending(planner, task, json.loads(json.dumps(state)))
    hil = LockstepHil(rig, q0, None)
    syncs = _record_syncs(hil)
    try:
        master, loop = _enabled(hil, rig)
        drives = DriveInterface(master, hil.clock, 0.5 * PERIOD_S)
        guard = GuardFilter(LimitGuard(StrokeLimits.from_rig(rig), PERIOD_S))
        s0 = drives.measured_stroke_m()
        guard.guard.reset(s0)
        q_hold = actuation.stroke_to_joint(rig, s0, check_limits=False)
        hold = HoldController(s0, q_hold)
        job = JobController(
            InlinePlanner(session, PERIOD_S),
            guard,
            JobLimits(4e-3, 3, 25, 5.0, 1e-3, 0.05, 1),
            rig,
            drives.axes,
            drives.describe,
            lambda record: None,
            10_000,
        )
        first = job.start(s0)  # prepared outside the loop
        back = HoldController(s0, q_hold)
        switched: dict[str, int] = {}

        def on_ended(ended: Any) -> tuple[Any, Any] | None:
            if ended is job:
                back.command.hold(guard.position_m, q_hold, Phase.WAIT)
                switched["back"] = int(master.feedback.sync_count)
                return back, back.command
            return None

        manager: ControllerManager

        def on_cycle(sync: int, _now: float) -> None:
            if sync == 100:
                manager.switch(job, first)
                switched["job"] = sync
            if "back" in switched and sync >= switched["back"] + 50:
                manager.stop()

        manager = ControllerManager(drives, guard, loop, on_cycle=on_cycle, on_ended=on_ended)
        stats = manager.run(hold, hold.command, s0, q_hold)
        tel = loop.telemetry.snapshot()
    finally:
        hil.close()
    assert job.status is ExecStatus.DONE, job.fault
    assert stats.overruns == 0
    # The job's first command went with the SYNC right after the switch; the hold's after its end.
    sync = tel["sync"]
    assert (np.diff(sync) == 1).all()
    row = int(np.flatnonzero(sync == switched["job"])[0])
    assert tel["phase"][row] == Phase.WAIT and tel["phase"][row + 1] != Phase.WAIT
    assert tel["tracking"][row + 1]
    end = int(np.flatnonzero(sync == switched["back"])[0])
    assert tel["phase"][end] == Phase.SETTLE and tel["phase"][end + 1] == Phase.WAIT
    # No gap in the SYNC stream the drives saw, across both switches.
    times = np.array(syncs[-len(sync) :])
    assert len(times) > 300
    np.testing.assert_allclose(np.diff(times), PERIOD_S, atol=1e-9)


def test_no_cycle_calls_a_planner(rig: Rig, pending: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    planner, task, state = pending
    session, q0 = restore_pending(planner, task, json.loads(json.dumps(state)))
    calls: list[tuple[str, bool]] = []
    in_cycle = [False]
    for cls, name in (
        (TrenchSession, "next_dig"),
        (TrenchSession, "record"),
        (TrenchSession, "exit_transitions"),
        (TrenchSession, "cycle"),
        (TrenchPlanner, "start"),
    ):
        original = getattr(cls, name)

        def spy(*args: Any, _original: Any = original, _name: str = name, **kw: Any) -> Any:
            calls.append((_name, in_cycle[0]))
            return _original(*args, **kw)

        monkeypatch.setattr(cls, name, spy)
    original_cycle = ControllerManager._cycle

    def cycle(self: ControllerManager, info: Any) -> Any:
        in_cycle[0] = True
        try:
            return original_cycle(self, info)
        finally:
            in_cycle[0] = False

    monkeypatch.setattr(ControllerManager, "_cycle", cycle)
    hil = LockstepHil(rig, q0, None)
    try:
        master, loop = _enabled(hil, rig)
        # Two digs: the second and its cycle are planned while the arm holds at the first's
        # exit.
        result = Executor(master, rig, loop, session, ExecutorConfig(max_digs=2)).run()
    finally:
        hil.close()
    assert result.status is ExecStatus.DONE, result.fault
    assert len(result.digs) == 2
    names = {name for name, _ in calls}
    assert {"record", "exit_transitions", "cycle"} <= names  # the planner planned, recorded...
    assert [c for c in calls if c[1]] == []  # ...never inside a cycle


def test_a_controller_that_raises_ends_in_the_guards_stop(rig: Rig, pending: Any) -> None:
    planner, task, state = pending
    session, q0 = restore_pending(planner, task, json.loads(json.dumps(state)))
    hil = LockstepHil(rig, q0, None)
    try:
        master, loop = _enabled(hil, rig)
        ex = Executor(master, rig, loop, session, ExecutorConfig(max_digs=1))
        original = ex.job.update
        count = [0]

        def update(*args: Any) -> tuple[Any, ControllerStatus]:
            count[0] += 1
            if count[0] == 400:  # mid-dig
                raise RuntimeError("a bug")
            return original(*args)

        ex.job.update = update  # type: ignore[method-assign]
        result = ex.run()
    finally:
        hil.close()
    assert result.status is ExecStatus.FAULT
    assert "controller error: RuntimeError('a bug')" in result.fault
    assert ex.guard.at_rest
    assert (result.telemetry["phase"][-10:] == Phase.STOP).all()


class _Reached(BaseException):
    """Raised at the first cyclic RPDO1 to end the run there (a BaseException: the cycle
    takes any Exception out of the bus as a bus error)."""


def test_the_demo_reaches_its_first_cyclic_rpdo1_in_few_calls(
    tmp_path: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``excavator-rt demo`` to the first RPDO1 the loop sends: at most 12 calls of the
    project's code across at most 8 modules (the data flow of DESIGN.md, visible)."""
    import traceback

    from rt_runtime.canbus.cyclic import CyclicExchange
    from rt_runtime.cli import main

    original = CyclicExchange.tx
    chains: list[list[traceback.FrameSummary]] = []

    def spy(self: Any, msg: Any) -> None:
        if 0x201 <= msg.arbitration_id <= 0x27F:
            stack = traceback.extract_stack()
            if any(f.name == "write_setpoints" for f in stack):
                chains.append(stack)
                raise _Reached
        original(self, msg)

    monkeypatch.setattr(CyclicExchange, "tx", spy)
    with pytest.raises(_Reached):
        main(["demo", "--out", str(tmp_path), "--no-plots", "--max-digs", "1"])
    stack = chains[0]
    root = Path(__file__).resolve().parents[1]
    own = [f for f in stack if Path(f.filename).resolve().is_relative_to(root)]
    own = [f for f in own if "/tests/" not in f.filename and "site-packages" not in f.filename]
    start = next(i for i, f in enumerate(own) if f.filename.endswith("cli.py") and f.name == "main")
    chain = own[start:]
    described = [f"{Path(f.filename).name}:{f.name}" for f in chain]
    assert len(chain) <= 12, described
    assert len({f.filename for f in chain}) <= 8, described


def test_every_telemetry_column_is_written_by_the_write_or_the_read() -> None:
    from rt_runtime.control import manager

    written = manager._COMMAND_COLUMNS + manager._ANSWER_COLUMNS
    assert sorted(written) == sorted(c.name for c in manager.EXECUTOR_COLUMNS)


def test_a_hold_powers_down_inside_the_loop(rig: Rig) -> None:
    hil = LockstepHil(rig, (0.5, -1.5, -1.0), None)
    syncs = _record_syncs(hil)
    try:
        master, loop = _enabled(hil, rig)
        drives = DriveInterface(master, hil.clock, 0.0)
        guard = GuardFilter(LimitGuard(StrokeLimits.from_rig(rig), PERIOD_S))
        s0 = drives.measured_stroke_m()
        guard.guard.reset(s0)
        hold = HoldController(s0, actuation.stroke_to_joint(rig, s0, check_limits=False))

        cycles = [0]

        def on_cycle(_sync: int, _now: float) -> None:
            cycles[0] += 1
            if cycles[0] == 50:
                hold.power_down(0.5)

        manager = ControllerManager(drives, guard, loop, on_cycle=on_cycle)
        stats = manager.run(hold, hold.command, s0, hold.command.q_rad)
        tel = loop.telemetry.snapshot()
    finally:
        hil.close()
    assert stats.stopped_by_step and stats.cycles < 50 + 0.5 / PERIOD_S
    # Disabled with one command; SYNC went on at the period until no drive was enabled.
    assert (tel["drive_state"][-1] != 4).all(), tel["drive_state"][-1]
    assert (tel["drive_state"][:50] == 4).all()
    np.testing.assert_allclose(np.diff(syncs[-len(tel["sync"]) :]), PERIOD_S, atol=1e-9)
