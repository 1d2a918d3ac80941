"""Measurement uncertainty of the certificate's figures (GUM, expanded with k = 2), by seeded Monte Carlo.

Two sources, both from the run itself:
- the CMM's stated uncertainty U (k = 2) of one measured sphere-centre coordinate: u = U / 2 on every coordinate of
  every tooling sphere, carried through the pose registration (``hilcal.pose_measurement``) by Monte Carlo to the
  covariance of one measured pose (``cmm_pose_covariance``);
- the poses measured several times with the same command: their pooled within-pose covariance
  (``pooled_covariance``), the machine's repeatability plus the CMM's random part.
A figure's value is computed from the measurements as they are; its standard uncertainty is the standard deviation
of the same figure over draws of its inputs (GUM Supplement 1), and U = 2 u. Every draw is seeded.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hilcal.error_models import forward_jacobian
from hilcal.kinematics import Geometry, split_pose
from hilcal.metrics import pose_errors
from hilcal.pose_measurement import pose_from_spheres
from hilcal.robot import Robot

K_COVERAGE = 2.0
"""Coverage factor of every expanded uncertainty on the certificate (about 95 % for a normal distribution)."""
DRAWS = 2000


@dataclass(frozen=True)
class Figure:
    """A result with its standard uncertainty u; the certificate shows the expanded U = k u (k = 2)."""

    value: float
    u: float
    unit: str

    @property
    def expanded(self) -> float:
        return K_COVERAGE * self.u

    def as_json(self) -> dict[str, float | str]:
        return {"value": self.value, "U": self.expanded, "k": K_COVERAGE, "unit": self.unit}


def _wrap_deg(angle: np.ndarray) -> np.ndarray:
    return (angle + 180.0) % 360.0 - 180.0


def cmm_pose_covariance(robot: Robot, sphere_u_mm: float, pose: np.ndarray | None = None, *, draws: int = 4000,
                        seed: int = 0) -> np.ndarray:
    """(6, 6) covariance (mm, deg) of one measured pose when every sphere-centre coordinate has standard u.

    The spheres are placed at `pose` (default home); the CMM frame is taken as the base frame, since its placement
    cancels in the registration. Rotations of the platform within the workspace change it very little.
    """
    if not sphere_u_mm > 0:
        raise ValueError(f"the sphere-centre uncertainty must be positive, got {sphere_u_mm}")
    q = robot.home if pose is None else np.asarray(pose, dtype=float)
    R, t = split_pose(q)
    platform = robot.platform_spheres @ R.T + t
    rng = np.random.default_rng(seed)
    fits = pose_from_spheres(platform + rng.normal(0.0, sphere_u_mm, (draws, *platform.shape)),
                             robot.base_spheres + rng.normal(0.0, sphere_u_mm, (draws, *robot.base_spheres.shape)),
                             robot).pose
    d = fits - q
    d[:, 3:] = _wrap_deg(d[:, 3:])
    return np.cov(d, rowvar=False)


def repeated_groups(commanded: np.ndarray, measured: np.ndarray) -> list[np.ndarray]:
    """The measured poses (n_g, 6) of every commanded pose that was measured at least twice."""
    cmd = np.asarray(commanded, dtype=float).reshape(-1, 6)
    meas = np.asarray(measured, dtype=float).reshape(-1, 6)
    if len(cmd) == 0:
        return []
    _, inverse, counts = np.unique(cmd, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    return [meas[inverse == g] for g in np.flatnonzero(counts >= 2)]


def pooled_covariance(groups: Sequence[np.ndarray]) -> tuple[np.ndarray | None, int]:
    """Pooled within-group covariance (6, 6) of repeated poses and its degrees of freedom (None, 0 without repeats)."""
    scatter = np.zeros((6, 6))
    dof = 0
    for g in groups:
        g = np.asarray(g, dtype=float)
        if len(g) < 2:
            continue
        d = g - g.mean(axis=0)
        d[:, 3:] = _wrap_deg(d[:, 3:])
        scatter += d.T @ d
        dof += len(g) - 1
    return (scatter / dof, dof) if dof else (None, 0)


def _normal_draws(cov: np.ndarray, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Draws N(0, cov) of shape (*shape, 6); a covariance that is only positive semi-definite is fine."""
    w, v = np.linalg.eigh(np.asarray(cov, dtype=float))
    root = v * np.sqrt(np.clip(w, 0.0, None))
    return rng.standard_normal((*shape, len(w))) @ root.T


def accuracy_figures(measured: np.ndarray, commanded: np.ndarray, cov: np.ndarray | None, *, draws: int = DRAWS,
                     seed: int = 0) -> dict[str, Figure]:
    """Largest and RMS position (mm) and orientation (deg) error over poses measured once each, with u.

    `cov` (6, 6) is the covariance of one measured pose (CMM, and the machine's repeatability); None: u = 0.
    """
    meas = np.asarray(measured, dtype=float).reshape(-1, 6)
    cmd = np.asarray(commanded, dtype=float).reshape(-1, 6)

    def figures(m: np.ndarray) -> dict[str, np.ndarray]:
        pos, ori = pose_errors(m, cmd)
        return {"max_position_mm": pos.max(axis=-1), "rms_position_mm": np.sqrt(np.mean(pos**2, axis=-1)),
                "max_orientation_deg": ori.max(axis=-1), "rms_orientation_deg": np.sqrt(np.mean(ori**2, axis=-1))}

    values = figures(meas)
    spread = {k: 0.0 for k in values}
    if cov is not None:
        drawn = figures(meas + _normal_draws(cov, (draws, len(meas)), np.random.default_rng(seed)))
        spread = {k: float(np.std(v, ddof=1)) for k, v in drawn.items()}
    return {k: Figure(float(v), spread[k], "mm" if k.endswith("_mm") else "deg") for k, v in values.items()}


