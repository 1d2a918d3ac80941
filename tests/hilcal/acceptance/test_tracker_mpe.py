"""A laser tracker's MPE carried into a pose's covariance: U(d) at the distances this test works out, and the Monte
Carlo covariance against the first-order formulas of a ring registration (the centroid's error u²/N per axis, the
turn about the ring's axis u²/(N r²)), with the tracker on the rings' axis so every target of a ring is as far."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.acceptance.tracker_mpe import (
    mpe_mm,
    pose_sigma,
    target_uncertainty_mm,
    tracker_origin_mm,
    tracker_pose_covariance,
)


def ring(n: int, radius_mm: float) -> np.ndarray:
    angles = 2 * np.pi * np.arange(n) / n + 0.3
    return np.column_stack([radius_mm * np.cos(angles), radius_mm * np.sin(angles), np.zeros(n)])


def test_the_mpe_grows_with_the_distance() -> None:
    assert mpe_mm(0.0, 15.0, 6.0) == pytest.approx(0.015)
    np.testing.assert_allclose(mpe_mm([5000.0, 10000.0], 15.0, 6.0), [0.045, 0.075])


def test_the_tracker_stands_where_its_alignment_puts_it() -> None:
    yaw = np.radians(30.0)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    where = np.array([4000.0, -1000.0, 1500.0])  # p_base = R p_tracker + where
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.T, -R.T @ where
    np.testing.assert_allclose(tracker_origin_mm(T), where, atol=1e-9)


def test_the_pose_covariance_is_the_registrations() -> None:
    platform, base = ring(4, 1000.0), ring(5, 2500.0)
    origin = np.array([0.0, 0.0, 6000.0])
    d1, d2 = np.hypot(1000.0, 6000.0), np.hypot(2500.0, 6000.0)
    u1, u2 = (15.0 + 6.0 * d1 / 1000.0) / 2000.0, (15.0 + 6.0 * d2 / 1000.0) / 2000.0
    np.testing.assert_allclose(target_uncertainty_mm(platform, base, np.zeros(6), origin, 15.0, 6.0),
                               2 * np.r_[[u1] * 4, [u2] * 5])
    cov = tracker_pose_covariance(platform, base, np.zeros(6), origin, 15.0, 6.0, draws=20000, seed=5)
    sd = np.sqrt(np.diag(cov))
    translation = np.sqrt(u1**2 / 4 + u2**2 / 5)
    np.testing.assert_allclose(sd[:3], translation, rtol=0.04)
    yaw = np.degrees(np.sqrt(u1**2 / (4 * 1000.0**2) + u2**2 / (5 * 2500.0**2)))
    assert sd[5] == pytest.approx(yaw, rel=0.04)
    position, orientation = pose_sigma(cov)
    assert position == pytest.approx(translation, rel=0.04) and orientation > yaw
    doubled = tracker_pose_covariance(platform, base, np.zeros(6), origin, 30.0, 12.0, draws=20000, seed=5)
    np.testing.assert_allclose(np.diag(doubled), 4.0 * np.diag(cov), rtol=1e-3)
