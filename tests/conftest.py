"""Fixtures and helpers shared by several test modules."""

from __future__ import annotations

import dataclasses
import gc
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import can
import numpy as np
import pytest

from rt_runtime.canbus import CanMaster
from rt_runtime.control.guard import (
    StrokeLimits,
    TraceCheck,
    check_setpoint_trace,
    rpdo1_setpoints,
)
from rt_runtime.planning.trench import TrenchPlanner, TrenchSession, load_task
from rt_runtime.rig import Rig

if TYPE_CHECKING:
    from hil_sim.sim import FaultKind, Truth
    from rt_runtime.control.executor import ExecutorResult
    from rt_runtime.planning.pinn import PinnPlanner


@pytest.fixture(scope="module")
def pending(rig: Rig) -> tuple[TrenchPlanner, Any, dict[str, Any]]:
    """Task A's planner and the session state with the first dig planned and pending (on the
    module's ``rig`` fixture)."""
    planner = TrenchPlanner(rig)
    task = load_task("A", rig)
    session = planner.start(task)
    session.next_dig()
    return planner, task, session.state()


def restore_pending(
    planner: TrenchPlanner, task: Any, state: dict[str, Any]
) -> tuple[TrenchSession, np.ndarray]:
    """The session restored from ``state`` (a dig must be pending) and the pending dig's entry
    pose ``q_start_rad``."""
    session = TrenchSession.restore(planner, task, state)
    assert session.pending is not None
    return session, np.asarray(session.pending.problem.q_start_rad)


class _Injectable(Protocol):
    def inject(self, kind: FaultKind, axis: int, param: float | None = None) -> None: ...


#: A fault to inject: kind, axis (-1: the bus), seconds after the first cycle, and optionally
#: its parameter.
Fault = tuple["FaultKind", int, float] | tuple["FaultKind", int, float, float]


def fault_on_cycle(
    hil: _Injectable, fault: Fault | None
) -> tuple[Callable[[int, float], None], list[float]]:
    """The executor's per-cycle hook injecting ``fault`` (kind, axis, seconds after the first
    cycle, optionally its parameter) into ``hil`` once, and the list it appends the injection
    time to."""
    start: list[float] = []
    injected: list[float] = []

    def on_cycle(_sync: int, now_s: float) -> None:
        if not start:
            start.append(now_s)
        if fault is not None and not injected and now_s - start[0] >= fault[2]:
            hil.inject(fault[0], fault[1], fault[3] if len(fault) > 3 else None)
            injected.append(now_s)

    return on_cycle, injected


@dataclass
class FaultRun:
    """One executor run on a transport (see :func:`run_on_lockstep`, :func:`run_on_bridge`).

    Attributes:
        result: The executor's result.
        master: The master after the run.
        injected: Simulated or monotonic time of the injection (empty: not injected).
        frames: Every frame of the bus ``(id, data)`` in bus order, as the HIL saw it.
        rest_rate_m_s: The plant's true stroke rates at the end ``(3,)``.
        truth: The HIL's truth (the plant at every SYNC).
        extra: The transport's own report keys (the bridge's HIL process statistics).
    """

    result: ExecutorResult
    master: CanMaster
    injected: list[float]
    frames: list[tuple[int, bytes]]
    rest_rate_m_s: np.ndarray
    truth: Truth
    extra: dict[str, Any] = field(default_factory=dict)


#: The bridge's HIL process stops by itself after this long even if a test dies.
BRIDGE_MAX_WALL_S = 60.0
#: The bridge runs on a shared test machine with a HIL process that is not real time: the
#: drives' SYNC/RPDO watchdog and the heartbeat timeouts (both ways) widened to 0.5 s, the
#: executor's stale-feedback limit to 100 cycles and the overrun policy to 50 in a row (the
#: rig's values are for a rig PC with SCHED_FIFO). The contract under test is the protocol and
#: the executor's reactions, not this machine's scheduling.
BRIDGE_PATIENCE_S = 0.5


