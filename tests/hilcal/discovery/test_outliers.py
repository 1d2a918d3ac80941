"""Measurement outliers: a gross error among the measure rows is found by the final model's left-out residual, left
out of the fit and named; a clean recording loses no row."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilcal.discovery.search import diagnose
from hilcal.recording import read_recording
from hilcal.robot import load_robot

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "electric_hexapod"


@pytest.fixture(scope="module")
def example():
    robot = load_robot(EXAMPLE / "robot.toml")
    return robot, read_recording(EXAMPLE / "recording.csv", robot)


@pytest.mark.slow
def test_a_gross_error_is_left_out_and_the_answer_holds(example):
    robot, rec = example
    meas = rec.meas.copy()
    meas[40, 0] += 0.3
    meas[77, 2] -= 0.2
    diag = diagnose(type(rec)(rec.seq, rec.phase, rec.time_s, rec.cmd, rec.legs_mm, meas, rec.extra), robot)
    assert [e["seq"] for e in diag.excluded] == [rec.seq[40], rec.seq[77]]
    assert diag.summary[0].startswith("Measurement outlier(s) left out of the fit: seq 41")
    assert diag.to_json()["excluded_rows"][0]["left_out_mm"] == pytest.approx(0.3, rel=0.2)
    assert diag.effect == "sensor_scale"
    assert diag.parameters["leg2_sensor_scale_ppm"] == pytest.approx(62500.0, rel=0.01)
    assert diag.after is not None and diag.after.position_mm.rms < 0.005


@pytest.mark.slow
def test_a_clean_recording_loses_no_row(example):
    robot, rec = example
    diag = diagnose(rec, robot)
    assert diag.excluded == () and diag.left_out_mm is not None
    assert np.all(np.isfinite(diag.left_out_mm)) and diag.left_out_mm.size == int(np.sum(rec.phase == "measure"))
