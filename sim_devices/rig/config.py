"""Configuration of the simulated rig: true geometric errors, non-geometric effects, temperature, noise, CMM.

Lengths are mm and angles degrees unless a field name says otherwise. The geometric errors are the "truth"
that a calibration should recover: per leg a platform-joint error da (platform frame), a base-joint error
db (base frame) and a stroke-zero length error dl0 (true geometric length = reported length + dl0). The
non-geometric effects (all off by default) are the physics a rigid model leaves out.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from hilcal.robot import Robot, default_robot
from sim_devices.config_base import Effect as _Effect
from sim_devices.config_base import PerLeg, per_leg
from sim_devices.config_base import Strict as _Strict
from sim_devices.config_base import check_non_negative as _check_non_negative
from sim_devices.rig.electric_config import ELECTRIC_EFFECT_NAMES, DriveComplianceConfig, MotorEncoderConfig
from sim_devices.rig.table_config import LegTablesConfig
from sim_devices.rig.unlisted_config import (
    PARTLY_LISTED_EFFECT_NAMES,
    SESSION_EFFECT_NAMES,
    UNLISTED_EFFECT_NAMES,
    CyclicStrokeErrorConfig,
    FrictionHysteresisConfig,
    HookeJointOffsetConfig,
    LocalHeatingConfig,
    TransducerBowConfig,
    ZeroShiftConfig,
)
from sim_devices.rotation import matrix_from_rpy_deg

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]

PAPER_ERRORS_FILE = Path(__file__).parent / "data" / "paper_errors.toml"
BUILTIN_ERROR_SETS = ("table2", "table3", "table4", "table5", "zero")
PARAMETERS_PER_LEG = 7


class LegErrors(_Strict):
    """Geometric errors of one leg, mm."""

    da_mm: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0], description="platform joint error")
    db_mm: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0], description="base joint error")
    dl0_mm: float = Field(default=0.0, description="true geometric length minus reported length")


class GeometryErrors(_Strict):
    """Errors of all six legs (the 42 parameters of the rigid error model)."""

    legs: Annotated[list[LegErrors], Field(min_length=6, max_length=6)]

    @classmethod
    def zero(cls) -> GeometryErrors:
        """A perfect robot."""
        return cls(legs=[LegErrors() for _ in range(6)])

    @classmethod
    def from_arrays(cls, da_mm: np.ndarray, db_mm: np.ndarray, dl0_mm: np.ndarray) -> GeometryErrors:
        """Build from (6, 3), (6, 3), (6,) arrays."""
        da, db, dl0 = (np.asarray(x, dtype=float) for x in (da_mm, db_mm, dl0_mm))
        if da.shape != (6, 3) or db.shape != (6, 3) or dl0.shape != (6,):
            raise ValueError(f"expected shapes (6, 3), (6, 3), (6,); got {da.shape}, {db.shape}, {dl0.shape}")
        return cls(
            legs=[
                LegErrors(da_mm=da[i].tolist(), db_mm=db[i].tolist(), dl0_mm=float(dl0[i])) for i in range(6)
            ]
        )

    @classmethod
    def from_vector(cls, v: np.ndarray) -> GeometryErrors:
        """Inverse of ``to_vector``: 42 values, per leg [da_x, da_y, da_z, db_x, db_y, db_z, dl0]."""
        p = np.asarray(v, dtype=float)
        if p.shape != (6 * PARAMETERS_PER_LEG,):
            raise ValueError(f"expected {6 * PARAMETERS_PER_LEG} values, got shape {p.shape}")
        p = p.reshape(6, PARAMETERS_PER_LEG)
        return cls.from_arrays(p[:, 0:3], p[:, 3:6], p[:, 6])

    def as_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(da (6, 3), db (6, 3), dl0 (6,)) in mm."""
        da = np.array([leg.da_mm for leg in self.legs], dtype=float)
        db = np.array([leg.db_mm for leg in self.legs], dtype=float)
        dl0 = np.array([leg.dl0_mm for leg in self.legs], dtype=float)
        return da, db, dl0

    def to_vector(self) -> np.ndarray:
        """42 values, per leg [da_x, da_y, da_z, db_x, db_y, db_z, dl0] (mm)."""
        da, db, dl0 = self.as_arrays()
        return np.column_stack([da, db, dl0]).reshape(-1)


