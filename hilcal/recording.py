"""The recording CSV: one row per executed pose (commanded pose, reported leg lengths, CMM-measured pose).

This file format is a contract between the rig drivers, the simulator and the calibration: columns are read
by header name, every value is validated on the way in, and writing then reading reproduces the arrays
exactly. Units are mm and degrees throughout.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import structlog

from hilcal.robot import Robot

log = structlog.get_logger(__name__)

_POSE_SUFFIXES = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
CMD_COLUMNS: tuple[str, ...] = tuple(f"cmd_{s}" for s in _POSE_SUFFIXES)
LEG_COLUMNS: tuple[str, ...] = tuple(f"leg{k}_mm" for k in range(1, 7))
MEAS_COLUMNS: tuple[str, ...] = tuple(f"meas_{s}" for s in _POSE_SUFFIXES)
FORCE_COLUMNS: tuple[str, ...] = tuple(f"leg{k}_force_kn" for k in range(1, 7))
"""Optional measured axial leg loads, kN, compression positive (docs/recording-format.md)."""
REQUIRED_COLUMNS: tuple[str, ...] = ("seq", "phase", "time_s", *CMD_COLUMNS, *LEG_COLUMNS, *MEAS_COLUMNS)
PHASES: tuple[str, ...] = ("measure", "verify")

N_MODEL_PARAMETERS = 42
"""Parameters of the rigid error model (per leg: da 3, db 3, dl0 1); each pose gives 6 equations."""

TEMP_RANGE_C = (-50.0, 150.0)
LEG_MARGIN_MM = 50.0
POSITION_MARGIN_MM = 200.0
ANGLE_MARGIN_DEG = 10.0
SESSION_GAP_S = 4 * 3600.0
"""A new session starts where time_s goes backwards or jumps by more than this (docs/recording-format.md)."""


class RecordingError(ValueError):
    """A recording that cannot be read or violates the format; ``line`` is 1-based (header = line 1)."""

    def __init__(self, message: str, *, line: int | None = None, column: str | None = None) -> None:
        super().__init__(message)
        self.line = line
        self.column = column


@dataclass(frozen=True)
class Recording:
    """A validated recording as arrays, rows in execution order (mm, degrees, seconds)."""

    seq: np.ndarray
    phase: np.ndarray
    time_s: np.ndarray
    cmd: np.ndarray
    legs_mm: np.ndarray
    meas: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.seq.shape[0] if self.seq.ndim == 1 else -1
        shapes = {
            "seq": (self.seq.shape, (n,)),
            "phase": (self.phase.shape, (n,)),
            "time_s": (self.time_s.shape, (n,)),
            "cmd": (self.cmd.shape, (n, 6)),
            "legs_mm": (self.legs_mm.shape, (n, 6)),
            "meas": (self.meas.shape, (n, 6)),
        }
        shapes.update({f"extra[{k!r}]": (v.shape, (n,)) for k, v in self.extra.items()})
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(f"Recording.{name} has shape {got}, expected {want}")

    @property
    def n(self) -> int:
        """Number of rows."""
        return int(self.seq.shape[0])

    @property
    def temp_c(self) -> np.ndarray | None:
        """Temperature column in degrees Celsius, or None when the recording has none."""
        return self.extra.get("temp_c")

    @property
    def stations(self) -> np.ndarray | None:
        """Each row's instrument station (integers) when the recording has a ``station`` column, else None: every
        station but the first gets a rigid frame error in the fits (``hilcal.stations``)."""
        values = self.extra.get("station")
        return None if values is None else np.asarray(values).astype(int)

    @property
    def has_cmd(self) -> bool:
        """True when every row carries its commanded pose."""
        return bool(np.all(np.isfinite(self.cmd)))

    def select(self, phase: str) -> Recording:
        """The rows of one phase (``measure`` or ``verify``), in their original order."""
        if phase not in PHASES:
            raise ValueError(f"unknown phase {_show(phase)}; expected one of {', '.join(PHASES)}")
        return self.rows(self.phase == phase)

    def rows(self, keep: np.ndarray) -> Recording:
        """The rows where ``keep`` is true (a boolean mask or indices), in their original order."""
        return Recording(
            seq=self.seq[keep],
            phase=self.phase[keep],
            time_s=self.time_s[keep],
            cmd=self.cmd[keep],
            legs_mm=self.legs_mm[keep],
            meas=self.meas[keep],
            extra={k: v[keep] for k, v in self.extra.items()},
        )


def session_numbers(time_s: Sequence[float] | np.ndarray, gap_s: float = SESSION_GAP_S) -> np.ndarray:
    """Session (0, 1, ...) of every row in execution order: the format's rule, a clock that goes back or jumps."""
    t = np.asarray(time_s, dtype=float)
    if t.size == 0:
        return np.zeros(0, dtype=int)
    dt = np.diff(t)
    return np.concatenate([[0], np.cumsum((dt < 0) | (dt > gap_s))]).astype(int)


