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
