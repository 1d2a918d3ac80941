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

from hilcal.discovery.context import EffectContext

LIBRARY = "library"
GENERIC = "generic"


@dataclass(frozen=True)
class PhysicalRange:
    """The physically possible values of a library effect's parameters, and why."""

    low: np.ndarray
    high: np.ndarray
    why: str

    def violations(self, values: np.ndarray, std_errors: np.ndarray, z: float) -> list[int]:
        """Indices of parameters outside the range by more than z standard errors (clear evidence)."""
        se = np.where(np.isfinite(std_errors), std_errors, 0.0)
        below = values < self.low - z * se
        above = values > self.high + z * se
        return [int(i) for i in np.flatnonzero(below | above)]


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

    @property
    def n_params(self) -> int:
        return len(self.names)

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
