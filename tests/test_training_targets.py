"""Direction targets and the direction loss of training (rt_runtime.training.targets)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rt_runtime.errors import ConfigurationError  # noqa: E402
from rt_runtime.planning.oneshot import DigType  # noqa: E402
from rt_runtime.rig import load_rig  # noqa: E402
from rt_runtime.training.physics import TorchPhysics  # noqa: E402
from rt_runtime.training.targets import (  # noqa: E402
    cone_gap,
    direction_targets,
    planned_objective,
    tangent_basis,
)
from rt_runtime.training.train import (  # noqa: E402
    Normalisation,
    TrainConfig,
    _load_widened,
    _losses,
    build_network,
)

RIG = load_rig("scale_model")
HELDOUT = Path(__file__).resolve().parents[1] / "onnx" / "pinn_backward_heldout.npz"


def _heldout(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The first n shipped held-out backward problems: X, teacher K, T, objective."""
    with np.load(HELDOUT) as z:
        X, Y, obj = z["X"][:n], z["Y"][:n], z["objective"][:n]
    T = Y[:, 3]
    return X, -Y[:, :3] * T[:, None] ** 6, T, obj


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_tangent_basis_is_orthonormal_and_right_handed() -> None:
    rng = np.random.default_rng(0)
    u = _unit(np.vstack([rng.normal(size=(50, 3)), np.eye(3), -np.eye(3)]))
    e1, e2 = tangent_basis(u)
    for a, b in ((u, e1), (u, e2), (e1, e2)):
        assert np.max(np.abs(np.sum(a * b, axis=1))) < 1e-12
    for a in (e1, e2):
        assert np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
    assert np.allclose(np.cross(u, e1), e2, atol=1e-12)


def _cone(n_dirs: int = 8) -> tuple[torch.Tensor, ...]:
    u = torch.tensor(_unit(np.array([[0.3, -0.5, 0.8], [-1.0, 0.2, 0.1]])))
    e1, e2 = (torch.tensor(a) for a in tangent_basis(u.numpy()))
    slopes = torch.tensor(np.arange(2 * n_dirs, dtype=np.float64).reshape(2, n_dirs) + 1.0)
    return u, e1, e2, slopes


def test_cone_gap_is_the_sampled_slope_times_the_angle() -> None:
    u, e1, e2, slopes = _cone()
    n_dirs = slopes.shape[1]
    theta = 0.05
    for j in range(n_dirs):
        phi = 2 * math.pi * j / n_dirs
        tilt = math.cos(phi) * e1 + math.sin(phi) * e2
        K = 3.0 * (math.cos(theta) * u + math.sin(theta) * tilt)
        got = cone_gap(K, u, e1, e2, slopes)
        assert torch.allclose(got, theta * slopes[:, j], rtol=1e-9)
    # Half-way between two sampled directions (wrapping from the last to the first): the mean.
    phi = 2 * math.pi * (n_dirs - 0.5) / n_dirs
    K = math.cos(theta) * u + math.sin(theta) * (math.cos(phi) * e1 + math.sin(phi) * e2)
    want = theta * 0.5 * (slopes[:, -1] + slopes[:, 0])
    assert torch.allclose(cone_gap(K, u, e1, e2, slopes), want, rtol=1e-9)
    # The opposite direction is the largest tilt, not a zero (the sign of K matters).
    assert torch.all(cone_gap(-u, u, e1, e2, slopes) > 3.0 * slopes.min(dim=1).values)


def test_cone_gap_is_zero_with_finite_gradient_on_the_teacher_direction() -> None:
    u, e1, e2, slopes = _cone()
    K = (2.0 * u).clone().requires_grad_(True)
    gap = cone_gap(K, u, e1, e2, slopes)
    assert torch.all(gap.abs() < 1e-9)
    gap.sum().backward()
    assert K.grad is not None and bool(torch.isfinite(K.grad).all())


def test_descending_the_direction_loss_finds_the_teacher_direction() -> None:
    u, e1, e2, slopes = _cone()
    K = (u + 0.4 * e1 - 0.3 * e2).clone().requires_grad_(True)
    opt = torch.optim.Adam([K], lr=0.02)
    for _ in range(400):
        opt.zero_grad()
        cone_gap(K, u, e1, e2, slopes).sum().backward()
        opt.step()
    cos = (K.detach() * u).sum(dim=1) / K.detach().norm(dim=1)
    assert torch.all(cos > math.cos(math.radians(1.0)))


