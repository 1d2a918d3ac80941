"""Link drop-outs in a full `hilcal run --sim` run: short heartbeat gaps are ridden through and nothing is commanded
once the host can know the link is down (a long gap, and the printed resume command, in test_link_guard_resume.py).
The gaps are made by the simulated controller (it sends no frame while one lasts). This is also the soak benchmark's
link-gap condition (benchmarks/bench_soak.py) at test size: nothing lost or duplicated, the uploaded set live and whole,
nothing commanded in a gap."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.cli.links.link_support import gap_log, journal_rows, late_commands, run_hilcal, sim_config
from tests.cli.sim_speed import plan_rows

pytestmark = pytest.mark.slow


@pytest.mark.timeout(900)
def test_short_gaps_are_ridden_through(tmp_path, small_plan):
    out = tmp_path / "run"
    config = sim_config(tmp_path, gap_at_frames=[40, 150, 250, 350, 450, 550], gap_min_s=0.2, gap_max_s=0.6,
                        seed=5)
    done = run_hilcal(["--sim", "--sim-config", str(config), "--plan", str(small_plan), "--out", str(out)], tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    gaps, received = gap_log(tmp_path)
    assert len(gaps) == 6 and all(0.2 <= g["length_s"] <= 0.6 for g in gaps)
    assert not late_commands(received), late_commands(received)
    holds = journal_rows(out, "SELECT data_json FROM events WHERE kind = 'link_hold'")
    assert len(holds) >= 3, "gaps longer than the heartbeat timeout during motion must hold the run"
    report = json.loads((out / "report.json").read_text())
    controller = report["links"]["controller"]
    assert controller["holds"] == len(holds) and not controller["lost"]
    assert 0 < controller["longest_hold_s"] < 0.6, "a hold ends when the heartbeats return"
    assert "controller: " in done.stdout and "holds/retries" in done.stdout
    rows = journal_rows(out, "SELECT phase, pose_index FROM measurements")
    assert len(rows) == len(set(rows)) == sum(plan_rows(small_plan)), "every pose measured exactly once"
    assert report["verification"]["after"]["max_position_mm"] <= 0.05
    uploaded = report["compensation"]["uploaded_parameters"]
    live = json.loads((out / "sim_state.json").read_text())["banks"]["live"]
    assert np.allclose(live, np.concatenate([np.ravel(uploaded["a_mm"]), np.ravel(uploaded["b_mm"]),
                                             uploaded["l0_mm"]]), atol=1e-3), "the uploaded set is live, whole"
