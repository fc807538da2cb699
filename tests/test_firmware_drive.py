"""Drive firmware model: CiA 301 protocol byte-exact, CiA 402 state machine, CSP cascade, faults.

Protocol tests script the exchange as ``(TX, id, bytes)`` (master -> drive) and ``(RX, id,
bytes)`` (drive -> master). The SDO server is also driven by canopen's own SDO client, an
independent implementation of the same standard. The cascade tests run the firmware against a
simple mass plant defined here.
"""

from __future__ import annotations

import itertools
import math
import queue
import random
import struct
from dataclasses import dataclass, field, replace

import numpy as np
import pytest
from canopen.objectdictionary import import_od
from canopen.sdo import SdoClient
from canopen.sdo.exceptions import SdoAbortedError

from firmware_models import CIA402_DRIVE_EDS
from firmware_models.drive import (
    LOAD_GAIN_RATIO_MIN,
    DeviceState,
    DriveFirmware,
    DriveKind,
    DriveParameters,
    EmcyCode,
    NmtState,
    SdoAbort,
    load_gain_ratio,
    overlap_jump,
    valve_velocity_gains_m_s,
)
from firmware_models.errors import FirmwareConfigurationError

NODE = 3
SDO_RX, SDO_TX = 0x600 + NODE, 0x580 + NODE
RPDO1, RPDO2, TPDO1, TPDO2 = 0x200 + NODE, 0x300 + NODE, 0x180 + NODE, 0x280 + NODE
EMCY, HEARTBEAT, SYNC, NMT = 0x080 + NODE, 0x700 + NODE, 0x080, 0x000
MASTER_HB = 0x77E
PERIOD_S = 2e-3
SUBSTEPS = 8
DT_S = PERIOD_S / SUBSTEPS

# Statusword of this model per state (bit 9 remote, bit 4 voltage enabled, bit 12 CSP follows).
SW = {
    DeviceState.SWITCH_ON_DISABLED: 0x0250,
    DeviceState.READY_TO_SWITCH_ON: 0x0231,
    DeviceState.SWITCHED_ON: 0x0233,
    DeviceState.OPERATION_ENABLED: 0x1237,
    DeviceState.QUICK_STOP_ACTIVE: 0x0217,
    DeviceState.FAULT_REACTION_ACTIVE: 0x021F,
    DeviceState.FAULT: 0x0218,
}
# CiA 402 state coding (mask, value), written from the standard.
CODING = {
    DeviceState.SWITCH_ON_DISABLED: (0x4F, 0x40),
    DeviceState.READY_TO_SWITCH_ON: (0x6F, 0x21),
    DeviceState.SWITCHED_ON: (0x6F, 0x23),
    DeviceState.OPERATION_ENABLED: (0x6F, 0x27),
    DeviceState.QUICK_STOP_ACTIVE: (0x6F, 0x07),
    DeviceState.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    DeviceState.FAULT: (0x4F, 0x08),
}


# ---------------------------------------------------------------------------------------------
# Stand-in rig and plant
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Drives:
    encoder_resolution_m: float = 1e-6
    position_gain_1_s: float = 80.0
    velocity_gain_s_m: float = 20.0
    velocity_integral_gain_1_s: float = 40.0
    servo_period_s: float = DT_S
    following_error_window_m: float = 2e-3
    following_error_timeout_s: float = 0.01
    heartbeat_period_s: float = 0.1
    heartbeat_timeout_s: float = 0.3
    sync_timeout_s: float = 0.02
    quick_stop_deceleration_m_s2: float = 1.0
    load_compensation_filter_s: float = 0.0
    pressure_feedback_gain: tuple[float, ...] = (0.0, 0.0, 0.0)
    pressure_feedback_filter_s: float = 0.0
    valve_overlap_compensation: float = 0.0


@dataclass(frozen=True)
class Hydraulic:
    supply_pressure_pa: float = 21e6
    piston_area_m2: float = 5.027e-3
    rod_area_m2: float = 1.59e-3
    valve_flow_m3_s: float = 40e-3 / 60.0


@dataclass(frozen=True)
class Actuators:
    force_max_n: float = 5000.0
    velocity_max_m_s: float = 0.2
    hydraulic: Hydraulic | None = None


@dataclass(frozen=True)
class Rig:
    drives: Drives = field(default_factory=Drives)
    actuators: Actuators = field(default_factory=Actuators)


@dataclass
class MassPlant:
    """Mass with viscous friction and a constant load, pushed by effort * force_max."""

    mass_kg: float = 50.0
    force_max_n: float = 5000.0
    viscous_n_s_m: float = 200.0
    load_n: float = -300.0
    position_m: float = 0.1
    velocity_m_s: float = 0.0
    blocked: bool = False

    def step(self, dt_s: float, effort: float) -> None:
        if self.blocked:
            self.velocity_m_s = 0.0
            return
        force = effort * self.force_max_n - self.viscous_n_s_m * self.velocity_m_s + self.load_n
        self.velocity_m_s += force / self.mass_kg * dt_s
        self.position_m += self.velocity_m_s * dt_s


class Harness:
    """One drive on a scripted bus with a mass plant; the master's side is written here."""

    def __init__(self, rig: Rig | None = None, **kwargs: object) -> None:
        self.plant = MassPlant()
        self.fw = DriveFirmware(
            NODE, rig or Rig(), "stick", initial_position_m=self.plant.position_m, **kwargs
        )  # type: ignore[arg-type]
        self.t_s = 0.0
        self.emcy: list[tuple[int, int]] = []
        self.heartbeats: list[int] = []
        self.efforts: list[float] = []

    def send(self, can_id: int, data: bytes = b"") -> list[tuple[int, bytes]]:
        return self.fw.on_frame(can_id, data, self.t_s)

    def poll(self) -> list[tuple[int, bytes]]:
        frames = self.fw.pending_frames(self.t_s)
        for can_id, data in frames:
            if can_id == EMCY:
                code, register = struct.unpack_from("<HB", data)
                self.emcy.append((code, register))
            elif can_id == HEARTBEAT:
                self.heartbeats.append(data[0])
        return frames

    def boot(self, start: bool = True) -> None:
        assert self.poll() == [(HEARTBEAT, b"\x00")]
        if start:
            assert self.send(NMT, bytes([0x01, NODE])) == []

    def controlword(self, word: int, mode: int = 8) -> None:
        assert self.send(RPDO2, struct.pack("<Hb", word, mode)) == []

    def enable(self) -> None:
        self.servo(1)
        self.controlword(0x06)
        self.controlword(0x07)
        self.controlword(0x0F)
        assert self.fw.state is DeviceState.OPERATION_ENABLED

    def servo(self, n: int) -> None:
        for _ in range(n):
            effort = self.fw.servo_step(DT_S, self.plant.position_m, self.plant.velocity_m_s)
            self.efforts.append(effort)
            self.plant.step(DT_S, effort)

    def cycle(
        self,
        target_m: float | None,
        velocity_m_s: float = 0.0,
        *,
        sync: bool = True,
        heartbeat: bool = True,
    ) -> list[tuple[int, bytes]]:
        """One master cycle: RPDO1, SYNC, master heartbeat, then one period of servo."""
        if target_m is not None:
            payload = struct.pack("<ii", round(target_m * 1e6), round(velocity_m_s * 1e6))
            self.send(RPDO1, payload)
        out = self.send(SYNC) if sync else []
        if heartbeat:
            self.send(MASTER_HB, b"\x05")
        self.poll()
        self.servo(SUBSTEPS)
        self.t_s += PERIOD_S
        return out


