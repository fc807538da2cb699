"""A dig over the 127.0.0.1 bridge, on the executor: the HIL in its own process.

Boot, enable, a dig with tracking and a readable trace, with the bridge (:mod:`hil_sim.bridge`)
between master and HIL and the executor's fixed-rate loop on the wall clock. The run plans in
the executor's planner process (the arm holds at the entry while the process starts). The HIL
process stops by itself after ``conftest.BRIDGE_MAX_WALL_S`` even if a test dies, and runs with
the bridge's patience (``conftest.BRIDGE_PATIENCE_S``: watchdog, heartbeat and stale-feedback
limits widened for a shared test machine). No assertion on timing: the round trip is printed.
The fault runs over the bridge are in ``test_faults.py``, written once for both transports.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from conftest import run_on_bridge

from rt_runtime.control.executor import ExecStatus
from rt_runtime.rig import Rig, load_rig


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


def test_a_dig_over_the_bridge_tracks(rig: Rig, pending: Any, tmp_path: Path) -> None:
    trace = tmp_path / "rt.blf"
    run = run_on_bridge(rig, pending, trace=trace)
    res, master, extra, truth = run.result, run.master, run.extra, run.truth
    tel = res.telemetry
    index = {int(s): i for i, s in enumerate(truth.sync_index)}
    rows = tel["sync"] >= 1
    sel = np.array([index.get(int(s), -1) for s in tel["sync"][rows]])
    stroke_true = np.full((len(tel["sync"]), 3), np.nan)
    stroke_true[rows] = np.where((sel >= 0)[:, None], truth.stroke_m[np.maximum(sel, 0)], np.nan)
    assert res.status is ExecStatus.DONE, res.fault
    assert len(master.drive_info) == 3
    assert [d.index for d in res.digs] == [0]
    track = tel["tracking"]
    err = (stroke_true - tel["stroke_ref_m"])[track]
    max_mm = np.nanmax(np.abs(err), axis=0) * 1e3
    rep = (tel["stroke_fb_m"] - tel["stroke_ref_m"])[track]
    # Bounded by the following-error window (no fault); the figure itself depends on this
    # machine's scheduling and is printed, not asserted (goal 1 mm: see the printed line).
    window_mm = rig.drives.following_error_window_m * 1e3
    assert (max_mm < window_mm).all(), max_mm
    assert (np.nanmax(np.abs(rep), axis=0) * 1e3 < window_mm).all()
    answered = np.isfinite(tel["rtt_s"])
    rtt = tel["rtt_s"][answered] * 1e6
    # Most SYNCs are answered within the read timeout (half a period) even on a busy machine.
    assert answered.mean() > 0.5, answered.mean()
    late = res.loop.lateness_s * 1e6
    print(
        f"\nSYNC -> TPDO round trip over 127.0.0.1: p50 {np.percentile(rtt, 50):.0f} us, "
        f"p99 {np.percentile(rtt, 99):.0f} us, max {rtt.max():.0f} us, answered in time "
        f"{answered.mean():.1%}; loop lateness p50 "
        f"{np.percentile(late, 50):.0f} us, p99 {np.percentile(late, 99):.0f} us, overruns "
        f"{res.overruns}; max truth error {max_mm.round(4).tolist()} mm; "
        f"{extra}"
    )
    messages = list(can.BLFReader(str(trace)))
    ids = {m.arbitration_id for m in messages}
    assert {0x000, 0x080, 0x181, 0x182, 0x183, 0x201, 0x77E, 0x701} <= ids


def test_the_real_time_hils_scanner_reaches_the_planner_process(
    rig: Rig, pending: Any, tmp_path: Path
) -> None:
    # The daemon's path with a scanner: the record is queued at once (a PendingScan on the
    # loop's thread), the planner link's sender fetches the HIL process's look (its terrain
    # cut in the process's terrain process, granular material included), and the planner
    # process plans the next dig on that surface, not ahead on the predicted material.
    from conftest import BRIDGE_MAX_WALL_S, BRIDGE_PATIENCE_S, patient, restore_pending

    from hil_sim.harness.realtime import RealtimeHilProcess
    from hil_sim.harness.scenario import NO_RT
    from hil_sim.terrain import Terrain
    from rt_runtime.canbus import CanMaster
    from rt_runtime.control import FixedRateLoop, LoopConfig, OverrunPolicy
    from rt_runtime.control.executor import Executor, ExecutorConfig, executor_telemetry
    from rt_runtime.control.planner_worker import PendingScan

    profile = tmp_path / "scale_model_imperfect.toml"
    text = (Path(__file__).parents[1] / "rt_runtime/rig/profiles/scale_model.toml").read_text()
    profile.write_text(text.replace("\nenabled = false ", "\nenabled = true ", 1))
    imperfect = load_rig(str(profile))
    assert imperfect.hil is not None and imperfect.hil.enabled and imperfect.hil.scanner
    session, q0 = restore_pending(*pending)
    material = imperfect.hil.active()
    assert material is not None and material.material is not None
    ground = Terrain(
        rig.ground_y_m, (session.x_lo, session.x_hi), rig.bucket.width_m, material=material.material
    )
    hil = RealtimeHilProcess.start(
        rig_name=str(profile),
        q0_rad=q0,
        terrain=ground,
        max_wall_s=BRIDGE_MAX_WALL_S,
        sync_timeout_s=BRIDGE_PATIENCE_S,
        scanner=True,
    )
    looked = [0]
    scans: list[tuple[np.ndarray, np.ndarray]] = []
    cuts: list[float] = []

    def fetch() -> tuple[np.ndarray, np.ndarray] | None:
        got = hil.scan(looked[0], timeout_s=30.0)
        assert got is not None
        looked[0], volume, x, y = got
        cuts.append(volume)
        scans.append((x, y))
        return x, y

    try:
        master = CanMaster(hil.master_bus, patient(rig), period_s=0.002, react_to_faults=False)
        loop = FixedRateLoop(
            hil.clock,
            LoopConfig(rt=NO_RT, overrun=OverrunPolicy(max_consecutive=50)),
            executor_telemetry(60_000),
        )
        executor = Executor(
            master,
            rig,
            loop,
            session,
            ExecutorConfig(max_digs=2, plan_in_worker=True, stale_cycles=100),
            surface_source=lambda: PendingScan(fetch),
        )
        try:
            master.boot(hil.clock.now, 2.0)
            master.enable(hil.clock.now, 2.0)
            res = executor.run()
        finally:
            executor.close()
        _, material_end, _, extra = hil.finish()
    finally:
        hil.close()
    assert res.status is ExecStatus.DONE, res.fault
    assert [r.index for r in res.digs] == [0, 1] and len(scans) == 2
    spacing = imperfect.hil.scanner.spacing_m
    for record, (x, y) in zip(res.digs, scans, strict=True):
        assert x[0] == pytest.approx(session.x_lo) and x[-1] <= session.x_hi + 1e-9
        np.testing.assert_allclose(np.diff(x), spacing)
        g = session.ground_y
        want = np.minimum(np.interp(session.grid, x, y, left=g, right=g), g)
        np.testing.assert_allclose(record.session_state["surface_m"], want, atol=1e-12)
    assert not res.digs[1].planned_ahead
    # Each look cut what the dig removed (the process's own terrain; the granular bucket
    # keeps less than it swept), and the terrain the process ends with is the cut one.
    assert all(v > 0.0 for v in cuts), cuts
    terrain = extra["terrain"]
    assert terrain["swept_m3"] == pytest.approx(sum(cuts))
    assert terrain["load_m3"] < terrain["swept_m3"]
    assert material_end is not None and material_end.area < ground.material.area
    # Its last look saw the surface the process ended with, to the scanner's noise.
    x, y = scans[-1]
    end = np.interp(x, terrain["x_m"], terrain["y_m"])
    assert float(np.std(y - end)) < 3.0 * imperfect.hil.scanner.noise_m
