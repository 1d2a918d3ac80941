"""The digital twin of a diagnosed recording (`hilcal diagnose --report DIR`): a simulator configuration holding what
the diagnosis learned about the machine, and the recording replayed on it pose by pose.

`sim_config.toml` (with `twin_errors.toml`, and a copy of the robot file when one was given) is read by
`hilcal sim --config`, `hilcal run --sim --sim-config` and `hilcal simulate --sim-config`. It holds the robot; the
geometric errors; every named effect with its values, in the rig's own parameters (`_library`); the unexplained
shapes and the zero shifts between sessions as per-leg tables and joint curvatures (the rig's `leg_tables`); the
recorded temperature history; the noise. The values are the diagnosis' model (its groups, the steps the held-out poses
do not confirm included) refitted on every row it can use (`learn`): the diagnosis keeps the verify rows out to judge
its choice, a twin learns from every measurement. The replay is therefore an in-sample comparison: it shows that the
twin holds what the recording shows; the held-out evidence is the diagnosis' own.

This module composes the two sides (it may import both): the diagnosis (`hilcal.discovery`) and the simulator's
configuration and rig (`sim_devices`), whose physics is written apart from the models `hilcal` fits.
"""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from hilcal.discovery.context import EffectContext, joint_axes
from hilcal.discovery.corrections import compensation_set
from hilcal.discovery.fitting import Problem, final_fit, fit_model, leg_residuals, shape_scales
from hilcal.discovery.noise import sphere_noise_covariance
from hilcal.discovery.physics import ZERO_SHIFT, RobotScales, zero_shift_group
from hilcal.discovery.result import Diagnosis
from hilcal.recording import Recording
from hilcal.reports.diagnosis_twin import TwinComparison
from hilcal.robot import Robot
from sim_devices.rig.config import GeometryErrors, RigConfig, errors_toml
from sim_devices.rig.replay import replay_poses
from sim_devices.sim_config import load_sim_config, sim_config_toml

CONFIG_FILE = "sim_config.toml"
ERRORS_FILE = "twin_errors.toml"
ROBOT_FILE = "robot.toml"
WIDE = 1e6
"""A linear term written as a two-point table spans ±WIDE in its variable (interpolation is exact inside)."""
PER_LEG = {"leg_compliance": "um_per_kN", "sensor_scale": "ppm", "joint_backlash": "mm",
           "oil_column_compliance": "um_per_kN_m", "drive_compliance": "um_per_kN_m"}


@dataclass(frozen=True)
class Twin:
    """The twin's simulator configuration (as written), its rig and the geometry-only rig, and what it leaves out."""

    config: dict[str, Any]
    rig: RigConfig
    geometry_rig: RigConfig
    notes: tuple[str, ...]
    fitted: np.ndarray
    """[N] the recording's rows the twin learned from."""


@dataclass(frozen=True)
class Learned:
    """What the twin holds: the diagnosis' groups refitted on every row it can use (measure and verify rows alike,
    outliers and rows of unknown history left out; the session zero shifts for every later session), the geometry
    alone refitted on the same rows, and their terms."""

    params: dict[str, float]
    geometry: np.ndarray
    geometry_only: np.ndarray
    terms: Any
    """hilcal.discovery.corrections.CompensationSet of the refitted groups."""
    sessions: np.ndarray
    rows: np.ndarray
    """[N] the rows fitted."""


