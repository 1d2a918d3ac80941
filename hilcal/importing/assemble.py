"""`hilcal import` as a function: CSV files and a mapping in, one validated recording and its session summary out.

Every file is read and converted before anything is built; the first problem stops the import with an
ImportFileError naming the file, line and column (missing columns, files whose columns disagree, empty or
non-numeric cells, NaN, duplicate rows, units that do not fit the values). Rows keep their file and line in the
``source_file`` and ``source_line`` columns of the recording.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hilcal.importing import conversions as conv
from hilcal.importing.errors import ImportFileError, ValueProblem
from hilcal.importing.frames import FrameAlignment, FrameAlignmentError, align_frames, align_frames_shared_target
from hilcal.importing.incomplete import leave_out_incomplete
from hilcal.importing.mapping import ImportMap, OrientationMap, PoseColumns
from hilcal.importing.sessions import (
    HoldOut,
    clocks,
    missing_session_start,
    phases_from_column,
    phases_from_hold_out,
    row_clock,
    stamps_seconds,
)
from hilcal.importing.summary import SessionSummary, summarise
from hilcal.importing.table import Table, read_table
from hilcal.importing.targets import register_targets
from hilcal.recording import (
    FORCE_COLUMNS,
    TEMP_RANGE_C,
    Recording,
    RecordingError,
    recording_from_arrays,
    session_numbers,
)
from hilcal.robot import Robot
from hilcal.wiring import LegWiring, check_wiring

_RECORDING_MESSAGE = re.compile(r"imported recording(?: row (\d+))?(?: \(seq \d+\))?(?:, column [^:]+)?: (.*)$", re.S)


@dataclass(frozen=True)
class ImportResult:
    """The imported recording, its sessions, the files in order, notes the user should read, and the rows left out
    (``skip_incomplete``: one sentence each, file and line first)."""

    recording: Recording
    sessions: tuple[SessionSummary, ...]
    files: tuple[str, ...]
    notes: tuple[str, ...]
    left_out: tuple[str, ...] = ()


@dataclass(frozen=True)
class _FileRows:
    """One file's rows converted to the recording's units."""

    table: Table
    legs_mm: np.ndarray
    meas: np.ndarray
    cmd: np.ndarray | None
    seconds: np.ndarray
    phase: np.ndarray
    temp_c: np.ndarray | None
    fit_rms_mm: np.ndarray | None
    force_kn: np.ndarray | None = None


def _at(table: Table, columns: Sequence[str], problem: ValueProblem) -> ImportFileError:
    column = columns[problem.column] if 0 <= problem.column < len(columns) else ", ".join(columns)
    return table.error(problem.row, column, problem.detail)


def _orientation_labels(orientation: OrientationMap) -> list[str]:
    """The column to blame for roll, pitch, yaw: its own for rpy kinds, the whole group otherwise."""
    if orientation.kind in ("rpy_deg", "rpy_rad"):
        return list(orientation.columns)
    return [", ".join(orientation.columns)] * 3


def _pose(table: Table, pose: PoseColumns, robot: Robot | None, *, allow_empty_rows: bool) -> np.ndarray:
    """(n, 6) pose from position and orientation columns, checked; all-empty rows give NaN when allowed."""
    columns = [*pose.position.columns, *pose.orientation.columns]
    values = table.numbers(columns, allow_empty_rows=allow_empty_rows)
    known = np.all(np.isfinite(values), axis=1)
    out = np.full((table.n, 6), np.nan)
    out[known, :3] = conv.position_mm(values[known, :3], pose.position.unit)
    try:
        out[known, 3:] = conv.orientation_deg(values[known, 3:], pose.orientation.kind, pose.orientation.sequence)
    except ValueProblem as p:
        row = int(np.flatnonzero(known)[p.row])
        raise _at(table, pose.orientation.columns, ValueProblem(row, p.column, p.detail)) from None
    labels = [*pose.position.columns, *_orientation_labels(pose.orientation)]
    try:
        conv.check_pose(out[known], robot)
    except ValueProblem as p:
        raise _at(table, labels, ValueProblem(int(np.flatnonzero(known)[p.row]), p.column, p.detail)) from None
    return out


def _measured(table: Table, mapping: ImportMap, robot: Robot | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The measured pose (n, 6) and, from target points, the registration RMS (n,). Poses still to be aligned to the
    base frame are checked after the alignment."""
    targets = mapping.targets
    aligned_later = mapping.frame.align != "none"
    if targets is None:
        assert mapping.position is not None and mapping.orientation is not None
        columns = PoseColumns(position=mapping.position, orientation=mapping.orientation)
        return _pose(table, columns, None if aligned_later else robot, allow_empty_rows=False), None
    scale = conv.MM_PER_UNIT[targets.unit]
    points = {body: scale * table.numbers([c for t in getattr(targets, body) for c in t.columns]).reshape(
        table.n, -1, 3) for body in ("platform", "base") if getattr(targets, body)}
    first_columns = [t.columns[0] for t in (*targets.platform, *targets.base)]
    try:
        fit = register_targets(points["platform"], targets.layout("platform"), points.get("base"),
                               targets.layout("base") if targets.base else None)
    except ValueProblem as p:
        raise _at(table, first_columns, p) from None
    if not aligned_later:
        try:
            conv.check_pose(fit.pose, robot)
        except ValueProblem as p:
            raise _at(table, _pose_labels(mapping), p) from None
    return fit.pose, fit.rms_mm


