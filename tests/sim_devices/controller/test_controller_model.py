"""The simulated controller model and the CAN protocol definition: transition table, servo, e-stop, the DBC and
CRC catalogue, and which code the driver and the simulator share.

Expected values come from the protocol definition in docs/protocols.md (byte layouts, codes, CRC catalogue
values) and from the robot geometry, never from the code under test.
"""

from __future__ import annotations

import ast
from pathlib import Path

import cantools
import numpy as np
import pytest

from drivers.controller.can_codec import FrameCodec
from hilcal.protocols import controller_dbc_text
from hilcal.protocols.checksums import crc8_sae_j1850, crc16_modbus, crc32_ieee
from hilcal.protocols.controller_states import Command, ControllerState, FaultCode, RefusalReason
from hilcal.robot import Robot
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig
from tests.drivers.controller.can_frames import (
    ID_ACK,
    ID_COMMAND,
    ID_ESTOP,
    ID_FAULT_EVENT,
    ID_STATUS,
    R,
    S,
    crc8_bitwise,
    seal,
)

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def rig(robot: Robot) -> SimulatedRig:
    return SimulatedRig(robot, RigConfig(seed=7, errors=GeometryErrors.zero()))


# ------------------------------------------------------------------ protocol definition


def test_checksum_catalogue_check_values() -> None:
    assert crc8_sae_j1850(b"123456789") == 0x4B
    assert crc8_bitwise(b"123456789") == 0x4B
    assert crc32_ieee(b"123456789") == 0xCBF43926
    assert crc16_modbus(b"123456789") == 0x4B37


def test_dbc_ids_and_counter_checksum_layout() -> None:
    db = cantools.database.load_string(controller_dbc_text(), "dbc")
    ids = {m.name: m.frame_id for m in db.messages}
    assert ids == {
        "EstopRequest": ID_ESTOP, "FaultEvent": ID_FAULT_EVENT, "Command": ID_COMMAND, "CommandAck": ID_ACK,
        "SetpointL12": 0x110, "SetpointL34": 0x111, "SetpointL56": 0x112, "Status": ID_STATUS,
        "FeedbackL12": 0x190, "FeedbackL34": 0x191, "FeedbackL56": 0x192,
    }
    for m in db.messages:
        sig = {s.name: s for s in m.signals}
        assert m.length == 8 and not m.is_extended_frame
        assert (sig["Counter"].start, sig["Counter"].length) == (48, 4), m.name
        assert (sig["Checksum"].start, sig["Checksum"].length) == (56, 8), m.name
    leg = db.get_message_by_name("SetpointL34").get_signal_by_name("Leg4Setpoint")
    assert (leg.start, leg.length, leg.scale, leg.unit) == (24, 24, 0.001, "mm")
    assert db.get_message_by_name("Status").cycle_time == 20


def test_dbc_value_tables_match_the_enums() -> None:
    db = cantools.database.load_string(controller_dbc_text(), "dbc")
    states = db.get_message_by_name("Status").get_signal_by_name("State").choices
    assert {int(k): str(v) for k, v in states.items()} == {s.value: s.name for s in ControllerState}
    reasons = db.get_message_by_name("CommandAck").get_signal_by_name("Reason").choices
    assert {int(k): str(v) for k, v in reasons.items()} == {r.value: r.name for r in RefusalReason}
    faults = db.get_message_by_name("Status").get_signal_by_name("FaultCode").choices
    assert {int(k): str(v) for k, v in faults.items()} == {f.value: f.name for f in FaultCode}


def test_driver_encodes_setpoint_bytes_as_documented() -> None:
    msg = FrameCodec().encode("SetpointL12", {"Leg1Setpoint": 4_300_123, "Leg2Setpoint": 3_800_000}, counter=21)
    assert msg.arbitration_id == 0x110
    payload = bytes([0x5B, 0x9D, 0x41, 0xC0, 0xFB, 0x39, 21 % 16])
    assert bytes(msg.data) == seal(0x110, payload)


