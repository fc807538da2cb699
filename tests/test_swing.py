"""The swing as a fourth axis: the axis maps, the master's configuration, the guard, the HIL's
swing plant and its drive, and a four-axis run on the lockstep HIL with a fault on the swing
drive ending in a safe stop of all four axes within their limits."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hil_sim.harness.fouraxis import PERIOD_S, FourAxisRun, run_path
from hil_sim.sim import FaultKind, HilCore
from hil_sim.swing import SwingParameters, SwingPlant, swing_drive_rig, velocity_lead_s
from rt_runtime import axes
from rt_runtime.canbus import DriveState
from rt_runtime.canbus.config import DEFAULT_EDS, MasterConfig, configuration_writes, load_od
from rt_runtime.control.executor import ExecStatus
from rt_runtime.control.guard import StrokeLimits, check_setpoint_trace, rpdo1_setpoints
from rt_runtime.control.planner_worker import PathJob
from rt_runtime.control.setpoints import connect_motion
from rt_runtime.errors import ConfigurationError, JointLimitError
from rt_runtime.rig import Rig, load_rig


@pytest.fixture(scope="module")
def field() -> Rig:
    return load_rig("field_excavator")


# -- the runtime's side -----------------------------------------------------------------------


@pytest.mark.parametrize("name", ["scale_model", "test_bench", "yang_pan_excavator"])
def test_planar_rigs_keep_three_axes(name: str) -> None:
    rig = load_rig(name)
    assert axes.names(rig) == ("boom", "stick", "bucket")
    config = MasterConfig.from_rig(rig, 0x7E, 0.002)
    assert config.axes == ("boom", "stick", "bucket")
    assert StrokeLimits.from_rig(rig).n == 3
    q = np.radians([[20.0, -60.0, -40.0]]).clip(rig.q_min_rad, rig.q_max_rad)
    np.testing.assert_array_equal(axes.from_joint_order(rig, q), q)


def test_the_field_excavator_streams_four_axes_the_swing_on_node_4(field: Rig) -> None:
    config = MasterConfig.from_rig(field, 0x7E, 0.002)
    assert config.axes == ("boom", "stick", "bucket", "swing")
    assert config.node_ids == (1, 2, 3, 4)
    # The swing drive's positions are microradians: its range and window in urad.
    assert config.stroke_min_um[3] == round(-math.pi * 1e6)
    assert config.stroke_max_um[3] == round(math.pi * 1e6)
    assert config.following_error_window_um[3] == round(axes.SWING_FOLLOWING_ERROR_WINDOW_RAD * 1e6)
    assert config.quick_stop_deceleration_um_s2[3] == round(
        field.swing.joint.acceleration_max_rad_s2 * 1e6  # type: ignore[union-attr]
    )
    writes = {(w.index, w.subindex): w.value for w in configuration_writes(
        config, load_od(DEFAULT_EDS, 4), 3
    )}
    assert writes[(0x607D, 2)] == config.stroke_max_um[3]
    assert writes[(0x6065, 0)] == config.following_error_window_um[3]
    assert writes[(0x6060, 0)] == 8


def test_axis_maps_round_trip_and_reorder(field: Rig) -> None:
    rng = np.random.default_rng(3)
    lo, hi, *_ = axes.joint_limits(field)
    q = lo + (hi - lo) * rng.uniform(0.05, 0.95, (200, 4))
    s = axes.joint_to_actuator(field, q)
    np.testing.assert_array_equal(s[:, 3], q[:, 3])  # the swing's actuator is its angle
    np.testing.assert_allclose(axes.actuator_to_joint(field, s), q, atol=1e-9)
    jac = axes.actuator_jacobian(field, q)
    h = 1e-6
    fd = (axes.joint_to_actuator(field, q + h) - axes.joint_to_actuator(field, q - h)) / (2 * h)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-9)
    joint_order = axes.to_joint_order(field, q)
    np.testing.assert_array_equal(joint_order[:, 0], q[:, 3])
    np.testing.assert_array_equal(axes.from_joint_order(field, joint_order), q)
    bad = q[0].copy()
    bad[3] = math.radians(181.0)
    with pytest.raises(JointLimitError, match="swing"):
        axes.joint_to_actuator(field, bad)


def test_guard_limits_of_the_swing_are_its_joint_limits(field: Rig) -> None:
    limits = StrokeLimits.from_rig(field, margin=0.02)
    sw = field.swing.joint  # type: ignore[union-attr]
    assert limits.n == 4
    assert limits.velocity_m_s[3] == pytest.approx(sw.velocity_max_rad_s * 1.02)
    assert limits.acceleration_m_s2[3] == pytest.approx(sw.acceleration_max_rad_s2 * 1.02)
    assert limits.jerk_m_s3[3] == pytest.approx(sw.jerk_max_rad_s3 * 1.02)
    planar = StrokeLimits.from_rig(dataclasses.replace(field, swing=None), margin=0.02)
    assert limits.velocity_m_s[:3] == planar.velocity_m_s


def test_a_path_with_the_wrong_number_of_axes_is_refused_before_anything_moves(
    field: Rig,
) -> None:
    planar = load_rig("test_bench")
    q0 = np.radians([20.0, -90.0, -10.0])
    motion = connect_motion(planar, PERIOD_S, q0, q0 + 0.1)

    class Sampled:
        duration_s = motion.duration_s

        @staticmethod
        def sample(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            return q0, np.zeros(3), np.zeros(3)

    with pytest.raises(Exception, match="4 axes"):
        PathJob((Sampled(),)).check(field)


# -- the HIL's swing ----------------------------------------------------------------------------


def test_swing_inertia_grows_with_reach(field: Rig) -> None:
    plant = SwingPlant(field, 0.0)
    tucked = plant.inertia(tuple(np.radians([60.0, -150.0, -130.0])))
    stretched = plant.inertia(tuple(np.radians([0.0, -30.0, 0.0])))
    upper = plant.params.upper_inertia_kgm2
    assert upper < tucked < stretched
    # Stretched flat: every link's centre of mass at a1 + its x, the links' own inertia whole.
    a1 = field.swing.base_offset_m  # type: ignore[union-attr]
    x0 = [0.0, field.links[0].length_m, field.links[0].length_m + field.links[1].length_m]
    q = np.radians([0.0, 0.0, 0.0])
    expected = upper + sum(
        lk.mass_kg * (a1 + x0[i] + lk.com_m[0]) ** 2 + lk.inertia_kgm2
        for i, lk in enumerate(field.links)
    )
    assert plant.inertia(tuple(q)) == pytest.approx(expected, rel=1e-12)


def test_swing_conserves_angular_momentum_as_the_arm_reaches_out(field: Rig) -> None:
    # A motor without torque (electric, effort ~0: no brake) and no friction: J w is constant
    # while the arm stretches, so the swing slows down.
    params = dataclasses.replace(
        SwingParameters.from_rig(field), hydraulic=False, viscous_nm_s=0.0
    )
    plant = SwingPlant(field, 0.0, params)
    plant.omega_rad_s = 0.5
    a = np.radians([50.0, -140.0, -100.0])
    b = np.radians([0.0, -40.0, -10.0])
    n = 4000
    plant.step(2.5e-4, 1e-15, tuple(a))
    l0 = plant.inertia_kgm2 * plant.omega_rad_s
    for k in range(1, n + 1):
        plant.step(2.5e-4, 1e-15, tuple(a + (b - a) * k / n))
    l1 = plant.inertia_kgm2 * plant.omega_rad_s
    # The plant's angular rate after the reach-out (rad/s, no clock): the arm's inertia grew.
    omega_after = plant.omega_rad_s
    assert omega_after < 0.5 * 0.8
    assert l1 == pytest.approx(l0, rel=1e-3)


def test_the_plant_takes_the_upper_inertia_and_line_volume_from_the_rig(field: Rig) -> None:
    assert field.swing is not None
    base = SwingParameters.from_rig(field)
    assert base.upper_inertia_kgm2 == field.swing.upper_inertia_kgm2
    assert base.line_volume_m3 == field.swing.motor_line_volume_m3
    stretched = tuple(np.radians([0.0, -30.0, 0.0]))
    j_base = SwingPlant(field, 0.0).inertia(stretched)
    w_base = base.mode_rad_s(j_base)

    heavy_upper = 2.0 * field.swing.upper_inertia_kgm2
    heavy = dataclasses.replace(
        field, swing=dataclasses.replace(field.swing, upper_inertia_kgm2=heavy_upper)
    )
    p = SwingParameters.from_rig(heavy)
    assert p.upper_inertia_kgm2 == heavy_upper
    j_heavy = SwingPlant(heavy, 0.0).inertia(stretched)
    assert j_heavy == pytest.approx(j_base + field.swing.upper_inertia_kgm2, rel=1e-12)
    # The hydraulic mode goes as 1 / sqrt(J): slower on the heavier upper structure, and the
    # swing's velocity lead (its mode's lag 2 zeta / w_h) longer.
    w_heavy = p.mode_rad_s(j_heavy)
    assert w_heavy < w_base
    assert w_heavy == pytest.approx(w_base * math.sqrt(j_base / j_heavy), rel=1e-12)
    assert velocity_lead_s(heavy)[3] > velocity_lead_s(field)[3]
    assert velocity_lead_s(heavy)[:3] == velocity_lead_s(field)[:3]

    # Twice the oil in each line: a softer spring, the mode down by sqrt(2) at the same J.
    soft = dataclasses.replace(
        field,
        swing=dataclasses.replace(
            field.swing, motor_line_volume_m3=2.0 * field.swing.motor_line_volume_m3
        ),
    )
    p = SwingParameters.from_rig(soft)
    assert p.line_volume_m3 == 2.0 * field.swing.motor_line_volume_m3
    assert p.mode_rad_s(j_base) == pytest.approx(w_base / math.sqrt(2.0), rel=1e-12)


def test_the_swing_drive_is_the_same_firmware_on_node_4(field: Rig) -> None:
    core = HilCore(field, np.radians([20.0, -90.0, -60.0, 15.0]), vcu=False)
    assert len(core.nodes) == 4
    node = core.nodes[3]
    assert node.node_id == 4 and node.firmware.joint == "swing"
    assert type(node.firmware) is type(core.nodes[0].firmware)
    assert node.firmware.position_actual_m == pytest.approx(math.radians(15.0), abs=1e-6)
    view = swing_drive_rig(field)
    assert view.drives.encoder_resolution_m == 1e-6
    # Its valve's no-load gain is the swing's no-load rate (the firmware's valve model).
    from firmware_models.drive import valve_velocity_gains_m_s

    assert view.actuators.hydraulic is not None
    up, down = valve_velocity_gains_m_s(view.actuators.hydraulic)
    assert up == pytest.approx(SwingParameters.from_rig(field).no_load_rad_s)
    assert down == pytest.approx(up)
    with pytest.raises(ConfigurationError, match="initial pose"):
        HilCore(load_rig("test_bench"), np.radians([20.0, -90.0, -10.0, 0.0]))


# -- four axes on the lockstep HIL ---------------------------------------------------------------

Q0 = np.radians([20.0, -90.0, -60.0, 0.0])
Q1 = np.radians([26.0, -80.0, -50.0, 60.0])


class RuckigMove:
    """A rest-to-rest move over the four axes within the joint limits (ruckig, no waypoints)."""

    def __init__(self, rig: Rig, a: np.ndarray, b: np.ndarray) -> None:
        from ruckig import InputParameter, Ruckig, Trajectory

        _, _, v, acc, j = axes.joint_limits(rig)
        inp = InputParameter(4)
        inp.max_velocity, inp.max_acceleration, inp.max_jerk = v.tolist(), acc.tolist(), j.tolist()
        inp.current_position, inp.target_position = a.tolist(), b.tolist()
        self.traj = Trajectory(4)
        Ruckig(4).calculate(inp, self.traj)
        self.duration_s = float(self.traj.duration)

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p, v, a = self.traj.at_time(min(max(t, 0.0), self.duration_s))
        return np.array(p), np.array(v), np.array(a)


def _job(rig: Rig) -> PathJob:
    return PathJob((RuckigMove(rig, Q0, Q1), RuckigMove(rig, Q1, Q0)))


def _setpoint_check(rig: Rig, run: FourAxisRun):  # type: ignore[no-untyped-def]
    nodes = [dict(rig.can.node_ids)[name] for name in axes.names(rig)]
    target, velocity = rpdo1_setpoints(run.frames, nodes)
    assert target.shape[1] == 4
    return check_setpoint_trace(
        target, StrokeLimits.from_rig(rig), PERIOD_S, velocity_um_s=velocity
    )


@pytest.fixture(scope="module")
def swing_run(field: Rig) -> FourAxisRun:
    return run_path(field, _job(field), Q0, keep_frames=True)


def test_a_four_axis_path_runs_to_its_end_on_the_hil(field: Rig, swing_run: FourAxisRun) -> None:
    run = swing_run
    assert run.status == "done", run.fault
    assert run.telemetry["stroke_cmd_m"].shape[1] == 4
    # The swing went there and came back, on its own drive.
    assert math.degrees(float(np.max(run.truth.swing_rad))) > 55.0
    assert abs(math.degrees(float(run.truth.swing_rad[-1]))) < 0.5
    tr = run.tracking
    print("four-axis path:", tr.to_json())
    assert tr.swing_max_deg < axes.SWING_FOLLOWING_ERROR_WINDOW_RAD * 180 / math.pi
    assert tr.cycles > 1000
    check = _setpoint_check(field, run)
    assert check.ok, check


def test_a_fault_on_the_swing_drive_stops_all_four_axes_safely(field: Rig) -> None:
    # The swing jams 0.8 s into the move (its effort lost, braked): the drive's own following
    # error (or the executor's monitor before it) stops the job; the guard's stop brings the
    # other three to rest within their limits; the swing stands.
    jam = (FaultKind.FOLLOWING_ERROR, 3, 0.8)
    run = run_path(field, _job(field), Q0, keep_frames=True, fault=jam)
    assert run.result is not None
    assert run.result.status is ExecStatus.FAULT, run.fault
    assert "swing" in run.fault, run.fault
    tel = run.telemetry
    assert not tel["tracking"][-1]
    check = _setpoint_check(field, run)
    for axis in range(4):  # every frame to every drive within the limits, the stop included
        assert check.velocity[axis] <= 1.0 and check.acceleration[axis] <= 1.0, check
        assert check.jerk[axis] <= 1.0, check
    for axis in range(3):  # the healthy drives: still enabled, at rest
        assert tel["drive_state"][-1, axis] == DriveState.OPERATION_ENABLED
        vel = tel["vel_fb_m_s"][:, axis]
        assert abs(vel[np.isfinite(vel)][-1]) < 1e-3
    # The swing stands within its range, and it stopped within the motor's torque: the true
    # deceleration never beyond relief torque over the smallest inertia (plus the sampling).
    sw = run.truth.swing_rad
    rate = run.truth.swing_rate_rad_s
    assert abs(float(rate[-1])) < 1e-3
    assert float(np.max(np.abs(sw))) < math.pi
    params = SwingParameters.from_rig(field)
    accel = np.abs(np.diff(rate)) / PERIOD_S
    assert float(np.max(accel)) <= 1.05 * params.torque_max_nm / params.upper_inertia_kgm2
    stop_cycles = int(np.count_nonzero(tel["phase"] == 8))
    v_max, a_max, j_max = StrokeLimits.from_rig(field).as_arrays()
    assert stop_cycles * PERIOD_S <= float(np.max(v_max / a_max + 2 * a_max / j_max)) + 0.3


def test_the_velocity_lead_is_rate_plus_lead_times_acceleration_and_jerk(field: Rig) -> None:
    from hil_sim.harness.lockstep import LockstepHil
    from rt_runtime.canbus import CanMaster
    from rt_runtime.control.hardware import DriveInterface

    lead = np.array([0.015, 0.015, 0.015, 0.04])
    lead2 = np.array([0.0, 0.0, 0.0, 0.002])
    with LockstepHil(field, Q0, keep_frames=True, vcu=False) as hil:
        master = CanMaster(hil.master_bus, field, period_s=PERIOD_S, react_to_faults=False)
        master.boot(hil.clock.now, 1.0)
        master.enable(hil.clock.now, 1.0)
        drives = DriveInterface(master, hil.clock, 0.0, True, lead_s=lead, lead2_s2=lead2)
        s = master.last_target_um() * 1e-6
        v = np.array([0.01, -0.02, 0.0, 0.3])
        a1 = np.array([0.1, 0.0, 0.0, 1.0])
        a2 = np.array([0.2, 0.0, 0.0, 1.5])
        drives.write(s, v, a1)
        drives.write(s, v, a2)
        nodes = [dict(field.can.node_ids)[n] for n in axes.names(field)]
        _, velocity = rpdo1_setpoints(hil.core.frames, nodes)
    expected = v + lead * a2 + lead2 * (a2 - a1) / PERIOD_S
    np.testing.assert_allclose(velocity[-1] * 1e-6, expected, atol=1e-6)
    with pytest.raises(ValueError, match="lead"):
        DriveInterface(master, hil.clock, 0.0, True, lead2_s2=lead2)
