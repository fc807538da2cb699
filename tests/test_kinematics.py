"""Kinematics: paper data, identities between forward and inverse, finite differences, Zhao eq 1."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from numpy.typing import NDArray

from rt_runtime import kinematics
from rt_runtime.errors import ConfigurationError, JointLimitError, UnreachableError
from rt_runtime.kinematics import (
    forward,
    forward_3d,
    inverse,
    inverse_3d,
    jacobian,
    joint_positions,
    tip_velocity,
)
from rt_runtime.rig import Rig, load_rig, profile_names

FloatArray = NDArray[np.float64]

# Gao Table 2: joint angles (deg) found by their inverse kinematics for the tip points (m).
GAO_TABLE_2 = [
    ((34.83, -40.32, -56.16), (2.2, 0.4)),
    ((34.05, -50.52, -57.47), (2.1, 0.2)),
    ((37.27, -65.58, -58.15), (1.9, 0.1)),
    ((41.75, -77.73, -60.14), (1.7, 0.1)),
    ((49.39, -89.13, -60.26), (1.5, 0.2)),
    ((58.46, -92.13, -61.07), (1.4, 0.4)),
]

RIGS = profile_names()


@pytest.fixture(scope="module", params=RIGS)
def rig(request: pytest.FixtureRequest) -> Rig:
    return load_rig(request.param)


@pytest.fixture(scope="module")
def field() -> Rig:
    return load_rig("field_excavator")


def _arm_states(rig: Rig, shape: tuple[int, ...], seed: int) -> FloatArray:
    """Arm joint states uniform within the limits, stick limited to the excavator branch."""
    rng = np.random.default_rng(seed)
    high = rig.q_max_rad.copy()
    high[1] = min(high[1], 0.0)
    return rng.uniform(rig.q_min_rad, high, size=(*shape, 3))


def _swing_states(rig: Rig, shape: tuple[int, ...], seed: int) -> FloatArray:
    assert rig.swing is not None
    rng = np.random.default_rng(seed)
    q = np.empty((*shape, 4))
    q[..., 0] = rng.uniform(rig.swing.joint.min_rad, rig.swing.joint.max_rad, size=shape)
    q[..., 1:] = _arm_states(rig, shape, seed + 1)
    return q


def _angle_diff(a: FloatArray, b: FloatArray) -> FloatArray:
    return np.abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def _worst(err: FloatArray, **arrays: FloatArray) -> str:
    """The worst case of a batch as text; ``err`` has the batch shape, arrays ``(*batch, k)``."""
    flat = err.reshape(-1)
    i = int(np.argmax(flat))
    parts = [f"{k}={v.reshape(flat.size, -1)[i].tolist()!r}" for k, v in arrays.items()]
    return f"worst case {i}: error {flat[i]:.3e}; " + ", ".join(parts)


# Forward kinematics against the papers


def test_forward_reproduces_gao_table_2() -> None:
    bench = load_rig("test_bench")
    q = np.radians([angles for angles, _ in GAO_TABLE_2])
    tip = np.array([point for _, point in GAO_TABLE_2])
    got = forward(bench, q)[:, :2]
    err = np.abs(got - tip).max(axis=-1)
    assert np.all(err <= 0.005), f"FK of Gao Table 2 off by {err} m: {got}"


def test_inverse_reproduces_gao_table_2_angles() -> None:
    # Table 2 is the output of Gao's own IK at the printed (rounded) tips: ours must agree to
    # the effect of that rounding (~1 mm over ~1 m of lever).
    bench = load_rig("test_bench")
    angles = np.radians([a for a, _ in GAO_TABLE_2])
    tip = np.array([p for _, p in GAO_TABLE_2])
    q = inverse(bench, tip[:, 0], tip[:, 1], angles.sum(axis=-1))
    assert np.degrees(np.abs(q - angles)).max() < 0.2, np.degrees(q)


def _zhao_eq1(
    a: tuple[float, float, float, float], d1: float, t: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Zhao eq 1 as printed: joints theta1..theta4 (swing, boom, stick, bucket), Z up."""
    a1, a2, a3, a4 = a
    t1, t2, t3, t4 = t[..., 0], t[..., 1], t[..., 2], t[..., 3]
    x = (
        a4 * np.cos(t2 + t3 + t4) * np.cos(t1)
        + a3 * np.cos(t2 + t3) * np.cos(t1)
        + a2 * np.cos(t2) * np.cos(t1)
        + a1 * np.cos(t1)
    )
    y = (
        a4 * np.cos(t2 + t3 + t4) * np.sin(t1)
        + a3 * np.cos(t2 + t3) * np.sin(t1)
        + a2 * np.cos(t2) * np.sin(t1)
        + a1 * np.sin(t1)
    )
    z = a4 * np.sin(t2 + t3 + t4) + a3 * np.sin(t2 + t3) + a2 * np.sin(t2) + d1
    xi = t2 + t3 + t4
    return x, y, z, xi


