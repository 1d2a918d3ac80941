"""Physics the library does not list (written in the simulator only) is `unexplained`, located and modelled."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from hilcal.discovery.augmentation import augment
from hilcal.discovery.context import EffectContext
from hilcal.discovery.search import diagnose
from hilcal.discovery.term_groups import per_leg_diagonal
from hilcal.error_models import forward_jacobian
from hilcal.kinematics import Geometry
from hilcal.planning import design
from hilcal.recording import write_recording
from procedures.cli.app import app
from procedures.cli.simulated_recording import simulate_with_truth
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.unlisted_concealed import UNLISTED_EFFECT_NAMES, concealed_unlisted_config
from tests.poses import default_design

SEED = 301
VARIABLE_OF = {"transducer_bow": {"stroke", "stroke_cyclic"}, "cyclic_stroke_error": {"stroke_cyclic"},
               "hooke_joint_offset": {"base_joint_angle", "platform_joint_angle"},
               "local_heating": {"time", "time_lag", "temperature"}}
"""Where each effect lives: the variable a correct generic description uses."""


@pytest.fixture(scope="module")
def plan(robot):
    return default_design(32, 0)


def _record(robot, plan, name: str):
    config = RigConfig(seed=SEED, errors=load_errors("table2", robot),
                       effects=concealed_unlisted_config(name, 1.0, SEED))
    return simulate_with_truth(robot, config, plan, design.verification_poses(robot, 24, 0))


@pytest.mark.slow
@pytest.mark.parametrize("name", UNLISTED_EFFECT_NAMES)
def test_out_of_library_physics_is_unexplained_located_and_modelled(robot, plan, name):
    rec, _ = _record(robot, plan, name)
    diag = diagnose(rec, robot)
    assert diag.effect == "unexplained" and diag.effects == ("unexplained",), diag.explanation
    assert "within" not in diag.explanation
    assert diag.noise_ratio.ratio_geometry > 2.0
    assert diag.after.position_mm.rms <= 0.5 * diag.before.position_mm.rms
    assert diag.shapes and {s.group.variable for s in diag.shapes} <= VARIABLE_OF[name]


@pytest.mark.slow
def test_cyclic_error_report_exports_a_correction_table(robot, plan, tmp_path):
    rec, _ = _record(robot, plan, "cyclic_stroke_error")
    path = tmp_path / "rec.csv"
    write_recording(path, rec)
    result = CliRunner().invoke(app, ["diagnose", str(path), "--json", "--report", str(tmp_path / "rep")])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["effect"] == "unexplained"
    term = data["unexplained"][0]
    assert term["variable"] == "stroke_cyclic" and term["pinned_down"] is True
    assert term["verify_rms_after_mm"] < 0.5 * term["verify_rms_before_mm"]
    tables = sorted((tmp_path / "rep").glob("correction_*.csv"))
    assert tables and (tmp_path / "rep" / "steps.png").stat().st_size > 0
    with tables[0].open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["leg", "stroke_mm", "correction_mm", "band_low_mm", "band_high_mm"]
    values = np.array([float(r["correction_mm"]) for r in rows])
    assert np.ptp(values) > 0.05
    assert all(float(r["band_low_mm"]) <= float(r["correction_mm"]) <= float(r["band_high_mm"]) for r in rows)


def test_extra_poses_pin_down_a_poorly_recorded_term(robot):
    """Eight poses barely see a per-leg quadratic in stroke; the proposed poses shrink its band to the target."""
    poses = design.verification_poses(robot, 10, 3)
    geometry = Geometry.nominal(robot)

    def phi(c: EffectContext) -> np.ndarray:
        return per_leg_diagonal((c.stroke_mm / 1000.0) ** 2)[:, :, :1]

    ctx = EffectContext.at_poses(robot, poses)
    D = forward_jacobian(geometry, poses, robot.characteristic_length_mm)
    J = np.concatenate([D, np.einsum("cal,clq->caq", D[..., [6, 13, 20, 27, 34, 41]], phi(ctx))], axis=2)
    J = J.reshape(-1, 43)
    block = np.array([42])
    before = float(np.sqrt(0.005**2 * np.linalg.pinv(J.T @ J)[42, 42]))
    aug = augment(robot, geometry, robot.characteristic_length_mm, J.T @ J, 0.005**2, phi, block,
                  lambda c: float(np.sqrt(c[0, 0])), before / 3.0)
    assert aug.reached_target and 1 <= len(aug.poses) <= 24
    assert np.all(np.diff(aug.predicted_band_mm) <= 1e-12)
    assert design.feasible(robot, aug.poses).all()


@pytest.mark.slow
def test_a_cyclic_errors_period_between_the_scanned_ones_is_found(robot, plan):
    """Leg compliance with a 36.17 mm cyclic error over a 1 m stroke (27 cycles; the coverage study's seed 2905). The
    scan steps by a quarter of the frequency resolution; its nearest period left a beat growing along the stroke that
    a scale took up, so the diagnosis named a scale error (truth 0) instead of the compliance. The period is refined
    between its scanned neighbours: the compliance is named, the period is within a tenth of a scan step."""
    from hilcal.discovery.context import EffectContext
    from hilcal.discovery.generic_terms import period_step
    from sim_devices.rig.config import EffectsConfig, concealed_effect_config

    seed = 2905
    effects = EffectsConfig.model_validate({
        "leg_compliance": concealed_effect_config("leg_compliance", 1.0, seed).leg_compliance.model_dump(),
        "cyclic_stroke_error": concealed_unlisted_config("cyclic_stroke_error", 1.0, seed)
        .cyclic_stroke_error.model_dump()})
    config = RigConfig(seed=seed, errors=load_errors("table2", robot), effects=effects)
    rec, _ = simulate_with_truth(robot, config, plan, design.verification_poses(robot, 24, 0), seconds_per_pose=45.0)
    diag = diagnose(rec, robot, n_boot=399, seed=seed)
    assert set(diag.effects) == {"unexplained", "leg_compliance"}, diag.explanation
    cyclic = [g for g in diag.groups if g.variable == "stroke_cyclic"]
    assert len(cyclic) == 1
    true_period = float(np.atleast_1d(effects.cyclic_stroke_error.period_mm)[0])
    step = period_step(EffectContext.from_recording(rec.select("measure"), robot))
    assert abs(1.0 / cyclic[0].period_mm - 1.0 / true_period) < 0.1 * step
    assert diag.after.position_mm.rms < 0.015
