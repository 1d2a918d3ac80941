"""The simulated CMM's stylus is a ball: PtMeas reports the ball's centre at R + r from a tooling sphere's true centre
(6.3.2.13), and the approach, search and retract follow the specification's geometry.

Driven over a real pty with a test client (not hilcal's driver). The true sphere centres are computed here from the
rig (base spheres: ``rig.to_cmm`` of the robot file's layout; platform spheres: ``rig.true_pose()`` with scipy
rotations), independently of the simulator. Directions are taken within 60 degrees of the CMM's +z, so that every
move between them, 60 mm off a sphere's surface, stays clear of it.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig, ToolConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from tests.conformance.ipp_client import IppClient, IppError, IppSession, numbers

pytestmark = pytest.mark.timeout(60)
ROBOT = default_robot()
R = ROBOT.sphere_radius_mm
UP = np.array([0.0, 0.0, 1.0])
CLEAR_MM = 60.0


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))


def true_centres(rig: SimulatedRig) -> np.ndarray:
    """(6, 3) true sphere centres in the CMM frame, platform spheres first."""
    pose = rig.true_pose()
    platform = Rotation.from_euler("xyz", pose[3:], degrees=True).apply(ROBOT.platform_spheres) + pose[:3]
    return rig.to_cmm(np.vstack([platform, ROBOT.base_spheres]))


def directions(count: int, seed: int) -> np.ndarray:
    """Unit vectors within 60 degrees of +z."""
    rng = np.random.default_rng(seed)
    tilt = np.radians(rng.uniform(0.0, 60.0, count))
    azimuth = rng.uniform(0.0, 2 * np.pi, count)
    return np.column_stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])


@contextmanager
def cmm(rig: SimulatedRig, **config: object) -> Iterator[tuple[CmmServerHandle, IppSession]]:
    server = start_cmm_server(ROBOT, rig, CmmServerConfig(seed=5, time_scale=0.0, **config))
    client = IppClient.pty(server.path)
    try:
        session = IppSession(client)
        session.start()
        yield server, session
    finally:
        client.close()
        server.close()


def touch_from_above(session: IppSession, centre: np.ndarray, n: np.ndarray) -> list[float]:
    """Over the sphere, out along n, then PtMeas at the surface point along n."""
    session.goto(centre + (R + CLEAR_MM) * UP)
    session.goto(centre + (R + CLEAR_MM) * n)
    return session.ptmeas(centre + R * n, n)


@pytest.mark.parametrize("ball_mm", [0.0, 1.5, 3.0])
def test_the_reported_ball_centre_lies_at_R_plus_r_from_the_true_centre(rig: SimulatedRig, ball_mm: float) -> None:
    tool = ToolConfig(name="Probe1", ball_radius_mm=ball_mm)
    sigma = 0.002
    with cmm(rig, tools=(tool,), noise_sigma_mm=sigma) as (_, session):
        session.call("OnPtMeasReport(X(), Y(), Z(), IJK(), ER(), Q())")
        [radius] = session.call("GetProp(Tool.AvrRadius())").data
        assert numbers(radius) == [pytest.approx(ball_mm)]
        gaps, offsets = [], []
        for k, centre in enumerate(true_centres(rig)):
            for n in directions(4, seed=k):
                report = touch_from_above(session, centre, n)
                ball, ijk, (er, q) = np.array(report[:3]), np.array(report[3:6]), report[6:]
                gaps.append(np.linalg.norm(ball - centre) - (R + ball_mm))
                offsets.append(np.linalg.norm(np.cross(ball - centre, n)))  # off the probing line
                np.testing.assert_allclose(ijk, n, atol=1e-6)  # IJK(): the probing direction
                assert (er, q) == (pytest.approx(ball_mm), 0.0)  # ER(): the ball's radius; Q(): a good point
    assert np.abs(gaps).max() < 5 * sigma * np.sqrt(3)
    assert np.std(gaps) == pytest.approx(sigma, rel=0.5)  # the noise is there, and its size
    assert np.max(offsets) < 5 * sigma * np.sqrt(2)


def test_a_noiseless_touch_is_exact_and_a_point_probe_reports_the_surface(rig: SimulatedRig) -> None:
    with cmm(rig, tools=(ToolConfig(name="Probe1", ball_radius_mm=2.0),), noise_sigma_mm=0.0) as (_, session):
        centre = true_centres(rig)[4]
        for n in directions(5, seed=9):
            ball = np.array(touch_from_above(session, centre, n))
            np.testing.assert_allclose(ball, centre + (R + 2.0) * n, atol=2e-6)
        session.call('ChangeTool("RefTool")')  # RefTool: a ball of radius 0, the surface itself
        for n in directions(3, seed=10):
            np.testing.assert_allclose(touch_from_above(session, centre, n), centre + R * n, atol=2e-6)


def test_approach_search_and_retract_follow_6_3_2_13(rig: SimulatedRig) -> None:
    r = 1.5
    with cmm(rig, noise_sigma_mm=0.0) as (server, session):
        centre = true_centres(rig)[3]
        nominal = centre + R * UP
        session.goto(centre + (R + CLEAR_MM) * UP)
        start = server.machine_time_s
        ball = np.array(session.ptmeas(nominal, UP))
        np.testing.assert_allclose(ball, centre + (R + r) * UP, atol=1e-6)
        # Retract 10 (its default, >= 0): the contact position shifted by 10 along IJK
        np.testing.assert_allclose(session.position(), ball + 10.0 * UP, atol=1e-6)
        # the machine's time: travel to the approach position (nominal + (10 + r) IJK) at 250 mm/s, 10 mm of
        # probing stroke at 10 mm/s down to the contact, the touch's 0.05 s, the 10 mm retract at 250 mm/s
        travel = (CLEAR_MM - 10.0 - r) / 250.0
        assert server.machine_time_s - start == pytest.approx(travel + 10.0 / 10.0 + 0.05 + 10.0 / 250.0)
        session.call("SetProp(Tool.PtMeasPar.Retract(-1))")  # Retract < 0: back to the approach position
        session.ptmeas(nominal, UP)
        np.testing.assert_allclose(session.position(), nominal + (10.0 + r) * UP, atol=1e-6)
        # nominal 4 mm above the surface with Search 3: the ball's surface may go 3 mm beyond nominal, no further
        session.call("SetProp(Tool.PtMeasPar.Search(3))")
        with pytest.raises(IppError) as missed:
            session.ptmeas(centre + (R + 4.0) * UP, UP)
        assert missed.value.codes == [1006]
        session.clear()  # 1006 has severity 2 (8.2): the session was in its error state
        np.testing.assert_allclose(session.position(), centre + (R + 4.0 + 10.0 + r) * UP, atol=1e-6)  # back
        ball = np.array(session.ptmeas(centre + (R + 2.5) * UP, UP))  # 2.5 mm: within the search
        np.testing.assert_allclose(ball, centre + (R + r) * UP, atol=1e-6)


def test_ptmeas_without_ijk_probes_from_where_the_ball_is(rig: SimulatedRig) -> None:
    """6.3.2.13: no IJK, the direction from the nominal point to the last position (here that of the last GoTo)."""
    with cmm(rig, noise_sigma_mm=0.0) as (_, session):
        centre = true_centres(rig)[0]
        n = directions(1, seed=3)[0]
        session.goto(centre + (R + CLEAR_MM) * UP)
        session.goto(centre + (R + 35.0) * n)
        x, y, z = centre + R * n
        [data] = session.call(f"PtMeas(X({x:.6f}), Y({y:.6f}), Z({z:.6f}))").data
        np.testing.assert_allclose(numbers(data), centre + (R + 1.5) * n, atol=1e-6)
        x, y, z = session.position()
        with pytest.raises(IppError) as no_norm:  # the nominal point where the ball is: no direction
            session.call(f"PtMeas(X({x:.6f}), Y({y:.6f}), Z({z:.6f}))")
        assert no_norm.value.codes == [1010]


def test_a_tool_change_resets_the_parameters_and_notool_does_not_measure(rig: SimulatedRig) -> None:
    with cmm(rig, tools=(ToolConfig(name="Probe1"), ToolConfig(name="Probe2", ball_radius_mm=4.0))) as (_, session):
        session.call("SetProp(Tool.PtMeasPar.Search(20), Tool.GoToPar.Speed(100))")
        [data] = session.call("GetProp(Tool.PtMeasPar.Search(), Tool.GoToPar.Speed.Act())").data
        assert data == "Tool.PtMeasPar.Search(20.000000), Tool.GoToPar.Speed.Act(100.000000)"
        clamped = session.call("SetProp(Tool.PtMeasPar.Search(1000))", check=False)  # beyond Max: clamped, 0504
        assert clamped.errors == [504] and clamped.markers == "&!%"
        [data] = session.call("GetProp(Tool.PtMeasPar.Search(), Tool.PtMeasPar.Search.Max())").data
        assert numbers(data) == [50.0, 50.0]
        session.call("Get(X())")  # a warning does not put the session in its error state (8.1)
        session.call('ChangeTool("Probe2")')
        [data] = session.call("GetProp(Tool.Name(), Tool.AvrRadius(), Tool.PtMeasPar.Search())").data
        assert data == 'Tool.Name("Probe2"), Tool.AvrRadius(4.000000), Tool.PtMeasPar.Search(10.000000)'
        assert [numbers(d) for d in session.call("EnumTools()").data] == [[], [], [], []]
        assert session.call("EnumTools()").data == ['"RefTool"', '"NoTool"', '"Probe1"', '"Probe2"']
        session.call('ChangeTool("NoTool")')
        session.goto(true_centres(rig)[3] + 100.0 * UP)  # NoTool moves
        with pytest.raises(IppError) as refused:
            session.ptmeas(true_centres(rig)[3] + R * UP, UP)
        assert refused.value.codes == [507]  # but does not measure (6.3.2.14; NIST's checker: 0507)