def test_forward_3d_matches_zhao_eq1(field: Rig) -> None:
    assert field.swing is not None
    a = (field.swing.base_offset_m, *(float(v) for v in field.lengths_m))
    q = _swing_states(field, (2000,), seed=11)
    big_x, big_y, big_z, xi = _zhao_eq1(a, field.swing.base_height_m, q)
    # Ours (x, y, z) = (X, Z, -Y): a proper rotation (det +1), so the frame stays right-handed.
    mapping = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    assert np.linalg.det(mapping) == pytest.approx(1.0)
    expected = np.stack([big_x, big_z, -big_y, xi], axis=-1)
    got = forward_3d(field, q)
    err = np.abs(got - expected).max(axis=-1)
    assert err.max() < 1e-12, _worst(err, q=q, got=got, expected=expected)


def test_forward_3d_is_the_arm_plane_turned_about_y(field: Rig) -> None:
    assert field.swing is not None
    q = _swing_states(field, (500,), seed=12)
    arm = forward(field, q[..., 1:])
    got = forward_3d(field, q)
    radial = field.swing.base_offset_m + arm[..., 0]
    # Positive swing turns +x towards -z: a counter-clockwise turn about +y seen from above.
    assert np.allclose(np.hypot(got[..., 0], got[..., 2]), np.abs(radial), atol=1e-12)
    assert np.allclose(got[..., 1], field.swing.base_height_m + arm[..., 1], atol=1e-12)
    assert np.allclose(got[..., 3], arm[..., 2], atol=1e-15)
    at_zero = q.copy()
    at_zero[..., 0] = 0.0
    p0 = forward_3d(field, at_zero)
    assert np.allclose(p0[..., 0], radial, atol=1e-12)
    assert np.all(p0[..., 2] == 0.0)
    small = at_zero.copy()
    small[..., 0] = 1e-3
    assert np.all(np.sign(forward_3d(field, small)[..., 2]) == -np.sign(radial))


# Inverse kinematics: identities


def test_inverse_of_forward_is_identity(rig: Rig) -> None:
    q = _arm_states(rig, (40, 250), seed=1)
    pose = forward(rig, q)
    back = inverse(rig, pose[..., 0], pose[..., 1], pose[..., 2])
    err = np.abs(back - q).max(axis=-1)
    assert err.max() <= 1e-9, f"{rig.name}: " + _worst(err, q=q, pose=pose, back=back)


def test_inverse_of_forward_is_identity_with_swing(field: Rig) -> None:
    assert field.swing is not None
    q = _swing_states(field, (20000,), seed=2)
    radial = field.swing.base_offset_m + forward(field, q[..., 1:])[..., 0]
    # The front branch: the tip ahead of the swing axis (and clear of it, where theta0 is
    # ill-conditioned); tips behind the axis are tested below.
    q = q[radial > 0.05]
    pose = forward_3d(field, q)
    back = inverse_3d(field, pose[..., 0], pose[..., 1], pose[..., 2], pose[..., 3])
    err = np.maximum(
        _angle_diff(back[..., 0], q[..., 0]), np.abs(back[..., 1:] - q[..., 1:]).max(axis=-1)
    )
    assert err.max() <= 1e-9, _worst(err, q=q, pose=pose, back=back)


def test_inverse_3d_returns_the_front_solution_for_tips_behind_the_axis(field: Rig) -> None:
    assert field.swing is not None
    q = _swing_states(field, (20000,), seed=3)
    radial = field.swing.base_offset_m + forward(field, q[..., 1:])[..., 0]
    behind = q[radial < -0.05][:40]
    assert len(behind) > 0
    solved = 0
    for qi in behind:
        pose = forward_3d(field, qi)
        try:
            back = inverse_3d(field, *pose, check_limits=False)
        except UnreachableError:
            continue
        solved += 1
        assert np.abs(forward_3d(field, back) - pose).max() < 1e-9, (qi, pose, back)
        assert _angle_diff(back[0], qi[0] + np.pi) < 1e-9, (qi, back)
    assert solved > 0


def test_inverse_3d_on_the_swing_axis_returns_zero_swing(field: Rig) -> None:
    assert field.swing is not None
    target = np.array([0.0, field.swing.base_height_m + 1.0, 0.0, -np.pi / 2])
    q = inverse_3d(field, *target, check_limits=False)
    assert q[0] == 0.0
    assert np.abs(forward_3d(field, q) - target).max() < 1e-12


