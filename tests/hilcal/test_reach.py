"""Which verification poses a corrected machine can still reach: the controller applies the block to a setpoint and
drives the raw stroke, and the leg limits apply to that raw stroke (docs/protocols.md). Expected strokes are worked
out here from the block's formula by hand (length = l0 + s (1 + scale))."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hilcal.compensation import ControllerGeometry, out_of_reach
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.leg_compensation import LegCompensation
from hilcal.robot import load_robot

SMALL = load_robot(Path(__file__).resolve().parents[2] / "examples" / "hexapod_small.toml")


def _nominal() -> ControllerGeometry:
    return ControllerGeometry(SMALL.a.copy(), SMALL.b.copy(), SMALL.l0.copy())


def _pose_with_a_leg_at(stroke_mm: float) -> tuple[np.ndarray, int]:
    """A pose (z raised from home) whose longest leg has this nominal stroke, and that leg."""
    geom = Geometry.nominal(SMALL)
    lo, hi = SMALL.home[2] - 30.0, SMALL.home[2] + 60.0
    for _ in range(80):
        z = 0.5 * (lo + hi)
        pose = SMALL.home.copy()
        pose[2] = z
        longest = (inverse_kinematics(geom, pose[None])[0] - SMALL.l0).max()
        lo, hi = (z, hi) if longest < stroke_mm else (lo, z)
    strokes = inverse_kinematics(geom, pose[None])[0] - SMALL.l0
    return pose, int(np.argmax(strokes))


def test_a_scale_correction_takes_a_pose_near_the_top_of_the_stroke_out_of_reach():
    top = SMALL.leg_limits[1] - SMALL.l0[0]  # 40 mm of raw stroke
    pose, _ = _pose_with_a_leg_at(top - 0.05)
    assert out_of_reach(SMALL, _nominal(), None, pose[None]) == []
    scale = np.full(6, -2000.0)  # every leg reads 0.2 % long: the controller drives 0.2 % more raw stroke
    found = out_of_reach(SMALL, _nominal(), LegCompensation(scale_ppm=scale), np.vstack([SMALL.home, pose]))
    assert [f.index for f in found] == [1]
    lengths = inverse_kinematics(Geometry.nominal(SMALL), pose[None])[0]
    raw = (lengths - SMALL.l0) / (1.0 - 2000e-6)
    assert found[0].leg == int(np.argmax(raw)) and abs(found[0].stroke_mm - raw.max()) < 1e-6
    assert found[0].stroke_mm > found[0].max_mm == top
    assert "beyond leg" in found[0].sentence("verify pose") and "above its 40.000 mm" in found[0].sentence("pose")


def test_a_shorter_leg_offset_needs_more_stroke_without_a_block():
    top = SMALL.leg_limits[1] - SMALL.l0[0]
    pose, leg = _pose_with_a_leg_at(top - 0.05)
    shifted = _nominal()
    shifted.l0[leg] -= 0.1  # the controller's l0 of that leg 0.1 mm shorter: 0.1 mm more raw stroke
    found = out_of_reach(SMALL, shifted, None, pose[None])
    assert [(f.index, f.leg) for f in found] == [(0, leg)] and abs(found[0].stroke_mm - (top + 0.05)) < 1e-6


def test_the_approach_from_below_must_fit_above_the_bottom_of_the_stroke():
    pose, _ = _pose_with_a_leg_at(10.0)
    lowest = (inverse_kinematics(Geometry.nominal(SMALL), pose[None])[0] - SMALL.l0).min()
    assert out_of_reach(SMALL, _nominal(), None, pose[None], approach_mm=lowest - 0.01) == []
    assert [f.index for f in out_of_reach(SMALL, _nominal(), None, pose[None], approach_mm=lowest + 0.01)] == [0]
