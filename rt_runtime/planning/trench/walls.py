"""The walls' digs: each wall's line from its top edge to the bottom, in pieces, a full dig
where it fills the bucket, else a finishing pass; a piece too thick across for one pass taken
in two."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.trench.candidates import Candidate
from rt_runtime.planning.trench.fit import _JOIN_REACH_M
from rt_runtime.planning.trench.geometry import FloatArray
from rt_runtime.planning.trench.layers import (
    _COLUMN_EDGE_M,
    _COLUMN_MAX_M,
    _CORNER_GAP_M,
    LayersMixin,
)
from rt_runtime.planning.trench.plan import PlannedDig

#: The near corner's joined backward dig (:meth:`WallsMixin._near_corner`): how far along the
#: bottom from the near wall's foot the exit of the dig it continues may lie (scale model, m),
#: and its attitude tables (deg; it curls the bucket as it climbs the wall).
_CORNER_RUN_M = 0.10
_NEAR_CORNER_ATTS = ((-110.0, -150.0), (-160.0, -200.0))

#: Least far-wall angle (deg) at which an upper layer's columns begin with the wall's piece
#: within the layer (:meth:`WallsMixin._layer_far_wall`): on a shallower wall the layer's
#: downward column from the wall follows it, and the piece first changed a few plans of the
#: random suites with no pass saved (seeds 7, 11, 3, 23: four of 800, 41-69 deg).
_LAYER_WALL_MIN_DEG = 70.0

#: End attitudes of wall digs (deg; the table's first and last of each end).
_WALL_ATTITUDES_DEG = {
    DigType.DOWNWARD: ((-80.0, -100.0), (-95.0, -130.0)),
    DigType.BACKWARD: ((-100.0, -125.0), (-120.0, -160.0)),
}


class WallsMixin(LayersMixin):
    """A session's walls' digs (see the module)."""

    def _next_wall(self, far: bool, remaining: Any, t0: float) -> PlannedDig | None:
        """The next piece of the far (``far``) or near wall's profile dig: the wall's line from
        its top edge to the bottom, in pieces no longer along it than :data:`_COLUMN_MAX_M`
        (scaled), top first; a full dig where it fills the bucket, else a finishing pass.
        None when the wall is done or nothing is left on it."""
        t = self.task
        g = self.ground_y
        xf = t.start_x_m
        xn = xf - t.length_m
        if far:
            if self.section != 0:
                return None
            top = np.array([xf, g])
            foot = np.array([xf - t.depth_m / math.tan(t.beta1_rad), self.bottom_y])
            beta = t.beta1_rad
        else:
            if self.section_lo > xn + 1e-9:
                return None
            top = np.array([xn, g])
            foot = np.array([xn + t.depth_m / math.tan(t.beta2_rad), self.bottom_y])
            beta = t.beta2_rad
            corner = self._near_corner(top, foot, remaining, t0)
            if corner is not None:
                return corner
        # Pieces no longer along the wall than the longest profile dig; each may be taken in
        # its two halves where it does not plan whole (a long fit along a shallow wall).
        # ``_wall_piece`` counts the halves done.
        span = foot - top
        n = max(1, math.ceil(float(np.hypot(*span)) / (_COLUMN_MAX_M * self.planner.scale)))
        kind = DigType.DOWNWARD if self._downward_wall(beta) else DigType.BACKWARD
        atts = _WALL_ATTITUDES_DEG[kind]
        # The last piece stops short of the corner: a path that reaches into it cuts past the
        # bottom before the bottom's columns have opened it (and the columns start there).
        short = foot - span * (_CORNER_GAP_M * self.planner.scale / float(np.hypot(*span)))
        halves = 2 * n
        while self._wall_piece < halves:
            k = self._wall_piece
            for stop in (k + 2, k + 1) if k % 2 == 0 else (k + 1,):
                self._wall_piece = stop
                a = top + (short - top) * k / halves
                b = top + (short - top) * stop / halves
                # Nothing on this piece: skip it.
                if self._material_above(np.array([a, b])) < _COLUMN_EDGE_M * self.planner.scale:
                    break
                found = self._fit_pass(kind, np.array([a, b]), atts)
                dig = None if found is None else self._plan_profile(found, remaining, t0)
                if dig is None and stop == k + 2:
                    # Too thick across for the boom's torque, say: the outer half first,
                    # along the piece's line moved in by half the thickness; the piece again
                    # after it.
                    dig = self._wall_inner_pass(kind, a, b, atts, remaining, t0)
                    if dig is not None:
                        self._wall_piece = k
                if dig is not None:
                    return dig
        return None

    def _layer_far_wall(self, remaining: Any, t0: float) -> PlannedDig | None:
        """At the start of an upper layer's columns in the first section (once a layer:
        ``_wall_piece``), the far wall's piece within the layer, from the layer above's floor
        (or the ground) down to the layer's floor, as a downward dig along the wall; a full
        dig where it fills the bucket, else a finishing pass that the layer's first column
        continues (:meth:`_continuing_layer_column`), taken only where that column plans on
        the material the pass leaves. A downward column from the wall leaves a wedge along a
        steep wall below its entry, which took a pass of its own at the layer's end. Where
        the layer's first column starts beyond a joined dig's reach of the piece's foot (the
        layer's network digs took the far part, or the column enters beyond the material's
        face), the piece's end attitudes are those that hold a load, so that the column may
        take it carried (or joined, where the fitted piece ends at the column's start).

        None where the wall is shallower than :data:`_LAYER_WALL_MIN_DEG` or too shallow for
        a downward dig, nothing is left on the piece or no such dig plans."""
        if self._wall_piece or self.section != 0 or self.layer >= len(self.layer_floors):
            return None
        self._wall_piece = 1
        t = self.task
        if t.beta1_rad < math.radians(_LAYER_WALL_MIN_DEG) or not self._downward_wall(t.beta1_rad):
            return None
        g = self.ground_y
        y_top = self.layer_floors[self.layer - 1] if self.layer else g
        y_floor = self.layer_floors[self.layer]
        xf = t.start_x_m
        line = np.array(
            [
                (xf - (g - y_top) / math.tan(t.beta1_rad), y_top),
                (xf - (g - y_floor) / math.tan(t.beta1_rad), y_floor),
            ]
        )
        s = self.planner.scale
        if self._material_above(line) < _COLUMN_EDGE_M * s:
            return None
        ends = self._column_ends(self._layer_floor, self.section_lo, self._reach_hi())
        if not ends:
            return None
        atts = _WALL_ATTITUDES_DEG[DigType.DOWNWARD]
        if abs(ends[0] - float(line[1, 0])) > _JOIN_REACH_M * s:
            # The layer's first column starts away from the piece's foot: the piece ends
            # curled enough to hold its load, which may be carried to that column.
            most = math.degrees(self.carry_attitude_max())
            if min(atts[1]) > most:
                return None
            atts = (atts[0], (min(atts[1][0], most), min(atts[1][-1], most)))
        found = self._fit_pass(DigType.DOWNWARD, line, atts)
        if found is None:
            return None
        dig = self._plan_profile(found, remaining, t0, lambda d: self._continued_after(d, t0))
        if dig is not None and dig.finishing:
            self._wall_piece = 2
        return dig

    def _continued_after(self, dig: PlannedDig, t0: float) -> bool:
        """Whether the layer's first column continues ``dig``'s bucket
        (:meth:`_continuing_layer_column`) on the material ``dig`` leaves as planned; the
        session is left as it was."""
        planned = self._planned_region
        assert planned is not None  # dig was just planned
        saved = (self.surface, self.material, self.joinable, planned, self._carry_checked)
        counts = (self.finishing_used, self.finish_passes)
        swept = planned[2]
        self.surface = self._surface_after(dig)
        if swept is not None:
            self.material = self.material.difference(swept)
        bucket = (float(saved[1].area) - float(self.material.area)) * self.width_m
        self.joinable = (np.asarray(dig.problem.q_end_rad, dtype=np.float64), bucket)
        try:
            column = self._continuing_layer_column(self.remaining_design(), t0)
        finally:
            (
                self.surface,
                self.material,
                self.joinable,
                self._planned_region,
                self._carry_checked,
            ) = saved
            self.finishing_used, self.finish_passes = counts
        return column is not None

    def _near_corner(
        self, top: FloatArray, foot: FloatArray, remaining: Any, t0: float
    ) -> PlannedDig | None:
        """The near wall taken with the bucket the bottom's last column filled: a backward
        dig joined to that column, from its exit along what is left of the bottom to the
        wall's foot and up the wall to its top edge (:data:`_NEAR_CORNER_ATTS`); None where
        the last dig may not be continued, its exit is not on the bottom within
        :data:`_CORNER_RUN_M` (scaled) of the foot, nothing is left on the wall, or no such
        dig plans."""
        exit_ = self._joinable_exit()
        if exit_ is None:
            return None
        s = self.planner.scale
        run = float(exit_[0] - foot[0])
        if abs(float(exit_[1]) - self.bottom_y) > _JOIN_REACH_M * s or not (
            -_JOIN_REACH_M * s <= run <= _CORNER_RUN_M * s
        ):
            return None
        if self._material_above(np.array([foot, top])) < _COLUMN_EDGE_M * s:
            return None
        line = np.array([exit_, foot, top]) if run > 0.002 * s else np.array([exit_, top])
        found = self._fit_pass(DigType.BACKWARD, line, _NEAR_CORNER_ATTS)
        if found is None or not found.joined or found.carried:
            return None
        return self._plan_profile(found, remaining, t0)

    def _wall_inner_pass(
        self,
        kind: DigType,
        a: FloatArray,
        b: FloatArray,
        atts: tuple[tuple[float, ...], tuple[float, ...]],
        remaining: Any,
        t0: float,
    ) -> PlannedDig | None:
        """A pass parallel to the wall piece ``a``-``b``, moved towards the design's inside
        by half the material's thickness across it; None where that thickness is under twice
        :data:`_COLUMN_EDGE_M` (scaled) or no such pass plans."""
        seg = b - a
        length = float(np.hypot(*seg))
        across = self._material_above(np.array([a, b])) * abs(float(seg[0])) / length
        if across < 2.0 * _COLUMN_EDGE_M * self.planner.scale:
            return None
        normal = self._inward_normal(a, b)
        shift = 0.5 * across * normal
        found = self._fit_pass(kind, np.array([a + shift, b + shift]), atts)
        return None if found is None else self._plan_profile(found, remaining, t0)

    def _plan_profile(
        self,
        found: Candidate,
        remaining: Any,
        t0: float,
        accept: Callable[[PlannedDig], bool] | None = None,
    ) -> PlannedDig | None:
        """A fitted profile dig planned as a full dig, or else (when the section's finishing
        passes allow) as a finishing pass; ``accept``: where given, a pass it refuses is not
        taken (nor counted)."""
        dig = self._first_plannable([found], remaining, t0)
        if dig is None:
            dig = self._first_plannable(
                [dataclasses.replace(found, may_underfill=True)], remaining, t0
            )
            if dig is not None and accept is not None and not accept(dig):
                return None
            self._count_pass(dig)
        return dig