def _pose_labels(mapping: ImportMap) -> list[str]:
    """The column to blame for each of x, y, z, roll, pitch, yaw of the measured pose."""
    if mapping.targets is not None:
        return [f"targets {', '.join(t.name for t in mapping.targets.platform)}"] * 6
    assert mapping.position is not None and mapping.orientation is not None
    return [*mapping.position.columns, *_orientation_labels(mapping.orientation)]


LEVER_NOTE_MM = 50.0
"""A target this far from the platform frame's origin gets a note on the lever of its orientation noise."""
SHARED_FRAME_MARGIN_MM = 2.0
"""A shared frame may leave this much more (RMS) than the files' own frames before it is taken for a moved
instrument: with few rows a file's own frame also absorbs some geometric error."""


def _far_worse(shared_rms_mm: float, own_rms_mm: float) -> bool:
    """A frame (or target place) shared by files fits far worse than a file's own: it moved between the files."""
    return shared_rms_mm > 3.0 * own_rms_mm + SHARED_FRAME_MARGIN_MM


def _fit_frame(part: list[_FileRows], robot: Robot) -> FrameAlignment:
    try:
        return align_frames(np.concatenate([r.meas for r in part]), np.concatenate([r.legs_mm for r in part]), robot)
    except FrameAlignmentError as e:
        raise ImportFileError(", ".join(r.table.source for r in part), str(e)) from None


def _fit_shared_target(rows: list[_FileRows], robot: Robot) -> list[FrameAlignment]:
    """Every file's instrument frame with one target place; refused (with the key to set) where the files' own
    target places fit far better: the target was mounted anew too."""
    try:
        joint, own = align_frames_shared_target([(r.meas, r.legs_mm) for r in rows], robot)
    except FrameAlignmentError as e:
        raise ImportFileError(", ".join(r.table.source for r in rows), str(e)) from None
    worst = max(range(len(rows)), key=lambda k: joint[k].rms_position_mm - 3.0 * own[k].rms_position_mm)
    if _far_worse(joint[worst].rms_position_mm, own[worst].rms_position_mm):
        raise ImportFileError(
            rows[worst].table.source,
            f"one target place for every file leaves {joint[worst].rms_position_mm:.3f} mm RMS in this file, its "
            f"own {own[worst].rms_position_mm:.3f} mm: the target was mounted anew between the files; set [frame] "
            'target = "per_file"')
    return joint


