"""The laser tracker's pose strategy (``drivers.tracker.pose``) against the simulated tracker over TCP: the pose and the
refined alignment from the monuments and nests, the ATR search radius from the prediction's bound, a search widened
after a miss, a target out of sight named, a broken beam measured again, a wrong layout refused; a tracker set up again
near its place found and counted as a new station (``drivers.tracker.station``), a still one staying one, one moved
beyond the searches stopping with what to do.

The truth is written here: a station placed by this test, four nests on a platform at a pose of this test, four
monuments on the floor; T_tracker<-base from the station's definition p_base = R p_tracker + t, R = Rz Ry Rx.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.instrument import TrackerMoved, TrackerPoseInstrument
from drivers.tracker.base import Environment
from drivers.tracker.emscon import EmsconConfig, EmsconTracker
from drivers.tracker.pose import TargetNotFound, TrackerPoseConfig, TrackerPoseError, TrackerPoser
from drivers.tracker.station import StationLog
from sim_devices.tracker.config import Station, TrackerServerConfig
from sim_devices.tracker.server import TrackerServerHandle, start_tracker_server

pytestmark = pytest.mark.timeout(60)

STATION = np.array([5500.0, -2000.0, 1700.0, 0.0, 0.0, 150.0])
NESTS = np.array([[950.0, 0.0, 80.0], [0.0, 950.0, 80.0], [-950.0, 0.0, 80.0], [0.0, -950.0, 80.0]])
MONUMENTS = np.array([[2800.0, 1600.0, 0.0], [-2800.0, 1600.0, 0.0], [0.0, -3200.0, 0.0], [-2800.0, -1600.0, 40.0]])
POSE = np.array([35.0, -20.0, 3100.0, 1.5, -2.0, 4.0])
FAST = dict(host="127.0.0.1", command_timeout_s=2.0, move_timeout_s=2.0, measure_timeout_s=2.0,
            initialize_timeout_s=2.0)


def rotation(angles_deg: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) of [roll, pitch, yaw] degrees."""
    return Rotation.from_euler("ZYX", np.asarray(angles_deg)[::-1], degrees=True).as_matrix()


def true_alignment() -> np.ndarray:
    """T_tracker<-base of the station: the inverse of p_base = R p_tracker + t."""
    R = rotation(STATION[3:])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.T, -R.T @ STATION[:3]
    return T


def shifted(T: np.ndarray, shift_mm: np.ndarray) -> np.ndarray:
    """T with the base frame's origin moved by shift_mm (base axes): a station set up that far off."""
    S = np.eye(4)
    S[:3, 3] = shift_mm
    return T @ S


def reflectors() -> np.ndarray:
    platform = NESTS @ rotation(POSE[3:]).T + POSE[:3]
    return np.vstack([platform, MONUMENTS])


@pytest.fixture
def sim() -> Iterator[TrackerServerHandle]:
    station = Station(**dict(zip(("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"), STATION, strict=True)))
    with start_tracker_server(reflectors, TrackerServerConfig(seed=3, time_scale=0.0, station=station,
                                                             noise_scale=0.0)) as handle:
        yield handle


@pytest.fixture
def tracker(sim: TrackerServerHandle) -> Iterator[EmsconTracker]:
    with EmsconTracker(EmsconConfig(port=sim.port, **FAST)) as t:
        t.initialize()
        t.setup()
        yield t


def measure(tracker: EmsconTracker, alignment: np.ndarray, tolerance: tuple[float, float], pose_sd_mm: float = 1.0,
            nests: np.ndarray = NESTS, **config: float):
    cov = np.diag([pose_sd_mm**2] * 3 + [np.radians(0.05) ** 2] * 3)
    poser = TrackerPoser(tracker, TrackerPoseConfig(**config))
    return poser.measure_pose(nests, MONUMENTS, alignment, POSE + np.array([0.8, -0.5, 0.3, 0.0, 0.01, -0.01]), cov,
                              alignment_tolerance=tolerance)


def test_the_pose_and_the_refined_alignment_are_the_truth(tracker) -> None:
    result = measure(tracker, shifted(true_alignment(), np.array([3.0, -2.0, 1.0])), (10.0, 0.2))
    np.testing.assert_allclose(result.pose, POSE, atol=1e-6)
    np.testing.assert_allclose(result.refined_alignment, true_alignment(), atol=1e-6)
    assert np.all(result.pose_fit.rms_residual_mm < 1e-6)
    assert result.extra["targets"] == 8 and result.extra["widened_searches"] == 0
    assert result.extra["remeasures"] == 0
    # each point's stated standard deviation is the MPE's half at its distance: U = 15 µm + 6 µm/m
    truth_in_tracker = reflectors() @ true_alignment()[:3, :3].T + true_alignment()[:3, 3]
    distances_m = np.linalg.norm(truth_in_tracker, axis=1) / 1000.0
    sd = np.array([t.point.std_mm[0] for t in (*result.platform, *result.base)])
    np.testing.assert_allclose(sd, (0.015 + 0.006 * distances_m) / 2.0, rtol=1e-9)


