"""How the simulated controller applies its compensation block: raw stroke to reported length, and back.

This is the controller's own arithmetic, written from the block's definition in docs/protocols.md and
``hilcal.protocols.compensation`` (not from the calibration tool's models): the reported length of a leg is its
offset l0 plus the raw stroke plus the block's corrections, evaluated with the controller's own force and
temperature readings and the direction of the leg's last move. A setpoint is such a length: the servo drives the
raw stroke until the corrected length equals it, found here by fixed-point iteration (the corrections change by far
less than the stroke does), with a bracketing root search as the fallback.
"""

from __future__ import annotations

from typing import Any

import numpy as np

N_LEGS = 6
MAX_FIXED_POINT_STEPS = 60
STROKE_TOLERANCE_MM = 1e-9
BRACKET_MM = 1000.0


class LegCorrector:
    """The live compensation block as arrays, with the forward and inverse length arithmetic."""

    def __init__(self, block: dict[str, Any]) -> None:
        self.scale = np.asarray(block["scale_ppm"], dtype=float) * 1e-6
        self.backlash_mm = np.asarray(block["backlash_mm"], dtype=float)
        self.compliance = np.asarray(block["compliance_mm_per_kn"], dtype=float)
        self.compliance_per_m = np.asarray(block["compliance_mm_per_kn_m"], dtype=float)
        self.thermal = np.asarray(block["thermal_ppm_per_k"], dtype=float) * 1e-6
        self.t_ref_c = float(block["reference_temperature_c"])
        self.points = int(block["table_points"])
        self.start_mm = np.asarray(block["table_start_mm"], dtype=float)
        self.end_mm = np.asarray(block["table_end_mm"], dtype=float)
        self.table_mm = [np.asarray(row, dtype=float) for row in block["table_mm"]]
        self.grid_mm = [np.linspace(self.start_mm[leg], self.end_mm[leg], self.points) for leg in range(N_LEGS)]
        self.needs_force = bool(np.any(self.compliance != 0.0) or np.any(self.compliance_per_m != 0.0))
        """The block has compliance terms: it uses the controller's axial-force reading."""
        self.needs_temperature = bool(np.any(self.thermal != 0.0))
        """The block has a thermal coefficient: it uses the controller's leg-temperature reading."""
        scalars = (self.scale, self.backlash_mm, self.compliance, self.compliance_per_m, self.thermal)
        self.active = bool(any(np.any(v != 0.0) for v in scalars) or any(np.any(t != 0.0) for t in self.table_mm))
        """False for the all-zero block: lengths are then l0 + stroke exactly."""

    def _table(self, stroke_mm: np.ndarray) -> np.ndarray:
        if self.points == 0:
            return np.zeros(N_LEGS)
        return np.array([np.interp(stroke_mm[leg], self.grid_mm[leg], self.table_mm[leg]) for leg in range(N_LEGS)])

    def corrections_mm(self, stroke_mm: np.ndarray, l0_mm: np.ndarray, force_kn: np.ndarray,
                       direction: np.ndarray, temperature_c: float) -> np.ndarray:
        """What the block adds to l0 + stroke for each leg (mm)."""
        s = np.asarray(stroke_mm, dtype=float)
        out = self.scale * s + self._table(s) + np.asarray(direction, dtype=float) * self.backlash_mm / 2.0
        if self.needs_force:
            f = np.asarray(force_kn, dtype=float)
            out = out - self.compliance * f - self.compliance_per_m * f * s / 1000.0
        if self.needs_temperature:
            out = out + self.thermal * (l0_mm + s) * (temperature_c - self.t_ref_c)
        return out

    def length_mm(self, stroke_mm: np.ndarray, l0_mm: np.ndarray, force_kn: np.ndarray, direction: np.ndarray,
                  temperature_c: float) -> np.ndarray:
        """The reported (corrected) leg lengths for these raw strokes."""
        return l0_mm + stroke_mm + self.corrections_mm(stroke_mm, l0_mm, force_kn, direction, temperature_c)

    def stroke_for(self, length_mm: np.ndarray, l0_mm: np.ndarray, force_kn: np.ndarray, direction: np.ndarray,
                   temperature_c: float) -> np.ndarray:
        """The raw strokes whose corrected lengths are `length_mm` (the servo's target for a setpoint)."""
        target = np.asarray(length_mm, dtype=float) - l0_mm
        s = target.copy()
        for _ in range(MAX_FIXED_POINT_STEPS):
            new = target - self.corrections_mm(s, l0_mm, force_kn, direction, temperature_c)
            done = float(np.max(np.abs(new - s))) <= STROKE_TOLERANCE_MM
            s = new
            if done:
                return s
        from scipy.optimize import brentq  # a rare fallback: scipy stays out of the simulator's start-up

        for leg in range(N_LEGS):
            def residual(x: float, leg: int = leg) -> float:
                trial = s.copy()
                trial[leg] = x
                return float(self.length_mm(trial, l0_mm, force_kn, direction, temperature_c)[leg]
                             - length_mm[leg])

            s[leg] = brentq(residual, target[leg] - BRACKET_MM, target[leg] + BRACKET_MM, xtol=STROKE_TOLERANCE_MM)
        return s