def test_inverse_hits_arbitrary_reachable_targets_on_the_excavator_branch(rig: Rig) -> None:
    # Targets drawn in Cartesian space, not from joint states: pivot anywhere in the annulus.
    rng = np.random.default_rng(4)
    l1, l2, l3 = rig.lengths_m
    n = 20000
    r = rng.uniform(abs(l1 - l2), l1 + l2, n)
    bearing = rng.uniform(-np.pi, np.pi, n)
    attitude = rng.uniform(-3 * np.pi, 3 * np.pi, n)
    x = r * np.cos(bearing) + l3 * np.cos(attitude)
    y = r * np.sin(bearing) + l3 * np.sin(attitude)
    q = inverse(rig, x, y, attitude, check_limits=False)
    assert np.all((q[:, 1] <= 0.0) & (q[:, 1] >= -np.pi))
    centre = 0.5 * (rig.q_min_rad + rig.q_max_rad)
    assert np.all(np.abs(q - centre) <= np.pi + 1e-12), "angles outside the window of their range"
    pose = forward(rig, q)
    err = np.maximum(
        np.abs(pose[:, :2] - np.stack([x, y], -1)).max(-1), _angle_diff(pose[:, 2], attitude)
    )
    assert err.max() < 1e-10, _worst(err, target=np.stack([x, y, attitude], -1), q=q)


def test_positive_stick_angles_come_back_mirrored() -> None:
    scale = load_rig("scale_model")
    assert scale.q_max_rad[1] > 0.0
    rng = np.random.default_rng(5)
    q = rng.uniform(scale.q_min_rad, scale.q_max_rad, size=(1000, 3))
    q[:, 1] = rng.uniform(0.01, scale.q_max_rad[1], 1000)
    pose = forward(scale, q)
    back = inverse(scale, pose[:, 0], pose[:, 1], pose[:, 2], check_limits=False)
    assert np.allclose(back[:, 1], -q[:, 1], atol=1e-12)
    assert np.allclose(forward(scale, back)[:, :2], pose[:, :2], atol=1e-12)


def test_full_extension_is_reachable_within_rounding(rig: Rig) -> None:
    q = np.array([0.3, 0.0, -0.2])
    pose = forward(rig, q)
    back = inverse(rig, *pose, check_limits=False)
    assert abs(back[1]) < 1e-6, back
    assert np.abs(forward(rig, back)[:2] - pose[:2]).max() < 1e-12


def test_joint_limit_corners_pass_the_limit_check(rig: Rig) -> None:
    low, high = rig.q_min_rad, rig.q_max_rad.copy()
    high[1] = min(high[1], -1e-3)
    corners = np.array(np.meshgrid(*zip(low, high, strict=True), indexing="ij")).reshape(3, -1).T
    pose = forward(rig, corners)
    back = inverse(rig, pose[:, 0], pose[:, 1], pose[:, 2])
    assert np.all((back >= rig.q_min_rad) & (back <= rig.q_max_rad)), back
    assert np.abs(back - corners).max() < 1e-9


# Inverse kinematics: failures


def _target_with_pivot_at(rig: Rig, distance_m: float) -> tuple[float, float, float]:
    attitude, bearing = -1.0, 0.4
    l3 = float(rig.lengths_m[2])
    return (
        distance_m * math.cos(bearing) + l3 * math.cos(attitude),
        distance_m * math.sin(bearing) + l3 * math.sin(attitude),
        attitude,
    )


def test_unreachable_targets_raise(rig: Rig) -> None:
    l1, l2, _ = (float(v) for v in rig.lengths_m)
    for distance in ((l1 + l2) * (1 + 1e-6), l1 + l2 + 0.5, abs(l1 - l2) * 0.5):
        with pytest.raises(UnreachableError, match="from the boom foot pin") as info:
            inverse(rig, *_target_with_pivot_at(rig, distance))
        assert f"{distance:.6g} m" in str(info.value)
        assert f"[{abs(l1 - l2):.6g}, {l1 + l2:.6g}] m" in str(info.value)


def test_unreachable_target_in_a_batch_names_its_index(rig: Rig) -> None:
    l1, l2, _ = (float(v) for v in rig.lengths_m)
    good = forward(rig, _arm_states(rig, (4,), seed=6))
    x, y, att = good[:, 0].copy(), good[:, 1].copy(), good[:, 2].copy()
    x[2], y[2], att[2] = _target_with_pivot_at(rig, l1 + l2 + 0.1)
    with pytest.raises(UnreachableError, match=r"batch index \(2,\)"):
        inverse(rig, x, y, att)


