"""The worked examples of examples/import and their exporters (examples/ is not a package: loaded by path)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np

from hilcal.recording import Recording, session_numbers

EXAMPLES = Path(__file__).resolve().parents[3] / "examples" / "import"
CASES = {
    "logger": (("day1.csv", "day2.csv"), "file:day2.csv", "robot.toml"),
    "tracker": (("tracker_export.csv",), "every:3", None),
    "paper": (("docking_sim_log.csv",), None, None),
}
"""Per example: its files, its --hold-out and its robot file (None: the built-in paper robot), as docs/import.md."""


def load_example_module(name: str) -> ModuleType:
    """A script of examples/import (``exporters`` or ``make_examples``) as a module."""
    key = f"hilcal_example_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, EXAMPLES / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]


def assert_same_recording(got: Recording, want: Recording, tol_mm: float, tol_deg: float) -> None:
    """Same rows, phases and sessions; lengths within tol_mm, angles within tol_deg, session times within 1 µs."""
    assert got.n == want.n
    assert np.array_equal(got.phase, want.phase)
    np.testing.assert_allclose(got.legs_mm, want.legs_mm, rtol=0, atol=tol_mm)
    for name in ("meas", "cmd"):
        a, b = getattr(got, name), getattr(want, name)
        assert np.array_equal(np.isnan(a), np.isnan(b)), name
        np.testing.assert_allclose(a[:, :3], b[:, :3], rtol=0, atol=tol_mm, err_msg=name)
        np.testing.assert_allclose(a[:, 3:], b[:, 3:], rtol=0, atol=tol_deg, err_msg=name)
    sessions = session_numbers(want.time_s)
    assert np.array_equal(session_numbers(got.time_s), sessions)
    for s in np.unique(sessions):
        rows = sessions == s
        since = [r.time_s[rows] - r.time_s[rows][0] for r in (got, want)]
        np.testing.assert_allclose(since[0], since[1], rtol=0, atol=1e-6)
    for name in ("temp_c", "sphere_fit_rms_mm"):
        assert (name in got.extra) == (name in want.extra), name
        if name in want.extra:
            np.testing.assert_allclose(got.extra[name], want.extra[name], rtol=0, atol=tol_mm, err_msg=name)
