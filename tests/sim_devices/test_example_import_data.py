"""The worked examples of examples/import: regenerated from their seeded generator, they are the committed files.

The generator (examples/import/make_examples.py) simulates each run on the rig; the committed files must be what it
writes now, so docs/import.md describes the committed data. Also checks the logger example's robot.toml is what
`hilcal robot-from-geometry` makes of its geometry.toml.
"""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.importing import import_recording, load_map
from hilcal.recording import read_recording
from tests.hilcal.importing.support import CASES, EXAMPLES, assert_same_recording, load_example_module


@pytest.fixture(scope="module")
def regenerated(tmp_path_factory):
    make = load_example_module("make_examples")
    out = tmp_path_factory.mktemp("examples")
    return out, {name: make.make(name, out / name) for name in CASES}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_committed_files_are_what_the_generator_writes(regenerated, name):
    out, examples = regenerated
    files, _, robot_file = CASES[name]
    robot = examples[name].robot
    if robot_file is not None:
        assert (out / name / robot_file).read_text() == (EXAMPLES / name / robot_file).read_text()
    committed = read_recording(EXAMPLES / name / "simulated.csv", robot)
    again = read_recording(out / name / "simulated.csv", robot)
    for field in ("time_s", "legs_mm", "meas"):
        np.testing.assert_allclose(getattr(committed, field), getattr(again, field), rtol=0, atol=1e-9, err_msg=field)
    mapping = load_map(EXAMPLES / name / "map.toml")
    header = mapping.csv.header_line
    for f in files:
        fresh, kept = (out / name / f).read_text().splitlines(), (EXAMPLES / name / f).read_text().splitlines()
        assert fresh[:header] == kept[:header] and len(fresh) == len(kept), f
    imported = [import_recording([folder / name / f for f in files], mapping).recording for folder in (EXAMPLES, out)]
    assert_same_recording(imported[0], imported[1], 1e-6, 1e-7)
