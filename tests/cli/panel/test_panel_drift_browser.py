"""The panel's History view in headless Chromium on a PostgreSQL records database: choosing a machine shows its runs
and its drift (the flag in words and the trend plots)."""

from __future__ import annotations

import pytest
from selenium.webdriver.support.ui import Select

from procedures.panel.app import PanelContext
from procedures.panel.live import LiveState
from procedures.panel.server import PanelServer
from procedures.records import Records
from tests.cli.browser_support import chromium, text, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]


def test_choosing_a_machine_shows_its_runs_and_drift(pg_url):
    with Records(pg_url) as db:
        for j in range(6):
            stroke = 612.0 + (0.2 if j >= 4 else 0.0) + 0.001 * (j % 2)
            db.save_run(f"run{j}", {"started_at": f"2026-0{1 + j}-01T08:00:00+00:00", "status": "complete",
                                    "robot_name": "paper-table1", "machine_serial": "SN-9"},
                        {"leg5_stroke_at_home_mm": (stroke, 0.002)})
        db.save_run("other", {"started_at": "2026-02-02T08:00:00+00:00", "status": "complete",
                              "robot_name": "hexapod-small"})
    with PanelServer(PanelContext(LiveState(), records_path=pg_url), "127.0.0.1", 0) as server, \
            chromium() as browser:
        browser.get(server.url)
        browser.find_element("id", "tab-history").click()
        wait_for(lambda: "run5" in text(browser, "history-table"), 20, "the history table")
        assert "hexapod-small" in text(browser, "history-table")
        Select(browser.find_element("id", "machines")).select_by_value("paper-table1/SN-9")
        flags = wait_for(lambda: text(browser, "drift-flags"), 20, "the drift of the chosen machine")
        assert "leg 5 stroke at home +0.20 mm since 2026-05-01" in flags
        assert "hexapod-small" not in text(browser, "history-table")
        assert browser.find_element("id", "drift-plot").get_attribute("src").startswith("data:image/png;base64,")
