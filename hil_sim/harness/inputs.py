"""Property-based checks of the HIL's firmware models against random and mutated CAN frames.

Registered through the ``excavator_rt.inputs`` entry point ``firmware`` (the runtime never
imports the HIL): ``excavator-rt bench inputs`` runs these entries beside the runtime's
(:mod:`rt_runtime.inputs_fuzz` has the runner and the properties' rules). Two entry points:

* ``drive_frames``: frames into :meth:`firmware_models.drive.DriveFirmware.on_frame` of a
  drive in OPERATION_ENABLED (NMT, SYNC, both RPDOs, SDO requests: valid ones mutated, random
  ones, any length 0..8). Nothing raises; every reply is an 11-bit frame of at most 8 bytes;
  an RPDO shorter than its mapping changes neither the device state nor the position demand;
  an SDO request answered with an abort changes no object; an NMT command of the wrong length
  or for another node changes nothing.
* ``vcu_frames``: frames into :meth:`firmware_models.vcu.VcuModel.on_frame`. Nothing raises;
  a command that does not decode changes nothing; every status frame decodes with the
  runtime's :class:`~rt_runtime.canbus.vcu.VcuClient`.
"""

from __future__ import annotations

import contextlib
import math
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from hypothesis import strategies as st

from firmware_models.drive import DeviceState, DriveFirmware, NmtState
from firmware_models.vcu import VcuModel
from rt_runtime.canbus.vcu import VcuClient
from rt_runtime.inputs_fuzz import InputEntry, PropertyViolation, Verdict, mutated_frames
from rt_runtime.rig import Rig, load_rig

__all__ = ["entries"]

_NODE = 1
_RPDO1, _RPDO2, _SDO_RX, _SDO_TX, _MASTER_HB = 0x200, 0x300, 0x600, 0x580, 0x77E

#: Objects the SDO requests address: statusword, controlword, mode, heartbeat, a PDO's COB-ID
#: and mapping, following error window, device name (segmented), one that does not exist.
_OBJECTS = ((0x6041, 0), (0x6040, 0), (0x6060, 0), (0x1017, 0), (0x1400, 1), (0x1600, 0),
            (0x1600, 1), (0x6065, 0), (0x1008, 0), (0x2FFF, 7))  # fmt: skip

Frame = tuple[int, bytes]


def _frame_strategy() -> st.SearchStrategy[list[Frame]]:
    obj = st.sampled_from(_OBJECTS)
    sdo_valid = st.one_of(
        st.builds(lambda o: bytes([0x40]) + struct.pack("<HB", *o) + bytes(4), obj),
        st.builds(lambda c, o, v: bytes([c]) + struct.pack("<HB", *o) + v,
                  st.sampled_from([0x23, 0x27, 0x2B, 0x2F, 0x21, 0x22, 0x20]), obj,
                  st.binary(min_size=4, max_size=4)),
        st.builds(lambda c, d: bytes([c]) + d, st.sampled_from([0x00, 0x10, 0x01, 0x11, 0x60,
                  0x70, 0x80, 0xA0, 0xC0, 0xE0]), st.binary(min_size=7, max_size=7)),
    )  # fmt: skip
    valid = st.one_of(
        st.tuples(st.just(_SDO_RX + _NODE), sdo_valid),
        st.tuples(st.just(_RPDO1 + _NODE), st.binary(min_size=8, max_size=8)),
        st.tuples(st.just(_RPDO2 + _NODE), st.builds(lambda w, m: struct.pack("<Hb", w, m),
                  st.sampled_from([0x00, 0x02, 0x06, 0x07, 0x0F, 0x80, 0x10F]),
                  st.integers(-128, 127))),
        st.tuples(st.just(0x000), st.builds(lambda c, n: bytes([c, n]),
                  st.sampled_from([0x01, 0x02, 0x80, 0x81, 0x82]), st.sampled_from([0, _NODE, 5]))),
        st.tuples(st.just(0x080), st.just(b"")),
        st.tuples(st.just(_MASTER_HB), st.just(b"\x05")),
    )  # fmt: skip


    known = [0x000, 0x080, _RPDO1 + _NODE, _RPDO2 + _NODE, _SDO_RX + _NODE, _MASTER_HB]
    ids = st.one_of(st.sampled_from(known), st.integers(0, 0x7FF))
    rand = st.tuples(ids, st.binary(max_size=8))
    return st.lists(st.one_of(mutated_frames(valid), rand), min_size=1, max_size=8)


@dataclass(slots=True)
class _DriveContext:
    rig: Rig
    now_s: float = 0.0


@contextlib.contextmanager
def _drive_context() -> Iterator[_DriveContext]:
    yield _DriveContext(load_rig("scale_model"))


def _enabled_drive(ctx: _DriveContext) -> DriveFirmware:
    """A booted drive in OPERATIONAL and OPERATION_ENABLED (CSP), as the master leaves it."""
    drive = DriveFirmware(_NODE, ctx.rig, "boom")
    drive.pending_frames(ctx.now_s)
    drive.on_frame(0x000, bytes([0x01, _NODE]), ctx.now_s)
    for word in (0x06, 0x07, 0x0F):
        drive.on_frame(_RPDO2 + _NODE, struct.pack("<Hb", word, 8), ctx.now_s)
    drive.on_frame(0x080, b"", ctx.now_s)
    enabled = drive.state is DeviceState.OPERATION_ENABLED
    if not enabled or drive.nmt_state is not NmtState.OPERATIONAL:
        raise PropertyViolation(f"the valid enable sequence left the drive in {drive.state.name}")
    return drive


