"""Calibrate from a recording: identify on the `measure` rows, judge accuracy on the `verify` rows.

The least-squares covariance carries the recording's measured noise and, when the residual exceeds it, the model's
misfit (``hilcal.misfit``): the noise is the robot file's `cmm.sphere_sigma_mm`, else the one the recording's
`sphere_fit_rms_mm` column shows, carried through the registration to every measured pose (``recording_noise``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hilcal.identification import IdentificationResult, identify, predict_poses
from hilcal.metrics import AccuracySummary
from hilcal.pose_measurement import sigma_from_sphere_fit, sphere_noise_covariance
from hilcal.recording import Recording, session_numbers
from hilcal.robot import Robot
from hilcal.stations import remove_frames


@dataclass(frozen=True)
class CalibrationOutcome:
    """An identification and the verification accuracy before and after it."""

    identification: IdentificationResult
    n_measure: int
    n_verify: int
    before: AccuracySummary | None
    after: AccuracySummary | None

    def to_json(self) -> dict[str, Any]:
        """The `hilcal identify --json` contract."""
        ident = self.identification
        out: dict[str, Any] = {
            "estimator": ident.estimator,
            "n_measure": self.n_measure,
            "n_verify": self.n_verify,
            "parameters": ident.parameters(),
            "before": self.before.brief() if self.before else None,
            "after": self.after.brief() if self.after else None,
            "model": ident.model,
            "formulation": ident.formulation,
            "method": ident.method,
            "converged": ident.converged,
            "max_residual_mm": ident.max_abs_residual,
            "rms_residual_mm": ident.rms_residual,
        }
        if ident.std_errors is not None:
            out["std_errors"] = {n: float(s) for n, s in zip(ident.names, ident.std_errors, strict=True)}
            out["sigma_mm"] = ident.sigma
        out["model_incomplete"] = None if ident.misfit is None else ident.misfit.incomplete
        out["misfit"] = None if ident.misfit is None else ident.misfit.to_json()
        return out


def verification_accuracy(
    rec: Recording, robot: Robot, ident: IdentificationResult | None
) -> tuple[AccuracySummary | None, AccuracySummary | None]:
    """Before (measured vs commanded) and after (measured vs calibrated prediction) on verify rows."""
    ver = rec.select("verify")
    if ver.n == 0:
        return None, None
    meas = ver.meas
    if ident is not None and ident.station_frames and ver.stations is not None:
        meas = remove_frames(meas, ver.stations, ident.station_frames, ident.length_mm, robot.home[:3])
    before = AccuracySummary.of(meas, ver.cmd) if not np.isnan(ver.cmd).any() else None
    after = None
    if ident is not None:
        after = AccuracySummary.of(meas, predict_poses(ident, robot, ver.legs_mm, meas))
    return before, after


def recording_noise(rec: Recording, robot: Robot) -> tuple[np.ndarray, float | None] | None:
    """The measured pose noise of every row [N, 6, 6] (residual metric) and its degrees of freedom (None: stated):
    from the robot file's sphere sigma, else the recording's sphere_fit_rms_mm column; None without either."""
    sigma, dof = robot.sphere_sigma_mm, None
    column = rec.extra.get("sphere_fit_rms_mm")
    if sigma is None and column is not None and column.dtype.kind == "f" and np.isfinite(column).sum() >= 3:
        sigma, dof = sigma_from_sphere_fit(column, robot)
    if sigma is None or not sigma > 0:
        return None
    return sphere_noise_covariance(robot, rec.meas, sigma, robot.characteristic_length_mm), dof


def stated_pose_noise(n_rows: int, robot: Robot, pose_sigma: tuple[float, float]) -> np.ndarray:
    """[n, 6, 6] pose noise in the residual metric from a stated standard deviation per position coordinate (mm) and
    per orientation axis (deg): an instrument that states its pose noise (a laser tracker's MPE through its
    registrations)."""
    position_mm, orientation_deg = pose_sigma
    spread = np.array([position_mm] * 3 + [np.radians(orientation_deg) * robot.characteristic_length_mm] * 3)
    return np.broadcast_to(np.diag(spread**2), (n_rows, 6, 6)).copy()


def calibrate(rec: Recording, robot: Robot, **identify_options: Any) -> CalibrationOutcome:
    """Identify on the measure rows (options as for `identify`) and evaluate on the verify rows; a least-squares fit
    of the 42-parameter model gets the recording's noise (``recording_noise``) unless the options give one."""
    mea = rec.select("measure")
    if mea.stations is not None and "stations" not in identify_options and identify_options.get("estimator",
                                                                                                 "ls") == "ls":
        identify_options = {**identify_options, "stations": mea.stations}
    if identify_options.get("estimator", "ls") == "ls" and "noise_covariance" not in identify_options:
        noise = recording_noise(rec, robot)
        if noise is not None:
            measure = rec.phase == "measure"
            identify_options = {**identify_options, "noise_covariance": noise[0][measure], "noise_dof": noise[1],
                                "sessions": session_numbers(rec.time_s)[measure]}
    ident = identify(robot, mea.legs_mm, mea.meas, **identify_options)
    before, after = verification_accuracy(rec, robot, ident)
    return CalibrationOutcome(ident, mea.n, rec.n - mea.n, before, after)
