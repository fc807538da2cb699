"""Planning the next dig without stopping the loop: the session driver, inline or in a process.

Role: the executor's planner side. A :class:`SessionDriver` wraps a
:class:`~rt_runtime.planning.trench.TrenchSession` with the two requests the executor makes:

* ``plan(q_from_rad)``: the next dig with every move the executor streams around it
  (:class:`DigPlan`: the cycle into it, from the measured pose on the first request and from
  the previous dig's exit after that, the dig, and the exit moves for when no dig follows),
  or the end of the task;
* ``record(strokes_m)``: the reported strokes of the executed dig -> the measured tip path in the
  work-site frame -> ``session.record`` (the surface follows what was measured) ->
  :class:`Recorded` with the session's JSON state for the job store.

Each :class:`DigPlan` also carries its motions as setpoint tables on the loop's period grid
(:mod:`rt_runtime.control.setpoints`), chained with CONNECT moves from the pose of the first
request: everything the job controller streams is computed here, none of it in a cycle.

Two links run it (same requests, same replies, :meth:`poll` once per cycle):

* :class:`InlinePlanner` answers the requests in-process in :meth:`~InlinePlanner.service`,
  which the controller manager calls between cycles. For a simulated clock (the lockstep HIL):
  time stands still while it plans, the run is deterministic.
* :class:`ProcessPlanner` runs the session in a separate process (``multiprocessing``, ``spawn``
  context: the loop's process may hold threads, which ``fork`` would copy in a locked state), so
  ``next_dig``'s candidate screening (several loop periods) never holds the loop's interpreter
  lock. A sender thread writes the requests to the pipe and a receiver thread reads and
  unpickles the replies (the setpoint tables are hundreds of kB); the loop only puts and takes
  queue items. The process rebuilds the planner from :class:`PlannerSpec` (rig, one-shot planner
  name, model directory, the loop's period) and the session from its state
  (:meth:`TrenchSession.restore`), so nothing but plain data crosses the pipe.

Prescribed paths. A :class:`PathJob` is a fixed sequence of joint motions an
operator or a task prescribes (e.g. Gao's mixed-order interpolation through key points, wrapped by
:class:`PolynomialMotion`); :class:`PathLink` is the planner link that hands it out: the first
``request_plan`` is answered with one :class:`PathPlan` holding every motion (and their setpoint
tables), and there is nothing
else to plan or record. The executor streams a path through the same guard, monitors, stops and
telemetry as a trench job (see :mod:`rt_runtime.control.executor`). :meth:`PathJob.check`
refuses, before anything is sent, a path that leaves the joint ranges
(:class:`~rt_runtime.errors.JointLimitError`, from :mod:`rt_runtime.actuation`) or that is faster
than the rig's joint velocity, acceleration or jerk limits (:class:`~rt_runtime.errors.
PlanningError`: the guard would otherwise slow it down and it would trail its own timing), or
whose motions do not start and end at rest.
"""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import logging
import math
import multiprocessing
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from rt_runtime import actuation, axes, kinematics
from rt_runtime.control.setpoints import (
    CONNECT_TOLERANCE_M,
    KIND_PHASE,
    Phase,
    SampledMotion,
    connect_motion,
    sample_cycle,
    sample_motion,
    stroke_gap_m,
)
from rt_runtime.errors import ConfigurationError, ExcavatorRtError, PlanningError
from rt_runtime.planning.filewatch import WATCH_PERIOD_S, FileWatch
from rt_runtime.planning.trench import (
    ONESHOT_PLANNERS,
    TRANSITION_PENETRATION_M,
    Cycle,
    PlannedDig,
    Transition,
    TravelMove,
    TrenchPlanner,
    TrenchSession,
    TrenchTask,
)
from rt_runtime.rig import Rig

__all__ = [
    "AT_ENTRY_TOLERANCE_M",
    "MODELS_CHANGED_EXIT",
    "PLANNER_START_EXIT",
    "DigPlan",
    "InlinePlanner",
    "JointMotion",
    "PathJob",
    "PathLink",
    "PathPlan",
    "PendingScan",
    "PlannerError",
    "PlannerGone",
    "PlannerLink",
    "PlannerSpec",
    "PolynomialMotion",
    "ProcessPlanner",
    "Recorded",
    "SessionDriver",
]

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

#: Nice value of the planner process.
PLANNER_NICE = 10
#: A measured pose this close to a pose (largest stroke difference) is at it: a dig starts
#: directly from its entry, and the arm at the home pose needs no dump.
AT_ENTRY_TOLERANCE_M = 5e-4
#: A dig planned ahead that continues the bucket is taken where the load the measured path
#: left differs from the planned path's by at most this fraction of V_max (drives tracking
#: within a fraction of a mm leave ~0.1 %; on task A a path 2 mm off its plan, 0.8 %).
_AHEAD_LOAD_TOLERANCE = 0.005


@dataclass(frozen=True, slots=True)
class DigPlan:
    """The next dig and the moves around it: ``cycle`` then ``dig`` stream, ``exit`` only where
    no dig follows.

    Attributes:
        dig: The dig, or None when the task is done.
        cycle: The moves into the dig from where the arm is (:meth:`TrenchSession.cycle`):
            on the first request planned from the measured pose (a lift where the bucket is in
            or near the material, a dump unless the arm is at the home pose), later the
            session's cycle from the previous dig's exit (lift out, dump, approach, enter,
            blended where clear; no dump into a carried dig, whose cycle is kept on the first
            request too where the arm is at that exit), checked against the material before
            the dig; None when the arm is at the dig's entry (or no dig).
        exit: Lift-out and dump to the home pose (:meth:`TrenchSession.exit_transitions`):
            after the dig, checked against the material its planned path leaves (they are
            planned before it runs); with no dig, from where the arm is. The executor streams
            them only where no dig follows (the task is done, the last dig a job allows, a
            planning error).
        travel: Crawler moves the session put before the dig (the executor cannot drive them).
        plan_us: Wall time of the request (s * 1e6).
        sampled: The cycle and the dig in streaming order as setpoint tables on the loop's
            period grid, with CONNECT moves where two do not meet (empty when the driver has
            no period).
        exit_sampled: The exit moves as setpoint tables, chained from where :attr:`sampled`
            ends.
        planned_ahead: Planned while the dig before it ran, on the material that dig's planned
            path leaves, and taken after its record (:meth:`SessionDriver.lookahead`):
            ``plan_us`` is then the time to check it against the measured material.
    """

    dig: PlannedDig | None
    cycle: Cycle | None
    exit: tuple[Transition, ...]
    travel: tuple[TravelMove, ...]
    plan_us: float
    sampled: tuple[SampledMotion, ...] = ()
    exit_sampled: tuple[SampledMotion, ...] = ()
    planned_ahead: bool = False


