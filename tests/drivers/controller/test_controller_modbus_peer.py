"""The driver against a Modbus server that is not ours: pymodbus's own simulator (``SimDevice``/``SimData``), laid out
by this test from a second map file (``examples/modbus_maps/hexapod-cdab.toml``: other addresses, word order CDAB,
leg offsets as int32 micrometres, a device without staging), taking uploads and rollbacks.

The registers are encoded and checked here with ``struct`` from the map file's text (read with ``tomllib``), not with
the driver's codec; faults are injected by the simulator's own ``action`` hook (a write refused, a write half done).
"""

from __future__ import annotations

import asyncio
import socket
import struct
import threading
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.controller.modbus import (
    CapabilityError,
    ControllerParams,
    IdentityError,
    ModbusExceptionResponse,
    NotDisabled,
    ParameterSet,
    UploadRefused,
)
from hilcal.protocols.registers import ParamStatus
from hilcal.protocols.toml_text import toml_lines
from hilcal.robot import Robot

pytestmark = pytest.mark.timeout(60)

MAP_FILE = Path(__file__).resolve().parents[3] / "examples" / "modbus_maps" / "hexapod-cdab.toml"
SPEC = tomllib.loads(MAP_FILE.read_text())
PARTS = {"a": (0, 18), "b": (18, 36), "l0": (36, 42)}
FMT = {"u16": "H", "u32": "I", "i32": "i", "f32": "f"}


def cdab(fmt: str, value: float | int) -> list[int]:
    """One value's registers, low word first (the map says CDAB), each word big-endian."""
    words = list(struct.unpack(f">{struct.calcsize(fmt) // 2}H", struct.pack(f">{fmt}", value)))
    return words[::-1]


def part_spec(name: str) -> tuple[int, str, float]:
    part, geometry = SPEC["geometry"][name], SPEC["geometry"]
    return part["live"], part.get("type", geometry["type"]), part.get("scale", 1.0)


def encode_set(values: np.ndarray) -> dict[int, list[int]]:
    """address -> registers of the whole set, as the map file lays it out."""
    out = {}
    for name, (lo, hi) in PARTS.items():
        address, type_, scale = part_spec(name)
        counts = [round(v / scale) if type_ == "i32" else float(v) for v in values[lo:hi]]
        out[address] = [w for c in counts for w in cdab(FMT[type_], c)]
    return out


def held(values: np.ndarray) -> np.ndarray:
    """The set as this device holds it: a and b float32, l0 whole micrometres."""
    out = np.asarray(values, dtype=np.float32).astype(float)
    out[36:] = np.round(np.asarray(values[36:]) / 0.001) * 0.001
    return out


@dataclass
class Peer:
    """pymodbus's simulator in a thread of its own, with a log of writes and one-shot write faults."""

    port: int
    writes: list[tuple[int, int, list[int]]] = field(default_factory=list)
    refuse: list[tuple[int, int]] = field(default_factory=list)
    """(n-th geometry write from now, Modbus exception code); code 4 executes half the write first."""
    geometry_writes: int = 0

    async def action(self, function_code: int, start_address: int, address: int, count: int,
                     registers: list[int], values: list[int] | None) -> ExcCodes | None:
        if values is None:
            return None
        self.writes.append((function_code, address, list(values)))
        if address < SPEC["geometry"]["a"]["live"]:
            return None
        self.geometry_writes += 1
        for k, (n, code) in enumerate(self.refuse):
            if n == self.geometry_writes:
                del self.refuse[k]
                if code == 4:
                    half = len(values) // 2
                    registers[address - start_address:address - start_address + half] = values[:half]
                return ExcCodes(code)
        return None


def simdata(values: np.ndarray, state: int, product: int) -> list[SimData]:
    ident = SPEC["identity"]
    out = [
        SimData(ident["magic"]["address"], values=cdab("I", product), datatype=DataType.REGISTERS, readonly=True),
        SimData(ident["firmware_version"]["address"], values=0x0105, datatype=DataType.REGISTERS, readonly=True),
        SimData(ident["serial_number"]["address"], values=cdab("I", 770_001), datatype=DataType.REGISTERS,
                readonly=True),
        SimData(SPEC["state"]["address"], values=state, datatype=DataType.REGISTERS),
        SimData(SPEC["commands"]["address"], values=0, datatype=DataType.REGISTERS),
    ]
    out += [SimData(a, values=w, datatype=DataType.REGISTERS) for a, w in encode_set(values).items()]
    return out


