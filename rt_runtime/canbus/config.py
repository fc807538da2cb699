"""What the master writes to the drives at boot, derived from the rig (outside the loop).

Role: :class:`MasterConfig` (the rig's CAN and drive settings in CAN units), the SDO downloads
that configure one drive (:func:`configuration_writes`, pure: the byte-exact tests use it), what a
drive tells about itself at boot (:class:`DriveInfo`), and the drives' EDS
(:data:`DEFAULT_EDS`, :func:`load_od`, checked against the PDO codecs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from canopen.objectdictionary import ObjectDictionary, import_od

from rt_runtime.canbus.pdo import PDOS, check_pdo_mapping, od_default
from rt_runtime.errors import ConfigurationError

if TYPE_CHECKING:
    from rt_runtime.rig.model import Rig

__all__ = [
    "AXES",
    "DEFAULT_EDS",
    "MODE_CSP",
    "DriveInfo",
    "MasterConfig",
    "SdoWrite",
    "configuration_writes",
    "interpolation_period",
    "load_od",
]

#: The drives' EDS, shipped beside ``rt_runtime`` (source tree and site-packages alike).
DEFAULT_EDS = Path(__file__).resolve().parents[2] / "firmware_models" / "cia402_drive.eds"

#: Modes of operation (0x6060): cyclic synchronous position.
MODE_CSP = 8

#: The arm's axes in array order (a rig with swing appends ``swing``:
#: :func:`rt_runtime.axes.names`).
AXES = ("boom", "stick", "bucket")

_COB_INVALID = 0x8000_0000


@dataclass(frozen=True, slots=True)
class MasterConfig:
    """Everything the master writes to the drives, in CAN units, derived from the rig.

    Attributes:
        axes: Axis names in array order (``boom``, ``stick``, ``bucket``, then ``swing`` on a
            rig with swing: :mod:`rt_runtime.axes`). Positions are millionths of the axis's SI
            unit: micrometres of stroke, microradians of swing.
        node_ids: Drive node id per axis.
        master_node_id: The master's heartbeat node id (0x7E by default).
        period_s: Cycle (SYNC) period.
        heartbeat_period_s: Heartbeat period of drives and master.
        heartbeat_timeout_s: Consumer timeout, both ways.
        following_error_window_um: 0x6065 per axis (the swing's:
            :data:`rt_runtime.axes.SWING_FOLLOWING_ERROR_WINDOW_RAD` in urad).
        following_error_timeout_ms: 0x6066.
        stroke_min_um: 0x607D sub 1 per axis.
        stroke_max_um: 0x607D sub 2 per axis.
        quick_stop_deceleration_um_s2: 0x6085 per axis (the swing's: its acceleration limit in
            urad/s^2).
        bitrate: Bus bitrate (bit/s).
        valve_overlap_compensation: 0x2100 (0.01 % of full opening) of the valve drives, one
            per cylinder in axis order; empty on a rig whose cylinders are electric (nothing is
            written then).
    """

    axes: tuple[str, ...]
    node_ids: tuple[int, ...]
    master_node_id: int
    period_s: float
    heartbeat_period_s: float
    heartbeat_timeout_s: float
    following_error_window_um: tuple[int, ...]
    following_error_timeout_ms: int
    stroke_min_um: tuple[int, ...]
    stroke_max_um: tuple[int, ...]
    quick_stop_deceleration_um_s2: tuple[int, ...]
    bitrate: int
    valve_overlap_compensation: tuple[int, ...] = ()

    @classmethod
    def from_rig(cls, rig: Rig, master_node_id: int, period_s: float) -> MasterConfig:
        """Derive the configuration from the rig's ``can``, ``drives``, cylinder travel and, on
        a rig with swing, its swing joint (node ``can.node_ids.swing``).

        Raises:
            ConfigurationError: A node id is missing or clashes with the master's, or a value
                does not fit its CAN object.
        """
        from rt_runtime import axes as rig_axes
        from rt_runtime.axes import SWING_FOLLOWING_ERROR_WINDOW_RAD

        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ConfigurationError(f"cycle period {period_s} s must be finite and > 0")
        ids = dict(rig.can.node_ids)
        names = rig_axes.names(rig)
        missing = [axis for axis in names if axis not in ids]
        if missing:
            raise ConfigurationError(
                f"rig {rig.name}: can.node_ids has no drive for {missing}; the master needs "
                f"{list(names)}"
            )
        node_ids = tuple(ids[axis] for axis in names)
        if master_node_id in node_ids or not 1 <= master_node_id <= 127:
            raise ConfigurationError(
                f"master node id {master_node_id} must be in 1..127 and differ from the drives' "
                f"{node_ids}"
            )
        lo_m, hi_m = rig_axes.actuator_limits(rig)
        drives = rig.drives
        window = [drives.following_error_window_m] * 3
        quick_stop = [drives.quick_stop_deceleration_m_s2] * 3
        if rig.swing is not None:
            window.append(SWING_FOLLOWING_ERROR_WINDOW_RAD)
            quick_stop.append(rig.swing.joint.acceleration_max_rad_s2)
        config = cls(
            axes=names,
            node_ids=node_ids,
            master_node_id=master_node_id,
            period_s=period_s,
            heartbeat_period_s=drives.heartbeat_period_s,
            heartbeat_timeout_s=drives.heartbeat_timeout_s,
            following_error_window_um=tuple(round(w * 1e6) for w in window),
            following_error_timeout_ms=round(drives.following_error_timeout_s * 1e3),
            stroke_min_um=tuple(round(float(v) * 1e6) for v in lo_m),
            stroke_max_um=tuple(round(float(v) * 1e6) for v in hi_m),
            quick_stop_deceleration_um_s2=tuple(round(d * 1e6) for d in quick_stop),
            bitrate=rig.can.bitrate,
            valve_overlap_compensation=(
                (round(drives.valve_overlap_compensation * 1e4),) * 3
                if rig.actuators.hydraulic is not None
                else ()
            ),
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
        SdoWrite(
            0x6065, 0, config.following_error_window_um[axis], "following error window (um)"
        ),
        SdoWrite(0x6066, 0, config.following_error_timeout_ms, "following error timeout (ms)"),
        SdoWrite(0x607D, 1, config.stroke_min_um[axis], "software position limit min (um)"),
        SdoWrite(0x607D, 2, config.stroke_max_um[axis], "software position limit max (um)"),
        SdoWrite(
            0x6085, 0, config.quick_stop_deceleration_um_s2[axis], "quick stop deceleration"
        ),
        SdoWrite(0x1017, 0, hb_ms, "producer heartbeat time (ms)"),
        SdoWrite(0x1016, 1, config.master_node_id << 16 | timeout_ms, "consume master heartbeat"),
    ]
    if axis < len(config.valve_overlap_compensation):
        compensation = config.valve_overlap_compensation[axis]
        writes.append(SdoWrite(0x2100, 0, compensation, "valve overlap compensation (0.01 %)"))
    writes.append(SdoWrite(0x6060, 0, MODE_CSP, "modes of operation: cyclic synchronous position"))
    return tuple(writes)


def load_od(path: Path, node_id: int) -> ObjectDictionary:
    """The drive's object dictionary from its EDS, its PDO layout checked against the codecs.

    Raises:
        ConfigurationError: The EDS is missing, does not parse, or its PDO layout differs.
    """
    if not path.is_file():
        raise ConfigurationError(f"drive EDS {path} does not exist")
    try:
        od = import_od(str(path), node_id)
    except Exception as exc:  # canopen raises assorted parser errors
        raise ConfigurationError(f"drive EDS {path} does not parse: {exc}") from exc
    check_pdo_mapping(od, node_id)
    return od
