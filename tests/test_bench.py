"""Benchmarks run end to end on reduced sizes and keep their JSON keys (a contract)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rt_runtime import bench
from rt_runtime.cli import main
from rt_runtime.rig import load_rig


def test_percentiles() -> None:
    p = bench.percentiles(np.arange(1001.0), tails=True)
    assert p == pytest.approx({"p50": 500.0, "p99": 990.0, "p999": 999.0, "max": 1000.0})


def test_bench_oneshot_keys_on_two_problems(capsys) -> None:  # type: ignore[no-untyped-def]
    assert main(["bench", "oneshot", "--problems", "2", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["problems"] == 2
    for key in ("solve_s", "de_solve_s"):
        assert set(r[key]) == {"p50", "p99"} and r[key]["p50"] > 0
    assert r["batch_problems_per_s"] > 0
    assert 0.0 <= r["within_1pct_of_de"] <= 1.0
    assert set(r["gap_to_de"]) == {"p50", "max"}
    assert r["paper"]["yao_pso_solve_s"] == [69.0, 71.0]
    assert len(r["per_problem"]) == 2


def test_bench_oneshot_without_reference() -> None:
    r = bench.bench_oneshot(load_rig("scale_model"), n_problems=2, de=False)
    assert "de_solve_s" not in r and r["feasible"] == 1.0


def test_bench_plan_compares_pinn_and_pso_on_the_same_dig_problems() -> None:
    from rt_runtime.bench import bench_plan
    from rt_runtime.rig import load_rig

    rig = load_rig("scale_model")
    quick = {"n_particles": 12, "n_iterations": 8, "polish_starts": 1}
    r = bench_plan(rig, ("B",), passes=1, pso_options=quick)
    e = r["tasks"]["B"]
    sp = e["same_problems"]
    roughing = [d for d in e["pinn"]["digs"] if d["status"] != "profile_pass"]
    assert sp["pinn"]["digs"] == sp["pso"]["digs"] == len(roughing) > 0
    for key in ("T_s", "volume_L", "energy_Wh"):
        assert sp["pso"][key] > 0.0
        assert sp["pinn_vs_pso"][key] == pytest.approx(sp["pinn"][key] / sp["pso"][key] - 1.0)
    # The PINN side is the one-shot plan of the same problems: its times are the digs' own
    # plans' order of magnitude (one-shot T within the planning thresholds).
    planning = rig.planning
    assert planning is not None
    assert planning.t_min_s * len(roughing) <= sp["pinn"]["T_s"] <= planning.t_max_s * len(roughing)
    assert "pso_totals" in e and "pinn_vs_pso" in e
    # The reference in the same run: the numpy geometry plans the same digs; the stages split
    # the whole plan's time.
    assert e["numpy_geometry_same_plan"] is True
    assert e["numpy_geometry_plan_us"]["p50"] > 0.0 and e["speedup_vs_numpy_geometry"] > 0.0
    assert sum(e["stage_us"].values()) == pytest.approx(e["plan_us"]["p50"], rel=1e-9)
    assert r["trench"]["geometry"] == "c"
