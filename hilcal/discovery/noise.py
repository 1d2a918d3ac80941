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

The leg readings carry noise of their own, which no instrument source sees: the model's inputs err too (errors in
variables). A reading error e moves the predicted pose by D e (D: d pose / d leg length), so the readings add
v D Dᵀ to every pose's covariance, v the variance of one reading (``ReadingNoise``): at least the step the readings
are rounded to (step² / 12), and what the repeated poses show beyond the instrument's noise (their scatter measures
the whole repeatability). The yardstick is the instrument's part plus the readings' (``NoiseLevel.covariance``).
The temperature readings are inputs too: their noise is the `temp_c` column's scatter about its smoothing (the one
the thermal terms use, `hilcal.discovery.context.smooth_temperature`), and what the smoothing keeps of it reaches the
poses through a model's temperature terms, correlated over neighbouring rows (``temperature_noise``, worked out by
the final covariance only where the model has such terms).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.discovery.context import detect_sessions, smooth_temperature
from hilcal.kinematics import Geometry, inverse_jacobian, split_pose
from hilcal.misfit import split_noise
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
REPEATS_SOURCE = "repeated pose(s) in the recording"
"""The end of the repeats' estimate's source (after their count)."""
READING_STEPS_MM = tuple(k * 10.0**-d for d in range(7) for k in (5.0, 2.5, 2.0, 1.0))
"""Encoder steps looked for, coarsest first: 5, 2.5, 2 and 1 times a power of ten, 5 mm down to 1 nm (a finer step
cannot be told from unrounded readings)."""


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
class ReadingNoise:
    """The leg readings' own noise: the variance of one reading (mm²), where it is known from, and its map to the
    pose (module docstring)."""

    variance_mm2: float
    floor_mm2: float
    """The least variance: a reading rounded to a step errs by up to half of it, step² / 12."""
    step_mm: float
    """The step the readings are rounded to (0: unrounded)."""
    source: str
    variance_of_estimate: float
    """The variance of variance_mm2 as estimated (0 when known: the step alone)."""
    unit_covariance: np.ndarray
    """[N, 6, 6] D Dᵀ per row: the pose covariance of readings with a variance of 1 mm² (residual metric)."""

    @property
    def sigma_mm(self) -> float:
        return float(np.sqrt(self.variance_mm2))

    @property
    def covariance(self) -> np.ndarray:
        """[N, 6, 6] the readings' part of every pose's covariance."""
        return self.variance_mm2 * self.unit_covariance

    def describe(self) -> str:
        return f"leg readings {self.sigma_mm * 1000:.2f} µm each (source: {self.source})"

    def to_json(self) -> dict:
        return {"sigma_mm": self.sigma_mm, "step_mm": self.step_mm, "floor_sigma_mm": float(np.sqrt(self.floor_mm2)),
                "source": self.source, "dof": self.dof}

    @property
    def dof(self) -> float | None:
        """Degrees of freedom of the estimated variance (None when known)."""
        if self.variance_of_estimate <= 0:
            return None
        return float(2.0 * self.variance_mm2**2 / self.variance_of_estimate)


@dataclass(frozen=True)
class TemperatureNoise:
    """The temperature readings' own noise (K²) and how the smoothing carries it: smoothed = M raw."""

    variance_k2: float
    dof: float
    smoothing: np.ndarray
    """(N, N) M: each row's smoothed temperature from the raw readings of its session."""

    @property
    def sigma_k(self) -> float:
        return float(np.sqrt(self.variance_k2))

    def describe(self) -> str:
        return (f"temperature readings {self.sigma_k:.3f} K each (source: temp_c scatter about its smoothing, "
                f"{self.dof:.0f} degrees of freedom)")

    def to_json(self) -> dict:
        return {"sigma_k": self.sigma_k, "dof": self.dof,
                "source": "temp_c scatter about its smoothing over neighbouring rows"}


def temperature_noise(temp_c: np.ndarray | None, session: np.ndarray) -> TemperatureNoise | None:
    """The temperature readings' noise from their scatter about the smoothing the thermal terms use (per session:
    E|x - M x|² = sigma² tr((I - M)ᵀ (I - M)); a leg's temperature changes over minutes, so that scatter is the
    sensor's), with its degrees of freedom (Satterthwaite); None without a usable column."""
    if temp_c is None:
        return None
    x = np.asarray(temp_c, dtype=float)
    if not np.all(np.isfinite(x)):
        return None
    n = x.size
    M = np.zeros((n, n))
    for s in np.unique(session):
        rows = np.flatnonzero(session == s)
        M[np.ix_(rows, rows)] = np.column_stack([smooth_temperature(e) for e in np.eye(rows.size)])
    A = np.eye(n) - M
    B = A.T @ A
    trace, trace2 = float(np.trace(B)), float(np.sum(B * B))
    if trace <= 0:
        return None
    scatter = x - M @ x
    return TemperatureNoise(float(scatter @ scatter) / trace, trace**2 / trace2, M)


