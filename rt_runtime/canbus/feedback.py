"""The cycle's results: the feedback workspace and the status codes of a cycle's read and write.

Role: what :class:`~rt_runtime.canbus.router.FrameRouter` fills from the drives' frames and the
cyclic exchange (:class:`~rt_runtime.canbus.cyclic.CyclicExchange`) returns every cycle; no
logic beyond a copy and a decode.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from rt_runtime.canbus.cia402 import DriveState
from rt_runtime.canbus.emcy import Emcy
from rt_runtime.canbus.heartbeat import HeartbeatEvent

__all__ = ["CycleStatus", "Feedback", "WriteStatus"]


class CycleStatus(IntEnum):
    """Outcome of one cycle's read (:meth:`.CyclicExchange.read_feedback`), the most severe
    condition found.

    Ordered by severity: a caller may compare (``status >= CycleStatus.HEARTBEAT_LOST``).
    """

    OK = 0
    #: A drive's TPDO1 answering the latest SYNC did not arrive in time; its values
    #: are the previous ones.
    STALE = 1
    #: An EMCY with a nonzero code arrived (see ``Feedback.emcys``) while every drive still
    #: reports a healthy state.
    EMCY = 2
    #: After :meth:`.CanMaster.enable`, a drive left OPERATION_ENABLED without a fault (quick
    #: stop, disabled, or the master stopped it).
    NOT_ENABLED = 3
    #: A drive's heartbeat timed out, or a drive booted again (reset itself).
    HEARTBEAT_LOST = 4
    #: A drive reports FAULT or FAULT_REACTION_ACTIVE.
    DRIVE_FAULT = 5
    #: The bus refused a frame the master had to send this cycle.
    BUS_ERROR = 6


class WriteStatus(IntEnum):
    """Outcome of a per-cycle send."""

    OK = 0
    #: A setpoint does not fit an i32, or the arrays are too short: nothing was sent.
    OUT_OF_RANGE = 1
    #: The bus refused a frame (``can.CanError``); the frames before it went out (of frames
    #: sent in one write, ``send_many``: none, some or all).
    BUS_ERROR = 2


class RxCounts:
    """What the master rode through on its receive side, counted since it was built.

    Attributes:
        malformed: Drive frames of the wrong length (TPDO1, TPDO2), ignored.
        error_frames: Error frames read off the bus.
        duplicate_tpdo1: A second TPDO1 of one drive for the same SYNC (a duplicate or a late
            one); the later one's values are kept.
        missed_tpdo1: Cycles a drive's TPDO1 was missing at the read (drive-cycles).
        implausible: Positions refused as implausible by the drives' interface (a jump the
            axis cannot make in the time since its last good report): counted as missing.
    """

    __slots__ = ("duplicate_tpdo1", "error_frames", "implausible", "malformed", "missed_tpdo1")

    def __init__(self) -> None:
        self.malformed = 0
        self.error_frames = 0
        self.duplicate_tpdo1 = 0
        self.missed_tpdo1 = 0
        self.implausible = 0

    def to_json(self) -> dict[str, int]:
        """``{"malformed", "error_frames", "duplicate_tpdo1", "missed_tpdo1", "implausible"}``."""
        return {name: int(getattr(self, name)) for name in sorted(self.__slots__)}


class Feedback:
    """The master's per-cycle feedback workspace (one object, reused every cycle).

    Arrays have shape ``(n,)`` in axis order (``MasterConfig.axes``). Values are the latest
    received; ``stale[i]`` says axis ``i`` did not answer the latest SYNC. The object and its
    arrays are overwritten by the next read (:meth:`.CyclicExchange.read_feedback`): a consumer
    on another thread takes :meth:`copy`.

    Attributes:
        status: Most severe condition of this cycle.
        sync_count: SYNCs sent so far; TPDOs received after SYNC ``k`` answer ``k``.
        position_um: 0x6064 position actual (i32, um of stroke).
        velocity_um_s: 0x606C velocity actual (i32, um/s).
        statusword: 0x6041 (u16).
        mode_display: 0x6061 (i8).
        error_code: 0x603F (u16).
        state: Decoded :class:`DriveState` value, -1 for an undecodable statusword (i8).
        tpdo1_sync: SYNC count the latest TPDO1 answered (i64); ``tpdo2_sync`` the SYNC count
            at which the latest TPDO2 (a statusword change) arrived.
        stale: Missing TPDO1 for ``sync_count`` (TPDO2 is sent on change only).
        heartbeat_lost: Heartbeat timed out (and not heard since).
        rx_timestamp_s: Bus timestamp of the latest TPDO1 (the bus's clock, for round trips).
        emcys: EMCYs received during this call.
        heartbeat_events: Heartbeat events noticed during this call.
        reacted: The master sent its fault reaction (quick stop to every drive) this call.
        counts: What the receive side rode through (:class:`RxCounts`), cumulative.
    """

    __slots__ = (
        "counts",
        "emcys",
        "error_code",
        "heartbeat_events",
        "heartbeat_lost",
        "mode_display",
        "position_um",
        "reacted",
        "rx_timestamp_s",
        "stale",
        "state",
        "status",
        "statusword",
        "sync_count",
        "tpdo1_sync",
        "tpdo2_sync",
        "velocity_um_s",
    )

    def __init__(self, n: int) -> None:
        self.status = CycleStatus.OK
        self.sync_count = 0
        self.position_um: NDArray[np.int32] = np.zeros(n, np.int32)
        self.velocity_um_s: NDArray[np.int32] = np.zeros(n, np.int32)
        self.statusword: NDArray[np.uint16] = np.zeros(n, np.uint16)
        self.mode_display: NDArray[np.int8] = np.zeros(n, np.int8)
        self.error_code: NDArray[np.uint16] = np.zeros(n, np.uint16)
        self.state: NDArray[np.int8] = np.full(n, -1, np.int8)
        self.tpdo1_sync: NDArray[np.int64] = np.full(n, -1, np.int64)
        self.tpdo2_sync: NDArray[np.int64] = np.full(n, -1, np.int64)
        self.stale: NDArray[np.bool_] = np.ones(n, np.bool_)
        self.heartbeat_lost: NDArray[np.bool_] = np.zeros(n, np.bool_)
        self.rx_timestamp_s: NDArray[np.float64] = np.zeros(n, np.float64)
        self.emcys: list[Emcy] = []
        self.heartbeat_events: list[HeartbeatEvent] = []
        self.reacted = False
        self.counts = RxCounts()

    def drive_state(self, axis: int) -> DriveState | None:
        """Decoded state of ``axis`` (None when undecodable)."""
        value = int(self.state[axis])
        return DriveState(value) if value >= 0 else None

    def copy(self) -> Feedback:
        """A deep copy, safe to hand to another thread."""
        out = Feedback(len(self.position_um))
        for name in self.__slots__:
            value = getattr(self, name)
            if isinstance(value, np.ndarray | list):
                value = value.copy()
            elif isinstance(value, RxCounts):
                value = RxCounts()
                for key in RxCounts.__slots__:
                    setattr(value, key, getattr(self.counts, key))
            setattr(out, name, value)
        return out
