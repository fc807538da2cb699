"""Rig profiles: the shipped files load, carry their sources, and bad files name the bad key."""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rt_runtime.errors import ConfigurationError, RigProfileError
from rt_runtime.rig import load_rig, parse_rig, profile_names
from rt_runtime.rig.loader import PROFILE_DIR


def _raw(name: str) -> dict[str, Any]:
    return tomllib.loads((PROFILE_DIR / f"{name}.toml").read_text())


def test_four_profiles_ship() -> None:
    assert profile_names() == ["field_excavator", "scale_model", "test_bench", "yang_pan_excavator"]


@pytest.mark.parametrize("name", profile_names())
def test_profiles_load_and_mark_assumptions(name: str) -> None:
    rig = load_rig(name)
    assert rig.name == name
    assert rig.sources
    assert rig.assumed, "every profile assumes something no paper gives"
    for key, reason in rig.assumed:
        assert reason.strip(), key
    assert all(rig.q_min_rad < rig.q_max_rad)
    assert rig.lengths_m.shape == (3,)
    with pytest.raises(ValueError):
        rig.lengths_m[0] = 1.0  # arrays are read-only like the dataclass


def test_scale_model_values_match_yao_tables() -> None:
    rig = load_rig("scale_model")
    assert rig.lengths_m.tolist() == [0.740, 0.350, 0.220]
    deg = [d for j in rig.joints for d in (math.degrees(j.min_rad), math.degrees(j.max_rad))]
    assert deg == pytest.approx([-20, 65, -160, 10, -160, 5])
    assert [math.degrees(v) for v in rig.qd_max_rad_s] == pytest.approx([15, 28, 30])
    assert [math.degrees(v) for v in rig.qdd_max_rad_s2] == pytest.approx([10, 10, 10])
    p = rig.planning
    assert p is not None
    assert (p.t_min_s, p.t_max_s) == (5.0, 10.0)
    assert p.volume_min_m3 == pytest.approx(3.74e-3)
    assert p.volume_max_m3 == pytest.approx(5.72e-3)
    assert p.energy_min_j == pytest.approx(0.025 * 3600)
    assert p.energy_max_j == pytest.approx(0.110 * 3600)
    assert p.power_max_w == 400.0
    assert p.weights == (0.5, 0.2, 0.3)
    assert rig.soil.yao.k0_n_m2 == pytest.approx(5e4)  # 5 N/cm^2
    assert rig.soil.yao.mu == 0.40
    assert rig.bucket.width_m == 0.22
    assert rig.ground_y_m == -0.25
    assert rig.can.node_id("boom") == 1 and rig.can.node_id("bucket") == 3
    assert not rig.has_swing and rig.dof == 3


def test_field_excavator_has_swing_and_errata_applied() -> None:
    rig = load_rig("field_excavator")
    assert rig.has_swing and rig.dof == 4
    assert rig.joint_names == ("swing", "boom", "stick", "bucket")
    assert rig.swing is not None
    assert rig.swing.base_offset_m == 0.860 and rig.swing.base_height_m == 1.125
    assert math.degrees(rig.joints[0].velocity_max_rad_s) == pytest.approx(45.0)  # not 845
    assert rig.is_assumed("joints.stick.min_deg")
    assert rig.can.node_id("swing") == 4


def test_yang_pan_soils_from_table_2() -> None:
    soil = load_rig("yang_pan_excavator").soil
    soft, hard = soil.fluid_named("soft"), soil.fluid_named("hard")
    assert (soft.density_kg_m3, soft.kp, soft.kv, soft.ks) == (1000, 1, 300, 0.5)
    assert (hard.density_kg_m3, hard.kp, hard.kv, hard.ks) == (2500, 3, 1000, 0.8)
    with pytest.raises(KeyError, match="known: soft, hard"):
        soil.fluid_named("clay")


def _set(doc: dict[str, Any], path: str, value: Any) -> None:
    *parents, last = path.split(".")
    node = doc
    for p in parents:
        node = node[p]
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value


