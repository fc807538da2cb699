"""The HIL's imperfections (profile ``[hil]``), each against its definition, and the switch.

Valve dead band (no flow inside the overlap), hysteresis (the loop's width), dead time and
slew; the stroke sensor's linearity error; the electric axis's backlash (the lost motion of a
reversal), breakaway friction and current loop; granular material (spill, fallback, slump to
the angle of repose conserving area); and with ``hil.enabled = false`` the plant is exactly
the ideal one.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hil_sim import ArmPlant, Terrain
from hil_sim.plant import play, sensor_error_m, valve_opening
from hil_sim.report import trench_shape
from hil_sim.terrain import slump
from rt_runtime import actuation, dynamics
from rt_runtime.errors import RigProfileError
from rt_runtime.rig import Material, Rig, load_rig, parse_rig

SCALE = load_rig("scale_model")
BENCH = load_rig("test_bench")
DT = 250e-6


def _on(rig: Rig, **tables: object) -> Rig:
    """``rig`` with its ``[hil]`` imperfections enabled and the given tables replaced."""
    assert rig.hil is not None
    return dataclasses.replace(rig, hil=dataclasses.replace(rig.hil, enabled=True, **tables))


def _mid(rig: Rig) -> np.ndarray:
    return 0.5 * (rig.q_min_rad + rig.q_max_rad)


# -- the switch --------------------------------------------------------------------------------


def test_shipped_profiles_carry_imperfections_switched_off() -> None:
    for rig in (SCALE, BENCH):
        assert rig.hil is not None and not rig.hil.enabled
        assert rig.hil.active() is None
    assert BENCH.hil is not None and BENCH.hil.valve is not None
    assert BENCH.hil.sensor is not None and BENCH.hil.sensor.linearity_fs == 0.001  # Gao 4.1
    assert SCALE.hil is not None and SCALE.hil.electric is not None


@pytest.mark.parametrize("rig", [SCALE, BENCH], ids=lambda r: r.name)
def test_switched_off_the_plant_is_the_ideal_one(rig: Rig) -> None:
    without = dataclasses.replace(rig, hil=None)
    q0 = _mid(rig)
    a, b = ArmPlant(rig, q0), ArmPlant(without, q0)
    rng = np.random.default_rng(3)
    for _ in range(400):
        u = rng.uniform(-0.3, 0.3, 3)
        a.step(DT, u)
        b.step(DT, u)
    assert a.imperfections is None
    assert a.q_rad.tolist() == b.q_rad.tolist()
    assert a.sensed_stroke_state() == b.stroke_state()


def test_profile_refuses_a_table_for_the_other_cylinder_kind() -> None:
    import tomllib

    from rt_runtime.rig.loader import PROFILE_DIR

    raw = tomllib.loads((PROFILE_DIR / "scale_model.toml").read_text())
    raw["hil"]["valve"] = {"overlap": 0.1, "hysteresis": 0.0, "slew_1_s": 10.0, "delay_ms": 1.0}
    with pytest.raises(RigProfileError, match=r"hil\.valve.*hydraulic"):
        parse_rig(raw)
    raw = tomllib.loads((PROFILE_DIR / "scale_model.toml").read_text())
    raw["hil"]["electric"]["breakaway_friction_n"] = 10.0
    with pytest.raises(RigProfileError, match=r"breakaway_friction_n.*coulomb"):
        parse_rig(raw)


# -- hydraulic valve ---------------------------------------------------------------------------


def test_dead_band_opening_is_zero_inside_the_overlap() -> None:
    for x in np.linspace(-0.1, 0.1, 41):
        assert valve_opening(float(x), 0.1) == 0.0
    assert valve_opening(1.0, 0.1) == 1.0
    assert valve_opening(-1.0, 0.1) == -1.0
    assert valve_opening(0.55, 0.1) == pytest.approx(0.5)


def test_dead_band_no_flow_inside_the_overlap_in_the_plant() -> None:
    """A spool held inside the overlap meters no flow: the cylinder does not move (beyond the
    null leakage's creep), while the same command beyond the overlap moves it."""
    assert BENCH.hil is not None and BENCH.hil.valve is not None
    overlap = 0.1
    valve = dataclasses.replace(BENCH.hil.valve, overlap=overlap, delay_s=0.0, hysteresis=0.0)
    rig = _on(BENCH, valve=valve, sensor=None)
    q0 = _mid(rig)
    moved = []
    for u in (0.8 * overlap, 1.5 * overlap):
        plant = ArmPlant(rig, q0)
        s0 = plant.stroke_m.copy()
        for _ in range(4000):  # 1 s
            plant.step(DT, [0.0, 0.0, u])
        moved.append(float(plant.stroke_m[2] - s0[2]))
    ideal = ArmPlant(dataclasses.replace(rig, hil=None), q0)
    s0 = ideal.stroke_m.copy()
    for _ in range(4000):
        ideal.step(DT, [0.0, 0.0, 0.8 * overlap])
    inside, outside = moved
    assert abs(inside) < 1e-3  # leakage creep only
    assert outside > 5e-3
    assert float(ideal.stroke_m[2] - s0[2]) > 5e-3  # without the overlap it moves


def test_hysteresis_loop_has_its_width() -> None:
    width = 0.04
    up = down = 0.0
    y = 0.0
    for u in np.linspace(-0.5, 0.5, 201):
        y = play(y, float(u), width)
        if abs(u) < 1e-12:
            up = y
    for u in np.linspace(0.5, -0.5, 201):
        y = play(y, float(u), width)
        if abs(u) < 1e-12:
            down = y
    assert down - up == pytest.approx(width)


def test_hysteresis_shows_in_the_spool() -> None:
    assert BENCH.hil is not None and BENCH.hil.valve is not None
    width = 0.06
    valve = dataclasses.replace(BENCH.hil.valve, overlap=0.0, hysteresis=width, delay_s=0.0)
    rig = _on(BENCH, valve=valve, sensor=None)
    plant = ArmPlant(rig, _mid(rig))
    for u in (0.2, 0.1):  # settle at 0.2, then come back to 0.1
        for _ in range(2000):
            plant.step(DT, [0.0, 0.0, u])
    spool = plant.spool
    assert spool is not None
    assert float(spool[2]) == pytest.approx(0.1 + 0.5 * width, abs=1e-6)


def test_valve_dead_time_and_slew() -> None:
    assert BENCH.hil is not None and BENCH.hil.valve is not None
    valve = dataclasses.replace(
        BENCH.hil.valve, overlap=0.0, hysteresis=0.0, delay_s=0.002, slew_1_s=25.0
    )
    rig = _on(BENCH, valve=valve, sensor=None)
    plant = ArmPlant(rig, _mid(rig))
    spools = []
    for _ in range(40):  # 10 ms of a full step
        plant.step(DT, [0.0, 0.0, 1.0])
        spool = plant.spool
        assert spool is not None
        spools.append(float(spool[2]))
    assert spools[7] == 0.0  # 8 sub-steps = 2 ms: nothing reached the spool yet
    assert spools[8] > 0.0
    rates = np.diff(spools) / DT
    assert rates.max() <= 25.0 + 1e-9


# -- sensor ------------------------------------------------------------------------------------


def test_sensor_linearity_error_is_bounded_by_its_class() -> None:
    fs = 0.368
    s = np.linspace(0.0, fs, 1001)
    err = np.array([sensor_error_m(float(x), fs, 0.001, 0.3) for x in s])
    assert np.abs(err).max() <= 0.001 * fs + 1e-15
    assert np.abs(err).max() > 0.9 * 0.001 * fs


def test_sensed_strokes_carry_the_sensor_error_and_repeat() -> None:
    rig = _on(BENCH)
    a, b = ArmPlant(rig, _mid(rig)), ArmPlant(rig, _mid(rig))
    true, _ = a.stroke_state()
    ra = [a.sensed_stroke_state()[0] for _ in range(200)]
    rb = [b.sensed_stroke_state()[0] for _ in range(200)]
    assert ra == rb  # seeded
    err = np.array(ra) - np.array(true)
    fs = actuation.stroke_limits(rig)[1]
    assert (np.abs(err) <= 0.001 * fs + 6 * 1e-6).all()
    assert np.std(err[:, 0]) == pytest.approx(1e-6, rel=0.3)


# -- electric axis -----------------------------------------------------------------------------


def _holding(rig: Rig, q: np.ndarray) -> np.ndarray:
    force = dynamics.gravity_torque(rig, q) / actuation.stroke_jacobian(rig, q)
    return np.asarray(force / rig.actuators.force_max_n)


def test_backlash_is_the_lost_motion_of_a_reversal() -> None:
    """Reversing the motor's force: the encoder (motor side) moves by the backlash relative to
    the rod, and the rod feels no motor force while the motor crosses the gap."""
    assert SCALE.hil is not None and SCALE.hil.electric is not None
    backlash = 50e-6
    electric = dataclasses.replace(SCALE.hil.electric, backlash_m=backlash)
    rig = _on(SCALE, electric=electric, sensor=None)
    q0 = _mid(rig)
    plant = ArmPlant(rig, q0, brakes=False)
    u_hold = _holding(rig, q0)
    sign = np.sign(u_hold[2])
    gaps = []
    forces = []
    for k in range(400):
        u = u_hold.copy()
        u[2] = u_hold[2] if k < 100 else -sign * 0.05  # reverse the bucket's force
        plant.step(DT, u)
        sensed = plant.sensed_stroke_state()[0][2]
        gaps.append(sensed - plant.stroke_state()[0][2])
        forces.append(float(plant.cylinder_force_n[2]))
    assert gaps[0] == pytest.approx(sign * backlash / 2)
    assert gaps[-1] == pytest.approx(-sign * backlash / 2)
    assert gaps[0] - gaps[-1] == pytest.approx(sign * backlash)  # the lost motion
    crossing = [i for i in range(100, 400) if abs(gaps[i]) < 0.99 * backlash / 2]
    assert crossing and all(forces[i] == 0.0 for i in crossing)


def test_current_loop_lags_the_force_command() -> None:
    assert SCALE.hil is not None and SCALE.hil.electric is not None
    electric = dataclasses.replace(SCALE.hil.electric, backlash_m=0.0, current_bandwidth_hz=100.0)
    rig = _on(SCALE, electric=electric, sensor=None)
    plant = ArmPlant(rig, _mid(rig), brakes=False)
    tau = 1.0 / (2.0 * math.pi * 100.0)
    n = round(tau / DT)
    for _ in range(n):
        plant.step(DT, [0.0, 0.0, 0.1])
    f = float(plant.cylinder_force_n[2]) / (0.1 * rig.actuators.force_max_n)
    assert f == pytest.approx(1.0 - math.exp(-n * DT / tau), abs=0.02)


def test_breakaway_friction_holds_what_coulomb_would_not() -> None:
    """A force between the Coulomb and the breakaway friction: the ideal axis creeps away,
    the imperfect one stays (a smoothed law creeps at ~(F / F_s) mm/s instead)."""
    assert SCALE.hil is not None and SCALE.hil.electric is not None
    electric = dataclasses.replace(SCALE.hil.electric, backlash_m=0.0)
    rig = _on(SCALE, electric=electric, sensor=None)
    q0 = _mid(rig)
    u = _holding(rig, q0)
    push = 0.5 * (rig.actuators.coulomb_friction_n + electric.breakaway_friction_n)
    u[2] += push / rig.actuators.force_max_n
    moved = []
    for r in (rig, dataclasses.replace(rig, hil=None)):
        plant = ArmPlant(r, q0, brakes=False)
        s0 = plant.stroke_m[2]
        for _ in range(2000):
            plant.step(DT, u)
        moved.append(abs(float(plant.stroke_m[2] - s0)))
    assert moved[0] < 0.5 * moved[1]


# -- granular material -------------------------------------------------------------------------


def test_slump_relaxes_a_steep_face_to_the_repose_angle_conserving_area() -> None:
    dx = 1e-3
    x = np.arange(0.0, 0.6, dx)
    y = np.where(x < 0.3, 0.0, -0.15)  # a vertical 0.15 m face
    area = y.sum() * dx
    repose = math.radians(35.0)
    moved = slump(y, dx, repose)
    assert y.sum() * dx == pytest.approx(area, abs=1e-12)
    slopes = np.abs(np.diff(y)) / dx
    assert slopes.max() <= math.tan(repose) + 1e-6 / dx
    assert moved > 0.0
    # The relaxed face runs at the angle of repose over its height.
    mid = (y < -0.03) & (y > -0.12)
    fit = abs(float(np.polyfit(x[mid], y[mid], 1)[0]))
    assert math.degrees(math.atan(fit)) == pytest.approx(35.0, abs=0.5)


@pytest.mark.parametrize("seed", range(5))
def test_slump_of_a_random_surface_conserves_area_and_bounds_every_slope(seed: int) -> None:
    rng = np.random.default_rng(seed)
    dx = 1e-3
    n = int(rng.integers(50, 3000))
    y = np.cumsum(rng.normal(0.0, 5e-3, n)) + np.where(rng.random(n) < 0.01, -0.1, 0.0)
    area = y.sum() * dx
    repose = math.radians(float(rng.uniform(25.0, 60.0)))
    slump(y, dx, repose)
    assert y.sum() * dx == pytest.approx(area, abs=1e-9), (seed, n)
    assert (np.abs(np.diff(y)) <= math.tan(repose) * dx + 1e-6 + 1e-12).all(), (seed, n)


def test_slump_leaves_a_face_flatter_than_repose_alone() -> None:
    dx = 1e-3
    x = np.arange(0.0, 0.4, dx)
    y = -0.5 * np.abs(x - 0.2)  # 26.6 deg faces
    before = y.copy()
    assert slump(y, dx, math.radians(35.0)) == 0.0
    assert (y == before).all()


def test_granular_cut_spills_falls_back_and_slumps() -> None:
    mat = Material(
        "test",
        spill_fraction=0.1,
        fallback_fraction=0.5,
        repose_rad=math.radians(40.0),
        resistance_factor=1.0,
    )
    ideal = Terrain(0.0, (0.0, 1.0), 0.2)
    granular = Terrain(0.0, (0.0, 1.0), 0.2, material=mat)
    # A rectangular dig 0.1 m deep with vertical ends.
    path = np.array([[0.3, 0.01], [0.3, -0.1], [0.7, -0.1], [0.7, 0.01]])
    a = ideal.cut(path)
    b = granular.cut(path)
    assert b.area_m2 == pytest.approx(a.area_m2)
    assert b.load_m3 == pytest.approx(0.9 * a.volume_m3)
    assert b.fallback_m3 == pytest.approx(0.05 * a.volume_m3)
    assert b.slumped_m3 > 0.0
    # The fallback is in the trench: the material lost is the swept area less it.
    lost = 0.0 - granular.surface_y_m
    assert lost.sum() * 1e-3 == pytest.approx(a.area_m2 - 0.05 * a.area_m2, rel=1e-3)
    _length, depth, b_far, b_near = trench_shape(granular.surface_x_m, granular.surface_y_m, 0.0)
    assert math.degrees(b_far) == pytest.approx(40.0, abs=1.0)
    assert math.degrees(b_near) == pytest.approx(40.0, abs=1.0)
    assert depth < 0.1
    assert granular.material.area == pytest.approx(ideal.material.area + 0.05 * a.area_m2, rel=1e-4)


def test_trench_shape_measures_a_design_profile() -> None:
    x = np.arange(0.0, 1.0, 1e-3)
    ground, depth, b1, b2 = 0.0, 0.15, math.radians(60.0), math.radians(50.0)
    x_near, x_far = 0.2, 0.8
    walls = np.maximum(-(x - x_near) * math.tan(b2), (x - x_far) * math.tan(b1))
    y = np.minimum(0.0, np.maximum(-depth, walls))
    length, d, far, near = trench_shape(x, y, ground)
    assert d == pytest.approx(depth)
    assert length == pytest.approx(0.6, abs=5e-3)
    assert far == pytest.approx(b1, abs=1e-3)
    assert near == pytest.approx(b2, abs=1e-3)


def test_a_materials_resistance_factor_scales_yaos_force() -> None:
    assert BENCH.hil is not None
    hard = BENCH.hil.with_material("hard").material
    soft = BENCH.hil.with_material("soft").material
    assert hard is not None and soft is not None
    forces = []
    for mat in (None, soft, hard):
        terrain = Terrain(BENCH.ground_y_m, (0.0, 3.0), BENCH.bucket.width_m, material=mat)
        load = terrain.soil_model(BENCH)
        forces.append(load.tip_load(1.5, BENCH.ground_y_m - 0.1, 0.2, -0.05)[:2])
    assert forces[1] == pytest.approx(forces[0])
    assert np.asarray(forces[2]) == pytest.approx(3.0 * np.asarray(forces[0]))


def test_an_unknown_material_is_refused_naming_the_known_ones() -> None:
    from rt_runtime.errors import ConfigurationError

    assert BENCH.hil is not None
    with pytest.raises(ConfigurationError, match="soft, hard"):
        BENCH.hil.with_material("gravel")


def test_the_scanner_samples_the_surface_with_its_noise() -> None:
    from hil_sim.scanner import ProfileScanner
    from rt_runtime.rig import Scanner

    terrain = Terrain(0.0, (0.0, 1.0), 0.2)
    terrain.cut(np.array([[0.3, 0.01], [0.3, -0.1], [0.7, -0.1], [0.7, 0.01]]))
    x, y = ProfileScanner(terrain, Scanner(spacing_m=0.005, noise_m=0.0)).scan()
    assert np.diff(x) == pytest.approx(0.005)
    assert y == pytest.approx(terrain.surface_y(x))
    noisy = ProfileScanner(terrain, Scanner(spacing_m=0.005, noise_m=1e-3), seed=2)
    _, y1 = noisy.scan()
    assert np.std(y1 - y) == pytest.approx(1e-3, rel=0.2)
    _, y2 = ProfileScanner(terrain, Scanner(spacing_m=0.005, noise_m=1e-3), seed=2).scan()
    assert (y1 == y2).all()  # seeded
