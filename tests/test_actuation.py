"""Joint <-> cylinder stroke mapping: inverses, derivatives, directions, the bucket four-bar
checked by independent constructions, and broken geometries rejected by the loader."""

from __future__ import annotations

import copy
import math
import tomllib
from typing import Any

import numpy as np
import pytest
from scipy.optimize import least_squares

from rt_runtime import actuation
from rt_runtime.errors import JointLimitError, KinematicsError, RigProfileError
from rt_runtime.rig import Rig, load_rig, parse_rig, profile_names
from rt_runtime.rig.loader import PROFILE_DIR

RIGS = profile_names()


def _raw(name: str) -> dict[str, Any]:
    return tomllib.loads((PROFILE_DIR / f"{name}.toml").read_text())


def _random_q(rig: Rig, n: int, seed: int) -> np.ndarray:
    """Uniform joint angles over the ranges plus every corner of the range box."""
    rng = np.random.default_rng(seed)
    lo, hi = rig.q_min_rad, rig.q_max_rad
    corners = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1).T
    return np.concatenate([corners, lo + (hi - lo) * rng.random((n, 3))])


def _worst(err: np.ndarray, inputs: np.ndarray) -> str:
    i = np.unravel_index(int(np.nanargmax(err)), err.shape)
    return f"max error {float(err[i]):.3e} at input {inputs[i[0]].tolist()}"


@pytest.mark.parametrize("name", RIGS)
def test_joint_to_stroke_and_back_over_the_joint_ranges(name: str) -> None:
    rig = load_rig(name)
    q = _random_q(rig, 20_000, seed=1)
    q_back = actuation.stroke_to_joint(rig, actuation.joint_to_stroke(rig, q))
    err = np.abs(q_back - q)
    assert np.all(err <= 1e-9), _worst(err, q)


@pytest.mark.parametrize("name", RIGS)
def test_stroke_to_joint_and_back_over_the_whole_travel(name: str) -> None:
    rig = load_rig(name)
    lo, hi = actuation.stroke_limits(rig)
    rng = np.random.default_rng(2)
    ends = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1).T
    s = np.concatenate([ends, lo + (hi - lo) * rng.random((20_000, 3))])
    q = actuation.stroke_to_joint(rig, s)
    assert np.all(np.isfinite(q)), "every stroke of the travel must map to a joint angle"
    err = np.abs(actuation.joint_to_stroke(rig, q, check_limits=False) - s)
    assert np.all(err <= 1e-9), _worst(err, s)


@pytest.mark.parametrize("name", RIGS)
def test_strokes_monotonic_inside_travel_in_gao_fig4_directions(name: str) -> None:
    rig = load_rig(name)
    lo, hi = actuation.stroke_limits(rig)
    n = 4001
    q = np.linspace(rig.q_min_rad, rig.q_max_rad, n)  # each column sweeps its full range
    s = actuation.joint_to_stroke(rig, q)
    assert np.all(s >= lo) and np.all(s <= hi), f"strokes {s.min(0)}..{s.max(0)} vs {hi}"
    ds = np.diff(s, axis=0)
    # Gao Fig. 4: boom stroke grows with theta1; stick and bucket strokes grow as theta2, theta3
    # decrease.
    assert np.all(ds[:, 0] > 0), f"boom not increasing at q={q[int(np.argmin(ds[:, 0]))]}"
    assert np.all(ds[:, 1] < 0), f"stick not decreasing at q={q[int(np.argmax(ds[:, 1]))]}"
    assert np.all(ds[:, 2] < 0), f"bucket not decreasing at q={q[int(np.argmax(ds[:, 2]))]}"
    jac = actuation.stroke_jacobian(rig, q)
    assert np.all(jac[:, 0] > 0) and np.all(jac[:, 1:] < 0)


