"""When a sequential calibration may stop: the accuracy rule, the diagnosis' minimum, the physics screening, reasons.

The accuracy rule: with a target T, stop once the predicted verify maximum's upper bound is below T; without one,
once that bound improves by less than a stated fraction per added row (averaged over the last few rows, so one
lucky row does not stop the run). Neither may act before the missing-physics diagnosis has what it needs:

- the repeats (one pose measured four times: the noise yardstick, and the pure error of the lack-of-fit test);
- spread in load and stroke, counted as what the geometry cannot absorb (a compliance is seen through the legs'
  loads, a scale error through their strokes, and the 42 geometric parameters soak up whatever part of that looks
  like geometry): the information about the 12 load and stroke terms once the geometry is fitted, as a
  Ds-efficiency against the fixed plan that the diagnosis was validated on, must reach a stated fraction;
- residual degrees of freedom beyond the 42 geometric and 12 library terms, so the screening's F-tests have
  an estimated denominator that costs them little.

At the first row where the rule and the minimum hold, the fit is screened once (one look, so its false-alarm rate is
its level): a lack-of-fit test against the repeats' pure error and added-variable F-tests of the load and the stroke
terms of all legs, Bonferroni-corrected. When it suspects physics, the run continues with poses chosen for the
library terms until their information (Ds-efficiency, after the geometry is absorbed) reaches that of the fixed
plan the diagnosis was validated on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.special import fdtrc

from hilcal.planning.prediction import N_PARAMETERS, PoseNoise, VerifyPrediction

N_LIBRARY = 12
"""Library terms screened and planned for: the load and the stroke of each leg."""

StopKind = Literal["target", "converged", "budget", "not_identifiable"]


@dataclass(frozen=True)
class MinimumSettings:
    """What the diagnosis needs before any stop: repeats, spread in load and stroke, residual dof."""

    repeat_rows: int = 4
    library_efficiency: float = 0.2
    residual_dof: int = 30


@dataclass(frozen=True)
class DiagnosisMinimum:
    """Whether the rows so far give the diagnosis its minimum, and what is still missing (in words).

    spread [2, 6]: the fraction of the candidates' range of each leg's load (row 0) and stroke (row 1) covered (shown,
    not required: the library efficiency is what counts).
    """

    repeat_rows: int
    library_efficiency: float
    spread: np.ndarray
    residual_dof: int
    met: bool
    missing: tuple[str, ...]

    @property
    def library_met(self) -> bool:
        return not any(m.startswith("load and stroke") for m in self.missing)

    def to_json(self) -> dict:
        return {"repeat_rows": self.repeat_rows, "library_efficiency": self.library_efficiency,
                "load_spread": self.spread[0].tolist(), "stroke_spread": self.spread[1].tolist(),
                "residual_dof": self.residual_dof, "met": self.met, "missing": list(self.missing)}


def diagnosis_minimum(n_rows: int, repeat_rows: int, efficiency: float, load_kn: np.ndarray, stroke_m: np.ndarray,
                      candidate_range: np.ndarray, settings: MinimumSettings) -> DiagnosisMinimum:
    """The minimum for n_rows rows, the largest number of measurements of one pose, the library Ds-efficiency, and
    the per-leg loads and strokes [n, 6] against the candidates' ranges [2, 6] (kN, m)."""
    if len(load_kn):
        covered = np.stack([np.ptp(load_kn, axis=0), np.ptp(stroke_m, axis=0)])
        spread = covered / np.where(candidate_range > 0, candidate_range, 1.0)
    else:
        spread = np.zeros((2, 6))
    dof = 6 * n_rows - N_PARAMETERS - N_LIBRARY
    missing = []
    if repeat_rows < settings.repeat_rows:
        missing.append(f"the repeated pose measured {repeat_rows} of {settings.repeat_rows} times")
    if efficiency < settings.library_efficiency:
        missing.append(f"load and stroke terms determined at {efficiency:.2f} of the fixed plan (Ds-efficiency), "
                       f"{settings.library_efficiency:.2f} needed")
    if dof < settings.residual_dof:
        missing.append(f"{dof} residual degrees of freedom beyond the 42 geometric and {N_LIBRARY} library terms, "
                       f"{settings.residual_dof} needed")
    return DiagnosisMinimum(repeat_rows, efficiency, spread, dof, not missing, tuple(missing))


@dataclass(frozen=True)
class Screening:
    """One look for missing physics in the geometric fit: p-values and whether the run should go on for it."""

    n_rows: int
    p_lack_of_fit: float
    p_load: float
    p_stroke: float
    alpha: float
    suspected: bool

    @property
    def lack_of_fit(self) -> bool:
        return self.p_lack_of_fit < self.alpha / 3

    def sentence(self) -> str:
        tests = (f"lack of fit against the repeats p = {self.p_lack_of_fit:.2g}, load terms p = {self.p_load:.2g}, "
                 f"stroke terms p = {self.p_stroke:.2g}")
        if not self.suspected:
            return f"no sign of missing physics after {self.n_rows} rows ({tests}; level {self.alpha:g} in all)"
        return (f"signs of missing physics after {self.n_rows} rows ({tests}; level {self.alpha:g} in all): measuring "
                "on for the diagnosis")

    def to_json(self) -> dict:
        return {"n_rows": self.n_rows, "p_lack_of_fit": self.p_lack_of_fit, "p_load": self.p_load,
                "p_stroke": self.p_stroke, "alpha": self.alpha, "suspected": self.suspected}


