"""Where the mismatch lives and how it compares with the noise: located findings, residual/noise ratios, and the
per-leg step between a measure session and a later verify-only session (re-homing or a zero shift).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.special import stdtr

from hilcal.discovery.context import EffectContext
from hilcal.discovery.regression import orth
from hilcal.discovery.result import EndStop, Finding, NoiseComparison, SessionShift
from hilcal.kinematics import Geometry, inverse_jacobian, inverse_kinematics, leg_vectors, split_pose
from hilcal.metrics import AccuracySummary
from hilcal.recording import Recording
from hilcal.robot import Robot

FINDING_T = 3.5
MAX_FINDINGS = 8
SHIFT_ALPHA = 0.01


def locate(ctx: EffectContext, rec: Recording, leg_res: np.ndarray) -> tuple[Finding, ...]:
    """Correlate each leg's residual with every variable the leg sees; keep the strongest (|t| > 3.5)."""
    drivers = {
        "axial load": ctx.force_kn,
        "stroke": ctx.stroke_mm,
        "direction of last motion": ctx.direction,
        "time": ctx.per_leg(ctx.time_s),
        "base joint angle 1": ctx.base_angle_rad[..., 0],
        "base joint angle 2": ctx.base_angle_rad[..., 1],
    }
    if ctx.temp_c is not None and np.ptp(ctx.temp_c) > 0:
        drivers["temperature"] = ctx.per_leg(ctx.temp_c)
    if np.unique(ctx.session).size > 1:
        drivers["session"] = ctx.per_leg(ctx.session)
    for axis, name in enumerate(("x", "y", "z")):
        drivers[f"platform {name}"] = ctx.per_leg(rec.meas[:, axis])
    findings = []
    n = len(leg_res)
    for name, values in drivers.items():
        for i in range(6):
            v = values[:, i]
            if np.ptp(v) == 0 or np.ptp(leg_res[:, i]) == 0:
                continue
            rho = float(np.corrcoef(v, leg_res[:, i])[0, 1])
            if abs(rho) * np.sqrt(n - 2) / np.sqrt(max(1 - rho**2, 1e-12)) > FINDING_T:
                findings.append(Finding(i + 1, name, rho, f"leg {i + 1} residual follows {name} (r = {rho:+.2f})"))
    findings.sort(key=lambda f: -abs(f.correlation))
    return tuple(findings[:MAX_FINDINGS])


def _leg_map(robot: Robot, poses: np.ndarray, length_mm: float) -> np.ndarray:
    """Per pose, the 6 x 6 map from a pose residual (mm, mm at the platform radius) to leg-length residuals."""
    R, t = split_pose(poses)
    G = inverse_jacobian(Geometry.nominal(robot), R, t)
    G[..., 3:] /= length_mm
    return G


def _blocks(blocks: np.ndarray, A: np.ndarray) -> np.ndarray:
    """The block-diagonal matrix of per-pose 6 x 6 `blocks` [N, 6, 6] times A [6 N, k]."""
    n = blocks.shape[0]
    return np.einsum("nij,njk->nik", blocks, A.reshape(n, 6, -1)).reshape(A.shape)


def _ratios(r: np.ndarray, J: np.ndarray, sigma: np.ndarray, leg_map: np.ndarray) -> tuple[float, np.ndarray, float]:
    """Observed / expected residual (total and per leg) under the noise covariance, for an LS fit with Jacobian J.

    With H = Q Q' the fit's projection and S the noise covariance (block diagonal, `sigma` [N, 6, 6]), the residual's
    covariance is C = (I - H) S (I - H): tr C = tr S - tr(Q'SQ), and with G the per-pose map to leg lengths
    (`leg_map`), diag(G C G') = diag(G S G') - 2 rowsum(GQ * GSQ) + rowsum(GQ (Q'SQ) * GQ), formed on the thin
    Q rather than on m x m matrices."""
    m = r.size
    Q = orth(J)
    SQ = _blocks(sigma, Q)
    M = Q.T @ SQ
    GQ, GSQ = _blocks(leg_map, Q), _blocks(leg_map, SQ)
    GSG = np.einsum("nij,njk,nik->ni", leg_map, sigma, leg_map).reshape(-1)
    C_rho = GSG - 2.0 * np.sum(GQ * GSQ, axis=1) + np.sum((GQ @ M) * GQ, axis=1)
    trace = float(np.trace(sigma, axis1=1, axis2=2).sum() - np.trace(M))
    rho = _blocks(leg_map, r[:, None])[:, 0]
    per_leg = np.array([np.sqrt(np.sum(rho[i::6] ** 2) / np.sum(C_rho[i::6])) for i in range(6)])
    return float(np.sqrt(r @ r / trace)), per_leg, float(np.sqrt(trace / m))


def noise_comparison(robot: Robot, poses: np.ndarray, covariance: np.ndarray, geometry: tuple[np.ndarray, np.ndarray],
                     final: tuple[np.ndarray, np.ndarray], length_mm: float) -> NoiseComparison:
    """Residual RMS of the geometry-only and the final fit against what the noise alone would leave."""
    sigma = np.asarray(covariance, dtype=float)
    leg_map = _leg_map(robot, poses, length_mm)
    ratio_geo, legs_geo, _ = _ratios(*geometry, sigma, leg_map)
    ratio_fin, legs_fin, expected = _ratios(*final, sigma, leg_map)
    r = final[0]
    return NoiseComparison(ratio_geo, ratio_fin, legs_geo, legs_fin, float(np.sqrt(np.mean(r**2))), expected)


