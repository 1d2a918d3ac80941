"""The simulated HX-6 hexapod controller against code we did not write: canopen's own ``RemoteNode``, ``SdoClient``,
``PdoMap``, ``EmcyConsumer`` and ``NmtMaster`` (unmodified) over python-can's ``slcan`` interface on the simulator's
pseudo-terminal.

Expected values come from outside the simulator: identity and defaults from the EDS read with ``configparser``,
the statusword masks from canopen's ``State402``, the geometry from the robot file, the CRC-32s computed here from
the definition in the EDS's [Comments], the platform's pose from the rig's physics through hilcal's inverse
kinematics, abort codes from CiA 301's table as canopen names them.
"""

from __future__ import annotations

import configparser
import struct
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass

import canopen
import numpy as np
import pytest
from canopen.profiles.p402 import State402
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.protocols.canopen import HEXAPOD_CONTROLLER_EDS
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
NODE_ID = 5
SERIAL = 0x12345678
EDS = configparser.ConfigParser(inline_comment_prefixes=(";",))
EDS.optionxform = str  # type: ignore[assignment,method-assign]
EDS.read(HEXAPOD_CONTROLLER_EDS)
NOMINAL = np.concatenate([ROBOT.a.ravel(), ROBOT.b.ravel(), ROBOT.l0]).astype(np.float32)
DEVICE_STATE, VALUE_RANGE, CANNOT_STORE, READ_ONLY = 0x08000022, 0x06090030, 0x08000020, 0x06010002
SAVE, LOAD = b"save", b"load"


@dataclass
class Device:
    servers: CanopenServers
    model: CanopenController
    rig: SimulatedRig
    net: canopen.Network
    node: canopen.RemoteNode
    boot_ups: list[float]


def count_boot_ups(node: canopen.RemoteNode) -> list[float]:
    """The times of the node's boot-up messages, as they arrive (canopen's own wait_for_bootup starts listening
    after the reset command went out, so a device that boots at once can beat it)."""
    seen: list[float] = []
    node.nmt.add_heartbeat_callback(lambda state: seen.append(time.monotonic()) if state == 0 else None)
    return seen


def reset_node(node: canopen.RemoteNode, boot_ups: list[float], command: str = "RESET") -> None:
    before = len(boot_ups)
    node.nmt.state = command
    wait_for(lambda: len(boot_ups) > before)


@pytest.fixture(scope="module")
def device() -> Iterator[Device]:
    rig = SimulatedRig(ROBOT, RigConfig(seed=3, errors=GeometryErrors.zero()))
    model = CanopenController(ROBOT, rig, ControllerSimConfig(time_scale=1000.0, serial_number=SERIAL))
    servers = serve_canopen(model, "hexapod", CanopenSimConfig(node_id=NODE_ID))
    net = canopen.Network()
    net.connect(interface="slcan", channel=servers.slcan_path, sleep_after_open=0)
    node = canopen.RemoteNode(NODE_ID, str(HEXAPOD_CONTROLLER_EDS))
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    net.add_node(node)
    try:
        yield Device(servers, model, rig, net, node, count_boot_ups(node))
    finally:
        net.disconnect()
        servers.close()


@pytest.fixture
def hx6(device: Device) -> canopen.RemoteNode:
    """The node freshly reset (NMT reset node: stored set loaded, SWITCH ON DISABLED, PRE-OPERATIONAL)."""
    reset_node(device.node, device.boot_ups)
    return device.node


def state402(node: canopen.RemoteNode) -> str:
    word = node.sdo[0x6041].raw
    return next(name for name, (mask, bits) in State402.SW_MASK.items() if word & mask == bits)


def enable(node: canopen.RemoteNode) -> None:
    for word in (State402.CW_SHUTDOWN, State402.CW_SWITCH_ON, State402.CW_OPERATION_ENABLED):
        node.sdo[0x6040].raw = word


def abort_code(call) -> int:
    with pytest.raises(SdoAbortedError) as info:
        call()
    return info.value.code


def actual_lengths(node: canopen.RemoteNode) -> np.ndarray:
    return np.array([node.sdo[0x2010][leg].raw for leg in range(1, 7)])


