"""The operator's parameter helpers behind ``hilcal upload`` and ``hilcal rollback``: read and check a parameter
file, show its diff to the controller's live set, upload or roll back transactionally, and record every attempt
(refused and failed ones too). They take a connected parameter interface (``ParameterInterface`` over Modbus,
``CanopenParams``) and never open a device themselves. A device without a backup bank (CANopen) is rolled back to the
set before its last upload, which that upload's record holds (``last_change``).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import ValidationError

from drivers.controller.base import ParameterInterface
from drivers.controller.parameter_sets import (
    CompensationBlock,
    ParameterSet,
    ParameterValidationError,
    ParamsError,
    UploadRecord,
)
from procedures.records.store import Records, now_iso


class ParameterFileError(ParameterValidationError):
    """A parameter file that cannot be read or is not a sane parameter set; nothing was written."""


class UploadDeclined(ParamsError):
    """The operator did not confirm the upload; nothing was written."""


def _parameter_names() -> list[str]:
    names = [f"leg{i}_a_{ax}_mm" for i in range(1, 7) for ax in "xyz"]
    names += [f"leg{i}_b_{ax}_mm" for i in range(1, 7) for ax in "xyz"]
    return names + [f"leg{i}_l0_mm" for i in range(1, 7)]


PARAMETER_NAMES = tuple(_parameter_names())


def read_parameter_file(path: Path | str) -> ParameterSet:
    """A parameter JSON file {a_mm: 6x3, b_mm: 6x3, l0_mm: 6}; ParameterFileError with every problem named."""
    return read_controller_set(path)[0]


def read_controller_set(path: Path | str) -> tuple[ParameterSet, CompensationBlock | None]:
    """A parameter JSON file {a_mm, b_mm, l0_mm[, compensation: {...}]} (a run's controller_set.json): the geometry
    and, when the file has one, the compensation block (docs/protocols.md); ParameterFileError naming every problem."""
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
    data = dict(data)
    block = data.pop("compensation", None)
    try:
        params = ParameterSet.model_validate(data)
    except ValidationError as err:
        problems = "; ".join(f"{_location(e['loc'])}: {e['msg']}" for e in err.errors())
        raise ParameterFileError(f"{path}: not a valid parameter set (indices from 0): {problems}") from None
    if block is None:
        return params, None
    try:
        return params, CompensationBlock.model_validate(block)
    except ValidationError as err:
        problems = "; ".join(f"compensation.{_location(e['loc'])}: {e['msg']}" for e in err.errors())
        raise ParameterFileError(f"{path}: not a valid compensation block (indices from 0): {problems}") from None


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
    params_client: ParameterInterface,
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
    params_client: ParameterInterface,
    path_json: Path | str,
    records: Records,
    operator: str,
    save: bool,
    yes: bool,
    confirm: Callable[[str], bool],
    *,
    machine: str | None = None,
    station: str | None = None,
) -> dict[str, Any]:
    """Upload a parameter file to the controller after showing the diff to the live set and asking.

    Returns {"record": UploadRecord dump or None, "diff": [...], "changed": bool, "file_sha256": str}. An
    unchanged set is not re-uploaded (that would overwrite the rollback backup with the same set); with
    save=True the live set is then only saved. Every attempt is recorded in `records`, refused and failed
    ones too; those raise: ParameterFileError (bad file), UploadDeclined (operator said no) or the driver's
    ParamsError (``err.record`` holds the UploadRecord). `machine` and `station` are recorded with each attempt.
    """
    try:
        new, block = read_controller_set(path_json)
    except ParameterFileError as err:
        err.record = _local_record(params_client, "refused", f"ParameterFileError: {err}")
        records.record_upload(err.record, operator, machine=machine, station=station)
        raise
    sha = records.add_parameter_set(new.model_dump(), "file")
    try:
        live = params_client.read_live()
        live_block = None if block is None else params_client.read_live_compensation()
    except ParamsError as err:
        err.record = err.record or _local_record(params_client, "failed", f"{type(err).__name__}: {err}", sha)
        records.record_upload(err.record, operator, machine=machine, station=station)
        raise
    records.add_parameter_set(live.model_dump(), "controller")
    diff = parameter_diff(live, new)
    block_changes = block is not None and block.as_float32() != live_block
    result: dict[str, Any] = {"record": None, "diff": diff, "changed": bool(diff) or block_changes,
                              "file_sha256": sha, "compensation_changes": block_changes}
    if not result["changed"] and not save:
        return result
    what = f"{len(diff)} changed parameters" + (" and the compensation block" if block_changes else "")
    action = (f"upload {what}" if result["changed"] else "save the live set (unchanged)") + (
        " and save them to non-volatile memory" if result["changed"] and save else "")
    shown = format_diff(diff) + ("\ncompensation block: the file's replaces the controller's" if block_changes else "")
    prompt = f"{shown}\n\n{action} on {params_client.endpoint}?"
    if not yes and not confirm(prompt):
        declined = UploadDeclined(f"{action} on {params_client.endpoint}: declined by the operator; nothing written")
        declined.record = _local_record(params_client, "refused", f"UploadDeclined: {declined}", sha)
        records.record_upload(declined.record, operator, machine=machine, station=station)
        raise declined
    try:
        record = (params_client.upload(new, save=save, compensation=block if block_changes else None)
                  if result["changed"] else params_client.save())
    except ParamsError as err:
        err.record = err.record or _local_record(params_client, "failed", f"{type(err).__name__}: {err}", sha)
        records.record_upload(err.record, operator, machine=machine, station=station)
        raise
    records.record_upload(record, operator, machine=machine, station=station)
    result["record"] = record.model_dump()
    return result


LAST_CHANGES = 500
"""How many of the newest runs and stand-alone uploads ``last_change`` looks through."""


def last_change(records: Records, device: str) -> UploadRecord | None:
    """The newest upload or rollback of ``device`` (an UploadRecord's ``device``) that wrote anything and kept the
    set before it: committed or rolled back, or failed after some writes (its old set was what the device held)."""
    found: list[tuple[str, dict[str, Any]]] = []
    for entry in records.history(LAST_CHANGES, include_standalone=True):
        for row in entry.get("uploads", []) if entry.get("kind") == "run" else [entry]:
            rec = row.get("record") or {}
            wrote = rec.get("outcome") in ("committed", "rolled_back") or (
                rec.get("outcome") == "failed" and any(w.get("ok") for w in rec.get("writes", [])))
            if rec.get("device") == device and rec.get("previous_params") and wrote and \
                    rec.get("operation") in ("upload", "rollback"):
                found.append((rec.get("started_at") or row.get("time") or "", rec))
    if not found:
        return None
    return UploadRecord.model_validate(max(found, key=lambda pair: pair[0])[1])


def rollback_controller(params_client: ParameterInterface, records: Records, operator: str, *,
                        machine: str | None = None, station: str | None = None) -> dict[str, Any]:
    """Undo the last commit: a controller with a backup bank swaps live and backup; one without (CANopen) gets the
    set before its last upload or rollback back (``last_change``). Recorded whatever the outcome.

    Returns the UploadRecord dump; the driver's ParamsError (with ``err.record``) on refusal or failure.
    """
    try:
        last = None
        if not params_client.has_backup:
            device_key = getattr(params_client, "device_key", None)
            if device_key is not None:
                last = last_change(records, device_key(params_client.read_identity()))
        record = params_client.rollback(last)
    except ParamsError as err:
        err.record = err.record or _local_record(params_client, "failed", f"{type(err).__name__}: {err}",
                                                 operation="rollback")
        records.record_upload(err.record, operator, machine=machine, station=station)
        raise
    records.record_upload(record, operator, machine=machine, station=station)
    return record.model_dump()

