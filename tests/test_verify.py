"""The one-shot verifier: C kernel and numpy backend against oneshot.evaluate, the reference."""

from __future__ import annotations

import dataclasses
import math
import types
import warnings

import numpy as np
import pytest

from rt_runtime import dynamics, kinematics
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import oneshot, verify
from rt_runtime.planning.oneshot import CONSTRAINT_NAMES, DigType
from rt_runtime.planning.verify import (
    COL_ENERGY_J,
    COL_OBJECTIVE,
    COL_PEAK_POWER_W,
    COL_PEAK_TORQUE_NM,
    COL_T_S,
    COL_THETA_P_RAD,
    COL_TOTAL,
    COL_VIOLATIONS,
    COL_VOLUME_M3,
    N_IN,
    N_OUT,
    N_RETIMED,
    PLAN_C_RANGE,
    PLAN_TOL,
    RETIME_RTOL,
    RT_A6,
    RT_T_S,
    TIME_DEPENDENT,
    Verifier,
    VerifyResult,
)
from rt_runtime.rig import Rig, load_rig
from rt_runtime.trajectory import sextic

RTOL = 1e-9
ATOL = 1e-12

SCALE = load_rig("scale_model")


def _variant(rig: Rig) -> Rig:
    """The scale model with every constant the kernel packs changed: catches hard-coded values."""
    assert rig.planning is not None
    boom, stick, bucket = (
        dataclasses.replace(
            lk,
            length_m=lk.length_m * f,
            mass_kg=lk.mass_kg * m,
            com_m=(lk.com_m[0] * 0.9, lk.com_m[1] + 0.01 * (i + 1)),
            inertia_kgm2=lk.inertia_kgm2 * (1.5 + i),
        )
        for i, (lk, f, m) in enumerate(
            zip(rig.links, (1.08, 0.93, 1.05), (1.7, 0.6, 2.3), strict=True)
        )
    )
    j_boom, j_stick, j_bucket = (
        dataclasses.replace(
            j,
            min_rad=j.min_rad - 0.05,
            max_rad=j.max_rad + 0.03 * (i + 1),
            velocity_max_rad_s=j.velocity_max_rad_s * (1.2 + 0.1 * i),
            acceleration_max_rad_s2=j.acceleration_max_rad_s2 * (1.3 + 0.2 * i),
            torque_max_nm=j.torque_max_nm * (0.4 - 0.05 * i),
        )
        for i, j in enumerate(rig.joints)
    )
    soil = dataclasses.replace(
        rig.soil, yao=dataclasses.replace(rig.soil.yao, k0_n_m2=7.3e4, mu=0.55)
    )
    planning = dataclasses.replace(
        rig.planning,
        t_min_s=4.0,
        t_max_s=11.0,
        volume_min_m3=0.8e-3,
        volume_max_m3=6.6e-3,
        energy_min_j=70.0,
        energy_max_j=450.0,
        power_max_w=300.0,
        weights=(0.6, 0.15, 0.25),
        theta_p_downward_rad=(math.radians(35.0), math.radians(85.0)),
        theta_p_backward_rad=(math.radians(-5.0), math.radians(45.0)),
    )
    return dataclasses.replace(
        rig,
        name="scale_model_variant",
        gravity_m_s2=9.7,
        links=(boom, stick, bucket),
        joints=(j_boom, j_stick, j_bucket),
        soil=soil,
        bucket=dataclasses.replace(rig.bucket, width_m=0.27),
        planning=planning,
    )


VARIANT = _variant(SCALE)
RIGS = {"scale_model": SCALE, "variant": VARIANT}


def _candidates(rig: Rig, n_problems: int, seed: int) -> np.ndarray:
    """Input rows: random particles in the search box on sampled problems of both dig types.

    Per problem five candidates: two on the sampled surface (the dig starts on it), one with
    the surface 3 cm lower (starts above it: entry on a later segment, or never), one 0.5 mm
    lower (above, but within the 1 mm that counts as a start on the surface) and one 2 cm
    higher (starts buried).
    """
    rng = np.random.default_rng(seed)
    lo, hi = oneshot.search_bounds(rig)
    rows = []
    for kind in DigType:
        for p in oneshot.sample_problems(rig, n_problems, kind, seed=seed + int(kind)):
            for shift in (0.0, 0.0, -0.03, -5e-4, 0.02):
                a6, T = oneshot.a6_from_particle(rng.uniform(lo, hi))
                rows.append(
                    verify.pack_inputs(
                        p.q_start_rad, p.q_end_rad, p.surface_y_m + shift, kind, a6, T
                    )[0]
                )
    return np.array(rows)


def _reference(rig: Rig, x: np.ndarray, n_samples: int) -> oneshot.Evaluation:
    """oneshot.evaluate on input rows, each its own problem with one candidate."""
    return oneshot.evaluate(
        rig,
        x[:, 0:3],
        x[:, 3:6],
        x[:, 6],
        x[:, 7].astype(int),
        x[:, None, 8:11],
        x[:, None, 11],
        n_samples,
    )


def _reference_rows(ev: oneshot.Evaluation) -> np.ndarray:
    n = ev.T_s.shape[0]
    out = np.empty((n, N_OUT))
    out[:, COL_VIOLATIONS : COL_VIOLATIONS + len(CONSTRAINT_NAMES)] = ev.violations[:, 0]
    out[:, COL_TOTAL] = ev.total_violation[:, 0]
    out[:, COL_OBJECTIVE] = ev.objective[:, 0]
    out[:, COL_T_S] = ev.T_s[:, 0]
    out[:, COL_VOLUME_M3] = ev.volume_m3[:, 0]
    out[:, COL_ENERGY_J] = ev.energy_j[:, 0]
    out[:, COL_THETA_P_RAD] = ev.theta_p_rad[:, 0]
    out[:, COL_PEAK_POWER_W] = ev.peak_power_w[:, 0]
    out[:, COL_PEAK_TORQUE_NM : COL_PEAK_TORQUE_NM + 3] = ev.peak_torque_nm[:, 0]
    return out


def _column_name(j: int) -> str:
    if j < len(CONSTRAINT_NAMES):
        return CONSTRAINT_NAMES[j]
    names = {
        COL_TOTAL: "total_violation",
        COL_OBJECTIVE: "objective",
        COL_T_S: "T_s",
        COL_VOLUME_M3: "volume_m3",
        COL_ENERGY_J: "energy_j",
        COL_THETA_P_RAD: "theta_p_rad",
        COL_PEAK_POWER_W: "peak_power_w",
    }
    return names.get(j, f"peak_torque_nm[{j - COL_PEAK_TORQUE_NM}]")


def _assert_rows_close(got: np.ndarray, want: np.ndarray, x: np.ndarray) -> None:
    """Every output within RTOL/ATOL; on failure name the worst row, column and its input."""
    err = np.abs(got - want) / (ATOL + RTOL * np.abs(want))
    if not np.all(err <= 1.0):
        i, j = np.unravel_index(int(np.argmax(np.where(np.isnan(err), np.inf, err))), err.shape)
        pytest.fail(
            f"{_column_name(int(j))} of row {i}: got {got[i, j]!r}, reference {want[i, j]!r}; "
            f"input row {x[i].tolist()!r}"
        )


@pytest.fixture(scope="module")
def c_verifiers() -> dict[str, Verifier]:
    # backend "c" raises when the kernel is not built: the product needs it, so that fails here.
    return {name: Verifier(rig, backend="c") for name, rig in RIGS.items()}


