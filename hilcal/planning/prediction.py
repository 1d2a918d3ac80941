"""The verification error a calibration will have, predicted from the poses measured so far and their noise.

The identified parameters err by δp with the least-squares sandwich covariance (AᵀA)⁻¹ Aᵀ Σ A (AᵀA)⁻¹, A the stacked
(6n, 42) pose-error Jacobian of the measured rows at the nominal geometry and Σ the pose noise of a row. A verify
pose k measured after the upload then shows the position error J_k δp + e_k, e_k the noise of that measurement
itself. The noise is a variance per pose component (x, y, z in mm, rotations in mm at the platform's characteristic
length; correlations between components are left out). It is found first in the repeated poses (the CMM's and the
machine's repeatability together): four measurements of one pose give 3 degrees of freedom per component, so each
block (position, rotation) is pooled over its three components, 9 each. Once the fit has more residual degrees of
freedom than that, it comes from the geometric fit's residuals, per component: they contain the repeats' scatter
and, when the fit leaves no lack of fit, measure the same noise with more degrees of freedom (the classical pooling
of pure error and lack of fit); when it does leave some, they measure what the verification will meet too.

When the fit's residual exceeds the repeats' noise, the model is incomplete and δp carries its misfit too: the
identification's misfit covariance (``hilcal.misfit``, the legs' discrepancy correlated over the workspace) is drawn
on top of the noise's part.

The prediction is the distribution of the maximum over the verify poses of |J_k δp + e_k|, by seeded Monte Carlo
with the same standard normal draws at every call (common random numbers: consecutive predictions differ by the
design, not by sampling). The noise level is itself uncertain: each draw scales it by sqrt(ν / χ²_ν) (the posterior
of a variance estimated with ν degrees of freedom), so the upper bound holds with few repeats too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import gammaincinv

from hilcal.error_models import pose_difference

N_PARAMETERS = 42


@dataclass(frozen=True)
class PoseNoise:
    """Pose noise of one measured row: σ per component (x, y, z mm; rotations as rad times the characteristic length,
    mm) with the degrees of freedom of each estimate.

    shared: the three components of each block (position, rotation) share one pooled estimate (and so one χ² in the
    prediction); otherwise each component has its own.
    """

    sigma_mm: tuple[float, float, float, float, float, float]
    dof: tuple[float, float, float, float, float, float]
    shared: bool
    source: str

    def __post_init__(self) -> None:
        if len(self.sigma_mm) != 6 or len(self.dof) != 6 or min(self.sigma_mm) <= 0 or min(self.dof) <= 0:
            raise ValueError(f"pose noise needs 6 positive sigmas and degrees of freedom, got {self}")

    @classmethod
    def isotropic(cls, position_mm: float, rotation_mm: float, position_dof: float, rotation_dof: float,
                  source: str) -> PoseNoise:
        """One σ for the three position components and one for the three rotation components, each pooled."""
        return cls((position_mm,) * 3 + (rotation_mm,) * 3, (position_dof,) * 3 + (rotation_dof,) * 3, True, source)

    @property
    def position_mm(self) -> float:
        """RMS of the three position components' σ (mm)."""
        return float(np.sqrt(np.mean(np.square(self.sigma_mm[:3]))))

    @property
    def rotation_mm(self) -> float:
        return float(np.sqrt(np.mean(np.square(self.sigma_mm[3:]))))

    @property
    def total_dof(self) -> float:
        """Degrees of freedom behind the whole estimate."""
        return float(self.dof[0] + self.dof[3]) if self.shared else float(sum(self.dof))

    def covariance(self) -> np.ndarray:
        """The (6, 6) diagonal covariance of one row in the residual metric."""
        return np.diag(np.square(self.sigma_mm))