@dataclass(frozen=True, slots=True)
class _Ahead:
    """A plan made ahead (:meth:`SessionDriver.lookahead`) by ``driver``, on a copy of the
    trench that recorded the pending dig ``index`` along its planned path (its height field
    is the planned one: only a record changes it)."""

    index: int
    driver: SessionDriver
    plan: DigPlan


@dataclass(frozen=True, slots=True)
class Recorded:
    """An executed dig recorded into the session.

    A path job's step (:attr:`PathJob.steps`) is recorded the same way: ``index`` the step's,
    no material (NaN), ``state`` ``{"steps_done": index + 1}``.

    Attributes:
        index: Dig index.
        measured_volume_m3: Material the measured path removed from the session's material.
        tip_path_m: Measured tip path, work-site frame, ``(n, 2)``.
        state: ``TrenchSession.state()`` after the record (JSON-able).
        step: A path step's kind (its record's ``dig_type``); empty for a dig.
        duration_s: A path step's length (s); NaN for a dig (its plan has it).
    """

    index: int
    measured_volume_m3: float
    tip_path_m: FloatArray
    state: dict[str, Any]
    step: str = ""
    duration_s: float = math.nan


@dataclass(frozen=True, slots=True)
class PlannerError:
    """A request failed (the message says which and why)."""

    message: str


@dataclass(frozen=True, slots=True)
class PlannerGone:
    """The planner process's last words before it ends on its own: why it cannot plan on
    (its model files changed on disk since they were verified). Not a reply to a request."""

    message: str


@runtime_checkable
class JointMotion(Protocol):
    """A joint motion the executor can stream: ``sample(t_s) -> (q, qd, qdd)`` for
    ``0 <= t_s <= duration_s`` (rad, rad/s, rad/s^2, each ``(n,)`` over the rig's axes in axis
    order: boom, stick, bucket, then swing on a rig with swing, :mod:`rt_runtime.axes`).
    Called once per cycle in the loop: it must be cheap."""

    @property
    def duration_s(self) -> float:
        """Length of the motion (s)."""
        ...

    def sample(self, t_s: float) -> tuple[Any, Any, Any]:
        """Joint position, velocity and acceleration at ``t_s`` (s from the motion's start)."""
        ...


class PolynomialMotion:
    """A piecewise polynomial joint path as a :class:`JointMotion` (loop-safe sampling).

    Wraps :class:`~rt_runtime.trajectory.mixed_order.PiecewisePolynomial` (three joints, rad):
    the position, velocity and acceleration tables of every piece are the path's own (built once
    with the path), so one :meth:`sample` is a bisection, one power vector and three small
    products (~5 us, against ~100 us for three ``PiecewisePolynomial.sample`` calls). Time 0 is
    the path's first knot.

    Args:
        path: The path (``n_joints == 3``).
        name: A label for reports.

    Raises:
        ConfigurationError: The path does not have three joints.
    """

    __slots__ = ("_durations", "_knots", "_starts", "_tables", "_width", "name", "path")

    def __init__(self, path: Any, name: str = "path") -> None:
        coef = np.asarray(path.u_coefficients, dtype=np.float64)  # (m, width, n_joints)
        if coef.ndim != 3 or coef.shape[2] != 3:
            raise ConfigurationError(
                f"a path motion needs three joints (boom, stick, bucket); got coefficients of "
                f"shape {coef.shape}"
            )
        self.path = path
        self.name = name
        knots = np.asarray(path.knots_s, dtype=np.float64)
        # The path's own tables (PiecewisePolynomial.__post_init__): tables[d, i, k, j] is the
        # coefficient of u**k in the d-th time derivative of piece i, joint j.
        self._tables = path._tables[:3]
        self._width = coef.shape[1]
        self._durations = path._durations_s
        self._starts = (knots - knots[0]).tolist()
        self._knots = knots

    @property
    def duration_s(self) -> float:
        """From the first to the last knot (s)."""
        return float(self._knots[-1] - self._knots[0])

    def sample(self, t_s: float) -> tuple[Any, Any, Any]:
        """``(q, qd, qdd)`` at ``t_s`` (clamped to the path; at a knot the right-hand piece)."""
        starts = self._starts
        m = len(starts) - 1
        t = min(max(float(t_s), 0.0), starts[-1])
        seg = min(max(bisect.bisect_right(starts, t) - 1, 0), m - 1)
        u = (t - starts[seg]) / self._durations[seg]
        powers = np.power(u, np.arange(self._width, dtype=np.float64))
        tab = self._tables
        return powers @ tab[0, seg], powers @ tab[1, seg], powers @ tab[2, seg]


#: Largest joint speed (rad/s) and acceleration (rad/s^2) at a path motion's ends that count as
#: rest.
PATH_REST_TOLERANCE = 1e-6


