"""The HIL's core: plant, terrain, the drive nodes and the VCU behind the CAN frames.

Role: emulate the rig behind the CAN bus (DESIGN.md "Loop, HIL and time"). :class:`HilCore` is the
transport-free part: it takes each frame the bus carries with its time, answers it through the
drive nodes (:mod:`hil_sim.drives`) and the VCU model, advances the plant in servo sub-steps, and
records the truth (true strokes, joint angles, tip, machine travel) at every SYNC. A rig with
swing has a fourth drive node (node ``can.node_ids.swing``, axis 3) on the swing plant
(:class:`~hil_sim.swing.SwingPlant`), composed beside the planar arm plant; its truth adds the
swing angle and rate. The truth is
bounded: the last ``truth_rows`` SYNCs are kept (:data:`TRUTH_ROWS` by default, a ring that
overwrites the oldest row), so a HIL that runs for hours keeps a flat memory. Two transports
drive it:

* :class:`~hil_sim.harness.lockstep.LockstepHil`: one process, one simulated clock, the
  master's bus an end of an in-process channel (it joins runtime and HIL: in the harness);
* :mod:`hil_sim.harness.realtime`: the same core in its own process at wall-clock speed,
  bridged over 127.0.0.1.

Frames of the whole bus can be written as a BLF or ASC trace with python-can's loggers
(``trace_path``); timestamps are the HIL's clock (simulated seconds in lockstep).

Frames: the world frame of the terrain is the work site (the arm frame of the machine's first
position); the machine's travel (the VCU's travel position) shifts the arm frame by
``machine_x_m``, so the soil law sees the tip at ``x_arm + machine_x_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Any

import can
import numpy as np
from numpy.typing import NDArray

from firmware_models.drive import DriveFirmware, Frame
from firmware_models.errors import FirmwareConfigurationError
from firmware_models.vcu import VcuModel
from hil_sim.drives import DriveNode, into_rock
from hil_sim.plant import ArmPlant, TipLoad
from hil_sim.swing import SwingPlant, swing_drive_rig
from hil_sim.terrain import Terrain
from rt_runtime import kinematics
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig

__all__ = [
    "GLITCH_MM",
    "GLITCH_SWING_MRAD",
    "TRUTH_ROWS",
    "FaultKind",
    "HilCore",
    "Truth",
    "TruthRing",
    "open_trace",
]

FloatArray = NDArray[np.float64]

COB_SYNC = 0x080
COB_NMT = 0x000
#: SDO requests to the drives (0x600 + node id): what may write their 0x2100.
COB_SDO_RX = 0x600
#: The master's heartbeat COB-ID (node 0x7E), which drives consume.
COB_MASTER_HEARTBEAT = 0x700 + 0x7E
_AXES = ("boom", "stick", "bucket")
#: The cylinder forces passed to drives that do not read them.
_NO_LOAD = (0.0, 0.0, 0.0)
#: Truth rows a :class:`HilCore` keeps by default: the last 2**20 SYNCs (35 min at 500 Hz,
#: 17 min at 1 kHz; 80 MB when full). Older rows are overwritten.
TRUTH_ROWS = 1 << 20
#: Rows a growing :class:`TruthRing` starts with.
_TRUTH_FIRST_ROWS = 4096


class FaultKind(IntEnum):
    """Faults a HIL run injects, by where they act.

    Drive faults act in one drive node (:mod:`hil_sim.drives`, :meth:`HilCore.inject`); bus
    faults on the frames between the master and one node or the whole bus (the transport's
    :class:`~hil_sim.busfaults.BusFaults`); host faults on the rig PC's side (the harness
    applies them: the loop, the planner process, the job store).
    """

    #: The axis jams (effort 0.0, braked): the drive's own following-error check trips (0x8611).
    FOLLOWING_ERROR = 1
    #: The drive stops receiving the master's heartbeat: its consumer trips (EMCY 0x8130).
    HEARTBEAT_LOSS = 2
    #: The drive stops transmitting: the master's heartbeat consumer trips.
    NODE_SILENT = 3
    #: The drive's own over-current (EMCY 0x2310): power stage off at once (reaction 0).
    OVERCURRENT = 4
    #: The drive's own over-temperature (EMCY 0x4310): quick-stop ramp (reaction 2).
    OVERTEMPERATURE = 5
    #: The drive's DC link under-voltage (EMCY 0x3220): power stage off at once (reaction 0).
    UNDERVOLTAGE = 6
    #: The drive reboots: its boot-up frame arrives unannounced, PDOs stop (PRE-OPERATIONAL).
    DRIVE_REBOOT = 7
    #: The position the drive reports jumps by the parameter (mm) and stays off.
    ENCODER_GLITCH = 8
    #: The axis meets a rock: the soil's force past its cylinder's, it stalls moving into it.
    ROCK = 9
    #: Frames to and from the target lost at a rate (the parameter, 0..1).
    FRAME_LOSS = 10
    #: The target's next frame (either way) delivered late by the parameter (ms).
    FRAME_DELAY = 11
    #: The target's next two frames (either way) delivered in swapped order.
    FRAME_REORDER = 12
    #: The target's next frame to the master one byte short (a wrong DLC).
    FRAME_TRUNCATED = 13
    #: The target's next frame to the master with random bytes (its length kept).
    FRAME_GARBAGE = 14
    #: The target's next frame (either way) delivered twice.
    FRAME_DUPLICATE = 15
    #: Error frames on the bus (the parameter: how many, one per period).
    ERROR_FRAMES = 16
    #: The master's adapter goes bus-off: every send raises until it is reopened.
    BUS_OFF = 17
    #: The bus unplugged for the parameter (s): nothing passes either way, then it is back.
    BUS_UNPLUGGED = 18
    #: The master's loop does not run for the parameter (ms): a VM pause.
    LOOP_STALL = 19
    #: The job's planner process is killed (SIGKILL).
    PLANNER_KILLED = 20
    #: The job store cannot be written (its disk full or read-only, its directory gone): the
    #: campaign puts a file where the state directory was, so every write fails.
    STORE_UNWRITABLE = 21
    #: A model file the planner was verified from changes on disk (a model deployed under a
    #: running job, a failing disk): the campaign overwrites the job's model with other bytes.
    MODEL_CHANGED = 22
    #: The daemon crashes mid-job (SIGKILL, a watchdog's SIGABRT): its loop stops sending and
    #: nothing it would do on a stop happens; the drives stop on their own, systemd restarts it.
    DAEMON_CRASH = 23

    @property
    def label(self) -> str:
        """The kind's name on the command line: ``frame_loss``."""
        return self.name.lower()

    @property
    def targets(self) -> tuple[str, ...]:
        """What the kind acts on on every rig: the arm's axis names (a drive node, or the frames
        to and from it), ``bus`` (every frame), ``host`` (the rig PC)."""
        layer = self.layer
        if layer == "drive":
            return _AXES
        if layer == "host":
            return ("host",)
        if self in (FaultKind.ERROR_FRAMES, FaultKind.BUS_OFF, FaultKind.BUS_UNPLUGGED):
            return ("bus",)
        return (*_AXES, "bus")

    @property
    def swing_targets(self) -> tuple[str, ...]:
        """:attr:`targets` on a rig with swing: ``swing`` as well where an axis is one."""
        targets = self.targets
        return (*_AXES, "swing", *targets[3:]) if targets[:3] == _AXES else targets

    @property
    def on_rig_pc(self) -> bool:
        """The kind acts on the rig PC's side: the host's kinds and the master adapter's
        bus-off. A HIL in its own process cannot make them (the real-time HIL refuses them)."""
        return self.layer == "host" or self is FaultKind.BUS_OFF

    @property
    def layer(self) -> str:
        """``drive``, ``bus`` or ``host``."""
        if self.value <= FaultKind.ROCK:
            return "drive"
        if self.value <= FaultKind.BUS_UNPLUGGED:
            return "bus"
        return "host"


