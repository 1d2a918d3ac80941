"""Near-aliases: library effects that explain nearly the same on this recording, which of them the machine's kind
makes more plausible, and what would tell them apart.

Two library groups are near-aliases when their fitted signatures on the measured poses point the same way (cosine
above ALIAS_SIGNATURE); one that would need an impossible value is still reported, so the answer says why it is not
the explanation. When their held-out gains in mm are also within ALIAS_GAIN of each other, the recording
cannot choose, so the choice goes by a Laplace approximation of each model's evidence with the graded prior of
its parameters (flat over the typical range, a smaller weight over the abnormal but possible range, zero beyond):
a scale error of 6 % that a mis-set ratio explains beats a drive compliance a thousand times softer than any belt.
Both are reported, with their values, why the recording cannot separate them, and extra poses (greedy
Ds-optimal for the two groups together) or a payload that would.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from hilcal.discovery.augmentation import augment, candidate_jacobians, candidate_pool
from hilcal.discovery.context import EffectContext
from hilcal.discovery.selection import GroupTest, similar
from hilcal.discovery.term_groups import LIBRARY, TermGroup, stack_phi
from hilcal.identification import IdentificationResult, residual_function
from hilcal.robot import Robot

N_GEO = 42
ALIAS_SIGNATURE = 0.8
"""Cosine of the fitted leg-length signatures above which two effects look alike on this recording."""
ALIAS_GAIN = 0.9
"""Held-out gains (mm) within 10 % of each other: the recording cannot choose between near-aliases."""
SEPARATED_CORRELATION = 0.8
"""Two effects are told apart when the correlation of their estimates falls below this."""
PAYLOAD_FACTORS = (1.0, 3.0, 10.0)
"""Payloads tried, as multiples of the moving mass, when poses alone cannot separate load-driven effects."""
LOAD_VARIABLES = ("axial load (kN)", "axial load x stroke (kN m)")
NOT_POSE_VARIABLES = ("temperature (°C)", "session")
"""Effects driven by the temperature or the session: more poses cannot separate them (a temperature swing or
another session can)."""


@dataclass(frozen=True)
class AliasChoice:
    """The group chosen among near-aliases, the others that were compared, and each one's log evidence."""

    chosen: GroupTest
    compared: tuple[GroupTest, ...]
    similar: tuple[GroupTest, ...]
    log_evidence: dict[str, float]


def _log_evidence(t: GroupTest, sigma2: float, dof: int) -> float:
    """log evidence of the current model plus group t, with a common noise variance sigma2 (whitened units)."""
    rng = t.group.physical_range
    if rng is None or not np.isfinite(t.log_det_information):
        return float("-inf")
    q = t.estimate.size
    own_sigma2 = max(t.rss_w / max(dof - t.rank, 1), 1e-300)
    return float(-0.5 * t.rss_w / sigma2 + 0.5 * q * np.log(2 * np.pi)
                 - 0.5 * (t.log_det_information - q * np.log(sigma2))
                 + rng.log_prior(t.estimate, t.std_errors * np.sqrt(sigma2 / own_sigma2)))


def resolve(best: GroupTest, tests: list[GroupTest], dof: int) -> AliasChoice:
    """Among the library groups that look like `best` and gain nearly as much, the one with the largest evidence."""
    if best.group.kind != LIBRARY:
        return AliasChoice(best, (), (), {})
    alike = tuple(t for t in tests if t is not best and t.group.kind == LIBRARY and t.significant
                  and similar(best, t) > ALIAS_SIGNATURE)
    close = tuple(t for t in alike if t.eligible and t.press_gain_mm >= ALIAS_GAIN * best.press_gain_mm)
    if not close:
        return AliasChoice(best, (), alike, {})
    pool = (best, *close)
    sigma2 = min(t.rss_w for t in pool) / max(dof - max(t.rank for t in pool), 1)
    evidence = {t.group.key: _log_evidence(t, sigma2, dof) for t in pool}
    chosen = max(pool, key=lambda t: evidence[t.group.key])
    others = tuple(t for t in alike if t is not chosen) + ((best,) if chosen is not best else ())
    return AliasChoice(chosen, tuple(t for t in pool if t is not chosen), others, evidence)


