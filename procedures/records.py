"""Calibration records in SQLite: runs, parameter sets and every controller upload, refused and failed ones too.

One file per workstation (the CLI chooses the path). WAL journal so a reader (``hilcal history``) never
blocks a run that is writing, foreign keys on so an upload cannot name a run that does not exist. Also the
operator-facing helpers behind ``hilcal upload`` and ``hilcal rollback``: they take a connected
``ControllerParams`` and never open a device themselves.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

from pydantic import ValidationError

from drivers.controller_modbus import (
    ControllerParams,
    ParameterSet,
    ParameterValidationError,
    ParamsError,
    UploadRecord,
)

SCHEMA_VERSION = 1
Source = Literal["identified", "controller", "file"]
PARAMETER_KEYS = frozenset({"a_mm", "b_mm", "l0_mm"})

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY,
    started_at TEXT NOT NULL,
    finished_at TEXT,
    status TEXT NOT NULL,
    robot_name TEXT,
    plan_sha256 TEXT,
    operator TEXT,
    out_dir TEXT,
    estimator TEXT,
    verify_before_json TEXT,
    verify_after_json TEXT
);
CREATE TABLE IF NOT EXISTS parameter_sets (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    sha256 TEXT NOT NULL UNIQUE,
    created_at TEXT NOT NULL,
    source TEXT NOT NULL CHECK (source IN ('identified', 'controller', 'file')),
    json TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS uploads (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id TEXT REFERENCES runs(run_id) ON DELETE RESTRICT,
    time TEXT NOT NULL,
    operator TEXT,
    endpoint TEXT,
    params_sha256 TEXT,
    outcome TEXT NOT NULL,
    record_json TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS uploads_by_run ON uploads(run_id);
CREATE INDEX IF NOT EXISTS uploads_by_endpoint_time ON uploads(endpoint, time);
CREATE INDEX IF NOT EXISTS runs_by_start ON runs(started_at);
"""

RUN_FIELDS = ("started_at", "finished_at", "status", "robot_name", "plan_sha256", "operator", "out_dir", "estimator",
              "verify_before", "verify_after")


class RecordsError(ValueError):
    """A records request that cannot be honoured (unknown run, unknown field, bad source)."""


class ParameterFileError(ParameterValidationError):
    """A parameter file that cannot be read or is not a sane parameter set; nothing was written."""


class UploadDeclined(ParamsError):
    """The operator did not confirm the upload; nothing was written."""


def now_iso() -> str:
    """UTC timestamp in the format of the driver's records (ISO 8601, microseconds, +00:00)."""
    return datetime.now(UTC).isoformat(timespec="microseconds")


