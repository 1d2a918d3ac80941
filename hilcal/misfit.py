"""Honest standard errors: a least-squares fit's parameter covariance from the measured noise and the model's misfit.

A fit's parameters err by G e, G = (JᵀJ + PᵀP)⁺ Jᵀ its linearised estimator (P: prior rows, stations projected out
of J), e what the model does not explain at the measured rows. Two parts:
- the measurement noise of the noise yardstick (S: per row, the 6 x 6 pose covariance in the residual metric):
  G S Gᵀ. It is what a complete model's parameters scatter by, without the leverage bias of a sandwich built from
  the fitted residuals;
- the model's misfit, when the model is incomplete. The residual is compared with what the noise alone leaves
  (tr R S Rᵀ, R the residual maker): it *exceeds the yardstick* when its sum of squares is beyond 1 + 2 cv times
  that, cv = sqrt(2 / residual dof + 2 / the yardstick's dof) (the spread of both estimates). A model that needed
  shapes no library names (``shapes``) is incomplete too. The misfit is then treated as a discrepancy of the legs'
  lengths, correlated over the workspace: per leg i an independent Gaussian process with variance s_i² and kernel
  ⅓ (exp(-(x_i - x_i')² / 2ℓ²) + exp(-|x - x'|² / 2ℓ²) + [same session]), x the six reported lengths, each over its
  recorded range (ℓ in that unit): smooth over the leg's own stroke (a transducer, a screw), smooth over the pose
  (loads, joint angles) and constant within a session (a zero that moved). It is carried through the estimator as
  G Σ Gᵀ with Σ_nm = Σ_i s_i² K_i(n, m) D_n e_i e_iᵀ D_mᵀ (D: d pose residual / d leg length), not as white noise, so
  the part the fit absorbs (and which therefore never shows in the residual) is counted too. The variances are the
  measured excess: per leg, the residual's sum of squares (in leg lengths) beyond the noise's share is matched by the
  discrepancy's share, non-negative least squares over the legs; ℓ is the one of (0.25, 0.5, 1, 2) under which the
  legs' residual series are most likely. An unexplained shape c on a leg may also scale with the leg's length, as
  thermal growth and strain do, which a shape in one variable does not know: c (L - L̄) / L̄ enters as a nuisance
  column with a unit Gaussian prior, g gᵀ with g = G times that column.
The result says whether the model is incomplete and by how much the errors grew (``Misfit``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hilcal.stations import StationFrames

EXCEEDS = 2.0
"""The residual exceeds the noise yardstick beyond this many standard deviations of the comparison."""
LENGTHS = (0.25, 0.5, 1.0, 2.0)
"""Kernel lengths tried, in units of each leg's recorded range of reported length."""
RCOND = 1e-10
"""Singular values of the column-scaled [J; P] below this fraction of the largest span no direction of the fit."""
MIN_SHAPE_MM = 1e-6


@dataclass(frozen=True)
class Misfit:
    """Whether a model is incomplete, and what its misfit adds to the parameters' covariance."""

    incomplete: bool
    residual_to_noise: float
    """Residual RMS over what the measurement noise alone leaves (1 for a complete model)."""
    tolerance: float
    """The ratio beyond which the residual exceeds the noise yardstick (its statistical spread)."""
    shapes: int
    """Unexplained shapes in the model (each carried with its possible scaling with the leg's length)."""
    leg_sigma_mm: tuple[float, ...] = (0.0,) * 6
    """Per leg, the discrepancy's standard deviation (mm) matched to the measured excess."""
    length: float | None = None
    """The kernel length chosen (the legs' recorded ranges); None when the model is complete."""
    inflation: float = 1.0
    """Median over the stated parameters of their standard error over the noise part alone."""
    largest: float = 1.0
    """The largest such ratio."""
    covariance: np.ndarray | None = field(default=None, repr=False, compare=False)
    """(p, p) the misfit's part of the parameters' covariance (None when the model is complete)."""

    def sentence(self, what: str = "the parameters") -> str:
        """The model-incomplete sentence (empty for a complete model); `what` names the fitted parameters."""
        if not self.incomplete:
            return ""
        why = []
        if self.residual_to_noise > self.tolerance:
            why.append(f"its residual is {self.residual_to_noise:.2f}x what the measurement noise alone leaves "
                       f"(noise allows up to {self.tolerance:.2f}x)")
        if self.shapes:
            why.append(f"{self.shapes} shape(s) that no library effect names were needed")
        carried = []
        if any(s > 0 for s in self.leg_sigma_mm):
            legs = ", ".join(f"{1000 * s:.1f}" for s in self.leg_sigma_mm)
            carried.append(f"the misfit as a discrepancy of the legs' lengths, correlated along each leg's stroke, "
                           f"over the pose and over each session (per leg {legs} µm, over {self.length:g} of the "
                           "recorded ranges)")
        if self.shapes:
            carried.append("each unexplained shape's possible scaling with its leg's length")
        return (f"The model is incomplete: {' and '.join(why) or 'its residual exceeds the noise'}. Every ± of "
                f"{what} carries {' and '.join(carried) or 'the misfit'}: the standard errors are "
                f"{self.inflation:.2f}x those of the measurement noise alone (median; up to {self.largest:.2f}x).")

    def to_json(self) -> dict[str, object]:
        return {"model_incomplete": self.incomplete, "residual_to_noise": self.residual_to_noise,
                "tolerance": self.tolerance, "unexplained_shapes": self.shapes,
                "leg_discrepancy_sigma_mm": list(self.leg_sigma_mm), "kernel_length": self.length,
                "inflation": self.inflation, "largest_inflation": self.largest, "sentence": self.sentence()}


