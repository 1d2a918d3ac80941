"""Pose planning and machine time: which poses to measure and how long the machine takes to visit them.

Holds the D-optimal designs of the paper (``design``), the leg-move time model and route estimate
(``machine_time``), the least-time pose order and its drift confounding (``ordering``), time-budgeted designs
(``budget``) and the sequential (adaptive) plan that measures until the accuracy is proven (``sequential``, with its
``candidates``, design ``criteria``, verify-error ``prediction``, ``stopping`` rule and time ``forecast``). May
import the calibration math at the top of ``hilcal`` (robot, kinematics, error models, workspace, identification)
and itself; never ``hilcal.discovery`` or ``hilcal.reports``.

A new planning rule (a design criterion, a motion constraint, an ordering heuristic) goes into the module of its
job here and is exported below if commands or procedures call it.
"""

import importlib

from hilcal.planning.budget import BudgetError, budgeted_design, predicted_verify_error
from hilcal.planning.design import Design, coordinate_exchange, paper_pose_sets, verification_poses
from hilcal.planning.machine_time import MotionRules, MotionTiming, TimeEstimate, estimate_route
from hilcal.planning.ordering import RouteOrder, order_route

_ADAPTIVE = {
    "hilcal.planning.forecast": ("Forecast", "TimeRange", "forecast", "time_range"),
    "hilcal.planning.prediction": ("PoseNoise", "VerifyPrediction"),
    "hilcal.planning.sequential": ("AdaptiveProblem", "AdaptiveSettings", "AdaptiveState", "Decision", "PoseChoice",
                                   "adaptive_problem", "decide", "next_pose", "replay", "start", "update"),
    "hilcal.planning.stopping": ("DiagnosisMinimum", "Screening", "StopReason"),
}
"""The adaptive plan's names, imported on first use: they need scipy.optimize (identification), which would add
about half a second to every command that only builds or checks a fixed plan."""


def __getattr__(name: str) -> object:
    for module, names in _ADAPTIVE.items():
        if name in names:
            return getattr(importlib.import_module(module), name)
    raise AttributeError(f"module 'hilcal.planning' has no attribute {name!r}")


__all__ = [
    "AdaptiveProblem",
    "AdaptiveSettings",
    "AdaptiveState",
    "BudgetError",
    "Decision",
    "Design",
    "DiagnosisMinimum",
    "Forecast",
    "MotionRules",
    "MotionTiming",
    "PoseChoice",
    "PoseNoise",
    "RouteOrder",
    "Screening",
    "StopReason",
    "TimeEstimate",
    "TimeRange",
    "VerifyPrediction",
    "adaptive_problem",
    "budgeted_design",
    "coordinate_exchange",
    "decide",
    "estimate_route",
    "forecast",
    "next_pose",
    "order_route",
    "paper_pose_sets",
    "predicted_verify_error",
    "replay",
    "start",
    "time_range",
    "update",
    "verification_poses",
]
