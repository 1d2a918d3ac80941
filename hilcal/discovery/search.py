"""Missing-physics discovery: calibrate the geometry, then add, one at a time, what the residuals demand.

The rule (docs/diagnosis.md):
1. Fit the 42 geometric parameters by least squares on the `measure` rows (forward pose residuals).
2. Forward selection over the library physics that the machine's kind admits (`hilcal.discovery.physics`) and
   the generic per-leg shapes (`hilcal.discovery.generic_terms`): at each step every remaining group is tested
   against the current model (`hilcal.discovery.selection`: added-variable F with min-P adjusted wild-bootstrap
   and Gaussian p-values, held-out PRESS in mm, graded plausibility); the eligible group with the largest held-out
   gain in mm is added (named physics wins when it explains nearly as much; near-aliases are settled by the
   evidence with each parameter's graded prior, `hilcal.discovery.aliases`), the model is refitted, and the search
   goes on until nothing passes.
3. The residual is compared with an absolute noise yardstick (`hilcal.discovery.noise`): "within noise" is only said
   with a noise level in mm and its source; a residual far above the noise that nothing explains is
   `unexplained`, never `none`.
4. The final model is refitted with every library parameter inside its possible range and the generic shapes held
   to the size the data shows; it is exported as one consistent compensation set (`hilcal.discovery.corrections`).
   The verify rows (never used for choosing) show what each step buys on held-out poses; a step that makes them
   worse (judged with any reported session shift removed) is not confirmed, and its group is left out of the
   exported set (refitted without it) unless `include_unconfirmed`.
5. Rows the model cannot speak for are left out and the search runs again (`hilcal.discovery.screen`): rows whose
   history terms are unknown, and measurement outliers; the context is computed once on the whole recording, so
   leaving rows out changes no other row's regressors.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import structlog
from threadpoolctl import threadpool_limits

from hilcal.discovery import explain
from hilcal.discovery.aliases import named_aliases, period_aliases, resolve
from hilcal.discovery.context import EffectContext
from hilcal.discovery.corrections import compensation_set
from hilcal.discovery.findings import (
    END_STOP_TOLERANCE_MM,
    end_stops,
    locate,
    noise_comparison,
    session_shift,
    zero_offsets,
    zero_sentence,
)
from hilcal.discovery.fitting import (
    Problem,
    final_covariance,
    final_fit,
    fit_model,
    groups_columns,
    judged_verify_mm,
    leg_residuals,
    linearized,
    mean_residual_variance,
    model_name,
    model_state,
    predict,
    shape_scales,
    unknown_terms,
    verify_accuracy,
)
from hilcal.discovery.generic_terms import generic_groups, refine_period
from hilcal.discovery.naming import named_effects
from hilcal.discovery.noise import NoiseLevel, noise_yardstick, sphere_noise_covariance, sphere_sources
from hilcal.discovery.physics import library_groups
from hilcal.discovery.result import Diagnosis, SessionShift, Step, candidate_results
from hilcal.discovery.screen import (
    OUTLIER_FACTOR,
    Screened,
    outlier_sentence,
    screen_rows,
    unknown_json,
    unknown_rows,
    unknown_sentence,
)
from hilcal.discovery.selection import GroupTest, assess, choose
from hilcal.discovery.shapes import shapes_for
from hilcal.discovery.stations import with_stations
from hilcal.discovery.term_groups import GENERIC, LIBRARY, TermGroup, stack_phi
from hilcal.error_models import pose_difference
from hilcal.identification import IdentificationResult
from hilcal.kinematics import forward_kinematics
from hilcal.recording import Recording
from hilcal.robot import Robot
from hilcal.wiring import LegWiring, check_wiring

log = structlog.get_logger(__name__)

N_GEO = 42
MAX_STEPS = 8
DEFAULT_ALPHA = 0.02
"""Family-wise false-alarm rate of a diagnosis on a recording without missing physics (library and generic
families share it); step k of the search uses alpha / k."""
WIRING = "leg_wiring"
"""The effect name of a set-up fault in the leg readings' order or direction (hilcal.wiring)."""
@dataclasses.dataclass
class _Selection:
    """The outcome of forward selection with backward elimination."""

    chosen: list[TermGroup]
    steps: list[Step]
    first_tests: list[GroupTest]
    rejected: dict[str, str]
    alternatives: dict[str, tuple[TermGroup, ...]]
    alike: dict[str, tuple[GroupTest, ...]]
    """Per chosen library group: the library groups that looked like it when it was chosen."""
    chosen_tests: dict[str, GroupTest]
    evidence: dict[str, dict[str, float]]
    fit: IdentificationResult
    models: list[tuple[list[TermGroup], IdentificationResult]] = dataclasses.field(default_factory=list)
    """The model after every step (groups and fit), for the held-out verdict of each step."""
    screened: Screened | None = None
    """The screen that stopped the selection early (`_select`'s `early`), else None."""


