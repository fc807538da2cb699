"""The HIL in real time: its own process, wall clock, the bus bridged over 127.0.0.1 only.

Role: the second transport of DESIGN.md "Loop, HIL and time" (daemon tests, timing). The HIL
process runs :class:`~hil_sim.sim.HilCore` behind the websocket bridge of
:mod:`hil_sim.harness.bridge` (python-can-remote's protocol), bound to ``127.0.0.1`` (never any
other address; port 0 takes a free one), in one thread: no bus object between the socket and
the models. The runtime's end is a :class:`~hil_sim.bridge.BridgeBus` (python-can-remote's
``RemoteBus("ws://127.0.0.1:<port>/")``, the daemon's ``remote`` interface, connects as well),
driven with :class:`rt_runtime.control.MonotonicClock`.

Time: the HIL's clock is ``time.monotonic()`` since start. Its loop waits for bus bytes at most
until the next servo tick (and at most ``poll_s``, 0.5 ms), advances drives and plant to the
current time in whole servo sub-steps, answers each frame at its arrival time (SYNC: truth
sampled, TPDOs and the nodes' time supervision sent at once), then runs the nodes' time
supervision. When the process falls behind (a terrain cut, a scheduler stall) it catches up in
a batch of sub-steps; the drives then answer late, which the master sees as it would on a rig.
Per SYNC it records the time from the SYNC's stamp to its answers leaving (``sync_handling``)
and its own work on it; a SYNC answered more than one period after its stamp is a missed one.

Memory is bounded, so the process runs for hours at a flat size (``excavator-rt bench soak``
measures it): the truth keeps the last ``--truth-s`` seconds of SYNCs (default
:data:`TRUTH_S`; a ring allocated whole at the start, :class:`~hil_sim.sim.TruthRing`), and the
SYNC statistics keep counts and maxima over the whole run and the last :data:`SYNC_STATS_ROWS`
SYNCs for percentiles (:class:`SyncStats`). Nothing else grows per frame: the bridge's output
to a client that does not read is capped (:data:`hil_sim.harness.bridge.MAX_PENDING_BYTES`),
and the trace (``--trace``) goes to its file.

Faults: ``inject`` switches a drive fault on in a node, or a wire fault (the kinds of
:class:`~hil_sim.busfaults.BusFaults` but the master adapter's bus-off) on the frames to and
from a node or the whole bus: every frame the master sends passes the fault model before the
nodes see it, every frame the nodes send before it goes on the bridge, frames held back leave
when due, and an error frame goes to the master with each SYNC while some are owed. An inject
the process cannot take is refused on stderr; the process runs on.

Control of the process (:class:`RealtimeHilProcess`): one line commands on stdin
(``inject <kind> <axis> [<param>]``, ``cut <sync_from> <sync_to>``, ``scan <sync_from>``,
``stop``), answers on stdout (``READY <port>``, ``CUT <m3>``, ``SCAN <sync> <m3> <x> <y>``).
``scan`` is the rig's profile scanner (``--scanner``: ``[hil.scanner]`` of the profile, seeded
with ``hil.seed``, as the lockstep HIL's): the terrain is cut with the true tip path from
``sync_from + 1`` to the last SYNC received, then sampled; the answer carries that SYNC, the
volume cut and the samples (float64, base64). On ``stop``, on end of stdin (the parent died)
or after ``--max-wall-s`` it writes its truth (``numpy.savez``: :class:`~hil_sim.sim.Truth`
arrays, the terrain's material as WKB and its surface and volumes, its loop statistics, its
resident memory) and exits, so a test can
never leave it running.

Scheduling: the process stands in for drive firmware, which a loaded rig PC never stalls, so it
asks for SCHED_FIFO (``--rt-priority``, default :data:`HIL_RT_PRIORITY` from
:meth:`RealtimeHilProcess.start`) before it starts its stdin thread, which inherits it. It sits
below the control loop's priority, waits in ``select`` between servo ticks, and where SCHED_FIFO
is refused it says so on stderr and runs on.

Run by hand:
``python -m hil_sim.harness.realtime --rig scale_model --q0 0.5 -1.5 -1.0 --port 54701``.
"""

from __future__ import annotations

