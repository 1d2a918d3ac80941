"""Error models: parameter names and the Jacobians that map geometric errors to residuals.

Two models:
- ``GEOMETRIC_42``: the rigid model, per leg da_i (3), db_i (3), dl0_i (1). Nonlinear and exact.
- ``PAPER_60``: the paper's eqs. 7–23, per leg dl_i, du_i (3), da_i (3), db_i (3). Linear only.

Two residual formulations for the 42-parameter model:
- forward: pose error (measured pose minus the pose forward kinematics predicts from the legs), eq. 22;
- implicit: leg-length error (length the measured pose implies minus the recorded length).

Rotations in residuals are rotation vectors in rad multiplied by a characteristic length (mm), so that
position and orientation residuals share one unit and one L-infinity bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.kinematics import N_LEGS, Geometry, leg_geometry, leg_vectors, split_pose

AXES = ("x", "y", "z")


@dataclass(frozen=True)
class ErrorModel:
    """Names and units of an error model's parameters."""

    key: str
    names: tuple[str, ...]
    units: tuple[str, ...]

    @property
    def size(self) -> int:
        return len(self.names)


def _names_42() -> tuple[tuple[str, ...], tuple[str, ...]]:
    names, units = [], []
    for i in range(1, N_LEGS + 1):
        names += [f"leg{i}_da_{a}_mm" for a in AXES] + [f"leg{i}_db_{a}_mm" for a in AXES] + [f"leg{i}_dl0_mm"]
        units += ["mm"] * 7
    return tuple(names), tuple(units)


def _names_60() -> tuple[tuple[str, ...], tuple[str, ...]]:
    names, units = [], []
    for i in range(1, N_LEGS + 1):
        names += [f"leg{i}_dl_mm"] + [f"leg{i}_du_{a}_rad" for a in AXES]
        names += [f"leg{i}_da_{a}_mm" for a in AXES] + [f"leg{i}_db_{a}_mm" for a in AXES]
        units += ["mm"] + ["rad"] * 3 + ["mm"] * 6
    return tuple(names), tuple(units)


