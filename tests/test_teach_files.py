"""Teach and plan end to end: demonstration files in (CSV, CAN traces), refused when bad, the
``teach`` command, the taught job file and its loader, ``bench teach``."""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_report_keys import README, _list_of, _paragraph, contract_keys, missing

from hil_sim.operator import Demonstration, demonstrate, write_csv
from rt_runtime.cli import main
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.rig import Rig, load_rig
from rt_runtime.teach import load_taught, pipeline
from rt_runtime.teach.demos import (
    MIN_SAMPLES,
    DemonstrationError,
    read_csv,
    read_demo,
    read_trace,
    write_trace,
)
from rt_runtime.teach.taught import TAUGHT_FILE


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("field_excavator")


@pytest.fixture(scope="module")
def demos(rig: Rig) -> list[Demonstration]:
    return [demonstrate(rig, seed=s) for s in range(4)]


@pytest.fixture(scope="module")
def files(demos: list[Demonstration], rig: Rig, tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("demos")
    for demo in demos:
        write_csv(demo, d / f"demo_{demo.seed:02d}.csv")
        write_trace(rig, d / f"demo_{demo.seed:02d}.blf", demo.t_s, demo.q_rad)
        write_trace(rig, d / f"demo_{demo.seed:02d}.asc", demo.t_s, demo.q_rad)
    return d


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


# --- demonstrations in ------------------------------------------------------------------------


def test_csv_and_can_trace_give_the_same_joints_and_waypoints(files: Path, rig: Rig) -> None:
    csvs = sorted(files.glob("*.csv"))
    for suffix in ("blf", "asc"):
        traces = [p.with_suffix(f".{suffix}") for p in csvs]
        for c, t in zip(csvs, traces, strict=True):
            a, b = read_csv(rig, c), read_trace(rig, t)
            # Stroke in um through the stroke-to-joint map, swing in urad: a few urad apart;
            # the CSV keeps 1e-6 deg.
            np.testing.assert_allclose(b.q_rad, a.q_rad, atol=2e-5)
            np.testing.assert_allclose(b.t_s - b.t_s[0], a.t_s - a.t_s[0], atol=1e-6)
        settings = pipeline.TeachSettings()
        _, _, idx_c, w_c = pipeline.learn_waypoints(rig, [read_csv(rig, p) for p in csvs], settings)
        _, _, idx_t, w_t = pipeline.learn_waypoints(
            rig, [read_demo(rig, p) for p in traces], settings
        )
        assert idx_c.tolist() == idx_t.tolist()
        np.testing.assert_allclose(w_t, w_c, atol=math.radians(0.01))


def _write(path: Path, header: str, rows: list[list[float]]) -> Path:
    path.write_text(header + "\n" + "\n".join(",".join(repr(v) for v in r) for r in rows) + "\n")
    return path


def _good_rows(demo: Demonstration) -> list[list[float]]:
    return np.column_stack([demo.t_s, np.degrees(demo.q_rad)]).tolist()


HEADER = "t_s,swing_deg,boom_deg,stick_deg,bucket_deg"


def _bad_files(tmp: Path, demo: Demonstration) -> list[tuple[Path, int, str]]:
    """Bad files, each with the row and the rule its refusal must name."""
    good = _good_rows(demo)
    out = []
    rows = [r[:] for r in good]
    rows[20][0], rows[21][0] = rows[21][0], rows[20][0]
    out.append((_write(tmp / "unsorted.csv", HEADER, rows), 23, "time"))
    rows = [r[:] for r in good]
    rows[30][0] = rows[29][0]
    out.append((_write(tmp / "repeated.csv", HEADER, rows), 32, "time"))
    rows = [r[:] for r in good]
    rows[40][3] = math.nan
    out.append((_write(tmp / "nan.csv", HEADER, rows), 42, "number"))
    rows = [r[:] for r in good]
    rows[50][2] += 5.0
    out.append((_write(tmp / "jump.csv", HEADER, rows), 52, "jump"))
    rows = [r[:] for r in good]
    for r in rows[60:]:
        r[4] = r[4] + (40.0 - rows[60][4]) + 1.0  # bucket past +40 deg from row 62 on
    out.append((_write(tmp / "range.csv", HEADER, rows), 62, "range"))
    out.append((_write(tmp / "few.csv", HEADER, good[: MIN_SAMPLES - 1]), 0, "samples"))
    out.append((_write(tmp / "missing.csv", "t_s,swing_deg,boom_deg,bucket_deg",
                       [r[:3] + r[4:] for r in good]), 1, "columns"))
    rows = [r[:] for r in good]
    out.append((_write(tmp / "text.csv", HEADER, rows[:10]), 0, ""))
    (tmp / "text.csv").write_text(HEADER + "\n0.0,1,2,abc,4\n")
    out[-1] = (tmp / "text.csv", 2, "number")
    return out


def test_bad_demonstrations_are_refused_naming_file_row_and_rule(
    demos: list[Demonstration], rig: Rig, tmp_path: Path
) -> None:
    for path, row, rule in _bad_files(tmp_path, demos[0]):
        with pytest.raises(DemonstrationError) as e:
            read_csv(rig, path)
        assert e.value.rule == rule, (path.name, str(e.value))
        assert e.value.row == row, (path.name, str(e.value))
        assert str(path) in str(e.value) and f"rule '{rule}'" in str(e.value)
        if row:
            assert f"row {row}" in str(e.value)


def test_extra_columns_are_ignored(demos: list[Demonstration], rig: Rig, tmp_path: Path) -> None:
    rows = [[*r, 99.0] for r in _good_rows(demos[0])]
    rec = read_csv(rig, _write(tmp_path / "extra.csv", "t_s,swing_deg,boom_deg,stick_deg,"
                               "bucket_deg,operator_mood", rows))
    np.testing.assert_allclose(rec.q_rad, demos[0].q_rad, atol=1e-9)


def test_bad_traces_are_refused(demos: list[Demonstration], rig: Rig, tmp_path: Path) -> None:
    import can

    good = tmp_path / "good.asc"
    write_trace(rig, good, demos[0].t_s, demos[0].q_rad)
    msgs = list(can.ASCReader(str(good)))
    # Drop the bucket drive's TPDO1 (node 3) after the 10th SYNC.
    syncs = [i for i, m in enumerate(msgs) if m.arbitration_id == 0x080]
    drop = next(i for i in range(syncs[9], syncs[10]) if msgs[i].arbitration_id == 0x183)
    bad = tmp_path / "lost.asc"
    with can.ASCWriter(str(bad)) as w:
        for i, m in enumerate(msgs):
            if i != drop:
                w.on_message_received(m)
    with pytest.raises(DemonstrationError, match=r"row 10: rule 'frames'.*bucket \(node 3\)"):
        read_trace(rig, bad)
    with pytest.raises(DemonstrationError, match="rule 'file'"):
        read_demo(rig, tmp_path / "demo.txt")
    # SYNCs before the drives answer (boot) and after the last answer are not samples.
    booting = tmp_path / "boot.asc"
    with can.ASCWriter(str(booting)) as w:
        for k in range(5):
            w.on_message_received(
                can.Message(timestamp=msgs[0].timestamp - 0.05 + 0.01 * k, arbitration_id=0x080,
                            is_extended_id=False, data=b"")
            )
        for m in msgs:
            w.on_message_received(m)
        w.on_message_received(can.Message(timestamp=msgs[-1].timestamp + 0.01,
                                          arbitration_id=0x080, is_extended_id=False, data=b""))
    rec = read_trace(rig, booting)
    np.testing.assert_allclose(rec.q_rad, read_trace(rig, good).q_rad)
    assert rec.rows[0] == 6
    empty = tmp_path / "empty.blf"
    with can.Logger(str(empty)):
        pass
    with pytest.raises(DemonstrationError, match="no SYNC"):
        read_trace(rig, empty)


# --- teach, the taught job, nothing from a bad set ----------------------------------------------


@pytest.fixture(scope="module")
def taught(files: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    out = tmp_path_factory.mktemp("taught")
    code, stdout, err = _run(
        ["teach", "--rig", "field_excavator", "--demos", *map(str, sorted(files.glob("*.csv"))),
         "--cycles", "3", "--out", str(out), "--json"]
    )
    assert code == 0, err
    return json.loads(stdout), out


def test_teach_json_holds_the_documented_keys(taught: tuple[dict[str, Any], Path]) -> None:
    report, _ = taught
    keys = contract_keys(_list_of(_paragraph(README, "`teach --json`")))
    assert {("waypoints_deg",), ("cycle", "segments"), ("cycles_total_s",)} <= keys
    assert missing(report, keys) == []


def test_taught_cycle_is_fast_exact_and_near_the_operator(
    taught: tuple[dict[str, Any], Path], rig: Rig, demos: list[Demonstration]
) -> None:
    report, _ = taught
    assert report["within_limits"]["exact"]
    assert report["cycle"]["T_s"] <= 0.7 * report["operator_mean_cycle_s"]
    assert len(report["trench"]["cycles"]) == 3
    assert report["cycles_total_s"] == pytest.approx(
        sum(c["T_s"] for c in report["trench"]["cycles"])
    )
    # The taught cycle re-evaluated from its JSON coefficients passes its waypoints.
    c = report["cycle"]
    h = np.array([s["duration_s"] for s in c["segments"]])
    coef = np.array([s["coefficients"] for s in c["segments"]])
    knots = np.concatenate(([0.0], np.cumsum(h)))
    wp = np.radians(report["waypoints_deg"])
    for k, tw in enumerate(c["waypoint_times_s"]):
        i = min(int(np.searchsorted(knots, tw, side="right")) - 1, len(h) - 1)
        tau = tw - knots[i]
        q = ((coef[i, :, 0] * tau + coef[i, :, 1]) * tau + coef[i, :, 2]) * tau + coef[i, :, 3]
        np.testing.assert_allclose(q, wp[k], atol=1e-7)
    # Near the path the operator meant (4 demonstrations here; 15 in bench teach).
    t = np.linspace(0.0, c["T_s"], 3000)
    i = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(h) - 1)
    tau = (t - knots[i])[:, None]
    ci = coef[i]
    q = ((ci[..., 0] * tau + ci[..., 1]) * tau + ci[..., 2]) * tau + ci[..., 3]
    gap = pipeline.frechet_distance(
        pipeline.resample_by_length(pipeline.tip_path(rig, q), 0.02),
        pipeline.resample_by_length(pipeline.tip_path(rig, demos[0].intended_q_rad), 0.02),
    )
    assert report["frechet_to_mean_m"] <= report["epsilon_mm"] / 1e3 + 0.02
    assert gap <= report["epsilon_mm"] / 1e3 + 0.04


def test_load_taught_gives_the_executor_a_verified_trench(
    taught: tuple[dict[str, Any], Path], rig: Rig
) -> None:
    report, out = taught
    job = load_taught(out)
    assert job.joint_names == tuple(rig.joint_names) and job.n_cycles == 3
    assert job.duration_s == pytest.approx(report["cycles_total_s"])
    t = np.linspace(0.0, job.duration_s, 20001)
    q, v, a = job.sample(t), job.sample(t, 1), job.sample(t, 2)
    joints = (rig.swing.joint, *rig.joints) if rig.swing else rig.joints
    vmax = np.array([j.velocity_max_rad_s for j in joints])
    amax = np.array([j.acceleration_max_rad_s2 for j in joints])
    assert np.all(np.abs(v) <= vmax * (1 + 1e-6)) and np.all(np.abs(a) <= amax * (1 + 1e-6))
    assert np.all(np.abs(np.diff(q, axis=0)) <= vmax * (t[1] - t[0]) * (1 + 1e-6))
    np.testing.assert_allclose(job.q0_rad, np.radians(report["waypoints_deg"][0]), atol=1e-7)
    np.testing.assert_allclose(v[[0, -1]], 0.0, atol=1e-9)
    chk = job.limit_check(rig)
    # Minimum time to the planned share of the limits: some joint at exactly that share.
    share = report["settings"]["limit_fraction"]
    assert share == pipeline.TeachSettings().limit_fraction < 1.0
    assert chk.within_limits and chk.velocity_ratio.max() == pytest.approx(share, abs=1e-6)
    # The report's peaks are against the rig's limits too.
    peak = max(pk["velocity_ratio"] for pk in report["peaks"].values())
    assert peak == pytest.approx(share, abs=1e-6)


def test_a_tampered_taught_job_is_refused(
    taught: tuple[dict[str, Any], Path], tmp_path: Path
) -> None:
    _, out = taught
    data = json.loads((out / TAUGHT_FILE).read_text())
    fast = json.loads(json.dumps(data))
    for cyc in fast["trench"]["cycles"]:
        for seg in cyc["segments"]:
            c = np.array(seg["coefficients"])
            c[0] *= 1.2  # the swing's moves 20 % larger in the same time: beyond its limits
            seg["coefficients"] = c.tolist()
    (tmp_path / TAUGHT_FILE).write_text(json.dumps(fast))
    with pytest.raises(PlanningError, match="breaks the limits"):
        load_taught(tmp_path)
    broken = json.loads(json.dumps(data))
    broken["trench"]["cycles"][1]["segments"][0]["coefficients"][0][3] += 0.01
    (tmp_path / TAUGHT_FILE).write_text(json.dumps(broken))
    with pytest.raises(ConfigurationError, match="position of joint 0 jumps"):
        load_taught(tmp_path)
    with pytest.raises(ConfigurationError, match="no taught job"):
        load_taught(tmp_path / "nowhere")


def test_nothing_is_planned_from_a_set_with_a_bad_file(
    files: Path, demos: list[Demonstration], tmp_path: Path
) -> None:
    bad = tmp_path / "bad.csv"
    rows = _good_rows(demos[1])
    rows[70][1] = math.nan
    _write(bad, HEADER, rows)
    out = tmp_path / "out"
    code, stdout, err = _run(
        ["teach", "--demos", str(files / "demo_00.csv"), str(bad), "--out", str(out), "--json"]
    )
    assert code == 2 and stdout == ""
    assert re.search(rf"{re.escape(str(bad))}, row 72: rule 'number'", err), err
    assert not (out / TAUGHT_FILE).exists()
    code, _, err = _run(["teach", "--rig", "scale_model", "--demos", str(files / "demo_00.csv")])
    assert code == 2 and "no swing" in err
    code, _, err = _run(["teach", "--demos", str(files / "demo_00.csv"), "--epsilon-mm", "0"])
    assert code == 2 and "--epsilon-mm" in err


def test_bench_teach_json_holds_the_documented_keys() -> None:
    code, stdout, err = _run(
        ["bench", "teach", "--demos", "3", "--passes", "1", "--cycles", "1", "--json"]
    )
    assert code == 0, err
    report = json.loads(stdout)
    keys = contract_keys(_list_of(_paragraph(README, "`bench teach --json`")))
    assert {("waypoints_ms", "p50"), ("frechet_intended_m",)} <= keys
    assert missing(report, keys) == []
    assert report["within_limits"]["exact"]


def test_teach_plots_and_prints_the_report(files: Path, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    code, stdout, err = _run(
        ["teach", "--demos", *map(str, sorted(files.glob("*.csv"))[:2]), "--cycles", "2",
         "--plot", str(tmp_path)]
    )
    assert code == 0, err
    for name in ("teach_demos.png", "teach_trench.png", "teach_joints.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    assert "of the operator's mean" in stdout and "Zhao: 80.8 s for 7" in stdout


def test_any_bytes_as_a_demonstration_give_a_demonstration_error_or_a_record(
    rig: Rig, tmp_path: Path
) -> None:
    """Property-based: mutated CSV text and random bytes are refused with the documented error
    (naming the file and a rule) or read; never another exception."""
    hypothesis = pytest.importorskip("hypothesis")
    st = hypothesis.strategies
    good = HEADER + "\n" + "\n".join(
        f"{0.01 * k:.2f},0.0,{20 + 0.01 * k:.3f},-90.0,-60.0" for k in range(60)
    )

    @hypothesis.settings(max_examples=400, deadline=None, derandomize=True)
    @hypothesis.given(
        st.one_of(
            st.binary(max_size=400),
            st.builds(
                lambda i, t: (good[:i] + t + good[i:]).encode("utf-8", "surrogatepass"),
                st.integers(0, len(good)),
                st.text(max_size=12),
            ),
        ),
        st.sampled_from(["d.csv", "d.asc", "d.blf"]),
    )
    def check(data: bytes, name: str) -> None:
        path = tmp_path / name
        path.write_bytes(data)
        try:
            read_demo(rig, path)
        except DemonstrationError as e:
            assert str(path) in str(e) and "rule '" in str(e)

    check()


def test_any_damage_to_a_taught_job_is_refused_with_the_documented_errors(
    taught: tuple[dict[str, Any], Path], rig: Rig, tmp_path: Path
) -> None:
    """Property-based: a taught job with one value replaced anywhere (a number, a string, a
    list, null, an object) loads (when the value did not matter) or raises ConfigurationError or
    PlanningError; never another exception."""
    hypothesis = pytest.importorskip("hypothesis")
    st = hypothesis.strategies
    _, out = taught
    data = json.loads((out / TAUGHT_FILE).read_text())
    data["trench"]["cycles"] = data["trench"]["cycles"][:1]
    paths: list[tuple[Any, ...]] = []

    def walk(node: Any, at: tuple[Any, ...]) -> None:
        if len(paths) > 3000:
            return
        paths.append(at)
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, (*at, k))
        elif isinstance(node, list):
            for i, v in enumerate(node[:3]):
                walk(v, (*at, i))

    walk(data, ())
    values = st.one_of(
        st.none(), st.booleans(), st.integers(-5, 5), st.floats(allow_nan=True),
        st.text(max_size=5), st.lists(st.integers(0, 3), max_size=3), st.just({}),
    )

    @hypothesis.settings(max_examples=300, deadline=None, derandomize=True)
    @hypothesis.given(st.sampled_from(paths[1:]), values)
    def check(at: tuple[Any, ...], value: Any) -> None:
        doc = json.loads(json.dumps(data))
        node = doc
        for key in at[:-1]:
            node = node[key]
        node[at[-1]] = value
        path = tmp_path / TAUGHT_FILE
        path.write_text(json.dumps(doc))
        try:
            load_taught(tmp_path, rig)
        except (ConfigurationError, PlanningError) as e:
            assert str(path) in str(e)

    check()