def _drop_test(p: Problem, chosen: list[TermGroup], group: TermGroup, alpha: float, n_boot: int,
               seed: int, start: IdentificationResult) -> GroupTest | None:
    """The test of a chosen group given all the others (None when the others absorb it)."""
    others = [g for g in chosen if g is not group]
    state, d_dl0 = model_state(p, fit_model(p, others, start), others)
    tests = assess(state, [group], groups_columns(p, state, d_dl0, [group]), alpha, n_boot, seed)
    return tests[0] if tests else None


def _drop_tests(p: Problem, chosen: list[TermGroup], alpha: float, n_boot: int, seed: int,
                start: IdentificationResult) -> dict[str, GroupTest | None]:
    """`_drop_test` of every chosen group but the last, two at a time (each is a fit and a test of its own); fits that
    did not converge are named in the order the tests would have run one after the other."""
    first = len(p.not_converged)
    with ThreadPoolExecutor(max_workers=2) as pool:
        tests = list(pool.map(lambda g: _drop_test(p, chosen, g, alpha, n_boot, seed, start), chosen[:-1]))
    serial = [model_name([c for c in chosen if c is not g]) for g in chosen[:-1]]
    p.not_converged[first:] = sorted(p.not_converged[first:], key=lambda n: serial.index(n) if n in serial else 0)
    return dict(zip([g.key for g in chosen[:-1]], tests, strict=True))


def _cv_mm(p: Problem, groups: list[TermGroup], start: IdentificationResult) -> float:
    """Leave-one-cluster-out residual RMS (mm) of a model: comparable across models."""
    state, _ = model_state(p, fit_model(p, groups, start), groups)
    return state.cv_mm


def _swap(p: Problem, sel: _Selection, library: list[TermGroup], alpha: float, n_boot: int, seed: int) -> None:
    """Replace a chosen library effect by another when that predicts held-out poses better (greedy is myopic)."""
    best_cv = _cv_mm(p, sel.chosen, sel.fit)
    improved = True
    while improved:
        improved = False
        chosen_keys = {g.key for g in sel.chosen}
        for old in [g for g in sel.chosen if g.kind == LIBRARY]:
            for new in library:
                if new.key in chosen_keys or new.key in sel.rejected:
                    continue
                trial = [new if g is old else g for g in sel.chosen]
                cv = _cv_mm(p, trial, sel.fit)
                if cv >= best_cv:
                    continue
                test = _drop_test(p, trial, new, alpha, n_boot, seed, sel.fit)
                if test is None or not test.eligible:
                    continue
                fit = fit_model(p, trial, sel.fit)
                sel.chosen, sel.fit, best_cv, improved = trial, fit, cv, True
                sel.models.append((list(trial), fit))
                sel.chosen_tests[new.key] = test
                sel.steps.append(Step(len(sel.steps) + 1, new.key, new.effect, new.kind, new.title, test.rank,
                                      test.f_statistic, test.p_value, test.p_wild, test.p_gauss,
                                      sel.steps[-1].cv_rms_mm, cv, verify_accuracy(p, fit, trial), (old.key,)))
                break
            if improved:
                break


