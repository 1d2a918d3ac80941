"""The simulated laser tracker's physics and protocol, seen over TCP: its noise against the MPE along and across the
beam, the refraction of a wrong pressure, the ATR search radius, what it answers to commands it does not know, and
``hilcal sim --instrument tracker``.

The expectations are written here from the tracker's specification: U = 15 µm + 6 µm/m read as k = 2 (σ = U/2 along
the beam and across it), NIST's shop-floor equation for the refractive index of air, the station this test places.
"""

from __future__ import annotations

import socket
import struct
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.tracker.base import Environment, ReflectorNotFound, TrackerNotSupported
from drivers.tracker.emscon import EmsconConfig, EmsconTracker
from hilcal.protocols import emscon
from hilcal.robot import default_robot
from sim_devices.launcher import _describe, spawn_sim_subprocess, stop_sim_subprocess
from sim_devices.sim_config import SimConfig
from sim_devices.simulator import start_sim
from sim_devices.tracker.config import Air, Station, TrackerServerConfig
from sim_devices.tracker.server import TrackerServerHandle, start_tracker_server

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
STATION = [-3000.0, -5500.0, 2500.0, 0.0, 0.0, 70.0]
FAST = dict(host="127.0.0.1", command_timeout_s=1.0, move_timeout_s=1.0, measure_timeout_s=1.0,
            initialize_timeout_s=1.0)


def station() -> Station:
    return Station(**dict(zip(("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"), STATION, strict=True)))


def base_in_tracker() -> np.ndarray:
    """(3, 3) base sphere centres in the tracker's frame (p_base = R p_tracker + t)."""
    R = Rotation.from_euler("xyz", STATION[3:], degrees=True).as_matrix()
    return (ROBOT.base_spheres - np.array(STATION[:3])) @ R


def nist_index(t_c: float, p_hpa: float, rh_pct: float) -> float:
    """NIST's shop-floor equation for the refractive index of air (p in kPa inside)."""
    return 1.0 + 7.86e-4 * (p_hpa / 10.0) / (273.0 + t_c) - 1.5e-11 * rh_pct * (t_c**2 + 160.0)


def serve(**overrides: Any) -> TrackerServerHandle:
    config = TrackerServerConfig(seed=21, time_scale=0.0, station=station(), **overrides)
    return start_tracker_server(lambda: ROBOT.base_spheres.copy(), config)


@pytest.fixture
def noiseless() -> Iterator[tuple[TrackerServerHandle, EmsconTracker]]:
    with serve(noise_scale=0.0, air=Air(temperature_c=18.0, pressure_hpa=990.0, humidity_pct=35.0)) as server, \
            EmsconTracker(EmsconConfig(port=server.port, **FAST)) as tracker:
        tracker.initialize()
        tracker.setup(Environment(18.0, 990.0, 35.0))  # the true air: no refraction error
        yield server, tracker


def test_noise_is_half_the_mpe_along_and_across_the_beam() -> None:
    q = base_in_tracker()[1]
    d = float(np.linalg.norm(q))
    sigma = (15.0 + 6.0 * d / 1000.0) / 2000.0
    with serve() as server, EmsconTracker(EmsconConfig(port=server.port, **FAST)) as tracker:
        tracker.initialize()
        tracker.setup()
        tracker.go_position(q)
        tracker.find_reflector(d)
        errors = np.array([tracker.measure().xyz_mm - q for _ in range(400)])
    beam = q / d
    across = np.linalg.svd(np.eye(3) - np.outer(beam, beam))[0][:, :2]
    n = len(errors)
    for name, e in (("x", errors[:, 0]), ("y", errors[:, 1]), ("z", errors[:, 2]), ("along", errors @ beam),
                    ("across 1", errors @ across[:, 0]), ("across 2", errors @ across[:, 1])):
        assert 0.85 * sigma < e.std() < 1.15 * sigma, (name, e.std(), sigma)  # > 4 standard errors of a std
        assert abs(e.mean()) < 4 * sigma / np.sqrt(n), (name, e.mean())


def test_a_wrong_pressure_scales_every_distance(noiseless: tuple[TrackerServerHandle, EmsconTracker]) -> None:
    _, tracker = noiseless
    q = base_in_tracker()[2]
    d = float(np.linalg.norm(q))

    def measured() -> np.ndarray:
        tracker.go_position(q)
        tracker.find_reflector(d)
        return tracker.measure().xyz_mm

    tracker.set_environment(Environment(18.0, 990.0, 35.0))  # the true air
    np.testing.assert_allclose(measured(), q, rtol=0, atol=1e-9)
    tracker.set_environment(Environment(18.0, 1020.0, 35.0))  # 30 hPa too high
    wrong = measured()
    scale = nist_index(18.0, 990.0, 35.0) / nist_index(18.0, 1020.0, 35.0)
    assert float(np.linalg.norm(wrong)) == pytest.approx(d * scale, rel=1e-12)
    assert (1.0 - scale) * 1e6 == pytest.approx(30 * 0.27, rel=0.05)  # about 0.27 ppm per hPa
    np.testing.assert_allclose(wrong / np.linalg.norm(wrong), q / d, atol=1e-12)  # the angles are not affected
    tracker.set_environment(Environment(25.0, 990.0, 35.0))  # 7 K too warm: distances too long
    assert float(np.linalg.norm(measured())) / d == pytest.approx(
        nist_index(18.0, 990.0, 35.0) / nist_index(25.0, 990.0, 35.0), rel=1e-12)