@pytest.mark.parametrize("name", RIGS)
def test_stroke_velocity_matches_finite_differences(name: str) -> None:
    rig = load_rig(name)
    rng = np.random.default_rng(3)
    q = _random_q(rig, 2000, seed=4)
    qd = rng.normal(size=q.shape)
    h = 1e-6
    fd = (
        actuation.joint_to_stroke(rig, q + h * qd, check_limits=False)
        - actuation.joint_to_stroke(rig, q - h * qd, check_limits=False)
    ) / (2 * h)
    sd = actuation.stroke_velocity(rig, q, qd)
    err = np.abs(sd - fd) / (1e-3 + np.abs(fd))
    assert np.all(err < 1e-6), _worst(err, q)


@pytest.mark.parametrize("name", RIGS)
def test_mapping_is_diagonal(name: str) -> None:
    rig = load_rig(name)
    q = _random_q(rig, 500, seed=5)
    s = actuation.joint_to_stroke(rig, q)
    for j in range(3):
        moved = q.copy()
        moved[:, j] = np.where(q[:, j] > 0.5 * (rig.q_min_rad[j] + rig.q_max_rad[j]), -0.1, 0.1)
        moved[:, j] = q[:, j] + moved[:, j]
        s_moved = actuation.joint_to_stroke(rig, moved, check_limits=False)
        others = [i for i in range(3) if i != j]
        assert np.array_equal(s_moved[:, others], s[:, others])


@pytest.mark.parametrize("name", RIGS)
def test_joint_velocity_inverts_stroke_velocity_and_matches_finite_differences(
    name: str,
) -> None:
    rig = load_rig(name)
    rng = np.random.default_rng(6)
    q = _random_q(rig, 2000, seed=7)
    qd = rng.normal(size=q.shape)
    s = actuation.joint_to_stroke(rig, q)
    sd = actuation.stroke_velocity(rig, q, qd)
    back = actuation.joint_velocity(rig, s, sd, check_limits=False)
    err = np.abs(back - qd) / (1.0 + np.abs(qd))
    assert np.all(err < 1e-8), _worst(err, q)
    # Independently: the time derivative of stroke_to_joint along a stroke path.
    lo, hi = actuation.stroke_limits(rig)
    s_in = lo + (hi - lo) * (0.01 + 0.98 * rng.random((2000, 3)))
    sd_in = rng.normal(size=s_in.shape) * hi
    h = 1e-7
    fd = (
        actuation.stroke_to_joint(rig, s_in + h * sd_in)
        - actuation.stroke_to_joint(rig, s_in - h * sd_in)
    ) / (2 * h)
    qd_in = actuation.joint_velocity(rig, s_in, sd_in)
    err = np.abs(qd_in - fd) / (1e-2 + np.abs(fd))
    assert np.all(err < 1e-5), _worst(err, s_in)


@pytest.mark.parametrize("name", RIGS)
def test_torque_from_force_is_virtual_work(name: str) -> None:
    rig = load_rig(name)
    rng = np.random.default_rng(8)
    q = _random_q(rig, 2000, seed=9)
    force = rng.normal(scale=1e4, size=q.shape)
    tau = actuation.torque_from_force(rig, q, force)
    h = 1e-6
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        ds = (
            actuation.joint_to_stroke(rig, q + step, check_limits=False)[:, j]
            - actuation.joint_to_stroke(rig, q - step, check_limits=False)[:, j]
        )
        work = force[:, j] * ds  # cylinder work over the virtual displacement 2h
        err = np.abs(tau[:, j] * 2 * h - work) / (1e-9 + np.abs(work))
        assert np.all(err < 1e-6), _worst(err, q)
    # Power balance for any motion: sum tau * qd == sum F * sd.
    qd = rng.normal(size=q.shape)
    power_joint = np.sum(tau * qd, axis=-1)
    power_cyl = np.sum(force * actuation.stroke_velocity(rig, q, qd), axis=-1)
    np.testing.assert_allclose(power_joint, power_cyl, rtol=1e-12, atol=1e-9)


