"""The noise of the model's inputs (hilcal.discovery.noise): the leg readings' step and what a pose measured again in
a row shows beyond the instrument, the temperature readings' scatter about their smoothing, and the parts a diagnosis
says it carried. The recordings are the coverage study's (benchmarks/studies/stated_errors/readings.py): the rig's
recording with every leg reading given noise of a known size and rounded to an encoder's step."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from hilcal.discovery.context import detect_sessions
from hilcal.discovery.noise import in_a_row, reading_step_mm, temperature_noise
from hilcal.discovery.search import diagnose

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "benchmarks" / "studies"))
import coverage_study as study  # noqa: E402
from stated_errors.readings import Readings  # noqa: E402

pytestmark = pytest.mark.timeout(600)


@pytest.mark.parametrize("step_mm", [0.001, 0.0005, 0.00025, 0.0001, 0.01])
def test_the_readings_step_is_found_from_where_they_start(step_mm: float) -> None:
    """Readings on an encoder's grid that does not start at a whole step (a count offset) give that step."""
    rng = np.random.default_rng(1)
    legs = 4300.00037 + np.round(rng.uniform(0.0, 900.0, (40, 6)) / step_mm) * step_mm
    assert reading_step_mm(legs) == pytest.approx(step_mm)


def test_unrounded_readings_have_no_step() -> None:
    assert reading_step_mm(4300.0 + np.random.default_rng(2).uniform(0.0, 900.0, (40, 6))) == 0.0


def test_only_repeats_in_a_row_count() -> None:
    """Visits of one pose with other poses between them may differ by the machine's history: only runs of
    consecutive rows are kept."""
    runs = in_a_row([np.array([3, 4, 5, 9]), np.array([10, 20]), np.array([30, 31])])
    assert [r.tolist() for r in runs] == [[3, 4, 5], [30, 31]]


def test_the_temperature_noise_is_its_scatter_about_the_smoothing() -> None:
    """A drift with a slow oscillation (the rig's temperature model) plus 0.05 K of sensor noise, in two sessions:
    the sigma found is 0.05 K within its sampling spread (the scatter about a 7-row smoothing keeps most of the 120
    rows' degrees of freedom)."""
    rng = np.random.default_rng(3)
    time_s = np.concatenate([np.arange(60) * 45.0, 86_400.0 + np.arange(60) * 45.0])
    true_c = 21.0 + time_s / 3600.0 * 1.2 + 0.3 * np.sin(2 * np.pi * time_s / 5400.0)
    noise = temperature_noise(true_c + rng.normal(0.0, 0.05, time_s.size), detect_sessions(time_s))
    assert noise is not None
    assert noise.sigma_k == pytest.approx(0.05, rel=0.2)
    assert 60 < noise.dof < 120


@pytest.fixture(scope="module")
def world() -> dict:
    study.init_worker()
    return study._WORKER


def _noisy(world: dict, seed: int, readings: Readings):
    case = study.CoverageCase("noisy readings", ("sensor_scale",), None, seed, readings=readings)
    rec, _, _ = study.build(case, world["robot"], world["measure"], world["verify"], world["table2"])
    return rec


@pytest.mark.slow
def test_readings_noisier_than_the_instrument_are_found_and_said(world) -> None:
    """Readings with 3 µm of noise on a 1 µm CMM (the readings are most of the noise): the pose measured four times
    shows them, the complete model's residual sets their level, and the JSON and the words say the parts and their
    sources. The readings' variance is 9 µm² plus the 1 µm step's 1/12."""
    rec = _noisy(world, 6100, Readings(3.0, 1.0, 1.0, 0.001, 3))
    diag = diagnose(rec, world["robot"], n_boot=199, seed=1)
    out = diag.to_json()
    yardstick = out["noise"]["leg_readings"]
    assert "repeated pose" in yardstick["source"] and yardstick["step_mm"] == pytest.approx(0.001)
    assert 1.8 < 1000 * yardstick["sigma_mm"] < 4.5  # 16-odd degrees of freedom
    carried = out["misfit"]["noise"]
    assert not out["model_incomplete"]
    assert 2.5 < 1000 * carried["leg_reading_sigma_mm"] < 3.5
    assert "complete model's residual" in carried["level_source"]
    assert carried["sentence"] in diag.explanation and carried["sentence"] in diag.evidence
    assert f"leg readings' {1000 * carried['leg_reading_sigma_mm']:.2f} µm each" in carried["sentence"]


@pytest.mark.slow
def test_without_repeats_the_readings_floor_is_their_step(world) -> None:
    """Without a pose measured again in a row the yardstick's readings part is their step's alone, and says so."""
    rec = _noisy(world, 6101, Readings(0.5, 0.5, 1.0, 0.005, 0))
    diag = diagnose(rec, world["robot"], n_boot=199, seed=1)
    readings = diag.noise.readings
    assert readings is not None
    assert readings.sigma_mm == pytest.approx(0.0005 / np.sqrt(12.0))
    assert "no pose measured again in a row" in readings.source
