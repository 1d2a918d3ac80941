"""Devices written by others, connected by configuration alone: the Zentrix HX-6 controller and an I++ DME server.

The device (tests/peers/zentrix_hx6: its EDS, its vendor manual, a ``canopen.LocalNode``) was written from CiA 301
behind an information barrier: its author read neither hilcal's code nor its docs. Its objects are its own: leg
lengths as INTEGER32 nm (2000h/2001h), a move started on a rising edge of a vendor control word (2010h) and finished
when a status bit says in position (2011h), the geometry as REAL32 mm in one record per leg (2101h-2106h), stored
with 1010h sub 4. The station and robot files were then written by another engineer from docs/controllers.md and the
vendor's manual alone (tests/peers/zentrix_hx6/INTEGRATION.md lists what the docs left unclear). Here hilcal must
check the device, round-trip its geometry through `hilcal upload` and `hilcal rollback` exactly (REAL32 values, read
back by canopen's own SdoClient and after a power cycle), and run a whole calibration on it, measured by a CMM
server written the same way from the I++ DME 1.4.3 specification and NIST's test files alone
(tests/peers/ippdme_server, NOTES.md: it reports the stylus ball's centre, as 6.3.2.13 says, and keeps the session in
its error state after any error of severity 2 or more until ClearAllErrors).
"""

from __future__ import annotations

import configparser
import itertools
import json
import shutil
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
from typer.testing import CliRunner

from drivers.controller.base import CommandRefused
from hilcal.robot import Robot, load_robot
from procedures.cli.app import app
from procedures.cli.sim_station import SIM_TIMING
from procedures.plan import make_plan, save_plan
from procedures.station import load_station, open_controller
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_config import SimConfig
from sim_devices.simulator import published_alignment
from tests.cli.others.rig_support import RigView
from tests.peers.ippdme_server.server import IppDmeServer
from tests.peers.zentrix_hx6.device import ZentrixHX6

pytestmark = [pytest.mark.timeout(240)]
PEER = Path(__file__).parents[2] / "peers" / "zentrix_hx6"
EDS = PEER / "zentrix_hx6.eds"
NODE_ID = 5
runner = CliRunner()
_n = itertools.count()


def _factory_geometry() -> np.ndarray:
    """(6, 7) per leg the EDS defaults of 2101h-2106h sub 1-7 (base x y z, platform x y z, zero length) as REAL32:
    read from the EDS with configparser, not through hilcal."""
    eds = configparser.ConfigParser()
    eds.read(EDS)
    return np.array([[float(eds[f"{0x2101 + leg:04X}sub{sub}"]["DefaultValue"]) for sub in range(1, 8)]
                     for leg in range(6)], dtype=np.float32)


def _device_geometry(channel: str) -> np.ndarray:
    """(6, 7) the geometry the device holds, read by canopen's own SdoClient with the vendor's EDS."""
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        node = network.add_node(NODE_ID, str(EDS))
        return np.array([[node.sdo[0x2101 + leg][sub].raw for sub in range(1, 8)] for leg in range(6)],
                        dtype=np.float32)
    finally:
        network.disconnect()


def _station(tmp: Path, channel: str, cmm: str | None = None) -> Path:
    """The integrator's station file on this test's bus channel: as written (its [cmm] a placeholder, which upload
    and rollback do not use), with the given [cmm] section instead, or the controller alone (cmm = "")."""
    for name in ("zentrix_hx6.eds", "zentrix_robot.toml"):
        shutil.copy(PEER / name, tmp / name)
    text = (PEER / "station.toml").read_text().replace('channel = "zentrix-hx6"', f'channel = "{channel}"')
    if cmm is not None:
        text = text[:text.index("[cmm]")] + cmm
    (tmp / "station.toml").write_text(text)
    return tmp / "station.toml"


@pytest.fixture
def device(tmp_path: Path) -> Iterator[tuple[ZentrixHX6, str]]:
    channel = f"zentrix-{next(_n)}-{time.monotonic_ns()}"
    hx6 = ZentrixHX6(channel, NODE_ID, storage_path=tmp_path / "nvm.json")
    try:
        yield hx6, channel
    finally:
        hx6.close()


def _heartbeat_ms(channel: str) -> int:
    """The device's producer heartbeat time (1017h), read by canopen's own SdoClient."""
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        return int(network.add_node(NODE_ID, str(EDS)).sdo[0x1017].raw)
    finally:
        network.disconnect()


