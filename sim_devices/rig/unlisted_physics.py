"""Truth physics of the rig's out-of-library and session effects: each a Δl_i (mm) on the true joint-centre distance.

Written for the simulator only; the calibration tool's diagnosis has no candidate for any of them. The rig adds
these corrections to those of sim_devices.rig.physics and solves the self-consistent pose with all of them.

Hooke (universal) joint with non-intersecting axes, at the base of leg i (effect ``hooke_joint_offset``):
the first axis, direction e1 (unit, fixed in the base), passes through the nominal joint centre b. The cross
carries the second axis e2 ⟂ e1 at the distance d from the first, along their common normal n = ±e1 × e2; the
cylinder is fixed to the second axis' yoke, so its axis is perpendicular to e2 and crosses it at the foot of
the common normal, c = b + d n. With joint angles θ1 (about e1) and θ2 (about e2), and n⁰, e2⁰ the reference
directions, n = R(e1, θ1) n⁰ and the leg direction is u = R(e1, θ1) R(e2⁰, θ2) n⁰ = cos θ2 n + sin θ2 e1.
So n = (u - (u·e1) e1) / |u - (u·e1) e1| is fixed by the leg direction alone (n·u = cos θ2 > 0), and the
point c = b + d n(u) the leg pivots about moves with the first joint angle. The leg line passes through c
and the platform joint p; the piston (reported + dl0 + other effects) spans |p - c|, the rig's joint-centre
distance is |p - b|, so

    Δl = |p - b| - |p - c|,  u = (p - c) / |p - c|,

solved by fixed-point iteration in c (contraction ≈ d / L: machine precision in a few steps). To first order
in d / L, Δl ≈ d (u·n) = d cos θ2 = d sqrt(1 - (u·e1)²) ≈ d - d (u·e1)² / 2: a constant (absorbed by dl0)
plus a term QUADRATIC in the leg direction. Rigid joint errors give only linear ones (-u·db at the base,
(Rᵀu)·da at the platform), so the quadratic part cannot be absorbed by the 42 geometric parameters. With e1
perpendicular to the home leg, θ2 = 0 at home and the signature is -d θ2² / 2: θ2 spans about ±0.1 rad on the
paper robot, so it needs a designed (tens of mm) rather than a manufacturing (1-2 mm) offset to reach a few
times the noise floor. Fraction of the variance of Δl over a run that a per-leg least-squares fit on
[1, u, Rᵀu] (exactly what rigid dl0/db/da errors produce, to first order) leaves unexplained, paper robot with
Table 2 errors, d = 1.5 mm on every leg, horizontal first axes: 0.38-0.51 per leg (median 0.45) over the
study's 32 D-optimal + 24 verification poses, 0.52-0.84 (median 0.68) over verification_poses(robot, 56, 0);
``python examples/unlisted_ratios.py --hooke-fraction``. The D-optimal design puts most poses at the workspace
corners, where θ2² is presumably closer to linear in u; turning the first axes about the leg
(``--axis-angle-deg`` 30, 60, 90, 120, 150) gives D-optimal medians 0.54, 0.45, 0.27, 0.50, 0.53. So about half
of the effect survives any rigid calibration; the rest is absorbed by small joint-position errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_devices.config_base import per_leg
from sim_devices.rig.config import EffectsConfig
from sim_devices.rig.physics import DEADBAND_ROUNDING_MM, DIRECTION_DEADBAND_MM, PPM

HOOKE_ITERATIONS = 8
"""Fixed-point steps for the pivot point c; the contraction factor is about d / L (< 1e-2 for any real joint)."""


@dataclass(frozen=True)
class LegState:
    """Everything the out-of-library effects depend on at one instant (base frame, mm, s)."""

    stroke_mm: np.ndarray
    """(6,) piston stroke (sim_devices.rig.physics.true_stroke_mm)."""
    stroke_min_mm: np.ndarray
    """(6,) stroke at the lower leg limit."""
    stroke_max_mm: np.ndarray
    """(6,) stroke at the upper leg limit."""
    base_joints_mm: np.ndarray
    """(6, 3) true base joint centres b_i."""
    platform_joints_mm: np.ndarray
    """(6, 3) true platform joint centres p_i at the current pose."""
    first_axes: np.ndarray
    """(6, 3) unit first axes e1 of the base Hooke joints (see hooke_first_axes)."""
    time_s: float
    """The rig's clock."""
    session_time_s: float
    """Time since the current session (power-on) started."""
    direction: np.ndarray
    """(6,) direction of the last move of each leg, +1 extending, -1 retracting."""
    last_move_mm: np.ndarray
    """(6,) size of the last move of each leg (inf before any move: a saturated state)."""


def last_move_size_mm(previous_mm: np.ndarray, step_mm: np.ndarray) -> np.ndarray:
    """Per-leg size of the last move; like physics.motion_direction, moves below the 1 µm deadband keep the old one."""
    moved = np.abs(step_mm) >= DIRECTION_DEADBAND_MM - DEADBAND_ROUNDING_MM
    return np.where(moved, np.abs(step_mm), previous_mm)


