"""The HIL in real time: its own process, wall clock, the bus bridged over 127.0.0.1 only.

Role: the second transport of DESIGN.md "Loop, HIL and time" (daemon tests, timing). The HIL
process runs :class:`~hil_sim.sim.HilCore` on python-can's ``virtual`` interface and serves that
bus with python-can-remote's :class:`can_remote.RemoteServer` bound to ``127.0.0.1`` (never any
other address; port 0 takes a free one). The runtime connects with python-can's ``remote``
interface (``can_remote.RemoteBus("ws://127.0.0.1:<port>/")``), a websocket bridge, and drives
it with :class:`rt_runtime.control.MonotonicClock`.

Time: the HIL's clock is ``time.monotonic()`` since start. Its loop waits for a frame at most
``poll_s`` (0.5 ms), advances drives and plant to the current time in whole servo sub-steps,
answers the frame at its arrival time (SYNC: truth sampled, TPDOs sent), then runs the nodes'
time supervision. When the process falls behind (a terrain cut, a scheduler stall) it catches up
in a batch of sub-steps; the drives then answer late, which the master sees as it would on a
rig.

Control of the process (:class:`RealtimeHilProcess`): one line commands on stdin
(``inject <kind> <axis>``, ``cut <sync_from> <sync_to>``, ``stop``), answers on stdout
(``READY <port>``, ``CUT <m3>``). On ``stop``, on end of stdin (the parent died) or after
``--max-wall-s`` it writes its truth (``numpy.savez``: :class:`~hil_sim.sim.Truth` arrays, the
terrain's material as WKB, its loop statistics) and exits, so a test can never leave it running.

Scheduling: the process stands in for drive firmware, which a loaded rig PC never stalls, so it
asks for SCHED_FIFO (``--rt-priority``, default :data:`HIL_RT_PRIORITY` from
:meth:`RealtimeHilProcess.start`) before it starts any thread, and every thread (bridge, stdin)
inherits it. It sits below the control loop's priority, waits in ``recv`` between frames
(~10 % of a core at 500 Hz), and where SCHED_FIFO is refused it says so on stderr and runs on.

Run by hand:
``python -m hil_sim.harness.realtime --rig scale_model --q0 0.5 -1.5 -1.0 --port 54701``.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import math
import os
import queue
import select
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
from can.interfaces.virtual import VirtualBus

from hil_sim.sim import COB_SYNC, FaultKind, HilCore, Truth, open_trace
from hil_sim.terrain import Terrain
from rt_runtime.control import MonotonicClock
from rt_runtime.control.rt import RtSettings, apply_rt
from rt_runtime.errors import CommunicationError
from rt_runtime.rig import load_rig

__all__ = ["HOST", "RealtimeHilProcess", "main", "serve"]

#: The only address the bridge binds.
HOST = "127.0.0.1"
#: SCHED_FIFO priority of the HIL process by default (below the loop's: 80, the daemon's default).
HIL_RT_PRIORITY = 30


def serve(args: argparse.Namespace) -> int:
    """The HIL process: bridge, core, loop (see the module docstring)."""
    from can_remote import RemoteServer

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
    # The bridge's threads forward frames; a short switch interval keeps them from waiting
    # 5 ms (the default) for the loop to give up the interpreter.
    sys.setswitchinterval(2e-4)
    rig = load_rig(args.rig)
    if args.sync_timeout_ms is not None:
        drives = dataclasses.replace(rig.drives, sync_timeout_s=args.sync_timeout_ms * 1e-3)
        rig = dataclasses.replace(rig, drives=drives)
    terrain = None
    if args.terrain is not None:
        ground, x_lo, x_hi, width = args.terrain
        terrain = Terrain(ground, (x_lo, x_hi), width)
    core = HilCore(
        rig,
        np.asarray(args.q0, dtype=np.float64),
        terrain,
        period_s=args.period,
        vcu=not args.no_vcu,
    )
    if args.trace:
        core.trace = open_trace(args.trace)
    channel = f"excavator-hil-rt-{os.getpid()}"
    bus = VirtualBus(channel=channel)
    # The bridge keeps each frame's own timestamp (the master stamps its send time) instead of
    # restamping it when the bridge thread gets to run: on a loaded host that thread runs in
    # bursts, and restamped SYNCs would reach the drives bunched, as if the master had sent
    # several periods of motion within a fraction of one (a following error made by the harness).
    server = RemoteServer(
        HOST, args.port, interface="virtual", channel=channel, preserve_timestamps=True
    )
    threading.Thread(target=server.serve_forever, name="bridge", daemon=True).start()
    commands: queue.Queue[str] = queue.Queue()

    def read_stdin() -> None:
        for line in sys.stdin:
            commands.put(line.strip())
        commands.put("stop")

    threading.Thread(target=read_stdin, name="stdin", daemon=True).start()
    print(f"READY {server.server_port}", flush=True)

    t0 = time.monotonic()
    servo = rig.drives.servo_period_s
    t_core = 0.0
    lateness: list[float] = []
    sent = 0

    def send(frames: list[tuple[int, bytes]], now: float) -> None:
        nonlocal sent
        for arbitration_id, data in frames:
            core.log(arbitration_id, data, now, is_rx=False)
            bus.send(can.Message(arbitration_id=arbitration_id, is_extended_id=False, data=data))
            sent += 1

    send(core.pending_frames(0.0), 0.0)
    # Frames carry the master's send time (time.time(), kept by the bridge); the HIL handles
    # each at that moment on its own clock, so a stall of this process (or of its bridge
    # thread) delays the answers but does not make the drives see gaps or bunches in the
    # master's SYNCs that were not on the bus.
    epoch_offset = time.time() - time.monotonic() + t0
    gc.freeze()
    running = True
    while running:
        msg = bus.recv(timeout=args.poll)
        while msg is not None:
            now = time.monotonic() - t0
            # An unstamped frame (a client that does not stamp) arrives now.
            arrival = min(msg.timestamp - epoch_offset, now) if msg.timestamp > 0.0 else now
            arrival = max(arrival, t_core)
            steps = math.floor((arrival - t_core) / servo + 1e-9)
            if steps > 0:
                core.advance(steps * servo)
                t_core += steps * servo
            if not msg.is_error_frame:
                data = bytes(msg.data)
                core.log(msg.arbitration_id, data, arrival, is_rx=True)
                send(core.on_frame(msg.arbitration_id, data, arrival), arrival)
                if msg.arbitration_id == COB_SYNC:
                    lateness.append(time.monotonic() - t0 - arrival)
                    # Time supervision at every SYNC, on the bus's clock: a process that has
                    # fallen behind drains a backlog here without ever leaving this loop, and
                    # its nodes must keep producing heartbeats (and judging their watchdogs)
                    # while it catches up, not only once the backlog is gone.
                    send(core.pending_frames(arrival), arrival)
            msg = bus.recv(timeout=0.0)
        now = time.monotonic() - t0
        steps = math.floor((now - t_core) / servo + 1e-9)
        if steps > 0:
            core.advance(steps * servo)
            t_core += steps * servo
        send(core.pending_frames(now), now)
        while not commands.empty():
            words = commands.get().split()
            if not words:
                continue
            if words[0] == "inject":
                core.inject(FaultKind[words[1]], int(words[2]))
            elif words[0] == "cut":
                volume = core.cut(int(words[1]), int(words[2]))
                print(f"CUT {volume!r}", flush=True)
            elif words[0] == "stop":
                running = False
        if now > args.max_wall_s:
            running = False
    server.shutdown()
    server.server_close()
    if core.trace is not None:
        core.trace.stop()
    truth = core.truth()
    extra = {
        "material_wkb": np.frombuffer(
            core.terrain.material.wkb if core.terrain is not None else b"", dtype=np.uint8
        ),
        "frames_sent": np.array(sent),
        "sync_handling_s": np.array(lateness),
        "wall_s": np.array(time.monotonic() - t0),
    }
    if args.out:
        arrays: dict[str, Any] = {**truth.to_npz_dict(), **extra}
        np.savez(args.out, **arrays)
    bus.shutdown()
    return 0


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
    p.add_argument("--poll", type=float, default=5e-4, help="longest wait for a frame (s)")
    p.add_argument("--max-wall-s", type=float, default=600.0, help="stop after this long")
    p.add_argument("--out", default=None, help="write the truth here (.npz) at the end")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the HIL process."""
    return serve(_parser().parse_args(argv))


