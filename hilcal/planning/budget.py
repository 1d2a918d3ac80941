"""Time-budgeted calibration designs: the most informative measure poses whose route fits a time budget.

From a D-optimal measure design, backward elimination gives nested subsets (each step drops the pose whose
loss lowers det M least), so information grows with the number of poses and the best design within a
budget is the largest subset whose ordered route (``hilcal.planning.ordering``) fits. What the budget costs is said
two ways: D-efficiency against the full design, (det M_subset / det M_full)^(1/42), and the predicted
verification error: the least-squares parameter covariance sigma² M⁻¹ carried to the verify poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.kinematics import Geometry
from hilcal.planning.design import N_PARAMETERS, pose_jacobians
from hilcal.planning.machine_time import MotionRules, MotionTiming, TimeEstimate, calibration_phases, estimate_route
from hilcal.planning.ordering import RouteOrder, order_route
from hilcal.robot import Robot

MIN_MEASURE_POSES = 10
"""Fewest measure poses a budgeted design may have (7 make M nonsingular; 10 leave some redundancy)."""


class BudgetError(ValueError):
    """No design fits the time budget."""


@dataclass(frozen=True)
class PredictedError:
    """Expected identification error at the verify poses under pose noise sigma (root mean square over noise).

    rms_* are over the verify poses; max_position_mm is the largest per-pose expected position error.
    The CMM's own noise on the verify measurements adds to these in quadrature.
    """

    noise_mm: float
    rms_position_mm: float
    max_position_mm: float
    rms_orientation_deg: float


def predicted_verify_error(robot: Robot, measure_rows: np.ndarray, verify_poses: np.ndarray, noise_mm: float
                           ) -> PredictedError:
    """Linearized least-squares error propagation from the measure rows to the verify poses.

    Each measured pose component has standard deviation noise_mm (rotations as rad times the platform's
    characteristic length, as the forward LS fit weighs them), so cov(p) = noise² (AᵀA)⁻¹ with A the
    stacked (6n, 42) pose-error Jacobian, and the pose error at verify pose k has covariance J_k cov J_kᵀ.
    """
    A = pose_jacobians(robot, np.atleast_2d(measure_rows)).reshape(-1, N_PARAMETERS)
    cov = noise_mm**2 * np.linalg.inv(A.T @ A)
    Jv = pose_jacobians(robot, np.atleast_2d(verify_poses))
    C = Jv @ cov @ np.swapaxes(Jv, -1, -2)
    pos = np.trace(C[:, :3, :3], axis1=1, axis2=2)
    rot = np.trace(C[:, 3:, 3:], axis1=1, axis2=2) / robot.characteristic_length_mm**2
    return PredictedError(noise_mm, float(np.sqrt(pos.mean())), float(np.sqrt(pos.max())),
                          float(np.degrees(np.sqrt(rot.mean()))))


def _log_det(M: np.ndarray) -> np.ndarray:
    sign, logabs = np.linalg.slogdet(M)
    return np.where(sign > 0, logabs, -np.inf)


def elimination_order(robot: Robot, poses: np.ndarray, keep: int | None = None) -> np.ndarray:
    """Pose indices in the order backward elimination drops them (the first is the least informative).

    `keep` is never dropped. The last N_PARAMETERS // 6 + 1 entries are not ranked (they stay in the order
    given): fewer poses than that cannot make M nonsingular.
    """
    J = pose_jacobians(robot, np.atleast_2d(poses))
    G = np.swapaxes(J, -1, -2) @ J
    left = [k for k in range(len(poses)) if k != keep]
    M = G.sum(axis=0)
    dropped: list[int] = []
    floor = -(-N_PARAMETERS // 6)
    while len(left) + (keep is not None) > floor:
        ld = _log_det(M[None] - G[left])
        k = left.pop(int(np.argmax(ld)))
        M = M - G[k]
        dropped.append(k)
    return np.array(dropped + left + ([keep] if keep is not None else []), dtype=int)


@dataclass(frozen=True)
class BudgetOption:
    """One nested design: its measure poses (design order), ordered route, time and accuracy."""

    measure_index: np.ndarray
    """Indices into the full design, in design order."""
    route: RouteOrder
    estimate: TimeEstimate
    d_efficiency: float
    predicted: PredictedError

    @property
    def n_measure(self) -> int:
        return len(self.measure_index)


@dataclass(frozen=True)
class BudgetedDesign:
    """The chosen design (the largest nested subset that fits) and the options that were evaluated."""

    budget_s: float
    chosen: BudgetOption
    options: tuple[BudgetOption, ...]


def budgeted_design(robot: Robot, measure: np.ndarray, verify: np.ndarray, budget_s: float, rules: MotionRules,
                    timing: MotionTiming, *, repeat: int | None = None, repeats: int = 0, noise_mm: float = 0.005,
                    seed: int = 0, min_measure: int = MIN_MEASURE_POSES) -> BudgetedDesign:
    """The most informative nested subset of `measure` whose calibration route takes at most budget_s.

    `repeat` is the index of the pose measured `repeats` extra times in a row (kept in every subset). The
    route's time is the ordered route's estimate (motion, settle, probing) with `verify` measured twice.
    The number of poses is found by bisection (time grows with it); BudgetError if min_measure poses do
    not fit. The options are the full design, the chosen one and the smallest, evaluated the same way (the
    full design alone when it fits).
    """
    geom = Geometry.nominal(robot)
    M, V = np.atleast_2d(measure).astype(float), np.atleast_2d(verify).astype(float)
    if not min_measure <= len(M):
        raise ValueError(f"the design has {len(M)} measure poses, fewer than min_measure={min_measure}")
    order = elimination_order(robot, M, keep=repeat)
    full_rows = _rows(M, np.arange(len(M)), repeat, repeats)
    full_logdet = float(_log_det(_information(robot, full_rows)))
    cache: dict[int, BudgetOption] = {}

    def option(n: int) -> BudgetOption:
        if n not in cache:
            index = np.sort(order[len(M) - n:])
            counts = np.ones(n, dtype=int)
            if repeat is not None:
                counts[np.searchsorted(index, repeat)] += repeats
            sub = M[index]
            route = order_route(geom, robot.home, sub, V, rules, timing, measure_counts=counts, seed=seed)
            rows = np.repeat(sub[route.measure_order], counts[route.measure_order], axis=0)
            estimate = estimate_route(geom, robot.home, calibration_phases(rows, V[route.verify_order]), rules,
                                      timing, robot.home)
            d_eff = float(np.exp((float(_log_det(_information(robot, rows))) - full_logdet) / N_PARAMETERS))
            cache[n] = BudgetOption(index, route, estimate, d_eff, predicted_verify_error(robot, rows, V, noise_mm))
        return cache[n]

    lo, hi = min_measure, len(M)
    if option(hi).estimate.total_s <= budget_s:
        return BudgetedDesign(budget_s, cache[hi], (cache[hi],))
    if option(lo).estimate.total_s > budget_s:
        raise BudgetError(f"even {lo} measure and {len(V)} verify poses take "
                          f"{option(lo).estimate.total_s / 60:.1f} min, over the budget of {budget_s / 60:.1f} min")
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if option(mid).estimate.total_s <= budget_s:
            lo = mid
        else:
            hi = mid - 1
    option(len(M))
    options = tuple(cache[n] for n in sorted({len(M), lo, min_measure}, reverse=True))
    return BudgetedDesign(budget_s, cache[lo], options)


def _rows(M: np.ndarray, index: np.ndarray, repeat: int | None, repeats: int) -> np.ndarray:
    counts = np.ones(len(index), dtype=int)
    if repeat is not None and repeat in index:
        counts[list(index).index(repeat)] += repeats
    return np.repeat(M[index], counts, axis=0)


def _information(robot: Robot, rows: np.ndarray) -> np.ndarray:
    J = pose_jacobians(robot, rows)
    return np.einsum("kij,kil->jl", J, J)