_DELETE = object()


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (
            "links.boom.length_m",
            -0.74,
            r"links\.boom\.length_m: must be > 0 and <= 50 \(got -0\.74\)",
        ),
        ("links.stick.mass_kg", float("nan"), r"links\.stick\.mass_kg: must be a finite number"),
        (
            "joints.bucket.min_deg",
            30.0,
            r"joints\.bucket\.min_deg: must be < joints\.bucket\.max_deg",
        ),
        ("joints.boom.velocity_max_deg_s", _DELETE, r"joints\.boom\.velocity_max_deg_s: missing"),
        ("links.boom.length_m", "long", r"links\.boom\.length_m: must be a number"),
        ("planning.t_s", [10.0, 5.0], r"planning\.t_s: min must be < max"),
        ("planning.weights", [0.5, 0.5, 0.5], r"planning\.weights: must sum to 1"),
        (
            "links.boom.lenght_m",
            1.0,
            r"links\.boom\.lenght_m: unknown key; allowed here: .*length_m",
        ),
        ("can.node_ids.stick", 1, r"can\.node_ids\.stick: node id 1 is already used by boom"),
        (
            "bucket.profile_m",
            [[0.1, 0.0], [0, 1], [1, 1]],
            r"bucket\.profile_m: must start at the tip",
        ),
        ("ground", _DELETE, r"ground: missing"),
        ("links.bucket.com_m", [0.1], r"links\.bucket\.com_m: must have exactly 2 numbers"),
    ],
)
def test_bad_profile_names_the_key(path: str, value: Any, message: str) -> None:
    doc = copy.deepcopy(_raw("scale_model"))
    _set(doc, path, value)
    with pytest.raises(RigProfileError, match=message) as info:
        parse_rig(doc, source="bad.toml")
    assert str(info.value).startswith("bad.toml: ")
    assert isinstance(info.value, ConfigurationError)


def test_assumed_must_name_existing_keys() -> None:
    doc = copy.deepcopy(_raw("scale_model"))
    doc["assumed"]["links.boom.colour"] = "made up"
    with pytest.raises(RigProfileError, match=r"assumed\.links\.boom\.colour: names a key"):
        parse_rig(doc)


def test_load_by_path_and_errors_for_missing(tmp_path: Path) -> None:
    src = (PROFILE_DIR / "test_bench.toml").read_text()
    f = tmp_path / "my_rig.toml"
    f.write_text(src)
    assert load_rig(f).name == "test_bench"
    with pytest.raises(
        RigProfileError, match="no rig profile 'moon_digger'; shipped: field_excavator"
    ):
        load_rig("moon_digger")
    with pytest.raises(RigProfileError, match="not found"):
        load_rig(tmp_path / "absent.toml")
    bad = tmp_path / "broken.toml"
    bad.write_text("name = [unclosed")
    with pytest.raises(RigProfileError, match="not valid TOML"):
        load_rig(bad)


# --- drives and actuators (issue 6) --------------------------------------------------------


@pytest.mark.parametrize("name", profile_names())
def test_drives_and_actuators_load_in_si_and_are_assumed(name: str) -> None:
    rig = load_rig(name)
    d, a = rig.drives, rig.actuators
    assert 0.0 < d.encoder_resolution_m <= 1e-6
    assert d.servo_period_s == pytest.approx(250e-6)
    assert d.heartbeat_timeout_s > d.heartbeat_period_s
    assert d.following_error_window_m >= 1e-3
    assert (a.hydraulic is not None) == (rig.cylinders.kind == "hydraulic")
    assert a.coulomb_friction_n < a.force_max_n
    if a.hydraulic is not None:
        h = a.hydraulic
        assert 0.0 < h.annulus_area_m2 < h.piston_area_m2
        assert a.force_max_n <= h.supply_pressure_pa * h.piston_area_m2
    raw = _raw(name)
    for table in ("drives", "actuators", "actuators.hydraulic"):
        node: Any = raw
        for part in table.split("."):
            node = node.get(part, {})
        for key, value in node.items():
            if not isinstance(value, dict):
                assert rig.is_assumed(f"{table}.{key}"), f"{table}.{key} has no [assumed] reason"


