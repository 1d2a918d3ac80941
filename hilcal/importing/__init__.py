"""Recordings from what machines and trackers write: `hilcal import` and `hilcal robot-from-geometry`, as pure code.

Holds the mapping file (``mapping``), CSV tables with line numbers (``table``), unit and orientation conversions
(``conversions``), the pose from raw target points by the CMM path's rigid registration (``targets``), clocks,
sessions and phases (``sessions``), the per-session summary (``summary``), the import itself (``assemble``), rows left
out on request (``incomplete``) and a robot file from documented geometry (``geometry``). Errors name the file, line
and column (``errors``). May import the calibration math at the top of ``hilcal`` and itself; never ``planning``,
``discovery`` or ``reports``.
"""

from hilcal.importing.assemble import ImportResult, import_recording
from hilcal.importing.errors import ImportFileError
from hilcal.importing.geometry import (
    GeometryCheck,
    GeometrySpec,
    check_geometry,
    geometry_robot_toml,
    load_geometry,
    robot_from_geometry,
)
from hilcal.importing.mapping import ImportMap, load_map, map_from_dict
from hilcal.importing.sessions import HoldOut, parse_hold_out
from hilcal.importing.summary import SessionSummary

__all__ = [
    "GeometryCheck",
    "GeometrySpec",
    "HoldOut",
    "ImportFileError",
    "ImportMap",
    "ImportResult",
    "SessionSummary",
    "check_geometry",
    "geometry_robot_toml",
    "import_recording",
    "load_geometry",
    "load_map",
    "map_from_dict",
    "parse_hold_out",
    "robot_from_geometry",
]
