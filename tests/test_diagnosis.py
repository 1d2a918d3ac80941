"""Missing-physics discovery on concealed-effect recordings from the independent rig, and on null recordings."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from hilcal import design
from hilcal.cli import app
from hilcal.diagnosis import diagnose
from hilcal.metrics import AccuracySummary
from hilcal.recording import write_recording
from procedures.simulated_recording import simulate_with_truth
from sim_devices.config import RigConfig, TemperatureConfig, concealed_effect_config, load_errors

SEED = 1
EFFECTS = ["leg_compliance", "sensor_scale", "thermal_expansion", "joint_backlash", "oil_column_compliance"]


@pytest.fixture(scope="module")
def plan(robot):
    return design.factorial_exchange(robot, 32, np.random.default_rng(0)).poses


def _record(robot, plan, effect: str, **config):
    cfg = RigConfig(seed=SEED, errors=load_errors("table2", robot), effects=concealed_effect_config(effect, 1.0, SEED),
                    **config)
    return simulate_with_truth(robot, cfg, plan, design.verification_poses(robot, 24, SEED))


@pytest.mark.parametrize("effect", EFFECTS)
def test_concealed_effect_is_named_and_modelled(robot, plan, effect):
    rec, truth = _record(robot, plan, effect)
    # Concealed: the raw (uncalibrated) error is millimetres, the effect tens of micrometres.
    assert AccuracySummary.of(rec.meas, rec.cmd).position_mm.max > 1.0
    diag = diagnose(rec, robot)
    assert diag.effect == effect, diag.explanation
    verify = rec.phase == "verify"
    floor = AccuracySummary.of(rec.meas[verify], truth[verify]).position_mm.rms
    assert diag.after.position_mm.rms <= 1.5 * floor
    assert diag.after.position_mm.rms < diag.before.position_mm.rms
    assert diag.cv_rms_effect_mm < diag.cv_rms_geometry_mm
    assert set(diag.parameters) == set(diag.std_errors) and len(diag.parameters) in (1, 6)


@pytest.mark.parametrize("noise_model", ["gaussian", "distance", "student_t"])
def test_null_recording_is_none(robot, plan, noise_model):
    rec, _ = _record(robot, plan, "none", cmm_noise_model=noise_model)
    diag = diagnose(rec, robot)
    assert diag.effect == "none", diag.explanation
    assert diag.parameters == {}


def test_constant_temperature_makes_thermal_untestable(robot, plan):
    still = TemperatureConfig(t0_c=23.0, drift_k_per_h=0.0, amplitude_k=0.0, period_s=3600.0, sensor_noise_k=0.01)
    rec, _ = _record(robot, plan, "sensor_scale", temperature=still)
    diag = diagnose(rec, robot)
    thermal = next(t for t in diag.tests if t.name == "thermal_expansion")
    assert not thermal.applicable and "temperature varied only" in thermal.reason
    assert diag.effect == "sensor_scale"
    assert "Thermal growth of the legs would look the same here" in diag.explanation


def test_cli_diagnose_json_and_report(robot, plan, tmp_path):
    rec, _ = _record(robot, plan, "leg_compliance")
    path = tmp_path / "rec.csv"
    write_recording(path, rec)
    result = CliRunner().invoke(app, ["diagnose", str(path), "--json", "--report", str(tmp_path / "rep")])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["effect"] == "leg_compliance"
    keys = {"max_position_mm", "rms_position_mm", "max_orientation_deg", "rms_orientation_deg"}
    assert set(data["before"]) == keys and set(data["after"]) == keys
    assert data["after"]["rms_position_mm"] < data["before"]["rms_position_mm"]
    assert "leg compliance" in data["explanation"]
    assert set(data["residual_rms_by_axis"]) == {"x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"}
    assert all(v > 0 for v in data["leg_residual_rms_mm"].values())
    for name in ("index.html", "legs.png", "time.png", "tests.png", "verify.png", "diagnosis.json"):
        assert (tmp_path / "rep" / name).stat().st_size > 0
    assert "data:image/png;base64," in (tmp_path / "rep" / "index.html").read_text()


def test_cli_diagnose_bad_input_exit_2(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("seq,phase\n1,measure\n")
    result = CliRunner().invoke(app, ["diagnose", str(bad), "--json"])
    assert result.exit_code == 2 and "missing" in result.output
