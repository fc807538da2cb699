"""The PINN pipeline on a reduced size, and the runtime planner's refusals.

dataset (PSO teacher, dask LocalCluster) -> train (physics-informed, a few epochs) -> export
(ONNX + card, parity with torch) -> load in onnxruntime -> plan -> verify. The networks trained
here are poor (tens of samples, a few epochs); what is tested is that every plan the planner
returns is feasible by the numpy reference, and that everything it cannot vouch for is refused.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("distributed")

from rt_runtime.errors import ConfigurationError, PlanningError  # noqa: E402
from rt_runtime.planning import oneshot  # noqa: E402
from rt_runtime.planning.oneshot import DigType  # noqa: E402
from rt_runtime.planning.pinn import PinnPlanner, PlanStatus, load_card  # noqa: E402
from rt_runtime.rig import load_rig  # noqa: E402
from rt_runtime.training import dataset as ds  # noqa: E402
from rt_runtime.training.export import export, sha256_file  # noqa: E402
from rt_runtime.training.train import (  # noqa: E402
    TrainConfig,
    load_checkpoint,
    network_from_checkpoint,
    plot_losses,
    save_checkpoint,
    train,
)

RIG = load_rig("scale_model")


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Run the whole pipeline once on a reduced size; returns its root directory."""
    root = tmp_path_factory.mktemp("pipeline")
    specs = [
        ds.DatasetSpec.default(
            kind,
            n_samples=24,
            n_test=6,
            chunk_size=8,
            n_particles=12,
            n_iterations=8,
            polish_starts=1,
        )
        for kind in ("downward", "backward")
    ]
    ds.generate_many(RIG, specs, root / "data", workers=1, progress=False)
    for kind in DigType:
        name = kind.name.lower()
        res = train(
            RIG,
            root / "data" / f"{name}.npz",
            kind,
            TrainConfig(epochs=6, eval_every=3, n_samples=51),
            progress=False,
        )
        save_checkpoint(res, root / "ckpt" / f"pinn_{name}.pt")
        plot_losses(res.history, root / "ckpt" / f"pinn_{name}_losses.png", name)
        export(root / "ckpt" / f"pinn_{name}.pt", root / "onnx" / f"pinn_{name}.onnx")
    return root


def _copy_models(pipeline: Path, dest: Path) -> Path:
    shutil.copytree(pipeline / "onnx", dest)
    return dest


def test_pipeline_artifacts_and_parity(pipeline: Path) -> None:
    for kind in ("downward", "backward"):
        card = json.loads((pipeline / "onnx" / f"pinn_{kind}.json").read_text())
        assert card["rig"] == "scale_model"
        assert card["rig_planning_fingerprint"] == RIG.planning_fingerprint
        assert card["model_sha256"] == sha256_file(pipeline / "onnx" / f"pinn_{kind}.onnx")
        assert card["parity_max_rel"] <= 1e-5
        assert card["dataset"]["train"] + card["dataset"]["test"] <= card["dataset"]["samples"]
        assert card["heldout"]["samples"] == card["dataset"]["test"]
        assert (pipeline / "ckpt" / f"pinn_{kind}_losses.png").stat().st_size > 10_000
        assert len(card["domain"]["min"]) == 7


def test_onnx_matches_torch_checkpoint(pipeline: Path) -> None:
    """Independent of the exporter's own check: torch and onnxruntime on fresh inputs."""
    import onnxruntime as ort

    payload = load_checkpoint(pipeline / "ckpt" / "pinn_downward.pt")
    net = network_from_checkpoint(payload)
    data = ds.load(pipeline / "data" / "downward.npz")
    x = np.asarray(data.X, dtype=np.float32)
    x = x + np.random.default_rng(3).normal(0.0, 0.01, x.shape).astype(np.float32)
    with torch.no_grad():
        ref = net(torch.from_numpy(x)).numpy()
    sess = ort.InferenceSession(str(pipeline / "onnx" / "pinn_downward.onnx"))
    got = sess.run(None, {"input": x})[0]
    scale = np.max(np.abs(ref), axis=0)
    assert np.max(np.abs(got - ref) / scale) <= 1e-5


def test_planner_returns_only_verified_plans(pipeline: Path) -> None:
    planner = PinnPlanner(RIG, pipeline / "onnx")
    returned = 0
    for kind in DigType:
        name = kind.name.lower()
        with np.load(pipeline / "onnx" / f"pinn_{name}_heldout.npz") as z:
            X = z["X"]
        for x in X:
            try:
                plan = planner.plan(x[0:3], x[3:6], float(x[6]), kind)
            except PlanningError as exc:
                assert "refused" in str(exc)
                continue
            returned += 1
            ev = oneshot.evaluate(
                RIG, x[None, 0:3], x[None, 3:6], x[None, 6], int(kind),
                np.asarray(plan.a6)[None, None], np.asarray([[plan.T_s]]),
            )
            assert ev.feasible[0, 0], (name, x, plan)
            assert plan.verification.feasible
            assert plan.plan_us > 0.0 and plan.infer_us > 0.0
            traj = plan.trajectory()
            np.testing.assert_allclose(traj.sample(0.0)[0], x[0:3], atol=1e-9)
            np.testing.assert_allclose(traj.sample(plan.T_s)[0], x[3:6], atol=1e-9)
            if plan.status == PlanStatus.RETIMED:
                # Filling and retiming keep the path's direction: K = c K_net.
                k_raw = -np.asarray(plan.raw_a6) * plan.raw_T_s**6
                k_new = -np.asarray(plan.a6) * plan.T_s**6
                np.testing.assert_allclose(k_new, plan.bulge_scale * k_raw, rtol=1e-6)
    assert returned > 0


