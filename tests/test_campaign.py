"""The fault model and the fault campaign (``excavator-rt hil campaign``).

The unit part checks each piece of the fault model on its own: the wire's faults
(:class:`~hil_sim.busfaults.BusFaults`), the drive node's faults (a jump in the reported
position, a rock, a reboot, the drive's own EMCYs with their reactions), the master's counts of
what it rides through and its refusal of implausible positions, and the ``--inject`` parser.

The campaign part runs one case of every fault kind on the daemon's runner in the lockstep HIL
(a one-dig job, each fault early in it) and asserts, per kind: detection within the kind's
stated bound (or a ride-through the master counted), the stop within the guard's limits on the
commanded RPDO1 stream and the plant, nothing enabling operation after the stop, and the job
resumed and done, not lost. The full matrix (>= 500 cases) is the command's.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import math
import os
import random
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any
from unittest import mock

import can
import numpy as np
import pytest

from firmware_models.drive import DeviceState, DriveFirmware
from hil_sim.busfaults import BusFaults
from hil_sim.harness.campaign import (
    CASE_TASK,
    PLANNER_KINDS,
    RULES,
    Case,
    _exposed,
    matrix,
    run_campaign,
)
from hil_sim.harness.cli import parse_fault
from hil_sim.harness.lockstep import LockstepHil
from hil_sim.sim import FaultKind, HilCore
from rt_runtime.canbus import RPDO1, TPDO1, CanMaster
from rt_runtime.canbus.inprocess import ChannelBus
from rt_runtime.control.hardware import DriveInterface
from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.trench import TrenchPlanner
from rt_runtime.rig import Rig, load_rig


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


# -- the wire ---------------------------------------------------------------------------------

TPDO1_BOOM = (0x181, bytes(8))
RPDO1_STICK = (0x202, bytes(8))
SYNC = (0x080, b"")


def test_every_kind_has_a_rule_and_the_catalogue_is_large_enough() -> None:
    assert set(RULES) == set(FaultKind)
    assert len(FaultKind) >= 18
    layers = {k.layer for k in FaultKind}
    assert layers == {"drive", "bus", "host"}


def test_frame_loss_drops_the_target_at_its_rate_and_leaves_the_others() -> None:
    wire = BusFaults(seed=3)
    wire.inject(FaultKind.FRAME_LOSS, 1, 0.3, 0.0)
    passed = sum(len(wire.to_master(TPDO1_BOOM, 0.0)) for _ in range(4000))
    assert 0.66 < passed / 4000 < 0.74
    assert all(wire.to_hil(RPDO1_STICK, 0.0) == [RPDO1_STICK] for _ in range(200))
    assert all(wire.to_hil(SYNC, 0.0) == [SYNC] for _ in range(200))  # a broadcast: bus only
    assert wire.affected["frame_loss"] == 4000 - passed
    wire.clear()
    assert not wire.active and wire.to_master(TPDO1_BOOM, 0.0) == [TPDO1_BOOM]


def test_one_shot_kinds_act_on_the_targets_next_frame_only() -> None:
    wire = BusFaults(seed=1)
    wire.inject(FaultKind.FRAME_DUPLICATE, 1, None, 0.0)
    assert wire.to_master(TPDO1_BOOM, 0.0) == [TPDO1_BOOM, TPDO1_BOOM]
    assert wire.to_master(TPDO1_BOOM, 0.0) == [TPDO1_BOOM]
    wire.inject(FaultKind.FRAME_TRUNCATED, 1, None, 0.0)
    assert wire.to_hil((0x201, bytes(8)), 0.0) == [(0x201, bytes(8))]  # device frames only
    assert wire.to_master(TPDO1_BOOM, 0.0) == [(0x181, bytes(7))]
    wire.inject(FaultKind.FRAME_GARBAGE, None, None, 0.0)
    ((cob, data),) = wire.to_master(TPDO1_BOOM, 0.0)
    assert cob == 0x181 and len(data) == 8 and data != bytes(8)
    wire.inject(FaultKind.FRAME_DELAY, 1, 5.0, 1.0)
    assert wire.to_master(TPDO1_BOOM, 1.0) == []
    assert wire.due(1.004) == ([], [])
    assert wire.due(1.005) == ([], [TPDO1_BOOM])
    wire.inject(FaultKind.FRAME_REORDER, None, None, 2.0)
    first, second = (0x181, b"\x01" * 8), (0x281, b"\x02" * 6)
    assert wire.to_master(first, 2.0) == []
    assert wire.to_master(second, 2.0) == [second, first]
    assert not wire.active


def test_unplugged_error_frames_and_bus_off() -> None:
    wire = BusFaults()
    wire.inject(FaultKind.BUS_UNPLUGGED, None, 0.2, 1.0)
    assert wire.to_hil(SYNC, 1.1) == [] and wire.to_master(TPDO1_BOOM, 1.19) == []
    assert wire.to_hil(SYNC, 1.2) == [SYNC]
    wire.inject(FaultKind.ERROR_FRAMES, None, 2, 0.0)
    assert [wire.error_frames_due() for _ in range(3)] == [True, True, False]
    wire.inject(FaultKind.BUS_OFF, None, None, 0.0)
    assert wire.bus_off
    wire.clear()
    assert not wire.bus_off


@pytest.mark.parametrize(
    ("kind", "node", "param", "words"),
    [
        (FaultKind.OVERCURRENT, 1, None, "not the bus's"),
        (FaultKind.FRAME_LOSS, 1, 1.5, "must be in 0..1"),
        (FaultKind.FRAME_DELAY, 1, -1.0, "finite and > 0"),
        (FaultKind.BUS_UNPLUGGED, None, math.inf, "finite and > 0"),
        (FaultKind.FRAME_LOSS, 200, 0.1, "1..127"),
    ],
)
def test_bad_bus_faults_are_refused_by_name(
    kind: FaultKind, node: int | None, param: float | None, words: str
) -> None:
    with pytest.raises(ValueError, match=words):
        BusFaults().inject(kind, node, param, 0.0)


# -- the drive nodes --------------------------------------------------------------------------


def test_drive_emcys_take_their_own_reactions(rig: Rig) -> None:
    core = HilCore(rig, TrenchPlanner(rig).home_pose_rad, vcu=False)
    with pytest.raises(ValueError, match="fault reaction"):
        core.nodes[0].firmware.inject_fault(0x2310, 5)
    with pytest.raises(ValueError, match="not a drive node's"):
        core.inject(FaultKind.BUS_OFF, 0)
    fw: DriveFirmware = core.nodes[1].firmware
    fw.inject_fault(0x4310, 0)  # not enabled: straight to FAULT whatever the reaction
    assert fw.state is DeviceState.FAULT and fw.error_code == 0x4310


def test_a_reboot_sends_its_boot_up_frame_and_forgets_the_masters_setup(rig: Rig) -> None:
    with LockstepHil(rig, TrenchPlanner(rig).home_pose_rad, vcu=False, keep_frames=True) as hil:
        master = CanMaster(hil.master_bus, rig, period_s=0.002, react_to_faults=False)
        master.boot(hil.clock.now, 1.0)
        master.enable(hil.clock.now, 1.0)
        hil.core.frames.clear()
        hil.inject(FaultKind.DRIVE_REBOOT, 2)
        assert hil.core.frames == [(0x703, b"\x00")]
        assert hil.core.nodes[2].firmware.state is DeviceState.SWITCH_ON_DISABLED


def _enabled(hil: LockstepHil, rig: Rig) -> tuple[CanMaster, DriveInterface, np.ndarray]:
    """A master booted and enabled on ``hil``, its drives' interface, and the strokes the
    drives reported (m)."""
    master = CanMaster(hil.master_bus, rig, period_s=0.002, react_to_faults=False)
    master.boot(hil.clock.now, 1.0)
    master.enable(hil.clock.now, 1.0)
    drives = DriveInterface(master, hil.clock, 0.0)
    return master, drives, master.feedback.position_um.astype(np.float64) * 1e-6


def test_an_encoder_glitch_moves_the_report_not_the_axis_and_the_master_refuses_it(
    rig: Rig,
) -> None:
    """The jump is refused as implausible (stale, counted) every cycle until the axis could
    have got there, so it never reaches the controllers; the plant does not move."""
    with LockstepHil(rig, TrenchPlanner(rig).home_pose_rad, vcu=False) as hil:
        master, drives, held = _enabled(hil, rig)
        zero = np.zeros(3)

        def cycle() -> Any:
            hil.clock.sleep_until(hil.clock.now() + 0.002)
            drives.write(held, zero)
            return drives.read()

        for _ in range(5):
            fb = cycle()
        assert fb.fresh and master.feedback.counts.implausible == 0
        true_before = hil.core.plant.stroke_m.copy()
        hil.inject(FaultKind.ENCODER_GLITCH, 1, 8.0)
        stale = [bool(cycle().stale[1]) for _ in range(12)]
        assert all(stale)
        assert master.feedback.counts.implausible == 12
        np.testing.assert_allclose(hil.core.plant.stroke_m, true_before, atol=2e-5)
        hil.clear_faults()
        fb = cycle()
        assert fb.fresh and abs(fb.stroke_m[1] - held[1]) < 1e-4


def test_the_router_counts_what_it_rides_through(rig: Rig) -> None:
    with LockstepHil(rig, TrenchPlanner(rig).home_pose_rad, vcu=False) as hil:
        master, drives, held = _enabled(hil, rig)
        other = ChannelBus(hil.channel)  # a second device repeating the boom's answer
        hil.clock.sleep_until(hil.clock.now() + 0.002)
        drives.write(held, np.zeros(3))
        boom = int(master.feedback.position_um[0])
        other.send(can.Message(arbitration_id=0x181, data=TPDO1.codec.pack(boom, 0),
                               is_extended_id=False))  # fmt: skip
        assert drives.read().fresh
        other.shutdown()
        hil.inject(FaultKind.FRAME_TRUNCATED, 1)
        hil.inject(FaultKind.ERROR_FRAMES, -1, 2.0)
        for _ in range(4):
            hil.clock.sleep_until(hil.clock.now() + 0.002)
            drives.write(held, np.zeros(3))
            drives.read()
        counts = master.feedback.counts
        assert counts.duplicate_tpdo1 == 1
        assert counts.malformed == 1
        assert counts.error_frames == 2
        assert counts.missed_tpdo1 >= 1


# -- the command line -------------------------------------------------------------------------


def test_inject_takes_a_target_and_a_parameter() -> None:
    spec = parse_fault("frame_loss:bus:1.5:0.1")
    assert (spec.kind, spec.axis, spec.at_s, spec.param) == (FaultKind.FRAME_LOSS, "bus", 1.5, 0.1)
    assert parse_fault("rock:stick:2").param is None
    for text, words in (
        ("overcurrent:bus:1", "allowed: boom, stick, bucket"),
        ("loop_stall:boom:1", "allowed: host"),
        ("frame_loss:bus:1:nan", "must be finite"),
        ("frame_loss:bus", "KIND:TARGET:AT_S"),
        ("meteor:bus:1", "allowed: following_error"),
    ):
        with pytest.raises(argparse.ArgumentTypeError, match=words):
            parse_fault(text)


def test_the_matrix_covers_every_kind_on_every_target() -> None:
    cases = matrix(seeds=10)
    assert len(cases) >= 500
    cells = {(c.kind, c.target) for c in cases}
    assert cells == {(k, t) for k in FaultKind for t in k.targets}
    assert len(matrix(axes=["stick"], seeds=1)) < len(matrix(seeds=1))


def test_on_a_rig_with_swing_the_swing_is_a_target_and_the_planner_kinds_are_left_out() -> None:
    cases = matrix(seeds=1, swing=True)
    cells = {(c.kind, c.target) for c in cases}
    assert cells == {(k, t) for k in FaultKind if k not in PLANNER_KINDS for t in k.swing_targets}
    assert (FaultKind.OVERCURRENT, "swing") in cells
    assert {c.target for c in matrix(axes=["swing"], seeds=1, swing=True)} <= {
        "swing",
        "bus",
        "host",
    }
    with pytest.raises(ConfigurationError, match="no planner process"):
        matrix([FaultKind.PLANNER_KILLED], seeds=1, swing=True)
    with pytest.raises(ConfigurationError, match="swing: the rig has boom, stick, bucket"):
        matrix(axes=["swing"], seeds=1)


def test_a_swing_campaign_stops_every_fault_on_the_swing_drive_safely_and_resumes() -> None:
    """The field excavator's taught trench (one cycle: the swing to the dump 3.1-4.7 s in, and
    back 5.9-7 s) with a fault on its swing drive, and the daemon's crash, on four axes."""
    cases = [
        Case(0, FaultKind.OVERCURRENT, "swing", 4.0, 0, digs=1),
        Case(1, FaultKind.ROCK, "swing", 3.4, 1, digs=1),
        Case(2, FaultKind.ENCODER_GLITCH, "swing", 6.2, 2, digs=1),
        Case(3, FaultKind.DAEMON_CRASH, "host", 3.8, 3, digs=1),
    ]
    report = run_campaign(cases, "field_excavator", jobs=2)
    for row in report["cases"]:
        assert not row["error"], row
        assert row["violations"] == [], row
        assert row["outcome"] == "stopped" and row["resumed"] and not row["lost_job"], row
        assert row["detection_s"] is not None and row["detection_s"] <= row["bound_s"], row
        assert row["digs"] == 1 and row["safe"], row
    # The three stops the master commanded (the crashed daemon commands none) within limits.
    peaks = [r["stop_peak"] for r in report["cases"] if r["stop_peak"].get("v") is not None]
    assert len(peaks) == 3 and all(p[k] <= 1.0 for p in peaks for k in ("v", "a", "j"))


