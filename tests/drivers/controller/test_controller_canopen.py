"""The CANopen driver against a controller it was not written for: the ACME LX-200 (``acme_lx200.eds``, served by a
plain ``canopen.LocalNode``, ``canopen_peer.py``), connected by the station file ``acme_lx200_station.toml`` alone.

Expected values come from the EDS and the peer's own state (its zero lengths in µm, a CRC-32 by ``zlib`` over the
INTEGER32s as the EDS [Comments] say), never from the driver's encoding.
"""

from __future__ import annotations

import itertools
import re
import struct
import time
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.controller.base import CommandRefused, ControllerLost, LimitViolation
from drivers.controller.canopen_mapping import drive_state
from drivers.controller.canopen_params import CanopenTransportError, NoPreviousSet, SdoAbortError
from drivers.controller.parameter_sets import CapabilityError, NotDisabled, ParameterSet
from hilcal.protocols.controller_states import ControllerState
from hilcal.robot import Robot
from procedures.sections.controller import open_canopen
from procedures.station import CanSection, StationConfig, StationConfigError, load_station
from tests.drivers.controller.canopen_peer import AcmePeer

pytestmark = pytest.mark.timeout(60)
STATION = Path(__file__).with_name("acme_lx200_station.toml")
_channels = itertools.count()


@pytest.fixture
def acme(robot: Robot) -> Iterator[tuple[AcmePeer, StationConfig]]:
    channel = f"acme-{next(_channels)}-{time.monotonic_ns()}"
    peer = AcmePeer(channel)
    station = load_station(STATION)
    station = station.model_copy(update={"can": CanSection(interface="virtual", channel=channel,
                                                           receive_own_messages=False)})
    yield peer, station
    peer.close()


@pytest.fixture
def opened(acme, robot: Robot):
    peer, station = acme
    controller, params = open_canopen(station.controller, station.can.bus_config(), robot, heartbeat_timeout_s=0.2,
                                      ack_timeout_s=0.5, position_tolerance_mm=0.002)
    controller.wait_for_heartbeat(2.0)
    yield peer, controller, params
    controller.close()


def test_identity_state_and_live_geometry(opened, robot: Robot) -> None:
    peer, _, params = opened
    identity = params.read_identity()
    assert (identity.vendor_id, identity.product_code, identity.serial_number) == (0xAC, 0x4C580200, 0x1234)
    assert identity.offsets_only and not identity.compensation
    assert params.read_state() is ControllerState.DISABLED
    live = params.read_live()
    assert live.l0_mm == [v / 1000 for v in peer.zero_um]
    assert np.array_equal(live.a_mm, robot.a)  # not held by the device: the robot file's
    described = params.describe()
    assert described["checksum"] == f"{zlib.crc32(struct.pack('<6l', *peer.zero_um)):08x}"
    assert described["checksum"] == described["checksum_expected"]


def test_upload_writes_reads_back_checks_and_stores(opened, robot: Robot) -> None:
    peer, _, params = opened
    new = ParameterSet.from_robot(robot).model_copy(update={"l0_mm": [3800.125, 3799.5, 3800.001, 3801.0, 3799.999,
                                                                      3800.0]})
    record = params.upload(new, save=True)
    assert peer.zero_um == [3800125, 3799500, 3800001, 3801000, 3799999, 3800000]
    assert peer.kept_um == peer.zero_um  # 1010h "save"
    assert record.outcome == "committed" and record.live_readback_match and record.checksum_match and record.saved
    assert [w.object.split()[0] for w in record.writes] == [f"0x4100:{k}@5" for k in range(1, 7)] + ["0x1010:1@5"]
    assert record.previous_params["l0_mm"] == [3800.0] * 6 and record.device == "canopen:000000ac:4c580200:00001234@5"
    assert params.read_live().l0_mm == new.l0_mm  # exactly: µm integers


def test_upload_refused_changes_nothing(opened, robot: Robot) -> None:
    peer, controller, params = opened
    moved = ParameterSet.from_robot(robot).to_vector()
    moved[0] += 0.5  # a1 x: the LX-200 holds no joint coordinates
    with pytest.raises(CapabilityError, match="does not hold a_mm"):
        params.upload(moved)
    controller.enable()
    with pytest.raises(NotDisabled, match="ENABLED"):
        params.upload(ParameterSet.from_robot(robot))
    assert peer.zero_um == [3800000] * 6 and params.records[-1].outcome == "refused" and not params.records[-1].writes


