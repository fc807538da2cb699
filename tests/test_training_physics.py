"""Torch port of the one-shot evaluation: parity with numpy, finite gradients, gradient check."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rt_runtime import kinematics  # noqa: E402
from rt_runtime.errors import ConfigurationError, PlanningError  # noqa: E402
from rt_runtime.planning import oneshot  # noqa: E402
from rt_runtime.planning.oneshot import CONSTRAINT_NAMES, DigType  # noqa: E402
from rt_runtime.rig import Rig, load_rig  # noqa: E402
from rt_runtime.training.physics import (  # noqa: E402
    TorchEvaluation,
    TorchPhysics,
    a6_from_particle,
)

RIG = load_rig("scale_model")
FIELDS = tuple(f.name for f in dataclasses.fields(TorchEvaluation))
# Surface offsets (m, added to H) that reach every branch of the entry angle and the area:
# start on the surface, 1.5 mm above it (just outside the 1 mm start tolerance) and 3 cm above
# it (entry on a later segment), 1 cm below it, and a path that never enters the material.
H_OFFSETS_M = (0.0, -0.0015, -0.03, 0.01, -5.0)


def _variant_rig(rig: Rig) -> Rig:
    """Every constant the evaluation reads changed, so a hard-coded scale-model value shows."""
    assert rig.planning is not None
    links = tuple(
        dataclasses.replace(
            lk,
            length_m=lk.length_m * 1.05,
            mass_kg=lk.mass_kg * f,
            com_m=(lk.com_m[0] * 0.9, lk.com_m[1] + 0.01),
            inertia_kgm2=lk.inertia_kgm2 * 1.3 + 0.01,
        )
        for lk, f in zip(rig.links, (1.7, 0.6, 2.3), strict=True)
    )
    joints = tuple(
        dataclasses.replace(
            j,
            velocity_max_rad_s=j.velocity_max_rad_s * 1.2,
            acceleration_max_rad_s2=j.acceleration_max_rad_s2 * 0.8,
            torque_max_nm=j.torque_max_nm * 0.7,
        )
        for j in rig.joints
    )
    p = rig.planning
    planning = dataclasses.replace(
        p,
        t_min_s=4.0,
        t_max_s=9.0,
        volume_min_m3=p.volume_min_m3 * 0.9,
        volume_max_m3=p.volume_max_m3 * 1.2,
        energy_min_j=p.energy_min_j * 1.5,
        energy_max_j=p.energy_max_j * 0.8,
        power_max_w=p.power_max_w * 0.9,
        weights=(0.2, 0.5, 0.3),
        theta_p_downward_rad=(p.theta_p_downward_rad[0] + 0.05, p.theta_p_downward_rad[1] + 0.1),
        theta_p_backward_rad=(p.theta_p_backward_rad[0] - 0.05, p.theta_p_backward_rad[1] + 0.1),
    )
    soil = dataclasses.replace(
        rig.soil, yao=dataclasses.replace(rig.soil.yao, k0_n_m2=rig.soil.yao.k0_n_m2 * 1.6, mu=0.3)
    )
    return dataclasses.replace(
        rig,
        links=links,
        joints=joints,
        planning=planning,
        soil=soil,
        bucket=dataclasses.replace(rig.bucket, width_m=0.27),
        gravity_m_s2=9.7,
    )


def _case(
    rig: Rig, n: int, dig_type: DigType, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` problems per surface offset with random particles inside the search bounds."""
    problems = oneshot.sample_problems(rig, n, dig_type, seed=seed)
    qs = np.array([p.q_start_rad for p in problems] * len(H_OFFSETS_M))
    qe = np.array([p.q_end_rad for p in problems] * len(H_OFFSETS_M))
    h = np.concatenate([[p.surface_y_m + off for p in problems] for off in H_OFFSETS_M])
    kind = np.full(h.shape, int(dig_type))
    lo, hi = oneshot.search_bounds(rig)
    X = np.random.default_rng(seed + 1000).uniform(lo, hi, size=(h.size, 4))
    a6, T = oneshot.a6_from_particle(X)
    return qs, qe, h, kind, a6, T


