"""The simulated controller's repeatability: a seeded settle error per leg and setpoint that the transducers do not
see, off by default. Expected values are the configured standard deviation, not the code's own numbers."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.protocols.controller_states import Command, ControllerState
from hilcal.robot import Robot
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)


class ManualClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def visits(robot: Robot, config: ControllerSimConfig, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n visits of one target, each from 2 mm below: (target, transducer readings (n, 6), actuator lengths (n, 6))."""
    rig = SimulatedRig(robot, RigConfig(seed=7, errors=GeometryErrors.zero()))
    clock = ManualClock()
    ctl = SimulatedController(robot, rig, config, clock=clock)
    assert ctl.command(Command.ENABLE).name == "ACCEPTED"
    target = ctl.snapshot().lengths_mm + 5.0
    reported, actual = [], []
    for _ in range(n):
        for legs in (target - 2.0, target):
            assert ctl.set_setpoint(legs).name == "ACCEPTED"
            clock.t += 1.0
            assert ctl.state is ControllerState.IN_POSITION
        reported.append(ctl.snapshot().lengths_mm)
        actual.append(rig.reported_lengths() - robot.l0 + ctl.live_parameters()[-6:])
    return target, np.array(reported), np.array(actual)


def test_settle_error_scatters_the_actuators_but_not_the_transducers(robot: Robot) -> None:
    sigma = 0.02
    target, reported, actual = visits(robot, ControllerSimConfig(time_scale=1.0, repeatability_mm=sigma,
                                                                 repeatability_seed=3), 400)
    np.testing.assert_allclose(reported, np.broadcast_to(target, reported.shape), atol=0.0011)
    error = actual - target
    assert np.all(np.abs(error.mean(axis=0)) < 4 * sigma / np.sqrt(len(error)))
    np.testing.assert_allclose(error.std(axis=0, ddof=1), sigma, rtol=0.15)
    assert abs(np.corrcoef(error[:, 0], error[:, 1])[0, 1]) < 0.2


def test_repeatability_is_off_by_default(robot: Robot) -> None:
    target, reported, actual = visits(robot, ControllerSimConfig(time_scale=1.0), 5)
    np.testing.assert_allclose(actual, reported, atol=1e-9)
    np.testing.assert_allclose(actual, np.broadcast_to(target, actual.shape), atol=0.0011)


def test_a_setpoint_where_the_legs_are_still_settles(robot: Robot) -> None:
    """A new settle error is drawn even when no leg moves; the controller must still reach IN_POSITION."""
    rig = SimulatedRig(robot, RigConfig(seed=7, errors=GeometryErrors.zero()))
    clock = ManualClock()
    ctl = SimulatedController(robot, rig, ControllerSimConfig(time_scale=1.0, repeatability_mm=0.05), clock=clock)
    ctl.command(Command.ENABLE)
    here = ctl.snapshot().lengths_mm
    for _ in range(3):
        before = rig.reported_lengths()
        assert ctl.set_setpoint(here).name == "ACCEPTED"
        clock.t += 1.0
        assert ctl.state is ControllerState.IN_POSITION
        assert not np.allclose(rig.reported_lengths(), before)