def exchange(harness: Harness, script: list[tuple[str, int, str]]) -> None:
    """Run a scripted exchange: every TX's replies must equal the RX lines that follow it."""
    pending: list[tuple[int, bytes]] = []
    for direction, can_id, hex_data in script:
        data = bytes.fromhex(hex_data)
        if direction == "TX":
            assert pending == [], f"unanswered replies before TX {can_id:03X} {hex_data}"
            pending = list(harness.send(can_id, data))
        else:
            assert pending, f"expected RX {can_id:03X} {hex_data}, the drive sent nothing"
            assert pending.pop(0) == (can_id, data), f"RX {can_id:03X} {hex_data}"
    assert pending == [], f"unexpected replies {pending}"


def sdo_client(harness: Harness) -> SdoClient:
    """canopen's SDO client wired synchronously to the drive."""
    client = SdoClient(SDO_RX, SDO_TX, import_od(str(CIA402_DRIVE_EDS), NODE))
    client.RESPONSE_TIMEOUT = 0.01

    class Network:
        def send_message(self, can_id: int, data: bytes | bytearray) -> None:
            for reply_id, reply in harness.send(can_id, bytes(data)):
                if reply_id == SDO_TX:
                    client.on_response(reply_id, reply, 0.0)

    client.network = Network()  # type: ignore[assignment]
    client.responses = queue.Queue()
    return client


# ---------------------------------------------------------------------------------------------
# NMT, heartbeat, boot
# ---------------------------------------------------------------------------------------------



def _statusword(replies: list[tuple[int, bytes]], previous: int) -> int:
    """The statusword of this SYNC's TPDO2, or ``previous`` (TPDO2 is sent on change only)."""
    for cob_id, data in replies:
        if cob_id == TPDO2:
            return int(struct.unpack_from("<H", data)[0])
    return previous

def test_boot_sdo_configuration_start_and_pdos_byte_exact() -> None:
    h = Harness()
    assert h.fw.nmt_state is NmtState.INITIALISING
    assert h.send(SDO_RX, bytes.fromhex("4041600000000000")) == []  # not up yet
    assert h.poll() == [(HEARTBEAT, b"\x00")]  # boot-up
    assert h.fw.nmt_state is NmtState.PRE_OPERATIONAL
    h.servo(1)
    exchange(
        h,
        [
            ("TX", SDO_RX, "2365600010270000"),  # 0x6065 = 10000 um
            ("RX", SDO_TX, "6065600000000000"),
            ("TX", SDO_RX, "2F60600008000000"),  # 0x6060 = 8 (CSP)
            ("RX", SDO_TX, "6060600000000000"),
            ("TX", SDO_RX, "2B17100064000000"),  # 0x1017 = 100 ms
            ("RX", SDO_TX, "6017100000000000"),
            ("TX", SDO_RX, "23161001C8007E00"),  # 0x1016:1 = master 0x7E, 200 ms
            ("RX", SDO_TX, "6016100100000000"),
            ("TX", SDO_RX, "4041600000000000"),  # upload statusword
            ("RX", SDO_TX, "4B41600050020000"),  # 0x0250 switch on disabled
            ("TX", SDO_RX, "4061600000000000"),  # upload modes display
            ("RX", SDO_TX, "4F61600008000000"),
            ("TX", SYNC, ""),  # pre-operational: no PDOs
            ("TX", NMT, "0103"),  # start node 3
            ("TX", RPDO1, "a086010000000000"),  # target 100000 um, offset 0
            ("TX", RPDO2, "060008"),  # shutdown, mode 8
            ("TX", SYNC, ""),
            ("RX", TPDO1, "a086010000000000"),  # actual 100000 um, 0 um/s
            ("RX", TPDO2, "3102080000"),  # ready to switch on, mode 8, no error
            ("TX", 0x204, "0000000000000000"),  # another node's RPDO1
            ("TX", NMT, "0204"),  # stop for node 4: not us
            ("TX", NMT, "0200"),  # stop all
            ("TX", SYNC, ""),  # stopped: nothing
            ("TX", SDO_RX, "4041600000000000"),  # stopped: no SDO
        ],
    )
    assert h.fw.nmt_state is NmtState.STOPPED
    assert h.fw.read_object(0x6065) == 10000
    assert h.fw.read_object(0x1016, 1) == 0x007E00C8


def test_heartbeat_producer_period_and_state_byte() -> None:
    h = Harness()
    h.boot(start=False)
    h.t_s = 0.0999
    assert h.poll() == []
    h.t_s = 0.1001
    assert h.poll() == [(HEARTBEAT, b"\x7f")]
    assert h.poll() == []
    h.send(NMT, bytes([0x01, 0]))
    h.t_s = 0.2001
    assert h.poll() == [(HEARTBEAT, b"\x05")]
    h.send(NMT, bytes([0x02, NODE]))
    h.t_s = 0.3001
    assert h.poll() == [(HEARTBEAT, b"\x04")]
    h.send(NMT, bytes([0x80, NODE]))
    h.t_s = 0.4001
    assert h.poll() == [(HEARTBEAT, b"\x7f")]
    exchange(h, [("TX", SDO_RX, "2B17100000000000"), ("RX", SDO_TX, "6017100000000000")])
    h.t_s = 1.0
    assert h.poll() == []  # producer off


def test_reset_node_restores_stored_values_reset_communication_only_comm() -> None:
    rig = Rig()
    h = Harness(rig)
    h.boot()
    window_um = round(rig.drives.following_error_window_m * 1e6)
    assert h.fw.read_object(0x6065) == window_um  # commissioned from the rig
    exchange(
        h,
        [
            ("TX", SDO_RX, "2365600040420F00"),  # 0x6065 = 1000000
            ("RX", SDO_TX, "6065600000000000"),
            ("TX", SDO_RX, "2B17100010270000"),  # 0x1017 = 10000 ms
            ("RX", SDO_TX, "6017100000000000"),
        ],
    )
    h.enable()
    assert h.send(NMT, bytes([0x82, NODE])) == [(HEARTBEAT, b"\x00")]
    assert h.fw.nmt_state is NmtState.PRE_OPERATIONAL
    assert h.fw.read_object(0x1017) == round(rig.drives.heartbeat_period_s * 1e3)
    assert h.fw.read_object(0x6065) == 1_000_000  # application area kept
    assert h.fw.state is DeviceState.OPERATION_ENABLED
    assert h.send(NMT, bytes([0x81, 0])) == [(HEARTBEAT, b"\x00")]
    assert h.fw.read_object(0x6065) == window_um
    assert h.fw.state is DeviceState.SWITCH_ON_DISABLED
    assert h.fw.last_transition == 1


# ---------------------------------------------------------------------------------------------
# SDO server
# ---------------------------------------------------------------------------------------------


