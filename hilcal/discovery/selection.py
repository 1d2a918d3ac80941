"""One step of forward selection: test every candidate group against the current model and pick the next.

The current model (geometry plus the groups chosen so far) is linearized at its least-squares fit and
whitened per pose. For every candidate group:
- the added-variable F statistic of its columns after projecting out everything the model absorbs;
- two family-wise adjusted p-values by the min-P method (Westfall-Young) over all groups of its family:
  a wild cluster bootstrap (Rademacher signs per pose, CR2 leverage-corrected residuals), which holds up
  under heteroscedastic and heavy-tailed noise, and a Gaussian Monte Carlo of the same statistics, which
  is exact for textbook noise; a group passes only if both are below its family's alpha;
- the exact leave-one-cluster-out residual (PRESS) of the model with the group, in mm: the held-out figure the
  report prints, and the one the choice goes by;
- for library physics, the fitted parameters graded against their physical ranges (typical, fault, impossible).
The families are the library (most of the error budget: it is prior knowledge) and the generic terms
(hundreds of shapes: strong evidence needed). Min-P accounts for the scan over knots and periods.
"""

from __future__ import annotations

import functools
import itertools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.special import fdtrc

from hilcal.discovery.naming import describe, unit_of
from hilcal.discovery.regression import LeaveOneOut, leverage_adjusted, orth
from hilcal.discovery.term_groups import FAULT, GENERIC, IMPOSSIBLE, LIBRARY, TermGroup

PLAUSIBILITY_Z = 3.0
"""A parameter is graded outside a range only when it lies beyond it by more than 3 standard errors."""
LIBRARY_PREFERENCE = 0.75
"""Named physics is preferred over a generic shape that explains at most 1/0.75 times as much held-out error."""
LIBRARY_ALPHA_SHARE = 0.5
RANK_TOL = 1e-6


@dataclass(frozen=True)
class ModelState:
    """The current model at its fit, in whitened form: what every candidate is tested against."""

    r0: np.ndarray
    Q: np.ndarray
    W: np.ndarray
    n_poses: int
    loo: LeaveOneOut
    press: float
    press_mm: float
    """Sum of squares of the left-out residuals in mm (rotations as mm at the platform's characteristic length)."""

    @property
    def dof(self) -> int:
        return self.r0.size - self.Q.shape[1]

    @classmethod
    def build(cls, r_w: np.ndarray, J_w: np.ndarray, W: np.ndarray, n_poses: int, clusters: np.ndarray) -> ModelState:
        Q = orth(J_w)
        r0 = r_w - Q @ (Q.T @ r_w)
        loo = LeaveOneOut(Q, n_poses, clusters)
        e = loo.residuals(r0)
        e_mm = _unwhiten(W, e, n_poses)
        return cls(r0, Q, W, n_poses, loo, float(e @ e), float(np.sum(e_mm**2)))

    def cv_rms(self, e: np.ndarray) -> tuple[float, float]:
        """(whitened RMS, RMS in mm) of left-out residuals."""
        e_mm = _unwhiten(self.W, e, self.n_poses)
        return float(np.sqrt(np.mean(e**2))), float(np.sqrt(np.mean(e_mm**2)))

    @property
    def cv_mm(self) -> float:
        return float(np.sqrt(self.press_mm / self.r0.size))

    def left_out_norms_mm(self) -> np.ndarray:
        """Per pose: the length (mm, rotations at the characteristic length) of its left-out residual."""
        e_mm = _unwhiten(self.W, self.loo.residuals(self.r0), self.n_poses).reshape(self.n_poses, 6)
        return np.linalg.norm(e_mm, axis=1)


