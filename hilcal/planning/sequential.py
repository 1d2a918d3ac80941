"""A sequential (adaptive) calibration plan: measure one pose at a time, the most useful next, until accuracy is proven.

The run calls it one pose at a time: ``start`` gives the empty state, ``decide`` the next pose (or the stop and its
reason), ``update`` the state with the row just measured. Everything is a pure function of the problem (fixed before
motion, seeded) and the measured rows, so a resumed run that replays the same rows makes the same next choices.

Next pose: from a seeded candidate set (``hilcal.planning.candidates``), the one with the largest gain per second
of machine time (its move from the current pose under the motion rules, settle and probing). The gain is
- before the 42 parameters are identifiable: D-optimal (ln det of the information, with a tiny ridge);
- then: the fall of the average predicted position variance over the verify poses (I-optimality aimed at them:
  what the stopping rule predicts and the verification measures; smoother than the maximum, whose worst pose
  changes from row to row);
- until the diagnosis has its minimum spread, that gain plus 1/12 of the Ds gain of the 12 load and stroke terms
  (the geometry fitted): a compound criterion; once the screening suspects physics, the Ds gain alone.
The first pose is measured 1 + repeats times in a row (the noise yardstick); it is chosen among the candidates with
room for a repeat's retreat. The selection uses the nominal Jacobians and unit noise, so it depends on the data
only through the screening; the noise sets the prediction and the stop (``hilcal.planning.stopping``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from threadpoolctl import threadpool_limits

from hilcal.error_models import GEOMETRIC_42, forward_jacobian, pose_difference
from hilcal.identifiability import identifiability
from hilcal.identification import IdentificationError, identify
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.planning.candidates import CandidateSet, candidate_set, designable_robot, library_columns, library_variables
from hilcal.planning.criteria import d_gain, ds_gain, v_gain
from hilcal.planning.design import factorial_exchange, pose_jacobians
from hilcal.planning.machine_time import MotionRules, MotionTiming, format_minutes, move_costs, repeatable_pose
from hilcal.planning.prediction import (
    Draws,
    PoseNoise,
    VerifyPrediction,
    predict_verify_max,
    repeat_groups,
    repeat_noise,
    residual_noise,
)
from hilcal.planning.stopping import (
    DiagnosisMinimum,
    MinimumSettings,
    RuleCheck,
    Screening,
    StopReason,
    accuracy_rule,
    diagnosis_minimum,
    library_efficiency,
    library_information,
    screen,
)
from hilcal.robot import Robot

RIDGE = 1e-6
"""Ridge of the information before it is nonsingular, relative to the candidates' mean information per parameter."""
Mode = Literal["first", "repeat", "fill", "compound", "accuracy", "diagnosis"]


class AdaptiveSettings(BaseModel):
    """How an adaptive run measures and stops (lengths in mm, times in s)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    max_measure_s: float = Field(gt=0, description="machine-time budget of the measure phase (the route estimate)")
    target_mm: float | None = Field(default=None, gt=0, description="stop once the verify maximum's bound is below")
    min_improvement: float = Field(default=0.05, gt=0, lt=1, description="without a target: stop when the bound "
                                   "improves by less than this fraction per row")
    window: int = Field(default=3, ge=1, le=10, description="rows over which the improvement is averaged")
    repeats: int = Field(default=3, ge=1, le=10, description="extra measurements of the first pose, in a row")
    confidence: float = Field(default=0.95, gt=0.5, lt=1.0, description="one-sided confidence of the upper bound")
    n_draws: int = Field(default=10000, ge=1000, le=200_000, description="Monte Carlo draws of a prediction")
    seed: int = Field(default=0, description="candidates and Monte Carlo draws")
    library_efficiency: float = Field(default=0.2, gt=0, le=2, description="load and stroke terms' Ds-efficiency "
                                      "against the reference plan needed before any stop")
    residual_dof: int = Field(default=30, ge=1, description="residual dof beyond 42 + 12 terms before a stop")
    screening_alpha: float = Field(default=0.02, gt=0, lt=0.5, description="level of the one-look physics screening "
                                   "(the diagnosis' default level)")
    diagnosis_efficiency: float = Field(default=1.0, gt=0, le=2, description="library Ds-efficiency against the "
                                        "reference plan needed once physics is suspected")
    n_boundary: int = Field(default=1000, ge=0, description="candidates on the feasible region's boundary")
    n_random: int = Field(default=1000, ge=0, description="uniform random candidates")

    def minimum(self) -> MinimumSettings:
        return MinimumSettings(1 + self.repeats, self.library_efficiency, self.residual_dof)


@dataclass(frozen=True)
class AdaptiveProblem:
    """Everything fixed before motion: robot, verify poses, rules and timing, candidates, draws, reference design."""

    robot: Robot
    settings: AdaptiveSettings
    rules: MotionRules
    timing: MotionTiming
    verify: np.ndarray
    candidates: CandidateSet
    repeatable: np.ndarray
    """[C] bool: room below the candidate for a repeat's retreat."""
    verify_position_jacobians: np.ndarray
    draws: Draws
    candidate_range: np.ndarray
    """[2, 6]: the range over the candidates of each leg's load (kN) and stroke (m)."""
    reference_library: np.ndarray
    """(12, 12): the library information of the reference (fixed) plan's measure rows."""
    ridge: float
    """Added to the information's diagonal while it is singular: RIDGE times the candidates' mean per term."""

    @property
    def dwell_s(self) -> float:
        return self.timing.settle_s + self.timing.cmm_s_per_pose


