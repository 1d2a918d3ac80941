"""Plans (hash, safety checks, motion rules) and the run journal (SQLite WAL, resume bookkeeping)."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from hilcal.kinematics import Geometry, inverse_kinematics
from procedures.journal import Journal
from procedures.plan import (
    CalibrationPlan,
    PlanError,
    check_plan,
    distinct_measure_poses,
    estimate_plan,
    load_plan,
    make_plan,
    plan_from_poses,
    save_plan,
    waypoints,
)
from procedures.timing import TimingSection

TIMING = TimingSection().timing()


@pytest.fixture(scope="module")
def design_plan(robot):
    return make_plan(robot, seed=0, timing=TIMING, order="design")


@pytest.fixture(scope="module")
def plan(robot, design_plan):
    return plan_from_poses(robot, distinct_measure_poses(design_plan)[0], design_plan.poses("verify"),
                           timing=TIMING, seed=0, settle_s=design_plan.settle_s, order="time")


def _runs(rows: np.ndarray) -> list[int]:
    """Lengths of the runs of equal consecutive rows."""
    change = np.flatnonzero(np.concatenate([[True], np.any(rows[1:] != rows[:-1], axis=1), [True]]))
    return np.diff(change).tolist()


def test_plan_has_32_measure_poses_one_measured_4_times_and_24_verify_poses(plan, design_plan, robot, tmp_path):
    for p in (plan, design_plan):
        rows = p.poses("measure")
        assert (len(rows), len(np.unique(rows, axis=0)), len(p.verify_poses)) == (35, 32, 24)
        assert sorted(_runs(rows)) == [1] * 31 + [4]
    assert plan.order == "time" and design_plan.order == "design"
    # the least-time plan is a reordering of the design-order plan's rows
    for phase in ("measure", "verify"):
        a, b = plan.poses(phase), design_plan.poses(phase)
        assert np.array_equal(a[np.lexsort(a.T)], b[np.lexsort(b.T)])
    assert plan.settle_s == TIMING.settle_s == design_plan.settle_s
    save_plan(plan, tmp_path / "plan.json")
    again = load_plan(tmp_path / "plan.json", robot)
    assert again.sha256() == plan.sha256()
    assert again.model_copy(update={"settle_s": 1.0}).sha256() != plan.sha256()


def test_least_time_order_halves_motion_on_the_default_plan(plan, design_plan, robot):
    ordered, design = estimate_plan(plan, robot, TIMING), estimate_plan(design_plan, robot, TIMING)
    assert ordered.motion_s <= 0.55 * design.motion_s
    assert ordered.settle_s == design.settle_s and ordered.probing_s == design.probing_s
    assert ordered.phase("measure").n_poses == 35 and ordered.phase("verify_after").n_poses == 24


def test_a_repeat_leaves_the_pose_and_comes_back_extending(plan, robot):
    geom = Geometry.nominal(robot)
    pose = np.array(plan.measure_poses[0])
    assert [kind for kind, _ in waypoints(geom, pose, pose, plan)] == ["retreat", "approach", "target"]
    with pytest.raises(ValueError, match="at least 3"):
        CalibrationPlan.model_validate({**plan.model_dump(), "repeat_retreat_mm": 5.0})
    # a repeated pose whose legs are too short for the retreat is refused before any motion
    rows = plan.poses("measure")
    margins = inverse_kinematics(geom, rows).min(axis=1) - robot.leg_limits[0]
    k = int(np.argmin(margins))
    low = np.insert(rows, k + 1, rows[k], axis=0)
    with pytest.raises(PlanError, match="repeat retreat"):
        check_plan(plan.model_copy(update={"measure_poses": low.tolist()}), robot)


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