def _unwhiten(W: np.ndarray, e: np.ndarray, n_poses: int) -> np.ndarray:
    """Whitened residuals [..., 6N] back in mm, per pose."""
    shaped = e.reshape(*e.shape[:-1], n_poses, 6)
    return (shaped @ np.linalg.inv(W).T).reshape(e.shape)


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
    """Whitened PRESS gain (kept for the record; the choice goes by the gain in mm)."""
    cv_rms_whitened: float = float("nan")
    cv_rms_mm: float = float("nan")
    press_gain_mm: float = 0.0
    """Fall of the left-out sum of squares in mm^2 when the group is added: the held-out gain the choice uses."""
    estimate: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    std_errors: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    signature: np.ndarray | None = field(default=None, repr=False)
    rejected: str | None = None
    alpha: float = 0.05
    grades: tuple[str, ...] = ()
    """Library groups: per parameter, typical / fault / impossible."""
    rss_w: float = float("nan")
    """Whitened residual sum of squares with the group (for the evidence of near-aliases)."""
    log_det_information: float = float("nan")
    """log det of the group's whitened information X'X in parameter units (the Occam factor)."""

    @property
    def p_value(self) -> float:
        """Family-wise adjusted p: both the bootstrap and the Gaussian calibration must be small."""
        return max(self.p_wild, self.p_gauss)

    @property
    def significant(self) -> bool:
        return bool(self.p_value < self.alpha)

    @property
    def eligible(self) -> bool:
        return self.significant and self.press_gain_mm > 0 and self.rejected is None

    @property
    def is_fault(self) -> bool:
        return FAULT in self.grades

    def log_evidence(self) -> float:
        """Laplace approximation of the log marginal likelihood with the group's graded prior (whitened units)."""
        rng = self.group.physical_range
        if rng is None or not np.isfinite(self.log_det_information):
            return float("nan")
        q = self.estimate.size
        return float(-0.5 * self.rss_w + 0.5 * q * np.log(2 * np.pi) - 0.5 * self.log_det_information
                     + rng.log_prior(self.estimate, self.std_errors))


def _impossible(group: TermGroup, estimate: np.ndarray, se: np.ndarray, grades: list[str]) -> str | None:
    rng = group.physical_range
    bad = [k for k, g in enumerate(grades) if g == IMPOSSIBLE]
    if rng is None or not bad:
        return None
    parts = [f"{describe(group.names[i])} {estimate[i]:+.3g} ± {se[i]:.2g} {unit_of(group.names[i])}" for i in bad[:3]]
    return (f"fitted {', '.join(parts)} lies outside the physically possible range [{rng.low[bad[0]]:.4g}, "
            f"{rng.high[bad[0]]:.4g}] ({rng.why})")


def _min_p_adjust(p_obs: np.ndarray, f_star: np.ndarray, ranks: np.ndarray, dof: int,
                  families: np.ndarray) -> np.ndarray:
    """Single-step min-P adjusted p-values: P*(min over the family of p* <= p_obs), per family.

    Within one family, groups of equal rank share a null distribution, so their smallest p* in a draw is the
    p-value of their largest F*: the F survival function is evaluated per rank class, not per group."""
    out = np.ones_like(p_obs)
    for fam in np.unique(families):
        rows = families == fam
        min_star = np.ones(f_star.shape[1])
        for q in np.unique(ranks[rows]):
            cls = rows & (ranks == q)
            min_star = np.minimum(min_star, fdtrc(q, dof - q, np.max(f_star[cls], axis=0)))
        counts = np.sum(min_star[None, :] <= p_obs[rows, None], axis=1)
        out[rows] = (1 + counts) / (min_star.size + 1)
    return out


@dataclass(frozen=True)
class Columns:
    """Candidate groups' whitened Jacobian columns as one block [6N, total], laid out width class by width class (each
    class contiguous), so that they are projected and tested in place, never gathered again."""

    block: np.ndarray
    widths: np.ndarray
    """Per group, in the groups' order: its number of columns."""
    order: np.ndarray
    """The groups in the block's order (stable by width)."""

    @staticmethod
    def layout(widths: np.ndarray) -> np.ndarray:
        return np.argsort(widths, kind="stable")

    @classmethod
    def of(cls, columns: list[np.ndarray]) -> Columns:
        """The block of per-group column arrays [6N, width]."""
        widths = np.array([X.shape[1] for X in columns], dtype=int)
        order = cls.layout(widths)
        return cls(np.concatenate([columns[k] for k in order], axis=1), widths, order)