def _show(value: object) -> str:
    """A value quoted as the user wrote or would write it ('mesure', 3.0), never as a numpy repr."""
    if isinstance(value, np.generic):
        value = value.item()
    return repr(value)


def _fmt(value: float) -> str:
    """Shortest text that reads back as exactly the same float."""
    return repr(float(value))


def _bound(value: float) -> str:
    return f"{value:g}"


class _Locator:
    """Turns a row index into the 'source line L (seq S), column C' prefix of an error message."""

    def __init__(self, source: str, lines: Sequence[int] | None) -> None:
        self.source = source
        self.lines = lines

    def line(self, row: int) -> int | None:
        return None if self.lines is None else self.lines[row]

    def where(self, row: int, seq: int | None) -> str:
        place = f"row {row + 1}" if self.lines is None else f"line {self.lines[row]}"
        seq_part = "" if seq is None else f" (seq {seq})"
        return f"{self.source} {place}{seq_part}"

    def error(self, row: int, seq: int | None, column: str, detail: str) -> RecordingError:
        return RecordingError(
            f"{self.where(row, seq)}, column {column}: {detail}", line=self.line(row), column=column
        )


def _angle_limits(robot: Robot | None) -> list[tuple[float, float]]:
    """Physically plausible [low, high] for roll, pitch, yaw in degrees."""
    generic = [(-180.0, 180.0), (-90.0, 90.0), (-180.0, 180.0)]
    if robot is None:
        return generic
    ws = robot.workspace[3:]
    return [
        (max(g[0], lo - ANGLE_MARGIN_DEG), min(g[1], hi + ANGLE_MARGIN_DEG))
        for g, (lo, hi) in zip(generic, ws, strict=True)
    ]


