"""Honest standard errors (hilcal.misfit) on a linear world built here, where the truth and the noise are known: six
legs read at random strokes, each with an offset and a gain error (the model), the pose residual being the legs'
length errors themselves. With nothing concealed the stated errors are the scatter of the estimates over many
recordings and the model is not called incomplete; with a smooth error over the stroke concealed (not in the model:
a transducer's nonlinearity, one third to one period over the stroke) they cover the truth where the noise alone
does not, and the model is called incomplete. (A concealed error that is nearly a straight line over the stroke is
taken up by the gain whole and leaves nothing in the residual to measure: docs/diagnosis.md says so.) With the
yardstick in its parts (an instrument and the readings), a complete model's residual sets the noise's level: an
instrument estimate that states too much is lowered, a stated one kept, and the readings' own noise carried."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.misfit import NoiseParts, honest_covariance, split_noise, variance_ratio_quantile

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


def _parts(instrument_sigma: float, instrument_dof: float | None, reading_variance: float = 0.0
           ) -> NoiseParts:
    """The yardstick in its parts for the linear world: an instrument of `instrument_sigma` per leg length and the
    readings' variance (both white in the legs: D is the identity here)."""
    eye = np.broadcast_to(np.eye(6), (N, 6, 6))
    return NoiseParts(instrument_sigma**2 * eye, "test instrument", instrument_dof, 1.0, eye, reading_variance, 0.0,
                      "test readings")


def _scatter_and_stated(parts: NoiseParts, reading_sigma: float = 0.0, runs: int = 300) -> tuple[np.ndarray, ...]:
    """The estimates' scatter over recordings of the world with noise SIGMA (and readings' noise `reading_sigma`),
    and the median stated error and instrument factor with the yardstick in `parts`."""
    rng = np.random.default_rng(5)
    s, J, truth, *_ = _world(rng, 0.0)
    errors, stated, factors = [], [], []
    for _ in range(runs):
        e = rng.normal(0, SIGMA, 6 * N) + rng.normal(0, reading_sigma, 6 * N)
        estimate = np.linalg.lstsq(J, J @ truth + e, rcond=None)[0]
        errors.append(estimate - truth)
        noise = parts.instrument_factor * parts.instrument + parts.reading_variance_mm2 * parts.readings_unit
        cov, misfit = honest_covariance(J, e - J @ (estimate - truth), noise, np.broadcast_to(np.eye(6), (N, 6, 6)),
                                        3000.0 + s, parts=parts, noise_dof=parts.instrument_dof)
        stated.append(np.sqrt(np.diag(cov)))
        factors.append(misfit.noise.instrument_factor if not misfit.incomplete else np.nan)
    return np.std(errors, axis=0), np.median(stated, axis=0), np.array(factors)


def test_a_complete_models_residual_corrects_an_instrument_estimate_that_states_too_much() -> None:
    """A sphere-fit column in another convention states 1.4x the noise: the complete model's residual is below it
    beyond the spread of both, so it sets the level, and the errors are the estimates' scatter, not 1.4x it."""
    scatter, stated, factors = _scatter_and_stated(_parts(1.4 * SIGMA, 200.0))
    assert stated == pytest.approx(scatter, rel=0.08)
    assert np.nanmedian(factors) == pytest.approx(1 / 1.4**2, rel=0.1)


def test_a_stated_instrument_noise_is_kept() -> None:
    """A noise the user states (--cmm-sigma-mm) is taken as stated, even where the residual leaves less."""
    scatter, stated, factors = _scatter_and_stated(_parts(1.4 * SIGMA, None))
    assert stated == pytest.approx(1.4 * scatter, rel=0.08)
    assert np.all(factors == 1.0)


def test_the_readings_noise_beyond_the_instrument_is_carried() -> None:
    """Readings with noise of their own (the model's inputs err, here 0.4 of the instrument's), below what tells an
    incomplete model: the instrument's yardstick is right but the complete model's residual shows more; the excess is
    carried as the readings' variance and the errors are the estimates' scatter, which the instrument's alone is not."""
    scatter, stated, factors = _scatter_and_stated(_parts(SIGMA, 200.0), 0.4 * SIGMA)
    alone = _scatter_and_stated(_parts(SIGMA, 200.0))[0]
    assert np.mean(np.isnan(factors)) < 0.1  # said incomplete about as often as the test's spread allows
    assert np.median(scatter / alone) == pytest.approx(np.hypot(1.0, 0.4), rel=0.03)
    assert np.median(stated / scatter) == pytest.approx(1.0, rel=0.05)


