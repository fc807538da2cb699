"""Lockstep HIL on the executor: tracking on a real dig, determinism, decodable traces.

Everything runs over the lockstep HIL's in-process channel in one process on simulated time,
the executor (fixed-rate loop, limit guard, monitors) driving the drives through the master.
The trace check decodes every frame independently of the product's codecs: PDOs and SDOs from
the EDS through canopen's object dictionary, VCU frames from the DBC through cantools, also for
the trace of a fault run (the fault runs' own checks are in ``test_faults.py``, on both
transports).
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Any

import can
import cantools
import numpy as np
import pytest
from canopen.objectdictionary import ODVariable, import_od
from conftest import rpdo1_limit_check, run_on_lockstep

from firmware_models import CIA402_DRIVE_EDS, VCU_DBC, VCU_DBC_NODE_ID
from hil_sim.harness.reports import HilReport
from hil_sim.harness.scenario import HilRun, Scenario, run_scenario
from hil_sim.sim import FaultKind
from rt_runtime.control.executor import ExecStatus
from rt_runtime.rig import Rig, load_rig

AXES = ("boom", "stick", "bucket")


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


@pytest.fixture(scope="module")
def one_dig_run(tmp_path_factory: pytest.TempPathFactory) -> HilRun:
    trace = tmp_path_factory.mktemp("trace") / "dig.asc"
    return run_scenario(
        Scenario(task="A", max_digs=1, start_at_entry=True, keep_frames=True, trace_path=str(trace))
    )


@pytest.fixture(scope="module")
def one_dig(one_dig_run: HilRun) -> HilReport:
    """The run's report."""
    return one_dig_run.report


# -- tracking ----------------------------------------------------------------------------------


def test_one_dig_tracks_within_the_goal(one_dig: HilReport) -> None:
    report = one_dig
    assert report.status == "done", report.fault
    assert len(report.digs) == 1
    assert report.overruns == 0
    for axis in AXES:
        fig = report.tracking[axis]
        assert 0.0 < fig.max_mm <= 1.0, (axis, fig)
        assert 0.0 < fig.rms_mm <= 0.3, (axis, fig)
        assert fig.reported.max_mm <= 1.0, (axis, fig)
    assert report.tip_error_max_mm <= 3.0
    # The bucket really removed material; the planner's measured-path volume agrees with the
    # volume the HIL's terrain lost to the true path (reported vs true strokes, micrometres).
    dig = report.digs[0]
    assert dig.cut_volume_L > 1.0
    assert dig.measured_volume_L == pytest.approx(dig.cut_volume_L, rel=0.02)
    assert report.coverage_error is not None and 0.0 < report.coverage_error < 1.0
    assert report.energy_Wh > 0.0


def test_a_carried_bucket_runs_through_the_executor_within_the_goal(tmp_path: Path) -> None:
    # 0.49 m x 0.07 m (random suite, seed 5): the last pass's bucket is carried from the exit
    # of the joined pass before it, its cycle without a dump, in the closed loop on the
    # measured paths as in the plan.
    from rt_runtime.bench import random_tasks

    task = random_tasks(load_rig("scale_model"), 200, 5)[59]
    path = tmp_path / "task.toml"
    path.write_text(
        f"length_m = {task.length_m!r}\ndepth_m = {task.depth_m!r}\n"
        f"beta1_deg = {math.degrees(task.beta1_rad)!r}\n"
        f"beta2_deg = {math.degrees(task.beta2_rad)!r}\nstart_x_m = {task.start_x_m!r}\n"
    )
    report = run_scenario(Scenario(task=str(path))).report
    assert report.status == "done", report.fault
    assert report.overruns == 0
    carried = [d for d in report.digs if d.carried]
    assert carried and all(d.joined for d in carried)
    for axis in AXES:
        fig = report.tracking[axis]
        assert 0.0 < fig.max_mm <= 1.0, (axis, fig)
        assert 0.0 < fig.rms_mm <= 0.3, (axis, fig)
    assert report.tip_error_max_mm <= 3.0
    for dig in carried:
        assert dig.measured_volume_L == pytest.approx(dig.cut_volume_L, rel=0.02)


def test_lockstep_runs_are_deterministic(one_dig_run: HilRun, tmp_path: Path) -> None:
    again = run_scenario(Scenario(task="A", max_digs=1, start_at_entry=True, keep_frames=True))
    first, second = one_dig_run.frames, again.frames
    assert first is not None and len(first) > 10_000
    assert first == second
    assert again.report.tracking == one_dig_run.report.tracking
    # The report's JSON is JSON as it is: nothing to drop before it is written.
    assert json.loads(json.dumps(one_dig_run.to_json())) == one_dig_run.report.to_json()


def test_the_whole_run_commands_within_the_limits(one_dig_run: HilRun, rig: Rig) -> None:
    assert one_dig_run.frames is not None
    check = rpdo1_limit_check(rig, one_dig_run.frames)
    assert check.frames > 5000
    assert check.ok, check


# -- traces ------------------------------------------------------------------------------------


