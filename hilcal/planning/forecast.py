"""How long an adaptive run will still measure: the remaining time after each row, and the range before motion.

The next poses of an adaptive plan depend on the measurements only through the noise level and the physics
screening (``hilcal.planning.sequential``), so the rest of the run can be simulated: the same choices, appended as
commanded rows without measurements, the prediction under the current noise estimate, until the stopping rule or the
budget would end the run. Before motion no noise is known: the best case is the run that stops as soon as the
diagnosis has its minimum (a target met at once; without a target, the improvement rule, which does not depend on the
noise's size), the worst case is the budget; with an assumed noise (the CMM's stated uncertainty) a likely case too.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from threadpoolctl import threadpool_limits

from hilcal.planning.prediction import PoseNoise
from hilcal.planning.sequential import (
    AdaptiveProblem,
    AdaptiveState,
    ChoiceMemo,
    MeasuredRow,
    mode_for,
)
from hilcal.planning.stopping import StopKind


@dataclass(frozen=True)
class Forecast:
    """The simulated rest of a run: further rows and machine time (s), how it would stop and the bound then (mm)."""

    n_rows: int
    remaining_s: float
    stop: StopKind
    upper_mm: float | None
    noise_source: str

    def to_json(self) -> dict:
        return {"n_rows": self.n_rows, "remaining_s": self.remaining_s, "stop": self.stop, "upper_mm": self.upper_mm,
                "noise_source": self.noise_source}


def forecast(problem: AdaptiveProblem, state: AdaptiveState, noise: PoseNoise | None = None, *,
             best_case: bool = False, memo: ChoiceMemo | None = None) -> Forecast:
    """Simulate the rest of the run from `state` (see the module docstring).

    noise: used until the repeats give one (None: unit noise with the repeats' dof, meaningful only without a target
    or for the best case).
    best_case: the accuracy rule counts as met whenever a prediction exists (stop as soon as the minimum holds).
    memo: the run's choices so far (``ChoiceMemo``): a forecast after every row then computes only the predictions.
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _forecast(problem, state, noise, best_case, ChoiceMemo() if memo is None else memo)


def _forecast(problem: AdaptiveProblem, state: AdaptiveState, noise: PoseNoise | None, best_case: bool,
              memo: ChoiceMemo) -> Forecast:
    dof = 3.0 * problem.settings.repeats
    unit = PoseNoise.isotropic(1.0, 1.0, dof, dof, "unit noise (the improvement rule does not depend on its size)")
    level = state.noise or noise or unit
    poses = state.commanded()
    candidates = [r.candidate for r in state.rows]
    elapsed, sim = state.elapsed_s, state
    budget = problem.settings.max_measure_s
    while True:
        if len(poses):
            minimum = memo.minimum(problem, poses)
            sim = AdaptiveState(sim.rows, elapsed, None, level, None, None, minimum, state.screening,
                                minimum.library_efficiency)
            if minimum.met and not sim.diagnosis_pending(problem):
                prediction, rule = memo.accuracy(problem, poses, level)
                if (prediction is not None) if best_case else rule.met:
                    return Forecast(len(poses) - state.n_rows, elapsed - state.elapsed_s, rule.kind or "target",
                                    None if prediction is None else prediction.upper_mm, level.source)
        choice = memo.choose(problem, poses, candidates, mode_for(problem, sim))
        if choice is None or elapsed + choice.time_s > budget:
            prediction = memo.accuracy(problem, poses, level)[0] if len(poses) else None
            kind: StopKind = "budget" if prediction is not None else "not_identifiable"
            return Forecast(len(poses) - state.n_rows, elapsed - state.elapsed_s, kind,
                            None if prediction is None else prediction.upper_mm, level.source)
        poses = np.vstack([poses, choice.pose[None]])
        candidates.append(choice.candidate)
        elapsed += choice.time_s
        sim = replace(sim, rows=(*sim.rows, MeasuredRow(choice.pose, np.full(6, np.nan), np.full(6, np.nan),
                                                         choice.candidate)))


@dataclass(frozen=True)
class TimeRange:
    """Machine time of the measure phase before motion (s): best case, likely case (with an assumed noise), budget."""

    best_s: float
    best_rows: int
    likely_s: float | None
    likely_rows: int | None
    worst_s: float

    def to_json(self) -> dict:
        return {"best_s": self.best_s, "best_rows": self.best_rows, "likely_s": self.likely_s,
                "likely_rows": self.likely_rows, "worst_s": self.worst_s}


def time_range(problem: AdaptiveProblem, assumed_noise: PoseNoise | None = None) -> TimeRange:
    """The measure phase's time range before motion (see the module docstring); the verify phases come on top."""
    empty = AdaptiveState()
    best = forecast(problem, empty, best_case=problem.settings.target_mm is not None)
    if problem.settings.target_mm is None:
        likely = best
    else:
        likely = forecast(problem, empty, assumed_noise) if assumed_noise is not None else None
    return TimeRange(best.remaining_s, best.n_rows, None if likely is None else likely.remaining_s,
                     None if likely is None else likely.n_rows, problem.settings.max_measure_s)
