"""Teach and plan (Zhao et al.): from an operator's demonstrations to a faster, smooth cycle.

Modules: :mod:`~rt_runtime.teach.demos` (demonstrations in: CSV and CAN-trace readers with
validation), :mod:`~rt_runtime.teach.pipeline` (alignment, moving average, average, forward
kinematics, Douglas-Peucker, inverse kinematics, the minimum time-jerk cycle and the trench),
:mod:`~rt_runtime.teach.taught` (the taught job's file and its loader for the executor).
"""

from rt_runtime.teach.taught import TAUGHT_FILE, TaughtJob, load_taught

__all__ = ["TAUGHT_FILE", "TaughtJob", "load_taught"]