def test_the_device_is_checked_by_the_station_file_alone(tmp_path: Path, device) -> None:
    """`hilcal check` reads and writes nothing: the device keeps its own heartbeat time (the station's heartbeat_ms
    is what a run sets)."""
    _, channel = device
    before = _heartbeat_ms(channel)
    station = _station(tmp_path, channel, cmm="")
    assert before != 100 and "heartbeat_ms = 100" in station.read_text()
    result = runner.invoke(app, ["check", "--station", str(station), "--json"])
    assert result.exit_code == 0, result.output
    assert _heartbeat_ms(channel) == before
    (controller,) = json.loads(result.stdout)["devices"]
    assert controller["ok"] and controller["problems"] == []
    assert controller["stops"] == {"stop": "none: a move in progress runs to its end",
                                   "estop": "none over the bus: the machine's hardware e-stop only"}
    assert controller["identity"]["vendor_id"] == 0x5A454E58 and controller["identity"]["node_id"] == NODE_ID
    geometry = controller["parameters"]["geometry"]
    factory = _factory_geometry()
    assert np.array_equal(np.float32(geometry["b_mm"]), factory[:, 0:3])
    assert np.array_equal(np.float32(geometry["a_mm"]), factory[:, 3:6])
    assert np.array_equal(np.float32(geometry["l0_mm"]), factory[:, 6])


def test_upload_and_rollback_round_trip_the_geometry_exactly(tmp_path: Path, device) -> None:
    hx6, channel = device
    station = _station(tmp_path, channel)
    old, heartbeat_ms = _device_geometry(channel), _heartbeat_ms(channel)
    # REAL32 holds these exactly: multiples of 1/64 mm below 2^17
    new = old.astype(float).copy()
    new[:, 0:6] = np.round(old[:, 0:6] * 64) / 64 + (np.arange(36).reshape(6, 6) % 7 - 3) / 16
    new[:, 6] = np.round(old[:, 6] * 64) / 64 + np.array([0.25, -0.125, 0.5, -0.5, 0.0625, 1.0])
    params = tmp_path / "new.json"
    params.write_text(json.dumps({"a_mm": new[:, 3:6].tolist(), "b_mm": new[:, 0:3].tolist(),
                                  "l0_mm": new[:, 6].tolist()}))
    db = str(tmp_path / "records.sqlite")
    result = runner.invoke(app, ["upload", str(params), "--station", str(station), "--yes", "--save", "--records",
                                 db])
    assert result.exit_code == 0, result.output
    assert np.array_equal(_device_geometry(channel), new.astype(np.float32))
    assert _heartbeat_ms(channel) == heartbeat_ms != 100, "the station's heartbeat_ms was set for the upload only"
    hx6.close()  # a power cycle: the device starts again from what 1010h stored
    again = ZentrixHX6(channel, NODE_ID, storage_path=tmp_path / "nvm.json")
    try:
        assert np.array_equal(_device_geometry(channel), new.astype(np.float32)), "stored with 1010h"
        result = runner.invoke(app, ["rollback", "--station", str(station), "--records", db])
        assert result.exit_code == 0, result.output
        assert np.array_equal(_device_geometry(channel), old), "the old set back, every value"
    finally:
        again.close()


class RigPlant:
    """The rig's legs as the HX-6's encoders: the device reports encoder + zero length, so the rig's reading is the
    encoder plus the zero length the device started with (an uploaded zero length changes the reading, not the leg)."""

    def __init__(self, rig: SimulatedRig, lock: threading.Lock, zero_mm: np.ndarray) -> None:
        self.rig, self.lock, self.zero_mm = rig, lock, zero_mm

    def move_to(self, encoder_mm: list[float]) -> None:
        with self.lock:
            self.rig.move_to_lengths(np.asarray(encoder_mm) + self.zero_mm)

    def read(self) -> list[float]:
        with self.lock:
            return list(self.rig.reported_lengths() - self.zero_mm)


