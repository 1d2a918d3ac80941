"""The calibration records of one `hilcal run`: where they go, the run recorded at its start, the machine's geometry
staged in the journal with its drift, and the outcome with its uploads (each a record of its own)."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

from hilcal.robot import Robot
from procedures.journal import Journal


def records_target(req: Any) -> str | Path | None:
    """--records, else the station file's records (a real run), else $HILCAL_RECORDS or the default file."""
    from procedures.station import StationConfigError, load_station

    if req.records_path is not None:
        return req.records_path
    if req.station_path is not None and not req.sim:
        try:
            return load_station(req.station_path).records_target()
        except StationConfigError:
            return None  # the run reports the station file's problems itself
    return None


def _station_identity(req: Any, options: dict) -> tuple[str | None, str | None]:
    """The station's name and the machine's serial from the station file, if the run has one (a --sim run's
    station file may hold only these, its [timing] and its sign-off settings: ``procedures.signoff``)."""
    from procedures.signoff import SignoffFileError, load_signoff

    path = req.station_path or options.get("station_path")
    if path is None:
        return None, None
    try:
        settings = load_signoff(path)
    except SignoffFileError:
        return None, None
    return settings.name, settings.machine_serial


def record_start(recorder: Any, journal: Journal, req: Any, run_id: str, started_at: str, robot: Robot,
                  plan: Any, operator: str | None, estimator: str) -> None:
    """Record the run at its start (a resumed run keeps what its first start recorded)."""
    from procedures.records.sync import run_fields, staged

    run = staged(journal)["run"]
    if not run:
        station, serial = _station_identity(req, journal.run_info()["options"])
        run = run_fields(run_id, started_at, robot.name, plan.sha256(), operator, req.out_dir, estimator, serial,
                         station)
    recorder.machine = run["machine"]
    recorder.write(journal, run=run)


def stage_parameters(journal: Journal, run_id: str, result: Any, robot: Robot, started_at: str,
                      recorder: Any) -> dict | None:
    """Stage the machine's estimated geometry in the journal; the drift since its earlier calibrations."""
    from procedures.records.sync import calibration_parameters, stage, staged

    parameters = calibration_parameters(result, robot)
    if parameters is None:
        return None
    stage(journal, parameters=parameters)
    if recorder is None:
        return None
    return recorder.drift_since(run_id, staged(journal)["run"].get("started_at", started_at), parameters)


def record_outcome(recorder: Any, journal: Journal, run_id: str, operator: str | None, result: Any) -> None:
    status = journal.run_info()["status"]
    fields: dict[str, Any] = {"status": status, "finished_at": dt.datetime.now(dt.UTC).isoformat()}
    if result.report_path is not None:
        report = json.loads(result.report_path.read_text())
        fields["verify_before"] = report["verification"]["before"]
        fields["verify_after"] = report["verification"]["after"]
    from procedures.records.sync import stage

    upload = journal.step("upload") or {}
    if upload.get("record"):
        stage(journal, upload={"upload_id": f"{run_id}/upload", "record": upload["record"], "operator": operator})
    saved = None  # the save is a step of its own, with its own record
    if upload.get("save_record"):
        saved = {"upload_id": f"{run_id}/save", "record": upload["save_record"], "operator": operator}
    recorder.write(journal, run=fields, upload=saved)
