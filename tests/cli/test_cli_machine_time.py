"""Machine time on the command line: `hilcal design --max-minutes` and the estimate `hilcal run` prints before
anything moves."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from hilcal.robot import load_robot
from procedures.cli.app import app
from procedures.journal import Journal
from procedures.plan import estimate_plan, load_plan, plan_from_poses, save_plan
from procedures.timing import TimingSection
from tests.poses import feasible_random_poses

runner = CliRunner()
SMALL_ROBOT = Path(__file__).resolve().parents[2] / "examples" / "hexapod_small.toml"
TIMING_TOML = """
[timing]
leg_speed_mm_s = 10.0
leg_accel_mm_s2 = 200.0
settle_s = 0.5
cmm_s_per_pose = 20.0
move_overhead_s = 0.1
"""
TIMING = TimingSection(leg_speed_mm_s=10.0, leg_accel_mm_s2=200.0, settle_s=0.5, cmm_s_per_pose=20.0,
                       move_overhead_s=0.1)


def _design(tmp_path: Path, minutes: float, name: str) -> tuple[int, str, Path]:
    (tmp_path / "station.toml").write_text(TIMING_TOML)
    plan_path = tmp_path / name
    result = runner.invoke(app, ["design", "--robot", str(SMALL_ROBOT), "--station", str(tmp_path / "station.toml"),
                                 "--n-verify", "4", "--max-minutes", str(minutes), "--plan-out", str(plan_path)])
    return result.exit_code, result.output, plan_path


@pytest.mark.slow
def test_design_within_a_budget_writes_a_plan_that_fits(tmp_path):
    robot = load_robot(SMALL_ROBOT)
    code, output, path = _design(tmp_path, 1000.0, "full.json")
    assert code == 0, output
    assert "least-time order" in output and "design order" in output and "D-efficiency" in output
    assert "legs 10 mm/s" in output
    full = load_plan(path, robot)
    assert len(full.measure_poses) == 35 and len(full.verify_poses) == 4 and full.order == "time"
    assert re.search(r"│\s+32 │.*│ chosen │", output)  # the full plan fits
    full_min = estimate_plan(full, robot, TIMING.timing()).total_s / 60
    budget = round(0.85 * full_min, 2)
    code, output, path = _design(tmp_path, budget, "budget.json")
    assert code == 0, output
    fitted = load_plan(path, robot)
    assert 10 + 3 <= len(fitted.measure_poses) < 35
    assert estimate_plan(fitted, robot, TIMING.timing()).total_s <= 60 * budget
    # the chosen poses are a subset of the full plan's
    assert {tuple(p) for p in fitted.measure_poses} <= {tuple(p) for p in full.measure_poses}
    code, output, _ = _design(tmp_path, -1.0, "none.json")
    assert code == 2 and "must be positive" in output


def test_run_prints_the_estimate_before_any_motion(tmp_path, robot):
    rng = np.random.default_rng(4)
    plan = plan_from_poses(robot, feasible_random_poses(robot, 10, rng), feasible_random_poses(robot, 3, rng),
                           timing=TIMING.timing(), settle_s=0.5)
    save_plan(plan, tmp_path / "plan.json")
    station = tmp_path / "station.toml"
    station.write_text('[can]\ninterface = "virtual"\nchannel = "hilcal-test-nobody"\n'
                       '[modbus]\nhost = "127.0.0.1"\nport = 9\n'
                       '[cmm]\nurl = "loop://"\nalignment = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]\n'
                       '[motion]\nconnect_timeout_s = 0.2\n' + TIMING_TOML)
    result = runner.invoke(app, ["run", "--station", str(station), "--plan", str(tmp_path / "plan.json"), "--yes",
                                 "--out", str(tmp_path / "run"), "--records", str(tmp_path / "records.sqlite")])
    assert result.exit_code == 3, result.output  # the controller never answers
    output = result.output
    assert "Estimated machine time" in output and "the run did not start: cannot connect to the controller" in output
    assert output.index("Estimated machine time") < output.index("cannot connect")
    for part in ("measure", "verify after", "return home", "motion", "settle", "probing", "total"):
        assert part in output
    total = estimate_plan(plan, robot, TIMING.timing()).total_s
    assert f"Estimated machine time: {total / 60:.1f} min" in output
    assert not (tmp_path / "run").exists()  # a run that never started leaves no folder that --resume would find


def test_report_times_each_phase_from_the_journal_checkpoints(tmp_path, robot):
    from procedures.runner import machine_time_report

    rng = np.random.default_rng(5)
    plan = plan_from_poses(robot, feasible_random_poses(robot, 9, rng), feasible_random_poses(robot, 2, rng),
                           timing=TIMING.timing(), settle_s=0.5)
    with Journal(tmp_path / "journal.sqlite") as journal:
        journal.start("run-1", plan.sha256(), plan.model_dump_json(), {})
        marks = {"measure": (100.0, 400.0), "verify": (400.5, 480.0), "verify_after": (900.0, None)}
        for phase, (start, end) in marks.items():
            for key, at in (("start", start), ("end", end)):
                if at is not None:
                    step = f"checkpoint:phase_{key}:{phase}"
                    journal.set_step(step, {})
                    journal._db.execute("UPDATE steps SET time = ? WHERE key = ?", (at, step))
        section = machine_time_report(journal, plan, robot, TIMING)
        assert section["phases"]["measure"]["actual_s"] == 300.0
        assert section["phases"]["verify"]["actual_s"] == 79.5
        assert section["phases"]["verify_after"]["actual_s"] is None  # never finished
        assert section["phases"]["return_home"]["actual_s"] is None
        assert section["interrupted"] is False
        estimate = estimate_plan(plan, robot, TIMING.timing())
        assert section["estimated_s"] == estimate.total_s
        assert section["phases"]["measure"]["estimated_probing_s"] == 12 * 20.0  # 9 poses, one measured 4 times
        journal.event("interrupted", reason="test")
        assert machine_time_report(journal, plan, robot, TIMING)["interrupted"] is True