@pytest.fixture
def start_peer(robot: Robot) -> Iterator:
    stops = []

    def start(values: np.ndarray | None = None, *, state: int | None = None, product: int | None = None) -> Peer:
        values = held(np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0]) if values is None else values)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            peer = Peer(s.getsockname()[1])
        device = SimDevice(1, simdata=simdata(values, SPEC["state"]["disabled"] if state is None else state,
                                              SPEC["identity"]["magic"]["expect"] if product is None else product),
                           action=peer.action)
        loop = asyncio.new_event_loop()
        ready = threading.Event()
        holder: dict[str, ModbusTcpServer] = {}

        async def serve() -> None:
            server = ModbusTcpServer(device, address=("127.0.0.1", peer.port))
            holder["server"] = server
            await server.serve_forever(background=True)
            ready.set()
            await server.serving

        thread = threading.Thread(target=loop.run_until_complete, args=(serve(),), daemon=True)
        thread.start()
        assert ready.wait(5.0), "pymodbus server did not start"

        def stop() -> None:
            asyncio.run_coroutine_threadsafe(holder["server"].shutdown(), loop).result(5.0)
            thread.join(5.0)
            loop.close()

        stops.append(stop)
        return peer

    yield start
    for stop in stops:
        stop()


class Raw:
    def __init__(self, port: int) -> None:
        self.client = ModbusTcpClient("127.0.0.1", port=port, timeout=1.0, retries=0)

    def read(self, address: int, count: int) -> list[int]:
        response = self.client.read_holding_registers(address, count=count, device_id=1)
        assert not response.isError(), response
        return list(response.registers)

    def registers_of_set(self) -> dict[int, list[int]]:
        return {a: self.read(a, len(w)) for a, w in encode_set(np.ones(42)).items()}


@pytest.fixture
def nominal(robot: Robot) -> np.ndarray:
    return np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0])


@pytest.fixture
def new_set(nominal: np.ndarray) -> np.ndarray:
    return nominal + np.random.default_rng(39).normal(0.0, 0.4, 42)


def params_for(peer: Peer) -> ControllerParams:
    return ControllerParams("127.0.0.1", peer.port, device_id=1, timeout_s=1.0, register_map=MAP_FILE)


def test_the_map_file_is_the_second_map_the_brief_asks_for() -> None:
    assert SPEC["device"]["transaction"] == "direct" and SPEC["device"]["word_order"] == "CDAB"
    assert part_spec("l0")[1:] == ("i32", 0.001) and "staging" not in SPEC["geometry"]["a"]
    assert cdab("f", 1.0) == [0x0000, 0x3F80]  # 1.0f is 3F 80 00 00: low word first


def test_identity_state_and_live_set_through_the_map(start_peer, nominal: np.ndarray) -> None:
    peer = start_peer()
    with params_for(peer) as params:
        identity = params.read_identity()
        assert (identity.magic, identity.firmware_version, identity.serial_number) == (0x48455836, 0x0105, 770_001)
        assert identity.parameter_count == 42 and not identity.offsets_only and not identity.compensation
        assert params.read_state().name == "DISABLED"
        np.testing.assert_allclose(params.read_live().to_vector(), held(nominal), rtol=0, atol=1e-9)
        described = params.describe()
    assert described["identity"]["magic"] == 0x48455836 and described["state"] == "DISABLED"
    assert described["transaction"] == "direct" and described["geometry"]["checksum_register"] is None
    assert peer.writes == []


def test_an_upload_lands_at_the_maps_addresses_in_cdab(start_peer, new_set: np.ndarray) -> None:
    peer = start_peer()
    raw = Raw(peer.port)
    with params_for(peer) as params:
        record = params.upload(new_set, save=True)
    assert record.outcome == "committed" and record.live_readback_match and record.saved
    assert raw.registers_of_set() == encode_set(held(new_set))
    assert record.params_sha256 == ParameterSet.from_vector(held(new_set)).sha256()
    geometry = [w for w in peer.writes if w[1] >= SPEC["geometry"]["a"]["live"]]
    assert all(len(values) <= SPEC["device"]["max_write_registers"] for _, _, values in geometry)
    assert sum(len(values) for _, _, values in geometry) == 36 + 36 + 12
    assert peer.writes[-1] == (6, SPEC["commands"]["address"], [SPEC["commands"]["save"]])
    raw.client.close()


@pytest.mark.parametrize("code", [3, 4])
def test_a_write_refused_mid_upload_puts_the_old_set_back(start_peer, nominal: np.ndarray, new_set: np.ndarray,
                                                          code: int) -> None:
    peer = start_peer()
    raw = Raw(peer.port)
    before = raw.registers_of_set()
    peer.refuse.append((2, code))  # the second geometry write; code 4: the device wrote half of it first
    with params_for(peer) as params, pytest.raises(ModbusExceptionResponse) as info:
        params.upload(new_set)
    err = info.value
    record = err.record
    assert err.code == code and record is not None and record.outcome == "failed"
    assert record.writes[0].ok and not record.writes[1].ok and record.writes[1].error
    assert raw.registers_of_set() == before
    assert record.live_after_sha256 == record.previous_live_sha256
    assert "the device holds the old set" in str(err) and "0x" in str(err)
    restores = [(w.address, w.count) for w in record.writes[2:]]  # what differed: a, and half of b if written
    assert restores == [(2000, 36)] + ([(2100, 18)] if code == 4 else [])
    raw.client.close()


