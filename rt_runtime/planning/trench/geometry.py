"""Geometry of the material model: lower envelopes of tip paths on the height field's grid,
the region a path sweeps (a shapely polygon), the sextic's shape functions, depths below a
height field, and the helpers the screening shares.

Work-site frame, m. Pure functions; none of them is used inside the control loop."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray
from shapely.geometry import Polygon

from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType

FloatArray = NDArray[np.float64]

#: No dig may cut below the design profile by more than this (m).
OVERDIG_LIMIT_M = 0.005

#: A dig must remove at least this fraction of the design's area of design material; when no
#: candidate does, the task is finished with what is left reported as coverage error.
MIN_USEFUL_FRACTION = 0.004

#: Grid step of the height field (m).
GRID_STEP_M = 0.001

# Thinner parts of a polygon difference are rounding, not ground (see TrenchSession.finish).
_SLIVER_M = 1e-6

#: Second difference (m) below which an envelope's grid point is on a straight piece of it
#: (:func:`_swept_polygon` drops it).
_COLLINEAR_M = 1e-12


def lower_envelope(path_xy: FloatArray, grid_x: FloatArray) -> FloatArray:
    """Lowest y of a polyline over each grid x it spans (+inf where it does not).

    Exact for the polyline: every segment is interpolated at the grid points inside its x-span.
    """
    x0 = float(grid_x[0])
    h = float(grid_x[1] - grid_x[0])
    n = grid_x.shape[0]
    env = np.full(n, np.inf)
    xa, xb = path_xy[:-1, 0], path_xy[1:, 0]
    ya, yb = path_xy[:-1, 1], path_xy[1:, 1]
    lo = np.minimum(xa, xb)
    i0 = np.clip(np.ceil((lo - x0) / h - 1e-9), 0, n).astype(np.int64)
    i1 = np.clip(np.floor((lo + np.abs(xb - xa) - x0) / h + 1e-9) + 1, 0, n).astype(np.int64)
    counts = np.maximum(i1 - i0, 0)
    total = int(counts.sum())
    if total:
        seg = np.repeat(np.arange(counts.shape[0]), counts)
        idx = np.arange(total) + np.repeat(i0 - (np.cumsum(counts) - counts), counts)
        dx = xb - xa
        flat = np.abs(dx) <= 1e-12
        slope = np.where(flat, 0.0, (yb - ya) / np.where(flat, 1.0, dx))
        y_lo = np.minimum(ya, yb)
        base = np.where(flat, y_lo, ya)
        y = base[seg] + slope[seg] * (grid_x[idx] - xa[seg])
        # Clipping y to the segment's range is clipping its parameter to [0, 1].
        y = np.minimum(np.maximum(y, y_lo[seg]), np.maximum(ya, yb)[seg])
        np.minimum.at(env, idx, y)
    return env


def _swept_polygon(
    path_xy: FloatArray,
    grid_x: FloatArray,
    top_y: float,
    env: FloatArray | None = None,
    envelope: Callable[[FloatArray, FloatArray], FloatArray] = lower_envelope,
) -> Polygon | None:
    """The region above the path's lower envelope over its span, up to ``top_y``.

    ``env``: the path's :func:`lower_envelope` on ``grid_x`` when the caller has it;
    ``envelope``: what computes it (the session's C kernel, else :func:`lower_envelope`).
    """
    if env is None:
        env = envelope(path_xy, grid_x)
    ok = np.flatnonzero(np.isfinite(env))
    if ok.shape[0] < 2:
        return None
    # The path is continuous, so the grid points it spans are one run: ok[0]..ok[-1].
    i0, i1 = int(ok[0]), int(ok[-1]) + 1
    # Keep the exact end points of the span (the grid may start inside it).
    x_lo = max(float(np.min(path_xy[:, 0])), float(grid_x[0]))
    x_hi = min(float(np.max(path_xy[:, 0])), float(grid_x[-1]))
    y = np.minimum(env[i0:i1], top_y)
    # Interior grid points on a straight piece of the envelope add nothing to the region: only
    # its kinks are kept (the envelope is linear between the path's samples, so ~3-4 of every
    # 4 points go). The region is the same to ~1e-8 m (1e-12 m per dropped point, k^2 / 8 of
    # it over a run of k), and every later polygon operation on the material, which would
    # accumulate these vertices dig after dig, costs that much less.
    keep = np.ones(y.shape[0], dtype=bool)
    keep[1:-1] = np.abs(y[2:] - 2.0 * y[1:-1] + y[:-2]) > _COLLINEAR_M
    m = int(np.count_nonzero(keep))
    coords = np.empty((m + 4, 2))
    coords[0] = (x_lo, top_y)
    coords[2 : m + 2, 0] = grid_x[i0:i1][keep]
    coords[2 : m + 2, 1] = y[keep]
    # The span's ends at the path's own lowest point there (its envelope on the two-point
    # grid of the ends), not at the nearest grid point's envelope: on a steep path that is up
    # to a grid step's worth of slope deeper than the path reaches at the end, which cut past
    # the design (5.15 mm by a dig whose path went 4.78 mm deep).
    ends = np.minimum(envelope(path_xy, np.array([x_lo, x_hi])), top_y)
    coords[1] = (x_lo, ends[0])
    coords[m + 2] = (x_hi, ends[1])
    coords[m + 3] = (x_hi, top_y)
    poly = shapely.polygons(coords)
    # Only a path reaching the top line makes the outline touch itself.
    if (np.any(y >= top_y) or np.any(ends >= top_y)) and not shapely.is_valid(poly):
        poly = poly.buffer(0)
    return poly


def _sextic_shapes(n: int) -> tuple[FloatArray, FloatArray]:
    """The sextic's shape functions on ``n`` uniform samples of [0, 1]: the joint blend
    ``10 s^3 - 15 s^4 + 6 s^5`` and the bulge profile ``s^3 (1 - s)^3``."""
    s = np.linspace(0.0, 1.0, n)
    return 10 * s**3 - 15 * s**4 + 6 * s**5, s**3 * (1 - s) ** 3


def sextic_bulge(a6: ArrayLike, T_s: float) -> FloatArray:
    """The bulge ``K`` (rad, ``(..., 3)``) of a sextic with sixth-order coefficients ``a6``
    (rad/s^6) over ``T_s`` (s): ``-a6 T^6``, the path's shape whatever its timing."""
    K: FloatArray = -np.asarray(a6, dtype=np.float64) * T_s**6
    return K


_VOLUME_COLUMNS = (
    oneshot.CONSTRAINT_NAMES.index("volume_min"),
    oneshot.CONSTRAINT_NAMES.index("volume_max"),
)


_ENTRY_COLUMNS = (
    oneshot.CONSTRAINT_NAMES.index("theta_p_min"),
    oneshot.CONSTRAINT_NAMES.index("theta_p_max"),
)

#: The theta_p range of a joined dig (rad): it starts in the material at the exit of the dig
#: before it and has no entry, so its first direction is free (up a wall to the top edge, say).
JOINED_THETA_P_RAD = (-math.pi, math.pi)


def _total_without_volume(row: FloatArray, joined: bool = False) -> float:
    """Total violation of a verifier row without the one-shot volume window (and, for a
    ``joined`` dig, without the theta_p bounds of an entry: :data:`JOINED_THETA_P_RAD`)."""
    v = row[0 : len(oneshot.CONSTRAINT_NAMES)].copy()
    v[list(_VOLUME_COLUMNS)] = 0.0
    if joined:
        v[list(_ENTRY_COLUMNS)] = 0.0
    return float(np.sum(np.maximum(v, 0.0)))


def _largest_scale_below(f: FloatArray, limit: float, G: FloatArray) -> FloatArray:
    """Per row of ``f`` ``(N, len(G))`` (a value growing with the bulge scale, sampled at the
    scales ``G``): the largest scale at which it is still ``<= limit``, linear between the
    samples; ``G[-1]`` where no sample exceeds it, and 0 where even ``G[0]`` does."""
    above = f > limit
    k = np.where(above.any(axis=1), np.argmax(above, axis=1), G.shape[0])
    kk = np.clip(k, 1, G.shape[0] - 1)
    r = np.arange(f.shape[0])
    f0, f1 = f[r, kk - 1], f[r, kk]
    frac = np.clip((limit - f0) / np.where(f1 > f0, f1 - f0, 1.0), 0.0, 1.0)
    c = G[kk - 1] + frac * (G[kk] - G[kk - 1])
    c = np.where(k == G.shape[0], G[-1], c)
    return np.where(k == 0, 0.0, c)


def _depth_below(
    grid: FloatArray, surface: FloatArray, x: FloatArray, y: FloatArray, cap_m: ArrayLike
) -> FloatArray:
    """How far points are inside the material under a height field (m, 0 outside it), up to
    ``cap_m``: ``min(depth, cap_m)``.

    The depth of a point ``(x, y)`` below ``surface`` (on the uniform ``grid``, linear between)
    is its distance to the nearest point above the surface, not the height of the surface over
    it: beside a steep face the two differ by the face's height (a tip 2 mm into the face of
    an 8 cm step is 2 mm deep, not 80 mm). The nearest point is sought in the grid columns
    within reach (the vertical depth, at most the cap), so the result is at most half a grid
    step too deep. Shapes: ``x``, ``y`` and the result alike; ``cap_m`` broadcasts to them.
    """
    h = float(grid[1] - grid[0])
    n = grid.shape[0]
    u = np.clip((x - grid[0]) / h, 0.0, n - 1.000001)
    i = u.astype(np.int64)
    w = u - i
    vertical = surface[i] * (1.0 - w) + surface[i + 1] * w - y
    out = np.zeros(np.shape(x))
    inside = vertical > 0.0
    if not np.any(inside):
        return out
    reach = np.minimum(vertical, np.broadcast_to(cap_m, np.shape(x)))[inside]
    px, py = x[inside], y[inside]
    col = np.rint((px - grid[0]) / h).astype(np.int64)
    depth = reach.copy()
    # Points in classes of reach (16 columns each): one window as wide as the deepest point's
    # costs ~10x more where a few points are deep (a bucket's back in a wall).
    cls = np.ceil(reach / (16.0 * h)).astype(np.int64)
    for j in np.unique(cls).tolist():
        m = cls == j
        k = 16 * j
        cols = np.clip(col[m, None] + np.arange(-k, k + 1), 0, n - 1)
        dx = grid[cols] - px[m, None]
        dy = np.maximum(surface[cols] - py[m, None], 0.0)
        depth[m] = np.minimum(np.sqrt(np.min(dx * dx + dy * dy, axis=1)), reach[m])
    out[inside] = depth
    return out


def _max_table(values: FloatArray) -> FloatArray:
    """A sparse table of ``values`` ``(n,)``: row j holds the maxima of the runs of 2^j
    starting at each index (the last 2^j - 1 entries of a row, where no full run starts, are
    not meaningful and :func:`_range_max` does not read them)."""
    n = values.shape[0]
    levels = 1
    while 1 << levels <= n:
        levels += 1
    table = np.empty((levels, n))
    table[0] = values
    for k in range(1, levels):
        j = 1 << (k - 1)
        prev, row = table[k - 1], table[k]
        row[-j:] = prev[-j:]
        np.maximum(prev[:-j], prev[j:], out=row[:-j])
    return table


def _range_max(table: FloatArray, i0: NDArray[np.int64], i1: NDArray[np.int64]) -> FloatArray:
    """Maxima of ``values[i0 : i1 + 1]`` (index arrays alike, ``i0 <= i1``) from its
    :func:`_max_table`."""
    level = np.floor(np.log2(i1 - i0 + 1)).astype(np.int64)
    top: FloatArray = np.maximum(table[level, i0], table[level, i1 - (1 << level) + 1])
    return top


#: A profile pass: its dig type, its line (2 points, work-site frame) and the attitude table of
#: its two ends (deg).
_Pass = tuple[DigType, FloatArray, tuple[tuple[float, ...], tuple[float, ...]]]


def runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """The runs of True in a 1-D mask: ``(start, stop)`` index pairs (stop exclusive), in
    order."""
    on = np.zeros(mask.shape[0] + 2, dtype=np.int8)
    on[1:-1] = mask
    change = np.diff(on)
    starts, stops = np.flatnonzero(change == 1), np.flatnonzero(change == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]
