"""The run's physics step: diagnose the run's own recording and decide what the upload corrects.

After the geometric identification the run looks for the physics the rigid model leaves out
(`hilcal.discovery.diagnose`, its noise yardstick from the repeated poses). Where the controller has the
compensation block, the upload is one set: the geometry fitted together with the effects, and the block that
corrects what the controller can correct. Without the block the upload is geometry only, and what the controller
cannot hold is said, faults first, with what to set by hand. A geometry the geometric fit makes implausible because it
absorbed a set-up fault (a scale error taken up by 30 mm of joint errors) is replaced by the joint fit's, which the
diagnosis explains. A geometry beyond the plausible bounds that the held-out verification poses vouch for (the model
holding it predicts them within SUPPORT_FACTOR of the noise yardstick) is a machine built that far from its robot
file: it is named as a gross assembly fault and uploaded. A geometry that stays implausible is refused with the
diagnosis' sentences.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hilcal.calibration import CalibrationOutcome
from hilcal.compensation import bound_violations, plausibility
from hilcal.leg_compensation import LegCompensation
from hilcal.metrics import AccuracySummary
from hilcal.recording import Recording
from hilcal.robot import Robot

SUPPORT_FACTOR = 3.0
"""Geometric errors beyond the plausible bounds are uploaded when the model holding them predicts the held-out verify
poses to within this many times the noise yardstick: the poses, not the bound, say how the machine is built."""

WHAT_IS_CORRECTED = {
    "sensor_scale": "the reading scale of each leg",
    "leg_compliance": "the sag, against the controller's own force reading",
    "oil_column_compliance": "the sag that grows with the stroke, against the controller's force reading",
    "drive_compliance": "the sag that grows with the stroke, against the controller's force reading",
    "joint_backlash": "the backlash, by the direction of each leg's last move",
    "thermal_expansion": "the growth with the leg temperature the controller reads",
    "unexplained": "with a table over the stroke",
}


@dataclass(frozen=True)
class ControllerInfo:
    """What the run read from the controller before it moved: its capabilities and the block it holds."""

    l0_mm: np.ndarray
    """The leg offsets it held while the recording was made (its stroke reference)."""
    offsets_only: bool = False
    compensation: bool = False
    force_reading: bool = False
    temperature_reading: bool = False
    live_block: LegCompensation = field(default_factory=LegCompensation)


@dataclass
class PhysicsDecision:
    """What the upload corrects, what it leaves, and the held-out accuracy predicted with and without the physics."""

    geometry_x: np.ndarray
    """The 42 geometric errors to upload (hilcal.error_models.GEOMETRIC_42)."""
    geometry_source: str
    block: LegCompensation | None = None
    """The block to upload; None leaves the controller's block as it is."""
    l0_shift_mm: np.ndarray = field(default_factory=lambda: np.zeros(6))
    problems: list[str] = field(default_factory=list)
    explained: list[str] = field(default_factory=list)
    """The geometric fit's implausible values that the physics explains (not a reason to refuse)."""
    findings: list[str] = field(default_factory=list)
    corrects: list[str] = field(default_factory=list)
    leaves: list[str] = field(default_factory=list)
    by_hand: list[str] = field(default_factory=list)
    predicted_with: AccuracySummary | None = None
    predicted_without: AccuracySummary | None = None
    diagnosis: Any = None
    loadable: Any = None
    enabled: bool = True

    def to_json(self) -> dict[str, Any]:
        return {
            "enabled": self.enabled, "geometry_source": self.geometry_source,
            "block": None if self.block is None else self.block.to_json(),
            "l0_shift_mm": self.l0_shift_mm.tolist(), "findings": self.findings, "corrects": self.corrects,
            "leaves": self.leaves, "by_hand": self.by_hand, "problems": self.problems, "explained": self.explained,
            "predicted_with_physics": None if self.predicted_with is None else self.predicted_with.brief(),
            "predicted_geometry_only": None if self.predicted_without is None else self.predicted_without.brief(),
            "corrected": [] if self.loadable is None else [c.to_json() for c in self.loadable.corrected],
            "not_corrected": [] if self.loadable is None else [c.to_json() for c in self.loadable.not_corrected],
            "effects": [] if self.diagnosis is None else list(self.diagnosis.effects),
            "noise_mm": None if self.diagnosis is None or self.diagnosis.noise.chosen is None else
            self.diagnosis.noise.chosen.position_mm,
            "noise_source": None if self.diagnosis is None or self.diagnosis.noise.chosen is None else
            self.diagnosis.noise.chosen.source,
        }


def _core(sentence: str, check: str) -> str:
    """A named effect's sentence without its check and full stop."""
    text = sentence.rstrip(".")
    return text[: -len(check) - 2] if check and text.endswith(": " + check) else text


def _said(correction: Any, check: str, loaded: bool) -> str:
    """One finding as the approval screen says it: what, and what the upload does about it."""
    core = _core(correction.sentence, check)
    if not loaded:
        return f"{core}: not corrected: {correction.why_not}."
    what = WHAT_IS_CORRECTED.get(correction.effect, "it")
    if correction.grade == "fault":
        return f"{core}: the upload corrects {what}; {check or 'find the cause'}."
    return f"{core}: the upload corrects it {what}." if correction.effect == "unexplained" else \
        f"{core}: the upload corrects {what}."


