"""Pose planning and machine time: which poses to measure and how long the machine takes to visit them.

Holds the D-optimal designs of the paper (``design``), the leg-move time model and route estimate
(``machine_time``), the least-time pose order and its drift confounding (``ordering``) and time-budgeted designs
(``budget``). May import the calibration math at the top of ``hilcal`` (robot, kinematics, error models,
workspace) and itself; never ``hilcal.discovery`` or ``hilcal.reports``.

A new planning rule (a design criterion, a motion constraint, an ordering heuristic) goes into the module of its
job here and is exported below if commands or procedures call it.
"""

from hilcal.planning.budget import BudgetError, budgeted_design, predicted_verify_error
from hilcal.planning.design import Design, coordinate_exchange, paper_pose_sets, verification_poses
from hilcal.planning.machine_time import MotionRules, MotionTiming, TimeEstimate, estimate_route
from hilcal.planning.ordering import RouteOrder, order_route

__all__ = [
    "BudgetError",
    "Design",
    "MotionRules",
    "MotionTiming",
    "RouteOrder",
    "TimeEstimate",
    "budgeted_design",
    "coordinate_exchange",
    "estimate_route",
    "order_route",
    "paper_pose_sets",
    "predicted_verify_error",
    "verification_poses",
]
