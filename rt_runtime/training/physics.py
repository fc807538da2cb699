"""Differentiable torch port of the one-shot dig evaluation, for physics-informed training.

The PINN of Yao 4.3 (eq 13-19) predicts ``(a16, a26, a36, T)`` per problem; its physics losses
need the objective and the constraint violations of that prediction as differentiable
functions of it. :class:`TorchPhysics` computes exactly what
:func:`rt_runtime.planning.oneshot.evaluate` computes, through the same formulas, for one
candidate per problem (numpy's candidate axis P squeezed): the sextic sampled on a uniform grid
(:mod:`rt_runtime.trajectory.sextic`), the tip state (:func:`rt_runtime.kinematics.tip_state`),
Yao's digging resistance with its speed regularisation (:func:`rt_runtime.soil.yao_resistance`),
the closed-form inverse dynamics (:func:`rt_runtime.dynamics.inverse_dynamics`), positive joint
power and its trapezoid energy, the excavated area, the entry angle theta_p, eq 11 and the 22
normalised violations of eq 12 in :data:`~rt_runtime.planning.oneshot.CONSTRAINT_NAMES` order.
``tests/test_training_physics.py`` holds the two to ~1e-12 relative in float64.

Where numpy selects (argmax, where, clip, max, abs), the torch code takes the same values and
the gradient flows through the selected elements; at kinks (max ties, abs or max(., 0) at 0)
it is a subgradient. Three places would give NaN gradients with the plain formula and use the
"safe where" pattern instead (compute on a safe argument, then select):

- the soil's ``v / max(|v|, reg)``: ``|v|`` is 0 at both ends of every rest-to-rest sample grid
  and the gradient of ``hypot`` there is 0/0, so the clamp is applied to ``|v|^2`` before the
  square root (same value, zero gradient below ``reg``);
- the entry angle's ``atan2(-dy, |dx|)`` at ``(0, 0)`` (a motionless path, or a start whose
  cubic term vanishes): its value is kept, its gradient is 0 there;
- the excavated area's ``max(d0, d1) / (|d0| + |d1|)``: the denominator is only used where it
  is positive, otherwise 1 (as in numpy).

A start within 1 mm of the surface counts as an entry (``oneshot._entry_angle``), so whether
the first sample lies a last bit below H, rounding noise in which torch and numpy differ, decides
nothing.

Everything is vectorised over problems and samples (no Python loop over either). The gradient
with respect to ``a6`` is about ``T^6`` (~1e5) times larger than that with respect to the shape
``K = -a6 T^6``; a network should predict a scaled quantity (:func:`a6_from_particle` maps the
optimiser's particle ``(K1, K2, K3, T)``).

Outside the runtime: this module imports torch and belongs to training only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from rt_runtime.dynamics import _Chain
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning.oneshot import (
    CONSTRAINT_NAMES,
    DEFAULT_SAMPLES,
    DigType,
    require_planning,
)
from rt_runtime.rig import Rig
from rt_runtime.soil import DEFAULT_SPEED_REG_M_S

# theta_p of a dig that starts within this height of the surface (or below it) is taken at
# t = 0 from J(q0) a3 (oneshot._entry_angle).
_AT_START_TOL_M = 1e-3


@dataclass(frozen=True, slots=True)
class TorchEvaluation:
    """One candidate per problem: :class:`~rt_runtime.planning.oneshot.Evaluation` with P squeezed.

    Tensors are ``(B,)`` unless noted, in the evaluator's dtype, attached to the autograd graph
    of the inputs.

    Attributes:
        T_s: Digging time.
        volume_m3: Excavated volume V_p.
        energy_j: Energy W_E (integral of the positive joint powers).
        theta_p_rad: Initial digging angle.
        peak_power_w: Largest total positive power.
        peak_torque_nm: Largest |torque| per joint, ``(B, 3)``.
        objective: Yao eq 11.
        violations: Signed normalised constraint values ``(B, 22)``, names in
            :data:`~rt_runtime.planning.oneshot.CONSTRAINT_NAMES`; <= 0 is satisfied.
        total_violation: Sum of the positive parts of ``violations``.
    """

    T_s: Tensor
    volume_m3: Tensor
    energy_j: Tensor
    theta_p_rad: Tensor
    peak_power_w: Tensor
    peak_torque_nm: Tensor
    objective: Tensor
    violations: Tensor
    total_violation: Tensor

    @property
    def feasible(self) -> Tensor:
        """Whether every constraint holds, ``(B,)`` bool (no gradient)."""
        return self.total_violation.detach() <= 0.0


def a6_from_particle(x: Tensor) -> tuple[Tensor, Tensor]:
    """``(a6 (..., 3) rad/s^6, T_s (...))`` from particles ``(K1, K2, K3, T_s)`` ``(..., 4)``.

    The torch twin of :func:`rt_runtime.planning.oneshot.a6_from_particle`; differentiable.
    """
    T = x[..., 3]
    return -x[..., :3] / T[..., None] ** 6, T


def _sextic_basis(n_samples: int) -> np.ndarray:
    """``(2, 3, m)``: value, first and second s-derivative of q(s) and p(s) on the grid.

    The corrected Yao eq 10 (DESIGN.md errata) written in normalised time:
    ``theta = theta1 + D q(s) + K p(s)`` with ``q = 10s^3 - 15s^4 + 6s^5``,
    ``p = s^3 (1 - s)^3`` and ``K = -a6 T^6``. Built from the monomial coefficients in float64
    whatever the evaluator's dtype.
    """
    s = np.linspace(0.0, 1.0, n_samples, dtype=np.float64)
    k = np.arange(7.0)
    mono = np.empty((3, n_samples, 7))  # d^j/ds^j s^k
    for j in range(3):
        factor = np.ones(7)
        for i in range(j):
            factor = factor * (k - i)
        mono[j] = factor * s[:, None] ** np.maximum(k - j, 0.0)
    q_coef = np.array([0.0, 0.0, 0.0, 10.0, -15.0, 6.0, 0.0])
    p_coef = np.array([0.0, 0.0, 0.0, 1.0, -3.0, 3.0, -1.0])
    return np.stack([mono @ q_coef, mono @ p_coef])


class TorchPhysics:
    """Differentiable one-shot evaluation of sextic digs on one rig (see the module docstring).

    Construction copies every rig constant the evaluation needs (joint limits, link lengths,
    the mass parameters of the closed-form dynamics, soil, bucket width, planning thresholds)
    and precomputes the sample grid and the sextic basis; :meth:`evaluate` only does tensor
    arithmetic on them.

    Args:
        rig: The rig; needs a ``[planning]`` table.
        n_samples: Samples per trajectory, uniform in time, ends included (numpy's
            ``n_samples``), >= 2.
        dtype: ``torch.float64`` (parity with numpy to ~1e-12) or ``torch.float32``.
        device: Where the constants live; inputs are moved there.

    Raises:
        ConfigurationError: The rig has no planning table, ``n_samples < 2``, or ``dtype`` is
            not a floating-point dtype.
    """

    def __init__(
        self,
        rig: Rig,
        n_samples: int = DEFAULT_SAMPLES,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        planning = require_planning(rig)
        if isinstance(n_samples, bool) or not isinstance(n_samples, int) or n_samples < 2:
            raise ConfigurationError(f"n_samples must be an int >= 2; got {n_samples!r}")
        if not dtype.is_floating_point:
            raise ConfigurationError(
                f"dtype must be a floating-point torch dtype (float64 or float32); got {dtype}"
            )
        self.rig = rig
        self.n_samples = n_samples
        self.dtype = dtype
        self.device = torch.device(device) if device is not None else torch.device("cpu")

        def vec(values: np.ndarray) -> Tensor:
            return torch.tensor(np.array(values, np.float64), device=self.device, dtype=dtype)

        self._basis = vec(_sextic_basis(n_samples))  # (2, 3, m)
        self._s = vec(np.linspace(0.0, 1.0, n_samples, dtype=np.float64))
        self._q_min = vec(rig.q_min_rad)
        self._q_max = vec(rig.q_max_rad)
        self._span = vec(rig.q_max_rad - rig.q_min_rad)
        self._qd_max = vec(rig.qd_max_rad_s)
        self._qdd_max = vec(rig.qdd_max_rad_s2)
        self._tau_max = vec(rig.tau_max_nm)
        # Scalars stay Python floats: they broadcast into any dtype without a copy.
        self._lengths = tuple(float(v) for v in rig.lengths_m)
        self._lengths_t = vec(rig.lengths_m)
        # The dynamics module's own mass parameters: one definition of the chain for both.
        self._chain = _Chain(rig)
        self._soil_gain = rig.soil.yao.k0_n_m2 * rig.bucket.width_m
        # 0-d tensors where torch.where selects between constants: Python scalars there would
        # come back in torch's default dtype (float32) and round mu and the bounds.
        self._mu = vec(np.array([rig.soil.yao.mu, -rig.soil.yao.mu]))
        self._reg2 = DEFAULT_SPEED_REG_M_S**2
        self._width = rig.bucket.width_m
        self._planning = planning
        self._theta_p_down = vec(np.array(planning.theta_p_downward_rad))
        self._theta_p_back = vec(np.array(planning.theta_p_backward_rad))

    def evaluate(
        self,
        q_start_rad: Tensor,
        q_end_rad: Tensor,
        surface_y_m: Tensor,
        dig_type: Tensor | int,
        a6: Tensor,
        T_s: Tensor,
    ) -> TorchEvaluation:
        """Evaluate one candidate sextic dig per problem, differentiably.

        Args:
            q_start_rad: Entry poses ``(B, 3)``.
            q_end_rad: Exit poses ``(B, 3)``.
            surface_y_m: Material surface height H per problem ``(B,)``, m.
            dig_type: :class:`~rt_runtime.planning.oneshot.DigType` per problem ``(B,)`` (long
                or float, 0 downward, anything else backward, as numpy) or one for all.
            a6: Sixth-order coefficients ``(B, 3)``, rad/s^6.
            T_s: Digging times ``(B,)``, s, > 0.

        Inputs are converted to the evaluator's dtype and device (differentiably).

        Returns:
            The :class:`TorchEvaluation`; gradients reach every floating-point input.

        Raises:
            ValueError: A shape other than those above (B taken from ``T_s``).
            PlanningError: A non-finite input or ``T_s <= 0`` (numpy's sextic raises the same).
        """
        raw_qs = torch.as_tensor(q_start_rad)
        raw_h = torch.as_tensor(surface_y_m)
        qs, qe, h, a6_, T = (
            torch.as_tensor(v).to(device=self.device, dtype=self.dtype)
            for v in (raw_qs, q_end_rad, raw_h, a6, T_s)
        )
        if T.ndim != 1:
            raise ValueError(f"T_s must have shape (B,); got {tuple(T.shape)}")
        B = T.shape[0]
        for name, v, shape in (
            ("q_start_rad", qs, (B, 3)),
            ("q_end_rad", qe, (B, 3)),
            ("surface_y_m", h, (B,)),
            ("a6", a6_, (B, 3)),
        ):
            if tuple(v.shape) != shape:
                raise ValueError(f"{name} must have shape {shape}; got {tuple(v.shape)}")
        kind = torch.as_tensor(dig_type, device=self.device)
        if kind.ndim > 1 or (kind.ndim == 1 and kind.shape[0] != B):
            raise ValueError(f"dig_type must have shape (B,) = ({B},) or (); got {kind.shape}")
        for name, v in (
            ("q_start_rad", qs),
            ("q_end_rad", qe),
            ("surface_y_m", h),
            ("a6", a6_),
            ("T_s", T),
        ):
            if not bool(torch.isfinite(v).all()):
                raise PlanningError(f"{name} must be finite; got non-finite values")
        if not bool((T > 0.0).all()):
            raise PlanningError(f"T_s must be > 0 s; got min {float(T.min())!r} s")
        return self._evaluate(qs, qe, h, kind.expand(B), a6_, T)

    def _evaluate(
        self,
        qs: Tensor,
        qe: Tensor,
        h: Tensor,
        kind: Tensor,
        a6: Tensor,
        T: Tensor,
    ) -> TorchEvaluation:
        """:meth:`evaluate` on validated tensors."""
        planning = self._planning
        m = self.n_samples
        B = T.shape[0]
        T6 = T**6
        D = qe - qs
        K = -a6 * T6[:, None]  # the sextic's shape term (sextic module docstring)

        # Sextic samples (B, 3, m): one product of (B*3, 2) [D, K] with the (2, 3m) basis.
        derivs = torch.stack([D, K], dim=-1).reshape(B * 3, 2) @ self._basis.reshape(2, 3 * m)
        derivs = derivs.reshape(B, 3, 3, m)
        inv_T = (1.0 / T)[:, None, None]
        q = qs[:, :, None] + derivs[:, :, 0]
        qd = derivs[:, :, 1] * inv_T
        qdd = derivs[:, :, 2] * (inv_T * inv_T)
        q1, q2, q3 = q.unbind(1)
        qd1, qd2, qd3 = qd.unbind(1)
        qdd1, qdd2, qdd3 = qdd.unbind(1)

        # Trigonometry shared by kinematics and dynamics (dynamics._trig): cos/sin of the
        # relative angles, the absolute angles by angle addition.
        c1, s1, c2, s2, c3, s3 = q1.cos(), q1.sin(), q2.cos(), q2.sin(), q3.cos(), q3.sin()
        c12 = c1 * c2 - s1 * s2
        s12 = s1 * c2 + c1 * s2
        c23 = c2 * c3 - s2 * s3
        s23 = s2 * c3 + c2 * s3
        cp0, sp0, cp1, sp1 = c1, s1, c12, s12
        cp2 = c12 * c3 - s12 * s3
        sp2 = s12 * c3 + c12 * s3

        # Tip state (kinematics.tip_state): absolute rates w = cumsum(qd).
        l0, l1, l2 = self._lengths
        w0 = qd1
        w1 = w0 + qd2
        w2 = w1 + qd3
        x = l0 * cp0 + l1 * cp1 + l2 * cp2
        y = l0 * sp0 + l1 * sp1 + l2 * sp2
        vx = -(l0 * sp0 * w0 + l1 * sp1 * w1 + l2 * sp2 * w2)
        vy = l0 * cp0 * w0 + l1 * cp1 * w1 + l2 * cp2 * w2

        # Yao eq 8 (soil.yao_resistance) with the flat surface H of each problem.
        hh = h[:, None]
        depth = torch.relu(hh - y)
        # max(|v|, reg) as sqrt(max(|v|^2, reg^2)): no 0/0 in the gradient at rest.
        speed = torch.sqrt(torch.clamp(vx * vx + vy * vy, min=self._reg2))
        gain = (self._soil_gain * depth) / speed
        tx = gain * vx
        ty = gain * vy
        side_mu = torch.where(vx > 0.0, self._mu[0], self._mu[1])
        fx = -tx - side_mu * ty
        fy = -ty + side_mu * tx

        # Inverse dynamics (dynamics._inverse_block), mz = 0.
        ch = self._chain
        hm, bm, g, d = ch.h, ch.b, ch.g, ch.d
        d01 = ch.l0 * (hm[1] * c2 - bm[1] * s2)
        k01 = ch.l0 * (bm[1] * c2 + hm[1] * s2)
        d02 = ch.l0 * (hm[2] * c23 - bm[2] * s23)
        k02 = ch.l0 * (bm[2] * c23 + hm[2] * s23)
        d12 = ch.l1 * (hm[2] * c3 - bm[2] * s3)
        k12 = ch.l1 * (bm[2] * c3 + hm[2] * s3)
        a0 = qdd1
        a1 = a0 + qdd2
        a2 = a1 + qdd3
        ww0, ww1, ww2 = w0 * w0, w1 * w1, w2 * w2
        t0 = d[0] * a0 + d01 * a1 + d02 * a2 - k01 * ww1 - k02 * ww2
        t0 = t0 + g * (hm[0] * cp0 - bm[0] * sp0) - l0 * (cp0 * fy - sp0 * fx)
        t1 = d01 * a0 + d[1] * a1 + d12 * a2 + k01 * ww0 - k12 * ww2
        t1 = t1 + g * (hm[1] * cp1 - bm[1] * sp1) - l1 * (cp1 * fy - sp1 * fx)
        t2 = d02 * a0 + d12 * a1 + d[2] * a2 + k02 * ww0 + k12 * ww1
        t2 = t2 + g * (hm[2] * cp2 - bm[2] * sp2) - l2 * (cp2 * fy - sp2 * fx)
        tau1 = t1 + t2
        tau = torch.stack([t0 + tau1, tau1, t2], dim=1)  # (B, 3, m)

        # Positive power and its trapezoid energy (dynamics.energy_j, mode "positive").
        power = torch.relu(tau * qd).sum(dim=1)  # (B, m)
        t = self._s[None, :] * T[:, None]
        energy = 0.5 * ((power[:, 1:] + power[:, :-1]) * (t[:, 1:] - t[:, :-1])).sum(dim=-1)
        volume = _excavated_area_m2(x, y, h) * self._width
        b3 = 10.0 * D + K  # a3 T^3: the direction of J(q0) a3 without the 1/T^3
        theta_p = self._entry_angle(qs, b3, x, y, h)

        peak_tau = tau.abs().max(dim=-1).values
        peak_power = power.max(dim=-1).values
        is_down = kind == DigType.DOWNWARD
        lo = torch.where(is_down, self._theta_p_down[0], self._theta_p_back[0])
        hi = torch.where(is_down, self._theta_p_down[1], self._theta_p_back[1])
        tp_span = hi - lo
        v_span = planning.volume_max_m3 - planning.volume_min_m3
        t_span = planning.t_max_s - planning.t_min_s
        violations = torch.cat(
            [
                (self._q_min - q.min(dim=-1).values) / self._span,
                (q.max(dim=-1).values - self._q_max) / self._span,
                qd.abs().max(dim=-1).values / self._qd_max - 1.0,
                qdd.abs().max(dim=-1).values / self._qdd_max - 1.0,
                peak_tau / self._tau_max - 1.0,
                torch.stack(
                    [
                        peak_power / planning.power_max_w - 1.0,
                        (lo - theta_p) / tp_span,
                        (theta_p - hi) / tp_span,
                        (planning.volume_min_m3 - volume) / v_span,
                        (volume - planning.volume_max_m3) / v_span,
                        (planning.t_min_s - T) / t_span,
                        (T - planning.t_max_s) / t_span,
                    ],
                    dim=-1,
                ),
            ],
            dim=-1,
        )
        return TorchEvaluation(
            T_s=T,
            volume_m3=volume,
            energy_j=energy,
            theta_p_rad=theta_p,
            peak_power_w=peak_power,
            peak_torque_nm=peak_tau,
            objective=self._objective(T, energy, volume),
            violations=violations,
            total_violation=torch.relu(violations).sum(dim=-1),
        )

    def _objective(self, T: Tensor, energy: Tensor, volume: Tensor) -> Tensor:
        """Yao eq 11 (oneshot.objective)."""
        p = self._planning
        l1, l2, l3 = p.weights
        t_t = (T - p.t_min_s) / (p.t_max_s - p.t_min_s)
        e_e = (energy - p.energy_min_j) / (p.energy_max_j - p.energy_min_j)
        v_v = (p.volume_max_m3 - volume) / (p.volume_max_m3 - p.volume_min_m3)
        return l1 * t_t + l2 * e_e + l3 * v_v

    def _entry_angle(
        self, qs: Tensor, b3: Tensor, x: Tensor, y: Tensor, h: Tensor
    ) -> Tensor:
        """theta_p (oneshot._entry_angle): the motion direction where the tip enters, ``(B,)``.

        A start within 1 mm of the surface (or below it) takes the limit direction J(q0) a3;
        otherwise the first sampled segment that reaches below H; -90 deg if none does.
        """
        m = self.n_samples
        below = y < h[:, None]
        k = torch.clamp(below.to(torch.uint8).argmax(dim=-1), 1, m - 1)[:, None]
        dx = (x.gather(-1, k) - x.gather(-1, k - 1))[:, 0]
        dy = (y.gather(-1, k) - y.gather(-1, k - 1))[:, 0]
        # Rows x, y of the tip Jacobian at q0 (kinematics.jacobian), applied to a3 T^3.
        phi = torch.cumsum(qs, dim=-1)
        jx = torch.flip(torch.cumsum(torch.flip(-phi.sin() * self._lengths_t, [-1]), -1), [-1])
        jy = torch.flip(torch.cumsum(torch.flip(phi.cos() * self._lengths_t, [-1]), -1), [-1])
        at_start = y[:, 0] <= h + _AT_START_TOL_M
        dx = torch.where(at_start, (jx * b3).sum(-1), dx)
        dy = torch.where(at_start, (jy * b3).sum(-1), dy)
        # atan2 at (0, 0) has a 0/0 gradient: evaluate on a safe direction, keep the value.
        moving = (dx != 0.0) | (dy != 0.0)
        safe_dx = torch.where(moving, dx, 1.0)
        safe_dy = torch.where(moving, dy, 0.0)
        angle = torch.where(
            moving,
            torch.atan2(-safe_dy, safe_dx.abs()),
            torch.atan2(-dy.detach(), dx.detach().abs()),
        )
        entered = below.any(dim=-1) | at_start
        return torch.where(entered, angle, torch.full_like(angle, -0.5 * math.pi))


def _excavated_area_m2(x: Tensor, y: Tensor, h: Tensor) -> Tensor:
    """Area between sampled paths ``(B, m)`` and the surfaces ``h`` ``(B,)`` (oneshot twin).

    Green's theorem on the polyline clipped at y = H; see
    :func:`rt_runtime.planning.oneshot.excavated_area_m2`.
    """
    hh = h[:, None]
    d0 = hh - y[:, :-1]
    d1 = hh - y[:, 1:]
    dx = x[:, 1:] - x[:, :-1]
    p0 = torch.relu(d0)
    p1 = torch.relu(d1)
    both = (d0 >= 0.0) & (d1 >= 0.0)
    # Where a segment crosses the surface one end is < 0, so |d0| + |d1| > 0 there; elsewhere
    # the denominator is 1 and the quotient unused (finite gradient either way).
    denom = torch.where(both, torch.ones_like(d0), d0.abs() + d1.abs())
    denom = torch.where(denom > 0.0, denom, torch.ones_like(denom))
    frac = torch.where(both, torch.ones_like(d0), torch.maximum(d0, d1) / denom)
    seg = 0.5 * (p0 + p1) * frac * dx
    return seg.sum(dim=-1).abs()


__all__ = ["CONSTRAINT_NAMES", "TorchEvaluation", "TorchPhysics", "a6_from_particle"]
