"""The records under concurrent writers and faults, against a real PostgreSQL server started by the tests (and the
same writers on a SQLite file): no lost, duplicated or half-written record."""

from __future__ import annotations

import multiprocessing
import time
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy import event

from procedures.journal import Journal
from procedures.records import Records, RecordsUnavailable
from procedures.records.sync import RunRecorder, run_fields, sync_folders
from procedures.runner import EXIT_INTERRUPTED, RunRequest, execute_run
from tests.postgres_server import postgres_server

pytestmark = pytest.mark.timeout(120)
RUNS_PER_WRITER = 50
NAMES = [f"leg{i}_{p}_mm" for i in range(1, 7) for p in ("a_x", "a_y", "a_z", "b_x", "b_y", "b_z", "l0",
                                                           "stroke_at_home")]


def parameters(k: int) -> dict[str, tuple[float, float | None]]:
    return {name: (1000.0 + k + 0.001 * j, 0.002) for j, name in enumerate(NAMES)}


def whole_run(k: int, writer: str) -> dict:
    return {"started_at": f"2026-10-01T08:{k // 60:02d}:{k % 60:02d}+00:00", "status": "complete",
            "robot_name": "paper-table1", "machine_serial": f"SN-{writer}", "station": f"bay {writer}",
            "operator": writer}


def upload(run_id: str, k: int) -> dict:
    return {"upload_id": f"{run_id}/upload", "operator": "ann",
            "record": {"operation": "upload", "outcome": "committed", "endpoint": "tcp://10.0.0.5:502",
                       "started_at": f"2026-10-01T09:00:{k % 60:02d}+00:00", "params_sha256": f"{k:064x}"}}


def writer(target: str, name: str, go: multiprocessing.synchronize.Event) -> None:
    """One station: opens the records (a fresh database: both migrate it at once), then writes its runs."""
    go.wait(30)
    with Records(target) as db:
        for k in range(RUNS_PER_WRITER):
            run_id = f"{name}-{k:03d}"
            db.save_run(run_id, whole_run(k, name), parameters(k), [upload(run_id, k)])


def two_writers_at_once(target: str) -> None:
    ctx = multiprocessing.get_context("spawn")
    go = ctx.Event()
    procs = [ctx.Process(target=writer, args=(target, name, go)) for name in ("A", "B")]
    for p in procs:
        p.start()
    time.sleep(1.0)  # both interpreters up and waiting
    go.set()
    for p in procs:
        p.join(90)
    assert [p.exitcode for p in procs] == [0, 0]