def test_a_stuck_axis_shows_when_its_command_outruns_where_it_truly_is() -> None:
    """The moment a jam can first show is measured against the axis's true stroke: a jammed
    hydraulic axis creeps on its oil column, and its error only grows as fast as the command
    outruns the creep; an electric axis stands where it stuck, and both measures agree."""
    period, window, v_cmd = 0.002, 0.024, 0.10  # s, m, m/s
    t_inj = 1.0
    cob = RPDO1.cob_id(1)
    t = np.arange(0.0, 3.0, period)
    command = v_cmd * t
    frames = [
        (float(ti), cob, RPDO1.codec.pack(round(c * 1e6), round(v_cmd * 1e6)))
        for ti, c in zip(t, command, strict=True)
    ]
    clock = SimpleNamespace(frames=frames, rock_direction=0.0)
    creep = 0.06  # m/s: the oil column giving way under the jam
    stuck = v_cmd * t_inj
    hydraulic = np.where(t <= t_inj, command, stuck + creep * (t - t_inj))
    electric = np.where(t <= t_inj, command, stuck)
    shown_h = _exposed(clock, cob, t_inj, window, t, hydraulic)  # type: ignore[arg-type]
    shown_e = _exposed(clock, cob, t_inj, window, t, electric)  # type: ignore[arg-type]
    assert shown_e - t_inj == pytest.approx(window / v_cmd, abs=2 * period)
    assert shown_h - t_inj == pytest.approx(window / (v_cmd - creep), abs=2 * period)
    # Without a truth: from where the command was at the injection (the electric measure).
    assert _exposed(clock, cob, t_inj, window, np.empty(0), np.empty(0)) == shown_e  # type: ignore[arg-type]
    # A rock: only the way into it counts.
    clock.rock_direction = -1.0
    assert _exposed(clock, cob, t_inj, window, t, electric) == math.inf  # type: ignore[arg-type]