def _assert_parity(
    rig: Rig,
    case: tuple[np.ndarray, ...],
    dtype: torch.dtype,
    rel: float,
) -> dict[str, float]:
    """Every field of torch against numpy within ``rel`` of (|value| + the field's largest).

    Returns the largest error per field relative to the field's largest magnitude.
    """
    qs, qe, h, kind, a6, T = case
    ref = oneshot.evaluate(rig, qs, qe, h, kind, a6[:, None], T[:, None])
    got = TorchPhysics(rig, dtype=dtype).evaluate(
        *(torch.from_numpy(v) for v in (qs, qe, h, kind, a6, T))
    )
    worst = {}
    for name in FIELDS:
        n = getattr(ref, name)[:, 0]
        t = getattr(got, name).detach().to(torch.float64).numpy()
        assert t.shape == n.shape, name
        scale = float(np.max(np.abs(n))) or 1.0
        err = np.abs(t - n)
        bad = err > rel * (np.abs(n) + scale)
        if np.any(bad):
            i = int(np.argwhere(bad)[0][0])
            pytest.fail(
                f"{name} differs at row {i}: torch {t[i]} numpy {n[i]} for q_start={qs[i]}, "
                f"q_end={qe[i]}, H={h[i]}, type={kind[i]}, a6={a6[i]}, T={T[i]}"
            )
        worst[name] = float(np.max(err)) / scale
    return worst


@pytest.mark.parametrize("dig_type", list(DigType))
def test_float64_matches_numpy_on_random_digs(dig_type: DigType) -> None:
    case = _case(RIG, 40, dig_type, seed=7)
    worst = _assert_parity(RIG, case, torch.float64, rel=1e-10)
    print(f"{dig_type.name} float64 worst error / field scale:", worst)


@pytest.mark.parametrize("dig_type", list(DigType))
def test_float32_matches_numpy_to_single_precision(dig_type: DigType) -> None:
    case = _case(RIG, 20, dig_type, seed=8)
    worst = _assert_parity(RIG, case, torch.float32, rel=3e-4)
    print(f"{dig_type.name} float32 worst error / field scale:", worst)


def test_variant_rig_matches_numpy() -> None:
    variant = _variant_rig(RIG)
    for dig_type in DigType:
        case = _case(variant, 15, dig_type, seed=9)
        _assert_parity(variant, case, torch.float64, rel=1e-10)
    # The variant really moves every output group: a constant copied from the scale model
    # instead of read from the rig would not have passed the parity above.
    case = _case(RIG, 5, DigType.DOWNWARD, seed=10)
    args = [torch.from_numpy(v) for v in case]
    base = TorchPhysics(RIG).evaluate(*args)
    other = TorchPhysics(variant).evaluate(*args)
    for name in ("energy_j", "peak_torque_nm", "volume_m3", "objective", "violations"):
        assert not torch.allclose(getattr(base, name), getattr(other, name)), name


def test_dig_type_accepts_long_float_and_scalar() -> None:
    qs, qe, h, kind, a6, T = (torch.from_numpy(v) for v in _case(RIG, 3, DigType.BACKWARD, 11))
    phys = TorchPhysics(RIG)
    ref = phys.evaluate(qs, qe, h, kind, a6, T).violations
    for k in (kind.to(torch.float64), int(DigType.BACKWARD), torch.tensor(1)):
        assert torch.equal(phys.evaluate(qs, qe, h, k, a6, T).violations, ref)
    down = phys.evaluate(qs, qe, h, DigType.DOWNWARD, a6, T).violations
    assert not torch.equal(down[:, 16:18], ref[:, 16:18])
    assert torch.equal(down[:, :16], ref[:, :16])


