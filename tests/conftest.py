"""Shared fixtures: the default robot and a seeded generator."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import structlog

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


def pytest_terminal_summary(terminalreporter) -> None:
    """Figures the tests measure but do not assert: the panel's live-update latency in a real browser."""
    support = sys.modules.get("tests.cli.browser_support")
    line = support.latency_report() if support is not None else None
    if line:
        terminalreporter.write_line(line)
