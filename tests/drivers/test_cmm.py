"""The CMM driver against the simulated CMM over a real pty (and TCP): accuracy, faults and recovery.

True sphere centres are computed here from ``rig.true_pose()`` and ``rig.to_cmm`` with scipy rotations,
independently of the driver and the simulator.
"""

from __future__ import annotations

import os
import select
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from structlog.testing import capture_logs

from drivers.cmm.base import (
    CmmError,
    CmmProtocolError,
    CmmTimeout,
    ProbeMiss,
    ProbeStatus,
    ProbingConfig,
    SphereMeasurementError,
)
from drivers.cmm.serial import SerialCmm, SerialCmmConfig
from hilcal.robot import Robot, default_robot
from sim_devices.cmm.config import CmmServerConfig, Fault
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(30)

ROBOT = default_robot()
SIGMA_MM = 0.002
FAST = SerialCmmConfig(ack_timeout_s=0.25, command_timeout_s=0.25, home_timeout_s=0.5, max_retries=2)


def true_centres_cmm(robot: Robot, rig: SimulatedRig) -> tuple[np.ndarray, np.ndarray]:
    """(platform (3, 3), base (3, 3)) true sphere centres in the CMM frame."""
    pose = rig.true_pose()
    R = Rotation.from_euler("xyz", pose[3:], degrees=True).as_matrix()  # extrinsic xyz = Rz Ry Rx
    platform_base = robot.platform_spheres @ R.T + pose[:3]
    return rig.to_cmm(platform_base), rig.to_cmm(robot.base_spheres)


def alignment_from_rig(
    rig: SimulatedRig, shift_mm: tuple[float, ...] = (0.0, 0.0, 0.0), tilt_deg: float = 0.0
) -> np.ndarray:
    """T_cmm<-base from the rig's CMM placement (p_base = R p_cmm + t), optionally spoiled."""
    c = rig.config.cmm_pose.as_array()
    R = Rotation.from_euler("xyz", c[3:], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R.T @ Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    T[:3, 3] = -R.T @ c[:3] + np.asarray(shift_mm)
    return T


@pytest.fixture
def rig() -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))


@pytest.fixture
def server(rig: SimulatedRig) -> Iterator[CmmServerHandle]:
    handle = start_cmm_server(ROBOT, rig, CmmServerConfig(seed=11, time_scale=0.0, noise_sigma_mm=SIGMA_MM, tcp_port=0))
    yield handle
    handle.close()


@pytest.fixture
def cmm(server: CmmServerHandle) -> Iterator[SerialCmm]:
    driver = SerialCmm(server.path, FAST)
    driver.start_session()
    driver.home()
    yield driver
    driver.close()


def events(logs: list[dict], name: str) -> list[dict]:
    return [e for e in logs if e["event"] == name]


# ---------------------------------------------------------------------- accuracy


def test_sphere_within_noise(cmm: SerialCmm, rig: SimulatedRig) -> None:
    _, base = true_centres_cmm(ROBOT, rig)
    r = ROBOT.sphere_radius_mm
    for k, true_centre in enumerate(base):
        m = cmm.measure_sphere(true_centre + np.array([0.8, -0.5, 0.6]), r)
        # centre std ~0.7 sigma per axis for pole + 6 at 30 deg; 0.01 mm is > 5 sigma
        assert np.linalg.norm(m.centre_mm - true_centre) < 0.01, k
        assert abs(m.radius_free_mm - r) < 0.02
        assert 0.2 * SIGMA_MM < m.rms_mm < 3 * SIGMA_MM
        pts = m.points_mm
        assert len(pts) == 7 and not m.rejected
        np.testing.assert_allclose(m.residuals_mm, np.linalg.norm(pts - m.centre_mm, axis=1) - r, atol=1e-9)
        # every returned point lies on the true sphere within the probing noise
        assert np.all(np.abs(np.linalg.norm(pts - true_centre, axis=1) - r) < 6 * SIGMA_MM)
        assert all(p.residual_mm is not None for p in m.probes)