import argparse
import base64
import collections
import concurrent.futures
import contextlib
import ctypes
import dataclasses
import gc
import math
import multiprocessing
import os
import queue
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from hil_sim.bridge import FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE
from hil_sim.busfaults import BusFaults
from hil_sim.harness.bridge import Bridge, RxFrame
from hil_sim.scanner import ProfileScanner
from hil_sim.sim import COB_SYNC, FaultKind, HilCore, Truth, open_trace
from hil_sim.terrain import Terrain
from rt_runtime.control import MonotonicClock
from rt_runtime.control.rt import RtSettings, apply_rt
from rt_runtime.errors import CommunicationError
from rt_runtime.rig import load_rig

__all__ = [
    "HOST",
    "SYNC_STATS_ROWS",
    "TRUTH_S",
    "RealtimeHilProcess",
    "SyncStats",
    "main",
    "process_memory_mb",
    "serve",
]

#: The only address the bridge binds.
HOST = Bridge.HOST
#: SCHED_FIFO priority of the HIL process by default (below the loop's: 80, the daemon's default).
HIL_RT_PRIORITY = 30
#: Seconds of truth the process keeps by default (the last ones; at the SYNC period given).
TRUTH_S = 300.0
#: <linux/prctl.h>: the signal a process gets when its parent ends.
_PR_SET_PDEATHSIG = 1
#: SYNCs whose timing the percentiles of :class:`SyncStats` are taken over (the last ones).
SYNC_STATS_ROWS = 1 << 17
_NOT_FOR_NODES = FLAG_EXTENDED | FLAG_REMOTE | FLAG_ERROR


def serve(args: argparse.Namespace) -> int:
    """The HIL process: bridge, core, loop (see the module docstring)."""
    if args.rt_priority is not None:
        only_fifo = RtSettings(
            sched_fifo_priority=args.rt_priority,
            lock_memory=False,
            cpu=None,
            timer_slack_ns=None,
            freeze_gc=False,
        )
        for item in apply_rt(only_fifo).refused:
            print(f"HIL: SCHED_FIFO {item.requested} refused ({item.reason}); running without",
                  file=sys.stderr)  # fmt: skip
    rig = load_rig(args.rig)
    if args.sync_timeout_ms is not None:
        drives = dataclasses.replace(rig.drives, sync_timeout_s=args.sync_timeout_ms * 1e-3)
        rig = dataclasses.replace(rig, drives=drives)
    terrain = None
    if args.terrain is not None:
        ground, x_lo, x_hi, width = args.terrain
        active = rig.hil.active() if rig.hil is not None else None
        material = active.material if active is not None else None
        terrain = Terrain(ground, (x_lo, x_hi), width, material=material)
    core = HilCore(
        rig,
        np.asarray(args.q0, dtype=np.float64),
        terrain,
        period_s=args.period,
        vcu=not args.no_vcu,
        truth_rows=max(2, math.ceil(args.truth_s / args.period) + 1),
        preallocate_truth=True,
    )
    scanner = None
    if args.scanner:
        spec = rig.hil.scanner if rig.hil is not None else None
        if terrain is None or spec is None or rig.hil is None:
            print("HIL: --scanner needs --terrain and the profile's [hil.scanner]", file=sys.stderr)
            return 2
        scanner = ProfileScanner(terrain, spec, seed=rig.hil.seed)
    if args.trace:
        core.trace = open_trace(args.trace)
    bridge = Bridge(args.port, channel_info=f"excavator-rt HIL ({rig.name})")
    commands: queue.SimpleQueue[str] = queue.SimpleQueue()

    def read_stdin() -> None:
        for line in sys.stdin:
            commands.put(line.strip())
        commands.put("stop")

    # Cuts and scans cut a copy of the terrain in a process of their own, one at a time, and
    # the copy takes the terrain's place between servo ticks: the drives answer every SYNC
    # meanwhile (a cut with its slump takes tens of ms, beyond the master's stale limit).
    terrain_commands: collections.deque[list[str]] = collections.deque()
    work: list[_TerrainWork] = []
    pool = (
        concurrent.futures.ProcessPoolExecutor(
            1,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_terrain_process_init,
        )
        if terrain is not None
        else None
    )
    if pool is not None:
        # Spawned and imported now, before READY: the first cut must not wait for it.
        pool.submit(_cut_copy, Terrain(0.0, (0.0, 1.0), 0.1), None).result()
    threading.Thread(target=read_stdin, name="stdin", daemon=True).start()
    print(f"READY {bridge.port}", flush=True)

    loop = _HilLoop(
        core, bridge, rig.drives.servo_period_s, args.period, BusFaults(args.fault_seed)
    )
    gc.freeze()
    running = True
    poll_s = args.poll
    while running:
        loop.run_once(poll_s)
        while not commands.empty():
            words = commands.get().split()
            if not words:
                continue
            if words[0] == "inject":
                try:
                    loop.inject(words[1:])
                except (KeyError, IndexError, ValueError) as exc:
                    print(f"HIL: inject {' '.join(words[1:])} refused: {exc}", file=sys.stderr)
            elif words[0] in ("cut", "scan"):
                terrain_commands.append(words)
            elif words[0] == "stop":
                running = False
        if work and work[0].done():
            print(work.pop().adopt(core, scanner), flush=True)
        if not work and terrain_commands:
            work.append(_TerrainWork.start(core, pool, scanner, terrain_commands.popleft()))
        if loop.now() > args.max_wall_s:
            running = False
    for pending in work:
        print(pending.adopt(core, scanner), flush=True)
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)
    bridge.close()
    if core.trace is not None:
        core.trace.stop()
    truth = core.truth()
    stats = loop.stats
    rss_mb, rss_max_mb = process_memory_mb()
    ground = core.terrain
    extra = {
        "terrain_x": ground.surface_x_m if ground is not None else np.zeros(0),
        "terrain_y": ground.surface_y_m if ground is not None else np.zeros(0),
        "terrain_m3": np.array(
            [ground.swept_m3, ground.load_m3, ground.fallback_m3, ground.slumped_m3]
            if ground is not None
            else []
        ),
        "material_wkb": np.frombuffer(
            core.terrain.material.wkb if core.terrain is not None else b"", dtype=np.uint8
        ),
        "frames_sent": np.array(loop.frames_sent),
        "frames_dropped": np.array(bridge.dropped),
        "syncs": np.array(stats.count),
        "missed_syncs": np.array(stats.missed),
        "sync_handling_s": stats.handling_s(),
        "sync_work_s": stats.work_s(),
        "sync_handling_max_s": np.array(stats.handling_max_s),
        "sync_work_max_s": np.array(stats.work_max_s),
        "truth_dropped": np.array(core.truth_ring.dropped),
        "rss_mb": np.array(rss_mb),
        "rss_max_mb": np.array(rss_max_mb),
        "wall_s": np.array(loop.now()),
    }
    if args.out:
        arrays: dict[str, Any] = {**truth.to_npz_dict(), **extra}
        np.savez(args.out, **arrays)
    return 0