def _validate(rec: Recording, loc: _Locator, robot: Robot | None, min_measure_rows: int) -> None:
    """Check every value against the format rules; raise RecordingError at the first violation."""
    seq, phase, time_s, cmd, legs_mm, meas, extra = (
        rec.seq, rec.phase, rec.time_s, rec.cmd, rec.legs_mm, rec.meas, rec.extra
    )
    if min_measure_rows < 0:
        raise ValueError(f"min_measure_rows must be >= 0, got {min_measure_rows}")
    n = seq.shape[0]
    if n == 0:
        raise RecordingError(f"{loc.source}: the recording has no data rows", line=None, column=None)

    if robot is not None:
        leg_lo, leg_hi = robot.leg_limits[0] - LEG_MARGIN_MM, robot.leg_limits[1] + LEG_MARGIN_MM
        pos_limits = [(lo - POSITION_MARGIN_MM, hi + POSITION_MARGIN_MM) for lo, hi in robot.workspace[:3]]
    else:
        leg_lo, leg_hi = 0.0, math.inf
        pos_limits = [(-math.inf, math.inf)] * 3
    ang_limits = _angle_limits(robot)
    pose_limits = pos_limits + ang_limits
    temp = extra.get("temp_c")
    station = extra.get("station")

    first_line_of_seq: dict[int, int] = {}
    for i in range(n):
        s = int(seq[i])
        if s in first_line_of_seq:
            j = first_line_of_seq[s]
            first = f"row {j + 1}" if loc.lines is None else f"line {loc.lines[j]}"
            raise loc.error(i, s, "seq", f"duplicate seq {s}, already used on {first}")
        first_line_of_seq[s] = i

        if phase[i] not in PHASES:
            raise loc.error(i, s, "phase", f"unknown phase {_show(phase[i])}; expected one of {', '.join(PHASES)}")

        t = float(time_s[i])
        if not math.isfinite(t):
            raise loc.error(i, s, "time_s", f"{_show(t)} is not finite")
        if t < 0:
            raise loc.error(i, s, "time_s", f"{_show(t)} s is negative; times are seconds >= 0")

        cmd_known = np.isfinite(cmd[i])
        cmd_nan = np.isnan(cmd[i])
        for k, col in enumerate(CMD_COLUMNS):
            if not cmd_known[k] and not cmd_nan[k]:
                raise loc.error(i, s, col, f"{_show(float(cmd[i, k]))} is not finite")
        if cmd_known.any() and not cmd_known.all():
            missing = [c for c, known in zip(CMD_COLUMNS, cmd_known, strict=True) if not known]
            raise loc.error(
                i,
                s,
                missing[0],
                f"commanded pose is partly given ({', '.join(missing)} empty); "
                "give all six cmd_* values or leave all six empty when the commanded pose is unknown",
            )

        for k, col in enumerate(LEG_COLUMNS):
            v = float(legs_mm[i, k])
            if not math.isfinite(v):
                raise loc.error(i, s, col, f"{_show(v)} is not finite")
            if robot is None and v <= 0:
                raise loc.error(i, s, col, f"{_show(v)} mm is not a positive leg length")
            if not leg_lo <= v <= leg_hi:
                raise loc.error(
                    i,
                    s,
                    col,
                    f"{_show(v)} mm is outside the physical range [{_bound(leg_lo)}, {_bound(leg_hi)}] mm "
                    f"(leg limits widened by {_bound(LEG_MARGIN_MM)} mm)",
                )

        for group, columns in (("meas", MEAS_COLUMNS), ("cmd", CMD_COLUMNS)):
            values = meas[i] if group == "meas" else cmd[i]
            if group == "cmd" and not cmd_known.all():
                continue
            for k, col in enumerate(columns):
                v = float(values[k])
                if not math.isfinite(v):
                    raise loc.error(i, s, col, f"{_show(v)} is not finite")
                lo, hi = pose_limits[k]
                if not lo <= v <= hi:
                    unit = "mm" if k < 3 else "deg"
                    if robot is None:
                        why = "plausible angle range"
                    elif k < 3:
                        why = f"workspace widened by {_bound(POSITION_MARGIN_MM)} mm"
                    else:
                        why = f"workspace widened by {_bound(ANGLE_MARGIN_DEG)} deg"
                    raise loc.error(
                        i,
                        s,
                        col,
                        f"{_show(v)} {unit} is outside the physical range "
                        f"[{_bound(lo)}, {_bound(hi)}] {unit} ({why})"
                        + (": a pose in an instrument's own frame? `hilcal import` with [frame] align brings it into "
                           "the base frame" if group == "meas" else ""),
                    )

        if temp is not None:
            if temp.dtype.kind != "f":
                raise loc.error(i, s, "temp_c", f"{_show(temp[i])} is not a number")
            v = float(temp[i])
            if not TEMP_RANGE_C[0] <= v <= TEMP_RANGE_C[1]:
                raise loc.error(
                    i,
                    s,
                    "temp_c",
                    f"{_show(v)} °C is outside the physical range [{_bound(TEMP_RANGE_C[0])}, "
                    f"{_bound(TEMP_RANGE_C[1])}] °C",
                )

        if station is not None:
            v = float(station[i]) if station.dtype.kind in "fiu" else math.nan
            if not (math.isfinite(v) and v >= 0 and v == int(v)):
                raise loc.error(i, s, "station", f"{_show(station[i])} is not a station number (an integer >= 0: "
                                "the instrument set-up the row was measured from)")

    n_measure = int(np.count_nonzero(phase == "measure"))
    if n_measure < min_measure_rows:
        raise RecordingError(
            f"{loc.source}, column phase: only {n_measure} 'measure' row(s); at least {min_measure_rows} are "
            f"needed: the {N_MODEL_PARAMETERS}-parameter model gets 6 equations per pose and needs more than "
            f"{N_MODEL_PARAMETERS}/6 = {N_MODEL_PARAMETERS // 6} poses for its residual variance to be "
            "estimable",
            line=None,
            column="phase",
        )
    if not np.any(phase == "verify"):
        log.warning(
            "recording has no verify rows; accuracy cannot be checked on independent poses", source=loc.source
        )


def _normalise_extra(extra: Mapping[str, Sequence | np.ndarray]) -> dict[str, np.ndarray]:
    """Float array where every cell parses as a float, else a str array (as read from a file)."""
    out: dict[str, np.ndarray] = {}
    for name, values in extra.items():
        arr = np.asarray(values)
        if arr.dtype.kind in "fiub":
            out[name] = arr.astype(float)
            continue
        cells = [str(v) for v in arr.tolist()]
        try:
            out[name] = np.array([float(c) for c in cells], dtype=float)
        except ValueError:
            out[name] = np.array(cells, dtype=str)
    return out


