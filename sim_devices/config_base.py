"""Building blocks shared by the rig's configuration modules: strict pydantic base, switchable effects, per-leg values.

Kept apart so the library effects (sim_devices.rig.config) and the out-of-library effects
(sim_devices.rig.unlisted_config) validate their fields the same way without importing each other.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

PerLeg = float | Annotated[list[float], Field(min_length=6, max_length=6)]
"""One value for all six legs, or a list of six."""


class Strict(BaseModel):
    """Frozen, no unknown keys, no inf/NaN: a typo in a rig file is an error, not a silent default."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Effect(Strict):
    """A switchable effect: off unless enabled."""

    enabled: bool = False


def per_leg(value: float | list[float]) -> np.ndarray:
    """(6,) array from a scalar (same for all legs) or a list of six values."""
    return np.broadcast_to(np.asarray(value, dtype=float), (6,)).copy()


def check_non_negative(value: float | list[float]) -> float | list[float]:
    """Field validator body: every per-leg value >= 0."""
    if np.any(per_leg(value) < 0):
        raise ValueError(f"must be >= 0, got {value}")
    return value


def check_positive(value: float | list[float]) -> float | list[float]:
    """Field validator body: every per-leg value > 0."""
    if np.any(per_leg(value) <= 0):
        raise ValueError(f"must be > 0, got {value}")
    return value
