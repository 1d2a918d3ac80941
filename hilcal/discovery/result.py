"""What a missing-physics diagnosis found: the steps of the selection, the named and generic effects, the noise
comparison, session shifts, located findings, and the JSON contract of `hilcal diagnose --json`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hilcal.discovery.context import EffectContext
from hilcal.discovery.noise import NoiseLevel
from hilcal.discovery.term_groups import TermGroup
from hilcal.identification import IdentificationResult
from hilcal.metrics import AccuracySummary

AXES = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")


def _finite(value: Any) -> Any:
    """NaN and infinity as JSON null."""
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


@dataclass(frozen=True)
class Step:
    """One accepted step of the forward selection."""

    index: int
    key: str
    effect: str
    kind: str
    title: str
    n_params: int
    f_statistic: float
    p_value: float
    p_wild: float
    p_gauss: float
    cv_before_mm: float
    cv_rms_mm: float
    verify: AccuracySummary | None
    removed: tuple[str, ...] = ()
    """Groups chosen earlier that this step made redundant (backward elimination)."""
    judged_before_mm: float | None = None
    judged_mm: float | None = None
    """Held-out verify RMS position error (mm) before and after this step, with any reported session shift removed
    (`hilcal.discovery.fitting.judged_verify_mm`): what confirms the step on held-out poses or not."""

    @property
    def confirmed(self) -> bool | None:
        """Whether the held-out figure did not get worse with this step (None without verify rows)."""
        if self.judged_mm is None or self.judged_before_mm is None:
            return None
        return self.judged_mm <= self.judged_before_mm

    def to_json(self) -> dict[str, Any]:
        return {
            "step": self.index, "group": self.key, "effect": self.effect, "kind": self.kind, "title": self.title,
            "n_params": self.n_params, "F": _finite(self.f_statistic), "p": _finite(self.p_value),
            "p_wild_bootstrap": _finite(self.p_wild), "p_gaussian": _finite(self.p_gauss),
            "cv_rms_before_mm": _finite(self.cv_before_mm), "cv_rms_mm": _finite(self.cv_rms_mm),
            "verify_rms_position_mm": None if self.verify is None else self.verify.position_mm.rms,
            "verify_judged_before_mm": self.judged_before_mm, "verify_judged_mm": self.judged_mm,
            "confirmed_on_held_out": self.confirmed,
            "removed": list(self.removed),
        }


@dataclass(frozen=True)
class CandidateResult:
    """A library candidate's evidence at the first step (or why it could not be tested)."""

    name: str
    title: str
    applicable: bool
    reason: str | None = None
    f_statistic: float = float("nan")
    p_value: float = float("nan")
    cv_rms_mm: float = float("nan")
    significant: bool = False
    rejected: str | None = None
    selected: bool = False
    grades: list[str] = field(default_factory=list)
    """Per parameter at the first step: typical, fault or impossible."""

    def to_json(self) -> dict[str, Any]:
        return {k: _finite(v) for k, v in self.__dict__.items()}


def candidate_results(first: list[Any], library: list[TermGroup], untestable: dict[str, str],
                      chosen_keys: set[str]) -> tuple[CandidateResult, ...]:
    """Every library candidate's evidence at the first step of the search (`first`: its `selection.GroupTest`s), or
    why it could not be tested."""
    by_key = {t.group.key: t for t in first}
    out = [CandidateResult(name, name, False, reason) for name, reason in untestable.items()]
    for g in library:
        t = by_key.get(g.key)
        if t is None:
            out.append(CandidateResult(g.key, g.title, False, "absorbed by the geometric parameters"))
            continue
        out.append(CandidateResult(g.key, g.title, True, None, t.f_statistic, t.p_value, t.cv_rms_mm,
                                   t.significant, t.rejected, g.key in chosen_keys, list(t.grades)))
    return tuple(out)


