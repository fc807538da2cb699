"""Physics-informed training of the one-shot planner network (Yao 4.3, eq 13-19).

One network per dig type maps ``X = (theta11, theta12, theta13, theta21, theta22, theta23, H)``
to ``Y = (a16, a26, a36, T)``. The loss is Yao eq 19::

    Loss_z = lambda_M Loss_1 + lambda_C (Loss_2 + Loss_3 + Loss_4) + lambda_F Loss_5 + lambda_R R(W)

with every physics term computed differentiably from the predicted ``Y`` by
:class:`rt_runtime.training.physics.TorchPhysics`, the torch twin of the numpy evaluation the PSO
teacher optimises (a test ties the two together):

- Loss_1 (eq 13): mean squared error against the PSO teacher, on standardised targets (below).
- Loss_2 (eq 14): hinge of the arm's limits: joint angle, velocity, acceleration, torque, power
  and the digging time range (eq 12's ``t_min <= T <= t_max`` sits with the kinematic limits).
- Loss_3 (eq 15): hinge of the initial digging angle range.
- Loss_4 (eq 16): hinge of the fill (volume) range.
- Loss_5 (eq 18): the normalised objective of eq 11.
- R(W): the squared L2 norm of the weights (biases excluded).

Beside them (not in the paper), weighted by ``lambda_d``:

- Loss_D, the direction loss: the objective gap of the plan the RUNTIME makes from the
  predicted bulge direction, to first order. The runtime keeps only the direction of
  ``K = -a6 T^6`` (fill and retime, :meth:`rt_runtime.planning.verify.Verifier.plan_into`), and
  fed the teacher's own ``(K, T)`` it reproduces the teacher's objective, so the planned gap is
  entirely the direction error. That gap is linear in the angle (a kink, not a quadratic
  minimum; see :mod:`rt_runtime.training.targets`) and anisotropic, so Loss_1's MSE on
  standardised ``(K, T)`` weighs it badly (design notes, N5). Loss_D is
  ``cap * log1p(cone / cap)`` per sample, ``cone = theta * s(phi)`` from the cost cones that
  :func:`rt_runtime.training.targets.direction_targets` measures with the runtime's own kernel
  before training (16 tilts of 1 deg per sample, seconds), averaged. Tilts the runtime cannot
  plan get a large slope (``dir_infeasible_slope``), so where the teacher sits on theta_p or a
  joint limit the network errs to the plannable side.

Choices where the paper is silent or would not work as printed, each measured on scale_model:

- Parametrisation. The network predicts the standardised ``(K1, K2, K3, T)``, with
  ``K = -a6 T^6`` the sextic's bulge (:mod:`rt_runtime.planning.oneshot`), not ``a6`` itself:
  ``a6`` spans orders of magnitude with ``T`` (``T^6`` from 5 to 10 s is a factor of 64), so an
  MSE on raw ``a6`` weighs long digs to nothing. ``a6 = -K / T^6`` is computed in the graph, and
  the exported model still outputs ``(a16, a26, a36, T)`` (DESIGN.md "Models").
- Loss_1 is a mean rather than eq 13's sum, so its weight does not depend on the batch size.
- The hinges carry a margin (``margin``, in the normalised units of
  :data:`rt_runtime.planning.oneshot.CONSTRAINT_NAMES`): the teacher's optima sit on constraint
  boundaries, and a network that only learns to land on a boundary lands on the wrong side of
  it half of the time. The margin pushes the prediction inside; the runtime's fill and retime
  (:meth:`rt_runtime.planning.verify.Verifier.plan_into`) take the plan back out to the
  boundaries, so a conservative network costs little objective (design notes, N3).
- Optimiser: Adam with a learning rate that decays on plateaus (Yao: mini-batch gradient descent,
  lr 1e-4, which needs thousands of epochs here), judged through an exponential moving average
  of the weights (``ema_decay``): with the direction loss the validation gap of the raw Adam
  iterate jumps by +-0.5 % between scorings (about one validation sample in raw feasibility),
  and early stopping then picks noise; the average is what is scored and kept.
- ``lambda_C`` 40 rather than 20 when the direction loss is on: the direction loss pulls the
  bulge to the teacher's direction, which sits on theta_p or a joint limit in a third of the
  samples, and the doubled hinge weight keeps the raw answers inside (design notes, N5).
- Warm start (``init_checkpoint``): training may continue from a checkpoint, typically one
  trained without the direction loss (``lambda_d = 0``, ``lambda_C = 20``, no average, from
  scratch), fine-tuned with the direction loss; the shipped models' chains of stages are in
  their model cards and the design notes (N6). A checkpoint with narrower hidden layers of the
  same depth is widened without changing its function (new units: zero outgoing weights).
- Early stopping on the targets: every ``eval_every`` epochs the model is scored on a validation
  split of the training data (never on the held-out test set) the way the runtime uses it: the
  network's float32 answers are verified on the runtime's grid (raw feasibility and gap) and
  planned as :class:`rt_runtime.planning.pinn.PinnPlanner` plans them (the path's bulge scaled
  to fill the bucket, then retimed to its smallest feasible T). The score is the raw
  feasibility up to its target, then the planned feasibility up to its target, then the
  planned mean objective gap to the teacher; training stops when all three targets hold for
  ``patience_evals`` consecutive scorings, or when the score has not improved for as many, and
  the best scored weights are kept.
"""

