"""The diagnosis in words: one sentence per finding first (what, on which legs, how big, in the machine's own
terms), then the evidence (steps, held-out figures, the noise comparison, what was rejected and why). Nothing is
claimed that the numbers beside it do not show.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hilcal.discovery.naming import describe, unit_of
from hilcal.discovery.noise import NoiseLevel
from hilcal.discovery.physics import CANDIDATES_BY_NAME, ZERO_SHIFT, ZERO_SHIFT_TITLE
from hilcal.discovery.result import EndStop, Finding, NamedEffect, NoiseComparison, SessionShift, Shape, Step
from hilcal.discovery.term_groups import FAULT, IMPOSSIBLE, TermGroup
from hilcal.metrics import AccuracySummary

FAR_ABOVE_NOISE = 2.0
"""A residual RMS at least twice what the noise alone leaves is structure, whatever the tests say."""
WITHIN_NOISE = 1.3
"""Up to 1.3x the noise (sampling spread, a slightly optimistic noise source) counts as within the noise."""


def title_of(effect: str) -> str:
    if effect in CANDIDATES_BY_NAME:
        return CANDIDATES_BY_NAME[effect].title
    if effect == ZERO_SHIFT:
        return ZERO_SHIFT_TITLE
    return effect


def _um(value_mm: float) -> str:
    return f"{value_mm * 1000:.1f} µm"


UNCONFIRMED = "not confirmed on held-out poses"


def _named_sentence(n: NamedEffect, unconfirmed: tuple[str, ...] = ()) -> str:
    kind = "Set-up fault" if n.grade == "fault" else "Missing physics"
    mark = f" ({UNCONFIRMED})" if n.effect in unconfirmed else ""
    return f"{kind} ({n.effect}, {n.title}){mark}: {n.sentence}"


def _drift_words(terms: list[Any]) -> str:
    """For a drift in time: how much each leg's length moved over its session, signed, and what a common sign means
    (a correction that grows means the leg grew while its reading did not)."""
    if not terms or any(t.variable != "session_time_s" for t in terms):
        return ""
    moved = []
    for t in terms:
        start, end = t.recorded_range
        if t.coefficient_mm is not None:
            moved.append(t.coefficient_mm * (end - start))
        else:
            moved.append(float(np.interp(end, t.grid, t.correction_mm) - np.interp(start, t.grid, t.correction_mm)))
    hours = (max(t.recorded_range[1] for t in terms) - min(t.recorded_range[0] for t in terms)) / 3600.0
    listed = ", ".join(f"leg {t.leg + 1} {m * 1000:+.1f} µm" for t, m in zip(terms, moved, strict=True))
    text = f"; over {hours:.2g} h of a session the legs' lengths moved against their readings by {listed}"
    if len(terms) >= 3 and (all(m > 0 for m in moved) or all(m < 0 for m in moved)):
        grew = moved[0] > 0
        text += (f": every leg {'grew' if grew else 'shrank'} while its reading did not, as legs "
                 f"{'warming up' if grew else 'cooling down'} do (a temperature column in the recording would let "
                 "thermal expansion be tested)")
    return text


def _range_words(term: Any) -> str:
    """' over the recorded LO-HI VARIABLE' of a term, or nothing when its range is empty or not finite."""
    lo, hi = term.recorded_range
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return ""
    if term.angle_terms:
        return f" over the recorded {lo:.3g}-{hi:.3g}° tilt of its {term.variable.replace('_', ' ')}"
    return f" over the recorded {lo:.4g}-{hi:.4g} {term.variable}"


def _shape_sentences(shapes: list[Shape], compensation: Any, unconfirmed: tuple[str, ...] = (),
                     steps: tuple[Step, ...] | list[Step] = (), shifted: bool = False) -> list[str]:
    """One sentence per generic group: where, how big over the recorded range, whether it is pinned down, whether
    the held-out poses confirm it (the held-out figures of its step, with the session shift removed when one is
    reported, as the verdict judges them)."""
    judged = {s.key: (s.judged_before_mm, s.judged_mm) for s in steps
              if s.judged_before_mm is not None and s.judged_mm is not None}
    out = []
    sizes = {} if compensation is None else {(t.group, t.leg): t for t in compensation.terms}
    for key in dict.fromkeys(s.group.key for s in shapes):
        group_shapes = [s for s in shapes if s.group.key == key]
        first = group_shapes[0]
        parts = []
        for s in group_shapes:
            term = sizes.get((key, s.leg))
            size = s.amplitude_mm if term is None or not np.isfinite(term.size_mm) else term.size_mm
            where = "" if term is None else _range_words(term)
            parts.append(f"leg {s.leg + 1} ±{_um(size)}{where}")
        text = f"Unexplained (no library effect describes it): {first.group.sentence} ({'; '.join(parts)})"
        text += _drift_words([sizes[(key, s.leg)] for s in group_shapes if (key, s.leg) in sizes])
        if key in judged:
            text += (f"; modelling it takes the held-out verify RMS{' (session shift removed)' if shifted else ''} "
                     f"from {judged[key][0]:.4f} to {judged[key][1]:.4f} mm")
        elif first.verify_before_mm is not None and first.verify_after_mm is not None:
            text += (f"; modelling it takes the held-out verify RMS from {first.verify_before_mm:.4f} to "
                     f"{first.verify_after_mm:.4f} mm")
        if key in unconfirmed:
            text += f"; {UNCONFIRMED} (see below)"
        loose = [s for s in group_shapes if not s.pinned]
        if loose:
            text += f"; not pinned down on leg(s) {', '.join(str(s.leg + 1) for s in loose)}: {loose[0].why_not_pinned}"
            n_extra = [len(s.proposed_poses) for s in loose if s.proposed_poses is not None and len(s.proposed_poses)]
            if n_extra:
                text += f"; {max(n_extra)} extra pose(s), D-optimal for these terms, would pin it down"
        out.append(text + ".")
    return out


def _alias_sentence(a: Any) -> str:
    values = ", ".join(f"{describe(k)} {v:+.3g} ± {a.other_std_errors[k]:.2g} {unit_of(k)}"
                       for k, v in a.other_values.items()
                       if abs(v) > 3 * a.other_std_errors[k]) or "values within their uncertainty of zero"
    grade = ("an impossible value" if IMPOSSIBLE in a.other_grades else
             "a value a healthy machine cannot have (a fault)" if FAULT in a.other_grades else "typical values")
    if a.other_named:
        text = (f"Near-aliases: {a.chosen} and {a.other} look alike on these poses ({a.why}); both are named, and "
                f"the recording {'separates' if a.correlation_now <= 0.8 else 'hardly separates'} them (their "
                f"estimates correlate at {a.correlation_now:.2f})")
        if a.separating_poses is not None and len(a.separating_poses):
            after = "" if a.correlation_after is None else f" to {a.correlation_after:.2f}"
            payload = "" if a.payload_kg is None else f" with a payload of {a.payload_kg:.3g} kg"
            text += f"; {len(a.separating_poses)} extra pose(s){payload} would bring that{after}"
        return text + "."
    if IMPOSSIBLE in a.other_grades:
        return (f"Not an alternative to {a.chosen}: {a.other} ({a.other_title}) could mimic it on these poses "
                f"({a.gain_ratio:.0%} as much of the held-out error), but only with impossible values ({values}); "
                "no pose is needed to rule it out.")
    text = (f"Near-alias of {a.chosen}: {a.other} ({a.other_title}) explains {a.gain_ratio:.0%} as much of the "
            f"held-out error "
            f"with {grade} ({values}); {a.why}")
    if a.log10_bayes_factor is not None:
        text += (f". Chosen by how typical each value is for this machine: the evidence favours {a.chosen} by a "
                 f"factor of 10^{a.log10_bayes_factor:.1f}")
    if a.separating_poses is not None and len(a.separating_poses):
        after = "" if a.correlation_after is None else f" to {a.correlation_after:.2f}"
        payload = "" if a.payload_kg is None else f" with a payload of {a.payload_kg:.3g} kg on the platform"
        text += (f". {len(a.separating_poses)} extra pose(s){payload}, D-optimal for telling them apart, would bring "
                 f"the correlation of the two estimates from {a.correlation_now:.2f}{after}")
    return text + "."


def _unconfirmed_sentence(a: Answer) -> str | None:
    """The steps whose held-out figure got worse, and what happens to their correction."""
    v = a.verdict
    if v is None or not v.unconfirmed:
        return None
    judged = " (judged with the session shift removed)" if v.shift_removed else ""
    parts = [f"step {s.index} ({s.key}) takes the held-out verify RMS from {s.judged_before_mm:.4f} to "
             f"{s.judged_mm:.4f} mm" for s in a.steps if s.key in v.unconfirmed and s.confirmed is False
             and s.judged_mm is not None and s.judged_before_mm is not None]
    text = f"Not confirmed on held-out poses: {'; '.join(parts)}{judged}. The tests chose it on the measure rows, "
    if v.included:
        return text + "and its correction is in the compensation set as asked (--include-unconfirmed)."
    after = "" if v.loadable_after is None else (
        f"; the set's model gives {v.loadable_after.position_mm.rms:.4f} mm on the verify poses")
    return (text + "but the held-out poses do not bear it out: its correction is left out of the compensation set, "
            f"whose geometry is refitted without it{after} (--include-unconfirmed puts it back).")


def summary_sentences(a: Answer) -> list[str]:
    """The opening of the answer: one sentence per finding."""
    named, shapes, aliases, shift, stops = a.named, a.shapes, a.aliases, a.shift, a.stops
    not_converged, effects, ratio, noise = a.not_converged, a.effects, a.ratio, a.noise
    unconfirmed = () if a.verdict is None else a.verdict.unconfirmed
    out = [_named_sentence(n, tuple(g.effect for g in a.chosen if g.key in unconfirmed)) for n in named]
    out += _shape_sentences(list(shapes), a.compensation, unconfirmed, a.steps,
                            a.verdict is not None and a.verdict.shift_removed)
    out += [_alias_sentence(x) for x in aliases]
    if shift is not None and shift.legs:
        moved = ", ".join(f"leg {i} {shift.shift_mm[i - 1] * 1000:+.1f} ± {shift.std_error_mm[i - 1] * 1000:.1f} µm"
                          for i in shift.legs)
        out.append(f"Zero shift in the held-out rows: between the measure session(s) and a later verify session the "
                   f"legs' zero moved ({moved}); the machine was re-homed or a transducer's zero shifted (estimated on "
                   "the verify rows, not fitted).")
    out += [f"Leg {s.leg} reads {s.reading_mm:.4f} mm (its {s.extreme}) in {s.n_rows} of {s.n_total} rows: it may sit "
            "on an end stop or a software limit, where its reading no longer follows the pose." for s in stops]
    out += [f"The fit of {name} did not converge: figures that depend on it are approximate." for name in not_converged]
    far = ratio is not None and ratio.ratio_final >= FAR_ABOVE_NOISE
    if far and not shapes:
        out.append(f"Unexplained: the residual stays {ratio.ratio_final:.1f}x the measurement noise and nothing in the "
                   "library, nor a smooth or periodic shape of one leg, explains it.")
    if not effects:
        if ratio is None:
            out.append("No missing physics found by the relative tests (noise level unknown: a residual can hide "
                       "structure that no test here can see).")
        elif ratio.ratio_final <= WITHIN_NOISE and noise.chosen is not None:
            out.append("No missing physics: the geometric model explains this recording to within its measurement "
                       f"noise (residual {ratio.ratio_final:.2f}x the noise; {noise.describe()}).")
        else:
            out.append(f"No missing physics is significant, but the residual is {ratio.ratio_final:.2f}x the noise: "
                       "small structure below the detection limit, or more noise than the source says.")
    said = _unconfirmed_sentence(a)
    if said:
        out.append(said)
    return out


def _noise_text(noise: NoiseLevel, ratio: NoiseComparison | None) -> str:
    if noise.chosen is None or ratio is None:
        return " ".join(noise.notes)
    legs = ", ".join(f"leg {i + 1} {v:.2f}" for i, v in enumerate(ratio.per_leg_final))
    text = (f"Residual after the model: {_um(ratio.residual_rms_mm)} RMS, {ratio.ratio_final:.2f}x what the "
            f"measurement noise alone leaves ({_um(ratio.expected_rms_mm)}; {noise.describe()}); geometry only: "
            f"{ratio.ratio_geometry:.2f}x. Per leg: {legs}.")
    if noise.notes:
        text += " Note: " + "; ".join(noise.notes) + "."
    return text


@dataclass(frozen=True)
class Answer:
    """Everything the words are made from."""

    effect: str
    effects: list[str]
    chosen: list[TermGroup]
    steps: list[Step]
    params: dict[str, float]
    std: dict[str, float]
    noise: NoiseLevel
    ratio: NoiseComparison | None
    shapes: list[Shape]
    shift: SessionShift | None
    rejected: dict[str, str]
    untestable: dict[str, str]
    aliases: tuple[Any, ...]
    before: AccuracySummary | None
    after: AccuracySummary | None
    findings: tuple[Finding, ...]
    named: tuple[NamedEffect, ...]
    stops: tuple[EndStop, ...]
    not_converged: tuple[str, ...]
    compensation: Any
    """The final model's terms (hilcal.discovery.corrections.CompensationSet), unconfirmed groups included."""
    verdict: Verdict | None = None


