"""The mapping file: the issue's key names load as written, and every mistake names its key."""

from __future__ import annotations

import pytest

from hilcal.importing import ImportFileError, load_map, map_from_dict

ISSUE_MAP = '''
[legs]
columns = ["leg_length_1", "leg_length_2", "leg_length_3", "leg_length_4", "leg_length_5", "leg_length_6"]
unit = "rev"                 # "mm", "m", "count" or "rev"
mm_per_unit = [5.0, 5.0, 5.0, 5.0, 5.0, 5.0]         # per leg (here a 5 mm screw lead); not needed for "mm" and "m"
zero_mm = [812.0, 812.0, 812.0, 812.0, 812.0, 812.0] # leg length at reading 0, per leg
[position]
columns = ["position_x", "position_y", "position_z"]
unit = "mm"                  # or "m"
[orientation]
columns = ["orientation_x", "orientation_y", "orientation_z", "orientation_w"]
kind = "quaternion_xyzw"
[time]                       # optional
column = "stamp"
unit = "s"                   # or "ms", "iso"
[phase]                      # optional
column = "kind"
measure = "cal"
verify = "check"
'''

LEGS = {"columns": [f"l{k}" for k in range(1, 7)], "unit": "mm"}
POSE = {"position": {"columns": ["x", "y", "z"]}, "orientation": {"columns": ["r", "p", "w"], "kind": "rpy_deg"}}


def test_the_issue_example_loads_with_its_key_names(tmp_path):
    path = tmp_path / "map.toml"
    path.write_text(ISSUE_MAP)
    m = load_map(path)
    assert m.legs.unit == "rev" and list(m.legs.scale_mm()) == [5.0] * 6 and list(m.legs.zero()) == [812.0] * 6
    assert m.orientation is not None and m.orientation.kind == "quaternion_xyzw"
    assert m.time is not None and m.time.clock_mode == "per_file"
    assert m.phase is not None and m.phase.measure_values == ("cal",) and m.phase.verify_values == ("check",)
    assert m.columns()[:2] == ["leg_length_1", "leg_length_2"] and "stamp" in m.columns() and "kind" in m.columns()


def test_leg_scale_is_fixed_for_mm_and_m_and_zero_defaults_to_0():
    m = map_from_dict({"legs": {**LEGS, "unit": "m"}, **POSE})
    assert list(m.legs.scale_mm()) == [1000.0] * 6 and list(m.legs.zero()) == [0.0] * 6
    m = map_from_dict({"legs": {**LEGS, "zero_mm": 3800.0}, **POSE})
    assert list(m.legs.zero()) == [3800.0] * 6


@pytest.mark.parametrize(("change", "key", "words"), [
    ({"legs": {**LEGS, "unit": "rev"}}, "legs", "needs mm_per_unit and zero_mm"),
    ({"legs": {**LEGS, "unit": "mm", "mm_per_unit": 2.0}}, "legs", "fixed for unit"),
    ({"legs": {**LEGS, "unit": "inch"}}, "legs.unit", "'mm', 'm', 'in', 'count' or 'rev'"),
    ({"legs": {**LEGS, "columns": ["a"] * 6}}, "legs.columns", "listed twice"),
    ({"orientation": {"columns": ["a", "b", "c"], "kind": "quaternion_wxyz"}}, "orientation", "needs 4 columns"),
    ({"position": None}, "(top level)", "go together"),
    ({"targets": {"platform": [{"name": "a", "columns": ["1", "2", "3"], "position_mm": [0, 0, 0]}] * 3}},
     "targets", "collinear"),
    ({"targets": {"platform": [{"name": f"t{k}", "columns": [f"{k}x", f"{k}y", f"{k}z"], "position_mm": p}
                               for k, p in enumerate([[0, 0, 0], [90, 0, 0], [0, 90, 0]])]}},
     "(top level)", "either as"),
    ({"tme": {"column": "t"}}, "tme", "Extra inputs are not permitted"),
    ({"phase": {"column": "k", "measure": "x", "verify": "x"}}, "phase", "both measure and verify"),
])
def test_every_mistake_names_its_key(change, key, words):
    data = {"legs": LEGS, **POSE, **change}
    data = {k: v for k, v in data.items() if v is not None}
    with pytest.raises(ImportFileError) as info:
        map_from_dict(data, "m.toml")
    assert info.value.column is not None and info.value.column.startswith(key)
    assert words in str(info.value) and str(info.value).startswith("m.toml, key ")


def test_targets_need_a_triangle_and_three_base_targets_or_none():
    targets = [{"name": f"t{k}", "columns": [f"t{k}x", f"t{k}y", f"t{k}z"], "position_mm": p}
               for k, p in enumerate([[0, 0, 0], [100, 0, 0], [0, 100, 0]])]
    ok = map_from_dict({"legs": LEGS, "targets": {"platform": targets}})
    assert ok.targets is not None and ok.targets.layout("platform").shape == (3, 3)
    for bad in ({"platform": [*targets[:2], {**targets[2], "position_mm": [200, 0, 0]}]},
                {"platform": targets, "base": targets[:2]}):
        with pytest.raises(ImportFileError):
            map_from_dict({"legs": LEGS, "targets": bad})


def test_unreadable_and_invalid_toml_are_errors(tmp_path):
    with pytest.raises(ImportFileError, match="cannot read"):
        load_map(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[legs\n")
    with pytest.raises(ImportFileError, match="not valid TOML"):
        load_map(bad)
