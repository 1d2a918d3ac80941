"""The small electric hexapod of examples/small_hexapod: another robot size, no cmd or temp_c, two sessions.

The expected values are the concealed truth listed in examples/small_hexapod/README.md (the recording was made
by the simulated rig with that truth), not outputs of the diagnosis.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilcal.discovery.search import diagnose
from hilcal.recording import read_recording
from hilcal.robot import load_robot

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "small_hexapod"
TRUE_BACKLASH_MM = np.array([4.1, 5.7, 2.1, 5.0, 6.0, 5.1]) / 1000
TRUE_ZERO_SHIFT_MM = {3: -0.0032, 4: -0.0039}


@pytest.fixture(scope="module")
def diag():
    robot = load_robot(EXAMPLE / "robot.toml")
    rec = read_recording(EXAMPLE / "recording.csv", robot)
    assert not rec.has_cmd and rec.temp_c is None
    return diagnose(rec, robot)


def test_backlash_is_named_with_the_concealed_values(diag):
    assert diag.effect == "joint_backlash"
    fitted = np.array([diag.parameters[f"leg{i}_joint_backlash_mm"] for i in range(1, 7)])
    np.testing.assert_allclose(fitted, TRUE_BACKLASH_MM, atol=0.0015)


def test_nothing_unphysical_and_the_residual_reaches_the_noise(diag):
    for g in diag.groups:
        if g.physical_range is not None:
            values = np.array([diag.parameters[n] for n in g.names])
            assert np.all((values >= g.physical_range.low) & (values <= g.physical_range.high))
    assert "unexplained" not in diag.effects
    assert diag.noise.chosen.source == "sphere_fit_rms_mm column"
    assert diag.noise_ratio.ratio_geometry > 1.5 and diag.noise_ratio.ratio_final < 1.3
    assert diag.after.position_mm.rms < diag.before.position_mm.rms
    assert "thermal_expansion" in {c.name for c in diag.candidates if not c.applicable}


SPURIOUS_SHIFT_MM = 0.0012
"""Legs without a concealed shift may show one of about 1 µm (the noise is 1 µm per sphere coordinate and the
ball-screw scale errors of legs 1, 2 and 5 sit at the detection limit): smaller than a third of the true ones."""


def test_the_rehoming_step_between_sessions_is_found(diag):
    shift = diag.session_shift
    assert set(TRUE_ZERO_SHIFT_MM) <= set(shift.legs)
    for leg in range(1, 7):
        if leg in TRUE_ZERO_SHIFT_MM:
            assert shift.shift_mm[leg - 1] == pytest.approx(TRUE_ZERO_SHIFT_MM[leg], abs=0.0012)
        else:
            assert abs(shift.shift_mm[leg - 1]) < SPURIOUS_SHIFT_MM
    assert shift.verify_without_shift.position_mm.rms < 0.6 * diag.after.position_mm.rms
