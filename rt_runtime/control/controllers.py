"""Controllers: what turns the drives' feedback into the next command, one cycle at a time
(ros2_control's controller interface), and the limit guard every command passes.

A controller has :meth:`Controller.update` ``(t_s, period_s, feedback) -> (Command, Status)``:
called once per cycle by the :class:`~rt_runtime.control.manager.ControllerManager` after the
drives answered the cycle's SYNC, it returns the target for the next SYNC and whether it is
still running. It never plans, blocks or raises: work that takes longer than a cycle (plans,
moves between plans) is prepared outside the loop (:meth:`Controller.service`, called between
cycles, and the planner process).

A :class:`Command` is the target stroke state one period ahead (stroke, rate, acceleration),
its mode (track it, or stop) and what the telemetry records with it (phase, motion, dig,
joint reference). :class:`GuardFilter` passes it through the ruckig limit guard
(:class:`~rt_runtime.control.guard.LimitGuard`): a verified plan passes unchanged, anything
else is limited, and STOP is the guard's jerk-limited stop from the commanded state.

:class:`HoldController` holds the last commanded stroke between jobs and, on a drive fault,
EMCY or lost heartbeat, quick-stops every drive once (the master's own reaction is off while
the controllers run). Asked to power down (:meth:`HoldController.power_down`), it disables every
drive and ends once none reports OPERATION_ENABLED, or after a timeout, SYNC going on meanwhile.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import IntEnum
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from rt_runtime.canbus import CycleStatus, DriveState
from rt_runtime.control.guard import GuardState, LimitGuard
from rt_runtime.control.hardware import DriveFeedback
from rt_runtime.control.setpoints import Phase

__all__ = [
    "Command",
    "Controller",
    "ControllerStatus",
    "GuardFilter",
    "HoldController",
    "Mode",
]

FloatArray = NDArray[np.float64]


class Mode(IntEnum):
    """What the guard does with a command."""

    #: Track the target state.
    TRACK = 0
    #: The guard's jerk-limited stop from the commanded state (the target is ignored).
    STOP = 1


class ControllerStatus(IntEnum):
    """What a controller's update says about itself."""

    RUNNING = 0
    #: Done: its last command was the last (the manager ends or switches at this boundary).
    ENDED = 1


class Command:
    """A controller's target for the next SYNC (reused by its controller; see the module
    docstring).

    Attributes:
        mode: TRACK or STOP.
        stroke_m, rate_m_s, accel_m_s2: Target actuator state ``(n,)`` in axis order (stroke m,
            m/s, m/s^2; the swing's rad, rad/s, rad/s^2: :mod:`rt_runtime.axes`).
        q_rad: The joint reference of the target (rad), for the telemetry.
        phase: :class:`~rt_runtime.control.setpoints.Phase` value (telemetry ``phase``).
        segment: Motion number, -1 while holding or stopping.
        dig: Dig index during a dig, else -1.
        tracking: The target streams a plan's motion.
        quick_stop: Quick-stop every drive with this command (once).
        disable: Disable every drive's power stage with this command (once; axes at rest).
    """

    __slots__ = (
        "accel_m_s2",
        "dig",
        "disable",
        "mode",
        "phase",
        "q_rad",
        "quick_stop",
        "rate_m_s",
        "segment",
        "stroke_m",
        "tracking",
    )

    def __init__(self, n: int = 3) -> None:
        self.mode = Mode.TRACK
        self.stroke_m: FloatArray = np.zeros(n)
        self.rate_m_s: FloatArray = np.zeros(n)
        self.accel_m_s2: FloatArray = np.zeros(n)
        self.q_rad: FloatArray = np.zeros(n)
        self.phase = int(Phase.WAIT)
        self.segment = -1
        self.dig = -1
        self.tracking = False
        self.quick_stop = False
        self.disable = False

    def hold(self, stroke_m: FloatArray, q_rad: FloatArray, phase: Phase) -> None:
        """Hold ``stroke_m`` at rest."""
        self.mode = Mode.TRACK
        self.stroke_m[:] = stroke_m
        self.rate_m_s[:] = 0.0
        self.accel_m_s2[:] = 0.0
        self.q_rad[:] = q_rad
        self.phase = int(phase)
        self.segment = -1
        self.dig = -1
        self.tracking = False


class Controller(Protocol):
    """A controller the manager runs (see the module docstring)."""

    def update(
        self, t_s: float, period_s: float, feedback: DriveFeedback
    ) -> tuple[Command, ControllerStatus]:
        """The command for the next SYNC from the feedback answering this one."""
        ...

    def service(self) -> None:
        """Work between cycles (never inside one): in-process planning, for example."""
        ...

    def fail(self, text: str) -> tuple[Command, ControllerStatus]:
        """Its update raised (a bug): the command that stops the drives safely from here."""
        ...

    def overrun(self, consecutive: int, lateness_s: float) -> None:
        """The loop's overrun policy asks for a safe stop."""
        ...


