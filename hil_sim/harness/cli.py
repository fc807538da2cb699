"""``excavator-rt hil``: plan a trench task, execute it through the master against the HIL, report.

Role: the command-line edge of :mod:`hil_sim.harness.scenario` (mm, Wh and percent appear only
here and in the report). ``rt_runtime.cli`` wires it in with :func:`add_parser` and :func:`run`::

    excavator-rt hil --task A [--rig scale_model] [--realtime] [--trace FILE.blf|.asc]
                     [--no-feedforward] [--controller csp|p] [--imperfect|--ideal] [--scanner]
                     [--material NAME]
                     [--max-digs N] [--json] [--plot DIR]
                     [--inject KIND:TARGET:AT_S[:PARAM] ...]
    excavator-rt hil campaign [--kinds K,...] [--axes A,...] [--seeds N] [--json] [--out DIR]
    excavator-rt hil soak [--hours H | --minutes M | --seconds S] [--fault-every-s S] [--json]
    excavator-rt hil --operator --demos N --out DIR [--seed S] [--json]
    excavator-rt hil --teach DIR [--trace FILE] [--inject KIND:TARGET:AT_S] [--json]
    excavator-rt hil --path gao|FILE.json|joints [--joints-deg B,S,K ...] [--rig test_bench]
                     [--orders auto|3-4-5-4-3|...] [--durations 3,3,3,3,3] [--start-deg B,S,K]
                     [--realtime] [--no-feedforward] [--trace FILE] [--json] [--plot DIR]
    excavator-rt hil --mintorque soft|hard [--rig yang_pan_excavator] [--fixed-time] [--json]

``--mintorque`` plans a minimum-torque dig (Yang/Pan) and runs it on the lockstep HIL in the
same fluid soil (:mod:`hil_sim.harness.mintorque`).

``--path`` runs a prescribed joint path instead of a task (:func:`hil_sim.harness.scenario.
run_path_scenario`): ``gao`` is Gao Table 2 with 3 s segments and the smoothest order pattern,
``FILE.json`` holds ``{"joints_deg": [[b, s, k], ...], "durations_s": [...]}``, and repeated
``--joints-deg`` key points imply ``--path joints``. ``--rig`` defaults to ``test_bench`` with a
path and to ``scale_model`` with a task.

Exit status: 0 when the run finished, 1 when a fault stopped it (the report says which), 2 for
a configuration or planning error.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from typing import Any

from hil_sim.harness import campaign, fouraxis, hil_soak
from hil_sim.harness.reports import HilReport
from hil_sim.harness.scenario import (
    CONTROLLERS,
    GAO_HOST_GAIN_1_S,
    FaultSpec,
    HilRun,
    PathScenario,
    Scenario,
    run_path_scenario,
    run_scenario,
)
from hil_sim.sim import FaultKind
from rt_runtime.errors import ConfigurationError, ExcavatorRtError

__all__ = ["add_parser", "format_report", "parse_fault", "parse_floats", "run"]


def parse_floats(text: str, n: int | None = None, what: str = "value") -> tuple[float, ...]:
    """Comma-separated finite numbers (``n`` of them when given).

    Raises:
        argparse.ArgumentTypeError: Not numbers, not finite, or the wrong count.
    """
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{what} {text!r}: expected comma-separated numbers"
        ) from None
    if not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"{what} {text!r}: numbers must be finite")
    if n is not None and len(values) != n:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: expected {n} numbers")
    return values


def _triple(text: str) -> tuple[float, float, float]:
    v = parse_floats(text, 3, "key point (deg: boom,stick,bucket)")
    return (v[0], v[1], v[2])


def _durations(text: str) -> tuple[float, ...]:
    values = parse_floats(text, None, "--durations")
    if not all(v > 0.0 for v in values):
        raise argparse.ArgumentTypeError(f"--durations {text!r}: every duration must be > 0 s")
    return values


def parse_fault(text: str) -> FaultSpec:
    """``KIND:TARGET:AT_S[:PARAM]`` (e.g. ``following_error:stick:2.5``,
    ``frame_loss:bus:1.0:0.1``) as a :class:`FaultSpec`.

    Raises:
        argparse.ArgumentTypeError: Unknown kind, a target the kind does not take, a bad time
            or parameter.
    """
    parts = text.split(":")
    kinds = ", ".join(k.label for k in FaultKind)
    if len(parts) not in (3, 4):
        raise argparse.ArgumentTypeError(
            f"--inject {text!r}: expected KIND:TARGET:AT_S[:PARAM] ({kinds})"
        )
    kind, target, at = parts[:3]
    try:
        fault_kind = FaultKind[kind.upper()]
    except KeyError:
        raise argparse.ArgumentTypeError(f"--inject kind {kind!r}; allowed: {kinds}") from None
    if target not in fault_kind.swing_targets:
        raise argparse.ArgumentTypeError(
            f"--inject {fault_kind.label} target {target!r}; allowed: "
            + ", ".join(fault_kind.swing_targets)
            + " (swing on a rig with swing)"
        )
    try:
        at_s = float(at)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--inject time {at!r} is not a number") from None
    if not (math.isfinite(at_s) and at_s >= 0.0):
        raise argparse.ArgumentTypeError(f"--inject time {at_s} must be >= 0 s")
    param = None
    if len(parts) == 4:
        try:
            param = float(parts[3])
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"--inject parameter {parts[3]!r} is not a number"
            ) from None
        if not math.isfinite(param):
            raise argparse.ArgumentTypeError(f"--inject parameter {param} must be finite")
    return FaultSpec(fault_kind, target, at_s, param)


def register(subparsers: Any) -> None:
    """Register the ``hil`` sub-command with its handler (the ``excavator_rt.commands`` entry
    point ``hil``)."""
    add_parser(subparsers).set_defaults(handler=run)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``hil`` sub-command to an ``argparse`` sub-parser set; returns its parser."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "hil",
        help="execute a trench task against the HIL and report tracking",
        description="Plan a trench task, execute it through the CAN master against the emulated "
        "drives and arm (HIL), and print the tracking report.",
    )
    p.add_argument("--task", default="A", help="built-in task A..D or a task TOML file")
    p.add_argument(
        "--rig",
        default=None,
        help="rig profile name or TOML file (default: scale_model; test_bench with --path)",
    )
    p.add_argument(
        "--path",
        default=None,
        metavar="gao|FILE.json|joints",
        help="run a prescribed joint path instead of a task (Gao/Yang mixed-order "
        "interpolation through key points): gao = Gao Table 2, 3 s segments",
    )
    p.add_argument(
        "--joints-deg",
        action="append",
        type=_triple,
        default=[],
        metavar="B,S,K",
        help="a key point of the path in deg (repeatable; implies --path joints)",
    )
    p.add_argument(
        "--orders",
        default="auto",
        help="path order pattern, e.g. 3-4-5-4-3, or auto (the smoothest of Gao's three)",
    )
    p.add_argument(
        "--durations",
        type=_durations,
        default=None,
        metavar="D1,D2,...",
        help="path segment durations in s (default 3 each)",
    )
    p.add_argument(
        "--start-deg",
        type=_triple,
        default=None,
        metavar="B,S,K",
        help="arm start pose for a path (default: the path's first key point)",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="HIL in its own process at wall-clock speed over 127.0.0.1",
    )
    p.add_argument(
        "--trace", default=None, metavar="FILE", help="write the CAN trace (.blf or .asc)"
    )
    p.add_argument("--no-feedforward", action="store_true", help="velocity offset 0x60B1 = 0")
    p.add_argument(
        "--controller",
        default="csp",
        choices=CONTROLLERS,
        help="csp: target stroke with velocity feed-forward and the valve drives' overlap "
        "compensation (ours); p: Gao's plain proportional displacement loop (no feed-forward, "
        "no overlap compensation), the paper's reference",
    )
    p.add_argument(
        "--host-gain",
        default=None,
        metavar="1/S[,1/S,...]",
        help="gain of the host's proportional displacement loop over the bus, added to the "
        "velocity offset: one for every axis, or one per axis comma-separated (boom,stick,"
        "bucket[,swing]; a swing left out takes the arm's lowest); default "
        f"{','.join(f'{g:g}' for g in GAO_HOST_GAIN_1_S)} with --controller p, 0 with csp",
    )
    p.add_argument(
        "--scanner",
        action="store_true",
        help="emulate the rig's profile scanner ([hil.scanner]) and plan each dig on the "
        "surface it measured (a task run, lockstep or real time)",
    )
    p.add_argument(
        "--material",
        default=None,
        metavar="NAME",
        help="the pit's granular material, one of the profile's [hil.materials] (with "
        "--imperfect; default the profile's hil.material)",
    )
    p.add_argument(
        "--hil-seed",
        type=int,
        default=None,
        metavar="N",
        help="seed of the HIL's stroke sensors (linearity phase and noise; lockstep; default "
        "the profile's hil.seed)",
    )
    real = p.add_mutually_exclusive_group()
    real.add_argument(
        "--imperfect",
        dest="imperfect",
        action="store_const",
        const=True,
        default=None,
        help="apply the rig profile's [hil] imperfections (valves, sensors, motors, material)",
    )
    real.add_argument(
        "--ideal",
        dest="imperfect",
        action="store_const",
        const=False,
        help="the ideal HIL whatever the profile's hil.enabled says",
    )
    p.add_argument("--max-digs", type=int, default=None, help="stop after N digs")
    p.add_argument("--period-ms", type=float, default=2.0, help="SYNC period (ms)")
    p.add_argument("--planner", default="pinn", choices=("pinn", "pso", "min_torque"))
    p.add_argument(
        "--inject",
        action="append",
        type=parse_fault,
        default=[],
        metavar="KIND:TARGET:AT_S[:PARAM]",
        help="inject a fault (repeatable): KIND one of "
        + ", ".join(k.label for k in FaultKind)
        + "; TARGET an axis, bus or host",
    )
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.add_argument("--plot", default=None, metavar="DIR", help="write figures (Yao Fig. 17-21)")
    p.add_argument(
        "--mintorque",
        default=None,
        metavar="SOIL",
        help="plan a minimum-torque dig (Yang/Pan) in this fluid soil (soft, hard) and run it "
        "on the lockstep HIL in the same soil (rig default yang_pan_excavator)",
    )
    p.add_argument(
        "--fixed-time", action="store_true", help="with --mintorque: keep the intervals fixed"
    )
    fouraxis.add_arguments(p)
    sub = p.add_subparsers(dest="hil_command", metavar="{campaign,soak}")
    campaign.add_parser(sub)
    hil_soak.add_parser(sub)
    return p


def format_report(report: HilReport) -> str:
    """Human-readable summary of a report (a task's or a path's)."""
    path = report.path
    head: list[str] = []
    if path is not None:
        key_err = path.cmd_at_key_error_um or ()
        head = [
            f"  path {path.name}: {len(path.key_points_deg)} key points, orders "
            f"{path.orders}, knots {list(path.knots_s)} s"
            + (f", key points scaled from {path.scaled_from}" if path.scaled_from else ""),
            "  commanded stroke at the key times: max |cmd - key point| "
            + (f"{max(key_err):.3g} um" if key_err else "n/a"),
        ]
        if report.tracking_path is not None:
            head.append(
                "  path only (truth): "
                + ", ".join(
                    f"{axis} max {fig.max_mm:.3f} rms {fig.rms_mm:.3f} mm"
                    for axis, fig in report.tracking_path.tracking.items()
                )
            )
    host = (
        f" (host loop {_gains_text(report.host_gain_per_axis_1_s)})" if report.host_gain_1_s else ""
    )
    lines = [
        f"HIL {report.transport}: task {report.task} on {report.rig}"
        f"{' (imperfect)' if report.imperfect else ''}, controller {report.controller}"
        f"{host}, "
        f"feed-forward {'on' if report.feedforward else 'off'}: {report.status}"
        + (f" ({report.fault})" if report.fault else ""),
        f"  digs {len(report.digs)}, simulated {report.sim_s:.1f} s, wall "
        f"{report.wall_s:.1f} s, overruns {report.overruns}",
        *head,
        "  cylinder tracking (truth / reported):",
    ]
    for axis, fig in report.tracking.items():
        rep = fig.reported
        lines.append(
            f"    {axis:6s} max {fig.max_mm:.3f} / {rep.max_mm:.3f} mm, "
            f"rms {fig.rms_mm:.3f} / {rep.rms_mm:.3f} mm"
        )
    lines.append(f"  tip error max {report.tip_error_max_mm:.2f} mm")
    if report.coverage_error is not None and report.overdig_max_mm is not None:
        lines.append(
            f"  profile: coverage error {report.coverage_error:.3f}, over-dig max "
            f"{report.overdig_max_mm:.2f} mm"
        )
    lines.append(f"  energy {report.energy_Wh:.3f} Wh")
    mat = report.material
    if mat is not None:
        lines.append(
            f"  material {mat.name}: bucket kept {mat.load_L:.2f} of {mat.swept_L:.2f} L swept, "
            f"{mat.load_ratio:.1%} of the planned {mat.planned_L:.2f} L (Yao 91 %); dig energy "
            f"{mat.energy_ratio:+.1%} against the plan (Yao +13 %); fell back "
            f"{mat.fallback_L:.2f} L, slumped {mat.slumped_L:.2f} L"
        )
        if mat.table6 is not None:
            t6 = mat.table6
            lines.append(
                f"  Table 6 (relative errors): L {t6.L:.1%}, D {t6.D:.1%}, beta1 {t6.beta1:.1%}, "
                f"beta2 {t6.beta2:.1%} (Yao 6.7, 6.7, 5.0, 11.7 %)"
            )
    load = report.can.bus_load
    if load is not None:
        lines.append(f"  bus load {load.nominal:.1%} nominal, {load.worst:.1%} worst case")
    rtt = report.can.sync_rtt_us
    if rtt is not None:
        lines.append(f"  SYNC -> TPDO round trip p50 {rtt.p50:.0f} us, p99 {rtt.p99:.0f} us")
    if report.trace:
        lines.append(f"  trace {report.trace}")
    return "\n".join(lines)


def _gains_text(gains: dict[str, float]) -> str:
    """The host loop's gains for a report line: one number, or one per axis."""
    values = set(gains.values())
    if len(values) == 1:
        return f"{values.pop():g} 1/s"
    return ", ".join(f"{axis} {g:g}" for axis, g in gains.items()) + " 1/s"