def test_sdo_segmented_upload_of_device_name_byte_exact() -> None:
    h = Harness()
    h.boot(start=False)
    exchange(
        h,
        [
            ("TX", SDO_RX, "4008100000000000"),
            ("RX", SDO_TX, "4108100029000000"),  # segmented, 41 bytes
            ("TX", SDO_RX, "6000000000000000"),
            ("RX", SDO_TX, "0065786361766174"),  # "excavat"
            ("TX", SDO_RX, "7000000000000000"),
            ("RX", SDO_TX, "106f722d72742043"),  # "or-rt C"
            ("TX", SDO_RX, "6000000000000000"),
            ("RX", SDO_TX, "0069412034303220"),  # "iA 402 "
            ("TX", SDO_RX, "7000000000000000"),
            ("RX", SDO_TX, "1063796c696e6465"),  # "cylinde"
            ("TX", SDO_RX, "6000000000000000"),
            ("RX", SDO_TX, "0072206472697665"),  # "r drive"
            ("TX", SDO_RX, "7000000000000000"),
            ("RX", SDO_TX, "13206d6f64656c00"),  # " model", 1 byte unused, last
        ],
    )


@pytest.mark.parametrize(
    ("request_hex", "abort_hex"),
    [
        ("4000200000000000", "8000200000000206"),  # unknown object 0x06020000
        ("4018100900000000", "8018100911000906"),  # no sub-index 0x06090011
        ("2B65600010270000", "8065600010000706"),  # 2 bytes into u32: 0x06070010
        ("2341600000000000", "8041600002000106"),  # read-only statusword: 0x06010002
        ("2B5A600003000000", "805A600030000906"),  # quick stop option 3: 0x06090030
        ("2F60600006000000", "8060600030000906"),  # mode 6 not supported
        ("2385600000000000", "8085600030000906"),  # zero quick-stop deceleration
        ("2F00160000000000", "8000160000000106"),  # mapping while RPDO valid: 0x06010000
        ("C040600000000000", "8040600001000405"),  # block upload: 0x05040001
        ("6000000000000000", "8000000001000405"),  # segment without a transfer
    ],
)
def test_sdo_aborts_byte_exact(request_hex: str, abort_hex: str) -> None:
    h = Harness()
    h.boot(start=False)
    exchange(h, [("TX", SDO_RX, request_hex), ("RX", SDO_TX, abort_hex)])


def test_sdo_toggle_error_and_segmented_download() -> None:
    h = Harness()
    h.boot(start=False)
    exchange(
        h,
        [
            ("TX", SDO_RX, "4008100000000000"),
            ("RX", SDO_TX, "4108100029000000"),
            ("TX", SDO_RX, "7000000000000000"),  # toggle must start at 0
            ("RX", SDO_TX, "8008100000000305"),  # 0x05030000
            # Segmented download of 0x6066 (u16) = 0x0123 with size indicated.
            ("TX", SDO_RX, "2166600002000000"),
            ("RX", SDO_TX, "6066600000000000"),
            ("TX", SDO_RX, "0B23010000000000"),  # toggle 0, 5 unused, last
            ("RX", SDO_TX, "2000000000000000"),
        ],
    )
    assert h.fw.read_object(0x6066) == 0x0123


def test_sdo_server_against_canopens_client() -> None:
    h = Harness()
    h.boot(start=False)
    client = sdo_client(h)
    assert client[0x1008].raw == "excavator-rt CiA 402 cylinder drive model"
    assert client[0x1000].raw == 0x00020192
    assert client[0x1800][1].raw == 0x180 + NODE
    client[0x6065].raw = 1234
    client[0x607D][1].raw = -50_000
    client[0x60C2][2].raw = -4
    assert h.fw.read_object(0x6065) == 1234
    assert client[0x607D][1].raw == -50_000
    assert client[0x60C2][2].raw == -4
    client.download(0x6066, 0, struct.pack("<H", 77), force_segment=True)
    assert client[0x6066].raw == 77
    assert client[0x6041].raw == SW[DeviceState.SWITCH_ON_DISABLED]
    with pytest.raises(SdoAbortedError) as aborted:
        client[0x6041].raw = 6
    assert aborted.value.code == SdoAbort.READ_ONLY
    with pytest.raises(SdoAbortedError) as aborted:
        client[0x60C2][2].raw = -7  # below the EDS LowLimit
    assert aborted.value.code == SdoAbort.VALUE_RANGE


def test_pdo_remapping_follows_cia301() -> None:
    """TPDO1 remapped to position demand only (invalid, sub0 = 0, entry, sub0 = 1, valid)."""
    h = Harness()
    h.boot(start=False)
    client = sdo_client(h)
    with pytest.raises(SdoAbortedError) as aborted:
        client[0x1A00][1].raw = 0x60620020  # PDO still valid
    assert aborted.value.code == SdoAbort.UNSUPPORTED_ACCESS
    client[0x1800][1].raw = 0x8000_0000 | TPDO1
    with pytest.raises(SdoAbortedError) as aborted:
        client[0x1A00][1].raw = 0x60620020  # sub 0 still 2
    assert aborted.value.code == SdoAbort.UNSUPPORTED_ACCESS
    client[0x1A00][0].raw = 0
    with pytest.raises(SdoAbortedError) as aborted:
        client[0x1A00][1].raw = 0x60650020  # 0x6065 is not mappable
    assert aborted.value.code == SdoAbort.NOT_MAPPABLE
    with pytest.raises(SdoAbortedError) as aborted:
        client[0x1A00][1].raw = 0x60620010  # wrong length
    assert aborted.value.code == SdoAbort.NOT_MAPPABLE
    client[0x1A00][1].raw = 0x60620020
    with pytest.raises(SdoAbortedError) as aborted:
        client[0x1A00][0].raw = 9
    assert aborted.value.code == SdoAbort.PDO_LENGTH
    client[0x1A00][0].raw = 1
    with pytest.raises(SdoAbortedError) as aborted:
        client[0x1800][2].raw = 0xFF  # event-driven TPDO not supported
    assert aborted.value.code == SdoAbort.VALUE_RANGE
    client[0x1800][1].raw = TPDO1
    h.send(NMT, bytes([0x01, NODE]))
    h.servo(1)
    replies = h.send(SYNC)
    assert replies[0] == (TPDO1, struct.pack("<i", 100_000))
    assert replies[1][0] == TPDO2


# ---------------------------------------------------------------------------------------------
# PDOs and SYNC
# ---------------------------------------------------------------------------------------------


def test_rpdo1_is_latched_at_sync_and_rpdo2_applied_on_receipt() -> None:
    h = Harness()
    h.boot()
    h.enable()
    h.send(RPDO1, struct.pack("<ii", 100_500, 2000))
    assert h.fw.read_object(0x607A) == 0  # buffered
    h.send(RPDO1, struct.pack("<ii", 100_600, 3000))  # the last one before SYNC counts
    h.send(SYNC)
    assert h.fw.read_object(0x607A) == 100_600
    assert h.fw.read_object(0x60B1) == 3000
    h.controlword(0x07)  # applied at once: disable operation
    assert h.fw.state is DeviceState.SWITCHED_ON
    h.send(RPDO1, bytes(4))  # short PDO: dropped, EMCY 0x8210
    h.poll()
    assert h.emcy[-1][0] == EmcyCode.PDO_LENGTH


