"""Tests of the minimum time-jerk generator (Zhao eq 3), its CLI and its benchmark.

Checked by the conditions themselves (waypoints, end states, continuity), by numerical
integration and differentiation, by dense resampling against the exact limit check, by
perturbing the optimum, by an independent minimum-time search, and against CasADi/IPOPT where
the ``reference`` extra is installed. Random problems are seeded and print the failing case.
"""

from __future__ import annotations

import builtins
import json
from typing import Any

import numpy as np
import pytest
import scipy.integrate
import scipy.optimize

from rt_runtime.bench_timejerk import random_problems
from rt_runtime.cli import main
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.rig import load_rig
from rt_runtime.trajectory.timejerk import (
    LIMIT_TOLERANCE,
    MIN_DURATION_S,
    TimeJerkProblem,
    TimeJerkTrajectory,
    interpolate,
    plan,
    start_durations,
)


def _case(p: TimeJerkProblem) -> str:
    """A failing problem, printable and replayable."""
    return (
        f"waypoints_rad={p.waypoints_rad.tolist()}, V={p.velocity_max_rad_s.tolist()}, "
        f"A={p.acceleration_max_rad_s2.tolist()}, w_jerk={p.w_jerk!r}, w_time={p.w_time!r}, "
        f"v0={p.start_velocity_rad_s.tolist()}, vn={p.end_velocity_rad_s.tolist()}, "
        f"a0={p.start_acceleration_rad_s2.tolist()}, an={p.end_acceleration_rad_s2.tolist()}"
    )


def _problems() -> list[TimeJerkProblem]:
    """Hand-made problems covering the shapes: two waypoints, one joint, moving ends, weights."""
    v = [0.5, 0.6, 0.7]
    a = [1.0, 0.8, 1.2]
    q = [[0.1, -1.0, -0.5], [0.6, -1.6, -1.2], [0.3, -0.8, -0.3], [0.5, -1.2, -0.9]]
    return [
        TimeJerkProblem.create(q, v, a),
        TimeJerkProblem.create(q, v, a, w_jerk=0.05),
        TimeJerkProblem.create(q[:2], v, a),
        TimeJerkProblem.create(q[:2], v, a, w_jerk=0.3),
        TimeJerkProblem.create([[0.0], [1.0], [0.2]], [0.4], [0.5], w_jerk=0.01),
        TimeJerkProblem.create(
            q,
            v,
            a,
            w_jerk=0.02,
            start_velocity_rad_s=[0.1, -0.2, 0.15],
            end_velocity_rad_s=[-0.1, 0.05, 0.2],
            start_acceleration_rad_s2=[0.2, 0.1, -0.3],
            end_acceleration_rad_s2=[-0.1, 0.2, 0.3],
        ),
    ]


PROBLEMS = _problems()


@pytest.fixture(scope="module")
def solved() -> list[TimeJerkTrajectory]:
    return [plan(p) for p in PROBLEMS]


def _assert_through_waypoints_and_continuous(
    traj: TimeJerkTrajectory, p: TimeJerkProblem, case: str
) -> None:
    """Through every waypoint at its time, the given end states, and each piece's end state
    (position, velocity, acceleration) the next piece's start, from the coefficients."""
    np.testing.assert_allclose(
        traj.sample(traj.waypoint_times_s), p.waypoints_rad, rtol=0, atol=1e-9, err_msg=case
    )
    start, end = traj.states(0.0), traj.states(traj.duration_s)
    for state, q, v, a in (
        (start, p.waypoints_rad[0], p.start_velocity_rad_s, p.start_acceleration_rad_s2),
        (end, p.waypoints_rad[-1], p.end_velocity_rad_s, p.end_acceleration_rad_s2),
    ):
        np.testing.assert_allclose(state[:3], [q, v, a], rtol=0, atol=1e-9, err_msg=case)
    c, h = traj.coefficients, traj.piece_durations_s[:, None]
    ends = np.stack(
        [
            ((c[..., 0] * h + c[..., 1]) * h + c[..., 2]) * h + c[..., 3],
            (3 * c[..., 0] * h + 2 * c[..., 1]) * h + c[..., 2],
            6 * c[..., 0] * h + 2 * c[..., 1],
        ]
    )[:, :-1]
    starts = np.stack([c[1:, :, 3], c[1:, :, 2], 2 * c[1:, :, 1]])
    np.testing.assert_allclose(ends, starts, rtol=0, atol=1e-9, err_msg=case)