def test_failed_write_puts_the_old_set_back(opened, robot: Robot) -> None:
    peer, _, params = opened
    peer.fail_next[(0x4100, 4)] = 0x06090030
    new = ParameterSet.from_robot(robot).model_copy(update={"l0_mm": [3801.0] * 6})
    with pytest.raises(SdoAbortError, match=r"0x06090030 \(invalid value for parameter") as err:
        params.upload(new)
    record = err.value.record
    assert [w.ok for w in record.writes] == [True, True, True, False]
    assert len(record.restore_writes) == 4 and record.restored_readback_match
    assert "3 of 4 writes had happened" in str(err.value)
    assert peer.zero_um == [3800000] * 6


def test_rollback_writes_back_the_set_before_the_upload(opened, robot: Robot) -> None:
    peer, _, params = opened
    with pytest.raises(NoPreviousSet):
        params.rollback(None)
    first = params.upload(ParameterSet.from_robot(robot).model_copy(update={"l0_mm": [3802.0] * 6}), save=True)
    record = params.rollback(first)
    assert record.outcome == "rolled_back" and peer.zero_um == [3800000] * 6 and peer.kept_um == peer.zero_um
    again = params.rollback(record)  # a rollback of the rollback: the uploaded set again
    assert again.outcome == "rolled_back" and peer.zero_um == [3802000] * 6


def test_silent_device_mid_upload_is_a_transport_error_and_power_cycle_keeps_the_stored_set(opened, robot) -> None:
    peer, _, params = opened
    params.upload(ParameterSet.from_robot(robot).model_copy(update={"l0_mm": [3803.0] * 6}), save=True)
    original = peer._on_write

    def go_silent(index: int, subindex: int, od: object, data: bytes) -> None:
        original(index, subindex, od, data)
        if (index, subindex) == (0x4100, 2):
            peer.silence()

    peer.node._write_callbacks[peer.node._write_callbacks.index(original)] = go_silent
    with pytest.raises(CanopenTransportError) as err:
        params.upload(ParameterSet.from_robot(robot).model_copy(update={"l0_mm": [3804.0] * 6}))
    assert err.value.record.outcome == "failed" and not err.value.record.restored_readback_match
    assert peer.zero_um[:2] == [3804000] * 2 and peer.zero_um[2:] == [3803000] * 4  # a mix in RAM ...
    peer.silence(False)
    peer.power_cycle()  # ... and the stored set after a restart
    assert peer.zero_um == [3803000] * 6


def test_motion_moves_the_legs_and_refuses_before_sending(opened, robot: Robot) -> None:
    peer, controller, _ = opened
    assert controller.state is ControllerState.DISABLED
    with pytest.raises(CommandRefused, match="not sent"):
        controller.move_legs([4200.0] * 6, 5.0)
    controller.enable()
    for target in ([4200.0] * 6, [4210.5, 4190.25, 4200.0, 4205.0, 4195.0, 4201.001], [4150.0] * 6):
        reached = controller.move_legs(target, 5.0)
        assert np.allclose(reached, target, atol=0.0015)
        assert np.allclose(np.array(peer.position_um) / 1000, target, atol=0.0015)
    assert peer.executes == 3
    with pytest.raises(LimitViolation, match="leg 2"):
        controller.move_legs([4200.0, 5000.0, 4200.0, 4200.0, 4200.0, 4200.0], 5.0)
    assert peer.executes == 3
    controller.disable()
    assert controller.state is ControllerState.DISABLED


def test_fault_is_named_and_lost_link_refuses_motion(opened) -> None:
    peer, controller, _ = opened
    controller.enable()
    peer.fault(0xFF10)
    deadline = time.monotonic() + 2.0
    while controller.state is not ControllerState.FAULT and time.monotonic() < deadline:
        time.sleep(0.01)
    with pytest.raises(CommandRefused, match="FAULT_ACTIVE"):
        controller.move_legs([4200.0] * 6, 5.0)
    time.sleep(0.05)
    assert "0xFF10 (axis drive overload)" in controller._fault()[1]
    assert "0x81 (generic error, manufacturer-specific)" in controller._fault()[1]
    controller.fault_reset()
    assert controller.state is ControllerState.DISABLED
    peer.silence()
    time.sleep(0.4)
    with pytest.raises(ControllerLost, match="node"):
        controller.enable()


