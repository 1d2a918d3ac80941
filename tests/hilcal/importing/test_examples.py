"""The three worked examples of docs/import.md: imported as documented, they are the simulator's own recording, and
`diagnose` gives the same answer on both (same effects, every parameter within its standard error)."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.discovery.search import diagnose
from hilcal.importing import import_recording, load_map, parse_hold_out
from hilcal.recording import read_recording
from hilcal.robot import default_robot, load_robot
from tests.hilcal.importing.support import CASES, EXAMPLES, assert_same_recording


@pytest.fixture(scope="module", params=list(CASES))
def example(request):
    name = request.param
    files, hold_out, robot_file = CASES[name]
    folder = EXAMPLES / name
    robot = default_robot() if robot_file is None else load_robot(folder / robot_file)
    result = import_recording([folder / f for f in files], load_map(folder / "map.toml"), robot=robot,
                              hold_out=None if hold_out is None else parse_hold_out(hold_out))
    direct = read_recording(folder / "simulated.csv", robot)
    return name, robot, result, direct


def test_the_import_is_the_simulators_recording(example):
    _, _, result, direct = example
    assert_same_recording(result.recording, direct, 1e-3, 1e-6)


@pytest.mark.slow
def test_diagnose_gives_the_same_answer(example):
    name, robot, result, direct = example
    imported, reference = diagnose(result.recording, robot), diagnose(direct, robot)
    assert imported.effects == reference.effects, name
    assert set(imported.parameters) == set(reference.parameters)
    for key, value in reference.parameters.items():
        assert abs(imported.parameters[key] - value) <= reference.std_errors[key], key
    same_shift = (imported.session_shift is None) == (reference.session_shift is None)
    assert same_shift and (reference.session_shift is None
                           or imported.session_shift.legs == reference.session_shift.legs)
    assert imported.noise.chosen is not None and reference.noise.chosen is not None
    assert imported.noise.chosen.source == reference.noise.chosen.source
    assert np.isclose(imported.noise.chosen.position_mm, reference.noise.chosen.position_mm, rtol=0.05)