def _check_shared(shared: FrameAlignment, rows: list[_FileRows], robot: Robot) -> None:
    """A shared frame that the files' own frames beat by far: the instrument was set up again between files."""
    try:
        own = max(align_frames(r.meas, r.legs_mm, robot).rms_position_mm for r in rows)
    except FrameAlignmentError:
        return  # a file too small to align alone: nothing to compare with
    if _far_worse(shared.rms_position_mm, own):
        raise ImportFileError(
            ", ".join(r.table.source for r in rows),
            f'[frame] align = "shared" leaves {shared.rms_position_mm:.3f} mm RMS between the logged poses and the '
            f"leg lengths, but each file aligned alone leaves at most {own:.3f} mm: the instrument was set up again "
            'between the files; set [frame] align = "per_file"')


def _align(rows: list[_FileRows], mapping: ImportMap, robot: Robot | None) -> tuple[list[_FileRows], list[str]]:
    """Measured poses from the instrument's frame into the base frame ([frame] align), checked there; notes."""
    mode = mapping.frame.align
    if mode == "none":
        return rows, []
    if robot is None:
        raise ImportFileError("the mapping file", f"[frame] align = {mode!r} needs the robot file (--robot): the "
                              "nominal geometry turns leg lengths into the poses the instrument's frame is fitted to")
    if mode == "per_file" and mapping.frame.target == "shared" and len(rows) > 1:
        pairs = list(zip([[r] for r in rows], _fit_shared_target(rows, robot), strict=True))
    else:
        pairs = [(part, _fit_frame(part, robot)) for part in ([rows] if mode == "shared" else [[r] for r in rows])]
        if mode == "shared" and len(rows) > 1:
            _check_shared(pairs[0][1], rows, robot)
    out: list[_FileRows] = []
    notes = []
    for part, fit in pairs:
        where = "all files" if mode == "shared" else part[0].table.source
        notes.append(f"[frame] aligned ({where}): {fit.describe()}")
        lever_mm = float(np.linalg.norm(fit.target_in_platform[:3]))
        if lever_mm > LEVER_NOTE_MM and not any(f"the target is {lever_mm:.0f} mm" in n for n in notes):
            notes.append(f"[frame] the target is {lever_mm:.0f} mm from the platform frame's origin ({where}): the "
                         f"instrument's orientation noise moves the recorded origin on that lever, so its position "
                         f"sigma per coordinate (--pose-sigma-mm of `hilcal diagnose`) is about sqrt(position sigma² "
                         f"+ 2/3 (orientation sigma in rad × {lever_mm:.0f} mm)²)")
        for r in part:
            meas = fit.apply(r.meas)
            try:
                conv.check_pose(meas, robot)
            except ValueProblem as p:
                raise _at(r.table, _pose_labels(mapping), ValueProblem(p.row, p.column, p.detail + " (after the "
                          "[frame] alignment)")) from None
            out.append(dataclasses.replace(r, meas=meas))
    if mode == "per_file" and len(rows) > 1:
        notes.append("[frame] per_file: each file is an instrument station (the recording's station column): its "
                     "frame is aligned here with the nominal geometry, then `hilcal identify` and `hilcal diagnose` "
                     "fit every file's frame but the first again, together with the geometry and the effects, so no "
                     "file's alignment takes up the geometric errors as a session change"
                     + ("; the target's place per file is the alignment's and is not fitted again"
                        if mapping.frame.target == "per_file" else ""))
    return out, notes


