"""The HIL contract over the 127.0.0.1 bridge, on the executor: the HIL in its own process.

The same contract as ``test_hil.py`` (boot, enable, a dig with tracking, a following error and a
lost heartbeat reaching the master as EMCY + statusword fault, the other axes brought to rest by
the executor's jerk-limited stop, a readable trace), with python-can-remote between master and
HIL and the executor's fixed-rate loop on the wall clock. The tracking run plans in the
executor's planner process (the arm holds at the entry while the process starts); the fault runs
plan in-process (the pending dig needs no planning). Each HIL process stops by itself after
``MAX_WALL_S`` even if a test dies. No assertion on timing: the round trip is printed.

The drives' SYNC/RPDO watchdog is widened to 0.5 s here, the heartbeat timeouts (both ways) to
0.5 s, the executor's stale-feedback limit to 100 cycles and the overrun policy to 50 in a row
(the rig's values are for a rig PC with SCHED_FIFO; a test machine shared with other jobs,
where the HIL process itself is not real time, stalls longer now and then): the contract under
test is the protocol and the executor's reactions, not this machine's scheduling.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from conftest import fault_on_cycle, restore_pending

from hil_sim.harness.realtime import RealtimeHilProcess
from hil_sim.scenario import NO_RT
from hil_sim.sim import FaultKind
from rt_runtime.canbus import CanMaster, CycleStatus, DriveState
from rt_runtime.control import (
    FixedRateLoop,
    LoopConfig,
    OverrunPolicy,
    RtSettings,
    apply_rt,
    restore_rt,
)
from rt_runtime.control.executor import (
    ExecStatus,
    Executor,
    ExecutorConfig,
    ExecutorResult,
    executor_telemetry,
)
from rt_runtime.planning.trench import TrenchPlanner
from rt_runtime.rig import Rig, load_rig

MAX_WALL_S = 60.0
rt: list[dict[str, Any]] = []


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


def _patient(rig: Rig) -> Rig:
    """The rig with a 0.5 s heartbeat timeout both ways (see the module docstring)."""
    return dataclasses.replace(rig, drives=dataclasses.replace(rig.drives, heartbeat_timeout_s=0.5))


def _run(
    rig: Rig,
    pending: tuple[TrenchPlanner, Any, dict[str, Any]],
    fault: tuple[FaultKind, int, float] | None = None,
    trace: Path | None = None,
) -> tuple[ExecutorResult, CanMaster, dict[str, Any], np.ndarray]:
    session, q0 = restore_pending(*pending)
    hil = RealtimeHilProcess.start(
        rig_name="scale_model",
        q0_rad=q0,
        max_wall_s=MAX_WALL_S,
        sync_timeout_s=0.5,
        trace_path=trace,
    )
    try:
        master = CanMaster(hil.master_bus, _patient(rig), period_s=0.002, react_to_faults=False)
        on_cycle, _injected = fault_on_cycle(hil, fault)
        config = ExecutorConfig(max_digs=1, plan_in_worker=fault is None, stale_cycles=100)
        loop = FixedRateLoop(
            hil.clock,
            LoopConfig(rt=NO_RT, overrun=OverrunPolicy(max_consecutive=50)),
            executor_telemetry(30_000),
        )
        # As the product does: executor (planner process) first, RT settings before boot (not
        # between enable and the first cycle), then boot, enable, run.
        executor = Executor(master, rig, loop, session, config, on_cycle=on_cycle)
        report = apply_rt(RtSettings())
        try:
            master.boot(hil.clock.now, 2.0)
            master.enable(hil.clock.now, 2.0)
            res = executor.run()
        finally:
            executor.close()
            restore_rt(report)
        rt[:] = [report.as_dict()]
        truth, _, _, extra = hil.finish()
    finally:
        hil.close()
    tel = res.telemetry
    index = {int(s): i for i, s in enumerate(truth.sync_index)}
    rows = tel["sync"] >= 1
    sel = np.array([index.get(int(s), -1) for s in tel["sync"][rows]])
    stroke_true = np.full((len(tel["sync"]), 3), np.nan)
    stroke_true[rows] = np.where((sel >= 0)[:, None], truth.stroke_m[np.maximum(sel, 0)], np.nan)
    return res, master, extra, stroke_true


def test_a_dig_over_the_bridge_tracks(rig: Rig, pending: Any, tmp_path: Path) -> None:
    trace = tmp_path / "rt.blf"
    res, master, extra, stroke_true = _run(rig, pending, trace=trace)
    assert res.status is ExecStatus.DONE, res.fault
    assert len(master.drive_info) == 3
    assert [d.index for d in res.digs] == [0]
    tel = res.telemetry
    track = tel["tracking"]
    err = (stroke_true - tel["stroke_ref_m"])[track]
    max_mm = np.nanmax(np.abs(err), axis=0) * 1e3
    rep = (tel["stroke_fb_m"] - tel["stroke_ref_m"])[track]
    # Bounded by the following-error window (no fault); the figure itself depends on this
    # machine's scheduling and is printed, not asserted (goal 1 mm: see the printed line).
    window_mm = rig.drives.following_error_window_m * 1e3
    assert (max_mm < window_mm).all(), max_mm
    assert (np.nanmax(np.abs(rep), axis=0) * 1e3 < window_mm).all()
    answered = np.isfinite(tel["rtt_s"])
    rtt = tel["rtt_s"][answered] * 1e6
    # Most SYNCs are answered within the read timeout (half a period) even on a busy machine.
    assert answered.mean() > 0.5, answered.mean()
    late = res.loop.lateness_s * 1e6
    print(
        f"\nSYNC -> TPDO round trip over 127.0.0.1: p50 {np.percentile(rtt, 50):.0f} us, "
        f"p99 {np.percentile(rtt, 99):.0f} us, max {rtt.max():.0f} us, answered in time "
        f"{answered.mean():.1%}; loop lateness p50 "
        f"{np.percentile(late, 50):.0f} us, p99 {np.percentile(late, 99):.0f} us, overruns "
        f"{res.overruns}; max truth error {max_mm.round(4).tolist()} mm; "
        f"rt {rt}; {extra}"
    )
    messages = list(can.BLFReader(str(trace)))
    ids = {m.arbitration_id for m in messages}
    assert {0x000, 0x080, 0x181, 0x182, 0x183, 0x201, 0x77E, 0x701} <= ids


def _assert_others_stopped(res: ExecutorResult, faulty: int) -> None:
    assert res.status is ExecStatus.FAULT, res.fault
    tel = res.telemetry
    for axis in range(3):
        if axis != faulty:
            assert tel["drive_state"][-1, axis] == DriveState.OPERATION_ENABLED
            # The last velocity the drive reported (a late TPDO leaves a row NaN).
            vel = tel["vel_fb_m_s"][:, axis]
            assert abs(vel[np.isfinite(vel)][-1]) < 1e-3


def test_following_error_over_the_bridge(rig: Rig, pending: Any) -> None:
    res, _master, _, _ = _run(rig, pending, (FaultKind.FOLLOWING_ERROR, 1, 0.4))
    tel = res.telemetry
    assert "following error on the stick axis" in res.fault or (2, 0x8611) in {
        (e.node_id, int(e.code)) for e in res.emcys
    }
    assert (tel["drive_state"][:, 1] == DriveState.FAULT).any()
    assert CycleStatus.DRIVE_FAULT in tel["cycle_status"].tolist()
    _assert_others_stopped(res, 1)


def test_heartbeat_loss_over_the_bridge(rig: Rig, pending: Any) -> None:
    res, _master, _, _ = _run(rig, pending, (FaultKind.HEARTBEAT_LOSS, 2, 0.4))
    assert (3, 0x8130) in {(e.node_id, int(e.code)) for e in res.emcys}
    assert (res.telemetry["drive_state"][:, 2] == DriveState.FAULT).any()
    _assert_others_stopped(res, 2)
