"""The trench session's state (what every step of the flow reads and writes): the stages a
section goes through, the stage timer, and the declared attributes the steps share."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from enum import IntEnum
from typing import TYPE_CHECKING, Any, TypeVar, cast

from shapely.geometry import Polygon

from rt_runtime.planning.oneshot import DigType
from rt_runtime.rig import Planning, Rig

if TYPE_CHECKING:
    from rt_runtime.planning.trench.geometry import FloatArray
    from rt_runtime.planning.trench.plan import Cycle, PlannedDig, Transition, TravelMove
    from rt_runtime.planning.trench.planner import TrenchPlanner
    from rt_runtime.planning.trench.session import TrenchSession
    from rt_runtime.planning.trench.task import TrenchTask


class Stage(IntEnum):
    """Where a section's digging is; a section goes through them in this order.

    The design is cut in horizontal layers, top first (:meth:`TrenchSession._choose_layers`).
    In each layer above the bottom one: ``ROUGH``, the network's digs (Yao Fig. 5: downward,
    then backward), each filled on the material left and judged against the layer's floor;
    then ``LAYER``, digs along the layer's floor (and the walls above it) take the rest of
    the layer in columns, far to near, each a full bucket. In the bottom layer: ``FAR_WALL``,
    the far wall's dig (it takes what the layers left on the wall); ``BOTTOM``, columns along
    the design's bottom, straight, far to near; ``NEAR_WALL``, the near wall's dig.
    ``FINISH``: finishing passes trim what is left. Digs that do not fill the bucket (the
    walls' mostly) are finishing passes, at most :data:`MAX_FINISHING_PER_SECTION` a section.
    """

    ROUGH = 0
    LAYER = 1
    FAR_WALL = 2
    BOTTOM = 3
    NEAR_WALL = 4
    FINISH = 5


#: The stages of TrenchPlan.stage_us that TrenchSession times (``other`` is the rest).
_STAGES = ("screen", "oneshot", "checks", "passes", "transitions", "record", "finish")

_Method = TypeVar("_Method", bound=Callable[..., Any])


def _stage(name: str) -> Callable[[_Method], _Method]:
    """Add a TrenchSession method's wall time to its ``stage_us[name]``."""

    def wrap(method: _Method) -> _Method:
        @functools.wraps(method)
        def timed(self: TrenchSession, *args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return method(self, *args, **kwargs)
            finally:
                self.stage_us[name] += (time.perf_counter() - t0) * 1e6

        return cast(_Method, timed)

    return wrap


class SessionState:
    """The attributes a trench session's steps share (set by ``TrenchSession.__init__`` and
    the steps; declared here so that each step's module is typed on its own).

    Frames and units: x in the work-site frame (the arm frame of the machine's first position,
    shifted by ``machine_x`` from the machine's current one), m; poses in rad.
    """

    planner: TrenchPlanner
    task: TrenchTask
    rig: Rig
    planning: Planning
    ground_y: float
    width_m: float
    v_max_m3: float
    design: Polygon
    design_area: float
    initial: Polygon
    material: Any
    x_lo: float
    x_hi: float
    top_y: float
    bottom_y: float
    #: The height field's grid (m) and the material's surface on it (m).
    grid: FloatArray
    surface: FloatArray
    design_floor: FloatArray
    _walls: FloatArray
    _design_edges: FloatArray
    steps: list[PlannedDig | Cycle | Transition | TravelMove]
    digs: list[PlannedDig]
    machine_x: float
    q_now: FloatArray | None
    pending: PlannedDig | None
    phase: DigType
    finishing_used: int
    #: The finishing passes the section's ``FINISH`` stage took (of :attr:`finishing_used`).
    finish_passes: int
    #: The section's design left plus its over-cut (m^2) when its last finishing pass beyond
    #: the two a section may take was chosen; None before one.
    finishing_difference: float | None
    sections: list[tuple[float, float]]
    stands: list[float]
    section: int
    section_lo: float
    section_hi: float
    layer_floors: tuple[float, ...]
    layer: int
    stage: Stage
    #: In a wall's stage, the halves of the wall's pieces done; in an upper layer's columns,
    #: 0 before the layer's far-wall piece was tried, 2 while the column that continues it
    #: is next, else 1.
    _wall_piece: int
    layer_y: float
    layer_design: Any
    _layer_floor: FloatArray
    _layer_walls: FloatArray
    _layer_edges: FloatArray
    stage_us: dict[str, float]
    _planned_region: tuple[FloatArray, FloatArray, Any] | None
    _moves: dict[tuple[Any, ...], tuple[FloatArray, tuple[Transition, ...]]]
    _max_tables: tuple[FloatArray, FloatArray]
    #: The spoil zone's dump poses per x limit (arm frame, m): ``(k, 3)``.
    _spoil: dict[float, FloatArray]
