"""Drift across calibrations, on simulated histories: each calibration is a real identification of a recording
made here from a true geometry (hilcal's kinematics, CMM noise added), with changes planted in the true geometry,
never in the identified parameters."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from hilcal.drift import THRESHOLD_MM, Calibration, describe, drift, machine_parameters
from hilcal.identification import identify
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import Robot
from tests.poses import feasible_random_poses

N_POSES = 36
POSITION_NOISE_MM = 0.003
ANGLE_NOISE_DEG = 0.0002


@dataclass
class Machine:
    """A machine whose true errors (42, per leg [da, db, dl0]) are fixed unless a test changes them."""

    robot: Robot
    errors: np.ndarray
    rng: np.random.Generator

    def calibrate(self, run: int, day: int, errors: np.ndarray | None = None, controller_shift_mm: np.ndarray | None
                  = None) -> Calibration:
        """One calibration: measure N_POSES poses, identify, and the machine's geometry with standard errors.

        `controller_shift_mm`: how far the controller's l0 was moved by an earlier upload (it reads each leg that
        much longer, so the identified offset comes out that much smaller)."""
        true = (self.errors if errors is None else errors).copy()
        shift = np.zeros(6) if controller_shift_mm is None else controller_shift_mm
        true[6::7] -= shift
        poses = feasible_random_poses(self.robot, N_POSES, self.rng)
        legs = inverse_kinematics(Geometry.nominal(self.robot).perturbed(true), poses)
        noise = np.concatenate([self.rng.normal(0, POSITION_NOISE_MM, (N_POSES, 3)),
                                self.rng.normal(0, ANGLE_NOISE_DEG, (N_POSES, 3))], axis=1)
        ident = identify(self.robot, legs, poses + noise)
        params = machine_parameters(self.robot, ident, self.robot.l0 + shift)
        time = (datetime(2026, 1, 1, 8, tzinfo=UTC) + timedelta(days=day)).isoformat()
        return Calibration(f"run{run:02d}", time, {k: v for k, (v, _) in params.items()},
                           {k: s for k, (_, s) in params.items()})


def machine(robot: Robot, seed: int) -> Machine:
    rng = np.random.default_rng(seed)
    return Machine(robot, rng.normal(0.0, 0.5, 42), rng)


def history(m: Machine, n: int = 20, step_at: int | None = None, step: np.ndarray | None = None,
            days_apart: int = 14) -> list[Calibration]:
    out = []
    for j in range(n):
        errors = m.errors + (step if step is not None and step_at is not None and j >= step_at else 0.0)
        out.append(m.calibrate(j, j * days_apart, errors))
    return out


def leg_offset_step(leg: int, mm: float) -> np.ndarray:
    """A transducer zero that moved: leg `leg`'s true offset changes by `mm`."""
    step = np.zeros(42)
    step[7 * (leg - 1) + 6] = mm
    return step


def test_a_planted_0p1_mm_step_in_20_calibrations_is_flagged_with_its_date_and_nothing_else(robot):
    m = machine(robot, 1)
    cals = history(m, step_at=10, step=leg_offset_step(3, 0.1))
    result = drift(cals, "paper-table1/DMS-1")
    assert [p.name for p in result.flagged] == ["leg3_stroke_at_home_mm"]
    p = result.flagged[0]
    # the true offset grew 0.1 mm, so the transducer reads 0.1 mm less at the home pose
    assert p.flag == "step" and p.step_mm == pytest.approx(-0.1, abs=0.01)
    assert p.times[p.step_index] == cals[10].time and abs(p.step_sigma) > 10
    (sentence,) = result.sentences()
    assert sentence.startswith(f"leg 3 stroke at home -0.10 mm since {cals[10].time[:10]}, ")
    assert "transducer or joint moved" in sentence
    # the offset alone is not determined well enough to see it (its estimate correlates with the joint along the leg)
    assert result.parameter("leg3_l0_mm").std_mm.mean() > 20 * p.std_mm.mean()


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_twenty_calibrations_without_a_change_flag_nothing(robot, seed):
    result = drift(history(machine(robot, seed)), "m")
    assert result.n_calibrations == 20 and len(result.parameters) == 48
    assert result.flagged == () and result.flagged_since_last == ()
    # the raw split statistics of 48 parameters do reach ~3σ by chance: the correction is what keeps them quiet
    assert max(abs(p.step_sigma) for p in result.parameters) > 2.0


