"""ONNX export of a trained planner network, with its model card (DESIGN.md "Models").

The exported graph is the whole mapping the runtime needs: ``input`` ``(B, 7)`` float32 =
(theta11, theta12, theta13, theta21, theta22, theta23 in rad, H in m) -> standardise -> tanh MLP
-> de-standardise -> ``a6 = -K / T^6`` -> ``output`` ``(B, 4)`` float32 = (a16, a26, a36 in
rad/s^6, T in s). One file, weights inside, a dynamic batch axis.

The model card (JSON beside the model) carries what the runtime checks before it plans with the
model (rig name and planning fingerprint, the model file's SHA-256, the input domain) and what a
researcher wants to know about it (dataset hash and size, training losses, held-out gap to the
PSO teacher, feasibility rate, opset, exporter).
"""

from __future__ import annotations

import datetime
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime.errors import ConfigurationError
from rt_runtime.fileio import atomic_write
from rt_runtime.planning.oneshot import CONSTRAINT_NAMES, DigType, evaluate
from rt_runtime.planning.pinn import CARD_FORMAT, INPUT_NAMES, OUTPUT_NAMES, sha256_file
from rt_runtime.rig import Rig, load_rig

FloatArray = NDArray[np.float64]

INPUT_UNITS = ("rad", "rad", "rad", "rad", "rad", "rad", "m")
OUTPUT_UNITS = ("rad/s^6", "rad/s^6", "rad/s^6", "s")
OPSET = 17
#: Largest relative difference allowed between onnxruntime and torch on the same inputs.
PARITY_TOLERANCE = 1e-5
#: Widening of the domain beyond the training inputs' range, as a fraction of that range.
DOMAIN_MARGIN = 0.01
#: The solution library's trigger (the fill's bulge scale at or above which the runtime tries
#: it) and candidates per try (:mod:`rt_runtime.planning.pinn`, step 4a; k = 2: each candidate
#: costs a plan, and the triggered plans set the p99; design notes, O7c).
LIBRARY_TRIGGER_BULGE_SCALE = 1.3
LIBRARY_K = 2
#: The training problems a library keeps: those whose own network plan (fill and retime, as at
#: run time) scales the bulge by this much or more. A triggered problem's useful neighbours are
#: of that kind (where the teacher has two families of optima); the search then reads ~45 % of
#: the backward rows (less of the cache, which the p50 and p99 show) for the same gap (design
#: notes, O7c). 0 keeps every training problem.
LIBRARY_KEEP_BULGE_SCALE = 1.2


def folded_network(net: Any) -> Any:
    """The trained network with its scalings folded into the first and last layers.

    The same function as ``net`` (the parity check compares them), in fewer graph nodes, which
    is what an onnxruntime call of a small network costs: the input standardisation goes into
    the first layer's weights and bias, the output de-standardisation and the sign of
    ``-K`` into the last one's, and the decode is one Gather, one Pow and one Mul:
    ``y * [T, T, T, T] ** [-6, -6, -6, 0]`` (a Split, Pow, Mul and Concat instead cost ~0.7 us
    more per call in onnxruntime 1.31, measured on this rig PC; the outputs are the same bit
    for bit, ``T ** 0`` being exactly 1).
    """
    import torch
    from torch import nn

    linears = [m for m in net.mlp if isinstance(m, nn.Linear)]
    with torch.no_grad():
        x_mean = net.x_mean.double()
        x_std = net.x_std.double()
        z_mean = net.z_mean.double()
        z_std = net.z_std.double()
        first = linears[0]
        w1 = first.weight.double() / x_std
        b1 = first.bias.double() - w1 @ x_mean
        last = linears[-1]
        sign = torch.tensor([-1.0, -1.0, -1.0, 1.0], dtype=torch.float64)
        wn = last.weight.double() * (z_std * sign)[:, None]
        bn = (last.bias.double() * z_std + z_mean) * sign

    class Folded(nn.Module):
        t_cols: torch.Tensor
        t_powers: torch.Tensor

        def __init__(self) -> None:
            super().__init__()
            layers: list[nn.Module] = []
            for m in net.mlp:
                if isinstance(m, nn.Linear):
                    lin = nn.Linear(m.in_features, m.out_features)
                    lin.weight.data = m.weight.data.clone()
                    lin.bias.data = m.bias.data.clone()
                    layers.append(lin)
                else:
                    layers.append(nn.Tanh())
            self.mlp = nn.Sequential(*layers)
            lin_layers = [m for m in self.mlp if isinstance(m, nn.Linear)]
            lin_layers[0].weight.data = w1.float()
            lin_layers[0].bias.data = b1.float()
            lin_layers[-1].weight.data = wn.float()
            lin_layers[-1].bias.data = bn.float()
            # The decode's constants: T in every column, raised to -6 (the a6 columns) or 0.
            self.register_buffer("t_cols", torch.tensor([3, 3, 3, 3], dtype=torch.int64))
            self.register_buffer("t_powers", torch.tensor([-6.0, -6.0, -6.0, 0.0]))

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            y: torch.Tensor = self.mlp(x)  # (-K, T)
            return y * torch.pow(y[:, self.t_cols], self.t_powers)  # (-K T^-6, T^0 T)

    folded = Folded()
    folded.eval()
    return folded


