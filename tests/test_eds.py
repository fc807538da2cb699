"""The drive EDS: valid CiA 306, read by canopen, and exactly the objects of the CAN contract."""

from __future__ import annotations

import configparser
import re

import pytest
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, import_od

from firmware_models import CIA402_DRIVE_EDS
from firmware_models.drive import load_object_dictionary
from firmware_models.errors import FirmwareConfigurationError

I8, I16, I32, U8, U16, U32, VS = 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x9

# (index, subindex): (data type, access, default with node id 0 for $NODEID, pdo mappable)
# written from the contract (issue 6, "Object dictionary"), independently of the EDS.
CONTRACT: dict[tuple[int, int], tuple[int, str, int | str | None, bool]] = {
    (0x1000, 0): (U32, "ro", 0x00020192, False),
    (0x1001, 0): (U8, "ro", 0, True),
    (0x1006, 0): (U32, "rw", None, False),
    (0x1008, 0): (VS, "const", None, False),
    (0x1014, 0): (U32, "rw", 0x80, False),
    (0x1016, 0): (U8, "ro", 1, False),
    (0x1016, 1): (U32, "rw", None, False),
    (0x1017, 0): (U16, "rw", None, False),
    (0x1018, 0): (U8, "ro", 4, False),
    (0x1018, 1): (U32, "ro", None, False),
    (0x1018, 2): (U32, "ro", None, False),
    (0x1018, 3): (U32, "ro", None, False),
    (0x1018, 4): (U32, "ro", None, False),
    (0x1400, 1): (U32, "rw", 0x200, False),
    (0x1400, 2): (U8, "rw", 1, False),
    (0x1401, 1): (U32, "rw", 0x300, False),
    (0x1401, 2): (U8, "rw", 0xFF, False),
    (0x1600, 0): (U8, "rw", 2, False),
    (0x1600, 1): (U32, "rw", 0x607A0020, False),
    (0x1600, 2): (U32, "rw", 0x60B10020, False),
    (0x1601, 0): (U8, "rw", 2, False),
    (0x1601, 1): (U32, "rw", 0x60400010, False),
    (0x1601, 2): (U32, "rw", 0x60600008, False),
    (0x1800, 1): (U32, "rw", 0x180, False),
    (0x1800, 2): (U8, "rw", 1, False),
    (0x1801, 1): (U32, "rw", 0x280, False),
    (0x1801, 2): (U8, "rw", 0, False),  # synchronous acyclic: on change
    (0x1A00, 0): (U8, "rw", 2, False),
    (0x1A00, 1): (U32, "rw", 0x60640020, False),
    (0x1A00, 2): (U32, "rw", 0x606C0020, False),
    (0x1A01, 0): (U8, "rw", 3, False),
    (0x1A01, 1): (U32, "rw", 0x60410010, False),
    (0x1A01, 2): (U32, "rw", 0x60610008, False),
    (0x1A01, 3): (U32, "rw", 0x603F0010, False),
    (0x2100, 0): (U16, "rw", 0, False),  # valve overlap compensation, 0.01 % of opening
    (0x603F, 0): (U16, "ro", None, True),
    (0x6040, 0): (U16, "rw", None, True),
    (0x6041, 0): (U16, "ro", None, True),
    (0x605A, 0): (I16, "rw", 2, False),
    (0x605E, 0): (I16, "rw", 2, False),
    (0x6060, 0): (I8, "rw", None, True),
    (0x6061, 0): (I8, "ro", None, True),
    (0x6062, 0): (I32, "ro", None, True),
    (0x6064, 0): (I32, "ro", None, True),
    (0x6065, 0): (U32, "rw", None, False),
    (0x6066, 0): (U16, "rw", None, False),
    (0x606C, 0): (I32, "ro", None, True),
    (0x607A, 0): (I32, "rw", None, True),
    (0x607D, 1): (I32, "rw", None, False),
    (0x607D, 2): (I32, "rw", None, False),
    (0x6085, 0): (U32, "rw", None, False),
    (0x60B1, 0): (I32, "rw", None, True),
    (0x60C2, 1): (U8, "rw", None, False),
    (0x60C2, 2): (I8, "rw", None, False),
    (0x6502, 0): (U32, "ro", None, False),
}
CONTRACT_INDICES = sorted({index for index, _ in CONTRACT})
COB_DEFAULTS = {(0x1014, 0): 0x80, (0x1400, 1): 0x200, (0x1401, 1): 0x300, (0x1800, 1): 0x180,
                (0x1801, 1): 0x280}  # fmt: skip


def _raw_eds() -> configparser.RawConfigParser:
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",))
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read(CIA402_DRIVE_EDS)
    return parser