def process_memory_mb(pid: int | str = "self") -> tuple[float, float]:
    """Resident memory of a process on Linux: ``(now, peak)`` in MB (10^6 bytes), from
    ``/proc/<pid>/status`` (``VmRSS``, ``VmHWM``).

    Raises:
        OSError: No such process (or no ``/proc``).
    """
    now_kb = peak_kb = 0
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                now_kb = int(line.split()[1])
            elif line.startswith("VmHWM:"):
                peak_kb = int(line.split()[1])
    return now_kb * 1024e-6, peak_kb * 1024e-6


class SyncStats:
    """The HIL's timing per SYNC in bounded memory.

    Counts and maxima cover every SYNC of the run; the values themselves are kept for the last
    ``rows`` SYNCs (two preallocated rings), which the percentiles are taken over.

    Args:
        rows: SYNCs whose values are kept (>= 1).
        period_s: SYNC period: a SYNC answered later than this after its stamp is missed.

    Attributes:
        count: SYNCs recorded.
        missed: SYNCs answered more than a period after their stamp.
        handling_max_s: Longest time from a SYNC's stamp to its answers leaving (s).
        work_max_s: Longest own work on a SYNC (s).
    """

    def __init__(self, rows: int, period_s: float) -> None:
        self.period_s = period_s
        self._handling = np.full(max(1, rows), np.nan)
        self._work = np.full(max(1, rows), np.nan)
        self.count = 0
        self.missed = 0
        self.handling_max_s = 0.0
        self.work_max_s = 0.0

    def record(self, handling_s: float, work_s: float) -> None:
        """One SYNC: from its stamp to its answers leaving, and the HIL's own work on it (s)."""
        i = self.count % len(self._handling)
        self._handling[i] = handling_s
        self._work[i] = work_s
        self.count += 1
        if handling_s > self.period_s:
            self.missed += 1
        if handling_s > self.handling_max_s:
            self.handling_max_s = handling_s
        if work_s > self.work_max_s:
            self.work_max_s = work_s

    def _ordered(self, ring: np.ndarray) -> np.ndarray:
        n = len(ring)
        if self.count <= n:
            return ring[: self.count].copy()
        i = self.count % n
        return np.concatenate((ring[i:], ring[:i]))

    def handling_s(self) -> np.ndarray:
        """The kept handling times, oldest first (s)."""
        return self._ordered(self._handling)

    def work_s(self) -> np.ndarray:
        """The kept own-work times, oldest first (s)."""
        return self._ordered(self._work)


