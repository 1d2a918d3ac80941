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
class Compensation:
    mode: str
    parameters: ControllerGeometry
    predicted: AccuracySummary
    uncompensated: AccuracySummary | None


def _true_geometry(robot: Robot, errors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = np.asarray(errors, dtype=float)[:42].reshape(6, 7)
    return robot.a + d[:, 0:3], robot.b + d[:, 3:6], d[:, 6]


def predicted_accuracy(robot: Robot, before: ControllerGeometry, errors: np.ndarray,
                       after: ControllerGeometry, poses: np.ndarray) -> AccuracySummary:
    """Pose error the calibrated model (its 42 errors) predicts when a controller with `after` commands `poses`."""
    a_true, b_true, dl0 = _true_geometry(robot, errors)
    setpoints = inverse_kinematics(after.ik_geometry(), poses)
    geometric = setpoints - after.l0 + before.l0 + dl0
    reached = forward_kinematics(Geometry(a_true, b_true), geometric, poses)
    return AccuracySummary.of(reached, poses)


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