from __future__ import annotations

import copy
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.oneshot import CONSTRAINT_NAMES, DigType
from rt_runtime.rig import Rig, load_rig

FloatArray = NDArray[np.float64]

#: Default hidden layers per dig type: Yao 5.2 (3 x 70 tanh downward, 3 x 60 backward).
PAPER_HIDDEN: dict[DigType, tuple[int, ...]] = {
    DigType.DOWNWARD: (70, 70, 70),
    DigType.BACKWARD: (60, 60, 60),
}
#: Yao's batch sizes (50 downward, 100 backward).
PAPER_BATCH: dict[DigType, int] = {DigType.DOWNWARD: 50, DigType.BACKWARD: 100}

# Column groups of the violation vector for Loss_2..Loss_4.
_LIMIT_COLS = [i for i, n in enumerate(CONSTRAINT_NAMES) if not n.startswith(("theta_p", "volume"))]
_ANGLE_COLS = [i for i, n in enumerate(CONSTRAINT_NAMES) if n.startswith("theta_p")]
_VOLUME_COLS = [i for i, n in enumerate(CONSTRAINT_NAMES) if n.startswith("volume")]

LOSS_NAMES = ("mse", "limits", "theta_p", "volume", "objective", "direction", "total")
_N_PARTS = len(LOSS_NAMES) - 1