def check_complete(target: str, runs: int) -> None:
    with Records(target) as db, db.engine.connect() as conn:
        count = {t: conn.execute(sa.text(f"SELECT COUNT(*) FROM {t}")).scalar() for t in
                 ("runs", "run_parameters", "uploads", "audit")}
        per_run = conn.execute(sa.text("SELECT run_id, COUNT(*) FROM run_parameters GROUP BY run_id")).all()
        upload_ids = conn.execute(sa.text("SELECT COUNT(DISTINCT upload_id) FROM uploads")).scalar()
        machines = {m["machine"]: m["runs"] for m in db.machines()}
    assert count == {"runs": runs, "run_parameters": runs * len(NAMES), "uploads": runs, "audit": runs}
    assert len(per_run) == runs and {n for _, n in per_run} == {len(NAMES)}
    assert upload_ids == runs
    assert machines == {"paper-table1/SN-A": runs // 2, "paper-table1/SN-B": runs // 2}


@pytest.mark.slow
def test_two_processes_writing_50_runs_each_into_postgresql_store_100_complete_records(pg_url):
    two_writers_at_once(pg_url)
    check_complete(pg_url, 2 * RUNS_PER_WRITER)


@pytest.mark.slow
def test_two_processes_writing_50_runs_each_into_one_sqlite_file_store_100_complete_records(tmp_path):
    target = str(tmp_path / "records.sqlite")
    two_writers_at_once(target)
    check_complete(target, 2 * RUNS_PER_WRITER)


def kill_when(db: Records, table: str, killer: sa.Engine) -> list[int]:
    """Terminate the writer's own backend (from another connection) just before it first writes `table`."""
    killed: list[int] = []

    @event.listens_for(db.engine, "before_cursor_execute")
    def _kill(conn, cursor, statement, params, context, executemany):
        if not killed and statement.lstrip().upper().startswith(f"INSERT INTO {table.upper()}"):
            pid = conn.exec_driver_sql("SELECT pg_backend_pid()").scalar()
            with killer.connect() as other:
                assert other.execute(sa.text("SELECT pg_terminate_backend(:p)"), {"p": pid}).scalar()
            killed.append(pid)

    return killed


def test_a_connection_killed_mid_transaction_leaves_nothing_half_written(pg_url):
    killer = sa.create_engine(pg_url)
    with Records(pg_url, retries=0) as db:
        db.save_run("r-first", whole_run(0, "A"), parameters(0), [upload("r-first", 0)])
        killed = kill_when(db, "run_parameters", killer)
        with pytest.raises(RecordsUnavailable):
            db.save_run("r-killed", whole_run(1, "A"), parameters(1), [upload("r-killed", 1)])
        assert killed  # the run row was written in the transaction, then its connection died
        assert db.run("r-killed") is None and db.run_parameters("r-killed") == {}
        assert [u["upload_id"] for u in db.history(include_standalone=True)[0]["uploads"]] == ["r-first/upload"]
    with Records(pg_url, retries=2) as db:  # with retries the same write goes through once, whole
        killed = kill_when(db, "uploads", killer)
        db.save_run("r-killed", whole_run(1, "A"), parameters(1), [upload("r-killed", 1)])
        assert killed
        assert len(db.run_parameters("r-killed")) == len(NAMES)
        assert [u["upload_id"] for u in db.run("r-killed")["uploads"]] == ["r-killed/upload"]
        assert len(db.audit_trail("r-killed/upload")) == 1
    killer.dispose()


def test_an_upload_and_its_audit_row_are_one_transaction(pg_url):
    killer = sa.create_engine(pg_url)
    with Records(pg_url, retries=0) as db:
        db.record_run("r1", started_at="2026-10-01T08:00:00+00:00", status="complete", robot_name="paper-table1")
        kill_when(db, "audit", killer)
        with pytest.raises(RecordsUnavailable):
            db.record_upload(upload("r1", 1)["record"], "ann", run_id="r1", upload_id="u-1")
        assert db.last_upload() is None and db.audit_trail("u-1") == []
        db.record_upload(upload("r1", 1)["record"], "ann", run_id="r1", upload_id="u-1")
        db.record_upload(upload("r1", 1)["record"], "ann", run_id="r1", upload_id="u-1")  # a retry: stored once
        assert len(db.run("r1")["uploads"]) == 1 and len(db.audit_trail("u-1")) == 1
    killer.dispose()


def test_a_database_down_at_the_start_refuses_the_run_before_anything_happens(tmp_path):
    with postgres_server() as pg:
        url = pg.new_database()
    started = []
    request = RunRequest(out_dir=tmp_path / "run", sim=True, yes=True, records_path=url,
                         sim_station=lambda *a: started.append(a))
    t0 = time.monotonic()
    result = execute_run(request, None)
    assert result.code == EXIT_INTERRUPTED and "is unavailable" in result.message
    assert "did not start and nothing moved" in result.message and "postgres@127.0.0.1" in result.message
    assert time.monotonic() - t0 < 30 and started == [] and not (tmp_path / "run").exists()


def test_a_database_lost_mid_run_keeps_the_records_in_the_journal_until_sync(tmp_path):
    folder = tmp_path / "runs" / "r1"
    folder.mkdir(parents=True)
    with postgres_server(fsync=True) as pg:  # durable commits: the stop below is a crash (immediate)
        url = pg.new_database()
        recorder = RunRecorder(url)
        recorder.open()
        with Journal(folder / "journal.sqlite") as journal:
            journal.start("r1", "p" * 64, "{}", {})
            start = run_fields("r1", "2026-10-01T08:00:00+00:00", "paper-table1", "p" * 64, "ann", folder, "ls",
                               "SN-7", "bay 2")
            recorder.write(journal, run=start)
            assert recorder.pending is None and recorder.records.run("r1")["status"] == "running"
            pg.stop()  # the database goes away while the machine measures
            recorder.write(journal, run={"status": "complete", "finished_at": "2026-10-01T08:40:00+00:00"},
                           parameters=parameters(1), upload=upload("r1", 1))
            assert recorder.pending is not None and "unavailable" in recorder.pending
            assert "hilcal records sync" in recorder.message(folder)
        recorder.close()
        pg.start()
        with Records(url) as db:
            assert db.run("r1")["status"] == "running"  # what was written before the loss
            for _ in range(2):  # sync twice: written once
                report = sync_folders(db, [tmp_path / "runs"], say=lambda _: None)
                assert report.written == ["r1"] and report.failed == []
            run = db.run("r1")
            assert run["status"] == "complete" and run["machine"] == "paper-table1/SN-7"
            assert [u["upload_id"] for u in run["uploads"]] == ["r1/upload"]
            assert len(db.run_parameters("r1")) == len(NAMES) and len(db.audit_trail("r1/upload")) == 1


def test_sync_finds_nothing_to_write_in_a_folder_without_runs(tmp_path):
    (tmp_path / "empty").mkdir()
    with Records(tmp_path / "r.sqlite") as db:
        report = sync_folders(db, [Path(tmp_path / "empty")], say=lambda _: None)
    assert report.written == [] and report.failed == []
