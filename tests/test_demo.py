"""``excavator-rt demo`` on a reduced run: one dig of task A through the executor and the
lockstep HIL; the run directory holds the report, the CAN trace and the figures."""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from rt_runtime.cli import main


def test_demo_one_dig_writes_the_run_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["demo", "--max-digs", "1", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "status done" in out and "worst tracking" in out and "wall time" in out
    (run_dir,) = tmp_path.iterdir()
    report = json.loads((run_dir / "report.json").read_text())
    assert report["status"] == "done" and len(report["digs"]) == 1
    assert report["goals"]["tracking_max_mm"]["met"]
    for key in ("tracking", "tip_error_max_mm", "coverage_error", "overdig_max_mm", "energy_Wh",
                "wall_s", "overruns", "demo"):  # fmt: skip
        assert key in report, key
    assert (run_dir / "timing.png").stat().st_size > 0
    assert any(p.name.startswith("fig18") for p in run_dir.glob("*.png"))
    with can.BLFReader(str(run_dir / "can.blf")) as reader:
        ids = {msg.arbitration_id for msg in reader}
    assert {0x080, 0x201, 0x181} <= ids  # SYNC, RPDO1 and TPDO1 of the boom drive
