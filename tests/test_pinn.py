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
from rt_runtime.planning import oneshot, verify  # noqa: E402
from rt_runtime.planning.oneshot import CONSTRAINT_NAMES, DigType, Problem  # noqa: E402
from rt_runtime.planning.pinn import (  # noqa: E402
    DEFAULT_MODEL_DIR,
    FAST_REPAIR_CALLS,
    PinnPlanner,
    PlanStatus,
    _nearest,
    load_card,
)
from rt_runtime.rig import load_rig  # noqa: E402
from rt_runtime.training import dataset as ds  # noqa: E402
from rt_runtime.training.export import LIBRARY_K, export, sha256_file  # noqa: E402
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
            # The plan and its problem are immutable values, the problem the one asked.
            assert plan.problem == Problem(tuple(x[0:3]), tuple(x[3:6]), float(x[6]), kind)
            with pytest.raises(AttributeError):
                plan.T_s = 1.0  # type: ignore[misc]
            with pytest.raises(AttributeError):
                plan.problem.surface_y_m = 0.0  # type: ignore[misc]
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


@pytest.fixture(scope="module")
def library_models(pipeline: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The pipeline's checkpoints exported with their solution libraries of every training
    problem (keep scale 0)."""
    out = tmp_path_factory.mktemp("library")
    for kind in DigType:
        name = kind.name.lower()
        export(
            pipeline / "ckpt" / f"pinn_{name}.pt",
            out / f"pinn_{name}.onnx",
            library=True,
            library_keep_scale=0.0,
        )
    return out


def _set_library(models: Path, name: str, **entry: object) -> None:
    card_path = models / f"pinn_{name}.json"
    card = json.loads(card_path.read_text())
    card["library"].update(entry)
    card_path.write_text(json.dumps(card))


def test_library_holds_the_training_split_only(pipeline: Path, library_models: Path) -> None:
    for kind in DigType:
        name = kind.name.lower()
        card = json.loads((library_models / f"pinn_{name}.json").read_text())
        entry = card["library"]
        path = library_models / entry["name"]
        assert entry["sha256"] == sha256_file(path)
        data = ds.load(pipeline / "data" / f"{name}.npz")
        with np.load(path) as z:
            np.testing.assert_array_equal(z["X"], np.asarray(data.X)[data.train_idx])
            np.testing.assert_array_equal(z["Y"], np.asarray(data.Y)[data.train_idx])
        assert entry["rows"] == entry["train_rows"] == data.train_idx.size
        assert entry["k"] == min(LIBRARY_K, data.train_idx.size)
        # Exported without --library: no library named, none planned with.
        plain = json.loads((pipeline / "onnx" / f"pinn_{name}.json").read_text())
        assert plain["library"] is None


def test_library_keeps_the_problems_the_network_fills_far_up(
    pipeline: Path, library_models: Path, tmp_path: Path
) -> None:
    """With a keep scale, the library holds exactly the training problems whose network plan
    (as the runtime plans it, library off) is retimed with a bulge scale at or above it; at a
    scale above every plan's, no library is written."""
    planner = PinnPlanner(RIG, library_models, library=False)
    kind = DigType.BACKWARD
    data = ds.load(pipeline / "data" / "backward.npz")
    X = np.asarray(data.X)[data.train_idx]
    scales = []
    for x in X:
        try:
            plan = planner.plan(x[0:3], x[3:6], float(x[6]), kind)
        except PlanningError:
            scales.append(0.0)
            continue
        scales.append(plan.bulge_scale if plan.status == PlanStatus.RETIMED else 0.0)
    c = np.asarray(scales)
    distinct = np.unique(c[c > 0.0])
    assert distinct.size >= 2, "the reduced pipeline must fill some plans to different scales"
    mid = distinct.size // 2
    keep_scale = float(0.5 * (distinct[mid - 1] + distinct[mid]))  # no plan sits on it
    card = export(
        pipeline / "ckpt" / "pinn_backward.pt",
        tmp_path / "pinn_backward.onnx",
        library=True,
        library_keep_scale=keep_scale,
    )
    entry = card["library"]
    kept = c >= keep_scale
    assert 0 < kept.sum() < X.shape[0]
    assert entry["rows"] == kept.sum() and entry["train_rows"] == X.shape[0]
    assert entry["keep_bulge_scale"] == keep_scale
    assert entry["k"] == min(LIBRARY_K, int(kept.sum()))
    with np.load(tmp_path / entry["name"]) as z:
        np.testing.assert_array_equal(z["X"], X[kept])
        np.testing.assert_array_equal(z["Y"], np.asarray(data.Y)[data.train_idx][kept])
    none = export(  # over the export above: its library file goes too
        pipeline / "ckpt" / "pinn_backward.pt",
        tmp_path / "pinn_backward.onnx",
        library=True,
        library_keep_scale=float(c.max()) + 1.0,
    )
    assert none["library"] is None
    assert not (tmp_path / "pinn_backward_library.npz").exists()
    for bad in (float("nan"), -0.1):
        with pytest.raises(ConfigurationError, match="keep scale must be finite and >= 0"):
            export(
                pipeline / "ckpt" / "pinn_backward.pt",
                tmp_path / "bad" / "pinn_backward.onnx",
                library=True,
                library_keep_scale=bad,
            )
    assert not (tmp_path / "bad").exists()  # refused before anything was written


def test_library_plans_are_verified_and_beat_the_network(
    pipeline: Path, library_models: Path, tmp_path: Path
) -> None:
    """Triggered on every retimed plan (trigger 1e-3): a training problem's nearest library
    entry is its own teacher answer, so some plans must come from the library; each is
    feasible by the numpy reference and better than the network's plan of the problem."""
    models = Path(shutil.copytree(library_models, tmp_path / "m"))
    for name in ("downward", "backward"):
        _set_library(models, name, trigger_bulge_scale=1e-3)
    with_lib = PinnPlanner(RIG, models)
    without = PinnPlanner(RIG, models, library=False)
    from_library = 0
    for kind in DigType:
        data = ds.load(pipeline / "data" / f"{kind.name.lower()}.npz")
        for x in np.asarray(data.X)[np.concatenate([data.train_idx, data.test_idx])]:
            args = (x[0:3], x[3:6], float(x[6]), kind)
            try:
                net = without.plan(*args)
            except PlanningError:
                with pytest.raises(PlanningError):
                    with_lib.plan(*args)
                continue
            plan = with_lib.plan(*args)
            off = with_lib.plan(*args, library=False)
            assert off.status == net.status and off.a6 == net.a6 and off.T_s == net.T_s
            if plan.status != PlanStatus.LIBRARY:
                assert plan.a6 == net.a6 and plan.T_s == net.T_s
                continue
            from_library += 1
            assert net.status == PlanStatus.RETIMED
            assert plan.raw_a6 == net.raw_a6  # the network's answer is still reported
            ev = _reference(list(x), kind, plan)
            assert ev.feasible[0, 0]
            assert ev.objective[0, 0] < net.verification.objective
    assert from_library > 0


def test_library_untriggered_and_off_plan_as_the_network(library_models: Path) -> None:
    """Above every fill scale (trigger 1e9) or switched off, the library changes nothing."""
    models = library_models
    planner = PinnPlanner(RIG, models, library=False)
    assert planner._libraries == {}
    with np.load(models / "pinn_backward_heldout.npz") as z:
        X = z["X"]
    loaded = PinnPlanner(RIG, models)
    assert set(loaded._libraries) == set(DigType)
    for lib in loaded._libraries.values():
        lib.trigger = 1e9
    for x in X:
        args = (x[0:3], x[3:6], float(x[6]), DigType.BACKWARD)
        try:
            a = planner.plan(*args)
        except PlanningError:
            continue
        b = loaded.plan(*args)
        assert (a.status, a.a6, a.T_s) == (b.status, b.a6, b.T_s)


def test_library_search_finds_the_nearest_rows(
    pipeline: Path, library_models: Path, tmp_path: Path
) -> None:
    """The library's k-d tree finds the k problems nearest each training problem, nearest first,
    as a brute-force numpy search over the scaled problems does; with every plan triggered,
    some plans come from those rows."""
    models = Path(shutil.copytree(library_models, tmp_path / "m"))
    for name in ("downward", "backward"):
        _set_library(models, name, trigger_bulge_scale=1e-3, k=3)
    planner = PinnPlanner(RIG, models)
    from_library = 0
    for kind in DigType:
        lib = planner._libraries[kind]
        scaled = np.asarray(lib.tree.data)
        data = ds.load(pipeline / "data" / f"{kind.name.lower()}.npz")
        for x in np.asarray(data.X):
            d = ((x * lib.inv_std - scaled) ** 2).sum(axis=1)
            want = np.argsort(d, kind="stable")[: lib.k]
            got = lib.nearest(list(x))
            if not np.array_equal(got, want):
                pytest.fail(f"nearest rows {got.tolist()} (distances {d[got].tolist()}), brute "
                            f"force {want.tolist()} ({d[want].tolist()}); problem {x.tolist()!r}")
            try:
                plan = planner.plan(x[0:3], x[3:6], float(x[6]), kind)
            except PlanningError:
                continue
            from_library += plan.status == PlanStatus.LIBRARY
    assert from_library > 0


def test_planner_needs_the_c_kernel(
    library_models: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without the compiled kernel the planner is not built: the message says how to build
    it."""
    monkeypatch.setattr(verify, "_load_extension", lambda: None)
    with pytest.raises(ConfigurationError, match=r"needs the compiled kernel.*pip install -e"):
        PinnPlanner(RIG, library_models)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("corrupt", r"library .*pinn_backward_library.npz is corrupt or was replaced"),
        ("missing", r"library file .* does not exist"),
        ("k", r"library k must be in \[1, \d+\] and trigger_bulge_scale > 0"),
        ("entry", r"library trigger_bulge_scale must be a finite number; got None"),
    ],
)
def test_bad_library_refused(
    library_models: Path, tmp_path: Path, change: str, message: str
) -> None:
    models = Path(shutil.copytree(library_models, tmp_path / "m"))
    path = models / "pinn_backward_library.npz"
    if change == "corrupt":
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    elif change == "missing":
        path.unlink()
    elif change == "k":
        _set_library(models, "backward", k=0)
    else:
        card_path = models / "pinn_backward.json"
        card = json.loads(card_path.read_text())
        del card["library"]["trigger_bulge_scale"]
        card_path.write_text(json.dumps(card))
    with pytest.raises(ConfigurationError, match=message):
        PinnPlanner(RIG, models)
    PinnPlanner(RIG, models, library=False)  # the networks alone still load


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
        assert plan.status in (PlanStatus.RAW, PlanStatus.TIME_SCALED, PlanStatus.REPAIRED)
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


# -- the fast repair -------------------------------------------------------------------------
#
# Network answers that fail the normal path (fill and retime), pinned here so that the cases do
# not depend on which networks are shipped: a stand-in session answers them. The problems are
# held-out problems; the answers are what networks trained on the shipped datasets gave.

# Backward row 4 of the shipped held-out set: the boom dips below its lower limit mid-path, and
# no bulge scale keeps both the boom in range and V_p >= V_min (SLSQP served it before).
BOOM_X = [-0.11897403270667706, -1.1543312812918345, -1.0678792357036995, -0.26727008754507564,
          -1.3844281531240807, -1.5448969749897588, -0.5803403383168766]
BOOM_Y = [0.00018114503473043442, 0.0001446689711883664, -0.00021662420476786792,
          6.214824676513672]
# Backward row 153: repaired path found, but it needs more boom torque than any T allows;
# the refinement serves it.
TORQUE_X = [-0.17880657091514524, -0.9015407154851449, -0.9705558136313537,
            -0.25538150650980096, -1.099580994412145, -1.379083708820552, -0.6354834594385348]
TORQUE_Y = [0.0003552054113242775, 0.00038819393375888467, -0.00028847815701738,
            5.45201301574707]
# A downward answer entering too flat (theta_p below its minimum): projected onto theta_p's
# half-space, then filled.
THETA_P_X = [0.041962009594897764, -1.052794932364652, -0.21295111744740058,
             0.10333892775245856, -1.4332045605432642, -1.28225601666702, -0.47238977704605606]
THETA_P_Y = [0.0001131445897044614, 0.00018338885274715722, -4.3922182157984935e-07,
             6.103066444396973]


class _FixedNetwork:
    """Stands in for a network's session: always answers ``y`` = (a16, a26, a36, T)."""

    def __init__(self, y: list[float]) -> None:
        self.x = np.zeros((1, 7), dtype=np.float32)
        self.y = np.array([y], dtype=np.float32)

    def run(self) -> None:
        pass


def _fixed_planner(kind: DigType, y: list[float], **options: bool) -> tuple[PinnPlanner, list[str]]:
    """The shipped planner with ``kind``'s network answering ``y``, and a log of its kernel
    calls (``_front``: the normal path's staging, inference and plan)."""
    planner = PinnPlanner(RIG, DEFAULT_MODEL_DIR, **options)
    planner._sessions[kind] = _FixedNetwork(y)  # type: ignore[assignment]
    planner._bind_front()
    calls: list[str] = []
    for name in ("_front", "_eval_rows", "_plan_rows", "_retime_rows", "_coarse_rows"):
        kernel = getattr(planner, name)

        def counted(*args: object, _kernel: object = kernel, _name: str = name) -> object:
            calls.append(_name)
            return _kernel(*args)  # type: ignore[operator]

        setattr(planner, name, counted)
    return planner, calls


def _reference(x: list[float], kind: DigType, plan: object) -> oneshot.Evaluation:
    a6 = np.asarray(plan.a6)  # type: ignore[attr-defined]
    return oneshot.evaluate(
        RIG, np.array([x[0:3]]), np.array([x[3:6]]), np.array([x[6]]), int(kind),
        a6[None, None], np.array([[plan.T_s]]),  # type: ignore[attr-defined]
    )


def test_fast_repair_fixes_a_boom_below_its_limit() -> None:
    kind = DigType.BACKWARD
    raw = oneshot.evaluate(
        RIG, np.array([BOOM_X[0:3]]), np.array([BOOM_X[3:6]]), np.array([BOOM_X[6]]),
        int(kind), np.array([[BOOM_Y[0:3]]], dtype=np.float32).astype(float),
        np.array([[np.float32(BOOM_Y[3])]], dtype=float),
    )
    assert raw.violations[0, 0, CONSTRAINT_NAMES.index("angle_min_boom")] > 0.0
    # Without it, the normal path fails and the case goes to the refinement (milliseconds).
    slow, _ = _fixed_planner(kind, BOOM_Y, fast_repair=False)
    assert slow.plan(BOOM_X[0:3], BOOM_X[3:6], BOOM_X[6], kind).status == PlanStatus.REFINED
    planner, calls = _fixed_planner(kind, BOOM_Y)
    plan = planner.plan(BOOM_X[0:3], BOOM_X[3:6], BOOM_X[6], kind)
    assert plan.status == PlanStatus.REPAIRED
    assert plan.verification.feasible
    assert _reference(BOOM_X, kind, plan).feasible[0, 0]
    # The normal path's plan, then at most FAST_REPAIR_CALLS kernel calls.
    assert calls[0] == "_front"
    assert 2 <= len(calls) <= 1 + FAST_REPAIR_CALLS, calls
    # The repair lands on the boom's limit (the teacher's optimum lies there), within 1 %.
    boom = plan.verification.violations[CONSTRAINT_NAMES.index("angle_min_boom")]
    assert -0.01 < boom <= 0.0
    volume = plan.verification.violations[CONSTRAINT_NAMES.index("volume_min")]
    assert -0.02 < volume <= 0.0
    traj = plan.trajectory()
    np.testing.assert_allclose(traj.sample(plan.T_s)[0], BOOM_X[3:6], atol=1e-9)


def test_fast_repair_projects_theta_p_and_fills() -> None:
    kind = DigType.DOWNWARD
    planner, calls = _fixed_planner(kind, THETA_P_Y)
    slow, _ = _fixed_planner(kind, THETA_P_Y, fast_repair=False, refine=False)
    with pytest.raises(PlanningError, match=r"violates theta_p_min .* could not be repaired"):
        slow.plan(THETA_P_X[0:3], THETA_P_X[3:6], THETA_P_X[6], kind)
    plan = planner.plan(THETA_P_X[0:3], THETA_P_X[3:6], THETA_P_X[6], kind)
    assert plan.status == PlanStatus.REPAIRED
    assert _reference(THETA_P_X, kind, plan).feasible[0, 0]
    assert len(calls) <= 1 + FAST_REPAIR_CALLS
    # No joint was clamped: the repaired path was filled (scaled to more volume).
    assert calls[-1] == "_plan_rows" and plan.bulge_scale > 1.0


def test_fast_repair_is_bounded_when_it_fails() -> None:
    """A repaired path that no T can time (torque) is left to the refinement, after at most
    FAST_REPAIR_CALLS kernel calls in the repair."""
    kind = DigType.BACKWARD
    planner, calls = _fixed_planner(kind, TORQUE_Y)
    in_repair: list[int] = []
    repair = planner._fast_repair

    def counted(*args: object) -> object:
        start = len(calls)
        outcome = repair(*args)  # type: ignore[arg-type]
        in_repair.append(len(calls) - start)
        return outcome

    planner._fast_repair = counted  # type: ignore[method-assign]
    plan = planner.plan(TORQUE_X[0:3], TORQUE_X[3:6], TORQUE_X[6], kind)
    assert plan.status == PlanStatus.REFINED
    assert _reference(TORQUE_X, kind, plan).feasible[0, 0]
    assert len(in_repair) == 1 and 1 <= in_repair[0] <= FAST_REPAIR_CALLS
    no_refine, _ = _fixed_planner(kind, TORQUE_Y, refine=False)
    with pytest.raises(PlanningError, match=r"fast repair: its path cannot be timed\)"):
        no_refine.plan(TORQUE_X[0:3], TORQUE_X[3:6], TORQUE_X[6], kind)


def test_fast_repair_without_retiming() -> None:
    """With fill and retime off, the repair follows time scaling and retimes its path."""
    kind = DigType.BACKWARD
    planner, calls = _fixed_planner(kind, BOOM_Y, retime=False, refine=False)
    plan = planner.plan(BOOM_X[0:3], BOOM_X[3:6], BOOM_X[6], kind)
    assert plan.status == PlanStatus.REPAIRED
    assert plan.bulge_scale == 1.0
    assert _reference(BOOM_X, kind, plan).feasible[0, 0]
    assert "_front" not in calls and "_plan_rows" not in calls and calls[-1] == "_retime_rows"


def _scipy_nearest(w: np.ndarray, A: np.ndarray, r: np.ndarray) -> tuple[bool, float]:
    """min sum(u^2 / w) subject to A u <= r by scipy's SLSQP: (converged and feasible, the
    minimum)."""
    from scipy.optimize import minimize

    res = minimize(
        lambda u: float(np.sum(u**2 / w)),
        np.zeros(w.size),
        jac=lambda u: 2.0 * u / w,
        constraints=[{"type": "ineq", "fun": lambda u: r - A @ u, "jac": lambda u: -A}],
        method="SLSQP",
        options={"ftol": 1e-12, "maxiter": 200},
    )
    return bool(res.success and np.all(r - A @ res.x >= -1e-9)), float(res.fun)


def test_nearest_point_against_scipy() -> None:
    """The repair's closed-form nearest point against scipy's SLSQP, on seeded random cases of
    its kind: one joint fixed, one violated half-space, two more that may become active."""
    rng = np.random.default_rng(7)
    found = missed = 0
    for case in range(100):
        K = rng.normal(0.0, 5.0, 3)
        w = rng.uniform(0.1, 2.0, 3)
        fixed = int(rng.integers(3))
        w[fixed] = 0.0
        free = np.flatnonzero(w > 0.0)
        A = rng.normal(0.0, 1.0, (3, 3))
        slack = np.concatenate([[-rng.uniform(0.5, 3.0)], rng.uniform(0.0, 3.0, 2)])
        b = A @ K + slack
        got = _nearest(K.tolist(), w.tolist(), [(A[i].tolist(), float(b[i])) for i in range(3)])
        ref_ok, ref_d = _scipy_nearest(w[free], A[:, free], b - A @ K)
        if got is None:
            missed += bool(ref_ok)
            continue
        found += 1
        assert np.all(A @ np.asarray(got) <= b + 1e-9), case
        assert got[fixed] == K[fixed], case
        d_got = float(np.sum((np.asarray(got) - K)[free] ** 2 / w[free]))
        if ref_ok:  # optimal: SLSQP finds no nearer point
            assert d_got <= ref_d * (1.0 + 1e-6) + 1e-9, (case, d_got, ref_d)
    assert found >= 80 and missed <= 5, (found, missed)


# Backward row 28: the boom dips below its limit and V_p is short; no path within the limits
# lies near the answer (the teacher's is elsewhere), and the refinement finds none either.
NO_PATH_X = [-0.13212793389398458, -1.570333786404607, -0.43744894044092186,
             -0.3368390724601505, -1.6213758991393872, -1.1801516381418657, -0.6297843377348948]
NO_PATH_Y = [2.3353719370788895e-05, 1.4795507013332099e-05, -4.2413699702592567e-05,
             8.85538387298584]


@pytest.mark.parametrize("refine_no_path", [False, True])
def test_no_path_is_refused_without_the_refinement(refine_no_path: bool) -> None:
    kind = DigType.BACKWARD
    planner, calls = _fixed_planner(kind, NO_PATH_Y, refine_no_path=refine_no_path)
    refinements: list[object] = []
    refine = planner._refine

    def counted(*args: object) -> object:
        refinements.append(args)
        return refine(*args)  # type: ignore[arg-type]

    planner._refine = counted  # type: ignore[method-assign]
    with pytest.raises(PlanningError, match=r"violates angle_min_boom .*fast repair: no path"):
        planner.plan(NO_PATH_X[0:3], NO_PATH_X[3:6], NO_PATH_X[6], kind)
    assert len(refinements) == int(refine_no_path)
    # plan_into, the repair's calls, the evaluation of the network's answer for the message.
    assert len(calls) <= 2 + FAST_REPAIR_CALLS
