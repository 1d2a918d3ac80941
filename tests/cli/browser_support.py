"""Headless Chromium for the panel's browser tests (Debian's chromium + chromium-driver, driven by selenium).

Under CI (CI=true) a missing browser fails the test: `.ci/run` installs it. On a developer machine the tests
skip with the command that installs it. Each browser gets a fresh profile folder and no network features,
and runs at idle CPU priority (SCHED_IDLE; Chromium resets plain nice values): on a 2-core machine it must
not starve the run under test, whose controller link treats 100 ms without a heartbeat as a lost controller.
"""

from __future__ import annotations

import os
import shutil
import socket
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

INSTALL = "apt-get install -y chromium chromium-driver"
LATENCIES_S: list[float] = []
"""Event-to-page delays measured by the browser tests in this session (printed by tests/conftest.py)."""
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-dev-shm-usage",
                  "--disable-extensions", "--mute-audio",
                  "--disable-features=Translate,MediaRouter,OptimizationHints,BackForwardCache,PaintHolding",
                  "--window-size=1400,1800")
"""A headless browser with nothing running beside the page (no extensions, translation, media routing or
optimization hints), so that its CPU goes to the page under test."""


def chromium_paths() -> tuple[str, str] | None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    return (browser, driver) if browser and driver else None


def require_chromium() -> tuple[str, str]:
    found = chromium_paths()
    if found is not None:
        return found
    message = f"headless Chromium and chromedriver not found; install them with `sudo {INSTALL}`"
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"CI must run the browser tests: {message} (.ci/run does this)")
    pytest.skip(message)


@contextmanager
def chromium() -> Iterator[Any]:
    """A headless Chromium driven by selenium, with its own fresh profile; quit and cleaned up on exit."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    browser, driver_path = require_chromium()
    profile = tempfile.mkdtemp(prefix="hilcal-chromium-")
    niced = Path(profile) / "chromedriver-idle"
    niced.write_text(f'#!/bin/sh\nexec chrt --idle 0 "{driver_path}" "$@"\n')
    niced.chmod(0o755)
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(executable_path=str(niced)))
    driver.set_page_load_timeout(30)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(condition: Callable[[], Any], timeout_s: float, what: str, poll_s: float = 0.1) -> Any:
    """Poll until condition() is truthy (returns it); AssertionError naming `what` after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            value = condition()
        except Exception:  # the element may be re-rendered between lookups
            value = None
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(poll_s)


def text(driver: Any, element_id: str) -> str:
    return driver.find_element("id", element_id).text


def latency_summary(values_s: list[float]) -> dict[str, float]:
    """Count, median, 95th percentile and maximum of the event-to-page delays (ms)."""
    ordered = sorted(values_s)
    if not ordered:
        return {"n": 0}

    def pct(q: float) -> float:
        return 1000.0 * ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]

    return {"n": len(ordered), "median_ms": pct(0.5), "p95_ms": pct(0.95), "max_ms": 1000.0 * ordered[-1],
            "within_500ms_fraction": sum(v <= 0.5 for v in ordered) / len(ordered)}


def latency_report() -> str | None:
    """One line for the test session's summary, or None if no browser test measured anything."""
    if not LATENCIES_S:
        return None
    summary = latency_summary(LATENCIES_S)
    return (f"panel live updates, server event to browser DOM (headless Chromium): n {summary['n']}, "
            f"median {summary['median_ms']:.1f} ms, p95 {summary['p95_ms']:.1f} ms, max {summary['max_ms']:.1f} ms, "
            f"{100 * summary['within_500ms_fraction']:.1f} % within 500 ms")
