"""Behaviour model of the CiA 402 cylinder drive firmware (CiA 301 communication + CiA 402 CSP).

Role: what a servo drive of the rig does with the frames the master sends, and what force (or
valve command) it puts on its cylinder. The HIL runs one :class:`DriveFirmware` per axis on the
bus; the model is bus-agnostic and clock-free: frames come in through :meth:`on_frame` with the
time they arrived, time-triggered frames (heartbeats, emergencies) come out of
:meth:`pending_frames`, and the servo cascade advances by an explicit ``dt_s`` in
:meth:`servo_step`. The same code therefore runs in lockstep (simulated time) and in real time.

Communication (CiA 301), object dictionary from ``cia402_drive.eds`` (see that file):

* NMT: INITIALISING -> boot-up heartbeat ``0x700+id [00]`` -> PRE-OPERATIONAL; start, stop,
  enter pre-operational, reset node (every object back to its stored value), reset communication
  (0x1000-0x1FFF only). Initialisation at power-on completes on the first
  :meth:`pending_frames` call; after an NMT reset the boot-up frame is the reply to the NMT frame.
* SDO server on 0x600+id / 0x580+id: expedited and segmented download and upload, aborts with
  the CiA 301 codes of :class:`SdoAbort`. Block transfer is not supported (abort 0x05040001).
* PDOs from the mapping objects as they stand (remapping follows CiA 301: COB-ID invalid, then
  sub-index 0 = 0, entries, sub-index 0 = n, then COB-ID valid). Synchronous RPDOs (type 0-240)
  are buffered and applied at the next SYNC; event RPDOs (0xFE, 0xFF) on receipt. TPDOs of type
  1-240 go out on every n-th SYNC; type 0 (synchronous acyclic, CiA 301: sent at a SYNC after an
  event, here a change of its content since the last one sent) at the first SYNC whose sampled
  content differs from what it last sent. Whether entering OPERATIONAL counts as such a change is
  the drive's choice (CiA 301 requires no transmission then): with ``tpdo_at_start`` (the
  default) the content is sent at the first SYNC after every NMT start; without it the content
  at NMT start is the baseline and nothing goes out until it changes. Event TPDOs (0xFE, 0xFF)
  are not supported (abort 0x06090030). A short RPDO is dropped with EMCY 0x8210.
* SYNC 0x080: apply buffered RPDOs, latch the CSP setpoint, send the TPDOs (operational only),
  sampled at the SYNC, i.e. from the last servo step, before the new period's motion.
* Heartbeat producer (0x1017) and consumer of the master (0x1016 sub 1: producer node id in bits
  16-23, time in ms in bits 0-15; monitoring starts with the first heartbeat received).
* EMCY on 0x1014: ``[error code u16, error register u8, 00 00 00 00 00]``; not sent while
  STOPPED. Codes: 0x8611 following error, 0x8130 heartbeat loss, 0x8250 missing SYNC/RPDO,
  0x8210 short PDO, 0x0000 after a fault reset, anything given to :meth:`inject_fault`.

Device control (CiA 402): the power drive state machine with every transition 0-16; fault reset
on the 0 -> 1 edge of controlword bit 7; quick stop option codes (0x605A) 0 (disable at once),
2 (quick-stop ramp, then SWITCH ON DISABLED) and 6 (quick-stop ramp, stay in QUICK STOP ACTIVE,
transition 16 allowed); fault reaction option codes (0x605E) 0 (disable at once) and 2
(quick-stop ramp). Ramps decelerate at 0x6085 from the measured position and velocity, so a
blocked axis is not pulled back towards an unreachable demand. Mode 8 (cyclic synchronous
position) with the velocity offset 0x60B1 as feed-forward; mode 0 holds the position at which
operation was enabled.

Servo cascade (:meth:`servo_step`, sub-step ``dt_s``, 250 us by default):

* encoder quantisation of the true stroke to ``encoder_resolution_m``; velocity from the
  difference of quantised positions, low-pass filtered with ``velocity_filter_s``;
* CSP interpolation: at each SYNC a segment starts at the current demand and ends at the latched
  target (clamped to the software limits 0x607D when min < max) after one interpolation period:
  0x60C2 (value * 10^index s) when its value is not 0, else 0x1006 when not 0, else the measured
  SYNC interval. The velocity offset is interpolated the same way. When a segment ends before
  the next SYNC the demand holds, so a late SYNC never makes the demand overshoot;
* electric: ``v_cmd = Kp (p_demand - p) + v_offset`` clamped to +-velocity_max, then a velocity
  PI ``u = Kv (e_v + Ki * integral(e_v))`` saturated to [-1, 1]; the integral stops while the
  output is saturated in the direction of the error (conditional integration) and is bounded to
  what the output can use. The effort is a fraction of the cylinder's force_max_n;
* hydraulic (no velocity loop): ``u = v_cmd / K_q`` with the valve's no-load velocity gain
  ``K_q`` (rod speed at full opening, from the rated flow per metering edge at 3.5 MPa and the
  differential cylinder's area balance, see :func:`valve_velocity_gains_m_s`; one value
  extending, one retracting), saturated to [-1, 1] (the spool's full opening). With load
  compensation (``load_compensation_filter_s`` > 0) the gain follows the load: the drive reads
  the cylinder force ``F = p_A A_A - p_B A_B`` from its chamber-pressure transducers (the
  ``load_force_n`` argument), low-passes it, and divides by the steady-state flow-gain ratio
  of the orifice law under that force, ``sqrt(1 - F / (p_s A_A))`` extending and
  ``sqrt(1 + F / (p_s A_B))`` retracting (:func:`load_gain_ratio`); a boom held up by its
  weight then extends slower and lowers faster than without load, and the drive opens the
  valve that much more or less. With dynamic pressure feedback (a per-cylinder
  ``pressure_feedback_gain`` > 0) the opening is then lessened by
  ``gain (F - LP(F)) / (p_s A_A)``, ``LP`` a first-order low-pass of
  ``pressure_feedback_filter_s``: a leakage across the piston for changes of the load faster
  than the filter, which damps the oil column's mode, and nothing for a held load. With overlap
  compensation (0x2100 > 0, in 0.01 % of full opening) the command finally jumps out of the
  valve's dead band: ``sign(u) (j + (1 - j) |u|)`` for ``|u| >= OVERLAP_JUMP_RAMP`` and a
  straight line through zero inside it (:func:`overlap_jump`), as a valve amplifier's jump
  function does;
* following error: ``|p_demand - p| > 0x6065`` continuously for longer than 0x6066 -> EMCY
  0x8611, statusword bit 13, fault reaction; 0x6065 = 0xFFFFFFFF switches it off;
* disabled states put out 0 (motor free or valve centred) and the demand follows the measured
  position, so enabling never jumps.

Supervision in :meth:`pending_frames`: lost master heartbeat -> EMCY 0x8130 and fault reaction
(the NMT state is kept, so TPDO2 still reports the fault); while OPERATION ENABLED no SYNC or no
RPDO1 for longer than ``sync_timeout_s`` -> EMCY 0x8250 and fault reaction (this runs whatever the
NMT state, so stopping the node's PDOs by NMT also stops the axis).

Parameters not in the object dictionary come from the rig: ``rig.drives`` (gains, encoder, servo
period, timeouts) and ``rig.actuators`` (velocity limit, hydraulic valve). The stored value of
the objects the rig also sets (0x1016 sub 1 with the master's node id 0x7E, 0x1017, 0x6065,
0x6066, 0x6085) is the rig's, as if the drive had been commissioned with it; the other objects
start at the EDS defaults. An NMT reset restores the stored values.

Everything here is cheap per call and never raises inside the cycle: a frame the drive cannot
use is ignored or answered with an SDO abort, as a drive would. Constructors raise
:class:`~firmware_models.errors.FirmwareConfigurationError` for bad parameters.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum, IntEnum
from functools import lru_cache
from pathlib import Path
from types import MappingProxyType
from typing import Protocol

from canopen.objectdictionary import ODArray, ODRecord, ODVariable, import_od

from firmware_models import CIA402_DRIVE_EDS
from firmware_models.errors import FirmwareConfigurationError

__all__ = [
    "LOAD_GAIN_RATIO_MIN",
    "MASTER_NODE_ID",
    "DeviceState",
    "DriveFirmware",
    "DriveKind",
    "DriveParameters",
    "EmcyCode",
    "Frame",
    "NmtCommand",
    "NmtState",
    "OdEntry",
    "SdoAbort",
    "load_gain_ratio",
    "load_object_dictionary",
    "overlap_jump",
    "valve_velocity_gains_m_s",
]

#: A CAN frame as (arbitration id, data).
Frame = tuple[int, bytes]

#: Node id of the master's heartbeat (COB 0x77E), the contract's default producer for 0x1016.
MASTER_NODE_ID = 0x7E

COB_NMT = 0x000
COB_SYNC = 0x080
COB_SDO_TX = 0x580
COB_SDO_RX = 0x600
COB_HEARTBEAT = 0x700

_PDO_INVALID = 0x8000_0000
_COB_EXTENDED = 0x2000_0000
_COB_MASK = 0x7FF
_I32_MIN = -(2**31)
_I32_MAX = 2**31 - 1
_WINDOW_OFF = 0xFFFF_FFFF
#: Rated pressure drop per control edge of the valve flow in the rig profile.
VALVE_RATED_DROP_PA = 3.5e6


class NmtState(IntEnum):
    """CiA 301 NMT states; the value is the heartbeat byte."""

    INITIALISING = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class NmtCommand(IntEnum):
    """CiA 301 NMT command specifiers (first byte of a frame on COB 0x000)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class DeviceState(IntEnum):
    """CiA 402 power drive states."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


class SdoAbort(IntEnum):
    """CiA 301 SDO abort codes the server uses."""

    TOGGLE_BIT = 0x0503_0000
    COMMAND_SPECIFIER = 0x0504_0001
    UNSUPPORTED_ACCESS = 0x0601_0000
    WRITE_ONLY = 0x0601_0001
    READ_ONLY = 0x0601_0002
    NO_OBJECT = 0x0602_0000
    NOT_MAPPABLE = 0x0604_0041
    PDO_LENGTH = 0x0604_0042
    LENGTH = 0x0607_0010
    NO_SUBINDEX = 0x0609_0011
    VALUE_RANGE = 0x0609_0030
    DEVICE_STATE = 0x0800_0022


class EmcyCode(IntEnum):
    """Emergency error codes (CiA 301 / 402) the model sends."""

    NO_ERROR = 0x0000
    HEARTBEAT = 0x8130
    PDO_LENGTH = 0x8210
    RPDO_TIMEOUT = 0x8250
    FOLLOWING_ERROR = 0x8611


class DriveKind(Enum):
    """What the drive's output commands."""

    ELECTRIC = "electric"  # effort = motor force / force_max_n
    HYDRAULIC = "hydraulic"  # effort = valve spool opening, signed


