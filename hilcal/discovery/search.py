"""Missing-physics discovery: calibrate the geometry, then add, one at a time, what the residuals demand.

The rule (docs/diagnosis.md):
1. Fit the 42 geometric parameters by least squares on the `measure` rows (forward pose residuals).
2. Forward selection over the library physics (`hilcal.discovery.physics`) and the generic per-leg shapes
   (`hilcal.discovery.generic_terms`): at each step every remaining group is tested against the current model
   (`hilcal.discovery.selection`: added-variable F with min-P adjusted wild-bootstrap and Gaussian p-values, held-out
   PRESS, physical plausibility); the eligible group with the largest held-out gain is added (named
   physics wins when it explains nearly as much), the model is refitted, and the search goes on until
   nothing passes.
3. The residual is compared with an absolute noise yardstick (`hilcal.discovery.noise`): "within noise" is only said
   with a noise level in mm and its source; a residual far above the noise that nothing explains is
   `unexplained`, never `none`.
4. The final model is refitted with every library parameter held inside its physical range; the verify rows
   (never used for choosing) show what each step buys on held-out poses.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import structlog
from scipy.optimize import least_squares

from hilcal.discovery import explain
from hilcal.discovery.context import EffectContext
from hilcal.discovery.findings import locate, noise_comparison, session_shift
from hilcal.discovery.generic_terms import generic_groups
from hilcal.discovery.noise import find_repeats, noise_yardstick
from hilcal.discovery.physics import library_groups
from hilcal.discovery.regression import cluster_robust_covariance, pooled_whitener, whiten
from hilcal.discovery.result import CandidateResult, Diagnosis, Step
from hilcal.discovery.selection import GroupTest, ModelState, assess, choose, similar
from hilcal.discovery.shapes import shapes_for
from hilcal.discovery.term_groups import GENERIC, LIBRARY, TermGroup
from hilcal.error_models import implicit_residuals, pose_difference
from hilcal.identification import IdentificationResult, identify, residual_function
from hilcal.kinematics import forward_kinematics
from hilcal.metrics import AccuracySummary
from hilcal.recording import Recording
from hilcal.robot import Robot

log = structlog.get_logger(__name__)

N_GEO = 42
DL0_COLUMNS = [7 * i + 6 for i in range(6)]
MAX_STEPS = 8
DEFAULT_ALPHA = 0.02
"""Family-wise false-alarm rate of a diagnosis on a recording without missing physics (library and generic
families share it); step k of the search uses alpha / k."""
SIMILAR_SIGNATURE = 0.9
ALIAS_GAIN = 0.9
"""Another setting of the same leg and variable (a period, a knot count) with 90 % of the chosen one's held-out
gain makes the shape's scale ambiguous."""


@dataclasses.dataclass
class _Problem:
    """The fixed inputs of one diagnosis: robot, rows, contexts and the cluster structure for held-out residuals."""

    robot: Robot
    rec: Recording
    measure: np.ndarray
    ctx_all: EffectContext
    ctx: EffectContext
    mea: Recording
    ver: Recording
    clusters: np.ndarray
    phi_cache: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @property
    def length_mm(self) -> float:
        return self.robot.characteristic_length_mm

    def phi(self, group: TermGroup) -> np.ndarray:
        if group.key not in self.phi_cache:
            self.phi_cache[group.key] = group.phi(self.ctx)
        return self.phi_cache[group.key]

    def phi_of(self, groups: list[TermGroup]) -> np.ndarray | None:
        return np.concatenate([self.phi(g) for g in groups], axis=2) if groups else None


def _names(groups: list[TermGroup]) -> tuple[str, ...]:
    return tuple(n for g in groups for n in g.names)