def _dumps(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def parameter_set_sha256(params_json: Mapping[str, Any]) -> str:
    """The controller's hash (SHA-256 of the float32 registers) for an {a_mm, b_mm, l0_mm} set, so it matches
    UploadRecord.params_sha256; SHA-256 of the canonical JSON for any other parameter dict."""
    if set(params_json) == PARAMETER_KEYS:
        try:
            return ParameterSet.model_validate(dict(params_json)).sha256()
        except ValidationError as err:
            raise ParameterValidationError(f"invalid parameter set: {err}") from None
    return hashlib.sha256(_dumps(dict(params_json)).encode()).hexdigest()


class Records:
    """The records database; use as a context manager (commits per call, closes on exit)."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path, timeout=10.0)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        version = self._db.execute("PRAGMA user_version").fetchone()[0]
        if version > SCHEMA_VERSION:
            self._db.close()
            raise RecordsError(f"{self.path} has schema version {version}; this hilcal knows {SCHEMA_VERSION}")
        with self._db:
            self._db.executescript(_SCHEMA)
            self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Records:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ writes

    def record_run(
        self,
        run_id: str,
        *,
        started_at: str,
        status: str,
        robot_name: str | None = None,
        plan_sha256: str | None = None,
        operator: str | None = None,
        out_dir: Path | str | None = None,
        estimator: str | None = None,
        finished_at: str | None = None,
        verify_before: Mapping[str, Any] | None = None,
        verify_after: Mapping[str, Any] | None = None,
    ) -> None:
        """Insert a run (typically at its start, status "running"); update_run fills in the rest."""
        with self._db:
            self._db.execute(
                "INSERT INTO runs (run_id, started_at, finished_at, status, robot_name, plan_sha256, operator, "
                "out_dir, estimator, verify_before_json, verify_after_json) VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                (run_id, started_at, finished_at, status, robot_name, plan_sha256, operator,
                 None if out_dir is None else str(out_dir), estimator,
                 None if verify_before is None else _dumps(verify_before),
                 None if verify_after is None else _dumps(verify_after)),
            )

    def update_run(self, run_id: str, **fields: Any) -> None:
        """Set columns of a run: any of RUN_FIELDS; verify_before/verify_after are dicts (stored as JSON)."""
        unknown = set(fields) - set(RUN_FIELDS)
        if unknown:
            raise RecordsError(f"unknown run fields {sorted(unknown)}; known: {', '.join(RUN_FIELDS)}")
        if not fields:
            return
        columns, values = [], []
        for key, value in fields.items():
            if key in ("verify_before", "verify_after"):
                columns.append(f"{key}_json")
                values.append(None if value is None else _dumps(value))
            else:
                columns.append(key)
                values.append(None if value is None else str(value))
        with self._db:
            cursor = self._db.execute(
                f"UPDATE runs SET {', '.join(f'{c} = ?' for c in columns)} WHERE run_id = ?", (*values, run_id)
            )
        if cursor.rowcount == 0:
            raise RecordsError(f"no run {run_id!r} in {self.path}")

    def add_parameter_set(self, params_json: Mapping[str, Any], source: Source) -> str:
        """Store a parameter set once (keyed by its SHA-256, see parameter_set_sha256); return the hash."""
        if source not in ("identified", "controller", "file"):
            raise RecordsError(f"unknown parameter-set source {source!r}: identified, controller or file")
        sha = parameter_set_sha256(params_json)
        with self._db:
            self._db.execute(
                "INSERT OR IGNORE INTO parameter_sets (sha256, created_at, source, json) VALUES (?,?,?,?)",
                (sha, now_iso(), source, _dumps(dict(params_json))),
            )
        return sha

    def record_upload(
        self, record: Mapping[str, Any] | UploadRecord, operator: str | None, run_id: str | None = None
    ) -> int:
        """Store one UploadRecord (any outcome); returns the row id."""
        data = record.model_dump() if isinstance(record, UploadRecord) else dict(record)
        if "outcome" not in data:
            raise RecordsError("an upload record needs an 'outcome'")
        with self._db:
            cursor = self._db.execute(
                "INSERT INTO uploads (run_id, time, operator, endpoint, params_sha256, outcome, record_json) "
                "VALUES (?,?,?,?,?,?,?)",
                (run_id, data.get("finished_at") or data.get("started_at") or now_iso(), operator,
                 data.get("endpoint"), data.get("params_sha256"), data["outcome"], _dumps(data)),
            )
        return int(cursor.lastrowid or 0)

    # ------------------------------------------------------------------ reads

    @staticmethod
    def _upload_row(row: sqlite3.Row) -> dict[str, Any]:
        out = {k: row[k] for k in ("id", "run_id", "time", "operator", "endpoint", "params_sha256", "outcome")}
        out["record"] = json.loads(row["record_json"])
        return out

    def _run_row(self, row: sqlite3.Row) -> dict[str, Any]:
        out = {k: row[k] for k in ("run_id", "started_at", "finished_at", "status", "robot_name", "plan_sha256",
                                   "operator", "out_dir", "estimator")}
        for key in ("verify_before", "verify_after"):
            text = row[f"{key}_json"]
            out[key] = None if text is None else json.loads(text)
        out["uploads"] = [self._upload_row(u) for u in self._db.execute(
            "SELECT * FROM uploads WHERE run_id = ? ORDER BY time, id", (row["run_id"],))]
        return out

    def run(self, run_id: str) -> dict[str, Any] | None:
        row = self._db.execute("SELECT * FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        return None if row is None else self._run_row(row)

    def parameter_set(self, sha256: str) -> dict[str, Any] | None:
        row = self._db.execute("SELECT * FROM parameter_sets WHERE sha256 = ?", (sha256,)).fetchone()
        if row is None:
            return None
        return {"sha256": row["sha256"], "created_at": row["created_at"], "source": row["source"],
                "params": json.loads(row["json"])}

    def history(self, limit: int = 20, *, include_standalone: bool = True) -> list[dict[str, Any]]:
        """The newest `limit` entries, newest first: runs (kind "run", with their uploads, oldest first) and,
        unless include_standalone is False, uploads/rollbacks made outside a run (kind "upload")."""
        runs = [dict(self._run_row(r), kind="run", time=r["started_at"]) for r in self._db.execute(
            "SELECT * FROM runs ORDER BY started_at DESC, rowid DESC LIMIT ?", (limit,))]
        loose: list[dict[str, Any]] = []
        if include_standalone:
            loose = [dict(self._upload_row(u), kind="upload") for u in self._db.execute(
                "SELECT * FROM uploads WHERE run_id IS NULL ORDER BY time DESC, id DESC LIMIT ?", (limit,))]
        merged = sorted(runs + loose, key=lambda e: _sort_key(e["time"]), reverse=True)
        return merged[:limit]

    def last_upload(self, endpoint: str | None = None, *, outcome: str | None = None) -> dict[str, Any] | None:
        """The most recent upload/rollback/save record, optionally for one endpoint and/or one outcome."""
        sql, args = "SELECT * FROM uploads WHERE 1=1", []
        if endpoint is not None:
            sql += " AND endpoint = ?"
            args.append(endpoint)
        if outcome is not None:
            sql += " AND outcome = ?"
            args.append(outcome)
        row = self._db.execute(sql + " ORDER BY time DESC, id DESC LIMIT 1", args).fetchone()
        return None if row is None else self._upload_row(row)


def _sort_key(timestamp: str | None) -> datetime:
    """Timestamps as aware datetimes (naive ones taken as UTC); unparsable ones sort oldest."""
    try:
        t = datetime.fromisoformat(timestamp or "")
    except ValueError:
        return datetime.min.replace(tzinfo=UTC)
    return t if t.tzinfo else t.replace(tzinfo=UTC)


# ------------------------------------------------------------------ operator helpers


def _parameter_names() -> list[str]:
    names = [f"leg{i}_a_{ax}_mm" for i in range(1, 7) for ax in "xyz"]
    names += [f"leg{i}_b_{ax}_mm" for i in range(1, 7) for ax in "xyz"]
    return names + [f"leg{i}_l0_mm" for i in range(1, 7)]


PARAMETER_NAMES = tuple(_parameter_names())


def read_parameter_file(path: Path | str) -> ParameterSet:
    """A parameter JSON file {a_mm: 6x3, b_mm: 6x3, l0_mm: 6}; ParameterFileError with every problem named."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ParameterFileError(f"{path}: cannot read: {err.strerror or err}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ParameterFileError(f"{path}: not JSON: {err.msg} at line {err.lineno} column {err.colno}") from None
    if not isinstance(data, dict):
        raise ParameterFileError(f"{path}: expected a JSON object with keys a_mm, b_mm, l0_mm")
    try:
        return ParameterSet.model_validate(data)
    except ValidationError as err:
        problems = "; ".join(f"{_location(e['loc'])}: {e['msg']}" for e in err.errors())
        raise ParameterFileError(f"{path}: not a valid parameter set (indices from 0): {problems}") from None


def _location(loc: tuple[int | str, ...]) -> str:
    """A pydantic error location as JSON-path-like text: a_mm[2][1]."""
    if not loc:
        return "(top level)"
    return str(loc[0]) + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc[1:])


