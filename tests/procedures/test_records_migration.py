"""The in-place migration of a records file written by the SQLite-only records layer (data/records_v0.sqlite, made
by data/make_records_v0.py through that layer's own API), and the engine-independent parts of the schema."""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import pytest
import sqlalchemy as sa
from alembic.script import ScriptDirectory

from procedures.records import Records, RecordsError, records_url
from procedures.records.migrate import HEAD, MIGRATIONS, _alembic_config
from procedures.station import load_station

V0 = Path(__file__).parent / "data" / "records_v0.sqlite"
RUNS = {"20260301T080000Z-aaaaaa": ("complete", "paper-table1", "J. Smith", "ls"),
        "20260302T090000Z-bbbbbb": ("interrupted", "paper-table1", "K. Lee", "linf"),
        "20260304T070000Z-cccccc": ("running", "hexapod-small", None, "ls")}


@pytest.fixture
def v0(tmp_path: Path) -> Path:
    path = tmp_path / "records.sqlite"
    shutil.copy(V0, path)
    return path


def raw_rows(path: Path, sql: str) -> list[tuple]:
    db = sqlite3.connect(path)
    try:
        return db.execute(sql).fetchall()
    finally:
        db.close()


def test_the_fixture_is_what_the_old_layer_wrote(v0: Path):
    assert raw_rows(v0, "PRAGMA user_version") == [(1,)]
    assert raw_rows(v0, "SELECT name FROM sqlite_master WHERE name = 'alembic_version'") == []
    assert len(raw_rows(v0, "SELECT * FROM uploads")) == 3


def test_an_old_file_upgrades_in_place_and_keeps_every_record(v0: Path):
    before = {t: raw_rows(v0, f"SELECT * FROM {t} ORDER BY 1") for t in ("runs", "parameter_sets", "uploads")}
    with Records(v0) as db:
        assert db.migration == "upgraded from 0001"
        runs = {r["run_id"]: r for r in db.history(include_standalone=False)}
        assert {k: (r["status"], r["robot_name"], r["operator"], r["estimator"]) for k, r in runs.items()} == RUNS
        assert {r["machine"] for r in runs.values()} == {"paper-table1", "hexapod-small"}  # no serial known then
        done = runs["20260301T080000Z-aaaaaa"]
        assert done["verify_after"]["max_position_mm"] == 0.0412 and done["out_dir"] == "/data/runs/r1"
        (committed,) = done["uploads"]
        assert committed["upload_id"] == "legacy-1" and committed["machine"] == "paper-table1"
        assert committed["record"]["live_readback_match"] is True
        rollback = db.last_upload(outcome="rolled_back")
        assert rollback is not None and rollback["operator"] == "bob" and rollback["run_id"] is None
        assert db.parameter_set(committed["params_sha256"])["source"] == "identified"
        # it takes the new records: an upload, parameters, a certificate
        db.record_upload({"outcome": "committed", "endpoint": "tcp://x:502"}, "ann",
                         run_id="20260304T070000Z-cccccc", upload_id="u-new")
        db.record_parameters("20260301T080000Z-aaaaaa", {"leg1_l0_mm": (3800.1, 0.002)})
        db.update_run("20260301T080000Z-aaaaaa", verdict="pass", certificate_number="C-1")
        assert db.run("20260301T080000Z-aaaaaa")["certificate_number"] == "C-1"
    after = {t: raw_rows(v0, f"SELECT * FROM {t} ORDER BY 1") for t in ("runs", "parameter_sets", "uploads")}
    assert [r[:11] for r in after["runs"]][:3] == [r[:11] for r in before["runs"]]
    assert after["parameter_sets"] == before["parameter_sets"]
    assert [r[:8] for r in after["uploads"][:3]] == [r[:8] for r in before["uploads"]]
    assert raw_rows(v0, "PRAGMA user_version") == [(2,)]  # the old layer (version 1 only) refuses it now
    with Records(v0) as again:
        assert again.migration == "current"


def schema(path: Path) -> dict:
    inspector = sa.inspect(sa.create_engine(f"sqlite:///{path}"))
    out = {}
    for table in sorted(inspector.get_table_names()):
        columns = [(c["name"], str(c["type"]), c["nullable"] or c["primary_key"]) for c in
                   inspector.get_columns(table)]
        fks = [(f["referred_table"], tuple(f["constrained_columns"]), f["options"].get("ondelete")) for f in
               inspector.get_foreign_keys(table)]
        indexes = sorted((i["name"], tuple(i["column_names"]), i["unique"]) for i in inspector.get_indexes(table))
        out[table] = (columns, fks, indexes)
    return out


def test_an_upgraded_file_has_exactly_the_schema_of_a_new_one(v0: Path, tmp_path: Path):
    Records(v0).close()
    Records(tmp_path / "new.sqlite").close()
    assert schema(v0) == schema(tmp_path / "new.sqlite")


def test_head_is_alembics_head_and_a_newer_database_is_refused(tmp_path: Path):
    path = tmp_path / "r.sqlite"
    with Records(path) as db, db.engine.connect() as conn:
        assert ScriptDirectory.from_config(_alembic_config(conn)).get_current_head() == HEAD
        assert (MIGRATIONS / "env.py").is_file()
        conn.execute(sa.text("UPDATE alembic_version SET version_num = '0099'"))
        conn.commit()
    with pytest.raises(RecordsError, match="newer hilcal"):
        Records(path)


def test_records_targets_paths_and_urls(tmp_path: Path):
    assert records_url(tmp_path / "a.sqlite").database == str(tmp_path / "a.sqlite")
    url = records_url("postgresql://ann:secret@db.plant:5433/hilcal")
    assert url.drivername == "postgresql+psycopg" and url.port == 5433 and url.database == "hilcal"
    with pytest.raises(RecordsError, match="SQLite or PostgreSQL"):
        records_url("mysql://db/x")
    with pytest.raises(RecordsError, match="name the database"):
        records_url("postgresql+psycopg://db.plant")
    with pytest.raises(RecordsError, match="in-memory"):
        records_url("sqlite://")
    with pytest.raises(RecordsError, match="psycopg"):
        records_url("postgresql+asyncpg://db/x")


STATION = """
[can]
interface = "virtual"
channel = "c"
[modbus]
host = "127.0.0.1"
[cmm]
url = "loop://"
alignment = [0, 0, 0, 0, 0, 0]
"""


def test_a_station_names_its_records_by_folder_file_or_url(tmp_path: Path):
    def target(head: str) -> str | None:
        (tmp_path / "station.toml").write_text(head + STATION)
        return load_station(tmp_path / "station.toml").records_target()

    assert target("") is None
    assert target('records = "runs"\n') == str(tmp_path / "runs" / "records.sqlite")
    assert target('records = "/data/plant.sqlite"\n') == "/data/plant.sqlite"
    url = "postgresql+psycopg://hilcal@db.plant/hilcal"
    assert target(f'[records]\nurl = "{url}"\n') == url
    assert target('[records]\nurl = "local/records.sqlite"\n') == str(tmp_path / "local" / "records.sqlite")