@pytest.mark.parametrize("k", range(len(PROBLEMS)))
def test_waypoints_end_states_and_continuity(k: int, solved: list[TimeJerkTrajectory]) -> None:
    traj, p = solved[k], PROBLEMS[k]
    assert traj.problem is p
    assert traj.n_pieces == p.waypoints_rad.shape[0] + 1
    _assert_through_waypoints_and_continuous(traj, p, _case(p))


@pytest.mark.parametrize("k", range(len(PROBLEMS)))
def test_jerk_integral_matches_a_numerical_integral(
    k: int, solved: list[TimeJerkTrajectory]
) -> None:
    traj = solved[k]
    total = 0.0
    for i in range(traj.n_pieces):
        a, b = traj.knots_s[i], traj.knots_s[i + 1]
        d = 1e-3 * (b - a)

        def jerk_sq(t: float, a: float = a, b: float = b, d: float = d) -> float:
            # Central difference of the acceleration inside the piece (the jerk jumps at knots).
            lo, hi = max(t - d, a), min(t + d, b)
            jerk = (traj.sample(hi, 2) - traj.sample(lo, 2)) / (hi - lo)
            return float(np.sum(jerk**2))

        total += scipy.integrate.quad(jerk_sq, a, b, epsabs=0.0, epsrel=1e-10, limit=200)[0]
    assert total == pytest.approx(traj.jerk_integral, rel=1e-7, abs=1e-12)
    p = traj.problem
    expected = p.w_jerk * traj.jerk_integral + p.w_time * traj.duration_s
    assert traj.objective == pytest.approx(expected)


def test_limits_hold_exactly_and_on_resamples_of_seeded_random_problems() -> None:
    """Random problems over every rig (both weights, moving ends): the exact check holds, a
    1 kHz resample and a dense resample through every knot agree with it, and the exact peaks
    are the dense maxima (the extreme finder misses nothing)."""
    for k, (rig, p) in enumerate(random_problems(24, seed=3, n_waypoints=6)):
        traj = plan(p)
        exact = traj.limit_check()
        case = f"problem {k} on {rig}: {_case(p)}"
        assert exact.exact and exact.within_limits, case
        assert np.all(exact.velocity_ratio <= 1 + LIMIT_TOLERANCE), case
        assert np.all(exact.acceleration_ratio <= 1 + LIMIT_TOLERANCE), case
        assert traj.sampled_limit_check(1000.0).within_limits, case
        t = np.unique(np.concatenate([np.linspace(0.0, traj.duration_s, 200_001), traj.knots_s]))
        dense_v = np.max(np.abs(traj.sample(t, 1)), axis=0)
        dense_a = np.max(np.abs(traj.sample(t, 2)), axis=0)
        np.testing.assert_allclose(dense_v, exact.velocity_peak_rad_s, rtol=1e-6, err_msg=case)
        np.testing.assert_allclose(
            dense_a, exact.acceleration_peak_rad_s2, rtol=1e-12, err_msg=case
        )
        assert np.all(dense_v <= exact.velocity_peak_rad_s * (1 + 1e-12)), case