def adaptive_problem(robot: Robot, verify: np.ndarray, settings: AdaptiveSettings, rules: MotionRules,
                     timing: MotionTiming, reference_measure: np.ndarray | None = None) -> AdaptiveProblem:
    """Build the problem. reference_measure: the fixed plan's measure rows (repeats included), which the diagnosis was
    validated on; None designs them as ``make_plan`` does (32 factorial-exchange poses, one measured 1 + repeats
    times). Its poses join the candidates."""
    V = np.atleast_2d(np.asarray(verify, dtype=float))
    if V.shape[1:] != (6,) or len(V) == 0:
        raise ValueError(f"verify poses must be (V, 6) with V >= 1, got {V.shape}")
    geom = Geometry.nominal(robot)
    if reference_measure is None:
        design = factorial_exchange(designable_robot(robot, rules.approach_mm), 32,
                                    np.random.default_rng(settings.seed)).poses
        k = repeatable_pose(geom, design, robot.leg_limits[0], rules)
        reference_measure = np.vstack([design, np.repeat(design[k:k + 1], settings.repeats, axis=0)])
    ref = np.atleast_2d(np.asarray(reference_measure, dtype=float))
    cands = candidate_set(robot, settings.seed, approach_mm=rules.approach_mm, n_boundary=settings.n_boundary,
                          n_random=settings.n_random, reference=ref)
    room = inverse_kinematics(geom, cands.poses).min(axis=1) - robot.leg_limits[0]
    ref_jac = pose_jacobians(robot, ref)
    ref_load, ref_stroke = library_variables(robot, ref)
    return AdaptiveProblem(
        robot, settings, rules, timing, V, cands, room >= rules.retreat_mm, pose_jacobians(robot, V)[:, :3],
        Draws.seeded(settings.seed, len(V), settings.n_draws),
        np.stack([np.ptp(cands.load_kn, axis=0), np.ptp(cands.stroke_m, axis=0)]),
        library_information(ref_jac, library_columns(ref_jac, ref_load, ref_stroke)),
        RIDGE * float(np.mean(np.sum(cands.jacobians**2, axis=1))))


@dataclass(frozen=True)
class MeasuredRow:
    """One measured row: the commanded pose, the reported leg lengths and the measured pose (mm, deg)."""

    pose: np.ndarray
    legs_mm: np.ndarray
    measured: np.ndarray
    candidate: int
    """Index of the commanded pose in the candidate set, -1 if it is none of them."""


