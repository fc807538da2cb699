"""One-shot digging cycle: evaluation of candidate sextic trajectories (Yao section 4.2).

A dig goes from an entry pose to an exit pose along one sextic per joint (Yao eq 9-10, corrected
in DESIGN.md); the free parameters are ``(a16, a26, a36, T)``. This module evaluates many
candidates at once, batched over problems and candidates ``(B, P)``: the tip path, joint torques
from the arm dynamics plus Yao's digging resistance (eq 7-8), driving power and energy W_E, the
excavated volume V_p, the initial digging angle theta_p, the normalised objective of eq 11 and
every constraint of eq 12 as a signed, normalised violation (<= 0 satisfied).

Choices where the paper is silent (each also stated where it is computed):

- Power is the sum over joints of the positive mechanical power max(tau_i qd_i, 0): servo drives
  do not recover energy, so braking a joint costs nothing and earns nothing. W_E integrates it.
- V_p is the area between the tip path and the material surface y = H, computed exactly for the
  sampled (piecewise linear) path with Green's theorem on the path clipped at y = H, times the
  bucket width b.
- theta_p is the angle below the horizontal of the tip's direction of motion where it enters the
  material. When the dig starts on the surface, velocity and acceleration are zero there, so the
  direction is the limit of the motion direction: J(q0) * a3 (the cubic term leads).
- The digging depth h of eq 8 is the tip's depth below the surface H.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime import dynamics, kinematics, soil
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning.pso import pso_minimize
from rt_runtime.planning.reference import de_minimize
from rt_runtime.rig import Planning, Rig
from rt_runtime.trajectory import sextic

FloatArray = NDArray[np.float64]

DEFAULT_SAMPLES = 101


class DigType(IntEnum):
    """The two trajectory types of Yao 4.2, told apart by theta_p."""

    DOWNWARD = 0
    BACKWARD = 1


CONSTRAINT_NAMES: tuple[str, ...] = (
    "angle_min_boom",
    "angle_min_stick",
    "angle_min_bucket",
    "angle_max_boom",
    "angle_max_stick",
    "angle_max_bucket",
    "velocity_boom",
    "velocity_stick",
    "velocity_bucket",
    "acceleration_boom",
    "acceleration_stick",
    "acceleration_bucket",
    "torque_boom",
    "torque_stick",
    "torque_bucket",
    "power",
    "theta_p_min",
    "theta_p_max",
    "volume_min",
    "volume_max",
    "time_min",
    "time_max",
)


@dataclass(frozen=True, slots=True)
class Problem:
    """One one-shot planning problem (the PINN's input).

    Attributes:
        q_start_rad: Entry pose (3,).
        q_end_rad: Exit pose (3,).
        surface_y_m: Material surface height H in the arm frame.
        dig_type: Downward or backward (sets the theta_p range).
    """

    q_start_rad: tuple[float, float, float]
    q_end_rad: tuple[float, float, float]
    surface_y_m: float
    dig_type: DigType


@dataclass(frozen=True, slots=True)
class Evaluation:
    """Everything computed for a batch of candidates, arrays shaped ``(B, P)`` unless noted.

    Attributes:
        T_s: Digging time.
        volume_m3: Excavated volume V_p.
        energy_j: Energy W_E.
        theta_p_rad: Initial digging angle.
        peak_power_w: Largest total positive power.
        peak_torque_nm: Largest |torque| per joint, ``(B, P, 3)``.
        objective: Yao eq 11.
        violations: Signed normalised constraint values ``(B, P, n)``, names in
            :data:`CONSTRAINT_NAMES`; <= 0 is satisfied.
        total_violation: Sum of the positive parts of ``violations``.
    """

    T_s: FloatArray
    volume_m3: FloatArray
    energy_j: FloatArray
    theta_p_rad: FloatArray
    peak_power_w: FloatArray
    peak_torque_nm: FloatArray
    objective: FloatArray
    violations: FloatArray
    total_violation: FloatArray

    @property
    def feasible(self) -> NDArray[np.bool_]:
        """Whether every constraint holds, ``(B, P)``."""
        return self.total_violation <= 0.0


def require_planning(rig: Rig) -> Planning:
    """The rig's planning thresholds.

    Raises:
        ConfigurationError: The profile has no ``[planning]`` table.
    """
    if rig.planning is None:
        raise ConfigurationError(
            f"rig {rig.name!r} has no [planning] table (thresholds of Yao Table 2); "
            "one-shot planning needs one"
        )
    return rig.planning


def theta_p_range(planning: Planning, dig_type: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Lower and upper theta_p bound per problem for the dig types given."""
    t = np.asarray(dig_type)
    down = np.asarray(planning.theta_p_downward_rad)
    back = np.asarray(planning.theta_p_backward_rad)
    is_down = t == DigType.DOWNWARD
    return np.where(is_down, down[0], back[0]), np.where(is_down, down[1], back[1])


def validate_problem(
    rig: Rig, q_start_rad: ArrayLike, q_end_rad: ArrayLike, surface_y_m: ArrayLike
) -> None:
    """Check poses and surface of a batch of problems before planning.

    Raises:
        PlanningError: A NaN, a pose outside the joint limits (naming the joint and problem), or
            a surface that is not finite.
    """
    qs = np.asarray(q_start_rad, dtype=np.float64)
    qe = np.asarray(q_end_rad, dtype=np.float64)
    h = np.asarray(surface_y_m, dtype=np.float64)
    for label, q in (("start", qs), ("end", qe)):
        if q.shape[-1:] != (3,):
            raise PlanningError(f"{label} pose must have shape (..., 3); got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise PlanningError(f"{label} pose contains NaN or infinity")
        bad = (q < rig.q_min_rad - 1e-12) | (q > rig.q_max_rad + 1e-12)
        if np.any(bad):
            idx = np.argwhere(bad)[0]
            j = rig.joints[int(idx[-1])]
            where = f" (problem {tuple(int(i) for i in idx[:-1])})" if q.ndim > 1 else ""
            raise PlanningError(
                f"{label} pose{where}: {j.name} at {np.degrees(q[tuple(idx)]):.3f} deg is outside "
                f"[{np.degrees(j.min_rad):.3f}, {np.degrees(j.max_rad):.3f}] deg"
            )
    if not np.all(np.isfinite(h)):
        raise PlanningError("surface height H contains NaN or infinity")


def excavated_area_m2(x_m: FloatArray, y_m: FloatArray, surface_y_m: ArrayLike) -> FloatArray:
    """Area between a sampled tip path and the surface y = H, exact for the polyline.

    The path is clipped to the half-plane y <= H (crossings interpolated exactly) and closed along
    the surface; Green's theorem gives the area as |sum of integral (H - y) dx| over the clipped
    segments (the closing segment on y = H adds nothing).

    Args:
        x_m: Path x, ``(..., m)``.
        y_m: Path y, ``(..., m)``.
        surface_y_m: H, broadcastable to ``(...)``.

    Returns:
        Area in m^2, ``(...)``.
    """
    h = np.asarray(surface_y_m, dtype=np.float64)[..., None]
    d0 = h - y_m[..., :-1]  # depth below the surface at the segment ends (> 0 inside material)
    d1 = h - y_m[..., 1:]
    dx = x_m[..., 1:] - x_m[..., :-1]
    p0 = np.maximum(d0, 0.0)
    p1 = np.maximum(d1, 0.0)
    both = (d0 >= 0.0) & (d1 >= 0.0)
    # One end inside: only the fraction f of the segment below the surface counts, a triangle.
    denom = np.where(both, 1.0, np.abs(d0) + np.abs(d1))
    denom = np.where(denom > 0.0, denom, 1.0)
    frac = np.where(both, 1.0, np.maximum(d0, d1) / denom)
    seg = np.where(both, 0.5 * (p0 + p1) * dx, 0.5 * (p0 + p1) * frac * dx)
    return np.asarray(np.abs(np.sum(seg, axis=-1)), dtype=np.float64)


def _entry_angle(
    rig: Rig,
    q_start: FloatArray,
    a3: FloatArray,
    x: FloatArray,
    y: FloatArray,
    surface_y: FloatArray,
) -> FloatArray:
    """theta_p: angle below the horizontal of the motion direction where the tip enters.

    A dig that starts on or below the surface (within 1 mm) enters at t = 0, where velocity and
    acceleration vanish: its direction is the limit J(q0) a3, the cubic term leading. A dig that
    starts above the surface enters on the first path segment that reaches below it. A path
    that never enters gets -90 deg, which violates every theta_p range.
    """
    h = surface_y[:, None]  # (B, 1) against paths (B, P, m)
    below = y < h[..., None]
    k = np.clip(np.argmax(below, axis=-1), 1, y.shape[-1] - 1)[..., None]
    dx = (np.take_along_axis(x, k, -1) - np.take_along_axis(x, k - 1, -1))[..., 0]
    dy = (np.take_along_axis(y, k, -1) - np.take_along_axis(y, k - 1, -1))[..., 0]
    jac = kinematics.jacobian(rig, q_start)[..., :2, :]  # (B, 2, 3)
    d0 = np.einsum("bij,bpj->bpi", jac, a3)
    at_start = y[..., 0] <= h + 1e-3
    dx = np.where(at_start, d0[..., 0], dx)
    dy = np.where(at_start, d0[..., 1], dy)
    angle = np.arctan2(-dy, np.abs(dx))
    # A start within the tolerance counts as an entry whatever the last bit of y0 says: the
    # poses are solved for y = H, so "below" at t = 0 is rounding noise.
    return np.where(np.any(below, axis=-1) | at_start, angle, -0.5 * np.pi)


def evaluate(
    rig: Rig,
    q_start_rad: ArrayLike,
    q_end_rad: ArrayLike,
    surface_y_m: ArrayLike,
    dig_type: ArrayLike,
    a6: ArrayLike,
    T_s: ArrayLike,
    n_samples: int = DEFAULT_SAMPLES,
) -> Evaluation:
    """Evaluate P candidate trajectories for each of B problems in one numpy pass.

    Args:
        rig: The rig; needs a ``[planning]`` table.
        q_start_rad: Entry poses ``(B, 3)``.
        q_end_rad: Exit poses ``(B, 3)``.
        surface_y_m: Material surface height H per problem ``(B,)``.
        dig_type: :class:`DigType` per problem ``(B,)`` (or one for all).
        a6: Sixth-order coefficients ``(B, P, 3)`` in rad/s^6.
        T_s: Digging times ``(B, P)``.
        n_samples: Samples per trajectory (uniform in time, ends included) at which limits,
            torque and power are checked and the path is taken.

    Returns:
        The :class:`Evaluation`, arrays ``(B, P)``.

    Raises:
        ConfigurationError: The rig has no planning table.
        PlanningError: Non-finite inputs or T <= 0 (from the sextic).
    """
    return _evaluate(rig, q_start_rad, q_end_rad, surface_y_m, dig_type, a6, T_s, n_samples)[0]


def _evaluate(
    rig: Rig,
    q_start_rad: ArrayLike,
    q_end_rad: ArrayLike,
    surface_y_m: ArrayLike,
    dig_type: ArrayLike,
    a6: ArrayLike,
    T_s: ArrayLike,
    n_samples: int,
) -> tuple[Evaluation, FloatArray, FloatArray]:
    """:func:`evaluate`, also returning the sampled ``qd`` and ``qdd`` ``(B, P, m, 3)``."""
    planning = require_planning(rig)
    qs = np.asarray(q_start_rad, dtype=np.float64)
    qe = np.asarray(q_end_rad, dtype=np.float64)
    h = np.asarray(surface_y_m, dtype=np.float64)
    T = np.asarray(T_s, dtype=np.float64)
    coeffs = sextic.sextic_coefficients(qs[:, None, :], qe[:, None, :], a6, T)  # (B, P, 3, 7)
    t, q, qd, qdd, _ = sextic.evaluate(coeffs, T, n_samples)
    pose, twist = kinematics.tip_state(rig, q, qd)  # (B, P, m, 3) each
    f_tip = soil.yao_resistance(rig, pose, twist, h[:, None, None])
    tau = dynamics.inverse_dynamics(rig, q, qd, qdd, f_tip)
    p_joint = dynamics.joint_power(tau, qd)
    # Servo drives do not regenerate: power and energy count each joint's positive part.
    power = np.sum(np.maximum(p_joint, 0.0), axis=-1)
    energy = dynamics.energy_j(t, p_joint, mode="positive")
    volume = excavated_area_m2(pose[..., 0], pose[..., 1], h[:, None]) * rig.bucket.width_m
    theta_p = _entry_angle(rig, qs, coeffs[..., 3], pose[..., 0], pose[..., 1], h)

    span = rig.q_max_rad - rig.q_min_rad
    v = np.empty((*T.shape, len(CONSTRAINT_NAMES)), dtype=np.float64)
    v[..., 0:3] = (rig.q_min_rad - np.min(q, axis=-2)) / span
    v[..., 3:6] = (np.max(q, axis=-2) - rig.q_max_rad) / span
    v[..., 6:9] = np.max(np.abs(qd), axis=-2) / rig.qd_max_rad_s - 1.0
    v[..., 9:12] = np.max(np.abs(qdd), axis=-2) / rig.qdd_max_rad_s2 - 1.0
    peak_tau = np.max(np.abs(tau), axis=-2)
    v[..., 12:15] = peak_tau / rig.tau_max_nm - 1.0
    peak_power = np.max(power, axis=-1)
    v[..., 15] = peak_power / planning.power_max_w - 1.0
    lo, hi = theta_p_range(planning, np.broadcast_to(np.asarray(dig_type), h.shape))
    tp_span = (hi - lo)[:, None]
    v[..., 16] = (lo[:, None] - theta_p) / tp_span
    v[..., 17] = (theta_p - hi[:, None]) / tp_span
    v_span = planning.volume_max_m3 - planning.volume_min_m3
    v[..., 18] = (planning.volume_min_m3 - volume) / v_span
    v[..., 19] = (volume - planning.volume_max_m3) / v_span
    t_span = planning.t_max_s - planning.t_min_s
    v[..., 20] = (planning.t_min_s - T) / t_span
    v[..., 21] = (T - planning.t_max_s) / t_span
    total = np.sum(np.maximum(v, 0.0), axis=-1)

    ev = Evaluation(
        T_s=T,
        volume_m3=volume,
        energy_j=energy,
        theta_p_rad=theta_p,
        peak_power_w=peak_power,
        peak_torque_nm=peak_tau,
        objective=objective(planning, T, energy, volume),
        violations=v,
        total_violation=total,
    )
    return ev, qd, qdd


def objective(
    planning: Planning, T_s: ArrayLike, energy_j: ArrayLike, volume_m3: ArrayLike
) -> FloatArray:
    """Yao eq 11: lambda1 T_t + lambda2 E_e + lambda3 V_v, each normalised by its thresholds."""
    l1, l2, l3 = planning.weights
    t_t = (np.asarray(T_s) - planning.t_min_s) / (planning.t_max_s - planning.t_min_s)
    e_e = (np.asarray(energy_j) - planning.energy_min_j) / (
        planning.energy_max_j - planning.energy_min_j
    )
    v_v = (planning.volume_max_m3 - np.asarray(volume_m3)) / (
        planning.volume_max_m3 - planning.volume_min_m3
    )
    return np.asarray(l1 * t_t + l2 * e_e + l3 * v_v, dtype=np.float64)


# The optimiser searches K = -a6 T^6 (rad), the sextic's bulge away from the quintic path
# (theta = theta1 + D q(s) + K p(s), p peaking at 1/64 at mid-time), instead of a6 itself: a6 is
# ~1e-5 rad/s^6 for multi-second digs and its effect on the path depends on T, while K fixes the
# path's shape and T only its timing. The bound lets the mid-path bulge reach a quarter of each
# joint's range.
K_BOUND_PER_RANGE = 16.0


def search_bounds(rig: Rig) -> tuple[FloatArray, FloatArray]:
    """Lower and upper bounds of the particle (K1, K2, K3, T_s)."""
    planning = require_planning(rig)
    k = K_BOUND_PER_RANGE * (rig.q_max_rad - rig.q_min_rad)
    return (
        np.array([*(-k), planning.t_min_s], dtype=np.float64),
        np.array([*k, planning.t_max_s], dtype=np.float64),
    )


def a6_from_particle(x: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """``(a6 (..., 3) rad/s^6, T_s (...))`` from particles ``(K1, K2, K3, T_s)`` shaped (..., 4)."""
    xa = np.asarray(x, dtype=np.float64)
    T = xa[..., 3]
    return -xa[..., :3] / T[..., None] ** 6, T


def particle_from_a6(a6: ArrayLike, T_s: ArrayLike) -> FloatArray:
    """Inverse of :func:`a6_from_particle`."""
    a = np.asarray(a6, dtype=np.float64)
    T = np.asarray(T_s, dtype=np.float64)
    return np.concatenate([-a * T[..., None] ** 6, T[..., None]], axis=-1)


@dataclass(frozen=True, slots=True)
class Solution:
    """The planned dig of one problem.

    Attributes:
        problem: What was solved.
        a6: Sixth-order coefficients (3,) in rad/s^6.
        T_s: Digging time.
        volume_m3, energy_j, theta_p_rad, objective: Performance of the plan.
        margins: (constraint name, margin) for every constraint of eq 12; a margin >= 0 holds
            (it is the negated normalised violation).
        feasible: Whether every constraint holds.
        solve_s: Wall time of the solve (shared equally when solved in a batch).
        method: ``pso`` or ``de``.
    """

    problem: Problem
    a6: tuple[float, float, float]
    T_s: float
    volume_m3: float
    energy_j: float
    theta_p_rad: float
    objective: float
    margins: tuple[tuple[str, float], ...]
    feasible: bool
    solve_s: float
    method: str

    def trajectory(self) -> sextic.SexticTrajectory:
        """The planned joint trajectory."""
        return sextic.SexticTrajectory(
            np.asarray(self.problem.q_start_rad),
            np.asarray(self.problem.q_end_rad),
            np.asarray(self.a6),
            self.T_s,
        )


def _stack(problems: list[Problem]) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    qs = np.array([p.q_start_rad for p in problems], dtype=np.float64)
    qe = np.array([p.q_end_rad for p in problems], dtype=np.float64)
    h = np.array([p.surface_y_m for p in problems], dtype=np.float64)
    kind = np.array([int(p.dig_type) for p in problems])
    return qs, qe, h, kind


def _solutions(
    rig: Rig, problems: list[Problem], x: FloatArray, solve_s: float, method: str, n_samples: int
) -> list[Solution]:
    qs, qe, h, kind = _stack(problems)
    a6, T = a6_from_particle(x[:, None, :])
    ev = evaluate(rig, qs, qe, h, kind, a6, T, n_samples)
    out = []
    for b, p in enumerate(problems):
        out.append(
            Solution(
                problem=p,
                a6=(float(a6[b, 0, 0]), float(a6[b, 0, 1]), float(a6[b, 0, 2])),
                T_s=float(T[b, 0]),
                volume_m3=float(ev.volume_m3[b, 0]),
                energy_j=float(ev.energy_j[b, 0]),
                theta_p_rad=float(ev.theta_p_rad[b, 0]),
                objective=float(ev.objective[b, 0]),
                margins=tuple(
                    (n, float(-ev.violations[b, 0, i])) for i, n in enumerate(CONSTRAINT_NAMES)
                ),
                feasible=bool(ev.feasible[b, 0]),
                solve_s=solve_s,
                method=method,
            )
        )
    return out


def solve_pso(
    rig: Rig,
    problems: list[Problem],
    *,
    n_particles: int = 40,
    n_iterations: int = 60,
    seed: int = 0,
    n_samples: int = DEFAULT_SAMPLES,
    search_samples: int = 31,
    polish_starts: int = 3,
    workers: int = 1,
) -> list[Solution]:
    """Plan each problem's dig with the PSO teacher: a ring-topology swarm, then SLSQP polish.

    The stages, each batched over all problems:

    1. Yao's PSO over ``(K1, K2, K3, T)`` (inertia weight, cognitive and social terms; settings
       in :mod:`rt_runtime.planning.pso`) with the ring (local-best) topology: the landscape is
       multimodal (different bulge regions K give different local optima) and the global-best
       swarm collapses on the first good region. The swarm evaluates its candidates on a
       coarse grid of ``search_samples`` samples, about 4x cheaper than the default grid; it
       only has to find the right basins.
    2. Polish, an engineering addition beyond the paper: the optima sit on three or four
       constraint boundaries at once (acceleration, torque, volume max, theta_p min, time
       min), where a swarm creeps. :func:`rt_runtime.planning.pso.slsqp_polish` runs SLSQP on
       the ``n_samples`` grid from ``polish_starts`` distinct personal bests: the swarm's best
       first, then the next best ones lying at least a tenth of the box (in every-coordinate
       max norm) from those already chosen, because the swarm is not converged after its
       iterations and a lower-ranked member often sits in a better basin. SLSQP sees every
       constraint of eq 12 separately, with the peak joint velocity and acceleration split by
       sign: ``max |qdd|`` has a kink where its positive and negative peaks are equal (at
       K = 0 for a joint, where many optima lie), on which SLSQP stalls.
    3. The answer is the best, by Deb's rules on the ``n_samples`` grid, of the polished points
       and every personal best re-evaluated there; feasibility is judged on that grid, so the
       coarse search never makes a plan look feasible that is not.

    Each problem draws from its own random stream, seeded by ``seed`` and the problem's data,
    and every evaluation computes each problem's row on its own, so a problem's answer does not
    depend on the other problems of the batch, its position there, or ``workers``, up to
    floating-point rounding: matrix products may round differently for other batch shapes
    (BLAS blocking), which moves an answer by ~1e-10 relative and can, rarely, steer a solve
    into another basin. The same problems, ``seed``, settings and ``workers`` give bitwise the
    same answers.

    Args:
        rig: The rig; needs a ``[planning]`` table.
        problems: The problems to solve.
        n_particles: Particles per problem, >= 2.
        n_iterations: Swarm updates, >= 1.
        seed: Seed of the per-problem random streams, >= 0.
        n_samples: Samples per trajectory for the polish and the final answer (the default grid
            of :func:`evaluate`).
        search_samples: Samples per trajectory during the swarm search, >= 2.
        polish_starts: Personal bests polished per problem, 0 to return the swarm's answer.
        workers: Processes solving contiguous parts of the batch in parallel (forked on
            Linux, spawned elsewhere, where a calling script needs the ``__main__`` guard);
            1 solves in this process.

    Returns:
        One :class:`Solution` per problem, ``solve_s`` the batch's wall time shared equally;
        ``feasible`` is False where no feasible point was found (the solution is then the
        least violating one and must not be executed).

    Raises:
        ConfigurationError: The rig has no planning table, or invalid settings.
        PlanningError: A pose outside the joint limits, or NaN input.
    """
    import time

    if seed < 0:
        raise ConfigurationError(f"seed must be >= 0; got {seed}")
    if search_samples < 2 or n_samples < 2:
        raise ConfigurationError(
            f"search_samples and n_samples must be >= 2; got {search_samples}, {n_samples}"
        )
    if polish_starts < 0 or polish_starts > n_particles:
        raise ConfigurationError(
            f"polish_starts must be in [0, n_particles={n_particles}]; got {polish_starts}"
        )
    if workers < 1:
        raise ConfigurationError(f"workers must be >= 1; got {workers}")
    if not problems:
        return []
    qs, qe, h, _ = _stack(problems)
    validate_problem(rig, qs, qe, h)
    settings = _PsoSettings(n_particles, n_iterations, n_samples, search_samples, polish_starts)
    streams = [_problem_stream(p, seed) for p in problems]

    t0 = time.perf_counter()
    parts = [p for p in np.array_split(np.arange(len(problems)), workers) if p.size]
    if len(parts) == 1:
        x = _pso_part(rig, problems, streams, settings)
    else:
        import multiprocessing
        import sys
        from concurrent.futures import ProcessPoolExecutor

        # fork on Linux: a child starts in milliseconds with everything imported, where spawn
        # re-imports numpy/scipy for about a second per call (fork is unsafe on macOS).
        method = "fork" if sys.platform.startswith("linux") else "spawn"
        context = multiprocessing.get_context(method)
        with ProcessPoolExecutor(len(parts), mp_context=context) as pool:
            futures = [
                pool.submit(
                    _pso_part,
                    rig,
                    [problems[i] for i in p],
                    [streams[i] for i in p],
                    settings,
                )
                for p in parts
            ]
            x = np.concatenate([f.result() for f in futures])
    elapsed = (time.perf_counter() - t0) / len(problems)
    return _solutions(rig, problems, x, elapsed, "pso", n_samples)


def _problem_stream(problem: Problem, seed: int) -> np.random.Generator:
    """The random stream of one problem: seeded by ``seed`` and the problem's exact data."""
    data = np.array(
        [*problem.q_start_rad, *problem.q_end_rad, problem.surface_y_m, int(problem.dig_type)],
        dtype="<f8",
    )
    return np.random.default_rng(np.random.SeedSequence([seed, *data.view("<u4").tolist()]))


@dataclass(frozen=True, slots=True)
class _PsoSettings:
    n_particles: int
    n_iterations: int
    n_samples: int
    search_samples: int
    polish_starts: int


# Polish starts after the first lie at least this far (max norm, fraction of the box) from the
# starts already chosen: closer ones would mostly polish into the same vertex.
_POLISH_MIN_DISTANCE = 0.1
# SLSQP reaches the vertex of a start's basin in 5-10 iterations; the rest of a longer budget
# goes to line searches that rarely gain 0.1 % (measured on 100 scale-model problems).
_POLISH_ITERATIONS = 15


def particle_evaluator(
    rig: Rig, problems: list[Problem], n_samples: int
) -> Callable[[FloatArray], tuple[FloatArray, FloatArray]]:
    """``evaluate(X (B, P, 4)) -> (objective, total violation)`` over particles (K1..K3, T_s)."""
    qs, qe, h, kind = _stack(problems)

    def run(X: FloatArray) -> tuple[FloatArray, FloatArray]:
        a6, T = a6_from_particle(X)
        ev = evaluate(rig, qs, qe, h, kind, a6, T, n_samples)
        return ev.objective, ev.total_violation

    return run


def _pso_part(
    rig: Rig, problems: list[Problem], streams: list[np.random.Generator], settings: _PsoSettings
) -> FloatArray:
    """Stages 1-3 of :func:`solve_pso` for some problems: the chosen particles ``(B, 4)``."""
    from rt_runtime.planning.pso import Topology, deb_argbest, slsqp_polish

    qs, qe, h, kind = _stack(problems)
    lo, hi = search_bounds(rig)
    B = len(problems)

    res = pso_minimize(
        particle_evaluator(rig, problems, settings.search_samples),
        lo,
        hi,
        n_particles=settings.n_particles,
        n_iterations=settings.n_iterations,
        seed=streams,
        topology=Topology.RING,
        n_problems=B,
    )
    assert res.swarm_x is not None and res.swarm_f is not None and res.swarm_violation is not None
    candidates = [res.swarm_x]
    if settings.polish_starts:
        starts = _distinct_starts(
            res.swarm_x, res.swarm_f, res.swarm_violation, settings.polish_starts, hi - lo
        )

        def constraints(rows: NDArray[np.intp], X: FloatArray) -> tuple[FloatArray, FloatArray]:
            return _polish_model(
                rig, qs[rows], qe[rows], h[rows], kind[rows], X, settings.n_samples
            )

        polished = slsqp_polish(constraints, lo, hi, starts, max_iterations=_POLISH_ITERATIONS)
        candidates.append(polished.x_best)
    X = np.concatenate(candidates, axis=1)
    a6, T = a6_from_particle(X)
    ev = evaluate(rig, qs, qe, h, kind, a6, T, settings.n_samples)
    best = deb_argbest(ev.objective, ev.total_violation, 0.0)
    return X[np.arange(B), best]


def _distinct_starts(
    x: FloatArray, f: FloatArray, v: FloatArray, k: int, span: FloatArray
) -> FloatArray:
    """k personal bests per problem ``(B, k, 4)``: the best, then the best far from those chosen.

    Ranked by Deb's rules on the search grid; where fewer than k lie far enough apart, the
    remaining starts are the best ones not yet chosen.
    """
    B, P, _ = x.shape
    # Deb's order as one key: feasible points by objective, then infeasible ones by violation.
    key = np.where(v <= 0.0, f, np.inf)
    order = np.lexsort((key, np.where(v <= 0.0, 0.0, v)), axis=-1)
    ranked = np.take_along_axis(x, order[..., np.newaxis], axis=1)
    rows = np.arange(B)
    chosen = np.zeros((B, P), dtype=np.bool_)
    chosen[:, 0] = True
    nearest = np.max(np.abs(ranked - ranked[:, :1]) / span, axis=-1)  # (B, P)
    for _ in range(1, k):
        far = ~chosen & (nearest >= _POLISH_MIN_DISTANCE)
        # argmax gives the first True in rank order; without one, the best not yet chosen.
        pick = np.where(np.any(far, axis=1), np.argmax(far, axis=1), np.argmax(~chosen, axis=1))
        chosen[rows, pick] = True
        d_new = np.max(np.abs(ranked - ranked[rows, pick][:, np.newaxis]) / span, axis=-1)
        nearest = np.minimum(nearest, d_new)
    # Keep rank order: the swarm's best first.
    return ranked[chosen].reshape(B, k, -1)


def _polish_model(
    rig: Rig,
    qs: FloatArray,
    qe: FloatArray,
    h: FloatArray,
    kind: ArrayLike,
    X: FloatArray,
    n_samples: int,
) -> tuple[FloatArray, FloatArray]:
    """Objective ``(n, S)`` and the smooth constraint pieces ``(n, S, 28)`` for the polish.

    The constraints of :func:`evaluate` (normalised, <= 0 holds) with the six peak-|qd|/|qdd|
    entries replaced by twelve: the positive and the negative peak of each joint's velocity
    and acceleration. Every point is feasible here exactly when it is for :func:`evaluate`.
    """
    a6, T = a6_from_particle(X)
    ev, qd, qdd = _evaluate(rig, qs, qe, h, kind, a6, T, n_samples)
    v = ev.violations
    c = np.concatenate(
        [
            v[..., 0:6],
            np.max(qd, axis=-2) / rig.qd_max_rad_s - 1.0,
            -np.min(qd, axis=-2) / rig.qd_max_rad_s - 1.0,
            np.max(qdd, axis=-2) / rig.qdd_max_rad_s2 - 1.0,
            -np.min(qdd, axis=-2) / rig.qdd_max_rad_s2 - 1.0,
            v[..., 12:],
        ],
        axis=-1,
    )
    return ev.objective, c


def solve_de(
    rig: Rig, problem: Problem, *, seed: int = 0, n_samples: int = DEFAULT_SAMPLES, **options: float
) -> Solution:
    """Plan one dig with scipy's differential evolution on the same objective and constraints.

    The reference the PSO is measured against; slower, thorough.
    """
    import time

    qs, qe, h, _ = _stack([problem])
    validate_problem(rig, qs, qe, h)
    lo, hi = search_bounds(rig)
    t0 = time.perf_counter()
    res = de_minimize(particle_evaluator(rig, [problem], n_samples), lo, hi, seed=seed, **options)  # type: ignore[arg-type]
    elapsed = time.perf_counter() - t0
    return _solutions(rig, [problem], res.x_best, elapsed, "de", n_samples)[0]


@dataclass(frozen=True, slots=True)
class SamplerRanges:
    """Where :func:`sample_problems` draws digs from (arm frame, relative to the rig's ground).

    The tip enters on the material surface H and leaves towards the machine (x decreasing),
    at or a little above H, with the bucket curled. Yao samples a region 0.8 m long and 0.4 m
    deep below the crawler (Fig. 9); the attitudes are those the scale model reaches there.
    The ranges are also the PINN's domain, so they cover every query the trench planner makes:
    entries from 0.55 to 1.10 m (a 0.55-0.70 m long trench of Yao Table 3 placed in the middle
    of the reach), material surfaces down to 0.40 m below the ground, digs 0.15-0.50 m long
    (short finishing cuts to a full backward pass along the bottom). All of a 40-problem draw of
    each type was feasible for the PSO teacher when these were chosen.

    Attributes:
        surface_below_ground_m: Range of ground_y - H (material surface below the ground).
        entry_x_m: Range of the entry tip x.
        length_m: Range of entry x - exit x.
        exit_rise_m: Range of exit y - H.
        entry_attitude_deg: Range of the bucket attitude at entry.
        exit_attitude_deg: Range of the bucket attitude at exit.
    """

    surface_below_ground_m: tuple[float, float]
    entry_x_m: tuple[float, float]
    length_m: tuple[float, float]
    exit_rise_m: tuple[float, float]
    entry_attitude_deg: tuple[float, float]
    exit_attitude_deg: tuple[float, float]


SAMPLER_RANGES: dict[DigType, SamplerRanges] = {
    DigType.DOWNWARD: SamplerRanges(
        surface_below_ground_m=(0.0, 0.25),
        entry_x_m=(0.55, 1.10),
        length_m=(0.15, 0.40),
        exit_rise_m=(0.0, 0.10),
        entry_attitude_deg=(-120.0, -70.0),
        exit_attitude_deg=(-180.0, -140.0),
    ),
    DigType.BACKWARD: SamplerRanges(
        surface_below_ground_m=(0.05, 0.40),
        entry_x_m=(0.55, 1.10),
        length_m=(0.20, 0.50),
        exit_rise_m=(0.0, 0.08),
        entry_attitude_deg=(-140.0, -100.0),
        exit_attitude_deg=(-185.0, -150.0),
    ),
}


def sample_problems(
    rig: Rig,
    n: int,
    dig_type: DigType,
    seed: int = 0,
    ranges: SamplerRanges | None = None,
) -> list[Problem]:
    """Draw ``n`` seeded one-shot problems whose entry and exit poses lie within the joint limits.

    Candidates are drawn from :data:`SAMPLER_RANGES` (or ``ranges``) relative to the rig's
    ground and scaled by the rig's reach against the scale model's; candidates whose inverse
    kinematics fails or leaves the limits are redrawn, so the result is reproducible per seed.

    Raises:
        PlanningError: Fewer than ``n`` valid problems after 200 n draws (ranges unreachable).
    """
    from rt_runtime.errors import KinematicsError

    r = ranges or SAMPLER_RANGES[DigType(dig_type)]
    scale = float(np.sum(rig.lengths_m)) / 1.31  # ranges are given for the scale model's reach
    rng = np.random.default_rng(seed)
    out: list[Problem] = []
    draws = 0
    while len(out) < n:
        draws += 1
        if draws > 200 * n:
            raise PlanningError(
                f"only {len(out)} of {n} {DigType(dig_type).name.lower()} problems are reachable "
                f"on {rig.name} after {draws - 1} draws; widen the sampler ranges"
            )
        u = rng.uniform(size=6)

        def pick(rng_: tuple[float, float], v: float) -> float:
            return rng_[0] + (rng_[1] - rng_[0]) * v

        h = rig.ground_y_m - scale * pick(r.surface_below_ground_m, u[0])
        xe = scale * pick(r.entry_x_m, u[1])
        xx = xe - scale * pick(r.length_m, u[2])
        yx = h + scale * pick(r.exit_rise_m, u[3])
        try:
            qs = kinematics.inverse(rig, xe, h, np.radians(pick(r.entry_attitude_deg, u[4])))
            qe = kinematics.inverse(rig, xx, yx, np.radians(pick(r.exit_attitude_deg, u[5])))
        except KinematicsError:
            continue
        out.append(
            Problem(
                q_start_rad=(float(qs[0]), float(qs[1]), float(qs[2])),
                q_end_rad=(float(qe[0]), float(qe[1]), float(qe[2])),
                surface_y_m=float(h),
                dig_type=DigType(dig_type),
            )
        )
    return out