def _select(p: Problem, candidates: list[TermGroup], alpha: float, n_boot: int, seed: int, max_steps: int,
            geo: IdentificationResult, early: bool = False) -> _Selection:
    """Forward selection (alpha / k at step k) with backward elimination of groups that the later ones explain.

    With `early`, the selection stops after the first step whose model finds rows to leave out (`screen_rows`): the
    search will run again without them, so its later steps would be spent for nothing."""
    sel = _Selection([], [], [], {}, {}, {}, {}, {}, geo)
    state, d_dl0 = model_state(p, geo, [])
    remaining = list(candidates)
    dropped: set[str] = set()
    for index in range(1, max_steps + 1):
        cv_now = state.cv_mm
        columns = groups_columns(p, state, d_dl0, remaining)
        tests = assess(state, remaining, columns, alpha / index, n_boot, seed + index)
        if index == 1:
            sel.first_tests = tests
        for t in tests:
            if t.rejected and t.significant:
                sel.rejected[t.group.key] = t.rejected
        best = choose(tests)
        if best is not None:
            settled = resolve(best, tests, state.dof)
            best = settled.chosen
            sel.alike[best.group.key] = settled.similar
            if settled.log_evidence:
                sel.evidence[best.group.key] = settled.log_evidence
        log.info("selection_step", step=index, n_candidates=len(tests), chosen=None if best is None else best.group.key)
        if best is None:
            break
        if best.group.period_mm is not None:
            whitened_d = np.einsum("ij,njl->nil", state.W, d_dl0)
            best = dataclasses.replace(best, group=refine_period(best.group, p.ctx, whitened_d, state.Q, state.r0))
        sel.chosen.append(best.group)
        sel.chosen_tests[best.group.key] = best
        if best.group.period_mm is not None:
            sel.alternatives[best.group.key] = period_aliases(best, tests)
        removed = []
        while len(sel.chosen) > 1:
            drops = _drop_tests(p, sel.chosen, alpha, n_boot, seed + 100 * index, sel.fit)
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
        sel.fit = fit_model(p, sel.chosen, sel.fit)
        sel.models.append((list(sel.chosen), sel.fit))
        sel.steps.append(Step(index, best.group.key, best.group.effect, best.group.kind, best.group.title, best.rank,
                              best.f_statistic, best.p_value, best.p_wild, best.p_gauss, cv_now, best.cv_rms_mm,
                              verify_accuracy(p, sel.fit, sel.chosen), tuple(removed)))
        state, d_dl0 = model_state(p, sel.fit, sel.chosen)
        if early:
            screened = screen_rows(sel.chosen, p.ctx, state.left_out_norms_mm())
            if screened.any:
                sel.screened = screened
                return sel
    if sel.chosen:
        _swap(p, sel, [g for g in candidates if g.kind == LIBRARY], alpha, n_boot, seed + 999)
    return sel


def diagnose(
    rec: Recording, robot: Robot, *, alpha: float = DEFAULT_ALPHA, n_boot: int = 999, seed: int = 0,
    cmm_sigma_mm: float | None = None, max_steps: int = MAX_STEPS, generic: bool = True,
    pose_sigma: tuple[float, float] | None = None, include_unconfirmed: bool = False,
) -> Diagnosis:
    """Locate, name and model the physics that the rigid geometric model leaves out of a recording.

    The noise yardstick may be stated: ``cmm_sigma_mm`` (sphere centres, through the robot file's sphere layout) or
    ``pose_sigma`` (mm per position coordinate, degrees per orientation axis: a tracker's 6-DoF probe).
    ``include_unconfirmed`` keeps the groups whose step made the held-out verify figure worse in the exported
    compensation set (by default they are left out of it, and its geometry is refitted without them).

    BLAS runs on one thread here: the matrices are small (6 N rows, tens of columns), so threads only add
    synchronisation, and on a busy PC their busy-waiting made the search several times slower
    (benchmarks/bench_diagnose.py)."""
    with threadpool_limits(limits=1, user_api="blas"):
        return with_stations(rec, robot, lambda r: _diagnose(
            r, robot, alpha=alpha, n_boot=n_boot, seed=seed, cmm_sigma_mm=cmm_sigma_mm, max_steps=max_steps,
            generic=generic, pose_sigma=pose_sigma, include_unconfirmed=include_unconfirmed))


def _titles(groups: tuple[TermGroup, ...]) -> dict[str, str]:
    return {g.key: g.effect if g.kind == LIBRARY else g.title for g in groups}