def test_driver_decode_rejects_flipped_bit_and_wrong_length() -> None:
    codec = FrameCodec()
    good = seal(ID_STATUS, bytes([3, 0, 0x3F, 0x15, 0, 0, 7]))
    decoded = codec.decode(ID_STATUS, good)
    assert decoded.signals["State"] == 3 and decoded.signals["InPosition"] == 0x3F
    assert decoded.signals["SetpointCounter"] == 5 and decoded.signals["SetpointValid"] == 1
    for bit in range(64):
        bad = bytearray(good)
        bad[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(Exception, match="checksum") as info:
            codec.decode(ID_STATUS, bytes(bad))
        assert type(info.value).__name__ == "ChecksumError"
    with pytest.raises(Exception, match="bytes instead of 8"):
        codec.decode(ID_STATUS, good[:7])


def _imports(path: str) -> set[str]:
    tree = ast.parse(Path(path).read_text())
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def test_driver_and_simulator_share_only_protocol_data() -> None:
    root = Path(__file__).resolve().parents[3]
    for name in ("base", "hilcal_can", "modbus"):
        imports = _imports(str(root / "drivers" / "controller" / f"{name}.py"))
        assert not any(m.startswith("sim_devices") for m in imports), name
    for name in ("state_machine", "servers", "can_peer", "can_faults", "slcan_protocol", "slcan_server",
                 "can_bus_server", "modbus_frames", "modbus_faults", "modbus_protocol", "modbus_server", "link_gaps"):
        imports = _imports(str(root / "sim_devices" / "controller" / f"{name}.py"))
        assert not any(m.startswith("drivers") or m == "hilcal.kinematics" for m in imports), name
    for name in ("__init__", "checksums", "controller_states", "registers"):
        imports = _imports(str(root / "hilcal" / "protocols" / f"{name}.py"))
        assert not imports & {"can", "cantools", "pymodbus", "serial", "socket", "threading"}, name
        assert not any(m.startswith(("drivers", "sim_devices")) for m in imports), name


# ------------------------------------------------------------------ state machine of the controller model


class ManualClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def model_in_state(robot: Robot, rig: SimulatedRig, state: ControllerState) -> tuple[SimulatedController, ManualClock]:
    clock = ManualClock()
    ctl = SimulatedController(robot, rig, ControllerSimConfig(time_scale=1.0), clock=clock)
    here = ctl.snapshot().lengths_mm
    if state in (S.ENABLED, S.MOVING, S.IN_POSITION):
        assert ctl.command(Command.ENABLE) is R.ACCEPTED
    if state is S.MOVING:
        assert ctl.set_setpoint(here + 10.0) is R.ACCEPTED
    if state is S.IN_POSITION:
        assert ctl.set_setpoint(here) is R.ACCEPTED
        clock.t += 1.0
    if state is S.FAULT:
        ctl.inject_fault(FaultCode.DRIVE)
    if state is S.ESTOP:
        ctl.press_estop("request")
    assert ctl.state is state
    return ctl, clock


ALLOWED = {  # the transition table of docs/protocols.md
    Command.ENABLE: {S.DISABLED},
    Command.DISABLE: {S.ENABLED, S.MOVING, S.IN_POSITION},
    Command.STOP: {S.ENABLED, S.MOVING, S.IN_POSITION},
    Command.FAULT_RESET: {S.FAULT, S.ESTOP},
}
AFTER = {Command.ENABLE: S.ENABLED, Command.DISABLE: S.DISABLED, Command.STOP: S.ENABLED,
         Command.FAULT_RESET: S.DISABLED}


@pytest.mark.parametrize("state", list(ControllerState))
@pytest.mark.parametrize("command", [Command.ENABLE, Command.DISABLE, Command.STOP, Command.FAULT_RESET])
def test_controller_enforces_transition_table(
    robot: Robot, rig: SimulatedRig, state: ControllerState, command: Command
) -> None:
    ctl, _ = model_in_state(robot, rig, state)
    reason = ctl.command(command)
    if state in ALLOWED[command]:
        assert reason is R.ACCEPTED
        assert ctl.state is AFTER[command]
    else:
        expected = {S.FAULT: R.FAULT_ACTIVE, S.ESTOP: R.ESTOP_ACTIVE}.get(state, R.WRONG_STATE)
        assert reason is expected
        assert ctl.state is state


@pytest.mark.parametrize("state", list(ControllerState))
def test_controller_accepts_setpoints_only_when_enabled(
    robot: Robot, rig: SimulatedRig, state: ControllerState
) -> None:
    ctl, _ = model_in_state(robot, rig, state)
    reason = ctl.set_setpoint(ctl.snapshot().lengths_mm + 1.0)
    expected = {S.DISABLED: R.WRONG_STATE, S.FAULT: R.FAULT_ACTIVE, S.ESTOP: R.ESTOP_ACTIVE}.get(state, R.ACCEPTED)
    assert reason is expected
    if expected is R.ACCEPTED:
        assert ctl.state is S.MOVING


def test_servo_moves_at_leg_speed_and_settles(robot: Robot, rig: SimulatedRig) -> None:
    clock = ManualClock()
    cfg = ControllerSimConfig(time_scale=10.0, leg_speed_mm_s=50.0, settle_s=0.05)
    ctl = SimulatedController(robot, rig, cfg, clock=clock)
    start = ctl.snapshot().lengths_mm
    ctl.command(Command.ENABLE)
    ctl.set_setpoint(start + np.array([10.0, -10.0, 5.0, 0.0, 2.0, -1.0]))
    clock.t += 0.01  # 0.1 s simulated -> at most 5 mm
    moved = ctl.snapshot().lengths_mm - start
    np.testing.assert_allclose(moved, [5.0, -5.0, 5.0, 0.0, 2.0, -1.0], atol=0.0011)
    assert ctl.state is S.MOVING
    clock.t += 0.01  # 0.2 s: every leg arrived at 0.2 s, not settled yet
    assert ctl.state is S.MOVING
    assert all(ctl.snapshot().in_position)
    clock.t += 0.006  # 0.06 s after arrival > settle time
    assert ctl.state is S.IN_POSITION


def test_controller_can_start_faulted_or_with_estop_pressed(robot: Robot, rig: SimulatedRig) -> None:
    faulted = SimulatedController(robot, rig, ControllerSimConfig(initial_fault=FaultCode.ENCODER))
    assert (faulted.state, faulted.snapshot().fault) == (S.FAULT, FaultCode.ENCODER)
    pressed = SimulatedController(robot, rig, ControllerSimConfig(estop_pressed=True))
    assert pressed.state is S.ESTOP and pressed.snapshot().estop_input
    assert pressed.command(Command.FAULT_RESET) is R.ESTOP_NOT_RELEASED


def test_estop_input_must_be_released_before_reset(robot: Robot, rig: SimulatedRig) -> None:
    ctl, _ = model_in_state(robot, rig, S.ENABLED)
    ctl.press_estop("input")
    assert ctl.state is S.ESTOP
    assert ctl.command(Command.FAULT_RESET) is R.ESTOP_NOT_RELEASED
    ctl.release_estop()
    assert ctl.state is S.ESTOP
    assert ctl.command(Command.FAULT_RESET) is R.ACCEPTED
    assert ctl.state is S.DISABLED
