"""Honest standard errors (hilcal.misfit) on a linear world built here, where the truth and the noise are known: six
legs read at random strokes, each with an offset and a gain error (the model), the pose residual being the legs'
length errors themselves. With nothing concealed the stated errors are the scatter of the estimates over many
recordings and the model is not called incomplete; with a smooth error over the stroke concealed (not in the model:
a transducer's nonlinearity, one third to one period over the stroke) they cover the truth where the noise alone
does not, and the model is called incomplete. (A concealed error that is nearly a straight line over the stroke is
taken up by the gain whole and leaves nothing in the residual to measure: docs/diagnosis.md says so.)"""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.misfit import honest_covariance

N, SIGMA = 40, 0.005
STROKE = 1000.0


def _world(rng: np.random.Generator, concealed_mm: float) -> tuple[np.ndarray, ...]:
    """Strokes, Jacobian (offset and gain per leg), true parameters, the estimates and one recording's residual at
    the fit, with a concealed error of amplitude `concealed_mm` per leg: a cosine of the stroke at a random period of
    0.3 to 1 stroke and a random phase."""
    s = rng.uniform(0.0, STROKE, (N, 6))
    J = np.zeros((N, 6, 12))
    J[:, range(6), range(6)] = 1.0
    J[:, range(6), range(6, 12)] = s / STROKE
    J = J.reshape(6 * N, 12)
    truth = np.concatenate([rng.normal(0, 0.1, 6), rng.normal(0, 0.05, 6)])
    period = rng.uniform(0.3, 1.0, 6) * STROKE
    phase = rng.uniform(0, 2 * np.pi, 6)
    concealed = concealed_mm * np.cos(2 * np.pi * s / period + phase)
    y = J @ truth + concealed.reshape(-1) + rng.normal(0, SIGMA, 6 * N)
    estimate = np.linalg.lstsq(J, y, rcond=None)[0]
    return s, J, truth, estimate, y - J @ estimate


def _stated(s: np.ndarray, J: np.ndarray, r: np.ndarray):
    noise = np.broadcast_to(SIGMA**2 * np.eye(6), (N, 6, 6))
    return honest_covariance(J, r, noise, np.broadcast_to(np.eye(6), (N, 6, 6)), 3000.0 + s)


def test_a_complete_model_states_the_scatter_of_its_estimates() -> None:
    rng = np.random.default_rng(7)
    s, J, truth, *_ = _world(rng, 0.0)
    errors, stated, incomplete = [], [], 0
    for _ in range(1500):
        e = rng.normal(0, SIGMA, 6 * N)
        estimate = np.linalg.lstsq(J, J @ truth + e, rcond=None)[0]
        errors.append(estimate - truth)
        if len(stated) < 200:
            cov, misfit = _stated(s, J, e - J @ (estimate - truth))
            stated.append(np.sqrt(np.diag(cov)))
            incomplete += misfit.incomplete
    scatter = np.std(errors, axis=0)
    assert np.median(stated, axis=0) == pytest.approx(scatter, rel=0.05)
    assert incomplete <= 0.05 * len(stated)  # said incomplete about as often as the 2-sigma spread allows


def test_a_concealed_smooth_error_is_covered_and_said() -> None:
    rng = np.random.default_rng(11)
    z_honest, z_noise, said = [], [], 0
    for _ in range(60):
        s, J, truth, estimate, r = _world(rng, 0.03)
        cov, misfit = _stated(s, J, r)
        said += misfit.incomplete and "The model is incomplete" in misfit.sentence()
        noise_only = SIGMA**2 * np.linalg.inv(J.T @ J)
        z_honest += list((estimate - truth) / np.sqrt(np.diag(cov)))
        z_noise += list((estimate - truth) / np.sqrt(np.diag(noise_only)))
    z_honest, z_noise = np.abs(z_honest), np.abs(z_noise)
    assert said == 60
    assert np.mean(z_noise <= 2) < 0.5  # the noise alone does not cover the truth
    assert np.mean(z_honest <= 2) >= 0.9 and z_honest.max() < 4.5