@pytest.mark.parametrize("rig_name", list(RIGS))
def test_c_kernel_equals_evaluate_on_random_candidates(
    rig_name: str, c_verifiers: dict[str, Verifier]
) -> None:
    rig = RIGS[rig_name]
    x = _candidates(rig, 25, seed=11)
    ev = _reference(rig, x, oneshot.DEFAULT_SAMPLES)
    out = np.full((x.shape[0], N_OUT), -7.0)
    c_verifiers[rig_name].evaluate_into(x, out)
    _assert_rows_close(out, _reference_rows(ev), x)
    np.testing.assert_array_equal(out[:, COL_TOTAL] <= 0.0, ev.feasible[:, 0])
    # The set must exercise what it claims to: every entry case and some feasible digs.
    theta_p = ev.theta_p_rad[:, 0]
    assert np.sum(theta_p == -0.5 * np.pi) >= 5, "no path that never enters"
    assert np.sum(x[:, 6] < kinematics.forward(rig, x[:, 0:3])[:, 1] - 1e-3) >= 40
    assert np.any(np.all(ev.violations[:, 0, 16:18] <= 0.0, axis=-1)), "no theta_p in range"


@pytest.mark.parametrize("rig_name", list(RIGS))
def test_feasibility_agrees_near_the_boundary(
    rig_name: str, c_verifiers: dict[str, Verifier]
) -> None:
    """Random candidates are rarely feasible: screen 2000 with the kernel, check the closest."""
    rig = RIGS[rig_name]
    x = _candidates(rig, 250, seed=21)
    out = np.empty((x.shape[0], N_OUT))
    c_verifiers[rig_name].evaluate_into(x, out)
    near = out[:, COL_TOTAL] <= 0.05
    ev = _reference(rig, x[near], oneshot.DEFAULT_SAMPLES)
    _assert_rows_close(out[near], _reference_rows(ev), x[near])
    np.testing.assert_array_equal(out[near, COL_TOTAL] <= 0.0, ev.feasible[:, 0])
    assert np.sum(ev.feasible) >= 3, "too few feasible candidates to test the flag"
    assert np.sum(~ev.feasible) >= 3


@pytest.mark.parametrize("n_samples", [3, 33, 64, 65])
def test_c_kernel_equals_evaluate_on_other_grids(n_samples: int) -> None:
    """Grids that end exactly on, just after, and before the kernel's 32-sample blocks."""
    x = _candidates(SCALE, 5, seed=5)
    out = np.empty((x.shape[0], N_OUT))
    Verifier(SCALE, n_samples, backend="c").evaluate_into(x, out)
    _assert_rows_close(out, _reference_rows(_reference(SCALE, x, n_samples)), x)


@pytest.fixture(scope="module")
def pso_plans() -> tuple[list[oneshot.Problem], list[oneshot.Solution]]:
    """Plans of the PSO teacher (small swarm) for two problems of each dig type."""
    problems = [
        *oneshot.sample_problems(SCALE, 2, DigType.DOWNWARD, seed=1),
        *oneshot.sample_problems(SCALE, 2, DigType.BACKWARD, seed=2),
    ]
    solutions = oneshot.solve_pso(SCALE, problems, n_particles=20, n_iterations=20, seed=0)
    return problems, solutions


def test_feasible_candidates_pass(
    pso_plans: tuple[list[oneshot.Problem], list[oneshot.Solution]],
) -> None:
    """Feasible plans from the PSO teacher come out feasible, with the reference's numbers."""
    problems, solutions = pso_plans
    verifier = Verifier(SCALE, backend="c")
    n_feasible = 0
    for p, sol in zip(problems, solutions, strict=True):
        res = verifier.check(
            p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type, sol.a6, sol.T_s
        )
        # Optima sit on constraint boundaries: the flag may differ where a margin is rounding.
        assert res.total_violation <= ATOL if sol.feasible else res.total_violation > 0.0
        assert res.objective == pytest.approx(sol.objective, rel=RTOL, abs=ATOL)
        n_feasible += sol.feasible
    assert n_feasible >= 1, "the PSO found no feasible plan: the test checks nothing"


def test_numpy_backend_is_evaluate() -> None:
    x = _candidates(SCALE, 4, seed=2)
    verifier = Verifier(SCALE, backend="numpy")
    assert verifier.backend == "numpy"
    out = np.empty((x.shape[0], N_OUT))
    verifier.evaluate_into(x, out)
    np.testing.assert_array_equal(out, _reference_rows(_reference(SCALE, x, 101)))


@pytest.mark.parametrize("backend", ["c", "numpy"])
def test_path_is_the_forward_kinematics_of_the_samples(backend: str) -> None:
    x = _candidates(SCALE, 3, seed=4)
    n = 57
    path = np.empty((x.shape[0], n, 2))
    out = np.empty((x.shape[0], N_OUT))
    Verifier(SCALE, n, backend=backend).evaluate_into(x, out, path)
    coeffs = sextic.sextic_coefficients(x[:, 0:3], x[:, 3:6], x[:, 8:11], x[:, 11])
    q = sextic.evaluate(coeffs, x[:, 11], n).q_rad
    np.testing.assert_allclose(path, kinematics.forward(SCALE, q)[..., :2], rtol=0, atol=1e-12)
    # At t = 0 the pose is q_start exactly, and its tip bit for bit what evaluate computes.
    pose, _ = kinematics.tip_state(SCALE, x[:, 0:3], np.zeros((x.shape[0], 3)))
    np.testing.assert_array_equal(path[:, 0], pose[:, :2])


def _bad_rows(x: np.ndarray) -> np.ndarray:
    """Rows evaluate refuses (or whose arithmetic overflows), each a copy of a valid row."""
    bad = []
    for col in range(N_IN):
        for value in (np.nan, np.inf, -np.inf):
            row = x[0].copy()
            row[col] = value
            bad.append(row)
    for col, value in ((11, 0.0), (11, -3.0), (7, 2.0), (7, 0.5), (11, 1e-300), (8, 1e300)):
        row = x[0].copy()
        row[col] = value
        bad.append(row)
    return np.array(bad)


@pytest.mark.parametrize("backend", ["c", "numpy"])
def test_bad_rows_are_rejected_without_touching_the_others(backend: str) -> None:
    x = _candidates(SCALE, 2, seed=3)
    bad = _bad_rows(x)
    mixed = np.concatenate([x[:3], bad, x[3:]])
    n = 41
    out = np.empty((mixed.shape[0], N_OUT))
    path = np.empty((mixed.shape[0], n, 2))
    verifier = Verifier(SCALE, n, backend=backend)
    verifier.evaluate_into(mixed, out, path)
    rejected = out[3 : 3 + len(bad)]
    assert np.all(rejected[:, COL_TOTAL] == np.inf), rejected[:, COL_TOTAL]
    # Rows refused before any arithmetic carry NaN everywhere else.
    assert np.all(np.isnan(np.delete(rejected[: 3 * N_IN + 4], COL_TOTAL, axis=1)))
    good = np.concatenate([out[:3], out[3 + len(bad) :]])
    alone = np.empty((x.shape[0], N_OUT))
    good_path = np.concatenate([path[:3], path[3 + len(bad) :]])
    alone_path = np.empty((x.shape[0], n, 2))
    verifier.evaluate_into(x, alone, alone_path)
    np.testing.assert_array_equal(good, alone)
    np.testing.assert_array_equal(good_path, alone_path)


def test_overflowing_row_is_rejected_as_by_evaluate() -> None:
    """Huge a6: finite input, overflowing arithmetic; evaluate's own total is inf or NaN."""
    x = _candidates(SCALE, 1, seed=9)[:1].copy()
    x[0, 8] = 1e300
    with np.errstate(all="ignore"):
        ev = _reference(SCALE, x, 101)
    assert not np.isfinite(ev.total_violation[0, 0])
    out = np.empty((1, N_OUT))
    Verifier(SCALE, backend="c").evaluate_into(x, out)
    assert out[0, COL_TOTAL] == np.inf


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"q_end_rad": (0.1, np.nan, 0.0)}, r"q_end_rad\[1\] is nan"),
        ({"a6": (np.inf, 0.0, 0.0)}, r"a6\[0\] is inf"),
        ({"surface_y_m": np.nan}, "surface_y_m"),
        ({"T_s": 0.0}, "T_s must be finite and > 0"),
        ({"T_s": np.inf}, "T_s must be finite and > 0"),
        ({"dig_type": 2}, "dig_type must be one of DOWNWARD"),
    ],
)
def test_check_raises_naming_the_bad_input(change: dict[str, object], message: str) -> None:
    p = oneshot.sample_problems(SCALE, 1, DigType.BACKWARD, seed=0)[0]
    args: dict[str, object] = {
        "q_start_rad": p.q_start_rad,
        "q_end_rad": p.q_end_rad,
        "surface_y_m": p.surface_y_m,
        "dig_type": p.dig_type,
        "a6": (1e-6, -2e-6, 0.0),
        "T_s": 7.0,
    }
    args.update(change)
    for backend in ("c", "numpy"):
        with pytest.raises(PlanningError, match=message):
            Verifier(SCALE, backend=backend).check(**args)  # type: ignore[arg-type]


