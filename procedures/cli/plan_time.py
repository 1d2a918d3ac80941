"""Machine time on the command line: the plan's estimated time before any motion (`hilcal run`), and the
calibration plan with its order and an optional time budget (`hilcal design --max-minutes`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rich.table import Table

from hilcal.planning.budget import BudgetError, budgeted_design
from hilcal.planning.machine_time import TimeEstimate, format_minutes
from hilcal.robot import Robot
from procedures.cli.common import fail, out
from procedures.plan import (
    REPEATS,
    CalibrationPlan,
    PlanError,
    distinct_measure_poses,
    estimate_plan,
    make_plan,
    motion_rules,
    plan_from_poses,
    save_plan,
    timing_for,
)
from procedures.timing import TimingFileError, TimingSection, load_timing

ORDERS = {"time": "poses in the order of least machine time", "design": "poses in the design's order",
          "adaptive": "poses as the adaptive run chose them"}
"""A plan's pose order in words."""


def timing_or_fail(station: Path | None) -> TimingSection:
    """The [timing] section of a station file (defaults without one); exit 2 if it is bad."""
    if station is None:
        return TimingSection()
    try:
        return load_timing(station)
    except TimingFileError as e:
        fail(str(e))


def estimate_table(title: str, rows: list[tuple[str, TimeEstimate]]) -> Table:
    """Motion, settle, probing and total per row, in minutes."""
    table = Table(title=title, title_justify="left")
    for column in ("", "leg travel (m)", "motion", "settle", "probing", "total"):
        table.add_column(column, justify="left" if not column else "right")
    for label, e in rows:
        table.add_row(label, f"{e.leg_travel_mm / 1000:.1f}", format_minutes(e.motion_s),
                      format_minutes(e.settle_s), format_minutes(e.probing_s), format_minutes(e.total_s))
    return table


def print_run_estimate(plan: CalibrationPlan, estimate: TimeEstimate, timing: TimingSection) -> None:
    """`hilcal run`: the estimated machine time and its parts, per phase, before anything moves."""
    rows = [(p.phase.replace("_", " "), TimeEstimate((p,))) for p in estimate.phases]
    said = timing.model_copy(update={"settle_s": plan.settle_s}).describe()  # the plan's settle wait is the one used
    order = ORDERS.get(plan.order, plan.order)
    out.print(estimate_table(f"Estimated machine time: {format_minutes(estimate.total_s)} ({order}; {said})",
                             [*rows, ("total", estimate)]))


def print_adaptive_estimate(run: Any, before_motion: dict, timing: TimingSection) -> None:
    """`hilcal run --adaptive`: the range before motion: the best case (the run stops as soon as the diagnosis has its
    minimum and the rule allows) and the worst case, the budget M; the verify phases come on top."""
    b = before_motion
    table = Table(title=f"Estimated machine time of the adaptive run: {format_minutes(b['run_best_s'])} to "
                        f"{format_minutes(b['run_worst_s'])} ({timing.describe()})", title_justify="left")
    for column in ("", "best case", "worst case (the budget)", "the fixed plan"):
        table.add_column(column, justify="left" if not column else "right")
    fixed_rows = run.budget.fixed_measure_rows
    table.add_row("measure", f"{format_minutes(b['best_s'])} ({b['best_rows']} rows)",
                  format_minutes(b["worst_s"]), f"{format_minutes(b['fixed_measure_s'])} ({fixed_rows} rows)")
    rest = format_minutes(b["after_measure_s"])
    table.add_row("verify, upload, verify, home", rest, rest, rest)
    table.add_row("total", format_minutes(b["run_best_s"]), format_minutes(b["run_worst_s"]),
                  format_minutes(b["fixed_total_s"]))
    out.print(table)
    target = run.options.target_mm
    rule = (f"stop once the verify maximum is predicted below {target * 1000:g} µm with 95 % confidence"
            if target is not None else "stop once the prediction improves by less than "
            f"{run.problem.settings.min_improvement:.0%} per row")
    out.print(f"adaptive plan: {rule}, never before the diagnosis has its minimum; budget {run.budget.source} "
              f"({format_minutes(run.budget.total_s)}, of which {format_minutes(run.budget.measure_s)} to measure). "
              "The best case does not depend on the noise; the noise found in the repeated pose decides.",
              highlight=False, markup=False, soft_wrap=True)