def _degenerate_inputs() -> tuple[torch.Tensor, ...]:
    """Edge cases: a motionless path (q_start == q_end, K = 0) just below the surface, so the
    entry direction is (0, 0); the same path exactly on the surface; a start exactly on the
    surface (H from forward kinematics) with a moving path; one far above the material."""
    p = oneshot.sample_problems(RIG, 1, DigType.DOWNWARD, seed=3)[0]
    q0 = np.array(p.q_start_rad)
    y0 = float(kinematics.forward(RIG, q0)[1])
    qs = np.stack([q0, q0, q0, q0])
    qe = np.stack([q0, q0, np.array(p.q_end_rad), np.array(p.q_end_rad)])
    h = np.array([y0 + 1e-4, y0, y0, y0 - 5.0])
    a6 = np.stack([np.zeros(3), np.zeros(3), np.full(3, -1e-5), np.full(3, 2e-5)])
    T = np.array([6.0, 6.0, 7.0, 8.0])
    return tuple(torch.from_numpy(v) for v in (qs, qe, h, np.zeros(4, dtype=np.int64), a6, T))


def _backward_all(phys: TorchPhysics, inputs: tuple[torch.Tensor, ...]) -> list[torch.Tensor]:
    """Gradients of the sum of every output field w.r.t. poses, H, a6 and T."""
    qs, qe, h, kind, a6, T = (v.detach().clone() for v in inputs)
    leaves = [qs, qe, h, a6, T]
    for v in leaves:
        v.requires_grad_(True)
    ev = phys.evaluate(qs, qe, h, kind, a6, T)
    for name in FIELDS:
        assert torch.isfinite(getattr(ev, name)).all(), name
    sum(getattr(ev, name).sum() for name in FIELDS).backward()
    return [v.grad for v in leaves]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gradients_are_finite_on_random_and_degenerate_inputs(dtype: torch.dtype) -> None:
    phys = TorchPhysics(RIG, dtype=dtype)
    random = tuple(
        torch.from_numpy(np.concatenate(parts))
        for parts in zip(*(_case(RIG, 8, t, seed=12) for t in DigType), strict=True)
    )
    for inputs in (random, _degenerate_inputs()):
        grads = _backward_all(phys, inputs)
        for name, g in zip(("q_start", "q_end", "H", "a6", "T"), grads, strict=True):
            assert g is not None and torch.isfinite(g).all(), f"{name}: {g}"
    # The motionless path just below the surface enters with direction (0, 0): theta_p is
    # numpy's atan2(-0, 0) = 0 and carries no gradient.
    qs, qe, h, kind, a6, T = _degenerate_inputs()
    ev = TorchPhysics(RIG).evaluate(qs, qe, h, kind, a6, T)
    ref = oneshot.evaluate(
        RIG, qs.numpy(), qe.numpy(), h.numpy(), 0, a6.numpy()[:, None], T.numpy()[:, None]
    )
    # Row 1 lies on the surface at every sample, where rounding alone decides whether it is
    # below (in numpy as here): no parity there.
    rows = [0, 2, 3]
    np.testing.assert_allclose(ev.theta_p_rad.numpy()[rows], ref.theta_p_rad[rows, 0], atol=1e-12)
    assert ev.theta_p_rad[0] == 0.0
    assert ev.theta_p_rad[3] == -0.5 * math.pi