@dataclass(frozen=True, slots=True)
class TrainConfig:
    """Settings of one training run.

    Attributes:
        hidden: Hidden layer widths (tanh); empty means the paper's for the dig type.
        epochs: Maximum epochs.
        batch_size: Mini-batch size; 0 means the paper's for the dig type.
        lr: Initial Adam learning rate.
        lambda_m, lambda_c, lambda_f, lambda_r: Weights of eq 19.
        margin: Hinge margin of the constraint losses (normalised units).
        n_samples: Samples per trajectory in the physics losses.
        val_fraction: Part of the training split held out for early stopping.
        eval_every: Epochs between validation scorings.
        target_feasible: Feasibility target of the raw and of the planned answers (as the
            runtime plans them) on the validation split.
        target_gap: Mean objective gap target on the validation split (fraction).
        patience_evals: Scorings without improvement before stopping (and consecutive scorings
            at the targets before stopping early).
        seed: Seed of the initialisation, the split and the batch order.
        lambda_d: Weight of the direction loss (beside eq 19's terms; 0 turns it off): the
            objective gap of the runtime's plan from the predicted bulge direction, to first
            order, from the cost cones of :func:`rt_runtime.training.targets.direction_targets`.
        dir_n: Tilt directions per sample of the cost cone.
        dir_radius_deg: Tilt at which the cone's slopes are measured, degrees.
        dir_cap: Soft cap of the direction loss, ``cap * log1p(gap / cap)`` (the cone is linear
            in the angle; the real gap grows slower beyond a few degrees).
        dir_infeasible_slope: Least cone slope (per rad) of a tilt the runtime cannot plan:
            makes the loss asymmetric where the teacher sits on a path-only limit (theta_p,
            joint range), so the network errs to the plannable side.
        ema_decay: Exponential moving average of the weights per optimiser step (0: off); when
            on, validation, early stopping and the kept weights use the average (the plateau of
            a noisy Adam is averaged out).
        init_checkpoint: Start from this checkpoint's weights and normalisation (same dig
            type, rig and architecture; its dataset need not be this one); "" starts fresh.
    """

    hidden: tuple[int, ...] = ()
    epochs: int = 1500
    batch_size: int = 0
    lr: float = 2e-3
    lambda_m: float = 1.0
    lambda_c: float = 40.0
    lambda_f: float = 1.0
    lambda_r: float = 1e-6
    margin: float = 0.03
    n_samples: int = 101
    val_fraction: float = 0.1
    eval_every: int = 10
    target_feasible: float = 0.95
    target_gap: float = 0.02
    patience_evals: int = 30
    seed: int = 0
    lambda_d: float = 10.0
    dir_n: int = 16
    dir_radius_deg: float = 1.0
    dir_cap: float = 0.1
    dir_infeasible_slope: float = 5.0
    ema_decay: float = 0.995
    init_checkpoint: str = ""

    def validate(self) -> None:
        """Raise ConfigurationError naming the first bad setting."""
        checks = [
            ("epochs", self.epochs >= 1, ">= 1"),
            ("batch_size", self.batch_size >= 0, ">= 0 (0: the paper's)"),
            ("lr", 0.0 < self.lr < 1.0, "in (0, 1)"),
            ("margin", 0.0 <= self.margin < 0.5, "in [0, 0.5)"),
            ("n_samples", self.n_samples >= 11, ">= 11"),
            ("val_fraction", 0.0 < self.val_fraction < 0.5, "in (0, 0.5)"),
            ("eval_every", self.eval_every >= 1, ">= 1"),
            ("patience_evals", self.patience_evals >= 1, ">= 1"),
            ("hidden", all(h >= 1 for h in self.hidden), "widths >= 1"),
            ("dir_n", self.dir_n >= 4, ">= 4"),
            ("dir_radius_deg", 0.0 < self.dir_radius_deg <= 10.0, "in (0, 10] deg"),
            ("dir_cap", self.dir_cap > 0.0, "> 0"),
            ("dir_infeasible_slope", self.dir_infeasible_slope > 0.0, "> 0 per rad"),
            ("ema_decay", 0.0 <= self.ema_decay < 1.0, "in [0, 1) (0: off)"),
        ]
        checks += [
            (name, getattr(self, name) >= 0.0, ">= 0")
            for name in ("lambda_m", "lambda_c", "lambda_f", "lambda_r", "lambda_d")
        ]
        for name, ok, allowed in checks:
            if not ok:
                raise ConfigurationError(
                    f"training setting {name} must be {allowed}; got {getattr(self, name)!r}"
                )


@dataclass(frozen=True, slots=True)
class Normalisation:
    """Affine scaling of inputs and of the internal targets ``(K1, K2, K3, T)``."""

    x_mean: tuple[float, ...]
    x_std: tuple[float, ...]
    z_mean: tuple[float, ...]
    z_std: tuple[float, ...]


@dataclass(slots=True)
class TrainResult:
    """What :func:`train` returns (and saves as a checkpoint)."""

    dig_type: DigType
    rig_name: str
    hidden: tuple[int, ...]
    normalisation: Normalisation
    state_dict: dict[str, Any]
    history: dict[str, list[float]]
    best_epoch: int
    epochs_run: int
    stop_reason: str
    val_feasible: float
    val_gap_mean: float
    train_s: float
    config: TrainConfig
    val_raw_feasible: float = math.nan
    val_raw_gap_mean: float = math.nan
    dataset_meta: dict[str, Any] = field(default_factory=dict)