def test_direction_targets_on_held_out_problems() -> None:
    X, K, T, teacher = _heldout(6)
    radius = math.radians(1.0)
    tg = direction_targets(RIG, X, DigType.BACKWARD, K, T, n_dirs=8, radius_rad=radius)
    # The runtime reproduces the teacher's objective from the teacher's own (K, T).
    assert np.allclose(tg.base_objective, teacher, rtol=1e-3)
    assert tg.slopes.shape == (6, 8) and np.all(np.isfinite(tg.slopes)) and np.all(tg.slopes >= 0)
    assert np.allclose(tg.u, _unit(K))
    # One slope by hand: tilt toward e2 (phi = pi / 2, index 2 of 8).
    i = 0
    tilt = math.cos(radius) * tg.u[i] + math.sin(radius) * tg.e2[i]
    f = planned_objective(
        RIG, X[i : i + 1], DigType.BACKWARD, tilt[None] * np.linalg.norm(K[i]), T[i : i + 1]
    )[0]
    if np.isfinite(f):
        want = max((f - tg.base_objective[i]) / (abs(tg.base_objective[i]) * radius), 0.0)
        assert tg.slopes[i, 2] == pytest.approx(want, rel=1e-9, abs=1e-12)
    # A tilted direction costs objective: the teacher sits at a kink (module docstring).
    assert np.mean(tg.slopes) > 0.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_dirs": 3}, "n_dirs"),
        ({"radius_rad": 0.0}, "radius_rad"),
        ({"radius_rad": 0.5}, "radius"),
        ({"infeasible_slope": 0.0}, "infeasible_slope"),
    ],
)
def test_direction_targets_rejects_bad_settings(kwargs: dict[str, float], match: str) -> None:
    X, K, T, _ = _heldout(2)
    with pytest.raises(ConfigurationError, match=match):
        direction_targets(RIG, X, DigType.BACKWARD, K, T, **kwargs)  # type: ignore[arg-type]


def test_direction_targets_rejects_a_zero_bulge_and_bad_shapes() -> None:
    X, K, T, _ = _heldout(2)
    with pytest.raises(ConfigurationError, match="non-zero"):
        direction_targets(RIG, X, DigType.BACKWARD, np.zeros_like(K), T)
    with pytest.raises(ConfigurationError, match="must be"):
        direction_targets(RIG, X, DigType.BACKWARD, K[:, :2], T)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("lambda_d", -1.0),
        ("dir_n", 3),
        ("dir_radius_deg", 0.0),
        ("dir_cap", 0.0),
        ("dir_infeasible_slope", 0.0),
        ("ema_decay", 1.0),
    ],
)
def test_train_config_rejects_bad_direction_settings(field: str, value: float) -> None:
    with pytest.raises(ConfigurationError, match=field):
        TrainConfig(**{field: value}).validate()  # type: ignore[arg-type]


def test_losses_add_the_direction_term_beside_eq_19() -> None:
    X, K, T, _ = _heldout(4)
    Z = np.column_stack([K, T])
    norm = Normalisation(
        x_mean=tuple(X.mean(axis=0)),
        x_std=tuple(np.maximum(X.std(axis=0), 1e-6)),
        z_mean=tuple(Z.mean(axis=0)),
        z_std=tuple(np.maximum(Z.std(axis=0), 1e-6)),
    )
    torch.manual_seed(0)
    net = build_network((8,), norm)
    phys = TorchPhysics(RIG, n_samples=21)
    tg = direction_targets(RIG, X, DigType.BACKWARD, K, T, n_dirs=4)
    cone = tuple(torch.tensor(a) for a in (tg.u, tg.e1, tg.e2, tg.slopes))
    x = torch.tensor(X, dtype=torch.float32)
    z = ((torch.tensor(Z) - torch.tensor(norm.z_mean)) / torch.tensor(norm.z_std)).float()
    kind = torch.full((4,), int(DigType.BACKWARD), dtype=torch.long)
    cfg_off = TrainConfig(lambda_d=0.0)
    cfg_on = TrainConfig(lambda_d=2.0)
    total_off, parts_off = _losses(net, phys, x, z, kind, cfg_off, cone)
    total_on, parts_on = _losses(net, phys, x, z, kind, cfg_on, cone)
    assert len(parts_on) == 6 and float(parts_off[5]) == 0.0
    # The five eq-19 parts do not change; the total gains lambda_d times the direction loss.
    for a, b in zip(parts_off[:5], parts_on[:5], strict=True):
        assert float(a.detach()) == pytest.approx(float(b.detach()), rel=1e-12)
    assert float(parts_on[5].detach()) > 0.0
    d = float(parts_on[5].detach())
    assert float(total_on.detach()) == pytest.approx(float(total_off.detach()) + 2.0 * d, rel=1e-9)
    total_on.backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)


def test_widening_a_checkpoint_keeps_its_function() -> None:
    norm = Normalisation(
        x_mean=(0.0,) * 7, x_std=(1.0,) * 7, z_mean=(0.1, -0.2, 0.3, 7.0), z_std=(1.0,) * 4
    )
    torch.manual_seed(1)
    small = build_network((5, 6), norm)
    big = build_network((9, 6), norm)
    _load_widened(big, small.state_dict(), seed=0)
    x = torch.randn(32, 7)
    with torch.no_grad():
        assert torch.allclose(small(x), big(x), rtol=1e-5, atol=1e-6)
    # The new units are wired in (non-zero incoming weights), ready to learn.
    first = big.mlp[0].weight.detach()
    assert float(first[5:].abs().sum()) > 0.0