def parameter_diff(live: ParameterSet, new: ParameterSet) -> list[dict[str, Any]]:
    """Parameters whose float32 value changes: name, live_mm, new_mm, delta_mm (register order)."""
    old_v, new_v = live.as_float32().to_vector(), new.as_float32().to_vector()
    return [
        {"name": name, "live_mm": float(a), "new_mm": float(b), "delta_mm": float(b - a)}
        for name, a, b in zip(PARAMETER_NAMES, old_v, new_v, strict=True) if a != b
    ]


def format_diff(diff: list[dict[str, Any]]) -> str:
    """The diff as a plain table (mm)."""
    if not diff:
        return "the live set already equals the new set"
    lines = [f"{'parameter':<14} {'live (mm)':>12} {'new (mm)':>12} {'change (mm)':>12}"]
    lines += [f"{d['name']:<14} {d['live_mm']:12.4f} {d['new_mm']:12.4f} {d['delta_mm']:+12.4f}" for d in diff]
    return "\n".join(lines)


def _local_record(
    params_client: ControllerParams,
    outcome: Literal["refused", "failed"],
    error: str,
    params_sha256: str | None = None,
    operation: Literal["upload", "rollback", "save"] = "upload",
) -> UploadRecord:
    """An UploadRecord for an attempt that ended before (or outside) the driver's own transaction record."""
    t = now_iso()
    return UploadRecord(operation=operation, endpoint=params_client.endpoint, device_id=params_client.device_id,
                        started_at=t, finished_at=t, outcome=outcome, error=error, params_sha256=params_sha256)