@dataclass(frozen=True)
class _Kept:
    """The groups that add something to the model, in the order of their bases in Q_all (class by class)."""

    index: np.ndarray
    """Per kept group: its position in the tested groups."""
    ranks: np.ndarray
    offsets: np.ndarray
    """Per kept group: its first column in Q_all."""
    Q_all: np.ndarray
    """[6N, sum(ranks)] every kept group's orthonormal basis, orthogonal to the model."""
    Xt_all: np.ndarray
    """[6N, total] every group's columns with the model projected out, in the block's order."""
    starts: np.ndarray
    widths: np.ndarray
    """Per kept group: its first column in Xt_all and its number of columns."""

    def basis(self, k: int) -> np.ndarray:
        return self.Q_all[:, int(self.offsets[k]):int(self.offsets[k] + self.ranks[k])]

    def projected(self, k: int) -> np.ndarray:
        return self.Xt_all[:, int(self.starts[k]):int(self.starts[k] + self.widths[k])]


def _bases(Q: np.ndarray, dof: int, columns: Columns) -> _Kept | None:
    """The projected columns and orthonormal basis of every group that adds something, batched by width.

    Every group's columns are projected off the model in one product on the width-ordered block. The basis comes from
    the eigen-decomposition of the small Gram matrix of the column-scaled projection (Qk = Xs V / sqrt(lambda)),
    formed for a whole width class at once; groups whose Gram matrix is ill-conditioned take an SVD instead (batched
    too). Within a class the bases are laid out eigen-decomposed first, then SVD, then the rest."""
    if not columns.widths.size:
        return None
    X_all = columns.block
    widths = columns.widths[columns.order]
    Xt_all = Q @ (Q.T @ X_all)
    np.subtract(X_all, Xt_all, out=Xt_all)
    norm_x2 = np.einsum("ij,ij->j", X_all, X_all)
    col2 = np.einsum("ij,ij->j", Xt_all, Xt_all)
    m = X_all.shape[0]
    index: list[np.ndarray] = []
    starts: list[np.ndarray] = []
    rank_list: list[int] = []
    made: list[tuple[int, np.ndarray, np.ndarray, np.ndarray | None, list[np.ndarray]]] = []
    """Per width class: (width, scaled columns, eigen-decomposed groups, their V / sqrt(lambda), other bases)."""
    first_column, first_group = 0, 0
    for width in np.unique(widths).tolist():
        n = int(np.sum(widths == width))
        idx = columns.order[first_group:first_group + n]
        cols = slice(first_column, first_column + n * width)
        class_starts = first_column + width * np.arange(n)
        first_group, first_column = first_group + n, first_column + n * width
        Xt = Xt_all[:, cols].reshape(m, n, width).transpose(1, 0, 2)
        norm_x = np.sqrt(norm_x2[cols].reshape(n, width).sum(axis=1))
        col = np.sqrt(col2[cols].reshape(n, width))
        norm_t = np.sqrt(np.sum(col**2, axis=1))
        scaled = Xt / np.where(col > 0, col, 1.0)[:, None, :]
        lam, V = np.linalg.eigh(np.swapaxes(scaled, 1, 2) @ scaled)
        s = np.sqrt(np.clip(lam[:, ::-1], 0.0, None))
        top = np.where(s[:, 0] > 0, s[:, 0], 1.0)
        rank = np.sum(s > top[:, None] * RANK_TOL, axis=1)
        adds = (norm_t > 1e-7 * np.maximum(norm_x, 1e-300)) & np.any(col > 0, axis=1) & (lam[:, -1] > 0)
        adds &= (rank > 0) & (rank < dof - 1)
        all_columns = np.all(col > 0, axis=1)
        full = adds & (rank == width) & all_columns & (s[:, -1] > s[:, 0] * 1e-4)
        svd = adds & ~full & all_columns
        rest = adds & ~full & ~all_columns
        bases: list[np.ndarray] = []
        if svd.any():
            U, sv, _ = np.linalg.svd(scaled[svd], full_matrices=False)
            bases += [u[:, values > values[0] * RANK_TOL] for u, values in zip(U, sv, strict=True)]
        bases += [orth(Xt[j], RANK_TOL) for j in np.flatnonzero(rest).tolist()]
        made.append((width, scaled, full, V[full] / np.sqrt(lam[full])[:, None, :] if full.any() else None, bases))
        rank_list += [width] * int(full.sum()) + [b.shape[1] for b in bases]
        for which in (full, svd, rest):
            index.append(idx[which])
            starts.append(class_starts[which])
    if not rank_list:
        return None
    ranks = np.array(rank_list, dtype=int)
    offsets = np.concatenate([[0], np.cumsum(ranks)[:-1]]).astype(int)
    Q_all = np.empty((m, int(ranks.sum())))
    column = 0
    for width, scaled, full, M, bases in made:
        done = 0
        for a, b in _runs(full):
            # Qk = Xs V / sqrt(lambda), written in place: each group's product is the one a gathered copy would give.
            np.matmul(scaled[a:b], M[done:done + b - a],
                      out=Q_all[:, column:column + (b - a) * width].reshape(m, b - a, width).transpose(1, 0, 2))
            column, done = column + (b - a) * width, done + b - a
        for basis in bases:
            Q_all[:, column:column + basis.shape[1]] = basis
            column += basis.shape[1]
    index_all = np.concatenate(index).astype(int)
    return _Kept(index_all, ranks, offsets, Q_all, Xt_all, np.concatenate(starts).astype(int),
                 columns.widths[index_all])


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[(start, end)] of the runs of True in a boolean mask."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


