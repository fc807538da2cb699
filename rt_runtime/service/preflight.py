"""What ``excavator-rtd`` checks before the bus: the files it will use, the host's timing.

Role: two checks that need no bus.

* :func:`check_start` is ``excavator-rtd --check``: everything a start checks that does not
  need the bus, and no file changed (no directory made, no stale socket or temporary file
  removed, no trace rotated): the python-can interface's backend imports; the state directory
  is writable or can be made and the job store in it is valid; the control socket's directory
  is owner-only (0700) and this user's, or can be made, and no daemon serves the socket; the
  trace's directory is writable or can be made. Then, on a scratch thread, the loop's RT
  settings as a start asks for them and :func:`timing_self_test`.
* :func:`timing_self_test`: the loop's thread, with its RT settings applied, runs the
  fixed-rate loop with an empty step for :data:`SELF_TEST_S` and measures how late it wakes.
  The runner runs it at every start before it boots the drives (nothing on the bus is enabled
  yet, so no watchdog runs), and logs the figures; where the host cannot hold what the drives
  and the loop need (SCHED_FIFO or mlockall refused, a delay that reaches the drives' SYNC
  watchdog, as many late cycles in a row as the overrun stop allows, any late cycle) it says
  so with the measured numbers, as warnings, before the drives are enabled.
"""

from __future__ import annotations

import importlib
import math
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rt_runtime.control.clock import Clock, MonotonicClock
from rt_runtime.control.loop import FixedRateLoop, LoopAction, LoopConfig, OverrunPolicy
from rt_runtime.control.rt import RtReport, RtSettings, apply_rt, restore_rt
from rt_runtime.control.telemetry import Telemetry
from rt_runtime.errors import ConfigurationError
from rt_runtime.service.config import ConfigKeyError, DaemonConfig, check_directory
from rt_runtime.service.control import check_socket_path
from rt_runtime.service.jobstore import JobStore

if TYPE_CHECKING:
    from rt_runtime.rig import Rig

__all__ = ["SELF_TEST_S", "TimingCheck", "check_start", "loop_rt_settings", "timing_self_test"]

#: Length of the timing self-test (s).
SELF_TEST_S = 0.5


def loop_rt_settings(config: DaemonConfig) -> RtSettings:
    """The RT settings the runner asks for on its loop's thread (for the daemon's life)."""
    cfg = config.loop
    return RtSettings(
        sched_fifo_priority=cfg.sched_fifo_priority,
        lock_memory=cfg.lock_memory,
        cpu=cfg.cpu,
        timer_slack_ns=1,
        freeze_gc=False,
    )


@dataclass(frozen=True, slots=True)
class TimingCheck:
    """What :func:`timing_self_test` measured and what it means for the drives and the loop.

    Attributes:
        period_s: The loop's period (s).
        cycles: Cycles run.
        lateness_p50_s, lateness_p99_s, lateness_max_s: How late the loop woke (s).
        overruns: Cycles later than half a period (the loop's overrun).
        max_consecutive_overruns: The longest run of them.
        rt: What the OS granted and refused.
        warnings: What the host cannot hold, with the numbers (empty when it holds).
    """

    period_s: float
    cycles: int
    lateness_p50_s: float
    lateness_p99_s: float
    lateness_max_s: float
    overruns: int
    max_consecutive_overruns: int
    rt: RtReport
    warnings: tuple[str, ...]

    def summary(self) -> str:
        """One line with the figures."""
        granted = ", ".join(
            f"{i.item} {i.requested} {'granted' if i.applied else 'refused'}" for i in self.rt.items
        )
        return (
            f"timing self-test: {self.cycles} cycles at {self.period_s * 1e3:g} ms "
            f"({granted or 'no RT settings asked for'}): wake-up lateness p50 "
            f"{self.lateness_p50_s * 1e6:.0f} us, p99 {self.lateness_p99_s * 1e6:.0f} us, max "
            f"{self.lateness_max_s * 1e6:.0f} us; {self.overruns} late cycle(s), at most "
            f"{self.max_consecutive_overruns} in a row"
        )


