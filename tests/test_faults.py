"""Drive faults on the executor, written once and run on both transports.

Each run starts at the entry of a planned dig (a session restored with the dig pending) and
injects a fault while it runs; the executor stops every other axis with the guard's jerk-limited
stop. Transports (``transport`` fixture, see ``conftest.py``):

* ``lockstep``: the HIL in this process on simulated time, the rig's own timeouts; exact
  (deterministic), so the order of reactions and the detection time are asserted tightly.
* ``bridge``: the HIL in its own process over 127.0.0.1 on the wall clock, with the bridge's
  patience (:data:`conftest.BRIDGE_PATIENCE_S`: watchdog and heartbeat timeouts 0.5 s, stale
  feedback 100 cycles); which of two reactions comes first depends on this machine's
  scheduling, and timing bounds carry the patience and a scheduling slack.

The stopped axes are checked on the RPDO1 frames of the whole bus (every frame, every axis,
within the limits) and on the plant's true rates at the end.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from conftest import (
    BRIDGE_PATIENCE_S,
    Fault,
    FaultRun,
    rpdo1_limit_check,
    run_on_bridge,
    run_on_lockstep,
)

from hil_sim.sim import FaultKind
from rt_runtime.canbus import CycleStatus, DriveState
from rt_runtime.control.executor import ExecStatus
from rt_runtime.control.guard import StrokeLimits
from rt_runtime.planning.trench import TrenchPlanner
from rt_runtime.rig import Rig, load_rig

Pending = tuple[TrenchPlanner, Any, dict[str, Any]]
Runner = Callable[[Rig, Pending, Fault], FaultRun]


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


class Transport:
    """How a fault run is made on one transport and what its timing allows.

    Attributes:
        name: ``lockstep`` or ``bridge``.
        run: Runs the pending dig with a fault.
        exact: Deterministic (simulated time): the order of reactions is fixed.
        heartbeat_timeout_s: The heartbeat timeouts in force (both ways).
        slack_s: What a detection time may exceed its timeout by (a heartbeat period in
            lockstep; scheduling on the bridge).
    """

    def __init__(self, name: str, rig: Rig) -> None:
        self.name = name
        self.exact = name == "lockstep"
        self.run: Runner = run_on_lockstep if self.exact else run_on_bridge
        self.heartbeat_timeout_s = (
            rig.drives.heartbeat_timeout_s if self.exact else (BRIDGE_PATIENCE_S)
        )
        self.slack_s = 0.01 if self.exact else 0.1


@pytest.fixture(params=["lockstep", "bridge"])
def transport(request: pytest.FixtureRequest, rig: Rig) -> Transport:
    return Transport(request.param, rig)


def _assert_others_stopped(run: FaultRun, rig: Rig, faulty: int) -> None:
    res = run.result
    assert res.status is ExecStatus.FAULT, res.fault
    tel = res.telemetry
    assert not tel["tracking"][-1]
    check = rpdo1_limit_check(rig, run.frames)
    for axis in range(3):
        # Every frame, for every axis (the faulted drive ignores them), within the limits.
        assert check.velocity[axis] <= 1.0 and check.acceleration[axis] <= 1.0, check
        assert check.jerk[axis] <= 1.0, check
        if axis == faulty:
            continue
        # The guard's stop ran to its end: still enabled, at rest (< 1 mm/s), both as the
        # plant's truth and as the drive last reported (a late TPDO leaves a row NaN).
        assert tel["drive_state"][-1, axis] == DriveState.OPERATION_ENABLED, tel["drive_state"][-1]
        assert abs(run.rest_rate_m_s[axis]) < 1e-3, (axis, run.rest_rate_m_s)
        vel = tel["vel_fb_m_s"][:, axis]
        assert abs(vel[np.isfinite(vel)][-1]) < 1e-3, (axis, vel[np.isfinite(vel)][-1])
    # A jerk-limited stop from the streamed speed: no longer than the guard's stop time.
    v_max, a_max, j_max = StrokeLimits.from_rig(rig).as_arrays()
    stop_cycles = int(np.count_nonzero(tel["phase"] == 8))
    assert stop_cycles * 0.002 <= float(np.max(v_max / a_max + 2 * a_max / j_max)) + 0.3


def test_following_error_reaches_the_master_and_the_others_stop(
    transport: Transport, rig: Rig, pending: Any
) -> None:
    stick = 1
    run = transport.run(rig, pending, (FaultKind.FOLLOWING_ERROR, stick, 0.6))
    assert run.injected
    res = run.result
    tel = res.telemetry
    codes = {(e.node_id, int(e.code)) for e in res.emcys}
    monitor = "following error on the stick axis" in res.fault
    drive = (2, 0x8611) in codes
    if transport.exact:
        # The executor's own following-error monitor trips first, the drive's check (0x8611)
        # follows while the guard's stop still moves the demand.
        assert monitor, res.fault
        assert drive, codes
        assert run.master.feedback.error_code[stick] == 0x8611
    else:
        # Which trips first depends on scheduling; one of them stops the run.
        assert monitor or drive, (res.fault, codes)
    assert (tel["drive_state"][:, stick] == DriveState.FAULT).any()
    assert CycleStatus.DRIVE_FAULT in tel["cycle_status"].tolist()
    _assert_others_stopped(run, rig, stick)


def test_master_heartbeat_loss_faults_the_drive_and_the_others_stop(
    transport: Transport, rig: Rig, pending: Any
) -> None:
    bucket = 2
    run = transport.run(rig, pending, (FaultKind.HEARTBEAT_LOSS, bucket, 0.5))
    assert run.injected
    res = run.result
    codes = {(e.node_id, int(e.code)) for e in res.emcys}
    assert (3, 0x8130) in codes
    tel = res.telemetry
    assert (tel["drive_state"][:, bucket] == DriveState.FAULT).any()
    # Detected within the consumer timeout and a heartbeat period (plus scheduling).
    first_fault = int(np.argmax(tel["cycle_status"] >= CycleStatus.EMCY))
    assert first_fault * 0.002 - 0.5 <= transport.heartbeat_timeout_s + transport.slack_s
    _assert_others_stopped(run, rig, bucket)


def test_a_silent_drive_is_lost_by_the_master_and_the_others_stop(
    transport: Transport, rig: Rig, pending: Any
) -> None:
    boom = 0
    run = transport.run(rig, pending, (FaultKind.NODE_SILENT, boom, 0.5))
    assert run.injected
    tel = run.result.telemetry
    assert CycleStatus.HEARTBEAT_LOST in tel["cycle_status"].tolist()
    assert run.master.feedback.heartbeat_lost[boom]
    assert np.isnan(tel["stroke_fb_m"][-1, boom])
    _assert_others_stopped(run, rig, boom)


# -- the wire's faults, on both transports (the bridge's HIL process passes every frame through
# the same fault model as the lockstep transport) -------------------------------------------------


def test_a_lossy_wire_to_a_drive_is_ridden_through_and_counted(
    transport: Transport, rig: Rig, pending: Any
) -> None:
    """Two percent of the frames to and from the boom's drive lost from 0.3 s on (no run of
    losses as long as a heartbeat timeout, at these odds): the dig runs to its end, the master
    counting the TPDO1s it missed."""
    run = transport.run(rig, pending, (FaultKind.FRAME_LOSS, 0, 0.3, 0.02))
    assert run.injected
    assert run.result.status is ExecStatus.DONE, run.result.fault
    # (The trace is the wire past the losses, where a lost setpoint shows as a double step: its
    # limits are the commanded stream's, checked by the other tests.)
    assert run.master.feedback.counts.missed_tpdo1 > 0, run.master.feedback.counts.to_json()


def test_an_unplugged_bus_stops_the_dig_and_every_axis_comes_to_rest(
    transport: Transport, rig: Rig, pending: Any
) -> None:
    """The whole bus unplugged for longer than the stale-feedback limit and the drives' SYNC
    watchdog (with the bridge's patience): the master loses its feedback and stops with the
    guard's jerk-limited stop, nothing commanded leaving the limits. (The plant's rest is not
    asserted: its truth is sampled at the SYNCs that reach the HIL, and none does while the
    bus is unplugged; the drives' own stop on their watchdog is ``test_campaign.py``'s.)"""
    unplugged_s = 0.8 if transport.exact else 1.5
    run = transport.run(rig, pending, (FaultKind.BUS_UNPLUGGED, -1, 0.5, unplugged_s))
    assert run.injected
    res = run.result
    assert res.status is ExecStatus.FAULT, res.fault
    statuses = set(res.telemetry["cycle_status"].tolist())
    assert statuses & {CycleStatus.STALE, CycleStatus.HEARTBEAT_LOST}, statuses
    check = rpdo1_limit_check(rig, run.frames)
    assert max(check.velocity) <= 1.0 and max(check.acceleration) <= 1.0, check
    assert max(check.jerk) <= 1.0, check
    assert "stale feedback" in res.fault or "heartbeat" in res.fault, res.fault


@pytest.mark.parametrize("fault", ["bus_off:bus:1.0", "loop_stall:host:1.0"])
def test_the_real_time_hil_refuses_the_faults_of_the_rig_pcs_side(
    fault: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The adapter's bus-off and the host's faults act in the master's process: the real-time
    HIL refuses them by name before anything moves, pointing to lockstep."""
    from rt_runtime.entry import main

    argv = ["hil", "--realtime", "--inject", fault, "--max-digs", "1", "--json"]
    assert main(argv) == 2
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "error" and fault.split(":")[0] in out["error"], out
    assert "lockstep" in out["error"], out