#: Drive faults that are the drive's own EMCY: code and fault reaction (0 power stage off at
#: once, 2 quick-stop ramp).
_DRIVE_EMCY = {
    FaultKind.OVERCURRENT: (0x2310, 0),
    FaultKind.OVERTEMPERATURE: (0x4310, 2),
    FaultKind.UNDERVOLTAGE: (0x3220, 0),
}
#: An encoder glitch's default jump (mm).
GLITCH_MM = 8.0
#: An encoder glitch's default jump on the swing (mrad, a thousandth of the swing drive's bus
#: unit as a mm is the cylinders'): 5.7 deg. The master refuses a report that jumped further
#: than twice the velocity limit allows since the last good one, a bound that grows with every
#: refused cycle: at 2 ms and the field excavator's 70 deg/s it passes 50 mrad after the 10
#: stale cycles that stop a job, so a smaller jump is taken as real before then.
GLITCH_SWING_MRAD = 100.0


class _ShiftedLoad:
    """A tip load in the work-site frame seen from the arm frame of a travelling machine."""

    __slots__ = ("inner", "offset_m")

    def __init__(self, inner: TipLoad) -> None:
        self.inner = inner
        self.offset_m = 0.0

    def tip_load(
        self, x_m: float, y_m: float, vx_m_s: float, vy_m_s: float
    ) -> tuple[float, float, float, float, float, float]:
        return self.inner.tip_load(x_m + self.offset_m, y_m, vx_m_s, vy_m_s)


