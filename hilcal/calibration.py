"""Calibrate from a recording: identify on the `measure` rows, judge accuracy on the `verify` rows."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hilcal.identification import IdentificationResult, identify, predict_poses
from hilcal.metrics import AccuracySummary
from hilcal.recording import Recording
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


def calibrate(rec: Recording, robot: Robot, **identify_options: Any) -> CalibrationOutcome:
    """Identify on the measure rows (options as for `identify`) and evaluate on the verify rows."""
    mea = rec.select("measure")
    if mea.stations is not None and "stations" not in identify_options and identify_options.get("estimator",
                                                                                                 "ls") == "ls":
        identify_options = {**identify_options, "stations": mea.stations}
    ident = identify(robot, mea.legs_mm, mea.meas, **identify_options)
    before, after = verification_accuracy(rec, robot, ident)
    return CalibrationOutcome(ident, mea.n, rec.n - mea.n, before, after)
