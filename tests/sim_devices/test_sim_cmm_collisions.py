"""The simulated CMM crashes as a real one does, and charges a touch its travel, its probing stroke and an overhead.

Driven over a real pty with the CMM driver's primitives (``SerialCmm.goto`` and ``.probe``). Sphere centres come
from the rig (``rig.to_cmm`` of the robot's base layout: base spheres do not move); every path is laid out here by
hand: straight over a sphere's top and down through it, or around it at a distance of 20 mm beyond its surface.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from structlog.testing import capture_logs

from drivers.cmm.base import CmmError
from drivers.cmm.serial import SerialCmm, SerialCmmConfig
from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.faults import FaultPlan
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.cmm.session import CmmMachine, MotionAborted
from sim_devices.launcher import spawn_sim_subprocess, stop_sim_subprocess
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
R = ROBOT.sphere_radius_mm
UP = np.array([0.0, 0.0, 1.0])
FAST = SerialCmmConfig(ack_timeout_s=0.5, command_timeout_s=0.5, home_timeout_s=0.5, max_retries=0)
COLLISION, ILLEGAL_TOUCH, TRANSACTION_ABORTED = 2504, 1001, 6


def make_rig() -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))


def base_sphere(rig: SimulatedRig, k: int = 0) -> np.ndarray:
    return rig.to_cmm(ROBOT.base_spheres)[k]


def collision_events(logs: list[dict]) -> list[dict]:
    return [e for e in logs if e["event"] == "cmm_sim.collision"]


@pytest.fixture
def rig() -> SimulatedRig:
    return make_rig()


def open_cmm(rig: SimulatedRig, on_collision: str) -> tuple[CmmServerHandle, SerialCmm]:
    server = start_cmm_server(ROBOT, rig, CmmServerConfig(seed=3, time_scale=0.0, noise_sigma_mm=0.0,
                                                          on_collision=on_collision))
    cmm = SerialCmm(server.path, FAST)
    cmm.start_session()
    cmm.home()
    return server, cmm


@pytest.fixture
def stopping(rig: SimulatedRig) -> Iterator[tuple[CmmServerHandle, SerialCmm]]:
    server, cmm = open_cmm(rig, "stop")
    yield server, cmm
    cmm.close()
    server.close()


def above(centre: np.ndarray) -> np.ndarray:
    return centre + (R + 20.0) * UP


def below(centre: np.ndarray) -> np.ndarray:
    return centre - (R + 20.0) * UP


def test_goto_through_a_sphere_is_a_latched_collision(stopping, rig: SimulatedRig) -> None:
    server, cmm = stopping
    c = base_sphere(rig)
    cmm.goto(above(c))
    assert server.collisions == 0
    with capture_logs() as logs:
        with pytest.raises(CmmError) as crash:
            cmm.goto(below(c))  # straight down through the sphere
    assert crash.value.code == COLLISION and "base sphere 1" in crash.value.text
    [event] = collision_events(logs)
    assert event["kind"] == "goto" and event["sphere"] == 3 and event["stopped"]
    np.testing.assert_allclose(event["from_mm"], above(c), atol=1e-3)
    np.testing.assert_allclose(event["to_mm"], below(c), atol=1e-3)
    np.testing.assert_allclose(event["contact_mm"], c + R * UP, atol=1e-3)  # it hit the top of the sphere
    assert server.collisions == 1
    with pytest.raises(CmmError) as latched:  # the crash latches the error state: no motion until cleared
        cmm.goto(above(c))
    assert latched.value.code == TRANSACTION_ABORTED
    cmm.clear_errors()
    cmm.goto(above(c))  # the probe stopped on the surface and can back off the way it came
    assert server.collisions == 1


def test_goto_around_a_sphere_is_fine(stopping, rig: SimulatedRig) -> None:
    server, cmm = stopping
    c = base_sphere(rig)
    side = np.array([R + 20.0, 0.0, 0.0])
    for point in (above(c), above(c) + side, below(c) + side, below(c)):
        cmm.goto(point)
    touched = cmm.probe(c - R * UP, -UP)  # from below, the south pole: an ordinary touch
    assert abs(touched[2] - (c[2] - R)) < 1e-5
    assert server.collisions == 0


def test_touching_a_sphere_is_not_a_collision(stopping, rig: SimulatedRig) -> None:
    server, cmm = stopping
    c = base_sphere(rig)
    cmm.goto(above(c))
    with capture_logs() as logs:
        for _ in range(3):
            touched = cmm.probe(c + R * UP, UP)  # the stroke runs into the sphere and stops at its surface
            assert abs(touched[2] - (c[2] + R)) < 1e-5
    assert not collision_events(logs) and server.collisions == 0


def test_ptmeas_whose_approach_crosses_a_sphere_is_a_collision(stopping, rig: SimulatedRig) -> None:
    server, cmm = stopping
    c = base_sphere(rig)
    side = np.array([R + 20.0, 0.0, 0.0])
    for point in (above(c), above(c) + side, below(c) + side, below(c)):
        cmm.goto(point)
    with capture_logs() as logs:
        with pytest.raises(CmmError) as crash:
            cmm.probe(c + R * UP, UP)  # the north pole from below: the approach goes up through the sphere
    assert crash.value.code == COLLISION
    [event] = collision_events(logs)
    assert event["kind"] == "approach" and event["sphere"] == 3
    np.testing.assert_allclose(event["contact_mm"], c - R * UP, atol=1e-3)  # met the bottom on the way up
    assert server.collisions == 1
    with pytest.raises(CmmError) as latched:
        cmm.probe(c - R * UP, -UP)
    assert latched.value.code == TRANSACTION_ABORTED


def test_ptmeas_start_inside_a_sphere_is_an_illegal_touch(stopping, rig: SimulatedRig) -> None:
    server, cmm = stopping
    c = base_sphere(rig)
    cmm.goto(above(c))
    with capture_logs() as logs:
        with pytest.raises(CmmError) as crash:
            cmm.probe(c + (R - 8.0) * UP, UP)  # 5 mm search: the start is 3 mm inside the sphere
    assert crash.value.code == ILLEGAL_TOUCH
    [event] = collision_events(logs)
    assert event["kind"] == "illegal_touch"
    np.testing.assert_allclose(event["contact_mm"], c + R * UP, atol=1e-3)
    assert server.collisions == 1
    with pytest.raises(CmmError) as latched:
        cmm.goto(above(c))
    assert latched.value.code == TRANSACTION_ABORTED


def test_counting_mode_passes_through_but_counts_and_logs(rig: SimulatedRig) -> None:
    server, cmm = open_cmm(rig, "count")
    try:
        c = base_sphere(rig)
        cmm.goto(above(c))
        with capture_logs() as logs:
            cmm.goto(below(c))  # through the sphere: counted, not stopped
            touched = cmm.probe(c + R * UP, UP)  # approach up through it: counted, and the touch is made
        assert abs(touched[2] - (c[2] + R)) < 1e-5
        assert [(e["kind"], e["stopped"]) for e in collision_events(logs)] == [("goto", False), ("approach", False)]
        assert server.collisions == 2
        with pytest.raises(CmmError) as inside:  # a target inside a sphere stops it in either mode
            cmm.goto(c)
        assert inside.value.code == COLLISION and server.collisions == 3
    finally:
        cmm.close()
        server.close()


def test_a_touch_costs_travel_probing_stroke_and_overhead(rig: SimulatedRig) -> None:
    """Durations from the model as documented, with the defaults: 250 mm/s travel, 10 mm/s probing, 0.05 s."""
    config = CmmServerConfig(noise_sigma_mm=0.0)
    assert (config.travel_speed_mm_s, config.probing_speed_mm_s, config.probe_time_s) == (250.0, 10.0, 0.05)
    machine = CmmMachine(ROBOT, rig, config)
    c = base_sphere(rig)
    machine.home()
    machine.goto(above(c))
    _, duration = machine.touch(c + R * UP, UP, 5.0, FaultPlan())
    # travel 20 - 5 = 15 mm to the start, then 5 mm of stroke to the surface: 0.06 s + 0.5 s + 0.05 s
    assert duration == pytest.approx(15.0 / 250.0 + 5.0 / 10.0 + 0.05)
    assert duration == pytest.approx(0.5, abs=0.12)  # about what a touch cost before the stroke had a speed
    _, far = machine.touch(c + (R + 3.0) * UP, UP, 5.0, FaultPlan())  # the target 3 mm above the surface
    assert far == pytest.approx(3.0 / 250.0 + 8.0 / 10.0 + 0.05)  # 3 mm up to the new start, 8 mm of stroke
    with pytest.raises(MotionAborted) as miss:  # nothing within the 2 x 5 mm stroke: the whole stroke is paid
        machine.touch(c + (R + 30.0) * UP, UP, 5.0, FaultPlan())
    assert miss.value.code.name == "SURFACE_NOT_FOUND"
    assert miss.value.duration_s == pytest.approx(27.0 / 250.0 + 10.0 / 10.0 + 0.05)  # from R + 8 up to R + 35


def test_the_collision_is_in_the_simulators_log(tmp_path) -> None:
    """`hilcal sim` as `hilcal run --sim` spawns it, log in a file: a crash is there, and the count at the stop. The
    configuration leaves `on_collision` at its default, which stops the probe as a real CMM."""
    (tmp_path / "sim.toml").write_text('[rig]\nseed = 7\n[cmm]\ntime_scale = 0.0\n')
    log_path = tmp_path / "sim.log"
    proc, channels = spawn_sim_subprocess(tmp_path / "sim.toml", log_path=log_path)
    try:
        with SerialCmm(channels["cmm"]["url"], FAST) as cmm:
            cmm.start_session()
            cmm.home()
            c = np.asarray(channels["cmm_alignment"])  # approximate T_cmm<-base: good to a few mm
            centre = c[:3, :3] @ ROBOT.base_spheres[1] + c[:3, 3]
            cmm.goto(above(centre))
            with pytest.raises(CmmError) as crash:
                cmm.goto(below(centre))
            assert crash.value.code == COLLISION
    finally:
        assert stop_sim_subprocess(proc) == 0
    text = log_path.read_text()
    [line] = [line for line in text.splitlines() if "cmm_sim.collision" in line]
    assert "kind=goto" in line and "sphere=4" in line
    assert "collisions=1" in next(line for line in text.splitlines() if "cmm_sim.stopped" in line)
