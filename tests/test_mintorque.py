"""Minimum-torque dig optimisation (Yang/Pan): model against independent evaluations, batched
gradients against finite differences, the optimum on the exact model at 1 ms, soils, time,
bad input, and the CasADi reference (skipped without the ``reference`` extra)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Polygon

from rt_runtime import dynamics, kinematics, soil
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import mintorque as mt
from rt_runtime.rig import load_rig

RIG = load_rig("yang_pan_excavator")
PROFILE = Path(__file__).resolve().parents[1] / "rt_runtime/rig/profiles/yang_pan_excavator.toml"


@pytest.fixture(scope="module")
def solutions() -> dict[str, tuple[mt.MinTorqueProblem, mt.Solution]]:
    out = {}
    for key, soil_name, fixed in (
        ("soft", "soft", False),
        ("hard", "hard", False),
        ("soft_fixed", "soft", True),
    ):
        p = mt.make_problem(RIG, soil_name, fixed_time=fixed)
        out[key] = (p, mt.solve(RIG, p))
    return out


def _start_point(p: mt.MinTorqueProblem, k: int = 0) -> np.ndarray:
    return mt.initial_point(p, mt.kinematic_starts(RIG, p, k + 1)[k])


def _grid(p: mt.MinTorqueProblem, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample times of the optimiser's grid and their trapezoid weights, built independently."""
    Q = p.samples_per_interval
    knots = np.concatenate([[0.0], np.cumsum(h)])
    t = np.concatenate([knots[i] + h[i] * np.linspace(0.0, 1.0, Q + 1) for i in range(len(h))])
    w = np.concatenate([np.r_[0.5, np.ones(Q - 1), 0.5] * h[i] / Q for i in range(len(h))])
    # Ends of an interval map to the next interval's start in sample_path: nudge them inside.
    for i in range(len(h)):
        t[i * (Q + 1) + Q] = knots[i + 1] - 1e-12
    return t, w


