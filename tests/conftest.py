"""Fixtures and helpers shared by several test modules."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import pytest

from rt_runtime.control.guard import (
    StrokeLimits,
    TraceCheck,
    check_setpoint_trace,
    rpdo1_setpoints,
)
from rt_runtime.planning.trench import TrenchPlanner, TrenchSession, load_task
from rt_runtime.rig import Rig

if TYPE_CHECKING:
    from hil_sim.sim import FaultKind
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
    def inject(self, kind: FaultKind, axis: int) -> None: ...


def fault_on_cycle(
    hil: _Injectable, fault: tuple[FaultKind, int, float] | None
) -> tuple[Callable[[int, float], None], list[float]]:
    """The executor's per-cycle hook injecting ``fault`` (kind, axis, seconds after the first
    cycle) into ``hil`` once, and the list it appends the injection time to."""
    start: list[float] = []
    injected: list[float] = []

    def on_cycle(_sync: int, now_s: float) -> None:
        if not start:
            start.append(now_s)
        if fault is not None and not injected and now_s - start[0] >= fault[2]:
            hil.inject(fault[0], fault[1])
            injected.append(now_s)

    return on_cycle, injected


def rpdo1_limit_check(rig: Rig, frames: Iterable[tuple[int, bytes]]) -> TraceCheck:
    """The RPDO1 setpoints of every drive in ``frames`` checked against the rig's stroke limits
    (2 ms SYNC period)."""
    nodes = [n for _, n in rig.can.node_ids]
    target, velocity = rpdo1_setpoints(frames, nodes)
    return check_setpoint_trace(target, StrokeLimits.from_rig(rig), 0.002, velocity_um_s=velocity)


def front_state(planner: PinnPlanner) -> np.ndarray:
    """A PINN planner's front buffers (row, out, retimed, scale) in one vector: what the C
    kernel's front and the Python path must leave bit for bit equal."""
    return np.concatenate([planner._row[0], planner._out[0], planner._retimed[0], planner._scale])