class _HilLoop:
    """One iteration of the HIL process's loop at a time (:meth:`run_once`).

    The drives' servo ticks run on the wall clock: the loop waits for bus bytes at most until the
    next servo tick and advances the drives and plant at each tick, so a frame finds the model
    at most one sub-step behind its arrival. Each frame is handled at its arrival time (the
    sender's stamp mapped onto the HIL's clock, never before the model's time): the model is
    advanced to it in whole sub-steps, then the frame is answered; after a SYNC, the nodes' time
    supervision runs and the answers leave at once (:meth:`Bridge.flush`).

    Attributes:
        stats: Per SYNC, from its stamp to its answers leaving, and the HIL's own work on it
            (advance, answers, supervision): :class:`SyncStats`.
        frames_sent: Frames the HIL put on the bus.
    """

    def __init__(
        self,
        core: HilCore,
        bridge: Bridge,
        servo_s: float,
        period_s: float,
        faults: BusFaults,
    ) -> None:
        self.core = core
        self.bridge = bridge
        self.faults = faults
        self.servo_s = servo_s
        self.period_s = period_s
        self.t0 = time.monotonic()
        # Frames carry the master's send time (time.time()); the HIL handles each at that
        # moment on its own clock, so a stall of this process delays the answers but does not
        # make the drives see gaps or bunches in the master's SYNCs that were not on the bus.
        self.epoch_offset = time.time() - time.monotonic() + self.t0
        self.t_core = 0.0
        self.frames_sent = 0
        self.stats = SyncStats(SYNC_STATS_ROWS, period_s)
        self._send(core.pending_frames(0.0), 0.0)
        bridge.flush()

    def now(self) -> float:
        """Seconds on the HIL's clock."""
        return time.monotonic() - self.t0

    def send(self, frames: list[tuple[int, bytes]], now_s: float) -> None:
        """Put frames of the HIL's nodes on the bus now (an injected reboot's boot-up)."""
        self._send(frames, now_s)
        self.bridge.flush()

    def inject(self, words: list[str]) -> None:
        """``<KIND> <axis> [<param>]``: a drive fault in the axis's node, or a bus fault on
        the wire to and from it (axis -1: the whole bus), from now on.

        Raises:
            KeyError: An unknown kind.
            IndexError: No axis.
            ValueError: A kind of the rig PC's side (:attr:`FaultKind.on_rig_pc`), a bad
                axis or parameter.
        """
        kind = FaultKind[words[0]]
        axis = int(words[1])
        param = float(words[2]) if len(words) > 2 else None
        now = self.now()
        if kind.on_rig_pc:
            raise ValueError(f"{kind.label} acts on the rig PC's side, not in the HIL")
        if kind.layer == "bus":
            nodes = self.core.nodes
            if not -1 <= axis < len(nodes):
                raise ValueError(f"axis must be -1 (the bus) or 0..{len(nodes) - 1}; got {axis}")
            self.faults.inject(kind, None if axis < 0 else nodes[axis].node_id, param, now)
            return
        self.send(self.core.inject(kind, axis, param, now), now)

    def _send(self, frames: list[tuple[int, bytes]], now_s: float) -> None:
        faults = self.faults
        if faults.active:
            frames = [out for frame in frames for out in faults.to_master(frame, now_s)]
        self._put(frames, now_s)

    def _put(self, frames: list[tuple[int, bytes]], now_s: float) -> None:
        """Frames onto the wire as they reach the master (past the bus faults)."""
        core = self.core
        bridge = self.bridge
        for arbitration_id, data in frames:
            core.log(arbitration_id, data, now_s, is_rx=False)
            bridge.send(arbitration_id, data)
        self.frames_sent += len(frames)

    def _advance_to(self, t_s: float) -> None:
        servo = self.servo_s
        steps = math.floor((t_s - self.t_core) / servo + 1e-9)
        if steps > 0:
            self.core.advance(steps * servo)
            self.t_core += steps * servo

    def on_frame(self, frame: RxFrame) -> None:
        """One frame from the bus, handled at its arrival time; the drives and the VCU take
        standard-id data frames only (an extended, remote or error frame is not theirs)."""
        stamp, arbitration_id, data, flags = frame
        started = time.monotonic()
        now = started - self.t0
        # An unstamped frame (a client that does not stamp) arrives now.
        arrival = min(stamp - self.epoch_offset, now) if stamp > 0.0 else now
        arrival = max(arrival, self.t_core)
        self._advance_to(arrival)
        if flags & _NOT_FOR_NODES:
            return
        faults = self.faults
        if faults.active:
            if arbitration_id == COB_SYNC and faults.error_frames_due():
                self.bridge.send(0, b"", FLAG_ERROR)
            for arrived in faults.to_hil((arbitration_id, data), arrival):
                self._handle(arrived[0], arrived[1], arrival, started)
            return
        self._handle(arbitration_id, data, arrival, started)

    def _handle(self, arbitration_id: int, data: bytes, arrival: float, started: float) -> None:
        """One frame reaches the nodes at ``arrival`` (HIL clock); after a SYNC the nodes' time
        supervision runs and the answers leave."""
        core = self.core
        core.log(arbitration_id, data, arrival, is_rx=True)
        self._send(core.on_frame(arbitration_id, data, arrival), arrival)
        if arbitration_id == COB_SYNC:
            # Time supervision at every SYNC, on the bus's clock: a process that has fallen
            # behind drains a backlog without leaving the receive path, and its nodes must keep
            # producing heartbeats (and judging their watchdogs) while it catches up.
            self._send(core.pending_frames(arrival), arrival)
            self.bridge.flush()
            done = time.monotonic()
            self.stats.record(done - self.t0 - arrival, done - started)

    def run_once(self, poll_s: float) -> None:
        """Wait for the bus until the next servo tick (at most ``poll_s``), handle what came,
        advance to now, run the nodes' time supervision."""
        wait = self.t_core + self.servo_s - self.now()
        if self.bridge.wait(min(wait, poll_s)):
            self.bridge.receive(self.on_frame)
        now = self.now()
        self._advance_to(now)
        if self.faults.active:  # frames the wire held back, now due
            to_hil, to_master = self.faults.due(now)
            for arbitration_id, data in to_hil:
                self._handle(arbitration_id, data, now, time.monotonic())
            self._put(to_master, now)
        self._send(self.core.pending_frames(now), now)
        self.bridge.flush()