@pytest.mark.parametrize("k", range(len(PROBLEMS)))
def test_the_optimum_is_stationary(k: int, solved: list[TimeJerkTrajectory]) -> None:
    """No single duration moved by +-1e-3 or +-1e-5 (relative) improves the objective while
    keeping every limit."""
    traj = solved[k]
    p = traj.problem
    for i in range(traj.n_pieces):
        for step in (1e-3, -1e-3, 1e-5, -1e-5):
            h = traj.piece_durations_s.copy()
            h[i] = max(h[i] * (1 + step), MIN_DURATION_S)
            moved = interpolate(p, h)
            if moved.limit_check().within_limits:
                assert moved.objective >= traj.objective * (1 - 1e-9), (
                    f"piece {i} x {1 + step}: {moved.objective!r} < {traj.objective!r}; {_case(p)}"
                )


@pytest.mark.parametrize("k", [0, 3, 4, 5])
def test_analytic_gradients_match_central_differences(k: int) -> None:
    """The search's objective and constraint gradients (position slots included) against
    central differences, at durations away from the optimum."""
    from rt_runtime.trajectory.timejerk import _Evaluator, _Layout

    base = PROBLEMS[k]
    p = TimeJerkProblem.create(
        base.waypoints_rad,
        base.velocity_max_rad_s,
        base.acceleration_max_rad_s2,
        w_jerk=base.w_jerk + 0.01,
        start_velocity_rad_s=base.start_velocity_rad_s,
        end_velocity_rad_s=base.end_velocity_rad_s,
        start_acceleration_rad_s2=base.start_acceleration_rad_s2,
        end_acceleration_rad_s2=base.end_acceleration_rad_s2,
        position_min_rad=np.min(base.waypoints_rad, axis=0) - 0.05,
        position_max_rad=np.max(base.waypoints_rad, axis=0) + 0.05,
    )
    lay = _Layout(p)
    h = start_durations(p) * np.random.default_rng(k).uniform(0.6, 1.4, p.n_pieces)

    def at(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        ev = _Evaluator(lay, 1.0, 1.0, positions=True)
        f, df = ev.fun(x)
        return f, df, ev.cons(x).copy(), ev.cons_jac(x).copy()

    _, df, _, dc = at(h)
    eps = 1e-7
    for i in range(p.n_pieces):
        up, down = h.copy(), h.copy()
        up[i] += eps
        down[i] -= eps
        (fu, _, cu, _), (fd, _, cd, _) = at(up), at(down)
        assert (fu - fd) / (2 * eps) == pytest.approx(df[i], rel=1e-5, abs=1e-7)
        np.testing.assert_allclose((cu - cd) / (2 * eps), dc[:, i], rtol=1e-5, atol=1e-6)


def _minimum_time_by_scaling(p: TimeJerkProblem, starts: list[np.ndarray]) -> float:
    """An independent minimum-time search for rest-to-rest ends: a uniform time scaling keeps the
    path, so the shortest feasible T of a duration shape ``x`` is ``sum(x) * r(x)`` with ``r``
    the exact peak ratio (velocity, root of acceleration); Nelder-Mead over log-shapes."""

    def t_of(log_x: np.ndarray) -> float:
        x = np.exp(log_x - np.max(log_x))
        chk = interpolate(p, np.maximum(x, 1e-9) * 10.0).limit_check()
        r = max(np.max(chk.velocity_ratio), np.sqrt(np.max(chk.acceleration_ratio)))
        h = x * 10.0 * r
        # The generator's shortest piece is a bound of the problem: honour it here too.
        return float(np.sum(h) + 1e3 * np.sum(np.maximum(MIN_DURATION_S - h, 0.0)))

    best = np.inf
    for x0 in starts:
        res = scipy.optimize.minimize(
            t_of,
            np.log(x0),
            method="Nelder-Mead",
            options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 20_000},
        )
        best = min(best, float(res.fun))
    return best


