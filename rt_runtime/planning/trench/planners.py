"""One-shot planners behind the trench planner's interface: the PINN (default; the network's
path filled on the material left) and the PSO teacher (Yao's reference, seconds a dig)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from rt_runtime.errors import PlanningError
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import Problem
from rt_runtime.planning.trench.geometry import FloatArray, _total_without_volume
from rt_runtime.planning.verify import (
    COL_TOTAL,
    N_OUT,
    pack_inputs,
)
from rt_runtime.rig import Rig


@dataclass(frozen=True, slots=True)
class OneShotResult:
    """A verified one-shot dig from a planner adapter."""

    a6: tuple[float, float, float]
    T_s: float
    evaluation: FloatArray
    plan_us: float
    status: str


class OneShotPlanner(Protocol):
    """What the trench planner needs of a one-shot planner."""

    name: str

    def plan_dig(self, problem: Problem, c_max: float) -> OneShotResult:
        """A verified dig for ``problem``; ``c_max`` caps the bulge scale where supported.

        Raises:
            PlanningError: No verified plan.
        """
        ...


class PinnOneShot:
    """The PINN planner (default): what :meth:`PinnPlanner.plan` returns, bulge capped.

    Without the solution library (:mod:`rt_runtime.planning.pinn`, step 4a): the screening
    predicts each candidate's cut from the network's bulge direction (only its scale changes
    in the plan), and a library path would cut elsewhere.
    """

    name = "pinn"

    def __init__(self, planner: Any) -> None:
        self.planner = planner

    def plan_dig(self, problem: Problem, c_max: float) -> OneShotResult:
        p = self.planner.plan(
            problem.q_start_rad,
            problem.q_end_rad,
            problem.surface_y_m,
            problem.dig_type,
            c_max=c_max,
            library=False,
        )
        return OneShotResult(p.a6, p.T_s, p.evaluation, p.plan_us, p.status.name.lower())

    def plan_scaled(
        self, problem: Problem, K_rad: FloatArray, T_s: float, c: float
    ) -> OneShotResult:
        """The network's path for ``problem`` with its bulge ``K_rad`` (``(3,)``, rad, the
        network's answer at ``T_s``) scaled by ``c``, retimed to the shortest feasible time.

        The trench planner chooses ``c`` so that the real cut on the material left fills the
        bucket (the fill rule); the one-shot volume window against a flat surface at H does
        not apply and is not checked here (the caller checks the real cut), every other limit
        of Yao eq 12 is.

        Raises:
            PlanningError: No time in the range makes the scaled path feasible.
        """
        t0 = time.perf_counter()
        verifier = self.planner.verifier
        a6 = -c * np.asarray(K_rad, dtype=np.float64) / T_s**6
        row = pack_inputs(
            problem.q_start_rad, problem.q_end_rad, problem.surface_y_m, problem.dig_type,
            a6, T_s,
        )  # fmt: skip
        out = np.zeros((1, N_OUT))
        retimed = np.zeros((1, 4))
        verifier.retime_into(row, out, retimed)
        if not np.isfinite(retimed[0, 3]) or _total_without_volume(out[0]) > 0.0:
            raise PlanningError("the scaled network path has no feasible time")
        r = retimed[0]
        return OneShotResult(
            (float(r[0]), float(r[1]), float(r[2])),
            float(r[3]),
            out[0].copy(),
            (time.perf_counter() - t0) * 1e6,
            "filled",
        )


class PsoOneShot:
    """The PSO teacher (seconds per dig): Yao's reference, same interface."""

    name = "pso"

    def __init__(self, rig: Rig, verifier: Any, **pso_options: Any) -> None:
        self.rig = rig
        self.verifier = verifier
        self.options = pso_options

    def plan_dig(self, problem: Problem, c_max: float) -> OneShotResult:
        t0 = time.perf_counter()
        sol = oneshot.solve_pso(self.rig, [problem], **self.options)[0]
        a6 = tuple(float(v) for v in sol.a6)
        p = problem
        row = pack_inputs(p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type, a6, sol.T_s)
        out = np.zeros((1, N_OUT))
        self.verifier.evaluate_into(row, out)
        if out[0, COL_TOTAL] > 0.0:
            raise PlanningError(
                f"PSO plan fails verification (total violation {out[0, COL_TOTAL]:.3g})"
            )
        return OneShotResult(
            (a6[0], a6[1], a6[2]),
            float(sol.T_s),
            out[0].copy(),
            (time.perf_counter() - t0) * 1e6,
            "pso",
        )
