"""Terrain of the HIL: the material cross-section the bucket digs, cut for real, and its soil force.

Role: the HIL's ground truth for "what was dug". The material in the arm plane is a shapely
polygon, as in the trench planner: the region between the surface line and a bottom
far below it, over ``x_range_m``. :meth:`Terrain.cut` removes what a bucket tip path swept and
returns the removed area and volume (area x bucket width); the surface the bucket leaves is what
the HIL report compares with the design profile.

What a cut removes. The tip carries away the material above it, so a tip path removes the union,
over its segments, of the region above each segment (inside the material): the material above
the lower envelope of the path. For a path that runs one way in x this is the area between the
path and the surface, exactly what :func:`rt_runtime.planning.oneshot.excavated_area_m2`
integrates; a path that doubles back removes nothing twice, and a vertical plunge removes
nothing by itself (the drag that follows does).

When to cut. Yao eq 8 takes h as the depth of *uncut* material above the tip. Cutting the
polygon while the bucket is still in the cut would put the surface at the tip and zero the
force, so the HIL cuts once per dig (after it, with the dig's whole tip path), not per sub-step.

Fast lookups. Besides the polygon the terrain keeps the surface sampled on a uniform grid
(``resolution_m``, default 1 mm) for :meth:`surface_y` (np.interp) and the plant's per-sub-step
soil force (:class:`YaoTipLoad`, index arithmetic, no polygon operation). The grid is updated by
each cut from the same lower envelope, so grid and polygon agree at every grid abscissa.

Granular material (``material``, profile ``[hil.materials]``): a cut keeps the spill out of the
bucket (:attr:`CutResult.load_m3`), lays the part of it that falls back into the trench over the
span it lowered, then relaxes every face steeper than the angle of repose (:func:`slump`,
area-conserving) and rebuilds the polygon from the sampled surface; the material's resistance
factor scales Yao eq 8. Without a material a cut removes exactly what the tip swept.

Soil force: :meth:`Terrain.soil_force` is Yao eq 8 through :func:`rt_runtime.soil.yao_resistance`
with the ground height looked up above each tip (batched). :class:`YaoTipLoad` is the same law
written out for one tip in plain floats (about ten times cheaper), plus the velocity derivative
the plant needs to integrate the law's stiff low-speed damping implicitly; ``tests/test_terrain.py``
holds the two to 1e-12.

Not for the fixed-rate control loop: cuts allocate and call shapely; the sub-step path
(:meth:`YaoTipLoad.tip_load`) allocates nothing.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray
from shapely.geometry import box
from shapely.geometry.base import BaseGeometry

from rt_runtime import soil as soil_models
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Material, Rig

FloatArray = NDArray[np.float64]

#: Default spacing of the sampled surface (m).
DEFAULT_RESOLUTION_M = 1e-3

#: Tolerance of the tip path's simplification before a cut (m; see :meth:`Terrain.cut`).
CUT_SIMPLIFY_M = 1e-6


@dataclass(frozen=True, slots=True)
class CutResult:
    """What one cut removed.

    Attributes:
        area_m2: Removed cross-section area (what the tip path swept).
        volume_m3: Removed volume, area times the bucket width.
        load_m3: What the bucket kept of it: ``volume_m3`` on ideal material, less the spill
            on granular material.
        fallback_m3: Spill that fell back into the trench (granular material).
        slumped_m3: Material the slump to the angle of repose moved (granular material).
    """

    area_m2: float
    volume_m3: float
    load_m3: float = math.nan
    fallback_m3: float = 0.0
    slumped_m3: float = 0.0

    def __post_init__(self) -> None:
        if self.load_m3 != self.load_m3:  # NaN: the ideal bucket keeps what it swept
            object.__setattr__(self, "load_m3", self.volume_m3)


def slump(y_m: FloatArray, dx_m: float, repose_rad: float, tol_m: float = 1e-6) -> float:
    """Relax a sampled surface in place until no face is steeper than the angle of repose.

    Each pass moves, between every two neighbouring samples whose height difference exceeds
    ``tan(repose) dx`` by ``e``, ``e / 4`` from the higher to the lower one (a quarter, so
    that a sample between two steep faces never overshoots); the sum of the heights (the area,
    times ``dx``) is conserved to rounding. Stops once no excess is above ``tol_m``.

    The passes diffuse a face's excess one sample at a time, so a face of n samples takes of
    the order of n^2 passes; the relaxation therefore runs first on the surface coarsened by
    pairs (means, twice the spacing: the same area), recursively, and each pair takes its
    coarse change back (the area stays); the passes on the fine surface then only smooth what
    the coarse one could not see, within a few samples (a 1 m face on a 1 mm grid: ~0.1 s
    instead of minutes).

    Args:
        y_m: Heights ``(n,)`` on a uniform grid, changed in place.
        dx_m: Grid spacing (m), > 0.
        repose_rad: Angle of repose, in (0, pi/2).
        tol_m: Largest excess left (m).

    Returns:
        The area moved (m^2): the sum of the height lost where the surface fell, times dx.
    """
    before = y_m.copy()
    _relax(y_m, dx_m, math.tan(repose_rad), tol_m)
    return float(np.maximum(before - y_m, 0.0).sum() * dx_m)


#: Below this many samples the relaxation runs on the surface as it is.
_SLUMP_DIRECT_SAMPLES = 64


def _relax(y: FloatArray, dx: float, slope: float, tol: float) -> None:
    """:func:`slump`'s relaxation, coarse to fine (see there)."""
    n = y.shape[0]
    if n >= 2 * _SLUMP_DIRECT_SAMPLES:
        m = n // 2
        pairs = y[: 2 * m].reshape(m, 2)
        coarse = pairs.mean(axis=1)
        relaxed = coarse.copy()
        _relax(relaxed, 2.0 * dx, slope, tol)
        pairs += (relaxed - coarse)[:, None]  # a view of y: each pair keeps its area change
    step = slope * dx
    while True:
        d = y[:-1] - y[1:]
        excess = np.sign(d) * np.maximum(np.abs(d) - step, 0.0)
        if float(np.abs(excess).max(initial=0.0)) <= tol:
            return
        move = 0.25 * excess
        y[:-1] -= move
        y[1:] += move


