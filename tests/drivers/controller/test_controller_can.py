"""Controller over CAN: the real driver against the simulated controller on SLCAN/pty, SLCAN/TCP and virtual CAN.

Expected values come from the protocol definition in docs/protocols.md (byte layouts, codes, CRC catalogue
values) and from the robot geometry, never from the code under test.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass

import can
import numpy as np
import pytest
import serial

from drivers.controller.base import (
    CommandRefused,
    CommandTimeout,
    ControllerError,
    ControllerFault,
    ControllerLost,
    EStopActive,
    LimitViolation,
)
from drivers.controller.hilcal_can import ControllerCan
from hilcal.protocols.controller_states import Command, FaultCode
from hilcal.robot import Robot
from sim_devices.controller.can_bus_server import CanBusServer
from sim_devices.controller.can_peer import ControllerCanPeer
from sim_devices.controller.servers import start_controller_servers
from sim_devices.controller.slcan_server import SlcanServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig
from tests.drivers.controller.can_frames import (
    HEARTBEAT_TIMEOUT_S,
    ID_ACK,
    ID_COMMAND,
    ID_FEEDBACK,
    ID_STATUS,
    Ack,
    R,
    S,
    command_frame,
    crc8_bitwise,
    ik,
    parse_ack,
    setpoint_frames,
    wait_until,
)

pytestmark = pytest.mark.timeout(60)


# ------------------------------------------------------------------ fixtures


@pytest.fixture
def rig(robot: Robot) -> SimulatedRig:
    return SimulatedRig(robot, RigConfig(seed=7, errors=GeometryErrors.zero()))


@dataclass
class CanRig:
    controller: SimulatedController
    server: SlcanServer | CanBusServer
    driver: ControllerCan

    @property
    def peer(self) -> ControllerCanPeer:
        return self.server.peer


@pytest.fixture
def make_can_rig(robot: Robot, rig: SimulatedRig) -> Iterator[Callable[..., CanRig]]:
    """Factory: a controller served on 'pty' (SLCAN), 'tcp' (SLCAN over socket://) or 'virtual' CAN."""
    stack = ExitStack()

    def make(transport: str = "pty", **config: object) -> CanRig:
        controller = SimulatedController(robot, rig, ControllerSimConfig(**config))
        peer = ControllerCanPeer(controller)
        if transport == "virtual":
            channel = f"hilcal-test-{os.getpid()}-{time.monotonic_ns()}"
            server: SlcanServer | CanBusServer = CanBusServer(peer, {"interface": "virtual", "channel": channel})
            bus_config: dict[str, object] = {"interface": "virtual", "channel": channel}
        else:
            server = SlcanServer(peer, transport=transport)  # type: ignore[arg-type]
        server.start()
        stack.callback(server.close)
        if transport != "virtual":  # with a bitrate python-can sends C, S6, an empty line, O, O
            bus_config = {"interface": "slcan", "channel": server.channel, "sleep_after_open": 0, "bitrate": 500000}
        driver = ControllerCan(bus_config, robot, heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S, ack_timeout_s=0.5)
        stack.callback(driver.close)
        driver.wait_for_heartbeat(2.0)
        return CanRig(controller, server, driver)

    yield make
    stack.close()


def test_driver_reports_an_interface_that_cannot_open(robot: Robot) -> None:
    with pytest.raises(ControllerError, match="cannot open the CAN interface"):
        ControllerCan({"interface": "slcan", "channel": "/dev/hilcal-no-such-port", "sleep_after_open": 0}, robot)


# ------------------------------------------------------------------ controller enforcement over the wire (virtual CAN)


class RawHost:
    """A hand-written CAN host on the virtual bus: frames built from the documented layout."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)

    def send(self, frame_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))

    def wait_for(self, frame_id: int, timeout_s: float = 1.0) -> bytes:
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(timeout=remaining)
            if msg is not None and msg.arbitration_id == frame_id:
                return bytes(msg.data)
        raise AssertionError(f"no frame 0x{frame_id:03X} within {timeout_s} s")

    def command(self, code: int, counter: int) -> Ack:
        self.send(ID_COMMAND, command_frame(code, counter))
        return parse_ack(self.wait_for(ID_ACK))


@pytest.fixture
def raw_host(robot: Robot, rig: SimulatedRig) -> Iterator[tuple[RawHost, SimulatedController, ControllerCanPeer]]:
    channel = f"hilcal-raw-{os.getpid()}-{time.monotonic_ns()}"
    controller = SimulatedController(robot, rig, ControllerSimConfig(time_scale=1000.0))
    peer = ControllerCanPeer(controller)
    with CanBusServer(peer, {"interface": "virtual", "channel": channel}).start():
        host = RawHost(channel)
        try:
            yield host, controller, peer
        finally:
            host.bus.shutdown()


def test_heartbeat_frames_decode_by_hand(
    raw_host: tuple[RawHost, SimulatedController, ControllerCanPeer], rig: SimulatedRig
) -> None:
    host, _, _ = raw_host
    status = host.wait_for(ID_STATUS)
    assert status[7] == crc8_bitwise(bytes([0x01, 0x80]) + status[:7])
    assert status[0] & 0x0F == S.DISABLED and status[1] == FaultCode.NONE
    reported = rig.reported_lengths()
    for k, fid in enumerate(ID_FEEDBACK):
        data = host.wait_for(fid)
        assert data[7] == crc8_bitwise(bytes([fid >> 8, fid & 0xFF]) + data[:7])
        legs = [int.from_bytes(data[0:3], "little"), int.from_bytes(data[3:6], "little")]
        np.testing.assert_allclose(legs, np.round(reported[2 * k:2 * k + 2] * 1000), atol=1)


def test_controller_refuses_commands_by_state_over_can(
    raw_host: tuple[RawHost, SimulatedController, ControllerCanPeer], robot: Robot
) -> None:
    host, controller, _ = raw_host
    assert host.command(Command.FAULT_RESET, 0) == Ack(Command.FAULT_RESET, R.WRONG_STATE, S.DISABLED, 0)
    here = controller.snapshot().lengths_mm
    for fid, data in setpoint_frames(here + 1.0, counter=3):
        host.send(fid, data)
    assert parse_ack(host.wait_for(ID_ACK)) == Ack(Command.SETPOINT, R.WRONG_STATE, S.DISABLED, 3)
    assert host.command(Command.ENABLE, 1) == Ack(Command.ENABLE, R.ACCEPTED, S.ENABLED, 1)
    assert host.command(Command.ENABLE, 2) == Ack(Command.ENABLE, R.WRONG_STATE, S.ENABLED, 2)
    assert host.command(0x55, 3) == Ack(0x55, R.UNKNOWN_COMMAND, S.ENABLED, 3)
    frames = setpoint_frames(here + 1.0, counter=4)
    host.send(*frames[0])
    host.send(*frames[2])
    assert parse_ack(host.wait_for(ID_ACK)) == Ack(Command.SETPOINT, R.SETPOINT_INCOMPLETE, S.ENABLED, 4)
    beyond = here.copy()
    beyond[4] = robot.leg_limits[1] + 0.5
    for fid, data in setpoint_frames(beyond, counter=5):
        host.send(fid, data)
    assert parse_ack(host.wait_for(ID_ACK)) == Ack(Command.SETPOINT, R.SETPOINT_OUT_OF_LIMITS, S.ENABLED, 5)
    for fid, data in setpoint_frames(here + 1.0, counter=6):
        host.send(fid, data)
    assert parse_ack(host.wait_for(ID_ACK)) == Ack(Command.SETPOINT, R.ACCEPTED, S.MOVING, 6)


def test_controller_discards_corrupted_and_repeated_commands(
    raw_host: tuple[RawHost, SimulatedController, ControllerCanPeer],
) -> None:
    host, controller, peer = raw_host
    bad = bytearray(command_frame(Command.ENABLE, 0))
    bad[0] ^= 0x04
    host.send(ID_COMMAND, bytes(bad))
    host.send(ID_COMMAND, command_frame(Command.ENABLE, 1))
    assert parse_ack(host.wait_for(ID_ACK)) == Ack(Command.ENABLE, R.ACCEPTED, S.ENABLED, 1)
    host.send(ID_COMMAND, command_frame(Command.DISABLE, 1))  # same counter: a repeat, must not execute
    host.send(ID_COMMAND, command_frame(Command.STOP, 4))  # counter jump 1 -> 4: two frames lost
    assert parse_ack(host.wait_for(ID_ACK)) == Ack(Command.STOP, R.ACCEPTED, S.ENABLED, 4)
    assert controller.state is S.ENABLED
    assert (peer.stats.rx_checksum_errors, peer.stats.rx_repeated, peer.stats.rx_lost) == (1, 1, 2)


# ------------------------------------------------------------------ the driver over SLCAN on a pty


def test_move_to_pose_over_slcan(make_can_rig: Callable[..., CanRig], robot: Robot) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    assert r.driver.state is S.DISABLED
    r.driver.enable()
    assert r.driver.state is S.ENABLED
    pose = [35.0, -20.0, 3150.0, 1.5, -2.0, 3.0]
    setpoint = ik(robot, pose)
    measured = r.driver.move_legs(setpoint, timeout_s=5.0)
    np.testing.assert_allclose(measured, setpoint, atol=0.002)
    lengths, state, fault = r.driver.feedback()
    assert state is S.IN_POSITION and fault is FaultCode.NONE
    np.testing.assert_allclose(lengths, setpoint, atol=0.002)
    true_pose = r.controller.true_pose()
    np.testing.assert_allclose(true_pose[:3], pose[:3], atol=0.01)
    np.testing.assert_allclose(true_pose[3:], pose[3:], atol=1e-4)
    r.driver.disable()
    assert r.driver.state is S.DISABLED


def test_setpoint_beyond_leg_limits_is_refused_before_sending(
    make_can_rig: Callable[..., CanRig], robot: Robot
) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    r.driver.enable()
    sent_before = r.driver.frame_stats.tx_frames
    lo, hi = robot.leg_limits
    for bad in ([hi + 0.001, *[4300.0] * 5], [4300.0] * 5 + [lo - 1.0], [4300.0, np.nan, *[4300.0] * 4]):
        with pytest.raises(LimitViolation, match="leg"):
            r.driver.move_legs(bad, timeout_s=1.0)
    with pytest.raises(LimitViolation, match="6 leg lengths"):
        r.driver.move_legs([4300.0] * 5, timeout_s=1.0)
    time.sleep(0.05)
    assert r.driver.frame_stats.tx_frames == sent_before
    assert not any(name.startswith("Setpoint") for name in r.peer.stats.rx_by_name)


def test_driver_refuses_commands_the_state_does_not_allow(make_can_rig: Callable[..., CanRig], robot: Robot) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    here = r.driver.feedback().lengths_mm
    with pytest.raises(CommandRefused) as info:
        r.driver.move_legs(here, timeout_s=1.0)
    assert (info.value.reason, info.value.by) == (R.WRONG_STATE, "driver")
    with pytest.raises(CommandRefused) as info:
        r.driver.fault_reset()
    assert info.value.reason is R.WRONG_STATE
    with pytest.raises(CommandRefused):
        r.driver.stop()
    assert sum(r.peer.stats.rx_by_name.values()) == 0
    r.driver.enable()
    with pytest.raises(CommandRefused) as info:
        r.driver.enable()
    assert info.value.reason is R.WRONG_STATE
    assert r.peer.stats.rx_by_name["Command"] == 1


def test_heartbeat_loss_refuses_commands_until_it_resumes(make_can_rig: Callable[..., CanRig]) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    assert r.driver.controller_alive
    r.server.faults.set_heartbeat(False)
    wait_until(lambda: not r.driver.controller_alive, timeout_s=2.0)
    with pytest.raises(ControllerLost, match="no heartbeat"):
        r.driver.feedback()
    with pytest.raises(ControllerLost):
        r.driver.enable()
    with pytest.raises(ControllerLost):
        _ = r.driver.state
    assert r.peer.stats.rx_by_name["Command"] == 0
    r.server.faults.set_heartbeat(True)
    r.driver.wait_for_heartbeat(2.0)
    r.driver.enable()
    assert r.controller.state is S.ENABLED


def test_dropped_corrupted_and_repeated_frames_are_detected(make_can_rig: Callable[..., CanRig]) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    stats = r.driver.frame_stats
    time.sleep(0.1)
    assert (stats.lost, stats.checksum_errors, stats.repeated) == (0, 0, 0)
    r.server.faults.drop_next(1, frame_id=ID_STATUS)
    wait_until(lambda: stats.lost >= 1)
    r.server.faults.corrupt_next(1, frame_id=ID_FEEDBACK[1])
    wait_until(lambda: stats.checksum_errors >= 1)
    r.server.faults.repeat_next(1, frame_id=ID_FEEDBACK[0])
    wait_until(lambda: stats.repeated >= 1)
    time.sleep(0.1)
    # the corrupted frame was discarded, so its ID's counter also shows one frame lost
    assert (stats.lost, stats.checksum_errors, stats.repeated) == (2, 1, 1)
    assert stats.incomplete_cycles == 2
    np.testing.assert_allclose(r.driver.feedback().lengths_mm, r.controller.snapshot().lengths_mm, atol=0.0011)


def test_corrupted_command_is_not_executed_and_times_out(make_can_rig: Callable[..., CanRig]) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    r.driver.enable()
    r.driver.disable()
    r.server.faults.corrupt_next(1, frame_id=ID_COMMAND, direction="rx")
    with pytest.raises(CommandTimeout, match="ENABLE"):
        r.driver.enable()
    assert r.controller.state is S.DISABLED
    assert r.peer.stats.rx_checksum_errors == 1
    r.driver.enable()
    assert r.controller.state is S.ENABLED
    assert r.peer.stats.rx_lost == 1


def test_a_late_acknowledgement_does_not_answer_a_later_setpoint(make_can_rig: Callable[..., CanRig]) -> None:
    """An acknowledgement that comes after its setpoint timed out is never used: 16 setpoints later the 4-bit
    counter is the same again, and that move still waits for its own acknowledgement and ends in position."""
    r = make_can_rig("pty", time_scale=500.0)
    r.driver.enable()
    start = r.driver.feedback().lengths_mm
    r.server.faults.delay_next(0.7, frame_id=ID_ACK)
    with pytest.raises(CommandTimeout, match="SETPOINT"):
        r.driver.move_legs(start + 0.5, timeout_s=3.0)
    time.sleep(0.4)  # the late acknowledgement arrives
    for k in range(1, 17):
        target = start + 0.5 + 0.1 * k
        np.testing.assert_allclose(r.driver.move_legs(target, timeout_s=3.0), target, atol=0.002)


def test_repeated_command_frame_executes_once(make_can_rig: Callable[..., CanRig]) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    r.server.faults.repeat_next(1, frame_id=ID_COMMAND, direction="rx")
    r.driver.enable()
    time.sleep(0.05)
    assert r.peer.stats.rx_repeated == 1
    assert r.peer.stats.rx_by_name["Command"] == 1
    assert r.controller.state is S.ENABLED


def test_fault_stops_motion_and_needs_a_reset(make_can_rig: Callable[..., CanRig]) -> None:
    r = make_can_rig("pty", time_scale=1.0, leg_speed_mm_s=50.0)
    r.driver.enable()
    start = r.driver.feedback().lengths_mm
    target = start + 20.0  # 0.4 s at 50 mm/s
    timer = threading.Timer(0.1, r.controller.inject_fault, args=(FaultCode.HYDRAULIC_PRESSURE,))
    timer.start()
    try:
        with pytest.raises(ControllerFault) as info:
            r.driver.move_legs(target, timeout_s=3.0)
    finally:
        timer.cancel()
    assert info.value.fault is FaultCode.HYDRAULIC_PRESSURE and info.value.state is S.FAULT
    first = r.controller.strokes_mm()
    time.sleep(0.15)
    np.testing.assert_array_equal(r.controller.strokes_mm(), first)
    assert (target - r.driver.feedback().lengths_mm).min() > 5.0
    with pytest.raises(CommandRefused) as refused:
        r.driver.enable()
    assert refused.value.reason is R.FAULT_ACTIVE
    r.driver.fault_reset()
    assert r.controller.state is S.DISABLED
    r.driver.enable()
    assert r.controller.state is S.ENABLED


def test_estop_stops_motion_and_is_latched(make_can_rig: Callable[..., CanRig]) -> None:
    r = make_can_rig("pty", time_scale=1.0, leg_speed_mm_s=50.0)
    r.driver.enable()
    target = r.driver.feedback().lengths_mm - 20.0
    with ThreadPoolExecutor(1) as pool:
        move = pool.submit(r.driver.move_legs, target, 3.0)
        wait_until(lambda: r.controller.state is S.MOVING)
        time.sleep(0.05)
        r.driver.estop()
        with pytest.raises(EStopActive):
            move.result(timeout=3.0)
    assert r.driver.state is S.ESTOP
    first = r.controller.strokes_mm()
    time.sleep(0.1)
    np.testing.assert_array_equal(r.controller.strokes_mm(), first)
    r.controller.press_estop("input")
    wait_until(lambda: r.driver.estop_input)
    with pytest.raises(CommandRefused) as refused:
        r.driver.fault_reset()
    assert refused.value.reason is R.ESTOP_NOT_RELEASED
    with pytest.raises(CommandRefused) as refused:
        r.driver.enable()
    assert refused.value.reason is R.ESTOP_ACTIVE
    r.controller.release_estop()
    wait_until(lambda: not r.driver.estop_input)
    r.driver.fault_reset()
    assert r.controller.state is S.DISABLED


def test_uploaded_leg_offsets_change_reported_and_commanded_lengths(
    make_can_rig: Callable[..., CanRig], robot: Robot, rig: SimulatedRig
) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    before = r.driver.feedback().lengths_mm
    rig_before = rig.reported_lengths()
    delta = np.array([0.5, -0.25, 0.125, 1.0, -1.5, 0.75])
    params = np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0 + delta])
    r.controller.install_parameters(params)
    wait_until(lambda: np.allclose(r.driver.feedback().lengths_mm - before, delta, atol=0.0011))
    np.testing.assert_allclose(rig.reported_lengths(), rig_before, atol=1e-9)
    r.driver.enable()
    setpoint = ik(robot, [0.0, 0.0, 3100.0, 0.0, 0.0, 0.0])
    r.driver.move_legs(setpoint, timeout_s=5.0)
    np.testing.assert_allclose(rig.reported_lengths(), setpoint - delta, atol=0.0011)


def test_delayed_frames_still_work_and_add_latency(make_can_rig: Callable[..., CanRig]) -> None:
    r = make_can_rig("pty", time_scale=500.0)
    r.server.faults.delay_s = 0.04
    r.driver.enable()
    t0 = time.monotonic()
    r.driver.move_legs(r.driver.feedback().lengths_mm + 0.5, timeout_s=3.0)
    assert time.monotonic() - t0 >= 0.04


# ------------------------------------------------------------------ other transports


def test_slcan_over_tcp_socket_url(make_can_rig: Callable[..., CanRig], robot: Robot) -> None:
    r = make_can_rig("tcp", time_scale=500.0)
    assert r.server.channel.startswith("socket://127.0.0.1:")
    r.driver.enable()
    setpoint = ik(robot, [0.0, 50.0, 3000.0, 0.0, 2.0, 0.0])
    np.testing.assert_allclose(r.driver.move_legs(setpoint, timeout_s=5.0), setpoint, atol=0.002)


def test_an_unplugged_adapter_is_opened_again_and_nothing_moves_meanwhile(
        make_can_rig: Callable[..., CanRig], robot: Robot) -> None:
    r = make_can_rig("tcp", time_scale=500.0)
    r.driver.enable()
    r.server.unplug()
    wait_until(lambda: not r.driver.controller_alive, timeout_s=2.0)
    with pytest.raises(ControllerLost):
        r.driver.move_legs(ik(robot, [0.0, 50.0, 3000.0, 0.0, 2.0, 0.0]), timeout_s=5.0)
    assert r.peer.stats.rx_by_name.get("SetpointL12", 0) == 0
    feedback = r.driver.wait_for_heartbeat(5.0)
    assert r.driver.frame_stats.reopens >= 1 and r.server.stats.unplugged == 1
    assert feedback.state is S.ENABLED, "the controller ran on; the host reads its state again"
    setpoint = ik(robot, [0.0, 50.0, 3000.0, 0.0, 2.0, 0.0])
    np.testing.assert_allclose(r.driver.move_legs(setpoint, timeout_s=5.0), setpoint, atol=0.002)


def test_virtual_bus_fast_path(make_can_rig: Callable[..., CanRig], robot: Robot) -> None:
    r = make_can_rig("virtual", time_scale=500.0)
    r.driver.enable()
    for pose in ([0.0, 0.0, 3000.0, 0.0, 0.0, 0.0], [100.0, -100.0, 3200.0, 5.0, -5.0, 8.0]):
        setpoint = ik(robot, pose)
        np.testing.assert_allclose(r.driver.move_legs(setpoint, timeout_s=5.0), setpoint, atol=0.002)
    r.driver.stop()
    assert r.driver.state is S.ENABLED


def test_slcan_adapter_protocol_on_the_pty(robot: Robot, rig: SimulatedRig) -> None:
    controller = SimulatedController(robot, rig, ControllerSimConfig())
    with SlcanServer(ControllerCanPeer(controller)).start() as server:
        port = serial.Serial(server.channel, timeout=0.5)
        try:
            time.sleep(0.05)
            assert port.in_waiting == 0  # nothing before the channel is opened
            port.write(b"V\r")
            assert port.read_until(b"\r") == b"V1013\r"
            port.write(b"t1008" + command_frame(Command.ENABLE, 0).hex().upper().encode() + b"\r")
            assert port.read_until(b"\a") == b"\a"  # frame on a closed channel
            port.write(b"S6\r\rO\r")
            assert port.read(3) == b"\r\r\r"
            status = port.read_until(b"\r")
            while not status.startswith(b"t180"):
                status = port.read_until(b"\r")
            data = bytes.fromhex(status[5:21].decode())
            assert data[7] == crc8_bitwise(bytes([0x01, 0x80]) + data[:7])
            port.write(b"Qjunk\r")
            reply = port.read_until(b"\a")
            assert reply.endswith(b"\a")
            port.write(b"C\r")
            time.sleep(0.1)
            port.reset_input_buffer()
            time.sleep(0.1)
            assert port.in_waiting == 0  # closed channel: heartbeats stop
        finally:
            port.close()
    assert not server.is_open


def test_python_can_slcan_version_and_serial_queries(robot: Robot, rig: SimulatedRig) -> None:
    controller = SimulatedController(robot, rig, ControllerSimConfig())
    with SlcanServer(ControllerCanPeer(controller)).start() as server:
        bus = can.Bus(interface="slcan", channel=server.channel, sleep_after_open=0)
        try:
            assert bus.get_version(1.0) == (10, 13)
            assert bus.get_serial_number(1.0) == "HC01"
            msg = bus.recv(timeout=1.0)
            while msg is not None and msg.arbitration_id != ID_STATUS:
                msg = bus.recv(timeout=1.0)
            assert msg is not None and msg.dlc == 8
        finally:
            bus.shutdown()
        assert server.stats.sessions == 1 and server.stats.errors == 0


def test_start_controller_servers_for_the_launcher(robot: Robot, rig: SimulatedRig) -> None:
    from drivers.controller.modbus import ControllerParams

    with start_controller_servers(robot, rig, ControllerSimConfig(time_scale=500.0, modbus_rtu=True)) as servers:
        with ControllerCan({"interface": "slcan", "channel": servers.slcan_path, "sleep_after_open": 0}, robot,
                           heartbeat_timeout_s=HEARTBEAT_TIMEOUT_S) as driver:
            driver.wait_for_heartbeat(2.0)
            assert driver.state is S.DISABLED
        with ControllerParams("127.0.0.1", servers.modbus_port, timeout_s=1.0) as params:
            assert params.read_identity().parameter_count == 42
        assert servers.modbus_rtu_path is not None
        with ControllerParams(serial_port=servers.modbus_rtu_path, timeout_s=1.0) as params:
            assert params.read_state() is S.DISABLED
    assert not servers.slcan.is_open