def test_scale_model_drive_values_in_si() -> None:
    rig = load_rig("scale_model")
    assert rig.drives.encoder_resolution_m == pytest.approx(0.05e-6)
    assert rig.drives.following_error_window_m == pytest.approx(5e-3)
    assert rig.drives.following_error_timeout_s == pytest.approx(0.1)
    assert rig.drives.quick_stop_deceleration_m_s2 == pytest.approx(0.5)
    assert rig.actuators.velocity_max_m_s == pytest.approx(0.1)
    assert rig.actuators.hydraulic is None
    bench = load_rig("test_bench").actuators.hydraulic
    assert bench is not None
    assert bench.supply_pressure_pa == pytest.approx(21e6)
    assert bench.piston_area_m2 == pytest.approx(50.27e-4)
    assert bench.valve_flow_m3_s == pytest.approx(40.0 / 60000.0)
    assert bench.valve_time_constant_s == pytest.approx(8e-3)


def test_drives_and_actuators_stay_out_of_the_planning_fingerprint() -> None:
    doc = copy.deepcopy(_raw("scale_model"))
    base = parse_rig(doc).planning_fingerprint
    doc["drives"]["position_gain_1_s"] = 12.0
    doc["actuators"]["force_max_n"] = 9000.0
    assert parse_rig(doc).planning_fingerprint == base


def test_servo_period_defaults_to_250_us() -> None:
    doc = copy.deepcopy(_raw("scale_model"))
    del doc["drives"]["servo_period_us"]
    del doc["assumed"]["drives.servo_period_us"]
    assert parse_rig(doc).drives.servo_period_s == pytest.approx(250e-6)


