"""``excavator-rt job ...``: the command-line client of the daemon's control socket.

::

    excavator-rt job submit --task A [--planner pinn|pso] [--max-digs N]
    excavator-rt job submit --task my_trench.toml      # read here, sent as numbers
    excavator-rt job submit --teach runs/taught        # a taught trench (rig with swing)
    excavator-rt job status [ID]
    excavator-rt job list
    excavator-rt job pause [ID] | resume ID | cancel ID
    excavator-rt job reset-fault [--wait-s S]

Every subcommand takes ``--socket PATH`` (default ``$EXCAVATOR_RTD_SOCKET`` or
``/run/excavator-rtd/control.sock``) and ``--json`` (print the daemon's reply object as is).
``reset-fault`` asks the daemon to reset its latched fault, then follows ``status`` until that
reset has ended (at most ``--wait-s``, default 60 s) and says how it went.
Exit codes: 0 done, 1 the daemon refused (the reason on stderr; a refusal because a fault is
latched has the code ``faulted``) or the reset failed, 2 no daemon to talk to.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from rt_runtime.service.config import DEFAULT_SOCKET, PLANNERS
from rt_runtime.service.control import request

__all__ = ["RESET_WAIT_S", "add_parser", "format_job", "format_progress", "run"]

#: Longest wait of ``job reset-fault`` for the reset's outcome (s).
RESET_WAIT_S = 60.0
#: Interval of the ``status`` requests while a reset runs (s).
_RESET_POLL_S = 0.2


def _default_socket() -> str:
    return os.environ.get("EXCAVATOR_RTD_SOCKET", str(DEFAULT_SOCKET))


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``job`` (and its subcommands) to the ``excavator-rt`` subcommands; handler :func:`run`.

    Args:
        subparsers: The ``add_subparsers()`` object of the main parser.

    Returns:
        The ``job`` parser (its handler is set).
    """
    p: argparse.ArgumentParser = subparsers.add_parser(
        "job",
        help="talk to the rig daemon excavator-rtd: submit, status, pause, resume, cancel, list, "
        "reset-fault",
        description="Client of excavator-rtd's control socket (docs/daemon.md).",
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--socket",
        default=_default_socket(),
        help="control socket (default: $EXCAVATOR_RTD_SOCKET or %(default)s)",
    )
    common.add_argument("--json", action="store_true", help="print the daemon's reply as JSON")
    sub = p.add_subparsers(dest="job_command", required=True, metavar="COMMAND")
    s = sub.add_parser("submit", parents=[common], help="queue a trench job or a taught job")
    what = s.add_mutually_exclusive_group(required=True)
    what.add_argument("--task", help="A, B, C, D (Yao Table 3) or a task TOML file")
    what.add_argument(
        "--teach",
        metavar="DIR",
        help="a taught trench (teach --out DIR) on a rig with swing; the daemon reads and "
        "verifies DIR/taught.json on this machine and keeps a copy",
    )
    s.add_argument("--planner", choices=PLANNERS, help="one-shot planner (daemon default)")
    s.add_argument("--max-digs", type=int, help="the job is done after this many digs")
    st = sub.add_parser("status", parents=[common], help="the daemon and a job (default: current)")
    st.add_argument("id", type=int, nargs="?")
    sub.add_parser("list", parents=[common], help="every job the daemon keeps")
    pa = sub.add_parser("pause", parents=[common], help="pause a job (default: the running one)")
    pa.add_argument("id", type=int, nargs="?")
    re = sub.add_parser("resume", parents=[common], help="resume a paused job, retry a failed one")
    re.add_argument("id", type=int)
    ca = sub.add_parser("cancel", parents=[common], help="cancel a job (the running one stops)")
    ca.add_argument("id", type=int)
    rf = sub.add_parser(
        "reset-fault",
        parents=[common],
        help="reset a latched fault: re-boot bus and drives, hold, queue the failed job again",
    )
    rf.add_argument(
        "--wait-s",
        type=float,
        default=RESET_WAIT_S,
        help="longest wait for the reset's outcome (default %(default)s s)",
    )
    p.set_defaults(handler=run)
    return p


def _task_spec(text: str) -> str | dict[str, Any]:
    """A built-in name as is; a TOML file read here and sent as numbers (the daemon never
    reads client paths)."""
    path = Path(text)
    if not path.suffix and not path.exists():
        return text
    from rt_runtime.planning.trench import read_task_file  # the planner stack: only when needed

    return {"name": path.stem, **read_task_file(path)}


def format_job(job: dict[str, Any]) -> str:
    """One line about a job (from a reply)."""
    t = job.get("task", {})
    text = (
        f"job {job.get('id')}: {job.get('status')}, task {t.get('name')} (L {t.get('length_m')} m, "
        f"D {t.get('depth_m')} m), planner {job.get('planner')}, {len(job.get('digs', []))} "
        "dig(s) done"
    )
    if job.get("fault"):
        text += f"; {job['fault']}"
    return text


