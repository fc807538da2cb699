"""VCU: the DBC message set, the runtime's client and the model, cross-checked with cantools."""

from __future__ import annotations

import itertools
import math
import random
import time
from dataclasses import dataclass

import cantools
import pytest

import firmware_models.vcu as model_vcu
import rt_runtime.canbus.vcu as client_vcu
from firmware_models import VCU_DBC
from firmware_models.errors import FirmwareConfigurationError
from firmware_models.vcu import VcuLimits, VcuModel
from rt_runtime.canbus.vcu import TravelMode, VcuClient, VcuCommand, VcuFault, VcuState
from rt_runtime.errors import ConfigurationError

NODE = 0x10
SYNC = 0x080
PERIOD_S = 2e-3


@dataclass
class Bus:
    """Master (client) and VCU model in lockstep, one SYNC per period."""

    client: VcuClient
    vcu: VcuModel
    t_s: float = 0.0

    def cycle(self, command: VcuCommand | None) -> client_vcu.VcuStatus:
        if command is not None:
            self.vcu.on_frame(*self.client.command_frame(command), self.t_s)
        replies = self.vcu.on_frame(SYNC, b"", self.t_s)
        self.vcu.pending_frames(self.t_s)
        self.vcu.step(PERIOD_S)
        self.t_s += PERIOD_S
        assert len(replies) == 1
        status = self.client.decode_status(*replies[0])
        assert status is not None
        return status


def _bus(node_id: int = NODE, limits: VcuLimits | None = None) -> Bus:
    return Bus(VcuClient(node_id), VcuModel(node_id, limits))


def test_dbc_layout_and_value_tables() -> None:
    db = cantools.database.load_file(str(VCU_DBC))
    assert isinstance(db, cantools.database.can.Database)
    command = db.get_message_by_name("VCU_Command")
    status = db.get_message_by_name("VCU_Status")
    assert (command.frame_id, command.length) == (0x200 + NODE, 8)
    assert (status.frame_id, status.length) == (0x180 + NODE, 8)
    for message in (command, status):
        bits = sorted(bit for s in message.signals for bit in range(s.start, s.start + s.length))
        assert bits == sorted(set(bits)), f"{message.name}: signals overlap"
        assert all(s.byte_order == "little_endian" for s in message.signals)
    # The enums of both sides equal the DBC value tables.
    for module in (model_vcu, client_vcu):
        for message, signal, enum in (
            (command, "TravelMode", module.TravelMode),
            (status, "State", module.VcuState),
            (status, "Fault", module.VcuFault),
        ):
            choices = message.get_signal_by_name(signal).choices
            assert {int(v): str(n) for v, n in choices.items()} == {m.value: m.name for m in enum}


def test_command_encoding_byte_exact_and_decoded_by_cantools() -> None:
    client = VcuClient(NODE)
    command = VcuCommand(
        enable=True,
        travel_mode=TravelMode.POSITION,
        travel_speed_m_s=0.15,
        travel_target_m=-1.234,
        swing_angle_rad=-0.5,
    )
    can_id, data = client.command_frame(command)
    # Enable 1 | mode 2 << 1 = 0x05; 150 mm/s = 0x0096; -1234 mm (24 bit) = 0xFFFB2E;
    # -5000 * 0.1 mrad = 0xEC78.
    assert (can_id, data.hex()) == (0x210, "0596002efbff78ec")
    decoded = cantools.database.load_file(str(VCU_DBC)).decode_message(can_id, data)
    assert decoded == {
        "Enable": 1,
        "TravelMode": "POSITION",
        "FaultReset": 0,
        "TravelSpeedCmd": 0.15,
        "TravelTargetPos": -1.234,
        "SwingAngleCmd": -0.5,
    }
    message = client.command_message(command)
    assert (message.arbitration_id, bytes(message.data), message.is_extended_id) == (
        0x210,
        data,
        False,
    )
    # Saturation to the signal ranges, refusal of non-finite values.
    wide = client.encode_command(VcuCommand(enable=True, swing_angle_rad=10.0))
    assert cantools.database.load_file(str(VCU_DBC)).decode_message(0x210, wide)[
        "SwingAngleCmd"
    ] == pytest.approx(3.2767)
    with pytest.raises(ValueError, match="finite"):
        client.encode_command(VcuCommand(enable=True, travel_speed_m_s=math.nan))


