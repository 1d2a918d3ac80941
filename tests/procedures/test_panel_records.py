"""The panel's history on a PostgreSQL records database shared by stations: machines, one machine's runs, its drift
with trend plots; and what the panel says when the records do not answer."""

from __future__ import annotations

import base64

from starlette.testclient import TestClient

from procedures.panel.app import PanelContext, build_app
from procedures.panel.live import LiveState
from procedures.records import Records


def client(records: str) -> TestClient:
    return TestClient(build_app(PanelContext(LiveState(), records_path=records), loopback_only=True),
                      base_url="http://127.0.0.1")


def test_history_of_one_machine_and_its_drift_with_trend_plots(pg_url):
    with Records(pg_url) as db:
        for j in range(8):
            stroke = 500.0 + (0.15 if j >= 5 else 0.0) + 0.001 * (j % 3)
            db.save_run(f"run{j}", {"started_at": f"2026-0{1 + j}-01T08:00:00+00:00", "status": "complete",
                                    "robot_name": "paper-table1", "machine_serial": "SN-1", "station": "bay 1"},
                        {"leg3_stroke_at_home_mm": (stroke, 0.002), "leg3_l0_mm": (3800.0, 0.3)})
        db.save_run("elsewhere", {"started_at": "2026-05-01T08:00:00+00:00", "status": "complete",
                                  "robot_name": "hexapod-small", "station": "bay 2"})
    c = client(pg_url)
    every = c.get("/api/history").json()
    assert {m["machine"]: m["runs"] for m in every["machines"]} == {"paper-table1/SN-1": 8, "hexapod-small": 1}
    assert "postgres@127.0.0.1" in every["records"] and len(every["entries"]) == 9
    one = c.get("/api/history", params={"machine": "paper-table1/SN-1"}).json()
    assert {e["machine"] for e in one["entries"]} == {"paper-table1/SN-1"} and len(one["entries"]) == 8
    drift = c.get("/api/drift", params={"machine": "paper-table1/SN-1"}).json()
    assert drift["n_calibrations"] == 8
    assert drift["flags"] == ["leg 3 stroke at home +0.15 mm since 2026-06-01, "
                              f"{abs(drift['parameters'][0]['step_sigma']):.0f}σ: a transducer or joint moved along "
                              "the leg"]
    assert base64.b64decode(drift["plot_png"])[:4] == b"\x89PNG"
    assert c.get("/api/drift", params={"machine": "nope"}).status_code == 404
    assert c.get("/api/drift").status_code == 400


def test_unreachable_records_are_a_note_not_a_crash():
    c = client("postgresql+psycopg://nobody@127.0.0.1:1/x")
    history = c.get("/api/history").json()
    assert history["entries"] == [] and "records unavailable" in history["note"]
    assert c.get("/api/drift", params={"machine": "m"}).status_code == 503
