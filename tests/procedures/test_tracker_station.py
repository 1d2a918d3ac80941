"""A station measured with a laser tracker: the [tracker] section's checks, the simulated station's file written and
read back, the real drivers opened on an in-process simulator, and the engine measuring poses with the tracker (the
journal's row, its detail keys and the link it names), its set-up refused for a reflector the tracker does not know.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from drivers.instrument import InstrumentSetupError, TrackerPoseInstrument
from procedures import messages as m
from procedures.engine import Engine, RunInterrupted
from procedures.journal import Journal
from procedures.link_guard import links_summary
from procedures.station import (
    Devices,
    StationConfigError,
    load_station,
    open_devices,
    save_station,
    station_from_channels,
    station_from_dict,
)
from sim_devices.sim_config import SimConfig, SimTrackerConfig
from sim_devices.simulator import SimHandle, start_sim

pytestmark = pytest.mark.timeout(60)

NESTS = [[900.0, 0.0, 90.0], [0.0, 900.0, 90.0], [-900.0, 0.0, 90.0], [0.0, -900.0, 90.0]]
MONUMENTS = [[2600.0, 1500.0, 100.0], [-2600.0, 1500.0, 100.0], [0.0, -3000.0, 100.0]]


@pytest.fixture(scope="module")
def sim() -> Iterator[SimHandle]:
    config = SimConfig(instrument="tracker", tracker=SimTrackerConfig(time_scale=0.0, platform_targets_mm=NESTS,
                                                                     base_monuments_mm=MONUMENTS))
    with start_sim(config) as handle:
        yield handle


@pytest.fixture
def devices(sim: SimHandle) -> Iterator[Devices]:
    with open_devices(station_from_channels(sim.channels())) as devs:
        yield devs


def tracker_station(**tracker: object) -> dict:
    section = {"host": "10.0.0.9", "alignment": [6000.0, -1500.0, 1800.0, 0.0, 0.0, 165.0],
               "environment": {"temperature_c": 21.0, "pressure_hpa": 990.0, "humidity_pct": 40.0},
               "platform_targets_mm": NESTS, "base_monuments_mm": MONUMENTS, **tracker}
    return {"can": {"interface": "virtual", "channel": "x"}, "modbus": {"host": "127.0.0.1"},
            "instrument": {"kind": "tracker"}, "tracker": section}


@pytest.mark.parametrize(("tracker", "said"), [
    ({"platform_targets_mm": NESTS[:2]}, "tracker.platform_targets_mm: at least 3 platform targets"),
    ({"base_monuments_mm": [[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [2000.0, 0.0, 5.0]]},
     "tracker.base_monuments_mm: the base monuments lie on a line"),
    ({"platform_targets_mm": [*NESTS, [905.0, 10.0, 90.0]]},
     "tracker.platform_targets_mm: platform targets 1 and 5 are 11.2 mm apart, closer than 20 mm"),
    ({"environment": {"temperature_c": 21.0, "pressure_hpa": 99.0, "humidity_pct": 40.0}},
     "tracker.environment.pressure_hpa: Input should be greater than or equal to 500"),
    ({"alignment": [1.0, 2.0]}, "tracker.alignment: must be [x, y, z, roll, pitch, yaw]"),
    ({"driver": {"port": 701}}, "give host and port in [tracker] itself"),
    ({"mpe_constant_um": 0.0}, "tracker.mpe_constant_um: Input should be greater than 0"),
])
def test_a_tracker_section_that_cannot_be_measured_with_is_refused(tracker: dict, said: str) -> None:
    with pytest.raises(StationConfigError) as caught:
        station_from_dict(tracker_station(**tracker), "station.toml")
    assert said in str(caught.value)


def test_the_simulated_station_is_written_and_read_back(sim: SimHandle, tmp_path) -> None:
    station = station_from_channels(sim.channels())
    assert station.instrument.kind == "tracker" and station.cmm is None
    tracker = station.measuring_tracker()
    np.testing.assert_array_equal(tracker.layouts()[0], NESTS)
    np.testing.assert_array_equal(tracker.layouts()[1], MONUMENTS)
    np.testing.assert_array_equal(tracker.alignment_matrix(), sim.tracker_alignment)
    assert station.instrument_address() == sim.tracker_server.address
    save_station(station, tmp_path / "station.toml")
    assert load_station(tmp_path / "station.toml") == station


def _poses(robot):
    yield m.Prompt("spheres", "ready?")
    yield m.PrepareCmm()
    yield m.Enable()
    first = yield m.Measure("measure", 0, m.as_tuple(robot.home))
    second = yield m.Measure("measure", 1, m.as_tuple(robot.home))
    yield m.Disable()
    return first, second


def test_the_engine_measures_with_the_tracker(sim: SimHandle, devices: Devices, tmp_path) -> None:
    assert isinstance(devices.instrument, TrackerPoseInstrument) and devices.cmm is None
    with Journal(tmp_path / "j.sqlite") as journal:
        first, second = Engine(devices, journal).run(_poses(devices.robot))
        truth = sim.rig.true_pose()
        for row in (first, second):
            assert np.max(np.abs(np.asarray(row["meas"])[:3] - truth[:3])) < 0.2  # tens of µm of tracker noise
            assert row["detail"]["targets"] == 7 and 0.0 < row["detail"]["sphere_fit_rms_mm"] < 0.2
        # the first pose searched as the station's tolerance says, the second on the registered alignment
        assert first["detail"]["largest_search_radius_mm"] > second["detail"]["largest_search_radius_mm"] == 5.0
        assert set(links_summary(journal)) == {"controller", "tracker", "modbus"}


def test_a_reflector_the_tracker_does_not_know_stops_the_set_up(sim: SimHandle, tmp_path) -> None:
    station = station_from_channels(sim.channels())
    station = station.model_copy(update={"tracker": station.tracker.model_copy(update={"reflector": "CCR 7/8in"})})
    with open_devices(station) as devs, Journal(tmp_path / "j.sqlite") as journal:
        with pytest.raises(RunInterrupted, match="the tracker knows no reflector 'CCR 7/8in'") as caught:
            Engine(devs, journal).run(_poses(devs.robot))
        assert isinstance(caught.value.__cause__, InstrumentSetupError)
        assert "1 'RRR 1.5in'" in str(caught.value)
