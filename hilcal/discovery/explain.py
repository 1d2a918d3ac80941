"""The diagnosis in words: what is missing, the evidence, what was rejected, and how the residual compares with
the measurement noise. Nothing is claimed that the numbers beside it do not show.
"""

from __future__ import annotations

from hilcal.discovery.noise import NoiseLevel
from hilcal.discovery.physics import CANDIDATES_BY_NAME, ZERO_SHIFT, ZERO_SHIFT_TITLE
from hilcal.discovery.result import Finding, NoiseComparison, SessionShift, Shape, Step
from hilcal.discovery.term_groups import LIBRARY, TermGroup
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


def _library_text(group: TermGroup, step: Step, params: dict[str, float], std: dict[str, float]) -> str:
    values = ", ".join(f"{n} = {params[n]:+.3g} ± {std[n]:.2g}" for n in group.names)
    return (f"{group.title}: {group.sentence}. Fitted with the geometry: {values}. Evidence (step {step.index}): "
            f"F = {step.f_statistic:.1f}, family-wise p = {step.p_value:.3g}; leave-one-pose-out residual "
            f"{_um(step.cv_before_mm)} -> {_um(step.cv_rms_mm)}.")


def _shapes_text(shapes: list[Shape]) -> str:
    """One sentence per generic group (an all-leg group lists its legs)."""
    texts = []
    for key in dict.fromkeys(s.group.key for s in shapes):
        group_shapes = [s for s in shapes if s.group.key == key]
        first = group_shapes[0]
        amplitudes = ", ".join(f"leg {s.leg + 1} {_um(s.amplitude_mm)}" for s in group_shapes)
        gain = ""
        if first.verify_before_mm is not None and first.verify_after_mm is not None:
            gain = f"; held-out verify RMS {first.verify_before_mm:.4f} -> {first.verify_after_mm:.4f} mm"
        text = f"{first.group.sentence} (amplitude {amplitudes}{gain})."
        for shape in group_shapes:
            if shape.pinned:
                continue
            text += f" Leg {shape.leg + 1}'s shape is not pinned down: {shape.why_not_pinned}."
            if shape.proposed_poses is not None and len(shape.proposed_poses):
                band = "" if shape.proposed_band_mm is None else f" (predicted band {_um(shape.proposed_band_mm)})"
                text += f" Measure {len(shape.proposed_poses)} extra pose(s), D-optimal for these terms{band}."
        texts.append(text)
    return " ".join(texts)


def _noise_text(noise: NoiseLevel, ratio: NoiseComparison | None) -> str:
    if noise.chosen is None or ratio is None:
        return " ".join(noise.notes)
    legs = ", ".join(f"leg {i + 1} {v:.2f}" for i, v in enumerate(ratio.per_leg_final))
    text = (f"Residual after the model: {_um(ratio.residual_rms_mm)} RMS, {ratio.ratio_final:.2f}x what the "
            f"measurement noise alone leaves ({_um(ratio.expected_rms_mm)}; {noise.chosen.describe()}); geometry only: "
            f"{ratio.ratio_geometry:.2f}x. Per leg: {legs}.")
    if noise.notes:
        text += " Note: " + "; ".join(noise.notes) + "."
    return text


def compose(
    effect: str, effects: list[str], chosen: list[TermGroup], steps: list[Step], params: dict[str, float],
    std: dict[str, float], noise: NoiseLevel, ratio: NoiseComparison | None, shapes: list[Shape],
    shift: SessionShift | None, rejected: dict[str, str], untestable: dict[str, str], ambiguous: tuple[str, ...],
    before: AccuracySummary | None, after: AccuracySummary | None, findings: tuple[Finding, ...],
) -> str:
    """The explanation printed by `hilcal diagnose` and stored in the report."""
    parts: list[str] = []
    named = [g for g in chosen if g.kind == LIBRARY]
    if named:
        parts.append("Missing physics: " + " and ".join(g.title for g in named) + ".")
        for g in named:
            step = next(s for s in steps if s.key == g.key)
            parts.append(_library_text(g, step, params, std))
    if shapes:
        parts.append("Unexplained (no library effect describes it), located and modelled: "
                     + _shapes_text(shapes))
    far = ratio is not None and ratio.ratio_final >= FAR_ABOVE_NOISE
    if far and not shapes:
        where = "; ".join(f.text for f in findings[:3]) or "no single leg or variable stands out"
        parts.append(f"Unexplained: the residual is {ratio.ratio_final:.1f}x the measurement noise, and neither the "
                     f"library nor a smooth or periodic shape of one leg in any variable explains it. Where it shows: "
                     f"{where}.")
    elif far:
        parts.append(f"Structure remains: after the model the residual is still {ratio.ratio_final:.1f}x the noise.")
    if not effects:
        if ratio is None:
            parts.append("No missing physics found by the relative tests (noise level unknown: relative tests only; "
                         "a residual can hide structure that no test here can see).")
        elif ratio.ratio_final <= WITHIN_NOISE:
            parts.append("No missing physics found: the geometric model explains this recording to within its "
                         f"measurement noise (residual {ratio.ratio_final:.2f}x the noise).")
        else:
            parts.append(f"No missing physics is significant, but the residual is {ratio.ratio_final:.2f}x the "
                         "noise: small structure below the detection limit, or more noise than the source says.")
    if steps and before is not None and after is not None:
        parts.append(f"Held-out verify poses: RMS position {before.position_mm.rms:.4f} mm (geometry only) -> "
                     f"{after.position_mm.rms:.4f} mm (with {', '.join(effects)}).")
    parts.append(_noise_text(noise, ratio))
    if ambiguous:
        parts.append("On this data it cannot be told apart from: " + ", ".join(title_of(a) for a in ambiguous)
                     + " (nearly the same signature).")
    for name, reason in rejected.items():
        parts.append(f"Not named as {title_of(name)}: {reason}.")
    if "sensor_scale" in effects and "thermal_expansion" in untestable:
        parts.append("Thermal growth of the legs would look like a scale error here, and it could not be tested: "
                     f"{untestable['thermal_expansion']}.")
    if shift is not None and shift.legs:
        moved = ", ".join(f"leg {i} {shift.shift_mm[i - 1] * 1000:+.1f} ± {shift.std_error_mm[i - 1] * 1000:.1f} µm"
                          for i in shift.legs)
        text = (f"Between the measure and the verify session the legs' zero moved ({moved}): the machine was "
                "re-homed or a transducer's zero shifted.")
        if shift.verify_without_shift is not None:
            text += (f" Without that step the verify RMS would be {shift.verify_without_shift.position_mm.rms:.4f} mm "
                     "(estimated on the verify rows themselves, so not held out).")
        parts.append(text)
    return " ".join(p for p in parts if p)
