"""The soak benchmark's link-gap run, short: a full run with the controller's heartbeat gone for 0.05-0.5 s at random
times, judged as `benchmarks/bench_soak.py` judges it (nothing lost or duplicated, the uploaded set whole, nothing
commanded in a gap)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))

from soak_runs import CONDITIONS, soak_run

from tests.cli.sim_speed import INSTANT_SIM

GAPS_PER_MIN = 60.0
"""The near-instant run lasts seconds, not the minutes of the benchmark's: the link gaps (0.05-0.5 s of real time,
as there) come three times as often, so the run still meets several."""


@pytest.mark.timeout(900)
def test_a_run_with_link_gaps_completes_with_nothing_lost(tmp_path, instant_plan):
    """The servo and the CMM work at once (tests/cli/sim_speed.py): the checks count what happened."""
    condition = next(c for c in CONDITIONS if c.name == "heartbeat_gaps")
    run = soak_run(condition, 2, tmp_path / "work", extra_sim_config=INSTANT_SIM, gaps_per_min=GAPS_PER_MIN,
                   extra_run_args=("--plan", str(instant_plan)))
    assert run.completed, run
    assert (run.rows, run.lost, run.duplicated) == (83, 0, 0)
    assert run.live_set == "new", "the uploaded set is live, whole"
    assert run.late_commands == 0
    assert run.verify_after_max_mm is not None and run.verify_after_max_mm <= 0.05
    assert run.gaps >= 3, run
