"""The CAN master, frame by frame: boot (NMT, every SDO download), 402 enable, the cycle
(RPDO1 + SYNC, TPDO feedback), faults, heartbeat loss; and boot against canopen's own slave
stack over python-can's virtual bus.

The expected exchanges are written from CiA 301/402: the SDO command bytes and the PDO
remapping procedure are built here by hand (``sdo_download``), not by the master's code.
"""

from __future__ import annotations

import contextlib
import itertools
import struct
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
from canopen.objectdictionary import import_od
from canopen.sdo.base import SdoVariable
from numpy.typing import NDArray

from rt_runtime.actuation import stroke_limits
from rt_runtime.canbus.cia402 import DriveState
from rt_runtime.canbus.config import (
    DEFAULT_EDS,
    MasterConfig,
    configuration_writes,
    interpolation_period,
)
from rt_runtime.canbus.emcy import EmcyCode
from rt_runtime.canbus.feedback import CycleStatus, WriteStatus
from rt_runtime.canbus.heartbeat import HeartbeatEventKind
from rt_runtime.canbus.master import CanMaster
from rt_runtime.canbus.scripted import RX, TX, ScriptClock, ScriptedBus, Step
from rt_runtime.canbus.sdo import SdoAbortedError
from rt_runtime.canbus.simtime import SimulatedTimeBus
from rt_runtime.errors import CommunicationError, ConfigurationError, DriveFault
from rt_runtime.rig import Rig, load_rig

NODES = (1, 2, 3)
POSITIONS_UM = (100_000, 200_000, 50_000)
SOD, RTSO, SO, OE, FAULT = 0x0250, 0x0231, 0x0233, 0x0237, 0x0218

Enabled = tuple[CanMaster, ScriptedBus, ScriptClock]


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("scale_model")


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def sdo_download(node: int, index: int, sub: int, fmt: str, value: int) -> list[Step]:
    """CiA 301 expedited download with size indicated, and the server's confirmation."""
    data = struct.pack(fmt, value)
    command = {4: 0x23, 3: 0x27, 2: 0x2B, 1: 0x2F}[len(data)]
    mux = struct.pack("<HB", index, sub)
    return [
        (TX, 0x600 + node, bytes([command]) + mux + data + bytes(4 - len(data))),
        (RX, 0x580 + node, bytes([0x60]) + mux + bytes(4)),
    ]


def sdo_upload(node: int, index: int, sub: int, data: bytes) -> list[Step]:
    """CiA 301 upload: expedited for up to 4 bytes, else segmented with 7-byte segments."""
    mux = struct.pack("<HB", index, sub)
    steps: list[Step] = [(TX, 0x600 + node, bytes([0x40]) + mux + bytes(4))]
    if len(data) <= 4:
        command = 0x43 | (4 - len(data)) << 2
        return [*steps, (RX, 0x580 + node, bytes([command]) + mux + data + bytes(4 - len(data)))]
    steps.append((RX, 0x580 + node, bytes([0x41]) + mux + struct.pack("<I", len(data))))
    chunks = [data[i : i + 7] for i in range(0, len(data), 7)]
    for i, chunk in enumerate(chunks):
        toggle = i % 2
        last = i == len(chunks) - 1
        steps.append((TX, 0x600 + node, bytes([0x60 | toggle << 4]) + bytes(7)))
        header = toggle << 4 | (7 - len(chunk)) << 1 | int(last)
        steps.append((RX, 0x580 + node, bytes([header]) + chunk + bytes(7 - len(chunk))))
    return steps


def expected_configuration(rig: Rig, axis: int) -> list[tuple[int, int, str, int]]:
    """(index, sub, struct format, value) of every download, from CiA 301/402 and the rig."""
    node = NODES[axis]
    drives = rig.drives
    _, hi_m = stroke_limits(rig)
    hb_ms = round(drives.heartbeat_period_s * 1000)
    timeout_ms = round(drives.heartbeat_timeout_s * 1000)
    writes = []
    # CiA 301 PDO mapping procedure: COB-ID invalid (bit 31), transmission type, count 0,
    # entries, count, COB-ID valid.
    for comm, mapping, cob, ttype, entries in (
        (0x1400, 0x1600, 0x200, 0x01, (0x607A0020, 0x60B10020)),
        (0x1401, 0x1601, 0x300, 0xFF, (0x60400010, 0x60600008)),
        (0x1800, 0x1A00, 0x180, 0x01, (0x60640020, 0x606C0020)),
        (0x1801, 0x1A01, 0x280, 0x00, (0x60410010, 0x60610008, 0x603F0010)),
    ):
        writes += [(comm, 1, "<I", 0x8000_0000 | cob + node), (comm, 2, "<B", ttype)]
        writes += [(mapping, 0, "<B", 0)]
        writes += [(mapping, i, "<I", e) for i, e in enumerate(entries, start=1)]
        writes += [(mapping, 0, "<B", len(entries)), (comm, 1, "<I", cob + node)]
    writes += [
        (0x1006, 0, "<I", 2000),  # 2 ms in us
        (0x60C2, 1, "<B", 2),  # 2 * 10^-3 s
        (0x60C2, 2, "<b", -3),
        (0x6065, 0, "<I", round(drives.following_error_window_m * 1e6)),
        (0x6066, 0, "<H", round(drives.following_error_timeout_s * 1e3)),
        (0x607D, 1, "<i", 0),
        (0x607D, 2, "<i", round(float(hi_m[axis]) * 1e6)),
        (0x6085, 0, "<I", round(drives.quick_stop_deceleration_m_s2 * 1e6)),
        (0x1017, 0, "<H", hb_ms),
        (0x1016, 1, "<I", 0x7E << 16 | timeout_ms),
        (0x6060, 0, "<b", 8),
    ]
    return writes