def build_network(hidden: tuple[int, ...], normalisation: Normalisation) -> Any:
    """The exportable network: standardise X, tanh MLP, de-standardise, ``a6 = -K / T^6``.

    Returns:
        A ``torch.nn.Module`` mapping ``(B, 7)`` float32 to ``(B, 4)`` = (a16, a26, a36, T);
        its ``internal(x)`` gives the standardised ``(K, T)`` prediction for the MSE.
    """
    import torch
    from torch import nn

    class PinnNet(nn.Module):
        x_mean: torch.Tensor
        x_std: torch.Tensor
        z_mean: torch.Tensor
        z_std: torch.Tensor

        def __init__(self) -> None:
            super().__init__()
            layers: list[nn.Module] = []
            width = 7
            for h in hidden:
                layers += [nn.Linear(width, h), nn.Tanh()]
                width = h
            layers.append(nn.Linear(width, 4))
            self.mlp = nn.Sequential(*layers)
            n = normalisation
            self.register_buffer("x_mean", torch.tensor(n.x_mean, dtype=torch.float32))
            self.register_buffer("x_std", torch.tensor(n.x_std, dtype=torch.float32))
            self.register_buffer("z_mean", torch.tensor(n.z_mean, dtype=torch.float32))
            self.register_buffer("z_std", torch.tensor(n.z_std, dtype=torch.float32))

        def internal(self, x: torch.Tensor) -> torch.Tensor:
            return self.mlp((x - self.x_mean) / self.x_std)  # type: ignore[no-any-return]

        def decode(self, z: torch.Tensor) -> torch.Tensor:
            kt = z * self.z_std + self.z_mean
            T = kt[:, 3:4]
            return torch.cat([-kt[:, :3] / T**6, T], dim=1)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return self.decode(self.internal(x))

    return PinnNet()


def _load_widened(net: Any, state: dict[str, Any], seed: int) -> None:
    """Load ``state`` into ``net``, whose hidden layers may be wider, preserving the function.

    Net2Net-style widening: the checkpoint's units keep their weights; each new unit gets small
    random incoming weights (std 0.01) and ZERO outgoing weights, so the widened network
    computes exactly what the checkpoint's did and training starts from there.
    """
    import torch

    gen = torch.Generator().manual_seed(seed + 7919)
    own = net.state_dict()
    with torch.no_grad():
        for name, target in own.items():
            src = state[name]
            if src.shape == target.shape:
                target.copy_(src)
                continue
            if not name.startswith("mlp."):
                raise ConfigurationError(f"init checkpoint tensor {name} has shape {src.shape}")
            fresh = torch.zeros_like(target)
            if name.endswith("weight"):
                fresh.normal_(0.0, 0.01, generator=gen)
                fresh[:, src.shape[1] :] = 0.0  # inputs from new units: zero
            fresh[tuple(slice(0, n) for n in src.shape)] = src
            target.copy_(fresh)
    net.load_state_dict(own)


def _losses(
    net: Any,
    phys: Any,
    x: Any,
    z_target: Any,
    kind: Any,
    cfg: TrainConfig,
    cone: tuple[Any, Any, Any, Any] | None = None,
) -> tuple[Any, list[Any]]:
    """Total loss, the five parts of eq 19 and the direction loss (physics in float64).

    ``cone`` holds the batch's rows of the :class:`~rt_runtime.training.targets.DirectionTargets`
    (u, e1, e2, slopes) as float64 tensors; None (or ``lambda_d = 0``) gives a direction loss of 0.
    """
    import torch

    from rt_runtime.training.targets import cone_gap

    z = net.internal(x)
    loss_mse = torch.mean((z - z_target) ** 2)
    y = net.decode(z).double()
    xd = x.double()
    ev = phys.evaluate(xd[:, 0:3], xd[:, 3:6], xd[:, 6], kind, y[:, :3], y[:, 3])
    v = ev.violations
    hinge = torch.relu(v + cfg.margin)
    loss_lim = hinge[:, _LIMIT_COLS].sum(dim=1).mean()
    loss_ang = hinge[:, _ANGLE_COLS].sum(dim=1).mean()
    loss_vol = hinge[:, _VOLUME_COLS].sum(dim=1).mean()
    loss_obj = ev.objective.mean()
    reg = sum((p**2).sum() for name, p in net.named_parameters() if name.endswith("weight"))
    if cone is not None and cfg.lambda_d > 0.0:
        K = z[:, :3].double() * net.z_std[:3].double() + net.z_mean[:3].double()
        gap = cone_gap(K, *cone)
        loss_dir = (cfg.dir_cap * torch.log1p(gap / cfg.dir_cap)).mean()
    else:
        loss_dir = torch.zeros((), dtype=torch.float64)
    total = (
        cfg.lambda_m * loss_mse
        + cfg.lambda_c * (loss_lim + loss_ang + loss_vol)
        + cfg.lambda_f * loss_obj
        + cfg.lambda_r * reg
        + cfg.lambda_d * loss_dir
    )
    return total, [loss_mse, loss_lim, loss_ang, loss_vol, loss_obj, loss_dir]


