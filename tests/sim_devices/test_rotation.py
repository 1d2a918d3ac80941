"""The simulators' numpy rotation helpers against scipy's Rotation and Slerp (an independent implementation), and the
simulator's start-up without scipy."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from sim_devices.rotation import (
    matrix_from_rotvec,
    matrix_from_rpy_deg,
    orthonormalized,
    rotvec_from_matrix,
    rpy_deg_from_matrix,
    slerp,
)

ROOT = Path(__file__).resolve().parents[2]
RNG_SEED = 20


def random_rpy_deg(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """[..., roll, pitch, yaw] (deg) away from the pitch's gimbal lock."""
    return rng.uniform([-180.0, -85.0, -180.0], [180.0, 85.0, 180.0], (*shape, 3))


def random_rotvecs(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) rotation vectors with angles from tiny to just below pi (rad)."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([[0.0, 1e-14, 1e-9, 1e-4, np.pi / 2, np.pi - 1e-6], rng.uniform(0.0, np.pi, n - 6)])
    return axes * angles[:, None]


def test_matrix_from_rpy_deg_is_scipys_intrinsic_zyx_batched() -> None:
    rpy = random_rpy_deg(np.random.default_rng(RNG_SEED), (4, 5))
    ours = matrix_from_rpy_deg(rpy)
    assert ours.shape == (4, 5, 3, 3)
    reference = Rotation.from_euler("ZYX", rpy.reshape(-1, 3)[:, ::-1], degrees=True).as_matrix()
    np.testing.assert_allclose(ours.reshape(-1, 3, 3), reference, rtol=0, atol=1e-14)
    np.testing.assert_allclose(matrix_from_rpy_deg(rpy[2, 3]), reference[13], rtol=0, atol=1e-14)


def test_rpy_deg_from_matrix_is_scipys_and_round_trips_batched() -> None:
    rpy = random_rpy_deg(np.random.default_rng(RNG_SEED + 1), (3, 7))
    R = Rotation.from_euler("ZYX", rpy.reshape(-1, 3)[:, ::-1], degrees=True).as_matrix().reshape(3, 7, 3, 3)
    ours = rpy_deg_from_matrix(R)
    assert ours.shape == (3, 7, 3)
    np.testing.assert_allclose(ours, rpy, rtol=0, atol=1e-10)
    reference = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("ZYX", degrees=True)[:, ::-1]
    np.testing.assert_allclose(ours.reshape(-1, 3), reference, rtol=0, atol=1e-10)
    np.testing.assert_allclose(matrix_from_rpy_deg(ours), R, rtol=0, atol=1e-14)


def test_rotation_vectors_match_scipy_both_ways_and_round_trip() -> None:
    for w in random_rotvecs(np.random.default_rng(RNG_SEED + 2), 200):
        R = matrix_from_rotvec(w)
        np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), rtol=0, atol=1e-14)
        np.testing.assert_allclose(R.T @ R, np.eye(3), rtol=0, atol=1e-14)
        back = rotvec_from_matrix(R)
        np.testing.assert_allclose(back, Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-9)
        np.testing.assert_allclose(back, w, rtol=0, atol=1e-9)
        np.testing.assert_allclose(matrix_from_rotvec(back), R, rtol=0, atol=1e-14)


def test_rotation_vector_of_a_half_turn_has_the_angle_pi() -> None:
    axis = np.array([2.0, -1.0, 0.5]) / np.linalg.norm([2.0, -1.0, 0.5])
    w = rotvec_from_matrix(matrix_from_rotvec(np.pi * axis))
    assert np.linalg.norm(w) == pytest.approx(np.pi, abs=1e-12)
    np.testing.assert_allclose(np.abs(w @ axis), np.pi, rtol=0, atol=1e-12)


def test_orthonormalized_removes_a_small_departure_and_keeps_the_rotation() -> None:
    rng = np.random.default_rng(RNG_SEED + 3)
    R = Rotation.random(random_state=rng).as_matrix()
    drifted = R + rng.normal(0.0, 1e-9, (3, 3))
    fixed = orthonormalized(drifted)
    np.testing.assert_allclose(fixed.T @ fixed, np.eye(3), rtol=0, atol=1e-15)
    np.testing.assert_allclose(fixed, R, rtol=0, atol=1e-8)
    np.testing.assert_allclose(orthonormalized(R), R, rtol=0, atol=1e-15)


@pytest.mark.parametrize("t", [0.0, 0.3, 1.0])
def test_slerp_matches_scipys(t: float) -> None:
    rng = np.random.default_rng(RNG_SEED + 4)
    for _ in range(50):
        R0, R1 = Rotation.random(2, random_state=rng).as_matrix()
        reference = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([R0, R1])))([t]).as_matrix()
        np.testing.assert_allclose(slerp(R0, R1, np.array([t])), reference, rtol=0, atol=1e-12)


def test_slerp_over_many_fractions_from_start_to_end() -> None:
    rng = np.random.default_rng(RNG_SEED + 5)
    R0, R1 = Rotation.random(2, random_state=rng).as_matrix()
    t = np.linspace(0.0, 1.0, 11)
    ours = slerp(R0, R1, t)
    assert ours.shape == (11, 3, 3)
    np.testing.assert_allclose(ours, Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([R0, R1])))(t).as_matrix(),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(ours[0], R0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(ours[-1], R1, rtol=0, atol=1e-12)


def test_the_simulator_starts_without_scipy() -> None:
    code = "import sys, sim_devices.launcher; print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))"
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60,
                          check=True)
    assert done.stdout.strip() == "[]", done.stdout