@dataclass(frozen=True)
class Alias:
    """An effect that explains nearly the same as a named one on this recording, and what would separate them."""

    chosen: str
    other: str
    other_title: str
    similarity: float
    gain_ratio: float
    log10_bayes_factor: float | None
    other_values: dict[str, float]
    other_std_errors: dict[str, float]
    other_grades: tuple[str, ...]
    why: str
    correlation_now: float
    separating_poses: np.ndarray | None
    correlation_after: float | None
    payload_kg: float | None
    other_named: bool = False
    """The other effect is named too (the recording needs both)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "chosen": self.chosen, "other": self.other, "other_title": self.other_title,
            "signature_cosine": self.similarity, "held_out_gain_ratio": self.gain_ratio,
            "log10_bayes_factor": self.log10_bayes_factor, "other_parameters": self.other_values,
            "other_std_errors": self.other_std_errors, "other_grades": list(self.other_grades), "why": self.why,
            "estimate_correlation_now": self.correlation_now,
            "separating_poses": None if self.separating_poses is None else self.separating_poses.tolist(),
            "estimate_correlation_after": self.correlation_after, "payload_kg": self.payload_kg,
            "other_named": self.other_named,
        }


def _canonical(block_a: int) -> Callable[[np.ndarray], float]:
    """Largest canonical correlation between the first `block_a` estimates and the rest, from their covariance."""

    def corr(C: np.ndarray) -> float:
        def inv_sqrt(M: np.ndarray) -> np.ndarray:
            w, V = np.linalg.eigh(M)
            return V @ np.diag(1.0 / np.sqrt(np.clip(w, w.max() * 1e-12, None))) @ V.T

        S = inv_sqrt(C[:block_a, :block_a]) @ C[:block_a, block_a:] @ inv_sqrt(C[block_a:, block_a:])
        return float(np.linalg.svd(S, compute_uv=False)[0])

    return corr


def alias_why(chosen: TermGroup, other: TermGroup, ctx: EffectContext, cosine: float) -> str:
    text = f"on the recorded poses their leg-length signatures have a cosine of {cosine:.3f}"
    variables = {chosen.variable, other.variable}
    if "axial load x stroke (kN m)" in variables and "stroke (mm)" in variables:
        r = [abs(np.corrcoef(ctx.force_kn[:, i] * ctx.stroke_mm[:, i], ctx.stroke_mm[:, i])[0, 1]) for i in range(6)]
        text += (f"; load x stroke follows the stroke (correlation {min(r):.2f} or more on every leg): the load on "
                 "each leg changes too little across these poses to tell a compliance from a scale")
    elif variables & set(LOAD_VARIABLES):
        load = np.abs(ctx.force_kn)
        spread = float(np.median(np.ptp(load, axis=0) / np.maximum(np.mean(load, axis=0), 1e-12)))
        text += f"; the axial load on a leg changes by {spread:.0%} of its mean across these poses (median over legs)"
    if "temperature (°C)" in variables:
        span = 0.0 if ctx.temp_c is None else float(np.ptp(ctx.temp_c))
        text += (f"; the temperature moved only {span:.2f} K: more poses cannot separate them, a measurement over a "
                 "temperature swing of several K can")
    if "session" in variables:
        text += "; a session of its own (after re-homing) separates a zero shift, more poses cannot"
    return text


def separation(robot: Robot, final: IdentificationResult, model: list[TermGroup], chosen: TermGroup,
               other: TermGroup, legs_mm: np.ndarray, poses: np.ndarray, ctx: EffectContext, seed: int
               ) -> tuple[float, np.ndarray | None, float | None, float | None]:
    """(estimate correlation now, extra poses, correlation after them, payload kg) that would tell `chosen` from
    `other`, greedy Ds-optimal for both groups with the rest of the model as nuisance."""
    groups = [*model, other]
    phi = stack_phi(groups, ctx)
    x = np.concatenate([final.x, np.zeros(other.n_params)])
    r, J = residual_function(robot, legs_mm, poses, "forward", final.length_mm, phi)(x)
    scale = np.linalg.norm(J, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    J = J / scale
    information = J.T @ J
    sigma2 = max(float(r @ r) / max(r.size - x.size, 1), 1e-12)
    start = 42 + sum(g.n_params for g in model[:model.index(chosen)])
    block = np.concatenate([np.arange(start, start + chosen.n_params),
                            np.arange(x.size - other.n_params, x.size)])
    corr = _canonical(chosen.n_params)
    p = information.shape[0]
    C = np.linalg.pinv(information + 1e-9 * np.trace(information) / p * np.eye(p))
    now = corr(C[np.ix_(block, block)])
    if now <= SEPARATED_CORRELATION or {chosen.variable, other.variable} & set(NOT_POSE_VARIABLES):
        return now, None, None, None
    geometry = final.geometry(robot)
    payloads = (0.0,) + (PAYLOAD_FACTORS if {chosen.variable, other.variable} & set(LOAD_VARIABLES) else ())
    best: tuple[np.ndarray | None, float | None, float | None] = (None, None, None)
    pool = candidate_pool(robot, seed)
    for factor in payloads:
        heavier = robot if factor == 0 else _with_payload(robot, factor * robot.moving_mass_kg)

        def phi(c: EffectContext) -> np.ndarray:
            return stack_phi(groups, c.at_recorded_state(ctx)) / scale[42:]

        aug = augment(heavier, geometry, final.length_mm, information, sigma2, phi, block, corr,
                      SEPARATED_CORRELATION, seed, geometry_scale=scale[:42],
                      candidates=(pool, candidate_jacobians(heavier, geometry, pool, final.length_mm, phi)))
        after = float(aug.predicted_band_mm[-1]) if aug.predicted_band_mm.size else None
        best = (aug.poses, after, None if factor == 0 else factor * robot.moving_mass_kg)
        if aug.reached_target:
            break
    return now, *best


def _with_payload(robot: Robot, payload_kg: float) -> Robot:
    mass = robot.spec.mass.model_copy(update={"moving_mass_kg": robot.moving_mass_kg + payload_kg})
    return replace(robot, spec=robot.spec.model_copy(update={"mass": mass}))


def final_without(final: IdentificationResult, chosen: list[TermGroup], group: TermGroup) -> IdentificationResult:
    """The final fit with one chosen group's parameters removed (to test it against another as an alias)."""
    if group not in chosen:
        return final
    start = N_GEO + sum(g.n_params for g in chosen[:chosen.index(group)])
    keep = np.r_[0:start, start + group.n_params:final.x.size]
    return replace(final, x=final.x[keep], names=tuple(np.array(final.names)[keep]))


