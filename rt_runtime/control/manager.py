"""The controller manager: one fixed-rate loop, the drives, the guard, and the controller that
runs this cycle (ros2_control's controller manager).

Each cycle (:meth:`ControllerManager._cycle`), read -> update -> write as ros2_control's:

1. read: the drives' answers to the last cycle's SYNC ``k - 1``, which had the whole period to
   arrive (:meth:`~rt_runtime.control.hardware.DriveInterface.read`; a missing one is stale,
   nothing waits), written into telemetry row ``k - 1``, the row of the SYNC they answer;
2. update: the active controller's :meth:`~.controllers.Controller.update` returns the next
   command (then a pending switch or the end of the controller takes effect);
3. write: the command passes the limit guard
   (:class:`~rt_runtime.control.controllers.GuardFilter`) and goes out as RPDO1 for
   ``t_k + T`` with SYNC ``k`` (:meth:`~.hardware.DriveInterface.write`); telemetry row ``k``
   takes the demand at ``t_k`` (``stroke_ref_m``, the previous command), the command for
   ``t_k + T`` and what it streams.

The first cycle only writes; a cycle that ends the loop only reads and updates (its row is
dropped), so row ``k`` is always the cycle that sent SYNC ``k``.

A :meth:`switch` (any thread) hands the drives to another controller at the next cycle
boundary: the new controller's first command, prepared by whoever switches, goes with the next
SYNC, so the SYNC stream has no gap. When the active controller ends, :attr:`on_ended` names the
next one, or ends the loop. Work that takes longer than a cycle runs between cycles: the loop's
idle hook calls the active controller's :meth:`~.controllers.Controller.service` after the step
(never inside one).

SYNC timing. In cycle ``k`` (SYNC ``k`` at ``t_k``) the RPDO1 carries the setpoint for
``t_k + T``: the drive latches it at SYNC ``k`` and reaches it one period later (CSP
interpolation), so the drive's demand at ``t_k`` is the setpoint sent with SYNC ``k - 1``; the
TPDO1 answering SYNC ``k`` reports the stroke at ``t_k``. The velocity offset 0x60B1 is the
guard's stroke rate at ``t_k + T`` (feed-forward), or 0 without feed-forward.
"""

from __future__ import annotations

import logging
import sys
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from rt_runtime.control.controllers import Command, Controller, ControllerStatus, GuardFilter
from rt_runtime.control.hardware import DriveFeedback, DriveInterface
from rt_runtime.control.loop import CycleInfo, FixedRateLoop, LoopAction, LoopStats
from rt_runtime.control.telemetry import LOOP_COLUMNS, Column, Telemetry

__all__ = ["EXECUTOR_COLUMNS", "ControllerManager", "executor_columns", "executor_telemetry"]

log = logging.getLogger(__name__)

def executor_columns(n: int = 3) -> tuple[Column, ...]:
    """The manager's telemetry columns for ``n`` axes (axis order, :mod:`rt_runtime.axes`; the
    ``_m`` columns hold the swing's rad): build the loop's Telemetry with them
    (:func:`executor_telemetry`)."""
    return (
        Column("sync", np.int64, (), -1),  # SYNC count of this cycle's SYNC
        Column("phase", np.int8, (), -1),  # Phase
        Column("segment", np.int32, (), -1),  # motion number (-1 while holding or stopping)
        Column("dig", np.int16, (), -1),  # dig index during a dig
        Column("tracking", np.bool_, (), False),  # streaming a plan's motion
        Column("q_ref_rad", np.float64, (n,)),  # joint reference at this SYNC
        Column("stroke_ref_m", np.float64, (n,)),  # demand at this SYNC (last cycle's command)
        Column("stroke_cmd_m", np.float64, (n,)),  # RPDO1 target with this SYNC (one period on)
        Column("vel_cmd_m_s", np.float64, (n,)),  # RPDO1 velocity offset
        Column("guard", np.int8, (), -1),  # GuardState
        Column("stroke_fb_m", np.float64, (n,)),  # TPDO1 answering this SYNC (NaN: stale)
        Column("vel_fb_m_s", np.float64, (n,)),
        Column("drive_state", np.int8, (n,), -1),
        Column("cycle_status", np.int8, (), -1),
        Column("rtt_s", np.float64),  # SYNC sent -> every TPDO1 in (clock), NaN if one missing
        Column("wait_s", np.float64),  # time the read waited for the answers
        Column("send_s", np.float64),  # time the write spent sending its frames (transport)
    )


#: The manager's telemetry columns of a three-axis rig (:func:`executor_columns`).
EXECUTOR_COLUMNS: tuple[Column, ...] = executor_columns(3)