class _Command(IntEnum):
    """CiA 402 device control commands decoded from the controlword."""

    NONE = 0
    SHUTDOWN = 1
    SWITCH_ON = 2  # also "disable operation": same bits, meaning depends on the state
    ENABLE_OPERATION = 3
    DISABLE_VOLTAGE = 4
    QUICK_STOP = 5


_S = DeviceState
_C = _Command

#: (state, command) -> (transitions, new state); pairs not listed leave the state unchanged.
_TRANSITIONS: Mapping[tuple[DeviceState, _Command], tuple[tuple[int, ...], DeviceState]] = (
    MappingProxyType(
        {
            (_S.SWITCH_ON_DISABLED, _C.SHUTDOWN): ((2,), _S.READY_TO_SWITCH_ON),
            (_S.READY_TO_SWITCH_ON, _C.SWITCH_ON): ((3,), _S.SWITCHED_ON),
            (_S.READY_TO_SWITCH_ON, _C.ENABLE_OPERATION): ((3, 4), _S.OPERATION_ENABLED),
            (_S.READY_TO_SWITCH_ON, _C.DISABLE_VOLTAGE): ((7,), _S.SWITCH_ON_DISABLED),
            (_S.READY_TO_SWITCH_ON, _C.QUICK_STOP): ((7,), _S.SWITCH_ON_DISABLED),
            (_S.SWITCHED_ON, _C.ENABLE_OPERATION): ((4,), _S.OPERATION_ENABLED),
            (_S.SWITCHED_ON, _C.SHUTDOWN): ((6,), _S.READY_TO_SWITCH_ON),
            (_S.SWITCHED_ON, _C.DISABLE_VOLTAGE): ((10,), _S.SWITCH_ON_DISABLED),
            (_S.SWITCHED_ON, _C.QUICK_STOP): ((10,), _S.SWITCH_ON_DISABLED),
            (_S.OPERATION_ENABLED, _C.SWITCH_ON): ((5,), _S.SWITCHED_ON),
            (_S.OPERATION_ENABLED, _C.SHUTDOWN): ((8,), _S.READY_TO_SWITCH_ON),
            (_S.OPERATION_ENABLED, _C.DISABLE_VOLTAGE): ((9,), _S.SWITCH_ON_DISABLED),
            (_S.OPERATION_ENABLED, _C.QUICK_STOP): ((11,), _S.QUICK_STOP_ACTIVE),
            (_S.QUICK_STOP_ACTIVE, _C.DISABLE_VOLTAGE): ((12,), _S.SWITCH_ON_DISABLED),
            (_S.QUICK_STOP_ACTIVE, _C.ENABLE_OPERATION): ((16,), _S.OPERATION_ENABLED),
        }
    )
)

#: Statusword bits 0-6 per state (bit 4 "voltage enabled": mains is always present in the model).
_STATUS_BITS: Mapping[DeviceState, int] = MappingProxyType(
    {
        _S.NOT_READY_TO_SWITCH_ON: 0x0000,
        _S.SWITCH_ON_DISABLED: 0x0050,
        _S.READY_TO_SWITCH_ON: 0x0031,
        _S.SWITCHED_ON: 0x0033,
        _S.OPERATION_ENABLED: 0x0037,
        _S.QUICK_STOP_ACTIVE: 0x0017,
        _S.FAULT_REACTION_ACTIVE: 0x001F,
        _S.FAULT: 0x0018,
    }
)
_SW_REMOTE = 0x0200
_SW_TARGET_REACHED = 0x0400
_SW_INTERNAL_LIMIT = 0x0800
_SW_FOLLOWS_COMMAND = 0x1000
_SW_FOLLOWING_ERROR = 0x2000
_CW_FAULT_RESET = 0x0080

_POWERED = frozenset({_S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE, _S.FAULT_REACTION_ACTIVE})
# Members as module constants for the per-SYNC and servo paths: an enum member looked up
# through its class costs ~0.1 us per access, and servo_step runs 4000 times per simulated
# second per axis.
_OPERATION_ENABLED = _S.OPERATION_ENABLED
_QUICK_STOP_ACTIVE = _S.QUICK_STOP_ACTIVE
_FAULT_REACTION_ACTIVE = _S.FAULT_REACTION_ACTIVE
_NMT_INITIALISING = NmtState.INITIALISING
_NMT_STOPPED = NmtState.STOPPED
_NMT_OPERATIONAL = NmtState.OPERATIONAL
_QUICK_STOP_CODES = frozenset({0, 2, 6})
_FAULT_REACTION_CODES = frozenset({0, 2})
_MODES = frozenset({0, 8})
_MODE_CSP = 8
#: Objects whose values are an enumeration: index -> allowed values.
_ALLOWED_VALUES: Mapping[int, frozenset[int]] = MappingProxyType(
    {0x605A: _QUICK_STOP_CODES, 0x605E: _FAULT_REACTION_CODES, 0x6060: _MODES}
)
#: Objects the servo loop caches in SI units (see DriveFirmware._refresh).
_PARAMETER_OBJECTS = frozenset(
    {0x1006, 0x2100, 0x605A, 0x605E, 0x6065, 0x6066, 0x607D, 0x6085, 0x60C2}
)

_ERR_GENERIC = 0x01
_ERR_CURRENT = 0x02
_ERR_VOLTAGE = 0x04
_ERR_TEMPERATURE = 0x08
_ERR_COMMUNICATION = 0x10
_ERR_PROFILE = 0x20


def _error_register_bits(code: int) -> int:
    """0x1001 bits for an emergency error code (CiA 301 Table "error codes")."""
    group = code >> 12
    bits = _ERR_GENERIC
    if group == 0x2:
        bits |= _ERR_CURRENT
    elif group == 0x3:
        bits |= _ERR_VOLTAGE
    elif group == 0x4:
        bits |= _ERR_TEMPERATURE
    elif (code & 0xFF00) in (0x8100, 0x8200):
        bits |= _ERR_COMMUNICATION
    elif group == 0x8:
        bits |= _ERR_PROFILE
    return bits


# --------------------------------------------------------------------------------------------
# Object dictionary
# --------------------------------------------------------------------------------------------

_CODECS: Mapping[int, struct.Struct] = MappingProxyType(
    {
        0x2: struct.Struct("<b"),
        0x3: struct.Struct("<h"),
        0x4: struct.Struct("<i"),
        0x5: struct.Struct("<B"),
        0x6: struct.Struct("<H"),
        0x7: struct.Struct("<I"),
    }
)
_VISIBLE_STRING = 0x9


@dataclass(frozen=True, slots=True)
class OdEntry:
    """One object (or sub-index) of the drive's object dictionary, as read from the EDS.

    Attributes:
        index: Object index.
        subindex: Sub-index (0 for a VAR object).
        name: ParameterName.
        data_type: CiA 301 data type code (0x2-0x7 integers, 0x9 VISIBLE_STRING).
        access: ``ro``, ``rw``, ``wo`` or ``const``.
        pdo_mappable: Whether a PDO may map it.
        default: DefaultValue with ``$NODEID`` substituted.
        low: LowLimit, or None.
        high: HighLimit, or None.
        codec: Little-endian struct of an integer type; None for a string.
    """

    index: int
    subindex: int
    name: str
    data_type: int
    access: str
    pdo_mappable: bool
    default: int | str
    low: int | None
    high: int | None
    codec: struct.Struct | None

    @property
    def size_bytes(self) -> int:
        """Encoded size (the default's for a string)."""
        if self.codec is not None:
            return self.codec.size
        return len(str(self.default).encode("ascii"))

    @property
    def readable(self) -> bool:
        """Whether an SDO upload may read it."""
        return self.access in ("ro", "rw", "const")

    @property
    def writable(self) -> bool:
        """Whether an SDO download may write it."""
        return self.access in ("rw", "wo")


def _entry(var: ODVariable, index: int, subindex: int) -> OdEntry:
    data_type = int(var.data_type) if var.data_type is not None else -1
    if data_type not in _CODECS and data_type != _VISIBLE_STRING:
        raise FirmwareConfigurationError(
            f"EDS object 0x{index:04X} sub {subindex} has data type 0x{data_type:X}; the drive "
            "model supports INTEGER8/16/32, UNSIGNED8/16/32 and VISIBLE_STRING"
        )
    codec = _CODECS.get(data_type)
    default: int | str
    if codec is None:
        default = str(var.default) if var.default is not None else ""
    else:
        if var.default is not None and not isinstance(var.default, int):
            raise FirmwareConfigurationError(
                f"EDS object 0x{index:04X} sub {subindex}: DefaultValue {var.default!r} is not "
                "an integer (is $NODEID used without a node id?)"
            )
        default = int(var.default) if var.default is not None else 0
    return OdEntry(
        index=index,
        subindex=subindex,
        name=var.name,
        data_type=data_type,
        access=var.access_type,
        pdo_mappable=bool(var.pdo_mappable),
        default=default,
        low=var.min,
        high=var.max,
        codec=codec,
    )


@lru_cache(maxsize=32)
def _load_table(path: str, node_id: int) -> Mapping[tuple[int, int], OdEntry]:
    od = import_od(path, node_id)
    table: dict[tuple[int, int], OdEntry] = {}
    for index in od:
        obj = od[index]
        if isinstance(obj, (ODRecord, ODArray)):
            for subindex, var in obj.subindices.items():
                table[(index, subindex)] = _entry(var, index, subindex)
        else:
            table[(index, 0)] = _entry(obj, index, 0)
    return MappingProxyType(table)