@pytest.mark.parametrize("soil_name", ["soft", "hard"])
def test_objective_against_dynamics_and_exact_soil(
    soil_name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the smoothing scales shrunk to nothing the model's torques are those of
    dynamics.inverse_dynamics with soil.fluid_resistance, and its cost their trapezoid sum."""
    monkeypatch.setattr(mt, "SMOOTH_DEPTH_M", 1e-12)
    monkeypatch.setattr(mt, "SMOOTH_SPEED_M_S", 1e-9)
    p = mt.make_problem(RIG, soil_name, samples_per_interval=8)
    rng = np.random.default_rng(3)
    x = _start_point(p) + np.r_[rng.normal(0.0, 0.02, 15), rng.uniform(-0.2, 0.2, 4)]
    keys, h = x[:15].reshape(5, 3), x[15:]
    t, w = _grid(p, h)
    q, qd, qdd = mt.sample_path(keys, h, t)
    pose, twist = kinematics.tip_state(RIG, q, qd)
    f = soil.fluid_resistance(RIG, p.soil, pose, twist, p.surface_y_m, speed_reg_m_s=1e-9)
    assert np.abs(f).max() > 1e3  # the dig is in the soil
    tau = dynamics.inverse_dynamics(RIG, q, qd, qdd, f)
    expected = float(np.sum(w * np.sum((tau / RIG.tau_max_nm) ** 2, axis=-1)))
    model = mt._Model(RIG, p, mt._NumpyOps)
    smp = model.samples(
        mt._keys_of(x[None, :], lambda a, i: a[:, i]), [x[None, 15 + i] for i in range(4)]
    )
    np.testing.assert_allclose(np.stack(smp.q, axis=-1)[0], q, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.stack(smp.qd, axis=-1)[0], qd, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.stack(smp.tau, axis=-1)[0], tau, rtol=1e-7, atol=1e-3)
    cost = mt.Evaluator(RIG, p).evaluate(x[None, :]).cost[0]
    assert cost == pytest.approx(expected, rel=1e-8)


def test_interpolation_is_rest_to_rest_and_c2() -> None:
    p = mt.make_problem(RIG, "soft")
    x = _start_point(p)
    keys, h = x[:15].reshape(5, 3), np.array([0.7, 1.1, 0.5, 1.3])
    q, qd, qdd = mt.sample_path(keys, h, [0.0, h.sum()])
    np.testing.assert_allclose(q, keys[[0, -1]], atol=1e-12)
    np.testing.assert_allclose(qd, 0.0, atol=1e-12)
    np.testing.assert_allclose(qdd, 0.0, atol=1e-12)
    knots = np.cumsum(h)[:-1]
    for eps_side in (-1e-9, 1e-9):
        qk, _, _ = mt.sample_path(keys, h, knots + eps_side)
        np.testing.assert_allclose(qk, keys[1:-1], atol=1e-7)
    _a, ad, add = mt.sample_path(keys, h, knots - 1e-7)
    _b, bd, bdd = mt.sample_path(keys, h, knots + 1e-7)
    np.testing.assert_allclose(ad, bd, atol=1e-5)
    np.testing.assert_allclose(add, bdd, atol=1e-4)
    # Velocities by differentiating the positions numerically.
    t = np.linspace(0.05, h.sum() - 0.05, 50)
    _qa, qda, qdda = mt.sample_path(keys, h, t)
    qp, qdp, _ = mt.sample_path(keys, h, t + 1e-6)
    qm, qdm, _ = mt.sample_path(keys, h, t - 1e-6)
    np.testing.assert_allclose((qp - qm) / 2e-6, qda, atol=1e-6)
    np.testing.assert_allclose((qdp - qdm) / 2e-6, qdda, atol=1e-5)


def test_constraints_against_independent_geometry() -> None:
    p = mt.make_problem(RIG, "hard")
    rng = np.random.default_rng(5)
    x = _start_point(p, 1) + np.r_[rng.normal(0.0, 0.03, 15), rng.uniform(-0.2, 0.2, 4)]
    ev = mt.Evaluator(RIG, p).evaluate(x[None, :])
    got = dict(zip(mt.CONSTRAINT_NAMES, ev.constraints[0], strict=True))
    keys, h = x[:15].reshape(5, 3), x[15:]
    tip = kinematics.forward(RIG, keys)
    H = p.surface_y_m
    vol = Polygon(tip[[0, 1, 2, 4], :2]).area * RIG.bucket.width_m
    lo, hi = p.volume_m3
    assert got["volume_min"] == pytest.approx((lo - vol) / (hi - lo), abs=1e-9)
    assert got["volume_max"] == pytest.approx((vol - hi) / (hi - lo), abs=1e-9)
    z1, z2 = p.depth_m
    for k, name in ((1, "b"), (2, "c")):
        depth = H - tip[k, 1]
        assert got[f"depth_min_{name}"] == pytest.approx((z1 - depth) / (z2 - z1), abs=1e-9)
        assert got[f"depth_max_{name}"] == pytest.approx((depth - z2) / (z2 - z1), abs=1e-9)
    band = p.surface_band_m
    assert got["entry_height_max"] == pytest.approx((tip[0, 1] - H) / band, abs=1e-9)
    assert got["exit_height_min"] == pytest.approx((H - tip[4, 1]) / band, abs=1e-9)
    x_lo, x_hi = p.entry_x_m
    assert got["entry_x_min"] == pytest.approx((x_lo - tip[0, 0]) / (x_hi - x_lo), abs=1e-9)
    # Heading cones: the worse half-plane is sin(angle from the axis) - cos(half-angle)...
    # i.e. the cone holds iff the angle to the axis is within the half-angle.
    down = math.degrees(abs(math.remainder(tip[0, 2] + math.pi / 2, 2 * math.pi)))
    entry = max(got["heading_entry_1"], got["heading_entry_2"])
    assert (entry <= 0.0) == (down <= p.entry_heading_deg)
    assert entry == pytest.approx(math.sin(math.radians(down - p.entry_heading_deg)), abs=1e-9)
    up = math.degrees(abs(math.remainder(tip[4, 2] - math.pi / 2, 2 * math.pi)))
    lift = max(got["heading_lift_1"], got["heading_lift_2"])
    assert lift == pytest.approx(math.sin(math.radians(up - p.lift_heading_deg)), abs=1e-9)
    for i in range(4):
        assert got[f"heading_turn_{i}"] == pytest.approx(
            math.sin(tip[i + 1, 2] - tip[i, 2]), abs=1e-9
        )
    chord = np.diff(tip[:, :2], axis=0)
    ang = np.arctan2(chord[:, 1], chord[:, 0])
    for i in range(3):
        assert got[f"travel_turn_{i}"] == pytest.approx(math.sin(ang[i + 1] - ang[i]), abs=1e-6)
    assert got["travel_penetration"] == pytest.approx(math.sin(ang[0]), abs=1e-6)
    assert got["travel_drag"] == pytest.approx(math.cos(ang[1]), abs=1e-6)
    assert got["travel_lift"] == pytest.approx(-math.sin(ang[3]), abs=1e-6)
    # Sampled limits: peaks on the optimiser's grid, from sample_path and the dynamics.
    t, _ = _grid(p, h)
    q, qd, _qdd = mt.sample_path(keys, h, t)
    span = RIG.q_max_rad - RIG.q_min_rad
    for j, name in enumerate(mt.JOINTS):
        assert got[f"angle_min_{name}"] == pytest.approx(
            (RIG.q_min_rad[j] - q[:, j].min()) / span[j], abs=1e-9
        )
        assert got[f"velocity_{name}"] == pytest.approx(
            np.abs(qd[:, j]).max() / RIG.qd_max_rad_s[j] - 1.0, abs=1e-9
        )
    assert len(got) == len(mt.CONSTRAINT_NAMES) == len(set(mt.CONSTRAINT_NAMES))


@pytest.mark.parametrize("backend", ["numpy", "c"])
@pytest.mark.parametrize("soil", ["soft", "hard"])
def test_a_row_alone_evaluates_as_it_does_in_a_batch(soil: str, backend: str) -> None:
    # numpy: up to _PLATE_AXIS_ROWS rows the soil's plates are one array axis, beyond it a
    # loop; C: a row at a time either way. The same cost and constraints, and the derivatives
    # from a given point's values equal those of one batched pass.
    p = mt.make_problem(RIG, soil)
    x = _start_point(p)
    rng = np.random.default_rng(3)
    X = x[None, :] + 1e-3 * rng.standard_normal((mt._PLATE_AXIS_ROWS + 2, x.size))
    ev = _evaluator(p, backend)
    batch = ev.evaluate(X)
    for i in range(X.shape[0]):
        row = ev.evaluate(X[i : i + 1])
        np.testing.assert_allclose(row.cost, batch.cost[i : i + 1], rtol=1e-12)
        np.testing.assert_allclose(row.split, batch.split[i : i + 1], rtol=1e-12, atol=1e-13)
    one = ev.evaluate(x[None, :])
    whole = ev.gradients(x)
    split = ev.gradients(x, (float(one.cost[0]), one.split[0]))
    for a, b in zip(whole, split, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("backend", ["numpy", "c"])
@pytest.mark.parametrize("fixed", [False, True])
def test_batched_gradients_against_central_differences(fixed: bool, backend: str) -> None:
    p = mt.make_problem(RIG, "hard", fixed_time=fixed, samples_per_interval=8)
    x = _start_point(p)
    ev = _evaluator(p, backend)
    f, df, c, dc = ev.gradients(x)
    step = 1e-5
    n = x.size
    num_f = np.empty(n)
    num_c = np.empty((c.size, n))
    for i in range(n):
        e = np.zeros(n)
        e[i] = step
        hi_e, lo_e = ev.evaluate((x + e)[None, :]), ev.evaluate((x - e)[None, :])
        num_f[i] = (hi_e.cost[0] - lo_e.cost[0]) / (2 * step)
        num_c[:, i] = (hi_e.split[0] - lo_e.split[0]) / (2 * step)
    assert f == pytest.approx(ev.evaluate(x[None, :]).cost[0])
    np.testing.assert_allclose(df, num_f, rtol=2e-3, atol=1e-4 * np.abs(num_f).max())
    np.testing.assert_allclose(dc, num_c, rtol=2e-3, atol=1e-4 * np.abs(num_c).max())


def _evaluator(p: mt.MinTorqueProblem, backend: str, **kw: object) -> mt.Evaluator:
    if backend == "c" and mt._kernel_module() is None:
        pytest.skip("the compiled kernel is not built")
    return mt.Evaluator(RIG, p, backend=backend, **kw)  # type: ignore[arg-type]


def _random_problem(rng: np.random.Generator) -> tuple[mt.MinTorqueProblem, np.ndarray]:
    """A problem with every number the kernel takes drawn at random (soil, surface, bands,
    time mode, samples, plates, limit scales) and a point anywhere within the variable bounds."""
    reach = float(np.sum(RIG.lengths_m))
    lo_v = rng.uniform(0.2, 0.7)
    p = mt.make_problem(
        RIG,
        str(rng.choice(["soft", "hard"])),
        volume_m3=(lo_v, lo_v + rng.uniform(0.05, 0.3)),
        fixed_time=bool(rng.integers(2)),
        entry_x_m=(rng.uniform(0.5, 0.6) * reach, rng.uniform(0.65, 0.8) * reach),
        surface_y_m=RIG.ground_y_m + rng.uniform(-0.5, 0.5),
        samples_per_interval=int(rng.choice([2, 5, 16, 32, 48])),
    )
    p = dataclasses.replace(
        p,
        n_elements=int(rng.integers(1, 13)),
        intervals_s=tuple(rng.uniform(0.4, 2.5, 4)),
        entry_heading_deg=rng.uniform(20.0, 70.0),
        lift_heading_deg=rng.uniform(20.0, 70.0),
    )
    bounds = mt.variable_bounds(RIG, p)
    x = np.array([rng.uniform(a, b) for a, b in bounds])
    return p, x


def test_the_compiled_model_equals_the_numpy_model_over_the_domain() -> None:
    # 40 seeded problems and points over the whole domain, plus a batch near each point: the
    # cost, every named constraint and every smooth maximum agree to rounding, and so do the
    # forward-difference derivatives (the kernel recomputes only the intervals a variable
    # moves; numpy recomputes every interval).
    rng = np.random.default_rng(20261128)
    for _ in range(40):
        p, x = _random_problem(rng)
        scale = rng.uniform(0.8, 1.0, (4, 3))
        c = _evaluator(p, "c", limit_scale=scale)
        n = mt.Evaluator(RIG, p, limit_scale=scale, backend="numpy")
        assert c.backend == "c" and n.backend == "numpy"
        X = x[None, :] + 1e-2 * rng.standard_normal((5, x.size))
        a, b = c.evaluate(X), n.evaluate(X)
        np.testing.assert_allclose(a.cost, b.cost, rtol=1e-11)
        np.testing.assert_allclose(a.constraints, b.constraints, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(a.split, b.split, rtol=1e-11, atol=1e-12)
        fa, dfa, ca, dca = c.gradients(x)
        fb, dfb, cb, dcb = n.gradients(x)
        assert fa == pytest.approx(fb, rel=1e-11)
        np.testing.assert_allclose(ca, cb, rtol=1e-11, atol=1e-12)
        # Differences of step 1e-6: a rounding of the cost (1e-16 relative) is 1e-10 of it.
        np.testing.assert_allclose(dfa, dfb, rtol=1e-6, atol=1e-9 * max(1.0, abs(fb)) / 1e-6)
        np.testing.assert_allclose(dca, dcb, rtol=1e-6, atol=1e-6)


def test_the_compiled_model_refuses_bad_arrays_and_an_unbuilt_kernel(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    p = mt.make_problem(RIG, "soft")
    ev = _evaluator(p, "c")
    params, basis, plates = ev._packed
    x = _start_point(p)
    cost, named, split = np.empty(1), np.empty((1, 44)), np.empty((1, mt.N_SPLIT))
    with pytest.raises(ValueError, match="15 or 19 columns"):
        ev.module.mintorque(np.zeros((1, 7)), params, basis, plates, cost, named, split)
    with pytest.raises(ValueError, match="params must have shape"):
        ev.module.mintorque(x[None, :], params[:10], basis, plates, cost, named, split)
    with pytest.raises(ValueError, match="plates must have at most"):
        big = np.zeros((300, 7))
        ev.module.mintorque(x[None, :], params, basis, big, cost, named, split)
    with pytest.raises(ValueError, match="one row per value of x"):
        ev.module.mintorque_perturbed(x, 1e-6, params, basis, plates, cost, split)
    with pytest.raises(ConfigurationError, match="unknown backend 'gpu'; allowed: auto, c, numpy"):
        mt.Evaluator(RIG, p, backend="gpu")
    monkeypatch.setattr(mt, "_kernel_module", lambda: None)
    with pytest.raises(ConfigurationError, match="not built"):
        mt.Evaluator(RIG, p, backend="c")
    assert mt.Evaluator(RIG, p).backend == "numpy"


@pytest.mark.parametrize("key", ["soft", "hard", "soft_fixed"])
def test_optimum_holds_on_the_exact_model_at_1_ms(solutions: dict, key: str) -> None:
    p, sol = solutions[key]
    assert sol.feasible, sol.margins
    assert min(sol.margins.values()) >= 0.0
    assert set(sol.margins) == set(mt.CONSTRAINT_NAMES)
    chk = mt.exact_check(RIG, p, sol.keypoints_rad, sol.intervals_s, dt_s=1e-3)
    assert np.diff(chk.t_s).max() <= 1e-3 + 1e-12
    assert np.all(chk.constraints <= 0.0)
    # Independently of the constraint code: joint and torque limits on the resample.
    q, qd, _ = sol.sample(chk.t_s)
    assert np.all(np.abs(qd) <= RIG.qd_max_rad_s)
    assert np.all(np.abs(chk.tau_nm) <= RIG.tau_max_nm)
    assert np.all((q >= RIG.q_min_rad) & (q <= RIG.q_max_rad))
    assert p.volume_m3[0] <= sol.volume_m3 <= p.volume_m3[1]
    assert sol.cost == pytest.approx(chk.cost)
    # The smoothed model the optimiser saw is within 10 % of the exact one (design note Y1).
    assert sol.cost_model == pytest.approx(sol.cost, rel=0.10)


def test_hard_soil_shallower_than_soft_from_the_same_start(solutions: dict) -> None:
    (ps, soft_sol), (ph, hard_sol) = solutions["soft"], solutions["hard"]
    starts_s = mt.kinematic_starts(RIG, ps, 3)
    starts_h = mt.kinematic_starts(RIG, ph, 3)
    for a, b in zip(starts_s, starts_h, strict=True):
        np.testing.assert_array_equal(a, b)
    assert hard_sol.max_depth_m < soft_sol.max_depth_m


def test_variable_time_cheaper_and_shorter_than_fixed(solutions: dict) -> None:
    _, var = solutions["soft"]
    _, fixed = solutions["soft_fixed"]
    # T is Yang/Pan's decision variable, the sum of the plan's keypoint intervals (the plan's
    # own time axis; no clock is read): the variable-time plan's intervals sum to less.
    planned_total = {
        name: float(np.sum(sol.intervals_s)) for name, sol in (("var", var), ("fixed", fixed))
    }
    assert planned_total["fixed"] == pytest.approx(5.0)
    assert planned_total["var"] < planned_total["fixed"]
    assert var.cost < fixed.cost


@pytest.mark.parametrize("key", ["soft", "hard"])
def test_halving_the_step_changes_the_cost_by_under_1_percent(solutions: dict, key: str) -> None:
    p, sol = solutions[key]
    p2 = dataclasses.replace(p, samples_per_interval=2 * p.samples_per_interval)
    c1 = mt.Evaluator(RIG, p).evaluate(sol.x[None, :]).cost[0]
    c2 = mt.Evaluator(RIG, p2).evaluate(sol.x[None, :]).cost[0]
    assert abs(c2 - c1) / c1 < 0.01
    e1 = mt.exact_check(RIG, p, sol.keypoints_rad, sol.intervals_s, dt_s=1e-3).cost
    e2 = mt.exact_check(RIG, p, sol.keypoints_rad, sol.intervals_s, dt_s=5e-4).cost
    assert abs(e2 - e1) / e1 < 0.01


@pytest.mark.parametrize(
    ("volume", "match"),
    [
        ((1.0, 0.8), "empty"),
        ((0.9, 0.9), "empty"),
        ((-0.2, 0.5), "not positive"),
        ((0.8, 1.5), "capacity"),
        ((math.nan, 1.0), "empty"),
    ],
)
def test_bad_volume_band_is_refused(volume: tuple[float, float], match: str) -> None:
    with pytest.raises(ConfigurationError, match=match):
        mt.make_problem(RIG, "soft", volume_m3=volume)


def test_unknown_soil_is_refused_naming_the_known_ones() -> None:
    with pytest.raises(ConfigurationError, match=r"no fluid soil 'clay'.*soft, hard"):
        mt.make_problem(RIG, "clay")


def test_a_rig_without_the_soil_is_refused(tmp_path: Path) -> None:
    text = PROFILE.read_text().replace("[soil.fluid.hard]", "[soil.fluid.medium]")
    path = tmp_path / "no_hard.toml"
    path.write_text(text)
    rig = load_rig(str(path))
    with pytest.raises(ConfigurationError, match=r"no fluid soil 'hard'.*soft, medium"):
        mt.make_problem(rig, "hard")


def test_no_reachable_start_is_a_planning_error() -> None:
    p = mt.make_problem(RIG, "soft", entry_x_m=(30.0, 31.0))
    assert mt.kinematic_starts(RIG, p, 3) == []
    with pytest.raises(PlanningError, match="no kinematic start"):
        mt.solve(RIG, p)


def test_the_cheapest_start_wins_when_the_answers_differ_by_rounding_in_their_violation() -> (
    None
):
    """Seeded soft problem 2 of the benchmark (seed 0): one start ends in IPOPT's basin a
    rounding (~1e-9) outside the offset constraints, another at 0 but 1.3 % dearer. Deb's rule
    counts both as feasible and takes the cheaper (design note Y2)."""
    from rt_runtime.bench_mintorque import random_problems

    p = random_problems(RIG, 3, 0)[2]
    starts = [mt.initial_point(p, s) for s in mt.kinematic_starts(RIG, p, 3)]
    alone = [mt.solve(RIG, p, starts=[s]) for s in starts]
    together = mt.solve(RIG, p, starts=starts)
    assert all(a.feasible for a in alone) and together.feasible
    cheapest = min(a.cost_model for a in alone)
    assert max(a.cost_model for a in alone) > 1.01 * cheapest  # two basins among the starts
    assert together.cost_model == pytest.approx(cheapest, rel=1e-9)


def test_reference_is_the_same_problem() -> None:
    """The CasADi NLP and the numpy model agree: IPOPT's answer evaluates the same in ours and
    is feasible there, and our answer has the same cost in the NLP and is feasible for it (the
    smooth maximum is above every sample). The gap from a common start is the benchmark's
    measure, not asserted here (the problem has several local optima)."""
    pytest.importorskip("casadi")
    p = mt.make_problem(RIG, "soft", fixed_time=True, samples_per_interval=8)
    sol = mt.solve(RIG, p, n_starts=1, rechecks=0)
    ref = mt.CasadiReference(RIG)
    r = ref.solve(p, sol.start, sol.limit_scale)
    assert r.ok, r.status
    ev = mt.Evaluator(RIG, p, limit_scale=sol.limit_scale).evaluate(r.x[None, :])
    assert ev.cost[0] == pytest.approx(r.cost_model, rel=1e-9)
    assert np.max(ev.constraints[0]) <= 1e-6
    f, g = ref.evaluate(p, sol.x, sol.limit_scale)
    assert f == pytest.approx(sol.cost_model, rel=1e-9)
    assert np.max(g) <= 1e-6  # SLSQP holds its constraints to ~1e-7
    # The NLP's rows are the numpy model's: one per sample, joint and side, then the keypoints.
    n_samples = mt.N_INTERVALS * (p.samples_per_interval + 1)
    assert g.size == 30 * n_samples + len(mt.KEYPOINT_CONSTRAINTS)
    e = mt.Evaluator(RIG, p, limit_scale=sol.limit_scale).evaluate(sol.x[None, :])
    np.testing.assert_allclose(
        g[-len(mt.KEYPOINT_CONSTRAINTS) :] - mt.CONSTRAINT_OFFSET,
        e.constraints[0, len(mt.SAMPLE_CONSTRAINTS) :],
        atol=1e-9,
    )


def test_cli_json_keys_and_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    from rt_runtime.cli import main

    assert main(["mintorque", "--rig", "yang_pan_excavator", "--soil", "clay"]) == 2
    err = capsys.readouterr()
    assert "clay" in err.out + err.err
    assert main(["mintorque", "--soil", "soft", "--volume-m3", "1.0,0.8"]) == 2
    assert "empty" in "".join(capsys.readouterr())
    assert main(["mintorque", "--soil", "soft", "--volume-m3", "x"]) == 2
    capsys.readouterr()
    code = main(["mintorque", "--rig", "yang_pan_excavator", "--soil", "hard", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == (0 if report["feasible"] else 1)
    for key in ("feasible", "keypoints", "intervals_s", "T_s", "cost", "volume_m3",
                "max_depth_m", "margins", "solve_s"):  # fmt: skip
        assert key in report
    assert set(report["margins"]) == set(mt.CONSTRAINT_NAMES)
    assert len(report["keypoints"]) == 5 and len(report["intervals_s"]) == 4


def test_readme_key_lists_name_keys_the_reports_hold(solutions: dict) -> None:
    """The README's ``mintorque --json`` list against a real report, and the ``bench
    mintorque --json`` list against a quick bench run's keys (structure only)."""
    from test_report_keys import README, _list_of, _paragraph, contract_keys, missing

    from rt_runtime.bench_mintorque import solution_json

    p, sol = solutions["hard"]
    report = solution_json(RIG, sol, p)
    report["plot"] = "f.png"
    keys = contract_keys(_list_of(_paragraph(README, "`mintorque --json`")))
    assert {("keypoints", "q_deg"), ("margins",), ("max_depth_m",)} <= keys
    assert missing(report, keys) == []
    bench_keys = contract_keys(_list_of(_paragraph(README, "`bench mintorque --json`")))
    for key in ("problems", "solve_s", "feasible", "gap_to_reference", "soil", "time"):
        assert (key,) in bench_keys
    assert {("soil", "max_depth_m"), ("time", "variable"), ("time", "T_s"), ("solve_s", "p99"),
            ("gap_to_reference", "max")} <= bench_keys  # fmt: skip


def test_bench_json_on_one_problem_without_the_reference(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from test_report_keys import README, _list_of, _paragraph, contract_keys, missing

    from rt_runtime.cli import main

    args = ["bench", "mintorque", "--quick", "--problems", "1", "--no-reference", "--json"]
    assert main(args) == 0
    report = json.loads(capsys.readouterr().out)
    keys = contract_keys(_list_of(_paragraph(README, "`bench mintorque --json`")))
    # Without the reference its figures are null or absent.
    keys = {
        k for k in keys if k[0] != "reference" and not (k[0] == "gap_to_reference" and len(k) > 1)
    }
    assert report["gap_to_reference"] is None and report["reference_skipped"]
    assert missing(report, keys) == []
    assert report["problems"] == 1 and report["n_starts"] == 1
    assert 0.0 <= report["feasible"] <= 1.0


def test_min_torque_one_shot_planner_in_the_trench_planner() -> None:
    """The torque cost as a one-shot planner: verified sextics no costlier (in that cost) than
    the PSO teacher's plan of the same problem, and a trench task with a dig it planned."""
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.mintorque_oneshot import MinTorqueOneShot
    from rt_runtime.planning.trench import TrenchPlanner, load_task

    rig = load_rig("scale_model")
    planner = TrenchPlanner(rig, "min_torque")
    adapter = planner.oneshot
    assert isinstance(adapter, MinTorqueOneShot) and adapter.name == "min_torque"
    problem = oneshot.sample_problems(rig, 1, oneshot.DigType.DOWNWARD, seed=1)[0]
    res = adapter.plan_dig(problem, 1.0)
    assert res.status == "min_torque"
    pso = oneshot.solve_pso(rig, [problem])[0]
    assert pso.feasible
    ours, v = adapter.cost(problem, oneshot.particle_from_a6(res.a6, res.T_s)[None, :])
    theirs, _ = adapter.cost(problem, oneshot.particle_from_a6(pso.a6, pso.T_s)[None, :])
    assert np.all(v <= 0.0)
    assert ours[0] <= theirs[0] * 1.001
    plan = planner.plan(load_task("D", rig))
    assert plan.status.name == "DONE"
    assert any(getattr(s, "status", "") == "min_torque" for s in plan.steps)
    with pytest.raises(ConfigurationError, match="min_torque"):
        TrenchPlanner(rig, "unknown")
    with pytest.raises(ConfigurationError, match="no fluid soil 'clay'"):
        MinTorqueOneShot(rig, planner.verifier, "clay")


@pytest.mark.parametrize("name", ["min_torque", "pso"])
def test_a_trench_is_planned_without_a_trained_network(name: str, tmp_path: Path) -> None:
    """On a rig whose model directory holds no network the min-torque and PSO planners still
    plan a trench: the rough stage screens with the closed-form bulge, the one-shot planner
    plans the chosen poses, and the plan meets the goals with a dig of its own."""
    from rt_runtime.planning.trench import TrenchPlanner, load_task

    rig = load_rig("scale_model")
    planner = TrenchPlanner(rig, name, model_dir=tmp_path)
    assert planner.pinn is None and planner.screening == "geometric"
    plan = planner.plan(load_task("D", rig))
    report = plan.to_json()
    assert report["status"] == "done", report["reason"]
    assert report["screening"] == "geometric" and report["planner"] == name
    assert report["coverage_error"] <= 0.02 and report["overdig_max_mm"] <= 5.0
    own = [d for d in report["digs"] if d["status"] == name]
    assert own, [d["status"] for d in report["digs"]]
    lo, hi = (v * 1e3 for v in oneshot_volume_band(rig))
    # The fill rule on each dig: its joined pieces together, one bucket.
    for k, volume in enumerate(report["bucket_L"]):
        pieces = [d for d in report["digs"] if d["bucket"] == k]
        assert pieces[0]["finishing"] or lo - 1e-9 <= volume <= hi + 1e-9, pieces


def oneshot_volume_band(rig: object) -> tuple[float, float]:
    from rt_runtime.planning import oneshot

    planning = oneshot.require_planning(rig)  # type: ignore[arg-type]
    return planning.volume_min_m3, planning.volume_max_m3


def test_the_geometric_bulge_moves_the_mid_path_tip_by_its_target(tmp_path: Path) -> None:
    # Its definition: for poses across the candidate grid, a small scale c of K moves the tip
    # at mid-path by c times the dig type's target (to first order), and turns the bucket by c
    # times the attitude target.
    from rt_runtime.planning.oneshot import DigType
    from rt_runtime.planning.trench import TrenchPlanner, load_task

    rig = load_rig("scale_model")
    planner = TrenchPlanner(rig, "pso", model_dir=tmp_path)
    session = planner.start(load_task("D", rig))
    rng = np.random.default_rng(5)
    X = np.empty((50, 7))
    X[:, 0:6] = np.tile(planner.home_pose_rad, 2) + rng.uniform(-0.3, 0.3, (50, 6))
    X[:, 6] = rig.ground_y_m
    from rt_runtime.planning.trench.geometry import _sextic_shapes

    assert _sextic_shapes(3)[1][1] == pytest.approx(1.0 / 64.0)  # the bulge's shape at s = 1/2
    c = 1e-4
    for kind in DigType:
        K, T = session._geometric_bulge(X, kind)
        assert np.all(np.isfinite(K)) and np.all(T > 0.0)
        mid = 0.5 * (X[:, 0:3] + X[:, 3:6])
        moved = kinematics.forward(rig, mid + c * K / 64.0) - kinematics.forward(rig, mid)
        np.testing.assert_allclose(
            moved / c, np.broadcast_to(planner.geometric_bulge[kind], moved.shape), rtol=2e-3,
            atol=1e-4,
        )


@pytest.mark.parametrize("rig_name", ["scale_model", "yang_pan_excavator"])
def test_the_one_shot_cost_by_the_kernel_equals_the_numpy_model(rig_name: str) -> None:
    # The min-torque one-shot planner's cost (the compiled model on the sextic's samples) and
    # its constraints (the verifier's kernel) against the numpy model and oneshot.evaluate, on
    # seeded problems of both dig types and particles anywhere in the search box, both soils.
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.mintorque_oneshot import MinTorqueOneShot
    from rt_runtime.planning.verify import Verifier

    rig = load_rig(rig_name)
    verifier = Verifier(rig, oneshot.DEFAULT_SAMPLES, backend="c")
    rng = np.random.default_rng(11)
    for soil_name in ("soft", "hard"):
        c = MinTorqueOneShot(rig, verifier, soil_name)
        n = MinTorqueOneShot(rig, verifier, soil_name, backend="numpy")
        if c.backend != "c":
            pytest.skip("the compiled kernel is not built")
        problems = oneshot.sample_problems(rig, 5, oneshot.DigType.DOWNWARD, seed=2)
        problems += oneshot.sample_problems(rig, 5, oneshot.DigType.BACKWARD, seed=3)
        for p in problems:
            X = c.lo + rng.uniform(size=(6, 4)) * (c.hi - c.lo)
            a, av = c.cost(p, X)
            b, bv = n.cost(p, X)
            np.testing.assert_allclose(a, b, rtol=1e-12)
            np.testing.assert_allclose(av, bv, rtol=1e-10, atol=1e-12)
    with pytest.raises(ConfigurationError, match="unknown backend"):
        MinTorqueOneShot(rig, verifier, backend="gpu")
    with pytest.raises(ConfigurationError, match="compiled verifier on 101 samples"):
        MinTorqueOneShot(rig, Verifier(rig, 51, backend="c"), backend="c")


def test_yang_pans_excavator_trench_planned_by_the_min_torque_planner(tmp_path: Path) -> None:
    # The rig has no trained network: the geometric screening picks the poses and the
    # minimum-torque planner plans the first dig of an 8 m x 1.5 m trench in each soil's cost:
    # verified on Yao's eq 12 and carrying 0.8-1.2 m^3 of real material (its planning table).
    from rt_runtime.planning.trench import TrenchPlanner, load_task
    from rt_runtime.planning.verify import COL_TOTAL

    rig = load_rig("yang_pan_excavator")
    path = tmp_path / "long.toml"
    path.write_text("length_m = 8.0\ndepth_m = 1.5\nbeta1_deg = 70.0\nbeta2_deg = 50.0\n")
    task = load_task(str(path), rig)
    planner = TrenchPlanner(rig, "min_torque")
    assert planner.screening == "geometric" and planner.soil == "soft"
    session = planner.start(task)
    dig = session.next_dig()
    assert dig is not None and dig.status == "min_torque" and not dig.finishing
    assert 0.8 - 1e-9 <= dig.volume_m3 <= 1.2 + 1e-9
    assert dig.evaluation[COL_TOTAL] <= 0.0
    with pytest.raises(ConfigurationError, match="applies to the min_torque planner only"):
        TrenchPlanner(rig, "pso", soil="hard")
    with pytest.raises(ConfigurationError, match="no fluid soil 'clay'"):
        TrenchPlanner(rig, "min_torque", soil="clay")
    assert TrenchPlanner(rig, "min_torque", soil="hard").oneshot.soil.name == "hard"


def test_the_network_screening_and_the_pinn_planner_need_the_models(tmp_path: Path) -> None:
    from rt_runtime.control.planner_worker import PlannerSpec
    from rt_runtime.planning.trench import TrenchPlanner, load_task

    rig = load_rig("scale_model")
    for kwargs in ({"planner": "pinn"}, {"planner": "min_torque", "screening": "network"}):
        with pytest.raises(ConfigurationError, match="need the rig's trained models"):
            TrenchPlanner(rig, model_dir=tmp_path, **kwargs)  # type: ignore[arg-type]
    with pytest.raises(ConfigurationError, match="unknown screening 'pinn'; allowed: auto"):
        TrenchPlanner(rig, "pso", screening="pinn")
    # With the shipped models the auto screening takes the network, and a planner process
    # rebuilds the planner with the screening its parent had.
    assert TrenchPlanner(rig, "pso").screening == "network"
    geometric = TrenchPlanner(rig, "pso", screening="geometric")
    assert geometric.pinn is None
    spec = PlannerSpec.of(geometric.start(load_task("A", rig)))
    assert spec.screening == "geometric"


def test_cli_exit_1_when_the_answer_is_not_feasible(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A depth band 5-6 m below the surface, out of the arm's reach from the entry window (a
    few SLSQP iterations from one start): the answer is reported, exit 1."""
    import rt_runtime.bench_mintorque as bench

    real = mt.solve

    def few_iterations(rig: object, problem: mt.MinTorqueProblem, **_: object) -> mt.Solution:
        deep = dataclasses.replace(problem, depth_m=(5.0, 6.0))
        start = mt.kinematic_starts(RIG, problem, 1)
        return real(rig, deep, starts=start, max_iterations=5, rechecks=0)  # type: ignore[arg-type]

    monkeypatch.setattr(bench.mt, "solve", few_iterations)
    from rt_runtime.cli import main

    assert main(["mintorque", "--soil", "soft", "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["feasible"] is False
    assert min(report["margins"].values()) < 0.0


def test_cli_refuses_a_rig_without_the_fluid_soil_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from rt_runtime.cli import main

    lines = PROFILE.read_text().splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith("[soil.fluid.soft]"))
    end = next(i for i, ln in enumerate(lines) if ln.startswith("[cylinders]"))
    path = tmp_path / "no_fluid.toml"
    path.write_text("\n".join(lines[:start] + lines[end:]) + "\n")
    assert main(["mintorque", "--rig", str(path), "--soil", "soft", "--json"]) == 2
    out = capsys.readouterr()
    assert "fluid" in out.err and out.out == ""


def test_hil_mintorque_runs_the_dig_and_reports_torques(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The optimised dig on the lockstep HIL in soft soil: it runs to its end, tracking and
    plant-against-planned torques are reported with every documented key."""
    from test_report_keys import README, _list_of, _paragraph, contract_keys, missing

    from rt_runtime.cli import main

    assert main(["hil", "--mintorque", "soft", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    keys = contract_keys(_list_of(_paragraph(README, "`hil --mintorque --json`")))
    assert {("torque", "rms_plant_nm"), ("tracking", "reported", "max_mm")} <= keys
    assert missing(report, keys) == []
    assert report["status"] == "done"
    # Soft soil within Gao's band on every cylinder with the lead of each cylinder's valve and
    # oil-column mode (the boom is 3.1 mm without it).
    assert report["velocity_lead2_s2"][0] > 0.0
    for axis, fig in report["tracking"].items():
        assert fig["max_mm"] <= 3.0, (axis, fig)
    assert set(report["torque"]) == set(mt.JOINTS)
    for t in report["torque"].values():
        assert t["rms_planned_nm"] > 0.0 and t["rms_plant_nm"] > 0.0
    assert main(["hil", "--mintorque", "clay", "--json"]) == 2
    assert "clay" in json.loads(capsys.readouterr().out)["error"]


def test_hil_mintorque_in_hard_soil_keeps_gaos_band_on_every_cylinder(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Hard soil loads the boom so that its oil column (3.7 Hz) rings under the plain position
    loop (11.6 mm); the boom drive's dynamic pressure feedback damps it (design note Y5)."""
    from rt_runtime.cli import main

    assert main(["hil", "--mintorque", "hard", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["status"] == "done"
    for axis, fig in report["tracking"].items():
        assert fig["max_mm"] <= 3.0, (axis, fig)
    # The plant's joint torques follow the plan's within a few % of the limits.
    for joint, t in report["torque"].items():
        assert t["rms_difference_of_limit"] < 0.1, (joint, t)
