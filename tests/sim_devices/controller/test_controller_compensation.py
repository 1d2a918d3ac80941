"""The simulated controller applies its compensation block to every reported length and every setpoint.

The expected lengths are the formula of docs/protocols.md written out here by hand, fed with the rig's raw leg
positions and the controller's own force reading: independent of the controller's arithmetic.
"""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.protocols.compensation import BLOCK_REGISTERS, block_words, zero_block
from hilcal.protocols.controller_states import Command, ControllerState
from hilcal.protocols.registers import ParamCommand, ParamStatus, crc32_of_words, split_u32
from hilcal.robot import Robot
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig, TemperatureConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def block(points: int = 9) -> dict:
    out = zero_block()
    out.update(scale_ppm=[400.0, -250.0, 0.0, 3000.0, 0.0, -80.0], backlash_mm=[0.03, 0.0, 0.05, 0.0, 0.0, 0.01],
               compliance_mm_per_kn=[0.005] * 6, compliance_mm_per_kn_m=[0.0, 0.002, 0.0, 0.0, 0.004, 0.0],
               thermal_ppm_per_k=[11.5] * 6, table_start_mm=[100.0] * 6, table_end_mm=[700.0] * 6,
               table_points=points, table_mm=[list(0.004 * np.sin(np.linspace(0, 6, points) + leg))
                                               for leg in range(6)])
    return out


def by_hand(b: dict, stroke: np.ndarray, l0: np.ndarray, force: np.ndarray, direction: np.ndarray, temp: float
            ) -> np.ndarray:
    """The documented formula, leg by leg."""
    out = np.empty(6)
    for i in range(6):
        s = stroke[i]
        grid = np.linspace(b["table_start_mm"][i], b["table_end_mm"][i], b["table_points"])
        table = np.interp(s, grid, b["table_mm"][i])  # linear, held at the ends
        out[i] = (l0[i] + s + b["scale_ppm"][i] * 1e-6 * s + table + direction[i] * b["backlash_mm"][i] / 2
                  - b["compliance_mm_per_kn"][i] * force[i] - b["compliance_mm_per_kn_m"][i] * force[i] * s / 1000
                  + b["thermal_ppm_per_k"][i] * 1e-6 * (l0[i] + s) * (temp - b["reference_temperature_c"]))
    return out


def make(robot: Robot) -> tuple[SimulatedController, SimulatedRig, Clock]:
    steady = TemperatureConfig(t0_c=23.0, drift_k_per_h=0.0, amplitude_k=0.0, sensor_noise_k=0.0)
    rig = SimulatedRig(robot, RigConfig(seed=3, errors=GeometryErrors.zero(), temperature=steady))
    clock = Clock()
    controller = SimulatedController(robot, rig, ControllerSimConfig(settle_s=0.05), clock=clock)
    return controller, rig, clock


def install(controller: SimulatedController, b: dict) -> None:
    """Upload the block (and the unchanged geometry) through the controller's transaction."""
    assert controller.param_command(ParamCommand.OPEN_STAGING) is ParamStatus.OK
    geometry = controller.bank_words("live")
    words = block_words(b)
    controller.write_staging(0, geometry)
    controller.write_comp_staging(0, words)
    controller.write_staging_header(84 + BLOCK_REGISTERS, split_u32(crc32_of_words(geometry)),
                                    split_u32(crc32_of_words(words)))
    assert controller.param_command(ParamCommand.COMMIT) is ParamStatus.OK


def settle(controller: SimulatedController, clock: Clock) -> None:
    for _ in range(2000):
        clock.t += 0.01
        if controller.snapshot().state is ControllerState.IN_POSITION:
            return
    raise AssertionError("never in position")


def test_reported_lengths_follow_the_documented_formula(robot: Robot) -> None:
    controller, rig, _ = make(robot)
    raw = rig.reported_lengths() - robot.l0
    plain = controller.snapshot().lengths_mm
    np.testing.assert_allclose(plain, robot.l0 + raw, rtol=0, atol=1e-9)  # the factory block corrects nothing
    b = block()
    install(controller, b)
    force = controller.leg_forces_reading()
    assert np.all(force > 1.0)
    # until the first setpoint the controller has read no force or temperature and knows the legs last extended
    expected = by_hand(b, raw, robot.l0, np.zeros(6), np.ones(6), 20.0)
    np.testing.assert_allclose(controller.snapshot().lengths_mm, expected, rtol=0, atol=1e-9)


def test_a_setpoint_is_reached_in_corrected_length(robot: Robot) -> None:
    controller, rig, clock = make(robot)
    b = block()
    install(controller, b)
    assert controller.command(Command.ENABLE).name == "ACCEPTED"
    start = controller.snapshot().lengths_mm
    for target, direction in ((start + np.array([40.0, 25.0, 60.0, 10.0, 30.0, 50.0]), 1.0),
                              (start + np.array([20.0, 5.0, 20.0, 2.0, 10.0, 20.0]), -1.0)):
        assert controller.set_setpoint(target).name == "ACCEPTED"
        settle(controller, clock)
        # the rig holds the raw stroke to its 1 µm resolution, so the corrected length is within half of it
        raw = rig.reported_lengths() - robot.l0
        force = controller.leg_forces_reading()
        expected = by_hand(b, raw, robot.l0, force, np.full(6, direction), 23.0)
        np.testing.assert_allclose(expected, target, rtol=0, atol=6e-4)
        np.testing.assert_allclose(controller.snapshot().lengths_mm, expected, rtol=0, atol=1e-6)


def test_backlash_makes_the_raw_stroke_depend_on_the_approach(robot: Robot) -> None:
    controller, rig, clock = make(robot)
    b = zero_block()
    b.update(backlash_mm=[0.04] * 6)
    install(controller, b)
    controller.command(Command.ENABLE)
    here = controller.snapshot().lengths_mm
    raws = []
    for offset in (-5.0, 5.0):
        controller.set_setpoint(here + offset)
        settle(controller, clock)
        controller.set_setpoint(here)
        settle(controller, clock)
        raws.append(rig.reported_lengths().copy())
        np.testing.assert_allclose(controller.snapshot().lengths_mm, here, rtol=0, atol=6e-4)
    # arriving extending (from below) the leg reads backlash/2 long, so it stops 0.04 mm lower than from above
    np.testing.assert_allclose(raws[1] - raws[0], 0.04, rtol=0, atol=1.5e-3)
