"""A run's records go through its local journal first, so a database that goes away never loses them.

The runner stages everything the records should hold (the run's fields, its estimated geometry, its upload) in
the run's journal (step ``records``) and then writes the whole run in one transaction. If the database does not
answer, the run goes on and completes on its journal; ``hilcal records sync FOLDER...`` later writes every staged
run it finds. Writing is idempotent (run id, upload id), so a run written twice is stored once.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from hilcal.drift import Calibration, drift, machine_parameters, reading_scale_parameters
from hilcal.robot import Robot
from procedures.journal import Journal, JournalError
from procedures.records.database import RecordsError, RecordsUnavailable, describe, records_url
from procedures.records.store import Records, machine_identity, now_iso

log = structlog.get_logger(__name__)
RECORDS_STEP = "records"
"""Journal step: {"run": fields, "parameters": {name: [value_mm, std_mm]} or None, "uploads": [...]}."""
SYNCED_STEP = "records_synced"
"""Journal step: the UTC time the staged records were last written, or False while they are pending."""


def staged(journal: Journal) -> dict[str, Any]:
    """The journal's staged records (empty parts if nothing was staged)."""
    payload = journal.step(RECORDS_STEP) or {}
    return {"run": dict(payload.get("run") or {}), "parameters": payload.get("parameters"),
            "uploads": list(payload.get("uploads") or [])}


def stage(journal: Journal, *, run: Mapping[str, Any] | None = None,
          parameters: Mapping[str, tuple[float, float | None]] | None = None,
          upload: Mapping[str, Any] | None = None) -> None:
    """Merge into the staged records: run fields (later values win, the first start time stays), the
    parameters (replaced) and an upload ({upload_id, record, operator}; stored once by upload_id)."""
    payload = staged(journal)
    for key, value in (run or {}).items():
        if key == "started_at" and payload["run"].get("started_at"):
            continue
        payload["run"][key] = value
    if parameters is not None:
        payload["parameters"] = {k: [v, s] for k, (v, s) in parameters.items()}
    if upload is not None and all(u["upload_id"] != upload["upload_id"] for u in payload["uploads"]):
        payload["uploads"].append(dict(upload))
    journal.set_step(RECORDS_STEP, payload)
    journal.set_step(SYNCED_STEP, False)


def write_staged(records: Records, journal: Journal) -> bool:
    """Write the journal's staged run in one transaction; False if nothing is staged. RecordsUnavailable
    if the database does not answer (the journal keeps everything)."""
    payload = staged(journal)
    run = payload["run"]
    if not run.get("run_id"):
        return False
    parameters = None if payload["parameters"] is None else {k: (v, s) for k, (v, s) in payload["parameters"].items()}
    records.save_run(run["run_id"], {k: v for k, v in run.items() if k != "run_id"}, parameters, payload["uploads"])
    journal.set_step(SYNCED_STEP, now_iso())
    return True


@dataclass
class RunRecorder:
    """The runner's records: the database is checked at the start (a run does not start without it), then every
    write is staged in the journal first, and a database lost mid-run only delays the records."""

    target: str | Path | None
    machine: str = ""
    """The machine's identity (set by the runner once the robot is known)."""
    records: Records | None = None
    pending: str | None = None
    """Why the records are not written yet (None: all written)."""

    def open(self) -> None:
        """Open (and migrate) the records; RecordsUnavailable or RecordsError refuse the run."""
        self.records = Records(self.target, retries=1, connect_timeout_s=3.0)

    def close(self) -> None:
        if self.records is not None:
            self.records.close()

    def write(self, journal: Journal, **parts: Any) -> None:
        """Stage parts (see ``stage``) and try to write the run; a lost database is noted, never raised."""
        stage(journal, **parts)
        if self.records is None:
            return
        try:
            write_staged(self.records, journal)
            self.pending = None
        except RecordsUnavailable as err:
            self.pending = str(err)
            log.warning("records_pending", error=str(err))

    def drift_since(self, run_id: str, started_at: str,
                    parameters: Mapping[str, tuple[float, float | None]]) -> dict[str, Any] | None:
        """This run's drift against the machine's earlier calibrations (None when the records do not answer)."""
        if self.records is None:
            return None
        try:
            earlier = self.records.calibrations(self.machine, before=started_at)
        except RecordsUnavailable as err:
            self.pending = str(err)
            return {"machine": self.machine, "error": f"drift not computed: {err}"}
        current = Calibration(run_id, started_at, {k: v for k, (v, _) in parameters.items()},
                              {k: s for k, (_, s) in parameters.items()})
        return drift([*earlier, current], self.machine).to_json()

    def message(self, out_dir: Path) -> str | None:
        """What the operator must do when records are pending."""
        if self.pending is None:
            return None
        where = "" if self.records is None else f" --records {self.records.where}"
        return (f"records not written ({self.pending}); the run's journal keeps them: write them when the database "
                f"is back with `hilcal records sync {out_dir}{where}`")