def test_the_search_radius_follows_the_prediction_bound(tracker) -> None:
    """The station's tolerance (25 mm, 0.1 deg) bounds the first monument; once it is measured only the turn is
    left (0.1 deg over the 5.6 m to the next: under 10 mm), after two nearly nothing. The platform's first nest is
    searched as wide as the pose prediction's 4 sigma."""
    result = measure(tracker, shifted(true_alignment(), np.array([12.0, -9.0, 5.0])), (25.0, 0.1), pose_sd_mm=12.0)
    first = result.base[0]
    assert first.search_radius_mm == pytest.approx(first.bound_mm) and first.bound_mm > 25.0
    assert first.offset_mm == pytest.approx(np.linalg.norm([12.0, -9.0, 5.0]), rel=0.05)
    assert 5.0 < result.base[1].search_radius_mm < np.radians(0.1) * 5600.0
    assert result.base[3].search_radius_mm == 5.0
    assert result.platform[0].search_radius_mm == pytest.approx(result.platform[0].bound_mm)
    assert result.platform[0].bound_mm == pytest.approx(4 * 12.0, rel=0.05)
    assert result.extra["widened_searches"] == 0
    assert tracker.search_params().radius_mm == pytest.approx(result.platform[-1].search_radius_mm)


def test_a_target_outside_its_bound_is_found_on_a_wider_search(tracker) -> None:
    """The station says 5 mm but is 30 mm off: the first monument is searched at 5, 10, 20 and 40 mm."""
    result = measure(tracker, shifted(true_alignment(), np.array([0.0, 30.0, 0.0])), (5.0, 0.0))
    assert result.base[0].searches == 4 and result.base[0].search_radius_mm == pytest.approx(40.0)
    assert result.extra["widened_searches"] == 3
    np.testing.assert_allclose(result.pose, POSE, atol=1e-6)


def test_a_target_out_of_sight_is_named(sim, tracker) -> None:
    nest = NESTS[1] @ rotation(POSE[3:]).T + POSE[:3]
    sim.set_obstacles([(nest + 0.25 * (STATION[:3] - nest), 150.0)])  # a column between the tracker and nest 2
    with pytest.raises(TargetNotFound, match=r"platform target 2: no reflector within 100\.0 mm") as caught:
        measure(tracker, true_alignment(), (2.0, 0.02))
    assert "line of sight" in str(caught.value)


def test_a_broken_beam_is_measured_again(sim, tracker) -> None:
    sim.faults.inject("beam_break", count=2, command="StartMeasurement")
    result = measure(tracker, true_alignment(), (2.0, 0.02))
    assert result.extra["remeasures"] == 2 and sim.faults.applied["beam_break"] == 2
    np.testing.assert_allclose(result.pose, POSE, atol=1e-6)


def test_a_layout_that_is_not_the_platforms_is_refused(tracker) -> None:
    wrong = NESTS.copy()
    wrong[2, 1] += 1.0  # the station file puts nest 3 a millimetre from where it is
    with pytest.raises(TrackerPoseError, match="platform targets do not match their layout"):
        measure(tracker, true_alignment(), (2.0, 0.02), nests=wrong)


def serve_moving(**config: float) -> TrackerServerHandle:
    """The station of this file, with noise, set up again after every pose it measured (``move_every_poses = 1``)."""
    station = Station(**dict(zip(("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"), STATION, strict=True)))
    settings = {"seed": 8, "time_scale": 0.0, "station": station, "move_every_poses": 1, **config}
    return start_tracker_server(reflectors, TrackerServerConfig(**settings), platform_reflectors=4)


def alignment_of_station(pose: np.ndarray) -> np.ndarray:
    R = rotation(pose[3:])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.T, -R.T @ pose[:3]
    return T


