"""PDO and SYNC codecs: precompiled structs, COB-IDs, and their check against the EDS.

Role: the per-cycle frame layouts of the master (CiA 301 pre-defined connection set, DESIGN.md
"CAN protocol"). Each PDO is one :class:`PdoSpec`: its communication and mapping objects, its
COB-ID base, its transmission type, the objects it maps and a precompiled :class:`struct.Struct`
for the payload. The loop packs with ``pack_into`` straight into a preallocated ``bytearray``
(a reused :class:`can.Message`'s ``data``), so a cycle allocates nothing here.

The codecs are written by hand because they are the product's hot path; the EDS stays the
authority: :func:`check_pdo_mapping` rebuilds each layout from the EDS mapping objects (0x1600,
0x1601, 0x1A00, 0x1A01) and the data types of the mapped objects, and raises when they differ,
so a changed EDS fails loudly at start-up instead of garbling frames.

Payloads (little endian)::

    RPDO1 0x200+id  <ii   0x607A target position (um), 0x60B1 velocity offset (um/s)
    RPDO2 0x300+id  <Hb   0x6040 controlword, 0x6060 modes of operation
    TPDO1 0x180+id  <ii   0x6064 position actual (um), 0x606C velocity actual (um/s)
    TPDO2 0x280+id  <HbH  0x6041 statusword, 0x6061 modes display, 0x603F error code
    SYNC  0x080     (no data)

Transmission types (comm sub 2; the master writes them at boot, the EDS defaults agree):

* RPDO1, type 1 (synchronous): the drive buffers it and applies it at the next SYNC.
* RPDO2, type 0xFF (event driven): applied on receipt, so a controlword acts before the SYNC.
* TPDO1, type 1: sent at every SYNC, sampled at the SYNC.
* TPDO2, type 0 (synchronous acyclic, CiA 301): sent at a SYNC only when its content (statusword,
  modes display, error code) differs from the last TPDO2 the drive sent. CiA 301 does not say
  whether entering OPERATIONAL counts as a change: the drive model (``DriveFirmware``) sends it at
  the first SYNC after every NMT start by default, and with ``tpdo_at_start=False`` only after a
  change, as other drives may. The master therefore never waits for a TPDO2: it reads the same
  objects by SDO before enabling and again during enable when no TPDO2 came for a few SYNCs
  (:meth:`~rt_runtime.canbus.master.CanMaster.enable`).

The statusword changes a few times per enable or fault, so type 0 takes 3 x 5-byte frames per
period off the bus (design notes, C1) while a state change is still reported at the SYNC that
follows it; a drive that stops talking is caught by TPDO1 staleness and the heartbeat consumer,
not by TPDO2.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING

import can
from canopen.objectdictionary import ODVariable

from rt_runtime.errors import ConfigurationError

if TYPE_CHECKING:
    from canopen.objectdictionary import ObjectDictionary

__all__ = [
    "COB_EMCY",
    "COB_HEARTBEAT",
    "COB_NMT",
    "COB_RPDO1",
    "COB_RPDO2",
    "COB_SDO_RX",
    "COB_SDO_TX",
    "COB_SYNC",
    "COB_TPDO1",
    "COB_TPDO2",
    "PDOS",
    "RPDO1",
    "RPDO2",
    "TPDO1",
    "TPDO2",
    "PdoSpec",
    "check_pdo_mapping",
    "cob_id",
    "function_code",
    "node_of",
    "od_default",
    "od_variable",
    "pdo_message",
    "sync_message",
]

# CiA 301 pre-defined connection set: COB-ID = function code + node id.
COB_NMT = 0x000
COB_SYNC = 0x080
COB_EMCY = 0x080
COB_TPDO1 = 0x180
COB_RPDO1 = 0x200
COB_TPDO2 = 0x280
COB_RPDO2 = 0x300
COB_SDO_TX = 0x580  # server -> client (drive answers)
COB_SDO_RX = 0x600  # client -> server (master requests)
COB_HEARTBEAT = 0x700

_NODE_MASK = 0x07F
_FUNCTION_MASK = 0x780

# CiA 301 data type codes of the objects a PDO may map here, and their struct letters.
_STRUCT_LETTER = {
    0x0002: "b",  # INTEGER8
    0x0003: "h",  # INTEGER16
    0x0004: "i",  # INTEGER32
    0x0005: "B",  # UNSIGNED8
    0x0006: "H",  # UNSIGNED16
    0x0007: "I",  # UNSIGNED32
}


@dataclass(frozen=True, slots=True)
class PdoSpec:
    """One PDO: where it is configured, what it maps, and its payload codec.

    Attributes:
        name: ``RPDO1`` ...
        comm_index: Communication parameter object (0x1400.., 0x1800..).
        mapping_index: Mapping object (0x1600.., 0x1A00..).
        cob_base: COB-ID without the node id.
        transmission_type: 1 = synchronous on every SYNC, 0 = synchronous acyclic (a TPDO
            sent at a SYNC when its content changed), 0xFF = event driven (applied on receipt
            for an RPDO).
        entries: Mapped objects as (index, subindex, bit length).
        codec: Precompiled little-endian payload struct.
    """

    name: str
    comm_index: int
    mapping_index: int
    cob_base: int
    transmission_type: int
    entries: tuple[tuple[int, int, int], ...]
    codec: struct.Struct

    @property
    def size(self) -> int:
        """Payload length in bytes."""
        return self.codec.size

    def mapping_values(self) -> tuple[int, ...]:
        """u32 values of the mapping object's sub-indices 1.. (index << 16 | sub << 8 | bits)."""
        return tuple(index << 16 | sub << 8 | bits for index, sub, bits in self.entries)

    def cob_id(self, node_id: int) -> int:
        """COB-ID of this PDO for ``node_id``."""
        return self.cob_base + node_id


