"""The soak benchmark's short version: a few full runs under faults, judged as `benchmarks/bench_soak.py` judges
them (no measurement lost or duplicated, no half-written parameter set, nothing commanded in a link gap)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from soak_runs import CONDITIONS, soak_run

BY_NAME = {c.name: c for c in CONDITIONS}


@pytest.mark.timeout(900)
@pytest.mark.parametrize(("condition", "seed", "link"), [
    ("modbus_drops", 1, "modbus"),  # the connection drops at the upload's first write
    ("heartbeat_gaps", 2, None),
    ("cmm_faults", 3, None),
])
def test_a_faulted_run_completes_with_nothing_lost(tmp_path, condition, seed, link):
    run = soak_run(BY_NAME[condition], seed, tmp_path / "work")
    assert run.completed, run
    assert (run.rows, run.lost, run.duplicated) == (83, 0, 0)
    assert run.live_set == "new", "the uploaded set is live, whole"
    assert run.late_commands == 0
    assert run.verify_after_max_mm is not None and run.verify_after_max_mm <= 0.05
    if link is not None:
        assert run.holds.get(link, 0) >= 1, f"the {link} fault happened and was ridden through: {run.holds}"
    if condition == "heartbeat_gaps":
        assert run.gaps >= 3, run
