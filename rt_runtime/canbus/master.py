"""The CiA 301/402 master of the arm's cylinder drives.

Role: boots and configures the drives (outside the loop), brings them to OPERATION_ENABLED, and
in every cycle sends the setpoints plus SYNC and collects the feedback. See the package docstring
(:mod:`rt_runtime.canbus`) for the API contract the executor and the HIL streamer use.

Who reads the bus: this object, and only on the caller's thread. python-can buses have one
receive queue, so a second reader (a ``can.Notifier``, canopen's network) would take frames the
loop needs. Every frame the master reads, wherever it reads it (SDO transfer, boot wait,
``read_feedback``), goes through one dispatcher, :meth:`CanMaster._dispatch`, which routes
TPDOs, EMCYs and heartbeats by COB-ID and ignores the rest. No thread, no clock: waits are
``bus.recv(timeout)`` calls bounded by the caller's ``now_fn`` or ``timeout_s``.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import TYPE_CHECKING

import can
import numpy as np
from canopen.objectdictionary import ObjectDictionary, import_od
from numpy.typing import NDArray

from rt_runtime.canbus.busload import BusLoad, bus_load_report, cia402_cycle_frames
from rt_runtime.canbus.cia402 import Command, DriveState, Target, decode_state, next_controlword
from rt_runtime.canbus.emcy import Emcy, parse_emcy
from rt_runtime.canbus.heartbeat import (
    HeartbeatConsumer,
    HeartbeatEvent,
    HeartbeatEventKind,
    HeartbeatProducer,
    parse_heartbeat,
)
from rt_runtime.canbus.nmt import NmtCommand, NmtState, nmt_message
from rt_runtime.canbus.pdo import (
    COB_EMCY,
    COB_HEARTBEAT,
    PDOS,
    RPDO1,
    RPDO2,
    TPDO1,
    TPDO2,
    check_pdo_mapping,
    od_default,
    pdo_message,
    sync_message,
)
from rt_runtime.canbus.sdo import SdoClient
from rt_runtime.errors import CommunicationError, ConfigurationError, DriveFault

if TYPE_CHECKING:
    from rt_runtime.rig.model import Rig

__all__ = [
    "DEFAULT_EDS",
    "MODE_CSP",
    "CanMaster",
    "CycleStatus",
    "DriveInfo",
    "Feedback",
    "MasterConfig",
    "SdoWrite",
    "WriteStatus",
    "configuration_writes",
    "interpolation_period",
]

#: The drives' EDS, shipped beside ``rt_runtime`` (source tree and site-packages alike).
DEFAULT_EDS = Path(__file__).resolve().parents[2] / "firmware_models" / "cia402_drive.eds"

#: Modes of operation (0x6060): cyclic synchronous position.
MODE_CSP = 8

_DEVICE_PROFILE_402 = 402
_CSP_SUPPORTED_BIT = 1 << 7
_COB_INVALID = 0x8000_0000

_AXES = ("boom", "stick", "bucket")

# Frame kinds for the dispatcher's COB-ID table.
_TPDO1, _TPDO2, _EMCY, _HEARTBEAT = 1, 2, 3, 4


_ENABLED = int(DriveState.OPERATION_ENABLED)
_FAULTED = (int(DriveState.FAULT), int(DriveState.FAULT_REACTION_ACTIVE))


class CycleStatus(IntEnum):
    """Outcome of one :meth:`CanMaster.read_feedback`, most severe condition found.

    Ordered by severity: a caller may compare (``status >= CycleStatus.HEARTBEAT_LOST``).
    """

    OK = 0
    #: A drive's TPDO1 answering the latest SYNC did not arrive in time; its values
    #: are the previous ones.
    STALE = 1
    #: An EMCY with a nonzero code arrived (see ``Feedback.emcys``) while every drive still
    #: reports a healthy state.
    EMCY = 2
    #: After :meth:`CanMaster.enable`, a drive left OPERATION_ENABLED without a fault (quick
    #: stop, disabled, or the master stopped it).
    NOT_ENABLED = 3
    #: A drive's heartbeat timed out, or a drive booted again (reset itself).
    HEARTBEAT_LOST = 4
    #: A drive reports FAULT or FAULT_REACTION_ACTIVE.
    DRIVE_FAULT = 5
    #: The bus refused a frame the master had to send this cycle.
    BUS_ERROR = 6


class WriteStatus(IntEnum):
    """Outcome of a per-cycle send."""

    OK = 0
    #: A setpoint does not fit an i32, or the arrays are too short: nothing was sent.
    OUT_OF_RANGE = 1
    #: The bus refused a frame (``can.CanError``); the frames before it went out.
    BUS_ERROR = 2


@dataclass(frozen=True, slots=True)
class MasterConfig:
    """Everything the master writes to the drives, in CAN units, derived from the rig.

    Attributes:
        axes: Axis names in array order (``boom``, ``stick``, ``bucket``).
        node_ids: Drive node id per axis.
        master_node_id: The master's heartbeat node id (0x7E by default).
        period_s: Cycle (SYNC) period.
        heartbeat_period_s: Heartbeat period of drives and master.
        heartbeat_timeout_s: Consumer timeout, both ways.
        following_error_window_um: 0x6065.
        following_error_timeout_ms: 0x6066.
        stroke_min_um: 0x607D sub 1 per axis.
        stroke_max_um: 0x607D sub 2 per axis.
        quick_stop_deceleration_um_s2: 0x6085.
        bitrate: Bus bitrate (bit/s).
    """

    axes: tuple[str, ...]
    node_ids: tuple[int, ...]
    master_node_id: int
    period_s: float
    heartbeat_period_s: float
    heartbeat_timeout_s: float
    following_error_window_um: int
    following_error_timeout_ms: int
    stroke_min_um: tuple[int, ...]
    stroke_max_um: tuple[int, ...]
    quick_stop_deceleration_um_s2: int
    bitrate: int

    @classmethod
    def from_rig(cls, rig: Rig, master_node_id: int, period_s: float) -> MasterConfig:
        """Derive the configuration from the rig's ``can``, ``drives`` and cylinder travel.

        Raises:
            ConfigurationError: A node id is missing or clashes with the master's, or a value
                does not fit its CAN object.
        """
        from rt_runtime.actuation import stroke_limits

        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ConfigurationError(f"cycle period {period_s} s must be finite and > 0")
        ids = dict(rig.can.node_ids)
        missing = [axis for axis in _AXES if axis not in ids]
        if missing:
            raise ConfigurationError(
                f"rig {rig.name}: can.node_ids has no drive for {missing}; the master needs "
                f"{list(_AXES)}"
            )
        node_ids = tuple(ids[axis] for axis in _AXES)
        if master_node_id in node_ids or not 1 <= master_node_id <= 127:
            raise ConfigurationError(
                f"master node id {master_node_id} must be in 1..127 and differ from the drives' "
                f"{node_ids}"
            )
        lo_m, hi_m = stroke_limits(rig)
        drives = rig.drives
        config = cls(
            axes=_AXES,
            node_ids=node_ids,
            master_node_id=master_node_id,
            period_s=period_s,
            heartbeat_period_s=drives.heartbeat_period_s,
            heartbeat_timeout_s=drives.heartbeat_timeout_s,
            following_error_window_um=round(drives.following_error_window_m * 1e6),
            following_error_timeout_ms=round(drives.following_error_timeout_s * 1e3),
            stroke_min_um=tuple(round(float(v) * 1e6) for v in lo_m),
            stroke_max_um=tuple(round(float(v) * 1e6) for v in hi_m),
            quick_stop_deceleration_um_s2=round(drives.quick_stop_deceleration_m_s2 * 1e6),
            bitrate=rig.can.bitrate,
        )
        hb_ms = round(config.heartbeat_period_s * 1e3)
        timeout_ms = round(config.heartbeat_timeout_s * 1e3)
        if not (0 < hb_ms <= 0xFFFF and 0 < timeout_ms <= 0xFFFF and hb_ms < timeout_ms):
            raise ConfigurationError(
                f"rig {rig.name}: heartbeat period {hb_ms} ms and timeout {timeout_ms} ms must be "
                "in 1..65535 ms with the period shorter than the timeout"
            )
        return config


@dataclass(frozen=True, slots=True)
class SdoWrite:
    """One SDO download of the boot configuration.

    Attributes:
        index: Object index.
        subindex: Sub-index.
        value: Value (encoded with the EDS data type).
        why: What it configures.
    """

    index: int
    subindex: int
    value: int
    why: str


@dataclass(frozen=True, slots=True)
class DriveInfo:
    """What a drive told about itself during boot.

    Attributes:
        axis: Axis name.
        node_id: Node id.
        device_type: 0x1000.
        device_name: 0x1008 (segmented upload).
        supported_modes: 0x6502.
    """

    axis: str
    node_id: int
    device_type: int
    device_name: str
    supported_modes: int


def interpolation_period(period_s: float) -> tuple[int, int]:
    """0x60C2 (value u8, index i8) with value * 10**index == period, index in -6..0.

    Raises:
        ConfigurationError: The period is not a whole number of microseconds expressible so.
    """
    period_us = round(period_s * 1e6)
    if period_us <= 0 or abs(period_us - period_s * 1e6) > 1e-6:
        raise ConfigurationError(f"period {period_s} s is not a whole number of microseconds")
    value, index = period_us, -6
    while value % 10 == 0 and index < 0:
        value //= 10
        index += 1
    if value > 255:
        raise ConfigurationError(
            f"period {period_s} s does not fit 0x60C2 (value <= 255 times a power of ten)"
        )
    return value, index


def configuration_writes(
    config: MasterConfig, od: ObjectDictionary, axis: int
) -> tuple[SdoWrite, ...]:
    """The SDO downloads that configure one drive, in order (pure; the byte-exact tests use it).

    PDOs are configured as CiA 301 requires: COB-ID invalid (bit 31), transmission type,
    mapping count 0, the mapping entries, the count, COB-ID valid again. COB-IDs and mapping
    values are the EDS's (checked against the codecs by :func:`check_pdo_mapping`).

    Args:
        config: The master's configuration.
        od: The drive's object dictionary.
        axis: Axis index into ``config.node_ids``.

    Raises:
        ConfigurationError: The EDS lacks an object or a value does not fit.
    """
    writes: list[SdoWrite] = []
    for spec in PDOS:
        cob = od_default(od, spec.comm_index, 1) & ~_COB_INVALID
        writes += [
            SdoWrite(spec.comm_index, 1, cob | _COB_INVALID, f"{spec.name} COB-ID invalid"),
            SdoWrite(spec.comm_index, 2, spec.transmission_type, f"{spec.name} transmission"),
            SdoWrite(spec.mapping_index, 0, 0, f"{spec.name} mapping cleared"),
        ]
        writes += [
            SdoWrite(spec.mapping_index, sub, value, f"{spec.name} object {sub}")
            for sub, value in enumerate(spec.mapping_values(), start=1)
        ]
        writes += [
            SdoWrite(spec.mapping_index, 0, len(spec.entries), f"{spec.name} mapping count"),
            SdoWrite(spec.comm_index, 1, cob, f"{spec.name} COB-ID valid"),
        ]
    ip_value, ip_index = interpolation_period(config.period_s)
    hb_ms = round(config.heartbeat_period_s * 1e3)
    timeout_ms = round(config.heartbeat_timeout_s * 1e3)
    writes += [
        SdoWrite(0x1006, 0, round(config.period_s * 1e6), "communication cycle period (us)"),
        SdoWrite(0x60C2, 1, ip_value, "interpolation period value"),
        SdoWrite(0x60C2, 2, ip_index, "interpolation period index"),
        SdoWrite(0x6065, 0, config.following_error_window_um, "following error window (um)"),
        SdoWrite(0x6066, 0, config.following_error_timeout_ms, "following error timeout (ms)"),
        SdoWrite(0x607D, 1, config.stroke_min_um[axis], "software position limit min (um)"),
        SdoWrite(0x607D, 2, config.stroke_max_um[axis], "software position limit max (um)"),
        SdoWrite(0x6085, 0, config.quick_stop_deceleration_um_s2, "quick stop deceleration"),
        SdoWrite(0x1017, 0, hb_ms, "producer heartbeat time (ms)"),
        SdoWrite(0x1016, 1, config.master_node_id << 16 | timeout_ms, "consume master heartbeat"),
        SdoWrite(0x6060, 0, MODE_CSP, "modes of operation: cyclic synchronous position"),
    ]
    return tuple(writes)


class Feedback:
    """The master's per-cycle feedback workspace (one object, reused every cycle).

    Arrays have shape ``(n,)`` in axis order (``MasterConfig.axes``). Values are the latest
    received; ``stale[i]`` says axis ``i`` did not answer the latest SYNC. The object and its
    arrays are overwritten by the next :meth:`CanMaster.read_feedback`: a consumer on another
    thread takes :meth:`copy`.

    Attributes:
        status: Most severe condition of this cycle.
        sync_count: SYNCs sent so far; TPDOs received after SYNC ``k`` answer ``k``.
        position_um: 0x6064 position actual (i32, um of stroke).
        velocity_um_s: 0x606C velocity actual (i32, um/s).
        statusword: 0x6041 (u16).
        mode_display: 0x6061 (i8).
        error_code: 0x603F (u16).
        state: Decoded :class:`DriveState` value, -1 for an undecodable statusword (i8).
        tpdo1_sync: SYNC count the latest TPDO1 answered (i64); ``tpdo2_sync`` the SYNC count
            at which the latest TPDO2 (a statusword change) arrived.
        stale: Missing TPDO1 for ``sync_count`` (TPDO2 is sent on change only).
        heartbeat_lost: Heartbeat timed out (and not heard since).
        rx_timestamp_s: Bus timestamp of the latest TPDO1 (the bus's clock, for round trips).
        emcys: EMCYs received during this call.
        heartbeat_events: Heartbeat events noticed during this call.
        reacted: The master sent its fault reaction (quick stop to every drive) this call.
    """

    __slots__ = (
        "emcys",
        "error_code",
        "heartbeat_events",
        "heartbeat_lost",
        "mode_display",
        "position_um",
        "reacted",
        "rx_timestamp_s",
        "stale",
        "state",
        "status",
        "statusword",
        "sync_count",
        "tpdo1_sync",
        "tpdo2_sync",
        "velocity_um_s",
    )

    def __init__(self, n: int) -> None:
        self.status = CycleStatus.OK
        self.sync_count = 0
        self.position_um: NDArray[np.int32] = np.zeros(n, np.int32)
        self.velocity_um_s: NDArray[np.int32] = np.zeros(n, np.int32)
        self.statusword: NDArray[np.uint16] = np.zeros(n, np.uint16)
        self.mode_display: NDArray[np.int8] = np.zeros(n, np.int8)
        self.error_code: NDArray[np.uint16] = np.zeros(n, np.uint16)
        self.state: NDArray[np.int8] = np.full(n, -1, np.int8)
        self.tpdo1_sync: NDArray[np.int64] = np.full(n, -1, np.int64)
        self.tpdo2_sync: NDArray[np.int64] = np.full(n, -1, np.int64)
        self.stale: NDArray[np.bool_] = np.ones(n, np.bool_)
        self.heartbeat_lost: NDArray[np.bool_] = np.zeros(n, np.bool_)
        self.rx_timestamp_s: NDArray[np.float64] = np.zeros(n, np.float64)
        self.emcys: list[Emcy] = []
        self.heartbeat_events: list[HeartbeatEvent] = []
        self.reacted = False

    def drive_state(self, axis: int) -> DriveState | None:
        """Decoded state of ``axis`` (None when undecodable)."""
        value = int(self.state[axis])
        return DriveState(value) if value >= 0 else None

    def copy(self) -> Feedback:
        """A deep copy, safe to hand to another thread."""
        out = Feedback(len(self.position_um))
        for name in self.__slots__:
            value = getattr(self, name)
            if isinstance(value, np.ndarray | list):
                value = value.copy()
            setattr(out, name, value)
        return out


class CanMaster:
    """CiA 301/402 master of the arm's three cylinder drives on a python-can bus.

    Args:
        bus: Any python-can bus (socketcan, kvaser, ``virtual``, a remote bridge). The master
            becomes its only reader; it does not own or shut it down. Optional capability: a
            bus with ``send_many(msgs)`` (send the messages in order, in one write; raise
            ``can.CanError`` as ``send`` does) gets each cycle's RPDO1s and SYNC in one call
            (the 127.0.0.1 bridge: one system call instead of four); any other bus gets one
            ``send`` a frame, which is what a socketcan socket takes anyway.
        rig: The rig (node ids, drive settings, cylinder travel, bitrate).
        eds_path: The drives' EDS; its PDO layout must match the codecs.
        master_node_id: Node id of the master's heartbeat (COB-ID 0x700 + id).
        period_s: Cycle period: 0x1006, 0x60C2, the pace of :meth:`enable`.
        sdo_timeout_s: Time allowed for each SDO transfer during boot.
        on_other_frame: Receives ``(message, now_s)`` for every frame the master reads that is
            not one of its drives' TPDOs, EMCYs or heartbeats (the VCU's status, say): the master
            is the bus's only reader, so other clients of the bus listen here. Called inside
            ``read_feedback``; it must be cheap and must not raise.
        react_to_faults: After :meth:`enable`, answer an EMCY with a nonzero code, a drive
            fault, a lost heartbeat or a drive leaving OPERATION_ENABLED by sending quick stop
            to every drive, once. Any EMCY counts: the drives send one only on a fault, and an
            unknown code is treated as one (a stop is the safe side).

    Raises:
        ConfigurationError: The EDS is missing, does not parse, or its PDO layout differs from
            the codecs; the rig lacks what the master needs.
    """

    def __init__(
        self,
        bus: can.BusABC,
        rig: Rig,
        eds_path: str | Path = DEFAULT_EDS,
        master_node_id: int = 0x7E,
        *,
        period_s: float = 0.002,
        sdo_timeout_s: float = 0.5,
        on_other_frame: Callable[[can.Message, float], None] | None = None,
        react_to_faults: bool = True,
    ) -> None:
        self.bus = bus
        self.rig = rig
        self.config = MasterConfig.from_rig(rig, master_node_id, period_s)
        self.sdo_timeout_s = sdo_timeout_s
        self.on_other_frame = on_other_frame
        self.react_to_faults = react_to_faults
        self.ods = tuple(self._load_od(Path(eds_path), node) for node in self.config.node_ids)
        n = len(self.config.node_ids)
        self.n = n
        self.feedback = Feedback(n)
        self.drive_info: tuple[DriveInfo, ...] = ()
        self._rpdo1 = [pdo_message(RPDO1, node) for node in self.config.node_ids]
        self._rpdo2 = [pdo_message(RPDO2, node) for node in self.config.node_ids]
        self._sync = sync_message()
        self._cycle_frames = (*self._rpdo1, self._sync)
        self._send_many: Callable[[Sequence[can.Message]], None] | None = getattr(
            bus, "send_many", None
        )
        self._producer = HeartbeatProducer(
            master_node_id, self.config.heartbeat_period_s, NmtState.OPERATIONAL
        )
        self._consumer = HeartbeatConsumer(self.config.node_ids, self.config.heartbeat_timeout_s)
        self._routes: dict[int, tuple[int, int]] = {}
        for axis, node in enumerate(self.config.node_ids):
            self._routes[TPDO1.cob_id(node)] = (_TPDO1, axis)
            self._routes[TPDO2.cob_id(node)] = (_TPDO2, axis)
            self._routes[COB_EMCY + node] = (_EMCY, axis)
            self._routes[COB_HEARTBEAT + node] = (_HEARTBEAT, axis)
        self._controlword = [0] * n
        self._pending = 0
        self._booted = False
        self._producing = False
        self._expect_enabled = False
        self._reacted = False
        self.last_emcy: list[Emcy | None] = [None] * n

    @staticmethod
    def _load_od(path: Path, node_id: int) -> ObjectDictionary:
        if not path.is_file():
            raise ConfigurationError(f"drive EDS {path} does not exist")
        try:
            od = import_od(str(path), node_id)
        except Exception as exc:  # canopen raises assorted parser errors
            raise ConfigurationError(f"drive EDS {path} does not parse: {exc}") from exc
        check_pdo_mapping(od, node_id)
        return od

    # ------------------------------------------------------------------ receiving

    def _dispatch(self, msg: can.Message, now_s: float) -> None:
        """Route one received frame; malformed drive frames are ignored, others passed on."""
        route = None
        if not (msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame):
            route = self._routes.get(msg.arbitration_id)
        if route is None:
            if self.on_other_frame is not None:
                self.on_other_frame(msg, now_s)
            return
        kind, axis = route
        fb = self.feedback
        data = msg.data
        if kind == _TPDO1:
            if len(data) != TPDO1.size:
                return
            fb.position_um[axis], fb.velocity_um_s[axis] = TPDO1.codec.unpack_from(data)
            fb.rx_timestamp_s[axis] = msg.timestamp
            if fb.tpdo1_sync[axis] != fb.sync_count:
                fb.tpdo1_sync[axis] = fb.sync_count
                self._pending -= 1
        elif kind == _TPDO2:
            if len(data) != TPDO2.size:
                return
            status, mode, error = TPDO2.codec.unpack_from(data)
            fb.statusword[axis], fb.mode_display[axis], fb.error_code[axis] = status, mode, error
            state = decode_state(status)
            fb.state[axis] = -1 if state is None else int(state)
            # TPDO2 is synchronous acyclic (sent only on change): never awaited per SYNC.
            fb.tpdo2_sync[axis] = fb.sync_count
        elif kind == _EMCY:
            emcy = parse_emcy(self.config.node_ids[axis], data, now_s)
            if emcy is not None:
                fb.emcys.append(emcy)
                self.last_emcy[axis] = emcy
        else:
            hb_state = parse_heartbeat(data)
            if hb_state is not None:
                event = self._consumer.on_heartbeat(self.config.node_ids[axis], hb_state, now_s)
                if event is not None:
                    fb.heartbeat_events.append(event)

    def _wait(
        self,
        done: Callable[[], bool],
        now_fn: Callable[[], float],
        timeout_s: float,
        what: str,
    ) -> None:
        """Read and dispatch frames until ``done()``; produce heartbeats meanwhile.

        Times out when ``now_fn`` passes the deadline or when empty waits add up to
        ``timeout_s`` (so a clock that does not move cannot hang it).

        Raises:
            CommunicationError: Timed out (``what`` names what was awaited).
        """
        start_s = now_fn()
        deadline_s = start_s + timeout_s
        idle_s = 0.0
        while not done():
            now_s = now_fn()
            if self._producing:
                self._send_heartbeat(now_s)
            remaining_s = min(deadline_s - now_s, timeout_s - idle_s)
            if remaining_s <= 0.0:
                raise CommunicationError(f"timed out after {timeout_s} s waiting for {what}")
            wait_s = remaining_s
            next_s = self._producer.next_due_s
            if self._producing and next_s is not None:
                # Wake up for the next heartbeat (at least a small step, so a clock that does
                # not move still ends the wait through the idle sum).
                wait_s = min(wait_s, max(next_s - now_s, 1e-4))
            msg = self.bus.recv(timeout=wait_s)
            if msg is None:
                idle_s += wait_s
            else:
                self._dispatch(msg, now_fn())

    def _drain(self, now_s: float) -> None:
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            self._dispatch(msg, now_s)

    # ------------------------------------------------------------------ sending

    def _tx(self, msg: can.Message) -> None:
        """Send one frame stamped with its send time (``time.time()``, the epoch clock python-can
        stamps received frames with). A bus that transmits at once ignores the stamp; a
        bridged bus (the 127.0.0.1 bridge into the HIL) carries it, so the far end can take the
        moment the frame entered the bus instead of when it got to read it.
        """
        msg.timestamp = time.time()
        self.bus.send(msg)

    def _send(self, msg: can.Message) -> None:
        try:
            self._tx(msg)
        except can.CanError as exc:
            raise CommunicationError(
                f"the bus refused frame 0x{msg.arbitration_id:03X}: {exc}"
            ) from exc

    def _send_heartbeat(self, now_s: float) -> None:
        if self._producer.due(now_s):
            self._send(self._producer.message)

    @property
    def sync_stamp_s(self) -> float:
        """The send stamp of the latest SYNC (the bus's clock, as the frames' timestamps)."""
        return float(self._sync.timestamp)

    def _send_sync(self) -> None:
        self._tx(self._sync)
        self._synced()

    def _synced(self) -> None:
        """A SYNC went out: the drives' TPDO1s that follow answer it."""
        self.feedback.sync_count += 1
        self._pending = self.n

    def _pack_rpdo2(self, axis: int, controlword: int) -> None:
        RPDO2.codec.pack_into(self._rpdo2[axis].data, 0, controlword, MODE_CSP)
        self._controlword[axis] = controlword

    # ------------------------------------------------------------------ boot

    def boot(self, now_fn: Callable[[], float], timeout_s: float) -> tuple[DriveInfo, ...]:
        """Reset, configure and start every drive (outside the loop).

        Sequence: NMT reset node per drive; wait for every boot-up message; per drive check
        0x1000 (CiA 402 device), 0x6502 (CSP supported), read 0x1008, then the SDO downloads of
        :func:`configuration_writes`; NMT start per drive; produce the master heartbeat and wait
        until every drive's heartbeat reports OPERATIONAL.

        Args:
            now_fn: Clock (s), monotonic or simulated.
            timeout_s: Time allowed for each wait (boot-up messages, operational heartbeats);
                every SDO transfer has ``sdo_timeout_s``.

        Returns:
            What each drive reported about itself (also kept in ``drive_info``).

        Raises:
            CommunicationError: A drive did not answer in time, or the bus refused a frame.
            SdoAbortedError: A drive refused a configuration value (index, sub, meaning).
            DriveFault: A drive is not a CiA 402 drive or lacks CSP.
        """
        cfg = self.config
        self._booted = False
        self._producing = False
        self._expect_enabled = False
        self._consumer.reset()
        self._drain(now_fn())
        booted: set[int] = set()
        self.feedback.heartbeat_events.clear()
        for node in cfg.node_ids:
            self._send(nmt_message(NmtCommand.RESET_NODE, node))

        def all_booted() -> bool:
            events = self.feedback.heartbeat_events
            booted.update(e.node_id for e in events if e.kind is HeartbeatEventKind.BOOT_UP)
            events.clear()
            return len(booted) == len(cfg.node_ids)

        try:
            self._wait(all_booted, now_fn, timeout_s, "boot-up messages")
        except CommunicationError as exc:
            silent = [n for n in cfg.node_ids if n not in booted]
            raise CommunicationError(
                f"boot: no boot-up message from nodes {silent} within {timeout_s} s of the NMT "
                "reset"
            ) from exc
        infos = []
        for axis, node in enumerate(cfg.node_ids):
            od = self.ods[axis]
            sdo = SdoClient(self.bus, node, on_other=self._dispatch)
            t = self.sdo_timeout_s
            device_type = int(sdo.read(od, 0x1000, 0, now_fn, t))
            if device_type & 0xFFFF != _DEVICE_PROFILE_402:
                raise DriveFault(
                    f"{cfg.axes[axis]} drive (node {node}) reports device type 0x{device_type:08X}"
                    f", not a CiA 402 drive (low word 0x0192)"
                )
            modes = int(sdo.read(od, 0x6502, 0, now_fn, t))
            if not modes & _CSP_SUPPORTED_BIT:
                raise DriveFault(
                    f"{cfg.axes[axis]} drive (node {node}) does not support cyclic synchronous "
                    f"position (0x6502 = 0x{modes:08X}, bit 7 clear)"
                )
            name = str(sdo.read(od, 0x1008, 0, now_fn, t))
            for write in configuration_writes(cfg, od, axis):
                sdo.write(od, write.index, write.subindex, write.value, now_fn, t)
            infos.append(DriveInfo(cfg.axes[axis], node, device_type, name, modes))
        for node in cfg.node_ids:
            self._send(nmt_message(NmtCommand.START, node))
        self._producing = True

        def all_operational() -> bool:
            self.feedback.heartbeat_events.clear()
            return all(self._consumer.state(n) is NmtState.OPERATIONAL for n in cfg.node_ids)

        try:
            self._wait(all_operational, now_fn, timeout_s, "OPERATIONAL heartbeats")
        except CommunicationError as exc:
            late = {
                n: self._consumer.state(n)
                for n in cfg.node_ids
                if self._consumer.state(n) is not NmtState.OPERATIONAL
            }
            raise CommunicationError(
                f"boot: after NMT start, nodes {late} (node: last heartbeat state) did not "
                f"report OPERATIONAL within {timeout_s} s"
            ) from exc
        self._consumer.start(now_fn())
        self.drive_info = tuple(infos)
        self._booted = True
        return self.drive_info

    # ------------------------------------------------------------------ enable

    def enable(self, now_fn: Callable[[], float], timeout_s: float) -> None:
        """Bring every drive to OPERATION_ENABLED (outside the loop).

        One step per SYNC period (paced on ``now_fn``): RPDO1 holding each drive at its actual
        position with zero velocity offset (so enabling does not jump), RPDO2 with the next
        controlword of :func:`~rt_runtime.canbus.cia402.next_controlword` to every drive not yet
        there, then SYNC; the TPDOs answering it decide the next step. The first step is a SYNC
        alone, to learn positions and states. A drive in FAULT gets fault-reset edges. Clears the
        master's fault latch.

        Args:
            now_fn: Clock (s), monotonic or simulated.
            timeout_s: Time allowed for the whole sequence.

        Raises:
            CommunicationError: Not booted, no TPDO answer in time, or the bus refused a frame.
            DriveFault: A drive is (still) in FAULT when time runs out.
        """
        if not self._booted:
            raise CommunicationError("enable() needs a successful boot() first")
        self._expect_enabled = False
        self._reacted = False
        fb = self.feedback
        start_s = now_fn()
        deadline_s = start_s + timeout_s
        first = True
        while True:
            now_s = now_fn()
            self._send_heartbeat(now_s)
            if not first:
                if (fb.state == DriveState.OPERATION_ENABLED).all():
                    self._expect_enabled = True
                    return
                if now_s >= deadline_s:
                    self._enable_failed(timeout_s)
                for axis in range(self.n):
                    RPDO1.codec.pack_into(self._rpdo1[axis].data, 0, int(fb.position_um[axis]), 0)
                    self._send(self._rpdo1[axis])
                for axis in range(self.n):
                    if fb.state[axis] != DriveState.OPERATION_ENABLED:
                        word = next_controlword(
                            int(fb.statusword[axis]),
                            Target.OPERATION_ENABLED,
                            self._controlword[axis],
                        )
                        self._pack_rpdo2(axis, word)
                        self._send(self._rpdo2[axis])
            first = False
            sync_s = now_fn()
            try:
                self._send_sync()
            except can.CanError as exc:
                raise CommunicationError(f"the bus refused SYNC: {exc}") from exc
            fb.emcys.clear()
            fb.heartbeat_events.clear()
            try:
                self._wait(
                    lambda: self._pending <= 0,
                    now_fn,
                    max(deadline_s - now_fn(), self.config.period_s),
                    "TPDOs",
                )
            except CommunicationError as exc:
                silent = [
                    f"{self.config.axes[a]} (node {self.config.node_ids[a]})"
                    for a in range(self.n)
                    if fb.tpdo1_sync[a] != fb.sync_count
                ]
                raise CommunicationError(
                    f"enable: no TPDO1 answer to SYNC {fb.sync_count} from {silent}"
                ) from exc
            self._wait_until(sync_s + self.config.period_s, now_fn)

    def _wait_until(self, t_s: float, now_fn: Callable[[], float]) -> None:
        """Dispatch frames until ``now_fn()`` reaches ``t_s`` (or one empty wait covers it)."""
        while (remaining_s := t_s - now_fn()) > 0.0:
            msg = self.bus.recv(timeout=remaining_s)
            if msg is None:
                return
            self._dispatch(msg, now_fn())

    def _enable_failed(self, timeout_s: float) -> None:
        fb = self.feedback
        lines = []
        faulted = False
        for axis in range(self.n):
            state = fb.drive_state(axis)
            faulted |= state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE)
            emcy = self.last_emcy[axis]
            last = f", last EMCY {emcy.description}" if emcy is not None else ""
            lines.append(
                f"{self.config.axes[axis]} (node {self.config.node_ids[axis]}): "
                f"{state.name if state is not None else 'undecodable'} "
                f"(statusword 0x{int(fb.statusword[axis]):04X}{last})"
            )
        text = f"drives not OPERATION_ENABLED after {timeout_s} s: " + "; ".join(lines)
        raise DriveFault(text) if faulted else CommunicationError(text)

    # ------------------------------------------------------------------ cycle

    def write_setpoints(
        self,
        stroke_um: Sequence[int] | NDArray[np.int32],
        velocity_um_s: Sequence[int] | NDArray[np.int32],
    ) -> WriteStatus:
        """Send RPDO1 (target stroke, velocity offset) to every drive, then SYNC.

        The frames are stamped with their send time (``time.time()``). On a bus with
        ``send_many`` (see :class:`CanMaster`) they go in one call, one stamp for all four;
        on any other bus one ``send`` each.

        Safe inside the loop: packs into the master's preallocated messages (no allocation but
        what the bus's send does) and never raises for bus errors.

        Args:
            stroke_um: Target stroke per axis, integer micrometres, shape ``(n,)``.
            velocity_um_s: Velocity offset (feed-forward) per axis, micrometres per second.

        Returns:
            ``OK``; ``OUT_OF_RANGE`` (nothing sent) when a value does not fit an i32 or an array
            is shorter than ``n``; ``BUS_ERROR`` when the bus refused a frame (the SYNC is then
            not counted as sent).
        """
        try:
            for axis in range(self.n):
                RPDO1.codec.pack_into(
                    self._rpdo1[axis].data, 0, int(stroke_um[axis]), int(velocity_um_s[axis])
                )
        except (struct.error, IndexError, OverflowError, ValueError):
            return WriteStatus.OUT_OF_RANGE
        try:
            if self._send_many is not None:
                stamp = time.time()
                for msg in self._cycle_frames:
                    msg.timestamp = stamp
                self._send_many(self._cycle_frames)
                self._synced()
            else:
                for msg in self._rpdo1:
                    self._tx(msg)
                self._send_sync()
        except can.CanError:
            return WriteStatus.BUS_ERROR
        return WriteStatus.OK

    def last_target_um(self) -> NDArray[np.int32]:
        """The stroke target (um) of the last RPDO1 sent to each drive, ``(n,)``.

        Read back from the master's own preallocated messages, so a caller holding the axes
        continues from exactly what was commanded last (enable's hold, an executor's last
        setpoint), never from a measured position. Outside the loop (allocates the result).
        """
        return np.array(
            [RPDO1.codec.unpack_from(msg.data)[0] for msg in self._rpdo1], dtype=np.int32
        )

    def read_feedback(self, now_s: float, timeout_s: float) -> Feedback:
        """Collect the drives' answers to the latest SYNC and everything else received.

        Waits until every drive's TPDO1 for the latest SYNC is in, each wait at most
        ``timeout_s`` (so the call returns at the latest ``timeout_s`` after the last frame that
        came); then takes whatever else is queued without waiting. Checks heartbeat timeouts at
        ``now_s``. When enabled and a drive sends an EMCY, faults, loses its heartbeat or leaves
        OPERATION_ENABLED, and ``react_to_faults`` is set, sends quick stop to every drive once
        (``Feedback.reacted``).

        Safe inside the loop: returns the master's reused :class:`Feedback` (valid until the next
        call), allocates only small temporaries and the EMCY and heartbeat event objects, never
        raises for bus conditions.

        Args:
            now_s: Time of this cycle (s), for heartbeat supervision and event stamps.
            timeout_s: Longest wait for one missing frame (0 = take only what is queued).
        """
        fb = self.feedback
        fb.emcys.clear()
        fb.heartbeat_events.clear()
        fb.reacted = False
        bus_error = False
        try:
            while self._pending > 0:
                msg = self.bus.recv(timeout=timeout_s)
                if msg is None:
                    break
                self._dispatch(msg, now_s)
            while (msg := self.bus.recv(timeout=0.0)) is not None:
                self._dispatch(msg, now_s)
        except can.CanError:
            bus_error = True
        consumer = self._consumer
        consumer.check(now_s, fb.heartbeat_events)
        np.not_equal(fb.tpdo1_sync, fb.sync_count, out=fb.stale)
        # Per-axis checks in plain Python: a handful of axes, cheaper than numpy's per call.
        lost_any = False
        for axis, node in enumerate(self.config.node_ids):
            lost = consumer.is_lost(node)
            fb.heartbeat_lost[axis] = lost
            lost_any = lost_any or lost
        rebooted = any(e.kind is HeartbeatEventKind.BOOT_UP for e in fb.heartbeat_events)
        states = fb.state.tolist()
        status = CycleStatus.OK
        if fb.stale.any():
            status = CycleStatus.STALE
        if any(not e.is_reset for e in fb.emcys):
            status = CycleStatus.EMCY
        if self._expect_enabled and any(x != _ENABLED for x in states):
            status = CycleStatus.NOT_ENABLED
        if lost_any or rebooted:
            status = CycleStatus.HEARTBEAT_LOST
        if any(x in _FAULTED for x in states):
            status = CycleStatus.DRIVE_FAULT
        if (
            self.react_to_faults
            and self._expect_enabled
            and not self._reacted
            and status >= CycleStatus.EMCY
        ):
            self._reacted = True
            fb.reacted = True
            bus_error |= self.quick_stop() is not WriteStatus.OK
        if bus_error:
            status = CycleStatus.BUS_ERROR
        fb.status = status
        return fb

    def heartbeat(self, now_s: float) -> WriteStatus:
        """Send the master's heartbeat when due (call every cycle; loop safe)."""
        try:
            if self._producer.due(now_s):
                self._tx(self._producer.message)
        except can.CanError:
            return WriteStatus.BUS_ERROR
        return WriteStatus.OK

    def _send_controlword(self, controlword: int) -> WriteStatus:
        status = WriteStatus.OK
        for axis in range(self.n):
            self._pack_rpdo2(axis, controlword)
            try:
                self._tx(self._rpdo2[axis])
            except can.CanError:
                status = WriteStatus.BUS_ERROR
        return status

    def quick_stop(self) -> WriteStatus:
        """Quick stop (controlword 0x0002) to every drive: each decelerates with 0x6085 and,
        with quick stop option code 2, ends in SWITCH_ON_DISABLED. Loop safe; tries every drive
        even when one send fails."""
        self._expect_enabled = False
        return self._send_controlword(int(Command.QUICK_STOP))

    def disable(self) -> WriteStatus:
        """Disable voltage (controlword 0x0000) to every drive: power stages off at once (the
        axes coast or brake); for axes at rest. Loop safe."""
        self._expect_enabled = False
        return self._send_controlword(int(Command.DISABLE_VOLTAGE))

    def bus_load(self, period_s: float | None = None) -> BusLoad:
        """Load of the cyclic traffic (RPDO1, SYNC, TPDO1, heartbeats) at ``period_s``
        (default: the configured period) on the rig's bitrate."""
        period = self.config.period_s if period_s is None else period_s
        frames = cia402_cycle_frames(self.n, period, self.config.heartbeat_period_s)
        return bus_load_report(frames, period, self.config.bitrate)