def test_tpdos_are_sampled_at_sync_and_quantised() -> None:
    h = Harness(Rig(drives=Drives(encoder_resolution_m=10e-6)))
    h.boot()
    h.plant.position_m = 0.1234567
    h.servo(1)
    replies = h.send(SYNC)
    position_um, velocity_um_s = struct.unpack("<ii", replies[0][1])
    assert position_um == 123_460  # 10 um encoder counts
    assert velocity_um_s == 0
    statusword, mode, error = struct.unpack("<HbH", replies[1][1])
    assert (statusword, mode, error) == (SW[DeviceState.SWITCH_ON_DISABLED], 0, 0)


def test_tpdo_transmission_types() -> None:
    h = Harness()
    h.boot(start=False)
    client = sdo_client(h)
    client[0x1800][2].raw = 3  # every third SYNC
    client[0x1801][2].raw = 0  # on SYNC when changed
    h.send(NMT, bytes([0x01, NODE]))
    h.servo(1)
    ids = [[cid for cid, _ in h.send(SYNC)] for _ in range(6)]
    assert ids == [[TPDO2], [], [TPDO1], [], [], [TPDO1]]
    h.controlword(0x06)
    assert [cid for cid, _ in h.send(SYNC)] == [TPDO2]


@pytest.mark.parametrize("at_start", [True, False])
def test_type_0_tpdo_after_nmt_start(at_start: bool) -> None:
    """Type 0 (sent at a SYNC after its content changed): at the first SYNC after every NMT
    start, or (``tpdo_at_start=False``) only once the content differs from what it was at NMT
    start; then on each change."""
    h = Harness(tpdo_at_start=at_start)
    h.boot()
    h.servo(1)
    start = [TPDO1, TPDO2] if at_start else [TPDO1]
    assert [cid for cid, _ in h.send(SYNC)] == start
    assert [cid for cid, _ in h.send(SYNC)] == [TPDO1]
    h.send(NMT, bytes([0x80, NODE]))  # pre-operational, then started again
    h.send(NMT, bytes([0x01, NODE]))
    assert [cid for cid, _ in h.send(SYNC)] == start
    h.controlword(0x06)  # shutdown, mode 8
    ready = struct.pack("<HbH", SW[DeviceState.READY_TO_SWITCH_ON], 8, 0)
    assert h.send(SYNC)[1:] == [(TPDO2, ready)]
    assert [cid for cid, _ in h.send(SYNC)] == [TPDO1]


# ---------------------------------------------------------------------------------------------
# CiA 402 state machine
# ---------------------------------------------------------------------------------------------


def _to_state(h: Harness, state: DeviceState) -> None:
    paths = {
        DeviceState.SWITCH_ON_DISABLED: [],
        DeviceState.READY_TO_SWITCH_ON: [0x06],
        DeviceState.SWITCHED_ON: [0x06, 0x07],
        DeviceState.OPERATION_ENABLED: [0x06, 0x07, 0x0F],
        DeviceState.QUICK_STOP_ACTIVE: [0x06, 0x07, 0x0F, 0x02],
    }
    for word in paths[state]:
        h.controlword(word)
    assert h.fw.state is state


@pytest.mark.parametrize(
    ("start", "word", "transition", "end"),
    [
        (DeviceState.SWITCH_ON_DISABLED, 0x06, 2, DeviceState.READY_TO_SWITCH_ON),
        (DeviceState.READY_TO_SWITCH_ON, 0x07, 3, DeviceState.SWITCHED_ON),
        (DeviceState.READY_TO_SWITCH_ON, 0x0F, 4, DeviceState.OPERATION_ENABLED),  # 3 + 4
        (DeviceState.SWITCHED_ON, 0x0F, 4, DeviceState.OPERATION_ENABLED),
        (DeviceState.OPERATION_ENABLED, 0x07, 5, DeviceState.SWITCHED_ON),
        (DeviceState.SWITCHED_ON, 0x06, 6, DeviceState.READY_TO_SWITCH_ON),
        (DeviceState.READY_TO_SWITCH_ON, 0x00, 7, DeviceState.SWITCH_ON_DISABLED),
        (DeviceState.READY_TO_SWITCH_ON, 0x02, 7, DeviceState.SWITCH_ON_DISABLED),
        (DeviceState.OPERATION_ENABLED, 0x06, 8, DeviceState.READY_TO_SWITCH_ON),
        (DeviceState.OPERATION_ENABLED, 0x0D, 9, DeviceState.SWITCH_ON_DISABLED),
        (DeviceState.SWITCHED_ON, 0x00, 10, DeviceState.SWITCH_ON_DISABLED),
        (DeviceState.SWITCHED_ON, 0x0B, 10, DeviceState.SWITCH_ON_DISABLED),
        (DeviceState.OPERATION_ENABLED, 0x0B, 11, DeviceState.QUICK_STOP_ACTIVE),
        (DeviceState.QUICK_STOP_ACTIVE, 0x00, 12, DeviceState.SWITCH_ON_DISABLED),
        # commands that do nothing in a state
        (DeviceState.SWITCH_ON_DISABLED, 0x0F, None, DeviceState.SWITCH_ON_DISABLED),
        (DeviceState.SWITCH_ON_DISABLED, 0x07, None, DeviceState.SWITCH_ON_DISABLED),
        (DeviceState.SWITCH_ON_DISABLED, 0x02, None, DeviceState.SWITCH_ON_DISABLED),
        (DeviceState.QUICK_STOP_ACTIVE, 0x0F, None, DeviceState.QUICK_STOP_ACTIVE),  # 0x605A=2
        (DeviceState.QUICK_STOP_ACTIVE, 0x06, None, DeviceState.QUICK_STOP_ACTIVE),
        (DeviceState.OPERATION_ENABLED, 0x8F, None, DeviceState.OPERATION_ENABLED),  # bit 7
    ],
)
def test_402_transitions(
    start: DeviceState, word: int, transition: int | None, end: DeviceState
) -> None:
    h = Harness()
    h.boot()
    h.servo(1)
    _to_state(h, start)
    before = h.fw.last_transition
    h.controlword(word)
    assert h.fw.state is end
    assert h.fw.last_transition == (before if transition is None else transition)
    mask, value = CODING[end]
    assert h.fw.statusword & mask == value
    assert h.fw.statusword & 0xFF6F == SW[end] & 0xFF6F  # bit 4 aside, as tabled here


def test_402_fault_transitions_13_14_15_and_reset_edge() -> None:
    h = Harness()
    h.boot()
    h.enable()
    h.cycle(0.1)
    h.fw.inject_fault(0x2310)
    assert h.fw.state is DeviceState.FAULT_REACTION_ACTIVE
    assert h.fw.last_transition == 13
    assert h.fw.statusword & 0x4F == 0x0F
    h.cycle(0.1)  # at rest: the ramp ends at once
    assert h.fw.state is DeviceState.FAULT
    assert h.fw.last_transition == 14
    assert h.emcy == [(0x2310, 0x03)]  # generic + current
    assert h.fw.read_object(0x603F) == 0x2310
    assert h.fw.read_object(0x1001) == 0x03
    h.controlword(0x0F)  # no command but fault reset counts in FAULT
    h.controlword(0x8F)
    assert h.fw.state is DeviceState.SWITCH_ON_DISABLED
    assert h.fw.last_transition == 15
    h.poll()
    assert h.emcy[-1] == (0x0000, 0x00)
    assert h.fw.read_object(0x603F) == 0
    h.fw.inject_fault(0x2310)
    assert h.fw.state is DeviceState.FAULT  # not powered: 13 then 14 at once
    h.controlword(0x80)  # bit 7 was already high: no edge
    assert h.fw.state is DeviceState.FAULT
    h.controlword(0x00)
    h.controlword(0x80)
    assert h.fw.state is DeviceState.SWITCH_ON_DISABLED
    with pytest.raises(ValueError, match=r"0x0001\.\.0xFFFF"):
        h.fw.inject_fault(0)


