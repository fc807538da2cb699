"""The shipped networks (onnx/): they load, match their cards and the rig, and plan held-out
problems as their cards say, every returned plan feasible by the numpy reference."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import front_state

from rt_runtime.bench import bench_pinn
from rt_runtime.errors import PlanningError
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, PinnPlanner, load_card
from rt_runtime.planning.verify import Verifier
from rt_runtime.rig import load_rig
from rt_runtime.training.export import sha256_file

RIG = load_rig("scale_model")
SUBSET = 40  # held-out problems per type planned here (the first ones: a fixed subset)


@pytest.fixture(scope="module")
def planner() -> PinnPlanner:
    return PinnPlanner(RIG, DEFAULT_MODEL_DIR)


@pytest.mark.parametrize("kind", ["downward", "backward"])
def test_cards_match_models_and_rig(kind: str) -> None:
    card = load_card(DEFAULT_MODEL_DIR / f"pinn_{kind}.json")
    assert card.rig == "scale_model"
    assert card.rig_planning_fingerprint == RIG.planning_fingerprint
    assert card.model_sha256 == sha256_file(card.model_path)
    raw = card.raw
    held = DEFAULT_MODEL_DIR / raw["heldout_file"]["name"]
    assert raw["heldout_file"]["sha256"] == sha256_file(held)
    assert raw["parity_max_rel"] <= 1e-5
    assert raw["dataset"]["test"] == 200
    assert raw["dataset"]["train"] >= 1600  # at least Yao's size
    assert raw["opset"] >= 13
    for key in ("hash", "samples"):
        assert raw["dataset"][key]


@pytest.mark.parametrize("kind", list(DigType))
def test_heldout_subset_planned_as_the_card_says(planner: PinnPlanner, kind: DigType) -> None:
    name = kind.name.lower()
    card = json.loads((DEFAULT_MODEL_DIR / f"pinn_{name}.json").read_text())
    with np.load(DEFAULT_MODEL_DIR / f"pinn_{name}_heldout.npz") as z:
        X, teacher = z["X"][:SUBSET], z["objective"][:SUBSET]
    gaps = []
    refused = 0
    for x, obj in zip(X, teacher, strict=True):
        try:
            plan = planner.plan(x[0:3], x[3:6], float(x[6]), kind)
        except PlanningError:
            refused += 1
            continue
        ev = oneshot.evaluate(
            RIG, x[None, 0:3], x[None, 3:6], x[None, 6], int(kind),
            np.asarray(plan.a6)[None, None], np.asarray([[plan.T_s]]),
        )
        assert ev.feasible[0, 0], (name, x.tolist(), plan.status)
        np.testing.assert_allclose(ev.objective[0, 0], plan.verification.objective, rtol=1e-9)
        gaps.append((ev.objective[0, 0] - obj) / abs(obj))
    # The card's held-out figures (all 200) hold on the subset, with room for sampling noise.
    planned = card["heldout"]["planned"]
    assert refused / SUBSET <= planned["refused"] + 0.05
    assert np.mean(gaps) <= planned["gap_mean"] + 0.03


def test_raw_answers_match_card(planner: PinnPlanner) -> None:
    """Raw feasibility on the whole held-out set is the card's number, recomputed."""
    for kind in DigType:
        name = kind.name.lower()
        card = json.loads((DEFAULT_MODEL_DIR / f"pinn_{name}.json").read_text())
        with np.load(DEFAULT_MODEL_DIR / f"pinn_{name}_heldout.npz") as z:
            X = z["X"]
        Y = planner.infer(kind, X)
        ev = oneshot.evaluate(
            RIG, X[:, 0:3], X[:, 3:6], X[:, 6], int(kind), Y[:, None, :3], Y[:, None, 3]
        )
        assert float(np.mean(ev.feasible[:, 0])) == pytest.approx(
            card["heldout"]["raw_feasible"], abs=1e-9
        )


def test_verifier_is_compiled() -> None:
    """CI builds the C kernel; the planner's latency depends on it."""
    assert Verifier(RIG).backend == "c"


