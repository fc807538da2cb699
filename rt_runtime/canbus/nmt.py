"""NMT (CiA 301 network management): commands, node states, frame builders and parsers.

Role: the frames the master uses to reset, start and stop nodes. Pure functions, no I/O; the
master sends what they build. Node states travel in heartbeats (:mod:`rt_runtime.canbus.heartbeat`).

Frame: COB-ID 0x000, two bytes ``[command, node id]`` (node id 0 addresses every node).
"""

from __future__ import annotations

from enum import IntEnum

import can

from rt_runtime.canbus.pdo import COB_NMT

__all__ = ["NmtCommand", "NmtState", "nmt_message", "parse_nmt"]


class NmtCommand(IntEnum):
    """NMT command specifiers."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as a heartbeat reports them."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def nmt_message(command: NmtCommand, node_id: int) -> can.Message:
    """The NMT frame commanding ``node_id`` (0 = all nodes).

    Raises:
        ValueError: ``node_id`` is outside 0..127.
    """
    if not 0 <= node_id <= 127:
        raise ValueError(f"NMT node id {node_id} is outside 0..127")
    return can.Message(
        arbitration_id=COB_NMT, is_extended_id=False, data=bytearray((int(command), node_id))
    )


def parse_nmt(data: bytes | bytearray) -> tuple[NmtCommand, int] | None:
    """(command, node id) of an NMT frame's payload, or None if it is not a valid NMT command."""
    if len(data) != 2:
        return None
    try:
        return NmtCommand(data[0]), data[1]
    except ValueError:
        return None