def test_status_round_trip_and_node_id_shift() -> None:
    vcu = VcuModel(0x12, travel_position_m=12.345, swing_angle_rad=-1.2345)
    client = VcuClient(0x12)
    assert (client.command_id, client.status_id) == (0x212, 0x192)
    assert vcu.on_frame(0x210, bytes(8), 0.0) == []  # node 0x10's command: not ours
    (reply,) = vcu.on_frame(SYNC, b"", 0.0)
    assert reply[0] == 0x192
    status = client.decode_status(*reply)
    assert status == client_vcu.VcuStatus(
        state=VcuState.DISABLED,
        fault=VcuFault.NONE,
        travel_position_m=pytest.approx(12.345),  # type: ignore[arg-type]
        swing_angle_rad=pytest.approx(-1.2345),  # type: ignore[arg-type]
        travel_speed_m_s=0.0,
    )
    assert client.decode_status(0x190, reply[1]) is None  # another node's id
    assert client.decode_status(0x192, b"\x00") is None  # truncated
    assert client.decode_status(0x192, bytes([0x0F]) + bytes(7)) is None  # state 15 unknown
    assert client.decode_errors == 2


class _Can:
    vcu_node_id = 0x11


class _Joint:
    min_rad = -1.0
    max_rad = 2.0
    velocity_max_rad_s = 0.5
    acceleration_max_rad_s2 = 0.25


class _Swing:
    joint = _Joint()


class _Rig:
    can = _Can()
    swing: _Swing | None = _Swing()


def test_from_rig_uses_the_vcu_node_id_and_swing_limits() -> None:
    assert VcuClient.from_rig(_Rig()).command_id == 0x211
    vcu = VcuModel.from_rig(_Rig())
    assert vcu.node_id == 0x11
    assert (vcu.limits.swing_min_rad, vcu.limits.swing_speed_max_rad_s) == (-1.0, 0.5)
    no_swing = _Rig()
    no_swing.swing = None
    assert VcuModel.from_rig(no_swing).limits == VcuLimits()
    with pytest.raises(ConfigurationError, match="outside"):
        VcuClient(0)
    with pytest.raises(FirmwareConfigurationError, match="must be > 0"):
        VcuLimits(travel_speed_max_m_s=0.0)


def test_swing_and_travel_move_within_their_limits() -> None:
    limits = VcuLimits()
    bus = _bus(limits=limits)
    assert bus.cycle(VcuCommand(enable=False)).state is VcuState.DISABLED
    command = VcuCommand(
        enable=True,
        travel_mode=TravelMode.POSITION,
        travel_speed_m_s=0.1,
        travel_target_m=0.3,
        swing_angle_rad=0.4,
    )
    swing, travel, speeds = [], [], []
    for _ in range(int(6.0 / PERIOD_S)):
        status = bus.cycle(command)
        swing.append(bus.vcu.swing_angle_rad)
        travel.append(bus.vcu.travel_position_m)
        speeds.append(bus.vcu.travel_speed_m_s)
    assert status.state is VcuState.ENABLED
    assert status.swing_angle_rad == pytest.approx(0.4, abs=1e-4)
    assert status.travel_position_m == pytest.approx(0.3, abs=1e-3)
    assert bus.vcu.swing_angle_rad == 0.4 and bus.vcu.travel_position_m == 0.3  # arrived exactly
    swing_rate = [(b - a) / PERIOD_S for a, b in itertools.pairwise(swing)]
    swing_acc = [(b - a) / PERIOD_S for a, b in itertools.pairwise(swing_rate)]
    assert max(swing_rate) <= limits.swing_speed_max_rad_s * (1 + 1e-9)
    assert max(abs(a) for a in swing_acc) <= limits.swing_acceleration_max_rad_s2 * 1.01
    assert max(speeds) == pytest.approx(0.1)  # POSITION: speed limit from the command
    assert max(travel) <= 0.3  # no overshoot
    # SPEED mode, limited by the VCU's maximum speed, then STOP
    for _ in range(int(3.0 / PERIOD_S)):
        bus.cycle(VcuCommand(enable=True, travel_mode=TravelMode.SPEED, travel_speed_m_s=-5.0))
    assert bus.vcu.travel_speed_m_s == pytest.approx(-limits.travel_speed_max_m_s)
    for _ in range(int(1.5 / PERIOD_S)):
        status = bus.cycle(VcuCommand(enable=True, travel_mode=TravelMode.STOP))
    assert status.travel_speed_m_s == 0.0


