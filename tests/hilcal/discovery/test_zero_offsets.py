"""A leg zero set wrong (homing offset, a logger's zero) is named as a set-up fault with its size; a measurement
frame placed elsewhere (a small rigid motion of all joints, as the identification sees it) is not a zero error."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from hilcal.discovery.findings import zero_offsets
from hilcal.discovery.search import diagnose
from hilcal.kinematics import Geometry
from hilcal.recording import read_recording
from hilcal.robot import load_robot

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "electric_hexapod"


@pytest.mark.slow
def test_a_leg_reading_2_mm_long_is_named():
    robot = load_robot(EXAMPLE / "robot.toml")
    rec = read_recording(EXAMPLE / "recording.csv", robot)
    legs = rec.legs_mm.copy()
    legs[:, 2] += 2.0
    diag = diagnose(dataclasses.replace(rec, legs_mm=legs), robot)
    assert diag.zero_offsets_mm is not None and diag.zero_offsets_mm[2] == pytest.approx(2.0, abs=0.2)
    said = next(s for s in diag.summary if s.startswith("Set-up fault (leg zero)"))
    assert "leg 3 1.9" in said or "leg 3 2.0" in said
    assert "mm long at every length" in said and "leg 1 " not in said


def test_rigidly_moved_joint_frames_are_no_zero_error():
    robot = load_robot(EXAMPLE / "robot.toml")
    rng = np.random.default_rng(5)
    c, s = np.cos(1e-4), np.sin(1e-4)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = Geometry(robot.a @ R.T + rng.normal(size=3) * 0.1, robot.b @ R + rng.normal(size=3) * 0.5, np.zeros(6))
    np.testing.assert_allclose(zero_offsets(robot, moved), 0.0, atol=1e-3)
    moved = dataclasses.replace(moved, dl0=np.array([0.0, 0.0, -1.5, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(zero_offsets(robot, moved), [0, 0, 1.5, 0, 0, 0], atol=1e-3)
