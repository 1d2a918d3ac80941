"""Robot definition: joint geometry, workspace, leg limits, mass and CMM sphere layout.

A robot file is TOML validated by pydantic; every user-facing quantity is in mm, degrees, kg.
The built-in default is the robot of the paper's Table 1 (``hilcal/data/paper_table1.toml``).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Range = Annotated[list[float], Field(min_length=2, max_length=2)]

POSE_AXES = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")


class RobotFileError(ValueError):
    """A robot file that cannot be read or does not describe a valid robot."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class LegSpec(_Strict):
    """One leg: platform joint a (platform frame), base joint b (base frame), stroke-zero length."""

    a_mm: Vec3
    b_mm: Vec3
    l0_mm: float = Field(gt=0, description="leg length (joint centre to joint centre) at zero transducer stroke")


class PoseSpec(_Strict):
    x_mm: float = 0.0
    y_mm: float = 0.0
    z_mm: float
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0

    def as_array(self) -> np.ndarray:
        return np.array([getattr(self, k) for k in POSE_AXES])


class WorkspaceSpec(_Strict):
    """Axis-aligned bounds of the commanded pose, [low, high] per axis."""

    x_mm: Range
    y_mm: Range
    z_mm: Range
    roll_deg: Range
    pitch_deg: Range
    yaw_deg: Range

    @model_validator(mode="after")
    def _ordered(self) -> WorkspaceSpec:
        for axis in POSE_AXES:
            lo, hi = getattr(self, axis)
            if not lo < hi:
                raise ValueError(f"workspace.{axis}: low ({lo}) must be below high ({hi})")
        for axis in ("roll_deg", "pitch_deg"):
            lo, hi = getattr(self, axis)
            if lo <= -90 or hi >= 90:
                raise ValueError(f"workspace.{axis}: must lie inside (-90, 90) degrees")
        return self

    def bounds(self) -> np.ndarray:
        """(6, 2) array of [low, high] in mm and degrees, in POSE_AXES order."""
        return np.array([getattr(self, k) for k in POSE_AXES], dtype=float)


class LegLimitSpec(_Strict):
    min_mm: float = Field(gt=0)
    max_mm: float = Field(gt=0)

    @model_validator(mode="after")
    def _ordered(self) -> LegLimitSpec:
        if not self.min_mm < self.max_mm:
            raise ValueError(f"leg_limits: min_mm ({self.min_mm}) must be below max_mm ({self.max_mm})")
        return self


class MassSpec(_Strict):
    """Moving mass (platform and payload); gravity acts along -z of the base frame."""

    moving_mass_kg: float = Field(gt=0)
    com_mm: Vec3 = Field(description="centre of mass in the platform frame")
    gravity_mps2: float = Field(default=9.80665, gt=0)


class CmmSpec(_Strict):
    """Centres of the tooling spheres: three on the platform (platform frame), three on the base."""

    platform_spheres_mm: Annotated[list[Vec3], Field(min_length=3)]
    base_spheres_mm: Annotated[list[Vec3], Field(min_length=3)]
    sphere_radius_mm: float = Field(default=12.7, gt=0, description="radius of the tooling spheres")
    sphere_sigma_mm: float | None = Field(
        default=None, gt=0, description="standard uncertainty of one measured sphere-centre coordinate (optional)")

    @field_validator("platform_spheres_mm", "base_spheres_mm")
    @classmethod
    def _not_collinear(cls, v: list[list[float]]) -> list[list[float]]:
        p = np.asarray(v, dtype=float)
        centred = p - p.mean(axis=0)
        s = np.linalg.svd(centred, compute_uv=False)
        if s[1] < 10.0:
            raise ValueError("spheres are (nearly) collinear: they cannot define a frame (need a triangle > 10 mm)")
        return v


ActuatorKind = Literal["hydraulic", "electric"]
TransducerKind = Literal["linear", "motor_encoder"]
DEFAULT_TRANSDUCER: dict[str, str] = {"hydraulic": "linear", "electric": "motor_encoder"}
"""The usual leg-length sensor of each actuator kind, when the robot file names only the kind."""