def test_a_killed_process_counts_as_ended_only_once_its_parent_can_reap_it() -> None:
    """A killed process with threads shows its main thread as a zombie while the others still
    exit, and its parent's ``waitpid`` does not yet find it ended; the campaign holds its clock
    until the process has ended (a killed planner), so ended must mean reapable."""
    from hil_sim.harness.campaign import _dead

    code = (
        "import threading, time\n"
        "for _ in range(256):\n"
        "    threading.Thread(target=time.sleep, args=(60,), daemon=True).start()\n"
        "print('up', flush=True)\n"
        "time.sleep(60)\n"
    )
    for _ in range(3):
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "up"
            os.kill(proc.pid, signal.SIGKILL)
            for _ in range(200_000):
                if _dead(proc.pid):
                    break
            else:
                pytest.fail("the killed process never ended")
            pid, status = os.waitpid(proc.pid, os.WNOHANG)
            assert pid == proc.pid and os.WIFSIGNALED(status), (pid, status)
            proc.returncode = -signal.SIGKILL
        finally:
            if proc.returncode is None:
                proc.kill()
                proc.wait()


def test_a_jammed_hydraulic_boom_is_detected_within_the_monitors_bound() -> None:
    """The field excavator's boom jammed in its taught cycle: it creeps on its oil column, the
    monitor latches within its cycles of the command outrunning it, the stop holds the limits,
    and the job resumes."""
    report = run_campaign(
        [Case(0, FaultKind.FOLLOWING_ERROR, "boom", 3.5, 0, digs=1)], "field_excavator", jobs=1
    )
    (row,) = report["cases"]
    assert not row["error"] and row["violations"] == [], row
    assert row["outcome"] == "stopped" and row["resumed"] and row["safe"], row
    assert row["shown_s"] > 0.0 and row["detection_s"] <= row["bound_s"], row