def _check_frames_out(frames: Sequence[Any], what: str) -> None:
    for f in frames:
        if not (
            isinstance(f, tuple)
            and len(f) == 2
            and isinstance(f[0], int)
            and 0 <= f[0] <= 0x7FF
            and isinstance(f[1], bytes)
            and len(f[1]) <= 8
        ):
            raise PropertyViolation(f"{what} returned {f!r}, not an 11-bit frame of <= 8 bytes")


def _check_drive(ctx: _DriveContext, frames: list[Frame]) -> Verdict:
    ctx.now_s += 0.002
    drive = _enabled_drive(ctx)
    refused = 0
    for cob, data in frames:
        state, demand, nmt = drive.state, drive.position_demand_m, drive.nmt_state
        values = dict(drive._values)
        out = drive.on_frame(cob, data, ctx.now_s)
        _check_frames_out(out, f"on_frame(0x{cob:03X}, {data.hex()})")
        short_rpdo = (cob == _RPDO1 + _NODE and len(data) < 8) or (
            cob == _RPDO2 + _NODE and len(data) < 3
        )
        aborted = any(i == _SDO_TX + _NODE and d[:1] == b"\x80" for i, d in out)
        bad_nmt = cob == 0x000 and (len(data) < 2 or data[1] not in (0, _NODE))
        if short_rpdo or bad_nmt:
            refused += 1
            moved = drive.state is not state or drive.position_demand_m != demand
            if moved or drive.nmt_state is not nmt:
                raise PropertyViolation(
                    f"a refused frame 0x{cob:03X} {data.hex()} changed the drive "
                    f"({state.name} -> {drive.state.name}, demand {demand} -> "
                    f"{drive.position_demand_m})"
                )
        if aborted:
            refused += 1
            changed = sorted(k for k in values if drive._values.get(k) != values[k])
            if changed:
                raise PropertyViolation(
                    f"an SDO request answered with an abort changed {changed[:4]} "
                    f"({data.hex()})"
                )
        ctx.now_s += 0.0005
        _check_frames_out(drive.pending_frames(ctx.now_s), "pending_frames")
    return Verdict.REFUSED if refused else Verdict.ACCEPTED


# -- the VCU ------------------------------------------------------------------------------------


@dataclass(slots=True)
class _VcuContext:
    rig: Rig
    client: VcuClient
    command_id: int
    status_id: int
    now_s: float = 0.0


@contextlib.contextmanager
def _vcu_context() -> Iterator[_VcuContext]:
    rig = load_rig("scale_model")
    model = VcuModel.from_rig(rig)
    yield _VcuContext(rig, VcuClient.from_rig(rig), model.command_id, model.status_id)


def _vcu_strategy() -> st.SearchStrategy[list[Frame]]:
    rig = load_rig("scale_model")
    model = VcuModel.from_rig(rig)
    cmd = model.command_id
    ids = st.sampled_from([cmd, 0x080, model.status_id]) | st.integers(0, 0x7FF)
    frame = st.one_of(
        st.tuples(st.just(cmd), st.binary(min_size=8, max_size=8)),
        st.tuples(st.just(cmd), st.binary(max_size=7)),
        st.tuples(ids, st.binary(max_size=8)),
    )
    return st.lists(frame, min_size=1, max_size=6)


_VCU_COMMAND_STATE = (
    "state", "fault", "_travel_mode", "_travel_speed_cmd_m_s", "_travel_target_m",
    "_swing_target_rad", "_enable", "_fault_reset", "_last_command_s",
)  # fmt: skip


def _check_vcu(ctx: _VcuContext, frames: list[Frame]) -> Verdict:
    ctx.now_s += 0.002
    vcu = VcuModel.from_rig(ctx.rig)
    vcu.on_frame(ctx.command_id, bytes(8), ctx.now_s)  # enable off, everything at rest
    refused = 0
    for cob, data in frames:
        before = [getattr(vcu, a) for a in _VCU_COMMAND_STATE]
        out = vcu.on_frame(cob, data, ctx.now_s)
        _check_frames_out(out, f"VcuModel.on_frame(0x{cob:03X}, {data.hex()})")
        if cob == ctx.command_id and len(data) != 8:
            refused += 1
            after = [getattr(vcu, a) for a in _VCU_COMMAND_STATE]
            if after != before:
                raise PropertyViolation(f"a command of {len(data)} bytes changed the VCU")
        for i, d in out:
            status = ctx.client.decode_status(i, d)
            if status is None:
                raise PropertyViolation(f"the VCU's status {d.hex()} does not decode")
        vcu.step(0.002)
        ctx.now_s += 0.002
        _check_frames_out(vcu.pending_frames(ctx.now_s), "VcuModel.pending_frames")
        for x in (vcu.travel_position_m, vcu.swing_angle_rad, vcu.travel_speed_m_s):
            if not math.isfinite(x):
                raise PropertyViolation(f"the VCU's state is not finite after {data.hex()}")
    return Verdict.REFUSED if refused else Verdict.ACCEPTED


def entries() -> list[InputEntry]:
    """The firmware models' entry points (the ``excavator_rt.inputs`` entry point)."""
    return [
        InputEntry(
            "drive_frames",
            "CAN frames into the drive firmware model (SDO server, RPDOs, NMT, SYNC)",
            _frame_strategy,
            _drive_context,
            _check_drive,
        ),
        InputEntry(
            "vcu_frames",
            "CAN frames into the VCU model (commands, SYNC)",
            _vcu_strategy,
            _vcu_context,
            _check_vcu,
        ),
    ]