GEOMETRIC_42 = ErrorModel("42", *_names_42())
PAPER_60 = ErrorModel("60", *_names_60())
MODELS = {"42": GEOMETRIC_42, "60": PAPER_60}


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices [..., 3, 3] with skew(v) @ w = v x w."""
    v = np.asarray(v, dtype=float)
    S = np.zeros((*v.shape, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vectors [..., 3] (rad) of rotation matrices (log map), accurate for small and large angles."""
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = 0.5 * np.linalg.norm(w, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    angle = np.arctan2(s, c)
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(s > 1e-12, angle / (2.0 * s), 0.5 + angle**2 / 12.0)
    return w * factor[..., None]


def pose_difference(measured: np.ndarray, reference: np.ndarray, length_mm: float) -> np.ndarray:
    """Residuals [..., 6]: [t_m - t_r (mm), length_mm * rotvec(R_m R_r^T)] for poses in mm/deg."""
    Rm, tm = split_pose(measured)
    Rr, tr = split_pose(reference)
    dw = rotation_vector(Rm @ np.swapaxes(Rr, -1, -2))
    return np.concatenate([tm - tr, length_mm * dw], axis=-1)


def constraint_jacobian(geom: Geometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """G [..., 6, 42]: d(geometric minus target length of leg i)/d(errors), for the rigid 42 model.

    g_i = |R (a_i + da_i) + t - (b_i + db_i)| - (L_i + dl0_i), so row i holds [u_i^T R, -u_i^T, -1]
    in the seven columns of leg i and zeros elsewhere.
    """
    _, _, u = leg_vectors(geom, R, t)
    return _constraint_rows(u, R)


def _constraint_rows(u: np.ndarray, R: np.ndarray) -> np.ndarray:
    """`constraint_jacobian` from the legs' unit directions u [..., 6, 3] and the rotations R [..., 3, 3]."""
    shape = u.shape[:-2]
    G = np.zeros((*shape, N_LEGS, 7 * N_LEGS))
    uR = np.einsum("...ij,...jk->...ik", u, R)
    for i in range(N_LEGS):
        G[..., i, 7 * i : 7 * i + 3] = uR[..., i, :]
        G[..., i, 7 * i + 3 : 7 * i + 6] = -u[..., i, :]
        G[..., i, 7 * i + 6] = -1.0
    return G


def forward_jacobian(geom: Geometry, poses: np.ndarray, length_mm: float) -> np.ndarray:
    """Pose-error Jacobian [..., 6, 42] of the rigid model: dOmega = J dp (the paper's eq. 22, rigid).

    For fixed reported leg lengths the platform moves by J_x [dt; dw] = -G dp, so J = -J_x^{-1} G,
    evaluated at the poses the geometry reaches; rotation rows are scaled by length_mm.
    """
    R, t = split_pose(poses)
    ra, v, length = leg_geometry(geom, R, t)
    u = v / length[..., None]
    Jx = np.concatenate([u, np.cross(ra, u)], axis=-1)  # inverse_jacobian
    G = _constraint_rows(u, R)
    D = -np.linalg.solve(Jx, G)
    D[..., 3:, :] *= length_mm
    return D


def implicit_residuals(geom: Geometry, legs_mm: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Leg-length residuals [..., 6] (mm): geometric length at the measured pose minus recorded + dl0."""
    R, t = split_pose(poses)
    _, length, _ = leg_vectors(geom, R, t)
    return length - (legs_mm + geom.dl0)


def implicit_jacobian(geom: Geometry, poses: np.ndarray) -> np.ndarray:
    """d(implicit residuals)/d(42 errors) [..., 6, 42] at the measured poses."""
    R, t = split_pose(poses)
    return constraint_jacobian(geom, R, t)


def paper60_jacobian(geom: Geometry, poses: np.ndarray, length_mm: float) -> np.ndarray:
    """The paper's error Jacobian J = (J_W^T J_W)^-1 J_W^T J_p (eqs. 14–23), [..., 6, 60], as written.

    Vector-chain rows (three per leg): dt + dw x (R a_i) = dl_i u_i + l_i du_i x u_i - R da_i + db_i,
    with the per-leg parameters ordered [dl, du (3), da (3), db (3)]. Rotation rows scaled by length_mm.
    """
    R, t = split_pose(poses)
    _v, length, u = leg_vectors(geom, R, t)
    ra = np.einsum("...jk,ik->...ij", R, geom.a)
    shape = u.shape[:-2]
    JW = np.zeros((*shape, 3 * N_LEGS, 6))
    Jp = np.zeros((*shape, 3 * N_LEGS, 10 * N_LEGS))
    eye = np.broadcast_to(np.eye(3), (*shape, 3, 3))
    for i in range(N_LEGS):
        rows = slice(3 * i, 3 * i + 3)
        JW[..., rows, 0:3] = eye
        JW[..., rows, 3:6] = np.swapaxes(skew(ra[..., i, :]), -1, -2)
        c = 10 * i
        Jp[..., rows, c] = u[..., i, :]
        Jp[..., rows, c + 1 : c + 4] = length[..., i, None, None] * np.swapaxes(skew(u[..., i, :]), -1, -2)
        Jp[..., rows, c + 4 : c + 7] = -R
        Jp[..., rows, c + 7 : c + 10] = eye
    JWt = np.swapaxes(JW, -1, -2)
    J = np.linalg.solve(JWt @ JW, JWt @ Jp)
    J[..., 3:, :] *= length_mm
    return J


def params42_to_60(dp42: np.ndarray) -> np.ndarray:
    """Embed rigid errors in the paper's vector: dl = dl0, du = 0, da and db copied."""
    d = np.asarray(dp42, dtype=float).reshape(N_LEGS, 7)
    out = np.zeros((N_LEGS, 10))
    out[:, 0] = d[:, 6]
    out[:, 4:7] = d[:, 0:3]
    out[:, 7:10] = d[:, 3:6]
    return out.reshape(-1)

