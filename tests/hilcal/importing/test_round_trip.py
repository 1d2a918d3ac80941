"""Round trips: a simulator recording -> a machine's format (examples/import/exporters.py) -> import -> the same.

The sources are the examples' simulated.csv files, which the simulator wrote directly. Exact exports must come
back to rounding error; exports with the digits a logger writes must come back within 1 µm and 1e-6 deg.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hilcal.importing import import_recording, load_map, map_from_dict, parse_hold_out
from hilcal.recording import read_recording
from hilcal.robot import default_robot, load_robot
from tests.hilcal.importing.support import CASES, EXAMPLES, assert_same_recording, load_example_module

AS_WRITTEN = {"legs": 7, "position": 6, "orientation": 10, "targets": 5, "time": 3, "temperature": 4, "fit_rms": 7}
"""Digits after the point as a logger writes them; the coarsest, positions in m to 1 µm, is within the criterion."""
TRACKER_FRAME = np.array([-3100.0, 2400.0, 650.0, 0.8, -1.1, 217.0])


def _source(name: str):
    robot_file = CASES[name][2]
    robot = default_robot() if robot_file is None else load_robot(EXAMPLES / name / robot_file)
    return robot, read_recording(EXAMPLES / name / "simulated.csv", robot)


@pytest.mark.parametrize("digits", ["exact", "as_written"])
@pytest.mark.parametrize("name", list(CASES))
def test_each_example_format_round_trips(name, digits, tmp_path):
    exporters = load_example_module("exporters")
    robot, source = _source(name)
    files, hold_out, _ = CASES[name]
    mapping = load_map(EXAMPLES / name / "map.toml")
    options = exporters.ExportOptions(decimals={} if digits == "exact" else AS_WRITTEN, instrument_pose=TRACKER_FRAME,
                                      preamble=["exported for a round trip;;", ";;", ";;"] if name == "tracker" else ())
    paths = exporters.export_recording(source, mapping, tmp_path, list(files), options)
    got = import_recording(paths, mapping, robot=robot, hold_out=None if hold_out is None else parse_hold_out(hold_out))
    tol = (1e-8, 1e-9) if digits == "exact" else (1e-3, 1e-6)
    assert_same_recording(got.recording, source, *tol)


def _paper_map() -> dict:
    return tomllib.loads((EXAMPLES / "paper" / "map.toml").read_text())


def _variant(update: dict) -> dict:
    data = {**_paper_map(), **update}
    return {k: v for k, v in data.items() if v is not None}


LEG_COLUMNS = _paper_map()["legs"]["columns"]
ORIENTATION = ["o1", "o2", "o3", "o4"]
VARIANTS = {
    "legs in encoder counts": {"legs": {"columns": LEG_COLUMNS, "unit": "count", "mm_per_unit": 0.000244140625,
                                        "zero_mm": [3800.0, 3801.5, 3799.25, 3800.0, 3802.0, 3798.5]}},
    "legs in revolutions, reversed": {"legs": {"columns": LEG_COLUMNS, "unit": "rev", "mm_per_unit": -10.0,
                                               "zero_mm": 4800.0}},
    "legs in m": {"legs": {"columns": LEG_COLUMNS, "unit": "m"}},
    "quaternion wxyz": {"orientation": {"columns": ORIENTATION, "kind": "quaternion_wxyz"}},
    "quaternion xyzw": {"orientation": {"columns": ORIENTATION, "kind": "quaternion_xyzw"}},
    "rotation matrix": {"orientation": {"columns": [f"r{k}" for k in range(9)], "kind": "matrix"},
                        "command": {"position": {"columns": ["cx", "cy", "cz"], "unit": "mm"},
                                    "orientation": {"columns": ["c1", "c2", "c3"], "kind": "rpy_deg"}}},
    "time in s since the epoch": {"time": {"column": "t", "unit": "s", "clock": "shared"}},
    "time in ms since the logger started": {"time": {"column": "t", "unit": "ms"}},
    "kelvin, semicolons and decimal commas": {"temperature": {"column": "T", "unit": "K"},
                                              "csv": {"delimiter": ";", "decimal": ","}},
    "inches and fahrenheit": {"legs": {"columns": LEG_COLUMNS, "unit": "in"},
                              "position": {"columns": ["px", "py", "pz"], "unit": "in"},
                              "temperature": {"column": "T", "unit": "F"}},
    "platform targets only": {"position": None, "orientation": None, "fit_rms": None, "targets": {
        "unit": "m", "platform": [{"name": f"T{k}", "columns": [f"T{k}x", f"T{k}y", f"T{k}z"], "position_mm": p}
                                  for k, p in enumerate([[1000.0, 0.0, 100.0], [-500.0, 866.03, 100.0],
                                                         [-500.0, -866.03, 100.0], [0.0, 0.0, 400.0]])]}},
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_every_unit_kind_and_clock_round_trips(variant, tmp_path):
    exporters = load_example_module("exporters")
    robot, source = _source("paper")
    mapping = map_from_dict(_variant(VARIANTS[variant]))
    paths = exporters.export_recording(source, mapping, tmp_path, ["log.csv"], exporters.ExportOptions())
    got = import_recording(paths, mapping, robot=robot).recording
    assert_same_recording(got, source, 1e-8, 1e-9)
