"""The master's send side and the cycle: setpoints and SYNC out, the drives' answers in.

Role: the part of the CiA 402 master the control loop runs every cycle
(:class:`CyclicExchange`): RPDO1 setpoints and SYNC (:meth:`~CyclicExchange.write_setpoints`),
the answers to the last SYNC with the cycle's status and the fault reaction
(:meth:`~CyclicExchange.read_feedback`), the master's heartbeat, quick stop and disable. It owns
the master's preallocated messages and stamps every frame with its send time (``time.time()``,
the epoch clock python-can stamps received frames with): a bus that transmits at once ignores
the stamp; a bridged bus (the 127.0.0.1 bridge into the HIL) carries it, so the far end can take
the moment the frame entered the bus instead of when it got to read it. Boot and enable
(:class:`~rt_runtime.canbus.master.CanMaster`) send through it as well.

Optional bus capability: a bus with ``send_many(msgs)`` (the messages in order, in one write;
``can.CanError`` as ``send`` raises it) gets each cycle's RPDO1s and SYNC in one call, one stamp
for the four (the bridge: one system call instead of four); any other bus gets one ``send`` a
frame, which is what a socketcan socket takes anyway.

Bus errors: any exception out of the bus is a bus error, whatever its type: python-can raises
``can.CanError`` and its subclasses, but a backend may let others through (python-can-remote's
client raises ``ConnectionResetError``, ``BrokenPipeError`` or its ``WebsocketClosed`` when the
far end is gone). The cycle's methods return ``BUS_ERROR`` for all of them and keep the latest
in :attr:`CyclicExchange.bus_exception`; the send helpers used outside the loop raise
:class:`~rt_runtime.errors.CommunicationError` naming it.

Loop safety: the cycle's methods pack into preallocated messages, never raise for bus
conditions (status codes instead) and allocate only small temporaries and the EMCY and heartbeat
event objects.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Sequence

import can
import numpy as np
from numpy.typing import NDArray

from rt_runtime.canbus.cia402 import Command, DriveState, Target, next_controlword
from rt_runtime.canbus.config import MODE_CSP, MasterConfig
from rt_runtime.canbus.feedback import CycleStatus, Feedback, WriteStatus
from rt_runtime.canbus.heartbeat import HeartbeatEventKind, HeartbeatProducer
from rt_runtime.canbus.nmt import NmtState
from rt_runtime.canbus.pdo import RPDO1, RPDO2, pdo_message, sync_message
from rt_runtime.canbus.router import FrameRouter
from rt_runtime.errors import CommunicationError

__all__ = ["CyclicExchange", "bus_error_text"]

_ENABLED = int(DriveState.OPERATION_ENABLED)
_FAULTED = (int(DriveState.FAULT), int(DriveState.FAULT_REACTION_ACTIVE))


def bus_error_text(exc: BaseException) -> str:
    """One line about an exception out of the bus: its type and message."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class CyclicExchange:
    """Frames out and the cycle's read on one python-can bus (see the module docstring).

    Args:
        bus: Any python-can bus; frames are read from it only through :meth:`read_feedback`.
        config: The master's configuration (node ids, heartbeat period).
        router: Where the frames read go (its feedback workspace is this object's).
        react_to_faults: See :attr:`react_to_faults`.

    Attributes:
        feedback: The feedback workspace (the router's).
        react_to_faults: While :attr:`expect_enabled`, answer an EMCY with a nonzero code, a
            drive fault, a lost heartbeat or a drive leaving OPERATION_ENABLED by sending quick
            stop to every drive, once until :meth:`clear_fault_latch`.
        expect_enabled: Every drive should be OPERATION_ENABLED (the master's enable sets it;
            quick stop and disable clear it); a drive that is not is ``NOT_ENABLED``.
        producing: The master's heartbeat is produced while boot and enable wait (from the
            drives' NMT start on).
        bus_exception: The latest exception out of the bus (None while it has raised none):
            the bus is broken or was refused a frame.
    """

    def __init__(
        self, bus: can.BusABC, config: MasterConfig, router: FrameRouter, react_to_faults: bool
    ) -> None:
        self.bus = bus
        self.config = config
        self.router = router
        self.feedback = router.feedback
        self.react_to_faults = react_to_faults
        self.expect_enabled = False
        self.producing = False
        self.bus_exception: BaseException | None = None
        self.n = len(config.node_ids)
        self._reacted = False
        self._rpdo1 = [pdo_message(RPDO1, node) for node in config.node_ids]
        self._rpdo2 = [pdo_message(RPDO2, node) for node in config.node_ids]
        self._sync = sync_message()
        self._cycle_frames = (*self._rpdo1, self._sync)
        self._send_many: Callable[[Sequence[can.Message]], None] | None = getattr(
            bus, "send_many", None
        )
        self._controlword = [0] * self.n
        self._producer = HeartbeatProducer(
            config.master_node_id, config.heartbeat_period_s, NmtState.OPERATIONAL
        )

    # ------------------------------------------------------------------ sending

    def tx(self, msg: can.Message) -> None:
        """Send one frame stamped with its send time (``time.time()``).

        Raises:
            Exception: Whatever the bus raised (see the module docstring); kept in
                :attr:`bus_exception`.
        """
        msg.timestamp = time.time()
        try:
            self.bus.send(msg)
        except Exception as exc:
            self.bus_exception = exc
            raise

    def send(self, msg: can.Message) -> None:
        """Send one frame outside the loop (boot, enable).

        Raises:
            CommunicationError: The bus refused it or failed (the message names the exception).
        """
        try:
            self.tx(msg)
        except Exception as exc:
            raise CommunicationError(
                f"the bus refused frame 0x{msg.arbitration_id:03X}: {bus_error_text(exc)}"
            ) from exc

    def send_sync(self) -> None:
        """SYNC alone (enable's steps).

        Raises:
            CommunicationError: The bus refused it (then it does not count as sent).
        """
        self.send(self._sync)
        self.router.sync_sent()

    @property
    def sync_stamp_s(self) -> float:
        """The send stamp of the latest SYNC (the bus's clock, as the frames' timestamps)."""
        return float(self._sync.timestamp)

    def produce_heartbeat(self, now_s: float) -> None:
        """The master's heartbeat when due and :attr:`producing` (boot's and enable's waits).

        Raises:
            CommunicationError: The bus refused it.
        """
        if self.producing and self._producer.due(now_s):
            self.send(self._producer.message)

    @property
    def next_heartbeat_s(self) -> float | None:
        """When the next heartbeat is due while :attr:`producing` (s), else None."""
        return self._producer.next_due_s if self.producing else None

    def hold(self, axis: int, stroke_um: int) -> None:
        """RPDO1 to one drive: target ``stroke_um`` (um), velocity offset 0 (enable's hold).

        Raises:
            CommunicationError: The bus refused it.
        """
        RPDO1.codec.pack_into(self._rpdo1[axis].data, 0, stroke_um, 0)
        self.send(self._rpdo1[axis])

    def step_to(self, axis: int, target: Target) -> None:
        """RPDO2 to one drive: the next controlword towards ``target`` from its last statusword
        (:func:`~rt_runtime.canbus.cia402.next_controlword`; a fault reset is an edge of bit 7
        against the controlword sent before).

        Raises:
            CommunicationError: The bus refused it.
        """
        word = next_controlword(
            int(self.feedback.statusword[axis]), target, self._controlword[axis]
        )
        self._pack_rpdo2(axis, word)
        self.send(self._rpdo2[axis])

    def clear_fault_latch(self) -> None:
        """Let the fault reaction fire again (once) after the next enable."""
        self._reacted = False

    def _pack_rpdo2(self, axis: int, controlword: int) -> None:
        RPDO2.codec.pack_into(self._rpdo2[axis].data, 0, controlword, MODE_CSP)
        self._controlword[axis] = controlword

    # ------------------------------------------------------------------ cycle

    def write_setpoints(
        self,
        stroke_um: Sequence[int] | NDArray[np.int32],
        velocity_um_s: Sequence[int] | NDArray[np.int32],
    ) -> WriteStatus:
        """Send RPDO1 (target stroke, velocity offset) to every drive, then SYNC.

        The frames are stamped with their send time (``time.time()``). On a bus with
        ``send_many`` they go in one call, one stamp for all four; on any other bus one
        ``send`` each. Loop safe.

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
                self.router.sync_sent()
            else:
                for msg in self._rpdo1:
                    self.tx(msg)
                self.tx(self._sync)
                self.router.sync_sent()
        except Exception as exc:  # any exception out of the bus: see the module docstring
            self.bus_exception = exc
            return WriteStatus.BUS_ERROR
        return WriteStatus.OK

    def last_target_um(self) -> NDArray[np.int32]:
        """The stroke target (um) of the last RPDO1 sent to each drive, ``(n,)``.

        Read back from the preallocated messages, so a caller holding the axes continues from
        exactly what was commanded last (enable's hold, an executor's last setpoint), never
        from a measured position. Outside the loop (allocates the result).
        """
        return np.array(
            [RPDO1.codec.unpack_from(msg.data)[0] for msg in self._rpdo1], dtype=np.int32
        )

    def read_feedback(self, now_s: float, timeout_s: float) -> Feedback:
        """Collect the drives' answers to the latest SYNC and everything else received.

        Waits until every drive's TPDO1 for the latest SYNC is in, each wait at most
        ``timeout_s`` (so the call returns at the latest ``timeout_s`` after the last frame that
        came); then takes whatever else is queued without waiting. Checks heartbeat timeouts at
        ``now_s``. While :attr:`expect_enabled`, when a drive sends an EMCY, faults, loses its
        heartbeat or leaves OPERATION_ENABLED, and :attr:`react_to_faults` is set, sends quick
        stop to every drive once (``Feedback.reacted``).

        Loop safe: returns the reused :class:`~rt_runtime.canbus.feedback.Feedback` (valid until
        the next call), never raises for bus conditions.

        Args:
            now_s: Time of this cycle (s), for heartbeat supervision and event stamps.
            timeout_s: Longest wait for one missing frame (0 = take only what is queued).
        """
        fb = self.feedback
        router = self.router
        bus = self.bus
        fb.emcys.clear()
        fb.heartbeat_events.clear()
        fb.reacted = False
        bus_error = False
        try:
            while router.pending > 0:
                msg = bus.recv(timeout=timeout_s)
                if msg is None:
                    break
                router.dispatch(msg, now_s)
            while (msg := bus.recv(timeout=0.0)) is not None:
                router.dispatch(msg, now_s)
        except Exception as exc:  # any exception out of the bus: see the module docstring
            self.bus_exception = exc
            bus_error = True
        consumer = router.consumer
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
        missed = fb.stale.tolist().count(True)
        if missed:
            status = CycleStatus.STALE
            fb.counts.missed_tpdo1 += missed
        if any(not e.is_reset for e in fb.emcys):
            status = CycleStatus.EMCY
        if self.expect_enabled and any(x != _ENABLED for x in states):
            status = CycleStatus.NOT_ENABLED
        if lost_any or rebooted:
            status = CycleStatus.HEARTBEAT_LOST
        if any(x in _FAULTED for x in states):
            status = CycleStatus.DRIVE_FAULT
        if (
            self.react_to_faults
            and self.expect_enabled
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
                self.tx(self._producer.message)
        except Exception:  # kept in bus_exception by tx
            return WriteStatus.BUS_ERROR
        return WriteStatus.OK

    def quick_stop(self) -> WriteStatus:
        """Quick stop (controlword 0x0002) to every drive: each decelerates with 0x6085 and,
        with quick stop option code 2, ends in SWITCH_ON_DISABLED. Loop safe; tries every drive
        even when one send fails."""
        self.expect_enabled = False
        return self._send_controlword(int(Command.QUICK_STOP))

    def disable(self) -> WriteStatus:
        """Disable voltage (controlword 0x0000) to every drive: power stages off at once (the
        axes coast or brake); for axes at rest. Loop safe."""
        self.expect_enabled = False
        return self._send_controlword(int(Command.DISABLE_VOLTAGE))

    def _send_controlword(self, controlword: int) -> WriteStatus:
        status = WriteStatus.OK
        for axis in range(self.n):
            self._pack_rpdo2(axis, controlword)
            try:
                self.tx(self._rpdo2[axis])
            except Exception:  # kept in bus_exception by tx
                status = WriteStatus.BUS_ERROR
        return status