def _project_out(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """X minus its least-squares projection on the columns of A."""
    return X - A @ np.linalg.lstsq(A, X, rcond=None)[0]


def screen(residuals: np.ndarray, jacobians: np.ndarray, library: np.ndarray, repeat_deviation: np.ndarray,
           noise: PoseNoise, alpha: float) -> Screening:
    """Screen a geometric fit for missing physics (one look; see the module docstring).

    residuals [n, 6] of the fit (residual metric), jacobians [n, 6, 42] at the fitted geometry, library [n, 6, 12]
    (load terms, then stroke terms), repeat_deviation [m, 6]: the repeated rows' deviations from their pose's mean.
    Rows are whitened by the repeats' noise (`noise`, with ν = `noise.total_dof` degrees of freedom). Lack of fit:
    the residual beyond the pure error against the pure error, F(6n - 42 - ν, ν). Load and stroke: added-variable
    F(6, 6n - 48) each.
    """
    w = 1.0 / np.asarray(noise.sigma_mm)
    n = len(residuals)
    A = (jacobians * w[:, None]).reshape(-1, N_PARAMETERS)
    r = _project_out(A, (residuals * w).reshape(-1, 1))[:, 0]
    rss = float(r @ r)
    pure = float(np.sum((repeat_deviation * w) ** 2))
    nu = noise.total_dof
    dof_fit = 6 * n - N_PARAMETERS
    dof_lof = dof_fit - nu
    p_lof = float(fdtrc(dof_lof, nu, max(rss - pure, 0.0) / dof_lof / (pure / nu))) if dof_lof > 0 else 1.0
    p = []
    for cols in (slice(0, 6), slice(6, 12)):
        X = _project_out(A, (library[..., cols] * w[:, None]).reshape(-1, 6))
        explained = float(r @ X @ np.linalg.lstsq(X, r, rcond=None)[0])
        dof_rest = dof_fit - 6
        p.append(float(fdtrc(6, dof_rest, (explained / 6) / max(rss - explained, 1e-300) * dof_rest)))
    suspected = min(p_lof, *p) < alpha / 3
    return Screening(n, p_lof, p[0], p[1], alpha, suspected)


def library_information(jacobians: np.ndarray, library: np.ndarray) -> np.ndarray:
    """(12, 12): the information about the library terms left once the 42 geometric parameters are fitted."""
    A = np.asarray(jacobians).reshape(-1, N_PARAMETERS)
    X = np.asarray(library).reshape(-1, N_LIBRARY)
    Xp = _project_out(A, X)
    return Xp.T @ Xp


def library_efficiency(information: np.ndarray, reference: np.ndarray) -> float:
    """Ds-efficiency (det S / det S_ref)^(1/12) of the library terms against a reference design (0 if singular)."""
    sign, logdet = np.linalg.slogdet(information)
    sign_ref, logdet_ref = np.linalg.slogdet(reference)
    if sign_ref <= 0:
        raise ValueError("the reference design does not identify the library terms")
    return float(np.exp((logdet - logdet_ref) / N_LIBRARY)) if sign > 0 else 0.0


@dataclass(frozen=True)
class RuleCheck:
    """The accuracy rule after the latest row: met or not, which one, the improvement per row that it saw."""

    met: bool
    kind: Literal["target", "converged"] | None
    improvement_per_row: float | None
    sentence: str


def accuracy_rule(current: VerifyPrediction | None, earlier: VerifyPrediction | None, window: int,
                  target_mm: float | None, min_improvement: float) -> RuleCheck:
    """Target: upper bound < target_mm. Without one: (U_{n-w} - U_n) / U_{n-w} / w < min_improvement.

    `earlier` is the prediction from the rows without the last `window` ones, with the same noise (None when those
    rows did not identify the parameters: then the bound is still falling from infinity).
    """
    if current is None:
        return RuleCheck(False, None, None, "no prediction yet: the parameters are not identifiable from these rows")
    if target_mm is not None:
        if current.upper_mm < target_mm:
            return RuleCheck(True, "target", None, f"the predicted maximum is below {_um(target_mm)} with "
                             f"{current.confidence:.0%} confidence (upper bound {_um(current.upper_mm)})")
        return RuleCheck(False, None, None, f"upper bound {_um(current.upper_mm)}, target {_um(target_mm)}")
    if earlier is None:
        return RuleCheck(False, None, None, f"upper bound {_um(current.upper_mm)}, still falling")
    gain = (earlier.upper_mm - current.upper_mm) / earlier.upper_mm / window
    if gain < min_improvement:
        return RuleCheck(True, "converged", gain, f"the upper bound ({_um(current.upper_mm)}) improved by "
                         f"{gain:.1%} per row over the last {window} rows, less than {min_improvement:.1%}")
    return RuleCheck(False, None, gain, f"upper bound {_um(current.upper_mm)}, improving {gain:.1%} per row")


def _um(mm: float) -> str:
    return f"{mm * 1000:.1f} µm"


@dataclass(frozen=True)
class StopReason:
    """Why the measure phase ended, with the prediction at that point, in data and in a sentence.

    kind: target (the bound fell below the target), converged (it stopped improving), budget (the time budget was
    reached; the accuracy proven by then is the prediction) or not_identifiable (the budget ended before the
    rows identified every parameter: unidentifiable names the parameters of the unresolved directions).
    """

    kind: StopKind
    sentence: str
    n_rows: int
    elapsed_s: float
    prediction: VerifyPrediction | None
    unidentifiable: tuple[str, ...] = ()
    screening: Screening | None = None

    def to_json(self) -> dict:
        return {"kind": self.kind, "sentence": self.sentence, "n_rows": self.n_rows, "elapsed_s": self.elapsed_s,
                "prediction": None if self.prediction is None else self.prediction.to_json(),
                "unidentifiable": list(self.unidentifiable),
                "screening": None if self.screening is None else self.screening.to_json()}