@dataclass(frozen=True, slots=True, eq=False)
class PathJob:
    """A prescribed joint path: motions streamed one after the other (see the module docstring).

    The executor connects its measured pose to the first motion's start with a ruckig move
    (phase CONNECT), and any two motions that do not meet likewise. Every motion starts and
    ends at rest (:meth:`check`), so a pause (which takes effect at motion boundaries) always
    holds the arm at rest.

    Attributes:
        motions: The motions, at least one.
        name: A label for reports.
        jerk_by_guard: The path bounds velocity and acceleration only (a minimum-time cubic
            spline through waypoints, Zhao eq 3, whose jerk is piecewise constant and
            unbounded by its planner): :meth:`check` leaves the jerk to the limit guard,
            which streams such a path within the jerk limits and trails it where it must.
        steps: Each motion is a step of a longer job (a taught trench's cycles) that the
            executor records when it has streamed it to its end (a :class:`Recorded` with
            ``state = {"steps_done": n}``), so a job cut short resumes at the step it was in.
            Motion ``i`` is step ``first_step + i``, named :attr:`step_name` in its record.
        first_step: The first motion's step index (a resumed job's steps done).
        step_name: The steps' kind in their records (the record's ``dig_type``).
        retreat: The move the arm makes first, from the pose it holds (axis order, rad),
            before the CONNECT move to the first motion: a motion starting at that pose, or
            None (connect straight). A taught trench resumed with the bucket in the ground
            lifts it out this way (:func:`rt_runtime.control.taught_path.lift_out`).
    """

    motions: tuple[JointMotion, ...]
    name: str = "path"
    jerk_by_guard: bool = False
    steps: bool = False
    first_step: int = 0
    step_name: str = "step"
    retreat: Callable[[FloatArray], JointMotion | None] | None = None

    def __post_init__(self) -> None:
        if len(self.motions) == 0:
            raise ConfigurationError("a path job needs at least one motion; got none")
        for i, motion in enumerate(self.motions):
            d = float(motion.duration_s)
            if not (math.isfinite(d) and d > 0.0):
                raise ConfigurationError(
                    f"path motion {i}: duration_s = {d}; allowed: a finite value > 0"
                )

    def check(self, rig: Rig, step_s: float = 1e-3) -> None:
        """Refuse a path the rig cannot follow, before anything is sent.

        Samples every motion every ``step_s`` (and at its end) and checks the joint ranges,
        the joint velocity, acceleration and jerk limits (velocity and acceleration to 1e-9
        relative, the rounding of a trajectory planned onto its limits; jerk as the difference
        of consecutive accelerations over the step, within 0.1 % headroom for that estimate)
        and rest at both ends.

        Args:
            rig: The rig.
            step_s: Sampling step (s), > 0.

        Raises:
            JointLimitError: A joint leaves its range (names the joint, value and range).
            PlanningError: A motion is faster than a joint limit, or does not start or end at
                rest (names the motion, joint, time and the allowed value).
            ConfigurationError: ``step_s`` is not > 0.
        """
        if not (math.isfinite(step_s) and step_s > 0.0):
            raise ConfigurationError(f"path check step_s = {step_s}; allowed: a finite value > 0")
        names = axes.names(rig)
        n_axes = len(names)
        _, _, qd_max, qdd_max, qddd_max = axes.joint_limits(rig)
        limits = (
            ("velocity", qd_max, "deg/s"),
            ("acceleration", qdd_max, "deg/s^2"),
            ("jerk", qddd_max, "deg/s^3"),
        )
        checked = limits[:2] if self.jerk_by_guard else limits
        for i, motion in enumerate(self.motions):
            duration = float(motion.duration_s)
            n = max(math.ceil(duration / step_s), 1)
            ts = np.linspace(0.0, duration, n + 1)
            rows = [motion.sample(float(t)) for t in ts]
            q = np.array([r[0] for r in rows], dtype=np.float64)
            qd = np.array([r[1] for r in rows], dtype=np.float64)
            qdd = np.array([r[2] for r in rows], dtype=np.float64)
            if (
                q.ndim != 2
                or q.shape[1] != n_axes
                or qd.shape != q.shape
                or qdd.shape != q.shape
            ):
                raise PlanningError(
                    f"path motion {i} samples joint states of shape {q.shape[1:]}; the rig "
                    f"{rig.name} has {n_axes} axes ({', '.join(names)})"
                )
            if not (np.isfinite(q).all() and np.isfinite(qd).all() and np.isfinite(qdd).all()):
                raise PlanningError(f"path motion {i} samples a non-finite joint state")
            # Raises JointLimitError naming the joint, the value and the range.
            axes.joint_to_actuator(rig, q, check_limits=True)
            jerk = np.diff(qdd, axis=0) / np.diff(ts)[:, None]
            for (what, limit, unit), values, slack in zip(
                checked, (qd, qdd, jerk), (1.0 + 1e-9, 1.0 + 1e-9, 1.001), strict=False
            ):
                peak = np.max(np.abs(values), axis=0)
                over = np.flatnonzero(peak > limit * slack)
                if over.size:
                    j = int(over[0])
                    k = int(np.argmax(np.abs(values[:, j])))
                    raise PlanningError(
                        f"path motion {i}: {names[j]} {what} {math.degrees(peak[j]):.3f} {unit} "
                        f"at t = {ts[min(k, len(ts) - 1)]:.3f} s exceeds the rig's limit "
                        f"{math.degrees(limit[j]):.3f} {unit}; allowed: a slower path (longer "
                        "durations)"
                    )
            for end, k in (("start", 0), ("end", -1)):
                v = float(np.max(np.abs(qd[k])))
                a = float(np.max(np.abs(qdd[k])))
                if v > PATH_REST_TOLERANCE or a > PATH_REST_TOLERANCE:
                    raise PlanningError(
                        f"path motion {i} does not {end} at rest (|qd| {v:.3g} rad/s, |qdd| "
                        f"{a:.3g} rad/s^2); allowed: <= {PATH_REST_TOLERANCE} (zero boundary "
                        "velocity and acceleration)"
                    )


@dataclass(frozen=True, slots=True)
class PathPlan:
    """The reply to a path job's plan request: every motion, in streaming order.

    Attributes:
        motions: The job's motions.
        name: The job's name.
        plan_us: Wall time of the request (s * 1e6: sampling the motions).
        sampled: The motions as setpoint tables, with CONNECT moves from the pose of the
            request and between motions that do not meet.
    """

    motions: tuple[JointMotion, ...]
    name: str
    plan_us: float = 0.0
    sampled: tuple[SampledMotion, ...] = ()


Reply = DigPlan | Recorded | PlannerError | PathPlan
#: Exit code of a planner process whose model files changed on disk (:class:`PlannerGone`).
MODELS_CHANGED_EXIT = 3
#: Exit code of a planner process that could not build its planner or trench
#: (:class:`PlannerGone`).
PLANNER_START_EXIT = 4


