"""Truth physics of the simulated rig: an uncalibrated controller driving a robot with geometric errors.

Deliberately independent of the calibration code (only the declarative robot loader is shared): the
kinematics here use their own rotation helpers (sim_devices.rotation) and a Newton forward solver over a rotation
vector, so a simulation cannot agree with the fitting code merely because both share a formulation.

Truth model, per leg i: true platform joint a_i + da_i, true base joint b_i + db_i, and true joint-centre distance =
reported length + dl0_i + the corrections of the enabled non-geometric effects (sim_devices.rig.physics), which may
depend on the pose (through the leg loads and directions), the leg temperature, the motion history and the time
since the session started (sim_devices.rig.physics for the library effects, sim_devices.rig.unlisted_physics for the
out-of-library and session effects, sim_devices.rig.electric_physics for electric legs, whose homing at every
session start moves their zero). Reported lengths are multiples of the leg resolution. The rig keeps a simulated
clock that drives a drifting temperature, read by a noisy temperature sensor.
"""

from __future__ import annotations

import numpy as np

from hilcal.robot import Robot
from sim_devices.rig import electric_physics, physics, table_physics, unlisted_physics
from sim_devices.rig.config import EffectsConfig, RigConfig
from sim_devices.rig.unlisted_config import TIME_DEPENDENT_EFFECTS
from sim_devices.rotation import matrix_from_rotvec, matrix_from_rpy_deg, orthonormalized, rpy_deg_from_matrix

FK_TOLERANCE_MM = 1e-9
NEWTON_TOLERANCE_MM = 1e-11
"""Newton stops when every leg is within this of its target (well inside FK_TOLERANCE_MM)."""
NEWTON_MAX_STEPS = 12
POSE_CONVERGENCE_MM = 1e-9
MAX_EFFECT_ITERATIONS = 50