def _summary(plan: CalibrationPlan) -> str:
    rows = plan.poses("measure")
    distinct = len(np.unique(rows, axis=0))
    return (f"{distinct} measure poses ({len(rows)} rows: repeats of one pose re-approached), "
            f"{len(plan.verify_poses)} verify poses measured before and after the upload")


def design_plan(robot: Robot, seed: int, timing: TimingSection, max_minutes: float | None, noise_mm: float,
                plan_out: Path | None, n_verify: int = 24) -> None:
    """`hilcal design`: the default plan in design and least-time order, or the best plan within a budget."""
    try:
        design_order = make_plan(robot, seed, n_verify=n_verify, timing=timing.timing(), order="design")
        timed = plan_from_poses(robot, distinct_measure_poses(design_order)[0], design_order.poses("verify"),
                                timing=timing.timing(), seed=seed, approach_mm=design_order.approach_mm,
                                settle_s=design_order.settle_s)
    except PlanError as e:
        fail(str(e))
    out.print(f"\nCalibration plan (seed {seed}): {_summary(timed)}. Station timing: {timing.describe()}.")
    rows = [("design order", estimate_plan(design_order, robot, timing.timing())),
            ("least-time order", estimate_plan(timed, robot, timing.timing()))]
    out.print(estimate_table("Estimated machine time (home, measure, verify, upload, verify, home)", rows))
    chosen = timed
    if max_minutes is not None:
        chosen = _budgeted(robot, design_order, timing, max_minutes, noise_mm)
    if plan_out is not None:
        save_plan(chosen, plan_out)
        out.print(f"wrote the plan ({len(chosen.measure_poses)} measure rows, "
                  f"{format_minutes(estimate_plan(chosen, robot, timing.timing()).total_s)}) to {plan_out}")


def _budgeted(robot: Robot, design_order: CalibrationPlan, timing: TimingSection, max_minutes: float,
              noise_mm: float) -> CalibrationPlan:
    """The largest nested D-optimal subset whose ordered plan fits max_minutes, and what it costs."""
    distinct, counts = distinct_measure_poses(design_order)
    repeat = int(np.argmax(counts)) if counts.max() > 1 else None
    verify = design_order.poses("verify")
    try:
        result = budgeted_design(robot, distinct, verify, 60.0 * max_minutes, motion_rules(design_order),
                                 timing_for(design_order, timing.timing()), repeat=repeat,
                                 repeats=int(counts.max() - 1), noise_mm=noise_mm, seed=design_order.seed)
    except BudgetError as e:
        fail(f"{e}; ask for more time or fewer verify poses")
    table = Table(title=f"Within {max_minutes:g} min: the largest nested D-optimal design that fits "
                        f"(pose noise {noise_mm:g} mm assumed)", title_justify="left")
    for column in ("measure poses", "total", "D-efficiency", "predicted verify error RMS (mm)",
                   "worst pose (mm)", "RMS orientation (deg)", ""):
        table.add_column(column, justify="right")
    for option in result.options:
        p = option.predicted
        table.add_row(str(option.n_measure), format_minutes(option.estimate.total_s), f"{option.d_efficiency:.3f}",
                      f"{p.rms_position_mm:.4f}", f"{p.max_position_mm:.4f}", f"{p.rms_orientation_deg:.5f}",
                      "chosen" if option is result.chosen else "")
    out.print(table)
    out.print("D-efficiency: (det M / det M of the full design)^(1/42). Predicted verify error: the identified "
              "model's error at the verify poses from the least-squares covariance; the CMM noise of the verify "
              "measurement adds to it.")
    try:
        return plan_from_poses(robot, distinct[result.chosen.measure_index], verify, timing=timing.timing(),
                               seed=design_order.seed, approach_mm=design_order.approach_mm,
                               settle_s=design_order.settle_s, repeats=REPEATS if repeat is not None else 0)
    except PlanError as e:
        fail(str(e))