def recording_from_arrays(
    seq: Sequence[int] | np.ndarray,
    phase: Sequence[str] | np.ndarray,
    time_s: Sequence[float] | np.ndarray,
    cmd: Sequence[Sequence[float]] | np.ndarray | None,
    legs_mm: Sequence[Sequence[float]] | np.ndarray,
    meas: Sequence[Sequence[float]] | np.ndarray,
    extra: Mapping[str, Sequence | np.ndarray] | None = None,
    *,
    robot: Robot | None = None,
    min_measure_rows: int = 8,
    source: str = "<arrays>",
) -> Recording:
    """Build a Recording from arrays, validated exactly as ``read_recording`` validates a file.

    ``cmd`` may be None (no commanded poses) or hold all-NaN rows where the commanded pose is unknown.
    Errors name the 1-based row instead of a file line (``RecordingError.line`` is None).
    """
    seq_arr = np.asarray(seq)
    n = seq_arr.shape[0] if seq_arr.ndim == 1 else -1
    if seq_arr.ndim != 1:
        raise RecordingError(
            f"{source}: seq must be one-dimensional, got shape {seq_arr.shape}", column="seq"
        )
    if seq_arr.dtype.kind == "f":
        bad = ~np.isfinite(seq_arr) | (seq_arr != np.round(seq_arr))
        if np.any(bad):
            i = int(np.argmax(bad))
            raise _Locator(source, None).error(i, None, "seq", f"{_show(seq_arr[i])} is not an integer")
    elif seq_arr.dtype.kind not in "iu":
        raise RecordingError(f"{source}: seq must be integers, got dtype {seq_arr.dtype}", column="seq")
    arrays = {
        "phase": np.asarray(phase, dtype=str),
        "time_s": np.asarray(time_s, dtype=float),
        "cmd": np.full((n, 6), np.nan) if cmd is None else np.asarray(cmd, dtype=float),
        "legs_mm": np.asarray(legs_mm, dtype=float),
        "meas": np.asarray(meas, dtype=float),
    }
    want = {"phase": (n,), "time_s": (n,), "cmd": (n, 6), "legs_mm": (n, 6), "meas": (n, 6)}
    for name, arr in arrays.items():
        if arr.shape != want[name]:
            raise RecordingError(
                f"{source}: {name} has shape {arr.shape}, expected {want[name]}", column=name
            )
    extra_arr = _normalise_extra(extra or {})
    for name, arr in extra_arr.items():
        if name in REQUIRED_COLUMNS:
            raise RecordingError(
                f"{source}: extra column {name!r} clashes with a required column", column=name
            )
        if arr.shape != (n,):
            raise RecordingError(
                f"{source}: extra column {name!r} has shape {arr.shape}, expected {(n,)}", column=name
            )
    rec = Recording(seq=seq_arr.astype(np.int64), extra=extra_arr, **arrays)
    _validate(rec, _Locator(source, None), robot, min_measure_rows)
    return rec