def test_gradient_check_on_objective_and_violations() -> None:
    # Two problems: a downward dig from the surface (entry direction J(q0) a3) and a backward
    # dig from 1 cm above it (entry on a sampled segment). Variables are the particle
    # (K, T), the surface H and the exit pose; outputs the objective, the quantities it is
    # made of, and every violation (max/abs kinks are not met at these points).
    down = oneshot.sample_problems(RIG, 1, DigType.DOWNWARD, seed=21)[0]
    back = oneshot.sample_problems(RIG, 1, DigType.BACKWARD, seed=22)[0]
    qs = torch.tensor([down.q_start_rad, back.q_start_rad], dtype=torch.float64)
    kind = torch.tensor([0, 1])
    K = torch.tensor([[2.0, -3.0, 4.0], [-2.0, 3.0, 0.5]], dtype=torch.float64)
    T = torch.tensor([6.5, 7.5], dtype=torch.float64)
    h = torch.tensor([down.surface_y_m, back.surface_y_m - 0.01], dtype=torch.float64)
    qe = torch.tensor([down.q_end_rad, back.q_end_rad], dtype=torch.float64)
    phys = TorchPhysics(RIG, n_samples=31)

    def f(
        K: torch.Tensor, T: torch.Tensor, h: torch.Tensor, qe: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        a6, T_s = a6_from_particle(torch.cat([K, T[:, None]], dim=-1))
        ev = phys.evaluate(qs, qe, h, kind, a6, T_s)
        return ev.objective, ev.energy_j, ev.volume_m3, ev.theta_p_rad, ev.violations

    inputs = tuple(v.clone().requires_grad_(True) for v in (K, T, h, qe))
    ev = f(*inputs)
    # Both entry branches are really taken, and the path is inside the material.
    assert torch.all(ev[2] > 0.0) and torch.all(ev[3] > -0.5 * math.pi)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_particle_conversion_matches_numpy() -> None:
    x = np.random.default_rng(1).uniform(*oneshot.search_bounds(RIG), size=(5, 4))
    a6, T = a6_from_particle(torch.from_numpy(x))
    ref_a6, ref_T = oneshot.a6_from_particle(x)
    np.testing.assert_allclose(a6.numpy(), ref_a6, rtol=1e-15)
    np.testing.assert_array_equal(T.numpy(), ref_T)


def test_invalid_input_and_configuration_raise() -> None:
    qs, qe, h, kind, a6, T = _case(RIG, 1, DigType.DOWNWARD, seed=2)
    args = [torch.from_numpy(v[:2]) for v in (qs, qe, h, kind, a6, T)]
    phys = TorchPhysics(RIG)
    with pytest.raises(ValueError, match=r"a6 must have shape \(2, 3\)"):
        phys.evaluate(*args[:4], args[4][:, :2], args[5])
    with pytest.raises(ValueError, match="T_s must have shape"):
        phys.evaluate(*args[:5], args[5][:, None])
    with pytest.raises(PlanningError, match="T_s must be > 0"):
        phys.evaluate(*args[:5], -args[5])
    with pytest.raises(PlanningError, match="surface_y_m must be finite"):
        phys.evaluate(args[0], args[1], args[2] * math.nan, *args[3:])
    with pytest.raises(ConfigurationError, match="planning"):
        TorchPhysics(dataclasses.replace(RIG, planning=None))
    with pytest.raises(ConfigurationError, match="n_samples"):
        TorchPhysics(RIG, n_samples=1)
    with pytest.raises(ConfigurationError, match="floating-point"):
        TorchPhysics(RIG, dtype=torch.int64)
    ev = phys.evaluate(*args)
    assert ev.violations.shape == (2, len(CONSTRAINT_NAMES))
    assert torch.equal(ev.feasible, ev.total_violation <= 0.0)


def test_runtime_modules_do_not_import_torch() -> None:
    # Every module of rt_runtime outside rt_runtime.training, imported in a fresh interpreter
    # that refuses torch. A module failing for another reason is its own tests' business.
    code = (
        "import importlib, importlib.abc, pkgutil, sys\n"
        "class NoTorch(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch' or name.startswith('torch.'):\n"
        "            raise RuntimeError('torch imported')\n"
        "sys.meta_path.insert(0, NoTorch())\n"
        "import rt_runtime\n"
        "for m in pkgutil.walk_packages(rt_runtime.__path__, 'rt_runtime.'):\n"
        "    if m.name.startswith('rt_runtime.training'):\n"
        "        continue\n"
        "    try:\n"
        "        importlib.import_module(m.name)\n"
        "    except RuntimeError as exc:\n"
        "        if 'torch imported' in str(exc):\n"
        "            sys.exit(f'{m.name} imports torch')\n"
        "    except Exception:\n"
        "        pass\n"
        "assert 'torch' not in sys.modules\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