def repeat_groups(commanded: np.ndarray) -> list[np.ndarray]:
    """Row indices of every pose commanded more than once (exactly the same pose), in first-visit order."""
    q = np.atleast_2d(np.asarray(commanded, dtype=float))
    _, first, inverse = np.unique(q, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    groups = [np.flatnonzero(inverse == g) for g in np.argsort(first)]
    return [g for g in groups if g.size >= 2]


def repeat_noise(commanded: np.ndarray, measured: np.ndarray, length_mm: float) -> PoseNoise | None:
    """The pose noise found in the repeated poses (None without a repeat or when they agree exactly).

    Per group the measured poses' deviations from their mean (residual metric: mm, rotations in mm at length_mm),
    pooled over the groups and over the three components of each block: dof = 3 * sum(group size - 1) per block.
    """
    groups = repeat_groups(commanded)
    if not groups:
        return None
    meas = np.atleast_2d(np.asarray(measured, dtype=float))
    dev = []
    for g in groups:
        d = pose_difference(meas[g], meas[g[0]], length_mm)
        dev.append(d - d.mean(axis=0))
    d = np.concatenate(dev)
    dof = 3.0 * sum(g.size - 1 for g in groups)
    position, rotation = float(np.sum(d[:, :3] ** 2) / dof), float(np.sum(d[:, 3:] ** 2) / dof)
    if position <= 0 or rotation <= 0:
        return None
    where = f"{len(groups)} repeated pose(s), {sum(g.size for g in groups)} measurements"
    return PoseNoise.isotropic(float(np.sqrt(position)), float(np.sqrt(rotation)), dof, dof, where)


def residual_noise(residuals: np.ndarray, jacobians: np.ndarray, note: str = "") -> PoseNoise:
    """The pose noise in a least-squares fit's residuals [n, 6], per component with its leverage-corrected dof.

    σ_k² = RSS_k / (n - h_k), h_k the sum of the hat matrix's diagonal over the rows of component k (jacobians
    [n, 6, 42] of the rows): the parameters' share of that component. Per component, because a CMM's pose noise is
    seldom isotropic (the sphere layout makes z and the rotation about it better determined).
    """
    r = np.asarray(residuals, dtype=float)
    A = np.asarray(jacobians, dtype=float).reshape(-1, N_PARAMETERS)
    leverage = np.einsum("ij,jk,ik->i", A, np.linalg.pinv(A.T @ A), A).reshape(-1, 6)
    dof = len(r) - leverage.sum(axis=0)
    sigma = np.sqrt(np.sum(r**2, axis=0) / dof)
    return PoseNoise(tuple(float(x) for x in sigma), tuple(float(x) for x in dof), False,
                     f"the geometric fit's residuals over {len(r)} rows{note}")


def parameter_covariance_parts(jacobians: np.ndarray) -> np.ndarray:
    """[6, 42, 42]: the parameter covariance per unit noise variance of each pose component.

    cov(δp) = sum_k σ_k² C_k for the unweighted least-squares fit on rows with Jacobians [n, 6, 42], C_k =
    (AᵀA)⁻¹ A_kᵀ A_k (AᵀA)⁻¹ with A_k the rows of component k. LinAlgError when the rows do not identify all 42.
    """
    J = np.asarray(jacobians, dtype=float).reshape(-1, 6, N_PARAMETERS)
    A = J.reshape(-1, N_PARAMETERS)
    if np.linalg.matrix_rank(A / np.linalg.norm(A, axis=0)) < N_PARAMETERS:
        raise np.linalg.LinAlgError(f"{len(J)} rows do not identify the {N_PARAMETERS} parameters")
    G = np.linalg.inv(A.T @ A)
    return np.stack([G @ (J[:, k].T @ J[:, k]) @ G for k in range(6)])


def _sqrt_psd(C: np.ndarray) -> np.ndarray:
    """L with L Lᵀ = C for a symmetric positive semi-definite C (eigendecomposition; tiny negatives clipped)."""
    w, V = np.linalg.eigh((C + C.T) / 2)
    return V * np.sqrt(np.clip(w, 0.0, None))


@dataclass(frozen=True)
class Draws:
    """Seeded standard draws shared by every prediction of a plan (common random numbers).

    parameters [6, 42, D]: for the part of δp that each pose component's noise makes; verify [V, 3, D]: the verify
    measurements' noise; uniform [6, D]: turned into the χ² of each component's noise level.
    """

    parameters: np.ndarray
    verify: np.ndarray
    uniform: np.ndarray
    misfit: np.ndarray = field(default_factory=lambda: np.zeros((N_PARAMETERS, 0)))
    """[42, D]: for the part of δp that the model's misfit makes (``predict_verify_max``'s misfit_covariance)."""
    _scales: dict[tuple[int, float], np.ndarray] = field(default_factory=dict, compare=False, repr=False)
    """The χ² factors already computed (a run predicts many designs under one noise estimate)."""
    _scaled: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict, compare=False,
                                                                           repr=False)
    """The draws scaled by one noise estimate (`scaled`), for the last two estimates: 20 MB each at 10000 draws."""

    @classmethod
    def seeded(cls, seed: int, n_verify: int, n_draws: int) -> Draws:
        rng = np.random.default_rng([seed, 0x9E7])
        return cls(rng.standard_normal((6, N_PARAMETERS, n_draws)), rng.standard_normal((n_verify, 3, n_draws)),
                   rng.random((6, n_draws)), rng.standard_normal((N_PARAMETERS, n_draws)))

    def chi2_scale(self, row: int, dof: float) -> np.ndarray:
        """sqrt(dof / χ²_dof) at the uniform draws of `row` (the factor on a σ estimated with dof degrees of freedom),
        kept for the last 64 (row, dof) pairs."""
        key = (row, float(dof))
        if key not in self._scales:
            if len(self._scales) >= 64:
                del self._scales[next(iter(self._scales))]
            self._scales[key] = _chi2_scale(self.uniform[row], dof)
        return self._scales[key]

    def scaled(self, noise: PoseNoise) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The draws under one noise estimate: the parameter draws [6 * 42, D] with each component's χ² factor, the
        verify noise [V, 3, D] in mm, and the maximum over the verify poses of its length [D] (the floor). They depend
        on the noise alone, so every design predicted under one estimate shares them."""
        sigma = np.asarray(noise.sigma_mm, dtype=float)
        rows = (0, 0, 0, 3, 3, 3) if noise.shared else tuple(range(6))
        key = (rows, tuple(map(float, noise.dof)), tuple(sigma[:3].tolist()))
        if key not in self._scaled:
            scale = np.stack([self.chi2_scale(row, noise.dof[k]) for k, row in enumerate(rows)])
            parameters = (self.parameters * scale[:, None, :]).reshape(len(rows) * N_PARAMETERS, -1)
            verify_noise = self.verify * (sigma[:3, None] * scale[:3])
            floor = np.linalg.norm(verify_noise, axis=1).max(axis=0)
            for array in (parameters, verify_noise, floor):
                array.flags.writeable = False
            if len(self._scaled) >= 2:
                del self._scaled[next(iter(self._scaled))]
            self._scaled[key] = (parameters, verify_noise, floor)
        return self._scaled[key]


@dataclass(frozen=True)
class VerifyPrediction:
    """The predicted maximum position error over the verify poses after the upload (mm), and its parts.

    max_mm is the median of the maximum, low_mm and upper_mm the (1 - confidence) and confidence quantiles (upper_mm
    is the one-sided upper bound: "below upper_mm with this confidence"). parameter_rms_mm is the RMS over the verify
    poses of the error that the parameters' uncertainty alone leaves (no verify noise, noise level as estimated);
    floor_upper_mm the upper bound of the maximum with perfectly known parameters (the verify noise alone).
    """

    n_rows: int
    max_mm: float
    low_mm: float
    upper_mm: float
    parameter_rms_mm: float
    floor_upper_mm: float
    confidence: float
    noise: PoseNoise
    model_incomplete: bool = False
    """The parameters' part carries the model's misfit (``hilcal.misfit``: the fit's residual exceeds the noise)."""

    def to_json(self) -> dict:
        return {"n_rows": self.n_rows, "max_mm": self.max_mm, "low_mm": self.low_mm, "upper_mm": self.upper_mm,
                "parameter_rms_mm": self.parameter_rms_mm, "floor_upper_mm": self.floor_upper_mm,
                "confidence": self.confidence, "noise_sigma_mm": list(self.noise.sigma_mm),
                "noise_dof": list(self.noise.dof), "noise_source": self.noise.source,
                "model_incomplete": self.model_incomplete}


def _chi2_scale(u: np.ndarray, dof: float) -> np.ndarray:
    """sqrt(dof / χ²_dof) at the quantiles u: the factor on a sigma estimated with dof degrees of freedom."""
    chi2 = 2.0 * gammaincinv(dof / 2.0, u)
    return np.sqrt(dof / np.maximum(chi2, 1e-300))


def predict_verify_max(row_jacobians: np.ndarray, verify_position_jacobians: np.ndarray, noise: PoseNoise,
                       draws: Draws, confidence: float = 0.95, misfit_covariance: np.ndarray | None = None
                       ) -> VerifyPrediction:
    """Distribution of max_k |J_k δp + e_k| over the verify poses (see the module docstring).

    row_jacobians [n, 6, 42] of the measured rows (repeats included), verify_position_jacobians [V, 3, 42]. Raises
    numpy's LinAlgError when the rows do not identify the 42 parameters. `misfit_covariance` (42, 42): the part of
    δp's covariance that an incomplete model's misfit adds (``hilcal.misfit``; the identification's misfit
    covariance), drawn on top of the noise's part.
    """
    if not 0.5 < confidence < 1:
        raise ValueError(f"confidence must be in (0.5, 1), got {confidence}")
    Jv = np.asarray(verify_position_jacobians, dtype=float)
    if draws.verify.shape[0] != len(Jv):
        raise ValueError(f"the draws are for {draws.verify.shape[0]} verify poses, not {len(Jv)}")
    parts = parameter_covariance_parts(row_jacobians)
    flat = Jv.reshape(-1, N_PARAMETERS)
    sigma = np.asarray(noise.sigma_mm)
    scaled_parameters, verify_noise, floor = draws.scaled(noise)
    weights = np.concatenate([flat @ _sqrt_psd(parts[k]) * sigma[k] for k in range(6)], axis=1)
    part = weights @ scaled_parameters
    extra = None if misfit_covariance is None else np.asarray(misfit_covariance, dtype=float)[:N_PARAMETERS,
                                                                                                :N_PARAMETERS]
    if extra is not None:
        part = part + flat @ _sqrt_psd(extra) @ draws.misfit
    worst = np.linalg.norm(part.reshape(Jv.shape[0], 3, -1) + verify_noise, axis=1).max(axis=0)
    low, mid, high = np.quantile(worst, [1.0 - confidence, 0.5, confidence])
    covariance = np.einsum("k,kij->ij", sigma**2, parts) + (0.0 if extra is None else extra)
    per_pose = np.einsum("vij,jk,vik->v", Jv, covariance, Jv)
    return VerifyPrediction(int(np.size(row_jacobians) // (6 * N_PARAMETERS)), float(mid), float(low), float(high),
                            float(np.sqrt(per_pose.mean())), float(np.quantile(floor, confidence)), confidence, noise,
                            extra is not None)