def test_platform_pose_matches_truth(cmm: SerialCmm, rig: SimulatedRig) -> None:
    commanded = np.array([120.0, -80.0, 3150.0, 2.0, -3.0, 5.0])
    rig.move_to_lengths(rig.controller_ik(commanded))
    alignment = alignment_from_rig(rig, (1.5, -1.0, 0.8), tilt_deg=0.02)
    result = cmm.measure_pose(ROBOT, alignment, commanded)
    truth = rig.true_pose()
    assert np.max(np.abs(truth[:3] - commanded[:3])) > 0.1, "the rig errors should make truth differ from command"
    assert np.max(np.abs(result.pose[:3] - truth[:3])) < 0.01
    assert np.max(np.abs(result.pose[3:] - truth[3:])) < 3e-4  # deg; 5 urad ~ 5 um over the 1 m platform
    platform, base = true_centres_cmm(ROBOT, rig)
    for m, c in zip(result.platform + result.base, np.vstack([platform, base]), strict=True):
        assert np.linalg.norm(m.centre_mm - c) < 0.01
    exact = alignment_from_rig(rig)
    np.testing.assert_allclose(result.refined_alignment[:3, :3], exact[:3, :3], atol=2e-6)
    np.testing.assert_allclose(result.refined_alignment[:3, 3], exact[:3, 3], atol=0.01)
    assert np.all(result.pose_fit.rms_residual_mm < 0.01)


def test_far_prediction_is_measured_again_around_the_fit(cmm: SerialCmm, rig: SimulatedRig) -> None:
    _, base = true_centres_cmm(ROBOT, rig)
    # 4.1 mm off, said to be within 5 mm (below 0.4 r: probed at once, no search)
    m = cmm.measure_sphere(base[0] + np.array([4.0, 0.0, -1.0]), ROBOT.sphere_radius_mm, bound_mm=5.0)
    assert m.superseded is not None and m.search is None
    assert m.superseded.offset_from_nominal_mm > 2.0
    assert len(m.superseded.probes) >= 7  # the first pass is kept, not dropped
    assert np.linalg.norm(m.nominal_centre_mm - base[0]) < 0.05
    assert np.linalg.norm(m.centre_mm - base[0]) < 0.01


def test_socket_transport(server: CmmServerHandle, rig: SimulatedRig) -> None:
    assert server.socket_url is not None
    _, base = true_centres_cmm(ROBOT, rig)
    with SerialCmm(server.socket_url, FAST) as cmm:
        cmm.start_session()
        cmm.home()
        m = cmm.measure_sphere(base[2] + np.array([0.3, 0.3, 0.3]), ROBOT.sphere_radius_mm)
        cmm.end_session()
    assert np.linalg.norm(m.centre_mm - base[2]) < 0.01


# ---------------------------------------------------------------------- protocol semantics


def test_commands_need_a_session_and_homing(server: CmmServerHandle) -> None:
    with SerialCmm(server.path, FAST) as cmm:
        with pytest.raises(CmmError) as err:
            cmm.goto(np.zeros(3))
        assert err.value.code == 508
        cmm.start_session()
        with pytest.raises(CmmError) as err:
            cmm.goto(np.zeros(3))
        assert err.value.code == 508 and "home" in err.value.text.lower()
        with pytest.raises(CmmError) as err:
            cmm.transact("Fly()")
        assert err.value.code == 501
        assert cmm.get_error_info(1006) == "Surface not found"


def test_miss_latches_the_error_state_until_cleared(cmm: SerialCmm, rig: SimulatedRig) -> None:
    _, base = true_centres_cmm(ROBOT, rig)
    far = base[0] + np.array([0.0, 0.0, 100.0])
    with pytest.raises(ProbeMiss) as miss:
        cmm.probe(far, np.array([0.0, 0.0, 1.0]))
    assert miss.value.code == 1006
    with pytest.raises(CmmError) as aborted:
        cmm.goto(far)
    assert aborted.value.code == 6
    cmm.clear_errors()
    cmm.goto(far)
    touched = cmm.probe(base[0] + [0.0, 0.0, ROBOT.sphere_radius_mm], np.array([0.0, 0.0, 1.0]))
    assert abs(touched[2] - (base[0][2] + ROBOT.sphere_radius_mm)) < 6 * SIGMA_MM


# ---------------------------------------------------------------------- injected faults