def _estimator(J: np.ndarray, prior: np.ndarray | None) -> tuple[np.ndarray, int]:
    """G = (JᵀJ + PᵀP)⁺ Jᵀ with column scaling, and the rank of [J; P]."""
    stacked = J if prior is None or not prior.size else np.vstack([J, prior])
    c = np.sqrt(np.mean(stacked**2, axis=0))
    c = np.where(c > 0, c, 1.0)
    _, s, Vt = np.linalg.svd(stacked / c, full_matrices=False)
    keep = s > s[0] * RCOND
    B = (Vt[keep].T / s[keep] ** 2) @ Vt[keep] / np.outer(c, c)
    return B @ J.T, int(keep.sum())


def _blocks(A: np.ndarray, S: np.ndarray) -> np.ndarray:
    """A (k, 6N) times the block-diagonal S (N, 6, 6)."""
    n = S.shape[0]
    return np.einsum("knj,nji->kni", A.reshape(A.shape[0], n, 6), S).reshape(A.shape)


def _kernels(legs_mm: np.ndarray, session: np.ndarray, length: float) -> np.ndarray:
    """(6, N, N) per leg: the mean of three unit kernels, squared exponentials of length `length` in the leg's own
    reported length and in the pose (all six reported lengths), each over its recorded range, and the same session."""
    span = np.maximum(np.ptp(legs_mm, axis=0), 1e-9)
    x = (legs_mm - legs_mm.mean(axis=0)) / span
    own = (x.T[:, :, None] - x.T[:, None, :]) ** 2
    pose = np.sum((x[:, None, :] - x[None, :, :]) ** 2, axis=2)
    same = (session[:, None] == session[None, :]).astype(float)
    return (np.exp(-own / (2.0 * length**2)) + (np.exp(-pose / (2.0 * length**2)) + same)[None]) / 3.0


def _subspaces(base: np.ndarray) -> list[np.ndarray]:
    """Per leg, an orthonormal basis of the subspace its residual series can span under the noise alone (the fit
    annihilates the rest, e.g. a constant that the leg's offset takes up)."""
    out = []
    for b in base:
        w, V = np.linalg.eigh(b)
        out.append(V[:, w > w.max() * 1e-9])
    return out


def _log_likelihood(rho: np.ndarray, base: np.ndarray, parts: np.ndarray, s2: np.ndarray,
                    spaces: list[np.ndarray]) -> float:
    """Sum over the legs of the Gaussian log-likelihood of each leg's residual series rho[i] (N,) under its covariance
    base[i] + sum_j s2_j parts[i, j], on the subspace of ``_subspaces``."""
    total = 0.0
    for i, V in enumerate(spaces):
        lam, U = np.linalg.eigh(V.T @ (base[i] + np.einsum("j,jab->ab", s2, parts[i])) @ V)
        lam = np.maximum(lam, lam.max() * 1e-12)
        z = U.T @ (V.T @ rho[i])
        total -= 0.5 * float(np.sum(np.log(lam)) + np.sum(z**2 / lam))
    return total