def test_joint_limit_violations_name_the_joint() -> None:
    bench = load_rig("test_bench")
    cases = {
        "boom": (80.0, -60.0, 0.0),
        "stick": (30.0, -20.0, 0.0),
        "bucket": (30.0, -60.0, 50.0),
    }
    for joint, degrees in cases.items():
        q = np.radians(degrees)
        pose = forward(bench, q)
        with pytest.raises(JointLimitError, match=joint) as info:
            inverse(bench, *pose)
        assert info.value.joint == joint
        assert np.allclose(inverse(bench, *pose, check_limits=False), q, atol=1e-12)


def test_joint_limit_violation_in_a_batch_names_the_first_offender() -> None:
    bench = load_rig("test_bench")
    q = np.radians([[30.0, -60.0, 0.0], [30.0, -60.0, 0.0], [30.0, -60.0, 50.0], [80.0, -60, 0]])
    pose = forward(bench, q)
    with pytest.raises(JointLimitError, match="bucket") as info:
        inverse(bench, pose[:, 0], pose[:, 1], pose[:, 2])
    assert "batch index (2,)" in " ".join(info.value.__notes__)


def test_out_of_range_angles_come_back_nearest_the_range() -> None:
    scale = load_rig("scale_model")  # bucket -160..5 deg
    q = np.radians([10.0, -60.0, -170.0])
    pose = forward(scale, q)
    back = inverse(scale, *pose, check_limits=False)
    assert np.degrees(back[2]) == pytest.approx(-170.0, abs=1e-9)
    with pytest.raises(JointLimitError, match=r"bucket joint at -170\.000 deg"):
        inverse(scale, *pose)


def test_swing_limits_are_checked(field: Rig) -> None:
    assert field.swing is not None
    swing = replace(field.swing, joint=replace(field.swing.joint, min_rad=-0.5, max_rad=0.5))
    narrow = replace(field, swing=swing)
    q = np.array([1.0, 0.3, -1.0, -0.5])
    pose = forward_3d(narrow, q)
    with pytest.raises(JointLimitError, match="swing"):
        inverse_3d(narrow, *pose)


def test_three_d_functions_refuse_planar_rigs() -> None:
    for name in RIGS:
        planar = load_rig(name)
        if planar.swing is not None:
            continue
        with pytest.raises(ConfigurationError, match="swing"):
            forward_3d(planar, np.zeros(4))
        with pytest.raises(ConfigurationError, match="planar"):
            inverse_3d(planar, 1.0, 0.0, 0.0, 0.0)


