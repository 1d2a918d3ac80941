"""The calibration records: runs (with the machine's identity and estimated geometry), parameter sets, every
controller upload (refused and failed ones too) and the audit trail, in SQLite or PostgreSQL.

Every write is one transaction: a run with its parameters and uploads is stored whole or not at all, and an upload
with its audit row. Writes are idempotent (a run by its id, an upload by its ``upload_id``), so a write retried
after a dropped connection, or repeated by ``hilcal records sync``, stores each record once. A database that does
not answer raises ``RecordsUnavailable`` after a few bounded retries; bad requests raise ``RecordsError``.
"""

from __future__ import annotations

import hashlib
import json
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal, TypeVar

import sqlalchemy as sa
import structlog
from pydantic import ValidationError
from sqlalchemy.engine import Connection
from sqlalchemy.exc import DBAPIError, IntegrityError

from drivers.controller.modbus import ParameterSet, ParameterValidationError, UploadRecord
from hilcal.drift import Calibration
from procedures.records.database import (
    WRITE,
    RecordsError,
    RecordsUnavailable,
    describe,
    is_unavailable,
    make_engine,
    records_url,
)
from procedures.records.migrate import upgrade
from procedures.records.schema import RUN_COLUMNS, audit, parameter_sets, run_parameters, runs, uploads

log = structlog.get_logger(__name__)
T = TypeVar("T")
Source = Literal["identified", "controller", "file"]
PARAMETER_KEYS = frozenset({"a_mm", "b_mm", "l0_mm"})
RUN_FIELDS = (*RUN_COLUMNS, "verify_before", "verify_after")
CALIBRATED = ("complete",)
"""Run statuses whose parameters count as a calibration of the machine (drift)."""


def now_iso() -> str:
    """UTC timestamp in the format of the driver's records (ISO 8601, microseconds, +00:00)."""
    return datetime.now(UTC).isoformat(timespec="microseconds")