@dataclass(frozen=True, slots=True)
class Truth:
    """The plant's state at every SYNC the HIL received (before the period's motion).

    Attributes:
        sync_index: 1-based count of the SYNC (the master's ``Feedback.sync_count``), ``(n,)``.
        t_s: HIL clock at the SYNC, ``(n,)``.
        stroke_m: True cylinder strokes, ``(n, 3)``.
        q_rad: True joint angles, ``(n, 3)``.
        tip_xy_m: True tip position in the work-site frame, ``(n, 2)``.
        machine_x_m: Machine travel, ``(n,)``.
        power_w: Drive power (non-regenerating) in the period before the SYNC, ``(n,)``.
        energy_j: Energy drawn so far (plant's Yao W_E reading).
        swing_rad: True swing angle ``(n,)`` on a rig with swing, else None.
        swing_rate_rad_s: True swing rate ``(n,)`` on a rig with swing, else None.
    """

    sync_index: NDArray[np.int64]
    t_s: FloatArray
    stroke_m: FloatArray
    q_rad: FloatArray
    tip_xy_m: FloatArray
    machine_x_m: FloatArray
    power_w: FloatArray
    energy_j: float
    swing_rad: FloatArray | None = None
    swing_rate_rad_s: FloatArray | None = None

    def to_npz_dict(self) -> dict[str, Any]:
        """Arrays for ``numpy.savez`` (the real-time HIL hands its truth over in a file)."""
        swing = {}
        if self.swing_rad is not None and self.swing_rate_rad_s is not None:
            swing = {"swing_rad": self.swing_rad, "swing_rate_rad_s": self.swing_rate_rad_s}
        return {
            **swing,
            "sync_index": self.sync_index,
            "t_s": self.t_s,
            "stroke_m": self.stroke_m,
            "q_rad": self.q_rad,
            "tip_xy_m": self.tip_xy_m,
            "machine_x_m": self.machine_x_m,
            "power_w": self.power_w,
            "energy_j": np.array(self.energy_j),
        }

    @classmethod
    def from_npz(cls, data: Any) -> Truth:
        """The inverse of :meth:`to_npz_dict` (``data`` from ``numpy.load``)."""
        return cls(
            sync_index=np.asarray(data["sync_index"], dtype=np.int64),
            t_s=np.asarray(data["t_s"], dtype=np.float64),
            stroke_m=np.asarray(data["stroke_m"], dtype=np.float64).reshape(-1, 3),
            q_rad=np.asarray(data["q_rad"], dtype=np.float64).reshape(-1, 3),
            tip_xy_m=np.asarray(data["tip_xy_m"], dtype=np.float64).reshape(-1, 2),
            machine_x_m=np.asarray(data["machine_x_m"], dtype=np.float64),
            power_w=np.asarray(data["power_w"], dtype=np.float64),
            energy_j=float(data["energy_j"]),
            swing_rad=(
                np.asarray(data["swing_rad"], dtype=np.float64) if "swing_rad" in data else None
            ),
            swing_rate_rad_s=(
                np.asarray(data["swing_rate_rad_s"], dtype=np.float64)
                if "swing_rate_rad_s" in data
                else None
            ),
        )


