"""The core issue's must-show: Table 2 errors, 0.005 mm CMM noise, 32 D-optimal + 24 verification poses.

The calibrated max verification position error must be close to what the rig's *true* parameters give
under the same noise (the noise floor); raw (uncalibrated) error is millimetres.
"""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.calibration import calibrate
from hilcal.kinematics import Geometry, forward_kinematics
from hilcal.metrics import AccuracySummary
from hilcal.planning import design
from hilcal.recording import write_recording
from procedures.cli.simulated_recording import simulate_recording
from sim_devices.rig.config import RigConfig, load_errors
from tests.poses import default_design


@pytest.fixture(scope="module")
def plan(robot):
    return default_design(32, 0)


def _ratios(robot, plan, seed: int) -> tuple[float, float, float]:
    errors = load_errors("table2", robot)
    rec = simulate_recording(robot, RigConfig(seed=seed, errors=errors, cmm_noise_mm=0.005), plan,
                             design.verification_poses(robot, 24, seed))
    ver = rec.select("verify")
    truth = Geometry.nominal(robot).perturbed(errors.to_vector())
    floor = AccuracySummary.of(ver.meas, forward_kinematics(truth, ver.legs_mm, ver.meas)).position_mm.max
    ls = calibrate(rec, robot, estimator="ls")
    linf = calibrate(rec, robot, estimator="linf")
    return ls.before.position_mm.max, ls.after.position_mm.max / floor, linf.after.position_mm.max / floor


def test_demo_seed_reaches_the_noise_floor(robot, plan):
    raw, ls_ratio, linf_ratio = _ratios(robot, plan, seed=0)
    assert raw > 1.5
    assert ls_ratio <= 1.2
    assert linf_ratio <= 1.2


def test_over_seeds_least_squares_is_at_the_floor_and_linf_close(robot, plan):
    ratios = np.array([_ratios(robot, plan, seed)[1:] for seed in range(1, 6)])
    assert np.median(ratios[:, 0]) <= 1.2
    # L-infinity is a less efficient estimator under Gaussian noise (see docs/paper_study.md).
    assert np.median(ratios[:, 1]) <= 1.35


def test_simulated_recording_is_deterministic(robot, plan, tmp_path):
    errors = load_errors("table2", robot)
    verify = design.verification_poses(robot, 24, 4)
    for name in ("a.csv", "b.csv"):
        rec = simulate_recording(robot, RigConfig(seed=4, errors=errors), plan, verify)
        write_recording(tmp_path / name, rec)
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "b.csv").read_text()