class _TerrainWork:
    """One ``cut`` or ``scan`` command: the true tip path taken on the servo's thread, the cut
    of a copy of the terrain in the terrain process (``pool``; no GIL shared with the servo),
    then :meth:`adopt` on the servo's thread puts the cut copy in the terrain's place, lets
    the scanner look at it and gives the answer line."""

    def __init__(self, words: list[str], future: concurrent.futures.Future[Any] | None) -> None:
        self.words = words
        self.future = future
        self.last_sync = -1
        self.error = ""

    def done(self) -> bool:
        return self.future is None or self.future.done()

    @classmethod
    def start(
        cls,
        core: HilCore,
        pool: concurrent.futures.Executor | None,
        scanner: ProfileScanner | None,
        words: list[str],
    ) -> _TerrainWork:
        try:
            if words[0] == "cut":
                lo, hi = int(words[1]), int(words[2])
            else:
                lo, hi = int(words[1]) + 1, core.sync_count
        except (IndexError, ValueError) as exc:
            work = cls(words, None)
            work.error = f"{' '.join(words)}: {exc}"
            return work
        tip = core.tip_path(lo, hi)
        if pool is None or core.terrain is None or (words[0] == "scan" and scanner is None):
            return cls(words, None)
        work = cls(words, pool.submit(_cut_copy, core.terrain.copy(), tip))
        work.last_sync = hi
        return work

    def adopt(self, core: HilCore, scanner: ProfileScanner | None) -> str:
        """Put the cut copy in place (the scanner looks at it); the command's answer line."""
        volume = 0.0
        if self.future is not None:
            try:
                terrain, volume = self.future.result()
            except Exception as exc:  # the process goes on; the command says why
                self.error = f"{' '.join(self.words)}: {type(exc).__name__}: {exc}"
            else:
                core.adopt_terrain(terrain)
        if self.error:
            print(f"HIL: {self.error}", file=sys.stderr)
        if self.words[0] == "cut":
            return f"CUT {volume!r}"
        if scanner is None or core.terrain is None or self.error:
            return "SCAN -1"
        x, y = scanner.scan(core.terrain)
        return f"SCAN {self.last_sync} {volume!r} {_b64(x)} {_b64(y)}"