THREADS = 2
"""The bootstrap's candidate products are split by columns over this many threads: single-threaded BLAS releases the
GIL, so the halves run on both cores of a small PC (BLAS's own threads busy-wait; see search.diagnose)."""


@dataclass(frozen=True)
class _Draws:
    """The null draws of one step: wild signs per pose with the leverage-adjusted residuals, Gaussian draws, and
    what the model itself takes from them."""

    signs: np.ndarray
    adjusted: np.ndarray
    gauss: np.ndarray
    rss: tuple[np.ndarray, np.ndarray]
    """Per draw, the sum of squares left after the model: (wild, Gaussian)."""

    @classmethod
    def make(cls, r0: np.ndarray, Q: np.ndarray, n_poses: int, n_boot: int, seed: int) -> _Draws:
        signs, gauss, signs32, gauss32, gauss_total = _random_draws(seed, n_poses, r0.size, n_boot)
        adj = leverage_adjusted(r0, Q, n_poses)
        wild_rss = float(np.sum(adj**2)) - np.sum((_per_pose(Q, adj, n_poses) @ signs) ** 2, axis=0)
        gauss_rss = gauss_total - np.sum((Q.T @ gauss) ** 2, axis=0)
        return cls(signs32, adj, gauss32, (wild_rss, gauss_rss))

    def candidate_sums(self, Q_part: np.ndarray, ranks: np.ndarray, n_poses: int) -> tuple[np.ndarray, np.ndarray]:
        """Per group of a block of candidate bases (consecutive groups of `ranks` columns) and per draw, the squared
        length of the draw's projection on the group: (wild, Gaussian). The candidates' part, thousands of columns
        by a thousand draws, is formed in single precision: its relative error (1e-7) is far below what a p-value
        resolved to 1/(draws + 1) can show, and it halves the search's largest product. A wild draw
        R[6n + a, b] = adj[n, a] * sign[n, b] acts on a basis through its per-pose inner products with the adjusted
        residuals (6x fewer flops than the full product); the bases are orthogonal to the model, so their products
        with a draw are already those of the model-projected draw."""
        wild = _per_pose(Q_part, self.adjusted, n_poses).astype(np.float32) @ self.signs
        gauss = Q_part.T.astype(np.float32) @ self.gauss
        return (squared_group_sums(wild, ranks).astype(float), squared_group_sums(gauss, ranks).astype(float))


def _pairwise(rows: np.ndarray) -> np.ndarray:
    """Sum over axis 1 of rows [G, n, B] (n <= 128) in numpy's pairwise order: sequential below 8 terms, else eight
    running sums combined pairwise, then the remainder."""
    n = rows.shape[1]
    if n < 8:
        total = rows[:, 0].copy()
        for i in range(1, n):
            total += rows[:, i]
        return total
    partial = rows[:, :8].copy()
    whole = n - n % 8
    for i in range(8, whole, 8):
        partial += rows[:, i:i + 8]
    p = partial.transpose(1, 0, 2)
    total = ((p[0] + p[1]) + (p[2] + p[3])) + ((p[4] + p[5]) + (p[6] + p[7]))
    for i in range(whole, n):
        total += rows[:, i]
    return total


