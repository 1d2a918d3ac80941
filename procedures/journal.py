"""The run journal: every completed measurement and step is committed to SQLite (WAL) before the next move.

One database per run folder. A resumed run reads it back, so no measurement is repeated or lost.
"""

from __future__ import annotations

import json
import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np

SCHEMA = """
CREATE TABLE IF NOT EXISTS run (
    run_id TEXT PRIMARY KEY, created_at REAL NOT NULL, plan_sha256 TEXT NOT NULL, plan_json TEXT NOT NULL,
    options_json TEXT NOT NULL, status TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS measurements (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, phase TEXT NOT NULL, pose_index INTEGER NOT NULL,
    time_s REAL NOT NULL, cmd_json TEXT NOT NULL, legs_json TEXT NOT NULL, meas_json TEXT NOT NULL,
    detail_json TEXT NOT NULL, UNIQUE (phase, pose_index)
);
CREATE TABLE IF NOT EXISTS steps (
    key TEXT PRIMARY KEY, time REAL NOT NULL, value_json TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, kind TEXT NOT NULL, data_json TEXT NOT NULL
);
"""


class JournalError(RuntimeError):
    """The journal cannot be opened or does not belong to this run."""


class Journal:
    """SQLite journal of one run; every write is its own committed transaction."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._db = sqlite3.connect(path, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(SCHEMA)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, run_id: str, plan_sha256: str, plan_json: str, options: dict[str, Any]) -> None:
        self._db.execute("INSERT INTO run VALUES (?, ?, ?, ?, ?, 'running')",
                         (run_id, time.time(), plan_sha256, plan_json, json.dumps(options)))

    def run_info(self) -> dict[str, Any]:
        row = self._db.execute("SELECT run_id, created_at, plan_sha256, plan_json, options_json, status FROM run"
                               ).fetchone()
        if row is None:
            raise JournalError(f"{self.path} holds no run")
        keys = ("run_id", "created_at", "plan_sha256", "plan_json", "options", "status")
        info = dict(zip(keys, row, strict=True))
        info["options"] = json.loads(info["options"])
        return info

    def set_options(self, options: dict[str, Any]) -> None:
        """Replace the run's options (only before anything moved: the operator changed the plan on the start form)."""
        self._db.execute("UPDATE run SET options_json = ?", (json.dumps(options),))

    def set_status(self, status: str) -> None:
        self._db.execute("UPDATE run SET status = ?", (status,))

    def add_measurement(self, phase: str, index: int, time_s: float, cmd: np.ndarray, legs: np.ndarray,
                        meas: np.ndarray, detail: dict[str, Any]) -> dict[str, Any]:
        self._db.execute(
            "INSERT INTO measurements (phase, pose_index, time_s, cmd_json, legs_json, meas_json, detail_json) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (phase, index, time_s, json.dumps(np.asarray(cmd).tolist()), json.dumps(np.asarray(legs).tolist()),
             json.dumps(np.asarray(meas).tolist()), json.dumps(detail)),
        )
        return self.measurement(phase, index)

    def measurement(self, phase: str, index: int) -> dict[str, Any] | None:
        row = self._db.execute("SELECT seq, phase, pose_index, time_s, cmd_json, legs_json, meas_json, detail_json "
                               "FROM measurements WHERE phase = ? AND pose_index = ?", (phase, index)).fetchone()
        return None if row is None else _row(row)

    def last_measurement(self) -> dict[str, Any] | None:
        """The row measured last, of any phase (None before the first)."""
        row = self._db.execute("SELECT seq, phase, pose_index, time_s, cmd_json, legs_json, meas_json, detail_json "
                               "FROM measurements ORDER BY seq DESC LIMIT 1").fetchone()
        return None if row is None else _row(row)

    def measurements(self, phases: tuple[str, ...]) -> list[dict[str, Any]]:
        marks = ",".join("?" * len(phases))
        rows = self._db.execute(f"SELECT seq, phase, pose_index, time_s, cmd_json, legs_json, meas_json, detail_json "
                                f"FROM measurements WHERE phase IN ({marks}) ORDER BY seq", phases).fetchall()
        return [_row(r) for r in rows]

    def step(self, key: str) -> Any:
        row = self._db.execute("SELECT value_json FROM steps WHERE key = ?", (key,)).fetchone()
        return None if row is None else json.loads(row[0])

    def step_time(self, key: str) -> float | None:
        """Wall-clock time (s since the epoch) at which the step was last written, None if never."""
        row = self._db.execute("SELECT time FROM steps WHERE key = ?", (key,)).fetchone()
        return None if row is None else float(row[0])

    def set_step(self, key: str, value: Any) -> None:
        self._db.execute("INSERT OR REPLACE INTO steps VALUES (?, ?, ?)", (key, time.time(), json.dumps(value)))

    def count_events(self, *kinds: str) -> int:
        """How many events of these kinds were journaled."""
        marks = ",".join("?" * len(kinds))
        return int(self._db.execute(f"SELECT COUNT(*) FROM events WHERE kind IN ({marks})", kinds).fetchone()[0])

    def events(self, *kinds: str) -> list[dict[str, Any]]:
        """Journaled events of these kinds in order: time (s since the epoch), kind, data."""
        marks = ",".join("?" * len(kinds))
        rows = self._db.execute(f"SELECT time, kind, data_json FROM events WHERE kind IN ({marks}) ORDER BY rowid",
                                kinds).fetchall()
        return [{"time": t, "kind": k, "data": json.loads(d)} for t, k, d in rows]

    def event(self, kind: str, **data: Any) -> None:
        self._db.execute("INSERT INTO events (time, kind, data_json) VALUES (?, ?, ?)",
                         (time.time(), kind, json.dumps(data, default=str)))


def _row(row: tuple) -> dict[str, Any]:
    seq, phase, index, time_s, cmd, legs, meas, detail = row
    return {"seq": seq, "phase": phase, "index": index, "time_s": time_s, "cmd": np.array(json.loads(cmd)),
            "legs": np.array(json.loads(legs)), "meas": np.array(json.loads(meas)), "detail": json.loads(detail)}
