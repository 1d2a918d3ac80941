"""The rank-6 update formulas of the sequential design criteria (hilcal.planning.criteria) against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.planning.criteria import d_gain, ds_gain, v_gain


@pytest.fixture
def problem(rng):
    A = rng.normal(size=(60, 10))
    info = A.T @ A
    candidates = rng.normal(size=(7, 6, 10))
    targets = rng.normal(size=(5, 3, 10))
    return info, candidates, targets


def test_d_gain_is_the_log_det_increase(problem):
    info, cands, _ = problem
    brute = [np.linalg.slogdet(info + c.T @ c)[1] - np.linalg.slogdet(info)[1] for c in cands]
    np.testing.assert_allclose(d_gain(info, cands, 0.0), brute, rtol=1e-9)


def test_v_gain_is_the_relative_fall_of_the_target_variance(problem):
    info, cands, targets = problem
    T = targets.reshape(-1, 10)

    def total(M):
        return np.trace(T @ np.linalg.inv(M) @ T.T)

    brute = [np.log(total(info) / total(info + c.T @ c)) for c in cands]
    np.testing.assert_allclose(v_gain(info, cands, targets), brute, rtol=1e-9)


def test_ds_gain_is_the_log_det_increase_of_the_schur_complement(problem):
    info, cands, _ = problem

    def schur(M):
        return M[6:, 6:] - M[6:, :6] @ np.linalg.solve(M[:6, :6], M[:6, 6:])

    brute = [np.linalg.slogdet(schur(info + c.T @ c))[1] - np.linalg.slogdet(schur(info))[1] for c in cands]
    np.testing.assert_allclose(ds_gain(info, cands, 6, 0.0), brute, rtol=1e-9)


def test_a_ridge_makes_a_singular_start_comparable(rng):
    cands = rng.normal(size=(4, 6, 10))
    gains = d_gain(np.zeros((10, 10)), cands, 1e-6)
    assert np.all(np.isfinite(gains)) and np.all(gains > 0)
