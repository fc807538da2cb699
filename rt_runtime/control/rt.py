"""Real-time settings of the loop's thread: what to ask the OS for, what it granted, and undo.

:func:`apply_rt` asks for each item of :class:`RtSettings` in turn (SCHED_FIFO priority, mlockall,
CPU affinity, timer slack, garbage collector frozen) and reports every item as applied or refused
with the reason (:class:`RtReport`); a refusal is never fatal, because a developer laptop or a
container without ``CAP_SYS_NICE`` must still run the loop, only with worse timing.
:func:`restore_rt` undoes what was applied. Both act on the *calling thread* (Linux
``sched_setscheduler(0, ...)`` and ``sched_setaffinity(0, ...)`` address the calling thread), so
call them from the thread that runs the loop; mlockall and the garbage collector are per process.

The OS calls go through :class:`RtPlatform` so tests can inject refusals; the default one uses
:mod:`os` and libc through :mod:`ctypes` (``mlockall``, ``munlockall``, ``prctl``), which the
standard library does not wrap.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import sys
import threading
from dataclasses import dataclass, field
from types import FrameType
from typing import Any, Protocol

from rt_runtime.errors import ConfigurationError

__all__ = [
    "HelperThreads",
    "OsRtPlatform",
    "RtItem",
    "RtPlatform",
    "RtReport",
    "RtSettings",
    "apply_rt",
    "restore_rt",
]

# <sys/mman.h> and <linux/prctl.h>; the same values on every Linux architecture we run on.
MCL_CURRENT = 1
MCL_FUTURE = 2
MCL_ONFAULT = 4
PR_SET_TIMERSLACK = 29
PR_GET_TIMERSLACK = 30


@dataclass(frozen=True, slots=True)
class RtSettings:
    """What to ask the OS for while the loop runs; each refusal is reported, never fatal.

    Attributes:
        sched_fifo_priority: SCHED_FIFO priority (1..99 on Linux) for the loop's thread; None
            leaves the scheduler alone.
        lock_memory: Lock the process's memory so no page fault stalls a cycle: every page
            mapped now is faulted in and locked (``MCL_CURRENT``); later mappings are locked
            as their pages are first touched (``MCL_FUTURE | MCL_ONFAULT``, Linux 4.4; plain
            ``MCL_FUTURE`` where the kernel refuses it). Not plain ``MCL_FUTURE``: it faults in
            every new mapping whole when it is made, a new thread's 8 MB stack inside
            ``pthread_create`` with the interpreter lock held (17-47 ms p50 on the loaded
            2-core build machine, against 1-2 ms on fault; design notes L2).
        cpu: Pin the loop's thread to this CPU (``os.sched_setaffinity``); None: no pinning.
        timer_slack_ns: ``prctl(PR_SET_TIMERSLACK)`` for the thread (ns, >= 1); None: leave it.
        freeze_gc: ``gc.collect(); gc.freeze(); gc.disable()`` while running, so no collection
            pause lands in a cycle.

    Raises:
        ConfigurationError: A negative CPU or a timer slack below 1 ns.
    """

    sched_fifo_priority: int | None = 80
    lock_memory: bool = True
    cpu: int | None = None
    timer_slack_ns: int | None = 1
    freeze_gc: bool = True

    def __post_init__(self) -> None:
        if self.cpu is not None and self.cpu < 0:
            raise ConfigurationError(f"rt.cpu is {self.cpu}; allowed: a CPU index >= 0 or None")
        if self.timer_slack_ns is not None and self.timer_slack_ns < 1:
            raise ConfigurationError(
                f"rt.timer_slack_ns is {self.timer_slack_ns}; allowed: an integer >= 1 or None "
                "(0 would reset the thread to the process default)"
            )


@dataclass(frozen=True, slots=True)
class RtItem:
    """One item :func:`apply_rt` asked for.

    Attributes:
        item: ``sched_fifo``, ``mlockall``, ``affinity``, ``timer_slack`` or ``gc_freeze``.
        requested: What was asked for, human-readable (``priority 80``, ``cpu 1``, ...).
        applied: True if the OS granted it.
        reason: Why it was refused (empty when applied).
    """

    item: str
    requested: str
    applied: bool
    reason: str = ""


class RtPlatform(Protocol):
    """The OS calls :func:`apply_rt` and :func:`restore_rt` make (injectable for tests).

    Each raises ``OSError`` (or ``ValueError``) when the OS refuses.
    """

    def get_scheduler(self) -> tuple[int, int]:
        """The calling thread's ``(policy, priority)``."""
        ...

    def set_scheduler(self, policy: int, priority: int) -> None:
        """Set the calling thread's policy and priority."""
        ...

    def fifo_priority_range(self) -> tuple[int, int]:
        """``(min, max)`` SCHED_FIFO priority."""
        ...

    def get_affinity(self) -> set[int]:
        """The calling thread's CPU set."""
        ...

    def set_affinity(self, cpus: set[int]) -> None:
        """Set the calling thread's CPU set."""
        ...

    def mlockall(self, flags: int) -> None:
        """Lock the process's memory."""
        ...

    def munlockall(self) -> None:
        """Unlock the process's memory."""
        ...

    def get_timer_slack_ns(self) -> int:
        """The calling thread's timer slack (ns)."""
        ...

    def set_timer_slack_ns(self, slack_ns: int) -> None:
        """Set the calling thread's timer slack (ns)."""
        ...


