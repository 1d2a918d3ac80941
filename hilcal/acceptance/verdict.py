"""The acceptance verdict: each configured limit against its figure and the figure's expanded uncertainty.

Every limit is an upper limit (smaller is better). Decision rules:
- ``iso14253-1`` (default, ISO 14253-1 for proving conformance): pass only if value + U <= limit; fail only if
  value - U > limit; a value whose uncertainty band contains the limit is "not proven".
- ``simple`` (simple acceptance, the uncertainty is stated but not used): pass if value <= limit, else fail.
A limit that holds for several figures (every ISO 9283 test pose, AP_a, AP_b and AP_c) fails if any figure fails and
is not proven if any is not proven. A limit without any figure (the ISO 9283 test was not run) is "not tested".
Overall: fail if any limit fails, otherwise not proven if any is not proven or not tested, otherwise pass.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from hilcal.acceptance.uncertainty import Figure

Decision = Literal["pass", "fail", "not proven", "not tested"]
DecisionRule = Literal["iso14253-1", "simple"]
NO_LIMITS = "no acceptance limits set"

LIMITS: dict[str, tuple[str, str]] = {
    "max_position_mm": ("largest position error at the verification poses after calibration", "mm"),
    "rms_position_mm": ("RMS position error at the verification poses after calibration", "mm"),
    "max_orientation_deg": ("largest orientation error at the verification poses after calibration", "deg"),
    "rms_orientation_deg": ("RMS orientation error at the verification poses after calibration", "deg"),
    "ap_position_mm": ("ISO 9283 position accuracy AP_P at every test pose", "mm"),
    "rp_position_mm": ("ISO 9283 position repeatability RP_l at every test pose", "mm"),
    "ap_orientation_deg": ("ISO 9283 orientation accuracy |AP_a|, |AP_b|, |AP_c| at every test pose", "deg"),
    "rp_orientation_deg": ("ISO 9283 orientation repeatability RP_a, RP_b, RP_c (3 S) at every test pose", "deg"),
}
"""The limits a station's [acceptance] section may set: key -> (what it limits, unit)."""

RULES: dict[str, str] = {
    "iso14253-1": "ISO 14253-1 (conformance must be proven): a figure passes only if its value plus its expanded "
                  "uncertainty U (k = 2) is within the limit, and fails only if its value minus U exceeds the limit; "
                  "a figure whose uncertainty band contains the limit is 'not proven'.",
    "simple": "simple acceptance: a figure passes if its value is within the limit; its expanded uncertainty "
              "U (k = 2) is stated but not used in the decision.",
}


def decide(value: float, expanded: float, limit: float, rule: DecisionRule = "iso14253-1") -> Decision:
    """One figure against an upper limit under the decision rule."""
    if rule == "simple":
        return "pass" if value <= limit else "fail"
    if rule != "iso14253-1":
        raise ValueError(f"unknown decision rule {rule!r}: {', '.join(RULES)}")
    if value + expanded <= limit:
        return "pass"
    if value - expanded > limit:
        return "fail"
    return "not proven"


@dataclass(frozen=True)
class LimitCheck:
    """One configured limit, the figure that decided it (where, value, U) and the decision."""

    key: str
    limit: float
    decision: Decision
    where: str | None = None
    value: float | None = None
    expanded: float | None = None

    @property
    def label(self) -> str:
        return LIMITS[self.key][0]

    @property
    def unit(self) -> str:
        return LIMITS[self.key][1]

    def as_json(self) -> dict[str, object]:
        return {"key": self.key, "label": self.label, "unit": self.unit, "limit": self.limit,
                "decision": self.decision, "where": self.where, "value": self.value, "U": self.expanded}


def check_limit(key: str, limit: float, figures: Sequence[tuple[str, Figure]], rule: DecisionRule) -> LimitCheck:
    """The limit against every (where, figure) it applies to; the deciding figure is reported with it."""
    if key not in LIMITS:
        raise ValueError(f"unknown acceptance limit {key!r}: {', '.join(LIMITS)}")
    if not figures:
        return LimitCheck(key, limit, "not tested")
    decided = [(decide(f.value, f.expanded, limit, rule), where, f) for where, f in figures]
    for outcome in ("fail", "not proven"):
        hits = [d for d in decided if d[0] == outcome]
        if hits:
            worst = max(hits, key=lambda d: d[2].value)
            return LimitCheck(key, limit, outcome, worst[1], worst[2].value, worst[2].expanded)
    worst = max(decided, key=lambda d: d[2].value + d[2].expanded)
    return LimitCheck(key, limit, "pass", worst[1], worst[2].value, worst[2].expanded)


def check_limits(limits: Mapping[str, float], figures: Mapping[str, Sequence[tuple[str, Figure]]],
                 rule: DecisionRule = "iso14253-1") -> list[LimitCheck]:
    """Every configured limit (in the order of LIMITS) against the figures under its key."""
    unknown = set(limits) - set(LIMITS)
    if unknown:
        raise ValueError(f"unknown acceptance limits {sorted(unknown)}: {', '.join(LIMITS)}")
    return [check_limit(key, float(limits[key]), figures.get(key, ()), rule) for key in LIMITS if key in limits]


def overall(checks: Sequence[LimitCheck]) -> str:
    """"pass", "fail", "not proven", or NO_LIMITS when nothing was configured."""
    if not checks:
        return NO_LIMITS
    decisions = {c.decision for c in checks}
    if "fail" in decisions:
        return "fail"
    if decisions & {"not proven", "not tested"}:
        return "not proven"
    return "pass"