def boot_script(rig: Rig) -> list[Step]:
    steps: list[Step] = [(TX, 0x000, bytes([0x81, n])) for n in NODES]  # NMT reset node
    steps += [(RX, 0x700 + n, h("00")) for n in NODES]  # boot-up
    for axis, node in enumerate(NODES):
        steps += sdo_upload(node, 0x1000, 0, struct.pack("<I", 0x00020192))
        steps += sdo_upload(node, 0x6502, 0, struct.pack("<I", 0x80))
        steps += sdo_upload(node, 0x1008, 0, f"drive of axis {axis}".encode())
        for index, sub, fmt, value in expected_configuration(rig, axis):
            steps += sdo_download(node, index, sub, fmt, value)
    steps += [(TX, 0x000, bytes([0x01, n])) for n in NODES]  # NMT start
    steps += [(TX, 0x77E, h("05"))]  # the master's heartbeat
    steps += [(RX, 0x700 + n, h("05")) for n in NODES]
    return steps


def tpdos(
    statuswords: tuple[int, ...],
    positions: tuple[int, ...] = POSITIONS_UM,
    error: tuple[int, ...] = (0, 0, 0),
) -> list[Step]:
    steps: list[Step] = []
    for node, pos, word, err in zip(NODES, positions, statuswords, error, strict=True):
        steps.append((RX, 0x180 + node, struct.pack("<ii", pos, 0)))
        steps.append((RX, 0x280 + node, struct.pack("<HbH", word, 8, err)))
    return steps


def enable_step(controlwords: tuple[int | None, ...]) -> list[Step]:
    steps: list[Step] = [
        (TX, 0x200 + n, struct.pack("<ii", p, 0)) for n, p in zip(NODES, POSITIONS_UM, strict=True)
    ]
    steps += [
        (TX, 0x300 + n, struct.pack("<Hb", cw, 8))
        for n, cw in zip(NODES, controlwords, strict=True)
        if cw is not None
    ]
    return [*steps, (TX, 0x080, b"")]


def status_uploads(
    statuswords: tuple[int, ...], error: tuple[int, ...] = (0, 0, 0), mode: int = 8
) -> list[Step]:
    """The SDO uploads that start enable: per drive the objects TPDO2 maps, in its order."""
    steps: list[Step] = []
    for node, word, err in zip(NODES, statuswords, error, strict=True):
        steps += sdo_upload(node, 0x6041, 0, struct.pack("<H", word))
        steps += sdo_upload(node, 0x6061, 0, struct.pack("<b", mode))
        steps += sdo_upload(node, 0x603F, 0, struct.pack("<H", err))
    return steps


def enable_script() -> list[Step]:
    steps: list[Step] = [*status_uploads((SOD, SOD, SOD)), (TX, 0x080, b"")]
    steps += tpdos((SOD, SOD, SOD))
    for word, state in ((0x06, RTSO), (0x07, SO), (0x0F, OE)):
        steps += enable_step((word, word, word)) + tpdos((state, state, state))
    return steps


@pytest.fixture
def enabled(rig: Rig) -> Enabled:
    clock = ScriptClock()
    bus = ScriptedBus(boot_script(rig) + enable_script(), clock)
    master = CanMaster(bus, rig)
    master.boot(clock, timeout_s=0.5)
    master.enable(clock, timeout_s=0.5)
    bus.assert_done()
    return master, bus, clock


# ---------------------------------------------------------------- configuration


def test_interpolation_period() -> None:
    assert interpolation_period(0.002) == (2, -3)
    assert interpolation_period(0.001) == (1, -3)
    assert interpolation_period(0.00025) == (25, -5)
    assert interpolation_period(0.0005) == (5, -4)
    assert interpolation_period(1.0) == (1, 0)
    with pytest.raises(ConfigurationError, match="0x60C2"):
        interpolation_period(0.000257)
    with pytest.raises(ConfigurationError, match="microseconds"):
        interpolation_period(1.5e-7)


def test_configuration_writes_match_the_standard(rig: Rig) -> None:
    config = MasterConfig.from_rig(rig, 0x7E, 0.002)
    for axis, node in enumerate(NODES):
        od = import_od(str(DEFAULT_EDS), node)
        got = [(w.index, w.subindex, w.value) for w in configuration_writes(config, od, axis)]
        want = [(i, s, v) for i, s, _, v in expected_configuration(rig, axis)]
        assert got == want


