"""The executor on the lockstep HIL: a job completes and records, every stop is a guard stop.

Each run starts a session restored from a state (the first dig of task A planned once per
module, pending) with the HIL at the dig's entry, so a run is one dig plus its exit moves. Limits
are checked on the RPDO1 frames of the bus (:func:`check_setpoint_trace`: finite differences over
spans, exact up to the micrometre rounding). The planner process is exercised once, with the
lockstep clock marked real time (the loop holds at the dig's exit while the process plans the
next dig and its cycle; time in the simulation does not wait for it).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from conftest import restore_pending, rpdo1_limit_check

from hil_sim.harness.lockstep import LockstepHil
from hil_sim.harness.scenario import NO_RT
from hil_sim.scanner import ProfileScanner
from hil_sim.sim import FaultKind
from hil_sim.terrain import Terrain
from rt_runtime.canbus import CanMaster
from rt_runtime.control import FixedRateLoop, LoopConfig, OverrunPolicy
from rt_runtime.control.executor import (
    DigRecord,
    ExecStatus,
    Executor,
    ExecutorConfig,
    ExecutorResult,
    Phase,
    StopRequest,
    executor_telemetry,
)
from rt_runtime.control.guard import GuardState, TraceCheck
from rt_runtime.errors import ConfigurationError, DriveFault, PlanningError
from rt_runtime.planning.trench import TrenchPlanner, TrenchSession, TrenchTask
from rt_runtime.rig import Rig, load_rig

PERIOD_S = 0.002


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


@pytest.fixture(scope="module")
def planner(pending: tuple[TrenchPlanner, TrenchTask, dict[str, Any]]) -> TrenchPlanner:
    return pending[0]


@pytest.fixture(scope="module")
def task(pending: tuple[TrenchPlanner, TrenchTask, dict[str, Any]]) -> TrenchTask:
    return pending[1]


@pytest.fixture(scope="module")
def pending_state(pending: tuple[TrenchPlanner, TrenchTask, dict[str, Any]]) -> dict[str, Any]:
    return json.loads(json.dumps(pending[2]))


class _Run:
    """One executor run on a fresh lockstep HIL."""

    def __init__(
        self,
        rig: Rig,
        session: TrenchSession,
        q0: np.ndarray,
        *,
        config: ExecutorConfig | None = None,
        on_cycle: Callable[[_Run, int, float], None] | None = None,
        wrap_clock: Callable[[Any], Any] | None = None,
        loop_config: LoopConfig | None = None,
        terrain: bool = True,
        cut: bool = True,
        surface_source: Callable[[_Run], Any] | None = None,
    ) -> None:
        self.session = session
        ground = Terrain(rig.ground_y_m, (session.x_lo, session.x_hi), rig.bucket.width_m)
        self.ground = ground
        self.hil = LockstepHil(rig, q0, ground if terrain else None, keep_frames=True)
        self.master = CanMaster(self.hil.master_bus, rig, period_s=PERIOD_S)
        self.master.boot(self.hil.clock.now, 1.0)
        self.master.enable(self.hil.clock.now, 1.0)
        clock = self.hil.clock if wrap_clock is None else wrap_clock(self.hil.clock)
        self.loop = FixedRateLoop(
            clock, loop_config or LoopConfig(rt=NO_RT), executor_telemetry(40_000)
        )
        self.records: list[DigRecord] = []
        self.start_s: float | None = None

        def dig_done(record: DigRecord) -> None:
            self.records.append(record)
            if cut:
                self.hil.core.cut(record.sync_first, record.sync_last)

        def cycle(sync: int, now_s: float) -> None:
            if self.start_s is None:
                self.start_s = now_s
            if on_cycle is not None:
                on_cycle(self, sync, now_s)

        self.executor = Executor(
            self.master,
            rig,
            self.loop,
            session,
            config or ExecutorConfig(max_digs=1),
            on_dig_done=dig_done,
            on_cycle=cycle,
            surface_source=None if surface_source is None else lambda: surface_source(self),
        )
        self.result: ExecutorResult = self.executor.run()
        self.hil.close()

    def trace_check(self, rig: Rig) -> TraceCheck:
        return rpdo1_limit_check(rig, self.hil.core.frames)

    def phases(self) -> list[Phase]:
        """The phases in order, consecutive repeats merged."""
        ph = self.result.telemetry["phase"]
        keep = np.concatenate([[True], np.diff(ph) != 0])
        return [Phase(int(p)) for p in ph[keep]]


def _restore(planner: TrenchPlanner, task: TrenchTask, state: dict[str, Any]) -> TrenchSession:
    return TrenchSession.restore(planner, task, json.loads(json.dumps(state)))


def _restore_pending(
    planner: TrenchPlanner, task: TrenchTask, state: dict[str, Any]
) -> tuple[TrenchSession, np.ndarray]:
    """The pending dig's session restored from a JSON copy of ``state``, and its entry pose."""
    return restore_pending(planner, task, json.loads(json.dumps(state)))


