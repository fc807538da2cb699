"""A drive on the bus: a :class:`~firmware_models.drive.DriveFirmware` and one plant axis (a
cylinder, or the swing motor on a rig with swing).

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
* :attr:`FaultState.rock_direction` -- the axis has met a rock: that way (+1 extending, -1
  retracting) the soil resists past the cylinder's force, so the plant receives 0.0 (the axis
  stands, as braked) while the drive pushes into it or the axis moves into it (under gravity, a
  boom lowers with its drive still holding it up); pulling back is free. The drive's
  following-error check trips as for a jam once the demand runs on into the rock.
* :attr:`FaultState.report_offset_m` -- the position the drive reports in its TPDO1 jumps by this
  much (an encoder that lost counts on the way to the bus: a glitch of the load encoder the
  drive reports, while its servo runs on the motor encoder), so the plant does not move but the
  master reads a jump.

Clock-free like the firmware: every call takes ``now_s``. Not thread-safe; one owner (the HIL).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from firmware_models.drive import DriveFirmware, Frame

#: TPDO1's COB-ID base and its default mapping: position actual 0x6064 (i32, um), velocity
#: actual 0x606C (i32, um/s).
_COB_TPDO1 = 0x180
_TPDO1 = struct.Struct("<ii")

__all__ = ["DriveNode", "FaultState", "into_rock"]


@dataclass(slots=True)
class FaultState:
    """Faults injected into one drive node (mutable: a scenario switches them on at a time).

    Attributes:
        jammed: The axis is stuck: the plant receives effort 0.0 (braked) whatever the drive says.
        silent: The node sends no frame at all.
        deaf_to: Arbitration ids the node does not receive.
        report_offset_m: Added to the position the node reports in its TPDO1 (m).
        rock_direction: +1 or -1: the way the axis cannot push (a rock); 0: no rock.
    """

    jammed: bool = False
    silent: bool = False
    deaf_to: frozenset[int] = field(default_factory=frozenset)
    report_offset_m: float = 0.0
    rock_direction: float = 0.0

    def clear(self) -> None:
        """Every injected fault off (the cause is gone: a repaired stub, a freed axis)."""
        self.jammed = self.silent = False
        self.deaf_to = frozenset()
        self.report_offset_m = 0.0
        self.rock_direction = 0.0


def into_rock(faults: FaultState, effort: float, rate_m_s: float) -> bool:
    """The axis pushes or moves into its rock (:attr:`FaultState.rock_direction`)."""
    way = faults.rock_direction
    return effort * way > 0.0 or rate_m_s * way > 0.0


class DriveNode:
    """One emulated drive: firmware model, its plant axis, injected faults.

    Args:
        firmware: The drive's firmware model (node id, rig parameters, EDS).
        axis: Index of the plant axis it drives (0 boom, 1 stick, 2 bucket, 3 swing: the swing
            plant, :mod:`hil_sim.swing`, whose positions are rad).

    Attributes:
        firmware: The firmware model.
        axis: Plant axis index.
        faults: Injected faults (see :class:`FaultState`).
        effort: Effort the drive commanded in the last servo step (before a jam is applied).
    """

    def __init__(self, firmware: DriveFirmware, axis: int) -> None:
        if not 0 <= axis <= 3:
            raise ValueError(
                f"axis must be 0 (boom), 1 (stick), 2 (bucket) or 3 (swing); got {axis}"
            )
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
        faults = self.faults
        if faults.silent:
            return []
        if faults.report_offset_m:
            out = [self._offset(frame) for frame in out]
        return out

    def _offset(self, frame: Frame) -> Frame:
        """``frame`` with :attr:`FaultState.report_offset_m` added to a TPDO1's position."""
        cob, data = frame
        if cob != _COB_TPDO1 + self.firmware.node_id or len(data) != _TPDO1.size:
            return frame
        position_um, velocity_um_s = _TPDO1.unpack(data)
        position_um += round(self.faults.report_offset_m * 1e6)
        return cob, _TPDO1.pack(max(-(2**31), min(2**31 - 1, position_um)), velocity_um_s)

    def pending_frames(self, now_s: float) -> list[Frame]:
        """Time supervision of the firmware; returns its due heartbeats and emergencies."""
        out = self.firmware.pending_frames(now_s)
        return [] if self.faults.silent else out

    def servo_step(self, dt_s: float, stroke_m: float, stroke_rate_m_s: float) -> float:
        """One servo sub-step on the true stroke; returns the effort the plant receives."""
        self.effort = e = self.firmware.servo_step(dt_s, stroke_m, stroke_rate_m_s)
        faults = self.faults
        stands = faults.jammed or (faults.rock_direction and into_rock(faults, e, stroke_rate_m_s))
        return 0.0 if stands else e
