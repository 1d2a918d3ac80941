"""The emScon tracker driver against the simulated tracker over TCP on 127.0.0.1: set-up, measurement against the
truth, typed errors, faults and bounded waits.

The truth is computed here: the reflectors are the robot file's sphere centres (the platform's moved by a pose this
test sets, with scipy's extrinsic rotations), seen from the station this test places (p_base = R p_tracker + t);
the noise bound is the MPE the tracker is configured with, U = 15 µm + 6 µm/m, read as k = 2 per axis.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from structlog.testing import capture_logs

from drivers.tracker.base import (
    Environment,
    MeasurementFailed,
    NoReflectorLocked,
    ReflectorNotFound,
    Refraction,
    TrackerConnectionError,
    TrackerNotInitialized,
    TrackerParameterError,
    TrackerTimeout,
)
from drivers.tracker.emscon import EmsconConfig, EmsconTracker
from hilcal.robot import default_robot
from sim_devices.tracker.config import Fault, Station, TrackerServerConfig
from sim_devices.tracker.server import TrackerServerHandle, start_tracker_server
from sim_devices.tracker.targets import rig_reflectors

pytestmark = pytest.mark.timeout(30)

ROBOT = default_robot()
STATION = [5200.0, -2400.0, 1500.0, 0.4, -0.3, 150.0]
"""x, y, z mm, roll, pitch, yaw deg: the tracker's frame in the base frame (slightly off level)."""
POSE = ROBOT.home + np.array([35.0, -20.0, 40.0, 1.5, -1.0, 2.0])


class Platform:
    """The platform's pose as the simulated tracker reads it."""

    def __init__(self, pose: np.ndarray) -> None:
        self.pose = np.asarray(pose, dtype=float)

    def true_pose(self) -> np.ndarray:
        return self.pose.copy()


def truth_in_tracker(pose: np.ndarray = POSE) -> np.ndarray:
    """(6, 3) reflector centres in the tracker's frame: platform spheres at ``pose``, then base spheres."""
    R_platform = Rotation.from_euler("xyz", pose[3:], degrees=True).as_matrix()  # extrinsic xyz = Rz Ry Rx
    points = np.vstack([ROBOT.platform_spheres @ R_platform.T + pose[:3], ROBOT.base_spheres])
    R = Rotation.from_euler("xyz", STATION[3:], degrees=True).as_matrix()
    return (points - np.array(STATION[:3])) @ R


def sigma_mm(distance_mm: float) -> float:
    """Per-axis standard deviation: half the MPE 15 µm + 6 µm/m."""
    return (15.0 + 6.0 * distance_mm / 1000.0) / 2000.0


def nist_index(t_c: float, p_hpa: float, rh_pct: float) -> float:
    """NIST's shop-floor equation for the refractive index of air (p in kPa inside)."""
    return 1.0 + 7.86e-4 * (p_hpa / 10.0) / (273.0 + t_c) - 1.5e-11 * rh_pct * (t_c**2 + 160.0)