def _rotation_from_pose(pose: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of pose(s) [..., x, y, z, roll, pitch, yaw deg]; R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return matrix_from_rpy_deg(np.asarray(pose)[..., 3:])


def _pose_from_rotation(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """[x, y, z mm, roll, pitch, yaw deg] from a rotation matrix and a translation (intrinsic ZYX: yaw first)."""
    return np.concatenate([np.asarray(t_mm, dtype=float), rpy_deg_from_matrix(R)], axis=-1)


class SimulatedRig:
    """A Gough platform with true geometric errors and optional non-geometric physics, a nominal-geometry
    controller, a clock with a drifting temperature and its sensor, and a noisy CMM."""

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
        self._active_effects = config.effects.active()
        self._clock_moves_pose = _clock_moves_pose(config.effects, self._active_effects)
        self._direction = np.ones(6)
        self._last_move_mm = np.full(6, np.inf)
        self._time_s = 0.0
        self._session_start_s = 0.0
        self._session = 0
        self._stroke_range_mm = (robot.leg_limits[0] - robot.l0, robot.leg_limits[1] - robot.l0)
        home_legs = physics.platform_joints_mm(self._last_rotation, self._last_translation, self.a_true)
        home_legs = home_legs - self.b_true
        self._first_axes = unlisted_physics.hooke_first_axes(
            home_legs / np.linalg.norm(home_legs, axis=1, keepdims=True),
            config.effects.hooke_joint_offset.axis_angle_deg,
        )
        self._temperature_rng = np.random.default_rng([config.seed, 0x7E5])

    # ------------------------------------------------------------------ controller side

    def controller_ik(self, pose: np.ndarray) -> np.ndarray:
        """Leg lengths (mm) an uncalibrated controller commands for pose(s) (6,) or (N, 6), quantized."""
        p = np.asarray(pose, dtype=float)
        if p.shape[-1] != 6 or p.ndim > 2:
            raise ValueError(f"pose must have shape (6,) or (N, 6), got {p.shape}")
        R = _rotation_from_pose(p)
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
        quantized = self._quantize(L)
        if np.array_equal(quantized, self._reported):
            return  # no step: the motion history (and so the pose) stays as it is
        self._direction = physics.motion_direction(self._direction, quantized - self._reported)
        self._last_move_mm = unlisted_physics.last_move_size_mm(self._last_move_mm, quantized - self._reported)
        self._reported = quantized
        self._pose_cache = None

    def reported_lengths(self) -> np.ndarray:
        """Leg lengths (mm) as the controller reports them now."""
        return self._reported.copy()

    def motion_direction(self) -> np.ndarray:
        """(6,) direction of the last motion of each leg: +1 extended, -1 retracted (initially +1)."""
        return self._direction.copy()

    def last_move_mm(self) -> np.ndarray:
        """(6,) size of the last move of each leg, mm (initially inf: as after a long move)."""
        return self._last_move_mm.copy()

    # ------------------------------------------------------------------ clock and temperature

    @property
    def time_s(self) -> float:
        """Simulated clock, s since the rig was created."""
        return self._time_s

    def advance_time(self, seconds: float) -> None:
        """Let simulated time pass (the temperature drifts)."""
        if not np.isfinite(seconds) or seconds < 0:
            raise ValueError(f"seconds must be finite and >= 0, got {seconds}")
        self.set_time(self._time_s + seconds)

    def set_time(self, t_s: float) -> None:
        """Set the simulated clock (s)."""
        if not np.isfinite(t_s) or t_s < 0:
            raise ValueError(f"t_s must be finite and >= 0, got {t_s}")
        if self._clock_moves_pose and t_s != self._time_s:
            self._pose_cache = None
        self._time_s = float(t_s)

    def start_session(self) -> None:
        """Power-on now: the time-since-power-on of the local heating restarts (the legs cooled in between), and
        motor-encoder legs home again (a new seeded trip point of each home switch)."""
        self._session_start_s = self._time_s
        self._session += 1
        if {"local_heating", "motor_encoder", "leg_tables"}.intersection(self._active_effects):
            self._pose_cache = None

    @property
    def session(self) -> int:
        """Number of the current session: 0 from the rig's creation, +1 at every start_session (homing)."""
        return self._session

    @property
    def session_start_s(self) -> float:
        """Clock time (s) at which the current session started (0 until start_session is called)."""
        return self._session_start_s

    def true_temperature_c(self) -> float:
        """True leg temperature (°C) now."""
        return physics.leg_temperature_c(self.config.temperature, self._time_s)

    def temperature_c(self) -> float:
        """Reading of the temperature sensor (°C): the true temperature plus sensor noise."""
        noise = self._temperature_rng.normal(0.0, self.config.temperature.sensor_noise_k)
        return self.true_temperature_c() + float(noise)

    # ------------------------------------------------------------------ truth side

    def true_lengths(self, reported_mm: np.ndarray) -> np.ndarray:
        """Rigid true joint-centre distances (mm) for reported lengths: reported + dl0 (without the effects)."""
        return np.asarray(reported_mm, dtype=float) + self.dl0_mm

    def _solve_fk(
        self,
        reported_mm: np.ndarray,
        start_rotation: np.ndarray,
        start_t_mm: np.ndarray,
        corrections_mm: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """FK of the true geometry: Newton steps with the exact Jacobian from the start pose (quadratic, a few
        steps from a warm start); Levenberg-Marquardt from the same start where Newton does not converge. The rotation
        is re-orthonormalized, so rounding does not pile up over the warm starts."""
        target = self.true_lengths(reported_mm)
        if corrections_mm is not None:
            target = target + corrections_mm
        solved = _newton_fk(self.a_true, self.b_true, target, start_rotation, start_t_mm)
        if solved is None:
            solved = self._solve_fk_lm(target, start_rotation, start_t_mm, reported_mm)
        return orthonormalized(solved[0]), solved[1]

    def _solve_fk_lm(
        self, target: np.ndarray, start_rotation: np.ndarray, start_t_mm: np.ndarray, reported_mm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """FK by Levenberg-Marquardt; unknowns: rotation vector relative to start_rotation (rad), t (mm)."""
        from scipy.optimize import least_squares  # a rare fallback: scipy stays out of the simulator's start-up

        a, b = self.a_true, self.b_true

        def residual(x: np.ndarray) -> np.ndarray:
            R = matrix_from_rotvec(x[:3]) @ start_rotation
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
        return matrix_from_rotvec(sol.x[:3]) @ start_rotation, sol.x[3:].copy()

    def _corrections_at(
        self, reported_mm: np.ndarray, R: np.ndarray, t_mm: np.ndarray, history: tuple[np.ndarray, np.ndarray]
    ) -> dict[str, np.ndarray]:
        """Δl (mm) of each enabled effect with the platform at (rotation matrix R, t_mm), at the rig's current time.

        history = (direction, last move size) of each leg.
        """
        joints = physics.platform_joints_mm(R, t_mm, self.a_true)
        forces = physics.axial_leg_forces_kn(
            R, t_mm, self.a_true, self.b_true, self.robot.moving_mass_kg, self.robot.com, self.robot.gravity_mps2
        )
        leg_lengths = np.linalg.norm(joints - self.b_true, axis=1)
        effects = self.config.effects
        out = physics.length_corrections_mm(
            effects,
            reported_mm=reported_mm,
            l0_mm=self.robot.l0,
            leg_lengths_mm=leg_lengths,
            forces_kn=forces,
            temperature_c=self.true_temperature_c(),
            direction=history[0],
        )
        electric = electric_physics.electric_corrections_mm(
            effects,
            reported_mm=reported_mm,
            l0_mm=self.robot.l0,
            forces_kn=forces,
            seed=self.config.seed,
            session=self._session,
        )
        state = unlisted_physics.LegState(
            stroke_mm=electric_physics.true_stroke_mm(reported_mm, self.robot.l0, effects, electric),
            stroke_min_mm=self._stroke_range_mm[0],
            stroke_max_mm=self._stroke_range_mm[1],
            base_joints_mm=self.b_true,
            platform_joints_mm=joints,
            first_axes=self._first_axes,
            time_s=self._time_s,
            session_time_s=self._time_s - self._session_start_s,
            direction=history[0],
            last_move_mm=history[1],
        )
        out.update(unlisted_physics.unlisted_corrections_mm(effects, state, leg_lengths))
        out.update(electric)
        if effects.leg_tables.enabled:
            u = (joints - self.b_true) / leg_lengths[:, None]
            out["leg_tables"] = table_physics.table_corrections_mm(effects.leg_tables, table_physics.TableState(
                stroke_mm=np.asarray(reported_mm, dtype=float) - self.robot.l0, forces_kn=forces,
                session_time_s=self._time_s - self._session_start_s, temperature_c=self.true_temperature_c(),
                session=self._session, direction=history[0], last_move_mm=history[1], base_directions=u,
                platform_directions=u @ R,
            ))
        return out

    def _solve_pose(
        self,
        reported_mm: np.ndarray,
        start_rotation: np.ndarray,
        start_t_mm: np.ndarray,
        history: tuple[np.ndarray, np.ndarray],
    ) -> tuple[np.ndarray, np.ndarray]:
        """True pose with every enabled effect: fixed-point iteration of FK on the corrected lengths.

        The corrections depend on the pose (leg loads, leg lengths), so FK is repeated with the corrections
        of the previous solution until no platform joint moves by POSE_CONVERGENCE_MM. Without effects this
        is the plain rigid FK.
        """
        rotation, t = self._solve_fk(reported_mm, start_rotation, start_t_mm)
        if not self._active_effects:
            return rotation, t
        for _ in range(MAX_EFFECT_ITERATIONS):
            corrections = self._corrections_at(reported_mm, rotation, t, history)
            new_rotation, new_t = self._solve_fk(reported_mm, rotation, t, np.sum(list(corrections.values()), axis=0))
            moved = physics.platform_joints_mm(new_rotation, new_t, self.a_true) - (
                physics.platform_joints_mm(rotation, t, self.a_true)
            )
            rotation, t = new_rotation, new_t
            if float(np.max(np.linalg.norm(moved, axis=1))) < POSE_CONVERGENCE_MM:
                return rotation, t
        raise RuntimeError(
            f"the pose with effects {', '.join(self._active_effects)} did not converge in {MAX_EFFECT_ITERATIONS} "
            f"iterations for reported lengths {reported_mm.tolist()} mm"
        )

    def _fk_warm(self, reported_mm: np.ndarray) -> np.ndarray:
        """Solve the true pose starting from the previous solution and remember this one as the next start."""
        rotation, t = self._solve_pose(
            reported_mm, self._last_rotation, self._last_translation, (self._direction, self._last_move_mm)
        )
        self._last_rotation, self._last_translation = rotation, t
        return _pose_from_rotation(rotation, t)

    def true_pose(self) -> np.ndarray:
        """Actual platform pose [x, y, z mm, roll, pitch, yaw deg] for the current actuator state."""
        if self._pose_cache is None:
            self._pose_cache = self._fk_warm(self._reported)
        return self._pose_cache.copy()

    def true_poses_for_lengths(self, reported_mm: np.ndarray) -> np.ndarray:
        """Actual poses (N, 6) for reported lengths (N, 6) visited in order; does not move the rig.

        With effects, the sequence starts from the rig's current lengths and motion history, at the current
        time and temperature (the clock does not advance).
        """
        L = np.asarray(reported_mm, dtype=float)
        if L.ndim != 2 or L.shape[1] != 6:
            raise ValueError(f"leg lengths must have shape (N, 6), got {L.shape}")
        rotation, t = _rotation_from_pose(self.robot.home), self.robot.home[:3]
        previous, direction, move = self._reported, self._direction, self._last_move_mm
        out = np.empty_like(L)
        for k, lengths in enumerate(L):
            direction = physics.motion_direction(direction, lengths - previous)
            move = unlisted_physics.last_move_size_mm(move, lengths - previous)
            previous = lengths
            rotation, t = self._solve_pose(lengths, rotation, t, (direction, move))
            out[k] = _pose_from_rotation(rotation, t)
        return out

    def leg_forces_kn(self) -> np.ndarray:
        """(6,) axial leg compressions (kN) holding the moving mass at the true pose."""
        pose = self.true_pose()
        return physics.axial_leg_forces_kn(
            _rotation_from_pose(pose),
            pose[:3],
            self.a_true,
            self.b_true,
            self.robot.moving_mass_kg,
            self.robot.com,
            self.robot.gravity_mps2,
        )

    def length_corrections_mm(self) -> dict[str, np.ndarray]:
        """Δl (mm, (6,)) of each enabled effect at the true pose, the current time and motion history."""
        pose = self.true_pose()
        return self._corrections_at(
            self._reported, _rotation_from_pose(pose), pose[:3], (self._direction, self._last_move_mm)
        )

    # ------------------------------------------------------------------ CMM

    def to_cmm(self, points_base_mm: np.ndarray) -> np.ndarray:
        """Express base-frame points (..., 3) in the CMM frame (noise-free)."""
        return (np.asarray(points_base_mm) - self._cmm_translation) @ self._cmm_rotation

    def measure_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Noisy sphere centres in the CMM frame: (platform (M, 3), base (K, 3)), mm."""
        pose = self.true_pose()
        platform_base = self.robot.platform_spheres @ _rotation_from_pose(pose).T + pose[:3]
        sigma = self.config.cmm_noise_mm
        platform = self.to_cmm(platform_base)
        base = self.to_cmm(self.robot.base_spheres)
        if self.config.cmm_noise_model == "gaussian":
            platform = platform + self._rng.normal(0.0, sigma, platform.shape)
            base = base + self._rng.normal(0.0, sigma, base.shape)
            return platform, base
        noisy = []
        for points in (platform, base):
            noise = physics.cmm_noise_mm(
                self._rng,
                points,
                sigma,
                self.config.cmm_noise_model,
                reference_distance_mm=self.config.cmm_noise_reference_distance_mm,
                student_t_dof=self.config.cmm_noise_student_t_dof,
            )
            noisy.append(points + noise)
        return noisy[0], noisy[1]


def _clock_moves_pose(effects: EffectsConfig, active: list[str] | tuple[str, ...]) -> bool:
    """Whether the platform moves when only the clock does: an effect that follows the time or the temperature (leg
    tables only where one is read against the session time or the temperature)."""
    timed = TIME_DEPENDENT_EFFECTS.intersection(active) - {"leg_tables"}
    clocked_tables = "leg_tables" in active and any(
        table.variable in ("session_time_s", "temp_c") for table in effects.leg_tables.tables)
    return bool(timed) or clocked_tables


def _newton_fk(
    a: np.ndarray, b: np.ndarray, target_mm: np.ndarray, R: np.ndarray, t_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """Rigid FK by Newton's method: leg i's length |R a_i + t - b_i| changes by u_i . dt + (R a_i x u_i) . w for a
    small rotation w applied on the left and a shift dt. None when it does not reach FK_TOLERANCE_MM in a few
    steps (far start, near a singularity): the caller falls back to a damped solver."""
    t = np.array(t_mm, dtype=float)
    for _ in range(NEWTON_MAX_STEPS):
        p = a @ R.T
        d = p + t - b
        lengths = np.linalg.norm(d, axis=1)
        r = lengths - target_mm
        if float(np.max(np.abs(r))) < NEWTON_TOLERANCE_MM:
            return R, t
        u = d / lengths[:, None]
        J = np.hstack([np.cross(p, u), u])
        try:
            step = np.linalg.solve(J, -r)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(step)) or float(np.linalg.norm(step[:3])) > 0.5:
            return None
        R = matrix_from_rotvec(step[:3]) @ R
        t = t + step[3:]
    return None
