"""Shared fixtures: the default robot and a seeded generator."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import structlog

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import Robot, default_robot


@pytest.fixture(autouse=True)
def _reset_structlog():
    """The CLI configures structlog for its own stderr; give every test the library defaults back."""
    yield
    structlog.reset_defaults()


@pytest.fixture(scope="session")
def robot() -> Robot:
    return default_robot()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def feasible_random_poses(robot: Robot, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform workspace poses whose nominal leg lengths respect the limits (written here, not in hilcal)."""
    ws = robot.workspace
    lo, hi = robot.leg_limits
    out = np.empty((0, 6))
    while len(out) < n:
        q = rng.uniform(ws[:, 0], ws[:, 1], size=(4 * n, 6))
        L = inverse_kinematics(Geometry.nominal(robot), q)
        out = np.concatenate([out, q[((L > lo) & (L < hi)).all(axis=1)]])
    return out[:n]


def pytest_terminal_summary(terminalreporter) -> None:
    """Figures the tests measure but do not assert: the panel's live-update latency in a real browser."""
    support = sys.modules.get("tests.browser_support")
    line = support.latency_report() if support is not None else None
    if line:
        terminalreporter.write_line(line)