def _host_gain(args: argparse.Namespace) -> float | tuple[float, ...]:
    """``--host-gain``, or the controller's default: Gao's PC loop for ``p``, none for csp.

    Raises:
        ConfigurationError: A gain that is negative, not finite or not a number (the count
            per axis is checked against the rig by the scenario).
    """
    text = args.host_gain
    if text is None:
        return GAO_HOST_GAIN_1_S if args.controller == "p" else 0.0
    try:
        gains = tuple(float(part) for part in str(text).split(","))
    except ValueError:
        gains = ()
    if not gains or not all(math.isfinite(g) and g >= 0.0 for g in gains):
        raise ConfigurationError(
            f"--host-gain {text}: allowed a finite gain >= 0 (1/s), or one per axis "
            "comma-separated (boom,stick,bucket[,swing])"
        )
    return gains[0] if len(gains) == 1 else gains


def run(args: argparse.Namespace) -> int:
    """Run the ``hil`` sub-command; returns the exit status."""
    if getattr(args, "operator", False) or getattr(args, "teach", None) is not None:
        return fouraxis.run_command(args)
    if getattr(args, "mintorque", None) is not None:
        return _run_mintorque(args)
    try:
        _host_gain(args)
    except ConfigurationError as exc:
        return _refused(args, exc)
    path = getattr(args, "path", None)
    joints = tuple(getattr(args, "joints_deg", []) or [])
    if path is not None or joints:
        return _run_path(args, path if path is not None else "joints", joints)
    scenario = Scenario(
        task=args.task,
        rig=args.rig if args.rig is not None else "scale_model",
        feedforward=not args.no_feedforward,
        realtime=args.realtime,
        trace_path=args.trace,
        max_digs=args.max_digs,
        faults=tuple(args.inject),
        period_s=args.period_ms * 1e-3,
        planner=args.planner,
        plot_dir=args.plot,
        imperfect=args.imperfect,
        controller=args.controller,
        host_gain_1_s=_host_gain(args),
        scanner=args.scanner,
        material=args.material,
        hil_seed=args.hil_seed,
    )
    return _print_run(args, lambda: run_scenario(scenario))