def _nnls(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    from scipy.optimize import nnls

    return nnls(A, b)[0]


def honest_covariance(
    J: np.ndarray, r: np.ndarray, noise: np.ndarray, leg_map: np.ndarray, legs_mm: np.ndarray,
    session: np.ndarray | None = None, *, prior: np.ndarray | None = None, frames: StationFrames | None = None,
    noise_dof: float | None = None, shapes: Sequence[np.ndarray] = (), stated: Sequence[int] | None = None,
) -> tuple[np.ndarray, Misfit]:
    """The parameters' covariance with the measured noise and the model's misfit (module docstring).

    J (6N, p) and r (6N,): the fit's Jacobian and residuals at its solution, with the stations projected out when
    `frames` are given; noise (N, 6, 6) the yardstick's pose covariance per row (residual metric); leg_map (N, 6, 6)
    d(pose residual)/d(leg length) per row (the leg offsets' columns of the Jacobian before any projection); legs_mm
    (N, 6) the reported lengths; session (N,) the rows' sessions; prior (k, p) prior rows of the fit; noise_dof the
    yardstick's degrees of freedom (None: stated, exact); shapes (N, 6) leg corrections of the unexplained shapes;
    stated: the parameters whose inflation is reported (default all)."""
    J, r, S, D = (np.asarray(a, dtype=float) for a in (J, r, noise, leg_map))
    L = np.asarray(legs_mm, dtype=float)
    n, m, p = L.shape[0], r.size, J.shape[1]
    session = np.zeros(n, dtype=int) if session is None else np.asarray(session)
    G, rank = _estimator(J, prior)
    c_noise = _blocks(G, S) @ G.T
    I_m = np.eye(m)
    projector = I_m if frames is None else frames.project(I_m[:, 0], I_m)[1]
    R = projector - J @ G
    observed, expected = float(r @ r), float(np.sum(_blocks(R, S) * R))
    dof = max(m - rank - (0 if frames is None else frames.n_params), 1)
    cv = np.sqrt(2.0 / dof + (0.0 if not noise_dof else 2.0 / noise_dof))
    ratio = float(np.sqrt(observed / max(expected, 1e-300)))
    tolerance = float(np.sqrt(1.0 + EXCEEDS * cv))
    shapes = [np.asarray(c, dtype=float) for c in shapes if np.ptp(np.asarray(c), axis=0).max() > MIN_SHAPE_MM]
    stated = list(range(p)) if stated is None else list(stated)
    if ratio <= tolerance and not shapes:
        return c_noise, Misfit(False, ratio, tolerance, 0)
    # per leg: the residual in leg lengths and the residual maker's rows that make it
    D_inv = np.linalg.inv(D)
    MR = np.einsum("nij,njk->ink", D_inv, R.reshape(n, 6, m)).reshape(6, n, n, 6)
    rho = np.einsum("nij,nj->in", D_inv, r.reshape(n, 6))
    base = np.einsum("iakl,klj,ibkj->iab", MR, S, MR, optimize=True)
    W = np.einsum("iakl,klj->jiak", MR, D)  # [leg j of the discrepancy, leg i of the residual, N, N]
    GA = np.einsum("pkl,klj->jpk", G.reshape(p, n, 6), D)  # [leg j, p, N]
    excess = np.maximum(np.sum(rho**2, axis=1) - np.einsum("iaa->i", base), 0.0)
    spaces = _subspaces(base)
    best: tuple[float, float, np.ndarray, np.ndarray] | None = None
    for length in LENGTHS:
        K = _kernels(L, session, length)
        parts = np.einsum("jiak,jkl,jibl->ijab", W, K, W, optimize=True)
        s2 = _nnls(np.einsum("ijaa->ij", parts), excess)
        score = _log_likelihood(rho, base, parts, s2, spaces)
        if best is None or score > best[0]:
            best = (score, length, s2, K)
    assert best is not None
    _, length, s2, K = best
    c_misfit = np.einsum("j,jpk,jkl,jql->pq", s2, GA, K, GA, optimize=True)
    span = L.mean(axis=0)
    for c in shapes:
        for i in np.flatnonzero(np.ptp(c, axis=0) > MIN_SHAPE_MM):
            g = GA[i] @ (c[:, i] * (L[:, i] - span[i]) / span[i])
            c_misfit += np.outer(g, g)
    cov = c_noise + c_misfit
    diag = np.diag(c_noise)[stated]
    ok = diag > 0
    grown = np.sqrt(np.diag(cov)[stated][ok] / diag[ok]) if ok.any() else np.ones(1)
    return cov, Misfit(True, ratio, tolerance, len(shapes), tuple(float(v) for v in np.sqrt(s2)), float(length),
                       float(np.median(grown)), float(np.max(grown)), c_misfit)
