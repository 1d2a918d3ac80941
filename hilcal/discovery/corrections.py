"""One consistent compensation set a machine can load: the refitted geometry and, per leg, the correction of every
effect of the final model, relative to that geometry and over the recorded range only.

A term adds to one leg's reported length either `coefficient x variable` (library physics: a formula in one
documented per-leg variable) or a table of the correction against one variable (generic shapes: linear
interpolation on a grid fine enough for 0.1 µm, held at its end values outside the recorded range). Applying the
geometry and every term to the recorded legs reproduces the diagnosis' predictions. Variables, per leg i and row:
`stroke_mm` (reported length - l0), `axial_load_kN` (statics at the pose), `axial_load_kN*stroke_m`,
`direction` (+1 last moved out, -1 in, 0 unknown), `session` (0, 1, ...), `session_time_s`, `temp_c`,
`leg_mm*(temp_c-20)`, `last_move_mm_out` / `last_move_mm_in` (size of the last move, by direction), and for
joint-angle curvature the products of the two joint angles (rad) of `hilcal.discovery.context.joint_angles`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from hilcal.discovery.context import EffectContext
from hilcal.discovery.term_groups import GENERIC, TermGroup
from hilcal.error_models import GEOMETRIC_42
from hilcal.identification import IdentificationResult

N_GEO = 42
TABLE_TOLERANCE_MM = 1e-4
"""Linear interpolation between table points stays within 0.1 µm of the shape."""
MAX_TABLE_POINTS = 20001

VARIABLES: dict[str, Callable[[EffectContext, int], np.ndarray]] = {
    "stroke_mm": lambda c, i: c.stroke_mm[:, i],
    "axial_load_kN": lambda c, i: c.force_kn[:, i],
    "axial_load_kN*stroke_m": lambda c, i: c.force_kn[:, i] * c.stroke_mm[:, i] * 1e-3,
    "direction": lambda c, i: c.direction[:, i],
    "session": lambda c, i: c.session.astype(float),
    "session_time_s": lambda c, i: c.session_time_s,
    "temp_c": lambda c, i: np.zeros(c.n) if c.temp_c is None else c.temp_c,
    "leg_mm*(temp_c-20)": lambda c, i: c.legs_mm[:, i] * ((0.0 if c.temp_c is None else c.temp_c) - 20.0),
    "last_move_mm_out": lambda c, i: np.where(c.direction[:, i] > 0, np.nan_to_num(c.move_mm[:, i]), np.nan),
    "last_move_mm_in": lambda c, i: np.where(c.direction[:, i] < 0, np.nan_to_num(c.move_mm[:, i]), np.nan),
}
LIBRARY_VARIABLE = {
    "sensor_scale": ("stroke_mm", -1e-6), "leg_compliance": ("axial_load_kN", -1e-3),
    "oil_column_compliance": ("axial_load_kN*stroke_m", -1e-3), "drive_compliance": ("axial_load_kN*stroke_m", -1e-3),
    "joint_backlash": ("direction", 0.5), "thermal_expansion": ("leg_mm*(temp_c-20)", 1e-6),
}
"""Library effect -> (variable, mm of correction per unit of the variable per unit of the parameter)."""
GENERIC_VARIABLE = {"stroke": "stroke_mm", "stroke_cyclic": "stroke_mm", "axial_force": "axial_load_kN",
                    "time": "session_time_s", "time_lag": "session_time_s", "temperature": "temp_c"}


@dataclass(frozen=True)
class Term:
    """One leg's correction from one effect: coefficient x variable, or a table against the variable."""

    effect: str
    group: str
    leg: int
    """0-based."""
    variable: str
    coefficient_mm: float | None = None
    grid: np.ndarray | None = None
    correction_mm: np.ndarray | None = None
    recorded_range: tuple[float, float] = (0.0, 0.0)
    """The variable's range over the recorded rows; for joint-angle terms the joint's tilt from its home direction,
    sqrt(a1^2 + a2^2), in degrees."""
    angle_terms: tuple[tuple[str, float], ...] = ()
    """Joint-angle curvature: (product of angles, mm per rad^2) pairs."""
    amplitude_mm: float | None = None
    """Joint-angle terms: half the range of the correction over the recorded rows (a quadratic in two angles has
    no one-variable range to take it from)."""

    def value(self, ctx: EffectContext) -> np.ndarray:
        """The correction (mm) this term adds to its leg's reported length at every row of ctx."""
        if self.angle_terms:
            angles = ctx.base_angle_rad if self.variable == "base_joint_angle" else ctx.platform_angle_rad
            a1, a2 = angles[:, self.leg, 0], angles[:, self.leg, 1]
            products = {"a1*a1": a1 * a1, "a1*a2": a1 * a2, "a2*a2": a2 * a2}
            return sum(c * products[k] for k, c in self.angle_terms)
        x = VARIABLES[self.variable](ctx, self.leg)
        if self.coefficient_mm is not None:
            return self.coefficient_mm * x
        assert self.grid is not None and self.correction_mm is not None
        if self.variable == "session":
            return np.interp(x, self.grid, self.correction_mm)
        return np.where(np.isnan(x), 0.0, np.interp(np.nan_to_num(x), self.grid, self.correction_mm))

    @property
    def size_mm(self) -> float:
        """Half the range of the correction over the recorded range of its variable (the printed amplitude)."""
        if self.correction_mm is not None:
            return float(np.ptp(self.correction_mm) / 2.0)
        if self.coefficient_mm is not None:
            return float(abs(self.coefficient_mm) * (self.recorded_range[1] - self.recorded_range[0]) / 2.0)
        return 0.0 if self.amplitude_mm is None else float(self.amplitude_mm)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"effect": self.effect, "group": self.group, "leg": self.leg + 1,
                               "variable": self.variable, "recorded_range": list(self.recorded_range)}
        if self.coefficient_mm is not None:
            out["coefficient_mm_per_unit"] = self.coefficient_mm
        if self.grid is not None and self.correction_mm is not None:
            out["table"] = {"x": self.grid.tolist(), "correction_mm": self.correction_mm.tolist()}
        if self.angle_terms:
            out["angle_terms_mm_per_rad2"] = dict(self.angle_terms)
            out["recorded_range_unit"] = "deg of joint tilt"
            out["amplitude_mm"] = self.size_mm
        return out