class CmmPose(_Strict):
    """Placement of the CMM frame in the base frame: p_base = R p_cmm + t, R = Rz(yaw) Ry(pitch) Rx(roll)."""

    x_mm: float
    y_mm: float
    z_mm: float
    roll_deg: float
    pitch_deg: float
    yaw_deg: float

    def as_array(self) -> np.ndarray:
        """[x, y, z mm, roll, pitch, yaw deg]."""
        return np.array([self.x_mm, self.y_mm, self.z_mm, self.roll_deg, self.pitch_deg, self.yaw_deg])


def random_cmm_pose(seed: int) -> CmmPose:
    """A seeded arbitrary CMM placement: any heading, a few degrees of tilt, a few metres away."""
    rng = np.random.default_rng([seed, 0xC33])
    xyz = rng.uniform(-4000.0, 4000.0, 3)
    roll, pitch = rng.uniform(-3.0, 3.0, 2)
    yaw = rng.uniform(0.0, 360.0)
    return CmmPose(
        x_mm=float(xyz[0]),
        y_mm=float(xyz[1]),
        z_mm=float(xyz[2]),
        roll_deg=float(roll),
        pitch_deg=float(pitch),
        yaw_deg=float(yaw),
    )


class LegComplianceConfig(_Effect):
    """Structural leg compliance: Δl_i = -c_i F_i, F_i the axial compression (kN) from the platform statics."""

    c_mm_per_kn: PerLeg = Field(default=0.005, description="compliance per leg (or one for all), mm/kN")

    _non_negative = field_validator("c_mm_per_kn")(_check_non_negative)


class SensorScaleConfig(_Effect):
    """Transducer gain error: reported stroke = true stroke (1 + g_i), stroke = length - l0."""

    gain_error_ppm: PerLeg = Field(default=50.0, description="gain error per leg (or one for all), ppm")

    @field_validator("gain_error_ppm")
    @classmethod
    def _above_minus_one(cls, value: float | list[float]) -> float | list[float]:
        if np.any(per_leg(value) <= -1e6):
            raise ValueError(f"a gain error must be above -1e6 ppm, got {value}")
        return value


class ThermalExpansionConfig(_Effect):
    """Thermal growth of the legs: Δl_i = alpha L_i (T - T_ref), L_i the current leg length, T the leg temperature."""

    alpha_ppm_per_k: PerLeg = Field(default=11.5, description="expansion coefficient per leg (or one), ppm/K")
    t_ref_c: float = Field(default=20.0, description="temperature at which the leg lengths are nominal, °C")


class JointBacklashConfig(_Effect):
    """Backlash: Δl_i = +b_i/2 after the leg last extended, -b_i/2 after it last retracted (moves < 1 µm keep it)."""

    backlash_mm: PerLeg = Field(default=0.03, description="backlash per leg (or one for all), mm")

    _non_negative = field_validator("backlash_mm")(_check_non_negative)


class OilColumnComplianceConfig(_Effect):
    """Oil-column compliance growing with the oil volume: Δl_i = -kappa_i F_i (s_i + s_dead), s_i the stroke in m."""

    kappa_mm_per_kn_m: PerLeg = Field(
        default=0.006, description="compliance per kN and per metre of oil column, per leg (or one), mm/(kN m)"
    )
    dead_length_m: float = Field(default=0.15, ge=0, description="dead oil volume as an equivalent length, m")

    _non_negative = field_validator("kappa_mm_per_kn_m")(_check_non_negative)


EFFECT_NAMES = ("leg_compliance", "sensor_scale", "thermal_expansion", "joint_backlash", "oil_column_compliance")
"""The effects that the calibration tool's diagnosis has candidates for (its library)."""

TABLE_EFFECT_NAMES = ("leg_tables",)
"""The generic per-leg effect a twin learns (sim_devices.rig.table_config)."""

ALL_EFFECT_NAMES = (
    *EFFECT_NAMES, *UNLISTED_EFFECT_NAMES, *PARTLY_LISTED_EFFECT_NAMES, *SESSION_EFFECT_NAMES, *ELECTRIC_EFFECT_NAMES,
    *TABLE_EFFECT_NAMES,
)


