"""Byte-exact CiA 301 protocol tests: PDO codecs and the EDS, SYNC, NMT, heartbeat, EMCY, SDO,
frame lengths and bus load.

Expected bytes are written out by hand from CiA 301 (and DESIGN.md's mapping), not produced by
the code under test.
"""

from __future__ import annotations

import random
import shutil
from pathlib import Path

import can
import pytest
from canopen.objectdictionary import import_od

from rt_runtime.canbus.busload import (
    bus_load,
    bus_load_report,
    cia402_cycle_frames,
    crc15,
    frame_bits_exact,
    frame_bits_nominal,
    frame_bits_worst,
)
from rt_runtime.canbus.config import DEFAULT_EDS
from rt_runtime.canbus.emcy import EmcyCode, emcy_message, parse_emcy
from rt_runtime.canbus.heartbeat import (
    HeartbeatConsumer,
    HeartbeatEvent,
    HeartbeatEventKind,
    HeartbeatProducer,
    heartbeat_message,
    parse_heartbeat,
)
from rt_runtime.canbus.nmt import NmtCommand, NmtState, nmt_message, parse_nmt
from rt_runtime.canbus.pdo import (
    RPDO1,
    RPDO2,
    TPDO1,
    TPDO2,
    check_pdo_mapping,
    function_code,
    node_of,
    pdo_message,
    sync_message,
)
from rt_runtime.canbus.scripted import RX, TX, ScriptClock, ScriptedBus, ScriptMismatch
from rt_runtime.canbus.sdo import (
    SdoAbortedError,
    SdoClient,
    SdoProtocolError,
    SdoTimeoutError,
    download_command,
)
from rt_runtime.errors import CommunicationError, ConfigurationError


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# ---------------------------------------------------------------- PDOs and the EDS


def test_pdo_payloads_byte_exact() -> None:
    msg = pdo_message(RPDO1, 2)
    RPDO1.codec.pack_into(msg.data, 0, 123_456, -7_890)
    assert msg.arbitration_id == 0x202
    assert bytes(msg.data) == h("40 e2 01 00 2e e1 ff ff")
    msg = pdo_message(RPDO2, 3)
    RPDO2.codec.pack_into(msg.data, 0, 0x000F, 8)
    assert (msg.arbitration_id, bytes(msg.data)) == (0x303, h("0f 00 08"))
    assert TPDO1.codec.unpack(h("a0 86 01 00 18 fc ff ff")) == (100_000, -1_000)
    assert TPDO2.codec.unpack(h("37 02 08 11 86")) == (0x0237, 8, 0x8611)
    assert (TPDO1.cob_id(1), TPDO2.cob_id(1), RPDO1.cob_id(3), RPDO2.cob_id(1)) == (
        0x181,
        0x281,
        0x203,
        0x301,
    )
    assert (RPDO1.size, RPDO2.size, TPDO1.size, TPDO2.size) == (8, 3, 8, 5)


def test_pack_into_reuses_the_buffer() -> None:
    msg = pdo_message(RPDO1, 1)
    buffer = msg.data
    for value in (1, -1, 2**31 - 1, -(2**31)):
        RPDO1.codec.pack_into(msg.data, 0, value, value)
        assert msg.data is buffer
    assert bytes(msg.data) == h("00 00 00 80 00 00 00 80")


def test_cob_helpers_and_sync() -> None:
    assert function_code(0x283) == 0x280 and node_of(0x283) == 3
    assert function_code(0x77E) == 0x700 and node_of(0x77E) == 0x7E
    sync = sync_message()
    assert (sync.arbitration_id, bytes(sync.data), sync.dlc, sync.is_extended_id) == (
        0x080,
        b"",
        0,
        False,
    )