def run_on_lockstep(
    rig: Rig,
    pending: tuple[TrenchPlanner, Any, dict[str, Any]],
    fault: Fault | None = None,
    trace: Path | None = None,
) -> FaultRun:
    """The pending dig from its entry on the lockstep HIL, ``fault`` injected at a time after
    the first cycle; the rig's own timeouts."""
    from hil_sim.harness.lockstep import LockstepHil
    from hil_sim.harness.scenario import NO_RT
    from rt_runtime.control import FixedRateLoop, LoopConfig
    from rt_runtime.control.executor import Executor, ExecutorConfig, executor_telemetry

    session, q0 = restore_pending(*pending)
    with LockstepHil(rig, q0, keep_frames=True, trace_path=trace) as hil:
        master = CanMaster(hil.master_bus, rig, period_s=0.002, react_to_faults=False)
        master.boot(hil.clock.now, 1.0)
        master.enable(hil.clock.now, 1.0)
        on_cycle, injected = fault_on_cycle(hil, fault)
        loop = FixedRateLoop(hil.clock, LoopConfig(rt=NO_RT), executor_telemetry(20_000))
        config = ExecutorConfig(max_digs=1)
        result = Executor(master, rig, loop, session, config, on_cycle=on_cycle).run()
        return FaultRun(
            result,
            master,
            injected,
            list(hil.core.frames),
            np.array(hil.core.plant.stroke_rate_m_s, dtype=np.float64),
            hil.core.truth(),
        )


def patient(rig: Rig) -> Rig:
    """The rig with the bridge's heartbeat timeout both ways (:data:`BRIDGE_PATIENCE_S`)."""
    drives = dataclasses.replace(rig.drives, heartbeat_timeout_s=BRIDGE_PATIENCE_S)
    return dataclasses.replace(rig, drives=drives)


def run_on_bridge(
    rig: Rig,
    pending: tuple[TrenchPlanner, Any, dict[str, Any]],
    fault: Fault | None = None,
    trace: Path | None = None,
    *,
    rig_name: str = "scale_model",
) -> FaultRun:
    """The pending dig from its entry on the real-time HIL in its own process over the
    127.0.0.1 bridge, on the wall clock, with the bridge's patience (:data:`BRIDGE_PATIENCE_S`);
    plans in the executor's planner process when there is no fault. ``trace`` (``.blf``) is
    written by the HIL process and always kept for :attr:`FaultRun.frames`."""
    import tempfile

    from hil_sim.harness.realtime import RealtimeHilProcess
    from hil_sim.harness.scenario import NO_RT
    from rt_runtime.control import (
        FixedRateLoop,
        LoopConfig,
        OverrunPolicy,
        RtSettings,
        apply_rt,
        restore_rt,
    )
    from rt_runtime.control.executor import Executor, ExecutorConfig, executor_telemetry

    session, q0 = restore_pending(*pending)
    with tempfile.TemporaryDirectory(prefix="excavator-bridge-") as tmp:
        trace_path = trace if trace is not None else Path(tmp) / "bus.blf"
        hil = RealtimeHilProcess.start(
            rig_name=rig_name,
            q0_rad=q0,
            max_wall_s=BRIDGE_MAX_WALL_S,
            sync_timeout_s=BRIDGE_PATIENCE_S,
            trace_path=trace_path,
        )
        try:
            master = CanMaster(hil.master_bus, patient(rig), period_s=0.002, react_to_faults=False)
            on_cycle, injected = fault_on_cycle(hil, fault)
            config = ExecutorConfig(max_digs=1, plan_in_worker=fault is None, stale_cycles=100)
            loop = FixedRateLoop(
                hil.clock,
                LoopConfig(rt=NO_RT, overrun=OverrunPolicy(max_consecutive=50)),
                executor_telemetry(30_000),
            )
            # As the product does: executor (planner process) first, RT settings before boot
            # (not between enable and the first cycle), then boot, enable, run.
            executor = Executor(master, rig, loop, session, config, on_cycle=on_cycle)
            report = apply_rt(RtSettings())
            try:
                master.boot(hil.clock.now, 2.0)
                master.enable(hil.clock.now, 2.0)
                result = executor.run()
            finally:
                executor.close()
                restore_rt(report)
            truth, _, _, extra = hil.finish()
        finally:
            hil.close()
        extra = {**extra, "rt": report.as_dict()}
        frames = [(m.arbitration_id, bytes(m.data)) for m in can.BLFReader(str(trace_path))]
    # The true rates at the end: the last two SYNCs' true strokes (the process's truth).
    dt = np.diff(truth.t_s[-2:])
    rate = np.diff(truth.stroke_m[-2:], axis=0)[0] / dt[0] if dt.size and dt[0] > 0 else np.zeros(3)
    return FaultRun(result, master, injected, frames, rate, truth, extra)


