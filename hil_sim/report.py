"""HIL tracking report: the stable JSON keys of DESIGN.md "Reports" and plots after Yao Fig. 17-21.

Role: turn one HIL run (the executor's per-SYNC telemetry, the HIL's truth at every SYNC, the
terrain the bucket really cut) into the figures of ``excavator-rt hil --json``:

* ``tracking``: per axis (boom, stick, bucket) ``max_mm`` and ``rms_mm`` of the true stroke
  (plant) minus the reference stroke at each SYNC, and ``reported`` the same on the drives'
  TPDO1 feedback (what the controller sees). Only cycles that streamed a motion count; holding
  and the stop after a fault do not (:class:`TrackingFigures`, with ``tip_error_max_mm`` and
  ``cycles``).
* ``tip_error_max_mm``: largest distance between the true tip and the reference tip (forward
  kinematics of the reference joint angles), same cycles.
* ``coverage_error``: area of the symmetric difference of what the bucket really removed from the
  terrain and the design, over the design's area (as the planner's own figure); ``overdig_max_mm``:
  the deepest point of the removed region outside the design, measured to the design
  (:class:`ProfileErrors`).

The whole report (these figures with the run's outcome, digs, energy, loop and CAN) is
:class:`hil_sim.harness.reports.HilReport`.

Plots (:func:`plot_report`, matplotlib when installed): joint angles reference vs truth (Fig. 17),
cylinder tracking error per axis (Fig. 18), joint rates from the drives (Fig. 19), drive power and
energy (Fig. 20), and the tip paths over the design and the surface that was cut (Fig. 21).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray

from rt_runtime import kinematics
from rt_runtime.rig import Rig

__all__ = [
    "AXES",
    "AxisError",
    "AxisTracking",
    "ProfileErrors",
    "Segment",
    "TrackingFigures",
    "axis_errors",
    "plot_report",
    "profile_errors",
    "tip_reference",
    "tracking_figures",
    "trench_shape",
]

FloatArray = NDArray[np.float64]
AXES = ("boom", "stick", "bucket")


@dataclass(frozen=True, slots=True)
class Segment:
    """One streamed motion joined with the truth, per SYNC (the report's raw material).

    Attributes:
        kind: ``dig``, ``lift_out``, ``dump``, ``approach``, ``enter``, ``connect``, ``hold``,
            ``stop``, ``travel``.
        index: Dig index for digs, else -1.
        sync_index: SYNC counts ``(n,)``.
        t_s: HIL clock at each SYNC ``(n,)``.
        tracking: Cycles that streamed the motion ``(n,)``.
        q_ref_rad, stroke_ref_m: Reference ``(n, 3)``.
        stroke_true_m, q_true_rad: Plant truth ``(n, 3)``.
        stroke_reported_m: Drive feedback ``(n, 3)`` (NaN where missing).
        velocity_reported_m_s: Drive feedback ``(n, 3)``.
        tip_ref_m, tip_true_m: Tip in the work-site frame ``(n, 2)``.
        power_w: Drive power per period ``(n,)``.
    """

    kind: str
    index: int
    sync_index: NDArray[np.int64]
    t_s: FloatArray
    tracking: NDArray[np.bool_]
    q_ref_rad: FloatArray
    stroke_ref_m: FloatArray
    stroke_true_m: FloatArray
    q_true_rad: FloatArray
    stroke_reported_m: FloatArray
    velocity_reported_m_s: FloatArray
    tip_ref_m: FloatArray
    tip_true_m: FloatArray
    power_w: FloatArray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True, slots=True)
class AxisError:
    """Stroke error of one axis (mm; NaN when no cycle counted).

    Attributes:
        max_mm: Largest absolute error.
        rms_mm: Root mean square error.
    """

    max_mm: float
    rms_mm: float

    def to_json(self) -> dict[str, float]:
        """``{"max_mm", "rms_mm"}``."""
        return {"max_mm": self.max_mm, "rms_mm": self.rms_mm}


@dataclass(frozen=True, slots=True)
class AxisTracking:
    """Tracking of one axis: on the plant's truth, and on the drives' feedback.

    Attributes:
        max_mm: Largest absolute error of the true stroke.
        rms_mm: Root mean square error of the true stroke.
        reported: The same on the stroke the drive reports.
    """

    max_mm: float
    rms_mm: float
    reported: AxisError

    def to_json(self) -> dict[str, Any]:
        """``{"max_mm", "rms_mm", "reported": {"max_mm", "rms_mm"}}``."""
        return {"max_mm": self.max_mm, "rms_mm": self.rms_mm, "reported": self.reported.to_json()}


@dataclass(frozen=True, slots=True)
class TrackingFigures:
    """Tracking over a set of segments.

    Attributes:
        tracking: Per axis name (:data:`AXES` order).
        tip_error_max_mm: Largest distance of the true tip from the reference tip (mm; NaN when
            no cycle counted).
        cycles: Cycles that counted (those that streamed a motion).
    """

    tracking: Mapping[str, AxisTracking]
    tip_error_max_mm: float
    cycles: int

    def to_json(self) -> dict[str, Any]:
        """``{"tracking": {axis: ...}, "tip_error_max_mm", "cycles"}``."""
        return {
            "tracking": {name: fig.to_json() for name, fig in self.tracking.items()},
            "tip_error_max_mm": self.tip_error_max_mm,
            "cycles": self.cycles,
        }


@dataclass(frozen=True, slots=True)
class ProfileErrors:
    """How the removed material compares with the design.

    Attributes:
        coverage_error: Symmetric difference of removed and design over the design's area.
        overdig_max_mm: Deepest point of the removed region outside the design (mm).
        removed_area_m2: Area of the removed region (m^2).
    """

    coverage_error: float
    overdig_max_mm: float
    removed_area_m2: float


def axis_errors(error_m: FloatArray) -> dict[str, AxisError]:
    """Per-axis error figures of an error array ``(n, 3)`` in m (NaN rows ignored)."""
    out: dict[str, AxisError] = {}
    for axis, name in enumerate(AXES):
        e = error_m[:, axis]
        e = e[np.isfinite(e)]
        if e.size == 0:
            out[name] = AxisError(math.nan, math.nan)
        else:
            out[name] = AxisError(
                float(np.max(np.abs(e)) * 1e3), float(np.sqrt(np.mean(e * e)) * 1e3)
            )
    return out


def tracking_figures(segments: list[Segment], digs_only: bool = False) -> TrackingFigures:
    """Tracking on truth (with the drives' ``reported`` figures per axis) and the tip error."""
    use = [s for s in segments if (s.kind == "dig") or not digs_only]
    if use:
        mask = np.concatenate([s.tracking for s in use])
        ref = np.concatenate([s.stroke_ref_m for s in use])[mask]
        true = np.concatenate([s.stroke_true_m for s in use])[mask]
        rep = np.concatenate([s.stroke_reported_m for s in use])[mask]
        tip_ref = np.concatenate([s.tip_ref_m for s in use])[mask]
        tip_true = np.concatenate([s.tip_true_m for s in use])[mask]
    else:
        ref = true = rep = np.zeros((0, 3))
        tip_ref = tip_true = np.zeros((0, 2))
    truth = axis_errors(true - ref)
    reported = axis_errors(rep - ref)
    tip = np.linalg.norm(tip_true - tip_ref, axis=1)
    return TrackingFigures(
        tracking={
            name: AxisTracking(truth[name].max_mm, truth[name].rms_mm, reported[name])
            for name in AXES
        },
        tip_error_max_mm=float(np.max(tip) * 1e3) if tip.size else math.nan,
        cycles=int(ref.shape[0]),
    )


def profile_errors(initial: Any, final: Any, design: Any) -> ProfileErrors:
    """Coverage error and over-dig of the material really removed.

    Args:
        initial: Terrain material polygon before the run (work-site frame).
        final: Material after the run.
        design: The designed cross-section polygon.
    """
    dug = initial.difference(final)
    sym = dug.symmetric_difference(design)
    coverage = float(sym.area) / float(design.area) if design.area > 0 else math.nan
    over = dug.difference(design)
    over_max = 0.0
    if not over.is_empty:
        coords = shapely.get_coordinates(over)
        if len(coords):
            over_max = float(np.max(shapely.distance(shapely.points(coords), design)))
    return ProfileErrors(coverage, over_max * 1e3, float(dug.area))


def trench_shape(
    x_m: FloatArray, y_m: FloatArray, ground_y_m: float
) -> tuple[float, float, float, float]:
    """The trench a sampled surface shows, in Yao Table 6's terms.

    ``D`` is the ground height less the lowest point; each wall's slope is the line fitted
    (least squares) through its samples between 20 % and 80 % of D below the ground, the walls
    split at the middle of the bottom (the samples within 10 % of D of the lowest); ``L`` the
    length at the top, between the two fitted walls where they meet the ground (without two
    walls: between the outermost samples more than 2 % of D below the ground).

    Args:
        x_m: Abscissae ``(n,)``, increasing.
        y_m: Surface heights ``(n,)``.
        ground_y_m: The undisturbed ground height.

    Returns:
        ``(L_m, D_m, beta_far_rad, beta_near_rad)``: the far wall is the one at larger x
        (Yao's beta1, where the task starts), the near one at smaller x (beta2); NaN where the
        surface shows no trench or a wall has fewer than two samples in its band.
    """
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    depth = ground_y_m - float(y.min())
    if not depth > 0.0:
        return math.nan, math.nan, math.nan, math.nan
    below = np.flatnonzero(y < ground_y_m - 0.02 * depth)
    length = float(x[below[-1]] - x[below[0]])
    bottom = np.flatnonzero(y <= float(y.min()) + 0.1 * depth)
    x_mid = 0.5 * (float(x[bottom[0]]) + float(x[bottom[-1]]))
    band = (y <= ground_y_m - 0.2 * depth) & (y >= ground_y_m - 0.8 * depth)
    slopes = []
    at_ground = []
    for side in (x > x_mid, x < x_mid):
        sel = band & side
        if int(sel.sum()) < 2:
            slopes.append(math.nan)
            continue
        m, c = (float(v) for v in np.polyfit(x[sel], y[sel], 1))
        slopes.append(math.atan(abs(m)))
        if m != 0.0:
            at_ground.append((ground_y_m - c) / m)
    if len(at_ground) == 2:
        length = at_ground[0] - at_ground[1]
    return length, depth, slopes[0], slopes[1]


def tip_reference(rig: Rig, q_ref_rad: FloatArray, machine_x_m: FloatArray) -> FloatArray:
    """Reference tip positions in the work-site frame ``(n, 2)``."""
    tip = np.array(kinematics.forward(rig, q_ref_rad), dtype=np.float64)[..., :2].reshape(-1, 2)
    tip[:, 0] += machine_x_m
    return tip


def plot_report(
    segments: list[Segment],
    out_dir: str | Path,
    *,
    design: Any = None,
    surface_m: FloatArray | None = None,
    title: str = "",
) -> list[Path]:
    """Write the figures (PNG) in the manner of Yao Fig. 17-21; empty list without matplotlib.

    Args:
        segments: The run's segments.
        out_dir: Directory (created).
        design: Design polygon for the profile figure, or None.
        surface_m: Final terrain surface ``(n, 2)`` for the profile figure, or None.
        title: Figure title prefix.

    Returns:
        The files written.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if not segments:
        return []
    t = np.concatenate([s.t_s for s in segments])
    t = t - t[0]
    q_ref = np.concatenate([s.q_ref_rad for s in segments])
    q_true = np.concatenate([s.q_true_rad for s in segments])
    err = np.concatenate([s.stroke_true_m - s.stroke_ref_m for s in segments])
    err_rep = np.concatenate([s.stroke_reported_m - s.stroke_ref_m for s in segments])
    vel = np.concatenate([s.velocity_reported_m_s for s in segments])
    power = np.concatenate([s.power_w for s in segments])
    mask = np.concatenate([s.tracking for s in segments])
    err[~mask] = np.nan
    err_rep[~mask] = np.nan
    files: list[Path] = []

    def save(fig: Any, name: str) -> None:
        path = out / name
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        files.append(path)

    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, name in enumerate(AXES):
        axes[i].plot(t, np.degrees(q_ref[:, i]), "k--", lw=1, label="reference")
        axes[i].plot(t, np.degrees(q_true[:, i]), lw=1, label="HIL truth")
        axes[i].set_ylabel(f"theta {name} (deg)")
    axes[0].legend(loc="best")
    axes[0].set_title(f"{title} joint angles (cf. Yao Fig. 17)")
    axes[-1].set_xlabel("t (s)")
    save(fig, "fig17_joint_angles.png")

    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, name in enumerate(AXES):
        axes[i].plot(t, err[:, i] * 1e3, lw=0.8, label="truth")
        axes[i].plot(t, err_rep[:, i] * 1e3, lw=0.8, alpha=0.7, label="reported")
        axes[i].set_ylabel(f"{name} error (mm)")
    axes[0].legend(loc="best")
    axes[0].set_title(f"{title} cylinder tracking error (cf. Yao Fig. 18)")
    axes[-1].set_xlabel("t (s)")
    save(fig, "fig18_tracking_error.png")

    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, name in enumerate(AXES):
        axes[i].plot(t, vel[:, i] * 1e3, lw=0.8)
        axes[i].set_ylabel(f"{name} rate (mm/s)")
    axes[0].set_title(f"{title} cylinder rates reported by the drives (cf. Yao Fig. 19)")
    axes[-1].set_xlabel("t (s)")
    save(fig, "fig19_cylinder_rates.png")

    fig, ax = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    ax[0].plot(t, power, lw=0.8)
    ax[0].set_ylabel("drive power (W)")
    dt = np.diff(t, prepend=t[0])
    ax[1].plot(t, np.cumsum(power * dt) / 3600.0, lw=1)
    ax[1].set_ylabel("energy (Wh)")
    ax[1].set_xlabel("t (s)")
    ax[0].set_title(f"{title} power and energy (cf. Yao Fig. 20)")
    save(fig, "fig20_power_energy.png")

    fig, ax = plt.subplots(figsize=(9, 5))
    if design is not None:
        x, y = design.exterior.xy
        ax.fill(x, y, color="0.85", label="design")
    if surface_m is not None:
        ax.plot(surface_m[:, 0], surface_m[:, 1], "k", lw=1.2, label="surface after digging")
    for s in segments:
        if s.kind == "dig":
            ax.plot(s.tip_ref_m[:, 0], s.tip_ref_m[:, 1], "--", lw=0.8, color="C0")
            ax.plot(s.tip_true_m[:, 0], s.tip_true_m[:, 1], lw=0.8, color="C3")
    ax.plot([], [], "--", color="C0", label="planned tip path")
    ax.plot([], [], color="C3", label="HIL tip path")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, work site)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best")
    ax.set_title(f"{title} trench profile (cf. Yao Fig. 21)")
    save(fig, "fig21_profile.png")
    return files
