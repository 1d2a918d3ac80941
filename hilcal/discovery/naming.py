"""Named effects in the machine's own terms: each library effect of the final model graded (physics or a fault of
the set-up), the legs it shows on, one sentence an engineer reads in seconds (% of reading, µm/kN and N/µm, µm of
play, mm of zero shift), and a row per parameter with its unit and uncertainty.
"""

from __future__ import annotations

import re

import numpy as np

from hilcal.discovery.context import EffectContext
from hilcal.discovery.physics import ZERO_SHIFT
from hilcal.discovery.result import NamedEffect, ParameterRow
from hilcal.discovery.term_groups import FAULT, IMPOSSIBLE, LIBRARY, TermGroup

GRADE_Z = 3.0
"""A value is graded outside a range, and a leg counted as showing the effect, beyond 3 standard errors."""
UNITS = {"ppm_per_K": "ppm/K", "um_per_kN_m": "µm/(kN m)", "um_per_kN": "µm/kN", "ppm": "ppm", "mm": "mm"}


def unit_of(name: str) -> str:
    for suffix, unit in UNITS.items():
        if name.endswith("_" + suffix):
            return unit
    return ""


def describe(name: str) -> str:
    """A parameter name as words: 'leg 1', 'leg 3 session 2' or the name itself."""
    leg = leg_of(name)
    if leg is None:
        return name
    session = re.search(r"session(\d+)", name)
    return f"leg {leg}" + (f" session {session.group(1)}" if session else "")


def leg_of(name: str) -> int | None:
    m = re.match(r"leg(\d)_", name)
    return int(m.group(1)) if m else None


def _session_of(name: str) -> str:
    m = re.search(r"session(\d+)", name)
    return m.group(1) if m else "?"


def _legs(legs: list[int]) -> str:
    if len(legs) == 1:
        return f"leg {legs[0]}"
    if legs == list(range(legs[0], legs[-1] + 1)) and len(legs) > 2:
        return f"legs {legs[0]}-{legs[-1]}"
    return "legs " + ", ".join(map(str, legs[:-1])) + f" and {legs[-1]}"


def _span(values: np.ndarray, fmt: str) -> str:
    lo, hi = float(np.min(values)), float(np.max(values))
    return format(lo, fmt) if np.isclose(lo, hi, rtol=0.05) else f"{format(lo, fmt)}-{format(hi, fmt)}"


def _micro_span(values_um: np.ndarray, per: str) -> str:
    """A span of values given in µm per something, in µm or, from 1 mm up, in mm (no 1.58e+05 µm in a sentence)."""
    if float(np.max(np.abs(values_um))) >= 1e3:
        return f"{_span(values_um / 1000.0, '.3g')} mm {per}"
    return f"{_span(values_um, '.3g')} µm {per}"


def _scale_sentence(v: np.ndarray, se: np.ndarray, legs: list[int], faults: list[int]) -> str:
    """The gain g (ppm of the reported stroke) as the reading's error: reported / true travel - 1 = g / (1 - g)."""
    def amount(g: float, s: float) -> str:
        ratio = g * 1e-6 / (1.0 - g * 1e-6)
        side = "long" if g > 0 else "short"
        if abs(g) >= 1000:
            return (f"{abs(ratio):.2%} {side} ({g:+.0f} ± {s:.0f} ppm of its reported stroke; the configured length "
                    f"per count or revolution times {1.0 - g * 1e-6:.4f} would read true)")
        return f"{abs(g):.0f} ppm {side}"

    parts = [f"leg {i} reads {amount(v[i - 1], se[i - 1])}" for i in (faults or legs)]
    text = "; ".join(parts)
    return text[0].upper() + text[1:]