def upload_parameter_file(
    params_client: ControllerParams,
    path_json: Path | str,
    records: Records,
    operator: str,
    save: bool,
    yes: bool,
    confirm: Callable[[str], bool],
) -> dict[str, Any]:
    """Upload a parameter file to the controller after showing the diff to the live set and asking.

    Returns {"record": UploadRecord dump or None, "diff": [...], "changed": bool, "file_sha256": str}. An
    unchanged set is not re-uploaded (that would overwrite the rollback backup with the same set); with
    save=True the live set is then only saved. Every attempt is recorded in `records`, refused and failed
    ones too; those raise: ParameterFileError (bad file), UploadDeclined (operator said no) or the driver's
    ParamsError (``err.record`` holds the UploadRecord).
    """
    try:
        new = read_parameter_file(path_json)
    except ParameterFileError as err:
        err.record = _local_record(params_client, "refused", f"ParameterFileError: {err}")
        records.record_upload(err.record, operator)
        raise
    sha = records.add_parameter_set(new.model_dump(), "file")
    try:
        live = params_client.read_live()
    except ParamsError as err:
        err.record = err.record or _local_record(params_client, "failed", f"{type(err).__name__}: {err}", sha)
        records.record_upload(err.record, operator)
        raise
    records.add_parameter_set(live.model_dump(), "controller")
    diff = parameter_diff(live, new)
    result: dict[str, Any] = {"record": None, "diff": diff, "changed": bool(diff), "file_sha256": sha}
    if not diff and not save:
        return result
    action = (f"upload {len(diff)} changed parameters" if diff else "save the live set (unchanged)") + (
        " and save them to non-volatile memory" if diff and save else "")
    prompt = f"{format_diff(diff)}\n\n{action} on {params_client.endpoint}?"
    if not yes and not confirm(prompt):
        declined = UploadDeclined(f"{action} on {params_client.endpoint}: declined by the operator; nothing written")
        declined.record = _local_record(params_client, "refused", f"UploadDeclined: {declined}", sha)
        records.record_upload(declined.record, operator)
        raise declined
    try:
        record = params_client.upload(new, save=save) if diff else params_client.save()
    except ParamsError as err:
        err.record = err.record or _local_record(params_client, "failed", f"{type(err).__name__}: {err}", sha)
        records.record_upload(err.record, operator)
        raise
    records.record_upload(record, operator)
    result["record"] = record.model_dump()
    return result


def rollback_controller(params_client: ControllerParams, records: Records, operator: str) -> dict[str, Any]:
    """Swap the controller's live and backup sets (undo the last commit); recorded whatever the outcome.

    Returns the UploadRecord dump; the driver's ParamsError (with ``err.record``) on refusal or failure.
    """
    try:
        record = params_client.rollback()
    except ParamsError as err:
        err.record = err.record or _local_record(params_client, "failed", f"{type(err).__name__}: {err}",
                                                 operation="rollback")
        records.record_upload(err.record, operator)
        raise
    records.record_upload(record, operator)
    return record.model_dump()


def _brief(verify: Mapping[str, Any] | None) -> str:
    if not verify or verify.get("max_position_mm") is None:
        return "-"
    return f"{verify['max_position_mm']:.4f}"


def format_history(rows: list[dict[str, Any]]) -> str:
    """history() as a plain-text table: one line per run (uploads indented beneath) or standalone upload."""
    if not rows:
        return "no runs or uploads recorded"
    header = (f"{'time (UTC)':<26} {'run / operation':<24} {'status':<10} {'robot':<14} {'est':<5} "
              f"{'operator':<10} {'max pos before mm':>17} {'max pos after mm':>16}")
    lines = [header, "-" * len(header)]

    def upload_line(u: Mapping[str, Any], indent: str) -> str:
        rec = u.get("record") or {}
        sha = (u.get("params_sha256") or "")[:12]
        what = f"{indent}{rec.get('operation', 'upload')}"
        error = f"  {rec['error']}" if rec.get("error") else ""
        return (f"{(u.get('time') or '')[:26]:<26} {what:<24} {u.get('outcome') or '':<10} "
                f"{u.get('endpoint') or '':<30} {u.get('operator') or '':<10} sha256 {sha}{error}")

    for row in rows:
        if row.get("kind") == "upload":
            lines.append(upload_line(row, ""))
            continue
        lines.append(
            f"{(row.get('started_at') or '')[:26]:<26} {row['run_id'][:24]:<24} {row.get('status') or '':<10} "
            f"{(row.get('robot_name') or '')[:14]:<14} {row.get('estimator') or '':<5} "
            f"{(row.get('operator') or '')[:10]:<10} {_brief(row.get('verify_before')):>17} "
            f"{_brief(row.get('verify_after')):>16}"
        )
        lines += [upload_line(u, "  ") for u in row.get("uploads", [])]
    return "\n".join(lines)
