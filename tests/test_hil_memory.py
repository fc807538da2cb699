"""The HIL's memory is bounded: the truth ring, the SYNC statistics, and a short soak of the
real-time HIL process against a client whose resident memory stays flat after the warm-up.

The soak's assertion is on memory, not time: ``soak_hil`` samples the HIL process's RSS once a
second for 30 s (10 s warm-up); the HIL as it was before (per-SYNC Python lists) grew by about
0.23 MB/s at 500 Hz on the build machine, 7 % of its size in the 20 s measured here. The drives'
SYNC watchdog is widened for this test only: the subject is memory, and a watchdog trip on the
shared machine would stop the drives, not the measurement.
"""

from __future__ import annotations

import tomllib
from importlib import import_module
from pathlib import Path

import numpy as np
import pytest

from hil_sim.harness.realtime import SyncStats
from hil_sim.harness.soak import GROWTH_GOAL, soak_hil
from hil_sim.sim import COB_SYNC, HilCore, TruthRing
from hil_sim.terrain import Terrain
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import load_rig

ROOT = Path(__file__).resolve().parents[1]


def test_truth_ring_keeps_the_last_rows_in_order() -> None:
    ring = TruthRing(5)
    for k in range(1, 13):
        ring.append((k, 0.1 * k, k, k, k, 0.0, 0.0, 0.0, 0.0, 1.0))
    assert (ring.count, ring.kept, ring.dropped) == (12, 5, 7)
    rows = ring.rows(0, ring.count - 1)
    assert rows[:, 0].tolist() == [8, 9, 10, 11, 12]
    assert ring.rows(8, 9)[:, 0].tolist() == [9, 10]  # rows 8..9 are SYNCs 9..10
    assert ring.rows(0, 6).shape == (0, 10)  # all overwritten
    assert ring.rows(5, 8)[:, 0].tolist() == [8, 9]  # clipped to what is kept
    with pytest.raises(ConfigurationError):
        TruthRing(1)


def test_truth_ring_grows_by_doubling_and_preallocates() -> None:
    ring = TruthRing(10_000)
    assert len(ring._data) == 4096
    for k in range(5000):
        ring.append((k + 1,) + (0.0,) * 9)
    assert len(ring._data) == 8192 and ring.dropped == 0
    assert ring.rows(0, 4999)[:, 0].tolist() == list(range(1, 5001))
    assert len(TruthRing(10_000, preallocate=True)._data) == 10_000


def test_hil_core_truth_is_bounded_and_cut_uses_what_is_kept() -> None:
    rig = load_rig("scale_model")
    q0 = np.radians([30.0, -90.0, -60.0])
    core = HilCore(rig, q0, Terrain(-0.25, (0.5, 2.0), 0.22), truth_rows=100)
    for k in range(1, 251):
        core.advance(0.002)
        core.on_frame(COB_SYNC, b"", 0.002 * k)
    truth = core.truth()
    assert core.sync_count == 250 and core.truth_ring.dropped == 150
    assert truth.sync_index.tolist() == list(range(151, 251))
    assert np.allclose(np.diff(truth.t_s), 0.002)
    assert truth.stroke_m.shape == (100, 3) and truth.tip_xy_m.shape == (100, 2)
    assert core.cut(1, 150) == 0.0  # overwritten: nothing to cut with
    assert core.cut(200, 250) >= 0.0


def test_sync_stats_keep_whole_run_counts_and_the_last_values() -> None:
    stats = SyncStats(4, period_s=0.002)
    for k in range(10):
        stats.record(0.001 * k, 1e-4 * k)
    assert stats.count == 10 and stats.missed == 7  # 3..9 ms: more than a period
    assert stats.handling_max_s == pytest.approx(0.009)
    assert stats.work_max_s == pytest.approx(9e-4)
    assert stats.handling_s() == pytest.approx([0.006, 0.007, 0.008, 0.009])
    assert stats.work_s() == pytest.approx([6e-4, 7e-4, 8e-4, 9e-4])


def test_soak_is_a_bench_subcommand_through_its_entry_point() -> None:
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    target = doc["project"]["entry-points"]["excavator_rt.bench"]["soak"]
    module, _, name = target.partition(":")
    assert getattr(import_module(module), name).__module__ == "hil_sim.harness.soak"


def test_real_time_hil_memory_is_flat_over_a_soak() -> None:
    try:
        report = soak_hil(
            "scale_model", 30.0, sample_s=1.0, warmup_s=10.0, sync_timeout_s=0.5, truth_s=20.0
        )
    except OSError as exc:
        pytest.skip(f"the real-time HIL process cannot start here: {exc}")
    samples = [round(m, 1) for _, m in report.samples]
    print(
        f"\nHIL soak 30 s: RSS {samples} MB; growth after the warm-up "
        f"{report.growth_after_warmup:+.2%} (largest {report.max_growth_after_warmup:+.2%}); "
        f"loop {report.cycles} cycles, {report.overruns} overruns; {report.hil_process}"
    )
    assert len(report.samples) >= 25
    assert min(report.travel_mm) > 5.0, report.travel_mm  # the arm moved all along
    assert report.hil_process["truth_dropped"] > 0  # the ring wrapped (20 s of truth kept)
    assert report.max_growth_after_warmup < 0.5 * GROWTH_GOAL, samples
