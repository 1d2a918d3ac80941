"""The diagnosis' model: the fixed inputs of one diagnosis, least-squares fits of geometry plus effect groups,
and what a fitted model predicts (poses, leg residuals, held-out accuracy).

Fits start from the previous model's parameters (warm start) and fall back to a fresh start when that does not
converge; the final fit keeps every library parameter inside its physically possible range and holds the
generic shapes to the size the data shows (a Gaussian prior on the correction, so a shape cannot cancel against
the refitted geometry with metres of opposite corrections).
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable

import numpy as np
import structlog
from scipy.optimize import lsq_linear

from hilcal.discovery.context import EffectContext
from hilcal.discovery.noise import NoiseLevel, find_repeats, temperature_noise
from hilcal.discovery.regression import cluster_robust_covariance, pooled_whitener, whiten
from hilcal.discovery.selection import Columns, ModelState
from hilcal.discovery.term_groups import GENERIC, TermGroup
from hilcal.error_models import GEOMETRIC_42, implicit_residuals
from hilcal.identification import IdentificationResult, residual_function
from hilcal.kinematics import KinematicsError, forward_kinematics
from hilcal.metrics import AccuracySummary
from hilcal.misfit import Misfit, NoiseParts, honest_covariance
from hilcal.recording import Recording
from hilcal.robot import Robot
from hilcal.stations import StationFrames, remove_frames

log = structlog.get_logger(__name__)

N_GEO = 42
DL0_COLUMNS = [7 * i + 6 for i in range(6)]
CACHED = 8
"""Entries per cache of a Problem: a search step asks again only for the last few models."""
MANY_GROUPS = 50
"""A candidate list this long is the search's (its regressors are kept as one block, `Problem.phi_columns`)."""
LENGTH_PROPORTIONAL = ("axial_force", "temperature", "time", "time_lag")
"""Generic variables whose physics grows with the leg's length (strain under load, thermal growth): their shapes
carry a possible scaling with it (`hilcal.misfit`). A shape in the stroke is a function of the length already; one in
the joint angles (joint geometry) or the last move (hysteresis) does not grow with it."""
DRIFT = ("time", "time_lag", "temperature")
"""Generic variables of a leg whose length drifts: its level between sessions is not pinned (`hilcal.misfit`)."""


