"""Write a recording in the formats that machines and trackers export, as described by an import mapping file.

This is example and test code, not part of hilcal: it makes the worked examples of docs/import.md and the round
trips of the tests (recording -> a machine's format -> `hilcal import` -> the same recording). It is written apart
from ``hilcal.importing``: orientations through scipy's Rotation, target points from the pose by hand. Only the
mapping model (column names, units) is shared, since it is what both sides read.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from hilcal.importing.mapping import ImportMap, OrientationMap, PositionMap
from hilcal.recording import Recording, session_numbers

MM_PER = {"mm": 1.0, "m": 1000.0, "in": 25.4}


@dataclass(frozen=True)
class ExportOptions:
    """How the files look: digits per group (None: exact repr), clock origins, preamble and unmapped columns."""

    decimals: Mapping[str, int] = field(default_factory=dict)
    """Digits after the point for 'legs', 'position', 'orientation', 'targets', 'time', 'temperature', 'fit_rms'."""
    start: datetime = datetime(2025, 3, 4, 8, 0, 0)
    """Wall-clock time of time_s = 0 (ISO stamps; epoch seconds of a shared s/ms clock)."""
    clock_origin_s: Sequence[float] | None = None
    """Per file, the recording time at which its own clock reads 0 (default: its first row)."""
    preamble: Sequence[str] = ()
    """Lines above the header (the mapping's csv.header_line must be len(preamble) + 1)."""
    extra_columns: Mapping[str, np.ndarray] = field(default_factory=dict)
    """Unmapped columns a real logger writes too, one value per recording row."""
    instrument_pose: np.ndarray | None = None
    """[x, y, z mm, roll, pitch, yaw deg] of the tracker's frame in the base frame (targets with base targets)."""
    measured_targets: np.ndarray | None = None
    """(n, K + M, 3) points as an instrument measured them (platform targets, then base targets), mm in its frame:
    written instead of points made from the recording's pose."""


def _rotation(rpy_deg: np.ndarray) -> Rotation:
    """R = Rz(yaw) Ry(pitch) Rx(roll): scipy's intrinsic ZYX."""
    return Rotation.from_euler("ZYX", np.asarray(rpy_deg)[..., ::-1], degrees=True)


def _text(value: float, digits: int | None, decimal: str) -> str:
    text = repr(float(value)) if digits is None else f"{value:.{digits}f}"
    return text.replace(".", ",") if decimal == "," else text


def _orientation_values(rpy_deg: np.ndarray, orientation: OrientationMap) -> np.ndarray:
    kind = orientation.kind
    if kind == "rpy_deg":
        return rpy_deg
    if kind == "rpy_rad":
        return np.radians(rpy_deg)
    rot = _rotation(rpy_deg)
    if kind == "matrix":
        return rot.as_matrix().reshape(len(rpy_deg), 9)
    xyzw = rot.as_quat()
    return xyzw if kind == "quaternion_xyzw" else xyzw[:, [3, 0, 1, 2]]


def _pose_columns(pose: np.ndarray, position: PositionMap, orientation: OrientationMap) -> dict[str, np.ndarray]:
    values = np.full((len(pose), 3 + len(orientation.columns)), np.nan)
    known = np.all(np.isfinite(pose), axis=1)
    values[known, :3] = pose[known, :3] / MM_PER[position.unit]
    values[known, 3:] = _orientation_values(pose[known, 3:], orientation)
    return dict(zip([*position.columns, *orientation.columns], values.T, strict=True))


def _target_columns(rec: Recording, mapping: ImportMap, instrument_pose: np.ndarray | None) -> dict[str, np.ndarray]:
    """Target points that register to the recording's pose with an RMS equal to its sphere_fit_rms_mm.

    The platform layout is scaled about its centroid by 1 + rms / (layout RMS radius): a rigid registration of
    such points returns the same rotation and translation and leaves exactly that RMS.
    """
    targets = mapping.targets
    assert targets is not None
    layout = np.array([t.position_mm for t in targets.platform])
    centre = layout.mean(axis=0)
    radius = np.sqrt(np.mean(np.sum((layout - centre) ** 2, axis=1)))
    rms = rec.extra.get("sphere_fit_rms_mm", np.zeros(rec.n))
    scaled = centre + (1.0 + rms / radius)[:, None, None] * (layout - centre)
    points = _rotation(rec.meas[:, 3:]).as_matrix() @ np.swapaxes(scaled, 1, 2)
    platform = np.swapaxes(points, 1, 2) + rec.meas[:, None, :3]
    bodies = [(targets.platform, platform)]
    if targets.base:
        frame = np.zeros(6) if instrument_pose is None else np.asarray(instrument_pose, dtype=float)
        to_instrument = _rotation(frame[3:]).inv()
        base = np.array([t.position_mm for t in targets.base])
        platform_i = to_instrument.apply((platform - frame[:3]).reshape(-1, 3)).reshape(platform.shape)
        base_i = np.broadcast_to(to_instrument.apply(base - frame[:3]), (rec.n, *base.shape))
        bodies = [(targets.platform, platform_i), (targets.base, base_i)]
    out = {}
    for body, pts in bodies:
        for k, target in enumerate(body):
            for axis, column in enumerate(target.columns):
                out[column] = pts[:, k, axis] / MM_PER[targets.unit]
    return out


def _columns(rec: Recording, mapping: ImportMap, options: ExportOptions) -> dict[str, tuple[np.ndarray, str]]:
    """Every mapped column as (values, digits group), in the mapping's units."""
    legs = mapping.legs
    readings = (rec.legs_mm - legs.zero()) / legs.scale_mm()
    out = {c: (readings[:, k], "legs") for k, c in enumerate(legs.columns)}
    if mapping.position is not None and mapping.orientation is not None:
        values = _pose_columns(rec.meas, mapping.position, mapping.orientation)
        out |= {c: (v, "position" if c in mapping.position.columns else "orientation") for c, v in values.items()}
    elif options.measured_targets is not None:
        assert mapping.targets is not None
        names = [t.columns for t in (*mapping.targets.platform, *mapping.targets.base)]
        scale = MM_PER[mapping.targets.unit]
        out |= {c: (options.measured_targets[:, k, axis] / scale, "targets")
                for k, cols in enumerate(names) for axis, c in enumerate(cols)}
    else:
        out |= {c: (v, "targets") for c, v in _target_columns(rec, mapping, options.instrument_pose).items()}
    if mapping.command is not None:
        cmd = mapping.command
        values = _pose_columns(rec.cmd, cmd.position, cmd.orientation)
        out |= {c: (v, "position" if c in cmd.position.columns else "orientation") for c, v in values.items()}
    if mapping.fit_rms is not None:
        out[mapping.fit_rms.column] = (rec.extra["sphere_fit_rms_mm"] / MM_PER[mapping.fit_rms.unit], "fit_rms")
    if mapping.temperature is not None:
        temp = {"C": rec.extra["temp_c"], "K": rec.extra["temp_c"] + 273.15,
                "F": rec.extra["temp_c"] * 1.8 + 32.0}[mapping.temperature.unit]
        out[mapping.temperature.column] = (temp, "temperature")
    return out


def _time_cells(time_s: np.ndarray, rows: np.ndarray, k: int, mapping: ImportMap, options: ExportOptions) -> list[str]:
    assert mapping.time is not None
    t = time_s[rows]
    if mapping.time.unit == "iso":
        return [(options.start + timedelta(seconds=float(v))).isoformat(timespec="microseconds") for v in t]
    if mapping.time.clock_mode == "shared":
        t = t + options.start.replace(tzinfo=UTC).timestamp()
    else:
        t = t - (t[0] if options.clock_origin_s is None else options.clock_origin_s[k])
    t = t * (1000.0 if mapping.time.unit == "ms" else 1.0)
    return [_text(v, options.decimals.get("time"), mapping.csv.decimal) for v in t]


def export_recording(rec: Recording, mapping: ImportMap, folder: Path, file_names: Sequence[str],
                     options: ExportOptions | None = None) -> list[Path]:
    """Write one file per session of the recording (file k holds session k) in the mapping's format."""
    options = options or ExportOptions()
    session = session_numbers(rec.time_s)
    if len(file_names) != session.max() + 1:
        raise ValueError(f"the recording has {session.max() + 1} session(s); give as many file names")
    columns = _columns(rec, mapping, options)
    header = [*options.extra_columns]
    if mapping.time is not None:
        header.append(mapping.time.column)
    if mapping.phase is not None:
        header.append(mapping.phase.column)
    header += list(columns)
    paths = []
    for k, name in enumerate(file_names):
        rows = np.flatnonzero(session == k)
        cells: dict[str, list[str]] = {c: [str(v) for v in values[rows]] for c, values in options.extra_columns.items()}
        if mapping.time is not None:
            cells[mapping.time.column] = _time_cells(rec.time_s, rows, k, mapping, options)
        if mapping.phase is not None:
            labels = {"measure": mapping.phase.measure_values[0], "verify": mapping.phase.verify_values[0]}
            cells[mapping.phase.column] = [labels[p] for p in rec.phase[rows]]
        for column, (values, group) in columns.items():
            digits = options.decimals.get(group)
            cells[column] = ["" if np.isnan(v) else _text(v, digits, mapping.csv.decimal) for v in values[rows]]
        path = folder / name
        with open(path, "w", newline="", encoding="utf-8") as fh:
            fh.writelines(f"{line}\n" for line in options.preamble)
            writer = csv.writer(fh, delimiter=mapping.csv.delimiter, lineterminator="\n")
            writer.writerow(header)
            writer.writerows(zip(*(cells[c] for c in header), strict=True))
        paths.append(path)
    return paths
