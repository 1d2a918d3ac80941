"""Sphere fitting: exact recovery, noise propagation, the outlier rule and the probe pattern."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.sphere_fit import (
    SphereFitError,
    fit_sphere,
    fit_sphere_robust,
    outlier_threshold_mm,
    sphere_probe_pattern,
)


def cap_points(rng: np.random.Generator, centre: np.ndarray, radius: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points on the upper cap (elevation 20..90 deg about a random axis), built here from spherical angles."""
    axis = Rotation.random(random_state=rng).as_matrix()
    el = np.radians(rng.uniform(20.0, 90.0, n))
    az = rng.uniform(0.0, 2.0 * np.pi, n)
    local = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    normals = local @ axis.T
    return centre + radius * normals, normals


def test_exact_fit_fixed_and_free_radius() -> None:
    rng = np.random.default_rng(0)
    for _ in range(30):
        centre = rng.uniform(-5000, 5000, 3)
        radius = rng.uniform(5.0, 50.0)
        pts, _ = cap_points(rng, centre, radius, int(rng.integers(5, 12)))
        fixed = fit_sphere(pts, radius)
        free = fit_sphere(pts)
        np.testing.assert_allclose(fixed.centre_mm, centre, atol=1e-8)
        np.testing.assert_allclose(free.centre_mm, centre, atol=1e-7)
        assert abs(free.radius_mm - radius) < 1e-7
        assert fixed.rms_mm < 1e-8 and free.rms_mm < 1e-7
        assert fixed.radius_fixed and not free.radius_fixed


def test_residuals_are_signed_radial_distances() -> None:
    centre, radius = np.array([10.0, -20.0, 30.0]), 12.7
    pts, normals = cap_points(np.random.default_rng(1), centre, radius, 8)
    offsets = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.003])
    fit = fit_sphere(pts + offsets[:, None] * normals, radius, centre)
    # the fit moves slightly towards the displaced point; its residual stays the largest and positive
    assert np.argmax(fit.residuals_mm) == 7 and fit.residuals_mm[7] > 0.001
    recomputed = np.linalg.norm(pts + offsets[:, None] * normals - fit.centre_mm, axis=1) - radius
    np.testing.assert_allclose(fit.residuals_mm, recomputed, atol=1e-12)
    assert fit.rms_mm == pytest.approx(np.sqrt(np.mean(recomputed**2)))


def test_noise_propagation_matches_linear_theory() -> None:
    """Centre covariance = sigma^2 (N^T N)^-1 for a fixed radius, N the unit normals at the touch points."""
    rng = np.random.default_rng(2)
    centre, radius, sigma = np.array([100.0, 200.0, 300.0]), 12.7, 0.002
    pts, normals = sphere_probe_pattern(centre, radius, (0.0, 0.0, 1.0), 6, (30.0,))
    expected = sigma**2 * np.linalg.inv(normals.T @ normals)
    fit0 = fit_sphere(pts, radius)
    np.testing.assert_allclose(fit0.centre_cov_unit * sigma**2, expected, rtol=1e-6, atol=1e-15)
    draws = 600
    errs = np.empty((draws, 3))
    rms = np.empty(draws)
    for k in range(draws):
        f = fit_sphere(pts + rng.normal(0.0, sigma, pts.shape), radius)
        errs[k] = f.centre_mm - centre
        rms[k] = f.sigma_hat_mm
    empirical = np.cov(errs.T)
    # variance estimates from 600 draws have ~6 % standard error
    np.testing.assert_allclose(np.diag(empirical), np.diag(expected), rtol=0.2)
    assert np.all(np.abs(errs.mean(axis=0)) < 4 * np.sqrt(np.diag(expected) / draws))
    # isotropic noise projects to sigma along each normal: sigma_hat estimates sigma
    assert np.sqrt(np.mean(rms**2)) == pytest.approx(sigma, rel=0.1)


def test_free_radius_with_noise_is_unbiased_enough() -> None:
    rng = np.random.default_rng(3)
    centre, radius, sigma = np.zeros(3), 12.7, 0.002
    pts, _ = sphere_probe_pattern(centre, radius, (0.0, 0.0, 1.0), 8, (20.0, 50.0))
    radii = [fit_sphere(pts + rng.normal(0.0, sigma, pts.shape)).radius_mm for _ in range(200)]
    assert abs(np.mean(radii) - radius) < 0.001
    assert np.std(radii) < 5 * sigma