@dataclass
class SyncReport:
    written: list[str] = field(default_factory=list)
    nothing_staged: list[Path] = field(default_factory=list)
    failed: list[tuple[Path, str]] = field(default_factory=list)


def journals(folders: Iterable[Path]) -> list[Path]:
    """Every run journal in or under the folders (a folder may itself be a run folder)."""
    found: set[Path] = set()
    for folder in folders:
        if folder.is_file() and folder.name == "journal.sqlite":
            found.add(folder.resolve())
        elif folder.is_dir():
            found.update(p.resolve() for p in folder.rglob("journal.sqlite"))
    return sorted(found)


def sync_folders(records: Records, folders: Iterable[Path], say: Callable[[str], None] = print) -> SyncReport:
    """Write every run staged in the journals under `folders` (idempotent: already written runs are rewritten
    to the same rows). Stops at the first RecordsUnavailable: the rest stays staged."""
    report = SyncReport()
    for path in journals(folders):
        try:
            with Journal(path) as journal:
                run_id = staged(journal)["run"].get("run_id")
                if not write_staged(records, journal):
                    report.nothing_staged.append(path)
                    continue
        except (JournalError, RecordsError, OSError) as err:
            report.failed.append((path, str(err)))
            say(f"{path}: not written: {err}")
            continue
        report.written.append(str(run_id))
        say(f"{run_id}: written ({path.parent})")
    return report


def run_fields(run_id: str, started_at: str, robot_name: str, plan_sha256: str, operator: str | None,
               out_dir: Path, estimator: str, serial: str | None, station: str | None) -> dict[str, Any]:
    """The fields a run is recorded with at its start."""
    return {"run_id": run_id, "started_at": started_at, "status": "running", "robot_name": robot_name,
            "plan_sha256": plan_sha256, "operator": operator, "out_dir": str(out_dir), "estimator": estimator,
            "machine": machine_identity(robot_name, serial), "machine_serial": serial, "station": station}


def finished_now() -> str:
    return dt.datetime.now(dt.UTC).isoformat()


def where(target: str | Path | None) -> str:
    """The records target as the operator should read it (path or redacted URL)."""
    return describe(records_url(target))


def calibration_parameters(result: Any, robot: Robot) -> dict[str, tuple[float, float | None]] | None:
    """The machine's estimated geometry from a run's ProcedureResult (None before identification): the geometry fitted
    together with the effects when the run's physics step found any, and each leg's transducer scale error when it
    was estimated (``hilcal.drift.reading_scale_parameters``)."""
    if not result.outcomes or result.before_params is None:
        return None
    ident = result.outcomes[result.chosen].identification
    if ident.model != "42":
        return None
    physics = getattr(result, "physics", None)
    diag = None if physics is None else physics.diagnosis
    if diag is not None and physics.geometry_source != "the geometric fit":
        ident = dataclasses.replace(diag.final_fit, x=np.concatenate([physics.geometry_x, diag.final_fit.x[42:]]))
    out = machine_parameters(robot, ident, result.before_params.l0_mm)
    scale = [] if diag is None else [f"leg{i}_sensor_scale_ppm" for i in range(1, 7)]
    if scale and all(name in diag.std_errors for name in scale) and physics.loadable is not None:
        lo, hi = robot.leg_limits
        reads_long = -physics.loadable.block.scale_ppm  # the machine's transducers, whatever the block corrects
        out.update(reading_scale_parameters(reads_long, [diag.std_errors[n] for n in scale], hi - lo))
    return out