RPDO1 = PdoSpec(
    "RPDO1", 0x1400, 0x1600, COB_RPDO1, 1, ((0x607A, 0, 32), (0x60B1, 0, 32)), struct.Struct("<ii")
)
RPDO2 = PdoSpec(
    "RPDO2",
    0x1401,
    0x1601,
    COB_RPDO2,
    0xFF,
    ((0x6040, 0, 16), (0x6060, 0, 8)),
    struct.Struct("<Hb"),
)
TPDO1 = PdoSpec(
    "TPDO1", 0x1800, 0x1A00, COB_TPDO1, 1, ((0x6064, 0, 32), (0x606C, 0, 32)), struct.Struct("<ii")
)
TPDO2 = PdoSpec(
    "TPDO2",
    0x1801,
    0x1A01,
    COB_TPDO2,
    0,
    ((0x6041, 0, 16), (0x6061, 0, 8), (0x603F, 0, 16)),
    struct.Struct("<HbH"),
)
#: Every PDO the master configures, in configuration order.
PDOS: tuple[PdoSpec, ...] = (RPDO1, RPDO2, TPDO1, TPDO2)


def cob_id(function: int, node_id: int) -> int:
    """COB-ID of a function code (``COB_*``) for ``node_id`` (1..127)."""
    return function + node_id


def function_code(can_id: int) -> int:
    """Function code part (bits 7-10) of an 11-bit COB-ID."""
    return can_id & _FUNCTION_MASK


def node_of(can_id: int) -> int:
    """Node id part (bits 0-6) of an 11-bit COB-ID."""
    return can_id & _NODE_MASK


def pdo_message(spec: PdoSpec, node_id: int) -> can.Message:
    """A reusable message for ``spec`` with a zeroed payload of the right length.

    The loop packs into ``message.data`` with ``spec.codec.pack_into`` and sends the same object
    every cycle (python-can's buses copy or serialise the data on send).
    """
    return can.Message(
        arbitration_id=spec.cob_id(node_id), is_extended_id=False, data=bytearray(spec.size)
    )


def sync_message() -> can.Message:
    """The SYNC frame (0x080, no data; no SYNC counter, 0x1019 = 0)."""
    return can.Message(arbitration_id=COB_SYNC, is_extended_id=False, data=bytearray())


