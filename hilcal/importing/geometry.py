"""A robot file from the numbers a machine's documentation gives: joint circles, home height, stroke, travel.

Hexapod datasheets give the joint circle radii and angles (or the angle between the two joints of a pair), the
leg length range or stroke, the home height and the travel range about home. ``robot_from_geometry`` turns these
into the robot file that ``hilcal.robot.load_robot`` reads (validated by the same RobotSpec), and
``check_geometry`` says how much of the travel box the legs can reach. What a newcomer may not know has a stated
default: the travel (the box about home whose corners the legs reach) and the moving mass (an aluminium top plate
sized from the platform's joint circle); ``GeometryDefaults`` says which were used and what they came to.
"""

from __future__ import annotations

import json
import textwrap
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
    """The whole geometry file; ``travel`` and ``mass`` may be left out (stated defaults, ``GeometryDefaults``)."""

    name: str = "robot"
    base: JointCircle
    platform: JointCircle
    legs: LegGeometry
    home: HomeGeometry
    travel: TravelSpec | None = None
    mass: MassSpec | None = None
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


PLATE_RADIUS_FACTOR, PLATE_THICKNESS_MM, ALUMINIUM_KG_M3 = 1.2, 20.0, 2700.0
"""The default moving mass: an aluminium top plate 1.2 x the platform's joint radius, 20 mm thick, no payload."""
TRAVEL_FRACTIONS = tuple(round(1.0 - 0.05 * k, 2) for k in range(19))
"""The default travel: the largest of these fractions of each axis' own reach whose box has all 64 corners reachable."""
REACH_SEARCH = (1000.0, 60.0)
"""Single-axis reach is searched up to this many mm (x, y, z) and degrees (roll, pitch, yaw) from home."""


@dataclass(frozen=True)
class GeometryDefaults:
    """What the geometry file left out and what hilcal took instead, in words (empty: nothing)."""

    notes: tuple[str, ...] = ()


def default_mass(spec: GeometrySpec) -> MassSpec:
    """An aluminium top plate sized from the platform's joint circle (``PLATE_RADIUS_FACTOR``), no payload."""
    r_m = PLATE_RADIUS_FACTOR * spec.platform.radius_mm / 1000.0
    kg = ALUMINIUM_KG_M3 * np.pi * r_m**2 * PLATE_THICKNESS_MM / 1000.0
    return MassSpec(moving_mass_kg=round(float(kg), 2), com_mm=[0.0, 0.0, spec.platform.z_mm])


def _reach(robot: Robot, home: np.ndarray, axis: int) -> float:
    """How far from home the legs reach along one pose axis alone (both directions; the smaller), by bisection."""
    limit = REACH_SEARCH[0] if axis < 3 else REACH_SEARCH[1]
    reach = limit
    for sign in (1.0, -1.0):
        lo, hi = 0.0, limit
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            pose = home.copy()
            pose[axis] += sign * mid
            lo, hi = (mid, hi) if feasible(robot, pose[None, :])[0] else (lo, mid)
        reach = min(reach, lo)
    return reach


def default_travel(data: dict[str, Any], home: np.ndarray, source: str) -> tuple[list[list[float]], str]:
    """The travel box about home when the file gives none: each axis a fraction of its own reach, the fraction the
    largest of ``TRAVEL_FRACTIONS`` whose 64 corners the legs reach; the bounds and a sentence saying so."""
    wide = {**data, "workspace": {axis: [float(home[k] - (REACH_SEARCH[0] if k < 3 else REACH_SEARCH[1])),
                                         float(home[k] + (REACH_SEARCH[0] if k < 3 else REACH_SEARCH[1]))]
                                  for k, axis in enumerate(POSE_AXES)}}
    robot = robot_from_dict(wide, source)
    reach = np.array([_reach(robot, home, k) for k in range(6)])
    for fraction in TRAVEL_FRACTIONS:
        half = np.round(fraction * reach, 1)
        corners = home + np.array(np.meshgrid(*[[-h, h] for h in half], indexing="ij")).reshape(6, -1).T
        if np.all(feasible(robot, corners)) and np.all(half > 0):
            break
    else:
        raise ValueError("the legs reach no travel box about home: check the legs' range and the home height")
    said = ", ".join(f"{axis.split('_')[0]} ±{h:g} {'mm' if k < 3 else 'deg'}"
                     for k, (axis, h) in enumerate(zip(POSE_AXES, half, strict=True)))
    note = (f"travel: not in the geometry file; took {said}: {fraction:.0%} of each axis' own reach from home, the "
            "largest share whose 64 box corners the legs reach (give [travel] from your datasheet)")
    return [[float(home[k] - half[k]), float(home[k] + half[k])] for k in range(6)], note