def test_w_jerk_zero_is_the_minimum_time_solution() -> None:
    p = TimeJerkProblem.create([[0.1, -1.0], [0.6, -1.6], [0.3, -0.9]], [0.5, 0.6], [1.0, 0.8])
    fastest = plan(p)
    assert fastest.objective == pytest.approx(fastest.duration_s)
    rng = np.random.default_rng(5)
    starts = [fastest.piece_durations_s, start_durations(p)] + [
        rng.uniform(0.2, 1.0, 4) for _ in range(3)
    ]
    # Trajectory durations (the plans' own time), not wall time.
    by_scaling = _minimum_time_by_scaling(p, starts)
    assert fastest.duration_s / by_scaling <= 1 + 1e-7
    assert fastest.duration_s == pytest.approx(by_scaling, rel=1e-4)
    # Any weight on the jerk costs time; a vanishing weight tends to the minimum time.
    previous = fastest.duration_s
    for w in (1e-9, 1e-3, 1e-2, 1e-1):
        weighted = plan(TimeJerkProblem.create(p.waypoints_rad, [0.5, 0.6], [1.0, 0.8], w_jerk=w))
        assert weighted.duration_s >= previous * (1 - 1e-7)
        assert weighted.jerk_integral <= fastest.jerk_integral * (1 + 1e-7)
        previous = weighted.duration_s
    tiny = plan(TimeJerkProblem.create(p.waypoints_rad, [0.5, 0.6], [1.0, 0.8], w_jerk=1e-12))
    assert tiny.duration_s == pytest.approx(fastest.duration_s, rel=1e-4)


def test_casadi_ipopt_reference_agrees() -> None:
    pytest.importorskip("casadi")
    from rt_runtime.bench_timejerk import CasadiReference

    ref = CasadiReference()
    for p in (PROBLEMS[0], PROBLEMS[1], PROBLEMS[2], PROBLEMS[5]):
        ours = plan(p)
        sol = ref.solve(p)
        assert sol.ok, sol.status
        assert ours.objective == pytest.approx(sol.objective, rel=1e-6), _case(p)
        assert sol.trajectory.limit_check().velocity_ratio.max() <= 1 + 1e-6


def test_toppra_bound_is_below_our_time() -> None:
    pytest.importorskip("toppra")
    from rt_runtime.bench_timejerk import toppra_bound

    for traj in (plan(PROBLEMS[0]), plan(PROBLEMS[1])):
        t_bound, slowdown = toppra_bound(traj)
        assert slowdown >= 1.0
        assert t_bound < traj.duration_s


def test_position_bounds_keep_an_overshooting_trajectory_inside() -> None:
    q = [[0.0], [0.9], [1.0], [0.2]]
    free = plan(TimeJerkProblem.create(q, [0.5], [0.6], w_jerk=0.01))
    assert free.limit_check().position_high_rad[0] > 1.0005  # the bound below is binding
    bounded = plan(
        TimeJerkProblem.create(
            q, [0.5], [0.6], w_jerk=0.01, position_min_rad=[-0.1], position_max_rad=[1.0005]
        )
    )
    chk = bounded.limit_check()
    assert chk.within_limits and chk.position_high_rad[0] <= 1.0005 * (1 + 1e-9)
    t = np.linspace(0.0, bounded.duration_s, 100_001)
    assert np.max(bounded.sample(t)) <= 1.0005 + 1e-9
    assert bounded.objective >= free.objective