def test_bad_inputs_raise_value_error(field: Rig) -> None:
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        forward_3d(field, np.zeros(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        forward(field, np.zeros(4))
    with pytest.raises(ValueError, match="broadcast"):
        inverse(field, np.ones(3), np.ones(4), 0.0)
    with pytest.raises(ValueError, match="y_m must be finite"):
        inverse(field, 3.0, np.nan, 0.0)


# Differential kinematics


def test_jacobian_matches_central_differences(rig: Rig) -> None:
    q = _arm_states(rig, (200,), seed=7)
    h = 1e-6
    steps = np.eye(3) * h
    fd = np.stack(
        [(forward(rig, q + steps[j]) - forward(rig, q - steps[j])) / (2 * h) for j in range(3)],
        axis=-1,
    )
    jac = jacobian(rig, q)
    err = np.abs(jac - fd).max(axis=(-2, -1))
    assert err.max() < 1e-8, _worst(err, q=q)


def test_tip_velocity_is_the_time_derivative_of_the_pose(rig: Rig) -> None:
    rng = np.random.default_rng(8)
    q = _arm_states(rig, (200,), seed=8)
    qd = rng.uniform(-rig.qd_max_rad_s, rig.qd_max_rad_s, size=q.shape)
    v = tip_velocity(rig, q, qd)
    dt = 1e-6
    fd = (forward(rig, q + qd * dt) - forward(rig, q - qd * dt)) / (2 * dt)
    assert np.abs(v - fd).max() < 1e-8
    assert np.allclose(v[:, 2], qd.sum(axis=-1), atol=1e-15)
    assert np.allclose(v, np.einsum("nij,nj->ni", jacobian(rig, q), qd), atol=1e-15)


def test_joint_positions_end_at_the_tip(rig: Rig) -> None:
    q = _arm_states(rig, (100,), seed=9)
    points = joint_positions(rig, q)
    assert np.allclose(points[:, 3], forward(rig, q)[:, :2], atol=1e-12)
    lengths = np.linalg.norm(np.diff(points, axis=-2), axis=-1)
    assert np.allclose(lengths, rig.lengths_m, atol=1e-12)


# Shapes


def test_shapes(rig: Rig) -> None:
    assert forward(rig, np.zeros(3)).shape == (3,)
    assert inverse(rig, *forward(rig, _arm_states(rig, (), seed=10))).shape == (3,)
    q = _arm_states(rig, (5, 7), seed=10)
    pose = forward(rig, q)
    assert pose.shape == (5, 7, 3)
    assert jacobian(rig, q).shape == (5, 7, 3, 3)
    assert inverse(rig, pose[..., 0], pose[..., 1], pose[..., 2]).shape == (5, 7, 3)
    # Scalars and arrays broadcast together: x (5, 1), y (7,), one attitude.
    x = np.full((5, 1), pose[0, 0, 0])
    y = np.full(7, pose[0, 0, 1])
    spread = inverse(rig, x, y, float(pose[0, 0, 2]))
    assert spread.shape == (5, 7, 3)
    assert np.abs(spread - q[0, 0]).max() < 1e-9


def test_shapes_3d(field: Rig) -> None:
    q = _swing_states(field, (5, 7), seed=13)
    pose = forward_3d(field, q)
    assert pose.shape == (5, 7, 4)
    assert forward_3d(field, q[0, 0]).shape == (4,)
    assert inverse_3d(field, *pose[0, 0], check_limits=False).shape == (4,)
    back = inverse_3d(
        field, pose[..., 0], pose[..., 1], pose[..., 2], pose[..., 3], check_limits=False
    )
    assert back.shape == (5, 7, 4)


@pytest.mark.parametrize("name", profile_names())
def test_tip_state_equals_forward_and_tip_velocity(name: str) -> None:
    rig = load_rig(name)
    rng = np.random.default_rng(7)
    q = rng.uniform(rig.q_min_rad, rig.q_max_rad, size=(4, 9, 3))
    qd = rng.normal(size=(4, 9, 3))
    pose, twist = kinematics.tip_state(rig, q, qd)
    np.testing.assert_allclose(pose, kinematics.forward(rig, q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(twist, kinematics.tip_velocity(rig, q, qd), rtol=0, atol=1e-12)


# -- FastArm: the unchecked hot-path twin of forward / inverse --------------------------------


def test_fast_arm_matches_forward_and_inverse(rig: Rig) -> None:
    arm = kinematics.FastArm(rig)
    rng = np.random.default_rng(7)
    lo, hi = np.asarray(rig.q_min_rad), np.asarray(rig.q_max_rad)
    q = lo + (hi - lo) * rng.random((400, 3))
    tip = forward(rig, q)
    x, y = arm.tip_xy(q)
    np.testing.assert_allclose(x, tip[:, 0], atol=1e-12)
    np.testing.assert_allclose(y, tip[:, 1], atol=1e-12)
    for i in range(0, 400, 37):
        np.testing.assert_allclose(arm.tip(q[i]), tip[i], atol=1e-12)
    # Batched IK: every pose forward() made is reachable; where inverse() accepts the pose
    # within the limits, both give the same angles (the excavator branch).
    qi, ok = arm.ik_many(tip[:, 0], tip[:, 1], tip[:, 2])
    ref = inverse(rig, tip[:, 0], tip[:, 1], tip[:, 2], check_limits=False)
    within = np.all((ref >= lo) & (ref <= hi), axis=1)
    np.testing.assert_array_equal(ok, within)
    np.testing.assert_allclose(qi[ok], ref[ok], atol=1e-12)
    assert ok.sum() > 100
    # Scalar IK agrees with the batch and refuses what the batch flags.
    for i in range(0, 400, 13):
        one = arm.ik(float(tip[i, 0]), float(tip[i, 1]), float(tip[i, 2]))
        if ok[i]:
            assert one is not None
            np.testing.assert_allclose(one, ref[i], atol=1e-12)
        elif not np.all((ref[i] >= lo - 1e-9) & (ref[i] <= hi + 1e-9)):
            assert one is None


def test_fast_arm_refuses_unreachable_poses(rig: Rig) -> None:
    arm = kinematics.FastArm(rig)
    far = 2.0 * float(sum(rig.lengths_m))
    assert arm.ik(far, 0.0, 0.0) is None
    _, ok = arm.ik_many(np.array([far, 0.0]), np.array([0.0, 0.0]), np.array([0.0, 0.0]))
    assert not ok[0]