def test_check_matches_evaluate_into() -> None:
    x = _candidates(SCALE, 1, seed=6)
    verifier = Verifier(SCALE, backend="c")
    out = np.empty((x.shape[0], N_OUT))
    verifier.evaluate_into(x, out)
    for row, o in zip(x, out, strict=True):
        res = verifier.check(row[0:3], row[3:6], row[6], DigType(int(row[7])), row[8:11], row[11])
        np.testing.assert_array_equal(res.violations, o[:22])
        np.testing.assert_array_equal(res.peak_torque_nm, o[COL_PEAK_TORQUE_NM:])
        assert (res.total_violation, res.objective, res.T_s) == tuple(o[22:25])
        assert (res.volume_m3, res.energy_j, res.theta_p_rad, res.peak_power_w) == tuple(o[25:29])
        assert res.feasible == (o[COL_TOTAL] <= 0.0)
        assert not res.violations.flags.writeable


def test_worst_names_the_largest_violation() -> None:
    row = np.zeros(N_OUT)
    row[:22] = -np.linspace(1.0, 0.1, 22)
    row[17] = 0.25
    row[3] = 0.2
    row[COL_TOTAL] = 0.45
    res = VerifyResult.from_row(row)
    assert res.worst() == ("theta_p_max", 0.25)
    assert not res.feasible
    row[:22] = -np.linspace(1.0, 0.1, 22)
    row[COL_TOTAL] = 0.0
    res = VerifyResult.from_row(row)
    name, value = res.worst()
    assert name == "time_max" and value == pytest.approx(-0.1)
    assert res.feasible
    row[5] = np.nan
    assert VerifyResult.from_row(row).worst()[0] == "angle_max_bucket"
    with pytest.raises(ValueError, match=r"shape \(32,\)"):
        VerifyResult.from_row(row[:-1])


@pytest.mark.parametrize("backend", ["c", "numpy"])
def test_wrong_arrays_raise_value_error(backend: str) -> None:
    v = Verifier(SCALE, 11, backend=backend)
    x = _candidates(SCALE, 1, seed=1)[:2].copy()
    out = np.empty((2, N_OUT))
    cases: list[tuple[np.ndarray, np.ndarray, np.ndarray | None, str]] = [
        (x[:, :11].copy(), out, None, r"inputs must have shape \(N, 12\)"),
        (x.astype(np.float32), out, None, "float64"),
        (np.repeat(x, 2, axis=1)[:, ::2], out, None, "C-contiguous"),
        (x, np.empty((2, N_OUT), dtype=np.float32), None, "float64"),
        (x, np.empty((3, N_OUT)), None, "same number of rows"),
        (x, out, np.empty((2, 12, 2)), r"path must have shape \(N, 11, 2\)"),
        (x, out, np.empty((1, 11, 2)), "same number of rows"),
    ]
    for inputs, o, path, message in cases:
        with pytest.raises(ValueError, match=message):
            v.evaluate_into(inputs, o, path)
    frozen = out.copy()
    frozen.setflags(write=False)
    with pytest.raises(ValueError, match="writable"):
        v.evaluate_into(x, frozen)


def test_backend_selection_and_configuration_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    assert Verifier(SCALE).backend == "c"  # built by pip install -e .
    assert Verifier(SCALE, backend="numpy").backend == "numpy"
    with pytest.raises(ConfigurationError, match="backend must be one of auto, c, numpy"):
        Verifier(SCALE, backend="fortran")
    with pytest.raises(ConfigurationError, match="n_samples must be >= 2"):
        Verifier(SCALE, 1)
    with pytest.raises(ConfigurationError, match="no \\[planning\\] table"):
        Verifier(dataclasses.replace(SCALE, planning=None))
    monkeypatch.setattr(verify, "_load_extension", lambda: None)
    assert Verifier(SCALE).backend == "numpy"
    with pytest.raises(ConfigurationError, match=r"pip install -e \."):
        Verifier(SCALE, backend="c")


def test_numpy_backend_evaluates_only() -> None:
    """Retiming and planning are the kernel's: the numpy backend refuses them, naming the
    build."""
    v = Verifier(SCALE, 11, backend="numpy")
    x = _candidates(SCALE, 1, seed=1)[:2].copy()
    out, rt = np.empty((2, N_OUT)), np.empty((2, N_RETIMED))
    with pytest.raises(ConfigurationError, match=r"retiming needs the C kernel; .*pip install"):
        v.retime_into(x, out, rt)
    with pytest.raises(ConfigurationError, match=r"planning .* needs the C kernel; .*pip install"):
        v.plan_into(x, out, rt)


def test_avx2_build_is_the_baseline_bit_for_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    # The AVX2 build of the same source must change the speed only: no FMA contraction and no
    # reassociation either way, so every output of every method is identical.
    fast = Verifier(SCALE)
    if fast.build != "avx2":
        pytest.skip("this CPU or compiler has no AVX2 build of the kernel")
    baseline = verify._load_extension(avx2=False)
    monkeypatch.setattr(verify, "_load_extension", lambda: baseline)
    slow = Verifier(SCALE)
    assert slow.build == "baseline"
    x = _candidates(SCALE, 30, seed=11)
    n, m = x.shape[0], oneshot.DEFAULT_SAMPLES
    results = []
    for v in (fast, slow):
        out, path = np.empty((n, N_OUT)), np.empty((n, m, 2))
        v.evaluate_into(x, out, path)
        rt_out, rt = np.empty((n, N_OUT)), np.empty((n, 4))
        v.retime_into(x, rt_out, rt)
        pl_out, pl, sc = np.empty((n, N_OUT)), np.empty((n, 4)), np.empty(n)
        v.plan_into(x, pl_out, pl, path=None, scale=sc)
        results.append((out, path, rt_out, rt, pl_out, pl, sc))
    for a, b in zip(*results, strict=True):
        assert np.array_equal(a, b, equal_nan=True)


# ------------------------------------------------------------------------------------------
# Retiming: the shortest feasible T along a kept path.
# ------------------------------------------------------------------------------------------

# The scale model with a 100 W power limit: power then binds on some random candidates, which
# takes the kernel's search (scan and Illinois) instead of its closed forms.
def _power_limited(rig: Rig) -> Rig:
    assert rig.planning is not None
    planning = dataclasses.replace(rig.planning, power_max_w=100.0)
    return dataclasses.replace(rig, name=f"{rig.name}_100W", planning=planning)


POWER_LIMITED = _power_limited(SCALE)
RETIME_RIGS = {**RIGS, "power_limited": POWER_LIMITED}
TD = list(TIME_DEPENDENT)


def _shape_terms(x: np.ndarray) -> np.ndarray:
    """K = -a6 T^6 of input rows (oneshot.particle_from_a6), the path a retiming keeps."""
    return np.asarray(-x[:, 8:11] * x[:, 11, None] ** 6)


