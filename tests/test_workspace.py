"""Monte Carlo workspace: determinism, kinematic bounds, convergence to optimised extremes."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.optimize import minimize

from rt_runtime.errors import ConfigurationError
from rt_runtime.kinematics import joint_positions
from rt_runtime.rig import Rig, load_rig, profile_names
from rt_runtime.workspace import Envelope, envelope, sample_tip_points

FloatArray = NDArray[np.float64]


@pytest.fixture(scope="module", params=profile_names())
def rig(request: pytest.FixtureRequest) -> Rig:
    return load_rig(request.param)


def _tip(rig: Rig, q: FloatArray) -> FloatArray:
    """Tip from the joint chain (joint_positions), not from forward()."""
    return joint_positions(rig, q)[..., 3, :]


def _optimised_max(rig: Rig, objective: Callable[[FloatArray], FloatArray]) -> float:
    """Largest objective of the tip over the joint box: coarse grid, then L-BFGS-B from the best."""
    axes = [np.linspace(lo, hi, 13) for lo, hi in zip(rig.q_min_rad, rig.q_max_rad, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    values = objective(_tip(rig, grid))
    bounds = list(zip(rig.q_min_rad, rig.q_max_rad, strict=True))
    best = float(values.max())
    for start in grid[np.argsort(values)[-8:]]:
        res = minimize(
            lambda q: -float(objective(_tip(rig, q))),
            start,
            method="L-BFGS-B",
            bounds=bounds,
            options={"ftol": 1e-15, "gtol": 1e-12},
        )
        best = max(best, -float(res.fun))
    return best


OBJECTIVES: dict[str, Callable[[FloatArray], FloatArray]] = {
    "max_height_m": lambda p: p[..., 1],
    "max_radius_m": lambda p: np.hypot(p[..., 0], p[..., 1]),
    "max_reach_x_m": lambda p: p[..., 0],
    "max_depth_m": lambda p: -p[..., 1],
}


def test_envelope_is_deterministic_per_seed(rig: Rig) -> None:
    a = envelope(rig, samples=5000, seed=3)
    assert a == envelope(rig, samples=5000, seed=3)
    assert a != envelope(rig, samples=5000, seed=4)
    assert np.array_equal(sample_tip_points(rig, 5000, 3), sample_tip_points(rig, 5000, 3))
    assert (a.samples, a.seed, a.rig_name) == (5000, 3, rig.name)


def test_envelope_is_a_frozen_record(rig: Rig) -> None:
    env = envelope(rig, samples=10)
    assert isinstance(env, Envelope)
    assert {f.name for f in dataclasses.fields(Envelope)} >= {
        "max_height_m",
        "max_radius_m",
        "max_reach_x_m",
        "max_depth_m",
        "max_depth_below_ground_m",
        "samples",
        "seed",
    }
    with pytest.raises(dataclasses.FrozenInstanceError):
        env.max_height_m = 0.0  # type: ignore[misc]


def test_points_follow_the_documented_draw(rig: Rig) -> None:
    u = np.random.default_rng(9).random((3000, 6))
    q = rig.q_min_rad + u[:, :3] * (rig.q_max_rad - rig.q_min_rad)
    at_min, at_max = u[:, 3:] < 0.05, u[:, 3:] >= 0.95
    q[at_min] = np.broadcast_to(rig.q_min_rad, q.shape)[at_min]
    q[at_max] = np.broadcast_to(rig.q_max_rad, q.shape)[at_max]
    points = sample_tip_points(rig, 3000, 9)
    assert points.shape == (3000, 2)
    assert np.allclose(points, _tip(rig, q), atol=1e-12)
    assert np.all((q >= rig.q_min_rad) & (q <= rig.q_max_rad))
    # Both limits of every joint are drawn, and most draws are interior.
    assert at_min.any(axis=0).all() and at_max.any(axis=0).all()
    assert 0.65 < np.mean(~(at_min | at_max).any(axis=1)) < 0.8


def test_points_lie_within_kinematic_bounds(rig: Rig) -> None:
    points = sample_tip_points(rig, 50_000, 1)
    reach = float(rig.lengths_m.sum())
    radius = np.hypot(points[:, 0], points[:, 1])
    i = int(np.argmax(radius))
    assert radius[i] <= reach + 1e-12, f"point {i} {points[i]} beyond l1+l2+l3 = {reach}"
    # The bucket pivot stays in the boom+stick annulus, so the tip stays within l3 of it.
    l1, l2, l3 = rig.lengths_m
    i = int(np.argmin(radius))
    assert radius[i] >= abs(l1 - l2) - l3 - 1e-12, f"point {i} {points[i]} inside the annulus"


def test_envelope_summarises_its_points(rig: Rig) -> None:
    env = envelope(rig, samples=20_000, seed=5)
    points = sample_tip_points(rig, 20_000, 5)
    assert env.max_height_m == points[:, 1].max()
    assert env.max_reach_x_m == points[:, 0].max()
    assert env.max_depth_m == -points[:, 1].min()
    assert env.max_radius_m == pytest.approx(np.linalg.norm(points, axis=-1).max(), rel=1e-15)
    assert env.max_depth_below_ground_m == pytest.approx(env.max_depth_m + rig.ground_y_m)


def test_envelope_converges_to_the_optimised_extremes(rig: Rig) -> None:
    small = envelope(rig, samples=200, seed=0)
    large = envelope(rig, samples=200_000, seed=0)
    for name, objective in OBJECTIVES.items():
        best = _optimised_max(rig, objective)
        got_small, got_large = getattr(small, name), getattr(large, name)
        case = f"{rig.name}.{name}: optimum {best}, 200 samples {got_small}, 200k {got_large}"
        # Nested draws: the larger sample holds the smaller one, so it can only get closer.
        assert got_small <= got_large <= best + 1e-9, case
        assert best - got_large <= 0.01 * abs(best), case


def test_bad_sample_counts_raise(rig: Rig) -> None:
    for samples in (0, -5, 2.5, True):
        with pytest.raises(ConfigurationError, match="samples must be a positive integer"):
            envelope(rig, samples=samples)  # type: ignore[arg-type]