class ActuatorSpec(_Strict):
    """What the legs are: it decides which physics can be missing (oil columns only in hydraulic legs, ...)."""

    kind: ActuatorKind = Field(description="hydraulic cylinders or electric (screw or belt) drives")
    transducer: TransducerKind | None = Field(
        default=None, description="linear: a length sensor on the leg (magnetostrictive, LVDT, linear scale); "
        "motor_encoder: motor counts through a screw, belt or gears. Default: linear for hydraulic legs, "
        "motor_encoder for electric ones")


class ToleranceSpec(_Strict):
    """How far the machine as built may be from this file before anything is measured (standard deviations): the
    run's acquisition predicts the first poses from these, and refits them as poses are measured."""

    joint_mm: float = Field(default=2.0, gt=0, description="joint centre positions, per coordinate")
    leg_offset_mm: float = Field(default=3.0, gt=0, description="leg lengths at zero stroke (leg offsets)")
    reading_scale_pct: float = Field(default=2.0, gt=0, le=50, description="the gradient of each leg's reading")
    misfit_mm: float = Field(default=0.02, gt=0, description="least leg-length misfit of a rigid model: resolution, "
                             "the physics it leaves out")


class RobotSpec(_Strict):
    """The whole robot file."""

    name: str = "robot"
    legs: Annotated[list[LegSpec], Field(min_length=6, max_length=6)]
    home: PoseSpec
    workspace: WorkspaceSpec
    leg_limits: LegLimitSpec
    mass: MassSpec
    cmm: CmmSpec
    actuators: ActuatorSpec | None = Field(default=None, description="the legs' kind; None: unknown")
    tolerances: ToleranceSpec = Field(default_factory=ToleranceSpec)

    @model_validator(mode="after")
    def _consistent(self) -> RobotSpec:
        a = np.array([leg.a_mm for leg in self.legs])
        b = np.array([leg.b_mm for leg in self.legs])
        for name, pts in (("a_mm", a), ("b_mm", b)):
            d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2) + np.eye(6) * 1e9
            i, j = np.unravel_index(np.argmin(d), d.shape)
            if d[i, j] < 1.0:
                raise ValueError(f"legs {i + 1} and {j + 1} have coincident {name} joints")
        home = self.home.as_array()
        bounds = self.workspace.bounds()
        for k, axis in enumerate(POSE_AXES):
            if not bounds[k, 0] <= home[k] <= bounds[k, 1]:
                raise ValueError(f"home.{axis} = {home[k]} lies outside workspace.{axis} {list(bounds[k])}")
        R = rotation_matrix(np.radians(home[3:]))
        lengths = np.linalg.norm(a @ R.T + home[:3] - b, axis=1)
        for i, length in enumerate(lengths):
            if not self.leg_limits.min_mm <= length <= self.leg_limits.max_mm:
                raise ValueError(
                    f"leg {i + 1} length at home is {length:.3f} mm, outside leg_limits "
                    f"[{self.leg_limits.min_mm}, {self.leg_limits.max_mm}]"
                )
        return self