def _finite(name: str, value: float) -> float:
    x = float(value)
    if not math.isfinite(x):
        raise ConfigurationError(f"{name} must be finite; got {value!r}")
    return x


def _points(name: str, value: ArrayLike) -> FloatArray:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 2:
        raise ValueError(f"{name} must have shape (..., 2) (x_m, y_m); got {a.shape}")
    if not np.isfinite(a).all():
        raise ConfigurationError(f"{name} has non-finite values (NaN or inf)")
    return a


class Terrain:
    """Material cross-section the bucket cuts, with a fast surface lookup (a mutable workspace).

    Args:
        ground_y_m: Initial flat surface height (arm frame, y up).
        x_range_m: ``(x_min, x_max)`` of the modelled material; beyond it the surface height
            continues flat at its end values (lookups) and nothing is cut.
        bucket_width_m: Cutting width b: volume = area x b.
        bottom_y_m: Bottom of the material polygon; default ``x_max - x_min + 1`` m below the
            ground. Material below it is not modelled.
        resolution_m: Spacing of the sampled surface.
        material: Granular material (profile ``[hil.material]``): a cut keeps the spill out of
            the bucket, lets part of it fall back into the trench, and slumps every face
            steeper than the angle of repose; None: a cut removes exactly what the tip swept.

    Raises:
        ConfigurationError: A non-finite value, ``x_min >= x_max``, a width or resolution not
            > 0, or a bottom not below the ground.
    """

    def __init__(
        self,
        ground_y_m: float,
        x_range_m: tuple[float, float],
        bucket_width_m: float,
        *,
        bottom_y_m: float | None = None,
        resolution_m: float = DEFAULT_RESOLUTION_M,
        material: Material | None = None,
    ) -> None:
        ground = _finite("ground_y_m", ground_y_m)
        x_min = _finite("x_range_m[0]", x_range_m[0])
        x_max = _finite("x_range_m[1]", x_range_m[1])
        if not x_min < x_max:
            raise ConfigurationError(
                f"x_range_m must be (min, max) with min < max; got {x_range_m}"
            )
        width = _finite("bucket_width_m", bucket_width_m)
        res = _finite("resolution_m", resolution_m)
        if not (width > 0.0 and res > 0.0):
            raise ConfigurationError(
                f"bucket_width_m and resolution_m must be > 0; got {bucket_width_m}, {resolution_m}"
            )
        bottom = (
            ground - (x_max - x_min) - 1.0
            if bottom_y_m is None
            else _finite("bottom_y_m", bottom_y_m)
        )
        if not bottom < ground:
            raise ConfigurationError(
                f"bottom_y_m must be below ground_y_m = {ground:g}; got {bottom:g}"
            )
        n = max(2, math.ceil((x_max - x_min) / res) + 1)
        self._x = np.linspace(x_min, x_max, n)
        self._y = np.full(n, ground)
        self._x0 = x_min
        self._inv_dx = (n - 1) / (x_max - x_min)
        self._last = n - 1
        # Plain-float copy of the grid for the per-sub-step lookup (list indexing beats numpy's
        # scalar indexing by ~10x).
        self._y_list: list[float] = self._y.tolist()
        self._material: BaseGeometry = box(x_min, bottom, x_max, ground)
        self._width = width
        self._bottom = bottom
        self._x_range = (x_min, x_max)
        self._removed_area = 0.0
        self._granular = material
        # Totals over the cuts (m^3): swept, kept in the bucket, fallen back, slumped.
        self._totals = [0.0, 0.0, 0.0, 0.0]

    def copy(self) -> Terrain:
        """An independent copy (cutting one leaves the other as it was)."""
        out = copy.copy(self)
        out._y = self._y.copy()
        out._y_list = list(self._y_list)
        out._totals = list(self._totals)
        return out

    @property
    def material(self) -> BaseGeometry:
        """The remaining material as a shapely geometry (a Polygon unless a cut split it)."""
        return self._material

    @property
    def swept_m3(self) -> float:
        """Volume the tip paths of all cuts swept."""
        return self._totals[0]

    @property
    def load_m3(self) -> float:
        """Volume the bucket kept over all cuts (the swept volume on ideal material)."""
        return self._totals[1]

    @property
    def fallback_m3(self) -> float:
        """Spill that fell back into the trench over all cuts."""
        return self._totals[2]

    @property
    def slumped_m3(self) -> float:
        """Volume the slumps moved over all cuts."""
        return self._totals[3]

    @property
    def granular(self) -> Material | None:
        """The granular material, or None (a cut removes exactly what the tip swept)."""
        return self._granular

    @property
    def bucket_width_m(self) -> float:
        """Cutting width used for volumes."""
        return self._width

    @property
    def x_range_m(self) -> tuple[float, float]:
        """``(x_min, x_max)`` of the modelled material."""
        return self._x_range

    @property
    def surface_x_m(self) -> FloatArray:
        """Abscissae of the sampled surface, ``(n,)`` (a read-only copy)."""
        out = self._x.copy()
        out.setflags(write=False)
        return out

    @property
    def surface_y_m(self) -> FloatArray:
        """Heights of the sampled surface, ``(n,)`` (a read-only copy)."""
        out = self._y.copy()
        out.setflags(write=False)
        return out

    @property
    def removed_area_m2(self) -> float:
        """Total area removed by all cuts so far."""
        return self._removed_area

    @property
    def removed_volume_m3(self) -> float:
        """Total volume removed by all cuts so far."""
        return self._removed_area * self._width

    def surface_profile(self) -> soil_models.SurfaceProfile:
        """The current surface as a :class:`rt_runtime.soil.SurfaceProfile` (e.g. for the
        fluid soil model or the planner)."""
        return soil_models.SurfaceProfile(self._x, self._y)

    def surface_y(self, x_m: ArrayLike) -> FloatArray:
        """Surface height above ``x_m`` (any shape; the same shape back), linear between grid
        points, the end heights beyond the x range.

        Raises:
            ConfigurationError: ``x_m`` has non-finite values.
        """
        x = np.asarray(x_m, dtype=np.float64)
        if not np.isfinite(x).all():
            raise ConfigurationError("x_m has non-finite values (NaN or inf)")
        out: FloatArray = np.interp(x, self._x, self._y)
        return out

    def depth_of_cut(self, tip_xy_m: ArrayLike) -> FloatArray:
        """Depth h of the tip below the surface directly above it, 0 above ground (Yao eq 8).

        Args:
            tip_xy_m: Tip positions ``(..., 2)``.

        Returns:
            ``(...)`` in m, >= 0.

        Raises:
            ValueError: Not shaped ``(..., 2)``.
            ConfigurationError: Non-finite values.
        """
        tip = _points("tip_xy_m", tip_xy_m)
        depth: FloatArray = np.maximum(np.interp(tip[..., 0], self._x, self._y) - tip[..., 1], 0.0)
        return depth

    def soil_force(
        self,
        tip_xy_m: ArrayLike,
        tip_velocity_xy_m_s: ArrayLike,
        rig: Rig,
        *,
        speed_reg_m_s: float = soil_models.DEFAULT_SPEED_REG_M_S,
    ) -> FloatArray:
        """Digging resistance of Yao eq 8 on the tip, from :func:`rt_runtime.soil.yao_resistance`.

        ``W_Q = K0 b h`` against the tip velocity and ``mu W_Q`` across it (pushing the edge
        out of the cut), h the depth below this terrain's surface; zero above the surface.
        Batched: the batch axes of position and velocity broadcast.

        Args:
            tip_xy_m: Tip positions ``(..., 2)``, arm frame.
            tip_velocity_xy_m_s: Tip velocities ``(..., 2)``.
            rig: The rig (K0, mu, bucket width of its Yao soil).
            speed_reg_m_s: Speed below which the force ramps to zero (see rt_runtime.soil).

        Returns:
            ``(..., 2)``: ``(fx_n, fy_n)`` the soil applies to the bucket at the tip.

        Raises:
            ValueError: Wrong shapes.
            ConfigurationError: Non-finite values or a bad ``speed_reg_m_s``.
        """
        tip = _points("tip_xy_m", tip_xy_m)
        vel = _points("tip_velocity_xy_m_s", tip_velocity_xy_m_s)
        batch = np.broadcast_shapes(tip.shape[:-1], vel.shape[:-1])
        pose = np.zeros((*batch, 3))
        twist = np.zeros((*batch, 3))
        pose[..., :2] = tip
        twist[..., :2] = vel
        ground = np.interp(pose[..., 0], self._x, self._y)
        wrench = soil_models.yao_resistance(rig, pose, twist, ground, speed_reg_m_s=speed_reg_m_s)
        return np.ascontiguousarray(wrench[..., :2])

    def soil_model(
        self, rig: Rig, *, speed_reg_m_s: float = soil_models.DEFAULT_SPEED_REG_M_S
    ) -> YaoTipLoad:
        """The per-sub-step soil law of ``rig`` on this terrain (live: later cuts count)."""
        return YaoTipLoad(self, rig, speed_reg_m_s=speed_reg_m_s)

    def surface_at(self, x_m: float) -> float:
        """Surface height above one abscissa, in plain floats (the sub-step path)."""
        u = (x_m - self._x0) * self._inv_dx
        if u <= 0.0:
            return self._y_list[0]
        if u >= self._last:
            return self._y_list[self._last]
        i = int(u)
        y0 = self._y_list[i]
        return y0 + (u - i) * (self._y_list[i + 1] - y0)

    def cut(self, tip_path_xy_m: ArrayLike, simplify_m: float = CUT_SIMPLIFY_M) -> CutResult:
        """Remove the material the tip swept: everything above the path's lower envelope.

        The path is first simplified (Douglas-Peucker within ``simplify_m``; by default
        :data:`CUT_SIMPLIFY_M`, below the drives' encoder resolution): a dig sampled every 2 ms
        has ~3000 points, nearly all collinear within a micrometre, and sweeping every segment
        took 30-90 ms, a stall the real-time HIL's drives cannot afford; ~500 points remain.
        The removed area moves by at most ``simplify_m`` times the path's length.

        Args:
            tip_path_xy_m: Tip path ``(m, 2)``, m >= 2, in time order (arm frame).
            simplify_m: Simplification tolerance (m); 0 sweeps every segment as given.

        Returns:
            The area removed by this cut and its volume (area x bucket width).

        Raises:
            ValueError: Not shaped ``(m, 2)`` with m >= 2.
            ConfigurationError: Non-finite values.
        """
        path = _points("tip_path_xy_m", tip_path_xy_m)
        if path.ndim != 2 or path.shape[0] < 2:
            raise ValueError(f"tip_path_xy_m must have shape (m, 2), m >= 2; got {path.shape}")
        if path.shape[0] > 2 and simplify_m > 0.0:
            line = shapely.simplify(shapely.linestrings(path), simplify_m, preserve_topology=False)
            path = shapely.get_coordinates(line)
        x0, y0 = path[:-1, 0], path[:-1, 1]
        x1, y1 = path[1:, 0], path[1:, 1]
        # A vertical segment sweeps no area (its neighbours carry its depth), nor does one
        # wholly above the material (the arm's moves in the air: most of a cycle's path).
        surface_top = float(self._y.max())
        above = max(surface_top, float(self._material.bounds[3]))
        keep = (x0 != x1) & (np.minimum(y0, y1) <= above)
        top = max(surface_top, float(path[:, 1].max())) + 1.0
        if not keep.any():
            return CutResult(0.0, 0.0)
        x0, y0, x1, y1 = x0[keep], y0[keep], x1[keep], y1[keep]
        rings = np.empty((x0.size, 5, 2))
        rings[:, 0, 0], rings[:, 0, 1] = x0, y0
        rings[:, 1, 0], rings[:, 1, 1] = x1, y1
        rings[:, 2, 0], rings[:, 2, 1] = x1, top
        rings[:, 3, 0], rings[:, 3, 1] = x0, top
        rings[:, 4] = rings[:, 0]
        sweep = shapely.union_all(shapely.polygons(rings))
        removed = float(self._material.intersection(sweep).area)
        self._material = self._material.difference(sweep)
        before = self._y.copy() if self._granular is not None else None
        self._lower_surface(x0, y0, x1, y1)
        self._removed_area += removed
        if before is None or self._granular is None:
            result = CutResult(removed, removed * self._width)
        else:
            result = self._granular_cut(self._granular, removed, before)
        totals = self._totals
        totals[0] += result.volume_m3
        totals[1] += result.load_m3
        totals[2] += result.fallback_m3
        totals[3] += result.slumped_m3
        return result

    def _granular_cut(self, mat: Material, removed_m2: float, before: FloatArray) -> CutResult:
        """After a cut on granular material: the spill's fallback lies down as an even layer
        over the span the cut lowered, then every face slumps to the angle of repose, and the
        polygon is rebuilt from the sampled surface (conserving the area to the grid's
        resolution)."""
        spill = mat.spill_fraction * removed_m2
        fallback = mat.fallback_fraction * spill
        lowered = np.flatnonzero(self._y < before)
        dx = (self._x[-1] - self._x[0]) / self._last
        if fallback > 0.0 and lowered.size:
            span = slice(int(lowered[0]), int(lowered[-1]) + 1)
            width = (span.stop - span.start) * dx
            self._y[span] = np.minimum(self._y[span] + fallback / width, before[span])
        slumped = slump(self._y, dx, mat.repose_rad)
        self._y_list = self._y.tolist()
        ring = np.concatenate(
            [
                [[self._x[0], self._bottom]],
                np.stack([self._x, self._y], axis=1),
                [[self._x[-1], self._bottom]],
            ]
        )
        self._material = shapely.Polygon(ring)
        w = self._width
        return CutResult(
            removed_m2,
            removed_m2 * w,
            load_m3=(removed_m2 - spill) * w,
            fallback_m3=fallback * w,
            slumped_m3=slumped * w,
        )

    def _lower_surface(
        self, x0: FloatArray, y0: FloatArray, x1: FloatArray, y1: FloatArray
    ) -> None:
        """Lower the sampled surface to the segments' envelope (the polygon's new top)."""
        lo = np.minimum(x0, x1)
        hi = np.maximum(x0, x1)
        first = np.searchsorted(self._x, lo, side="left")
        last = np.searchsorted(self._x, hi, side="right")
        for k in np.flatnonzero(last > first):
            span = slice(first[k], last[k])
            ys = y0[k] + (self._x[span] - x0[k]) * ((y1[k] - y0[k]) / (x1[k] - x0[k]))
            np.minimum(self._y[span], np.maximum(ys, self._bottom), out=self._y[span])
        self._y_list = self._y.tolist()