def _convert(table: Table, mapping: ImportMap, robot: Robot | None, hold_out: HoldOut | None) -> _FileRows:
    """Parse, convert and check every mapped column of one file."""
    legs = mapping.legs
    readings = table.numbers(legs.columns)
    lengths = conv.legs_mm(readings, legs)
    try:
        conv.check_legs(lengths, readings, legs, robot)
    except ValueProblem as p:
        raise _at(table, legs.columns, p) from None
    meas, rms = _measured(table, mapping, robot)
    if mapping.fit_rms is not None:
        column = mapping.fit_rms.column
        rms = conv.MM_PER_UNIT[mapping.fit_rms.unit] * table.numbers([column])[:, 0]
        if np.any(rms < 0):
            i = int(np.argmax(rms < 0))
            raise table.error(i, column, f"{rms[i]:g} mm: a registration RMS cannot be negative")
    cmd = None if mapping.command is None else _pose(table, mapping.command, robot, allow_empty_rows=True)

    seconds = row_clock(table.n)
    if mapping.time is not None:
        column = mapping.time.column
        numbers = None if mapping.time.unit == "iso" else table.numbers([column])[:, 0]
        try:
            seconds = stamps_seconds(table.texts(column), mapping.time.unit, numbers)
        except ValueProblem as p:
            raise _at(table, [column], p) from None

    if mapping.phase is not None:
        try:
            phase = phases_from_column(table.texts(mapping.phase.column), mapping.phase.measure_values,
                                       mapping.phase.verify_values)
        except ValueProblem as p:
            raise _at(table, [mapping.phase.column], p) from None
    else:
        phase = phases_from_hold_out(table.n, table.name, hold_out)

    temp = None
    if mapping.temperature is not None:
        column = mapping.temperature.column
        temp = mapping.temperature.celsius(table.numbers([column])[:, 0])
        bad = (temp < TEMP_RANGE_C[0]) | (temp > TEMP_RANGE_C[1])
        if np.any(bad):
            i = int(np.argmax(bad))
            raise table.error(i, column, f"{temp[i]:g} °C is outside [{TEMP_RANGE_C[0]:g}, {TEMP_RANGE_C[1]:g}] °C: "
                              f"check [temperature] unit ({mapping.temperature.unit})")
    force = None
    if mapping.force is not None:
        force = mapping.force.forces_kn({c: table.numbers([c])[:, 0] for c in mapping.force.all_columns()})
    return _FileRows(table, lengths, meas, cmd, seconds, phase, temp, rms, force)


def _check_columns(tables: Sequence[Table], mapping: ImportMap) -> None:
    """Every mapped column exists (in the first file), and every file has the same columns as the first."""
    first = tables[0]
    for column in mapping.columns():
        first.index(column)
    for table in tables[1:]:
        missing = [c for c in first.header if c not in table.header]
        extra = [c for c in table.header if c not in first.header]
        if missing:
            raise table.error(None, missing[0], f"the file has no column {missing[0]!r}, which {first.source} has: "
                              f"files whose columns disagree ({len(missing)} missing) cannot be one recording")
        if extra:
            raise table.error(None, extra[0], f"column {extra[0]!r} is not in {first.source}: files whose columns "
                              f"disagree ({len(extra)} extra) cannot be one recording")
        for column in mapping.columns():
            table.index(column)


def _check_duplicates(tables: Sequence[Table], columns: Sequence[str]) -> None:
    """No row repeats an earlier row (in any file) in every mapped column: the same sample written twice."""
    seen: dict[tuple[str, ...], tuple[str, int]] = {}
    for table in tables:
        cells = [table.texts(c) for c in columns]
        for i in range(table.n):
            key = tuple(col[i] for col in cells)
            if key in seen:
                source, line = seen[key]
                if (source, line) == (table.source, table.lines[i]):
                    raise table.error(None, None, "the same file is given twice")
                where = f"line {line}" if source == table.source else f"{source} line {line}"
                raise table.error(i, columns[0], f"duplicate row: the same values as {where} in every mapped column "
                                  f"({len(columns)} columns)")
            seen[key] = (table.source, table.lines[i])