@dataclass(frozen=True)
class AdaptiveState:
    """The measured rows and everything derived from them (a pure function of the rows; see ``update``)."""

    rows: tuple[MeasuredRow, ...] = ()
    elapsed_s: float = 0.0
    """Estimated machine time of the route measured so far (home, the rows), under the problem's rules and timing."""
    parameters: np.ndarray | None = None
    """The 42 identified errors (least squares) once the rows identify them."""
    noise: PoseNoise | None = None
    prediction: VerifyPrediction | None = None
    rule: RuleCheck | None = None
    minimum: DiagnosisMinimum | None = None
    screening: Screening | None = None
    library_efficiency: float = 0.0
    unidentifiable: tuple[str, ...] = ()
    """While the rows do not identify the parameters: those involved in the unresolved directions."""
    n_unresolved: int = 0
    """How many parameter directions the rows leave unresolved (42 minus the rank)."""

    @property
    def n_rows(self) -> int:
        return len(self.rows)

    def commanded(self) -> np.ndarray:
        return np.array([r.pose for r in self.rows]).reshape(-1, 6)

    def diagnosis_pending(self, problem: AdaptiveProblem) -> bool:
        """Physics suspected and the library terms not yet as well measured as in the reference plan."""
        return (self.screening is not None and self.screening.suspected
                and self.library_efficiency < problem.settings.diagnosis_efficiency)


def start(problem: AdaptiveProblem) -> AdaptiveState:
    """The state before the first row."""
    del problem
    return AdaptiveState()


def _candidate_index(problem: AdaptiveProblem, pose: np.ndarray) -> int:
    hit = np.flatnonzero(np.all(problem.candidates.poses == pose, axis=1))
    return int(hit[0]) if hit.size else -1


def _prediction(problem: AdaptiveProblem, poses: np.ndarray, noise: PoseNoise | None,
                misfit: np.ndarray | None = None) -> VerifyPrediction | None:
    """The verify prediction for these commanded rows (with an incomplete model's misfit covariance of the
    parameters), None when they do not identify the parameters."""
    if noise is None or 6 * len(poses) <= 42:
        return None
    try:
        return predict_verify_max(pose_jacobians(problem.robot, poses), problem.verify_position_jacobians, noise,
                                  problem.draws, problem.settings.confidence, misfit)
    except np.linalg.LinAlgError:
        return None


def evaluate(problem: AdaptiveProblem, poses: np.ndarray, noise: PoseNoise | None, misfit: np.ndarray | None = None
             ) -> tuple[VerifyPrediction | None, RuleCheck, DiagnosisMinimum]:
    """Prediction, accuracy rule and diagnosis minimum of commanded rows [n, 6] under a noise (no measurements),
    with an incomplete model's misfit covariance of the parameters when given."""
    return *accuracy(problem, poses, noise, misfit), minimum_for(problem, poses)


def accuracy(problem: AdaptiveProblem, poses: np.ndarray, noise: PoseNoise | None, misfit: np.ndarray | None = None
             ) -> tuple[VerifyPrediction | None, RuleCheck]:
    """Prediction and accuracy rule of commanded rows [n, 6] under a noise (the Monte Carlo part of ``evaluate``)."""
    s = problem.settings
    prediction = _prediction(problem, poses, noise, misfit)
    earlier = _prediction(problem, poses[:-s.window], noise, misfit) if len(poses) > s.window else None
    return prediction, accuracy_rule(prediction, earlier, s.window, s.target_mm, s.min_improvement)


def minimum_for(problem: AdaptiveProblem, poses: np.ndarray) -> DiagnosisMinimum:
    """The diagnosis minimum of commanded rows [n, 6]: a function of the poses alone, not of the noise."""
    load, stroke = library_variables(problem.robot, poses) if len(poses) else (np.zeros((0, 6)),) * 2
    groups = repeat_groups(poses) if len(poses) else []
    return diagnosis_minimum(len(poses), max((g.size for g in groups), default=0),
                             _library_efficiency(problem, poses), load, stroke, problem.candidate_range,
                             problem.settings.minimum())


def _library_efficiency(problem: AdaptiveProblem, poses: np.ndarray) -> float:
    """Ds-efficiency of the load and stroke terms of these rows against the reference plan's (0 while singular)."""
    if 6 * len(poses) <= 42 + 12:
        return 0.0
    J = pose_jacobians(problem.robot, poses)
    load, stroke = library_variables(problem.robot, poses)
    return library_efficiency(library_information(J, library_columns(J, load, stroke)), problem.reference_library)


