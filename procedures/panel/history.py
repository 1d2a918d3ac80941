"""Past runs for the panel: the records database (runs, uploads, each machine's drift with trend plots), each run's
report files, and a diagnosis on demand.

Read-only towards the records and the run folders, except that a diagnosis writes its own report into
``RUN/diagnosis/``. Files are served only by fixed names from folders the records (or the live run) name,
never from a path a browser sends.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from pathlib import Path
from typing import Any

import structlog

log = structlog.get_logger(__name__)

RUN_FILES = {"report.html": "text/html", "report.json": "application/json", "recording.csv": "text/csv",
             "plan.json": "application/json", "reference_plan.json": "application/json",
             "diagnosis/index.html": "text/html",
             "diagnosis/diagnosis.json": "application/json", "certificate.html": "text/html",
             "certificate.pdf": "application/pdf"}


def _open(records: str | Path | None) -> Any:
    """The records, or None when there are none yet (a SQLite file not yet written); raises RecordsUnavailable."""
    from procedures.records import Records, records_url

    if records is None:
        return None
    url = records_url(records)
    if url.get_backend_name() == "sqlite" and not Path(str(url.database)).exists():
        return None
    return Records(url, retries=1, connect_timeout_s=3.0)  # a page waits for this: fail fast, say so


def history(records_path: str | Path | None, limit: int = 50, machine: str | None = None) -> dict[str, Any]:
    """Runs and stand-alone uploads, newest first (of one machine, or all), with the report files each run
    folder holds, and the machines in the records."""
    from procedures.records import RecordsError, RecordsUnavailable, redact

    where = None if records_path is None else redact(str(records_path))
    try:
        db = _open(records_path)
        if db is None:
            return {"records": where, "entries": [], "machines": [], "note": "no records database yet"}
        with db:
            entries = db.history(limit, machine=machine)
            machines = db.machines()
            where = db.where
    except (RecordsUnavailable, RecordsError) as e:
        return {"records": where, "entries": [], "machines": [], "note": f"records unavailable: {e}"}
    for entry in entries:
        if entry.get("kind") == "run":
            folder = Path(entry["out_dir"]) if entry.get("out_dir") else None
            entry["files"] = [name for name in RUN_FILES if folder is not None and (folder / name).is_file()]
    return {"records": where, "machine": machine, "machines": machines, "entries": entries}


def machine_drift(records_path: str | Path | None, machine: str) -> dict[str, Any]:
    """A machine's drift over its calibrations: flags in sentences, per-parameter numbers, trend plots (PNG)."""
    from hilcal.drift import drift
    from hilcal.reports.drift import trend_png

    db = _open(records_path)
    if db is None:
        raise LookupError("no records database yet")
    with db:
        if machine not in {m["machine"] for m in db.machines()}:
            raise LookupError(f"no machine {machine!r} in the records")
        result = drift(db.calibrations(machine), machine).to_json()
    return {**result, "plot_png": trend_png(result)}


def run_folder(records_path: str | Path | None, live_runs: dict[str, Path], run_id: str) -> Path | None:
    """The folder of a run: the live run's, else the one its record names."""
    if run_id in live_runs:
        return live_runs[run_id]
    from procedures.records import RecordsError, RecordsUnavailable

    try:
        db = _open(records_path)
        if db is None:
            return None
        with db:
            row = db.run(run_id)
    except (RecordsUnavailable, RecordsError):
        return None
    return None if row is None or not row.get("out_dir") else Path(row["out_dir"])


def journal_options(folder: Path) -> dict[str, Any]:
    """The run's options from its journal, read-only (robot path, estimator, ...)."""
    db = sqlite3.connect(f"file:{folder / 'journal.sqlite'}?mode=ro", uri=True, timeout=2.0)
    try:
        row = db.execute("SELECT options_json FROM run").fetchone()
    finally:
        db.close()
    return {} if row is None else json.loads(row[0])


def diagnose_folder(folder: Path) -> dict[str, Any]:
    """Run the missing-physics diagnosis on the run's recording.csv; write RUN/diagnosis/; return its summary."""
    from hilcal.discovery.search import diagnose
    from hilcal.recording import read_recording
    from hilcal.reports.diagnosis import write_report
    from hilcal.robot import load_robot

    robot = load_robot(journal_options(folder).get("robot_path"))
    recording = read_recording(folder / "recording.csv", robot)
    diag = diagnose(recording, robot)
    write_report(diag, folder / "diagnosis")
    summary = diag.to_json()
    return {"effect": summary["effect"], "explanation": summary["explanation"], "before": summary["before"],
            "after": summary["after"], "findings": [f.text for f in diag.findings[:5]],
            "residual_rms_by_axis": diag.residual_rms_by_axis()}


class DiagnosisJobs:
    """One diagnosis at a time in a background thread; its state is the panel's `diagnosis` section."""

    def __init__(self, live: Any) -> None:
        self.live = live
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def start(self, run_id: str, folder: Path) -> None:
        if not (folder / "recording.csv").is_file():
            raise FileNotFoundError(f"run {run_id} has no recording.csv yet (it is written when measuring ends)")
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                raise RuntimeError("a diagnosis is already running")
            self.live.set("diagnosis", {"run_id": run_id, "status": "running"})
            self._thread = threading.Thread(target=self._work, args=(run_id, folder), name="panel-diagnosis",
                                            daemon=True)
            self._thread.start()

    def _work(self, run_id: str, folder: Path) -> None:
        try:
            summary = diagnose_folder(folder)
        except Exception as e:
            log.warning("panel_diagnosis_failed", run_id=run_id, error=str(e))
            self.live.set("diagnosis", {"run_id": run_id, "status": "failed", "error": f"{type(e).__name__}: {e}"})
            return
        self.live.set("diagnosis", {"run_id": run_id, "status": "done", **summary,
                                    "report_url": f"/runs/{run_id}/diagnosis/index.html"})
        self.live.note(f"diagnosis of {run_id}: {summary['effect']}")

    def join(self, timeout_s: float) -> None:
        if self._thread is not None:
            self._thread.join(timeout_s)
