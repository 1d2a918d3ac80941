"""The simulated CMM crashes as a real one does: the stylus ball (not a point) entering a tooling sphere on a
positioning move is 2504 Collision with the table's severity 3, the machine stopped where the ball met the surface.

Driven over a real pty with a test client (not hilcal's driver). Sphere centres come from the rig (``rig.to_cmm`` of
the robot's base layout: base spheres do not move); every path is laid out here by hand: straight over a sphere's
top and down through it, or around it at 20 mm beyond its surface. The ball's radius is the default tool's, 1.5 mm.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from structlog.testing import capture_logs

from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.launcher import spawn_sim_subprocess, stop_sim_subprocess
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from tests.conformance.ipp_client import IppClient, IppError, IppSession

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
R = ROBOT.sphere_radius_mm
BALL = 1.5
UP = np.array([0.0, 0.0, 1.0])
COLLISION, ILLEGAL_TOUCH = 2504, 1001
REFUSED = [511, 514]
"""The answer in the error state after a crash (6.3.1.7), until ClearAllErrors."""


def make_rig() -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))


def base_sphere(rig: SimulatedRig, k: int = 0) -> np.ndarray:
    return rig.to_cmm(ROBOT.base_spheres)[k]


def collision_events(logs: list[dict]) -> list[dict]:
    return [e for e in logs if e["event"] == "cmm_sim.collision"]


@pytest.fixture
def rig() -> SimulatedRig:
    return make_rig()


@contextmanager
def open_cmm(rig: SimulatedRig, on_collision: str = "stop") -> Iterator[tuple[CmmServerHandle, IppSession]]:
    server = start_cmm_server(ROBOT, rig, CmmServerConfig(seed=3, time_scale=0.0, noise_sigma_mm=0.0,
                                                          on_collision=on_collision))
    client = IppClient.pty(server.path)
    try:
        session = IppSession(client)
        session.start()
        yield server, session
    finally:
        client.close()
        server.close()


def above(centre: np.ndarray) -> np.ndarray:
    return centre + (R + 20.0) * UP


def below(centre: np.ndarray) -> np.ndarray:
    return centre - (R + 20.0) * UP


def around_to_below(cmm: IppSession, c: np.ndarray) -> None:
    side = np.array([R + 20.0, 0.0, 0.0])
    for point in (above(c), above(c) + side, below(c) + side, below(c)):
        cmm.goto(point)


def test_goto_through_a_sphere_is_a_collision_that_stops_the_ball_at_the_surface(rig: SimulatedRig) -> None:
    with open_cmm(rig) as (server, cmm):
        c = base_sphere(rig)
        cmm.goto(above(c))
        with capture_logs() as logs, pytest.raises(IppError) as crash:
            cmm.goto(below(c))  # straight down through the sphere
        assert crash.value.codes == [COLLISION]
        assert '! Error(3, 2504, "GoTo", "Collision")' in crash.value.transaction.lines[1]  # severity 3 (8.2)
        [event] = collision_events(logs)
        assert event["kind"] == "goto" and event["sphere"] == 3 and event["stopped"]
        np.testing.assert_allclose(event["from_mm"], above(c), atol=1e-3)
        np.testing.assert_allclose(event["to_mm"], below(c), atol=1e-3)
        np.testing.assert_allclose(event["contact_mm"], c + (R + BALL) * UP, atol=1e-3)  # the ball on the top
        assert server.collisions == 1
        with pytest.raises(IppError) as refused:  # the session is in its error state: no motion until cleared
            cmm.goto(above(c))
        assert refused.value.codes == REFUSED
        cmm.clear()
        np.testing.assert_allclose(cmm.position(), c + (R + BALL) * UP, atol=1e-6)  # stopped where it met it
        cmm.goto(above(c))  # and can back off the way it came
        assert server.collisions == 1


def test_goto_around_a_sphere_is_fine(rig: SimulatedRig) -> None:
    with open_cmm(rig) as (server, cmm):
        c = base_sphere(rig)
        around_to_below(cmm, c)
        ball = cmm.ptmeas(c - R * UP, -UP)  # from below, at the south pole: an ordinary touch
        np.testing.assert_allclose(ball, c - (R + BALL) * UP, atol=1e-6)
        assert server.collisions == 0


def test_touching_a_sphere_is_not_a_collision(rig: SimulatedRig) -> None:
    with open_cmm(rig) as (server, cmm):
        c = base_sphere(rig)
        cmm.goto(above(c))
        with capture_logs() as logs:
            for _ in range(3):
                ball = cmm.ptmeas(c + R * UP, UP)  # the stroke runs into the sphere and stops at its surface
                np.testing.assert_allclose(ball, c + (R + BALL) * UP, atol=1e-6)
        assert not collision_events(logs) and server.collisions == 0


def test_ptmeas_whose_approach_crosses_a_sphere_is_a_collision(rig: SimulatedRig) -> None:
    with open_cmm(rig) as (server, cmm):
        c = base_sphere(rig)
        around_to_below(cmm, c)
        with capture_logs() as logs, pytest.raises(IppError) as crash:
            cmm.ptmeas(c + R * UP, UP)  # the north pole from below: the approach goes up through the sphere
        assert crash.value.codes == [COLLISION]
        [event] = collision_events(logs)
        assert event["kind"] == "approach" and event["sphere"] == 3
        np.testing.assert_allclose(event["contact_mm"], c - (R + BALL) * UP, atol=1e-3)  # met the bottom
        assert server.collisions == 1
        with pytest.raises(IppError) as refused:
            cmm.ptmeas(c - R * UP, -UP)
        assert refused.value.codes == REFUSED


def test_an_approach_position_inside_a_sphere_is_an_illegal_touch(rig: SimulatedRig) -> None:
    with open_cmm(rig) as (server, cmm):
        c = base_sphere(rig)
        cmm.goto(above(c))
        with capture_logs() as logs, pytest.raises(IppError) as crash:
            cmm.ptmeas(c + (R - 15.0) * UP, UP)  # approach at nominal + 11.5 mm: 3.5 mm inside the sphere
        assert crash.value.codes == [ILLEGAL_TOUCH]
        [event] = collision_events(logs)
        assert event["kind"] == "illegal_touch"
        np.testing.assert_allclose(event["contact_mm"], c + (R + BALL) * UP, atol=1e-3)
        assert server.collisions == 1
        with pytest.raises(IppError) as refused:
            cmm.goto(above(c))
        assert refused.value.codes == REFUSED


def test_counting_mode_passes_through_but_counts_and_logs(rig: SimulatedRig) -> None:
    with open_cmm(rig, "count") as (server, cmm):
        c = base_sphere(rig)
        cmm.goto(above(c))
        with capture_logs() as logs:
            cmm.goto(below(c))  # through the sphere: counted, not stopped
            ball = cmm.ptmeas(c + R * UP, UP)  # approach up through it: counted, and the touch is made
        np.testing.assert_allclose(ball, c + (R + BALL) * UP, atol=1e-6)
        assert [(e["kind"], e["stopped"]) for e in collision_events(logs)] == [("goto", False), ("approach", False)]
        assert server.collisions == 2
        with pytest.raises(IppError) as inside:  # a target inside a sphere stops it in either mode
            cmm.goto(c)
        assert inside.value.codes == [COLLISION] and server.collisions == 3


def test_the_collision_is_in_the_simulators_log(tmp_path) -> None:
    """`hilcal sim` as `hilcal run --sim` spawns it, log in a file: a crash is there, and the count at the stop. The
    configuration leaves `on_collision` at its default, which stops the ball as a real CMM."""
    (tmp_path / "sim.toml").write_text('[rig]\nseed = 7\n[cmm]\ntime_scale = 0.0\n')
    log_path = tmp_path / "sim.log"
    proc, channels = spawn_sim_subprocess(tmp_path / "sim.toml", log_path=log_path)
    try:
        with IppClient.tcp(int(channels["cmm"]["socket_url"].rsplit(":", 1)[1])) as client:
            cmm = IppSession(client)
            cmm.start()
            c = np.asarray(channels["cmm_alignment"])  # approximate T_cmm<-base: good to a few mm
            centre = c[:3, :3] @ ROBOT.base_spheres[1] + c[:3, 3]
            cmm.goto(above(centre))
            with pytest.raises(IppError) as crash:
                cmm.goto(below(centre))
            assert crash.value.codes == [COLLISION]
    finally:
        assert stop_sim_subprocess(proc) == 0
    text = log_path.read_text()
    [line] = [line for line in text.splitlines() if "cmm_sim.collision" in line]
    assert "kind=goto" in line and "sphere=4" in line
    assert "collisions=1" in next(line for line in text.splitlines() if "cmm_sim.stopped" in line)
