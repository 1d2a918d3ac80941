"""Configuration of the simulated rig: the true geometric errors, sensor noise and the CMM placement.

All quantities are mm and degrees. The errors are the "truth" that a calibration should recover: per leg
a platform-joint error da (platform frame), a base-joint error db (base frame) and a stroke-zero length
error dl0 (true geometric length = reported length + dl0).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from scipy.spatial.transform import Rotation

from hilcal.robot import Robot, default_robot

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]

PAPER_ERRORS_FILE = Path(__file__).parent / "data" / "paper_errors.toml"
BUILTIN_ERROR_SETS = ("table2", "table3", "table4", "table5", "zero")
PARAMETERS_PER_LEG = 7


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


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


class RigConfig(_Strict):
    """Everything that makes one simulated rig: truth errors, noise, resolution, CMM placement, seed."""

    seed: int = 0
    errors: GeometryErrors
    cmm_noise_mm: float = Field(default=0.005, ge=0, description="std of noise per sphere-centre coordinate")
    leg_resolution_mm: float = Field(
        default=0.001, ge=0, description="reported lengths are multiples of this"
    )
    cmm_pose: CmmPose = Field(description="CMM frame in the base frame; default: random_cmm_pose(seed)")

    @model_validator(mode="before")
    @classmethod
    def _default_cmm_pose(cls, data: Any) -> Any:
        """Fill in the seeded random CMM placement so the resolved config records it explicitly."""
        if isinstance(data, dict) and data.get("cmm_pose") is None:
            seed = data.get("seed", 0)
            data = {**data, "cmm_pose": random_cmm_pose(seed if isinstance(seed, int) else 0)}
        return data


def _home_leg_directions(robot: Robot) -> np.ndarray:
    """(6, 3) unit leg vectors at the home pose with the nominal geometry."""
    home = robot.home
    R = Rotation.from_euler("ZYX", home[[5, 4, 3]], degrees=True).as_matrix()
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


def random_errors(seed: int, sigma_mm: float) -> GeometryErrors:
    """All 42 parameters drawn independently from N(0, sigma_mm^2) with a seeded generator."""
    if sigma_mm < 0:
        raise ValueError(f"sigma_mm must be >= 0, got {sigma_mm}")
    rng = np.random.default_rng([seed, 0xE77])
    return GeometryErrors.from_vector(rng.normal(0.0, sigma_mm, 6 * PARAMETERS_PER_LEG))