class EffectsConfig(_Strict):
    """The non-geometric truth physics of the rig; every effect is off by default.

    The first five are the diagnosis library's effects; the out-of-library and session effects are configured
    in sim_devices.rig.unlisted_config, the electric legs' (motor encoder, drive compliance) in
    sim_devices.rig.electric_config, the per-leg tables a twin learns in sim_devices.rig.table_config. Any
    combination may be enabled: the rig adds their Δl.
    """

    leg_compliance: LegComplianceConfig = Field(default_factory=LegComplianceConfig)
    sensor_scale: SensorScaleConfig = Field(default_factory=SensorScaleConfig)
    thermal_expansion: ThermalExpansionConfig = Field(default_factory=ThermalExpansionConfig)
    joint_backlash: JointBacklashConfig = Field(default_factory=JointBacklashConfig)
    oil_column_compliance: OilColumnComplianceConfig = Field(default_factory=OilColumnComplianceConfig)
    transducer_bow: TransducerBowConfig = Field(default_factory=TransducerBowConfig)
    cyclic_stroke_error: CyclicStrokeErrorConfig = Field(default_factory=CyclicStrokeErrorConfig)
    hooke_joint_offset: HookeJointOffsetConfig = Field(default_factory=HookeJointOffsetConfig)
    local_heating: LocalHeatingConfig = Field(default_factory=LocalHeatingConfig)
    friction_hysteresis: FrictionHysteresisConfig = Field(default_factory=FrictionHysteresisConfig)
    zero_shift: ZeroShiftConfig = Field(default_factory=ZeroShiftConfig)
    motor_encoder: MotorEncoderConfig = Field(default_factory=MotorEncoderConfig)
    drive_compliance: DriveComplianceConfig = Field(default_factory=DriveComplianceConfig)
    leg_tables: LegTablesConfig = Field(default_factory=LegTablesConfig)

    def active(self) -> tuple[str, ...]:
        """Names of the enabled effects, in ALL_EFFECT_NAMES order (library, out-of-library, session, electric)."""
        return tuple(name for name in ALL_EFFECT_NAMES if getattr(self, name).enabled)


# Scale-1 magnitudes of concealed_effect_config (see its docstring for the resulting leg-length signatures).
CONCEALED_COMPLIANCE_MM_PER_KN = (0.004, 0.006)
CONCEALED_GAIN_ERROR_PPM = (30.0, 80.0)
CONCEALED_ALPHA_PPM_PER_K = (11.0, 12.0)
CONCEALED_BACKLASH_MM = (0.02, 0.05)
CONCEALED_KAPPA_MM_PER_KN_M = (0.005, 0.007)


def concealed_effect_config(effect_name: str, magnitude_scale: float, seed: int) -> EffectsConfig:
    """One effect enabled with realistic, seeded magnitudes for a 4000 kg platform on 4.3 m hydraulic legs.

    "none" gives all effects off. Per-leg values are drawn uniformly from the ranges below (seeded) and
    multiplied by magnitude_scale. Leg-length signature at scale 1 = spread (max - min over the poses) of
    Δl_i, measured on the paper robot with Table 2 errors over the 56-pose run of ``hilcal simulate`` (the
    32 D-optimal + 24 verification poses of seed 0, 45 s per pose; rig and effect seeds 0-4): tens of µm,
    far below the mm geometric errors, a few times the 5 µm CMM noise. Axial loads: 9.1 kN per leg at
    home, 3.9-14.4 kN over the run.

    - leg_compliance: c = 0.004-0.006 mm/kN per leg (a stiffness of ~200 kN/mm): Δl ≈ -45 µm at home,
      spread 37-56 µm.
    - sensor_scale: g = ±(30-80) ppm per leg (random sign), strokes 0-1000 mm: spread 31-79 µm.
    - thermal_expansion: alpha = 11-12 ppm/K (steel, one value for all legs), T_ref = 20 °C, i.e. ~50 µm/K
      on a 4.3 m leg; with the rig's default drift (0.5-2 K/h + 0.3 K oscillation) the 42-min run changes
      T by ~0.9-1.6 K: spread 42-80 µm (mean offset 75-110 µm, absorbed by dl0).
    - joint_backlash: b = 0.02-0.05 mm per leg, Δl = ±b/2: spread = b = 20-47 µm.
    - oil_column_compliance: kappa = 0.005-0.007 mm/(kN m) per leg, s_dead = 0.15 m; F (s + s_dead) is
      ~5.9 kN m at home: Δl ≈ -32 µm on average, spread 30-48 µm.
    """
    if magnitude_scale < 0:
        raise ValueError(f"magnitude_scale must be >= 0, got {magnitude_scale}")
    if effect_name == "none":
        return EffectsConfig()
    if effect_name not in EFFECT_NAMES:
        raise ValueError(f"unknown effect {effect_name!r}; expected one of none, {', '.join(EFFECT_NAMES)}")
    rng = np.random.default_rng([seed, 0xEFF, EFFECT_NAMES.index(effect_name)])

    def draw(bounds: tuple[float, float]) -> np.ndarray:
        return rng.uniform(*bounds, 6) * magnitude_scale

    effect: _Effect
    if effect_name == "leg_compliance":
        effect = LegComplianceConfig(enabled=True, c_mm_per_kn=draw(CONCEALED_COMPLIANCE_MM_PER_KN).tolist())
    elif effect_name == "sensor_scale":
        sign = rng.choice([-1.0, 1.0], 6)
        effect = SensorScaleConfig(enabled=True, gain_error_ppm=(sign * draw(CONCEALED_GAIN_ERROR_PPM)).tolist())
    elif effect_name == "thermal_expansion":
        alpha = float(rng.uniform(*CONCEALED_ALPHA_PPM_PER_K) * magnitude_scale)
        effect = ThermalExpansionConfig(enabled=True, alpha_ppm_per_k=alpha)
    elif effect_name == "joint_backlash":
        effect = JointBacklashConfig(enabled=True, backlash_mm=draw(CONCEALED_BACKLASH_MM).tolist())
    else:
        effect = OilColumnComplianceConfig(enabled=True, kappa_mm_per_kn_m=draw(CONCEALED_KAPPA_MM_PER_KN_M).tolist())
    return EffectsConfig.model_validate({effect_name: effect})


