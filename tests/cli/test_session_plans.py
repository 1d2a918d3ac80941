"""The session's plans (tests/cli/conftest.py) are what their docstrings say: `calibration_plan` measures the default
plan's rows (`instant_plan`'s) and verifies at 8 poses of its own."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.mark.slow
def test_the_calibration_plan_measures_the_default_plans_rows_and_verifies_at_8_poses(instant_plan: Path,
                                                                                        calibration_plan: Path) -> None:
    default, calibration = (json.loads(path.read_text()) for path in (instant_plan, calibration_plan))
    assert len(default["measure_poses"]) == 35 and len(default["verify_poses"]) == 24
    assert sorted(map(tuple, calibration["measure_poses"])) == sorted(map(tuple, default["measure_poses"]))
    assert len(calibration["verify_poses"]) == 8 and calibration["settle_s"] == default["settle_s"] == 0.0
