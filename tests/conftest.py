"""Shared fixtures: the default robot, a seeded generator, and a throw-away PostgreSQL server (``postgres``,
``pg_url``) for the records tests."""

from __future__ import annotations

import gc
import signal
import sys

import numpy as np
import pytest
import structlog

from hilcal.robot import Robot, default_robot
from tests.postgres_server import pg_url, postgres  # noqa: F401  (fixtures)


def pytest_configure(config) -> None:
    """Ctrl-C must reach Python: a shell's background job (`make test &`, some CI runners) starts with SIGINT
    ignored, and Python then installs no KeyboardInterrupt handler, so the pause and abort tests would see no
    Ctrl-C. Restored in every process (xdist workers included) before any test runs; children inherit it."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_collection_finish(session) -> None:
    """What collection imported and built lives as long as the session: moved out of the garbage collector's sight
    (gc.freeze), a full collection in a worker no longer walks it again."""
    gc.freeze()


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


def pytest_sessionfinish(session) -> None:
    """Under pytest-xdist a worker hands its browser latencies to the controller, which prints the summary."""
    support = sys.modules.get("tests.cli.browser_support")
    if hasattr(session.config, "workeroutput") and support is not None:
        session.config.workeroutput["panel_latencies_s"] = list(support.LATENCIES_S)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error) -> None:
    """The controller of an xdist run collects what a finished worker measured (pytest-xdist's hook)."""
    latencies = getattr(node, "workeroutput", {}).get("panel_latencies_s")
    if latencies:
        from tests.cli import browser_support

        browser_support.LATENCIES_S.extend(latencies)


def pytest_terminal_summary(terminalreporter) -> None:
    """Figures the tests measure but do not assert: the panel's live-update latency in a real browser."""
    support = sys.modules.get("tests.cli.browser_support")
    line = support.latency_report() if support is not None else None
    if line:
        terminalreporter.write_line(line)