# -- the campaign, one case of every kind -----------------------------------------------------

#: Each case's fault early in its one-dig job (0.5-5 s after the first motion: the approach
#: and the dig), its target drawn among those the kind takes.
_SHORT_SEED = 27


def _short_cases() -> list[Case]:
    rng = random.Random(_SHORT_SEED)
    return [
        Case(i, kind, rng.choice(kind.targets), round(rng.uniform(0.5, 5.0), 2), i, digs=1)
        for i, kind in enumerate(FaultKind)
    ]


@pytest.fixture(scope="module")
def short_campaign() -> dict[str, Any]:
    return run_campaign(_short_cases(), jobs=2)


@pytest.mark.parametrize("kind", list(FaultKind), ids=lambda k: k.label)
def test_each_kind_is_detected_stopped_within_limits_and_resumed(
    short_campaign: dict[str, Any], kind: FaultKind
) -> None:
    (row,) = [r for r in short_campaign["cases"] if r["kind"] == kind.label]
    assert not row["error"], row
    assert row["violations"] == [], row
    assert row["resumed"] and not row["lost_job"], row
    if RULES[kind].outcome == "stopped":
        assert row["outcome"] == "stopped", row
        assert row["detection_s"] <= row["bound_s"], row
        for key in ("v", "a", "j"):
            assert (row["stop_peak"][key] or 0.0) <= 1.0, row
        assert row["plant_peak_v"] is None or row["plant_peak_v"] <= 1.05, row
    else:
        # Ridden through, or (a run of losses taking out a heartbeat) a safe stop.
        assert row["outcome"] in ("ridden_through", "stopped"), row
    assert row["safe"], row


