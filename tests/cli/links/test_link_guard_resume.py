"""Link drop-outs in a full `hilcal run --sim` run: a gap longer than the grace period ends the run cleanly, nothing
is commanded once the host can know the link is down, and the printed resume command works when pasted (the
simulator restarts on the run's state file and goes on counting its gaps)."""

from __future__ import annotations

import shlex

import pytest

from tests.cli.links.link_support import gap_log, journal_rows, late_commands, run_hilcal, sim_config
from tests.cli.sim_speed import plan_rows

pytestmark = pytest.mark.slow


@pytest.mark.timeout(900)
def test_a_long_gap_ends_the_run_and_the_printed_command_resumes_it(tmp_path, small_plan):
    out = tmp_path / "run folder with spaces"
    config = sim_config(tmp_path, gap_at_frames=[150], gap_min_s=1.6, gap_max_s=1.8, max_gaps=1)
    stopped = run_hilcal(["--sim", "--sim-config", str(config), "--plan", str(small_plan), "--out", str(out)],
                         tmp_path)
    assert stopped.returncode == 3, stopped.stdout + stopped.stderr
    assert "controller link lost" in stopped.stderr and "grace period" in stopped.stderr
    gaps, received = gap_log(tmp_path)
    assert len(gaps) == 1 and not late_commands(received), received
    assert journal_rows(out, "SELECT COUNT(*) FROM events WHERE kind = 'link_lost'") == [(1,)]
    measured = journal_rows(out, "SELECT COUNT(*) FROM measurements")[0][0]
    assert 0 < measured < plan_rows(small_plan)[0]

    command = stopped.stderr.split("continue with: ", 1)[1].strip().splitlines()[0]
    argv = shlex.split(command)
    assert argv[:3] == ["hilcal", "run", "--resume"] and argv[argv.index("--out") + 1] == str(out)
    resumed = run_hilcal(argv[2:], tmp_path)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    rows = journal_rows(out, "SELECT phase, pose_index FROM measurements")
    assert len(rows) == len(set(rows)) == sum(plan_rows(small_plan))
    assert gap_log(tmp_path)[0] == gaps, "max_gaps counts across the simulator's restart"