@pytest.fixture(scope="module")
def blind_run(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A whole run, answered --yes: the HX-6 moves a rig of the integrator's robot file (the paper's Table 2 errors
    at a tenth: up to 0.1 mm on this 0.4 m machine), the I++ DME server measures it over TCP."""
    tmp = tmp_path_factory.mktemp("blind_run")
    channel = f"zentrix-run-{next(_n)}-{time.monotonic_ns()}"
    _station(tmp, channel)
    robot: Robot = load_robot(tmp / "zentrix_robot.toml")
    config = SimConfig.model_validate({"rig": {"seed": 3, "errors": "table2", "errors_scale": 0.1,
                                               "temperature": {"drift_k_per_h": 0.0, "amplitude_k": 0.0}}})
    rig = SimulatedRig(robot, config.rig.rig_config(robot))
    rig.move_to_lengths(rig.controller_ik(robot.home))
    lock = threading.Lock()
    view = RigView(rig, lock)
    cmm = IppDmeServer(lambda: view.spheres_in_cmm(robot), stylus_radius_mm=1.5, noise_mm=0.0005, seed=3,
                       limits=((-5000.0, 5000.0),) * 3)
    zero_nm = np.round(_factory_geometry()[:, 6].astype(float) * 1e6)  # as the device counts them (manual §2)
    hx6 = ZentrixHX6(channel, NODE_ID, plant=RigPlant(rig, lock, zero_nm / 1e6), storage_path=tmp / "nvm.json")
    heartbeat_ms = _heartbeat_ms(channel)
    try:
        alignment = published_alignment(rig, 2.0, 0.02, 3)
        _station(tmp, channel, f'[cmm]\nurl = "{cmm.url}"\ntool = "Probe1"\nalignment = '
                               f"{json.dumps(alignment.tolist())}\n")
        save_plan(make_plan(robot, 0, n_measure=12, n_verify=6, settle_s=0.0, timing=SIM_TIMING.timing()),
                  tmp / "plan.json")
        result = runner.invoke(app, ["run", "--station", str(tmp / "station.toml"), "--plan", str(tmp / "plan.json"),
                                     "--operator", "T", "--out", str(tmp / "run"), "--yes"],
                               env={"HILCAL_RECORDS": str(tmp / "records.sqlite"), "COLUMNS": "200"})
        return {"result": result, "run": tmp / "run", "moves": hx6.moves, "transcript": list(cmm.transcript),
                "held": _device_geometry(channel), "heartbeats_ms": (heartbeat_ms, _heartbeat_ms(channel))}
    finally:
        hx6.close()
        cmm.close()


@pytest.mark.slow
def test_a_whole_run_on_the_two_devices_completes_and_corrects_the_machine(blind_run) -> None:
    result = blind_run["result"]
    assert result.exit_code == 0, result.output
    report = json.loads((blind_run["run"] / "report.json").read_text())
    assert report["status"] == "complete" and report["uploaded"] and blind_run["moves"] > 0
    found, after_run = blind_run["heartbeats_ms"]
    assert after_run == found != 100, "the device is left with its own heartbeat time, not the station's"
    before, after = report["verification"]["before"], report["verification"]["after"]
    predicted = report["compensation"]["predicted_held_out"]
    assert after["rms_position_mm"] < before["rms_position_mm"] / 5
    assert after["max_position_mm"] <= 1.5 * predicted["max_position_mm"], (after, predicted)
    uploaded = report["compensation"]["uploaded_parameters"]
    held = blind_run["held"]
    assert np.array_equal(held[:, 3:6], np.float32(uploaded["a_mm"])) and np.array_equal(
        held[:, 0:3], np.float32(uploaded["b_mm"])) and np.array_equal(held[:, 6], np.float32(uploaded["l0_mm"]))


@pytest.mark.slow
def test_the_cmm_session_is_clean_by_the_servers_own_reading_of_the_standard(blind_run) -> None:
    """The server answers with an error line whatever it finds against 1.4.3; the run's session has none, asked the
    stylus radius of the CMM (6.3.13) and ended its session."""
    lines = [(who, line) for who, line in blind_run["transcript"] if who in ("client", "server")]
    errors = [line for who, line in lines if who == "server" and " ! " in line]
    assert errors == []
    sent = [line[6:] for who, line in lines if who == "client"]
    assert sent[0].startswith("StartSession()") and sent[-1].startswith("EndSession()")
    assert any("Tool.AvrRadius()" in line for line in sent)
    assert sum(line.startswith("PtMeas(") for line in sent) > 100


def test_a_device_without_halt_or_quick_stop_is_told_so_and_nothing_is_written(tmp_path: Path, device) -> None:
    """The HX-6 has neither a halt nor a quick stop over the bus (its manual, §3.3 and §5.1): mapped "none", stop and
    e-stop are refused in words and no SDO download reaches the device, while moves still work. An observer on the
    bus (python-can, not hilcal) counts the SDO requests to node 5 that write (client command specifier 1)."""
    _, channel = device
    station = load_station(_station(tmp_path, channel, cmm=""), partial=True)
    robot = load_robot(tmp_path / "zentrix_robot.toml")
    writes: list[bytes] = []
    observer = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    notifier = can.Notifier(observer, [lambda m: writes.append(bytes(m.data))
                                       if m.arbitration_id == 0x600 + NODE_ID and m.data[0] >> 5 == 1 else None])
    try:
        with ExitStack() as stack:
            controller, _ = open_controller(station, robot, stack, check=True)
            controller.enable()
            start = controller.feedback().lengths_mm
            reached = controller.move_legs(start + 0.5, timeout_s=5.0)
            assert np.allclose(reached, start + 0.5, atol=1e-3)
            time.sleep(0.2)
            moved = len(writes)
            assert moved >= 6, "the move wrote its six setpoints"
            with pytest.raises(CommandRefused, match=r"no halt over the bus .*runs to its end"):
                controller.stop()
            with pytest.raises(CommandRefused, match=r"no quick stop over the bus .*hardware e-stop"):
                controller.estop()
            time.sleep(0.2)
            assert len(writes) == moved, [w.hex() for w in writes[moved:]]
    finally:
        notifier.stop()
        observer.shutdown()
