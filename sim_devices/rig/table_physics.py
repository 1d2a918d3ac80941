"""The rig's generic per-leg effect: corrections from tables and joint curvatures (sim_devices.rig.table_config).

Written for the simulator, apart from the calibration tool's models: every variable is the rig's own (its reported
lengths, its statics at the true pose, its clock, its true leg temperature, its motion history and its true joints).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_devices.rig.table_config import LegTablesConfig


@dataclass(frozen=True)
class TableState:
    """What the tables are read against at one instant (per leg where an array)."""

    stroke_mm: np.ndarray
    """(6,) reported stroke: reported length - l0."""
    forces_kn: np.ndarray
    """(6,) axial compression at the true pose."""
    session_time_s: float
    temperature_c: float
    session: int
    direction: np.ndarray
    """(6,) direction of each leg's last move, +1 out, -1 in."""
    last_move_mm: np.ndarray
    """(6,) size of each leg's last move."""
    base_directions: np.ndarray
    """(6, 3) unit leg directions (base joint to platform joint) in the base frame."""
    platform_directions: np.ndarray
    """(6, 3) the same in the platform frame."""


def _variable(name: str, state: TableState, leg: int) -> float | None:
    """The value of a table's variable for one leg (None: the table does not apply now)."""
    if name == "stroke_mm":
        return float(state.stroke_mm[leg])
    if name == "axial_load_kN":
        return float(state.forces_kn[leg])
    if name == "axial_load_kN*stroke_m":
        return float(state.forces_kn[leg] * state.stroke_mm[leg] / 1000.0)
    if name == "direction":
        return float(state.direction[leg])
    if name == "session_time_s":
        return state.session_time_s
    if name == "temp_c":
        return state.temperature_c
    if name == "session":
        return float(state.session)
    wanted = 1.0 if name == "last_move_mm_out" else -1.0
    if state.direction[leg] != wanted or not np.isfinite(state.last_move_mm[leg]):
        return None
    return float(state.last_move_mm[leg])


def table_corrections_mm(config: LegTablesConfig, state: TableState) -> np.ndarray:
    """Δl (mm, (6,)) of every table and joint curvature, summed per leg."""
    out = np.zeros(6)
    for table in config.tables:
        i = table.leg - 1
        x = _variable(table.variable, state, i)
        if x is not None:
            out[i] += float(np.interp(x, table.x, table.correction_mm))
    for curve in config.curvatures:
        i = curve.leg - 1
        u = (state.base_directions if curve.joint == "base" else state.platform_directions)[i]
        a1, a2 = float(u @ np.asarray(curve.axis1)), float(u @ np.asarray(curve.axis2))
        c11, c12, c22 = curve.mm_per_rad2
        out[i] += c11 * a1 * a1 + c12 * a1 * a2 + c22 * a2 * a2
    return out