def update(problem: AdaptiveProblem, state: AdaptiveState, pose: np.ndarray, legs_mm: np.ndarray,
           measured: np.ndarray) -> AdaptiveState:
    """The state with one more measured row: route time, fit, noise, prediction, rule, minimum, screening."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _update(problem, state, pose, legs_mm, measured)


def _update(problem: AdaptiveProblem, state: AdaptiveState, pose: np.ndarray, legs_mm: np.ndarray,
            measured: np.ndarray) -> AdaptiveState:
    q, legs, meas = (np.asarray(v, dtype=float).reshape(6) for v in (pose, legs_mm, measured))
    if not (np.isfinite(q).all() and np.isfinite(legs).all() and np.isfinite(meas).all()):
        raise ValueError("a measured row must have a finite commanded pose, leg lengths and measured pose")
    robot = problem.robot
    previous = state.rows[-1].pose if state.rows else robot.home
    move = move_costs(Geometry.nominal(robot), previous, q, problem.rules, problem.timing).time_s[0]
    rows = (*state.rows, MeasuredRow(q, legs, meas, _candidate_index(problem, q)))
    poses = np.array([r.pose for r in rows])
    L, M = np.array([r.legs_mm for r in rows]), np.array([r.measured for r in rows])
    length = robot.characteristic_length_mm
    noise = repeat_noise(poses, M, length)
    parameters, residuals, misfit = None, None, None
    report = identifiability(robot, poses, max_listed=42)
    unidentifiable = tuple(sorted({n for d in report.unidentifiable for n in d.coefficients},
                                  key=GEOMETRIC_42.names.index))
    if report.rank == 42 and 6 * len(rows) > 42:
        try:
            fit = identify(robot, L, M, x0=state.parameters, **({} if noise is None else {
                "noise_covariance": np.broadcast_to(noise.covariance(), (len(rows), 6, 6)),
                "noise_dof": noise.total_dof}))
            parameters, residuals = fit.x, fit.residuals
            misfit = None if fit.misfit is None or not fit.misfit.incomplete else fit.misfit.covariance
        except IdentificationError:
            parameters = None
    repeats = noise
    screening = state.screening
    if noise is not None and residuals is not None and 6 * len(rows) - 42 > noise.total_dof:
        lack = "" if screening is None or not screening.lack_of_fit else " (lack of fit against the repeats)"
        noise = residual_noise(residuals, pose_jacobians(robot, poses), lack)
    prediction, rule, minimum = evaluate(problem, poses, noise, misfit)
    if screening is None and rule.met and minimum.met and residuals is not None and repeats is not None:
        screening = _screen(problem, poses, M, residuals, parameters, repeats)
    return AdaptiveState(rows, state.elapsed_s + float(move) + problem.dwell_s, parameters, noise, prediction, rule,
                         minimum, screening, minimum.library_efficiency, unidentifiable, 42 - report.rank)


def _screen(problem: AdaptiveProblem, poses: np.ndarray, measured: np.ndarray, residuals: np.ndarray,
            parameters: np.ndarray, noise: PoseNoise) -> Screening:
    robot = problem.robot
    length = robot.characteristic_length_mm
    J = forward_jacobian(Geometry.nominal(robot).perturbed(parameters), measured, length)
    load, stroke = library_variables(robot, poses)
    deviation = []
    for g in repeat_groups(poses):
        d = pose_difference(measured[g], measured[g[0]], length)
        deviation.append(d - d.mean(axis=0))
    return screen(residuals, J, library_columns(J, load, stroke), np.concatenate(deviation), noise,
                  problem.settings.screening_alpha)


def replay(problem: AdaptiveProblem, rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> AdaptiveState:
    """The state after these (commanded pose, legs, measured pose) rows, as after a crash: resume from it."""
    state = start(problem)
    for pose, legs, measured in rows:
        state = update(problem, state, pose, legs, measured)
    return state


@dataclass(frozen=True)
class PoseChoice:
    """The next pose to measure and why: its mode, move and total time (s), its gain per second."""

    pose: np.ndarray
    candidate: int
    mode: Mode
    move_s: float
    time_s: float
    score: float

    @property
    def repeat(self) -> bool:
        return self.mode == "repeat"


def mode_for(problem: AdaptiveProblem, state: AdaptiveState) -> Mode:
    """How the next pose is chosen after these rows (see the module docstring)."""
    if not state.rows:
        return "first"
    first = state.rows[0].pose
    if len(state.rows) < 1 + problem.settings.repeats and all(np.array_equal(r.pose, first) for r in state.rows):
        return "repeat"
    if _singular(_information(problem, state.commanded())[0]):
        return "fill"
    if state.diagnosis_pending(problem):
        return "diagnosis"
    return "compound" if state.minimum is None or not state.minimum.library_met else "accuracy"


def _information(problem: AdaptiveProblem, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Information (42 x 42) and that of the geometry with the library terms (54 x 54) of commanded rows."""
    if not len(poses):
        return np.zeros((42, 42)), np.zeros((54, 54))
    J = pose_jacobians(problem.robot, poses)
    load, stroke = library_variables(problem.robot, poses)
    E = np.concatenate([J, library_columns(J, load, stroke)], axis=-1).reshape(-1, 54)
    return E[:, :42].T @ E[:, :42], E.T @ E