@dataclass(frozen=True)
class NoiseLevel:
    """The yardstick used (None when no source is available), every estimate found and the leg readings' part."""

    chosen: NoiseEstimate | None
    estimates: tuple[NoiseEstimate, ...]
    notes: tuple[str, ...] = ()
    readings: ReadingNoise | None = None
    """The leg readings' own noise, added to the instrument's (`chosen`) in `covariance`."""
    instrument_factor: float = 1.0
    """The factor on the chosen estimate's variance in the yardstick: 1, or pooled with the repeats' level where they
    show less."""
    dof: float | None = None
    """Degrees of freedom of the whole yardstick's level (None: stated, exact): the instrument's and the readings'
    estimates carried together."""
    instrument_dof: float | None = None
    """Degrees of freedom of the chosen estimate's level (None: stated): a repeats' 6 x 6 covariance from k contrasts
    gives about 6 k for its level."""

    @property
    def covariance(self) -> np.ndarray:
        """[N, 6, 6] the yardstick: the instrument's pose noise plus the leg readings' (module docstring)."""
        assert self.chosen is not None
        instrument = self.chosen.covariance if self.instrument_factor == 1.0 else (
            self.instrument_factor * self.chosen.covariance)
        return instrument if self.readings is None else instrument + self.readings.covariance

    def describe(self) -> str:
        """The yardstick's parts in words."""
        assert self.chosen is not None
        said = f"instrument: {self.chosen.describe()}"
        if self.instrument_factor != 1.0:
            said += f", {np.sqrt(self.instrument_factor):.2f}x as the repeated poses show"
        return said if self.readings is None else f"{said}; {self.readings.describe()}"

    def to_json(self) -> dict:
        def one(e: NoiseEstimate) -> dict:
            return {"source": e.source, "position_mm": e.position_mm, "sphere_sigma_mm": e.sphere_sigma_mm,
                    "dof": e.dof}

        return {
            "known": self.chosen is not None,
            "position_mm": None if self.chosen is None else self.chosen.position_mm,
            "source": None if self.chosen is None else self.chosen.source,
            "sphere_sigma_mm": None if self.chosen is None else self.chosen.sphere_sigma_mm,
            "instrument_factor": self.instrument_factor,
            "leg_readings": None if self.readings is None else self.readings.to_json(),
            "total_position_mm": None if self.chosen is None else float(
                np.sqrt(np.mean(np.trace(self.covariance[:, :3, :3], axis1=1, axis2=2)))),
            "dof": self.dof,
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


def reading_step_mm(legs_mm: np.ndarray) -> float:
    """The step of the recorded leg readings: the coarsest of READING_STEPS_MM that every leg's readings differ from
    its first by whole multiples of (an encoder's count need not start at zero); 0 when there is none (unrounded)."""
    legs = np.asarray(legs_mm, dtype=float)
    moves = np.concatenate([column[np.isfinite(column)] - column[np.isfinite(column)][:1] for column in legs.T])
    if not np.any(moves):
        return 0.0
    for step in READING_STEPS_MM:
        if np.max(np.abs(moves / step - np.round(moves / step))) < 1e-6 * max(1.0, 1e-3 / step):
            return step
    return 0.0


def leg_to_pose(robot: Robot, poses: np.ndarray, length_mm: float) -> np.ndarray:
    """[N, 6, 6] D = d pose / d leg length per pose (residual metric: rotations as mm at `length_mm`), of the
    nominal geometry: how a reading's error moves the pose the model predicts."""
    R, t = split_pose(np.asarray(poses, dtype=float))
    D = np.linalg.inv(inverse_jacobian(Geometry.nominal(robot), R, t))
    D[:, 3:, :] *= length_mm
    return D


def _repeat_sums(groups: list[np.ndarray], residuals: np.ndarray, *covariances: np.ndarray
                 ) -> tuple[float, list[float]]:
    """The repeats' within-group sum of squared residual deviations, and what each covariance [N, 6, 6] would make
    it on average: sum over a group of n rows of (1 - 1/n) tr S_k."""
    dev = sum(float(np.sum((residuals[g] - residuals[g].mean(axis=0)) ** 2)) for g in groups)
    expected = [sum((1.0 - 1.0 / g.size) * float(np.trace(S[g], axis1=1, axis2=2).sum()) for g in groups)
                for S in covariances]
    return dev, expected


def _repeat_dof(groups: list[np.ndarray], covariance: np.ndarray) -> float:
    """Degrees of freedom of the repeats' sum of squares under a pose covariance [N, 6, 6] (Satterthwaite: a group of
    n rows gives n - 1 contrasts, each (tr S)² / tr S² for its anisotropic 6 x 6 covariance)."""
    total = 0.0
    for g in groups:
        S = covariance[g].mean(axis=0)
        total += (g.size - 1) * float(np.trace(S) ** 2 / max(np.trace(S @ S), 1e-300))
    return total


def in_a_row(groups: list[np.ndarray]) -> list[np.ndarray]:
    """The runs of consecutive rows (at least two) within repeat groups: a pose measured again right after itself has
    the same history (the last move's direction, the warming since power-on), so the geometry's residual changes only
    by the noise; visits with other poses between them may differ by the machine's history, which is physics."""
    runs = []
    for g in groups:
        runs += [run for run in np.split(g, np.flatnonzero(np.diff(g) != 1) + 1) if run.size >= 2]
    return runs


def reading_noise(rec: Recording, robot: Robot, residuals: np.ndarray, length_mm: float,
                  instrument: NoiseEstimate, groups: list[np.ndarray]) -> tuple[ReadingNoise, float, float | None]:
    """The leg readings' noise, the instrument's factor and the degrees of freedom of the whole yardstick's level
    (None: exact). The readings' variance is at least their step's (step² / 12); with a pose measured again in a row
    (`in_a_row`: its scatter is the whole repeatability) it is what the repeats show beyond the instrument's noise,
    and where they show less, the instrument's estimate is pooled with them (``hilcal.misfit.split_noise``)."""
    D = leg_to_pose(robot, rec.meas, length_mm)
    unit = D @ np.swapaxes(D, 1, 2)
    step = reading_step_mm(rec.legs_mm)
    floor = step**2 / 12.0
    said = f"the readings' step of {step * 1000:g} µm" if step > 0 else "unrounded readings"
    a = float(np.trace(instrument.covariance, axis1=1, axis2=2).sum())
    u = float(np.trace(unit, axis1=1, axis2=2).sum())
    var_a = 2.0 * a**2 / instrument.dof if instrument.dof else 0.0

    def exact_readings(factor: float, var_factor: float) -> float | None:
        """The level's dof when the readings are at their floor (known) and the instrument's factor is estimated."""
        return None if var_factor <= 0 or a <= 0 else 2.0 * (factor * a + floor * u) ** 2 / (var_factor * a**2)

    if instrument.source.endswith(REPEATS_SOURCE):
        return ReadingNoise(0.0, 0.0, step, "within the repeated poses' scatter (the instrument's yardstick)", 0.0,
                            unit), 1.0, _repeat_dof(groups, instrument.covariance)
    groups = in_a_row(groups)
    if not groups:
        return (ReadingNoise(floor, floor, step, f"{said}; no pose measured again in a row to show more", 0.0, unit),
                1.0, exact_readings(1.0, 2.0 / instrument.dof if instrument.dof else 0.0))
    dev, (e_instrument, e_unit) = _repeat_sums(groups, residuals, instrument.covariance, unit)
    repeat_dof = _repeat_dof(groups, instrument.covariance)
    factor, variance, how = split_noise(dev, e_instrument, e_unit, repeat_dof, instrument.dof, floor,
                                        contradict=False)
    repeats = f"{len(groups)} repeated pose(s), {repeat_dof:.0f} degrees of freedom"
    if how == "within":
        return ReadingNoise(floor, floor, step, f"{said}; {repeats} show no more", 0.0, unit), 1.0, None
    if how == "pooled":
        return (ReadingNoise(floor, floor, step, f"{said}; {repeats} show no more (the instrument's estimate pooled "
                             "with them)", 0.0, unit), factor,
                exact_readings(factor, 2.0 * factor**2 / (instrument.dof + repeat_dof)))
    dof = _repeat_dof(groups, instrument.covariance + variance * unit)
    var_dev = 2.0 * dev**2 / dof
    readings = ReadingNoise(variance, floor, step, f"{repeats}: their scatter beyond the instrument's noise",
                            (var_dev + var_a * (e_instrument / max(a, 1e-300)) ** 2) / e_unit**2, unit)
    # the level T = a + v u with v = (dev - w_a a) / e_unit: an instrument set high leaves v lower (they cancel)
    w_a, w_u = e_instrument / max(a, 1e-300), e_unit / u
    var_total = var_a * (1.0 - w_a / w_u) ** 2 + var_dev / w_u**2
    return readings, 1.0, float(2.0 * (a + variance * u) ** 2 / var_total)


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
        estimates.append(NoiseEstimate(f"{len(groups)} {REPEATS_SOURCE}",
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
    readings, factor, dof = reading_noise(rec, robot, residuals, length_mm, chosen, groups)
    return NoiseLevel(chosen, tuple(estimates), tuple(notes), readings, factor, dof,
                      _repeat_dof(groups, chosen.covariance) if chosen.source.endswith(REPEATS_SOURCE) else chosen.dof)