def _hold_out_file(tables: Sequence[Table], hold_out: HoldOut | None) -> None:
    if hold_out is None or hold_out.file is None:
        return
    names = [t.name for t in tables]
    if hold_out.file not in names:
        raise ImportFileError("--hold-out", f"file:{hold_out.file} names none of the input files "
                              f"({', '.join(names)})")
    if names.count(hold_out.file) > 1:
        raise ImportFileError("--hold-out", f"file:{hold_out.file} names {names.count(hold_out.file)} input files")


def _recording_error(err: RecordingError, rows: Sequence[_FileRows]) -> ImportFileError:
    """A RecordingError of the assembled arrays, with its row number turned back into a file and line."""
    message = str(err)
    m = _RECORDING_MESSAGE.match(message)
    detail = message if m is None else m.group(2)
    if m is not None and m.group(1):
        index = int(m.group(1)) - 1
        for part in rows:
            if index < part.table.n:
                return ImportFileError(part.table.source, detail, line=part.table.lines[index], column=err.column)
            index -= part.table.n
    return ImportFileError("imported recording", detail, column=err.column)


def _clocks(rows: Sequence[_FileRows], mapping: ImportMap) -> np.ndarray:
    mode = "per_file" if mapping.time is None else mapping.time.clock_mode
    per_file = clocks([r.seconds for r in rows], mode)
    time_s = np.concatenate(per_file)
    if mode == "per_file":
        k = missing_session_start(per_file, session_numbers(time_s))
        if k is not None:
            previous, table = rows[k - 1].table, rows[k].table
            column = None if mapping.time is None else mapping.time.column
            raise table.error(0, column, f"the file's clock does not restart after {previous.source}, so it would "
                              "join that file's session: a file's first row must be its earliest (or set [time] "
                              "clock = 'shared')")
    return time_s


def _notes(rows: Sequence[_FileRows], mapping: ImportMap, robot: Robot | None, hold_out: HoldOut | None) -> list[str]:
    notes = []
    if robot is None:
        notes.append("no robot file: leg lengths and poses were checked for plausibility only, not against a robot's "
                     "limits (give --robot)")
    if mapping.phase is not None and hold_out is not None:
        notes.append(f"the map's [phase] column decides the phases; --hold-out {hold_out.describe()} is not used")
    if mapping.time is None:
        notes.append("no [time] column: time_s counts the rows of each file (the order is known, not the times)")
    if mapping.targets is not None and robot is not None:
        same = all(
            len(mapping.targets.layout(body)) == len(layout)
            and np.allclose(mapping.targets.layout(body), layout, atol=0.01)
            for body, layout in (("platform", robot.platform_spheres), ("base", robot.base_spheres))
        )
        if not same:
            notes.append("the map's targets differ from the robot file's [cmm] spheres: `hilcal diagnose` reads "
                         "sphere_fit_rms_mm against the robot file's layout, so put the targets there")
    if robot is not None:
        wiring = check_wiring(np.concatenate([r.legs_mm for r in rows]), np.concatenate([r.meas for r in rows]), robot)
        if wiring.problem:
            note = f"leg wiring: {wiring.sentence(list(mapping.legs.columns))}"
            if wiring.reordered and not wiring.dead:
                order = ", ".join(f'"{mapping.legs.columns[j]}"' for j in wiring.column_of_leg)
                note += f"; if the robot file's numbering is right, set [legs] columns = [{order}]"
            if wiring.reversed_legs and not wiring.dead:
                note += _reversed_fix(mapping, wiring)
            notes.append(note)
    if not any(np.any(r.phase == "verify") for r in rows):
        notes.append("no verify rows: accuracy cannot be judged on held-out poses (use --hold-out or [phase])")
    return notes