def _cut_copy(terrain: Terrain, tip: np.ndarray | None) -> tuple[Terrain, float]:
    """In the terrain process: ``terrain`` cut with ``tip`` (None: not cut) and the volume."""
    volume = terrain.cut(tip).volume_m3 if tip is not None else 0.0
    return terrain, volume


def _terrain_process_init() -> None:
    """The terrain process runs below the servo's thread (the default scheduler, niced) and
    ends with the HIL process, however that ends (``PR_SET_PDEATHSIG``)."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError):
        os.nice(5)
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(ctypes.c_int(_PR_SET_PDEATHSIG), ctypes.c_ulong(signal.SIGTERM))


def _b64(values: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(values, dtype="<f8").tobytes()).decode("ascii")


def _from_b64(text: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(text), dtype="<f8").astype(np.float64)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        "python -m hil_sim.harness.realtime", description=__doc__.split("\n")[0]
    )
    p.add_argument("--rig", default="scale_model")
    p.add_argument("--q0", type=float, nargs=3, required=True, help="initial joint angles (rad)")
    p.add_argument("--period", type=float, default=0.002, help="SYNC period (s)")
    p.add_argument(
        "--terrain",
        type=float,
        nargs=4,
        default=None,
        metavar=("GROUND_Y", "X_MIN", "X_MAX", "WIDTH"),
    )
    p.add_argument("--no-vcu", action="store_true")
    p.add_argument(
        "--scanner",
        action="store_true",
        help="emulate the profile's [hil.scanner] over the terrain (the scan command)",
    )
    p.add_argument(
        "--sync-timeout-ms",
        type=float,
        default=None,
        help="override the drives' SYNC/RPDO watchdog (rig.drives.sync_timeout_s)",
    )
    p.add_argument("--trace", default=None, help=".blf or .asc trace file")
    p.add_argument(
        "--rt-priority",
        type=int,
        default=None,
        help="SCHED_FIFO priority for the process (1..99; default: none)",
    )
    p.add_argument("--port", type=int, default=0, help="TCP port on 127.0.0.1 (0: any free)")
    p.add_argument(
        "--fault-seed", type=int, default=0, help="seed of the wire's random faults (bus kinds)"
    )
    p.add_argument("--poll", type=float, default=5e-4, help="longest wait for a frame (s)")
    p.add_argument("--max-wall-s", type=float, default=600.0, help="stop after this long")
    p.add_argument(
        "--truth-s",
        type=float,
        default=TRUTH_S,
        help=f"seconds of truth kept, the last ones (default {TRUTH_S:g}; memory is allocated "
        "for them at the start)",
    )
    p.add_argument("--out", default=None, help="write the truth here (.npz) at the end")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the HIL process."""
    return serve(_parser().parse_args(argv))


