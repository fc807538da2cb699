"""The lockstep transport: the HIL core and the runtime's master in one process on one
simulated clock (DESIGN.md "Loop, HIL and time").

:class:`LockstepHil` runs :class:`~hil_sim.sim.HilCore` on an in-process channel
(:mod:`rt_runtime.canbus.inprocess`). The HIL has its own bus end; the master gets
:attr:`LockstepHil.master_bus`, an end on the same channel that hands control to the HIL after
every frame it sends (:meth:`LockstepHil.pump`) and whose ``recv(timeout)`` with nothing queued
advances the simulated clock by ``timeout`` instead of waiting. SDO, NMT and heartbeats are
answered at once; on each SYNC the HIL answers with the TPDOs (sampled at the SYNC) and then
advances the plant by exactly one period in servo sub-steps. Time-triggered frames (heartbeats,
emergencies) go out whenever the simulated clock moves (:class:`LockstepClock`).
Single-threaded and free of wall-clock reads, so two runs give identical traces.
:class:`HilCost` splits each period's wall time into the HIL's own and the runtime's
(:class:`LockstepCost`).

It joins runtime and HIL (it is the runtime's bus), so it lives in the harness.
"""

from __future__ import annotations

import array
import itertools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from time import perf_counter_ns
from typing import Any

import can
import numpy as np
from numpy.typing import NDArray

from firmware_models.drive import Frame
from hil_sim.busfaults import BusFaults
from hil_sim.sim import COB_SYNC, TRUTH_ROWS, FaultKind, FloatArray, HilCore, open_trace
from hil_sim.terrain import Terrain
from rt_runtime.canbus.inprocess import ChannelBus, InProcessChannel
from rt_runtime.canbus.simtime import SimulatedTimeBus
from rt_runtime.reports import Distribution
from rt_runtime.rig import Rig

_channel_numbers = itertools.count()


class LockstepClock:
    """Simulated seconds, advanced only by sleeping (``sleep_until``) or an empty ``recv``.

    Args:
        on_advance: Called with the new time whenever the clock moves (the HIL's supervision).
    """

    realtime = False

    def __init__(self, on_advance: Callable[[float], None]) -> None:
        self._now = 0.0
        self._on_advance = on_advance

    def now(self) -> float:
        """Current simulated time (s)."""
        return self._now

    def sleep_until(self, t_s: float) -> None:
        """Move the clock to ``t_s`` (no-op if it is already there or later)."""
        if t_s > self._now:
            self._now = t_s
            self._on_advance(t_s)


class LockstepBus(SimulatedTimeBus, ChannelBus):
    """The master's end of the lockstep bus: an in-process channel end on the simulated clock.

    ``send`` stamps the copy with the simulated time and lets the far end answer at once
    (``pump``: :meth:`LockstepHil.pump`). ``_recv_internal(timeout)`` never blocks on the wall
    clock: with nothing queued it advances the simulated clock by ``timeout`` (the HIL's
    heartbeats and supervision run meanwhile) and returns what arrived, or None; with
    ``timeout=None`` it advances one period at a time, up to 10 s. python-can's filters apply,
    measured on the simulated clock (:class:`~rt_runtime.canbus.simtime.SimulatedTimeBus`).

    Args:
        channel: The in-process channel (the HIL's end is on it).
        clock: The simulated clock.
        pump: Called after every send and before every receive: the far end handles what is
            queued for it.
        period_s: The step of a ``recv(None)`` wait.
    """

    def __init__(
        self,
        channel: InProcessChannel,
        clock: LockstepClock,
        pump: Callable[[], None],
        period_s: float,
    ) -> None:
        super().__init__(channel, clock=clock.now)
        self.sim_clock = clock
        self._pump = pump
        self._period_s = period_s

    def now_s(self) -> float:
        """The simulated clock (s)."""
        return self.sim_clock.now()

    #: The adapter is bus-off (a :class:`~hil_sim.busfaults.BusFaults` fault): sends raise.
    bus_off = False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.bus_off:
            raise can.CanOperationError(f"{self.channel_info}: the adapter is bus-off")
        super().send(msg, timeout)
        self._pump()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._pump()
        msg = self.take()
        if msg is not None:
            return msg, False
        clock = self.sim_clock
        if timeout is None:
            period_s = self._period_s
            for _ in range(round(10.0 / period_s)):
                clock.sleep_until(clock.now() + period_s)
                msg = self.take()
                if msg is not None:
                    break
        elif timeout > 0.0:
            clock.sleep_until(clock.now() + timeout)
            msg = self.take()
        return msg, False


