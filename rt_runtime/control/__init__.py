"""Control: what runs the drives from plans (DESIGN.md "Loop, HIL and time").

The fixed-rate loop (:mod:`~rt_runtime.control.loop`) with its clock (:mod:`~.clock`), RT
settings (:mod:`~.rt`) and per-cycle telemetry (:mod:`~.telemetry`); the executor
(:mod:`~.executor`) that runs a trench job in it through the ruckig limit guard (:mod:`~.guard`),
planning the next dig in a planner process on a real-time clock (:mod:`~.planner_worker`).
Nothing here imports ``hil_sim``: the runtime talks to drives only through CAN frames.

The executor's names load on first use (``from rt_runtime.control import Executor`` works): they
pull in the trench planner (onnxruntime, scipy, ~1 s), which the loop alone, the HIL process
and the client commands do not need.
"""

from typing import Any

from rt_runtime.control.clock import Clock, MonotonicClock
from rt_runtime.control.guard import (
    GuardState,
    LimitGuard,
    StrokeLimits,
    TraceCheck,
    check_setpoint_trace,
    rpdo1_setpoints,
)
from rt_runtime.control.loop import (
    CycleInfo,
    FixedRateLoop,
    LoopAction,
    LoopConfig,
    LoopStats,
    OverrunEvent,
    OverrunPolicy,
)
from rt_runtime.control.rt import RtItem, RtReport, RtSettings, apply_rt, restore_rt
from rt_runtime.control.telemetry import LOOP_COLUMNS, Column, Telemetry

_LAZY = {
    "EXECUTOR_COLUMNS": "rt_runtime.control.executor",
    "DigRecord": "rt_runtime.control.executor",
    "ExecStatus": "rt_runtime.control.executor",
    "Executor": "rt_runtime.control.executor",
    "ExecutorConfig": "rt_runtime.control.executor",
    "ExecutorResult": "rt_runtime.control.executor",
    "Phase": "rt_runtime.control.executor",
    "StopRequest": "rt_runtime.control.executor",
    "executor_telemetry": "rt_runtime.control.executor",
    "DigPlan": "rt_runtime.control.planner_worker",
    "InlinePlanner": "rt_runtime.control.planner_worker",
    "PlannerSpec": "rt_runtime.control.planner_worker",
    "ProcessPlanner": "rt_runtime.control.planner_worker",
    "Recorded": "rt_runtime.control.planner_worker",
    "SessionDriver": "rt_runtime.control.planner_worker",
}


def __getattr__(name: str) -> Any:
    """Load the executor's names on first use (see the module docstring)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'rt_runtime.control' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)


__all__ = [
    "EXECUTOR_COLUMNS",
    "LOOP_COLUMNS",
    "Clock",
    "Column",
    "CycleInfo",
    "DigPlan",
    "DigRecord",
    "ExecStatus",
    "Executor",
    "ExecutorConfig",
    "ExecutorResult",
    "FixedRateLoop",
    "GuardState",
    "InlinePlanner",
    "LimitGuard",
    "LoopAction",
    "LoopConfig",
    "LoopStats",
    "MonotonicClock",
    "OverrunEvent",
    "OverrunPolicy",
    "Phase",
    "PlannerSpec",
    "ProcessPlanner",
    "Recorded",
    "RtItem",
    "RtReport",
    "RtSettings",
    "SessionDriver",
    "StopRequest",
    "StrokeLimits",
    "Telemetry",
    "TraceCheck",
    "apply_rt",
    "check_setpoint_trace",
    "executor_telemetry",
    "restore_rt",
    "rpdo1_setpoints",
]