def _holm(p: np.ndarray) -> np.ndarray:
    order = np.argsort(p)
    adjusted = np.empty_like(p)
    running = 0.0
    for rank, k in enumerate(order):
        running = max(running, min(1.0, (len(p) - rank) * p[k]))
        adjusted[k] = running
    return adjusted


def session_shift(ctx: EffectContext, measure: np.ndarray, leg_res: np.ndarray, rec: Recording,
                  predict: Callable[[np.ndarray, np.ndarray], np.ndarray],
                  unknown: np.ndarray | None = None,
                  model_variance: Callable[[np.ndarray], np.ndarray] | None = None) -> SessionShift | None:
    """Per-leg mean residual of verify rows in sessions without measure rows (t test per leg, Holm over legs).

    Such a step is itself a finding: the machine was re-homed or a transducer's zero moved between the
    sessions. It is estimated on the verify rows themselves, so the corrected verify error is not held out.
    `predict(rows, leg_offsets_mm)` gives the model's poses for those rows with extra leg offsets. Rows in
    `unknown` (a term of the model cannot apply there: its history is unknown) do not enter the estimate.
    `model_variance(rows)` (6,): the variance the model's own uncertainty leaves in each leg's mean residual there
    (mm²); it is added to the rows' scatter, so a step the model cannot rule out is not named.
    """
    later = ~measure & ~np.isin(ctx.session, np.unique(ctx.session[measure]))
    known = later if unknown is None else later & ~unknown
    n = int(known.sum())
    if n < 3:
        return None
    res = leg_res[known]
    mean = res.mean(axis=0)
    se = res.std(axis=0, ddof=1) / np.sqrt(n)
    if model_variance is not None:
        se = np.sqrt(se**2 + model_variance(known))
    p = _holm(2 * stdtr(n - 1, -np.abs(mean) / np.maximum(se, 1e-300)))
    legs = tuple(int(i) + 1 for i in np.flatnonzero(p < SHIFT_ALPHA))
    corrected = None
    if legs:
        verify = ~measure
        offsets = np.where(later[verify][:, None], mean[None, :], 0.0)
        corrected = AccuracySummary.of(rec.meas[verify], predict(verify, offsets))
    return SessionShift(mean, se, p, legs, corrected)


END_STOP_FRACTION = 0.1
"""A leg whose reading equals its extreme in at least 10 % of the rows (and 3 rows) may sit on an end stop."""
END_STOP_TOLERANCE_MM = 0.002


def end_stops(rec: Recording, robot: Robot) -> tuple[EndStop, ...]:
    """Legs whose reading sits at the same extreme value in many rows: an end stop or a software limit, where the
    reading no longer follows the pose."""
    out = []
    n = rec.n
    for i in range(6):
        legs = rec.legs_mm[:, i]
        for extreme, value in (("minimum", float(np.min(legs))), ("maximum", float(np.max(legs)))):
            at = int(np.sum(np.abs(legs - value) <= END_STOP_TOLERANCE_MM))
            if at >= max(3, END_STOP_FRACTION * n):
                out.append(EndStop(i + 1, value, extreme, at, n))
    return tuple(out)


ZERO_FAULT_FRACTION = 0.01
"""A leg whose reading is off by more than 1 % of the stroke range at every length has its zero set wrong."""


def _frame_part(joints: np.ndarray, moved: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """The small rigid motion (omega x p + t) of a set of joints that best explains their displacement across the
    legs: the component along each leg's axis is left out of the fit (there a joint slide and a zero are one)."""
    P = np.eye(3) - axes[:, :, None] * axes[:, None, :]
    skew = np.zeros((len(joints), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -joints[:, 2], joints[:, 1], -joints[:, 0]
    skew -= np.swapaxes(skew, 1, 2)
    A = (P @ np.concatenate([-skew, np.broadcast_to(np.eye(3), skew.shape)], axis=2)).reshape(-1, 6)
    w_t = np.linalg.lstsq(A, (P @ (moved - joints)[..., None]).reshape(-1), rcond=None)[0]
    return np.cross(w_t[:3], joints) + w_t[3:]


def zero_offsets(robot: Robot, geometry: Geometry) -> np.ndarray:
    """(6,) how much each leg reads more (mm, + long) than the robot file says at the home pose, once the rigid
    motions of the base joints and of the platform joints are taken out (a measurement frame placed elsewhere moves
    all joints rigidly and is no zero error)."""
    home = robot.home[None]
    R, t = split_pose(home)
    _, _, u = leg_vectors(Geometry.nominal(robot), R, t)
    b = geometry.b - _frame_part(robot.b, geometry.b, u[0])
    a = geometry.a - _frame_part(robot.a, geometry.a, u[0] @ R[0])
    return inverse_kinematics(Geometry(a, b, geometry.dl0), home)[0] - inverse_kinematics(Geometry.nominal(robot),
                                                                                          home)[0]


def zero_sentence(robot: Robot, offsets_mm: np.ndarray) -> str | None:
    """A set-up fault sentence for legs whose zero is off by more than ZERO_FAULT_FRACTION of the stroke range."""
    limit = ZERO_FAULT_FRACTION * (robot.leg_limits[1] - robot.leg_limits[0])
    legs = [i for i in range(6) if abs(offsets_mm[i]) > limit]
    if not legs:
        return None
    parts = ", ".join(f"leg {i + 1} {abs(offsets_mm[i]):.3f} mm {'long' if offsets_mm[i] > 0 else 'short'}"
                      for i in legs)
    return (f"Set-up fault (leg zero): {parts} at every length (more than {ZERO_FAULT_FRACTION:.0%} of the "
            f"{robot.leg_limits[1] - robot.leg_limits[0]:g} mm stroke range): check the homing offset or the zero "
            "in the controller or logger; the calibration's leg offsets correct it.")
