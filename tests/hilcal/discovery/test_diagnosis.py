"""Missing-physics discovery on recordings from the independent rig: single effects, pairs, nulls, the noise
yardstick, physically impossible fits, structure far above the noise, sessions, and the CLI contract."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from hilcal.discovery.noise import sphere_noise_covariance
from hilcal.discovery.search import diagnose
from hilcal.metrics import AccuracySummary
from hilcal.planning import design
from hilcal.recording import write_recording
from procedures.cli.app import app
from procedures.cli.simulated_recording import simulate_with_truth
from sim_devices.rig.config import EffectsConfig, RigConfig, concealed_effect_config, load_errors, random_errors
from sim_devices.rig.physics import axial_leg_forces_kn
from tests.poses import default_design

SEED = 1
EFFECTS = ["leg_compliance", "sensor_scale", "thermal_expansion", "joint_backlash", "oil_column_compliance"]
COMPANIONS = {"oil_column_compliance": {"leg_compliance"}}
"""The rig's oil column includes a dead volume (a load term independent of stroke): a structural compliance."""


@pytest.fixture(scope="module")
def plan(robot):
    return default_design(32, 0)


def _record(robot, plan, effects: list[str], seed: int = SEED, **config):
    merged = {e: getattr(concealed_effect_config(e, 1.0, seed), e) for e in effects}
    cfg = RigConfig(seed=seed, errors=config.pop("errors", load_errors("table2", robot)),
                    effects=EffectsConfig.model_validate(merged), **config)
    return simulate_with_truth(robot, cfg, plan, design.verification_poses(robot, 24, seed))


def _floor(rec, truth):
    verify = rec.phase == "verify"
    return AccuracySummary.of(rec.meas[verify], truth[verify]).position_mm.rms


def _within_ranges(diag):
    for g in diag.groups:
        if g.physical_range is None:
            continue
        values = np.array([diag.parameters[n] for n in g.names])
        assert np.all(values >= g.physical_range.low - 1e-9) and np.all(values <= g.physical_range.high + 1e-9)


@pytest.mark.parametrize("effect", EFFECTS)
def test_concealed_effect_is_named_and_modelled(robot, plan, effect):
    rec, truth = _record(robot, plan, [effect])
    assert AccuracySummary.of(rec.meas, rec.cmd).position_mm.max > 1.0
    diag = diagnose(rec, robot)
    assert diag.effect == effect, diag.explanation
    assert set(diag.effects) <= {effect} | COMPANIONS.get(effect, set())
    assert diag.after.position_mm.rms <= 1.5 * _floor(rec, truth)
    assert diag.after.position_mm.rms < diag.before.position_mm.rms
    assert diag.cv_rms_effect_mm < diag.cv_rms_geometry_mm
    _within_ranges(diag)


@pytest.mark.parametrize("pair", [("leg_compliance", "thermal_expansion"), ("sensor_scale", "joint_backlash")])
def test_two_effects_at_once_are_both_named(robot, plan, pair):
    rec, truth = _record(robot, plan, list(pair))
    diag = diagnose(rec, robot)
    assert set(diag.effects) == set(pair), diag.explanation
    assert [s.effect for s in diag.steps][:2] == list(diag.effects)
    assert diag.after.position_mm.rms <= 1.5 * _floor(rec, truth)
    _within_ranges(diag)


@pytest.mark.parametrize("noise_model", ["gaussian", "distance", "student_t"])
def test_null_recording_is_none_within_a_stated_noise(robot, plan, noise_model):
    rec, _ = _record(robot, plan, [], seed=10_001, cmm_noise_model=noise_model, errors=random_errors(10_001, 0.5))
    diag = diagnose(rec, robot)
    assert diag.effect == "none" and diag.effects == (), diag.explanation
    assert "within its measurement noise" in diag.explanation
    assert "sphere_fit_rms_mm column" in diag.explanation and "µm" in diag.explanation
    assert diag.noise_ratio.ratio_final < 1.3


def test_without_a_noise_source_only_relative_tests_are_claimed(robot, plan):
    rec, _ = _record(robot, plan, [], seed=10_002, errors=random_errors(10_002, 0.5))
    rec = dataclasses.replace(rec, extra={"temp_c": rec.extra["temp_c"]})
    diag = diagnose(rec, robot)
    assert diag.effect == "none"
    assert "noise level unknown: relative tests only" in diag.explanation
    assert "within its measurement noise" not in diag.explanation
    assert diag.noise_ratio is None
    stated = diagnose(rec, robot, cmm_sigma_mm=0.005)
    assert "--cmm-sigma-mm" in stated.explanation and "within its measurement noise" in stated.explanation
    # The same noise stated as a 6-DoF instrument's pose sigmas (the sphere registration's average, per axis).
    length = robot.characteristic_length_mm
    cov = sphere_noise_covariance(robot, rec.meas, 0.005, length)
    sd = np.sqrt(np.mean(np.diagonal(cov, axis1=1, axis2=2), axis=0))
    pose_sigma = (float(np.sqrt(np.mean(sd[:3] ** 2))), float(np.degrees(np.sqrt(np.mean(sd[3:] ** 2)) / length)))
    as_pose = diagnose(rec, robot, pose_sigma=pose_sigma)
    assert "--pose-sigma-mm" in as_pose.explanation and "within its measurement noise" in as_pose.explanation
    assert as_pose.noise.chosen.position_mm == pytest.approx(np.sqrt(3) * pose_sigma[0])


