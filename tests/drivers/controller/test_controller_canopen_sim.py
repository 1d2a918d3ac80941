"""The CANopen driver against the simulated devices it was written alongside (sharing only their EDS files), on
python-can's virtual bus: the HX-6 hexapod controller through the station mapping of ``examples/stations`` and six
CiA 402 LD-1 drives through the ``cia402-hexapod`` preset. What the devices hold is read from the simulator's rig and
parameter memory, not from the driver.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator

import numpy as np
import pytest

from hilcal.protocols.canopen import CIA402_LEG_DRIVE_EDS, HEXAPOD_CONTROLLER_EDS
from hilcal.protocols.controller_states import ControllerState
from hilcal.robot import default_robot
from procedures.cli.sim_station import HX6_MAPPING
from procedures.sections.controller import CanopenControllerSection, open_canopen
from sim_devices.canopen import CanopenController, CanopenSimConfig, serve_canopen
from sim_devices.controller.config import ControllerSimConfig
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)
ROBOT = default_robot()
_n = itertools.count()
SECTIONS = {
    "hexapod": {"kind": "canopen", "eds": str(HEXAPOD_CONTROLLER_EDS), "node_id": 1, "heartbeat_ms": 20,
                **HX6_MAPPING},
    "cia402": {"kind": "canopen", "eds": str(CIA402_LEG_DRIVE_EDS), "node_ids": [1, 2, 3, 4, 5, 6],
               "profile": "cia402-hexapod", "position_unit_mm": 0.001, "heartbeat_ms": 20},
}


@pytest.fixture(params=["hexapod", "cia402"], scope="module")
def device(request: pytest.FixtureRequest) -> Iterator[tuple[str, CanopenController, object, object]]:
    variant = request.param
    bus = {"interface": "virtual", "channel": f"sim-{variant}-{next(_n)}-{time.monotonic_ns()}",
           "receive_own_messages": False}
    rig = SimulatedRig(ROBOT, RigConfig(seed=3, errors=GeometryErrors.zero()))
    model = CanopenController(ROBOT, rig, ControllerSimConfig(time_scale=1000.0))
    servers = serve_canopen(model, variant, CanopenSimConfig(), bus_config=bus)
    section = CanopenControllerSection.model_validate(SECTIONS[variant])
    controller, params = open_canopen(section, bus, ROBOT, heartbeat_timeout_s=0.2, ack_timeout_s=1.0,
                                      position_tolerance_mm=0.01)
    controller.wait_for_heartbeat(3.0)
    yield variant, model, controller, params
    controller.close()
    servers.close()


def test_enable_move_disable(device) -> None:
    _, model, controller, _ = device
    controller.enable()
    home = controller.feedback().lengths_mm
    for step in (2.0, -3.5, 0.0):
        reached = controller.move_legs(home + step, 10.0)
        assert np.allclose(reached, home + step, atol=0.01)
        assert np.allclose(model.strokes_mm() + model.geometry("live")[36:], home + step, atol=0.01)
    controller.disable()
    assert controller.state is ControllerState.DISABLED


def test_upload_the_leg_offsets_and_store(device) -> None:
    variant, model, _, params = device
    live = params.read_live()
    new = live.model_copy(update={"l0_mm": [v + 0.25 * (k + 1) for k, v in enumerate(live.l0_mm)]})
    record = params.upload(new, save=True)
    assert record.outcome == "committed" and record.saved and record.live_readback_match
    assert params.read_live().l0_mm == pytest.approx(new.l0_mm, abs=1e-3)
    assert model.geometry("saved")[36:] == pytest.approx(new.l0_mm, abs=1e-3)
    if variant == "hexapod":
        assert record.checksum_match
    described = params.describe()
    assert described["geometry"]["l0_mm"] == pytest.approx(new.l0_mm, abs=1e-3)
    if variant == "hexapod":
        assert described["checksum"] == described["checksum_expected"]
    params.upload(live)  # back


def test_estop_stops_and_fault_reset_clears(device) -> None:
    _, model, controller, _ = device
    controller.enable()
    controller.estop()
    assert not model.is_enabled()
    assert controller.state in (ControllerState.DISABLED, ControllerState.ESTOP, ControllerState.FAULT)
    if controller.state is not ControllerState.DISABLED:
        controller.fault_reset()
    assert controller.state is ControllerState.DISABLED
    controller.enable()  # and it moves again
    home = controller.feedback().lengths_mm
    assert np.allclose(controller.move_legs(home + 1.0, 10.0), home + 1.0, atol=0.01)
    controller.disable()
