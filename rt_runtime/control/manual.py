"""Manual mode: the drives follow an operator's levers, one lever command per tick.

Role: the controller of a machine driven by hand (the HIL's operator, a joystick on the rig).
A lever command is a joint velocity per axis (rad/s, axis order: boom, stick, bucket, then
swing; :mod:`rt_runtime.axes`), as an excavator's pilot levers command the spools. Every
``tick`` cycles :class:`LeverController` hands the lever source the measured joint angles (the
drives' last fresh report mapped to joints) and takes its command. The commanded velocity is
shaped in joint space by ruckig's velocity interface within the joints' velocity, acceleration
and jerk limits (one ``update`` a cycle, no waypoints), as the valves' pilot stage ramps a
slammed lever; the shaped reference (pose, velocity, acceleration one period ahead) is then
the target the limit guard (:class:`~rt_runtime.control.guard.LimitGuard`) passes through,
its limits being the stroke-space image of the same joint limits with a margin. (A target a
step ahead at a speed the guard cannot reach in one period would be reached time-optimally by
first moving the other way: the lever must not be handed to the guard unshaped.)

Safety: the joint ranges are the end of the lever's travel (the target is clipped 0.5 deg inside
them); a drive fault, EMCY or lost heartbeat (cycle status EMCY and worse) starts the guard's
jerk-limited stop of every axis and ends the run with :attr:`LeverController.fault` set, as the
job controller does; so does stale feedback for ``stale_cycles`` in a row. When the source
returns None (the operator is done) the axes are brought to rest with the guard's stop and the
controller ends.

Loop safety: the source is called inside the cycle; it must be cheap and must not raise (the
manager's ``fail`` path stops the axes if it does).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig

from rt_runtime import axes
from rt_runtime.canbus import CycleStatus
from rt_runtime.control.controllers import Command, ControllerStatus, GuardFilter, Mode
from rt_runtime.control.hardware import DriveFeedback
from rt_runtime.control.setpoints import Phase
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig

__all__ = ["LeverController", "LeverSource"]

FloatArray = NDArray[np.float64]

#: ``source(t_s, q_measured_rad) -> lever_rad_s or None``: axis order, rad and rad/s.
LeverSource = Callable[[float, FloatArray], "FloatArray | None"]

#: How far inside the joint ranges the lever's reference stops (rad): it brakes at the
#: acceleration limit so as to stop there.
RANGE_MARGIN_RAD = math.radians(0.5)


class LeverController:
    """Manual mode (see the module docstring).

    Args:
        rig: The rig (its axes and joint ranges).
        guard: The guard filter every command passes (the controller reads its commanded
            state).
        source: The levers.
        tick: Cycles per lever tick (>= 1): 5 at 2 ms for a 100 Hz lever.
        describe: Text of the drives' state for a fault message (outside the hot path).
        stale_cycles: Consecutive cycles without a fresh report that count as a fault.
        rest_velocity: Below this (axis units per s) every axis counts as at rest.

    Attributes:
        fault: Empty, or why the run stopped early.
        lever: The last lever command ``(n,)``.
        q_measured_rad: The last measured joint angles ``(n,)``.
        ticks: Lever ticks so far.

    Raises:
        ConfigurationError: ``tick`` or ``stale_cycles`` below 1.
    """

    def __init__(
        self,
        rig: Rig,
        guard: GuardFilter,
        source: LeverSource,
        *,
        tick: int = 5,
        describe: Callable[[CycleStatus], str] | None = None,
        stale_cycles: int = 10,
        rest_velocity: float = 1e-3,
    ) -> None:
        if tick < 1 or stale_cycles < 1:
            raise ConfigurationError(
                f"lever tick {tick} and stale_cycles {stale_cycles}; allowed: integers >= 1"
            )
        self.rig = rig
        self.guard = guard
        self.source = source
        self.tick = int(tick)
        self.describe = describe
        self.stale_cycles = int(stale_cycles)
        self.rest_velocity = float(rest_velocity)
        n = axes.count(rig)
        lo, hi, v_max, a_max, j_max = axes.joint_limits(rig)
        self._lo = lo + RANGE_MARGIN_RAD
        self._hi = hi - RANGE_MARGIN_RAD
        self._v_max = v_max
        self._a_max = a_max
        self._j_max = j_max
        self._held = np.zeros(n, dtype=bool)
        self._otg = Ruckig(n, guard.guard.period_s)
        self._inp = InputParameter(n)
        self._out = OutputParameter(n)
        inp = self._inp
        inp.control_interface = ControlInterface.Velocity
        inp.max_velocity = v_max.tolist()
        inp.max_acceleration = a_max.tolist()
        inp.max_jerk = j_max.tolist()
        self._q_ref: FloatArray = np.zeros(n)
        self.command = Command(n)
        self.lever: FloatArray = np.zeros(n)
        self.q_measured_rad: FloatArray = np.full(n, np.nan)
        self.fault = ""
        self.ticks = 0
        self._cycles = 0
        self._stale = 0
        self._stopping = False

    def first(self) -> Command:
        """The first command: hold the guard's commanded pose (outside the loop)."""
        cmd = self.command
        s = np.asarray(self.guard.position_m, dtype=np.float64).copy()
        self._q_ref = axes.actuator_to_joint(self.rig, s, check_limits=False)
        n = len(s)
        inp = self._inp
        inp.current_position = self._q_ref.tolist()
        inp.current_velocity = [0.0] * n
        inp.current_acceleration = [0.0] * n
        cmd.hold(s, self._q_ref, Phase.PATH)
        return cmd

    def _stop(self, why: str) -> None:
        if not self._stopping:
            self._stopping = True
            self.fault = self.fault or why
            self.command.mode = Mode.STOP
            self.command.phase = int(Phase.STOP)
            self.command.tracking = False

    def update(
        self, t_s: float, period_s: float, feedback: DriveFeedback
    ) -> tuple[Command, ControllerStatus]:
        """The next target from the levers (loop safe)."""
        cmd = self.command
        if feedback.fresh:
            self.q_measured_rad = axes.actuator_to_joint(
                self.rig, feedback.stroke_m, check_limits=False
            )
        if self._stopping:
            rest = self.guard.at_rest and bool(
                np.all(np.abs(feedback.last_velocity_m_s) < self.rest_velocity)
            )
            return cmd, ControllerStatus.ENDED if rest else ControllerStatus.RUNNING
        if feedback.status >= CycleStatus.EMCY:
            status = feedback.status
            what = self.describe(status) if self.describe is not None else status.name
            self._stop(f"drive fault in manual mode: {what}")
            return cmd, ControllerStatus.RUNNING
        self._stale = 0 if feedback.fresh else self._stale + 1
        if self._stale >= self.stale_cycles:
            self._stop(f"stale feedback for {self._stale} cycles in manual mode")
            return cmd, ControllerStatus.RUNNING
        if self._cycles % self.tick == 0:
            lever = self.source(t_s, self.q_measured_rad)
            self.ticks += 1
            if lever is None:
                self._stopping = True
                cmd.mode = Mode.STOP
                cmd.phase = int(Phase.STOP)
                cmd.tracking = False
                return cmd, ControllerStatus.RUNNING
            self.lever = np.asarray(lever, dtype=np.float64)
        self._cycles += 1
        inp, out = self._inp, self._out
        q0 = self._q_ref
        v0 = np.asarray(inp.current_velocity)
        a0 = np.abs(np.asarray(inp.current_acceleration))
        # Brake so as to stop inside the range's margin: where a jerk-limited stop from here
        # (the acceleration first turned round, the speed growing meanwhile) could pass it.
        # Once braking, an axis stays held until its lever points away from that end.
        v = np.abs(v0) + a0 * a0 / (2.0 * self._j_max)
        stop = v * ((a0 + self._a_max) / self._j_max) + v * v / (2.0 * self._a_max)
        want = np.clip(self.lever, -self._v_max, self._v_max)
        held = self._held
        held |= ((q0 + stop >= self._hi) & (v0 > 0.0) & (want > 0.0)) | (
            (q0 - stop <= self._lo) & (v0 < 0.0) & (want < 0.0)
        )
        held &= ((q0 > 0.5 * (self._lo + self._hi)) & (want > 0.0)) | (
            (q0 < 0.5 * (self._lo + self._hi)) & (want < 0.0)
        )
        want = np.where(held, 0.0, want)
        inp.target_velocity = want.tolist()
        inp.target_acceleration = [0.0] * len(want)
        if self._otg.update(inp, out) not in (Result.Working, Result.Finished):
            self._stop("manual mode: the lever's ruckig shaping refused its input")
            return cmd, ControllerStatus.RUNNING
        out.pass_to_input(inp)
        q = np.asarray(out.new_position)
        qd = np.asarray(out.new_velocity)
        qdd = np.asarray(out.new_acceleration)
        self._q_ref = q
        # Stroke state of the joint state: s(q), J qd, J qdd + J' qd^2 (J' by a central
        # difference, as the setpoint tables).
        h = 1e-4
        s_lo = axes.joint_to_actuator(self.rig, q - h, check_limits=False)
        s_mid = axes.joint_to_actuator(self.rig, q, check_limits=False)
        s_hi = axes.joint_to_actuator(self.rig, q + h, check_limits=False)
        jac = (s_hi - s_lo) / (2.0 * h)
        dj = (s_hi - 2.0 * s_mid + s_lo) / (h * h)
        cmd.mode = Mode.TRACK
        cmd.stroke_m[:] = s_mid
        cmd.rate_m_s[:] = jac * qd
        cmd.accel_m_s2[:] = jac * qdd + dj * qd * qd
        cmd.q_rad[:] = q
        cmd.phase = int(Phase.PATH)
        cmd.tracking = True
        return cmd, ControllerStatus.RUNNING

    def service(self) -> None:
        """Nothing to prepare between cycles."""

    def fail(self, text: str) -> tuple[Command, ControllerStatus]:
        """The update raised: stop every axis."""
        self._stop(f"manual mode failed: {text}")
        return self.command, ControllerStatus.RUNNING

    def overrun(self, consecutive: int, lateness_s: float) -> None:
        """The loop's overrun policy asks for a safe stop."""
        self._stop(f"{consecutive} consecutive loop overruns (last {lateness_s * 1e6:.0f} us)")