def test_a_restore_that_fails_says_the_device_may_hold_a_mix(start_peer, new_set: np.ndarray) -> None:
    peer = start_peer()
    peer.refuse += [(2, 4), (3, 4), (4, 4), (5, 4)]
    with params_for(peer) as params, pytest.raises(ModbusExceptionResponse, match="may hold a mix"):
        params.upload(new_set)


def test_rollback_writes_the_set_before_the_last_upload_back(start_peer, nominal: np.ndarray,
                                                             new_set: np.ndarray) -> None:
    peer = start_peer()
    raw = Raw(peer.port)
    old = raw.registers_of_set()
    with params_for(peer) as params:
        params.upload(new_set)
        record = params.rollback()
    assert record.outcome == "rolled_back" and record.live_readback_match
    assert raw.registers_of_set() == old
    with params_for(peer) as fresh:  # a new session keeps no set: it needs one from the records
        n = len(peer.writes)
        with pytest.raises(UploadRefused) as info:
            fresh.rollback()
        assert info.value.status is ParamStatus.NO_BACKUP and len(peer.writes) == n
        last = fresh.upload(new_set)
    previous = ParameterSet.model_validate(last.previous_params).to_vector()
    np.testing.assert_allclose(previous, nominal, atol=1e-4)  # a and b as the driver fills them (float32)
    with params_for(peer) as fresh:  # the upload's record (hilcal rollback finds it in the records) says what to put
        record = fresh.rollback(last)
    assert record.outcome == "rolled_back" and raw.registers_of_set() == old
    raw.client.close()


def test_nothing_is_written_unless_the_device_is_disabled(start_peer, new_set: np.ndarray) -> None:
    peer = start_peer(state=SPEC["state"]["enabled"] | 0x0030)  # bits outside the mask do not matter
    with params_for(peer) as params, pytest.raises(NotDisabled, match="ENABLED"):
        params.upload(new_set)
    assert peer.writes == []


def test_a_device_that_is_not_the_maps_is_refused_and_named(start_peer, new_set: np.ndarray) -> None:
    peer = start_peer(product=0x12345678)
    with params_for(peer) as params:
        with pytest.raises(IdentityError, match=r"magic 0x12345678 \(expected 0x48455836\)"):
            params.upload(new_set)
        assert params.describe()["identity_error"].startswith("IdentityError: not a compatible controller")
    assert peer.writes == []
    with ControllerParams("127.0.0.1", peer.port, timeout_s=1.0) as hilcal_map:  # the wrong map: hilcal-1.1
        described = hilcal_map.describe()
    assert "Modbus exception 2 (ILLEGAL DATA ADDRESS" in described["identity_error"]
    assert "read geometry live at 0x0100" in described["geometry_error"]


def test_a_map_of_the_leg_offsets_alone(start_peer, robot: Robot, nominal: np.ndarray, tmp_path: Path) -> None:
    data = tomllib.loads(MAP_FILE.read_text())
    del data["geometry"]["a"], data["geometry"]["b"]
    path = tmp_path / "offsets-only.toml"
    path.write_text("\n".join(toml_lines(data)) + "\n")
    peer = start_peer()
    raw = Raw(peer.port)
    before = raw.registers_of_set()
    fill = ParameterSet.from_robot(robot)
    with ControllerParams("127.0.0.1", peer.port, register_map=path, nominal=fill) as params:
        identity = params.read_identity()
        assert identity.offsets_only and identity.parameter_count == 6
        np.testing.assert_array_equal(params.read_live().to_vector(), np.r_[nominal[:36], held(nominal)[36:]])
        changed_a = nominal.copy()
        changed_a[4] += 0.5
        with pytest.raises(CapabilityError, match="only the six leg offsets"):
            params.upload(changed_a)
        assert peer.writes == []
        new = nominal.copy()
        new[36:] += [0.25, -0.5, 0.125, 1.0, -1.0, 0.0005]
        record = params.upload(new)
    assert record.outcome == "committed" and [(w.address, w.count) for w in record.writes] == [(2200, 12)]
    after = raw.registers_of_set()
    assert after[2200] == encode_set(held(new))[2200] and after[2000] == before[2000] and after[2100] == before[2100]
    raw.client.close()


def test_a_save_the_map_cannot_do_is_refused_before_writing(start_peer, new_set: np.ndarray, tmp_path: Path) -> None:
    data = tomllib.loads(MAP_FILE.read_text())
    del data["commands"]
    path = tmp_path / "no-save.toml"
    path.write_text("\n".join(toml_lines(data)) + "\n")
    peer = start_peer()
    with ControllerParams("127.0.0.1", peer.port, register_map=path) as params:
        with pytest.raises(CapabilityError, match="no save command"):
            params.upload(new_set, save=True)
        assert peer.writes == [] and params.records[-1].outcome == "refused"
        assert params.upload(new_set).outcome == "committed"
