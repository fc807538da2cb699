"""``excavator-rt hil campaign``: every fault kind, on every target, at many times, on the daemon's
runner in the lockstep HIL, with what each case did in one table.

Usage::

    excavator-rt hil campaign [--kinds K1,K2,...] [--axes boom,stick,...] [--seeds N]
                              [--seed S] [--rig scale_model] [--jobs J] [--json] [--out DIR]

A *case* is one fault kind on one target at one time. It runs the product's own path: a
:class:`~rt_runtime.service.runner.RigRunner` (the daemon's runner: boot, hold, job, latch, reset,
resume) on a :class:`~hil_sim.harness.lockstep.LockstepHil` (simulated time, deterministic),
with a job store in a temporary state directory and a short job (:data:`CASE_TASK`, two digs by
default). On a rig with swing (``--rig field_excavator``) the job is a taught trench of as many
cycles (:func:`taught_case_job`, taught once per campaign from the simulated operator), each
cycle a dig of the job; the swing is a target as the cylinders are, and the kinds that strike
the planner process (:data:`PLANNER_KINDS`) are left out: a taught job has none.
The fault is switched on ``at_s`` seconds after the job's first commanded motion, on the
runner's own thread between two cycles (:class:`_CaseClock`), so nothing races the loop. Then:

* a fault that latches is *detected*: ``detection_s`` is the runner's latch time
  (:attr:`~rt_runtime.service.runner.RigRunner.fault_at_s`) minus the injection's (for a jam
  or a rock, minus the moment the axis's command first ran a following-error window ahead of
  where the axis truly is, if later: a held axis shows neither, and a hydraulic one creeps on
  its oil column after it stuck); the cause is
  cleared (:meth:`~hil_sim.harness.lockstep.LockstepHil.clear_faults`; a bus-off adapter is
  reopened by the runner's ``reopen``), ``reset-fault`` is requested and the job must end
  ``done`` at its two digs: ``resumed``;
* a fault that does not latch is *ridden through*: the job must end ``done`` on its own, and
  the master's receive counts (:class:`~rt_runtime.canbus.feedback.RxCounts`) and the wire's
  (:attr:`~hil_sim.busfaults.BusFaults.affected`) say what it rode through.

Checks of a stopped case, on what the master sent (every frame, read off the bus by a monitor
end of the channel) from the detection to the reset, and on the plant:

* ``stop_peak``: the commanded RPDO1 stream's peak stroke rate, acceleration and jerk as
  fractions of the guard's limits (:func:`~rt_runtime.control.guard.check_setpoint_trace`);
  over 1 is a violation;
* once the commanded stream has been at rest for :data:`_REST_FRAMES` periods it stays there
  until the reset (a target that moves again is a violation), and no controlword enables
  operation before the reset;
* the plant's true stroke rate stays within :data:`PLANT_RATE_MARGIN` of the rate limit (its
  acceleration is physics, a rock stops it hard: not checked);
* detection within the kind's stated bound (:data:`RULES`, from the rig's timing).

A case is *safe* when it has no violation, its outcome is a stop detected within its bound or a
ride-through, and its job is not lost (done at the end, its digs all in the store). The
campaign's ``summary`` counts them. Cases run in parallel over local cores
(:class:`concurrent.futures.ProcessPoolExecutor`, its workers replaced after every
:data:`CASES_PER_WORKER` cases each: a case leaves some tens of MB behind in its process, and a
whole campaign in long-lived workers outgrows the machine); ``--out DIR`` writes the table
(``campaign.json``) and, for every case that is not safe, the frames the master sent and the
plant's truth (``case-<n>.npz``).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import random
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from firmware_models.drive import DeviceState
from hil_sim.harness.lockstep import LockstepHil
from hil_sim.harness.scenario import STALL_MS
from hil_sim.sim import FaultKind
from rt_runtime import axes as rig_axes
from rt_runtime.canbus.inprocess import ChannelBus
from rt_runtime.canbus.pdo import RPDO1, RPDO2
from rt_runtime.control.executor import ExecutorConfig
from rt_runtime.control.guard import StrokeLimits, check_setpoint_trace
from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR
from rt_runtime.planning.trench import TrenchPlanner
from rt_runtime.rig import Rig, load_rig
from rt_runtime.service.config import DaemonConfig, parse_config
from rt_runtime.service.jobstore import JobStatus, JobStore
from rt_runtime.service.runner import PLANNER_CHECK_CYCLES, RigRunner
from rt_runtime.teach import load_taught

__all__ = [
    "AXES",
    "CASE_TASK",
    "PLANNER_KINDS",
    "RULES",
    "Case",
    "CaseResult",
    "Rule",
    "add_parser",
    "lockstep_config",
    "matrix",
    "run_campaign",
    "run_case",
    "taught_case_job",
    "wait_for",
]

AXES = ("boom", "stick", "bucket")
#: The kinds that strike the planner process: a rig with swing runs taught jobs, which have none.
PLANNER_KINDS = (FaultKind.PLANNER_KILLED, FaultKind.MODEL_CHANGED)
#: The operator seeds whose demonstrations teach a swing rig's case job.
TAUGHT_SEEDS = (0, 1, 2)
#: The job of every case: scale model task A's trench (its digs: :attr:`Case.digs`).
CASE_TASK: dict[str, Any] = {
    "name": "campaign",
    "length_m": 0.6,
    "depth_m": 0.15,
    "beta1_deg": 60.0,
    "beta2_deg": 60.0,
    "start_x_m": 1.05,
}
#: The plant's stroke rate may exceed the limit by this fraction (the servo's overshoot).
PLANT_RATE_MARGIN = 0.05
#: Longest wall time of one phase of a case (boot, the job, the latch, the resume).
PHASE_WALL_S = 180.0
#: Cases a worker process runs before a fresh one replaces it (each case leaves 50-70 MB in its
#: process: 8 keep a worker under ~0.6 GB of that).
CASES_PER_WORKER = 8
#: Injection times are drawn from this range (s after the job's first cycle): the approach,
#: the first dig, its lift-out and dump.
AT_RANGE_S = (0.2, 14.0)
#: A commanded axis at rest: moves under this much per period (m).
_REST_STEP_M = 1e-6
#: Periods without a step that make a commanded stream at rest.
_REST_FRAMES = 25
#: Controlwords that enable operation (CiA 402: enable operation, with the fault-reset bit).
_ENABLING = (0x000F, 0x001F)


@dataclass(frozen=True, slots=True)
class Rule:
    """What must happen for a fault kind (see the module docstring).

    Attributes:
        outcome: ``stopped`` or ``ridden_through`` (with the default parameter).
        bound: The detection bound (s) from the rig and the configuration; None for a
            ride-through.
        why: How it is detected (or ridden through), for the report.
    """

    outcome: str
    bound: Callable[[Rig, DaemonConfig], float] | None
    why: str


def _cycles(n: float) -> Callable[[Rig, DaemonConfig], float]:
    return lambda rig, cfg: n * cfg.loop.period_s


def _stale(extra: float) -> Callable[[Rig, DaemonConfig], float]:
    return lambda rig, cfg: (cfg.stale_cycles + extra) * cfg.loop.period_s


#: Detection bound of a stuck axis, in cycles after it shows: the monitor's cycles in a row,
#: and the cycles the drive's servo needs to see the error grow past it.
_FE_CYCLES = ExecutorConfig().following_error_cycles + 10
#: The fault kinds and what must happen (their targets: :attr:`FaultKind.targets`).
RULES: dict[FaultKind, Rule] = {
    FaultKind.FOLLOWING_ERROR: Rule(
        "stopped",
        _cycles(_FE_CYCLES),
        "the executor's following-error monitor (or the drive's 0x8611) once the command is a "
        "window away from where the axis jammed",
    ),
    FaultKind.HEARTBEAT_LOSS: Rule(
        "stopped",
        lambda rig, cfg: (
            rig.drives.heartbeat_timeout_s + rig.drives.heartbeat_period_s + 3 * cfg.loop.period_s
        ),
        "the drive's heartbeat consumer: EMCY 0x8130 after its timeout",
    ),
    FaultKind.NODE_SILENT: Rule(
        "stopped", _stale(2), "stale feedback: no TPDO1 for stale_cycles cycles"
    ),
    FaultKind.OVERCURRENT: Rule("stopped", _cycles(3), "EMCY 0x2310 at the next read"),
    FaultKind.OVERTEMPERATURE: Rule("stopped", _cycles(3), "EMCY 0x4310 at the next read"),
    FaultKind.UNDERVOLTAGE: Rule("stopped", _cycles(3), "EMCY 0x3220 at the next read"),
    FaultKind.DRIVE_REBOOT: Rule(
        "stopped", _cycles(3), "the unannounced boot-up frame at the next read"
    ),
    FaultKind.ENCODER_GLITCH: Rule(
        "stopped",
        _stale(2),
        "the jump refused as implausible every cycle: stale feedback after stale_cycles",
    ),
    FaultKind.ROCK: Rule(
        "stopped",
        _cycles(_FE_CYCLES),
        "following error of the stalled axis (monitor or 0x8611) once its command runs a "
        "window on into the rock",
    ),
    FaultKind.FRAME_LOSS: Rule(
        "ridden_through", None, "a lost TPDO1 is a stale cycle, counted (missed_tpdo1)"
    ),
    FaultKind.FRAME_DELAY: Rule(
        "ridden_through", None, "one late frame: a stale cycle or a late answer, counted"
    ),
    FaultKind.FRAME_REORDER: Rule(
        "ridden_through", None, "two frames swapped: a stale cycle and a late answer"
    ),
    FaultKind.FRAME_TRUNCATED: Rule(
        "ridden_through", None, "a frame of the wrong length is ignored (malformed)"
    ),
    FaultKind.FRAME_GARBAGE: Rule(
        "ridden_through",
        None,
        "a garbled TPDO1 is refused as implausible (a garbled heartbeat or EMCY may stop: safe)",
    ),
    FaultKind.FRAME_DUPLICATE: Rule(
        "ridden_through", None, "a second TPDO1 for one SYNC is counted (duplicate_tpdo1)"
    ),
    FaultKind.ERROR_FRAMES: Rule("ridden_through", None, "error frames are counted (error_frames)"),
    FaultKind.BUS_OFF: Rule(
        "stopped", _cycles(3), "the adapter's send raises: bus error at the next write"
    ),
    FaultKind.BUS_UNPLUGGED: Rule(
        "stopped", _stale(2), "no answers: stale feedback after stale_cycles"
    ),
    FaultKind.LOOP_STALL: Rule(
        "stopped",
        lambda rig, cfg: STALL_MS * 1e-3 + 3 * cfg.loop.period_s,
        "the drives' SYNC watchdog (EMCY 0x8250) during a 50 ms stall, read at the next cycle",
    ),
    FaultKind.STORE_UNWRITABLE: Rule(
        "stopped",
        lambda rig, cfg: STORE_WRITE_S + (PLANNER_CHECK_CYCLES + 3) * cfg.loop.period_s,
        "the runner's store check every PLANNER_CHECK_CYCLES cycles after the store's next "
        "write fails (a dig's record or a job's status: within a dig cycle)",
    ),
    FaultKind.PLANNER_KILLED: Rule(
        "stopped",
        lambda rig, cfg: (PLANNER_CHECK_CYCLES + 3) * cfg.loop.period_s,
        "the runner's planner check every PLANNER_CHECK_CYCLES cycles (the case's clock stands "
        "still from the SIGKILL until the process has ended)",
    ),
    FaultKind.DAEMON_CRASH: Rule(
        "stopped",
        lambda rig, cfg: rig.drives.sync_timeout_s + 3 * cfg.loop.period_s,
        "the drives' own SYNC watchdog (EMCY 0x8250) once the crashed daemon's SYNCs stop: "
        "the first drive out of operation enabled; the restarted daemon (RESTART_S later) "
        "boots the drives from their fault and resumes the job from its store",
    ),
    FaultKind.MODEL_CHANGED: Rule(
        "stopped",
        lambda rig, cfg: (PLANNER_CHECK_CYCLES + 3) * cfg.loop.period_s,
        "the planner process looks at its verified files every WATCH_PERIOD_S of wall time and "
        "before each plan, says which changed and ends; the runner's planner check latches it "
        "(the case's clock stands still until the process has ended)",
    ),
}
#: The daemon's restart after a crash: systemd's ``RestartSec`` of the shipped unit (s).
RESTART_S = 2.0
#: The longest a running job goes without writing the store (a dig cycle, s): the bound of a
#: store that cannot be written counts from its next write.
STORE_WRITE_S = 20.0
#: Faults seen only once their axis is commanded away: detection counts from when the command
#: is a following-error window ahead of where the axis truly is (a jam of a held axis, or a rock
#: the axis is not pushing into, harm nothing and show nothing; a jammed hydraulic axis creeps
#: on its oil column, so its error grows only as the command outruns the creep).
_SEEN_IN_MOTION = (FaultKind.FOLLOWING_ERROR, FaultKind.ROCK)


@dataclass(frozen=True, slots=True)
class Case:
    """One cell of the matrix.

    Attributes:
        number: Its index in the campaign.
        kind: The fault.
        target: Axis name, ``bus`` or ``host``.
        at_s: Seconds after the job's first cycle.
        seed: Seed of the wire's random draws.
        param: The kind's parameter (None: its default).
        digs: The job's digs (its ``max_digs``).
    """

    number: int
    kind: FaultKind
    target: str
    at_s: float
    seed: int
    param: float | None = None
    digs: int = 2


@dataclass(slots=True)
class CaseResult:
    """What one case did (``cases[]`` of the JSON report)."""

    case: Case
    outcome: str = "none"
    detection_s: float = math.nan
    shown_s: float = math.nan
    bound_s: float = math.nan
    stop_peak: dict[str, float] = field(default_factory=dict)
    plant_peak_v: float = math.nan
    violations: list[str] = field(default_factory=list)
    resumed: bool = False
    lost_job: bool = False
    fault: str = ""
    sent_after_detection: dict[str, int] = field(default_factory=dict)
    rode_through: dict[str, int] = field(default_factory=dict)
    wire: dict[str, int] = field(default_factory=dict)
    digs: int = 0
    error: str = ""
    wall_s: float = 0.0

    @property
    def safe(self) -> bool:
        """No violation, no lost job, no error; a stop within its bound or a ride-through."""
        if self.violations or self.lost_job or self.error:
            return False
        if self.outcome == "stopped":
            # A kind a robust master rides through may still stop (a run of losses that takes
            # out a heartbeat's whole timeout): safe when the stop is and the job resumes.
            bounded = math.isnan(self.bound_s) or self.detection_s <= self.bound_s
            return bounded and self.resumed
        return self.outcome == "ridden_through"

    def to_json(self) -> dict[str, Any]:
        c = self.case
        return {
            "number": c.number,
            "kind": c.kind.label,
            "target": c.target,
            "at_s": c.at_s,
            "seed": c.seed,
            "param": c.param,
            "digs_asked": c.digs,
            "expected": RULES[c.kind].outcome,
            "outcome": self.outcome,
            "detection_s": _num(self.detection_s),
            "shown_s": _num(self.shown_s),
            "bound_s": _num(self.bound_s),
            "stop_peak": {k: _num(self.stop_peak.get(k, math.nan)) for k in ("v", "a", "j")},
            "plant_peak_v": _num(self.plant_peak_v),
            "violations": list(self.violations),
            "resumed": self.resumed,
            "lost_job": self.lost_job,
            "safe": self.safe,
            "fault": self.fault,
            "sent_after_detection": dict(self.sent_after_detection),
            "rode_through": dict(self.rode_through),
            "wire": dict(self.wire),
            "digs": self.digs,
            "error": self.error,
            "wall_s": self.wall_s,
        }


def _num(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def matrix(
    kinds: Sequence[FaultKind] | None = None,
    axes: Sequence[str] | None = None,
    seeds: int = 1,
    seed: int = 0,
    digs: int = 2,
    swing: bool = False,
) -> list[Case]:
    """The cases: every kind on every target it takes (axes filtered by ``axes``; ``bus`` and
    ``host`` always), ``seeds`` times each at a time drawn from :data:`AT_RANGE_S`. With
    ``swing`` (a rig with swing, whose case job is a taught trench of ``digs`` cycles) the swing
    is an axis too and the :data:`PLANNER_KINDS` are left out (a taught job has no planner
    process).

    Raises:
        ConfigurationError: No case (a filter left nothing), ``seeds`` below 1, a planner kind
            asked for on a rig with swing, or the swing asked for on a planar rig.
    """
    if seeds < 1:
        raise ConfigurationError(f"--seeds {seeds} must be >= 1")
    names = (*AXES, "swing") if swing else AXES
    if axes is not None and (bad := [a for a in axes if a not in names]):
        raise ConfigurationError(f"axes {', '.join(bad)}: the rig has {', '.join(names)}")
    rng = random.Random(seed)
    chosen = list(RULES) if kinds is None else list(kinds)
    if swing:
        asked = [k.label for k in chosen if k in PLANNER_KINDS and kinds is not None]
        if asked:
            raise ConfigurationError(
                f"{', '.join(asked)}: a rig with swing runs taught jobs, which have no planner "
                "process to strike"
            )
        chosen = [k for k in chosen if k not in PLANNER_KINDS]
    wanted = set(names if axes is None else axes)
    cases: list[Case] = []
    for s in range(seeds):
        for kind in chosen:
            for target in kind.swing_targets if swing else kind.targets:
                if target in names and target not in wanted:
                    continue
                at = round(rng.uniform(*AT_RANGE_S), 3)
                cases.append(Case(len(cases), kind, target, at, seed * 1000 + s, digs=digs))
    if not cases:
        raise ConfigurationError("the campaign's filters leave no case")
    return cases


# -- one case -----------------------------------------------------------------------------------


def _target_um(data: bytes) -> int:
    """An RPDO1's target stroke (um)."""
    return int.from_bytes(data[:4], "little", signed=True)


