"""Minimal trajectory streamer: joint trajectories -> CSP setpoints through the CAN master.

Role: the runtime side of the HIL until the executor (issue 7) replaces it. It boots and enables
the drives through :class:`~rt_runtime.canbus.CanMaster`, streams each motion (a sextic dig, a
ruckig transition) sampled at the SYNC period as cylinder strokes and stroke rates, reads the
drives' feedback, and stops safely on a fault. It works on any python-can bus and any clock
(:class:`Clock`): the lockstep HIL's simulated clock or :class:`MonotonicClock`.

Timing of one cycle ``k`` (SYNC ``k`` at ``t_k = t_0 + k T`` of the motion)::

    write_setpoints(s(t_k + T), sd(t_k + T))   # RPDO1 x 3, SYNC k
    read_feedback(now, timeout)                # TPDO1/TPDO2 answering SYNC k: stroke at t_k
    heartbeat(now); sleep until t_{k+1}

The drive latches the target at SYNC k and reaches it one period later (CSP interpolation), so
the drive's demand at ``t_k`` is ``s(t_k)``: the report compares the stroke at SYNC k with
``s(t_k)`` (truth from the plant, "reported" from the TPDO1). The velocity offset 0x60B1 is the
stroke rate at the same instant (feed-forward), or 0 when feed-forward is off.

Pure work outside the loop: :meth:`TrajectoryStreamer.prepare` samples the whole motion, maps it
to strokes (:mod:`rt_runtime.actuation`, joint limits checked) and integer micrometres before a
frame is sent, so a motion outside the limits is refused whole (``PlanningError``/
``JointLimitError``). The loop only packs prepared integers.

Safety: the master reacts to an EMCY, a drive fault, a lost heartbeat or a drive leaving
OPERATION_ENABLED by sending quick stop to every drive (``react_to_faults``); the streamer then
stops streaming the motion and keeps the bus alive (SYNC with the drives held at their reported
positions, heartbeats) until every axis has come to rest or ``stop_timeout_s`` passed, so the
quick-stop ramps run to their end; the result says why it stopped.

Real time: between motions the caller may compute (plan the next dig); the drives need SYNC and
RPDO1 within their watchdog meanwhile, so :meth:`TrajectoryStreamer.hold_while` runs the work in
a thread while the loop holds position (on a simulated clock it just runs the work: time stands
still).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from rt_runtime import actuation, kinematics
from rt_runtime.canbus import CanMaster, CycleStatus, DriveInfo, Emcy, WriteStatus
from rt_runtime.canbus.cia402 import DriveState
from rt_runtime.control.clock import Clock, MonotonicClock
from rt_runtime.errors import PlanningError
from rt_runtime.rig import Rig

__all__ = [
    "Clock",
    "JointMotion",
    "MonotonicClock",
    "Setpoints",
    "StreamResult",
    "StreamStatus",
    "TrajectoryStreamer",
    "ruckig_motion",
    "sextic_motion",
]

FloatArray = NDArray[np.float64]
T = TypeVar("T")


class JointMotion(Protocol):
    """A joint trajectory the streamer can sample: ``duration_s`` and ``sample(t) -> (q, qd)``."""

    @property
    def duration_s(self) -> float:
        """Duration (s)."""
        ...

    def sample(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        """Joint angles and rates ``(3,)`` at ``t_s`` (held at the ends outside [0, duration])."""
        ...


@dataclass(frozen=True, slots=True)
class _Sampled:
    duration_s: float
    fn: Callable[[float], tuple[FloatArray, FloatArray]]

    def sample(self, t_s: float) -> tuple[FloatArray, FloatArray]:
        return self.fn(min(max(t_s, 0.0), self.duration_s))


def sextic_motion(trajectory: Any) -> JointMotion:
    """Adapter for :class:`rt_runtime.trajectory.sextic.SexticTrajectory` (``T_s``, ``sample``)."""

    def fn(t: float) -> tuple[FloatArray, FloatArray]:
        q, qd, _ = trajectory.sample(t)
        return np.asarray(q, dtype=np.float64), np.asarray(qd, dtype=np.float64)

    return _Sampled(float(trajectory.T_s), fn)


def ruckig_motion(trajectory: Any) -> JointMotion:
    """Adapter for a ``ruckig.Trajectory`` (``duration``, ``at_time``)."""

    def fn(t: float) -> tuple[FloatArray, FloatArray]:
        pos, vel, _ = trajectory.at_time(t)
        return np.asarray(pos, dtype=np.float64), np.asarray(vel, dtype=np.float64)

    return _Sampled(float(trajectory.duration), fn)


class StreamStatus(IntEnum):
    """Why a stream ended."""

    DONE = 0
    #: The master saw a fault (EMCY, drive fault, heartbeat lost, a drive left OPERATION
    #: ENABLED) and quick-stopped every drive; the axes were brought to rest.
    FAULT = 1
    #: The bus refused frames.
    BUS_ERROR = 2


@dataclass(frozen=True, slots=True)
class Setpoints:
    """A motion sampled for streaming (computed outside the loop).

    Attributes:
        t_s: SYNC times relative to the motion's start, ``k T``, ``(n,)``.
        q_ref_rad: Reference joint angles at ``t_s``, ``(n, 3)``.
        stroke_ref_m: Reference strokes at ``t_s``, ``(n, 3)``.
        target_um: RPDO1 target stroke sent with SYNC k: the reference at ``t_k + T``, ``(n, 3)``.
        velocity_um_s: RPDO1 velocity offset with SYNC k (zeros without feed-forward), ``(n, 3)``.
    """

    t_s: FloatArray
    q_ref_rad: FloatArray
    stroke_ref_m: FloatArray
    target_um: NDArray[np.int32]
    velocity_um_s: NDArray[np.int32]


@dataclass(frozen=True, slots=True)
class StreamResult:
    """What one stream did, per SYNC it sent.

    Attributes:
        status: Why it ended.
        sync_index: The master's SYNC count of each cycle's SYNC, ``(n,)``.
        t_s: Time of each SYNC since the stream started (clock), ``(n,)``.
        q_ref_rad: Reference joint angles at each SYNC, ``(n, 3)`` (the hold position after a
            fault).
        stroke_ref_m: Reference strokes at each SYNC, ``(n, 3)``.
        stroke_reported_m: TPDO1 position answering each SYNC, NaN when it did not come,
            ``(n, 3)``.
        velocity_reported_m_s: TPDO1 velocity, ``(n, 3)``.
        state: Drive states after each SYNC (``DriveState`` values, -1 undecodable), ``(n, 3)``.
        cycle_status: ``CycleStatus`` of each cycle, ``(n,)``.
        tracking: True for the cycles that streamed the motion (False for the stop after a
            fault), ``(n,)``.
        tip_path_m: Tip path reconstructed from the reported strokes, arm frame, ``(m, 2)`` over
            the cycles with feedback.
        rtt_s: SYNC sent -> last TPDO1 received (clock), NaN when one was missing, ``(n,)``.
        overruns: Cycles that started after their deadline.
        fault: What went wrong (empty when DONE).
        emcys: Emergencies received.
    """

    status: StreamStatus
    sync_index: NDArray[np.int64]
    t_s: FloatArray
    q_ref_rad: FloatArray
    stroke_ref_m: FloatArray
    stroke_reported_m: FloatArray
    velocity_reported_m_s: FloatArray
    state: NDArray[np.int8]
    cycle_status: NDArray[np.int8]
    tracking: NDArray[np.bool_]
    tip_path_m: FloatArray
    rtt_s: FloatArray
    overruns: int
    fault: str
    emcys: tuple[Emcy, ...]


_STOPPING = (
    int(DriveState.OPERATION_ENABLED),
    int(DriveState.QUICK_STOP_ACTIVE),
    int(DriveState.FAULT_REACTION_ACTIVE),
)


class TrajectoryStreamer:
    """Streams joint motions to the drives through a :class:`CanMaster`.

    Args:
        master: The master (its bus, rig and period).
        rig: The rig (stroke mapping, kinematics).
        clock: Time source and sleeper (``master`` must be booted with the same clock).
        feedforward: Send the stroke rate as velocity offset 0x60B1; else 0.
        read_timeout_s: Longest wait for a TPDO after SYNC; default 0.6 of the period.
        stop_timeout_s: Longest time the safe stop keeps the bus alive for the ramps.
        on_cycle: Called after every cycle with ``(sync_index, now_s)`` (scenarios inject faults
            here); must be cheap and must not raise.

    Attributes:
        overruns: Cycles started late, over the streamer's life.
        faulted: A fault ended a stream; further streams refuse to run.
    """

    def __init__(
        self,
        master: CanMaster,
        rig: Rig,
        clock: Clock,
        *,
        feedforward: bool = True,
        read_timeout_s: float | None = None,
        stop_timeout_s: float = 3.0,
        on_cycle: Callable[[int, float], None] | None = None,
    ) -> None:
        self.master = master
        self.rig = rig
        self.clock = clock
        self.period_s = master.config.period_s
        self.feedforward = feedforward
        self.read_timeout_s = 0.6 * self.period_s if read_timeout_s is None else read_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self.on_cycle = on_cycle
        self.overruns = 0
        self.faulted = False
        self._next_s: float | None = None

    # -- outside the loop -----------------------------------------------------------------------

    def start(self, timeout_s: float = 1.0) -> tuple[DriveInfo, ...]:
        """Boot, configure and enable every drive.

        Raises:
            CommunicationError, DriveFault, SdoAbortedError: From the master.
        """
        info = self.master.boot(self.clock.now, timeout_s)
        self.master.enable(self.clock.now, timeout_s)
        self._next_s = None
        return info

    def prepare(self, motion: JointMotion) -> Setpoints:
        """Sample ``motion`` at the period and map it to integer stroke setpoints.

        Raises:
            JointLimitError: The motion leaves a joint's range.
            PlanningError: A stroke setpoint is not finite.
        """
        period = self.period_s
        n = max(1, math.ceil(motion.duration_s / period - 1e-9)) + 1
        t = np.arange(n, dtype=np.float64) * period
        times = np.concatenate([t, [t[-1] + period]])
        samples = [motion.sample(float(tk)) for tk in times]
        q = np.array([s[0] for s in samples], dtype=np.float64)
        qd = np.array([s[1] for s in samples], dtype=np.float64)
        stroke = actuation.joint_to_stroke(self.rig, q)
        rate = actuation.stroke_velocity(self.rig, q, qd)
        if not (np.isfinite(stroke).all() and np.isfinite(rate).all()):
            raise PlanningError("motion maps to non-finite stroke setpoints; nothing was sent")
        target = np.rint(stroke[1:] * 1e6).astype(np.int32)
        vel = np.rint(rate[1:] * 1e6).astype(np.int32)
        if not self.feedforward:
            vel = np.zeros_like(target)
        return Setpoints(t, q[:-1], stroke[:-1], target, vel)

    def hold_while(self, work: Callable[[], T]) -> T:
        """Run ``work()``; on a real-time clock in a thread while the drives hold position.

        Raises:
            Whatever ``work`` raises.
        """
        if not self.clock.realtime:
            return work()
        box: dict[str, Any] = {}

        def run() -> None:
            try:
                box["value"] = work()
            except BaseException as exc:  # re-raised on the caller's thread
                box["error"] = exc

        thread = threading.Thread(target=run, name="streamer-work", daemon=True)
        thread.start()
        while thread.is_alive():
            self._hold_cycles(1)
        thread.join()
        if "error" in box:
            raise box["error"]
        return box["value"]  # type: ignore[no-any-return]

    # -- the loop ---------------------------------------------------------------------------------

    def hold(self, duration_s: float) -> StreamResult:
        """Hold every axis at its last reported stroke for ``duration_s``."""
        fb = self.master.feedback
        stroke = fb.position_um.astype(np.float64) * 1e-6
        q = actuation.stroke_to_joint(self.rig, stroke, check_limits=False)
        motion = _Sampled(max(duration_s, 0.0), lambda _t: (q.copy(), np.zeros(3)))
        return self.stream(motion)

    def _hold_cycles(self, n: int) -> None:
        fb = self.master.feedback
        for _ in range(n):
            self._wait_deadline()
            self.master.write_setpoints(fb.position_um, np.zeros(3, np.int32))
            now = self.clock.now()
            self.master.read_feedback(now, self.read_timeout_s)
            self.master.heartbeat(self.clock.now())

    def _wait_deadline(self) -> None:
        now = self.clock.now()
        if self._next_s is None or self._next_s < now - self.period_s:
            if self._next_s is not None:
                self.overruns += 1
            self._next_s = now
        else:
            self.clock.sleep_until(self._next_s)
        self._next_s += self.period_s

    def stream(self, motion: JointMotion | Setpoints) -> StreamResult:
        """Stream one motion (or prepared setpoints); stop safely on a fault.

        Returns:
            The per-SYNC record; ``status`` FAULT when the master reacted to a fault (the
            motion was cut short and the axes brought to rest), BUS_ERROR when frames were
            refused.

        Raises:
            JointLimitError, PlanningError: From :meth:`prepare` (nothing was sent).
        """
        if self.faulted:
            raise PlanningError("the streamer stopped on a fault; re-enable before streaming")
        if isinstance(motion, Setpoints):
            sp = motion
        else:
            sp = self.hold_while(lambda: self.prepare(motion))
        n = len(sp.t_s)
        cap = n + math.ceil(self.stop_timeout_s / self.period_s) + 1
        sync_index = np.zeros(cap, np.int64)
        t_rec = np.zeros(cap)
        q_ref = np.zeros((cap, 3))
        s_ref = np.zeros((cap, 3))
        s_rep = np.full((cap, 3), np.nan)
        v_rep = np.full((cap, 3), np.nan)
        state = np.full((cap, 3), -1, np.int8)
        cstatus = np.zeros(cap, np.int8)
        tracking = np.zeros(cap, np.bool_)
        rtt = np.full(cap, np.nan)
        emcys: list[Emcy] = []
        master = self.master
        fb = master.feedback
        clock = self.clock
        status = StreamStatus.DONE
        fault = ""
        overruns0 = self.overruns
        start_s: float | None = None
        k = 0
        stopping = False
        stop_until = 0.0
        hold_um = np.zeros(3, np.int32)
        zero = np.zeros(3, np.int32)
        while k < cap:
            self._wait_deadline()
            now = clock.now()
            if start_s is None:
                start_s = now
            if not stopping:
                if k >= n:
                    break
                w = master.write_setpoints(sp.target_um[k], sp.velocity_um_s[k])
                q_ref[k], s_ref[k] = sp.q_ref_rad[k], sp.stroke_ref_m[k]
                tracking[k] = True
            else:
                np.copyto(hold_um, fb.position_um)
                w = master.write_setpoints(hold_um, zero)
                q_ref[k] = q_ref[k - 1]
                s_ref[k] = s_ref[k - 1]
            sent_s = clock.now()
            sync_index[k] = fb.sync_count
            t_rec[k] = now - start_s
            fb = master.read_feedback(clock.now(), self.read_timeout_s)
            emcys.extend(fb.emcys)
            cstatus[k] = int(fb.status)
            fresh = ~fb.stale
            s_rep[k] = np.where(fresh, fb.position_um * 1e-6, np.nan)
            v_rep[k] = np.where(fresh, fb.velocity_um_s * 1e-6, np.nan)
            state[k] = fb.state
            if fresh.all():
                rtt[k] = clock.now() - sent_s
            master.heartbeat(clock.now())
            if self.on_cycle is not None:
                self.on_cycle(int(fb.sync_count), clock.now())
            k += 1
            if w is WriteStatus.BUS_ERROR or fb.status is CycleStatus.BUS_ERROR:
                status, fault = StreamStatus.BUS_ERROR, "the bus refused frames"
                break
            if not stopping and (fb.reacted or fb.status >= CycleStatus.EMCY):
                stopping = True
                self.faulted = True
                status = StreamStatus.FAULT
                fault = _describe(master, fb.status)
                stop_until = clock.now() + self.stop_timeout_s
                if not fb.reacted:
                    master.quick_stop()
            elif stopping:
                # An axis that no longer answers cannot be watched; its drive got the quick
                # stop too and its own watchdogs stop it.
                known = ~fb.heartbeat_lost
                at_rest = not (np.isin(fb.state, _STOPPING) & known).any() and bool(
                    ((np.abs(fb.velocity_um_s) < 1000) | ~known).all()
                )
                if at_rest or clock.now() >= stop_until:
                    break
        m = k
        ok = ~np.isnan(s_rep[:m]).any(axis=1)
        q_meas = actuation.stroke_to_joint(self.rig, s_rep[:m][ok], check_limits=False)
        tip = np.asarray(kinematics.forward(self.rig, q_meas), dtype=np.float64)[..., :2]
        return StreamResult(
            status=status,
            sync_index=sync_index[:m],
            t_s=t_rec[:m],
            q_ref_rad=q_ref[:m],
            stroke_ref_m=s_ref[:m],
            stroke_reported_m=s_rep[:m],
            velocity_reported_m_s=v_rep[:m],
            state=state[:m],
            cycle_status=cstatus[:m],
            tracking=tracking[:m],
            tip_path_m=tip.reshape(-1, 2),
            rtt_s=rtt[:m],
            overruns=self.overruns - overruns0,
            fault=fault,
            emcys=tuple(emcys),
        )

    def shutdown(self) -> WriteStatus:
        """Disable every drive (power stages off; call with the axes at rest)."""
        return self.master.disable()


def _describe(master: CanMaster, status: CycleStatus) -> str:
    fb = master.feedback
    parts = [f"cycle status {status.name}"]
    for axis, name in enumerate(master.config.axes):
        state = fb.drive_state(axis)
        emcy = master.last_emcy[axis]
        text = f"{name}: {state.name if state is not None else 'undecodable'}"
        if fb.heartbeat_lost[axis]:
            text += ", heartbeat lost"
        if emcy is not None:
            text += f", EMCY {emcy.description}"
        parts.append(text)
    return "; ".join(parts)