def _singular(info: np.ndarray) -> bool:
    scale = max(float(np.abs(info).max()), 1e-300)
    return bool(np.linalg.matrix_rank(info / scale, tol=1e-12) < 42)


def choose(problem: AdaptiveProblem, poses: np.ndarray, candidates: list[int], mode: Mode) -> PoseChoice | None:
    """The next pose in `mode` after commanded rows [n, 6] (their candidate indices, -1 for others); None if no
    unmeasured candidate can be reached within the leg limits."""
    cands = problem.candidates
    geom = Geometry.nominal(problem.robot)
    here = poses[-1] if len(poses) else problem.robot.home
    if mode == "repeat":
        move = move_costs(geom, here, here, problem.rules, problem.timing).time_s[0]
        return PoseChoice(here.copy(), candidates[-1], "repeat", float(move), float(move) + problem.dwell_s, 0.0)
    info, info_ext = _information(problem, poses)
    costs = move_costs(geom, np.broadcast_to(here, cands.poses.shape), cands.poses, problem.rules, problem.timing)
    ok = costs.within(problem.robot.leg_limits)
    ok[[c for c in candidates if c >= 0]] = False
    if mode == "first":
        ok &= problem.repeatable
    if not ok.any():
        return None
    idx = np.flatnonzero(ok)
    J = cands.jacobians[idx]
    if mode in ("first", "fill"):
        gain = d_gain(info, J, problem.ridge)
    elif mode == "accuracy":
        gain = v_gain(info, J, problem.verify_position_jacobians)
    else:
        library = ds_gain(info_ext, np.concatenate([J, cands.library[idx]], axis=-1), 42, problem.ridge)
        gain = library if mode == "diagnosis" else v_gain(info, J, problem.verify_position_jacobians) + library / 12
    time_s = costs.time_s[idx] + problem.dwell_s
    k = int(np.argmax(gain / time_s))
    c = int(idx[k])
    return PoseChoice(cands.poses[c].copy(), c, mode, float(costs.time_s[c]), float(time_s[k]),
                      float(gain[k] / time_s[k]))


class ChoiceMemo:
    """Choices already made for one problem, keyed by the commanded rows and the mode.

    ``choose`` is a pure function of them, so a run that forecasts its rest after every row (the same future rows each
    time, until the screening changes the mode) computes each choice once. Pass one memo per problem.
    """

    def __init__(self) -> None:
        self._choices: dict[tuple[bytes, tuple[int, ...], str], PoseChoice | None] = {}
        self._predictions: dict[tuple[bytes, PoseNoise | None], VerifyPrediction | None] = {}
        self._minima: dict[bytes, DiagnosisMinimum] = {}

    def choose(self, problem: AdaptiveProblem, poses: np.ndarray, candidates: list[int], mode: Mode
               ) -> PoseChoice | None:
        key = (_rows_key(poses), tuple(candidates), mode)
        if key not in self._choices:
            self._choices[key] = choose(problem, poses, candidates, mode)
        return self._choices[key]

    def accuracy(self, problem: AdaptiveProblem, poses: np.ndarray, noise: PoseNoise | None
                 ) -> tuple[VerifyPrediction | None, RuleCheck]:
        """``accuracy`` with each prediction computed once per rows and noise: a forecast's rule compares the rows
        with the rows a window earlier, and the forecasts after later rows walk the same rows under the same noise."""
        s = problem.settings
        prediction = self._prediction(problem, poses, noise)
        earlier = self._prediction(problem, poses[:-s.window], noise) if len(poses) > s.window else None
        return prediction, accuracy_rule(prediction, earlier, s.window, s.target_mm, s.min_improvement)

    def minimum(self, problem: AdaptiveProblem, poses: np.ndarray) -> DiagnosisMinimum:
        """``minimum_for``, once per rows."""
        key = _rows_key(poses)
        if key not in self._minima:
            self._minima[key] = minimum_for(problem, poses)
        return self._minima[key]

    def _prediction(self, problem: AdaptiveProblem, poses: np.ndarray, noise: PoseNoise | None
                    ) -> VerifyPrediction | None:
        key = (_rows_key(poses), noise)
        if key not in self._predictions:
            self._predictions[key] = _prediction(problem, poses, noise)
        return self._predictions[key]

    def __len__(self) -> int:
        return len(self._choices)


