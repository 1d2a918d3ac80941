"""Turn identified errors into controller parameters: the full geometry, or the best six leg offsets.

Controller parameters are a (platform joints), b (base joints) and l0 (stroke-zero length per leg), all
mm. The controller reports length = stroke + l0; identification found geometric = reported + dl0, so
the true stroke-zero length is l0 + dl0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from hilcal.error_models import GEOMETRIC_42, pose_difference
from hilcal.identification import IdentificationResult
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.leg_compensation import LegCompensation
from hilcal.metrics import AccuracySummary
from hilcal.robot import Robot


@dataclass(frozen=True)
class ControllerGeometry:
    """The parameter set a controller holds (mm)."""

    a: np.ndarray
    b: np.ndarray
    l0: np.ndarray

    def ik_geometry(self) -> Geometry:
        """Geometry for host-side inverse kinematics in controller units (setpoint = stroke + l0)."""
        return Geometry(self.a, self.b)


@dataclass(frozen=True)
class OutOfReach:
    """A pose the controller cannot drive to with a parameter set (and block): a leg's raw stroke outside its travel."""

    index: int
    leg: int
    stroke_mm: float
    min_mm: float
    max_mm: float

    def sentence(self, what: str) -> str:
        side = f"above its {self.max_mm:.3f} mm" if self.stroke_mm > self.max_mm else f"below its {self.min_mm:.3f} mm"
        return (f"{what} {self.index + 1} is beyond leg {self.leg + 1}'s travel with the new parameters: it needs a "
                f"raw stroke of {self.stroke_mm:.3f} mm, {side}")


def out_of_reach(robot: Robot, geometry: ControllerGeometry, comp: LegCompensation | None, poses: np.ndarray,
                 approach_mm: float = 0.0) -> list[OutOfReach]:
    """Poses [N, 6] whose setpoints under `geometry` (and the block `comp`, approached with every leg extending
    from approach_mm below) need a raw stroke outside the legs' travel, the robot's leg limits less its nominal l0
    (docs/protocols.md: the limits apply to the raw stroke). One entry per pose, for its worst leg."""
    q = np.atleast_2d(np.asarray(poses, dtype=float))
    if not len(q):
        return []
    lengths = inverse_kinematics(geometry.ik_geometry(), q)
    if comp is None or comp.is_zero:
        strokes = lengths - geometry.l0
    else:
        strokes = comp.raw_strokes_mm(lengths, geometry.l0, direction=np.ones_like(lengths))
    l0_nominal = np.asarray(robot.l0, dtype=float)
    lo, hi = robot.leg_limits[0] - l0_nominal, robot.leg_limits[1] - l0_nominal
    over = np.maximum(strokes - hi, lo - (strokes - approach_mm))
    found = []
    for k in np.flatnonzero((over > 0).any(axis=1)):
        leg = int(np.argmax(over[k]))
        found.append(OutOfReach(int(k), leg, float(strokes[k, leg]), float(lo[leg]), float(hi[leg])))
    return found


@dataclass(frozen=True)
class Compensation:
    mode: str
    parameters: ControllerGeometry
    predicted: AccuracySummary
    uncompensated: AccuracySummary | None


