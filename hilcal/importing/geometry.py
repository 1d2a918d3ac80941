"""A robot file from the numbers a machine's documentation gives: joint circles, home height, stroke, travel.

Hexapod datasheets give the joint circle radii and angles (or the angle between the two joints of a pair), the
leg length range or stroke, the home height and the travel range about home. ``robot_from_geometry`` turns these
into the robot file that ``hilcal.robot.load_robot`` reads (validated by the same RobotSpec), and
``check_geometry`` says how much of the travel box the legs can reach.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hilcal.importing.errors import ImportFileError
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import POSE_AXES, ActuatorSpec, CmmSpec, MassSpec, Robot, RobotFileError, robot_from_dict
from hilcal.workspace import feasible

Travel = Annotated[float, Field(gt=0)] | Annotated[list[float], Field(min_length=2, max_length=2)]
N_REACH_SAMPLES = 4000
DEFAULT_SPHERE_RADIUS_FRACTION = {"platform": 0.8, "base": 1.1}
DEFAULT_CMM_COMMENT = ("Not from the geometry file: a nominal layout of three tooling spheres on each body.\n"
                       "Replace it with your spheres' (or targets') positions before measuring.")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class JointCircle(_Strict):
    """The six joints of one body on a circle: explicit angles in leg order, or pairs spaced by pair_spacing_deg.

    With pair_spacing_deg the layout is the paper's: base pairs centred at 60, 180, 300 deg, platform pairs at
    0, 120, 240 deg; leg 2j+1 joins the base joint at 60 + 120 j - s_b/2 to the platform joint at 120 j + s_p/2,
    leg 2j+2 the base joint at 60 + 120 j + s_b/2 to the platform joint at 120 (j + 1) - s_p/2.
    """

    radius_mm: float = Field(gt=0)
    angles_deg: Annotated[list[float], Field(min_length=6, max_length=6)] | None = None
    pair_spacing_deg: float | None = Field(default=None, gt=0, lt=120)
    z_mm: float = Field(default=0.0, description="height of the joint centres in the body's frame")

    @model_validator(mode="after")
    def _one_layout(self) -> JointCircle:
        if (self.angles_deg is None) == (self.pair_spacing_deg is None):
            raise ValueError("give either angles_deg (six, in leg order) or pair_spacing_deg")
        return self

    def joints(self, body: str) -> np.ndarray:
        """(6, 3) joint centres in the body's frame, mm."""
        if self.angles_deg is not None:
            angles = np.asarray(self.angles_deg, dtype=float)
        else:
            s = float(self.pair_spacing_deg or 0.0)
            j = np.repeat(np.arange(3), 2)
            first = np.arange(6) % 2 == 0
            if body == "base":
                angles = 60.0 + 120.0 * j + np.where(first, -s / 2, s / 2)
            else:
                angles = 120.0 * j + np.where(first, s / 2, 120.0 - s / 2)
        rad = np.radians(angles)
        return np.column_stack([self.radius_mm * np.cos(rad), self.radius_mm * np.sin(rad), np.full(6, self.z_mm)])


class LegGeometry(_Strict):
    """Leg length range, joint centre to joint centre."""

    min_mm: float = Field(gt=0, description="shortest (fully retracted) leg length")
    stroke_mm: float = Field(gt=0)
    zero_mm: float | None = Field(default=None, gt=0, description="length at zero transducer reading (default min)")


class HomeGeometry(_Strict):
    """The home pose: its height (z_mm) or the length all six legs have there (leg_mm), level and centred."""

    z_mm: float | None = None
    leg_mm: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _one(self) -> HomeGeometry:
        if (self.z_mm is None) == (self.leg_mm is None):
            raise ValueError("give either z_mm (height of the platform frame) or leg_mm (all legs at home)")
        return self


class TravelSpec(_Strict):
    """Travel about home per axis: a number for +-, or [low, high] relative to home (mm, deg)."""

    x_mm: Travel
    y_mm: Travel
    z_mm: Travel
    roll_deg: Travel
    pitch_deg: Travel
    yaw_deg: Travel

    def bounds(self, home: np.ndarray) -> list[list[float]]:
        out = []
        for k, axis in enumerate(POSE_AXES):
            value = getattr(self, axis)
            lo, hi = (-value, value) if isinstance(value, float | int) else value
            out.append([float(home[k] + lo), float(home[k] + hi)])
        return out


class GeometrySpec(_Strict):
    """The whole geometry file."""

    name: str = "robot"
    base: JointCircle
    platform: JointCircle
    legs: LegGeometry
    home: HomeGeometry
    travel: TravelSpec
    mass: MassSpec
    actuators: ActuatorSpec | None = None
    cmm: CmmSpec | None = None


@dataclass(frozen=True)
class GeometryCheck:
    """How the documented numbers fit together: home leg lengths and the reachable share of the travel box."""

    home_legs_mm: np.ndarray
    leg_limits_mm: tuple[float, float]
    corners_reachable: int
    """Of the 64 corners of the travel box, how many the legs reach (away from singularities)."""
    reachable_fraction: float
    """Share of uniform random poses in the travel box that the legs reach."""


def _home_height(spec: GeometrySpec, a: np.ndarray, b: np.ndarray) -> float:
    if spec.home.z_mm is not None:
        return spec.home.z_mm
    length = float(spec.home.leg_mm or 0.0)
    d = np.linalg.norm(a[:, :2] - b[:, :2], axis=1)
    if np.any(d >= length):
        raise ValueError(f"home.leg_mm = {length:g} mm is shorter than the horizontal joint distance {d.max():.1f} mm")
    z = b[:, 2] - a[:, 2] + np.sqrt(length**2 - d**2)
    if np.ptp(z) > 1.0:
        raise ValueError("with these joint angles the legs cannot all have home.leg_mm at one height; give home.z_mm")
    return float(np.mean(z))