def _at_time(x: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Input rows ``x`` moved to durations ``T`` along their own paths."""
    y = x.copy()
    y[:, 8:11] = -_shape_terms(x) / np.asarray(T)[:, None] ** 6
    y[:, 11] = T
    return y


def _retime(verifier: Verifier, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    out = np.full((x.shape[0], N_OUT), -7.0)
    retimed = np.full((x.shape[0], N_RETIMED), -7.0)
    verifier.retime_into(x, out, retimed)
    return out, retimed


def _time_ok(out: np.ndarray) -> np.ndarray:
    """Whether the time-dependent constraints of output rows hold."""
    return np.asarray(np.all(out[:, TD] <= 0.0, axis=1))


def _time_violation(out: np.ndarray) -> np.ndarray:
    return np.asarray(np.sum(np.maximum(out[:, TD], 0.0), axis=1))


def _reference_out(rig: Rig, x: np.ndarray, n_samples: int = oneshot.DEFAULT_SAMPLES) -> np.ndarray:
    """Output rows of input rows by oneshot.evaluate (the numpy backend: the reference)."""
    out = np.empty((x.shape[0], N_OUT))
    Verifier(rig, n_samples, backend="numpy").evaluate_into(x, out)
    return out


def _row_case(x: np.ndarray, i: int, **values: object) -> str:
    """A failing row as the message shows it: the values named, then the input row."""
    said = ", ".join(f"{k} {v!r}" for k, v in values.items())
    return f"{said}; input row {x[i].tolist()!r}"


@pytest.fixture(scope="module")
def retime_verifiers() -> dict[str, Verifier]:
    """The C verifier per retiming rig."""
    return {name: Verifier(rig, backend="c") for name, rig in RETIME_RIGS.items()}


@pytest.mark.parametrize("rig_name", list(RETIME_RIGS))
def test_retime_holds_every_time_limit_by_the_reference(
    rig_name: str, retime_verifiers: dict[str, Verifier]
) -> None:
    """On seeded random candidates: T' in [t_min, t_max]; out is the kernel's evaluation of the
    retimed row bit for bit, and oneshot.evaluate of it agrees (every limit at every sample:
    the same feasibility, values to 1e-7); never worse than the start (feasible and no longer
    where the row's own T is feasible; no more violated than at t_max); where no T' was found,
    none of 64 durations over the range is feasible by oneshot.evaluate either."""
    rig = RETIME_RIGS[rig_name]
    assert rig.planning is not None
    t_min, t_max = rig.planning.t_min_s, rig.planning.t_max_s
    verifier = retime_verifiers[rig_name]
    every = _candidates(rig, 25, seed=31)
    out_all, rt_all = _retime(verifier, every)
    # The first 30 rows and every row where power binds at T' (the searched case).
    power_binds = _time_ok(out_all) & (out_all[:, 15] > -1e-6)
    pick = np.flatnonzero(power_binds | (np.arange(every.shape[0]) < 30))
    x, out, rt = every[pick], out_all[pick], rt_all[pick]
    t_new = rt[:, RT_T_S]
    for i in np.flatnonzero(~((t_new >= t_min) & (t_new <= t_max))):
        pytest.fail(f"T' out of range: {_row_case(x, i, T=t_new[i])}")
    y = _planned_rows(x, rt)  # the retimed rows: a6' and T'
    again = np.empty_like(out)
    verifier.evaluate_into(y, again)
    np.testing.assert_array_equal(out, again)
    ref = _reference_out(rig, y)
    ok, ok_ref = _time_ok(out), _time_ok(ref)
    for i in np.flatnonzero(ok != ok_ref):
        pytest.fail(f"time feasible: kernel {ok[i]}, oneshot.evaluate {ok_ref[i]}: "
                    f"{_row_case(x, i, T=t_new[i])}")
    np.testing.assert_array_equal(out[:, COL_TOTAL] <= 0.0, ref[:, COL_TOTAL] <= 0.0)
    np.testing.assert_allclose(out[ok], ref[ok], rtol=1e-7, atol=1e-8)
    # Never worse than the start: where the row's own T is feasible, T' is feasible and no
    # longer; where nothing is, the violation is no worse than at t_max.
    own_ok = _time_ok(_reference_out(rig, x)) & (x[:, 11] >= t_min) & (x[:, 11] <= t_max)
    for i in np.flatnonzero(own_ok & ~(ok & (t_new <= x[:, 11] * (1.0 + RETIME_RTOL)))):
        pytest.fail(f"the row's own T works, T' is worse: {_row_case(x, i, T=t_new[i])}")
    at_t_max = _time_violation(_reference_out(rig, _at_time(x, np.full(x.shape[0], t_max))))
    for i in np.flatnonzero(_time_violation(ref) > at_t_max + 1e-9):
        pytest.fail(f"the time violation at T' exceeds that at t_max ({at_t_max[i]!r}): "
                    f"{_row_case(x, i, T=t_new[i])}")
    grid = t_min * (t_max / t_min) ** np.linspace(0.0, 1.0, 64)
    missed = np.flatnonzero(~ok)
    tried = np.concatenate([_at_time(x[missed], np.full(missed.size, g)) for g in grid])
    feasible = _time_ok(_reference_out(rig, tried)).reshape(grid.size, missed.size)
    for k in np.flatnonzero(np.any(feasible, axis=0)):
        g = grid[np.argmax(feasible[:, k])]
        i = missed[k]
        pytest.fail(f"no T' found, but T {g!r} is feasible: {_row_case(x, i, T=t_new[i])}")
    # The set exercises what it claims to.
    assert np.sum(ok) >= 10 and np.sum(~ok) >= 3
    assert np.any(t_new < x[:, 11]) and np.any(t_new > x[:, 11])
    if rig_name == "power_limited":
        assert np.sum(power_binds) >= 5, "power never binds: the search goes untested"


@pytest.mark.parametrize("rig_name", list(RETIME_RIGS))
def test_retime_is_minimal(rig_name: str, retime_verifiers: dict[str, Verifier]) -> None:
    """At T' (1 - 2 RETIME_RTOL) some time-dependent constraint fails by oneshot.evaluate (the
    independent reference), unless T' = t_min."""
    rig = RETIME_RIGS[rig_name]
    assert rig.planning is not None
    verifier = retime_verifiers[rig_name]
    x = _candidates(rig, 50, seed=41)
    out, rt = _retime(verifier, x)
    found = _time_ok(out)
    above = found & (rt[:, RT_T_S] > rig.planning.t_min_s)
    assert np.sum(above) >= 100
    if rig_name == "scale_model":
        assert np.sum(found & ~above) >= 2, "no row retimed to t_min"
    y = _at_time(x[above], rt[above, RT_T_S] * (1.0 - 2.0 * RETIME_RTOL))
    faster = _reference_out(rig, y)
    for i in np.flatnonzero(_time_ok(faster)):
        pytest.fail(f"feasible below T': {_row_case(x[above], i, T=rt[above][i, 3])}")
    np.testing.assert_array_equal(rt[found & ~above, RT_T_S], rig.planning.t_min_s)


def test_retime_keeps_the_path() -> None:
    """K, the sampled path and every path-only output are those of the input row."""
    x = _candidates(SCALE, 3, seed=51)
    n = 41
    verifier = Verifier(SCALE, n, backend="c")
    out, before = np.empty((x.shape[0], N_OUT)), np.empty((x.shape[0], N_OUT))
    rt = np.empty((x.shape[0], N_RETIMED))
    path, path_before = np.empty((x.shape[0], n, 2)), np.empty((x.shape[0], n, 2))
    verifier.retime_into(x, out, rt, path)
    verifier.evaluate_into(x, before, path_before)
    assert np.any(np.abs(rt[:, RT_T_S] / x[:, 11] - 1.0) > 0.05), "nothing was retimed"
    K_new = -rt[:, RT_A6 : RT_A6 + 3] * rt[:, RT_T_S, None] ** 6
    np.testing.assert_allclose(K_new, _shape_terms(x), rtol=1e-14, atol=1e-300)
    np.testing.assert_allclose(path, path_before, rtol=0.0, atol=1e-12)
    path_only = [*range(6), 16, 17, 18, 19, COL_VOLUME_M3, COL_THETA_P_RAD]
    np.testing.assert_allclose(out[:, path_only], before[:, path_only], rtol=1e-9, atol=1e-12)


def test_retime_where_nothing_works() -> None:
    """Rows no T in range makes feasible: T' is the least violating, the violation reported."""
    assert SCALE.planning is not None
    t_max = SCALE.planning.t_max_s
    x = _candidates(SCALE, 2, seed=61)
    # A bulge too large for the acceleration limit at any T in range: least violated at t_max.
    fast = _at_time(x, np.full(x.shape[0], 7.0))
    fast[:, 8:11] *= 40.0
    # Torque limits below what gravity alone needs: violated at every T.
    weak = dataclasses.replace(
        SCALE,
        joints=tuple(dataclasses.replace(j, torque_max_nm=1.0) for j in SCALE.joints),
    )
    for rig, rows in ((SCALE, fast), (weak, x)):
        verifier = Verifier(rig, backend="c")
        out, rt = _retime(verifier, rows)
        assert np.all(~_time_ok(out)) and np.all(out[:, COL_TOTAL] > 0.0)
        assert np.all((rt[:, RT_T_S] >= SCALE.planning.t_min_s) & (rt[:, RT_T_S] <= t_max))
        at_t_max = np.empty_like(out)
        verifier.evaluate_into(_at_time(rows, np.full(rows.shape[0], t_max)), at_t_max)
        assert np.all(_time_violation(out) <= _time_violation(at_t_max) + 1e-9)
        if rig is SCALE:
            np.testing.assert_array_equal(rt[:, RT_T_S], t_max)


def test_retime_finds_a_feasible_interval_closed_from_above() -> None:
    """A torque limit the dynamics helps to meet: feasible only from the acceleration bound to
    a little above it (narrower than the numpy reference's grid step)."""
    assert SCALE.planning is not None
    t_min, t_max = SCALE.planning.t_min_s, SCALE.planning.t_max_s
    x = _candidates(SCALE, 5, seed=71)
    c_verifier = Verifier(SCALE, backend="c")
    out, rt = _retime(c_verifier, x)
    at_t_max = np.empty_like(out)
    c_verifier.evaluate_into(_at_time(x, np.full(x.shape[0], t_max)), at_t_max)
    torque = slice(COL_PEAK_TORQUE_NM, COL_PEAK_TORQUE_NM + 3)
    growth = at_t_max[:, torque] / out[:, torque] - 1.0
    growth[~(_time_ok(out) & (rt[:, RT_T_S] > t_min))] = -1.0
    i, j = np.unravel_index(int(np.argmax(growth)), growth.shape)
    assert growth[i, j] > 0.01, "no peak torque that grows with T"
    joints = list(SCALE.joints)
    joints[j] = dataclasses.replace(
        joints[j], torque_max_nm=float(out[i, COL_PEAK_TORQUE_NM + j]) * (1.0 + 1e-5)
    )
    rig = dataclasses.replace(SCALE, joints=tuple(joints))
    verifier = Verifier(rig, backend="c")
    row = x[i : i + 1]
    out_new, rt_new = _retime(verifier, row)
    assert _time_ok(out_new)[0]
    assert rt_new[0, RT_T_S] == pytest.approx(rt[i, RT_T_S], rel=RETIME_RTOL)
    later = np.empty_like(out_new)
    verifier.evaluate_into(_at_time(row, rt_new[:, RT_T_S] * 1.01), later)
    assert later[0, 12 + j] > 0.0, "the interval is not closed from above"


def test_retime_of_pso_plans(
    pso_plans: tuple[list[oneshot.Problem], list[oneshot.Solution]],
) -> None:
    """A PSO optimum retimes to T' <= T and no worse an objective; slowed down, it comes back."""
    problems, solutions = pso_plans
    c_verifier = Verifier(SCALE, backend="c")
    rows = []
    for p, sol in zip(problems, solutions, strict=True):
        row = verify.pack_inputs(p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type,
                                 sol.a6, sol.T_s)
        rows += [row, _at_time(row, np.array([min(1.3 * sol.T_s, 10.0)]))]
    x = np.concatenate(rows)
    out, rt = _retime(c_verifier, x)
    n_feasible = 0
    for k, sol in enumerate(solutions):
        if not sol.feasible:
            continue
        n_feasible += 1
        for i in (2 * k, 2 * k + 1):
            res = VerifyResult.from_row(out[i])
            assert rt[i, RT_T_S] <= sol.T_s * (1.0 + RETIME_RTOL), (k, rt[i, RT_T_S], sol.T_s)
            assert res.objective <= sol.objective + 1e-9, (k, res.objective, sol.objective)
            assert _time_ok(out[i : i + 1])[0]
            assert res.total_violation <= 1e-9  # path-only margins of an optimum are rounding
        assert rt[2 * k + 1, RT_T_S] == pytest.approx(rt[2 * k, RT_T_S], rel=RETIME_RTOL)
    assert n_feasible >= 2, "the PSO found too few feasible plans: the test checks little"


def test_retime_rejects_bad_rows_without_touching_the_others() -> None:
    x = _candidates(SCALE, 2, seed=3)
    bad = _bad_rows(x)
    # Two of them are valid paths: T = 1e-300 (K = -a6 T^6 rounds to 0: the quintic) and
    # a6 = 1e300 (K ~ 1e305, finite, whose evaluation overflows); checked below.
    special = (bad[:, 11] == 1e-300) | (bad[:, 8] == 1e300)
    assert np.sum(special) == 2
    bad = bad[~special]
    mixed = np.concatenate([x[:3], bad, x[3:]])
    n = 21
    verifier = Verifier(SCALE, n, backend="c")
    out = np.empty((mixed.shape[0], N_OUT))
    rt = np.empty((mixed.shape[0], N_RETIMED))
    path = np.empty((mixed.shape[0], n, 2))
    verifier.retime_into(mixed, out, rt, path)
    rejected = slice(3, 3 + len(bad))
    assert np.all(out[rejected, COL_TOTAL] == np.inf)
    assert np.all(np.isnan(np.delete(out[rejected], COL_TOTAL, axis=1)))
    assert np.all(np.isnan(rt[rejected])) and np.all(np.isnan(path[rejected]))
    alone = np.empty((x.shape[0], N_OUT))
    alone_rt = np.empty((x.shape[0], N_RETIMED))
    alone_path = np.empty((x.shape[0], n, 2))
    verifier.retime_into(x, alone, alone_rt, alone_path)
    keep = np.r_[0:3, 3 + len(bad) : mixed.shape[0]]
    np.testing.assert_array_equal(out[keep], alone)
    np.testing.assert_array_equal(rt[keep], alone_rt)
    np.testing.assert_array_equal(path[keep], alone_path)
    quintic, huge = x[:1].copy(), x[:1].copy()
    quintic[0, 11] = 1e-300
    huge[0, 8] = 1e300
    q_out, q_rt = _retime(verifier, quintic)
    assert np.all(np.isfinite(q_rt)) and np.all(q_rt[0, :3] == 0.0)
    assert np.isfinite(q_out[0, COL_TOTAL])
    assert SCALE.planning is not None
    h_out, h_rt = _retime(verifier, huge)
    assert h_out[0, COL_TOTAL] == np.inf and h_rt[0, RT_T_S] == SCALE.planning.t_max_s


def test_retime_convenience_matches_retime_into() -> None:
    x = _candidates(SCALE, 1, seed=7)[:4]
    verifier = Verifier(SCALE, backend="c")
    out, rt = _retime(verifier, x)
    for row, o, r in zip(x, out, rt, strict=True):
        a6, T, res = verifier.retime(row[0:3], row[3:6], row[6], DigType(int(row[7])),
                                     row[8:11], row[11])
        np.testing.assert_array_equal(a6, r[:3])
        assert T == r[3] == res.T_s
        np.testing.assert_array_equal(res.violations, o[:22])
        assert res.total_violation == o[COL_TOTAL]
    with pytest.raises(PlanningError, match="T_s must be finite and > 0"):
        verifier.retime(x[0, 0:3], x[0, 3:6], x[0, 6], 0, x[0, 8:11], 0.0)
    with pytest.raises(PlanningError, match="dig_type must be one of"):
        verifier.retime(x[0, 0:3], x[0, 3:6], x[0, 6], 3, x[0, 8:11], 6.0)


def test_retime_wrong_arrays_raise_value_error() -> None:
    v = Verifier(SCALE, 11, backend="c")
    x = _candidates(SCALE, 1, seed=1)[:2].copy()
    out = np.empty((2, N_OUT))
    rt = np.empty((2, N_RETIMED))
    cases: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, str]] = [
        (x[:, :11].copy(), out, rt, None, r"inputs must have shape \(N, 12\)"),
        (x, out, np.empty((2, 3)), None, r"retimed must have shape \(N, 4\)"),
        (x, out, np.empty((2, 4), dtype=np.float32), None, "float64"),
        (x, out, np.empty((3, 4)), None, "same number of rows"),
        (x, np.empty((1, N_OUT)), rt, None, "same number of rows"),
        (x, out, rt, np.empty((2, 12, 2)), r"path must have shape \(N, 11, 2\)"),
    ]
    for inputs, o, r, path, message in cases:
        with pytest.raises(ValueError, match=message):
            v.retime_into(inputs, o, r, path)
    frozen = rt.copy()
    frozen.setflags(write=False)
    with pytest.raises(ValueError, match="writable"):
        v.retime_into(x, out, frozen)