def test_a_tracker_set_up_again_near_its_place_is_found_and_counted() -> None:
    """After every pose the tracker moves 40 mm and turns 0.5 deg (its monuments 4.8-9.2 m away: up to 120 mm in its
    view). Each next pose starts from the previous registration, known to about 0.02 mm: the nearest monument is found
    on a widened search, the others from the alignment known again to 100 mm and 1 deg; every pose is the truth to
    the tracker's noise and every registration is a new station, by the move the simulator made."""
    cov = np.diag([0.5**2] * 3 + [np.radians(0.02) ** 2] * 3)
    with serve_moving() as sim, EmsconTracker(EmsconConfig(port=sim.port, **FAST)) as tracker:
        tracker.initialize()
        tracker.setup()
        poser = TrackerPoser(tracker)
        stations = StationLog(MONUMENTS, 15.0, 6.0)
        result = poser.measure_pose(NESTS, MONUMENTS, true_alignment(), POSE, cov, alignment_tolerance=(2.0, 0.02))
        assert stations.observe(result.refined_alignment) is None and stations.number == 1
        for n in range(2, 6):
            before = sim.station  # where the tracker stands now (it moved after the pose above)
            result = poser.measure_pose(NESTS, MONUMENTS, result.refined_alignment, POSE, cov,
                                        alignment_cov=result.refined_cov)
            np.testing.assert_allclose(result.pose[:3], POSE[:3], atol=0.2)
            np.testing.assert_allclose(result.refined_alignment[:3, 3], alignment_of_station(before)[:3, 3], atol=0.3)
            assert result.base[0].searches > 1 and all(t.searches == 1 for t in (*result.base[1:], *result.platform))
            change = stations.observe(result.refined_alignment)
            assert change is not None and change.station == stations.number == n
            assert change.moved_mm == pytest.approx(40.0, abs=0.3)
            assert change.turned_deg == pytest.approx(0.5, abs=0.005)


def test_a_still_tracker_stays_one_station() -> None:
    """40 poses from one station: the registrations scatter by the tracker's noise, far below the threshold of ten
    MPEs at the farthest monument (U = 15 µm + 6 µm/m at its 9.2 m: 70 µm, threshold 0.70 mm)."""
    cov = np.diag([0.5**2] * 3 + [np.radians(0.02) ** 2] * 3)
    with serve_moving(move_every_poses=0) as sim, EmsconTracker(EmsconConfig(port=sim.port, **FAST)) as tracker:
        tracker.initialize()
        tracker.setup()
        poser = TrackerPoser(tracker)
        stations = StationLog(MONUMENTS, 15.0, 6.0)
        result = poser.measure_pose(NESTS, MONUMENTS, true_alignment(), POSE, cov, alignment_tolerance=(2.0, 0.02))
        shifts = []
        for _ in range(40):
            previous = stations.last
            stations.observe(result.refined_alignment)
            if previous is not None:
                d = result.refined_alignment - previous
                shifts.append(np.max(np.linalg.norm(MONUMENTS @ d[:3, :3].T + d[:3, 3], axis=1)))
            result = poser.measure_pose(NESTS, MONUMENTS, result.refined_alignment, POSE, cov,
                                        alignment_cov=result.refined_cov)
    far = np.max(np.linalg.norm(MONUMENTS @ true_alignment()[:3, :3].T + true_alignment()[:3, 3], axis=1))
    threshold = 10 * (15.0 + 6.0 * far / 1000.0) / 1000.0
    assert stations.number == 1 and stations.threshold_mm(true_alignment()) == pytest.approx(threshold, rel=1e-3)
    assert 0.01 < np.mean(shifts) and max(shifts) < threshold / 3


def test_a_tracker_moved_beyond_the_searches_stops_with_what_to_do() -> None:
    """Moved 400 mm after the first pose: no monument within the widest search of where the first pose registered
    it; the instrument says the tracker was moved and how to go on."""
    with serve_moving(move_mm=400.0) as sim, EmsconTracker(EmsconConfig(port=sim.port, **FAST)) as tracker:
        instrument = TrackerPoseInstrument(tracker, sim.address, true_alignment(), (2.0, 0.02), NESTS, MONUMENTS,
                                           Environment(20.0, 1013.25, 50.0), "RRR 1.5in")
        instrument.prepare()
        first = instrument.measure_pose(None, POSE, None)
        assert first.extra["station"] == 1 and "station_change" not in first.extra
        with pytest.raises(TrackerMoved) as moved:
            instrument.measure_pose(None, POSE, None)
    said = str(moved.value)
    assert said.startswith("the tracker was moved: base monument 1 is not within 100 mm")
    assert "station 1" in said and "Set the tracker up again nearer that place" in said
    assert "[tracker] alignment" in said and "resume" in said
