"""The CMM driver finds spheres that are not where predicted, against the simulated CMM over a real pty, and never
crashes its stylus ball: the simulator stops on any positioning move, approach or retract of the ball into a sphere
(``on_collision = "stop"``, 2504) and counts it; every test ends with that count at zero.

The searches descend from above the highest the ball could meet the sphere: with a 12.7 mm sphere, a 1.5 mm ball and
the server's default Approach, Search and Retract of 10 mm, a driver that took the ball for a point put its nominal
point below the sphere's top and its approach position inside the sphere (the 2504 of the field report). True sphere
centres come from the rig (``rig.to_cmm``) with scipy rotations, independently of the driver.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.cmm.ippdme import IppDmeCmm, IppDmeConfig
from hilcal.acquisition.spheres import park_height_mm
from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig, ToolConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
R_MM = ROBOT.sphere_radius_mm


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))


@pytest.fixture(scope="module", params=[1.5, 2.5], ids=["ball1.5", "ball2.5"])
def server(rig: SimulatedRig, request: pytest.FixtureRequest) -> Iterator[CmmServerHandle]:
    tool = ToolConfig(name="Probe1", ball_radius_mm=request.param)
    handle = start_cmm_server(ROBOT, rig, CmmServerConfig(seed=3, time_scale=0.0, noise_sigma_mm=0.002,
                                                          on_collision="stop", tools=(tool,)))
    yield handle
    handle.close()


@pytest.fixture
def cmm(server: CmmServerHandle) -> Iterator[IppDmeCmm]:
    with IppDmeCmm(server.path, IppDmeConfig(ack_timeout_s=0.5, query_timeout_s=1.0, motion_timeout_s=2.0)) as driver:
        driver.start_session()
        driver.home()
        yield driver
    assert server.collisions == 0, "the stylus ball crashed into a sphere"


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


def test_a_sphere_off_by_far_more_than_its_radius_is_searched_for_and_found(cmm: IppDmeCmm, rig: SimulatedRig) -> None:
    true_centre = _base_centres(rig)[0]
    offset = np.array([18.0, -21.0, 6.0])
    m = cmm.measure_sphere(true_centre + offset, R_MM, bound_mm=35.0)
    assert m.search is not None and m.search.touches >= 1
    assert np.linalg.norm(m.centre_mm - true_centre) < 0.01
    assert m.offset_from_nominal_mm == pytest.approx(np.linalg.norm(offset), abs=0.01)


def test_a_sphere_outside_its_stated_bound_is_searched_for_after_the_pattern_misses(cmm: IppDmeCmm,
                                                                                     rig: SimulatedRig) -> None:
    """25 mm below where it is said to be within 2 mm: every touch of the pattern misses, a search finds it. (A bound
    is what keeps the ball's approach positions out of the sphere: 25 mm to the side, a ring touch would start inside
    it, and the CMM would stop on the collision.)"""
    true_centre = _base_centres(rig)[1]
    m = cmm.measure_sphere(true_centre + np.array([0.0, 0.0, 25.0]), R_MM, bound_mm=2.0)
    assert m.search is not None
    assert np.linalg.norm(m.centre_mm - true_centre) < 0.01


def test_a_sphere_higher_than_predicted_is_approached_from_above_its_top(cmm: IppDmeCmm, rig: SimulatedRig) -> None:
    """The sphere stands 8 mm higher than predicted, within the 10 mm bound: the first descent starts above where the
    ball could meet it (R + r + bound + margin above the prediction), not at a nominal point below its top."""
    true_centre = _base_centres(rig)[2]
    m = cmm.measure_sphere(true_centre - np.array([0.0, 0.0, 8.0]), R_MM, bound_mm=10.0)
    assert m.search is not None and np.linalg.norm(m.centre_mm - true_centre) < 0.01


@pytest.mark.parametrize("shift", [[0.0, 0.0, -50.0], [35.0, -35.0, 10.0]])
def test_a_pose_with_the_station_alignment_far_off_is_measured(cmm: IppDmeCmm, rig: SimulatedRig,
                                                               shift: list[float]) -> None:
    """The station says 10 mm, the alignment is 50 mm off; straight down too: the spheres stand 50 mm higher than
    predicted, so a search that started just above its bound would start inside the first one. The server's stroke
    (Approach + Search at most 50 + 50 mm) is shorter than such a descent: it continues down what it swept clear."""
    commanded = np.array([100.0, 50.0, 3100.0, 2.0, -1.0, 4.0])
    rig.move_to_lengths(rig.controller_ik(commanded))
    result = cmm.measure_pose(ROBOT, _alignment(rig, np.array(shift)), commanded, alignment_tolerance=(10.0, 0.2),
                              registered=False)
    truth = rig.true_pose()
    assert np.max(np.abs(result.pose[:3] - truth[:3])) < 0.01
    assert result.extra["searched_spheres"] >= 1 and result.extra["largest_search_offset_mm"] > 40.0
    np.testing.assert_allclose(result.refined_alignment[:3, 3], _alignment(rig, np.zeros(3))[:3, 3], atol=0.02)


def test_the_ball_waits_above_the_platform_after_a_pose(cmm: IppDmeCmm, rig: SimulatedRig) -> None:
    commanded = np.array([-150.0, 80.0, 3300.0, -3.0, 4.0, -6.0])
    rig.move_to_lengths(rig.controller_ik(commanded))
    result = cmm.measure_pose(ROBOT, _alignment(rig, np.zeros(3)), commanded)
    T = result.refined_alignment
    in_base = T[:3, :3].T @ (cmm.where() - T[:3, 3])
    assert in_base[2] >= park_height_mm(ROBOT, cmm.stylus())  # the ball's bottom above every platform sphere's top
