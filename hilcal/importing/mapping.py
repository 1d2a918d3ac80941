"""The mapping file of `hilcal import`: which columns of a machine's or tracker's CSV hold what, in which unit.

A small TOML validated by pydantic (unknown keys are errors, so a typo is not silently ignored). The key names
are a contract used by files outside this repository; docs/import.md documents every key.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hilcal.importing.errors import ImportFileError

Names3 = Annotated[list[str], Field(min_length=3, max_length=3)]
Names6 = Annotated[list[str], Field(min_length=6, max_length=6)]
PerLeg = float | Annotated[list[float], Field(min_length=6, max_length=6)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]

LengthUnit = Literal["mm", "m", "in"]
"""Lengths as loggers write them: mm, metres or inches (25.4 mm)."""
LegUnit = Literal["mm", "m", "in", "count", "rev"]
OrientationKind = Literal["quaternion_xyzw", "quaternion_wxyz", "rpy_deg", "rpy_rad", "matrix", "euler_deg",
                          "euler_rad", "rotvec_deg", "rotvec_rad"]
ORIENTATION_COLUMNS: dict[str, int] = {
    "quaternion_xyzw": 4, "quaternion_wxyz": 4, "rpy_deg": 3, "rpy_rad": 3, "matrix": 9, "euler_deg": 3,
    "euler_rad": 3, "rotvec_deg": 3, "rotvec_rad": 3,
}
EULER_SEQUENCE = re.compile(r"^(?:[xyz]{3}|[XYZ]{3})$")
"""Euler axis sequences as scipy writes them: lower case about the fixed (base) axes, upper case about the moving
(platform) axes, angles in the order of the letters."""
MIN_TARGET_SPREAD_MM = 1.0
"""The targets of one body must span a triangle: its second singular value at least this (mm)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _distinct(names: list[str]) -> list[str]:
    stripped = [n.strip() for n in names]
    if any(not n for n in stripped):
        raise ValueError("column names must not be empty")
    twice = sorted({n for n in stripped if stripped.count(n) > 1})
    if twice:
        raise ValueError(f"column(s) {', '.join(twice)} listed twice")
    return stripped


class LegsMap(_Strict):
    """Leg readings: length_mm = zero_mm + mm_per_unit * reading (mm: 1, m: 1000, in: 25.4; zero_mm 0 unless
    given)."""

    columns: Names6
    unit: LegUnit
    mm_per_unit: PerLeg | None = Field(default=None, description="per leg, for count and rev (negative: reversed)")
    zero_mm: PerLeg | None = Field(default=None, description="leg length at reading 0, per leg")

    _names = field_validator("columns")(_distinct)

    @model_validator(mode="after")
    def _scale_given_where_needed(self) -> LegsMap:
        if self.unit in ("count", "rev"):
            if self.mm_per_unit is None or self.zero_mm is None:
                raise ValueError(f"unit {self.unit!r} needs mm_per_unit and zero_mm (per leg or one for all)")
            if np.any(np.asarray(self.mm_per_unit, dtype=float) == 0.0):
                raise ValueError("mm_per_unit must not be 0")
        elif self.mm_per_unit is not None:
            raise ValueError(f"mm_per_unit is fixed for unit {self.unit!r}; remove it (or use 'count' or 'rev')")
        return self

    def scale_mm(self) -> np.ndarray:
        """(6,) mm per reading unit."""
        fixed = {"mm": 1.0, "m": 1000.0, "in": 25.4}
        value = fixed[self.unit] if self.unit in fixed else self.mm_per_unit
        return np.broadcast_to(np.asarray(value, dtype=float), (6,)).copy()

    def zero(self) -> np.ndarray:
        """(6,) leg length (mm) at reading 0."""
        return np.broadcast_to(np.asarray(0.0 if self.zero_mm is None else self.zero_mm, dtype=float), (6,)).copy()


class PositionMap(_Strict):
    """The platform frame's origin in the base frame: x, y, z columns."""

    columns: Names3
    unit: LengthUnit = "mm"

    _names = field_validator("columns")(_distinct)