def test_ridden_through_faults_are_counted(short_campaign: dict[str, Any]) -> None:
    rows = {r["kind"]: r for r in short_campaign["cases"]}
    assert rows["frame_loss"]["rode_through"]["missed_tpdo1"] > 0
    assert rows["frame_duplicate"]["wire"]["frame_duplicate"] == 1
    assert rows["error_frames"]["rode_through"]["error_frames"] >= 1
    summary = short_campaign["summary"]
    assert summary["cases"] == len(FaultKind)
    assert summary["safe"] == summary["cases"] and summary["lost_jobs"] == 0


def test_the_json_holds_every_documented_key(short_campaign: dict[str, Any]) -> None:
    from test_report_keys import README, _list_of, _paragraph, contract_keys, missing

    keys = contract_keys(_list_of(_paragraph(README, "`hil campaign --json`:")))
    assert ("cases", "stop_peak", "j") in keys and ("summary", "lost_jobs") in keys
    assert missing(short_campaign, keys) == []


# -- the soak, on a reduced size ---------------------------------------------------------------


def test_a_short_soak_keeps_every_job_and_record() -> None:
    """Jobs back to back with a fault every 8 simulated seconds (on average) for 25 s of wall
    time: every fault latched is reset, the store reads back after every dig and reset, nothing
    is lost. The memory growth is the command's (10 minutes in the benchmark), reported, not
    asserted."""
    from test_report_keys import README, _list_of, _paragraph, contract_keys, missing

    from hil_sim.harness.hil_soak import soak

    report = soak(25.0, fault_every_s=8.0, seed=5, warmup_s=5.0)
    keys = contract_keys(_list_of(_paragraph(README, "`hil soak --json`:")))
    assert ("loop", "runtime_us_p99_max") in keys and missing(report, keys) == []
    assert report["faults_injected"] >= 3 and report["resets"] >= 1, report
    assert report["store_checks"] >= report["resets"], report
    assert report["lost_jobs"] == 0 and report["corrupt_records"] == 0, report["problems"]
    assert report["memory_mb"]["warm"] > 0.0 and math.isfinite(report["memory_growth"])
    assert report["loop"]["speed"] > 0.0