def test_valve_drives_get_their_overlap_compensation_before_the_mode() -> None:
    """0x2100 goes to the three valve drives of a hydraulic rig (0.01 % of full opening), to
    no drive of an electric rig; Gao's loop and the ideal HIL are commissioned without it."""
    from hil_sim.harness.scenario import PathScenario, _master_rig, scenario_rig

    bench = load_rig("test_bench")
    config = MasterConfig.from_rig(bench, 0x7E, 0.002)
    assert config.valve_overlap_compensation == (1900, 1900, 1900)
    for axis, node in enumerate(config.node_ids):
        od = import_od(str(DEFAULT_EDS), node)
        got = [(w.index, w.subindex, w.value) for w in configuration_writes(config, od, axis)]
        assert got[-2:] == [(0x2100, 0, 1900), (0x6060, 0, 8)]
    scale = MasterConfig.from_rig(load_rig("scale_model"), 0x7E, 0.002)
    assert scale.valve_overlap_compensation == ()
    od = import_od(str(DEFAULT_EDS), 1)
    assert all(w.index != 0x2100 for w in configuration_writes(scale, od, 0))
    compensation = {
        (controller, imperfect): _master_rig(
            sc, scenario_rig(sc)
        ).drives.valve_overlap_compensation
        for controller in ("csp", "p")
        for imperfect in (True, False)
        for sc in [PathScenario(rig="test_bench", imperfect=imperfect, controller=controller)]
    }
    assert compensation == {
        ("csp", True): 0.19, ("csp", False): 0.0, ("p", True): 0.0, ("p", False): 0.0
    }


def test_master_refuses_a_bad_setup(rig: Rig, tmp_path: Path) -> None:
    bus = ScriptedBus()
    with pytest.raises(ConfigurationError, match="does not exist"):
        CanMaster(bus, rig, eds_path=tmp_path / "missing.eds")
    with pytest.raises(ConfigurationError, match="master node id"):
        CanMaster(bus, rig, master_node_id=2)
    bad = tmp_path / "bad.eds"
    bad.write_text(DEFAULT_EDS.read_text().replace("DefaultValue=0x60B10020", "DefaultValue=0"))
    with pytest.raises(ConfigurationError, match="RPDO1"):
        CanMaster(bus, rig, eds_path=bad)


# ---------------------------------------------------------------- boot and enable


def test_boot_and_enable_byte_exact(enabled: Enabled) -> None:
    master, bus, clock = enabled
    assert [i.device_name for i in master.drive_info] == [
        "drive of axis 0",
        "drive of axis 1",
        "drive of axis 2",
    ]
    fb = master.feedback
    assert list(fb.state) == [DriveState.OPERATION_ENABLED] * 3
    assert list(fb.position_um) == list(POSITIONS_UM)
    assert fb.sync_count == 4
    # Enable is paced one SYNC period per step (4 SYNCs).
    assert clock.now_s == pytest.approx(0.008)
    counts = {
        "SDO downloads": sum(1 for i, d in bus.sent if 0x601 <= i <= 0x603 and d[0] & 0xE0 == 0x20),
        "RPDO2": sum(1 for i, _ in bus.sent if 0x301 <= i <= 0x303),
    }
    # Per drive: 4 PDOs remapped (7 + 7 + 7 + 8 downloads) and 11 settings.
    assert counts == {"SDO downloads": 3 * 40, "RPDO2": 9}


def test_boot_reports_silent_nodes(rig: Rig) -> None:
    clock = ScriptClock()
    steps: list[Step] = [(TX, 0x000, bytes([0x81, n])) for n in NODES]
    steps += [(RX, 0x701, h("00")), (RX, 0x702, h("00"))]
    master = CanMaster(ScriptedBus(steps, clock), rig)
    with pytest.raises(CommunicationError, match=r"no boot-up message from nodes \[3\]"):
        master.boot(clock, timeout_s=0.25)
    assert clock.now_s == pytest.approx(0.25)


def test_boot_propagates_an_sdo_abort(rig: Rig) -> None:
    clock = ScriptClock()
    steps: list[Step] = [(TX, 0x000, bytes([0x81, n])) for n in NODES]
    steps += [(RX, 0x700 + n, h("00")) for n in NODES]
    steps += sdo_upload(1, 0x1000, 0, struct.pack("<I", 0x00020192))
    steps += sdo_upload(1, 0x6502, 0, struct.pack("<I", 0x80))
    steps += sdo_upload(1, 0x1008, 0, b"d1")
    steps += [
        (TX, 0x601, h("23 00 14 01 01 02 00 80")),
        (RX, 0x581, h("80 00 14 01 02 00 01 06")),  # 0x06010002: read only
    ]
    master = CanMaster(ScriptedBus(steps, clock), rig)
    with pytest.raises(SdoAbortedError, match=r"0x1400 sub 1.*read only"):
        master.boot(clock, timeout_s=0.25)


def test_boot_refuses_a_drive_without_csp(rig: Rig) -> None:
    clock = ScriptClock()
    steps: list[Step] = [(TX, 0x000, bytes([0x81, n])) for n in NODES]
    steps += [(RX, 0x700 + n, h("00")) for n in NODES]
    steps += sdo_upload(1, 0x1000, 0, struct.pack("<I", 0x00020192))
    steps += sdo_upload(1, 0x6502, 0, struct.pack("<I", 0x01))  # profile position only
    master = CanMaster(ScriptedBus(steps, clock), rig)
    with pytest.raises(DriveFault, match=r"boom drive.*cyclic synchronous position"):
        master.boot(clock, timeout_s=0.25)