def _default_cmm(spec: GeometrySpec) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for body, offset in (("platform", 0.0), ("base", 60.0)):
        circle: JointCircle = getattr(spec, body)
        r = DEFAULT_SPHERE_RADIUS_FRACTION[body] * circle.radius_mm
        rad = np.radians(offset + np.array([0.0, 120.0, 240.0]))
        out[f"{body}_spheres_mm"] = [[round(float(r * np.cos(t)), 3), round(float(r * np.sin(t)), 3), circle.z_mm]
                                     for t in rad]
    return out


def robot_dict_from_geometry(spec: GeometrySpec, source: str = "<geometry>") -> tuple[dict[str, Any],
                                                                                      GeometryDefaults]:
    """The robot file's content (a dict that ``hilcal.robot.robot_from_dict`` validates) and the defaults taken."""
    a, b = spec.platform.joints("platform"), spec.base.joints("base")
    z = _home_height(spec, a, b)
    home = np.array([0.0, 0.0, z, 0.0, 0.0, 0.0])
    l0 = spec.legs.zero_mm or spec.legs.min_mm
    notes: list[str] = []
    mass = spec.mass
    if mass is None:
        mass = default_mass(spec)
        notes.append(f"mass: not in the geometry file; took {mass.moving_mass_kg:g} kg at the platform frame's "
                     f"origin, an aluminium top plate {PLATE_RADIUS_FACTOR:g} x the platform's joint radius and "
                     f"{PLATE_THICKNESS_MM:g} mm thick, no payload (give [mass] with your payload: the legs' loads "
                     "and the compliance the diagnosis looks for depend on it)")
    data: dict[str, Any] = {
        "name": spec.name,
        "home": dict(zip(POSE_AXES, (float(v) for v in home), strict=True)),
        "leg_limits": {"min_mm": spec.legs.min_mm, "max_mm": spec.legs.min_mm + spec.legs.stroke_mm},
    }
    if spec.actuators is not None:
        data["actuators"] = spec.actuators.model_dump(exclude_none=True)
    data["mass"] = mass.model_dump()
    data["cmm"] = spec.cmm.model_dump(exclude_none=True) if spec.cmm is not None else _default_cmm(spec)
    data["legs"] = [{"a_mm": [round(float(v), 6) for v in a[k]], "b_mm": [round(float(v), 6) for v in b[k]],
                     "l0_mm": l0} for k in range(6)]
    if spec.travel is not None:
        bounds = spec.travel.bounds(home)
    else:
        bounds, note = default_travel(data, home, source)
        notes.append(note)
    data = {"name": data.pop("name"), "home": data.pop("home"),
            "workspace": dict(zip(POSE_AXES, bounds, strict=True)), **data}
    return data, GeometryDefaults(tuple(notes))


def robot_from_geometry(spec: GeometrySpec, source: str = "<geometry>") -> tuple[Robot, dict[str, Any],
                                                                                   GeometryDefaults]:
    """The validated robot, its file content and the defaults taken; an ImportFileError if the numbers do not make
    a valid robot."""
    try:
        data, defaults = robot_dict_from_geometry(spec, source)
        return robot_from_dict(data, source), data, defaults
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


def geometry_robot_toml(spec: GeometrySpec, source: str) -> tuple[Robot, str, GeometryDefaults]:
    """The robot, the text of its robot file (where it came from and the defaults taken in its header) and the
    defaults."""
    robot, data, defaults = robot_from_geometry(spec, source)
    header = (f"Robot file made by `hilcal robot-from-geometry {Path(source).name}` from the machine's documented\n"
              "geometry. Units: mm, degrees, kg. a_mm in the platform frame, b_mm in the base frame."
              + "".join("\n" + textwrap.fill(f"Default {note}.", 110) for note in defaults.notes))
    comments = {} if spec.cmm is not None else {"cmm": DEFAULT_CMM_COMMENT}
    return robot, robot_toml(data, header, comments), defaults