def test_planner_without_retiming_verifies_or_repairs(pipeline: Path) -> None:
    planner = PinnPlanner(RIG, pipeline / "onnx", retime=False, refine=False)
    with np.load(pipeline / "onnx" / "pinn_backward_heldout.npz") as z:
        X = z["X"]
    for x in X:
        try:
            plan = planner.plan(x[0:3], x[3:6], float(x[6]), DigType.BACKWARD)
        except PlanningError as exc:
            assert "violates" in str(exc) or "outside" in str(exc)
            continue
        assert plan.status in (PlanStatus.RAW, PlanStatus.TIME_SCALED)
        assert plan.verification.feasible
        if plan.status == PlanStatus.RAW:
            assert plan.T_s == plan.raw_T_s


def _x0(pipeline: Path) -> np.ndarray:
    with np.load(pipeline / "onnx" / "pinn_downward_heldout.npz") as z:
        return np.asarray(z["X"][0])


def test_nan_input_refused(pipeline: Path) -> None:
    planner = PinnPlanner(RIG, pipeline / "onnx")
    x = _x0(pipeline)
    with pytest.raises(PlanningError, match=r"theta12 is nan; inputs must be finite"):
        planner.plan([x[0], np.nan, x[2]], x[3:6], float(x[6]), DigType.DOWNWARD)
    with pytest.raises(PlanningError, match=r"input H is nan"):
        planner.plan(x[0:3], x[3:6], float("nan"), DigType.DOWNWARD)


def test_out_of_domain_refused_or_sent_to_teacher(pipeline: Path) -> None:
    planner = PinnPlanner(RIG, pipeline / "onnx")
    card = load_card(pipeline / "onnx" / "pinn_downward.json")
    x = _x0(pipeline)
    low_h = card.domain_min[6] - 0.05
    with pytest.raises(PlanningError, match=r"input H = .* outside the downward model's domain"):
        planner.plan(x[0:3], x[3:6], low_h, DigType.DOWNWARD)
    # With the teacher allowed, the same problem is planned by the PSO (and verified).
    teacher = PinnPlanner(RIG, pipeline / "onnx", teacher_fallback=True)
    try:
        plan = teacher.plan(x[0:3], x[3:6], low_h, DigType.DOWNWARD)
    except PlanningError as exc:
        assert "PSO teacher found no feasible plan" in str(exc)
    else:
        assert plan.status == PlanStatus.TEACHER
        assert plan.verification.feasible


def test_corrupted_model_refused(pipeline: Path, tmp_path: Path) -> None:
    models = _copy_models(pipeline, tmp_path / "m")
    path = models / "pinn_backward.onnx"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ConfigurationError, match=r"pinn_backward.onnx is corrupt or was replaced"):
        PinnPlanner(RIG, models)


def test_unloadable_model_refused(pipeline: Path, tmp_path: Path) -> None:
    """A model whose card hash matches but that onnxruntime cannot load (truncated)."""
    models = _copy_models(pipeline, tmp_path / "m")
    path = models / "pinn_downward.onnx"
    path.write_bytes(path.read_bytes()[:200])
    card_path = models / "pinn_downward.json"
    card = json.loads(card_path.read_text())
    card["model_sha256"] = sha256_file(path)
    card_path.write_text(json.dumps(card))
    with pytest.raises(ConfigurationError, match=r"cannot be loaded by onnxruntime"):
        PinnPlanner(RIG, models)


def test_model_for_another_rig_refused(pipeline: Path, tmp_path: Path) -> None:
    models = _copy_models(pipeline, tmp_path / "m")
    card_path = models / "pinn_downward.json"
    card = json.loads(card_path.read_text())
    card["rig"] = "test_bench"
    card_path.write_text(json.dumps(card))
    with pytest.raises(ConfigurationError, match=r"trained for rig 'test_bench'"):
        PinnPlanner(RIG, models)


def test_model_for_other_rig_values_refused(pipeline: Path) -> None:
    import dataclasses

    heavier = dataclasses.replace(
        RIG, links=(dataclasses.replace(RIG.links[0], mass_kg=9.0), *RIG.links[1:])
    )
    with pytest.raises(ConfigurationError, match=r"trained for other values of rig"):
        PinnPlanner(heavier, pipeline / "onnx")


def test_missing_or_broken_card_refused(pipeline: Path, tmp_path: Path) -> None:
    models = _copy_models(pipeline, tmp_path / "m")
    (models / "pinn_backward.json").write_text("{not json")
    with pytest.raises(ConfigurationError, match=r"pinn_backward.json is not valid JSON"):
        PinnPlanner(RIG, models)
    (models / "pinn_backward.json").unlink()
    with pytest.raises(ConfigurationError, match=r"model card .* does not exist"):
        PinnPlanner(RIG, models)


def test_train_refuses_dataset_of_other_type(pipeline: Path) -> None:
    with pytest.raises(ConfigurationError, match=r"holds 'downward' digs"):
        train(RIG, pipeline / "data" / "downward.npz", DigType.BACKWARD, TrainConfig(epochs=1))


def test_train_config_errors_name_the_setting() -> None:
    with pytest.raises(ConfigurationError, match=r"training setting margin must be in \[0, 0.5\)"):
        TrainConfig(margin=0.7).validate()
    with pytest.raises(ConfigurationError, match=r"training setting epochs must be >= 1"):
        TrainConfig(epochs=0).validate()