@dataclass(frozen=True, slots=True)
class PlannerSpec:
    """What a planner process needs to rebuild the planner (plain, picklable data).

    Attributes:
        rig: The rig.
        planner: One-shot planner name (:data:`~rt_runtime.planning.trench.ONESHOT_PLANNERS`).
        model_dir: PINN model directory.
        pso_options: Options of the PSO planner.
        max_digs: The planner's bound on digs per task.
        task: The task.
        period_s: The loop's period: the replies' motions are sampled on its grid.
        screening: The planner's screening (``network`` or ``geometric``), so that the
            process plans with the same candidates as the planner it rebuilds.
        soil: The minimum-torque planner's soil (None with another planner).
    """

    rig: Rig
    planner: str
    model_dir: str
    pso_options: dict[str, Any] = field(default_factory=dict)
    max_digs: int | None = 40
    task: TrenchTask | None = None
    period_s: float | None = None
    screening: str = "auto"
    soil: str | None = None

    @classmethod
    def of(cls, session: TrenchSession, period_s: float | None = None) -> PlannerSpec:
        """The spec of ``session``'s planner.

        Raises:
            ConfigurationError: The session uses a one-shot planner object other than the
                built-in ones (:data:`~rt_runtime.planning.trench.ONESHOT_PLANNERS`: it cannot
                be rebuilt in another process).
        """
        planner = session.planner
        name = planner.oneshot.name
        if name not in ONESHOT_PLANNERS:
            raise ConfigurationError(
                f"one-shot planner {name!r} cannot run in a planner process; allowed: "
                f"{', '.join(ONESHOT_PLANNERS)} (or plan in-process: "
                "ExecutorConfig(plan_in_worker=False))"
            )
        return cls(
            rig=session.rig,
            planner=name,
            model_dir=str(planner.model_dir),
            pso_options=dict(planner.pso_options),
            max_digs=planner.max_digs,
            task=session.task,
            period_s=period_s,
            screening=planner.screening,
            soil=planner.soil,
        )


@dataclass(frozen=True, slots=True)
class PendingScan:
    """A scan that a scanner takes after the dig ended and hands over later, off the loop's
    thread (a real-time HIL's scanner in another process, a scanner on its own link).

    Attributes:
        fetch: Waits for the scan (its own bound on the wait) and returns ``(x_m, y_m)``, or
            None where none came in time (the next dig is then planned on the tip paths).
            :class:`ProcessPlanner` calls it on its sender thread before the record leaves
            for the planner process, which plans the next dig once the scan is there (the
            arm holds at the exit meanwhile); an in-process link calls it as it records.
    """

    fetch: Callable[[], tuple[FloatArray, FloatArray] | None]


#: A profile scanner's surface measured after the dig just recorded ended, ``(x_m, y_m)``
#: (work-site frame), a :class:`PendingScan` for one still to come, or None where it has none
#: that recent (the next dig is then planned on the tip paths): a scan from before the dig
#: ended would put back what the dig removed. Asked as each record is queued, on the caller's
#: thread (the loop's): it must return at once.
SurfaceSource = Callable[[], "tuple[FloatArray, FloatArray] | PendingScan | None"]


def _surface_arrays(surface: tuple[FloatArray, FloatArray]) -> tuple[FloatArray, FloatArray]:
    x, y = surface
    return np.array(x, dtype=np.float64), np.array(y, dtype=np.float64)


def _fetched(pending: PendingScan) -> tuple[FloatArray, FloatArray] | None:
    """The pending scan's surface, or None where it raised (logged: the next dig is then
    planned on the tip paths, as without a scanner)."""
    try:
        surface = pending.fetch()
    except Exception:
        log.exception("the profile scanner's surface could not be fetched")
        return None
    return None if surface is None else _surface_arrays(surface)