def _default_cmm(spec: GeometrySpec) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for body, offset in (("platform", 0.0), ("base", 60.0)):
        circle: JointCircle = getattr(spec, body)
        r = DEFAULT_SPHERE_RADIUS_FRACTION[body] * circle.radius_mm
        rad = np.radians(offset + np.array([0.0, 120.0, 240.0]))
        out[f"{body}_spheres_mm"] = [[round(float(r * np.cos(t)), 3), round(float(r * np.sin(t)), 3), circle.z_mm]
                                     for t in rad]
    return out


def robot_dict_from_geometry(spec: GeometrySpec) -> dict[str, Any]:
    """The robot file's content (a dict that ``hilcal.robot.robot_from_dict`` validates)."""
    a, b = spec.platform.joints("platform"), spec.base.joints("base")
    z = _home_height(spec, a, b)
    home = np.array([0.0, 0.0, z, 0.0, 0.0, 0.0])
    l0 = spec.legs.zero_mm or spec.legs.min_mm
    data: dict[str, Any] = {
        "name": spec.name,
        "home": dict(zip(POSE_AXES, (float(v) for v in home), strict=True)),
        "workspace": dict(zip(POSE_AXES, spec.travel.bounds(home), strict=True)),
        "leg_limits": {"min_mm": spec.legs.min_mm, "max_mm": spec.legs.min_mm + spec.legs.stroke_mm},
    }
    if spec.actuators is not None:
        data["actuators"] = spec.actuators.model_dump(exclude_none=True)
    data["mass"] = spec.mass.model_dump()
    data["cmm"] = spec.cmm.model_dump(exclude_none=True) if spec.cmm is not None else _default_cmm(spec)
    data["legs"] = [{"a_mm": [round(float(v), 6) for v in a[k]], "b_mm": [round(float(v), 6) for v in b[k]],
                     "l0_mm": l0} for k in range(6)]
    return data


def robot_from_geometry(spec: GeometrySpec, source: str = "<geometry>") -> tuple[Robot, dict[str, Any]]:
    """The validated robot and its file content; an ImportFileError if the numbers do not make a valid robot."""
    try:
        data = robot_dict_from_geometry(spec)
        return robot_from_dict(data, source), data
    except (ValueError, RobotFileError) as err:
        raise ImportFileError(source, f"these numbers do not make a valid robot: {err}") from None


def check_geometry(robot: Robot, seed: int = 0) -> GeometryCheck:
    """Home leg lengths and how much of the travel box the legs reach (corners, and uniform random poses)."""
    ws = robot.workspace
    corners = np.array(np.meshgrid(*ws, indexing="ij")).reshape(6, -1).T
    draws = ws[:, 0] + np.random.default_rng(seed).random((N_REACH_SAMPLES, 6)) * (ws[:, 1] - ws[:, 0])
    return GeometryCheck(
        home_legs_mm=inverse_kinematics(Geometry.nominal(robot), robot.home[None, :])[0],
        leg_limits_mm=robot.leg_limits,
        corners_reachable=int(np.sum(feasible(robot, corners))),
        reachable_fraction=float(np.mean(feasible(robot, draws))),
    )


def load_geometry(path: str | Path) -> GeometrySpec:
    """Read and validate a geometry TOML file; errors name the key."""
    source = str(path)
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as err:
        raise ImportFileError(source, f"cannot read the geometry file: {err.strerror or err}") from None
    except tomllib.TOMLDecodeError as err:
        raise ImportFileError(source, f"not valid TOML: {err}") from None
    try:
        return GeometrySpec.model_validate(data)
    except ValidationError as err:
        where = [".".join(str(p) for p in e["loc"]) for e in err.errors()]
        problems = "; ".join(f"{w}: {e['msg'].removeprefix('Value error, ')}" for w, e in zip(where, err.errors(),
                                                                                             strict=True))
        raise ImportFileError(source, f"{err.error_count()} problem(s): {problems}", column=where[0],
                              label="key") from None


def _value(v: Any) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return repr(float(v))


def robot_toml(data: dict[str, Any], header: str = "", comments: dict[str, str] | None = None) -> str:
    """TOML text of a robot dict (scalars, tables of scalars and lists, the array of leg tables)."""
    comments = comments or {}
    lines = [f"# {line}" for line in header.splitlines()]
    lines += [f"{k} = {_value(v)}" for k, v in data.items() if not isinstance(v, dict | list)]
    for key, table in data.items():
        if isinstance(table, dict):
            lines += ["", *(f"# {c}" for c in comments.get(key, "").splitlines()), f"[{key}]"]
            lines += [f"{k} = {_value(v)}" for k, v in table.items()]
    for key, tables in data.items():
        if isinstance(tables, list) and tables and isinstance(tables[0], dict):
            for table in tables:
                lines += ["", f"[[{key}]]", *(f"{k} = {_value(v)}" for k, v in table.items())]
    return "\n".join(lines) + "\n"


def geometry_robot_toml(spec: GeometrySpec, source: str) -> tuple[Robot, str]:
    """The robot and the text of its robot file, with where it came from in its header."""
    robot, data = robot_from_geometry(spec, source)
    header = (f"Robot file made by `hilcal robot-from-geometry {Path(source).name}` from the machine's documented\n"
              "geometry. Units: mm, degrees, kg. a_mm in the platform frame, b_mm in the base frame.")
    comments = {} if spec.cmm is not None else {"cmm": DEFAULT_CMM_COMMENT}
    return robot, robot_toml(data, header, comments)