def test_enable_resets_a_fault_with_an_edge_and_reports_a_persistent_one(rig: Rig) -> None:
    clock = ScriptClock()
    steps = [*boot_script(rig), *status_uploads((SOD, FAULT, SOD), error=(0, 0x8611, 0))]
    steps += [(TX, 0x080, b""), *tpdos((SOD, FAULT, SOD), error=(0, 0x8611, 0))]
    steps += [(RX, 0x082, h("11 86 80 00 00 00 00 00"))]  # the stick's EMCY
    steps += enable_step((0x06, 0x80, 0x06)) + tpdos((RTSO, FAULT, RTSO))
    steps += enable_step((0x07, 0x00, 0x07)) + tpdos((SO, FAULT, SO))
    bus = ScriptedBus(steps, clock)
    master = CanMaster(bus, rig)
    master.boot(clock, timeout_s=0.5)
    with pytest.raises(DriveFault, match=r"stick \(node 2\): FAULT .*FOLLOWING_ERROR"):
        master.enable(clock, timeout_s=0.005)
    bus.assert_done()


def test_enable_names_a_drive_that_does_not_report_its_status(rig: Rig) -> None:
    clock = ScriptClock()
    steps = [*boot_script(rig), (TX, 0x601, h("40 41 60 00 00 00 00 00"))]
    steps += [(TX, 0x601, h("80 41 60 00 00 00 04 05"))]  # the client's abort: timed out
    bus = ScriptedBus(steps, clock)
    master = CanMaster(bus, rig, sdo_timeout_s=0.1)
    master.boot(clock, timeout_s=0.5)
    with pytest.raises(CommunicationError, match=r"status of the boom drive \(node 1\)"):
        master.enable(clock, timeout_s=1.0)
    bus.assert_done()
    assert clock.now_s == pytest.approx(0.1)


def test_enable_needs_boot(rig: Rig) -> None:
    with pytest.raises(CommunicationError, match="boot"):
        CanMaster(ScriptedBus(), rig).enable(ScriptClock(), 0.1)


# ---------------------------------------------------------------- the cycle


def setpoint_frames(
    stroke: Sequence[int] | NDArray[np.int32], velocity: Sequence[int] | NDArray[np.int32]
) -> list[Step]:
    steps: list[Step] = [
        (TX, 0x200 + n, struct.pack("<ii", s, v))
        for n, s, v in zip(NODES, stroke, velocity, strict=True)
    ]
    return [*steps, (TX, 0x080, b"")]


def test_cycle_byte_exact(enabled: Enabled) -> None:
    master, bus, clock = enabled
    stroke = np.array([100_010, 199_990, 50_000], np.int32)
    velocity = np.array([5_000, -5_000, 0], np.int32)
    bus.extend(setpoint_frames(stroke, velocity))
    bus.extend(tpdos((OE, OE, OE), positions=(100_005, 199_995, 50_000)))
    assert master.write_setpoints(stroke, velocity) is WriteStatus.OK
    fb = master.read_feedback(clock(), timeout_s=0.001)
    bus.assert_done()
    assert fb.status is CycleStatus.OK
    assert list(fb.position_um) == [100_005, 199_995, 50_000]
    assert list(fb.tpdo1_sync) == list(fb.tpdo2_sync) == [5, 5, 5] and fb.sync_count == 5
    assert not fb.stale.any() and not fb.reacted
    # Literal bytes of the first RPDO1: 100010 = 0x000186AA, 5000 = 0x00001388.
    assert list(master.last_target_um()) == [100_010, 199_990, 50_000]
    assert bus.sent[-4] == (0x201, h("aa 86 01 00 88 13 00 00"))
    assert bus.sent[-1] == (0x080, b"")
    snapshot = fb.copy()
    assert snapshot.position_um is not fb.position_um
    assert list(snapshot.position_um) == list(fb.position_um)


def test_a_bus_with_send_many_gets_the_cycle_in_one_call(enabled: Enabled) -> None:
    """The optional capability: RPDO1s and SYNC in one ``send_many``, the same bytes in the same
    order as one ``send`` each, one send stamp for all; a refused batch is a status."""
    enabled_master, bus, _ = enabled
    batches: list[list[can.Message]] = []
    refuse = False

    def send_many(msgs: Sequence[can.Message]) -> None:
        if refuse:
            raise can.CanOperationError("transmit buffer full")
        batches.append(list(msgs))
        for msg in msgs:
            bus.send(msg)

    bus.send_many = send_many  # type: ignore[attr-defined]
    master = CanMaster(bus, enabled_master.rig)  # the capability is looked up at construction
    stroke, velocity = [100_010, 199_990, 50_000], [5_000, -5_000, 0]
    bus.extend(setpoint_frames(stroke, velocity))
    before = time.time()
    assert master.write_setpoints(stroke, velocity) is WriteStatus.OK
    bus.assert_done()
    assert [len(b) for b in batches] == [4]
    assert [m.arbitration_id for m in batches[0]] == [*(0x200 + n for n in NODES), 0x080]
    assert len({m.timestamp for m in batches[0]}) == 1 and batches[0][0].timestamp >= before
    assert master.feedback.sync_count == 1
    refuse = True
    assert master.write_setpoints(stroke, velocity) is WriteStatus.BUS_ERROR
    assert master.feedback.sync_count == 1


