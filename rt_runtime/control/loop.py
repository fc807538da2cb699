"""The fixed-rate loop: the one place that owns time (read -> update -> write in the step).

:class:`FixedRateLoop` calls ``step(info)`` once per cycle at absolute deadlines
``t0 + k * period_s`` on a :class:`~rt_runtime.control.clock.Clock` (sleep, then a short spin on
:class:`~rt_runtime.control.clock.MonotonicClock`; simulated time on the lockstep HIL's clock).
Deadlines never drift: each is computed from ``t0``, never from the previous wake-up.

Overruns. A cycle whose start is later than ``deadline + late_fraction * period_s`` is an overrun:
it is counted, its lateness recorded (and logged outside the hot path), and the deadlines that
passed meanwhile are skipped: the next deadline is the first one after the late start on the
*original* grid (re-phase), so the loop never runs a burst of back-to-back catch-up cycles.
After ``max_consecutive`` overruns in a row :attr:`CycleInfo.safe_stop` becomes True and stays
True; the loop keeps calling the step, which must then bring the axes to rest (a jerk-limited
stop needs cycles) and return :attr:`LoopAction.STOP`.

Per cycle the loop records ``cycle``, ``t_s``, ``lateness_s``, ``exec_s`` (step start to end) and
``overrun`` in a preallocated :class:`~rt_runtime.control.telemetry.Telemetry`; the step adds its
own columns. One :class:`CycleInfo` is updated in place each cycle: the loop allocates nothing per
cycle beyond the floats the clock returns.

RT settings (:mod:`rt_runtime.control.rt`) are applied on the calling thread at the start of
:meth:`FixedRateLoop.run` and restored when it returns or raises; refusals are in
:attr:`LoopStats.rt`. Applying them takes tens of milliseconds (``mlockall`` faults in every
page of the process, ``gc.collect`` walks the heap: about 0.1 s in a process with onnxruntime
loaded), longer than a drive's SYNC watchdog: with drives already enabled call
:meth:`FixedRateLoop.acquire_rt` *before* enabling them (same thread as :meth:`run`); ``run``
then keeps those settings and :meth:`FixedRateLoop.release_rt` undoes them.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime.control.clock import Clock
from rt_runtime.control.rt import RtPlatform, RtReport, RtSettings, apply_rt, restore_rt
from rt_runtime.control.telemetry import Telemetry
from rt_runtime.errors import ConfigurationError

__all__ = [
    "CycleInfo",
    "FixedRateLoop",
    "LoopAction",
    "LoopConfig",
    "LoopStats",
    "OverrunEvent",
    "OverrunPolicy",
]

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Overruns kept for logging between two log flushes (more are counted, not itemised).
_OVERRUN_LOG_CAPACITY = 64
#: Least clock time between two in-loop log flushes (s).
_LOG_INTERVAL_S = 1.0
#: Default telemetry rows when the caller gives none (65 s at 1 kHz, 131 s at 500 Hz).
DEFAULT_TELEMETRY_CAPACITY = 65_536


@dataclass(frozen=True, slots=True)
class OverrunPolicy:
    """When a cycle is an overrun and when overruns stop the machine.

    Attributes:
        late_fraction: A cycle starting later than ``deadline + late_fraction * period_s`` is an
            overrun (0 < late_fraction).
        max_consecutive: This many overruns in a row set :attr:`CycleInfo.safe_stop` (>= 1).

    Raises:
        ConfigurationError: A value outside the allowed range.
    """

    late_fraction: float = 0.5
    max_consecutive: int = 5

    def __post_init__(self) -> None:
        if not (self.late_fraction > 0.0 and math.isfinite(self.late_fraction)):
            raise ConfigurationError(
                f"overrun.late_fraction is {self.late_fraction}; allowed: a finite number > 0"
            )
        if self.max_consecutive < 1:
            raise ConfigurationError(
                f"overrun.max_consecutive is {self.max_consecutive}; allowed: an integer >= 1"
            )


@dataclass(frozen=True, slots=True)
class LoopConfig:
    """The loop's period and policies.

    Attributes:
        period_s: Cycle period (s), > 0; default 2 ms (500 Hz); 1 ms works.
        spin_s: Busy-spin before each deadline (s), 0 <= spin_s < period_s; applied to a clock
            that has a ``spin_s`` attribute (:class:`MonotonicClock`) while :meth:`run` runs.
        rt: RT settings applied while running.
        overrun: Overrun policy.

    Raises:
        ConfigurationError: A value outside the allowed range.
    """

    period_s: float = 0.002
    spin_s: float = 2e-4
    rt: RtSettings = field(default_factory=RtSettings)
    overrun: OverrunPolicy = field(default_factory=OverrunPolicy)

    def __post_init__(self) -> None:
        if not (self.period_s > 0.0 and math.isfinite(self.period_s)):
            raise ConfigurationError(f"period_s is {self.period_s}; allowed: a finite number > 0")
        if not 0.0 <= self.spin_s < self.period_s:
            raise ConfigurationError(
                f"spin_s is {self.spin_s}; allowed: 0 <= spin_s < period_s ({self.period_s})"
            )


class LoopAction(IntEnum):
    """What the step tells the loop."""

    CONTINUE = 0
    STOP = 1


class CycleInfo:
    """The current cycle, one preallocated object updated in place (do not keep references).

    Attributes:
        index: Cycle index on the period grid: ``deadline_s = t0 + index * period_s``; it jumps
            by ``1 + skipped`` after an overrun.
        count: Steps called before this one (0 on the first cycle; no gaps).
        deadline_s: This cycle's deadline (clock, s).
        start_s: When the cycle started (clock, s).
        lateness_s: ``start_s - deadline_s`` (s).
        period_s: The nominal period (s).
        overrun: This cycle is an overrun.
        skipped: Deadlines skipped by the re-phase after this overrun (0 otherwise).
        consecutive_overruns: Overruns in a row ending with this cycle (0 if it is on time).
        overruns: Overruns since :meth:`FixedRateLoop.run` started.
        safe_stop: Set by the overrun policy and stays True: the step must stop safely.
    """

    __slots__ = (
        "consecutive_overruns",
        "count",
        "deadline_s",
        "index",
        "lateness_s",
        "overrun",
        "overruns",
        "period_s",
        "safe_stop",
        "skipped",
        "start_s",
    )

    def __init__(self, period_s: float = 0.0) -> None:
        self.period_s = period_s
        self.reset()

    def reset(self) -> None:
        """Back to the state before the first cycle."""
        self.index = 0
        self.count = 0
        self.deadline_s = 0.0
        self.start_s = 0.0
        self.lateness_s = 0.0
        self.overrun = False
        self.skipped = 0
        self.consecutive_overruns = 0
        self.overruns = 0
        self.safe_stop = False


@dataclass(frozen=True, slots=True)
class OverrunEvent:
    """One overrun, for the log and the stats.

    Attributes:
        index: Cycle index on the period grid.
        lateness_s: How late the cycle started (s).
        skipped: Deadlines skipped by the re-phase.
    """

    index: int
    lateness_s: float
    skipped: int


@dataclass(frozen=True, slots=True)
class LoopStats:
    """What one :meth:`FixedRateLoop.run` did.

    Attributes:
        period_s: Nominal period (s).
        cycles: Steps called.
        overruns: Overrun cycles.
        skipped: Deadlines skipped by re-phasing, in total.
        max_consecutive_overruns: Longest run of overruns in a row.
        safe_stop: The overrun policy requested a safe stop.
        stopped_by_step: The step returned STOP (else ``max_cycles`` ended the run).
        max_lateness_s: Largest lateness (s).
        max_exec_s: Longest step (s).
        overrun_events: The first overruns (index, lateness, skipped), up to 64 per log flush.
        lateness_s: Lateness of the recorded cycles, cycle order (the telemetry's last
            ``capacity`` cycles), ``(n,)``.
        exec_s: Step execution time of the same cycles, ``(n,)``.
        t_s: Start time of the same cycles (clock, s), ``(n,)``.
        cycle: Grid index of the same cycles, ``(n,)``.
        rt: What the OS granted and refused.
    """

    period_s: float
    cycles: int
    overruns: int
    skipped: int
    max_consecutive_overruns: int
    safe_stop: bool
    stopped_by_step: bool
    max_lateness_s: float
    max_exec_s: float
    overrun_events: tuple[OverrunEvent, ...]
    lateness_s: FloatArray
    exec_s: FloatArray
    t_s: FloatArray
    cycle: NDArray[np.int64]
    rt: RtReport

    def period_jitter_s(self) -> FloatArray:
        """Actual minus nominal period between consecutive grid cycles (s), ``(m,)``.

        Pairs separated by a skip are left out (their gap is a re-phase, not jitter).
        """
        if self.t_s.size < 2:
            return np.zeros(0)
        adjacent = np.diff(self.cycle) == 1
        return np.asarray(np.diff(self.t_s)[adjacent] - self.period_s, dtype=np.float64)

    def summary(self) -> dict[str, Any]:
        """JSON-able counters (no arrays)."""
        return {
            "period_s": self.period_s,
            "cycles": self.cycles,
            "overruns": self.overruns,
            "skipped": self.skipped,
            "max_consecutive_overruns": self.max_consecutive_overruns,
            "safe_stop": self.safe_stop,
            "max_lateness_s": self.max_lateness_s,
            "max_exec_s": self.max_exec_s,
            "rt": self.rt.as_dict(),
        }


class FixedRateLoop:
    """Calls a step at a fixed rate on absolute deadlines, with overrun handling and telemetry.

    Args:
        clock: Time source (wall or simulated).
        config: Period and policies.
        telemetry: Ring buffer to record into (the step's columns declared by its owner); a
            loop-only one of :data:`DEFAULT_TELEMETRY_CAPACITY` rows when None.
        rt_platform: OS calls for the RT settings (tests inject refusals); the real OS when None.

    Attributes:
        clock: The time source.
        config: The configuration.
        telemetry: The ring buffer (cleared at the start of each run).
        info: The one :class:`CycleInfo` handed to the step.
        stats: The last run's :class:`LoopStats` (None before the first run ends).
    """

    def __init__(
        self,
        clock: Clock,
        config: LoopConfig | None = None,
        telemetry: Telemetry | None = None,
        *,
        rt_platform: RtPlatform | None = None,
    ) -> None:
        self.clock = clock
        self.config = config if config is not None else LoopConfig()
        self.telemetry = (
            telemetry if telemetry is not None else Telemetry(DEFAULT_TELEMETRY_CAPACITY)
        )
        self.info = CycleInfo(self.config.period_s)
        self.stats: LoopStats | None = None
        self._rt_platform = rt_platform
        self._ev_index = np.zeros(_OVERRUN_LOG_CAPACITY, dtype=np.int64)
        self._ev_lateness = np.zeros(_OVERRUN_LOG_CAPACITY, dtype=np.float64)
        self._ev_skipped = np.zeros(_OVERRUN_LOG_CAPACITY, dtype=np.int64)
        self._ev_count = 0
        self._ev_lost = 0
        self._events: list[OverrunEvent] = []
        self._held_rt: RtReport | None = None

    def acquire_rt(self) -> RtReport:
        """Apply the RT settings now and keep them across runs until :meth:`release_rt`.

        Call outside the loop, before enabling drives (applying takes tens of ms), from the
        thread that calls :meth:`run` (the scheduler and affinity are per thread). Calling it
        again while held returns the held report.

        Returns:
            What the OS granted and refused (also in each run's :attr:`LoopStats.rt`).
        """
        if self._held_rt is None:
            self._held_rt = apply_rt(self.config.rt, self._rt_platform)
        return self._held_rt

    def release_rt(self) -> None:
        """Undo :meth:`acquire_rt` (no-op when nothing is held). Same thread as acquire."""
        if self._held_rt is not None:
            restore_rt(self._held_rt)
            self._held_rt = None

    def _flush_overrun_log(self) -> None:
        """Log the overruns kept since the last flush (one line each), then forget them."""
        n = min(self._ev_count, _OVERRUN_LOG_CAPACITY)
        for i in range(n):
            ev = OverrunEvent(
                int(self._ev_index[i]), float(self._ev_lateness[i]), int(self._ev_skipped[i])
            )
            if len(self._events) < _OVERRUN_LOG_CAPACITY:
                self._events.append(ev)
            log.warning(
                "loop overrun at cycle %d: %.1f us late (period %.1f us), %d deadline(s) skipped",
                ev.index,
                ev.lateness_s * 1e6,
                self.config.period_s * 1e6,
                ev.skipped,
            )
        if self._ev_lost:
            log.warning("loop: %d more overrun(s) not itemised", self._ev_lost)
        self._ev_count = 0
        self._ev_lost = 0

    def run(
        self,
        step: Callable[[CycleInfo], LoopAction],
        *,
        max_cycles: int | None = None,
        idle: Callable[[], None] | None = None,
    ) -> LoopStats:
        """Run ``step`` once per cycle until it returns STOP or ``max_cycles`` steps ran.

        The first deadline is the clock's time at the start. RT settings are applied on the
        calling thread first and restored on return (or when the step raises, which ends the
        loop and propagates: the step should return status, not raise), unless
        :meth:`acquire_rt` holds them already (then they stay applied).

        Args:
            step: Called with :attr:`info` each cycle; returns :class:`LoopAction`.
            max_cycles: Stop after this many steps (None: only the step stops the loop).
            idle: Called after each step that continues, outside its timing (``exec_s``),
                before the wait for the next deadline: work between cycles.

        Returns:
            The run's statistics (also in :attr:`stats`).

        Raises:
            ConfigurationError: ``max_cycles`` below 0.
        """
        if max_cycles is not None and max_cycles < 0:
            raise ConfigurationError(f"max_cycles is {max_cycles}; allowed: an integer >= 0")
        cfg = self.config
        period = cfg.period_s
        late_limit = cfg.overrun.late_fraction * period
        max_consecutive = cfg.overrun.max_consecutive
        clock = self.clock
        tel = self.telemetry
        info = self.info
        info.period_s = period
        info.reset()
        tel.clear()
        self._ev_count = 0
        self._ev_lost = 0
        self._events = []
        ev_index, ev_lateness, ev_skipped = self._ev_index, self._ev_lateness, self._ev_skipped
        limit = max_cycles if max_cycles is not None else -1

        old_spin = getattr(clock, "spin_s", None)
        if old_spin is not None:
            clock.spin_s = cfg.spin_s  # type: ignore[attr-defined]

        cycles = 0
        overruns = 0
        skipped_total = 0
        max_run = 0
        max_lateness = -math.inf
        max_exec = 0.0
        stopped_by_step = False
        held = self._held_rt is not None
        report = self._held_rt if self._held_rt is not None else apply_rt(cfg.rt, self._rt_platform)
        try:
            t0 = clock.now()
            next_log_s = t0 + _LOG_INTERVAL_S
            k = 0
            consecutive = 0
            while cycles != limit:
                deadline = t0 + k * period
                clock.sleep_until(deadline)
                start = clock.now()
                lateness = start - deadline
                skipped = 0
                overrun = lateness > late_limit
                if overrun:
                    # Deadlines d_{k+1} .. d_{k+skipped} are already behind the start: skip them so
                    # the next deadline is the first one still ahead on the original grid.
                    skipped = int(lateness // period)
                    overruns += 1
                    skipped_total += skipped
                    consecutive += 1
                    if consecutive > max_run:
                        max_run = consecutive
                    if consecutive >= max_consecutive:
                        info.safe_stop = True
                    n_ev = self._ev_count
                    if n_ev < _OVERRUN_LOG_CAPACITY:
                        ev_index[n_ev] = k
                        ev_lateness[n_ev] = lateness
                        ev_skipped[n_ev] = skipped
                        self._ev_count = n_ev + 1
                    else:
                        self._ev_lost += 1
                else:
                    consecutive = 0
                if lateness > max_lateness:
                    max_lateness = lateness
                info.index = k
                info.count = cycles
                info.deadline_s = deadline
                info.start_s = start
                info.lateness_s = lateness
                info.overrun = overrun
                info.skipped = skipped
                info.consecutive_overruns = consecutive
                info.overruns = overruns
                tel = self.telemetry  # the step may hand the next rows to another buffer
                tel.begin(k, start, lateness, overrun)
                action = step(info)
                end = clock.now()
                exec_s = end - start
                tel.end(exec_s)
                if exec_s > max_exec:
                    max_exec = exec_s
                cycles += 1
                k += 1 + skipped
                if action == LoopAction.STOP:
                    stopped_by_step = True
                    break
                if idle is not None:
                    idle()
                if self._ev_count and end >= next_log_s:
                    # In the slack after the step, at most once per interval.
                    self._flush_overrun_log()
                    next_log_s = end + _LOG_INTERVAL_S
        finally:
            if not held:
                restore_rt(report)
            if old_spin is not None:
                clock.spin_s = old_spin  # type: ignore[attr-defined]
            self._flush_overrun_log()

        snap = tel.snapshot()
        self.stats = LoopStats(
            period_s=period,
            cycles=cycles,
            overruns=overruns,
            skipped=skipped_total,
            max_consecutive_overruns=max_run,
            safe_stop=info.safe_stop,
            stopped_by_step=stopped_by_step,
            max_lateness_s=max_lateness if cycles else 0.0,
            max_exec_s=max_exec,
            overrun_events=tuple(self._events),
            lateness_s=snap["lateness_s"],
            exec_s=snap["exec_s"],
            t_s=snap["t_s"],
            cycle=snap["cycle"],
            rt=report,
        )
        if overruns:
            log.warning(
                "loop: %d overrun(s) in %d cycles, %d deadline(s) skipped, max lateness %.1f us%s",
                overruns,
                cycles,
                skipped_total,
                max_lateness * 1e6,
                ", safe stop requested" if info.safe_stop else "",
            )
        return self.stats
