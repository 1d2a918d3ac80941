"""A controller's per-leg length compensation, as the calibration math sees it: what it adds to each leg's length.

The same terms as the controller's compensation block (docs/protocols.md): per leg a reading scale, backlash by the
direction of the last move, a compliance against the axial force and one that grows with the stroke, a thermal
coefficient against the leg temperature, and a table over the stroke (equally spaced points, linear interpolation,
held at the ends). ``corrections_mm`` evaluates them on recorded or planned rows; the identified model's predictions
and the block a controller holds are compared through it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

N_LEGS = 6
REFERENCE_TEMPERATURE_C = 20.0
SCALAR_FIELDS = ("scale_ppm", "backlash_mm", "compliance_mm_per_kn", "compliance_mm_per_kn_m", "thermal_ppm_per_k")


def _zeros() -> np.ndarray:
    return np.zeros(N_LEGS)


@dataclass(frozen=True)
class LegCompensation:
    """Per-leg compensation terms (arrays of 6; the table [6, n] over [table_start_mm, table_end_mm] of stroke)."""

    scale_ppm: np.ndarray = field(default_factory=_zeros)
    backlash_mm: np.ndarray = field(default_factory=_zeros)
    compliance_mm_per_kn: np.ndarray = field(default_factory=_zeros)
    compliance_mm_per_kn_m: np.ndarray = field(default_factory=_zeros)
    thermal_ppm_per_k: np.ndarray = field(default_factory=_zeros)
    table_start_mm: np.ndarray = field(default_factory=_zeros)
    table_end_mm: np.ndarray = field(default_factory=_zeros)
    table_mm: np.ndarray = field(default_factory=lambda: np.zeros((N_LEGS, 0)))
    reference_temperature_c: float = REFERENCE_TEMPERATURE_C

    @property
    def table_points(self) -> int:
        return int(self.table_mm.shape[1])

    @property
    def is_zero(self) -> bool:
        return not any(np.any(getattr(self, name) != 0.0) for name in SCALAR_FIELDS) and not np.any(self.table_mm)

    @property
    def needs_force(self) -> bool:
        return bool(np.any(self.compliance_mm_per_kn != 0.0) or np.any(self.compliance_mm_per_kn_m != 0.0))

    @property
    def needs_temperature(self) -> bool:
        return bool(np.any(self.thermal_ppm_per_k != 0.0))

    def table_at(self, stroke_mm: np.ndarray) -> np.ndarray:
        """The table's correction [N, 6] at raw strokes [N, 6]."""
        s = np.atleast_2d(np.asarray(stroke_mm, dtype=float))
        if self.table_points == 0:
            return np.zeros_like(s)
        out = np.empty_like(s)
        for leg in range(N_LEGS):
            grid = np.linspace(self.table_start_mm[leg], self.table_end_mm[leg], self.table_points)
            out[:, leg] = np.interp(s[:, leg], grid, self.table_mm[leg])
        return out

    def corrections_mm(self, stroke_mm: np.ndarray, l0_mm: np.ndarray, force_kn: np.ndarray | None = None,
                       direction: np.ndarray | None = None, temp_c: np.ndarray | None = None) -> np.ndarray:
        """What the compensation adds to l0 + stroke, [N, 6] mm, at raw strokes [N, 6] (the leg offsets l0 (6,),
        axial compressions [N, 6] kN, last-move directions [N, 6] of +1/-1/0 and leg temperatures [N] °C;
        a missing variable contributes nothing)."""
        s = np.atleast_2d(np.asarray(stroke_mm, dtype=float))
        out = self.scale_ppm * 1e-6 * s + self.table_at(s)
        if direction is not None:
            out = out + np.asarray(direction, dtype=float) * self.backlash_mm / 2.0
        if force_kn is not None:
            f = np.asarray(force_kn, dtype=float)
            out = out - self.compliance_mm_per_kn * f - self.compliance_mm_per_kn_m * f * s / 1000.0
        if temp_c is not None:
            dt = np.asarray(temp_c, dtype=float)[:, None] - self.reference_temperature_c
            out = out + self.thermal_ppm_per_k * 1e-6 * (l0_mm + s) * dt
        return out

    def raw_strokes_mm(self, lengths_mm: np.ndarray, l0_mm: np.ndarray, direction: np.ndarray | None = None,
                       iterations: int = 50) -> np.ndarray:
        """The raw strokes [N, 6] at which the corrected length l0 + s + corrections equals `lengths_mm` [N, 6]: what
        the servo drives to for these setpoints (fixed-point iteration; the scale and table are small slopes).
        The force and thermal terms are left out: they need the readings at the reached pose."""
        L = np.atleast_2d(np.asarray(lengths_mm, dtype=float))
        s = L - l0_mm
        for _ in range(iterations):
            new = L - l0_mm - self.corrections_mm(s, l0_mm, direction=direction)
            if float(np.max(np.abs(new - s), initial=0.0)) < 1e-9:
                return new
            s = new
        return s

    def resampled(self, start_mm: np.ndarray, end_mm: np.ndarray, points: int) -> LegCompensation:
        """The same corrections with the table on `points` equally spaced points over [start, end] per leg (the
        present table is evaluated there, held at its ends)."""
        start, end = np.asarray(start_mm, dtype=float), np.asarray(end_mm, dtype=float)
        grids = np.linspace(start, end, points)
        return replace(self, table_start_mm=start, table_end_mm=end, table_mm=self.table_at(grids).T.copy())

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {name: getattr(self, name).tolist() for name in SCALAR_FIELDS}
        out.update(table_points=self.table_points, table_start_mm=self.table_start_mm.tolist(),
                   table_end_mm=self.table_end_mm.tolist(), table_mm=self.table_mm.tolist(),
                   reference_temperature_c=self.reference_temperature_c)
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> LegCompensation:
        """From ``to_json`` (or a controller block's fields)."""
        table = np.asarray(data.get("table_mm") or [[] for _ in range(N_LEGS)], dtype=float).reshape(N_LEGS, -1)
        return cls(**{name: np.asarray(data[name], dtype=float) for name in SCALAR_FIELDS},
                   table_start_mm=np.asarray(data.get("table_start_mm", _zeros()), dtype=float),
                   table_end_mm=np.asarray(data.get("table_end_mm", _zeros()), dtype=float), table_mm=table,
                   reference_temperature_c=float(data.get("reference_temperature_c", REFERENCE_TEMPERATURE_C)))
