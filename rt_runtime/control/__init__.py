"""Control: what runs the drives from plans (DESIGN.md "Loop, HIL and time").

The fixed-rate loop (:mod:`~rt_runtime.control.loop`) with its clock (:mod:`~.clock`), RT
settings (:mod:`~.rt`) and per-cycle telemetry (:mod:`~.telemetry`); the minimal trajectory
streamer (:mod:`rt_runtime.control.streamer`) that the HIL and ``excavator-rt hil`` use until the
executor replaces it. Nothing here imports ``hil_sim``: the runtime talks to drives only through
CAN frames.
"""

from rt_runtime.control.clock import Clock, MonotonicClock
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
from rt_runtime.control.streamer import (
    JointMotion,
    Setpoints,
    StreamResult,
    StreamStatus,
    TrajectoryStreamer,
    ruckig_motion,
    sextic_motion,
)
from rt_runtime.control.telemetry import LOOP_COLUMNS, Column, Telemetry

__all__ = [
    "LOOP_COLUMNS",
    "Clock",
    "Column",
    "CycleInfo",
    "FixedRateLoop",
    "JointMotion",
    "LoopAction",
    "LoopConfig",
    "LoopStats",
    "MonotonicClock",
    "OverrunEvent",
    "OverrunPolicy",
    "RtItem",
    "RtReport",
    "RtSettings",
    "Setpoints",
    "StreamResult",
    "StreamStatus",
    "Telemetry",
    "TrajectoryStreamer",
    "apply_rt",
    "restore_rt",
    "ruckig_motion",
    "sextic_motion",
]