@pytest.mark.parametrize(
    ("profile", "path", "value", "message"),
    [
        ("scale_model", "drives", _DELETE, r"drives: missing"),
        (
            "scale_model",
            "drives.position_gain_1_s",
            -1.0,
            r"drives\.position_gain_1_s: must be > 0 and <= 10000 \(got -1\)",
        ),
        ("scale_model", "drives.velocity_gain", "fast", r"drives\.velocity_gain: must be a number"),
        (
            "scale_model",
            "drives.encoder_resolution_um",
            0.0,
            r"drives\.encoder_resolution_um: must be > 0",
        ),
        (
            "scale_model",
            "drives.servo_period_us",
            250.5,
            r"drives\.servo_period_us: must be an integer",
        ),
        (
            "scale_model",
            "drives.heartbeat_timeout_ms",
            50,
            r"drives\.heartbeat_timeout_ms: must be > heartbeat_period_ms \(50\)",
        ),
        (
            "scale_model",
            "drives.following_error_timeout_ms",
            70000,
            r"drives\.following_error_timeout_ms: must be >= 0 and <= 65535",
        ),
        (
            "scale_model",
            "drives.sync_timeout_ms",
            _DELETE,
            r"drives\.sync_timeout_ms: missing",
        ),
        (
            "scale_model",
            "drives.velocity_gain_s_m",
            8.0,
            r"drives\.velocity_gain_s_m: unknown key; allowed here: .*velocity_gain",
        ),
        (
            "scale_model",
            "drives.quick_stop_deceleration_mm_s2",
            float("inf"),
            r"drives\.quick_stop_deceleration_mm_s2: must be a finite number",
        ),
        (
            "field_excavator",
            "drives.load_compensation_filter_ms",
            -1.0,
            r"drives\.load_compensation_filter_ms: must be >= 0",
        ),
        (
            "scale_model",
            "drives.load_compensation_filter_ms",
            50.0,
            r"drives\.load_compensation_filter_ms: only for valve drives",
        ),
        (
            "scale_model",
            "drives.pressure_feedback_gain",
            [0.5, 0.0, 0.0],
            r"drives\.pressure_feedback_gain: only for valve drives",
        ),
        (
            "scale_model",
            "drives.valve_overlap_compensation",
            0.1,
            r"drives\.valve_overlap_compensation: only for valve drives",
        ),
        (
            "test_bench",
            "drives.valve_overlap_compensation",
            0.6,
            r"drives\.valve_overlap_compensation: must be >= 0 and <= 0\.5",
        ),
        (
            "test_bench",
            "drives.valve_overlap_compensation",
            0.21,
            r"drives\.valve_overlap_compensation: must be <= hil\.valve\.overlap \(0\.2\)",
        ),
        (
            "yang_pan_excavator",
            "drives.pressure_feedback_gain",
            0.5,
            r"drives\.pressure_feedback_gain: must be a list of numbers",
        ),
        (
            "yang_pan_excavator",
            "drives.pressure_feedback_gain",
            [0.5, 0.0],
            r"drives\.pressure_feedback_gain: must have exactly 3 numbers",
        ),
        (
            "yang_pan_excavator",
            "drives.pressure_feedback_gain",
            [0.5, -1.0, 0.0],
            r"drives\.pressure_feedback_gain\[1\]: must be >= 0",
        ),
        (
            "yang_pan_excavator",
            "drives.pressure_feedback_filter_ms",
            0.0,
            r"drives\.pressure_feedback_filter_ms: must be > 0 when pressure_feedback_gain is",
        ),
        (
            "scale_model",
            "actuators.force_max_n",
            0.0,
            r"actuators\.force_max_n: must be > 0",
        ),
        (
            "scale_model",
            "actuators.coulomb_friction_n",
            30000.0,
            r"actuators\.coulomb_friction_n: must be < force_max_n",
        ),
        (
            "scale_model",
            "actuators.reflected_mass_kg",
            -5.0,
            r"actuators\.reflected_mass_kg: must be >= 0",
        ),
        (
            "scale_model",
            "actuators.hydraulic",
            {"supply_pressure_mpa": 20.0},
            r"actuators\.hydraulic: not allowed for cylinders\.kind = 'electric'",
        ),
        (
            "test_bench",
            "actuators.hydraulic",
            _DELETE,
            r"actuators\.hydraulic: missing \(required for cylinders\.kind = \"hydraulic\"\)",
        ),
        (
            "test_bench",
            "actuators.hydraulic.rod_area_cm2",
            60.0,
            r"actuators\.hydraulic\.rod_area_cm2: must be < actuators\.hydraulic\.piston_area_cm2",
        ),
        (
            "test_bench",
            "actuators.hydraulic.bulk_modulus_mpa",
            -1.0,
            r"actuators\.hydraulic\.bulk_modulus_mpa: must be > 0",
        ),
        (
            "test_bench",
            "actuators.force_max_n",
            200000.0,
            r"actuators\.force_max_n: must be <= supply pressure x piston area = 105567 N",
        ),
    ],
)
def test_bad_drive_and_actuator_values_name_the_key(
    profile: str, path: str, value: Any, message: str
) -> None:
    doc = copy.deepcopy(_raw(profile))
    _set(doc, path, value)
    with pytest.raises(RigProfileError, match=message) as info:
        parse_rig(doc, source="bad.toml")
    assert str(info.value).startswith("bad.toml: ")


# --- the trench task domain (issue 23) ----------------------------------------------------------


@pytest.mark.parametrize("name", profile_names())
def test_trench_length_max_is_the_scale_model_s_20_m_scaled_by_reach(name: str) -> None:
    rig = load_rig(name)
    assert rig.trench.length_max_m == pytest.approx(20.0 * sum(rig.lengths_m) / 1.31, abs=0.01)
    assert rig.is_assumed("trench.length_max_m")
    # without the table the loader applies the same rule
    doc = copy.deepcopy(_raw(name))
    del doc["trench"]
    for key in [k for k in doc["assumed"] if k.startswith("trench.")]:
        del doc["assumed"][key]
    rule = parse_rig(doc).trench.length_max_m
    assert rule == pytest.approx(20.0 * sum(rig.lengths_m) / 1.31, rel=1e-12)