def _plan_scores(
    net: Any, verifier: Any, X: FloatArray, teacher_objective: FloatArray, dig_type: DigType
) -> tuple[float, float, float, float]:
    """Raw and planned feasibility and mean objective gap on ``X``, as the runtime judges them.

    The network runs in float32 as exported; its answers are verified on the runtime's grid
    (raw) and filled and retimed as :class:`rt_runtime.planning.pinn.PinnPlanner` does (planned).
    """
    import torch

    from rt_runtime.planning.verify import COL_OBJECTIVE, COL_TOTAL, N_OUT

    with torch.no_grad():
        y = net(torch.tensor(X, dtype=torch.float32)).double().numpy()
    rows = np.concatenate([X, np.full((X.shape[0], 1), float(dig_type)), y], axis=1)
    raw = np.zeros((X.shape[0], N_OUT))
    verifier.evaluate_into(rows, raw)
    planned = np.zeros_like(raw)
    verifier.plan_into(rows, planned, np.zeros((X.shape[0], 4)))
    scale = np.abs(teacher_objective)

    def gap(out: FloatArray) -> float:
        return float(np.mean((out[:, COL_OBJECTIVE] - teacher_objective) / scale))

    return (
        float(np.mean(raw[:, COL_TOTAL] <= 0.0)),
        gap(raw),
        float(np.mean(planned[:, COL_TOTAL] <= 0.0)),
        gap(planned),
    )


