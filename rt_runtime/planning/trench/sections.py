"""Sections of a trench longer than the reach from one stand, and the crawler travel between
them (back along the trench, one way)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.trench.finishing import FinishingMixin
from rt_runtime.planning.trench.plan import TravelMove
from rt_runtime.planning.trench.state import Stage

if TYPE_CHECKING:
    pass


#: Where a stand puts the far edge of its section, and the nearest the section reaches
#: (arm frame, scale model, m): the entries' far end less 5 cm, and the near edge of Yao's
#: task B from its default start (0.35 m: the nearest a 0.10 m trench was dug to).
_STAND_FAR_X_M = 1.05

_STAND_NEAR_X_M = 0.35

#: Safety bound on a task's digs per section (TrenchPlanner max_digs=None).
_MAX_DIGS_PER_SECTION = 20


class SectionsMixin(FinishingMixin):
    """A session's sections and travel (see the module)."""

    def _plan_sections(self) -> tuple[list[tuple[float, float]], list[float]]:
        """The trench's sections, far first, and the machine's position (travel from its
        first position) for each: one section where the trench lies within reach of the
        first stand; else equal sections, each within ``[_STAND_NEAR_X_M, _STAND_FAR_X_M]``
        (scaled) of the arm from its stand, the machine travelling back by one section each
        time (first back to put the far edge at _STAND_FAR_X_M where it lies nearer)."""
        s = self.planner.scale
        t = self.task
        xf = t.start_x_m
        near = _STAND_NEAR_X_M * s
        if xf - t.length_m >= near - 1e-9:
            return [(xf - t.length_m, xf)], [0.0]
        m0 = min(0.0, xf - _STAND_FAR_X_M * s)
        n = math.ceil(t.length_m / (xf - m0 - near) - 1e-9)
        step = t.length_m / n
        sections = [(xf - (k + 1) * step, xf - k * step) for k in range(n)]
        return sections, [m0 - k * step for k in range(n)]

    def _begin_section(self, k: int) -> None:
        """Start section ``k``: travel to its stand, choose its layers, first stage."""
        self.section = k
        self.section_lo, self.section_hi = self.sections[k]
        move = self.stands[k] - self.machine_x
        if abs(move) > 1e-9:
            self._travel(move)
        self.finishing_used = 0
        self.finish_passes = 0
        self.finishing_difference = None
        self.layer_floors = self._choose_layers()
        self.layer = 0
        self.stage = Stage.ROUGH if self.layer_floors else Stage.FAR_WALL
        self.phase = DigType.DOWNWARD
        self._wall_piece = 0
        self._set_layer()

    def _travel(self, move: float) -> None:
        """Crawler travel by ``move`` (m along the trench, negative: back, away from the dug
        part); the arm's pose is unknown after."""
        self.steps.append(TravelMove(move, self.machine_x, self.machine_x + move))
        self.machine_x += move
        self.q_now = None
        self.joinable = None
