"""Behaviour model of the vehicle control unit (travel and swing motors, Yao et al. 2023, 5.1).

Role: the HIL's stand-in for the rig's VCU, speaking the message set of ``vcu.dbc`` (read with
cantools, the same file the runtime's :mod:`rt_runtime.canbus.vcu` reads). Like the drive model
it is bus-agnostic and clock-free: :meth:`VcuModel.on_frame` takes frames with their arrival
time, :meth:`VcuModel.step` advances the motors by ``dt_s``, :meth:`VcuModel.pending_frames`
runs the command watchdog.

Behaviour:

* ``VCU_Command`` (0x200 + node): Enable, TravelMode (STOP, SPEED, POSITION), FaultReset,
  TravelSpeedCmd (SPEED: setpoint; POSITION: speed limit), TravelTargetPos, SwingAngleCmd.
* ``VCU_Status`` (0x180 + node): State, Fault, TravelPosition, SwingAngle, TravelSpeed; sent on
  every SYNC (0x080), sampled before the period's motion like a TPDO.
* Each axis is a velocity- and acceleration-limited double integrator. Speed tracking ramps the
  velocity at the acceleration limit; position tracking follows the braking curve
  ``v = sign(e) min(v_max, sqrt(2 a |e|))`` (in its discrete form, so it neither overshoots nor
  exceeds the acceleration limit) and arrives exactly.
  The swing target is clamped to the swing range.
* States: DISABLED (at rest, brakes on) -> Enable 1 -> ENABLED; Enable 0 -> STOPPING (both axes
  decelerate at their limits) -> DISABLED at rest. No command for ``command_timeout_s`` while
  ENABLED, or :meth:`VcuModel.inject_fault` -> FAULT (axes decelerate to rest); a rising
  FaultReset with Enable 0 clears it once at rest.

Limits not in the rig profile are assumed (marked in :meth:`VcuLimits.from_rig`): travel
0.2 m/s and 0.2 m/s^2 (a scale-model crawler), swing range +-pi, 30 deg/s and 10 deg/s^2 (Yao
Table 1's arm joint figures) unless the rig has a swing joint, whose limits are used.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Protocol

import cantools
from cantools.database.can import Database, Message

from firmware_models import VCU_DBC, VCU_DBC_NODE_ID
from firmware_models.errors import FirmwareConfigurationError

__all__ = [
    "TravelMode",
    "VcuFault",
    "VcuLimits",
    "VcuModel",
    "VcuState",
    "load_vcu_database",
]

Frame = tuple[int, bytes]

COB_SYNC = 0x080


class VcuState(IntEnum):
    """``VCU_Status.State`` (DBC value table)."""

    DISABLED = 0
    ENABLED = 1
    STOPPING = 2
    FAULT = 3


class VcuFault(IntEnum):
    """``VCU_Status.Fault`` (DBC value table)."""

    NONE = 0
    COMMAND_TIMEOUT = 1
    MOTOR = 2


class TravelMode(IntEnum):
    """``VCU_Command.TravelMode`` (DBC value table)."""

    STOP = 0
    SPEED = 1
    POSITION = 2


def load_vcu_database(dbc: Path | str = VCU_DBC) -> Database:
    """Read the VCU message set with cantools.

    Raises:
        FirmwareConfigurationError: The file is missing, is not a CAN DBC, or lacks the VCU
            messages.
    """
    path = Path(dbc)
    if not path.is_file():
        raise FirmwareConfigurationError(f"VCU DBC file {path} does not exist")
    db = cantools.database.load_file(str(path))
    if not isinstance(db, Database):
        raise FirmwareConfigurationError(f"{path} is not a CAN database")
    names = {m.name for m in db.messages}
    missing = {"VCU_Command", "VCU_Status"} - names
    if missing:
        raise FirmwareConfigurationError(f"{path} lacks the messages {sorted(missing)}")
    return db


def shifted_frame_id(message: Message, node_id: int) -> int:
    """Frame id of ``message`` for a VCU at ``node_id`` (the DBC is written for node 0x10)."""
    return int(message.frame_id) - VCU_DBC_NODE_ID + node_id


class _JointLike(Protocol):
    @property
    def min_rad(self) -> float: ...
    @property
    def max_rad(self) -> float: ...
    @property
    def velocity_max_rad_s(self) -> float: ...
    @property
    def acceleration_max_rad_s2(self) -> float: ...


class _SwingLike(Protocol):
    @property
    def joint(self) -> _JointLike: ...


class _CanLike(Protocol):
    @property
    def vcu_node_id(self) -> int: ...


class _RigLike(Protocol):
    @property
    def can(self) -> _CanLike: ...
    @property
    def swing(self) -> _SwingLike | None: ...


@dataclass(frozen=True, slots=True)
class VcuLimits:
    """Motion limits of the VCU's axes (SI units).

    Attributes:
        travel_speed_max_m_s: Travel speed limit.
        travel_acceleration_max_m_s2: Travel acceleration limit.
        swing_min_rad: Lower end of the swing range.
        swing_max_rad: Upper end of the swing range.
        swing_speed_max_rad_s: Swing rate limit.
        swing_acceleration_max_rad_s2: Swing acceleration limit.
        command_timeout_s: Longest gap between commands while enabled.
    """

    travel_speed_max_m_s: float = 0.2  # assumed: scale-model crawler
    travel_acceleration_max_m_s2: float = 0.2  # assumed
    swing_min_rad: float = -math.pi  # assumed: the swing signal's range
    swing_max_rad: float = math.pi
    swing_speed_max_rad_s: float = math.radians(30.0)  # assumed: Yao Table 1 bucket rate
    swing_acceleration_max_rad_s2: float = math.radians(10.0)  # assumed: Yao Table 1
    command_timeout_s: float = 0.1

    def __post_init__(self) -> None:
        for name in (
            "travel_speed_max_m_s",
            "travel_acceleration_max_m_s2",
            "swing_speed_max_rad_s",
            "swing_acceleration_max_rad_s2",
            "command_timeout_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise FirmwareConfigurationError(f"VCU limit {name} = {value!r} must be > 0")
        if not -math.pi <= self.swing_min_rad < self.swing_max_rad <= math.pi:
            raise FirmwareConfigurationError(
                f"VCU swing range [{self.swing_min_rad!r}, {self.swing_max_rad!r}] rad must be "
                "increasing and inside [-pi, pi] (the SwingAngle signal's range)"
            )

    @classmethod
    def from_rig(cls, rig: _RigLike) -> VcuLimits:
        """Swing limits from the rig's swing joint where it has one, assumed values otherwise."""
        if rig.swing is None:
            return cls()
        joint = rig.swing.joint
        return cls(
            swing_min_rad=max(joint.min_rad, -math.pi),
            swing_max_rad=min(joint.max_rad, math.pi),
            swing_speed_max_rad_s=joint.velocity_max_rad_s,
            swing_acceleration_max_rad_s2=joint.acceleration_max_rad_s2,
        )