def _with_sentence(diag: Diagnosis, said: str, first: bool) -> Diagnosis:
    """The diagnosis with one more summary sentence: first, or after the others (before the evidence)."""
    if first:
        return dataclasses.replace(diag, summary=(said, *diag.summary), explanation=f"{said} {diag.explanation}")
    text = diag.explanation
    if diag.evidence and text.endswith(diag.evidence):
        text = f"{text[:-len(diag.evidence)]}{said} {diag.evidence}"
    else:
        text = f"{text} {said}"
    return dataclasses.replace(diag, summary=(*diag.summary, said), explanation=text)


def _diagnose(rec: Recording, robot: Robot, *, alpha: float, n_boot: int, seed: int, cmm_sigma_mm: float | None,
              max_steps: int, generic: bool, pose_sigma: tuple[float, float] | None,
              include_unconfirmed: bool) -> Diagnosis:
    wiring = check_wiring(rec.legs_mm, rec.meas, robot)
    if wiring.problem:
        log.info("leg_wiring", problem=wiring.sentence())
        if not wiring.dead:
            rec = dataclasses.replace(rec, legs_mm=wiring.corrected(rec.legs_mm))
    kwargs = {"alpha": alpha, "n_boot": n_boot, "seed": seed, "cmm_sigma_mm": cmm_sigma_mm, "max_steps": max_steps,
              "generic": generic, "pose_sigma": pose_sigma}
    ctx = EffectContext.from_recording(rec, robot)
    unit = (sphere_noise_covariance(robot, rec.meas, 1.0, robot.characteristic_length_mm)
            if sphere_sources(rec, robot, cmm_sigma_mm) else None)

    def rows(keep: np.ndarray | None) -> dict[str, Any]:
        """The per-row inputs worked out once on the whole recording, for its kept rows."""
        return {"unit_covariance": unit if unit is None or keep is None else unit[keep]}

    described = {"seed": seed, "include_unconfirmed": include_unconfirmed}
    searched = _searched(rec, robot, ctx, early=True, **kwargs, **rows(None))
    screened = searched.screened()
    if not screened.any:
        return _wired(_describe(searched, robot, **described), wiring)
    measure_rows = np.flatnonzero(rec.phase == "measure")
    leave = _left_out_rows(screened, measure_rows, rec.n)
    again = _searched(rec.rows(~leave), robot, ctx.rows(~leave), **kwargs, **rows(~leave))
    if searched.early and not _confirmed(again, screened, rec, ctx, measure_rows):
        log.info("early_screen_not_confirmed")
        searched = _searched(rec, robot, ctx, **kwargs, **rows(None))
        screened = searched.screened()
        leave = _left_out_rows(screened, measure_rows, rec.n)
        again = _searched(rec.rows(~leave), robot, ctx.rows(~leave), **kwargs, **rows(~leave))
    return _wired(_with_rows_left_out(_describe(again, robot, stops_from=rec, **described), screened, searched, rec,
                                      measure_rows), wiring)


def _left_out_rows(screened: Screened, measure_rows: np.ndarray, n: int) -> np.ndarray:
    """[n] the rows of the recording to leave out: outliers and rows whose terms are unknown."""
    leave = np.zeros(n, dtype=bool)
    leave[measure_rows[np.concatenate([screened.outliers, screened.found.rows]).astype(int)]] = True
    return leave


def _confirmed(again: _Searched, screened: Screened, rec: Recording, ctx: EffectContext,
               measure_rows: np.ndarray) -> bool:
    """Whether the rows an early screen left out are what the model fitted without them says: every outlier's
    left-out residual still beyond OUTLIER_FACTOR times the median, every row of unknown history still unknown to its
    terms, and no further row to leave out."""
    if again.screened().any:
        return False
    rows = measure_rows[screened.outliers]
    median = again.screened().median_mm
    if rows.size and np.any(again.predicted_mm(rec.rows(rows), ctx.rows(rows)) <= OUTLIER_FACTOR * median):
        return False
    unknown = measure_rows[screened.found.rows]
    return bool(not unknown.size or set(unknown_rows(again.sel.chosen, ctx.rows(unknown)).rows.tolist())
                == set(range(unknown.size)))


