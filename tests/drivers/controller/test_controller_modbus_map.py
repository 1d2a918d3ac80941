"""Register map files: the default map against the register table of docs/protocols.md, every kind of bad map refused
with the key named and nothing sent, the station's ``[modbus] map`` key, and the driver's word orders against
pymodbus's own register conversion and ``struct``.
"""

from __future__ import annotations

import copy
import re
import socket
import struct
import tomllib
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from drivers.controller.modbus import ControllerParams, ParameterSet
from drivers.controller.modbus_codec import decode, encode
from hilcal.protocols.modbus_map import (
    DEFAULT_MAP,
    RegisterMapError,
    built_in_maps,
    load_register_map,
    register_map_from_dict,
)
from hilcal.robot import Robot
from procedures.station import StationConfigError, station_from_dict
from sim_devices.controller.modbus_server import ModbusTcpServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[3]
DEFAULT_FILE = ROOT / "hilcal" / "protocols" / "modbus_maps" / "hilcal-1.1.toml"
EXAMPLE_FILE = ROOT / "examples" / "modbus_maps" / "hexapod-cdab.toml"
DEFAULT = tomllib.loads(DEFAULT_FILE.read_text())

DOC_NAMES = {
    "MAGIC": "identity.magic.address", "PROTOCOL_VERSION": "identity.protocol_version.address",
    "FIRMWARE_VERSION": "identity.firmware_version.address", "SERIAL_NUMBER": "identity.serial_number.address",
    "CAPABILITIES": "identity.capabilities.address", "PARAMETER_COUNT": "identity.parameter_count.address",
    "CONTROLLER_STATE": "state.address", "FAULT_CODE": "fault_code.address", "PARAM_COMMAND": "commands.address",
    "PARAM_STATUS": "status.address", "COMMIT_COUNTER": "diagnostics.commit_counter.address",
    "SAVE_COUNTER": "diagnostics.save_counter.address", "STAGED_WRITTEN": "diagnostics.staged_written.address",
    "LIVE_CRC32": "checksum.live", "BACKUP_CRC32": "checksum.backup", "SAVED_CRC32": "checksum.saved",
    "STAGED_LENGTH": "staging.length", "STAGED_CRC32": "checksum.staged",
    "STAGED_COMP_CRC32": "compensation.checksum.staged", "LIVE_COMP_CRC32": "compensation.checksum.live",
    "BACKUP_COMP_CRC32": "compensation.checksum.backup", "SAVED_COMP_CRC32": "compensation.checksum.saved",
    "LEG_FORCES": "sensors.leg_forces_kn.address", "LEG_TEMPERATURE": "sensors.temperature_c.address",
    "LIVE": "geometry.a.live", "STAGING": "geometry.a.staging", "BACKUP": "geometry.a.backup",
    "SAVED": "geometry.a.saved", "COMP_LIVE": "compensation.live", "COMP_STAGING": "compensation.staging",
    "COMP_BACKUP": "compensation.backup", "COMP_SAVED": "compensation.saved",
}


def at(data: dict[str, Any], path: str) -> Any:
    for key in path.split("."):
        data = data[key]
    return data


def test_the_default_map_file_is_the_register_table_of_the_protocol_doc() -> None:
    text = (ROOT / "docs" / "protocols.md").read_text()
    rows = dict(re.findall(r"^\| (0x[0-9A-F]{4}) \| +\d+ \| ([A-Z_0-9]+) \|", text, re.MULTILINE))
    table = {name: int(address, 16) for address, name in rows.items()}
    assert set(table) == set(DOC_NAMES)
    assert {name: at(DEFAULT, path) for name, path in DOC_NAMES.items()} == table
    for bank in ("live", "staging", "backup", "saved"):  # a, b, l0 follow one another: 84 registers per bank
        assert at(DEFAULT, f"geometry.b.{bank}") == at(DEFAULT, f"geometry.a.{bank}") + 36
        assert at(DEFAULT, f"geometry.l0.{bank}") == at(DEFAULT, f"geometry.a.{bank}") + 72
    assert DEFAULT["geometry"]["type"] == "f32" and DEFAULT["device"]["word_order"] == "ABCD"
    assert DEFAULT["commands"] | {"address": 0} == {"address": 0, "open_staging": 1, "commit": 2, "rollback": 3,
                                                    "save": 4}
    assert built_in_maps() == [DEFAULT_MAP] and load_register_map(DEFAULT_MAP).device.name == DEFAULT_MAP


