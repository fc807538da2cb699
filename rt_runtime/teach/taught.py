"""The taught job: the file ``excavator-rt teach --out DIR`` writes and the executor loads.

Role: the one format between teach-and-plan (Zhao et al.) and whatever runs the taught trench
(the HIL's ``hil --teach DIR``, the daemon's ``job submit --teach DIR``). ``DIR/taught.json``
is the ``teach --json`` report; the executor needs of it:

* ``rig`` (profile name) and ``joints`` (``["swing", "boom", "stick", "bucket"]``, swing first);
* ``trench``: ``cycles``, a list of the trench's cycles in order, each with ``index``,
  ``offset_m`` (its shift along the trench axis), ``start_s`` (its start on the job's clock),
  ``T_s`` and ``segments``; a segment is ``{"duration_s": h, "coefficients": [[c3, c2, c1, c0]
  per joint]}``: joint ``j`` on the segment is ``c3 tau^3 + c2 tau^2 + c1 tau + c0`` in rad,
  ``tau`` the time in s from the segment's start (the ``timejerk --json`` format);
* ``cycle``: the taught cycle alone in the same format (``T_s``, ``segments``).

:func:`load_taught` reads it into a :class:`TaughtJob`, a piecewise-cubic joint trajectory over
the whole trench that the executor samples (:meth:`TaughtJob.sample`), and verifies it before
anything moves: shapes and numbers, every segment at least 1 ms, position, velocity and
acceleration continuous across segments and cycles (1e-6 relative), rest at the start and at
the end, and the exact limit check against the rig (:meth:`TaughtJob.limit_check`: velocity
and acceleration, and the joint ranges). A file that fails any of it raises and gives no job.

Units: rad, rad/s, rad/s^2, s inside; joints swing first. Loading is outside the loop;
:meth:`TaughtJob.sample` is vectorised and cheap at batch size 1.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.rig import Rig, load_rig

__all__ = [
    "TAUGHT_FILE",
    "TaughtJob",
    "TaughtLimitCheck",
    "load_taught",
    "segments_json",
    "taught_from_json",
]

FloatArray = NDArray[np.float64]

#: The taught job's file name inside the directory of ``teach --out``.
TAUGHT_FILE = "taught.json"
#: Shortest segment (s), as the time-jerk generator's shortest piece.
MIN_SEGMENT_S = 1e-3
#: Relative tolerance of the continuity and limit checks.
TOLERANCE = 1e-6


def segments_json(durations_s: ArrayLike, coefficients: ArrayLike) -> list[dict[str, Any]]:
    """Segments in the file's format: ``[{"duration_s", "coefficients"}]`` from durations
    ``(m,)`` and coefficients ``(m, J, 4)`` (highest power first, rad, local time s)."""
    h = np.asarray(durations_s, dtype=np.float64)
    c = np.asarray(coefficients, dtype=np.float64)
    return [
        {"duration_s": float(h[i]), "coefficients": c[i].tolist()} for i in range(h.shape[0])
    ]


@dataclass(frozen=True, slots=True, eq=False)
class TaughtLimitCheck:
    """Exact peaks of a taught job against the rig's limits (per joint, swing first).

    Attributes:
        velocity_ratio: ``(J,)`` peak |velocity| over the limit.
        acceleration_ratio: ``(J,)`` peak |acceleration| over the limit.
        position_low_rad, position_high_rad: ``(J,)`` lowest and highest angle reached.
        within_limits: Every ratio ``<= 1 + 1e-6`` and every angle within the ranges.
    """

    velocity_ratio: FloatArray
    acceleration_ratio: FloatArray
    position_low_rad: FloatArray
    position_high_rad: FloatArray
    within_limits: bool


@dataclass(frozen=True, slots=True, eq=False)
class TaughtJob:
    """A taught trench as one piecewise-cubic joint trajectory (swing first).

    Attributes:
        rig_name: Profile the job was taught on.
        joint_names: ``(J,)`` joint names, swing first.
        knots_s: ``(m + 1,)`` segment boundaries from 0, s.
        coefficients: ``(m, J, 4)`` per segment and joint, highest power first, rad, local s.
        cycle_starts_s: ``(n_cycles,)`` start of every cycle, s.
        offsets_m: ``(n_cycles,)`` every cycle's shift along the trench axis, m.
        waypoints_rad: ``(n_waypoints, J)`` the taught cycle's waypoints.
    """

    rig_name: str
    joint_names: tuple[str, ...]
    knots_s: FloatArray
    coefficients: FloatArray
    cycle_starts_s: FloatArray
    offsets_m: FloatArray
    waypoints_rad: FloatArray

    @property
    def duration_s(self) -> float:
        """Whole trench, s."""
        return float(self.knots_s[-1])

    @property
    def n_cycles(self) -> int:
        """Number of cycles."""
        return int(self.cycle_starts_s.shape[0])

    @property
    def q0_rad(self) -> FloatArray:
        """``(J,)`` the pose the job starts from."""
        return np.asarray(self.coefficients[0, :, 3], dtype=np.float64)

    def sample(self, t_s: ArrayLike, derivative: int = 0) -> FloatArray:
        """Position (0), velocity (1), acceleration (2) or jerk (3) at ``t_s``.

        Args:
            t_s: Times, any shape, s; outside ``[0, duration_s]`` the nearer end's state.
            derivative: 0..3.

        Returns:
            ``(*t_s.shape, J)`` in rad/s**derivative.

        Raises:
            ValueError: ``derivative`` not in 0..3 or a non-finite time.
        """
        if derivative not in (0, 1, 2, 3):
            raise ValueError(f"derivative must be 0, 1, 2 or 3; got {derivative!r}")
        t = np.asarray(t_s, dtype=np.float64)
        if not np.all(np.isfinite(t)):
            raise ValueError("t_s must be finite")
        knots = self.knots_s
        m = self.coefficients.shape[0]
        seg = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, m - 1)
        tau = (np.clip(t, 0.0, knots[-1]) - knots[seg])[..., None]
        c = self.coefficients[seg]
        if derivative == 0:
            out = ((c[..., 0] * tau + c[..., 1]) * tau + c[..., 2]) * tau + c[..., 3]
        elif derivative == 1:
            out = (3.0 * c[..., 0] * tau + 2.0 * c[..., 1]) * tau + c[..., 2]
        elif derivative == 2:
            out = 6.0 * c[..., 0] * tau + 2.0 * c[..., 1]
        else:
            out = 6.0 * c[..., 0] + 0.0 * tau
        return np.asarray(out, dtype=np.float64)

    def limit_check(self, rig: Rig) -> TaughtLimitCheck:
        """Exact peaks: acceleration is linear on a segment (its extremes at the ends),
        velocity quadratic (ends and the acceleration's root), position cubic (ends and the
        velocity's roots).

        Raises:
            ConfigurationError: The rig's joints are not the job's.
        """
        if tuple(rig.joint_names) != self.joint_names:
            raise ConfigurationError(
                f"taught job has joints {list(self.joint_names)}; rig {rig.name} has "
                f"{list(rig.joint_names)}"
            )
        joints = ((rig.swing.joint,) if rig.swing is not None else ()) + rig.joints
        v_max = np.array([j.velocity_max_rad_s for j in joints])
        a_max = np.array([j.acceleration_max_rad_s2 for j in joints])
        lo = np.array([j.min_rad for j in joints])
        hi = np.array([j.max_rad for j in joints])
        return _check(self.knots_s, self.coefficients, v_max, a_max, lo, hi)


def _check(
    knots: FloatArray,
    c: FloatArray,
    v_max: FloatArray,
    a_max: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
) -> TaughtLimitCheck:
    h = np.diff(knots)[:, None]
    c3, c2, c1, c0 = c[..., 0], c[..., 1], c[..., 2], c[..., 3]
    acc = np.abs(np.concatenate([2.0 * c2, 6.0 * c3 * h + 2.0 * c2]))
    vel_end = np.abs(np.concatenate([c1, (3.0 * c3 * h + 2.0 * c2) * h + c1]))
    with np.errstate(divide="ignore", invalid="ignore"):
        tv = np.where(c3 != 0.0, -c2 / (3.0 * c3), -1.0)
    inside = (tv > 0.0) & (tv < h)
    tv = np.where(inside, tv, 0.0)
    vel_in = np.where(inside, np.abs((3.0 * c3 * tv + 2.0 * c2) * tv + c1), 0.0)
    pos_end = np.concatenate([c0, ((c3 * h + c2) * h + c1) * h + c0])
    # Position extremes inside a segment: roots of 3 c3 t^2 + 2 c2 t + c1.
    qa, qb, qc = 3.0 * c3, 2.0 * c2, c1
    disc = qb * qb - 4.0 * qa * qc
    sq = np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        candidates = ((-qb + sq) / (2.0 * qa), (-qb - sq) / (2.0 * qa), -qc / qb)
        roots = [np.where(np.isfinite(r) & (r > 0.0) & (r < h), r, 0.0) for r in candidates]
    pos_in = np.stack([((c3 * r + c2) * r + c1) * r + c0 for r in roots])
    low = np.minimum(pos_end.min(axis=0), pos_in.min(axis=(0, 1)))
    high = np.maximum(pos_end.max(axis=0), pos_in.max(axis=(0, 1)))
    v_ratio = np.maximum(vel_end.max(axis=0), vel_in.max(axis=0)) / v_max
    a_ratio = acc.max(axis=0) / a_max
    span = hi - lo
    ok = bool(
        np.all(v_ratio <= 1.0 + TOLERANCE)
        and np.all(a_ratio <= 1.0 + TOLERANCE)
        and np.all(low >= lo - TOLERANCE * span)
        and np.all(high <= hi + TOLERANCE * span)
    )
    return TaughtLimitCheck(v_ratio, a_ratio, low, high, ok)


def _fail(path: Path, message: str) -> ConfigurationError:
    return ConfigurationError(f"{path}: {message}")


def _segments(path: Path, where: str, raw: Any, n_joints: int) -> tuple[FloatArray, FloatArray]:
    if not isinstance(raw, list) or not raw:
        raise _fail(path, f"{where}.segments must be a non-empty list")
    h = np.empty(len(raw))
    c = np.empty((len(raw), n_joints, 4))
    for i, seg in enumerate(raw):
        try:
            h[i] = float(seg["duration_s"])
            ci = np.array(seg["coefficients"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as e:
            raise _fail(
                path, f"{where}.segments[{i}] needs duration_s and coefficients ({e})"
            ) from None
        if ci.shape != (n_joints, 4):
            raise _fail(
                path,
                f"{where}.segments[{i}].coefficients must be {n_joints} joints x 4 "
                f"(highest power first); got shape {ci.shape}",
            )
        if not (math.isfinite(h[i]) and h[i] >= MIN_SEGMENT_S) or not np.all(np.isfinite(ci)):
            raise _fail(
                path,
                f"{where}.segments[{i}]: duration {h[i]:g} s and coefficients must be finite, "
                f"the duration >= {MIN_SEGMENT_S} s",
            )
        c[i] = ci
    return h, c


def load_taught(directory: str | Path, rig: Rig | None = None) -> TaughtJob:
    """Read and verify ``DIR/taught.json`` (or the file itself) as a :class:`TaughtJob`.

    Args:
        directory: The directory ``teach --out`` wrote, or the path of its ``taught.json``.
        rig: The rig it must run on (default: the profile named in the file).

    Raises:
        ConfigurationError: Missing or malformed file, wrong joints, a discontinuity between
            segments or cycles, a start or end not at rest; the message names the file and the
            place.
        PlanningError: The trajectory breaks a velocity, acceleration or range limit of the
            rig (exact check); nothing of it may move the machine.
    """
    path = Path(directory)
    if path.is_dir():
        path = path / TAUGHT_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigurationError(
            f"{path}: no taught job here (write one with `excavator-rt teach ... --out DIR`)"
        ) from None
    except (OSError, ValueError) as e:
        raise _fail(path, f"not a readable JSON taught job ({e})") from None
    return taught_from_json(data, rig, path)


def taught_from_json(
    data: Any, rig: Rig | None = None, path: str | Path = TAUGHT_FILE
) -> TaughtJob:
    """Verify a taught job held in memory (the object ``taught.json`` holds) as
    :func:`load_taught` does; ``path`` names it in messages. ``teach --out`` runs it before
    writing the file.

    Raises:
        ConfigurationError, PlanningError: As :func:`load_taught`.
    """
    path = Path(path)
    if not isinstance(data, dict):
        raise _fail(path, "must hold one JSON object")
    if rig is None:
        name = data.get("rig")
        if not isinstance(name, str):
            raise _fail(path, "needs the rig's profile name under 'rig'")
        rig = load_rig(name)
    if not isinstance(data.get("joints"), list):
        raise _fail(path, f"needs joints, the list of joint names {list(rig.joint_names)}")
    joints = data.get("joints")
    names = tuple(joints) if isinstance(joints, list) else ()
    if names != tuple(rig.joint_names):
        raise _fail(
            path, f"joints {list(names)} are not the rig {rig.name}'s {list(rig.joint_names)}"
        )
    n_j = len(names)
    trench = data.get("trench")
    if not isinstance(trench, dict) or not isinstance(trench.get("cycles"), list):
        raise _fail(path, "needs trench.cycles, the list of the trench's cycles")
    cycles = trench["cycles"]
    if not cycles:
        raise _fail(path, "trench.cycles is empty")
    hs, cs, starts, offsets = [], [], [], []
    t = 0.0
    for k, cyc in enumerate(cycles):
        if not isinstance(cyc, dict):
            raise _fail(path, f"trench.cycles[{k}] must be an object")
        h, c = _segments(path, f"trench.cycles[{k}]", cyc.get("segments"), n_j)
        try:
            offsets.append(float(cyc.get("offset_m", 0.0)))
        except (TypeError, ValueError):
            raise _fail(path, f"trench.cycles[{k}].offset_m must be a number") from None
        starts.append(t)
        t += float(h.sum())
        hs.append(h)
        cs.append(c)
    h = np.concatenate(hs)
    c = np.concatenate(cs)
    knots = np.concatenate(([0.0], np.cumsum(h)))
    _continuity(path, h, c)
    try:
        waypoints = np.radians(np.array(data.get("waypoints_deg", []), dtype=np.float64))
        waypoints = waypoints.reshape(-1, n_j)
    except (TypeError, ValueError):
        raise _fail(path, f"waypoints_deg must be rows of {n_j} numbers") from None
    job = TaughtJob(
        rig_name=rig.name,
        joint_names=names,
        knots_s=knots,
        coefficients=c,
        cycle_starts_s=np.array(starts),
        offsets_m=np.array(offsets),
        waypoints_rad=waypoints,
    )
    check = job.limit_check(rig)
    if not check.within_limits:
        j = int(np.argmax(np.maximum(check.velocity_ratio, check.acceleration_ratio)))
        raise PlanningError(
            f"{path}: the taught trench breaks the limits of {rig.name}: peak velocity "
            f"{check.velocity_ratio.max():.6f}, acceleration "
            f"{check.acceleration_ratio.max():.6f} of the limit (worst joint {names[j]}), "
            f"range reached {np.degrees(check.position_low_rad).round(3).tolist()} .. "
            f"{np.degrees(check.position_high_rad).round(3).tolist()} deg; nothing of it runs"
        )
    return job


def _continuity(path: Path, h: FloatArray, c: FloatArray) -> None:
    """Position, velocity and acceleration continuous at every boundary; rest at both ends."""
    hh = h[:-1, None]
    c3, c2, c1, c0 = (c[:-1, :, i] for i in range(4))
    end = np.stack(
        [((c3 * hh + c2) * hh + c1) * hh + c0, (3.0 * c3 * hh + 2.0 * c2) * hh + c1,
         6.0 * c3 * hh + 2.0 * c2]
    )
    start = np.stack([c[1:, :, 3], c[1:, :, 2], 2.0 * c[1:, :, 1]])
    scale = 1.0 + np.abs(end)
    bad = np.abs(end - start) > TOLERANCE * scale
    if np.any(bad):
        d, i, j = (int(v) for v in np.argwhere(bad)[0])
        what = ("position", "velocity", "acceleration")[d]
        raise _fail(
            path,
            f"{what} of joint {j} jumps between segments {i} and {i + 1} "
            f"({end[d, i, j]:.9g} -> {start[d, i, j]:.9g}); a taught trench is C2",
        )
    last = c[-1]
    hl = h[-1]
    v_end = (3.0 * last[:, 0] * hl + 2.0 * last[:, 1]) * hl + last[:, 2]
    a_end = 6.0 * last[:, 0] * hl + 2.0 * last[:, 1]
    for what, value in (
        ("start velocity", c[0, :, 2]),
        ("start acceleration", 2.0 * c[0, :, 1]),
        ("end velocity", v_end),
        ("end acceleration", a_end),
    ):
        if np.any(np.abs(value) > 1e-6):
            raise _fail(
                path, f"{what} {value.tolist()} is not rest: a taught trench starts at rest "
                "and ends at rest",
            )