def test_tpdo2_is_not_awaited_and_a_change_is_taken_when_it_comes(enabled: Enabled) -> None:
    """TPDO2 is synchronous acyclic (sent on change): a cycle with only TPDO1s is complete,
    the last statusword holds, and a TPDO2 that does come (a fault) is decoded at once."""
    master, bus, clock = enabled
    tpdo1_only = [step for step in tpdos((OE, OE, OE)) if step[1] < 0x280]
    bus.extend(setpoint_frames(POSITIONS_UM, (0, 0, 0)) + tpdo1_only)
    assert master.write_setpoints(list(POSITIONS_UM), [0, 0, 0]) is WriteStatus.OK
    start_s = clock()
    fb = master.read_feedback(clock(), timeout_s=0.0005)
    assert clock() == start_s  # nothing was waited for
    assert fb.status is CycleStatus.OK and not fb.stale.any()
    assert [fb.drive_state(a) for a in range(3)] == [DriveState.OPERATION_ENABLED] * 3
    bus.extend(setpoint_frames(POSITIONS_UM, (0, 0, 0)) + tpdo1_only)
    bus.extend([(RX, 0x282, struct.pack("<HbH", FAULT, 8, 0x8611))])
    bus.extend([(TX, 0x300 + n, h("02 00 08")) for n in NODES])  # the master's quick stop
    master.write_setpoints(list(POSITIONS_UM), [0, 0, 0])
    fb = master.read_feedback(clock(), timeout_s=0.0005)
    bus.assert_done()
    assert fb.status is CycleStatus.DRIVE_FAULT and fb.drive_state(1) is DriveState.FAULT


def test_missing_tpdo_is_stale_not_an_exception(enabled: Enabled) -> None:
    master, bus, clock = enabled
    bus.extend(setpoint_frames(POSITIONS_UM, (0, 0, 0)))
    bus.extend(tpdos((OE, OE, OE))[:4])  # the bucket does not answer
    assert master.write_setpoints(list(POSITIONS_UM), [0, 0, 0]) is WriteStatus.OK
    start_s = clock()
    fb = master.read_feedback(clock(), timeout_s=0.0005)
    assert fb.status is CycleStatus.STALE
    assert list(fb.stale) == [False, False, True]
    assert clock() - start_s == pytest.approx(0.0005)  # one bounded wait
    bus.assert_done()


def test_other_frames_reach_the_listener(rig: Rig) -> None:
    clock = ScriptClock()
    seen: list[tuple[int, bytes, float]] = []
    bus = ScriptedBus(boot_script(rig) + enable_script(), clock)
    master = CanMaster(
        bus, rig, on_other_frame=lambda m, t: seen.append((m.arbitration_id, bytes(m.data), t))
    )
    master.boot(clock, timeout_s=0.5)
    master.enable(clock, timeout_s=0.5)
    bus.extend([(RX, 0x190, h("01 02 03 04 05 06 07 08")), (RX, 0x704, h("05"))])
    master.read_feedback(0.01, timeout_s=0.0)
    # The VCU's status and a foreign node's heartbeat are not the master's: passed on.
    assert seen == [(0x190, h("01 02 03 04 05 06 07 08"), 0.01), (0x704, h("05"), 0.01)]


def test_out_of_range_setpoint_sends_nothing(enabled: Enabled) -> None:
    master, bus, _ = enabled
    before = len(bus.sent)
    assert master.write_setpoints([2**31, 0, 0], [0, 0, 0]) is WriteStatus.OUT_OF_RANGE
    assert master.write_setpoints([0, 0], [0, 0]) is WriteStatus.OUT_OF_RANGE
    assert len(bus.sent) == before


def test_following_error_fault_stops_every_axis(enabled: Enabled) -> None:
    master, bus, clock = enabled
    bus.extend(setpoint_frames(POSITIONS_UM, (0, 0, 0)))
    bus.extend(tpdos((OE, FAULT, OE), error=(0, 0x8611, 0)))
    bus.extend([(RX, 0x082, h("11 86 80 00 00 00 00 00"))])
    # The master's reaction: quick stop (controlword 0x0002, mode 8) to every drive.
    bus.extend([(TX, 0x300 + n, h("02 00 08")) for n in NODES])
    master.write_setpoints(list(POSITIONS_UM), [0, 0, 0])
    fb = master.read_feedback(clock(), timeout_s=0.001)
    bus.assert_done()
    assert fb.status is CycleStatus.DRIVE_FAULT and fb.reacted
    assert fb.drive_state(1) is DriveState.FAULT and fb.error_code[1] == 0x8611
    assert [(e.node_id, e.code) for e in fb.emcys] == [(2, EmcyCode.FOLLOWING_ERROR)]
    # Reported again next cycle, but the reaction is sent once.
    bus.extend(setpoint_frames(POSITIONS_UM, (0, 0, 0)))
    bus.extend(tpdos((0x0217, FAULT, 0x0217), error=(0, 0x8611, 0)))
    master.write_setpoints(list(POSITIONS_UM), [0, 0, 0])
    fb = master.read_feedback(clock(), timeout_s=0.001)
    bus.assert_done()
    assert fb.status is CycleStatus.DRIVE_FAULT and not fb.reacted and fb.emcys == []
    assert fb.drive_state(0) is DriveState.QUICK_STOP_ACTIVE


