"""One-shot dig evaluation: volume, entry angle and energy against independent computations."""

from __future__ import annotations

import copy
import math
import tomllib

import numpy as np
import pytest
from scipy import integrate

from rt_runtime import dynamics, kinematics, soil
from rt_runtime.errors import ConfigurationError, PlanningError, RigProfileError
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType, Problem
from rt_runtime.rig import load_rig, parse_rig
from rt_runtime.rig.loader import PROFILE_DIR
from rt_runtime.trajectory import sextic

RIG = load_rig("scale_model")


def _boom_swing(
    q_start_deg: tuple[float, float, float], boom_end_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """A dig that turns only the boom: the tip runs on a circle about the boom foot pin."""
    qs = np.radians(q_start_deg)
    qe = qs.copy()
    qe[0] = math.radians(boom_end_deg)
    return qs, qe


def _evaluate_one(p: Problem, a6: np.ndarray, T_s: float, n_samples: int) -> oneshot.Evaluation:
    """Evaluate one candidate of one problem (batch shape (1, 1))."""
    return oneshot.evaluate(
        RIG,
        np.array([p.q_start_rad]),
        np.array([p.q_end_rad]),
        np.array([p.surface_y_m]),
        p.dig_type,
        np.asarray(a6)[None, None],
        np.array([[T_s]]),
        n_samples=n_samples,
    )


def test_area_of_polylines_is_exact() -> None:
    h = -0.3
    # Trapezoid below the surface, traversed towards the machine (x decreasing).
    x = np.array([1.0, 0.9, 0.6, 0.5])
    y = np.array([h, h - 0.1, h - 0.1, h])
    assert oneshot.excavated_area_m2(x, y, h) == pytest.approx(0.5 * (0.5 + 0.3) * 0.1, rel=1e-12)
    # Starting above the surface: only the part below y = H counts (a triangle of depth 0.05).
    x2 = np.array([1.0, 0.8, 0.6])
    y2 = np.array([h + 0.05, h - 0.05, h + 0.05])
    assert oneshot.excavated_area_m2(x2, y2, h) == pytest.approx(0.5 * 0.2 * 0.05, rel=1e-12)
    # Never below the surface: nothing.
    assert oneshot.excavated_area_m2(x2, y2 + 1.0, h) == 0.0


@pytest.mark.parametrize("depth_m", [0.02, 0.06, 0.1])
def test_volume_of_circular_arc_matches_the_circular_segment(depth_m: float) -> None:
    # Only the stick turns, bucket in line with it: the tip runs on a circle of radius l2 + l3
    # about the stick pivot (0.74, 0), sweeping through its lowest point towards the machine.
    qs = np.radians([0.0, -20.0, 0.0])
    qe = np.radians([0.0, -150.0, 0.0])
    radius = 0.350 + 0.220
    h = -radius + depth_m  # the lowest point of the arc lies depth_m below the surface
    ev = oneshot.evaluate(
        RIG,
        qs[None],
        qe[None],
        np.array([h]),
        DigType.DOWNWARD,
        np.zeros((1, 1, 3)),
        np.full((1, 1), 6.0),
        n_samples=4001,
    )
    d = radius - depth_m  # distance from the circle's centre to the chord y = H
    segment = radius**2 * math.acos(d / radius) - d * math.sqrt(radius**2 - d**2)
    assert ev.volume_m3[0, 0] == pytest.approx(segment * RIG.bucket.width_m, rel=2e-5)


def test_entry_angle_of_circular_arc_is_its_tangent() -> None:
    # Start on the surface: the tip leaves along the circle's tangent, the boom turning down.
    qs, qe = _boom_swing((30.0, -110.0, -60.0), 0.0)
    tip0 = kinematics.forward(RIG, qs)
    ev = oneshot.evaluate(
        RIG,
        qs[None],
        qe[None],
        np.array([tip0[1]]),
        DigType.DOWNWARD,
        np.zeros((1, 1, 3)),
        np.full((1, 1), 6.0),
    )
    # Boom turning clockwise: velocity = omega x r with omega < 0 -> (y, -x) direction.
    vx, vy = tip0[1], -tip0[0]
    expected = math.atan2(-vy, abs(vx))
    assert ev.theta_p_rad[0, 0] == pytest.approx(expected, abs=1e-9)


def test_energy_is_the_integral_of_power_computed_independently() -> None:
    problems = oneshot.sample_problems(RIG, 3, DigType.DOWNWARD, seed=11)
    rng = np.random.default_rng(3)
    for p in problems:
        k = rng.uniform(-5.0, 5.0, size=3)
        T = float(rng.uniform(5.0, 9.0))
        a6 = -k / T**6
        ev = _evaluate_one(p, a6, T, n_samples=2001)
        # Independently: the scalar trajectory sampler, then dynamics and soil per sample.
        traj = sextic.SexticTrajectory(np.array(p.q_start_rad), np.array(p.q_end_rad), a6, T)
        t = np.linspace(0.0, T, 4001)
        q, qd, qdd = (np.array(v) for v in zip(*(traj.sample(ti) for ti in t), strict=True))
        pose = kinematics.forward(RIG, q)
        twist = kinematics.tip_velocity(RIG, q, qd)
        f = soil.yao_resistance(RIG, pose, twist, p.surface_y_m)
        tau = dynamics.inverse_dynamics(RIG, q, qd, qdd, f)
        power = np.maximum(tau * qd, 0.0).sum(axis=-1)
        energy = integrate.simpson(power, x=t)
        assert ev.energy_j[0, 0] == pytest.approx(energy, rel=2e-3), p


def test_objective_is_yao_eq_11() -> None:
    pl = RIG.planning
    assert pl is not None
    f = oneshot.objective(pl, 7.5, 0.0675 * 3600, 4.73e-3)
    assert float(f) == pytest.approx(0.5 * 0.5 + 0.2 * 0.5 + 0.3 * 0.5, rel=1e-9)


def test_pso_plans_feasible_digs_in_yao_ranges_and_dense_grid_confirms() -> None:
    problems = oneshot.sample_problems(RIG, 4, DigType.DOWNWARD, seed=1) + oneshot.sample_problems(
        RIG, 4, DigType.BACKWARD, seed=1
    )
    sols = oneshot.solve_pso(RIG, problems, seed=0)
    assert all(s.feasible for s in sols), [s.margins for s in sols if not s.feasible]
    for s in sols:
        assert s.T_s == pytest.approx(7.5, abs=2.5)  # Yao's range 5..10 s
        assert 3.74e-3 <= s.volume_m3 <= 5.72e-3
        lo, hi = (40.0, 90.0) if s.problem.dig_type == DigType.DOWNWARD else (0.0, 40.0)
        assert lo <= math.degrees(s.theta_p_rad) <= hi
        assert all(m >= 0.0 for _, m in s.margins)
        # Ten times denser sampling finds no violation worth the name.
        p = s.problem
        ev = _evaluate_one(p, np.array(s.a6), s.T_s, n_samples=1001)
        assert ev.total_violation[0, 0] < 1e-2, dict(
            zip(oneshot.CONSTRAINT_NAMES, ev.violations[0, 0], strict=True)
        )
        traj = s.trajectory()
        q_end, qd_end, _ = traj.sample(s.T_s)
        np.testing.assert_allclose(q_end, p.q_end_rad, atol=1e-9)
        np.testing.assert_allclose(qd_end, 0.0, atol=1e-9)


def test_pso_reports_an_impossible_dig_as_infeasible() -> None:
    good = oneshot.sample_problems(RIG, 1, DigType.DOWNWARD, seed=2)[0]
    # Material 2 m below the pin: out of reach, no dig can fill the bucket.
    hopeless = Problem(good.q_start_rad, good.q_end_rad, -2.0, DigType.DOWNWARD)
    sols = oneshot.solve_pso(RIG, [good, hopeless], seed=0)
    assert sols[0].feasible
    assert not sols[1].feasible
    assert dict(sols[1].margins)["volume_min"] < 0.0


def test_bad_inputs_raise_clear_errors() -> None:
    p = oneshot.sample_problems(RIG, 1, DigType.DOWNWARD, seed=4)[0]
    bad_pose = Problem(
        (math.radians(80.0), *p.q_start_rad[1:]), p.q_end_rad, p.surface_y_m, p.dig_type
    )  # type: ignore[arg-type]
    with pytest.raises(
        PlanningError, match=r"start pose.*boom at 80\.000 deg is outside \[-20\.000, 65\.000\]"
    ):
        oneshot.solve_pso(RIG, [bad_pose])
    nan_pose = Problem(p.q_start_rad, (float("nan"), *p.q_end_rad[1:]), p.surface_y_m, p.dig_type)  # type: ignore[arg-type]
    with pytest.raises(PlanningError, match="end pose contains NaN"):
        oneshot.solve_pso(RIG, [nan_pose])
    with pytest.raises(PlanningError, match="surface height H"):
        oneshot.solve_pso(RIG, [Problem(p.q_start_rad, p.q_end_rad, float("nan"), p.dig_type)])
    with pytest.raises(ConfigurationError, match=r"rig 'test_bench' has no \[planning\] table"):
        oneshot.search_bounds(load_rig("test_bench"))
    doc = copy.deepcopy(tomllib.loads((PROFILE_DIR / "scale_model.toml").read_text()))
    doc["planning"]["t_s"] = [5.0, 5.0]
    with pytest.raises(RigProfileError, match=r"planning\.t_s: min must be < max"):
        parse_rig(doc)