def _true_geometry(robot: Robot, errors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = np.asarray(errors, dtype=float)[:42].reshape(6, 7)
    return robot.a + d[:, 0:3], robot.b + d[:, 3:6], d[:, 6]


def reached_poses(robot: Robot, before: ControllerGeometry, errors: np.ndarray, after: ControllerGeometry,
                  poses: np.ndarray) -> np.ndarray:
    """Where the calibrated model (its 42 errors) puts the platform when a controller holding `after` commands
    `poses`, the readings' zero being `before`'s."""
    a_true, b_true, dl0 = _true_geometry(robot, errors)
    setpoints = inverse_kinematics(after.ik_geometry(), poses)
    return forward_kinematics(Geometry(a_true, b_true), setpoints - after.l0 + before.l0 + dl0, poses)


def predicted_accuracy(robot: Robot, before: ControllerGeometry, errors: np.ndarray,
                       after: ControllerGeometry, poses: np.ndarray) -> AccuracySummary:
    """Pose error the calibrated model (its 42 errors) predicts when a controller with `after` commands `poses`."""
    return AccuracySummary.of(reached_poses(robot, before, errors, after, poses), poses)


def held_out_after(robot: Robot, before: ControllerGeometry, errors: np.ndarray, after: ControllerGeometry,
                   legs_mm: np.ndarray, measured: np.ndarray, commanded: np.ndarray) -> AccuracySummary:
    """The pose error a controller holding `after` predicts when it commands held-out poses again (rows read with
    `before`: their leg readings, measured and commanded poses): the model's pose for the new setpoints plus the
    model's misfit at each row as measured, which no fit used. With the full geometry uploaded this is the misfit
    alone; with the leg offsets alone, what the joint positions the controller cannot hold leave is added."""
    a_true, b_true, dl0 = _true_geometry(robot, errors)
    q, meas = np.atleast_2d(np.asarray(commanded, dtype=float)), np.atleast_2d(np.asarray(measured, dtype=float))
    misfit = meas - forward_kinematics(Geometry(a_true, b_true), np.atleast_2d(legs_mm) + dl0, meas)
    return AccuracySummary.of(reached_poses(robot, before, errors, after, q) + misfit, q)


def compensate(robot: Robot, before: ControllerGeometry, ident: IdentificationResult | np.ndarray,
               offsets_only: bool, sample_poses: np.ndarray) -> Compensation:
    """Parameters to upload for an identification (or its 42 geometric errors), and the accuracy that model
    predicts over `sample_poses`.

    With offsets only, a and b stay as they are and l0 minimizes the predicted pose errors (position in
    mm, rotation as mm at the platform radius) over the samples; what remains is reported as uncompensated.
    """
    errors = ident.x[:42] if isinstance(ident, IdentificationResult) else np.asarray(ident, dtype=float)[:42]
    a_true, b_true, dl0 = _true_geometry(robot, errors)
    full = ControllerGeometry(a_true, b_true, before.l0 + dl0)
    if not offsets_only:
        return Compensation("full", full, predicted_accuracy(robot, before, errors, full, sample_poses), None)
    lc = robot.characteristic_length_mm

    def residual(l0: np.ndarray) -> np.ndarray:
        candidate = ControllerGeometry(before.a, before.b, l0)
        setpoints = inverse_kinematics(candidate.ik_geometry(), sample_poses)
        reached = forward_kinematics(Geometry(a_true, b_true), setpoints - l0 + before.l0 + dl0, sample_poses)
        return pose_difference(reached, sample_poses, lc).ravel()

    best = least_squares(residual, before.l0 + dl0, method="lm").x
    offsets = ControllerGeometry(before.a, before.b, best)
    predicted = predicted_accuracy(robot, before, errors, offsets, sample_poses)
    return Compensation("offsets_only", offsets, predicted, predicted)


def bound_violations(errors: np.ndarray, joint_bound_mm: float = 10.0, offset_bound_mm: float = 20.0) -> list[str]:
    """The 42 geometric errors beyond physically plausible bounds (joint errors, leg-offset errors), as reasons."""
    problems = []
    for name, value in zip(GEOMETRIC_42.names, np.asarray(errors, dtype=float)[:42], strict=True):
        bound = offset_bound_mm if name.endswith("dl0_mm") else joint_bound_mm
        if not abs(value) <= bound:
            problems.append(f"{name} = {value:+.3f} mm exceeds the plausible ±{bound} mm")
    return problems


def plausibility(ident: IdentificationResult, joint_bound_mm: float = 10.0, offset_bound_mm: float = 20.0
                 ) -> list[str]:
    """Reasons to refuse an identified set: non-convergence, or errors beyond physically plausible bounds."""
    problems = [] if ident.converged else [f"identification did not converge: {ident.message}"]
    problems += bound_violations(ident.x[:42], joint_bound_mm, offset_bound_mm)
    if ident.std_errors is not None:
        bad = [n for n, s in zip(ident.names[:42], ident.std_errors[:42], strict=True) if not np.isfinite(s)]
        if bad:
            problems.append(f"undetermined parameters: {', '.join(bad)}")
    return problems