def test_402_transition_16_with_quick_stop_option_6() -> None:
    h = Harness()
    h.boot()
    exchange(h, [("TX", SDO_RX, "2B5A600006000000"), ("RX", SDO_TX, "605A600000000000")])
    h.enable()
    for k in range(50):
        h.cycle(0.1 + 0.05 * (k + 1) * PERIOD_S, 0.05)
    h.controlword(0x02)
    assert h.fw.state is DeviceState.QUICK_STOP_ACTIVE
    for _ in range(300):
        h.cycle(None)
    assert h.fw.state is DeviceState.QUICK_STOP_ACTIVE  # option 6 stays
    assert h.fw.statusword & 0x0400  # target reached: at rest
    assert abs(h.efforts[-1]) > 0.0  # holding, not free
    h.controlword(0x0F)
    assert h.fw.state is DeviceState.OPERATION_ENABLED
    assert h.fw.last_transition == 16


# ---------------------------------------------------------------------------------------------
# Servo cascade
# ---------------------------------------------------------------------------------------------


def _track_ramp(h: Harness, velocity_m_s: float, feed_forward: bool, cycles: int) -> list[float]:
    """Master streams p(t) = p0 + v t one period ahead; returns |truth - reference| per cycle."""
    p0 = h.plant.position_m
    errors = []
    for k in range(cycles):
        target = p0 + velocity_m_s * (k + 1) * PERIOD_S
        h.cycle(target, velocity_m_s if feed_forward else 0.0)
        reference = p0 + velocity_m_s * (k + 1) * PERIOD_S  # demand reaches it one period later
        errors.append(abs(h.plant.position_m - reference))
    return errors


def test_csp_tracks_a_ramp_and_feed_forward_helps() -> None:
    results = {}
    for feed_forward in (True, False):
        h = Harness()
        h.boot()
        h.enable()
        for _ in range(200):  # settle the load
            h.cycle(0.1)
        errors = _track_ramp(h, 0.05, feed_forward, 500)
        results[feed_forward] = max(errors[100:])
        assert h.fw.state is DeviceState.OPERATION_ENABLED
    print(f"ramp 50 mm/s, steady error: ff on {results[True] * 1e3:.4f} mm, "
          f"off {results[False] * 1e3:.4f} mm")  # fmt: skip
    assert results[True] < 0.05e-3
    assert results[False] > 5 * results[True]
    assert results[False] == pytest.approx(0.05 / 80.0, rel=0.1)  # v / Kp, a P position loop


def test_interpolation_is_linear_across_the_sync_period() -> None:
    h = Harness()
    h.boot()
    h.enable()
    h.cycle(0.1)
    h.cycle(0.1)  # two SYNCs: interval measured
    h.send(RPDO1, struct.pack("<ii", 100_800, 0))
    h.send(SYNC)
    demands = []
    for _ in range(SUBSTEPS):
        h.servo(1)
        demands.append(h.fw.position_demand_m)
    steps = [b - a for a, b in itertools.pairwise([0.1, *demands])]
    assert steps == pytest.approx([0.8e-3 / SUBSTEPS] * SUBSTEPS, abs=1e-12)
    h.servo(4)  # a late SYNC: the demand holds at the target
    assert h.fw.position_demand_m == pytest.approx(0.1008, abs=1e-12)
    # 0x60C2 = 4 ms: half way after one SYNC period
    exchange(
        h,
        [
            ("TX", SDO_RX, "2FC2600104000000"),
            ("RX", SDO_TX, "60C2600100000000"),
            ("TX", SDO_RX, "2FC26002FD000000"),
            ("RX", SDO_TX, "60C2600200000000"),
        ],
    )
    h.send(RPDO1, struct.pack("<ii", 101_800, 0))
    h.send(SYNC)
    h.servo(SUBSTEPS)
    assert h.fw.position_demand_m == pytest.approx(0.1013, abs=1e-9)


def test_saturation_and_anti_windup() -> None:
    h = Harness()
    h.boot()
    h.enable()
    for _ in range(100):
        h.cycle(0.1)
    h.send(RPDO1, struct.pack("<ii", 110_000, 0))  # 10 mm step, far beyond the window
    exchange(h, [("TX", SDO_RX, "23656000FFFFFFFF"), ("RX", SDO_TX, "6065600000000000")])
    start = len(h.efforts)
    limit_bits, positions, speeds = [], [], []
    statusword = 0
    for _ in range(300):
        statusword = _statusword(h.cycle(0.11), statusword)
        limit_bits.append(statusword & 0x0800)
        positions.append(h.plant.position_m)
        speeds.append(h.fw.velocity_actual_m_s)
    efforts = h.efforts[start:]
    assert max(efforts) == 1.0  # saturated, never beyond
    assert min(efforts) >= -1.0
    assert limit_bits[1] and not limit_bits[-1]  # internal limit active while limited only
    assert max(speeds) < 0.2 * 1.02  # the velocity command is limited to velocity_max
    # conditional integration: no wind-up overshoot after the long saturated approach
    assert max(positions) - 0.11 < 0.1e-3
    assert h.plant.position_m == pytest.approx(0.11, abs=5e-6)


def test_software_position_limits_clamp_the_target() -> None:
    h = Harness()
    h.boot(start=False)
    client = sdo_client(h)
    client[0x607D][1].raw = 90_000
    client[0x607D][2].raw = 102_000
    h.send(NMT, bytes([0x01, NODE]))
    h.enable()
    for _ in range(400):
        h.cycle(0.2)
    assert h.fw.position_demand_m == pytest.approx(0.102)
    assert h.plant.position_m == pytest.approx(0.102, abs=20e-6)
    assert h.fw.statusword & 0x0800


def test_following_error_faults_after_the_timeout_with_emcy_8611() -> None:
    h = Harness()
    h.boot()
    h.enable()
    h.cycle(0.1)
    h.plant.blocked = True
    window_m, timeout_s = 2e-3, 0.01
    velocity = 0.1
    k_exceeded = None
    statusword = 0
    for k in range(60):
        target = 0.1 + velocity * (k + 1) * PERIOD_S
        statusword = _statusword(h.cycle(target, velocity), statusword)
        if k_exceeded is None and abs(h.fw.position_demand_m - h.plant.position_m) > window_m:
            k_exceeded = k
            assert statusword & 0x2000 == 0  # reported from the next TPDO2 on
        if h.fw.state is not DeviceState.OPERATION_ENABLED:
            break
    assert k_exceeded is not None
    # Simulated time, counted in SYNC periods (no clock is read): the fault comes once the
    # error has stayed outside the window for the timeout, within two periods.
    timeout_periods = round(timeout_s / PERIOD_S)
    assert timeout_periods <= k - k_exceeded <= timeout_periods + 2
    replies = h.cycle(None)
    assert h.emcy == [(EmcyCode.FOLLOWING_ERROR, 0x21)]
    assert h.fw.state is DeviceState.FAULT  # blocked: the ramp from rest ends at once
    replies += h.cycle(None)
    tpdo2 = [data for cob_id, data in replies if cob_id == TPDO2]
    statusword, _, error = struct.unpack("<HbH", tpdo2[-1])
    assert statusword & 0x4F == 0x08
    assert error == 0x8611
    assert h.efforts[-1] == 0.0


