"""HIL plant: cross-checks with rt_runtime's physics, conservation, statics, stops, hydraulics."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from hil_sim import ArmPlant, Terrain
from hil_sim.plant import STOP_DEFLECTION_M
from rt_runtime import actuation, dynamics, kinematics, soil
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig, load_rig
from rt_runtime.trajectory import sextic

SCALE = load_rig("scale_model")
BENCH = load_rig("test_bench")
DT = 250e-6
ONNX = Path(__file__).resolve().parent.parent / "onnx"


def _frictionless(rig: Rig, reflected_mass_kg: float | None = None) -> Rig:
    act = dataclasses.replace(
        rig.actuators,
        coulomb_friction_n=0.0,
        viscous_friction_n_s_m=0.0,
        reflected_mass_kg=(
            rig.actuators.reflected_mass_kg if reflected_mass_kg is None else reflected_mass_kg
        ),
    )
    return dataclasses.replace(rig, actuators=act)


def _mid(rig: Rig) -> np.ndarray:
    return 0.5 * (rig.q_min_rad + rig.q_max_rad)


def _holding_effort(rig: Rig, q: np.ndarray) -> np.ndarray:
    """Electric effort whose motor force holds ``q`` against gravity."""
    force = dynamics.gravity_torque(rig, q) / actuation.stroke_jacobian(rig, q)
    return force / rig.actuators.force_max_n


def _random_poses(rig: Rig, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rig.q_min_rad + rng.uniform(0.05, 0.95, (n, 3)) * (rig.q_max_rad - rig.q_min_rad)


def test_stroke_maps_match_rt_runtime_actuation() -> None:
    rng = np.random.default_rng(1)
    for rig in (SCALE, BENCH):
        for q in _random_poses(rig, 20, seed=2):
            qd = rng.normal(0.0, 0.3, 3)
            plant = ArmPlant(rig, q, qd0_rad_s=qd)
            want_s = actuation.joint_to_stroke(rig, q)
            want_sd = actuation.stroke_velocity(rig, q, qd)
            np.testing.assert_allclose(plant.stroke_m, want_s, rtol=0, atol=1e-10)
            np.testing.assert_allclose(plant.stroke_rate_m_s, want_sd, rtol=1e-8, atol=1e-12)
            np.testing.assert_allclose(plant.tip_xy_m, kinematics.forward(rig, q)[:2])


@pytest.mark.parametrize("with_tip_force", [False, True])
def test_one_substep_matches_rt_runtime_dynamics(with_tip_force: bool) -> None:
    """qd after one frictionless sub-step = qd + h M_tot^-1 (tau - C qd - G - C_r + J^T f)."""
    rig = _frictionless(SCALE)
    m_r = rig.actuators.reflected_mass_kg
    rng = np.random.default_rng(3)
    for q in _random_poses(rig, 10, seed=4):
        qd = rng.normal(0.0, 0.15, 3)  # stroke rates below the motors' field-weakening knee
        effort = rng.uniform(-0.05, 0.05, 3)
        f_tip = rng.normal(0.0, 200.0, 2) if with_tip_force else None
        plant = ArmPlant(rig, q, qd0_rad_s=qd, brakes=False)
        plant.step(DT, effort, f_tip)

        slope = actuation.stroke_jacobian(rig, q)
        eps = 1e-6
        curvature = (
            actuation.stroke_jacobian(rig, q + eps) - actuation.stroke_jacobian(rig, q - eps)
        ) / (2 * eps)
        wrench = np.zeros(3) if f_tip is None else np.array([f_tip[0], f_tip[1], 0.0])
        # inverse_dynamics at qdd = 0 is C qd + G - J^T f.
        bias = dynamics.inverse_dynamics(rig, q, qd, np.zeros(3), wrench)
        tau = actuation.torque_from_force(rig, q, effort * rig.actuators.force_max_n)
        tau -= m_r * slope * curvature * qd**2
        mass = dynamics.mass_matrix(rig, q) + np.diag(m_r * slope**2)
        want = qd + DT * np.linalg.solve(mass, tau - bias)
        np.testing.assert_allclose(plant.qd_rad_s, want, rtol=1e-7, atol=1e-10)
        np.testing.assert_allclose(plant.q_rad, q + DT * want, rtol=0, atol=1e-12)


def _energy_drift(substep_s: float) -> tuple[float, float]:
    rig = _frictionless(SCALE)
    plant = ArmPlant(rig, np.radians([20.0, -80.0, -60.0]), substep_s=substep_s, brakes=False)
    e0 = plant.mechanical_energy_j()
    drift = 0.0
    ke_max = 0.0
    lo, hi = actuation.stroke_limits(rig)
    for _ in range(50):
        plant.step(0.01, np.zeros(3))
        s = plant.stroke_m
        assert np.all(s > lo) and np.all(s < hi), "the test motion must not reach an end stop"
        drift = max(drift, abs(plant.mechanical_energy_j() - e0))
        qd = plant.qd_rad_s
        ke_max = max(ke_max, e0 - float(dynamics.potential_energy(rig, plant.q_rad)))
        assert np.isfinite(qd).all()
    return drift, ke_max


def test_energy_is_conserved_without_forces_or_friction() -> None:
    drift, ke_max = _energy_drift(DT)
    assert ke_max > 20.0  # the arm really falls: tens of joules change form
    assert drift < 2e-3 * ke_max, (drift, ke_max)
    # The scheme is first order: half the step, half the drift.
    drift_half, _ = _energy_drift(DT / 2)
    assert 1.6 < drift / drift_half < 2.4


def test_constant_force_holds_against_gravity() -> None:
    for q in _random_poses(SCALE, 3, seed=5):
        effort = _holding_effort(SCALE, q)
        assert np.all(np.abs(effort) < 1.0)
        plant = ArmPlant(SCALE, q)
        for _ in range(200):
            plant.step(0.005, effort)
        np.testing.assert_allclose(plant.q_rad, q, rtol=0, atol=1e-9)
        torque = actuation.torque_from_force(SCALE, q, plant.cylinder_force_n)
        np.testing.assert_allclose(torque, dynamics.gravity_torque(SCALE, q), rtol=1e-12)
    # Half the force and the arm sags (5 % less would not overcome the screw's friction).
    q = _mid(SCALE)
    plant = ArmPlant(SCALE, q)
    for _ in range(100):
        plant.step(0.005, 0.5 * _holding_effort(SCALE, q))
    assert plant.q_rad[0] < q[0] - 1e-3


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("rig", [SCALE, BENCH], ids=["electric", "hydraulic"])
def test_step_effort_moves_each_axis_the_right_way(rig: Rig, axis: int) -> None:
    q = _mid(rig)
    hold = _holding_effort(rig, q) if rig.cylinders.kind == "electric" else np.zeros(3)
    # Extending a cylinder raises the boom and curls stick and bucket in (Gao Fig. 4).
    joint_sign = (1.0, -1.0, -1.0)[axis]
    for sign in (1.0, -1.0):
        plant = ArmPlant(rig, q)
        effort = hold.copy()
        effort[axis] += 0.2 * sign
        s0 = plant.stroke_m
        for _ in range(100):
            plant.step(0.002, effort)
        ds = plant.stroke_m[axis] - s0[axis]
        assert sign * ds > 1e-3, (axis, sign, ds)
        assert sign * plant.stroke_rate_m_s[axis] > 0.0
        assert sign * joint_sign * (plant.q_rad[axis] - q[axis]) > 0.0


@pytest.mark.parametrize("rig", [SCALE, BENCH], ids=["electric", "hydraulic"])
def test_end_stops_hold_the_cylinder_at_its_travel(rig: Rig) -> None:
    lo, hi = actuation.stroke_limits(rig)
    q = _mid(rig)
    for axis in range(3):
        for sign, end in ((1.0, hi[axis]), (-1.0, lo[axis])):
            plant = ArmPlant(rig, q)
            effort = np.zeros(3)
            effort[axis] = sign
            if rig.cylinders.kind == "electric":
                effort = _holding_effort(rig, q)
                effort[axis] = sign
            for _ in range(300):  # 3 s: every cylinder crosses its travel
                plant.step(0.01, effort)
            s = plant.stroke_m[axis]
            beyond = sign * (s - end)
            assert 0.0 < beyond < 1.2 * STOP_DEFLECTION_M, (axis, sign, beyond)
            assert abs(plant.stroke_rate_m_s[axis]) < 1e-4


def test_electric_brake_holds_an_axis_with_zero_effort() -> None:
    q = _mid(SCALE)
    braked = ArmPlant(SCALE, q)
    free = ArmPlant(SCALE, q, brakes=False)
    for _ in range(100):
        braked.step(0.005, np.zeros(3))
        free.step(0.005, np.zeros(3))
    assert braked.brakes_engaged == (True, True, True)
    np.testing.assert_array_equal(braked.q_rad, q)
    assert free.q_rad[0] < q[0] - 0.05  # without brakes the boom falls


def test_hydraulic_pressures_rise_and_settle() -> None:
    hyd = BENCH.actuators.hydraulic
    assert hyd is not None
    ps = hyd.supply_pressure_pa
    # Bucket cylinder at its extended end (bucket curled in): open the valve fully against it.
    q = _mid(BENCH)
    q[2] = BENCH.q_min_rad[2]
    plant = ArmPlant(BENCH, q)
    effort = np.array([0.0, 0.0, 1.0])
    trace = []
    for _ in range(200):
        plant.step(0.002, effort)
        p = plant.pressures_pa
        assert p is not None
        trace.append(p[2].copy())
    p_a, p_b = np.array(trace).T
    assert p_a[-1] > 0.97 * ps and p_b[-1] < 0.03 * ps
    assert p_a[5] < p_a[-1]  # it rose
    tail = slice(-50, None)  # the last 0.1 s
    assert np.ptp(p_a[tail]) < 1e-3 * ps and np.ptp(p_b[tail]) < 1e-3 * ps
    assert plant.cylinder_force_n[2] == pytest.approx(
        p_a[-1] * hyd.piston_area_m2 - p_b[-1] * hyd.annulus_area_m2
    )
    spool = plant.spool
    assert spool is not None and spool[2] == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("name", ["test_bench", "field_excavator", "yang_pan_excavator"])
def test_hydraulic_speed_matches_the_profile_valve_gain(name: str) -> None:
    """At 30 % spool the bucket cylinder runs at ~30 % of velocity_max (the no-load speed)."""
    rig = load_rig(name)
    plant = ArmPlant(rig, _mid(rig))
    for _ in range(250):
        plant.step(0.002, [0.0, 0.0, 0.3])
    v = plant.stroke_rate_m_s[2]
    assert v == pytest.approx(0.3 * rig.actuators.velocity_max_m_s, rel=0.08)


def test_power_bookkeeping_balances_the_mechanical_energy() -> None:
    rig = _frictionless(SCALE)
    q = _mid(rig)
    plant = ArmPlant(rig, q, brakes=False)
    e0 = plant.mechanical_energy_j()
    effort = _holding_effort(rig, q) + np.array([0.05, -0.03, 0.02])
    for _ in range(250):
        plant.step(0.002, effort)
    gained = plant.mechanical_energy_j() - e0
    assert gained > 1.0
    assert plant.energy_signed_j == pytest.approx(gained, rel=5e-3)
    assert plant.energy_j >= plant.energy_signed_j
    assert plant.power_w >= max(plant.power_signed_w, 0.0)


def test_soil_resists_the_tip_below_the_surface() -> None:
    q = np.radians([0.0, -90.0, -60.0])
    tip = kinematics.forward(SCALE, q)
    terrain = Terrain(float(tip[1]) + 0.05, (-0.5, 1.5), SCALE.bucket.width_m)
    plant = ArmPlant(SCALE, q, terrain, qd0_rad_s=np.radians([0.0, -10.0, 0.0]))
    effort = _holding_effort(SCALE, q)
    for _ in range(10):
        plant.step(DT, effort)
        f = plant.soil_force_xy_n
        v = plant.tip_velocity_xy_m_s
        assert float(f @ v) < 0.0
    assert plant.soil_energy_j > 0.0
    above = ArmPlant(SCALE, q, Terrain(float(tip[1]) - 0.01, (-0.5, 1.5), 0.22))
    above.step(DT, effort)
    np.testing.assert_array_equal(above.soil_force_xy_n, [0.0, 0.0])


def test_runs_are_deterministic() -> None:
    def run() -> tuple[np.ndarray, ...]:
        plant = ArmPlant(BENCH, _mid(BENCH))
        for k in range(200):
            plant.step(DT, [0.3 * math.sin(k / 20), -0.2, 0.1])
        p = plant.pressures_pa
        assert p is not None
        return plant.q_rad, plant.qd_rad_s, p

    for a, b in zip(run(), run(), strict=True):
        np.testing.assert_array_equal(a, b)


def test_scale_model_cylinders_cover_the_verified_digs() -> None:
    """force_max and velocity_max exceed what the verified held-out digs ask, with margin."""
    rig = SCALE
    force = []
    rate = []
    for kind in ("downward", "backward"):
        data = np.load(ONNX / f"pinn_{kind}_heldout.npz")
        x, y = data["X"], data["Y"]
        coeffs = sextic.sextic_coefficients(x[:, :3], x[:, 3:6], y[:, :3], y[:, 3])
        _, q, qd, qdd, _ = sextic.evaluate(coeffs, y[:, 3], 101)
        pose, twist = kinematics.tip_state(rig, q, qd)
        wrench = soil.yao_resistance(rig, pose, twist, x[:, 6][:, None])
        tau = dynamics.inverse_dynamics(rig, q, qd, qdd, wrench)
        slope = actuation.stroke_jacobian(rig, q, check_limits=False)
        force.append(np.abs(tau / slope).max())
        rate.append(np.abs(slope * qd).max())
    assert rig.actuators.force_max_n > 1.5 * max(force)
    assert rig.actuators.velocity_max_m_s > 1.5 * max(rate)


def test_verified_dig_tracks_and_cuts_its_planned_volume() -> None:
    """A held-out dig through a minimal CSP cascade with the profile's gains: sub-mm tracking,
    and the terrain loses the volume the planner promised."""
    rig = SCALE
    data = np.load(ONNX / "pinn_downward_heldout.npz")
    x, y = data["X"][0], data["Y"][0]
    period, n_sub = 2e-3, 8
    h = period / n_sub
    coeffs = sextic.sextic_coefficients(x[:3], x[3:6], y[:3], y[3])
    t = np.arange(0.0, float(y[3]) + 0.2, period)
    _, q, qd, _, _ = sextic.evaluate(coeffs, y[3], s_grid=np.clip(t / y[3], 0.0, 1.0))
    s_ref = actuation.joint_to_stroke(rig, q, check_limits=False)
    v_ref = actuation.stroke_jacobian(rig, q, check_limits=False) * qd
    terrain = Terrain(float(x[6]), (-0.5, 1.5), rig.bucket.width_m)
    plant = ArmPlant(rig, q[0], terrain)
    d = rig.drives
    res = d.encoder_resolution_m
    integral = np.zeros(3)
    last = np.round(plant.stroke_m / res) * res
    err = 0.0
    path = [plant.tip_xy_m]
    for k in range(1, len(t)):
        for j in range(1, n_sub + 1):
            a = j / n_sub
            demand = s_ref[k - 1] + a * (s_ref[k] - s_ref[k - 1])
            v_ff = v_ref[k - 1] + a * (v_ref[k] - v_ref[k - 1])
            meas = np.round(plant.stroke_m / res) * res
            ev = v_ff + d.position_gain_1_s * (demand - meas) - (meas - last) / h
            last = meas
            raw = d.velocity_gain_s_m * (ev + integral)
            integral += np.where(np.abs(raw) < 1.0, d.velocity_integral_gain_1_s * ev * h, 0.0)
            plant.step(h, np.clip(raw, -1.0, 1.0))
            err = max(err, float(np.abs(demand - plant.stroke_m).max()))
        path.append(plant.tip_xy_m)
    assert err < 0.2e-3
    cut = terrain.cut(np.array(path))
    assert cut.volume_m3 == pytest.approx(float(data["volume_m3"][0]), rel=0.03)
    assert 0.02 * 3600 < plant.energy_j < 0.2 * 3600  # Yao's 0.025..0.110 Wh class


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ConfigurationError, match="boom cylinder outside its travel"):
        ArmPlant(SCALE, np.radians([80.0, -80.0, -60.0]))
    with pytest.raises(ValueError, match="q0_rad must have shape"):
        ArmPlant(SCALE, [0.0, 0.0])
    with pytest.raises(ConfigurationError, match="qd0_rad_s must be finite"):
        ArmPlant(SCALE, _mid(SCALE), qd0_rad_s=[0.0, math.nan, 0.0])
    plant = ArmPlant(SCALE, _mid(SCALE))
    with pytest.raises(ValueError, match="efforts must have 3 values"):
        plant.step(DT, [0.1, 0.2])
    with pytest.raises(ValueError, match="efforts must not be NaN"):
        plant.step(DT, [0.1, math.nan, 0.0])
    with pytest.raises(ValueError, match="dt_s must be finite and > 0"):
        plant.step(0.0, [0.0, 0.0, 0.0])
    assert plant.pressures_pa is None and plant.spool is None
