"""The CMM driver end to end against the simulated CMM (I++ DME 1.4.3) over TCP on 127.0.0.1 and over a pty:
accuracy with a ball stylus, the session, the tool, an AbortE recovery, an emergency stop, injected faults, and every
line of a measured pose checked by the NIST-mirroring validators (``tests.conformance.nist_grammar``).

True sphere centres come from the rig (``rig.to_cmm`` of the robot file's layout, ``rig.true_pose()`` with scipy
rotations), independently of the driver and the simulator. The simulator's touch settings are its defaults (Approach,
Search and Retract 10 mm, Min 0.5, Max 50); its noise is 1 µm per coordinate unless a test says otherwise, so that
5 µm is five standard deviations per axis.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from structlog.testing import capture_logs

from drivers.cmm.ippdme import IppDmeCmm, IppDmeConfig
from drivers.cmm.transcript import TranscriptMemory
from drivers.cmm.types import (
    CmmEmergencyStop,
    CmmInErrorState,
    CmmMotionTimeout,
    ProbeStatus,
    SphereMeasurementError,
)
from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig, Fault, ToolConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from tests.conformance.nist_grammar import check_command_line, check_response_line

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
R = ROBOT.sphere_radius_mm
UP = np.array([0.0, 0.0, 1.0])
QUICK = IppDmeConfig(ack_timeout_s=1.0, query_timeout_s=2.0, motion_timeout_s=5.0, abort_timeout_s=2.0)
COMMANDED = np.array([120.0, -80.0, 3150.0, 2.0, -3.0, 5.0])


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    rig = SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))
    rig.move_to_lengths(rig.controller_ik(COMMANDED))
    return rig


def true_centres(rig: SimulatedRig) -> tuple[np.ndarray, np.ndarray]:
    """(platform (3, 3), base (3, 3)) true sphere centres in the CMM frame."""
    pose = rig.true_pose()
    platform = Rotation.from_euler("xyz", pose[3:], degrees=True).apply(ROBOT.platform_spheres) + pose[:3]
    return rig.to_cmm(platform), rig.to_cmm(ROBOT.base_spheres)


def alignment(rig: SimulatedRig, shift_mm: tuple[float, ...] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """T_cmm<-base from the rig's CMM placement (p_base = R p_cmm + t), shifted."""
    c = rig.config.cmm_pose.as_array()
    Rb = Rotation.from_euler("xyz", c[3:], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = Rb.T
    T[:3, 3] = -Rb.T @ c[:3] + np.asarray(shift_mm)
    return T


@contextmanager
def simulated(rig: SimulatedRig, transport: str = "tcp", *, config: IppDmeConfig = QUICK, tool: str | None = None,
              **server: object) -> Iterator[tuple[CmmServerHandle, IppDmeCmm, TranscriptMemory]]:
    """The simulated CMM and the driver on it, session started and homed."""
    settings = {"seed": 11, "time_scale": 0.0, "noise_sigma_mm": 0.001, "tcp_port": 0, **server}
    handle = start_cmm_server(ROBOT, rig, CmmServerConfig(**settings))
    transcript = TranscriptMemory()
    cmm = IppDmeCmm(handle.socket_url if transport == "tcp" else handle.path, config, transcript=transcript, tool=tool)
    try:
        cmm.start_session()
        cmm.home()
        yield handle, cmm, transcript
    finally:
        cmm.close()
        handle.close()


def sent(transcript: TranscriptMemory, method: str) -> list[str]:
    return [line for line in transcript.sent() if line[6:].startswith(method + "(")]


# ---------------------------------------------------------------------- accuracy with a ball stylus


@pytest.mark.parametrize(("transport", "ball_mm"), [("tcp", 1.5), ("pty", 1.5), ("tcp", 2.5), ("pty", 2.5)])
def test_the_spheres_are_measured_within_5_um_with_a_ball_stylus(rig: SimulatedRig, transport: str,
                                                                 ball_mm: float) -> None:
    with simulated(rig, transport, tools=(ToolConfig(name="Probe1", ball_radius_mm=ball_mm),)) as (server, cmm, _):
        assert cmm.stylus_radius_mm == ball_mm and (cmm.touch.approach_mm, cmm.touch.search_mm) == (10.0, 10.0)
        result = cmm.measure_pose(ROBOT, alignment(rig, (1.5, -1.0, 0.8)), COMMANDED)
        assert server.collisions == 0
    platform, base = true_centres(rig)
    for m, truth in zip((*result.base, *result.platform), (*base, *platform), strict=True):
        assert np.linalg.norm(m.centre_mm - truth) < 0.005
        assert m.stylus_radius_mm == ball_mm and abs(m.radius_free_mm - R) < 0.01
        # PtMeas reports the ball's centre: every used point is R + r from the true centre, within the noise
        assert np.all(np.abs(np.linalg.norm(m.points_mm - truth, axis=1) - (R + ball_mm)) < 0.006)
    assert np.max(np.abs(result.pose[:3] - rig.true_pose()[:3])) < 0.005


def test_every_line_of_a_measured_pose_passes_nists_validators(rig: SimulatedRig) -> None:
    with simulated(rig, "tcp") as (_, cmm, transcript):
        cmm.measure_pose(ROBOT, alignment(rig, (1.0, 1.0, -1.0)), COMMANDED)
    assert len(transcript.sent()) > 100
    assert {line: check_command_line(line) for line in transcript.sent() if check_command_line(line)} == {}
    assert {line: check_response_line(line) for line in transcript.received() if check_response_line(line)} == {}


# ---------------------------------------------------------------------- session, homing, tool


def test_a_second_session_and_a_second_client_home_only_once(rig: SimulatedRig) -> None:
    with simulated(rig, "tcp") as (server, cmm, transcript):
        assert len(sent(transcript, "Home")) == 1
        cmm.start_session()  # 0008: ClearAllErrors, EndSession, StartSession (6.3.1)
        cmm.home()
        assert [line[6:] for line in transcript.sent() if "Session" in line] == [
            "StartSession()", "StartSession()", "EndSession()", "StartSession()"]
        assert any("! Error(3, 0008" in line for line in transcript.received())
        assert len(sent(transcript, "Home")) == 1  # IsHomed answered 1
        again = TranscriptMemory()
        with IppDmeCmm(server.path, QUICK, transcript=again) as other:
            other.start_session()
            other.home()
            other.end_session()
        assert not sent(again, "Home") and sent(again, "IsHomed")


def test_the_station_tool_is_activated_and_its_radius_read(rig: SimulatedRig) -> None:
    tools = (ToolConfig(name="Probe1", ball_radius_mm=1.5), ToolConfig(name="Probe2", ball_radius_mm=2.5))
    with simulated(rig, "pty", tool="Probe2", tools=tools) as (_, cmm, transcript):
        assert sent(transcript, "ChangeTool") and sent(transcript, "ChangeTool")[0].endswith('ChangeTool("Probe2")')
        assert cmm.active_tool == "Probe2" and cmm.stylus_radius_mm == 2.5
        _, base = true_centres(rig)
        m = cmm.measure_sphere(base[0] + np.array([0.3, -0.2, 0.1]), R)
        assert np.linalg.norm(m.centre_mm - base[0]) < 0.005 and abs(m.radius_free_mm - R) < 0.01


def test_a_clamped_touch_setting_is_read_back_and_planned_with(rig: SimulatedRig) -> None:
    with simulated(rig, "tcp") as (_, cmm, transcript):
        cmm.limits.clear()  # as if the server had not stated its Max: the request goes out and is clamped
        with capture_logs() as logs:
            got = cmm.set_touch(80.0, 80.0)
        assert (got.approach_mm, got.search_mm, got.retract_mm) == (50.0, 50.0, 50.0)
        assert any("! Error(1, 0504" in line for line in transcript.received())
        assert [e["code"] for e in logs if e["event"] == "cmm.warning"] == [504]
        _, base = true_centres(rig)  # the clamped stroke still finds a sphere 30 mm off
        m = cmm.measure_sphere(base[1] + np.array([0.0, 30.0, 0.0]), R, bound_mm=35.0)
        assert m.search is not None and np.linalg.norm(m.centre_mm - base[1]) < 0.005


# ---------------------------------------------------------------------- AbortE, emergency stop (6.3.1.5, 6.2.4)


def test_a_timed_out_touch_is_aborted_never_sent_again_and_the_position_is_known(rig: SimulatedRig) -> None:
    """The probing stroke at 10 mm/s takes ~2 s in real time: the driver waits 0.3 s, then AbortE, ClearAllErrors,
    the error status and the position; the touch was sent once."""
    config = QUICK.model_copy(update={"motion_timeout_s": 0.3})
    _, base = true_centres(rig)
    start = base[2] + (R + 1.5 + 60.0) * UP  # 60 mm clear of the sphere: the 10 + 10 mm stroke cannot reach it
    with simulated(rig, "tcp", config=config, time_scale=1.0, home_time_s=0.0,
                   home_position_mm=tuple(start)) as (server, cmm, transcript):
        with pytest.raises(CmmMotionTimeout) as err:
            cmm.probe(start, UP)
        np.testing.assert_allclose(err.value.position_mm, server.machine.position_mm, atol=1e-6)
        assert err.value.error_status is False and np.allclose(cmm.position_mm, err.value.position_mm)
    (touch,) = sent(transcript, "PtMeas")
    lines = transcript.sent()
    after = [line[6:] for line in lines[lines.index(touch) + 1:]]
    assert after[:5] == ["AbortE()", "ClearAllErrors()", "GetErrStatusE()", "GetXtdErrStatus()", "Get(X(), Y(), Z())"]
    assert lines[lines.index(touch) + 1].startswith("E")  # AbortE on the fast queue
    assert any(line.startswith(f"{touch[:5]} ! Error(2, 0006") for line in transcript.received())


def test_an_emergency_stop_mid_pose_stops_the_measurement_until_released_and_cleared(rig: SimulatedRig) -> None:
    _, base = true_centres(rig)
    near = tuple(base[0] + 100.0 * UP)
    with simulated(rig, "pty", time_scale=1.0, home_time_s=0.0, home_position_mm=near) as (server, cmm, transcript):
        threading.Timer(0.4, server.emergency_stop).start()
        t0 = time.monotonic()
        with pytest.raises(CmmEmergencyStop) as err:
            cmm.measure_pose(ROBOT, alignment(rig), COMMANDED)
        assert err.value.code == 500 and time.monotonic() - t0 < 3.0
        moves = len(sent(transcript, "GoTo")) + len(sent(transcript, "PtMeas"))
        with pytest.raises(CmmInErrorState):
            cmm.goto(cmm.where() if cmm.position_mm is not None else np.zeros(3))
        assert len(sent(transcript, "GoTo")) + len(sent(transcript, "PtMeas")) == moves  # nothing sent
        server.release_emergency_stop()
        cmm.clear_errors()
        here = cmm.where()
        cmm.goto(here + 5.0 * UP)
        assert np.allclose(server.machine.position_mm, here + 5.0 * UP)


# ---------------------------------------------------------------------- injected faults


@pytest.fixture(scope="module")
def faulty(rig: SimulatedRig) -> Iterator[tuple[CmmServerHandle, IppDmeCmm, TranscriptMemory]]:
    config = QUICK.model_copy(update={"ack_timeout_s": 0.3, "query_timeout_s": 0.3, "motion_timeout_s": 0.3})
    with simulated(rig, "pty", config=config) as handles:
        yield handles


@pytest.fixture
def cmm(faulty: tuple[CmmServerHandle, IppDmeCmm, TranscriptMemory]) -> Iterator[IppDmeCmm]:
    server, driver, transcript = faulty
    yield driver
    server.faults.clear()
    server.faults.set_rates({})
    transcript.lines.clear()
    if driver.link.error_state is not None:
        driver.clear_errors()


def test_garbage_lines_are_logged_and_skipped(cmm: IppDmeCmm, faulty, rig: SimulatedRig) -> None:
    server = faulty[0]
    _, base = true_centres(rig)
    server.faults.inject(Fault.GARBAGE, count=3, command="PtMeas")
    with capture_logs() as logs:
        m = cmm.measure_sphere(base[1], R)
    assert server.faults.applied[Fault.GARBAGE] == 3
    assert len([e for e in logs if e["event"] == "cmm.malformed_line"]) >= 3
    assert not m.rejected and np.linalg.norm(m.centre_mm - base[1]) < 0.005


def test_a_cut_touch_report_is_a_motion_timeout_with_the_position_known(cmm: IppDmeCmm, faulty,
                                                                         rig: SimulatedRig) -> None:
    server, _, transcript = faulty
    _, base = true_centres(rig)
    server.faults.inject(Fault.PARTIAL, command="PtMeas")
    with pytest.raises(CmmMotionTimeout) as err:
        cmm.measure_sphere(base[1], R)
    (touch,) = sent(transcript, "PtMeas")
    assert err.value.position_mm is not None and np.allclose(err.value.position_mm, server.machine.position_mm)
    cut = [line for line in transcript.received() if line.startswith(touch[:5] + " #")]
    assert len(cut) == 1 and not cut[0].endswith(")")  # the cut report is in the transcript as it came
    m = cmm.measure_sphere(base[1], R)  # measured again from where the ball is: a new measurement, not a resend
    assert np.linalg.norm(m.centre_mm - base[1]) < 0.005


def test_a_silent_query_is_asked_again_and_a_silent_motion_is_aborted(cmm: IppDmeCmm, faulty) -> None:
    server, _, transcript = faulty
    server.faults.inject(Fault.SILENCE, command="Get")
    cmm.position_mm = None
    here = cmm.where()
    gets = sent(transcript, "Get")
    assert len(gets) == 2 and gets[0][:5] != gets[1][:5]
    server.faults.inject(Fault.SILENCE, command="GoTo")
    with pytest.raises(CmmMotionTimeout) as err:
        cmm.goto(here + 10.0 * UP)
    assert len(sent(transcript, "GoTo")) == 1 and np.allclose(err.value.position_mm, here)


def test_a_miss_is_cleared_located_and_touched_again(cmm: IppDmeCmm, faulty, rig: SimulatedRig) -> None:
    server, _, transcript = faulty
    _, base = true_centres(rig)
    server.faults.inject(Fault.MISS, count=2)
    m = cmm.measure_sphere(base[2], R)
    misses = [p for p in m.probes if p.status is ProbeStatus.MISS]
    assert len(misses) == 2 and len(m.points_mm) == 7
    assert np.linalg.norm(m.centre_mm - base[2]) < 0.005
    lines = [line[6:] for line in transcript.sent()]
    k = next(i for i, line in enumerate(lines) if line.startswith("ClearAllErrors"))
    assert lines[k + 1:k + 3] == ["GetErrStatusE()", "Get(X(), Y(), Z())"]  # 1006: no position defined, asked


def test_an_outlier_is_rejected_and_touched_again(cmm: IppDmeCmm, faulty, rig: SimulatedRig) -> None:
    server = faulty[0]
    _, base = true_centres(rig)
    server.faults.inject(Fault.OUTLIER)
    m = cmm.measure_sphere(base[0], R)
    (bad,) = m.rejected
    assert bad.status is ProbeStatus.OUTLIER
    assert np.linalg.norm(bad.point_mm - base[0]) - (R + cmm.stylus()) == pytest.approx(0.5, abs=0.01)
    assert len(m.points_mm) == 7 and np.linalg.norm(m.centre_mm - base[0]) < 0.005


def test_a_sphere_that_is_not_there_is_searched_for_then_a_clear_error(cmm: IppDmeCmm, faulty,
                                                                         rig: SimulatedRig) -> None:
    """Every touch misses (nothing within 90 mm of the prediction): the pattern, then descents on widening lattices
    down to 90 mm, each continued down the corridor its miss swept clear; no collision."""
    server = faulty[0]
    _, base = true_centres(rig)
    before = cmm.touches
    with pytest.raises(SphereMeasurementError, match=r"not found within 90\.0 mm") as err:
        cmm.measure_sphere(base[2] + np.array([400.0, 0.0, 0.0]), R)
    descents = int(str(err.value).split("(")[-1].split(" ")[0])
    assert cmm.touches - before > descents > 50 and server.collisions == 0


def test_every_touch_displaced_fails_the_radius_check(cmm: IppDmeCmm, faulty, rig: SimulatedRig) -> None:
    server = faulty[0]
    _, base = true_centres(rig)
    server.faults.set_rates({"outlier": 1.0})
    with pytest.raises(SphereMeasurementError, match=r"radius|consistent|threshold"):
        cmm.measure_sphere(base[0], R)