def train(
    rig: Rig | str,
    dataset_path: Path,
    dig_type: DigType,
    config: TrainConfig | None = None,
    *,
    progress: bool = True,
    log: Any = None,
) -> TrainResult:
    """Train one network on the feasible training split of a teacher dataset.

    Args:
        rig: The rig (or profile name) the dataset was generated for; must match its metadata.
        dataset_path: The consolidated dataset file of :mod:`rt_runtime.training.dataset`.
        dig_type: Which network.
        config: Settings (defaults: the paper's architecture, measured loss weights).
        progress: Show a progress bar.
        log: Optional callable taking one line of text per validation scoring.

    Returns:
        The trained weights, normalisation, loss history and validation scores.

    Raises:
        ConfigurationError: Bad settings, or a dataset for another rig or dig type.
    """
    import torch

    from rt_runtime.planning.verify import Verifier
    from rt_runtime.training import dataset as ds
    from rt_runtime.training.physics import TorchPhysics

    cfg = config or TrainConfig()
    cfg.validate()
    rig_obj = load_rig(rig) if isinstance(rig, str) else rig
    data = ds.load(dataset_path)
    meta = data.meta
    spec = meta.get("spec", {})
    if spec.get("rig") not in (None, rig_obj.name):
        raise ConfigurationError(
            f"dataset {dataset_path} was generated for rig {spec.get('rig')!r}, "
            f"not {rig_obj.name!r}"
        )
    if spec.get("dig_type") not in (None, dig_type.name.lower()):
        raise ConfigurationError(
            f"dataset {dataset_path} holds {spec.get('dig_type')!r} digs, not "
            f"{dig_type.name.lower()!r}"
        )
    hidden = cfg.hidden or PAPER_HIDDEN[dig_type]
    batch = cfg.batch_size or PAPER_BATCH[dig_type]

    train_idx = np.asarray(data.train_idx)
    if train_idx.size < 4:
        raise ConfigurationError(
            f"dataset {dataset_path} has {train_idx.size} feasible training samples; need >= 4"
        )
    rng = np.random.default_rng(cfg.seed)
    perm = rng.permutation(train_idx)
    n_val = max(2, round(cfg.val_fraction * perm.size))
    val_idx, fit_idx = perm[:n_val], perm[n_val:]

    X = np.asarray(data.X, dtype=np.float64)
    # The internal targets: the teacher's particles (K1, K2, K3, T), stored by the dataset.
    Zt = np.column_stack([data.K_rad, data.T_s])
    norm = Normalisation(
        x_mean=tuple(float(v) for v in X[fit_idx].mean(axis=0)),
        x_std=tuple(float(v) for v in np.maximum(X[fit_idx].std(axis=0), 1e-6)),
        z_mean=tuple(float(v) for v in Zt[fit_idx].mean(axis=0)),
        z_std=tuple(float(v) for v in np.maximum(Zt[fit_idx].std(axis=0), 1e-6)),
    )
    init = None
    if cfg.init_checkpoint:
        init = load_checkpoint(Path(cfg.init_checkpoint))
        if init["dig_type"] != dig_type.name.lower() or init["rig"] != rig_obj.name:
            raise ConfigurationError(
                f"init checkpoint {cfg.init_checkpoint} is for {init['rig']!r} "
                f"{init['dig_type']} digs, not {rig_obj.name!r} {dig_type.name.lower()}"
            )
        narrower = len(init["hidden"]) == len(hidden) and all(
            a <= b for a, b in zip(init["hidden"], hidden, strict=True)
        )
        if not narrower:
            raise ConfigurationError(
                f"init checkpoint {cfg.init_checkpoint} has hidden layers {init['hidden']}; "
                f"it can start {list(hidden)} only with as many layers, none wider"
            )
        norm = Normalisation(**{k: tuple(v) for k, v in init["normalisation"].items()})
    torch.manual_seed(cfg.seed)
    net = build_network(hidden, norm)
    if init is not None:
        _load_widened(net, init["state_dict"], cfg.seed)
    phys = TorchPhysics(rig_obj, n_samples=cfg.n_samples)
    # The judged network: the weights' moving average when ema_decay > 0, else the network.
    judge = copy.deepcopy(net) if cfg.ema_decay > 0.0 else net
    cone_fit: tuple[Any, Any, Any, Any] | None = None
    cone_val: tuple[Any, Any, Any, Any] | None = None
    if cfg.lambda_d > 0.0:
        from rt_runtime.training.targets import direction_targets

        # The cones of the fit and validation samples only (never of the test split).
        used = np.concatenate([fit_idx, val_idx])
        tg = direction_targets(
            rig_obj,
            X[used],
            dig_type,
            np.asarray(data.K_rad, dtype=np.float64)[used],
            np.asarray(data.T_s, dtype=np.float64)[used],
            n_dirs=cfg.dir_n,
            radius_rad=math.radians(cfg.dir_radius_deg),
            infeasible_slope=cfg.dir_infeasible_slope,
        )
        # Rows of the targets are those of `used`: the fit samples', then the validation's.
        cones = [np.asarray(a, dtype=np.float64) for a in (tg.u, tg.e1, tg.e2, tg.slopes)]
        n_fit = fit_idx.size
        u, e1, e2, sl = (torch.tensor(a[:n_fit]) for a in cones)
        cone_fit = (u, e1, e2, sl)
        u, e1, e2, sl = (torch.tensor(a[n_fit:]) for a in cones)
        cone_val = (u, e1, e2, sl)
        if log is not None:
            log(
                f"direction cones: {used.size} samples x {cfg.dir_n} tilts of "
                f"{cfg.dir_radius_deg:g} deg, median slope "
                f"{float(np.median(tg.slopes)) * math.pi / 180.0:.4f} per deg, "
                f"{tg.infeasible_fraction:.1%} of tilts not plannable"
            )

    def tensors(idx: NDArray[np.intp]) -> tuple[Any, Any, Any, FloatArray]:
        x = torch.tensor(X[idx], dtype=torch.float32)
        z = (torch.tensor(Zt[idx]) - torch.tensor(norm.z_mean)) / torch.tensor(norm.z_std)
        kind = torch.full((idx.size,), int(dig_type), dtype=torch.long)
        return x, z.float(), kind, np.asarray(data.objective)[idx]

    x_fit, z_fit, k_fit, _ = tensors(fit_idx)
    x_val, z_val, k_val, obj_val = tensors(val_idx)

    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=8, min_lr=1e-5)

    history: dict[str, list[float]] = {f"train_{n}": [] for n in LOSS_NAMES}
    history.update({f"val_{n}": [] for n in LOSS_NAMES})
    history.update(
        {
            k: []
            for k in (
                "eval_epoch",
                "val_raw_feasible",
                "val_raw_gap_mean",
                "val_feasible",
                "val_gap_mean",
                "lr",
            )
        }
    )
    verifier = Verifier(rig_obj)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.epochs, desc=f"train {dig_type.name.lower()}", unit="epoch")

    best_score = (0.0, 0.0, math.inf)
    best_state = {k: v.clone() for k, v in net.state_dict().items()}
    best_epoch, stale, at_target = 0, 0, 0
    stop_reason = "max_epochs"
    best_feas, best_gap = 0.0, math.inf
    best_raw = (math.nan, math.nan)
    t0 = time.perf_counter()
    epoch = 0
    for epoch in range(1, cfg.epochs + 1):
        net.train()
        order = torch.randperm(
            fit_idx.size, generator=torch.Generator().manual_seed(cfg.seed + epoch)
        )
        sums = np.zeros(len(LOSS_NAMES))
        for start in range(0, fit_idx.size, batch):
            sel = order[start : start + batch]
            cone = None if cone_fit is None else tuple(a[sel] for a in cone_fit)
            total, parts = _losses(net, phys, x_fit[sel], z_fit[sel], k_fit[sel], cfg, cone)
            opt.zero_grad()
            total.backward()
            opt.step()
            if judge is not net:
                with torch.no_grad():
                    for pe, pn in zip(judge.parameters(), net.parameters(), strict=True):
                        pe.mul_(cfg.ema_decay).add_(pn.detach(), alpha=1.0 - cfg.ema_decay)
            w = sel.numel() / fit_idx.size
            sums[:_N_PARTS] += w * np.array([float(p.detach()) for p in parts])
            sums[_N_PARTS] += w * float(total.detach())
        for i, n in enumerate(LOSS_NAMES):
            history[f"train_{n}"].append(float(sums[i]))
        net.eval()
        judge.eval()
        with torch.no_grad():
            total, parts = _losses(judge, phys, x_val, z_val, k_val, cfg, cone_val)
        for i, n in enumerate(LOSS_NAMES[:_N_PARTS]):
            history[f"val_{n}"].append(float(parts[i]))
        history["val_total"].append(float(total))
        if bar is not None:
            bar.update(1)
        if epoch % cfg.eval_every and epoch != cfg.epochs:
            continue
        raw_feas, raw_gap, feas, gap = _plan_scores(judge, verifier, X[val_idx], obj_val, dig_type)
        sched.step(float(total))
        history["eval_epoch"].append(float(epoch))
        history["val_raw_feasible"].append(raw_feas)
        history["val_raw_gap_mean"].append(raw_gap)
        history["val_feasible"].append(feas)
        history["val_gap_mean"].append(gap)
        history["lr"].append(float(opt.param_groups[0]["lr"]))
        if log is not None:
            log(
                f"epoch {epoch}: validation plans feasible {feas:.3f}, gap {gap:+.4f} "
                f"(raw answers {raw_feas:.3f}, {raw_gap:+.4f}); loss {float(total):.4g}, "
                f"lr {opt.param_groups[0]['lr']:.2g}"
            )
        # Score, lexicographic: raw feasibility up to its target, planned feasibility up to its
        # target (both in steps of half a percent), then the planned gap.
        score = (
            -math.floor(min(raw_feas, cfg.target_feasible) * 200.0) / 200.0,
            -math.floor(min(feas, cfg.target_feasible) * 200.0) / 200.0,
            gap,
        )
        if score < best_score:
            best_score, best_epoch, stale = score, epoch, 0
            best_feas, best_gap = feas, gap
            best_raw = (raw_feas, raw_gap)
            best_state = {k: v.clone() for k, v in judge.state_dict().items()}
        else:
            stale += 1
        on_target = min(raw_feas, feas) >= cfg.target_feasible and gap <= cfg.target_gap
        at_target = at_target + 1 if on_target else 0
        if at_target >= cfg.patience_evals:
            stop_reason = "targets_reached"
            break
        if stale >= cfg.patience_evals:
            stop_reason = "no_improvement"
            break
    if bar is not None:
        bar.close()
    net.load_state_dict(best_state)
    return TrainResult(
        dig_type=dig_type,
        rig_name=rig_obj.name,
        hidden=tuple(hidden),
        normalisation=norm,
        state_dict={k: v.detach().cpu() for k, v in net.state_dict().items()},
        history=history,
        best_epoch=best_epoch,
        epochs_run=epoch,
        stop_reason=stop_reason,
        val_feasible=best_feas,
        val_gap_mean=best_gap,
        val_raw_feasible=best_raw[0],
        val_raw_gap_mean=best_raw[1],
        train_s=time.perf_counter() - t0,
        config=cfg,
        dataset_meta={**meta, "path": str(dataset_path)},
    )