def od_variable(od: ObjectDictionary, index: int, subindex: int) -> ODVariable:
    """The EDS variable at ``index``/``subindex`` (a plain variable is sub-index 0).

    Raises:
        ConfigurationError: The EDS has no such object.
    """
    try:
        obj = od[index]
        var = obj if isinstance(obj, ODVariable) else obj[subindex]
    except KeyError as exc:
        raise ConfigurationError(
            f"the EDS has no object 0x{index:04X} sub {subindex}, which the master needs"
        ) from exc
    if var.subindex != subindex and isinstance(obj, ODVariable):
        raise ConfigurationError(
            f"EDS object 0x{index:04X} is a plain variable and has no sub-index {subindex}"
        )
    return var


def od_default(od: ObjectDictionary, index: int, subindex: int) -> int:
    """Integer default value of an EDS variable (``$NODEID`` already substituted).

    Raises:
        ConfigurationError: The object is missing or has no integer default.
    """
    var = od_variable(od, index, subindex)
    value = var.default
    if not isinstance(value, int):
        raise ConfigurationError(
            f"EDS object 0x{index:04X} sub {subindex} ({var.name}) has no integer default value"
        )
    return value


def check_pdo_mapping(od: ObjectDictionary, node_id: int) -> None:
    """Check that the EDS's PDO objects match the hand-written codecs exactly.

    For each PDO: the COB-ID (bits 0-10 of comm sub 1) is ``cob_base + node_id``, the
    transmission type (comm sub 2) matches, the mapping object lists the same objects with the
    same bit lengths in the same order, and the struct built from the mapped objects' data types
    equals the codec's format.

    Args:
        od: Object dictionary imported with ``canopen.objectdictionary.import_od(eds, node_id)``.
        node_id: The node id the EDS was imported for.

    Raises:
        ConfigurationError: Naming the PDO, the object and what differs.
    """
    for spec in PDOS:
        cob = od_default(od, spec.comm_index, 1) & 0x7FF
        if cob != spec.cob_id(node_id):
            raise ConfigurationError(
                f"{spec.name}: EDS 0x{spec.comm_index:04X} sub 1 COB-ID is 0x{cob:03X}, the "
                f"codec expects 0x{spec.cob_id(node_id):03X} (0x{spec.cob_base:03X} + node id)"
            )
        ttype = od_default(od, spec.comm_index, 2)
        if ttype != spec.transmission_type:
            raise ConfigurationError(
                f"{spec.name}: EDS 0x{spec.comm_index:04X} sub 2 transmission type is "
                f"0x{ttype:02X}, the master expects 0x{spec.transmission_type:02X}"
            )
        count = od_default(od, spec.mapping_index, 0)
        mapped = tuple(od_default(od, spec.mapping_index, sub) for sub in range(1, count + 1))
        if mapped != spec.mapping_values():
            got = ", ".join(f"0x{v:08X}" for v in mapped)
            want = ", ".join(f"0x{v:08X}" for v in spec.mapping_values())
            raise ConfigurationError(
                f"{spec.name}: EDS 0x{spec.mapping_index:04X} maps [{got}], the codec "
                f"{spec.codec.format!r} expects [{want}]"
            )
        letters = []
        for index, sub, bits in spec.entries:
            data_type = od_variable(od, index, sub).data_type
            letter = _STRUCT_LETTER.get(data_type or 0)
            if data_type is None or letter is None or struct.calcsize(letter) * 8 != bits:
                raise ConfigurationError(
                    f"{spec.name}: mapped object 0x{index:04X} sub {sub} has data type "
                    f"0x{data_type or 0:04X}, which does not fit {bits} bits of an integer"
                )
            letters.append(letter)
        fmt = "<" + "".join(letters)
        if fmt != spec.codec.format:
            raise ConfigurationError(
                f"{spec.name}: the EDS data types give the layout {fmt!r}, the codec is "
                f"{spec.codec.format!r}"
            )
