"""The master's receive side: every frame it reads, routed by COB-ID into one feedback workspace.

Role: who reads the bus is the master alone, on the caller's thread. python-can buses have one
receive queue, so a second reader (a ``can.Notifier``, canopen's network) would take frames the
loop needs. Every frame the master reads, wherever it reads it (an SDO transfer, a boot wait,
the cycle's read), goes through one dispatcher, :meth:`FrameRouter.dispatch`: the drives' TPDO1
and TPDO2 into the :class:`~rt_runtime.canbus.feedback.Feedback` workspace, their EMCYs into it
and :attr:`FrameRouter.last_emcy`, their heartbeats to the heartbeat consumer (its events into
the workspace); malformed drive frames are ignored and counted, error frames counted
(:class:`~rt_runtime.canbus.feedback.RxCounts`), any other frame goes to the ``on_other_frame``
callback. The router reads no bus and no clock: callers pass each frame and
its ``now_s``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import can

from rt_runtime.canbus.cia402 import decode_state
from rt_runtime.canbus.emcy import Emcy, parse_emcy
from rt_runtime.canbus.feedback import Feedback
from rt_runtime.canbus.heartbeat import HeartbeatConsumer, parse_heartbeat
from rt_runtime.canbus.pdo import COB_EMCY, COB_HEARTBEAT, TPDO1, TPDO2

__all__ = ["FrameRouter"]

# Frame kinds of the COB-ID table.
_TPDO1, _TPDO2, _EMCY, _HEARTBEAT = 1, 2, 3, 4


class FrameRouter:
    """Routes received frames into the feedback workspace (see the module docstring).

    A TPDO1 is attributed to the latest SYNC sent (:meth:`sync_sent`; the SYNC has no counter
    byte), so a TPDO1 that arrives only after the next SYNC counts for that one.

    Args:
        node_ids: Drive node id per axis, in axis order.
        feedback: The workspace filled (shape ``(len(node_ids),)`` arrays).
        consumer: The drives' heartbeat consumer.
        on_other_frame: Receives ``(message, now_s)`` for every other frame (the VCU's status,
            say); it must be cheap and must not raise.

    Attributes:
        feedback: The workspace.
        consumer: The heartbeat consumer.
        on_other_frame: The callback for other frames, or None.
        last_emcy: Per axis, the latest EMCY received (None before the first).
        pending: TPDO1s still missing for the latest SYNC.
    """

    def __init__(
        self,
        node_ids: Sequence[int],
        feedback: Feedback,
        consumer: HeartbeatConsumer,
        on_other_frame: Callable[[can.Message, float], None] | None = None,
    ) -> None:
        self.feedback = feedback
        self.consumer = consumer
        self.on_other_frame = on_other_frame
        self.last_emcy: list[Emcy | None] = [None] * len(node_ids)
        self.pending = 0
        self._node_ids = tuple(node_ids)
        self._routes: dict[int, tuple[int, int]] = {}
        for axis, node in enumerate(self._node_ids):
            self._routes[TPDO1.cob_id(node)] = (_TPDO1, axis)
            self._routes[TPDO2.cob_id(node)] = (_TPDO2, axis)
            self._routes[COB_EMCY + node] = (_EMCY, axis)
            self._routes[COB_HEARTBEAT + node] = (_HEARTBEAT, axis)

    def sync_sent(self) -> None:
        """A SYNC went out: the drives' TPDO1s that follow answer it."""
        self.feedback.sync_count += 1
        self.pending = len(self._node_ids)

    def set_status(self, axis: int, statusword: int, mode: int, error_code: int) -> None:
        """Put the objects TPDO2 maps (0x6041, 0x6061, 0x603F) of ``axis`` into the workspace
        and decode its state, whether they came in a TPDO2 or by SDO upload. Loop safe."""
        fb = self.feedback
        fb.statusword[axis], fb.mode_display[axis], fb.error_code[axis] = (
            statusword,
            mode,
            error_code,
        )
        state = decode_state(statusword)
        fb.state[axis] = -1 if state is None else int(state)

    def dispatch(self, msg: can.Message, now_s: float) -> None:
        """Route one received frame (loop safe; allocates only EMCY and heartbeat events)."""
        route = None
        if msg.is_error_frame:
            self.feedback.counts.error_frames += 1
            return
        if not (msg.is_extended_id or msg.is_remote_frame):
            route = self._routes.get(msg.arbitration_id)
        if route is None:
            if self.on_other_frame is not None:
                self.on_other_frame(msg, now_s)
            return
        kind, axis = route
        fb = self.feedback
        data = msg.data
        if kind == _TPDO1:
            if len(data) != TPDO1.size:
                fb.counts.malformed += 1
                return
            fb.position_um[axis], fb.velocity_um_s[axis] = TPDO1.codec.unpack_from(data)
            fb.rx_timestamp_s[axis] = msg.timestamp
            if fb.tpdo1_sync[axis] != fb.sync_count:
                fb.tpdo1_sync[axis] = fb.sync_count
                self.pending -= 1
            else:
                fb.counts.duplicate_tpdo1 += 1
        elif kind == _TPDO2:
            if len(data) != TPDO2.size:
                fb.counts.malformed += 1
                return
            self.set_status(axis, *TPDO2.codec.unpack_from(data))
            # TPDO2 is synchronous acyclic (sent only on change): never awaited per SYNC.
            fb.tpdo2_sync[axis] = fb.sync_count
        elif kind == _EMCY:
            emcy = parse_emcy(self._node_ids[axis], data, now_s)
            if emcy is not None:
                fb.emcys.append(emcy)
                self.last_emcy[axis] = emcy
        else:
            hb_state = parse_heartbeat(data)
            if hb_state is not None:
                event = self.consumer.on_heartbeat(self._node_ids[axis], hb_state, now_s)
                if event is not None:
                    fb.heartbeat_events.append(event)
