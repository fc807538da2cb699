"""The harness: ``bench hil`` (lockstep speed and whose time a period is)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hil_sim.harness.bench import bench_step, format_report
from hil_sim.sim import LockstepHil
from rt_runtime.canbus import CanMaster
from rt_runtime.cli import build_parser, main
from rt_runtime.rig import load_rig

# -- bench hil ---------------------------------------------------------------------------------


def test_bench_hil_is_a_bench_subcommand_from_an_entry_point() -> None:
    args = build_parser().parse_args(["bench", "hil", "--task", "B", "--seconds", "2", "--json"])
    assert (args.task, args.seconds, args.json) == ("B", 2.0, True)
    assert args.handler.__module__ == "hil_sim.harness.bench"


def test_bench_hil_refuses_a_negative_duration(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "hil", "--seconds", "-1"]) == 2
    assert "--seconds" in capsys.readouterr().out


def test_bench_hil_runs_a_dig_and_says_whose_time_it_was(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["bench", "hil", "--max-digs", "1", "--seconds", "0.2", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    task = r["task"]
    assert (task["task"], task["status"], task["digs"]) == ("A", "done", 1)
    assert task["sim_s"] > 5.0 and task["speed"] == pytest.approx(task["sim_s"] / task["wall_s"])
    assert 0.0 < task["hil_share"] < 1.0
    assert task["hil_s"] < task["wall_s"] and task["runtime_s"] > 0.0
    for part in ("hil_us", "runtime_us"):
        assert 0.0 < task[part]["p50"] <= task[part]["p99"] <= task[part]["max"], task[part]
    assert r["step"]["periods"] == 100
    text = format_report(r)
    assert "x real time" in text and "HIL share" in text and "models alone" in text


def test_the_step_measurement_replays_digs_for_the_machine_time_asked() -> None:
    r = bench_step(load_rig("scale_model"), 0.5)
    assert r["periods"] == 250 and r["digs"] == 1 and r["clock"] == "wall"
    for part in ("frames_us", "advance_us", "total_us"):
        assert 0.0 < r[part]["p50"] <= r[part]["p99"] <= r[part]["max"], (part, r[part])
    assert r["total_us"]["p50"] >= r["advance_us"]["p50"]


def test_the_lockstep_hil_splits_each_period_into_its_own_time_and_the_rest() -> None:
    rig = load_rig("scale_model")
    with LockstepHil(rig, np.radians([30.0, -90.0, -60.0])) as hil:
        master = CanMaster(hil.master_bus, rig, period_s=0.002)
        master.boot(hil.clock.now, 1.0)
        master.enable(hil.clock.now, 1.0)
        hold = master.feedback.position_um.copy()
        before = len(hil.cost.sync_wall_ns)
        for k in range(200):
            master.write_setpoints(hold, np.zeros_like(hold))
            master.read_feedback(hil.clock.now(), 0.0005)
            master.heartbeat(hil.clock.now())
            hil.clock.sleep_until((k + 1) * 0.002 + 1.0)
        summary = hil.cost.summary()
    assert len(hil.cost.sync_wall_ns) - before == 200
    assert summary["periods"] == len(hil.cost.sync_wall_ns) - 1
    assert 0.0 < summary["hil_us"]["p50"] <= summary["hil_us"]["max"]
    assert summary["runtime_us"]["p50"] > 0.0
    assert summary["hil_s"] + summary["runtime_s"] == pytest.approx(summary["wall_s"], rel=1e-9)
    wall, hil_ns = hil.cost.periods()
    assert wall.shape == hil_ns.shape and bool(np.all(hil_ns <= wall))
