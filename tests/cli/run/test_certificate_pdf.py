"""certificate.pdf from WeasyPrint (procedures/pdf.py), without a browser: a real PDF that pypdf opens, A4 with the
certificate's fonts embedded, its text extractable, the verdict and the run id on page 1; `hilcal certificate` with
no Chromium on the PATH; a print that fails or runs out of time leaves no PDF; the page never reaches the network.

The report is written here by hand (the keys of report.json's sign-off), so these tests need no simulated run.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from pypdf import PdfReader

from hilcal.reports.certificate import certificate_html
from procedures.pdf import PdfError, print_to_pdf
from tests.cli.run.certificate_support import pdf_text

RUN_ID = "20260102T030405Z-abc123"
A4_PT = (595.28, 841.89)
"""210 mm x 297 mm in PDF points (1/72 inch): the print CSS's @page size."""


def _figure(value: float, u: float, unit: str) -> dict:
    return {"value": value, "U": u, "k": 2.0, "unit": unit}


def _iso_pose(name: str, x_mm: float) -> dict:
    return {"pose": name, "commanded": [x_mm, 0.0, 3100.0, 0.0, 0.0, 0.0], "n_cycles": 3,
            "ap_p_mm": _figure(0.002, 0.003, "mm"), "l_mean_mm": 0.0015, "s_l_mm": 0.0004,
            "rp_l_mm": _figure(0.0028, 0.002, "mm"),
            **{f"ap_{a}_deg": _figure(0.00001, 0.0002, "deg") for a in "abc"},
            **{f"rp_{a}_deg": _figure(0.0001, 0.0001, "deg") for a in "abc"}}


def _report(verdict: str) -> dict:
    """A complete run's report.json as far as the certificate reads it: 4 limits, the ISO 9283 table, an upload."""
    limit = {"key": "max_position_mm", "label": "largest position error at the verification poses after calibration",
             "where": "verification poses after calibration", "value": 0.0048, "U": 0.0029, "unit": "mm",
             "limit": 0.05, "decision": verdict}
    figures = {"max_position_mm": _figure(0.0048, 0.0029, "mm"), "rms_position_mm": _figure(0.0028, 0.0009, "mm"),
               "max_orientation_deg": _figure(0.00017, 0.00011, "deg"),
               "rms_orientation_deg": _figure(0.0001, 0.00003, "deg")}
    return {
        "run_id": RUN_ID, "operator": "A. Tester",
        "times": {"started_at": "2026-01-02T03:04:05+00:00", "finished_at": "2026-01-02T03:05:00+00:00"},
        "station": {"name": "test bay", "file": None, "simulated": True},
        "machine": {"robot_name": "paper-table1", "robot_file": "robot.toml", "serial": "SIM-0001"},
        "software": {"name": "hilcal", "version": "0.1.0", "git_revision": "0" * 40, "git_modified": False},
        "instrument": {"kind": "cmm", "cmm": "simulated CMM", "url": "/dev/pts/9", "stated_uncertainty_mm": 0.004,
                       "uncertainty_source": "station file", "calibration_due": "2027-01-31", "overdue": False},
        "environment": {"temperature_c": {"mean": 20.9, "min": 20.8, "max": 21.1, "n": 98}, "note": ""},
        "method": {"model": 42, "estimator": "ls", "effects": [], "plan_sha256": "a" * 64, "n_measure_rows": 35,
                   "n_verify_poses": 24, "plan": "fixed"},
        "uncertainty": {"before": {k: _figure(v["value"] * 300, v["U"], v["unit"]) for k, v in figures.items()},
                        "after": figures},
        "iso9283": {"standard": "ISO 9283:1998", "cycles": 3, "order": ["P1", "P5", "P4", "P3", "P2"],
                    "cube": {"centre_mm": [0.0, 0.0, 3100.0], "side_mm": 500.0, "orientation_deg": [0.0, 0.0, 0.0]},
                    "poses": [_iso_pose(f"P{i}", 100.0 * i) for i in range(1, 6)], "notes": []},
        "certificate": {"number": f"HILCAL-{RUN_ID}", "issued_at": "2026-01-02T03:05:00+00:00", "verdict": verdict,
                        "limits": [limit, {**limit, "key": "rms_position_mm", "label": "RMS position error"}],
                        "decision_rule": {"key": "iso14253-1", "text": "ISO 14253-1"}, "warnings": []},
        "upload": {"outcome": "saved", "record": {"params_sha256": "b" * 64, "live_after_sha256": "b" * 64,
                                                  "live_readback_match": True, "staging_readback_match": True,
                                                  "saved": True, "saved_readback_match": True,
                                                  "endpoint": "tcp://127.0.0.1:5020",
                                                  "finished_at": "2026-01-02T03:04:50+00:00"}},
    }