def test_garbage_lines_are_skipped(cmm: SerialCmm, server: CmmServerHandle, rig: SimulatedRig) -> None:
    _, base = true_centres_cmm(ROBOT, rig)
    server.faults.inject(Fault.GARBAGE, count=3, command="PtMeas")
    with capture_logs() as logs:
        m = cmm.measure_sphere(base[1], ROBOT.sphere_radius_mm)
    assert server.faults.applied[Fault.GARBAGE] == 3
    assert len(events(logs, "cmm.garbage_skipped")) >= 3
    assert not events(logs, "cmm.transaction_failed")
    assert not m.rejected and np.linalg.norm(m.centre_mm - base[1]) < 0.01


def test_partial_line_times_out_and_is_retried(cmm: SerialCmm, server: CmmServerHandle, rig: SimulatedRig) -> None:
    _, base = true_centres_cmm(ROBOT, rig)
    server.faults.inject(Fault.PARTIAL, command="PtMeas")
    with capture_logs() as logs:
        m = cmm.measure_sphere(base[1], ROBOT.sphere_radius_mm)
    assert server.faults.applied[Fault.PARTIAL] == 1
    failed = events(logs, "cmm.transaction_failed")  # a busy test machine may add a late acknowledgement
    assert len([f for f in failed if "partial line" in f["error"]]) == 1
    discarded = events(logs, "cmm.input_discarded")
    assert discarded and "# X(" in discarded[0]["data"]  # the cut data line is logged, not lost silently
    assert len(m.probes) == 7 and not m.rejected
    assert np.linalg.norm(m.centre_mm - base[1]) < 0.01


def test_one_silence_is_retried(cmm: SerialCmm, server: CmmServerHandle, rig: SimulatedRig) -> None:
    _, base = true_centres_cmm(ROBOT, rig)
    server.faults.inject(Fault.SILENCE, command="PtMeas")
    m = cmm.measure_sphere(base[0], ROBOT.sphere_radius_mm)
    assert server.faults.applied[Fault.SILENCE] == 1
    assert np.linalg.norm(m.centre_mm - base[0]) < 0.01


def test_persistent_silence_is_a_timeout_after_bounded_retries(cmm: SerialCmm, server: CmmServerHandle) -> None:
    server.faults.set_rates({"silence": 1.0})
    start = time.monotonic()
    with pytest.raises(CmmTimeout, match="3 attempts"):
        cmm.goto(np.array([0.0, 0.0, 10.0]))
    elapsed = time.monotonic() - start
    assert server.faults.applied[Fault.SILENCE] == 1 + FAST.max_retries
    assert 3 * FAST.ack_timeout_s <= elapsed < 3 * FAST.ack_timeout_s + 1.0
    server.faults.clear()
    cmm.goto(np.array([0.0, 0.0, 10.0]))  # the link recovers once the CMM answers again


def test_probe_miss_is_reprobed(cmm: SerialCmm, server: CmmServerHandle, rig: SimulatedRig) -> None:
    _, base = true_centres_cmm(ROBOT, rig)
    server.faults.inject(Fault.MISS, count=2)
    m = cmm.measure_sphere(base[2], ROBOT.sphere_radius_mm)
    misses = [p for p in m.probes if p.status is ProbeStatus.MISS]
    assert len(misses) == 2 and all(p.point_mm is None for p in misses)
    assert len(m.points_mm) == 7
    assert np.linalg.norm(m.centre_mm - base[2]) < 0.01


def test_persistent_misses_are_a_clear_error(cmm: SerialCmm, server: CmmServerHandle, rig: SimulatedRig) -> None:
    """A sphere that never answers is searched for on widening patterns up to max_search_mm, then given up on."""
    _, base = true_centres_cmm(ROBOT, rig)
    server.faults.set_rates({"miss": 1.0})
    before = cmm.touches
    with pytest.raises(SphereMeasurementError, match=r"not found within 90\.0 mm") as err:
        cmm.measure_sphere(base[2], ROBOT.sphere_radius_mm)
    cfg = ProbingConfig()
    made = cmm.touches - before
    assert made > 1 + cfg.n_ring + cfg.max_reprobes  # the pattern, then the search
    # the 90 mm lattice has (90 + 0.8 r)^2 / (0.8 sqrt(3) r)^2 * 2 pi / sqrt(3) ~ 126 descents; all stages < 300
    assert made < 300
    assert f"({made - 1 - cfg.n_ring - cfg.max_reprobes} descents)" in str(err.value)


