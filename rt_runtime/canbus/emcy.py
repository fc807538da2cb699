"""EMCY (CiA 301 emergency) frames: error codes, decoding and a builder.

Role: the master's emergency consumer decodes what a drive reports (following error, heartbeat
loss, RPDO/SYNC watchdog, ...); the builder is shared with tests and emulators. Pure functions;
safe inside the loop (one small frozen object per EMCY received, which is rare).

Frame: COB-ID 0x080 + node id, 8 bytes: error code u16 LE, error register (0x1001) u8,
5 manufacturer-specific bytes. Code 0x0000 means "error reset / no error": the drive sends it
when its last error has gone (after a fault reset).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import can

from rt_runtime.canbus.pdo import COB_EMCY

__all__ = ["EMCY_MEANINGS", "Emcy", "EmcyCode", "emcy_meaning", "emcy_message", "parse_emcy"]

_EMCY = struct.Struct("<HB5s")


class EmcyCode(IntEnum):
    """Emergency error codes this project knows (CiA 301 Table 21, CiA 402 Annex)."""

    NO_ERROR = 0x0000
    GENERIC = 0x1000
    CONTINUOUS_OVER_CURRENT = 0x2310
    DC_LINK_OVER_VOLTAGE = 0x3210
    DC_LINK_UNDER_VOLTAGE = 0x3220
    DRIVE_TEMPERATURE = 0x4310
    DEVICE_HARDWARE = 0x5000
    INTERNAL_SOFTWARE = 0x6100
    SENSOR = 0x7300
    CAN_OVERRUN = 0x8110
    CAN_ERROR_PASSIVE = 0x8120
    HEARTBEAT_ERROR = 0x8130
    BUS_OFF_RECOVERED = 0x8140
    PDO_LENGTH_ERROR = 0x8210
    PDO_LENGTH_EXCEEDED = 0x8220
    RPDO_TIMEOUT = 0x8250
    FOLLOWING_ERROR = 0x8611
    DEVICE_SPECIFIC = 0xFF00


#: What each known code means, for people (fault messages, logs).
EMCY_MEANINGS: dict[int, str] = {
    EmcyCode.NO_ERROR: "error reset: the drive's last error has gone",
    EmcyCode.GENERIC: "generic error",
    EmcyCode.CONTINUOUS_OVER_CURRENT: "continuous over-current in the motor output",
    EmcyCode.DC_LINK_OVER_VOLTAGE: "DC link over-voltage",
    EmcyCode.DC_LINK_UNDER_VOLTAGE: "DC link under-voltage (supply lost or too low)",
    EmcyCode.DRIVE_TEMPERATURE: "drive over-temperature",
    EmcyCode.DEVICE_HARDWARE: "drive hardware fault",
    EmcyCode.INTERNAL_SOFTWARE: "drive firmware error",
    EmcyCode.SENSOR: "position sensor (encoder) fault",
    EmcyCode.CAN_OVERRUN: "CAN receive overrun: the drive lost frames",
    EmcyCode.CAN_ERROR_PASSIVE: "the drive's CAN controller is error passive",
    EmcyCode.HEARTBEAT_ERROR: "heartbeat lost: no heartbeat from the master within 0x1016",
    EmcyCode.BUS_OFF_RECOVERED: "the drive's CAN controller recovered from bus-off",
    EmcyCode.PDO_LENGTH_ERROR: "an RPDO was too short and was dropped",
    EmcyCode.PDO_LENGTH_EXCEEDED: "an RPDO was longer than its mapping",
    EmcyCode.RPDO_TIMEOUT: (
        "SYNC/RPDO watchdog: no SYNC or setpoint from the master within the drive's timeout "
        "(the master stopped cycling or the bus is gone)"
    ),
    EmcyCode.FOLLOWING_ERROR: (
        "following error: the axis stayed farther from its demand than 0x6065 for longer "
        "than 0x6066"
    ),
    EmcyCode.DEVICE_SPECIFIC: "manufacturer-specific error",
}

#: CiA 301 error code classes (the high nibble, or byte for 0xF0/0xFF), for unknown codes.
_CLASSES = {
    0x1: "generic error",
    0x2: "current error",
    0x3: "voltage error",
    0x4: "temperature error",
    0x5: "device hardware error",
    0x6: "device software error",
    0x7: "additional modules error",
    0x8: "monitoring or communication error",
    0x9: "external error",
}


def emcy_meaning(code: int) -> str:
    """What an emergency error code means (a known code's text, else its CiA 301 class)."""
    known = EMCY_MEANINGS.get(int(code))
    if known is not None:
        return known
    high = (int(code) >> 8) & 0xFF
    if high == 0xFF:
        return "manufacturer-specific error"
    if high == 0xF0:
        return "additional functions error"
    kind = _CLASSES.get(high >> 4)
    return f"unknown code of class: {kind}" if kind is not None else "unknown code"


@dataclass(frozen=True, slots=True)
class Emcy:
    """A decoded emergency message.

    Attributes:
        node_id: The node that sent it.
        code: Error code; an :class:`EmcyCode` where known, else the raw int.
        error_register: Object 0x1001 at the time of the error.
        manufacturer: The five manufacturer-specific bytes.
        now_s: When the master received it.
    """

    node_id: int
    code: int
    error_register: int
    manufacturer: bytes
    now_s: float

    @property
    def is_reset(self) -> bool:
        """Whether this is the "error reset / no error" message (code 0)."""
        return self.code == 0

    @property
    def description(self) -> str:
        """Code name, e.g. ``FOLLOWING_ERROR (0x8611)``."""
        name = self.code.name if isinstance(self.code, EmcyCode) else "UNKNOWN"
        return f"{name} (0x{int(self.code):04X})"

    @property
    def meaning(self) -> str:
        """What the code means (:func:`emcy_meaning`)."""
        return emcy_meaning(self.code)


def parse_emcy(node_id: int, data: bytes | bytearray, now_s: float) -> Emcy | None:
    """Decode an EMCY payload; None when it is not 8 bytes long."""
    if len(data) != 8:
        return None
    raw, register, manufacturer = _EMCY.unpack(data)
    code: int
    try:
        code = EmcyCode(raw)
    except ValueError:
        code = raw
    return Emcy(node_id, code, register, manufacturer, now_s)


def emcy_message(
    node_id: int, code: int, error_register: int, manufacturer: bytes = bytes(5)
) -> can.Message:
    """The EMCY frame of ``node_id``.

    Raises:
        ValueError: ``manufacturer`` is longer than 5 bytes, or a field is out of range.
    """
    if len(manufacturer) > 5:
        raise ValueError(f"EMCY manufacturer data is {len(manufacturer)} bytes, at most 5 fit")
    try:
        data = _EMCY.pack(code, error_register, manufacturer)
    except struct.error as exc:
        raise ValueError(f"EMCY code 0x{code:X} or register {error_register} out of range") from exc
    return can.Message(arbitration_id=COB_EMCY + node_id, is_extended_id=False, data=data)