def test_an_unwritable_store_latches_and_a_reset_says_why_until_it_is_back(
    rig: Rig, tmp_path: Path
) -> None:
    """The store's directory replaced by a file (every write fails, as on a full or read-only
    disk): the next write (the job's submission) latches a fault naming the store; a reset
    fails, saying so, while the cause stays; with the directory back the reset succeeds and the
    job runs to its end."""
    from hil_sim.harness.campaign import lockstep_config, wait_for
    from rt_runtime.service.jobstore import JobStatus, JobStore
    from rt_runtime.service.runner import RigRunner

    cfg = lockstep_config(tmp_path / "state", "scale_model")
    planner = TrenchPlanner(rig)
    hil = LockstepHil(rig, planner.home_pose_rad, vcu=False)
    store = JobStore(cfg.paths.state_dir)
    store.start()
    runner = RigRunner(cfg, rig, planner, hil.master_bus, store, hil.clock, hil.reopen_master_bus)
    state = cfg.paths.state_dir
    away = state.with_name("state.away")
    try:
        runner.start()
        wait_for(lambda: runner.health()[0], "holding")
        state.rename(away)
        state.write_text("in the way")
        job = store.submit(dict(CASE_TASK), "pinn", max_digs=1)
        store.changed.set()
        wait_for(lambda: runner.state().endswith("waiting for reset-fault"), "the latch")
        assert "the job store is not written" in runner.fault(), runner.fault()
        number = runner.reset_fault()
        wait_for(lambda: runner.resets_done >= number, "the first reset")
        assert "the latest reset failed: the job store is still not written" in runner.fault()
        state.unlink()
        away.rename(state)
        number = runner.reset_fault()
        wait_for(lambda: runner.resets_done >= number, "the second reset")
        assert runner.fault() == ""
        wait_for(lambda: store.get(job.id).status is JobStatus.DONE, "the job")
        assert len(store.get(job.id).digs) == 1
    finally:
        assert runner.shutdown(30.0)
        store.close()
        hil.close()


def _fill(directory: Path) -> Path:
    """Fill the filesystem of ``directory`` to its last block; the filler file."""
    filler = directory / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    block = bytes(4096)
    try:
        while True:
            os.write(fd, block)
    except OSError as exc:
        assert exc.errno == errno.ENOSPC, exc
    finally:
        os.close(fd)
    return filler