#: What each motion phase of a running job means, for people.
_PHASES = {
    "wait": "waiting for the next motion",
    "connect": "moving to the next motion's start",
    "dig": "digging",
    "lift_out": "lifting out",
    "dump": "moving to dump",
    "approach": "approaching the next dig",
    "enter": "entering the next dig",
    "path": "following the path",
    "settle": "at the end, waiting for the drives to rest",
    "stop": "stopping (jerk-limited)",
    "idle": "starting",
}


def format_progress(progress: dict[str, Any]) -> str:
    """The running job's progress (a ``status`` reply's ``progress``) in words."""
    phase = str(progress.get("phase", ""))
    text = _PHASES.get(phase, phase.replace("_", " ") or "starting")
    if phase == "dig" and int(progress.get("dig", -1)) >= 0:
        text += f" dig {int(progress['dig']) + 1}"
    text += f"; {progress.get('digs_done', 0)} dig(s) done"
    if progress.get("paused"):
        text += "; paused: holds at the end of this motion until resumed"
    if progress.get("stopping"):
        text += "; stopping"
    if progress.get("planning"):
        text += "; planning the next dig"
    if progress.get("status"):
        text += f"; {progress['status']}"
    return text


def _print_human(command: str, reply: dict[str, Any]) -> None:
    if command == "list":
        jobs = reply.get("jobs", [])
        if not jobs:
            print("no jobs")
        for job in jobs:
            print(format_job(job))
        return
    daemon = reply.get("daemon")
    if daemon is not None:
        print(
            f"daemon: {daemon.get('state')}; rig {daemon.get('rig')}, period "
            f"{daemon.get('period_s', 0.0) * 1e3:g} ms, healthy {daemon.get('healthy')}"
        )
        if daemon.get("fault"):
            print("  nothing moves until `excavator-rt job reset-fault`")
    job = reply.get("job")
    if command == "submit" and reply.get("fault"):
        print(f"a fault is latched ({reply['fault']}): the job starts after a reset-fault")
    if job is not None:
        print(format_job(job))
        for d in job.get("digs", []):
            print(
                f"  dig {d['index']}: {d['dig_type']}, T {d['T_s']:.2f} s, planned "
                f"{d['planned_volume_m3'] * 1e3:.2f} L, "
                f"measured {d['measured_volume_m3'] * 1e3:.2f} L"
            )
        progress = reply.get("progress")
        if progress:
            print("  now: " + format_progress(progress))
    elif command == "status":
        print("no job")


def run(args: argparse.Namespace) -> int:
    """``excavator-rt job <command>``: one request, the reply printed; the exit code.

    Raises:
        ConfigurationError: An unreadable task file.
        CommunicationError: No daemon at the socket (the CLI prints it, exit 2).
    """
    command = args.job_command
    if command == "reset-fault":
        return _reset_fault(args)
    req: dict[str, Any] = {"cmd": command}
    if command == "submit" and args.teach is not None:
        # A taught trench (~200 kB for 7 cycles) is larger than a request line may be: the
        # daemon, on this machine behind an owner-only socket, reads it from its absolute path.
        req["teach"] = str(Path(args.teach).resolve())
    elif command == "submit":
        req["task"] = _task_spec(args.task)
        if args.planner:
            req["planner"] = args.planner
        if args.max_digs is not None:
            req["max_digs"] = args.max_digs
    elif getattr(args, "id", None) is not None:
        req["id"] = args.id
    reply = request(args.socket, req)
    if args.json:
        print(json.dumps(reply, indent=2))
    if not reply.get("ok"):
        print(f"excavator-rt job {command}: {reply.get('error', reply)}", file=sys.stderr)
        return 1
    if not args.json:
        _print_human(command, reply)
    return 0


def _reset_fault(args: argparse.Namespace) -> int:
    """``job reset-fault``: the request, then ``status`` until the reset has ended."""
    reply = request(args.socket, {"cmd": "reset-fault"})
    if not reply.get("ok"):
        if args.json:
            print(json.dumps(reply, indent=2))
        print(f"excavator-rt job reset-fault: {reply.get('error', reply)}", file=sys.stderr)
        return 1
    number = int(reply["reset"])
    if not args.json:
        print(f"resetting: {reply['fault']}")
    end = time.monotonic() + args.wait_s
    while True:
        status = request(args.socket, {"cmd": "status"})
        daemon = status.get("daemon", {})
        if int(daemon.get("resets_done", 0)) >= number:
            break
        if time.monotonic() > end:
            print(
                f"excavator-rt job reset-fault: the reset has not ended within {args.wait_s:g} s;"
                f" the daemon says: {daemon.get('state')}",
                file=sys.stderr,
            )
            return 1
        time.sleep(_RESET_POLL_S)
    if args.json:
        print(json.dumps(status, indent=2))
    fault = daemon.get("fault", "")
    if fault:
        print(f"excavator-rt job reset-fault: the reset failed: {fault}", file=sys.stderr)
        return 1
    if not args.json:
        print(f"fault reset: {daemon.get('state')}")
    return 0
