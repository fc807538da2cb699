"""Teach and plan (Zhao et al.): the pipeline's steps against known answers and references."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import shapely

from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig, load_rig
from rt_runtime.teach import pipeline
from rt_runtime.teach.demos import DemoRecord


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("field_excavator")


def known_path(t: np.ndarray) -> np.ndarray:
    """A smooth 4-joint path on [0, 1] inside the field excavator's ranges, rad ``(N, 4)``."""
    s = np.asarray(t)[:, None]
    base = np.radians([10.0, 20.0, -90.0, -60.0])
    amp = np.radians([60.0, 15.0, 25.0, 50.0])
    phase = np.array([0.0, 0.7, 1.9, 2.6])
    freq = np.array([1.0, 2.0, 1.5, 2.5])
    return base + amp * np.sin(2.0 * np.pi * freq * s * 0.5 + phase) * np.sin(np.pi * s)


def test_alignment_undoes_a_known_time_warp() -> None:
    rate = 100.0
    t_ref = np.arange(0.0, 10.0 + 1e-9, 1.0 / rate)
    q_ref = known_path(t_ref / 10.0)
    # The same path at another pace and warped: u = w(t) on [0, 13 s] -> [0, 1].
    t_w = np.arange(0.0, 13.0 + 1e-9, 1.0 / rate)
    x = t_w / 13.0
    u = x + 0.12 * np.sin(2.0 * np.pi * x) / (2.0 * np.pi) * 3.0 * (1.0 - x)
    u = (u - u[0]) / (u[-1] - u[0])
    assert np.all(np.diff(u) > 0.0)
    q_w = known_path(u)
    aligned = pipeline.align(t_ref, q_ref, t_w, q_w, smooth_s=0.0, rate_hz=50.0)
    err = np.abs(aligned - q_ref).max()
    # Uniform time scaling alone (the warp left in) is far off; DTW undoes it to within the
    # distance the path moves in one DTW sample (20 ms).
    uniform = np.stack([np.interp(t_ref * 1.3, t_w, q_w[:, j]) for j in range(4)], axis=1)
    step = np.abs(np.diff(q_ref, axis=0)).max() * 2.0
    assert np.abs(uniform - q_ref).max() > 10.0 * step
    assert err <= step, (math.degrees(err), math.degrees(step))


def test_dtw_matches_a_brute_force_dynamic_programme() -> None:
    rng = np.random.default_rng(5)
    for n, m in ((7, 9), (12, 5), (1, 4), (6, 1)):
        a, b = rng.normal(size=(n, 2)), rng.normal(size=(m, 2))
        ia, ib = pipeline.dtw_path(a, b)
        cost = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
        acc = np.full((n + 1, m + 1), np.inf)
        acc[0, 0] = 0.0
        for i in range(1, n + 1):
            for j in range(1, m + 1):
                best = min(acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1])
                acc[i, j] = cost[i - 1, j - 1] + best
        assert cost[ia, ib].sum() == pytest.approx(acc[n, m], rel=1e-9)
        assert ia[0] == ib[0] == 0 and ia[-1] == n - 1 and ib[-1] == m - 1
        steps = np.stack([np.diff(ia), np.diff(ib)], axis=1)
        assert np.all((steps >= 0) & (steps <= 1)) and np.all(steps.sum(axis=1) >= 1)


def test_averaging_15_noisy_copies_recovers_the_path_within_noise_over_sqrt15(rig: Rig) -> None:
    sigma = math.radians(0.5)
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 10.0 + 1e-9, 0.01)
    truth = known_path(t / 10.0)
    copies = [truth + rng.normal(0.0, sigma, truth.shape) for _ in range(15)]
    mean = pipeline.average(copies)
    rms = float(np.sqrt(np.mean((mean - truth) ** 2)))
    bound = sigma / math.sqrt(15.0)
    assert 0.9 * bound <= rms <= 1.1 * bound  # the plain mean: exactly the sqrt(15) reduction
    # The whole front end (DTW on copies of different pace, centred moving average, mean)
    # recovers it at least as well.
    records = []
    for k, c in enumerate(copies):
        scale = 0.8 + 0.03 * k
        # Built directly: noise of 0.5 deg breaks the readers' jump rule, which is not the
        # subject here.
        records.append(DemoRecord(f"copy {k}", t * scale, c, np.arange(t.size)))
    settings = pipeline.TeachSettings()
    t_mean, q_mean = pipeline.mean_path(rig, records, settings)
    back = known_path(t_mean / t_mean[-1])
    rms_all = float(np.sqrt(np.mean((q_mean - back) ** 2)))
    assert rms_all <= bound


def test_a_causal_filter_lags_the_centred_one_does_not() -> None:
    t = np.linspace(0.0, 1.0, 201)
    q = np.sin(2.0 * np.pi * t)[:, None]
    centred = pipeline.moving_average(q, 15)
    causal = np.array([q[max(0, i - 14) : i + 1].mean(axis=0) for i in range(len(q))])
    peak = int(np.argmax(q[:, 0]))
    assert int(np.argmax(centred[:, 0])) == peak
    assert int(np.argmax(causal[:, 0])) > peak + 5