class GuardFilter:
    """The limit guard as the filter every command passes (see the module docstring).

    Args:
        guard: The guard (its commanded state is the drives' target).
    """

    def __init__(self, guard: LimitGuard) -> None:
        self.guard = guard

    @property
    def position_m(self) -> FloatArray:
        """The filtered target stroke (m)."""
        return self.guard.position_m

    @property
    def velocity_m_s(self) -> FloatArray:
        """The filtered stroke rate (m/s)."""
        return self.guard.velocity_m_s

    @property
    def at_rest(self) -> bool:
        """The commanded state is at rest."""
        return self.guard.at_rest

    def apply(self, command: Command) -> GuardState:
        """Filter one command (loop safe)."""
        guard = self.guard
        if command.mode is Mode.STOP:
            guard.stop()
            return guard.step_stop()
        return guard.track(command.stroke_m, command.rate_m_s, command.accel_m_s2)


class HoldController:
    """Holds a stroke between jobs; quick-stops every drive once on a fault (see the module
    docstring).

    Args:
        stroke_m: The actuator positions to hold, ``(n,)`` in axis order: the last commanded.
        q_rad: Its joint pose (telemetry).
        settled_m: How close to the held stroke the drives' report counts as settled (m).
        describe: Text of the drives' state for the fault message (axes, nodes, EMCY codes;
            :meth:`~rt_runtime.control.hardware.DriveInterface.describe`); None: the cycle
            status's name.

    Attributes:
        fault: Empty, or what the drives reported when it quick-stopped them.
        settled: The drives' last fresh report was within ``settled_m`` of the held stroke.
    """

    def __init__(
        self,
        stroke_m: FloatArray,
        q_rad: FloatArray,
        settled_m: float = 2e-6,
        describe: Callable[[CycleStatus], str] | None = None,
    ) -> None:
        hold = np.asarray(stroke_m, dtype=np.float64)
        self.command = Command(len(hold))
        self.command.hold(hold, q_rad, Phase.WAIT)
        self.settled_m = float(settled_m)
        self._describe = describe
        self.fault = ""
        self.settled = False
        self._power_down_timeout_s: float | None = None  # asked to power down (any thread)
        self._power_down_until_s: float | None = None  # the power-down's end at the latest

    def power_down(self, timeout_s: float) -> None:
        """Disable every drive with the next command and end once none is enabled (or after
        ``timeout_s``). Any thread."""
        self._power_down_timeout_s = float(timeout_s)

    def update(
        self, t_s: float, period_s: float, feedback: DriveFeedback
    ) -> tuple[Command, ControllerStatus]:
        """Hold; on the first fault status, quick-stop every drive with the next command."""
        cmd = self.command
        cmd.quick_stop = False
        cmd.disable = False
        until = self._power_down_until_s
        if until is None and self._power_down_timeout_s is not None:
            # Asked since the last update: disable with the next command, end by the timeout.
            self._power_down_until_s = t_s + self._power_down_timeout_s
            cmd.disable = True
            return cmd, ControllerStatus.RUNNING
        if until is not None:
            enabled = bool((feedback.state == DriveState.OPERATION_ENABLED).any())
            ended = not enabled or t_s >= until
            return cmd, ControllerStatus.ENDED if ended else ControllerStatus.RUNNING
        if not self.fault and feedback.status >= CycleStatus.EMCY:
            # Once, when the fault appears: the text is built here, outside the hot path.
            status = feedback.status
            what = self._describe(status) if self._describe is not None else status.name
            self.fault = f"while holding: {what}"
            cmd.quick_stop = True
        # Plain Python over the handful of axes (numpy's reductions cost more per call); a
        # NaN stroke (a stale axis) is not settled.
        tol = self.settled_m
        self.settled = feedback.fresh and all(
            abs(x - c) <= tol
            for x, c in zip(feedback.stroke_m.tolist(), cmd.stroke_m.tolist(), strict=True)
        )
        return cmd, ControllerStatus.RUNNING

    def service(self) -> None:
        """Nothing to prepare."""

    def overrun(self, consecutive: int, lateness_s: float) -> None:
        """Nothing to stop: a hold is at rest."""

    def fail(self, text: str) -> tuple[Command, ControllerStatus]:
        """Keep holding (a hold is already at rest)."""
        self.fault = self.fault or text
        return self.command, ControllerStatus.RUNNING