@pytest.mark.parametrize("name", profile_names())
def test_spoil_zone_is_the_scale_model_s_scaled_by_reach_and_assumed(name: str) -> None:
    rig = load_rig(name)
    s = sum(rig.lengths_m) / 1.31
    zone = rig.trench.spoil
    for key in ("x_m", "height_m", "attitude_deg", "edge_gap_m"):
        assert rig.is_assumed(f"trench.spoil.{key}"), key
    assert zone.x_m == pytest.approx((0.25 * s, 0.45 * s), rel=1e-3)
    assert zone.height_m == pytest.approx((0.25 * s, 0.40 * s), rel=1e-3)
    assert zone.edge_gap_m == pytest.approx(0.05 * s, rel=1e-3)
    assert np.degrees(zone.attitude_rad) == pytest.approx((-100.0, -60.0))
    # without the table the loader applies the same rule
    doc = copy.deepcopy(_raw(name))
    del doc["trench"]["spoil"]
    for key in [k for k in doc["assumed"] if k.startswith("trench.spoil.")]:
        del doc["assumed"][key]
    rule = parse_rig(doc).trench.spoil
    assert rule.x_m == pytest.approx(zone.x_m, rel=1e-3)
    assert rule.height_m == pytest.approx(zone.height_m, rel=1e-3)
    assert rule.attitude_rad == pytest.approx(zone.attitude_rad)


def test_spoil_zone_values_are_checked() -> None:
    doc = copy.deepcopy(_raw("scale_model"))
    for key, bad, message in (
        ("x_m", [0.45, 0.25], r"trench\.spoil\.x_m: min must be < max"),
        ("x_m", [0.25, 5.0], r"trench\.spoil\.x_m\[1\]: must be >= -1\.31 and <= 1\.31"),
        ("height_m", [-0.1, 0.4], r"trench\.spoil\.height_m\[0\]: must be >= 0"),
        ("attitude_deg", [-100.0, 200.0], r"trench\.spoil\.attitude_deg\[1\]: must be >= -180"),
        ("edge_gap_m", -0.01, r"trench\.spoil\.edge_gap_m: must be >= 0"),
    ):
        bad_doc = copy.deepcopy(doc)
        bad_doc["trench"]["spoil"][key] = bad
        with pytest.raises(RigProfileError, match=message):
            parse_rig(bad_doc)
    bad_doc = copy.deepcopy(doc)
    bad_doc["trench"]["spoil"]["depth_m"] = 1.0
    with pytest.raises(RigProfileError, match=r"trench\.spoil\.depth_m: unknown key"):
        parse_rig(bad_doc)


def test_trench_domain_is_checked_and_stays_out_of_the_planning_fingerprint() -> None:
    doc = copy.deepcopy(_raw("scale_model"))
    base = parse_rig(doc).planning_fingerprint
    doc["trench"]["length_max_m"] = 5.0
    rig = parse_rig(doc)
    assert rig.trench.length_max_m == 5.0 and rig.planning_fingerprint == base
    for bad, message in (
        (0.0, r"trench\.length_max_m: must be > 0 and <= 1310"),
        (1e308, r"trench\.length_max_m: must be > 0 and <= 1310"),
        ("20", r"trench\.length_max_m: must be a number"),
    ):
        doc["trench"]["length_max_m"] = bad
        with pytest.raises(RigProfileError, match=message):
            parse_rig(doc)
    doc["trench"] = {"length_max_m": 20.0, "width_m": 1.0}
    with pytest.raises(RigProfileError, match=r"trench\.width_m: unknown key"):
        parse_rig(doc)


# --- the swing's dynamics constants ([swing] upper_inertia_kgm2, motor_line_volume_l) ---------


def _electric_with_swing() -> dict[str, Any]:
    """The scale model (electric cylinders) with the field excavator's ``[swing]`` table, less
    the hydraulic-only key."""
    doc = copy.deepcopy(_raw("scale_model"))
    doc["swing"] = copy.deepcopy(_raw("field_excavator")["swing"])
    del doc["swing"]["motor_line_volume_l"]
    doc["can"]["node_ids"]["swing"] = 4
    return doc


