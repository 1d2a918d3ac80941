"""A throw-away PostgreSQL server for the records tests and benchmarks: Debian's ``postgresql`` binaries, a
temporary data directory, trust authentication, listening on 127.0.0.1 on a free port; stopped and removed at
the end. PostgreSQL refuses to run as root, so as root the server runs as the ``postgres`` user.

Under CI (CI=true) missing binaries fail the test (``.ci/run`` installs them); elsewhere the test skips with the
command that installs them.
"""

from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

INSTALL = "apt-get install -y postgresql"


def pg_bin() -> Path | None:
    """The folder of pg_ctl and initdb: Debian's newest /usr/lib/postgresql/N/bin, else the PATH."""
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"), key=lambda p: int(Path(p).parts[4]))
    if versions:
        return Path(versions[-1]).parent
    found = shutil.which("pg_ctl")
    return Path(found).parent if found and shutil.which("initdb") else None


def require_postgres() -> Path:
    found = pg_bin()
    if found is not None:
        return found
    message = f"PostgreSQL server binaries (initdb, pg_ctl) not found; install them with `sudo {INSTALL}`"
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"CI must run the PostgreSQL tests: {message} (.ci/run does this)")
    pytest.skip(message)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class PgServer:
    """A running server: its port, and databases created on demand."""

    bin: Path
    folder: Path
    port: int
    fsync: bool = False

    def _as_owner(self, *args: str) -> list[str]:
        return ["runuser", "-u", "postgres", "--", *args] if os.geteuid() == 0 else list(args)

    def url(self, database: str = "postgres") -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/{database}"

    def new_database(self) -> str:
        """A fresh empty database; returns its URL."""
        import psycopg

        name = f"hilcal_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(f"host=127.0.0.1 port={self.port} user=postgres dbname=postgres",
                             autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def start(self) -> None:
        options = f"-h 127.0.0.1 -p {self.port} -k {self.folder} -c max_connections=60"
        if not self.fsync:
            options += " -F -c synchronous_commit=off -c full_page_writes=off"
        subprocess.run(self._as_owner(str(self.bin / "pg_ctl"), "-D", str(self.folder / "data"), "-o", options,
                                      "-l", str(self.folder / "server.log"), "-w", "-t", "60", "start"),
                       check=True, capture_output=True)

    def stop(self) -> None:
        subprocess.run(self._as_owner(str(self.bin / "pg_ctl"), "-D", str(self.folder / "data"), "-m", "immediate",
                                      "-w", "stop"), check=False, capture_output=True)


@contextmanager
def postgres_server(fsync: bool = False) -> Iterator[PgServer]:
    """Start a server in a temporary folder. Without `fsync` commits are not durable (fast, for tests that never
    crash the server); with it, a crash (``stop``, immediate mode) keeps every committed transaction."""
    binaries = require_postgres()
    folder = Path(tempfile.mkdtemp(prefix="hilcal-pg-"))
    if os.geteuid() == 0:
        shutil.chown(folder, "postgres", "postgres")
    folder.chmod(0o700)
    server = PgServer(binaries, folder, _free_port(), fsync)
    try:
        subprocess.run(server._as_owner(str(binaries / "initdb"), "-D", str(folder / "data"), "-A", "trust",
                                        "-U", "postgres", "-E", "UTF8", "--no-sync"), check=True, capture_output=True)
        server.start()
        yield server
    finally:
        server.stop()
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="session")
def postgres() -> Iterator[PgServer]:
    """One server for the test session (tests take a fresh database each with ``pg_url``)."""
    with postgres_server() as server:
        yield server


@pytest.fixture
def pg_url(postgres: PgServer) -> str:
    return postgres.new_database()
