"""Where the records live: a SQLite file (the default, one per station) or a PostgreSQL server (a whole plant).

``records_url`` turns what the operator gave (``--records``, the station's ``[records] url``, ``$HILCAL_RECORDS``)
into an SQLAlchemy URL: a plain path is a SQLite file, anything with ``://`` is a database URL
(``postgresql+psycopg://user@host/db``; ``postgresql://`` uses psycopg too). ``make_engine`` opens it with what
each engine needs for safe concurrent writers: SQLite in WAL mode with foreign keys on and writers taking the
lock at BEGIN (BEGIN IMMEDIATE, so two stations never deadlock on a lock upgrade); PostgreSQL with a bounded
connect timeout and a liveness check before a pooled connection is reused.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

from sqlalchemy import create_engine, event
from sqlalchemy.engine import URL, Connection, Engine, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, InterfaceError, OperationalError

WRITE = {"hilcal_write": True}
"""Execution option of a connection that writes: on SQLite its transaction starts with BEGIN IMMEDIATE."""


class RecordsError(ValueError):
    """A records request that cannot be honoured (unknown run, unknown field, bad source, bad URL, newer schema)."""


class RecordsUnavailable(RuntimeError):
    """The records database cannot be reached (down, refused, timed out, locked for too long)."""


def default_target() -> str:
    """$HILCAL_RECORDS (a path or a URL), else ~/.local/share/hilcal/records.sqlite."""
    env = os.environ.get("HILCAL_RECORDS")
    return env if env else str(Path.home() / ".local" / "share" / "hilcal" / "records.sqlite")


def records_url(target: str | Path | URL | None) -> URL:
    """The SQLAlchemy URL of a records target (a path, a URL or None for the default); RecordsError if unusable."""
    if isinstance(target, URL):
        url = target
    else:
        text = default_target() if target is None else str(target)
        if not text.strip():
            raise RecordsError("the records target is empty: give a file path or a database URL")
        if "://" not in text:
            return URL.create("sqlite", database=str(Path(text).expanduser().resolve()))
        try:
            url = make_url(text)
        except ArgumentError as err:
            raise RecordsError(f"not a database URL: {redact(text)} ({err})") from None
    backend = url.get_backend_name()
    if backend == "postgresql":
        if url.drivername == "postgresql":
            url = url.set(drivername="postgresql+psycopg")
        elif url.drivername != "postgresql+psycopg":
            raise RecordsError(f"{redact(url)}: hilcal talks to PostgreSQL through psycopg: postgresql+psycopg://...")
        if not url.database:
            raise RecordsError(f"{redact(url)}: name the database (postgresql+psycopg://user@host:port/DATABASE)")
    elif backend == "sqlite":
        if url.database in (None, "", ":memory:"):
            raise RecordsError("an in-memory SQLite database would lose the records: give a file")
        url = url.set(database=str(Path(url.database).expanduser().resolve()))
    else:
        raise RecordsError(f"records need SQLite or PostgreSQL, not {backend!r} ({redact(url)})")
    return url


def redact(url: str | URL) -> str:
    """The URL for messages and logs, without its password."""
    if isinstance(url, URL):
        return url.render_as_string(hide_password=True)
    if "://" not in url:
        return url
    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:
        return "<unparsable URL>"


def describe(url: URL) -> str:
    """What the operator reads: the SQLite file's path, or the redacted server URL."""
    return str(url.database) if url.get_backend_name() == "sqlite" else redact(url)


def make_engine(url: URL, connect_timeout_s: float = 5.0) -> Engine:
    """An engine for the records: SQLite (WAL, foreign keys, BEGIN IMMEDIATE for writers) or PostgreSQL."""
    if url.get_backend_name() == "sqlite":
        Path(str(url.database)).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"timeout": 30.0, "check_same_thread": False})

        @event.listens_for(engine, "connect")
        def _sqlite_connect(dbapi_connection: Any, _record: Any) -> None:
            dbapi_connection.isolation_level = None  # SQLAlchemy emits BEGIN itself (below)
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute("PRAGMA busy_timeout=30000")
            cursor.close()

        @event.listens_for(engine, "begin")
        def _sqlite_begin(conn: Connection) -> None:
            conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("hilcal_write") else "BEGIN")

        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=2, max_overflow=4,
                         connect_args={"connect_timeout": max(1, math.ceil(connect_timeout_s)),
                                       "application_name": "hilcal"})


def is_unavailable(err: BaseException) -> bool:
    """True for errors that mean 'the database is not reachable right now' (worth a retry, never bad input)."""
    if isinstance(err, DBAPIError) and err.connection_invalidated:
        return True
    if isinstance(err, OperationalError | InterfaceError):
        return True
    return isinstance(err, DBAPIError) and type(err.orig).__name__ in ("AdminShutdown", "OperationalError")