def _approach(
    x: float, v: float, target: float, v_max: float, a_max: float, dt_s: float
) -> tuple[float, float]:
    """One step of time-optimal-ish position tracking; returns (x, v)."""
    error = target - x
    dv = a_max * dt_s
    if abs(error) <= 0.5 * dv * dt_s and abs(v) <= dv:
        return target, 0.0
    # Braking speed of the discrete deceleration sequence (v, v - dv, ..., 0) over the distance
    # left after this step's half-step of travel: never overshoots, never exceeds a_max.
    distance = max(abs(error) - 0.5 * abs(v) * dt_s, 0.0)
    brake = math.sqrt(2.0 * a_max * distance + 0.25 * dv * dv) - 0.5 * dv
    v_des = math.copysign(min(v_max, brake), error)
    v_new = v + min(max(v_des - v, -dv), dv)
    x_new = x + 0.5 * (v + v_new) * dt_s
    if (target - x_new) * error <= 0.0:  # arrives within this step
        return target, 0.0
    return x_new, v_new


def _ramp(x: float, v: float, v_des: float, a_max: float, dt_s: float) -> tuple[float, float]:
    """One step of acceleration-limited speed tracking; returns (x, v)."""
    dv = a_max * dt_s
    v_new = v + min(max(v_des - v, -dv), dv)
    return x + 0.5 * (v + v_new) * dt_s, v_new


@dataclass(frozen=True, slots=True)
class _Command:
    """The fields of one decoded ``VCU_Command`` (the swing target not yet clamped)."""

    enable: bool
    fault_reset: bool
    travel_mode: TravelMode
    travel_speed_m_s: float
    travel_target_m: float
    swing_angle_rad: float

    @classmethod
    def from_fields(cls, fields: Mapping[str, object]) -> _Command:
        """From cantools' signal values (missing or non-numeric signals read as 0)."""
        mode = int(_number(fields, "TravelMode"))
        valid_modes = {m.value for m in TravelMode}
        return cls(
            enable=_number(fields, "Enable") != 0,
            fault_reset=_number(fields, "FaultReset") != 0,
            travel_mode=TravelMode(mode) if mode in valid_modes else TravelMode.STOP,  # 3: STOP
            travel_speed_m_s=_number(fields, "TravelSpeedCmd"),
            travel_target_m=_number(fields, "TravelTargetPos"),
            swing_angle_rad=_number(fields, "SwingAngleCmd"),
        )


