"""Which robot a run is about: the robot file a station file names, and one robot agreed among the places that name
one (the station, the simulator, the run's options), compared by content with the first difference in words."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from hilcal.robot import Robot, RobotFileError, load_robot
from procedures.station import StationConfigError

BUILT_IN_ROBOT = "the built-in paper Table 1 robot"


def named_robot(path: str | Path) -> Path | None:
    """The robot file a station file names (relative to the station file), None if it names none.

    Only the ``robot`` key is read: a ``--sim`` run's station file may hold only its [timing] and sign-off settings.
    """
    p = Path(path)
    try:
        value = tomllib.loads(p.read_text()).get("robot")
    except OSError as err:
        raise StationConfigError(f"station file {p}: cannot read: {err.strerror}") from None
    except tomllib.TOMLDecodeError as err:
        raise StationConfigError(f"station file {p}: not valid TOML: {err}") from None
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise StationConfigError(f"station file {p}: robot: a robot file's path is expected, not {value!r}")
    return Path(value) if Path(value).is_absolute() else p.resolve().parent / value


def agreed_robot(sources: list[tuple[str, Path | None]]) -> Path | None:
    """The one robot of a run from the places that name one, each (what it is, its robot file; None: the built-in
    robot), first the one to use: they must hold the same robot, by content (two files may hold it). The first's file;
    StationConfigError naming both places and the first difference where two are not the same robot.
    """
    if not sources:
        return None
    try:
        robots = [load_robot(path) for _, path in sources]
    except RobotFileError as err:
        raise StationConfigError(str(err)) from None
    for (other, _), robot in zip(sources[1:], robots[1:], strict=True):
        difference = robot_difference(robots[0], robot)
        if difference is not None:
            raise StationConfigError(f"two robots: {sources[0][0]} and {other} are not the same robot: {difference}. "
                                     "A run plans, moves and measures with one robot")
    return sources[0][1]


def robot_difference(a: Robot, b: Robot) -> str | None:
    """The first difference between two robots' content, in the robot file's order (name, legs, home, workspace, leg
    limits, mass, CMM spheres, ...) and in words ("leg 3's a_mm differs: y 12.0 vs 12.5 mm"); None: the same robot."""
    found = _first_difference(a.spec.model_dump(), b.spec.model_dump(), ())
    if found is None:
        return None
    path, va, vb = found
    if path == ("name",):
        return f"the robot names differ: {va!r} vs {vb!r}"
    words: list[str] = []
    component = ""
    for i, p in enumerate(path):
        if isinstance(p, str):
            words.append(p)
        elif path[i - 1] == "legs":
            words[-1] = f"leg {p + 1}'s"
        elif i < len(path) - 1:
            words.append(str(p + 1))  # a sphere's number
        else:  # a coordinate of a vector, or the end of a workspace range
            component = ("min ", "max ")[p] if path[i - 1] in _RANGES else f"{'xyz'[p]} "
    key = next(p for p in reversed(path) if isinstance(p, str))
    unit = next((f" {u}" for u in ("mm", "deg", "kg") if key.endswith(f"_{u}")), "")
    numbers = all(isinstance(v, float | int) and not isinstance(v, bool) for v in (va, vb))
    return f"{' '.join(words)} differs: {component}{_said(va)} vs {_said(vb)}{unit if numbers else ''}"


_RANGES = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
"""The workspace's [min, max] pairs."""


def _said(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, dict):
        return "a section"
    if isinstance(value, list | tuple):
        return f"{len(value)} entries"
    return repr(value)


def _first_difference(a: Any, b: Any, path: tuple) -> tuple[tuple, Any, Any] | None:
    """(path, a's value, b's value) of the first difference between two parsed robot files, None if they are equal."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in [*a, *(k for k in b if k not in a)]:
            found = _first_difference(a.get(key), b.get(key), (*path, key))
            if found is not None:
                return found
        return None
    if isinstance(a, list | tuple) and isinstance(b, list | tuple) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            found = _first_difference(x, y, (*path, i))
            if found is not None:
                return found
        return None
    if all(isinstance(v, float) for v in (a, b)):
        return None if abs(a - b) <= 1e-9 * max(1.0, abs(a), abs(b)) else (path, a, b)
    return None if a == b else (path, a, b)