class SessionDriver:
    """The executor's two requests on a session (see the module docstring).

    Args:
        session: The session (may hold a pending dig, which is then the next dig).
        period_s: The loop's period: each :class:`DigPlan` carries its motions sampled on this
            grid (:attr:`DigPlan.sampled`), chained from the pose of the first request; None:
            not sampled.
        surface_source: A profile scanner's latest measured surface, ``(x_m, y_m)`` in the
            work-site frame, a :class:`PendingScan` (fetched here) or None when it has none,
            asked after each :meth:`record`: the next dig is planned on it
            (:meth:`TrenchSession.observe_surface`). None: no scanner, the trench is planned
            from the measured tip paths alone.
    """

    def __init__(
        self,
        session: TrenchSession,
        period_s: float | None = None,
        surface_source: SurfaceSource | None = None,
    ) -> None:
        self.session = session
        self.rig = session.rig
        self.period_s = period_s
        self.surface_source = surface_source
        #: Where the last motion handed out ends (the next plan's motions start there).
        self._end_rad: FloatArray | None = None
        #: The next plan, made ahead while the pending dig runs (:meth:`lookahead`).
        self._ahead: _Ahead | None = None

    def lookahead(self) -> bool:
        """Plan the dig after the pending one now, while the pending one runs: on a copy of
        the session that records the pending dig along its planned path. The next
        :meth:`plan` after the real :meth:`record` takes it where the measured material
        allows (:meth:`_take_ahead`), else plans as always. Whether a plan was made (not
        without a pending dig or a period, or where the copy's planning fails).

        Only a driver that owns its session may look ahead (the planner process's): taking
        the plan replaces :attr:`session` by the copy.
        """
        self._ahead = None
        s = self.session
        dig = s.pending
        if dig is None or self.period_s is None:
            return False
        try:
            copy = TrenchSession.restore(s.planner, s.task, s.state())
            assert copy.pending is not None
            copy.record(copy.pending, copy.pending.tip_path_m)
            driver = SessionDriver(copy, self.period_s)
            driver._end_rad = self._end_rad
            plan = driver.plan(None)
        except ExcavatorRtError:
            return False
        if plan.dig is None or plan.travel:
            return False  # the end of the task, or a section change: planned as always
        self._ahead = _Ahead(dig.index, driver, plan)
        return True

    def _take_ahead(self, t0: float) -> DigPlan | None:
        """The plan made ahead, where it holds on the measured material; None otherwise.

        It holds where the dig it followed was recorded (and nothing since) and its moves stay
        within :data:`TRANSITION_PENETRATION_M` on the measured material: a point's depth
        below the height field, and so its allowances, move by at most the largest difference
        between the measured and the planned field, so a move's penetration moves by at most
        twice that. Beyond that bound (a near-vertical stretch of a path between two grid
        columns can differ by cm in one column) the moves are checked again on the measured
        material, exactly: a blended cycle (:meth:`TrenchSession.blend_clear`), the exit moves
        planned again (they must be the same moves); a few ms against a plan's 0.1-0.3 s.
        The session then continues from the copy, with the measured material.
        """
        ahead, self._ahead = self._ahead, None
        s = self.session
        if ahead is None or s.pending is not None or not s.digs:
            return None
        if s.digs[-1].index != ahead.index:
            return None
        copy = ahead.driver.session
        plan = ahead.plan
        if plan.dig is not None and plan.dig.joined:
            # A dig that continues the bucket was fitted to the load the planned path left:
            # taken where the measured path left that load, within _AHEAD_LOAD_TOLERANCE.
            held, planned = s.joinable, copy.joinable
            if held is None or planned is None:
                return None
            if abs(held[1] - planned[1]) > _AHEAD_LOAD_TOLERANCE * s.v_max_m3:
                return None
            copy.joinable = held
        delta = float(np.max(np.abs(s.surface - copy.surface)))
        limit = TRANSITION_PENETRATION_M - 2.0 * delta
        copy.material, copy.surface = s.material, s.surface.copy()
        cycle, exits = plan.cycle, plan.exit
        try:
            if cycle is not None and cycle.penetration_m > limit:
                # Beyond the bound: the blend checked again on the measured material, exactly.
                depth = copy.blend_clear(cycle)
                if depth is None:
                    raise PlanningError("the cycle planned ahead is not clear")
                cycle = dataclasses.replace(cycle, penetration_m=depth)
            if max((m.penetration_m for m in exits), default=0.0) > limit:
                # The exit moves planned again on the measured material: the same moves, or
                # the plan is not taken (their setpoint tables are the plan's).
                dig = copy.pending
                assert dig is not None
                exits = copy.exit_transitions(dig.problem.q_end_rad, after=dig)
                if [(m.q_from_rad, m.q_to_rad) for m in exits] != [
                    (m.q_from_rad, m.q_to_rad) for m in plan.exit
                ]:
                    raise PlanningError("the exit moves planned ahead changed")
        except PlanningError:
            return None  # the copy goes with it
        if cycle is not None and cycle is not plan.cycle:
            at = next(i for i, st in enumerate(copy.steps) if st is plan.cycle)
            copy.steps[at] = cycle
        self.session = copy
        self._end_rad = ahead.driver._end_rad
        return dataclasses.replace(
            plan,
            cycle=cycle,
            exit=exits,
            plan_us=(time.perf_counter() - t0) * 1e6,
            planned_ahead=True,
        )

    def plan(self, q_from_rad: FloatArray | None = None) -> DigPlan:
        """The next dig and its moves (see :class:`DigPlan`).

        Args:
            q_from_rad: The measured pose on the first request (the cycle from it and the
                at-entry check), None afterwards (the arm is at the previous dig's exit).

        Raises:
            PlanningError: From the session (no verified dig; a move that cannot be planned).
        """
        t0 = time.perf_counter()
        if q_from_rad is None and self._ahead is not None:
            ahead = self._take_ahead(t0)
            if ahead is not None:
                return ahead
        self._ahead = None
        s = self.session
        if (
            q_from_rad is not None
            and s.joinable is not None
            and not self._at(np.asarray(q_from_rad, dtype=np.float64), s.joinable[0])
        ):
            # The arm left the last dig's exit (a job that ended there dumped its bucket, the
            # cycle from the measured pose dumps): the next dig, or the pending one, holds no
            # load of the dig before it.
            s.joinable = None
        dig = s.pending if s.pending is not None else s.next_dig()
        tail: list[Any] = []
        for step in reversed(s.steps):
            if isinstance(step, PlannedDig):
                break
            tail.append(step)
        tail.reverse()
        cycle = next((c for c in reversed(tail) if isinstance(c, Cycle)), None)
        travel = tuple(t for t in tail if isinstance(t, TravelMove))
        home = np.asarray(s.planner.home_pose_rad, dtype=np.float64)
        if q_from_rad is not None:
            q0 = np.asarray(q_from_rad, dtype=np.float64)
            self._end_rad = q0
            if dig is not None and self._at(q0, np.asarray(dig.problem.q_start_rad)):
                cycle = None
            elif (
                dig is not None
                and dig.carried
                and cycle is not None
                and self._at(q0, np.asarray(cycle.waypoints_rad[0], dtype=np.float64))
            ):
                pass  # at the exit the load is carried from: the session's carry cycle
            elif dig is not None:
                cycle = s.cycle(q0, dig, dump=not self._at(q0, home))
        if dig is not None:
            exit_moves = s.exit_transitions(dig.problem.q_end_rad, after=dig)
            end: FloatArray | None = np.asarray(dig.problem.q_end_rad, dtype=np.float64)
        else:
            end = self._end_rad if self._end_rad is not None else s.q_now
            exit_moves = () if end is None or self._at(end, home) else s.exit_transitions(end)
            end = home if exit_moves else end
        sampled, exit_sampled, chained = self._sample(dig, cycle, exit_moves)
        # Where the handed-out motions end (the next plan's start there): the dig's exit, or
        # with no dig the end of the exit moves, which then stream.
        self._end_rad = chained if chained is not None else end
        return DigPlan(
            dig,
            cycle,
            exit_moves,
            travel,
            (time.perf_counter() - t0) * 1e6,
            sampled,
            exit_sampled,
        )

    def _sample(
        self,
        dig: PlannedDig | None,
        cycle: Cycle | None,
        exit_moves: tuple[Transition, ...],
    ) -> tuple[tuple[SampledMotion, ...], tuple[SampledMotion, ...], FloatArray | None]:
        """The plan's motions and its exit moves on the period grid, chained from where the
        last motion handed out ended (the exit from where the plan's motions end), and the
        pose where the handed-out motions end (None without a period)."""
        period = self.period_s
        if period is None:
            return (), (), None
        rig = self.rig

        def move(t: Transition) -> SampledMotion:
            return connect_motion(rig, period, t.q_from_rad, t.q_to_rad, KIND_PHASE[t.kind])

        out: list[SampledMotion] = []
        if cycle is not None:
            out.extend(move(t) for t in cycle.moves)
            if cycle.blended:
                out.append(sample_cycle(rig, period, cycle))
        if dig is not None:
            out.append(
                sample_motion(
                    rig, period, Phase.DIG, dig.T_s, dig.trajectory().sample, dig_index=dig.index
                )
            )
        out, end = chain(rig, period, self._end_rad, out)
        exits, exit_end = chain(rig, period, end, [move(t) for t in exit_moves])
        return tuple(out), tuple(exits), end if dig is not None else exit_end

    def _at(self, q_a: FloatArray, q_b: FloatArray) -> bool:
        return stroke_gap_m(self.rig, q_a, q_b) <= AT_ENTRY_TOLERANCE_M

    def record(self, strokes_m: FloatArray) -> Recorded:
        """Record the pending dig from the drives' reported strokes ``(n, 3)`` (SYNC order).

        Raises:
            PlanningError: No dig is pending, or fewer than two finite samples.
        """
        s = self.session
        dig = s.pending
        if dig is None:
            raise PlanningError("no dig is pending: nothing to record")
        strokes = np.asarray(strokes_m, dtype=np.float64).reshape(-1, 3)
        q = actuation.stroke_to_joint(self.rig, strokes, check_limits=False)
        tip = np.asarray(kinematics.forward(self.rig, q), dtype=np.float64)[..., :2]
        tip = tip.reshape(-1, 2)
        tip = tip[np.isfinite(tip).all(axis=1)]
        tip[:, 0] += dig.machine_x_m
        volume = s.record(dig, tip)
        if self.surface_source is not None:
            measured = self.surface_source()
            if isinstance(measured, PendingScan):
                measured = _fetched(measured)
            if measured is not None:
                s.observe_surface(*measured)
                # A plan made ahead chose its dig's fill on the predicted material; what the
                # scanner saw (slumped, fallen back) can hold more or less: planned again.
                self._ahead = None
        return Recorded(dig.index, volume, tip, s.state())


