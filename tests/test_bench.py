"""Benchmarks run end to end on reduced sizes and keep their JSON keys (a contract)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rt_runtime import bench
from rt_runtime.cli import main
from rt_runtime.reports import Distribution
from rt_runtime.rig import load_rig


def test_percentiles() -> None:
    p = Distribution.of(np.arange(1001.0), tails=True).to_json()
    assert p == pytest.approx({"p50": 500.0, "p99": 990.0, "p999": 999.0, "max": 1000.0})
    assert set(Distribution.of(np.arange(3.0)).to_json()) == {"p50", "p99"}


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
    assert "de_solve_s" not in r.to_json() and r.feasible == 1.0


def test_bench_plan_compares_pinn_and_pso_on_the_same_dig_problems() -> None:
    from rt_runtime.bench import bench_plan
    from rt_runtime.rig import load_rig

    rig = load_rig("scale_model")
    quick = {"n_particles": 12, "n_iterations": 8, "polish_starts": 1}
    # D: the network digs its upper layer (A-C are dug along the outline alone).
    r = bench_plan(rig, ("D",), passes=1, pso_options=quick)
    assert r.tasks is not None and r.trench is not None
    e = r.tasks["D"]
    assert e.pso is not None
    sp = e.pso.same_problems
    roughing = [d for d in e.pinn.digs if d.status == "filled"]
    assert sp.pinn.digs == sp.pso.digs == len(roughing) > 0
    for key in ("T_s", "volume_L", "energy_Wh"):
        pinn, pso = getattr(sp.pinn, key), getattr(sp.pso, key)
        assert pso > 0.0
        assert sp.pinn_vs_pso[key] == pytest.approx(pinn / pso - 1.0)
    # The PINN side is the one-shot plan of the same problems: its times are the digs' own
    # plans' order of magnitude (one-shot T within the planning thresholds).
    planning = rig.planning
    assert planning is not None
    # The plans' own durations (machine time of the sextics), not wall time.
    dig_durations = sp.pinn.T_s
    shortest, longest = planning.t_min_s * len(roughing), planning.t_max_s * len(roughing)
    assert shortest <= dig_durations <= longest
    j = e.to_json()
    assert "pso_totals" in j and "pinn_vs_pso" in j
    # The reference in the same run: the numpy geometry plans the same digs; the stages split
    # the whole plan's time.
    assert e.numpy_geometry_same_plan is True
    assert e.numpy_geometry_plan_us.p50 > 0.0 and e.speedup_vs_numpy_geometry > 0.0
    assert sum(e.stage_us.values()) == pytest.approx(e.plan_us.p50, rel=1e-9)
    # Without the dig cycles' planning (stage transitions): the dig's choice, plan and checks.
    assert 0.0 < e.dig_plan_per_dig_ms.p50 < e.plan_per_dig_ms.p50
    assert j["dig_plan_per_dig_ms"] == e.dig_plan_per_dig_ms.to_json()
    assert r.to_json()["trench"]["dig_plan_per_dig_ms"] is not None
    # Each dig's own planning (next_dig less the moves into it): one time per dig, together
    # no more than the whole plan less its moves and the material updates.
    each = e.pinn.dig_plan_us
    assert len(each) == len(e.pinn.digs) and min(each) > 0.0
    st = e.pinn.stage_us
    assert sum(each) <= e.pinn.plan_total_us - st["transitions"] - st["record"]
    assert e.pinn.to_json()["dig_plan_us"] == list(each)
    assert j["dig_plan_each_ms"]["max"] == pytest.approx(max(each) / 1e3)
    assert set(r.to_json()["trench"]["dig_plan_each_ms"]) == {"p50", "p99", "p999", "max"}
    assert r.trench.geometry == "c"
    # The dig cycles, per task as the plan reports them and over the tasks.
    cycles = j["cycles"]
    # One cycle into each dig but the first; a dig's joined pieces have none between them.
    assert cycles == j["pinn"]["cycles"] and len(cycles) == len(e.pinn.buckets) - 1
    assert {"waypoints_deg", "moves_s", "bound_s"} <= set(cycles[0])
    assert j["moves_per_cycle_s"] == pytest.approx(np.mean([c["moves_s"] for c in cycles]))
    figures = j["cycle_figures"]
    assert figures["cycles"] == len(cycles) and set(figures["moves_vs_bound"]) == {"mean", "max"}
    assert r.to_json()["trench"]["cycles"] == figures
    assert {"moves_vs_bound_mean_max", "moves_vs_bound_max"} <= set(r.to_json()["goals"])


def test_random_suite_is_seeded_and_has_every_key() -> None:
    from rt_runtime.planning.trench import task_limits

    rig = load_rig("scale_model")
    tasks = bench.random_tasks(rig, 3, seed=5)
    again = bench.random_tasks(rig, 3, seed=5)
    assert tasks == again and tasks != bench.random_tasks(rig, 3, seed=6)
    limits = task_limits(rig)
    for t in tasks:
        assert limits["depth_m"][0] <= t.depth_m <= limits["depth_m"][1]
        assert 0.3 <= t.length_m <= 1.5 and t.bottom_length_m >= 0.0
    suite = bench.bench_plan_random(rig, 3, seed=5)
    r = suite.to_json()
    keys = {
        "tasks", "seed", "within_2pct", "within_4pct", "coverage_error", "overdig_max_mm",
        "digs", "fill", "finishing_per_section_max", "transition_penetration_max_mm",
        "plan_ms", "plan_per_dig_ms", "status_done", "errors", "error_tasks", "worst",
        "reference", "plan_per_dig_over_pinn_plan", "per_task", "cycles",
        "dig_plan_per_dig_ms", "sections_within_finishing_goal", "dig_plan_each_ms",
    }  # fmt: skip
    assert keys <= set(r)
    assert set(r["cycles"]) == {"cycles", "moves_per_cycle_s", "moves_vs_bound", "fallbacks"}
    for key in ("task_time_s", "moves_per_cycle_s", "moves_vs_bound_max", "cycle_fallbacks"):
        assert key in r["per_task"][0]
    assert r["tasks"] == 3 and r["seed"] == 5 and r["errors"] == 0
    assert set(r["coverage_error"]) == {"p50", "p99", "max"}
    for key in ("overdig_max_mm", "digs", "transition_penetration_max_mm"):
        assert set(r[key]) == {"p50", "max"}
    for key in ("plan_ms", "plan_per_dig_ms", "dig_plan_per_dig_ms"):
        assert set(r[key]) == {"p50", "p99"} and r[key]["p50"] > 0.0
    each = r["dig_plan_each_ms"]
    assert set(each) == {"p50", "p99", "p999", "max"}
    assert 0.0 < each["p50"] <= each["p99"] <= each["p999"] <= each["max"]
    # The dig's own planning is the whole plan less the dig cycles' (stage transitions).
    tasks_json = r["per_task"]
    assert all(0.0 < t["cycles_plan_ms"] < t["plan_ms"] for t in tasks_json)
    # Per dig planned: each joined piece is one request to the planner.
    want = [(t["plan_ms"] - t["cycles_plan_ms"]) / t["pieces"] for t in tasks_json]
    assert all(t["pieces"] >= t["digs"] for t in tasks_json)
    assert r["dig_plan_per_dig_ms"]["p50"] == pytest.approx(float(np.percentile(want, 50)))
    sections = [k for t in tasks_json for k in t["finishing_per_section"]]
    assert max(sections) == r["finishing_per_section_max"]
    assert r["sections_within_finishing_goal"] == pytest.approx(
        sum(k <= 2 for k in sections) / len(sections)
    )
    assert set(r["fill"]) == {"min", "p50", "max", "band_L", "within_band", "n"}
    assert r["fill"]["band_L"] == pytest.approx([3.74, 5.72])
    assert 0.0 <= r["within_2pct"] <= r["within_4pct"] <= 1.0
    assert 0.0 <= r["status_done"] <= 1.0
    assert len(r["worst"]) == 3
    worst = r["worst"][0]
    assert worst["coverage_error"] == r["coverage_error"]["max"]
    for key in ("length_m", "depth_m", "beta1_deg", "beta2_deg", "start_x_m", "coverage_error",
                "overdig_max_mm", "digs", "status", "reason"):  # fmt: skip
        assert key in worst
    assert r["reference"]["pinn_plan_ms"]["p50"] > 0.0 and r["plan_per_dig_over_pinn_plan"] > 0.0
    # a task of the suite replays: the same values plan to the same coverage
    from rt_runtime.planning.trench import TrenchPlanner, make_task

    w = suite.worst[0]
    t = make_task(rig, w.length_m, w.depth_m, w.beta1_deg, w.beta2_deg, w.start_x_m)
    assert w.planned is not None
    assert TrenchPlanner(rig).plan(t).coverage_error == pytest.approx(w.planned.coverage_error)


def test_random_suite_counts_a_failing_task_and_goes_on(monkeypatch: pytest.MonkeyPatch) -> None:
    from rt_runtime.planning import trench

    rig = load_rig("scale_model")
    planner = trench.TrenchPlanner(rig)
    original = trench.TrenchPlanner.plan

    def fails_once(self: trench.TrenchPlanner, task: trench.TrenchTask) -> trench.TrenchPlan:
        if task.name.endswith("-0"):
            raise ValueError("boom (test)")
        return original(self, task)

    monkeypatch.setattr(trench.TrenchPlanner, "plan", fails_once)
    r = bench.bench_plan_random(rig, 2, seed=5, planner=planner)
    assert r.errors == 1 and len(r.per_task) == 2
    assert r.error_tasks[0].error == "ValueError: boom (test)"
    assert r.error_tasks[0].name == "random-5-0"
    assert r.coverage_error is not None and len(r.worst) == 1


def test_bench_plan_random_cli(capsys) -> None:  # type: ignore[no-untyped-def]
    assert main(["bench", "plan", "--random", "1", "--seed", "3", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r) == {"rig", "random"} and r["random"]["tasks"] == 1  # no named tasks
    assert main(["bench", "plan", "--random", "1", "--seed", "3"]) == 0
    assert "Random suite on scale_model: 1 tasks, seed 3" in capsys.readouterr().out
    assert main(["bench", "plan", "--random", "0"]) == 2
