"""The sign-off of `hilcal run --sim --acceptance iso9283`: the certificate (HTML and PDF), report.json's sign-off
keys, the verdict with its exit code, the records and history, `hilcal certificate`, the simulated repeatability
measured back, and the certificate page in headless Chromium (the PDF, from WeasyPrint without a browser:
test_certificate_pdf.py).

Two simulated runs on a small plan (12 measure and 6 verify poses) keep this fast: one as the brief's command
(no station file: the simulated station's example limits and its CMM's stated uncertainty, 3 cycles) and one with a
limit the demo machine cannot meet. The run with limits the machine cannot meet is in test_certificate_failed.py.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
from pathlib import Path

import pytest
from pypdf import PdfReader
from typer.testing import CliRunner

from procedures.cli.app import app
from tests.cli.browser_support import chromium, require_chromium, text
from tests.cli.run.certificate_support import OPERATOR, hilcal, pdf_text
from tests.cli.sim_speed import INSTANT_SIM, instant_timing

pytestmark = pytest.mark.timeout(420)
NOISE_MM = 0.002
"""The simulated CMM's touch-point noise in the brief's run; the CMM states U = 2 x NOISE_MM per sphere coordinate."""
EXAMPLE_LIMITS = {"max_position_mm", "rms_position_mm", "max_orientation_deg", "rms_orientation_deg"}
@pytest.fixture(scope="module")
def accepted(tmp_path_factory: pytest.TempPathFactory, small_plan: Path) -> tuple[Path, subprocess.CompletedProcess]:
    """The brief's command (with 3 cycles and the small plan): no station file, so the simulated station's."""
    tmp = tmp_path_factory.mktemp("accepted")
    (tmp / "sim.toml").write_text(INSTANT_SIM.replace("[cmm]\n", f"[cmm]\nnoise_sigma_mm = {NOISE_MM}\n"))
    done = hilcal("run", "--sim", "--yes", "--operator", OPERATOR, "--acceptance", "iso9283", "--cycles", "3",
                   "--plan", str(small_plan), "--sim-config", str(tmp / "sim.toml"), "--out", str(tmp / "run"),
                   records=tmp / "records.sqlite")
    return tmp, done


@pytest.fixture(scope="module")
def strict(tmp_path_factory: pytest.TempPathFactory, small_plan: Path) -> tuple[Path, subprocess.CompletedProcess]:
    """The demo machine against a station file with a limit it cannot meet and no [cmm]: the simulator states U."""
    tmp = tmp_path_factory.mktemp("strict")
    (tmp / "station.toml").write_text(f"[acceptance]\nmax_position_mm = 0.0005\n{instant_timing()}")
    (tmp / "sim.toml").write_text(INSTANT_SIM)
    done = hilcal("run", "--sim", "--yes", "--operator", OPERATOR, "--station", str(tmp / "station.toml"),
                   "--station-timing", "--sim-config", str(tmp / "sim.toml"), "--plan", str(small_plan), "--out",
                   str(tmp / "run"), records=tmp / "records.sqlite")
    return tmp, done


@pytest.mark.slow
def test_accepted_run_writes_the_certificate_and_its_pdf(accepted: tuple[Path, subprocess.CompletedProcess]) -> None:
    tmp, done = accepted
    assert done.returncode == 0, done.stdout + done.stderr
    run = tmp / "run"
    report = json.loads((run / "report.json").read_text())
    assert report["operator"] == OPERATOR
    assert report["machine"]["robot_name"] == "paper-table1" and report["station"]["simulated"] is True
    assert report["software"]["name"] == "hilcal" and report["software"]["version"]
    cert = report["certificate"]
    assert cert["number"] == f"HILCAL-{report['run_id']}"
    assert cert["verdict"] == "pass" and {c["key"] for c in cert["limits"]} == EXAMPLE_LIMITS
    assert cert["decision_rule"]["key"] == "iso14253-1"
    iso = report["iso9283"]
    assert [p["pose"] for p in iso["poses"]] == ["P1", "P2", "P3", "P4", "P5"]
    assert all(p["n_cycles"] == 3 for p in iso["poses"]) and iso["order"] == ["P1", "P5", "P4", "P3", "P2"]
    for p in iso["poses"]:
        assert p["ap_p_mm"]["unit"] == "mm" and p["ap_p_mm"]["U"] > 0 and p["rp_a_deg"]["unit"] == "deg"
    after = report["uncertainty"]["after"]["max_position_mm"]
    assert after["value"] == pytest.approx(report["verification"]["after"]["max_position_mm"]) and after["U"] > 0
    phases = report["machine_time"]["phases"]
    assert phases["acceptance"]["n_poses"] == 15 and phases["acceptance"]["actual_s"] > 0
    estimate = done.stdout.split("Estimated machine time")[1].split("return home")[0]  # printed before motion
    assert "acceptance" in estimate and done.stdout.index("Estimated machine time") < done.stdout.index("pose 1")
    assert "certificate HILCAL-" in done.stdout
    pdf = pdf_text(run / "certificate.pdf")
    for needle in (OPERATOR, cert["number"].split("-")[0], "Verdict: pass", "ISO 9283", "RPl", "APP",
                   "P1", "P5", "Calibration certificate"):
        assert needle in pdf, needle
    assert cert["number"].replace("-", "") in pdf.replace("-", "").replace("\n", "")
    assert len(PdfReader(run / "certificate.pdf").pages) <= 2


@pytest.mark.slow
def test_records_and_history_show_the_verdict(accepted: tuple[Path, subprocess.CompletedProcess]) -> None:
    tmp, _ = accepted
    report = json.loads((tmp / "run" / "report.json").read_text())
    db = sqlite3.connect(tmp / "records.sqlite")
    try:
        row = db.execute("SELECT operator, verdict, certificate_number, certificate_path FROM runs").fetchone()
    finally:
        db.close()
    assert row[:3] == (OPERATOR, "pass", report["certificate"]["number"])
    assert Path(row[3]) == (tmp / "run" / "certificate.pdf").resolve()
    history = hilcal("history", "--records", str(tmp / "records.sqlite"), records=tmp / "records.sqlite")
    assert history.returncode == 0, history.stderr
    assert "sign-off: pass" in history.stdout and report["certificate"]["number"] in history.stdout


@pytest.mark.slow
def test_the_simulated_station_states_its_cmm_and_example_limits(accepted: tuple[Path, subprocess.CompletedProcess]
                                                                 ) -> None:
    """Without a station file the certificate has a verdict with uncertainties: the simulator's CMM statement
    (2 x its touch noise) and the example limits, each passed with its U inside the limit (ISO 14253-1)."""
    tmp, done = accepted
    assert done.returncode == 0, done.stdout + done.stderr
    report = json.loads((tmp / "run" / "report.json").read_text())
    instrument = report["instrument"]
    assert instrument["stated_uncertainty_mm"] == pytest.approx(2 * NOISE_MM)
    assert "simulated CMM" in instrument["uncertainty_source"] and f"{NOISE_MM:g} mm" in instrument["cmm"]
    assert instrument["warning"] is None and report["uncertainty"]["cmm_pose_sd"] is not None
    after = report["uncertainty"]["after"]
    for check in report["certificate"]["limits"]:
        assert check["decision"] == "pass"
        assert check["value"] == after[check["key"]]["value"] and check["U"] == after[check["key"]]["U"] > 0
        assert check["value"] + check["U"] <= check["limit"]
    before = report["verification"]["before"]  # the limits mean something: the uncalibrated machine misses them
    assert all(before[check["key"]] > check["limit"] for check in report["certificate"]["limits"])


@pytest.mark.slow
def test_the_run_ends_with_its_summary(accepted: tuple[Path, subprocess.CompletedProcess]) -> None:
    """The last thing printed: the verification poses before and after (± U) as report.json has them, what was
    uploaded, what the physics step found, the verdict and where the report and certificate are."""
    tmp, done = accepted
    report = json.loads((tmp / "run" / "report.json").read_text())
    lines = done.stdout.rstrip().splitlines()
    start = next(i for i, line in enumerate(lines) if f"run {report['run_id']}: complete" in line)
    assert "holds/retries" in lines[start - 1]  # after the links' statistics, and nothing after it
    summary = [" ".join(line.split()) for line in lines[start:]]
    assert summary[1] == "6 verification poses before after"
    u = report["uncertainty"]
    for row, (key, label, decimals) in zip(summary[2:6], [("max_position_mm", "max position (mm)", 4),
                                                         ("rms_position_mm", "RMS position (mm)", 4),
                                                         ("max_orientation_deg", "max orientation (deg)", 5),
                                                         ("rms_orientation_deg", "RMS orientation (deg)", 5)],
                                      strict=True):
        before, after = u["before"][key], u["after"][key]
        assert row == (f"{label} {before['value']:.{decimals}f} ± {before['U']:.{decimals}f} "
                       f"{after['value']:.{decimals}f} ± {after['U']:.{decimals}f}")
    assert summary[7].startswith("uploaded joint positions a, b and leg offsets l0")
    assert report["upload"]["record"]["params_sha256"][:12] in summary[8]
    noise_um = report["physics"]["noise_mm"] * 1000  # the demo machine has no physics beyond the geometry
    assert summary[9] == f"physics: nothing beyond the geometry (noise yardstick {noise_um:.1f} µm)"
    assert summary[10] == "verdict pass (4 limits, ISO 14253-1 decision rule)"
    assert summary[11] == f"report {tmp / 'run' / 'report.html'} (and report.json)"
    assert summary[12].startswith(f"certificate {tmp / 'run' / 'certificate.'}") and len(summary) == 13



@pytest.mark.slow
def test_every_view_tells_the_same_upload_story(accepted: tuple[Path, subprocess.CompletedProcess]) -> None:
    """The run commits, then saves as a separate step, each with its own record: the commit's record says saved
    false, the save's says saved true. report.html, the certificate and the terminal say the same facts in words
    (a report once said "outcome saved" above "saved False")."""
    tmp, done = accepted
    run = tmp / "run"
    upload = json.loads((run / "report.json").read_text())["upload"]
    commit, save = upload["record"], upload["save_record"]
    assert commit["operation"] == "upload" and commit["outcome"] == "committed" and commit["saved"] is False
    assert commit["live_readback_match"] is True and commit["staging_readback_match"] is True
    assert save["operation"] == "save" and save["saved"] is True and save["saved_readback_match"] is True
    with sqlite3.connect(tmp / "records.sqlite") as db:
        rows = db.execute("SELECT record_json FROM uploads ORDER BY id").fetchall()
    operations = [json.loads(row[0])["operation"] for row in rows]
    assert operations == ["upload", "save"], "each step has its own record"
    for name in ("report.html", "certificate.html"):
        page = (run / name).read_text()
        assert "Committed to the controller&#x27;s live set" in page and "the live set read back matches" in page, name
        assert "Saved to non-volatile memory" in page and "the saved set read back matches" in page, name
        assert "Not saved" not in page and "saved False" not in page and "DIFFERS" not in page, name
    summary = [" ".join(line.split()) for line in done.stdout.splitlines()]
    assert any(line.startswith("committed and saved to non-volatile memory; read back: matches (sha256 ")
               for line in summary), "the terminal's summary"

@pytest.mark.slow
def test_a_limit_the_demo_machine_cannot_meet_fails(strict: tuple[Path, subprocess.CompletedProcess]) -> None:
    tmp, done = strict
    assert done.returncode == 4, done.stdout + done.stderr
    report = json.loads((tmp / "run" / "report.json").read_text())
    cert = report["certificate"]
    assert cert["verdict"] == "fail" and [c["key"] for c in cert["limits"]] == ["max_position_mm"]
    check = cert["limits"][0]
    assert check["decision"] == "fail" and check["value"] - check["U"] > check["limit"] == 0.0005
    assert report["instrument"]["stated_uncertainty_mm"] == pytest.approx(0.004)  # the simulator's default 2 x 0.002
    assert "simulated CMM" in report["instrument"]["uncertainty_source"]
    summary = " ".join(done.stdout[done.stdout.index(f"run {report['run_id']}: complete"):].split())
    assert ("verdict fail (1 limit, ISO 14253-1 decision rule); largest position error at the verification poses "
            "after calibration fail") in summary


@pytest.mark.slow
def test_certificate_command_regenerates_both_files(accepted: tuple[Path, subprocess.CompletedProcess],
                                                    tmp_path: Path) -> None:
    run = accepted[0] / "run"
    number = json.loads((run / "report.json").read_text())["certificate"]["number"]
    (run / "certificate.pdf").unlink()
    (run / "certificate.html").unlink()
    result = CliRunner().invoke(app, ["certificate", str(run)])
    assert result.exit_code == 0, result.output
    assert (run / "certificate.pdf").is_file() and number in (run / "certificate.html").read_text()
    assert OPERATOR in pdf_text(run / "certificate.pdf")
    missing = CliRunner().invoke(app, ["certificate", str(tmp_path)])
    assert missing.exit_code == 2 and "report.json" in missing.output


@pytest.mark.slow
def test_the_certificate_opens_in_headless_chromium(accepted: tuple[Path, subprocess.CompletedProcess]) -> None:
    require_chromium()
    run = accepted[0] / "run"
    report = json.loads((run / "report.json").read_text())
    with chromium() as browser:
        browser.get((run / "certificate.html").resolve().as_uri())
        assert text(browser, "certificate-number") == report["certificate"]["number"]
        assert text(browser, "operator") == OPERATOR
        assert "pass" in text(browser, "verdict")
        rows = browser.find_elements("css selector", "#iso-repeatability tr")
        assert len(rows) == 6 and rows[1].text.startswith("P1")
        assert browser.execute_script("return document.documentElement.scrollWidth <= window.innerWidth")
        browser.get((run / "report.html").resolve().as_uri())
        links = [a.get_attribute("href") for a in browser.find_elements("css selector", "a")]
        assert any(h.endswith("certificate.pdf") for h in links) and any(h.endswith("certificate.html") for h in links)


@pytest.mark.slow
def test_design_prints_the_iso_poses_and_the_test_time(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["design", "--acceptance", "iso9283", "--cycles", "4"])
    assert result.exit_code == 0, result.output
    rows = {line.split("│")[1].strip(): line for line in result.output.splitlines() if line.startswith("│ P")}
    assert sorted(rows) == ["P1", "P2", "P3", "P4", "P5"]
    assert "3100.000" in rows["P1"] and "-200.000" in rows["P2"] and "2900.000" in rows["P2"]
    assert "20 measurements" in result.output and "P1, P5, P4, P3, P2" in result.output


@pytest.mark.slow
def test_the_cmm_conversation_is_kept_and_speaks_the_standard(accepted: tuple[Path, subprocess.CompletedProcess]
                                                              ) -> None:
    """instrument_transcript.txt holds every line sent and received, `<ISO time> > line` / `<ISO time> < line`; every
    command passes NIST's command checks and every response NIST's response checks (tests/conformance/nist_grammar.py;
    the 1.4.3 forms NIST's 1.40-era parsers predate are noted, not refused), and every transaction is `&` first and
    `%` last, also after `!` (6.2.3)."""
    from datetime import datetime

    from tests.conformance.nist_grammar import check_command_line, check_response_line, version_notes

    tmp, _ = accepted
    lines = (tmp / "run" / "instrument_transcript.txt").read_text().splitlines()
    assert len(lines) > 1000
    problems, notes, open_tags, closed = [], set(), {}, 0
    for number, line in enumerate(lines, 1):
        stamp, direction, body = line.split(" ", 2)
        assert datetime.fromisoformat(stamp).tzinfo is not None and direction in "<>", line
        found = check_command_line(body) if direction == ">" else check_response_line(body)
        problems += [f"line {number}: {body}: {p}" for p in found]
        notes |= set(version_notes(body))
        tag, marker = body[:5], body[6:7]
        if direction == ">":
            open_tags[tag] = []
        elif tag != "E0000":
            seen = open_tags[tag]
            assert (marker == "&") == (not seen), f"line {number}: {body}: '&' must come first, and once"
            seen.append(marker)
            if marker == "%":
                del open_tags[tag]
                closed += 1
    assert not problems, "\n".join(problems[:20])
    assert not open_tags, f"transactions never completed: {sorted(open_tags)}"
    assert closed > 500 and notes <= {"1.4.3: Tool.AvrRadius() (6.3.13)",
                                      "1.4.3: GetMachineClass answers an enumeration, not a string (6.3.2.8)",
                                      "1.4.3: Q() (6.3.2.24)"}, notes