def _remount(directory: Path, option: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{option}", str(directory)], check=True)


#: The disk faults of a real filesystem: (what breaks it, the OS's words, what mends it).
_DISK_FAULTS: dict[str, tuple[Callable[[Path], Any], str, Callable[[Path, Any], None]]] = {
    "full": (_fill, "No space left on device", lambda d, filler: filler.unlink()),
    "read-only": (
        lambda d: _remount(d, "ro"),
        "Read-only file system",
        lambda d, _: _remount(d, "rw"),
    ),
}


@pytest.mark.parametrize("disk", sorted(_DISK_FAULTS))
def test_a_real_disk_fault_latches_keeps_the_store_whole_and_resumes_once_mended(
    rig: Rig, tmp_path: Path, disk: str
) -> None:
    """The state directory on a small tmpfs of its own, which after a first job is done is
    filled to its last block (a real ENOSPC) or remounted read-only (a real EROFS). The second
    job's submission cannot be written: a fault naming the store and the OS's error latches,
    the store on disk is still the one before (the first job done, no temporary file left), a
    reset fails while the cause stays; once the disk is mended the reset succeeds and the second
    job runs to its end."""
    from hil_sim.harness.campaign import lockstep_config, wait_for
    from rt_runtime.service.jobstore import JobStatus, JobStore, read_store
    from rt_runtime.service.runner import RigRunner

    breaks, words, mends = _DISK_FAULTS[disk]
    cfg = lockstep_config(tmp_path / "state", "scale_model")
    state = cfg.paths.state_dir
    state.mkdir(parents=True, exist_ok=True)
    mount = shutil.which("mount")
    done = (
        subprocess.run(
            [mount, "-t", "tmpfs", "-o", "size=16m,mode=0700", "tmpfs", str(state)],
            capture_output=True,
            check=False,
        )
        if mount
        else None
    )
    if done is None or done.returncode != 0:
        why = "no mount command" if done is None else done.stderr.decode().strip()
        pytest.skip(f"a real disk fault needs a tmpfs of its own, and none mounts here: {why}")
    try:
        planner = TrenchPlanner(rig)
        hil = LockstepHil(rig, planner.home_pose_rad, vcu=False)
        store = JobStore(state)
        store.start()
        runner = RigRunner(
            cfg, rig, planner, hil.master_bus, store, hil.clock, hil.reopen_master_bus
        )
        try:
            runner.start()
            wait_for(lambda: runner.health()[0], "holding")
            first = store.submit(dict(CASE_TASK), "pinn", max_digs=1)
            store.changed.set()
            wait_for(lambda: store.get(first.id).status is JobStatus.DONE, "the first job")
            assert store.sync()
            cause = breaks(state)
            second = store.submit(dict(CASE_TASK), "pinn", max_digs=1)
            store.changed.set()
            wait_for(lambda: runner.state().endswith("waiting for reset-fault"), "the latch")
            assert "the job store is not written" in runner.fault(), runner.fault()
            assert words in runner.fault(), runner.fault()
            _, on_disk = read_store(store.path)
            assert [(j.id, j.status) for j in on_disk] == [(first.id, JobStatus.DONE)]
            assert not list(state.glob(".*.tmp"))
            number = runner.reset_fault()
            wait_for(lambda: runner.resets_done >= number, "the first reset")
            assert "the latest reset failed: the job store is still not written" in runner.fault()
            mends(state, cause)
            number = runner.reset_fault()
            wait_for(lambda: runner.resets_done >= number, "the second reset")
            assert runner.fault() == ""
            wait_for(lambda: store.get(second.id).status is JobStatus.DONE, "the second job")
            assert store.sync()
            _, on_disk = read_store(store.path)
            assert [(j.id, j.status, len(j.digs)) for j in on_disk] == [
                (first.id, JobStatus.DONE, 1),
                (second.id, JobStatus.DONE, 1),
            ]
        finally:
            assert runner.shutdown(30.0)
            store.close()
            hil.close()
    finally:
        subprocess.run(["umount", "-l", str(state)], capture_output=True, check=False)


def _runner_on_own_models(rig: Rig, tmp_path: Path) -> tuple[Path, LockstepHil, Any, Any]:
    """A runner on the lockstep HIL planning from a copy of the shipped models (the
    directory under ``tmp_path``, which a test may change): ``(models, hil, store, runner)``,
    the store started, the runner not."""
    from hil_sim.harness.campaign import lockstep_config
    from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR
    from rt_runtime.service.jobstore import JobStore
    from rt_runtime.service.runner import RigRunner

    models = tmp_path / "models"
    shutil.copytree(DEFAULT_MODEL_DIR, models)
    cfg = lockstep_config(tmp_path / "state", "scale_model", models)
    planner = TrenchPlanner(rig, model_dir=models)
    hil = LockstepHil(rig, planner.home_pose_rad, vcu=False)
    store = JobStore(cfg.paths.state_dir)
    store.start()
    runner = RigRunner(cfg, rig, planner, hil.master_bus, store, hil.clock, hil.reopen_master_bus)
    return models, hil, store, runner


def _reset_to_the_end(runner: Any, store: Any, job_id: int, digs: int) -> None:
    """``reset-fault`` with the cause mended: the latch clears and the job resumes to its end,
    ``digs`` digs recorded."""
    from hil_sim.harness.campaign import wait_for
    from rt_runtime.service.jobstore import JobStatus

    number = runner.reset_fault()
    wait_for(lambda: runner.resets_done >= number, "the reset")
    wait_for(lambda: store.get(job_id).status is JobStatus.DONE, "the job")
    assert runner.fault() == ""
    assert len(store.get(job_id).digs) == digs


def test_a_changed_model_latches_and_a_reset_says_why_until_it_is_back(
    rig: Rig, tmp_path: Path
) -> None:
    """Other bytes deployed over a model under a running job: its planner process names the
    file and ends, the runner latches; a reset while the file stays changed fails the planner's
    start, saying which file and why; with the verified bytes back the job resumes to its end."""
    from hil_sim.harness.campaign import _change_model, _dead, wait_for

    models, hil, store, runner = _runner_on_own_models(rig, tmp_path)
    try:
        runner.start()
        wait_for(lambda: runner.health()[0], "holding")
        job = store.submit(dict(CASE_TASK), "pinn", max_digs=2)
        store.changed.set()
        # The first dig recorded: the planner process serves (it was verified and watches).
        wait_for(lambda: len(store.get(job.id).digs) >= 1, "the first dig")
        pid = runner.planner_pid()
        assert pid is not None
        undo = _change_model(models)
        wait_for(lambda: _dead(pid), "the planner process ending", 30.0)
        wait_for(lambda: runner.state().endswith("waiting for reset-fault"), "the latch")
        assert "pinn_downward.onnx changed on disk" in runner.fault(), runner.fault()
        number = runner.reset_fault()
        wait_for(lambda: runner.resets_done >= number, "the first reset")
        wait_for(lambda: runner.state().endswith("waiting for reset-fault"), "the second latch")
        fault = runner.fault()
        assert "could not start" in fault and "pinn_downward.onnx" in fault, fault
        assert "corrupt or was replaced" in fault, fault
        undo()
        _reset_to_the_end(runner, store, job.id, digs=2)
    finally:
        assert runner.shutdown(30.0)
        store.close()
        hil.close()


def test_a_model_change_noticed_only_at_the_last_dig_s_record_fails_the_job_not_done(
    rig: Rig, tmp_path: Path
) -> None:
    """A planner process that notices its changed model only when the job's last dig
    (``max_digs``) asks for its record (held stopped here, as a busy machine's niced process
    is held back) ends in place of that record: the job is not ``done`` with its last dig
    unrecorded, the runner latches why, and after a reset with the verified bytes back the
    dig is dug again and the job ends with both."""
    from hil_sim.harness.campaign import _change_model, _dead, wait_for
    from rt_runtime.service.jobstore import JobStatus

    models, hil, store, runner = _runner_on_own_models(rig, tmp_path)

    def progress() -> dict[str, Any]:
        return runner.progress() or {}

    pid: int | None = None
    try:
        runner.start()
        wait_for(lambda: runner.health()[0], "holding")
        job = store.submit(dict(CASE_TASK), "pinn", max_digs=2)
        store.changed.set()
        # The second dig streams: its plan is in; the process is held from here on.
        wait_for(
            lambda: progress().get("digs_done", 0) >= 1 and progress().get("phase") == "dig",
            "the last dig",
        )
        pid = runner.planner_pid()
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        undo = _change_model(models)
        # The last dig and its exit moves ran: the job waits for nothing but the record.
        wait_for(lambda: progress().get("phase") == "wait", "the record alone outstanding")
        os.kill(pid, signal.SIGCONT)
        wait_for(lambda: _dead(pid), "the planner process ending", 30.0)
        wait_for(lambda: runner.state().endswith("waiting for reset-fault"), "the latch")
        assert "pinn_downward.onnx changed on disk" in runner.fault(), runner.fault()
        assert store.get(job.id).status is JobStatus.FAILED
        assert len(store.get(job.id).digs) == 1
        undo()
        _reset_to_the_end(runner, store, job.id, digs=2)
    finally:
        if pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        assert runner.shutdown(30.0)
        store.close()
        hil.close()


def test_a_rock_stops_an_axis_that_pushes_or_moves_into_it(rig: Rig) -> None:
    """A boom lowering under gravity has its drive still pushing up: the rock below stops it
    all the same; resting on it and pulling away from it are free."""
    core = HilCore(rig, TrenchPlanner(rig).home_pose_rad, vcu=False)
    node = core.nodes[0]
    stroke = float(core.plant.stroke_m[0])
    with mock.patch.object(node.firmware, "servo_step", return_value=0.3):  # pushing up
        node.faults.rock_direction = -1.0  # the rock is below: retracting runs into it
        assert node.servo_step(2.5e-4, stroke, -0.01) == 0.0  # lowering: into the rock
        assert node.servo_step(2.5e-4, stroke, 0.0) == 0.3  # resting on it
        assert node.servo_step(2.5e-4, stroke, 0.01) == 0.3  # lifting off it
        node.faults.rock_direction = 1.0  # a rock above
        assert node.servo_step(2.5e-4, stroke, 0.0) == 0.0  # pushing into it
        node.faults.clear()
        assert node.servo_step(2.5e-4, stroke, 0.01) == 0.3
