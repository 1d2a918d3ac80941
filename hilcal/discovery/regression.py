"""Linear-algebra pieces of the diagnosis: bases, per-pose whitening, leave-one-cluster-out residuals, robust SEs.

Residual vectors are stacked per pose ([6N]: six pose components per measured pose); a cluster is a set of
poses whose residuals are left out together (one pose, or all repeats of one pose).
"""

from __future__ import annotations

import numpy as np

MAX_CONDITION = 1e10
"""A left-out cluster that the model fits exactly (leverage 1) cannot be predicted: its residual is infinite."""


def orth(A: np.ndarray, rel_tol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the column space of A (columns scaled first, tiny singular values dropped)."""
    if A.shape[1] == 0:
        return A
    norms = np.linalg.norm(A, axis=0)
    keep = norms > 0
    if not keep.any():
        return A[:, :0]
    U, s, _ = np.linalg.svd(A[:, keep] / norms[keep], full_matrices=False)
    return U[:, s > s[0] * rel_tol] if s.size and s[0] > 0 else A[:, :0]


def leverage_adjusted(r: np.ndarray, Q: np.ndarray, n_poses: int) -> np.ndarray:
    """Per-pose residuals [N, 6] scaled by (I - H_cc)^-1/2 (CR2), undoing the shrinkage of fitted residuals."""
    rc = r.reshape(n_poses, 6)
    Qc = Q.reshape(n_poses, 6, -1)
    w, V = np.linalg.eigh(np.eye(6) - Qc @ np.swapaxes(Qc, 1, 2))
    scaled = np.einsum("nji,nj->ni", V, rc) / np.sqrt(np.clip(w, 1e-6, None))
    return np.einsum("nij,nj->ni", V, scaled)


def pooled_whitener(r: np.ndarray, J: np.ndarray, n_poses: int) -> np.ndarray:
    """Inverse square root (6 x 6) of the pooled within-pose residual covariance, leverage-corrected.

    A CMM measures the six pose components with unequal and correlated noise (it depends on the sphere
    layout); whitening makes the F statistics and the bootstrap compare like with like.
    """
    adjusted = leverage_adjusted(r, orth(J), n_poses)
    cov = adjusted.T @ adjusted / n_poses
    w, V = np.linalg.eigh(cov)
    return V @ np.diag(1.0 / np.sqrt(np.clip(w, w.max() * 1e-12, None))) @ V.T


def whiten(A: np.ndarray, W: np.ndarray, n_poses: int) -> np.ndarray:
    """Apply the per-pose whitener to stacked residuals [6N] or Jacobian columns [6N, k]."""
    shaped = A.reshape(n_poses, 6, -1)
    return np.einsum("ij,cjk->cik", W, shaped).reshape(A.shape)


def clusters_from_labels(labels: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Split pose labels into single poses and multi-pose clusters (repeats): (singles, [pose indices])."""
    labels = np.asarray(labels)
    _, inverse, counts = np.unique(labels, return_inverse=True, return_counts=True)
    singles = np.flatnonzero(counts[inverse] == 1)
    multi = [np.flatnonzero(inverse == k) for k in np.flatnonzero(counts > 1)]
    return singles, multi


class LeaveOneOut:
    """Exact leave-one-cluster-out residuals of linear least squares r0 + Q d for a fixed base model.

    The base model's basis Q (orthonormal, [6N, p]) is fixed; `press` adds an orthonormal block Qk that is
    orthogonal to Q. Residuals of a left-out cluster c are e_c = (I - H_cc)^-1 (r - H r)_c.
    """

    def __init__(self, Q: np.ndarray, n_poses: int, cluster_labels: np.ndarray) -> None:
        self.n = n_poses
        self.Q = Q
        self.singles, self.multi = clusters_from_labels(cluster_labels)
        Qc = Q.reshape(n_poses, 6, -1)
        self.H_single = Qc[self.singles] @ np.swapaxes(Qc[self.singles], 1, 2)
        self.multi_rows = [np.concatenate([np.arange(6 * p, 6 * p + 6) for p in poses]) for poses in self.multi]
        self.H_multi = [Q[rows] @ Q[rows].T for rows in self.multi_rows]

    def residuals(self, resid: np.ndarray, Qk: np.ndarray | None = None) -> np.ndarray:
        """Left-out residuals [6N] given the in-sample residuals of the model [Q, Qk]."""
        out = np.empty_like(resid)
        rc = resid.reshape(self.n, 6)
        H = self.H_single
        if Qk is not None and Qk.shape[1]:
            Qkc = Qk.reshape(self.n, 6, -1)[self.singles]
            H = H + Qkc @ np.swapaxes(Qkc, 1, 2)
        A = np.eye(6) - H
        degenerate = np.linalg.cond(A) > MAX_CONDITION
        A[degenerate] = np.eye(6)
        e = np.linalg.solve(A, rc[self.singles][..., None])[..., 0]
        e[degenerate] = np.inf
        out.reshape(self.n, 6)[self.singles] = e
        for rows, Hm in zip(self.multi_rows, self.H_multi, strict=True):
            Hc = Hm if Qk is None or not Qk.shape[1] else Hm + Qk[rows] @ Qk[rows].T
            A = np.eye(rows.size) - Hc
            out[rows] = np.inf if np.linalg.cond(A) > MAX_CONDITION else np.linalg.solve(A, resid[rows])
        return out

    def residuals_batch(self, resid: np.ndarray, bases: list[np.ndarray]) -> np.ndarray:
        """`residuals` for G models at once: in-sample residuals [G, 6N], each with its own added basis Qk.

        Models are batched by the width of their basis, so a few wide ones do not pad the many narrow ones."""
        out = np.empty_like(resid)
        by_width: dict[int, list[int]] = {}
        for g, b in enumerate(bases):
            by_width.setdefault(b.shape[1], []).append(g)
        for width, idx in by_width.items():
            Qk = np.stack([bases[g] for g in idx]) if width else np.zeros((len(idx), resid.shape[1], 0))
            out[idx] = self._batch(resid[idx], Qk)
        return out

    def _batch(self, resid: np.ndarray, Qk: np.ndarray) -> np.ndarray:
        """Left-out residuals [G, 6N] of G models whose added bases Qk [G, 6N, q] share one width q."""
        G = resid.shape[0]
        out = np.empty_like(resid)
        shaped = out.reshape(G, self.n, 6)
        Qkc = Qk.reshape(G, self.n, 6, -1)[:, self.singles]
        A = np.eye(6) - self.H_single[None] - np.einsum("gnik,gnjk->gnij", Qkc, Qkc)
        rc = resid.reshape(G, self.n, 6)[:, self.singles]
        shaped[:, self.singles] = _solve_or_inf(A, rc)
        for rows, Hm in zip(self.multi_rows, self.H_multi, strict=True):
            Qr = Qk[:, rows]
            A = np.eye(rows.size) - Hm[None] - Qr @ np.swapaxes(Qr, 1, 2)
            out[:, rows] = _solve_or_inf(A, resid[:, rows])
        return out


def _solve_or_inf(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched solve of (I - H) e = r; clusters that the model fits exactly (leverage 1) get an infinite residual.

    The leverage check (a determinant far below the product of the diagonal) is cheap; only those few matrices
    get an eigenvalue test."""
    sign, logdet = np.linalg.slogdet(A)
    scale = np.sum(np.log(np.clip(np.diagonal(A, axis1=-2, axis2=-1), 1e-300, None)), axis=-1)
    suspect = (sign <= 0) | (logdet - scale < -np.log(MAX_CONDITION) / 2)
    degenerate = suspect.copy()
    if suspect.any():
        eig = np.linalg.eigvalsh(A[suspect])
        degenerate[suspect] = eig[..., 0] <= eig[..., -1] / MAX_CONDITION
    if degenerate.any():
        A = A.copy()
        A[degenerate] = np.eye(A.shape[-1])
    e = np.linalg.solve(A, b[..., None])[..., 0]
    e[degenerate] = np.inf
    return e


def cluster_robust_covariance(J: np.ndarray, r: np.ndarray, n_poses: int) -> np.ndarray:
    """Sandwich covariance that trusts neither equal noise across poses nor independence within a pose."""
    bread = np.linalg.pinv(J.T @ J)
    Jc = J.reshape(n_poses, 6, -1)
    rc = r.reshape(n_poses, 6)
    scores = np.einsum("cij,ci->cj", Jc, rc)
    meat = scores.T @ scores * n_poses / max(n_poses - 1, 1)
    return bread @ meat @ bread
