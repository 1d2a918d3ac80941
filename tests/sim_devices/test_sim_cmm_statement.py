"""The uncertainty the simulated CMM states covers what the CMM driver measures with it, and reaches the station.

The simulator's configuration states U (k = 2) per sphere-centre coordinate, as a real CMM's calibration certificate
does for the station file; by default 2 x the touch-point noise. One sphere measured 60 times over a pty (nine
touches of the stylus ball, its centre fitted here at R + r from the reported ball centres, by a test client rather
than hilcal's driver): the fitted centre's error per coordinate (scatter and bias, against the true centre computed
here) must lie within the stated standard uncertainty U / 2, and not far below it.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from hilcal.robot import default_robot
from procedures.station import station_from_channels
from sim_devices.cmm.server import start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_config import SimCmmConfig, SimConfig
from sim_devices.simulator import start_sim
from tests.conformance.ipp_client import IppClient, IppSession

pytestmark = pytest.mark.timeout(60)
ROBOT = default_robot()
R = ROBOT.sphere_radius_mm
TILT = np.radians(60.0)
DIRECTIONS = np.array([[0.0, 0.0, 1.0], *([np.sin(TILT) * np.cos(a), np.sin(TILT) * np.sin(a), np.cos(TILT)]
                                          for a in np.radians(np.arange(0.0, 360.0, 45.0)))])


def measure_sphere(cmm: IppSession, nominal: np.ndarray, ball_mm: float) -> np.ndarray:
    """Nine touches on a sphere near ``nominal``; the centre at R + r from the reported ball centres."""
    balls = []
    for n in DIRECTIONS:
        cmm.goto(nominal + (R + 40.0) * np.array([0.0, 0.0, 1.0]))
        cmm.goto(nominal + (R + 40.0) * n)
        balls.append(cmm.ptmeas(nominal + R * n, n))
    balls_mm = np.array(balls)
    fit = least_squares(lambda c: np.linalg.norm(balls_mm - c, axis=1) - (R + ball_mm), nominal)
    return fit.x


def test_default_statement_is_twice_the_touch_noise_and_can_be_set() -> None:
    assert SimCmmConfig(noise_sigma_mm=0.003).stated_uncertainty() == pytest.approx(0.006)
    assert SimCmmConfig(noise_sigma_mm=0.003, stated_uncertainty_mm=0.001).stated_uncertainty() == 0.001
    assert SimCmmConfig(noise_sigma_mm=0.0).stated_uncertainty() is None  # a noiseless CMM states nothing


def test_stated_uncertainty_covers_the_measured_sphere_centre() -> None:
    config = SimCmmConfig(time_scale=0.0, tcp_port=None)
    rig = SimulatedRig(ROBOT, RigConfig(seed=3, errors=load_errors("table2"), cmm_noise_mm=0.0))
    true_centre = rig.to_cmm(ROBOT.base_spheres)[0]  # a base sphere: it does not move
    server = start_cmm_server(ROBOT, rig, config.server_config(default_seed=5))
    client = IppClient.pty(server.path)
    try:
        cmm = IppSession(client)
        cmm.start()
        ball_mm = config.tools[0].ball_radius_mm
        centres = np.array([measure_sphere(cmm, true_centre + 0.3, ball_mm) for _ in range(60)])
    finally:
        client.close()
        server.close()
    error_rms_mm = np.sqrt(np.mean((centres - true_centre) ** 2, axis=0))
    u_mm = config.stated_uncertainty() / 2.0
    assert np.all(error_rms_mm <= u_mm), (error_rms_mm, u_mm)
    assert np.all(error_rms_mm >= u_mm / 3.0), (error_rms_mm, u_mm)


def test_the_simulated_station_carries_the_statement() -> None:
    """The simulator publishes its CMM's identity and statement; the station of `hilcal run --sim` has them."""
    config = SimConfig.model_validate({"cmm": {"time_scale": 0.0, "noise_sigma_mm": 0.0025}})
    with start_sim(config) as sim:
        station = station_from_channels(sim.channels())
    assert station.cmm.stated_uncertainty_mm == pytest.approx(0.005)
    assert "0.0025 mm" in station.cmm.identity