def test_heartbeat_loss_faults_with_emcy_8130() -> None:
    h = Harness()
    h.boot()
    h.enable()
    for _ in range(10):
        h.cycle(0.1, heartbeat=False)  # monitoring has not started: no heartbeat seen yet
    assert h.emcy == []
    h.cycle(0.1)  # first master heartbeat arms the consumer (300 ms)
    armed_at = h.t_s - PERIOD_S
    while not h.emcy and h.t_s < 1.0:
        h.cycle(0.1, heartbeat=False)
    lost_after = h.t_s - PERIOD_S - armed_at
    assert 0.3 < lost_after <= 0.3 + PERIOD_S
    assert h.emcy == [(EmcyCode.HEARTBEAT, 0x11)]
    assert h.fw.state in (DeviceState.FAULT_REACTION_ACTIVE, DeviceState.FAULT)
    assert h.fw.nmt_state is NmtState.OPERATIONAL  # TPDO2 still reports the fault


def test_missing_sync_faults_with_emcy_8250() -> None:
    h = Harness()
    h.boot()
    h.enable()
    for _ in range(20):
        h.cycle(0.1)
    for _ in range(10):
        h.cycle(0.1, sync=False)
        if h.emcy:
            break
    assert h.emcy == [(EmcyCode.RPDO_TIMEOUT, 0x11)]
    assert h.fw.state in (DeviceState.FAULT_REACTION_ACTIVE, DeviceState.FAULT)
    # RPDOs missing while SYNC keeps coming also trips it
    h2 = Harness()
    h2.boot()
    h2.enable()
    for _ in range(5):
        h2.cycle(0.1)
    for _ in range(20):
        h2.cycle(None)
    assert h2.emcy == [(EmcyCode.RPDO_TIMEOUT, 0x11)]


def test_quick_stop_ramps_at_0x6085_then_disables() -> None:
    h = Harness()
    h.boot()
    h.enable()
    velocity = 0.1
    for k in range(150):
        h.cycle(0.1 + velocity * (k + 1) * PERIOD_S, velocity)
    assert h.fw.velocity_actual_m_s == pytest.approx(velocity, rel=0.05)
    h.controlword(0x02)
    assert h.fw.state is DeviceState.QUICK_STOP_ACTIVE
    demands = [h.fw.position_demand_m]
    while h.fw.state is DeviceState.QUICK_STOP_ACTIVE and len(demands) < 2000:
        h.servo(1)
        demands.append(h.fw.position_demand_m)
    decel = 1.0  # Drives.quick_stop_deceleration_m_s2
    stop_time_s = (len(demands) - 1) * DT_S
    assert stop_time_s == pytest.approx(velocity / decel, abs=3 * DT_S)
    speeds = [(b - a) / DT_S for a, b in itertools.pairwise(demands)]
    accelerations = [(b - a) / DT_S for a, b in itertools.pairwise(speeds)]
    assert max(abs(a) for a in accelerations[:-1]) == pytest.approx(decel, rel=0.01)
    assert demands[-1] - demands[0] == pytest.approx(velocity**2 / (2 * decel), rel=0.05)
    assert h.fw.state is DeviceState.SWITCH_ON_DISABLED
    assert h.fw.last_transition == 12
    h.servo(1)
    assert h.efforts[-1] == 0.0
    assert h.fw.brake_engaged


def test_fault_reaction_ramp_from_motion() -> None:
    h = Harness()
    h.boot()
    h.enable()
    for k in range(150):
        h.cycle(0.1 + 0.1 * (k + 1) * PERIOD_S, 0.1)
    h.fw.inject_fault(0x5000)
    assert h.fw.state is DeviceState.FAULT_REACTION_ACTIVE
    steps = 0
    while h.fw.state is DeviceState.FAULT_REACTION_ACTIVE:
        h.servo(1)
        steps += 1
    assert steps * DT_S == pytest.approx(0.1, abs=3 * DT_S)
    assert h.fw.state is DeviceState.FAULT and h.fw.last_transition == 14


def test_hydraulic_cascade_is_position_p_plus_feed_forward_over_valve_gain() -> None:
    rig = Rig(actuators=Actuators(velocity_max_m_s=0.28, hydraulic=Hydraulic()))
    h = Harness(rig)
    assert h.fw.params.kind is DriveKind.HYDRAULIC
    extend, retract = valve_velocity_gains_m_s(Hydraulic())
    assert extend == pytest.approx(0.2828, abs=1e-4)  # the no-load extension speed
    assert retract < extend
    h.boot()
    h.enable()
    h.send(RPDO1, struct.pack("<ii", 100_000 + 100, 20_000))  # 0.1 mm ahead, 20 mm/s
    h.send(SYNC)
    h.servo(SUBSTEPS)  # demand reaches the target; plant (mass) barely moved
    error = h.fw.position_demand_m - h.fw.position_actual_m
    expected = (80.0 * error + 0.02) / extend
    assert h.efforts[-1] == pytest.approx(expected, rel=1e-9)
    h.send(RPDO1, struct.pack("<ii", 90_000, -100_000))
    h.send(SYNC)
    h.servo(SUBSTEPS)
    error = h.fw.position_demand_m - h.fw.position_actual_m
    expected = max(80.0 * error - 0.1, -0.28) / retract
    assert h.efforts[-1] == pytest.approx(max(expected, -1.0), rel=1e-9)


def _steady_velocity(hyd: Hydraulic, force_n: float, opening: float) -> float:
    """Rod velocity of a differential cylinder at a fixed valve opening under a constant
    force, by solving the orifice law on both metering edges for the chamber pressures
    (scipy's root finder on the force balance; no closed form used)."""
    from scipy.optimize import brentq

    k = hyd.valve_flow_m3_s / math.sqrt(3.5e6)
    a_a, a_b, p_s = hyd.piston_area_m2, hyd.piston_area_m2 - hyd.rod_area_m2, hyd.supply_pressure_pa
    x = abs(opening)

    def force_residual(v: float) -> float:
        if opening > 0.0:  # supply -> A, B -> tank
            p_a = p_s - (a_a * v / (k * x)) ** 2
            p_b = (a_b * v / (k * x)) ** 2
        else:  # supply -> B, A -> tank
            p_b = p_s - (a_b * v / (k * x)) ** 2
            p_a = (a_a * v / (k * x)) ** 2
        return p_a * a_a - p_b * a_b - force_n

    v = brentq(force_residual, 0.0, 10.0)
    return v if opening > 0.0 else -v