def _words(text: str) -> str:
    """pypdf's text with its lines joined by a space."""
    return " ".join(text.split())


@pytest.fixture(scope="module")
def printed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("pdf")
    (tmp / "certificate.html").write_text(certificate_html(_report("fail")), encoding="utf-8")
    return print_to_pdf(tmp / "certificate.html", tmp / "certificate.pdf")


def test_the_pdf_is_a4_with_the_verdict_and_the_run_on_page_1(printed: Path) -> None:
    reader = PdfReader(printed)
    assert 1 <= len(reader.pages) <= 2
    for page in reader.pages:
        assert (float(page.mediabox.width), float(page.mediabox.height)) == pytest.approx(A4_PT, abs=0.5)
    first = _words(reader.pages[0].extract_text())
    assert "Calibration certificate" in first and "Verdict: fail" in first and RUN_ID in first
    assert f"HILCAL-{RUN_ID}" in first and "A. Tester" in first
    text = pdf_text(printed)
    assert "ISO 9283" in text and "P5" in text and "RPl" in text and "Approved by" in text
    fonts = {str(f.get_object()["/BaseFont"]).split("+")[-1] for page in reader.pages
             for f in page["/Resources"]["/Font"].values()}
    assert fonts == {"DejaVu-Sans", "DejaVu-Sans-Bold", "DejaVu-Sans-Mono"}  # the CSS's, embedded
    assert not printed.with_name("certificate.pdf.partial").exists()


def test_hilcal_certificate_writes_the_pdf_without_chromium(tmp_path: Path) -> None:
    """PATH holds only the interpreter's folder (no chromium, no chromedriver) and HILCAL_CHROMIUM is unset."""
    (tmp_path / "report.json").write_text(json.dumps(_report("pass")))
    env = {k: v for k, v in os.environ.items() if k != "HILCAL_CHROMIUM"}
    env["PATH"] = str(Path(sys.executable).parent)
    done = subprocess.run([sys.executable, "-m", "procedures.cli", "certificate", str(tmp_path)], env=env,
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "warning" not in done.stderr and f"and {tmp_path / 'certificate.pdf'}" in done.stdout
    assert "Verdict: pass" in PdfReader(tmp_path / "certificate.pdf").pages[0].extract_text()


def test_a_print_out_of_time_or_of_a_missing_page_leaves_no_pdf(tmp_path: Path) -> None:
    (tmp_path / "page.html").write_text(certificate_html(_report("pass")), encoding="utf-8")
    pdf = tmp_path / "page.pdf"
    with pytest.raises(PdfError, match=r"within 0\.05 s"):
        print_to_pdf(tmp_path / "page.html", pdf, timeout_s=0.05)
    with pytest.raises(PdfError, match="does not exist"):
        print_to_pdf(tmp_path / "nothing.html", pdf)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["page.html"]


def test_the_page_cannot_reach_the_network(tmp_path: Path) -> None:
    """An image on a listening 127.0.0.1 port is not fetched (no connection arrives); the PDF is still written."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        (tmp_path / "page.html").write_text(f"<!doctype html><p>before</p><img src='http://127.0.0.1:{port}/x.png'>"
                                            "<p>after</p>", encoding="utf-8")
        print_to_pdf(tmp_path / "page.html", tmp_path / "page.pdf", timeout_s=60)
        server.setblocking(False)
        with pytest.raises(BlockingIOError):
            server.accept()
    assert "after" in pdf_text(tmp_path / "page.pdf")
