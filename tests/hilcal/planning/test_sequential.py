"""A sequential (adaptive) plan walked on a simulated machine (hilcal.planning.sequential and forecast): repeats first,
a stop after the diagnosis' minimum, the same choices after a replay, honest stop reasons, physics keeps it going."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.planning.forecast import forecast, time_range
from hilcal.planning.machine_time import MotionRules, MotionTiming, estimate_route
from hilcal.planning.sequential import (
    AdaptiveSettings,
    AdaptiveState,
    ChoiceMemo,
    adaptive_problem,
    decide,
    next_pose,
    replay,
    start,
    update,
)
from hilcal.workspace import feasible
from tests.poses import feasible_random_poses

TIMING = MotionTiming(leg_speed_mm_s=50.0, leg_accel_mm_s2=100.0, settle_s=2.0, cmm_s_per_pose=45.0,
                      move_overhead_s=0.5)
RULES = MotionRules()
FAST = {"n_draws": 2000, "n_boundary": 300, "n_random": 300}


class Machine:
    """A machine with seeded geometric errors (and optionally a scale fault on leg 1) under an uncalibrated
    controller, measured by an instrument with pose noise of `sigma_mm` per coordinate (rotations: at the
    platform's characteristic length)."""

    def __init__(self, robot, seed: int, sigma_mm: float = 0.005, scale_ppm: float = 0.0) -> None:
        self.robot = robot
        self.rng = np.random.default_rng(seed)
        self.true = Geometry.nominal(robot).perturbed(self.rng.normal(0.0, 0.5, 42))
        self.sigma = sigma_mm
        self.scale = np.array([scale_ppm * 1e-6, 0, 0, 0, 0, 0])

    def measure(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        legs = np.round(inverse_kinematics(Geometry.nominal(self.robot), pose), 3)
        reached = forward_kinematics(self.true, legs + self.scale * (legs - self.robot.l0), pose)[0]
        out = reached.copy()
        out[:3] += self.rng.normal(0.0, self.sigma, 3)
        R = Rotation.from_euler("ZYX", reached[[5, 4, 3]], degrees=True)
        dR = Rotation.from_rotvec(self.rng.normal(0.0, self.sigma / self.robot.characteristic_length_mm, 3))
        out[[5, 4, 3]] = (dR * R).as_euler("ZYX", degrees=True)
        return legs, out


def walk(problem, machine: Machine) -> tuple[AdaptiveState, list, list]:
    """Run the plan to its stop: the final state, the decisions and the measured rows."""
    state, decisions, rows = start(problem), [], []
    while True:
        decision = decide(problem, state)
        decisions.append(decision)
        if decision.stop is not None:
            return state, decisions, rows
        legs, measured = machine.measure(decision.next.pose)
        rows.append((decision.next.pose, legs, measured))
        state = update(problem, state, decision.next.pose, legs, measured)


@pytest.fixture(scope="module")
def setup(robot):
    rng = np.random.default_rng(5)
    verify = feasible_random_poses(robot, 12, rng)
    reference = np.vstack([feasible_random_poses(robot, 32, rng)])
    reference = reference[inverse_kinematics(Geometry.nominal(robot), reference).min(axis=1) > 3810]
    return verify, np.vstack([reference, np.repeat(reference[:1], 3, axis=0)])


def make(robot, setup, **settings):
    verify, reference = setup
    options = {"max_measure_s": 2400.0, **FAST, **settings}
    return adaptive_problem(robot, verify, AdaptiveSettings(**options), RULES, TIMING, reference_measure=reference)


@pytest.fixture(scope="module")
def run(robot, setup):
    problem = make(robot, setup)
    return problem, *walk(problem, Machine(robot, 1))


def test_repeats_first_then_distinct_feasible_poses(robot, run):
    _problem, state, decisions, _rows = run
    poses = state.commanded()
    assert all(np.array_equal(poses[k], poses[0]) for k in range(4))
    assert [d.next.mode for d in decisions[:4]] == ["first", "repeat", "repeat", "repeat"]
    assert len(np.unique(poses[4:], axis=0)) == len(poses) - 4 and not np.any(np.all(poses[4:] == poses[0], axis=1))
    lo, hi = robot.leg_limits
    legs = inverse_kinematics(Geometry.nominal(robot), poses)
    assert np.all(feasible(robot, poses)) and legs.min() >= lo + RULES.approach_mm and legs.max() <= hi
    assert legs[0].min() - RULES.retreat_mm >= lo


def test_stops_converged_once_the_diagnosis_has_its_minimum(run):
    problem, state, decisions, rows = run
    stop = decisions[-1].stop
    assert stop.kind == "converged" and stop.n_rows == state.n_rows == len(rows)
    assert state.minimum.met and state.minimum.repeat_rows == 4 and state.minimum.residual_dof >= 30
    assert state.rule.improvement_per_row < problem.settings.min_improvement
    assert state.screening is not None and not state.screening.suspected
    assert stop.prediction.low_mm < stop.prediction.max_mm < stop.prediction.upper_mm
    assert state.elapsed_s < problem.settings.max_measure_s
    # the noise is the machine's (5 µm per coordinate), from the fit's residuals: 6n - 42 degrees of freedom in all
    assert 0.0035 < state.noise.position_mm < 0.0065 and 0.0035 < state.noise.rotation_mm < 0.0065
    assert sum(state.noise.dof) == pytest.approx(6 * state.n_rows - 42) and not state.noise.shared
    assert state.noise.source.startswith("the geometric fit's residuals")
    after_repeats = replay(problem, rows[:4]).noise
    assert after_repeats.dof == (9,) * 6 and after_repeats.shared and "repeated pose" in after_repeats.source


def test_machine_time_is_the_route_estimate(robot, run):
    _problem, state, _, _ = run
    route = estimate_route(Geometry.nominal(robot), robot.home, [("measure", state.commanded())], RULES, TIMING)
    assert state.elapsed_s == pytest.approx(route.total_s, rel=1e-12)


def test_a_replay_makes_the_same_next_choices(robot, setup, run):
    _problem, _state, decisions, rows = run
    again = make(robot, setup)  # as after a crash: the problem rebuilt from the stored settings
    for k in (4, 9, len(rows) - 1):
        resumed = replay(again, rows[:k])
        assert np.array_equal(next_pose(again, resumed).pose, decisions[k].next.pose)
    final = decide(again, replay(again, rows))
    assert final.stop.kind == decisions[-1].stop.kind and final.stop.sentence == decisions[-1].stop.sentence


def test_the_forecast_after_the_repeats_is_the_run(run):
    problem, state, _decisions, rows = run
    after_repeats = replay(problem, rows[:4])
    predicted = forecast(problem, after_repeats)
    # the choices do not depend on the data; the stop may move by a row as the noise estimate grows its dof
    assert predicted.stop == "converged" and abs(predicted.n_rows - (len(rows) - 4)) <= 1
    assert abs(after_repeats.elapsed_s + predicted.remaining_s - state.elapsed_s) < 90.0
    before = time_range(problem)
    assert before.best_s <= state.elapsed_s + 1e-6 and before.worst_s == problem.settings.max_measure_s


@pytest.mark.slow
def test_a_memo_of_the_choices_changes_no_decision_and_no_forecast(run):
    problem, _state, decisions, rows = run
    memo = ChoiceMemo()
    for k in (0, 4, 11, len(rows) - 2):  # the run forecasts after every row with one memo
        state = replay(problem, rows[:k])
        assert forecast(problem, state, memo=memo) == forecast(problem, state)
        assert np.array_equal(decide(problem, state, memo).next.pose, decisions[k].next.pose)
    assert len(memo) > len(rows) - 2, "the memo holds the choices the forecasts walked"


def test_a_target_stops_below_it(robot, setup):
    problem = make(robot, setup, target_mm=0.05)
    state, decisions, _ = walk(problem, Machine(robot, 2))
    stop = decisions[-1].stop
    assert stop.kind == "target" and stop.prediction.upper_mm < 0.05 and state.minimum.met
    assert "below 50.0 µm with 95% confidence" in stop.sentence


def test_the_budget_ends_the_run_with_the_reason(robot, setup):
    short = make(robot, setup, max_measure_s=400.0)
    state, decisions, _ = walk(short, Machine(robot, 3))
    stop = decisions[-1].stop
    assert stop.kind == "not_identifiable" and stop.prediction is None and stop.unidentifiable
    assert state.elapsed_s <= 400.0 and "ended before the rows identified every parameter" in stop.sentence
    medium = make(robot, setup, max_measure_s=800.0)
    state, decisions, _ = walk(medium, Machine(robot, 3))
    stop = decisions[-1].stop
    assert stop.kind == "budget" and stop.prediction is not None and not state.minimum.met
    assert f"{stop.prediction.upper_mm * 1000:.1f} µm" in stop.sentence


def test_missing_physics_keeps_the_run_measuring_for_the_diagnosis(robot, setup, run):
    problem = make(robot, setup)
    state, decisions, _ = walk(problem, Machine(robot, 1, scale_ppm=3000.0))
    assert state.screening.suspected and state.screening.p_stroke < 1e-6
    screened = state.screening.n_rows
    modes = [d.next.mode for d in decisions[screened:-1]]
    assert modes and set(modes) == {"diagnosis"}
    assert state.n_rows > run[1].n_rows
    assert "missing physics" in decisions[-1].stop.sentence or decisions[-1].stop.kind == "budget"
    assert state.noise.source.startswith("the geometric fit's residuals")


def test_bad_settings_and_rows_are_refused(robot, run):
    for bad in ({"max_measure_s": -1.0}, {"max_measure_s": 60.0, "target_mm": 0.0},
                {"max_measure_s": 60.0, "min_improvement": 1.5}, {"max_measure_s": 60.0, "speed": 1}):
        with pytest.raises(ValidationError):
            AdaptiveSettings(**bad)
    problem, state, _, _ = run
    with pytest.raises(ValueError, match="finite"):
        update(problem, state, robot.home, np.full(6, np.nan), robot.home)


def test_the_room_exports_the_adaptive_plan_without_importing_it_up_front():
    import subprocess
    import sys

    import hilcal.planning as planning

    assert all(hasattr(planning, name) for name in planning.__all__)
    assert planning.decide is decide and planning.AdaptiveSettings is AdaptiveSettings
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        planning.nothing  # noqa: B018
    probe = "import sys, hilcal.planning; print('hilcal.planning.sequential' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          check=True).stdout.strip() == "False"