@dataclass(frozen=True)
class ParameterRow:
    """One fitted effect parameter as an engineer reads it: which effect and leg, value, unit, uncertainty, grade."""

    effect: str
    name: str
    leg: int | None
    value: float
    unit: str
    std_error: float
    grade: str

    def to_json(self) -> dict[str, Any]:
        return {k: _finite(v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class NamedEffect:
    """A named library effect, graded: physics (typical values) or a fault of the set-up (what to check)."""

    effect: str
    title: str
    grade: str
    """'physics' or 'fault'."""
    legs: tuple[int, ...]
    """1-based legs where the effect is clearly non-zero (or faulty)."""
    sentence: str
    check: str
    rows: tuple[ParameterRow, ...]

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "title": self.title, "grade": self.grade, "legs": list(self.legs),
                "sentence": self.sentence, "check": self.check or None}


@dataclass(frozen=True)
class EndStop:
    """A leg whose reading sits at its extreme in many rows: an end stop or a software limit."""

    leg: int
    reading_mm: float
    extreme: str
    n_rows: int
    n_total: int

    def to_json(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class Shape:
    """A generic (unexplained) correction of one leg in one variable, with its 95 % band, ready to export."""

    group: TermGroup
    leg: int
    """0-based leg this correction applies to."""
    param_index: np.ndarray
    """Indices of its parameters in the final fit's parameter vector."""
    local_columns: np.ndarray
    """Columns of the group's regressor that act on this leg."""
    columns: tuple[str, ...]
    grid: np.ndarray
    correction_mm: np.ndarray
    band_mm: np.ndarray
    amplitude_mm: float
    verify_before_mm: float | None
    verify_after_mm: float | None
    pinned: bool
    why_not_pinned: str = ""
    alternatives: tuple[str, ...] = ()
    proposed_poses: np.ndarray | None = None
    proposed_band_mm: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "group": self.group.key, "leg": self.leg + 1,
            "variable": self.group.variable, "setting": self.group.setting, "description": self.group.sentence,
            "amplitude_mm": self.amplitude_mm, "max_band_mm": float(np.max(self.band_mm)),
            "verify_rms_before_mm": self.verify_before_mm, "verify_rms_after_mm": self.verify_after_mm,
            "pinned_down": self.pinned, "why_not_pinned": self.why_not_pinned or None,
            "alternatives": list(self.alternatives),
            "proposed_extra_poses": None if self.proposed_poses is None else len(self.proposed_poses),
            "proposed_band_mm": self.proposed_band_mm,
        }


@dataclass(frozen=True)
class SessionShift:
    """Per-leg step of the leg-length residuals between the measure session(s) and a later verify-only session."""

    shift_mm: np.ndarray
    std_error_mm: np.ndarray
    p_values: np.ndarray
    legs: tuple[int, ...]
    verify_without_shift: AccuracySummary | None

    def to_json(self) -> dict[str, Any]:
        return {
            "shift_mm": self.shift_mm.tolist(), "std_error_mm": self.std_error_mm.tolist(),
            "p_holm": self.p_values.tolist(), "legs": list(self.legs),
            "verify_without_shift": None if self.verify_without_shift is None else self.verify_without_shift.brief(),
        }


@dataclass(frozen=True)
class NoiseComparison:
    """Residual against the noise yardstick, in total and per leg, for the geometry-only and the final model."""

    ratio_geometry: float
    ratio_final: float
    per_leg_geometry: np.ndarray
    per_leg_final: np.ndarray
    residual_rms_mm: float
    expected_rms_mm: float

    def to_json(self) -> dict[str, Any]:
        return {
            "ratio_geometry": self.ratio_geometry, "ratio_final": self.ratio_final,
            "per_leg_geometry": {f"leg{i + 1}": float(v) for i, v in enumerate(self.per_leg_geometry)},
            "per_leg_final": {f"leg{i + 1}": float(v) for i, v in enumerate(self.per_leg_final)},
            "residual_rms_mm": self.residual_rms_mm, "expected_from_noise_rms_mm": self.expected_rms_mm,
        }


@dataclass(frozen=True)
class Finding:
    """One located structure in the geometric fit's residuals."""

    leg: int | None
    driver: str
    correlation: float
    text: str


@dataclass(frozen=True)
class Diagnosis:
    """The whole answer: what is missing, how sure, how it was modelled and what that buys on held-out poses."""

    effect: str
    effects: tuple[str, ...]
    explanation: str
    parameters: dict[str, float]
    std_errors: dict[str, float]
    before: AccuracySummary | None
    after: AccuracySummary | None
    steps: tuple[Step, ...]
    candidates: tuple[CandidateResult, ...]
    rejected: tuple[tuple[str, str], ...]
    ambiguous_with: tuple[str, ...]
    cv_rms_geometry_mm: float
    cv_rms_final_mm: float
    noise: NoiseLevel
    noise_ratio: NoiseComparison | None
    shapes: tuple[Shape, ...]
    session_shift: SessionShift | None
    findings: tuple[Finding, ...]
    groups: tuple[TermGroup, ...]
    geometry_fit: IdentificationResult
    final_fit: IdentificationResult
    leg_residuals_mm: np.ndarray = field(repr=False)
    leg_residuals_final_mm: np.ndarray = field(repr=False)
    context: EffectContext = field(repr=False)
    measure: np.ndarray = field(repr=False)
    named: tuple[NamedEffect, ...] = ()
    aliases: tuple[Any, ...] = ()
    """Near-aliases of the named effects (hilcal.discovery.aliases.Alias)."""
    end_stops: tuple[EndStop, ...] = ()
    not_converged: tuple[str, ...] = ()
    """Fits that stopped before converging."""
    compensation: Any = None
    """The exported compensation set (hilcal.discovery.corrections.CompensationSet)."""
    summary: tuple[str, ...] = ()
    """One sentence per finding: what, on which legs, how big, in the machine's own terms."""
    evidence: str = ""
    """The evidence behind the summary (steps, held-out figures, noise, rejections)."""
    wiring: Any = None
    """The leg-wiring check (hilcal.wiring.LegWiring): readings in another order or counting the wrong way."""
    left_out_mm: np.ndarray | None = field(default=None, repr=False)
    """Per measure row: the length of the final model's left-out residual (mm). (The outlier screen reads the selected
    model's, before the final bounded fit: `hilcal.discovery.screen`.)"""
    zero_offsets_mm: np.ndarray | None = field(default=None, repr=False)
    """Per leg: how much it reads long (mm) at home with the calibrated geometry, joint frames removed."""
    excluded: tuple[dict[str, float], ...] = ()
    """Measure rows left out of the fit as measurement outliers: seq, left-out residual (mm), times the median."""
    unknown_rows: tuple[dict[str, Any], ...] = ()
    """Measure rows where a chosen history term cannot apply (never outliers): seq, legs, groups, left-out residual."""
    unconfirmed: tuple[str, ...] = ()
    """Keys of the final model's groups whose step made the held-out verify figure worse (judged with any reported
    session shift removed). They stay in the model the tests chose; `compensation` leaves them out unless
    `diagnose(..., include_unconfirmed=True)`."""
    compensation_after: AccuracySummary | None = None
    """Held-out verify accuracy of the exported compensation set's model (the final model when nothing is left
    out)."""
    station_frames: dict[int, np.ndarray] | None = None
    """Each instrument station's rigid error [dt (mm); dw (rad)] fitted with the model (``hilcal.discovery.stations``;
    the first station's is zero by definition); None: one station."""
    misfit: Any = None
    """Whether the model is incomplete and what its misfit adds to every standard error (``hilcal.misfit.Misfit``);
    None without a noise yardstick (the errors are then the cluster-robust sandwich of the residuals)."""

    @property
    def faults(self) -> tuple[NamedEffect, ...]:
        return tuple(n for n in self.named if n.grade == "fault")

    @property
    def parameter_table(self) -> tuple[ParameterRow, ...]:
        return tuple(r for n in self.named for r in n.rows)

    @property
    def cv_rms_effect_mm(self) -> float | None:
        return self.cv_rms_final_mm if self.steps else None

    def residual_rms_by_axis(self) -> dict[str, float]:
        """RMS of the geometry-only fit's pose residuals per axis: x, y, z in mm; roll, pitch, yaw in deg."""
        r = self.geometry_fit.residuals
        rms = np.sqrt(np.mean(r**2, axis=0))
        rms[3:] = np.degrees(rms[3:] / self.geometry_fit.length_mm)
        return dict(zip(AXES, map(float, rms), strict=True))

    def to_json(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "effects": list(self.effects),
            "summary": list(self.summary),
            "named": [n.to_json() for n in self.named],
            "faults": [n.to_json() for n in self.faults],
            "parameter_table": [r.to_json() for r in self.parameter_table],
            "aliases": [a.to_json() for a in self.aliases],
            "end_stops": [s.to_json() for s in self.end_stops],
            "not_converged": list(self.not_converged),
            "compensation": None if self.compensation is None else self.compensation.to_json(),
            "wiring": None if self.wiring is None else self.wiring.to_json(),
            "excluded_rows": list(self.excluded),
            "unknown_rows": list(self.unknown_rows),
            "unconfirmed": list(self.unconfirmed),
            "compensation_after": None if self.compensation_after is None else self.compensation_after.brief(),
            "leg_zero_offsets_mm": None if self.zero_offsets_mm is None else self.zero_offsets_mm.tolist(),
            "explanation": self.explanation,
            "parameters": self.parameters,
            "std_errors": self.std_errors,
            "geometry_mm": {n: float(v) for n, v in zip(self.final_fit.names[:42], self.final_fit.x[:42], strict=True)},
            "before": self.before.brief() if self.before else None,
            "after": self.after.brief() if self.after else None,
            "steps": [s.to_json() for s in self.steps],
            "candidates": [c.to_json() for c in self.candidates],
            "rejected": [{"effect": e, "reason": r} for e, r in self.rejected],
            "ambiguous_with": list(self.ambiguous_with),
            "cv_rms_geometry_mm": self.cv_rms_geometry_mm,
            "cv_rms_effect_mm": self.cv_rms_effect_mm,
            "noise": self.noise.to_json(),
            "model_incomplete": None if self.misfit is None else self.misfit.incomplete,
            "misfit": None if self.misfit is None else self.misfit.to_json(),
            "residual_to_noise": None if self.noise_ratio is None else self.noise_ratio.to_json(),
            "station_frames": None if self.station_frames is None else {
                str(k): {"dt_mm": v[:3].tolist(), "dw_deg": np.degrees(v[3:]).tolist()}
                for k, v in self.station_frames.items()},
            "unexplained": [s.to_json() for s in self.shapes],
            "session_shift": None if self.session_shift is None else self.session_shift.to_json(),
            "findings": [f.text for f in self.findings],
            "residual_rms_by_axis": self.residual_rms_by_axis(),
            "leg_residual_rms_mm": {f"leg{i + 1}": float(v) for i, v in
                                    enumerate(np.sqrt(np.mean(self.leg_residuals_mm[self.measure] ** 2, axis=0)))},
        }