def ap_figures(attained: np.ndarray, commanded: np.ndarray, cmm_cov: np.ndarray | None, *, draws: int = DRAWS,
               seed: int = 0) -> dict[str, Figure]:
    """AP_P (mm) and AP_a, AP_b, AP_c (deg) of one test pose with u.

    The barycentre's covariance is the cycles' sample covariance / n (type A) plus the CMM's pose covariance in
    full (type B: the CMM's systematic part does not average out over the cycles).
    """
    q = np.asarray(attained, dtype=float)
    c = np.asarray(commanded, dtype=float)
    angles = c[3:] + _wrap_deg(q[:, 3:] - c[3:])
    q = np.hstack([q[:, :3], angles])
    bary = q.mean(axis=0)
    cov = np.cov(q, rowvar=False) / len(q) + (0.0 if cmm_cov is None else np.asarray(cmm_cov))
    drawn = bary + _normal_draws(cov, (draws,), np.random.default_rng(seed))
    ap_p = np.linalg.norm(drawn[:, :3] - c[:3], axis=1)
    out = {"ap_p_mm": Figure(float(np.linalg.norm(bary[:3] - c[:3])), float(np.std(ap_p, ddof=1)), "mm")}
    for k, name in enumerate(("a", "b", "c")):
        out[f"ap_{name}_deg"] = Figure(float(bary[3 + k] - c[3 + k]), float(np.std(drawn[:, 3 + k], ddof=1)), "deg")
    return out


def rp_statistics(attained: np.ndarray) -> np.ndarray:
    """RP_l = l̄ + 3 S_l (mm) and 3 S_a, 3 S_b, 3 S_c (deg) of attained poses [..., n, 6] (batched)."""
    q = np.asarray(attained, dtype=float)
    bary = q.mean(axis=-2, keepdims=True)
    l_mm = np.linalg.norm(q[..., :3] - bary[..., :3], axis=-1)
    rp_l = l_mm.mean(axis=-1) + 3.0 * np.std(l_mm, axis=-1, ddof=1)
    rp_abc = 3.0 * np.std(_wrap_deg(q[..., 3:] - bary[..., 3:]), axis=-2, ddof=1)
    return np.concatenate([rp_l[..., None], rp_abc], axis=-1)


def rp_figures(attained: np.ndarray, *, draws: int = DRAWS, seed: int = 0) -> dict[str, Figure]:
    """RP_l (mm) and RP_a, RP_b, RP_c (deg) of one test pose, with u from a bootstrap over its cycles.

    The CMM's random part is already in the cycles' scatter and its systematic part cancels in a scatter, so
    the sampling of the n cycles is the uncertainty that remains.
    """
    q = np.asarray(attained, dtype=float)
    values = rp_statistics(q)
    resampled = rp_statistics(q[np.random.default_rng(seed).integers(0, len(q), (draws, len(q)))])
    spread = np.std(resampled, axis=0, ddof=1)
    names = ("rp_l_mm", "rp_a_deg", "rp_b_deg", "rp_c_deg")
    return {n: Figure(float(values[k]), float(spread[k]), "mm" if k == 0 else "deg") for k, n in enumerate(names)}


@dataclass(frozen=True)
class ModelUncertainty:
    """The identified parameters' covariance carried to workspace poses: expected pose error (1 sigma, RMS over
    the parameter uncertainty) per pose, summarised as the RMS over the poses and the worst pose."""

    n_poses: int
    rms_position_mm: float
    max_position_mm: float
    rms_orientation_deg: float
    max_orientation_deg: float

    def as_json(self) -> dict[str, float | int]:
        return {"n_poses": self.n_poses, "rms_position_mm": self.rms_position_mm,
                "max_position_mm": self.max_position_mm, "rms_orientation_deg": self.rms_orientation_deg,
                "max_orientation_deg": self.max_orientation_deg, "k": 1.0}


def model_uncertainty(robot: Robot, covariance: np.ndarray, poses: np.ndarray) -> ModelUncertainty:
    """Pose error covariance J C Jᵀ at each pose from the 42 parameters' covariance C (mm²), J the pose-error
    Jacobian of the rigid model at the nominal geometry (the identified errors change it negligibly)."""
    C = np.asarray(covariance, dtype=float)
    if C.shape != (42, 42):
        raise ValueError(f"need the 42 x 42 covariance of the rigid model, got {C.shape}")
    length = robot.characteristic_length_mm
    J = forward_jacobian(Geometry.nominal(robot), np.atleast_2d(np.asarray(poses, dtype=float)), length)
    P = J @ C @ np.swapaxes(J, -1, -2)
    pos = np.sqrt(np.trace(P[:, :3, :3], axis1=1, axis2=2))
    ori = np.degrees(np.sqrt(np.trace(P[:, 3:, 3:], axis1=1, axis2=2)) / length)
    return ModelUncertainty(len(pos), float(np.sqrt(np.mean(pos**2))), float(pos.max()),
                            float(np.sqrt(np.mean(ori**2))), float(ori.max()))
