"""The trench planner: what a session needs that does not change from task to task (the rig,
the one-shot planner, the verifier, the candidate grids), and the open-loop plan of a task."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from rt_runtime import kinematics
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import oneshot
from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, PinnPlanner
from rt_runtime.planning.trench.candidates import (
    _CANDIDATES,
    _GEOMETRIC_BULGE,
    _SCREEN_C,
    _SCREEN_SAMPLES,
    PASS_T_MIN_FRACTION,
)
from rt_runtime.planning.trench.cycles import home_pose
from rt_runtime.planning.trench.fit import _FIT_SAMPLES
from rt_runtime.planning.trench.geometry import FloatArray, _sextic_shapes
from rt_runtime.planning.trench.motion import _Mover
from rt_runtime.planning.trench.plan import PlannedDig, TrenchPlan
from rt_runtime.planning.trench.planners import OneShotPlanner, PinnOneShot, PsoOneShot
from rt_runtime.planning.trench.session import TrenchSession
from rt_runtime.planning.trench.task import _ENTRY_X_M, TrenchTask, _reach_scale, load_task
from rt_runtime.planning.verify import Verifier
from rt_runtime.rig import Rig

#: The one-shot planners a :class:`TrenchPlanner` builds by name (and a planner process
#: rebuilds from its name).
ONESHOT_PLANNERS = ("pinn", "pso", "min_torque")
#: How the rough stage's candidates get their bulge (:class:`TrenchPlanner`, ``screening``).
SCREENINGS = ("auto", "network", "geometric")


class TrenchPlanner:
    """Plans trench tasks dig by dig (Yao Fig. 5).

    Args:
        rig: The rig (needs planning thresholds and shipped PINN models for screening).
        planner: ``pinn`` (default), ``pso``, ``min_torque`` (Yang/Pan's torque cost with the
            soft fluid soil, :mod:`rt_runtime.planning.mintorque_oneshot`), or an object with
            ``plan_dig``.
        model_dir: PINN model directory (default: the shipped ``onnx/``).
        pso_options: Keyword arguments for :func:`rt_runtime.planning.oneshot.solve_pso`.
        max_digs: Safety bound on the number of digs of one task (None: 20 a section).
        soil: The fluid soil (Yang/Pan Table 2) of the minimum-torque planner's cost: one of
            the rig's (``soft`` by default); refused with another planner.
        screening: How the rough stage's candidate digs get their bulge before the fill
            scales it: ``"network"`` (the PINN's answer for each candidate's poses),
            ``"geometric"`` (a closed-form bulge per dig type, :data:`~rt_runtime.planning.
            trench.candidates._GEOMETRIC_BULGE`, so that the PSO and the minimum-torque planner
            run on a rig with no trained network), or ``"auto"`` (the network where its models
            load for the rig, else geometric; the PINN planner always needs the network).
        geometry: Who computes the screening geometry, the over-dig of sampled paths and the
            envelopes: ``"c"`` (the verifier's compiled kernel, ``kernel/trench.c``), ``"numpy"``
            (the reference) or ``"auto"`` (C where the verifier runs on C). The plans are the
            same (tests/test_trench.py compares them); C is ~2x faster on a whole plan.

    Raises:
        ConfigurationError: Unknown planner name, geometry or screening; models that do not
            load for the rig where the network is needed (the PINN planner, ``screening=
            "network"``); ``geometry="c"`` where the verifier has no compiled kernel.
    """

    def __init__(
        self,
        rig: Rig,
        planner: str | OneShotPlanner = "pinn",
        *,
        model_dir: Path | str | None = None,
        pso_options: dict[str, Any] | None = None,
        max_digs: int | None = None,
        geometry: str = "auto",
        screening: str = "auto",
        soil: str | None = None,
    ) -> None:

        oneshot.require_planning(rig)
        if screening not in SCREENINGS:
            raise ConfigurationError(
                f"unknown screening {screening!r}; allowed: {', '.join(SCREENINGS)}"
            )
        self.rig = rig
        #: What built this planner (a planner process rebuilds it from these).
        self.model_dir = Path(model_dir or DEFAULT_MODEL_DIR)
        self.pso_options = dict(pso_options or {})
        needs_network = planner == "pinn" or screening == "network"
        #: The PINN (None where the screening is geometric: no network is loaded).
        self.pinn: PinnPlanner | None = None
        if needs_network or screening == "auto":
            try:
                self.pinn = PinnPlanner(rig, self.model_dir, refine=True)
            except ConfigurationError as e:
                if needs_network:
                    raise ConfigurationError(
                        f"{e}; the pinn planner and the network screening need the rig's "
                        "trained models (the pso and min_torque planners plan without them, "
                        "screening geometrically)"
                    ) from None
        #: ``"network"`` or ``"geometric"``: what gives the rough stage's candidates a bulge.
        self.screening = "network" if self.pinn is not None else "geometric"
        self.verifier = (
            self.pinn.verifier
            if self.pinn is not None
            else Verifier(rig, oneshot.DEFAULT_SAMPLES, backend="c")
        )
        planning = rig.planning
        assert planning is not None  # the verifier refuses a rig without one
        #: The finishing passes' verifier: every limit of :attr:`verifier`, the time window's
        #: lower end at :data:`PASS_T_MIN_FRACTION` of Yao's (a pass is not a one-shot dig).
        self.pass_verifier = Verifier(
            dataclasses.replace(
                rig,
                planning=dataclasses.replace(
                    planning, t_min_s=PASS_T_MIN_FRACTION * planning.t_min_s
                ),
            ),
            self.verifier.n_samples,
            backend=self.verifier.backend,
        )
        if geometry not in ("auto", "c", "numpy"):
            raise ConfigurationError(f"unknown geometry {geometry!r}; allowed: auto, c, numpy")
        if geometry == "c" and self.verifier.module is None:
            raise ConfigurationError(
                "geometry 'c' needs the verifier's compiled kernel, which is not in use here "
                f"(verifier backend {self.verifier.backend!r})"
            )
        use_c = geometry != "numpy" and self.verifier.module is not None
        #: The compiled kernel and its module for the geometry (None: the numpy reference).
        self.geo_kernel: Any = self.verifier.kernel if use_c else None
        self.geo_module: Any = self.verifier.module if use_c else None
        if isinstance(planner, str):
            if planner == "pinn":
                assert self.pinn is not None
                self.oneshot: OneShotPlanner = PinnOneShot(self.pinn)
            elif planner == "pso":
                self.oneshot = PsoOneShot(rig, self.verifier, **(pso_options or {}))
            elif planner == "min_torque":
                from rt_runtime.planning.mintorque_oneshot import MinTorqueOneShot

                self.oneshot = MinTorqueOneShot(rig, self.verifier, soil or "soft")
            else:
                raise ConfigurationError(
                    f"unknown planner {planner!r}; allowed: {', '.join(ONESHOT_PLANNERS)}"
                )
        else:
            self.oneshot = planner
        if soil is not None and self.oneshot.name != "min_torque":
            raise ConfigurationError(
                f"a soil ({soil!r}) applies to the min_torque planner only, not to "
                f"{self.oneshot.name!r}"
            )
        #: The minimum-torque planner's soil (None with another planner).
        self.soil = (soil or "soft") if self.oneshot.name == "min_torque" else None
        self.max_digs = max_digs
        s = _reach_scale(rig)
        self.scale = s
        self.entry_x_range = (_ENTRY_X_M[0] * s, _ENTRY_X_M[1] * s)
        self.arm = kinematics.FastArm(rig)
        self.screen_qf, self.screen_pf = _sextic_shapes(_SCREEN_SAMPLES)
        self.screen_shapes = np.stack([self.screen_qf, self.screen_pf])
        self.screen_c = np.asarray(_SCREEN_C)
        # Second derivatives of the sextic's shape functions on a 1001-point grid.
        t = np.linspace(0.0, 1.0, 1001)
        self.fine_qf2 = 60 * t - 180 * t**2 + 120 * t**3
        self.fine_pf2 = 6 * t - 36 * t**2 + 60 * t**3 - 30 * t**4
        self.qdd_max = np.asarray(rig.qdd_max_rad_s2, dtype=np.float64)
        self.fit_qf, self.fit_pf = _sextic_shapes(_FIT_SAMPLES)
        # On the verifier's grid: the profile passes' paths as the verifier samples them.
        self.full_qf, self.full_pf = _sextic_shapes(self.verifier.n_samples)
        self.mover = _Mover(rig)
        #: Each dig type's exit candidates relative to the entry, flat: (length, rise, attitude).
        self.exit_grid = {
            kind: tuple(
                g.ravel()
                for g in np.meshgrid(
                    np.asarray(cand.length_m) * s,
                    np.asarray(cand.exit_rise_m) * s,
                    np.radians(cand.exit_attitude_deg),
                    indexing="ij",
                )
            )
            for kind, cand in _CANDIDATES.items()
        }
        #: Per dig type the network's input domain (None with the geometric screening).
        self.domain = (
            None
            if self.pinn is None
            else {
                k: (np.asarray(c.domain_min), np.asarray(c.domain_max))
                for k, c in self.pinn.cards.items()
            }
        )
        #: Per dig type the geometric screening's bulge target at mid-path: tip x and y
        #: (scaled by reach) and the attitude (rad).
        self.geometric_bulge = {
            kind: np.array([b[0] * s, b[1] * s, np.radians(b[2])])
            for kind, b in _GEOMETRIC_BULGE.items()
        }
        #: Where the arm starts a task and where the moves after its last dig end: the spoil
        #: zone's point nearest the machine (joint angles; :func:`cycles.home_pose`).
        self.home_pose_rad = home_pose(rig, self.arm)

    def sextic_path(self, q1: FloatArray, q2: FloatArray, K: FloatArray) -> FloatArray:
        """Joint poses (rad) of sextics from ``q1`` to ``q2`` with bulge ``K`` (each
        ``(..., 3)``) on the verifier's samples: ``(..., n, 3)``."""
        path: FloatArray = (
            q1[..., None, :]
            + self.full_qf[:, None] * (q2 - q1)[..., None, :]
            + self.full_pf[:, None] * K[..., None, :]
        )
        return path

    def verifier_for(self, pass_window: bool) -> Verifier:
        """:attr:`pass_verifier` for a dig timed in the finishing passes' window, else
        :attr:`verifier`."""
        return self.pass_verifier if pass_window else self.verifier

    def start(self, task: TrenchTask) -> TrenchSession:
        """A closed-loop session for ``task`` (plan a dig, execute it, record its path)."""
        return TrenchSession(self, task)

    def plan(self, task: TrenchTask) -> TrenchPlan:
        """The whole plan for ``task`` on the predicted paths (open loop).

        A PlanningError mid-way (no verified dig removes the rest, the bound on the digs) does
        not propagate: the plan holds the digs before it, ends after the last of them (the
        moves towards the dig that failed are dropped) and is incomplete with that error as
        its :attr:`TrenchPlan.planning_error`. Check :attr:`TrenchPlan.status`.
        """
        t0 = time.perf_counter()
        trench = self.start(task)
        error: str | None = None
        try:
            while True:
                dig = trench.next_dig()
                if dig is None:
                    break
                trench.record(dig, dig.tip_path_m)
        except PlanningError as e:
            error = str(e)
        plan = trench.finish(plan_total_us=0.0)
        total = (time.perf_counter() - t0) * 1e6
        stages = dict(trench.stage_us)
        stages["other"] = max(0.0, total - sum(stages.values()))
        if error is None:
            return dataclasses.replace(plan, plan_total_us=total, stage_us=stages)
        last = max((i for i, st in enumerate(plan.steps) if isinstance(st, PlannedDig)), default=-1)
        return dataclasses.replace(
            plan,
            steps=plan.steps[: last + 1],
            plan_total_us=total,
            stage_us=stages,
            planning_error=error,
        )


def plan_task(rig: Rig, task: TrenchTask | str, planner: str = "pinn", **kwargs: Any) -> TrenchPlan:
    """Convenience: load ``task`` if given by name/path and plan it."""
    t = load_task(task, rig) if isinstance(task, str) else task
    return TrenchPlanner(rig, planner, **kwargs).plan(t)