def learn(diag: Diagnosis, rec: Recording, robot: Robot) -> Learned:
    """Refit the diagnosis' model on all the rows it can use: a twin learns from every measurement, where the
    diagnosis keeps the verify rows out to judge its choice (`Learned`)."""
    legs = rec.legs_mm
    if diag.wiring is not None and diag.wiring.problem and not diag.wiring.dead:
        legs = diag.wiring.corrected(legs)
    whole = replace(rec, legs_mm=legs)
    dropped = [e["seq"] for e in (*diag.excluded, *diag.unknown_rows)]
    rows = ~np.isin(rec.seq, dropped)
    ctx = EffectContext.from_recording(whole, robot).rows(rows)
    fitted = replace(whole.rows(rows), phase=np.full(int(rows.sum()), "measure"))
    p = Problem.of(fitted, robot, ctx)
    groups = [g for g in diag.groups if g.key != ZERO_SHIFT]
    held = diag.session_shift is not None and bool(diag.session_shift.legs)
    if (held or len(groups) < len(diag.groups)) and (shift := zero_shift_group(ctx, RobotScales.of(robot, ctx))):
        groups.append(shift)
    geometry_only = fit_model(p, [], label="twin geometry only")
    scales = shape_scales(leg_residuals(p, geometry_only, []))
    chosen = diag.noise.chosen
    noise = None if chosen is None else float(np.sqrt(np.mean(np.trace(chosen.covariance, axis1=1, axis2=2)) / 6.0))
    p.shape_prior = (scales, noise)
    fit = fit_model(p, groups, diag.final_fit, label="twin")
    final = final_fit(p, groups, fit, scales, max(fit.rms_residual, 1e-6))
    params = {n: float(v) for n, v in zip(final.names[42:], final.x[42:], strict=True)}
    return Learned(params, final.x[:42], geometry_only.x[:42], compensation_set(ctx, final, groups),
                   np.unique(ctx.session), rows)


def _values(params: dict[str, float], effect: str) -> np.ndarray | None:
    names = [f"leg{i}_{effect}_{PER_LEG[effect]}" for i in range(1, 7)]
    return np.array([params[n] for n in names]) if all(n in params for n in names) else None


def _line(leg: int, variable: str, slope_mm: float) -> dict[str, Any]:
    """A leg table for Δl = slope · variable (exact between ±WIDE)."""
    return {"leg": leg, "variable": variable, "x": [-WIDE, WIDE], "correction_mm": [-slope_mm * WIDE, slope_mm * WIDE]}


