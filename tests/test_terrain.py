"""HIL terrain: cuts remove exactly the swept area, the surface follows, Yao soil force on it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from shapely.geometry import LineString

from hil_sim import Terrain
from hil_sim.terrain import CUT_SIMPLIFY_M
from rt_runtime import soil
from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.oneshot import excavated_area_m2
from rt_runtime.rig import load_rig

RIG = load_rig("scale_model")
GROUND = -0.25
WIDTH = 0.22


def _terrain(**kw: float) -> Terrain:
    return Terrain(GROUND, (-0.5, 1.5), WIDTH, **kw)


def test_rectangle_path_removes_its_rectangle() -> None:
    t = _terrain()
    # Plunge at x = 0.6 to 0.1 m below ground, drag back to x = 0.3, lift out.
    path = [(0.6, -0.20), (0.6, -0.35), (0.3, -0.35), (0.3, -0.20)]
    cut = t.cut(path)
    assert cut.area_m2 == pytest.approx(0.3 * 0.1, rel=1e-12)
    assert cut.volume_m3 == pytest.approx(0.3 * 0.1 * WIDTH, rel=1e-12)
    assert t.removed_volume_m3 == pytest.approx(cut.volume_m3)
    np.testing.assert_allclose(t.surface_y([0.31, 0.45, 0.59]), -0.35, rtol=0, atol=1e-12)
    np.testing.assert_allclose(t.surface_y([0.0, 0.25, 0.65, 1.2]), GROUND, rtol=0, atol=1e-12)
    assert t.material.area == pytest.approx(2.0 * 3.0 - 0.03, rel=1e-12)  # 2 m wide, 3 m deep
    # The same path again finds nothing left to remove.
    assert t.cut(path).area_m2 == pytest.approx(0.0, abs=1e-15)


def test_trapezoid_path_removes_the_hand_computed_area() -> None:
    t = _terrain()
    # Enter at 45 deg from (0.7, ground), run 0.2 m at depth 0.1, leave at 45 deg to x = 0.3.
    path = [(0.75, -0.20), (0.6, -0.35), (0.4, -0.35), (0.25, -0.20)]
    # Below ground: bottom 0.2 m, top (at ground) 0.4 m, depth 0.1 m.
    assert t.cut(path).area_m2 == pytest.approx(0.5 * (0.2 + 0.4) * 0.1, rel=1e-12)
    assert t.surface_y(0.65) == pytest.approx(-0.30, abs=1e-12)  # on the 45 deg entry wall
    # An overlapping deeper cut removes only the new material: 0.1 x 0.05 under the old floor.
    second = t.cut([(0.55, -0.2), (0.55, -0.40), (0.45, -0.40), (0.45, -0.2)])
    assert second.area_m2 == pytest.approx(0.1 * 0.05, rel=1e-9)


def test_curved_monotonic_path_matches_the_planners_area() -> None:
    x = np.linspace(0.8, 0.2, 301)
    y = GROUND - 0.12 * np.sin(np.pi * (0.8 - x) / 0.6) + 0.01  # enters and leaves 1 cm deep
    t = _terrain()
    cut = t.cut(np.stack([x, y], axis=-1), simplify_m=0.0)
    assert cut.area_m2 == pytest.approx(float(excavated_area_m2(x, y, GROUND)), rel=1e-9)


def test_simplified_cut_stays_within_its_tolerance_times_the_length() -> None:
    x = np.linspace(0.8, 0.2, 3001)
    y = GROUND - 0.12 * np.sin(np.pi * (0.8 - x) / 0.6) + 0.01
    path = np.stack([x, y], axis=-1)
    exact = _terrain().cut(path, simplify_m=0.0).area_m2
    t = _terrain()
    fast = t.cut(path)  # the default tolerance
    length = float(np.sum(np.hypot(np.diff(x), np.diff(y))))
    assert abs(fast.area_m2 - exact) <= CUT_SIMPLIFY_M * length
    assert fast.area_m2 != exact  # it did simplify (a curved path loses its chords' slivers)
    # The surface it leaves is the exact one within the tolerance.
    ref = _terrain()
    ref.cut(path, simplify_m=0.0)
    xs = np.linspace(0.25, 0.75, 101)
    np.testing.assert_allclose(t.surface_y(xs), ref.surface_y(xs), rtol=0, atol=2 * CUT_SIMPLIFY_M)


def test_a_path_that_doubles_back_removes_nothing_twice() -> None:
    t = _terrain()
    there = [(0.6, -0.2), (0.6, -0.3), (0.3, -0.3)]
    back = [(0.5, -0.3), (0.4, -0.3), (0.6, -0.3), (0.6, -0.2)]
    assert t.cut(there + back).area_m2 == pytest.approx(0.3 * 0.05, rel=1e-12)


def test_sampled_surface_agrees_with_the_polygon() -> None:
    t = _terrain()
    rng = np.random.default_rng(7)
    for _ in range(3):
        x = np.sort(rng.uniform(0.0, 1.2, 40))[::-1]
        y = GROUND - rng.uniform(0.0, 0.2, 40)
        t.cut(np.stack([x, y], axis=-1))
    xs = t.surface_x_m[::37]
    lines = [LineString([(xi, -10.0), (xi, 10.0)]) for xi in xs]
    tops = shapely.bounds(shapely.intersection(t.material, lines))[:, 3]
    np.testing.assert_allclose(t.surface_y_m[::37], tops, rtol=0, atol=1e-12)
    between = rng.uniform(-0.7, 1.7, 200)  # off the grid and beyond both ends
    np.testing.assert_allclose(
        [t.surface_at(float(v)) for v in between], t.surface_y(between), rtol=0, atol=1e-12
    )


def test_depth_of_cut() -> None:
    t = _terrain()
    t.cut([(0.6, -0.2), (0.6, -0.35), (0.3, -0.35), (0.3, -0.2)])
    depth = t.depth_of_cut([[0.45, -0.40], [0.45, -0.30], [0.8, -0.30], [0.8, 0.0]])
    np.testing.assert_allclose(depth, [0.05, 0.0, 0.05, 0.0], rtol=0, atol=1e-12)
    assert t.depth_of_cut(np.zeros((4, 5, 2))).shape == (4, 5)


def test_soil_force_is_zero_above_ground_and_opposes_motion_below() -> None:
    t = _terrain()
    rng = np.random.default_rng(11)
    tip = np.stack([rng.uniform(0.0, 1.2, 500), rng.uniform(-0.5, 0.0, 500)], axis=-1)
    vel = rng.normal(0.0, 0.1, (500, 2))
    f = t.soil_force(tip, vel, RIG)
    depth = t.depth_of_cut(tip)
    above = depth == 0.0
    assert above.any() and (~above).any()
    np.testing.assert_array_equal(f[above], 0.0)
    assert np.all(np.einsum("ij,ij->i", f[~above], vel[~above]) < 0.0)
    # Magnitude sqrt(1 + mu^2) K0 b h above the regularisation speed (Yao eq 8).
    fast = ~above & (np.hypot(vel[:, 0], vel[:, 1]) > 1e-3)
    k0, mu = RIG.soil.yao.k0_n_m2, RIG.soil.yao.mu
    want = math.sqrt(1 + mu**2) * k0 * RIG.bucket.width_m * depth[fast]
    np.testing.assert_allclose(np.hypot(f[fast, 0], f[fast, 1]), want, rtol=1e-12)


def test_fast_tip_load_equals_rt_runtime_soil() -> None:
    t = _terrain()
    t.cut([(0.7, -0.2), (0.5, -0.33), (0.3, -0.2)])
    model = t.soil_model(RIG)
    rng = np.random.default_rng(12)
    tip = np.stack([rng.uniform(0.0, 1.2, 300), rng.uniform(-0.45, -0.15, 300)], axis=-1)
    vel = rng.normal(0.0, 0.05, (300, 2)) * rng.choice([1e-3, 1.0], (300, 1))  # both regimes
    want = t.soil_force(tip, vel, RIG)
    # The library's own surface lookup agrees with the terrain's.
    lib = soil.yao_resistance(
        RIG,
        np.concatenate([tip, np.zeros((300, 1))], axis=-1),
        np.concatenate([vel, np.zeros((300, 1))], axis=-1),
        t.surface_profile(),
    )[:, :2]
    np.testing.assert_allclose(want, lib, rtol=1e-12, atol=1e-9)
    for (x, y), (vx, vy), (fx, fy) in zip(tip, vel, want, strict=True):
        gx, gy, dxx, dxy, dyx, dyy = model.tip_load(x, y, vx, vy)
        assert gx == pytest.approx(fx, rel=1e-12, abs=1e-9)
        assert gy == pytest.approx(fy, rel=1e-12, abs=1e-9)
        # The frozen law F = -D v reproduces the force.
        assert -(dxx * vx + dxy * vy) == pytest.approx(gx, rel=1e-12, abs=1e-9)
        assert -(dyx * vx + dyy * vy) == pytest.approx(gy, rel=1e-12, abs=1e-9)
        # Its symmetric part is a damper (dissipative).
        assert dxx >= 0.0 and dyy >= 0.0 and dxy == -dyx


def test_cuts_are_deterministic_and_mutate_only_the_terrain() -> None:
    path = np.array([(0.7, -0.2), (0.55, -0.31), (0.35, -0.31), (0.25, -0.2)])
    a, b = _terrain(), _terrain()
    ra, rb = a.cut(path), b.cut(path.copy())
    assert ra == rb
    np.testing.assert_array_equal(a.surface_y_m, b.surface_y_m)
    assert a.material.equals(b.material)
    with pytest.raises(ValueError):
        a.surface_y_m[0] = 1.0  # read-only copies


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ConfigurationError, match="x_range_m must be"):
        Terrain(GROUND, (1.0, 0.0), WIDTH)
    with pytest.raises(ConfigurationError, match="bottom_y_m must be below"):
        Terrain(GROUND, (0.0, 1.0), WIDTH, bottom_y_m=0.0)
    with pytest.raises(ConfigurationError, match="bucket_width_m and resolution_m must be > 0"):
        Terrain(GROUND, (0.0, 1.0), 0.0)
    t = _terrain()
    with pytest.raises(ValueError, match=r"tip_path_xy_m must have shape \(m, 2\)"):
        t.cut([(0.1, 0.2)])
    with pytest.raises(ValueError, match=r"must have shape \(\.\.\., 2\)"):
        t.cut(np.zeros((4, 3)))
    with pytest.raises(ConfigurationError, match="non-finite"):
        t.cut([(0.1, 0.2), (math.nan, 0.0)])
    with pytest.raises(ConfigurationError, match="speed_reg_m_s"):
        t.soil_model(RIG, speed_reg_m_s=0.0)


def test_the_path_in_the_air_cuts_nothing_and_is_left_out() -> None:
    # A cycle's tip path: high over the pit (dump, swing back), then the dig. The moves above
    # the material sweep nothing: the cut, the surface and the polygon are the dig's alone.
    dig = [(0.75, -0.20), (0.6, -0.35), (0.4, -0.35), (0.25, -0.20)]
    arc = [(1.4 - 0.01 * i, 0.3 + 0.2 * math.sin(0.1 * i)) for i in range(60)]
    alone, cycle = _terrain(), _terrain()
    a = alone.cut(dig, simplify_m=0.0)
    b = cycle.cut([*arc, (0.9, -0.1), *dig, (0.1, 0.2), (-0.3, 0.5)], simplify_m=0.0)
    assert b.area_m2 == pytest.approx(a.area_m2, rel=1e-12)
    np.testing.assert_array_equal(cycle.surface_y_m, alone.surface_y_m)
    assert cycle.material.symmetric_difference(alone.material).area < 1e-12
    # A path wholly in the air removes nothing.
    assert _terrain().cut(arc).area_m2 == 0.0


def test_a_copy_cuts_on_its_own() -> None:
    material = load_rig("scale_model").hil
    assert material is not None
    t = _terrain(material=material.materials[0])
    t.cut([(0.75, -0.20), (0.6, -0.35), (0.4, -0.35), (0.25, -0.20)])
    before = (t.surface_y_m.copy(), t.material, t.swept_m3, t.slumped_m3)
    copy = t.copy()
    cut = copy.cut([(1.2, -0.2), (1.1, -0.4), (0.9, -0.4), (0.85, -0.2)])
    assert cut.area_m2 > 0.0 and copy.swept_m3 > before[2]
    np.testing.assert_array_equal(t.surface_y_m, before[0])
    assert t.material is before[1] and t.swept_m3 == before[2] and t.slumped_m3 == before[3]
    assert t.surface_at(1.0) == pytest.approx(GROUND) and copy.surface_at(1.0) < GROUND - 0.1
