"""Teach and plan (Zhao et al., II-B and III): demonstrations to waypoints to a fast, smooth cycle.

Role: the pipeline of ``excavator-rt teach``. From validated demonstrations
(:mod:`rt_runtime.teach.demos`, joints swing first, rad):

0. **Rest trimmed** (:func:`trim_rest`): the idle machine before and after the cycle cut off.
1. **Swing unwrapped** (:func:`unwrap_swing`): each demonstration's swing made continuous, and
   every demonstration put on the 2 pi branch of the first one, so an average never mixes
   -179 deg with +179 deg.
2. **Time alignment** by dynamic time warping (:func:`dtw_path`, :func:`align`): every
   demonstration warped onto the timeline of a reference (the one of median duration). The
   warping path is computed on a lightly smoothed copy (noise makes DTW warp for nothing) and
   applied to the raw samples (the demonstration read at the reference-time map the match
   gives). Passes of DTW barycentre averaging (all aligned again to their average) are an
   option (``dba_passes``); they did not bring the mean path nearer the intended one (Z2).
3. **Centred moving average** (:func:`moving_average`) of each aligned demonstration: centred,
   because a causal filter lags and moves the waypoints along the path.
4. **Average** over demonstrations (:func:`average`).
5. **Forward kinematics** to pose space (Zhao eq 1: :func:`rt_runtime.kinematics.forward_3d`):
   tip ``x, y, z`` (m) and attitude (rad).
6. **Douglas-Peucker** in pose space (:func:`douglas_peucker`) with a scale per axis: metres
   stay metres, the attitude counts as the arc its change sweeps at the bucket's length
   (``attitude * a4``, m), so one tolerance ``epsilon`` (m) bounds both.
7. The waypoints back to **joint space** by the inverse kinematics
   (:func:`rt_runtime.kinematics.inverse_3d`), checked to land on the branch of the averaged
   joint path they came from (the swing on its unwrapped branch).
8. The **minimum time-jerk trajectory** through them (Zhao eq 3:
   :mod:`rt_runtime.trajectory.timejerk`), rest to rest, within the rig's velocity and
   acceleration limits and joint ranges.
9. The **trench** (:func:`plan_trench`): ``cycles`` copies of the taught cycle along the trench
   axis (the swing frame's horizontal heading at the dig's swing angle), each shifted by
   ``-k * step`` (towards the machine); the waypoints on the dig side (swing within 5 deg of the
   dig's) move with the cycle, those at the dump do not; every cycle ends where the next one
   starts (the last at its own last waypoint), each its own minimum time-jerk trajectory.

Units: SI inside (m, rad, s); every function is pure and runs outside the loop.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import uniform_filter1d
from scipy.spatial import cKDTree

from rt_runtime import kinematics
from rt_runtime.errors import ConfigurationError, KinematicsError, PlanningError
from rt_runtime.rig import Rig
from rt_runtime.teach.demos import MIN_SAMPLES, DemoRecord
from rt_runtime.trajectory.timejerk import TimeJerkProblem, TimeJerkTrajectory, interpolate, plan

__all__ = [
    "DIG_SIDE_RAD",
    "Taught",
    "TeachSettings",
    "Trench",
    "TrenchCycle",
    "align",
    "average",
    "douglas_peucker",
    "dtw_path",
    "frechet_distance",
    "mean_path",
    "moving_average",
    "plan_trench",
    "teach",
    "tip_path",
    "unwrap_swing",
    "waypoints_from_path",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Waypoints whose swing is this close to the dig's swing are on the dig side (they move
#: with the cycle along the trench).
DIG_SIDE_RAD = math.radians(5.0)
#: A joint (averaged over 0.25 s) that moves this far from where it rests is in motion (rad).
REST_THRESHOLD_RAD = math.radians(0.1)
#: A waypoint's inverse kinematics must reproduce the averaged joints to this (rad).
_BRANCH_TOL_RAD = 1e-6


@dataclass(frozen=True, slots=True)
class TeachSettings:
    """Settings of :func:`teach`.

    Attributes:
        epsilon_m: Douglas-Peucker tolerance in pose space, m (> 0).
        window_s: Width of the centred moving average, s (>= 0; 0: none).
        dtw_smooth_s: Width of the smoothing of the copies DTW aligns, s.
        dtw_rate_hz: Rate the demonstrations are resampled to for DTW, Hz (the alignment is
            applied at the recorded rate).
        dba_passes: Realignments to the average after the first alignment (>= 0).
        w_jerk: Weight of the jerk integral (Zhao eq 3), >= 0.
        w_time: Weight of the duration, > 0.
        cycles: Cycles of the trench, >= 1.
        step_m: Shift of each cycle along the trench axis, m (towards the machine).
        alignment: ``dtw`` (dynamic time warping) or ``linear`` (each demonstration's time
            scaled uniformly onto the reference's: the phase alignment DTW is checked against).
        refine: Most waypoints added where the planned tip strays from the mean path by more
            than ``epsilon_m`` (>= 0; 0: Douglas-Peucker's waypoints only).
        limit_fraction: Share of the joints' velocity and acceleration limits the cycles are
            planned to, in (0, 1]: the rest is headroom for the drives' tracking (a hydraulic
            axis planned onto its limit runs a few percent over it, and a valve that closes on
            a fault jolts its neighbours further).
    """

    epsilon_m: float = 0.05
    window_s: float = 0.15
    dtw_smooth_s: float = 0.1
    dtw_rate_hz: float = 20.0
    dba_passes: int = 0
    w_jerk: float = 0.0
    w_time: float = 1.0
    cycles: int = 7
    step_m: float = 0.15
    refine: int = 12
    alignment: str = "dtw"
    limit_fraction: float = 0.9

    def __post_init__(self) -> None:
        checks = (
            ("epsilon_m", self.epsilon_m > 0.0, "> 0"),
            ("window_s", self.window_s >= 0.0, ">= 0"),
            ("dtw_smooth_s", self.dtw_smooth_s >= 0.0, ">= 0"),
            ("dtw_rate_hz", 1.0 <= self.dtw_rate_hz <= 10_000.0, "1..10000 Hz"),
            ("w_jerk", self.w_jerk >= 0.0, ">= 0"),
            ("w_time", self.w_time > 0.0, "> 0"),
            ("step_m", abs(self.step_m) <= 5.0, "within +-5 m"),
            ("limit_fraction", 0.0 < self.limit_fraction <= 1.0, "in (0, 1]"),
        )
        for name, ok, allowed in checks:
            value = float(getattr(self, name))
            if not (math.isfinite(value) and ok):
                raise ConfigurationError(f"teach setting {name} = {value!r}: allowed {allowed}")
        if not (isinstance(self.cycles, int) and 1 <= self.cycles <= 1000):
            raise ConfigurationError(f"teach setting cycles = {self.cycles!r}: allowed 1..1000")
        if self.alignment not in ("dtw", "linear"):
            raise ConfigurationError(
                f"teach setting alignment = {self.alignment!r}: allowed 'dtw' or 'linear'"
            )
        if not (isinstance(self.refine, int) and 0 <= self.refine <= 100):
            raise ConfigurationError(f"teach setting refine = {self.refine!r}: allowed 0..100")
        if not (isinstance(self.dba_passes, int) and 0 <= self.dba_passes <= 10):
            raise ConfigurationError(
                f"teach setting dba_passes = {self.dba_passes!r}: allowed 0..10"
            )


def trim_rest(
    record: DemoRecord, threshold_rad: float = REST_THRESHOLD_RAD, window_s: float = 0.25
) -> DemoRecord:
    """The demonstration without the idle machine before the operator starts and after he
    stops: from the last sample before any joint, averaged over ``window_s`` (centred), has
    moved ``threshold_rad`` from where it rested at the start (the mean of the first window),
    to the first sample after which none moves that far from where it rests at the end. A
    recording of a manual run keeps the machine idle around the cycle; the cycle (and the
    operator's cycle time) is the motion.
    0.1 deg: ten times the noise of the rigs' angle sensors (0.05 deg) left after the average
    over 25 samples; the tip of the field excavator moves < 1 cm for it."""
    q = record.q_rad
    rate = (q.shape[0] - 1) / max(record.duration_s, 1e-9)
    w = max(1, round(window_s * rate))
    smooth = moving_average(q, w)
    # Where it rests: the mean of the first and of the last window (a smoothed end sample
    # leans on the end sample itself).
    start, end = q[:w].mean(axis=0), q[-w:].mean(axis=0)
    moved = np.flatnonzero(np.any(np.abs(smooth - start) > threshold_rad, axis=1))
    still = np.flatnonzero(np.any(np.abs(smooth - end) > threshold_rad, axis=1))
    if moved.size == 0 or still.size == 0:
        return record
    a = max(int(moved[0]) - 1, 0)
    b = min(int(still[-1]) + 1, q.shape[0] - 1)
    if b - a + 1 < MIN_SAMPLES:
        return record
    return DemoRecord(record.path, record.t_s[a : b + 1], q[a : b + 1], record.rows[a : b + 1])


def cycle_times_s(records: Sequence[DemoRecord]) -> FloatArray:
    """The operator's cycle time of each demonstration: its motion (:func:`trim_rest`), s."""
    return np.array([trim_rest(r).duration_s for r in records])


def unwrap_swing(rig: Rig, demos: Sequence[FloatArray]) -> list[FloatArray]:
    """Each ``(N, J)`` demonstration with its swing (column 0 on a rig with swing) unwrapped
    in time and shifted by a multiple of 2 pi to start nearest the first one's start."""
    if rig.swing is None:
        return [np.asarray(q, dtype=np.float64) for q in demos]
    out = []
    ref = None
    for q in demos:
        a = np.array(q, dtype=np.float64)
        a[:, 0] = np.unwrap(a[:, 0])
        if ref is None:
            ref = float(a[0, 0])
        a[:, 0] -= 2.0 * math.pi * round((a[0, 0] - ref) / (2.0 * math.pi))
        out.append(a)
    return out


def moving_average(q: ArrayLike, window: int) -> FloatArray:
    """Centred moving average over ``window`` samples (odd; an even one is made odd) along
    axis 0; the ends repeat the first and last sample (no lag, no shrink). ``window <= 1``
    returns a copy."""
    a = np.asarray(q, dtype=np.float64)
    if window <= 1:
        return a.copy()
    w = window | 1
    return np.asarray(uniform_filter1d(a, size=w, axis=0, mode="nearest"), dtype=np.float64)


def dtw_path(a: ArrayLike, b: ArrayLike) -> tuple[IntArray, IntArray]:
    """Dynamic time warping of ``a (N, d)`` against ``b (M, d)``: the warping path.

    Cost: squared Euclidean distance; steps (1, 0), (0, 1), (1, 1); the path runs from
    ``(0, 0)`` to ``(N - 1, M - 1)``. The accumulated cost is filled a row at a time: within
    a row ``D[j] = c[j] + min(D[j - 1], m[j])`` with ``m[j] = min(D'[j - 1], D'[j])`` of the
    row before, which with ``E = D - cumsum(c)`` is ``E[j] = min(E[j - 1], m[j] - S[j - 1])``:
    one running minimum (``np.minimum.accumulate``) per row, O(N M) work in N numpy calls.

    Returns:
        ``(ia, ib)``: matched index pairs, both non-decreasing, each step advancing one or both.
    """
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    n, m = x.shape[0], y.shape[0]
    cost = (
        np.sum(x * x, axis=1)[:, None] + np.sum(y * y, axis=1)[None, :] - 2.0 * (x @ y.T)
    )
    np.maximum(cost, 0.0, out=cost)
    csum = np.cumsum(cost, axis=1)
    acc = np.empty((n, m))
    acc[0] = csum[0]
    shifted = np.empty(m)
    for i in range(1, n):
        prev = acc[i - 1]
        shifted[0] = prev[0]
        np.minimum(prev[1:], prev[:-1], out=shifted[1:])
        shifted[1:] -= csum[i, :-1]
        np.minimum.accumulate(shifted, out=acc[i])
        acc[i] += csum[i]
    # Backtrack from the end (ties prefer the diagonal), on Python floats: the path is
    # N + M steps of three comparisons, which numpy's per-call overhead would dominate.
    rows = acc.tolist()
    ia = [n - 1]
    ib = [m - 1]
    i, j = n - 1, m - 1
    while i > 0 or j > 0:
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        else:
            up = rows[i - 1]
            d, u, left = up[j - 1], up[j], rows[i][j - 1]
            if d <= u and d <= left:
                i -= 1
                j -= 1
            elif u <= left:
                i -= 1
            else:
                j -= 1
        ia.append(i)
        ib.append(j)
    return np.asarray(ia[::-1], dtype=np.int64), np.asarray(ib[::-1], dtype=np.int64)


def _resample(t: FloatArray, q: FloatArray, rate_hz: float) -> tuple[FloatArray, FloatArray]:
    n = max(2, round((t[-1] - t[0]) * rate_hz) + 1)
    tt = np.linspace(t[0], t[-1], n)
    return tt, np.stack([np.interp(tt, t, q[:, j]) for j in range(q.shape[1])], axis=1)


def align(
    ref_t_s: ArrayLike,
    ref_q: ArrayLike,
    t_s: ArrayLike,
    q: ArrayLike,
    *,
    smooth_s: float = 0.1,
    rate_hz: float = 20.0,
) -> FloatArray:
    """``q`` warped onto the timeline of ``ref``: ``(len(ref_t_s), J)``.

    DTW (:func:`dtw_path`) matches the two at ``rate_hz`` on copies smoothed over
    ``smooth_s``; the match, as a monotone map from the reference's time to the
    demonstration's, is interpolated to the reference's samples and the raw ``q`` read there
    (linear interpolation in time). A demonstration that is the reference with its time warped
    comes back as the reference.
    """
    rt = np.asarray(ref_t_s, dtype=np.float64)
    rq = np.asarray(ref_q, dtype=np.float64)
    dt_ = np.asarray(t_s, dtype=np.float64)
    dq = np.asarray(q, dtype=np.float64)
    rs_t, rs_q = _resample(rt, rq, rate_hz)
    ds_t, ds_q = _resample(dt_, dq, rate_hz)
    w = round(smooth_s * rate_hz)
    ia, ib = dtw_path(moving_average(rs_q, w), moving_average(ds_q, w))
    # Many-to-one matches: the reference sample takes the mean demonstration time matched.
    counts = np.bincount(ia, minlength=rs_t.shape[0])
    mapped = np.bincount(ia, weights=ds_t[ib], minlength=rs_t.shape[0]) / counts
    mapped = np.maximum.accumulate(mapped)
    t_map = np.interp(rt, rs_t, mapped)
    return np.stack([np.interp(t_map, dt_, dq[:, j]) for j in range(dq.shape[1])], axis=1)


def average(aligned: Sequence[FloatArray]) -> FloatArray:
    """The mean over demonstrations of aligned ``(N, J)`` series."""
    return np.asarray(np.mean(np.stack(aligned), axis=0), dtype=np.float64)


def mean_path(
    rig: Rig, records: Sequence[DemoRecord], settings: TeachSettings
) -> tuple[FloatArray, FloatArray]:
    """Steps 0-4: the operator's mean joint path ``(t_s (N,), q_rad (N, J))`` on the timeline of
    the demonstration of median duration (starting at 0).

    Raises:
        ConfigurationError: No demonstration.
    """
    if not records:
        raise ConfigurationError("teach needs at least one demonstration")
    records = [trim_rest(r) for r in records]
    qs = unwrap_swing(rig, [r.q_rad for r in records])
    ts = [r.t_s - r.t_s[0] for r in records]
    order = np.argsort([t[-1] for t in ts])
    k = int(order[len(order) // 2])
    ref_t, ref_q = ts[k], qs[k]
    rate = 1.0 / float(np.median(np.diff(ref_t)))
    window = round(settings.window_s * rate)
    if settings.alignment == "linear":
        aligned = [
            np.stack(
                [np.interp(ref_t * (t[-1] / ref_t[-1]), t, q[:, j]) for j in range(q.shape[1])],
                axis=1,
            )
            for t, q in zip(ts, qs, strict=True)
        ]
        return ref_t, average([moving_average(a, window) for a in aligned])
    mean = ref_q
    for _ in range(1 + settings.dba_passes):
        aligned = [
            align(ref_t, mean, t, q, smooth_s=settings.dtw_smooth_s,
                  rate_hz=settings.dtw_rate_hz)
            for t, q in zip(ts, qs, strict=True)
        ]
        mean = average([moving_average(a, window) for a in aligned])
    return ref_t, mean


def _scaled(rig: Rig, pose: FloatArray) -> FloatArray:
    """Pose ``(..., 4)`` (x, y, z m, attitude rad) in metres: the attitude times a4."""
    out = np.array(pose, dtype=np.float64)
    out[..., 3] *= float(rig.lengths_m[2])
    return out


def douglas_peucker(points: ArrayLike, epsilon: float) -> IntArray:
    """Indices of the points Douglas-Peucker keeps (Douglas and Peucker 1973, Zhao ref [15]).

    Any dimension. A section keeps its farthest point (distance to the segment between its
    ends; the first of equals) when that distance exceeds ``epsilon``, and is then split there;
    otherwise only its ends stay. The rule and the tie-break are those of GEOS, so on 2-D points
    this keeps exactly what ``shapely.simplify(..., preserve_topology=False)`` keeps.

    Args:
        points: ``(N, d)``, N >= 2.
        epsilon: Tolerance, in the points' unit, >= 0.

    Returns:
        Sorted indices, first and last included.
    """
    p = np.asarray(points, dtype=np.float64)
    n = p.shape[0]
    if n < 2:
        raise ConfigurationError(f"Douglas-Peucker needs at least 2 points; got {n}")
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = p[i], p[j]
        seg = b - a
        pts = p[i + 1 : j]
        rel = pts - a
        den = float(seg @ seg)
        if den > 0.0:
            t = np.clip(rel @ seg / den, 0.0, 1.0)
            d = np.linalg.norm(rel - t[:, None] * seg, axis=1)
        else:
            d = np.linalg.norm(rel, axis=1)
        k = int(np.argmax(d))
        if d[k] > epsilon:
            mid = i + 1 + k
            keep[mid] = True
            stack.append((mid, j))
            stack.append((i, mid))
    return np.flatnonzero(keep).astype(np.int64)


def tip_path(rig: Rig, q_rad: ArrayLike) -> FloatArray:
    """Tip positions ``(N, 3)`` (x, y, z in the swing frame, m) of joint angles ``(N, 4)``."""
    return np.asarray(kinematics.forward_3d(rig, q_rad)[..., :3], dtype=np.float64)


def waypoints_from_path(
    rig: Rig, q_rad: ArrayLike, epsilon_m: float
) -> tuple[IntArray, FloatArray]:
    """Steps 5-7: Douglas-Peucker in scaled pose space, then back to joints by the IK.

    Returns:
        ``(indices, waypoints_rad (n, J))``: the kept samples and their joint angles from the
        inverse kinematics (the swing on the path's unwrapped branch).

    Raises:
        PlanningError: A waypoint's IK fails or lands on another branch than the path's.
    """
    q = np.asarray(q_rad, dtype=np.float64)
    pose = kinematics.forward_3d(rig, q)
    idx = douglas_peucker(_scaled(rig, pose), epsilon_m)
    return idx, _ik_on_branch(rig, pose[idx], q[idx])


def _ik_on_branch(rig: Rig, pose: FloatArray, q_path: FloatArray) -> FloatArray:
    try:
        q = kinematics.inverse_3d(rig, pose[:, 0], pose[:, 1], pose[:, 2], pose[:, 3])
    except KinematicsError as e:
        raise PlanningError(f"a waypoint has no inverse kinematics on {rig.name}: {e}") from None
    q[:, 0] += 2.0 * math.pi * np.round((q_path[:, 0] - q[:, 0]) / (2.0 * math.pi))
    off = np.abs(q - q_path)
    if np.any(off > _BRANCH_TOL_RAD):
        i, j = (int(v) for v in np.argwhere(off > _BRANCH_TOL_RAD)[0])
        raise PlanningError(
            f"waypoint {i + 1}: the inverse kinematics gives {rig.joint_names[j]} "
            f"{math.degrees(q[i, j]):.4f} deg where the taught path has "
            f"{math.degrees(q_path[i, j]):.4f} deg: another branch; the operator's path is "
            "not on the excavator branch there"
        )
    return q


@dataclass(frozen=True, slots=True, eq=False)
class TrenchCycle:
    """One cycle of the trench.

    Attributes:
        index: 0-based.
        offset_m: Shift along the trench axis, m.
        waypoints_rad: ``(n, J)`` its waypoints.
        trajectory: Its minimum time-jerk trajectory.
    """

    index: int
    offset_m: float
    waypoints_rad: FloatArray
    trajectory: TimeJerkTrajectory


@dataclass(frozen=True, slots=True, eq=False)
class Trench:
    """The taught trench: its cycles in order, each starting where the one before ended."""

    cycles: tuple[TrenchCycle, ...]

    @property
    def total_s(self) -> float:
        """Sum of the cycles' durations, s."""
        return float(sum(c.trajectory.duration_s for c in self.cycles))


def _shift(rig: Rig, waypoints: FloatArray, shift_m: FloatArray, axis: FloatArray) -> FloatArray:
    """The waypoints with their tip poses moved by ``shift_m (n,)`` along ``axis``, back
    through the IK on the same branch (the swing on the waypoints' unwrapped branch)."""
    if not np.any(shift_m):
        return waypoints.copy()
    moved = kinematics.forward_3d(rig, waypoints)
    moved[:, :3] += shift_m[:, None] * axis[None, :]
    try:
        q = kinematics.inverse_3d(rig, moved[:, 0], moved[:, 1], moved[:, 2], moved[:, 3])
    except KinematicsError as e:
        raise PlanningError(
            f"a trench cycle shifted by up to {float(np.min(shift_m)):+.3f} m along the trench "
            f"axis leaves the arm's reach or range: {e} (fewer --cycles or a smaller step)"
        ) from None
    q[:, 0] += 2.0 * math.pi * np.round((waypoints[:, 0] - q[:, 0]) / (2.0 * math.pi))
    return q


def _scaled_from(problem: TimeJerkProblem, base: TimeJerkTrajectory) -> TimeJerkTrajectory | None:
    """The spline of ``problem`` on ``base``'s piece durations, stretched uniformly in time
    until within the velocity and acceleration limits (rest-to-rest: velocity falls with the
    stretch, acceleration with its square); None where the path leaves a joint's range (no
    stretch changes the path)."""
    if problem.n_pieces != base.n_pieces:
        return None
    traj = interpolate(problem, base.piece_durations_s)
    chk = traj.limit_check()
    r = max(float(np.max(chk.velocity_ratio)), math.sqrt(float(np.max(chk.acceleration_ratio))))
    traj = interpolate(problem, base.piece_durations_s * r * (1.0 + 1e-9))
    return traj if traj.limit_check().within_limits else None


def peak_ratios(trench: Trench, settings: TeachSettings) -> tuple[FloatArray, FloatArray, bool]:
    """Each joint's peak velocity and acceleration over a planned trench as fractions of the
    rig's limits (exact, per cubic piece), and whether every cycle is within its planned
    limits. The cycles are planned to ``settings.limit_fraction`` of the rig's limits, which
    is what their own checks compare with."""
    share = settings.limit_fraction
    checks = [c.trajectory.limit_check() for c in trench.cycles]
    v = share * np.max([c.velocity_ratio for c in checks], axis=0)
    a = share * np.max([c.acceleration_ratio for c in checks], axis=0)
    return v, a, all(c.within_limits for c in checks)


def plan_trench(
    rig: Rig,
    waypoints_rad: ArrayLike,
    settings: TeachSettings,
    taught: TimeJerkTrajectory | None = None,
) -> Trench:
    """Step 9: the trench of ``settings.cycles`` cycles (module docstring).

    Each cycle is its own minimum time-jerk search. Where that search does not converge
    (SLSQP on a few dozen waypoints now and then stops on an incompatible linearisation), the
    cycle takes the taught cycle's piece durations (``taught``), stretched to the limits: its
    waypoints are the taught ones moved a little, so that is close to its optimum.

    Raises:
        PlanningError: A shifted cycle is out of reach, or a cycle has no trajectory within the
            limits.
    """
    w = np.asarray(waypoints_rad, dtype=np.float64)
    heading = float(w[0, 0])
    axis = np.array([math.cos(heading), 0.0, -math.sin(heading)])
    dig = np.abs(w[:, 0] - heading) <= DIG_SIDE_RAD
    cycles = []
    n = settings.cycles
    for k in range(n):
        off = -k * settings.step_m
        # Every cycle ends where the next one starts (its first waypoint, shifted by the next
        # offset); the last ends at its own last waypoint.
        wk = w.copy()
        if k + 1 < n:
            wk[-1] = w[0]
        shift = np.where(dig, off, 0.0)
        shift[-1] = -(k + 1) * settings.step_m if k + 1 < n else (off if dig[-1] else 0.0)
        if k + 1 < n and not dig[0]:
            shift[-1] = 0.0
        wk = _shift(rig, wk, shift, axis)
        problem = TimeJerkProblem.for_rig(
            rig, wk, w_jerk=settings.w_jerk, w_time=settings.w_time,
            limit_fraction=settings.limit_fraction,
        )
        try:
            traj = plan_cycle(rig, wk, settings)
        except PlanningError as e:
            fallback = None if taught is None else _scaled_from(problem, taught)
            if fallback is None:
                raise PlanningError(f"trench cycle {k + 1} of {n}: {e}") from None
            traj = fallback
        cycles.append(TrenchCycle(k, off, wk, traj))
    return Trench(tuple(cycles))


def frechet_distance(a: ArrayLike, b: ArrayLike) -> float:
    """Discrete Frechet distance between polylines ``a (N, d)`` and ``b (M, d)`` (Eiter and
    Mannila 1994), filled by anti-diagonals (each one numpy step)."""
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    n, m = x.shape[0], y.shape[0]
    d = np.sqrt(
        np.maximum(
            np.sum(x * x, 1)[:, None] + np.sum(y * y, 1)[None, :] - 2.0 * (x @ y.T), 0.0
        )
    )
    f = np.full((n, m), np.inf)
    f[0, 0] = d[0, 0]
    f[0, :] = np.maximum.accumulate(d[0, :])
    f[:, 0] = np.maximum.accumulate(d[:, 0])
    for s in range(2, n + m - 1):
        i = np.arange(max(1, s - m + 1), min(n - 1, s - 1) + 1)
        if i.size == 0:
            continue
        j = s - i
        best = np.minimum(np.minimum(f[i - 1, j - 1], f[i - 1, j]), f[i, j - 1])
        f[i, j] = np.maximum(d[i, j], best)
    return float(f[-1, -1])


def resample_by_length(points: ArrayLike, spacing_m: float) -> FloatArray:
    """A polyline ``(N, d)`` resampled at equal arc-length steps of at most ``spacing_m``."""
    p = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate(([0.0], np.cumsum(seg)))
    n = max(2, math.ceil(s[-1] / spacing_m) + 1)
    ss = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(ss, s, p[:, j]) for j in range(p.shape[1])], axis=1)


@dataclass(frozen=True, slots=True, eq=False)
class Taught:
    """Everything :func:`teach` found.

    Attributes:
        mean_t_s: ``(N,)`` the mean path's timeline, s.
        mean_q_rad: ``(N, J)`` the operator's mean joint path.
        waypoint_indices: ``(n,)`` samples of the mean path Douglas-Peucker kept.
        waypoints_rad: ``(n, J)`` the waypoints in joint space.
        cycle: The taught cycle (at offset 0, from the mean path's first sample to its last).
        trench: The trench.
        operator_cycle_s: ``(D,)`` each demonstration's cycle time (its motion), s.
        settings: The settings used.
    """

    mean_t_s: FloatArray
    mean_q_rad: FloatArray
    waypoint_indices: IntArray
    waypoints_rad: FloatArray
    cycle: TimeJerkTrajectory
    trench: Trench
    operator_cycle_s: FloatArray
    settings: TeachSettings

    @property
    def operator_mean_cycle_s(self) -> float:
        """Mean duration of the demonstrations, s."""
        return float(np.mean(self.operator_cycle_s))


def learn_waypoints(
    rig: Rig, records: Sequence[DemoRecord], settings: TeachSettings
) -> tuple[FloatArray, FloatArray, IntArray, FloatArray]:
    """Steps 1-7 (demonstrations to waypoints): ``(mean_t_s, mean_q_rad, indices, waypoints)``.

    Raises:
        ConfigurationError: No demonstration, or a rig without swing.
        PlanningError: A waypoint off the excavator branch.
    """
    if rig.swing is None:
        raise ConfigurationError(
            f"teach plans a trenching cycle with swing (Zhao eq 1); rig {rig.name!r} has no "
            "swing joint (use field_excavator)"
        )
    t, q = mean_path(rig, records, settings)
    idx, wps = waypoints_from_path(rig, q, settings.epsilon_m)
    return t, q, idx, wps


#: Jerk weights (s^6/rad^2) tried, in order, where the search with ``w_jerk = 0`` does not
#: converge: pure minimum time drives the two end pieces to 1 ms, and SLSQP on a few dozen
#: waypoints then now and then stops on a positive directional derivative; a weight of 1e-8
#: gives the end pieces a finite jerk: where both converge, T differs by < 0.01 % (design
#: note Z3).
JERK_REGULARISATION = (1e-8, 1e-6)


def plan_cycle(rig: Rig, waypoints: FloatArray, s: TeachSettings) -> TimeJerkTrajectory:
    """The minimum time-jerk trajectory through ``waypoints`` (rest to rest, within the rig's
    velocity and acceleration limits and ranges). With ``w_jerk = 0`` and no convergence, the
    search is repeated with the weights of :data:`JERK_REGULARISATION`; the trajectory's
    ``problem.w_jerk`` says which weight it solved.

    Raises:
        PlanningError: No weight gives a trajectory within the limits.
    """
    try:
        return plan(TimeJerkProblem.for_rig(
            rig, waypoints, w_jerk=s.w_jerk, w_time=s.w_time, limit_fraction=s.limit_fraction
        ))
    except PlanningError as first:
        if s.w_jerk != 0.0:
            raise
        for w in JERK_REGULARISATION:
            try:
                return plan(TimeJerkProblem.for_rig(
                    rig, waypoints, w_jerk=w, w_time=s.w_time, limit_fraction=s.limit_fraction
                ))
            except PlanningError:
                continue
        raise first from None


def deviation_m(rig: Rig, traj: TimeJerkTrajectory, path_tree: cKDTree,
                rate_hz: float = 200.0) -> tuple[float, float, FloatArray]:
    """Largest distance of the planned tip from a path (a KD-tree of its points, m), the time
    it happens (s) and the tip there ``(3,)``."""
    t = np.linspace(0.0, traj.duration_s, max(2, math.ceil(traj.duration_s * rate_hz) + 1))
    tip = tip_path(rig, traj.sample(t))
    dist, _ = path_tree.query(tip)
    k = int(np.argmax(dist))
    return float(dist[k]), float(t[k]), tip[k]


def refine_cycle(
    rig: Rig, mean_q: FloatArray, indices: IntArray, s: TeachSettings
) -> tuple[IntArray, FloatArray, TimeJerkTrajectory]:
    """Plan the cycle through the waypoints at ``indices`` of the mean path; while the planned
    tip strays from the mean path by more than ``epsilon_m`` (a time-optimal spline overshoots
    where a joint stops or turns), add the mean path's sample nearest to the worst planned
    point, inside the waypoint interval it falls in, and plan again (at most ``s.refine``
    times). Every waypoint stays a sample of the mean path.

    Returns:
        ``(indices, waypoints_rad, trajectory)``.
    """
    tip = tip_path(rig, mean_q)
    tree = cKDTree(resample_by_length(tip, 0.005))
    pose = kinematics.forward_3d(rig, mean_q)
    idx = np.asarray(indices, dtype=np.int64)
    wps = _ik_on_branch(rig, pose[idx], mean_q[idx])
    traj = plan_cycle(rig, wps, s)
    inserted = 0
    for attempt in range(s.refine + 1):
        if attempt:
            more = _ik_on_branch(rig, pose[idx], mean_q[idx])
            try:
                traj_more = plan_cycle(rig, more, s)
            except PlanningError:
                # SLSQP may fail on the larger problem: keep the plan before the insertion.
                idx = np.delete(idx, inserted)
                break
            wps, traj = more, traj_more
        dev, t_worst, p_worst = deviation_m(rig, traj, tree)
        if dev <= s.epsilon_m or attempt == s.refine:
            break
        k = int(np.clip(np.searchsorted(traj.waypoint_times_s, t_worst) - 1, 0, idx.size - 2))
        a, b = int(idx[k]), int(idx[k + 1])
        if b - a < 2:
            break
        j = a + 1 + int(np.argmin(np.linalg.norm(tip[a + 1 : b] - p_worst, axis=1)))
        inserted = k + 1
        idx = np.insert(idx, inserted, j)
    return idx, wps, traj


def teach(rig: Rig, records: Sequence[DemoRecord], settings: TeachSettings | None = None) -> Taught:
    """The whole pipeline (module docstring) on validated demonstrations.

    Raises:
        ConfigurationError: No demonstration, a rig without swing, bad settings.
        PlanningError: A waypoint off the branch, a trench cycle out of reach, or no
            trajectory within the limits.
    """
    s = settings or TeachSettings()
    t, q, idx, _ = learn_waypoints(rig, records, s)
    idx, wps, cycle = refine_cycle(rig, q, idx, s)
    trench = plan_trench(rig, wps, s, cycle)
    return Taught(
        mean_t_s=t,
        mean_q_rad=q,
        waypoint_indices=idx,
        waypoints_rad=wps,
        cycle=cycle,
        trench=trench,
        operator_cycle_s=cycle_times_s(records),
        settings=s,
    )