class OsRtPlatform:
    """:class:`RtPlatform` on Linux: :mod:`os` for the scheduler and affinity, libc for the rest."""

    def __init__(self) -> None:
        self._libc = ctypes.CDLL(None, use_errno=True)

    def _check(self, result: int, what: str) -> int:
        if result == -1:
            errno = ctypes.get_errno()
            raise OSError(errno, f"{what}: {os.strerror(errno)}")
        return result

    def get_scheduler(self) -> tuple[int, int]:
        """See :class:`RtPlatform`."""
        return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority

    def set_scheduler(self, policy: int, priority: int) -> None:
        """See :class:`RtPlatform`."""
        os.sched_setscheduler(0, policy, os.sched_param(priority))

    def fifo_priority_range(self) -> tuple[int, int]:
        """See :class:`RtPlatform`."""
        return os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)

    def get_affinity(self) -> set[int]:
        """See :class:`RtPlatform`."""
        return set(os.sched_getaffinity(0))

    def set_affinity(self, cpus: set[int]) -> None:
        """See :class:`RtPlatform`."""
        os.sched_setaffinity(0, cpus)

    def mlockall(self, flags: int) -> None:
        """See :class:`RtPlatform`."""
        self._check(self._libc.mlockall(ctypes.c_int(flags)), "mlockall")

    def munlockall(self) -> None:
        """See :class:`RtPlatform`."""
        self._check(self._libc.munlockall(), "munlockall")

    def get_timer_slack_ns(self) -> int:
        """See :class:`RtPlatform`."""
        return self._check(
            self._libc.prctl(ctypes.c_int(PR_GET_TIMERSLACK), ctypes.c_ulong(0)), "prctl"
        )

    def set_timer_slack_ns(self, slack_ns: int) -> None:
        """See :class:`RtPlatform`."""
        self._check(
            self._libc.prctl(ctypes.c_int(PR_SET_TIMERSLACK), ctypes.c_ulong(slack_ns)), "prctl"
        )