@pytest.mark.parametrize("force_kn", [-40.0, -5.0, 0.0, 12.0, 60.0])
def test_load_gain_ratio_is_the_orifice_laws_velocity_under_the_force(force_kn: float) -> None:
    hyd = Hydraulic()
    f = force_kn * 1e3
    stall_out = hyd.supply_pressure_pa * hyd.piston_area_m2
    stall_in = hyd.supply_pressure_pa * (hyd.piston_area_m2 - hyd.rod_area_m2)
    extend, retract = valve_velocity_gains_m_s(hyd)
    assert _steady_velocity(hyd, 0.0, 1.0) == pytest.approx(extend, rel=1e-9)
    assert _steady_velocity(hyd, 0.0, -1.0) == pytest.approx(-retract, rel=1e-9)
    for opening in (0.3, -0.3):
        ratio = load_gain_ratio(f, opening > 0.0, stall_out, stall_in)
        gain = extend if opening > 0.0 else retract
        assert abs(_steady_velocity(hyd, f, opening)) == pytest.approx(
            ratio * gain * 0.3, rel=1e-9
        )
    # A weight (F > 0) slows extending and speeds retracting; near stall the ratio is floored.
    assert load_gain_ratio(0.999 * stall_out, True, stall_out, stall_in) == LOAD_GAIN_RATIO_MIN


def test_load_compensation_divides_the_valve_command_by_the_filtered_ratio() -> None:
    hyd = Hydraulic()
    actuators = Actuators(velocity_max_m_s=0.28, hydraulic=hyd)
    tau = 0.05
    plain = Harness(Rig(actuators=actuators))
    comp = Harness(Rig(drives=Drives(load_compensation_filter_s=tau), actuators=actuators))
    assert comp.fw.load_compensated and not plain.fw.load_compensated
    stall_out = hyd.supply_pressure_pa * hyd.piston_area_m2
    stall_in = hyd.supply_pressure_pa * (hyd.piston_area_m2 - hyd.rod_area_m2)
    for h in (plain, comp):
        h.boot()
        h.enable()  # one servo step with no load: the filter starts from an unloaded reading
    force = 30e3
    efforts: dict[str, list[float]] = {"plain": [], "comp": []}
    for name, h in (("plain", plain), ("comp", comp)):
        fw = h.fw
        fw.on_frame(RPDO1, struct.pack("<ii", 100_050, 20_000), 0.0)  # 50 um ahead, 20 mm/s
        fw.on_frame(SYNC, b"", 0.0)
        n_tau = round(tau / DT_S)
        for _ in range(20 * n_tau):  # the position is held: same error, same feed-forward
            efforts[name].append(fw.servo_step(DT_S, 0.1, 0.0, force))
    settled = efforts["plain"][-1] / load_gain_ratio(force, True, stall_out, stall_in)
    assert efforts["comp"][-1] == pytest.approx(settled, rel=1e-9)
    # One time constant after the step the filter holds 1 - 1/e of the force.
    k = round(tau / DT_S) - 1
    at_tau = efforts["plain"][k] / load_gain_ratio(
        force * (1.0 - math.exp(-1.0)), True, stall_out, stall_in
    )
    assert efforts["comp"][k] == pytest.approx(at_tau, rel=5e-3)
    with pytest.raises(FirmwareConfigurationError, match="load compensation"):
        DriveParameters.from_rig(Rig(drives=Drives(load_compensation_filter_s=tau)))


def test_overlap_compensation_jumps_the_spool_command_out_of_the_dead_band() -> None:
    """The valve amplifier's jump function against its definition, and in the drive: 0x2100
    (0.01 % of full opening) is commissioned from the rig, written over SDO, checked against its
    range, applied to a valve drive's command and ignored by an electric drive."""
    j = 0.19
    assert overlap_jump(0.0, j) == 0.0
    for u in (0.005, 0.02, 0.3, 1.0):
        assert overlap_jump(u, j) == pytest.approx(j + (1.0 - j) * u, rel=1e-12)
        assert overlap_jump(-u, j) == pytest.approx(-(j + (1.0 - j) * u), rel=1e-12)
    commands = np.linspace(-1.0, 1.0, 4001)
    out = np.array([overlap_jump(float(u), j) for u in commands])
    assert np.all(np.diff(out) > 0.0)  # monotonic, and continuous at the ramp's ends:
    for end in (0.005, -0.005):
        assert overlap_jump(end * (1.0 - 1e-12), j) == pytest.approx(overlap_jump(end, j))
    assert overlap_jump(0.0025, j) == pytest.approx(0.5 * (j + (1.0 - j) * 0.005))

    actuators = Actuators(velocity_max_m_s=0.28, hydraulic=Hydraulic())
    plain = Harness(Rig(actuators=actuators))
    jumped = Harness(Rig(actuators=actuators))
    commissioned = Harness(
        Rig(drives=Drives(valve_overlap_compensation=j), actuators=actuators)
    )
    electric, electric_jumped = Harness(), Harness()
    for h in (plain, jumped, commissioned, electric, electric_jumped):
        h.boot()
    write = ("TX", SDO_RX, "2B002100" + struct.pack("<H", 1900).hex() + "0000")
    for h in (jumped, electric_jumped):
        exchange(h, [write, ("RX", SDO_TX, "6000210000000000")])
    # Beyond the object's range (0..5000): refused, the value kept.
    exchange(jumped, [("TX", SDO_RX, "2B00210089130000"), ("RX", SDO_TX, "8000210030000906")])
    efforts = {}
    for name, h in (("plain", plain), ("jumped", jumped), ("commissioned", commissioned),
                    ("electric", electric), ("electric_jumped", electric_jumped)):  # fmt: skip
        h.enable()
        fw = h.fw
        fw.on_frame(RPDO1, struct.pack("<ii", 100_050, 2_000), 0.0)  # 50 um ahead, 2 mm/s
        fw.on_frame(SYNC, b"", 0.0)
        efforts[name] = fw.servo_step(DT_S, 0.1, 0.0)
    assert 0.005 < efforts["plain"] < 0.1
    assert efforts["jumped"] == pytest.approx(overlap_jump(efforts["plain"], j), rel=1e-12)
    assert efforts["commissioned"] == efforts["jumped"]
    assert efforts["electric_jumped"] == efforts["electric"]


def test_pressure_feedback_takes_off_the_high_passed_force_and_keeps_the_static_stiffness() -> (
    None
):
    """Dynamic pressure feedback against its definition: the valve opening less
    ``gain (F - low-pass(F)) / (p_s A_A)``. A force step acts at once and fades with the
    high-pass, so a held load leaves the opening as it is without the feedback."""
    hyd = Hydraulic()
    actuators = Actuators(velocity_max_m_s=0.28, hydraulic=hyd)
    tau, gain = 0.1, 0.5
    drives = Drives(pressure_feedback_gain=(0.0, gain, 0.0), pressure_feedback_filter_s=tau)
    plain = Harness(Rig(actuators=actuators))
    damped = Harness(Rig(drives=drives, actuators=actuators))  # the harness's axis: stick
    assert damped.fw.reads_load and not damped.fw.load_compensated
    assert not plain.fw.reads_load
    # Per cylinder: the boom's entry is 0, and an axis that is no cylinder gets none.
    for joint in ("boom", "swing"):
        assert not DriveFirmware(NODE, Rig(drives=drives, actuators=actuators), joint).reads_load
    stall_out = hyd.supply_pressure_pa * hyd.piston_area_m2
    for h in (plain, damped):
        h.boot()
        h.enable()  # one servo step with no load: the low-pass starts from an unloaded reading
    force = 30e3
    n = 20 * round(tau / DT_S)
    efforts: dict[str, list[float]] = {"plain": [], "damped": []}
    for name, h in (("plain", plain), ("damped", damped)):
        fw = h.fw
        fw.on_frame(RPDO1, struct.pack("<ii", 100_050, 20_000), 0.0)  # 50 um ahead, 20 mm/s
        fw.on_frame(SYNC, b"", 0.0)
        for _ in range(n):  # the position is held: same error, same feed-forward
            efforts[name].append(fw.servo_step(DT_S, 0.1, 0.0, force))
    taken = np.asarray(efforts["plain"]) - np.asarray(efforts["damped"])
    a = DT_S / (tau + DT_S)
    expected = gain * force / stall_out * (1.0 - a) ** np.arange(1, n + 1)
    np.testing.assert_allclose(taken, expected, rtol=1e-9, atol=1e-12)
    assert taken[0] > 0.1  # a step: taken off at once ...
    assert taken[-1] < 1e-8  # ... and nothing of a held load after 20 time constants
    with pytest.raises(FirmwareConfigurationError, match="pressure feedback"):
        DriveParameters.from_rig(Rig(drives=drives), joint="stick")  # electric
    with pytest.raises(FirmwareConfigurationError, match="pressure feedback"):
        no_filter = replace(drives, pressure_feedback_filter_s=0.0)
        DriveParameters.from_rig(Rig(drives=no_filter, actuators=actuators), joint="stick")


