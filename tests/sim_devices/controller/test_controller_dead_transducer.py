"""A dead length transducer in the simulated controller, and the following-error monitor that catches it.

Transport-free, on a manual clock. The physical leg is read from the rig (``rig.reported_lengths()``: what a sound
transducer would read), the controller's reading from its snapshot. Expected values come from the configuration (leg
speed, following-error limit, dead reading) and the start lengths, never from the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from hilcal.protocols.controller_states import Command, ControllerState, FaultCode
from hilcal.robot import Robot
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_config import load_sim_config

pytestmark = pytest.mark.timeout(60)
S = ControllerState
RESOLUTION_MM = 0.0011  # the rig's 1 µm leg resolution, with rounding


class ManualClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def make(robot: Robot, **config: object) -> tuple[SimulatedController, SimulatedRig, ManualClock]:
    rig = SimulatedRig(robot, RigConfig(seed=7, errors=GeometryErrors.zero()))
    clock = ManualClock()
    ctl = SimulatedController(robot, rig, ControllerSimConfig(time_scale=1.0, leg_speed_mm_s=50.0, **config),
                              clock=clock)
    assert ctl.command(Command.ENABLE).name == "ACCEPTED"
    return ctl, rig, clock


def test_a_dead_leg_keeps_its_power_up_reading_and_trips_the_following_error(robot: Robot) -> None:
    ctl, rig, clock = make(robot, dead_transducer_legs=[4])
    start = ctl.snapshot().lengths_mm
    physical0 = rig.reported_lengths()
    assert ctl.set_setpoint(start + 20.0).name == "ACCEPTED"
    clock.t += 0.06  # 3 mm of ramp: below the 5 mm limit, still moving
    snap = ctl.snapshot()
    assert snap.state is S.MOVING
    assert snap.lengths_mm[3] == start[3]  # leg 4's reading does not follow its actuator
    np.testing.assert_allclose(rig.reported_lengths() - physical0, 3.0, atol=RESOLUTION_MM)  # leg 4 moves too
    np.testing.assert_allclose(np.delete(snap.lengths_mm - start, 3), 3.0, atol=RESOLUTION_MM)
    clock.t += 1.0  # one coarse step that would be 50 mm more: the monitor stops at the limit all the same
    snap = ctl.snapshot()
    assert (snap.state, snap.fault) == (S.FAULT, FaultCode.FOLLOWING_ERROR)
    moved = rig.reported_lengths() - physical0
    np.testing.assert_allclose(moved, 5.0, atol=RESOLUTION_MM)  # the physical legs moved only that far
    assert snap.lengths_mm[3] == start[3]
    clock.t += 1.0
    np.testing.assert_array_equal(rig.reported_lengths() - physical0, moved)  # and hold there
    assert ctl.command(Command.FAULT_RESET).name == "ACCEPTED" and ctl.state is S.DISABLED
    assert ctl.snapshot().lengths_mm[3] == start[3]


def test_a_broken_wire_reads_its_fixed_length_and_the_servo_drives_the_leg_the_wrong_way(robot: Robot) -> None:
    ctl, rig, clock = make(robot, dead_transducer_legs=[2, 5], dead_reading_mm=0.0)
    start = ctl.snapshot().lengths_mm
    assert start[1] == start[4] == 0.0
    physical0 = rig.reported_lengths()
    target = physical0 - robot.l0 + ctl.live_parameters()[-6:] - 20.0  # every leg 20 mm shorter than it is
    assert ctl.set_setpoint(target).name == "ACCEPTED"
    clock.t += 1.0
    snap = ctl.snapshot()
    assert (snap.state, snap.fault) == (S.FAULT, FaultCode.FOLLOWING_ERROR)
    moved = rig.reported_lengths() - physical0
    # The servo believes legs 2 and 5 are 0 mm long: it extends them, and the limit stops them 5 mm out.
    np.testing.assert_allclose(moved[[1, 4]], 5.0, atol=RESOLUTION_MM)
    np.testing.assert_allclose(moved[[0, 2, 3, 5]], -5.0, atol=RESOLUTION_MM)
    np.testing.assert_array_equal(snap.lengths_mm[[1, 4]], 0.0)


def test_a_dead_leg_asked_less_than_the_limit_is_driven_on_until_it_trips(robot: Robot) -> None:
    """Its ramp arrives 3 mm out, its reading does not: the servo drives it on, as an integrating loop does, until
    the ramp is 5 mm from the reading. The sound legs stop at their 3 mm."""
    ctl, rig, clock = make(robot, dead_transducer_legs=[1])
    start = ctl.snapshot().lengths_mm
    physical0 = rig.reported_lengths()
    assert ctl.set_setpoint(start + 3.0).name == "ACCEPTED"
    clock.t += 0.08  # 4 mm of drive at 50 mm/s: leg 1 is 1 mm past its setpoint, not yet at the limit
    assert ctl.snapshot().state is S.MOVING
    np.testing.assert_allclose(rig.reported_lengths()[0] - physical0[0], 4.0, atol=RESOLUTION_MM)
    clock.t += 2.0
    snap = ctl.snapshot()
    assert (snap.state, snap.fault) == (S.FAULT, FaultCode.FOLLOWING_ERROR)
    moved = rig.reported_lengths() - physical0
    np.testing.assert_allclose(moved, [5.0, 3.0, 3.0, 3.0, 3.0, 3.0], atol=RESOLUTION_MM)
    np.testing.assert_allclose(snap.lengths_mm[1:] - start[1:], 3.0, atol=RESOLUTION_MM)
    assert snap.lengths_mm[0] == start[0]


@pytest.mark.parametrize("limit_mm", [5.0, 0.05])
def test_sound_legs_never_trip_the_monitor(robot: Robot, limit_mm: float) -> None:
    """With the largest settle error the configuration allows (1 mm) and a limit far below it: the readings follow."""
    ctl, _, clock = make(robot, repeatability_mm=1.0, repeatability_seed=4, following_error_mm=limit_mm)
    home = ctl.snapshot().lengths_mm
    rng = np.random.default_rng(9)
    for _ in range(30):
        assert ctl.set_setpoint(home + rng.uniform(-80.0, 80.0, 6)).name == "ACCEPTED"
        for step_s in (0.013, 0.4, 5.0):
            clock.t += step_s
            assert ctl.snapshot().fault is FaultCode.NONE
        assert ctl.state is S.IN_POSITION


def test_the_settings_are_checked_and_read_from_the_sim_config(tmp_path) -> None:
    for legs in ([0], [7], [3, 3]):
        with pytest.raises(ValidationError, match="dead_transducer_legs"):
            ControllerSimConfig(dead_transducer_legs=legs)
    with pytest.raises(ValidationError):
        ControllerSimConfig(dead_reading_mm=-1.0)
    with pytest.raises(ValidationError):
        ControllerSimConfig(following_error_mm=0.0)
    default = ControllerSimConfig()
    assert (default.dead_transducer_legs, default.dead_reading_mm, default.following_error_mm) == ([], None, 5.0)
    path = tmp_path / "sim.toml"
    path.write_text("[controller]\ndead_transducer_legs = [4]\ndead_reading_mm = 0.0\nfollowing_error_mm = 2.5\n")
    controller = load_sim_config(path).controller
    assert (controller.dead_transducer_legs, controller.dead_reading_mm, controller.following_error_mm) == (
        [4], 0.0, 2.5)
