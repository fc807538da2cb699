"""A python-can bus that hands every frame it sends and receives to a trace writer.

Role: the daemon's CAN trace (``paths.trace``) without work on the loop's thread beyond one
queue put per frame: a writer thread (the daemon's ``TraceRecorder``) turns the queued items
into python-can log records. It wraps any bus as a python-can backend: ``send`` and
``_recv_internal`` on the wrapped bus; python-can's :meth:`can.BusABC.recv` applies this bus's
filters (the trace keeps every frame the wrapped bus delivered).
"""

from __future__ import annotations

import time
from typing import Any, Protocol

import can

__all__ = ["TraceSink", "TracedBus"]


class TraceSink(Protocol):
    """Where a :class:`TracedBus` puts frames: ``(unix_s, id, data, is_rx)`` tuples for sent
    frames (copied at send time: the sender may reuse its message), received messages as
    they are; only while ``active``."""

    active: bool

    @property
    def queue(self) -> Any:
        """Anything with ``put(item)`` that never blocks."""
        ...


class TracedBus(can.BusABC):
    """A python-can bus that hands every frame sent and received to a :class:`TraceSink`.

    Safe inside the loop: one tuple and one queue put per frame sent, one put per frame received.

    Args:
        bus: The real bus (closed by :meth:`shutdown`).
        recorder: Where frames go (only while ``recorder.active``).
    """

    def __init__(self, bus: can.BusABC, recorder: TraceSink) -> None:
        self._bus = bus
        self._recorder = recorder
        self.channel_info = f"traced {getattr(bus, 'channel_info', '')}"
        super().__init__(channel=str(getattr(bus, "channel", "") or "traced"))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send through the real bus, then record (a refused frame is not recorded)."""
        self._bus.send(msg, timeout)
        if self._recorder.active:
            self._recorder.queue.put((time.time(), msg.arbitration_id, bytes(msg.data), False))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self._bus.recv(timeout)
        if msg is not None and self._recorder.active:
            self._recorder.queue.put(msg)
        return msg, False

    def shutdown(self) -> None:
        """Shut the real bus down."""
        self._bus.shutdown()
        super().shutdown()
