"""``excavator-rt bench soak``: the real-time HIL's memory over a long run against a client.

Registered as a ``bench`` subcommand through the ``excavator_rt.bench`` entry point ``soak``
(also ``python -m hil_sim.harness.soak``)::

    excavator-rt bench soak [--minutes 15 | --seconds S] [--rate 500] [--sample-s 5]
                            [--warmup-s 60] [--rig scale_model] [--sync-timeout-ms MS]
                            [--truth-s S] [--json]

The real-time HIL process (:mod:`hil_sim.harness.realtime`) runs against the runtime's master
in this process, as the daemon drives it: boot, enable, then one
:class:`~rt_runtime.control.manager.ControllerManager` loop at the rate whose controller sweeps
every axis slowly (:class:`SweepController`: each stroke a cosine of :data:`SWEEP_AMPLITUDE_M`
over :data:`SWEEP_PERIOD_S`, through the limit guard), so drives, plant and bridge work every
SYNC. A thread reads the HIL process's resident memory (``/proc/<pid>/status`` ``VmRSS``) every
``--sample-s``. The report: the samples, the memory at the end of the warm-up and at the end,
the growth after the warm-up (goal :data:`GROWTH_GOAL`, reported, not asserted: the test of the
memory runs a shorter soak), the HIL's own figures (SYNCs, missed SYNCs, truth rows dropped)
and the loop's (cycles, overruns, the drives' first fault).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hil_sim.harness.realtime import RealtimeHilProcess, process_memory_mb
from rt_runtime import actuation
from rt_runtime.canbus import CanMaster, CycleStatus
from rt_runtime.control import FixedRateLoop, LimitGuard, LoopConfig, MonotonicClock, StrokeLimits
from rt_runtime.control.controllers import Command, ControllerStatus, GuardFilter, Mode
from rt_runtime.control.hardware import DriveFeedback, DriveInterface
from rt_runtime.control.manager import ControllerManager, executor_telemetry
from rt_runtime.control.rt import RtSettings
from rt_runtime.control.setpoints import Phase
from rt_runtime.rig import Rig, load_rig

__all__ = [
    "GROWTH_GOAL",
    "SWEEP_AMPLITUDE_M",
    "SWEEP_PERIOD_S",
    "SoakReport",
    "SweepController",
    "add_parser",
    "main",
    "run",
    "soak_hil",
]

FloatArray = NDArray[np.float64]

#: Goal: the HIL's resident memory at the end within this fraction above its value after the
#: warm-up.
GROWTH_GOAL = 0.05
#: Stroke travel of the sweep on every axis (m).
SWEEP_AMPLITUDE_M = 0.01
#: Period of the sweep of the boom (s); the stick's is 1.3 times it, the bucket's 1.7 times.
SWEEP_PERIOD_S = 10.0
#: Joint pose the HIL starts in (deg): mid-range of the scale model's joints.
_START_DEG = (30.0, -90.0, -60.0)


class SweepController:
    """Moves every axis back and forth, for ever: stroke ``s0 + a (1 - cos(w t)) / 2``, from
    rest at ``s0``, each axis at its own period (so the arm's pose keeps changing).

    Loop safe (the command's arrays are written in place). Its commands pass the limit guard
    like every controller's; the sweep itself stays well inside the scale model's limits.

    Args:
        stroke0_m: Stroke at the start (m), ``(3,)``: the sweep adds ``0 .. amplitude_m``.
        q0_rad: Joint pose at the start (rad), the telemetry's joint reference.
        amplitude_m: Stroke travel (m).
        period_s: Sweep period of the boom (s); the stick's and the bucket's are 1.3 and 1.7
            times it.

    Attributes:
        fault: Empty, or the first cycle status at EMCY or worse (the soak reports it).
    """

    def __init__(
        self,
        stroke0_m: FloatArray,
        q0_rad: FloatArray,
        amplitude_m: float = SWEEP_AMPLITUDE_M,
        period_s: float = SWEEP_PERIOD_S,
    ) -> None:
        self.command = Command()
        self.command.hold(np.asarray(stroke0_m, dtype=np.float64), q0_rad, Phase.WAIT)
        self.command.tracking = True
        self._s0 = np.asarray(stroke0_m, dtype=np.float64).copy()
        self._half = 0.5 * float(amplitude_m)
        self._w = 2.0 * math.pi / (float(period_s) * np.array([1.0, 1.3, 1.7]))
        self._rate_gain = self._half * self._w
        self._accel_gain = self._half * self._w**2
        self._arg = np.zeros(3)
        self._t0_s: float | None = None
        self.fault = ""

    def update(
        self, t_s: float, period_s: float, feedback: DriveFeedback
    ) -> tuple[Command, ControllerStatus]:
        """The sweep's state one period ahead; the first fault status is kept."""
        if not self.fault and feedback.status >= CycleStatus.EMCY:
            self.fault = f"{CycleStatus(feedback.status).name} at SYNC {feedback.sync_count}"
        if self._t0_s is None:
            self._t0_s = t_s
        cmd = self.command
        half, arg = self._half, self._arg
        np.multiply(self._w, t_s + period_s - self._t0_s, out=arg)
        np.cos(arg, out=cmd.stroke_m)
        cmd.stroke_m *= -half
        cmd.stroke_m += half
        cmd.stroke_m += self._s0
        np.sin(arg, out=cmd.rate_m_s)
        cmd.rate_m_s *= self._rate_gain
        np.cos(arg, out=cmd.accel_m_s2)
        cmd.accel_m_s2 *= self._accel_gain
        cmd.mode = Mode.TRACK
        return cmd, ControllerStatus.RUNNING

    def service(self) -> None:
        """Nothing to prepare."""

    def fail(self, text: str) -> tuple[Command, ControllerStatus]:
        """Stop (the guard's jerk-limited stop) and end."""
        self.fault = self.fault or text
        self.command.mode = Mode.STOP
        return self.command, ControllerStatus.ENDED

    def overrun(self, consecutive: int, lateness_s: float) -> None:
        """Nothing to stop: the soak measures memory, and late cycles are counted."""


@dataclass(frozen=True, slots=True)
class SoakReport:
    """What :func:`soak_hil` measured.

    Attributes:
        seconds: Length of the run (s).
        period_s: SYNC period (s).
        warmup_s: The warm-up (s): growth is measured from the first sample at or after it.
        samples: ``(t_s, rss_mb)`` of the HIL process, from the client's start.
        rss_warm_mb: The HIL's resident memory at the end of the warm-up (MB).
        rss_end_mb: At the last sample (MB).
        rss_max_after_warmup_mb: The largest sample from the warm-up's end on (MB).
        growth_after_warmup: ``(rss_end_mb - rss_warm_mb) / rss_warm_mb``.
        max_growth_after_warmup: The same with the largest sample after the warm-up.
        cycles: Loop cycles run.
        overruns: Late cycles of the loop.
        fault: The drives' first fault status (empty when none).
        travel_mm: Stroke travel per axis in the truth the HIL kept (max - min, mm): the
            plant moved.
        hil_process: The HIL's own figures (:meth:`RealtimeHilProcess.finish`).
    """

    seconds: float
    period_s: float
    warmup_s: float
    samples: tuple[tuple[float, float], ...]
    rss_warm_mb: float
    rss_end_mb: float
    rss_max_after_warmup_mb: float
    growth_after_warmup: float
    max_growth_after_warmup: float
    cycles: int
    overruns: int
    fault: str
    travel_mm: tuple[float, float, float]
    hil_process: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        """The report's JSON object (``--json``)."""
        return {
            "seconds": self.seconds,
            "period_us": self.period_s * 1e6,
            "warmup_s": self.warmup_s,
            "samples": [[round(t, 1), round(m, 2)] for t, m in self.samples],
            "rss_mb": {
                "start": round(self.samples[0][1], 2) if self.samples else math.nan,
                "warm": round(self.rss_warm_mb, 2),
                "end": round(self.rss_end_mb, 2),
                "max_after_warmup": round(self.rss_max_after_warmup_mb, 2),
            },
            "growth_after_warmup": self.growth_after_warmup,
            "max_growth_after_warmup": self.max_growth_after_warmup,
            "goals": {"growth_after_warmup": GROWTH_GOAL},
            "goal_met": bool(self.growth_after_warmup < GROWTH_GOAL),
            "loop": {"cycles": self.cycles, "overruns": self.overruns, "fault": self.fault},
            "travel_mm": list(self.travel_mm),
            "hil_process": self.hil_process,
        }


def _rss_sampler(
    pid: int, sample_s: float, t0_s: float, out: list[tuple[float, float]], stop: threading.Event
) -> None:
    """Append ``(t_s, rss_mb)`` of ``pid`` every ``sample_s`` until ``stop`` or the process is
    gone."""
    while True:
        try:
            rss_mb, _peak = process_memory_mb(pid)
        except OSError:
            return
        out.append((time.monotonic() - t0_s, rss_mb))
        if stop.wait(sample_s):
            return


def soak_hil(
    rig: Rig | str = "scale_model",
    seconds: float = 900.0,
    *,
    period_s: float = 0.002,
    sample_s: float = 5.0,
    warmup_s: float = 60.0,
    sync_timeout_s: float | None = None,
    truth_s: float | None = None,
    rt: RtSettings | None = None,
) -> SoakReport:
    """Run the real-time HIL against a sweeping client for ``seconds`` and sample its memory.

    Args:
        rig: Rig profile (or its name / file).
        seconds: Length of the loop's run (s).
        period_s: SYNC period (s).
        sample_s: Interval of the memory samples (s).
        warmup_s: Growth is measured from the first sample at or after this (s, < ``seconds``).
        sync_timeout_s: The HIL drives' SYNC/RPDO watchdog (None: the rig's).
        truth_s: Seconds of truth the HIL keeps (None: its default).
        rt: RT settings of the loop (default: SCHED_FIFO 50 where permitted, no mlockall).

    Returns:
        The report.

    Raises:
        ConfigurationError: ``warmup_s`` not below ``seconds``, or a bad rig.
        CommunicationError, DriveFault: The HIL did not start or the drives did not enable.
    """
    from rt_runtime.errors import ConfigurationError

    if not (0.0 <= warmup_s < seconds and sample_s > 0.0):
        raise ConfigurationError(
            f"soak: need 0 <= warm-up ({warmup_s:g} s) < run ({seconds:g} s) and a sample "
            f"interval > 0 ({sample_s:g} s)"
        )
    rig_obj = load_rig(rig) if isinstance(rig, str) else rig
    rig_name = rig if isinstance(rig, str) else rig_obj.name
    q0 = np.radians(np.array(_START_DEG))
    hil = RealtimeHilProcess.start(
        rig_name=rig_name,
        q0_rad=q0,
        period_s=period_s,
        max_wall_s=seconds + 120.0,
        sync_timeout_s=sync_timeout_s,
        truth_s=truth_s,
    )
    settings = rt if rt is not None else RtSettings(50, False, None, 1, True)
    clock = MonotonicClock()
    loop = FixedRateLoop(
        clock, LoopConfig(period_s=period_s, rt=settings), executor_telemetry(1024)
    )
    samples: list[tuple[float, float]] = []
    stop = threading.Event()
    sampler: threading.Thread | None = None
    try:
        loop.acquire_rt()
        master = CanMaster(hil.master_bus, rig_obj, period_s=period_s)
        master.boot(clock.now, 5.0)
        master.enable(clock.now, 5.0)
        drives = DriveInterface(master, clock, 0.0)
        s0 = drives.measured_stroke_m()
        guard = GuardFilter(LimitGuard(StrokeLimits.from_rig(rig_obj), period_s))
        guard.guard.reset(s0)
        q_start = actuation.stroke_to_joint(rig_obj, s0, check_limits=False)
        sweep = SweepController(s0, q_start)
        manager = ControllerManager(drives, guard, loop)
        sampler = threading.Thread(
            target=_rss_sampler,
            args=(hil.proc.pid, sample_s, clock.now(), samples, stop),
            name="rss",
            daemon=True,
        )
        sampler.start()
        stats = manager.run(
            sweep, sweep.command, s0, q_start, max_cycles=max(1, round(seconds / period_s))
        )
        stop.set()
        sampler.join(5.0)
        master.disable()
        truth, _material, _frames, end = hil.finish()
        extra = end.get("hil_process", {})
    finally:
        stop.set()
        loop.release_rt()
        hil.close()
    warm = [m for t, m in samples if t >= warmup_s] or [samples[-1][1]]
    rss_warm, rss_end, rss_max = warm[0], samples[-1][1], max(warm)
    strokes = truth.stroke_m if len(truth.stroke_m) else np.zeros((1, 3))
    travel = (strokes.max(axis=0) - strokes.min(axis=0)) * 1e3
    return SoakReport(
        seconds=float(seconds),
        period_s=float(period_s),
        warmup_s=float(warmup_s),
        samples=tuple(samples),
        rss_warm_mb=rss_warm,
        rss_end_mb=rss_end,
        rss_max_after_warmup_mb=rss_max,
        growth_after_warmup=(rss_end - rss_warm) / rss_warm,
        max_growth_after_warmup=(rss_max - rss_warm) / rss_warm,
        cycles=stats.cycles,
        overruns=stats.overruns,
        fault=sweep.fault,
        travel_mm=(
            round(float(travel[0]), 2),
            round(float(travel[1]), 2),
            round(float(travel[2]), 2),
        ),
        hil_process=dict(extra),
    )


def format_report(report: SoakReport) -> str:
    """The report as text lines."""
    lines = [
        f"HIL soak: {report.seconds:g} s at {1.0 / report.period_s:g} Hz, memory sampled "
        f"{len(report.samples)} times",
        "  t [s]   RSS [MB]",
    ]
    step = max(1, len(report.samples) // 20)
    shown = list(report.samples[::step])
    if report.samples and shown[-1] != report.samples[-1]:
        shown.append(report.samples[-1])
    lines += [f"  {t:6.0f}   {m:8.1f}" for t, m in shown]
    met = "met" if report.growth_after_warmup < GROWTH_GOAL else "NOT met"
    lines += [
        f"  after the {report.warmup_s:g} s warm-up: {report.rss_warm_mb:.1f} MB -> "
        f"{report.rss_end_mb:.1f} MB at the end ({report.growth_after_warmup:+.1%}; "
        f"largest {report.rss_max_after_warmup_mb:.1f} MB); goal < {GROWTH_GOAL:.0%}: {met}",
        f"  loop: {report.cycles} cycles, {report.overruns} overruns; stroke travel "
        f"{', '.join(f'{v:.1f}' for v in report.travel_mm)} mm"
        + (f", drives' fault: {report.fault}" if report.fault else ""),
        f"  HIL: {report.hil_process}",
    ]
    return "\n".join(lines)


def add_parser(bench_sub: Any) -> argparse.ArgumentParser:
    """Add ``soak`` to the ``bench`` subparsers (the ``excavator_rt.bench`` entry point)."""
    p: argparse.ArgumentParser = bench_sub.add_parser(
        "soak",
        help="the real-time HIL's memory over a long run against a client",
        description=(__doc__ or "").split("\n")[0],
    )
    _arguments(p)
    p.set_defaults(handler=run)
    return p


def _arguments(p: argparse.ArgumentParser) -> None:
    length = p.add_mutually_exclusive_group()
    length.add_argument("--minutes", type=float, default=15.0, help="length of the run")
    length.add_argument("--seconds", type=float, default=None, help="length of the run (s)")
    p.add_argument("--rate", type=float, default=500.0, help="SYNC rate (Hz)")
    p.add_argument("--sample-s", type=float, default=5.0, help="memory sample interval (s)")
    p.add_argument("--warmup-s", type=float, default=60.0, help="growth measured after this (s)")
    p.add_argument("--rig", default="scale_model", help="rig profile name or file")
    p.add_argument(
        "--sync-timeout-ms",
        type=float,
        default=None,
        help="the HIL drives' SYNC watchdog (default: the rig's)",
    )
    p.add_argument("--truth-s", type=float, default=None, help="seconds of truth the HIL keeps")
    p.add_argument("--json", action="store_true")


def run(args: argparse.Namespace) -> int:
    """Handler of ``excavator-rt bench soak``: 0 with the report printed (the goal is
    reported, not an exit status), 2 for bad arguments."""
    seconds = args.seconds if args.seconds is not None else args.minutes * 60.0
    if not (math.isfinite(seconds) and seconds > 0.0 and 0.0 < args.rate <= 10_000.0):
        print(f"bench soak: need a run > 0 s ({seconds:g}) and a rate in (0, 10000] Hz "
              f"({args.rate:g})", file=sys.stderr)  # fmt: skip
        return 2
    warmup = min(args.warmup_s, 0.5 * seconds)
    report = soak_hil(
        args.rig,
        seconds,
        period_s=1.0 / args.rate,
        sample_s=args.sample_s,
        warmup_s=warmup,
        sync_timeout_s=None if args.sync_timeout_ms is None else args.sync_timeout_ms * 1e-3,
        truth_s=args.truth_s,
    )
    print(json.dumps(report.to_json()) if args.json else format_report(report))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m hil_sim.harness.soak``: the same as ``excavator-rt bench soak``."""
    p = argparse.ArgumentParser("python -m hil_sim.harness.soak", description=__doc__)
    _arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