def chain(
    rig: Rig, period_s: float, q_at_rad: FloatArray | None, motions: list[SampledMotion]
) -> tuple[list[SampledMotion], FloatArray | None]:
    """``motions`` with a CONNECT move before each one that does not start where the arm is
    (``q_at_rad``, then the end of the motion before it), and the pose where the last ends.

    Raises:
        PlanningError: ruckig cannot plan a connecting move.
    """
    out: list[SampledMotion] = []
    at = q_at_rad
    for m in motions:
        if at is not None and stroke_gap_m(rig, at, m.q_start_rad) > CONNECT_TOLERANCE_M:
            out.append(connect_motion(rig, period_s, at, m.q_start_rad))
        out.append(m)
        at = m.q_rad[-1]
    return out, at


class PlannerLink(Protocol):
    """The job's side of a planner: requests, then one non-blocking :meth:`poll` a cycle.

    A request only queues work; the work runs in a planner process or, for links that answer
    in-process, in :meth:`service`, which the controller manager calls between cycles (never
    inside one).
    """

    def request_plan(self, q_from_rad: FloatArray | None) -> None:
        """Ask for the next :class:`DigPlan`."""
        ...

    def request_record(self, strokes_m: FloatArray, plan_next: bool) -> None:
        """Record the pending dig (then plan the next one when ``plan_next``)."""
        ...

    def poll(self) -> Reply | None:
        """The next reply, or None (never waits)."""
        ...

    def service(self) -> None:
        """Run queued in-process work (between cycles; nothing for a process)."""
        ...

    def close(self) -> None:
        """Release the planner (outside the loop)."""
        ...


class _AnsweredLink:
    """A link that answers its requests in-process in :meth:`service` (on the thread that calls
    it, between cycles): the requests wait in one queue, the replies in another for
    :meth:`poll`; nothing to release."""

    def __init__(self) -> None:
        self._requests: deque[tuple[Any, ...]] = deque()
        self._replies: deque[Reply] = deque()

    def poll(self) -> Reply | None:
        """The oldest reply, or None."""
        return self._replies.popleft() if self._replies else None

    def service(self) -> None:
        """Answer every queued request."""
        while self._requests:
            request = self._requests.popleft()
            self._answer(request)

    def _answer(self, request: tuple[Any, ...]) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """Nothing to release."""


class InlinePlanner(_AnsweredLink):
    """Runs the trench's requests in-process in :meth:`service` (simulated clock:
    deterministic, time stands still while it plans).

    Args:
        trench: The trench being dug (a :class:`TrenchSession`).
        period_s: The loop's period (see :class:`SessionDriver`).
        surface_source: A profile scanner (see :class:`SessionDriver`), or None.
    """

    def __init__(
        self,
        trench: TrenchSession,
        period_s: float | None = None,
        surface_source: SurfaceSource | None = None,
    ) -> None:
        super().__init__()
        self.driver = SessionDriver(trench, period_s, surface_source)

    def _run(self, fn: Any, *args: Any) -> None:
        try:
            self._replies.append(fn(*args))
        except ExcavatorRtError as exc:
            self._replies.append(PlannerError(str(exc)))

    def request_plan(self, q_from_rad: FloatArray | None) -> None:
        """Queue a plan request (answered in :meth:`service`)."""
        self._requests.append(("plan", None if q_from_rad is None else np.array(q_from_rad)))

    def request_record(self, strokes_m: FloatArray, plan_next: bool) -> None:
        """Queue a record request (then a plan when ``plan_next`` and the record succeeds)."""
        self._requests.append(("record", np.array(strokes_m, dtype=np.float64), plan_next))

    def _answer(self, request: tuple[Any, ...]) -> None:
        if request[0] == "plan":
            self._run(self.driver.plan, request[1])
            return
        self._run(self.driver.record, request[1])
        if request[2] and not isinstance(self._replies[-1], PlannerError):
            self._run(self.driver.plan, None)


