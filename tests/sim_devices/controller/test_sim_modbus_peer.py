"""The simulated controller read by a Modbus client that is not ours: pyModbusTCP, guided by the default map file's
text (read with ``tomllib``) and decoding with its own helpers (``word_list_to_long``, ``decode_ieee``): identity,
state, the live geometry in the map's types and word order and its CRC-32 register, equal to what our driver reads.
The simulator also serves a map at other addresses, and refuses one it cannot serve.
"""

from __future__ import annotations

import struct
import tomllib
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pyModbusTCP.client import ModbusClient
from pyModbusTCP.utils import decode_ieee, word_list_to_long

from drivers.controller.modbus import ControllerParams
from hilcal.protocols.toml_text import toml_lines
from hilcal.robot import Robot
from sim_devices.controller.modbus_protocol import ControllerRegisterMap
from sim_devices.controller.modbus_server import ModbusTcpServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[3]
DEFAULT_MAP = ROOT / "hilcal" / "protocols" / "modbus_maps" / "hilcal-1.1.toml"
SPEC = tomllib.loads(DEFAULT_MAP.read_text())
LENGTHS = {"a": 18, "b": 18, "l0": 6}


def controller_for(robot: Robot, **config: Any) -> SimulatedController:
    rig = SimulatedRig(robot, RigConfig(seed=3, errors=GeometryErrors.zero()))
    return SimulatedController(robot, rig, ControllerSimConfig(**config))


@pytest.fixture(scope="module")
def served(robot: Robot) -> Iterator[tuple[SimulatedController, ModbusTcpServer, ModbusClient]]:
    controller = controller_for(robot, serial_number=0x00C0FFEE, firmware_version=0x0302)
    with ModbusTcpServer(controller).start() as server:
        client = ModbusClient(host="127.0.0.1", port=server.port, unit_id=1, timeout=1.0, auto_open=True)
        yield controller, server, client
        client.close()


def longs(client: ModbusClient, address: int, n: int) -> list[int]:
    regs = client.read_holding_registers(address, 2 * n)
    assert regs is not None, client.last_except_as_txt
    return word_list_to_long(regs, big_endian=SPEC["device"]["word_order"] == "ABCD")


def test_identity_and_state_by_the_map(served, robot: Robot) -> None:
    _, server, client = served
    ident = SPEC["identity"]
    assert client.read_holding_registers(ident["magic"]["address"], 1) == [ident["magic"]["expect"]]
    assert client.read_holding_registers(ident["parameter_count"]["address"], 1) == [42]
    assert ident["serial_number"]["type"] == "u32"
    assert longs(client, ident["serial_number"]["address"], 1) == [0x00C0FFEE]
    state = SPEC["state"]
    raw = client.read_holding_registers(state["address"], 1)[0] & state["mask"]
    assert [k for k in ("disabled", "enabled", "fault") if state[k] == raw] == ["disabled"]
    with ControllerParams("127.0.0.1", server.port) as params:
        identity = params.read_identity()
        assert (identity.magic, identity.serial_number, identity.firmware_version) == (
            ident["magic"]["expect"], 0x00C0FFEE, client.read_holding_registers(ident["firmware_version"]["address"],
                                                                               1)[0])
        assert params.read_state().name == "DISABLED"


def test_live_geometry_in_the_maps_types_equals_the_drivers(served, robot: Robot) -> None:
    controller, server, client = served
    new = np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0]) + np.random.default_rng(5).normal(0, 0.3, 42)
    with ControllerParams("127.0.0.1", server.port) as params:
        params.upload(new)
        driver_reads = params.read_live().to_vector()
        try:
            geometry = SPEC["geometry"]
            assert all(geometry[p].get("type", geometry["type"]) == "f32" for p in LENGTHS)
            values: list[float] = []
            registers: list[int] = []
            for part, n in LENGTHS.items():
                values += [decode_ieee(v) for v in longs(client, geometry[part]["live"], n)]
                registers += client.read_holding_registers(geometry[part]["live"], 2 * n)
            np.testing.assert_array_equal(values, driver_reads)
            np.testing.assert_array_equal(values, controller.live_parameters())
            np.testing.assert_allclose(values, new, atol=1e-3)
            crc = longs(client, SPEC["checksum"]["live"], 1)[0]
            assert crc == zlib.crc32(struct.pack(f">{len(registers)}H", *registers))
        finally:
            params.rollback()


def shifted_map(tmp_path: Path, by: int) -> Path:
    """The default map with every register below 0x1000 moved by ``by`` (the compensation banks stay)."""
    keys = {"address", "live", "staging", "backup", "saved", "staged", "length"}

    def shift(node: Any) -> Any:
        if isinstance(node, dict):
            return {k: (v + by if k in keys and isinstance(v, int) and v < 0x1000 else shift(v))
                    for k, v in node.items()}
        return node

    data = shift(tomllib.loads(DEFAULT_MAP.read_text()))
    data["device"]["name"] = "hilcal-1.1-shifted"
    path = tmp_path / "shifted.toml"
    path.write_text("\n".join(toml_lines(data)) + "\n")
    return path


def test_the_simulator_serves_the_map_it_is_given(robot: Robot, tmp_path: Path) -> None:
    from hilcal.protocols.modbus_map import load_register_map

    path = shifted_map(tmp_path, 0x0800)
    controller = controller_for(robot)
    server = ModbusTcpServer(controller, register_map=load_register_map(path)).start()
    client = ModbusClient(host="127.0.0.1", port=server.port, unit_id=1, timeout=1.0, auto_open=True)
    try:
        assert client.read_holding_registers(0x0000, 1) is None and client.last_except == 2
        assert client.read_holding_registers(0x0800, 1) == [SPEC["identity"]["magic"]["expect"]]
        new = controller.live_parameters() + 0.125
        with ControllerParams("127.0.0.1", server.port, register_map=path) as params:
            record = params.upload(new, save=True)
            assert record.outcome == "committed" and record.saved
            assert {w.address for w in record.writes} >= {SPEC["commands"]["address"] + 0x0800,
                                                         SPEC["geometry"]["a"]["staging"] + 0x0800}
        np.testing.assert_allclose(controller.live_parameters(), new, atol=1e-3)
        np.testing.assert_allclose(controller.saved_parameters(), new, atol=1e-3)
    finally:
        client.close()
        server.close()


def test_the_simulator_refuses_a_map_it_cannot_serve(robot: Robot) -> None:
    from hilcal.protocols.modbus_map import load_register_map

    other = load_register_map(ROOT / "examples" / "modbus_maps" / "hexapod-cdab.toml")
    with pytest.raises(ValueError, match="staged transaction in word order ABCD") as info:
        ControllerRegisterMap(controller_for(robot), other)
    assert "geometry.l0: the simulated controller holds float32 ABCD in mm" in str(info.value)
