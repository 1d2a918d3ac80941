"""Commands that bring a machine's own data in: `hilcal import` (CSV files + mapping -> recording) and
`hilcal robot-from-geometry` (documented geometry -> robot file). Bad input exits 2 and writes nothing.

``hilcal.importing`` (and every hilcal module) is imported inside the commands, so the other commands and
`hilcal --help` do not pay for its start-up.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from procedures.cli.common import fail, out, robot_or_fail

if TYPE_CHECKING:
    from hilcal.importing import ImportResult
    from hilcal.robot import Robot

LEFT_OUT_SHOWN = 20
"""Rows left out by --skip-incomplete printed in the summary (--json lists every one)."""
_INCOMPLETE = re.compile(r"empty cell|NaN is not a measurement|duplicate row")
"""Import errors that --skip-incomplete turns into listed rows."""
MIN_REACHABLE_FRACTION = 0.05
"""Below this share of reachable poses in the travel box, pose designs and random poses barely find any."""


def _writable(path: Path, inputs: list[Path]) -> None:
    """Refuse an output that would overwrite an input, or whose folder does not exist."""
    if not path.parent.is_dir():
        fail(f"--out {path}: the folder {path.parent} does not exist")
    if path.is_dir():
        fail(f"--out {path} is a folder")
    if any(path.resolve() == p.resolve() for p in inputs):
        fail(f"--out {path} is one of the input files")


def _write_atomically(path: Path, write: Callable[[Path], object]) -> None:
    """Write to a temporary file next to ``path`` and rename it, so an interrupted write leaves nothing half-done."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as e:
        fail(f"--out {path}: cannot write: {e.strerror or e}")
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _range(lo: float, hi: float, digits: int) -> str:
    return f"{lo:.{digits}f} .. {hi:.{digits}f}"


def _print_summary(result: ImportResult, robot: Robot | None) -> None:
    from hilcal.robot import POSE_AXES

    sessions = Table(title="sessions (as `hilcal diagnose` sees them)")
    for col in ("session", "files", "rows", "measure", "verify", "time span s"):
        sessions.add_column(col, justify="left" if col == "files" else "right")
    for s in result.sessions:
        sessions.add_row(str(s.index), ", ".join(s.files), str(s.n_rows), str(s.n_measure), str(s.n_verify),
                         f"{s.time_span_s:.1f}")
    out.print(sessions)
    ranges = Table(title="ranges per session (legs and positions mm, angles deg)")
    ranges.add_column("quantity")
    for s in result.sessions:
        ranges.add_column(f"session {s.index}", justify="right")
    for k in range(6):
        ranges.add_row(f"leg{k + 1}_mm", *(_range(s.legs_min_mm[k], s.legs_max_mm[k], 3) for s in result.sessions))
    for k, axis in enumerate(POSE_AXES):
        ranges.add_row(axis, *(_range(s.pose_min[k], s.pose_max[k], 3 if k < 3 else 4) for s in result.sessions))
    if robot is not None:
        lo, hi = robot.leg_limits
        ranges.add_row(f"readings at a leg's extreme\n(within 1 % of [{lo:g}, {hi:g}] mm)", *(
            ", ".join(f"leg{k + 1}: {int(c)}" for k, c in enumerate(s.at_extreme) if c) or "none"
            for s in result.sessions if s.at_extreme is not None))
    out.print(ranges)
    for note in result.notes:
        out.print(f"[yellow]note:[/] {escape(note)}", highlight=False, markup=True)
    if result.left_out:
        out.print(f"[yellow]left out {len(result.left_out)} row(s)[/] (--skip-incomplete):", highlight=False,
                  markup=True)
        for sentence in result.left_out[:LEFT_OUT_SHOWN]:
            out.print(f"  {escape(sentence)}", highlight=False)
        if len(result.left_out) > LEFT_OUT_SHOWN:
            out.print(f"  ... and {len(result.left_out) - LEFT_OUT_SHOWN} more (--json lists every one)",
                      highlight=False)


