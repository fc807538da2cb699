"""The trench session: one task being dug, dig by dig, in the closed loop (plan a dig, execute
it, record the measured tip path); the steps of the flow are the modules of this package."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import shapely
from numpy.typing import ArrayLike
from shapely.geometry import Polygon

from rt_runtime.errors import PlanningError
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.trench.geometry import GRID_STEP_M, FloatArray, _swept_polygon
from rt_runtime.planning.trench.persist import PersistMixin
from rt_runtime.planning.trench.plan import Cycle, PlannedDig, Transition, TravelMove, TrenchPlan
from rt_runtime.planning.trench.sections import _MAX_DIGS_PER_SECTION
from rt_runtime.planning.trench.state import _STAGES, Stage, _stage
from rt_runtime.planning.trench.task import TrenchTask, design_polygon

#: How near the measured path's end must come to the planned exit for the next dig to
#: continue the bucket from there (scale model, m).
_JOIN_END_M = 0.005

#: A bucket this full (of V_max) takes no joined dig.
_JOIN_BUCKET_MAX = 0.97

if TYPE_CHECKING:
    from rt_runtime.planning.trench.planner import TrenchPlanner


class TrenchSession(PersistMixin):
    """One task being dug: the material state and the steps so far (closed loop).

    Use :meth:`next_dig` to plan the next dig from the current material (``None`` when the task
    is done), execute it, then :meth:`record` the measured tip path (work-site frame); the
    material is updated from what was measured, not what was planned. ``next_dig`` also
    appends to :attr:`steps` the :class:`Cycle` that leads into the dig (from the previous
    dig's exit, or from the home pose), checked against the material as it is before the dig;
    the dig itself joins :attr:`steps` when it is recorded.
    """

    def __init__(self, planner: TrenchPlanner, task: TrenchTask) -> None:
        self.planner = planner
        self.task = task
        rig = planner.rig
        self.rig = rig
        self.ground_y = rig.ground_y_m
        self.width_m = rig.bucket.width_m
        self.planning = oneshot.require_planning(rig)
        self.v_max_m3 = self.planning.volume_max_m3
        self.design = design_polygon(task, self.ground_y)
        xf = task.start_x_m
        xn = xf - task.length_m
        margin = 0.5 * planner.scale
        self.x_lo, self.x_hi = xn - margin, xf + margin
        self.grid = np.arange(self.x_lo, self.x_hi + GRID_STEP_M / 2, GRID_STEP_M)
        self.bottom_y = self.ground_y - task.depth_m
        box_bottom = self.bottom_y - 0.2 * planner.scale
        self.top_y = self.ground_y + 1.0
        self.initial = Polygon(
            [
                (self.x_lo, self.ground_y),
                (self.x_lo, box_bottom),
                (self.x_hi, box_bottom),
                (self.x_hi, self.ground_y),
            ]
        )
        self.material: Any = self.initial
        self.surface = np.full(self.grid.shape[0], self.ground_y)
        self.design_floor = self._design_floor()
        # Half-planes of the design's walls and bottom: n . p <= c inside (unit n).
        b1, b2 = task.beta1_rad, task.beta2_rad
        self._walls = np.array(
            [
                # far wall through (xf, g), inside is x <= ...: n = (sin b1, -cos b1)
                [math.sin(b1), -math.cos(b1), math.sin(b1) * xf - math.cos(b1) * self.ground_y],
                # near wall through (xn, g): n = (-sin b2, -cos b2)
                [-math.sin(b2), -math.cos(b2), -math.sin(b2) * xn - math.cos(b2) * self.ground_y],
                # bottom: n = (0, -1), -y <= -(bottom) -> y >= bottom
                [0.0, -1.0, -self.bottom_y],
            ]
        )
        # The design's edges for the over-dig distance, one row per edge: start point, vector,
        # squared length (ax, ay, abx, aby, |ab|^2; the C geometry takes the same rows).
        ring = np.asarray(self.design.exterior.coords)  # closed: last == first
        edge = ring[1:] - ring[:-1]
        self._design_edges = np.column_stack([ring[:-1], edge, np.sum(edge * edge, axis=1)])
        self.steps: list[PlannedDig | Cycle | Transition | TravelMove] = []
        self.digs: list[PlannedDig] = []
        self.machine_x = 0.0
        self.q_now: FloatArray | None = None
        self.pending: PlannedDig | None = None
        self.design_area = float(self.design.area)
        self.phase = DigType.DOWNWARD
        self.finishing_used = 0
        self.finish_passes = 0
        self.joinable = None
        #: The sections (work-site x ranges, far first) and where the machine stands for each.
        self.sections, self.stands = self._plan_sections()
        self.section = 0
        self.section_lo, self.section_hi = self.sections[0]
        self.layer_floors: tuple[float, ...] = ()
        self.layer = 0
        self.stage = Stage.ROUGH
        self._wall_piece = 0
        self._begin_section(0)
        #: Time spent per stage so far (us; TrenchPlan.stage_us).
        self.stage_us: dict[str, float] = dict.fromkeys(_STAGES, 0.0)
        #: Each dig's planning in :meth:`next_dig` without the moves into it (us; one per
        #: dig :meth:`next_dig` returned, in order; TrenchPlan.dig_plan_us).
        self.dig_plan_us: list[float] = []
        #: The pending dig's planned tip path, its envelope and swept region (for record()).
        self._planned_region: tuple[FloatArray, FloatArray, Any] | None = None
        #: Transitions planned lately: key -> (the height field they were checked on, moves).
        self._moves: dict[tuple[Any, ...], tuple[FloatArray, tuple[Transition, ...]]] = {}
        #: The sparse max table of the height field the last move was checked on.
        self._max_tables: tuple[FloatArray, FloatArray] = (np.empty(0), np.empty((0, 0)))
        self._spoil: dict[float, FloatArray] = {}

    @classmethod
    def restore(
        cls, planner: TrenchPlanner, task: TrenchTask, state: dict[str, Any]
    ) -> TrenchSession:
        """A session continuing from :meth:`state` (a daemon restart resumes the next dig).

        Args:
            planner: The planner (same rig as the state's).
            task: The task (same as the state's).
            state: What :meth:`state` returned (after a JSON round trip or not).

        Raises:
            ConfigurationError: A key is missing or malformed, the version is unknown, or the
                rig or task differ from the state's (the message names the key).
        """
        session = cls(planner, task)
        session.apply_state(state)
        return session

    def next_dig(self) -> PlannedDig | None:
        """Plan the next dig from the current material, or None when the task is done.

        Raises:
            PlanningError: Material is left but no verified dig removes any of it, or the
                safety bound on the number of digs is reached.
        """
        if self.pending is not None:
            raise PlanningError("record() the executed path of the previous dig first")
        t_call = time.perf_counter()
        moves_us = self.stage_us["transitions"]
        remaining = self.remaining_design()
        left = float(remaining.area)
        # Done when the design of the sections still ahead (this one and those nearer the
        # machine) is dug within half a percent: of each section's own design, for the last.
        ahead = shapely.box(self.sections[-1][0], self.bottom_y - 1.0, self.section_hi, self.top_y)
        if float(remaining.intersection(ahead).area) <= 0.005 * float(
            self.design.intersection(ahead).area
        ):
            return None
        bound = self.planner.max_digs or _MAX_DIGS_PER_SECTION * len(self.sections)
        if len(self.digs) >= bound:
            raise PlanningError(
                f"task {self.task.name}: {left / self.design_area:.1%} of the design is left "
                f"after {len(self.digs)} digs (the bound)"
            )
        t0 = time.perf_counter()
        dig = self._next_in_section(remaining, t0)
        while dig is None and self.section + 1 < len(self.sections):
            self._begin_section(self.section + 1)
            dig = self._next_in_section(remaining, t0)
        if dig is None:
            return None
        if not dig.joined or dig.carried:
            self._append_transitions(dig)
        self.pending = dig
        self.dig_plan_us.append(
            (time.perf_counter() - t_call) * 1e6 - (self.stage_us["transitions"] - moves_us)
        )
        return dig

    def _next_in_section(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The section's next dig through its stages (:class:`Stage`), or None when the
        section is done."""
        dig: PlannedDig | None = None
        while dig is None and self.stage is not Stage.FINISH:
            stage = self.stage
            if stage is Stage.ROUGH:
                dig = self._next_rough(remaining, t0)
            elif stage is Stage.LAYER:
                dig = self._layer_far_wall(remaining, t0) or self._next_layer_column(
                    remaining, t0
                )
            elif stage is Stage.BOTTOM:
                dig = self._next_column(remaining, t0)
            else:
                dig = self._next_wall(stage is Stage.FAR_WALL, remaining, t0)
            if dig is None:
                self._advance()
        if dig is None:
            dig = self._next_finishing(remaining, t0)
        return dig

    @_stage("record")
    def record(self, dig: PlannedDig, measured_path_m: ArrayLike) -> float:
        """Update the material from the executed dig's measured tip path (work-site frame).

        Returns:
            The volume (m^3) the measured path removed.

        Raises:
            PlanningError: ``dig`` is not the pending dig, or the path is not a finite
                ``(n >= 2, 2)`` array.
        """
        if self.pending is None or dig is not self.pending:
            raise PlanningError("record() takes the dig next_dig() returned last")
        path = np.asarray(measured_path_m, dtype=np.float64)
        if path.ndim != 2 or path.shape[1] != 2 or path.shape[0] < 2:
            raise PlanningError(f"measured path must have shape (n >= 2, 2); got {path.shape}")
        if not np.all(np.isfinite(path)):
            raise PlanningError("measured path has non-finite values")
        before = float(self.material.area)
        planned = self._planned_region
        if planned is not None and np.array_equal(path, planned[0]):
            env, swept = planned[1], planned[2]
        else:
            env = self._envelope(path, self.grid)
            swept = _swept_polygon(path, self.grid, self.top_y, env, self._envelope)
        self._planned_region = None
        if swept is not None:
            self.material = self.material.difference(swept)
        self.surface = np.minimum(self.surface, env)
        removed = (before - float(self.material.area)) * self.width_m
        held = self.joinable[1] if dig.joined and self.joinable is not None else 0.0
        if dig.joined and not dig.finishing:
            self._fill_bucket()
        self.steps.append(dig)
        self.digs.append(dig)
        self.q_now = np.asarray(dig.problem.q_end_rad)
        self.pending = None
        # The next dig may continue this one where the arm ended where it was planned to
        # (the bucket not yet full).
        bucket = held + removed
        reach = _JOIN_END_M * self.planner.scale
        ended = float(np.hypot(*(path[-1] - dig.tip_path_m[-1]))) <= reach
        self.joinable = (
            (self.q_now, bucket) if ended and bucket < _JOIN_BUCKET_MAX * self.v_max_m3 else None
        )
        return removed

    def _fill_bucket(self) -> None:
        """The digs of the bucket a joined full dig completes are no finishing passes: the
        recorded ones before it (back to the dig that began the bucket) lose the mark."""
        k = len(self.digs) - 1
        while k >= 0:
            d = self.digs[k]
            if d.finishing:
                full = dataclasses.replace(d, finishing=False, status="profile")
                at = next(i for i, st in enumerate(self.steps) if st is d)
                self.steps[at] = full
                self.digs[k] = full
            if not d.joined:
                break
            k -= 1

    def observe_surface(self, x_m: ArrayLike, y_m: ArrayLike) -> None:
        """Take a measured surface (a profile scanner's, work-site frame) as the material.

        After :meth:`record`: the material becomes everything below the measured surface
        (linear between the samples, the ground beyond them, never above the ground), so what
        slumped or fell back into the trench, which no tip path shows, is planned for again.
        Without a scanner the material stays the one the measured tip paths left.

        Args:
            x_m: Abscissae ``(m,)``, m >= 2, strictly increasing.
            y_m: Surface heights ``(m,)``.

        Raises:
            PlanningError: Malformed samples (shapes, non-finite, not increasing), or a dig
                is pending (record it first).
        """
        if self.pending is not None:
            raise PlanningError("record() the pending dig before observing the surface")
        x = np.asarray(x_m, dtype=np.float64)
        y = np.asarray(y_m, dtype=np.float64)
        if x.ndim != 1 or x.shape != y.shape or x.shape[0] < 2:
            raise PlanningError(
                f"measured surface must be two (m >= 2,) arrays; got {x.shape}, {y.shape}"
            )
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise PlanningError("measured surface has non-finite values")
        if not np.all(np.diff(x) > 0.0):
            raise PlanningError("measured surface abscissae must be strictly increasing")
        surface = np.minimum(
            np.interp(self.grid, x, y, left=self.ground_y, right=self.ground_y), self.ground_y
        )
        box_bottom = float(self.initial.bounds[1])
        ring = [
            (self.x_lo, box_bottom),
            *zip(self.grid.tolist(), surface.tolist(), strict=True),
            (self.x_hi, box_bottom),
        ]
        self.material = Polygon(ring).buffer(0).intersection(self.initial)
        self.surface = surface

    @_stage("finish")
    def finish(self, plan_total_us: float) -> TrenchPlan:
        """The frozen plan of everything recorded so far."""
        dug = self.initial.difference(self.material)
        sym = dug.symmetric_difference(self.design)
        coverage = float(sym.area) / self.design_area
        over_max = self._overdig_of_region(dug)
        final_surface = np.stack([self.grid, self.surface], axis=1)
        removed = (float(self.initial.area) - float(self.material.area)) * self.width_m
        return TrenchPlan(
            task=self.task,
            rig=self.rig.name,
            planner=self.planner.oneshot.name,
            steps=tuple(self.steps),
            digs=tuple(self.digs),
            design=self.design,
            dug=dug,
            final_surface_m=final_surface,
            coverage_error=coverage,
            overdig_max_m=over_max,
            removed_m3=removed,
            design_m3=self.design_area * self.width_m,
            plan_total_us=plan_total_us,
            dig_plan_us=tuple(self.dig_plan_us),
            screening=self.planner.screening,
            soil=self.planner.soil,
        )
