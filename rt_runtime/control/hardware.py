"""The drives as the controllers see them: commands and feedback in SI units over the CiA 402
master (ros2_control's hardware interface).

:class:`DriveInterface` alone owns the :class:`~rt_runtime.canbus.CanMaster` and the conversion
between metres and the drives' integer micrometres. One cycle is :meth:`~DriveInterface.write`
(RPDO1 target stroke and stroke-rate feed-forward to every drive, then SYNC ``k``) and
:meth:`~DriveInterface.read` (the drives' answers to SYNC ``k``, waiting at most
``read_timeout_s``, then the master's heartbeat when due). Both are loop safe: preallocated
buffers, no exceptions for bus conditions (statuses instead).

Units: strokes m, stroke rates m/s, times s; a swing axis (index 3, :mod:`rt_runtime.axes`)
in rad and rad/s under the same names, microradians on the bus. A drive whose TPDO1 for this
SYNC did not arrive is *stale*: its ``stroke_m`` and ``velocity_m_s`` are NaN this cycle,
``last_velocity_m_s`` keeps its last report.

Plausibility: a reported stroke further from the axis's last good report than the axis can
move in the time between them (:data:`JUMP_RATE_FACTOR` times the rig's largest stroke rate,
plus :data:`JUMP_MARGIN_M`) is refused: the axis counts as stale this cycle and the master's
:class:`~rt_runtime.canbus.feedback.RxCounts` counts it as ``implausible``. A garbled TPDO1 or
an encoder that jumped never reaches the controllers as a position; if it persists, the stale
feedback monitor stops the job (the drives' interface keeps the last good report as its
reference, so a jump stays refused until the axis could have got there).

Timing: :attr:`DriveFeedback.send_s` is the time the write spent handing its frames to the bus
(RPDO1s and SYNC), :attr:`DriveFeedback.wait_s` the time :meth:`~DriveInterface.read` spent
taking the answers off the bus (receiving and decoding, and waiting where ``read_timeout_s``
lets it). The round trip :attr:`DriveFeedback.rtt_s` is measured on the bus's own stamps: the
latest answer's receive stamp minus the SYNC's send stamp.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from rt_runtime.canbus import CanMaster, CycleStatus, DriveState, Emcy, WriteStatus, emcy_meaning
from rt_runtime.canbus.cyclic import bus_error_text
from rt_runtime.control.clock import Clock
from rt_runtime.errors import ConfigurationError

__all__ = ["JUMP_MARGIN_M", "JUMP_RATE_FACTOR", "DriveFeedback", "DriveInterface"]

#: A report is implausible past this many times the rig's largest stroke rate ...
JUMP_RATE_FACTOR = 2.0
#: ... plus this much (m): encoder quantisation and the servo's own overshoot.
JUMP_MARGIN_M = 0.5e-3

FloatArray = NDArray[np.float64]


class DriveFeedback:
    """The drives' state after one :meth:`DriveInterface.read` (reused: valid until the next).

    Attributes:
        sync_count: SYNCs sent so far (the one these answers belong to).
        stroke_m: Reported stroke per axis (m), NaN where stale, ``(n,)``.
        velocity_m_s: Reported stroke rate (m/s), NaN where stale.
        last_velocity_m_s: Last reported stroke rate (m/s), stale or not.
        stale: No TPDO1 answered this SYNC.
        fresh: Every drive answered (``not stale.any()``).
        state: CiA 402 state per axis (:class:`~rt_runtime.canbus.DriveState` value, -1 unknown).
        heartbeat_lost: The drive's heartbeat timed out.
        status: The cycle's :class:`~rt_runtime.canbus.CycleStatus`.
        write_status: What the cycle's write returned.
        emcys: Emergencies received this cycle.
        rtt_s: SYNC sent -> every TPDO1 in (s), NaN when one was missing.
        send_s: Time the write spent sending its frames (s).
        wait_s: Time the read waited for the answers (s).
    """

    __slots__ = (
        "emcys",
        "fresh",
        "heartbeat_lost",
        "last_velocity_m_s",
        "rtt_s",
        "send_s",
        "stale",
        "state",
        "status",
        "stroke_m",
        "sync_count",
        "velocity_m_s",
        "wait_s",
        "write_status",
    )

    def __init__(self, n: int) -> None:
        self.sync_count = 0
        self.stroke_m: FloatArray = np.full(n, np.nan)
        self.velocity_m_s: FloatArray = np.full(n, np.nan)
        self.last_velocity_m_s: FloatArray = np.zeros(n)
        self.stale: NDArray[np.bool_] = np.ones(n, np.bool_)
        self.fresh = False
        self.state: NDArray[np.int8] = np.full(n, -1, np.int8)
        self.heartbeat_lost: NDArray[np.bool_] = np.zeros(n, np.bool_)
        self.status = CycleStatus.OK
        self.write_status = WriteStatus.OK
        self.emcys: list[Emcy] = []
        self.rtt_s = math.nan
        self.send_s = 0.0
        self.wait_s = 0.0


def per_axis_gain(gain_1_s: float | Sequence[float], n: int | None = None) -> tuple[float, ...]:
    """The host loop's gain per axis (1/s) from one value for every axis or one per axis of
    ``n`` (None: the values as given, checked only).

    Raises:
        ConfigurationError: A gain that is negative or not finite, no gain, or a count other
            than 1 or ``n`` (the message names what is allowed).
    """
    values = (gain_1_s,) if isinstance(gain_1_s, (int, float)) else tuple(gain_1_s)
    counts = (1, n) if n is not None else (len(values),)
    if (
        not values
        or len(values) not in counts
        or not all(isinstance(g, (int, float)) and math.isfinite(g) and g >= 0.0 for g in values)
    ):
        axes = f" ({n})" if n is not None else ""
        raise ConfigurationError(
            f"correction_gain_1_s = {gain_1_s!r}; allowed: one finite value >= 0 (1/s) for "
            f"every axis or one per axis{axes}"
        )
    out = tuple(float(g) for g in values)
    return out * n if n is not None and len(out) == 1 else out


class DriveInterface:
    """The drives in SI units (see the module docstring).

    Args:
        master: The CAN master (booted and enabled by its owner).
        clock: The loop's clock (times of SYNC, answers, heartbeat).
        read_timeout_s: Longest wait for one missing answer (s); 0: take what arrived.
        feedforward: Send the stroke rate as velocity offset 0x60B1 (else 0).
        correction_gain_1_s: Gain of the host's proportional displacement loop (1/s), one for
            every axis or one per axis (axis order): each cycle adds ``gain * (last target -
            reported stroke)`` to the velocity offset, on a fresh report (0: none). It closes
            a second loop over the bus around the drive's own, as a PC controller does (Gao
            4.1), and takes out the part of the following error that the drive's loop leaves
            (a valve's dead band, a screw's friction).
        lead_s: Per axis, a lead (s) added to the velocity offset as ``lead * acceleration``:
            the velocity demand of a first-order lag ``1 / (lead s + 1)`` between the offset
            and the axis's motion (a valve's spool, a motor's hydraulic spring) made good ahead
            of time. None: none (the offset is the rate).
        lead2_s2: Per axis, the second-order term (s^2) of the same inverse, added as
            ``lead2 * jerk`` (the jerk as the change of the acceleration given over one
            period): for an axis behind a spring-mass mode ``1 / (s^2 / w^2 + 2 zeta s / w +
            1)``, ``1 / w^2`` (plus the product with a first-order lag). Needs ``lead_s``.
    """

    def __init__(
        self,
        master: CanMaster,
        clock: Clock,
        read_timeout_s: float,
        feedforward: bool = True,
        correction_gain_1_s: float | Sequence[float] = 0.0,
        lead_s: NDArray[np.float64] | None = None,
        lead2_s2: NDArray[np.float64] | None = None,
    ) -> None:
        self.master = master
        # The cycle's calls go straight to the master's cyclic part (CyclicExchange): one call
        # fewer a cycle than through the master's own methods.
        self.cycle = master.cycle
        self.clock = clock
        self.read_timeout_s = float(read_timeout_s)
        self.feedforward = feedforward
        self.n = master.n
        self.correction_gain_1_s = per_axis_gain(correction_gain_1_s, self.n)
        self._correcting = any(g > 0.0 for g in self.correction_gain_1_s)
        self._last_target_m: list[float] | None = None
        self.axes: tuple[str, ...] = tuple(master.config.axes)
        self.feedback = DriveFeedback(self.n)
        self._zero_um = [0] * self.n
        self.lead_s: NDArray[np.float64] | None = None
        if lead_s is not None:
            lead = np.asarray(lead_s, dtype=np.float64)
            if lead.shape != (self.n,) or not bool(np.all(np.isfinite(lead) & (lead >= 0.0))):
                raise ValueError(
                    f"velocity lead {lead_s!r}: allowed one finite value >= 0 s per axis ({self.n})"
                )
            self.lead_s = lead
        self.lead2_s2: NDArray[np.float64] | None = None
        if lead2_s2 is not None:
            lead2 = np.asarray(lead2_s2, dtype=np.float64)
            if (
                self.lead_s is None
                or lead2.shape != (self.n,)
                or not bool(np.all(np.isfinite(lead2) & (lead2 >= 0.0)))
            ):
                raise ValueError(
                    f"second-order velocity lead {lead2_s2!r}: allowed with lead_s, one finite "
                    f"value >= 0 s^2 per axis ({self.n})"
                )
            self.lead2_s2 = lead2
        self._offset = np.zeros(self.n)
        self._jerk = np.zeros(self.n)
        self._accel_prev: NDArray[np.float64] | None = None
        self._inv_period = 1.0 / master.config.period_s
        from rt_runtime import axes

        rate = JUMP_RATE_FACTOR * axes.actuator_velocity_max(master.rig)
        self._jump_per_sync_m: list[float] = (rate * master.config.period_s).tolist()
        self._good_m = [math.nan] * self.n
        self._good_sync = [0] * self.n

    @property
    def sync_count(self) -> int:
        """SYNCs sent so far."""
        return int(self.master.feedback.sync_count)

    def measured_stroke_m(self) -> FloatArray:
        """The strokes the drives reported last (m), a new array (outside the loop)."""
        return np.asarray(self.master.feedback.position_um, dtype=np.float64) * 1e-6

    def operation_enabled(self) -> bool:
        """Every drive reports OPERATION_ENABLED."""
        return bool((self.master.feedback.state == DriveState.OPERATION_ENABLED).all())

    def drive_states(self) -> list[str]:
        """Each drive's state name (for messages)."""
        fb = self.master.feedback
        return [
            s.name if (s := fb.drive_state(a)) is not None else "undecodable" for a in range(self.n)
        ]

    def write(
        self,
        stroke_m: FloatArray,
        velocity_m_s: FloatArray,
        acceleration_m_s2: FloatArray | None = None,
    ) -> WriteStatus:
        """RPDO1 (target stroke, velocity offset when feed-forward is on: the rate, plus
        ``lead_s * acceleration`` when a lead is set and the acceleration given) to every drive,
        then SYNC; rounds to micrometres. Loop safe."""
        clock = self.clock
        lead = self.lead_s
        if lead is not None and acceleration_m_s2 is not None:
            np.multiply(lead, acceleration_m_s2, out=self._offset)
            self._offset += velocity_m_s
            lead2 = self.lead2_s2
            if lead2 is not None:
                prev = self._accel_prev
                if prev is None:
                    self._accel_prev = prev = np.array(acceleration_m_s2, dtype=np.float64)
                np.subtract(acceleration_m_s2, prev, out=self._jerk)
                self._jerk *= self._inv_period
                self._jerk *= lead2
                self._offset += self._jerk
                prev[:] = acceleration_m_s2
            velocity_m_s = self._offset
        # round() is round-half-to-even, as np.rint; plain ints skip numpy's per-call cost.
        try:
            target = [round(x * 1e6) for x in stroke_m.tolist()]
            velocity = (
                [round(x * 1e6) for x in velocity_m_s.tolist()]
                if self.feedforward
                else self._zero_um
            )
            if self._correcting:
                last = self._last_target_m
                fb = self.feedback
                if last is not None and fb.fresh:
                    velocity = [
                        v + round(g * (t - x) * 1e6)
                        for v, g, t, x in zip(
                            velocity,
                            self.correction_gain_1_s,
                            last,
                            fb.stroke_m.tolist(),
                            strict=True,
                        )
                    ]
                self._last_target_m = stroke_m.tolist()
        except (ValueError, OverflowError):  # NaN or infinite: nothing is sent
            status = WriteStatus.OUT_OF_RANGE
        else:
            t_send = clock.now()
            status = self.cycle.write_setpoints(target, velocity)
            self.feedback.send_s = clock.now() - t_send
        self.feedback.write_status = status
        return status

    def read(self) -> DriveFeedback:
        """The answers to the last SYNC (waiting at most ``read_timeout_s`` per missing one),
        then the master's heartbeat when due. Loop safe."""
        clock = self.clock
        t0 = clock.now()
        cycle = self.cycle
        raw = cycle.read_feedback(t0, self.read_timeout_s)
        t1 = clock.now()
        out = self.feedback
        # Plain Python over the handful of axes: numpy's reductions cost more per call.
        fresh = True not in raw.stale.tolist()
        out.fresh = fresh
        rtt = max(raw.rx_timestamp_s.tolist()) - cycle.sync_stamp_s if fresh else math.nan
        out.rtt_s = rtt if rtt >= 0.0 else math.nan
        cycle.heartbeat(clock.now())
        out.sync_count = raw.sync_count
        pos = out.stroke_m
        np.multiply(raw.position_um, 1e-6, out=pos)
        vel = out.last_velocity_m_s
        np.multiply(raw.velocity_um_s, 1e-6, out=vel)
        out.velocity_m_s[:] = vel
        out.stale[:] = raw.stale
        if self._implausible(raw.sync_count, pos, out.stale):
            out.fresh = fresh = False
            out.rtt_s = math.nan
        if not fresh:
            pos[out.stale] = np.nan
            out.velocity_m_s[out.stale] = np.nan
        out.state[:] = raw.state
        out.heartbeat_lost[:] = raw.heartbeat_lost
        out.status = raw.status
        out.emcys = raw.emcys
        out.wait_s = t1 - t0
        return out

    def _implausible(self, sync: int, pos: FloatArray, stale: NDArray[np.bool_]) -> bool:
        """Refuse the reports that jumped (see the module docstring): mark them stale, count
        them; True when one was refused. Plain Python over the handful of axes."""
        refused = False
        good, good_sync = self._good_m, self._good_sync
        step = self._jump_per_sync_m
        for axis, (x, gone) in enumerate(zip(pos.tolist(), stale.tolist(), strict=True)):
            if gone:
                continue
            last = good[axis]
            if (
                last == last
                and abs(x - last) > step[axis] * (sync - good_sync[axis]) + JUMP_MARGIN_M
            ):
                stale[axis] = True
                refused = True
                self.master.feedback.counts.implausible += 1
                continue
            good[axis] = x
            good_sync[axis] = sync
        return refused

    def describe(self, status: CycleStatus) -> str:
        """What the drives report, for a fault message (outside the hot path): the cycle's
        status, then per axis its name, node id and CiA 402 state (marked when it did not
        answer the latest SYNC), a lost heartbeat, the
        latest EMCY (code, name and meaning) or, where no EMCY came, a nonzero error code
        0x603F with its meaning; for a bus error, the exception the bus raised."""
        master = self.master
        fb = master.feedback
        cycle = master.cycle
        head = f"cycle status {status.name}"
        if status is CycleStatus.BUS_ERROR and cycle.bus_exception is not None:
            head += f" ({bus_error_text(cycle.bus_exception)})"
        parts = [head]
        for axis, name in enumerate(self.axes):
            state = fb.drive_state(axis)
            node = master.config.node_ids[axis]
            text = f"{name} (node {node}): {state.name if state is not None else 'undecodable'}"
            if fb.stale[axis]:
                text += " (its last report)"
            if fb.heartbeat_lost[axis]:
                text += ", heartbeat lost"
            emcy = master.last_emcy[axis]
            if emcy is not None and not emcy.is_reset:
                text += f", EMCY {emcy.description}: {emcy.meaning}"
            elif int(fb.error_code[axis]) != 0:
                code = int(fb.error_code[axis])
                text += f", error code 0x{code:04X}: {emcy_meaning(code)}"
            parts.append(text)
        return "; ".join(parts)

    def quick_stop(self) -> WriteStatus:
        """Quick stop to every drive (their own ramp). Loop safe."""
        return self.cycle.quick_stop()

    def disable(self) -> WriteStatus:
        """Disable voltage to every drive (for axes at rest). Loop safe."""
        return self.cycle.disable()

    def react_to_faults(self, on: bool) -> None:
        """Let the master quick-stop every drive on a fault (off: the controllers react)."""
        self.cycle.react_to_faults = on