def start(**overrides: object) -> TrackerServerHandle:
    config = TrackerServerConfig(seed=3, time_scale=0.0, station=Station(**dict(zip(
        ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"), STATION, strict=True))), **overrides)
    return start_tracker_server(rig_reflectors(ROBOT, Platform(POSE)), config)


FAST = dict(host="127.0.0.1", command_timeout_s=1.0, move_timeout_s=1.0, measure_timeout_s=1.0,
            initialize_timeout_s=1.0, connect_timeout_s=1.0)


@pytest.fixture
def server() -> Iterator[TrackerServerHandle]:
    handle = start()
    yield handle
    handle.close()


@pytest.fixture
def tracker(server: TrackerServerHandle) -> Iterator[EmsconTracker]:
    with EmsconTracker(EmsconConfig(port=server.port, **FAST)) as driver:
        driver.initialize()
        driver.setup()
        yield driver


def events(logs: list[dict], name: str) -> list[dict]:
    return [e for e in logs if e["event"] == name]


# ---------------------------------------------------------------------- set-up


def test_units_environment_refraction_reflectors(server: TrackerServerHandle) -> None:
    with EmsconTracker(EmsconConfig(port=server.port, **FAST)) as t:
        assert t.units().length.startswith("Meter")  # emScon's power-up units, before the driver sets its own
        with pytest.raises(TrackerNotInitialized, match="GoPosition"):
            t.go_position(truth_in_tracker()[0])
        t.initialize()
        t.setup(Environment(21.5, 1002.0, 40.0), reflector_id=2)
        units = t.units()
        assert [units.length, units.angle, units.temperature, units.pressure, units.humidity] == [
            "Millimeter (1)", "Degree (1)", "Celsius (0)", "HPascal (1)", "RH (0)"]
        assert t.environment() == Environment(21.5, 1002.0, 40.0)
        n = nist_index(21.5, 1002.0, 40.0)
        assert t.refraction().adm_index == pytest.approx(n, abs=1e-12)
        assert t.refraction().ifm_index == pytest.approx(n, abs=1e-12)
        t.set_refraction(Refraction(1.00027, 1.00028))
        assert t.refraction() == Refraction(1.00027, 1.00028)
        t.set_environment(Environment(20.0, 1013.25, 50.0))  # the environment sets the indices again
        assert t.refraction().adm_index == pytest.approx(nist_index(20.0, 1013.25, 50.0), abs=1e-12)
        reflectors = t.reflectors()
        assert len(reflectors) == 3 and len({r.reflector_id for r in reflectors}) == 3
        assert all(r.name and 5.0 < r.surface_offset_mm < 20.0 for r in reflectors)  # SMR radii in mm, not m
        assert t.reflector() == 2
        with pytest.raises(TrackerParameterError, match="SetReflector"):
            t.set_reflector(99)
        assert t.reflector() == 2
        with pytest.raises(TrackerParameterError, match="MeteoDataOutOfRange"):
            t.set_environment(Environment(20.0, 3000.0, 50.0))
        t.set_search_params(80.0, 2.5)
        assert (t.search_params().radius_mm, t.search_params().timeout_s) == (80.0, 2.5)


def test_measured_points_match_the_truth_within_the_mpe(tracker: EmsconTracker) -> None:
    truth = truth_in_tracker()
    z2 = []
    for k, q in enumerate(truth):
        point = tracker.measure_point(q + np.array([12.0, -9.0, 6.0]))  # where the station's plan says it is
        d = float(np.linalg.norm(q))
        s = sigma_mm(d)
        np.testing.assert_allclose(point.std_mm, s, rtol=1e-9)
        np.testing.assert_allclose(point.apriori_std_mm, s, rtol=1e-9)
        assert point.std_total_mm == pytest.approx(s * np.sqrt(3.0), rel=1e-9)
        assert np.all(np.abs(point.xyz_mm - q) < 4.5 * s), (k, point.xyz_mm - q, s)
        z2.append(np.sum(((point.xyz_mm - q) / s) ** 2))
        assert point.environment == Environment(20.0, 1013.25, 50.0)
    assert sum(z2) < 42.3, z2  # chi-square, 18 degrees of freedom: p = 0.001
    assert sum(z2) > 4.9, z2  # p = 0.001 from below: the noise is there


def test_direction_is_in_degrees(tracker: EmsconTracker) -> None:
    q = truth_in_tracker()[4]
    tracker.go_position(q)
    hz, v = tracker.direction_deg()
    assert hz == pytest.approx(np.degrees(np.arctan2(q[1], q[0])), abs=1e-9)
    assert v == pytest.approx(np.degrees(np.arccos(q[2] / np.linalg.norm(q))), abs=1e-9)


def test_a_measurement_needs_a_locked_reflector(tracker: EmsconTracker) -> None:
    q = truth_in_tracker()[3]
    tracker.go_position(q)  # pointed there, not locked
    with pytest.raises(NoReflectorLocked, match=r"StartMeasurement.*MeasurementStatusNotReady"):
        tracker.measure()
    tracker.go_position(q + np.array([0.0, 0.0, 20.0]), use_adm=True)  # locks on what it finds within 50 mm
    assert np.all(np.abs(tracker.measure().xyz_mm - q) < 4.5 * sigma_mm(float(np.linalg.norm(q))))


# ---------------------------------------------------------------------- line of sight and the beam


def test_a_reflector_out_of_the_line_of_sight_is_not_found(server: TrackerServerHandle,
                                                           tracker: EmsconTracker) -> None:
    truth = truth_in_tracker()
    R = Rotation.from_euler("xyz", STATION[3:], degrees=True).as_matrix()
    between = np.array(STATION[:3]) + R @ (0.5 * truth[0])  # halfway along the beam, in the base frame
    server.set_obstacles([(between, 200.0)])
    with pytest.raises(ReflectorNotFound, match=r"FindReflector.*no reflector found near \(-?\d+"):
        tracker.measure_point(truth[0])
    point = tracker.measure_point(truth[3])  # a base sphere the obstacle does not hide
    assert np.all(np.abs(point.xyz_mm - truth[3]) < 4.5 * sigma_mm(float(np.linalg.norm(truth[3]))))
    with pytest.raises(ReflectorNotFound):
        tracker.measure_point(truth[3] + np.array([0.0, 300.0, 0.0]))  # nothing within the 50 mm search radius


def test_a_beam_break_is_an_error_and_the_retry_measures(server: TrackerServerHandle, tracker: EmsconTracker) -> None:
    q = truth_in_tracker()[1]
    tracker.go_position(q)
    tracker.find_reflector(float(np.linalg.norm(q)))
    server.faults.inject(Fault.BEAM_BREAK, command="StartMeasurement")
    with pytest.raises(MeasurementFailed, match=r"error packet to StartMeasurement.*NoStationaryResult") as err:
        tracker.measure()
    assert err.value.unsolicited
    with pytest.raises(NoReflectorLocked):  # the break lost the lock
        tracker.measure()
    server.faults.inject(Fault.BEAM_BREAK, count=2, command="StartMeasurement")
    with capture_logs() as logs:
        point = tracker.measure_point(q)
    assert server.faults.applied[Fault.BEAM_BREAK] == 3
    assert len(events(logs, "tracker.measure_again")) == 2
    assert np.all(np.abs(point.xyz_mm - q) < 4.5 * sigma_mm(float(np.linalg.norm(q))))
    server.faults.inject(Fault.BEAM_BREAK, count=3, command="StartMeasurement")
    with pytest.raises(MeasurementFailed):  # 1 + measure_retries (2) breaks in a row: the error
        tracker.measure_point(q)


# ---------------------------------------------------------------------- bounded waits and faults


def test_a_silent_tracker_times_out_naming_the_command(server: TrackerServerHandle) -> None:
    config = EmsconConfig(port=server.port, **{**FAST, "command_timeout_s": 0.2, "move_timeout_s": 0.3},
                          max_retries=1)
    with EmsconTracker(config) as t:
        t.initialize()
        t.setup()
        server.faults.set_rates({"silence": 1.0})
        t0 = time.monotonic()
        with pytest.raises(TrackerTimeout, match=r"GetReflector.*within 0.2 s.*2 attempts") as err:
            t.reflector()
        assert time.monotonic() - t0 < 2 * 0.2 + 1.0
        assert "GetReflector" in err.value.command and err.value.attempts == 2
        t0 = time.monotonic()
        with pytest.raises(TrackerTimeout, match=r"GoPosition.*within 0.3 s"):
            t.go_position(truth_in_tracker()[0])
        assert time.monotonic() - t0 < 2 * 0.3 + 1.0
        server.faults.clear()
        assert t.reflector() == 1  # the tracker answers again: the driver connects anew
        assert t.reconnects >= 2


def test_late_cut_and_unknown_answers_and_a_dropped_link_are_survived() -> None:
    with start(delay_s=0.4) as server, EmsconTracker(
            EmsconConfig(port=server.port, **{**FAST, "measure_timeout_s": 0.3})) as t:
        t.initialize()
        t.setup()
        q = truth_in_tracker()[2]
        server.faults.inject(Fault.DELAY, command="GoPosition")  # within the 1 s timeout: simply late
        t.go_position(q)
        t.find_reflector(float(np.linalg.norm(q)))
        with capture_logs() as logs:
            server.faults.inject(Fault.GARBAGE, command="StartMeasurement")
            first = t.measure()
            server.faults.inject(Fault.PARTIAL, command="StartMeasurement")
            second = t.measure()
        assert len(events(logs, "tracker.unknown_packet_skipped")) == server.config.garbage_packets
        failed = events(logs, "tracker.transaction_failed")
        assert len(failed) == 1 and "never finished" in failed[0]["error"]
        assert t.reconnects == 1
        for point in (first, second):
            assert np.all(np.abs(point.xyz_mm - q) < 4.5 * sigma_mm(float(np.linalg.norm(q))))
        server.disconnect_clients()  # a cable pulled: the next command connects anew
        assert t.reflector() == 1 and t.reconnects == 2
        with EmsconTracker(EmsconConfig(port=server.port, **{**FAST, "command_timeout_s": 0.15})) as impatient:
            server.faults.inject(Fault.DELAY, command="GetReflector")
            with capture_logs() as logs:
                assert impatient.reflector() == 1  # asked again on a new connection: the late answer dies
            assert impatient.reconnects == 1 and len(events(logs, "tracker.transaction_failed")) == 1


def test_no_tracker_is_a_connection_error_at_once() -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with pytest.raises(TrackerConnectionError, match=f"127.0.0.1:{port}"):
        EmsconTracker(EmsconConfig(port=port, **FAST))
    assert time.monotonic() - t0 < 1.5