@dataclass(frozen=True, slots=True)
class RtReport:
    """What :func:`apply_rt` asked for and got, and what :func:`restore_rt` needs to undo it.

    Attributes:
        items: One entry per item asked for, in the order asked.
        prev_scheduler: ``(policy, priority)`` before, when SCHED_FIFO was applied.
        prev_affinity: CPU set before, when the affinity was applied.
        prev_timer_slack_ns: Timer slack before, when the slack was applied.
        memory_locked: True when mlockall was applied.
        gc_was_enabled: ``gc.isenabled()`` before, when the collector was frozen; None otherwise.
    """

    items: tuple[RtItem, ...] = ()
    prev_scheduler: tuple[int, int] | None = None
    prev_affinity: frozenset[int] | None = None
    prev_timer_slack_ns: int | None = None
    memory_locked: bool = False
    gc_was_enabled: bool | None = None
    platform: RtPlatform | None = field(default=None, repr=False, compare=False)

    @property
    def refused(self) -> tuple[RtItem, ...]:
        """The items the OS refused."""
        return tuple(i for i in self.items if not i.applied)

    def as_dict(self) -> dict[str, dict[str, object]]:
        """JSON-able ``{item: {requested, applied, reason}}`` for reports."""
        return {
            i.item: {"requested": i.requested, "applied": i.applied, "reason": i.reason}
            for i in self.items
        }


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.errno is not None:
        return f"{os.strerror(exc.errno)} (errno {exc.errno}); {exc}"
    return str(exc)


def apply_rt(settings: RtSettings, platform: RtPlatform | None = None) -> RtReport:
    """Ask the OS for each item of ``settings`` for the calling thread (mlockall first, then
    SCHED_FIFO, the CPU, the timer slack, the collector); never raises on refusal.

    Not for inside the loop (it calls the OS and ``gc.collect``): call it before the first cycle.

    Args:
        settings: What to ask for.
        platform: The OS calls (default :class:`OsRtPlatform`; tests inject refusals).

    Returns:
        Every item asked for, applied or refused with the reason, plus what
        :func:`restore_rt` needs.
    """
    plat: RtPlatform = platform if platform is not None else OsRtPlatform()
    items: list[RtItem] = []
    prev_scheduler: tuple[int, int] | None = None
    prev_affinity: frozenset[int] | None = None
    prev_slack: int | None = None
    locked = False
    gc_was_enabled: bool | None = None

    # Memory first, at the thread's old priority: faulting in the whole process takes tens of
    # milliseconds of CPU, which at SCHED_FIFO would hold up every lower real-time task there.
    if settings.lock_memory:
        try:
            plat.mlockall(MCL_CURRENT)
            locked = True
            try:
                plat.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT)
                requested = "MCL_CURRENT, then MCL_FUTURE|MCL_ONFAULT"
            except OSError:
                plat.mlockall(MCL_CURRENT | MCL_FUTURE)
                requested = "MCL_CURRENT|MCL_FUTURE (no MCL_ONFAULT)"
            items.append(RtItem("mlockall", requested, True))
        except OSError as exc:
            items.append(RtItem("mlockall", "MCL_CURRENT, MCL_FUTURE", False, _reason(exc)))

    if settings.sched_fifo_priority is not None:
        prio = settings.sched_fifo_priority
        requested = f"priority {prio}"
        try:
            lo, hi = plat.fifo_priority_range()
            if not lo <= prio <= hi:
                raise ValueError(f"priority {prio} is outside the allowed range [{lo}, {hi}]")
            before = plat.get_scheduler()
            plat.set_scheduler(os.SCHED_FIFO, prio)
            prev_scheduler = before
            items.append(RtItem("sched_fifo", requested, True))
        except (OSError, ValueError) as exc:
            items.append(RtItem("sched_fifo", requested, False, _reason(exc)))

    if settings.cpu is not None:
        requested = f"cpu {settings.cpu}"
        try:
            before_cpus = frozenset(plat.get_affinity())
            plat.set_affinity({settings.cpu})
            prev_affinity = before_cpus
            items.append(RtItem("affinity", requested, True))
        except (OSError, ValueError) as exc:
            items.append(RtItem("affinity", requested, False, _reason(exc)))

    if settings.timer_slack_ns is not None:
        requested = f"{settings.timer_slack_ns} ns"
        try:
            before_slack = plat.get_timer_slack_ns()
            plat.set_timer_slack_ns(settings.timer_slack_ns)
            prev_slack = before_slack
            items.append(RtItem("timer_slack", requested, True))
        except OSError as exc:
            items.append(RtItem("timer_slack", requested, False, _reason(exc)))

    if settings.freeze_gc:
        gc_was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        items.append(RtItem("gc_freeze", "collect, freeze, disable", True))

    return RtReport(
        items=tuple(items),
        prev_scheduler=prev_scheduler,
        prev_affinity=prev_affinity,
        prev_timer_slack_ns=prev_slack,
        memory_locked=locked,
        gc_was_enabled=gc_was_enabled,
        platform=plat,
    )


