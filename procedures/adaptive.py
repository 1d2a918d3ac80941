"""The adaptive plan in a run (`hilcal run --adaptive`): its options and budget, the problem, what it shows while it
measures, and the plan as executed.

The math is ``hilcal.planning.sequential``; this module ties it to a run. The operator's budget M bounds the whole
run's machine time: the verify phases (24 poses before and after the upload, the acceptance test if any, the way
home) are estimated on the fixed plan's route and subtracted, and what is left is the measure phase's budget. Budget
stops stay deterministic on resume because the adaptive state counts the route estimate of its rows, never the wall
clock. The fixed plan (``procedures.plan.make_plan``, or ``--plan``) gives the verify poses, the motion rules, the
seed, and its measure rows as the reference of the diagnosis' minimum (and among the candidates); the journal keeps
that plan and these options, so a resumed run rebuilds the same problem and replays its rows to the same state.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hilcal.planning.machine_time import MotionTiming, format_minutes
from hilcal.robot import Robot
from procedures.plan import (
    REPEATS,
    CalibrationPlan,
    PlanError,
    check_plan,
    estimate_plan,
    motion_rules,
    save_plan,
    timing_for,
)

STOP_LABEL = "adaptive_stop"
"""The journal checkpoint of the measure phase's stop (its reason and the rows as executed)."""
PROGRESS_LABEL = "adaptive"
"""The checkpoint after every decision: the prediction so far and the forecast (the terminal and the panel show it)."""


class AdaptiveError(ValueError):
    """Adaptive options that cannot make a run (bad values, or a budget smaller than the verify phases)."""


class AdaptiveOptions(BaseModel):
    """What the operator asks of an adaptive run (stored in the journal's options, so a resume asks the same)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    target_mm: float | None = Field(default=None, gt=0, le=10.0, description="stop once the verify maximum's 95 % "
                                    "upper bound is below this (None: when it stops improving)")
    max_minutes: float | None = Field(default=None, gt=0, le=10_000, description="the whole run's machine time "
                                      "(None: the fixed plan's estimate)")


def adaptive_options(target_mm: float | None, max_minutes: float | None) -> AdaptiveOptions:
    """Validated options; AdaptiveError naming the field otherwise."""
    try:
        return AdaptiveOptions(target_mm=target_mm, max_minutes=max_minutes)
    except ValidationError as e:
        names = {"target_mm": "--target-mm", "max_minutes": "--max-minutes"}
        raise AdaptiveError("; ".join(f"{names.get(str(err['loc'][0]), err['loc'][0])}: {err['msg']}"
                                      for err in e.errors())) from None


@dataclass(frozen=True)
class AdaptiveBudget:
    """The whole run's machine-time budget split into the measure phase's and the rest's (s, route estimates)."""

    total_s: float
    measure_s: float
    after_measure_s: float
    """The verify phases, the acceptance test and the way home, estimated on the fixed plan's route."""
    fixed_total_s: float
    fixed_measure_s: float
    fixed_measure_rows: int
    source: str

    def to_json(self) -> dict[str, Any]:
        return {"total_s": self.total_s, "measure_s": self.measure_s, "after_measure_s": self.after_measure_s,
                "fixed_total_s": self.fixed_total_s, "fixed_measure_s": self.fixed_measure_s,
                "fixed_measure_rows": self.fixed_measure_rows, "source": self.source}


def adaptive_budget(plan: CalibrationPlan, robot: Robot, timing: MotionTiming, options: AdaptiveOptions,
                    acceptance_poses: np.ndarray | None = None) -> AdaptiveBudget:
    """M minus the estimate of every phase after the measure phase; AdaptiveError if nothing is left to measure."""
    fixed = estimate_plan(plan, robot, timing, acceptance_poses=acceptance_poses)
    measure = fixed.phase("measure").total_s
    rest = fixed.total_s - measure
    if options.max_minutes is None:
        total, source = fixed.total_s, "the fixed plan's estimated machine time"
    else:
        total, source = 60.0 * options.max_minutes, "--max-minutes"
    if total - rest <= 0:
        raise AdaptiveError(f"--max-minutes {options.max_minutes:g} does not even cover the verify phases "
                            f"({format_minutes(rest)}: {len(plan.verify_poses)} poses before and after the upload"
                            f"{', the acceptance test' if acceptance_poses is not None else ''} and the way home)")
    return AdaptiveBudget(total, total - rest, rest, fixed.total_s, measure, len(plan.measure_poses), source)


@dataclass
class AdaptiveRun:
    """The problem of one adaptive run with its budget, and the choices made so far (a memo: every forecast walks
    the same future rows)."""

    options: AdaptiveOptions
    budget: AdaptiveBudget
    problem: Any
    """``hilcal.planning.sequential.AdaptiveProblem``."""
    memo: Any
    """``hilcal.planning.sequential.ChoiceMemo``."""

    def to_json(self) -> dict[str, Any]:
        s = self.problem.settings
        return {"options": self.options.model_dump(), "budget": self.budget.to_json(),
                "settings": s.model_dump(), "n_candidates": len(self.problem.candidates)}


