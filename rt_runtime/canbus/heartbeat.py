"""Heartbeat (CiA 301 error control): frames, a producer and a consumer driven by ``now_s``.

Role: the master produces its own heartbeat (node 0x7E by default, COB-ID 0x77E) that the drives
consume through 0x1016, and consumes the drives' heartbeats (0x700 + id) with a timeout. Neither
class reads a clock: every method takes ``now_s`` (monotonic or simulated seconds), so the same
code runs in lockstep and in real time. Both are safe inside the loop (no allocation but the
events they report).

Frame: COB-ID 0x700 + node id, one byte, the NMT state (0x00 boot-up, 0x04 stopped,
0x05 operational, 0x7F pre-operational).

Consumer rules (CiA 301 7.2.8.3.2.2): a node is monitored from its first heartbeat on, or from
:meth:`HeartbeatConsumer.start` for nodes that must be there already; it times out when no
heartbeat came for longer than the timeout. Each timeout is reported once, as is the recovery.
A boot-up message from a node (state 0x00) is reported as ``BOOT_UP``: outside boot it means the
drive reset itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import can

from rt_runtime.canbus.nmt import NmtState
from rt_runtime.canbus.pdo import COB_HEARTBEAT

__all__ = [
    "HeartbeatConsumer",
    "HeartbeatEvent",
    "HeartbeatEventKind",
    "HeartbeatProducer",
    "heartbeat_message",
    "parse_heartbeat",
]


class HeartbeatEventKind(IntEnum):
    """What happened to a monitored node."""

    TIMEOUT = 1
    RECOVERED = 2
    BOOT_UP = 3
    STATE_CHANGED = 4


@dataclass(frozen=True, slots=True)
class HeartbeatEvent:
    """One heartbeat event.

    Attributes:
        node_id: The node.
        kind: What happened.
        state: The node's NMT state as last heard (None if never heard).
        now_s: When it was noticed.
    """

    node_id: int
    kind: HeartbeatEventKind
    state: NmtState | None
    now_s: float


def heartbeat_message(node_id: int, state: NmtState) -> can.Message:
    """The heartbeat frame of ``node_id`` reporting ``state``."""
    return can.Message(
        arbitration_id=COB_HEARTBEAT + node_id, is_extended_id=False, data=bytearray((int(state),))
    )


def parse_heartbeat(data: bytes | bytearray) -> NmtState | None:
    """The NMT state a heartbeat payload reports, or None for a malformed one.

    Bit 7 (the toggle bit of node guarding) is ignored.
    """
    if len(data) != 1:
        return None
    try:
        return NmtState(data[0] & 0x7F)
    except ValueError:
        return None


class HeartbeatProducer:
    """Decides when the master's heartbeat is due and holds the reusable frame.

    Args:
        node_id: Producer node id (0x7E for the master).
        period_s: Heartbeat period; 0 disables the producer.
        state: NMT state to report.

    Raises:
        ValueError: ``period_s`` is negative or not finite.
    """

    __slots__ = ("_next_s", "message", "period_s")

    def __init__(self, node_id: int, period_s: float, state: NmtState = NmtState.OPERATIONAL):
        if not (math.isfinite(period_s) and period_s >= 0.0):
            raise ValueError(f"heartbeat period {period_s} s must be finite and >= 0")
        self.period_s = period_s
        self.message = heartbeat_message(node_id, state)
        self._next_s: float | None = None

    def set_state(self, state: NmtState) -> None:
        """Report ``state`` from the next heartbeat on."""
        self.message.data[0] = int(state)

    @property
    def next_due_s(self) -> float | None:
        """When the next heartbeat is due (None before the first one or when disabled)."""
        return self._next_s if self.period_s > 0.0 else None

    def due(self, now_s: float) -> bool:
        """Whether a heartbeat is due at ``now_s``; if so, counts it as sent.

        The first call is always due. Later ones keep a fixed grid (no drift); after a stall
        longer than a period the grid restarts at ``now_s``.
        """
        if self.period_s == 0.0:
            return False
        if self._next_s is None or now_s >= self._next_s:
            nxt = (now_s if self._next_s is None else self._next_s) + self.period_s
            self._next_s = nxt if nxt > now_s else now_s + self.period_s
            return True
        return False


class HeartbeatConsumer:
    """Monitors the heartbeats of a set of nodes.

    Args:
        node_ids: Nodes to monitor.
        timeout_s: Time without a heartbeat after which a node is lost (> 0).

    Raises:
        ValueError: ``timeout_s`` is not positive and finite.
    """

    __slots__ = ("_last_s", "_lost", "_state", "node_ids", "timeout_s")

    def __init__(self, node_ids: tuple[int, ...], timeout_s: float):
        if not (math.isfinite(timeout_s) and timeout_s > 0.0):
            raise ValueError(f"heartbeat timeout {timeout_s} s must be finite and > 0")
        self.node_ids = node_ids
        self.timeout_s = timeout_s
        self._last_s: dict[int, float] = {}
        self._state: dict[int, NmtState] = {}
        self._lost: set[int] = set()

    def start(self, now_s: float) -> None:
        """Monitor every node from ``now_s`` on, also those not heard yet."""
        for node in self.node_ids:
            self._last_s.setdefault(node, now_s)

    def reset(self) -> None:
        """Forget every node (before an NMT reset)."""
        self._last_s.clear()
        self._state.clear()
        self._lost.clear()

    def state(self, node_id: int) -> NmtState | None:
        """Last NMT state heard from ``node_id`` (None if none)."""
        return self._state.get(node_id)

    def last_seen_s(self, node_id: int) -> float | None:
        """When ``node_id`` was last heard (None if never)."""
        return self._last_s.get(node_id) if node_id in self._state else None

    def is_lost(self, node_id: int) -> bool:
        """Whether ``node_id`` has timed out and not been heard since."""
        return node_id in self._lost

    def on_heartbeat(self, node_id: int, state: NmtState, now_s: float) -> HeartbeatEvent | None:
        """Record a heartbeat; returns the event it causes, if any.

        Nodes not in ``node_ids`` are ignored (None).
        """
        if node_id not in self.node_ids:
            return None
        previous = self._state.get(node_id)
        self._last_s[node_id] = now_s
        self._state[node_id] = state
        if node_id in self._lost:
            self._lost.discard(node_id)
            if state is not NmtState.BOOT_UP:
                return HeartbeatEvent(node_id, HeartbeatEventKind.RECOVERED, state, now_s)
        if state is NmtState.BOOT_UP:
            return HeartbeatEvent(node_id, HeartbeatEventKind.BOOT_UP, state, now_s)
        if previous is not None and previous is not state:
            return HeartbeatEvent(node_id, HeartbeatEventKind.STATE_CHANGED, state, now_s)
        return None

    def check(self, now_s: float, out: list[HeartbeatEvent]) -> None:
        """Append a ``TIMEOUT`` event to ``out`` for every node that just timed out."""
        for node, last_s in self._last_s.items():
            if node not in self._lost and now_s - last_s > self.timeout_s:
                self._lost.add(node)
                out.append(
                    HeartbeatEvent(node, HeartbeatEventKind.TIMEOUT, self._state.get(node), now_s)
                )