class _CaseClock:
    """The lockstep clock as the runner's loop sees it; between two cycles (on the loop's
    thread) it reads the monitor end and switches the case's fault on at its time.

    The case's time starts at the job's first commanded motion (its first RPDO1 target that
    differs from the one before), not at its first cycle: in lockstep the job holds for as long
    as its planner process takes on the wall clock, which is many simulated seconds on a busy
    machine, and a fault during that hold would test the hold only.
    """

    realtime = False

    def __init__(self, hil: LockstepHil, case: Case, monitor: ChannelBus) -> None:
        self.hil = hil
        self.case = case
        self.monitor = monitor
        self.runner: RigRunner | None = None
        self.t0 = math.nan
        self.injected_at = math.nan
        self.reset_at = math.inf
        self.rock_direction = 0.0
        self.undo: Callable[[], None] | None = None  # clears a host fault's cause
        self.model_dir: Path | None = None  # the case's own copy of the models
        #: A crash: the crashed runner's loop hangs in the clock (it sends nothing more) until
        #: ``release`` at the case's end.
        self.crashed = threading.Event()
        self.release = threading.Event()
        self.inject_error = ""
        #: Master frames seen: (time, cob, data) of RPDO1, RPDO2, SYNC and NMT.
        self.frames: list[tuple[float, int, bytes]] = []
        self._keep = {0x000, 0x080}
        self._last: dict[int, bytes | None] = {}
        for node in (n for _, n in hil.core.rig.can.node_ids):
            self._keep.add(RPDO1.cob_id(node))
            self._keep.add(RPDO2.cob_id(node))
            self._last[RPDO1.cob_id(node)] = None

    def now(self) -> float:
        return self.hil.clock.now()

    def sleep_until(self, t_s: float) -> None:
        self.hil.clock.sleep_until(t_s)
        self.tick()

    def tick(self) -> None:
        """Read the monitor; start the case's time at the job's first cycle; inject at
        ``at_s``."""
        keep, frames, take = self._keep, self.frames, self.monitor.take
        runner = self.runner
        waiting = math.isnan(self.t0) and runner is not None and runner.current_job() is not None
        while (msg := take()) is not None:
            cob = msg.arbitration_id
            if cob in keep and not msg.is_error_frame:
                data = bytes(msg.data)
                frames.append((msg.timestamp, cob, data))
                if waiting and cob in self._last:
                    last, self._last[cob] = self._last[cob], data
                    if last is not None and _target_um(data) != _target_um(last):
                        self.t0 = msg.timestamp
                        waiting = False
        if runner is None or math.isnan(self.t0) or not math.isnan(self.injected_at):
            return
        now = self.now()
        if now - self.t0 >= self.case.at_s:
            self._inject(runner, now)

    def _inject(self, runner: RigRunner, now: float) -> None:
        case = self.case
        kind = case.kind
        self.injected_at = now
        try:
            if kind is FaultKind.LOOP_STALL:
                stall = STALL_MS if case.param is None else case.param
                self.hil.clock.sleep_until(now + stall * 1e-3)
            elif kind is FaultKind.STORE_UNWRITABLE:
                state = runner.store.path.parent
                away = state.with_name(state.name + ".away")
                state.rename(away)
                state.write_text("not a directory: the job store cannot be written here\n")

                def undo() -> None:
                    state.unlink()
                    away.rename(state)

                self.undo = undo
            elif kind is FaultKind.PLANNER_KILLED:
                pid = runner.planner_pid()
                if pid is None:
                    raise ConfigurationError("no planner process to kill")
                os.kill(pid, signal.SIGKILL)
                wait_for(lambda: _dead(pid), "the killed planner process ending", 10.0)
            elif kind is FaultKind.DAEMON_CRASH:
                self.crashed.set()
                self.release.wait()  # this loop's process is gone
            elif kind is FaultKind.MODEL_CHANGED:
                watched = runner.planner_pid()
                if watched is None:
                    raise ConfigurationError("no planner process to watch its models")
                self.undo = _change_model(self.model_dir)
                wait_for(lambda: _dead(watched), "the planner seeing its model changed", 10.0)
            else:
                names = rig_axes.names(self.hil.core.rig)
                axis = names.index(case.target) if case.target in names else -1
                self.hil.inject(kind, axis, case.param)
                if kind is FaultKind.ROCK:
                    self.rock_direction = self.hil.core.nodes[axis].faults.rock_direction
        except (ConfigurationError, ValueError, OSError) as exc:
            self.inject_error = f"{type(exc).__name__}: {exc}"


