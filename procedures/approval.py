"""What the operator reads before approving an upload, as data (the panel's page) and as text (the terminal).

Faults first, then what the upload corrects and what it leaves (``procedures.physics``), the held-out accuracy
predicted with and without the physics, the compensation block and every changed parameter. The prediction is the
uploaded model against the held-out verification poses (measured before the upload, not used in the fit) and the
parameters' covariance carried to workspace poses; the model against itself (zero for a full upload) predicts
nothing and is not shown.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from drivers.controller.modbus import CompensationBlock, ParameterSet
from hilcal.acceptance.uncertainty import model_uncertainty
from hilcal.calibration import CalibrationOutcome
from hilcal.compensation import Compensation
from hilcal.misfit import Misfit
from hilcal.reports.physics import physics_lines
from hilcal.robot import Robot
from hilcal.workspace import random_poses
from procedures.physics import PhysicsDecision
from procedures.records import parameter_diff

WORKSPACE_SAMPLES = 64


def workspace_samples(robot: Robot, seed: int) -> np.ndarray:
    """The 64 poses, uniform over the feasible workspace and seeded by the plan, where the approval evaluates the
    compensation's fit and the model's spread. Uniform draws rather than the verification poses' Sobol set: the
    average and worst pose over 64 draws need no low discrepancy, and scipy.stats would add half a second to the
    start of every run."""
    return random_poses(robot, WORKSPACE_SAMPLES, np.random.default_rng(seed))


def upload_sha256(params: ParameterSet, block: CompensationBlock | None) -> str:
    """What the operator approves: the parameter set's registers, and the block's when one goes with it."""
    if block is None:
        return params.sha256()
    return hashlib.sha256(bytes.fromhex(params.sha256()) + bytes.fromhex(block.sha256())).hexdigest()


def model_covariance(outcome: CalibrationOutcome, estimator: str, physics: PhysicsDecision | None
                     ) -> tuple[np.ndarray | None, str]:
    """The uploaded geometry's 42 x 42 covariance and what it is: the geometric fit's, or the fit's with the effects
    when that is the geometry uploaded (the geometric fit's is inflated by the physics it left out)."""
    ident = outcome.identification
    if physics is not None and physics.diagnosis is not None and physics.geometry_source != "the geometric fit":
        final = physics.diagnosis.final_fit
        return (None if final.covariance is None else final.covariance[:42, :42],
                "the geometry's (fitted together with the effects)")
    return (ident.covariance if ident.model == "42" else None), f"the {estimator} parameters'"


def model_misfit(outcome: CalibrationOutcome, physics: PhysicsDecision | None) -> Misfit | None:
    """Whether the model behind the uploaded geometry's covariance is incomplete (``hilcal.misfit``): the diagnosis'
    when its geometry is uploaded, else the identification's (None without a noise yardstick)."""
    if physics is not None and physics.diagnosis is not None and physics.geometry_source != "the geometric fit":
        return physics.diagnosis.misfit
    return outcome.identification.misfit


def approval_detail(before: ParameterSet, new: ParameterSet, block: CompensationBlock | None, comp: Compensation,
                    outcome: CalibrationOutcome, estimator: str, physics: PhysicsDecision | None, robot: Robot,
                    samples: np.ndarray) -> dict[str, Any]:
    """Every changed parameter, the block, the physics in sentences and what can be predicted (module docstring)."""
    covariance, source = model_covariance(outcome, estimator, physics)
    misfit = model_misfit(outcome, physics)
    spread = None
    if covariance is not None and np.all(np.isfinite(covariance)):
        spread = model_uncertainty(robot, covariance, samples).as_json()
    predicted = outcome.after if physics is None or physics.predicted_with is None else physics.predicted_with
    return {"estimator": estimator, "mode": comp.mode, "new_sha256": upload_sha256(new, block),
            "live_sha256": before.sha256(), "diff": parameter_diff(before, new),
            "measured_before": outcome.before.brief() if outcome.before else None,
            "predicted_after": predicted.brief() if predicted else None,
            "predicted_geometry_only": outcome.after.brief() if outcome.after else None,
            "physics": None if physics is None else physics.to_json(),
            "compensation_block": None if block is None else block.model_dump(),
            "predicted_basis": f"the uploaded model against the {outcome.n_verify} held-out verification poses "
                               "(measured before the upload, not used in the fit)",
            "model_uncertainty": spread,
            "model_uncertainty_basis": None if spread is None else (
                f"{source} covariance carried to {len(samples)} workspace poses: expected error, 1 sigma (k = 2 "
                "doubles it)"),
            "model_incomplete": None if misfit is None else misfit.incomplete,
            "model_incomplete_note": misfit.sentence("the parameters") if spread and misfit else "",
            "uncompensated": None if comp.uncompensated is None else comp.uncompensated.brief()}


def _brief(b: dict[str, float]) -> str:
    return f"max {b['max_position_mm']:.4f} mm, RMS {b['rms_position_mm']:.4f} mm"


def approval_lines(detail: dict[str, Any], diff_first: bool = False) -> list[str]:
    """The approval as plain text (the terminal's view): findings, predictions, block, then the parameter diff
    (diff_first: the diff first, so that the findings stay on the screen just above the question that follows)."""
    physics = detail.get("physics")
    lines = [f"  - {line}" for line in physics_lines(physics)]
    if physics and physics.get("enabled", True):
        lines.insert(0, "What this run's recording shows beyond the geometry (faults first):")
    before, after = detail.get("measured_before") or {}, detail.get("predicted_after") or {}
    geometry_only = detail.get("predicted_geometry_only") or {}
    if before:
        lines.append(f"verification poses now (measured): {_brief(before)}")
    if after:
        lines.append(f"predicted after the upload: {_brief(after)} ({detail.get('predicted_basis', '')})")
    offsets_only = detail.get("mode") == "offsets_only"
    if offsets_only and geometry_only:
        lines.append(f"with the joint positions too (this controller holds the leg offsets only): "
                     f"{_brief(geometry_only)}")
    elif physics and physics.get("enabled", True) and geometry_only and geometry_only != after:
        lines.append(f"predicted with the geometry alone: {_brief(geometry_only)}")
    if offsets_only and detail.get("uncompensated"):
        lines.append(f"left uncompensated by the offsets over {WORKSPACE_SAMPLES} workspace poses: "
                     f"{_brief(detail['uncompensated'])}")
    spread = detail.get("model_uncertainty")
    if spread:
        lines.append(f"parameter uncertainty in the workspace: RMS {spread['rms_position_mm']:.4f} mm, worst pose "
                     f"{spread['max_position_mm']:.4f} mm ({detail.get('model_uncertainty_basis', '')})")
        if detail.get("model_incomplete_note"):
            lines.append(detail["model_incomplete_note"])
    block = detail.get("compensation_block")
    if block:
        lines.append("compensation block: " + block_summary(block))
    lines += [f"out of reach: {sentence}" for sentence in detail.get("out_of_reach") or []]
    diff = [f"{'parameter':<14} {'live (mm)':>12} {'new (mm)':>12} {'change (mm)':>12}"]
    diff += [f"{d['name']:<14} {d['live_mm']:12.4f} {d['new_mm']:12.4f} {d['delta_mm']:+12.4f}"
             for d in detail.get("diff", [])]
    lines = diff + lines if diff_first else lines + diff
    lines.append(f"upload sha256 {detail.get('new_sha256', '')[:16]}")
    return lines


def block_summary(block: dict[str, Any]) -> str:
    """A compensation block in one line: the non-zero terms per leg."""
    units = {"scale_ppm": ("scale", "ppm", 1.0), "backlash_mm": ("backlash", "µm", 1000.0),
             "compliance_mm_per_kn": ("compliance", "µm/kN", 1000.0),
             "compliance_mm_per_kn_m": ("compliance per metre", "µm/(kN m)", 1000.0),
             "thermal_ppm_per_k": ("thermal", "ppm/K", 1.0)}
    parts = []
    for name, (label, unit, factor) in units.items():
        values = [float(v) * factor for v in block.get(name, [])]
        if any(values):
            parts.append(f"{label} " + ", ".join(f"{v:+.3g}" for v in values) + f" {unit}")
    points = len((block.get("table_mm") or [[]])[0])
    if points:
        amplitude = max(abs(float(v)) for row in block["table_mm"] for v in row) * 1000.0
        parts.append(f"stroke table of {points} points per leg (up to {amplitude:.1f} µm)")
    return "; ".join(parts) or "corrects nothing"
