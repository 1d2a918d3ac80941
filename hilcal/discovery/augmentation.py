"""Extra poses that would pin down a poorly determined term: greedy Ds-optimal augmentation of a recording.

Given the information the recorded poses already carry about a model (geometry plus effect terms), each
candidate pose adds a rank-6 update. The pose chosen next is the one that most shrinks the determinant of
the covariance of the terms of interest (Ds-optimality), updated in closed form (Woodbury), so a pool of
a thousand candidates costs milliseconds per pick.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hilcal.discovery.context import EffectContext
from hilcal.error_models import forward_jacobian
from hilcal.kinematics import Geometry
from hilcal.robot import Robot
from hilcal.workspace import random_poses

POOL_SIZE = 1000
MAX_EXTRA_POSES = 24
RIDGE = 1e-9


@dataclass(frozen=True)
class Augmentation:
    """Proposed poses (mm, deg) in the order to add them, and the predicted band after each addition."""

    poses: np.ndarray
    predicted_band_mm: np.ndarray
    reached_target: bool


def candidate_jacobians(robot: Robot, geometry: Geometry, poses: np.ndarray, length_mm: float,
                        phi: Callable[[EffectContext], np.ndarray]) -> np.ndarray:
    """Model Jacobian rows [C, 6, 42 + q] at planned poses: geometry and effect columns (effect via dl0)."""
    D = forward_jacobian(geometry, poses, length_mm)
    effect = np.einsum("cal,clq->caq", D[..., [7 * i + 6 for i in range(6)]], phi(EffectContext.at_poses(robot, poses)))
    return np.concatenate([D, effect], axis=2)


def candidate_pool(robot: Robot, seed: int) -> np.ndarray:
    """The seeded pool of feasible poses the augmentation picks from (the same for every term of one model)."""
    return random_poses(robot, POOL_SIZE, np.random.default_rng(seed))


def augment(robot: Robot, geometry: Geometry, length_mm: float, information: np.ndarray, sigma2: float,
            phi: Callable[[EffectContext], np.ndarray], block: np.ndarray, band_of: Callable[[np.ndarray], float],
            target_band_mm: float, seed: int = 0, geometry_scale: np.ndarray | None = None,
            candidates: tuple[np.ndarray, np.ndarray] | None = None) -> Augmentation:
    """Greedy Ds-optimal poses for the parameters `block` until `band_of(cov_block)` <= target (or the cap).

    `information` is J^T J of the recorded measure rows for the full parameter vector (geometry first),
    `sigma2` the residual variance, `phi` the effect regressors of the whole model. When the parameters were
    scaled (J / scale, so that units as different as mm and ppm invert well), `geometry_scale` divides the geometry
    columns of the candidates the same way (and `phi` returns the scaled effect regressors). `candidates`: the pool
    (`candidate_pool(robot, seed)`) and its `candidate_jacobians` when several terms of one model are augmented.
    """
    if candidates is None:
        pool = candidate_pool(robot, seed)
        Jc = candidate_jacobians(robot, geometry, pool, length_mm, phi)
    else:
        pool, Jc = candidates[0], candidates[1].copy()
    if geometry_scale is not None:
        Jc[..., :42] /= geometry_scale
    p = information.shape[0]
    C = sigma2 * np.linalg.pinv(information + RIDGE * np.trace(information) / p * np.eye(p))
    chosen: list[int] = []
    bands: list[float] = []
    available = np.ones(len(pool), dtype=bool)
    A = Jc @ C
    for _ in range(MAX_EXTRA_POSES):
        S = sigma2 * np.eye(6) + A @ np.swapaxes(Jc, 1, 2)
        Ab = A[:, :, block]
        K = np.linalg.solve(S, Ab)
        reduced = C[np.ix_(block, block)] - np.swapaxes(Ab, 1, 2) @ K
        sign, logdet = np.linalg.slogdet(reduced)
        score = np.where((sign > 0) & available, logdet, np.inf)
        best = int(np.argmin(score))
        if not np.isfinite(score[best]):
            break
        gain = np.linalg.solve(S[best], A[best])
        C = C - A[best].T @ gain
        A -= (Jc @ A[best].T) @ gain  # = Jc @ C with the new C, at a fraction of the cost
        available[best] = False
        chosen.append(best)
        bands.append(band_of(C[np.ix_(block, block)]))
        if bands[-1] <= target_band_mm:
            break
    return Augmentation(pool[chosen], np.array(bands), bool(bands) and bands[-1] <= target_band_mm)