class RealtimeHilProcess:
    """The real-time HIL as a subprocess, and the runtime's bus end connected to it.

    Use :meth:`start`. Attributes ``master_bus`` (a python-can ``remote`` bus on 127.0.0.1) and
    ``clock`` (:class:`~rt_runtime.control.MonotonicClock`) go to the master and the streamer.
    """

    def __init__(self, proc: subprocess.Popen[str], port: int, out: Path, tmp: Any) -> None:
        from can_remote import RemoteBus

        self.proc = proc
        self.port = port
        self._out = out
        self._tmp = tmp
        self.clock = MonotonicClock()
        self.master_bus: can.BusABC = RemoteBus(f"ws://{HOST}:{port}/")
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
        if sync_timeout_s is not None:
            cmd += ["--sync-timeout-ms", repr(sync_timeout_s * 1e3)]
        if trace_path is not None:
            cmd += ["--trace", str(trace_path)]
        if rt_priority is not None:
            cmd += ["--rt-priority", str(rt_priority)]
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
        return cls(proc, int(line.split()[1]), out, tmp)

    def _command(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def inject(self, kind: FaultKind, axis: int) -> None:
        """Inject a fault in the HIL process now."""
        self._command(f"inject {kind.name} {axis}")

    def cut(self, sync_from: int, sync_to: int) -> float:
        """Cut the HIL's terrain with the true tip path between two SYNCs; the volume (m^3)."""
        self._command(f"cut {sync_from} {sync_to}")
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        return float(line.split()[1]) if line.startswith("CUT ") else 0.0

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
        extra: dict[str, Any] = {
            "hil_process": {
                "wall_s": float(data["wall_s"]),
                "frames_sent": int(data["frames_sent"]),
                "sync_handling_us": {
                    "p50": float(np.percentile(handling, 50)) if handling.size else math.nan,
                    "p99": float(np.percentile(handling, 99)) if handling.size else math.nan,
                    "max": float(np.max(handling)) if handling.size else math.nan,
                },
            }
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


if __name__ == "__main__":
    sys.exit(main())