@pytest.mark.parametrize("node", [1, 2, 3, 127])
def test_eds_mapping_matches_codecs(node: int) -> None:
    od = import_od(str(DEFAULT_EDS), node)
    check_pdo_mapping(od, node)
    assert od[0x1600][1].default == 0x607A0020
    assert od[0x1A01][0].default == 3


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("DefaultValue=0x60B10020", "DefaultValue=0x60B10010", "RPDO1"),
        (
            "DefaultValue=0x03\nPDOMapping=0\n\n[1A01sub1]",
            "DefaultValue=0x02\nPDOMapping=0\n\n[1A01sub1]",
            "TPDO2",
        ),
        ("DefaultValue=$NODEID+0x180", "DefaultValue=$NODEID+0x190", "TPDO1"),
        (
            "[6064]\nParameterName=Position actual value\nObjectType=0x7\nDataType=0x0004",
            "[6064]\nParameterName=Position actual value\nObjectType=0x7\nDataType=0x0007",
            "TPDO1",
        ),
        ("DefaultValue=0xFF", "DefaultValue=0x01", "RPDO2"),
    ],
)
def test_changed_eds_fails_loudly(tmp_path: Path, old: str, new: str, message: str) -> None:
    text = DEFAULT_EDS.read_text()
    assert old in text
    path = tmp_path / "drive.eds"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ConfigurationError, match=message):
        check_pdo_mapping(import_od(str(path), 1), 1)


def test_unchanged_copy_passes(tmp_path: Path) -> None:
    path = tmp_path / "copy.eds"
    shutil.copy(DEFAULT_EDS, path)
    check_pdo_mapping(import_od(str(path), 5), 5)


# ---------------------------------------------------------------- NMT, heartbeat, EMCY


def test_nmt_frames() -> None:
    cases = [
        (NmtCommand.START, 1, "01 01"),
        (NmtCommand.STOP, 2, "02 02"),
        (NmtCommand.ENTER_PRE_OPERATIONAL, 3, "80 03"),
        (NmtCommand.RESET_NODE, 1, "81 01"),
        (NmtCommand.RESET_COMMUNICATION, 0, "82 00"),
    ]
    for command, node, data in cases:
        msg = nmt_message(command, node)
        assert (msg.arbitration_id, bytes(msg.data)) == (0x000, h(data))
        assert parse_nmt(msg.data) == (command, node)
    assert parse_nmt(h("99 01")) is None
    with pytest.raises(ValueError, match=r"0\.\.127"):
        nmt_message(NmtCommand.START, 128)


def test_heartbeat_frames() -> None:
    msg = heartbeat_message(0x7E, NmtState.OPERATIONAL)
    assert (msg.arbitration_id, bytes(msg.data)) == (0x77E, h("05"))
    assert parse_heartbeat(h("00")) is NmtState.BOOT_UP
    assert parse_heartbeat(h("7f")) is NmtState.PRE_OPERATIONAL
    assert parse_heartbeat(h("84")) is NmtState.STOPPED  # toggle bit ignored
    assert parse_heartbeat(h("05 00")) is None
    assert parse_heartbeat(h("33")) is None


def test_heartbeat_producer_grid() -> None:
    producer = HeartbeatProducer(0x7E, 0.05)
    times = [0.0, 0.01, 0.049, 0.05, 0.07, 0.1, 0.26, 0.30, 0.31]
    due = [t for t in times if producer.due(t)]
    # First call; then 0.05 and 0.1 on the grid; 0.26 after a stall restarts the grid (0.31).
    assert due == [0.0, 0.05, 0.1, 0.26, 0.31]
    off = HeartbeatProducer(0x7E, 0.0)
    assert not any(off.due(t) for t in times)
    with pytest.raises(ValueError, match="heartbeat period"):
        HeartbeatProducer(1, -1.0)


def test_heartbeat_consumer_timeout_recovery_boot() -> None:
    # Binary-exact times so that "exactly at the timeout" is exact.
    consumer = HeartbeatConsumer((1, 2, 3), timeout_s=0.25)
    events: list[HeartbeatEvent] = []
    assert consumer.on_heartbeat(1, NmtState.OPERATIONAL, 0.0) is None
    assert consumer.on_heartbeat(9, NmtState.OPERATIONAL, 0.0) is None  # not monitored
    consumer.check(1.0, events)
    # Node 1 timed out; nodes 2 and 3 were never heard and not started: not monitored yet.
    assert [(e.node_id, e.kind) for e in events] == [(1, HeartbeatEventKind.TIMEOUT)]
    events.clear()
    consumer.check(1.125, events)
    assert events == []  # reported once
    assert consumer.is_lost(1)
    event = consumer.on_heartbeat(1, NmtState.OPERATIONAL, 1.25)
    assert event is not None and event.kind is HeartbeatEventKind.RECOVERED
    assert not consumer.is_lost(1)
    consumer.start(1.25)
    consumer.check(1.5, events)
    assert events == []  # exactly at the timeout is not late
    consumer.check(1.5001, events)
    assert sorted(e.node_id for e in events) == [1, 2, 3]
    event = consumer.on_heartbeat(2, NmtState.BOOT_UP, 1.75)
    assert event is not None and event.kind is HeartbeatEventKind.BOOT_UP
    consumer.on_heartbeat(3, NmtState.OPERATIONAL, 1.75)
    event = consumer.on_heartbeat(3, NmtState.PRE_OPERATIONAL, 1.875)
    assert event is not None and event.kind is HeartbeatEventKind.STATE_CHANGED
    assert consumer.state(3) is NmtState.PRE_OPERATIONAL
    assert consumer.last_seen_s(3) == 1.875


