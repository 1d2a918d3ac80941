"""The CAN driver names the leg whose transducer does not follow: the real driver against the simulated controller
over SLCAN on a pty, with a dead transducer.

Expected values are the lengths the driver reported before the move and the setpoint this test computed by inverse
kinematics, formatted as the driver's message promises (docs/protocols.md), never read back from the driver.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import ExitStack

import numpy as np
import pytest

from drivers.controller.base import ControllerFault, MotionTimeout
from drivers.controller.hilcal_can import ControllerCan
from hilcal.protocols.controller_states import ControllerState, FaultCode
from hilcal.robot import Robot
from sim_devices.controller.can_peer import ControllerCanPeer
from sim_devices.controller.slcan_server import SlcanServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig
from tests.drivers.controller.can_frames import HEARTBEAT_TIMEOUT_S, ik

pytestmark = pytest.mark.timeout(60)
POSE = [35.0, -20.0, 3150.0, 1.5, -2.0, 3.0]


@pytest.fixture
def connect(robot: Robot) -> Iterator[Callable[..., tuple[SimulatedController, ControllerCan]]]:
    stack = ExitStack()

    def make(**config: object) -> tuple[SimulatedController, ControllerCan]:
        rig = SimulatedRig(robot, RigConfig(seed=7, errors=GeometryErrors.zero()))
        controller = SimulatedController(robot, rig, ControllerSimConfig(**config))
        server = SlcanServer(ControllerCanPeer(controller), transport="pty")
        server.start()
        stack.callback(server.close)
        driver = ControllerCan({"interface": "slcan", "channel": server.channel, "sleep_after_open": 0}, robot,
                               heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S, ack_timeout_s=0.5)
        stack.callback(driver.close)
        driver.wait_for_heartbeat(2.0)
        driver.enable()
        return controller, driver

    yield make
    stack.close()


def test_the_fault_names_the_dead_leg_and_what_it_read(connect, robot: Robot) -> None:
    _, driver = connect(time_scale=200.0, dead_transducer_legs=[4])
    before = driver.feedback().lengths_mm
    setpoint = ik(robot, POSE)
    assert np.all(np.abs(setpoint - before) > 5.0)  # every leg is asked beyond the 5 mm following-error limit
    with pytest.raises(ControllerFault) as info:
        driver.move_legs(setpoint, timeout_s=5.0)
    assert info.value.fault is FaultCode.FOLLOWING_ERROR and info.value.state is ControllerState.FAULT
    assert info.value.legs == (4,)
    assert str(info.value) == (
        f"controller fault FOLLOWING_ERROR during the move: leg 4 read {before[3]:.3f} mm throughout while its "
        f"setpoint was {setpoint[3]:.3f} mm (the other legs followed): its transducer does not follow the leg "
        "(dead or disconnected)")


def test_broken_wires_are_named_with_their_reading_outside_the_leg_limits(connect, robot: Robot) -> None:
    _, driver = connect(time_scale=200.0, dead_transducer_legs=[2, 5], dead_reading_mm=0.0)
    setpoint = ik(robot, POSE)
    with pytest.raises(ControllerFault) as info:
        driver.move_legs(setpoint, timeout_s=5.0)
    lo, hi = robot.leg_limits
    assert info.value.legs == (2, 5)
    assert (f"legs 2 and 5 read 0.000 and 0.000 mm throughout, outside the leg limits [{lo:g}, {hi:g}] mm, while "
            f"their setpoints were {setpoint[1]:.3f} and {setpoint[4]:.3f} mm") in str(info.value)


def test_a_small_move_of_a_dead_leg_trips_too(connect) -> None:
    _, driver = connect(time_scale=200.0, dead_transducer_legs=[1])
    before = driver.feedback().lengths_mm
    with pytest.raises(ControllerFault) as info:
        driver.move_legs(before + 2.0, timeout_s=5.0)  # 2 mm: less than the limit; the servo drives leg 1 on
    assert info.value.fault is FaultCode.FOLLOWING_ERROR and info.value.legs == (1,)
    assert f"leg 1 read {before[0]:.3f} mm throughout while its setpoint was {before[0] + 2.0:.3f} mm" in str(
        info.value)


def test_a_move_that_times_out_names_the_leg_that_did_not_follow(connect) -> None:
    # A 100 mm limit at 50 mm/s: 2 s before the monitor trips, the driver gives up after 0.5 s.
    _, driver = connect(time_scale=1.0, leg_speed_mm_s=50.0, dead_transducer_legs=[1], following_error_mm=100.0)
    before = driver.feedback().lengths_mm
    with pytest.raises(MotionTimeout) as info:
        driver.move_legs(before + 2.0, timeout_s=0.5)
    assert str(info.value).endswith(
        f"STOP sent: leg 1 read {before[0]:.3f} mm throughout while its setpoint was {before[0] + 2.0:.3f} mm (the "
        "other legs followed): its transducer does not follow the leg (dead or disconnected)")


def test_a_fault_with_every_leg_following_names_no_leg(connect) -> None:
    controller, driver = connect(time_scale=1.0, leg_speed_mm_s=50.0)
    before = driver.feedback().lengths_mm
    timer = threading.Timer(0.1, controller.inject_fault, args=(FaultCode.FOLLOWING_ERROR,))
    timer.start()
    try:
        with pytest.raises(ControllerFault) as info:
            driver.move_legs(before + 20.0, timeout_s=3.0)
    finally:
        timer.cancel()
    assert info.value.fault is FaultCode.FOLLOWING_ERROR and info.value.legs == ()
    assert str(info.value) == "controller fault FOLLOWING_ERROR during the move"
