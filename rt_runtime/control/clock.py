"""Where the control code's time comes from: the :class:`Clock` protocol and the wall clock.

Two clocks satisfy :class:`Clock`: :class:`MonotonicClock` (``time.monotonic`` with an
absolute-deadline sleep, for the rig and the real-time HIL) and
``hil_sim.harness.lockstep.LockstepClock`` (simulated seconds that move only when the loop
sleeps, for the lockstep HIL). The fixed-rate loop
(:mod:`rt_runtime.control.loop`) and the CAN master only ever read time through one of these.
"""

from __future__ import annotations

import time
from typing import Protocol

__all__ = ["Clock", "MonotonicClock"]


class Clock(Protocol):
    """A source of time the loop can read and sleep on.

    Attributes:
        realtime: True for a wall clock (work between cycles must not stop the cycle).
    """

    realtime: bool

    def now(self) -> float:
        """Current time (s)."""
        ...

    def sleep_until(self, t_s: float) -> None:
        """Return at ``t_s`` (at once if it has passed)."""
        ...


class MonotonicClock:
    """``time.monotonic`` with an absolute-deadline sleep: sleep, then spin the last ``spin_s``.

    The coarse sleep wakes up to a timer-slack plus scheduler latency late, so it aims
    ``spin_s`` early and the busy spin takes the remaining time exactly.

    Args:
        spin_s: Time before the deadline at which sleeping stops and spinning starts (s, >= 0).
    """

    realtime = True

    def __init__(self, spin_s: float = 2e-4) -> None:
        self.spin_s = spin_s

    def now(self) -> float:
        """``time.monotonic()`` (s). Safe inside the loop."""
        return time.monotonic()

    def sleep_until(self, t_s: float) -> None:
        """Sleep to ``t_s - spin_s``, then spin to ``t_s``. Safe inside the loop.

        Args:
            t_s: Absolute deadline on ``time.monotonic`` (s).
        """
        remaining = t_s - time.monotonic() - self.spin_s
        if remaining > 0.0:
            time.sleep(remaining)
        while time.monotonic() < t_s:
            pass