def bad(change: Any) -> str:
    data = copy.deepcopy(DEFAULT)
    change(data)
    with pytest.raises(RegisterMapError) as info:
        register_map_from_dict(data, "test map")
    return str(info.value)


@pytest.mark.parametrize(("change", "expected"), [
    (lambda d: d["geometry"]["b"].update(live=0x0120),
     "geometry.b.live (0x0120..0x0143) overlaps geometry.a.live (0x0100..0x0123)"),
    (lambda d: d["diagnostics"].update(extra={"address": 0x0029}), "overlaps checksum.live"),
    (lambda d: d["geometry"]["l0"].update(type="f16"), "geometry.l0.type: Input should be 'u16'"),
    (lambda d: d["identity"]["magic"].update(type="u8"), "identity.magic.type"),
    (lambda d: d["commands"].pop("commit"), 'commands.commit: transaction = "staged" needs the commit command'),
    (lambda d: d.pop("status"), 'status: transaction = "staged" needs a [status] register'),
    (lambda d: d.pop("commands"), 'commands.open_staging: transaction = "staged" needs the open_staging command'),
    (lambda d: d["geometry"]["b"].pop("backup"), "geometry.b.backup: the rollback command needs"),
    (lambda d: d["geometry"]["a"].pop("staging"), "geometry.a.staging: transaction = \"staged\" needs"),
    (lambda d: d["device"].update(transaction="direct"), 'commands.open_staging: transaction = "direct" has no'),
    (lambda d: d["state"].update(enabled=0), "state: enabled and disabled share the value 0x0"),
    (lambda d: d["geometry"].pop("b"), "a device holds a and b together"),
    (lambda d: d["geometry"]["a"].update(address=0x100), "geometry.a.address: Extra inputs are not permitted"),
    (lambda d: d["identity"]["magic"].update(expect=0x12345), "does not fit a u16"),
    (lambda d: d["device"].update(max_read_registers=200), "device.max_read_registers"),
    (lambda d: d["compensation"].update(live=0xF800), "compensation.live: 0xF800 + 3160 registers runs past"),
])
def test_a_bad_map_is_refused_naming_the_key(change: Any, expected: str) -> None:
    assert expected in bad(change)


def test_a_map_that_cannot_be_read_is_named(tmp_path: Path) -> None:
    with pytest.raises(RegisterMapError, match=r"neither a built-in map \(hilcal-1.1\) nor a readable file"):
        load_register_map("hilcal-9.9")
    broken = tmp_path / "broken.toml"
    broken.write_text("format = 1\n[device\n")
    with pytest.raises(RegisterMapError, match="not valid TOML"):
        load_register_map(broken)


def test_nothing_is_sent_to_a_device_with_an_invalid_map(robot: Robot, tmp_path: Path) -> None:
    path = tmp_path / "overlap.toml"
    path.write_text(DEFAULT_FILE.read_text().replace("live = 0x0124", "live = 0x0120"))
    controller = SimulatedController(robot, SimulatedRig(robot, RigConfig(seed=1, errors=GeometryErrors.zero())),
                                     ControllerSimConfig())
    with ModbusTcpServer(controller).start() as server:
        with pytest.raises(RegisterMapError, match=r"geometry\.b\.live"):
            ControllerParams("127.0.0.1", server.port, register_map=path)
        assert server.connections_accepted == 0 and server.protocol.requests == 0


def test_a_map_holding_the_leg_offsets_alone_needs_the_nominal_set(robot: Robot) -> None:
    data = tomllib.loads(EXAMPLE_FILE.read_text())
    for part in ("a", "b"):
        del data["geometry"][part]
    offsets_only = register_map_from_dict(data)
    assert offsets_only.held_values() == 6
    with pytest.raises(ValueError, match="leg offsets alone: give nominal="):
        ControllerParams("127.0.0.1", 1, register_map=offsets_only)


STATION = {"can": {"interface": "virtual", "channel": "x"}, "cmm": {"url": "loop://", "alignment": [0, 0, 0, 0, 0, 0]}}


def test_the_station_names_its_map(robot: Robot, tmp_path: Path) -> None:
    station = station_from_dict({**STATION, "modbus": {"host": "10.0.0.7"}})
    assert station.modbus.map is None and station.modbus.register_map().device.name == DEFAULT_MAP
    station = station_from_dict({**STATION, "modbus": {"host": "10.0.0.7", "map": str(EXAMPLE_FILE)}})
    assert station.modbus.register_map().device.name == "hexapod-cdab"
    params = station.modbus.open_params(ParameterSet.from_robot(robot))
    assert params.map.device.transaction == "direct" and params.endpoint == "tcp://10.0.0.7:502"
    params.close()
    wrong = tmp_path / "wrong.toml"
    wrong.write_text(EXAMPLE_FILE.read_text().replace('type = "i32"', 'type = "i24"'))
    with pytest.raises(StationConfigError, match=r"modbus.map: register map .*wrong.toml: 1 problem\(s\)"):
        station_from_dict({**STATION, "modbus": {"host": "10.0.0.7", "map": str(wrong)}})