def _reversed_fix(mapping: ImportMap, wiring: LegWiring) -> str:
    """The [legs] values that read the reversed legs the right way: length = mirror - (zero + k r) = (mirror - zero)
    - k r, so the sign of mm_per_unit flips and zero_mm becomes mirror - zero; mm and m readings cannot flip."""
    if mapping.legs.unit not in ("count", "rev"):
        return ("; the mapping reads mm and m as they are, so reverse the direction sign in the logger or "
                "controller")
    scale, zero = mapping.legs.scale_mm(), mapping.legs.zero()
    for leg in wiring.reversed_legs:
        column = int(wiring.column_of_leg[leg - 1])
        scale[column], zero[column] = -scale[column], wiring.mirror_mm[leg - 1] - zero[column]
    return (f"; to read them the right way set [legs] mm_per_unit = [{', '.join(f'{v:g}' for v in scale)}] and "
            f"zero_mm = [{', '.join(f'{v:.3f}' for v in zero)}] (the new zeros are fitted to the nominal geometry: "
            "check them against the machine's home)")


def import_recording(
    paths: Sequence[str | Path],
    mapping: ImportMap,
    *,
    robot: Robot | None = None,
    hold_out: HoldOut | None = None,
    min_measure_rows: int = 8,
    skip_incomplete: bool = False,
) -> ImportResult:
    """Read, convert and check every file, then build one recording (rows in file order, seq from 1).

    skip_incomplete: rows without a measurement or repeating an earlier row are left out and listed
    (``hilcal.importing.incomplete``) instead of being errors."""
    if not paths:
        raise ImportFileError("command line", "no input files")
    tables = [read_table(p, mapping.csv) for p in paths]
    _check_columns(tables, mapping)
    _hold_out_file(tables, hold_out)
    left_out: list[str] = []
    if skip_incomplete:
        twice = sorted({t.source for t in tables if sum(u.source == t.source for u in tables) > 1})
        if twice:
            raise ImportFileError(twice[0], "the same file is given twice")
        tables, left_out = leave_out_incomplete(tables, mapping)
    converted = [_convert(t, mapping, robot, hold_out) for t in tables]  # a file's own errors first, in file order
    _check_duplicates(tables, mapping.columns())
    rows, frame_notes = _align(converted, mapping, robot)
    time_s = _clocks(rows, mapping)
    extra: dict[str, np.ndarray] = {}
    if mapping.targets is not None or mapping.fit_rms is not None:
        extra["sphere_fit_rms_mm"] = np.concatenate([r.fit_rms_mm for r in rows])
    if mapping.temperature is not None:
        extra["temp_c"] = np.concatenate([r.temp_c for r in rows])
    if mapping.force is not None:
        forces = np.concatenate([r.force_kn for r in rows])
        extra |= {name: forces[:, k] for k, name in enumerate(FORCE_COLUMNS)}
    if mapping.frame.align == "per_file" and len(rows) > 1:  # every file a station, fitted with the model
        extra["station"] = np.concatenate([np.full(r.table.n, float(k)) for k, r in enumerate(rows)])
    file_of_row = np.concatenate([np.full(r.table.n, r.table.name, dtype=object) for r in rows]).astype(str)
    extra["source_file"] = file_of_row
    extra["source_line"] = np.concatenate([np.asarray(r.table.lines, dtype=float) for r in rows])
    n = sum(r.table.n for r in rows)
    try:
        rec = recording_from_arrays(
            seq=np.arange(1, n + 1),
            phase=np.concatenate([r.phase for r in rows]),
            time_s=np.round(time_s, 6),  # clocks tick in µs at best: 61.002, not 61.001999855041504
            cmd=None if mapping.command is None else np.concatenate([r.cmd for r in rows]),
            legs_mm=np.concatenate([r.legs_mm for r in rows]),
            meas=np.concatenate([r.meas for r in rows]),
            extra=extra,
            robot=robot,
            min_measure_rows=min_measure_rows,
            source="imported recording",
        )
    except RecordingError as err:
        raise _recording_error(err, rows) from None
    return ImportResult(recording=rec, sessions=summarise(rec, file_of_row, robot),
                        files=tuple(t.source for t in tables),
                        notes=(*frame_notes, *_notes(rows, mapping, robot, hold_out)), left_out=tuple(left_out))