#: Columns written with the command (the write), in the order the cycle unpacks them.
_COMMAND_COLUMNS = (
    "sync", "phase", "segment", "dig", "tracking", "q_ref_rad", "stroke_ref_m", "stroke_cmd_m",
    "vel_cmd_m_s", "guard", "send_s",
)  # fmt: skip
#: Columns written with the answers to that SYNC (the next cycle's read).
_ANSWER_COLUMNS = ("stroke_fb_m", "vel_fb_m_s", "drive_state", "cycle_status", "rtt_s", "wait_s")


def executor_telemetry(capacity: int, n: int = 3) -> Telemetry:
    """A telemetry ring buffer with the manager's columns for ``n`` axes (give it to the loop;
    a manager on another number of axes replaces it by its own, same capacity).

    Raises:
        ConfigurationError: ``capacity`` below 1.
    """
    return Telemetry(capacity, executor_columns(n))


OnEnded = Callable[[Any], "tuple[Any, Command] | None"]


class ControllerManager:
    """Runs controllers on the drives in one fixed-rate loop (see the module docstring).

    Args:
        drives: The drives.
        guard: The limit guard every command passes.
        loop: The fixed-rate loop; its telemetry is replaced by one with
            :data:`EXECUTOR_COLUMNS` added (same capacity) when it lacks them.
        on_cycle: Called at the end of every cycle with ``(sync_index, now_s)`` on the loop's
            thread (fault injection in tests, liveness); must be cheap and must not raise.
        on_ended: Called on the loop's thread when the active controller ends, with it: returns
            the next controller and its first command, or None to end the loop. Default: end.
    """

    def __init__(
        self,
        drives: DriveInterface,
        guard: GuardFilter,
        loop: FixedRateLoop,
        *,
        on_cycle: Callable[[int, float], None] | None = None,
        on_ended: OnEnded | None = None,
    ) -> None:
        self.drives = drives
        self.guard = guard
        self.loop = loop
        self.on_cycle = on_cycle
        self.on_ended = on_ended
        self.period_s = loop.config.period_s
        self.realtime = bool(loop.clock.realtime)
        self.controller: Any = None
        self.n = n = drives.n
        self._columns = executor_columns(n)
        self._cmd = Command(n)
        self._pending: tuple[Any, Command] | None = None
        self._stop = False
        self._lock = threading.Lock()
        self._s_ref = np.zeros(n)
        self._q_ref = np.zeros(n)
        self._sent_slot = -1  # the telemetry row of the last SYNC sent (-1: none yet)
        self._install_telemetry()
        self._sent_cols: tuple[Any, ...] = ()
        tel = self.loop.telemetry
        self._bind(tel)

    def _install_telemetry(self) -> None:
        tel = self.loop.telemetry
        have = {c.name: c for c in tel.columns}
        if all(c.name in have and have[c.name].shape == c.shape for c in self._columns):
            return
        ours = {c.name for c in self._columns}
        loop_names = {c.name for c in LOOP_COLUMNS}
        extra = [c for c in tel.columns if c.name not in loop_names and c.name not in ours]
        extra += list(self._columns)
        self.loop.telemetry = Telemetry(tel.capacity, extra)

    # -- any thread -----------------------------------------------------------------------------

    def switch(self, controller: Controller, first: Command) -> None:
        """Hand the drives to ``controller`` at the next cycle boundary; ``first`` is its first
        command (prepared outside the loop). Any thread."""
        with self._lock:
            self._pending = (controller, first)

    def use_telemetry(self, telemetry: Telemetry) -> None:
        """Write the rows from the next cycle on into ``telemetry`` (built with
        :func:`executor_telemetry`; the loop's columns included). On the loop's thread, after
        the cycle's row: from ``on_cycle`` or ``on_ended``."""
        self.loop.telemetry = telemetry
        self._bind(telemetry)

    def _bind(self, telemetry: Telemetry) -> None:
        """The columns a cycle writes: the command's at the write, the answers' at the read."""
        self._tel = telemetry
        self._cmd_cols = tuple(telemetry.column(name) for name in _COMMAND_COLUMNS)
        self._answer_cols = tuple(telemetry.column(name) for name in _ANSWER_COLUMNS)


    def stop(self) -> None:
        """End the loop at the next cycle boundary (any thread)."""
        self._stop = True

    # -- the loop's thread ----------------------------------------------------------------------

    def run(
        self,
        controller: Controller,
        first: Command,
        s_ref_m: Any,
        q_ref_rad: Any,
        *,
        max_cycles: int | None = None,
    ) -> LoopStats:
        """Run the loop with ``controller`` (``first`` its first command; ``s_ref_m`` and
        ``q_ref_rad`` the demand the drives hold now) until :attr:`on_ended` or :meth:`stop`
        ends it, or ``max_cycles`` cycles ran."""
        self.controller = controller
        self._cmd = first
        self._s_ref[:] = s_ref_m
        self._q_ref[:] = q_ref_rad
        self._stop = False
        self._sent_slot = -1
        # Another thread of this process holding the interpreter lock delays the loop by up to
        # the switch interval (5 ms by default): on a real-time clock it is cut to a tenth of
        # the period while the loop runs.
        old_switch = sys.getswitchinterval()
        if self.realtime:
            sys.setswitchinterval(min(old_switch, 0.1 * self.period_s))
        try:
            stats = self.loop.run(self._cycle, max_cycles=max_cycles, idle=self._idle)
            if self._sent_slot >= 0:
                # Ended by max_cycles after a write: its answers, a period on, complete the row.
                clock = self.loop.clock
                clock.sleep_until(self.loop.info.deadline_s + self.period_s)
                self._take_answers()
            return stats
        finally:
            sys.setswitchinterval(old_switch)

    def _idle(self) -> None:
        controller = self.controller
        if controller is not None:
            controller.service()

    def _cycle(self, info: CycleInfo) -> LoopAction:
        """read -> update -> write: the answers to the last cycle's SYNC (they had the period to
        arrive; nothing waits), the controller's next command, the guard, RPDO1s and SYNC."""
        drives = self.drives
        if self._sent_slot >= 0:
            fb = self._take_answers()
            controller = self.controller
            now = self.loop.clock.now()
            if info.safe_stop:
                controller.overrun(info.consecutive_overruns, info.lateness_s)
            try:
                nxt, status = controller.update(now, self.period_s, fb)
            except Exception as exc:  # a bug must still end in the guard's stop, never a dead loop
                log.exception("controller update failed")
                nxt, status = controller.fail(f"controller error: {exc!r}")
            if self.on_cycle is not None:
                self.on_cycle(int(fb.sync_count), now)
            if self._pending is not None:
                with self._lock:
                    pending, self._pending = self._pending, None
                if pending is not None:
                    self.controller, nxt = pending
                    status = ControllerStatus.RUNNING
            if status is ControllerStatus.ENDED:
                after = self.on_ended(controller) if self.on_ended is not None else None
                if after is None:
                    self._end()
                    return LoopAction.STOP
                self.controller, nxt = after
            self._cmd = nxt
            if self._stop:
                self._end()
                return LoopAction.STOP
        guard = self.guard
        cmd = self._cmd
        (
            c_sync,
            c_phase,
            c_segment,
            c_dig,
            c_tracking,
            c_q_ref,
            c_s_ref,
            c_s_cmd,
            c_v_cmd,
            c_guard,
            c_send,
        ) = self._cmd_cols
        if cmd.quick_stop:
            drives.quick_stop()
        if cmd.disable:
            drives.disable()
        gstate = guard.apply(cmd)
        drives.write(guard.position_m, guard.velocity_m_s, guard.guard.acceleration_m_s2)
        tel = self._tel
        slot = tel.slot
        c_sync[slot] = drives.sync_count
        c_phase[slot] = cmd.phase
        c_segment[slot] = cmd.segment
        c_dig[slot] = cmd.dig
        c_tracking[slot] = cmd.tracking
        c_q_ref[slot] = self._q_ref
        c_s_ref[slot] = self._s_ref
        c_s_cmd[slot] = guard.position_m
        c_v_cmd[slot] = guard.velocity_m_s
        c_guard[slot] = gstate
        c_send[slot] = drives.feedback.send_s
        self._s_ref[:] = guard.position_m
        self._q_ref[:] = cmd.q_rad
        self._sent_slot = slot
        self._sent_cols = self._answer_cols  # the buffer this SYNC's row is in
        return LoopAction.CONTINUE

    def _take_answers(self) -> DriveFeedback:
        """Read the answers to the last SYNC into the row of that SYNC (in the buffer it was
        in)."""
        fb = self.drives.read()
        row = self._sent_slot
        a_pos, a_vel, a_state, a_status, a_rtt, a_wait = self._sent_cols
        a_pos[row] = fb.stroke_m
        a_vel[row] = fb.velocity_m_s
        a_state[row] = fb.state
        a_status[row] = fb.status
        a_rtt[row] = fb.rtt_s
        a_wait[row] = fb.wait_s
        return fb

    def _end(self) -> None:
        """The loop ends in this cycle before its write: its row holds nothing."""
        self._tel.discard()
        self._sent_slot = -1
