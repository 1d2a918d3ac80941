"""The end-of-run summary read from report.json: figures as the report has them, what was uploaded (the compensation
mode and, when the report has one, the physics it corrected), the verdict, and keys a run did not reach said as
such. Reports are written here by hand; the whole run's summary is checked in tests/cli/run/test_certificate.py."""

from __future__ import annotations

import io
from pathlib import Path

from rich.console import Console

from procedures.cli.run_summary import run_summary

BEFORE = {"max_position_mm": 1.5, "rms_position_mm": 1.25, "max_orientation_deg": 0.05, "rms_orientation_deg": 0.04}
AFTER = {"max_position_mm": 0.0125, "rms_position_mm": 0.0075, "max_orientation_deg": 0.0003,
         "rms_orientation_deg": 0.0002}


def _text(report: dict, certificate: Path | None = None) -> list[str]:
    console = Console(width=200, record=True, file=io.StringIO())
    console.print(run_summary(report, Path("/runs/[bay 2]/report.json"), certificate))
    return [" ".join(line.split()) for line in console.export_text().splitlines() if line.strip()]


def _report(**changes: object) -> dict:
    report = {"run_id": "R1", "status": "complete", "uploaded": True, "method": {"n_verify_poses": 24},
              "verification": {"before": BEFORE, "after": AFTER},
              "uncertainty": {"before": {"max_position_mm": {"value": 1.5, "U": 0.004}},
                              "after": {"max_position_mm": {"value": 0.0125, "U": 0.0025}}},
              "compensation": {"mode": "offsets_only"},
              "upload": {"outcome": "committed", "record": {"params_sha256": "abcdef0123456789",
                                                            "live_readback_match": True}},
              "certificate": {"verdict": "not proven", "decision_rule": {"key": "simple"}, "limits": [
                  {"key": "max_position_mm", "label": "largest position error after calibration",
                   "decision": "not proven", "value": 0.0125, "U": 0.0025, "unit": "mm",
                   "limit": 0.013},
                  {"key": "rms_position_mm", "decision": "pass", "value": 0.0075, "U": 0.001, "unit": "mm",
                   "limit": 0.02}]}}
    return report | changes


def test_summary_of_a_complete_run() -> None:
    lines = _text(_report(), Path("/runs/[bay 2]/certificate.pdf"))
    assert "run R1: complete" in lines[0]
    assert lines[1:6] == ["24 verification poses before after",
                          "max position (mm) 1.5000 ± 0.0040 0.0125 ± 0.0025",
                          "RMS position (mm) 1.2500 0.0075",  # no U in the report for it: none is printed
                          "max orientation (deg) 0.05000 0.00030",
                          "RMS orientation (deg) 0.04000 0.00020"]
    assert lines[7:] == ["uploaded leg offsets l0 only",
                         "committed (not saved); read back: matches (sha256 abcdef012345)",
                         "verdict not proven (2 limits, simple decision rule); largest position error after "
                         "calibration not proven: 0.0125 ± 0.0025 mm against 0.013",
                         "report /runs/[bay 2]/report.html (and report.json)",
                         "certificate /runs/[bay 2]/certificate.pdf"]


def test_the_physics_corrected_are_listed_under_uploaded() -> None:
    lines = _text(_report(compensation={"mode": "physics"}, physics={"corrected": ["leg compliance", "backlash"]}))
    at = lines.index("uploaded compensation mode physics")
    assert lines[at + 2] == "corrected: leg compliance, backlash"
    assert all("corrected" not in line for line in _text(_report(physics={"found": ["backlash"]})))


def test_a_run_that_uploaded_nothing_says_so() -> None:
    lines = _text({"status": "refused", "uploaded": False, "verification": {"before": BEFORE, "after": None}})
    assert "run report: refused" not in lines[0] and "run [bay 2]: refused" in lines[0]  # no run id: the folder
    assert lines[1] == "verification poses before after"
    assert lines[2] == "max position (mm) 1.5000 not measured"
    assert lines[6:] == ["uploaded nothing uploaded (run refused)", "verdict no sign-off in this report",
                         "report /runs/[bay 2]/report.html (and report.json)"]