def test_the_atr_finds_a_reflector_within_its_search_radius(
        noiseless: tuple[TrackerServerHandle, EmsconTracker]) -> None:
    _, tracker = noiseless
    q = base_in_tracker()[0]
    d = float(np.linalg.norm(q))
    side = np.cross(q, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    tracker.go_position(q + 40.0 * side)  # within the 50 mm search radius
    tracker.find_reflector(d)
    np.testing.assert_allclose(tracker.measure().xyz_mm, q, atol=1e-6)
    tracker.go_position(q + 70.0 * side)
    with pytest.raises(ReflectorNotFound, match="MeasurementStatusNotReady"):
        tracker.find_reflector(d)
    tracker.set_search_params(100.0, 2.0)
    tracker.find_reflector(d)
    np.testing.assert_allclose(tracker.measure().xyz_mm, q, atol=1e-6)


def test_what_the_tracker_does_not_know(noiseless: tuple[TrackerServerHandle, EmsconTracker]) -> None:
    server, tracker = noiseless
    with pytest.raises(TrackerNotSupported, match="Park"):
        tracker.transact(emscon.new_command(emscon.Command.Park))
    with socket.create_connection(("127.0.0.1", server.port), timeout=2.0) as raw:
        raw.sendall(struct.pack("<iII", 12, int(emscon.DataType.Command), 9999))  # no such command
        raw.sendall(struct.pack("<iII", 12, 4321, 0))  # no such data type
        buf = bytearray()
        while len(buf) < 32:
            buf += raw.recv(64)
    answers = [emscon.decode(p, answer=True) for p in emscon.take_packets(buf)]
    assert [(emscon.packet_type(a), a.command, a.status) for a in answers] == [
        (emscon.DataType.Error, 9999, emscon.ResultStatus.NotImplemented),
        (emscon.DataType.Error, emscon.Command.Unknown, emscon.ResultStatus.InvalidInputData)]


def test_hilcal_sim_serves_the_tracker_instead_of_the_cmm(tmp_path: Path) -> None:
    config = tmp_path / "sim.toml"
    config.write_text("[tracker]\nstation = { " + ", ".join(
        f"{k} = {v}" for k, v in zip(("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"), STATION,
                                      strict=True)) + " }\n")
    proc: subprocess.Popen[bytes] | None = None
    try:
        proc, channels = spawn_sim_subprocess(config, ["--instrument", "tracker"], log_path=tmp_path / "sim.log")
        assert channels["instrument"] == "tracker" and "cmm" not in channels
        tracker_channel = channels["tracker"]
        assert tracker_channel["host"] == "127.0.0.1" and tracker_channel["protocol"] == "emscon"
        approx = np.asarray(channels["tracker_alignment"]) @ np.r_[ROBOT.base_spheres[1], 1.0]
        q = base_in_tracker()[1]
        assert 0.3 < np.linalg.norm(approx[:3] - q) < 10.0  # the published set-up is off by a few mm
        with EmsconTracker(EmsconConfig(port=tracker_channel["port"], **FAST)) as tracker:
            tracker.initialize()
            tracker.setup(Environment(**tracker_channel["air"]))
            point = tracker.measure_point(approx[:3])
        sigma = (15.0 + 6.0 * np.linalg.norm(q) / 1000.0) / 2000.0
        assert np.all(np.abs(point.xyz_mm - q) < 4.5 * sigma)
    finally:
        if proc is not None:
            stop_sim_subprocess(proc)
    with start_sim(SimConfig(instrument="tracker")) as handle:
        assert handle.cmm_server is None and handle.tracker_server is not None
        text = _describe(handle.channels(), handle)
    assert f"tracker       127.0.0.1:{handle.tracker_server.port}" in text and "CMM" not in text


def test_the_tracker_is_set_up_again_after_every_k_poses() -> None:
    """Two reflectors on the "platform", one on the floor: a pose is a round measuring both platform ones (the floor's
    never counts); after every second round the station moves by 40 mm and turns by 0.5 deg, and the tracker then
    reports the floor's reflector where the new station sees it (p_base = R p_tracker + t)."""
    points = ROBOT.base_spheres.copy()
    config = TrackerServerConfig(seed=5, time_scale=0.0, station=station(), noise_scale=0.0, move_every_poses=2)
    with start_tracker_server(lambda: points, config, platform_reflectors=2) as server, \
            EmsconTracker(EmsconConfig(port=server.port, **FAST)) as tracker:
        tracker.initialize()
        tracker.setup()

        def seen_from(pose: np.ndarray) -> np.ndarray:
            R = Rotation.from_euler("ZYX", pose[[5, 4, 3]], degrees=True).as_matrix()
            return (points - pose[:3]) @ R

        def measure(k: int) -> np.ndarray:
            tracker.set_search_params(100.0, 1.0)
            return tracker.measure_point(seen_from(server.station)[k]).xyz_mm

        first = server.station
        np.testing.assert_allclose(first, STATION, atol=1e-9)
        for k in (2, 2, 0, 2, 1, 0):  # the floor's thrice, then round 1 (0, 1); round 2 starts with 0
            measure(k)
        assert server.moves == 0
        measure(1)  # round 2 complete: the tracker is set up again
        assert server.moves == 1
        moved = server.station
        assert np.linalg.norm(moved[:3] - first[:3]) == pytest.approx(40.0, abs=1e-9)
        turn = (Rotation.from_euler("ZYX", moved[[5, 4, 3]], degrees=True)
                * Rotation.from_euler("ZYX", first[[5, 4, 3]], degrees=True).inv())
        assert np.degrees(turn.magnitude()) == pytest.approx(0.5, abs=1e-9)
        np.testing.assert_allclose(measure(2), seen_from(moved)[2], atol=1e-6)
        assert np.linalg.norm(seen_from(moved)[2] - seen_from(first)[2]) > 10.0
