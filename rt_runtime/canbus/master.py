"""The CiA 301/402 master of the arm's cylinder drives.

Role: boots and configures the drives and brings them to OPERATION_ENABLED (outside the loop),
and gives the loop its cycle. See the package docstring (:mod:`rt_runtime.canbus`) for the API
contract the executor and the HIL streamer use. :class:`CanMaster` is built of three parts, one
responsibility each:

* this module: boot (NMT, the SDO configuration of :mod:`~rt_runtime.canbus.config`) and the
  CiA 402 enable sequence, with the waits they need;
* :class:`~rt_runtime.canbus.cyclic.CyclicExchange`: the frames out (stamped at send) and the
  cycle: setpoints and SYNC, the answers with the cycle's status and the fault reaction, the
  master's heartbeat, quick stop, disable;
* :class:`~rt_runtime.canbus.router.FrameRouter`: every frame read, routed by COB-ID into the
  one :class:`~rt_runtime.canbus.feedback.Feedback` workspace.

Who reads the bus: the master alone, on the caller's thread (the router's docstring says why).
No thread, no clock: waits are ``bus.recv(timeout)`` calls bounded by the caller's ``now_fn`` or
``timeout_s``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import can
import numpy as np
from numpy.typing import NDArray

from rt_runtime.canbus.busload import (
    BusLoad,
    bus_load_report,
    cia402_cycle_frames,
    vcu_cycle_frames,
)
from rt_runtime.canbus.cia402 import DriveState, Target
from rt_runtime.canbus.config import (
    DEFAULT_EDS,
    DriveInfo,
    MasterConfig,
    configuration_writes,
    load_od,
)
from rt_runtime.canbus.cyclic import CyclicExchange, bus_error_text
from rt_runtime.canbus.emcy import Emcy
from rt_runtime.canbus.feedback import Feedback, WriteStatus
from rt_runtime.canbus.heartbeat import HeartbeatConsumer, HeartbeatEventKind
from rt_runtime.canbus.nmt import NmtCommand, NmtState, nmt_message
from rt_runtime.canbus.pdo import TPDO2
from rt_runtime.canbus.router import FrameRouter
from rt_runtime.canbus.sdo import SdoClient, SdoTimeoutError
from rt_runtime.errors import CommunicationError, DriveFault, ExcavatorRtError

if TYPE_CHECKING:
    from rt_runtime.rig.model import Rig

__all__ = ["STATUS_REREAD_SYNCS", "CanMaster"]

_DEVICE_PROFILE_402 = 402
_CSP_SUPPORTED_BIT = 1 << 7
#: During :meth:`CanMaster.enable`, a drive not yet OPERATION_ENABLED whose status (0x6041,
#: 0x6061, 0x603F) was last learned this many SYNCs ago (no TPDO2 since: TPDO2 is sent on change
#: only, and a drive may send none) has it read again by SDO.
STATUS_REREAD_SYNCS = 3


@contextlib.contextmanager
def _bus_errors(what: str) -> Iterator[None]:
    """Any exception out of the bus during ``what`` as a :class:`CommunicationError` naming it
    (the runtime's own errors pass as they are)."""
    try:
        yield
    except ExcavatorRtError:
        raise
    except Exception as exc:
        raise CommunicationError(f"{what}: the bus failed: {bus_error_text(exc)}") from exc


class CanMaster:
    """CiA 301/402 master of the arm's three cylinder drives on a python-can bus.

    Args:
        bus: Any python-can bus (socketcan, kvaser, ``virtual``, a remote bridge). The master
            becomes its only reader; it does not own or shut it down. A bus with the optional
            ``send_many`` gets each cycle's frames in one call
            (:mod:`~rt_runtime.canbus.cyclic`).
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

    Attributes:
        config: What the master writes to the drives (:class:`~.config.MasterConfig`).
        ods: Each drive's object dictionary, in axis order.
        n: Number of drives.
        feedback: The feedback workspace, reused every cycle.
        drive_info: What each drive reported at the last :meth:`boot`.
        router: The receive side.
        cycle: The send side and the cycle; :meth:`write_setpoints`, :meth:`read_feedback`,
            :meth:`heartbeat`, :meth:`quick_stop` and :meth:`disable` are its.

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
        self.ods = tuple(load_od(Path(eds_path), node) for node in self.config.node_ids)
        self.n = len(self.config.node_ids)
        self.feedback = Feedback(self.n)
        self.drive_info: tuple[DriveInfo, ...] = ()
        consumer = HeartbeatConsumer(self.config.node_ids, self.config.heartbeat_timeout_s)
        self.router = FrameRouter(self.config.node_ids, self.feedback, consumer, on_other_frame)
        self.cycle = CyclicExchange(bus, self.config, self.router, react_to_faults)
        self._booted = False

    # ------------------------------------------------------------------ the cycle's API

    def write_setpoints(
        self,
        stroke_um: Sequence[int] | NDArray[np.int32],
        velocity_um_s: Sequence[int] | NDArray[np.int32],
    ) -> WriteStatus:
        """RPDO1 to every drive, then SYNC (:meth:`.CyclicExchange.write_setpoints`). Loop safe."""
        return self.cycle.write_setpoints(stroke_um, velocity_um_s)

    def read_feedback(self, now_s: float, timeout_s: float) -> Feedback:
        """The answers to the latest SYNC, the cycle's status and the fault reaction
        (:meth:`.CyclicExchange.read_feedback`). Loop safe."""
        return self.cycle.read_feedback(now_s, timeout_s)

    def heartbeat(self, now_s: float) -> WriteStatus:
        """Send the master's heartbeat when due (call every cycle; loop safe)."""
        return self.cycle.heartbeat(now_s)

    def quick_stop(self) -> WriteStatus:
        """Quick stop to every drive (:meth:`.CyclicExchange.quick_stop`). Loop safe."""
        return self.cycle.quick_stop()

    def disable(self) -> WriteStatus:
        """Disable voltage to every drive (:meth:`.CyclicExchange.disable`). Loop safe."""
        return self.cycle.disable()

    def last_target_um(self) -> NDArray[np.int32]:
        """The stroke target (um) of the last RPDO1 sent to each drive, ``(n,)``
        (:meth:`.CyclicExchange.last_target_um`). Outside the loop."""
        return self.cycle.last_target_um()

    @property
    def sync_stamp_s(self) -> float:
        """The send stamp of the latest SYNC (the bus's clock, as the frames' timestamps)."""
        return self.cycle.sync_stamp_s

    @property
    def last_emcy(self) -> list[Emcy | None]:
        """Per axis, the latest EMCY received (None before the first)."""
        return self.router.last_emcy

    @property
    def react_to_faults(self) -> bool:
        """Whether the cycle's read quick-stops every drive on a fault (see the class's args)."""
        return self.cycle.react_to_faults

    @react_to_faults.setter
    def react_to_faults(self, on: bool) -> None:
        self.cycle.react_to_faults = on

    def cycle_frames(
        self, period_s: float | None = None, *, vcu: bool | None = None
    ) -> tuple[tuple[int, float], ...]:
        """Every frame on the bus per SYNC period at ``period_s`` (default: the configured
        period), as (payload bytes, frames per period): RPDO1, SYNC, TPDO1, heartbeats
        (:func:`~.busload.cia402_cycle_frames`), and the VCU's status on every SYNC
        (:func:`~.busload.vcu_cycle_frames`) when ``vcu`` (default: the rig's ``can.vcu``)
        says the VCU is on the bus."""
        period = self.config.period_s if period_s is None else period_s
        frames = cia402_cycle_frames(self.n, period, self.config.heartbeat_period_s)
        if self.rig.can.vcu if vcu is None else vcu:
            frames += vcu_cycle_frames(period)
        return frames

    def bus_load(self, period_s: float | None = None, *, vcu: bool | None = None) -> BusLoad:
        """Load of :meth:`cycle_frames` (same arguments) on the rig's bitrate."""
        period = self.config.period_s if period_s is None else period_s
        return bus_load_report(self.cycle_frames(period, vcu=vcu), period, self.config.bitrate)

    # ------------------------------------------------------------------ waiting

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
        cycle = self.cycle
        start_s = now_fn()
        deadline_s = start_s + timeout_s
        idle_s = 0.0
        while not done():
            now_s = now_fn()
            cycle.produce_heartbeat(now_s)
            remaining_s = min(deadline_s - now_s, timeout_s - idle_s)
            if remaining_s <= 0.0:
                raise CommunicationError(f"timed out after {timeout_s} s waiting for {what}")
            wait_s = remaining_s
            next_s = cycle.next_heartbeat_s
            if next_s is not None:
                # Wake up for the next heartbeat (at least a small step, so a clock that does
                # not move still ends the wait through the idle sum).
                wait_s = min(wait_s, max(next_s - now_s, 1e-4))
            msg = self.bus.recv(timeout=wait_s)
            if msg is None:
                idle_s += wait_s
            else:
                self.router.dispatch(msg, now_fn())

    def _drain(self, now_s: float) -> None:
        while (msg := self.bus.recv(timeout=0.0)) is not None:
            self.router.dispatch(msg, now_s)

    def _wait_until(self, t_s: float, now_fn: Callable[[], float]) -> None:
        """Dispatch frames until ``now_fn()`` reaches ``t_s`` (or one empty wait covers it)."""
        while (remaining_s := t_s - now_fn()) > 0.0:
            msg = self.bus.recv(timeout=remaining_s)
            if msg is None:
                return
            self.router.dispatch(msg, now_fn())

    # ------------------------------------------------------------------ boot

    def boot(self, now_fn: Callable[[], float], timeout_s: float) -> tuple[DriveInfo, ...]:
        """Reset, configure and start every drive (outside the loop), from whatever state they
        are in (the NMT reset node brings each back to its power-on state).

        Sequence: NMT reset node per drive; wait for every boot-up message; per drive check
        0x1000 (CiA 402 device), 0x6502 (CSP supported), read 0x1008, then the SDO downloads of
        :func:`~rt_runtime.canbus.config.configuration_writes`; NMT start per drive; produce the
        master heartbeat and wait until every drive's heartbeat reports OPERATIONAL.

        Args:
            now_fn: Clock (s), monotonic or simulated.
            timeout_s: Time allowed for each wait (boot-up messages, operational heartbeats);
                every SDO transfer has ``sdo_timeout_s``.

        Returns:
            What each drive reported about itself (also kept in ``drive_info``).

        Raises:
            CommunicationError: A drive did not answer in time, or the bus refused a frame or
                failed (any exception out of the bus, named).
            SdoAbortedError: A drive refused a configuration value (index, sub, meaning).
            DriveFault: A drive is not a CiA 402 drive or lacks CSP.
        """
        with _bus_errors("boot"):
            return self._boot(now_fn, timeout_s)

    def _boot(self, now_fn: Callable[[], float], timeout_s: float) -> tuple[DriveInfo, ...]:
        cfg = self.config
        cycle = self.cycle
        consumer = self.router.consumer
        self._booted = False
        cycle.producing = False
        cycle.expect_enabled = False
        consumer.reset()
        self._drain(now_fn())
        booted: set[int] = set()
        self.feedback.heartbeat_events.clear()
        for node in cfg.node_ids:
            cycle.send(nmt_message(NmtCommand.RESET_NODE, node))

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
            sdo = SdoClient(self.bus, node, on_other=self.router.dispatch)
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
            cycle.send(nmt_message(NmtCommand.START, node))
        cycle.producing = True

        def all_operational() -> bool:
            self.feedback.heartbeat_events.clear()
            return all(consumer.state(n) is NmtState.OPERATIONAL for n in cfg.node_ids)

        try:
            self._wait(all_operational, now_fn, timeout_s, "OPERATIONAL heartbeats")
        except CommunicationError as exc:
            late = {
                n: consumer.state(n)
                for n in cfg.node_ids
                if consumer.state(n) is not NmtState.OPERATIONAL
            }
            raise CommunicationError(
                f"boot: after NMT start, nodes {late} (node: last heartbeat state) did not "
                f"report OPERATIONAL within {timeout_s} s"
            ) from exc
        consumer.start(now_fn())
        self.drive_info = tuple(infos)
        self._booted = True
        return self.drive_info

    # ------------------------------------------------------------------ enable

    def enable(self, now_fn: Callable[[], float], timeout_s: float) -> None:
        """Bring every drive to OPERATION_ENABLED (outside the loop).

        First each drive's status, the objects TPDO2 maps (0x6041 statusword, 0x6061 modes
        display, 0x603F error code), is read by SDO upload: TPDO2 is sent only when its content
        changes (transmission type 0), so a drive need not send one after NMT start. Then one
        step per SYNC period (paced on ``now_fn``): RPDO1 holding each drive at its actual
        position with zero velocity offset (so enabling does not jump), RPDO2 with the next
        controlword of :func:`~rt_runtime.canbus.cia402.next_controlword` to every drive not yet
        there, then SYNC; the TPDO1s answering it are awaited, a TPDO2 that comes updates the
        drive's status. A drive not yet there whose status was last learned
        :data:`STATUS_REREAD_SYNCS` SYNCs ago has it read again by SDO, so no decision waits
        for a TPDO2. The first step is a SYNC alone, to learn positions. A drive in FAULT gets
        fault-reset edges. Clears the master's fault latch.

        Args:
            now_fn: Clock (s), monotonic or simulated.
            timeout_s: Time allowed for the whole sequence (each SDO upload is bounded by
                ``sdo_timeout_s`` and by what is left of it, at least one period).

        Raises:
            CommunicationError: Not booted, no TPDO1 answer or SDO response in time (naming the
                drive), a drive aborted the upload of its status (:class:`SdoAbortedError`),
                drives not there when time runs out, or the bus refused a frame or failed (any
                exception out of the bus, named).
            DriveFault: A drive is (still) in FAULT when time runs out.
        """
        with _bus_errors("enable"):
            self._enable(now_fn, timeout_s)

    def _read_status(self, axis: int, now_fn: Callable[[], float], deadline_s: float) -> None:
        """Upload the objects TPDO2 maps from one drive and put them in the feedback."""
        node = self.config.node_ids[axis]
        sdo = SdoClient(self.bus, node, on_other=self.router.dispatch)
        values = []
        for index, sub, _ in TPDO2.entries:
            timeout_s = min(self.sdo_timeout_s, max(deadline_s - now_fn(), self.config.period_s))
            try:
                values.append(int(sdo.read(self.ods[axis], index, sub, now_fn, timeout_s)))
            except SdoTimeoutError as exc:
                raise SdoTimeoutError(
                    f"enable: reading the status of the {self.config.axes[axis]} drive "
                    f"(node {node}): {exc}"
                ) from exc
        statusword, mode, error_code = values
        self.router.set_status(axis, statusword, mode, error_code)

    def _enable(self, now_fn: Callable[[], float], timeout_s: float) -> None:
        if not self._booted:
            raise CommunicationError("enable() needs a successful boot() first")
        cycle = self.cycle
        cycle.expect_enabled = False
        cycle.clear_fault_latch()
        fb = self.feedback
        start_s = now_fn()
        deadline_s = start_s + timeout_s
        # Per axis, the SYNC count at which its status was last learned (TPDO2 or SDO).
        learned = np.full(self.n, fb.sync_count, np.int64)
        for axis in range(self.n):
            self._read_status(axis, now_fn, deadline_s)
        first = True
        while True:
            now_s = now_fn()
            cycle.produce_heartbeat(now_s)
            if not first:
                np.maximum(learned, fb.tpdo2_sync, out=learned)
                for axis in range(self.n):
                    if (
                        fb.state[axis] != DriveState.OPERATION_ENABLED
                        and fb.sync_count - learned[axis] >= STATUS_REREAD_SYNCS
                        and now_s < deadline_s
                    ):
                        self._read_status(axis, now_fn, deadline_s)
                        learned[axis] = fb.sync_count
                if (fb.state == DriveState.OPERATION_ENABLED).all():
                    cycle.expect_enabled = True
                    return
                if now_fn() >= deadline_s:
                    self._enable_failed(timeout_s)
                for axis in range(self.n):
                    cycle.hold(axis, int(fb.position_um[axis]))
                for axis in range(self.n):
                    if fb.state[axis] != DriveState.OPERATION_ENABLED:
                        cycle.step_to(axis, Target.OPERATION_ENABLED)
            first = False
            sync_s = now_fn()
            cycle.send_sync()
            fb.emcys.clear()
            fb.heartbeat_events.clear()
            try:
                self._wait(
                    lambda: self.router.pending <= 0,
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

    def _enable_failed(self, timeout_s: float) -> None:
        fb = self.feedback
        lines = []
        faulted = False
        for axis in range(self.n):
            state = fb.drive_state(axis)
            faulted |= state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE)
            emcy = self.router.last_emcy[axis]
            last = f", last EMCY {emcy.description}: {emcy.meaning}" if emcy is not None else ""
            lines.append(
                f"{self.config.axes[axis]} (node {self.config.node_ids[axis]}): "
                f"{state.name if state is not None else 'undecodable'} "
                f"(statusword 0x{int(fb.statusword[axis]):04X}{last})"
            )
        text = f"drives not OPERATION_ENABLED after {timeout_s} s: " + "; ".join(lines)
        raise DriveFault(text) if faulted else CommunicationError(text)