def rpdo1_limit_check(rig: Rig, frames: Iterable[tuple[int, bytes]]) -> TraceCheck:
    """The RPDO1 setpoints of every drive in ``frames``, in bus order (the arm's three, then the
    swing where the rig has one), checked against the rig's stroke limits (2 ms SYNC period)."""
    from rt_runtime import axes

    ids = dict(rig.can.node_ids)
    nodes = [ids[name] for name in axes.names(rig)]
    target, velocity = rpdo1_setpoints(frames, nodes)
    return check_setpoint_trace(target, StrokeLimits.from_rig(rig), 0.002, velocity_um_s=velocity)


def front_state(planner: PinnPlanner) -> np.ndarray:
    """A PINN planner's front buffers (row, out, retimed, scale) in one vector: what the C
    kernel's front and the Python path must leave bit for bit equal."""
    return np.concatenate([planner._row[0], planner._out[0], planner._retimed[0], planner._scale])


def max_sync_gap_s(trace_dir: Path, arbitration_id: int = 0x080) -> float:
    """The largest gap between the frames of one id (by default the SYNCs a master sent) over
    the closed BLF traces in ``trace_dir`` (s)."""
    gap = 0.0
    for path in sorted(trace_dir.glob("*.blf")):
        stamps = np.array(
            [m.timestamp for m in can.BLFReader(str(path)) if m.arbitration_id == arbitration_id]
        )
        if stamps.size > 1:
            gap = max(gap, float(np.diff(stamps).max()))
    return gap


def host_stall(
    fault: str,
    trace_dir: Path,
    rig: Rig,
    hil_process: dict[str, Any] | None = None,
    stale_window_s: float | None = None,
) -> str | None:
    """Why a daemon's latched ``fault`` is the host's doing, from the daemon's own evidence
    and the HIL process's; None where it is not.

    The host's doing: the drives' SYNC watchdog EMCY while the daemon's trace (closed, in
    ``trace_dir``) shows the master sent no SYNC for longer than that watchdog, or the loop's
    own overrun stop (it measured that many cycles in a row started late). Also stale feedback
    (no TPDO1 for the loop's ``stale_window_s``) while the real-time HIL's own statistics
    (``hil_process``, :meth:`RealtimeHilProcess.finish`) show it answered a SYNC that long or
    longer after the master sent it: the drives' stand-in was stopped, which drive firmware on
    a rig never is. A shared build machine stops processes for tens of milliseconds at times;
    the daemon is right to stop the arm then, and a test that runs it against the real-time
    HIL runs its scenario again.
    """
    gap_s = max_sync_gap_s(trace_dir)
    watchdog_s = rig.drives.sync_timeout_s
    if "RPDO_TIMEOUT (0x8250)" in fault and gap_s > watchdog_s:
        return (
            f"the master sent no SYNC for {gap_s * 1e3:.1f} ms (the drives' watchdog "
            f"{watchdog_s * 1e3:.0f} ms): {fault[:200]}"
        )
    if "overrun_stop" in fault:
        return f"the loop's overrun stop (largest SYNC gap {gap_s * 1e3:.1f} ms): {fault[:200]}"
    if "stale feedback" in fault and hil_process is not None and stale_window_s is not None:
        late_s = float(hil_process["sync_handling_us"]["max"]) * 1e-6
        if late_s >= stale_window_s:
            return (
                f"the HIL process answered a SYNC {late_s * 1e3:.1f} ms after the master sent "
                f"it (the stale window {stale_window_s * 1e3:.0f} ms; largest SYNC gap "
                f"{gap_s * 1e3:.1f} ms): {fault[:200]}"
            )
    return None


def pytest_unconfigure(config: pytest.Config) -> None:
    """What the runs in this process froze out of the collector's reach (the daemon's runner
    freezes what it prepared) collected before the interpreter ends, so no native object
    outlives its extension module (nanobind reports those as leaks)."""
    gc.unfreeze()
    gc.collect()
