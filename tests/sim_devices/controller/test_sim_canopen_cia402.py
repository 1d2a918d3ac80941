"""The six simulated LD-1 leg drives against canopen's own ``BaseNode402`` (unmodified): its PDO set-up, its state
machine driver, operation mode, fault reset, and profile-position moves by the CiA 402 set-point handshake, over
python-can's ``slcan`` interface on the simulator's pseudo-terminal.

The platform's pose comes from the rig's physics through hilcal's inverse kinematics; units from the drive's own
608Fh/6091h/6092h as a host reads them; the leg offsets from the robot file.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import canopen
import numpy as np
import pytest
from canopen.profiles.p402 import BaseNode402, State402
from canopen.sdo import SdoAbortedError

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.protocols.canopen import CIA402_LEG_DRIVE_EDS
from hilcal.protocols.controller_states import FaultCode
from hilcal.robot import default_robot
from sim_devices.canopen import CanopenController, CanopenServers, CanopenSimConfig, serve_canopen
from sim_devices.controller.config import ControllerSimConfig
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

SDO_TIMEOUT_S = 2.0
"""canopen's SdoClient waits 0.3 s for an answer by default; a busy 2-core CI machine can take longer."""

ROBOT = default_robot()
NODE_IDS = [11, 12, 13, 14, 15, 16]
SAVE = b"save"


@dataclass
class Drives:
    servers: CanopenServers
    model: CanopenController
    net: canopen.Network
    nodes: list[BaseNode402]
    boot_ups: dict[int, list[float]]


def reset(drives: Drives, nodes: list[BaseNode402]) -> None:
    """NMT reset node (broadcast when all six), then wait for each one's boot-up message."""
    before = {n.id: len(drives.boot_ups[n.id]) for n in nodes}
    if len(nodes) == len(drives.nodes):
        drives.net.nmt.state = "RESET"
    else:
        for node in nodes:
            node.nmt.state = "RESET"
    wait_for(lambda: all(len(drives.boot_ups[n.id]) > before[n.id] for n in nodes))


@pytest.fixture(scope="module")
def drives() -> Iterator[Drives]:
    rig = SimulatedRig(ROBOT, RigConfig(seed=4, errors=GeometryErrors.zero()))
    model = CanopenController(ROBOT, rig, ControllerSimConfig(time_scale=1000.0))
    servers = serve_canopen(model, "cia402", CanopenSimConfig(drive_node_ids=NODE_IDS))
    net = canopen.Network()
    net.connect(interface="slcan", channel=servers.slcan_path, sleep_after_open=0)
    nodes = [BaseNode402(node_id, str(CIA402_LEG_DRIVE_EDS)) for node_id in NODE_IDS]
    for node in nodes:
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    boot_ups: dict[int, list[float]] = {}
    for node in nodes:
        net.add_node(node)
        seen = boot_ups[node.id] = []
        node.nmt.add_heartbeat_callback(lambda state, seen=seen: seen.append(time.monotonic()) if state == 0 else None)
    try:
        yield Drives(servers, model, net, nodes, boot_ups)
    finally:
        net.disconnect()
        servers.close()


@pytest.fixture
def legs(drives: Drives) -> list[BaseNode402]:
    """Every drive reset (NMT reset node, broadcast), its PDOs read by BaseNode402, then OPERATIONAL."""
    reset(drives, drives.nodes)
    for node in drives.nodes:
        node.setup_402_state_machine()
        node.nmt.state = "OPERATIONAL"
    return drives.nodes