def _with_rows_left_out(diag: Diagnosis, screened: Screened, searched: _Searched, rec: Recording,
                        measure_rows: np.ndarray) -> Diagnosis:
    """The diagnosis of the kept rows with the sentences and JSON of the rows left out."""
    left_out, median = screened.left_out_mm, screened.median_mm
    rows = measure_rows[screened.outliers]
    excluded = tuple({"seq": float(rec.seq[r]), "left_out_mm": float(left_out[k]),
                      "times_median": float(left_out[k] / median)}
                     for r, k in zip(rows, screened.outliers, strict=True))
    unknown = unknown_json(screened.found, rec.seq[measure_rows], left_out, median)
    log.info("rows_left_out", outliers=[e["seq"] for e in excluded], unknown=[e["seq"] for e in unknown])
    if rows.size:
        at_stop = {int(r): f", leg {s.leg} at its {s.extreme}" for r in rows for s in diag.end_stops
                   if abs(rec.legs_mm[r, s.leg - 1] - s.reading_mm) <= END_STOP_TOLERANCE_MM}
        diag = _with_sentence(diag, outlier_sentence(rows, excluded, median, at_stop), True)
    said = unknown_sentence(screened.found, unknown, searched.p.ctx, _titles(tuple(searched.sel.chosen)))
    if said:
        diag = _with_sentence(diag, said, False)
    return dataclasses.replace(diag, excluded=excluded, unknown_rows=unknown)


def _wired(diag: Diagnosis, wiring: LegWiring) -> Diagnosis:
    """The diagnosis with the leg-wiring check: a set-up fault sentence first when the readings were re-ordered."""
    if not wiring.problem:
        return dataclasses.replace(diag, wiring=wiring)
    said = wiring.sentence([f"leg{i}_mm" for i in range(1, 7)])
    first = f"Set-up fault (leg wiring): {said[0].upper()}{said[1:]}" + (
        "; the legs are re-ordered and mirrored as found for everything below." if not wiring.dead else
        "; the reading that follows no leg cannot be corrected, so everything below is unreliable.")
    compensation = diag.compensation
    if compensation is not None and not wiring.dead:
        wired = wiring.to_json()
        compensation = dataclasses.replace(compensation, readings={
            k: wired[k] for k in ("column_of_leg", "reversed_legs", "mirror_mm", "rule")})
    return dataclasses.replace(diag, wiring=wiring, effects=(WIRING, *diag.effects), effect=WIRING,
                               summary=(first, *diag.summary), explanation=f"{first} {diag.explanation}",
                               compensation=compensation)


def _judge(p: Problem, geo: IdentificationResult, sel: _Selection, shift: SessionShift | None) -> list[Step]:
    """Every step with its held-out verify figure before and after, judged with any reported session shift
    removed (the verify rows never choose; they only confirm or not)."""
    legs = () if shift is None else shift.legs
    if legs:
        figures = [judged_verify_mm(p, geo, [], legs)] + [judged_verify_mm(p, fit, groups, legs)
                                                           for groups, fit in sel.models]
    else:
        before = verify_accuracy(p, geo, [])
        figures = [None if before is None else before.position_mm.rms] + [
            None if s.verify is None else s.verify.position_mm.rms for s in sel.steps]
    return [dataclasses.replace(s, judged_before_mm=figures[k], judged_mm=figures[k + 1])
            for k, s in enumerate(sel.steps)]


@dataclasses.dataclass
class _Searched:
    """The selection on one set of rows: the problem, its library, the geometry-only fit, the noise and the steps."""

    rec: Recording
    p: Problem
    library: list[TermGroup]
    untestable: dict[str, str]
    geo: IdentificationResult
    cv_geometry: float
    leg_res: np.ndarray
    noise: NoiseLevel
    sel: _Selection

    @property
    def early(self) -> bool:
        """The selection stopped at its first step that found rows to leave out."""
        return self.sel.screened is not None

    def screened(self) -> Screened:
        """The screen of the measure rows under the selected model (or the model that stopped it early)."""
        if self.sel.screened is not None:
            return self.sel.screened
        chosen = self.sel.chosen
        state = model_state(self.p, self.sel.fit if chosen else self.geo, chosen)[0]
        return screen_rows(chosen, self.p.ctx, state.left_out_norms_mm())

    def predicted_mm(self, rec: Recording, ctx: EffectContext) -> np.ndarray:
        """Per row of another set of rows: the length (mm, rotations at the platform's length) of the selected
        model's residual there; for rows the fit left out, their left-out residual."""
        chosen, fit = self.sel.chosen, self.sel.fit if self.sel.chosen else self.geo
        legs = rec.legs_mm + (stack_phi(chosen, ctx) @ fit.x[N_GEO:] if chosen else 0.0)
        predicted = forward_kinematics(fit.geometry(self.p.robot), legs, rec.meas)
        return np.linalg.norm(pose_difference(rec.meas, predicted, self.p.length_mm), axis=1)


