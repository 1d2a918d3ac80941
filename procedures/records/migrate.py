"""Bring a records database to the schema this hilcal knows (Alembic), in place, on its first open.

Three cases: an empty database (every migration runs), a file written by the SQLite-only records layer (its tables
exist but Alembic never saw it: it is stamped at revision 0001, then upgraded), and one already at the head (a
single SELECT, so opening the records stays fast). The upgrade runs in one transaction that holds the
database's migration lock (BEGIN IMMEDIATE on SQLite, an advisory lock on PostgreSQL), so two stations opening a
new database at once migrate it once. A database newer than this hilcal is refused, never downgraded.
"""

from __future__ import annotations

from pathlib import Path

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from procedures.records.database import WRITE, RecordsError

HEAD = "0002"
"""The newest migration in ``migrations/versions`` (tests check that Alembic agrees)."""
MIGRATIONS = Path(__file__).resolve().parent / "migrations"
LEGACY_USER_VERSION = 1
"""PRAGMA user_version of the SQLite-only records layer."""
_LOCK_KEY = 0x68696C63  # "hilc": the PostgreSQL advisory lock of hilcal's migrations


def current_revision(conn: Connection) -> str | None:
    """The database's Alembic revision; None if Alembic never ran on it."""
    if not sa.inspect(conn).has_table("alembic_version"):
        return None
    return conn.execute(sa.text("SELECT version_num FROM alembic_version")).scalar()


def _known_revisions() -> set[str]:
    return {p.name.split("_", 1)[0] for p in (MIGRATIONS / "versions").glob("*.py")}


def _alembic_config(conn: Connection):
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.attributes["connection"] = conn
    return config


def _legacy(conn: Connection) -> bool:
    """True for a file of the SQLite-only records layer (its tables, no Alembic); RecordsError if newer than it."""
    if not sa.inspect(conn).has_table("runs"):
        return False
    if conn.dialect.name == "sqlite":
        version = conn.exec_driver_sql("PRAGMA user_version").scalar() or 0
        if version > LEGACY_USER_VERSION:
            raise RecordsError(f"schema version {version} without Alembic: not written by any hilcal")
    return True


def upgrade(engine: Engine) -> str:
    """Migrate the database to HEAD if it is not there yet; returns what was done ("current", "created",
    "upgraded from 0001", ...). RecordsError for a database newer than this hilcal."""
    with engine.connect() as conn:
        revision = current_revision(conn)
    if revision == HEAD:
        return "current"
    _check_known(revision)
    from alembic import command

    with engine.connect().execution_options(**WRITE) as conn, conn.begin():
        if conn.dialect.name == "postgresql":
            conn.execute(sa.text("SELECT pg_advisory_xact_lock(:key)"), {"key": _LOCK_KEY})
        revision = current_revision(conn)  # another station may have migrated while we waited for the lock
        if revision == HEAD:
            return "current"
        _check_known(revision)
        config = _alembic_config(conn)
        if revision is None and _legacy(conn):
            command.stamp(config, "0001")
            revision = "0001"
        command.upgrade(config, "head")
    return "created" if revision is None else f"upgraded from {revision}"


def _check_known(revision: str | None) -> None:
    if revision is not None and revision not in _known_revisions():
        raise RecordsError(f"the records database is at schema revision {revision}, which this hilcal does not "
                           f"know (it knows up to {HEAD}): it was written by a newer hilcal; update hilcal")
