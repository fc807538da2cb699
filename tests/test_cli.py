"""The command line: every command runs, --json prints one object, errors exit non-zero."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from rt_runtime.cli import main
from rt_runtime.rig import profile_names


@pytest.mark.parametrize("name", profile_names())
def test_rig_show_json(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig", "show", name, "--json", "--samples", "20000"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["name"] == name
    env = r["envelope"]
    assert 0 < env["max_radius_m"] <= sum(lk["length_m"] for lk in r["links"]) + 1e-9
    assert env["max_depth_below_ground_m"] == pytest.approx(
        env["max_depth_m"] + r["ground_y_m"], abs=1e-9
    )
    for c in r["cylinders"]:
        lo, hi = c["stroke_limits_mm"]
        for key in ("stroke_at_joint_min_mm", "stroke_at_joint_max_mm"):
            assert lo <= c[key] <= hi
    assert r["assumed"] and all(a["reason"] for a in r["assumed"])
    assert r["dof"] == (4 if name == "field_excavator" else 3)


def test_rig_show_text_and_list(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig", "show", "test_bench", "--samples", "5000"]) == 0
    out = capsys.readouterr().out
    assert "reach envelope" in out and "assumed values" in out and "hydraulic" in out
    assert main(["rig", "list"]) == 0
    assert "scale_model (default)" in capsys.readouterr().out


def test_rig_show_json_kinematics_table(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig", "show", "scale_model", "--json", "--samples", "2000"]) == 0
    r = json.loads(capsys.readouterr().out)
    rows = r["kinematics"]
    assert rows[0]["pose"] == "mid-range" and len(rows) == 7
    boom_min = next(row for row in rows if row["pose"] == "boom min")
    assert boom_min["q_deg"][0] == pytest.approx(-20.0)
    # The attitude column is the sum of the joint angles (Yao eq 2).
    for row in rows:
        assert row["attitude_deg"] == pytest.approx(sum(row["q_deg"]), abs=1e-6)


def test_oneshot_json(capsys: pytest.CaptureFixture[str]) -> None:
    args = [
        "oneshot",
        "--type",
        "downward",
        "--start-deg",
        "1.78",
        "-34.25",
        "-71.94",
        "--end-deg",
        "2.03",
        "-51.06",
        "-114.04",
        "--surface-m",
        "-0.378",
        "--json",
    ]
    assert main(args) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["feasible"] and 5.0 <= r["T_s"] <= 10.0 and 3.74 <= r["volume_L"] <= 5.72
    assert all(m >= 0 for m in r["margins"].values()) and len(r["margins"]) == 22
    assert 40.0 <= r["theta_p_deg"] <= 90.0 and math.isfinite(r["objective"])


def test_errors_exit_non_zero_with_a_message(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rig", "show", "moon_digger"]) == 2
    assert "no rig profile 'moon_digger'" in capsys.readouterr().err
    args = [
        "oneshot",
        "--type",
        "downward",
        "--start-deg",
        "100",
        "0",
        "0",
        "--end-deg",
        "0",
        "-50",
        "-100",
        "--surface-m",
        "-0.3",
    ]
    assert main(args) == 2
    assert "boom at 100.000 deg is outside" in capsys.readouterr().err


def test_console_scripts_are_installed() -> None:
    bindir = __import__("pathlib").Path(sys.executable).parent
    out = subprocess.run([bindir / "excavator-rt", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.startswith("excavator-rt ")
    daemon = subprocess.run([bindir / "excavator-rtd"], capture_output=True, text=True)
    assert daemon.returncode != 0 and "--config" in daemon.stderr  # nothing starts unconfigured


def test_interp_gao_table2_chooses_3_4_5_4_3(capsys: pytest.CaptureFixture[str], tmp_path) -> None:  # type: ignore[no-untyped-def]
    png = tmp_path / "interp.png"
    assert main(["interp", "--json", "--plot", str(png)]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["chosen"] == "3-4-5-4-3"  # Gao's conclusion
    assert set(r["strategies"]) == {"3-4-5-4-3", "3-4-7-4-3", "3-3-7-3-3"}
    # Segment 5 of the boom holds the last key point at t = 15 s.
    c = r["coefficients_deg"]["boom"][4]
    assert sum(a * 15.0 ** (len(c) - 1 - i) for i, a in enumerate(c)) == pytest.approx(
        58.46, abs=1e-6
    )
    assert png.stat().st_size > 10_000


def test_interp_bad_input(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["interp", "--joints-deg", "1,2", "3,4,5"]) == 2
    assert "takes a,b,c triples" in capsys.readouterr().err
    assert main(["interp", "--durations", "3", "3"]) == 2
    assert "--durations needs 5 values" in capsys.readouterr().err
    assert main(["interp", "--points", "9,9,0", "2.1,0.2,-70"]) == 2
    assert "error" in capsys.readouterr().err


# -- plan: the task domain and the status ---------------------------------------------------------


def test_plan_refuses_a_task_outside_the_domain_and_plans_nothing(
    capsys: pytest.CaptureFixture[str],
    tmp_path,
    monkeypatch: pytest.MonkeyPatch,  # type: ignore[no-untyped-def]
) -> None:
    from rt_runtime.planning import trench

    planned: list[object] = []
    monkeypatch.setattr(trench.TrenchPlanner, "plan", lambda self, task: planned.append(task))
    f = tmp_path / "huge.toml"
    f.write_text("length_m = 1e308\ndepth_m = 0.1\nbeta1_deg = 60\nbeta2_deg = 60\n")
    assert main(["plan", "--task", str(f), "--json"]) == 2
    out = capsys.readouterr()
    assert out.out == "" and "Traceback" not in out.err
    assert "task huge: length_m = 1e+308 is outside [0.3, 20] m" in out.err
    f.write_text("length_m = 0.6\ndepth_m = 0.15\nbeta1_deg = 60\nbeta2_deg = 90\n")
    assert main(["plan", "--task", str(f)]) == 2
    assert "beta2_deg = 90 is outside [30, 85] deg" in capsys.readouterr().err
    assert planned == []


def test_plan_exits_0_when_done(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", "--task", "A", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["status"] == "done" and r["reason"] is None and r["volume_left_L"] >= 0.0
    for d in r["digs"]:
        assert isinstance(d["finishing"], bool) and d["section"] == 0


def test_plan_exits_1_when_incomplete_and_prints_the_plan(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from rt_runtime.errors import PlanningError
    from rt_runtime.planning import trench

    # The session stops after its first dig (no dig removes the rest).
    original = trench.TrenchSession.next_dig

    def second_fails(self: trench.TrenchSession) -> object:
        if self.digs:
            raise PlanningError("no verified dig removes the rest (test)")
        return original(self)

    monkeypatch.setattr(trench.TrenchSession, "next_dig", second_fails)
    assert main(["plan", "--task", "A", "--json"]) == 1
    r = json.loads(capsys.readouterr().out)
    assert r["status"] == "incomplete" and len(r["digs"]) == 1
    assert r["reason"].startswith("planning stopped: no verified dig removes the rest (test)")
    assert "coverage error" in r["reason"] and r["volume_left_L"] > 0.0
    assert main(["plan", "--task", "A"]) == 1
    out = capsys.readouterr().out
    assert "status: incomplete" in out and "L of the design left" in out
