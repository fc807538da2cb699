"""CAN 2.0A frame lengths and bus load.

Role: how much of the bus the cyclic traffic takes, for the bench and for choosing a period.
Pure functions. The cyclic traffic is every frame that goes out each SYNC period: the drives'
(:func:`cia402_cycle_frames`) and, on a rig with one, the VCU's (:func:`vcu_cycle_frames`).

A CAN 2.0A (11-bit identifier) data frame with ``n`` data bytes has, on the wire::

    SOF 1, identifier 11, RTR 1, IDE 1, r0 1, DLC 4, data 8n, CRC 15      = 34 + 8n  (stuffed)
    CRC delimiter 1, ACK slot 1, ACK delimiter 1, EOF 7                  = 10       (not stuffed)
    intermission (interframe space) 3                                    = 3

so ``47 + 8n`` bits without stuff bits (the *nominal* length: 111 bits for 8 bytes, 47 for a
SYNC). The transmitter inserts a complementary bit after five equal bits from SOF to the end of
the CRC; the stuff bits count towards the next run, so the worst case is one stuff bit per four
bits after the first: ``floor((34 + 8n - 1) / 4)`` (Davis, Burns, Bril, Lukkien, Real-Time
Systems 35, 2007, correcting Tindell's ``floor((34 + 8n) / 5)``). The worst-case length is
``47 + 8n + floor((33 + 8n) / 4)``: 135 bits for 8 bytes, 55 for 0 bytes.
:func:`frame_bits_exact` counts the stuff bits of one concrete frame (CRC-15 included), which is
what the bus really carries; tests check it never exceeds the bound.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

__all__ = [
    "VCU_FRAME_BYTES",
    "BusLoad",
    "bus_load",
    "bus_load_report",
    "cia402_cycle_frames",
    "crc15",
    "frame_bits_exact",
    "frame_bits_nominal",
    "frame_bits_worst",
    "vcu_cycle_frames",
]

#: Payload of both VCU messages (``firmware_models/vcu.dbc``: VCU_Command, VCU_Status).
VCU_FRAME_BYTES = 8

_STUFFED_FIXED = 34  # SOF + 11 id + RTR + IDE + r0 + 4 DLC + 15 CRC
_UNSTUFFED_TAIL = 13  # CRC delimiter, ACK slot, ACK delimiter, 7 EOF, 3 intermission
_CRC15_POLY = 0x4599


def _check_dlc(payload_bytes: int) -> None:
    if not 0 <= payload_bytes <= 8:
        raise ValueError(f"a CAN 2.0 data frame carries 0..8 bytes, not {payload_bytes}")


def frame_bits_nominal(payload_bytes: int) -> int:
    """Bits of a standard data frame without stuff bits, intermission included (47 + 8n).

    Raises:
        ValueError: ``payload_bytes`` outside 0..8.
    """
    _check_dlc(payload_bytes)
    return _STUFFED_FIXED + 8 * payload_bytes + _UNSTUFFED_TAIL


def frame_bits_worst(payload_bytes: int) -> int:
    """Bits of a standard data frame with the most stuff bits any content can cause.

    Raises:
        ValueError: ``payload_bytes`` outside 0..8.
    """
    stuffed = _STUFFED_FIXED + 8 * payload_bytes
    return frame_bits_nominal(payload_bytes) + (stuffed - 1) // 4


def crc15(bits: Iterable[int]) -> int:
    """CAN CRC-15 (x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1, initial 0) of a bit sequence."""
    crc = 0
    for bit in bits:
        feedback = bit ^ (crc >> 14 & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CRC15_POLY
    return crc


def _bits(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def frame_bits_exact(can_id: int, data: bytes | bytearray) -> int:
    """Bits one standard data frame takes on the wire: its own stuff bits, intermission included.

    Args:
        can_id: 11-bit identifier.
        data: 0..8 payload bytes.

    Returns:
        Nominal length plus the stuff bits the transmitter inserts for this content.

    Raises:
        ValueError: ``can_id`` is not 11 bits or ``data`` is longer than 8 bytes.
    """
    if not 0 <= can_id <= 0x7FF:
        raise ValueError(f"CAN 2.0A identifier 0x{can_id:X} does not fit 11 bits")
    _check_dlc(len(data))
    bits = [0, *_bits(can_id, 11), 0, 0, 0, *_bits(len(data), 4)]
    for byte in data:
        bits += _bits(byte, 8)
    bits += _bits(crc15(bits), 15)
    stuff = 0
    run_bit, run = bits[0], 0
    for bit in bits:
        if bit == run_bit:
            run += 1
        else:
            run_bit, run = bit, 1
        if run == 5:
            stuff += 1
            run_bit, run = 1 - bit, 1  # the stuff bit starts the next run
    return len(bits) + stuff + _UNSTUFFED_TAIL


@dataclass(frozen=True, slots=True)
class BusLoad:
    """Bus load of a periodic frame set.

    Attributes:
        nominal: Fraction of the bitrate without stuff bits.
        worst_case: Fraction with worst-case stuff bits in every frame (the guaranteed bound).
        bits_per_s_nominal: Bits per second without stuff bits.
        bits_per_s_worst_case: Bits per second, worst case.
    """

    nominal: float
    worst_case: float
    bits_per_s_nominal: float
    bits_per_s_worst_case: float


def bus_load(
    frames_per_period: Iterable[tuple[int, float]],
    period_s: float,
    bitrate: float,
    stuffing: Literal["worst", "none"] = "worst",
) -> float:
    """Fraction of the bus a periodic frame set takes.

    Args:
        frames_per_period: (payload bytes, frames per period) pairs; the count may be fractional
            for slower frames (a 100 ms heartbeat is 0.02 frames per 2 ms period).
        period_s: Period (s), > 0.
        bitrate: Bus bitrate (bit/s), > 0.
        stuffing: ``worst`` for the worst-case stuffed length, ``none`` for the nominal length.

    Returns:
        Load as a fraction of ``bitrate`` (may exceed 1 for an impossible set).

    Raises:
        ValueError: A non-positive period or bitrate, or a payload outside 0..8 bytes.
    """
    if not (period_s > 0.0 and bitrate > 0.0):
        raise ValueError(f"period {period_s} s and bitrate {bitrate} bit/s must be > 0")
    length = frame_bits_worst if stuffing == "worst" else frame_bits_nominal
    bits = sum(length(n) * count for n, count in frames_per_period)
    return bits / period_s / bitrate


def cia402_cycle_frames(
    n_drives: int, period_s: float, heartbeat_period_s: float
) -> tuple[tuple[int, float], ...]:
    """The master's cyclic frame set per period (DESIGN.md "CAN protocol").

    Per period: RPDO1 (8 B) per drive, one SYNC (0 B), TPDO1 (8 B) per drive; heartbeats (1 B)
    of every drive and of the master, ``period_s / heartbeat_period_s`` each. TPDO2 (statusword;
    synchronous acyclic, sent only when it changed), RPDO2, SDO and EMCY are event traffic and
    not included: a few frames per state change, none while the drives run. Other nodes' frames
    (the VCU's: :func:`vcu_cycle_frames`) are added by the caller.

    Raises:
        ValueError: A non-positive period.
    """
    if not (period_s > 0.0 and heartbeat_period_s > 0.0):
        raise ValueError(
            f"period {period_s} s and heartbeat period {heartbeat_period_s} s must be > 0"
        )
    return (
        (8, float(n_drives)),  # RPDO1
        (0, 1.0),  # SYNC
        (8, float(n_drives)),  # TPDO1
        (1, (n_drives + 1) * period_s / heartbeat_period_s),  # heartbeats
    )


def vcu_cycle_frames(
    period_s: float, command_period_s: float | None = None
) -> tuple[tuple[int, float], ...]:
    """The VCU's frames per SYNC period (``firmware_models/vcu.dbc``).

    VCU_Status (8 B) on every SYNC; VCU_Command (8 B) every ``command_period_s`` when a client
    sends commands (None: none are sent; the DBC asks for one at least every 0.1 s while the
    VCU is enabled). No heartbeat: the VCU sends none.

    Raises:
        ValueError: A non-positive period.
    """
    if not (period_s > 0.0 and (command_period_s is None or command_period_s > 0.0)):
        raise ValueError(f"period {period_s} s and command period {command_period_s} s must be > 0")
    status = ((VCU_FRAME_BYTES, 1.0),)  # VCU_Status
    if command_period_s is None:
        return status
    return (*status, (VCU_FRAME_BYTES, period_s / command_period_s))  # VCU_Command


def bus_load_report(
    frames_per_period: Iterable[tuple[int, float]], period_s: float, bitrate: float
) -> BusLoad:
    """:class:`BusLoad` (nominal and worst case) of a periodic frame set; arguments as
    :func:`bus_load`."""
    frames = tuple(frames_per_period)
    nominal = bus_load(frames, period_s, bitrate, "none")
    worst = bus_load(frames, period_s, bitrate, "worst")
    return BusLoad(nominal, worst, nominal * bitrate, worst * bitrate)