def hooke_first_axes(home_leg_directions: np.ndarray, axis_angle_deg: float | list[float]) -> np.ndarray:
    """(6, 3) first axes: horizontal and perpendicular to the home leg, turned by axis_angle_deg about that leg.

    A vertical home leg has no horizontal normal; then the base x axis is used as the reference instead.
    """
    u = np.asarray(home_leg_directions, dtype=float)
    reference = np.cross([0.0, 0.0, 1.0], u)
    vertical = np.linalg.norm(reference, axis=1) < 1e-9
    reference[vertical] = np.cross(np.cross(u[vertical], [1.0, 0.0, 0.0]), u[vertical])
    reference /= np.linalg.norm(reference, axis=1, keepdims=True)
    angle = np.radians(per_leg(axis_angle_deg))[:, None]
    # Rodrigues' rotation of reference (⟂ u) about u: cos·r + sin·(u × r).
    return np.cos(angle) * reference + np.sin(angle) * np.cross(u, reference)


def hooke_offset_mm(
    offset_mm: np.ndarray, first_axes: np.ndarray, base_joints_mm: np.ndarray, platform_joints_mm: np.ndarray
) -> np.ndarray:
    """Δl = |p - b| - |p - c| with c = b + d n(u), n the part of u perpendicular to e1, normalised (module doc)."""
    d = np.asarray(offset_mm, dtype=float)[:, None]
    e1 = np.asarray(first_axes, dtype=float)
    b, p = np.asarray(base_joints_mm, dtype=float), np.asarray(platform_joints_mm, dtype=float)
    c = b.copy()
    for _ in range(HOOKE_ITERATIONS):
        u = (p - c) / np.linalg.norm(p - c, axis=1, keepdims=True)
        across = u - np.sum(u * e1, axis=1, keepdims=True) * e1
        c = b + d * across / np.linalg.norm(across, axis=1, keepdims=True)
    return np.linalg.norm(p - b, axis=1) - np.linalg.norm(p - c, axis=1)


def transducer_bow_mm(
    amplitude_mm: np.ndarray, stroke_mm: np.ndarray, lo_mm: np.ndarray, hi_mm: np.ndarray
) -> np.ndarray:
    """A sin(π (s - s_min) / (s_max - s_min)): zero at both stroke ends, A at mid-stroke."""
    return amplitude_mm * np.sin(np.pi * (stroke_mm - lo_mm) / (hi_mm - lo_mm))


def cyclic_stroke_error_mm(
    amplitude_mm: np.ndarray, period_mm: np.ndarray, phase_deg: np.ndarray, stroke_mm: np.ndarray
) -> np.ndarray:
    """A sin(2π s / P + φ)."""
    return amplitude_mm * np.sin(2.0 * np.pi * stroke_mm / period_mm + np.radians(phase_deg))


def local_heating_mm(
    delta_t_k: np.ndarray, time_constant_s: float, alpha_ppm_per_k: float, leg_lengths_mm: np.ndarray, t_s: float
) -> np.ndarray:
    """α L (T_leg - T_amb) with T_leg - T_amb = ΔT (1 - exp(-t / τ)), t the time since power-on."""
    excess_k = delta_t_k * (1.0 - np.exp(-max(t_s, 0.0) / time_constant_s))
    return alpha_ppm_per_k * PPM * leg_lengths_mm * excess_k


def friction_hysteresis_mm(
    amplitude_mm: np.ndarray, length_mm: float, direction: np.ndarray, last_move_mm: np.ndarray
) -> np.ndarray:
    """h dir (1 - exp(-|Δ| / λ))."""
    return amplitude_mm * direction * (1.0 - np.exp(-np.asarray(last_move_mm) / length_mm))


def unlisted_corrections_mm(
    effects: EffectsConfig, state: LegState, leg_lengths_mm: np.ndarray
) -> dict[str, np.ndarray]:
    """Δl (mm, (6,)) of every enabled out-of-library and session effect; leg_lengths_mm = |p_i - b_i|."""
    out: dict[str, np.ndarray] = {}
    if effects.transducer_bow.enabled:
        out["transducer_bow"] = transducer_bow_mm(
            per_leg(effects.transducer_bow.amplitude_mm), state.stroke_mm, state.stroke_min_mm, state.stroke_max_mm
        )
    if effects.cyclic_stroke_error.enabled:
        cfg = effects.cyclic_stroke_error
        out["cyclic_stroke_error"] = cyclic_stroke_error_mm(
            per_leg(cfg.amplitude_mm), per_leg(cfg.period_mm), per_leg(cfg.phase_deg), state.stroke_mm
        )
    if effects.hooke_joint_offset.enabled:
        out["hooke_joint_offset"] = hooke_offset_mm(
            per_leg(effects.hooke_joint_offset.offset_mm),
            state.first_axes,
            state.base_joints_mm,
            state.platform_joints_mm,
        )
    if effects.local_heating.enabled:
        cfg = effects.local_heating
        out["local_heating"] = local_heating_mm(
            per_leg(cfg.delta_t_k), cfg.time_constant_s, cfg.alpha_ppm_per_k, leg_lengths_mm, state.session_time_s
        )
    if effects.friction_hysteresis.enabled:
        cfg = effects.friction_hysteresis
        out["friction_hysteresis"] = friction_hysteresis_mm(
            per_leg(cfg.amplitude_mm), cfg.length_mm, state.direction, state.last_move_mm
        )
    if effects.zero_shift.enabled:
        applies = state.time_s >= effects.zero_shift.from_time_s
        out["zero_shift"] = per_leg(effects.zero_shift.shift_mm) * (1.0 if applies else 0.0)
    return out
