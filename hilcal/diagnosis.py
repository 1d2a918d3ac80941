"""Missing-physics discovery: calibrate the geometry, find structure it leaves, name the effect, refit.

The decision rule (documented in docs/diagnosis.md):
1. Fit the 42 geometric parameters by least squares on the `measure` rows (forward pose residuals).
2. For each applicable candidate in `hilcal.physics`, the added-variable F statistic of its parameter
   group after projecting out what the geometric Jacobian absorbs. A generic smooth basis in stroke and
   time (the omnibus test) looks for structure no candidate describes.
3. Residuals are whitened per pose with the pooled within-pose covariance (a CMM measures the six pose
   components with unequal, correlated noise). Each test needs both the classical F p-value and a wild
   cluster bootstrap p-value (Rademacher signs per pose, CR2 leverage-corrected residuals) to be small:
   the F test is exact for textbook noise, the bootstrap holds up under heteroscedastic and heavy-tailed
   noise, and requiring both keeps either one's failure from raising false alarms. Holm's correction
   over all tests bounds the family-wise false-alarm rate by alpha.
4. A significant candidate must also lower the leave-one-pose-out cross-validated residual (held-out
   evidence). Of those, the one with the lowest CV residual is named; another whose fitted signature is
   nearly the same (cosine > 0.9) is reported as indistinguishable on this data.
5. Nothing significant -> "none"; only the omnibus or candidates without held-out gain -> "unexplained".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog
from scipy.stats import f as f_dist

from hilcal.error_models import implicit_residuals
from hilcal.identification import IdentificationResult, identify, residual_function
from hilcal.kinematics import forward_kinematics
from hilcal.metrics import AccuracySummary
from hilcal.physics import CANDIDATES, CANDIDATES_BY_NAME, Candidate, EffectContext
from hilcal.recording import Recording
from hilcal.robot import Robot

log = structlog.get_logger(__name__)

N_GEO = 42
OMNIBUS = "omnibus"
SIMILAR_SIGNATURE = 0.9


@dataclass(frozen=True)
class EffectTest:
    """The evidence for one candidate (or the omnibus structure test)."""

    name: str
    title: str
    n_params: int
    applicable: bool
    reason: str | None = None
    f_statistic: float = float("nan")
    p_value: float = float("nan")
    p_f_test: float = float("nan")
    p_holm: float = float("nan")
    cv_rms_mm: float = float("nan")
    cv_rms_whitened: float = float("nan")
    significant: bool = False
    supported: bool = False


@dataclass(frozen=True)
class Finding:
    """One located structure in the geometric fit's residuals."""

    leg: int | None
    driver: str
    correlation: float
    text: str


@dataclass(frozen=True)
class Diagnosis:
    effect: str
    explanation: str
    parameters: dict[str, float]
    std_errors: dict[str, float]
    before: AccuracySummary | None
    after: AccuracySummary | None
    tests: tuple[EffectTest, ...]
    ambiguous_with: tuple[str, ...]
    cv_rms_geometry_mm: float
    cv_rms_effect_mm: float | None
    findings: tuple[Finding, ...]
    geometry_fit: IdentificationResult
    effect_fit: IdentificationResult | None
    leg_residuals_mm: np.ndarray = field(repr=False)
    context: EffectContext = field(repr=False)

    def residual_rms_by_axis(self) -> dict[str, float]:
        """RMS of the geometry-only fit's pose residuals per axis: x, y, z in mm; roll, pitch, yaw in deg."""
        r = self.geometry_fit.residuals
        rms = np.sqrt(np.mean(r**2, axis=0))
        rms[3:] = np.degrees(rms[3:] / self.geometry_fit.length_mm)
        return dict(zip(("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"), map(float, rms), strict=True))

    def to_json(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "explanation": self.explanation,
            "parameters": self.parameters,
            "std_errors": self.std_errors,
            "before": self.before.brief() if self.before else None,
            "after": self.after.brief() if self.after else None,
            "ambiguous_with": list(self.ambiguous_with),
            "cv_rms_geometry_mm": self.cv_rms_geometry_mm,
            "cv_rms_effect_mm": self.cv_rms_effect_mm,
            "tests": [
                {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in t.__dict__.items()}
                for t in self.tests
            ],
            "findings": [f.text for f in self.findings],
            "residual_rms_by_axis": self.residual_rms_by_axis(),
            "leg_residual_rms_mm": {f"leg{i + 1}": float(v) for i, v in
                                    enumerate(np.sqrt(np.mean(self.leg_residuals_mm**2, axis=0)))},
        }