def _searched(rec: Recording, robot: Robot, ctx: EffectContext, *, alpha: float, n_boot: int, seed: int,
              cmm_sigma_mm: float | None, max_steps: int, generic: bool,
              pose_sigma: tuple[float, float] | None, early: bool = False,
              unit_covariance: np.ndarray | None = None) -> _Searched:
    """Geometry, noise yardstick and forward selection on `rec` as given, with `ctx` its rows' context (computed on
    the whole recording when `rec` is a subset of it; so is `unit_covariance`, see `noise_yardstick`); `early`: see
    `_select`."""
    p = Problem.of(rec, robot, ctx)
    library, untestable = library_groups(p.ctx, robot)
    limits = (robot.leg_limits[0] - robot.l0, robot.leg_limits[1] - robot.l0)
    candidates = library + (generic_groups(p.ctx, limits) if generic else [])
    geo = fit_model(p, [], label="geometry only")
    cv_geometry = model_state(p, geo, [])[0].cv_mm
    leg_res = leg_residuals(p, geo, [])
    residuals_all = pose_difference(rec.meas, predict(p, geo, [], np.ones(rec.n, dtype=bool)), p.length_mm)
    noise = noise_yardstick(rec, robot, residuals_all, p.length_mm, cmm_sigma_mm, pose_sigma, p.ctx_all.session,
                            unit_covariance)
    p.shape_prior = (shape_scales(leg_res[p.measure]), None if noise.chosen is None else max(
        float(np.sqrt(np.mean(np.trace(noise.covariance[p.measure], axis1=1, axis2=2)) / 6.0)), 1e-9))
    sel = _select(p, candidates, alpha, n_boot, seed, max_steps, geo, early)
    return _Searched(rec, p, library, untestable, geo, cv_geometry, leg_res, noise, sel)


