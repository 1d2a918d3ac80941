"""Machine time in the run report: estimated parts against actual seconds, per phase, in JSON and HTML."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hilcal.planning.machine_time import PhaseTime, TimeEstimate
from hilcal.reports.run import report_json, write_run_report
from hilcal.reports.timing import time_html, time_section
from tests.hilcal.reports.test_run_report import make_report

ESTIMATE = TimeEstimate((
    PhaseTime("measure", 35, 300, 12_600.0, 700.0, 70.0, 1575.0),
    PhaseTime("verify", 24, 200, 7_100.0, 400.0, 48.0, 1080.0),
    PhaseTime("verify_after", 24, 200, 7_200.0, 410.0, 48.0, 1080.0),
    PhaseTime("return_home", 0, 5, 330.0, 18.0, 0.0, 0.0),
))
TIMING = {"leg_speed_mm_s": 50.0, "leg_accel_mm_s2": 100.0, "settle_s": 2.0, "cmm_s_per_pose": 45.0}


def test_section_per_phase_and_totals():
    actual = {"measure": 2345.0 + 0.0, "verify": 1500.0, "verify_after": None}
    out = time_section(ESTIMATE, actual, TIMING)
    m = out["phases"]["measure"]
    assert m["estimated_s"] == pytest.approx(700.0 + 70.0 + 1575.0)
    assert m["actual_s"] == 2345.0 and m["actual_over_estimated"] == pytest.approx(1.0)
    assert out["phases"]["verify_after"]["actual_s"] is None
    assert out["phases"]["verify_after"]["actual_over_estimated"] is None
    assert out["estimated_s"] == pytest.approx(700 + 70 + 1575 + 400 + 48 + 1080 + 410 + 48 + 1080 + 18)
    assert out["estimated_motion_s"] == pytest.approx(700 + 400 + 410 + 18)
    assert out["actual_s"] == pytest.approx(2345.0 + 1500.0) and out["actual_phases"] == ["measure", "verify"]
    assert out["timing"] == TIMING and out["interrupted"] is False


def test_report_json_and_page_show_estimated_against_actual(tmp_path: Path):
    section = time_section(ESTIMATE, {"measure": 2400.0, "verify": 1600.0, "verify_after": 1550.0,
                                      "return_home": 20.0}, TIMING, interrupted=True)
    report = make_report({}, machine_time=section)
    assert report_json(report)["machine_time"]["phases"]["verify"]["actual_s"] == 1600.0
    json_path, html_path = write_run_report(tmp_path, report)
    assert json.loads(json_path.read_text())["machine_time"]["estimated_settle_s"] == pytest.approx(70.0 + 48.0 + 48.0)
    page = html_path.read_text()
    assert "Machine time: estimated against actual" in page
    assert "verify poses (after)" in page and "1550.0 s" in page and "interrupted or paused" in page
    assert report_json(make_report({}))["machine_time"] is None
    assert "no machine-time estimate" in time_html(None)