def export_onnx(net: Any, path: Path) -> None:
    """Write ``net`` (folded, :func:`folded_network`) as a single-file ONNX model.

    Uses the TorchScript-based exporter (``dynamo=False``): for a plain MLP it gives the
    smallest graph (Gemm + Tanh), and it needs neither onnxscript nor a fixed batch size. The
    batch axis is dynamic.
    """
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".onnx.tmp")
    with torch.no_grad():
        torch.onnx.export(
            folded_network(net),
            (torch.zeros(1, 7, dtype=torch.float32),),
            str(tmp),
            input_names=["input"],
            output_names=["output"],
            dynamic_axes={"input": {0: "batch"}, "output": {0: "batch"}},
            opset_version=OPSET,
            dynamo=False,
            external_data=False,
        )
    os.replace(tmp, path)


def onnx_session(path: Path) -> Any:
    """A single-threaded onnxruntime session on ``path`` (for checks, not the hot path)."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def onnx_answers(path: Path, X: FloatArray) -> FloatArray:
    """The exported network's answers ``(N, 4)`` (a16, a26, a36, T) to the problems ``X``,
    staged as float32 as the runtime stages them, returned as float64."""
    x = np.asarray(X, dtype=np.float32)
    return np.asarray(onnx_session(path).run(["output"], {"input": x})[0], dtype=np.float64)


def parity(net: Any, path: Path, X: FloatArray) -> float:
    """Largest relative difference between torch and onnxruntime outputs on ``X``.

    Relative per output column, against the column's largest magnitude (a6 spans orders of
    magnitude within a column, so an element-wise relative error would be dominated by the
    smallest coefficients, which matter least).
    """
    import torch

    x = np.asarray(X, dtype=np.float32)
    with torch.no_grad():
        ref = net(torch.from_numpy(x)).numpy().astype(np.float64)
    got = onnx_answers(path, np.asarray(X, dtype=np.float64))
    scale = np.maximum(np.max(np.abs(ref), axis=0), np.finfo(np.float64).tiny)
    return float(np.max(np.abs(got - ref) / scale))


def holdout_metrics(
    rig: Rig, path: Path, dig_type: DigType, X: FloatArray, teacher_objective: FloatArray
) -> dict[str, Any]:
    """Raw quality of the exported model on held-out problems, judged by the numpy evaluation.

    Returns:
        ``samples``, ``raw_feasible`` (fraction), ``gap_mean`` and ``gap_max`` (objective gap to
        the teacher as a fraction of the teacher's objective, over all samples), and the most
        frequently violated constraints.
    """
    x = np.asarray(X, dtype=np.float64)
    y = onnx_answers(path, x)
    ev = evaluate(rig, x[:, 0:3], x[:, 3:6], x[:, 6], int(dig_type), y[:, None, :3], y[:, None, 3])
    obj = ev.objective[:, 0]
    gap = (obj - teacher_objective) / np.abs(teacher_objective)
    violated = np.sum(ev.violations[:, 0, :] > 0.0, axis=0)
    top = sorted(
        ((CONSTRAINT_NAMES[i], int(c)) for i, c in enumerate(violated) if c), key=lambda t: -t[1]
    )
    return {
        "samples": int(x.shape[0]),
        "raw_feasible": float(np.mean(ev.feasible[:, 0])),
        "gap_mean": float(np.mean(gap)),
        "gap_max": float(np.max(gap)),
        "violated": dict(top[:6]),
    }


def export(
    checkpoint_path: Path,
    out_path: Path,
    *,
    rig: Rig | str | None = None,
    dataset_path: Path | None = None,
    library: bool = False,
    library_keep_scale: float | None = None,
) -> dict[str, Any]:
    """Export a checkpoint to ONNX, check parity, measure held-out quality, write the held-out
    set (and, with ``library``, the solution library) and the card.

    Args:
        checkpoint_path: Written by :func:`rt_runtime.training.train.save_checkpoint`.
        out_path: The ``.onnx`` file; the card goes beside it with the suffix ``.json``.
        rig: The rig (default: the checkpoint's); must match the checkpoint's.
        dataset_path: The dataset the checkpoint was trained on, for the held-out metrics and
            the domain (default: the path recorded in the checkpoint).
        library: Also write the solution library (:func:`_write_library`) and name it in the
            card (None there when no training problem is kept).
        library_keep_scale: The library keeps the training problems whose network plan fills
            to this bulge scale or more (None: :data:`LIBRARY_KEEP_BULGE_SCALE`; 0: all of
            them); finite and >= 0.

    Returns:
        The model card.

    Raises:
        ConfigurationError: Rig mismatch, missing dataset, a keep scale that is not finite
            and >= 0, or parity above :data:`PARITY_TOLERANCE`.
    """
    import torch

    keep = LIBRARY_KEEP_BULGE_SCALE if library_keep_scale is None else float(library_keep_scale)
    if not (math.isfinite(keep) and keep >= 0.0):
        raise ConfigurationError(f"library keep scale must be finite and >= 0; got {keep}")

    from rt_runtime.training import dataset as ds
    from rt_runtime.training.train import load_checkpoint, network_from_checkpoint

    payload = load_checkpoint(checkpoint_path)
    rig_obj = load_rig(payload["rig"]) if rig is None else rig
    rig_obj = load_rig(rig_obj) if isinstance(rig_obj, str) else rig_obj
    if rig_obj.name != payload["rig"]:
        raise ConfigurationError(
            f"checkpoint {checkpoint_path} was trained for rig {payload['rig']!r}, "
            f"not {rig_obj.name!r}"
        )
    dig_type = DigType[payload["dig_type"].upper()]
    ds_path = dataset_path or Path(payload["dataset_meta"].get("path", ""))
    if not ds_path or not Path(ds_path).is_file():
        raise ConfigurationError(
            f"dataset {str(ds_path)!r} not found; pass --data (the dataset directory the model "
            "was trained on)"
        )
    data = ds.load(Path(ds_path))
    if data.meta.get("hash") != payload["dataset_meta"].get("hash"):
        raise ConfigurationError(
            f"dataset {ds_path} (hash {data.meta.get('hash')}) is not the one the checkpoint was "
            f"trained on (hash {payload['dataset_meta'].get('hash')})"
        )

    net = network_from_checkpoint(payload)
    export_onnx(net, out_path)
    X = np.asarray(data.X, dtype=np.float64)
    test_idx = np.asarray(data.test_idx)
    train_idx = np.asarray(data.train_idx)
    worst = parity(net, out_path, X[np.concatenate([train_idx[:256], test_idx])])
    if worst > PARITY_TOLERANCE:
        out_path.unlink(missing_ok=True)
        raise ConfigurationError(
            f"onnxruntime output differs from torch by {worst:.3g} (allowed {PARITY_TOLERANCE})"
        )
    held = holdout_metrics(
        rig_obj, out_path, dig_type, X[test_idx], np.asarray(data.objective)[test_idx]
    )
    # The domain: the training inputs' range widened by DOMAIN_MARGIN of itself on each side
    # (held-out problems drawn from the same sampler fall a hair outside the training range).
    lo = X[train_idx].min(axis=0)
    hi = X[train_idx].max(axis=0)
    lo, hi = lo - DOMAIN_MARGIN * (hi - lo), hi + DOMAIN_MARGIN * (hi - lo)
    hist = payload["history"]
    card: dict[str, Any] = {
        "format": CARD_FORMAT,
        "model_file": out_path.name,
        "model_sha256": sha256_file(out_path),
        "dig_type": dig_type.name.lower(),
        "rig": rig_obj.name,
        "rig_planning_fingerprint": rig_obj.planning_fingerprint,
        "inputs": [{"name": n, "unit": u} for n, u in zip(INPUT_NAMES, INPUT_UNITS, strict=True)],
        "outputs": [
            {"name": n, "unit": u} for n, u in zip(OUTPUT_NAMES, OUTPUT_UNITS, strict=True)
        ],
        "domain": {
            "min": [float(v) for v in lo],
            "max": [float(v) for v in hi],
            "note": f"per-input range of the training inputs widened by {DOMAIN_MARGIN:.0%} of "
            "itself; the runtime refuses inputs outside",
            "sampler": data.meta.get("spec", {}).get("sampler"),
        },
        "dataset": {
            "path": str(ds_path),
            "hash": data.meta.get("hash"),
            "samples": int(X.shape[0]),
            "train": int(train_idx.size),
            "test": int(test_idx.size),
            "seed": data.meta.get("spec", {}).get("seed"),
        },
        "architecture": {
            "hidden": list(payload["hidden"]),
            "activation": "tanh",
            "parametrisation": "standardised (K1, K2, K3, T), K = -a6 T^6; a6 = -K/T^6 in graph",
        },
        "training": {
            "config": payload["config"],
            "epochs_run": payload["epochs_run"],
            "best_epoch": payload["best_epoch"],
            "stop_reason": payload["stop_reason"],
            "train_s": payload["train_s"],
            "val_feasible": payload["val_feasible"],
            "val_gap_mean": payload["val_gap_mean"],
            "final_losses": {
                k: hist[k][payload["best_epoch"] - 1]
                for k in hist
                if k.startswith(("train_", "val_")) and len(hist[k]) >= payload["best_epoch"] > 0
            },
        },
        "heldout": held,
        "heldout_file": _write_heldout(data, out_path),
        "library": (_write_library(data, out_path, rig_obj, dig_type, keep) if library else None),
        "parity_max_rel": worst,
        "opset": OPSET,
        "exporter": f"torch {torch.__version__} torch.onnx.export (TorchScript)",
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    _write_card(out_path.with_suffix(".json"), card)
    return card


def _write_card(path: Path, card: dict[str, Any]) -> None:
    """Write a model card atomically (a reader never sees half a card)."""
    data = (json.dumps(card, indent=2) + "\n").encode()
    atomic_write(path, lambda f: f.write(data))


def _write_heldout(data: Any, model_path: Path) -> dict[str, str]:
    """Write the held-out problems and the teacher's answers beside the model.

    ``<model stem>_heldout.npz`` holds the test split the card's ``heldout`` numbers were
    measured on (``X``, ``Y``, ``objective``, ``T_s``, ``volume_m3``, ``energy_j``), so that
    ``excavator-rt bench pinn`` and the tests can measure the shipped model without the
    dataset.

    Returns:
        The card's ``heldout_file`` entry: the file's name and SHA-256.
    """
    idx = np.asarray(data.test_idx)
    return _write_beside(
        model_path,
        "_heldout.npz",
        X=np.asarray(data.X)[idx],
        Y=np.asarray(data.Y)[idx],
        objective=np.asarray(data.objective)[idx],
        T_s=np.asarray(data.T_s)[idx],
        volume_m3=np.asarray(data.volume_m3)[idx],
        energy_j=np.asarray(data.energy_j)[idx],
    )


def _write_beside(model_path: Path, suffix: str, **arrays: Any) -> dict[str, Any]:
    """Write ``arrays`` atomically to ``<model stem><suffix>`` (compressed npz) beside the model;
    returns the card's entry for the file: its name and SHA-256."""
    out = model_path.with_name(model_path.stem + suffix)
    atomic_write(out, lambda f: np.savez_compressed(f, **arrays))
    return {"name": out.name, "sha256": sha256_file(out)}


def _write_library(
    data: Any, model_path: Path, rig: Rig, dig_type: DigType, keep_scale: float
) -> dict[str, Any] | None:
    """Write the solution library beside the model: the training problems ``X`` whose network
    plan fills to ``keep_scale`` or more (:func:`network_fill_scales`; all of them at 0) and the
    teacher's answers ``Y`` (a16, a26, a36, T), float64 (the held-out split is not in it).

    Returns:
        The card's ``library`` entry: file name, SHA-256, ``rows`` (kept), ``train_rows``,
        ``keep_bulge_scale``, ``trigger_bulge_scale`` and ``k``
        (:data:`LIBRARY_TRIGGER_BULGE_SCALE`, :data:`LIBRARY_K`); None (and no file) when no
        training problem is kept.
    """
    idx = np.asarray(data.train_idx)
    X = np.asarray(data.X, dtype=np.float64)[idx]
    Y = np.asarray(data.Y, dtype=np.float64)[idx]
    if keep_scale > 0.0:
        keep = network_fill_scales(rig, model_path, dig_type, X) >= keep_scale
        X, Y = X[keep], Y[keep]
    if X.shape[0] == 0:  # and no library left from an earlier export beside the model
        model_path.with_name(model_path.stem + "_library.npz").unlink(missing_ok=True)
        return None
    return {
        **_write_beside(model_path, "_library.npz", X=X, Y=Y),
        "rows": int(X.shape[0]),
        "train_rows": int(idx.size),
        "keep_bulge_scale": float(keep_scale),
        "trigger_bulge_scale": LIBRARY_TRIGGER_BULGE_SCALE,
        "k": min(LIBRARY_K, int(X.shape[0])),
        "note": "teacher answers to the training problems whose network plan fills to "
        "keep_bulge_scale or more; the runtime plans the k nearest where the fill scales the "
        "network's bulge by trigger_bulge_scale or more",
    }


def network_fill_scales(rig: Rig, model_path: Path, dig_type: DigType, X: FloatArray) -> FloatArray:
    """The bulge scale ``c`` of the runtime's plan of the network's answer to each problem of
    ``X`` (fill and retime over the default range, as :class:`~rt_runtime.planning.pinn.
    PinnPlanner` plans it before any repair or library step); 0 where that plan fails."""
    from rt_runtime.planning.verify import COL_TOTAL, N_OUT, Verifier, pack_inputs

    x = np.asarray(X, dtype=np.float64)
    n = x.shape[0]
    y = onnx_answers(model_path, x)
    rows = pack_inputs(x[:, 0:3], x[:, 3:6], x[:, 6], int(dig_type), y[:, 0:3], y[:, 3])
    out = np.zeros((n, N_OUT))
    scale = np.zeros(n)
    Verifier(rig).plan_into(rows, out, np.zeros((n, 4)), scale=scale)
    return np.where(out[:, COL_TOTAL] <= 0.0, scale, 0.0)


def record_planned_heldout(rig: Rig, model_dir: Path) -> dict[str, dict[str, Any]]:
    """Plan every held-out problem with the runtime planner; write the figures into the cards.

    Needs both dig types exported into ``model_dir`` (the planner loads both). Adds to each
    card's ``heldout`` a ``planned`` block: ``samples``, ``returned`` and ``refused``
    (fractions), ``gap_mean``/``gap_max`` (returned plans against the teacher, fractions of
    the teacher's objective) and how the plans came about (``status``). The model files do not
    change, so their hashes in the cards stay valid.

    Returns:
        The ``planned`` block per dig type name.
    """
    from rt_runtime.errors import PlanningError
    from rt_runtime.planning.pinn import PinnPlanner

    planner = PinnPlanner(rig, model_dir)
    blocks: dict[str, dict[str, Any]] = {}
    for kind in DigType:
        name = kind.name.lower()
        with np.load(model_dir / f"pinn_{name}_heldout.npz") as z:
            X, teacher = z["X"], z["objective"]
        gaps: list[float] = []
        status: dict[str, int] = {}
        refused = 0
        for x, obj in zip(X, teacher, strict=True):
            try:
                plan = planner.plan(x[0:3], x[3:6], float(x[6]), kind)
            except PlanningError:
                refused += 1
                continue
            gaps.append((plan.verification.objective - obj) / abs(obj))
            status[plan.status.name.lower()] = status.get(plan.status.name.lower(), 0) + 1
        n = int(X.shape[0])
        block = {
            "samples": n,
            "returned": (n - refused) / n,
            "refused": refused / n,
            "gap_mean": float(np.mean(gaps)) if gaps else float("nan"),
            "gap_max": float(np.max(gaps)) if gaps else float("nan"),
            "status": status,
        }
        card_path = model_dir / f"pinn_{name}.json"
        card = json.loads(card_path.read_text())
        card["heldout"]["planned"] = block
        _write_card(card_path, card)
        blocks[name] = block
    return blocks