def _sentence(group: TermGroup, v: np.ndarray, se: np.ndarray, legs: list[int], faults: list[int],
              ctx: EffectContext) -> str:
    shown = faults or legs
    idx = np.array(shown) - 1
    if group.effect == "sensor_scale":
        return _scale_sentence(v, se, legs, faults)
    if group.effect == "leg_compliance":
        sag = v[idx] * np.max(np.abs(ctx.force_kn[:, idx]), axis=0)
        compliance = _micro_span(v[idx], "per kN")
        return (f"{_legs(shown).capitalize()} sag under the platform's weight: compliance {compliance} "
                f"(stiffness {_span(1000.0 / np.maximum(v[idx], 1e-12), '.3g')} N/µm), up to "
                f"{np.max(sag):.1f} µm at the largest load")
    if group.effect in ("oil_column_compliance", "drive_compliance"):
        sag = v[idx] * np.max(np.abs(ctx.force_kn[:, idx] * ctx.stroke_mm[:, idx]) * 1e-3, axis=0)
        compliance = _micro_span(v[idx], "per kN of load and metre of stroke")
        return (f"{_legs(shown).capitalize()} sag more as they extend: {compliance}, up to {np.max(sag):.1f} µm at "
                "full stroke and load")
    if group.effect == "thermal_expansion":
        grow = v[0] * 1e-6 * np.mean(ctx.legs_mm) * (np.ptp(ctx.temp_c) if ctx.temp_c is not None else 0.0)
        return (f"The legs grow {v[0]:.3g} ± {se[0]:.2g} ppm/K with temperature ({grow * 1000:.1f} µm over the "
                "recorded temperature range)")
    if group.effect == "joint_backlash":
        return (f"{_legs(shown).capitalize()} have {_span(np.abs(v[idx]) * 1000, '.3g')} µm of play depending on the "
                "direction of approach (backlash)")
    if group.effect == ZERO_SHIFT:
        moved = [(n, x, s) for n, x, s in zip(group.names, v, se, strict=True) if leg_of(n) in shown]
        # the parameter is true minus reported length: positive where the leg now reads short
        parts = [f"leg {leg_of(n)} reads {abs(x) * 1000:.1f} ± {s * 1000:.1f} µm {'short' if x > 0 else 'long'} in "
                 f"session {_session_of(n)}" for n, x, s in moved if abs(x) > GRADE_Z * s]
        return ("The legs' zero moved between sessions (against the first): "
                + (", ".join(parts) or "by less than its uncertainty"))
    return group.sentence


def named_effects(chosen: list[TermGroup], params: dict[str, float], std: dict[str, float],
                  ctx: EffectContext) -> tuple[NamedEffect, ...]:
    """Every library group of the final model as a graded, located, one-sentence statement."""
    out = []
    for g in chosen:
        if g.kind != LIBRARY or g.physical_range is None:
            continue
        v = np.array([params[n] for n in g.names])
        se = np.array([std[n] for n in g.names])
        grades = g.physical_range.grades(v, se, GRADE_Z)
        clear = [leg_of(n) or 0 for n, x, s in zip(g.names, v, se, strict=True) if abs(x) > GRADE_Z * s]
        legs = sorted({leg for leg in clear if leg})
        faults = sorted({leg_of(n) or 0 for n, grade in zip(g.names, grades, strict=True) if grade == FAULT} - {0})
        if not g.names[0].startswith("leg"):
            legs = []
        is_fault = FAULT in grades or IMPOSSIBLE in grades
        sentence = _sentence(g, v, se, legs or list(range(1, 7)), faults, ctx)
        check = g.physical_range.fault_check if is_fault else ""
        if check:
            sentence += f": {check}"
        rows = tuple(ParameterRow(g.effect, n, leg_of(n), float(x), unit_of(n), float(s), grade)
                     for n, x, s, grade in zip(g.names, v, se, grades, strict=True))
        out.append(NamedEffect(g.effect, g.title, "fault" if is_fault else "physics", tuple(faults or legs),
                               sentence + ".", check, rows))
    out.sort(key=lambda n: n.grade != "fault")
    return tuple(out)