def test_for_rig_orders_swing_first_and_takes_the_limits() -> None:
    rig = load_rig("field_excavator")
    p = TimeJerkProblem.for_rig(rig, np.radians([[0, 10, -60, -40], [90, 20, -100, -30]]))
    assert p.n_joints == 4
    assert p.velocity_max_rad_s[0] == rig.swing.joint.velocity_max_rad_s  # type: ignore[union-attr]
    np.testing.assert_array_equal(p.acceleration_max_rad_s2[1:], rig.qdd_max_rad_s2)
    with pytest.raises(ConfigurationError, match="4 joints"):
        TimeJerkProblem.for_rig(rig, np.zeros((2, 3)))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"waypoints_rad": [[0.0, 0.0]]}, "at least 2 waypoints"),
        ({"waypoints_rad": [[0.0, np.nan], [1.0, 1.0]]}, "finite"),
        ({"waypoints_rad": [[0.0, 0.0], [0.0, 0.0]]}, "same pose"),
        ({"velocity_max_rad_s": [1.0, 0.0]}, "velocity_max_rad_s must be > 0"),
        ({"acceleration_max_rad_s2": [1.0, 1.0, 1.0]}, "shape"),
        ({"w_jerk": -1.0}, "w_jerk must be"),
        ({"w_time": 0.0}, "w_time must be > 0"),
        ({"w_time": float("nan")}, "w_time must be"),
        ({"start_velocity_rad_s": [2.0, 0.0]}, "beyond the joint's limit"),
        (
            {"position_min_rad": [-1.0, -1.0], "position_max_rad": [0.5, 2.0]},
            "outside the position bounds",
        ),
    ],
)
def test_malformed_problems_are_refused(kwargs: dict[str, Any], match: str) -> None:
    args: dict[str, Any] = {
        "waypoints_rad": [[0.0, 0.0], [1.0, 0.5]],
        "velocity_max_rad_s": [1.0, 1.0],
        "acceleration_max_rad_s2": [1.0, 1.0],
    }
    args.update(kwargs)
    with pytest.raises(ConfigurationError, match=match):
        TimeJerkProblem.create(**args)


def test_sample_shapes_and_interpolate_checks(solved: list[TimeJerkTrajectory]) -> None:
    traj = solved[0]
    assert traj.sample(1.0).shape == (3,)
    assert traj.sample(np.zeros((2, 5)), 3).shape == (2, 5, 3)
    assert traj.states(np.zeros(7)).shape == (7, 4, 3)
    np.testing.assert_allclose(traj.sample(-1.0), traj.sample(0.0))
    with pytest.raises(ValueError, match="derivative"):
        traj.sample(0.0, 4)
    with pytest.raises(ConfigurationError, match="piece durations"):
        interpolate(traj.problem, traj.piece_durations_s[:-1])
    with pytest.raises(ConfigurationError, match=r">= 0\.001 s"):
        interpolate(traj.problem, np.full(traj.n_pieces, 1e-4))


def test_an_infeasible_problem_is_an_error_not_a_trajectory() -> None:
    # Full speed at the start towards a waypoint right behind: it must stop within the limits.
    p = TimeJerkProblem.create(
        [[0.0], [-1e-3]], [1.0], [1.0], start_velocity_rad_s=[1.0], start_acceleration_rad_s2=[1.0]
    )
    with pytest.raises(PlanningError):
        plan(p)


# --- the CLI -------------------------------------------------------------------------------


def test_cli_json_coefficients_reproduce_the_waypoints(capsys: pytest.CaptureFixture[str]) -> None:
    wp = ["10,-60,-40", "40,-100,-90", "20,-40,-20"]
    assert main(["timejerk", "--waypoints-deg", *wp, "--w-jerk", "0.1", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["T_s"] == pytest.approx(sum(s["duration_s"] for s in r["segments"]))
    # Re-evaluate from the JSON alone: highest power first, time from the segment's start.
    ends = [np.polyval(c, 0.0) for c in r["segments"][0]["coefficients"]]
    np.testing.assert_allclose(np.degrees(ends), [10, -60, -40], atol=1e-9)
    pos = [[np.polyval(c, s["duration_s"]) for c in s["coefficients"]] for s in r["segments"]]
    hits = [
        np.degrees(pos[i]) for i, s in enumerate(r["segments"]) if s["to"].startswith("waypoint")
    ]
    np.testing.assert_allclose(hits, [[40, -100, -90], [20, -40, -20]], atol=1e-9)
    for pk in r["peaks"].values():
        assert pk["velocity_ratio"] <= 1 + 1e-9 and pk["acceleration_ratio"] <= 1 + 1e-9
    assert r["within_limits"] == {"exact": True, "resample_1khz": True}


def test_cli_text_on_a_rig_with_swing(capsys: pytest.CaptureFixture[str]) -> None:
    args = [
        "timejerk",
        "--rig",
        "field_excavator",
        "--waypoints-deg",
        "0,10,-60,-40",
        "90,20,-100,-30",
    ]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "T = " in out and "jerk integral" in out and "swing" in out and "peak |v| / V" in out


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--waypoints-deg", "10,-60,-40"], "at least two waypoints"),
        (["--waypoints-deg", "10,-60", "20,-50"], "3 joints"),
        (["--waypoints-deg", "10,-60,nan", "20,-50,-20"], "finite"),
        (["--waypoints-deg", "10,-60,x", "20,-50,-20"], "numbers in degrees"),
        (["--waypoints-deg", "10,-60,-40", "80,-50,-20"], "outside its range"),
        (["--waypoints-deg", "10,-60,-40", "10,-60,-40"], "same pose"),
        (["--waypoints-deg", "10,-60,-40", "20,-50,-20", "--w-jerk", "-1"], "--w-jerk"),
        (["--waypoints-deg", "10,-60,-40", "20,-50,-20", "--w-time", "0"], "--w-time"),
        (["--waypoints-deg", "10,-60,-40", "20,-50,-20", "--w-jerk", "nan"], "--w-jerk"),
        (["--rig", "field_excavator", "--waypoints-deg", "10,-60,-40", "20,-50,-20"], "4 joints"),
    ],
)
def test_cli_bad_input_is_a_clear_error(
    args: list[str], match: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["timejerk", *args]) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err