@dataclass(frozen=True)
class Verdict:
    """What the held-out poses say of the steps: the groups they do not confirm and what the export does with them."""

    unconfirmed: tuple[str, ...]
    included: bool
    """--include-unconfirmed: their corrections stay in the compensation set."""
    loadable_after: AccuracySummary | None
    shift_removed: bool


def compose(a: Answer) -> str:
    """The explanation printed by `hilcal diagnose` and stored in the report: the summary, then the evidence."""
    return " ".join([*summary_sentences(a), evidence(a)])


def evidence(a: Answer) -> str:
    """The evidence behind the summary: steps, held-out figures, the noise comparison, what was rejected."""
    parts: list[str] = []
    shifted = a.verdict is not None and a.verdict.shift_removed
    for s in a.steps:
        removed = f" (made {', '.join(s.removed)} redundant)" if s.removed else ""
        held = ""
        if s.judged_mm is not None and s.judged_before_mm is not None:
            held = (f"; held-out verify RMS{' (session shift removed)' if shifted else ''} {s.judged_before_mm:.4f} "
                    f"-> {s.judged_mm:.4f} mm{'' if s.confirmed else ': ' + UNCONFIRMED}")
        parts.append(f"Step {s.index} added {s.key}{removed}: F = {s.f_statistic:.1f}, family-wise p = "
                     f"{s.p_value:.3g}; leave-one-pose-out residual {_um(s.cv_before_mm)} -> {_um(s.cv_rms_mm)}"
                     f"{held}.")
    if a.steps and a.before is not None and a.after is not None:
        parts.append(f"Held-out verify poses: RMS position {a.before.position_mm.rms:.4f} mm (geometry only) -> "
                     f"{a.after.position_mm.rms:.4f} mm (with {', '.join(a.effects)}).")
    far = a.ratio is not None and a.ratio.ratio_final >= FAR_ABOVE_NOISE
    if far and a.shapes:
        parts.append(f"Structure remains: after the model the residual is still {a.ratio.ratio_final:.1f}x the noise.")
    if far and not a.shapes:
        where = "; ".join(f.text for f in a.findings[:3]) or "no single leg or variable stands out"
        parts.append(f"Where it shows: {where}.")
    parts.append(_noise_text(a.noise, a.ratio))
    for name, reason in a.rejected.items():
        parts.append(f"Not named as {title_of(name)}: {reason}.")
    for name, reason in a.untestable.items():
        if CANDIDATES_BY_NAME.get(name) is not None and "declares" in reason:
            parts.append(f"Not tried: {title_of(name)} ({reason}).")
    if "sensor_scale" in a.effects and "thermal_expansion" in a.untestable:
        parts.append("Thermal growth of the legs would look like a scale error here, and it could not be tested: "
                     f"{a.untestable['thermal_expansion']}.")
    return " ".join(p for p in parts if p)
