"""A cylinder drive on the bus: a :class:`~firmware_models.drive.DriveFirmware` and one plant axis.

Role: the HIL's emulated servo drive. A :class:`DriveNode` routes the frames the bus delivers to
its firmware model, returns the firmware's replies and time-triggered frames, and runs the
firmware's servo cascade on the plant's true stroke of its axis (the firmware quantises it like
an encoder). Faults that a scenario injects are applied here, at the boundary between the drive
and the world, so the firmware behaves exactly as it would on a real bus:

* :attr:`DriveNode.jammed` -- the axis is mechanically stuck (a seized screw, a motor phase lost
  with the holding brake engaged): the effort reaching the plant is exactly 0.0, which the plant
  treats as a braked axis. The drive's servo cascade keeps pushing, its following error grows
  until the window 0x6065 is exceeded for 0x6066, and the firmware itself raises EMCY 0x8611.
* :attr:`DriveNode.silent` -- the node's transmitter is gone (a broken CAN stub, the drive lost
  its logic supply's CAN transceiver): it still receives and moves but sends nothing, so the
  master sees no heartbeat and no TPDOs.
* :attr:`DriveNode.deaf_to` -- COB-IDs the node no longer receives (the master's heartbeat 0x77E,
  say): the firmware's heartbeat consumer times out and it takes its fault reaction (EMCY 0x8130).

Clock-free like the firmware: every call takes ``now_s``. Not thread-safe; one owner (the HIL).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from firmware_models.drive import DriveFirmware, Frame

__all__ = ["DriveNode", "FaultState"]


@dataclass(slots=True)
class FaultState:
    """Faults injected into one drive node (mutable: a scenario switches them on at a time).

    Attributes:
        jammed: The axis is stuck: the plant receives effort 0.0 (braked) whatever the drive says.
        silent: The node sends no frame at all.
        deaf_to: Arbitration ids the node does not receive.
    """

    jammed: bool = False
    silent: bool = False
    deaf_to: frozenset[int] = field(default_factory=frozenset)


class DriveNode:
    """One emulated drive: firmware model, its plant axis, injected faults.

    Args:
        firmware: The drive's firmware model (node id, rig parameters, EDS).
        axis: Index of the plant axis it drives (0 boom, 1 stick, 2 bucket).

    Attributes:
        firmware: The firmware model.
        axis: Plant axis index.
        faults: Injected faults (see :class:`FaultState`).
        effort: Effort the drive commanded in the last servo step (before a jam is applied).
    """

    def __init__(self, firmware: DriveFirmware, axis: int) -> None:
        if not 0 <= axis <= 2:
            raise ValueError(f"axis must be 0 (boom), 1 (stick) or 2 (bucket); got {axis}")
        self.firmware = firmware
        self.axis = axis
        self.faults = FaultState()
        self.effort = 0.0

    @property
    def node_id(self) -> int:
        """The drive's CAN node id."""
        return self.firmware.node_id

    def on_frame(self, arbitration_id: int, data: bytes, now_s: float) -> list[Frame]:
        """Deliver one bus frame; returns the frames the node puts on the bus in reply."""
        if arbitration_id in self.faults.deaf_to:
            return []
        out = self.firmware.on_frame(arbitration_id, data, now_s)
        return [] if self.faults.silent else out

    def pending_frames(self, now_s: float) -> list[Frame]:
        """Time supervision of the firmware; returns its due heartbeats and emergencies."""
        out = self.firmware.pending_frames(now_s)
        return [] if self.faults.silent else out

    def servo_step(self, dt_s: float, stroke_m: float, stroke_rate_m_s: float) -> float:
        """One servo sub-step on the true stroke; returns the effort the plant receives."""
        self.effort = self.firmware.servo_step(dt_s, stroke_m, stroke_rate_m_s)
        return 0.0 if self.faults.jammed else self.effort
