"""The CMM driver finds spheres that are not where predicted, over a real pty against the simulated CMM, and never
crashes its probe: the simulator stops on any positioning move through a sphere (on_collision = "stop") and counts
it; every test ends with that count at zero.

True sphere centres come from the rig (``rig.to_cmm``) with scipy rotations, independently of the driver.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.cmm.serial import SerialCmm, SerialCmmConfig
from hilcal.acquisition.spheres import park_height_mm
from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
R_MM = ROBOT.sphere_radius_mm


@pytest.fixture
def rig() -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))


@pytest.fixture
def server(rig: SimulatedRig) -> Iterator[CmmServerHandle]:
    handle = start_cmm_server(ROBOT, rig, CmmServerConfig(seed=3, time_scale=0.0, noise_sigma_mm=0.002,
                                                          on_collision="stop"))
    yield handle
    assert handle.collisions == 0, "the probe crashed into a sphere"
    handle.close()


@pytest.fixture
def cmm(server: CmmServerHandle) -> Iterator[SerialCmm]:
    driver = SerialCmm(server.path, SerialCmmConfig(ack_timeout_s=0.5, command_timeout_s=1.0))
    driver.start_session()
    driver.home()
    yield driver
    driver.close()


def _base_centres(rig: SimulatedRig) -> np.ndarray:
    return rig.to_cmm(ROBOT.base_spheres)


def _alignment(rig: SimulatedRig, shift_mm: np.ndarray) -> np.ndarray:
    """T_cmm<-base from the rig's CMM placement, shifted."""
    c = rig.config.cmm_pose.as_array()
    R = Rotation.from_euler("xyz", c[3:], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ c[:3] + shift_mm
    return T


def test_a_sphere_off_by_far_more_than_its_radius_is_searched_for_and_found(cmm: SerialCmm, rig: SimulatedRig) -> None:
    true_centre = _base_centres(rig)[0]
    offset = np.array([18.0, -21.0, 6.0])
    m = cmm.measure_sphere(true_centre + offset, R_MM, bound_mm=35.0)
    assert m.search is not None and m.search.touches >= 1
    assert np.linalg.norm(m.centre_mm - true_centre) < 0.01
    assert m.offset_from_nominal_mm == pytest.approx(np.linalg.norm(offset), abs=0.01)


def test_a_sphere_outside_its_stated_bound_is_searched_for_after_the_pattern_misses(cmm: SerialCmm,
                                                                                     rig: SimulatedRig) -> None:
    true_centre = _base_centres(rig)[1]
    m = cmm.measure_sphere(true_centre + np.array([0.0, 25.0, 0.0]), R_MM, bound_mm=2.0)
    assert m.search is not None
    assert np.linalg.norm(m.centre_mm - true_centre) < 0.01


@pytest.mark.parametrize("shift", [[0.0, 0.0, -50.0], [35.0, -35.0, 10.0]])
def test_a_pose_with_the_station_alignment_far_off_is_measured(cmm: SerialCmm, rig: SimulatedRig,
                                                               shift: list[float]) -> None:
    """The station says 10 mm, the alignment is 50 mm off; straight down too: the spheres stand 50 mm higher than
    predicted, so a search that started just above its bound would start inside the first one (registered=True
    crashes: tried)."""
    commanded = np.array([100.0, 50.0, 3100.0, 2.0, -1.0, 4.0])
    rig.move_to_lengths(rig.controller_ik(commanded))
    result = cmm.measure_pose(ROBOT, _alignment(rig, np.array(shift)), commanded, alignment_tolerance=(10.0, 0.2),
                              registered=False)
    truth = rig.true_pose()
    assert np.max(np.abs(result.pose[:3] - truth[:3])) < 0.01
    assert result.extra["searched_spheres"] >= 1 and result.extra["largest_search_offset_mm"] > 40.0
    np.testing.assert_allclose(result.refined_alignment[:3, 3], _alignment(rig, np.zeros(3))[:3, 3], atol=0.02)


def test_the_probe_waits_above_the_platform_after_a_pose(cmm: SerialCmm, rig: SimulatedRig) -> None:
    commanded = np.array([-150.0, 80.0, 3300.0, -3.0, 4.0, -6.0])
    rig.move_to_lengths(rig.controller_ik(commanded))
    result = cmm.measure_pose(ROBOT, _alignment(rig, np.zeros(3)), commanded)
    T = result.refined_alignment
    in_base = T[:3, :3].T @ (cmm.position_mm - T[:3, 3])
    assert in_base[2] >= park_height_mm(ROBOT, 0.0)