def _describe(s: _Searched, robot: Robot, *, seed: int, include_unconfirmed: bool,
              stops_from: Recording | None = None) -> Diagnosis:
    """The diagnosis of a selection: the final bounded fit, held-out figures and verdicts, noise comparison, shapes,
    aliases, the compensation set and the answer in words; end stops are looked for in `stops_from`, the rows
    before any exclusion."""
    rec, p, geo, sel, noise, leg_res = s.rec, s.p, s.geo, s.sel, s.noise, s.leg_res
    chosen, rejected, alternatives = sel.chosen, sel.rejected, sel.alternatives
    cv_final = _cv_mm(p, chosen, sel.fit) if chosen else s.cv_geometry
    scales, noise_mm = p.shape_prior[0], max(sel.fit.rms_residual, 1e-6)
    final = final_fit(p, chosen, sel.fit if chosen else geo, scales, noise_mm)
    with ThreadPoolExecutor(max_workers=1) as pool:
        # What separates the named near-aliases (pose augmentation) needs only the final fit: found meanwhile.
        aliasing = pool.submit(named_aliases, p, sel.chosen, sel.chosen_tests, sel.alike, sel.evidence, final, seed)
        r_final, J_final = linearized(p, chosen, final.x)
        cov, misfit = final_covariance(p, final, chosen, noise, scales, noise_mm)
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        final = dataclasses.replace(final, covariance=cov, std_errors=se)
        before = verify_accuracy(p, geo, [])
        after = verify_accuracy(p, final, chosen)

        r_geo, J_geo = linearized(p, [], geo.x)
        ratio = None
        if noise.chosen is not None:
            ratio = noise_comparison(p.robot, p.mea.meas, noise.covariance[p.measure], (r_geo, J_geo),
                                     (r_final, J_final), p.length_mm)
        shift = session_shift(p.ctx_all, p.measure, leg_residuals(p, final, chosen), rec,
                              lambda rows, offsets: predict(p, final, chosen, rows, offsets), unknown_terms(p, chosen),
                              lambda rows: mean_residual_variance(p, final, chosen, cov, rows))
        steps = _judge(p, geo, sel, shift)
        chosen_keys = {g.key for g in chosen}
        unconfirmed = tuple(dict.fromkeys(s.key for s in steps if s.confirmed is False and s.key in chosen_keys))
        loadable = chosen if include_unconfirmed else [g for g in chosen if g.key not in unconfirmed]
        model_terms = compensation_set(p.ctx_all, final, chosen)
        loadable_fit, compensation = final, model_terms
        if len(loadable) < len(chosen):
            refit = fit_model(p, loadable, sel.fit) if loadable else geo
            loadable_fit = final_fit(p, loadable, refit, scales, noise_mm)
            compensation = compensation_set(p.ctx_all, loadable_fit, loadable)
        compensation_after = after if loadable_fit is final else verify_accuracy(p, loadable_fit, loadable)
        shapes = shapes_for(robot, p.ctx, final, cov, J_final, chosen, steps, before, alternatives, seed)
        left_out = model_state(p, final, chosen)[0].left_out_norms_mm()
        offsets = zero_offsets(robot, final.geometry(robot))
        zero_said = zero_sentence(robot, offsets)
        aliases = aliasing.result()

    effects: list[str] = []
    for g in chosen:
        if g.effect not in effects:
            effects.append(g.effect)
    if ratio is not None and ratio.ratio_final >= explain.FAR_ABOVE_NOISE and "unexplained" not in effects:
        effects.append("unexplained")
    effect = effects[0] if effects else "none"
    params = {n: float(v) for n, v in zip(final.names[N_GEO:], final.x[N_GEO:], strict=True)}
    std = {n: float(s) for n, s in zip(final.names[N_GEO:], se[N_GEO:], strict=True)}
    named = named_effects(chosen, params, std, p.ctx)
    findings = locate(p.ctx_all, rec, leg_res)
    stops = end_stops(rec if stops_from is None else stops_from, robot)
    verdict = explain.Verdict(unconfirmed, include_unconfirmed, compensation_after, bool(shift and shift.legs))
    answer = explain.Answer(
        effect, effects, chosen, steps, params, std, noise, ratio, shapes, shift, rejected, s.untestable, aliases,
        before, after, findings, named, stops, tuple(p.not_converged), model_terms, verdict,
    )
    log.info("diagnosed", effects=effects, steps=len(steps), not_converged=p.not_converged, unconfirmed=unconfirmed)
    diag = Diagnosis(
        effect=effect, effects=tuple(effects), explanation=explain.compose(answer), parameters=params, std_errors=std,
        before=before, after=after, steps=tuple(steps),
        candidates=candidate_results(sel.first_tests, s.library, s.untestable, chosen_keys),
        rejected=tuple(rejected.items()), ambiguous_with=tuple(a.other for a in aliases),
        cv_rms_geometry_mm=s.cv_geometry, cv_rms_final_mm=cv_final, noise=noise, noise_ratio=ratio,
        shapes=tuple(shapes), session_shift=shift, findings=findings, groups=tuple(chosen), geometry_fit=geo,
        final_fit=final, leg_residuals_mm=leg_res, leg_residuals_final_mm=leg_residuals(p, final, chosen),
        context=p.ctx_all, measure=p.measure, named=named, aliases=aliases, end_stops=stops,
        not_converged=tuple(p.not_converged), compensation=compensation,
        summary=(*([zero_said] if zero_said else []), *explain.summary_sentences(answer)),
        evidence=explain.evidence(answer), left_out_mm=left_out, zero_offsets_mm=offsets,
        unconfirmed=unconfirmed, compensation_after=compensation_after, misfit=misfit,
    )
    if misfit is not None and misfit.noise is not None:
        said = misfit.noise.sentence()
        diag = dataclasses.replace(diag, explanation=f"{diag.explanation} {said}", evidence=f"{diag.evidence} {said}")
    return _with_sentence(diag, misfit.sentence("the parameters"), False) if misfit and misfit.incomplete else diag