TYPES = {"u16": (ModbusTcpClient.DATATYPE.UINT16, [0, 1, 0xBEEF, 0xFFFF]),
         "i16": (ModbusTcpClient.DATATYPE.INT16, [-32768, -2, 0, 32767]),
         "u32": (ModbusTcpClient.DATATYPE.UINT32, [0, 0x12345678, 0xFFFFFFFF]),
         "i32": (ModbusTcpClient.DATATYPE.INT32, [-2**31, -1234567, 3_800_123]),
         "f32": (ModbusTcpClient.DATATYPE.FLOAT32, [1.0, -1394.7, 3800.0, 1e-20]),
         "f64": (ModbusTcpClient.DATATYPE.FLOAT64, [1.0, -1394.7, 2049.3000000001])}


@pytest.mark.parametrize("type_", list(TYPES))
def test_word_orders_agree_with_pymodbus_and_struct(type_: str) -> None:
    datatype, values = TYPES[type_]
    fmt = {"u16": "H", "i16": "h", "u32": "I", "i32": "i", "f32": "f", "f64": "d"}[type_]
    for v in values:
        abcd = ModbusTcpClient.convert_to_registers(v, datatype, word_order="big")
        assert encode([v], type_, "ABCD") == abcd
        wide = len(abcd) > 1
        assert encode([v], type_, "CDAB") == ModbusTcpClient.convert_to_registers(v, datatype, word_order="little")
        little = list(struct.unpack(f">{len(abcd)}H", struct.pack(f"<{fmt}", v)))
        assert encode([v], type_, "DCBA") == (little if wide else abcd)
        swapped = [((w & 0xFF) << 8) | (w >> 8) for w in abcd]
        assert encode([v], type_, "BADC") == (swapped if wide else abcd)
        for order in ("ABCD", "CDAB", "BADC", "DCBA"):
            back = decode(encode([v], type_, order), type_, order)[0]
            assert back == (np.float32(v) if type_ == "f32" else v)
    with pytest.raises(ValueError, match="does not fit"):
        encode([float("inf") if type_.startswith("f") else 2**64], type_, "ABCD")


def test_describe_is_what_hilcal_check_shows(robot: Robot) -> None:
    controller = SimulatedController(robot, SimulatedRig(robot, RigConfig(seed=1, errors=GeometryErrors.zero())),
                                     ControllerSimConfig(serial_number=4711))
    with ModbusTcpServer(controller).start() as server, ControllerParams("127.0.0.1", server.port) as params:
        described = params.describe()
        raw = ModbusTcpClient("127.0.0.1", port=server.port, timeout=1.0, retries=0)
        live = raw.read_holding_registers(0x0100, count=84, device_id=1).registers
        counters = raw.read_holding_registers(0x0022, count=3, device_id=1).registers  # docs/protocols.md
        fault = raw.read_holding_registers(0x0011, count=1, device_id=1).registers[0]
        raw.close()
        assert server.writes == []
    crc = f"{zlib.crc32(struct.pack('>84H', *live)):08x}"
    assert described["identity"]["serial_number"] == 4711 and described["state"] == "DISABLED"
    assert described["geometry"]["crc32"] == described["geometry"]["checksum_register"] == crc
    assert described["geometry"]["checksum_match"] is True and described["map"] == DEFAULT_MAP
    assert described["registers"] == dict(zip(("commit_counter", "save_counter", "staged_written"), counters,
                                              strict=True)) | {"fault_code": fault}
    np.testing.assert_array_equal(ParameterSet.model_validate(described["geometry"]["set"]).to_vector(),
                                  np.asarray(struct.unpack(">42f", struct.pack(">84H", *live)), dtype=float))
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        dead = s.getsockname()[1]
    with ControllerParams("127.0.0.1", dead, timeout_s=0.5) as params:
        described = params.describe()
    assert described["identity_error"].startswith("ModbusTransportError: read identity at 0x0000")
    assert described["geometry_error"] == "ModbusTransportError: not read: the link failed reading identity"