def read_recording(path: str | Path, robot: Robot | None = None, min_measure_rows: int = 8) -> Recording:
    """Read and validate a recording CSV; with a robot, values are also checked against its physical range."""
    source = str(path)
    rows: list[tuple[list[str], int]] = []
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            for cells in reader:
                if any(c.strip() for c in cells):
                    rows.append((cells, reader.line_num))
    except OSError as err:
        raise RecordingError(f"{source}: cannot read: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise RecordingError(f"{source}: not a UTF-8 text file: {err.reason}") from None
    except csv.Error as err:
        raise RecordingError(f"{source}: not a valid CSV file: {err}") from None
    if not rows:
        raise RecordingError(f"{source} line 1: the file is empty (expected a header row)", line=1)

    header = [name.strip() for name in rows[0][0]]
    seen: dict[str, int] = {}
    for k, name in enumerate(header):
        if name in seen:
            raise RecordingError(
                f"{source} line 1, column {name}: duplicate column name "
                f"(columns {seen[name] + 1} and {k + 1})",
                line=1,
                column=name,
            )
        seen[name] = k
    missing = [c for c in REQUIRED_COLUMNS if c not in seen]
    if missing:
        raise RecordingError(
            f"{source} line 1, column {', '.join(missing)}: missing required column(s) {', '.join(missing)}",
            line=1,
            column=", ".join(missing),
        )
    extra_names = [name for name in header if name not in REQUIRED_COLUMNS]

    data = rows[1:]
    lines = [line for _, line in data]
    loc = _Locator(source, lines)
    n = len(data)
    seq = np.empty(n, dtype=np.int64)
    phase: list[str] = []
    time_s = np.empty(n)
    cmd = np.empty((n, 6))
    legs = np.empty((n, 6))
    meas = np.empty((n, 6))
    extra_cells: dict[str, list[str]] = {name: [] for name in extra_names}

    for i, (cells, _line) in enumerate(data):
        if len(cells) != len(header):
            col = header[len(cells)] if len(cells) < len(header) else None
            where = loc.where(i, None)
            detail = f"row has {len(cells)} cells but the header has {len(header)}"
            if col is not None:
                raise RecordingError(f"{where}, column {col}: {detail}", line=lines[i], column=col)
            raise RecordingError(f"{where}: {detail}", line=lines[i], column=None)
        cell = {name: cells[k] for name, k in seen.items()}

        text = cell["seq"].strip()
        try:
            seq[i] = int(text)
        except ValueError:
            raise loc.error(i, None, "seq", f"{text!r} is not an integer") from None
        s = int(seq[i])

        phase.append(cell["phase"].strip())
        time_s[i] = _parse_number(cell["time_s"], loc, i, s, "time_s")
        cmd_texts = [cell[c].strip() for c in CMD_COLUMNS]
        if all(t == "" for t in cmd_texts):
            cmd[i] = np.nan
        else:
            for k, col in enumerate(CMD_COLUMNS):
                if cmd_texts[k] == "":
                    empty = [c for c, t in zip(CMD_COLUMNS, cmd_texts, strict=True) if t == ""]
                    raise loc.error(
                        i,
                        s,
                        col,
                        f"commanded pose is partly given ({', '.join(empty)} empty); "
                        "give all six cmd_* values or leave all six empty when the commanded pose is unknown",
                    )
                cmd[i, k] = _parse_number(cmd_texts[k], loc, i, s, col)
                if not math.isfinite(cmd[i, k]):
                    raise loc.error(
                        i,
                        s,
                        col,
                        f"{cmd_texts[k]!r} is not finite; leave all six cmd_* cells empty when the "
                        "commanded pose is unknown",
                    )
        for k, col in enumerate(LEG_COLUMNS):
            legs[i, k] = _parse_number(cell[col], loc, i, s, col)
        for k, col in enumerate(MEAS_COLUMNS):
            meas[i, k] = _parse_number(cell[col], loc, i, s, col)
        for name in extra_names:
            extra_cells[name].append(cell[name])
        if "temp_c" in cell:
            _parse_number(cell["temp_c"], loc, i, s, "temp_c")
        for name in FORCE_COLUMNS:  # measured loads: a number, or empty where the row has none
            if cell.get(name, "").strip():
                _parse_number(cell[name], loc, i, s, name)

    extra = _normalise_extra(extra_cells)
    rec = Recording(
        seq=seq,
        phase=np.array(phase, dtype=str),
        time_s=time_s,
        cmd=cmd,
        legs_mm=legs,
        meas=meas,
        extra=extra,
    )
    _validate(rec, loc, robot, min_measure_rows)
    return rec


def _parse_number(text: str, loc: _Locator, row: int, seq: int, column: str) -> float:
    """A cell as a float, or a RecordingError naming the line and column."""
    stripped = text.strip()
    if stripped == "":
        raise loc.error(row, seq, column, "empty cell; a number is required")
    try:
        return float(stripped)
    except ValueError:
        raise loc.error(row, seq, column, f"{stripped!r} is not a number") from None


def write_recording(path: str | Path, rec: Recording) -> None:
    """Write a recording CSV that reads back to identical arrays (exact float text; NaN cmd rows empty)."""
    extra_names = list(rec.extra)
    clash = [name for name in extra_names if name in REQUIRED_COLUMNS]
    if clash:
        raise ValueError(f"extra columns {clash} clash with required columns")
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow([*REQUIRED_COLUMNS, *extra_names])
        for i in range(rec.n):
            cmd_cells = [""] * 6 if np.all(np.isnan(rec.cmd[i])) else [_fmt(v) for v in rec.cmd[i]]
            extra_cells = [
                _fmt(col[i]) if col.dtype.kind == "f" else str(col[i]) for col in rec.extra.values()
            ]
            writer.writerow(
                [
                    str(int(rec.seq[i])),
                    str(rec.phase[i]),
                    _fmt(rec.time_s[i]),
                    *cmd_cells,
                    *(_fmt(v) for v in rec.legs_mm[i]),
                    *(_fmt(v) for v in rec.meas[i]),
                    *extra_cells,
                ]
            )