def test_outlier_is_rejected_and_reprobed(cmm: SerialCmm, server: CmmServerHandle, rig: SimulatedRig) -> None:
    _, base = true_centres_cmm(ROBOT, rig)
    r = ROBOT.sphere_radius_mm
    server.faults.inject(Fault.OUTLIER)
    m = cmm.measure_sphere(base[0], r)
    assert server.faults.applied[Fault.OUTLIER] == 1
    (bad,) = m.rejected
    assert bad.status is ProbeStatus.OUTLIER
    assert np.linalg.norm(bad.point_mm - base[0]) - r == pytest.approx(0.5, abs=0.01)  # against the truth
    assert bad.residual_mm == pytest.approx(0.5, abs=0.01)
    assert not any(np.allclose(bad.point_mm, p) for p in m.points_mm)  # never used
    assert len(m.points_mm) == 7
    assert np.linalg.norm(m.centre_mm - base[0]) < 0.01


def test_all_points_off_fail_the_radius_check(cmm: SerialCmm, server: CmmServerHandle, rig: SimulatedRig) -> None:
    """Every touch displaced outwards looks like a bigger sphere: caught by the free-radius check."""
    _, base = true_centres_cmm(ROBOT, rig)
    server.faults.set_rates({"outlier": 1.0})
    with pytest.raises(SphereMeasurementError, match=r"radius|consistent|threshold"):
        cmm.measure_sphere(base[0], ROBOT.sphere_radius_mm)


# ---------------------------------------------------------------------- scripted peers (a real pty, no server)


class ScriptedPeer:
    """The far end of a real pty answering each command line with ``reply(line)``."""

    def __init__(self, reply: Callable[[bytes], bytes]) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.reply = reply
        self.lines: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
                continue
            buf += os.read(self.master, 4096)
            while b"\r\n" in buf:
                line, buf = buf.split(b"\r\n", 1)
                self.lines.append(line)
                out = self.reply(line)
                if out:
                    os.write(self.master, out)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        os.close(self.master)
        os.close(self.slave)


def test_wrong_tag_is_a_protocol_error() -> None:
    peer = ScriptedPeer(lambda line: b"00042 &\r\n00042 %\r\n")
    try:
        with SerialCmm(peer.path, FAST) as cmm, pytest.raises(CmmProtocolError, match="tag 00042"):
            cmm.start_session()
    finally:
        peer.close()


def test_stale_response_of_an_abandoned_tag_is_skipped() -> None:
    def reply(line: bytes) -> bytes:
        tag = line[:5]
        if tag == b"00001":
            return b""  # silent: the driver gives up on 00001
        return b"00001 &\r\n00001 # X(1), Y(2), Z(3)\r\n00001 %\r\n" + tag + b" &\r\n" + tag + b" %\r\n"

    peer = ScriptedPeer(reply)
    try:
        with capture_logs() as logs, SerialCmm(peer.path, FAST) as cmm:
            cmm.end_session()
        stale = events(logs, "cmm.stale_response_skipped")
        assert len(stale) == 3 and "X(1)" in stale[1]["raw"]
        assert [line[:5] for line in peer.lines] == [b"00001", b"00002"]
    finally:
        peer.close()


def test_malformed_line_for_our_tag_is_retried_then_an_error() -> None:
    peer = ScriptedPeer(lambda line: line[:5] + b" & junk\r\n")
    try:
        with SerialCmm(peer.path, FAST) as cmm, pytest.raises(CmmProtocolError, match="3 attempts"):
            cmm.home()
        assert len(peer.lines) == 3
    finally:
        peer.close()


def test_loopback_echo_is_not_mistaken_for_a_response() -> None:
    with SerialCmm("loop://", FAST) as cmm, pytest.raises(CmmProtocolError):
        cmm.start_session()


def test_server_threads_stop_on_close(rig: SimulatedRig) -> None:
    handle = start_cmm_server(ROBOT, rig, CmmServerConfig(time_scale=0.0, tcp_port=0))
    with SerialCmm(handle.socket_url, FAST) as cmm:
        cmm.start_session()
    handle.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("cmm-sim")]
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", handle.tcp_port), timeout=1.0).close()