def _fixed_points_from_gao_angles(rig: Rig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """G, I and H in the stick frame built with rotation matrices from the printed angles."""
    b = rig.cylinders.bucket

    def rot(a: float) -> np.ndarray:
        return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

    g = np.array([rig.lengths_m[1], 0.0])
    gd = np.array([-1.0, 0.0])
    i = g + b.l_ig_m * rot(-b.angle_igd_rad) @ gd  # G->D turned clockwise by IGD
    ig = (g - i) / np.linalg.norm(g - i)
    h = i + b.l_hi_m * rot(b.angle_hig_rad) @ ig  # I->G turned counter-clockwise by HIG
    return g, i, h


@pytest.mark.parametrize("name", RIGS)
def test_bucket_four_bar_against_independent_construction(name: str) -> None:
    rig = load_rig(name)
    b = rig.cylinders.bucket
    g, i, h = _fixed_points_from_gao_angles(rig)
    rng = np.random.default_rng(10)
    theta3 = rng.uniform(rig.q_min_rad[2], rig.q_max_rad[2], 200)
    pts = actuation.bucket_linkage_points(rig, theta3)
    np.testing.assert_allclose(pts.g_m, np.broadcast_to(g, pts.g_m.shape), atol=1e-12)
    np.testing.assert_allclose(pts.i_m, np.broadcast_to(i, pts.i_m.shape), atol=1e-12)
    np.testing.assert_allclose(pts.h_m, np.broadcast_to(h, pts.h_m.shape), atol=1e-12)
    # Loop closure: every bar has its length, the bucket lever sits at theta3 + LGK.
    gk = pts.k_m - g
    np.testing.assert_allclose(np.linalg.norm(gk, axis=-1), b.l_gk_m, atol=1e-12)
    lever = np.arctan2(gk[:, 1], gk[:, 0])
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (lever - theta3 - b.angle_lgk_rad))), 0.0, atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.norm(pts.j_m - i, axis=-1), b.l_ij_m, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pts.j_m - pts.k_m, axis=-1), b.l_jk_m, atol=1e-12)
    stroke = actuation.joint_to_stroke(
        rig,
        np.stack([np.zeros_like(theta3), np.zeros_like(theta3), theta3], -1),
        check_limits=False,
    )[:, 2]
    np.testing.assert_allclose(
        np.linalg.norm(pts.j_m - h, axis=-1), stroke + b.retracted_length_m, atol=1e-12
    )
    # Gao eq 13, first line: theta3 = pi - IGD - LGK - IGK, IGK from G->K to G->I.
    gi = i - g
    igk = np.mod(math.atan2(gi[1], gi[0]) - lever, 2 * math.pi)
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (math.pi - b.angle_igd_rad - b.angle_lgk_rad - igk - theta3))),
        0.0,
        atol=1e-12,
    )
    # J solved again by a numerical root finder from a start on the backhoe branch's side (left of
    # I->K, a quarter turn off): it must land on the closed-form J.
    for n in range(len(theta3)):
        k = pts.k_m[n]
        ik = k - i
        start = i + b.l_ij_m * np.array([-ik[1], ik[0]]) / np.linalg.norm(ik)
        sol = least_squares(
            lambda j, k=k: [np.linalg.norm(j - i) - b.l_ij_m, np.linalg.norm(j - k) - b.l_jk_m],
            start,
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
        )
        assert np.linalg.norm(sol.x - pts.j_m[n]) < 1e-9, (
            f"theta3={theta3[n]!r}: closed form J={pts.j_m[n]}, root finder J={sol.x}"
        )


