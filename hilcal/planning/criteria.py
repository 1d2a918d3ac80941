"""Gains of candidate poses for a sequential design: what adding one pose buys under each criterion.

Each function scores every candidate [C] at once from the current information and the candidates' Jacobians
[C, 6, p], using the matrix determinant lemma and the Woodbury identity (a rank-6 update per candidate) instead of
refactoring the information per candidate.
"""

from __future__ import annotations

import numpy as np


def _regularized_inverse(info: np.ndarray, ridge: float) -> np.ndarray:
    return np.linalg.inv(info + ridge * np.eye(len(info)))


def d_gain(info: np.ndarray, jacobians: np.ndarray, ridge: float) -> np.ndarray:
    """ln det(M + J_cᵀ J_c) - ln det(M) per candidate (D-optimality), M regularized by ridge·I."""
    inv = _regularized_inverse(info, ridge)
    S = np.eye(jacobians.shape[1]) + jacobians @ inv @ np.swapaxes(jacobians, -1, -2)
    return np.linalg.slogdet(S)[1]


def ds_gain(info: np.ndarray, jacobians: np.ndarray, n_nuisance: int, ridge: float) -> np.ndarray:
    """Gain in ln det of the information about the last p - n_nuisance terms once the first ones are fitted (Ds).

    det of that Schur complement = det M / det M_nuisance, so the gain is the D-gain of the whole model minus the
    D-gain of the nuisance block alone.
    """
    k = n_nuisance
    return d_gain(info, jacobians, ridge) - d_gain(info[:k, :k], jacobians[..., :k], ridge)


def v_gain(info: np.ndarray, jacobians: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """-ln(1 - fall / total) per candidate: the relative fall of sum_k trace(T_k M⁻¹ T_kᵀ) (I-optimality).

    targets [V, r, p]: the rows whose predicted variance is to fall (e.g. the verify poses' position rows). M must be
    nonsingular. With S_c = I + J_c M⁻¹ J_cᵀ, the fall is trace(S_c⁻¹ J_c M⁻¹ Tᵀ T M⁻¹ J_cᵀ).
    """
    inv = np.linalg.inv(info)
    T = targets.reshape(-1, info.shape[0])
    total = float(np.einsum("ij,jk,ik->", T, inv, T))
    K = jacobians @ inv @ T.T
    S = np.eye(jacobians.shape[1]) + jacobians @ inv @ np.swapaxes(jacobians, -1, -2)
    fall = np.einsum("cir,cir->c", K, np.linalg.solve(S, K))
    return -np.log(np.clip(1.0 - fall / total, 1e-300, None))