def _variables(node_id: int) -> dict[tuple[int, int], ODVariable]:
    od = import_od(str(CIA402_DRIVE_EDS), node_id)
    out: dict[tuple[int, int], ODVariable] = {}
    for index in od:
        obj = od[index]
        if isinstance(obj, (ODRecord, ODArray)):
            for sub, var in obj.subindices.items():
                out[(index, sub)] = var
        else:
            out[(index, 0)] = obj
    return out


def test_objects_are_exactly_the_contracts() -> None:
    od = import_od(str(CIA402_DRIVE_EDS), 1)
    assert sorted(od) == CONTRACT_INDICES
    variables = _variables(1)
    # Records and arrays may carry more sub-indices (sub 0, unused mapping entries), never other
    # objects; every contract entry is there.
    assert set(CONTRACT) <= set(variables)
    extra = {key for key in variables if key not in CONTRACT}
    assert all(key[1] == 0 or key[0] in (0x1600, 0x1601, 0x1A00, 0x1A01) for key in extra), sorted(
        extra
    )


@pytest.mark.parametrize("node_id", [1, 2, 3, 127])
def test_entries_match_the_contract_with_nodeid_substituted(node_id: int) -> None:
    variables = _variables(node_id)
    for key, (data_type, access, default, mappable) in CONTRACT.items():
        var = variables[key]
        where = f"0x{key[0]:04X} sub {key[1]}"
        assert var.data_type == data_type, where
        assert var.access_type == access, where
        assert var.pdo_mappable == mappable, where
        if default is not None:
            expected = default + node_id if key in COB_DEFAULTS else default
            assert var.default == expected, where
    assert variables[(0x1000, 0)].default == 0x00020192  # servo drive, CiA 402
    assert variables[(0x6502, 0)].default & 0x80  # bit 7: cyclic synchronous position


def test_unused_mapping_entries_are_zero_and_mapping_fits_a_frame() -> None:
    variables = _variables(1)
    for mapping in (0x1600, 0x1601, 0x1A00, 0x1A01):
        count = variables[(mapping, 0)].default
        assert isinstance(count, int)
        bits = sum(int(variables[(mapping, s)].default or 0) & 0xFF for s in range(1, count + 1))
        assert bits <= 64
        for sub in range(count + 1, 9):
            assert variables[(mapping, sub)].default == 0
        for sub in range(1, count + 1):
            entry = int(variables[(mapping, sub)].default or 0)
            mapped = variables[(entry >> 16, (entry >> 8) & 0xFF)]
            assert mapped.pdo_mappable
            assert len(mapped) == entry & 0xFF  # bit length of the data type


def test_cia306_structure() -> None:
    eds = _raw_eds()
    for section in ("FileInfo", "DeviceInfo", "MandatoryObjects", "OptionalObjects",
                    "ManufacturerObjects", "Comments"):  # fmt: skip
        assert eds.has_section(section), section
    assert eds.get("FileInfo", "EDSVersion") == "4.0"
    assert int(eds.get("DeviceInfo", "NrOfRXPDO")) == 2
    assert int(eds.get("DeviceInfo", "NrOfTXPDO")) == 2
    assert eds.get("DeviceInfo", "BaudRate_1000") == "1"
    listed: list[int] = []
    for group in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        count = int(eds.get(group, "SupportedObjects"))
        entries = [int(eds.get(group, str(n)), 0) for n in range(1, count + 1)]
        assert len(eds.options(group)) == count + 1
        listed += entries
    assert sorted(listed) == CONTRACT_INDICES
    assert [int(eds.get("MandatoryObjects", str(n)), 0) for n in (1, 2, 3)] == [
        0x1000,
        0x1001,
        0x1018,
    ]
    object_sections = [s for s in eds.sections() if re.fullmatch(r"[0-9A-F]{4}", s)]
    assert sorted(int(s, 16) for s in object_sections) == CONTRACT_INDICES
    for section in object_sections:
        object_type = int(eds.get(section, "ObjectType"), 0)
        if object_type == 0x7:
            subs = [section]
        else:
            assert object_type in (0x8, 0x9), section
            subs = [s for s in eds.sections() if s.startswith(section + "sub")]
            assert int(eds.get(section, "SubNumber")) == len(subs), section
        for sub in subs:
            for key in ("ParameterName", "ObjectType", "DataType", "AccessType", "DefaultValue",
                        "PDOMapping"):  # fmt: skip
                assert eds.has_option(sub, key), f"{sub} lacks {key}"


def test_flat_table_and_its_errors() -> None:
    table = load_object_dictionary(2)
    assert table[(0x1800, 1)].default == 0x182
    assert table[(0x1008, 0)].codec is None
    assert table[(0x6064, 0)].codec is not None and table[(0x6064, 0)].codec.format == "<i"
    assert load_object_dictionary(2) is table  # cached
    with pytest.raises(FirmwareConfigurationError, match=r"outside 1\.\.127"):
        load_object_dictionary(0)
    with pytest.raises(FirmwareConfigurationError, match="does not exist"):
        load_object_dictionary(1, "/nonexistent/drive.eds")