class TruthRing:
    """The truth at every SYNC in a bounded ring: the last ``capacity`` rows.

    One float64 array ``(rows, columns)``; a row is the SYNC index (exact in a float64 below
    2**53), the HIL clock (s), the true strokes (m, 3), the joint angles (rad, 3), the machine
    travel (m) and the drive power in the period before the SYNC (W); with ``columns = 12`` (a
    rig with swing) then the swing angle (rad) and rate (rad/s). The array grows by doubling up
    to ``capacity`` rows, or is allocated whole at the start with every page written
    (``preallocate``: the memory of a long-running process is then flat from its first SYNC);
    once it holds ``capacity`` rows, each new row overwrites the oldest.

    Row ``r`` (0-based count of the rows recorded) sits at ``r % len(array)``; with one row per
    SYNC, SYNC ``k`` (1-based) is row ``k - 1``.

    Args:
        capacity: Rows kept, >= 2.
        preallocate: Allocate and touch all of them now.
        columns: Values per row: :attr:`COLUMNS`, or 12 with the swing.

    Raises:
        ConfigurationError: ``capacity`` below 2.

    Attributes:
        capacity: Rows kept at most.
        count: Rows recorded since creation (kept or overwritten).
    """

    COLUMNS = 10

    def __init__(self, capacity: int, *, preallocate: bool = False, columns: int = 10) -> None:
        if capacity < 2:
            raise ConfigurationError(f"truth capacity {capacity} rows must be >= 2")
        self.COLUMNS = int(columns)
        self.capacity = int(capacity)
        rows = self.capacity if preallocate else min(self.capacity, _TRUTH_FIRST_ROWS)
        # np.full writes every element, so the pages are resident from here on.
        self._data: FloatArray = np.full((rows, self.COLUMNS), np.nan)
        self.count = 0

    @property
    def kept(self) -> int:
        """Rows held now (the newest ``kept`` of :attr:`count`)."""
        return min(self.count, len(self._data))

    @property
    def dropped(self) -> int:
        """Rows overwritten (the oldest ``count - kept``)."""
        return self.count - self.kept

    def append(self, row: tuple[float, ...]) -> None:
        """Record one row (:attr:`COLUMNS` values); grows the array only before it first fills
        to ``capacity`` rows."""
        data = self._data
        n = len(data)
        if self.count == n < self.capacity:
            grown = np.full((min(2 * n, self.capacity), self.COLUMNS), np.nan)
            grown[:n] = data
            self._data = data = grown
            n = len(data)
        data[self.count % n] = row
        self.count += 1

    def rows(self, first: int, last: int) -> FloatArray:
        """The rows recorded ``first`` .. ``last`` (0-based, inclusive) that are still kept,
        oldest first, as a new ``(n, 10)`` array (``n`` may be 0)."""
        lo = max(first, self.count - self.kept)
        hi = min(last, self.count - 1)
        if hi < lo:
            return np.zeros((0, self.COLUMNS))
        return self._data[np.arange(lo, hi + 1) % len(self._data)]


def open_trace(path: str | Path) -> can.Listener:
    """A python-can logger for ``path`` (``.blf`` or ``.asc``).

    Raises:
        ConfigurationError: Another suffix.
    """
    suffix = Path(path).suffix.lower()
    if suffix not in (".blf", ".asc"):
        raise ConfigurationError(f"trace file {path}: suffix must be .blf or .asc, not {suffix!r}")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    logger: can.Listener = can.Logger(str(path))
    return logger


