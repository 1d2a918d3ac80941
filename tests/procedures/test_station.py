"""Station files and the device factory: TOML round trip, clear errors, and the real drivers on an in-process sim."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from hilcal.protocols.controller_states import ControllerState
from hilcal.robot import default_robot
from procedures.station import (
    DeviceOpenError,
    StationConfig,
    StationConfigError,
    load_station,
    open_devices,
    save_station,
    station_from_channels,
    station_from_dict,
    station_to_toml,
)
from procedures.timing import TimingFileError, TimingSection, load_timing
from sim_devices.sim_config import SimConfig
from sim_devices.simulator import SimHandle, start_sim

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
ROBOT_FILE = Path(__file__).resolve().parents[2] / "hilcal" / "data" / "paper_table1.toml"
YAW_90 = [[0.0, -1.0, 0.0, 1250.5], [1.0, 0.0, 0.0, -3400.0], [0.0, 0.0, 1.0, -820.25], [0.0, 0.0, 0.0, 1.0]]


def full_station(**overrides: object) -> StationConfig:
    data = {
        "robot": str(ROBOT_FILE),
        "records": "/data/records",
        "operator": "J. Smith",
        "can": {"interface": "socketcan", "channel": "can0", "bitrate": 500000, "receive_own_messages": False},
        "modbus": {"host": "192.168.10.20", "port": 1502, "device_id": 3, "timeout_s": 0.5},
        "cmm": {
            "url": "socket://10.0.0.5:1294",
            "alignment": YAW_90,
            "tool": "Probe2",
            "ippdme": {"motion_timeout_s": 12.5, "query_retries": 1},
            "probing": {"n_ring": 8, "elevations_deg": [20.0, 45.0]},
        },
        "motion": {"move_timeout_s": 90.0, "connect_timeout_s": 2.0},
        "timing": {"leg_speed_mm_s": 30.0, "leg_accel_mm_s2": 60.0, "settle_s": 3.0, "cmm_s_per_pose": 50.0},
    }
    data.update(overrides)
    return station_from_dict(data)


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "station.toml"
    path.write_text(text)
    return path


MINIMAL = """
[can]
interface = "virtual"
channel = "hil"
[modbus]
host = "127.0.0.1"
[cmm]
url = "loop://"
alignment = [100.0, 200.0, 300.0, 0.0, 0.0, 45.0]
"""


# ---------------------------------------------------------------------- files


def test_toml_round_trip(tmp_path: Path) -> None:
    station = full_station()
    path = tmp_path / "station.toml"
    save_station(station, path)
    assert load_station(path) == station
    loaded = load_station(path)
    assert loaded.can.bus_config() == {"interface": "socketcan", "channel": "can0", "bitrate": 500000,
                                       "receive_own_messages": False}
    assert loaded.cmm.probing.elevations_deg == (20.0, 45.0)
    np.testing.assert_array_equal(loaded.cmm.alignment_matrix(), np.array(YAW_90))

    rtu = full_station(modbus={"serial_port": "/dev/ttyUSB1", "baudrate": 57600},
                       cmm={"url": "/dev/ttyUSB0", "alignment": [1.0, 2.0, 3.0, 0.5, -0.5, 90.0]}, records=None)
    assert load_station(write(tmp_path, station_to_toml(rtu))) == rtu
    T = rtu.cmm.alignment_matrix()
    np.testing.assert_allclose(T[:3, 3], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)


def test_minimal_file_defaults_and_relative_paths(tmp_path: Path) -> None:
    (tmp_path / "robots").mkdir()
    station = load_station(write(tmp_path, 'robot = "robots/r.toml"\nrecords = "runs"\n' + MINIMAL))
    assert station.robot == tmp_path / "robots" / "r.toml"
    assert station.records == tmp_path / "runs"
    assert station.modbus.port == 502 and station.modbus.device_id == 1
    assert station.motion.move_timeout_s == 120.0 and station.operator is None
    assert load_station(write(tmp_path, MINIMAL)).robot is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[can\ninterface = 1", "not valid TOML"),
        (MINIMAL + "[motion]\nmove_timeout = 3.0\n", r"motion\.move_timeout: Extra inputs"),
        (MINIMAL.replace('host = "127.0.0.1"', 'host = "h"\nserial_port = "/dev/ttyS0"'), "either host"),
        (MINIMAL.replace('host = "127.0.0.1"', "device_id = 1"), "either host"),
        (MINIMAL.replace("45.0]", "45.0, 1.0]"), r"cmm\.alignment"),
        (MINIMAL.replace('url = "loop://"\n', ""), r"cmm\.url: Field required"),
        (MINIMAL.replace('channel = "hil"\n', ""), r"can\.channel: Field required"),
        (MINIMAL.replace("[100.0, 200.0, 300.0, 0.0, 0.0, 45.0]", "[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], "
                         "[0, 0, 0, 1]]"), "not a proper rotation"),
        (MINIMAL.replace("[100.0, 200.0, 300.0, 0.0, 0.0, 45.0]", "[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], "
                         "[0, 0, 1, 1]]"), r"last row"),
        (MINIMAL.replace("[modbus]", "[modbus]\nport = 70000"), r"modbus\.port"),
        (MINIMAL + "[timing]\nleg_speed_mm_s = 0.0\n", r"timing\.leg_speed_mm_s: Input should be greater than 0"),
        (MINIMAL + "[timing]\nleg_speed = 10.0\n", r"timing\.leg_speed: Extra inputs"),
    ],
)
def test_bad_files_give_clear_errors(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(StationConfigError, match=message) as info:
        load_station(path)
    assert str(path) in str(info.value)


def test_timing_section_alone_for_simulated_runs(tmp_path: Path) -> None:
    assert load_station(write(tmp_path, MINIMAL)).timing == TimingSection()
    timing = load_timing(write(tmp_path, "[timing]\nleg_speed_mm_s = 12.5\ncmm_s_per_pose = 30.0\n"))
    assert (timing.leg_speed_mm_s, timing.cmm_s_per_pose, timing.settle_s) == (12.5, 30.0, TimingSection().settle_s)
    assert timing.timing().leg_speed_mm_s == 12.5 and timing.timing(settle_s=0.1).settle_s == 0.1
    with pytest.raises(TimingFileError, match=r"timing\.settle_s"):
        load_timing(write(tmp_path, "[timing]\nsettle_s = -1.0\n"))
    with pytest.raises(TimingFileError, match="cannot read"):
        load_timing(tmp_path / "nope.toml")


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(StationConfigError, match="cannot read"):
        load_station(tmp_path / "nope.toml")


# ---------------------------------------------------------------------- devices on the simulator


@pytest.fixture
def sim() -> Iterator[SimHandle]:
    with start_sim(SimConfig.model_validate({"rig": {"seed": 4}, "cmm": {"time_scale": 0.0}})) as handle:
        yield handle


def wait_for(predicate: Callable[[], bool], timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_open_devices_on_the_simulator(sim: SimHandle) -> None:
    station = station_from_channels(sim.channels())
    assert station.robot is None and station.can.bus_config()["sleep_after_open"] == 0
    with open_devices(station) as devices:
        assert devices.robot.name == ROBOT.name
        assert devices.controller.state is ControllerState.DISABLED
        assert devices.params.read_identity().parameter_count == 42
        np.testing.assert_array_equal(devices.cmm_alignment, np.asarray(sim.channels()["cmm_alignment"]))
        assert sim.controller_servers.slcan.is_open
        devices.cmm.start_session()
        devices.cmm.home()
        result = devices.cmm.measure_pose(devices.robot, devices.cmm_alignment)
        np.testing.assert_allclose(result.pose[:3], sim.controller.true_pose()[:3], atol=0.01)
    assert wait_for(lambda: not sim.controller_servers.slcan.is_open), "closing the devices must close the CAN link"
    assert wait_for(lambda: not devices.controller.controller_alive)
    assert not devices.cmm.is_open


def test_a_failing_device_closes_the_others(sim: SimHandle, tmp_path: Path) -> None:
    channels = sim.channels()
    bad_cmm = {**channels, "cmm": {"url": str(tmp_path / "no-such-port")}}
    with pytest.raises(DeviceOpenError, match="CMM"):
        open_devices(station_from_channels(bad_cmm))
    assert wait_for(lambda: not sim.controller_servers.slcan.is_open)
    bad_modbus = {**channels, "modbus": {"host": "127.0.0.1", "port": 1, "timeout_s": 0.3}}
    with pytest.raises(DeviceOpenError, match="Modbus"):
        open_devices(station_from_channels(bad_modbus))
    assert wait_for(lambda: not sim.controller_servers.slcan.is_open)
    bad_can = {**channels, "can": {**channels["can"], "channel": str(tmp_path / "no-such-tty")}}
    with pytest.raises(DeviceOpenError, match="controller"):
        open_devices(station_from_channels(bad_can))


def test_station_from_channels_checks_the_robot(sim: SimHandle, tmp_path: Path) -> None:
    assert station_from_channels(sim.channels(), ROBOT_FILE).robot == ROBOT_FILE
    other = tmp_path / "other.toml"
    other.write_text(ROBOT_FILE.read_text().replace(f'name = "{ROBOT.name}"', 'name = "plant-7"'))
    with pytest.raises(StationConfigError, match="plant-7"):
        station_from_channels(sim.channels(), other)
    with pytest.raises(StationConfigError, match="cmm"):
        station_from_channels({k: v for k, v in sim.channels().items() if k != "cmm"})
