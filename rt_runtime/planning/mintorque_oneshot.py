"""The minimum-torque objective (Yang/Pan) as a one-shot planner of the trench planner.

The trench planner asks a one-shot planner for a dig between two given poses on a material
surface H and executes a sextic per joint (Yao eq 9-10, parameters ``(a6, T)``), which it
verifies against Yao's eq 12 with its compiled verifier. :class:`MinTorqueOneShot` answers
with the sextic that minimises Yang/Pan's cost, ``integral sum_j (tau_j / tau_max_j)^2 dt``
with the fluid soil's wrench (eq 13-18, the smoothed model of
:mod:`rt_runtime.planning.mintorque`) in the inverse dynamics, subject to every constraint of
Yao's eq 12 as :func:`rt_runtime.planning.oneshot.evaluate` signs and normalises them. The
search is over ``(K1, K2, K3, T)`` (the PSO's particle, design note T1) by SLSQP with batched
forward-difference gradients from a few starts; the answer is verified by the trench planner's
verifier before it is returned, like the PSO's.

Within this interface the entry and exit poses are the trench planner's, and the keypoints of
:mod:`~rt_runtime.planning.mintorque` in between become the sextic's bulge: the objective and
the soil are Yang/Pan's, the path family and the limits are the trench planner's.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import mintorque as mt
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import Problem
from rt_runtime.rig import Rig
from rt_runtime.trajectory import sextic

FloatArray = np.typing.NDArray[np.float64]

#: Samples of the sextic for the cost (trapezoid) and the constraints.
N_SAMPLES = 101
#: Starts: no bulge, at these fractions of the time range.
START_TIMES = (0.2, 0.5, 0.8)


class MinTorqueOneShot:
    """Yang/Pan's minimum-torque cost behind the one-shot interface (module docstring).

    Args:
        rig: The rig; needs a ``[planning]`` table (the trench planner's limits).
        verifier: The trench planner's verifier (``evaluate_into``).
        soil: The rig's fluid soil (``soft``, ``hard``).

    Raises:
        ConfigurationError: No planning table, or no such soil on the rig.
    """

    name = "min_torque"

    def __init__(
        self, rig: Rig, verifier: Any, soil: str = "soft", *, backend: str = "auto"
    ) -> None:
        oneshot.require_planning(rig)
        module = mt.kernel_for(backend)
        self.rig = rig
        self.verifier = verifier
        check_soil(rig, soil)
        self.soil = rig.soil.fluid_named(soil)
        self.lo, self.hi = oneshot.search_bounds(rig)
        # The compiled path needs the verifier's own kernel on this grid for the constraints.
        c_verifier = getattr(verifier, "module", None) is not None
        c_verifier = c_verifier and getattr(verifier, "n_samples", None) == N_SAMPLES
        #: The compiled kernel's module (the cost, ``kernel/mintorque.c``; the constraints by
        #: the verifier's kernel), or None for numpy (the reference).
        self.module = module if c_verifier else None
        if backend == "c" and self.module is None:
            raise ConfigurationError(
                f"backend 'c' needs a compiled verifier on {N_SAMPLES} samples"
            )
        #: ``"c"`` or ``"numpy"``: who evaluates the cost and the constraints.
        self.backend = "numpy" if self.module is None else "c"
        self._params, _, self._plates = mt._pack_kernel(self._model_at(0.0), np.ones((4, 3)))

    def _model_at(self, surface_y_m: float) -> Any:
        return mt._Model(
            self.rig,
            mt.MinTorqueProblem(
                soil=self.soil,
                surface_y_m=surface_y_m,
                volume_m3=(0.0, 1.0),
                depth_m=(0.0, 1.0),
                entry_x_m=(0.0, 1.0),
            ),
            mt._NumpyOps,
        )

    def cost(self, problem: Problem, X: Any) -> tuple[FloatArray, FloatArray]:
        """Cost ``(B,)`` and Yao's eq 12 violations ``(B, 22)`` of particles ``X`` ``(B, 4)``."""
        x = np.atleast_2d(np.asarray(X, dtype=np.float64))
        a6, T = oneshot.a6_from_particle(x)
        qs = np.asarray(problem.q_start_rad)[None, :]
        qe = np.asarray(problem.q_end_rad)[None, :]
        coef = sextic.sextic_coefficients(qs[:, None, :], qe[:, None, :], a6[None], T[None])
        t, q, qd, qdd, _ = sextic.evaluate(coef, T[None], N_SAMPLES)
        if self.module is not None:
            from rt_runtime.planning.verify import N_OUT, pack_inputs

            rows = pack_inputs(
                qs[0], qe[0], problem.surface_y_m, int(problem.dig_type), a6, T
            )
            out = np.zeros((x.shape[0], N_OUT))
            self.verifier.evaluate_into(rows, out)
            dt = np.diff(t[0], axis=-1)
            w = np.zeros(t[0].shape)
            w[:, :-1] += 0.5 * dt
            w[:, 1:] += 0.5 * dt
            params = self._params.copy()
            params[mt.KERNEL_SURFACE] = problem.surface_y_m
            cost = np.empty(x.shape[0])
            self.module.mintorque_path_cost(
                np.ascontiguousarray(q[0]), np.ascontiguousarray(qd[0]),
                np.ascontiguousarray(qdd[0]), w, params, self._plates, cost,
            )  # fmt: skip
            return cost, out[:, : len(oneshot.CONSTRAINT_NAMES)].copy()
        ev = oneshot.evaluate(
            self.rig, qs, qe, np.array([problem.surface_y_m]), int(problem.dig_type),
            a6[None], T[None], N_SAMPLES,
        )  # fmt: skip
        tau, _ = self._model_at(problem.surface_y_m)._torques(
            [q[0, ..., j] for j in range(3)],
            [qd[0, ..., j] for j in range(3)],
            [qdd[0, ..., j] for j in range(3)],
        )
        sq = sum((tau[j] / float(self.rig.tau_max_nm[j])) ** 2 for j in range(3))
        dt = np.diff(t[0], axis=-1)
        cost = np.sum(0.5 * (sq[..., 1:] + sq[..., :-1]) * dt, axis=-1)
        return np.asarray(cost, dtype=np.float64), ev.violations[0]

    def solve(self, problem: Problem) -> tuple[FloatArray, float, float]:
        """The best particle ``(4,)`` over the starts, its cost and its total violation."""
        from scipy.optimize import minimize

        n = 4
        lo, hi = self.lo, self.hi
        span = hi - lo
        best: tuple[float, float, FloatArray] | None = None
        for frac in START_TIMES:
            z0 = np.array([0.5, 0.5, 0.5, frac])
            cache: dict[bytes, tuple[float, FloatArray, FloatArray, FloatArray]] = {}

            def at(z: FloatArray, cache: dict[bytes, Any] = cache) -> Any:
                key = z.tobytes()
                if key not in cache:
                    Z = np.repeat(z[None, :], n + 1, axis=0)
                    Z[1:] += mt.FD_STEP * np.eye(n)
                    c, v = self.cost(problem, lo + Z * span)
                    g = -(v + mt.CONSTRAINT_OFFSET)
                    cache.clear()
                    cache[key] = (
                        c[0],
                        (c[1:] - c[0]) / mt.FD_STEP,
                        g[0],
                        ((g[1:] - g[0]) / mt.FD_STEP).T,
                    )
                return cache[key]

            f0 = max(float(at(z0)[0]), 1e-12)  # cost scaled to 1 at the start
            res = minimize(
                lambda z, f0=f0: at(z)[0] / f0,
                z0,
                jac=lambda z, f0=f0: at(z)[1] / f0,
                method="SLSQP",
                bounds=[(0.0, 1.0)] * n,
                constraints=[
                    {"type": "ineq", "fun": lambda z: at(z)[2], "jac": lambda z: at(z)[3]}
                ],
                options={"maxiter": 100, "ftol": 1e-8},
            )
            x = lo + np.clip(res.x, 0.0, 1.0) * span
            c, v = self.cost(problem, x[None, :])
            key = (float(np.sum(np.maximum(v[0], 0.0))), float(c[0]))
            if best is None or key < best[:2]:
                best = (key[0], key[1], x)
        assert best is not None
        return best[2], best[1], best[0]

    def plan_dig(self, problem: Problem, c_max: float) -> Any:
        """A verified minimum-torque dig for ``problem`` (``c_max`` does not apply).

        Raises:
            PlanningError: No start reaches a plan within Yao's eq 12, or the verifier refuses it.
        """
        from rt_runtime.planning.trench.planners import OneShotResult
        from rt_runtime.planning.verify import COL_TOTAL, N_OUT, pack_inputs

        t0 = time.perf_counter()
        x, _, violation = self.solve(problem)
        if violation > 0.0:
            raise PlanningError(
                f"min-torque one-shot plan violates Yao's eq 12 (total {violation:.3g})"
            )
        a6v, Tv = oneshot.a6_from_particle(x)
        a6 = (float(a6v[0]), float(a6v[1]), float(a6v[2]))
        p = problem
        row = pack_inputs(p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type, a6, float(Tv))
        out = np.zeros((1, N_OUT))
        self.verifier.evaluate_into(row, out)
        if out[0, COL_TOTAL] > 0.0:
            raise PlanningError(
                f"min-torque plan fails verification (total violation {out[0, COL_TOTAL]:.3g})"
            )
        return OneShotResult(
            a6, float(Tv), out[0].copy(), (time.perf_counter() - t0) * 1e6, "min_torque"
        )


def check_soil(rig: Rig, soil: str) -> None:
    """Raise :class:`ConfigurationError` unless ``rig`` has the fluid soil ``soil``."""
    try:
        rig.soil.fluid_named(soil)
    except KeyError:
        raise ConfigurationError(
            f"rig {rig.name!r} has no fluid soil {soil!r}; its soils: "
            + ", ".join(s.name for s in rig.soil.fluid)
        ) from None
