"""Honest standard errors: a least-squares fit's parameter covariance from the measured noise and the model's misfit.

A fit's parameters err by G e, G = (JᵀJ + PᵀP)⁺ Jᵀ its linearised estimator (P: prior rows, stations projected out
of J), e what the model does not explain at the measured rows. Two parts:
- the measurement noise of the noise yardstick (S: per row, the 6 x 6 pose covariance in the residual metric):
  G S Gᵀ. It is what a complete model's parameters scatter by, without the leverage bias of a sandwich built from
  the fitted residuals. Given in its parts (``NoiseParts``), S = I + v D Dᵀ: the instrument's pose noise I and the
  leg readings' own noise (variance v per reading, carried through D = d pose / d leg length: the model's inputs err
  too). Where the model is complete, its residual is noise alone, and with 6 N - p degrees of freedom it is the best
  measure of the noise's level: E[rᵀr] = tr R I Rᵀ + v tr R D Dᵀ Rᵀ (R the residual maker) is solved for the level,
  the instrument's part kept as stated (or lowered to what the residual leaves, when it is an estimate such as a
  sphere-fit column, whose convention may not be hilcal's), the rest the readings' variance, never below its floor
  (the readings' step² / 12) (``split_noise``). Other inputs' noise (the temperature readings through a model's
  thermal terms, correlated between the rows a smoothed reading serves) enters as F Fᵀ, kept as estimated;
- the model's misfit, when the model is incomplete. The residual is compared with what the noise alone leaves
  (tr R S Rᵀ, R the residual maker): it *exceeds the yardstick* when the ratio of the two sums of squares is beyond
  what noise alone exceeds with the probability of two standard deviations (2.3 %): the ratio of two variance
  estimates is F-distributed with the residual's and the yardstick's degrees of freedom (chi-square over its dof
  for a stated yardstick), whose quantile, unlike a normal approximation, holds for a yardstick of few degrees of
  freedom (the repeats of one pose). A model that needed
  shapes no library names (``shapes``) is incomplete too. The misfit is then treated as a discrepancy of the legs'
  lengths, correlated over the workspace: per leg i an independent Gaussian process with variance s_i² and kernel ⅓
  (exp(-(x_i - x_i')² / 2ℓ²) + exp(-|x - x'|² / 2ℓ²) + [same session]), x the six reported lengths, each over its
  recorded range (ℓ in that unit): smooth over the leg's own stroke (a transducer, a screw), smooth over the pose
  (loads, joint angles) and constant within a session (a zero that moved, a leg warmer in one session). Where the fit
  takes up every leg's constant in every session whole (leg offsets, per-session zero shifts), such a discrepancy
  never reaches the residual and nothing measured sizes it: it is then carried only on the legs whose length the model
  found drifting (``drifting``: a shape in time or temperature, whose level between sessions no term pins down; a zero
  shift fitted there may be the drift's), not on the others, whose shifts it would only pad. It is carried through the
  estimator as G Σ Gᵀ with Σ_nm = Σ_i s_i² K_i(n, m) D_n e_i e_iᵀ D_mᵀ (D: d pose residual / d leg length), not as
  white noise, so the part the fit absorbs (and which therefore never shows in the residual) is counted too. The
  variances are the measured excess: per leg, the residual's sum of squares (in leg lengths) beyond the noise's share
  is matched by the discrepancy's share, non-negative least squares over the legs; ℓ is the one of (0.25, 0.5, 1, 2)
  under which the legs' residual series are most likely. An unexplained shape c on a leg may also scale with the leg's
  length, as thermal growth and strain do, which a shape in one variable does not know: c (L - L̄) / L̄ enters as a
  nuisance column with a unit Gaussian prior, g gᵀ with g = G times that column; only for shapes whose physics grows
  with the length (``length_scaled``: in load, temperature or time), not for those in the leg's own stroke (a function
  of its length already), its joint angles (joint geometry) or its last move (hysteresis).
The result says whether the model is incomplete and by how much the errors grew (``Misfit``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hilcal.stations import StationFrames

EXCEEDS = 2.0
"""The residual exceeds the noise yardstick beyond this many standard deviations of the comparison (in probability:
the normal distribution's beyond 2, 2.3 %)."""
LENGTHS = (0.25, 0.5, 1.0, 2.0)
"""Kernel lengths tried, in units of each leg's recorded range of reported length."""
RCOND = 1e-10
"""Singular values of the column-scaled [J; P] below this fraction of the largest span no direction of the fit."""
MIN_SHAPE_MM = 1e-6


@dataclass(frozen=True)
class NoiseParts:
    """The noise yardstick in its parts (module docstring): the instrument's pose covariance and the leg readings'."""

    instrument: np.ndarray
    """(N, 6, 6) the instrument's pose covariance per row (residual metric)."""
    instrument_source: str
    instrument_dof: float | None
    """Degrees of freedom of the instrument's estimate (None: stated, kept as it is)."""
    instrument_factor: float
    """The yardstick's factor on the instrument's estimate (1 unless pooled with repeats that showed less)."""
    readings_unit: np.ndarray
    """(N, 6, 6) D Dᵀ: the pose covariance of leg readings with a variance of 1 mm²."""
    reading_variance_mm2: float
    reading_floor_mm2: float
    readings_source: str
    inputs: np.ndarray | None = None
    """(6 N, k) F: the other inputs' noise (the temperature readings through the model's thermal terms), with
    covariance F Fᵀ over all rows (correlated: a smoothed reading serves neighbouring rows); None without."""
    inputs_source: str = ""


@dataclass(frozen=True)
class NoiseUsed:
    """The noise every ± carries, by part: the instrument's (its factor on the yardstick's variance) and the leg
    readings' (sigma per reading), and where their level comes from."""

    instrument_source: str
    instrument_position_mm: float
    """RMS length of the instrument's 3-D position noise per pose, as carried."""
    instrument_factor: float
    """The carried instrument variance over the yardstick's (1: as the source says)."""
    reading_sigma_mm: float
    readings_source: str
    level_source: str
    """The yardstick, or the complete model's residual."""
    inputs_source: str = ""
    """The other inputs' noise carried (the temperature readings'), in words; empty without."""

    def sentence(self) -> str:
        lowered = (f", {np.sqrt(self.instrument_factor):.2f}x its sigma" if abs(self.instrument_factor - 1.0) > 5e-3
                   else "")
        inputs = f", the {self.inputs_source} through the model's temperature terms" if self.inputs_source else ""
        return (f"Every ± carries the measurement noise: the instrument's {self.instrument_position_mm * 1000:.2f} µm "
                f"RMS per pose ({self.instrument_source}{lowered}) and the leg readings' "
                f"{self.reading_sigma_mm * 1000:.2f} µm each ({self.readings_source}){inputs}; level from "
                f"{self.level_source}.")

    def to_json(self) -> dict[str, object]:
        return {"instrument_source": self.instrument_source, "instrument_position_mm": self.instrument_position_mm,
                "instrument_factor": self.instrument_factor, "leg_reading_sigma_mm": self.reading_sigma_mm,
                "leg_readings_source": self.readings_source, "level_source": self.level_source,
                "other_inputs": self.inputs_source or None, "sentence": self.sentence()}


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
    noise: NoiseUsed | None = None
    """The noise's parts as carried (None when the yardstick was given whole)."""

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
                "inflation": self.inflation, "largest_inflation": self.largest, "sentence": self.sentence(),
                "noise": None if self.noise is None else self.noise.to_json()}


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


