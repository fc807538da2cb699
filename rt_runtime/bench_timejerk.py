"""``excavator-rt bench timejerk``: the minimum time-jerk generator against two references.

The generator (:mod:`rt_runtime.trajectory.timejerk`) is timed on seeded random problems over
every rig's limits and checked exactly and on a 1 kHz resample. Two independent references,
used here only (never by the runtime), need the ``reference`` extra (casadi, toppra):

* :class:`CasadiReference`: the same problem (Zhao eq 3 with the same two free knots and the
  same shortest piece) as one nonlinear program over every spline coefficient and every
  duration, solved by IPOPT through CasADi. Velocity limits hold at every instant through an
  exact certificate: a quadratic ``p(u) >= 0`` on ``[0, 1]`` iff ``p = sigma + lambda u (1 - u)``
  with ``sigma`` a sum of squares and ``lambda >= 0`` (Lukacs), i.e. one extra variable and
  three smooth inequalities per piece, joint and side. Acceleration is linear on a piece, so its
  ends bound it.
* :func:`toppra_bound`: toppra's time-optimal parameterisation of the generator's own geometric
  path under the same limits, a lower bound on T for that path. toppra holds its limits at its
  grid points only, so its output is resampled at 1 kHz and slowed uniformly (velocity by the
  factor, acceleration by its square) until the resample is within the limits; that time is
  the bound compared against.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.reports import Distribution
from rt_runtime.rig import load_rig, profile_names
from rt_runtime.trajectory import timejerk

FloatArray = NDArray[np.float64]

#: Goals of issue 26 for this benchmark (reported, never asserted: design note B1).
GOALS = {
    "solve_ms_p50_max": 20.0,
    "solve_ms_p99_max": 100.0,
    "feasible_min": 0.99,
    "gap_to_reference_max": 1e-3,
}
#: Share of the random problems with moving ends (start and end velocity and acceleration drawn
#: within 30 % of the limits), and of those with a jerk weight.
MOVING_ENDS_EVERY = 4
#: toppra's discretisations, tried in turn until one parameterises the path: (grid intervals,
#: scheme 1 interpolation or 0 collocation).
TOPPRA_SCHEMES = ((1000, 1), (500, 1), (2000, 1), (1000, 0))


def random_problems(
    n: int, seed: int = 0, n_waypoints: int = 10
) -> list[tuple[str, timejerk.TimeJerkProblem]]:
    """Seeded random problems over every shipped rig's limits, the rigs taken in turn.

    Each problem has ``n_waypoints`` waypoints drawn uniformly over the rig's joint ranges
    (swing included where the rig has one), the rig's velocity and acceleration limits and no
    position bounds (eq 3 as printed). Even problems are pure minimum time (``w_jerk = 0``); odd
    ones weigh the jerk so that it is a share ``rho`` (log-uniform in 0.01..1) of the time at
    the search's start: ``w_jerk = rho T0 / jerk0``. Every ``MOVING_ENDS_EVERY``-th problem has
    moving ends (velocity and acceleration within 30 % of the limits).

    Returns:
        ``(rig name, problem)`` pairs.
    """
    if n < 1 or n_waypoints < 2:
        raise ConfigurationError(
            f"need at least 1 problem and 2 waypoints; got {n} problems, {n_waypoints} waypoints"
        )
    rng = np.random.default_rng(seed)
    rigs = [load_rig(name) for name in profile_names()]
    out = []
    for k in range(n):
        rig = rigs[k % len(rigs)]
        joints = ((rig.swing.joint,) if rig.swing is not None else ()) + rig.joints
        lo = np.array([j.min_rad for j in joints])
        hi = np.array([j.max_rad for j in joints])
        v_max = np.array([j.velocity_max_rad_s for j in joints])
        a_max = np.array([j.acceleration_max_rad_s2 for j in joints])
        q = lo + (hi - lo) * rng.random((n_waypoints, len(joints)))
        ends: dict[str, Any] = {}
        if k % MOVING_ENDS_EVERY == MOVING_ENDS_EVERY - 1:
            ends = {
                "start_velocity_rad_s": 0.3 * v_max * rng.uniform(-1.0, 1.0, len(joints)),
                "end_velocity_rad_s": 0.3 * v_max * rng.uniform(-1.0, 1.0, len(joints)),
                "start_acceleration_rad_s2": 0.3 * a_max * rng.uniform(-1.0, 1.0, len(joints)),
                "end_acceleration_rad_s2": 0.3 * a_max * rng.uniform(-1.0, 1.0, len(joints)),
            }
        problem = timejerk.TimeJerkProblem.create(q, v_max, a_max, **ends)
        if k % 2 == 1:
            h0 = timejerk.start_durations(problem)
            jerk0 = timejerk.interpolate(problem, h0).jerk_integral
            rho = 10.0 ** rng.uniform(-2.0, 0.0)
            problem = timejerk.TimeJerkProblem.create(
                q, v_max, a_max, w_jerk=rho * float(np.sum(h0)) / jerk0, **ends
            )
        out.append((rig.name, problem))
    return out


@dataclass(frozen=True, slots=True, eq=False)
class ReferenceSolution:
    """What IPOPT returned for one problem.

    Attributes:
        ok: IPOPT reported success.
        status: IPOPT's return status.
        objective: ``w_jerk * jerk integral + w_time * T`` of its answer.
        trajectory: Its answer as a trajectory (durations and coefficients), for checks.
        solve_s: Wall time of the solver call (the NLP is built once per size).
    """

    ok: bool
    status: str
    objective: float
    trajectory: timejerk.TimeJerkTrajectory
    solve_s: float


class CasadiReference:
    """Zhao eq 3 as one NLP over coefficients and durations, solved by IPOPT (module docstring).

    One solver is built per (waypoints, joints) size and reused with the problem as parameters.
    Needs casadi (the ``reference`` extra).
    """

    def __init__(self, tolerance: float = 1e-10, max_iterations: int = 3000) -> None:
        import casadi

        self._ca = casadi
        self._opts = {
            "ipopt.tol": tolerance,
            "ipopt.max_iter": max_iterations,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "print_time": False,
        }
        self._solvers: dict[tuple[int, int], tuple[Any, FloatArray, FloatArray]] = {}

    def _build(self, n_way: int, n_j: int) -> tuple[Any, FloatArray, FloatArray]:
        ca = self._ca
        m = n_way + 1
        h = ca.SX.sym("h", m)
        c = ca.SX.sym("c", m * n_j * 4)
        lam = ca.SX.sym("lam", m * n_j * 2)
        par = ca.SX.sym("p", n_way * n_j + 6 * n_j + 2)
        y = ca.reshape(par[: n_way * n_j], n_j, n_way).T
        off = n_way * n_j
        v0, vn, a0, an, v_max, a_max = (par[off + k * n_j : off + (k + 1) * n_j] for k in range(6))
        w_jerk, w_time = par[off + 6 * n_j], par[off + 6 * n_j + 1]
        way = (0, *range(2, m - 1), m)

        def coef(i: int, j: int, k: int) -> Any:
            return c[(i * n_j + j) * 4 + k]

        eq: list[Any] = []
        ineq: list[Any] = []
        jerk = 0
        for j in range(n_j):
            for i in range(m):
                c0, c1, c2, c3 = (coef(i, j, k) for k in range(4))
                hi = h[i]
                end = (
                    c0 + c1 * hi + c2 * hi**2 + c3 * hi**3,
                    c1 + 2 * c2 * hi + 3 * c3 * hi**2,
                    2 * c2 + 6 * c3 * hi,
                )
                if i + 1 < m:
                    nxt = (coef(i + 1, j, 0), coef(i + 1, j, 1), 2 * coef(i + 1, j, 2))
                    eq += [end[d] - nxt[d] for d in range(3)]
                else:
                    eq += [end[0] - y[n_way - 1, j], end[1] - vn[j], end[2] - an[j]]
                if i in way[:-1]:
                    eq.append(c0 - y[way.index(i), j])
                if i == 0:
                    eq += [c1 - v0[j], 2 * c2 - a0[j]]
                jerk += 36 * c3**2 * hi
                ineq += [1 - 2 * c2 / a_max[j], 1 + 2 * c2 / a_max[j]]
                ineq += [1 - end[2] / a_max[j], 1 + end[2] / a_max[j]]
                # Velocity c1 + 2 c2 h u + 3 c3 h^2 u^2 within +-V on u in [0, 1] (Lukacs).
                p0, p1, p2 = c1 / v_max[j], 2 * c2 * hi / v_max[j], 3 * c3 * hi**2 / v_max[j]
                for side, sign in enumerate((-1, 1)):
                    q0, q1, q2 = 1 + sign * p0, sign * p1, sign * p2
                    lm = lam[(i * n_j + j) * 2 + side]
                    ineq += [q0, q2 + lm, 4 * q0 * (q2 + lm) - (q1 - lm) ** 2]
        f = w_jerk * jerk + w_time * ca.sum1(h)
        g = ca.vertcat(*eq, *ineq)
        nlp = {"x": ca.vertcat(h, c, lam), "p": par, "f": f, "g": g}
        solver = ca.nlpsol("timejerk_reference", "ipopt", nlp, self._opts)
        lbg = np.zeros(len(eq) + len(ineq))
        ubg = np.concatenate([np.zeros(len(eq)), np.full(len(ineq), np.inf)])
        return solver, lbg, ubg

    def solve(
        self, problem: timejerk.TimeJerkProblem, start_s: FloatArray | None = None
    ) -> ReferenceSolution:
        """Solve ``problem`` from the spline at ``start_s`` (default: the generator's own start,
        :func:`~rt_runtime.trajectory.timejerk.start_durations`, not its answer).

        Raises:
            ConfigurationError: The problem has position bounds (not part of eq 3 here).
        """
        if problem.position_min_rad is not None:
            raise ConfigurationError("the CasADi reference solves eq 3 without position bounds")
        n_way, n_j = problem.waypoints_rad.shape
        key = (n_way, n_j)
        if key not in self._solvers:
            self._solvers[key] = self._build(n_way, n_j)
        solver, lbg, ubg = self._solvers[key]
        m = problem.n_pieces
        h0 = timejerk.start_durations(problem) if start_s is None else np.asarray(start_s)
        guess = timejerk.interpolate(problem, h0)
        c0 = guess.coefficients[..., ::-1]  # (m, J, 4) lowest power first
        # Multipliers of the certificate: |linear coefficient| of the normalised velocity.
        lin = np.abs(2.0 * c0[..., 2] * h0[:, None]) / problem.velocity_max_rad_s
        lam0 = np.repeat((lin + 1e-3)[..., None], 2, axis=-1)
        x0 = np.concatenate([h0, c0.reshape(-1), lam0.reshape(-1)])
        lbx = np.concatenate(
            [
                np.full(m, timejerk.MIN_DURATION_S),
                np.full(m * n_j * 4, -np.inf),
                np.zeros(m * n_j * 2),
            ]
        )
        par = np.concatenate(
            [
                problem.waypoints_rad.reshape(-1),
                problem.start_velocity_rad_s,
                problem.end_velocity_rad_s,
                problem.start_acceleration_rad_s2,
                problem.end_acceleration_rad_s2,
                problem.velocity_max_rad_s,
                problem.acceleration_max_rad_s2,
                [problem.w_jerk, problem.w_time],
            ]
        )
        t0 = time.perf_counter()
        res = solver(x0=x0, lbx=lbx, ubx=np.inf, lbg=lbg, ubg=ubg, p=par)
        solve_s = time.perf_counter() - t0
        stats = solver.stats()
        x = np.asarray(res["x"]).reshape(-1)
        h = x[:m]
        coef = x[m : m + m * n_j * 4].reshape(m, n_j, 4)
        jerk = float(np.sum(36.0 * coef[..., 3] ** 2 * h[:, None]))
        traj = timejerk.TimeJerkTrajectory(
            problem=problem,
            piece_durations_s=h,
            coefficients=coef[..., ::-1],
            jerk_integral=jerk,
            objective=float(res["f"]),
        )
        return ReferenceSolution(
            ok=bool(stats["success"]),
            status=str(stats["return_status"]),
            objective=float(res["f"]),
            trajectory=traj,
            solve_s=solve_s,
        )


class _TrajectoryPath:
    """A trajectory as toppra's geometric path (path parameter = the trajectory's time)."""

    def __init__(self, traj: timejerk.TimeJerkTrajectory) -> None:
        self.traj = traj

    def __call__(self, s: Any, order: int = 0) -> FloatArray:
        return self.traj.sample(s, order)

    @property
    def dof(self) -> int:
        return self.traj.problem.n_joints

    @property
    def path_interval(self) -> FloatArray:
        return np.array([0.0, self.traj.duration_s])

    @property
    def waypoints(self) -> None:
        return None


def toppra_bound(traj: timejerk.TimeJerkTrajectory, rate_hz: float = 1000.0) -> tuple[float, float]:
    """toppra's time-optimal duration of ``traj``'s geometric path, made feasible.

    Returns:
        ``(T_s, scale)``: the duration after the uniform slow-down that puts toppra's output,
        resampled at ``rate_hz``, within the limits, and that slow-down factor (>= 1).

    Raises:
        PlanningError: toppra found no parameterisation.
    """
    import toppra
    import toppra.algorithm
    import toppra.constraint

    p = traj.problem
    path_cls = type(
        "TimeJerkPath", (_TrajectoryPath, toppra.interpolator.AbstractGeometricPath), {}
    )
    path = path_cls(traj)
    v_lim = np.stack([-p.velocity_max_rad_s, p.velocity_max_rad_s], axis=1)
    a_lim = np.stack([-p.acceleration_max_rad_s2, p.acceleration_max_rad_s2], axis=1)
    # The path parameter is the trajectory's own time, so a moving end has path speed 1.
    sd_start = 1.0 if np.any(p.start_velocity_rad_s != 0.0) else 0.0
    sd_end = 1.0 if np.any(p.end_velocity_rad_s != 0.0) else 0.0
    out = None
    # Interpolation first (it holds the limits closely between gridpoints: slow-downs of
    # ~1.003); it is reported uncontrollable on some grids of paths that start at rest (path
    # derivative zero there), so other grids, then collocation (slow-downs of ~1.7).
    for points, scheme in TOPPRA_SCHEMES:
        acc = toppra.constraint.JointAccelerationConstraint(a_lim, discretization_scheme=scheme)
        instance = toppra.algorithm.TOPPRA(
            [toppra.constraint.JointVelocityConstraint(v_lim), acc],
            path,
            gridpoints=np.linspace(0.0, traj.duration_s, points + 1),
            parametrizer="ParametrizeConstAccel",
        )
        out = instance.compute_trajectory(sd_start, sd_end)
        if out is not None:
            break
    if out is None:
        raise PlanningError("toppra found no time parameterisation of the path")
    duration = float(out.duration)
    t = np.append(np.arange(0.0, duration, 1.0 / rate_hz), duration)
    v = np.max(np.abs(out(t, 1)), axis=0) / p.velocity_max_rad_s
    a = np.max(np.abs(out(t, 2)), axis=0) / p.acceleration_max_rad_s2
    scale = max(1.0, float(np.max(v)), math.sqrt(float(np.max(a))))
    return duration * scale, scale


def bench_timejerk(
    n_problems: int = 200, seed: int = 0, n_waypoints: int = 10, *, reference: bool = True
) -> dict[str, Any]:
    """The generator on :func:`random_problems`, with both references in the same run.

    Each problem is planned once untimed (warm-up of the first) and once timed. ``feasible``
    counts problems solved and within every limit by the exact check and on the 1 kHz resample.
    With ``reference`` (needs casadi and toppra) every solved problem is also solved by
    :class:`CasadiReference` from the generator's start, and bounded by :func:`toppra_bound`.

    Returns:
        JSON-ready dict: ``problems``, ``solve_ms`` (p50, p99, max; wall time),
        ``solve_cpu_ms`` (the same in process CPU time: apart from other work on the machine,
        whose ``load_average`` at the end is given), ``feasible`` (fraction),
        ``gap_to_reference`` (p50, max of ``(ours - reference) / reference`` objectives over the
        problems both solved; null without reference), ``t_over_toppra`` (p50, max of our T over
        toppra's feasible time-optimal T of our path), and more (README).
    """
    problems = random_problems(n_problems, seed, n_waypoints)
    timejerk.plan(problems[0][1])
    solve_s: list[float] = []
    cpu_s: list[float] = []
    by_joints: dict[str, list[float]] = {}
    failures: list[dict[str, Any]] = []
    trajectories: list[timejerk.TimeJerkTrajectory | None] = []
    exact_max = 0.0
    sampled_max = 0.0
    feasible = 0
    iterations: list[float] = []
    for k, (rig, problem) in enumerate(problems):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            traj = timejerk.plan(problem)
        except PlanningError as e:
            failures.append({"problem": k, "rig": rig, "error": str(e)})
            trajectories.append(None)
            continue
        dt = time.perf_counter() - t0
        cpu_s.append(time.process_time() - c0)
        solve_s.append(dt)
        by_joints.setdefault(str(problem.n_joints), []).append(dt)
        iterations.append(traj.iterations)
        exact = traj.limit_check()
        sampled = traj.sampled_limit_check(1000.0)
        exact_max = max(
            exact_max, float(np.max(exact.velocity_ratio)), float(np.max(exact.acceleration_ratio))
        )
        sampled_max = max(
            sampled_max,
            float(np.max(sampled.velocity_ratio)),
            float(np.max(sampled.acceleration_ratio)),
        )
        if exact.within_limits and sampled.within_limits:
            feasible += 1
        else:
            failures.append({"problem": k, "rig": rig, "error": "outside the limits"})
        trajectories.append(traj)

    def ms(values: list[float]) -> dict[str, float] | None:
        if not values:
            return None
        return Distribution.spread(np.array(values) * 1e3).to_json()

    out: dict[str, Any] = {
        "problems": len(problems),
        "waypoints": n_waypoints,
        "seed": seed,
        "solve_ms": ms(solve_s),
        "solve_ms_by_joints": {k: ms(v) for k, v in sorted(by_joints.items())},
        "solve_cpu_ms": ms(cpu_s),
        "load_average": list(os.getloadavg()),
        "iterations": Distribution.spread(iterations).to_json()
        if iterations
        else None,
        "feasible": feasible / len(problems),
        "solved": len(solve_s) / len(problems),
        "exact_ratio_max": exact_max,
        "sampled_ratio_max": sampled_max,
        "failures": failures,
        "gap_to_reference": None,
        "t_over_toppra": None,
    }
    if reference:
        out.update(_references(problems, trajectories, solve_s))
    out["goals"] = GOALS
    sm, gap = out["solve_ms"], out["gap_to_reference"]
    out["met"] = {
        "solve_ms_p50": sm is not None and sm["p50"] <= GOALS["solve_ms_p50_max"],
        "solve_ms_p99": sm is not None and sm["p99"] <= GOALS["solve_ms_p99_max"],
        "feasible": out["feasible"] >= GOALS["feasible_min"],
        "gap_to_reference": None
        if gap is None
        else bool(gap["max"] <= GOALS["gap_to_reference_max"]),
    }
    return out


def _references(
    problems: list[tuple[str, timejerk.TimeJerkProblem]],
    trajectories: list[timejerk.TimeJerkTrajectory | None],
    solve_s: list[float],
) -> dict[str, Any]:
    """The CasADi/IPOPT and toppra comparisons of :func:`bench_timejerk`."""
    ref = CasadiReference()
    gaps: list[float] = []
    ref_s: list[float] = []
    ref_failed: list[dict[str, Any]] = []
    ref_ratio_max = 0.0
    t_ratio: list[float] = []
    slowdowns: list[float] = []
    toppra_failed: list[dict[str, Any]] = []
    for k, ((rig, problem), traj) in enumerate(zip(problems, trajectories, strict=True)):
        if traj is None:
            continue
        sol = ref.solve(problem)
        if sol.ok:
            ref_s.append(sol.solve_s)
            gaps.append((traj.objective - sol.objective) / abs(sol.objective))
            chk = sol.trajectory.limit_check()
            ref_ratio_max = max(
                ref_ratio_max,
                float(np.max(chk.velocity_ratio)),
                float(np.max(chk.acceleration_ratio)),
            )
        else:
            ref_failed.append({"problem": k, "rig": rig, "status": sol.status})
        try:
            t_bound, slow = toppra_bound(traj)
        except PlanningError as e:
            toppra_failed.append({"problem": k, "rig": rig, "error": str(e)})
            continue
        t_ratio.append(traj.duration_s / t_bound)
        slowdowns.append(slow)
    ours_p50 = float(np.percentile(solve_s, 50)) if solve_s else math.nan
    ref_p50 = float(np.percentile(ref_s, 50)) if ref_s else math.nan
    return {
        "gap_to_reference": {
            "p50": float(np.percentile(gaps, 50)),
            "max": float(np.max(gaps)),
            "min": float(np.min(gaps)),
        }
        if gaps
        else None,
        "t_over_toppra": {
            "p50": float(np.percentile(t_ratio, 50)),
            "max": float(np.max(t_ratio)),
            "min": float(np.min(t_ratio)),
        }
        if t_ratio
        else None,
        "reference": {
            "solver": "casadi ipopt, full NLP (coefficients and durations)",
            "solved": len(gaps),
            "failed": ref_failed,
            "solve_ms": Distribution.spread(np.array(ref_s) * 1e3).to_json()
            if ref_s
            else None,
            "reference_over_ours_solve_p50": ref_p50 / ours_p50,
            "exact_ratio_max": ref_ratio_max,
        },
        "toppra": {
            "schemes": [list(x) for x in TOPPRA_SCHEMES],
            "bounded": len(t_ratio),
            "failed": toppra_failed,
            "slowdown": {
                "p50": float(np.percentile(slowdowns, 50)),
                "max": float(np.max(slowdowns)),
            }
            if slowdowns
            else None,
        },
    }