def _rows_key(poses: np.ndarray) -> bytes:
    return np.ascontiguousarray(poses, dtype=float).tobytes()


def next_pose(problem: AdaptiveProblem, state: AdaptiveState, memo: ChoiceMemo | None = None) -> PoseChoice | None:
    """The next pose for the measured state (None: no candidate is reachable within the leg limits)."""
    pick = choose if memo is None else memo.choose
    with threadpool_limits(limits=1, user_api="blas"):
        return pick(problem, state.commanded(), [r.candidate for r in state.rows], mode_for(problem, state))


@dataclass(frozen=True)
class Decision:
    """What to do after the rows so far: measure `next`, or stop for `stop`; with the current prediction."""

    next: PoseChoice | None
    stop: StopReason | None
    prediction: VerifyPrediction | None
    sentence: str


def may_stop(problem: AdaptiveProblem, state: AdaptiveState) -> bool:
    """The accuracy rule holds, the diagnosis has its minimum, and no suspected physics still needs rows."""
    return (state.rule is not None and state.rule.met and state.minimum is not None and state.minimum.met
            and state.screening is not None and not state.diagnosis_pending(problem))


def decide(problem: AdaptiveProblem, state: AdaptiveState, memo: ChoiceMemo | None = None) -> Decision:
    """Stop (target, converged, budget, not identifiable) or the next pose, for the measured state (memo: choices
    already made, see ``ChoiceMemo``)."""
    s = problem.settings
    physics = "" if state.screening is None or not state.screening.suspected else f"; {state.screening.sentence()}"
    if may_stop(problem, state):
        assert state.rule is not None and state.rule.kind is not None
        extra = "" if not physics else f"{physics} until the load and stroke terms were determined as well as in " \
            f"the fixed plan (Ds-efficiency {state.library_efficiency:.2f}): run the diagnosis"
        reason = StopReason(state.rule.kind, f"{state.rule.sentence}{extra}", state.n_rows, state.elapsed_s,
                            state.prediction, (), state.screening)
        return Decision(None, reason, state.prediction, reason.sentence)
    choice = next_pose(problem, state, memo)
    if choice is not None and state.elapsed_s + choice.time_s <= s.max_measure_s:
        why = state.rule.sentence if state.rule is not None else "starting: the first pose, then its repeats"
        if state.diagnosis_pending(problem):
            why = f"{why}; measuring the load and stroke terms for the diagnosis (Ds-efficiency " \
                  f"{state.library_efficiency:.2f} of {s.diagnosis_efficiency:.2f})"
        elif state.minimum is not None and not state.minimum.met:
            why = f"{why}; the diagnosis still needs: {'; '.join(state.minimum.missing)}"
        return Decision(choice, None, state.prediction, why)
    budget = f"the measure budget of {format_minutes(s.max_measure_s)}"
    if state.prediction is None:
        if state.n_unresolved:
            names = state.unidentifiable
            said = f"{state.n_unresolved} of 42 parameter directions unresolved, involving {', '.join(names)}"
        else:
            names = ()
            said = "no noise estimate yet (the repeats are not complete)"
        reason = StopReason("not_identifiable", f"{budget} ended before the rows identified every parameter: {said}",
                            state.n_rows, state.elapsed_s, None, names, state.screening)
    else:
        reason = StopReason("budget", f"{budget} is reached: the verify maximum is predicted below "
                            f"{state.prediction.upper_mm * 1000:.1f} µm with {state.prediction.confidence:.0%} "
                            f"confidence{physics}", state.n_rows, state.elapsed_s, state.prediction, (),
                            state.screening)
    return Decision(None, reason, state.prediction, reason.sentence)
