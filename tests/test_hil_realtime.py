"""The HIL contract over the 127.0.0.1 bridge: the HIL in its own process at wall-clock speed.

The same contract as ``test_hil.py`` (boot, enable, stream with tracking, a following error and a
lost heartbeat reaching the master as EMCY + statusword fault, the other axes stopping, a
readable trace), with python-can-remote between master and HIL. Each HIL process stops by itself
after ``MAX_WALL_S`` even if a test dies. No assertion on timing: the round trip is printed.

The drives' SYNC/RPDO watchdog is widened to 100 ms here (the rig's 20 ms is for a rig PC with
SCHED_FIFO; a test machine shared with other jobs stalls longer now and then): the contract under
test is the protocol, not this machine's scheduling.
"""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest

from hil_sim.realtime import RealtimeHilProcess
from hil_sim.sim import FaultKind
from rt_runtime.canbus import CanMaster, CycleStatus, DriveState
from rt_runtime.control import StreamResult, StreamStatus, TrajectoryStreamer, sextic_motion
from rt_runtime.rig import Rig, load_rig
from rt_runtime.trajectory.sextic import SexticTrajectory

MAX_WALL_S = 40.0
Q0 = np.radians([30.0, -90.0, -60.0])
Q1 = np.radians([10.0, -60.0, -110.0])


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


def _run(
    rig: Rig, fault: tuple[FaultKind, int, float] | None = None, trace: Path | None = None
) -> tuple[StreamResult, CanMaster, dict[str, object], np.ndarray]:
    hil = RealtimeHilProcess.start(
        rig_name="scale_model",
        q0_rad=Q0,
        max_wall_s=MAX_WALL_S,
        sync_timeout_s=0.1,
        trace_path=trace,
    )
    try:
        master = CanMaster(hil.master_bus, rig, period_s=0.002)
        start: list[float] = []
        injected: list[float] = []

        def on_cycle(_sync: int, now_s: float) -> None:
            if not start:
                start.append(now_s)
            if fault is not None and not injected and now_s - start[0] >= fault[2]:
                hil.inject(fault[0], fault[1])
                injected.append(now_s)

        streamer = TrajectoryStreamer(master, rig, hil.clock, on_cycle=on_cycle)
        streamer.start(timeout_s=2.0)
        res = streamer.stream(sextic_motion(SexticTrajectory(Q0, Q1, np.zeros(3), 1.5)))
        if res.status is StreamStatus.DONE:
            streamer.hold(0.02)
            streamer.shutdown()
        truth, _, _, extra = hil.finish()
    finally:
        hil.close()
    index = {int(s): i for i, s in enumerate(truth.sync_index)}
    sel = np.array([index[int(s)] for s in res.sync_index])
    return res, master, extra, truth.stroke_m[sel]


def test_stream_over_the_bridge_tracks(rig: Rig, tmp_path: Path) -> None:
    trace = tmp_path / "rt.blf"
    res, master, extra, stroke_true = _run(rig, trace=trace)
    assert res.status is StreamStatus.DONE, res.fault
    assert len(master.drive_info) == 3
    err = (stroke_true - res.stroke_ref_m)[res.tracking]
    max_mm = np.abs(err).max(axis=0) * 1e3
    rep = (res.stroke_reported_m - res.stroke_ref_m)[res.tracking]
    # Bounded by the following-error window (no fault); the figure itself depends on this
    # machine's scheduling and is printed, not asserted (goal 1 mm: see the printed line).
    window_mm = rig.drives.following_error_window_m * 1e3
    assert (max_mm < window_mm).all(), max_mm
    assert (np.nanmax(np.abs(rep), axis=0) * 1e3 < window_mm).all()
    rtt = res.rtt_s[np.isfinite(res.rtt_s)] * 1e6
    assert rtt.size > 0.9 * len(res.rtt_s)
    print(
        f"\nSYNC -> TPDO round trip over 127.0.0.1: p50 {np.percentile(rtt, 50):.0f} us, "
        f"p99 {np.percentile(rtt, 99):.0f} us, max {rtt.max():.0f} us; overruns "
        f"{res.overruns}; max truth error {max_mm.round(4).tolist()} mm; {extra}"
    )
    messages = list(can.BLFReader(str(trace)))
    ids = {m.arbitration_id for m in messages}
    assert {0x000, 0x080, 0x181, 0x182, 0x183, 0x201, 0x77E, 0x701} <= ids


def _assert_others_stopped(res: StreamResult, faulty: int) -> None:
    assert res.status is StreamStatus.FAULT, res.fault
    for axis in range(3):
        if axis != faulty:
            assert res.state[-1, axis] == DriveState.SWITCH_ON_DISABLED, res.state[-1]
            assert abs(res.velocity_reported_m_s[-1, axis]) < 1e-3


def test_following_error_over_the_bridge(rig: Rig) -> None:
    res, _master, _, _ = _run(rig, (FaultKind.FOLLOWING_ERROR, 1, 0.4))
    assert (2, 0x8611) in {(e.node_id, int(e.code)) for e in res.emcys}
    assert (res.state[:, 1] == DriveState.FAULT).any()
    assert CycleStatus.DRIVE_FAULT in res.cycle_status.tolist()
    _assert_others_stopped(res, 1)


def test_heartbeat_loss_over_the_bridge(rig: Rig) -> None:
    res, _master, _, _ = _run(rig, (FaultKind.HEARTBEAT_LOSS, 2, 0.4))
    assert (3, 0x8130) in {(e.node_id, int(e.code)) for e in res.emcys}
    assert (res.state[:, 2] == DriveState.FAULT).any()
    _assert_others_stopped(res, 2)
