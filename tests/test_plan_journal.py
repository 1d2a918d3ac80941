"""Plans (hash, safety checks, motion rules) and the run journal (SQLite WAL, resume bookkeeping)."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from hilcal.kinematics import Geometry, inverse_kinematics
from procedures.journal import Journal
from procedures.plan import PlanError, check_plan, load_plan, make_plan, save_plan, waypoints


@pytest.fixture(scope="module")
def plan(robot):
    return make_plan(robot, seed=0)


def test_plan_has_32_measure_and_24_verify_poses_and_a_stable_hash(plan, robot, tmp_path):
    assert (len(plan.measure_poses), len(plan.verify_poses)) == (32, 24)
    save_plan(plan, tmp_path / "plan.json")
    again = load_plan(tmp_path / "plan.json", robot)
    assert again.sha256() == plan.sha256()
    assert again.model_copy(update={"settle_s": 1.0}).sha256() != plan.sha256()


def test_unsafe_plans_are_refused_before_any_motion(plan, robot, tmp_path):
    poses = [list(p) for p in plan.measure_poses]
    poses[3][0] = 400.0
    with pytest.raises(PlanError, match="measure pose 4 is outside the workspace in x_mm"):
        check_plan(plan.model_copy(update={"measure_poses": poses}), robot)
    # A pose at the bottom of the workspace with its legs near the lower limit: the approach point goes below.
    low = [0.0, 0.0, 2850.0, 0.0, 0.0, 0.0]
    legs = inverse_kinematics(Geometry.nominal(robot), np.array(low))
    deep = plan.model_copy(update={"verify_poses": [low], "approach_mm": float(legs.min() - robot.leg_limits[0] + 1)})
    with pytest.raises(PlanError, match="leave the leg limits"):
        check_plan(deep, robot)
    (tmp_path / "bad.json").write_text('{"robot_name": "paper-table1", "measure_poses": [[1,2,3]]}')
    with pytest.raises(PlanError, match="problem"):
        load_plan(tmp_path / "bad.json", robot)


def test_waypoints_bound_the_step_and_end_with_approach_then_target(plan, robot):
    geom = Geometry.nominal(robot)
    start, target = np.array(plan.measure_poses[0]), np.array(plan.measure_poses[1])
    legs0 = inverse_kinematics(geom, start)
    path = waypoints(geom, start, target, plan)
    assert [kind for kind, _ in path[-2:]] == ["approach", "target"]
    previous = legs0
    for _, pose in path:
        legs = inverse_kinematics(geom, pose)
        assert np.abs(legs - previous).max() <= plan.max_step_mm + 1e-6
        previous = legs


def test_journal_is_wal_and_measurements_are_unique(tmp_path):
    path = tmp_path / "journal.sqlite"
    with Journal(path) as j:
        j.start("run-1", "abc", "{}", {"sim": True})
        j.add_measurement("measure", 0, 1.0, np.zeros(6), np.ones(6), np.full(6, 2.0), {"x": 1})
        with pytest.raises(sqlite3.IntegrityError):
            j.add_measurement("measure", 0, 2.0, np.zeros(6), np.ones(6), np.zeros(6), {})
        j.set_step("upload", {"outcome": "started"})
    with Journal(path) as j:
        assert j.run_info()["run_id"] == "run-1" and j.run_info()["options"] == {"sim": True}
        rows = j.measurements(("measure",))
        assert len(rows) == 1 and rows[0]["meas"].tolist() == [2.0] * 6
        assert j.step("upload") == {"outcome": "started"}
    mode = sqlite3.connect(path).execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"
