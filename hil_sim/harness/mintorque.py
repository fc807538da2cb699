"""``excavator-rt hil --mintorque SOIL``: an optimised minimum-torque dig (Yang/Pan) executed
through the CiA 402 master against the lockstep HIL, in the same fluid soil it was planned for.

The dig of :func:`rt_runtime.planning.mintorque.solve` is streamed as one path motion (its own
C2 interpolation between the keypoints, sampled each cycle), from the entry pose, on the
rig's hydraulic drives and arm. The plant's soil is the fluid model of the plan
(:func:`rt_runtime.soil.fluid_resistance`, exact, on a flat surface at the plan's H) fed to the
plant as a tip force: the plant's soil interface takes a force at the tip, so the model's
moment about the tip is not applied (the report gives its RMS so that its share is seen). The
attitude and rotation rate the force needs are the plant's own at each sub-step, and its
damping ``D = -dF/dv`` is taken by differences for the plant's implicit integrator.

The report: tracking per cylinder (truth and drive feedback, as ``hil``), and per joint the
torque the plant's cylinders delivered (``actuation.torque_from_force`` of the plant's
cylinder forces) against the planned torque at the same time of the dig (the exact model
at the commanded state), as RMS and largest difference. Lockstep only: the sampling and
the soil law allocate.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil_sim.harness.scenario import (
    GOALS_MM,
    PathScenario,
    _execute,
    _open_hil,
    _segments,
)
from hil_sim.report import tracking_figures
from hil_sim.swing import cylinder_velocity_lead
from hil_sim.terrain import Terrain
from rt_runtime import actuation, soil
from rt_runtime.canbus import CanMaster
from rt_runtime.control import FixedRateLoop
from rt_runtime.control.executor import Executor, ExecutorConfig
from rt_runtime.control.planner_worker import PathJob
from rt_runtime.errors import PlanningError
from rt_runtime.planning import mintorque as mt
from rt_runtime.rig import FluidSoil, Rig, load_rig

FloatArray = NDArray[np.float64]

#: Speed step of the damping differences (m/s).
_DV_M_S = 1e-4


class DigMotion:
    """A :class:`~rt_runtime.planning.mintorque.Solution` as a joint motion."""

    def __init__(self, solution: mt.Solution) -> None:
        self.solution = solution

    @property
    def duration_s(self) -> float:
        return self.solution.T_s

    def sample(self, t_s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        q, qd, qdd = self.solution.sample(t_s)
        return q[0], qd[0], qdd[0]


class _FluidLoad:
    """The fluid model as the plant's tip force law (module docstring); ``plant`` is set once
    the plant exists."""

    def __init__(self, rig: Rig, fs: FluidSoil, surface_y_m: float) -> None:
        self.rig = rig
        self.fs = fs
        self.h = surface_y_m
        self.plant: Any = None
        self.moment_sq = 0.0
        self.samples = 0

    def _force(self, x: float, y: float, vx: float, vy: float) -> FloatArray:
        q = self.plant.q_rad
        qd = self.plant.qd_rad_s
        f: FloatArray = soil.fluid_resistance(
            self.rig, self.fs, (x, y, float(np.sum(q))), (vx, vy, float(np.sum(qd))), self.h
        )
        return f

    def tip_load(
        self, x_m: float, y_m: float, vx_m_s: float, vy_m_s: float
    ) -> tuple[float, float, float, float, float, float]:
        f0 = self._force(x_m, y_m, vx_m_s, vy_m_s)
        fx = self._force(x_m, y_m, vx_m_s + _DV_M_S, vy_m_s)
        fy = self._force(x_m, y_m, vx_m_s, vy_m_s + _DV_M_S)
        self.moment_sq += float(f0[2]) ** 2
        self.samples += 1
        return (
            float(f0[0]),
            float(f0[1]),
            -(fx[0] - f0[0]) / _DV_M_S,
            -(fy[0] - f0[0]) / _DV_M_S,
            -(fx[1] - f0[1]) / _DV_M_S,
            -(fy[1] - f0[1]) / _DV_M_S,
        )


class _FluidTerrain(Terrain):
    """Flat material whose soil law is :class:`_FluidLoad`."""

    def __init__(self, rig: Rig, load: _FluidLoad) -> None:
        reach = float(np.sum(rig.lengths_m))
        super().__init__(load.h, (-reach, reach), rig.bucket.width_m)
        self.load = load

    def soil_model(self, rig: Rig, **_: Any) -> Any:
        return self.load


def run_mintorque(
    soil_name: str,
    rig_name: str = "yang_pan_excavator",
    *,
    fixed_time: bool = False,
    period_s: float = 0.002,
    feedforward: bool = True,
    lead: bool = True,
) -> dict[str, Any]:
    """Plan the dig, execute it on the lockstep HIL in the same soil, report (module docstring).
    With ``lead`` (and the feed-forward) the velocity offsets lead each cylinder's valve lag and
    hydraulic mode (:func:`hil_sim.swing.cylinder_velocity_lead`), as a commissioned rig's
    would.

    Raises:
        ConfigurationError: Bad rig or soil.
        PlanningError: No feasible dig (nothing moves).
    """
    wall0 = time.perf_counter()
    rig = load_rig(rig_name)
    lead_s, lead2_s2 = cylinder_velocity_lead(rig) if lead and feedforward else (None, None)
    config = ExecutorConfig(
        feedforward=feedforward, velocity_lead_s=lead_s, velocity_lead2_s2=lead2_s2
    )
    problem = mt.make_problem(rig, soil_name, fixed_time=fixed_time)
    sol = mt.solve(rig, problem)
    if not sol.feasible:
        raise PlanningError(
            "no feasible minimum-torque dig (exact re-check): nothing was sent; margins below "
            "zero: " + ", ".join(f"{n} {v:.3g}" for n, v in sol.margins.items() if v < 0.0)
        )
    q0 = np.asarray(sol.keypoints_rad[0], dtype=np.float64)
    actuation.joint_to_stroke(rig, q0, check_limits=True)
    load = _FluidLoad(rig, problem.soil, problem.surface_y_m)
    sc = PathScenario(path="joints", rig=rig.name, period_s=period_s, feedforward=feedforward)
    hil = _open_hil(sc, rig, q0, _FluidTerrain(rig, load))
    plant = hil.hil.core.plant  # type: ignore[attr-defined]
    load.plant = plant
    log_t: list[float] = []
    log_q: list[FloatArray] = []
    log_f: list[FloatArray] = []

    def on_cycle(_sync: int, now_s: float) -> None:
        log_t.append(now_s)
        log_q.append(plant.q_rad.copy())
        log_f.append(plant.cylinder_force_n.copy())

    try:

        def make_executor(master: CanMaster, loop: FixedRateLoop, _hook: Any) -> Executor:
            job = PathJob((DigMotion(sol),), name=f"mintorque {soil_name}")
            return Executor.for_path(
                master, rig, loop, job, config, on_cycle=on_cycle
            )

        result, _ = _execute(sc, rig, hil, [], sol.T_s + 30.0, make_executor)
    finally:
        end = hil.finish()
        hil.close()
    segments = _segments(rig, result, end.truth)
    figures = tracking_figures(segments)
    path = [s for s in segments if s.kind == "path"]
    torque = _torques(rig, problem, sol, path, np.asarray(log_t), log_q, log_f)
    goal = GOALS_MM.get(rig.cylinders.kind)
    return {
        "rig": rig.name,
        "soil": soil_name,
        "status": result.status.name.lower(),
        "fault": result.fault,
        "plan": {
            "T_s": sol.T_s,
            "cost": sol.cost,
            "max_depth_m": sol.max_depth_m,
            "volume_m3": sol.volume_m3,
            "intervals_s": sol.intervals_s.tolist(),
            "solve_s": sol.solve_s,
        },
        **figures.to_json(),
        "tracking_goal_max_mm": None if goal is None else goal.max_mm,
        "velocity_lead_s": None if lead_s is None else list(lead_s),
        "velocity_lead2_s2": None if lead2_s2 is None else list(lead2_s2),
        "torque": torque,
        "soil_moment_rms_nm": math.sqrt(load.moment_sq / max(load.samples, 1)),
        "soil_moment_applied": False,
        "wall_s": time.perf_counter() - wall0,
    }


def _torques(
    rig: Rig,
    problem: mt.MinTorqueProblem,
    sol: mt.Solution,
    path: list[Any],
    log_t: FloatArray,
    log_q: list[FloatArray],
    log_f: list[FloatArray],
) -> dict[str, Any]:
    """Plant against planned joint torques over the dig (per joint RMS and largest)."""
    if not path or not len(log_t):
        return {}
    t0 = float(path[0].t_s[0])
    t1 = float(path[-1].t_s[-1])
    sel = (log_t >= t0) & (log_t <= t1)
    q = np.asarray(log_q)[sel]
    f = np.asarray(log_f)[sel]
    plant_tau = actuation.torque_from_force(rig, q, f, check_limits=False)
    chk = mt.exact_check(rig, problem, sol.keypoints_rad, sol.intervals_s)
    planned = np.stack(
        [np.interp(log_t[sel] - t0, chk.t_s, chk.tau_nm[:, j]) for j in range(3)], axis=-1
    )
    diff = plant_tau - planned
    out: dict[str, Any] = {}
    for j, name in enumerate(mt.JOINTS):
        out[name] = {
            "rms_planned_nm": float(np.sqrt(np.mean(planned[:, j] ** 2))),
            "rms_plant_nm": float(np.sqrt(np.mean(plant_tau[:, j] ** 2))),
            "rms_difference_nm": float(np.sqrt(np.mean(diff[:, j] ** 2))),
            "max_difference_nm": float(np.max(np.abs(diff[:, j]))),
            "rms_difference_of_limit": float(np.sqrt(np.mean(diff[:, j] ** 2)) / rig.tau_max_nm[j]),
        }
    return out