# Members as module constants for VcuModel.step (one call per servo sub-step in the HIL): an
# enum member looked up through its class costs ~0.1 us per access.
_DISABLED = VcuState.DISABLED
_ENABLED = VcuState.ENABLED
_STOPPING = VcuState.STOPPING
_SPEED = TravelMode.SPEED
_POSITION = TravelMode.POSITION
_STOP = TravelMode.STOP


class VcuModel:
    """The VCU on the bus: commands in, status on SYNC, travel and swing motion.

    Args:
        node_id: Node id the frame ids are shifted to (``rig.can.vcu_node_id``).
        limits: Motion limits.
        dbc: Message set.
        travel_position_m: Initial travel position.
        swing_angle_rad: Initial swing angle.

    Raises:
        FirmwareConfigurationError: Bad node id, DBC or limits.
    """

    def __init__(
        self,
        node_id: int,
        limits: VcuLimits | None = None,
        dbc: Path | str = VCU_DBC,
        *,
        travel_position_m: float = 0.0,
        swing_angle_rad: float = 0.0,
    ) -> None:
        if not 1 <= node_id <= 127:
            raise FirmwareConfigurationError(f"VCU node id {node_id} is outside 1..127")
        self.node_id = node_id
        self.limits = limits if limits is not None else VcuLimits()
        db = load_vcu_database(dbc)
        self._command_msg = db.get_message_by_name("VCU_Command")
        self._status_msg = db.get_message_by_name("VCU_Status")
        self.command_id = shifted_frame_id(self._command_msg, node_id)
        self.status_id = shifted_frame_id(self._status_msg, node_id)
        self.travel_position_m = travel_position_m
        self.travel_speed_m_s = 0.0
        self.swing_angle_rad = swing_angle_rad
        self.swing_velocity_rad_s = 0.0
        self.state = VcuState.DISABLED
        self.fault = VcuFault.NONE
        self._enable = False
        self._fault_reset = False
        self._travel_mode = TravelMode.STOP
        self._travel_speed_cmd_m_s = 0.0
        self._travel_target_m = travel_position_m
        self._swing_target_rad = swing_angle_rad
        self._last_command_s: float | None = None
        # One-entry caches of the cantools codec (~5 us a call): the master repeats its command
        # every period and the status repeats while the axes stand; both maps are pure.
        self._command_cache: tuple[bytes, _Command | None] | None = None
        self._status_cache: tuple[tuple[int, int, float, float, float], bytes] | None = None

    @classmethod
    def from_rig(cls, rig: _RigLike, dbc: Path | str = VCU_DBC) -> VcuModel:
        """The VCU of ``rig``: node id from ``rig.can.vcu_node_id``, limits from the rig."""
        return cls(rig.can.vcu_node_id, VcuLimits.from_rig(rig), dbc)

    @property
    def at_rest(self) -> bool:
        """Whether both axes stand still."""
        return self.travel_speed_m_s == 0.0 and self.swing_velocity_rad_s == 0.0

    def on_frame(self, arbitration_id: int, data: bytes, now_s: float) -> list[Frame]:
        """Handle one received frame; returns the status frame on SYNC, else nothing.

        A command frame that does not decode is ignored (and does not feed the watchdog).
        """
        if arbitration_id == COB_SYNC:
            return [(self.status_id, self.status_payload())]
        if arbitration_id != self.command_id:
            return []
        payload = bytes(data)
        cached = self._command_cache
        if cached is not None and cached[0] == payload:
            command = cached[1]
        else:
            try:
                fields = self._command_msg.decode(payload, decode_choices=False)
            except cantools.database.DecodeError:
                fields = None
            command = _Command.from_fields(fields) if isinstance(fields, dict) else None
            self._command_cache = (payload, command)
        if command is not None:
            self._apply_command(command, now_s)
        return []

    def _apply_command(self, command: _Command, now_s: float) -> None:
        self._last_command_s = now_s
        enable = command.enable
        fault_reset = command.fault_reset
        self._travel_mode = command.travel_mode
        self._travel_speed_cmd_m_s = command.travel_speed_m_s
        self._travel_target_m = command.travel_target_m
        lim = self.limits
        swing = command.swing_angle_rad
        self._swing_target_rad = min(max(swing, lim.swing_min_rad), lim.swing_max_rad)
        rising_reset = fault_reset and not self._fault_reset
        self._fault_reset = fault_reset
        self._enable = enable
        if self.state is VcuState.FAULT:
            if rising_reset and not enable and self.at_rest:
                self.state, self.fault = VcuState.DISABLED, VcuFault.NONE
            return
        if enable and self.state is VcuState.DISABLED:
            self.state = VcuState.ENABLED
        elif not enable and self.state is VcuState.ENABLED:
            self.state = VcuState.STOPPING

    def status_payload(self) -> bytes:
        """``VCU_Status`` as it would be sent now."""
        key = (
            int(self.state),
            int(self.fault),
            self.travel_position_m,
            self.swing_angle_rad,
            self.travel_speed_m_s,
        )
        cached = self._status_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        payload = bytes(
            self._status_msg.encode(
                {
                    "State": key[0],
                    "Fault": key[1],
                    "TravelPosition": _clamp_signal(
                        self._status_msg, "TravelPosition", self.travel_position_m
                    ),
                    "SwingAngle": _clamp_signal(
                        self._status_msg, "SwingAngle", self.swing_angle_rad
                    ),
                    "TravelSpeed": _clamp_signal(
                        self._status_msg, "TravelSpeed", self.travel_speed_m_s
                    ),
                },
                strict=False,
            )
        )
        self._status_cache = (key, payload)
        return payload

    def pending_frames(self, now_s: float) -> list[Frame]:
        """Run the command watchdog; the VCU sends nothing time-triggered (status is on SYNC)."""
        last = self._last_command_s
        if (
            self.state is VcuState.ENABLED
            and last is not None
            and now_s - last > self.limits.command_timeout_s
        ):
            self.inject_fault(VcuFault.COMMAND_TIMEOUT)
        return []

    def inject_fault(self, code: VcuFault | int = VcuFault.MOTOR) -> None:
        """Fault the VCU (scenarios): both axes decelerate to rest and stay braked.

        Raises:
            ValueError: ``code`` is not a fault of :class:`VcuFault` (NONE is not).
        """
        fault = VcuFault(code)
        if fault is VcuFault.NONE:
            raise ValueError("inject_fault needs a fault code, not NONE")
        self.state, self.fault = VcuState.FAULT, fault

    def step(self, dt_s: float) -> None:
        """Advance both axes by ``dt_s`` seconds."""
        lim = self.limits
        state = self.state
        x, v = self.travel_position_m, self.travel_speed_m_s
        th, w = self.swing_angle_rad, self.swing_velocity_rad_s
        if v == 0.0 and w == 0.0:
            # At rest and holding (the VCU's usual state while the arm digs): the general path
            # below would compute exactly these values (_ramp from rest to rest gives x + 0.0
            # and speed 0.0; _approach at its target returns the target and 0.0).
            if state is _ENABLED and self._travel_mode is _STOP and th == self._swing_target_rad:
                self.travel_position_m, self.travel_speed_m_s = x + 0.0, 0.0
                self.swing_angle_rad, self.swing_velocity_rad_s = self._swing_target_rad, 0.0
                return
            if state is _DISABLED and lim.swing_min_rad <= th <= lim.swing_max_rad:
                self.travel_position_m, self.travel_speed_m_s = x + 0.0, 0.0
                self.swing_angle_rad, self.swing_velocity_rad_s = th + 0.0, 0.0
                return
        a = lim.travel_acceleration_max_m_s2
        if state is _ENABLED:
            mode = self._travel_mode
            v_max = lim.travel_speed_max_m_s
            if mode is _SPEED:
                v_des = min(max(self._travel_speed_cmd_m_s, -v_max), v_max)
                x, v = _ramp(x, v, v_des, a, dt_s)
            elif mode is _POSITION:
                limit = min(abs(self._travel_speed_cmd_m_s), v_max)
                if limit > 0.0:
                    x, v = _approach(x, v, self._travel_target_m, limit, a, dt_s)
                else:
                    x, v = _ramp(x, v, 0.0, a, dt_s)
            else:
                x, v = _ramp(x, v, 0.0, a, dt_s)
            th, w = _approach(
                th,
                w,
                self._swing_target_rad,
                lim.swing_speed_max_rad_s,
                lim.swing_acceleration_max_rad_s2,
                dt_s,
            )
        else:
            x, v = _ramp(x, v, 0.0, a, dt_s)
            th, w = _ramp(th, w, 0.0, lim.swing_acceleration_max_rad_s2, dt_s)
            th = min(max(th, lim.swing_min_rad), lim.swing_max_rad)
        self.travel_position_m, self.travel_speed_m_s = x, v
        self.swing_angle_rad, self.swing_velocity_rad_s = th, w
        if state is _STOPPING and v == 0.0 and w == 0.0:
            self.state = _DISABLED


def _number(fields: Mapping[str, object], name: str) -> float:
    value = fields.get(name, 0)
    return float(value) if isinstance(value, (int, float)) else 0.0


def _clamp_signal(message: Message, name: str, value: float) -> float:
    signal = message.get_signal_by_name(name)
    low = signal.minimum if signal.minimum is not None else value
    high = signal.maximum if signal.maximum is not None else value
    return min(max(value, low), high)