def _rig_forces(robot, rec, truth, errors):
    """Axial leg loads (kN) at the true poses, from the rig's own statics (independent of hilcal)."""
    da, db, _ = errors.as_arrays()
    R = Rotation.from_euler("ZYX", truth[:, [5, 4, 3]], degrees=True).as_matrix()
    return np.array([axial_leg_forces_kn(R[k], truth[k, :3], robot.a + da, robot.b + db, robot.moving_mass_kg,
                                         robot.com, robot.gravity_mps2) for k in range(len(truth))])


def test_a_physically_impossible_fit_is_not_named(robot, plan):
    """Legs that LENGTHEN under load (20 µm/kN): compliance would need a negative value; it must not be named."""
    rec, truth = _record(robot, plan, [])
    forces = _rig_forces(robot, rec, truth, load_errors("table2", robot))
    rec = dataclasses.replace(rec, legs_mm=rec.legs_mm - 0.020 * forces)
    diag = diagnose(rec, robot)
    assert "leg_compliance" not in diag.effects and "oil_column_compliance" not in diag.effects
    reasons = dict(diag.rejected)
    assert "outside the physically possible range" in reasons["leg_compliance"]
    assert "Not named as leg compliance" in diag.explanation
    _within_ranges(diag)
    assert diag.effect == "unexplained"


def test_structure_far_above_the_noise_is_never_called_none(robot, plan):
    """Random per-row leg errors of 30 µm: no variable describes them, but they are far above the CMM noise."""
    rec, _ = _record(robot, plan, [])
    jitter = np.random.default_rng(5).normal(0.0, 0.030, rec.legs_mm.shape)
    rec = dataclasses.replace(rec, legs_mm=rec.legs_mm + jitter)
    diag = diagnose(rec, robot)
    assert diag.effect == "unexplained", diag.explanation
    assert "within" not in diag.explanation
    assert diag.noise_ratio.ratio_final > 2.0


def test_verify_session_with_a_zero_shift_without_cmd_or_temperature(robot, plan):
    rec, _ = _record(robot, plan, ["sensor_scale"], seed=0)
    verify = rec.phase == "verify"
    legs = rec.legs_mm.copy()
    legs[verify] -= np.array([0.0, 0.03, 0.0, 0.0, -0.02, 0.0])
    time_s = rec.time_s.copy()
    time_s[verify] += 86_400.0
    rec = dataclasses.replace(rec, cmd=np.full_like(rec.cmd, np.nan), legs_mm=legs, time_s=time_s,
                              extra={"sphere_fit_rms_mm": rec.extra["sphere_fit_rms_mm"]})
    diag = diagnose(rec, robot)
    assert diag.effect == "sensor_scale"
    assert {2, 5} <= set(diag.session_shift.legs)
    assert diag.session_shift.shift_mm[1] == pytest.approx(0.03, abs=0.006)
    assert diag.session_shift.shift_mm[4] == pytest.approx(-0.02, abs=0.006)
    assert "re-homed" in diag.explanation
    assert diag.session_shift.verify_without_shift.position_mm.rms < diag.after.position_mm.rms


def test_cli_diagnose_json_and_report(robot, plan, tmp_path):
    rec, _ = _record(robot, plan, ["leg_compliance"])
    path = tmp_path / "rec.csv"
    write_recording(path, rec)
    result = CliRunner().invoke(app, ["diagnose", str(path), "--json", "--report", str(tmp_path / "rep")])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["effect"] == "leg_compliance" and data["effects"] == ["leg_compliance"]
    keys = {"max_position_mm", "rms_position_mm", "max_orientation_deg", "rms_orientation_deg"}
    assert set(data["before"]) == keys and set(data["after"]) == keys
    assert data["after"]["rms_position_mm"] < data["before"]["rms_position_mm"]
    step = data["steps"][0]
    assert step["group"] == "leg_compliance" and step["p"] < 0.05 and step["F"] > 1
    assert step["verify_rms_position_mm"] == pytest.approx(data["after"]["rms_position_mm"], rel=0.05)
    assert data["noise"]["known"] and data["noise"]["source"] == "sphere_fit_rms_mm column"
    assert set(data["residual_to_noise"]["per_leg_final"]) == {f"leg{i}" for i in range(1, 7)}
    for name in ("index.html", "legs.png", "time.png", "steps.png", "noise.png", "diagnosis.json"):
        assert (tmp_path / "rep" / name).stat().st_size > 0
    assert "data:image/png;base64," in (tmp_path / "rep" / "index.html").read_text()


@pytest.mark.parametrize("args, message", [([], "missing"), (["--cmm-sigma-mm", "-1"], "positive"),
                                           (["--pose-sigma-mm", "0.002"], "go together")])
def test_cli_diagnose_bad_input_exit_2(tmp_path, args, message):
    bad = tmp_path / "bad.csv"
    bad.write_text("seq,phase\n1,measure\n")
    result = CliRunner().invoke(app, ["diagnose", str(bad), "--json", *args])
    assert result.exit_code == 2 and message in result.output