def wait_for(predicate, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_identity_from_the_eds(hx6: canopen.RemoteNode) -> None:
    assert hx6.sdo[0x1018][1].raw == int(EDS["1018sub1"]["DefaultValue"], 0)
    assert hx6.sdo[0x1018][2].raw == int(EDS["DeviceInfo"]["ProductNumber"], 0)
    assert hx6.sdo[0x1018][3].raw == int(EDS["DeviceInfo"]["RevisionNumber"], 0)
    assert hx6.sdo[0x1018][4].raw == SERIAL
    assert hx6.sdo[0x1000].raw == int(EDS["1000"]["DefaultValue"], 0)
    # 1008h is longer than four bytes: a segmented upload.
    assert hx6.sdo[0x1008].raw == EDS["1008"]["DefaultValue"]
    assert hx6.sdo[0x1200][1].raw == 0x600 + NODE_ID and hx6.sdo[0x1200][2].raw == 0x580 + NODE_ID
    assert abort_code(lambda: hx6.sdo.upload(0x3000, 0)) == 0x06020000
    assert abort_code(lambda: hx6.sdo.download(0x1018, 1, struct.pack("<I", 1))) == READ_ONLY


def heartbeat_shows(node: canopen.RemoteNode, state: str, beats: int = 3) -> bool:
    """Whether one of the node's next `beats` heartbeats reports `state`: a heartbeat already on the SLCAN line when
    an NMT command was sent still reports the state before it (a heartbeat carries the producer's NMT state when it
    was sent)."""
    return any(node.nmt.wait_for_heartbeat(1.0) == state for _ in range(beats))


def test_nmt_boot_up_heartbeat_and_states(device: Device, hx6: canopen.RemoteNode) -> None:
    assert hx6.nmt.wait_for_heartbeat(1.0) == "PRE-OPERATIONAL"
    hx6.nmt.state = "OPERATIONAL"
    assert heartbeat_shows(hx6, "OPERATIONAL")
    hx6.nmt.state = "STOPPED"
    assert heartbeat_shows(hx6, "STOPPED")
    hx6.sdo.RESPONSE_TIMEOUT = 0.3  # canopen's default: the silence is what is expected here
    with pytest.raises(SdoCommunicationError):  # no SDO in STOPPED
        hx6.sdo[0x1018][1].raw  # noqa: B018
    hx6.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    hx6.nmt.state = "PRE-OPERATIONAL"
    assert heartbeat_shows(hx6, "PRE-OPERATIONAL")
    hx6.sdo[0x1017].raw = 20
    stamps = []
    for _ in range(10):
        hx6.nmt.wait_for_heartbeat(1.0)
        stamps.append(hx6.nmt.timestamp)
    assert 0.015 < float(np.median(np.diff(stamps))) < 0.03  # heartbeats 20 ms apart
    reset_node(hx6, device.boot_ups, "RESET COMMUNICATION")
    assert hx6.sdo[0x1017].raw == int(EDS["1017"]["DefaultValue"], 0)  # not stored: back to the default


def test_cia402_state_machine_and_fault(device: Device, hx6: canopen.RemoteNode) -> None:
    assert state402(hx6) == "SWITCH ON DISABLED"
    for word, expected in ((State402.CW_SHUTDOWN, "READY TO SWITCH ON"), (State402.CW_SWITCH_ON, "SWITCHED ON"),
                           (State402.CW_OPERATION_ENABLED, "OPERATION ENABLED"),
                           (State402.CW_SWITCH_ON, "SWITCHED ON"), (State402.CW_DISABLE_VOLTAGE, "SWITCH ON DISABLED")):
        hx6.sdo[0x6040].raw = word
        assert state402(hx6) == expected
    assert hx6.sdo[0x6041].raw & 0x0200  # remote
    enable(hx6)
    hx6.emcy.reset()
    device.model.inject_fault(FaultCode.FOLLOWING_ERROR)
    wait_for(lambda: hx6.emcy.active)
    emcy = hx6.emcy.active[-1]
    assert emcy.code == 0x8611 and emcy.register & 0x01
    assert state402(hx6) == "FAULT"
    assert hx6.sdo[0x6041].raw & 0x2000  # following error
    assert hx6.sdo[0x1001].raw == emcy.register
    assert hx6.sdo[0x1003][0].raw >= 1 and hx6.sdo[0x1003][1].raw & 0xFFFF == 0x8611
    assert hx6.sdo[0x603F].raw == 0x8611
    hx6.sdo[0x6040].raw = State402.CW_OPERATION_ENABLED  # no fault reset edge: stays in FAULT
    assert state402(hx6) == "FAULT"
    hx6.sdo[0x6040].raw = 0x0000
    hx6.sdo[0x6040].raw = State402.CW_SWITCH_ON_DISABLED  # bit 7's rising edge
    assert state402(hx6) == "SWITCH ON DISABLED"
    wait_for(lambda: hx6.emcy.log[-1].code == 0x0000)  # EMCY error reset
    assert hx6.emcy.log[-1].register == 0 and hx6.emcy.active == []
    assert hx6.sdo[0x1001].raw == 0
    hx6.sdo[0x1003][0].raw = 0
    assert hx6.sdo[0x1003][0].raw == 0


def test_estop_fault_reset_needs_the_input_released(device: Device, hx6: canopen.RemoteNode) -> None:
    enable(hx6)
    device.model.press_estop("input")
    wait_for(lambda: state402(hx6) == "FAULT")
    assert hx6.sdo[0x6041].raw & 0x4000  # e-stop input (manufacturer bit 14)
    hx6.sdo[0x6040].raw = 0x0000
    hx6.sdo[0x6040].raw = 0x0080
    assert state402(hx6) == "FAULT"
    device.model.release_estop()
    hx6.sdo[0x6040].raw = 0x0000
    hx6.sdo[0x6040].raw = 0x0080
    assert state402(hx6) == "SWITCH ON DISABLED"


def test_sdo_setpoints_move_the_platform(device: Device, hx6: canopen.RemoteNode) -> None:
    pose = ROBOT.home + np.array([20.0, -10.0, 25.0, 0.5, -0.4, 1.0])
    lengths = inverse_kinematics(Geometry.nominal(ROBOT), pose)
    for leg in range(6):
        hx6.sdo[0x2000][leg + 1].raw = float(lengths[leg])
    assert abort_code(lambda: hx6.sdo[0x2001].write(7)) == DEVICE_STATE  # not enabled
    assert hx6.sdo[0x2003].raw == 1  # wrong state
    enable(hx6)
    hx6.sdo[0x2001].raw = 7
    wait_for(lambda: hx6.sdo[0x6041].raw & 0x0400)  # target reached
    assert hx6.sdo[0x2002].raw == 7 and hx6.sdo[0x2003].raw == 0
    assert np.allclose(actual_lengths(hx6), lengths, atol=0.006)
    assert np.allclose(device.model.true_pose(), pose, atol=0.01)  # the rig's physics (zero errors)
    assert hx6.sdo[0x2011].raw == 0x3F
    forces = [hx6.sdo[0x2012][leg].raw for leg in range(1, 7)]
    assert all(f > 0 for f in forces)  # a 4000 kg platform compresses every leg
    beyond = ROBOT.leg_limits[1] + 10.0
    hx6.sdo[0x2000][3].raw = beyond
    assert abort_code(lambda: hx6.sdo[0x2001].write(8)) == VALUE_RANGE
    assert hx6.sdo[0x6041].raw & 0x0800  # internal limit active
    assert hx6.sdo[0x2002].raw == 7 and hx6.sdo[0x2003].raw == 5
    assert np.allclose(actual_lengths(hx6), lengths, atol=0.006)  # nothing moved


def test_pdo_setpoints_and_actual_lengths(device: Device, hx6: canopen.RemoteNode) -> None:
    hx6.tpdo.read()
    hx6.rpdo.read()
    assert [v.index for v in hx6.tpdo[2]] == [0x2010, 0x2010]
    enable(hx6)
    t0 = time.time()
    hx6.nmt.state = "OPERATIONAL"  # every TPDO is sent on entering OPERATIONAL, then on a change or its timer
    wait_for(lambda: all((hx6.tpdo[n].timestamp or 0) > t0 for n in (1, 2, 3, 4)))
    start = np.array([hx6.tpdo[2 + leg // 2][leg % 2].raw for leg in range(6)])
    assert np.allclose(start, actual_lengths(hx6), atol=0.002)
    target = start + np.array([5.0, -5.0, 3.0, -3.0, 1.0, -1.0])
    for leg in range(6):
        hx6.rpdo[1 + leg // 2][leg % 2].raw = float(target[leg])
    for n in (1, 2, 3):
        hx6.rpdo[n].transmit()
    hx6.rpdo[4][0].raw = 99
    hx6.rpdo[4].transmit()

    def tpdo_lengths() -> np.ndarray:
        return np.array([hx6.tpdo[2 + leg // 2][leg % 2].raw for leg in range(6)])

    wait_for(lambda: np.allclose(tpdo_lengths(), target, atol=0.006) and hx6.tpdo[1][1].raw == 99)
    # statusword bit 10, target reached: its TPDO follows the lengths' on its own change, so it is waited for too
    wait_for(lambda: bool(hx6.tpdo[1][0].raw & 0x0400))
    hx6.nmt.state = "PRE-OPERATIONAL"


def test_pdo_remapping_follows_cia301(device: Device, hx6: canopen.RemoteNode) -> None:
    hx6.tpdo.read()
    assert abort_code(lambda: hx6.sdo[0x1A03][0].write(0)) == DEVICE_STATE  # mapping of a valid PDO
    tpdo = hx6.tpdo[4]
    tpdo.clear()
    tpdo.add_variable(0x2013)
    tpdo.add_variable(0x2400, 1)
    tpdo.trans_type = 1  # every SYNC
    tpdo.save()  # canopen's sequence: invalidate, re-map, validate
    hx6.nmt.state = "OPERATIONAL"
    t0 = time.time()
    device.net.sync.transmit()
    wait_for(lambda: (tpdo.timestamp or 0) > t0)
    assert tpdo[0].raw == pytest.approx(device.model.temperature_reading(), abs=0.5)
    hx6.nmt.state = "PRE-OPERATIONAL"
    hx6.sdo[0x1803][1].raw = 0x80000000 | (0x480 + NODE_ID)
    hx6.sdo[0x1A03][0].raw = 0
    hx6.sdo[0x1A03][1].raw = 0x20100110  # an actual length (REAL32) with 16 bits: not mappable
    assert abort_code(lambda: hx6.sdo[0x1A03][0].write(1)) == 0x06040041


def test_geometry_read_written_and_checked(device: Device, hx6: canopen.RemoteNode) -> None:
    live = np.array([hx6.sdo[0x2100 + leg][axis].raw for leg in range(6) for axis in (1, 2, 3)]
                    + [hx6.sdo[0x2110 + leg][axis].raw for leg in range(6) for axis in (1, 2, 3)]
                    + [hx6.sdo[0x2120][leg].raw for leg in range(1, 7)], dtype=np.float32)
    assert np.array_equal(live, NOMINAL)
    assert hx6.sdo[0x2300][1].raw == zlib.crc32(struct.pack("<42f", *live))
    enable(hx6)
    assert abort_code(lambda: hx6.sdo[0x2120][2].write(4000.25)) == DEVICE_STATE
    hx6.sdo[0x6040].raw = State402.CW_SHUTDOWN
    hx6.sdo[0x2120][2].raw = 4000.25
    hx6.sdo[0x2110 + 3][2].raw = -812.5
    assert hx6.sdo[0x2120][2].raw == 4000.25 and hx6.sdo[0x2110 + 3][2].raw == -812.5
    live[37], live[18 + 3 * 3 + 1] = 4000.25, -812.5
    assert hx6.sdo[0x2300][1].raw == zlib.crc32(struct.pack("<42f", *live))
    assert hx6.sdo[0x2300][3].raw == zlib.crc32(struct.pack("<42f", *NOMINAL))  # not stored
    assert abort_code(lambda: hx6.sdo[0x2120][1].write(float("nan"))) == VALUE_RANGE
    assert abort_code(lambda: hx6.sdo[0x2100][1].write(20000.0)) == VALUE_RANGE
    reset_node(hx6, device.boot_ups)
    assert hx6.sdo[0x2120][2].raw == NOMINAL[37]  # a reset loads the stored set


def test_compensation_terms_and_stroke_tables(device: Device, hx6: canopen.RemoteNode) -> None:
    hx6.sdo[0x2200][2].raw = 5
    table = [0.01, -0.02, 0.03, 0.0, 0.015]
    hx6.sdo[0x2212].raw = struct.pack("<5f", *table)  # leg 3's table: a segmented download
    assert struct.unpack("<5f", hx6.sdo[0x2212].raw) == pytest.approx(table)
    assert abort_code(lambda: hx6.sdo[0x2210].write(struct.pack("<4f", 0, 0, 0, 0))) == 0x06070010
    hx6.sdo[0x2206][3].raw = -400.0
    hx6.sdo[0x2207][3].raw = 400.0
    hx6.sdo[0x2202][1].raw = 0.05
    hx6.sdo[0x2200][3].raw = 21.5
    assert abort_code(lambda: hx6.sdo[0x2201][1].write(1e6)) == VALUE_RANGE
    block = device.model.block()
    assert block["table_mm"][2] == pytest.approx(table) and block["backlash_mm"][0] == pytest.approx(0.05)
    data = struct.pack("<HHf", 1, 5, 21.5)
    for leg in range(6):
        terms = [0.0] * 7
        if leg == 0:
            terms[1] = 0.05
        if leg == 2:
            terms[5], terms[6] = -400.0, 400.0
        data += struct.pack("<7f", *terms) + struct.pack("<5f", *(table if leg == 2 else [0.0] * 5))
    assert hx6.sdo[0x2300][2].raw == zlib.crc32(data)
    reset_node(hx6, device.boot_ups)
    assert hx6.sdo[0x2200][2].raw == 0 and hx6.sdo[0x2202][1].raw == 0.0


def test_store_signature_and_restore_defaults(device: Device, hx6: canopen.RemoteNode) -> None:
    assert hx6.sdo[0x1010][1].raw == 1  # stores on command
    assert abort_code(lambda: hx6.sdo.download(0x1010, 1, b"SAVE")) == CANNOT_STORE
    enable(hx6)
    assert abort_code(lambda: hx6.sdo.download(0x1010, 4, SAVE)) == DEVICE_STATE
    hx6.sdo[0x6040].raw = State402.CW_SHUTDOWN
    count = hx6.sdo[0x2300][5].raw
    hx6.sdo[0x2120][6].raw = 4001.0
    hx6.sdo.download(0x1010, 4, SAVE)
    assert hx6.sdo[0x2300][5].raw == count + 1
    reset_node(hx6, device.boot_ups)
    assert hx6.sdo[0x2120][6].raw == 4001.0
    hx6.sdo.download(0x1011, 4, LOAD)
    assert hx6.sdo[0x2120][6].raw == 4001.0  # restored defaults take effect at the next reset
    reset_node(hx6, device.boot_ups)
    assert hx6.sdo[0x2120][6].raw == NOMINAL[41]


def test_stored_communication_parameters_survive_a_reset(device: Device, hx6: canopen.RemoteNode) -> None:
    hx6.sdo[0x1017].raw = 250
    hx6.sdo.download(0x1010, 2, SAVE)
    reset_node(hx6, device.boot_ups)
    assert hx6.sdo[0x1017].raw == 250
    hx6.sdo.download(0x1011, 2, LOAD)
    reset_node(hx6, device.boot_ups, "RESET COMMUNICATION")
    assert hx6.sdo[0x1017].raw == int(EDS["1017"]["DefaultValue"], 0)


def test_virtual_bus_carrier(tmp_path) -> None:
    rig = SimulatedRig(ROBOT, RigConfig(seed=1, errors=GeometryErrors.zero()))
    model = CanopenController(ROBOT, rig, ControllerSimConfig(time_scale=1000.0))
    channel = f"hx6-{tmp_path.name}"
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel)
    node = canopen.RemoteNode(1, str(HEXAPOD_CONTROLLER_EDS))
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    net.add_node(node)
    states: list[int] = []
    node.nmt.add_heartbeat_callback(states.append)
    try:
        with serve_canopen(model, "hexapod", bus_config={"interface": "virtual", "channel": channel}):
            wait_for(lambda: 0x7F in states)
            assert states[0] == 0x00  # the boot-up went out on the bus at power-on, then heartbeats
            assert node.sdo[0x1018][1].raw == int(EDS["1018sub1"]["DefaultValue"], 0)
    finally:
        net.disconnect()


def test_dead_transducer_stops_the_move_with_a_following_error_emcy(tmp_path) -> None:
    rig = SimulatedRig(ROBOT, RigConfig(seed=2, errors=GeometryErrors.zero()))
    model = CanopenController(ROBOT, rig, ControllerSimConfig(time_scale=1000.0, dead_transducer_legs=[2]))
    channel = f"hx6-dead-{tmp_path.name}"
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel)
    node = canopen.RemoteNode(1, str(HEXAPOD_CONTROLLER_EDS))
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    net.add_node(node)
    try:
        with serve_canopen(model, "hexapod", bus_config={"interface": "virtual", "channel": channel}):
            wait_for(lambda: node.sdo[0x6041].raw == 0x0240)
            enable(node)
            start = actual_lengths(node)
            for leg in range(6):
                node.sdo[0x2000][leg + 1].raw = float(start[leg] + 20.0)
            node.sdo[0x2001].raw = 1
            wait_for(lambda: node.emcy.active and node.emcy.active[-1].code == 0x8611)
            emcy = node.emcy.active[-1]
            assert emcy.register & 0x21 == 0x21 and emcy.data[0] == FaultCode.FOLLOWING_ERROR
            assert state402(node) == "FAULT" and node.sdo[0x6041].raw & 0x2000
            assert node.sdo[0x2400][2].raw == FaultCode.FOLLOWING_ERROR
            moved = actual_lengths(node) - start
            assert moved[1] == pytest.approx(0.0, abs=0.002) and 4.0 < moved[0] < 6.0  # stopped at the 5 mm limit
    finally:
        net.disconnect()
