"""The ruckig limit guard: stroke limits from the rig, exact passthrough, limited steps, stops.

Checks are identities and finite differences: a plan within the joint limits passes unchanged
(to 1e-9 m); a jump is approached with every output inside the limits (velocity and acceleration
from the guard's state, jerk as the difference quotient of the acceleration, which is exact for
ruckig's piecewise-constant jerk); a stop from full speed ends at rest within the limits.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from numpy.typing import NDArray

from rt_runtime import actuation
from rt_runtime.control.guard import GuardState, LimitGuard, StrokeLimits
from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.trench import joint_move
from rt_runtime.rig import Rig, load_rig
from rt_runtime.trajectory.sextic import SexticTrajectory

PERIOD_S = 0.002
Q0 = np.radians([30.0, -90.0, -60.0])
Q1 = np.radians([10.0, -60.0, -110.0])


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


@pytest.fixture(scope="module")
def limits(rig: Rig) -> StrokeLimits:
    return StrokeLimits.from_rig(rig)


def _stroke_samples(
    rig: Rig, q: NDArray[np.float64], qd: NDArray[np.float64], qdd: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    h = 1e-4
    s = actuation.joint_to_stroke(rig, q)
    j = actuation.stroke_jacobian(rig, q)
    dj = (
        actuation.joint_to_stroke(rig, q + h, check_limits=False)
        - 2.0 * s
        + actuation.joint_to_stroke(rig, q - h, check_limits=False)
    ) / h**2
    return s, j * qd, j * qdd + dj * qd**2


def _sextic_samples(rig: Rig) -> tuple[NDArray[np.float64], ...]:
    traj = SexticTrajectory(Q0, Q1, np.zeros(3), 8.0)
    t = np.arange(int(8.0 / PERIOD_S) + 1) * PERIOD_S
    rows = [traj.sample(float(tk)) for tk in t]
    q, qd, qdd = (np.array([r[i] for r in rows]) for i in range(3))
    return _stroke_samples(rig, q, qd, qdd)


def _ruckig_samples(rig: Rig) -> tuple[NDArray[np.float64], ...]:
    traj, duration = joint_move(rig, Q0, Q1)
    t = np.arange(int(duration / PERIOD_S) + 2) * PERIOD_S
    rows = [traj.at_time(float(min(tk, duration))) for tk in t]
    q, qd, qdd = (np.array([r[i] for r in rows], dtype=np.float64) for i in range(3))
    return _stroke_samples(rig, q, qd, qdd)


def _run(guard: LimitGuard, targets: tuple[NDArray[np.float64], ...]) -> dict[str, NDArray]:
    s, sd, sdd = targets
    out = {k: np.zeros((len(s) - 1, 3)) for k in ("p", "v", "a")}
    states = []
    for k in range(1, len(s)):
        states.append(guard.track(s[k], sd[k], sdd[k]))
        out["p"][k - 1] = guard.position_m
        out["v"][k - 1] = guard.velocity_m_s
        out["a"][k - 1] = guard.acceleration_m_s2
    out["state"] = np.array(states)
    return out


def _assert_within(
    limits: StrokeLimits, p: NDArray, v: NDArray, a: NDArray, p0: NDArray, a0: NDArray
) -> None:
    v_max, a_max, j_max = limits.as_arrays()
    tol = 1 + 1e-6
    assert (np.abs(v) <= v_max * tol + 1e-12).all(), np.abs(v).max(axis=0) / v_max
    assert (np.abs(a) <= a_max * tol + 1e-12).all(), np.abs(a).max(axis=0) / a_max
    dp = np.diff(np.vstack([p0, p]), axis=0) / PERIOD_S
    assert (np.abs(dp) <= v_max * tol + 1e-12).all()
    jerk = np.diff(np.vstack([a0, a]), axis=0) / PERIOD_S
    assert (np.abs(jerk) <= j_max * tol + 1e-9).all(), np.abs(jerk).max(axis=0) / j_max


def test_limits_bound_joint_motions_at_their_limits(rig: Rig, limits: StrokeLimits) -> None:
    v_max, a_max, j_max = limits.as_arrays()
    assert (v_max <= rig.actuators.velocity_max_m_s).all()
    # A time-optimal joint move runs at the joint limits; its stroke derivatives (finite
    # differences of the exact strokes) stay inside the guard's limits without the margin.
    _, sd, sdd = _ruckig_samples(rig)
    assert (np.abs(sd).max(axis=0) <= v_max / 1.02 + 1e-12).all()
    assert (np.abs(sdd).max(axis=0) <= a_max / 1.02 + 1e-12).all()
    jerk = np.diff(sdd, axis=0) / PERIOD_S
    assert (np.abs(jerk).max(axis=0) <= j_max / 1.02).all()
    # ... and the limiting joint uses a good part of them (the bound is not absurdly loose).
    assert (np.abs(sd).max(axis=0) / v_max).max() >= 0.5


def test_limits_are_validated(rig: Rig) -> None:
    with pytest.raises(ConfigurationError, match="margin"):
        StrokeLimits.from_rig(rig, margin=-0.1)
    with pytest.raises(ConfigurationError, match="velocity_m_s"):
        StrokeLimits((0.1, 0.0, 0.1), (1.0, 1.0, 1.0), (1.0, 1.0, 1.0))
    with pytest.raises(ConfigurationError, match="period_s"):
        LimitGuard(StrokeLimits.from_rig(rig), 0.0)


@pytest.mark.parametrize("source", ["sextic", "ruckig"])
def test_a_plan_within_limits_passes_through_unchanged(
    rig: Rig, limits: StrokeLimits, source: str
) -> None:
    targets = _sextic_samples(rig) if source == "sextic" else _ruckig_samples(rig)
    guard = LimitGuard(limits, PERIOD_S)
    guard.reset(targets[0][0])
    t0 = time.perf_counter()
    out = _run(guard, targets)
    cost_us = (time.perf_counter() - t0) / len(out["p"]) * 1e6
    err = np.abs(out["p"] - targets[0][1:]).max()
    assert err <= 1e-9, err
    assert np.abs(out["v"] - np.clip(targets[1][1:], -1, 1)).max() <= 1e-9
    assert (out["state"] == GuardState.PASSTHROUGH).all()
    print(f"\nguard {source}: passthrough error {err:.2e} m, {cost_us:.1f} us per cycle")


def test_a_jump_is_approached_within_the_limits(rig: Rig, limits: StrokeLimits) -> None:
    s0 = actuation.joint_to_stroke(rig, Q0)
    guard = LimitGuard(limits, PERIOD_S)
    guard.reset(s0)
    target = s0 + np.array([0.02, -0.015, 0.01])
    zero = np.zeros(3)
    n = 2000
    p, v, a = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    states = []
    for k in range(n):
        states.append(guard.track(target, zero, zero))
        p[k], v[k], a[k] = guard.position_m, guard.velocity_m_s, guard.acceleration_m_s2
    assert states[0] is GuardState.LIMITED
    _assert_within(limits, p, v, a, s0, zero)
    # A jerk-limited approach: no step, smooth start, then exactly at the target and at rest.
    assert np.abs(p[0] - s0).max() < 1e-6
    assert np.abs(p[-1] - target).max() <= 1e-9
    assert guard.at_rest
    assert states[-1] is GuardState.PASSTHROUGH
    # Time-optimal per axis: a few times the velocity-limited time, not more.
    reached = int(np.argmax(np.all(np.abs(p - target) < 1e-9, axis=1)))
    v_max, _, _ = limits.as_arrays()
    assert reached * PERIOD_S < 3.0 * float(np.max(np.abs(target - s0) / v_max)) + 1.0


def test_a_target_beyond_the_velocity_limit_is_limited(rig: Rig, limits: StrokeLimits) -> None:
    s0 = actuation.joint_to_stroke(rig, Q0)
    guard = LimitGuard(limits, PERIOD_S)
    guard.reset(s0)
    v_max, _, _ = limits.as_arrays()
    fast = 3.0 * v_max * np.array([1.0, -1.0, 1.0])
    zero = np.zeros(3)
    n = 1500
    p, v, a = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    for k in range(n):
        guard.track(s0 + fast * (k + 1) * PERIOD_S, fast, zero)
        p[k], v[k], a[k] = guard.position_m, guard.velocity_m_s, guard.acceleration_m_s2
    assert guard.state is GuardState.LIMITED
    _assert_within(limits, p, v, a, s0, zero)
    # Time synchronisation keeps the direction: the slowest axis runs at its limit.
    assert (np.abs(v[-1]) / v_max).max() == pytest.approx(1.0, rel=1e-6)


def test_stop_from_full_speed_is_jerk_limited_and_ends_at_rest(
    rig: Rig, limits: StrokeLimits
) -> None:
    v_max, a_max, j_max = limits.as_arrays()
    s0 = actuation.joint_to_stroke(rig, Q0)
    guard = LimitGuard(limits, PERIOD_S)
    v0 = v_max * np.array([1.0, -1.0, 0.5])
    a0 = np.array([0.0, 0.5, -0.5]) * a_max
    guard.reset(s0, v0, a0)
    guard.stop()
    n = 3000
    p, v, a = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    states = []
    for k in range(n):
        states.append(guard.step_stop())
        p[k], v[k], a[k] = guard.position_m, guard.velocity_m_s, guard.acceleration_m_s2
    _assert_within(limits, p, v, a, s0, a0)
    assert states[0] is GuardState.STOPPING and states[-1] is GuardState.AT_REST
    assert guard.at_rest
    assert (v[-1] == 0.0).all() and (a[-1] == 0.0).all()
    stop_cycles = int(np.argmax(np.array(states) == GuardState.AT_REST))
    bound = float(np.max(np.abs(v0) / a_max + 2.0 * a_max / j_max)) + 0.1
    assert 0 < stop_cycles * PERIOD_S <= bound
    # Moving on: position keeps its last value; tracking in stop mode keeps stopping.
    assert guard.track(s0, np.zeros(3), np.zeros(3)) is GuardState.AT_REST
    assert np.array_equal(guard.position_m, p[-1])
    guard.reset(guard.position_m)
    assert not guard.stopping


def test_reset_rejects_bad_states(limits: StrokeLimits) -> None:
    guard = LimitGuard(limits, PERIOD_S)
    with pytest.raises(ConfigurationError, match="position_m"):
        guard.reset([0.1, np.nan, 0.1])
    with pytest.raises(ConfigurationError, match="velocity_m_s"):
        guard.reset([0.1, 0.1, 0.1], [0.0, 0.0])