class OrientationMap(_Strict):
    """The platform's orientation in the base frame (the rotation that maps platform vectors to base vectors)."""

    columns: list[str]
    kind: OrientationKind
    sequence: str | None = Field(default=None, description="euler kinds only: e.g. 'ZYX' (moving axes) or 'xyz' "
                                 "(fixed axes), the columns' angles in that order")

    _names = field_validator("columns")(_distinct)

    @model_validator(mode="after")
    def _count(self) -> OrientationMap:
        want = ORIENTATION_COLUMNS[self.kind]
        if len(self.columns) != want:
            raise ValueError(f"kind {self.kind!r} needs {want} columns, got {len(self.columns)}")
        if self.kind.startswith("euler"):
            seq = self.sequence or ""
            if not EULER_SEQUENCE.match(seq) or seq[0].lower() == seq[1].lower() or seq[1].lower() == seq[2].lower():
                raise ValueError(f"kind {self.kind!r} needs sequence = three axes such as 'ZYX' (about the moving "
                                 "axes) or 'xyz' (about the fixed axes), no axis twice in a row; "
                                 f"got {self.sequence!r}")
        elif self.sequence is not None:
            raise ValueError(f"sequence is only for the euler kinds, not {self.kind!r}")
        return self


class PoseColumns(_Strict):
    """A pose given by position and orientation columns (the commanded pose)."""

    position: PositionMap
    orientation: OrientationMap


class TimeMap(_Strict):
    """Time stamps: seconds, milliseconds or ISO 8601 text; clock 'per_file' or 'shared' (see ``clock_mode``)."""

    column: str
    unit: Literal["s", "ms", "iso"] = "s"
    clock: Literal["per_file", "shared"] | None = Field(
        default=None, description="per_file: each file its own clock and session; shared: one clock for all files "
        "(sessions where it goes back or jumps by more than 4 h). Default: shared for iso, per_file otherwise")

    @property
    def clock_mode(self) -> str:
        """'shared' or 'per_file' (ISO stamps are absolute, so their default is one clock for all files)."""
        return self.clock or ("shared" if self.unit == "iso" else "per_file")


class PhaseMap(_Strict):
    """A column that says which rows are measure rows and which are verify rows (wins over --hold-out)."""

    column: str
    measure: str | list[str] = "measure"
    verify: str | list[str] = "verify"

    @model_validator(mode="after")
    def _disjoint(self) -> PhaseMap:
        both = set(self.measure_values) & set(self.verify_values)
        if both:
            raise ValueError(f"value(s) {', '.join(sorted(both))} mean both measure and verify")
        return self

    @property
    def measure_values(self) -> tuple[str, ...]:
        return (self.measure,) if isinstance(self.measure, str) else tuple(self.measure)

    @property
    def verify_values(self) -> tuple[str, ...]:
        return (self.verify,) if isinstance(self.verify, str) else tuple(self.verify)


class TargetMap(_Strict):
    """One target (tracker reflector or sphere): its x, y, z columns and its position on its body (mm)."""

    name: str
    columns: Names3
    position_mm: Vec3

    _names = field_validator("columns")(_distinct)


def _spread(targets: list[TargetMap], body: str) -> None:
    p = np.array([t.position_mm for t in targets], dtype=float)
    if np.linalg.svd(p - p.mean(axis=0), compute_uv=False)[1] < MIN_TARGET_SPREAD_MM:
        raise ValueError(f"the {body} targets are (nearly) collinear: they cannot define a frame")
    names = [t.name for t in targets]
    if len(set(names)) != len(names):
        raise ValueError(f"{body} target names must be distinct, got {names}")


class TargetsMap(_Strict):
    """Raw target points instead of a pose: three or more on the platform, optionally three or more on the base.

    Platform positions are in the platform frame, base positions in the base frame. Without base targets the
    points are taken as given in the base frame; with them, each row's base targets register the instrument's
    frame, as the CMM path does with its base spheres.
    """

    unit: LengthUnit = "mm"
    platform: Annotated[list[TargetMap], Field(min_length=3)]
    base: list[TargetMap] = Field(default_factory=list)

    @model_validator(mode="after")
    def _layouts(self) -> TargetsMap:
        _spread(self.platform, "platform")
        if self.base:
            if len(self.base) < 3:
                raise ValueError("base needs three or more targets (or none)")
            _spread(self.base, "base")
        return self

    def layout(self, body: str) -> np.ndarray:
        """(K, 3) target positions on the platform or the base, mm."""
        return np.array([t.position_mm for t in getattr(self, body)], dtype=float)