class RealtimeHilProcess:
    """The real-time HIL as a subprocess, and the runtime's bus end connected to it.

    Use :meth:`start`. Attributes ``master_bus`` (a :class:`~hil_sim.bridge.BridgeBus` on
    127.0.0.1) and
    ``clock`` (:class:`~rt_runtime.control.MonotonicClock`) go to the master and the streamer.
    """

    def __init__(
        self, proc: subprocess.Popen[str], port: int, out: Path, tmp: Any, period_s: float
    ) -> None:
        from hil_sim.bridge import BridgeBus

        self.proc = proc
        self.period_s = period_s
        self.port = port
        self._out = out
        self._tmp = tmp
        self.clock = MonotonicClock()
        # python-can-remote's own RemoteBus connects as well; this end sends without a thread.
        self.master_bus: can.BusABC = BridgeBus(port)
        # Commands come from several threads (fault injection, the dig-done callback, the
        # planner link's sender): one line and its answer at a time.
        self._lock = threading.Lock()
        self._finished: tuple[Truth, Any, list[tuple[int, bytes]], dict[str, Any]] | None = None

    @classmethod
    def start(
        cls,
        *,
        rig_name: str,
        q0_rad: Any,
        terrain: Terrain | None = None,
        period_s: float = 0.002,
        vcu: bool = True,
        trace_path: str | Path | None = None,
        max_wall_s: float = 600.0,
        ready_timeout_s: float = 30.0,
        sync_timeout_s: float | None = None,
        rt_priority: int | None = HIL_RT_PRIORITY,
        truth_s: float | None = None,
        scanner: bool = False,
    ) -> RealtimeHilProcess:
        """Start the HIL process and connect to it.

        Args:
            rig_name: Rig profile name or file.
            q0_rad: Initial joint angles.
            terrain: A terrain to rebuild in the process (flat ground, x range, width), or None.
            period_s: SYNC period.
            vcu: Put the VCU model on the bus.
            trace_path: The process writes the bus trace here.
            max_wall_s: The process stops by itself after this long.
            ready_timeout_s: Time allowed for the process to start serving.
            sync_timeout_s: Override the drives' SYNC/RPDO watchdog (a shared machine stalls
                longer than a rig PC), or None for the rig's.
            rt_priority: SCHED_FIFO priority of the process (see the module docstring), or
                None for the default scheduler.
            truth_s: Seconds of truth the process keeps (the last ones), or None for
                :data:`TRUTH_S`.
            scanner: Emulate the profile's scanner over ``terrain`` (:meth:`scan`).

        Raises:
            CommunicationError: The process did not report ready in time.
        """
        tmp = tempfile.TemporaryDirectory(prefix="excavator-hil-")
        out = Path(tmp.name) / "truth.npz"
        cmd = [
            sys.executable, "-m", "hil_sim.harness.realtime",
            "--rig", rig_name,
            "--q0", *(repr(float(v)) for v in q0_rad),
            "--period", repr(period_s),
            "--max-wall-s", repr(max_wall_s),
            "--out", str(out),
        ]  # fmt: skip
        if terrain is not None:
            x_lo, x_hi = terrain.x_range_m
            cmd += [
                "--terrain",
                *(
                    repr(float(v))
                    for v in (float(terrain.surface_y_m[0]), x_lo, x_hi, terrain.bucket_width_m)
                ),
            ]
        if not vcu:
            cmd.append("--no-vcu")
        if scanner:
            cmd.append("--scanner")
        if sync_timeout_s is not None:
            cmd += ["--sync-timeout-ms", repr(sync_timeout_s * 1e3)]
        if trace_path is not None:
            cmd += ["--trace", str(trace_path)]
        if rt_priority is not None:
            cmd += ["--rt-priority", str(rt_priority)]
        if truth_s is not None:
            cmd += ["--truth-s", repr(float(truth_s))]
        proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1
        )
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], ready_timeout_s)
        line = proc.stdout.readline() if ready else ""
        if not line.startswith("READY "):
            proc.kill()
            proc.wait()
            tmp.cleanup()
            raise CommunicationError(
                f"the real-time HIL did not start within {ready_timeout_s} s (said {line!r})"
            )
        return cls(proc, int(line.split()[1]), out, tmp, period_s)

    def _command(self, line: str) -> None:
        with self._lock:
            self._write(line)

    def _write(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def _ask(self, line: str, answer: str, timeout_s: float) -> list[str] | None:
        """Send ``line``, and the words of the next stdout line that starts with ``answer``
        (None when none came within ``timeout_s`` or the process is gone)."""
        assert self.proc.stdout is not None
        with self._lock:
            try:
                self._write(line)
            except (BrokenPipeError, ValueError):
                return None
            deadline = time.monotonic() + timeout_s
            while (left := deadline - time.monotonic()) > 0.0:
                ready, _, _ = select.select([self.proc.stdout], [], [], left)
                if not ready:
                    break
                reply = self.proc.stdout.readline()
                if not reply:
                    break
                if reply.startswith(answer + " "):
                    return reply.split()
        return None

    def inject(self, kind: FaultKind, axis: int, param: float | None = None) -> None:
        """Inject a fault in the HIL process now: a drive fault in the axis's node
        (:meth:`HilCore.inject`) or a bus fault on the wire to and from it, axis -1 the whole
        bus (:meth:`BusFaults.inject`, in the process's frame path both ways).

        Raises:
            ValueError: A host fault, or ``bus_off`` (the master's adapter goes bus-off, which
                the HIL's process cannot make: lockstep only), or a bus fault's parameter out
                of its range (checked here, where the caller sees it).
        """
        if kind.on_rig_pc:
            raise ValueError(
                f"{kind.label} acts on the rig PC's side (the master's adapter, loop, planner or "
                "store): the real-time HIL injects drive and wire faults; run it in lockstep"
            )
        if kind.layer == "bus":
            BusFaults().inject(kind, None, param, 0.0)  # the parameter's range, said here
        self._command(f"inject {kind.name} {axis}" + ("" if param is None else f" {param!r}"))

    def cut(self, sync_from: int, sync_to: int, timeout_s: float = 30.0) -> float:
        """Cut the HIL's terrain with the true tip path between two SYNCs; the volume (m^3),
        0 where no answer came within ``timeout_s``."""
        words = self._ask(f"cut {sync_from} {sync_to}", "CUT", timeout_s)
        return float(words[1]) if words is not None else 0.0

    def scan(
        self, sync_from: int, timeout_s: float = 5.0
    ) -> tuple[int, float, np.ndarray, np.ndarray] | None:
        """The profile scanner's look (started with ``scanner``): the terrain cut with the
        true tip path after SYNC ``sync_from`` up to the last SYNC the process received, then
        scanned. Waits at most ``timeout_s`` (not on the loop's thread).

        Returns:
            ``(last SYNC, volume cut (m^3), x_m, y_m)``, or None without a scanner or an
            answer in time.
        """
        words = self._ask(f"scan {sync_from}", "SCAN", timeout_s)
        if words is None or len(words) != 5:
            return None
        return int(words[1]), float(words[2]), _from_b64(words[3]), _from_b64(words[4])

    def finish(self) -> tuple[Truth, Any, list[tuple[int, bytes]], dict[str, Any]]:
        """Disconnect, stop the process and load its truth (idempotent).

        Returns:
            ``(truth, terrain material or None, [], extra report keys)``.
        """
        if self._finished is not None:
            return self._finished
        import shapely

        self.master_bus.shutdown()
        if self.proc.poll() is None:
            self._command("stop")
        self.proc.wait(timeout=30)
        data = np.load(self._out)
        truth = Truth.from_npz(data)
        wkb = bytes(data["material_wkb"])
        material = shapely.from_wkb(wkb) if wkb else None
        handling = np.asarray(data["sync_handling_s"]) * 1e6
        work = np.asarray(data["sync_work_s"]) * 1e6
        extra: dict[str, Any] = {
            "hil_process": {
                "wall_s": float(data["wall_s"]),
                "frames_sent": int(data["frames_sent"]),
                "frames_dropped": int(data["frames_dropped"]),
                "syncs": int(data["syncs"]),
                "missed_syncs": int(data["missed_syncs"]),
                "sync_handling_us": _spread(handling, float(data["sync_handling_max_s"]) * 1e6),
                "sync_work_us": _spread(work, float(data["sync_work_max_s"]) * 1e6),
                "truth_dropped": int(data["truth_dropped"]),
                "rss_mb": round(float(data["rss_mb"]), 1),
                "rss_max_mb": round(float(data["rss_max_mb"]), 1),
            }
        }
        if "terrain_m3" in data and len(data["terrain_m3"]) == 4:
            swept, load, fallback, slumped = (float(v) for v in data["terrain_m3"])
            extra["terrain"] = {
                "x_m": np.asarray(data["terrain_x"], dtype=np.float64),
                "y_m": np.asarray(data["terrain_y"], dtype=np.float64),
                "swept_m3": swept,
                "load_m3": load,
                "fallback_m3": fallback,
                "slumped_m3": slumped,
            }
        self._finished = (truth, material, [], extra)
        return self._finished

    def close(self) -> None:
        """Stop the process if it still runs (by its pid) and remove the temporary files."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                stream.close()
        self._tmp.cleanup()


def _spread(values_us: np.ndarray, max_us: float) -> dict[str, float]:
    """p50 and p99 of the kept values, the whole run's max (NaN when nothing was kept)."""
    if not values_us.size:
        return {"p50": math.nan, "p99": math.nan, "max": math.nan}
    return {
        "p50": float(np.percentile(values_us, 50)),
        "p99": float(np.percentile(values_us, 99)),
        "max": max_us,
    }


if __name__ == "__main__":
    sys.exit(main())
