"""`hilcal check --station FILE [--json] [--home]`: the pre-flight check against the simulated devices.

The CMM alone: a station file with only [cmm], its alignment off by a few mm (within its tolerance), a stylus whose
radius only the CMM knows: the base spheres measured within 5 µm of the rig's true centres in the CMM's frame, the
platform not moved. Not homed without --home: nothing measured, exit 3. A whole simulated station (controller and CMM)
on its real transports. Bad files exit 2, an unreachable CMM 3.
"""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from hilcal.protocols.toml_text import toml_lines
from procedures.cli.app import app
from procedures.station import save_station, station_from_channels
from sim_devices.cmm.config import CmmServerConfig, ToolConfig
from sim_devices.cmm.server import start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_config import SimConfig
from sim_devices.simulator import start_sim
from tests.drivers.cmm.test_cmm import COMMANDED, ROBOT, alignment, true_centres

runner = CliRunner()
BALL_MM = 2.0
"""Not the simulator's default (1.5 mm): the check must read the radius from the CMM."""


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    """The rig with Table 2's errors, its platform somewhere off home: where it stays while the check measures."""
    made = SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))
    made.move_to_lengths(made.controller_ik(COMMANDED))
    return made


def _station(path: Path, url: str, T: np.ndarray, tolerance_mm: float = 10.0) -> Path:
    cmm = {"url": url, "alignment": T.tolist(), "alignment_tolerance_mm": tolerance_mm}
    path.write_text("\n".join(toml_lines({"cmm": cmm}, "")) + "\n")
    return path


def _check(*args: str) -> tuple[int, dict | str]:
    done = runner.invoke(app, ["check", *args])
    try:
        return done.exit_code, json.loads(done.stdout)
    except json.JSONDecodeError:
        return done.exit_code, done.output


def test_the_cmm_alone_measures_the_base_spheres_in_its_own_frame(tmp_path: Path, rig: SimulatedRig) -> None:
    config = CmmServerConfig(seed=3, time_scale=0.0, noise_sigma_mm=0.001, tcp_port=0,
                             tools=(ToolConfig(name="Probe1", ball_radius_mm=BALL_MM),))
    handle = start_cmm_server(ROBOT, rig, config)
    try:
        station = _station(tmp_path / "cmm.toml", handle.socket_url, alignment(rig, (4.0, -3.0, 2.0)))
        pose_before = rig.true_pose().copy()
        code, report = _check("--station", str(station), "--json", "--home")
        assert code == 0, report
        assert report["ok"] and [d["kind"] for d in report["devices"]] == ["cmm"]
        cmm = report["devices"][0]
        assert cmm["stylus_radius_mm"] == BALL_MM and cmm["homed"] and cmm["identity"]["dme_version"] == "1.4.3"
        assert "Probe1" in cmm["tools"] and cmm["problems"] == []
        _, base_true = true_centres(rig)
        measured = np.array([s["centre_mm"] for s in cmm["spheres"]])
        assert [s["name"] for s in cmm["spheres"]] == ["base 1", "base 2", "base 3"]
        assert np.max(np.linalg.norm(measured - base_true, axis=1)) < 0.005, measured - base_true
        assert all(abs(s["radius_mm"] - ROBOT.sphere_radius_mm) < 0.01 for s in cmm["spheres"])
        np.testing.assert_array_equal(rig.true_pose(), pose_before)  # the platform did not move
        assert handle.collisions == 0
    finally:
        handle.close()


def test_a_cmm_not_homed_is_not_moved_without_the_operators_word(tmp_path: Path, rig: SimulatedRig) -> None:
    handle = start_cmm_server(ROBOT, rig, CmmServerConfig(seed=3, time_scale=0.0, tcp_port=0))
    try:
        station = _station(tmp_path / "cmm.toml", handle.socket_url, alignment(rig))
        code, report = _check("--station", str(station), "--json")
        assert code == 3 and not report["ok"]
        cmm = report["devices"][0]
        assert cmm["homed"] is False and "spheres" not in cmm and "not homed" in cmm["problems"][0]
        assert handle.machine_time_s == 0.0, "nothing moved"
    finally:
        handle.close()


def test_a_whole_simulated_station(tmp_path: Path) -> None:
    """The controller (hilcal's CAN messages over SLCAN and Modbus TCP) and the CMM, as `hilcal sim` serves them."""
    config = SimConfig.model_validate({"cmm": {"time_scale": 0.0}})
    with start_sim(config) as sim:
        station = station_from_channels(sim.channels())
        save_station(station, tmp_path / "station.toml")
        code, report = _check("--station", str(tmp_path / "station.toml"), "--json", "--home")
    assert code == 0, report
    controller, cmm = report["devices"]
    assert controller["kind"] == "controller" and controller["state"] == "DISABLED"
    assert controller["identity"]["parameter_count"] == 42
    geometry = controller["parameters"]["geometry"]
    assert geometry["checksum_match"] is True and len(geometry["set"]["l0_mm"]) == 6
    assert cmm["kind"] == "cmm" and len(cmm["spheres"]) == 3 and cmm["registration_rms_mm"] < 0.01


def test_bad_station_files_exit_2_and_an_unreachable_cmm_3(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[cmm]\nurl = 7\n")
    code, text = _check("--station", str(bad))
    assert code == 2 and "cmm" in str(text)
    empty = tmp_path / "empty.toml"
    empty.write_text('name = "bay 2"\n')
    code, text = _check("--station", str(empty))
    assert code == 2 and "names no device" in str(text)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    station = _station(tmp_path / "gone.toml", f"socket://127.0.0.1:{port}", np.eye(4))
    code, report = _check("--station", str(station), "--json")
    assert code == 3 and not report["ok"] and report["devices"][0]["problems"]

