"""An adaptive run's options, budget, start form and executed plan (procedures.adaptive), without devices."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from hilcal.robot import default_robot
from procedures.adaptive import (
    AdaptiveError,
    adaptive_budget,
    adaptive_options,
    adaptive_run,
    apply_start_plan,
    executed_plan,
    progress_line,
    start_form,
)
from procedures.journal import Journal
from procedures.panel.control import OperatorControl, PanelRequestError
from procedures.panel.live import LiveState
from procedures.plan import CalibrationPlan, check_plan, estimate_plan, make_plan
from procedures.timing import TimingSection

TIMING = TimingSection().timing()


@pytest.fixture(scope="module")
def plan() -> CalibrationPlan:
    return make_plan(default_robot(), 0, timing=TIMING)


def test_the_budget_of_the_whole_run_leaves_the_verify_phases_their_estimate(plan):
    robot = default_robot()
    fixed = estimate_plan(plan, robot, TIMING)
    rest = fixed.total_s - fixed.phase("measure").total_s
    default = adaptive_budget(plan, robot, TIMING, adaptive_options(None, None))
    assert default.total_s == pytest.approx(fixed.total_s) and default.measure_s == pytest.approx(
        fixed.phase("measure").total_s) and "fixed plan" in default.source
    given = adaptive_budget(plan, robot, TIMING, adaptive_options(0.03, 70.0))
    assert given.total_s == 4200.0 and given.measure_s == pytest.approx(4200.0 - rest)
    with pytest.raises(AdaptiveError, match=r"--max-minutes 40 does not even cover the verify phases \(4\d\.\d min"):
        adaptive_budget(plan, robot, TIMING, adaptive_options(None, 40.0))
    for bad, field in (((-1.0, None), "--target-mm"), ((None, 0.0), "--max-minutes")):
        with pytest.raises(AdaptiveError, match=field):
            adaptive_options(*bad)


def test_the_problem_is_the_plans_and_the_budgets(plan):
    run = adaptive_run(plan, default_robot(), TIMING, adaptive_options(0.03, None))
    s = run.problem.settings
    assert s.max_measure_s == run.budget.measure_s and s.target_mm == 0.03 and s.seed == plan.seed
    assert np.array_equal(run.problem.verify, plan.poses("verify"))
    reference = {tuple(p) for p in plan.poses("measure")}
    assert reference <= {tuple(p) for p in run.problem.candidates.poses}, "the fixed plan's poses are candidates"


def test_the_start_form_checks_a_choice_and_the_journal_takes_it(plan, tmp_path):
    robot = default_robot()
    shown, check = start_form(plan, robot, TIMING, {"adaptive": None}, None, True)
    assert shown["choosable"] and not shown["adaptive"] and shown["fixed_minutes"] == pytest.approx(
        estimate_plan(plan, robot, TIMING).total_s / 60)
    assert check({"adaptive": False}) == {"adaptive": False}
    assert check({"adaptive": True, "target_mm": "0.03"}) == {"adaptive": True, "target_mm": 0.03, "max_minutes": None}
    with pytest.raises(ValueError, match="does not even cover"):
        check({"adaptive": True, "max_minutes": 1.0})
    (tmp_path / "plan.json").write_text("{}")
    with Journal(tmp_path / "journal.sqlite") as journal:
        options = {"sim": True, "adaptive": None}
        journal.start("run-1", plan.sha256(), plan.model_dump_json(), options)
        assert apply_start_plan({"adaptive": False}, journal, options, tmp_path) is False
        assert apply_start_plan({"adaptive": True, "target_mm": 0.03, "max_minutes": None}, journal, options, tmp_path)
        assert journal.run_info()["options"]["adaptive"] == {"target_mm": 0.03, "max_minutes": None}
    assert (tmp_path / "reference_plan.json").exists() and not (tmp_path / "plan.json").exists()


def test_the_executed_plan_is_a_fixed_plan_that_passes_the_checks(plan):
    robot = default_robot()
    rows = np.vstack([np.repeat(plan.poses("measure")[:1], 4, axis=0), plan.poses("measure")[4:14]])
    executed = executed_plan(plan, rows.tolist(), "run-1")
    check_plan(executed, robot)
    assert executed.order == "adaptive" and executed.verify_poses == plan.verify_poses
    assert json.loads(executed.model_dump_json())["measure_poses"] == rows.tolist()
    assert executed_plan(plan, rows[:7].tolist(), "run-1") is None, "fewer than 8 rows make no plan"


def test_a_decision_on_one_terminal_line():
    prediction = {"max_mm": 0.0049, "low_mm": 0.0034, "upper_mm": 0.0077, "confidence": 0.95}
    line = progress_line({"n_rows": 16, "prediction": prediction, "target_mm": None, "stop": None,
                          "remaining_s": 26.0, "remaining_measure_s": 0.6, "after_measure_s": 25.4,
                          "forecast": {"n_rows": 1}, "next": {"mode": "compound"}})
    assert line == ("adaptive plan, 16 rows: predicted verify maximum 4.9 µm (5-95 %: 3.4 µm-7.7 µm; below 7.7 µm "
                    "with 95% confidence); next: compound pose; remaining about 26 s (1 more row, 1 s, then the "
                    "verify phases)")
    early = progress_line({"n_rows": 2, "prediction": None, "target_mm": 0.03, "stop": None, "remaining_s": None,
                           "remaining_measure_range_s": [800.0, 2000.0], "after_measure_s": 2900.0,
                           "next": {"mode": "repeat"}})
    assert "target 30.0 µm" in early
    assert "remaining between 1 h 02 min and 1 h 22 min (no noise known before the repeats)" in early


def test_the_panels_start_form_refuses_a_plan_that_cannot_run_and_keeps_one_that_can(plan):
    control = OperatorControl(LiveState(), say=lambda text: None, operator="K. Lee")
    shown, check = start_form(plan, default_robot(), TIMING, {"adaptive": None}, None, True)
    thread = threading.Thread(target=lambda: control.wait_start("Start?", shown, check))
    thread.start()
    while control.live.get("prompt") is None:
        time.sleep(0.01)
    prompt = control.live.get("prompt")
    assert prompt["detail"]["plan"]["choosable"] is True
    for bad, said in (({"adaptive": True, "max_minutes": 1.0}, "does not even cover"), ({"adaptive": "yes"}, "true or"),
                      ({"adaptive": True, "target_mm": -1}, "--target-mm")):
        with pytest.raises(PanelRequestError, match=said) as err:
            control.answer(prompt["id"], True, plan=bad)
        assert err.value.status == 400 and control.start_plan is None and thread.is_alive()
    control.answer(prompt["id"], True, plan={"adaptive": True, "target_mm": 0.02, "max_minutes": None})
    thread.join(5)
    assert control.start_plan == {"adaptive": True, "target_mm": 0.02, "max_minutes": None}
