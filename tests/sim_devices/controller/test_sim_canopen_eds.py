"""The two EDS files against CiA 306 (read here with configparser, not with the simulator's code) and against
canopen's EDS reader: object lists, sub-index counts, data and access types, default PDO mappings that fit the
objects they name, the predefined connection set's COB-IDs, CiA 402's objects for a profile-position drive."""

from __future__ import annotations

import configparser
import re
from pathlib import Path

import canopen
import pytest
from canopen.objectdictionary import ODArray, ODRecord

from hilcal.protocols.canopen import CIA402_LEG_DRIVE_EDS, HEXAPOD_CONTROLLER_EDS

FILES = [HEXAPOD_CONTROLLER_EDS, CIA402_LEG_DRIVE_EDS]
BITS = {0x1: 1, 0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32, 0x8: 32}
"""CiA 301 basic data types: BOOLEAN, INTEGER8-32, UNSIGNED8-32, REAL32 (bits); 0x9 VISIBLE_STRING, 0xF DOMAIN."""
ACCESS = {"ro", "wo", "rw", "rwr", "rww", "const"}
COUNT_SUB0 = {0x1003} | set(range(0x1600, 0x1604)) | set(range(0x1A00, 0x1A04))
"""Sub-index 0 counts entries (errors, mapped objects) instead of naming the highest sub-index."""


def read(path: Path) -> configparser.ConfigParser:
    eds = configparser.ConfigParser(inline_comment_prefixes=(";",), interpolation=None)
    eds.optionxform = str  # type: ignore[assignment,method-assign]
    eds.read(path)
    return eds


def number(text: str, node_id: int = 0) -> int:
    text = text.replace(" ", "")
    if "$NODEID" in text:
        return int(re.sub(r"\+?\$NODEID\+?", "", text), 0) + node_id
    return int(text, 0)


def objects(eds: configparser.ConfigParser) -> list[int]:
    return sorted(int(s, 16) for s in eds.sections() if re.fullmatch(r"[0-9A-F]{4}", s))


def subs(eds: configparser.ConfigParser, index: int) -> list[int]:
    return sorted(int(m.group(1), 16) for s in eds.sections() if (m := re.fullmatch(f"{index:04X}sub([0-9A-F]+)", s)))


def variable(eds: configparser.ConfigParser, index: int, sub: int) -> configparser.SectionProxy:
    return eds[f"{index:04X}"] if int(eds[f"{index:04X}"].get("ObjectType", "0x7"), 0) == 0x7 else \
        eds[f"{index:04X}sub{sub:X}"]


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_cia306_structure(path: Path) -> None:
    eds = read(path)
    assert eds["FileInfo"]["FileName"] == path.name and eds["FileInfo"]["EDSVersion"] == "4.0"
    listed: list[int] = []
    for group in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        count = int(eds[group]["SupportedObjects"])
        entries = [number(eds[group][str(k)]) for k in range(1, count + 1)]
        assert len(eds[group]) == count + 1
        listed += entries
    assert sorted(listed) == objects(eds) and len(set(listed)) == len(listed)
    mandatory = [number(v) for k, v in eds["MandatoryObjects"].items() if k != "SupportedObjects"]
    manufacturer = [number(v) for k, v in eds["ManufacturerObjects"].items() if k != "SupportedObjects"]
    assert {0x1000, 0x1001, 0x1018} <= set(mandatory)
    assert all(0x2000 <= i <= 0x5FFF for i in manufacturer)
    for index in objects(eds):
        section = eds[f"{index:04X}"]
        kind = int(section.get("ObjectType", "0x7"), 0)
        assert kind in (0x7, 0x8, 0x9), f"{index:04X}"
        members = [(index, 0)] if kind == 0x7 else [(index, s) for s in subs(eds, index)]
        if kind != 0x7:
            assert int(section["SubNumber"], 0) == len(members), f"{index:04X}: SubNumber"
            sub0 = eds[f"{index:04X}sub0"]
            assert int(sub0["DataType"], 0) == 0x5
            if index not in COUNT_SUB0:
                assert number(sub0["DefaultValue"]) == max(s for _, s in members), f"{index:04X}: highest sub-index"
        for i, s in members:
            var = variable(eds, i, s)
            assert int(var["DataType"], 0) in (*BITS, 0x9, 0xF), f"{i:04X}sub{s}"
            assert var["AccessType"] in ACCESS and var["PDOMapping"] in ("0", "1"), f"{i:04X}sub{s}"


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_default_pdos_fit_their_objects(path: Path) -> None:
    eds = read(path)
    node_id = 7
    rx = [i for i in objects(eds) if 0x1400 <= i <= 0x15FF]
    tx = [i for i in objects(eds) if 0x1800 <= i <= 0x19FF]
    assert len(rx) == int(eds["DeviceInfo"]["NrOfRXPDO"]) and len(tx) == int(eds["DeviceInfo"]["NrOfTXPDO"])
    for comm, base, writable in [(i, 0x200, True) for i in rx] + [(i, 0x180, False) for i in tx]:
        n = comm & 0xFF
        assert number(eds[f"{comm:04X}sub1"]["DefaultValue"], node_id) & 0x7FF == base + 0x100 * n + node_id
        mapping = comm + 0x200
        count = number(eds[f"{mapping:04X}sub0"]["DefaultValue"])
        bits = 0
        for k in range(1, count + 1):
            entry = number(eds[f"{mapping:04X}sub{k:X}"]["DefaultValue"])
            target = variable(eds, entry >> 16, (entry >> 8) & 0xFF)
            assert target["PDOMapping"] == "1" and BITS[int(target["DataType"], 0)] == entry & 0xFF
            assert ("w" in target["AccessType"]) if writable else ("r" in target["AccessType"])
            bits += entry & 0xFF
        assert bits <= 64


def test_leg_drive_has_cia402_profile_position_objects() -> None:
    eds = read(CIA402_LEG_DRIVE_EDS)
    assert number(eds["1000"]["DefaultValue"]) & 0xFFFF == 402
    assert {0x603F, 0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x607A, 0x607C, 0x6081, 0x6083, 0x6084, 0x608F, 0x6091,
            0x6092, 0x6502} <= set(objects(eds))
    assert number(eds["6502"]["DefaultValue"]) & 0x1  # profile position supported


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_canopen_reads_every_object(path: Path) -> None:
    eds = read(path)
    od = canopen.import_od(str(path), 3)
    for index in objects(eds):
        obj = od[index]
        expected = subs(eds, index)
        if isinstance(obj, ODRecord | ODArray):
            assert sorted(obj.subindices) == expected
        else:
            assert not expected