class YaoTipLoad:
    """Yao eq 8 on one tip in plain floats, with its velocity derivative (the plant's hot path).

    The force law is ``F = -G(v) v`` with ``G = g [[1, s mu], [-s mu, 1]]``,
    ``g = K0 b h / max(|v|, speed_reg)`` and ``s = +1`` when the tip moves forward (vx > 0),
    else -1: exactly :func:`rt_runtime.soil.yao_resistance`. :meth:`tip_load` returns the force
    and ``G`` frozen at the current state, so the plant can take the next velocity implicitly
    (``F = -G v_next``): below ``speed_reg`` the law is a damper of gain up to ~1e6 N*s/m that
    an explicit step at 250 us cannot follow.

    Args:
        terrain: The terrain whose (current) surface gives the depth.
        rig: The rig: ``soil.yao`` K0 and mu, ``bucket.width_m``; K0 times the terrain's
            granular ``resistance_factor`` where it has one.
        speed_reg_m_s: Regularisation speed, as in rt_runtime.soil.

    Raises:
        ConfigurationError: ``speed_reg_m_s`` not finite and > 0.
    """

    __slots__ = ("_k0b", "_mu", "_reg", "_terrain")

    def __init__(
        self,
        terrain: Terrain,
        rig: Rig,
        *,
        speed_reg_m_s: float = soil_models.DEFAULT_SPEED_REG_M_S,
    ) -> None:
        reg = float(speed_reg_m_s)
        if not (math.isfinite(reg) and reg > 0.0):
            raise ConfigurationError(f"speed_reg_m_s must be finite and > 0; got {speed_reg_m_s!r}")
        self._terrain = terrain
        factor = terrain.granular.resistance_factor if terrain.granular is not None else 1.0
        self._k0b = rig.soil.yao.k0_n_m2 * rig.bucket.width_m * factor
        self._mu = rig.soil.yao.mu
        self._reg = reg

    def tip_load(
        self, x_m: float, y_m: float, vx_m_s: float, vy_m_s: float
    ) -> tuple[float, float, float, float, float, float]:
        """Soil force on the tip and its damping matrix ``D = -dF/dv`` frozen at this state.

        Returns:
            ``(fx_n, fy_n, d_xx, d_xy, d_yx, d_yy)``, D in N*s/m; all zero above the surface.
        """
        depth = self._terrain.surface_at(x_m) - y_m
        if depth <= 0.0:
            return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        speed = math.hypot(vx_m_s, vy_m_s)
        g = self._k0b * depth / (speed if speed > self._reg else self._reg)
        r = g * self._mu if vx_m_s > 0.0 else -g * self._mu
        return (-g * vx_m_s - r * vy_m_s, -g * vy_m_s + r * vx_m_s, g, r, -r, g)