def rotation_matrix(rpy_rad: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) for angles [..., 3] in radians (the paper's eq. 2, typo fixed)."""
    rpy = np.asarray(rpy_rad, dtype=float)
    cr, sr = np.cos(rpy[..., 0]), np.sin(rpy[..., 0])
    cp, sp = np.cos(rpy[..., 1]), np.sin(rpy[..., 1])
    cy, sy = np.cos(rpy[..., 2]), np.sin(rpy[..., 2])
    R = np.empty((*rpy.shape[:-1], 3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


@dataclass(frozen=True)
class Robot:
    """A validated robot as numpy arrays (mm, internal radians where noted)."""

    spec: RobotSpec

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def a(self) -> np.ndarray:
        """(6, 3) platform joints in the platform frame, mm."""
        return np.array([leg.a_mm for leg in self.spec.legs], dtype=float)

    @property
    def b(self) -> np.ndarray:
        """(6, 3) base joints in the base frame, mm."""
        return np.array([leg.b_mm for leg in self.spec.legs], dtype=float)

    @property
    def l0(self) -> np.ndarray:
        """(6,) leg length at zero stroke, mm."""
        return np.array([leg.l0_mm for leg in self.spec.legs], dtype=float)

    @property
    def home(self) -> np.ndarray:
        """Home pose [x, y, z mm, roll, pitch, yaw deg]."""
        return self.spec.home.as_array()

    @property
    def workspace(self) -> np.ndarray:
        """(6, 2) pose bounds in mm and degrees."""
        return self.spec.workspace.bounds()

    @property
    def leg_limits(self) -> tuple[float, float]:
        return self.spec.leg_limits.min_mm, self.spec.leg_limits.max_mm

    @property
    def moving_mass_kg(self) -> float:
        return self.spec.mass.moving_mass_kg

    @property
    def com(self) -> np.ndarray:
        return np.array(self.spec.mass.com_mm, dtype=float)

    @property
    def gravity_mps2(self) -> float:
        return self.spec.mass.gravity_mps2

    @property
    def platform_spheres(self) -> np.ndarray:
        return np.array(self.spec.cmm.platform_spheres_mm, dtype=float)

    @property
    def base_spheres(self) -> np.ndarray:
        return np.array(self.spec.cmm.base_spheres_mm, dtype=float)

    @property
    def sphere_radius_mm(self) -> float:
        return self.spec.cmm.sphere_radius_mm

    @property
    def sphere_sigma_mm(self) -> float | None:
        """The CMM's stated sphere-centre uncertainty (mm), if the robot file gives one."""
        return self.spec.cmm.sphere_sigma_mm

    @property
    def actuator_kind(self) -> str | None:
        """'hydraulic', 'electric', or None when the robot file does not say."""
        return None if self.spec.actuators is None else self.spec.actuators.kind

    @property
    def transducer(self) -> str | None:
        """'linear' or 'motor_encoder' (the default of the actuator kind), or None when unknown."""
        act = self.spec.actuators
        if act is None:
            return None
        return act.transducer or DEFAULT_TRANSDUCER[act.kind]

    @property
    def tolerances(self) -> ToleranceSpec:
        """The machine's tolerances before it is measured (``[tolerances]``, defaults when the file has none)."""
        return self.spec.tolerances

    @property
    def characteristic_length_mm(self) -> float:
        """RMS radius of the platform joints: converts rotation (rad) to a displacement (mm) for weighting."""
        a = self.a
        return float(np.sqrt(np.mean(np.sum((a - a.mean(axis=0)) ** 2, axis=1))))


def _location(loc: tuple) -> str:
    """Dotted field path; a leg index is shown as the 1-based leg number (legs.3 is leg 3)."""
    parts = []
    for i, p in enumerate(loc):
        parts.append(str(p + 1) if isinstance(p, int) and i > 0 and loc[i - 1] == "legs" else str(p))
    return ".".join(parts) or "<top>"


def _format_validation_error(source: str, err: ValidationError) -> str:
    lines = [f"robot file {source}: {err.error_count()} problem(s)"]
    for e in err.errors():
        lines.append(f"  {_location(e['loc'])}: {e['msg'].removeprefix('Value error, ')}")
    return "\n".join(lines)


def robot_from_dict(data: dict, source: str = "<dict>") -> Robot:
    """Validate a parsed robot description; raise RobotFileError naming each bad field."""
    try:
        return Robot(RobotSpec.model_validate(data))
    except ValidationError as err:
        raise RobotFileError(_format_validation_error(source, err)) from None


def load_robot(path: str | Path | None = None) -> Robot:
    """Load a robot TOML file, or the built-in paper Table 1 robot when path is None."""
    if path is None:
        text = resources.files("hilcal.data").joinpath("paper_table1.toml").read_text()
        source = "<built-in paper_table1>"
    else:
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as err:
            raise RobotFileError(f"robot file {p}: cannot read: {err.strerror}") from None
        source = str(p)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise RobotFileError(f"robot file {source}: not valid TOML: {err}") from None
    return robot_from_dict(data, source)


def default_robot() -> Robot:
    """The paper's Table 1 robot with the home pose, mass and workspace of the project brief."""
    return load_robot(None)