def test_bench_pinn_small() -> None:
    report = bench_pinn(RIG, limit=6, passes=1, pso_problems=1)
    r = report.to_json()
    for key in (
        "samples",
        "gap_mean",
        "gap_max",
        "raw_feasible",
        "verified_feasible",
        "refused",
        "infer_us",
        "plan_us",
        "pso_solve_s",
        "table4",
    ):
        assert key in r
    assert report.samples == 12
    assert report.executed_feasible == 1.0
    assert report.verified_feasible + report.refused == pytest.approx(1.0)
    assert set(r["plan_us"]) >= {"p50", "p99"}
    assert set(report.table4) == {"downward", "backward"}


@pytest.mark.parametrize("kind", list(DigType))
def test_c_front_plans_the_network_answer(planner: PinnPlanner, kind: DigType) -> None:
    """The C kernel's Front (staging, inference, plan in one call) stages the problem and the
    network's answer into the row and leaves in out, retimed and scale exactly what
    Kernel.plan gives for that row, with capped and default fills."""
    with np.load(DEFAULT_MODEL_DIR / f"pinn_{kind.name.lower()}_heldout.npz") as z:
        X = z["X"][:SUBSET]
    session = planner._sessions[kind]
    feasible = 0
    for x, (c_lo, c_hi) in zip(X, [(0.3, 2.0), (0.2, 0.9)] * SUBSET, strict=False):
        got = planner._front(x[0:3], x[3:6], float(x[6]), kind, c_lo, c_hi)
        assert got is not None and got[1] > 0.0
        row = planner._row.copy()
        np.testing.assert_array_equal(row[0, 0:7], x)
        assert row[0, 7] == int(kind)
        np.testing.assert_array_equal(row[0, 8:12], session.y[0].astype(np.float64))
        out, planned, scale = np.empty((1, 32)), np.empty((1, 4)), np.empty(1)
        planner.verifier.plan_into(row, out, planned, (c_lo, c_hi), None, scale)
        want = np.concatenate([row[0], out[0], planned[0], scale])
        np.testing.assert_array_equal(front_state(planner), want)
        assert got[0] == (out[0, 22] <= 0.0)
        feasible += got[0]
    assert feasible > SUBSET // 2


def test_c_front_reads_poses_of_any_form(planner: PinnPlanner) -> None:
    """Tuples, lists, strided arrays or arrays of another dtype plan the same; a wrong pose is
    named."""
    kind = DigType.DOWNWARD
    with np.load(DEFAULT_MODEL_DIR / "pinn_downward_heldout.npz") as z:
        x = np.asarray(z["X"][0])
    want = planner.plan(x[0:3], x[3:6], float(x[6]), kind)
    cols = np.repeat(x[None, 0:6], 2, axis=0).T  # (6, 2): x[0:3] as a strided column
    for qs, qe in (
        (tuple(x[0:3]), list(x[3:6])),
        (cols[0:3, 1], cols[3:6, 0]),
        (x[0:3].astype(np.longdouble), x[3:6]),  # another dtype: read as a sequence
    ):
        got = planner.plan(qs, qe, float(x[6]), kind)
        assert (got.a6, got.T_s, got.status) == (want.a6, want.T_s, want.status)
        assert got.problem == want.problem
    with pytest.raises(ValueError, match=r"q_start_rad must have 3 values .*got 2"):
        planner.plan(x[0:2], x[3:6], float(x[6]), kind)
    with pytest.raises(TypeError, match=r"q_end_rad must hold 3 numbers; item 1 is str"):
        planner.plan(x[0:3], [x[3], "a", x[5]], float(x[6]), kind)
    with pytest.raises(TypeError, match=r"q_start_rad must be a sequence of 3 numbers"):
        planner.plan(1.0, x[3:6], float(x[6]), kind)
    # After the errors the planner plans as before.
    again = planner.plan(x[0:3], x[3:6], float(x[6]), kind)
    assert (again.a6, again.T_s) == (want.a6, want.T_s)