def test_fixed_radius_avoids_the_mirror_solution_on_a_cap() -> None:
    centre, radius = np.array([0.0, 0.0, 0.0]), 12.7
    pts, _ = sphere_probe_pattern(centre, radius, (0.0, 0.0, 1.0), 5, (60.0,))
    fit = fit_sphere(pts, radius, initial_centre_mm=centre + np.array([0.5, -0.5, 0.5]))
    np.testing.assert_allclose(fit.centre_mm, centre, atol=1e-9)


def test_outlier_is_rejected_and_clean_points_are_kept() -> None:
    rng = np.random.default_rng(4)
    centre, radius, sigma = np.array([1.0, 2.0, 3.0]), 12.7, 0.002
    pts, normals = sphere_probe_pattern(centre, radius, (0.0, 0.3, 1.0), 6, (30.0,))
    threshold = outlier_threshold_mm(sigma)
    false_alarms = 0
    for trial in range(100):
        noisy = pts + rng.normal(0.0, sigma, pts.shape)
        clean = fit_sphere_robust(noisy, radius, threshold, centre)
        false_alarms += int(not clean.inliers.all())
        bad = trial % len(pts)
        noisy[bad] += 0.5 * normals[bad]
        robust = fit_sphere_robust(noisy, radius, threshold, centre)
        assert robust.outliers.tolist() == [bad]
        assert robust.residuals_mm[bad] == pytest.approx(0.5, abs=0.02)
        assert np.linalg.norm(robust.fit.centre_mm - centre) < 0.01
        assert robust.consistent
        assert len(robust.fit.residuals_mm) == len(pts) - 1
    assert false_alarms == 0


def test_two_outliers_and_an_inward_one() -> None:
    rng = np.random.default_rng(5)
    centre, radius = np.zeros(3), 12.7
    pts, normals = sphere_probe_pattern(centre, radius, (0.0, 0.0, 1.0), 8, (30.0,))
    noisy = pts + rng.normal(0.0, 0.002, pts.shape)
    noisy[2] += 0.2 * normals[2]
    noisy[6] -= 0.1 * normals[6]
    robust = fit_sphere_robust(noisy, radius, 0.01, centre)
    assert sorted(robust.outliers.tolist()) == [2, 6]
    assert robust.residuals_mm[6] < -0.05


def test_threshold_rule() -> None:
    assert outlier_threshold_mm(0.002, 5.0, 0.005) == pytest.approx(0.01)
    assert outlier_threshold_mm(0.0005, 5.0, 0.005) == pytest.approx(0.005)
    with pytest.raises(ValueError):
        outlier_threshold_mm(0.002, 0.0)


@pytest.mark.parametrize(
    ("points", "radius"),
    [
        (np.zeros((3, 3)), 1.0),
        (np.full((5, 3), np.nan), 1.0),
        (np.zeros((5, 2)), 1.0),
        (np.array([[1.0, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0.6, 0.8, 0]]), None),
        (np.array([[1.0, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]]), -1.0),
    ],
)
def test_degenerate_input_is_a_clean_error(points: np.ndarray, radius: float | None) -> None:
    with pytest.raises(SphereFitError):
        fit_sphere(points, radius)


def test_probe_pattern_geometry() -> None:
    centre, radius = np.array([5.0, 6.0, 7.0]), 12.7
    up = np.array([0.1, -0.2, 1.0])
    targets, normals = sphere_probe_pattern(centre, radius, up, 6, (30.0, 45.0))
    assert targets.shape == (13, 3)
    np.testing.assert_allclose(np.linalg.norm(targets - centre, axis=1), radius)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    np.testing.assert_allclose(normals[0], up / np.linalg.norm(up))
    elevation = np.degrees(np.arcsin(normals @ (up / np.linalg.norm(up))))
    np.testing.assert_allclose(elevation, [90.0] + [30.0] * 6 + [45.0] * 6, atol=1e-9)
    with pytest.raises(ValueError):
        sphere_probe_pattern(centre, radius, (0.0, 0.0, 0.0))