def _dumps(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def machine_identity(robot_name: str | None, serial: str | None) -> str | None:
    """The machine's identity in the records: the robot file's name and the station's serial, "NAME/SERIAL"."""
    if robot_name is None:
        return None
    return robot_name if not serial else f"{robot_name}/{serial}"


def parameter_set_sha256(params_json: Mapping[str, Any]) -> str:
    """The controller's hash (SHA-256 of the float32 registers) for an {a_mm, b_mm, l0_mm} set, so it matches
    UploadRecord.params_sha256; SHA-256 of the canonical JSON for any other parameter dict."""
    if set(params_json) == PARAMETER_KEYS:
        try:
            return ParameterSet.model_validate(dict(params_json)).sha256()
        except ValidationError as err:
            raise ParameterValidationError(f"invalid parameter set: {err}") from None
    return hashlib.sha256(_dumps(dict(params_json)).encode()).hexdigest()


def _run_values(fields: Mapping[str, Any]) -> dict[str, Any]:
    unknown = set(fields) - set(RUN_FIELDS)
    if unknown:
        raise RecordsError(f"unknown run fields {sorted(unknown)}; known: {', '.join(RUN_FIELDS)}")
    values: dict[str, Any] = {}
    for key, value in fields.items():
        if key in ("verify_before", "verify_after"):
            values[f"{key}_json"] = None if value is None else _dumps(value)
        else:
            values[key] = None if value is None else str(value)
    return values


def _upload_values(record: Mapping[str, Any] | UploadRecord, operator: str | None, run_id: str | None,
                   upload_id: str | None, machine: str | None, station: str | None) -> dict[str, Any]:
    data = record.model_dump() if isinstance(record, UploadRecord) else dict(record)
    if "outcome" not in data:
        raise RecordsError("an upload record needs an 'outcome'")
    return {"upload_id": upload_id or f"upload-{uuid.uuid4().hex}", "run_id": run_id,
            "time": data.get("finished_at") or data.get("started_at") or now_iso(), "operator": operator,
            "endpoint": data.get("endpoint"), "params_sha256": data.get("params_sha256"),
            "outcome": data["outcome"], "record_json": _dumps(data), "machine": machine, "station": station}


class Records:
    """The records database (a SQLite path or a database URL; None: $HILCAL_RECORDS or the default file).

    Opening it migrates it in place if needed. Use as a context manager; every method is its own transaction.
    """

    def __init__(self, target: str | Path | None = None, *, retries: int = 3, connect_timeout_s: float = 5.0
                 ) -> None:
        self.url = records_url(target)
        self.where = describe(self.url)
        self.path = Path(str(self.url.database)) if self.url.get_backend_name() == "sqlite" else None
        self.retries = retries
        self.engine = make_engine(self.url, connect_timeout_s)
        try:
            self.migration = self._retry("opening the records", lambda: upgrade(self.engine))
        except BaseException:
            self.engine.dispose()
            raise

    @property
    def dialect(self) -> str:
        return self.engine.dialect.name

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> Records:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ transactions

    def _retry(self, what: str, attempt: Callable[[], T]) -> T:
        """Run `attempt`, retrying (bounded, with back-off) while the database is unreachable."""
        delay_s, last = 0.2, None
        for n in range(self.retries + 1):
            try:
                return attempt()
            except DBAPIError as err:
                if isinstance(err, IntegrityError) or not is_unavailable(err):
                    raise
                last = err
                log.warning("records_unavailable", where=self.where, what=what, attempt=n + 1, error=str(err.orig))
                if n < self.retries:
                    time.sleep(delay_s)
                    delay_s *= 2.5
        raise RecordsUnavailable(f"the records database {self.where} is unavailable ({what}): "
                                 f"{str(getattr(last, 'orig', last)).strip()}")

    def _write(self, what: str, work: Callable[[Connection], T]) -> T:
        def attempt() -> T:
            with self.engine.connect().execution_options(**WRITE) as conn, conn.begin():
                return work(conn)

        try:
            return self._retry(what, attempt)
        except IntegrityError as err:
            raise RecordsError(f"{what}: refused by the database: {str(err.orig).strip()}") from None

    def _read(self, what: str, work: Callable[[Connection], T]) -> T:
        def attempt() -> T:
            with self.engine.connect() as conn:
                return work(conn)

        return self._retry(what, attempt)

    def _insert(self, table: sa.Table) -> Any:
        if self.dialect == "postgresql":
            from sqlalchemy.dialects.postgresql import insert
        else:
            from sqlalchemy.dialects.sqlite import insert
        return insert(table)

    # ------------------------------------------------------------------ writes

    def record_run(self, run_id: str, *, started_at: str, status: str, out_dir: Path | str | None = None,
                   **fields: Any) -> None:
        """Insert a run (typically at its start, status "running"); update_run fills in the rest.

        Fields: see RUN_FIELDS. Recording the same run again with the same start time is a no-op (a retried
        write); a different run under an existing id is a RecordsError.
        """
        if fields.get("machine") is None and fields.get("robot_name") is not None:
            fields["machine"] = machine_identity(fields["robot_name"], fields.get("machine_serial"))
        values = {"run_id": run_id, **_run_values({"started_at": started_at, "status": status,
                                                   "out_dir": out_dir, **fields})}

        def work(conn: Connection) -> None:
            inserted = conn.execute(self._insert(runs).values(**values).on_conflict_do_nothing(
                index_elements=["run_id"]).returning(runs.c.run_id)).first() is not None
            if not inserted:
                existing = conn.execute(sa.select(runs.c.started_at).where(runs.c.run_id == run_id)).scalar()
                if existing != started_at:
                    raise RecordsError(f"run {run_id} is already recorded (started {existing})")
            if inserted:
                self._audit(conn, "run_recorded", run_id, fields.get("operator"), fields.get("station"),
                            values.get("machine"), {"status": status})

        self._write(f"recording run {run_id}", work)

    def update_run(self, run_id: str, **fields: Any) -> None:
        """Set columns of a run: any of RUN_FIELDS; verify_before/verify_after are dicts (stored as JSON)."""
        values = _run_values(fields)
        if not values:
            return

        def work(conn: Connection) -> None:
            if conn.execute(runs.update().where(runs.c.run_id == run_id).values(**values)).rowcount == 0:
                raise RecordsError(f"no run {run_id!r} in {self.where}")

        self._write(f"updating run {run_id}", work)

    def save_run(self, run_id: str, run: Mapping[str, Any], parameters: Mapping[str, tuple[float, float | None]]
                 | None = None, run_uploads: Iterable[Mapping[str, Any]] = ()) -> None:
        """Store a whole run in one transaction: its fields (inserted or updated), its parameters (replaced) and
        its uploads (each {record, operator, upload_id}; stored once by upload_id). Idempotent."""
        values = _run_values(run)
        if "started_at" not in values or "status" not in values:
            raise RecordsError(f"run {run_id}: save_run needs started_at and status")
        if values.get("machine") is None and values.get("robot_name") is not None:
            values["machine"] = machine_identity(values["robot_name"], values.get("machine_serial"))
        rows = [_upload_values(u["record"], u.get("operator"), run_id, u["upload_id"], values.get("machine"),
                               values.get("station")) for u in run_uploads]

        def work(conn: Connection) -> None:
            update = {k: v for k, v in values.items() if k != "started_at"}
            conn.execute(self._insert(runs).values(run_id=run_id, **values).on_conflict_do_update(
                index_elements=["run_id"], set_=update))
            if parameters is not None:
                self._replace_parameters(conn, run_id, parameters)
            for row in rows:
                self._insert_upload(conn, row)

        self._write(f"saving run {run_id}", work)

    def record_parameters(self, run_id: str, parameters: Mapping[str, tuple[float, float | None]]) -> None:
        """Replace a run's estimated geometry: name -> (value mm, standard error mm or None)."""
        self._write(f"recording the parameters of run {run_id}",
                    lambda conn: self._replace_parameters(conn, run_id, parameters))

    def _replace_parameters(self, conn: Connection, run_id: str,
                            parameters: Mapping[str, tuple[float, float | None]]) -> None:
        conn.execute(run_parameters.delete().where(run_parameters.c.run_id == run_id))
        if parameters:
            conn.execute(run_parameters.insert(), [
                {"run_id": run_id, "name": name, "value_mm": float(value),
                 "std_mm": None if std is None else float(std)} for name, (value, std) in parameters.items()])

    def add_parameter_set(self, params_json: Mapping[str, Any], source: Source) -> str:
        """Store a parameter set once (keyed by its SHA-256, see parameter_set_sha256); return the hash."""
        if source not in ("identified", "controller", "file"):
            raise RecordsError(f"unknown parameter-set source {source!r}: identified, controller or file")
        sha = parameter_set_sha256(params_json)
        statement = self._insert(parameter_sets).values(
            sha256=sha, created_at=now_iso(), source=source, json=_dumps(dict(params_json))
        ).on_conflict_do_nothing(index_elements=["sha256"])
        self._write("storing a parameter set", lambda conn: conn.execute(statement))
        return sha

    def record_upload(self, record: Mapping[str, Any] | UploadRecord, operator: str | None,
                      run_id: str | None = None, *, upload_id: str | None = None, machine: str | None = None,
                      station: str | None = None) -> int:
        """Store one UploadRecord (any outcome) with its audit row, in one transaction; returns the row id.

        The same upload_id twice stores it once (the second call returns the first row's id).
        """
        row = _upload_values(record, operator, run_id, upload_id, machine, station)

        def work(conn: Connection) -> int:
            if row["machine"] is None and run_id is not None:
                row["machine"] = conn.execute(sa.select(runs.c.machine).where(runs.c.run_id == run_id)).scalar()
            return self._insert_upload(conn, row)

        return self._write("recording an upload", work)

    def _insert_upload(self, conn: Connection, row: dict[str, Any]) -> int:
        if row["run_id"] is not None and conn.execute(
                sa.select(runs.c.run_id).where(runs.c.run_id == row["run_id"])).first() is None:
            raise RecordsError(f"an upload names run {row['run_id']!r}, which is not recorded")
        result = conn.execute(self._insert(uploads).values(**row).on_conflict_do_nothing(
            index_elements=["upload_id"]).returning(uploads.c.id))
        new_id = result.scalar()
        if new_id is None:
            return int(conn.execute(sa.select(uploads.c.id).where(uploads.c.upload_id == row["upload_id"])).scalar())
        data = json.loads(row["record_json"])
        self._audit(conn, data.get("operation", "upload"), row["upload_id"], row["operator"], row["station"],
                    row["machine"], {"outcome": row["outcome"], "run_id": row["run_id"], "endpoint": row["endpoint"],
                                     "params_sha256": row["params_sha256"]})
        return int(new_id)

    @staticmethod
    def _audit(conn: Connection, action: str, subject: str, operator: str | None, station: str | None,
               machine: str | None, detail: Mapping[str, Any]) -> None:
        conn.execute(audit.insert().values(time=now_iso(), action=action, subject=subject, operator=operator,
                                           station=station, machine=machine, detail_json=_dumps(dict(detail))))

    # ------------------------------------------------------------------ reads

    @staticmethod
    def _upload_row(row: Any) -> dict[str, Any]:
        m = row._mapping
        out = {k: m[k] for k in ("id", "upload_id", "run_id", "time", "operator", "endpoint", "params_sha256",
                                 "outcome", "machine", "station")}
        out["record"] = json.loads(m["record_json"])
        return out

    @staticmethod
    def _run_row(row: Any) -> dict[str, Any]:
        m = row._mapping
        out = {k: m[k] for k in ("run_id", *RUN_COLUMNS)}
        for key in ("verify_before", "verify_after"):
            text = m[f"{key}_json"]
            out[key] = None if text is None else json.loads(text)
        out["uploads"] = []
        return out

    def _with_uploads(self, conn: Connection, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
        by_id = {r["run_id"]: r for r in rows}
        if by_id:
            for u in conn.execute(sa.select(uploads).where(uploads.c.run_id.in_(list(by_id)))
                                  .order_by(uploads.c.time, uploads.c.id)):
                by_id[u.run_id]["uploads"].append(self._upload_row(u))
        return rows

    def run(self, run_id: str) -> dict[str, Any] | None:
        def work(conn: Connection) -> dict[str, Any] | None:
            row = conn.execute(sa.select(runs).where(runs.c.run_id == run_id)).first()
            return None if row is None else self._with_uploads(conn, [self._run_row(row)])[0]

        return self._read(f"reading run {run_id}", work)

    def run_parameters(self, run_id: str) -> dict[str, tuple[float, float | None]]:
        """A run's estimated geometry: name -> (value mm, standard error mm or None)."""
        def work(conn: Connection) -> dict[str, tuple[float, float | None]]:
            rows = conn.execute(sa.select(run_parameters).where(run_parameters.c.run_id == run_id)
                                .order_by(run_parameters.c.name))
            return {r.name: (r.value_mm, r.std_mm) for r in rows}

        return self._read(f"reading the parameters of run {run_id}", work)

    def parameter_set(self, sha256: str) -> dict[str, Any] | None:
        def work(conn: Connection) -> dict[str, Any] | None:
            row = conn.execute(sa.select(parameter_sets).where(parameter_sets.c.sha256 == sha256)).first()
            return None if row is None else {"sha256": row.sha256, "created_at": row.created_at,
                                             "source": row.source, "params": json.loads(row.json)}

        return self._read("reading a parameter set", work)

    def history(self, limit: int = 20, *, include_standalone: bool = True, machine: str | None = None
                ) -> list[dict[str, Any]]:
        """The newest `limit` entries, newest first: runs (kind "run", with their uploads, oldest first) and,
        unless include_standalone is False, uploads/rollbacks made outside a run (kind "upload"); optionally of
        one machine only."""
        def work(conn: Connection) -> list[dict[str, Any]]:
            query = sa.select(runs).order_by(runs.c.started_at.desc(), runs.c.run_id.desc()).limit(limit)
            if machine is not None:
                query = query.where(runs.c.machine == machine)
            found = self._with_uploads(conn, [self._run_row(r) for r in conn.execute(query)])
            entries = [dict(r, kind="run", time=r["started_at"]) for r in found]
            if include_standalone:
                loose = sa.select(uploads).where(uploads.c.run_id.is_(None))
                if machine is not None:
                    loose = loose.where(uploads.c.machine == machine)
                entries += [dict(self._upload_row(u), kind="upload") for u in conn.execute(
                    loose.order_by(uploads.c.time.desc(), uploads.c.id.desc()).limit(limit))]
            return sorted(entries, key=lambda e: _sort_key(e["time"]), reverse=True)[:limit]

        return self._read("reading the history", work)

    def last_upload(self, endpoint: str | None = None, *, outcome: str | None = None) -> dict[str, Any] | None:
        """The most recent upload/rollback/save record, optionally for one endpoint and/or one outcome."""
        query = sa.select(uploads)
        if endpoint is not None:
            query = query.where(uploads.c.endpoint == endpoint)
        if outcome is not None:
            query = query.where(uploads.c.outcome == outcome)
        query = query.order_by(uploads.c.time.desc(), uploads.c.id.desc()).limit(1)

        def work(conn: Connection) -> dict[str, Any] | None:
            row = conn.execute(query).first()
            return None if row is None else self._upload_row(row)

        return self._read("reading the last upload", work)

    def machines(self) -> list[dict[str, Any]]:
        """Every machine with runs: its identity, number of runs and the newest run's start."""
        query = (sa.select(runs.c.machine, sa.func.count().label("runs"), sa.func.max(runs.c.started_at)
                           .label("last_run")).where(runs.c.machine.is_not(None)).group_by(runs.c.machine)
                 .order_by(runs.c.machine))
        return self._read("listing the machines", lambda conn: [dict(r._mapping) for r in conn.execute(query)])

    def calibrations(self, machine: str, *, statuses: tuple[str, ...] = CALIBRATED, before: str | None = None
                     ) -> list[Calibration]:
        """The machine's calibrations with stored parameters, oldest first (optionally only those started before
        the ISO time `before`)."""
        query = (sa.select(runs.c.run_id, runs.c.started_at, run_parameters.c.name, run_parameters.c.value_mm,
                           run_parameters.c.std_mm)
                 .join(run_parameters, run_parameters.c.run_id == runs.c.run_id)
                 .where(runs.c.machine == machine, runs.c.status.in_(statuses))
                 .order_by(runs.c.started_at, runs.c.run_id))
        if before is not None:
            query = query.where(runs.c.started_at < before)

        def work(conn: Connection) -> list[Calibration]:
            out: list[Calibration] = []
            current: str | None = None
            for run_id, started_at, name, value, std in conn.execute(query):
                if run_id != current:
                    out.append(Calibration(run_id, started_at, {}, {}))
                    current = run_id
                out[-1].values[name] = value  # type: ignore[index]
                out[-1].std[name] = std  # type: ignore[index]
            return out

        return self._read(f"reading the calibrations of {machine}", work)

    def audit_trail(self, subject: str | None = None) -> list[dict[str, Any]]:
        """Audit rows, oldest first (optionally of one run or upload id)."""
        query = sa.select(audit).order_by(audit.c.id)
        if subject is not None:
            query = query.where(audit.c.subject == subject)
        return self._read("reading the audit trail", lambda conn: [
            dict(r._mapping, detail=json.loads(r.detail_json)) for r in conn.execute(query)])


def _sort_key(timestamp: str | None) -> datetime:
    """Timestamps as aware datetimes (naive ones taken as UTC); unparsable ones sort oldest."""
    try:
        t = datetime.fromisoformat(timestamp or "")
    except ValueError:
        return datetime.min.replace(tzinfo=UTC)
    return t if t.tzinfo else t.replace(tzinfo=UTC)