def test_emcy_decode() -> None:
    emcy = parse_emcy(2, h("11 86 80 00 00 00 00 00"), now_s=0.5)
    assert emcy is not None
    assert emcy.code is EmcyCode.FOLLOWING_ERROR and emcy.code == 0x8611
    assert (emcy.node_id, emcy.error_register, emcy.manufacturer, emcy.now_s) == (
        2,
        0x80,
        bytes(5),
        0.5,
    )
    assert not emcy.is_reset
    assert emcy.description == "FOLLOWING_ERROR (0x8611)"
    for raw, code in [("30 81", EmcyCode.HEARTBEAT_ERROR), ("50 82", EmcyCode.RPDO_TIMEOUT)]:
        decoded = parse_emcy(1, h(raw + " 11 00 00 00 00 00"), 0.0)
        assert decoded is not None and decoded.code is code
    reset = parse_emcy(1, bytes(8), 0.0)
    assert reset is not None and reset.is_reset and reset.code is EmcyCode.NO_ERROR
    unknown = parse_emcy(1, h("34 12 01 aa bb cc dd ee"), 0.0)
    assert unknown is not None
    assert unknown.code == 0x1234 and not isinstance(unknown.code, EmcyCode)
    assert unknown.manufacturer == h("aa bb cc dd ee")
    assert unknown.description == "UNKNOWN (0x1234)"
    assert parse_emcy(1, h("11 86 80"), 0.0) is None
    msg = emcy_message(3, EmcyCode.FOLLOWING_ERROR, 0x81)
    assert (msg.arbitration_id, bytes(msg.data)) == (0x083, h("11 86 81 00 00 00 00 00"))


# ---------------------------------------------------------------- SDO


def test_download_command_bytes() -> None:
    assert [download_command(n) for n in (4, 3, 2, 1)] == [0x23, 0x27, 0x2B, 0x2F]
    with pytest.raises(ValueError, match=r"1\.\.4"):
        download_command(5)


def test_sdo_expedited_downloads() -> None:
    bus = ScriptedBus(
        [
            (TX, 0x602, h("23 00 14 01 02 02 00 80")),  # 0x1400 sub 1 = 0x80000202 (u32)
            (RX, 0x582, h("60 00 14 01 00 00 00 00")),
            (TX, 0x602, h("2b 17 10 00 32 00 00 00")),  # 0x1017 = 50 (u16)
            (RX, 0x582, h("60 17 10 00 00 00 00 00")),
            (TX, 0x602, h("2f 60 60 00 08 00 00 00")),  # 0x6060 = 8 (i8)
            (RX, 0x582, h("60 60 60 00 00 00 00 00")),
            (TX, 0x602, h("2f c2 60 02 fd 00 00 00")),  # 0x60C2 sub 2 = -3 (i8)
            (RX, 0x582, h("60 c2 60 02 00 00 00 00")),
        ]
    )
    clock = ScriptClock()
    sdo = SdoClient(bus, 2)
    od = import_od(str(DEFAULT_EDS), 2)
    sdo.download(0x1400, 1, h("02 02 00 80"), clock, 0.1)
    sdo.write(od, 0x1017, 0, 50, clock, 0.1)
    sdo.write(od, 0x6060, 0, 8, clock, 0.1)
    sdo.write(od, 0x60C2, 2, -3, clock, 0.1)
    bus.assert_done()


def test_sdo_abort_names_object_and_meaning() -> None:
    bus = ScriptedBus(
        [
            (TX, 0x601, h("23 65 60 00 ff ff ff 7f")),
            (RX, 0x581, h("80 65 60 00 30 00 09 06")),
        ]
    )
    with pytest.raises(SdoAbortedError) as info:
        SdoClient(bus, 1).download(0x6065, 0, h("ff ff ff 7f"), ScriptClock(), 0.1)
    err = info.value
    assert (err.node_id, err.index, err.subindex, err.code) == (1, 0x6065, 0, 0x06090030)
    assert "0x6065 sub 0" in str(err) and "Value range of parameter exceeded" in str(err)
    assert isinstance(err, CommunicationError)