@dataclass(frozen=True)
class CompensationSet:
    """The refitted geometry (mm, the 42 parameters) and every leg's correction terms relative to it."""

    geometry_mm: dict[str, float]
    terms: tuple[Term, ...]
    readings: dict[str, Any] | None = None
    """How the reported lengths come from the logged readings when the legs were re-ordered or mirrored (the
    diagnosis's wiring check), else None: the readings are the reported lengths."""

    def leg_corrections(self, ctx: EffectContext) -> np.ndarray:
        """[N, 6] mm to add to the reported leg lengths of the rows of ctx."""
        out = np.zeros((ctx.n, 6))
        for term in self.terms:
            out[:, term.leg] += term.value(ctx)
        return out

    def to_json(self) -> dict[str, Any]:
        rule = "geometric leg length = reported + sum of terms (mm), with the geometry above"
        if self.readings is not None:
            rule += "; reported = the logged readings as `readings` re-orders and mirrors them"
        out: dict[str, Any] = {"geometry_mm": self.geometry_mm, "terms": [t.to_json() for t in self.terms],
                               "rule": rule}
        if self.readings is not None:
            out["readings"] = self.readings
        return out


def _table(values: Callable[[np.ndarray], np.ndarray], lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """A grid over [lo, hi] on which linear interpolation reproduces values() to TABLE_TOLERANCE_MM."""
    n = 201
    while True:
        grid = np.linspace(lo, hi, n)
        y = values(grid)
        mid = 0.5 * (grid[1:] + grid[:-1])
        if n >= MAX_TABLE_POINTS or np.max(np.abs(values(mid) - 0.5 * (y[1:] + y[:-1])), initial=0.0) <= \
                TABLE_TOLERANCE_MM:
            return grid, y
        n = 2 * n - 1


def _generic_terms(g: TermGroup, theta: np.ndarray, ctx: EffectContext) -> list[Term]:
    legs = [g.leg] if g.leg is not None else list(range(6))
    out = []
    for leg in legs:
        th = theta[g.leg_columns(leg)]
        assert g.curve is not None
        if g.variable in ("base_joint_angle", "platform_joint_angle"):
            angles = ctx.base_angle_rad if g.variable.startswith("base") else ctx.platform_angle_rad
            scale = np.max(np.abs(angles), axis=(0, 2))[leg]
            tilt = np.degrees(np.linalg.norm(angles[:, leg, :], axis=1))
            products = tuple((k, float(c / scale**2)) for k, c in zip(("a1*a1", "a1*a2", "a2*a2"), th, strict=True))
            term = Term("unexplained", g.key, leg, g.variable,
                        recorded_range=(float(np.min(tilt)), float(np.max(tilt))), angle_terms=products)
            out.append(replace(term, amplitude_mm=float(np.ptp(term.value(ctx)) / 2.0)))
            continue
        if g.variable == "last_move":
            for name, d in (("last_move_mm_out", 1.0), ("last_move_mm_in", -1.0)):
                x = ctx.move_mm[ctx.direction[:, leg] == d, leg]
                if not x.size:
                    continue
                lo, hi = float(np.min(x)), float(np.max(x))

                def by_size(s: np.ndarray, d: float = d, leg: int = leg, th: np.ndarray = th) -> np.ndarray:
                    pts = np.stack([np.full_like(s, d), s], axis=-1)
                    return g.curve(pts, leg) @ th

                grid, y = _table(by_size, lo, hi) if hi > lo else (np.array([lo, lo + 1e-9]), by_size(np.array(
                    [lo, lo])))
                out.append(Term("unexplained", g.key, leg, name, grid=grid, correction_mm=y, recorded_range=(lo, hi)))
            continue
        variable = GENERIC_VARIABLE[g.variable]
        x = VARIABLES[variable](ctx, leg)
        lo, hi = float(np.min(x)), float(np.max(x))

        def shape(v: np.ndarray, leg: int = leg, th: np.ndarray = th) -> np.ndarray:
            return g.curve(v, leg) @ th

        grid, y = _table(shape, lo, hi)
        out.append(Term("unexplained", g.key, leg, variable, grid=grid, correction_mm=y, recorded_range=(lo, hi)))
    return out


def _library_terms(g: TermGroup, theta: np.ndarray, ctx: EffectContext) -> list[Term]:
    if g.effect in LIBRARY_VARIABLE:
        variable, per_unit = LIBRARY_VARIABLE[g.effect]
        out = []
        for k, _name in enumerate(g.names):
            legs = range(6) if len(g.names) == 1 else [k]
            for leg in legs:
                x = VARIABLES[variable](ctx, leg)
                out.append(Term(g.effect, g.key, leg, variable, coefficient_mm=float(per_unit * theta[k]),
                                recorded_range=(float(np.min(x)), float(np.max(x)))))
        return out
    sessions = np.unique(ctx.session)
    out = []
    for leg in range(6):
        shifts = np.zeros(sessions.size)
        for name, value in zip(g.names, theta, strict=True):
            m = re.match(r"leg(\d)_zero_shift_session(\d+)_mm", name)
            if m and int(m.group(1)) == leg + 1 and int(m.group(2)) - 1 in sessions:
                shifts[np.searchsorted(sessions, int(m.group(2)) - 1)] = value
        out.append(Term(g.effect, g.key, leg, "session", grid=sessions.astype(float), correction_mm=shifts,
                        recorded_range=(float(sessions[0]), float(sessions[-1]))))
    return out


def compensation_set(ctx: EffectContext, final: IdentificationResult,
                     groups: list[TermGroup]) -> CompensationSet:
    """The final model as a loadable set: geometry plus one term per leg and effect; tables span the variables'
    range over every recorded row of `ctx` (measure and verify), where the model and the set agree."""
    geometry = {n: float(v) for n, v in zip(GEOMETRIC_42.names, final.x[:N_GEO], strict=True)}
    terms: list[Term] = []
    k = N_GEO
    for g in groups:
        theta = final.x[k:k + g.n_params]
        k += g.n_params
        terms += _generic_terms(g, theta, ctx) if g.kind == GENERIC else _library_terms(g, theta, ctx)
    return CompensationSet(geometry, tuple(terms))