class HilCore:
    """Plant, terrain, drive nodes and VCU behind one bus (transport-free, clock-free).

    Args:
        rig: The rig simulated (drives, actuators, cylinders, node ids).
        q0_rad: Initial joint angles ``(3,)`` (boom, stick, bucket); on a rig with swing
            ``(4,)`` in axis order (the swing angle last, :mod:`rt_runtime.axes`) or ``(3,)``
            with the swing at 0.
        terrain: Material the bucket cuts (work-site frame), or None for a free arm.
        period_s: SYNC period; the lockstep transport advances the plant by it per SYNC.
        vcu: Put the VCU model (travel and swing) on the bus.
        keep_frames: Keep every frame in :attr:`frames` (unbounded: for short lockstep runs).
        truth_rows: The truth kept: the last this many SYNCs (see :class:`TruthRing`).
        preallocate_truth: Allocate the whole truth ring at once (a long-running process).
        tpdo_at_start: The drives send their type-0 TPDO2 at the first SYNC after NMT start;
            False: only when its content changes (``DriveFirmware``'s option).

    Attributes:
        plant: The arm.
        terrain: The terrain (or None).
        nodes: Drive nodes in axis order.
        vcu: The VCU model or None.
        sync_count: SYNCs received.
        truth_ring: The truth of the last ``truth_rows`` SYNCs.
        frames: Every frame on the bus as ``(arbitration id, data)`` in bus order, when
            ``keep_frames`` was set (the determinism test compares these).

    Raises:
        ConfigurationError: Bad pose, rig or period (a drive or VCU parameter the firmware
            models refuse, too).
    """

    def __init__(
        self,
        rig: Rig,
        q0_rad: FloatArray | tuple[float, float, float],
        terrain: Terrain | None = None,
        *,
        period_s: float = 0.002,
        vcu: bool = True,
        keep_frames: bool = False,
        truth_rows: int = TRUTH_ROWS,
        preallocate_truth: bool = False,
        tpdo_at_start: bool = True,
    ) -> None:
        if not (math.isfinite(period_s) and period_s > 0.0):
            raise ConfigurationError(f"period_s {period_s} must be finite and > 0")
        self.rig = rig
        self.period_s = period_s
        self.terrain = terrain
        self._load = _ShiftedLoad(terrain.soil_model(rig)) if terrain is not None else None
        q0 = np.asarray(q0_rad, dtype=np.float64).reshape(-1)
        if q0.shape not in ((3,), (4,)) or (q0.shape == (4,) and rig.swing is None):
            raise ConfigurationError(
                f"initial pose of shape {q0.shape}; allowed: (3,) (boom, stick, bucket), or "
                "(4,) with the swing angle last on a rig with swing"
            )
        self.plant = ArmPlant(rig, q0[:3], soil=self._load)
        self.swing: SwingPlant | None = None
        if rig.swing is not None:
            self.swing = SwingPlant(rig, float(q0[3]) if q0.shape == (4,) else 0.0)
        ids = dict(rig.can.node_ids)
        stroke0 = self.plant.stroke_m
        try:
            nodes = [
                DriveNode(
                    DriveFirmware(
                        ids[name],
                        rig,
                        name,
                        initial_position_m=float(stroke0[axis]),
                        tpdo_at_start=tpdo_at_start,
                    ),
                    axis,
                )
                for axis, name in enumerate(_AXES)
            ]
            if self.swing is not None:
                nodes.append(
                    DriveNode(
                        DriveFirmware(
                            ids["swing"],
                            swing_drive_rig(rig),
                            "swing",
                            initial_position_m=self.swing.theta_rad,
                            tpdo_at_start=tpdo_at_start,
                        ),
                        3,
                    )
                )
            self.nodes = tuple(nodes)
            self.vcu = VcuModel.from_rig(rig) if vcu else None
        except FirmwareConfigurationError as exc:
            raise ConfigurationError(
                f"rig {rig.name}: the drive or VCU model refuses it: {exc}"
            ) from exc
        self.sync_count = 0
        self.keep_frames = keep_frames
        self.frames: list[tuple[int, bytes]] = []
        self.trace: can.Listener | None = None
        self._servo_dt_s = rig.drives.servo_period_s
        # Valve drives with load compensation or pressure feedback read the cylinder forces
        # (chamber pressures); read from the plant each sub-step only then.
        self._reads_load = any(n.firmware.reads_load for n in self.nodes[:3])
        self._ideal_valves()
        self.truth_ring = TruthRing(
            truth_rows, preallocate=preallocate_truth, columns=10 if self.swing is None else 12
        )
        self._energy_at_sync = self.plant.energy_j
        self._dt_since_sync = 0.0

    # -- frames ---------------------------------------------------------------------------------

    @property
    def machine_x_m(self) -> float:
        """The machine's travel from its first position (the VCU's travel position)."""
        return self.vcu.travel_position_m if self.vcu is not None else 0.0

    def log(self, arbitration_id: int, data: bytes, t_s: float, *, is_rx: bool) -> None:
        """Record one bus frame (trace file and ``frames``)."""
        if self.keep_frames:
            self.frames.append((arbitration_id, bytes(data)))
        if self.trace is not None:
            self.trace.on_message_received(
                can.Message(
                    timestamp=t_s,
                    arbitration_id=arbitration_id,
                    is_extended_id=False,
                    data=data,
                    is_rx=is_rx,
                    channel=0,
                )
            )

    def on_frame(self, arbitration_id: int, data: bytes, now_s: float) -> list[Frame]:
        """One frame from the bus: the truth is sampled on SYNC, then every node answers.

        Returns:
            The frames the emulated nodes send in reply, in node order.
        """
        if arbitration_id == COB_SYNC:
            self._sample_truth(now_s)
        out: list[Frame] = []
        for node in self.nodes:
            out.extend(node.on_frame(arbitration_id, data, now_s))
        if self.vcu is not None:
            out.extend(self.vcu.on_frame(arbitration_id, data, now_s))
        if arbitration_id == COB_NMT or COB_SDO_RX < arbitration_id <= COB_SDO_RX + 127:
            self._ideal_valves()  # a drive's 0x2100 may have changed (SDO, NMT reset)
        return out

    def _ideal_valves(self) -> None:
        """An ideal plant's valves take the overlap their drives compensate (0x2100; see
        :attr:`~hil_sim.plant.ArmPlant.compensated_overlap`)."""
        plant = self.plant
        if plant.imperfections is None:
            n0, n1, n2 = self.nodes[:3]
            plant.compensated_overlap = (
                n0.firmware.overlap_compensation,
                n1.firmware.overlap_compensation,
                n2.firmware.overlap_compensation,
            )

    def pending_frames(self, now_s: float) -> list[Frame]:
        """Time supervision of every node at ``now_s``; their due heartbeats and emergencies."""
        out: list[Frame] = []
        for node in self.nodes:
            out.extend(node.pending_frames(now_s))
        if self.vcu is not None:
            out.extend(self.vcu.pending_frames(now_s))
        return out

    # -- time -----------------------------------------------------------------------------------

    def advance(self, dt_s: float) -> None:
        """Advance drives and plant by ``dt_s`` in servo sub-steps (the last one shorter if
        ``dt_s`` is not a multiple of the servo period)."""
        # The servo loop of every sub-step, flattened: the drive nodes' servo_step (firmware
        # cascade, then a jam or a rock applied at the axis) and the plant's servo_substep (the
        # firmware's
        # efforts are finite and within [-1, 1], so step()'s checks and clipping change nothing).
        if self.swing is not None:
            self._advance_with_swing(dt_s, self.swing)
            return
        remaining = dt_s
        plant = self.plant
        n0, n1, n2 = self.nodes
        fw0, fw1, fw2 = n0.firmware, n1.firmware, n2.firmware
        f0, f1, f2 = n0.faults, n1.faults, n2.faults
        load = self._load
        vcu = self.vcu
        servo = self._servo_dt_s
        full = servo * (1.0 + 1e-9)
        # What the drives' sensors read: the true strokes on an ideal plant.
        sense = plant.stroke_state if plant.imperfections is None else plant.sensed_stroke_state
        pressures = self._reads_load
        while remaining > 1e-12:
            h = servo if remaining > full else remaining
            (s0, s1, s2), (v0, v1, v2) = sense()
            l0, l1, l2 = plant.cylinder_forces_n if pressures else _NO_LOAD
            e0 = n0.effort = fw0.servo_step(h, s0, v0, l0)
            e1 = n1.effort = fw1.servo_step(h, s1, v1, l1)
            e2 = n2.effort = fw2.servo_step(h, s2, v2, l2)
            if load is not None:
                load.offset_m = vcu.travel_position_m if vcu is not None else 0.0
            plant.servo_substep(
                h,
                [
                    0.0 if f0.jammed or (f0.rock_direction and into_rock(f0, e0, v0)) else e0,
                    0.0 if f1.jammed or (f1.rock_direction and into_rock(f1, e1, v1)) else e1,
                    0.0 if f2.jammed or (f2.rock_direction and into_rock(f2, e2, v2)) else e2,
                ],
            )
            if vcu is not None:
                vcu.step(h)
            remaining -= h
        self._dt_since_sync += dt_s

    def _advance_with_swing(self, dt_s: float, swing: SwingPlant) -> None:
        """:meth:`advance` with the swing's node and plant: each sub-step the arm as there, then
        the swing on the arm's new pose (its inertia depends on the reach)."""
        remaining = dt_s
        plant = self.plant
        n0, n1, n2, n3 = self.nodes
        fw0, fw1, fw2, fw3 = n0.firmware, n1.firmware, n2.firmware, n3.firmware
        f0, f1, f2, f3 = n0.faults, n1.faults, n2.faults, n3.faults
        load = self._load
        vcu = self.vcu
        servo = self._servo_dt_s
        full = servo * (1.0 + 1e-9)
        # What the arm drives' sensors read (as in advance()).
        sense = plant.stroke_state if plant.imperfections is None else plant.sensed_stroke_state
        pressures = self._reads_load
        while remaining > 1e-12:
            h = servo if remaining > full else remaining
            (s0, s1, s2), (v0, v1, v2) = sense()
            w = swing.omega_rad_s
            l0, l1, l2 = plant.cylinder_forces_n if pressures else _NO_LOAD
            e0 = n0.effort = fw0.servo_step(h, s0, v0, l0)
            e1 = n1.effort = fw1.servo_step(h, s1, v1, l1)
            e2 = n2.effort = fw2.servo_step(h, s2, v2, l2)
            e3 = n3.effort = fw3.servo_step(h, swing.theta_rad, w)
            if load is not None:
                load.offset_m = vcu.travel_position_m if vcu is not None else 0.0
            plant.servo_substep(
                h,
                [
                    0.0 if f0.jammed or (f0.rock_direction and into_rock(f0, e0, v0)) else e0,
                    0.0 if f1.jammed or (f1.rock_direction and into_rock(f1, e1, v1)) else e1,
                    0.0 if f2.jammed or (f2.rock_direction and into_rock(f2, e2, v2)) else e2,
                ],
            )
            q = plant.q_rad
            swing.step(
                h,
                0.0 if f3.jammed or (f3.rock_direction and into_rock(f3, e3, w)) else e3,
                (float(q[0]), float(q[1]), float(q[2])),
            )
            if vcu is not None:
                vcu.step(h)
            remaining -= h
        self._dt_since_sync += dt_s

    def _sample_truth(self, now_s: float) -> None:
        self.sync_count += 1
        plant = self.plant
        (s0, s1, s2), _ = plant.stroke_state()
        q0, q1, q2 = plant.q_rad.tolist()
        energy = plant.energy_j
        dt = self._dt_since_sync
        power = (energy - self._energy_at_sync) / dt if dt > 0.0 else 0.0
        self._energy_at_sync = energy
        self._dt_since_sync = 0.0
        row: tuple[float, ...] = (
            self.sync_count, now_s, s0, s1, s2, q0, q1, q2, self.machine_x_m, power
        )
        if self.swing is not None:
            row += (self.swing.theta_rad, self.swing.omega_rad_s)
        self.truth_ring.append(row)

    # -- injection and material -----------------------------------------------------------------

    def inject(
        self, kind: FaultKind, axis: int, param: float | None = None, now_s: float = 0.0
    ) -> list[Frame]:
        """Switch a drive fault on in one drive node, from now on (see :class:`FaultKind`).

        Args:
            kind: A drive fault (``kind.layer == "drive"``).
            axis: The node's axis (0 boom, 1 stick, 2 bucket, 3 swing on a rig with swing).
            param: The kind's parameter (the glitch in mm, default :data:`GLITCH_MM`; on the
                swing in mrad, default :data:`GLITCH_SWING_MRAD`); unused by the others.
            now_s: The HIL's clock (a reboot's boot-up frame is stamped with it).

        Returns:
            Frames the node sends at once (a reboot's boot-up frame), for the transport to put
            on the bus.

        Raises:
            ValueError: ``axis`` not a node's, or a bus or host kind.
        """
        if not 0 <= axis < len(self.nodes):
            names = ", ".join((*_AXES, "swing")[: len(self.nodes)])
            raise ValueError(f"axis must be 0..{len(self.nodes) - 1} ({names}); got {axis}")
        if kind.layer != "drive":
            raise ValueError(f"{kind.label} is a {kind.layer} fault, not a drive node's")
        node = self.nodes[axis]
        faults = node.faults
        if kind is FaultKind.FOLLOWING_ERROR:
            faults.jammed = True
        elif kind is FaultKind.HEARTBEAT_LOSS:
            faults.deaf_to = faults.deaf_to | {COB_MASTER_HEARTBEAT}
        elif kind is FaultKind.NODE_SILENT:
            faults.silent = True
        elif kind in _DRIVE_EMCY:
            code, reaction = _DRIVE_EMCY[kind]
            node.firmware.inject_fault(code, reaction)
        elif kind is FaultKind.DRIVE_REBOOT:
            if faults.silent:
                return []
            frames = node.firmware.power_cycle(now_s)
            self._ideal_valves()  # its stored 0x2100 again
            return frames
        elif kind is FaultKind.ENCODER_GLITCH:
            default = GLITCH_SWING_MRAD if axis == 3 else GLITCH_MM
            faults.report_offset_m = (default if param is None else float(param)) * 1e-3
        else:
            faults.rock_direction = self._rock_direction(axis)
        return []

    def _rock_direction(self, axis: int) -> float:
        """The way an axis meets a rock: the way it moves (or pushes, at rest), extending when
        it does neither."""
        _, arm_rate = self.plant.stroke_state()
        rate = (*arm_rate, self.swing.omega_rad_s if self.swing is not None else 0.0)
        if abs(rate[axis]) > 1e-3:
            return math.copysign(1.0, rate[axis])
        effort = self.nodes[axis].effort
        return math.copysign(1.0, effort) if effort else 1.0

    def clear(self) -> None:
        """Every drive fault's cause gone (a freed axis, a repaired stub, the rock removed);
        what the drives latched stays latched until the master resets it."""
        for node in self.nodes:
            node.faults.clear()

    def truth(self) -> Truth:
        """The truth kept (the last ``truth_rows`` SYNCs; ``energy_j`` over the whole run)."""
        rows = self.truth_ring.rows(0, self.truth_ring.count - 1)
        q = np.ascontiguousarray(rows[:, 5:8])
        mx = rows[:, 8].copy()
        return Truth(
            sync_index=rows[:, 0].astype(np.int64),
            t_s=rows[:, 1].copy(),
            stroke_m=np.ascontiguousarray(rows[:, 2:5]),
            q_rad=q,
            tip_xy_m=self._tip_m(q, mx),
            machine_x_m=mx,
            power_w=rows[:, 9].copy(),
            energy_j=self.plant.energy_j,
            swing_rad=rows[:, 10].copy() if self.swing is not None else None,
            swing_rate_rad_s=rows[:, 11].copy() if self.swing is not None else None,
        )

    def _tip_m(self, q_rad: FloatArray, machine_x_m: FloatArray) -> FloatArray:
        """Tip positions ``(n, 2)`` in the work-site frame."""
        if not len(q_rad):
            return np.zeros((0, 2))
        tip = np.array(kinematics.forward(self.rig, q_rad)[..., :2], dtype=np.float64)
        tip = tip.reshape(-1, 2)
        tip[:, 0] += machine_x_m
        return tip

    def cut(self, sync_from: int, sync_to: int) -> float:
        """Cut the terrain with the true tip path between two SYNCs (inclusive, 1-based; the
        part of it the truth still keeps).

        Returns:
            The volume removed (m^3); 0 without a terrain or with fewer than two samples.
        """
        tip = self.tip_path(sync_from, sync_to)
        if self.terrain is None or tip is None:
            return 0.0
        return self.terrain.cut(tip).volume_m3

    def tip_path(self, sync_from: int, sync_to: int) -> FloatArray | None:
        """The true tip path between two SYNCs (inclusive, 1-based; work-site frame, ``(m,
        2)``), or None with fewer than two samples kept."""
        rows = self.truth_ring.rows(sync_from - 1, sync_to - 1)
        if len(rows) < 2:
            return None
        return self._tip_m(np.ascontiguousarray(rows[:, 5:8]), rows[:, 8])

    def adopt_terrain(self, terrain: Terrain) -> None:
        """Put ``terrain`` in the place of the one the arm digs (a copy cut off the servo's
        thread: :class:`hil_sim.harness.realtime`); the soil law follows it."""
        self.terrain = terrain
        if self._load is not None:
            self._load.inner = terrain.soil_model(self.rig)