def adaptive_run(plan: CalibrationPlan, robot: Robot, timing: MotionTiming, options: AdaptiveOptions,
                 acceptance_poses: np.ndarray | None = None) -> AdaptiveRun:
    """The run's problem: the plan's verify poses, rules, seed and reference rows; the budget left for measuring."""
    from hilcal.planning.sequential import AdaptiveSettings, ChoiceMemo, adaptive_problem

    budget = adaptive_budget(plan, robot, timing, options, acceptance_poses)
    settings = AdaptiveSettings(max_measure_s=budget.measure_s, target_mm=options.target_mm, seed=plan.seed,
                                repeats=REPEATS)
    try:
        problem = adaptive_problem(robot, plan.poses("verify"), settings, motion_rules(plan), timing_for(plan, timing),
                                   reference_measure=plan.poses("measure"))
    except ValueError as e:
        raise AdaptiveError(f"the plan's measure poses cannot be the adaptive plan's reference: {e}") from None
    return AdaptiveRun(options, budget, problem, ChoiceMemo())


def time_range_json(run: AdaptiveRun) -> dict[str, Any]:
    """Before motion: the measure phase's best case and the budget, and the whole run's range (s)."""
    from hilcal.planning.forecast import time_range

    r = time_range(run.problem)
    rest = run.budget.after_measure_s
    return {**r.to_json(), "after_measure_s": rest, "run_best_s": r.best_s + rest, "run_worst_s": r.worst_s + rest,
            "fixed_total_s": run.budget.fixed_total_s, "fixed_measure_s": run.budget.fixed_measure_s}


def _um(mm: float | None) -> str:
    return "-" if mm is None else f"{mm * 1000:.1f} µm"


def progress(run: AdaptiveRun, state: Any, decision: Any) -> dict[str, Any]:
    """What the run shows after a decision: the rows so far, the prediction, the forecast of the rest, the stop."""
    from hilcal.planning.forecast import forecast

    problem, budget = run.problem, run.budget
    target = problem.settings.target_mm
    remaining = rest_range = rest = None
    if decision.stop is None:
        if target is not None and state.noise is None:  # no noise known yet: the best case and the budget
            rest = forecast(problem, state, best_case=True, memo=run.memo)
            rest_range = [rest.remaining_s, max(problem.settings.max_measure_s - state.elapsed_s, rest.remaining_s)]
        else:
            rest = forecast(problem, state, memo=run.memo)
            remaining = rest.remaining_s
    else:
        remaining = 0.0
    p = decision.prediction
    choice = decision.next
    return {
        "n_rows": state.n_rows, "distinct": len(np.unique(state.commanded(), axis=0)) if state.n_rows else 0,
        "elapsed_s": state.elapsed_s, "measure_budget_s": problem.settings.max_measure_s,
        "after_measure_s": budget.after_measure_s, "target_mm": target, "confidence": problem.settings.confidence,
        "prediction": None if p is None else p.to_json(), "sentence": decision.sentence,
        "next": None if choice is None else {"pose": choice.pose.tolist(), "mode": choice.mode,
                                             "time_s": choice.time_s},
        "forecast": None if rest is None else rest.to_json(),
        "remaining_measure_s": remaining,
        "remaining_measure_range_s": rest_range,
        "remaining_s": None if remaining is None else remaining + budget.after_measure_s,
        "poses": state.commanded().tolist(),
        "minimum": None if state.minimum is None else state.minimum.to_json(),
        "screening": None if state.screening is None else state.screening.to_json(),
        "stop": None if decision.stop is None else decision.stop.to_json(),
    }


def progress_line(data: dict[str, Any]) -> str:
    """The payload of ``progress`` as one terminal line."""
    p = data.get("prediction")
    n = data["n_rows"]
    if p is None:
        accuracy = "no prediction yet (the parameters are not identified from these rows)"
    else:
        band = f"{_um(p['low_mm'])}-{_um(p['upper_mm'])}"
        accuracy = (f"predicted verify maximum {_um(p['max_mm'])} (5-95 %: {band}; below {_um(p['upper_mm'])} with "
                    f"{p['confidence']:.0%} confidence)")
    if data.get("target_mm") is not None:
        accuracy += f", target {_um(data['target_mm'])}"
    if data.get("stop") is not None:
        return f"adaptive plan, {n} rows: {accuracy}; stop ({data['stop']['kind']}): {data['stop']['sentence']}"
    if data.get("remaining_s") is not None:
        f = data["forecast"]
        rows = f"{f['n_rows']} more row{'s' if f['n_rows'] != 1 else ''}"
        left = (f"remaining about {format_minutes(data['remaining_s'])} ({rows}, "
                f"{format_minutes(data['remaining_measure_s'])}, then the verify phases)")
    else:
        low, high = data["remaining_measure_range_s"]
        left = (f"remaining between {format_minutes(low + data['after_measure_s'])} and "
                f"{format_minutes(high + data['after_measure_s'])} (no noise known before the repeats)")
    nxt = data.get("next") or {}
    return f"adaptive plan, {n} rows: {accuracy}; next: {nxt.get('mode', '-')} pose; {left}"


