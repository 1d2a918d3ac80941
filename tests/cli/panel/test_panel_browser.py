"""`hilcal run --sim --panel` in headless Chromium: a whole run driven from the page alone (start, prompts, the
upload approval opening with the run's findings, report). The run watched live in two browsers, paused, aborted and
resumed is in test_panel_live_browser.py; the helpers both use in panel_support.py.

Each change's delay from the server's event to the page's updated DOM is measured in the browser and reported at the
end of the test session; it is not asserted (a loaded CI machine would make that flaky).
"""

from __future__ import annotations

import json
import sqlite3

import pytest

from tests.cli.browser_support import chromium, free_port, require_chromium, text, wait_for
from tests.cli.panel.panel_support import collect_latency, journal_rows, start_panel_run, stop
from tests.cli.sim_speed import INSTANT_SIM

pytestmark = pytest.mark.slow

SCALE_FAULT = """
[rig.effects.sensor_scale]
enabled = true
gain_error_ppm = [2500.0, 0.0, 0.0, 0.0, 0.0, 0.0]
[rig.effects.leg_compliance]
enabled = true
c_mm_per_kn = 0.006
"""
"""Leg 1's transducer configured 0.25 % long and legs that sag: the approval must open with what the run found."""


@pytest.fixture(autouse=True)
def _browser_present():
    require_chromium()


def _answer_questions(browser, operator: str, checks: dict) -> str:
    """Answer every question the page asks, as an operator would, until the run's result shows; return it."""
    answered: set[str] = set()

    def step() -> str | None:
        result = browser.find_elements("id", "result-message")
        if result and result[0].text:
            return result[0].text
        box = browser.find_element("id", "question")
        qid, title = box.get_attribute("data-id"), text(browser, "question-title")
        if not box.is_displayed() or not qid or qid in answered:
            return None
        yes = browser.find_element("id", "question-yes")
        if title == "Start the run":
            if "missing_name" not in checks:
                yes.click()
                wait_for(lambda: "operator's name" in text(browser, "question-error"), 10, "the missing-name error")
                checks["missing_name"] = True
            browser.find_element("id", "operator-name").send_keys(operator)
        elif title == "Approve the parameter upload":
            checks["diff_rows"] = len(browser.find_elements("css selector", "#upload-diff tr")) - 1
            checks["physics"] = text(browser, "upload-physics")
            checks["block"] = text(browser, "upload-block")
            checks["prediction"] = text(browser, "upload-prediction")
            checks["disabled_before_confirm"] = not yes.is_enabled()
            browser.find_element("id", "upload-confirm").click()
        yes.click()
        answered.add(qid)
        return None

    return wait_for(step, 300, "the run's result", poll_s=0.2)


@pytest.mark.timeout(900)
def test_a_whole_run_driven_from_the_browser_alone(tmp_path, calibration_plan):
    """Start, prompts, upload approval, report: all on the page (short heartbeat delays on a loaded machine are
    ridden through by the link guard, so the run completes in one go). The calibration plan: the findings need the
    default measurement design, and nothing here compares the verification with the prediction."""
    out = tmp_path / "run"
    checks: dict = {}
    proc = None
    try:
        with chromium() as browser:
            port = free_port()
            url = f"http://127.0.0.1:{port}/"
            (tmp_path / "sim.toml").write_text(INSTANT_SIM + SCALE_FAULT)  # the page drives it; its pace is not tested
            proc, log = start_panel_run(tmp_path, port, "--sim", "--sim-config", str(tmp_path / "sim.toml"), "--plan",
                               str(calibration_plan), "--out", str(out))
            browser.get(url)
            outcome = _answer_questions(browser, "B. Rowser", checks)
            assert "complete" in outcome, outcome
            physics = checks["physics"]  # the approval opens with the findings, faults first
            assert physics.index("Leg 1 reads 0.25% long") < physics.index("sag under the platform's weight")
            assert "the upload corrects the reading scale of each leg; check its transducer" in physics
            assert checks["block"].startswith("scale -2"), checks["block"]
            assert checks["missing_name"] and checks["disabled_before_confirm"]
            assert checks["diff_rows"] > 6, "the diff lists the changed parameters"
            assert "Predicted after the upload" in checks["prediction"] and "max" in checks["prediction"]
            assert text(browser, "upload-outcome") == "committed and saved to non-volatile memory; read back: matches"
            assert "after" in text(browser, "verification-summary")
            collect_latency(browser)
            report_url = browser.find_element("id", "link-report-html").get_attribute("href")
            browser.get(report_url)
            assert browser.find_element("tag name", "h1").text.startswith("Calibration run")
            browser.get(url)
            wait_for(lambda: browser.find_element("id", "close-panel").is_displayed(), 30, "the close button")
            browser.find_element("id", "close-panel").click()
            assert proc.wait(30) == 0, log.read_text()
        printed = " ".join(log.read_text().split())  # the terminal ends the panel run with the summary too
        assert "verification poses before after max position (mm)" in printed
        assert "uploaded joint positions a, b and leg offsets l0" in printed
        assert "verdict pass" in printed and f"report {out / 'report.html'} (and report.json)" in printed
        answers = [json.loads(r[0]) for r in journal_rows(out, "SELECT data_json FROM events WHERE kind = "
                                                           "'operator_answer' ORDER BY id")]
        assert {(a["answer"], a["via"], a["operator"]) for a in answers} == {(True, "page", "B. Rowser")}
        assert [a["key"] for a in answers][:3] == ["start", "spheres", "area"]
        assert {a["key"] for a in answers} == {"start", "spheres", "area", "upload"}
        records = sqlite3.connect(tmp_path / "records.sqlite")
        assert records.execute("SELECT operator, status FROM runs").fetchall() == [("B. Rowser", "complete")]
        assert records.execute("SELECT operator FROM uploads").fetchall() == [("B. Rowser",)] * 2  # upload, save
    finally:
        if proc is not None:
            stop(proc)