def wait_for(predicate, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def abort_code(call) -> int:
    with pytest.raises(SdoAbortedError) as info:
        call()
    return info.value.code


def move(node: BaseNode402, target_um: int) -> None:
    """Profile position (CiA 402-2): target, new set-point, wait for the acknowledge, release it."""
    node.sdo[0x607A].raw = target_um
    node.controlword = State402.CW_OPERATION_ENABLED | 0x0010
    wait_for(lambda: node.sdo[0x6041].raw & 0x1000)
    node.controlword = State402.CW_OPERATION_ENABLED


def test_state_machine_and_profile_position_moves(drives: Drives, legs: list[BaseNode402]) -> None:
    for node in legs:
        assert node.sdo[0x1000].raw == 0x00020192  # CiA 402 servo drive
        assert node.state == "SWITCH ON DISABLED"
        node.state = "OPERATION ENABLED"
        node.op_mode = "PROFILED POSITION"
        assert node.op_mode == "PROFILED POSITION"
    pose = ROBOT.home + np.array([-15.0, 20.0, -30.0, -0.7, 0.9, -1.2])
    lengths_um = np.round(inverse_kinematics(Geometry.nominal(ROBOT), pose) * 1000).astype(int)
    for node, target in zip(legs, lengths_um, strict=True):
        move(node, int(target))
    for node in legs:
        wait_for(lambda node=node: node.sdo[0x6041].raw & 0x0400)  # target reached
    actual = np.array([node.sdo[0x6064].raw for node in legs])
    assert np.all(np.abs(actual - lengths_um) <= 6)  # the in-position tolerance, µm
    assert np.allclose(drives.model.true_pose(), pose, atol=0.01)
    node = legs[0]
    lo, hi = node.sdo[0x607D][1].raw, node.sdo[0x607D][2].raw
    assert (lo, hi) == (round(ROBOT.leg_limits[0] * 1000), round(ROBOT.leg_limits[1] * 1000))
    move(node, hi + 1000)
    assert node.sdo[0x6041].raw & 0x0800  # internal limit: the target was not taken
    assert node.sdo[0x6064].raw == actual[0]
    node.sdo[0x607A].raw = -2000
    node.controlword = State402.CW_OPERATION_ENABLED | 0x0050  # new relative set-point
    wait_for(lambda: node.sdo[0x6041].raw & 0x1000)
    node.controlword = State402.CW_OPERATION_ENABLED
    wait_for(lambda: abs(node.sdo[0x6064].raw - (lengths_um[0] - 2000)) <= 6)
    assert not node.sdo[0x6041].raw & 0x0800
    for node in legs:
        node.state = "SWITCH ON DISABLED"
    assert abort_code(lambda: legs[0].sdo[0x6060].write(3)) == 0x06090030  # profile velocity: not supported


def test_units_from_the_drive_objects(legs: list[BaseNode402]) -> None:
    node = legs[2]
    increments = node.sdo[0x608F][1].raw / node.sdo[0x608F][2].raw
    gear = node.sdo[0x6091][1].raw / node.sdo[0x6091][2].raw
    feed_um = node.sdo[0x6092][1].raw / node.sdo[0x6092][2].raw
    stroke_um = node.sdo[0x6064].raw - node.sdo[0x607C].raw
    assert node.sdo[0x6063].raw == pytest.approx(stroke_um * increments * gear / feed_um, abs=1)
    assert node.sdo[0x607C].raw == round(ROBOT.l0[2] * 1000)


def test_fault_on_every_drive_and_reset(drives: Drives, legs: list[BaseNode402]) -> None:
    for node in legs:
        node.state = "OPERATION ENABLED"
        node.emcy.reset()
    drives.model.inject_fault(FaultCode.FOLLOWING_ERROR)
    for node in legs:
        wait_for(lambda node=node: node.emcy.active and node.emcy.active[-1].code == 0x8611)
        wait_for(node.is_faulted)  # the statusword's TPDO may come after the EMCY: neither has to come first
        assert node.sdo[0x603F].raw == 0x8611
        assert node.sdo[0x6041].raw & 0x2000
    legs[0].reset_from_fault()  # the first reset takes the machine out of FAULT
    for node in legs[1:]:
        node.state = "OPERATION ENABLED"  # BaseNode402's path out of FAULT: controlword bit 7's edge
    for node in legs:
        assert node.state == "OPERATION ENABLED"
        assert node.emcy.active == []
    for node in legs:
        node.state = "SWITCH ON DISABLED"


def test_home_offset_is_the_leg_offset_and_stored_per_drive(drives: Drives, legs: list[BaseNode402]) -> None:
    two, three = legs[1], legs[2]
    two.state = "OPERATION ENABLED"
    assert abort_code(lambda: three.sdo[0x607C].write(4_000_000)) == 0x08000022
    two.state = "SWITCH ON DISABLED"
    before = two.sdo[0x6064].raw
    offset = two.sdo[0x607C].raw
    two.sdo[0x607C].raw = offset + 500
    assert two.sdo[0x6064].raw == before + 500  # position actual value = home offset + stroke
    assert drives.model.geometry()[37] == pytest.approx((offset + 500) / 1000, abs=1e-3)
    two.sdo.download(0x1010, 3, SAVE)
    three.sdo[0x607C].raw = three.sdo[0x607C].raw + 700  # not stored
    reset(drives, [two, three])
    assert two.sdo[0x607C].raw == offset + 500
    assert three.sdo[0x607C].raw == round(ROBOT.l0[2] * 1000)
    two.sdo.download(0x1011, 3, b"load")
    reset(drives, [two])
    assert two.sdo[0x607C].raw == round(ROBOT.l0[1] * 1000)
