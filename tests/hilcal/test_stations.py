"""Instrument stations fitted with the geometry (hilcal.stations, hilcal.identification): a recording from the
simulated rig whose measured poses are seen through three set-ups of the instrument, two of them off by a planted
rigid error (written here with scipy rotations, apart from hilcal). The fit finds the planted errors relative to the
first set-up and calibrates as if there had been one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.calibration import calibrate
from hilcal.planning import design
from hilcal.recording import Recording
from hilcal.robot import default_robot
from procedures.cli.simulated_recording import simulate_recording
from sim_devices.rig.config import RigConfig, load_errors
from tests.poses import default_design

ROBOT = default_robot()


def seen_through(meas: np.ndarray, dt_mm: np.ndarray, dw_rad: np.ndarray) -> np.ndarray:
    """Poses seen through a set-up off by a rigid motion: turned by dw about the workspace centre, shifted by dt."""
    c = ROBOT.home[:3]
    turn = Rotation.from_rotvec(dw_rad)
    out = meas.copy()
    out[:, :3] = turn.apply(meas[:, :3] - c) + c + dt_mm
    rotated = turn * Rotation.from_euler("ZYX", meas[:, [5, 4, 3]], degrees=True)
    out[:, 3:] = rotated.as_euler("ZYX", degrees=True)[:, ::-1]
    return out


def with_stations(seed: int, planted: dict[int, tuple[np.ndarray, np.ndarray]]) -> tuple[Recording, Recording]:
    """(the clean recording, the same seen through three interleaved set-ups, with its station column)."""
    rec = simulate_recording(ROBOT, RigConfig(seed=seed, errors=load_errors("table2"), cmm_noise_mm=0.002),
                             default_design(32, seed), design.verification_poses(ROBOT, 16, seed))
    stations = np.arange(rec.n) % 3
    meas = rec.meas.copy()
    for s, (dt, dw) in planted.items():
        meas[stations == s] = seen_through(meas[stations == s], dt, dw)
    return rec, Recording(rec.seq, rec.phase, rec.time_s, rec.cmd, rec.legs_mm, meas,
                          {**rec.extra, "station": stations.astype(float)})


PLANTED = {1: (np.array([0.3, -0.5, 0.2]), np.array([1e-4, -2e-4, 5e-5])),
           2: (np.array([-0.6, 0.1, 0.4]), np.array([-3e-4, 1e-4, 2e-4]))}


@pytest.mark.slow
def test_the_set_ups_errors_are_found_and_the_calibration_is_as_with_one() -> None:
    clean, seen = with_stations(1, PLANTED)
    one, many = calibrate(clean, ROBOT), calibrate(seen, ROBOT)
    for s, (dt, dw) in PLANTED.items():
        found = many.identification.station_frames[s]
        np.testing.assert_allclose(found[:3], dt, atol=0.01)
        np.testing.assert_allclose(found[3:], dw, atol=1e-5)
    assert many.after.position_mm.rms == pytest.approx(one.after.position_mm.rms, rel=0.3)
    ignored = calibrate(Recording(seen.seq, seen.phase, seen.time_s, seen.cmd, seen.legs_mm, seen.meas,
                                  {k: v for k, v in seen.extra.items() if k != "station"}), ROBOT)
    assert ignored.after.position_mm.rms > 20 * one.after.position_mm.rms


@pytest.mark.slow
def test_the_station_column_must_hold_station_numbers(tmp_path) -> None:
    from hilcal.recording import RecordingError, read_recording, write_recording

    _, seen = with_stations(2, {})
    path = tmp_path / "rec.csv"
    write_recording(path, seen)
    assert np.array_equal(read_recording(path, ROBOT).stations, np.arange(seen.n) % 3)
    text = path.read_text().splitlines()
    header = text[0].split(",")
    col = header.index("station")
    cells = text[3].split(",")
    cells[col] = "1.5"
    text[3] = ",".join(cells)
    path.write_text("\n".join(text) + "\n")
    with pytest.raises(RecordingError, match=r"line 4.*station.*1\.5 is not a station number"):
        read_recording(path, ROBOT)


@pytest.mark.slow
def test_the_rank_report_counts_what_the_stations_take() -> None:
    """Three interleaved stations of 10-11 poses: their frames take six equations each and leave the geometry's
    rank; the report says how many stations it counted."""
    from hilcal.identifiability import format_report, identifiability

    _, seen = with_stations(3, PLANTED)
    mea = seen.select("measure")
    alone = identifiability(ROBOT, mea.meas)
    bundled = identifiability(ROBOT, mea.meas, stations=mea.stations)
    assert bundled.n_stations == 3 and alone.n_stations == 1
    assert bundled.rank == alone.rank  # 10-11 poses per station: the frames take their own six each, nothing more
    assert "3 instrument stations" in format_report(bundled) and "stations" not in format_report(alone)
