"""Fixtures of the command-line tests: the default plan made once per test process, with no settle wait.

`hilcal run` designs its plan (D-optimal poses, least-time order: about 2.5 s) and waits the station's settle time
at every pose. A test whose check is not the design passes this plan with `--plan`: the same poses and order as the
default plan (robot file, seed 0, the simulated station's speeds), without the wait (the near-instant servo of
tests/cli/sim_speed.py has settled long before)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hilcal.robot import default_robot
from procedures.cli.sim_station import SIM_TIMING
from procedures.plan import make_plan, save_plan


@pytest.fixture(scope="session")
def instant_plan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("plans") / "default_plan_no_settle.json"
    save_plan(make_plan(default_robot(), 0, settle_s=0.0, timing=SIM_TIMING.timing()), path)
    return path


@pytest.fixture(scope="session")
def small_plan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 measure and 6 verify poses, no settle wait: the sign-off tests' runs, which check the certificate, not the
    calibration."""
    path = tmp_path_factory.mktemp("plans") / "small_plan.json"
    save_plan(make_plan(default_robot(), 0, n_measure=12, n_verify=6, settle_s=0.0, timing=SIM_TIMING.timing()), path)
    return path
