"""VCU client: travel and swing commands out, VCU status in, from the DBC message set (cantools).

Role: the runtime's side of the vehicle control unit (Yao et al. 2023, 5.1: travel and swing
motors). The message set lives in ``firmware_models/vcu.dbc`` (the emulator's VCU model reads the
same file); this module encodes ``VCU_Command`` and decodes ``VCU_Status`` with cantools, so the
frame layout has one authority. At construction the client checks that the DBC's value tables
(TravelMode, State, Fault) match the enums here, so a changed DBC fails at start-up, not in the
loop.

Frame ids: the DBC is written for node 0x10 (command 0x210, status 0x190, i.e. 0x200 + node and
0x180 + node like RPDO1/TPDO1 of CiA 301); a VCU at ``rig.can.vcu_node_id`` shifts both by the
difference.

Cost: one cantools encode or decode is some tens of microseconds, small
against a 2 ms cycle; both are safe inside the loop (no I/O; a status frame that does not decode
returns None and counts in :attr:`VcuClient.decode_errors`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Protocol

import can
import cantools
from cantools.database.can import Database, Message

from firmware_models import VCU_DBC, VCU_DBC_NODE_ID
from rt_runtime.errors import ConfigurationError

__all__ = [
    "TravelMode",
    "VcuClient",
    "VcuCommand",
    "VcuFault",
    "VcuState",
    "VcuStatus",
]


class TravelMode(IntEnum):
    """How the VCU uses the travel fields of a command (DBC ``VCU_Command.TravelMode``)."""

    STOP = 0
    SPEED = 1  # travel_speed_m_s is the setpoint
    POSITION = 2  # travel_target_m is the target, |travel_speed_m_s| the speed limit


class VcuState(IntEnum):
    """DBC ``VCU_Status.State``."""

    DISABLED = 0
    ENABLED = 1
    STOPPING = 2
    FAULT = 3


class VcuFault(IntEnum):
    """DBC ``VCU_Status.Fault``."""

    NONE = 0
    COMMAND_TIMEOUT = 1
    MOTOR = 2


@dataclass(frozen=True, slots=True)
class VcuCommand:
    """One ``VCU_Command``.

    Attributes:
        enable: Motors enabled and following the command; False decelerates both axes to rest.
        travel_mode: Use of the travel fields.
        travel_speed_m_s: SPEED: signed setpoint; POSITION: speed limit (magnitude).
        travel_target_m: POSITION: travel position target (from the position at power-on).
        swing_angle_rad: Swing angle target.
        fault_reset: Rising edge clears a VCU fault (with ``enable`` False, axes at rest).
    """

    enable: bool
    travel_mode: TravelMode = TravelMode.STOP
    travel_speed_m_s: float = 0.0
    travel_target_m: float = 0.0
    swing_angle_rad: float = 0.0
    fault_reset: bool = False


@dataclass(frozen=True, slots=True)
class VcuStatus:
    """One decoded ``VCU_Status``.

    Attributes:
        state: VCU state.
        fault: Latched fault.
        travel_position_m: Travel position (resolution 1 mm).
        swing_angle_rad: Swing angle (resolution 0.1 mrad).
        travel_speed_m_s: Travel speed (resolution 1 mm/s).
    """

    state: VcuState
    fault: VcuFault
    travel_position_m: float
    swing_angle_rad: float
    travel_speed_m_s: float


class _CanLike(Protocol):
    @property
    def vcu_node_id(self) -> int: ...


class _RigLike(Protocol):
    @property
    def can(self) -> _CanLike: ...


_STATES = frozenset(m.value for m in VcuState)
_FAULTS = frozenset(m.value for m in VcuFault)

_ENUMS: dict[tuple[str, str], type[IntEnum]] = {
    ("VCU_Command", "TravelMode"): TravelMode,
    ("VCU_Status", "State"): VcuState,
    ("VCU_Status", "Fault"): VcuFault,
}


def _load(dbc: Path | str) -> Database:
    path = Path(dbc)
    if not path.is_file():
        raise ConfigurationError(f"VCU DBC file {path} does not exist")
    db = cantools.database.load_file(str(path))
    if not isinstance(db, Database):
        raise ConfigurationError(f"{path} is not a CAN database")
    for (message_name, signal_name), enum in _ENUMS.items():
        try:
            signal = db.get_message_by_name(message_name).get_signal_by_name(signal_name)
        except KeyError:
            raise ConfigurationError(
                f"{path}: signal {message_name}.{signal_name} is missing"
            ) from None
        choices = {int(value): str(name) for value, name in (signal.choices or {}).items()}
        expected = {member.value: member.name for member in enum}
        if choices != expected:
            raise ConfigurationError(
                f"{path}: value table of {message_name}.{signal_name} is {choices}; the runtime "
                f"expects {expected}"
            )
    return db


class VcuClient:
    """Encodes VCU commands and decodes VCU status frames for one VCU.

    Args:
        node_id: The VCU's node id (``rig.can.vcu_node_id``), 1..127.
        dbc: Message set.

    Raises:
        ConfigurationError: Bad node id, missing DBC, or a DBC whose value tables differ from
            :class:`TravelMode`, :class:`VcuState`, :class:`VcuFault`.
    """

    def __init__(self, node_id: int, dbc: Path | str = VCU_DBC) -> None:
        if not 1 <= node_id <= 127:
            raise ConfigurationError(f"VCU node id {node_id} is outside 1..127")
        db = _load(dbc)
        self.node_id = node_id
        self._command: Message = db.get_message_by_name("VCU_Command")
        self._status: Message = db.get_message_by_name("VCU_Status")
        #: Arbitration id of VCU_Command for this node.
        self.command_id = int(self._command.frame_id) - VCU_DBC_NODE_ID + node_id
        #: Arbitration id of VCU_Status for this node.
        self.status_id = int(self._status.frame_id) - VCU_DBC_NODE_ID + node_id
        #: Status frames with the status id that did not decode.
        self.decode_errors = 0
        self._ranges = {
            s.name: (
                float(s.minimum) if s.minimum is not None else -math.inf,
                float(s.maximum) if s.maximum is not None else math.inf,
            )
            for s in self._command.signals
        }

    @classmethod
    def from_rig(cls, rig: _RigLike, dbc: Path | str = VCU_DBC) -> VcuClient:
        """The client for ``rig.can.vcu_node_id``."""
        return cls(rig.can.vcu_node_id, dbc)

    def _saturate(self, name: str, value: float) -> float:
        if not math.isfinite(value):
            raise ValueError(f"VCU command field {name} is {value!r}; it must be finite")
        low, high = self._ranges[name]
        return min(max(value, low), high)

    def encode_command(self, command: VcuCommand) -> bytes:
        """Payload of ``VCU_Command`` (8 bytes).

        Speeds, positions and angles beyond the signals' ranges are saturated to them (the VCU
        limits them further); the DBC's resolution rounds them (1 mm/s, 1 mm, 0.1 mrad).

        Raises:
            ValueError: A field is NaN or infinite.
        """
        data = self._command.encode(
            {
                "Enable": int(command.enable),
                "TravelMode": int(command.travel_mode),
                "FaultReset": int(command.fault_reset),
                "TravelSpeedCmd": self._saturate("TravelSpeedCmd", command.travel_speed_m_s),
                "TravelTargetPos": self._saturate("TravelTargetPos", command.travel_target_m),
                "SwingAngleCmd": self._saturate("SwingAngleCmd", command.swing_angle_rad),
            }
        )
        return bytes(data)

    def command_frame(self, command: VcuCommand) -> tuple[int, bytes]:
        """``(arbitration id, payload)`` of a command."""
        return self.command_id, self.encode_command(command)

    def command_message(self, command: VcuCommand) -> can.Message:
        """A python-can message carrying ``command`` (11-bit id)."""
        return can.Message(
            arbitration_id=self.command_id, data=self.encode_command(command), is_extended_id=False
        )

    def decode_status(self, arbitration_id: int, data: bytes | bytearray) -> VcuStatus | None:
        """Decode a frame if it is this VCU's status.

        Returns:
            The status, or None when the frame is another one or does not decode (counted in
            :attr:`decode_errors`).
        """
        if arbitration_id != self.status_id:
            return None
        try:
            fields = self._status.decode(bytes(data), decode_choices=False)
        except cantools.database.DecodeError:
            self.decode_errors += 1
            return None
        if not isinstance(fields, dict):
            self.decode_errors += 1
            return None
        values = {name: value for name, value in fields.items() if isinstance(value, int | float)}
        state, fault = int(values.get("State", -1)), int(values.get("Fault", -1))
        if state not in _STATES or fault not in _FAULTS or len(values) != len(fields):
            self.decode_errors += 1
            return None
        return VcuStatus(
            state=VcuState(state),
            fault=VcuFault(fault),
            travel_position_m=float(values["TravelPosition"]),
            swing_angle_rad=float(values["SwingAngle"]),
            travel_speed_m_s=float(values["TravelSpeed"]),
        )
