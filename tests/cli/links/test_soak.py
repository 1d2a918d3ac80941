"""The soak benchmark's short version: full runs under faults, judged as `benchmarks/bench_soak.py` judges them (no
measurement lost or duplicated, no half-written parameter set, nothing commanded in a link gap): a Modbus connection
dropped in the upload and a CMM that falls silent or garbles its replies here, link gaps in test_link_guard.py.

The two faulted runs run at once and record into one PostgreSQL database, so they are also the records' test of two
runs at once (a whole run is expensive: tests of claims about the same runs share them)."""

from __future__ import annotations

import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from typer.testing import CliRunner

from procedures.cli.app import app
from procedures.records import Records
from tests.cli.sim_speed import INSTANT_SIM, plan_rows

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))

from soak_runs import CONDITIONS, SoakRun, soak_run

BY_NAME = {c.name: c for c in CONDITIONS}
FAULTS = {"modbus_drops": (1, "modbus", "A"),  # the connection drops at the upload's first write
          "cmm_faults": (3, "cmm", "B")}
"""condition: (seed, the link it faults, the operator's name in the records)."""

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


@pytest.fixture(scope="module")
def soaked(tmp_path_factory: pytest.TempPathFactory, small_plan: Path, postgres
           ) -> tuple[dict[str, SoakRun], str, Path]:
    """Both faulted runs at once, each recording into the same PostgreSQL database (--records), on the small plan."""
    tmp = tmp_path_factory.mktemp("soak")
    pg_url = postgres.new_database()

    def one(condition: str) -> SoakRun:
        seed, _, operator = FAULTS[condition]
        return soak_run(BY_NAME[condition], seed, tmp / condition, extra_sim_config=INSTANT_SIM,
                        extra_run_args=("--plan", str(small_plan), "--records", pg_url, "--operator", operator))

    with ThreadPoolExecutor(len(FAULTS)) as pool:
        runs = dict(zip(FAULTS, pool.map(one, FAULTS), strict=True))
    return runs, pg_url, tmp


@pytest.mark.parametrize("condition", list(FAULTS))
def test_a_faulted_run_completes_with_nothing_lost(soaked, small_plan: Path, condition: str) -> None:
    """The servo and the CMM work at once (tests/cli/sim_speed.py) and the plan is the small one (12 + 6 poses):
    every check counts what happened (rows, commands in a gap, holds), not how long it took."""
    run = soaked[0][condition]
    _, link, _ = FAULTS[condition]
    assert run.completed, run
    assert (run.rows, run.lost, run.duplicated) == (sum(plan_rows(small_plan)), 0, 0)
    assert run.live_set == "new", "the uploaded set is live, whole"
    assert run.late_commands == 0
    assert run.verify_after_max_mm is not None and run.verify_after_max_mm <= 0.05
    assert run.holds.get(link, 0) >= 1, f"the {link} fault happened and was ridden through: {run.holds}"


def test_two_simulated_runs_at_once_record_into_one_postgresql_database(soaked) -> None:
    runs, pg_url, tmp = soaked
    assert all(run.completed for run in runs.values()), runs
    history = CliRunner().invoke(app, ["history", "--records", pg_url, "--json"])
    entries = [e for e in json.loads(history.output)["entries"] if e["kind"] == "run"]
    assert sorted(e["operator"] for e in entries) == ["A", "B"]
    assert {e["status"] for e in entries} == {"complete"} and {e["machine"] for e in entries} == {"paper-table1"}
    # the commit and the save, each with its own record
    assert all([u["outcome"] for u in e["uploads"]] == ["committed", "saved"] for e in entries)
    with Records(pg_url) as db:
        for e in entries:
            assert len(db.run_parameters(e["run_id"])) == 48
        assert len(db.calibrations("paper-table1")) == 2
    reports = [json.loads((tmp / condition / "run" / "report.json").read_text()) for condition in runs]
    assert sorted(r["drift"]["n_calibrations"] for r in reports) in ([1, 2], [2, 2], [1, 1])
    assert not any((tmp / condition / "records.sqlite").exists() for condition in runs), "--records, not the default"