def test_mapping_that_does_not_fit_the_eds_is_refused_naming_the_key(tmp_path: Path) -> None:
    text = STATION.read_text()
    (tmp_path / "acme_lx200.eds").write_text(Path(STATION.with_name("acme_lx200.eds")).read_text())
    cases = {
        'l0_mm = { array = "0x4100" }': ('l0_mm = { array = "0x4010" }', "controller.geometry.l0_mm[0]: 0x4010:1"),
        'object = "0x4101"': ('object = "0x4102"', "controller.checksum.object: object 0x4102 does not exist"),
        'legs = { array = "0x4000" }   # INTEGER32 µm, sub 1..6\nscale = 1000.0': (
            'legs = { array = "0x4000" }', "controller.setpoints.legs[0]: 0x4000:1 (Axis setpoint.Axis 1, INTEGER32) "
            "is an integer: give the group's scale"),
    }
    for old, (new, expected) in cases.items():
        assert old in text
        path = tmp_path / "station.toml"
        path.write_text(text.replace(old, new))
        with pytest.raises(StationConfigError, match=re.escape(expected)):
            load_station(path)
    path.write_text(text.replace('l0_mm = { array = "0x4100" }', 'l0_mm = { array = "0x4010" }'))
    with pytest.raises(StationConfigError, match="is read-only"):
        load_station(path)


def test_a_statusword_coding_names_cia_402s_states_or_says_there_are_none(tmp_path: Path) -> None:
    """A state name outside CiA 402-2 §8.4's is refused (it would never match what the driver waits for); a device
    without power states codes its fault alone, and its at-rest and moving come from the target reached bit."""
    (tmp_path / "acme_lx200.eds").write_text(Path(STATION.with_name("acme_lx200.eds")).read_text())
    text = STATION.read_text().replace("[controller.emcy_codes]", "[controller.device_control]\n{}\n"
                                       "[controller.emcy_codes]")
    path = tmp_path / "station.toml"
    cases = {
        "states = { operation_enabled = [0x6F, 0x27] }": "unknown statusword state(s) ['operation_enabled']",
        "power_states = false\nstates = { fault = [4, 4], enabled = [4, 0] }": "codes `fault` only",
        "power_states = false\nstates = { ready = [4, 0] }": "lacks ['fault']",
    }
    for section, expected in cases.items():
        path.write_text(text.replace("{}", section))
        with pytest.raises(StationConfigError, match=re.escape(expected)):
            load_station(path)
    path.write_text(text.replace("{}", "power_states = false\ntarget_reached_bit = 1\nstates = { fault = [4, 4] }"))
    control = load_station(path).controller.device_control
    assert [drive_state(word, control) for word in (0b010, 0b001, 0b110)] == ["at_rest", "moving", "fault"]


def test_a_bit_or_command_the_device_lacks_is_written_none(tmp_path: Path) -> None:
    """TOML has no null: `"none"` (any case) says the device has no halt bit, quick stop or limit bit; another word or
    a bit beyond 15 is refused, naming the key."""
    (tmp_path / "acme_lx200.eds").write_text(Path(STATION.with_name("acme_lx200.eds")).read_text())
    text = STATION.read_text().replace("[controller.emcy_codes]", "[controller.device_control]\n{}\n"
                                       "[controller.emcy_codes]")
    path = tmp_path / "station.toml"
    path.write_text(text.replace("{}", 'halt_bit = "none"\nquick_stop = "None"\nlimit_bit = "none"'))
    control = load_station(path).controller.device_control
    assert (control.halt_bit, control.quick_stop, control.limit_bit) == (None, None, None)
    path.write_text(text.replace("{}", ""))
    control = load_station(path).controller.device_control
    assert (control.halt_bit, control.quick_stop, control.limit_bit) == (8, 0x0002, 11)
    for section, key in (('halt_bit = "off"', "halt_bit"), ("limit_bit = 16", "limit_bit"),
                         ('quick_stop = ""', "quick_stop")):
        path.write_text(text.replace("{}", section))
        with pytest.raises(StationConfigError, match=key):
            load_station(path)
