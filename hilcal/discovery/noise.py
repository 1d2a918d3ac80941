"""The absolute noise yardstick: how large the measurement noise of a recording is, in mm, and where that is known from.

A residual can only be called "within noise" against a noise level that does not come from the residuals
themselves. Sources, in the order they are trusted:
1. a value the user states (`--cmm-sigma-mm`): standard uncertainty of one sphere-centre coordinate;
2. the robot file's `cmm.sphere_sigma_mm`;
3. the recording's `sphere_fit_rms_mm` column: every pose is registered from three or more spheres, and the
   registration residual measures the sphere-centre noise independently of the kinematic model;
4. repeated poses in the recording: the scatter of the model residuals between repeats of one pose.
Sphere-centre noise is propagated to the pose through the same registration the tool uses
(`hilcal.pose_measurement`), giving a 6 x 6 covariance per pose in the residual metric (mm, rotations as
mm at the platform's characteristic length). Every available source is reported, so they can be compared.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.discovery.context import detect_sessions
from hilcal.pose_measurement import sigma_from_sphere_fit, sphere_noise_covariance
from hilcal.recording import Recording
from hilcal.robot import Robot

REPEAT_LEG_TOLERANCE_MM = 0.005
"""Rows without a commanded pose whose six reported leg lengths agree to 5 µm are repeats."""
REPEAT_SERVO_TOLERANCE_MM = 0.05
"""Rows with the same commanded pose are repeats where the servo landed within 50 µm on every leg: a real servo's
landing scatter (µm to tens of µm) is the machine's repeatability, which the repeats are there to measure."""
REPEAT_WINDOW_S = 3600.0
"""Repeats are measured within an hour of the first: visits of one pose hours apart differ by drift (a leg warming
up, a re-homing), which is not noise and would make a yardstick that hides the physics. A plan that revisits a pose
to check drift within a session (examples/small_hexapod: three visits over 42 minutes) keeps its repeats."""


@dataclass(frozen=True)
class NoiseEstimate:
    """One estimate of the pose noise of a recording."""

    source: str
    covariance: np.ndarray
    """[N, 6, 6] pose-noise covariance of every row in the residual metric (mm, mm at the platform radius)."""
    sphere_sigma_mm: float | None
    dof: float | None
    """Degrees of freedom behind an estimated level; None for a stated one."""

    @property
    def position_mm(self) -> float:
        """RMS length of the 3-D position noise of one measured pose, mm (the verify-error floor)."""
        return float(np.sqrt(np.mean(np.trace(self.covariance[:, :3, :3], axis1=1, axis2=2))))

    def describe(self) -> str:
        sigma = "" if self.sphere_sigma_mm is None else f"sphere-centre sigma {self.sphere_sigma_mm * 1000:.2f} µm, "
        dof = "" if self.dof is None else f", {self.dof:.0f} degrees of freedom"
        return f"{sigma}pose position noise {self.position_mm * 1000:.2f} µm RMS (source: {self.source}{dof})"


@dataclass(frozen=True)
class NoiseLevel:
    """The yardstick used (None when no source is available) and every estimate found."""

    chosen: NoiseEstimate | None
    estimates: tuple[NoiseEstimate, ...]
    notes: tuple[str, ...] = ()

    def to_json(self) -> dict:
        def one(e: NoiseEstimate) -> dict:
            return {"source": e.source, "position_mm": e.position_mm, "sphere_sigma_mm": e.sphere_sigma_mm,
                    "dof": e.dof}

        return {
            "known": self.chosen is not None,
            "position_mm": None if self.chosen is None else self.chosen.position_mm,
            "source": None if self.chosen is None else self.chosen.source,
            "sphere_sigma_mm": None if self.chosen is None else self.chosen.sphere_sigma_mm,
            "estimates": [one(e) for e in self.estimates],
            "notes": list(self.notes),
        }


def find_repeats(rec: Recording, session: np.ndarray | None = None) -> list[np.ndarray]:
    """Groups (>= 2 rows, one session, within REPEAT_WINDOW_S of the first) of rows measured at the same pose: the
    same commanded pose with the legs within REPEAT_SERVO_TOLERANCE_MM, else legs within REPEAT_LEG_TOLERANCE_MM.

    `session`: the rows' sessions when they are a subset of a longer recording (else from their clock)."""
    session = detect_sessions(rec.time_s) if session is None else np.asarray(session)
    has_cmd = np.all(np.isfinite(rec.cmd), axis=1)
    time_s = np.asarray(rec.time_s, dtype=float)
    unused = np.ones(rec.n, dtype=bool)
    groups = []
    for k in range(rec.n):
        if not unused[k]:
            continue
        same = (session == session[k]) & unused
        if np.isfinite(time_s[k]):
            same &= ~np.isfinite(time_s) | (np.abs(time_s - time_s[k]) <= REPEAT_WINDOW_S)
        legs = np.max(np.abs(rec.legs_mm - rec.legs_mm[k]), axis=1)
        if has_cmd[k]:
            commanded = np.max(np.abs(rec.cmd - rec.cmd[k]), axis=1) <= 1e-6
            same &= np.where(has_cmd, commanded & (legs <= REPEAT_SERVO_TOLERANCE_MM),
                             legs <= REPEAT_LEG_TOLERANCE_MM)
        else:
            same &= legs <= REPEAT_LEG_TOLERANCE_MM
        rows = np.flatnonzero(same)
        if rows.size >= 2:
            groups.append(rows)
            unused[rows] = False
    return groups


