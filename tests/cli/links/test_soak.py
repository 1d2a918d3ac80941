"""The soak benchmark's short version: full runs under faults, judged as `benchmarks/bench_soak.py` judges them (no
measurement lost or duplicated, no half-written parameter set, nothing commanded in a link gap): a Modbus connection
dropped in the upload and a CMM that falls silent or garbles its replies here, link gaps in test_link_guard.py."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))

from soak_runs import CONDITIONS, soak_run

from tests.cli.sim_speed import INSTANT_SIM, plan_rows

BY_NAME = {c.name: c for c in CONDITIONS}


@pytest.mark.timeout(900)
@pytest.mark.parametrize(("condition", "seed", "link"), [
    ("modbus_drops", 1, "modbus"),  # the connection drops at the upload's first write
    ("cmm_faults", 3, "cmm"),
])
def test_a_faulted_run_completes_with_nothing_lost(tmp_path, small_plan, condition, seed, link):
    """The servo and the CMM work at once (tests/cli/sim_speed.py) and the plan is the small one (12 + 6 poses):
    every check counts what happened (rows, commands in a gap, holds), not how long it took."""
    run = soak_run(BY_NAME[condition], seed, tmp_path / "work", extra_sim_config=INSTANT_SIM,
                   extra_run_args=("--plan", str(small_plan)))
    assert run.completed, run
    assert (run.rows, run.lost, run.duplicated) == (sum(plan_rows(small_plan)), 0, 0)
    assert run.live_set == "new", "the uploaded set is live, whole"
    assert run.late_commands == 0
    assert run.verify_after_max_mm is not None and run.verify_after_max_mm <= 0.05
    assert run.holds.get(link, 0) >= 1, f"the {link} fault happened and was ridden through: {run.holds}"