class TemperatureConfig(_Strict):
    """Leg (= ambient) temperature over the rig's clock: T(t) = T0 + drift t / 3600 + A sin(2 pi t / period), or a
    recorded history (table_time_s, table_c: linear interpolation, held at the ends) that replaces the model."""

    t0_c: float = Field(default=21.0, description="temperature at t = 0, °C")
    drift_k_per_h: float = Field(default=1.0, description="linear drift, K/h")
    amplitude_k: float = Field(default=0.3, ge=0, description="amplitude of the periodic part, K")
    period_s: float = Field(default=5400.0, gt=0, description="period of the periodic part, s")
    sensor_noise_k: float = Field(default=0.05, ge=0, description="std of the temperature sensor noise, K")
    table_time_s: list[float] | None = Field(default=None, description="rig clock of a recorded history, s")
    table_c: list[float] | None = Field(default=None, description="leg temperature at those times, °C")

    @model_validator(mode="after")
    def _history(self) -> TemperatureConfig:
        if (self.table_time_s is None) != (self.table_c is None):
            raise ValueError("table_time_s and table_c go together")
        if self.table_time_s is not None and self.table_c is not None:
            if len(self.table_time_s) != len(self.table_c) or not self.table_time_s:
                raise ValueError("table_time_s and table_c must have the same, non-zero length")
            if np.any(np.diff(self.table_time_s) < 0):
                raise ValueError("table_time_s must not decrease")
        return self


def random_temperature(seed: int) -> TemperatureConfig:
    """A seeded drifting temperature: T0 20-22 °C, drift 0.5-2 K/h, 0.3 K oscillation with a 1-2 h period."""
    rng = np.random.default_rng([seed, 0x7E3])
    return TemperatureConfig(
        t0_c=float(rng.uniform(20.0, 22.0)),
        drift_k_per_h=float(rng.uniform(0.5, 2.0)),
        amplitude_k=0.3,
        period_s=float(rng.uniform(3600.0, 7200.0)),
        sensor_noise_k=0.05,
    )


class RigConfig(_Strict):
    """Everything that makes one simulated rig: truth errors, noise, resolution, CMM placement, seed."""

    seed: int = 0
    errors: GeometryErrors
    cmm_noise_mm: float = Field(default=0.005, ge=0, description="std of noise per sphere-centre coordinate")
    leg_resolution_mm: float = Field(
        default=0.001, ge=0, description="reported lengths are multiples of this"
    )
    cmm_pose: CmmPose = Field(description="CMM frame in the base frame; default: random_cmm_pose(seed)")
    cmm_noise_model: Literal["gaussian", "distance", "student_t"] = Field(
        default="gaussian",
        description="gaussian: std cmm_noise_mm; distance: std cmm_noise_mm (1 + d / reference distance), d the "
        "distance from the CMM origin; student_t: heavy tails with std cmm_noise_mm",
    )
    cmm_noise_reference_distance_mm: float = Field(default=2000.0, gt=0, description="d_ref of the distance model")
    cmm_noise_student_t_dof: float = Field(default=3.0, gt=2, description="degrees of freedom of the student_t model")
    effects: EffectsConfig = Field(default_factory=EffectsConfig, description="non-geometric physics, all off")
    temperature: TemperatureConfig = Field(description="leg temperature model; default: random_temperature(seed)")

    @model_validator(mode="before")
    @classmethod
    def _seeded_defaults(cls, data: Any) -> Any:
        """Fill in the seeded CMM placement and temperature model so the resolved config records them explicitly."""
        if not isinstance(data, dict):
            return data
        seed = data.get("seed", 0)
        seed = seed if isinstance(seed, int) else 0
        if data.get("cmm_pose") is None:
            data = {**data, "cmm_pose": random_cmm_pose(seed)}
        if data.get("temperature") is None:
            data = {**data, "temperature": random_temperature(seed)}
        return data