def load_object_dictionary(
    node_id: int, eds: Path | str = CIA402_DRIVE_EDS
) -> Mapping[tuple[int, int], OdEntry]:
    """Read an EDS into a flat, read-only table keyed by ``(index, subindex)``.

    Parsed with ``canopen.objectdictionary.import_od`` (``$NODEID`` substituted); cached per
    (file, node id).

    Args:
        node_id: Node id substituted into ``$NODEID+...`` defaults, 1..127.
        eds: EDS file.

    Returns:
        The entries; a VAR object is at sub-index 0.

    Raises:
        FirmwareConfigurationError: The node id is out of range, the file is missing, or an object
            uses a data type the model does not support.
    """
    if not 1 <= node_id <= 127:
        raise FirmwareConfigurationError(f"drive node id {node_id} is outside 1..127 (CiA 301)")
    path = Path(eds)
    if not path.is_file():
        raise FirmwareConfigurationError(f"EDS file {path} does not exist")
    return _load_table(str(path.resolve()), node_id)


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------


class DrivesLike(Protocol):
    """What the model reads from ``rig.drives`` (SI units)."""

    @property
    def encoder_resolution_m(self) -> float: ...
    @property
    def position_gain_1_s(self) -> float: ...
    @property
    def velocity_gain_s_m(self) -> float: ...
    @property
    def velocity_integral_gain_1_s(self) -> float: ...
    @property
    def servo_period_s(self) -> float: ...
    @property
    def following_error_window_m(self) -> float: ...
    @property
    def following_error_timeout_s(self) -> float: ...
    @property
    def heartbeat_period_s(self) -> float: ...
    @property
    def heartbeat_timeout_s(self) -> float: ...
    @property
    def sync_timeout_s(self) -> float: ...
    @property
    def quick_stop_deceleration_m_s2(self) -> float: ...
    @property
    def load_compensation_filter_s(self) -> float: ...
    @property
    def pressure_feedback_gain(self) -> tuple[float, ...]: ...
    @property
    def pressure_feedback_filter_s(self) -> float: ...
    @property
    def valve_overlap_compensation(self) -> float: ...


class HydraulicLike(Protocol):
    """What the model reads from ``rig.actuators.hydraulic`` (SI units)."""

    @property
    def supply_pressure_pa(self) -> float: ...
    @property
    def piston_area_m2(self) -> float: ...
    @property
    def rod_area_m2(self) -> float: ...
    @property
    def valve_flow_m3_s(self) -> float: ...


class ActuatorsLike(Protocol):
    """What the model reads from ``rig.actuators``."""

    @property
    def velocity_max_m_s(self) -> float: ...
    @property
    def hydraulic(self) -> HydraulicLike | None: ...


class RigLike(Protocol):
    """The parts of :class:`rt_runtime.rig.Rig` the drive model needs."""

    @property
    def drives(self) -> DrivesLike: ...
    @property
    def actuators(self) -> ActuatorsLike: ...