def test_heartbeat_loss_stops_every_axis(enabled: Enabled) -> None:
    master, bus, clock = enabled
    # Every drive was last heard at t = 0 (boot); the profile's timeout is 150 ms.
    assert master.config.heartbeat_timeout_s == pytest.approx(0.15)
    times = [0.06, 0.11, 0.16, 0.21, 0.26]
    statuses = []
    for now_s in times:
        clock.now_s = now_s
        bus.extend([(TX, 0x77E, h("05"))])  # the master's own heartbeat (every 50 ms)
        assert master.heartbeat(now_s) is WriteStatus.OK
        bus.extend([(RX, 0x701, h("05")), (RX, 0x702, h("05"))])  # the bucket is silent
        if now_s == 0.16:
            bus.extend([(TX, 0x300 + n, h("02 00 08")) for n in NODES])  # reaction, once
        fb = master.read_feedback(now_s, timeout_s=0.0)
        bus.assert_done()
        statuses.append(fb.status)
        assert fb.reacted is (now_s == 0.16)
        if fb.reacted:
            assert [(e.node_id, e.kind) for e in fb.heartbeat_events] == [
                (3, HeartbeatEventKind.TIMEOUT)
            ]
        assert list(fb.heartbeat_lost) == [False, False, now_s > 0.15]
    # No SYNC was sent, so nothing is stale: all is well until the bucket's timeout.
    ok, lost = CycleStatus.OK, CycleStatus.HEARTBEAT_LOST
    assert statuses == [ok, ok, lost, lost, lost]


def test_quick_stop_disable_and_bus_load(enabled: Enabled) -> None:
    master, bus, _ = enabled
    bus.extend([(TX, 0x300 + n, h("02 00 08")) for n in NODES])
    bus.extend([(TX, 0x300 + n, h("00 00 08")) for n in NODES])
    assert master.quick_stop() is WriteStatus.OK
    assert master.disable() is WriteStatus.OK
    bus.assert_done()
    # No TPDO2; 865 (713 nominal) bits of drive frames, 135 (111) of the VCU's status.
    load = master.bus_load()
    assert master.rig.can.vcu
    assert load.worst_case == pytest.approx((865 + 135 + 4 * 65 * 0.002 / 0.05) / 2000)
    assert load.nominal == pytest.approx((713 + 111 + 4 * 55 * 0.002 / 0.05) / 2000)
    assert master.bus_load(vcu=False).nominal == pytest.approx((713 + 4 * 55 * 0.002 / 0.05) / 2000)
    assert master.bus_load(0.001).worst_case > load.worst_case


