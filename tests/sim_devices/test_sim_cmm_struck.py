"""The simulated CMM notices a platform that carries a tooling sphere through the parked probe: a crash ("struck").

Driven over a real pty with a test client (not hilcal's driver); the platform is moved as the controller moves it
(``rig.move_to_lengths`` of the controller's IK). The machine notices the strike at the next command: an unsolicited
``E0000 ! Error(3, 2504, ...)`` (6.2.4) puts the session in its error state, so that command is refused (0511, 0514)
until ClearAllErrors. Sphere centres are computed here from
``rig.true_pose()`` with scipy rotations and ``rig.to_cmm``, independently of the simulator; every probe position is
laid out by hand beside a platform sphere: ahead of it on its way, behind it, beside or above its way, on the arc or
the chord of a turn. The stylus ball (radius 1.5 mm) is struck when a sphere's surface comes within its radius.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from structlog.testing import capture_logs

from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from tests.conformance.ipp_client import IppClient, IppError, IppSession

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
R = ROBOT.sphere_radius_mm
BALL = 1.5
REFUSED = [511, 514]
STRUCK = 'E0000 ! Error(3, 2504, "PlatformStruckProbe", "Collision")'
SHIFT_MM = 60.0
"""The platform's move: this far along the base x axis (from the home pose)."""
K = 0
"""The platform sphere the tests park the probe next to."""


def platform_centres(rig: SimulatedRig) -> np.ndarray:
    """(3, 3) true platform sphere centres in the CMM frame."""
    pose = rig.true_pose()
    rot = Rotation.from_euler("xyz", pose[3:], degrees=True)  # extrinsic xyz = Rz Ry Rx
    return rig.to_cmm(rot.apply(ROBOT.platform_spheres) + pose[:3])


def cmm_direction(rig: SimulatedRig, base_vector: np.ndarray) -> np.ndarray:
    """A base-frame direction in the CMM frame (unit)."""
    d = rig.to_cmm(np.asarray(base_vector, dtype=float)) - rig.to_cmm(np.zeros(3))
    return d / np.linalg.norm(d)


def move_platform(rig: SimulatedRig, shift_mm: float) -> None:
    """The platform to the home pose shifted along base x, as the controller commands it."""
    rig.move_to_lengths(rig.controller_ik(ROBOT.home + np.array([shift_mm, 0.0, 0.0, 0.0, 0.0, 0.0])))


def distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return float(np.linalg.norm(a + t * (b - a) - p))


def collision_events(logs: list[dict]) -> list[dict]:
    return [e for e in logs if e["event"] == "cmm_sim.collision"]


@pytest.fixture
def rig() -> SimulatedRig:
    rig = SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))
    move_platform(rig, 0.0)
    return rig


@contextmanager
def open_cmm(rig: SimulatedRig, **config: object) -> Iterator[tuple[CmmServerHandle, IppSession]]:
    server = start_cmm_server(ROBOT, rig, CmmServerConfig(seed=3, time_scale=0.0, noise_sigma_mm=0.0, **config))
    client = IppClient.pty(server.path)
    try:
        cmm = IppSession(client)
        cmm.start()
        yield server, cmm
    finally:
        client.close()
        server.close()


@pytest.fixture
def default_cmm(rig: SimulatedRig) -> Iterator[tuple[CmmServerHandle, IppSession]]:
    """The simulated CMM with its default ``on_collision`` (stop)."""
    with open_cmm(rig) as (server, cmm):
        assert server.config.on_collision == "stop"
        yield server, cmm


def refused_after_strike(cmm: IppSession, point: np.ndarray) -> IppError:
    """A GoTo to ``point`` that the strike noticed at it refuses; the unsolicited error came with it."""
    with pytest.raises(IppError) as refused:
        cmm.goto(point)
    assert refused.value.codes == REFUSED and refused.value.transaction.others == [STRUCK]
    return refused.value


def park(cmm: IppSession, rig: SimulatedRig, point: np.ndarray) -> None:
    """Down onto `point` from 300 mm above it (clear of every sphere: the tests check no collision)."""
    cmm.goto(point + 300.0 * cmm_direction(rig, [0.0, 0.0, 1.0]))
    cmm.goto(point)


def test_a_platform_sphere_carried_through_the_parked_probe_is_a_latched_collision(default_cmm, rig) -> None:
    server, cmm = default_cmm
    before = platform_centres(rig)[K]
    x = cmm_direction(rig, [1.0, 0.0, 0.0])
    park(cmm, rig, before + (R + 30.0) * x)
    touched = np.array(cmm.ptmeas(before + R * x, x))  # a touch on the sphere's side, on its way
    assert abs((touched - before) @ x - (R + BALL)) < 1e-5 and server.collisions == 0
    ahead = before + (R + BALL + 10.0) * x  # where the retract (10 mm) left the ball
    np.testing.assert_allclose(cmm.position(), ahead, atol=1e-6)
    move_platform(rig, SHIFT_MM)  # the sphere sweeps through the ball and comes to rest beyond it
    after = platform_centres(rig)[K]
    assert distance_to_segment(ahead, before, after) < 1.0  # the ball stood on the sphere's way, near its middle
    assert np.linalg.norm(after - ahead) > R + 20.0  # and is clear of where the sphere stopped
    with capture_logs() as logs:
        refused_after_strike(cmm, ahead + 50.0 * cmm_direction(rig, [0.0, 0.0, 1.0]))
    [event] = collision_events(logs)
    assert event["kind"] == "struck" and event["code"] == 2504 and event["stopped"] and event["command"] is None
    assert event["sphere"] == K and event["sphere_name"] == "platform sphere 1" and event["collisions"] == 1
    np.testing.assert_allclose(event["contact_mm"], ahead, atol=1e-3)  # where the ball stood
    np.testing.assert_allclose(event["from_mm"], before, atol=1e-3)  # the sphere's way
    np.testing.assert_allclose(event["to_mm"], after, atol=1e-3)
    assert server.collisions == 1
    with pytest.raises(IppError) as still:  # the error state, as after any crash, and counted once
        cmm.ptmeas(after + R * x, x)
    assert still.value.codes == REFUSED and server.collisions == 1
    cmm.clear()
    np.testing.assert_allclose(cmm.position(), ahead, atol=1e-6)  # the ball was left where it stood
    cmm.goto(ahead + 50.0 * cmm_direction(rig, [0.0, 0.0, 1.0]))
    assert server.collisions == 1


