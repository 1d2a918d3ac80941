"""``hilcal sim`` as a separate process: the real drivers on its channels, a clean stop, state across restarts.

The truth is recomputed here from the rig's physics (SimulatedRig with the same seed and errors), never read
from the simulator process; parameter sets are checked against values computed in the test.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.cmm.ippdme import IppDmeCmm
from drivers.controller.hilcal_can import ControllerCan
from drivers.controller.modbus import ControllerParams
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.protocols.controller_states import ControllerState
from hilcal.robot import default_robot
from sim_devices.launcher import SimStartError, spawn_sim_subprocess, stop_sim_subprocess
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_config import SimConfig, SimConfigError, load_sim_config
from sim_devices.sim_state import SimStateError
from sim_devices.simulator import start_sim

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
SEED = 5
POSE = ROBOT.home + np.array([25.0, -15.0, 30.0, 0.8, -0.6, 1.5])
NOMINAL = np.concatenate([ROBOT.a.ravel(), ROBOT.b.ravel(), ROBOT.l0])
Spawn = Callable[..., tuple[subprocess.Popen[bytes], dict[str, Any]]]


def nominal_lengths(pose: np.ndarray) -> np.ndarray:
    return inverse_kinematics(Geometry.nominal(ROBOT), pose)


def write_config(path: Path, text: str = "") -> Path:
    path.write_text(f'[rig]\nseed = {SEED}\nerrors = "table2"\n\n[cmm]\nnoise_sigma_mm = 0.001\n{text}')
    return path


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Spawn]:
    """Start simulator subprocesses; every one is stopped (SIGTERM, then SIGKILL) at the end of the test."""
    procs: list[subprocess.Popen[bytes]] = []

    def start(config: Path | None, *args: str) -> tuple[subprocess.Popen[bytes], dict[str, Any]]:
        proc, channels = spawn_sim_subprocess(config, args, log_path=tmp_path / f"sim{len(procs)}.log")
        procs.append(proc)
        return proc, channels

    yield start
    for proc in procs:
        stop_sim_subprocess(proc)


def test_real_drivers_on_spawned_simulator_then_sigterm(spawn: Spawn, tmp_path: Path) -> None:
    proc, ch = spawn(write_config(tmp_path / "sim.toml"))
    assert ch["robot"] == ROBOT.name and ch["can"]["interface"] == "slcan" and ch["modbus"]["host"] == "127.0.0.1"
    target = nominal_lengths(POSE)
    with ControllerCan(ch["can"], ROBOT, heartbeat_timeout_s=0.3) as can_driver:
        assert can_driver.wait_for_heartbeat(5.0).state is ControllerState.DISABLED
        can_driver.enable()
        measured = can_driver.move_legs(target, timeout_s=10.0)
        np.testing.assert_allclose(measured, target, atol=0.002)
        feedback = can_driver.feedback()
        assert feedback.state is ControllerState.IN_POSITION
        np.testing.assert_allclose(feedback.lengths_mm, target, atol=0.002)
        with ControllerParams(ch["modbus"]["host"], ch["modbus"]["port"], device_id=ch["modbus"]["device_id"]) as p:
            assert p.read_identity().parameter_count == 42
            np.testing.assert_array_equal(p.read_live().to_vector(), NOMINAL.astype(np.float32).astype(float))
        with IppDmeCmm(ch["cmm"]["url"]) as cmm:
            cmm.start_session()
            cmm.home()
            result = cmm.measure_pose(ROBOT, np.asarray(ch["cmm_alignment"]), POSE)
            cmm.end_session()
        can_driver.disable()

    rig = SimulatedRig(ROBOT, RigConfig(seed=SEED, errors=load_errors("table2", ROBOT)))
    rig.move_to_lengths(target)
    truth = rig.true_pose()
    assert np.max(np.abs(truth[:3] - POSE[:3])) > 0.1, "the table2 errors must move the platform off the command"
    np.testing.assert_allclose(result.pose[:3], truth[:3], atol=0.01)
    np.testing.assert_allclose(result.pose[3:], truth[3:], atol=3e-4)
    exact = np.eye(4)
    origin = rig.to_cmm(np.zeros(3))
    exact[:3, :3], exact[:3, 3] = (rig.to_cmm(np.eye(3)) - origin).T, origin
    np.testing.assert_allclose(result.refined_alignment[:3, 3], exact[:3, 3], atol=0.01)
    published = np.asarray(ch["cmm_alignment"])
    base = np.c_[ROBOT.base_spheres, np.ones(3)]
    offsets = np.linalg.norm((base @ published.T - base @ exact.T)[:, :3], axis=1)
    assert np.all((offsets > 0.3) & (offsets < 5.0)), f"published alignment off by {offsets} mm at the spheres"

    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=5.0) == 0
    assert time.monotonic() - t0 < 5.0


def test_state_survives_kill_and_restart(spawn: Spawn, tmp_path: Path) -> None:
    config = write_config(tmp_path / "sim.toml")
    config.write_text('state_file = "state/sim.json"\n' + config.read_text())
    state_file = tmp_path / "state" / "sim.json"
    proc, ch = spawn(config)
    assert ch["state_file"] == str(state_file)
    target = nominal_lengths(POSE)
    new_set = NOMINAL + np.random.default_rng(7).normal(0.0, 0.5, 42)
    with ControllerCan(ch["can"], ROBOT, heartbeat_timeout_s=0.3) as can_driver:
        can_driver.wait_for_heartbeat(5.0)
        can_driver.enable()
        can_driver.move_legs(target, timeout_s=10.0)
        can_driver.disable()
    with ControllerParams(ch["modbus"]["host"], ch["modbus"]["port"]) as params:
        assert params.upload(new_set).outcome == "committed"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=5.0)

    _, ch2 = spawn(config)
    uploaded = new_set.astype(np.float32).astype(float)
    with ControllerParams(ch2["modbus"]["host"], ch2["modbus"]["port"]) as params:
        np.testing.assert_array_equal(params.read_live().to_vector(), uploaded)
        np.testing.assert_array_equal(params.read_backup().to_vector(), NOMINAL.astype(np.float32).astype(float))
        np.testing.assert_array_equal(params.read_saved().to_vector(), NOMINAL.astype(np.float32).astype(float))
    with ControllerCan(ch2["can"], ROBOT, heartbeat_timeout_s=0.3) as can_driver:
        feedback = can_driver.wait_for_heartbeat(5.0)
    assert feedback.state is ControllerState.DISABLED
    strokes = feedback.lengths_mm - uploaded[36:]
    np.testing.assert_allclose(strokes, target - ROBOT.l0, atol=0.002)
    saved = json.loads(state_file.read_text())
    np.testing.assert_array_equal(saved["banks"]["live"], uploaded)


def test_spawn_reports_why_the_simulator_did_not_start(spawn: Spawn, tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[rig]\nseed = 1\nbogus_setting = 3\n")
    with pytest.raises(SimStartError, match="bogus_setting"):
        spawn(bad)


def test_spawned_simulator_stops_when_its_parent_goes(spawn: Spawn) -> None:
    proc, _ = spawn(None, "--seed", "1")
    assert proc.stdin is not None
    proc.stdin.close()
    assert proc.wait(timeout=5.0) == 0


def test_text_mode_prints_channels_and_stops_on_sigint(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "sim_devices.launcher", "--seed", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, start_new_session=True,
        cwd=Path(__file__).resolve().parents[2],
    )
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(3)]
        assert "seed 2" in lines[0] and "/dev/pts/" in lines[1] and "127.0.0.1:" in lines[2]
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=5.0) == 0
    finally:
        stop_sim_subprocess(proc)


# ---------------------------------------------------------------------- in-process: config and state file rules


def test_config_file_paths_and_overrides(tmp_path: Path) -> None:
    config = tmp_path / "sim.toml"
    config.write_text(
        'state_file = "s.json"\n[rig]\nseed = 3\nerrors = "errs/mine.toml"\nleg_resolution_mm = 0.01\n'
        "[controller]\nleg_speed_mm_s = 80.0\n[cmm]\nnoise_sigma_mm = 0.004\n"
    )
    cfg = load_sim_config(config, seed=9)
    assert cfg.state_file == tmp_path / "s.json"
    assert cfg.rig.seed == 9 and cfg.rig.errors == str(tmp_path / "errs" / "mine.toml")
    assert cfg.controller.time_scale == 100.0 and cfg.controller.leg_speed_mm_s == 80.0
    assert cfg.cmm.server_config(cfg.rig.seed).seed == 9
    assert load_sim_config(None, state_file="x.json").state_file == Path("x.json")
    config.write_text("[controller]\nleg_speed = 80.0\n")
    with pytest.raises(SimConfigError, match=r"controller\.leg_speed"):
        load_sim_config(config)
    config.write_text("[rig]\nleg_resolution_mm = -1\n")
    with pytest.raises(SimConfigError, match="leg_resolution_mm"):
        load_sim_config(config)
    with pytest.raises(SimConfigError, match="cannot read"):
        load_sim_config(tmp_path / "missing.toml")


def test_state_file_is_exclusive_and_checked(tmp_path: Path) -> None:
    state_file = tmp_path / "sim.json"
    fast = {"cmm": {"time_scale": 0.0}, "state_file": str(state_file)}
    with start_sim(SimConfig.model_validate(fast)) as sim:
        assert not sim.restored
        assert json.loads(state_file.read_text())["robot"] == ROBOT.name
        with pytest.raises(SimStateError, match="in use by another simulator"):
            start_sim(SimConfig.model_validate(fast), lock_timeout_s=0.2)
    with start_sim(SimConfig.model_validate(fast)) as sim:
        assert sim.restored
    state = json.loads(state_file.read_text())
    state_file.write_text(json.dumps({**state, "robot": "another-robot"}))
    with pytest.raises(SimStateError, match="another-robot"):
        start_sim(SimConfig.model_validate(fast))
    state_file.write_text(json.dumps({**state, "banks": {**state["banks"], "live": [1.0] * 41}}))
    with pytest.raises(SimStateError, match=r"banks\.live"):
        start_sim(SimConfig.model_validate(fast))
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())


def test_commit_is_on_disk_before_the_answer(tmp_path: Path) -> None:
    state_file = tmp_path / "sim.json"
    new_set = NOMINAL + np.random.default_rng(3).normal(0.0, 0.3, 42)
    cfg = SimConfig.model_validate({"cmm": {"time_scale": 0.0}, "state_file": str(state_file)})
    with start_sim(cfg) as sim, ControllerParams("127.0.0.1", sim.channels()["modbus"]["port"]) as params:
        params.upload(new_set)
        on_disk = json.loads(state_file.read_text())["banks"]
        np.testing.assert_array_equal(on_disk["live"], new_set.astype(np.float32).astype(float))
        np.testing.assert_array_equal(on_disk["backup"], NOMINAL.astype(np.float32).astype(float))
        params.rollback()
        on_disk = json.loads(state_file.read_text())["banks"]
        np.testing.assert_array_equal(on_disk["live"], NOMINAL.astype(np.float32).astype(float))
        assert on_disk["commit_counter"] == 2
    assert os.path.exists(state_file)