@dataclass(frozen=True, slots=True)
class DriveParameters:
    """Firmware parameters that are not objects of the dictionary (SI units).

    Attributes:
        kind: Electric (force) or hydraulic (valve) output.
        encoder_resolution_m: Stroke per encoder count.
        position_gain_1_s: Kp of the position loop (m/s of command per m of error).
        velocity_gain_s_m: Kv of the velocity PI (effort per m/s of error); unused when hydraulic.
        velocity_integral_gain_1_s: Ki of the velocity PI (``Kv (e + Ki * integral e)``).
        servo_period_s: Nominal servo sub-step (the HIL's ``dt_s``).
        velocity_filter_s: Time constant of the velocity estimate's low-pass; 0 for none.
        velocity_max_m_s: Velocity command limit.
        sync_timeout_s: Longest gap between SYNCs or RPDO1s while OPERATION ENABLED.
        valve_gain_extend_m_s: Hydraulic: no-load rod velocity at full opening, extending.
        valve_gain_retract_m_s: Hydraulic: the same retracting.
        load_filter_s: Hydraulic: time constant of the load-force low-pass of the load
            compensation; 0 for none.
        stall_force_extend_n: Hydraulic: ``p_s A_A``, the force at which extending stalls.
        stall_force_retract_n: Hydraulic: ``p_s A_B``, the pulling force at which retracting
            stalls.
        pressure_feedback_gain: Hydraulic: valve opening taken off per unit of the high-passed
            cylinder force over ``stall_force_extend_n`` (dynamic pressure feedback, which damps
            the oil column's mode); 0 for none.
        pressure_feedback_filter_s: Hydraulic: time constant of that high-pass (the force less
            its low-pass of this time constant); > 0 when the gain is.
    """

    kind: DriveKind
    encoder_resolution_m: float
    position_gain_1_s: float
    velocity_gain_s_m: float
    velocity_integral_gain_1_s: float
    servo_period_s: float
    velocity_filter_s: float
    velocity_max_m_s: float
    sync_timeout_s: float
    valve_gain_extend_m_s: float
    valve_gain_retract_m_s: float
    load_filter_s: float = 0.0
    stall_force_extend_n: float = 0.0
    stall_force_retract_n: float = 0.0
    pressure_feedback_gain: float = 0.0
    pressure_feedback_filter_s: float = 0.0

    def __post_init__(self) -> None:
        positive = (
            "encoder_resolution_m",
            "position_gain_1_s",
            "servo_period_s",
            "velocity_max_m_s",
            "sync_timeout_s",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise FirmwareConfigurationError(f"drive parameter {name} = {value!r} must be > 0")
        non_negative = (
            "velocity_gain_s_m",
            "velocity_integral_gain_1_s",
            "velocity_filter_s",
            "load_filter_s",
            "pressure_feedback_gain",
            "pressure_feedback_filter_s",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise FirmwareConfigurationError(f"drive parameter {name} = {value!r} must be >= 0")
        if self.kind is DriveKind.ELECTRIC and self.velocity_gain_s_m <= 0.0:
            raise FirmwareConfigurationError(
                f"drive parameter velocity_gain_s_m = {self.velocity_gain_s_m!r} must be > 0 "
                "for an electric drive"
            )
        if self.kind is DriveKind.HYDRAULIC and not (
            self.valve_gain_extend_m_s > 0.0 and self.valve_gain_retract_m_s > 0.0
        ):
            raise FirmwareConfigurationError(
                "hydraulic drive: valve velocity gains must be > 0, got "
                f"{self.valve_gain_extend_m_s!r} / {self.valve_gain_retract_m_s!r} m/s"
            )
        if self.load_filter_s > 0.0 and not (
            self.kind is DriveKind.HYDRAULIC
            and self.stall_force_extend_n > 0.0
            and self.stall_force_retract_n > 0.0
        ):
            raise FirmwareConfigurationError(
                "load compensation needs a hydraulic drive with stall forces > 0, got "
                f"{self.kind.value} with {self.stall_force_extend_n!r} / "
                f"{self.stall_force_retract_n!r} N"
            )
        if self.pressure_feedback_gain > 0.0 and not (
            self.kind is DriveKind.HYDRAULIC
            and self.stall_force_extend_n > 0.0
            and self.pressure_feedback_filter_s > 0.0
        ):
            raise FirmwareConfigurationError(
                "pressure feedback needs a hydraulic drive with a stall force > 0 and a "
                f"high-pass time constant > 0, got {self.kind.value} with "
                f"{self.stall_force_extend_n!r} N and {self.pressure_feedback_filter_s!r} s"
            )

    @classmethod
    def from_rig(
        cls,
        rig: RigLike,
        kind: DriveKind | str | None = None,
        velocity_filter_s: float | None = None,
        joint: str = "",
    ) -> DriveParameters:
        """Parameters from ``rig.drives`` and ``rig.actuators``.

        Args:
            rig: The rig (or anything with the same ``drives``/``actuators`` fields).
            kind: ``"electric"``, ``"hydraulic"``, or None: hydraulic when the rig has
                ``actuators.hydraulic``, electric otherwise.
            velocity_filter_s: Velocity low-pass time constant; None for one servo period.
            joint: The axis (``boom``, ``stick``, ``bucket``) whose entry of the per-cylinder
                ``drives.pressure_feedback_gain`` applies; any other name: no pressure feedback.

        Returns:
            The validated parameters.

        Raises:
            FirmwareConfigurationError: Unknown kind, hydraulic without valve data, or a bad value.
        """
        drives, actuators = rig.drives, rig.actuators
        hydraulic = actuators.hydraulic
        if kind is None:
            resolved = DriveKind.HYDRAULIC if hydraulic is not None else DriveKind.ELECTRIC
        else:
            try:
                resolved = DriveKind(kind)
            except ValueError:
                allowed = ", ".join(k.value for k in DriveKind)
                raise FirmwareConfigurationError(
                    f"drive kind {kind!r} is unknown; allowed: {allowed}"
                ) from None
        extend_m_s = retract_m_s = stall_extend_n = stall_retract_n = 0.0
        load_filter_s = float(drives.load_compensation_filter_s)
        if resolved is DriveKind.HYDRAULIC:
            if hydraulic is None:
                raise FirmwareConfigurationError(
                    "a hydraulic drive needs rig.actuators.hydraulic ([actuators.hydraulic])"
                )
            extend_m_s, retract_m_s = valve_velocity_gains_m_s(hydraulic)
            supply = hydraulic.supply_pressure_pa
            stall_extend_n = supply * hydraulic.piston_area_m2
            stall_retract_n = supply * (hydraulic.piston_area_m2 - hydraulic.rod_area_m2)
        return cls(
            kind=resolved,
            encoder_resolution_m=float(drives.encoder_resolution_m),
            position_gain_1_s=float(drives.position_gain_1_s),
            velocity_gain_s_m=float(drives.velocity_gain_s_m),
            velocity_integral_gain_1_s=float(drives.velocity_integral_gain_1_s),
            servo_period_s=float(drives.servo_period_s),
            velocity_filter_s=float(
                drives.servo_period_s if velocity_filter_s is None else velocity_filter_s
            ),
            velocity_max_m_s=float(actuators.velocity_max_m_s),
            sync_timeout_s=float(drives.sync_timeout_s),
            valve_gain_extend_m_s=extend_m_s,
            valve_gain_retract_m_s=retract_m_s,
            load_filter_s=load_filter_s,
            stall_force_extend_n=stall_extend_n,
            stall_force_retract_n=stall_retract_n,
            pressure_feedback_gain=(
                float(drives.pressure_feedback_gain[CYLINDER_AXES.index(joint)])
                if joint in CYLINDER_AXES
                else 0.0
            ),
            pressure_feedback_filter_s=float(drives.pressure_feedback_filter_s),
        )


#: The cylinders in the order of the rig's per-cylinder drive values.
CYLINDER_AXES = ("boom", "stick", "bucket")


#: Smallest flow-gain ratio the load compensation divides by: near stall the orifice law's
#: gain goes to 0 and the opening it asks for would be unbounded (it saturates anyway).
LOAD_GAIN_RATIO_MIN = 0.2


#: Half-width of the straight line through zero of the overlap compensation (fraction of
#: full command): a command this small passes without the full jump, so a drive at rest does
#: not throw the spool across the dead band on every sign change of its error.
OVERLAP_JUMP_RAMP = 0.005


def overlap_jump(u: float, jump: float) -> float:
    """Spool command after a valve amplifier's overlap compensation (jump function).

    ``sign(u) (jump + (1 - jump) |u|)`` for ``|u| >= OVERLAP_JUMP_RAMP``, so that a command just
    past zero already opens a valve whose overlap is ``jump`` and full command stays full
    opening; inside the ramp a straight line through zero that meets it at its ends.

    Args:
        u: Spool command, fraction of full opening in [-1, 1].
        jump: The compensation, fraction of full opening in [0, 1).
    """
    a = abs(u)
    if a >= OVERLAP_JUMP_RAMP:
        return math.copysign(jump + (1.0 - jump) * a, u)
    return u * (jump + (1.0 - jump) * OVERLAP_JUMP_RAMP) / OVERLAP_JUMP_RAMP


def load_gain_ratio(
    force_n: float, extending: bool, stall_extend_n: float, stall_retract_n: float
) -> float:
    """Steady-state rod velocity per opening under the cylinder force ``force_n`` (positive
    pushing out) over the no-load one, by the orifice law on both metering edges:
    ``sqrt(1 - F / (p_s A_A))`` extending, ``sqrt(1 + F / (p_s A_B))`` retracting, bounded
    below by :data:`LOAD_GAIN_RATIO_MIN`.

    Extending, ``Q_A = K x sqrt(p_s - p_A) = A_A v`` and ``Q_B = K x sqrt(p_B) = A_B v``; with
    ``F = p_A A_A - p_B A_B`` that is ``(v / K x)^2 (A_A^3 + A_B^3) = p_s A_A - F``; retracting
    the edges swap and ``(v / K x)^2 (A_A^3 + A_B^3) = p_s A_B + F``. At ``F = 0`` these are
    :func:`valve_velocity_gains_m_s`.
    """
    ratio = 1.0 - force_n / stall_extend_n if extending else 1.0 + force_n / stall_retract_n
    return math.sqrt(ratio) if ratio > LOAD_GAIN_RATIO_MIN**2 else LOAD_GAIN_RATIO_MIN


def valve_velocity_gains_m_s(hydraulic: HydraulicLike) -> tuple[float, float]:
    """No-load rod velocity at full valve opening, (extending, retracting), in m/s.

    Each metering edge passes ``Q = Q_n sqrt(dp / 3.5 MPa)`` at full opening. Without load the
    chamber pressures balance on the differential cylinder, ``p_A A_A = p_B A_B``, and the flows
    match the areas, which with ``a = A_B / A_A`` (A_B the annulus: piston minus the rod's
    cross-section) gives the pressure drop across the inflow edge:

        extending:  p_s - p_A = p_s / (1 + a^3),        v = Q_n sqrt(.../3.5 MPa) / A_A
        retracting: p_s - p_B = p_s a^3 / (1 + a^3),    v = Q_n sqrt(.../3.5 MPa) / A_B

    (the extending value is the rig's ``actuators.velocity_max_m_s`` for a hydraulic rig).

    Raises:
        FirmwareConfigurationError: A non-positive area, supply or flow, or a rod as large as
            the piston.
    """
    piston, rod = hydraulic.piston_area_m2, hydraulic.rod_area_m2
    if not (piston > 0.0 and 0.0 <= rod < piston):
        raise FirmwareConfigurationError(
            f"hydraulic cylinder: piston area {piston!r} m^2 must be > 0 and the rod's "
            f"cross-section {rod!r} m^2 in [0, piston)"
        )
    supply, flow = hydraulic.supply_pressure_pa, hydraulic.valve_flow_m3_s
    if not (supply > 0.0 and flow > 0.0):
        raise FirmwareConfigurationError(
            "hydraulic cylinder: supply_pressure_pa and valve_flow_m3_s must be > 0, got "
            f"{supply!r}, {flow!r}"
        )
    annulus = piston - rod
    a3 = (annulus / piston) ** 3
    extend = flow * math.sqrt(supply / (1.0 + a3) / VALVE_RATED_DROP_PA) / piston
    retract = flow * math.sqrt(supply * a3 / (1.0 + a3) / VALVE_RATED_DROP_PA) / annulus
    return extend, retract


# --------------------------------------------------------------------------------------------
# PDOs
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Pdo:
    """One PDO as currently configured."""

    comm_index: int
    cob_id: int  # 11-bit identifier
    valid: bool
    transmission_type: int
    keys: tuple[tuple[int, int], ...]
    codec: struct.Struct


def _sdo_frame(command: int, index: int, subindex: int, payload: bytes = b"") -> bytes:
    return struct.pack("<BHB", command, index, subindex) + payload.ljust(4, b"\x00")


def _abort_frame(index: int, subindex: int, code: int) -> bytes:
    return struct.pack("<BHBI", 0x80, index, subindex, code)


@dataclass(slots=True)
class _Upload:
    key: tuple[int, int]
    data: bytes
    offset: int
    toggle: int


@dataclass(slots=True)
class _Download:
    key: tuple[int, int]
    size: int | None
    buffer: bytearray
    toggle: int


class DriveFirmware:
    """One CiA 402 drive: communication, device control and the servo cascade.

    Args:
        node_id: CAN node id, 1..127.
        rig: Rig with ``drives`` and ``actuators`` (see :class:`RigLike`).
        joint: Axis name (``boom``, ``stick``, ``bucket``, ...), for reports.
        kind: ``"electric"``, ``"hydraulic"``, or None to follow the rig (hydraulic when
            ``rig.actuators.hydraulic`` is set).
        eds: Object dictionary file.
        master_node_id: Heartbeat producer the stored 0x1016 sub 1 watches.
        velocity_filter_s: Velocity estimate low-pass; None for one servo period.
        initial_position_m: Stroke reported before the first :meth:`servo_step`.
        tpdo_at_start: Send each type-0 TPDO at the first SYNC after NMT start; False: only
            after its content changed from what it was at NMT start (see the module docstring).

    Attributes:
        node_id: CAN node id.
        joint: Axis name.
        od: The object dictionary's entries (read-only, from the EDS).
        params: Firmware parameters from the rig.
        last_transition: Number of the last CiA 402 transition (0-16).
        effort: Output of the last :meth:`servo_step`.

    Raises:
        FirmwareConfigurationError: Bad node id, EDS, kind or parameters.

    Calls are not thread-safe; one owner (the HIL's drive emulator) drives all of them.
    """

    def __init__(
        self,
        node_id: int,
        rig: RigLike,
        joint: str,
        kind: DriveKind | str | None = None,
        eds: Path | str = CIA402_DRIVE_EDS,
        *,
        master_node_id: int = MASTER_NODE_ID,
        velocity_filter_s: float | None = None,
        initial_position_m: float = 0.0,
        tpdo_at_start: bool = True,
    ) -> None:
        self.node_id = node_id
        self._tpdo_at_start = tpdo_at_start
        self.joint = joint
        self.od = load_object_dictionary(node_id, eds)
        self._params = DriveParameters.from_rig(rig, kind, velocity_filter_s, joint)
        # The cascade's constants as plain attributes (read every servo sub-step).
        p = self._params
        self._res_m = p.encoder_resolution_m
        self._filter_s = p.velocity_filter_s
        self._kp_1_s = p.position_gain_1_s
        self._kv_s_m = p.velocity_gain_s_m
        self._ki_1_s = p.velocity_integral_gain_1_s
        self._v_max_m_s = p.velocity_max_m_s
        self._sync_timeout_s = p.sync_timeout_s
        self._valve_output = p.kind is DriveKind.HYDRAULIC
        self._valve_extend_m_s = p.valve_gain_extend_m_s
        self._valve_retract_m_s = p.valve_gain_retract_m_s
        self._load_filter_s = p.load_filter_s
        self._stall_extend_n = p.stall_force_extend_n
        self._stall_retract_n = p.stall_force_retract_n
        self._load_n: float | None = None  # the filtered cylinder force; None before a reading
        self._pf_gain = p.pressure_feedback_gain
        self._pf_filter_s = p.pressure_feedback_filter_s
        self._pf_low_n: float | None = None  # the force's low-pass of the pressure feedback
        # Anti-windup bound of the integral (what the output can use), formed once.
        self._integral_bound_m = (
            1.0 / (p.velocity_gain_s_m * p.velocity_integral_gain_1_s)
            if p.velocity_gain_s_m > 0.0 and p.velocity_integral_gain_1_s > 0.0
            else math.inf
        )
        drives = rig.drives
        self._stored: dict[tuple[int, int], int | str] = {
            key: entry.default for key, entry in self.od.items()
        }
        if not 1 <= master_node_id <= 127:
            raise FirmwareConfigurationError(f"master node id {master_node_id} is outside 1..127")
        commissioned = {
            (0x1016, 1): (master_node_id << 16) | _ms(drives.heartbeat_timeout_s, 0xFFFF),
            (0x1017, 0): _ms(drives.heartbeat_period_s, 0xFFFF),
            (0x6065, 0): _clip(round(drives.following_error_window_m * 1e6), 0, _WINDOW_OFF),
            (0x6066, 0): _ms(drives.following_error_timeout_s, 0xFFFF),
            (0x6085, 0): _clip(round(drives.quick_stop_deceleration_m_s2 * 1e6), 1, _WINDOW_OFF),
            (0x2100, 0): _clip(round(drives.valve_overlap_compensation * 1e4), 0, 5000),
        }
        for key, value in commissioned.items():
            if key in self._stored:
                self._stored[key] = value
        self._values: dict[tuple[int, int], int | str] = dict(self._stored)
        self._live: dict[tuple[int, int], Callable[[], int]] = {
            (0x1001, 0): lambda: self._error_register,
            (0x603F, 0): lambda: self._error_code,
            (0x6041, 0): lambda: self.statusword,
            (0x6061, 0): lambda: self._mode,
            (0x6062, 0): lambda: _clip(round(self._demand_m * 1e6), _I32_MIN, _I32_MAX),
            (0x6064, 0): lambda: _clip(round(self._p_meas_m * 1e6), _I32_MIN, _I32_MAX),
            (0x606C, 0): lambda: _clip(round(self._v_est_m_s * 1e6), _I32_MIN, _I32_MAX),
        }
        # Communication.
        self._nmt = NmtState.INITIALISING
        self._handlers: dict[int, Callable[[bytes, float], list[Frame]]] = {}
        self._rpdos: tuple[_Pdo, ...] = ()
        self._tpdos: tuple[_Pdo, ...] = ()
        self._rpdo_buffer: dict[int, bytes] = {}
        self._tpdo_sync_count: dict[int, int] = {}
        self._tpdo_last: dict[int, bytes] = {}
        self._emcy_cob: int | None = None
        self._emcy_queue: list[int] = []
        self._hb_next_s: float | None = None
        self._hb_consumer_cob: int | None = None
        self._hb_consumer_timeout_s = 0.0
        self._hb_last_rx_s: float | None = None
        self._sdo_upload: _Upload | None = None
        self._sdo_download: _Download | None = None
        self._last_sync_s: float | None = None
        self._sync_interval_s: float | None = None
        self._last_rpdo1_s: float | None = None
        self._enabled_at_s: float | None = None
        # Device control.
        self._state = _S.NOT_READY_TO_SWITCH_ON
        self.last_transition = 0
        self._controlword = 0
        self._mode = 0
        self._error_code = 0
        self._error_register = 0
        # Servo.
        self._p_meas_m = initial_position_m
        self._p_prev_m = initial_position_m
        self._v_est_m_s = 0.0
        self._measured = False
        self._demand_m = initial_position_m
        self._voff_m_s = 0.0
        self._seg_p0_m = initial_position_m
        self._seg_p1_m = initial_position_m
        self._seg_v0_m_s = 0.0
        self._seg_v1_m_s = 0.0
        self._seg_t_s = 0.0
        self._seg_T_s = 0.0
        self._integral_m = 0.0
        self._fe_time_s = 0.0
        self._following_error = False
        self._limit_active = False
        self._target_limited = False
        self._ramping = False
        self._ramp_v_m_s = 0.0
        self.effort = 0.0
        # Objects the servo loop uses, cached in SI (refreshed when one is written, _refresh).
        self._window_m = math.inf
        self._fe_timeout_s = 0.0
        self._qs_decel_m_s2 = 1.0
        self._limit_min_m = -math.inf
        self._limit_max_m = math.inf
        self._interp_T_s = 0.0
        self._qs_option = 2
        self._fr_option = 2
        self._refresh()
        self._rebuild_communication()

    # ----------------------------------------------------------------------------------------
    # Public state
    # ----------------------------------------------------------------------------------------

    @property
    def params(self) -> DriveParameters:
        """Firmware parameters from the rig (fixed at construction)."""
        return self._params

    @property
    def nmt_state(self) -> NmtState:
        """Current NMT state."""
        return self._nmt

    @property
    def state(self) -> DeviceState:
        """Current CiA 402 device state."""
        return self._state

    @property
    def statusword(self) -> int:
        """0x6041 as it would be sent now."""
        state = self._state
        word = _STATUS_BITS[state] | _SW_REMOTE
        if state is _OPERATION_ENABLED and self._mode == _MODE_CSP:
            word |= _SW_FOLLOWS_COMMAND
        if state is _QUICK_STOP_ACTIVE and not self._ramping:
            word |= _SW_TARGET_REACHED
        if self._following_error:
            word |= _SW_FOLLOWING_ERROR
        if self._limit_active and state in _POWERED:
            word |= _SW_INTERNAL_LIMIT
        return word

    @property
    def error_code(self) -> int:
        """0x603F: the last fault's emergency code, 0 after a fault reset."""
        return self._error_code

    @property
    def mode(self) -> int:
        """0x6061 modes of operation display."""
        return self._mode

    @property
    def position_demand_m(self) -> float:
        """Position demand (interpolated setpoint or ramp) in m."""
        return self._demand_m

    @property
    def position_actual_m(self) -> float:
        """Last quantised stroke measurement in m."""
        return self._p_meas_m

    @property
    def velocity_actual_m_s(self) -> float:
        """Last velocity estimate in m/s."""
        return self._v_est_m_s

    @property
    def brake_engaged(self) -> bool:
        """Whether the power stage is off (a plant may model a holding brake with this)."""
        return self._state not in _POWERED

    def read_object(self, index: int, subindex: int = 0) -> int | str:
        """Current value of an object, as an SDO upload would read it.

        Raises:
            KeyError: No such object or sub-index.
        """
        key = (index, subindex)
        if key not in self.od:
            raise KeyError(f"object 0x{index:04X} sub {subindex} is not in the dictionary")
        return self._read(key)

    # ----------------------------------------------------------------------------------------
    # Frames in
    # ----------------------------------------------------------------------------------------

    def on_frame(self, arbitration_id: int, data: bytes, now_s: float) -> list[Frame]:
        """Handle one received frame.

        Args:
            arbitration_id: 11-bit identifier.
            data: Payload.
            now_s: Arrival time (monotonic or simulated), s.

        Returns:
            The frames the drive sends in reply, in order (SDO response, TPDOs on SYNC, boot-up
            after an NMT reset); empty when the frame is not for this drive.
        """
        if self._nmt is _NMT_INITIALISING:
            return []
        handler = self._handlers.get(arbitration_id)
        if handler is None:
            return []
        return handler(bytes(data), now_s)

    def _on_nmt(self, data: bytes, now_s: float) -> list[Frame]:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return []
        command = data[0]
        if command == NmtCommand.START:
            if self._nmt is not NmtState.OPERATIONAL:
                self._rpdo_buffer.clear()
                for pdo in self._tpdos:
                    if pdo.transmission_type == 0:
                        if self._tpdo_at_start:
                            self._tpdo_last.pop(pdo.comm_index, None)
                        else:
                            self._tpdo_last[pdo.comm_index] = self._tpdo_payload(pdo)
            self._nmt = NmtState.OPERATIONAL
        elif command == NmtCommand.STOP:
            self._nmt = NmtState.STOPPED
            self._abort_sdo_state()
        elif command == NmtCommand.ENTER_PRE_OPERATIONAL:
            self._nmt = NmtState.PRE_OPERATIONAL
        elif command == NmtCommand.RESET_NODE:
            return self._reset(now_s, application=True)
        elif command == NmtCommand.RESET_COMMUNICATION:
            return self._reset(now_s, application=False)
        return []

    def _reset(self, now_s: float, *, application: bool) -> list[Frame]:
        for key, value in self._stored.items():
            if application or key[0] < 0x2000:
                self._values[key] = value
        if application:
            self._reset_application()
        self._rpdo_buffer.clear()
        self._tpdo_sync_count.clear()
        self._tpdo_last.clear()
        self._emcy_queue.clear()
        self._abort_sdo_state()
        self._last_sync_s = self._sync_interval_s = self._last_rpdo1_s = None
        self._refresh()
        self._rebuild_communication()
        return [self._boot(now_s)]

    def _reset_application(self) -> None:
        self._state = _S.NOT_READY_TO_SWITCH_ON
        self.last_transition = 0
        self._controlword = 0
        self._mode = int(self._values.get((0x6060, 0), 0))
        self._error_code = 0
        self._error_register = 0
        self._following_error = False
        self._fe_time_s = 0.0
        self._ramping = False
        self._integral_m = 0.0
        self._hold_at_actual()
        self._transition(1, _S.SWITCH_ON_DISABLED)

    def _boot(self, now_s: float) -> Frame:
        """Finish initialisation: boot-up message, PRE-OPERATIONAL, heartbeat schedule."""
        if self._state is _S.NOT_READY_TO_SWITCH_ON:
            self._transition(1, _S.SWITCH_ON_DISABLED)
        self._nmt = NmtState.PRE_OPERATIONAL
        period_s = int(self._values[(0x1017, 0)]) * 1e-3
        self._hb_next_s = now_s + period_s if period_s > 0.0 else None
        self._hb_last_rx_s = None
        return (COB_HEARTBEAT + self.node_id, b"\x00")

    def _on_sync(self, data: bytes, now_s: float) -> list[Frame]:
        if self._nmt is _NMT_STOPPED:
            return []
        if self._last_sync_s is not None and now_s > self._last_sync_s:
            self._sync_interval_s = now_s - self._last_sync_s
        self._last_sync_s = now_s
        out: list[Frame] = []
        if self._nmt is _NMT_OPERATIONAL:
            for pdo in self._rpdos:
                payload = self._rpdo_buffer.pop(pdo.cob_id, None)
                if payload is not None:
                    self._apply_rpdo(pdo, payload, now_s)
        self._latch_setpoint()
        if self._nmt is _NMT_OPERATIONAL:
            for pdo in self._tpdos:
                frame = self._tpdo_on_sync(pdo)
                if frame is not None:
                    out.append(frame)
        return out

    def _on_rpdo(self, data: bytes, now_s: float, pdo: _Pdo) -> list[Frame]:
        if self._nmt is not _NMT_OPERATIONAL:
            return []
        if len(data) < pdo.codec.size:
            self._emcy_queue.append(EmcyCode.PDO_LENGTH)
            return []
        if pdo.comm_index == 0x1400:
            self._last_rpdo1_s = now_s
        if pdo.transmission_type <= 240:
            self._rpdo_buffer[pdo.cob_id] = data
        else:
            self._apply_rpdo(pdo, data, now_s)
        return []

    def _apply_rpdo(self, pdo: _Pdo, data: bytes, now_s: float) -> None:
        values = pdo.codec.unpack_from(data)
        for key, value in zip(pdo.keys, values, strict=True):
            if self._check_value(key, value) is None:
                self._store(key, value, now_s)

    def _tpdo_payload(self, pdo: _Pdo) -> bytes:
        # The mapped objects' values as _read gives them, looked up inline (every SYNC samples
        # every mapped object); a string object (excluded by the mapping checks) packs as 0.
        live, values = self._live, self._values
        ints: list[int] = []
        for key in pdo.keys:
            getter = live.get(key)
            value = getter() if getter is not None else values[key]
            ints.append(value if isinstance(value, int) else 0)
        return pdo.codec.pack(*ints)

    def _tpdo_on_sync(self, pdo: _Pdo) -> Frame | None:
        payload = self._tpdo_payload(pdo)
        tt = pdo.transmission_type
        if tt == 0:
            if self._tpdo_last.get(pdo.comm_index) == payload:
                return None
        else:
            count = self._tpdo_sync_count.get(pdo.comm_index, 0) + 1
            if count < tt:
                self._tpdo_sync_count[pdo.comm_index] = count
                return None
            self._tpdo_sync_count[pdo.comm_index] = 0
        self._tpdo_last[pdo.comm_index] = payload
        return (pdo.cob_id, payload)

    def _on_heartbeat(self, data: bytes, now_s: float) -> list[Frame]:
        if data:
            self._hb_last_rx_s = now_s
        return []

    # ----------------------------------------------------------------------------------------
    # SDO server
    # ----------------------------------------------------------------------------------------

    def _on_sdo(self, data: bytes, now_s: float) -> list[Frame]:
        if self._nmt not in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL):
            return []
        request = data.ljust(8, b"\x00")
        response = self._sdo(request, now_s)
        return [] if response is None else [(COB_SDO_TX + self.node_id, response)]

    def _sdo(self, request: bytes, now_s: float) -> bytes | None:
        ccs = request[0] >> 5
        if ccs == 4:  # client abort
            self._abort_sdo_state()
            return None
        if ccs in (0, 3):
            return self._sdo_segment(ccs, request, now_s)
        index, subindex = struct.unpack_from("<HB", request, 1)
        self._abort_sdo_state()
        if ccs == 1:
            return self._sdo_initiate_download(request, index, subindex, now_s)
        if ccs == 2:
            return self._sdo_initiate_upload(index, subindex)
        return _abort_frame(index, subindex, SdoAbort.COMMAND_SPECIFIER)

    def _lookup(self, index: int, subindex: int) -> OdEntry | SdoAbort:
        entry = self.od.get((index, subindex))
        if entry is not None:
            return entry
        if any(i == index for i, _ in self.od):
            return SdoAbort.NO_SUBINDEX
        return SdoAbort.NO_OBJECT

    def _sdo_initiate_upload(self, index: int, subindex: int) -> bytes:
        entry = self._lookup(index, subindex)
        if isinstance(entry, SdoAbort):
            return _abort_frame(index, subindex, entry)
        if not entry.readable:
            return _abort_frame(index, subindex, SdoAbort.WRITE_ONLY)
        payload = self._encode(entry, self._read((index, subindex)))
        if len(payload) <= 4:
            command = 0x43 | ((4 - len(payload)) << 2)
            return _sdo_frame(command, index, subindex, payload)
        self._sdo_upload = _Upload((index, subindex), payload, 0, 0)
        return _sdo_frame(0x41, index, subindex, struct.pack("<I", len(payload)))

    def _sdo_initiate_download(
        self, request: bytes, index: int, subindex: int, now_s: float
    ) -> bytes:
        entry = self._lookup(index, subindex)
        if isinstance(entry, SdoAbort):
            return _abort_frame(index, subindex, entry)
        if not entry.writable:
            return _abort_frame(index, subindex, SdoAbort.READ_ONLY)
        if entry.codec is None:
            return _abort_frame(index, subindex, SdoAbort.UNSUPPORTED_ACCESS)
        expedited, size_indicated = bool(request[0] & 0x02), bool(request[0] & 0x01)
        if expedited:
            size = 4 - ((request[0] >> 2) & 0x03) if size_indicated else entry.codec.size
            abort = self._download_value(entry, request[4 : 4 + size], now_s)
            if abort is not None:
                return _abort_frame(index, subindex, abort)
            return _sdo_frame(0x60, index, subindex)
        total = struct.unpack_from("<I", request, 4)[0] if size_indicated else None
        if total is not None and total != entry.codec.size:
            return _abort_frame(index, subindex, SdoAbort.LENGTH)
        self._sdo_download = _Download((index, subindex), total, bytearray(), 0)
        return _sdo_frame(0x60, index, subindex)

    def _sdo_segment(self, ccs: int, request: bytes, now_s: float) -> bytes:
        toggle = request[0] & 0x10
        if ccs == 3:
            upload = self._sdo_upload
            if upload is None:
                return _abort_frame(0, 0, SdoAbort.COMMAND_SPECIFIER)
            if toggle != upload.toggle:
                self._sdo_upload = None
                return _abort_frame(*upload.key, SdoAbort.TOGGLE_BIT)
            chunk = upload.data[upload.offset : upload.offset + 7]
            upload.offset += len(chunk)
            last = upload.offset >= len(upload.data)
            command = toggle | ((7 - len(chunk)) << 1) | (0x01 if last else 0x00)
            upload.toggle ^= 0x10
            if last:
                self._sdo_upload = None
            return bytes([command]) + chunk.ljust(7, b"\x00")
        download = self._sdo_download
        if download is None:
            return _abort_frame(0, 0, SdoAbort.COMMAND_SPECIFIER)
        index, subindex = download.key
        if toggle != download.toggle:
            self._sdo_download = None
            return _abort_frame(index, subindex, SdoAbort.TOGGLE_BIT)
        n_unused = (request[0] >> 1) & 0x07
        download.buffer += request[1 : 8 - n_unused]
        download.toggle ^= 0x10
        response = bytes([0x20 | toggle]) + bytes(7)
        if not request[0] & 0x01:
            return response
        self._sdo_download = None
        entry = self.od[download.key]
        if download.size is not None and len(download.buffer) != download.size:
            return _abort_frame(index, subindex, SdoAbort.LENGTH)
        abort = self._download_value(entry, bytes(download.buffer), now_s)
        if abort is not None:
            return _abort_frame(index, subindex, abort)
        return response

    def _download_value(self, entry: OdEntry, payload: bytes, now_s: float) -> SdoAbort | None:
        codec = entry.codec
        if codec is None or len(payload) != codec.size:
            return SdoAbort.LENGTH
        value = int(codec.unpack(payload)[0])
        key = (entry.index, entry.subindex)
        abort = self._check_value(key, value)
        if abort is None:
            self._store(key, value, now_s)
        return abort

    def _abort_sdo_state(self) -> None:
        self._sdo_upload = None
        self._sdo_download = None

    # ----------------------------------------------------------------------------------------
    # Object values
    # ----------------------------------------------------------------------------------------

    def _read(self, key: tuple[int, int]) -> int | str:
        live = self._live.get(key)
        return live() if live is not None else self._values[key]

    @staticmethod
    def _encode(entry: OdEntry, value: int | str) -> bytes:
        if entry.codec is None:
            return str(value).encode("ascii")
        return entry.codec.pack(int(value))

    def _check_value(self, key: tuple[int, int], value: int) -> SdoAbort | None:
        """Why ``value`` may not be written to ``key`` now, or None."""
        entry = self.od[key]
        if (entry.low is not None and value < entry.low) or (
            entry.high is not None and value > entry.high
        ):
            return SdoAbort.VALUE_RANGE
        index, subindex = key
        if index in (0x1400, 0x1401, 0x1800, 0x1801):
            return self._check_pdo_comm(index, subindex, value)
        if index in (0x1600, 0x1601, 0x1A00, 0x1A01):
            return self._check_pdo_mapping(index, subindex, value)
        if index == 0x1014 and value & _COB_EXTENDED:
            return SdoAbort.VALUE_RANGE
        allowed = _ALLOWED_VALUES
        if index in allowed and value not in allowed[index]:
            return SdoAbort.VALUE_RANGE
        if index == 0x6085 and value == 0:
            return SdoAbort.VALUE_RANGE
        return None

    def _check_pdo_comm(self, index: int, subindex: int, value: int) -> SdoAbort | None:
        if subindex == 1:
            if value & _COB_EXTENDED or (value & _COB_MASK) == 0:
                return SdoAbort.VALUE_RANGE
            old = int(self._values[(index, 1)])
            both_valid = not (old & _PDO_INVALID) and not (value & _PDO_INVALID)
            if both_valid and (old & _COB_MASK) != (value & _COB_MASK):
                return SdoAbort.VALUE_RANGE
        elif subindex == 2:
            receive = index < 0x1800
            if not (value <= 240 or (receive and value in (0xFE, 0xFF))):
                return SdoAbort.VALUE_RANGE
        return None

    def _check_pdo_mapping(self, index: int, subindex: int, value: int) -> SdoAbort | None:
        comm = index - 0x200
        if not int(self._values[(comm, 1)]) & _PDO_INVALID:
            return SdoAbort.UNSUPPORTED_ACCESS
        receive = index < 0x1A00
        if subindex == 0:
            if value > 8:
                return SdoAbort.PDO_LENGTH
            bits = 0
            for sub in range(1, value + 1):
                mapped = int(self._values.get((index, sub), 0))
                if self._mappable(mapped, receive) is not None:
                    return SdoAbort.NOT_MAPPABLE
                bits += mapped & 0xFF
            return SdoAbort.PDO_LENGTH if bits > 64 else None
        if int(self._values[(index, 0)]) != 0:
            return SdoAbort.UNSUPPORTED_ACCESS
        return None if value == 0 else self._mappable(value, receive)

    def _mappable(self, mapped: int, receive: bool) -> SdoAbort | None:
        entry = self.od.get((mapped >> 16, (mapped >> 8) & 0xFF))
        if (
            entry is None
            or not entry.pdo_mappable
            or entry.codec is None
            or entry.codec.size * 8 != (mapped & 0xFF)
            or (receive and not entry.writable)
            or (not receive and not entry.readable)
        ):
            return SdoAbort.NOT_MAPPABLE
        return None

    def _store(self, key: tuple[int, int], value: int, now_s: float) -> None:
        """Write a checked value and apply what it changes."""
        self._values[key] = value
        index = key[0]
        if index == 0x6040:
            self._on_controlword(value, now_s)
        elif index == 0x6060:
            self._set_mode(value)
        elif index == 0x1017:
            self._hb_next_s = now_s + value * 1e-3 if value > 0 else None
        elif index in _PARAMETER_OBJECTS:
            self._refresh()
        elif 0x1000 <= index < 0x2000:
            self._rebuild_communication()

    def _refresh(self) -> None:
        """Cache the objects the servo loop uses, in SI units."""
        v = self._values
        window = int(v[(0x6065, 0)])
        self._window_m = math.inf if window == _WINDOW_OFF else window * 1e-6
        self._fe_timeout_s = int(v[(0x6066, 0)]) * 1e-3
        self._qs_decel_m_s2 = max(int(v[(0x6085, 0)]), 1) * 1e-6
        low, high = int(v[(0x607D, 1)]), int(v[(0x607D, 2)])
        self._limit_min_m, self._limit_max_m = (
            (low * 1e-6, high * 1e-6) if low < high else (-math.inf, math.inf)
        )
        period_value, period_index = int(v[(0x60C2, 1)]), int(v[(0x60C2, 2)])
        cycle_us = int(v[(0x1006, 0)])
        if period_value > 0:
            self._interp_T_s = period_value * 10.0**period_index
        elif cycle_us > 0:
            self._interp_T_s = cycle_us * 1e-6
        else:
            self._interp_T_s = 0.0
        self._qs_option = int(v[(0x605A, 0)])
        self._fr_option = int(v[(0x605E, 0)])
        jump = v.get((0x2100, 0), 0)
        self._jump = int(jump) * 1e-4 if self._valve_output else 0.0

    def _rebuild_communication(self) -> None:
        """COB-IDs, PDO layouts and the frame dispatch table from the current values."""
        v = self._values
        self._rpdos = (self._pdo(0x1400), self._pdo(0x1401))
        self._tpdos = tuple(p for p in (self._pdo(0x1800), self._pdo(0x1801)) if p.valid)
        emcy = int(v[(0x1014, 0)])
        self._emcy_cob = None if emcy & _PDO_INVALID else emcy & _COB_MASK
        consumer = int(v[(0x1016, 1)])
        producer, time_ms = (consumer >> 16) & 0xFF, consumer & 0xFFFF
        if 1 <= producer <= 127 and time_ms > 0:
            cob = COB_HEARTBEAT + producer
            if cob != self._hb_consumer_cob or time_ms * 1e-3 != self._hb_consumer_timeout_s:
                self._hb_last_rx_s = None  # re-armed by the next heartbeat
            self._hb_consumer_cob, self._hb_consumer_timeout_s = cob, time_ms * 1e-3
        else:
            self._hb_consumer_cob, self._hb_consumer_timeout_s = None, 0.0
            self._hb_last_rx_s = None
        handlers: dict[int, Callable[[bytes, float], list[Frame]]] = {
            COB_NMT: self._on_nmt,
            COB_SYNC: self._on_sync,
            COB_SDO_RX + self.node_id: self._on_sdo,
        }
        if self._hb_consumer_cob is not None:
            handlers[self._hb_consumer_cob] = self._on_heartbeat
        for pdo in self._rpdos:
            if pdo.valid:
                handlers[pdo.cob_id] = _bind_rpdo(self._on_rpdo, pdo)
        self._handlers = handlers
        valid_cobs = {p.cob_id for p in self._rpdos if p.valid}
        for cob in list(self._rpdo_buffer):
            if cob not in valid_cobs:
                del self._rpdo_buffer[cob]

    def _pdo(self, comm_index: int) -> _Pdo:
        v = self._values
        cob = int(v[(comm_index, 1)])
        mapping_index = comm_index + 0x200
        count = int(v[(mapping_index, 0)])
        keys: list[tuple[int, int]] = []
        fmt = "<"
        for sub in range(1, count + 1):
            mapped = int(v[(mapping_index, sub)])
            key = (mapped >> 16, (mapped >> 8) & 0xFF)
            codec = self.od[key].codec
            if codec is None:  # excluded by the mapping checks
                continue
            keys.append(key)
            fmt += codec.format[1:]
        return _Pdo(
            comm_index=comm_index,
            cob_id=cob & _COB_MASK,
            valid=not cob & _PDO_INVALID and count > 0,
            transmission_type=int(v[(comm_index, 2)]),
            keys=tuple(keys),
            codec=struct.Struct(fmt),
        )

    # ----------------------------------------------------------------------------------------
    # Device control (CiA 402)
    # ----------------------------------------------------------------------------------------

    def _transition(self, number: int, state: DeviceState) -> None:
        self.last_transition = number
        self._state = state

    def _on_controlword(self, word: int, now_s: float) -> None:
        previous, self._controlword = self._controlword, word
        state = self._state
        if state is _S.FAULT:
            if word & _CW_FAULT_RESET and not previous & _CW_FAULT_RESET:
                self._fault_reset()
            return
        if state in (_S.NOT_READY_TO_SWITCH_ON, _S.FAULT_REACTION_ACTIVE):
            return
        command = _decode_controlword(word)
        step = _TRANSITIONS.get((state, command))
        if step is None:
            return
        numbers, target = step
        if numbers == (16,) and self._qs_option < 5:
            return
        for number in numbers:
            self._transition(number, target)
        if target is _S.OPERATION_ENABLED:
            self._enable_operation(now_s, resume=numbers == (16,))
        elif target is _S.QUICK_STOP_ACTIVE:
            self._start_quick_stop()
        elif target not in _POWERED:
            self._power_off()

    def _enable_operation(self, now_s: float, *, resume: bool) -> None:
        self._enabled_at_s = now_s
        self._fe_time_s = 0.0
        self._following_error = False
        self._ramping = False
        if not resume:
            self._integral_m = 0.0
            self._hold_at_actual()
        else:
            self._hold_at(self._demand_m)

    def _start_quick_stop(self) -> None:
        if self._qs_option == 0:
            self._transition(12, _S.SWITCH_ON_DISABLED)
            self._power_off()
            return
        self._start_ramp()

    def _start_ramp(self) -> None:
        self._ramping = True
        self._demand_m = self._p_meas_m
        self._ramp_v_m_s = self._v_est_m_s
        self._fe_time_s = 0.0
        self._following_error = False

    def _power_off(self) -> None:
        self._ramping = False
        self._integral_m = 0.0
        self._fe_time_s = 0.0
        self._following_error = False
        self._hold_at_actual()

    def _ramp_done(self) -> None:
        """A quick-stop or fault-reaction ramp reached standstill."""
        self._ramping = False
        if self._state is _S.FAULT_REACTION_ACTIVE:
            self._transition(14, _S.FAULT)
            self._power_off()
        elif self._state is _S.QUICK_STOP_ACTIVE and self._qs_option < 5:
            self._transition(12, _S.SWITCH_ON_DISABLED)
            self._power_off()
        else:
            self._hold_at(self._demand_m)

    def _raise_fault(self, code: int, reaction: int | None = None) -> None:
        """A fault: EMCY, 0x603F, error register, transition 13 and the fault reaction
        (``reaction``: a fault reaction option code, 0x605E's when None)."""
        self._error_code = code
        self._error_register |= _error_register_bits(code)
        self._emcy_queue.append(code)
        state = self._state
        if state in (_S.FAULT_REACTION_ACTIVE, _S.FAULT):
            return
        self._transition(13, _S.FAULT_REACTION_ACTIVE)
        option = self._fr_option if reaction is None else reaction
        if state in (_S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE) and option != 0:
            self._start_ramp()
        else:
            self._transition(14, _S.FAULT)
            self._power_off()

    def _fault_reset(self) -> None:
        self._transition(15, _S.SWITCH_ON_DISABLED)
        self._error_code = 0
        self._error_register = 0
        self._emcy_queue.append(EmcyCode.NO_ERROR)
        self._power_off()

    def inject_fault(self, code: int, reaction: int | None = None) -> None:
        """Raise a drive fault from outside (scenarios): EMCY ``code`` and the fault reaction.

        Args:
            code: Emergency error code (u16), e.g. 0x2310 (continuous over-current).
            reaction: The fault's own reaction, a fault reaction option code: 0 disable the
                drive function at once (power stage off, brake on: an over-current or an
                under-voltage leaves nothing to ramp with), 2 the quick-stop ramp (an
                over-temperature warning still has power to stop with); None: 0x605E's.

        Raises:
            ValueError: ``code`` is 0 or does not fit 16 bits, or ``reaction`` is not 0 or 2.
        """
        if not 0 < code <= 0xFFFF:
            raise ValueError(f"emergency code 0x{code:X} must be in 0x0001..0xFFFF")
        if reaction not in (None, 0, 2):
            raise ValueError(f"fault reaction {reaction!r}; allowed: 0 (disable), 2 (ramp)")
        self._raise_fault(code, reaction)

    def power_cycle(self, now_s: float) -> list[Frame]:
        """The drive reboots (its logic supply dipped): every object back to its stored value,
        the power drive state machine from NOT READY TO SWITCH ON, the power stage off, and the
        boot-up frame ``0x700+id [00]`` sent unannounced (PRE-OPERATIONAL: no PDOs until the
        master starts the node again).

        Returns:
            The boot-up frame.
        """
        return self._reset(now_s, application=True)

    def _set_mode(self, mode: int) -> None:
        if mode == self._mode:
            return
        self._mode = mode
        self._hold_at(self._demand_m)

    # ----------------------------------------------------------------------------------------
    # Time-triggered frames and supervision
    # ----------------------------------------------------------------------------------------

    def pending_frames(self, now_s: float) -> list[Frame]:
        """Run the time supervision and return the time-triggered frames due at ``now_s``.

        Completes initialisation at power-on (boot-up frame), checks the master's heartbeat and
        the SYNC/RPDO watchdog (either may raise a fault), then returns the queued emergencies
        followed by a heartbeat when one is due. Call it at least once per SYNC period.

        Args:
            now_s: Current time (same clock as :meth:`on_frame`), s.

        Returns:
            Frames to send, in order.
        """
        out: list[Frame] = []
        if self._nmt is _NMT_INITIALISING:
            self._reset_application_at_power_on()
            out.append(self._boot(now_s))
        self._supervise(now_s)
        if self._emcy_queue:
            if self._nmt is not _NMT_STOPPED and self._emcy_cob is not None:
                register = self._error_register
                out.extend(
                    (self._emcy_cob, struct.pack("<HB5x", code, register))
                    for code in self._emcy_queue
                )
            self._emcy_queue.clear()
        if self._hb_next_s is not None and now_s >= self._hb_next_s:
            out.append((COB_HEARTBEAT + self.node_id, bytes([self._nmt])))
            period_s = int(self._values[(0x1017, 0)]) * 1e-3
            self._hb_next_s += period_s
            if self._hb_next_s <= now_s:
                self._hb_next_s = now_s + period_s
        return out

    def _reset_application_at_power_on(self) -> None:
        self._mode = int(self._values.get((0x6060, 0), 0))
        self._hold_at_actual()

    def _supervise(self, now_s: float) -> None:
        last_hb = self._hb_last_rx_s
        if last_hb is not None and now_s - last_hb > self._hb_consumer_timeout_s:
            self._hb_last_rx_s = None
            self._raise_fault(EmcyCode.HEARTBEAT)
        if self._state is _OPERATION_ENABLED and self._enabled_at_s is not None:
            timeout_s = self._sync_timeout_s
            since = self._enabled_at_s
            last_sync = max(since, self._last_sync_s if self._last_sync_s is not None else since)
            last_rpdo = max(since, self._last_rpdo1_s if self._last_rpdo1_s is not None else since)
            if now_s - last_sync > timeout_s or now_s - last_rpdo > timeout_s:
                self._raise_fault(EmcyCode.RPDO_TIMEOUT)

    # ----------------------------------------------------------------------------------------
    # Servo
    # ----------------------------------------------------------------------------------------

    def _hold_at_actual(self) -> None:
        self._hold_at(self._p_meas_m)

    def _hold_at(self, position_m: float) -> None:
        self._demand_m = position_m
        self._seg_p0_m = self._seg_p1_m = position_m
        self._seg_v0_m_s = self._seg_v1_m_s = self._voff_m_s = 0.0
        self._seg_t_s = self._seg_T_s = 0.0

    def _latch_setpoint(self) -> None:
        """SYNC: start a new interpolation segment towards 0x607A / 0x60B1."""
        if self._state is not _OPERATION_ENABLED or self._mode != _MODE_CSP:
            return
        target_m = int(self._values[(0x607A, 0)]) * 1e-6
        limited = min(max(target_m, self._limit_min_m), self._limit_max_m)
        self._target_limited = limited != target_m
        period_s = self._interp_T_s
        if period_s <= 0.0 and self._sync_interval_s is not None:
            period_s = self._sync_interval_s
        self._seg_p0_m = self._demand_m
        self._seg_p1_m = limited
        self._seg_v0_m_s = self._voff_m_s
        self._seg_v1_m_s = int(self._values[(0x60B1, 0)]) * 1e-6
        self._seg_t_s = 0.0
        self._seg_T_s = period_s

    @property
    def overlap_compensation(self) -> float:
        """The jump out of the valve's dead band this drive applies (0x2100; fraction of full
        opening; 0 on an electric drive)."""
        return self._jump

    @property
    def load_compensated(self) -> bool:
        """True for a valve drive that reads the cylinder force (``load_force_n`` of
        :meth:`servo_step`) to scale its flow gain to the load."""
        return self._load_filter_s > 0.0

    @property
    def reads_load(self) -> bool:
        """True for a valve drive that reads the cylinder force from its chamber-pressure
        transducers (``load_force_n`` of :meth:`servo_step`): for load compensation, pressure
        feedback or both."""
        return self._load_filter_s > 0.0 or self._pf_gain > 0.0

    def servo_step(
        self, dt_s: float, position_m: float, velocity_m_s: float, load_force_n: float = 0.0
    ) -> float:
        """Advance the servo cascade by one sub-step.

        Args:
            dt_s: Sub-step, s (> 0; the rig's servo period, 250 us by default).
            position_m: True cylinder stroke from the plant, m (quantised here).
            velocity_m_s: True stroke rate, m/s; seeds the velocity estimate on the first call
                only (afterwards the firmware differentiates its encoder, as a drive must).
            load_force_n: Cylinder force from the chamber-pressure transducers, N (positive
                pushing out); read only by a valve drive with load compensation.

        Returns:
            Effort in [-1, 1]: force / force_max_n (electric) or valve opening (hydraulic);
            0 while the power stage is off.
        """
        res = self._res_m
        p_meas = math.floor(position_m / res + 0.5) * res
        if not self._measured:
            self._measured = True
            self._p_prev_m = p_meas
            self._v_est_m_s = velocity_m_s
            self._hold_at(p_meas)
        else:
            v_raw = (p_meas - self._p_prev_m) / dt_s
            v_est = self._v_est_m_s
            self._v_est_m_s = v_est + (v_raw - v_est) * (dt_s / (self._filter_s + dt_s))
            self._p_prev_m = p_meas
        self._p_meas_m = p_meas
        load = None
        tau = self._load_filter_s
        if tau > 0.0:  # the transducers' force, low-passed whatever the state
            load = self._load_n
            load = (
                load_force_n
                if load is None
                else load + (load_force_n - load) * (dt_s / (tau + dt_s))
            )
            self._load_n = load
        damping = 0.0
        if self._pf_gain > 0.0:  # dynamic pressure feedback: the force less its low-pass
            low = self._pf_low_n
            low = (
                load_force_n
                if low is None
                else low + (load_force_n - low) * (dt_s / (self._pf_filter_s + dt_s))
            )
            self._pf_low_n = low
            damping = self._pf_gain * (load_force_n - low) / self._stall_extend_n
        state = self._state
        if state is _OPERATION_ENABLED:
            if self._mode == _MODE_CSP:
                seg_T = self._seg_T_s
                t = self._seg_t_s + dt_s
                self._seg_t_s = t
                f = 1.0 if t >= seg_T else t / seg_T
                p0 = self._seg_p0_m
                self._demand_m = p0 + (self._seg_p1_m - p0) * f
                v0 = self._seg_v0_m_s
                self._voff_m_s = v0 + (self._seg_v1_m_s - v0) * f
            feed_forward_m_s = self._voff_m_s
        elif state is _QUICK_STOP_ACTIVE or state is _FAULT_REACTION_ACTIVE:
            feed_forward_m_s = 0.0
            if self._ramping:
                v0 = self._ramp_v_m_s
                dv = self._qs_decel_m_s2 * dt_s
                v1 = 0.0 if abs(v0) <= dv else v0 - math.copysign(dv, v0)
                self._demand_m += 0.5 * (v0 + v1) * dt_s
                self._ramp_v_m_s = feed_forward_m_s = v1
        else:
            self._demand_m = p_meas
            self._limit_active = False
            self.effort = 0.0
            return 0.0

        # Cascade: position P (+ feed-forward) -> velocity PI -> effort, or -> valve command.
        v_max = self._v_max_m_s
        v_cmd = self._kp_1_s * (self._demand_m - p_meas) + feed_forward_m_s
        limited = False
        if v_cmd > v_max:
            v_cmd, limited = v_max, True
        elif v_cmd < -v_max:
            v_cmd, limited = -v_max, True
        if self._valve_output:
            u = v_cmd / (self._valve_extend_m_s if v_cmd >= 0.0 else self._valve_retract_m_s)
            if load is not None:
                u /= load_gain_ratio(
                    load, v_cmd >= 0.0, self._stall_extend_n, self._stall_retract_n
                )
            u -= damping
            if self._jump > 0.0:
                u = overlap_jump(u, self._jump)
        else:
            error = v_cmd - self._v_est_m_s
            ki = self._ki_1_s
            integral = self._integral_m
            u = self._kv_s_m * (error + ki * integral)
            # Conditional integration, bounded to what the output can use (anti-windup).
            if ki > 0.0 and not ((u > 1.0 and error > 0.0) or (u < -1.0 and error < 0.0)):
                bound = self._integral_bound_m
                integral += error * dt_s
                self._integral_m = -bound if integral < -bound else min(integral, bound)  # clamp
        if u > 1.0:
            u, limited = 1.0, True
        elif u < -1.0:
            u, limited = -1.0, True
        self.effort = u

        if state is _OPERATION_ENABLED:
            self._limit_active = limited or self._target_limited
            if abs(self._demand_m - p_meas) > self._window_m:
                self._following_error = True
                self._fe_time_s += dt_s
                if self._fe_time_s > self._fe_timeout_s:
                    self._raise_fault(EmcyCode.FOLLOWING_ERROR)
            else:
                self._following_error = False
                self._fe_time_s = 0.0
        else:
            self._limit_active = limited
            if self._ramping and feed_forward_m_s == 0.0:
                self._ramp_done()
        return u


def _bind_rpdo(
    handler: Callable[[bytes, float, _Pdo], list[Frame]], pdo: _Pdo
) -> Callable[[bytes, float], list[Frame]]:
    def on_rpdo(data: bytes, now_s: float) -> list[Frame]:
        return handler(data, now_s, pdo)

    return on_rpdo


def _decode_controlword(word: int) -> _Command:
    """CiA 402 device control command of a controlword (bit 7 set: none)."""
    if word & _CW_FAULT_RESET:
        return _C.NONE
    if not word & 0x02:
        return _C.DISABLE_VOLTAGE
    if not word & 0x04:
        return _C.QUICK_STOP
    if not word & 0x01:
        return _C.SHUTDOWN
    return _C.ENABLE_OPERATION if word & 0x08 else _C.SWITCH_ON


def _ms(seconds: float, maximum: int) -> int:
    return _clip(round(seconds * 1e3), 0, maximum)


def _clip(value: int, low: int, high: int) -> int:
    return low if value < low else high if value > high else value
