"""The run's checks on the machine as it is (procedures.acquisition), against the simulated rig's truth physics:
readings outside the travel stop before motion, a first pose far off stops the run or is noted, and a pose the
model puts beyond a leg's travel is named before it is driven to."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import default_robot
from procedures.acquisition import Acquisition, MachineNotMeasurable
from sim_devices.rig.config import EffectsConfig, GeometryErrors, RigConfig, SensorScaleConfig
from sim_devices.rig.rig import SimulatedRig

ROBOT = default_robot()
NOMINAL = Geometry.nominal(ROBOT)


def _start() -> Acquisition:
    return Acquisition.start(ROBOT, ROBOT.a, ROBOT.b, ROBOT.l0, [])


def _row(rig: SimulatedRig, pose: np.ndarray) -> dict:
    rig.move_to_lengths(inverse_kinematics(NOMINAL, pose))
    return {"legs": rig.reported_lengths(), "meas": rig.true_pose()}


def test_a_reading_outside_the_travel_stops_before_motion() -> None:
    legs = inverse_kinematics(NOMINAL, ROBOT.home)
    _start().check_readings(legs)
    legs[1] = 0.0
    with pytest.raises(MachineNotMeasurable, match=r"leg 2 reads 0\.000 mm, outside its travel 3800\.0-4800\.0 mm: "
                                                   r"its transducer is dead or disconnected .*nothing moved"):
        _start().check_readings(legs)


@pytest.mark.parametrize(("dl0_mm", "stops"), [(300.0, True), (120.0, False)])
def test_a_leg_far_off_at_the_first_pose(dl0_mm: float, stops: bool) -> None:
    """A leg 300 mm longer than it reads (beyond a quarter of the 1000 mm travel) stops the run naming it; 120 mm is
    a gross fault, noted and measured as it is."""
    dl0 = np.zeros(6)
    dl0[1] = dl0_mm
    rig = SimulatedRig(ROBOT, RigConfig(errors=GeometryErrors.from_arrays(np.zeros((6, 3)), np.zeros((6, 3)), dl0)))
    acq = _start()
    row = _row(rig, ROBOT.home)
    if stops:
        with pytest.raises(MachineNotMeasurable, match=r"leg 2 reads 300\.0 mm short at the first pose"):
            acq.learn(row)
        return
    acq.learn(row)
    [note] = acq.notes
    assert note.startswith("leg 2 reads 120.00 mm short at the first pose") and "measured as it is" in note
    assert Acquisition.start(ROBOT, ROBOT.a, ROBOT.b, ROBOT.l0, [row]).notes == [note]  # a resumed run says it too


def test_a_pose_the_model_puts_beyond_a_leg_s_travel_is_named() -> None:
    """Leg 1's transducer reads 9 % short: a setpoint 40 mm below the top of its travel drives it beyond."""
    effects = EffectsConfig(sensor_scale=SensorScaleConfig(enabled=True, gain_error_ppm=[-90000.0, 0, 0, 0, 0, 0]))
    rig = SimulatedRig(ROBOT, RigConfig(errors=GeometryErrors.zero(), effects=effects))
    acq = _start()
    rng = np.random.default_rng(0)
    for _ in range(8):
        pose = ROBOT.home + np.concatenate([rng.uniform(-200, 200, 3), rng.uniform(-5, 5, 3)])
        acq.learn(_row(rig, pose))
    top = np.full(6, 4300.0)
    top[0] = 4760.0  # physically 3800 + 960 / 0.91 = 4854.9 mm
    why = acq.unreachable(np.vstack([top - 2.0, top]), "measure pose 7")
    assert why is not None and why.startswith("measure pose 7 is out of reach: under the model measured so far leg 1 "
                                              "would be at 4854.9 mm for a setpoint of 4760.0 mm")
    assert "reads -9.00 % of its stroke" in why
    assert acq.unreachable(np.full((2, 6), 4300.0), "measure pose 8") is None