def test_bus_error_is_a_status(enabled: Enabled) -> None:
    master, bus, _ = enabled

    def refuse(msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("transmit buffer full")

    bus.send = refuse  # type: ignore[method-assign]
    assert master.write_setpoints(list(POSITIONS_UM), [0, 0, 0]) is WriteStatus.BUS_ERROR
    assert master.quick_stop() is WriteStatus.BUS_ERROR
    assert master.heartbeat(10.0) is WriteStatus.BUS_ERROR


# ---------------------------------------------------------------- interoperability


@contextlib.contextmanager
def canopen_slaves() -> Iterator[tuple[canopen.Network, can.BusABC, dict[int, canopen.LocalNode]]]:
    """canopen's LocalNode (SDO server, NMT slave, heartbeat producer) as the drives, on a
    virtual bus; yields the network, the master's end of the bus and the nodes by node id."""
    channel = f"canbus-interop-{time.monotonic_ns()}"
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        slaves = {}
        for node in NODES:
            slave = canopen.LocalNode(node, import_od(str(DEFAULT_EDS), node))
            network.add_node(slave)
            slaves[node] = slave

        def on_nmt(can_id: int, data: bytearray, timestamp: float) -> None:
            # canopen's NmtSlave sends no boot-up on a received reset; a drive does.
            if data[0] == 0x81 and data[1] in slaves:
                slaves[data[1]].nmt.send_command(0x81)
                slaves[data[1]].nmt.send_command(0x80)

        network.subscribe(0, on_nmt)
        yield network, bus, slaves
    finally:
        network.disconnect()
        bus.shutdown()


def test_boot_against_canopen_slaves_on_a_virtual_bus(rig: Rig) -> None:
    with canopen_slaves() as (_, bus, slaves):
        master = CanMaster(bus, rig)
        info = master.boot(time.monotonic, timeout_s=2.0)
        assert [i.device_type for i in info] == [0x00020192] * 3
        assert info[0].device_name == "excavator-rt CiA 402 cylinder drive model"
        for axis, slave in enumerate(slaves.values()):
            assert slave.nmt.state == "OPERATIONAL"
            final = {(i, sub): v for i, sub, _, v in expected_configuration(rig, axis)}
            for (index, sub), value in final.items():
                obj = slave.sdo[index]
                got = obj.raw if isinstance(obj, SdoVariable) else obj[sub].raw
                assert got == value, (slave.id, hex(index), sub)


# CiA 402 device control, written from the standard for the canopen-built drives below:
# (statusword, command pattern) -> statusword; the command is the controlword masked with 0x8F.
_DEVICE_CONTROL = {
    (SOD, 0x06): RTSO,
    (RTSO, 0x07): SO,
    (RTSO, 0x0F): SO,  # switch on (3); enable operation (4) needs a second controlword
    (SO, 0x0F): OE,
    (SO, 0x06): RTSO,
    (OE, 0x07): SO,
    (OE, 0x06): RTSO,
}


@pytest.mark.parametrize("tpdo2", ["on_change", "never"])
def test_enable_against_canopen_slaves(rig: Rig, tpdo2: str) -> None:
    """canopen's LocalNode as a CiA 402 drive: controlword from RPDO2, statusword 0x6041 in its
    object dictionary (served by canopen's SDO server), TPDO1 on every SYNC, and TPDO2 either
    sent at a SYNC when the statusword changed since NMT start (type 0) or never. The master
    reaches OPERATION_ENABLED on every drive either way."""
    with canopen_slaves() as (network, bus, slaves):
        sent_status = {node: SOD for node in NODES}
        tpdo2_sent: list[int] = []
        for node, slave in slaves.items():
            slave.sdo[0x6041].raw = SOD

            def on_rpdo2(can_id: int, data: bytearray, timestamp: float) -> None:
                slave = slaves[can_id - 0x300]
                controlword = struct.unpack_from("<H", data)[0]
                word = slave.sdo[0x6041].raw
                slave.sdo[0x6041].raw = _DEVICE_CONTROL.get((word, controlword & 0x8F), word)

            network.subscribe(0x300 + node, on_rpdo2)

        def on_sync(can_id: int, data: bytearray, timestamp: float) -> None:
            for node, slave in slaves.items():
                if slave.nmt.state != "OPERATIONAL":
                    continue
                network.send_message(0x180 + node, struct.pack("<ii", POSITIONS_UM[node - 1], 0))
                word = slave.sdo[0x6041].raw
                if tpdo2 == "on_change" and word != sent_status[node]:
                    network.send_message(0x280 + node, struct.pack("<HbH", word, 8, 0))
                    sent_status[node] = word
                    tpdo2_sent.append(node)

        network.subscribe(0x080, on_sync)
        master = CanMaster(bus, rig)
        master.boot(time.monotonic, timeout_s=2.0)
        master.enable(time.monotonic, timeout_s=2.0)
        assert [master.feedback.drive_state(a) for a in range(3)] == [
            DriveState.OPERATION_ENABLED
        ] * 3
        assert [slave.sdo[0x6041].raw for slave in slaves.values()] == [OE] * 3
        assert list(master.feedback.position_um) == list(POSITIONS_UM)
        assert len(tpdo2_sent) == (9 if tpdo2 == "on_change" else 0)


class _FirmwareBus(SimulatedTimeBus):
    """Helper B's drive firmware models on an in-process bus, with a stand-in plant.

    Lockstep: a SYNC advances simulated time by one period in servo sub-steps; an empty
    ``recv(timeout)`` advances it by ``timeout``. Each axis is a 500 kg mass pushed by
    effort * force_max_n with viscous damping (no gravity): enough to close the drives' loops.
    """

    def __init__(self, rig: Rig, clock: ScriptClock, start_m: list[float]) -> None:
        from firmware_models.drive import DriveFirmware

        self.clock = clock
        self.force_n = rig.actuators.force_max_n
        self.fw = [
            DriveFirmware(node, rig, axis, initial_position_m=x)
            for node, axis, x in zip(NODES, ("boom", "stick", "bucket"), start_m, strict=True)
        ]
        self.sub_s = self.fw[0].params.servo_period_s
        self.pos_m, self.vel_m_s = list(start_m), [0.0, 0.0, 0.0]
        self.queue: list[tuple[int, bytes]] = []
        self.sent: list[tuple[int, bytes]] = []
        self.channel_info = "firmware"
        super().__init__(channel="firmware")

    def _advance(self, dt_s: float) -> None:
        for _ in range(max(1, round(dt_s / self.sub_s))):
            for i, fw in enumerate(self.fw):
                u = fw.servo_step(self.sub_s, self.pos_m[i], self.vel_m_s[i])
                accel = (u * self.force_n - 5000.0 * self.vel_m_s[i]) / 500.0
                self.vel_m_s[i] += accel * self.sub_s
                self.pos_m[i] += self.vel_m_s[i] * self.sub_s
            self.clock.advance(self.sub_s)
            for fw in self.fw:
                self.queue += fw.pending_frames(self.clock())

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((msg.arbitration_id, bytes(msg.data)))
        if msg.arbitration_id == 0x080:
            self._advance(0.002)
        for fw in self.fw:
            self.queue += fw.on_frame(msg.arbitration_id, bytes(msg.data), self.clock())

    def now_s(self) -> float:
        return self.clock()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self.queue and timeout:
            self._advance(timeout)
        if not self.queue:
            return None, False
        can_id, data = self.queue.pop(0)
        return can.Message(arbitration_id=can_id, data=data, is_extended_id=False), False


def test_against_the_drive_firmware_model(rig: Rig, request: pytest.FixtureRequest) -> None:
    """Boot, enable, a ramp, then a following-error fault on the stick stops every axis."""
    clock = ScriptClock()
    _, hi_m = stroke_limits(rig)
    start_m = [float(x) / 2 for x in hi_m]
    bus = _FirmwareBus(rig, clock, start_m)
    request.addfinalizer(bus.shutdown)
    master = CanMaster(bus, rig)
    master.boot(clock, timeout_s=1.0)
    master.enable(clock, timeout_s=1.0)
    start_um = master.feedback.position_um.copy()
    assert np.abs(start_um - np.array(start_m) * 1e6).max() <= 1
    # 0.5 s ramp of the boom at 10 mm/s with velocity feed-forward.
    target = start_um.astype(np.int64)
    velocity = np.array([10_000, 0, 0], np.int32)
    for _ in range(250):
        fb = master.read_feedback(clock(), timeout_s=0.0)
        assert fb.status is CycleStatus.OK, fb.status
        master.heartbeat(clock())
        target[0] += 20  # um per 2 ms
        assert master.write_setpoints(target.astype(np.int32), velocity) is WriteStatus.OK
    fb = master.read_feedback(clock(), timeout_s=0.0)
    moved_um = fb.position_um - start_um
    assert 4_500 <= moved_um[0] <= 5_100 and abs(moved_um[1]) < 50 and abs(moved_um[2]) < 50
    # A following error on the stick: EMCY, FAULT, and quick stop to every drive, once.
    bus.fw[1].inject_fault(0x8611)
    statuses, reactions = [], 0
    for _ in range(300):
        master.heartbeat(clock())
        master.write_setpoints(target.astype(np.int32), np.zeros(3, np.int32))
        fb = master.read_feedback(clock(), timeout_s=0.0)
        statuses.append(fb.status)
        reactions += fb.reacted
    assert statuses[0] >= CycleStatus.EMCY and reactions == 1
    assert [(i, d) for i, d in bus.sent if i in (0x301, 0x302, 0x303)][-3:] == [
        (0x300 + n, h("02 00 08")) for n in NODES
    ]
    assert fb.drive_state(1) is DriveState.FAULT
    assert fb.drive_state(0) is fb.drive_state(2) is DriveState.SWITCH_ON_DISABLED
    assert abs(int(fb.velocity_um_s[0])) < 100


def test_a_drive_that_sends_its_tpdo2_only_on_change_is_enabled(rig: Rig) -> None:
    """Lockstep HIL, every drive's TPDO2 sent only when its content changes and not after NMT
    start (CiA 301 type 0 requires nothing then): enable learns the states by SDO and reaches
    OPERATION_ENABLED on every axis."""
    from hil_sim.harness.lockstep import LockstepHil

    with LockstepHil(
        rig, np.radians([30.0, -90.0, -60.0]), keep_frames=True, tpdo_at_start=False
    ) as hil:
        master = CanMaster(hil.master_bus, rig, period_s=0.002)
        master.boot(hil.clock.now, 1.0)
        master.enable(hil.clock.now, 1.0)
        frames = list(hil.core.frames)
        assert [master.feedback.drive_state(a) for a in range(3)] == [
            DriveState.OPERATION_ENABLED
        ] * 3
        assert master.feedback.sync_count == 4  # no re-read needed: each step got its TPDO2
    ids = [i for i, _ in frames]
    started = max(k for k, (i, d) in enumerate(frames) if i == 0x000 and d[0] == 0x01)
    first_rpdo2 = min(k for k, i in enumerate(ids) if 0x301 <= i <= 0x303)
    # The SYNCs before the first controlword got TPDO1s and no TPDO2.
    assert 0x080 in ids[started:first_rpdo2]
    assert not [i for i in ids[started:first_rpdo2] if 0x281 <= i <= 0x283]
    # Each controlword step changed the statusword, so each step got its TPDO2 (3 per drive).
    assert [ids.count(0x280 + n) for n in NODES] == [3, 3, 3]


@pytest.mark.parametrize("vcu", [True, False])
def test_bus_load_counts_every_frame_of_a_lockstep_trace(rig: Rig, vcu: bool) -> None:
    """The report's frames per period against the frames of the lockstep bus while the loop
    holds the arm, with and without the VCU (the rig has one): the same frames in every SYNC
    period (heartbeats aside), and the same load over the whole run."""
    from hil_sim.harness.lockstep import LockstepHil
    from rt_runtime.canbus.busload import frame_bits_nominal

    with LockstepHil(rig, np.radians([30.0, -90.0, -60.0]), keep_frames=True, vcu=vcu) as hil:
        master = CanMaster(hil.master_bus, rig, period_s=0.002)
        master.boot(hil.clock.now, 1.0)
        master.enable(hil.clock.now, 1.0)
        hold = master.feedback.position_um.copy()
        first = len(hil.core.frames)
        start_s = hil.clock.now()
        cycles = 500  # 1 s: 20 heartbeat periods of every node
        for k in range(cycles):
            master.heartbeat(hil.clock.now())
            master.write_setpoints(hold, np.zeros(3, np.int32))
            assert master.read_feedback(hil.clock.now(), 0.001).status is CycleStatus.OK
            hil.clock.sleep_until(start_s + (k + 1) * 0.002)
        frames = list(hil.core.frames[first:])
    assert rig.can.vcu
    load = master.bus_load() if vcu else master.bus_load(vcu=False)
    # Per period the report lists whole frames (payload bytes, n per period) and heartbeats
    # as a fraction; the trace's periods run from one SYNC to the next.
    whole = [(size, int(count)) for size, count in master.cycle_frames(vcu=vcu) if count >= 1.0]
    report = sorted(size for size, count in whole for _ in range(count))
    syncs = [k for k, (i, _) in enumerate(frames) if i == 0x080]
    assert len(syncs) == cycles
    for a, b in itertools.pairwise(syncs):
        period = [len(d) for i, d in frames[a:b] if not 0x700 <= i <= 0x77F]
        assert sorted(period) == report
    # Over the run, heartbeats included: the trace's load is the report's.
    bits = sum(frame_bits_nominal(len(d)) for _, d in frames)
    assert bits / (cycles * 0.002) / rig.can.bitrate == pytest.approx(load.nominal, rel=0.005)