def _assert_at_rest(run: _Run, rig: Rig) -> None:
    check = run.trace_check(rig)
    assert check.ok, check
    assert np.abs(run.hil.core.plant.stroke_rate_m_s).max() < 1e-3
    assert run.executor.guard.at_rest


@pytest.fixture(scope="module")
def first_run(
    rig: Rig, planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> _Run:
    session, q0 = _restore_pending(planner, task, pending_state)
    return _Run(rig, session, q0)


# -- a job ---------------------------------------------------------------------------------------


def test_session_state_round_trips(
    planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> None:
    session = _restore(planner, task, pending_state)
    again = json.loads(json.dumps(session.state()))
    assert again["pending"] == pending_state["pending"]
    assert again["steps"] == pending_state["steps"]
    assert again["surface_m"] == pending_state["surface_m"]
    assert session.material.area == pytest.approx(planner.start(task).material.area, rel=1e-12)
    with pytest.raises(ConfigurationError, match="'rig'"):
        TrenchSession.restore(planner, task, {**pending_state, "rig": "field_excavator"})
    with pytest.raises(ConfigurationError, match="version"):
        TrenchSession.restore(planner, task, {**pending_state, "version": 99})


def test_a_short_job_completes_and_records(first_run: _Run, rig: Rig) -> None:
    res = first_run.result
    assert res.status is ExecStatus.DONE, res.fault
    assert res.overruns == 0
    assert [r.index for r in res.digs] == [0] and first_run.records == list(res.digs)
    record = res.digs[0]
    assert record.dig_type == "downward"
    assert 0 < record.sync_first < record.sync_last
    n_sync = record.sync_last - record.sync_first + 1
    assert n_sync == int(np.ceil(record.T_s / PERIOD_S - 1e-9)) + 1
    assert record.tip_path_m.shape == (n_sync, 2)
    assert record.measured_volume_m3 == pytest.approx(record.planned_volume_m3, rel=0.05)
    json.dumps(record.session_state)
    assert record.session_state["digs_done"] == 1 and record.session_state["pending"] is None
    # Planned in the first cycle (in-process, simulated time); connect (measured pose ->
    # entry, micrometres), the dig, lift-out, dump, hold.
    assert first_run.phases() == [
        Phase.CONNECT,
        Phase.DIG,
        Phase.LIFT_OUT,
        Phase.DUMP,
        Phase.SETTLE,
    ]
    tel = res.telemetry
    # A verified plan passes the guard unchanged, everywhere.
    assert (tel["guard"][tel["tracking"]] == GuardState.PASSTHROUGH).all()
    _assert_at_rest(first_run, rig)
    progress = first_run.executor.progress()
    assert progress["status"] == "done" and progress["digs_done"] == 1


def test_resume_from_a_restored_state_digs_the_next_dig(
    first_run: _Run, rig: Rig, planner: TrenchPlanner, task: TrenchTask
) -> None:
    state = first_run.result.digs[0].session_state
    session = _restore(planner, task, state)
    assert session.pending is None and len(session.digs) == 1
    # The arm where the first dig ended: in the material, so the run lifts out first.
    q_end = np.asarray(session.digs[0].problem.q_end_rad)
    run = _Run(rig, session, q_end)
    res = run.result
    assert res.status is ExecStatus.DONE, res.fault
    assert [r.index for r in res.digs] == [1]
    assert res.digs[0].session_state["digs_done"] == 2
    # One cycle from the measured pose: lift out, dump, approach and enter; after the dig (the
    # job's last) its exit.
    assert run.phases()[:6] == [
        Phase.LIFT_OUT,
        Phase.DUMP,
        Phase.APPROACH,
        Phase.ENTER,
        Phase.DIG,
        Phase.LIFT_OUT,
    ]
    _assert_at_rest(run, rig)


_CYCLE_PHASES = (Phase.LIFT_OUT, Phase.DUMP, Phase.APPROACH, Phase.ENTER)


def _from_the_first_exit(first_run: _Run, planner: TrenchPlanner, task: TrenchTask) -> tuple[
    TrenchSession, np.ndarray
]:
    """The session after the first dig and the dig's exit pose (the arm in the material)."""
    session = _restore(planner, task, first_run.result.digs[0].session_state)
    return session, np.asarray(session.digs[0].problem.q_end_rad)


def test_the_cycle_from_a_measured_pose_streams_as_one_blended_motion(
    first_run: _Run, rig: Rig, planner: TrenchPlanner, task: TrenchTask
) -> None:
    session, q_end = _from_the_first_exit(first_run, planner, task)
    run = _Run(rig, session, q_end)
    assert run.result.status is ExecStatus.DONE, run.result.fault
    tel = run.result.telemetry
    moving = np.isin(tel["phase"], [int(p) for p in _CYCLE_PHASES])
    first_dig = int(np.argmax(tel["phase"] == Phase.DIG))
    cycle = moving[:first_dig]
    # One motion (one segment) passing through the four phases in order, through the guard
    # unchanged.
    assert len(np.unique(tel["segment"][:first_dig][cycle])) == 1
    assert run.phases()[:5] == [*_CYCLE_PHASES, Phase.DIG]
    assert (tel["guard"][:first_dig][cycle] == GuardState.PASSTHROUGH).all()
    _assert_at_rest(run, rig)


@pytest.mark.parametrize("stop", ["fault", "cancel"])
def test_a_stop_during_a_blended_cycle_is_the_guard_stop_within_limits(
    first_run: _Run, rig: Rig, planner: TrenchPlanner, task: TrenchTask, stop: str
) -> None:
    session, q_end = _from_the_first_exit(first_run, planner, task)
    stick = 1
    seen: dict[str, Phase] = {}

    def act(run: _Run, _sync: int, now_s: float) -> None:
        assert run.start_s is not None
        if now_s - run.start_s < 4.0 or seen:
            return
        stream = run.executor.job.stream
        assert stream is not None
        seen["phase"] = stream.phase
        if stop == "fault":
            run.hil.inject(FaultKind.FOLLOWING_ERROR, stick)
        else:
            run.executor.request_stop(StopRequest.CANCEL)

    config = ExecutorConfig(max_digs=1, following_error_m=1e-3)
    run = _Run(rig, session, q_end, config=config, on_cycle=act, terrain=False)
    res = run.result
    # The stop came in the middle of the cycle, the arm moving.
    assert seen["phase"] in _CYCLE_PHASES
    if stop == "fault":
        assert res.status is ExecStatus.FAULT
        assert res.fault.startswith("following error on the stick axis"), res.fault
    else:
        assert res.status is ExecStatus.CANCELLED, res.fault
    tel = res.telemetry
    stopping = tel["phase"] == Phase.STOP
    first = int(np.argmax(stopping))
    assert stopping[-1] and Phase(int(tel["phase"][first - 1])) in _CYCLE_PHASES
    assert np.abs(tel["vel_cmd_m_s"][first - 1]).max() > 1e-3
    assert not (tel["phase"] == Phase.DIG).any()
    assert res.digs == ()
    check = run.trace_check(rig)
    assert check.ok, check
    rates = run.hil.core.plant.stroke_rate_m_s
    for axis in (0, 2) if stop == "fault" else (0, 1, 2):
        assert abs(rates[axis]) < 1e-3, rates


def test_pause_takes_effect_at_the_next_motion_boundary(
    rig: Rig, planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> None:
    session, q0 = _restore_pending(planner, task, pending_state)
    seen: dict[str, float] = {}

    def pause_then_resume(run: _Run, _sync: int, now_s: float) -> None:
        assert run.start_s is not None
        t = now_s - run.start_s
        if "paused" not in seen and t >= 1.0:  # mid-dig
            run.executor.pause()
            seen["paused"] = t
        if run.executor.progress()["phase"] == "wait" and "held" not in seen:
            seen["held"] = t
        if "held" in seen and "resumed" not in seen and t >= seen["held"] + 0.5:
            run.executor.resume()
            seen["resumed"] = t

    run = _Run(rig, session, q0, on_cycle=pause_then_resume, terrain=False)
    assert run.result.status is ExecStatus.DONE, run.result.fault
    # The dig ran to its end, the arm held (at rest, at the dig's exit) until resumed.
    assert run.phases() == [
        Phase.CONNECT,
        Phase.DIG,
        Phase.WAIT,
        Phase.LIFT_OUT,
        Phase.DUMP,
        Phase.SETTLE,
    ]
    tel = run.result.telemetry
    wait = tel["phase"] == Phase.WAIT
    # Held 0.5 s from when progress() first said "wait": it is published every 64 cycles,
    # so the hold seen in the telemetry is up to 64 cycles longer.
    assert 0.45 <= wait.sum() * PERIOD_S <= 0.5 + 65 * PERIOD_S
    assert np.abs(tel["vel_cmd_m_s"][wait]).max() < 1e-12
    assert not run.executor.progress()["paused"]


# -- stops ---------------------------------------------------------------------------------------


def test_cancel_mid_dig_is_a_jerk_limited_stop(
    rig: Rig, planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> None:
    session, q0 = _restore_pending(planner, task, pending_state)

    def cancel(run: _Run, _sync: int, now_s: float) -> None:
        assert run.start_s is not None
        if now_s - run.start_s >= 1.5:
            run.executor.request_stop(StopRequest.CANCEL)

    run = _Run(rig, session, q0, on_cycle=cancel, terrain=False)
    res = run.result
    assert res.status is ExecStatus.CANCELLED, res.fault
    assert res.digs == () and session.pending is not None
    tel = res.telemetry
    stop = tel["phase"] == Phase.STOP
    assert stop.any() and stop[-1]
    # Stopped from dig speed: the stop took cycles, and the command was moving when it began.
    first = int(np.argmax(stop))
    assert np.abs(tel["vel_cmd_m_s"][first - 1]).max() > 1e-3
    assert stop.sum() > 100
    _assert_at_rest(run, rig)
    assert run.executor.progress()["status"] == "cancelled"


def test_an_injected_following_error_stops_the_other_axes_within_limits(
    rig: Rig, planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> None:
    session, q0 = _restore_pending(planner, task, pending_state)
    stick = 1

    def jam(run: _Run, _sync: int, now_s: float) -> None:
        assert run.start_s is not None
        if now_s - run.start_s >= 1.0 and not run.hil.core.nodes[stick].faults.jammed:
            run.hil.inject(FaultKind.FOLLOWING_ERROR, stick)

    config = ExecutorConfig(max_digs=1, following_error_m=1e-3)
    run = _Run(rig, session, q0, config=config, on_cycle=jam, terrain=False)
    res = run.result
    assert res.status is ExecStatus.FAULT
    assert res.fault.startswith("following error on the stick axis"), res.fault
    tel = res.telemetry
    # The executor's monitor (1 mm) stopped the job before the drive's own window (5 mm).
    stop_row = int(np.argmax(tel["phase"] == Phase.STOP))
    drive_fault = tel["drive_state"][:, stick] == 7
    assert not drive_fault[:stop_row].any()
    check = run.trace_check(rig)
    assert check.ok, check
    rates = run.hil.core.plant.stroke_rate_m_s
    for axis in (0, 2):
        assert abs(rates[axis]) < 1e-3, rates
        assert tel["drive_state"][-1, axis] == 4  # OPERATION_ENABLED until disabled at the end


class _WrappedClock:
    """The lockstep clock, declared real time or not (``realtime``: the executor plans in its
    planner process), oversleeping every deadline by 1.2 periods from ``stall_at_s`` on (never
    if None)."""

    def __init__(
        self, inner: Any, *, realtime: bool = False, stall_at_s: float | None = None
    ) -> None:
        self.inner = inner
        self.realtime = realtime
        self.stall_at_s = stall_at_s

    def now(self) -> float:
        return float(self.inner.now())

    def sleep_until(self, t_s: float) -> None:
        if self.stall_at_s is None:
            self.inner.sleep_until(t_s)
            return
        late = 1.2 * PERIOD_S if t_s >= self.stall_at_s else 0.0
        self.inner.sleep_until(t_s + late)


def test_a_stalling_clock_leads_to_an_overrun_safe_stop(
    rig: Rig, planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> None:
    session, q0 = _restore_pending(planner, task, pending_state)
    run = _Run(
        rig,
        session,
        q0,
        wrap_clock=lambda clock: _WrappedClock(clock, stall_at_s=clock.now() + 1.0),
        loop_config=LoopConfig(rt=NO_RT, overrun=OverrunPolicy(max_consecutive=5)),
        terrain=False,
    )
    res = run.result
    assert res.status is ExecStatus.OVERRUN_STOP, res.fault
    assert res.loop.safe_stop and res.overruns >= 5
    assert "consecutive loop overruns" in res.fault
    _assert_at_rest(run, rig)


# -- the planner process -------------------------------------------------------------------------


def _two_digs_in_the_planner_process(
    rig: Rig, session: TrenchSession, q0: np.ndarray, **kwargs: Any
) -> _Run:
    """Two digs with the planner process (the lockstep clock marked real time). The HIL's
    terrain is not cut in on_dig_done: it runs on the callback thread, and the lockstep HIL is
    single-threaded."""
    return _Run(
        rig,
        session,
        q0,
        config=ExecutorConfig(max_digs=2),
        wrap_clock=lambda clock: _WrappedClock(clock, realtime=True),
        cut=False,
        **kwargs,
    )


def test_the_planner_process_plans_on_the_profile_scanners_surface(
    rig: Rig, planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> None:
    # The real-time path (the daemon's): the scanner's surface after each dig goes with the
    # record to the planner process, which plans the next dig on it, not on the tip path.
    session, q0 = _restore_pending(planner, task, pending_state)
    assert rig.hil is not None and rig.hil.scanner is not None
    scans: list[tuple[np.ndarray, np.ndarray]] = []
    looked = [0]
    scanner: list[ProfileScanner] = []

    def scan(run: _Run) -> tuple[np.ndarray, np.ndarray]:
        # On the loop's thread as the record is queued: the terrain cut by the true tip path
        # since the last look, then scanned (as the lockstep HIL's scanner does).
        if not scanner:
            scanner.append(ProfileScanner(run.ground, rig.hil.scanner, seed=3))
        now = run.hil.core.sync_count
        run.hil.core.cut(looked[0] + 1, now)
        looked[0] = now
        scans.append(scanner[0].scan())
        return scans[-1]

    run = _two_digs_in_the_planner_process(rig, session, q0, surface_source=scan)
    res = run.result
    assert run.executor.plan_in_worker
    assert res.status is ExecStatus.DONE, res.fault
    assert [r.index for r in res.digs] == [0, 1] and len(scans) == 2
    # Each record's state (the process's session) holds the material below that record's
    # scan; the next dig was planned on it, not ahead on the predicted material.
    for record, (x, y) in zip(res.digs, scans, strict=True):
        g = session.ground_y
        want = np.minimum(np.interp(session.grid, x, y, left=g, right=g), g)
        np.testing.assert_allclose(record.session_state["surface_m"], want, atol=1e-12)
    assert not res.digs[1].planned_ahead
    # The parent's session caught up with the process's, scanned surface included.
    np.testing.assert_allclose(session.surface, res.digs[1].session_state["surface_m"])


def test_the_next_dig_is_planned_in_the_planner_process(
    rig: Rig, planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> None:
    session, q0 = _restore_pending(planner, task, pending_state)
    run = _two_digs_in_the_planner_process(rig, session, q0)
    res = run.result
    assert run.executor.plan_in_worker
    assert res.status is ExecStatus.DONE, res.fault
    assert [r.index for r in res.digs] == [0, 1] and len(run.records) == 2
    assert [r.session_state["digs_done"] for r in res.digs] == [1, 2]
    assert res.overruns == 0
    # The parent's session caught up with the process's after the run.
    assert len(session.digs) == 2 and session.pending is None
    # The second dig and its cycle were planned while the arm held at the first dig's exit
    # (WAIT), then the cycle streamed through its four phases.
    phases = run.phases()
    dig_at = [i for i, p in enumerate(phases) if p is Phase.DIG]
    assert len(dig_at) == 2
    between = [p for p in phases[dig_at[0] : dig_at[1]] if p is not Phase.WAIT]
    assert between == [Phase.DIG, Phase.LIFT_OUT, Phase.DUMP, Phase.APPROACH, Phase.ENTER]
    _assert_at_rest(run, rig)


# -- configuration -------------------------------------------------------------------------------


def test_bad_configuration_is_refused(
    rig: Rig, planner: TrenchPlanner, task: TrenchTask, pending_state: dict[str, Any]
) -> None:
    with pytest.raises(ConfigurationError, match="stale_cycles"):
        ExecutorConfig(stale_cycles=0)
    with pytest.raises(ConfigurationError, match="following_error_m"):
        ExecutorConfig(following_error_m=-1.0)
    session, q0 = _restore_pending(planner, task, pending_state)
    hil = LockstepHil(rig, q0)
    master = CanMaster(hil.master_bus, rig, period_s=PERIOD_S)
    loop = FixedRateLoop(hil.clock, LoopConfig(period_s=0.001, rt=NO_RT))
    with pytest.raises(ConfigurationError, match="period"):
        Executor(master, rig, loop, session)
    loop = FixedRateLoop(hil.clock, LoopConfig(rt=NO_RT))
    executor = Executor(master, rig, loop, session)
    assert {"stroke_cmd_m", "stroke_fb_m"} <= {c.name for c in loop.telemetry.columns}
    with pytest.raises(DriveFault, match="OPERATION_ENABLED"):
        executor.run()  # not booted, not enabled: nothing is sent
    with pytest.raises(PlanningError, match="once"):
        executor.run()
    hil.close()


def test_a_pending_scan_is_fetched_once_and_a_failed_one_leaves_the_tip_paths(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from rt_runtime.control.planner_worker import PendingScan, _fetched

    x, y = np.linspace(0.0, 1.0, 5), np.full(5, -0.25)
    calls: list[int] = []

    def fetch() -> tuple[np.ndarray, np.ndarray]:
        calls.append(1)
        return x, y

    got = _fetched(PendingScan(fetch))
    assert got is not None and calls == [1]
    np.testing.assert_array_equal(got[0], x)
    assert got[0] is not x  # a copy goes to the planner process
    assert _fetched(PendingScan(lambda: None)) is None

    def broken() -> tuple[np.ndarray, np.ndarray]:
        raise TimeoutError("no scan within 5 s")

    with caplog.at_level("ERROR"):
        assert _fetched(PendingScan(broken)) is None
    assert "scanner" in caplog.text and "no scan within 5 s" in caplog.text