def _home_leg_directions(robot: Robot) -> np.ndarray:
    """(6, 3) unit leg vectors at the home pose with the nominal geometry."""
    home = robot.home
    R = matrix_from_rpy_deg(home[3:])
    legs = robot.a @ R.T + home[:3] - robot.b
    return legs / np.linalg.norm(legs, axis=1, keepdims=True)


def _errors_from_table(table: dict[str, Any], robot: Robot, source: str) -> GeometryErrors:
    """Parse ``legs = [{da_mm, db_mm, dl0_mm | dl_mm}, ...]``; a dl_mm vector is projected on the leg."""
    legs = table.get("legs")
    if not isinstance(legs, list) or len(legs) != 6:
        raise ValueError(f"{source}: expected exactly 6 [[legs]] entries")
    u = _home_leg_directions(robot)
    parsed = []
    for i, leg in enumerate(legs):
        if not isinstance(leg, dict):
            raise ValueError(f"{source}: leg {i + 1} is not a table")
        entry = dict(leg)
        if "dl_mm" in entry:
            if "dl0_mm" in entry:
                raise ValueError(f"{source}: leg {i + 1} gives both dl_mm (vector) and dl0_mm (scalar)")
            dl = np.asarray(entry.pop("dl_mm"), dtype=float)
            if dl.shape != (3,):
                raise ValueError(f"{source}: leg {i + 1} dl_mm must have 3 values")
            entry["dl0_mm"] = float(u[i] @ dl)
        parsed.append(entry)
    try:
        return GeometryErrors(legs=parsed)
    except ValidationError as err:
        raise ValueError(f"{source}: invalid geometry errors:\n{err}") from None


def load_errors(path_or_name: str | Path, robot: Robot | None = None) -> GeometryErrors:
    """Errors from a TOML file or a built-in set (``table2``..``table5`` of the paper, ``zero``).

    A file holds six ``[[legs]]`` tables with ``da_mm``, ``db_mm`` and either a scalar ``dl0_mm`` or the
    paper's leg-vector error ``dl_mm``. A vector is mapped to dl0_i = u_i . dl_i, u_i the unit leg direction
    at the home pose of the nominal ``robot`` (default: the paper's Table 1 robot): a rigid 42-parameter
    model has one length error per leg, and the part of dl_i across the leg is a direction change that is
    already fixed by the joint errors da_i, db_i.
    """
    robot = robot or default_robot()
    name = str(path_or_name)
    if name == "zero":
        return GeometryErrors.zero()
    if name in BUILTIN_ERROR_SETS:
        with open(PAPER_ERRORS_FILE, "rb") as fh:
            return _errors_from_table(tomllib.load(fh)[name], robot, f"built-in {name}")
    path = Path(path_or_name)
    try:
        text = path.read_text()
    except OSError as err:
        raise ValueError(
            f"errors {name!r}: not a built-in set ({', '.join(BUILTIN_ERROR_SETS)}) "
            f"and cannot read the file: "
            f"{err.strerror}"
        ) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"errors file {path}: not valid TOML: {err}") from None
    return _errors_from_table(data, robot, f"errors file {path}")


def errors_toml(errors: GeometryErrors, header: str = "") -> str:
    """The errors as a TOML file that ``load_errors`` reads back: six ``[[legs]]`` with da_mm, db_mm, dl0_mm."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    for leg in errors.legs:
        lines += ["", "[[legs]]", f"da_mm = {[float(v) for v in leg.da_mm]!r}",
                  f"db_mm = {[float(v) for v in leg.db_mm]!r}", f"dl0_mm = {float(leg.dl0_mm)!r}"]
    return "\n".join(lines).lstrip("\n") + "\n"


def random_errors(seed: int, sigma_mm: float) -> GeometryErrors:
    """All 42 parameters drawn independently from N(0, sigma_mm^2) with a seeded generator."""
    if sigma_mm < 0:
        raise ValueError(f"sigma_mm must be >= 0, got {sigma_mm}")
    rng = np.random.default_rng([seed, 0xE77])
    return GeometryErrors.from_vector(rng.normal(0.0, sigma_mm, 6 * PARAMETERS_PER_LEG))