def save_checkpoint(result: TrainResult, path: Path) -> None:
    """Save a training result (weights, normalisation, history, settings) with torch.save."""
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": "excavator-rt-pinn-checkpoint/1",
        "dig_type": result.dig_type.name.lower(),
        "rig": result.rig_name,
        "hidden": list(result.hidden),
        "normalisation": asdict(result.normalisation),
        "state_dict": result.state_dict,
        "history": result.history,
        "best_epoch": result.best_epoch,
        "epochs_run": result.epochs_run,
        "stop_reason": result.stop_reason,
        "val_feasible": result.val_feasible,
        "val_gap_mean": result.val_gap_mean,
        "val_raw_feasible": result.val_raw_feasible,
        "val_raw_gap_mean": result.val_raw_gap_mean,
        "train_s": result.train_s,
        "config": asdict(result.config),
        "dataset_meta": json.loads(json.dumps(result.dataset_meta, default=str)),
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint`.

    Raises:
        ConfigurationError: Missing or not a checkpoint of this format.
    """
    import torch

    if not path.is_file():
        raise ConfigurationError(f"checkpoint {path} does not exist; run `excavator-rt train`")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several unrelated types for a bad file
        raise ConfigurationError(f"checkpoint {path} cannot be read: {exc}") from exc
    if not isinstance(payload, dict) or payload.get("format") != "excavator-rt-pinn-checkpoint/1":
        raise ConfigurationError(f"{path} is not an excavator-rt PINN checkpoint")
    return payload


def network_from_checkpoint(payload: dict[str, Any]) -> Any:
    """Rebuild the trained network (eval mode) from a checkpoint payload."""
    norm = Normalisation(**{k: tuple(v) for k, v in payload["normalisation"].items()})
    net = build_network(tuple(payload["hidden"]), norm)
    net.load_state_dict(payload["state_dict"])
    net.eval()
    return net


def plot_losses(history: dict[str, list[float]], path: Path, title: str) -> None:
    """Loss curves in the manner of Yao Fig. 10-11: six panels, training and validation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {
        "mse": "Loss$_1$ (MSE)",
        "limits": "Loss$_2$ (working device constraint)",
        "theta_p": "Loss$_3$ (cutting angle constraint)",
        "volume": "Loss$_4$ (fill factor constraint)",
        "objective": "Loss$_5$ (performance)",
        "total": "Loss$_z$ (all)",
    }
    if history.get("train_direction"):  # older histories have no direction loss
        labels = {**labels, "direction": "Direction (first-order gap)"}
        fig, axes = plt.subplots(2, 4, figsize=(17, 7))
        axes.flat[-1].set_visible(False)
    else:
        fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    for ax, (key, label) in zip(axes.flat, labels.items(), strict=False):
        tr = np.asarray(history[f"train_{key}"])
        va = np.asarray(history[f"val_{key}"])
        ep = np.arange(1, tr.size + 1)
        ax.plot(ep, tr, label="Training")
        ax.plot(ep, va, label="Validation")
        if key in ("limits", "theta_p", "volume") and np.all(np.concatenate([tr, va]) >= 0):
            ax.set_yscale("symlog", linthresh=1e-5)
        ax.set_xlabel("Epochs")
        ax.set_ylabel(label)
        ax.legend()
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