def restore_rt(report: RtReport) -> None:
    """Undo what :func:`apply_rt` applied (on the calling thread); best effort, never raises.

    The scheduler goes back first so a thread that fails to restore something else is not left
    spinning at real-time priority.

    Args:
        report: What :func:`apply_rt` returned.
    """
    plat: RtPlatform = report.platform if report.platform is not None else OsRtPlatform()
    if report.prev_scheduler is not None:
        with contextlib.suppress(OSError, ValueError):
            plat.set_scheduler(*report.prev_scheduler)
    if report.prev_affinity is not None:
        with contextlib.suppress(OSError, ValueError):
            plat.set_affinity(set(report.prev_affinity))
    if report.prev_timer_slack_ns is not None:
        with contextlib.suppress(OSError):
            plat.set_timer_slack_ns(report.prev_timer_slack_ns)
    if report.memory_locked:
        with contextlib.suppress(OSError):
            plat.munlockall()
    if report.gc_was_enabled is not None:
        gc.unfreeze()
        if report.gc_was_enabled:
            gc.enable()


class HelperThreads:
    """SCHED_FIFO at a low priority for a process's other threads: the calling thread and
    every thread the :mod:`threading` module starts until :meth:`restore`.

    Why: Python threads share one interpreter lock. A thread at normal priority that holds it
    and is preempted by any other process keeps the loop's thread (SCHED_FIFO, waiting for the
    lock) from running until it is scheduled again: tens of milliseconds on a loaded host,
    longer than the drives' SYNC watchdog. At a real-time priority below the loop's (and below
    a HIL process standing in for drive firmware) those threads are never preempted by normal
    work while they hold the lock, and release it within the switch interval.

    Every thread is set with ``SCHED_RESET_ON_FORK``: processes it starts (the planner's) begin
    at normal priority; a thread it starts sets itself here when it begins (a
    :func:`threading.setprofile` hook that puts back the profile hook there was before at the
    thread's first call).

    Args:
        priority: SCHED_FIFO priority (1..99).

    Attributes:
        item: What the OS granted for the calling thread (refused: nothing else is done).
    """

    def __init__(self, priority: int) -> None:
        self.priority = int(priority)
        self._previous: tuple[int, int] | None = None
        self._previous_hook = threading.getprofile()
        requested = f"priority {self.priority} for the other threads"
        try:
            self._previous = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            self._set()
        except (OSError, ValueError) as exc:
            self._previous = None
            self.item = RtItem("helper_fifo", requested, False, _reason(exc))
            return
        self.item = RtItem("helper_fifo", requested, True)
        threading.setprofile(self._hook)

    def _set(self) -> None:
        os.sched_setscheduler(
            0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(self.priority)
        )

    def _hook(self, _frame: FrameType, _event: str, _arg: Any) -> None:
        sys.setprofile(self._previous_hook)
        with contextlib.suppress(OSError, ValueError):
            self._set()

    def restore(self) -> None:
        """Threads started from now on keep the normal priority, and so does the calling
        thread (the one that built this); threads already raised stay raised. Idempotent."""
        if self._previous is None:
            return
        threading.setprofile(self._previous_hook)
        with contextlib.suppress(OSError, ValueError):
            policy, priority = self._previous
            os.sched_setscheduler(0, policy, os.sched_param(priority))
        self._previous = None
