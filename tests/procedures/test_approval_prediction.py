"""The upload approval predicts honestly: the identified model against the held-out verification poses, and the
parameter covariance carried to the workspace, never the model against itself (zero for a full upload)."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.calibration import calibrate
from hilcal.compensation import ControllerGeometry, compensate
from hilcal.planning import design
from hilcal.robot import Robot
from procedures.approval import approval_detail, approval_lines
from procedures.calibration_procedure import to_parameter_set
from procedures.cli.simulated_recording import simulate_recording
from sim_devices.rig.config import RigConfig, load_errors


@pytest.mark.slow
def test_approval_shows_the_held_out_prediction_and_the_parameter_uncertainty(robot: Robot) -> None:
    config = RigConfig(seed=2, errors=load_errors("table2", robot), cmm_noise_mm=0.005)
    measure = design.factorial_exchange(robot, 32, np.random.default_rng(2)).poses
    recording = simulate_recording(robot, config, measure, design.verification_poses(robot, 12, 2))
    outcome = calibrate(recording, robot, estimator="ls")
    before = ControllerGeometry(robot.a, robot.b, robot.l0)
    samples = design.verification_poses(robot, 64, 5)
    comp = compensate(robot, before, outcome.identification, False, samples)
    assert comp.predicted.position_mm.max < 1e-6  # the model against itself: zero by construction, predicts nothing
    detail = approval_detail(to_parameter_set(before), to_parameter_set(comp.parameters), None, comp, outcome, "ls",
                             None, robot, samples)
    held_out = outcome.after.brief()
    assert detail["predicted_after"] == held_out and held_out["max_position_mm"] > 1e-3
    assert "12 held-out verification poses" in detail["predicted_basis"]
    spread = detail["model_uncertainty"]
    assert spread["n_poses"] == 64 and 0 < spread["rms_position_mm"] <= spread["max_position_mm"] < 0.05
    lines = "\n".join(approval_lines(detail))
    assert f"predicted after the upload: max {held_out['max_position_mm']:.4f} mm" in lines
    assert f"worst pose {spread['max_position_mm']:.4f} mm" in lines and "0.0000 mm" not in lines


@pytest.mark.slow
def test_approval_says_when_the_model_is_incomplete(robot: Robot) -> None:
    """A transducer gain error the geometry cannot hold: the parameter uncertainty carries the misfit and the approval
    says the model is incomplete (terminal and panel data); the complete recording of the test above says nothing."""
    from sim_devices.rig.config import EffectsConfig, concealed_effect_config

    measure = design.factorial_exchange(robot, 32, np.random.default_rng(2)).poses
    samples = design.verification_poses(robot, 64, 5)
    before = ControllerGeometry(robot.a, robot.b, robot.l0)
    details = {}
    for name, effects in (("complete", EffectsConfig()), ("gain", concealed_effect_config("sensor_scale", 1.0, 2))):
        config = RigConfig(seed=2, errors=load_errors("table2", robot), cmm_noise_mm=0.005, effects=effects)
        outcome = calibrate(simulate_recording(robot, config, measure, design.verification_poses(robot, 12, 2)),
                            robot, estimator="ls")
        comp = compensate(robot, before, outcome.identification, False, samples)
        details[name] = approval_detail(to_parameter_set(before), to_parameter_set(comp.parameters), None, comp,
                                        outcome, "ls", None, robot, samples)
    assert details["complete"]["model_incomplete"] is False and not details["complete"]["model_incomplete_note"]
    assert "The model is incomplete" not in "\n".join(approval_lines(details["complete"]))
    gain = details["gain"]
    assert gain["model_incomplete"] is True and gain["model_incomplete_note"].startswith("The model is incomplete")
    assert gain["model_incomplete_note"] in "\n".join(approval_lines(gain))
    spread = {k: d["model_uncertainty"]["rms_position_mm"] for k, d in details.items()}
    assert spread["gain"] > 2 * spread["complete"], spread