def _kernels(legs_mm: np.ndarray, session: np.ndarray, length: float, with_session: np.ndarray) -> np.ndarray:
    """(6, N, N) per leg: the mean of three unit kernels, squared exponentials of length `length` in the leg's own
    reported length and in the pose (all six reported lengths), each over its recorded range, and the same session
    (legs not `with_session`: the mean of the first two)."""
    span = np.maximum(np.ptp(legs_mm, axis=0), 1e-9)
    x = (legs_mm - legs_mm.mean(axis=0)) / span
    own = np.exp(-(x.T[:, :, None] - x.T[:, None, :]) ** 2 / (2.0 * length**2))
    pose = np.exp(-np.sum((x[:, None, :] - x[None, :, :]) ** 2, axis=2) / (2.0 * length**2))
    same = (session[:, None] == session[None, :]).astype(float)
    flags = np.asarray(with_session, dtype=bool)[:, None, None]
    return np.where(flags, (own + (pose + same)[None]) / 3.0, (own + pose[None]) / 2.0)


def _absorbs_sessions(R: np.ndarray, D: np.ndarray, session: np.ndarray) -> bool:
    """Whether the fit takes up a constant of every leg in every session whole (leg offsets, and per-session zero
    shifts where there are more sessions): the residual never shows such a discrepancy, so the data cannot size it."""
    n = D.shape[0]
    for s in np.unique(session):
        V = np.zeros((n, 6, 6))
        V[session == s] = D[session == s]
        V = V.reshape(6 * n, 6)
        if np.linalg.norm(R @ V) > 1e-6 * np.linalg.norm(V):
            return False
    return True


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