def test_disable_stops_then_disables_and_timeout_faults() -> None:
    bus = _bus()
    for _ in range(300):  # 0.5 s to reach 0.1 m/s at 0.2 m/s^2
        bus.cycle(VcuCommand(enable=True, travel_mode=TravelMode.SPEED, travel_speed_m_s=0.1))
    status = bus.cycle(VcuCommand(enable=False))  # command first, then SYNC: reported at once
    assert status.state is VcuState.STOPPING
    assert status.travel_speed_m_s == pytest.approx(0.1)  # sampled before the period's motion
    while bus.vcu.state is model_vcu.VcuState.STOPPING:
        bus.cycle(VcuCommand(enable=False))
    assert bus.vcu.state is model_vcu.VcuState.DISABLED and bus.vcu.at_rest
    # command timeout while enabled
    for _ in range(100):
        bus.cycle(VcuCommand(enable=True, travel_mode=TravelMode.SPEED, travel_speed_m_s=0.1))
    last_command_s = bus.t_s - PERIOD_S
    while bus.vcu.state is model_vcu.VcuState.ENABLED:
        bus.cycle(None)
    assert bus.t_s - PERIOD_S - last_command_s == pytest.approx(0.1 + PERIOD_S, abs=PERIOD_S)
    status = bus.cycle(None)
    assert (status.state, status.fault) == (VcuState.FAULT, VcuFault.COMMAND_TIMEOUT)
    while not bus.vcu.at_rest:
        bus.cycle(VcuCommand(enable=False))
    bus.cycle(VcuCommand(enable=False, fault_reset=True))
    assert (bus.vcu.state, bus.vcu.fault) == (model_vcu.VcuState.DISABLED, model_vcu.VcuFault.NONE)


def test_injected_fault_needs_a_reset_edge_at_rest() -> None:
    bus = _bus()
    bus.cycle(VcuCommand(enable=True, swing_angle_rad=0.2))
    bus.vcu.inject_fault()
    assert bus.cycle(VcuCommand(enable=True)).fault is VcuFault.MOTOR
    bus.cycle(VcuCommand(enable=True, fault_reset=True))  # enable still set: no reset
    assert bus.vcu.state is model_vcu.VcuState.FAULT
    bus.cycle(VcuCommand(enable=False, fault_reset=True))  # no edge: still high
    assert bus.vcu.state is model_vcu.VcuState.FAULT
    bus.cycle(VcuCommand(enable=False))
    bus.cycle(VcuCommand(enable=False, fault_reset=True))
    assert bus.vcu.state is model_vcu.VcuState.DISABLED
    with pytest.raises(ValueError, match="NONE"):
        bus.vcu.inject_fault(0)


def test_codec_cost_report() -> None:
    """Prints the per-call cost of the client's cantools codec (no assertion on time)."""
    client = VcuClient(NODE)
    vcu = VcuModel(NODE)
    command = VcuCommand(enable=True, travel_mode=TravelMode.SPEED, travel_speed_m_s=0.1)
    (status_frame,) = vcu.on_frame(SYNC, b"", 0.0)
    n = 2000
    start = time.perf_counter()
    for _ in range(n):
        client.encode_command(command)
    encode_us = (time.perf_counter() - start) / n * 1e6
    start = time.perf_counter()
    for _ in range(n):
        client.decode_status(*status_frame)
    decode_us = (time.perf_counter() - start) / n * 1e6
    print(f"VCU client: encode {encode_us:.1f} us, decode {decode_us:.1f} us per frame")
    assert client.decode_status(*status_frame) is not None


# Pinned trajectory: a regression guard for performance work on the model. The values were
# computed with firmware_models/vcu.py before it was optimised (issue 7); an optimisation may
# reassociate floating-point sums, nothing more (rtol 1e-9). A behaviour change that moves them
# must recompute them on purpose, in its own commit, with the reason.


def _pinned_run() -> dict[str, list[float]]:
    """Seeded commands in every travel mode, a disable, a timeout fault and its reset."""
    rng = random.Random(90210)
    limits = VcuLimits(travel_acceleration_max_m_s2=2.0, swing_acceleration_max_rad_s2=3.0)
    bus = _bus(limits=limits)
    payload_sum = 0
    for k in range(900):
        block = k // 75
        if block in (3, 9):
            command = VcuCommand(enable=False, fault_reset=block == 9 and k % 75 > 40)
        elif block == 7 and k % 75 > 20:
            command = None  # the watchdog trips
        else:
            command = VcuCommand(
                enable=True,
                travel_mode=TravelMode(block % 3),
                travel_speed_m_s=rng.uniform(-0.3, 0.3) if k % 40 == 0 else 0.15 - 0.01 * block,
                travel_target_m=0.05 * block - 0.2,
                swing_angle_rad=0.3 * math.sin(0.7 * block),
            )
        status = bus.cycle(command)
        payload_sum += (k + 1) * int(status.state) + round(status.travel_position_m * 1e3)
    v = bus.vcu
    return {
        "travel": [v.travel_position_m, v.travel_speed_m_s],
        "swing": [v.swing_angle_rad, v.swing_velocity_rad_s],
        "state": [float(v.state), float(v.fault)],
        "status_sum": [float(payload_sum)],
    }


PINNED = {
    "travel": [0.062479999999999924, 0.04],
    "swing": [-0.02684422980816351, 0.5235987755982988],
    "state": [1.0, 0.0],
    "status_sum": [589683.0],
}


def test_pinned_trajectory() -> None:
    got = _pinned_run()
    assert got.keys() == PINNED.keys()
    for key, values in PINNED.items():
        assert got[key] == pytest.approx(values, rel=1e-9, abs=1e-15), key