def timing_self_test(
    clock: Clock,
    period_s: float,
    rt: RtReport,
    *,
    sync_watchdog_s: float,
    max_consecutive_overruns: int,
    seconds: float = SELF_TEST_S,
) -> TimingCheck:
    """Run the fixed-rate loop with an empty step on the calling thread and judge the host.

    Call it on the loop's thread with its RT settings applied (``rt``: what :func:`apply_rt`
    granted there); nothing runs on the bus meanwhile.

    Args:
        clock: The loop's clock.
        period_s: The loop's period (s).
        rt: The RT settings of this thread as applied.
        sync_watchdog_s: The drives' SYNC watchdog (s): a SYNC gap as long trips it.
        max_consecutive_overruns: The loop's overrun stop (late cycles in a row).
        seconds: Length of the test (s).

    Returns:
        The figures and the warnings.
    """
    cycles = max(2, math.ceil(seconds / period_s))
    loop = FixedRateLoop(
        clock,
        LoopConfig(
            period_s=period_s,
            spin_s=min(2e-4, 0.25 * period_s),
            rt=RtSettings(None, False, None, None, False),
            overrun=OverrunPolicy(max_consecutive=cycles + 1),
        ),
        Telemetry(cycles),
    )
    stats = loop.run(lambda _info: LoopAction.CONTINUE, max_cycles=cycles)
    late = stats.lateness_s if stats.lateness_s.size else np.zeros(1)
    p50, p99 = (float(v) for v in np.percentile(late, (50, 99)))
    worst = float(np.max(late))
    warnings = []
    for item in rt.refused:
        if item.item == "sched_fifo":
            warnings.append(
                f"loop.sched_fifo_priority: SCHED_FIFO {item.requested} refused ({item.reason}): "
                "the loop runs at normal priority, and any busy process on its CPU delays cycles "
                "by milliseconds (LimitRTPRIO= in the unit, or run as root)"
            )
        elif item.item == "mlockall":
            warnings.append(
                f"loop.lock_memory: mlockall refused ({item.reason}): a page fault can stall a "
                "cycle (LimitMEMLOCK=infinity in the unit)"
            )
        else:
            warnings.append(f"{item.item} {item.requested} refused: {item.reason}")
    if worst + period_s >= sync_watchdog_s:
        warnings.append(
            f"the loop woke up to {worst * 1e3:.1f} ms late: a SYNC gap of "
            f"{(worst + period_s) * 1e3:.1f} ms reaches the drives' SYNC watchdog "
            f"({sync_watchdog_s * 1e3:g} ms); the drives would fault"
        )
    if stats.max_consecutive_overruns >= max_consecutive_overruns:
        warnings.append(
            f"{stats.max_consecutive_overruns} late cycles in a row: "
            f"loop.max_consecutive_overruns ({max_consecutive_overruns}) would stop a job"
        )
    elif stats.overruns:
        warnings.append(
            f"{stats.overruns} of {stats.cycles} cycles more than half a period late in "
            f"{seconds:g} s (max {worst * 1e6:.0f} us): this host shares the loop's CPU; "
            f"{max_consecutive_overruns} in a row stop a job (an isolated core: loop.cpu)"
        )
    return TimingCheck(
        period_s=period_s,
        cycles=stats.cycles,
        lateness_p50_s=p50,
        lateness_p99_s=p99,
        lateness_max_s=worst,
        overruns=stats.overruns,
        max_consecutive_overruns=stats.max_consecutive_overruns,
        rt=rt,
        warnings=tuple(warnings),
    )


def _check_interface(config: DaemonConfig) -> str:
    """The python-can backend of ``bus.interface`` imports (the bus itself is not opened)."""
    import can

    name = config.bus.interface
    module_name, class_name = can.interfaces.BACKENDS[name]
    try:
        getattr(importlib.import_module(module_name), class_name)
    except Exception as exc:  # a backend's import fails in its own ways (missing driver, ...)
        raise ConfigKeyError(
            "bus.interface",
            f"{name!r}: python-can's backend {module_name}.{class_name} does not import: "
            f"{type(exc).__name__}: {exc}",
            str(config.source),
        ) from exc
    return f"bus: {name} ({module_name}.{class_name}) on {config.bus.channel}; not opened"


def check_start(config: DaemonConfig, rig: Rig) -> list[str]:
    """Everything a start checks that does not need the bus; no file is changed (see the
    module docstring). The rig and the models are checked before (``load_planning``).

    Args:
        config: The validated configuration.
        rig: Its rig.

    Returns:
        What was checked, a line each; lines starting ``warning:`` are what the host cannot
        hold (a start logs the same).

    Raises:
        ConfigurationError: What a start would refuse, the key named.
    """
    lines = [_check_interface(config)]
    paths = config.paths
    jobs, stale = JobStore.check(paths.state_dir)
    stale_text = f"; {stale} temporary file(s) a crash left, removed at start" if stale else ""
    lines.append(f"job store: {paths.state_dir} ({jobs} job(s)){stale_text}")
    left = check_socket_path(paths.socket, create=False)
    lines.append(
        f"control socket: {paths.socket}"
        + ("; a dead daemon's socket is there, removed at start" if left else "")
    )
    if paths.trace is not None:
        check_directory(paths.trace.parent, "paths.trace", create=False)
        lines.append(f"trace: {paths.trace}")
    timing = _timing_on_a_thread(config, rig)
    lines.append(timing.summary())
    lines += [f"warning: {w}" for w in timing.warnings]
    return lines


def _timing_on_a_thread(config: DaemonConfig, rig: Rig) -> TimingCheck:
    """The start's RT settings and :func:`timing_self_test` on a scratch thread (the settings
    are undone after it)."""
    out: list[TimingCheck] = []
    errors: list[BaseException] = []

    def run() -> None:
        report = apply_rt(loop_rt_settings(config))
        try:
            out.append(
                timing_self_test(
                    MonotonicClock(),
                    config.loop.period_s,
                    report,
                    sync_watchdog_s=rig.drives.sync_timeout_s,
                    max_consecutive_overruns=config.loop.max_consecutive_overruns,
                )
            )
        except BaseException as exc:
            errors.append(exc)
        finally:
            restore_rt(report)

    thread = threading.Thread(target=run, name="self-test", daemon=True)
    thread.start()
    thread.join()
    if errors:
        raise errors[0]
    if not out:
        raise ConfigurationError("the timing self-test did not run")
    return out[0]