def _orth(A: np.ndarray, rel_tol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the column space of A (columns scaled first, tiny singular values dropped)."""
    if A.shape[1] == 0:
        return A
    norms = np.linalg.norm(A, axis=0)
    A = A[:, norms > 0] / norms[norms > 0]
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    return U[:, s > s[0] * rel_tol] if s.size and s[0] > 0 else A[:, :0]


def _omnibus_regressors(ctx: EffectContext) -> np.ndarray:
    """A generic smooth basis per leg (stroke^2, stroke^3, time, time^2, stroke x time) for unnamed structure."""
    s = ctx.stroke_mm - ctx.stroke_mm.mean(axis=0)
    s = s / (np.abs(s).max(axis=0) + 1e-12)
    t = ctx.time_s - ctx.time_s.mean()
    t = (t / (np.abs(t).max() + 1e-12))[:, None] * np.ones_like(s)
    basis = [s**2, s**3, t, t**2, s * t]
    out = np.zeros((*s.shape, 6 * len(basis)))
    for j, b in enumerate(basis):
        for i in range(6):
            out[:, i, 6 * j + i] = b[:, i]
    return out


def _loo_cv_rms(r0: np.ndarray, A: np.ndarray, n_poses: int, unwhiten: np.ndarray) -> tuple[float, float]:
    """Leave-one-pose-out residual RMS of the linearized model r0 + A d (exact group-deletion formula).

    Returns (whitened RMS, the decision metric; RMS in mm with rotations as mm at the platform radius).
    """
    U = _orth(A)
    resid = (r0 - U @ (U.T @ r0)).reshape(n_poses, 6)
    Upose = U.reshape(n_poses, 6, -1)
    total_w = total_mm = 0.0
    for c in range(n_poses):
        H_cc = Upose[c] @ Upose[c].T
        e = np.linalg.lstsq(np.eye(6) - H_cc, resid[c], rcond=1e-10)[0]
        e_mm = unwhiten @ e
        total_w += float(e @ e)
        total_mm += float(e_mm @ e_mm)
    return float(np.sqrt(total_w / r0.size)), float(np.sqrt(total_mm / r0.size))


def _whitener(r: np.ndarray, J: np.ndarray, n_poses: int) -> np.ndarray:
    """Inverse square root of the pooled within-pose residual covariance (6 x 6), leverage-corrected.

    A CMM measures the six pose components with unequal and correlated noise (it depends on the sphere
    layout); whitening makes the F statistics and the bootstrap compare like with like.
    """
    adjusted = _leverage_adjusted(r, _orth(J), n_poses)
    cov = adjusted.T @ adjusted / n_poses
    w, V = np.linalg.eigh(cov)
    return V @ np.diag(1.0 / np.sqrt(np.clip(w, w.max() * 1e-12, None))) @ V.T


def _whiten(A: np.ndarray, W: np.ndarray, n_poses: int) -> np.ndarray:
    """Apply the per-pose whitener to stacked residuals [6N] or Jacobian columns [6N, k]."""
    shaped = A.reshape(n_poses, 6, -1)
    return np.einsum("ij,cjk->cik", W, shaped).reshape(A.shape)


def _leverage_adjusted(r: np.ndarray, Q: np.ndarray, n_poses: int) -> np.ndarray:
    """Per-pose residuals scaled by (I - H_cc)^-1/2 (CR2), undoing the shrinkage of fitted residuals."""
    rc = r.reshape(n_poses, 6)
    Qc = Q.reshape(n_poses, 6, -1)
    out = np.empty_like(rc)
    for c in range(n_poses):
        w, V = np.linalg.eigh(np.eye(6) - Qc[c] @ Qc[c].T)
        out[c] = V @ ((V.T @ rc[c]) / np.sqrt(np.clip(w, 1e-6, None)))
    return out


def _holm(p: np.ndarray) -> np.ndarray:
    order = np.argsort(p)
    adjusted = np.empty_like(p)
    running = 0.0
    for rank, k in enumerate(order):
        running = max(running, min(1.0, (len(p) - rank) * p[k]))
        adjusted[k] = running
    return adjusted


def _cluster_robust_se(J: np.ndarray, r: np.ndarray, n_poses: int) -> np.ndarray:
    """Standard errors that trust neither equal noise across poses nor independence within a pose."""
    bread = np.linalg.pinv(J.T @ J)
    Jc = J.reshape(n_poses, 6, -1)
    rc = r.reshape(n_poses, 6)
    scores = np.einsum("cij,ci->cj", Jc, rc)
    meat = scores.T @ scores * n_poses / max(n_poses - 1, 1)
    return np.sqrt(np.diag(bread @ meat @ bread))


def _locate(rec: Recording, ctx: EffectContext, leg_res: np.ndarray) -> tuple[Finding, ...]:
    """Correlate each leg's residual with the drivers of the candidate physics and with time."""
    drivers = {
        "axial load": ctx.force_kn,
        "stroke": ctx.stroke_mm,
        "direction of last motion": ctx.direction,
        "time": np.broadcast_to(ctx.time_s[:, None], leg_res.shape),
    }
    if ctx.temp_c is not None and np.ptp(ctx.temp_c) > 0:
        drivers["temperature"] = np.broadcast_to(ctx.temp_c[:, None], leg_res.shape)
    for axis, name in enumerate(("x", "y", "z")):
        drivers[f"platform {name}"] = np.broadcast_to(rec.meas[:, axis][:, None], leg_res.shape)
    findings = []
    n = len(leg_res)
    for name, values in drivers.items():
        for i in range(6):
            v = values[:, i]
            if np.ptp(v) == 0:
                continue
            rho = float(np.corrcoef(v, leg_res[:, i])[0, 1])
            if abs(rho) * np.sqrt(n - 2) / np.sqrt(max(1 - rho**2, 1e-12)) > 3.5:
                findings.append(Finding(i + 1, name, rho, f"leg {i + 1} residual follows {name} (r = {rho:+.2f})"))
    findings.sort(key=lambda f: -abs(f.correlation))
    return tuple(findings[:8])


def _predict(robot: Robot, fit: IdentificationResult, legs: np.ndarray, guess: np.ndarray,
             phi: np.ndarray | None) -> np.ndarray:
    lengths = legs if phi is None else legs + phi @ fit.x[N_GEO:]
    return forward_kinematics(fit.geometry(robot), lengths, guess)


def _explain(cand: Candidate, fit: IdentificationResult, se: np.ndarray, test: EffectTest, cv0: float,
             ambiguous: tuple[str, ...], untestable: dict[str, str]) -> str:
    values = ", ".join(f"{n} = {v:+.3g} ± {s:.2g}" for n, v, s in zip(fit.names[N_GEO:], fit.x[N_GEO:], se,
                                                                       strict=True))
    text = (f"Missing physics: {cand.title}. In words: {cand.sentence}. Fitted with the geometry: {values}. "
            f"Evidence: Holm-corrected p = {test.p_holm:.3g} (F test and wild bootstrap); leave-one-pose-out residual "
            f"{cv0 * 1000:.1f} -> {test.cv_rms_mm * 1000:.1f} um.")
    if ambiguous:
        names = ", ".join(CANDIDATES_BY_NAME[a].title for a in ambiguous)
        text += f" On this data it cannot be told apart from: {names} (nearly the same signature)."
    if cand.name == "sensor_scale" and "thermal_expansion" in untestable:
        text += (" Thermal growth of the legs would look the same here, and it could not be tested: "
                 f"{untestable['thermal_expansion']}.")
    return text


@dataclass(frozen=True)
class _NullModel:
    """The geometry-only fit in whitened form: what every candidate is tested against."""

    fit: IdentificationResult
    residuals: np.ndarray
    jacobian: np.ndarray
    basis: np.ndarray
    whitener: np.ndarray
    n_poses: int
    columns_of: Callable[[np.ndarray], np.ndarray]

    @property
    def dof(self) -> int:
        return self.residuals.size - self.basis.shape[1]


def _null_model(robot: Robot, mea: Recording) -> _NullModel:
    lc = robot.characteristic_length_mm
    geo = identify(robot, mea.legs_mm, mea.meas, estimator="ls")
    r_mm, J_mm = residual_function(robot, mea.legs_mm, mea.meas, "forward", lc)(geo.x)
    W = _whitener(r_mm, J_mm, mea.n)
    J0 = _whiten(J_mm, W, mea.n)
    Q0 = _orth(J0)
    r0 = _whiten(r_mm, W, mea.n)

    def columns_of(phi: np.ndarray) -> np.ndarray:
        """Whitened residual Jacobian columns of an effect's parameters at the geometric solution."""
        x = np.concatenate([geo.x, np.zeros(phi.shape[2])])
        J = residual_function(robot, mea.legs_mm, mea.meas, "forward", lc, phi)(x)[1]
        return _whiten(J[:, N_GEO:], W, mea.n)

    return _NullModel(geo, r0 - Q0 @ (Q0.T @ r0), J0, Q0, W, mea.n, columns_of)


def _group_tests(
    null: _NullModel, groups: dict[str, np.ndarray], n_boot: int, seed: int
) -> dict[str, tuple[float, float, float, np.ndarray, np.ndarray]]:
    """Added-variable F, its bootstrap and F-distribution p-values, per group of effect regressors.

    Returns name -> (F, p_bootstrap, p_F, basis of the part the geometry cannot absorb, raw columns).
    """
    r0, Q0, m = null.residuals, null.basis, null.residuals.size
    signs = np.random.default_rng(seed).choice([-1.0, 1.0], size=(null.n_poses, n_boot))
    R_star = (_leverage_adjusted(r0, Q0, null.n_poses)[:, :, None] * signs[:, None, :]).reshape(m, n_boot)
    R_star -= Q0 @ (Q0.T @ R_star)
    rss0, rss_star = float(r0 @ r0), np.sum(R_star**2, axis=0)

    def f_stat(Qk: np.ndarray, r: np.ndarray, rss: np.ndarray | float) -> np.ndarray:
        explained = np.sum((Qk.T @ r) ** 2, axis=0)
        return (explained / Qk.shape[1]) / ((rss - explained) / (null.dof - Qk.shape[1]))

    out = {}
    for name, phi in groups.items():
        X = null.columns_of(phi)
        Xt = X - Q0 @ (Q0.T @ X)
        Qk = _orth(Xt, rel_tol=1e-6)
        if Qk.shape[1] == 0 or np.linalg.norm(Xt) <= 1e-9 * np.linalg.norm(X):
            continue
        f = float(f_stat(Qk, r0, rss0))
        p_boot = float((1 + np.sum(f_stat(Qk, R_star, rss_star) >= f)) / (n_boot + 1))
        p_f = float(f_dist.sf(f, Qk.shape[1], null.dof - Qk.shape[1]))
        out[name] = (f, p_boot, p_f, Qk, X)
    return out


def diagnose(
    rec: Recording, robot: Robot, *, alpha: float = 0.05, n_boot: int = 1999, seed: int = 0,
    candidates: tuple[Candidate, ...] = CANDIDATES,
) -> Diagnosis:
    """Locate, name and model the physics that the rigid geometric model leaves out of a recording."""
    ctx_all = EffectContext.from_recording(rec, robot)
    is_measure = rec.phase == "measure"
    ctx = ctx_all.rows(is_measure)
    mea = rec.select("measure")
    null = _null_model(robot, mea)
    geo, r0, J0 = null.fit, null.residuals, null.jacobian

    titles = {c.name: c.title for c in candidates}
    titles[OMNIBUS] = "structure no candidate describes (generic stroke/time basis)"
    reasons = {c.name: c.applicable(ctx) for c in candidates}
    groups = {c.name: c.regressor(ctx) for c in candidates if reasons[c.name] is None}
    groups[OMNIBUS] = _omnibus_regressors(ctx)
    raw = _group_tests(null, groups, n_boot, seed)
    names = list(raw)
    p_holm = dict(zip(names, _holm(np.array([max(raw[n][1], raw[n][2]) for n in names])), strict=True))

    W_inv = np.linalg.inv(null.whitener)
    cv0_w, cv0 = _loo_cv_rms(r0, J0, null.n_poses, W_inv)
    tests: list[EffectTest] = []
    for name, title in titles.items():
        q = groups[name].shape[2] if name in groups else 0
        if name not in raw:
            tests.append(EffectTest(name, title, q, False, reasons.get(name) or "absorbed by the geometric parameters"))
            continue
        f, p_boot, p_f, _, X = raw[name]
        cv_w, cv = _loo_cv_rms(r0, np.concatenate([J0, X], axis=1), null.n_poses, W_inv)
        significant = bool(p_holm[name] < alpha)
        tests.append(EffectTest(name, title, q, True, None, f, p_boot, p_f, p_holm[name], cv, cv_w, significant,
                                significant and cv_w < cv0_w and name != OMNIBUS))
    supported = sorted((t for t in tests if t.supported), key=lambda t: t.cv_rms_whitened)
    untestable = {t.name: t.reason for t in tests if not t.applicable and t.reason}

    mea_verify = rec.select("verify")
    geo_pred = (_predict(robot, geo, mea_verify.legs_mm, mea_verify.meas, None) if mea_verify.n else None)
    before = AccuracySummary.of(mea_verify.meas, geo_pred) if mea_verify.n else None
    leg_res = _leg_residuals(robot, geo, rec)
    findings = _locate(rec, ctx_all, leg_res)

    if not supported:
        structured = [t for t in tests if t.significant]
        effect = "unexplained" if structured else "none"
        if effect == "none":
            explanation = ("No missing physics found: no candidate effect and no generic structure is significant "
                           f"(all Holm-corrected bootstrap p >= {alpha}); the geometric model explains this "
                           "recording to within its measurement noise.")
        else:
            what = "; ".join(f.text for f in findings[:3]) or "no single leg or driver stands out"
            explanation = ("Unexplained structure: the residuals of the geometric fit are structured "
                           f"({', '.join(f'{t.name} p = {t.p_holm:.3g}' for t in structured)}), but no candidate "
                           f"both explains it and predicts held-out poses better. Where it shows: {what}.")
        return Diagnosis(effect, explanation, {}, {}, before, before, tuple(tests), (), cv0, None, findings,
                         geo, None, leg_res, ctx_all)

    best = supported[0]
    cand = CANDIDATES_BY_NAME[best.name]
    phi = cand.regressor(ctx)
    fit = identify(robot, mea.legs_mm, mea.meas, estimator="ls", extra_regressors=phi,
                   extra_names=cand.parameter_names())
    r1, J1 = residual_function(robot, mea.legs_mm, mea.meas, "forward", robot.characteristic_length_mm, phi)(fit.x)
    se = _cluster_robust_se(J1, r1, mea.n)[N_GEO:]
    basis_of = {name: raw[name][3] for name in raw}
    signature = basis_of[best.name] @ (basis_of[best.name].T @ r0)
    ambiguous = []
    for other in supported[1:]:
        s2 = basis_of[other.name] @ (basis_of[other.name].T @ r0)
        cos = float(signature @ s2 / (np.linalg.norm(signature) * np.linalg.norm(s2) + 1e-300))
        if cos > SIMILAR_SIGNATURE:
            ambiguous.append(other.name)
    after = None
    if mea_verify.n:
        phi_v = cand.regressor(ctx_all.rows(~is_measure))
        after = AccuracySummary.of(mea_verify.meas, _predict(robot, fit, mea_verify.legs_mm, mea_verify.meas, phi_v))
    explanation = _explain(cand, fit, se, best, cv0, tuple(ambiguous), untestable)
    params = {n: float(v) for n, v in zip(fit.names[N_GEO:], fit.x[N_GEO:], strict=True)}
    log.info("diagnosed", effect=best.name, p_holm=best.p_holm, cv_rms_mm=best.cv_rms_mm, cv0_mm=cv0)
    return Diagnosis(best.name, explanation, params, dict(zip(params, map(float, se), strict=True)), before, after,
                     tuple(tests), tuple(ambiguous), cv0, best.cv_rms_mm, findings, geo, fit, leg_res, ctx_all)


def _leg_residuals(robot: Robot, geo: IdentificationResult, rec: Recording) -> np.ndarray:
    """Per-leg length residuals (mm) of every row: length implied by the measured pose minus recorded + dl0."""
    return implicit_residuals(geo.geometry(robot), rec.legs_mm, rec.meas)