def test_split_noise_by_the_evidence() -> None:
    """The readings' variance is what the observed sum shows beyond the instrument (never below its floor); where it
    shows less, the instrument's estimate is pooled with it by degrees of freedom, or replaced when the difference is
    beyond their spread, and a stated instrument stays."""
    assert split_noise(150.0, 100.0, 10.0, 100.0, 100.0, 0.5) == (1.0, 5.0, "beyond")
    assert split_noise(101.0, 100.0, 10.0, 100.0, 100.0, 0.5) == (pytest.approx(0.98), 0.5, "pooled")
    factor, variance, how = split_noise(55.0, 100.0, 10.0, 100.0, 100.0, 0.5)
    assert (factor, variance, how) == (pytest.approx(0.5), 0.5, "contradicted")
    assert split_noise(55.0, 100.0, 10.0, 100.0, 100.0, 0.5, contradict=False)[2] == "pooled"
    assert split_noise(55.0, 100.0, 10.0, 100.0, None, 0.5) == (1.0, 0.5, "within")


def test_the_variance_ratio_quantiles_are_the_f_distributions() -> None:
    """Two standard deviations in probability (2.3 % in each tail) of the F distribution, and of chi-square over its
    degrees of freedom for an exact reference."""
    from scipy import stats

    tail = stats.norm.sf(2.0)
    assert variance_ratio_quantile(150, 16) == pytest.approx(stats.f.ppf(1 - tail, 150, 16))
    assert variance_ratio_quantile(150, 170, upper=False) == pytest.approx(stats.f.ppf(tail, 150, 170))
    assert variance_ratio_quantile(150, None) == pytest.approx(stats.chi2.ppf(1 - tail, 150) / 150)


def _sessions_world(rng: np.random.Generator, concealed_mm: float, warmer_mm: float) -> tuple[np.ndarray, ...]:
    """The linear world over two sessions, the model holding each leg's zero shift in the second (18 parameters):
    a smooth error over the stroke concealed (`concealed_mm`), and leg 1 warmer by `warmer_mm` through the second
    session (a drift's level, which its zero shift takes up whole). The truth of every shift is 0."""
    s, J12, truth12, *_ = _world(rng, 0.0)
    session = (np.arange(N) >= N // 2).astype(int)
    shift = np.zeros((N, 6, 6))
    shift[session == 1] = np.eye(6)
    J = np.hstack([J12, shift.reshape(6 * N, 6)])
    truth = np.concatenate([truth12, np.zeros(6)])
    period = rng.uniform(0.3, 1.0, 6) * STROKE
    concealed = concealed_mm * np.cos(2 * np.pi * s / period + rng.uniform(0, 2 * np.pi, 6))
    concealed[:, 0] += warmer_mm * session
    y = J @ truth + concealed.reshape(-1) + rng.normal(0, SIGMA, 6 * N)
    estimate = np.linalg.lstsq(J, y, rcond=None)[0]
    return s, J, session, truth, estimate, y - J @ estimate


def _shift_z(drifting: list[bool] | None, warmer_mm: float, runs: int = 40) -> np.ndarray:
    """(runs, 6) z of the zero shifts over recordings of `_sessions_world`."""
    rng = np.random.default_rng(23)
    out = []
    for _ in range(runs):
        s, J, session, truth, estimate, r = _sessions_world(rng, 0.03, warmer_mm)
        noise = np.broadcast_to(SIGMA**2 * np.eye(6), (N, 6, 6))
        cov, misfit = honest_covariance(J, r, noise, np.broadcast_to(np.eye(6), (N, 6, 6)), 3000.0 + s, session,
                                        drifting=drifting)
        assert misfit.incomplete
        out.append(((estimate - truth) / np.sqrt(np.diag(cov)))[12:])
    return np.abs(np.array(out))


def test_a_discrepancy_nothing_measures_between_sessions_does_not_pad_the_zero_shifts() -> None:
    """The model takes up every leg's constant in each session whole (offsets and zero shifts): a discrepancy constant
    within a session never reaches the residual, so nothing sizes it. Carried on every leg, it pads the shifts; carried
    only on a leg the model found drifting, the shifts of the others state their scatter."""
    padded = _shift_z(None, 0.0)
    honest = _shift_z([False] * 6, 0.0)
    assert np.mean(honest <= 2) >= 0.9
    assert np.median(honest) > 1.5 * np.median(padded)
    assert np.median(honest) > 0.5


def test_a_drifting_legs_zero_shift_carries_the_drifts_level() -> None:
    """Leg 1 warmer through the second session: its zero shift takes the drift's level (truth 0). The session part is
    what covers it, carried where the model found the leg drifting."""
    flagged = _shift_z([True] + [False] * 5, 0.02)
    unflagged = _shift_z([False] * 6, 0.02)
    assert np.mean(flagged[:, 0] <= 2) >= 0.9
    assert np.mean(unflagged[:, 0] <= 2) < 0.5
