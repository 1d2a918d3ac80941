"""One step of forward selection: test every candidate group against the current model and pick the next.

The current model (geometry plus the groups chosen so far) is linearized at its least-squares fit and
whitened per pose. For every candidate group:
- the added-variable F statistic of its columns after projecting out everything the model absorbs;
- two family-wise adjusted p-values by the min-P method (Westfall-Young) over all groups of its family:
  a wild cluster bootstrap (Rademacher signs per pose, CR2 leverage-corrected residuals), which holds up
  under heteroscedastic and heavy-tailed noise, and a Gaussian Monte Carlo of the same statistics, which
  is exact for textbook noise; a group passes only if both are below its family's alpha;
- the exact leave-one-cluster-out residual (PRESS) of the model with the group (held-out evidence);
- for library physics, the fitted parameters and whether they are physically possible.
The families are the library (most of the error budget: it is prior knowledge) and the generic terms
(hundreds of shapes: strong evidence needed). Min-P accounts for the scan over knots and periods.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import f as f_dist

from hilcal.discovery.regression import LeaveOneOut, leverage_adjusted, orth
from hilcal.discovery.term_groups import GENERIC, LIBRARY, TermGroup

PLAUSIBILITY_Z = 3.0
"""A library fit is rejected when a parameter lies outside its physical range by more than 3 standard errors."""
LIBRARY_PREFERENCE = 0.75
"""Named physics is preferred over a generic shape that explains at most 1/0.75 times as much held-out error."""
LIBRARY_ALPHA_SHARE = 0.5


@dataclass(frozen=True)
class ModelState:
    """The current model at its fit, in whitened form: what every candidate is tested against."""

    r0: np.ndarray
    Q: np.ndarray
    W: np.ndarray
    n_poses: int
    loo: LeaveOneOut
    press: float

    @property
    def dof(self) -> int:
        return self.r0.size - self.Q.shape[1]

    @classmethod
    def build(cls, r_w: np.ndarray, J_w: np.ndarray, W: np.ndarray, n_poses: int, clusters: np.ndarray) -> ModelState:
        Q = orth(J_w)
        r0 = r_w - Q @ (Q.T @ r_w)
        loo = LeaveOneOut(Q, n_poses, clusters)
        e = loo.residuals(r0)
        return cls(r0, Q, W, n_poses, loo, float(e @ e))

    def cv_rms(self, e: np.ndarray) -> tuple[float, float]:
        """(whitened RMS, RMS in mm) of left-out residuals."""
        e_mm = np.einsum("ij,cj->ci", np.linalg.inv(self.W), e.reshape(self.n_poses, 6))
        return float(np.sqrt(np.mean(e**2))), float(np.sqrt(np.mean(e_mm**2)))


@dataclass(frozen=True)
class GroupTest:
    """The evidence for one candidate group at one step."""

    group: TermGroup
    rank: int
    f_statistic: float
    p_f: float
    p_wild: float = float("nan")
    p_gauss: float = float("nan")
    press_gain: float = 0.0
    cv_rms_whitened: float = float("nan")
    cv_rms_mm: float = float("nan")
    estimate: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    std_errors: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    signature: np.ndarray | None = field(default=None, repr=False)
    rejected: str | None = None
    alpha: float = 0.05

    @property
    def p_value(self) -> float:
        """Family-wise adjusted p: both the bootstrap and the Gaussian calibration must be small."""
        return max(self.p_wild, self.p_gauss)

    @property
    def significant(self) -> bool:
        return bool(self.p_value < self.alpha)

    @property
    def eligible(self) -> bool:
        return self.significant and self.press_gain > 0 and self.rejected is None


def _plausibility(group: TermGroup, estimate: np.ndarray, se: np.ndarray) -> str | None:
    rng = group.physical_range
    if rng is None:
        return None
    bad = rng.violations(estimate, se, PLAUSIBILITY_Z)
    if not bad:
        return None
    parts = [f"{group.names[i]} = {estimate[i]:+.4g} ± {se[i]:.2g}" for i in bad[:3]]
    return (f"fitted {', '.join(parts)} lies outside the physical range [{rng.low[bad[0]]:.4g}, "
            f"{rng.high[bad[0]]:.4g}] ({rng.why})")


def _min_p_adjust(p_obs: np.ndarray, p_star: np.ndarray, families: np.ndarray) -> np.ndarray:
    """Single-step min-P adjusted p-values: P*(min over the family of p* <= p_obs), per family."""
    out = np.ones_like(p_obs)
    for fam in np.unique(families):
        rows = families == fam
        min_star = np.min(p_star[rows], axis=0)
        counts = np.sum(min_star[None, :] <= p_obs[rows, None], axis=1)
        out[rows] = (1 + counts) / (min_star.size + 1)
    return out


def assess(state: ModelState, groups: list[TermGroup], columns: list[np.ndarray], alpha: float, n_boot: int,
           seed: int) -> list[GroupTest]:
    """Test every group (its whitened Jacobian columns given) against the current model."""
    r0, Q = state.r0, state.Q
    m, dof = r0.size, state.dof
    rss0 = float(r0 @ r0)
    alphas = {LIBRARY: alpha * LIBRARY_ALPHA_SHARE, GENERIC: alpha * (1 - LIBRARY_ALPHA_SHARE)}
    if not any(g.kind == LIBRARY for g in groups):
        alphas[GENERIC] = alpha
    if not any(g.kind == GENERIC for g in groups):
        alphas[LIBRARY] = alpha
    kept: list[tuple[TermGroup, np.ndarray, np.ndarray]] = []
    for group, X in zip(groups, columns, strict=True):
        Xt = X - Q @ (Q.T @ X)
        if np.linalg.norm(Xt) <= 1e-7 * max(np.linalg.norm(X), 1e-300):
            continue
        Qk = orth(Xt, rel_tol=1e-6)
        if Qk.shape[1] == 0 or Qk.shape[1] >= dof - 1:
            continue
        kept.append((group, Xt, Qk))
    if not kept:
        return []
    ranks = np.array([Qk.shape[1] for _, _, Qk in kept])
    Q_all = np.concatenate([Qk for _, _, Qk in kept], axis=1)
    offsets = np.concatenate([[0], np.cumsum(ranks)[:-1]])
    explained = np.add.reduceat((Q_all.T @ r0) ** 2, offsets)
    f_obs = (explained / ranks) / ((rss0 - explained) / (dof - ranks))
    p_obs = f_dist.sf(f_obs, ranks, dof - ranks)

    rng = np.random.default_rng(seed)
    signs = rng.choice([-1.0, 1.0], size=(state.n_poses, n_boot))
    wild = (leverage_adjusted(r0, Q, state.n_poses)[:, :, None] * signs[:, None, :]).reshape(m, n_boot)
    gauss = rng.standard_normal((m, n_boot))
    adjusted = []
    families = np.array([g.kind for g, _, _ in kept])
    for R in (wild, gauss):
        R = R - Q @ (Q.T @ R)
        rss = np.sum(R**2, axis=0)
        e_star = np.add.reduceat((Q_all.T @ R) ** 2, offsets, axis=0)
        f_star = (e_star / ranks[:, None]) / ((rss[None, :] - e_star) / (dof - ranks)[:, None])
        p_star = f_dist.sf(f_star, ranks[:, None], (dof - ranks)[:, None])
        adjusted.append(_min_p_adjust(p_obs, p_star, families))

    tests = []
    for k, (group, Xt, Qk) in enumerate(kept):
        fitted = Qk @ (Qk.T @ r0)
        e = state.loo.residuals(r0 - fitted, Qk)
        cv_w, cv_mm = state.cv_rms(e)
        estimate, se, rejected = np.zeros(0), np.zeros(0), None
        if group.kind == LIBRARY:
            pinv = np.linalg.pinv(Xt)
            estimate = -pinv @ r0
            sigma2 = (rss0 - explained[k]) / (dof - ranks[k])
            se = np.sqrt(np.clip(np.diag(sigma2 * pinv @ pinv.T), 0.0, None))
            rejected = _plausibility(group, estimate, se)
        tests.append(GroupTest(
            group, int(ranks[k]), float(f_obs[k]), float(p_obs[k]), float(adjusted[0][k]), float(adjusted[1][k]),
            state.press - float(e @ e), cv_w, cv_mm, estimate, se,
            fitted if group.kind == LIBRARY else None, rejected, alphas[group.kind],
        ))
    return tests


def choose(tests: list[GroupTest]) -> GroupTest | None:
    """The eligible group with the largest held-out gain; named physics wins when it explains nearly as much."""
    eligible = [t for t in tests if t.eligible]
    if not eligible:
        return None
    best = max(eligible, key=lambda t: t.press_gain)
    library = [t for t in eligible if t.group.kind == LIBRARY]
    if library:
        best_library = max(library, key=lambda t: t.press_gain)
        if best_library.press_gain >= LIBRARY_PREFERENCE * best.press_gain:
            return best_library
    return best


def similar(a: GroupTest, b: GroupTest) -> float:
    """Cosine between the fitted signatures of two library groups (1 = indistinguishable on this data)."""
    if a.signature is None or b.signature is None:
        return 0.0
    return float(a.signature @ b.signature / (np.linalg.norm(a.signature) * np.linalg.norm(b.signature) + 1e-300))