def revisited_poses(rec: Recording, groups: list[np.ndarray]) -> int:
    """Commanded poses measured more than once whose visits are not repeats (hours or sessions apart, or landed
    too far apart): said when the noise level stays unknown, so the reader knows why they were not used."""
    has_cmd = np.all(np.isfinite(rec.cmd), axis=1)
    in_group = np.zeros(rec.n, dtype=bool)
    for g in groups:
        in_group[g] = True
    _, inverse, counts = np.unique(np.round(rec.cmd[has_cmd], 6), axis=0, return_inverse=True, return_counts=True)
    visited = counts[inverse.ravel()] >= 2
    return len(np.unique(inverse.ravel()[visited & ~in_group[has_cmd]]))


def noise_from_repeats(residuals: np.ndarray, groups: list[np.ndarray]) -> tuple[np.ndarray, float] | None:
    """Pooled within-group covariance [6, 6] of model residuals [N, 6] over repeat groups, and its dof.

    Residuals rather than raw poses: what the model predicts cancels between repeats even if the legs
    differ slightly, so only the measurement's scatter (and the machine's repeatability) remains.
    """
    dof = sum(g.size - 1 for g in groups)
    if dof < 2:
        return None
    dev = np.concatenate([residuals[g] - residuals[g].mean(axis=0) for g in groups])
    return dev.T @ dev / dof, float(dof)


def sphere_sources(rec: Recording, robot: Robot, cmm_sigma_mm: float | None) -> bool:
    """Whether a sphere-centre noise source is available (then `sphere_noise_covariance` will be needed)."""
    return cmm_sigma_mm is not None or robot.sphere_sigma_mm is not None or "sphere_fit_rms_mm" in rec.extra


def noise_yardstick(rec: Recording, robot: Robot, residuals: np.ndarray, length_mm: float,
                    cmm_sigma_mm: float | None = None, pose_sigma: tuple[float, float] | None = None,
                    session: np.ndarray | None = None, unit_covariance: np.ndarray | None = None) -> NoiseLevel:
    """Every available noise estimate for the rows of rec, and the one to trust (see the module docstring).

    `residuals` [N, 6] are the geometric model's pose residuals of every row (residual metric), used for
    repeats; `session` the rows' sessions (find_repeats); `unit_covariance` their `sphere_noise_covariance` at a
    sphere sigma of 1 mm when it was already worked out (the covariance scales with sigma squared).
    """
    estimates: list[NoiseEstimate] = []

    def from_sigma(sigma: float, source: str, dof: float | None) -> NoiseEstimate:
        if unit_covariance is not None:
            return NoiseEstimate(source, sigma**2 * unit_covariance, sigma, dof)
        return NoiseEstimate(source, sphere_noise_covariance(robot, rec.meas, sigma, length_mm), sigma, dof)

    if cmm_sigma_mm is not None:
        estimates.append(from_sigma(cmm_sigma_mm, "--cmm-sigma-mm", None))
    if pose_sigma is not None:
        position_mm, orientation_deg = pose_sigma
        spread = np.array([position_mm] * 3 + [np.radians(orientation_deg) * length_mm] * 3)
        estimates.append(NoiseEstimate(f"--pose-sigma-mm {position_mm:g} --pose-sigma-deg {orientation_deg:g}",
                                       np.broadcast_to(np.diag(spread**2), (rec.n, 6, 6)).copy(), None, None))
    if robot.sphere_sigma_mm is not None:
        estimates.append(from_sigma(robot.sphere_sigma_mm, "robot file cmm.sphere_sigma_mm", None))
    column = rec.extra.get("sphere_fit_rms_mm")
    if column is not None and column.dtype.kind == "f" and np.isfinite(column).sum() >= 3:
        sigma, dof = sigma_from_sphere_fit(column, robot)
        if sigma > 0:
            estimates.append(from_sigma(sigma, "sphere_fit_rms_mm column", dof))
    groups = find_repeats(rec, session)
    repeats = noise_from_repeats(residuals, groups)
    if repeats is not None:
        cov, dof = repeats
        estimates.append(NoiseEstimate(f"{len(groups)} repeated pose(s) in the recording",
                                       np.broadcast_to(cov, (rec.n, 6, 6)).copy(), None, dof))
    notes = []
    if not estimates:
        revisited = revisited_poses(rec, groups)
        why = (f"; {revisited} commanded pose(s) were visited again, but not as repeats (more than "
               f"{REPEAT_WINDOW_S / 60:.0f} min or a session apart, or legs landing more than "
               f"{REPEAT_SERVO_TOLERANCE_MM * 1000:.0f} µm apart): drift between visits is not measurement noise"
               if revisited else "")
        return NoiseLevel(None, (), ("noise level unknown: relative tests only (give --cmm-sigma-mm, the robot "
                                     "file's cmm.sphere_sigma_mm, a sphere_fit_rms_mm column or repeated poses)"
                                     + why,))
    chosen = estimates[0]
    for other in estimates[1:]:
        ratio = other.position_mm / chosen.position_mm
        if ratio > 1.5 or ratio < 1 / 1.5:
            notes.append(f"{other.source} gives {ratio:.2f}x the noise of {chosen.source} "
                         f"({other.position_mm * 1000:.2f} vs {chosen.position_mm * 1000:.2f} µm)"
                         + (": the machine's repeatability or drift between repeats exceeds the CMM noise"
                            if "repeat" in other.source and ratio > 1 else ""))
    return NoiseLevel(chosen, tuple(estimates), tuple(notes))
