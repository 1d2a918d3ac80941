"""The sign-off settings of a station file (limits, the CMM's identity and calibration) and the acceptance test's
definition: read, validated with the field named, round-tripped, and the test's route checked before motion."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest

from hilcal.robot import default_robot
from procedures.acceptance import AcceptanceTest, check_acceptance, make_acceptance
from procedures.certificate import signoff_settings
from procedures.plan import PlanError, estimate_plan, make_plan
from procedures.signoff import SignoffFileError, load_signoff, signoff_from_station
from procedures.station import load_station, save_station, station_from_dict
from procedures.timing import TimingSection

ROBOT = default_robot()
STATION = """
name = "bay 2"
operator = "J. Smith"
[machine]
serial = "DMS-0042"
[can]
interface = "virtual"
channel = "x"
[modbus]
host = "127.0.0.1"
[cmm]
url = "socket://127.0.0.1:1"
alignment = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
identity = "Leitz PMM-C, serial 4711"
stated_uncertainty_mm = 0.004
calibration_due = 2027-03-31
[acceptance]
max_position_mm = 0.05
rp_position_mm = 0.02
decision_rule = "simple"
"""


def test_station_sign_off_settings_read_in_full_and_alone(tmp_path: Path) -> None:
    path = tmp_path / "station.toml"
    path.write_text(STATION)
    alone = load_signoff(path)
    full = signoff_from_station(load_station(path), path)
    for s in (alone, full):
        assert (s.name, s.operator, s.machine_serial) == ("bay 2", "J. Smith", "DMS-0042")
        assert s.cmm.identity == "Leitz PMM-C, serial 4711" and s.cmm.stated_uncertainty_mm == 0.004
        assert s.cmm.calibration_due == dt.date(2027, 3, 31)
        assert s.acceptance.limits() == {"max_position_mm": 0.05, "rp_position_mm": 0.02}
        assert s.acceptance.decision_rule == "simple" and s.acceptance.needs_iso9283()
    assert load_signoff(None).acceptance.limits() == {}


def test_station_with_sign_off_settings_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "station.toml"
    path.write_text(STATION)
    station = load_station(path)
    again = tmp_path / "again.toml"
    save_station(station, again)
    assert load_station(again) == station



def _sim_station():
    """A station as `hilcal run --sim` hands it over: the simulator's CMM statement and example limits."""
    return station_from_dict({"can": {"interface": "virtual", "channel": "x"}, "modbus": {"host": "127.0.0.1"},
                              "cmm": {"url": "socket://127.0.0.1:1", "alignment": [0.0] * 6,
                                      "identity": "simulated CMM", "stated_uncertainty_mm": 0.006},
                              "acceptance": {"max_position_mm": 0.05, "rms_position_mm": 0.02}})


def test_sim_run_signs_off_with_the_simulated_station_unless_a_station_file_says_otherwise(tmp_path: Path) -> None:
    alone = signoff_settings({"sim": True, "station_path": None}, _sim_station())
    assert alone.cmm.stated_uncertainty_mm == 0.006 and alone.cmm.identity == "simulated CMM"
    assert "simulator" in alone.cmm_uncertainty_source
    assert alone.acceptance.limits() == {"max_position_mm": 0.05, "rms_position_mm": 0.02}

    strict = tmp_path / "strict.toml"  # limits of its own, no [cmm]: the simulator's statement still holds
    strict.write_text("name = \"strict bay\"\n[acceptance]\nmax_position_mm = 0.0005\n")
    settings = signoff_settings({"sim": True, "station_path": str(strict)}, _sim_station())
    assert settings.acceptance.limits() == {"max_position_mm": 0.0005} and settings.name == "strict bay"
    assert settings.cmm.stated_uncertainty_mm == 0.006 and "simulator" in settings.cmm_uncertainty_source

    full = tmp_path / "station.toml"  # the file's CMM statement wins, and the source says so
    full.write_text(STATION)
    settings = signoff_settings({"sim": True, "station_path": str(full)}, _sim_station())
    assert settings.cmm.stated_uncertainty_mm == 0.004 and settings.cmm.identity == "Leitz PMM-C, serial 4711"
    assert settings.cmm_uncertainty_source is None and settings.acceptance.decision_rule == "simple"

    timing_only = tmp_path / "timing.toml"  # a file without [acceptance] replaces the example limits with none
    timing_only.write_text("[timing]\nsettle_s = 0.0\n")
    assert signoff_settings({"sim": True, "station_path": str(timing_only)}, _sim_station()).acceptance.limits() == {}

@pytest.mark.parametrize(("text", "field"), [
    ("[acceptance]\nrp_position_mm = -1.0\n", "acceptance.rp_position_mm"),
    ("[acceptance]\nrepeatability = 0.1\n", "acceptance.repeatability"),
    ("[acceptance]\ndecision_rule = \"lenient\"\n", "acceptance.decision_rule"),
    ("[cmm]\ncalibration_due = \"soon\"\n", "cmm.calibration_due"),
    ("[machine]\nserial = \"\"\n", "machine.serial"),
])
def test_bad_sign_off_settings_name_the_field(tmp_path: Path, text: str, field: str) -> None:
    path = tmp_path / "station.toml"
    path.write_text(text)
    with pytest.raises(SignoffFileError, match=field.replace(".", r"\.")):
        load_signoff(path)


def test_acceptance_test_for_the_paper_robot() -> None:
    plan = make_plan(ROBOT, 0, n_measure=12, n_verify=4, timing=TimingSection().timing(), order="design")
    test = make_acceptance(ROBOT, plan, cycles=3)
    rows, which = test.route()
    assert rows.shape == (15, 6) and which[:5].tolist() == [0, 4, 3, 2, 1]
    assert AcceptanceTest.model_validate(test.model_dump()).sha256() == test.sha256()
    estimate = estimate_plan(plan, ROBOT, TimingSection().timing(), acceptance_poses=rows)
    phase = estimate.phase("acceptance")
    assert phase.n_poses == 15 and phase.probing_s == pytest.approx(15 * TimingSection().cmm_s_per_pose)
    assert [p.phase for p in estimate.phases][-2:] == ["acceptance", "return_home"]
    with pytest.raises(PlanError, match="cycles"):
        make_acceptance(ROBOT, plan, cycles=1)


def test_acceptance_route_outside_the_leg_limits_is_refused() -> None:
    plan = make_plan(ROBOT, 0, n_measure=12, n_verify=4, timing=TimingSection().timing(), order="design")
    test = make_acceptance(ROBOT, plan, cycles=2)
    poses = np.array(test.poses)
    poses[3, 2] = 3600.0  # P4 far above the workspace: the legs cannot reach it
    bad = test.model_copy(update={"poses": poses.tolist()})
    with pytest.raises(PlanError, match="P4"):
        check_acceptance(bad, ROBOT, plan)