def variance_ratio_quantile(dof: float, reference_dof: float | None, upper: bool = True) -> float:
    """The quantile of a ratio of two independent variance estimates (dof over reference_dof; None: the reference is
    exact) that noise alone exceeds (upper) or falls below with the probability of EXCEEDS standard deviations."""
    from scipy.special import chdtri, fdtri, ndtr

    tail = float(ndtr(-EXCEEDS))
    if not reference_dof:
        return float(chdtri(dof, tail if upper else 1.0 - tail) / dof)
    return float(fdtri(dof, reference_dof, 1.0 - tail if upper else tail))


def _position_mm(S: np.ndarray) -> float:
    """RMS length of the 3-D position noise per row of a pose covariance (N, 6, 6)."""
    return float(np.sqrt(np.mean(np.trace(S[:, :3, :3], axis1=1, axis2=2))))


def split_noise(observed: float, e_instrument: float, e_unit: float, observed_dof: float,
                instrument_dof: float | None, floor_mm2: float, *, contradict: bool = True) -> tuple[float, float, str]:
    """The noise's parts from a sum of squares that noise alone makes (a complete model's residual, the repeats'
    scatter): (the instrument's factor on its estimate, the leg readings' variance in mm², how they were found).

    The maximum likelihood of the two parts, with E[observed] = factor e_instrument + variance e_unit and the
    instrument's own estimate (factor 1, `instrument_dof`; None: stated, kept): what the observed sum shows beyond the
    instrument is the readings' variance, at least its floor; where it shows less, the readings are at their floor and
    the instrument's estimate is pooled with what the observed sum implies, by their degrees of freedom, unless that is
    below the estimate beyond their spread (`variance_ratio_quantile`) and `contradict`: then the estimate is
    contradicted (a column in another convention than hilcal's) and the observed sum alone sets it. The repeats of
    one pose do not contradict (16-odd degrees of freedom would set the level that decides the model's completeness
    on too little); a complete model's residual, with 150-odd, does."""
    excess = (observed - e_instrument) / e_unit if e_unit > 0 else -np.inf
    if excess >= floor_mm2:
        return 1.0, float(excess), "beyond"
    if instrument_dof is None or e_instrument <= 0:
        return 1.0, floor_mm2, "within"
    implied = max(observed - floor_mm2 * max(e_unit, 0.0), 0.0) / e_instrument
    if contradict and implied < variance_ratio_quantile(observed_dof, instrument_dof, upper=False):
        return float(implied), floor_mm2, "contradicted"
    return float((instrument_dof + observed_dof * implied) / (instrument_dof + observed_dof)), floor_mm2, "pooled"


