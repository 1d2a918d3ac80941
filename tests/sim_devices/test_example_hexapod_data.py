"""The committed small-hexapod example (examples/small_hexapod): regenerated from its seeded generator, and readable.

The generator is loaded from its file (examples/ is not a package); the committed CSV must equal what it
produces now, so the README's truth belongs to the committed data.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from hilcal.recording import read_recording, write_recording
from hilcal.robot import default_robot, load_robot

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "small_hexapod"


def _generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("small_hexapod_make_recording", EXAMPLE / "make_recording.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def generated() -> tuple[ModuleType, tuple]:
    module = _generator()
    return module, module.simulate()


def test_committed_csv_is_what_the_generator_produces(generated, tmp_path) -> None:
    _, (robot, _, rec, _) = generated
    fresh = tmp_path / "recording.csv"
    write_recording(fresh, rec)
    committed_text, fresh_text = (EXAMPLE / "recording.csv").read_text(), fresh.read_text()
    assert committed_text.splitlines()[0] == fresh_text.splitlines()[0]
    committed, again = read_recording(EXAMPLE / "recording.csv", robot), read_recording(fresh, robot)
    np.testing.assert_array_equal(committed.phase, again.phase)
    for name in ("seq", "time_s", "legs_mm", "meas"):
        np.testing.assert_allclose(getattr(committed, name), getattr(again, name), rtol=0, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(committed.extra["sphere_fit_rms_mm"], again.extra["sphere_fit_rms_mm"], atol=1e-9)


def test_recording_reads_with_the_robot_file_and_has_the_described_shape() -> None:
    robot = load_robot(EXAMPLE / "robot.toml")
    default = default_robot()
    assert robot.moving_mass_kg == 8.0 and default.moving_mass_kg / robot.moving_mass_kg == 500.0
    assert 240.0 < np.mean(robot.leg_limits) < 260.0 and robot.leg_limits[1] - robot.leg_limits[0] == 50.0
    rec = read_recording(EXAMPLE / "recording.csv", robot)
    measure, verify = rec.phase == "measure", rec.phase == "verify"
    assert (int(measure.sum()), int(verify.sum())) == (51, 24)
    assert np.all(measure[:51]) and np.all(verify[51:])
    assert not rec.has_cmd and np.all(np.isnan(rec.cmd))
    assert rec.temp_c is None and list(rec.extra) == ["sphere_fit_rms_mm"]
    # About a day between the sessions, regular steps within each.
    gap_h = (rec.time_s[51] - rec.time_s[50]) / 3600.0
    assert 18.0 < gap_h < 26.0
    assert np.all(np.diff(rec.time_s[:51]) > 0) and np.all(np.diff(rec.time_s[51:]) > 0)
    # Sphere-fit RMS of a 1 µm CMM: of order a micrometre.
    rms = rec.extra["sphere_fit_rms_mm"]
    assert 0.0002 < np.median(rms) < 0.002 and rms.max() < 0.005
    # Random order: every leg moves both ways between consecutive rows.
    steps = np.diff(rec.legs_mm[:51], axis=0)
    assert np.all((steps > 0.001).sum(axis=0) > 10) and np.all((steps < -0.001).sum(axis=0) > 10)
    # Three repeats of one pose among the measure rows.
    distinct = np.unique(np.round(rec.legs_mm[:51], 2), axis=0)
    assert len(distinct) == 51 - 2


def test_readme_states_the_generated_truth(generated) -> None:
    module, simulated = generated
    readme = (EXAMPLE / "README.md").read_text()
    assert "simulated" in readme.lower()
    assert module.truth_markdown(simulated) in readme