def test_sdo_timeout_sends_abort() -> None:
    clock = ScriptClock()
    bus = ScriptedBus(
        [
            (TX, 0x603, h("2b 17 10 00 32 00 00 00")),
            (TX, 0x603, h("80 17 10 00 00 00 04 05")),  # abort 0x05040000 (timeout)
        ],
        clock,
    )
    with pytest.raises(SdoTimeoutError, match="node 3 to download of 0x1017 sub 0"):
        SdoClient(bus, 3).download(0x1017, 0, h("32 00"), clock, 0.25)
    bus.assert_done()
    assert clock.now_s == pytest.approx(0.25)


def test_sdo_expedited_upload_and_other_frames_forwarded() -> None:
    bus = ScriptedBus(
        [
            (TX, 0x601, h("40 00 10 00 00 00 00 00")),
            (RX, 0x701, h("7f")),  # a heartbeat arrives meanwhile
            (RX, 0x581, h("43 00 10 00 92 01 02 00")),
            (TX, 0x601, h("40 61 60 00 00 00 00 00")),
            (RX, 0x581, h("4f 61 60 00 08 00 00 00")),  # 1 byte, size indicated
            (TX, 0x601, h("40 66 60 00 00 00 00 00")),
            (RX, 0x581, h("43 66 60 00 64 00 00 00")),  # u16 answered with 4 bytes
        ]
    )
    seen: list[tuple[int, bytes, float]] = []
    clock = ScriptClock(3.0)
    sdo = SdoClient(bus, 1, on_other=lambda m, t: seen.append((m.arbitration_id, bytes(m.data), t)))
    od = import_od(str(DEFAULT_EDS), 1)
    assert sdo.read(od, 0x1000, 0, clock, 0.1) == 0x00020192
    assert seen == [(0x701, h("7f"), 3.0)]
    assert sdo.upload(0x6061, 0, clock, 0.1) == h("08")
    assert sdo.read(od, 0x6066, 0, clock, 0.1) == 100
    bus.assert_done()


def test_sdo_segmented_upload_of_a_string() -> None:
    name = b"excavator-rt drive"  # 18 bytes: 7 + 7 + 4
    bus = ScriptedBus(
        [
            (TX, 0x601, h("40 08 10 00 00 00 00 00")),
            (RX, 0x581, h("41 08 10 00 12 00 00 00")),  # segmented, size 18
            (TX, 0x601, h("60 00 00 00 00 00 00 00")),  # toggle 0
            (RX, 0x581, bytes([0x00]) + name[0:7]),
            (TX, 0x601, h("70 00 00 00 00 00 00 00")),  # toggle 1
            (RX, 0x581, bytes([0x10]) + name[7:14]),
            (TX, 0x601, h("60 00 00 00 00 00 00 00")),
            (RX, 0x581, bytes([0x00 | (3 << 1) | 1]) + name[14:18] + bytes(3)),  # n=3, last
        ]
    )
    od = import_od(str(DEFAULT_EDS), 1)
    assert SdoClient(bus, 1).read(od, 0x1008, 0, ScriptClock(), 0.1) == name.decode()
    bus.assert_done()


def test_sdo_toggle_error_aborts() -> None:
    bus = ScriptedBus(
        [
            (TX, 0x601, h("40 08 10 00 00 00 00 00")),
            (RX, 0x581, h("41 08 10 00 0e 00 00 00")),
            (TX, 0x601, h("60 00 00 00 00 00 00 00")),
            (RX, 0x581, h("10 61 62 63 64 65 66 67")),  # toggle 1, expected 0
            (TX, 0x601, h("80 08 10 00 00 00 03 05")),  # abort 0x05030000
        ]
    )
    with pytest.raises(SdoProtocolError, match="toggle"):
        SdoClient(bus, 1).upload(0x1008, 0, ScriptClock(), 0.1)
    bus.assert_done()


def test_sdo_mismatched_answer_aborts() -> None:
    bus = ScriptedBus(
        [
            (TX, 0x601, h("2b 17 10 00 32 00 00 00")),
            (RX, 0x581, h("60 16 10 01 00 00 00 00")),  # answers another object
            (TX, 0x601, h("80 17 10 00 01 00 04 05")),  # abort 0x05040001
        ]
    )
    with pytest.raises(SdoProtocolError, match="0x1016 sub 1"):
        SdoClient(bus, 1).download(0x1017, 0, h("32 00"), ScriptClock(), 0.1)
    bus.assert_done()