def executed_plan(plan: CalibrationPlan, rows: list[list[float]], run_id: str) -> CalibrationPlan | None:
    """The plan as the adaptive run executed it (its measure rows in order, the same verify poses and rules), which
    ``--plan`` re-runs as a fixed plan; None if too few rows were measured to make a plan."""
    if len(rows) < 8:
        return None
    return CalibrationPlan.model_validate({**plan.model_dump(), "name": f"adaptive run {run_id} as executed",
                                          "measure_poses": [list(map(float, r)) for r in rows],
                                          "order": "adaptive"})


def check_route_on(plan: CalibrationPlan, rows: np.ndarray, robot: Robot) -> None:
    """Before the verify phase: the route from the last measured row through the verify poses stays within the leg
    limits (the adaptive choice checked the measure moves only). PlanError otherwise."""
    if len(rows) < 8:
        return
    try:
        check_plan(CalibrationPlan.model_validate({**plan.model_dump(), "measure_poses": np.asarray(rows).tolist(),
                                                   "order": "adaptive"}), robot)
    except PlanError as e:
        raise PlanError(f"the adaptive plan's route to the verify poses: {e}") from None


def write_executed_plan(journal: Any, out_dir: Path, plan: CalibrationPlan, run_id: str) -> CalibrationPlan | None:
    """Once the measure phase has stopped (its journal checkpoint): plan.json, the plan as executed; else None. With
    fewer than 8 rows no plan file is written; the plan returned then serves the time estimate only."""
    stop = journal.step(f"checkpoint:{STOP_LABEL}")
    if stop is None:
        return None
    executed = executed_plan(plan, stop["poses"], run_id)
    if executed is None:
        return plan.model_copy(update={"measure_poses": stop["poses"], "order": "adaptive"})
    save_plan(executed, out_dir / "plan.json")
    return executed


def adaptive_summary(run: AdaptiveRun, result: Any, reference: CalibrationPlan, executed: CalibrationPlan
                     ) -> dict[str, Any]:
    """report.json's `adaptive` section of a finished run (``hilcal.reports.adaptive.adaptive_section``)."""
    from hilcal.metrics import AccuracySummary
    from hilcal.reports.adaptive import adaptive_section

    measured = None
    if result.after_rows:
        rows = result.after_rows
        measured = AccuracySummary.of(np.array([r["meas"] for r in rows]),
                                      np.array([r["cmd"] for r in rows])).position_mm.max
    plans = {"reference_sha256": reference.sha256(),
             "executed_sha256": None if executed is reference or len(executed.measure_poses) < 8 else
             executed.sha256()}
    physics = result.physics
    effects = None if physics is None or physics.diagnosis is None else {
        "effects": list(physics.diagnosis.effects),
        "predicted_max_mm": None if physics.predicted_with is None else physics.predicted_with.position_mm.max}
    return adaptive_section(result.adaptive, run.to_json(), measured, plans, effects)


def start_form(plan: CalibrationPlan, robot: Robot, timing: MotionTiming, options: dict[str, Any],
               acceptance_poses: np.ndarray | None, choosable: bool
               ) -> tuple[dict[str, Any], Callable[[dict[str, Any]], dict[str, Any]]]:
    """The plan on the panel's start form (a new run's can change there) and the check of a choice made there."""
    current = options.get("adaptive") or {}
    fixed = estimate_plan(plan, robot, timing, acceptance_poses=acceptance_poses)
    shown = {"choosable": choosable, "adaptive": bool(options.get("adaptive")), "target_mm": current.get("target_mm"),
             "max_minutes": current.get("max_minutes"), "fixed_minutes": fixed.total_s / 60.0}

    def check(choice: dict[str, Any]) -> dict[str, Any]:
        if not choice["adaptive"]:
            return {"adaptive": False}
        chosen = adaptive_options(choice.get("target_mm"), choice.get("max_minutes"))
        adaptive_budget(plan, robot, timing, chosen, acceptance_poses)
        return {"adaptive": True, **chosen.model_dump()}

    return shown, check


def apply_start_plan(choice: dict[str, Any], journal: Any, options: dict[str, Any], out_dir: Path) -> bool:
    """The plan chosen on the start form into the journal's options (before anything moved); True if it changed."""
    new = {**options, "adaptive": None if not choice["adaptive"] else
           {k: v for k, v in choice.items() if k != "adaptive"}}
    if new == options:
        return False
    journal.set_options(new)
    names = ("plan.json", "reference_plan.json")
    source, target = names if new["adaptive"] else names[::-1]
    if (out_dir / source).exists():
        (out_dir / source).replace(out_dir / target)
    return True