@dataclasses.dataclass
class Problem:
    """The fixed inputs of one diagnosis: robot, rows, contexts and the cluster structure for held-out residuals."""

    robot: Robot
    rec: Recording
    measure: np.ndarray
    ctx_all: EffectContext
    ctx: EffectContext
    mea: Recording
    ver: Recording
    clusters: np.ndarray
    phi_cache: dict[str | tuple[str, str], np.ndarray] = dataclasses.field(default_factory=dict)
    shape_prior: tuple[np.ndarray, float | None] | None = None
    """(per-leg scale in mm, noise per residual component in mm or None) of the generic shapes' Gaussian prior
    (`prior_rows`), once the geometry-only fit has set it: every fit with a generic group then holds the shapes to
    the size the data shows. Without a noise level, each fit takes its start's residual RMS."""
    not_converged: list[str] = dataclasses.field(default_factory=list)
    """Fits that stopped before converging (named in the answer)."""
    linearized: dict[tuple, tuple[np.ndarray, np.ndarray]] = dataclasses.field(default_factory=dict)
    """(r, J) of the measure rows at a fit's solution, by (parameter names, x): what the fit's last step computed,
    so that the model's linearization (`model_state`) need not compute it again."""
    states: dict[tuple, tuple[ModelState, np.ndarray]] = dataclasses.field(default_factory=dict)
    """`model_state` by (parameter names, x): the search asks for the same model's state more than once."""
    fits: dict[tuple, IdentificationResult] = dataclasses.field(default_factory=dict)
    """`fit_model` by (groups, start, prior, label): a refit from a model's own solution is asked for again."""
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock, repr=False)
    phi_block: tuple[np.ndarray, dict[str, tuple[int, int]]] | None = None
    """The regressors of the first long candidate list, concatenated in their width order, with each group's
    columns: the search's later lists are subsets of it, taken in one gather instead of concatenated again."""

    def phi_columns(self, groups: list[TermGroup], order: np.ndarray) -> np.ndarray:
        """[N, 6, total] the groups' regressors concatenated in `order` (the same numbers as concatenating them)."""
        ranges = self.phi_block[1] if self.phi_block is not None else {}
        ordered = [groups[k] for k in order.tolist()]
        if len(groups) < MANY_GROUPS or not all(g.key in ranges for g in ordered):
            block = np.concatenate([self.phi(g) for g in ordered], axis=2)
            if len(groups) >= MANY_GROUPS:
                starts = np.cumsum([0] + [self.phi(g).shape[2] for g in ordered])
                self.phi_block = (block, {g.key: (int(a), int(b)) for g, a, b in zip(ordered, starts[:-1], starts[1:],
                                                                                      strict=True)})
            return block
        columns = np.concatenate([np.arange(*ranges[g.key]) for g in ordered])
        return np.take(self.phi_block[0], columns, axis=2)

    def remember(self, cache: dict, key: tuple, value: object) -> None:
        """Keep value under key, with at most CACHED entries (the oldest goes first); read with `get` (the search's
        drop tests run in two threads)."""
        with self.lock:
            if len(cache) >= CACHED:
                cache.pop(next(iter(cache)))
            cache[key] = value

    @classmethod
    def of(cls, rec: Recording, robot: Robot, ctx_all: EffectContext | None = None) -> Problem:
        """`ctx_all`: the rows' context when they are a subset of a longer recording (computed on the whole
        recording, so leaving rows out changes no other row's history, session or time); else from `rec`."""
        measure = rec.phase == "measure"
        if ctx_all is None:
            ctx_all = EffectContext.from_recording(rec, robot)
        if ctx_all.n != rec.n:
            raise ValueError(f"the context has {ctx_all.n} rows, the recording {rec.n}")
        mea = rec.select("measure")
        labels = np.arange(mea.n)
        for group in find_repeats(mea, ctx_all.session[measure]):
            labels[group] = group[0]
        return cls(robot, rec, measure, ctx_all, ctx_all.rows(measure), mea, rec.select("verify"), labels)

    @property
    def length_mm(self) -> float:
        return self.robot.characteristic_length_mm

    def phi(self, group: TermGroup) -> np.ndarray:
        if group.key not in self.phi_cache:
            self.phi_cache[group.key] = group.phi(self.ctx)
        return self.phi_cache[group.key]

    def phi_all(self, groups: list[TermGroup]) -> np.ndarray:
        """[N, 6, q] the groups' regressors on every row of the recording (each group's computed once)."""
        for g in groups:
            if ("all", g.key) not in self.phi_cache:
                self.phi_cache[("all", g.key)] = g.phi(self.ctx_all)
        return np.concatenate([self.phi_cache[("all", g.key)] for g in groups], axis=2)

    def phi_of(self, groups: list[TermGroup]) -> np.ndarray | None:
        return np.concatenate([self.phi(g) for g in groups], axis=2) if groups else None


def names_of(groups: list[TermGroup]) -> tuple[str, ...]:
    return tuple(n for g in groups for n in g.names)


def _start(groups: list[TermGroup], start: IdentificationResult | None) -> np.ndarray | None:
    """The previous fit's values for the parameters both models share, zero for the new ones."""
    if start is None:
        return None
    values = dict(zip(start.names, start.x, strict=True))
    return np.array([values.get(n, 0.0) for n in GEOMETRIC_42.names + names_of(groups)])


GN_ITERATIONS = 30
GN_TOLERANCE = 1e-13
"""Gauss-Newton stops when a full step would lower the sum of squares by less than this fraction of it."""
RCOND = 1e-5
"""Singular values below this fraction of the largest (column-scaled Jacobian) are treated as zero: directions the
data cannot see get no step (minimum-norm steps), so a fit never drifts along them."""


