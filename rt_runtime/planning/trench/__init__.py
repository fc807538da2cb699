"""Task-oriented continuous trench planning (Yao 4.4, Fig. 5): a trench drawing to a sequence
of verified digs, each a full bucket, the moves between them, and the machine's travel.

The flow, one module a step:

- ``task``: the trench task, the rig's task domain, validation, the design polygon.
- ``planner``: what stays from task to task (rig, one-shot planner, verifier, grids); the
  open-loop plan of a task.
- ``session``: one task dug dig by dig in the closed loop (plan, execute, record the measured
  tip path), built from the steps below (each a mixin of the session's state, ``state``):
  ``sections`` (sections and one-way travel), ``layers`` (the layers and their columns),
  ``walls`` (the walls' digs), ``rough`` (the network's digs, Fig. 5), ``finishing``
  (finishing passes), ``fit`` (digs fitted along the design's outline), ``digs`` (planning
  a chosen dig for real and checking it), ``cycles`` (the moves between digs as one
  trajectory through their corners, dumping in the spoil zone), ``moves`` (the rest-to-rest
  moves: the corners and the fallback), ``material`` (material accounting), ``persist`` (the
  session as data).
- ``candidates``, ``plan``, ``geometry``, ``planners``: the typed candidate, the frozen plan and
  its report, the material model's geometry, the one-shot planners (PINN, PSO).

Material model. The material is a shapely polygon of the cross-section in the work-site frame
(the arm frame of the machine's first position; travel shifts the arm frame by ``machine_x_m``)
mirrored by a height field on a 1 mm grid. A dig removes the region its bucket sweeps:
everything above the tip path's lower envelope over the path's x-span. Every dig's volume is
its real cut (polygon areas times the bucket width); the digs' volumes add up to the total.

Digs. Each dig carries V_min..V_max of real material (Yao's V_p range, 0.8-1.2 x the struck
volume), except finishing passes, at most two a section where the material allows. The design
is cut in horizontal layers, top first; the network's digs and columns along each layer's
floor take the layers above the bottom one, straight columns along the bottom and the walls'
digs the bottom one (docs/design-notes.md, decision R8).
"""

from rt_runtime.planning.trench.candidates import Candidate
from rt_runtime.planning.trench.cycles import CYCLE_W_JERK
from rt_runtime.planning.trench.finishing import MAX_FINISHING_PER_SECTION
from rt_runtime.planning.trench.geometry import GRID_STEP_M, OVERDIG_LIMIT_M, lower_envelope
from rt_runtime.planning.trench.motion import joint_move
from rt_runtime.planning.trench.moves import TRANSITION_PENETRATION_M
from rt_runtime.planning.trench.plan import (
    COVERAGE_GOAL,
    OVERDIG_GOAL_M,
    Cycle,
    PlannedDig,
    PlanStatus,
    Transition,
    TransitionKind,
    TravelMove,
    TrenchPlan,
    cycle_problem,
    iter_moves,
    plan_goals,
)
from rt_runtime.planning.trench.planner import ONESHOT_PLANNERS, TrenchPlanner, plan_task
from rt_runtime.planning.trench.planners import (
    OneShotPlanner,
    OneShotResult,
    PinnOneShot,
    PsoOneShot,
)
from rt_runtime.planning.trench.session import TrenchSession
from rt_runtime.planning.trench.state import Stage
from rt_runtime.planning.trench.task import (
    BUILTIN_TASKS,
    TASK_KEYS,
    WALL_SLOPE_DEG,
    YAO_FIG14,
    TrenchTask,
    check_task_keys,
    design_polygon,
    load_task,
    make_task,
    read_task_file,
    task_limits,
)

__all__ = [
    "BUILTIN_TASKS",
    "COVERAGE_GOAL",
    "CYCLE_W_JERK",
    "GRID_STEP_M",
    "MAX_FINISHING_PER_SECTION",
    "ONESHOT_PLANNERS",
    "OVERDIG_GOAL_M",
    "OVERDIG_LIMIT_M",
    "TASK_KEYS",
    "TRANSITION_PENETRATION_M",
    "WALL_SLOPE_DEG",
    "YAO_FIG14",
    "Candidate",
    "Cycle",
    "OneShotPlanner",
    "OneShotResult",
    "PinnOneShot",
    "PlanStatus",
    "PlannedDig",
    "PsoOneShot",
    "Stage",
    "Transition",
    "TransitionKind",
    "TravelMove",
    "TrenchPlan",
    "TrenchPlanner",
    "TrenchSession",
    "TrenchTask",
    "check_task_keys",
    "cycle_problem",
    "design_polygon",
    "iter_moves",
    "joint_move",
    "load_task",
    "lower_envelope",
    "make_task",
    "plan_goals",
    "plan_task",
    "read_task_file",
    "task_limits",
]
