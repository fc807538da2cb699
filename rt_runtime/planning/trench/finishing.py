"""Finishing passes: the walls, the bottom in pieces and lines across thick material, taken
where the section's digs left design material (at most two a section where the material
allows, more only where the section would otherwise miss the coverage goal)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import shapely

from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.trench.candidates import Candidate, difference_lowered
from rt_runtime.planning.trench.geometry import _Pass
from rt_runtime.planning.trench.layers import _CUT_MAX_M
from rt_runtime.planning.trench.plan import COVERAGE_GOAL, PlannedDig
from rt_runtime.planning.trench.walls import WallsMixin

#: Finishing passes a section may take (they need not fill the bucket).
MAX_FINISHING_PER_SECTION = 2

#: Finishing passes the section's last stage (``FINISH``) takes at most where its design is
#: not dug otherwise (the under-filled digs of the stages before it not counted: a deep
#: trench's steep wall can spend eight of them before its finishing passes begin).
MAX_FINISHING_HARD = 8

#: Least material on a finishing pass's line for the pass to be tried (scale model, m).
_FINISH_MIN_M = 0.002

#: Least design material a finishing pass removes, as a fraction of its section's design.
_FINISH_MIN_USEFUL = 0.001

#: Share of that least amount by which a pass beyond the two must have lowered the section's
#: difference of dug and design, measured after it, for another to be taken (the planned
#: pass lowers it by the least amount or more; half of it allows for the polygon's measure
#: against the height field's).
_REALISED_SHARE = 0.5
#: Attitude tables of the walls' finishing passes (deg; first and last of each end).
_FAR_WALL_ATTS = ((-80.0, -100.0), (-95.0, -120.0))

_NEAR_WALL_ATTS = ((-80.0, -100.0), (-100.0, -130.0))

#: Spacing of the finishing lines across thick material (:meth:`FinishingMixin._finishing_lines`),
#: m on the scale model.
_LAYER_M = 0.05


def _pass_rank(c: Candidate, beyond: bool) -> tuple[bool, float]:
    """The order of the finishing passes that lower the difference enough: first those that
    continue the last dig's bucket (joined, or carried to it), which take no bucket of their
    own, then the others; each by the design material it removes, the most first, or with
    ``beyond`` (passes beyond the section's two, taken for the coverage goal) by how much it
    lowers the difference of dug and design."""
    return (not c.joined, -(difference_lowered(c) if beyond else c.useful_m2))


class FinishingMixin(WallsMixin):
    """A session's finishing passes (see the module)."""

    def _next_finishing(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The finishing pass that removes the most design material of the section's
        (:meth:`_finishing_lines`) among those that lower the symmetric difference of dug
        and design (design material removed less what is cut outside the design); None when
        the section's design is dug (within half a percent), no pass lowers it by a useful
        amount, or :data:`MAX_FINISHING_HARD` passes of this stage are spent. Passes beyond
        :data:`MAX_FINISHING_PER_SECTION` are taken only where the section would otherwise
        miss the coverage goal (the design material left plus what was dug outside the
        design, over the section's design), the one that lowers the difference most first:
        a finished trench comes first."""
        if self.finish_passes >= MAX_FINISHING_HARD:
            return None
        box = shapely.box(self.section_lo, self.bottom_y - 1.0, self.section_hi, self.top_y)
        part = self.design.intersection(box)
        left = float(part.intersection(self.material).area)
        if left <= 0.005 * float(part.area):
            return None
        least = _FINISH_MIN_USEFUL * float(part.area)
        beyond = self.finishing_used >= MAX_FINISHING_PER_SECTION
        difference = math.nan
        if beyond:
            # The coverage goal counts the design material left and what was dug outside
            # the design alike (the symmetric difference): the section's share of both.
            dug = box.intersection(self.initial).difference(self.material)
            over = float(dug.difference(self.design).area)
            difference = left + over
            if difference <= COVERAGE_GOAL * float(part.area):
                return None
            last = self.finishing_difference
            if last is not None and last - difference < _REALISED_SHARE * least:
                # The last such pass did not lower the difference on the measured material
                # (what it took slumped back and the face eroded, as a profile scanner
                # shows): more passes would chase the material's angle of repose.
                return None
        found: list[Candidate] = []
        for kind, line, atts in self._finishing_lines():
            fit = self._fit_pass(kind, line, atts)
            if fit is not None:
                found.append(dataclasses.replace(fit, may_underfill=True))
        # A pass is one that lowers the symmetric difference (the design material it removes
        # less what it cuts outside the design) by more than next to nothing (a thousandth of
        # the section's design: what is left there is within the coverage budget's rounding).
        found = [c for c in found if difference_lowered(c) >= least]
        found.sort(key=lambda c: _pass_rank(c, beyond))
        dig = self._first_plannable(found, remaining, t0)
        if self._count_pass(dig):
            self.finish_passes += 1
        if dig is not None and beyond:
            self.finishing_difference = difference
        return dig

    def _finishing_lines(self) -> list[_Pass]:
        """The section's finishing passes: the far wall (in the first section), the bottom in
        pieces (:meth:`_bottom_passes`), the near wall (in the last), and where the material
        left is thicker than a dig cuts through, lines across it every :data:`_LAYER_M`
        (scaled) from the top (the bottom-like passes at those heights); each only where
        material is left on it."""
        t = self.task
        g = self.ground_y
        s = self.planner.scale
        xf, xn = t.start_x_m, t.start_x_m - t.length_m
        lo, hi = self.section_lo, self._reach_hi()
        far_foot = xf - t.depth_m / math.tan(t.beta1_rad)
        near_foot = xn + t.depth_m / math.tan(t.beta2_rad)
        x = self.grid
        inside = (x >= lo) & (x <= hi)
        thick = np.where(inside, self.surface - self.design_floor, 0.0)
        passes: list[_Pass] = []
        if self.section == 0:
            passes.append(
                (DigType.DOWNWARD, np.array([(xf, g), (far_foot, self.bottom_y)]), _FAR_WALL_ATTS)
            )
        b_hi, b_lo = min(far_foot, hi), max(near_foot, lo)
        if b_hi > b_lo:
            passes += self._bottom_passes((b_hi, self.bottom_y), (b_lo, self.bottom_y))
        if lo <= xn + 1e-9:
            passes.append(
                (DigType.DOWNWARD, np.array([(xn, g), (near_foot, self.bottom_y)]), _NEAR_WALL_ATTS)
            )
        top = float(np.max(thick)) if thick.size else 0.0
        if top > _CUT_MAX_M * s:
            n = math.ceil(top / (_LAYER_M * s))
            for k in range(1, n):
                y = self.bottom_y + top * (1.0 - k / n)
                far = (min(xf - (g - y) / math.tan(t.beta1_rad), hi), y)
                near = (max(xn + (g - y) / math.tan(t.beta2_rad), lo), y)
                if far[0] > near[0]:
                    passes += self._bottom_passes(far, near)
        return [p for p in passes if self._material_above(p[1]) > _FINISH_MIN_M * s]
