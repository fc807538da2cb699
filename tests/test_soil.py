"""Digging resistance (Yao eq 8, Yang/Pan eq 13-18): identities, hand-computed plates and an
independent plate-by-plate implementation of the fluid model; seeded random states print the
failing case."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable
from typing import cast

import numpy as np
import pytest
from numpy.typing import NDArray

from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import FluidSoil, Rig, load_rig
from rt_runtime.soil import (
    DEFAULT_SPEED_REG_M_S,
    SurfaceProfile,
    fluid_resistance,
    yao_resistance,
)

FloatArray = NDArray[np.float64]
RIGS = ("scale_model", "test_bench", "field_excavator", "yang_pan_excavator")


@pytest.fixture(scope="module")
def scale() -> Rig:
    return load_rig("scale_model")


def _plate_rig(rig: Rig, profile: tuple[tuple[float, float], ...]) -> Rig:
    """``rig`` with another bucket outline (a flat plate lets forces be computed by hand)."""
    return dataclasses.replace(rig, bucket=dataclasses.replace(rig.bucket, profile_m=profile))


def _cross2(r: FloatArray, f: FloatArray) -> FloatArray:
    return np.asarray(r[..., 0] * f[..., 1] - r[..., 1] * f[..., 0], dtype=np.float64)


def _reference_plates(
    rig: Rig,
    soil: FluidSoil,
    pose: FloatArray,
    twist: FloatArray,
    height: Callable[[float], float],
    n: int,
    reg: float = DEFAULT_SPEED_REG_M_S,
) -> tuple[FloatArray, FloatArray]:
    """Plate centres and forces of one state, arm frame, plate by plate with 3-D cross products.

    Written from the paper's equations independently of the module's bucket-frame matrices.
    """
    x, y, att = pose
    rot = np.array([[math.cos(att), -math.sin(att)], [math.sin(att), math.cos(att)]])
    outline = [rot @ np.asarray(p, dtype=np.float64) for p in rig.bucket.profile_m]
    tip = np.array([x, y])
    centres: list[FloatArray] = []
    forces: list[FloatArray] = []
    for a, b in itertools.pairwise(outline):
        seg = b - a
        length = float(np.linalg.norm(seg))
        tangent = seg / length
        normal = np.array([-tangent[1], tangent[0]])
        area = length / n * rig.bucket.width_m
        for j in range(n):
            r = a + (j + 0.5) / n * seg
            p = tip + r
            depth = height(float(p[0])) - p[1]
            if depth <= 0.0:
                continue
            v = twist[:2] + np.cross([0.0, 0.0, twist[2]], [r[0], r[1], 0.0])[:2]
            v_n = (v @ normal) * normal
            v_t = (v @ tangent) * tangent
            pressure = soil.density_kg_m3 * rig.gravity_m_s2 * depth  # eq 13
            mag = (soil.kp * pressure + soil.kv * np.linalg.norm(v_n)) * area  # |N|, eq 15
            big_n = -mag * v_n / max(float(np.linalg.norm(v_n)), reg)
            fric = -soil.ks * mag * v_t / max(float(np.linalg.norm(v_t)), reg)  # eq 16
            centres.append(p)
            forces.append(big_n + fric)
    return np.array(centres).reshape(-1, 2), np.array(forces).reshape(-1, 2)


def _random_surface(rng: np.random.Generator, y0: float, scale_m: float) -> SurfaceProfile:
    x = np.cumsum(rng.uniform(0.05, 0.5, 12) * scale_m) - 1.0 * scale_m
    y = y0 + np.cumsum(rng.normal(0.0, 0.1 * scale_m, 12))
    return SurfaceProfile(x, y)


# ---------------------------------------------------------------------------------------------
# SurfaceProfile


def test_surface_interpolates_linearly_and_extrapolates_constantly() -> None:
    surf = SurfaceProfile(np.array([0.0, 1.0, 3.0]), np.array([-0.2, 0.0, -1.0]))
    x = np.array([[-5.0, 0.0, 0.25], [2.0, 3.0, 10.0]])
    expected = np.array([[-0.2, -0.2, -0.15], [-0.5, -1.0, -1.0]])
    np.testing.assert_allclose(surf.height_at(x), expected, atol=1e-15)
    assert surf.height_at(0.5).shape == ()
    flat = SurfaceProfile.flat(-0.25)
    np.testing.assert_array_equal(flat.height_at(np.linspace(-9, 9, 7)), np.full(7, -0.25))


def test_surface_copies_and_freezes_its_arrays() -> None:
    x = np.array([0.0, 1.0])
    y = np.array([0.0, 1.0])
    surf = SurfaceProfile(x, y)
    x[1] = 0.0  # the caller's buffer changes; the profile does not
    assert surf.x_m[1] == 1.0
    with pytest.raises(ValueError):
        surf.y_m[0] = 5.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        surf.x_m = x  # type: ignore[misc]


@pytest.mark.parametrize(
    ("x", "y", "error", "words"),
    [
        ([0.0, 1.0, 1.0], [0.0, 0.0, 0.0], ConfigurationError, "strictly increasing"),
        ([0.0, 2.0, 1.0], [0.0, 0.0, 0.0], ConfigurationError, "x_m[2]"),
        ([0.0, math.nan], [0.0, 0.0], ConfigurationError, "finite"),
        ([0.0, 1.0], [0.0, math.inf], ConfigurationError, "finite"),
        ([0.0, 1.0], [0.0], ValueError, "same length"),
        ([[0.0, 1.0]], [[0.0, 1.0]], ValueError, "1-D"),
        ([], [], ValueError, "n >= 1"),
    ],
)
def test_surface_rejects_bad_input(
    x: list[float], y: list[float], error: type[Exception], words: str
) -> None:
    with pytest.raises(error) as info:
        SurfaceProfile(np.array(x), np.array(y))
    assert words in str(info.value), str(info.value)


def test_flat_surface_rejects_non_finite_height(scale: Rig) -> None:
    with pytest.raises(ConfigurationError, match="h_m"):
        SurfaceProfile.flat(math.nan)
    with pytest.raises(ConfigurationError, match="h_m"):
        yao_resistance(scale, [0.5, -0.3, -2.0], [-0.1, 0.0, 0.0], math.inf)


# ---------------------------------------------------------------------------------------------
# Both models


@pytest.mark.parametrize("name", RIGS)
def test_bucket_above_the_surface_feels_nothing(name: str) -> None:
    rig = load_rig(name)
    rng = np.random.default_rng(11)
    n = 500
    surface = -3.0
    reach = float(np.linalg.norm(rig.bucket.profile_m, axis=1).max())
    pose = np.stack(
        [
            rng.uniform(-2.0, 5.0, n),
            rng.uniform(surface + reach + 1e-3, surface + 3.0, n),
            rng.uniform(-math.pi, math.pi, n),
        ],
        axis=-1,
    )
    twist = rng.normal(0.0, 1.0, (n, 3))
    assert not yao_resistance(rig, pose, twist, surface).any()
    for soil in rig.soil.fluid:
        assert not fluid_resistance(rig, soil, pose, twist, surface).any()


@pytest.mark.parametrize("name", RIGS)
def test_soil_never_pushes_the_bucket_along_its_motion(name: str) -> None:
    rig = load_rig(name)
    rng = np.random.default_rng(12)
    n = 4000
    l3 = rig.links[2].length_m
    surf = _random_surface(rng, 0.0, l3)
    x = rng.uniform(-0.5 * l3, 2.0 * l3, n)
    pose = np.stack(
        [x, surf.height_at(x) + rng.uniform(-l3, 0.3 * l3, n), rng.uniform(-math.pi, math.pi, n)],
        axis=-1,
    )
    # Speeds from far below to far above the regularisation, so the ramp is covered too.
    twist = rng.normal(0.0, 1.0, (n, 3)) * 10.0 ** rng.uniform(-5.0, 0.5, (n, 1))
    wrenches = {"yao": yao_resistance(rig, pose, twist, surf)}
    for soil in rig.soil.fluid:
        wrenches[soil.name] = fluid_resistance(rig, soil, pose, twist, surf)
    for model, w in wrenches.items():
        power = np.einsum("...i,...i->...", w, twist)
        scale = np.abs(w).sum(-1) * np.abs(twist).sum(-1) + 1e-12
        bad = np.flatnonzero(power > 1e-12 * scale)
        assert bad.size == 0, (model, pose[bad[:1]], twist[bad[:1]], power[bad[:1]])


@pytest.mark.parametrize(
    ("pose", "twist", "error", "words"),
    [
        ([0.5, -0.3], [0.0, 0.0, 0.0], ValueError, "tip_pose must have shape"),
        (0.5, [0.0, 0.0, 0.0], ValueError, "tip_pose must have shape"),
        ([0.5, -0.3, 0.0], [[0.0, 0.0]], ValueError, "tip_twist must have shape"),
        (np.zeros((4, 3)), np.zeros((5, 3)), ValueError, "do not broadcast"),
        ([0.5, math.nan, 0.0], [0.0, 0.0, 0.0], ConfigurationError, "tip_pose has non-finite"),
        ([0.5, -0.3, 0.0], [0.0, math.inf, 0.0], ConfigurationError, "tip_twist has non-finite"),
    ],
)
def test_bad_tip_state_raises_clear_errors(
    scale: Rig, pose: object, twist: object, error: type[Exception], words: str
) -> None:
    for call in (
        lambda: yao_resistance(scale, pose, twist, -0.25),  # type: ignore[arg-type]
        lambda: fluid_resistance(scale, "soft", pose, twist, -0.25),  # type: ignore[arg-type]
    ):
        with pytest.raises(error) as info:
            call()
        assert words in str(info.value), str(info.value)


def test_bad_options_raise_clear_errors(scale: Rig) -> None:
    pose = [0.5, -0.3, -2.0]
    twist = [-0.1, 0.0, 0.0]
    with pytest.raises(ConfigurationError, match="speed_reg_m_s"):
        yao_resistance(scale, pose, twist, -0.25, speed_reg_m_s=0.0)
    with pytest.raises(ConfigurationError, match="speed_reg_m_s"):
        fluid_resistance(scale, "soft", pose, twist, -0.25, speed_reg_m_s=math.nan)
    with pytest.raises(ConfigurationError, match="n_elements"):
        fluid_resistance(scale, "soft", pose, twist, -0.25, n_elements=0)
    with pytest.raises(ConfigurationError, match="n_elements"):
        fluid_resistance(scale, "soft", pose, twist, -0.25, n_elements=cast(int, 2.5))
    with pytest.raises(ConfigurationError, match="known: soft, hard"):
        fluid_resistance(scale, "clay", pose, twist, -0.25)


def test_shapes_broadcast_and_batch(scale: Rig) -> None:
    rng = np.random.default_rng(13)
    batch = (2000, 200)
    pose = np.stack(
        [
            rng.uniform(0.3, 0.9, batch),
            rng.uniform(-0.4, -0.2, batch),
            rng.uniform(-3.0, -1.0, batch),
        ],
        axis=-1,
    )
    twist = rng.normal(0.0, 0.1, (*batch, 3))
    surf = SurfaceProfile(np.linspace(0.0, 1.5, 300), -0.25 + 0.02 * np.sin(np.linspace(0, 9, 300)))
    w = yao_resistance(scale, pose, twist, surf)
    assert w.shape == (2000, 200, 3) and w.dtype == np.float64 and np.isfinite(w).all()
    # One twist for a batch of poses, and a single state.
    assert yao_resistance(scale, pose[0], twist[0, 0], surf).shape == (200, 3)
    assert fluid_resistance(scale, "hard", pose[:5, :7], twist[0, 0], surf).shape == (5, 7, 3)
    assert fluid_resistance(scale, "soft", pose[0, 0], twist[0, 0], -0.25).shape == (3,)
    np.testing.assert_array_equal(
        fluid_resistance(scale, "soft", pose[:3], twist[:3], surf)[1],
        fluid_resistance(scale, "soft", pose[1], twist[1], surf),
    )
    # A plain float is flat ground.
    np.testing.assert_array_equal(
        yao_resistance(scale, pose[:4], twist[:4], -0.25),
        yao_resistance(scale, pose[:4], twist[:4], SurfaceProfile.flat(-0.25)),
    )


# ---------------------------------------------------------------------------------------------
# Yao eq 8


def _yao_states(
    rng: np.random.Generator, n: int, surf: SurfaceProfile
) -> tuple[FloatArray, FloatArray, FloatArray]:
    x = rng.uniform(-0.5, 2.0, n)
    depth = rng.uniform(1e-3, 0.3, n)
    pose = np.stack([x, surf.height_at(x) - depth, rng.uniform(-math.pi, math.pi, n)], axis=-1)
    heading = rng.uniform(-math.pi, math.pi, n)
    speed = rng.uniform(1.01, 500.0, n) * DEFAULT_SPEED_REG_M_S
    twist = np.stack(
        [speed * np.cos(heading), speed * np.sin(heading), rng.normal(0.0, 1.0, n)], axis=-1
    )
    return pose, twist, depth


def test_yao_magnitude_and_directions(scale: Rig) -> None:
    rng = np.random.default_rng(21)
    surf = _random_surface(rng, -0.25, 0.3)
    pose, twist, depth = _yao_states(rng, 3000, surf)
    w = yao_resistance(scale, pose, twist, surf)
    k0 = scale.soil.yao.k0_n_m2
    mu = scale.soil.yao.mu
    b = scale.bucket.width_m
    w_q = k0 * b * depth
    t_hat = twist[:, :2] / np.linalg.norm(twist[:, :2], axis=-1, keepdims=True)
    perp = np.stack([-t_hat[:, 1], t_hat[:, 0]], axis=-1)
    up = np.where(perp[:, 1:] >= 0.0, perp, -perp)  # the perpendicular out of the cut
    checks = {
        "|F| = sqrt(1+mu^2) K0 b h": (np.linalg.norm(w[:, :2], axis=-1), math.hypot(1, mu) * w_q),
        "tangential = -W_Q": (np.einsum("ij,ij->i", w[:, :2], t_hat), -w_q),
        "normal = +mu W_Q, upward side": (np.einsum("ij,ij->i", w[:, :2], up), mu * w_q),
        "no moment": (w[:, 2], np.zeros_like(w_q)),
    }
    for what, (got, want) in checks.items():
        bad = np.flatnonzero(~np.isclose(got, want, rtol=1e-12, atol=1e-9))
        assert bad.size == 0, (what, pose[bad[:1]], twist[bad[:1]], got[bad[:1]], want[bad[:1]])


def test_yao_scale_model_sanity(scale: Rig) -> None:
    # K0 = 5 N/cm^2, b = 0.22 m, h = 0.05 m: W_Q = 550 N; dragging towards the machine the
    # tangential part points forward (+x) and the normal part up.
    w = yao_resistance(scale, [0.6, -0.30, -2.0], [-0.2, 0.0, 0.3], -0.25)
    np.testing.assert_allclose(w, [550.0, 0.40 * 550.0, 0.0], rtol=1e-12)


def test_yao_is_linear_in_depth(scale: Rig) -> None:
    rng = np.random.default_rng(22)
    surf = _random_surface(rng, -0.25, 0.3)
    pose, twist, depth = _yao_states(rng, 500, surf)
    base = yao_resistance(scale, pose, twist, surf)
    for k in (0.5, 2.0, 3.7):
        deeper = pose.copy()
        deeper[:, 1] = surf.height_at(pose[:, 0]) - k * depth
        np.testing.assert_allclose(
            yao_resistance(scale, deeper, twist, surf), k * base, rtol=1e-11, atol=1e-9
        )


def test_yao_uses_the_local_depth_on_a_sloped_surface(scale: Rig) -> None:
    # Ground rising 0.2 m per m between x = 0 and x = 2, flat beyond both ends.
    surf = SurfaceProfile(np.array([0.0, 2.0]), np.array([-0.25, 0.15]))
    tip_y = -0.30
    x = np.array([-1.0, 0.0, 0.5, 1.0, 1.9, 2.0, 3.0])
    local_surface = np.clip(-0.25 + 0.2 * x, -0.25, 0.15)
    pose = np.stack([x, np.full_like(x, tip_y), np.full_like(x, -2.0)], axis=-1)
    w = yao_resistance(scale, pose, [-0.1, 0.0, 0.0], surf)
    k0b = scale.soil.yao.k0_n_m2 * scale.bucket.width_m
    np.testing.assert_allclose(w[:, 0], k0b * (local_surface - tip_y), rtol=1e-12)


def test_yao_vertical_motion_counts_as_a_dig_towards_the_machine(scale: Rig) -> None:
    pose = [0.6, -0.35, -1.6]
    w_q = scale.soil.yao.k0_n_m2 * scale.bucket.width_m * 0.10
    mu_wq = scale.soil.yao.mu * w_q
    down = yao_resistance(scale, pose, [0.0, -0.1, 0.0], -0.25)
    np.testing.assert_allclose(down, [-mu_wq, w_q, 0.0], rtol=1e-12)
    # The limit of a dig turning vertical from the machine side is continuous.
    near = yao_resistance(scale, pose, [-1e-9, -0.1, 0.0], -0.25)
    np.testing.assert_allclose(near, down, rtol=1e-6)
    up = yao_resistance(scale, pose, [0.0, 0.1, 0.0], -0.25)
    np.testing.assert_allclose(up, [mu_wq, -w_q, 0.0], rtol=1e-12)
    np.testing.assert_allclose(yao_resistance(scale, pose, [-1e-9, 0.1, 0.0], -0.25), up, rtol=1e-6)


def test_yao_at_rest_is_zero_and_ramps_linearly(scale: Rig) -> None:
    pose = [0.6, -0.35, -1.6]
    assert not yao_resistance(scale, pose, [0.0, 0.0, 0.7], -0.25).any()
    direction = np.array([-0.6, -0.8, 0.0])
    at_reg = yao_resistance(scale, pose, DEFAULT_SPEED_REG_M_S * direction, -0.25)
    for frac in (1e-12, 1e-3, 0.5):
        slow = yao_resistance(scale, pose, frac * DEFAULT_SPEED_REG_M_S * direction, -0.25)
        np.testing.assert_allclose(slow, frac * at_reg, rtol=1e-12, atol=1e-20)
    fast = yao_resistance(scale, pose, 100.0 * DEFAULT_SPEED_REG_M_S * direction, -0.25)
    np.testing.assert_allclose(fast, at_reg, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Yang/Pan fluid model


@pytest.mark.parametrize("name", RIGS)
def test_fluid_matches_an_independent_plate_by_plate_implementation(name: str) -> None:
    rig = load_rig(name)
    rng = np.random.default_rng(31)
    l3 = rig.links[2].length_m
    surf = _random_surface(rng, 0.0, l3)
    n = 7
    for case in range(40):
        soil = rig.soil.fluid[case % len(rig.soil.fluid)]
        x = rng.uniform(-0.5 * l3, 2.0 * l3)
        y = float(surf.height_at(x)) + rng.uniform(-l3, 0.2 * l3)
        pose = np.array([x, y, rng.uniform(-math.pi, math.pi)])
        twist = rng.normal(0.0, 1.0, 3) * 10.0 ** rng.uniform(-4.0, 0.0)
        got = fluid_resistance(rig, soil, pose, twist, surf, n_elements=n)
        centres, forces = _reference_plates(
            rig, soil, pose, twist, lambda u: float(surf.height_at(u)), n
        )
        want = np.array([*forces.sum(0), _cross2(centres - pose[:2], forces).sum()])
        scale = float(np.abs(forces).sum()) + 1e-12
        assert np.allclose(got, want, rtol=1e-9, atol=1e-12 * scale), (case, pose, twist, got, want)


def test_fluid_moment_about_another_point_is_m_plus_r_cross_f() -> None:
    rig = load_rig("yang_pan_excavator")
    soil = rig.soil.fluid_named("hard")
    rng = np.random.default_rng(32)
    surf = _random_surface(rng, -1.0, 1.0)
    for case in range(30):
        x = rng.uniform(2.0, 6.0)
        pose = np.array([x, float(surf.height_at(x)) - rng.uniform(0.0, 1.0), rng.uniform(-3, 0)])
        twist = rng.normal(0.0, 0.5, 3)
        fx, fy, m_tip = fluid_resistance(rig, soil, pose, twist, surf, n_elements=9)
        centres, forces = _reference_plates(
            rig, soil, pose, twist, lambda u: float(surf.height_at(u)), 9
        )
        q = rng.normal(0.0, 3.0, 2)
        m_q_direct = _cross2(centres - q, forces).sum()  # eq 18 about q, plate by plate
        m_q_transfer = m_tip + _cross2(pose[:2] - q, np.array([fx, fy]))
        assert math.isclose(m_q_direct, m_q_transfer, rel_tol=1e-9, abs_tol=1e-6), (
            case, pose, twist, q, m_q_direct, m_q_transfer,
        )


@pytest.mark.parametrize("soil_name", ["soft", "hard"])
def test_fluid_plate_pushed_normal_to_itself_matches_hand_computation(
    scale: Rig, soil_name: str
) -> None:
    # A horizontal plate from the tip 0.10 m and then 0.15 m more towards the pivot (attitude 0:
    # bucket frame = arm frame), 0.08 m under flat ground, pushed straight down at 0.2 m/s.
    rig = _plate_rig(scale, ((0.0, 0.0), (-0.10, 0.0), (-0.25, 0.0)))
    soil = rig.soil.fluid_named(soil_name)
    h, v, n = 0.08, 0.2, 6
    b = rig.bucket.width_m
    per_area = soil.kp * soil.density_kg_m3 * rig.gravity_m_s2 * h + soil.kv * v
    # Plate j of a segment of length L: S = L / n * b, force per_area * S straight up.
    areas = np.concatenate([np.full(n, 0.10 / n * b), np.full(n, 0.15 / n * b)])
    centres_x = np.concatenate(
        [-0.10 * (np.arange(n) + 0.5) / n, -0.10 - 0.15 * (np.arange(n) + 0.5) / n]
    )
    want = np.array([0.0, per_area * areas.sum(), per_area * (areas * centres_x).sum()])
    got = fluid_resistance(rig, soil, [0.4, -0.33, 0.0], [0.0, -v, 0.0], -0.25, n_elements=n)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(want[1], per_area * 0.25 * b, rtol=1e-12)


def test_fluid_friction_is_ks_times_the_normal_force(scale: Rig) -> None:
    rig = _plate_rig(scale, ((0.0, 0.0), (-0.10, 0.0), (-0.25, 0.0)))
    h, b = 0.08, rig.bucket.width_m
    for soil in rig.soil.fluid:
        pressure = soil.kp * soil.density_kg_m3 * rig.gravity_m_s2 * h
        # Pulled back along the plate while sinking: friction forward, |friction| = Ks |N|.
        fx, fy, _ = fluid_resistance(rig, soil, [0.4, -0.33, 0.0], [-0.3, -0.1, 0.0], -0.25)
        assert math.isclose(fy, (pressure + soil.kv * 0.1) * 0.25 * b, rel_tol=1e-12)
        assert math.isclose(fx, soil.ks * fy, rel_tol=1e-12)
        # Sliding in its own plane (v_n = 0): no net normal force, friction Ks Kp P S.
        fx, fy, _ = fluid_resistance(rig, soil, [0.4, -0.33, 0.0], [0.3, 0.0, 0.0], -0.25)
        assert fy == 0.0
        assert math.isclose(fx, -soil.ks * pressure * 0.25 * b, rel_tol=1e-12)


@pytest.mark.parametrize("name", RIGS)
def test_fluid_bucket_at_rest_feels_nothing(name: str) -> None:
    rig = load_rig(name)
    l3 = rig.links[2].length_m
    pose = np.array([[1.0, -2.0 * l3, a] for a in np.linspace(-math.pi, math.pi, 13)])
    for soil in rig.soil.fluid:
        w = fluid_resistance(rig, soil, pose, np.zeros(3), 0.0)
        assert not w.any(), (soil.name, w)
        # Slow motion ramps up from zero in proportion to the speed (the Kv term, quadratic in
        # the speed there, is negligible at 1e-9 m/s).
        slow = fluid_resistance(rig, soil, pose, [1e-9, -1e-9, 1e-9], 0.0)
        slower = fluid_resistance(rig, soil, pose, [2e-10, -2e-10, 2e-10], 0.0)
        assert np.isfinite(slow).all() and np.abs(slow).max() > 0.0
        np.testing.assert_allclose(slower, 0.2 * slow, rtol=1e-6, atol=1e-20)


def test_fluid_plate_count_converges_as_the_midpoint_rule_predicts() -> None:
    # Fully buried and translating: pressure and velocity are linear along each plate, so the
    # midpoint sum of the force is the exact integral for any plate count, and the moment
    # (integrand quadratic) has error exactly C / n^2, which Richardson extrapolation removes.
    rig = load_rig("yang_pan_excavator")
    pose = np.array([4.0, -3.0, -2.2])
    twist = np.array([-0.7, -0.4, 0.0])

    def wrench(n: int) -> FloatArray:
        return fluid_resistance(rig, "soft", pose, twist, 0.0, n_elements=n)

    ref = wrench(1)
    for n in (2, 5, 40):
        np.testing.assert_allclose(wrench(n)[:2], ref[:2], rtol=1e-10)
    exact_m = (4.0 * wrench(2)[2] - ref[2]) / 3.0
    assert math.isclose((4.0 * wrench(40)[2] - wrench(20)[2]) / 3.0, exact_m, rel_tol=1e-10)
    assert abs(wrench(40)[2] - exact_m) < 1e-3 * abs(ref[2] - exact_m)


@pytest.mark.parametrize("name", RIGS)
def test_hard_soil_resists_more_than_soft(name: str) -> None:
    rig = load_rig(name)
    soft = rig.soil.fluid_named("soft")
    hard = rig.soil.fluid_named("hard")
    rng = np.random.default_rng(41)
    l3 = rig.links[2].length_m
    n = 2000
    pose = np.stack(
        [rng.uniform(0.0, 2.0, n), rng.uniform(-1.2 * l3, 0.1 * l3, n), rng.uniform(-3.2, 0.2, n)],
        axis=-1,
    )
    twist = rng.normal(0.0, 0.5, (n, 3))
    p_soft = np.einsum("ij,ij->i", fluid_resistance(rig, soft, pose, twist, 0.0), twist)
    p_hard = np.einsum("ij,ij->i", fluid_resistance(rig, hard, pose, twist, 0.0), twist)
    bad = np.flatnonzero(p_hard > p_soft * (1.0 - 1e-12) + 1e-15)
    assert bad.size == 0, (pose[bad[:1]], twist[bad[:1]], p_soft[bad[:1]], p_hard[bad[:1]])
    # A drag: bucket half buried, pulled towards the machine.
    drag_pose = [1.0, -0.5 * l3, -2.0]
    drag = [-0.3, 0.0, 0.0]
    f_soft = np.linalg.norm(fluid_resistance(rig, soft, drag_pose, drag, 0.0)[:2])
    f_hard = np.linalg.norm(fluid_resistance(rig, hard, drag_pose, drag, 0.0)[:2])
    assert f_hard > 2.0 * f_soft > 0.0, (f_soft, f_hard)