@pytest.mark.parametrize("where", ["behind", "beside", "above"])
def test_a_probe_parked_off_the_spheres_way_is_not_struck(default_cmm, rig, where: str) -> None:
    server, cmm = default_cmm
    before = platform_centres(rig)[K]
    x, y, z = (cmm_direction(rig, axis) for axis in np.eye(3))
    spot = {"behind": before - (R + 10.0) * x,  # the sphere moves away from it
            "beside": before + 0.5 * SHIFT_MM * x + (R + 3.0) * y,  # 3 mm off the way's edge: 1.5 mm off the ball
            "above": before + 0.5 * SHIFT_MM * x + 200.0 * z}[where]
    park(cmm, rig, spot)
    with capture_logs() as logs:
        move_platform(rig, SHIFT_MM)
        assert distance_to_segment(spot, before, platform_centres(rig)[K]) > R + 2.0
        cmm.goto(spot + 50.0 * z)
        touched = np.array(cmm.ptmeas(platform_centres(rig)[K] + R * z, z))  # the moved sphere's top: works on
    assert abs((touched - platform_centres(rig)[K]) @ z - (R + BALL)) < 1e-5
    assert not collision_events(logs) and server.collisions == 0


def test_a_sphere_that_stops_over_the_probe_pushes_it_to_its_surface(default_cmm, rig) -> None:
    server, cmm = default_cmm
    before = platform_centres(rig)[K]
    x = cmm_direction(rig, [1.0, 0.0, 0.0])
    spot = before + (R + 10.0) * x
    park(cmm, rig, spot)
    move_platform(rig, R + 12.0)  # the sphere's centre stops 2 mm past the ball's
    after = platform_centres(rig)[K]
    assert np.linalg.norm(after - spot) < R - 1.0
    refused_after_strike(cmm, spot)
    assert server.collisions == 1
    cmm.clear()
    assert np.linalg.norm(np.array(cmm.position()) - after) == pytest.approx(R + BALL)  # pushed to the surface
    cmm.goto(after - (R + 20.0) * x)  # from the surface the sphere pushed it to, away from the sphere: no crash
    assert server.collisions == 1
    with pytest.raises(IppError):
        cmm.goto(after + (R + 20.0) * x)  # but not through the sphere
    assert server.collisions == 2


def test_counting_mode_counts_a_strike_without_latching(rig) -> None:
    with open_cmm(rig, on_collision="count") as (server, cmm):
        before = platform_centres(rig)[K]
        x = cmm_direction(rig, [1.0, 0.0, 0.0])
        park(cmm, rig, before + (R + 10.0) * x)
        move_platform(rig, SHIFT_MM)
        with capture_logs() as logs:
            cmm.goto(before + (R + 10.0) * x + 50.0 * cmm_direction(rig, [0.0, 0.0, 1.0]))
        assert [(e["kind"], e["stopped"]) for e in collision_events(logs)] == [("struck", False)]
        assert server.collisions == 1


def turn_platform(rig: SimulatedRig, yaw_deg: float) -> None:
    """The platform to the home pose turned about its vertical axis, as the controller commands it."""
    rig.move_to_lengths(rig.controller_ik(ROBOT.home + np.array([0.0, 0.0, 0.0, 0.0, 0.0, yaw_deg])))


@pytest.mark.parametrize("where", ["on the arc", "on the chord"])
def test_a_turning_platform_strikes_along_its_arc_not_its_chord(default_cmm, rig, where: str) -> None:
    """A 20 degree turn swings a sphere 1 m out on an arc 15 mm outside the chord between its ends: a probe on the arc
    is struck, one in the middle of the chord is not (the sphere swings around it)."""
    server, cmm = default_cmm
    turn_platform(rig, 0.0)
    middle = platform_centres(rig)[K]  # where the sphere is halfway through the turn
    turn_platform(rig, 10.0)
    end = platform_centres(rig)[K]
    turn_platform(rig, -10.0)
    start = platform_centres(rig)[K]
    chord = 0.5 * (start + end)
    assert np.linalg.norm(middle - chord) > R + 2.0  # the chord misses the arc's middle by more than a radius
    spot = middle if where == "on the arc" else chord
    park(cmm, rig, spot)
    assert server.collisions == 0
    turn_platform(rig, 10.0)
    with capture_logs() as logs:
        if where == "on the arc":
            refused_after_strike(cmm, spot + 50.0 * cmm_direction(rig, [0.0, 0.0, 1.0]))
        else:
            cmm.goto(spot + 50.0 * cmm_direction(rig, [0.0, 0.0, 1.0]))
    assert [e["kind"] for e in collision_events(logs)] == (["struck"] if where == "on the arc" else [])
    assert server.collisions == (1 if where == "on the arc" else 0)
