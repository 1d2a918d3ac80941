"""Pose-error metrics: position error norm (mm), orientation error angle (deg), and the paper's Table 7 indicators."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from hilcal.error_models import rotation_vector
from hilcal.kinematics import split_pose


def pose_errors(measured: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pose position error |t_m - t_r| (mm) and orientation error angle(R_m R_r^T) (deg)."""
    Rm, tm = split_pose(measured)
    Rr, tr = split_pose(reference)
    position = np.linalg.norm(tm - tr, axis=-1)
    angle = np.linalg.norm(rotation_vector(Rm @ np.swapaxes(Rr, -1, -2)), axis=-1)
    return position, np.degrees(angle)


@dataclass(frozen=True)
class Indicators:
    """The four indicators of the paper's Table 7 for one error series."""

    max: float
    range: float
    mean: float
    rms: float

    @classmethod
    def of(cls, errors: np.ndarray) -> Indicators:
        e = np.asarray(errors, dtype=float)
        return cls(float(e.max()), float(e.max() - e.min()), float(e.mean()), float(np.sqrt(np.mean(e**2))))


@dataclass(frozen=True)
class AccuracySummary:
    """Position (mm) and orientation (deg) indicators over a set of poses."""

    position_mm: Indicators
    orientation_deg: Indicators
    n_poses: int

    @classmethod
    def of(cls, measured: np.ndarray, reference: np.ndarray) -> AccuracySummary:
        pos, ori = pose_errors(measured, reference)
        return cls(Indicators.of(pos), Indicators.of(ori), int(pos.size))

    def brief(self) -> dict[str, float]:
        """The four headline numbers used by the CLI JSON contract."""
        return {
            "max_position_mm": self.position_mm.max,
            "rms_position_mm": self.position_mm.rms,
            "max_orientation_deg": self.orientation_deg.max,
            "rms_orientation_deg": self.orientation_deg.rms,
        }

    def full(self) -> dict[str, dict[str, float]]:
        return {"position_mm": asdict(self.position_mm), "orientation_deg": asdict(self.orientation_deg)}