class HilCost:
    """The lockstep HIL's own wall time, per SYNC period (what the master's loop does not own).

    A period runs from one SYNC's arrival at the HIL to the next's. Per period it holds the
    nanoseconds spent inside the HIL (frame handling, the nodes' answers and supervision, the
    servo sub-steps, its bus end) and the wall clock at the SYNC, so the whole period's wall time
    and the rest of it (the runtime: loop, controllers, master, its bus end) follow. Storage is
    two ``array('q')`` (no Python object kept per period).

    Attributes:
        hil_ns: HIL time per completed period (ns).
        sync_wall_ns: ``time.perf_counter_ns()`` at each SYNC.
    """

    __slots__ = ("_acc", "hil_ns", "sync_wall_ns")

    def __init__(self) -> None:
        self.hil_ns = array.array("q")
        self.sync_wall_ns = array.array("q")
        self._acc = 0

    def add(self, started_ns: int) -> None:
        """Count the HIL's time from ``started_ns`` to now in the current period."""
        self._acc += perf_counter_ns() - started_ns

    def sync(self, started_ns: int) -> int:
        """A SYNC arrived: close the period (counting from ``started_ns``); returns now (ns)."""
        now = perf_counter_ns()
        if self.sync_wall_ns:
            self.hil_ns.append(self._acc + now - started_ns)
        self.sync_wall_ns.append(now)
        self._acc = 0
        return now

    def periods(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Per completed period: ``(wall_ns, hil_ns)``; the runtime's share is their
        difference."""
        wall: NDArray[np.int64] = np.diff(np.frombuffer(self.sync_wall_ns, dtype=np.int64)).astype(
            np.int64
        )
        hil = np.frombuffer(self.hil_ns, dtype=np.int64)[: wall.size]
        return wall, hil

    def summary(self) -> LockstepCost:
        """The periods' split: HIL time and the runtime's, per period and summed."""
        wall, hil = self.periods()
        rest = wall - hil
        return LockstepCost(
            periods=int(wall.size),
            hil_us=Distribution.spread(hil * 1e-3),
            runtime_us=Distribution.spread(rest * 1e-3),
            hil_s=float(np.sum(hil)) * 1e-9,
            runtime_s=float(np.sum(rest)) * 1e-9,
            wall_s=float(np.sum(wall)) * 1e-9,
        )


@dataclass(frozen=True, slots=True)
class LockstepCost:
    """Whose wall time the periods of a lockstep run were (``hil_lockstep`` of the HIL report).

    Attributes:
        periods: Completed SYNC periods.
        hil_us: The HIL's own time per period (us; p50, p99, max; NaN without a period).
        runtime_us: The rest of each period, the runtime's (us; p50, p99, max).
        hil_s: The HIL's time summed over the periods (s).
        runtime_s: The runtime's time summed (s).
        wall_s: The periods' wall time summed (s): ``hil_s + runtime_s``.
    """

    periods: int
    hil_us: Distribution
    runtime_us: Distribution
    hil_s: float
    runtime_s: float
    wall_s: float

    def to_json(self) -> dict[str, Any]:
        """``{"periods", "hil_us", "runtime_us", "hil_s", "runtime_s", "wall_s"}``."""
        return {
            "periods": self.periods,
            "hil_us": self.hil_us.to_json(),
            "runtime_us": self.runtime_us.to_json(),
            "hil_s": self.hil_s,
            "runtime_s": self.runtime_s,
            "wall_s": self.wall_s,
        }


class LockstepHil:
    """The HIL in lockstep over an in-process channel (one process, deterministic).

    Args:
        rig, q0_rad, terrain, period_s, vcu, keep_frames, tpdo_at_start, truth_rows: As
            :class:`HilCore`.
        fault_seed: Seed of the wire's random faults (:class:`~hil_sim.busfaults.BusFaults`).
        trace_path: Write the bus trace here (``.blf`` or ``.asc``), or None.

    Bus faults (:class:`~hil_sim.busfaults.BusFaults`, :meth:`inject`): every frame either way
    passes :attr:`bus_faults`; error frames go to the master one per SYNC; a bus-off adapter
    makes the master's sends raise (:meth:`reopen_master_bus` gives the master a working end
    again once the fault is cleared).

    Plant time: each SYNC advances the plant to one period past the SYNC; when the clock moves
    past the plant's time without a SYNC (a lost SYNC, an unplugged bus, a stalled loop) the
    plant follows the clock, so the drives and the arm go on moving with the master silent.

    Attributes:
        core: The HIL.
        clock: The simulated clock; give ``clock.now`` to the master and the clock to the loop.
        channel: The in-process channel (open another end on it to watch the bus).
        master_bus: The bus end for the master.
        bus_faults: The wire's faults.
        cost: The HIL's own wall time per SYNC period (:class:`HilCost`); it reads the wall
            clock only to measure, never to decide, so runs stay deterministic.
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
        trace_path: str | Path | None = None,
        tpdo_at_start: bool = True,
        fault_seed: int = 0,
        truth_rows: int = TRUTH_ROWS,
    ) -> None:
        self.core = HilCore(
            rig,
            q0_rad,
            terrain,
            period_s=period_s,
            vcu=vcu,
            keep_frames=keep_frames,
            tpdo_at_start=tpdo_at_start,
            truth_rows=truth_rows,
        )
        if trace_path is not None:
            self.core.trace = open_trace(trace_path)
        self.bus_faults = BusFaults(fault_seed)
        self.clock = LockstepClock(self._on_time)
        self.channel = InProcessChannel(f"excavator-hil-lockstep-{next(_channel_numbers)}")
        self._bus = ChannelBus(self.channel, clock=self.clock.now)
        self._period_s = period_s
        self.master_bus = LockstepBus(self.channel, self.clock, self.pump, period_s)
        self._pumping = False
        self._plant_t = 0.0
        self.cost = HilCost()
        self._send(self.core.pending_frames(0.0))  # power-on boot-up messages

    @property
    def period_s(self) -> float:
        """The SYNC period the HIL steps by when the master is silent (s)."""
        return self._period_s

    def reopen_master_bus(self) -> LockstepBus:
        """A new bus end for the master (the old one shut down): an adapter reopened after a
        bus-off. It is bus-off again while the fault lasts."""
        self.master_bus.shutdown()
        self.master_bus = LockstepBus(self.channel, self.clock, self.pump, self._period_s)
        self.master_bus.bus_off = self.bus_faults.bus_off
        return self.master_bus

    def _send(self, frames: list[Frame]) -> None:
        now = self.clock.now()
        faults = self.bus_faults
        for frame in frames:
            for arbitration_id, data in faults.to_master(frame, now) if faults.active else (frame,):
                self.core.log(arbitration_id, data, now, is_rx=False)
                self._bus.send_data(arbitration_id, data)

    def pump(self) -> None:
        """Handle every frame queued at the HIL's end, at the current simulated time."""
        if self._pumping:
            return
        self._pumping = True
        cost = self.cost
        started = perf_counter_ns()
        try:
            faults = self.bus_faults
            while True:
                msg = self._bus.take()
                if msg is None:
                    break
                now = self.clock.now()
                frame = (msg.arbitration_id, bytes(msg.data))
                if msg.arbitration_id == COB_SYNC:
                    started = cost.sync(started)
                    if faults.active and faults.error_frames_due():
                        self._bus.send(can.Message(is_error_frame=True, check=False))
                if faults.active:
                    for arrived in faults.to_hil(frame, now):
                        self._receive(arrived, now)
                else:
                    self._receive(frame, now)
        finally:
            self._pumping = False
            cost.add(started)

    def _receive(self, frame: Frame, now: float) -> None:
        """One frame reaches the HIL's nodes; a SYNC then advances the plant."""
        core = self.core
        arbitration_id, data = frame
        core.log(arbitration_id, data, now, is_rx=True)
        self._send(core.on_frame(arbitration_id, data, now))
        if arbitration_id == COB_SYNC:
            end = now + core.period_s
            if end > self._plant_t:
                core.advance(end - self._plant_t)
                self._plant_t = end

    def _on_time(self, t_s: float) -> None:
        self.pump()
        started = perf_counter_ns()
        if t_s > self._plant_t + 1e-9:  # no SYNC for longer than a period: the plant goes on
            self.core.advance(t_s - self._plant_t)
            self._plant_t = t_s
        faults = self.bus_faults
        if faults.active:
            to_hil, to_master = faults.due(t_s)
            for frame in to_hil:
                self._receive(frame, t_s)
            self._send_now(to_master)
        self._send(self.core.pending_frames(t_s))
        self.cost.add(started)

    def _send_now(self, frames: list[Frame]) -> None:
        """Frames to the master that already passed the bus faults (held back ones)."""
        now = self.clock.now()
        for arbitration_id, data in frames:
            self.core.log(arbitration_id, data, now, is_rx=False)
            self._bus.send_data(arbitration_id, data)

    def inject(self, kind: FaultKind, axis: int, param: float | None = None) -> None:
        """Inject a drive or bus fault now (:meth:`HilCore.inject`, :meth:`BusFaults.inject`).

        ``axis`` is the target axis (0..2) or -1 for the whole bus (bus faults only).

        Raises:
            ValueError: A host fault, a bad axis or parameter.
        """
        now = self.clock.now()
        if kind.layer == "bus":
            node = None if axis < 0 else self.core.nodes[axis].node_id
            self.bus_faults.inject(kind, node, param, now)
            self.master_bus.bus_off = self.bus_faults.bus_off
            return
        self._send(self.core.inject(kind, axis, param, now))

    def clear_faults(self) -> None:
        """Every injected cause gone (the drives' and the wire's); what the drives latched
        stays until the master resets it."""
        self.core.clear()
        self.bus_faults.clear()
        self.master_bus.bus_off = False

    def close(self) -> None:
        """Close the trace and both bus ends."""
        if self.core.trace is not None:
            self.core.trace.stop()
            self.core.trace = None
        self.master_bus.shutdown()
        self._bus.shutdown()

    def __enter__(self) -> LockstepHil:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