@pytest.mark.parametrize("name", RIGS)
def test_bucket_inverse_against_numerical_loop_closure(name: str) -> None:
    """Solve |HJ| = L, |IJ| = l_ij, |JK(theta3)| = l_jk for (J, theta3) numerically."""
    rig = load_rig(name)
    b = rig.cylinders.bucket
    _, i, h = _fixed_points_from_gao_angles(rig)
    g = np.array([rig.lengths_m[1], 0.0])
    rng = np.random.default_rng(11)
    lo, hi = actuation.stroke_limits(rig)
    for s in rng.uniform(lo[2], hi[2], 40):
        length = s + b.retracted_length_m
        q = actuation.stroke_to_joint(rig, [0.0, 0.0, s], check_limits=False)
        theta3 = float(q[2])

        def residual(x: np.ndarray, length: float = length) -> list[float]:
            j, t = x[:2], x[2]
            k = g + b.l_gk_m * np.array(
                [math.cos(t + b.angle_lgk_rad), math.sin(t + b.angle_lgk_rad)]
            )
            return [
                float(np.linalg.norm(j - h)) - length,
                float(np.linalg.norm(j - i)) - b.l_ij_m,
                float(np.linalg.norm(j - k)) - b.l_jk_m,
            ]

        j0 = actuation.bucket_linkage_points(rig, theta3).j_m
        start = np.array([*(j0 + 0.02 * b.l_ij_m), theta3 + 0.03])
        sol = least_squares(residual, start, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert abs(sol.x[2] - theta3) < 1e-9, (
            f"stroke {s!r}: closed form {theta3}, solver {sol.x[2]}"
        )


@pytest.mark.parametrize("name", RIGS)
def test_linkage_stays_clear_of_dead_points(name: str) -> None:
    rig = load_rig(name)
    theta3 = np.linspace(rig.q_min_rad[2], rig.q_max_rad[2], 2001)
    angles = actuation.transmission_angles_rad(rig, theta3)
    assert np.all(angles >= actuation.TRANSMISSION_ANGLE_MIN_RAD)
    assert np.all(angles <= math.pi - actuation.TRANSMISSION_ANGLE_MIN_RAD)
    for axis, cyl in ((0, rig.cylinders.boom), (1, rig.cylinders.stick)):
        phi = cyl.angle_sign * np.array([rig.q_min_rad[axis], rig.q_max_rad[axis]])
        phi = phi + cyl.angle_offset_rad
        assert np.all((phi > 0) & (phi < math.pi)), (name, axis, np.degrees(phi))


@pytest.mark.parametrize("name", RIGS)
def test_cylinder_proportions_look_like_real_cylinders(name: str) -> None:
    rig = load_rig(name)
    for cyl in (rig.cylinders.boom, rig.cylinders.stick, rig.cylinders.bucket):
        assert cyl.stroke_max_m <= 0.9 * cyl.retracted_length_m


def test_shapes_and_stroke_limits() -> None:
    rig = load_rig("scale_model")
    q = _random_q(rig, 10, seed=12)[:10].reshape(2, 5, 3)
    for out in (
        actuation.joint_to_stroke(rig, q),
        actuation.stroke_jacobian(rig, q),
        actuation.stroke_velocity(rig, q, np.ones(3)),
        actuation.torque_from_force(rig, q, np.ones(3)),
        actuation.stroke_to_joint(rig, actuation.joint_to_stroke(rig, q)),
    ):
        assert out.shape == (2, 5, 3)
    one = actuation.joint_to_stroke(rig, q[0, 0].tolist())
    assert one.shape == (3,)
    np.testing.assert_array_equal(one, actuation.joint_to_stroke(rig, q)[0, 0])
    lo, hi = actuation.stroke_limits(rig)
    assert lo.tolist() == [0.0, 0.0, 0.0]
    c = rig.cylinders
    assert hi.tolist() == [c.boom.stroke_max_m, c.stick.stroke_max_m, c.bucket.stroke_max_m]
    with pytest.raises(ValueError, match=r"q_rad must have shape \(\.\.\., 3\)"):
        actuation.joint_to_stroke(rig, np.zeros(4))
    with pytest.raises(ValueError, match="must broadcast"):
        actuation.stroke_velocity(rig, np.zeros((4, 3)), np.zeros((5, 3)))


def test_out_of_range_input_names_the_axis() -> None:
    rig = load_rig("scale_model")
    q = 0.5 * (rig.q_min_rad + rig.q_max_rad)
    bad = np.tile(q, (4, 1))
    bad[2, 1] = rig.q_max_rad[1] + 0.01
    with pytest.raises(JointLimitError, match="stick joint at") as info:
        actuation.joint_to_stroke(rig, bad)
    assert info.value.joint == "stick"
    assert any("(2,)" in note for note in info.value.__notes__)
    nan = q.copy()
    nan[0] = np.nan
    with pytest.raises(JointLimitError, match="boom"):
        actuation.torque_from_force(rig, nan, np.ones(3))
    _, hi = actuation.stroke_limits(rig)
    s = 0.5 * hi
    s_bad = s.copy()
    s_bad[2] = hi[2] + 1e-3
    with pytest.raises(KinematicsError, match=r"bucket cylinder stroke .* outside its travel"):
        actuation.stroke_to_joint(rig, s_bad)
    s_bad = s.copy()
    s_bad[0] = -1e-4
    with pytest.raises(KinematicsError, match="boom cylinder stroke"):
        actuation.joint_velocity(rig, s_bad, np.zeros(3))
    # Unchecked: defined a little beyond the limits, NaN where the geometry cannot close.
    beyond = q.copy()
    beyond[1] = rig.q_max_rad[1] + math.radians(0.5)
    assert np.all(np.isfinite(actuation.joint_to_stroke(rig, beyond, check_limits=False)))
    far = actuation.stroke_to_joint(rig, [0.0, 0.0, 10.0], check_limits=False)
    assert np.isnan(far[2]) and np.all(np.isfinite(far[:2]))


def _assert_rejected(raw: dict[str, Any], key: str, message: str) -> None:
    with pytest.raises(RigProfileError, match=message) as info:
        parse_rig(raw, source="broken.toml")
    assert info.value.key_path == key, str(info.value)
    assert str(info.value).startswith("broken.toml: ")


def test_four_bar_that_cannot_assemble_is_rejected() -> None:
    raw = _raw("field_excavator")
    raw["cylinders"]["bucket"]["l_jk_m"] = 1.5  # longer than l_ij + |IK| allows anywhere
    _assert_rejected(raw, "cylinders.bucket", "cannot assemble")


def test_four_bar_near_a_dead_point_is_rejected() -> None:
    raw = _raw("scale_model")
    raw["joints"]["bucket"]["min_deg"] = -220.0  # far past the linkage's design range
    raw["cylinders"]["bucket"]["stroke_max_m"] = 0.25
    _assert_rejected(raw, "cylinders.bucket", r"theta3 = -2\d\d\.\d\d deg .* transmission angle")
    # Within the joint range but with a travel longer than the linkage can follow.
    raw["joints"]["bucket"]["min_deg"] = -165.0
    _assert_rejected(raw, "cylinders.bucket", "does not assemble in the backhoe layout")


def test_stroke_too_short_for_the_range_is_rejected() -> None:
    raw = _raw("test_bench")
    raw["cylinders"]["bucket"]["stroke_max_m"] *= 0.8
    _assert_rejected(raw, "cylinders.bucket.stroke_max_m", "too short")
    raw = _raw("yang_pan_excavator")
    raw["cylinders"]["stick"]["stroke_max_m"] -= 0.05
    _assert_rejected(raw, "cylinders.stick.stroke_max_m", "too short")


def test_retracted_length_too_long_is_rejected() -> None:
    raw = _raw("scale_model")
    raw["cylinders"]["boom"]["retracted_length_m"] += 0.01
    _assert_rejected(raw, "cylinders.boom.retracted_length_m", "cannot reach that joint limit")


def test_travel_past_the_dead_point_is_rejected() -> None:
    raw = _raw("field_excavator")
    raw["cylinders"]["stick"]["stroke_max_m"] = 1.5
    _assert_rejected(raw, "cylinders.stick.stroke_max_m", "dead point")
    raw = _raw("yang_pan_excavator")
    raw["cylinders"]["bucket"]["stroke_max_m"] += 0.3
    _assert_rejected(raw, "cylinders.bucket", r"over the cylinder travel|backhoe layout")


def test_included_angle_leaving_zero_to_pi_is_rejected() -> None:
    raw = _raw("scale_model")
    raw["cylinders"]["stick"]["angle_offset_deg"] = 5.0  # phi = -theta2 + 5 < 0 at theta2 = 10
    _assert_rejected(raw, "cylinders.stick.angle_offset_deg", "strictly monotonic")


def test_stroke_sign_is_not_profile_data() -> None:
    raw = copy.deepcopy(_raw("scale_model"))
    raw["cylinders"]["boom"]["angle_sign"] = 1
    _assert_rejected(raw, "cylinders.boom.angle_sign", "unknown key")