def import_command(
    files: Annotated[list[Path], typer.Argument(help="CSV files; each is a session unless a shared clock says not")],
    map_file: Annotated[Path, typer.Option("--map", help="mapping TOML: which column holds what (docs/import.md)")],
    out_path: Annotated[Path, typer.Option("--out", help="recording CSV to write (docs/recording-format.md)")],
    robot: Annotated[Path | None, typer.Option(
        "--robot", help="robot TOML: leg lengths and poses are checked against its limits (default: no robot checks)",
    )] = None,
    hold_out: Annotated[str | None, typer.Option(
        "--hold-out", help="every:N (every N-th row of every file) or file:NAME (that file's rows) are verify rows",
    )] = None,
    skip_incomplete: Annotated[bool, typer.Option(
        "--skip-incomplete", help="leave out rows with an empty or NaN measurement cell and rows that repeat an "
        "earlier row, and list each (default: such a row is an error)",
    )] = False,
    as_json: Annotated[bool, typer.Option("--json", help="print the summary as one JSON object")] = False,
) -> None:
    """Write a recording from the CSV files that machines and trackers export, with a summary per session."""
    from hilcal.importing import ImportFileError, import_recording, load_map, parse_hold_out
    from hilcal.recording import write_recording

    try:
        mapping = load_map(map_file)
        chosen = None if hold_out is None else parse_hold_out(hold_out)
    except ValueError as e:
        fail(str(e))
    rb = None if robot is None else robot_or_fail(robot)
    _writable(out_path, files)
    try:
        result = import_recording(files, mapping, robot=rb, hold_out=chosen, skip_incomplete=skip_incomplete)
    except ImportFileError as e:
        hint = ("" if skip_incomplete or not _INCOMPLETE.search(e.detail) else
                " (--skip-incomplete leaves such rows out and lists them)")
        fail(str(e) + hint)
    _write_atomically(out_path, lambda tmp: write_recording(tmp, result.recording))
    rec = result.recording
    if as_json:
        print(json.dumps({"out": str(out_path), "rows": rec.n, "measure": int((rec.phase == "measure").sum()),
                          "verify": int((rec.phase == "verify").sum()), "files": list(result.files),
                          "sessions": [s.to_json() for s in result.sessions], "notes": list(result.notes),
                          "left_out": list(result.left_out)}, indent=2))
        return
    _print_summary(result, rb)
    out.print(f"wrote {out_path}: {rec.n} rows ({int((rec.phase == 'measure').sum())} measure, "
              f"{int((rec.phase == 'verify').sum())} verify) in {len(result.sessions)} session(s)")


def robot_from_geometry_command(
    geometry: Annotated[Path, typer.Argument(help="geometry TOML: joint circles, legs, home; travel and mass if "
                                             "known (the README's 'Describing your machine' has the format)")],
    out_path: Annotated[Path, typer.Option("--out", help="robot TOML to write")],
) -> None:
    """Write a robot file from the numbers in a machine's documentation (docs/import.md)."""
    from hilcal.importing import ImportFileError, check_geometry, geometry_robot_toml, load_geometry

    try:
        spec = load_geometry(geometry)
        robot, text, defaults = geometry_robot_toml(spec, str(geometry))
    except ImportFileError as e:
        fail(str(e))
    _writable(out_path, [geometry])
    check = check_geometry(robot)
    _write_atomically(out_path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
    legs = ", ".join(f"{v:.3f}" for v in check.home_legs_mm)
    lo, hi = check.leg_limits_mm
    out.print(f"home leg lengths: {legs} mm (limits {lo:g} .. {hi:g} mm)")
    out.print(f"travel box: {check.corners_reachable} of 64 corners and {check.reachable_fraction:.0%} of random "
              "poses are reachable (legs within limits, away from singularities)")
    if check.reachable_fraction < MIN_REACHABLE_FRACTION:
        out.print("[yellow]note:[/] the legs reach little of the travel box: check stroke, home and travel",
                  markup=True)
    if spec.cmm is None:
        out.print("[yellow]note:[/] no \\[cmm] section: the robot file holds a nominal tooling-sphere layout; "
                  "replace it with your spheres' positions before measuring with a CMM", highlight=False,
                  markup=True)
    for note in defaults.notes:
        out.print(f"[yellow]default[/] {escape(note)}", markup=True, highlight=False)
    out.print(f"wrote {out_path}")