def _vouched(violations: list[str], held_out: AccuracySummary | None, diag: Any) -> str | None:
    """The finding that names bound violations the held-out poses vouch for (None: they do not, or there are none)."""
    noise = None if diag is None or diag.noise.chosen is None else diag.noise.chosen.position_mm
    if not violations or noise is None or held_out is None or not held_out.position_mm.rms <= SUPPORT_FACTOR * noise:
        return None
    return (f"Gross assembly fault: {'; '.join(violations)}; the model holding them predicts the {held_out.n_poses} "
            f"held-out verification poses to {1000 * held_out.position_mm.rms:.1f} µm RMS, within {SUPPORT_FACTOR:g}x "
            f"the noise yardstick ({1000 * noise:.1f} µm): the machine is built that far from its robot file; the "
            "upload corrects it; check the assembly and the robot file.")


def _split(problems: list[str], held_out: AccuracySummary | None, diag: Any) -> tuple[list[str], str | None]:
    """The problems left once the bound violations the held-out poses vouch for are a finding instead."""
    bounds = [p for p in problems if "exceeds the plausible" in p]
    finding = _vouched(bounds, held_out, diag)
    return ([p for p in problems if p not in bounds] if finding else problems), finding


def decide(rec: Recording, robot: Robot, outcome: CalibrationOutcome, info: ControllerInfo, *, physics: bool,
           joint_bound_mm: float = 10.0, offset_bound_mm: float = 20.0,
           pose_sigma: tuple[float, float] | None = None) -> PhysicsDecision:
    """The upload's geometry and block for this run (see the module docstring). ``pose_sigma`` (mm per position
    coordinate, deg per orientation axis) states the instrument's pose noise as the diagnosis' yardstick (a laser
    tracker's, from its MPE); None: the diagnosis' own (the CMM's sphere-fit residuals, the repeated poses)."""
    geo = outcome.identification
    geo_problems = plausibility(geo, joint_bound_mm, offset_bound_mm)
    without = outcome.after
    if not physics:
        return PhysicsDecision(geo.x[:42].copy(), "the geometric fit", problems=geo_problems,
                               predicted_without=without, enabled=False)
    from hilcal.discovery import diagnose
    from hilcal.discovery.loadable import held_out_prediction, loadable_compensation

    diag = diagnose(rec, robot) if pose_sigma is None else diagnose(rec, robot, pose_sigma=pose_sigma)
    findings = list(diag.summary)
    if not diag.steps:
        geo_problems, gross = _split(geo_problems, without, diag)
        return PhysicsDecision(
            geo.x[:42].copy(), "the geometric fit", problems=geo_problems, findings=[*findings, *filter(None, [gross])],
            corrects=["Nothing beyond the geometry: the residual is explained by the geometry and the noise, so the "
                      "controller's compensation block stays as it is."],
            predicted_with=without, predicted_without=without, diagnosis=diag)
    can_hold = info.compensation
    # without a block, what a block could hold is listed as such (not as a reading the controller lacks)
    loadable = loadable_compensation(diag, robot, info.l0_mm, live=info.live_block,
                                     force_reading=info.force_reading or not can_hold,
                                     temperature_reading=info.temperature_reading or not can_hold)
    joint_problems = bound_violations(loadable.geometry_x, joint_bound_mm, offset_bound_mm)
    if diag.wiring is not None and diag.wiring.problem:
        joint_problems.insert(0, f"the leg readings do not follow the legs ({diag.wiring.sentence()}): check the "
                                 "controller's feedback wiring before any upload")
    if not diag.final_fit.converged:
        joint_problems.insert(0, f"the fit with the effects did not converge: {diag.final_fit.message}")
    joint_problems, gross = _split(joint_problems, diag.compensation_after or diag.after, diag)
    if gross:
        findings.append(gross)
    checks = {n.effect: n.check for n in diag.named}
    decision = PhysicsDecision(loadable.geometry_x, "fitted together with the effects", problems=joint_problems,
                               findings=findings, predicted_without=without, diagnosis=diag, loadable=loadable)
    decision.explained = [] if joint_problems else geo_problems
    for c in loadable.corrected:
        check = checks.get(c.effect, "")
        if can_hold:
            decision.corrects.append(_said(c, check, True))
            continue
        decision.leaves.append(f"{_core(c.sentence, check)}: not corrected: this controller has no compensation "
                               "block.")
        if c.grade == "fault":
            decision.by_hand.append(f"{_core(c.sentence, check)}: {check or 'find the cause'}, and set it right on "
                                    "the controller by hand.")
    decision.leaves += [_said(c, checks.get(c.effect, ""), False) for c in loadable.not_corrected]
    if can_hold and loadable.corrects_anything:
        decision.block, decision.l0_shift_mm = loadable.block, loadable.l0_shift_mm
        decision.predicted_with = held_out_prediction(diag, loadable, rec, robot)
    elif not can_hold and not decision.by_hand and not geo_problems:
        # the machine as it is, without a block: the best rigid fit is the geometric one
        decision.geometry_x, decision.geometry_source = geo.x[:42].copy(), "the geometric fit"
        decision.problems, decision.predicted_with = geo_problems, without
    else:
        decision.predicted_with = held_out_prediction(diag, replace(loadable, loadable_keys=()), rec, robot)
    return decision