def honest_covariance(
    J: np.ndarray, r: np.ndarray, noise: np.ndarray, leg_map: np.ndarray, legs_mm: np.ndarray,
    session: np.ndarray | None = None, *, prior: np.ndarray | None = None, frames: StationFrames | None = None,
    noise_dof: float | None = None, shapes: Sequence[np.ndarray] = (), stated: Sequence[int] | None = None,
    parts: NoiseParts | None = None, length_scaled: Sequence[bool] | None = None,
    drifting: Sequence[bool] | None = None,
) -> tuple[np.ndarray, Misfit]:
    """The parameters' covariance with the measured noise and the model's misfit (module docstring).

    J (6N, p) and r (6N,): the fit's Jacobian and residuals at its solution, with the stations projected out when
    `frames` are given; noise (N, 6, 6) the yardstick's pose covariance per row (residual metric); leg_map (N, 6, 6)
    d(pose residual)/d(leg length) per row (the leg offsets' columns of the Jacobian before any projection); legs_mm
    (N, 6) the reported lengths; session (N,) the rows' sessions; prior (k, p) prior rows of the fit; noise_dof the
    yardstick's degrees of freedom (None: stated, exact); shapes (N, 6) leg corrections of the unexplained shapes;
    stated: the parameters whose inflation is reported (default all); parts: the yardstick in its parts (then
    `noise` is their sum, and a complete model's residual sets the noise's level); length_scaled: per shape, whether
    it may scale with its leg's length (default all); drifting (6,): the legs with a shape in time or temperature
    (None: every leg carries the session part)."""
    J, r, S, D = (np.asarray(a, dtype=float) for a in (J, r, noise, leg_map))
    L = np.asarray(legs_mm, dtype=float)
    n, m, p = L.shape[0], r.size, J.shape[1]
    session = np.zeros(n, dtype=int) if session is None else np.asarray(session)
    G, rank = _estimator(J, prior)
    I_m = np.eye(m)
    projector = I_m if frames is None else frames.project(I_m[:, 0], I_m)[1]
    R = projector - J @ G
    observed = float(r @ r)
    if parts is None:
        c_noise = _blocks(G, S) @ G.T
        expected = float(np.sum(_blocks(R, S) * R))
    else:
        c_instrument = _blocks(G, parts.instrument) @ G.T
        c_unit = _blocks(G, parts.readings_unit) @ G.T
        e_instrument = float(np.sum(_blocks(R, parts.instrument) * R))
        e_unit = float(np.sum(_blocks(R, parts.readings_unit) * R))
        f, v = parts.instrument_factor, parts.reading_variance_mm2
        S = f * parts.instrument + v * parts.readings_unit
        c_inputs, e_inputs = np.zeros((p, p)), 0.0
        if parts.inputs is not None:
            GF = G @ parts.inputs
            c_inputs, e_inputs = GF @ GF.T, float(np.sum((R @ parts.inputs) ** 2))
        c_noise = f * c_instrument + v * c_unit + c_inputs
        expected = f * e_instrument + v * e_unit + e_inputs
    dof = max(m - rank - (0 if frames is None else frames.n_params), 1)
    ratio = float(np.sqrt(observed / max(expected, 1e-300)))
    tolerance = float(np.sqrt(variance_ratio_quantile(dof, noise_dof)))
    scaled = [True] * len(shapes) if length_scaled is None else list(length_scaled)
    kept = [(np.asarray(c, dtype=float), f) for c, f in zip(shapes, scaled, strict=True)
            if np.ptp(np.asarray(c), axis=0).max() > MIN_SHAPE_MM]
    shapes = [c for c, _ in kept]
    stated = list(range(p)) if stated is None else list(stated)

    def used(factor: float, variance: float, level: str) -> NoiseUsed | None:
        if parts is None:
            return None
        return NoiseUsed(parts.instrument_source, float(np.sqrt(factor)) * _position_mm(parts.instrument), factor,
                         float(np.sqrt(variance)), parts.readings_source, level, parts.inputs_source)

    if ratio <= tolerance and not shapes:
        if parts is None:
            return c_noise, Misfit(False, ratio, tolerance, 0)
        factor, variance, how = split_noise(observed - e_inputs, e_instrument, e_unit, dof, parts.instrument_dof,
                                            parts.reading_floor_mm2)
        level = {"beyond": f"the complete model's residual ({dof} degrees of freedom; {ratio:.2f}x the yardstick in "
                           "RMS), its excess over the instrument's as the readings' noise",
                 "within": "the yardstick (the complete model's residual shows no more)",
                 "pooled": f"the instrument's estimate pooled with the complete model's residual ({dof} degrees of "
                           f"freedom; {ratio:.2f}x the yardstick in RMS)",
                 "contradicted": f"the complete model's residual ({dof} degrees of freedom; {ratio:.2f}x the "
                                 "yardstick in RMS, below the instrument's estimate beyond the spread of both)"}[how]
        return factor * c_instrument + variance * c_unit + c_inputs, Misfit(
            False, ratio, tolerance, 0, noise=used(factor, variance, level))
    # per leg: the residual in leg lengths and the residual maker's rows that make it
    D_inv = np.linalg.inv(D)
    MR = np.einsum("nij,njk->ink", D_inv, R.reshape(n, 6, m)).reshape(6, n, n, 6)
    rho = np.einsum("nij,nj->in", D_inv, r.reshape(n, 6))
    base = np.einsum("iakl,klj,ibkj->iab", MR, S, MR, optimize=True)
    if parts is not None and parts.inputs is not None:
        MRF = MR.reshape(6, n, m) @ parts.inputs
        base += MRF @ np.swapaxes(MRF, 1, 2)
    W = np.einsum("iakl,klj->jiak", MR, D)  # [leg j of the discrepancy, leg i of the residual, N, N]
    GA = np.einsum("pkl,klj->jpk", G.reshape(p, n, 6), D)  # [leg j, p, N]
    excess = np.maximum(np.sum(rho**2, axis=1) - np.einsum("iaa->i", base), 0.0)
    spaces = _subspaces(base)
    best: tuple[float, float, np.ndarray, np.ndarray] | None = None
    with_session = np.ones(6, dtype=bool)
    if drifting is not None and _absorbs_sessions(R, D, session):
        with_session = np.asarray(drifting, dtype=bool)
    for length in LENGTHS:
        K = _kernels(L, session, length, with_session)
        misfit_parts = np.einsum("jiak,jkl,jibl->ijab", W, K, W, optimize=True)
        s2 = _nnls(np.einsum("ijaa->ij", misfit_parts), excess)
        score = _log_likelihood(rho, base, misfit_parts, s2, spaces)
        if best is None or score > best[0]:
            best = (score, length, s2, K)
    assert best is not None
    _, length, s2, K = best
    c_misfit = np.einsum("j,jpk,jkl,jql->pq", s2, GA, K, GA, optimize=True)
    span = L.mean(axis=0)
    for c in (c for c, f in kept if f):
        for i in np.flatnonzero(np.ptp(c, axis=0) > MIN_SHAPE_MM):
            g = GA[i] @ (c[:, i] * (L[:, i] - span[i]) / span[i])
            c_misfit += np.outer(g, g)
    cov = c_noise + c_misfit
    diag = np.diag(c_noise)[stated]
    ok = diag > 0
    grown = np.sqrt(np.diag(cov)[stated][ok] / diag[ok]) if ok.any() else np.ones(1)
    noise_used = None if parts is None else used(parts.instrument_factor, parts.reading_variance_mm2, "the yardstick "
                                                 "(the model is incomplete: its residual is not noise alone)")
    return cov, Misfit(True, ratio, tolerance, len(shapes), tuple(float(v) for v in np.sqrt(s2)), float(length),
                       float(np.median(grown)), float(np.max(grown)), c_misfit, noise_used)