class IndependentDecoder:
    """Decodes every frame of this bus from the EDS (canopen) and the DBC (cantools) alone."""

    NMT_COMMANDS = frozenset({0x01, 0x02, 0x80, 0x81, 0x82})
    NMT_STATES = frozenset({0x00, 0x04, 0x05, 0x7F})

    def __init__(self, node_ids: tuple[int, ...], vcu_node_id: int) -> None:
        self.pdos: dict[int, tuple[str, list[ODVariable]]] = {}
        self.ods = {}
        for node in node_ids:
            od = import_od(str(CIA402_DRIVE_EDS), node)
            self.ods[node] = od
            for comm, mapping, name in (
                (0x1400, 0x1600, "RPDO1"),
                (0x1401, 0x1601, "RPDO2"),
                (0x1800, 0x1A00, "TPDO1"),
                (0x1801, 0x1A01, "TPDO2"),
            ):
                cob = int(od[comm][1].default) & 0x7FF
                count = int(od[mapping][0].default)
                variables = []
                for sub in range(1, count + 1):
                    value = int(od[mapping][sub].default)
                    index, subindex = value >> 16, (value >> 8) & 0xFF
                    obj = od[index]
                    variables.append(obj if isinstance(obj, ODVariable) else obj[subindex])
                self.pdos[cob] = (name, variables)
        self.db = cantools.database.load_file(str(VCU_DBC))
        self.vcu_shift = vcu_node_id - VCU_DBC_NODE_ID
        self.node_ids = node_ids
        self.counts: dict[str, int] = {}

    def decode(self, arbitration_id: int, data: bytes) -> dict[str, Any]:
        """The frame's meaning; raises AssertionError when it is not a valid frame of this bus."""
        kind, out = self._decode(arbitration_id, data)
        self.counts[kind] = self.counts.get(kind, 0) + 1
        return out

    def _decode(self, cid: int, data: bytes) -> tuple[str, dict[str, Any]]:
        node = cid & 0x7F
        function = cid & 0x780
        if cid == 0x000:
            assert len(data) == 2 and data[0] in self.NMT_COMMANDS
            assert data[1] in (0, *self.node_ids)
            return "NMT", {"command": data[0], "node": data[1]}
        if cid == 0x080:
            assert len(data) == 0
            return "SYNC", {}
        if cid in self.pdos:
            name, variables = self.pdos[cid]
            assert len(data) == sum(len(v) // 8 for v in variables), (hex(cid), data)
            values, offset = {}, 0
            for var in variables:
                size = len(var) // 8
                values[var.name] = var.decode_raw(data[offset : offset + size])
                offset += size
            return name, values
        try:
            message = self.db.get_message_by_frame_id(cid - self.vcu_shift)
        except KeyError:
            message = None
        if message is not None:
            return message.name, dict(message.decode(data, decode_choices=False))
        assert node in self.node_ids or cid == 0x77E, hex(cid)
        if function == 0x080:
            assert len(data) == 8
            code, register = struct.unpack_from("<HB", data)
            assert data[3:] == bytes(5)
            return "EMCY", {"code": code, "register": register}
        if function in (0x580, 0x600):
            assert len(data) == 8
            command = data[0] >> 5
            if function == 0x600:
                assert command in (0, 1, 2, 3), data  # download/upload initiate and segments
            else:
                assert command in (0, 1, 2, 3, 4), data  # responses and abort
            if command in (1, 2) or (function == 0x580 and command in (3, 4)):
                index, sub = struct.unpack_from("<HB", data, 1)
                obj = self.ods[node][index]
                assert isinstance(obj, ODVariable) or sub in obj, (hex(index), sub)
            return "SDO", {}
        if function == 0x700:
            assert len(data) == 1 and data[0] in self.NMT_STATES
            return "HEARTBEAT", {"state": data[0]}
        raise AssertionError(f"frame 0x{cid:03X} {data.hex()} is not a frame of this bus")


def _read_trace(path: Path) -> list[can.Message]:
    reader = can.BLFReader(str(path)) if path.suffix == ".blf" else can.ASCReader(str(path))
    return list(reader)


def test_asc_trace_reads_back_and_every_frame_decodes(one_dig_run: HilRun, rig: Rig) -> None:
    assert one_dig_run.report.trace is not None
    path = Path(one_dig_run.report.trace)
    messages = _read_trace(path)
    frames = one_dig_run.frames
    assert [(m.arbitration_id, bytes(m.data)) for m in messages] == frames
    decoder = IndependentDecoder(tuple(n for _, n in rig.can.node_ids), rig.can.vcu_node_id)
    decoded = [decoder.decode(m.arbitration_id, bytes(m.data)) for m in messages]
    for kind in ("NMT", "SYNC", "SDO", "RPDO1", "RPDO2", "TPDO1", "TPDO2", "HEARTBEAT"):
        assert decoder.counts.get(kind, 0) > 0, (kind, decoder.counts)
    assert decoder.counts.get("VCU_Status", 0) == decoder.counts["SYNC"]
    # TPDO1 positions are micrometres of stroke: inside the cylinder travel.
    travel_um = max(rig.cylinders.boom.stroke_max_m, rig.cylinders.stick.stroke_max_m) * 1e6
    positions = [d["Position actual value"] for d in decoded if "Position actual value" in d]
    assert positions and all(0 <= p <= travel_um for p in positions)


def test_blf_trace_of_a_fault_reads_back_and_decodes(
    rig: Rig, pending: Any, tmp_path: Path
) -> None:
    path = tmp_path / "fault.blf"
    run = run_on_lockstep(rig, pending, (FaultKind.FOLLOWING_ERROR, 1, 0.6), trace=path)
    frames, res = run.frames, run.result
    messages = _read_trace(path)
    assert [(m.arbitration_id, bytes(m.data)) for m in messages] == frames
    times = [m.timestamp for m in messages]
    assert times == sorted(times)
    decoder = IndependentDecoder(tuple(n for _, n in rig.can.node_ids), rig.can.vcu_node_id)
    emcys = [
        decoder.decode(m.arbitration_id, bytes(m.data))
        for m in messages
        if m.arbitration_id == 0x082
    ]
    assert {"code": 0x8611, "register": emcys[0]["register"]} in emcys
    for m in messages:
        decoder.decode(m.arbitration_id, bytes(m.data))
    assert res.status is ExecStatus.FAULT
    assert math.isfinite(float(np.nanmax(np.abs(res.telemetry["stroke_fb_m"]))))
