"""A python-can bus that plays a scripted exchange, for byte-exact protocol tests.

Role: test equipment in the manner of canopen's protocol tests: a script of
``(TX, id, bytes)`` / ``(RX, id, bytes)`` steps. Every frame the code under test sends must be
the next ``TX`` step, byte for byte; ``recv`` hands out the ``RX`` steps that follow, in order.
When the script has no ``RX`` step ready, ``recv(timeout)`` returns None at once and advances
the attached :class:`ScriptClock` by ``timeout``, so timeouts happen in simulated time,
deterministically and without waiting. Any mismatch raises :class:`ScriptMismatch` (an
``AssertionError``) from ``send``, naming the step.

It is a real ``can.BusABC`` backend (``send`` and ``_recv_internal``; python-can's receive
policy on the script's clock, :class:`~rt_runtime.canbus.simtime.SimulatedTimeBus`), so it
exercises the same code paths as any backend.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Literal

import can

from rt_runtime.canbus.simtime import SimulatedTimeBus

__all__ = ["RX", "TX", "ScriptClock", "ScriptMismatch", "ScriptedBus", "Step"]

TX: Literal["TX"] = "TX"
RX: Literal["RX"] = "RX"

#: One step: direction, 11-bit COB-ID, payload.
Step = tuple[Literal["TX", "RX"], int, bytes]


class ScriptMismatch(AssertionError):
    """The code under test sent something other than the script's next step."""


class ScriptClock:
    """A simulated clock: ``clock()`` returns seconds; only :meth:`advance` moves it."""

    def __init__(self, start_s: float = 0.0) -> None:
        self.now_s = start_s

    def __call__(self) -> float:
        return self.now_s

    def advance(self, dt_s: float) -> None:
        """Move the clock forward by ``dt_s`` (>= 0)."""
        if dt_s < 0.0:
            raise ValueError(f"a clock does not go back ({dt_s} s)")
        self.now_s += dt_s


def _fmt(step: Step) -> str:
    return f"{step[0]} 0x{step[1]:03X} [{step[2].hex(' ')}]"


class ScriptedBus(SimulatedTimeBus):
    """Plays ``script``; see the module docstring.

    Args:
        script: The exchange, in order.
        clock: Advanced by the timeout of every ``recv`` that finds no ``RX`` step ready.
    """

    def __init__(self, script: Iterable[Step] = (), clock: ScriptClock | None = None) -> None:
        self.steps: list[Step] = list(script)
        self.position = 0
        self.clock = clock
        self.sent: list[tuple[int, bytes]] = []
        self.channel_info = "scripted"
        super().__init__(channel="scripted")
        # Nothing to release: python-can's shutdown bookkeeping is done now, so collecting an
        # unclosed script does not warn (the script itself keeps working).
        super().shutdown()

    def now_s(self) -> float:
        """The script's clock (0.0 without one: then one empty poll is the whole timeout)."""
        return self.clock.now_s if self.clock is not None else 0.0

    def extend(self, steps: Iterable[Step]) -> None:
        """Append steps to the script."""
        self.steps.extend(steps)

    @property
    def remaining(self) -> list[Step]:
        """Steps not played yet."""
        return self.steps[self.position :]

    def assert_done(self) -> None:
        """Raise :class:`ScriptMismatch` unless every step was played."""
        if self.position != len(self.steps):
            left = "\n  ".join(_fmt(s) for s in self.remaining[:8])
            raise ScriptMismatch(f"{len(self.remaining)} steps not played, first:\n  {left}")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        got: Step = (TX, msg.arbitration_id, bytes(msg.data))
        self.sent.append((msg.arbitration_id, bytes(msg.data)))
        if self.position >= len(self.steps):
            raise ScriptMismatch(f"step {self.position}: sent {_fmt(got)} after the script ended")
        want = self.steps[self.position]
        if got != want or msg.is_extended_id:
            raise ScriptMismatch(
                f"step {self.position}: sent {_fmt(got)}, script says {_fmt(want)}"
            )
        self.position += 1

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.position < len(self.steps) and self.steps[self.position][0] == RX:
            _, can_id, data = self.steps[self.position]
            self.position += 1
            stamp = self.clock.now_s if self.clock is not None else 0.0
            msg = can.Message(
                arbitration_id=can_id, is_extended_id=False, data=data, timestamp=stamp
            )
            return msg, False
        if timeout is None:
            nxt = _fmt(self.steps[self.position]) if self.position < len(self.steps) else "end"
            raise ScriptMismatch(f"step {self.position}: recv() would block forever; next {nxt}")
        if self.clock is not None:
            self.clock.advance(timeout)
        return None, False