@pytest.mark.parametrize("seed", range(6))
def test_douglas_peucker_keeps_what_shapely_keeps(seed: int) -> None:
    """On 2-D points shapely's simplify (GEOS Douglas-Peucker) is the reference; embedded in a
    random plane of the 4-D pose space the distances are the same, so the kept points are."""
    rng = np.random.default_rng(seed)
    n = 300
    xy = np.cumsum(rng.normal(size=(n, 2)), axis=0)
    for eps in (0.5, 1.5, 4.0):
        ref = shapely.simplify(shapely.LineString(xy), eps, preserve_topology=False)
        coords = np.asarray(ref.coords)
        expected = [int(np.flatnonzero(np.all(xy == c, axis=1))[0]) for c in coords]
        assert pipeline.douglas_peucker(xy, eps).tolist() == expected
        basis, _ = np.linalg.qr(rng.normal(size=(4, 2)))
        in4d = xy @ basis.T + rng.normal(size=4)
        assert pipeline.douglas_peucker(in4d, eps).tolist() == expected


def test_douglas_peucker_bounds_the_distance_to_the_simplified_line(rig: Rig) -> None:
    rng = np.random.default_rng(2)
    pts = np.cumsum(rng.normal(size=(500, 4)) * 0.01, axis=0)
    eps = 0.05
    keep = pipeline.douglas_peucker(pts, eps)
    for a, b in itertools.pairwise(keep):
        seg = pts[b] - pts[a]
        rel = pts[a : b + 1] - pts[a]
        u = np.clip(rel @ seg / (seg @ seg), 0.0, 1.0)
        assert np.linalg.norm(rel - u[:, None] * seg, axis=1).max() <= eps + 1e-12


def test_frechet_distance_matches_shapely() -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        a = np.cumsum(rng.normal(size=(40, 2)), axis=0)
        b = np.cumsum(rng.normal(size=(55, 2)), axis=0)
        ref = shapely.frechet_distance(shapely.LineString(a), shapely.LineString(b))
        assert pipeline.frechet_distance(a, b) == pytest.approx(ref, rel=1e-12)


def test_swing_is_unwrapped_before_averaging(rig: Rig) -> None:
    t = np.linspace(0.0, 1.0, 100)
    q = np.zeros((100, 4))
    q[:, 0] = np.radians(170.0 + 20.0 * t)  # crosses +180 deg
    wrapped = q.copy()
    wrapped[:, 0] = (wrapped[:, 0] + np.pi) % (2.0 * np.pi) - np.pi
    other = q.copy()
    other[:, 0] -= 2.0 * np.pi
    out = pipeline.unwrap_swing(rig, [q, wrapped, other])
    for a in out:
        np.testing.assert_allclose(a[:, 0], q[:, 0], atol=1e-12)


def test_waypoints_come_back_on_the_same_ik_branch(rig: Rig) -> None:
    t = np.linspace(0.0, 1.0, 400)
    q = np.radians([0.0, 20.0, -90.0, -60.0]) + np.radians([60.0, 10.0, 20.0, 40.0]) * np.stack(
        [np.sin(np.pi * t), np.sin(2 * np.pi * t), t, t**2], axis=1
    )
    idx, wps = pipeline.waypoints_from_path(rig, q, 0.02)
    np.testing.assert_allclose(wps, q[idx], atol=1e-9)
    assert idx[0] == 0 and idx[-1] == len(t) - 1


def test_settings_are_checked() -> None:
    for bad in ({"epsilon_m": 0.0}, {"w_time": 0.0}, {"cycles": 0}, {"window_s": -1.0},
                {"alignment": "phase"}, {"w_jerk": float("nan")}):
        with pytest.raises(ConfigurationError):
            pipeline.TeachSettings(**bad)  # type: ignore[arg-type]


def test_idle_rest_around_the_cycle_is_not_the_operators_time(rig: Rig) -> None:
    t = np.arange(0.0, 12.0, 0.01)
    q = np.tile(np.radians([0.0, 20.0, -90.0, -60.0]), (t.size, 1))
    moving = (t >= 2.0) & (t <= 9.0)
    q[moving, 0] += np.radians(70.0) * np.sin(np.pi * (t[moving] - 2.0) / 7.0)
    rng = np.random.default_rng(0)
    noisy = q + rng.normal(0.0, np.radians(0.05), q.shape)
    rec = DemoRecord("idle", t, noisy, np.arange(t.size))
    trimmed = pipeline.trim_rest(rec)
    assert trimmed.duration_s == pytest.approx(7.0, abs=0.6)
    assert pipeline.cycle_times_s([rec])[0] == pytest.approx(trimmed.duration_s)