class PathLink(_AnsweredLink):
    """The planner link of a :class:`PathJob`: hands out its motions once (inline, any clock).

    The first :meth:`request_plan` is answered with a :class:`PathPlan`; a later one with an
    empty plan (nothing left). :meth:`request_record` records the next step of a job with
    :attr:`PathJob.steps` (the executor asks as each step's motion ends, in order), and is
    answered with a :class:`PlannerError` for any other path (it has nothing to record).

    Args:
        job: The path.
        rig: The rig, and ``period_s`` the loop's period: with both, the reply carries the
            motions sampled (:attr:`PathPlan.sampled`), chained from the pose of the request.
    """

    def __init__(self, job: PathJob, rig: Rig | None = None, period_s: float | None = None) -> None:
        super().__init__()
        self.job = job
        self.rig = rig
        self.period_s = period_s
        self._handed_out = False
        self._next_step = job.first_step

    def request_plan(self, q_from_rad: FloatArray | None) -> None:
        """Queue the path's motions (first request) or an empty plan (later ones)."""
        q = None if q_from_rad is None else np.array(q_from_rad, dtype=np.float64)
        self._requests.append(("plan", q))

    def request_record(self, strokes_m: FloatArray, plan_next: bool) -> None:
        """Record the next step (a path with steps), else answered with a
        :class:`PlannerError`."""
        self._requests.append(("record",))

    def _answer(self, request: tuple[Any, ...]) -> None:
        job = self.job
        if request[0] == "record":
            self._replies.append(self._record())
            return
        t0 = time.perf_counter()
        motions = () if self._handed_out else job.motions
        self._handed_out = True
        sampled: tuple[SampledMotion, ...] = ()
        if self.rig is not None and self.period_s is not None and motions:
            rig, period = self.rig, self.period_s
            try:
                tables = [
                    sample_motion(
                        rig,
                        period,
                        Phase.PATH,
                        m.duration_s,
                        m.sample,
                        dig_index=job.first_step + i if job.steps else -1,
                    )
                    for i, m in enumerate(motions)
                ]
                at = request[1]
                back = None if at is None or job.retreat is None else job.retreat(at)
                if back is not None:
                    tables.insert(
                        0,
                        sample_motion(rig, period, Phase.CONNECT, back.duration_s, back.sample),
                    )
                sampled = tuple(chain(rig, period, at, tables)[0])
            except ExcavatorRtError as exc:
                self._replies.append(PlannerError(str(exc)))
                return
        self._replies.append(PathPlan(motions, job.name, (time.perf_counter() - t0) * 1e6, sampled))

    def _record(self) -> Recorded | PlannerError:
        """The next step's record (see :attr:`PathJob.steps`)."""
        job = self.job
        step = self._next_step
        i = step - job.first_step
        if not job.steps or not 0 <= i < len(job.motions):
            return PlannerError(f"path job {job.name!r} has no step {step} to record")
        self._next_step += 1
        return Recorded(
            index=step,
            measured_volume_m3=math.nan,
            tip_path_m=np.zeros((0, 2)),
            state={"steps_done": step + 1},
            step=job.step_name,
            duration_s=float(job.motions[i].duration_s),
        )


# -- the planner process --------------------------------------------------------------------------


def _worker_main(conn: Any, spec: PlannerSpec) -> None:
    """Entry point of the planner process: rebuild planner and session, serve requests.

    The first message is ``("init", state)``: the session state to continue from (None: a
    fresh session). It comes over the pipe, not as a process argument: with the ``spawn``
    start method the arguments are written to the child's pipe inside ``Process.start()``,
    which blocks until the child reads them once they pass the pipe buffer (64 KiB; a long
    job's state is larger).
    """
    with contextlib.suppress(AttributeError, OSError, PermissionError):
        # Never inherit a real-time policy from whoever started us: planning is background work.
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    try:
        first = conn.recv()
    except (EOFError, OSError):
        conn.close()
        return
    state: dict[str, Any] | None = first[1] if first[0] == "init" else None
    try:
        planner = TrenchPlanner(
            spec.rig,
            spec.planner,
            model_dir=spec.model_dir,
            pso_options=spec.pso_options or None,
            max_digs=spec.max_digs,
            screening=spec.screening,
            soil=spec.soil,
        )
        assert spec.task is not None
        trench = (
            planner.start(spec.task)
            if state is None
            else TrenchSession.restore(planner, spec.task, state)
        )
        driver = SessionDriver(trench, spec.period_s)
    except ExcavatorRtError as exc:
        # Its files (a model that fails its card's digest, say) or the state it was handed:
        # the job cannot go on until the cause is cleared, and the process says why.
        with contextlib.suppress(EOFError, OSError):
            conn.send(PlannerGone(f"planner process could not start: {exc}"))
        conn.close()
        raise SystemExit(PLANNER_START_EXIT) from None

    def reply(work: Callable[..., Any], arg: Any) -> tuple[bool, bool]:
        """Send what ``work(arg)`` returns, or the error it raised: whether the pipe is still open
        (not where the job's side is gone: a stopped job, a daemon that ended) and whether
        ``work`` succeeded."""
        done = False
        try:
            answer, done = work(arg), True
        except ExcavatorRtError as exc:
            answer = PlannerError(str(exc))
        except Exception as exc:  # keep the process answering; the executor stops the job
            answer = PlannerError(f"planner process: {type(exc).__name__}: {exc}")
        try:
            conn.send(answer)
        except (EOFError, OSError):
            return False, done
        return True, done

    # A planner screening geometrically loaded no network: no model files to watch.
    watch = FileWatch(planner.pinn.verified_files() if planner.pinn is not None else ())
    while True:
        try:
            ready = conn.poll(WATCH_PERIOD_S)
            changed = watch.changed()
            if changed is not None:
                # What was verified is no longer what is on disk: plan nothing more from it.
                with contextlib.suppress(EOFError, OSError):
                    conn.send(PlannerGone(f"the planner's model files: {changed}"))
                conn.close()
                raise SystemExit(MODELS_CHANGED_EXIT)
            if not ready:
                continue
            message = conn.recv()
        except (EOFError, OSError):
            break
        kind = message[0]
        if kind == "stop":
            break
        if kind == "plan":
            open_, planned = reply(driver.plan, message[1])
        elif kind == "record":
            # The scanner's surface of the record comes with it (ProcessPlanner.request_record).
            scan = message[3] if len(message) > 3 else None
            driver.surface_source = None if scan is None else lambda scan=scan: scan
            open_, recorded = reply(driver.record, message[1])
            planned = False
            if open_ and recorded and message[2]:
                open_, planned = reply(driver.plan, None)
        else:
            continue
        if not open_:
            break
        if planned:
            # While the dig just handed out runs: the next one, taken at its record if the
            # measured material allows.
            try:
                driver.lookahead()
            except Exception:  # a plan made ahead is an optimisation; planning goes on
                log.exception("planning ahead failed")
    conn.close()


