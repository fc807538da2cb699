"""The shipped networks (onnx/): they load, match their cards and the rig, and plan held-out
problems as their cards say, every returned plan feasible by the numpy reference."""

from __future__ import annotations

import json

import numpy as np
import pytest

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
    r = bench_pinn(RIG, limit=6, passes=1, pso_problems=1)
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
    assert r["samples"] == 12
    assert r["executed_feasible"] == 1.0
    assert r["verified_feasible"] + r["refused"] == pytest.approx(1.0)
    assert set(r["plan_us"]) >= {"p50", "p99"}
    assert set(r["table4"]) == {"downward", "backward"}