def test_the_excavators_valve_drives_read_the_load() -> None:
    """Load compensation on both excavators' valve drives, pressure feedback on Yang/Pan's
    boom only (its oil column is the one that rings under a hard soil's load)."""
    from rt_runtime.rig import load_rig
    from rt_runtime.rig.loader import profile_names

    excavators = {"field_excavator", "yang_pan_excavator"}
    for name in profile_names():
        rig = load_rig(name)
        for joint in ("boom", "stick", "bucket"):
            fw = DriveFirmware(1, rig, joint)
            assert fw.load_compensated is (name in excavators), (name, joint)
            damped = fw.params.pressure_feedback_gain > 0.0
            assert damped is (name == "yang_pan_excavator" and joint == "boom"), (name, joint)


def test_parameters_from_the_shipped_rigs_and_their_errors() -> None:
    from rt_runtime.rig import load_rig

    scale = load_rig("scale_model")
    fw = DriveFirmware(scale.can.node_id("boom"), scale, "boom")
    assert fw.params.kind is DriveKind.ELECTRIC
    assert fw.read_object(0x6065) == round(scale.drives.following_error_window_m * 1e6)
    assert fw.read_object(0x1016, 1) == (0x7E << 16) | round(scale.drives.heartbeat_timeout_s * 1e3)
    bench = load_rig("test_bench")
    assert DriveFirmware(1, bench, "boom").params.kind is DriveKind.HYDRAULIC
    with pytest.raises(FirmwareConfigurationError, match="hydraulic"):
        DriveFirmware(1, scale, "boom", kind="hydraulic")
    with pytest.raises(FirmwareConfigurationError, match="allowed: electric, hydraulic"):
        DriveParameters.from_rig(scale, kind="pneumatic")
    with pytest.raises(FirmwareConfigurationError, match="position_gain_1_s"):
        DriveParameters.from_rig(Rig(drives=Drives(position_gain_1_s=0.0)))
    with pytest.raises(FirmwareConfigurationError, match="node id 0"):
        DriveFirmware(0, scale, "boom")


def test_lockstep_runs_are_deterministic() -> None:
    def run() -> list[tuple[int, bytes]]:
        h = Harness()
        h.boot()
        h.enable()
        trace = []
        for k in range(300):
            trace += h.cycle(0.1 + 0.02 * math.sin(k * 0.02), 0.02 * 0.02 / PERIOD_S)
        return trace

    assert run() == run()


def test_dataclass_rig_stand_in_is_replaceable() -> None:
    rig = replace(Rig(), drives=replace(Drives(), sync_timeout_s=0.5))
    assert DriveParameters.from_rig(rig).sync_timeout_s == 0.5


# ---------------------------------------------------------------------------------------------
# Pinned trajectory (regression guard for performance work on the servo cascade)
# ---------------------------------------------------------------------------------------------


def _pinned_run(rig: Rig) -> dict[str, list[float]]:
    """Seeded CSP motion, quick stop, re-enable, then a jam that trips the following error.

    The TPDOs of every SYNC enter a checksum, so the frames are pinned too.
    """
    rng = random.Random(4111)
    h = Harness(rig)
    h.boot()
    h.enable()
    amp, omega = rng.uniform(0.005, 0.02), 2.0 * math.pi / rng.uniform(0.3, 0.6)
    frames: list[tuple[int, bytes]] = []
    for k in range(200):
        t = (k + 1) * PERIOD_S
        frames += h.cycle(0.1 + amp * math.sin(omega * t), amp * omega * math.cos(omega * t))
    h.controlword(0x02)
    for _ in range(60):
        frames += h.cycle(None)
    h.controlword(0x06)
    h.controlword(0x07)
    h.controlword(0x0F)
    for _ in range(40):
        frames += h.cycle(h.fw.position_actual_m + rng.uniform(-1e-4, 1e-4))
    h.plant.blocked = True
    target = h.fw.position_actual_m
    for _ in range(80):
        target += 0.2 * PERIOD_S
        frames += h.cycle(target, 0.2)
    checksum = float(sum((i + 1) * sum(data) for i, (_, data) in enumerate(frames)))
    return {
        "efforts": [h.efforts[-1], sum(h.efforts), sum(abs(e) for e in h.efforts)],
        "position_m": [h.fw.position_demand_m, h.fw.position_actual_m, h.plant.position_m],
        "velocity_m_s": [h.fw.velocity_actual_m_s, h.plant.velocity_m_s],
        "words": [float(h.fw.statusword), float(h.fw.state), float(h.fw.last_transition)],
        "emcy": [float(code) for code, _ in h.emcy],
        "frames": [float(len(frames)), checksum],
    }


# Computed with firmware_models/drive.py before its servo path was optimised (issue 7); an
# optimisation may reassociate floating-point sums, nothing more (rtol 1e-9). A behaviour change
# that moves them must recompute them on purpose, in its own commit, with the reason.
PINNED = {
    "electric": {
        "efforts": [0.0, 219.6141448726908, 223.35572686365765],
        "position_m": [0.072277, 0.072277, 0.07227749592793509],
        "velocity_m_s": [1.8842508785434825e-195, 0.0],
        "words": [536.0, 7.0, 14.0],
        "emcy": [34321.0],
        "frames": [392.0, 42455750.0],
    },
    "hydraulic": {
        "efforts": [0.0, 33.19338342074315, 182.9542040201038],
        "position_m": [-0.274101, -0.274101, -0.27410148219341207],
        "velocity_m_s": [-5.593200485150106e-193, 0.0],
        "words": [536.0, 7.0, 14.0],
        "emcy": [34321.0],
        "frames": [384.0, 83466594.0],
    },
}


@pytest.mark.parametrize("kind", ["electric", "hydraulic"])
def test_pinned_trajectory(kind: str) -> None:
    rig = Rig()
    if kind == "hydraulic":
        rig = Rig(actuators=Actuators(velocity_max_m_s=0.28, hydraulic=Hydraulic()))
    got = _pinned_run(rig)
    assert got.keys() == PINNED[kind].keys()
    for key, values in PINNED[kind].items():
        assert got[key] == pytest.approx(values, rel=1e-9, abs=1e-15), key