class TemperatureMap(_Strict):
    """A leg (or ambient, or oil) temperature column in °C, K or °F, written as ``temp_c``."""

    column: str
    unit: Literal["C", "K", "F"] = "C"

    def celsius(self, values: np.ndarray) -> np.ndarray:
        """The readings in °C."""
        values = np.asarray(values, dtype=float)
        if self.unit == "K":
            return values - 273.15
        if self.unit == "F":
            return (values - 32.0) * (5.0 / 9.0)
        return values


PASCAL_PER_UNIT = {"bar": 1e5, "MPa": 1e6, "psi": 6894.757293168}
KN_PER_UNIT = {"kN": 1.0, "N": 1e-3, "lbf": 4.4482216152605e-3}


class ForceMap(_Strict):
    """Measured leg loads, written as ``leg1_force_kn`` ... ``leg6_force_kn`` (axial, positive = compression: the
    leg pushes the platform): six force columns, or a hydraulic cylinder's cap- and rod-side pressures and bores
    (force = p_cap · π/4 · bore² − p_rod · π/4 · (bore² − rod²))."""

    columns: Names6 | None = Field(default=None, description="axial force per leg")
    cap_columns: Names6 | None = Field(default=None, description="cap-side (extending) pressure per leg")
    rod_columns: Names6 | None = Field(default=None, description="rod-side (retracting) pressure per leg")
    unit: Literal["kN", "N", "lbf", "bar", "MPa", "psi"]
    bore_mm: PerLeg | None = Field(default=None, description="piston diameter, one or six")
    rod_mm: PerLeg | None = Field(default=None, description="rod diameter, one or six")
    tension_positive: bool = Field(default=False, description="the logger writes tension as positive")

    @model_validator(mode="after")
    def _forces_or_pressures(self) -> ForceMap:
        pressure = self.unit in PASCAL_PER_UNIT
        if pressure:
            if self.cap_columns is None or self.bore_mm is None:
                raise ValueError(f"pressures in {self.unit} need cap_columns and bore_mm (and rod_columns with rod_mm)")
            if (self.rod_columns is None) != (self.rod_mm is None):
                raise ValueError("rod_columns and rod_mm go together")
            if self.columns is not None:
                raise ValueError(f"columns are forces; pressures in {self.unit} go in cap_columns and rod_columns")
            bore = np.asarray(self.bore_mm, dtype=float)
            rod = np.asarray(0.0 if self.rod_mm is None else self.rod_mm, dtype=float)
            if np.any(bore <= 0) or np.any(rod < 0) or np.any(rod >= bore):
                raise ValueError("need 0 <= rod_mm < bore_mm and bore_mm > 0")
        elif self.columns is None or self.cap_columns is not None or self.rod_columns is not None:
            raise ValueError(f"forces in {self.unit} need columns (six), and no cap_columns or rod_columns")
        return self

    def all_columns(self) -> list[str]:
        return [*(self.columns or ()), *(self.cap_columns or ()), *(self.rod_columns or ())]

    def forces_kn(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """(n, 6) axial leg forces, kN, compression positive, from the mapped columns' values."""
        sign = -1.0 if self.tension_positive else 1.0
        if self.columns is not None:
            return sign * KN_PER_UNIT[self.unit] * np.column_stack([values[c] for c in self.columns])
        bore_m2 = np.pi / 4.0 * (np.broadcast_to(np.asarray(self.bore_mm, dtype=float), (6,)) * 1e-3) ** 2
        rod_m2 = np.pi / 4.0 * (np.broadcast_to(np.asarray(self.rod_mm or 0.0, dtype=float), (6,)) * 1e-3) ** 2
        pa = PASCAL_PER_UNIT[self.unit]
        cap = np.column_stack([values[c] for c in self.cap_columns or ()]) * pa * bore_m2
        rod = 0.0 if self.rod_columns is None else np.column_stack([values[c] for c in self.rod_columns]) * pa * (
            bore_m2 - rod_m2)
        return sign * (cap - rod) / 1000.0


class FitRmsMap(_Strict):
    """The pose measurement's registration RMS as the CMM or tracker software writes it: ``sphere_fit_rms_mm``."""

    column: str
    unit: LengthUnit = "mm"


class FrameMap(_Strict):
    """Poses logged in the instrument's own frame: align them to the base frame by the leg lengths (needs the robot).

    ``align``: ``"shared"``, one instrument frame for every file; ``"per_file"``, the instrument was set up anew for
    each file. ``target``, with per_file: ``"shared"`` (default), the target stayed mounted on the platform while the
    instrument moved, so one target place is fitted with every file's frame; ``"per_file"``, it was mounted anew too."""

    align: Literal["none", "shared", "per_file"] = "none"
    target: Literal["shared", "per_file"] = "shared"


class CsvMap(_Strict):
    """How the files are written: delimiter, decimal mark, and the line of the header (lines above it are skipped)."""

    delimiter: str = Field(default=",", min_length=1, max_length=1)
    decimal: Literal[".", ","] = "."
    header_line: int = Field(default=1, ge=1)

    @model_validator(mode="after")
    def _not_ambiguous(self) -> CsvMap:
        if self.decimal == self.delimiter:
            raise ValueError(f"decimal mark and delimiter are both {self.delimiter!r}")
        return self


class ImportMap(_Strict):
    """The whole mapping file."""

    legs: LegsMap
    position: PositionMap | None = None
    orientation: OrientationMap | None = None
    targets: TargetsMap | None = None
    command: PoseColumns | None = None
    time: TimeMap | None = None
    phase: PhaseMap | None = None
    temperature: TemperatureMap | None = None
    fit_rms: FitRmsMap | None = None
    force: ForceMap | None = None
    frame: FrameMap = Field(default_factory=FrameMap)
    csv: CsvMap = Field(default_factory=CsvMap)

    @model_validator(mode="after")
    def _one_pose_source(self) -> ImportMap:
        pose = (self.position is not None, self.orientation is not None)
        if pose[0] != pose[1]:
            raise ValueError("[position] and [orientation] go together")
        if pose[0] == (self.targets is not None):
            raise ValueError("give the measured pose either as [position] and [orientation] or as [targets]")
        if self.targets is not None and self.fit_rms is not None:
            raise ValueError("[fit_rms] comes from the [targets] registration; remove one of them")
        return self

    def columns(self) -> list[str]:
        """Every column the map reads, each once, in the map's order."""
        names: list[str] = [*self.legs.columns]
        if self.position is not None and self.orientation is not None:
            names += [*self.position.columns, *self.orientation.columns]
        if self.targets is not None:
            names += [c for t in (*self.targets.platform, *self.targets.base) for c in t.columns]
        if self.command is not None:
            names += [*self.command.position.columns, *self.command.orientation.columns]
        names += [m.column for m in (self.time, self.phase, self.temperature, self.fit_rms) if m is not None]
        if self.force is not None:
            names += self.force.all_columns()
        return list(dict.fromkeys(names))


def _where(loc: tuple) -> str:
    return ".".join(str(p + 1) if isinstance(p, int) else str(p) for p in loc) or "(top level)"


def map_from_dict(data: dict, source: str = "<dict>") -> ImportMap:
    """Validate a parsed mapping; raise ImportFileError naming each bad key (list items counted from 1)."""
    try:
        return ImportMap.model_validate(data)
    except ValidationError as err:
        problems = "; ".join(f"{_where(e['loc'])}: {e['msg'].removeprefix('Value error, ')}" for e in err.errors())
        first = _where(err.errors()[0]["loc"])
        detail = f"{err.error_count()} problem(s): {problems}"
        raise ImportFileError(source, detail, column=first, label="key") from None


def load_map(path: str | Path) -> ImportMap:
    """Read and validate a mapping TOML file."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as err:
        raise ImportFileError(source, f"cannot read the mapping file: {err.strerror or err}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ImportFileError(source, f"not valid TOML: {err}") from None
    return map_from_dict(data, source)
