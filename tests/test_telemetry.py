"""Telemetry ring buffer: wraps right, keeps cycle order, step columns, npz, no allocation."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from rt_runtime.control import Column, Telemetry
from rt_runtime.errors import ConfigurationError


def _record(tel: Telemetry, n: int, first: int = 0) -> None:
    stroke = tel.column("stroke_m")
    for k in range(first, first + n):
        tel.begin(k, 0.002 * k, 1e-6 * k, k % 7 == 0)
        stroke[tel.slot] = (k, 2 * k, 3 * k)
        tel.end(1e-7 * k)


def test_snapshot_before_wrap_is_in_order() -> None:
    tel = Telemetry(8, [Column("stroke_m", np.float64, (3,))])
    _record(tel, 5)
    snap = tel.snapshot()
    assert tel.size == 5 and tel.dropped == 0
    np.testing.assert_array_equal(snap["cycle"], np.arange(5))
    np.testing.assert_allclose(snap["t_s"], 0.002 * np.arange(5))
    np.testing.assert_allclose(snap["exec_s"], 1e-7 * np.arange(5))
    np.testing.assert_array_equal(snap["overrun"], np.arange(5) % 7 == 0)
    assert snap["stroke_m"].shape == (5, 3)
    np.testing.assert_allclose(snap["stroke_m"][:, 1], 2 * np.arange(5))


@pytest.mark.parametrize("n", [8, 9, 20, 23, 64])
def test_wraps_and_keeps_the_last_capacity_cycles_in_order(n: int) -> None:
    tel = Telemetry(8, [Column("stroke_m", np.float64, (3,))])
    _record(tel, n)
    snap = tel.snapshot()
    expected = np.arange(max(0, n - 8), n)
    assert tel.count == n and tel.size == 8 and tel.dropped == n - 8
    np.testing.assert_array_equal(snap["cycle"], expected)
    np.testing.assert_allclose(snap["lateness_s"], 1e-6 * expected)
    np.testing.assert_allclose(snap["stroke_m"][:, 2], 3 * expected)
    assert np.all(np.diff(snap["t_s"]) > 0)


def test_unwritten_step_columns_get_their_fill_not_stale_values() -> None:
    tel = Telemetry(
        4, [Column("q_rad", np.float64, (3,)), Column("phase", np.int8, (), -1), Column("seg")]
    )
    q = tel.column("q_rad")
    phase = tel.column("phase")
    for k in range(6):
        tel.begin(k, float(k), 0.0, False)
        if k < 4:  # the first 4 rows are written, then overwritten by rows the step skips
            q[tel.slot] = 1.0
            phase[tel.slot] = 2
        tel.end(0.0)
    snap = tel.snapshot()
    np.testing.assert_array_equal(snap["cycle"], [2, 3, 4, 5])
    np.testing.assert_array_equal(snap["phase"], [2, 2, -1, -1])
    assert np.all(snap["q_rad"][:2] == 1.0) and np.all(np.isnan(snap["q_rad"][2:]))
    assert np.all(np.isnan(snap["seg"]))


def test_clear_and_snapshot_of_empty_buffer() -> None:
    tel = Telemetry(4)
    assert all(v.shape[0] == 0 for v in tel.snapshot().values())
    tel.begin(0, 0.0, 0.0, False)
    tel.end(0.0)
    tel.clear()
    assert tel.count == 0 and tel.snapshot()["cycle"].size == 0


def test_snapshot_is_a_copy() -> None:
    tel = Telemetry(4)
    tel.begin(0, 1.0, 0.0, False)
    tel.end(0.0)
    snap = tel.snapshot()
    snap["t_s"][0] = 99.0
    assert tel.snapshot()["t_s"][0] == 1.0


def test_write_npz_round_trip(tmp_path: Path) -> None:
    tel = Telemetry(8, [Column("stroke_m", np.float64, (3,))])
    _record(tel, 11)
    out = tel.write_npz(tmp_path / "sub" / "trace")
    assert out.name == "trace.npz" and out.exists()
    with np.load(out) as data:
        snap = tel.snapshot()
        assert set(data.files) == set(snap)
        for name, arr in snap.items():
            np.testing.assert_array_equal(data[name], arr)


def test_bad_configuration_is_refused_with_names() -> None:
    with pytest.raises(ConfigurationError, match="capacity"):
        Telemetry(0)
    with pytest.raises(ConfigurationError, match="lateness_s"):
        Telemetry(4, [Column("lateness_s")])
    with pytest.raises(ConfigurationError, match="'a'"):
        Telemetry(4, [Column("a"), Column("a")])
    with pytest.raises(ConfigurationError, match="no column 'nope'"):
        Telemetry(4).column("nope")


def test_recording_a_cycle_does_not_allocate() -> None:
    tel = Telemetry(1024, [Column("stroke_m", np.float64, (3,)), Column("phase", np.int8)])
    stroke = tel.column("stroke_m")
    phase = tel.column("phase")
    value = np.array([0.1, 0.2, 0.3])
    t = 0.0
    for k in range(2000):  # warm up (first-use caches)
        tel.begin(k, t, 0.0, False)
        stroke[tel.slot] = value
        phase[tel.slot] = 1
        tel.end(0.0)
    tracemalloc.start()
    try:
        before, _ = tracemalloc.get_traced_memory()
        for k in range(10_000):
            t += 0.002
            tel.begin(k, t, 1e-6, k % 100 == 0)
            stroke[tel.slot] = value
            phase[tel.slot] = 2
            tel.end(1e-5)
        after, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert after - before < 4096, f"{after - before} bytes kept over 10k cycles"


def test_a_dropped_row_after_the_wrap_takes_the_oldest_with_it() -> None:
    tel = Telemetry(4, [Column("x", np.int64, (), -1)])
    x = tel.column("x")
    for k in range(6):
        tel.begin(k, float(k), 0.0, False)
        x[tel.slot] = k
    tel.begin(6, 6.0, 0.0, False)  # overwrites row 2's slot, then turns out to send nothing
    tel.discard()
    snap = tel.snapshot()
    assert snap["x"].tolist() == [3, 4, 5]
    assert snap["cycle"].tolist() == [3, 4, 5]
    tel.begin(6, 6.0, 0.0, False)  # the next record fills the gap
    x[tel.slot] = 6
    assert tel.snapshot()["x"].tolist() == [3, 4, 5, 6]
    # Before the wrap a dropped row takes nothing else.
    tel.clear()
    for k in range(2):
        tel.begin(k, float(k), 0.0, False)
        x[tel.slot] = k
    tel.begin(2, 2.0, 0.0, False)
    tel.discard()
    assert tel.snapshot()["x"].tolist() == [0, 1]
