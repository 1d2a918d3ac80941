"""No NaN, no infinity and no empty range anywhere in what `hilcal diagnose` says: every string and number of its JSON,
its report files (diagnosis.json, compensation.json, twin.json, the CSV tables, the page) on real-shaped recordings
(benchmarks/studies/diagnosis_real_shaped.py: two sessions, a re-homing shift, generic terms with a base-joint-angle
shape, near-aliases, an outlier) and on the examples."""

from __future__ import annotations

import html
import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hilcal.discovery.search import diagnose
from hilcal.recording import read_recording
from hilcal.reports.diagnosis import write_report
from hilcal.robot import load_robot
from procedures.cli.twin import compare, write_twin

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks" / "studies"))
from diagnosis_real_shaped import ROBOT_FILE, real_shaped  # noqa: E402

NOT_A_NUMBER = re.compile(r"\b(nan|inf|infinity)\b", re.IGNORECASE)
NUMBER = r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?"
RANGE = re.compile(rf"(?<![\w.])({NUMBER})(?:-|–|\s+to\s+)({NUMBER})(?![\w.])")


def _strings_and_numbers(value: Any, where: str = "") -> list[tuple[str, Any]]:
    if isinstance(value, dict):
        return [item for k, v in value.items() for item in _strings_and_numbers(v, f"{where}/{k}")]
    if isinstance(value, list | tuple):
        return [item for i, v in enumerate(value) for item in _strings_and_numbers(v, f"{where}[{i}]")]
    return [(where, value)]


def _bad_text(text: str) -> list[str]:
    """NaN or infinity words, and ranges whose two ends are the same number (an empty range)."""
    bad = [m.group(0) for m in NOT_A_NUMBER.finditer(text)]
    bad += [m.group(0) for m in RANGE.finditer(text) if float(m.group(1)) == float(m.group(2))]
    return bad


def _check_json(data: Any, source: str) -> None:
    for where, value in _strings_and_numbers(data):
        if isinstance(value, str):
            assert not _bad_text(value), f"{source}{where}: {_bad_text(value)} in {value!r}"
        elif isinstance(value, float):
            assert np.isfinite(value), f"{source}{where}: {value}"


def _refuse_constants(name: str) -> None:
    raise AssertionError(f"JSON holds {name}")


def _check_report(folder: Path) -> None:
    for path in folder.glob("*.json"):
        _check_json(json.loads(path.read_text(), parse_constant=_refuse_constants), path.name)
    for path in folder.glob("*.csv"):
        assert not NOT_A_NUMBER.search(path.read_text()), path.name
    page = html.unescape(re.sub(r"<[^>]+>", " ", re.sub(r'src="data:[^"]*"', "", (folder / "index.html").read_text())))
    assert not _bad_text(page), _bad_text(page)


def _check(rec, robot, robot_path, tmp_path: Path) -> None:
    diag = diagnose(rec, robot)
    _check_json(diag.to_json(), "--json")
    assert not _bad_text(diag.explanation) and not any(_bad_text(s) for s in diag.summary)
    twin = write_twin(diag, rec, robot, robot_path, tmp_path)
    write_report(diag, tmp_path, compare(twin, diag, rec, robot), twin.notes)
    _check_report(tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_a_real_shaped_recording_is_said_without_nan_or_empty_ranges(seed, tmp_path):
    made = real_shaped(seed)
    _check(made.recording, made.robot, ROBOT_FILE, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("example", ["electric_hexapod", "small_hexapod"])
def test_the_examples_are_said_without_nan_or_empty_ranges(example, tmp_path):
    robot_path = ROOT / "examples" / example / "robot.toml"
    robot = load_robot(robot_path)
    _check(read_recording(ROOT / "examples" / example / "recording.csv", robot), robot, robot_path, tmp_path)


def test_the_checks_catch_what_they_look_for():
    assert _bad_text("leg 2 ±nan µm over the recorded 0-0 base_joint_angle") == ["nan", "0-0"]
    assert _bad_text("Legs 1-6 sag; over the recorded 0.1241-49.12 stroke_mm; 1.5e-3 to 2e-3") == []
    with pytest.raises(AssertionError):
        _check_json({"a": [float("nan")]}, "x")