def _refused(args: argparse.Namespace, exc: Exception) -> int:
    """Print why a run was refused before anything moved (``--json`` or text); exit status 2."""
    if args.json:
        print(json.dumps({"status": "error", "error": str(exc)}))
    else:
        print(f"excavator-rt hil: {exc}")
    return 2


def _print_run(args: argparse.Namespace, run: Callable[[], HilRun]) -> int:
    """Run a scenario and print its report (``--json`` or text); the command's exit status:
    0 done, 1 stopped otherwise, 2 refused before anything moved (bad input, planning)."""
    try:
        report = run().report
    except (ExcavatorRtError, ValueError) as exc:
        return _refused(args, exc)
    print(json.dumps(report.to_json()) if args.json else format_report(report))
    if report.status == "planning_error":
        return 2
    return 0 if report.status == "done" else 1


def _run_mintorque(args: argparse.Namespace) -> int:
    """``hil --mintorque SOIL``: exit 0 when the dig ran to its end, 1 when it stopped
    otherwise, 2 on bad input or when no feasible dig was found (nothing moved)."""
    from hil_sim.harness.mintorque import run_mintorque

    try:
        r = run_mintorque(
            args.mintorque,
            args.rig if args.rig is not None else "yang_pan_excavator",
            fixed_time=args.fixed_time,
            period_s=args.period_ms * 1e-3,
            feedforward=not args.no_feedforward,
            lead=not args.no_lead,
        )
    except (ExcavatorRtError, ValueError) as exc:
        return _refused(args, exc)
    if args.json:
        print(json.dumps(r))
    else:
        plan = r["plan"]
        print(
            f"HIL lockstep: minimum-torque dig on {r['rig']} in {r['soil']} soil: {r['status']}"
            f"; T {plan['T_s']:.2f} s, cost {plan['cost']:.4g} s, max depth "
            f"{plan['max_depth_m']:.3f} m"
        )
        for axis, fig in r["tracking"].items():
            print(f"  {axis:6s} tracking max {fig['max_mm']:.3f} mm, rms {fig['rms_mm']:.3f} mm")
        for joint, t in r["torque"].items():
            print(
                f"  {joint:6s} torque rms planned {t['rms_planned_nm'] / 1e3:.1f} kN*m, plant "
                f"{t['rms_plant_nm'] / 1e3:.1f} kN*m, difference rms "
                f"{t['rms_difference_nm'] / 1e3:.1f} kN*m ({t['rms_difference_of_limit']:.1%} "
                "of the limit)"
            )
        print(
            f"  soil moment about the tip (not applied by the plant) rms "
            f"{r['soil_moment_rms_nm'] / 1e3:.2f} kN*m"
        )
    return 0 if r["status"] == "done" else 1


def _run_path(
    args: argparse.Namespace, path: str, joints: tuple[tuple[float, float, float], ...]
) -> int:
    """``hil --path``: a prescribed joint path on the HIL."""
    if joints and path != "joints":
        print("excavator-rt hil: --joints-deg gives the key points itself; use it without --path")
        return 2
    if args.scanner:
        print("excavator-rt hil: --scanner scans a task's trench; a path has none")
        return 2
    scenario = PathScenario(
        path=path,
        rig=args.rig if args.rig is not None else "test_bench",
        joints_deg=joints,
        orders=args.orders,
        durations_s=args.durations,
        start_deg=args.start_deg,
        feedforward=not args.no_feedforward,
        realtime=args.realtime,
        trace_path=args.trace,
        period_s=args.period_ms * 1e-3,
        plot_dir=args.plot,
        faults=tuple(args.inject),
        imperfect=args.imperfect,
        controller=args.controller,
        host_gain_1_s=_host_gain(args),
        hil_seed=args.hil_seed,
    )
    return _print_run(args, lambda: run_path_scenario(scenario))
