"""`hilcal run --sim --panel` in headless Chromium, watched live in two browsers, paused, aborted from the page and
resumed (the helpers in panel_support.py).

The run needs to be slow enough to pause in its middle: the CMM probes at the demo's pace (about 0.4 s a pose) while
the servo moves at once, on the small plan (12 + 6 poses), so the run is spent waiting on the instrument, as at a
machine, and not CPU-bound (which on a 2-core machine shared with Chromium would cost the controller's heartbeats).
"""

from __future__ import annotations

import json
import re

import pytest

from tests.cli.browser_support import chromium, free_port, require_chromium, text, wait_for
from tests.cli.panel.panel_support import collect_latency, done_count, journal_rows, page_view, start_panel_run, stop
from tests.cli.sim_speed import plan_rows

pytestmark = pytest.mark.slow

SIM = """
[controller]
time_scale = 100000.0
[cmm]
time_scale = 0.01
[rig.temperature]
drift_k_per_h = 0.0
amplitude_k = 0.0
"""
"""The servo near-instant and the CMM 20 times slower than the demo's (its 122 s of machine time per pose take about
1.2 s): the browsers, at idle priority on a loaded machine, must find the run still measuring when they pause it. The
rig's clock follows the servo's: its temperature is held."""


@pytest.fixture(autouse=True)
def _browser_present():
    require_chromium()


@pytest.mark.timeout(900)
def test_live_run_in_two_browsers_then_abort_from_the_page_and_resume(tmp_path, small_plan):
    out = tmp_path / "run"
    (tmp_path / "sim.toml").write_text(SIM)
    n_measure, n_verify = plan_rows(small_plan)
    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    proc = None
    try:
        with chromium() as first, chromium() as second:  # started first: their start-up loads the CPU
            proc, log = start_panel_run(tmp_path, port, "--sim", "--yes", "--sim-config", str(tmp_path / "sim.toml"),
                                        "--plan", str(small_plan), "--out", str(out))
            first.get(url)
            done = wait_for(lambda p=proc: (done_count(first) >= 3 and done_count(first)) or p.poll() is not None, 120,
                            "three poses done on the page")
            assert proc.poll() is None, log.read_text()
            assert re.fullmatch(rf"(measure|verify) pose \d+ of ({n_measure}|{n_verify // 2})",
                                text(first, "current-pose"))
            (journaled,) = journal_rows(out, "SELECT COUNT(*) FROM measurements")[0]
            assert done <= journaled, "the page cannot be ahead of the journal"
            # the design poses with one of them measured 3 more times, then the verify poses
            assert len(first.find_elements("css selector", "#plan-table tr")) == 1 + n_measure + n_verify // 2

            second.get(url)
            first.find_element("id", "pause").click()
            for driver in (first, second):
                wait_for(lambda d=driver: text(d, "status") == "paused" and "Continue the run" in
                         text(d, "question-text"), 30, "the pause question in both browsers")
            assert page_view(first) == page_view(second)
            paused_view = page_view(first)
            assert paused_view["points"] == done_count(first) >= done
            second.refresh()
            wait_for(lambda: text(second, "status") == "paused" and text(second, "question-text"), 30,
                     "the reloaded page")
            assert page_view(second) == paused_view
            collect_latency(first)

            second.find_element("id", "question-no").click()  # "Abort run"
            assert proc.wait(60) == 3, log.read_text()
        assert f"--resume {journal_rows(out, 'SELECT run_id FROM run')[0][0]}" in log.read_text()
        (run_id, status), = journal_rows(out, "SELECT run_id, status FROM run")
        assert status == "interrupted"
        answers = [json.loads(r[0]) for r in journal_rows(out, "SELECT data_json FROM events WHERE kind = "
                                                           "'operator_answer' AND data_json LIKE '%pause%'")]
        assert [(a["answer"], a["via"]) for a in answers] == [(False, "page")]
        kept = journal_rows(out, "SELECT COUNT(*) FROM measurements")[0][0]
        assert kept >= paused_view["points"]

        port = free_port()
        with chromium() as third:
            proc, log = start_panel_run(tmp_path, port, "--resume", run_id, "--yes", "--out", str(out))
            third.get(f"http://127.0.0.1:{port}/")
            wait_for(lambda: done_count(third) >= kept, 60, "the resumed run's journaled poses on the page")
            assert "resumed" in text(third, "run-title")
        code = proc.wait(240)  # the browser is closed; the run goes on
        assert code == 0, log.read_text()
        rows = journal_rows(out, "SELECT phase, pose_index FROM measurements")
        assert len(rows) == len(set(rows)) == n_measure + n_verify
        assert json.loads((out / "report.json").read_text())["status"] == "complete"
    finally:
        if proc is not None:
            stop(proc)