def test_scripted_bus_catches_a_wrong_frame() -> None:
    bus = ScriptedBus([(TX, 0x601, h("2b 17 10 00 32 00 00 00"))])
    with pytest.raises(ScriptMismatch, match="script says"):
        bus.send(can.Message(arbitration_id=0x601, is_extended_id=False, data=h("2b 17 10 00")))


# ---------------------------------------------------------------- frame lengths and bus load


def _crc15_by_division(bits: list[int]) -> int:
    # Independent: the remainder of (message * x^15) divided by the generator, as integers.
    generator = (1 << 15) | 0x4599
    value = int("".join(map(str, bits)) or "0", 2) << 15
    for shift in range(value.bit_length() - 16, -1, -1):
        if value >> (shift + 15) & 1:
            value ^= generator << shift
    return value


def test_crc15_matches_polynomial_division() -> None:
    rng = random.Random(6)
    for _ in range(200):
        bits = [rng.getrandbits(1) for _ in range(rng.randint(1, 83))]
        assert crc15(bits) == _crc15_by_division(bits), bits


def test_frame_lengths_by_hand() -> None:
    # 1 SOF + 11 id + RTR + IDE + r0 + 4 DLC + 64 data + 15 CRC + 1 + 1 + 1 + 7 EOF + 3 IFS.
    assert frame_bits_nominal(8) == 111
    assert frame_bits_nominal(0) == 47
    assert frame_bits_nominal(5) == 87
    # Worst case stuff bits: floor((34 + 8n - 1) / 4).
    assert frame_bits_worst(8) == 111 + 24 == 135
    assert frame_bits_worst(0) == 47 + 8 == 55
    assert frame_bits_worst(5) == 87 + 18
    assert frame_bits_worst(1) == 55 + 10
    with pytest.raises(ValueError, match=r"0\.\.8"):
        frame_bits_nominal(9)


def test_exact_stuffing_by_hand() -> None:
    # Id 0, no data: SOF..DLC are 19 zeros, and the CRC of all zeros is 0: 34 zeros in a row.
    # A stuff bit (1) after every 5 zeros; each stuff bit starts a new run: 6 stuff bits.
    assert frame_bits_exact(0x000, b"") == 47 + 6
    # Any content lies between the nominal length and the worst-case bound.
    rng = random.Random(402)
    for _ in range(500):
        n = rng.randint(0, 8)
        data = bytes(rng.getrandbits(8) for _ in range(n))
        bits = frame_bits_exact(rng.randint(0, 0x7FF), data)
        assert frame_bits_nominal(n) <= bits <= frame_bits_worst(n), (n, data.hex())


def test_bus_load_three_drives_500hz_by_hand() -> None:
    period_s, bitrate, heartbeat_s = 0.002, 1_000_000, 0.05
    frames = cia402_cycle_frames(3, period_s, heartbeat_s)
    # Per 2 ms: RPDO1 3 x 8 B, SYNC, TPDO1 3 x 8 B (TPDO2 only on change); 4 heartbeats per 50 ms.
    nominal_bits = 3 * 111 + 47 + 3 * 111 + 4 * 55 * period_s / heartbeat_s
    worst_bits = 3 * 135 + 55 + 3 * 135 + 4 * 65 * period_s / heartbeat_s
    assert nominal_bits == pytest.approx(721.8)
    assert worst_bits == pytest.approx(875.4)
    assert bus_load(frames, period_s, bitrate, "none") == pytest.approx(nominal_bits / 2000)
    assert bus_load(frames, period_s, bitrate) == pytest.approx(worst_bits / 2000)
    report = bus_load_report(frames, period_s, bitrate)
    assert report.nominal == pytest.approx(0.3609)
    assert report.worst_case == pytest.approx(0.4377)
    assert report.bits_per_s_worst_case == pytest.approx(437_700)
    print(
        f"\n3 drives at 500 Hz on 1 Mbit/s: nominal {report.nominal:.1%}, "
        f"worst case {report.worst_case:.1%}"
    )
    with pytest.raises(ValueError, match="must be > 0"):
        bus_load(frames, 0.0, bitrate)