def gauss_newton(fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], x0: np.ndarray,
                 max_iter: int | None = None, bounds: tuple[np.ndarray, np.ndarray] | None = None,
                 ) -> tuple[np.ndarray, np.ndarray, int, bool, str, np.ndarray]:
    """Least squares by Gauss-Newton with minimum-norm steps on the column-scaled Jacobian and step shortening.

    The diagnosis' models are linear in every effect parameter and nearly linear in the small geometric errors,
    so from a warm start a few steps reach the minimum; a Levenberg-Marquardt search with a trust region crawled for
    hundreds of evaluations along directions the poses hardly see (benchmarks/bench_diagnose.py). With `bounds`
    (x0 inside them), a step that would leave them is the bounded linear least-squares step instead.
    Returns (x, residuals, evaluations, converged, message, Jacobian at x)."""
    max_iter = GN_ITERATIONS if max_iter is None else max_iter
    x = np.asarray(x0, dtype=float).copy()
    r, J = fun(x)
    cost = float(r @ r)
    evaluations = 1
    for _ in range(max_iter):
        c = np.sqrt(np.mean(J**2, axis=0))
        c = np.where(c > 0, c, 1.0)
        d = np.linalg.lstsq(J / c, -r, rcond=RCOND)[0] / c
        if bounds is not None and np.any((x + d < bounds[0]) | (x + d > bounds[1])):
            d = lsq_linear(J / c, -r, bounds=((bounds[0] - x) * c, (bounds[1] - x) * c), method="bvls").x / c
        predicted = float(np.sum((J @ d) ** 2))
        if predicted <= GN_TOLERANCE * cost:
            return x, r, evaluations, True, "Gauss-Newton: the next step gains nothing", J
        t = 1.0
        while True:
            try:
                r_new, J_new = fun(x + t * d)
                new_cost = float(r_new @ r_new)
            except KinematicsError:
                new_cost = np.inf
            evaluations += 1
            if new_cost <= cost:
                break
            t *= 0.25
            if t < 1e-6:
                return x, r, evaluations, True, "Gauss-Newton: no step lowers the sum of squares", J
        x, r, J, cost = x + t * d, r_new, J_new, new_cost
    return x, r, evaluations, False, f"Gauss-Newton stopped after {max_iter} steps", J


def prior_rows(p: Problem, groups: list[TermGroup], shape_scale_mm: np.ndarray, noise_mm: float) -> np.ndarray:
    """Ridge rows [6 N, 42 + q] of the generic shapes' Gaussian prior: each shape's correction at every recorded row
    and leg, weighted by noise / scale (a prior of `shape_scale_mm` per leg); no rows without a generic group."""
    size = N_GEO + sum(g.n_params for g in groups)
    generic = np.zeros(size, dtype=bool)
    k = N_GEO
    for g in groups:
        generic[k:k + g.n_params] = g.kind == GENERIC
        k += g.n_params
    if not generic.any():
        return np.zeros((0, size))
    phi = p.phi_of(groups)
    assert phi is not None
    weight = noise_mm / np.maximum(np.asarray(shape_scale_mm, dtype=float), max(noise_mm, 1e-9))
    P = np.zeros((phi.shape[0] * 6, size))
    P[:, generic] = (weight[None, :, None] * phi[:, :, generic[N_GEO:]]).reshape(-1, int(generic.sum()))
    return P


def model_name(groups: list[TermGroup], label: str = "") -> str:
    """How a fit that did not converge is named in the answer."""
    return label or ("geometry" if not groups else "geometry + " + ", ".join(g.key for g in groups))


