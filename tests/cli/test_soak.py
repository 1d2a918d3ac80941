"""The soak benchmark's short version: a few full runs under faults, judged as `benchmarks/bench_soak.py` judges
them (no measurement lost or duplicated, no half-written parameter set, nothing commanded in a link gap)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from soak_runs import CONDITIONS, soak_run

BY_NAME = {c.name: c for c in CONDITIONS}
INSTANT_CMM = "[cmm]\ntime_scale = 0.0\n"
"""For disturbances counted in commands (a dropped write, a silent or garbled CMM reply): the CMM probes at once,
so the run is not spent waiting for simulated probing. Link gaps come per minute, so that run keeps its time."""


@pytest.mark.timeout(900)
@pytest.mark.parametrize(("condition", "seed", "link", "extra"), [
    ("modbus_drops", 1, "modbus", INSTANT_CMM),  # the connection drops at the upload's first write
    ("heartbeat_gaps", 2, None, ""),
    ("cmm_faults", 3, None, INSTANT_CMM),
])
def test_a_faulted_run_completes_with_nothing_lost(tmp_path, condition, seed, link, extra):
    run = soak_run(BY_NAME[condition], seed, tmp_path / "work", extra_sim_config=extra)
    assert run.completed, run
    assert (run.rows, run.lost, run.duplicated) == (83, 0, 0)
    assert run.live_set == "new", "the uploaded set is live, whole"
    assert run.late_commands == 0
    assert run.verify_after_max_mm is not None and run.verify_after_max_mm <= 0.05
    if link is not None:
        assert run.holds.get(link, 0) >= 1, f"the {link} fault happened and was ridden through: {run.holds}"
    if condition == "heartbeat_gaps":
        assert run.gaps >= 3, run