class ProcessPlanner:
    """The trench being dug, continued in a planner process (real-time clock; see the module
    docstring).

    A sender thread writes the requests to the pipe and a receiver thread reads and unpickles
    the replies (a plan's setpoint tables are hundreds of kB), so the loop's thread only puts
    and takes queue items.

    Args:
        trench: The trench to continue (its state, pending dig included, is copied over; the
            object itself is not touched while the process runs).
        spec: How to rebuild the planner; default :meth:`PlannerSpec.of` the trench.
        period_s: The loop's period (replies carry their motions sampled on its grid), when
            ``spec`` is not given.
        surface_source: A profile scanner (see :class:`SessionDriver`), or None. It is asked
            on the caller's thread as each record is queued (it must return the scan it holds
            or a :class:`PendingScan`, never wait for one), and its surface goes to the
            process with the record (a pending one once the sender thread has fetched it).

    Raises:
        ConfigurationError: The trench's planner cannot be rebuilt in another process.
    """

    def __init__(
        self,
        trench: TrenchSession,
        spec: PlannerSpec | None = None,
        period_s: float | None = None,
        surface_source: SurfaceSource | None = None,
    ) -> None:
        self.spec = spec if spec is not None else PlannerSpec.of(trench, period_s)
        self._surface_source = surface_source
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=True)
        self._outbox: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._inbox: queue.SimpleQueue[Reply] = queue.SimpleQueue()
        self._closing = False
        #: Why the process ended on its own (:class:`PlannerGone`), once it said so.
        self.last_words: str | None = None
        # The state goes first through the sender thread (see _worker_main), so start()
        # returns once the child is spawned, whatever the size of the job.
        self._outbox.put(("init", trench.state()))
        self._process = ctx.Process(
            target=_worker_main,
            args=(child, self.spec),
            name="excavator-planner",
            daemon=True,
        )
        self._process.start()
        child.close()
        if self._process.pid is not None:
            with contextlib.suppress(OSError):
                # Planning is background work: the loop, the drives' bus and (on a test
                # machine) the HIL come first, also while the process imports and loads models.
                os.setpriority(os.PRIO_PROCESS, self._process.pid, PLANNER_NICE)
        self._sender = threading.Thread(target=self._send_loop, name="planner-send", daemon=True)
        self._sender.start()
        self._receiver = threading.Thread(
            target=self._receive_loop, name="planner-receive", daemon=True
        )
        self._receiver.start()

    def _send_loop(self) -> None:
        while True:
            item = self._outbox.get()
            if item is None:
                break
            if item[0] == "record" and isinstance(item[3], PendingScan):
                item = (*item[:3], _fetched(item[3]))
            try:
                self._conn.send(item)
            except (OSError, ValueError):
                break

    def _receive_loop(self) -> None:
        while True:
            try:
                reply: Reply = self._conn.recv()
            except (EOFError, OSError) as exc:
                if not self._closing:
                    why = self.last_words or repr(exc)
                    self._inbox.put(PlannerError(f"the planner process ended: {why}"))
                break
            if isinstance(reply, PlannerGone):
                self.last_words = reply.message
                continue
            self._inbox.put(reply)

    def request_plan(self, q_from_rad: FloatArray | None) -> None:
        """Queue a plan request (loop safe: a queue put)."""
        q = None if q_from_rad is None else np.array(q_from_rad, dtype=np.float64)
        self._outbox.put(("plan", q))

    def request_record(self, strokes_m: FloatArray, plan_next: bool) -> None:
        """Queue a record request (loop safe: a copy of the strokes and a queue put), with the
        profile scanner's surface where there is one (a :class:`PendingScan` is fetched on
        the sender thread, and the record leaves once it is there)."""
        surface = self._surface_source() if self._surface_source is not None else None
        if surface is not None and not isinstance(surface, PendingScan):
            surface = _surface_arrays(surface)
        self._outbox.put(("record", np.array(strokes_m, dtype=np.float64), plan_next, surface))

    def poll(self) -> Reply | None:
        """One reply if the receiver has one (never waits); a PlannerError once the process
        is gone."""
        try:
            return self._inbox.get_nowait()
        except queue.Empty:
            return None

    def service(self) -> None:
        """Nothing: the process works on its own."""

    @property
    def pid(self) -> int | None:
        """The planner process's id (None before it started)."""
        return self._process.pid

    def exit_code(self) -> int | None:
        """The planner process's exit code once it has ended (negative: the signal that ended
        it), None while it runs. Any thread; one ``waitpid`` (not inside the cycle's step)."""
        return self._process.exitcode

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the process (outside the loop): ask, wait ``timeout_s``, then terminate."""
        self._closing = True
        self._outbox.put(("stop",))
        self._outbox.put(None)
        self._sender.join(timeout_s)
        self._process.join(timeout_s)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(timeout_s)
        self._conn.close()
        self._receiver.join(timeout_s)
