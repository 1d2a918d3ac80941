"""Truth physics of the simulated rig: an uncalibrated controller driving a robot with geometric errors.

Deliberately independent of the calibration code (only the declarative robot loader is shared): the
kinematics here use scipy rotations and a least-squares forward solver over a rotation vector, so a
simulation cannot agree with the fitting code merely because both share a formulation.

Truth model, per leg i: true platform joint a_i + da_i, true base joint b_i + db_i, and true geometric
leg length = reported length + dl0_i. Reported lengths are multiples of the leg resolution.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from hilcal.robot import Robot
from sim_devices.config import RigConfig

FK_TOLERANCE_MM = 1e-9


def _rotation_from_pose(pose: np.ndarray) -> Rotation:
    """Rotation of pose(s) [..., x, y, z, roll, pitch, yaw] (deg); R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return Rotation.from_euler("ZYX", np.asarray(pose)[..., [5, 4, 3]], degrees=True)


def _pose_from_rotation(rot: Rotation, t_mm: np.ndarray) -> np.ndarray:
    """[x, y, z mm, roll, pitch, yaw deg] from a rotation and a translation (intrinsic ZYX: yaw first)."""
    ypr = rot.as_euler("ZYX", degrees=True)
    return np.concatenate([np.asarray(t_mm, dtype=float), ypr[..., ::-1]], axis=-1)


class SimulatedRig:
    """A Gough platform with true geometric errors, a nominal-geometry controller and a noisy CMM."""

    def __init__(self, robot: Robot, config: RigConfig) -> None:
        self.robot = robot
        self.config = config
        da, db, dl0 = config.errors.as_arrays()
        self.a_true = robot.a + da
        self.b_true = robot.b + db
        self.dl0_mm = dl0
        self._rng = np.random.default_rng(config.seed)
        cmm = config.cmm_pose.as_array()
        self._cmm_rotation = _rotation_from_pose(cmm)
        self._cmm_translation = cmm[:3]
        self._reported = self.controller_ik(robot.home)
        self._last_rotation = _rotation_from_pose(robot.home)
        self._last_translation = robot.home[:3].copy()
        self._pose_cache: np.ndarray | None = None

    # ------------------------------------------------------------------ controller side

    def controller_ik(self, pose: np.ndarray) -> np.ndarray:
        """Leg lengths (mm) an uncalibrated controller commands for pose(s) (6,) or (N, 6), quantized."""
        p = np.asarray(pose, dtype=float)
        if p.shape[-1] != 6 or p.ndim > 2:
            raise ValueError(f"pose must have shape (6,) or (N, 6), got {p.shape}")
        R = _rotation_from_pose(p).as_matrix()
        joints = np.einsum("...jk,ik->...ij", R, self.robot.a) + p[..., None, :3]
        lengths = np.linalg.norm(joints - self.robot.b, axis=-1)
        return self._quantize(lengths)

    def _quantize(self, lengths_mm: np.ndarray) -> np.ndarray:
        res = self.config.leg_resolution_mm
        return lengths_mm if res == 0 else np.round(lengths_mm / res) * res

    def move_to_lengths(self, reported_mm: np.ndarray) -> None:
        """Drive the actuators until the controller reports these lengths (quantized to the resolution)."""
        L = np.asarray(reported_mm, dtype=float)
        if L.shape != (6,):
            raise ValueError(f"leg lengths must have shape (6,), got {L.shape}")
        lo, hi = self.robot.leg_limits
        for i, value in enumerate(L):
            if not np.isfinite(value) or not lo <= value <= hi:
                raise ValueError(f"leg {i + 1}: {value} mm is outside the leg limits [{lo}, {hi}] mm")
        self._reported = self._quantize(L)
        self._pose_cache = None

    def reported_lengths(self) -> np.ndarray:
        """Leg lengths (mm) as the controller reports them now."""
        return self._reported.copy()

    # ------------------------------------------------------------------ truth side

    def true_lengths(self, reported_mm: np.ndarray) -> np.ndarray:
        """True joint-centre distances (mm) for reported lengths: reported + dl0."""
        return np.asarray(reported_mm, dtype=float) + self.dl0_mm

    def _solve_fk(
        self, reported_mm: np.ndarray, start_rotation: Rotation, start_t_mm: np.ndarray
    ) -> tuple[Rotation, np.ndarray]:
        """FK of the true geometry; unknowns: rotation vector relative to start_rotation (rad), t (mm)."""
        target = self.true_lengths(reported_mm)
        a, b = self.a_true, self.b_true

        def residual(x: np.ndarray) -> np.ndarray:
            R = (Rotation.from_rotvec(x[:3]) * start_rotation).as_matrix()
            return np.linalg.norm(a @ R.T + x[3:] - b, axis=1) - target

        x0 = np.concatenate([np.zeros(3), start_t_mm])
        sol = least_squares(
            residual,
            x0,
            method="lm",
            x_scale=np.array([1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0]),
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=2000,
        )
        worst = float(np.max(np.abs(residual(sol.x))))
        if worst > FK_TOLERANCE_MM:
            raise RuntimeError(
                f"forward kinematics did not converge (worst leg residual {worst:.3g} mm) for reported "
                f"lengths {reported_mm.tolist()} mm; the pose may be near a singularity or unreachable"
            )
        return Rotation.from_rotvec(sol.x[:3]) * start_rotation, sol.x[3:].copy()

    def _fk_warm(self, reported_mm: np.ndarray) -> np.ndarray:
        """Solve FK starting from the previous solution and remember this one as the next start."""
        rotation, t = self._solve_fk(reported_mm, self._last_rotation, self._last_translation)
        self._last_rotation, self._last_translation = rotation, t
        return _pose_from_rotation(rotation, t)

    def true_pose(self) -> np.ndarray:
        """Actual platform pose [x, y, z mm, roll, pitch, yaw deg] for the current actuator state."""
        if self._pose_cache is None:
            self._pose_cache = self._fk_warm(self._reported)
        return self._pose_cache.copy()

    def true_poses_for_lengths(self, reported_mm: np.ndarray) -> np.ndarray:
        """Actual poses (N, 6) for reported lengths (N, 6); does not move the rig."""
        L = np.asarray(reported_mm, dtype=float)
        if L.ndim != 2 or L.shape[1] != 6:
            raise ValueError(f"leg lengths must have shape (N, 6), got {L.shape}")
        rotation, t = _rotation_from_pose(self.robot.home), self.robot.home[:3]
        out = np.empty_like(L)
        for k, lengths in enumerate(L):
            rotation, t = self._solve_fk(lengths, rotation, t)
            out[k] = _pose_from_rotation(rotation, t)
        return out

    # ------------------------------------------------------------------ CMM

    def to_cmm(self, points_base_mm: np.ndarray) -> np.ndarray:
        """Express base-frame points (..., 3) in the CMM frame (noise-free)."""
        return self._cmm_rotation.inv().apply(np.asarray(points_base_mm) - self._cmm_translation)

    def measure_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Noisy sphere centres in the CMM frame: (platform (M, 3), base (K, 3)), mm."""
        pose = self.true_pose()
        platform_base = _rotation_from_pose(pose).apply(self.robot.platform_spheres) + pose[:3]
        sigma = self.config.cmm_noise_mm
        platform = self.to_cmm(platform_base)
        base = self.to_cmm(self.robot.base_spheres)
        platform = platform + self._rng.normal(0.0, sigma, platform.shape)
        base = base + self._rng.normal(0.0, sigma, base.shape)
        return platform, base