def test_cli_plot_without_matplotlib_says_so(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Any
) -> None:
    real_import = builtins.__import__

    def no_matplotlib(name: str, *args: Any, **kwargs: Any) -> Any:
        if name.startswith("matplotlib"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    args = [
        "timejerk",
        "--waypoints-deg",
        "10,-60,-40",
        "20,-50,-20",
        "--plot",
        str(tmp_path / "t.png"),
    ]
    assert main(args) == 2
    assert "matplotlib" in capsys.readouterr().err


# --- the benchmark -------------------------------------------------------------------------

BENCH_KEYS = {"problems", "solve_ms", "feasible", "gap_to_reference", "t_over_toppra"}


def test_bench_quick_keys_without_references(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "timejerk", "--quick", "--no-reference", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r) >= BENCH_KEYS
    assert r["problems"] == 8 and r["feasible"] == 1.0
    assert set(r["solve_ms"]) >= {"p50", "p99"}
    assert r["gap_to_reference"] is None and r["t_over_toppra"] is None


def test_bench_quick_with_references(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("casadi")
    pytest.importorskip("toppra")
    assert main(["bench", "timejerk", "--quick", "--problems", "4", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r) >= BENCH_KEYS
    assert set(r["gap_to_reference"]) >= {"p50", "max"} and set(r["t_over_toppra"]) >= {
        "p50",
        "max",
    }
    assert r["gap_to_reference"]["max"] <= 1e-3
    assert r["t_over_toppra"]["p50"] > 0.0
    assert r["reference"]["solve_ms"]["p50"] > 0.0


# --- jerk limits, shape knots, the reversal bound (issue 26, part 3) -----------------------------


def _shaped_problems() -> list[TimeJerkProblem]:
    """Seeded problems over every rig with its jerk limits, shape knots in some intervals (the
    dig cycles' use) and moving ends in one."""
    out = []
    for k, (rig_name, p) in enumerate(random_problems(8, seed=11, n_waypoints=5)):
        rig = load_rig(rig_name)
        joints = ((rig.swing.joint,) if rig.swing is not None else ()) + rig.joints
        ends = (
            {
                "start_velocity_rad_s": p.start_velocity_rad_s,
                "end_velocity_rad_s": p.end_velocity_rad_s,
                "start_acceleration_rad_s2": p.start_acceleration_rad_s2,
                "end_acceleration_rad_s2": p.end_acceleration_rad_s2,
            }
            if k == 3
            else {}
        )
        out.append(
            TimeJerkProblem.create(
                p.waypoints_rad,
                p.velocity_max_rad_s,
                p.acceleration_max_rad_s2,
                w_jerk=1e-3,
                jerk_max_rad_s3=[j.jerk_max_rad_s3 for j in joints],
                shape_knots=((0, 2, 2, 0), 1, (2, 0, 0, 1))[k % 3],
                **ends,
            )
        )
    return out


SHAPED = _shaped_problems()


@pytest.fixture(scope="module")
def shaped() -> list[TimeJerkTrajectory]:
    return [plan(p, max_iterations=150) for p in SHAPED]


@pytest.mark.parametrize("k", range(len(SHAPED)))
def test_shape_knots_keep_waypoints_continuity_and_every_limit(
    k: int, shaped: list[TimeJerkTrajectory]
) -> None:
    traj, p = shaped[k], SHAPED[k]
    case = _case(p) + f", shape_knots={p.shape_knots}"
    assert traj.n_pieces == p.waypoints_rad.shape[0] + 1 + sum(p.shape_knots)
    assert traj.shape_positions_rad.shape == (sum(p.shape_knots), p.n_joints)
    _assert_through_waypoints_and_continuous(traj, p, case)
    # The shape knots sit where the trajectory says.
    knots = traj.knots_s[list(p.shape_knot_indices)]
    np.testing.assert_allclose(traj.sample(knots), traj.shape_positions_rad, atol=1e-9)
    exact = traj.limit_check()
    assert exact.within_limits, case
    assert np.all(exact.jerk_ratio <= 1 + LIMIT_TOLERANCE), case
    assert traj.sampled_limit_check(1000.0).within_limits, case
    # Rebuilt from its durations and shape positions, the same trajectory.
    again = interpolate(p, traj.piece_durations_s, traj.shape_positions_rad)
    np.testing.assert_array_equal(again.coefficients, traj.coefficients)
    # Never worse than eq 3's pieces (the search starts from their optimum).
    base = plan(p.without_shape_knots())
    assert traj.objective <= base.objective * (1 + 1e-9), case


def test_the_search_with_shape_knots_starts_from_the_same_trajectory() -> None:
    from rt_runtime.trajectory.timejerk import _with_shape_knots

    p = SHAPED[0]
    base = plan(p.without_shape_knots())
    h, shape = _with_shape_knots(p, base)
    start = interpolate(p, h, shape)
    t = np.linspace(0.0, base.duration_s, 2001)
    for d in range(3):
        np.testing.assert_allclose(start.sample(t, d), base.sample(t, d), atol=1e-9)


@pytest.mark.parametrize("k", [0, 2, 3])
def test_gradients_with_jerk_limits_and_shape_knots_match_central_differences(k: int) -> None:
    from rt_runtime.trajectory.timejerk import _Evaluator, _Layout, _with_shape_knots

    base = SHAPED[k]
    p = TimeJerkProblem.create(
        base.waypoints_rad,
        base.velocity_max_rad_s,
        base.acceleration_max_rad_s2,
        w_jerk=0.01,
        jerk_max_rad_s3=base.jerk_max_rad_s3,
        shape_knots=base.shape_knots,
        start_velocity_rad_s=base.start_velocity_rad_s,
        end_velocity_rad_s=base.end_velocity_rad_s,
        start_acceleration_rad_s2=base.start_acceleration_rad_s2,
        end_acceleration_rad_s2=base.end_acceleration_rad_s2,
        position_min_rad=np.min(base.waypoints_rad, axis=0) - 0.05,
        position_max_rad=np.max(base.waypoints_rad, axis=0) + 0.05,
    )
    lay = _Layout(p)
    h, shape = _with_shape_knots(p, plan(p.without_shape_knots()))
    rng = np.random.default_rng(k)
    x = np.concatenate(
        [h * rng.uniform(0.7, 1.3, h.shape), (shape + rng.normal(0.0, 0.02, shape.shape)).ravel()]
    )

    def at(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        ev = _Evaluator(lay, 1.0, 1.0, positions=True)
        f, df = ev.fun(x)
        return f, df, ev.cons(x).copy(), ev.cons_jac(x).copy()

    _, df, _, dc = at(x)
    eps = 1e-7
    for i in range(x.shape[0]):
        up, down = x.copy(), x.copy()
        up[i] += eps
        down[i] -= eps
        (fu, _, cu, _), (fd, _, cd, _) = at(up), at(down)
        assert (fu - fd) / (2 * eps) == pytest.approx(df[i], rel=1e-5, abs=1e-7), i
        np.testing.assert_allclose((cu - cd) / (2 * eps), dc[:, i], rtol=1e-5, atol=1e-6)


def test_rest_to_rest_time_matches_ruckig() -> None:
    from ruckig import InputParameter, Ruckig, Trajectory

    from rt_runtime.trajectory.timejerk import rest_to_rest_time_s

    otg, inp, out = Ruckig(1), InputParameter(1), Trajectory(1)
    rng = np.random.default_rng(2)
    d = rng.uniform(0.0, 3.0, 400) * 10.0 ** rng.uniform(-4.0, 0.0, 400)
    v, a, j = rng.uniform(0.1, 2.0, 400), rng.uniform(0.1, 3.0, 400), rng.uniform(0.2, 10.0, 400)
    ours = rest_to_rest_time_s(d, v, a, j)
    for i in range(d.shape[0]):
        inp.current_position, inp.target_position = [0.0], [float(d[i])]
        inp.max_velocity, inp.max_acceleration = [float(v[i])], [float(a[i])]
        inp.max_jerk = [float(j[i])]
        otg.calculate(inp, out)
        case = (d[i], v[i], a[i], j[i])
        assert ours[i] == pytest.approx(out.duration, rel=1e-9, abs=1e-12), case
    assert rest_to_rest_time_s(0.0, 1.0, 1.0, 1.0) == 0.0


def test_the_reversal_bound_sums_the_runs_of_each_joint() -> None:
    from rt_runtime.trajectory.timejerk import rest_to_rest_time_s, reversal_bound_s

    v, a, j = np.array([1.0, 1.0]), np.array([1.0, 1.0]), np.array([10.0, 10.0])
    w = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.5], [1.5, 1.0], [1.5, 0.2]])

    def t(d: float) -> float:
        return float(rest_to_rest_time_s(d, 1.0, 1.0, 10.0))

    # Joint 0: up 2 (a step of zero joins), down 0.5; joint 1: up 1 (its zero step joins),
    # down 0.8. The slower joint.
    expect = max(t(2.0) + t(0.5), t(1.0) + t(0.8))
    assert float(reversal_bound_s(w, v, a, j)) == pytest.approx(expect)
    # Batched over leading axes; a joint that never moves takes no time.
    batch = np.stack([w, w[::-1]])
    assert reversal_bound_s(batch, v, a, j) == pytest.approx([expect, expect])
    still = np.array([[0.0, 0.0], [0.0, 1.0]])
    assert float(reversal_bound_s(still, v, a, j)) == pytest.approx(t(1.0))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"shape_knots": -1}, "shape_knots"),
        ({"shape_knots": (1, 2)}, "one per waypoint interval"),
        ({"shape_knots": 1.5}, "shape_knots"),
        ({"jerk_max_rad_s3": [1.0, 0.0]}, "jerk_max_rad_s3 must be > 0"),
    ],
)
def test_malformed_jerk_limits_and_shape_knots_are_refused(
    kwargs: dict[str, Any], match: str
) -> None:
    with pytest.raises(ConfigurationError, match=match):
        TimeJerkProblem.create([[0.0, 0.0], [1.0, 0.5]], [1.0, 1.0], [1.0, 1.0], **kwargs)
    p = TimeJerkProblem.create([[0.0, 0.0], [1.0, 0.5]], [1.0, 1.0], [1.0, 1.0], shape_knots=1)
    with pytest.raises(ConfigurationError, match="shape knots need"):
        interpolate(p, np.full(p.n_pieces, 0.5))