def test_the_stated_threshold_keeps_a_tiny_but_certain_change_quiet(robot):
    cals = history(machine(robot, 5), step_at=10, step=leg_offset_step(2, 0.03))
    p = drift(cals, "m").parameter("leg2_stroke_at_home_mm")
    assert abs(p.step_sigma) > 6 and p.flag is None  # certain (many σ) but below 0.05 mm
    assert THRESHOLD_MM == 0.05
    finer = drift(cals, "m", threshold_mm=0.02)
    assert [q.name for q in finer.flagged] == ["leg2_stroke_at_home_mm"]


def test_an_upload_between_calibrations_is_not_drift(robot):
    m = machine(robot, 6)
    before = m.calibrate(0, 0)
    after_upload = m.calibrate(1, 14, controller_shift_mm=np.array([0.8, -0.5, 0.3, 0.0, 1.2, -0.9]))
    result = drift([before, after_upload], "m")
    assert result.flagged_since_last == () and result.flagged == ()
    p = result.parameter("leg5_l0_mm")
    assert abs(p.since_last_mm) < 3 * np.hypot(*p.std_mm)


def test_the_last_calibration_against_the_previous_one(robot):
    m = machine(robot, 7)
    cals = [*history(m, n=6), m.calibrate(6, 6 * 14, m.errors + leg_offset_step(6, -0.2))]
    result = drift(cals, "m")
    (moved,) = result.flagged_since_last
    assert moved.name == "leg6_stroke_at_home_mm" and moved.since_last_mm == pytest.approx(0.2, abs=0.015)
    (sentence,) = result.to_json()["since_last"]
    assert sentence.startswith(f"leg 6 stroke at home {moved.since_last_mm:+.3f} mm since the previous calibration "
                               f"({cals[-2].time[:10]})")


def test_a_creeping_offset_is_reported_per_month(robot):
    m = machine(robot, 8)
    cals = [m.calibrate(j, 30 * j, m.errors + leg_offset_step(4, 0.02 * j)) for j in range(12)]
    p = drift(cals, "m").parameter("leg4_stroke_at_home_mm")
    assert p.flag == "creep" and p.slope_mm_per_month == pytest.approx(-0.02, abs=0.003)
    assert "creeps -0.02" in p.sentence and "per month" in p.sentence


def test_understated_standard_errors_are_widened_instead_of_flagging_noise(robot):
    cals = history(machine(robot, 9))
    shrunk = [Calibration(c.run_id, c.time, c.values, {k: 0.1 * s for k, s in c.std.items()}) for c in cals]
    result = drift(shrunk, "m")
    assert result.flagged == ()
    assert min(p.birge_ratio for p in result.parameters) > 5  # the scatter says the errors are ~10x too small


def test_fewer_than_two_calibrations_and_bad_input():
    one = Calibration("r", "2026-01-01T00:00:00+00:00", {"leg1_l0_mm": 1.0}, {"leg1_l0_mm": 0.1})
    assert drift([one], "m").parameters == () and drift([], "m").n_calibrations == 0
    without_std = Calibration("s", "2026-02-01T00:00:00+00:00", {"leg1_l0_mm": 1.2}, {"leg1_l0_mm": None})
    assert drift([one, without_std], "m").skipped == ("leg1_l0_mm",)
    with pytest.raises(ValueError, match="threshold_mm"):
        drift([one], "m", threshold_mm=float("nan"))
    assert describe("leg4_b_z_mm") == ("leg 4 base joint z", "the base joint of leg 4 moved (loose mount, wear, "
                                                              "a knock)")


def test_a_transducer_scale_that_grows_between_calibrations_is_named_as_failing() -> None:
    """Each leg's reading error at full stroke (from the scale the run's diagnosis estimated) drifts like the joints:
    leg 2's transducer reads 300 ppm long for five calibrations, then 650 ppm (a failing magnetostrictive wire)."""
    from hilcal.drift import reading_scale_parameters

    rng = np.random.default_rng(3)
    cals = []
    for j in range(8):
        truth = np.array([20.0, 300.0 if j < 5 else 650.0, -40.0, 0.0, 10.0, 5.0])
        params = reading_scale_parameters(truth + rng.normal(0, 3.0, 6), np.full(6, 3.0), 1000.0)
        time = (datetime(2026, 1, 1, tzinfo=UTC) + timedelta(days=30 * j)).isoformat()
        cals.append(Calibration(f"run{j}", time, {k: v for k, (v, _) in params.items()},
                                {k: s for k, (_, s) in params.items()}))
    result = drift(cals, "m")
    assert [p.name for p in result.flagged] == ["leg2_reads_long_at_full_stroke_mm"]
    flagged = result.flagged[0]
    assert flagged.flag == "step" and flagged.step_mm == pytest.approx(0.35, abs=0.02)
    assert "failing transducer" in flagged.sentence and "leg 2 reading at full stroke" in flagged.sentence