def named_aliases(p: Any, chosen: list[TermGroup], chosen_tests: dict[str, GroupTest],
                  alike: dict[str, tuple[GroupTest, ...]], evidence: dict[str, dict[str, float]],
                  final: IdentificationResult, seed: int) -> tuple[Alias, ...]:
    """Every named library effect's near-aliases, with their values and what would separate them.

    `p` is the diagnosis' problem (`hilcal.discovery.fitting.Problem`); `alike` per chosen group the library groups
    that looked like it when it was chosen, `evidence` their log evidence."""
    out = []
    chosen_keys = [c.key for c in chosen]
    for g in chosen:
        chosen_test = chosen_tests.get(g.key)
        if g.kind != LIBRARY or chosen_test is None:
            continue
        group_evidence = evidence.get(g.key, {})
        for t in alike.get(g.key, ()):
            if t.group.key in chosen_keys and chosen_keys.index(t.group.key) < chosen_keys.index(g.key):
                continue
            model = [c for c in chosen if c.key != t.group.key]
            now, poses, after, payload = separation(p.robot, final_without(final, chosen, t.group), model, g,
                                                    t.group, p.mea.legs_mm, p.mea.meas, p.ctx, seed)
            factor = None
            if g.key in group_evidence and t.group.key in group_evidence:
                factor = (group_evidence[g.key] - group_evidence[t.group.key]) / np.log(10.0)
            cosine = similar(chosen_test, t)
            out.append(Alias(
                g.key, t.group.key, t.group.title, cosine, t.press_gain_mm / max(chosen_test.press_gain_mm, 1e-300),
                factor, dict(zip(t.group.names, map(float, t.estimate), strict=True)),
                dict(zip(t.group.names, map(float, t.std_errors), strict=True)), t.grades,
                alias_why(g, t.group, p.ctx, cosine), now, poses, after, payload, t.group.key in chosen_keys,
            ))
    return tuple(out)


def period_aliases(best: GroupTest, tests: list[GroupTest]) -> tuple[TermGroup, ...]:
    """Other periods of a chosen cyclic group's leg, beyond the frequency resolution, that explain nearly as much
    (within ALIAS_GAIN of its held-out gain): the shape's scale is then ambiguous."""
    g = best.group
    assert g.period_mm is not None and g.curve_range is not None
    resolution = 1.0 / max(g.curve_range[1] - g.curve_range[0], 1e-9)
    return tuple(
        t.group for t in tests
        if t.eligible and t.group.leg == g.leg and t.group.period_mm is not None
        and abs(1.0 / t.group.period_mm - 1.0 / g.period_mm) > resolution
        and t.press_gain_mm >= ALIAS_GAIN * best.press_gain_mm
    )