def test_field_excavator_sets_the_swing_s_dynamics_constants_as_assumed() -> None:
    rig = load_rig("field_excavator")
    assert rig.swing is not None
    assert rig.swing.upper_inertia_kgm2 == 4600.0
    assert rig.swing.motor_line_volume_m3 == pytest.approx(2e-3, rel=1e-15)
    assert rig.is_assumed("swing.upper_inertia_kgm2")
    assert rig.is_assumed("swing.motor_line_volume_l")


def test_swing_dynamics_constants_default_to_the_field_excavator_s() -> None:
    doc = copy.deepcopy(_raw("field_excavator"))
    for key in ("upper_inertia_kgm2", "motor_line_volume_l"):
        del doc["swing"][key]
        del doc["assumed"][f"swing.{key}"]
    rig = parse_rig(doc)
    assert rig.swing == load_rig("field_excavator").swing
    assert rig.swing is not None
    assert (rig.swing.upper_inertia_kgm2, rig.swing.motor_line_volume_m3) == (4600.0, 2e-3)


def test_swing_dynamics_constants_load_in_si_and_stay_out_of_the_planning_fingerprint() -> None:
    doc = copy.deepcopy(_raw("field_excavator"))
    base = parse_rig(doc).planning_fingerprint
    doc["swing"]["upper_inertia_kgm2"] = 9000.0
    doc["swing"]["motor_line_volume_l"] = 3.5
    rig = parse_rig(doc)
    assert rig.swing is not None
    assert rig.swing.upper_inertia_kgm2 == 9000.0
    assert rig.swing.motor_line_volume_m3 == pytest.approx(3.5e-3, rel=1e-15)
    assert rig.planning_fingerprint == base
    doc["swing"]["base_offset_m"] = 0.9  # the swing's geometry still counts
    assert parse_rig(doc).planning_fingerprint != base


@pytest.mark.parametrize("key", ["upper_inertia_kgm2", "motor_line_volume_l"])
@pytest.mark.parametrize(
    ("value", "message"),
    [
        (0.0, r"must be > 0 \(got 0\)"),
        (-4600, r"must be > 0 \(got -4600\)"),
        (float("nan"), r"must be a finite number > 0 \(got nan\)"),
        (float("inf"), r"must be a finite number > 0 \(got inf\)"),
        ("4600", r"must be a number > 0 \(got '4600'\)"),
        (True, r"must be a number > 0 \(got True\)"),
    ],
)
def test_bad_swing_dynamics_constants_name_the_key(key: str, value: Any, message: str) -> None:
    doc = copy.deepcopy(_raw("field_excavator"))
    doc["swing"][key] = value
    with pytest.raises(RigProfileError, match=rf"swing\.{key}: {message}") as info:
        parse_rig(doc, source="bad.toml")
    assert str(info.value).startswith("bad.toml: ")


def test_the_swing_motor_line_volume_is_refused_on_an_electric_rig() -> None:
    doc = _electric_with_swing()
    doc["swing"]["upper_inertia_kgm2"] = 3000.0  # the inertia belongs to any swing
    rig = parse_rig(doc)
    assert rig.actuators.hydraulic is None and rig.swing is not None
    assert rig.swing.upper_inertia_kgm2 == 3000.0
    assert rig.swing.motor_line_volume_m3 == 2e-3  # the default, unused without hydraulics
    doc["swing"]["motor_line_volume_l"] = 2.0
    with pytest.raises(
        RigProfileError,
        match=r"swing\.motor_line_volume_l: only for a hydraulic swing motor "
        r"\(cylinders\.kind = 'hydraulic'\), not 'electric'; leave it out",
    ):
        parse_rig(doc)


def test_unknown_swing_keys_list_the_dynamics_constants() -> None:
    doc = copy.deepcopy(_raw("field_excavator"))
    doc["swing"]["upper_inertia_kg_m2"] = 4600.0
    with pytest.raises(
        RigProfileError,
        match=r"swing\.upper_inertia_kg_m2: unknown key; allowed here: .*motor_line_volume_l.*"
        r"upper_inertia_kgm2",
    ):
        parse_rig(doc)
