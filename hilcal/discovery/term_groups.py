"""A group of leg-length terms that the diagnosis can add to the geometric model, library physics or generic.

Every group corrects the geometric length of the legs linearly in its parameters:
    geometric length = reported length + dl0 + phi(row) @ theta,   phi: [N, 6, q] from an EffectContext.
A group is bound to the rows it was fitted on (spline knots, sessions), so `phi` gives the same basis on
any other rows, e.g. the held-out verify rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from hilcal.discovery.context import EffectContext

LIBRARY = "library"
GENERIC = "generic"


TYPICAL = "typical"
FAULT = "fault"
IMPOSSIBLE = "impossible"
PRIOR_FAULT_WEIGHT = 0.1
"""Prior share of a set-up fault (abnormal but possible value) against a typical value, per parameter: machines
come to calibration because something is off, so a fault is not rare."""


@dataclass(frozen=True)
class PhysicalRange:
    """Graded values of a library effect's parameters: typical (physics), abnormal but possible (a fault of the
    set-up, with what to check) and impossible (outside ``low``-``high``: never named). Each bound says why."""

    low: np.ndarray
    high: np.ndarray
    why: str
    typical_low: np.ndarray | None = None
    typical_high: np.ndarray | None = None
    typical_why: str = ""
    fault_check: str = ""
    """What a value outside the typical range means and what to check on the machine."""

    def violations(self, values: np.ndarray, std_errors: np.ndarray, z: float) -> list[int]:
        """Indices of parameters outside the possible range by more than z standard errors (clear evidence)."""
        se = np.where(np.isfinite(std_errors), std_errors, 0.0)
        below = values < self.low - z * se
        above = values > self.high + z * se
        return [int(i) for i in np.flatnonzero(below | above)]

    def typical_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if self.typical_low is None or self.typical_high is None:
            return self.low, self.high
        return self.typical_low, self.typical_high

    def grades(self, values: np.ndarray, std_errors: np.ndarray, z: float) -> list[str]:
        """Per parameter: impossible (outside the possible range by > z SE), fault (outside the typical range by
        > z SE) or typical."""
        se = np.where(np.isfinite(std_errors), std_errors, 0.0)
        lo, hi = self.typical_bounds()
        out = []
        for k, v in enumerate(values):
            if v < self.low[k] - z * se[k] or v > self.high[k] + z * se[k]:
                out.append(IMPOSSIBLE)
            elif v < lo[k] - z * se[k] or v > hi[k] + z * se[k]:
                out.append(FAULT)
            else:
                out.append(TYPICAL)
        return out

    def log_prior(self, values: np.ndarray, std_errors: np.ndarray) -> float:
        """log of the prior density averaged over each parameter's posterior N(value, se^2): flat within the
        typical range (weight 1 - PRIOR_FAULT_WEIGHT) and within the possible range (PRIOR_FAULT_WEIGHT), zero
        outside (a Laplace approximation of the evidence uses this)."""
        se = np.maximum(np.where(np.isfinite(std_errors), std_errors, 0.0), 1e-12 * (1.0 + np.abs(values)))
        lo, hi = self.typical_bounds()

        def mass(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return np.clip(ndtr((b - values) / se) - ndtr((a - values) / se), 0.0, 1.0)

        w_typ = 1.0 - PRIOR_FAULT_WEIGHT if self.typical_low is not None else 1.0
        density = w_typ * mass(lo, hi) / np.maximum(hi - lo, 1e-300)
        if self.typical_low is not None:
            density = density + PRIOR_FAULT_WEIGHT * mass(self.low, self.high) / np.maximum(self.high - self.low,
                                                                                             1e-300)
        return float(np.sum(np.log(np.maximum(density, 1e-300))))


@dataclass(frozen=True)
class TermGroup:
    """One candidate group of terms: a library effect, or a generic shape of one leg in one variable."""

    key: str
    kind: str
    effect: str
    title: str
    names: tuple[str, ...]
    phi: Callable[[EffectContext], np.ndarray]
    leg: int | None = None
    variable: str | None = None
    setting: str = ""
    physical_range: PhysicalRange | None = None
    sentence: str = ""
    curve: Callable[[np.ndarray, int], np.ndarray] | None = None
    """Generic groups: one leg's basis as a function of the variable's values (for shape plots and tables)."""
    curve_range: tuple[float, float] | None = None
    unit: str = ""
    period_mm: float | None = None
    angle_scale_rad: float | None = None
    history: bool = False
    """The terms depend on the motion history (the direction of the last move): unknown at a session's first row."""

    @property
    def n_params(self) -> int:
        return len(self.names)

    def unknown_rows(self, ctx: EffectContext) -> np.ndarray:
        """[N, 6] where this group's terms cannot be evaluated on a leg: its history is unknown there."""
        legs = np.zeros((ctx.n, 6), dtype=bool)
        if self.history:
            legs = ctx.unknown_history()
            if self.leg is not None:
                legs = legs & (np.arange(6) == self.leg)[None, :]
        return legs

    def leg_columns(self, leg: int) -> np.ndarray:
        """Columns of the regressor (and parameters) that act on one leg."""
        if self.leg is not None:
            return np.arange(self.n_params)
        q = self.n_params // 6
        return np.arange(leg * q, (leg + 1) * q)


def per_leg_diagonal(values: np.ndarray) -> np.ndarray:
    """[N, 6] leg-wise regressor -> [N, 6, 6] with one parameter per leg."""
    out = np.zeros((*values.shape, 6))
    for i in range(6):
        out[:, i, i] = values[:, i]
    return out


def stack_phi(groups: list[TermGroup], ctx: EffectContext) -> np.ndarray:
    """The regressors of several groups side by side: [N, 6, sum q]."""
    if not groups:
        return np.zeros((ctx.n, 6, 0))
    return np.concatenate([g.phi(ctx) for g in groups], axis=2)
