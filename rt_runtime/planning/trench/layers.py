"""Layers and columns: the layers the design is cut in (chosen so that each splits into the
fewest full buckets), columns along a layer's floor, far to near, and the bottom's straight
columns (the walls' digs are in ``walls``)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray

from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.trench.candidates import _FILL_MARGIN, _ROUGH_SPARE, Candidate
from rt_runtime.planning.trench.fit import _PASS_OFFSETS_M
from rt_runtime.planning.trench.geometry import GRID_STEP_M, FloatArray, runs
from rt_runtime.planning.trench.plan import PlannedDig
from rt_runtime.planning.trench.rough import RoughMixin
from rt_runtime.planning.trench.state import Stage

#: Range of the profile layer's thickness (scale model, m): thin enough for the boom's torque
#: through a full cut along the bottom (a 0.25 m column verifies up to ~0.11 m), thick
#: enough that a column of it no longer than _COLUMN_MAX_M fills the bucket.
_LAYER_RANGE_M = (0.045, 0.10)

#: Thickest material a dig along the floor cuts through in one pass (scale model, m; a
#: 0.25 m column verifies up to ~0.11 m).
_CUT_MAX_M = 0.105

#: Thickest layer above the bottom one (scale model, m): what the layer's columns cut, with
#: room for what the network's digs leave above the layer's floor.
_UPPER_LAYER_MAX_M = 0.09

#: How far short of the design's bottom corners the walls' digs stop (scale model, m).
_CORNER_GAP_M = 0.005

#: How far beyond the face of the material a bottom column enters (scale model, m).
_FACE_GAP_M = 0.004


#: Material within this of the design's floor is not counted for a column (scale model, m).
_COLUMN_SKIN_M = 0.003

#: A column starts where the material above the design's floor is thicker than this (scale
#: model, m).
_COLUMN_EDGE_M = 0.012

#: Longest profile dig (scale model, m).
_COLUMN_MAX_M = 0.45

#: Longest column of a layer above the bottom one (scale model, m): its floor is not the
#: design's (the layer below takes what a longer fit leaves), and a layer 3-4 cm thick fills
#: the bucket only over about half a metre.
_UPPER_COLUMN_MAX_M = 0.55

#: A bottom layer at most this thick (scale model, m) fills the bucket only over more than
#: :data:`_COLUMN_MAX_M`: its columns may be :data:`_THIN_COLUMN_MAX_M` long (a 3-5 cm
#: trench's section of half a metre or more went in two under-filled halves).
_THIN_BOTTOM_M = 0.05
_THIN_COLUMN_MAX_M = 0.75

#: How far below an upper layer's floor a column may go to take a rest of the layer that
#: fills no bucket with the top of the layer below (scale model, m; tried in this order).
_DEEPEN_M = (0.005, 0.01, 0.015, 0.02, 0.025, 0.03)

#: How far beyond the run where the layer below would be too thick a pass that must take
#: the rest of an upper layer reaches (scale model, m).
_MUST_PAD_M = 0.05

#: Longest piece of a rest taken under-filled (scale model, m).
_PARTIAL_MAX_M = 0.25
#: Fraction of V_max a column aims at.
_FILL_AIM = 0.93

#: Shorter full columns tried where the whole rest of a layer in one bucket does not plan
#: (multiples of V_min with the fill margin, in this order; :meth:`_column_ends` with
#: ``shorter``), in upper layers and thin bottom layers: such a rest was split into
#: under-filled passes. Not in a thick bottom layer, where the rest such a column leaves is
#: next to the machine and the near wall, and finishing passes did not take it (one task of
#: seed 7 ended at 5 %).
_SHORT_COLUMN_FILLS = (1.3, 1.15, 1.05)

#: How far beyond a later section's far edge its columns may take what the section before
#: left at its near face (scale model, m): a rest under the bucket's capacity that the
#: section before could not lift out of beside the next section's standing material.
_CARRY_M = 0.10

#: End attitudes of a layer's columns (deg; the table's first and last of each end).
_LAYER_ATTITUDES_DEG = {
    DigType.DOWNWARD: ((-60.0, -120.0), (-110.0, -190.0)),
    DigType.BACKWARD: ((-100.0, -140.0), (-140.0, -200.0)),
}

#: End attitudes of bottom columns (deg; the table's first and last of each end).
_COLUMN_ATTITUDES_DEG = {DigType.BACKWARD: ((-110.0, -135.0), (-150.0, -175.0))}


class LayersMixin(RoughMixin):
    """A session's layers, columns and walls' digs (see the module)."""

    def _downward_wall(self, beta_rad: float) -> bool:
        """Whether a downward dig enters a wall of angle ``beta_rad`` (its theta_p range, the
        lower end with 0.02 rad to spare): the walls' digs and the columns that reach a wall
        are downward there, backward on a shallower wall."""
        lo_d, hi_d = oneshot.theta_p_range(self.planning, int(DigType.DOWNWARD))
        return float(lo_d) + 0.02 <= beta_rad <= float(hi_d)

    def _digs_for(self, area: float, spare: float) -> float:
        """Full buckets an area takes (``spare``: the fraction of the fill band's ends kept
        free, for what the digs' shapes miss); inf when no whole number of them fits."""
        lo_a, hi_a = self._fill_band()
        n = max(1, math.ceil(area / (hi_a * (1.0 - spare))))
        return float(n) if area / n >= lo_a * (1.0 + spare) else math.inf

    def _advance(self) -> None:
        """The next stage (:class:`Stage`): after a layer's columns the next layer's network
        digs, after the last the bottom layer's far wall."""
        self._wall_piece = 0
        if self.stage is Stage.LAYER and self.layer + 1 < len(self.layer_floors):
            self.layer += 1
            self.stage = Stage.ROUGH
            self.phase = DigType.DOWNWARD
        else:
            if self.stage is Stage.LAYER:
                self.layer = len(self.layer_floors)
            self.stage = Stage(self.stage + 1)
        self._set_layer()

    def _choose_layers(self) -> tuple[float, ...]:
        """The floors of the layers above the bottom one (work-site y, top first).

        The bottom layer is cut by straight columns along the bottom, the layers above by
        the network's digs and columns along their floors; no layer is thicker than the
        boom's torque allows through a full cut (:data:`_LAYER_RANGE_M`,
        :data:`_UPPER_LAYER_MAX_M`). Among the bottom layer's thicknesses on a 2.5 mm grid
        (scaled; the whole depth when that is thin enough), the one whose layers split into
        the fewest full buckets (each layer's area in as few as the fill band allows with a
        spare at its ends; walls aside) is taken, ties to the thicker bottom layer.
        """
        s = self.planner.scale
        t = self.task
        lo, hi = (v * s for v in _LAYER_RANGE_M)
        up_max = _UPPER_LAYER_MAX_M * s
        options = [float(v) for v in np.arange(lo, hi + 1e-9, 0.0025 * s) if v < t.depth_m]
        if t.depth_m <= hi:
            options.append(t.depth_m)
        best: tuple[float, float, tuple[float, ...]] = (math.inf, 0.0, ())
        for bottom_layer in options or [t.depth_m]:
            rest = t.depth_m - bottom_layer
            n_up = math.ceil(rest / up_max - 1e-9) if rest > 1e-9 else 0
            depths = [rest * k / n_up for k in range(1, n_up + 1)] if n_up else []
            digs = 0.0
            top = 0.0
            for d in depths:
                digs += self._digs_for(self._area_above(d) - self._area_above(top), _ROUGH_SPARE)
                top = d
            b_lo, b_hi = self._bottom_span()
            cols = max(b_hi - b_lo, 0.0) * (bottom_layer - _COLUMN_SKIN_M * s)
            n_cols = self._digs_for(cols, _FILL_MARGIN)
            if cols / max(n_cols, 1.0) > bottom_layer * _COLUMN_MAX_M * s:
                n_cols = math.inf  # a column longer than a straight dig follows
            key = (digs + n_cols, -bottom_layer, tuple(self.ground_y - d for d in depths))
            if key[:2] < best[:2]:
                best = key
        if not math.isfinite(best[0]):
            # No split fills every bucket: layers of the thickest the torque allows.
            rest = max(t.depth_m - hi, 0.0)
            n_up = math.ceil(rest / up_max - 1e-9) if rest > 1e-9 else 0
            return tuple(self.ground_y - rest * k / n_up for k in range(1, n_up + 1))
        return best[2]

    def _set_layer(self) -> None:
        """The current layer's design (the design above its floor) as the screening and the
        columns take it: ``layer_y``, its floor on the grid, half-planes, edges and polygon
        (the bottom layer's are the design's)."""
        upper = self.layer < len(self.layer_floors)
        y = self.layer_floors[self.layer] if upper else self.bottom_y
        self.layer_y = y
        self._layer_floor, self._layer_walls = self._floor_at(y)
        top = shapely.box(self.x_lo, y, self.x_hi, self.top_y)
        part = self.design.intersection(top)
        self.layer_design: Any = part if not part.is_empty else self.design
        ring = np.asarray(shapely.get_exterior_ring(shapely.normalize(self.layer_design)).coords)
        edge = ring[1:] - ring[:-1]
        self._layer_edges = np.column_stack([ring[:-1], edge, np.sum(edge * edge, axis=1)])

    def _floor_at(self, y: float) -> tuple[FloatArray, FloatArray]:
        """A layer's floor at level ``y`` (work-site m): the design's outline raised to it on
        the grid, and the outline's half-planes with the floor's row at it."""
        walls = self._walls.copy()
        walls[2, 2] = -y
        return np.maximum(self.design_floor, min(y, self.ground_y)), walls

    def _reach_hi(self, surface: FloatArray | None = None) -> float:
        """The far end (work-site x) of what the current section's columns take: the
        section's far edge; in a later section just beyond it (a column enters the near face
        of the section before from the dug ground beyond it, :data:`_FACE_GAP_M`), and where
        the section before left material thicker than :data:`_COLUMN_EDGE_M` within
        :data:`_CARRY_M` (scaled) of that face, beyond the first such run (at most that far
        beyond the edge). ``surface``: the material's surface on the grid (default the
        current one)."""
        surface = self.surface if surface is None else surface
        hi = self.section_hi
        if self.section == 0:
            return hi
        s = self.planner.scale
        x = self.grid
        gap = _FACE_GAP_M * s + 3.0 * GRID_STEP_M
        i0 = int(np.searchsorted(x, hi - 1e-9))
        i_cap = int(np.searchsorted(x, hi + _CARRY_M * s + 1e-9))
        thick = surface[i0:i_cap] - self.design_floor[i0:i_cap] > _COLUMN_EDGE_M * s
        if not thick.any():
            return hi + gap
        first = int(np.argmax(thick))
        rest = thick[first:]
        n = first + (rest.size if rest.all() else int(np.argmin(rest)))
        return min(max(float(x[i0 + n - 1]) + gap, hi + gap), hi + _CARRY_M * s)

    def _bottom_span(self) -> tuple[float, float]:
        """Where the bottom's columns run within the section (x range, work-site frame; a
        later section's reaching to :meth:`_reach_hi`): the design's flat bottom, and into
        each corner as far as the wall's dig stops short of it (:data:`_CORNER_GAP_M` along
        the wall), so that no sliver stands between the two (a 2.5 mm wide, 9 cm tall one
        beside each corner of D otherwise)."""
        t = self.task
        gap = _CORNER_GAP_M * self.planner.scale
        xf = t.start_x_m
        bx = xf - t.depth_m / math.tan(t.beta1_rad) + gap * math.cos(t.beta1_rad)
        cx = xf - t.length_m + t.depth_m / math.tan(t.beta2_rad) - gap * math.cos(t.beta2_rad)
        return max(cx, self.section_lo), min(bx, self._reach_hi())

    def _column_ends(
        self,
        floor: FloatArray,
        x_lo: float,
        x_hi: float,
        partial: bool = False,
        surface: FloatArray | None = None,
        shorter: bool = False,
        bucket: float = 0.0,
    ) -> list[float]:
        """The next column of the material above ``floor`` (on the grid) within ``[x_lo,
        x_hi]``: its start (just beyond the far edge of that material, at most ``x_hi``) and
        where it may end (x, work-site frame), best first. The material (less a skin) from the
        far edge towards the machine is split into as few full buckets as the fill band
        allows, equal in area, and the column is the far one; what no bucket would fill is
        taken with the last. Empty when what is left cannot fill one bucket, unless
        ``partial``: then the rest in as few columns as the bucket and the longest dig allow
        (under-filled: finishing passes). With ``shorter`` (and not ``partial``), where the
        whole rest fits one bucket: shorter full columns instead, the far part of the rest at
        each of :data:`_SHORT_COLUMN_FILLS` times V_min, the rest left for a pass (empty
        otherwise). ``surface``: the material's surface on the grid (default the current
        one). ``bucket``: material already in the bucket (m^2 of cross-section: a column
        joined to the dig before it), which the fill band's ends count."""
        surface = self.surface if surface is None else surface
        lo_a, hi_a = (v - bucket for v in self._fill_band())
        s = self.planner.scale
        x = self.grid
        t = np.clip(surface - floor - _COLUMN_SKIN_M * s, 0.0, None)
        t[(x < x_lo - 1e-9) | (x > x_hi + 1e-9)] = 0.0
        # The far edge of the material a dig along the floor leaves (its fit and offset leave
        # a few mm on the outline: the finishing passes' part), thick over a few mm (the grid
        # point beside a wall's foot can stand alone).
        thick = np.convolve(t > _COLUMN_EDGE_M * s, np.ones(5), mode="same") >= 5
        # Runs too small to count (a quarter of V_min) are left to the walls' digs and the
        # finishing passes: a column that starts at one would carry little else. Not so for
        # the rest taken under-filled: that is taken because it must be (too thick to leave).
        too_thick = self._too_thick_below(surface) if partial else None
        for i0, i1 in runs(thick):
            small = float(np.sum(t[i0:i1])) * GRID_STEP_M < 0.25 * lo_a
            if small and not (too_thick is not None and np.any(too_thick[i0:i1])):
                thick[i0:i1] = False
        idx = np.flatnonzero(thick)
        if not idx.size:
            return []
        i_lo = int(np.searchsorted(x, x_lo - 1e-9))
        # The column enters just beyond the face (on dug ground, so that it enters from the
        # air), at most at the span's far end.
        i_hi = int(np.searchsorted(x, x_hi + 1e-9)) - 1
        i_start = min(int(idx[-1]) + 2 + int(_FACE_GAP_M * s / GRID_STEP_M), i_hi)
        cum = np.cumsum(t[i_lo : i_start + 1][::-1]) * GRID_STEP_M  # from the far edge
        total = float(cum[-1])
        w_max = round(self._column_max() / GRID_STEP_M)
        if partial:
            # The rest in as few pieces as the bucket and the longest dig allow; where such a
            # piece fails (a long fit along a corner, a thick rest), shorter ones.
            ends_p: list[float] = []
            for w in (w_max, round(_PARTIAL_MAX_M * s / GRID_STEP_M)):
                n = max(math.ceil(total / (hi_a * _FILL_AIM)), math.ceil(cum.shape[0] / w), 1)
                k = min(int(np.searchsorted(cum, total / n)), cum.shape[0] - 1, w)
                for kk in (k, max(k // 2, 1)):
                    x_end = float(x[i_start - kk])
                    if all(abs(x_end - e) > 2.0 * GRID_STEP_M for e in ends_p):
                        ends_p.append(x_end)
            return [float(x[i_start]), *ends_p]
        if total < lo_a * (1.0 + _FILL_MARGIN):
            return []
        n = max(1, math.ceil(total / (hi_a * _FILL_AIM)))
        if n > 1 and total / n < lo_a:
            n -= 1  # no even split fills every bucket: this one full, the rest left over
        target = total / n
        ends: list[float] = []
        last = min(cum.shape[0] - 1, w_max)
        whole = n == 1 and total <= hi_a
        if whole:
            ends.append(float(x[i_start - last]))  # the whole rest in one bucket
        for f in (1.0, 1.06, 0.94, 1.12, 0.88):
            area = min(target * f, hi_a * (1.0 - _FILL_MARGIN))
            if area < lo_a:
                continue
            k = min(int(np.searchsorted(cum, area)), last)
            # What would be left behind this column that no bucket fills goes with it.
            if float(cum[-1] - cum[k]) < lo_a and total <= hi_a:
                k = last
            x_end = float(x[i_start - k])
            if all(abs(x_end - e) > 2.0 * GRID_STEP_M for e in ends):
                ends.append(x_end)
        if shorter:
            short: list[float] = []
            for f in _SHORT_COLUMN_FILLS if whole else ():
                area = lo_a * (1.0 + _FILL_MARGIN) * f
                if area >= total:
                    continue
                k = min(int(np.searchsorted(cum, area)), last)
                x_end = float(x[i_start - k])
                if all(abs(x_end - e) > 2.0 * GRID_STEP_M for e in [*ends, *short]):
                    short.append(x_end)
            return [float(x[i_start]), *short] if short else []
        return [float(x[i_start]), *ends]

    def _thin_bottom(self) -> bool:
        """Whether the current layer is the bottom one and no thicker than
        :data:`_THIN_BOTTOM_M` (scaled)."""
        if self.layer < len(self.layer_floors):
            return False
        top = self.layer_floors[-1] if self.layer_floors else self.ground_y
        return top - self.bottom_y <= _THIN_BOTTOM_M * self.planner.scale + 1e-12

    def _column_max(self) -> float:
        """The longest column of the current layer (m): :data:`_UPPER_COLUMN_MAX_M` above the
        bottom layer, :data:`_THIN_COLUMN_MAX_M` in a bottom layer no thicker than
        :data:`_THIN_BOTTOM_M`, else :data:`_COLUMN_MAX_M` (all scaled)."""
        s = self.planner.scale
        if self.layer < len(self.layer_floors):
            return _UPPER_COLUMN_MAX_M * s
        if self._thin_bottom():
            return _THIN_COLUMN_MAX_M * s
        return _COLUMN_MAX_M * s

    def _next_layer_column(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The next column of the current layer (above the bottom one): a dig along the
        layer's floor, and down the far wall or up the near wall where the column reaches
        them (:meth:`_fit_profile` on the layer's outline), carrying a full bucket; after
        the layer's far-wall piece (``walls``), first the column that continues its bucket.
        Where what is left fills none (a quarter of V_min or more), a full column along the
        floor lowered by :data:`_DEEPEN_M` (scaled, the least first: the rest and the top of
        the layer below); where there is none and the rest is too much to leave to the next
        layer (:meth:`_layer_must_be_taken`), the rest under-filled, else nothing (the next
        layer takes it). A rest over a wall's slope is never too much to leave, and a later
        section's layers under it found it too thick to cut beneath: one such section ended
        with 22 % of the design left. A full column of an upper layer that would leave such
        a rest behind it gives way to the first full column along a lowered floor whose fit
        leaves none. None when the layer is done."""
        floor = self._layer_floor
        y_floor = self.layer_y
        walls = self._layer_walls
        upper = self.layer < len(self.layer_floors)
        if self._wall_piece == 2:
            # The layer's far-wall pass (``walls``) was planned for this column to continue.
            self._wall_piece = 1
            dig = self._continuing_layer_column(remaining, t0)
            if dig is not None:
                return dig
        dig = self._layer_column(floor, y_floor, walls, False, remaining, t0)
        planned = self._planned_region
        if dig is not None and not (upper and planned and self._leaves_rest(floor, planned[1])):
            return dig
        must = True
        if dig is None and upper:
            rest = self._column_ends(floor, self.section_lo, self._reach_hi(), True)
            if not rest:
                return None
            must = self._layer_must_be_taken()
        if upper:

            def leaves_none(c: Candidate) -> bool:
                return c.envelope is None or not self._leaves_rest(floor, c.envelope)

            keep = None if dig is None else leaves_none
            s = self.planner.scale
            for deeper in _DEEPEN_M:
                y = y_floor - deeper * s
                floor_y, lowered = self._floor_at(y)
                other = self._layer_column(floor_y, y, lowered, False, remaining, t0, keep)
                if other is not None:
                    return other
            if dig is not None:
                self._planned_region = planned  # record() reuses the dig's region
                return dig
            if not must:
                return None
        return self._layer_column(floor, y_floor, walls, True, remaining, t0)

    def _continuing_layer_column(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The current layer's next full column, continuing the last dig's bucket: joined at
        its exit where that lies at the column's start, else carried to the column; its ends
        chosen for the fill with the bucket's content. None where the last dig may not be
        continued or no such column plans."""
        if self.joinable is None:
            return None
        floor = self._layer_floor
        ends = self._column_ends(floor, self.section_lo, self._reach_hi())
        if not ends:
            return None
        a = np.array([ends[0], float(np.interp(ends[0], self.grid, floor))])
        at_exit = self._join_at(a) is not None
        bucket = self.joinable[1] / self.width_m

        def continues(c: Candidate) -> bool:
            return c.joined and c.carried is not at_exit

        return self._layer_column(
            floor, self.layer_y, self._layer_walls, False, remaining, t0, continues, bucket
        )

    def _leaves_rest(self, floor: FloatArray, envelope: FloatArray) -> bool:
        """Whether a dig reaching down to ``envelope`` (on the grid) leaves above ``floor``
        a rest of the current layer that fills no bucket but must be taken
        (:meth:`_layer_must_be_taken`)."""
        after = np.minimum(self.surface, envelope)
        reach = self._reach_hi(after)
        if self._column_ends(floor, self.section_lo, reach, False, after):
            return False
        rest = self._column_ends(floor, self.section_lo, reach, True, after)
        return bool(rest) and self._layer_must_be_taken(after)

    def _layer_column(
        self,
        floor: FloatArray,
        y_floor: float,
        walls: FloatArray,
        partial: bool,
        remaining: Any,
        t0: float,
        keep: Callable[[Candidate], bool] | None = None,
        bucket: float = 0.0,
        span: tuple[float, float] | None = None,
    ) -> PlannedDig | None:
        """A column of the material above ``floor`` (on the grid; ``y_floor`` its level
        and ``walls`` the outline's half-planes with the floor's row at it): a full bucket,
        or with ``partial`` the rest under-filled where it must be taken
        (:meth:`_layer_must_be_taken`); None where none plans. Where an upper layer's whole
        rest does not plan as one full column, shorter full ones (:meth:`_column_ends` with
        ``shorter``). ``keep``: where given, only fits it keeps are planned (and no shorter
        columns are tried). ``bucket``: material already in the bucket (m^2 of
        cross-section, :meth:`_column_ends`). ``span``: the material within this x range
        (work-site m) alone; by default the section's, and for a rest that must be taken a
        pass along the whole rest where it leaves nothing too thick below, else one over
        the far run of what is too thick, :data:`_MUST_PAD_M` (scaled) beyond it each side:
        a long pass that grazes that run left most of it, and the same pass was taken again
        and again."""
        if span is None:
            lo, hi = self.section_lo, self._reach_hi()
            thick = runs(self._too_thick_below()) if partial else []
            if thick:

                def clears(c: Candidate) -> bool:
                    if keep is not None and not keep(c):
                        return False
                    env = c.envelope
                    after = self.surface if env is None else np.minimum(self.surface, env)
                    return not bool(np.any(self._too_thick_below(after)))

                args = (floor, y_floor, walls, partial, remaining, t0)
                dig = self._layer_column(*args, clears, bucket, (lo, hi))
                if dig is not None:
                    return dig
                i0, i1 = thick[-1]
                pad = _MUST_PAD_M * self.planner.scale
                lo = max(lo, float(self.grid[i0]) - pad)
                hi = min(hi, float(self.grid[i1 - 1]) + pad)
            span = (lo, hi)
        steep = self._downward_wall(self.task.beta1_rad)
        rise = 0.005 * self.planner.scale
        ends = self._column_ends(floor, span[0], span[1], partial, bucket=bucket)
        if not ends:
            return None
        if partial and not self._layer_must_be_taken():
            return None
        x_start = ends[0]
        a = np.array([x_start, float(np.interp(x_start, self.grid, floor))])
        on_wall = a[1] > y_floor + rise
        kind = DigType.DOWNWARD if on_wall and steep else DigType.BACKWARD
        if not on_wall:
            a[1] += 0.002  # enters descending (theta_p >= 0)

        def tries() -> Iterator[tuple[float, tuple[float, ...]]]:
            """The column's ends with their fits' fixed shifts; after the full ends of an
            upper layer's whole rest, shorter full columns (adaptive fits only: with the
            fixed shifts a fit that finds nothing costs ~10 ms)."""
            for x_end in ends[1:]:
                yield x_end, _PASS_OFFSETS_M
            if not partial and keep is None and self.layer < len(self.layer_floors):
                short = self._column_ends(floor, self.section_lo, self._reach_hi(), shorter=True)
                for x_end in short[1:]:
                    yield x_end, ()

        for x_end, offsets in tries():
            b = np.array([x_end, float(np.interp(x_end, self.grid, floor))])
            rows = [0] if on_wall else []
            rows.append(2)
            if b[1] > y_floor + rise:
                rows.append(1)
            found = self._fit_profile(kind, a, b, walls[rows], _LAYER_ATTITUDES_DEG[kind], offsets)
            if found is not None and keep is not None and not keep(found):
                continue
            dig = self._plan_column(found, partial, remaining, t0)
            if dig is not None:
                return dig
        return None

    def _too_thick_below(self, surface: FloatArray | None = None) -> NDArray[np.bool_]:
        """Where, on the grid, the material left above the current layer's floor would make
        the layer below thicker than a dig cuts through (:data:`_CUT_MAX_M`, scaled); nowhere
        in the bottom layer (nothing below takes it). Above the walls' slopes, nowhere: what
        the layers leave there is the walls' digs' (top edge to foot, in pieces and halves
        where it is thick, ``walls``), not the columns' of the layers below. ``surface``: the
        material's surface on the grid (default the current one)."""
        surface = self.surface if surface is None else surface
        x = self.grid
        if self.layer >= len(self.layer_floors):
            return np.zeros(x.shape[0], dtype=bool)
        nxt = self.layer + 1
        below = self.layer_floors[nxt] if nxt < len(self.layer_floors) else self.bottom_y
        floor = np.maximum(self.design_floor, below)
        inside = (x >= self.section_lo) & (x <= self.section_hi)
        inside &= self.design_floor <= self.bottom_y + 1e-9
        mask: NDArray[np.bool_] = inside & (surface - floor > _CUT_MAX_M * self.planner.scale)
        return mask

    def _layer_must_be_taken(self, surface: FloatArray | None = None) -> bool:
        """Whether what is left above the current layer's floor (``surface``, default the
        current one) must be taken under-filled: left to the layer below, it would make that
        layer thicker anywhere than the boom's torque cuts through (:data:`_CUT_MAX_M`,
        scaled)."""
        if self.layer >= len(self.layer_floors):
            return True  # the bottom layer: nothing below takes it
        return bool(np.any(self._too_thick_below(surface)))

    def _next_column(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The next bottom column (:meth:`_column_ends`): a straight backward dig along the
        bottom over its span (:meth:`_fit_pass`), carrying a full bucket of real material;
        where what is left fills none, the rest under-filled (finishing passes). None when
        nothing thicker than the skin is left on the bottom."""
        x_lo, x_hi = self._bottom_span()
        # Full columns; in a thin bottom layer then shorter full ones where the whole rest does
        # not plan (adaptive fits only, as in :meth:`_layer_column`); then the rest in passes.
        tries = [(False, False), (False, True)] if self._thin_bottom() else [(False, False)]
        # Where the column may start at the last dig's exit (joined), first the full columns
        # that fill the bucket it holds: the first two sizes (each is fitted joined and
        # alone), taken only joined. A light bucket (below the fill band) counts where the
        # column is sized: the rest may fill it with what it holds, and alone would not.
        floor = self.design_floor
        first: list[float] = []
        if self.joinable is not None:
            bucket = self.joinable[1] / self.width_m
            light = bucket < self._fill_band()[0]
            first = self._column_ends(floor, x_lo, x_hi, bucket=bucket if light else 0.0)
        if first and self._join_at(np.array([first[0], self.bottom_y + 0.002])) is not None:
            ends = first if light else self._column_ends(floor, x_lo, x_hi, bucket=bucket)
            dig = self._bottom_column(ends[:3], False, False, remaining, t0, joined_only=True)
            if dig is not None:
                return dig
        for partial, shorter in [*tries, (True, False)]:
            ends = self._column_ends(self.design_floor, x_lo, x_hi, partial, shorter=shorter)
            dig = self._bottom_column(ends, partial, shorter, remaining, t0)
            if dig is not None:
                return dig
        # The boom's torque refuses a column through the bottom layer's whole thickness
        # (deep and near the machine it needs more than along the rest of the bottom): the
        # material above the layer's mid-height first, as a column along that height.
        dig = self._next_mid_column(x_lo, x_hi, remaining, t0)
        if dig is not None:
            return dig
        # No straight column enters (a steep far wall whose dig could not open the face, or
        # a column whose moves would plough): one down the wall and along the bottom.
        return self._next_layer_column(remaining, t0)

    def _bottom_column(
        self,
        ends: list[float],
        partial: bool,
        shorter: bool,
        remaining: Any,
        t0: float,
        joined_only: bool = False,
    ) -> PlannedDig | None:
        """The first of the bottom columns ``ends`` (:meth:`_column_ends`: the start, then
        the ends, best first) that plans (:meth:`_plan_column`); ``shorter``: adaptive fits
        only; ``joined_only``: only a column that continues the last dig's bucket (joined at
        its exit, or the bucket carried to it). None where none does."""
        if not ends:
            return None
        atts = _COLUMN_ATTITUDES_DEG[DigType.BACKWARD]
        a = (ends[0], self.bottom_y + 0.002)  # enters descending (theta_p >= 0)
        offsets = () if shorter else None
        for x_end in ends[1:]:
            line = np.array([a, (x_end, self.bottom_y)])
            found = self._fit_pass(DigType.BACKWARD, line, atts, offsets)
            if joined_only and (found is None or not found.joined):
                continue
            dig = self._plan_column(found, partial, remaining, t0)
            if dig is not None:
                return dig
        return None

    def _next_mid_column(
        self, x_lo: float, x_hi: float, remaining: Any, t0: float
    ) -> PlannedDig | None:
        """A straight column along the bottom layer's mid-height (:meth:`_column_ends` on
        the design floor raised to it), a full bucket or else under-filled; None where the
        material on the bottom is too thin to halve (twice :data:`_COLUMN_EDGE_M`, scaled)
        or no such column plans."""
        s = self.planner.scale
        t = self.task
        x = self.grid
        inside = (x >= x_lo - 1e-9) & (x <= x_hi + 1e-9)
        thick = np.where(inside, self.surface - self.design_floor, 0.0)
        top = float(np.max(thick)) if thick.size else 0.0
        if top < 2.0 * _COLUMN_EDGE_M * s:
            return None
        y_mid = self.bottom_y + 0.5 * top
        g = self.ground_y
        far = min(t.start_x_m - (g - y_mid) / math.tan(t.beta1_rad), self._reach_hi())
        near = max(t.start_x_m - t.length_m + (g - y_mid) / math.tan(t.beta2_rad), self.section_lo)
        floor = np.maximum(self.design_floor, y_mid)
        atts = _COLUMN_ATTITUDES_DEG[DigType.BACKWARD]
        for partial in (False, True):
            ends = self._column_ends(floor, near, far, partial)
            if not ends:
                continue
            a = (ends[0], y_mid + 0.002)  # enters descending (theta_p >= 0)
            for x_end in ends[1:]:
                found = self._fit_pass(DigType.BACKWARD, np.array([a, (x_end, y_mid)]), atts)
                dig = self._plan_column(found, partial, remaining, t0)
                if dig is not None:
                    return dig
        return None

    def _plan_column(
        self, found: Candidate | None, partial: bool, remaining: Any, t0: float
    ) -> PlannedDig | None:
        """A fitted column planned: a full dig, or with ``partial`` a finishing pass."""
        if found is None:
            return None
        dig = self._first_plannable(
            [dataclasses.replace(found, may_underfill=partial)], remaining, t0
        )
        self._count_pass(dig)
        return dig
