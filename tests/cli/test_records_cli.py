"""`hilcal history`, `hilcal drift`, `hilcal records sync|machines` on real databases (a SQLite file and the
throw-away PostgreSQL server). Two `hilcal run --sim` at once recording into one PostgreSQL database: the two faulted
runs of tests/cli/links/test_soak.py."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta

import numpy as np
from typer.testing import CliRunner

from procedures.cli.app import app
from procedures.journal import Journal
from procedures.records import Records
from procedures.records.sync import stage

runner = CliRunner()


def text(result) -> str:
    """The command's output with rich's line wrapping undone."""
    return " ".join(result.output.split())
MACHINE = "paper-table1/DMS-0042"


def seed_history(target: str, n: int = 20, step_at: int = 12, step_mm: float = 0.1) -> list[str]:
    """A machine with n calibrations; leg 2's stroke at home moves by step_mm from calibration step_at on.
    (Values drawn here with their standard errors; tests/hilcal/test_drift.py plants steps in true geometries.)"""
    rng = np.random.default_rng(11)
    starts = []
    with Records(target) as db:
        for j in range(n):
            start = (datetime(2026, 3, 1, 8, tzinfo=UTC) + timedelta(days=14 * j)).isoformat()
            starts.append(start)
            params = {f"leg{i}_stroke_at_home_mm": (500.0 + i + rng.normal(0, 0.002)
                                                    + (step_mm if i == 2 and j >= step_at else 0.0), 0.002)
                      for i in range(1, 7)}
            params |= {f"leg{i}_l0_mm": (3800.0 + rng.normal(0, 0.3), 0.3) for i in range(1, 7)}
            db.save_run(f"run{j:02d}", {"started_at": start, "status": "complete", "robot_name": "paper-table1",
                                        "machine_serial": "DMS-0042", "station": "bay 2"}, params)
        db.save_run("other", {"started_at": starts[0], "status": "complete", "robot_name": "hexapod-small"})
    return starts


def test_history_json_of_one_machine_on_postgresql(pg_url):
    seed_history(pg_url, n=3)
    result = runner.invoke(app, ["history", "--records", pg_url, "--machine", MACHINE, "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert [e["run_id"] for e in data["entries"]] == ["run02", "run01", "run00"]
    assert {e["machine"] for e in data["entries"]} == {MACHINE} and "postgres@127.0.0.1" in data["records"]
    listing = runner.invoke(app, ["records", "machines", "--records", pg_url])
    assert "paper-table1/DMS-0042" in listing.output and "hexapod-small" in listing.output
    unknown = runner.invoke(app, ["history", "--records", pg_url, "--machine", "nope"])
    assert unknown.exit_code == 2 and "known: hexapod-small, paper-table1/DMS-0042" in text(unknown)


def test_drift_flags_the_planted_step_in_words_and_plots_it(tmp_path):
    target = str(tmp_path / "records.sqlite")
    starts = seed_history(target)
    plot = tmp_path / "trends.png"
    result = runner.invoke(app, ["drift", "--machine", MACHINE, "--records", target, "--plot", str(plot)])
    assert result.exit_code == 0, result.output
    out = text(result)
    assert f"flags: leg 2 stroke at home +0.10 mm since {starts[12][:10]}, " in out
    assert out.count("σ: a transducer or joint moved") == 1  # nothing else flagged
    assert "at least 0.05 mm" in out and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(runner.invoke(app, ["drift", "--machine", MACHINE, "--records", target, "--json"]).output)
    assert len(data["flags"]) == 1 and data["n_calibrations"] == 20
    quiet = runner.invoke(app, ["drift", "--machine", MACHINE, "--records", target, "--threshold-mm", "0.2"])
    assert "no parameter moved beyond the rule" in text(quiet)


def test_bad_and_unreachable_records_have_their_exit_codes(tmp_path):
    bad = runner.invoke(app, ["history", "--records", "mysql://db/x"])
    assert bad.exit_code == 2 and "SQLite or PostgreSQL" in text(bad)
    down = runner.invoke(app, ["history", "--records", "postgresql+psycopg://nobody@127.0.0.1:1/x"])
    assert down.exit_code == 3 and "unavailable" in text(down)


def test_records_sync_writes_what_a_journal_kept(tmp_path):
    run_dir = tmp_path / "runs" / "r1"
    run_dir.mkdir(parents=True)
    with Journal(run_dir / "journal.sqlite") as journal:
        journal.start("r1", "p" * 64, "{}", {})
        stage(journal, run={"run_id": "r1", "started_at": "2026-10-01T08:00:00+00:00", "status": "complete",
                            "robot_name": "paper-table1", "machine": "paper-table1"},
              parameters={"leg1_l0_mm": (3800.0, 0.3)},
              upload={"upload_id": "r1/upload", "operator": "ann",
                      "record": {"operation": "upload", "outcome": "committed", "endpoint": "tcp://x:502"}})
    target = str(tmp_path / "records.sqlite")
    for _ in range(2):
        result = runner.invoke(app, ["records", "sync", str(tmp_path / "runs"), "--records", target])
        assert result.exit_code == 0 and "1 run(s) written" in text(result)
    with Records(target) as db:
        assert [u["upload_id"] for u in db.run("r1")["uploads"]] == ["r1/upload"]
    assert runner.invoke(app, ["records", "sync", str(tmp_path / "nope")]).exit_code == 2
