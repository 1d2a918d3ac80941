"""Configuration of the rig's generic per-leg effect: corrections given as tables, for a rig that learns a machine.

A digital twin of a measured machine (``hilcal diagnose --report`` writes one) holds shapes that no physics formula
of the rig describes: a cyclic error over the stroke, a drift in time, a curvature in a joint's angles. Each is a
correction Δl_i (mm) to the true joint-centre distance of one leg, either a table against one variable the rig knows
(linear interpolation, held at the end values outside the table) or a quadratic in the two angles of one of the leg's
joints. The formulas live in sim_devices.rig.table_physics; the rig evaluates the variables itself, from its own
geometry, statics, clock and motion history.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from sim_devices.config_base import Effect, Strict

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]

TableVariable = Literal["stroke_mm", "axial_load_kN", "axial_load_kN*stroke_m", "direction", "session_time_s",
                        "temp_c", "session", "last_move_mm_out", "last_move_mm_in"]
"""What a table's x may be, per leg: the reported stroke (reported length - l0, mm), the axial compression (kN, from
the rig's statics at the true pose), their product (kN m), the direction of the leg's last move (+1 out, -1 in), the
time since the session (power-on) started (s), the leg temperature (°C), the session number (0 from the rig's
creation, +1 at every power-on), and the size (mm) of the leg's last move when it was outwards (or inwards); a
last-move table adds nothing while the leg last moved the other way."""


class LegTable(Strict):
    """One leg's correction against one variable: Δl = interp(variable, x, correction_mm), held at the ends."""

    leg: int = Field(ge=1, le=6, description="leg, 1-6")
    variable: TableVariable
    x: list[float] = Field(min_length=1, description="table points of the variable, increasing")
    correction_mm: list[float] = Field(min_length=1, description="correction at each point, mm")

    @model_validator(mode="after")
    def _increasing(self) -> LegTable:
        if len(self.x) != len(self.correction_mm):
            raise ValueError(f"x has {len(self.x)} points but correction_mm {len(self.correction_mm)}")
        if np.any(np.diff(self.x) <= 0):
            raise ValueError("x must be strictly increasing")
        return self


class JointCurvature(Strict):
    """One leg's correction quadratic in the angles of one of its joints: Δl = c11 a1² + c12 a1 a2 + c22 a2².

    a_k = u · axis_k, with u the unit leg direction from base joint to platform joint, in the base frame for the base
    joint and in the platform frame for the platform joint (what a universal joint turns through, as small angles
    from a reference direction the axes are perpendicular to)."""

    leg: int = Field(ge=1, le=6, description="leg, 1-6")
    joint: Literal["base", "platform"]
    axis1: Vec3
    axis2: Vec3
    mm_per_rad2: Annotated[list[float], Field(min_length=3, max_length=3)] = Field(
        description="c11, c12, c22: mm per rad² of a1², a1 a2, a2²")


class LegTablesConfig(Effect):
    """Per-leg corrections as tables and joint curvatures (all added): what a twin learned that no formula holds."""

    tables: list[LegTable] = Field(default_factory=list)
    curvatures: list[JointCurvature] = Field(default_factory=list)
