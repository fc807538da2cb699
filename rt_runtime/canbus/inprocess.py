"""An in-process CAN channel: python-can bus ends that share one process-local bus.

Role: the transport of the lockstep HIL (and of tests that need two bus ends in one process),
in place of python-can's ``virtual`` interface, whose ``send`` deep-copies every frame for every
receiver (~35 us per ``can.Message`` here) and whose channels live in module-level state.

Rules: an :class:`InProcessChannel` is one bus; each :class:`ChannelBus` is one end of it.
``send`` gives every other end (and the sender, with ``receive_own_messages``) its own copy of
the frame, made at send time, so the sender may reuse and repack its message at once (the
master does, every cycle). The copy carries the frame's fields (id, flags, DLC, data) and a
timestamp: the sender's (``preserve_timestamps``) or the end's clock at send time (``clock``,
default ``time.time``). Receive queues are unbounded C ``queue.SimpleQueue``s; python-can's
:meth:`can.BusABC.recv` applies timeouts (wall clock) and filters. After :meth:`ChannelBus.
shutdown` the end leaves the channel; ``send`` and ``recv`` on it raise
``can.CanOperationError``, and a ``recv`` blocked in another thread wakes up and raises.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import can

__all__ = ["ChannelBus", "InProcessChannel"]

#: Put on an end's queue by its shutdown: wakes a blocked reader.
_CLOSED: Any = None


class InProcessChannel:
    """One process-local CAN bus: the set of its open ends.

    Args:
        name: Shown in each end's ``channel_info``.
    """

    def __init__(self, name: str = "in-process") -> None:
        self.name = name
        self._lock = threading.Lock()
        #: The open ends, replaced (never mutated) on join and leave so ``send`` reads it
        #: without the lock.
        self.ends: tuple[ChannelBus, ...] = ()

    def open(self, **kwargs: Any) -> ChannelBus:
        """A new end on this channel (keyword arguments as :class:`ChannelBus`)."""
        return ChannelBus(self, **kwargs)

    def _join(self, end: ChannelBus) -> None:
        with self._lock:
            self.ends = (*self.ends, end)

    def _leave(self, end: ChannelBus) -> None:
        with self._lock:
            self.ends = tuple(e for e in self.ends if e is not end)


class ChannelBus(can.BusABC):
    """One end of an :class:`InProcessChannel` (see the module docstring).

    Args:
        channel: The channel joined.
        receive_own_messages: Also receive a copy of what this end sends.
        preserve_timestamps: Copies keep the sent message's timestamp instead of ``clock()``.
        clock: Stamps each copy with its send time (s), when timestamps are not preserved.
        can_filters: python-can filters, applied by :meth:`can.BusABC.recv`.
    """

    def __init__(
        self,
        channel: InProcessChannel,
        *,
        receive_own_messages: bool = False,
        preserve_timestamps: bool = False,
        clock: Callable[[], float] = time.time,
        can_filters: can.typechecking.CanFilters | None = None,
    ) -> None:
        self.bus_channel = channel
        self.channel_info = f"in-process channel {channel.name!r}"
        self.receive_own_messages = receive_own_messages
        self.preserve_timestamps = preserve_timestamps
        self.clock = clock
        self.queue: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self._open = True
        super().__init__(channel=channel.name, can_filters=can_filters)
        channel._join(self)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Queue a copy of ``msg`` at every other end (see the module docstring); never blocks.

        Raises:
            can.CanOperationError: This end is shut down.
        """
        if not self._open:
            raise can.CanOperationError(f"{self.channel_info}: send on a closed bus end")
        stamp = msg.timestamp if self.preserve_timestamps else self.clock()
        data = bytes(msg.data)
        name = self.bus_channel.name
        self._fan_out(
            lambda own: can.Message(
                timestamp=stamp,
                arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame,
                channel=name,
                dlc=msg.dlc,
                data=data,
                is_fd=msg.is_fd,
                bitrate_switch=msg.bitrate_switch,
                error_state_indicator=msg.error_state_indicator,
                is_rx=not own,
                check=False,
            )
        )

    def send_data(self, arbitration_id: int, data: bytes) -> None:
        """Send a standard-id data frame given by its id and payload (no message to copy: the
        cheap path for an emulator that produces frames as ``(id, bytes)``).

        Raises:
            can.CanOperationError: This end is shut down.
        """
        if not self._open:
            raise can.CanOperationError(f"{self.channel_info}: send on a closed bus end")
        stamp = self.clock()
        name = self.bus_channel.name
        self._fan_out(
            lambda own: can.Message(
                timestamp=stamp,
                arbitration_id=arbitration_id,
                is_extended_id=False,
                channel=name,
                dlc=len(data),
                data=data,
                is_rx=not own,
                check=False,
            )
        )

    def _fan_out(self, copy: Callable[[bool], can.Message]) -> None:
        """Queue a copy of one frame at every end that receives it (``copy(own)``: the copy
        for this end itself, or another's)."""
        for end in self.bus_channel.ends:
            own = end is self
            if own and not self.receive_own_messages:
                continue
            end.queue.put(copy(own))

    def take(self) -> can.Message | None:
        """The next queued frame without waiting and without filtering, or None.

        Raises:
            can.CanOperationError: This end is shut down.
        """
        if not self._open:
            raise can.CanOperationError(f"{self.channel_info}: receive on a closed bus end")
        q = self.queue
        return None if q.empty() else q.get_nowait()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.take()
        if msg is not None or (timeout is not None and timeout <= 0.0):
            return msg, False
        try:
            msg = self.queue.get(timeout=timeout)
        except queue.Empty:
            return None, False
        if msg is _CLOSED:
            raise can.CanOperationError(f"{self.channel_info}: receive on a closed bus end")
        return msg, False

    def shutdown(self) -> None:
        """Leave the channel (idempotent); frames still queued are dropped."""
        if self._open:
            self._open = False
            self.bus_channel._leave(self)
            self.queue.put(_CLOSED)
        super().shutdown()