def squared_group_sums(values: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """[groups, B] sums of squares of consecutive row groups of values [sum(ranks), B] (overwritten by its squares).

    The same numbers as ``np.add.reduceat(values**2, starts, axis=0)``, bit for bit (its first row plus the pairwise
    sum of the rest), formed rank by rank on [groups, rank, B] blocks: reduceat along the first axis walks the rows one
    group at a time and cost the bootstrap as much as its products (benchmarks/bench_diagnose.py)."""
    squares = np.square(values, out=values)
    starts = np.concatenate([[0], np.cumsum(ranks)[:-1]]).astype(int)
    out = np.empty((ranks.size, values.shape[1]), dtype=values.dtype)
    for q in np.unique(ranks).tolist():
        which = np.flatnonzero(ranks == q)
        rows = squares[starts[which, None] + np.arange(q)]
        out[which] = rows[:, 0] if q == 1 else rows[:, 0] + _pairwise(rows[:, 1:])
    return out


@functools.lru_cache(maxsize=4)
def _random_draws(seed: int, n_poses: int, m: int, n_boot: int) -> tuple[np.ndarray, ...]:
    """The seeded null draws (signs per pose, Gaussian per residual; also in single precision) and the Gaussian
    draws' sums of squares: the same for every test of one step (the backward elimination tests each chosen group
    with one seed), so they are drawn once."""
    rng = np.random.default_rng(seed)
    signs = rng.choice([-1.0, 1.0], size=(n_poses, n_boot))
    gauss = rng.standard_normal((m, n_boot))
    for a in (signs, gauss):
        a.flags.writeable = False
    return signs, gauss, signs.astype(np.float32), gauss.astype(np.float32), np.sum(gauss**2, axis=0)


def _per_pose(basis: np.ndarray, adj: np.ndarray, n_poses: int) -> np.ndarray:
    """[k, N] inner products of every basis column with the adjusted residuals, pose by pose."""
    return np.einsum("nak,na->kn", basis.reshape(n_poses, 6, -1), adj)


def _null_sums(draws: _Draws, Q_all: np.ndarray, ranks: np.ndarray, n_poses: int) -> tuple[np.ndarray, np.ndarray]:
    """`_Draws.candidate_sums` of every group, the groups split in THREADS blocks of about equal columns."""
    ends = np.cumsum(ranks)
    cuts = [0, *[int(np.searchsorted(ends, ends[-1] * k / THREADS)) + 1 for k in range(1, THREADS)], len(ranks)]
    cuts = sorted(set(min(c, len(ranks)) for c in cuts))
    blocks = [(a, b) for a, b in itertools.pairwise(cuts) if b > a]
    starts = np.concatenate([[0], ends[:-1]])

    def block(ab: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        a, b = ab
        return draws.candidate_sums(Q_all[:, int(starts[a]):int(ends[b - 1])], ranks[a:b], n_poses)

    with ThreadPoolExecutor(max_workers=len(blocks)) as pool:
        parts = list(pool.map(block, blocks))
    return np.concatenate([w for w, _ in parts]), np.concatenate([g for _, g in parts])


def assess(state: ModelState, groups: list[TermGroup], columns: Columns | list[np.ndarray], alpha: float, n_boot: int,
           seed: int) -> list[GroupTest]:
    """Test every group (its whitened Jacobian columns given, per group or as a `Columns` block) against the current
    model; the tests come in the groups' order."""
    r0, Q = state.r0, state.Q
    m, dof = r0.size, state.dof
    rss0 = float(r0 @ r0)
    alphas = {LIBRARY: alpha * LIBRARY_ALPHA_SHARE, GENERIC: alpha * (1 - LIBRARY_ALPHA_SHARE)}
    if not any(g.kind == LIBRARY for g in groups):
        alphas[GENERIC] = alpha
    if not any(g.kind == GENERIC for g in groups):
        alphas[LIBRARY] = alpha
    if not isinstance(columns, Columns):
        columns = Columns.of(columns)
    with ThreadPoolExecutor(max_workers=1) as pool:
        # The null draws do not depend on the candidates: they are made while the candidates' bases are.
        making = pool.submit(_Draws.make, r0, Q, state.n_poses, n_boot, seed)
        kept = _bases(Q, dof, columns)
        draws = making.result()
    if kept is None:
        return []
    ranks, Q_all, offsets = kept.ranks, kept.Q_all, kept.offsets
    explained = np.add.reduceat((Q_all.T @ r0) ** 2, offsets)
    f_obs = (explained / ranks) / ((rss0 - explained) / (dof - ranks))
    p_obs = fdtrc(ranks, dof - ranks, f_obs)

    kinds = [groups[k].kind for k in kept.index.tolist()]
    families = np.array(kinds)
    adjusted = []
    for e_star, rss in zip(_null_sums(draws, Q_all, ranks, state.n_poses), draws.rss, strict=True):
        # F* = (e / q) / ((rss - e) / (dof - q)), formed in place on the [groups, draws] array.
        f_star = np.subtract(rss[None, :], e_star)
        np.divide(e_star, f_star, out=f_star)
        f_star *= ((dof - ranks) / ranks)[:, None]
        adjusted.append(_min_p_adjust(p_obs, f_star, ranks, dof, families))

    # Held-out residuals only where they can matter: a group that fails its test can never be chosen, so only
    # the significant ones and the library (whose figures the report prints) need them.
    significant = np.maximum(adjusted[0], adjusted[1]) < np.array([alphas[kind] for kind in kinds])
    need = np.flatnonzero(significant | (families == LIBRARY))
    fitted_all = {int(k): kept.basis(k) @ (kept.basis(k).T @ r0) for k in need}
    press_w = np.full(len(kinds), state.press)
    press_mm_all = np.full(len(kinds), state.press_mm)
    computed = np.zeros(len(kinds), dtype=bool)
    if need.size:
        left_out = state.loo.residuals_batch(np.stack([r0 - fitted_all[k] for k in need]),
                                             [kept.basis(k) for k in need])
        press_w[need] = np.sum(left_out**2, axis=1)
        press_mm_all[need] = np.sum(_unwhiten(state.W, left_out, state.n_poses) ** 2, axis=1)
        computed[need] = True
    tests = []
    for k in np.argsort(kept.index, kind="stable").tolist():
        group, Xt = groups[int(kept.index[k])], kept.projected(k)
        cv_w = float(np.sqrt(press_w[k] / m)) if computed[k] else float("nan")
        cv_mm = float(np.sqrt(press_mm_all[k] / m)) if computed[k] else float("nan")
        press_mm = float(press_mm_all[k])
        estimate, se, rejected, grades = np.zeros(0), np.zeros(0), None, ()
        rss_w, log_det = float("nan"), float("nan")
        if group.kind == LIBRARY:
            pinv = np.linalg.pinv(Xt)
            estimate = -pinv @ r0
            sigma2 = (rss0 - explained[k]) / (dof - ranks[k])
            se = np.sqrt(np.clip(np.diag(sigma2 * pinv @ pinv.T), 0.0, None))
            grade_list = ([] if group.physical_range is None
                          else group.physical_range.grades(estimate, se, PLAUSIBILITY_Z))
            grades = tuple(grade_list)
            rejected = _impossible(group, estimate, se, grade_list)
            rss_w = float(rss0 - explained[k])
            sign, log_det = np.linalg.slogdet(Xt.T @ Xt)
            log_det = float(log_det) if sign > 0 else float("nan")
        tests.append(GroupTest(
            group, int(ranks[k]), float(f_obs[k]), float(p_obs[k]), float(adjusted[0][k]), float(adjusted[1][k]),
            state.press - float(press_w[k]), cv_w, cv_mm, state.press_mm - press_mm, estimate, se,
            fitted_all.get(k) if group.kind == LIBRARY else None, rejected, alphas[group.kind], grades, rss_w, log_det,
        ))
    return tests


def choose(tests: list[GroupTest]) -> GroupTest | None:
    """The eligible group with the largest held-out gain in mm; named physics wins when it explains nearly as much."""
    eligible = [t for t in tests if t.eligible]
    if not eligible:
        return None
    best = max(eligible, key=lambda t: t.press_gain_mm)
    library = [t for t in eligible if t.group.kind == LIBRARY]
    if library:
        best_library = max(library, key=lambda t: t.press_gain_mm)
        if best_library.press_gain_mm >= LIBRARY_PREFERENCE * best.press_gain_mm:
            return best_library
    return best


def similar(a: GroupTest, b: GroupTest) -> float:
    """Cosine between the fitted signatures of two library groups (1 = indistinguishable on this data)."""
    if a.signature is None or b.signature is None:
        return 0.0
    return float(a.signature @ b.signature / (np.linalg.norm(a.signature) * np.linalg.norm(b.signature) + 1e-300))