def fit_model(p: Problem, groups: list[TermGroup], start: IdentificationResult | None = None,
              label: str = "") -> IdentificationResult:
    """Least squares of geometry + groups on the measure rows (Gauss-Newton), warm-started from `start` when
    given, else from the nominal geometry; generic shapes are held by the problem's shape prior when it is set
    (a shape and the geometry can otherwise trade against each other far along a valley the poses hardly see).
    The same fit asked for again (same groups, start and prior) is the one made before."""
    names = GEOMETRIC_42.names + names_of(groups)
    x0 = _start(groups, start)
    prior = None if p.shape_prior is None else (np.asarray(p.shape_prior[0]).tobytes(), p.shape_prior[1])
    key = (names, None if x0 is None else x0.tobytes(), prior, label, None if start is None else start.rms_residual)
    cached = p.fits.get(key)
    if cached is not None:
        return cached
    data = residual_function(p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm, p.phi_of(groups))
    P = np.zeros((0, len(names)))
    if p.shape_prior is not None:
        scale, noise = p.shape_prior
        if noise is None:
            noise = start.rms_residual if start is not None else float(np.min(scale))
        P = prior_rows(p, groups, scale, noise)

    def fun(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, J = data(x)
        return (np.concatenate([r, P @ x]), np.concatenate([J, P])) if P.size else (r, J)

    result = None
    if x0 is not None:
        try:
            result = gauss_newton(fun, x0)
        except KinematicsError:
            result = None
    if result is None or not result[3]:
        result = gauss_newton(fun, np.zeros(len(names)))
    x, r, evaluations, converged, message, J = result
    r = r[:6 * p.mea.n]
    p.remember(p.linearized, (names, x.tobytes()), (r, J[:6 * p.mea.n]))
    if not converged:
        name = model_name(groups, label)
        if name not in p.not_converged:
            p.not_converged.append(name)
        log.warning("fit_not_converged", model=name, evaluations=evaluations, message=message)
    rms = float(np.sqrt(np.mean(r**2)))
    fit = IdentificationResult(
        x=x, names=names, model=GEOMETRIC_42.key, estimator="ls", formulation="forward", method="gauss-newton",
        residuals=r.reshape(-1, 6), max_abs_residual=float(np.max(np.abs(r))), rms_residual=rms,
        sigma=float(np.sqrt(r @ r / max(r.size - len(names), 1))), std_errors=None, covariance=None,
        rank=len(names), n_iterations=evaluations, converged=converged, message=message, length_mm=p.length_mm,
    )
    p.remember(p.fits, key, fit)
    return fit


def _bounds(groups: list[TermGroup], size: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(size, -np.inf)
    hi = np.full(size, np.inf)
    k = N_GEO
    for g in groups:
        if g.physical_range is not None:
            lo[k:k + g.n_params], hi[k:k + g.n_params] = g.physical_range.low, g.physical_range.high
        k += g.n_params
    return lo, hi


SHAPE_PRIOR_FACTOR = 3.0
"""A generic shape's correction on a leg gets a Gaussian prior of 3 x the largest discrepancy the geometric fit
leaves on that leg: a real shape is not shrunk, a shape that cancels against the geometry with corrections far
beyond anything the data shows is."""


def shape_scales(leg_residuals_mm: np.ndarray) -> np.ndarray:
    """Per leg, the prior scale (mm) of a generic correction: SHAPE_PRIOR_FACTOR x the largest |residual|."""
    return SHAPE_PRIOR_FACTOR * np.max(np.abs(leg_residuals_mm), axis=0)


def final_fit(p: Problem, groups: list[TermGroup], start: IdentificationResult, shape_scale_mm: np.ndarray,
              noise_mm: float) -> IdentificationResult:
    """The model that is reported and exported: library parameters inside their possible ranges, generic shapes
    with a Gaussian prior of `shape_scale_mm` (per leg) on their leg corrections at the recorded rows (ridge rows
    weighted by noise / scale), so the geometry takes what it can absorb and a shape is no larger than the data
    shows."""
    fit = start
    lo, hi = _bounds(groups, fit.x.size)
    inside = bool(np.all((fit.x >= lo) & (fit.x <= hi)))
    P = prior_rows(p, groups, shape_scale_mm, noise_mm)
    if inside and not P.size:
        return fit
    fun = residual_function(p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm, p.phi_of(groups))

    def residuals(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        try:
            r, J = fun(x)
        except KinematicsError:
            # A trial step so far off that some poses have no forward kinematics: it is shortened (gauss_newton),
            # not the end of the diagnosis.
            r, J = np.full(6 * p.mea.n, np.inf), np.zeros((6 * p.mea.n, x.size))
        return np.concatenate([r, P @ x]), np.concatenate([J, P])

    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    margin_lo, margin_hi = lo + 1e-9 * span, hi - 1e-9 * span
    x0 = fit.x if inside else _inside_start(residuals, fit.x, margin_lo, margin_hi)
    x0 = np.clip(x0, margin_lo, margin_hi)
    if not np.all(np.isfinite(residuals(x0)[0])):
        p.not_converged.append("final model (bounded, shapes held to the data)")
        return fit
    x, _, _, converged, message, _ = gauss_newton(residuals, x0, bounds=(lo, hi))
    if not converged:
        p.not_converged.append("final model (bounded, shapes held to the data)")
    r = fun(x)[0]
    return dataclasses.replace(fit, x=x, residuals=r.reshape(-1, 6), max_abs_residual=float(np.max(np.abs(r))),
                               rms_residual=float(np.sqrt(np.mean(r**2))), converged=converged,
                               message=f"final refit: {message}")


def final_covariance(p: Problem, final: IdentificationResult, groups: list[TermGroup], noise: NoiseLevel,
                     shape_scale_mm: np.ndarray, noise_mm: float) -> tuple[np.ndarray, Misfit | None]:
    """The final model's parameter covariance, with the instrument stations' errors projected out (every error carries
    their uncertainty): with a noise yardstick, the measured noise in its parts (the instrument's and the leg
    readings') and the model's misfit (``hilcal.misfit``: the unexplained shapes are the generic groups; the inflation
    is summarised over the library effects' parameters, or the geometry's without any); without one, the
    cluster-robust sandwich of the fitted residuals."""
    stations = p.mea.stations
    r, J = linearized(p, groups, final.x) if stations is None else residual_function(
        p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm, p.phi_of(groups), stations)(final.x)
    if noise.chosen is None:
        return cluster_robust_covariance(J, r, p.mea.n), None
    raw = linearized(p, groups, final.x)[1]
    frames = None if stations is None else StationFrames.of(stations, p.mea.meas, p.length_mm, p.robot.home[:3])
    shapes, scaled, stated, k = [], [], [], N_GEO
    drifting = np.zeros(6, dtype=bool)
    for g in groups:
        if g.kind == GENERIC:
            shapes.append(p.phi(g) @ final.x[k:k + g.n_params])
            scaled.append(g.variable in LENGTH_PROPORTIONAL)
            if g.variable in DRIFT:
                drifting[slice(None) if g.leg is None else g.leg] = True
        else:
            stated += range(k, k + g.n_params)
        k += g.n_params
    leg_map = raw.reshape(p.mea.n, 6, -1)[:, :, DL0_COLUMNS]
    readings = noise.readings
    parts = None
    if readings is not None:
        inputs, said = temperature_factor(p, groups, final.x, leg_map)
        parts = NoiseParts(noise.chosen.covariance[p.measure], noise.chosen.source, noise.instrument_dof,
                           noise.instrument_factor, readings.unit_covariance[p.measure], readings.variance_mm2,
                           readings.floor_mm2, readings.source, inputs, said)
    return honest_covariance(
        J, r, noise.covariance[p.measure], leg_map, p.mea.legs_mm, p.ctx.session,
        prior=prior_rows(p, groups, shape_scale_mm, noise_mm), frames=frames, noise_dof=noise.dof, shapes=shapes,
        stated=stated or range(N_GEO), parts=parts, length_scaled=scaled, drifting=drifting)


def temperature_factor(p: Problem, groups: list[TermGroup], x: np.ndarray, leg_map: np.ndarray
                       ) -> tuple[np.ndarray | None, str]:
    """F (6 N, rows) with F Fᵀ the covariance the temperature readings' noise gives the measure rows' pose residuals
    through the model's temperature terms (an input with errors: its noise, smoothed as the terms use it, times the
    legs' correction per kelvin, carried to the pose by `leg_map`), and the source in words; None without such
    terms or a temperature column."""
    ctx = p.ctx
    if ctx.temp_c is None or not groups:
        return None, ""
    warmer = dataclasses.replace(ctx, temp_c=ctx.temp_c + 1.0)
    per_kelvin = np.zeros((p.mea.n, 6))
    k = N_GEO
    for g in groups:
        per_kelvin += (g.phi(warmer) - p.phi(g)) @ x[k:k + g.n_params]
        k += g.n_params
    noise = temperature_noise(p.rec.temp_c, p.ctx_all.session)
    if noise is None or not np.any(per_kelvin) or noise.variance_k2 <= 0:
        return None, ""
    t = np.einsum("nij,nj->ni", leg_map, per_kelvin)
    F = noise.sigma_k * (t[:, :, None] * noise.smoothing[p.measure][:, None, :]).reshape(6 * p.mea.n, -1)
    return F, noise.describe()


def _inside_start(residuals: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], x: np.ndarray, lo: np.ndarray,
                  hi: np.ndarray) -> np.ndarray:
    """A start inside the bounds for a fit whose parameters left them: the bounded linear least-squares step from x.

    A fit outside the possible range usually drifted along a direction the data cannot see (a stroke spline and a
    scale on the same leg trade against each other); clipping alone would then move the legs by the drifted
    amount, far from any pose. The linearised step moves the trading parameters together, back inside."""
    r, J = residuals(x)
    scale = np.linalg.norm(J, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    step = lsq_linear(J / scale, -r, bounds=((lo - x) * scale, (hi - x) * scale), method="bvls")
    return x + step.x / scale


def predict(p: Problem, fit: IdentificationResult, groups: list[TermGroup], rows: np.ndarray,
            leg_offsets_mm: np.ndarray | float = 0.0) -> np.ndarray:
    """Poses the model predicts from the recorded leg lengths of some rows (mm, deg), optionally offset."""
    ctx = p.ctx_all.rows(rows)
    legs = p.rec.legs_mm[rows] + leg_offsets_mm
    if groups:
        legs = legs + np.concatenate([g.phi(ctx) for g in groups], axis=2) @ fit.x[N_GEO:]
    return forward_kinematics(fit.geometry(p.robot), legs, p.rec.meas[rows])


def verify_accuracy(p: Problem, fit: IdentificationResult, groups: list[TermGroup]) -> AccuracySummary | None:
    rows = ~p.measure
    if not rows.any():
        return None
    return AccuracySummary.of(p.rec.meas[rows], predict(p, fit, groups, rows))


def later_verify(p: Problem) -> np.ndarray:
    """Verify rows in sessions without measure rows (where a re-homing between sessions shows)."""
    return ~p.measure & ~np.isin(p.ctx_all.session, np.unique(p.ctx_all.session[p.measure]))


def unknown_terms(p: Problem, groups: list[TermGroup]) -> np.ndarray:
    """[N] rows (all phases) where a term of these groups cannot apply: its history is unknown there."""
    out = np.zeros(p.rec.n, dtype=bool)
    for g in groups:
        if g.history:
            out |= g.unknown_rows(p.ctx_all).any(axis=1)
    return out


def judged_verify_mm(p: Problem, fit: IdentificationResult, groups: list[TermGroup],
                     shift_legs: tuple[int, ...] = ()) -> float | None:
    """The held-out verify RMS position error (mm) of a model with the session shift of `shift_legs` (1-based legs
    the diagnosis reports a shift on) removed: each leg's mean residual over the later verify session (rows whose
    terms are known), estimated for this model as `hilcal.discovery.findings.session_shift` does. Without a reported
    shift: the plain figure."""
    verify = ~p.measure
    if not verify.any():
        return None
    offsets: np.ndarray | float = 0.0
    later = later_verify(p)
    known = later & ~unknown_terms(p, groups)
    if shift_legs and known.sum() >= 3:
        mean = leg_residuals(p, fit, groups)[known].mean(axis=0)
        on = np.isin(np.arange(1, 7), shift_legs)
        offsets = np.where(later[verify][:, None] & on[None, :], mean[None, :], 0.0)
    return AccuracySummary.of(p.rec.meas[verify], predict(p, fit, groups, verify, offsets)).position_mm.rms


def leg_residuals(p: Problem, fit: IdentificationResult, groups: list[TermGroup]) -> np.ndarray:
    """Per-leg length residuals (mm) of every row: length implied by the measured pose minus the modelled length."""
    legs = p.rec.legs_mm
    if groups:
        legs = legs + p.phi_all(groups) @ fit.x[N_GEO:]
    return implicit_residuals(fit.geometry(p.robot), legs, p.rec.meas)


def mean_residual_variance(p: Problem, fit: IdentificationResult, groups: list[TermGroup], cov: np.ndarray,
                           rows: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """(6,) the variance (mm²) of the model's share of each leg's mean residual over `rows`: what the fitted
    parameters' uncertainty (`cov`) leaves in it. With instrument stations, the rows' stations' frames move with the
    parameters (re-estimated from the measure rows), so their uncertainty is counted too. By central differences."""
    rows = np.asarray(rows)
    stations = p.mea.stations
    frames = None if stations is None else StationFrames.of(stations, p.mea.meas, p.length_mm, p.robot.home[:3])
    fun = residual_function(p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm, p.phi_of(groups))
    row_stations = None if frames is None or p.rec.stations is None else p.rec.stations[rows]
    phi_rows = (np.concatenate([g.phi(p.ctx_all.rows(rows)) for g in groups], axis=2)
                if row_stations is not None and groups else None)

    def mean(x: np.ndarray) -> np.ndarray:
        moved = dataclasses.replace(fit, x=x)
        res = leg_residuals(p, moved, groups)[rows]
        if row_stations is not None:
            meas = remove_frames(p.rec.meas[rows], row_stations, frames.estimate(fun(x)[0]), p.length_mm,
                                 p.robot.home[:3])
            legs = p.rec.legs_mm[rows]
            if phi_rows is not None:
                legs = legs + phi_rows @ x[N_GEO:]
            res = implicit_residuals(moved.geometry(p.robot), legs, meas)
        return res.mean(axis=0)

    scale = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    G = np.zeros((6, fit.x.size))
    for k in np.flatnonzero(scale > 0):
        h = step * max(scale[k], 1e-9) / max(float(np.max(scale)), 1e-12) + step
        up, down = fit.x.copy(), fit.x.copy()
        up[k] += h
        down[k] -= h
        G[:, k] = (mean(up) - mean(down)) / (2.0 * h)
    return np.einsum("ij,jk,ik->i", G, cov, G)


def linearized(p: Problem, groups: list[TermGroup], x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r, J) of the measure rows (forward residuals of geometry + groups, no instrument stations) at x: the fit's last
    evaluation when x is a fit's solution, else computed (and kept)."""
    key = (GEOMETRIC_42.names + names_of(groups), x.tobytes())
    cached = p.linearized.get(key)
    if cached is None:
        fun = residual_function(p.robot, p.mea.legs_mm, p.mea.meas, "forward", p.length_mm, p.phi_of(groups))
        cached = fun(x)
        p.remember(p.linearized, key, cached)
    return cached


def model_state(p: Problem, fit: IdentificationResult, groups: list[TermGroup]) -> tuple[ModelState, np.ndarray]:
    """The model linearized and whitened at its fit, and d(residual)/d(dl0) per leg for new groups' columns."""
    key = (GEOMETRIC_42.names + names_of(groups), fit.x.tobytes())
    cached = p.states.get(key)
    if cached is not None:
        return cached
    r, J = linearized(p, groups, fit.x)
    n = p.mea.n
    W = pooled_whitener(r, J, n)
    state = ModelState.build(whiten(r, W, n), whiten(J, W, n), W, n, p.clusters)
    cached = (state, J.reshape(n, 6, -1)[:, :, DL0_COLUMNS])
    p.remember(p.states, key, cached)
    return cached


def group_columns(p: Problem, state: ModelState, d_dl0: np.ndarray, group: TermGroup) -> np.ndarray:
    """A candidate group's whitened Jacobian columns at the current model."""
    return groups_columns(p, state, d_dl0, [group]).block


def groups_columns(p: Problem, state: ModelState, d_dl0: np.ndarray, groups: list[TermGroup]) -> Columns:
    """`group_columns` of many groups in one product, as one block laid out by width (`selection.Columns`): the
    whitener and d(residual)/d(dl0) act on every column of a pose alike, so their product is formed once and applied
    to all the groups' regressors together."""
    phis = [p.phi(g) for g in groups]
    widths = np.array([ph.shape[2] for ph in phis], dtype=int)
    order = Columns.layout(widths)
    if not groups:
        return Columns(np.zeros((6 * p.mea.n, 0)), widths, order)
    whitened_d = np.einsum("ij,njl->nil", state.W, d_dl0)
    cols = whitened_d @ p.phi_columns(groups, order)
    return Columns(cols.reshape(6 * p.mea.n, -1), widths, order)