def _library(params: dict[str, float]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The named effects in the rig's parameters, and tables for values its effects cannot take (negative ones).

    The diagnosis' terms are in the reported stroke s (reported length - l0); the rig's compliances act on its true
    stroke, s / (1 + g) with its gain error g, so their values are scaled by (1 + g) to give the same Δl."""
    effects: dict[str, Any] = {}
    tables: list[dict[str, Any]] = []
    scale = _values(params, "sensor_scale")
    g = np.zeros(6) if scale is None else scale * 1e-6 / (1.0 - scale * 1e-6)
    if scale is not None:
        effects["sensor_scale"] = {"enabled": True, "gain_error_ppm": (g * 1e6).tolist()}
    compliance = _values(params, "leg_compliance")
    if compliance is not None:
        c = compliance * 1e-3
        effects["leg_compliance"] = {"enabled": True, "c_mm_per_kn": np.maximum(c, 0.0).tolist()}
        tables += [_line(i + 1, "axial_load_kN", -c[i]) for i in range(6) if c[i] < 0]
    backlash = _values(params, "joint_backlash")
    if backlash is not None:
        effects["joint_backlash"] = {"enabled": True, "backlash_mm": np.maximum(backlash, 0.0).tolist()}
        tables += [_line(i + 1, "direction", backlash[i] / 2.0) for i in range(6) if backlash[i] < 0]
    if "thermal_expansion_ppm_per_K" in params:
        effects["thermal_expansion"] = {"enabled": True, "t_ref_c": 20.0,
                                        "alpha_ppm_per_k": params["thermal_expansion_ppm_per_K"]}
    for name in ("oil_column_compliance", "drive_compliance"):
        kappa = _values(params, name)
        if kappa is None:
            continue
        k = kappa * 1e-3
        native = (np.maximum(k, 0.0) * (1.0 + g)).tolist()
        effects[name] = ({"enabled": True, "kappa_mm_per_kn_m": native, "dead_length_m": 0.0}
                         if name == "oil_column_compliance" else
                         {"enabled": True, "c_fixed_mm_per_kn": 0.0, "c_per_length_mm_per_kn_m": native,
                          "free_length_at_zero_stroke_mm": 0.0})
        tables += [_line(i + 1, "axial_load_kN*stroke_m", -k[i]) for i in range(6) if k[i] < 0]
    return effects, tables


def _sessions(learned: Learned) -> list[dict[str, Any]]:
    """Per leg, a table against the session number: the zero shift of every later session against the first."""
    sessions = learned.sessions
    if sessions.size < 2:
        return []
    shift = np.zeros((6, sessions.size))
    for name, value in learned.params.items():
        m = re.fullmatch(r"leg(\d)_zero_shift_session(\d+)_mm", name)
        if m and int(m.group(2)) - 1 in sessions:
            shift[int(m.group(1)) - 1, np.searchsorted(sessions, int(m.group(2)) - 1)] = value
    return [{"leg": i + 1, "variable": "session", "x": sessions.astype(float).tolist(),
             "correction_mm": shift[i].tolist()} for i in range(6) if np.any(shift[i] != 0.0)]


def _shapes(learned: Learned, robot: Robot) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The unexplained terms as leg tables and joint curvatures (axes of `joint_axes`)."""
    model = learned.terms
    axes = dict(zip(("base_joint_angle", "platform_joint_angle"), joint_axes(robot), strict=True))
    tables, curvatures = [], []
    for term in model.terms:
        if term.effect != "unexplained":
            continue
        if term.angle_terms:
            c = dict(term.angle_terms)
            a = axes[term.variable][term.leg]
            curvatures.append({"leg": term.leg + 1, "joint": term.variable.split("_")[0], "axis1": a[0].tolist(),
                               "axis2": a[1].tolist(), "mm_per_rad2": [c["a1*a1"], c["a1*a2"], c["a2*a2"]]})
        elif term.grid is not None and term.correction_mm is not None:
            tables.append({"leg": term.leg + 1, "variable": term.variable, "x": term.grid.tolist(),
                           "correction_mm": term.correction_mm.tolist()})
    return tables, curvatures


def _sphere_sigma_mm(diag: Diagnosis, robot: Robot, rec: Recording) -> float | None:
    """The CMM's sphere-centre noise of the yardstick; for a pose-noise source, the sphere noise giving the same pose
    position noise with the robot file's sphere layout."""
    chosen = diag.noise.chosen
    if chosen is None:
        return None
    if chosen.sphere_sigma_mm is not None:
        return chosen.sphere_sigma_mm
    unit = sphere_noise_covariance(robot, rec.meas, 1.0, robot.characteristic_length_mm)
    return chosen.position_mm / float(np.sqrt(np.mean(np.trace(unit[:, :3, :3], axis1=1, axis2=2))))


def _leg_resolution_mm(legs_mm: np.ndarray) -> float:
    """The step of the recorded leg readings: the coarsest decimal step (1 mm to 1 nm) they are all multiples of
    (0: none, then the twin reports lengths unrounded)."""
    legs = np.asarray(legs_mm, dtype=float)
    for digits in range(7):
        step = 10.0**-digits
        if np.max(np.abs(legs / step - np.round(legs / step)), initial=0.0) < 1e-6:
            return step
    return 0.0


def twin_of(diag: Diagnosis, learned: Learned, rec: Recording, robot: Robot,
            robot_path: Path | None) -> tuple[dict[str, Any], str, tuple[str, ...]]:
    """(the simulator configuration as a dict, the errors file's text, notes on what the twin leaves out)."""
    notes = []
    effects, tables = _library(learned.params)
    tables += _sessions(learned)
    shape_tables, curvatures = _shapes(learned, robot)
    tables += shape_tables
    if tables or curvatures:
        effects["leg_tables"] = {"enabled": True, "tables": tables, "curvatures": curvatures}
    if "joint_backlash" in effects or any(t["variable"] in ("direction", "last_move_mm_out", "last_move_mm_in")
                                          for t in tables):
        notes.append("the motion before each session's first row is not in the recording: the twin starts every "
                     "leg as after a long outward move")
    sigma = _sphere_sigma_mm(diag, robot, rec)
    if sigma is None:
        notes.append("the recording's noise is unknown: the twin measures without noise")
    rig: dict[str, Any] = {"seed": 0, "errors": ERRORS_FILE, "cmm_noise_mm": sigma or 0.0,
                           "leg_resolution_mm": _leg_resolution_mm(rec.legs_mm), "effects": effects}
    ctx = diag.context
    if ctx.temp_c is not None:
        clock = ctx.time_s - np.min(rec.time_s)
        order = np.argsort(clock, kind="stable")
        rig["temperature"] = {"table_time_s": clock[order].tolist(), "table_c": ctx.temp_c[order].tolist()}
    else:
        rig["temperature"] = {"t0_c": 20.0, "drift_k_per_h": 0.0, "amplitude_k": 0.0}
    if diag.wiring is not None and diag.wiring.problem:
        notes.append("the twin reports its legs in the robot file's order and direction (the diagnosis found them "
                     "re-ordered or mirrored in the recording)")
    config: dict[str, Any] = {"rig": rig}
    if robot_path is not None:
        config = {"robot": ROBOT_FILE, **config}
    geometry = GeometryErrors.from_vector(learned.geometry)
    header = (f"The geometric errors of the digital twin: the diagnosis' model ({len(diag.groups)} effect group(s)) "
              f"refitted on {int(learned.rows.sum())} rows.\nPer leg da (platform joint, platform frame), db (base "
              "joint, base frame), dl0 (true minus reported length), mm.")
    return config, errors_toml(geometry, header), tuple(notes)


def write_twin(diag: Diagnosis, rec: Recording, robot: Robot, robot_path: Path | None, out_dir: Path) -> Twin:
    """Write sim_config.toml, twin_errors.toml (and the robot file) into out_dir; read them back as the simulator
    would (so the replay runs what was written); the geometry-only twin beside it."""
    learned = learn(diag, rec, robot)
    config, errors_text, notes = twin_of(diag, learned, rec, robot, robot_path)
    out_dir.mkdir(parents=True, exist_ok=True)
    if robot_path is not None:
        shutil.copyfile(robot_path, out_dir / ROBOT_FILE)
    (out_dir / ERRORS_FILE).write_text(errors_text)
    header = ("Digital twin of a diagnosed recording, written by `hilcal diagnose --report` (procedures/cli/twin.py):\n"
              "the robot, the fitted geometric errors, every named effect with its fitted values, the unexplained\n"
              "shapes and session shifts as per-leg tables, the temperature history and the noise.")
    path = out_dir / CONFIG_FILE
    path.write_text(sim_config_toml(config, header))
    loaded = load_sim_config(path)
    rig = loaded.rig.rig_config(robot)
    geometry = RigConfig(seed=0, errors=GeometryErrors.from_vector(learned.geometry_only),
                         cmm_noise_mm=rig.cmm_noise_mm, leg_resolution_mm=rig.leg_resolution_mm,
                         temperature=rig.temperature)
    return Twin(config, rig, geometry, notes, learned.rows)


def compare(twin: Twin, diag: Diagnosis, rec: Recording, robot: Robot) -> TwinComparison:
    """The recording replayed on both twins: the poses each reaches at the recording's rows."""
    legs = rec.legs_mm
    if diag.wiring is not None and diag.wiring.problem and not diag.wiring.dead:
        legs = diag.wiring.corrected(legs)
    chosen = diag.noise.chosen
    return TwinComparison(
        seq=rec.seq, phase=rec.phase, measured=rec.meas,
        twins={"geometry": replay_poses(robot, twin.geometry_rig, rec.time_s, legs),
               "physics": replay_poses(robot, twin.rig, rec.time_s, legs)},
        noise_position_mm=None if chosen is None else chosen.position_mm,
        noise_source="" if chosen is None else chosen.source, length_mm=robot.characteristic_length_mm,
        left_out=~twin.fitted,
    )