def fit_model(p: _Problem, groups: list[TermGroup], bounded: bool = False) -> IdentificationResult:
    """Least squares of geometry + groups on the measure rows; with `bounded`, library parameters stay physical."""
    phi = p.phi_of(groups)
    fit = identify(p.robot, p.mea.legs_mm, p.mea.meas, estimator="ls", extra_regressors=phi,
                   extra_names=_names(groups))
    if not bounded or not any(g.physical_range is not None for g in groups):
        return fit
    lo = np.full(fit.x.size, -np.inf)
    hi = np.full(fit.x.size, np.inf)
    k = N_GEO
    for g in groups:
        if g.physical_range is not None:
            lo[k:k + g.n_params], hi[k:k + g.n_params] = g.physical_range.low, g.physical_range.high
        k += g.n_params
    if np.all((fit.x >= lo) & (fit.x <= hi)):
        return fit
    fun = residual_function(p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm, phi)
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    x0 = np.clip(fit.x, lo + 1e-9 * span, hi - 1e-9 * span)
    sol = least_squares(lambda x: fun(x)[0], x0, jac=lambda x: fun(x)[1], bounds=(lo, hi), method="trf",
                        x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    r = sol.fun
    return dataclasses.replace(fit, x=sol.x, residuals=r.reshape(-1, 6), max_abs_residual=float(np.max(np.abs(r))),
                               rms_residual=float(np.sqrt(np.mean(r**2))), converged=bool(sol.status > 0),
                               message=f"bounded refit: {sol.message}")


def predict(p: _Problem, fit: IdentificationResult, groups: list[TermGroup], rows: np.ndarray,
            leg_offsets_mm: np.ndarray | float = 0.0) -> np.ndarray:
    """Poses the model predicts from the recorded leg lengths of some rows (mm, deg), optionally offset."""
    ctx = p.ctx_all.rows(rows)
    legs = p.rec.legs_mm[rows] + leg_offsets_mm
    if groups:
        legs = legs + np.concatenate([g.phi(ctx) for g in groups], axis=2) @ fit.x[N_GEO:]
    return forward_kinematics(fit.geometry(p.robot), legs, p.rec.meas[rows])


def verify_accuracy(p: _Problem, fit: IdentificationResult, groups: list[TermGroup]) -> AccuracySummary | None:
    rows = ~p.measure
    if not rows.any():
        return None
    return AccuracySummary.of(p.rec.meas[rows], predict(p, fit, groups, rows))


def leg_residuals(p: _Problem, fit: IdentificationResult, groups: list[TermGroup]) -> np.ndarray:
    """Per-leg length residuals (mm) of every row: length implied by the measured pose minus the modelled length."""
    legs = p.rec.legs_mm
    if groups:
        legs = legs + np.concatenate([g.phi(p.ctx_all) for g in groups], axis=2) @ fit.x[N_GEO:]
    return implicit_residuals(fit.geometry(p.robot), legs, p.rec.meas)


def _state(p: _Problem, fit: IdentificationResult, groups: list[TermGroup]) -> tuple[ModelState, np.ndarray]:
    """The model linearized and whitened at its fit, and d(residual)/d(dl0) per leg for new groups' columns."""
    fun = residual_function(p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm, p.phi_of(groups))
    r, J = fun(fit.x)
    n = p.mea.n
    W = pooled_whitener(r, J, n)
    state = ModelState.build(whiten(r, W, n), whiten(J, W, n), W, n, p.clusters)
    return state, J.reshape(n, 6, -1)[:, :, DL0_COLUMNS]


def _columns(p: _Problem, state: ModelState, d_dl0: np.ndarray, group: TermGroup) -> np.ndarray:
    cols = np.einsum("nal,nlq->naq", d_dl0, p.phi(group)).reshape(6 * p.mea.n, -1)
    return whiten(cols, state.W, state.n_poses)


def _clusters(mea: Recording) -> np.ndarray:
    labels = np.arange(mea.n)
    for group in find_repeats(mea):
        labels[group] = group[0]
    return labels


def _problem(rec: Recording, robot: Robot) -> _Problem:
    measure = rec.phase == "measure"
    ctx_all = EffectContext.from_recording(rec, robot)
    mea = rec.select("measure")
    return _Problem(robot, rec, measure, ctx_all, ctx_all.rows(measure), mea, rec.select("verify"), _clusters(mea))


def _aliases(best: GroupTest, tests: list[GroupTest]) -> tuple[TermGroup, ...]:
    """Other periods of the same leg, beyond the frequency resolution, that explain nearly as much."""
    g = best.group
    assert g.period_mm is not None and g.curve_range is not None
    resolution = 1.0 / max(g.curve_range[1] - g.curve_range[0], 1e-9)
    return tuple(
        t.group for t in tests
        if t.eligible and t.group.leg == g.leg and t.group.period_mm is not None
        and abs(1.0 / t.group.period_mm - 1.0 / g.period_mm) > resolution
        and t.press_gain >= ALIAS_GAIN * best.press_gain
    )


def _candidate_results(first: list[GroupTest], library: list[TermGroup], untestable: dict[str, str],
                       chosen_keys: set[str]) -> tuple[CandidateResult, ...]:
    by_key = {t.group.key: t for t in first}
    out = [CandidateResult(name, name, False, reason) for name, reason in untestable.items()]
    for g in library:
        t = by_key.get(g.key)
        if t is None:
            out.append(CandidateResult(g.key, g.title, False, "absorbed by the geometric parameters"))
            continue
        out.append(CandidateResult(g.key, g.title, True, None, t.f_statistic, t.p_value, t.cv_rms_mm,
                                   t.significant, t.rejected, g.key in chosen_keys))
    return tuple(out)


@dataclasses.dataclass
class _Selection:
    """The outcome of forward selection with backward elimination."""

    chosen: list[TermGroup]
    steps: list[Step]
    first_tests: list[GroupTest]
    rejected: dict[str, str]
    alternatives: dict[str, tuple[TermGroup, ...]]
    ambiguous: tuple[str, ...]


def _drop_test(p: _Problem, chosen: list[TermGroup], group: TermGroup, alpha: float, n_boot: int,
               seed: int) -> GroupTest | None:
    """The test of a chosen group given all the others (None when the others absorb it)."""
    others = [g for g in chosen if g is not group]
    state, d_dl0 = _state(p, fit_model(p, others), others)
    tests = assess(state, [group], [_columns(p, state, d_dl0, group)], alpha, n_boot, seed)
    return tests[0] if tests else None


def _cv_mm(p: _Problem, groups: list[TermGroup]) -> float:
    """Leave-one-cluster-out residual RMS (mm) of a model: comparable across models."""
    state, _ = _state(p, fit_model(p, groups), groups)
    return state.cv_rms(state.loo.residuals(state.r0))[1]


def _swap(p: _Problem, sel: _Selection, library: list[TermGroup], alpha: float, n_boot: int, seed: int) -> None:
    """Replace a chosen library effect by another when that predicts held-out poses better (greedy is myopic)."""
    best_cv = _cv_mm(p, sel.chosen)
    improved = True
    while improved:
        improved = False
        chosen_keys = {g.key for g in sel.chosen}
        for old in [g for g in sel.chosen if g.kind == LIBRARY]:
            for new in library:
                if new.key in chosen_keys or new.key in sel.rejected:
                    continue
                trial = [new if g is old else g for g in sel.chosen]
                cv = _cv_mm(p, trial)
                if cv >= best_cv:
                    continue
                test = _drop_test(p, trial, new, alpha, n_boot, seed)
                if test is None or not test.eligible:
                    continue
                fit = fit_model(p, trial)
                sel.chosen, best_cv, improved = trial, cv, True
                sel.steps.append(Step(len(sel.steps) + 1, new.key, new.effect, new.kind, new.title, test.rank,
                                      test.f_statistic, test.p_value, test.p_wild, test.p_gauss,
                                      sel.steps[-1].cv_rms_mm, cv, verify_accuracy(p, fit, trial), (old.key,)))
                break
            if improved:
                break


def _select(p: _Problem, candidates: list[TermGroup], alpha: float, n_boot: int, seed: int, max_steps: int,
            state: ModelState, d_dl0: np.ndarray) -> _Selection:
    """Forward selection (alpha / k at step k) with backward elimination of groups that the later ones explain."""
    sel = _Selection([], [], [], {}, {}, ())
    remaining = list(candidates)
    dropped: set[str] = set()
    for index in range(1, max_steps + 1):
        cv_now = state.cv_rms(state.loo.residuals(state.r0))[1]
        columns = [_columns(p, state, d_dl0, g) for g in remaining]
        tests = assess(state, remaining, columns, alpha / index, n_boot, seed + index)
        if index == 1:
            sel.first_tests = tests
        for t in tests:
            if t.rejected and t.significant:
                sel.rejected[t.group.key] = t.rejected
        best = choose(tests)
        log.info("selection_step", step=index, n_candidates=len(tests), chosen=None if best is None else best.group.key)
        if best is None:
            break
        if not sel.steps and best.group.kind == LIBRARY:
            sel.ambiguous = tuple(t.group.key for t in tests if t is not best and t.eligible
                                  and t.group.kind == LIBRARY and similar(best, t) > SIMILAR_SIGNATURE)
        sel.chosen.append(best.group)
        if best.group.period_mm is not None:
            sel.alternatives[best.group.key] = _aliases(best, tests)
        removed = []
        while len(sel.chosen) > 1:
            drops = {g.key: _drop_test(p, sel.chosen, g, alpha, n_boot, seed + 100 * index) for g in sel.chosen[:-1]}
            p_drop = {k: 1.0 if t is None else t.p_value for k, t in drops.items()}
            worst = max(p_drop, key=lambda k: p_drop[k])
            if p_drop[worst] < alpha:
                break
            sel.chosen = [g for g in sel.chosen if g.key != worst]
            removed.append(worst)
            dropped.add(worst)
        done = {(g.leg, g.variable) for g in sel.chosen if g.kind == GENERIC}
        sel.rejected.pop(best.group.key, None)
        remaining = [g for g in remaining if g.key != best.group.key and g.key not in dropped
                     and not (g.kind == GENERIC and (g.leg, g.variable) in done)]
        fit = fit_model(p, sel.chosen)
        sel.steps.append(Step(index, best.group.key, best.group.effect, best.group.kind, best.group.title, best.rank,
                              best.f_statistic, best.p_value, best.p_wild, best.p_gauss, cv_now, best.cv_rms_mm,
                              verify_accuracy(p, fit, sel.chosen), tuple(removed)))
        state, d_dl0 = _state(p, fit, sel.chosen)
    if sel.chosen:
        _swap(p, sel, [g for g in candidates if g.kind == LIBRARY], alpha, n_boot, seed + 999)
    return sel


def diagnose(
    rec: Recording, robot: Robot, *, alpha: float = DEFAULT_ALPHA, n_boot: int = 999, seed: int = 0,
    cmm_sigma_mm: float | None = None, max_steps: int = MAX_STEPS, generic: bool = True,
) -> Diagnosis:
    """Locate, name and model the physics that the rigid geometric model leaves out of a recording."""
    p = _problem(rec, robot)
    library, untestable = library_groups(p.ctx, robot)
    candidates = library + (generic_groups(p.ctx) if generic else [])
    geo = fit_model(p, [])
    state, d_dl0 = _state(p, geo, [])
    cv_geometry = state.cv_rms(state.loo.residuals(state.r0))[1]

    sel = _select(p, candidates, alpha, n_boot, seed, max_steps, state, d_dl0)
    chosen, steps, rejected, alternatives = sel.chosen, sel.steps, sel.rejected, sel.alternatives
    cv_final = _cv_mm(p, chosen) if chosen else cv_geometry

    final = fit_model(p, chosen, bounded=True)
    r_final, J_final = residual_function(p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm,
                                         p.phi_of(chosen))(final.x)
    cov = cluster_robust_covariance(J_final, r_final, p.mea.n)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    before = verify_accuracy(p, geo, [])
    after = verify_accuracy(p, final, chosen)

    residuals_all = pose_difference(rec.meas, predict(p, geo, [], np.ones(rec.n, dtype=bool)), p.length_mm)
    noise = noise_yardstick(rec, robot, residuals_all, p.length_mm, cmm_sigma_mm)
    r_geo, J_geo = residual_function(p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm)(geo.x)
    ratio = None
    if noise.chosen is not None:
        ratio = noise_comparison(p.robot, p.mea.meas, noise.chosen.covariance[p.measure], (r_geo, J_geo),
                                 (r_final, J_final), p.length_mm)
    shift = session_shift(p.ctx_all, p.measure, leg_residuals(p, final, chosen), rec,
                          lambda rows, offsets: predict(p, final, chosen, rows, offsets))
    shapes = shapes_for(robot, p.ctx, final, cov, J_final, chosen, steps, before, alternatives, seed)

    effects: list[str] = []
    for g in chosen:
        if g.effect not in effects:
            effects.append(g.effect)
    if ratio is not None and ratio.ratio_final >= explain.FAR_ABOVE_NOISE and "unexplained" not in effects:
        effects.append("unexplained")
    effect = effects[0] if effects else "none"
    params = {n: float(v) for n, v in zip(final.names[N_GEO:], final.x[N_GEO:], strict=True)}
    std = {n: float(s) for n, s in zip(final.names[N_GEO:], se[N_GEO:], strict=True)}
    leg_res = leg_residuals(p, geo, [])
    findings = locate(p.ctx_all, rec, leg_res)
    explanation = explain.compose(effect, effects, chosen, steps, params, std, noise, ratio, shapes, shift,
                                  rejected, untestable, sel.ambiguous, before, after, findings)
    log.info("diagnosed", effects=effects, steps=len(steps))
    return Diagnosis(
        effect=effect, effects=tuple(effects), explanation=explanation, parameters=params, std_errors=std,
        before=before, after=after, steps=tuple(steps),
        candidates=_candidate_results(sel.first_tests, library, untestable, {g.key for g in chosen}),
        rejected=tuple(rejected.items()), ambiguous_with=sel.ambiguous, cv_rms_geometry_mm=cv_geometry,
        cv_rms_final_mm=cv_final, noise=noise, noise_ratio=ratio, shapes=tuple(shapes), session_shift=shift,
        findings=findings, groups=tuple(chosen), geometry_fit=geo, final_fit=final, leg_residuals_mm=leg_res,
        leg_residuals_final_mm=leg_residuals(p, final, chosen), context=p.ctx_all, measure=p.measure,
    )
