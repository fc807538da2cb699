"""Control: what runs the drives from plans (DESIGN.md "Loop, HIL and time").

For now the minimal trajectory streamer (:mod:`rt_runtime.control.streamer`) that the HIL and
``excavator-rt hil`` use; the executor of issue 7 (fixed-rate loop, limit guard, monitors) will
replace it. Nothing here imports ``hil_sim``: the runtime talks to drives only through CAN frames.
"""

from rt_runtime.control.streamer import (
    Clock,
    JointMotion,
    MonotonicClock,
    Setpoints,
    StreamResult,
    StreamStatus,
    TrajectoryStreamer,
    ruckig_motion,
    sextic_motion,
)

__all__ = [
    "Clock",
    "JointMotion",
    "MonotonicClock",
    "Setpoints",
    "StreamResult",
    "StreamStatus",
    "TrajectoryStreamer",
    "ruckig_motion",
    "sextic_motion",
]