# -- plan: the volume-filling path scale, then retiming ----------------------------------------

PATH_ONLY = [*range(6), 16, 17, 18, 19]
assert SCALE.planning is not None
V_MAX = SCALE.planning.volume_max_m3
V_SPAN = V_MAX - SCALE.planning.volume_min_m3

# Bulge factors per joint of the teacher's plan: what an imprecise network gives. Uneven, so
# that no scale recovers the teacher's optimum exactly (it often sits on two boundaries at
# once, theta_p and torque, and is then the only feasible point of its family).
_NET_FACTORS = (
    (0.86, 0.8, 0.83),
    (0.62, 0.91, 0.77),
    (1.0, 1.0, 1.0),
    (1.27, 1.19, 1.23),
    (0.91, 0.63, 1.07),
    (0.71, 0.76, 0.66),
)


def _plan(
    verifier: Verifier,
    x: np.ndarray,
    c_range: tuple[float, float] = PLAN_C_RANGE,
    path: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    out = np.full((x.shape[0], N_OUT), -7.0)
    planned = np.full((x.shape[0], N_RETIMED), -7.0)
    scale = np.full(x.shape[0], -7.0)
    verifier.plan_into(x, out, planned, c_range, path, scale)
    return out, planned, scale


def _scaled(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Input rows with their bulge K scaled by ``c``."""
    y = x.copy()
    y[:, 8:11] *= np.asarray(c)[:, None]
    return y


def _path_violation(verifier: Verifier, x: np.ndarray) -> np.ndarray:
    """Worst path-only constraint value (joint limits, theta_p, volume) of input rows."""
    out = np.empty((x.shape[0], N_OUT))
    verifier.evaluate_into(x, out)
    return np.asarray(np.max(out[:, PATH_ONLY], axis=1))


def _planned_rows(x: np.ndarray, planned: np.ndarray) -> np.ndarray:
    y = x.copy()
    y[:, 8:11] = planned[:, RT_A6 : RT_A6 + 3]
    y[:, 11] = planned[:, RT_T_S]
    return y


@pytest.fixture(scope="module")
def plan_set() -> dict[str, tuple[np.ndarray, ...]]:
    """Network-like rows (teacher plans of four problems per dig type with their bulge scaled
    unevenly and T 10 % longer), planned and retimed on their own paths."""
    assert SCALE.planning is not None
    problems = [
        *oneshot.sample_problems(SCALE, 4, DigType.DOWNWARD, seed=1),
        *oneshot.sample_problems(SCALE, 4, DigType.BACKWARD, seed=2),
    ]
    solutions = oneshot.solve_pso(SCALE, problems, n_particles=20, n_iterations=20, seed=0)
    rows = []
    for p, sol in zip(problems, solutions, strict=True):
        K = -np.asarray(sol.a6) * sol.T_s**6
        T = min(1.1 * sol.T_s, SCALE.planning.t_max_s)
        for f in _NET_FACTORS:
            a6 = -(K * np.array(f)) / T**6
            rows.append(
                verify.pack_inputs(p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type, a6, T)[0]
            )
    x = np.array(rows)
    c_verifier = Verifier(SCALE, backend="c")
    own = _retime(c_verifier, x)
    return {
        "x": (x,),
        "c": _plan(c_verifier, x),
        "own": own,
    }


def test_plan_holds_every_limit_by_the_reference(
    plan_set: dict[str, tuple[np.ndarray, ...]],
) -> None:
    """out is the kernel's evaluation of planned bit for bit, and oneshot.evaluate of it agrees
    (every limit at every sample: the same feasibility, values to 1e-7); the scale stays in
    range; a feasible plan is the largest scale that works: where the volume cap binds, V_p
    within PLAN_TOL below it, else a bulge 0.3 % larger breaks a path limit or no longer
    retimes feasibly (both judged by oneshot.evaluate); where no plan is found, neither any of
    25 scales over the range, each retimed."""
    (x,) = plan_set["x"]
    out, pl, sc = plan_set["c"]
    verifier = Verifier(SCALE, backend="c")
    y = _planned_rows(x, pl)
    again = np.empty_like(out)
    verifier.evaluate_into(y, again)
    np.testing.assert_array_equal(out, again)
    ref = _reference_out(SCALE, y)
    ok = out[:, COL_TOTAL] <= 0.0
    for i in np.flatnonzero(ok != (ref[:, COL_TOTAL] <= 0.0)):
        pytest.fail(f"feasible: kernel {ok[i]}, oneshot.evaluate {not ok[i]}: "
                    f"{_row_case(x, i, c=sc[i], T=pl[i, RT_T_S])}")
    np.testing.assert_allclose(out[ok], ref[ok], rtol=1e-7, atol=1e-8)
    assert np.all((sc >= PLAN_C_RANGE[0]) & (sc <= PLAN_C_RANGE[1]))
    vol = out[:, COL_VOLUME_M3]
    capped = ok & (vol >= V_MAX - PLAN_TOL * V_SPAN)
    assert np.all(vol[ok] <= V_MAX)
    # Below the cap: a slightly larger bulge fails a path limit, or its retiming (by the
    # reference) a time limit.
    below = np.flatnonzero(ok & ~capped & (sc < PLAN_C_RANGE[1]))
    larger = _scaled(x[below], sc[below] * 1.003)
    path_bad = np.max(_reference_out(SCALE, larger)[:, PATH_ONLY], axis=1) > 0.0
    _, rt_larger = _retime(verifier, larger)
    time_bad = _reference_out(SCALE, _planned_rows(larger, rt_larger))[:, COL_TOTAL] > 0.0
    for k in np.flatnonzero(~(path_bad | time_bad)):
        i = below[k]
        pytest.fail(f"a 0.3 % larger bulge also works: {_row_case(x, i, c=sc[i], V=vol[i])}")
    # Nothing found: no scale of a 25-point grid retimes feasibly either.
    failed = np.flatnonzero(~ok)
    grid = np.linspace(*PLAN_C_RANGE, 25)
    tried = np.concatenate([_scaled(x[failed], np.full(failed.size, c)) for c in grid])
    _, rt_tried = _retime(verifier, tried)
    works = _reference_out(SCALE, _planned_rows(tried, rt_tried))[:, COL_TOTAL] <= 0.0
    works = works.reshape(grid.size, failed.size)
    for k in np.flatnonzero(np.any(works, axis=0)):
        c = grid[np.argmax(works[:, k])]
        pytest.fail(f"no plan found, but c {c!r} retimes feasibly: {_row_case(x, failed[k])}")
    # The set exercises what it claims to: capped rows, back-off rows (feasible below the cap
    # with path slack: a time-dependent limit decided), rows below and above c = 1, failures.
    slack = _path_violation(verifier, _scaled(x, sc * 1.002)) < 0.0
    backed_off = ok & (vol < V_MAX - 0.01 * V_SPAN) & slack & (sc != 1.0)
    assert np.sum(capped & (sc != 1.0)) >= 15 and np.sum(backed_off) >= 3
    assert np.sum(~ok) >= 2
    assert np.sum(ok & (sc < 1.0)) >= 5 and np.sum(ok & (sc > 1.0)) >= 5


def test_plan_backs_off_to_the_boundary(plan_set: dict[str, tuple[np.ndarray, ...]]) -> None:
    """Where the retime of c* fails on a time-dependent limit, the back-off lands within 1e-3
    in c of where the retiming stops finding a time: a bulge 0.3 % larger cannot be timed, by
    oneshot.evaluate of its retiming."""
    (x,) = plan_set["x"]
    out_c, _, sc_c = plan_set["c"]
    verifier = Verifier(SCALE, backend="c")
    ok = out_c[:, COL_TOTAL] <= 0.0
    slack = _path_violation(verifier, _scaled(x, sc_c * 1.003)) < 0.0
    backed_off = (ok & (out_c[:, COL_VOLUME_M3] < V_MAX - 0.01 * V_SPAN) & slack
                  & (sc_c != 1.0) & (sc_c < PLAN_C_RANGE[1]))
    assert np.sum(backed_off) >= 5
    larger = _scaled(x[backed_off], sc_c[backed_off] * 1.003)
    _, rt = _retime(verifier, larger)
    beyond = _reference_out(SCALE, _planned_rows(larger, rt))
    for k in np.flatnonzero(beyond[:, COL_TOTAL] <= 0.0):
        i = np.flatnonzero(backed_off)[k]
        pytest.fail(f"the back-off stopped short of the boundary: {_row_case(x, i, c=sc_c[i])}")


# A network answer (a candidate model's, held-out problem) whose retimed T rises from 6.5 s to
# 9.8 s over the last 0.3 % of c before the retiming stops finding a time: a torque bound
# pushes T above the acceleration bound there.
_STEEP_T_ROW = (
    0.12159470704598468, -0.9065310971238985, -1.0918591192622462, -0.06322975502906886,
    -0.764982117491176, -2.085584627217118, -0.36739476123660764, 0.0,
    0.00011385644029360265, 0.0002175837435061112, 5.189147486817092e-05, 6.665980815887451,
)


def test_plan_back_off_avoids_a_steeply_rising_time() -> None:
    """The back-off's largest c would take T = 9.8 s (objective ~0.96); where a torque bound has
    raised T like that, the scale where it started rising is tried too and the better one in T
    and V_p kept (objective ~0.63)."""
    x = np.array([_STEEP_T_ROW])
    out, _, scale = _plan(Verifier(SCALE, backend="c"), x)
    assert out[0, COL_TOTAL] <= 0.0
    assert out[0, COL_T_S] < 7.0 and out[0, COL_OBJECTIVE] < 0.64, (scale[0], out[0, COL_T_S])
    # The largest c whose retiming finds a time lies above it, at a far longer T.
    verifier = Verifier(SCALE, backend="c")
    beyond, _ = _retime(verifier, _scaled(x, np.array([1.0401])))
    assert beyond[0, COL_TOTAL] <= 0.0 and beyond[0, COL_T_S] > 9.0


def test_plan_batch_equals_single_rows(plan_set: dict[str, tuple[np.ndarray, ...]]) -> None:
    """The kernel's per-row scratch carries nothing from one row to the next: each row of the
    plan set (capped, backed-off and failed rows) planned alone gives the batch's bits."""
    (x,) = plan_set["x"]
    verifier = Verifier(SCALE, backend="c")
    got = [np.empty((x.shape[0], N_OUT)), np.empty((x.shape[0], N_RETIMED)),
           np.empty(x.shape[0])]
    for i in range(x.shape[0]):
        verifier.plan_into(x[i : i + 1], got[0][i : i + 1], got[1][i : i + 1], PLAN_C_RANGE,
                           None, got[2][i : i + 1])
    for g, want in zip(got, plan_set["c"], strict=True):
        np.testing.assert_array_equal(g, want)


def test_plan_is_never_worse_than_retiming_the_own_path(
    plan_set: dict[str, tuple[np.ndarray, ...]],
) -> None:
    """Where the own path retimes feasibly, the plan is feasible with at least its volume. Its
    objective could still be worse (the largest volume is chosen, and a bigger bulge takes more
    time and energy; none of 300 such rows of a validation set was), but only by buying
    volume."""
    out_own, _ = plan_set["own"]
    out, _, _ = plan_set["c"]
    ok_own, ok = out_own[:, COL_TOTAL] <= 0.0, out[:, COL_TOTAL] <= 0.0
    assert np.all(ok[ok_own])
    both = ok & ok_own
    vol, vol_own = out[both, COL_VOLUME_M3], out_own[both, COL_VOLUME_M3]
    np.testing.assert_array_less(vol_own - vol, PLAN_TOL * V_SPAN)
    worse = out[both, COL_OBJECTIVE] > out_own[both, COL_OBJECTIVE]
    assert np.all(vol[worse] > vol_own[worse]), "a worse objective must buy volume"
    assert np.sum(ok & ~ok_own) >= 10, "the plan rescues too few rows to test much"


def test_plan_fills_the_volume_cap(plan_set: dict[str, tuple[np.ndarray, ...]]) -> None:
    """With torque and power limits out of reach (retiming then meets every time-dependent
    limit), c* is the largest path-feasible scale: V_p within PLAN_TOL of the cap (or another
    path constraint at its limit), and a slightly larger bulge breaks a path constraint."""
    assert SCALE.planning is not None
    strong = dataclasses.replace(
        SCALE,
        joints=tuple(dataclasses.replace(j, torque_max_nm=1e6) for j in SCALE.joints),
        planning=dataclasses.replace(SCALE.planning, power_max_w=1e7),
    )
    verifier = Verifier(strong, backend="c")
    (x,) = plan_set["x"]
    out, _, scale = _plan(verifier, x)
    ok = (out[:, COL_TOTAL] <= 0.0) & (scale != 1.0) & (scale < PLAN_C_RANGE[1])
    assert np.sum(ok) >= 10
    path_worst = np.max(out[ok][:, PATH_ONLY], axis=1)
    assert np.all(path_worst >= -PLAN_TOL - 1e-9), "c* stopped short of every path limit"
    capped = out[ok, COL_VOLUME_M3] >= V_MAX - PLAN_TOL * V_SPAN
    assert np.sum(capped) >= 5 and np.all(out[ok, COL_VOLUME_M3] <= V_MAX)
    beyond = _path_violation(verifier, _scaled(x[ok], scale[ok] * 1.001))
    assert np.all(beyond > 0.0), "a larger bulge would still hold: c* is not the largest"


def test_plan_keeps_the_path_direction() -> None:
    """K of the plan is c* times the input's; path is the tip path of the planned rows."""
    x = _candidates(SCALE, 2, seed=91)
    n = 31
    verifier = Verifier(SCALE, n, backend="c")
    path = np.empty((x.shape[0], n, 2))
    out, planned, scale = _plan(verifier, x, path=path)
    K_out = -planned[:, RT_A6 : RT_A6 + 3] * planned[:, RT_T_S, None] ** 6
    np.testing.assert_allclose(K_out, scale[:, None] * _shape_terms(x), rtol=1e-13, atol=0.0)
    again, again_path = np.empty_like(out), np.empty_like(path)
    verifier.evaluate_into(_planned_rows(x, planned), again, again_path)
    np.testing.assert_array_equal(out, again)
    np.testing.assert_array_equal(path, again_path)
    assert np.all((scale >= PLAN_C_RANGE[0]) & (scale <= PLAN_C_RANGE[1]))
    assert np.any(scale != 1.0), "nothing was scaled"


def test_plan_where_nothing_works(plan_set: dict[str, tuple[np.ndarray, ...]]) -> None:
    """No scale passes the path constraints, no bulge, c_range (1, 1): the row's own path and
    scale 1; where it breaks a path-only limit (no T fixes that), the row itself as
    evaluate_into gives it, else retimed exactly as retime_into gives it."""
    verifier = Verifier(SCALE, backend="c")
    x = _candidates(SCALE, 1, seed=101)[:4]
    never_enters = x.copy()
    never_enters[:, 6] -= 1.0  # the surface a metre down: no path reaches it (theta_p -90 deg)
    quintic = x.copy()
    quintic[:, 8:11] = 0.0
    (net,) = plan_set["x"]
    own_path_ok = net[_path_violation(Verifier(SCALE, backend="c"), net) < 0.0][:3]
    kinds = [0, 0]  # rows reported as evaluated, as retimed
    for rows, c_range in (
        (never_enters, PLAN_C_RANGE),
        (quintic, PLAN_C_RANGE),
        (x, (1.0, 1.0)),
        (own_path_ok, (1.0, 1.0)),
    ):
        out, planned, scale = _plan(verifier, rows, c_range)
        own_out, own_rt = _retime(verifier, rows)
        ev = np.empty_like(out)
        verifier.evaluate_into(rows, ev)
        with np.errstate(invalid="ignore"):
            broken = ~(np.max(ev[:, PATH_ONLY], axis=1) <= 0.0)
        np.testing.assert_array_equal(scale, 1.0)
        np.testing.assert_array_equal(out[broken], ev[broken])
        np.testing.assert_array_equal(planned[broken, RT_A6 : RT_A6 + 3], rows[broken, 8:11])
        np.testing.assert_array_equal(planned[broken, RT_T_S], rows[broken, 11])
        np.testing.assert_array_equal(out[~broken], own_out[~broken])
        np.testing.assert_array_equal(planned[~broken], own_rt[~broken])
        # The path-only values are the own path's either way.
        np.testing.assert_allclose(out[:, PATH_ONLY], own_out[:, PATH_ONLY], rtol=1e-9,
                                   atol=1e-12)
        assert np.all(out[:, COL_TOTAL] >= 0.0)
        if rows is never_enters:
            assert np.all(broken)
        kinds[0] += int(np.sum(broken))
        kinds[1] += int(np.sum(~broken))
    assert kinds[0] >= 4 and kinds[1] >= 3, kinds


def test_plan_rejects_bad_rows_without_touching_the_others() -> None:
    x = _candidates(SCALE, 2, seed=3)[:4]
    bad = _bad_rows(x)
    bad = bad[(bad[:, 11] != 1e-300) & (bad[:, 8] != 1e300)]  # valid paths (retime tests)
    mixed = np.concatenate([x[:2], bad, x[2:]])
    n = 21
    verifier = Verifier(SCALE, n, backend="c")
    path = np.empty((mixed.shape[0], n, 2))
    out, planned, scale = _plan(verifier, mixed, path=path)
    rejected = slice(2, 2 + len(bad))
    assert np.all(out[rejected, COL_TOTAL] == np.inf)
    assert np.all(np.isnan(np.delete(out[rejected], COL_TOTAL, axis=1)))
    assert np.all(np.isnan(planned[rejected])) and np.all(np.isnan(path[rejected]))
    assert np.all(np.isnan(scale[rejected]))
    alone_path = np.empty((x.shape[0], n, 2))
    alone = _plan(verifier, x, path=alone_path)
    keep = np.r_[0:2, 2 + len(bad) : mixed.shape[0]]
    for got, want in zip((out, planned, scale, path), (*alone, alone_path), strict=True):
        np.testing.assert_array_equal(got[keep], want)


def test_plan_wrong_arrays_raise_value_error() -> None:
    v = Verifier(SCALE, 11, backend="c")
    x = _candidates(SCALE, 1, seed=1)[:2].copy()
    out = np.empty((2, N_OUT))
    pl = np.empty((2, N_RETIMED))
    sc = np.empty(2)
    cases: list[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, str]] = [
        (x, np.empty((2, 3)), None, None, r"planned must have shape \(N, 4\)"),
        (x, np.empty((3, 4)), None, None, "same number of rows"),
        (x, pl, np.empty((2, 12, 2)), None, r"path must have shape \(N, 11, 2\)"),
        (x, pl, None, np.empty((2, 1)), r"scale must have shape \(N,\)"),
        (x, pl, None, np.empty(3), "same number of rows"),
        (x, pl, None, np.empty(2, dtype=np.float32), "float64"),
        (x[:, :11].copy(), pl, None, None, r"inputs must have shape \(N, 12\)"),
    ]
    for inputs, p, path, s, message in cases:
        with pytest.raises(ValueError, match=message):
            v.plan_into(inputs, out, p, PLAN_C_RANGE, path, s)
    for c_range in ((-0.1, 1.0), (2.0, 1.0), (math.nan, 1.0), (0.5, math.inf)):
        with pytest.raises(ValueError, match="c_range must be finite with 0 <= c_lo <= c_hi"):
            v.plan_into(x, out, pl, c_range, None, sc)
    with pytest.raises(ValueError, match="c_range must be two floats"):
        v.plan_into(x, out, pl, (0.5,), None, sc)  # type: ignore[arg-type]


def test_plan_convenience_matches_plan_into() -> None:
    x = _candidates(SCALE, 1, seed=7)[:4]
    verifier = Verifier(SCALE, backend="c")
    out, planned, scale = _plan(verifier, x)
    for row, o, r, c in zip(x, out, planned, scale, strict=True):
        a6, T, res, c_got = verifier.plan(row[0:3], row[3:6], row[6], DigType(int(row[7])),
                                          row[8:11], row[11])
        np.testing.assert_array_equal(a6, r[:3])
        assert T == r[3] == res.T_s and c_got == c
        np.testing.assert_array_equal(res.violations, o[:22])
    with pytest.raises(PlanningError, match="T_s must be finite and > 0"):
        verifier.plan(x[0, 0:3], x[0, 3:6], x[0, 6], 0, x[0, 8:11], 0.0)
    with pytest.raises(ValueError, match="c_range"):
        verifier.plan(x[0, 0:3], x[0, 3:6], x[0, 6], 0, x[0, 8:11], 6.0, c_range=(1.0, 0.5))


class _RenamedChain:
    """dynamics._Chain after a refactoring that renamed its fields."""

    def __init__(self, rig: Rig) -> None:
        chain = dynamics._Chain(rig)
        self.first_moment = chain.h


class _ChangedChain(dynamics._Chain):
    """dynamics._Chain whose h no longer means what the kernel's closed form assumes."""

    def __init__(self, rig: Rig) -> None:
        super().__init__(rig)
        self.h = [1.1 * v for v in self.h]


@pytest.mark.parametrize(
    ("chain", "message"),
    [(_RenamedChain, "_Chain"), (_ChangedChain, "disagrees with rt_runtime.planning.oneshot")],
)
def test_a_changed_dynamics_chain_disables_the_kernel(
    chain: type, message: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """verify reads the private dynamics._Chain: a change there never goes unnoticed."""
    monkeypatch.setattr(verify, "dynamics", types.SimpleNamespace(_Chain=chain))
    with pytest.raises(ConfigurationError, match=message):
        Verifier(SCALE, backend="c")
    with pytest.warns(RuntimeWarning, match=message):
        fallback = Verifier(SCALE)
    assert fallback.backend == "numpy"
    if chain is _RenamedChain:
        with pytest.raises(ConfigurationError, match="h, b, d"):
            verify.pack_params(SCALE)


def test_the_intact_kernel_builds_without_warnings() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert Verifier(VARIANT, 17).backend == "c"
