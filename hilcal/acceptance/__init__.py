"""Acceptance of a calibrated machine: the ISO 9283 pose accuracy and repeatability test, the uncertainty of the
certificate's figures (GUM, k = 2) and the verdict against the station's limits (ISO 14253-1 decision rule).

Holds the test cube, the poses P1-P5 and AP/RP by the standard's definitions (``iso9283``), the uncertainty of
every figure by seeded Monte Carlo from the CMM's stated uncertainty and the run's repeated poses
(``uncertainty``), AP and RP per test pose with their uncertainties (``evaluation``) and the verdict (``verdict``).
May import the calibration math at the top of ``hilcal`` and ``hilcal.planning``; ``hilcal.reports`` may import it.
"""

from hilcal.acceptance.evaluation import IsoPoseResult, evaluate_iso9283, limit_figures
from hilcal.acceptance.iso9283 import (
    CYCLE_ORDER,
    DEFAULT_CYCLES,
    POSE_NAMES,
    IsoCube,
    PoseCharacteristics,
    cycle_route,
    iso_poses,
    largest_cube,
    pose_characteristics,
)
from hilcal.acceptance.uncertainty import (
    K_COVERAGE,
    Figure,
    ModelUncertainty,
    accuracy_figures,
    cmm_pose_covariance,
    model_uncertainty,
    pooled_covariance,
    repeated_groups,
)
from hilcal.acceptance.verdict import LIMITS, NO_LIMITS, RULES, LimitCheck, check_limits, decide, overall

__all__ = [
    "CYCLE_ORDER",
    "DEFAULT_CYCLES",
    "K_COVERAGE",
    "LIMITS",
    "NO_LIMITS",
    "POSE_NAMES",
    "RULES",
    "Figure",
    "IsoCube",
    "IsoPoseResult",
    "LimitCheck",
    "ModelUncertainty",
    "PoseCharacteristics",
    "accuracy_figures",
    "check_limits",
    "cmm_pose_covariance",
    "cycle_route",
    "decide",
    "evaluate_iso9283",
    "iso_poses",
    "largest_cube",
    "limit_figures",
    "model_uncertainty",
    "overall",
    "pooled_covariance",
    "pose_characteristics",
    "repeated_groups",
]