def _change_model(model_dir: Path | None) -> Callable[[], None]:
    """Deploy other bytes over the downward dig's model (a new file moved into place, as a
    deployment does); return what puts the verified bytes back."""
    if model_dir is None:
        raise ConfigurationError("the case has no model directory of its own to change")
    path = model_dir / "pinn_downward.onnx"
    original = path.read_bytes()
    changed = bytearray(original)
    changed[len(changed) // 2] ^= 0xFF
    staged = path.with_name(path.name + ".new")

    def put(data: bytes) -> None:
        staged.write_bytes(data)
        os.replace(staged, path)

    put(bytes(changed))
    return lambda: put(original)


def _dead(pid: int) -> bool:
    """The process has ended: gone, or a zombie its parent can reap. A killed process's main
    thread shows as a zombie while its other threads are still exiting, and until they have
    it cannot be reaped (its parent's ``waitpid`` still finds it running): its last thread
    counts."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    state = fields.get("State", "").strip()[:1]
    threads = int(fields.get("Threads", "1").strip() or 1)
    return state in ("Z", "X") and threads <= 1


def lockstep_config(state_dir: Path, rig_name: str, model_dir: Path | None = None) -> DaemonConfig:
    """The daemon's configuration of a case: the example's loop and executor values, no
    real-time settings (simulated time), state under ``state_dir``, the models of
    ``model_dir`` (None: the shipped ones)."""
    raw: dict[str, Any] = {
        "bus": {"interface": "virtual", "channel": "unused", "boot_timeout_s": 1.0},
        "rig": {"profile": rig_name},
        "loop": {"sched_fifo_priority": 0, "lock_memory": False},
        "paths": {"state_dir": str(state_dir), "socket": str(state_dir / "c.sock")},
    }
    if model_dir is not None:
        raw["models"] = {"dir": str(model_dir)}
    return parse_config(raw, state_dir / "campaign.toml")


def wait_for(pred: Callable[[], bool], what: str, limit_s: float = PHASE_WALL_S) -> None:
    """Poll ``pred`` until it holds (TimeoutError naming ``what`` after ``limit_s`` of wall
    time)."""
    end = time.monotonic() + limit_s
    while not pred():
        if time.monotonic() > end:
            raise TimeoutError(f"{what}: not within {limit_s:.0f} s of wall time")
        time.sleep(0.002)


def run_case(
    case: Case, rig_name: str = "scale_model", taught: str | None = None
) -> tuple[CaseResult, dict[str, Any]]:
    """Run one case (see the module docstring). On a rig with swing the job is the taught
    trench ``taught`` (:func:`taught_case_job`), its cycles the digs.

    Returns:
        The result and its trace (``frames``: ``(t, cob, data)`` the master sent; ``truth``:
        SYNC times and true strokes) for the record of a failing case.

    Raises:
        ConfigurationError: A rig with swing and no taught job.
    """
    wall0 = time.monotonic()
    result = CaseResult(case)
    trace: dict[str, Any] = {}
    rig = load_rig(rig_name)
    if rig.swing is not None and taught is None:
        raise ConfigurationError(f"rig {rig.name} has a swing: its cases run a taught job")
    with tempfile.TemporaryDirectory(prefix="excavator-campaign-") as tmp:
        model_dir = None
        if case.kind is FaultKind.MODEL_CHANGED:  # the shipped models stay as they are
            model_dir = Path(tmp) / "models"
            shutil.copytree(DEFAULT_MODEL_DIR, model_dir)
        planner: TrenchPlanner | None = None
        if taught is None:
            planner = TrenchPlanner(rig, model_dir=model_dir)
            q0 = planner.home_pose_rad
        else:
            q0 = rig_axes.from_joint_order(rig, load_taught(taught, rig).q0_rad)
        cfg = lockstep_config(Path(tmp), rig_name, model_dir)
        rule = RULES[case.kind]
        result.bound_s = rule.bound(rig, cfg) if rule.bound is not None else math.nan
        hil = LockstepHil(rig, q0, vcu=False, fault_seed=case.seed)
        monitor = ChannelBus(hil.channel, clock=hil.clock.now)
        clock = _CaseClock(hil, case, monitor)
        clock.model_dir = model_dir
        store = JobStore(cfg.paths.state_dir)
        store.start()  # its writer thread, as the daemon's
        runner = RigRunner(cfg, rig, planner, hil.master_bus, store, clock, hil.reopen_master_bus)
        clock.runner = runner
        restarted: list[tuple[RigRunner, JobStore]] = []

        def restart() -> tuple[RigRunner, JobStore]:
            """The daemon as systemd starts it again: its store read from disk, a new runner
            on a new bus end, the same clock."""
            again = JobStore(cfg.paths.state_dir)
            again.start()
            new = RigRunner(cfg, rig, planner, hil.master_bus, again, clock, hil.reopen_master_bus)
            restarted.append((new, again))
            clock.runner = new
            return new, again

        try:
            _drive_case(case, result, runner, store, hil, clock, restart, taught)
        except (TimeoutError, ConfigurationError) as exc:
            now = restarted[-1][0] if restarted else runner
            result.error = f"{type(exc).__name__}: {exc}; runner: {now.state()}"
        finally:
            for again, again_store in reversed(restarted):
                if not again.shutdown(30.0):
                    result.error = result.error or "the restarted runner did not shut down"
                again_store.close()
            if clock.crashed.is_set():
                # The crashed runner's loop, let go on a bus end and a store that are closed:
                # asked to stop first (else its next send fails on the closed end and it
                # latches; either way it ends and writes nowhere).
                stopper = threading.Thread(target=runner.shutdown, args=(30.0,), daemon=True)
                stopper.start()
                time.sleep(0.1)
                clock.release.set()
                stopper.join(30.0)
            elif not runner.shutdown(30.0):
                result.error = result.error or "the runner did not shut down"
            if clock.undo is not None and not runner.store.path.parent.is_dir():
                clock.undo()
            store.close()
            truth = hil.core.truth()
            stroke = truth.stroke_m
            if truth.swing_rad is not None:  # the swing drive's position: the angle (rad)
                stroke = np.column_stack((stroke, truth.swing_rad))
            trace = {"frames": clock.frames, "t_s": truth.t_s, "stroke_m": stroke}
            _check_stop(result, rig, cfg, clock, truth.t_s, stroke)
            result.wire = dict(hil.bus_faults.affected)
            monitor.shutdown()
            hil.close()
    result.wall_s = time.monotonic() - wall0
    return result, trace


def _drive_case(
    case: Case,
    result: CaseResult,
    runner: RigRunner,
    store: JobStore,
    hil: LockstepHil,
    clock: _CaseClock,
    restart: Callable[[], tuple[RigRunner, JobStore]],
    taught: str | None = None,
) -> None:
    runner.start()
    wait_for(lambda: runner.health()[0], "the runner holding")
    if taught is None:
        job = store.submit(dict(CASE_TASK), "pinn", max_digs=case.digs)
    else:
        job = store.submit({}, "pinn", taught=taught)
    store.changed.set()

    def settled() -> bool:
        if clock.crashed.is_set():
            return True
        status = store.get(job.id).status
        return bool(runner.fault()) or status in (JobStatus.DONE, JobStatus.FAILED)

    wait_for(settled, "the job ending or a fault")
    if not clock.crashed.is_set() and not runner.fault() and not store.sync() and store.write_error:
        # The job's last change is written on the store's own thread after the job ends, and
        # the runner reads a failed write every PLANNER_CHECK_CYCLES cycles: it latches then.
        wait_for(lambda: bool(runner.fault()), "the runner latching the store's failed write")
    if clock.crashed.is_set():
        _crash_and_restart(result, store, hil, clock, job.id, restart)
        return
    before = None
    if clock.inject_error:
        raise ConfigurationError(f"the injection failed: {clock.inject_error}")
    if math.isnan(clock.injected_at):
        result.error = "the job ended before the fault's time"
        result.digs = len(store.get(job.id).digs)
        return
    if runner.fault():
        wait_for(lambda: runner.state().endswith("waiting for reset-fault"), "the latch")
        result.outcome = "stopped"
        result.fault = runner.fault()
        result.detection_s = runner.fault_at_s - clock.injected_at
        digs_at_fault = len(store.get(job.id).digs)
        before = runner.rx_counts()
        clock.reset_at = clock.now()  # the loop has ended: the clock stands still
        hil.clear_faults()
        if clock.undo is not None:
            clock.undo()
        number = runner.reset_fault()
        wait_for(lambda: runner.resets_done >= number, "the reset")
        if runner.fault():
            result.error = f"the reset failed: {runner.fault()}"
        else:
            store.changed.set()
            wait_for(
                lambda: (
                    store.get(job.id).status in (JobStatus.DONE, JobStatus.FAILED)
                    or bool(runner.fault())
                ),
                "the resumed job ending",
            )
        final = store.get(job.id)
        result.digs = len(final.digs)
        result.resumed = final.status is JobStatus.DONE and result.digs >= case.digs
        result.lost_job = result.digs < digs_at_fault
        if not result.resumed and not result.error:
            result.error = f"not resumed: job {final.status.label}, {final.fault or runner.fault()}"
    else:
        final = store.get(job.id)
        result.digs = len(final.digs)
        result.outcome = "ridden_through" if final.status is JobStatus.DONE else "failed"
        result.resumed = final.status is JobStatus.DONE
        result.lost_job = final.status is not JobStatus.DONE
        if final.status is not JobStatus.DONE:
            result.error = f"job {final.status.label}: {final.fault}"
    counts = runner.rx_counts()
    result.rode_through = counts.to_json() if counts is not None else {}
    if result.outcome == "stopped" and before is not None:  # the boot before the reset's too
        for key, value in before.to_json().items():
            result.rode_through[key] = result.rode_through.get(key, 0) + value


def _crash_and_restart(
    result: CaseResult,
    store: JobStore,
    hil: LockstepHil,
    clock: _CaseClock,
    job_id: int,
    restart: Callable[[], tuple[RigRunner, JobStore]],
) -> None:
    """A crashed daemon: its loop hangs (nothing more is sent), its bus end is gone, its store
    is what it had written; the world goes on for :data:`RESTART_S` (the drives' watchdogs stop
    them: the detection is the first drive out of operation enabled), then a new runner reads
    the store and must resume the job at its next undone dig.

    The old store's writer is stopped with what it had queued written: a crash can also cut a
    write short, which the store's atomic replace survives (``tests/test_jobstore.py`` kills a
    writer at random moments)."""
    digs_at_crash = len(store.get(job_id).digs)
    store.close()
    hil.reopen_master_bus()  # the crashed process's socket: closed
    nodes, plant = hil.core.nodes, hil.core.plant
    period = hil.period_s
    rate_limit = StrokeLimits.from_rig(hil.core.rig).as_arrays()[0]
    peak = 0.0  # the plant's stroke rate from the detection on, as a fraction of the limit
    t = clock.now()
    end = t + RESTART_S
    while t < end:
        t = min(t + period, end)
        hil.clock.sleep_until(t)
        if math.isnan(result.detection_s) and any(
            n.firmware.state is not DeviceState.OPERATION_ENABLED for n in nodes
        ):
            result.detection_s = clock.now() - clock.injected_at
        if not math.isnan(result.detection_s):
            rate = plant.stroke_rate_m_s
            if hil.core.swing is not None:  # the swing's rate (rad/s) is its axis's
                rate = np.append(rate, hil.core.swing.omega_rad_s)
            peak = max(peak, float(np.max(np.abs(rate) / rate_limit)))
    result.plant_peak_v = peak
    if peak > 1.0 + PLANT_RATE_MARGIN:
        result.violations.append(f"the plant's stroke rate {peak:.3f} of the limit")
    result.outcome = "stopped"
    result.fault = "the daemon crashed; the drives stopped on their own"
    clock.reset_at = clock.now()
    runner, again = restart()
    runner.start()
    wait_for(lambda: runner.health()[0] or bool(runner.fault()), "the restarted runner holding")
    again.changed.set()
    wait_for(
        lambda: (
            again.get(job_id).status in (JobStatus.DONE, JobStatus.FAILED) or bool(runner.fault())
        ),
        "the resumed job ending",
    )
    final = again.get(job_id)
    result.digs = len(final.digs)
    result.resumed = final.status is JobStatus.DONE and result.digs >= result.case.digs
    result.lost_job = result.digs < digs_at_crash
    if not result.resumed:
        result.error = f"not resumed: job {final.status.label}, {final.fault or runner.fault()}"
    counts = runner.rx_counts()
    result.rode_through = counts.to_json() if counts is not None else {}


def _check_stop(
    result: CaseResult,
    rig: Rig,
    cfg: DaemonConfig,
    clock: _CaseClock,
    t_truth: np.ndarray,
    stroke_truth: np.ndarray,
) -> None:
    """The stop's checks on the master's frames and the plant (see the module docstring)."""
    if result.outcome != "stopped" or not math.isfinite(result.detection_s):
        return
    period = cfg.loop.period_s
    t_detect = clock.injected_at + result.detection_s
    nodes = [n.node_id for n in clock.hil.core.nodes]  # axis order, as the limits
    if result.case.kind in _SEEN_IN_MOTION:
        job_limits = ExecutorConfig(stale_cycles=cfg.stale_cycles).limits(rig)
        swing = result.case.target == "swing"  # its own window, in rad
        window = job_limits.swing_following_error_rad if swing else job_limits.following_error_m
        axis = rig_axes.names(rig).index(result.case.target)
        exposed = _exposed(
            clock,
            RPDO1.cob_id(nodes[axis]),
            clock.injected_at,
            window,
            t_truth,
            stroke_truth[:, axis] if stroke_truth.ndim == 2 else np.empty(0),
        )
        shown = max(clock.injected_at, min(exposed, t_detect))
        result.shown_s = shown - clock.injected_at
        result.detection_s = t_detect - shown
    rpdo1 = {RPDO1.cob_id(n): i for i, n in enumerate(nodes)}
    rpdo2 = {RPDO2.cob_id(n): i for i, n in enumerate(nodes)}
    limits = StrokeLimits.from_rig(rig)
    span = 25  # the jerk check's span: history before the detection
    rows: list[list[int]] = [[] for _ in nodes]
    vel: list[list[int]] = [[] for _ in nodes]
    sent: dict[str, int] = {}
    enabling = 0
    first_after: list[int | None] = [None] * len(nodes)
    for t, cob, data in clock.frames:
        if t >= clock.reset_at:
            break
        after = t >= t_detect - 0.5 * period
        if cob in rpdo1 and len(data) == RPDO1.size:
            axis = rpdo1[cob]
            target, velocity = RPDO1.codec.unpack(data)
            if after and first_after[axis] is None:
                first_after[axis] = len(rows[axis])
            rows[axis].append(target)
            vel[axis].append(velocity)
        if not after:
            continue
        name = (
            "rpdo1"
            if cob in rpdo1
            else "rpdo2"
            if cob in rpdo2
            else ("sync" if cob == 0x080 else "nmt")
        )
        sent[name] = sent.get(name, 0) + 1
        if cob in rpdo2 and len(data) >= 2:
            word = int.from_bytes(data[:2], "little")
            if word in _ENABLING:
                enabling += 1
    result.sent_after_detection = sent
    if enabling:
        result.violations.append(f"{enabling} controlword(s) enabling operation after the stop")
    starts = [f for f in first_after if f is not None]
    if starts and all(len(r) for r in rows):
        start = max(0, min(starts) - span)
        n = min(len(r) for r in rows)
        target = np.array([r[start:n] for r in rows], dtype=np.int64).T
        velocity = np.array([v[start:n] for v in vel], dtype=np.int64).T
        if len(target) >= 3:
            check = check_setpoint_trace(target, limits, period, velocity_um_s=velocity)
            peak = {
                "v": float(np.max(check.velocity)),
                "a": float(np.max(check.acceleration)),
                "j": float(np.max(check.jerk)),
            }
            result.stop_peak = peak
            for key, value in peak.items():
                if value > 1.0:
                    result.violations.append(f"stop peak {key} {value:.3f} of the limit")
            steps = np.abs(np.diff(target * 1e-6, axis=0)).max(axis=1)
            moving = (steps > _REST_STEP_M)[min(starts) - start :].astype(np.int64)
            # At rest: _REST_FRAMES periods in a row without a step (a jerk-limited stop
            # never pauses that long on its way down).
            still = np.convolve(1 - moving, np.ones(_REST_FRAMES, np.int64), "valid")
            rested = np.flatnonzero(still == _REST_FRAMES)
            if rested.size:
                moved = int(np.count_nonzero(moving[int(rested[0]) + _REST_FRAMES :]))
                if moved:
                    result.violations.append(
                        f"the commanded stroke moved {moved} time(s) after coming to rest"
                    )
    if len(t_truth) > 2:
        sel = (t_truth >= t_detect) & (t_truth < clock.reset_at)
        if np.count_nonzero(sel) > 3:
            dt = np.diff(t_truth[sel])
            ok = dt > 0.5 * period  # SYNCs a stalled loop sends back to back: no rate
            v = np.abs(np.diff(stroke_truth[sel], axis=0))[ok] / dt[ok, None]
            peak_v = float(np.max(v / limits.as_arrays()[0]))
            result.plant_peak_v = peak_v
            if peak_v > 1.0 + PLANT_RATE_MARGIN:
                result.violations.append(f"the plant's stroke rate {peak_v:.3f} of the limit")
    if result.detection_s > result.bound_s:
        result.violations.append(
            f"detected after {result.detection_s * 1e3:.1f} ms > {result.bound_s * 1e3:.1f} ms"
        )


def _exposed(
    clock: _CaseClock,
    cob_of_axis: int,
    t_s: float,
    window_m: float,
    t_truth: np.ndarray,
    truth: np.ndarray,
) -> float:
    """When a stuck axis could first show: the stroke commanded in the case's axis's RPDO1
    (``cob_of_axis``) first more than ``window_m`` (the following-error monitor's window, m;
    the swing's rad) from where the axis truly is (``truth`` at ``t_truth``: its plant's
    stroke, m, or angle, rad), after ``t_s``; for a rock, that far on into the rock.

    Measured against the true stroke, not against where the axis was at ``t_s``: a jammed or
    rock-stopped hydraulic axis creeps on on its oil column, and its error grows only as fast
    as the command outruns that creep; an electric axis stops where it stuck, and the two
    are the same. Without a truth (none recorded), from the stroke commanded at ``t_s``.
    inf: never before the reset."""
    way = clock.rock_direction
    first = math.nan
    window_um = window_m * 1e6
    with_truth = t_truth.shape[0] >= 2 and truth.shape[0] == t_truth.shape[0]
    for t, cob, data in clock.frames:
        if cob != cob_of_axis or len(data) != RPDO1.size:
            continue
        target = _target_um(data)
        if t <= t_s or math.isnan(first):
            first = target
            continue
        where = float(np.interp(t, t_truth, truth)) * 1e6 if with_truth else first
        ahead = (target - where) * way if way else abs(target - where)
        if ahead > window_um:
            return t
    return math.inf


# -- the campaign -------------------------------------------------------------------------------


def taught_case_job(rig: Rig, out_dir: Path, cycles: int) -> Path:
    """The case job of a rig with swing: a taught trench of ``cycles`` cycles, taught from the
    simulated operator's demonstrations (:data:`TAUGHT_SEEDS`, the pipeline's default
    settings), written as ``teach --out`` writes it; returns its ``taught.json``.

    Raises:
        ConfigurationError, PlanningError: As ``teach`` (no swing, no plan).
    """
    from hil_sim.operator import demonstrate, write_csv
    from rt_runtime.teach import pipeline
    from rt_runtime.teach.command import teach_report
    from rt_runtime.teach.demos import read_demo

    out_dir.mkdir(parents=True, exist_ok=True)
    records = []
    for seed in TAUGHT_SEEDS:
        path = out_dir / f"demo_{seed}.csv"
        write_csv(demonstrate(rig, seed=seed), path)
        records.append(read_demo(rig, path))
    taught = pipeline.teach(rig, records, pipeline.TeachSettings(cycles=cycles))
    report = teach_report(rig, records, taught, timing_ms={})
    file = out_dir / "taught.json"
    file.write_text(json.dumps(report, indent=1))
    load_taught(file, rig)  # verified as the runner will load it
    return file


def _run_one(args: tuple[Case, str, str | None, str | None]) -> dict[str, Any]:
    case, rig_name, out, taught = args
    try:
        result, trace = run_case(case, rig_name, taught)
    except Exception as exc:  # a bug in a case must not end the campaign: it is reported
        result, trace = CaseResult(case, error=f"{type(exc).__name__}: {exc}"), {}
    # The runner freezes the heap (gc.freeze) at its boots and jobs: what this case froze is
    # garbage now, and a worker runs case after case.
    gc.unfreeze()
    gc.collect()
    row = result.to_json()
    if out is not None and not result.safe and trace:
        path = Path(out) / f"case-{case.number}.npz"
        frames = trace["frames"]
        np.savez_compressed(
            path,
            frame_t_s=np.array([f[0] for f in frames]),
            frame_cob=np.array([f[1] for f in frames], dtype=np.int32),
            frame_data=np.array([f[2].ljust(8, b"\0") for f in frames], dtype="S8"),
            truth_t_s=trace["t_s"],
            truth_stroke_m=trace["stroke_m"],
        )
        row["trace"] = str(path)
    return row


def run_campaign(
    cases: Sequence[Case], rig_name: str = "scale_model", jobs: int | None = None,
    out: str | None = None,
) -> dict[str, Any]:  # fmt: skip
    """Run the cases over ``jobs`` processes (default: the CPUs); the report (see the README:
    ``kinds``, ``cases``, ``summary``). With ``out``, each case's row is written to
    ``out/cases.jsonl`` as it ends and the report to ``out/campaign.json`` at the end."""
    wall0 = time.monotonic()
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
    rig = load_rig(rig_name)
    taught_dir = None
    taught: dict[int, str] = {}
    if rig.swing is not None:  # its cases run a taught trench, one per cycle count
        taught_dir = tempfile.TemporaryDirectory(prefix="excavator-campaign-taught-")
        for digs in sorted({c.digs for c in cases}):
            where = Path(taught_dir.name) / f"cycles-{digs}"
            taught[digs] = str(taught_case_job(rig, where, digs))
    work = [(c, rig_name, out, taught.get(c.digs)) for c in cases]
    workers = max(1, min(jobs or os.cpu_count() or 1, len(work)))
    rows: list[dict[str, Any]] = []
    log = None if out is None else (Path(out) / "cases.jsonl").open("w")

    def keep(row: dict[str, Any]) -> None:
        """A finished case: kept, one line in ``cases.jsonl`` (a long run that is stopped
        keeps what it ran), and one progress line on stderr when it writes to a directory."""
        rows.append(row)
        if log is not None:
            log.write(json.dumps(row) + "\n")
            log.flush()
            mark = "safe" if row["safe"] else "NOT SAFE"
            print(
                f"case {len(rows)}/{len(work)}: {row['kind']} on {row['target']} at "
                f"{row['at_s']} s: {row['outcome']}, {mark}",
                file=sys.stderr,
                flush=True,
            )

    try:
        if workers == 1:
            for w in work:
                keep(_run_one(w))
        else:
            # A fresh pool for every CASES_PER_WORKER cases a worker (Python 3.11's
            # max_tasks_per_child deadlocks when a worker retires: CPython gh-115634).
            batch = workers * CASES_PER_WORKER
            for first in range(0, len(work), batch):
                with ProcessPoolExecutor(workers) as pool:
                    for row in pool.map(_run_one, work[first : first + batch]):
                        keep(row)
    finally:
        if log is not None:
            log.close()
        if taught_dir is not None:
            taught_dir.cleanup()
    kinds = sorted({c.kind.label for c in cases})
    stopped = [r for r in rows if r["outcome"] == "stopped"]
    detection: dict[str, dict[str, float | None]] = {}
    for kind in kinds:
        d = [r["detection_s"] for r in stopped if r["kind"] == kind]
        d = [x for x in d if x is not None]
        bound = next((r["bound_s"] for r in rows if r["kind"] == kind), None)
        detection[kind] = {
            "max_s": max(d) if d else None,
            "median_s": float(np.median(d)) if d else None,
            "bound_s": bound,
        }
    summary = {
        "cases": len(rows),
        "safe": sum(1 for r in rows if r["safe"]),
        "violations": sum(len(r["violations"]) for r in rows),
        "lost_jobs": sum(1 for r in rows if r["lost_job"]),
        "stopped": len(stopped),
        "ridden_through": sum(1 for r in rows if r["outcome"] == "ridden_through"),
        "as_expected": sum(1 for r in rows if r["outcome"] == r["expected"]),
        "resumed": sum(1 for r in stopped if r["resumed"]),
        "errors": sum(1 for r in rows if r["error"]),
        "wall_s": time.monotonic() - wall0,
        "workers": workers,
    }
    report = {
        "kinds": kinds,
        "rig": rig_name,
        "rules": {k.label: {"expected": RULES[k].outcome, "how": RULES[k].why} for k in RULES},
        "detection": detection,
        "cases": rows,
        "summary": summary,
    }
    if out is not None:
        (Path(out) / "campaign.json").write_text(json.dumps(report, indent=1))
    return report


# -- command line -------------------------------------------------------------------------------


def _kinds(text: str) -> list[FaultKind]:
    out = []
    for word in (w.strip() for w in text.split(",") if w.strip()):
        try:
            out.append(FaultKind[word.upper()])
        except KeyError:
            allowed = ", ".join(k.label for k in FaultKind)
            raise argparse.ArgumentTypeError(f"--kinds {word!r}; allowed: {allowed}") from None
    if not out:
        raise argparse.ArgumentTypeError("--kinds needs at least one kind")
    return out


def _axes(text: str) -> list[str]:
    out = [w.strip() for w in text.split(",") if w.strip()]
    allowed = (*AXES, "swing")
    bad = [a for a in out if a not in allowed]
    if bad or not out:
        raise argparse.ArgumentTypeError(
            f"--axes {text!r}; allowed: {', '.join(allowed)} (swing on a rig with swing)"
        )
    return out


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``campaign`` to the ``hil`` command's sub-commands."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "campaign",
        help="run the fault matrix on the daemon's runner in the lockstep HIL",
        description="Every fault kind on every target at drawn times: detection, the stop's "
        "peaks, what was sent after detection, the resume. One table.",
    )
    p.add_argument("--kinds", type=_kinds, default=None, help="comma-separated fault kinds")
    p.add_argument("--axes", type=_axes, default=None, help="comma-separated axes")
    p.add_argument("--seeds", type=int, default=10, help="times drawn per kind and target")
    p.add_argument("--seed", type=int, default=0, help="seed of the times and the wire")
    p.add_argument(
        "--digs",
        type=int,
        default=2,
        help="digs of each case's job (on a rig with swing: cycles of its taught trench)",
    )
    p.add_argument("--rig", default="scale_model", help="rig profile name or TOML file")
    p.add_argument("--jobs", type=int, default=None, help="worker processes (default: CPUs)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.add_argument("--out", default=None, metavar="DIR", help="write the table and traces here")
    p.set_defaults(handler=main)
    return p


def format_report(report: dict[str, Any]) -> str:
    """The table as text: a line per case, then the summary."""
    lines = [
        f"{'#':>4} {'kind':<16} {'target':<7} {'at_s':>6} {'outcome':<15} {'det_ms':>7} "
        f"{'bound':>7} {'v':>5} {'a':>5} {'j':>5} {'res':>4} safe"
    ]
    for r in report["cases"]:
        peak = r["stop_peak"]

        def f(x: float | None, scale: float = 1.0, width: int = 5) -> str:
            return (
                f"{x * scale:>{width}.{1 if scale > 1 else 2}f}"
                if x is not None
                else " " * (width - 1) + "-"
            )

        lines.append(
            f"{r['number']:>4} {r['kind']:<16} {r['target']:<7} {r['at_s']:>6.2f} "
            f"{r['outcome']:<15} {f(r['detection_s'], 1e3, 7)} {f(r['bound_s'], 1e3, 7)} "
            f"{f(peak.get('v'))} {f(peak.get('a'))} {f(peak.get('j'))} "
            f"{'yes' if r['resumed'] else 'no':>4} {'yes' if r['safe'] else 'NO'}"
            + (f"  {'; '.join(r['violations'])}" if r["violations"] else "")
            + (f"  error: {r['error']}" if r["error"] else "")
        )
    s = report["summary"]
    lines.append(
        f"{s['cases']} cases: {s['safe']} safe, {s['violations']} violations, "
        f"{s['lost_jobs']} lost jobs, {s['stopped']} stopped ({s['resumed']} resumed), "
        f"{s['ridden_through']} ridden through, {s['as_expected']} as expected; "
        f"{s['wall_s']:.0f} s on {s['workers']} worker(s)"
    )
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    """``excavator-rt hil campaign``: 0 when every case is safe, 1 otherwise, 2 for bad input."""
    try:
        rig = load_rig(args.rig)
        if args.digs < 1:
            raise ConfigurationError(f"--digs {args.digs} must be >= 1")
        cases = matrix(
            args.kinds, args.axes, args.seeds, args.seed, args.digs, rig.swing is not None
        )
    except ConfigurationError as exc:
        print(f"excavator-rt hil campaign: {exc}", file=sys.stderr)
        return 2
    if args.jobs is not None and args.jobs < 1:
        print(f"excavator-rt hil campaign: --jobs {args.jobs} must be >= 1", file=sys.stderr)
        return 2
    report = run_campaign(cases, str(args.rig) if rig is not None else "scale_model", args.jobs,
                          args.out)  # fmt: skip
    print(json.dumps(report) if args.json else format_report(report))
    s = report["summary"]
    return 0 if s["safe"] == s["cases"] else 1
